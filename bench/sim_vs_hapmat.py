"""Compare the simulated pen's IMU statistics with real hand-held stick recordings (HapMat).

HapMat (``shared/datasets/hapmat/``) is a 6-axis IMU on a rigid stick swiped over 5 materials
at 100 Hz. It has no pressure channel, its accelerometer has gravity removed (user acceleration
in g) and its rotation rate is in rad/s. To compare like with like, this script:

- converts the simulator's raw counts to g and rad/s (``PEN_CHANNELS`` scales, deg -> rad);
- removes gravity from the simulator's accelerometer with a complementary filter (the gravity
  direction in the IMU frame is propagated with the gyro and pulled towards the accelerometer
  with a 1 s time constant) -- what a phone's "linear acceleration" output does;
- removes each channel's mean from both sources (HapMat's gyro has small offsets too).

Figures per source: per-channel RMS of accel (g) and gyro (rad/s); spectral centroid (Hz) and
the fraction of power in 0-2, 2-10 and 10-50 Hz, of accel and of gyro (Welch, axes summed);
stroke reversals per second (zero crossings, with hysteresis, of the 3 Hz low-passed gyro
projected on its principal axis: the rod rocks with the stroke, so its rate changes sign at
each reversal). The verdict says whether each simulated figure falls inside the range of the
5 real materials, widened by a factor 1.5 for magnitudes (``[min / 1.5, max * 1.5]``) and by
0.1 absolute for band fractions. It prints; it asserts nothing.

Usage: python bench/sim_vs_hapmat.py [--hapmat PATH] [--sessions 5] [--seconds 60]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from tactile.device.protocol import PEN_CHANNELS, PEN_RATE_HZ
from tactile.device.sim import TEXTURES, simulate

DEFAULT_HAPMAT = (
    Path(__file__).resolve().parents[2] / "shared" / "datasets" / "hapmat" / "hapmat_stick_imu.npz"
)
FS = PEN_RATE_HZ
BANDS = ((0.0, 2.0), (2.0, 10.0), (10.0, 50.0))
WIDEN_FACTOR = 1.5  # magnitudes: real range widened to [min / 1.5, max * 1.5]
WIDEN_FRACTION = 0.1  # band fractions: real range widened by +/- 0.1

FIGURES = (
    "acc_rms_x",
    "acc_rms_y",
    "acc_rms_z",
    "gyr_rms_x",
    "gyr_rms_y",
    "gyr_rms_z",
    "acc_centroid",
    "acc_0_2",
    "acc_2_10",
    "acc_10_50",
    "gyr_centroid",
    "gyr_0_2",
    "gyr_2_10",
    "gyr_10_50",
    "reversals_per_s",
)


def remove_gravity(accel_g: np.ndarray, gyro_rad: np.ndarray, fs: float = FS) -> np.ndarray:
    """User acceleration (n, 3) g: accel minus a gyro-propagated, accel-corrected gravity."""
    dt, alpha = 1.0 / fs, 1.0 / fs  # alpha = dt / tau with tau = 1 s
    g = accel_g[: int(fs)].mean(axis=0)
    out = np.empty_like(accel_g)
    for k in range(len(accel_g)):
        g = g - dt * np.cross(gyro_rad[k], g)  # gravity is fixed in the world: dg/dt = -w x g
        g = (1 - alpha) * g + alpha * accel_g[k]
        out[k] = accel_g[k] - g
    return out


def band_figures(x: np.ndarray, fs: float = FS, nper: int = 256) -> tuple[float, list[float]]:
    """Spectral centroid (Hz) and band power fractions of ``x`` (n, 3), axes summed (Welch)."""
    x = x - x.mean(axis=0)
    win = np.hanning(nper)
    starts = range(0, len(x) - nper + 1, nper // 2)
    psd = sum(np.abs(np.fft.rfft(x[s : s + nper] * win[:, None], axis=0)) ** 2 for s in starts)
    psd = np.asarray(psd).sum(axis=1)
    f = np.fft.rfftfreq(nper, 1.0 / fs)
    psd[0] = 0.0
    total = psd.sum()
    fractions = [
        psd[(f >= lo) & (f < hi if hi < fs / 2 else f <= hi)].sum() / total for lo, hi in BANDS
    ]
    return float((f * psd).sum() / total), fractions


def lowpass(x: np.ndarray, cutoff: float, fs: float = FS) -> np.ndarray:
    """Zero-phase brick-wall low-pass along axis 0 (FFT)."""
    spec = np.fft.rfft(x, axis=0)
    spec[np.fft.rfftfreq(len(x), 1.0 / fs) > cutoff] = 0.0
    return np.fft.irfft(spec, len(x), axis=0)


def reversal_rate(gyro_rad: np.ndarray, fs: float = FS) -> float:
    """Sign changes per second of the 3 Hz low-passed gyro on its principal axis (hysteresis)."""
    slow = lowpass(gyro_rad - gyro_rad.mean(axis=0), 3.0, fs)
    _, _, vt = np.linalg.svd(slow, full_matrices=False)
    w = slow @ vt[0]
    threshold = 0.1 * w.std()
    state, crossings = 0, 0
    for value in w:
        new = 1 if value > threshold else -1 if value < -threshold else state
        if state and new != state:
            crossings += 1
        state = new
    return crossings * fs / len(w)


def figures(accel_g: np.ndarray, gyro_rad: np.ndarray) -> dict[str, float]:
    """All figures of one recording: ``accel_g`` user acceleration, ``gyro_rad`` (n, 3)."""
    accel_g = accel_g - accel_g.mean(axis=0)
    gyro_rad = gyro_rad - gyro_rad.mean(axis=0)
    out = {f"acc_rms_{a}": float(v) for a, v in zip("xyz", np.sqrt((accel_g**2).mean(0)))}
    out |= {f"gyr_rms_{a}": float(v) for a, v in zip("xyz", np.sqrt((gyro_rad**2).mean(0)))}
    for name, x in (("acc", accel_g), ("gyr", gyro_rad)):
        centroid, fractions = band_figures(x)
        out[f"{name}_centroid"] = centroid
        for (lo, hi), frac in zip(BANDS, fractions):
            out[f"{name}_{lo:.0f}_{hi:.0f}"] = frac
    out["reversals_per_s"] = reversal_rate(gyro_rad)
    return out


def hapmat_figures(path: Path) -> dict[str, dict[str, float]]:
    """Figures per HapMat material (accel columns 0-2 in g, rota columns 6-8 in rad/s)."""
    data = np.load(path)
    x = data["X"].astype(np.float64)
    return {
        f"hapmat:{name}": figures(x[i, :, 0:3], x[i, :, 6:9])
        for i, name in enumerate(data["classes"])
    }


def sim_figures(texture: str, sessions: int, seconds: float) -> dict[str, float]:
    """Figures of ``texture`` averaged over ``sessions`` simulated sessions (seeds 0..)."""
    scales = np.array([c.scale for c in PEN_CHANNELS])
    runs = []
    for seed in range(sessions):
        raw = simulate(texture, seconds, seed=seed).astype(np.float64) * scales
        gyro = np.radians(raw[:, 5:8])
        runs.append(figures(remove_gravity(raw[:, 2:5], gyro), gyro))
    return {k: float(np.mean([r[k] for r in runs])) for k in FIGURES}


def verdict(real: dict[str, dict[str, float]], sim: dict[str, dict[str, float]]) -> list[str]:
    """One line per figure: the real range (widened) and which simulated textures fall out."""
    lines = []
    for key in FIGURES:
        values = [r[key] for r in real.values()]
        lo, hi = min(values), max(values)
        if "_rms_" in key or key.endswith(("centroid", "per_s")):
            wlo, whi = lo / WIDEN_FACTOR, hi * WIDEN_FACTOR
        else:
            wlo, whi = max(0.0, lo - WIDEN_FRACTION), min(1.0, hi + WIDEN_FRACTION)
        out = [name.split(":")[1] for name, s in sim.items() if not wlo <= s[key] <= whi]
        status = "IN " if not out else "OUT"
        detail = "all simulated textures inside" if not out else "outside: " + ", ".join(out)
        lines.append(
            f"{key:16s} real {lo:8.4f}..{hi:8.4f} widened {wlo:8.4f}..{whi:8.4f}  {status} {detail}"
        )
    return lines


def table(rows: dict[str, dict[str, float]]) -> list[str]:
    """Sources as rows, figures as columns."""
    short = [k.replace("reversals_per_s", "rev/s").replace("_centroid", "_cen") for k in FIGURES]
    lines = ["source".ljust(22) + "".join(s.rjust(10) for s in short)]
    for name, fig in rows.items():
        lines.append(name.ljust(22) + "".join(f"{fig[k]:10.4f}" for k in FIGURES))
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hapmat", type=Path, default=DEFAULT_HAPMAT, help="hapmat_stick_imu.npz")
    parser.add_argument("--sessions", type=int, default=5, help="simulated sessions per texture")
    parser.add_argument("--seconds", type=float, default=60.0, help="seconds per session")
    args = parser.parse_args(argv)
    if not args.hapmat.is_file():
        print(f"error: HapMat file not found: {args.hapmat} (use --hapmat PATH)", file=sys.stderr)
        return 1
    real = hapmat_figures(args.hapmat)
    sim = {f"sim:{t}": sim_figures(t, args.sessions, args.seconds) for t in TEXTURES}
    print("units: acc g (gravity removed), gyr rad/s, centroid Hz, bands = power fraction, rev/s")
    print(f"simulated: mean over {args.sessions} sessions x {args.seconds:g} s per texture\n")
    print("\n".join(table(real | sim)))
    print("\nverdict (simulated texture means vs real range over the 5 materials):")
    print("\n".join(verdict(real, sim)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
