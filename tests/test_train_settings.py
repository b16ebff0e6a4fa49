"""Threads, device, config errors, log lines, per-take votes and plots of a training run."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch

from tactile.device.sim import make_dataset
from tactile.errors import ConfigError
from tactile.training.commands.eval import main as eval_main
from tactile.training.commands.train import main as train_main
from tactile.training.config import (
    MAX_AUTO_THREADS,
    TrainConfig,
    apply_threads,
    resolve_device,
    resolve_threads,
)
from tactile.training.data import Windows
from tactile.training.evaluate import per_take, shifted_line, summary, table
from tactile.training.log import Log
from tactile.training.overrides import parse_sets
from tactile.training.prepare import centered
from tactile.training.prepare import log_center as _log_center
from tactile.training.run_files import plots as _plots
from tactile.training.train import train

TINY = dict(epochs=2, hidden=6, layers=1, batch_size=64, patience=2, seed=2)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    make_dataset(out, takes=4, textures=("non_contact", "paper"), seconds=6, seed=1)
    return out


def test_automatic_threads_never_oversubscribe():
    assert resolve_threads(0, 1, cpus=2) == 1  # the 2-core machine: one thread
    assert resolve_threads(0, 1, cpus=1) == 1
    assert resolve_threads(0, 1, cpus=8) == MAX_AUTO_THREADS
    assert resolve_threads(0, 2, cpus=8) == 3  # two processes share 7 CPUs
    assert resolve_threads(0, 4, cpus=4) == 1
    assert resolve_threads(3, 1, cpus=2) == 3  # a number given is a number kept
    for procs in (1, 2, 3):
        for cpus in range(1, 17):
            assert 1 <= resolve_threads(0, procs, cpus) * procs <= max(procs, cpus - 1)
    assert TrainConfig().threads == 0
    with pytest.raises(ConfigError, match=r"threads must be 0..1024 \(0: automatic\)"):
        TrainConfig(threads=-1)


def test_apply_threads_sets_torch():
    old = torch.get_num_threads()
    try:
        assert apply_threads(1) == 1 and torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(old)


def test_eval_uses_the_runs_threads(dataset, tmp_path, capsys):
    run = tmp_path / "run"
    train(dataset, run, TrainConfig(**TINY, threads=1), progress=False)
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        assert eval_main([str(run), str(dataset), "--json"]) == 0
        assert torch.get_num_threads() == 1
        assert json.loads(capsys.readouterr().out)["threads"] == 1
        assert eval_main([str(run), str(dataset), "--json", "--threads", "2"]) == 0
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(old)


def test_more_threads_than_cpus_is_warned_once(dataset, tmp_path, capsys, monkeypatch):
    """A set thread count above the usable CPUs trains, with one warning line saying why it
    is slow; a count that fits says nothing."""
    import tactile.training.train as train_module

    monkeypatch.setattr(train_module, "usable_cpus", lambda: 1)
    old = torch.get_num_threads()
    try:
        train(dataset, tmp_path / "two", TrainConfig(**TINY, threads=2), progress=False)
        err = capsys.readouterr().err
        assert err.count("warning: 2 thread(s) x 1 process(es) here is more than the 1 usable "
                         "CPUs") == 1, err
        train(dataset, tmp_path / "one", TrainConfig(**TINY, threads=1), progress=False)
        assert "usable CPUs" not in capsys.readouterr().err
    finally:
        torch.set_num_threads(old)


def test_training_names_a_finished_take_that_lost_rows(dataset, tmp_path, capsys):
    import shutil

    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    take = sorted(data.glob("*.csv"))[0]
    lines = take.read_text().splitlines(keepends=True)
    take.write_text("".join(lines[:-100]))  # a copy cut at a line's end
    train(data, tmp_path / "run", TrainConfig(**TINY, threads=1), progress=False)
    err = capsys.readouterr().err
    assert f"warning: {take}: holds {len(lines) - 101} samples" in err, err
    assert err.count("rows were lost or added after recording") == 1, err


def test_device_resolution():
    assert resolve_device("auto", cuda_available=True) == "cuda"
    assert resolve_device("auto", cuda_available=False) == "cpu"
    assert resolve_device("cpu", cuda_available=True) == "cpu"
    assert resolve_device("cuda", cuda_available=True) == "cuda"
    with pytest.raises(ConfigError, match="device='cuda' but torch sees no GPU"):
        resolve_device("cuda", cuda_available=False)
    with pytest.raises(ConfigError, match="device must be one of auto, cpu, cuda"):
        TrainConfig(device="tpu")


def test_same_seed_on_cpu_gives_the_same_run(dataset, tmp_path):
    cfg = TrainConfig(**TINY, threads=1, device="cpu")
    a = train(dataset, tmp_path / "a", cfg, progress=False)
    b = train(dataset, tmp_path / "b", cfg, progress=False)
    wa = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=True)["state_dict"]
    wb = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=True)["state_dict"]
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    assert a["accuracy"] == b["accuracy"] and a["device"] == "cpu"


def test_config_errors_name_only_the_settings_involved():
    with pytest.raises(ConfigError) as e:
        parse_sets(["hop=-5"], TrainConfig())
    assert str(e.value) == "hop must be 1..1000000 samples (got hop=-5)"
    with pytest.raises(ConfigError) as e:
        parse_sets(["hop=3", "dropout=2"], TrainConfig())
    assert str(e.value) == "dropout must be in [0, 1) (got dropout=2.0)"


@pytest.mark.parametrize("bad", ["lr=inf", "lr=1e999", "lr=nan", "lr=0", "weight_decay=inf",
                                 "weight_decay=nan", "weight_decay=-1e-4", "lr=1e308",
                                 "weight_decay=3.5e38"])
def test_a_rate_or_decay_that_cannot_train_is_refused(bad):
    """An infinite or NaN learning rate trains on NaN losses to the end and exits 0, and one
    past float32's range stopped the first step with torch's overflow traceback; the setting
    is refused before any work, naming both settings of the check."""
    with pytest.raises(ConfigError, match="lr must be > 0 and weight_decay >= 0, each within "
                       r"float32's range \(3.4e38\)"):
        parse_sets([bad], TrainConfig())
    assert parse_sets(["lr=3e38", "weight_decay=3e38"], TrainConfig()).lr == 3e38  # in range


@pytest.mark.parametrize("bad", ["seed=-1", "seed=4294967296"])
def test_a_seed_out_of_numpys_range_is_refused_naming_it(bad):
    """numpy's own line ("Seed must be between 0 and 2**32 - 1") named no setting."""
    with pytest.raises(ConfigError, match=r"^seed must be in 0\.\.4294967295 \(numpy's range\) "
                       r"\(got seed=-?\d+\)$"):
        parse_sets([bad], TrainConfig())
    assert parse_sets(["seed=4294967295"], TrainConfig()).seed == 2**32 - 1


@pytest.mark.parametrize("bad, message", [
    ("hop=9223372036854775808", "config hop=9223372036854775808: must be a whole number within "
                                "+-2147483647"),
    ("hidden=99999999999999999999", "config hidden=99999999999999999999: must be a whole "
                                    "number within +-2147483647"),
    ("threads=99999999999999999999", "config threads=99999999999999999999: must be a whole "
                                     "number within +-2147483647"),
    ("layers=65", "layers must be 1..64 and hidden 1..1000000 (got layers=65, hidden=64)"),
    ("ensemble=65", "ensemble must be 1..64 (1: one model) (got ensemble=65)"),
    ("window=1000001", "window must be 4..1000000 samples (got window=1000001)"),
    ("hop=1000001", "hop must be 1..1000000 samples (got hop=1000001)"),
    ("frame_hop=1000001", "frame must be 2..window samples and frame_hop 1..1000000 (got "
                          "frame=20, frame_hop=1000001, window=50)"),
    ("threads=1025", "threads must be 0..1024 (0: automatic) (got threads=1025)"),
])
def test_a_whole_number_past_its_cap_is_refused_naming_it(bad, message):
    """hop=2**63 and hidden=10**20 were tracebacks from numpy and torch, window=10**20 numpy's
    'Maximum allowed size exceeded', and layers=10**20 or ensemble=10**20 built a model layer
    by layer until the memory was gone. Each is one line naming the setting."""
    with pytest.raises(ConfigError) as e:
        parse_sets([bad], TrainConfig())
    assert str(e.value) == message
    for fine in ("layers=64", "ensemble=64", "window=1000000", "threads=1024"):
        parse_sets([fine], TrainConfig())


def test_a_modality_size_past_its_cap_is_refused_naming_it():
    from tactile.training.config import Modality

    with pytest.raises(ConfigError, match=r"^modalities\.m\.atoms=100000000000000000000: must "
                       r"be an integer 1\.\.65536$"):
        Modality("m", ("accel_x",), atoms=10**20)


def test_settings_the_training_does_not_read_are_named():
    """emd_imfs without emd_channels, carry_steps without state='carry', frame or [signals]
    with front='none', test_fraction with a named test, an LSTM's sizes for a linear model: each
    trained exactly as without it, with no word."""
    from tactile.training.config import Modality, unused

    assert unused(TrainConfig()) == []
    assert unused(TrainConfig(emd_imfs=8, carry_steps=100)) == [
        "emd_imfs=8 (only with emd_channels)", "carry_steps=100 (only state='carry')"]
    assert unused(TrainConfig(front="none", frame=50, frame_hop=3)) == [
        "frame=50 (only front='spectral')", "frame_hop=3 (only front='spectral')"]
    assert unused(TrainConfig(test="user:2", test_fraction=0.9, val_fraction=0.5)) == [
        "test_fraction=0.9 (test='user:2' names the test takes)"]
    vib = (("vib", ("pac_*",)),)  # read as plain channels without the spectral front
    assert unused(TrainConfig(front="none", signals=vib)) == [
        "signals={'vib': ['pac_*']} (front='none' reads a signal's sub-samples as plain "
        "channels)"]
    assert unused(TrainConfig(signals=vib)) == []
    assert unused(TrainConfig(model="linear", emd_channels=("accel_x",), front="none",
                              signals=vib)) == [
        "front='none' (only model='lstm')"]
    linear = TrainConfig(model="linear", modalities=(Modality("imu", ("accel_*",)),), hidden=3,
                         wide=False, emd_sifts=5, emd_imfs=2)
    assert unused(linear) == [
        "wide=False (only model='lstm')", "hidden=3 (model='linear' has no LSTM)",
        "emd_imfs=2 (only with emd_channels; a modality sets its own imfs)"]
    assert unused(TrainConfig(emd_channels=("accel_x",), emd_imfs=2, state="carry", hop=50,
                              carry_steps=3)) == []


def test_tactile_train_says_both_warnings_naming_itself(dataset, tmp_path, capsys):
    """The unused settings and the users a named take leaves in training reach stderr, each
    in one line after the command's name (the library's own lines name the running command)."""
    sets = [f"--set={k}={v}" for k, v in TINY.items()]
    assert train_main([str(dataset), "--out", str(tmp_path / "r"), *sets, "--set",
                       "carry_steps=5", "--set", "test=name:paper-user000", "--set",
                       "val=user:1"]) == 0
    out, err = capsys.readouterr()
    # wall time and CPU, each named (the wall time alone read as CPU beside the docs' figures)
    assert re.search(r"^trained in [\d.]+ s of wall time, [\d.]+ s of CPU; run in ", out,
                     re.M), out
    err = err.splitlines()
    assert ("tactile-train: warning: settings this training does not read: carry_steps=5 "
            "(only state='carry')") in err, err
    assert ("tactile-train: warning: user 0 has takes in test and in training "
            "(test='name:paper-user000' names takes, not whole users): the test figures "
            "include users seen in training") in err, err


def test_a_channel_given_twice_is_refused():
    """channels=accel_x,accel_x trained a run whose export then failed on the file's names."""
    for key in ("channels", "emd_channels"):
        with pytest.raises(ConfigError, match=rf"^{key}: 'accel_x' given twice \(got {key}="
                           r"\['accel_x', 'gyro_x', 'accel_x'\]\)$"):
            parse_sets([f"{key}=accel_x,gyro_x,accel_x"], TrainConfig())


@pytest.mark.parametrize("bad", ["patience=0", "patience=-1"])
def test_a_patience_below_one_is_refused(bad):
    """patience=-1 stopped every run after its first epoch, silently."""
    with pytest.raises(ConfigError, match=r"epochs, batch_size and patience must be >= 1 "
                       r"\(got epochs=150, batch_size=128, patience=-?\d\)"):
        parse_sets([bad], TrainConfig())



def test_a_switch_is_set_by_on_off_true_false_1_0():
    for value, want in (("on", True), ("True", True), ("1", True),
                        ("off", False), ("false", False), ("0", False)):
        assert parse_sets([f"wide={value}"], TrainConfig()).wide is want
    with pytest.raises(ConfigError) as e:
        parse_sets(["wide=yes"], TrainConfig())
    assert str(e.value) == "--set wide='yes': not on/off, true/false or 1/0"

def test_a_log_file_gets_a_plain_line_per_epoch(dataset, tmp_path, capsys):
    sets = [f"--set={k}={v}" for k, v in TINY.items()]
    assert train_main([str(dataset), "--out", str(tmp_path / "r"), *sets]) == 0
    err = capsys.readouterr().err  # not a terminal
    assert "\r" not in err and "\x1b" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("fit epoch ")]
    assert [ln.split(":")[0] for ln in lines] == ["fit epoch 1/2", "fit epoch 2/2"]
    assert all("train loss" in ln and "val acc" in ln for ln in lines)
    assert re.search(r"^threads \d+ per process \(automatic; \d+ usable CPUs", err, re.M)


def test_center_patterns_say_what_they_matched(capsys):
    channels = ("pdc", "pac_0", "electrode_0")
    log = Log(progress=True)
    _log_center(log, channels, ("accel_*", "gyro_*"), centered(channels, ("accel_*", "gyro_*")))
    err = capsys.readouterr().err
    assert err.startswith("warning: center patterns accel_*, gyro_* match none of the channels "
                          "pdc, pac_0, electrode_0: no channel is centred")
    # the defaults (the pen's IMU) on another sensor: said, not a warning to set center=
    _log_center(log, channels, ("accel_*", "gyro_*"), [], default=True)
    assert capsys.readouterr().err == ("center: none (the defaults accel_*, gyro_*, the pen's "
                                       "IMU, match none of these channels)\n")
    many = tuple(f"ele_{i:02d}" for i in range(19))  # a long list is shortened to one line
    _log_center(log, many, ("accel_*",), [])
    assert capsys.readouterr().err.startswith("warning: center patterns accel_* match none of the "
                                              "channels ele_00, ele_01, ele_02, ele_03, ele_04, "
                                              "ele_05, ... (19 in all): no channel is centred")
    _log_center(Log(progress=False), channels, ("accel_*",), [])  # warnings even when quiet
    assert "warning" in capsys.readouterr().err
    _log_center(log, channels, ("pac_*", "e*"), centered(channels, ("pac_*", "e*")))
    assert capsys.readouterr().err == "center (pac_*, e*): pac_0, electrode_0\n"


def test_a_class_without_windows_has_no_recall_rather_than_zero():
    """A class with no test window got recall 0.0 and a row of zeros in the confusion table,
    where the warning said its figures were left out."""
    y = np.array([0, 0, 1, 1])
    probs = np.array([[0.9, 0.05, 0.05], [0.2, 0.7, 0.1], [0.1, 0.8, 0.1], [0.6, 0.3, 0.1]])
    s = summary(y, probs, ("a", "b", "c"))
    assert s["recall"] == {"a": 0.5, "b": 0.5, "c": None}
    rows = table(s, ("a", "b", "c")).splitlines()
    assert rows[2].split() == ["a", "0.500", "0.500", "0.000"]
    assert rows[4].split() == ["c", "-", "-", "-"]


def test_majority_vote_per_take():
    # take 0: labels 0, windows voted 0, 0, 1 -> 0 (right); take 1: label 1, voted 0, 0, 1 -> 0
    # (wrong); take 2: label 1, voted 0, 1 (a tie) -> the larger summed probability, 1 (right)
    probs = np.array([[.9, .1], [.8, .2], [.3, .7], [.6, .4], [.7, .3], [.2, .8], [.55, .45],
                      [.1, .9]], np.float32)
    y = np.array([0, 0, 0, 1, 1, 1, 1, 1])
    take = np.array([0, 0, 0, 1, 1, 1, 2, 2])
    w = Windows(np.zeros((8, 4, 1), np.float32), y, take, np.arange(8), take)
    r = per_take(w, probs, ["a", "b", "c"])
    assert r["takes"] == 3 and r["take_accuracy"] == pytest.approx(2 / 3)
    assert r["per_take"]["a"] == {"label": 0, "vote": 0, "windows": 3,
                                  "share": pytest.approx(2 / 3)}
    assert r["per_take"]["b"]["vote"] == 0 and r["per_take"]["c"]["vote"] == 1
    line = shifted_line({"-0.2s": 0.5, "+0.2s": 0.75, "mean": 0.625})
    assert line == "shifted windows (robustness): -0.2s 0.500, +0.2s 0.750, mean 0.625"


def test_windows_that_cannot_shift_one_way_are_left_out_of_the_shifted_check(dataset, tmp_path,
                                                                           capsys):
    """With one window a segment (hop past the take's length) each window starts at its
    segment's first sample, so no earlier-shifted window fits: the run trained to its end and
    then failed with "no window of 50 samples fits", leaving nothing. The later shifts are
    measured and the earlier ones left out."""
    sets = [f"--set={k}={v}" for k, v in TINY.items()]
    out = tmp_path / "r"
    assert train_main([str(dataset), "--out", str(out), *sets, "--set", "hop=100000"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert set(m["shifted"]) == {"+0.1s", "+0.2s", "mean"}
    later = (m["shifted"]["+0.1s"], m["shifted"]["+0.2s"])
    assert m["shifted"]["mean"] == pytest.approx(sum(later) / 2)
    assert "shifted windows (robustness): +0.1s " in capsys.readouterr().out
    assert shifted_line({}) == "shifted windows (robustness): not measured"


def test_shifts_the_hop_divides_are_not_a_robustness_figure(dataset, tmp_path, capsys):
    """At the defaults' hop (10 samples at 100 Hz) every shift of the check (0.1, 0.2 s) is
    whole hops: the shifted windows were the test windows one or two hops on, and the line
    printed the test accuracy four times as robustness. Those shifts are left out, and the
    line says why when none is left; a hop of 20 keeps the 0.1 s shifts."""
    sets = [f"--set={k}={v}" for k, v in TINY.items()]
    assert train_main([str(dataset), "--out", str(tmp_path / "r"), *sets]) == 0
    m = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert m["shifted"] == {"not_measured": "the hop (10 samples, 0.1 s) divides every shift, "
                                            "so the shifted windows are the test windows again"}
    assert ("shifted windows (robustness): not measured: the hop (10 samples, 0.1 s) divides "
            "every shift") in capsys.readouterr().out
    assert train_main([str(dataset), "--out", str(tmp_path / "r20"), *sets, "--set",
                       "hop=20"]) == 0
    m = json.loads((tmp_path / "r20" / "metrics.json").read_text())
    assert set(m["shifted"]) == {"-0.1s", "+0.1s", "mean"}


def _in_units(src, dst, unit: str, only: str | None = None) -> None:
    """A copy of dataset ``src`` whose accelerometer channels are in ``unit`` (scale x 9.81:
    the same values in m/s^2), in every take or only in the take named ``only``."""
    import shutil

    shutil.copytree(src, dst)
    for js in sorted(dst.glob("*.json")):
        if only is not None and js.stem != only:
            continue
        meta = json.loads(js.read_text())
        for ch in meta["device"]["channels"]:
            if ch["name"].startswith("accel_"):
                ch["unit"], ch["scale"] = unit, ch["scale"] * 9.81
        js.write_text(json.dumps(meta))


def test_figures_on_data_the_model_would_misread_are_refused(dataset, tmp_path, capsys):
    """Data at another rate or in other units gave tactile-eval, tactile-export --data and
    tactile-check --data figures (exit 0) for windows tactile-run refuses (exit 3): each now
    names the difference in one line, exit 1."""
    from tactile.export.commands.check import main as check_main
    from tactile.export.commands.export import main as export_main

    sets = [f"--set={k}={v}" for k, v in TINY.items()]
    run, onnx = tmp_path / "r", tmp_path / "m.onnx"
    assert train_main([str(dataset), "--out", str(run), *sets]) == 0
    assert export_main([str(run), "--out", str(onnx)]) == 0
    slow = tmp_path / "slow"
    make_dataset(slow, takes=2, textures=("non_contact", "paper"), seconds=6, seed=1,
                 rate_hz=50.0)
    _in_units(dataset, tmp_path / "si", "m/s^2")
    more = tmp_path / "more"  # check and export measured the known classes' takes alone
    make_dataset(more, takes=2, textures=("non_contact", "paper", "desk"), seconds=6, seed=1)
    capsys.readouterr()
    for data, says in ((slow, f"{slow}: recorded at 50 Hz, the model reads 100 Hz"),
                       (more, f"{more}: labels ['desk'] are not among the model's "
                              "['non_contact', 'paper']"),
                       (tmp_path / "si", "accel_x is in 'm/s^2', the model reads it in 'g' "
                                         "(and 2 more channels)")):
        for cmd, args in ((eval_main, [str(run), str(data)]),
                          (export_main, [str(run), "--out", str(tmp_path / "x.onnx"),
                                         "--data", str(data)]),
                          (check_main, [str(onnx), "--data", str(data)]),
                          (check_main, [str(onnx), "--run", str(run), "--data", str(data)])):
            assert cmd(args) == 1, (cmd, data)
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and err[0].endswith(says), err
    assert not (tmp_path / "x.onnx").exists()
    assert eval_main([str(run), str(dataset)]) == 0  # the data it was trained on
    # a CSV device's takes declare no units: taken in the model's, as tactile-run takes them
    # (eval and check refused them, naming '' against 'N', where a replay labelled them)
    import shutil

    for name, device in (("csv", "csv"), ("blank", "pen")):
        shutil.copytree(dataset, tmp_path / name)
        for js in (tmp_path / name).glob("*.json"):
            meta = json.loads(js.read_text())
            for ch in meta["device"]["channels"]:
                ch["unit"] = ""
            meta["device"]["device"] = device
            js.write_text(json.dumps(meta))
    capsys.readouterr()
    assert eval_main([str(run), str(tmp_path / "csv")]) == 0
    assert check_main([str(onnx), "--data", str(tmp_path / "csv")]) == 0
    assert eval_main([str(run), str(tmp_path / "blank")]) == 1  # a device that says '' means it
    assert "pressure_0 is in '', the model reads it in 'N'" in capsys.readouterr().err


def test_a_dataset_in_two_units_is_refused(dataset, tmp_path):
    """Takes of one channel in g and in m/s^2 were read as one unit (training mixed them)."""
    from tactile.device.recordings import load_dataset
    from tactile.errors import RecordingError

    _in_units(dataset, tmp_path / "mixed", "m/s^2", only="paper-user001")
    with pytest.raises(RecordingError, match=r"paper-user001.csv: accel_x is in 'm/s\^2', in "
                       r".*-user000.csv in 'g'$"):
        load_dataset(tmp_path / "mixed")


def test_takes_of_one_name_in_two_sub_folders_are_refused(dataset, tmp_path, capsys):
    """Runs name their test takes by file name: two sub-folders holding takes of the same
    names trained with one of each pair lost from the split's names and the per-take vote,
    and the run's own dataset was not recognised by tactile-eval."""
    import shutil

    from tactile.device.recordings import load_dataset
    from tactile.errors import RecordingError

    shutil.copytree(dataset, tmp_path / "d" / "a")
    shutil.copytree(dataset, tmp_path / "d" / "b")
    with pytest.raises(RecordingError, match=r"two takes named non_contact-user000\.csv \(.*"
                       r"a/non_contact-user000\.csv and .*b/non_contact-user000\.csv\): "
                       r"rename one"):
        load_dataset(tmp_path / "d")
    assert train_main([str(tmp_path / "d"), "--out", str(tmp_path / "r")]) == 1
    assert "two takes named" in capsys.readouterr().err


def test_a_class_without_training_windows_is_refused_and_one_without_validation_named(
        tmp_path, capsys):
    """A class recorded only by test or validation users trained on the others, exit 0,
    and scored recall 0 on test without a word."""
    sets = [f"--set={k}={v}" for k, v in TINY.items()] + ["--set", "test=user:0",
                                                           "--set", "val=user:1"]
    only_held_out, no_val = tmp_path / "a", tmp_path / "b"
    for folder in (only_held_out, no_val):
        make_dataset(folder, takes=4, textures=("non_contact",), seconds=4, seed=1)
    make_dataset(only_held_out, takes=2, textures=("paper",), seconds=4, seed=1)  # users 0, 1
    make_dataset(no_val, takes=1, textures=("paper",), seconds=4, seed=1)  # user 0
    make_dataset(no_val, takes=2, textures=("paper",), seconds=4, seed=1, first_take=2)
    assert train_main([str(only_held_out), "--out", str(tmp_path / "r1"), *sets]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == ("tactile-train: error: class(es) ['paper'] have no training window in "
                       "this split: each class needs takes (users) in training; record more, "
                       "or name the test/validation takes (test=..., val=...)"), err
    assert not (tmp_path / "r1").exists()
    assert train_main([str(no_val), "--out", str(tmp_path / "r2"), *sets]) == 0
    err = capsys.readouterr().err
    assert ("warning: class(es) ['paper'] have no validation window in this split: its "
            "figures leave them out") in err


def test_a_user_split_over_takes_of_which_some_name_no_user_is_refused(dataset, tmp_path,
                                                                        capsys):
    """One take without a 'user' made split=user split by take: a test user's other takes
    trained the model, exit 0. Takes of which none names a user are each their own user."""
    import shutil

    for name, drop in (("some", ["paper-user001"]), ("none", None)):
        folder = tmp_path / name
        shutil.copytree(dataset, folder)
        for js in folder.glob("*.json"):
            if drop is None or js.stem in drop:
                meta = json.loads(js.read_text())
                del meta["user"]
                js.write_text(json.dumps(meta))
    sets = [f"--set={k}={v}" for k, v in TINY.items()]
    assert train_main([str(tmp_path / "some"), "--out", str(tmp_path / "r1"), *sets]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == ("tactile-train: error: split='user': 1 of 8 takes have no 'user' field "
                       "(e.g. paper-user001.csv): give every take one, or use split='take'"), err
    assert train_main([str(tmp_path / "none"), "--out", str(tmp_path / "r2"), *sets]) == 0
    assert "split user: test takes " in capsys.readouterr().err  # each take its own user


def test_a_reader_that_goes_away_does_not_stop_training_or_export(dataset, tmp_path):
    """`tactile-train ... 2>&1 | head -1` ended the training at its next line, exit 0, with
    nothing saved; so did an export piped to head."""
    import subprocess
    import sys

    sets = [f"--set={k}={v}" for k, v in TINY.items()]
    run, onnx = tmp_path / "r", tmp_path / "m.onnx"
    for module, args, made in (
            ("tactile.training.commands.train", [str(dataset), "--out", str(run), *sets],
             run / "checkpoint.pt"),
            ("tactile.export.commands.export", [str(run), "-o", str(onnx)], onnx)):
        proc = subprocess.Popen([sys.executable, "-m", module, *args], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT)
        proc.stdout.readline()  # the first line, then the reader goes away
        proc.stdout.close()
        assert proc.wait(timeout=600) == 0, module
        assert made.is_file(), module


def test_a_model_larger_than_memory_is_one_line(dataset, tmp_path, capsys):
    """hidden=1000000 asks torch for 15 TB: its allocation error was a 40-line traceback."""
    sets = [f"--set={k}={v}" for k, v in TINY.items()]
    assert train_main([str(dataset), "--out", str(tmp_path / "r"), *sets,
                       "--set", "hidden=1000000"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and not (tmp_path / "r").exists()
    assert re.fullmatch(r"tactile-train: error: out of memory \(an allocation of [\d.]+ GiB\): "
                        r"smaller settings \(hidden, batch_size, window\) or a smaller dataset",
                        err.strip().splitlines()[-1]), err


def test_numpy_out_of_memory_and_other_runtime_errors():
    """numpy's MemoryError is the same one line; a RuntimeError that is no allocation stays a
    traceback (a defect to report, not a user's setting)."""
    from tactile.cli import run

    def huge(_):
        return np.empty(10**15)

    def broken(_):
        raise RuntimeError("some defect")

    args = type("A", (), {"debug": False})()
    assert run("x", huge, args) == 1
    with pytest.raises(RuntimeError, match="some defect"):
        run("x", broken, args)


def test_plots_mark_the_best_epoch_and_show_counts(monkeypatch):
    from matplotlib.axes import Axes

    lines, texts = [], []
    real_line, real_text = Axes.axvline, Axes.text
    monkeypatch.setattr(Axes, "axvline", lambda self, x, *a, **k: (
        lines.append(x), real_line(self, x, *a, **k))[1])
    monkeypatch.setattr(Axes, "text", lambda self, x, y, s, *a, **k: (
        texts.append(s), real_text(self, x, y, s, *a, **k))[1])
    history = {"train_loss": [1.0, 0.8, 0.7], "val_loss": [1.1, 0.9, 1.0],
               "val_acc": [0.5, 0.7, 0.6], "best_epoch": 1}
    metrics = {"accuracy": 0.75, "confusion": [[3, 1], [0, 4]],
               "confusion_normalised": [[0.75, 0.25], [0.0, 1.0]]}
    pictures = _plots(history, metrics, ("a", "b"))
    assert lines == [2, 2]  # epoch 2 (1-based) on both panels
    assert texts == ["0.75\n(3)", "0.25\n(1)", "0.00\n(0)", "1.00\n(4)"]
    assert sorted(pictures) == ["confusion.png", "curves.png"]
    assert all(p.startswith(b"\x89PNG") and len(p) > 1000 for p in pictures.values())

    points = []  # with the blended regression: its validation accuracy at the kept epoch
    real_plot = Axes.plot
    monkeypatch.setattr(Axes, "plot", lambda self, *a, **k: (
        points.append((a, k.get("label"))), real_plot(self, *a, **k))[1])
    blend = {"c": 10.0, "mix": 0.5, "val_acc": 0.82}
    _plots({**history, "blend": blend}, metrics, ("a", "b"))
    assert [(xy, label) for xy, label in points if label and "regression" in label] == [
        (([2], [0.82]), "with the regression (mix 0.5)")]
    assert [label for _, label in points][:3] == ["train", "validation",
                                                  "the recurrent model alone"]
    points.clear()
    _plots({**history, "blend": {**blend, "mix": 0.0}}, metrics, ("a", "b"))  # the LSTM alone
    assert [label for _, label in points] == ["train", "validation", None]


def test_eval_help_reads_as_a_sentence(capsys):
    with pytest.raises(SystemExit) as e:
        eval_main(["--help"])
    assert e.value.code == 0
    description = capsys.readouterr().out.split("\n\n")[1].replace("\n", " ")
    assert description.startswith("Evaluate a trained run on a dataset") and \
        description.endswith(".")


def _kept(select: str, curves: list[tuple[float, float]], patience: int = 3) -> int:
    """The epoch (0-based) ``_validate``'s rule keeps over (accuracy, loss) per epoch."""
    from tactile.training.loop import improves as _improves

    s, best, stale = {"best": float("inf"), "best_acc": -1.0}, 0, 0
    for e, (acc, loss) in enumerate(curves):
        if _improves(select, acc, loss, s["best"], s["best_acc"]):
            s["best"], s["best_acc"], best, stale = loss, acc, e, 0
        else:
            stale += 1
            if stale >= patience:
                break
    return best


def test_selection_by_loss_or_by_accuracy_with_the_loss_as_tie_break():
    # the loss bottoms at epoch 1 while the accuracy climbs until epoch 4
    curves = [(0.50, 1.0), (0.60, 0.8), (0.65, 0.9), (0.70, 1.1), (0.75, 1.3), (0.74, 1.4),
              (0.75, 1.2), (0.70, 1.5), (0.60, 1.6)]
    assert _kept("loss", curves) == 1
    # epoch 6 ties epoch 4's accuracy with a lower loss; lower by less than 1e-4 is no tie-break
    assert _kept("accuracy", curves, patience=5) == 6
    assert _kept("accuracy", curves[:6] + [(0.75, 1.3 - 5e-5)], patience=5) == 4
    # patience counts epochs without a better one: one (epoch 5) ends the run before epoch 6
    assert _kept("accuracy", curves, patience=1) == 4
    with pytest.raises(ConfigError, match="select must be one of loss, accuracy"):
        TrainConfig(select="f1")


@pytest.mark.parametrize("select", ["accuracy", "loss"])
def test_the_training_loop_keeps_the_epoch_its_rule_names(dataset, tmp_path, monkeypatch, select):
    """A real run (not a replay of the rule): the kept epoch has the best validation figure
    of every epoch run (accuracy: the best accuracy, and the lowest loss, within 1e-4, among
    the epochs that reach it; loss: the lowest loss within 1e-4), and the run stopped either
    at ``epochs`` or ``patience`` epochs after it."""
    from tactile.training import train as train_mod

    seen = {}
    real = train_mod.write_run

    def spy(out, cfg, model, metrics, history, *a, **k):
        seen["history"], seen["metrics"] = history, metrics
        return real(out, cfg, model, metrics, history, *a, **k)

    monkeypatch.setattr(train_mod, "write_run", spy)
    cfg = TrainConfig(**{**TINY, "epochs": 12, "patience": 2, "epoch_windows": 128,
                         "select": select, "threads": 1})
    train(dataset, tmp_path / "r", cfg, progress=False)
    h, m = seen["history"], seen["metrics"]
    acc, loss, best = h["val_acc"], h["val_loss"], h["best_epoch"]
    assert m["best_epoch"] == best and m["epochs_run"] == len(acc) == len(loss)
    # the run's validation figure is the blended model's, at least the LSTM's alone (a mix of
    # 0 is among the choices); the LSTM's own is its best epoch's
    assert m["val_accuracy"] >= acc[best]
    assert m["blend"]["recurrent_val_acc"] == pytest.approx(acc[best], abs=1e-9)
    if select == "accuracy":
        assert acc[best] >= max(acc) - 1e-9
        assert loss[best] <= min(v for a, v in zip(acc, loss) if a >= acc[best] - 1e-9) + 1e-4
    else:
        assert loss[best] <= min(loss) + 1e-4  # improvements of 1e-4 or less do not count
    assert len(acc) in (cfg.epochs, best + 1 + cfg.patience), (len(acc), best)


def test_augment_offset_moves_only_the_uncentred_channels():
    from tactile.training.loop import augment_offset as _augment_offset
    from tactile.training.model import TextureModel

    def model(offset, center):
        cfg = TrainConfig(augment_offset=offset, emd_channels=("c",))
        return TextureModel(cfg, 2, torch.zeros(3), torch.ones(3), [2], center)

    m = model(0.5, [0])  # channel 0 centred, 1 and 2 not, then the EMD features of channel 2
    n_f = m.pre.n_features
    scale = m.offset_scale()
    assert n_f > 3 and scale.tolist() == [0.0, 0.5, 0.5] + [0.0] * (n_f - 3)
    assert model(0.0, [0]).offset_scale() is None  # off
    assert model(0.5, [0, 1, 2]).offset_scale() is None  # every channel centred

    f = torch.randn(400, 2, 7, n_f)
    d = _augment_offset(f, scale, torch.Generator().manual_seed(0)) - f
    assert torch.allclose(d, d[:, :, :1].expand_as(d), atol=1e-6)  # one offset per window
    assert torch.equal(d[..., scale == 0], torch.zeros_like(d[..., scale == 0]))
    moved = d[:, :, 0, 1:3].flatten()
    assert moved.abs().max() <= 0.5
    # uniform in +/- 0.5: mean 0, standard deviation 0.5 / sqrt(3) = 0.289 (1,600 draws)
    assert abs(moved.mean().item()) < 0.03 and abs(moved.std().item() - 0.289) < 0.02


def test_augment_offset_in_training_and_its_bounds(dataset, tmp_path):
    def weights(name, **kw):
        train(dataset, tmp_path / name, TrainConfig(**TINY, threads=1, **kw), progress=False)
        return torch.load(tmp_path / name / "checkpoint.pt", weights_only=True)["state_dict"]

    plain = weights("plain")
    moved = weights("moved", augment_offset=1.0)
    assert any(not torch.equal(plain[k], moved[k]) for k in plain)
    # with every channel centred no offset reaches the model: the run is the run without
    a = weights("a", center=("*",))
    b = weights("b", center=("*",), augment_offset=1.0)
    assert all(torch.equal(a[k], b[k]) for k in a)
    for bad in ("-0.1", "11"):
        with pytest.raises(ConfigError, match=rf"augment_offset must be in \[0, 10\].*"
                                              rf"augment_offset={bad}"):
            parse_sets([f"augment_offset={bad}"], TrainConfig())


def test_data_that_does_not_fit_is_the_only_line(dataset, tmp_path, capsys):
    """The run's threads line comes once the data is known to fit: a bad input prints its
    one-line error and nothing before it (exit 1)."""
    one = tmp_path / "one"
    make_dataset(one, takes=2, textures=("paper",), seconds=2, seed=1)
    for args in ([str(tmp_path / "nope")], [str(one)],
                 [str(dataset), "--set", "emd_channels=accel_q"],
                 [str(dataset), "--set", "channels=accel_x,acel_z"]):
        assert train_main([*args, "--out", str(tmp_path / "r")]) == 1, args
        err = capsys.readouterr().err
        assert err.startswith("tactile-train: error: ") and err.count("\n") == 1, (args, err)


def test_an_ensembles_train_loss_is_its_members_mean(dataset, tmp_path, capsys):
    """The printed (and plotted) train loss of ensemble=2 is the members' mean, on the scale
    of one model's (their sum trains them: each member gets its own loss's gradient). Two
    models from other initial weights differ a little; the sum would be twice the size."""
    losses = {}
    for n in (1, 2):
        sets = [f"--set={k}={v}" for k, v in {**TINY, "ensemble": n}.items()]
        assert train_main([str(dataset), "--out", str(tmp_path / f"r{n}"), *sets]) == 0
        first = next(ln for ln in capsys.readouterr().err.splitlines()
                     if ln.startswith("fit epoch 1/"))
        losses[n] = float(re.search(r"train loss ([0-9.]+)", first).group(1))
    assert 0.75 < losses[2] / losses[1] < 1.33, losses


def test_the_feature_pass_names_sparse_codes_only_for_a_model_that_has_them(capsys):
    """An F-RNN (EMD, no dictionaries) logged 'EMD and sparse codes in float64 by ...'."""
    from types import SimpleNamespace

    from tactile.training.prepare import features

    model = SimpleNamespace(pre=SimpleNamespace(emds=[object()], needs_dictionaries=False))
    assert features(model, {}, 0, Log(progress=True), None) == {}
    assert capsys.readouterr().err.startswith("EMD in float64 by ")
