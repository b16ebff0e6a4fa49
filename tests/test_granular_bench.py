"""bench/granular_experiments.py on a tiny simulated pen set, and every config of
configs/granular/ parsed and built into a model on matching tiny data."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import sys

import pytest
from conftest import REPO

CONFIGS = REPO / "configs" / "granular"
# the Table 1 rows; biotac-recommended.toml is the toolkit's pick among models, tested below
TABLE_CONFIGS = sorted(p for p in CONFIGS.glob("*.toml") if p.stem != "biotac-recommended")


def _bench():
    spec = importlib.util.spec_from_file_location("granular_experiments",
                                                  REPO / "bench" / "granular_experiments.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


ge = _bench()


def _rows(text: str) -> dict[str, list[str]]:
    """{model label: cells} of the markdown table rows printed by the bench."""
    out = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("| ") and cells[0] in ge.LABELS.values():
            out[cells[0]] = cells
    return out


def test_the_bench_trains_exports_times_prints_and_resumes(tmp_path, capsys, monkeypatch):
    args = ["--cache", str(tmp_path), "--dataset", "pen", "--models", "linear",
            "--seeds", "1", "--pen-users", "15", "--pen-seconds", "3",
            "--set", "epochs=1", "--set", "epoch_windows=64"]
    assert ge.main(args) == 0
    rows = _rows(capsys.readouterr().out)
    assert set(rows) == {"linear"}
    # dims: the log energy of 4 IMFs of each of the 7 channels (configs/granular/pen-linear)
    assert rows["linear"][1:3] == ["28", "N/A"]
    for cells in rows.values():
        assert float(cells[3]) > 0  # ms to label 1 s of data
        for acc in cells[4:7]:  # validation, test, novel (%), one seed: no spread
            assert 0.0 <= float(acc) <= 100.0
        assert cells[8] == "0"
    assert rows["linear"][9] == "32, N/A, 2.2, 60.8 / 62.0 / 62.0"  # the paper's, beside
    runs = sorted((tmp_path / "runs").glob("*/*/seed0"))
    assert [r.parts[-3] for r in runs] == ["pen-linear"]
    for r in runs:
        assert {"metrics.json", "model.onnx", "timing.json", "cost.json"} <= {
            p.name for p in r.iterdir()}
    stamps = {r: (r / "model.onnx").stat().st_mtime_ns for r in runs}

    def refuse(*a, **k):
        raise AssertionError("a finished run was trained again")

    monkeypatch.setattr("tactile.training.train.train", refuse)
    assert ge.main(args) == 0  # resumable: every finished step is skipped
    assert _rows(capsys.readouterr().out) == rows
    assert {r: (r / "model.onnx").stat().st_mtime_ns for r in runs} == stamps
    # another setting is another run, never a finished one reused
    assert ge.settings_key(ge.Row("pen", "all", "linear").config(), ["epochs=2"],
                           tmp_path / "data") != runs[0].parts[-2]


def test_ctrl_c_stops_the_bench_in_one_line_with_exit_130(tmp_path, capsys, monkeypatch):
    """A training stopped by Ctrl-C ends the benchmark with one line (no traceback) and 130;
    the same command continues it."""
    args = ["--cache", str(tmp_path), "--dataset", "pen", "--models", "linear",
            "--seeds", "1", "--pen-users", "15", "--pen-seconds", "3",
            "--set", "epochs=1", "--set", "epoch_windows=64"]

    def stopped(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(ge, "train_job", stopped)
    assert ge.main(args) == 130
    err = capsys.readouterr().err
    assert "stopped; the same command continues where it stopped" in err
    assert "Traceback" not in err


def test_seed_and_choice_options():
    p = ge.build_parser()
    assert p.parse_args(["--seeds", "3"]).seeds == (0, 1, 2)
    assert p.parse_args(["--seeds", "4,7"]).seeds == (4, 7)
    assert p.parse_args(["--models", "sf_rnn,linear"]).models == ("sf_rnn", "linear")
    for bad in (["--seeds", "0"], ["--models", "lstm"], ["--block", "pressure"]):
        with pytest.raises(SystemExit):
            p.parse_args(bad)
    names = [r.name for r in ge.rows(("biotac", "pen"), None, ge.MODELS)]
    assert sorted(f"{n}.toml" for n in names) == sorted(p.name for p in TABLE_CONFIGS)


def test_spread_is_mean_and_population_sd_in_percent():
    assert ge.spread([0.5, 0.7]) == "60.0 +/- 10.0"
    assert ge.spread([0.25]) == "25.0"
    assert ge.spread([]) == "-"
    assert ge.spread([float("nan"), 0.4]) == "40.0"


def test_emd_memo_returns_what_the_emd_computes(tmp_path):
    import torch

    from tactile.training.emd import EMD

    x = torch.randn(3, 2, 60, generator=torch.Generator().manual_seed(0))
    emd = EMD(3, 4)
    want = emd(x)
    memo = ge.EMDMemo(tmp_path)
    compute = EMD.forward
    try:
        memo.install()
        first, again = emd(x), emd(x)
        other = emd(x + 1.0)
    finally:
        EMD.forward = compute
    assert (memo.misses, memo.hits) == (2, 1)
    for a, b, c in zip(want, first, again, strict=True):
        assert torch.equal(a, b) and torch.equal(a, c)
    assert not torch.equal(other[0], want[0])
    assert len(list(tmp_path.glob("*.pt"))) == 2
    json.dumps(ge.PAPER)  # the paper's figures are plain data


def test_paper_figures_match_the_papers_table_1():
    text = (REPO.parent / "shared" / "papers" / "001_86ae307f4aede738.txt")
    if not text.exists():
        pytest.skip(f"the paper's text is not at {text}")
    body = text.read_text()
    heads = {"linear": r"Linear\s+Classifier", "sparse_linear": r"Linear\s+classifier",
             "f_rnn": r"F-RNN\[9\]", "sf_rnn": r"SF-RNN"}
    for model, head in heads.items():
        m = re.search(head + r"\s+((?:[\d.]+|N/A)\s+){12}", body)
        assert m, model
        got = m.group(0).split()[-12:]
        ours = [*ge.PAPER["vibration"][model], *ge.PAPER["all"][model]]
        want = ["N/A" if v is None else (str(v) if isinstance(v, int) else f"{v:.1f}")
                for v in ours]
        assert got == want, model


# dims of the feature space each config's classifier sees, from the paper's sizes (sec. II.A-B):
# vibration image 1 signal x 8 IMFs x 22 samples = 176, pressure 1 x 5 x 5 = 25, electrodes
# 19 x 5 = 95 (no EMD); atoms 200 / 100 / 100; the linear classifier: one log energy per IMF,
# electrodes their mean and log std (2 each). The pen: 4 IMFs x 5 steps of pressure_0 (20),
# accel_x/y/z (60) and gyro_x/y/z (60), 100 atoms each.
DIMS = {
    "biotac-vibration": {"linear": 8, "sparse_linear": 200, "f_rnn": 176, "sf_rnn": 200},
    "biotac-all": {"linear": 8 + 5 + 38, "sparse_linear": 400, "f_rnn": 176 + 25 + 95,
                   "sf_rnn": 400},
    "pen": {"linear": 4 + 12 + 12, "sparse_linear": 300, "f_rnn": 20 + 60 + 60, "sf_rnn": 300},
}


@pytest.mark.parametrize("path", TABLE_CONFIGS, ids=lambda p: p.stem)
def test_every_config_parses_and_builds_a_model_on_matching_data(path):
    import numpy as np
    import torch

    from tactile.device.protocol import PEN_CHANNELS
    from tactile.device.recordings.biotac import channels as biotac_channels
    from tactile.training.config import TrainConfig
    from tactile.training.models import build_model

    cfg = TrainConfig.from_toml(path)
    prefix, model = path.stem.rsplit("-", 1)
    assert cfg.model == model
    names = (tuple(c.name for c in biotac_channels()) if prefix.startswith("biotac")
             else tuple(c.name for c in PEN_CHANNELS))
    assert set(cfg.channels) <= set(names)
    c = len(cfg.channels)
    m = build_model(cfg, 5, torch.zeros(c), torch.ones(c), channels=cfg.channels, rate_hz=100.0)
    assert m.pre.n_features == DIMS[prefix][model]
    if model.endswith("rnn"):  # the paper's 4 x 50 LSTM, dropout 0.4
        assert (cfg.layers, cfg.hidden, cfg.dropout) == (4, 50, 0.4)
    assert (cfg.window, cfg.hop) == (50, 50)
    if m.pre.needs_dictionaries:  # random unit atoms stand in for learned ones
        rng = np.random.default_rng(0)
        dicts = [rng.standard_normal((lay.atoms, lay.features)).astype(np.float32)
                 for lay in m.pre.layout]
        m.pre.set_dictionaries([d / np.linalg.norm(d, axis=1, keepdims=True) for d in dicts])
    x = torch.randn(2, cfg.window, c, generator=torch.Generator().manual_seed(1))
    m.eval()
    with torch.no_grad():
        probs, h, _ = m(x, *m.zero_state(2))
    assert probs.shape == (2, 5)
    assert torch.allclose(probs.sum(1), torch.ones(2), atol=1e-5)
    assert torch.isfinite(h).all()


def test_a_run_held_by_a_live_process_is_passed_by_and_a_stale_lock_taken_over(tmp_path):
    import subprocess

    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    dead = int(done.stdout)  # a pid whose process has ended
    with ge.RunLock(tmp_path):
        with pytest.raises(ge.Busy):  # held by this (live) process
            ge.RunLock(tmp_path).__enter__()
    assert not (tmp_path / ".lock").exists()
    (tmp_path / ".lock").write_text(str(dead))
    with ge.RunLock(tmp_path):
        assert (tmp_path / ".lock").read_text() == str(os.getpid())


def test_recommended_biotac_config_is_the_f_rnn_row_at_the_toolkit_budget_blended():
    from tactile.training.config import TrainConfig

    rec = TrainConfig.from_toml(CONFIGS / "biotac-recommended.toml")
    row = TrainConfig.from_toml(CONFIGS / "biotac-all-f_rnn.toml")
    assert rec.blends and not row.blends
    assert rec == row.replace(blend="on")
    assert (rec.val, rec.test) == ("repetition:4", "repetition:5")
