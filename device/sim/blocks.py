"""The simulator's building blocks: slow random processes, FIR filters, the surface's height
profile under the tip, the stroke planner, and rotations.

Each holds its own random draws and filter state, so that :class:`~tactile.device.sim.
simulator.PenSimulator` streams the same samples whatever size its reads are.
"""

from __future__ import annotations

import math

import numpy as np

from tactile.device.sim.session import Session
from tactile.device.sim.textures import TextureParams

GRAIN_MM = 2.0  # mm: features shorter than this are felt one by one as grain


class _Wander:
    """A smooth random process as a sum of sinusoids of absolute time (stateless, exact)."""

    def __init__(
        self, rng: np.random.Generator, rms: float, f_lo: float, f_hi: float, n: int = 6
    ) -> None:
        self.freqs = np.exp(rng.uniform(math.log(f_lo), math.log(f_hi), n))  # (n,) Hz
        self.phases = rng.uniform(0.0, 2 * math.pi, n)
        self.amps = np.full(n, rms * math.sqrt(2.0 / n))  # sum of n sines has RMS `rms`

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """Values at times ``t`` (s), shape like ``t``."""
        arg = 2 * math.pi * t[:, None] * self.freqs + self.phases  # (T, n)
        return np.sin(arg) @ self.amps


def _second_order_kernel(f_hz: float, zeta: float, fs: float, base_excited: bool) -> np.ndarray:
    """FIR of ``H(s) = (b1 s + w^2) / (s^2 + 2 zeta w s + w^2)``, unit DC gain.

    ``b1 = 2 zeta w`` (``base_excited``: a mass on a spring-damper whose base moves) or 0 (a
    plain low-pass). Discretised with a first-order hold (input linear between samples), so a
    system much faster than the sample rate becomes an identity rather than a one-sample delay.
    Returns ``(taps,)`` with ``y[n] = sum_j k[j] x[n-j]``.
    """
    w = 2 * math.pi * f_hz
    if abs(zeta - 1.0) < 1e-3:  # the partial fractions below need distinct poles
        zeta = 1.0 + 1e-3
    root = w * np.sqrt(complex(zeta * zeta - 1.0))
    p1, p2 = -zeta * w + root, -zeta * w - root
    b1 = 2 * zeta * w if base_excited else 0.0
    r1, r2 = (b1 * p1 + w * w) / (p1 - p2), (b1 * p2 + w * w) / (p2 - p1)
    dt = 1.0 / fs
    decay = 1.0 / (zeta * w) if zeta < 1 else 1.0 / abs(p1.real)  # slowest time constant, s
    taps = int(min(max(8, math.ceil(6 * decay * fs) + 2), 512))
    sub = 32  # sub-steps per sample for the hold integral
    tau = (np.arange(taps * sub) + 0.5) * (dt / sub)  # (taps*sub,) s
    h = np.real(r1 * np.exp(p1 * tau) + r2 * np.exp(p2 * tau)) * (dt / sub)
    u = tau / dt
    j = np.floor(u).astype(int)
    frac = u - j
    kernel = np.bincount(j, h * (1 - frac), taps + 1) + np.bincount(j + 1, h * frac, taps + 1)
    kernel = kernel[:taps]
    return kernel / kernel.sum()


def _first_order_kernel(tau_s: float, fs: float) -> np.ndarray:
    """FIR of a first-order lag ``1 / (tau s + 1)`` (unit DC gain, input held over each sample);
    ``[1.0]`` for ``tau_s`` = 0."""
    if tau_s <= 0:
        return np.ones(1)
    taps = int(min(max(2, math.ceil(6 * tau_s * fs) + 1), 512))
    edges = np.exp(-np.arange(taps + 1) / (tau_s * fs))
    kernel = edges[:-1] - edges[1:]  # step response increments: exact for a held input
    return kernel / kernel.sum()


class _Fir:
    """A causal FIR filter that keeps its input history between blocks."""

    def __init__(self, kernel: np.ndarray) -> None:
        self.kernel = kernel
        self.history = np.zeros(len(kernel) - 1)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Filter ``x`` (n,), continuing from the previous call."""
        xx = np.concatenate([self.history, x])
        self.history = xx[len(xx) - len(self.history) :]
        return np.convolve(xx, self.kernel, mode="valid")


class _Surface:
    """A periodic 1-D height profile ``h(x)`` (m) read at the tip's position along the stroke.

    Built by spectral synthesis: a self-affine random part (spectrum flat up to ``1/corr`` and
    falling as ``k^-3.6`` beyond), a periodic part, both smoothed by the contact patch. Its first
    and second running integrals are kept too, so that box averages of ``h`` and of its integral
    over any stretch of path are exact differences (no sampling of the fine profile in time).
    """

    LENGTH = 0.4096  # m, long enough that strokes do not visibly repeat
    DX = 2.5e-5  # m grid step (25 um), finer than any feature the tip resolves

    def __init__(self, p: TextureParams, rng: np.random.Generator) -> None:
        n = int(round(self.LENGTH / self.DX))
        k = 2 * math.pi * np.fft.rfftfreq(n, self.DX)  # rad/m, (n//2+1,)
        amp = (1.0 + (k * p.corr_mm * 1e-3) ** 2) ** -0.9  # spectral amplitude, Hurst ~0.8
        amp[0] = 0.0
        h = np.fft.irfft(amp * np.exp(1j * rng.uniform(0, 2 * math.pi, len(k))), n)
        h *= p.roughness_um * 1e-6 / np.sqrt(np.mean(h**2))
        if p.period_mm > 0:
            cycles = max(1, round(self.LENGTH / (p.period_mm * 1e-3)))  # keep it periodic
            phase = 2 * math.pi * cycles * np.arange(n) / n + rng.uniform(0, 2 * math.pi)
            h += p.period_um * 1e-6 * np.sin(phase)
        # The contact patch averages features shorter than itself away (first-order roll-off:
        # a soft rubber tip still feels single fibres and edges, only weaker).
        h = np.fft.irfft(np.fft.rfft(h) / (1.0 + (k * p.patch_mm * 1e-3) ** 2), n)
        self.x = np.arange(n + 1) * self.DX  # (n+1,) grid including the period's end
        self.h = self._periodic(h - h.mean())
        self.h1 = self._integral(self.h)  # m^2, running integral of h (zero mean)
        self.h2 = self._integral(self.h1)  # m^3, running integral of h1
        self.offset = rng.uniform(0, self.LENGTH)
        self.rms = float(np.sqrt(np.mean(self.h**2)))  # m, of the whole profile

    def _periodic(self, y: np.ndarray) -> np.ndarray:
        return np.append(y, y[0])

    def _integral(self, y: np.ndarray) -> np.ndarray:
        """Zero-mean, exactly periodic running integral of the periodic ``y`` (n+1,)."""
        c = np.concatenate([[0.0], np.cumsum((y[1:] + y[:-1]) * 0.5 * self.DX)])
        c -= self.x / self.LENGTH * c[-1]  # remove the (rounding-level) drift over one period
        return self._periodic(c[:-1] - c[:-1].mean())

    def _at(self, table: np.ndarray, x: np.ndarray) -> np.ndarray:
        return np.interp(np.mod(x + self.offset, self.LENGTH), self.x, table)

    def mean(
        self, table: np.ndarray, upper: np.ndarray, x: np.ndarray, width: np.ndarray
    ) -> np.ndarray:
        """Average of the profile ``table`` over ``[x - width/2, x + width/2]``, (n,).

        ``upper`` is the running integral of ``table``; where ``width`` is below the grid step
        the point value is returned.
        """
        wide = width > self.DX
        w = np.where(wide, width, 1.0)
        boxed = (self._at(upper, x + w / 2) - self._at(upper, x - w / 2)) / w
        return np.where(wide, boxed, self._at(table, x))

    def read(
        self, x: np.ndarray, v: np.ndarray, aperture_s: float, follow_hz: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What the tip feels at positions ``x`` (n,) m moving at ``v`` (n,) m/s.

        The sensor integrates over ``aperture_s`` (its own bandwidth; much shorter than a
        sample period, so texture vibration aliases as on a real 100 Hz pen). The moving mass
        follows features longer than ~``|v| / follow_hz``; shorter ones compress the contact.
        Returns ``(seen, du, du_int, dslope)``: the height under the tip (m), the contact
        compression from roughness (m), its time integral (m*s), and the surface slope under the
        tip beyond what the moving mass follows (m/m), each (n,).
        """
        travel = np.abs(v) * aperture_s
        follow = 0.44 * np.abs(v) / follow_hz  # box length whose half-power wavelength ~ v/f
        seen = self.mean(self.h, self.h1, x, travel)
        du = seen - self.mean(self.h, self.h1, x, follow)
        # integral over time of du = integral over path / v (the tip moves at v)
        du_path = self._at(self.h1, x) - self.mean(self.h1, self.h2, x, follow)
        moving = np.abs(v) > 1e-4
        du_int = np.where(moving, du_path / np.where(moving, v, 1.0), 0.0)  # dt = dx / v
        half = np.maximum(travel, self.DX) / 2
        slope = (self._at(self.h, x + half) - self._at(self.h, x - half)) / (2 * half)
        far = np.maximum(follow, 4 * self.DX) / 2
        slope_follow = (self._at(self.h, x + far) - self._at(self.h, x - far)) / (2 * far)
        return seen, du, du_int, slope - slope_follow

    def grain(self, x: np.ndarray, v: np.ndarray, seen: np.ndarray) -> np.ndarray:
        """Unit-RMS texture grain under the tip, (n,).

        The height ``seen`` (from :meth:`read`) minus its mean over :data:`GRAIN_MM`, divided
        by the profile's RMS: the asperities and fibres the tip rides over one by one.
        """
        width = np.full_like(x, GRAIN_MM * 1e-3)
        return (seen - self.mean(self.h, self.h1, x, width)) / self.rms


# ------------------------------------------------------------------------------------------
# The stroke planner
# ------------------------------------------------------------------------------------------


class _Planner:
    """The hand's path along the stroke axis: ``s`` (m) and tip contact (0..1) per sample.

    Strokes are minimum-jerk moves (smooth start and stop, so the pen decelerates, stops and
    reverses) between turning points around a wandering centre; after each a short dwell,
    sometimes a pause; some strokes are lifts (the tip leaves the surface mid-stroke).
    """

    def __init__(
        self, session: Session, rng: np.random.Generator, fs: float, in_contact: bool
    ) -> None:
        self.session, self.rng, self.fs, self.in_contact = session, rng, fs, in_contact
        self.s = 0.0
        self.centre = 0.0
        self.direction = 1.0 if rng.random() < 0.5 else -1.0
        self.pending_s = np.zeros(0)
        self.pending_c = np.zeros(0)

    def take(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The next ``n`` samples: ``(s (n,) m, contact (n,) in 0..1)``."""
        while len(self.pending_s) < n:
            s, c = self._next_segment()
            self.pending_s = np.concatenate([self.pending_s, s])
            self.pending_c = np.concatenate([self.pending_c, c])
        s, self.pending_s = self.pending_s[:n], self.pending_s[n:]
        c, self.pending_c = self.pending_c[:n], self.pending_c[n:]
        return s, c

    def _next_segment(self) -> tuple[np.ndarray, np.ndarray]:
        ses, rng, fs = self.session, self.rng, self.fs
        length = ses.stroke_length * math.exp(rng.normal(0.0, 0.25))
        # The centre wanders but is pulled back: the hand stays over the same patch.
        self.centre = 0.7 * self.centre + rng.normal(0.0, 0.2 * ses.stroke_length)
        target = self.centre + self.direction * length / 2
        speed = ses.speed * math.exp(rng.normal(0.0, ses.speed_jitter))
        duration = abs(target - self.s) / speed
        n = int(np.clip(round(duration * fs), max(3, round(0.12 * fs)), round(4.0 * fs)))
        tau = np.arange(1, n + 1) / n
        s = self.s + (target - self.s) * (10 * tau**3 - 15 * tau**4 + 6 * tau**5)
        contact = np.ones(n)
        if rng.random() < ses.lift_prob:
            contact = 1.0 - np.sin(math.pi * tau) ** 0.5  # up in the middle, ramps at the ends
            contact[contact < 0.05] = 0.0
        dwell = int(rng.integers(0, max(1, round(0.05 * fs)) + 1))  # reversal: stop 0..50 ms
        if rng.random() < ses.pause_rate * duration:
            dwell += int(rng.uniform(0.3, 1.5) * fs)
        s = np.concatenate([s, np.full(dwell, target)])
        contact = np.concatenate([contact, np.full(dwell, contact[-1])])
        self.s = target
        self.direction = -self.direction
        if not self.in_contact:
            contact[:] = 0.0
        return s, contact


# ------------------------------------------------------------------------------------------
# Rotations
# ------------------------------------------------------------------------------------------

# Body -> world when all angles are zero: rod vertical, IMU x up the rod, IMU z facing -X.
_R0 = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])


def _rot(axis: int, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) about a coordinate axis (0=x, 1=y, 2=z) by ``angle`` rad."""
    c, s = np.cos(angle), np.sin(angle)
    r = np.zeros((len(angle), 3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r[:, axis, axis] = 1.0
    r[:, i, i], r[:, j, j] = c, c
    r[:, i, j], r[:, j, i] = -s, s
    return r


def _orientation(
    pitch: np.ndarray, lean: np.ndarray, yaw: np.ndarray, roll: np.ndarray
) -> np.ndarray:
    """Body-to-world rotations (n, 3, 3): yaw about Z, pitch about Y, lean about X, roll about
    the rod."""
    return _rot(2, yaw) @ _rot(1, pitch) @ _rot(0, lean) @ _R0 @ _rot(0, roll)
