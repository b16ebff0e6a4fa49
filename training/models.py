"""Which model a config names: one registry from ``cfg.model`` to the code that builds it.

The pen's models (:class:`~tactile.training.model.TextureModel`: ``lstm``, ``linear`` on EMD
features) and the granular-media paper's (:class:`~tactile.training.granular.GranularModel`:
``sf_rnn``, ``f_rnn``, ``sparse_linear``, ``linear`` on modalities) are both built here, so
that neither module needs the other's builder (``granular`` builds on ``model``'s
:class:`~tactile.training.model.Classifier`, never the reverse).
"""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor

from tactile.errors import ConfigError
from tactile.training.config import TrainConfig
from tactile.training.granular import GranularModel
from tactile.training.modality import resolve, resolve_signals
from tactile.training.model import Classifier, TextureModel

Builder = Callable[..., Classifier]


def _texture(cfg: TrainConfig, n_classes: int, mean: Tensor, std: Tensor, *,
             channels: tuple[str, ...], rate_hz: float, emd_index: list[int] | None,
             center_index: list[int] | None,
             center_groups: list[list[int]] | None = None) -> Classifier:
    return TextureModel(cfg, n_classes, mean, std, list(emd_index or []), center_index,
                        signal_index(cfg, channels), center_groups)


def signal_index(cfg: TrainConfig, channels: tuple[str, ...]) -> list[list[int]] | None:
    """Per high-rate signal of ``cfg.signals`` the indices of its sub-sample channels in
    ``channels`` (time order); None without signals (or without channels to resolve them)."""
    if not (cfg.signals and channels):
        return None
    signals = resolve_signals(cfg.signals, tuple(channels))
    return [[channels.index(c) for c in names] for _, names in signals]


def _granular(cfg: TrainConfig, n_classes: int, mean: Tensor, std: Tensor, *,
              channels: tuple[str, ...], rate_hz: float, emd_index: list[int] | None,
              center_index: list[int] | None,
              center_groups: list[list[int]] | None = None) -> Classifier:
    return GranularModel(cfg, n_classes, resolve(cfg, tuple(channels), rate_hz), mean, std)


# (family, cfg.model) -> builder; the family is "granular" when the config has modalities
# (``linear`` is a model of both: on the pen's EMD features, or on modalities' energies)
MODELS: dict[tuple[str, str], Builder] = {
    ("pen", "lstm"): _texture,
    ("pen", "linear"): _texture,
    ("granular", "sf_rnn"): _granular,
    ("granular", "f_rnn"): _granular,
    ("granular", "sparse_linear"): _granular,
    ("granular", "linear"): _granular,
}


def family(cfg: TrainConfig) -> str:
    """``granular`` for a config with modalities, else ``pen``."""
    return "granular" if cfg.modalities else "pen"


def build_model(cfg: TrainConfig, n_classes: int, mean: Tensor, std: Tensor, *,
                channels: tuple[str, ...] = (), rate_hz: float = 100.0,
                emd_index: list[int] | None = None,
                center_index: list[int] | None = None,
                center_groups: list[list[int]] | None = None) -> Classifier:
    """The model ``cfg`` describes, untrained: a :class:`TextureModel` (the pen's models), or
    with ``cfg.modalities`` a :class:`~tactile.training.granular.GranularModel` whose
    modalities are resolved against ``channels`` (x's last axis, in order) at ``rate_hz``
    (``cfg.signals`` names the high-rate signals). ``mean``, ``std``: (C,) normalisation;
    ``emd_index``, ``center_index``: channel indices (the pen's models only);
    ``center_groups``: the signals centred whole (None: each signal with a centred sub-sample,
    as a new run has them; a checkpoint says which)."""
    builder = MODELS.get((family(cfg), cfg.model))
    if builder is None:  # TrainConfig refuses these combinations first
        raise ConfigError(f"model={cfg.model!r} is not a {family(cfg)} model")
    return builder(cfg, n_classes, mean, std, channels=channels, rate_hz=rate_hz,
                   emd_index=emd_index, center_index=center_index,
                   center_groups=center_groups)


__all__ = ["MODELS", "build_model", "family"]
