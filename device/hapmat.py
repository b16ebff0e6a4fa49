"""Import the HapMat recordings (a 6-axis IMU on a hand-held stick, 5 materials, 100 Hz) as takes.

    tactile-import-hapmat PATH/hapmat_stick_imu.npz --out data/hapmat

Each material's 60 s session becomes one take labelled with the material in lower case. Channels
map onto the pen's names: ``accel_x..z`` from HapMat's accelerometer (g, gravity already
removed upstream) and ``gyro_x..z`` from its calibrated rotation rate ``rota_x..z``, converted
from rad/s to the pen's deg/s. The pen's ``pressure_0/1`` are absent (the stick has no tip
sensor) and listed as such in each take's metadata. Values are stored as float64, scale 1.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from tactile.cli import Parser, add_debug, run
from tactile.device.info import ChannelSpec, DeviceInfo
from tactile.device.recording import TakeWriter
from tactile.errors import RecordingError

CHANNELS = (
    ChannelSpec("accel_x", "g"),
    ChannelSpec("accel_y", "g"),
    ChannelSpec("accel_z", "g"),
    ChannelSpec("gyro_x", "deg/s"),
    ChannelSpec("gyro_y", "deg/s"),
    ChannelSpec("gyro_z", "deg/s"),
)
SOURCE_COLUMNS = ("accel_x", "accel_y", "accel_z", "rota_x", "rota_y", "rota_z")


def import_hapmat(npz: Path, out: Path) -> list[Path]:
    """Write one take per material; returns the CSV paths."""
    try:
        d = np.load(npz, allow_pickle=False)
        x, classes, names = d["X"], d["classes"], [str(c) for c in d["channels"]]
        rate = float(d["fs_hz"])
    except (OSError, KeyError, ValueError) as e:
        raise RecordingError(f"{npz}: not the HapMat .npz ({e})") from None
    try:
        cols = [names.index(c) for c in SOURCE_COLUMNS]
    except ValueError:
        raise RecordingError(f"{npz}: channels {names} lack one of {SOURCE_COLUMNS}") from None
    info = DeviceInfo(rate, CHANNELS, device="hapmat-stick-imu")
    to_deg = np.array([1, 1, 1, 180 / math.pi, 180 / math.pi, 180 / math.pi])
    paths = []
    for k, material in enumerate(classes):
        values = x[k][:, cols].astype(np.float64) * to_deg  # (n, 6)
        if not np.all(np.isfinite(values)):
            raise RecordingError(f"{npz}: {material} holds NaN or inf")
        label = str(material).lower()
        extra = {
            "absent_channels": ["pressure_0", "pressure_1"],
            "origin": str(d["source"]) if "source" in d.files else "HapMat",
            "licence": "MIT (HapMat, haptic-kinematics repository)",
            "user": 0,
            "notes": "accel has gravity removed upstream; gyro from rota_* (rad/s -> deg/s)",
        }
        name = f"hapmat-{label}"
        with TakeWriter(out, label, info, f"hapmat:{npz.name}", name=name, extra=extra) as w:
            w.write(0, 0, values)
        paths.append(w.csv_path)
    return paths


def _main(args: argparse.Namespace) -> int:
    for p in import_hapmat(args.npz, args.out):
        print(p)
    return 0


def main(argv: list[str] | None = None) -> int:
    p = Parser(
        prog="tactile-import-hapmat", description="Import the HapMat stick-IMU recordings."
    )
    p.add_argument("npz", type=Path, help="hapmat_stick_imu.npz")
    p.add_argument("--out", type=Path, required=True, help="dataset folder to write")
    add_debug(p)
    return run("tactile-import-hapmat", _main, p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
