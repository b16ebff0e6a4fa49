"""The per-stream object: samples in, one label per window out.

A :class:`Stream` holds one pen's ring buffer and LSTM state, and optionally its labels'
:class:`~tactile.postprocess.smoothing.PostProcessor`, reset with the state; the model object it
calls is stateless and may be shared by many streams. Four verbs: :meth:`Stream.accept` samples,
:meth:`Stream.ready`, :meth:`Stream.classify`, :meth:`Stream.reset` (plus :meth:`Stream.gap`
when samples were lost). The serial loop is a few lines over it, and tests drive it with arrays.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from tactile.errors import ConfigError, ModelContractError, TactileError
from tactile.postprocess.smoothing import PostProcessor, Smoothed

# (window (1, T, C) float32, h, c) -> (probabilities (1, K), h, c)
ClassifyFn = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray,
                                                                   np.ndarray]]


@dataclass(frozen=True)
class Label:
    """The result for one window."""

    seq: int  # sequence number of the window's last sample
    t_us: int  # device time of the window's last sample
    label: str
    probability: float
    probabilities: dict[str, float]
    latency_ms: float  # wall time of this window's model call (preprocessing + model)
    # the post-processor's result (averaged label, stability, change event), when there is one
    smoothed: Smoothed | None = None

    def to_dict(self) -> dict:
        """The JSON object of one window: the raw fields (``t`` s, ``seq``, ``label``, ``p``,
        ``probs``, ``latency_ms``), and with a post-processor ``smoothed`` {``label``, ``p``},
        ``stable`` and, on the first window after a reset, ``reset`` (its reason)."""
        d = {
            "t": self.t_us / 1e6,
            "seq": self.seq,
            "label": self.label,
            "p": round(self.probability, 6),
            "probs": {k: round(v, 6) for k, v in self.probabilities.items()},
            "latency_ms": round(self.latency_ms, 3),
        }
        if self.smoothed is not None:
            d["smoothed"] = {"label": self.smoothed.label, "p": round(self.smoothed.p, 6)}
            d["stable"] = self.smoothed.stable
            if self.smoothed.reset is not None:
                d["reset"] = self.smoothed.reset
        return d


class InvalidWindow(TactileError):
    """The model's output for a window is not finite (the window's values are past what the
    model can take): the window has no label; the state and the post-processor's average were
    reset (the next window's ``smoothed.reset`` is ``"invalid"``), and the next window starts
    after this one. ``seq`` and ``t_us`` are the window's last sample's."""

    def __init__(self, seq: int, t_us: int) -> None:
        super().__init__(f"window ending at seq {seq}: the model's output is not finite (its "
                         "values are past what the model can take); no label")
        self.seq, self.t_us = seq, t_us


class Stream:
    """Ring buffer + state for one pen.

    Args:
        classify: the model's function (see :data:`ClassifyFn`).
        classes: class names, in the model's output order.
        window, hop: samples per window and between windows.
        channels: channels per sample.
        carry: carry the LSTM state from window to window (else a zero state per window).
        state_shape: (layers, hidden) of the state tensors.
        post: optional :class:`~tactile.postprocess.smoothing.PostProcessor` (for ``classes``, in
            that order) fed with every window; its result is the label's ``smoothed``. It is
            reset with the LSTM state (:meth:`reset`, :meth:`gap`).
        rate_hz: the pen's sample rate, which times the samples of an :meth:`accept` call
            after its first (else each call must give ``period_us``).

    :meth:`for_model` takes all of these from a model's contract.
    """

    def __init__(
        self,
        classify: ClassifyFn,
        classes: tuple[str, ...],
        window: int,
        hop: int,
        channels: int,
        carry: bool,
        state_shape: tuple[int, int],
        post: PostProcessor | None = None,
        rate_hz: float | None = None,
    ) -> None:
        if not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool)
                   for v in (window, hop)):
            raise ConfigError(f"window {window!r} and hop {hop!r} must be whole numbers of "
                              "samples")
        if window < 1 or hop < 1:
            raise ConfigError(f"window {window} and hop {hop} must be >= 1")
        if carry and hop != window:
            raise ConfigError(
                f"the model carries its state between windows, so hop must equal the window "
                f"({window}); got hop {hop}"
            )
        self._classify = classify
        self.classes = classes
        self.window, self.hop, self.channels = window, hop, channels
        self.carry = carry
        self.state_shape = state_shape
        if post is not None and tuple(post.classes) != tuple(classes):
            raise ConfigError(f"post-processor classes {list(post.classes)} are not the "
                              f"stream's {list(classes)} (names and order)")
        self.post = post
        self._reason: str | None = None  # why the state was last reset, until the next window
        if rate_hz is not None and not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ConfigError(f"rate_hz {rate_hz}: must be a finite number > 0")
        self.period_us = None if rate_hz is None else 1e6 / rate_hz
        self._clear()

    @classmethod
    def for_model(cls, model, hop: int | None = None,
                  post: PostProcessor | None = None) -> Stream:
        """A stream for a :class:`~tactile.runtime.model.Model`: window, hop (unless given),
        channels, state mode and sample rate from its contract."""
        c = model.contract
        return cls(model.classify, c.classes, c.window, c.hop if hop is None else hop,
                   len(c.channels), c.state_mode == "carry", model.state_shape, post,
                   rate_hz=c.sample_rate_hz)

    def reset(self, reason: str = "reset") -> None:
        """Forget the buffered samples, the state and the post-processor's average (after a gap,
        a restart, a reconnection or on request). The next window's ``smoothed.reset`` is
        ``reason`` (``"gap"``, ``"restart"``, ``"reconnect"``, ...): the first one given since
        the last window, which names the cause when one fault brings several resets (a
        reconnection, then the restarted pen's gap)."""
        self._clear()
        self._restart_average(reason)

    def _restart_average(self, reason: str) -> None:
        """The post-processor starts afresh; the next window's ``smoothed.reset`` names the
        first ``reason`` since the last window."""
        if self._reason is None:
            self._reason = reason
        if self.post is not None:
            self.post.reset(self._reason)

    def _clear(self) -> None:
        """Empty buffer, zero state (the post-processor is :meth:`reset`'s business)."""
        self._buf = np.zeros((0, self.channels), np.float32)  # samples from index _base on
        self._seq = np.zeros(0, np.int64)
        self._t = np.zeros(0, np.int64)
        self._base = 0  # index (since reset) of _buf[0]
        self._next_end = self.window  # index one past the next window's last sample
        self._last_seq: int | None = None  # the next accept must continue from it
        self._last_window_t: int | None = None  # t_us of the last window since the reset
        layers, hidden = self.state_shape
        self.h = np.zeros((layers, 1, hidden), np.float32)
        self.c = np.zeros((layers, 1, hidden), np.float32)

    def gap(self, reason: str = "gap") -> None:
        """Samples were lost: no window may span the gap, and a carried state is void."""
        self.reset(reason)

    def accept(self, values: np.ndarray, seq: int, t_us: int,
               period_us: float | None = None) -> None:
        """Append samples (n, channels) in the channels' units; ``seq``/``t_us`` of the first,
        the others ``period_us`` apart (by default the stream's ``rate_hz``). ``seq`` must
        continue the previous call's (after lost samples call :meth:`gap` first), and every
        value must be a finite number: a :class:`ConfigError` says which rule was broken."""
        values = np.asarray(values, dtype=np.float32)
        if values.ndim != 2 or values.shape[1] != self.channels:
            raise ConfigError(f"samples of shape {values.shape}: expected (n, {self.channels})")
        n = len(values)
        if self._last_seq is not None and seq != self._last_seq + 1:
            raise ConfigError(f"seq {seq} does not follow {self._last_seq}: call gap() after "
                              "lost samples, reset() to start over")
        if not np.isfinite(values).all():
            raise ConfigError("samples with NaN or inf values (a window must be all numbers)")
        if period_us is None:
            period_us = self.period_us
        if period_us is None:
            if n > 1:
                raise ConfigError(f"{n} samples in one call need period_us (or the stream's "
                                  "rate_hz) to time all but the first")
            period_us = 0.0
        self._buf = np.concatenate([self._buf, values])
        self._seq = np.concatenate([self._seq, seq + np.arange(n)])
        self._t = np.concatenate([self._t, t_us + np.round(np.arange(n) * period_us)
                                  .astype(np.int64)])
        self._last_seq = seq + n - 1
        self._trim()

    def _trim(self) -> None:
        """Drop the samples no window needs any more (with a hop longer than the window, those
        between windows too, also when they arrive after the previous window was made)."""
        drop = min(self._next_end - self.window - self._base, len(self._buf))
        if drop > 0:
            self._buf, self._seq, self._t = self._buf[drop:], self._seq[drop:], self._t[drop:]
            self._base += drop

    def ready(self) -> bool:
        """True while a window is due: its last sample has arrived."""
        return self._base + len(self._buf) >= self._next_end

    def classify(self) -> Label:
        """Run the model on the oldest due window and return its label (windows come in order);
        :class:`InvalidWindow` when the model's output for it is not finite."""
        if not self.ready():
            raise ConfigError("no window is ready")
        end = self._next_end - self._base
        x = self._buf[end - self.window : end][None]  # (1, T, C)
        last_seq, last_t = int(self._seq[end - 1]), int(self._t[end - 1])
        if not self.carry:
            self.h = np.zeros_like(self.h)
            self.c = np.zeros_like(self.c)
        t0 = time.perf_counter()
        probs, h, c = self._classify(x, self.h, self.c)
        latency = (time.perf_counter() - t0) * 1e3
        want = (1, len(self.classes))
        if np.shape(probs) != want or np.shape(h) != self.h.shape or np.shape(c) != self.c.shape:
            raise ModelContractError(
                f"the model returned probs {np.shape(probs)}, h {np.shape(h)}, c {np.shape(c)} "
                f"for one window; its contract declares probs {want} ({len(self.classes)} "
                f"classes), h and c {self.h.shape}")
        if not (np.isfinite(probs).all() and (not self.carry or (np.isfinite(h).all()
                                                                 and np.isfinite(c).all()))):
            # values the model cannot take (a device's 1e20: finite, but past what its
            # normalisation and LSTM hold): no label, and no state or average to carry it on;
            # the next window starts after this one (one overlapping it holds its values)
            self._next_end += max(self.window, self.hop)
            self._trim()
            self.h, self.c = np.zeros_like(self.h), np.zeros_like(self.c)
            self._restart_average("invalid")
            raise InvalidWindow(last_seq, last_t)
        self._next_end += self.hop
        self._trim()
        if self.carry:
            self.h, self.c = h, c
        p = probs[0]
        k = int(p.argmax())
        smoothed = None
        if self.post is not None:
            if self._last_window_t is not None and last_t < self._last_window_t:
                self.post.reset("clock")  # the device's time went back without a lost sample
            smoothed = self.post.update(p, last_t / 1e6, last_seq)
        self._last_window_t = last_t
        self._reason = None
        return Label(
            last_seq, last_t, self.classes[k], float(p[k]),
            {name: float(v) for name, v in zip(self.classes, p)}, latency, smoothed,
        )
