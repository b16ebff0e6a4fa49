"""How one simulated person holds and moves the pen during one take (:class:`Session`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tactile.errors import ConfigError


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

    The defaults are one person inside the ranges :meth:`random` draws from.
    """

    speed: float = 0.08
    speed_jitter: float = 0.2
    stroke_length: float = 0.05
    force: float = 1.5
    force_wander: float = 0.07
    push_bias: float = 0.05
    tilt_deg: float = 25.0
    lean_deg: float = 0.0
    roll_deg: float = 0.0
    rock_rad_per_m: float = -2.0
    twist_rad_per_m: float = 0.25
    swing_rad_per_m: float = 0.5
    tremor_dps: float = 1.0
    tremor_hz: float = 9.0
    grip_stiffness: float = 2.1
    grip_hz: float = 20.0
    grip_damping: float = 0.5
    hand_stiffness: float = 1000.0
    pause_rate: float = 0.04
    lift_prob: float = 0.02

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


__all__ = ["Session"]
