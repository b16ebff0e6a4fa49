"""bench/soak.py: a short soak of a model of some of the pen's channels (tactile-run takes them
by name) matches its ground truth, window for window and gap for gap."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("torch", reason="the [train] extra (torch) is not installed")

ROOT = Path(__file__).resolve().parents[1]


def test_a_short_soak_of_a_model_of_some_channels_matches_the_ground_truth(tmp_path):
    from tactile.device.sim import make_dataset
    from tactile.export.exporter import export_run
    from tactile.training.config import TrainConfig
    from tactile.training.train import train

    make_dataset(tmp_path / "d", 3, ("paper", "desk"), seconds=6.0, seed=2)
    cfg = TrainConfig(channels=("pressure_0", "accel_x", "accel_y", "accel_z"), epochs=1,
                      test="user:2", val="user:1", refit="off")
    train(tmp_path / "d", tmp_path / "run", cfg, progress=False)
    model = tmp_path / "m.onnx"
    export_run(tmp_path / "run", model, log=lambda s: None)
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "soak.py"), "--seconds", "40",
                        "--model", str(model)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert "result: identical to ground truth" in r.stdout, r.stdout
    assert "labels equal: yes" in r.stdout and "identical positions: yes" in r.stdout
