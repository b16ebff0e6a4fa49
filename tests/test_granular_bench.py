"""bench/granular_experiments.py on a tiny simulated pen set, and every config of
configs/granular/ parsed and built into a model on matching tiny data."""

from __future__ import annotations

import importlib.util
import json
import re
import sys

import pytest
from conftest import REPO

CONFIGS = REPO / "configs" / "granular"


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
    args = ["--cache", str(tmp_path), "--dataset", "pen", "--models", "linear,sf_rnn",
            "--seeds", "1", "--pen-users", "15", "--pen-seconds", "3",
            "--set", "epochs=1", "--set", "epoch_windows=64"]
    assert ge.main(args) == 0
    rows = _rows(capsys.readouterr().out)
    assert set(rows) == {"linear", "SF-RNN"}
    # dims: the linear classifier sees the log energy of 4 IMFs of each of the 7 channels;
    # SF-RNN the concatenated codes, 100 atoms per modality (configs/granular/pen-*.toml)
    assert rows["linear"][1:3] == ["28", "N/A"]
    assert rows["SF-RNN"][1:3] == ["300", "50"]
    for cells in rows.values():
        assert float(cells[3]) > 0  # ms to label 1 s of data
        for acc in cells[4:7]:  # validation, test, novel (%), one seed: no spread
            assert 0.0 <= float(acc) <= 100.0
        assert cells[8] == "0"
    assert rows["SF-RNN"][9] == "400, 50, 3.0, 98.4 / 98.7 / 98.0"  # the paper's, beside
    runs = sorted((tmp_path / "runs").glob("*/*/seed0"))
    assert [r.parts[-3] for r in runs] == ["pen-linear", "pen-sf_rnn"]
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


def test_seed_and_choice_options():
    p = ge.build_parser()
    assert p.parse_args(["--seeds", "3"]).seeds == (0, 1, 2)
    assert p.parse_args(["--seeds", "4,7"]).seeds == (4, 7)
    assert p.parse_args(["--models", "sf_rnn,linear"]).models == ("sf_rnn", "linear")
    for bad in (["--seeds", "0"], ["--models", "lstm"], ["--block", "pressure"]):
        with pytest.raises(SystemExit):
            p.parse_args(bad)
    names = [r.name for r in ge.rows(("biotac", "pen"), None, ge.MODELS)]
    assert sorted(f"{n}.toml" for n in names) == sorted(p.name for p in CONFIGS.glob("*.toml"))


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
