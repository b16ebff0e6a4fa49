"""Make what ``scripts/aarch64-check.sh`` replays on the emulated board: one recorded take and
two small exported models that exercise the graph's heavy parts, an EMD-feature LSTM and a
granular SF-RNN (EMD, sparse codes, fusion). Trained for one epoch on a small simulated
dataset: the point is the same file giving the same labels on two machines, not accuracy.

Usage: python scripts/aarch64_models.py OUT  (writes OUT/take.csv, .json, emd.onnx, sf_rnn.onnx)
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

BIN = Path(sys.executable).parent
TEXTURES = "paper,mouse_pad,nonwoven_cloth"
GRANULAR = """model = "sf_rnn"
window = 50
hop = 50
layers = 2
hidden = 16
epochs = 1
refit = "off"
emd_sifts = 10

[modalities.pressure]
channels = ["pressure_0"]
imfs = 3
steps = 5
atoms = 16

[modalities.acceleration]
channels = ["accel_*"]
imfs = 3
steps = 5
atoms = 16
"""


def sh(*args: str | Path) -> None:
    subprocess.run([str(a) for a in args], check=True, stdout=subprocess.DEVNULL)


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        data, runs = Path(tmp) / "data", Path(tmp) / "runs"
        sh(BIN / "tactile-sim", "--dataset", data, "--takes", 6, "--seconds", 20, "--seed", 7,
           "--textures", TEXTURES)
        take = sorted(data.glob("*.csv"))[-1]  # a test user's take (the last users test)
        shutil.copy(take, out / "take.csv")
        shutil.copy(take.with_suffix(".json"), out / "take.json")  # its header and label
        (Path(tmp) / "granular.toml").write_text(GRANULAR)
        sh(BIN / "tactile-train", data, "--out", runs / "emd", "--set", "epochs=1",
           "--set", "refit=off", "--set", "emd_channels=pressure_0,accel_x,accel_y,accel_z")
        sh(BIN / "tactile-train", data, "--out", runs / "sf_rnn", "--config",
           Path(tmp) / "granular.toml")
        for name in ("emd", "sf_rnn"):
            sh(BIN / "tactile-export", runs / name, "-o", out / f"{name}.onnx", "--data", data)
    print(f"made {out / 'take.csv'}, {out / 'emd.onnx'}, {out / 'sf_rnn.onnx'}", file=sys.stderr)


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__.strip().splitlines()[-1])
    main(Path(sys.argv[1]))
