"""The simulated pen's hardware: the rod, the tip sensor and the IMU, as fixed numbers.

These belong to the pen (its construction and its sensors' data sheets), not to the user or
the texture; :mod:`~tactile.device.sim.simulator` and the textures' contact figures
(:class:`~tactile.device.sim.textures.TextureParams`) read them.
"""

from __future__ import annotations

import math

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
