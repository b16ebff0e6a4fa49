"""bench/baselines.py's judging of stopping rules: the epoch each rule keeps and its score on
held-out halves of the validation takes, on curves made by hand."""

from __future__ import annotations

import importlib.util
import json
import sys

import numpy as np
import pytest
from conftest import REPO


def _bench():
    spec = importlib.util.spec_from_file_location("baselines", REPO / "bench" / "baselines.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def test_halves_split_every_take_in_time():
    b = _bench()
    take = np.array([0, 0, 0, 0, 1, 1, 1])
    start = np.array([30, 0, 20, 10, 5, 0, 10])
    assert b._halves(take, start).tolist() == [False, True, False, True, False, True, False]


def test_pick_epoch_follows_the_rules_and_the_patience():
    b = _bench()
    acc = np.array([0.5, 0.6, 0.7, 0.8, 0.8, 0.7])
    loss = np.array([1.0, 0.8, 0.9, 1.2, 1.1, 1.5])
    assert b.pick_epoch("loss", acc, loss, patience=5) == 1
    assert b.pick_epoch("accuracy", acc, loss, patience=5) == 4  # the tie: the lower loss
    late = np.array([0.5, 0.6, 0.55, 0.8])  # a better epoch after one that is not
    assert b.pick_epoch("accuracy", late, loss[:4], patience=1) == 1
    assert b.pick_epoch("accuracy", late, loss[:4], patience=2) == 3


def test_rules_are_scored_on_the_half_they_did_not_pick_on(tmp_path):
    b = _bench()
    # 2 takes x 4 windows, 2 classes, 2 epochs; q: the probability of the right class. Epoch 0:
    # half the windows of each half-take sure and right (0.95), half wrong (0.45): accuracy
    # 0.5, loss 0.43; epoch 1: all barely right (0.55): accuracy 1, loss 0.60
    y = np.array([0, 1, 0, 1, 1, 0, 1, 0])
    take = np.repeat([0, 1], 4)
    start = np.tile([0, 1, 2, 3], 2)
    q = np.array([np.where(start % 2 == 0, 0.95, 0.45), np.full(8, 0.55)])
    probs = np.zeros((2, 8, 2))
    rows = np.arange(8)
    probs[:, rows, y] = q
    probs[:, rows, 1 - y] = 1 - q
    np.savez(tmp_path / "c.npz", probs=probs, y=y, take=take, start=start)
    r = b.selection_rules(tmp_path / "c.npz", patience=5)
    # on either half the loss keeps epoch 0 (0.5 on the other half), the accuracy epoch 1 (1.0)
    assert r["loss"] == {"held_out": 0.5, "epoch": 1, "val_accuracy": 0.5}
    assert r["accuracy"] == {"held_out": 1.0, "epoch": 2, "val_accuracy": 1.0}


def _names(takes, part) -> set[str]:
    return {takes[i].path.stem for i in part}


def test_nested_split_by_user_never_holds_a_test_take(tmp_path):
    from tactile.device.recordings import load_dataset
    from tactile.device.sim import make_dataset
    from tactile.training.config import TrainConfig
    from tactile.training.data import split_takes

    b = _bench()
    make_dataset(tmp_path / "d", 8, ("paper", "mouse_pad"), 2.0, seed=0)
    takes = load_dataset(tmp_path / "d")
    for seed in (0, 1):
        cfg = TrainConfig(seed=seed)
        outer = split_takes(takes, cfg)
        ncfg = b.nested_data(takes, cfg, tmp_path / f"nested{seed}")
        inner_takes = load_dataset(tmp_path / f"nested{seed}")
        inner = split_takes(inner_takes, ncfg)
        folder = {t.path.stem for t in inner_takes}
        # the folder: the outer training and validation takes, no test take
        assert folder == _names(takes, outer.train) | _names(takes, outer.val)
        assert not folder & _names(takes, outer.test) and len(outer.test) == 2 * 2
        # its test is the outer validation; its validation and training the outer training
        assert _names(inner_takes, inner.test) == _names(takes, outer.val)
        assert _names(inner_takes, inner.val) | _names(inner_takes, inner.train) == \
            _names(takes, outer.train)
        assert not _names(inner_takes, inner.val) & _names(inner_takes, inner.train)
        # drawn in whole users as the bench draws validation: 1 of the 5 training users here
        users = {t.meta["user"] for i, t in enumerate(inner_takes) if i in inner.val}
        assert len(users) == 1 and len(inner.val) == 2


def test_nested_split_in_time_cuts_the_takes_before_their_test_block(tmp_path):
    from tactile.device.recordings import load_dataset
    from tactile.device.sim import make_dataset
    from tactile.training.config import TrainConfig
    from tactile.training.data import split_takes

    b = _bench()
    make_dataset(tmp_path / "d", 1, ("paper", "mouse_pad"), 3.1, seed=0)
    takes = load_dataset(tmp_path / "d")
    cfg = TrainConfig(split="time")
    outer = split_takes(takes, cfg)
    ncfg = b.nested_data(takes, cfg, tmp_path / "nested")
    cut = load_dataset(tmp_path / "nested")
    inner = split_takes(cut, ncfg)
    for i, (t, c) in enumerate(zip(takes, cut, strict=True)):
        assert c.path.stem == t.path.stem and c.meta["user"] == t.meta["user"]
        end = outer.val[i][1]  # the test block's first row: not in the copy
        assert len(c.seq) == end == outer.test[i][0]
        np.testing.assert_array_equal(c.values(), t.values()[:end])
        np.testing.assert_array_equal(c.seq, t.seq[:end])
        assert inner.test[i] == outer.val[i]  # the proxy test: the outer validation block
        assert inner.train[i][0] == 0 and inner.train[i][1] == inner.val[i][0]
        assert inner.val[i][1] == outer.val[i][0]  # the inner validation ends where it began
        assert inner.val[i][0] == round(outer.val[i][0] * (1 - cfg.val_fraction))


def test_nested_runs_read_no_test_take(tmp_path, monkeypatch):
    from tactile.device.recordings import reader as recording
    from tactile.device.sim import make_dataset
    from tactile.training.config import TrainConfig
    from tactile.training.data import split_takes

    b = _bench()
    make_dataset(tmp_path / "d", 6, ("paper", "mouse_pad"), 2.0, seed=0)
    takes = recording.load_dataset(tmp_path / "d")
    base = TrainConfig(threads=1, epochs=2, patience=1, hidden=4, layers=1, epoch_windows=64)
    test = {takes[i].path.stem for i in split_takes(takes, base).test}
    read = []
    real = recording.read_take

    def spy(path):
        read.append(recording.Path(path).stem)
        return real(path)

    monkeypatch.setattr(recording, "read_take", spy)
    rows = b.run_nested("small", takes, tmp_path / "out", (0,), base)
    assert read and not set(read) & test
    r = rows[0]
    assert r["off"]["refit_epochs"] == 0 and r["on"]["refit_epochs"] == r["on"]["best_epoch"] + 1
    # the same first phase: same split, same inner validation figure
    assert r["off"]["val_accuracy"] == r["on"]["val_accuracy"]
    assert r["off"]["split_windows"] == r["on"]["split_windows"]
    assert "| small | 0 |" in b.nested_table(rows)


def test_literal_selector_names_only_that_take():
    from tactile.training.data import _matches

    b = _bench()
    for name in ("a[1]*", "3-5", "x?y", "paper-user000"):
        pattern = b._literal(name)
        assert _matches(name, pattern)
        for other in ("a1", "a[1]x", "4", "xzy", "3-50", "paper-user0001"):
            assert not _matches(other, pattern) or other == name


def test_same_split_with_another_seed(tmp_path):
    from tactile.device.recordings import load_dataset
    from tactile.device.sim import make_dataset
    from tactile.training.config import TrainConfig
    from tactile.training.data import split_takes

    b = _bench()
    make_dataset(tmp_path / "d", 8, ("paper", "mouse_pad"), 1.0, seed=0)
    takes = load_dataset(tmp_path / "d")
    for cfg in (TrainConfig(seed=2), TrainConfig(seed=2, test="user:5")):
        again = b.same_split(takes, cfg, 1002)
        first, second = split_takes(takes, cfg), split_takes(takes, again)
        assert again.seed == 1002 and (first.train, first.val, first.test) == (
            second.train, second.val, second.test)
        # the seed alone would have drawn another split
        other = split_takes(takes, cfg.replace(seed=1002))
        assert (other.val, other.test) != (first.val, first.test)
    assert b.same_split(takes, TrainConfig(split="time"), 7).seed == 7


def test_only_runs_the_script_finished_are_reused(tmp_path):
    """A run folder counts as done only with the script's times in its metrics and no
    interruption: train()'s own metrics.json (written also after Ctrl-C) does not."""
    baselines = _bench()
    run = tmp_path / "small-seed0"
    run.mkdir()
    assert baselines.finished(run) is None  # nothing there
    (run / "metrics.json").write_text(json.dumps({"accuracy": 0.5}))
    assert baselines.finished(run) is None  # train() wrote it, the script did not finish
    (run / "metrics.json").write_text(json.dumps({"accuracy": 0.5, "interrupted": True,
                                                  "cpu_seconds": 3.0}))
    assert baselines.finished(run) is None
    (run / "metrics.json").write_text("{half")
    assert baselines.finished(run) is None
    with pytest.raises(KeyboardInterrupt):
        baselines._timed(run, {"accuracy": 0.5, "interrupted": True}, 0.0, 0.0)
    m = baselines._timed(run, {"accuracy": 0.5}, 0.0, 0.0)
    assert m["cpu_seconds"] >= 0 and baselines.finished(run) == json.loads(
        (run / "metrics.json").read_text())


def test_nothing_to_run_is_exit_2_not_an_empty_table(tmp_path, monkeypatch, capsys):
    """With every dataset asked for skipped, the script says so and exits 2 (it printed an
    empty table and exited 0)."""
    baselines = _bench()
    monkeypatch.setattr(baselines, "HAPMAT", tmp_path / "absent.npz")
    assert baselines.main(["--out", str(tmp_path / "out"), "--only", "hapmat"]) == 2
    out, err = capsys.readouterr()
    assert f"hapmat: skipped, no absent.npz in {tmp_path} -->" in out
    assert "|" not in out and err.strip().endswith("nothing to run")


def test_the_command_lines_settings_win_over_a_datasets_own(tmp_path, monkeypatch):
    """--set hop=10 (or a candidate's hop) reaches BioTac's runs, whose own data settings
    say hop=50; the settings the command line does not give stay. Checked on the config the
    training and the baseline of a run_dataset call receive (both stand-ins here)."""
    from tactile.training.config import TrainConfig

    b = _bench()
    assert b.dataset_settings("biotac") == {"hop": 50, "test": "repetition:5",
                                            "channels": b.BIOTAC_CHANNELS}
    assert b.dataset_settings("biotac", b._keys(["hop=10", "refit=off", "channels=f0_pdc"])) == {
        "test": "repetition:5"}
    assert b.dataset_settings("hapmat", b._keys(["hop=10"])) == {"split": "time"}
    got = []

    def fake_train(data, run, cfg, progress=True):
        got.append(("train", cfg.hop, cfg.test))
        run.mkdir(parents=True, exist_ok=True)
        return {"accuracy": 0.5, "val_accuracy": 0.5, "best_epoch": 0}

    def fake_baseline(takes, cfg):
        got.append(("baseline", cfg.hop, cfg.test))
        return {"accuracy": 0.5, "val_accuracy": 0.5, "C": 1.0, "cpu_seconds": 0.0}

    monkeypatch.setattr(b.train_module, "train", fake_train)
    monkeypatch.setattr(b, "band_logistic", fake_baseline)
    base = b.parse_sets(["hop=10"], TrainConfig(threads=1))
    b.run_dataset("biotac", tmp_path / "d", [], tmp_path / "given", (0,), base,
                  given=b._keys(["hop=10"]))
    b.run_dataset("biotac", tmp_path / "d", [], tmp_path / "own", (0,), base)
    assert got == [("train", 10, "repetition:5"), ("baseline", 10, "repetition:5"),
                   ("train", 50, "repetition:5"), ("baseline", 50, "repetition:5")]


def test_a_run_or_baseline_made_with_other_settings_is_refused_not_reused(tmp_path):
    """Reused results are keyed by folder name: with other settings in the same OUT the
    script stops, naming what differs, instead of printing the old runs' figures."""
    from tactile.training.config import TrainConfig

    b = _bench()
    run = tmp_path / "biotac-seed0"
    run.mkdir()
    cfg = TrainConfig(hop=50, seed=0)
    b._timed(run, {"accuracy": 0.5}, 0.0, 0.0, cfg)
    assert b.finished(run, cfg)["accuracy"] == 0.5
    with pytest.raises(b.StaleRun, match=r"hop 50 -> 10"):
        b.finished(run, cfg.replace(hop=10))
    # stored before the ensemble key: one model, as now; before the wide key: not the default
    m = json.loads((run / "metrics.json").read_text())
    del m["bench_settings"]["ensemble"]
    (run / "metrics.json").write_text(json.dumps(m))
    assert b.finished(run, cfg)["accuracy"] == 0.5
    with pytest.raises(b.StaleRun, match=r"ensemble 1 -> 2"):
        b.finished(run, cfg.replace(ensemble=2))
    del m["bench_settings"]["wide"]
    (run / "metrics.json").write_text(json.dumps(m))
    with pytest.raises(b.StaleRun, match=r"wide False -> True"):
        b.finished(run, cfg)
    (run / "metrics.json").write_text(json.dumps({"accuracy": 0.4, "cpu_seconds": 1.0}))
    assert b.finished(run, cfg.replace(hop=10))["accuracy"] == 0.4  # stored before settings

    calls = []

    def compute():
        calls.append(1)
        return {"accuracy": 0.7, "take_accuracy": 0.8}

    bfile = tmp_path / "baseline" / "biotac-seed0.json"
    assert b.cached_baseline(bfile, cfg, compute)["accuracy"] == 0.7
    # the model's settings do not matter to the baseline; its windows and refit do
    assert b.cached_baseline(bfile, cfg.replace(hidden=32), compute)["accuracy"] == 0.7
    assert len(calls) == 1
    # stored before the vote per take was: computed again (the table prints it)
    kept = json.loads(bfile.read_text())
    del kept["take_accuracy"]
    bfile.write_text(json.dumps(kept))
    assert b.cached_baseline(bfile, cfg, compute)["take_accuracy"] == 0.8 and len(calls) == 2
    with pytest.raises(b.StaleRun, match=r"refits True -> False"):
        b.cached_baseline(bfile, cfg.replace(refit="off"), compute)
    with pytest.raises(b.StaleRun, match=r"hop 50 -> 10"):
        b.cached_baseline(bfile, cfg.replace(hop=10), compute)


def test_a_grid_with_reinit_keeps_each_splits_baseline_apart(tmp_path, monkeypatch, capsys):
    """--reinit trains each candidate again with seed + K on the seed's split, named: its
    baseline has other settings (seed, named takes) and is kept in its own folder. Sharing
    the seed's baseline file stopped the grid (exit 2) at the first reinit run."""
    from tactile.device.recordings import load_dataset
    from tactile.device.sim import make_dataset

    b = _bench()
    make_dataset(tmp_path / "d", 8, ("paper", "mouse_pad"), 1.0, seed=0)
    takes = load_dataset(tmp_path / "d")
    monkeypatch.setattr(b, "prepare", lambda name, out, cache: (tmp_path / "d", takes))
    seeds = []

    def fake_train(data, run, cfg, progress=True):
        seeds.append(cfg.seed)
        run.mkdir(parents=True, exist_ok=True)
        return {"accuracy": 0.5, "val_accuracy": 0.5, "best_epoch": 0}

    fitted = []
    monkeypatch.setattr(b.train_module, "train", fake_train)
    monkeypatch.setattr(b, "band_logistic", lambda takes, cfg: fitted.append(cfg.seed) or {
        "accuracy": 0.4, "val_accuracy": 0.4, "C": 1.0, "cpu_seconds": 0.0})
    out = tmp_path / "out"
    assert b.main(["--out", str(out), "--only", "small", "--seeds", "0,1",
                   "--candidate", "x", "--reinit", "1000"]) == 0
    assert seeds == [0, 1, 1000, 1001]
    assert fitted == [0, 1]  # the reinit pass has the seeds' splits: fitted once each
    kept = {p.parent.name + "/" + p.name: json.loads(p.read_text())["settings"]["seed"]
            for p in out.glob("baseline*/*.json")}
    assert kept == {"baseline/small-seed0.json": 0, "baseline/small-seed1.json": 1,
                    "baseline-reinit1000/small-seed0.json": 1000,
                    "baseline-reinit1000/small-seed1.json": 1001}
    assert "x, seed + 1000" in capsys.readouterr().out


@pytest.mark.parametrize("sets, computed", [
    ([], [0, 1, 2]),  # the validation user drawn from each seed: three splits
    (["--set", "val=user:1", "--set", "test=user:0"], [0])])  # named: one split
def test_a_baseline_is_computed_once_per_split(tmp_path, monkeypatch, capsys, sets, computed):
    """With the test and validation takes named every seed has the same windows, and the
    baseline (which has no seed of its own) was fitted again for each: 160 s of CPU a seed on
    BioTac finger 0. Each seed still gets its file, with its own settings."""
    from tactile.device.recordings import load_dataset
    from tactile.device.sim import make_dataset

    b = _bench()
    make_dataset(tmp_path / "d", 8, ("paper", "mouse_pad"), 1.0, seed=0)
    takes = load_dataset(tmp_path / "d")
    monkeypatch.setattr(b, "prepare", lambda name, out, cache: (tmp_path / "d", takes))

    def fake_train(data, run, cfg, progress=True):
        run.mkdir(parents=True, exist_ok=True)
        return {"accuracy": 0.5, "val_accuracy": 0.5, "best_epoch": 0, "take_accuracy": 0.5,
                "split_windows": {"train": 1, "val": 1, "test": 1}}

    fitted = []

    def fake_baseline(takes, cfg):
        fitted.append(cfg.seed)
        return {"accuracy": 0.4 + cfg.seed / 100, "val_accuracy": 0.4, "C": 1.0,
                "take_accuracy": 0.5, "cpu_seconds": 0.0,
                "split_windows": {"train": 1, "val": 1, "test": 1}}

    monkeypatch.setattr(b.train_module, "train", fake_train)
    monkeypatch.setattr(b, "band_logistic", fake_baseline)
    out = tmp_path / "out"
    assert b.main(["--out", str(out), "--only", "small", "--seeds", "0,1,2", *sets]) == 0
    assert fitted == computed
    kept = [json.loads((out / "baseline" / f"small-seed{s}.json").read_text())
            for s in range(3)]
    assert [k["settings"]["seed"] for k in kept] == [0, 1, 2]
    assert [k["accuracy"] for k in kept] == [0.4 + (s if len(computed) == 3 else 0) / 100
                                             for s in range(3)]
    said = capsys.readouterr().out.count("the same split as seed 0: computed once")
    assert said == (0 if len(computed) == 3 else 2)


def test_biotac_channels_are_vibration_pressure_and_electrodes():
    """The bench's BioTac channels are the issue's plain channels, pressure + vibration +
    electrodes, in the importer's order: every channel of both fingers but the temperatures."""
    pytest.importorskip("h5py", reason="the [biotac] extra (h5py) is not installed")
    from tactile.device.recordings.biotac import channels

    b = _bench()
    every = [c.name for c in channels()]
    assert len(every) == 88 and len(b.BIOTAC_CHANNELS) == 84
    assert list(b.BIOTAC_CHANNELS) == [n for n in every if not n.endswith(("_tac", "_tdc"))]


def test_the_baselines_vote_per_take_is_the_models_rule(tmp_path, monkeypatch):
    """The baseline's majority vote per take, beside its window accuracy, is tactile-eval's
    per_take on the test windows and the baseline's probabilities (columns in class order:
    their argmax gives the window accuracy it reports); each take's vote is the most common
    window label there, counted here by hand."""
    pytest.importorskip("sklearn", reason="the [train] extra (scikit-learn) is not installed")
    from tactile.device.recordings import load_dataset
    from tactile.device.sim import make_dataset
    from tactile.training.config import TrainConfig

    b = _bench()
    make_dataset(tmp_path / "d", 6, ("paper", "non_contact", "mouse_pad"), 6.0, seed=0)
    takes = load_dataset(tmp_path / "d")
    seen = {}
    real = b.per_take

    def spy(w, probs, names):
        seen.update(w=w, probs=probs, names=names, out=real(w, probs, names))
        return seen["out"]

    monkeypatch.setattr(b, "per_take", spy)
    r = b.band_logistic(takes, TrainConfig(seed=1, threads=1))
    w, probs = seen["w"], seen["probs"]
    assert seen["names"] == [t.path.stem for t in takes]
    np.testing.assert_allclose(probs.sum(1), 1.0, atol=1e-9)
    assert r["accuracy"] == pytest.approx(float((probs.argmax(1) == w.y).mean()))
    right = []
    for t in np.unique(w.take):
        counts = np.bincount(probs[w.take == t].argmax(1), minlength=probs.shape[1])
        assert seen["out"]["per_take"][takes[t].path.stem]["vote"] == counts.argmax()
        right.append(counts.argmax() == w.y[w.take == t][0])
    assert r["take_accuracy"] == pytest.approx(np.mean(right)) and len(right) >= 3


def test_bad_arguments_are_one_line_before_any_dataset_is_made(tmp_path, monkeypatch, capsys):
    """--seeds that are not numbers, a bad --set or a candidate's bad setting: one line on
    stderr, exit 1, and no dataset prepared (a wrong setting must not wait for an import)."""
    b = _bench()
    monkeypatch.setattr(b, "prepare", lambda *a: pytest.fail("prepared a dataset"))
    for args, says in ((["--seeds", "x"], "--seeds 'x': not comma-separated whole numbers"),
                       (["--seeds", ","], "--seeds: give at least one seed"),
                       (["--set", "ensemble=0"], "ensemble must be 1..64"),
                       (["--candidate", "c", "hop=0"], "hop must be 1..1000000")):
        with pytest.raises(SystemExit) as e:
            b.main(["--out", str(tmp_path / "o"), "--only", "small", *args])
        err = capsys.readouterr().err
        assert e.value.code == 1 and err.count("\n") == 1 and says in err, err
        assert "Traceback" not in err


def test_signal_features_put_a_tone_in_its_band():
    """The baseline's high-rate bands: a 2.2 kHz signal given as 22 sub-sample channels of 50
    frames; a 300 Hz tone's energy lands in the third-octave band holding 300 Hz (bins of 2 Hz
    in a 1,100-sample window), at the energy of the Hann-tapered tone; the plain channel
    beside it is not read."""
    from tactile.training.frontend import band_bins

    b = _bench()
    r, t = 22, np.arange(50 * 22) / 2200.0
    s = 2.0 * np.sin(2 * np.pi * 300.0 * t) + 7.0
    x = np.concatenate([np.ones((1, 50, 1)), s.reshape(1, 50, r)], axis=2)  # plain, then signal
    f = b.signal_features(x, [list(range(1, 1 + r))], 100.0)
    bands = band_bins(551)
    assert f.shape == (1, len(bands))
    k = next(i for i, (lo, hi) in enumerate(bands) if lo <= 300.0 / 2 < hi)  # bin 150
    assert int(np.argmax(f[0])) == k
    w = np.hanning(len(s))
    # Parseval: the one-sided rfft energy of the tapered tone, (A / 2)^2 * N * sum(w^2)
    want = np.log(2 * (2.0 / 2) ** 2 * len(s) * np.sum(w**2) / 2)
    assert f[0, k] == pytest.approx(want, abs=0.02)
    assert np.all(np.delete(f[0], k) < want - 8)
    x2 = x.copy()
    x2[..., 0] = 5.0
    np.testing.assert_array_equal(b.signal_features(x2, [list(range(1, 1 + r))], 100.0), f)


def test_your_own_folder_gets_the_defaults_against_the_baselines(tmp_path, capsys):
    """The comparison ran on the four built-in datasets only: a user with their own takes had
    to write their own baseline. --data DIR runs it on that folder (--set's settings alone),
    its row named by the folder; a folder training refuses is one line, exit 1."""
    from tactile.device.sim import make_dataset

    b = _bench()
    data = tmp_path / "my takes"
    make_dataset(data, takes=5, textures=("non_contact", "paper"), seconds=4, seed=1)
    sets = ["--set", "epochs=1", "--set", "hidden=8", "--set", "layers=1", "--set",
            "refit=off", "--set", "blend=off"]
    assert b.main(["--out", str(tmp_path / "out"), "--data", str(data), "--seeds", "0",
                   *sets]) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| own-my_takes |"))
    cells = [c.strip() for c in row.split("|")[1:-1]]
    assert 0 <= float(cells[2]) <= 1 and 0 <= float(cells[4]) <= 1, row  # ours, the baseline
    assert len(list((tmp_path / "out").glob("takes-*/own-my_takes-seed0/metrics.json"))) == 1
    assert "| small |" not in out  # --data alone: the built-in datasets are not run
    make_dataset(data, takes=1, textures=("non_contact", "paper"), seconds=4, seed=2,
                 first_take=5)  # more takes: new runs, not the old figures
    assert b.main(["--out", str(tmp_path / "out"), "--data", str(data), "--seeds", "0",
                   *sets]) == 0
    assert len(list((tmp_path / "out").glob("takes-*/own-my_takes-seed0/metrics.json"))) == 2
    few = tmp_path / "few"
    make_dataset(few, takes=1, textures=("non_contact", "paper"), seconds=2, seed=1)
    assert b.main(["--out", str(tmp_path / "out2"), "--data", str(few), "--seeds", "0",
                   *sets]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("baselines.py: error: "), err
    with pytest.raises(SystemExit) as e:
        b.main(["--out", str(tmp_path / "out3"), "--data", str(tmp_path / "none")])
    assert e.value.code == 1 and "--data" in capsys.readouterr().err
