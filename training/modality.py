"""Modalities and high-rate signals, resolved once against the channel names of the input.

A **high-rate signal** is a named group of channels that hold consecutive sub-samples of one
signal per frame, in time order (the BioTac's ``f0_pac_00`` .. ``f0_pac_21``: one 2.2 kHz
signal at 100 frames/s); ``x (B, T, r)`` of its channels is the signal ``(B, T * r)`` by a
reshape. A **modality** is a named group of *units* (signals, and channels that belong to no
signal), all at one rate. :func:`resolve` turns the config's name patterns into index lists
(:class:`ModalityLayout`) that the preprocessing and the exported graph use; every mistake is
one :class:`~tactile.errors.ConfigError` line naming the bad value.
"""

from __future__ import annotations

import fnmatch
import math
from dataclasses import dataclass

from tactile.errors import ConfigError
from tactile.training.config import TrainConfig

Signals = tuple[tuple[str, tuple[str, ...]], ...]  # (name, exact channel names in time order)


@dataclass(frozen=True)
class ModalityLayout:
    """One modality of the input, resolved (one per ``[modalities.NAME]``, in config order).

    ``index``: channel indices into x's last axis, signal-major with each signal's sub-samples
    in time order; ``n`` signals or channels in the image (``n * r == len(index)``); ``r``
    sub-samples per frame (1 for plain channels); ``rate_hz``: device rate x r; ``units``: the
    names of the n signals or channels; ``signal``: whether they are high-rate signals.
    """

    name: str
    index: tuple[int, ...]
    n: int
    r: int
    rate_hz: float
    imfs: int
    steps: int
    atoms: int
    nonzero: int
    units: tuple[str, ...] = ()
    signal: bool = False

    @property
    def features(self) -> int:
        """Values in one step's data image: n x max(imfs, 1) x steps."""
        return self.n * max(self.imfs, 1) * self.steps

    @property
    def frames(self) -> int:
        """Frames one image spans: ceil(steps / r)."""
        return math.ceil(self.steps / self.r)


def n_steps(layout: tuple[ModalityLayout, ...], window: int) -> int:
    """Steps S of a window of ``window`` frames: ``T - max_m ceil(steps_m / r_m) + 1`` (steps
    whose image would start before the window are dropped)."""
    return window - max(m.frames for m in layout) + 1


def _unmatched(pattern: str, what: str, names: list[str]) -> ConfigError:
    shown = ", ".join(names[:12]) + (f", ... ({len(names)} in all)" if len(names) > 12 else "")
    return ConfigError(f"{what}: pattern {pattern!r} matches none of: {shown}")


def resolve_signals(patterns: Signals, channels: tuple[str, ...]) -> Signals:
    """``[signals]`` (name, channel name patterns) as exact channel names: the patterns'
    order, and the channels one pattern matches in the order of ``channels``. A run records its
    signals as exact names in time order, which this keeps whatever order ``channels`` (the
    model's) lists them in; training sorts a config's patterns' channels into recording order
    (:func:`recorded_order`). A pattern that matches nothing, a channel in two signals, or a
    signal named like a channel is a :class:`ConfigError`."""
    out, owner = [], {}
    for name, pats in patterns:
        if name in channels:
            raise ConfigError(f"signals.{name}: a channel has that name; name the signal "
                              "otherwise")
        picked: dict[int, None] = {}  # in the patterns' order, each channel once
        for p in pats:
            hit = [i for i, c in enumerate(channels) if fnmatch.fnmatchcase(c, p)]
            if not hit:
                raise _unmatched(p, f"signals.{name}", list(channels))
            picked.update(dict.fromkeys(hit))
        for i in picked:
            if channels[i] in owner:
                raise ConfigError(f"signals.{name}: channel {channels[i]!r} is already in "
                                  f"signal {owner[channels[i]]!r}")
            owner[channels[i]] = name
        out.append((name, tuple(channels[i] for i in picked)))
    return tuple(out)


def recorded_order(takes, channels: tuple[str, ...]) -> tuple[str, ...]:
    """``channels`` (a model's, in the order the user chose) in the takes' recording order:
    what a signal's patterns are resolved against, so that its sub-samples keep their time
    order whatever order ``channels`` lists them in."""
    chosen = set(channels)
    return tuple(c for c in takes[0].channels if c in chosen) if takes else channels


def partial_signals(takes, channels: tuple[str, ...]) -> list[str]:
    """The signals the takes declare of which ``channels`` hold some sub-samples but not all
    (read as plain channels at the device rate, not as the signal), each as ``name (k of n)``."""
    d = (takes[0].meta.get("signals") or {}) if takes else {}
    chosen = set(channels)
    return [f"{k} ({sum(c in chosen for c in v)} of {len(v)})" for k, v in d.items()
            if 0 < sum(c in chosen for c in v) < len(v)]


def signals_of_takes(takes, channels: tuple[str, ...]) -> Signals:
    """The high-rate signals the takes declare (their JSON's ``signals``), restricted to
    signals whose channels are all among ``channels``. Every take must declare the same;
    otherwise a :class:`ConfigError` names the first take that differs."""
    first = takes[0].declared_signals if takes else ()
    for t in takes[1:]:
        if t.declared_signals != first:
            raise ConfigError(f"{t.path.name}: declares signals {dict(t.declared_signals)} but "
                              f"{takes[0].path.name} declares {dict(first)}: the takes must "
                              "agree (or set [signals] in the config)")
    return tuple((k, v) for k, v in first if all(c in channels for c in v))


def resolve(cfg: TrainConfig, channels: tuple[str, ...], rate_hz: float,
            signals: Signals | None = None) -> tuple[ModalityLayout, ...]:
    """The config's modalities as index layouts over ``channels`` (x's last axis) at the device
    rate ``rate_hz``. ``signals``: the high-rate signals as exact channel names (default: the
    config's ``[signals]`` resolved against ``channels``).

    Each pattern of a modality matches units by name: signal names, and the names of channels
    that belong to no signal. Units are taken in recording order (a signal's place: its first
    channel). Raises :class:`ConfigError` (one line) for a pattern that matches nothing, a unit
    in two modalities, a modality mixing rates, or an image longer than the window."""
    if signals is None:
        signals = resolve_signals(cfg.signals, channels)
    members = {c for _, names in signals for c in names}
    units: dict[str, tuple[int, ...]] = {n: tuple(channels.index(c) for c in names)
                                         for n, names in signals}
    is_signal = set(units)
    units.update({c: (i,) for i, c in enumerate(channels) if c not in members})
    taken: dict[str, str] = {}
    out = []
    for m in cfg.modalities:
        where = f"modalities.{m.name}.channels"
        picked: set[str] = set()
        for p in m.channels:
            hit = {u for u in units if fnmatch.fnmatchcase(u, p)}
            if not hit:
                inside = [c for c in members if fnmatch.fnmatchcase(c, p)]
                if inside:
                    sig = next(n for n, names in signals if inside[0] in names)
                    raise ConfigError(f"{where}: pattern {p!r} matches only sub-samples of the "
                                      f"high-rate signal {sig!r}: name the signal")
                raise _unmatched(p, where, list(units))
            picked |= hit
        for u in sorted(picked):
            if u in taken:
                raise ConfigError(f"{where}: {u!r} is in modalities {taken[u]!r} and "
                                  f"{m.name!r}")
            taken[u] = m.name
        names = sorted(picked, key=lambda u: units[u][0])
        widths = {len(units[u]) for u in names}
        if len(widths) > 1 or (len({u in is_signal for u in names}) > 1):
            shown = ", ".join(f"{u} (x{len(units[u])})" for u in names)
            raise ConfigError(f"{where}: mixes rates ({shown}): one modality holds signals "
                              "of one rate, or plain channels")
        r = widths.pop()
        if m.steps > cfg.window * r:
            raise ConfigError(f"modalities.{m.name}.steps={m.steps}: longer than the window "
                              f"({cfg.window} frames x {r} = {cfg.window * r} samples at "
                              f"{rate_hz * r:g} Hz)")
        out.append(ModalityLayout(
            name=m.name, index=tuple(i for u in names for i in units[u]), n=len(names), r=r,
            rate_hz=float(rate_hz) * r, imfs=m.imfs, steps=m.steps, atoms=m.atoms,
            nonzero=m.nonzero, units=tuple(names), signal=names[0] in is_signal))
    return tuple(out)


def literal_signals(signals: Signals) -> Signals:
    """Exact channel names as patterns that match only themselves (``*``, ``?``, ``[`` in
    brackets): how a run's config records the signals it resolved."""
    def lit(name: str) -> str:
        return "".join(f"[{ch}]" if ch in "*?[" else ch for ch in name)

    return tuple((n, tuple(lit(c) for c in names)) for n, names in signals)


__all__ = ["ModalityLayout", "Signals", "resolve", "resolve_signals", "recorded_order",
           "partial_signals", "literal_signals", "signals_of_takes", "n_steps"]
