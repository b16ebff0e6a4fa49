"""Post-processing of one stream's labels: averaged probabilities, a stability rule, change events.

The model gives one probability vector per window, and its argmax (the raw label) flickers on a
stroke: 30 s of a simulated mouse pad gave 16 label changes on one unchanging surface. A
:class:`PostProcessor` per stream (one per pen, beside its :class:`~tactile.runtime.stream.Stream`)
averages the probabilities over the last windows, reports the leading class only once it is
confident and settled, and says when the reported surface changes:

    settings = SmoothingSettings(n=5, p_min=0.6, hold=2)
    post = PostProcessor(settings, model.contract.classes)
    out = post.update(probs, t=12.5, seq=1250)   # probs (classes,) of one window
    out.label, out.p, out.stable, out.event      # "paper", 0.83, True, None
    post.reset("gap")                            # wherever the stream's LSTM state is reset

The settings travel in the model file's ``metadata_props`` under the ``postprocess.`` prefix
(:func:`settings_to_metadata`, :func:`settings_from_metadata`); a file without those keys has no
post-processing defaults. numpy only: the runtime, the exporter and tactile-eval share it.
"""

from __future__ import annotations

import json
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from tactile.contract import KEYS as CONTRACT_KEYS
from tactile.contract import POSTPROCESS_PREFIX
from tactile.errors import ConfigError, ModelContractError

UNCERTAIN = "uncertain"
"""The label reported while no class is stable; reserved: no model may name a class so."""

PREFIX = POSTPROCESS_PREFIX
"""Prefix of every post-processing key in an ONNX file's ``metadata_props``."""
VERSION = "1"
"""Version of the ``postprocess.*`` keys' meaning, written as ``postprocess.version``."""
CALIBRATION_KEY = PREFIX + "calibration"
"""The optional key: the figures the calibration saw, as a JSON object."""
KEYS = tuple(k for k in CONTRACT_KEYS if k.startswith(PREFIX) and k != CALIBRATION_KEY)
"""The keys a file with post-processing defaults must hold (version, smooth, p_min, hold; all
defined in :data:`tactile.contract.KEYS`)."""


def check_classes(classes: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """``classes`` as a tuple; :class:`ConfigError` if one of them is the reserved
    :data:`UNCERTAIN` (a stream could not tell that class from "no stable label")."""
    if UNCERTAIN in classes:
        raise ConfigError(f"class name {UNCERTAIN!r} is reserved for the post-processor's "
                          "unsettled label: rename that class")
    return tuple(classes)


MAX_WINDOWS = 100_000
"""The most windows a moving average holds or a hold asks for (7 hours at the pen's 4 windows
a second): the average's memory is allocated from it."""


@dataclass(frozen=True)
class SmoothingSettings:
    """How one stream's probabilities are averaged and when a label counts as stable.

    Give one averaging: ``n`` (a moving average) or ``tau`` (an exponential one), not both;
    neither means n 1. ``SmoothingSettings()`` is the raw stream (n 1, p_min 0, hold 1: every
    window's argmax is stable). Checked when built: a bad value is a one-line
    :class:`ConfigError`.
    """

    # windows in the moving average of the class probabilities (1: no averaging); None with tau
    n: int | None = None
    # time constant of an exponential average, s (weight 1 - exp(-dt / tau) for a window dt s
    # after the previous one); None for the moving average
    tau: float | None = None
    # the leading class's averaged probability must be at least this (0..1) to be stable
    p_min: float = 0.0
    # ... and it must have led for at least this many consecutive windows (>= 1)
    hold: int = 1

    def __post_init__(self) -> None:
        if self.n is None and self.tau is None:
            object.__setattr__(self, "n", 1)  # frozen: set once, here
        if self.n is not None and self.tau is not None:
            raise ConfigError(f"smoothing n={self.n}, tau={self.tau}: give one of n (a moving "
                              "average over n windows) or tau (an exponential one, s)")
        if self.n is not None and not (_is_int(self.n) and 1 <= self.n <= MAX_WINDOWS):
            raise ConfigError(f"smoothing n {self.n!r}: must be an integer from 1 to "
                              f"{MAX_WINDOWS} (windows)")
        if self.tau is not None and not (_is_real(self.tau) and math.isfinite(self.tau)
                                         and self.tau > 0):
            raise ConfigError(f"smoothing tau {self.tau!r}: must be a finite number > 0 (s)")
        if not (_is_real(self.p_min) and 0.0 <= self.p_min <= 1.0):
            raise ConfigError(f"p_min {self.p_min!r}: must be a number from 0 to 1")
        if not (_is_int(self.hold) and 1 <= self.hold <= MAX_WINDOWS):
            raise ConfigError(f"hold {self.hold!r}: must be an integer from 1 to {MAX_WINDOWS} "
                              "(windows)")

    @property
    def smooth(self) -> str:
        """The averaging as written in metadata and options: ``ma:N`` or ``ema:TAU`` (s)."""
        return f"ma:{self.n}" if self.n is not None else f"ema:{self.tau!r}"

    def describe(self) -> str:
        """One line for people, e.g. ``ma:5 p_min=0.6 hold=2``."""
        return f"{self.smooth} p_min={self.p_min:g} hold={self.hold}"


def _is_int(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def _is_real(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)


def parse_smooth(text: str) -> dict:
    """``ma:N`` -> ``{"n": N, "tau": None}``, ``ema:TAU`` -> ``{"n": None, "tau": TAU}`` (s);
    anything else is a one-line :class:`ConfigError`."""
    kind, _, value = str(text).strip().partition(":")
    try:
        if kind == "ma":
            return {"n": int(value), "tau": None}
        if kind == "ema":
            return {"n": None, "tau": float(value)}
    except ValueError:
        pass
    raise ConfigError(f"smoothing {text!r}: expected ma:N (a moving average over N windows) or "
                      "ema:TAU (an exponential average, TAU in s)")


def make_settings(smooth: str = "ma:1", p_min: float = 0.0, hold: int = 1) -> SmoothingSettings:
    """Settings from an averaging string (:func:`parse_smooth`) and the two thresholds."""
    return SmoothingSettings(**parse_smooth(smooth), p_min=p_min, hold=hold)


def parse_smooth_option(text: str) -> dict:
    """The averaging as ``tactile-run --smooth`` takes it: ``N`` (a moving average over N
    windows), ``Ts`` (an exponential average with a time constant of T s, e.g. ``1.5s``), or the
    metadata's ``ma:N``/``ema:TAU``; -> ``{"n", "tau"}`` checked as :class:`SmoothingSettings`
    checks them. Anything else is a one-line :class:`ConfigError`."""
    t = str(text).strip()
    try:
        if t.isdigit():
            parsed = {"n": int(t), "tau": None}
        elif t.endswith("s") and ":" not in t:
            parsed = {"n": None, "tau": float(t[:-1])}
        else:
            parsed = parse_smooth(t)
    except (ValueError, ConfigError):
        raise ConfigError(f"{text!r}: expected N (a moving average over N windows) or Ts (an "
                          "exponential average with a time constant of T s, e.g. 1.5s)") from None
    SmoothingSettings(**parsed)  # n >= 1, tau > 0 and finite
    return parsed


def override(defaults: SmoothingSettings | None, smooth: str | None = None,
             p_min: float | None = None, hold: int | None = None) -> SmoothingSettings | None:
    """``defaults`` (a model's, None for a file without any) with the given values in place of
    its own: ``smooth`` as :func:`parse_smooth_option` reads it, ``p_min``, ``hold``. Nothing
    given: ``defaults`` as they are (None: no post-processing); a value given over no defaults
    starts from :class:`SmoothingSettings` () (the raw stream: ma:1, p_min 0, hold 1)."""
    if smooth is None and p_min is None and hold is None:
        return defaults
    base = defaults if defaults is not None else SmoothingSettings()
    averaging = parse_smooth_option(smooth) if smooth is not None else \
        {"n": base.n, "tau": base.tau}
    return SmoothingSettings(**averaging, p_min=base.p_min if p_min is None else p_min,
                             hold=base.hold if hold is None else hold)


@dataclass(frozen=True)
class Smoothed:
    """The post-processor's result for one window.

    ``label`` is the reported label: the leading class when it is stable, else
    :data:`UNCERTAIN`; ``leader`` and ``p`` are the class with the highest averaged probability
    (ties to the lowest class index, as ``numpy.argmax``) and that probability (0..1), whether
    stable or not. ``probs`` (classes,) are the averaged probabilities. ``event`` is None or
    ``{"event": "change", "from": ..., "to": ..., "t": ..., "seq": ...}`` (see
    :class:`PostProcessor`); ``reset`` is the reason given to the last :meth:`PostProcessor.reset`
    on the first window after it, else None.
    """

    label: str
    leader: str
    p: float
    stable: bool
    probs: np.ndarray
    event: dict | None
    reset: str | None

    def to_dict(self) -> dict:
        """The fields added beside the raw ones in a JSON line: ``smoothed`` {label, p},
        ``stable``, ``event``, and ``reset`` on the first window after a reset."""
        d = {"smoothed": {"label": self.label, "p": round(self.p, 6)}, "stable": self.stable,
             "event": self.event}
        if self.reset is not None:
            d["reset"] = self.reset
        return d


class PostProcessor:
    """Averaged probabilities, stable label and change events for one stream.

    For each window, :meth:`update` averages the class probabilities (a moving average of the
    last ``n`` windows since the last reset, or an exponential average with time constant
    ``tau`` s, seeded with the first window after a reset); the leader is their argmax (ties to
    the lowest class index). The leader is *stable* when its averaged probability is at least
    ``p_min`` and it has been the leader for at least ``hold`` consecutive windows (this one
    included); otherwise the reported label is :data:`UNCERTAIN`.

    A change event is emitted on a window whose stable label differs from the last one
    announced. Passing through uncertain is no event by itself: mouse_pad -> uncertain ->
    mouse_pad emits nothing, mouse_pad -> uncertain -> paper emits one event (from mouse_pad to
    paper) on the first stable paper window. The first stable label of a stream emits an event
    with ``from`` None.

    :meth:`reset` is called wherever the stream's LSTM state is reset (a gap, a restart, a
    reconnection); it forgets the average and the leader's run, so the label is uncertain until
    a leader is stable again, and the next result carries its reason. It keeps the last
    announced label: the stable label that forms after the reset is announced only if it
    differs (a link that drops now and then on one surface gives no change events; a pen put
    down on another surface during the gap gives one).
    """

    def __init__(self, settings: SmoothingSettings, classes: tuple[str, ...] | list[str]
                 ) -> None:
        if not isinstance(settings, SmoothingSettings):
            raise ConfigError(f"settings: a SmoothingSettings, not {type(settings).__name__}")
        self.settings = settings
        self.classes = check_classes(classes)
        if not self.classes:
            raise ConfigError("classes: at least one class name")
        self._history: deque[np.ndarray] = deque(maxlen=settings.n or 1)
        self._reason: str | None = None
        self._announced: str | None = None  # the last stable label announced by an event
        self.reset(None)

    def reset(self, reason: str | None = "reset") -> None:
        """Forget the average and the leader's run (not the last announced label); the next
        result's ``reset`` is ``reason`` (e.g. ``"gap"``, ``"restart"``, ``"reconnect"``)."""
        self._history.clear()
        self._ema: np.ndarray | None = None
        self._t: float | None = None  # time of the previous window, s
        self._leader: int | None = None
        self._run = 0  # consecutive windows the leader has led
        self._reason = reason

    def update(self, probs: np.ndarray, t: float, seq: int) -> Smoothed:
        """One window: ``probs`` (classes,) its class probabilities (0..1), ``t`` its time in s
        (the window's last sample, non-decreasing since the last reset), ``seq`` its sequence
        number (copied into an event). A wrong shape, a non-finite value or a time that goes
        back is a :class:`ConfigError`."""
        p = np.array(probs, np.float64).reshape(-1)
        if p.shape != (len(self.classes),):
            raise ConfigError(f"probabilities of shape {np.shape(probs)}: expected "
                              f"({len(self.classes)},)")
        if not np.isfinite(p).all():
            raise ConfigError(f"probabilities {np.round(p, 6).tolist()}: not all finite")
        if not math.isfinite(t) or (self._t is not None and t < self._t):
            raise ConfigError(f"window time {t} s is before the previous one ({self._t} s): "
                              "call reset() when the stream starts over")
        avg = self._average(p, t)
        self._t = t
        k = int(np.argmax(avg))
        self._run = self._run + 1 if k == self._leader else 1
        self._leader = k
        s = self.settings
        stable = bool(avg[k] >= s.p_min and self._run >= s.hold)
        event = None
        if stable and self.classes[k] != self._announced:
            event = {"event": "change", "from": self._announced, "to": self.classes[k], "t": t,
                     "seq": seq}
            self._announced = self.classes[k]
        reason, self._reason = self._reason, None
        return Smoothed(self.classes[k] if stable else UNCERTAIN, self.classes[k],
                        float(avg[k]), stable, avg, event, reason)

    def _average(self, p: np.ndarray, t: float) -> np.ndarray:
        """The averaged probabilities (classes,) including this window."""
        tau = self.settings.tau
        if tau is None:
            self._history.append(p)
            return np.mean(np.stack(self._history), axis=0)
        if self._ema is None:
            self._ema = p
        else:
            w = 1.0 - math.exp(-(t - self._t) / tau)  # a window dt s later weighs this much
            self._ema = self._ema + w * (p - self._ema)
        return self._ema

    def feed(self, label) -> Smoothed:
        """:meth:`update` from a runtime :class:`~tactile.runtime.stream.Label` (its
        ``probabilities`` in this post-processor's class order, ``t_us``, ``seq``)."""
        probs = np.array([label.probabilities[c] for c in self.classes])
        return self.update(probs, label.t_us / 1e6, label.seq)


def settings_to_metadata(settings: SmoothingSettings, figures: dict | None = None
                         ) -> dict[str, str]:
    """The ``metadata_props`` entries (string keys and values) for ``settings``:
    ``postprocess.version``, ``postprocess.smooth`` (``ma:N`` or ``ema:TAU``),
    ``postprocess.p_min``, ``postprocess.hold``, and, given ``figures`` (what the calibration
    saw, JSON-able), ``postprocess.calibration`` as a JSON object."""
    meta = {PREFIX + "version": VERSION, PREFIX + "smooth": settings.smooth,
            PREFIX + "p_min": repr(float(settings.p_min)), PREFIX + "hold": str(settings.hold)}
    if figures is not None:
        meta[CALIBRATION_KEY] = json.dumps(figures, sort_keys=True)
    return meta


def settings_from_metadata(meta: dict[str, str]) -> SmoothingSettings | None:
    """The post-processing defaults a model file carries, or None when it has no
    ``postprocess.*`` key (an older file: run it as before, without post-processing).

    A file with some of the keys but not all, an unknown ``postprocess.*`` key, another
    version or a bad value is a :class:`ModelContractError` naming the key."""
    ours = {k: v for k, v in meta.items() if k.startswith(PREFIX)}
    if not ours:
        return None
    unknown = sorted(set(ours) - set(KEYS) - {CALIBRATION_KEY})
    if unknown:
        raise ModelContractError(f"metadata key {unknown[0]!r}: not one this runtime knows "
                                 f"({', '.join(KEYS + (CALIBRATION_KEY,))})")
    for k in KEYS:
        if k not in ours:
            raise ModelContractError(f"metadata key {k!r} is missing (the file has other "
                                     f"{PREFIX}* keys)")
    if ours[PREFIX + "version"] != VERSION:
        raise ModelContractError(f"metadata key {PREFIX}version: "
                                 f"{ours[PREFIX + 'version']!r}, this runtime reads {VERSION!r}")
    def value(name: str, parse):
        key = PREFIX + name
        try:
            return parse(ours[key])
        except ConfigError as e:
            raise ModelContractError(f"metadata key {key}: {ours[key]!r} ({e})") from None
        except ValueError:  # int() or float() of text that is none
            raise ModelContractError(f"metadata key {key}: {ours[key]!r} is not "
                                     f"{'an integer' if name == 'hold' else 'a number'}"
                                     ) from None

    # each value checked on its own, so that the error names its key
    averaging = value("smooth", lambda v: SmoothingSettings(**parse_smooth(v)))
    p_min = value("p_min", lambda v: SmoothingSettings(p_min=float(v)).p_min)
    hold = value("hold", lambda v: SmoothingSettings(hold=int(v)).hold)
    return SmoothingSettings(averaging.n, averaging.tau, p_min, hold)


def figures_from_metadata(meta: dict[str, str]) -> dict | None:
    """The calibration's figures (``postprocess.calibration``), or None when absent; a value
    that is not a JSON object is a :class:`ModelContractError`."""
    text = meta.get(CALIBRATION_KEY)
    if text is None:
        return None
    try:
        figures = json.loads(text)
    except json.JSONDecodeError:
        figures = None
    if not isinstance(figures, dict):
        raise ModelContractError(f"metadata key {CALIBRATION_KEY}: not a JSON object")
    return figures


__all__ = [
    "CALIBRATION_KEY", "KEYS", "PREFIX", "UNCERTAIN", "VERSION", "PostProcessor", "Smoothed",
    "SmoothingSettings", "check_classes", "figures_from_metadata", "make_settings", "override",
    "parse_smooth", "parse_smooth_option", "settings_from_metadata", "settings_to_metadata",
]
