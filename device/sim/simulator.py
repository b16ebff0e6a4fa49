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

from tactile.device.protocol.info import (
    ACCEL_SCALE,
    GYRO_SCALE,
    PEN_CHANNELS,
    PEN_RATE_HZ,
    PRESSURE_SCALE,
    DeviceInfo,
    pen_info,
)
from tactile.device.sim.blocks import (
    _Fir,
    _first_order_kernel,
    _orientation,
    _Planner,
    _second_order_kernel,
    _Surface,
    _Wander,
)
from tactile.device.sim.pen import (
    ACCEL_BIAS_G,
    ACCEL_BIAS_REPEAT_G,
    ACCEL_NOISE_G,
    ADC_MAX,
    FRICTION_V0,
    G0,
    GRIP_LEVER,
    GYRO_BIAS_DPS,
    GYRO_BIAS_REPEAT_DPS,
    GYRO_NOISE_DPS,
    IMU_FROM_TIP,
    IMU_RADIUS,
    INT16_MAX,
    INT16_MIN,
    PEN_SERIAL,
    PRESSURE_NOISE_COUNTS,
    PRESSURE_OFFSET_COUNTS,
    ROD_INERTIA,
    SENSOR_APERTURE_S,
)
from tactile.device.sim.session import Session
from tactile.device.sim.textures import TEXTURES, TextureParams, _check_texture, texture_params
from tactile.errors import ConfigError, TactileError

BLOCK = 128  # samples per internal block; fixed so that output never depends on read sizes


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

    Channels in :data:`tactile.device.protocol.info.PEN_CHANNELS` order: pressure twice (one
    sensor, as the real pen sends), accel x y z, gyro x y z. Deterministic given ``seed`` (and
    ``session``), and independent of how the stream is chunked.
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


__all__ = ["BLOCK", "TEXTURES", "PenSimulator", "Session", "TextureParams", "simulate",
           "texture_params"]
