"""Simulated pen: a physical model of the pen-type touch sensor stroked over a texture.

The pen is a rigid rod held in the fingers, a pressure-conductive rubber sensor at its tip and a
6-axis IMU on its side. A simulated user strokes it back and forth over a surface. The model
(``docs/simulator.md`` gives the equations in words) has four parts:

1. **Hand motion** -- minimum-jerk strokes along the world X axis with reversals, dwells, pauses
   and lifts; pen tilt, lean and wrist roll that rock with the stroke and wander slowly; tremor.
2. **Contact** -- the user's push reaches the tip through the surface's compliance (a second-order
   system and a viscoelastic creep per texture); the hand's jitter and the long features the tip
   rides over press through the arm and the surface in series; a spatial roughness profile
   ``h(x)`` read at the tip's position gives a force ripple whose temporal frequency is
   ``speed / wavelength``; friction (Coulomb, slope of the profile, stick-slip below a
   texture-specific speed) bends the rod in the grip, and stick-slip chatter loads the tip
   sensor along the tilted rod.
3. **Rigid-body kinematics** -- the IMU's position and orientation give its specific force
   (gravity included, ~1 g) and body angular rate.
4. **Sensors** -- MEMS noise and bias (the one pen's offsets, plus turn-on repeatability),
   quantisation to int16 counts, saturation at +/-2 g, +/-250 deg/s and the 12-bit pressure
   ADC (0..4095).

Streaming is chunk-invariant: samples are produced in internal blocks of :data:`BLOCK` samples,
whatever the caller asks for, and every random draw and filter state lives in the object.
Slow processes (force wander, tilt wander, tremor) are sums of sinusoids of the absolute sample
time, so they need no state at all.

World frame: X along the stroke, Y to the side, Z up. IMU (body) frame: x along the rod towards
the hand, z normal to the rod's side face the IMU is glued to, y = z cross x.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tactile.device.info import (
    ACCEL_SCALE,
    GYRO_SCALE,
    PEN_CHANNELS,
    PEN_RATE_HZ,
    PRESSURE_SCALE,
    DeviceInfo,
    pen_info,
)
from tactile.errors import ConfigError, TactileError

TEXTURES: tuple[str, ...] = (
    "desk",
    "cardboard",
    "nonwoven_cloth",
    "paper",
    "plastic_folder",
    "mouse_pad",
    "non_contact",
)

GRAIN_MM = 2.0  # mm: features shorter than this are felt one by one as grain
BLOCK = 128  # samples per internal block; fixed so that output never depends on read sizes
G0 = 9.80665  # m/s^2 per g

# --- the pen itself (fixed by its construction, not by the user) ---------------------------
IMU_FROM_TIP = 0.04  # m along the rod from the tip to the IMU
IMU_RADIUS = 0.006  # m from the rod's axis to the IMU (the rod is ~10 mm thick, IMU on its side)
GRIP_LEVER = 0.08  # m from the tip to where the fingers hold the rod
TIP_STIFFNESS = 3.0e4  # N/m, the rubber tip sensor compressed axially (a few mm of soft rubber)
MOVING_MASS = 0.025  # kg, the rod plus the finger pads that move with it at contact rates
ROD_INERTIA = 3.0e-4  # kg*m^2, rod plus finger pads rotating about the grip
FRICTION_V0 = 0.004  # m/s, speed over which Coulomb friction changes sign (regularisation)

# --- sensors (MPU-6050 class IMU with a ~44 Hz digital low-pass; 12-bit ADC on the tip) -----
ACCEL_NOISE_G = 400e-6 * math.sqrt(44.0)  # 400 ug/sqrt(Hz) over 44 Hz -> ~2.7 mg RMS
GYRO_NOISE_DPS = 0.005 * math.sqrt(44.0)  # 0.005 dps/sqrt(Hz) over 44 Hz -> ~0.033 dps RMS
ACCEL_BIAS_G = 0.02  # RMS zero-g offset per axis after factory trim
GYRO_BIAS_DPS = 1.0  # RMS zero-rate offset per axis
# The offsets above belong to the pen (one pen, drawn once from PEN_SERIAL); from one session to
# the next they only move by their turn-on repeatability and temperature drift.
PEN_SERIAL = 20190601
ACCEL_BIAS_REPEAT_G = 0.003
GYRO_BIAS_REPEAT_DPS = 0.1
# No anti-alias filter in front of either sensor: an MPU-6050 left at its default digital
# low-pass (~260 Hz) and an ADC reading the tip's divider directly see the contact at an instant
# (~2 ms), so texture vibration above 50 Hz folds into the 100 Hz samples.
SENSOR_APERTURE_S = 1.0 / (2 * 260.0)
PRESSURE_NOISE_COUNTS = 0.8  # ADC plus divider noise, counts RMS
PRESSURE_OFFSET_COUNTS = 3.0  # upper bound of the unloaded sensor's reading, counts
ADC_MAX = 4095
INT16_MIN, INT16_MAX = -32768, 32767


@dataclass(frozen=True)
class TextureParams:
    """What the tip feels on one surface (see ``_TEXTURE_TABLE`` for where numbers come from).

    ``roughness_um``/``corr_mm``: RMS height (um) and correlation length (mm) of the random
    part of the height profile; ``period_mm``/``period_um``: wavelength and amplitude of a
    periodic part (0 = none); ``patch_mm``: contact patch radius, which smooths features shorter
    than it; ``mu_kinetic``/``mu_static``: friction of the rubber tip on it; ``stick_speed``:
    m/s below which the contact sticks and slips; ``mu_variation``: RMS
    variation of the friction coefficient along the path; ``grain``: RMS normal-force ripple
    per newton of push from single asperities and fibres (what the rubber sensor feels most
    directly); ``stiffness``: N/m of the surface layer under
    the tip; ``damping``: damping ratio of the tip-on-surface contact; ``creep_s``: time
    constant of the layer's viscoelastic creep (foam, fibre pile): the push builds up at the tip
    this much later, and faster push changes (tremor, push/pull steps) are smoothed.
    """

    roughness_um: float
    corr_mm: float
    period_mm: float
    period_um: float
    patch_mm: float
    mu_kinetic: float
    mu_static: float
    stick_speed: float
    mu_variation: float
    grain: float
    stiffness: float
    damping: float
    creep_s: float

    @property
    def contact_stiffness(self) -> float:
        """N/m of the tip and the surface in series."""
        return 1.0 / (1.0 / TIP_STIFFNESS + 1.0 / self.stiffness)

    @property
    def contact_hz(self) -> float:
        """Natural frequency of the moving mass on the contact stiffness (Hz)."""
        return math.sqrt(self.contact_stiffness / MOVING_MASS) / (2.0 * math.pi)


# Where the numbers come from (order-of-magnitude physics, then tuned so that IMU figures fall
# in the range of real hand-held stick recordings, see bench/sim_vs_hapmat.py):
# - roughness: a pen tip only feels features larger than its contact patch (~0.3-1 mm for a
#   rubber tip, larger on soft surfaces where it sinks in). Laminate desks and PP folders are
#   smooth (Ra ~0.5-2 um at mm scale); copy paper ~3-5 um with ~0.1-0.3 mm fibre flocs;
#   corrugated cardboard has flutes of 6-8 mm pitch (B/C flute) under the liner, tens of um
#   deep; non-woven cloth is fuzzy (tens of um, ~1 mm fibre clumps); a mouse pad has a fine
#   weave (~0.5 mm) on foam.
# - friction: rubber is grippy on smooth, clean plastics (mu ~0.7-1, squeaks: stick-slip),
#   less on paper/wood (~0.4-0.6); fabrics snag the tip (high static friction at low speed).
# - stiffness: the surface layer under the tip: a desk and a folder on it are rigid compared
#   with the rubber tip (>= 1e5 N/m); paper and cardboard liners compress a little; a 3 mm
#   foam mouse pad or a ~1 mm non-woven cloth is ~2-4e3 N/m (so the contact bandwidth drops
#   to ~45-60 Hz). Damping: foams and fibres dissipate (zeta 0.5-0.8), hard stacks ring.
#   Foam and fibre pile also creep: the force builds up over tens of ms (creep_s), paper and
#   cardboard liners a little, desk and folder not at all.
# - friction sets how far the drag bends the rod in the grip (a tilt offset flipping with the
#   stroke); its contrast between textures (0.3 on a waxed desk to ~0.9 for rubber snagging on
#   fabric or foam) is one of the main cues that survives between people.
_TEXTURE_TABLE: dict[str, TextureParams] = {
    "desk": TextureParams(
        roughness_um=1.5,
        corr_mm=0.5,
        period_mm=0.0,
        period_um=0.0,
        patch_mm=0.2,
        mu_kinetic=0.3,
        mu_static=0.4,
        stick_speed=0.005,
        mu_variation=0.02,
        grain=0.004,
        stiffness=3e5,
        damping=0.15,
        creep_s=0.0,
    ),
    "cardboard": TextureParams(
        roughness_um=12.0,
        corr_mm=0.4,
        period_mm=7.0,
        period_um=80.0,
        patch_mm=0.3,
        mu_kinetic=0.55,
        mu_static=0.65,
        stick_speed=0.01,
        mu_variation=0.05,
        grain=0.07,
        stiffness=1.5e4,
        damping=0.35,
        creep_s=0.01,
    ),
    "nonwoven_cloth": TextureParams(
        roughness_um=80.0,
        corr_mm=0.6,
        period_mm=0.0,
        period_um=0.0,
        patch_mm=0.3,
        mu_kinetic=0.9,
        mu_static=1.2,
        stick_speed=0.05,
        mu_variation=0.15,
        grain=0.25,
        stiffness=3e3,
        damping=0.6,
        creep_s=0.04,
    ),
    "paper": TextureParams(
        roughness_um=6.0,
        corr_mm=0.25,
        period_mm=0.0,
        period_um=0.0,
        patch_mm=0.2,
        mu_kinetic=0.6,
        mu_static=0.7,
        stick_speed=0.008,
        mu_variation=0.03,
        grain=0.06,
        stiffness=8e4,
        damping=0.25,
        creep_s=0.003,
    ),
    "plastic_folder": TextureParams(
        roughness_um=0.6,
        corr_mm=0.6,
        period_mm=0.0,
        period_um=0.0,
        patch_mm=0.2,
        mu_kinetic=0.7,
        mu_static=1.1,
        stick_speed=0.1,
        mu_variation=0.015,
        grain=0.006,
        stiffness=1.5e5,
        damping=0.12,
        creep_s=0.0,
    ),
    "mouse_pad": TextureParams(
        roughness_um=20.0,
        corr_mm=0.5,
        period_mm=0.5,
        period_um=10.0,
        patch_mm=0.3,
        mu_kinetic=0.9,
        mu_static=1.1,
        stick_speed=0.025,
        mu_variation=0.06,
        grain=0.12,
        stiffness=2e3,
        damping=0.75,
        creep_s=0.06,
    ),
}


def texture_params(texture: str) -> TextureParams | None:
    """The contact parameters of ``texture``; ``None`` for ``non_contact``."""
    _check_texture(texture)
    return _TEXTURE_TABLE.get(texture)


def _check_texture(texture: str) -> None:
    if texture not in TEXTURES:
        raise ConfigError(f"unknown texture {texture!r}: expected one of {', '.join(TEXTURES)}")


# ------------------------------------------------------------------------------------------
# The user session
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Session:
    """How one person holds and moves the pen during one take (all units SI unless named).

    speed: mean stroke speed, m/s (0.05..0.11 in random sessions); speed_jitter: per-stroke
    log-normal sigma; stroke_length: m, tip travel per stroke; force: mean push on the tip, N;
    force_wander: relative RMS of the slow force variation; push_bias: relative extra force when
    stroking towards +X (people press differently pushing and pulling); tilt_deg: pen tilt from
    vertical in the stroke plane; lean_deg: sideways lean; roll_deg: rotation of the IMU about
    the rod; rock_rad_per_m / twist_rad_per_m: pitch and roll change per metre of stroke travel
    (wrist rocking); swing_rad_per_m: yaw per metre (strokes driven by the wrist swing the pen
    about the vertical); tremor_dps: RMS physiological tremor as angular rate, deg/s; tremor_hz:
    its centre frequency; grip_stiffness: N*m/rad of the fingers resisting rod rotation; grip_hz
    and grip_damping: resonance of the rod rocking in the grip; hand_stiffness: N/m of the arm
    behind the push; pause_rate: pauses per second; lift_prob: chance a stroke is in the air.
    """

    speed: float = 0.08
    speed_jitter: float = 0.25
    stroke_length: float = 0.05
    force: float = 1.5
    force_wander: float = 0.12
    push_bias: float = 0.05
    tilt_deg: float = 25.0
    lean_deg: float = 0.0
    roll_deg: float = 0.0
    rock_rad_per_m: float = 2.0
    twist_rad_per_m: float = 0.5
    swing_rad_per_m: float = 1.0
    tremor_dps: float = 1.0
    tremor_hz: float = 9.0
    grip_stiffness: float = 6.0
    grip_hz: float = 20.0
    grip_damping: float = 0.25
    hand_stiffness: float = 1000.0
    pause_rate: float = 0.04
    lift_prob: float = 0.03

    def __post_init__(self) -> None:
        positive = (
            "speed",
            "stroke_length",
            "force",
            "tremor_hz",
            "grip_stiffness",
            "grip_hz",
            "grip_damping",
            "hand_stiffness",
        )
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ConfigError(f"session {name}={value!r}: must be a finite number > 0")
        non_negative = ("speed_jitter", "force_wander", "tremor_dps", "pause_rate", "lift_prob")
        for name in non_negative:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ConfigError(f"session {name}={value!r}: must be a finite number >= 0")
        if self.lift_prob > 1:
            raise ConfigError(f"session lift_prob={self.lift_prob!r}: must be in [0, 1]")

    @classmethod
    def random(cls, rng: np.random.Generator) -> Session:
        """A plausible person: independent draws over what differs between people.

        Ranges are what people plausibly do, not the widest a model can take: stroke speed
        varies ~2x (5-11 cm/s) and push 2.5x (1-2.5 N); the pen is held 20-45 deg from
        vertical (45-70 deg from the surface) with the IMU's side up within +/-10 deg (the
        pen's grip orients it); the wrist rocks the pen the same way for everyone (drawing the
        tip towards the palm stands the pen up), 1.5-3 rad/m; tremor 0.5-1.2 deg/s. The grip
        is light (1.5-3 N m/rad) and well damped (finger pads, zeta 0.4-0.6), so the drag of
        the surface shows as a tilt offset that flips with the stroke.
        """

        def logu(lo: float, hi: float) -> float:  # log-uniform: as many slow as fast users
            return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))

        return cls(
            speed=logu(0.05, 0.11),
            speed_jitter=float(rng.uniform(0.1, 0.25)),
            stroke_length=logu(0.03, 0.07),
            force=logu(1.0, 2.5),
            force_wander=float(rng.uniform(0.04, 0.1)),
            push_bias=float(rng.uniform(-0.08, 0.08)),
            tilt_deg=float(rng.uniform(20.0, 45.0)),
            lean_deg=float(rng.uniform(-5.0, 5.0)),
            roll_deg=float(rng.uniform(-10.0, 10.0)),
            rock_rad_per_m=-logu(1.5, 3.0),
            twist_rad_per_m=float(rng.uniform(-0.5, 0.5)),
            swing_rad_per_m=float(rng.uniform(-1.0, 1.0)),
            tremor_dps=logu(0.5, 1.2),
            tremor_hz=float(rng.uniform(8.0, 11.0)),
            grip_stiffness=logu(1.5, 3.0),
            grip_hz=float(rng.uniform(16.0, 24.0)),
            grip_damping=float(rng.uniform(0.4, 0.6)),
            hand_stiffness=logu(700.0, 1400.0),
            pause_rate=float(rng.uniform(0.0, 0.05)),
            lift_prob=float(rng.uniform(0.0, 0.03)),
        )


# ------------------------------------------------------------------------------------------
# Building blocks: slow processes, filters, the surface
# ------------------------------------------------------------------------------------------


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


# ------------------------------------------------------------------------------------------
# The simulator
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _TipForces:
    """What happens at the tip in one block, each (n,): ``normal`` force (N, what the pressure
    sensor reads), slow ``tangential`` friction (N), rod angular acceleration ``alpha``
    (rad/s^2) and rate ``omega`` (rad/s) from texture vibration, tip height ``z`` (m)."""

    normal: np.ndarray
    tangential: np.ndarray
    alpha: np.ndarray
    omega: np.ndarray
    z: np.ndarray


class PenSimulator:
    """A simulated pen: ``read(n)`` returns the next ``n`` raw samples, shape (n, 8) int16.

    Channels in :data:`tactile.device.info.PEN_CHANNELS` order: pressure twice (one sensor, as
    the real pen sends), accel x y z, gyro x y z. Deterministic given ``seed`` (and ``session``),
    and independent of how the stream is chunked.
    """

    def __init__(
        self,
        texture: str,
        seed: int = 0,
        rate_hz: float = PEN_RATE_HZ,
        session: Session | None = None,
    ) -> None:
        _check_texture(texture)
        if isinstance(rate_hz, bool) or not isinstance(rate_hz, (int, float)):
            raise ConfigError(f"rate_hz {rate_hz!r}: must be a number")
        if not (math.isfinite(rate_hz) and 10.0 <= rate_hz <= 10000.0):
            raise ConfigError(f"rate_hz {rate_hz!r}: must be in [10, 10000]")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ConfigError(f"seed {seed!r}: must be an integer >= 0")
        if session is not None and not isinstance(session, Session):
            raise ConfigError(f"session {session!r}: must be a Session or None")
        try:
            self.info: DeviceInfo = pen_info(float(rate_hz))
        except TactileError as exc:
            raise ConfigError(str(exc)) from exc
        self.texture = texture
        self.seed = int(seed)
        self.rate_hz = float(rate_hz)
        seeds = np.random.SeedSequence(self.seed).spawn(4)
        self._seeds = seeds
        self.session = (
            session if session is not None else Session.random(np.random.default_rng(seeds[0]))
        )
        self.params = texture_params(texture)
        self.reset()

    # -- public --------------------------------------------------------------------------

    def read(self, n: int) -> np.ndarray:
        """The next ``n`` samples, (n, 8) int16 raw counts, continuing the stream."""
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ConfigError(f"n {n!r}: must be an integer >= 0")
        n = int(n)
        parts = [self._buffer]
        have = len(self._buffer)
        while have < n:
            block = self._block()
            parts.append(block)
            have += len(block)
        data = np.concatenate(parts) if len(parts) > 1 else self._buffer
        out, self._buffer = data[:n], data[n:]
        self.n_read += n
        return out

    def reset(self) -> None:
        """Back to sample 0: the same seed gives the same stream again."""
        fs = self.rate_hz
        ses = self.session
        p = self.params
        plan_rng = np.random.default_rng(self._seeds[1])
        static_rng = np.random.default_rng(self._seeds[2])
        self._noise_rng = np.random.default_rng(self._seeds[3])
        self._planner = _Planner(ses, plan_rng, fs, in_contact=p is not None)
        self._surface = _Surface(p, static_rng) if p is not None else None
        # Slow and tremor processes (rad, or relative for force).
        tremor_rad = math.radians(ses.tremor_dps) / (2 * math.pi * ses.tremor_hz)
        f_lo, f_hi = ses.tremor_hz / 1.2, ses.tremor_hz * 1.2
        self._force_wander = _Wander(static_rng, ses.force_wander, 0.05, 1.0)
        self._pitch_wander = _Wander(static_rng, math.radians(3.0), 0.03, 0.5)
        self._lean_wander = _Wander(static_rng, math.radians(2.0), 0.03, 0.5)
        self._yaw_wander = _Wander(static_rng, math.radians(4.0), 0.02, 0.3)
        self._roll_wander = _Wander(static_rng, math.radians(3.0), 0.03, 0.5)
        self._y_wander = _Wander(static_rng, 0.2 * ses.stroke_length, 0.02, 0.3)
        self._tremor = [_Wander(static_rng, tremor_rad, f_lo, f_hi, 8) for _ in range(3)]
        self._tremor_gain = _Wander(static_rng, 0.4, 0.1, 0.5)  # tremor waxes and wanes
        # Sensor offsets: those of the one pen every session uses (drawn once, from a fixed
        # seed), plus what changes from power-up to power-up and with temperature.
        pen_rng = np.random.default_rng(PEN_SERIAL)
        self._accel_bias = pen_rng.normal(0.0, ACCEL_BIAS_G, 3) + static_rng.normal(
            0.0, ACCEL_BIAS_REPEAT_G, 3
        )
        self._gyro_bias = pen_rng.normal(0.0, GYRO_BIAS_DPS, 3) + static_rng.normal(
            0.0, GYRO_BIAS_REPEAT_DPS, 3
        )
        self._pressure_offset = pen_rng.uniform(0.0, PRESSURE_OFFSET_COUNTS)
        # Filters: tip on surface (user's push, roughness) and rod rocking in the grip.
        if p is not None:
            contact_lp = _second_order_kernel(p.contact_hz, p.damping, fs, False)
            creep = _first_order_kernel(p.creep_s, fs)
            self._push_lp = _Fir(np.convolve(contact_lp, creep))
        grip = _second_order_kernel(ses.grip_hz, ses.grip_damping, fs, False)
        self._grip_lp = _Fir(grip)
        # Carried kinematic state: previous tip position, IMU positions, orientation.
        self._s_prev: float | None = None
        self._p_prev: np.ndarray | None = None  # (2, 3) IMU positions at k-2, k-1
        self._r_prev: np.ndarray | None = None  # (3, 3)
        self._slip_phase = 0.0  # stick-slip cycles, fractional part
        self._k = 0  # index of the next sample to generate
        self._buffer = np.zeros((0, len(PEN_CHANNELS)), np.int16)
        self.n_read = 0

    # -- one block ------------------------------------------------------------------------

    def _block(self) -> np.ndarray:
        """Generate the next :data:`BLOCK` samples, (BLOCK, 8) int16."""
        fs, n = self.rate_hz, BLOCK
        t = (self._k + np.arange(n)) / fs  # (n,) s
        self._k += n
        s, contact = self._planner.take(n)
        s_prev = s[0] if self._s_prev is None else self._s_prev
        v = np.diff(np.concatenate([[s_prev], s])) * fs  # (n,) m/s, tip speed along X
        tip = self._contact(t, s, s_prev, v, contact)
        rates, specific_force, _ = self._rigid_body(t, s, tip)
        self._s_prev = float(s[-1])
        return self._sensors(tip.normal, specific_force, rates)

    def _contact(
        self, t: np.ndarray, s: np.ndarray, s_prev: float, v: np.ndarray, contact: np.ndarray
    ) -> _TipForces:
        """Forces at the tip for one block (see :class:`_TipForces`)."""
        ses, p = self.session, self.params
        tremor_z = GRIP_LEVER * self._tremor[0](t)  # m, hand's vertical jitter from tremor
        push = ses.force * (1 + self._force_wander(t) + ses.push_bias * np.tanh(v / 0.02))
        zeros = np.zeros_like(t)
        if p is None:  # non_contact: nothing touches, the tip is in the air
            return _TipForces(zeros, zeros, zeros, zeros, zeros + 0.002)
        seen, du, du_int, dslope = self._surface.read(s, v, SENSOR_APERTURE_S, p.contact_hz)
        # The hand holds its height on these time scales, so its jitter and the long features
        # the tip rides over (height seen minus the part not followed: cardboard flutes, cloth
        # clumps) press through the arm and the surface layer in series: a soft layer takes up
        # part of them.
        k_series = 1.0 / (1.0 / ses.hand_stiffness + 1.0 / p.stiffness)
        push = np.maximum(push + k_series * (tremor_z + seen - du), 0.0) * contact
        steady = self._push_lp(push)  # the push, slowed by the surface's compliance (N)
        # Fibres, weave and fillers make the friction coefficient itself vary along the path;
        # it follows the same profile (normalised), scaled by the texture's mu_variation. The
        # rod's rotation in the grip cannot follow faster than the grip's resonance, so what
        # bends it is the friction averaged over each sample's travel (not the instant value,
        # which would alias texture far above the resonance into it).
        srf = self._surface
        mean_h = srf.mean(srf.h, srf.h1, s, np.abs(v) / self.rate_hz)
        mu_local = p.mu_kinetic + p.mu_variation * mean_h / srf.rms
        grain = self._surface.grain(s, v, seen)
        # Normal force ripple: the roughness the moving mass cannot follow compresses the
        # contact, and single asperities/fibres load the rubber tip one by one (grain).
        ripple = (p.contact_stiffness * du + p.grain * steady * grain) * contact  # N
        # Its time integral drives the rod's rotation rate. Grain is left out: its single
        # asperity kicks are short (well above the grip's resonance), so the fingers absorb the
        # rotation they would cause; it still shows in the pressure and the acceleration.
        ripple_int = p.contact_stiffness * du_int * contact  # N*s
        slip = self._stick_slip(s, s_prev, v, steady)
        # Stick-slip jerks the tip along the surface; the tilted rod turns part of each jerk
        # into a load along its axis, so the chatter shows in the pressure as well.
        tilt = math.radians(ses.tilt_deg)
        chatter = -math.sin(tilt) * steady * slip * contact
        normal = np.maximum(steady + ripple + chatter, 0.0)
        direction = np.tanh(v / FRICTION_V0)  # friction opposes motion; smooth through v = 0
        tangential = steady * (mu_local * direction + slip)  # N, friction as sampled
        # Fast forces rock the rod about the grip: the normal ripple acts on a lever arm
        # L sin(tilt), the friction ripple (mu on the normal ripple, plus the tip climbing the
        # short slopes) on L cos(tilt).
        moving = np.abs(v) > 1e-4
        climb_int = np.where(moving, du / np.where(moving, v, 1.0), 0.0)  # int of slope dt
        fast_t = p.mu_kinetic * direction * ripple + steady * dslope * contact
        fast_t_int = p.mu_kinetic * direction * ripple_int + steady * climb_int * contact
        arm_n, arm_t = GRIP_LEVER * math.sin(tilt), GRIP_LEVER * math.cos(tilt)
        alpha = (arm_n * ripple + arm_t * fast_t) / ROD_INERTIA  # rad/s^2
        omega = (arm_n * ripple_int + arm_t * fast_t_int) / ROD_INERTIA  # rad/s
        z_tip = -steady / p.stiffness  # soft surfaces: the tip sinks in as you push
        return _TipForces(normal, tangential, alpha, omega, z_tip)

    def _stick_slip(
        self, s: np.ndarray, s_prev: float, v: np.ndarray, normal: np.ndarray
    ) -> np.ndarray:
        """Extra friction coefficient from stick-slip (n,), a sawtooth in travelled distance.

        While stuck, the grip's compliance loads up to ``(mu_s - mu_k) N`` and then slips: one
        cycle per ``2 (mu_s - mu_k) N / k_t`` of travel, ``k_t`` the grip's stiffness seen at the
        tip. It fades out above ``stick_speed`` (velocity-strengthening at speed). The sawtooth
        is averaged over each sample analytically, so high slip rates do not alias.
        """
        p, ses = self.params, self.session
        dmu = p.mu_static - p.mu_kinetic
        k_t = ses.grip_stiffness / GRIP_LEVER**2  # N/m at the tip
        cycle = np.maximum(2 * dmu * normal / k_t, 1e-5)  # m of travel per stick-slip cycle
        active = np.clip(1.0 - np.abs(v) / p.stick_speed, 0.0, 1.0) * (normal > 0)
        travel = np.abs(np.diff(np.concatenate([[s_prev], s])))
        phase = self._slip_phase + np.concatenate([[0.0], np.cumsum(active * travel / cycle)])
        self._slip_phase = float(phase[-1] % 1.0)

        def ramp_integral(x: np.ndarray) -> np.ndarray:  # integral of frac(x)
            return 0.5 * np.floor(x) + 0.5 * (x - np.floor(x)) ** 2

        step = np.diff(phase)
        moving = step > 1e-6
        mean_saw = np.where(
            moving, np.diff(ramp_integral(phase)) / np.where(moving, step, 1.0), phase[1:] % 1.0
        )
        return dmu * (2.0 * mean_saw - 1.0) * active * np.sign(v)

    def _rigid_body(
        self, t: np.ndarray, s: np.ndarray, tip: _TipForces
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Body angular rate (n, 3) rad/s, specific force (n, 3) in g (IMU frame) and the rod's
        pitch from vertical (n,) rad."""
        ses, fs = self.session, self.rate_hz
        # Slow friction bends the rod in the grip: a torque lever * F_t against the grip's
        # stiffness, through the rocking resonance (this is what rings at reversals).
        bend = self._grip_lp(GRIP_LEVER * tip.tangential / ses.grip_stiffness)  # rad
        gain = 1.0 + self._tremor_gain(t)
        pitch = (
            math.radians(ses.tilt_deg)
            + ses.rock_rad_per_m * s
            + self._pitch_wander(t)
            + gain * self._tremor[1](t)
            + bend
        )
        lean = math.radians(ses.lean_deg) + self._lean_wander(t) + gain * self._tremor[2](t)
        yaw = ses.swing_rad_per_m * s + self._yaw_wander(t)
        roll = math.radians(ses.roll_deg) + ses.twist_rad_per_m * s + self._roll_wander(t)
        rot = _orientation(pitch, lean, yaw, roll)  # (n, 3, 3) body -> world
        tip_pos = np.stack([s, self._y_wander(t), tip.z], axis=1)  # (n, 3) m
        imu = tip_pos + IMU_FROM_TIP * rot[:, :, 0] + IMU_RADIUS * rot[:, :, 2]  # (n, 3) m
        r_prev = rot[0] if self._r_prev is None else self._r_prev
        p_prev = np.stack([imu[0], imu[0]]) if self._p_prev is None else self._p_prev
        # Body rate from consecutive orientations: R_{k-1}^T R_k ~ I + [w]x dt.
        rel = np.concatenate([r_prev[None], rot[:-1]]).transpose(0, 2, 1) @ rot
        rates = (
            0.5
            * fs
            * np.stack(
                [
                    rel[:, 2, 1] - rel[:, 1, 2],
                    rel[:, 0, 2] - rel[:, 2, 0],
                    rel[:, 1, 0] - rel[:, 0, 1],
                ],
                axis=1,
            )
        )
        pos = np.concatenate([p_prev, imu])  # (n+2, 3)
        accel = (pos[2:] - 2 * pos[1:-1] + pos[:-2]) * fs * fs  # (n, 3) m/s^2, world
        accel[:, 2] += G0  # an accelerometer measures a - g: +1 g up at rest
        # Texture vibration, sampled at the instant (it aliases, as on the real pen): rotation
        # about world Y around the grip, which sits up the rod from the IMU.
        y_axis = np.array([0.0, 1.0, 0.0])
        from_grip = -(GRIP_LEVER - IMU_FROM_TIP) * rot[:, :, 0]  # (n, 3) m, grip -> IMU
        accel += tip.alpha[:, None] * np.cross(y_axis, from_grip)
        rates += tip.omega[:, None] * rot[:, 1, :]  # world Y in body coordinates = R^T e_Y
        specific = np.einsum("nji,nj->ni", rot, accel) / G0  # world -> body
        self._r_prev, self._p_prev = rot[-1], pos[-2:]
        return rates, specific, pitch

    def _sensors(self, force: np.ndarray, specific: np.ndarray, rates: np.ndarray) -> np.ndarray:
        """Noise, bias, quantisation and saturation: (n, 8) int16 raw counts."""
        rng, n = self._noise_rng, len(force)
        pressure = (
            force / PRESSURE_SCALE
            + self._pressure_offset
            + rng.normal(0.0, PRESSURE_NOISE_COUNTS, n)
        )
        accel = specific + self._accel_bias + rng.normal(0.0, ACCEL_NOISE_G, (n, 3))
        gyro = np.degrees(rates) + self._gyro_bias + rng.normal(0.0, GYRO_NOISE_DPS, (n, 3))
        out = np.empty((n, 8), np.int16)
        out[:, 0] = out[:, 1] = np.clip(np.rint(pressure), 0, ADC_MAX)
        out[:, 2:5] = np.clip(np.rint(accel / ACCEL_SCALE), INT16_MIN, INT16_MAX)
        out[:, 5:8] = np.clip(np.rint(gyro / GYRO_SCALE), INT16_MIN, INT16_MAX)
        return out


def simulate(
    texture: str, seconds: float, seed: int = 0, rate_hz: float = PEN_RATE_HZ
) -> np.ndarray:
    """``round(seconds * rate_hz)`` samples of ``texture`` from a fresh simulator, (n, 8) int16."""
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)):
        raise ConfigError(f"seconds {seconds!r}: must be a number")
    if not (math.isfinite(seconds) and seconds >= 0):
        raise ConfigError(f"seconds {seconds!r}: must be finite and >= 0")
    sim = PenSimulator(texture, seed=seed, rate_hz=rate_hz)
    return sim.read(int(round(seconds * sim.rate_hz)))
