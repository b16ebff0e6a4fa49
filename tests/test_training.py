"""Training: config validation, leak-free splits, windows, normalisation, checkpoints, learning."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from tactile.device.protocol import pen_info
from tactile.device.recordings import TakeWriter, load_dataset, read_take
from tactile.device.sim import make_dataset
from tactile.errors import ConfigError, RecordingError
from tactile.training.checkpoint import load_checkpoint
from tactile.training.commands.eval import main as eval_main
from tactile.training.commands.train import main as train_main
from tactile.training.config import TrainConfig
from tactile.training.data import channel_stats, classes_of, concat, cut, split_takes
from tactile.training.evaluate import predict
from tactile.training.overrides import parse_sets
from tactile.training.train import train

EASY = ("non_contact", "paper", "nonwoven_cloth")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    make_dataset(out, takes=6, textures=EASY, seconds=12, seed=1)
    return out


@pytest.fixture(scope="module")
def trained(dataset, tmp_path_factory):
    run = tmp_path_factory.mktemp("run")
    cfg = TrainConfig(epochs=12, hidden=32, layers=1, batch_size=64, lr=1e-2, patience=12,
                      seed=3, threads=1)
    metrics = train(dataset, run, cfg, progress=False)
    return run, metrics


def test_config_rejects_unknown_keys_and_bad_values(tmp_path):
    with pytest.raises(ConfigError, match=r"unknown config key\(s\) \['hiden'\]"):
        TrainConfig.from_dict({"hiden": 3})
    with pytest.raises(ConfigError, match="hidden='64': must be int"):
        TrainConfig.from_dict({"hidden": "64"})
    with pytest.raises(ConfigError, match="dropout must be in"):
        TrainConfig(dropout=1.5)
    with pytest.raises(ConfigError, match=r"ensemble must be 1..64 \(1: one model\) \(got "
                       r"ensemble=0\)"):
        TrainConfig(ensemble=0)
    with pytest.raises(ConfigError, match=r"ensemble=2 needs model='lstm' \(got model='linear'"):
        TrainConfig(ensemble=2, model="linear", emd_channels=("accel_z",))
    with pytest.raises(ConfigError, match="hop == window"):
        TrainConfig(state="carry", hop=25)
    with pytest.raises(ConfigError, match="emd_channels"):
        TrainConfig(model="linear")
    with pytest.raises(ConfigError, match="schedule must be one of constant, plateau, cosine"):
        TrainConfig(schedule="step")
    with pytest.raises(ConfigError, match=r"label_smoothing must be in \[0, 1\)"):
        TrainConfig(label_smoothing=1.0)
    with pytest.raises(ConfigError, match=r"ema must be in \[0, 1\)"):
        TrainConfig(ema=-0.1)
    with pytest.raises(ConfigError, match="refit must be one of auto, on, off"):
        TrainConfig(refit="yes")
    assert TrainConfig().refit == "on" and TrainConfig(split="user").refits  # the default
    assert TrainConfig(split="time", refit="auto").refits
    assert not TrainConfig(split="user", refit="auto").refits
    assert TrainConfig(refit="on").refits and not TrainConfig(split="time", refit="off").refits
    toml = tmp_path / "c.toml"
    toml.write_text('hidden = 16\nemd_channels = ["accel_z"]\n')
    cfg = TrainConfig.from_toml(toml)
    assert cfg.hidden == 16 and cfg.emd_channels == ("accel_z",)
    for text, says in ((b"\xff\xfehidden = 16\n", "not UTF-8 text (a TOML file is)"),
                       (b"hiden = 16\n", "unknown config key(s) ['hiden']"),
                       (b"hidden = \n", "Invalid value (at line 1, column 10)")):
        (tmp_path / "bad.toml").write_bytes(text)
        with pytest.raises(ConfigError) as e:
            TrainConfig.from_toml(tmp_path / "bad.toml")
        assert str(e.value).startswith(f"{tmp_path / 'bad.toml'}: {says}"), e.value
    assert parse_sets(["layers=3", "emd_channels=a,b"], cfg).emd_channels == ("a", "b")
    assert parse_sets(["refit=on", "label_smoothing=0.1"], cfg).refits
    with pytest.raises(ConfigError, match="unknown setting"):
        parse_sets(["nope=1"], cfg)
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg


def test_splits_never_share_a_user_or_take(dataset):
    takes = load_dataset(dataset)
    for split in ("user", "take"):
        s = split_takes(takes, TrainConfig(split=split, seed=5))
        sets = [set(s.train), set(s.val), set(s.test)]
        assert not (sets[0] & sets[1] or sets[0] & sets[2] or sets[1] & sets[2])
        assert set().union(*sets) == set(range(len(takes)))
        if split == "user":
            users = [{takes[i].meta["user"] for i in part} for part in sets]
            assert not (users[0] & users[1] or users[0] & users[2] or users[1] & users[2])
    s = split_takes(takes, TrainConfig(split="time", test_fraction=0.3))
    for i in range(len(takes)):
        (a0, a1), (b0, b1), (c0, c1) = s.train[i], s.val[i], s.test[i]
        assert a0 == 0 and a1 == b0 and b1 == c0 and c1 == len(takes[i].seq)
    w_train = cut(takes, classes_of(takes), (), 50, 25, s.train)
    w_test = cut(takes, classes_of(takes), (), 50, 25, s.test)
    for i in range(len(takes)):  # time split: no test window overlaps a training window
        tr = w_train.start[w_train.take == i]
        te = w_test.start[w_test.take == i]
        assert tr.max() + 50 <= te.min()


def test_windows_never_span_a_gap(tmp_path):
    info = pen_info()
    raw = np.arange(300 * 8, dtype=np.int16).reshape(300, 8)
    with TakeWriter(tmp_path, "paper", info, name="g") as w:
        w.write(0, 0, raw[:120])
        w.write(130, 1_300_000, raw[130:300])  # 10 samples lost
    take = read_take(tmp_path / "g.csv")
    assert take.segments() == [(0, 120), (120, 290)]
    win = cut([take], ("paper",), (), 50, 10, None)
    for s in win.start:
        seqs = take.seq[s : s + 50]
        assert np.all(np.diff(seqs) == 1)
    # rows 0..119 give starts 0, 10, ..., 70; rows 120..289 give starts 120, 130, ..., 240
    assert win.start.tolist() == list(range(0, 71, 10)) + list(range(120, 241, 10))
    # the shifted ("novel") windows stay inside their run too
    shifted = cut([take], ("paper",), (), 50, 10, None, shift=7)
    assert all(np.all(np.diff(take.seq[s : s + 50]) == 1) for s in shifted.start)


def test_normalisation_comes_from_training_windows_only(trained, dataset):
    run, metrics = trained
    model, ck = load_checkpoint(run)
    takes = load_dataset(dataset)
    names = [t.path.name for t in takes]
    test = {names.index(n) for n in ck["test_rows"]}
    cfg = model.cfg
    every = cut(takes, tuple(ck["classes"]), tuple(ck["channels"]), cfg.window, cfg.hop, None)
    s = split_takes(takes, cfg)  # the split is deterministic given the config
    mean, std = channel_stats(cut(takes, tuple(ck["classes"]), tuple(ck["channels"]),
                                  cfg.window, cfg.hop, s.train))
    np.testing.assert_allclose(ck["mean"], mean, rtol=1e-6)
    np.testing.assert_allclose(ck["std"], std, rtol=1e-6)
    all_mean, _ = channel_stats(every)
    assert not np.allclose(all_mean, mean, rtol=1e-3)
    assert not set(s.train) & test


def test_training_learns_above_chance(trained):
    _, metrics = trained
    # 3 classes: chance is 1/3; test users were never seen in training
    assert metrics["accuracy"] >= 0.6, metrics["accuracy"]
    assert metrics["recall"]["non_contact"] >= 0.9  # no pressure at all: the easy class
    assert set(metrics["shifted"]) == {"not_measured"}  # hop 10: every shift is whole hops


def test_a_run_says_which_libraries_it_ran_on(trained):
    # the figures of the same code, data and seed move with scikit-learn's or numpy's version:
    # metrics.json records them, as the libraries themselves report their versions
    import platform

    import onnxruntime
    import sklearn

    import tactile

    run, metrics = trained
    on_disk = json.loads((run / "metrics.json").read_text())["libraries"]
    assert on_disk == metrics["libraries"]
    assert on_disk["python"] == platform.python_version()
    assert on_disk["tactile"] == tactile.__version__
    assert on_disk["torch"] == torch.__version__
    assert on_disk["numpy"] == np.__version__
    assert on_disk["scikit-learn"] == sklearn.__version__
    assert on_disk["onnxruntime"] == onnxruntime.__version__


def test_checkpoint_round_trip_rebuilds_the_same_model(trained, dataset):
    run, metrics = trained
    ck = torch.load(run / "checkpoint.pt", weights_only=True)  # data, not code
    assert ck["classes"] == sorted(EASY)
    model, _ = load_checkpoint(run)
    takes = load_dataset(dataset)
    names = [t.path.name for t in takes]
    rows = {names.index(n): tuple(r) for n, r in ck["test_rows"].items()}
    w = cut(takes, tuple(ck["classes"]), tuple(ck["channels"]), model.cfg.window,
            model.cfg.hop, rows)
    probs = predict(model, w)
    acc = float((probs.argmax(1) == w.y).mean())
    assert acc == pytest.approx(metrics["accuracy"], abs=1e-9)
    for f in ("metrics.json", "confusion.txt", "curves.png", "confusion.png"):
        assert (run / f).stat().st_size > 100
    assert "label of input data" in (run / "confusion.txt").read_text()


def test_eval_cli_json(trained, dataset, capsys):
    run, metrics = trained
    assert eval_main([str(run), str(dataset), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["scope"].startswith("the run's test split") and "matched by content" in out["scope"]
    assert out["accuracy"] == pytest.approx(metrics["accuracy"])
    assert out["shifted"] == metrics["shifted"] == {"not_measured": (
        "the hop (10 samples, 0.1 s) divides every shift, so the shifted windows are the test "
        "windows again")}
    # the majority vote per take, beside the window accuracy: one entry per test take
    ck = torch.load(run / "checkpoint.pt", weights_only=True)
    assert {n + ".csv" for n in out["per_take"]} == set(ck["test_rows"])
    assert out["takes"] == len(ck["test_rows"])
    right = sum(v["vote"] == v["label"] for v in out["per_take"].values())
    assert out["take_accuracy"] == pytest.approx(right / out["takes"])
    assert eval_main([str(run), str(dataset)]) == 0
    text = capsys.readouterr().out
    assert f"per take (majority vote): {out['take_accuracy']:.3f} over {out['takes']} takes" \
        in text
    assert "shifted windows (robustness): not measured: the hop " in text


def test_carry_emd_and_linear_variants_train(dataset, tmp_path):
    base = dict(epochs=2, hidden=8, layers=1, threads=1, patience=2)
    m = train(dataset, tmp_path / "carry",
              TrainConfig(**base, state="carry", hop=50, carry_steps=4), progress=False)
    assert m["split_windows"]["test"] > 0 and 0 <= m["accuracy"] <= 1
    m = train(dataset, tmp_path / "emd",
              TrainConfig(**base, emd_channels=("pressure_0",), emd_imfs=2, emd_sifts=4),
              progress=False)
    model, _ = load_checkpoint(tmp_path / "emd")
    assert model.pre.n_features == 8 + 2
    m = train(dataset, tmp_path / "lin",
              TrainConfig(**base, model="linear", emd_channels=("accel_z",), emd_imfs=3),
              progress=False)
    assert 0 <= m["accuracy"] <= 1


def test_cli_errors(dataset, tmp_path, capsys):
    assert train_main([str(dataset), "--out", str(tmp_path), "--set", "hidden=x"]) == 1
    assert "hidden='x'" in capsys.readouterr().err
    assert train_main([str(tmp_path / "none"), "--out", str(tmp_path)]) == 1
    assert "not a folder" in capsys.readouterr().err
    assert eval_main([str(tmp_path), str(dataset)]) == 1
    assert "no checkpoint" in capsys.readouterr().err
    with pytest.raises(RecordingError, match="only one label"):
        one = tmp_path / "one"
        make_dataset(one, 3, ("paper",), seconds=2)
        train(one, tmp_path / "r", TrainConfig(epochs=1), progress=False)
    with pytest.raises(ConfigError, match="not among the input channels"):
        train(dataset, tmp_path / "r", TrainConfig(channels=("accel_x",),
                                                   emd_channels=("accel_z",)), progress=False)


def test_center_removes_the_window_mean_of_matching_channels_only():
    from tactile.training.model import Preprocess
    from tactile.training.prepare import centered

    names = ("pressure_0", "accel_x", "gyro_z", "ch0")
    assert centered(names, ("accel_*", "gyro_*")) == [1, 2]
    assert centered(names, ()) == []
    pre = Preprocess(torch.zeros(4), torch.full((4,), 2.0), [], 4, 10, center_index=[1, 2])
    x = torch.randn(3, 50, 4) + 5.0
    z = pre(x)
    torch.testing.assert_close(z[:, :, [0, 3]], x[:, :, [0, 3]] / 2)
    torch.testing.assert_close(z[:, :, 1:3].mean(1), torch.zeros(3, 2), atol=1e-6, rtol=0)
    torch.testing.assert_close(z[:, :, 1:3], (x[:, :, 1:3] - x[:, :, 1:3].mean(1, True)) / 2)


def test_concat_keeps_runs_apart(dataset):
    takes = load_dataset(dataset)
    s = split_takes(takes, TrainConfig(split="time"))
    a = cut(takes, classes_of(takes), (), 50, 25, s.train)
    b = cut(takes, classes_of(takes), (), 50, 25, s.val)
    both = concat(a, b)
    assert len(both) == len(a) + len(b)
    np.testing.assert_array_equal(both.x[len(a):], b.x)
    assert not set(both.run[: len(a)]) & set(both.run[len(a):])
    assert len(np.unique(both.run)) == len(np.unique(a.run)) + len(np.unique(b.run))


def test_refit_trains_on_train_and_validation_for_the_best_epoch_count(dataset, tmp_path,
                                                                        monkeypatch):
    """With a time split and refit='auto', a second training on train + validation windows."""
    import tactile.training.loop as tr

    seen = []
    real = tr.train_head

    def spy(model, w, f_all, n_epochs, ctx, val=None, resume=None):
        seen.append((len(w), n_epochs, val is None))
        return real(model, w, f_all, n_epochs, ctx, val, resume)

    monkeypatch.setattr(tr, "train_head", spy)
    cfg = TrainConfig(epochs=3, hidden=8, layers=1, threads=1, split="time",
                      label_smoothing=0.1, schedule="cosine", ema=0.9, refit="auto")
    m = train(dataset, tmp_path / "refit", cfg, progress=False)
    (n_train, epochs, no_val), (n_both, refit_epochs, refit_no_val) = seen
    assert epochs == 3 and not no_val
    assert n_both == n_train + m["split_windows"]["val"] and refit_no_val
    assert refit_epochs == m["best_epoch"] + 1 == m["refit_epochs"]
    model, ck = load_checkpoint(tmp_path / "refit")
    assert ck["config"]["refit"] == "auto" and 0 <= m["accuracy"] <= 1
    seen.clear()  # refit off: one training, the best validation epoch's weights
    m = train(dataset, tmp_path / "plain", cfg.replace(refit="off", schedule="plateau"),
              progress=False)
    assert [n for _, n, _ in seen] == [3] and m["refit_epochs"] == 0
    seen.clear()  # a plateau schedule refits at a constant rate (no validation loss to watch)
    m = train(dataset, tmp_path / "plateau", cfg.replace(refit="on", split="user",
                                                         schedule="plateau"), progress=False)
    assert len(seen) == 2 and m["refit_epochs"] == m["best_epoch"] + 1


def test_refit_failed_judges_the_refit_by_the_first_trainings_progress():
    from tactile.training.loop import refit_failed

    fit = [1.605, 1.578, 1.50, 1.45, 1.30, 1.27]  # best epoch 5 (0-based): 1.27
    assert refit_failed(fit, 5, [1.60, 1.50, 1.40, 1.35, 1.30, 1.28]) is None
    assert refit_failed(fit, 5, [1.60, 1.50, 1.43]) is None  # below halfway, 1.4375
    assert refit_failed(fit, 5, [1.60, 1.50, 1.45]) is not None
    why = refit_failed(fit, 5, [1.607, 1.600, 1.588, 1.606])  # the units died: class priors
    assert why is not None and "1.6060" in why and "1.4375" in why
    assert refit_failed(fit, 5, [1.6, float("nan")]) is not None
    assert refit_failed(fit, 0, [1.7]) is None  # best at the first epoch: nothing to judge by
    assert refit_failed([1.5, 1.6], 1, [1.9]) is None  # the first training did not progress
    assert refit_failed(fit, 5, []) is None
    # converged in its first epoch (an L-BFGS fit: 1.5102825 -> 1.5102752): a refit's loss over
    # training + validation windows, 1.522, says nothing about it
    assert refit_failed([1.5102825, 1.5102752], 1, [1.5220, 1.5220]) is None
    assert refit_failed([1.60, 1.53], 1, [1.59]) is None  # 4.4 % progress: not judged
    assert refit_failed([1.60, 1.50], 1, [1.59]) is not None  # 6.3 %: judged


def test_a_refit_that_learned_nothing_is_not_kept(dataset, tmp_path, monkeypatch, capsys):
    """A refit whose training loss stays near where training starts (here: made so by zeroing
    its weights) ships the first training's validated best weights, says so, and records it;
    with them the regression blended with the first model (solved on the training windows),
    not the one the refit solved again."""
    import tactile.training.loop as tr

    real, first, refitted = tr.train_head, {}, {}
    real_refit = tr.blend.refit

    def spy_refit(model, *args):
        real_refit(model, *args)
        refitted.update({k: v.clone() for k, v in model.head.regression.state_dict().items()})

    def sabotage(model, w, f_all, n_epochs, ctx, val=None, resume=None):
        history = real(model, w, f_all, n_epochs, ctx, val, resume)
        if val is not None:
            first.update({k: v.clone() for k, v in model.head.state_dict().items()})
            assert len(history["train_loss"]) == 4  # no early stop
            return {**history, "train_loss": [1.6, 1.2, 1.0, 0.9], "best_epoch": 3}
        with torch.no_grad():
            for p in model.head.parameters():
                p.zero_()
        return {**history, "train_loss": [1.6] * n_epochs}

    monkeypatch.setattr(tr, "train_head", sabotage)
    monkeypatch.setattr(tr.blend, "refit", spy_refit)
    cfg = TrainConfig(epochs=4, hidden=8, layers=1, threads=1, patience=10, refit="on")
    m = train(dataset, tmp_path / "run", cfg, progress=False)
    assert m["refit_kept"] is False and m["refit_epochs"] == 4
    assert "refit not kept" in capsys.readouterr().err
    model, _ = load_checkpoint(tmp_path / "run")
    for k, v in model.head.state_dict().items():
        if k.startswith("recurrent."):  # the LSTM: its first training's best epoch
            torch.testing.assert_close(v, first[k], rtol=0, atol=0)
    assert float(model.head.mix) == m["blend"]["mix"]
    coef = model.head.regression.coef
    assert coef.abs().max() > 0 and not torch.equal(coef, refitted["coef"])


def test_eval_recognises_the_test_split_by_content_not_by_name(trained, dataset, tmp_path,
                                                                capsys):
    run, _ = trained
    ck = torch.load(run / "checkpoint.pt", weights_only=True)
    assert set(ck["test_fingerprints"]) == set(ck["test_rows"])
    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    victim = copy / sorted(ck["test_rows"])[0]
    lines = victim.read_text().splitlines(keepends=True)
    row = lines[1].rstrip("\n").split(",")
    row[2] = str(int(row[2]) + 1)  # one count of one sample: another recording, same name
    lines[1] = ",".join(row) + "\n"
    victim.write_text("".join(lines))
    assert eval_main([str(run), str(copy), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["scope"].startswith("every take") and victim.name in out["scope"]


def test_metrics_name_every_take_of_each_part(trained, dataset):
    """metrics.json's `split` is the log's line, cut to a few names ("... (18 in all)"): a
    baseline on the same split had to guess the training takes. `split_takes` names them all,
    with their rows."""
    run, _ = trained
    ck = torch.load(run / "checkpoint.pt", weights_only=True)
    parts = json.loads((run / "metrics.json").read_text())["split_takes"]
    assert sorted([*parts["train"], *parts["val"], *parts["test"]]) == sorted(
        p.name for p in dataset.glob("*.csv"))
    assert parts["test"] == {n: list(r) for n, r in ck["test_rows"].items()}
    takes = {t.path.name: t for t in load_dataset(dataset)}
    assert all(r == [0, len(takes[n].seq)] for part in parts.values() for n, r in part.items())


def _seen_and_test(ck: dict, dataset: Path, folder: Path) -> Path:
    """A folder of two takes the run trained or validated on and one of its test takes."""
    folder.mkdir()
    seen = sorted(n.name for n in dataset.glob("*.csv") if n.name not in ck["test_rows"])
    for n in [*seen[:2], sorted(ck["test_rows"])[0]]:
        for suffix in (".csv", ".json"):
            shutil.copy(dataset / Path(n).with_suffix(suffix), folder)
    return folder


def test_export_and_check_on_takes_the_run_trained_on_say_so(trained, dataset, tmp_path,
                                                             capsys):
    """tactile-export --data and tactile-check --data measured on every take of a folder
    without a word when some were the run's training or validation takes (tactile-eval
    warned); their source now says how many, and the file carries the fingerprints for
    tactile-check, which has no run folder."""
    from tactile.export.commands.check import main as check_main
    from tactile.export.exporter import export_run
    from tactile.export.windows import from_dataset

    run, _ = trained
    ck = torch.load(run / "checkpoint.pt", weights_only=True)
    folder = _seen_and_test(ck, dataset, tmp_path / "mine")
    seen = sorted(n.name for n in folder.glob("*.csv") if n.name not in ck["test_rows"])
    note = (f"; 2 of them the run trained or validated on (by content, e.g. {seen[0]}): these "
            "figures are not a test")
    assert from_dataset(ck, folder).source == f"every take of mine (3 takes){note}"
    assert not from_dataset(ck, dataset).source.endswith("not a test")  # its test split
    model = tmp_path / "m.onnx"
    report = export_run(run, model, data=folder, log=lambda s: None)
    assert report["parity"]["source"].startswith(f"every take of mine (3 takes){note}")
    capsys.readouterr()
    assert check_main([str(model), "--data", str(folder)]) == 0
    out = capsys.readouterr().out
    assert f"measured on      every take of mine (3 takes){note}: " in out, out
    assert check_main([str(model), "--data", str(dataset)]) == 0
    assert "not a test" not in capsys.readouterr().out


def test_eval_on_takes_the_run_trained_on_says_the_figures_are_not_a_test(trained, dataset,
                                                                          tmp_path, capsys):
    """tactile-eval on a folder without the run's test takes evaluates every take it holds, and
    said nothing when those were the run's training or validation takes (accuracy 0.99, per
    take 1.000, read as a test). The run keeps the fingerprints of the takes it read."""
    run, _ = trained
    ck = torch.load(run / "checkpoint.pt", weights_only=True)
    takes = {t.path.name: t for t in load_dataset(dataset)}
    seen = [n for n in takes if n not in ck["test_rows"]]
    assert sorted(ck["seen_fingerprints"]) == sorted({takes[n].fingerprint() for n in seen})
    folder = _seen_and_test(ck, dataset, tmp_path / "mine")
    assert eval_main([str(run), str(folder), "--json"]) == 0
    said = capsys.readouterr()
    out = json.loads(said.out)
    assert out["scope"].startswith("every take") and sorted(out["seen_takes"]) == sorted(seen[:2])
    assert "these figures are not a test" in out["scope"]
    assert said.err == (f"tactile-eval: warning: 2 of the takes evaluated are ones the run "
                        f"trained or validated on (e.g. {out['seen_takes'][0]}): the figures "
                        "are not a test\n")
    assert eval_main([str(run), str(dataset), "--json"]) == 0  # its own test split: no word
    said = capsys.readouterr()
    assert json.loads(said.out)["seen_takes"] == [] and said.err == ""
    old = tmp_path / "old"  # a run saved before the checkpoint kept them: not known, null
    shutil.copytree(run, old)
    del ck["seen_fingerprints"]
    torch.save(ck, old / "checkpoint.pt")
    assert eval_main([str(old), str(folder), "--json"]) == 0
    said = capsys.readouterr()
    assert json.loads(said.out)["seen_takes"] is None and said.err == ""


def test_a_class_named_uncertain_is_refused_before_training(tmp_path, capsys):
    """``uncertain`` is the label stream's name for "no stable label": a dataset with a class so
    named is one line and exit 1, before any training."""
    data = tmp_path / "data"
    make_dataset(data, 2, ("paper", "desk"), seconds=2, seed=1)
    for meta in data.glob("desk-*.json"):
        d = json.loads(meta.read_text())
        d["label"] = "uncertain"
        meta.write_text(json.dumps(d))
    assert train_main([str(data), "--out", str(tmp_path / "run")]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "'uncertain'" in err and "reserve" in err
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


def test_eval_keeps_the_raw_stream_where_export_would(trained, dataset, capsys, monkeypatch):
    """When no setting meets the limits and the one with the fewest false changes labels fewer
    validation windows right than the raw stream, tactile-export leaves the file raw;
    tactile-eval reported the setting anyway."""
    import dataclasses

    import tactile.training.label_stream as ls_mod

    real = ls_mod.calibrate

    def worse(streams, **limits):  # made to miss the limits and to label fewer right than raw
        cal = real(streams, **limits)
        figures = {**cal.figures, "met_limit": False, "smoothed": {
            **cal.figures["smoothed"], "accuracy": cal.figures["raw"]["accuracy"] - 0.1}}
        return dataclasses.replace(cal, figures=figures)

    monkeypatch.setattr(ls_mod, "calibrate", worse)
    monkeypatch.setattr(ls_mod, "shortfall", lambda streams: "")  # this set's 0.6 min will do
    run, _ = trained
    assert eval_main([str(run), str(dataset), "--json"]) == 0
    ls = json.loads(capsys.readouterr().out)["label_stream"]
    assert ls["source"].startswith("calibrated on the run's validation takes"), ls["source"]
    assert ls["setting"] == "ma:1 p_min=0 hold=1", ls["setting"]
    assert "gives fewer correct stable labels than the raw stream" in ls["source"]
    assert ls["smoothed"]["accuracy"] == pytest.approx(ls["raw"]["accuracy"])


def test_eval_label_stream_figures(trained, dataset, capsys):
    """tactile-eval's label stream: each user's test rows joined into one stream of samples and
    windowed as a pen does it (windows across the takes' boundaries, a window's truth its last
    sample's class); its windows counted and cut here by hand, and the figures are the metrics
    functions' on those windows' predictions (a stated setting here)."""
    from tactile.device.recordings import load_dataset
    from tactile.postprocess.metrics import WindowStream, compare
    from tactile.postprocess.smoothing import SmoothingSettings
    from tactile.postprocess.streams import make_streams
    from tactile.training.data import Windows, find_test_split
    from tactile.training.label_stream import pieces

    run, _ = trained
    assert eval_main([str(run), str(dataset), "--json", "--smooth", "3", "--p-min", "0.5",
                      "--hold", "2"]) == 0
    out = json.loads(capsys.readouterr().out)
    ls = out["label_stream"]
    assert ls["setting"] == "ma:3 p_min=0.5 hold=2" and ls["source"] == "given"
    assert ls["raw"]["uncertain"] == 0 and ls["smoothed"]["windows"] == ls["raw"]["windows"]
    model, ck = load_checkpoint(run)
    takes = load_dataset(dataset)
    rows, _, _ = find_test_split(takes, ck["test_rows"], ck["test_fingerprints"], dataset.name)
    classes, channels = tuple(ck["classes"]), tuple(ck["channels"])
    win, hop = model.cfg.window, model.cfg.hop
    per_user: dict[str, int] = {}
    for i, (a, b) in rows.items():
        user = str(takes[i].meta.get("user", "-"))
        per_user[user] = per_user.get(user, 0) + b - a
    assert ls["streams"] == len(per_user)
    assert ls["raw"]["windows"] == sum((n - win) // hop + 1 for n in per_user.values())
    right, streams = 0, []
    for s in make_streams(pieces(takes, rows, classes, channels, 100.0), classes, 100.0):
        starts = np.arange(0, len(s.truth) - win + 1, hop)
        x = np.stack([s.values[a:a + win] for a in starts])
        y = s.truth[starts + win - 1]
        zeros = np.zeros(len(starts), np.int64)
        probs = predict(model, Windows(x, y, zeros, starts, zeros))
        right += int((probs.argmax(1) == y).sum())
        streams.append(WindowStream((starts + win - 1) / 100.0, y, probs, classes))
    assert ls["raw"]["accuracy"] == pytest.approx(right / ls["raw"]["windows"])
    want = compare(streams, SmoothingSettings(n=3, p_min=0.5, hold=2))
    for part in ("raw", "smoothed"):
        for k, v in want[part].items():
            assert ls[part][k] == pytest.approx(v, rel=1e-6, abs=1e-9), (part, k)
    # without a setting: calibrated on the validation takes, or said why not; text side by side
    assert eval_main([str(run), str(dataset)]) == 0
    text = capsys.readouterr().out
    assert "label stream: " in text and "post-processed with " in text
    assert "false changes per minute" in text and "raw" in text


def test_an_out_that_cannot_be_a_folder_is_refused_before_training(dataset, tmp_path, capsys,
                                                                   monkeypatch):
    """--out naming a file, or a path through one, is one line and exit 1 before any work (it
    used to fail after the whole training, losing the run)."""
    import tactile.training.train as training

    monkeypatch.setattr(training, "train", lambda *a, **k: pytest.fail("trained"))
    afile = tmp_path / "afile"
    afile.write_text("keep me\n")
    for out, says in ((afile, "a file, not a folder"),
                      (afile / "sub", f"{afile} is a file, not a folder")):
        assert train_main([str(dataset), "--out", str(out)]) == 1
        err = capsys.readouterr().err
        assert says in err and len(err.strip().splitlines()) == 1, err
    assert afile.read_text() == "keep me\n"
    # the dataset folder itself (a run's files among the takes), however it is spelled
    for spelled in (str(dataset), f"{dataset}/", f"{dataset}/../{dataset.name}"):
        assert train_main([str(dataset), "--out", spelled, "--force"]) == 1
        err = capsys.readouterr().err
        assert "the dataset folder itself" in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc")
def test_an_out_that_cannot_be_made_is_refused_before_training(dataset, tmp_path, capsys,
                                                               monkeypatch):
    """/proc lets root "write" by os.access but makes no folder: the run trained to its end,
    then failed, losing the model. The folders are tried before training; the run folder is
    then made and held while training runs, and a run that writes nothing leaves no empty
    folder behind."""
    import tactile.training.train as training

    seen = []
    monkeypatch.setattr(training, "train", lambda *a, **k: pytest.fail("trained"))
    assert train_main([str(dataset), "--out", "/proc/tactile-run/r"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["tactile-train: error: --out /proc/tactile-run/r: cannot be written "
                   "(No such file or directory)"], err
    monkeypatch.setattr(training, "train", lambda *a, **k: (
        seen.append((tmp_path / "a" / "b" / "r").is_dir()), {"interrupted": True})[1])
    assert train_main([str(dataset), "--out", str(tmp_path / "a" / "b" / "r")]) == 130
    assert seen == [True]  # held while training
    assert list(tmp_path.iterdir()) == []  # nothing written: every folder made is gone
