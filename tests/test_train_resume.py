"""Ctrl-C during training and ``--resume``: stop cleanly, save, continue to the same end.

The interruption is deterministic: a hook after epoch k raises SIGINT in the process itself
(the handler notes it; the loop stops at the next batch), or the stop check answers yes at a
chosen batch. No timer anywhere.
"""

from __future__ import annotations

import contextlib
import fcntl
import io
import json
import os
import signal
import subprocess
import sys

import pytest
import torch

from tactile.cli import EXIT_INTERRUPTED, EXIT_TERMINATED, Terminated
from tactile.device.sim import make_dataset
from tactile.training.checkpoint import RESUME, load_checkpoint, load_resume
from tactile.training.commands.train import main as train_main
from tactile.training.config import TrainConfig
from tactile.training.log import Stop
from tactile.training.train import train

SMALL = dict(epochs=5, hidden=12, layers=2, batch_size=64, lr=1e-2, patience=5, seed=4,
             threads=1)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    make_dataset(out, takes=5, textures=("non_contact", "paper", "nonwoven_cloth"), seconds=8,
                 seed=2)
    return out


def sigint_after(phase: str, epoch: int):
    def hook(p: str, e: int) -> None:
        if (p, e) == (phase, epoch):
            signal.raise_signal(signal.SIGINT)
    return hook


def weights(run) -> dict:
    return torch.load(run / "checkpoint.pt", weights_only=True)["state_dict"]


def assert_same_run(a_run, b_run, a: dict, b: dict) -> None:
    """Same final weights (tolerance 1e-6: on one CPU thread they are in fact bit-identical)
    and the same figures."""
    wa, wb = weights(a_run), weights(b_run)
    assert wa.keys() == wb.keys()
    for k in wa:
        torch.testing.assert_close(wa[k], wb[k], rtol=0, atol=1e-6)
    for k in ("accuracy", "take_accuracy", "best_epoch", "val_accuracy", "epochs_run",
              "refit_epochs"):
        assert a[k] == pytest.approx(b[k], abs=1e-9), k


def resume_run(run):
    r = load_resume(run)
    return train(r["data"], run, TrainConfig.from_dict(r["config"]), progress=False,
                 resume=r["state"])


def test_sigint_after_an_epoch_then_resume_ends_where_an_uninterrupted_run_does(dataset,
                                                                                tmp_path,
                                                                                capsys):
    cfg = TrainConfig(**SMALL)
    full = train(dataset, tmp_path / "full", cfg, progress=False)
    cut = train(dataset, tmp_path / "cut", cfg, progress=False, on_epoch=sigint_after("fit", 2))
    assert cut["interrupted"] and cut["epochs_run"] == 2 and cut["shifted"] is None
    saved = json.loads((tmp_path / "cut" / "metrics.json").read_text())
    assert saved["interrupted"] is True and saved["epochs_run"] == 2
    # the best checkpoint so far is an ordinary, loadable checkpoint (data only)
    ck = torch.load(tmp_path / "cut" / "checkpoint.pt", weights_only=True)
    assert ck["metrics"]["interrupted"] is True
    load_checkpoint(tmp_path / "cut")
    state = torch.load(tmp_path / "cut" / RESUME, weights_only=True)["state"]
    assert state["phase"] == "fit" and state["epoch"] == 2
    # exporting it works, and says the run is not finished (the export said nothing)
    from tactile.export.commands.export import main as export_main

    capsys.readouterr()
    assert export_main([str(tmp_path / "cut"), "-o", str(tmp_path / "cut.onnx")]) == 0
    assert (f"tactile-export: warning: {tmp_path / 'cut'}: its training was interrupted "
            f"(resume.pt is there): the file gets the best model so far; tactile-train --resume "
            f"{tmp_path / 'cut'} finishes it") in capsys.readouterr().err
    assert set(state["rng"]) >= {"torch", "numpy", "python", "order", "gain"}
    resumed = resume_run(tmp_path / "cut")
    assert not resumed["interrupted"] and not (tmp_path / "cut" / RESUME).exists()
    assert_same_run(tmp_path / "full", tmp_path / "cut", full, resumed)


def test_a_stop_in_mid_epoch_rolls_back_to_the_last_finished_epoch(dataset, tmp_path,
                                                                   monkeypatch):
    """Stopped at the 3rd batch of a refit epoch (split=time refits), with the options that
    carry state of their own (plateau schedule, EMA, label smoothing): same end."""
    cfg = TrainConfig(**SMALL, split="time", schedule="plateau", ema=0.9, label_smoothing=0.1)
    full = train(dataset, tmp_path / "full", cfg, progress=False)
    assert full["refit_epochs"] >= 2
    calls, at = [0], []

    def requested(self) -> bool:  # yes at the 3rd batch after the first refit epoch
        calls[0] += 1
        return bool(at) and calls[0] == at[0] + 3

    def hook(phase: str, epoch: int) -> None:
        if (phase, epoch) == ("refit", 1):
            at.append(calls[0])

    monkeypatch.setattr(Stop, "requested", requested)
    cut = train(dataset, tmp_path / "cut", cfg, progress=False, on_epoch=hook)
    monkeypatch.undo()
    assert cut["interrupted"] and cut["phase"] == "refit"
    assert load_resume(tmp_path / "cut")["state"]["epoch"] == 1  # the refit's first epoch
    resumed = resume_run(tmp_path / "cut")
    assert_same_run(tmp_path / "full", tmp_path / "cut", full, resumed)


def test_ctrl_c_while_the_blend_is_chosen_then_resume_ends_where_an_uninterrupted_run_does(
        dataset, tmp_path, monkeypatch):
    """SIGINT during the blended regression's fits (after an early stop, the first training
    over): the run stops there, saved as its last fit epoch; the resume trains no epoch more
    (the phase had stopped), chooses again and refits: the same run as one never stopped."""
    import tactile.training.blend as blend

    cfg = TrainConfig(**{**SMALL, "epochs": 30, "patience": 2})
    full = train(dataset, tmp_path / "full", cfg, progress=False)
    assert full["epochs_run"] < 30  # it stopped early
    real, calls = blend.choose, []

    def interrupted(model, parts, feats, dist, check):
        calls.append(1)
        checks = []

        def stop_at_the_second_check():  # between the first fit and the second
            checks.append(1)
            if len(calls) < 3 and len(checks) == 2:
                signal.raise_signal(signal.SIGINT)
            check()
        return real(model, parts, feats, dist, stop_at_the_second_check)

    monkeypatch.setattr(blend, "choose", interrupted)
    cut = train(dataset, tmp_path / "cut", cfg, progress=False)
    assert cut["interrupted"] and cut["epochs_run"] == full["epochs_run"]
    model, _ = load_checkpoint(tmp_path / "cut")  # the LSTM's best epoch, no regression yet
    assert float(model.head.mix) == 0 and not model.head.regression.coef.any()
    saved = (tmp_path / "cut" / RESUME).read_bytes()
    again = resume_run(tmp_path / "cut")  # stopped again in the choice: the same state saved
    assert again["interrupted"] and again["epochs_run"] == full["epochs_run"]
    assert torch.load(tmp_path / "cut" / RESUME, weights_only=True)["state"]["epoch"] == \
        torch.load(io.BytesIO(saved), weights_only=True)["state"]["epoch"]
    resumed = resume_run(tmp_path / "cut")
    assert len(calls) == 3 and resumed["epochs_run"] == full["epochs_run"]
    for k in ("c", "mix", "val_acc", "regression_val_acc", "recurrent_val_acc"):
        assert resumed["blend"][k] == pytest.approx(full["blend"][k], abs=1e-9), k
    assert_same_run(tmp_path / "full", tmp_path / "cut", full, resumed)


@pytest.mark.parametrize("sig, exit_code", [("SIGINT", EXIT_INTERRUPTED),
                                             ("SIGTERM", EXIT_TERMINATED)])
def test_ctrl_c_or_sigterm_in_the_command_saves_without_a_traceback_and_resume_finishes(
        dataset, tmp_path, capsys, sig, exit_code):
    """SIGTERM (timeout, kill, systemd, a batch scheduler) killed the training at once, with
    nothing saved; it now stops and saves as Ctrl-C does, and exits 143."""
    run = tmp_path / "run"
    sets = [f"--set={k}={v}" for k, v in {**SMALL, "epochs": 3}.items()]
    code = ("import functools, signal, sys\n"
            "import tactile.training.train as t\n"
            "from tactile.training.commands.train import main\n"
            "def hook(phase, epoch):\n"
            f"    if epoch == 1: signal.raise_signal(signal.{sig})\n"
            "t.train = functools.partial(t.train, on_epoch=hook)\n"
            "sys.exit(main(sys.argv[1:]))\n")
    proc = subprocess.run([sys.executable, "-c", code, str(dataset), "--out", str(run), *sets],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == exit_code, proc.stderr
    assert "Traceback" not in proc.stderr and "KeyboardInterrupt" not in proc.stderr
    assert f"interrupted ({sig}): fit epoch 1 was the last finished" in proc.stderr
    assert f"--resume {run}" in proc.stderr
    assert json.loads((run / "metrics.json").read_text())["interrupted"] is True
    with _holding(run):  # as a training that writes it now does: --resume waits for it
        assert train_main(["--resume", str(run), "--quiet"]) == 1
        assert capsys.readouterr().err == (f"tactile-train: error: --resume {run}: another "
                                           "tactile-train is writing into it now: wait for it "
                                           "to end\n")
    # the dataset moved: --resume says to give it
    moved = tmp_path / "moved"
    dataset.rename(moved)
    try:
        assert train_main(["--resume", str(run), "--quiet"]) == 1
        assert capsys.readouterr().err == (
            f"tactile-train: error: {dataset}: the run's dataset is not there (moved?): give "
            f"it, tactile-train DATA --resume {run}\n")
    finally:
        moved.rename(dataset)
    # the folder holds a run: a new training refuses it, --resume continues it
    assert train_main([str(dataset), "--out", str(run), "--quiet"]) == 1
    assert f"holds a run already (checkpoint.pt): choose another --out or add --force to " \
        f"overwrite it, or --resume {run} to continue it" in capsys.readouterr().err
    assert train_main(["--resume", str(run), "--set", "hidden=3"]) == 1
    assert "own settings" in capsys.readouterr().err
    assert train_main(["--resume", str(run), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "per take (majority vote)" in out and "shifted windows (robustness): not measured" in out
    m = json.loads((run / "metrics.json").read_text())
    assert m["interrupted"] is False and m["epochs_run"] == 3
    assert train_main(["--resume", str(run)]) == 1
    assert "nothing to resume" in capsys.readouterr().err


@pytest.mark.parametrize("stop, exit_code, says", [
    (KeyboardInterrupt, EXIT_INTERRUPTED, "interrupted"),
    (Terminated, EXIT_TERMINATED, "terminated (SIGTERM)")])
def test_sigint_or_sigterm_before_the_first_epoch_saves_nothing(
        dataset, tmp_path, monkeypatch, capsys, stop, exit_code, says):
    import tactile.training.train as t

    def interrupted(*a, **k):
        raise stop  # as SIGINT (SIGTERM) does while the takes load or EMD runs

    monkeypatch.setattr(t, "load_dataset", interrupted)
    assert train_main([str(dataset), "--out", str(tmp_path / "a" / "b" / "r")]) == exit_code
    assert capsys.readouterr().err == f"tactile-train: {says} before training started: " \
        "nothing saved\n"
    assert list(tmp_path.iterdir()) == []  # no folder made for the run is left


def test_train_called_from_a_script_leaves_sigterm_to_the_script(dataset, tmp_path):
    """Only the command takes SIGTERM as Ctrl-C: a script that calls train() and kept
    Python's default is ended by it, and does not go on as if the run had finished."""
    code = ("import signal, sys\n"
            "from pathlib import Path\n"
            "from tactile.training.config import TrainConfig\n"
            "from tactile.training.train import train\n"
            "def hook(phase, epoch):\n"
            "    if epoch == 1: signal.raise_signal(signal.SIGTERM)\n"
            f"cfg = TrainConfig(**{ {**SMALL, 'epochs': 3}!r})\n"
            "train(Path(sys.argv[1]), Path(sys.argv[2]), cfg, progress=False, on_epoch=hook)\n"
            "print('carried on')\n")
    proc = subprocess.run([sys.executable, "-c", code, str(dataset), str(tmp_path / "run")],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == -signal.SIGTERM, (proc.returncode, proc.stderr)
    assert "carried on" not in proc.stdout and not (tmp_path / "run" / RESUME).exists()


def test_force_overwrites_a_run(dataset, tmp_path, capsys):
    run = tmp_path / "run"
    sets = [f"--set={k}={v}" for k, v in {**SMALL, "epochs": 1}.items()]
    assert train_main([str(dataset), "--out", str(run), "--quiet", *sets]) == 0
    first = (run / "checkpoint.pt").read_bytes()
    again = [str(dataset), "--out", str(run), "--quiet", *sets, "--set", "seed=5"]
    assert train_main(again) == 1
    err = capsys.readouterr().err  # finished: no resume to offer
    assert "holds a run already (checkpoint.pt)" in err and "--resume" not in err
    assert "(it finished: nothing to resume)" in err
    assert (run / "checkpoint.pt").read_bytes() == first  # untouched
    assert train_main([*again, "--force"]) == 0
    assert torch.load(run / "checkpoint.pt", weights_only=True)["config"]["seed"] == 5


def test_ctrl_c_while_the_saved_run_is_printed_is_ignored(dataset, tmp_path, monkeypatch,
                                                          capsys):
    """The run is saved before its lines are printed: a Ctrl-C then ended the command with
    exit 130, as if the run were lost. The handler it found is back afterwards."""
    import tactile.training.evaluate as evaluate

    real = evaluate.table

    def table(*a, **k):
        signal.raise_signal(signal.SIGINT)
        return real(*a, **k)

    monkeypatch.setattr(evaluate, "table", table)
    found = signal.signal(signal.SIGINT, signal.default_int_handler)  # Python's, as a command has
    try:
        sets = [f"--set={k}={v}" for k, v in {**SMALL, "epochs": 1}.items()]
        assert train_main([str(dataset), "--out", str(tmp_path / "r"), "--quiet", *sets]) == 0
        assert "run in " in capsys.readouterr().out
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, found)


def test_a_forced_run_that_fails_leaves_the_old_run_resumable(dataset, tmp_path, capsys):
    """--force removed resume.pt before anything else: a forced run that then failed (here on
    data that cannot be split) left an interrupted run that --resume called finished."""
    run = tmp_path / "r"
    cfg = TrainConfig(**{**SMALL, "epochs": 2, "patience": 2})
    assert train(dataset, run, cfg, progress=False, on_epoch=sigint_after("fit", 1))[
        "interrupted"]
    two_users = tmp_path / "two"
    make_dataset(two_users, takes=2, textures=("non_contact", "paper"), seconds=4, seed=2)
    assert train_main([str(two_users), "--out", str(run), "--force", "--quiet"]) == 1
    assert "cannot be split" in capsys.readouterr().err
    assert (run / RESUME).is_file()
    assert train_main(["--resume", str(run), "--quiet"]) == 0


@pytest.mark.parametrize("limit, fails", [(1_000, "metrics.json"), (100_000, "checkpoint.pt")])
def test_a_run_that_cannot_be_written_is_one_line_exit_4_and_leaves_no_run(
        dataset, tmp_path, limit, fails):
    """The operating system refuses a run file's growth (RLIMIT_FSIZE, a real EFBIG as a full
    disk gives ENOSPC): torch.save's RuntimeError was a traceback and left a cut-short
    checkpoint.pt that the next training called a finished run. Now one line naming the file,
    exit 4, no run file left, and the same --out trains once there is room. (hidden=48: the
    checkpoint, about 200 kB, is well above the limit, the pictures, about 30 kB, below it.)"""
    import resource

    def limit_files():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails instead of killing
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    run = tmp_path / "run"
    sets = [f"--set={k}={v}" for k, v in {**SMALL, "epochs": 1, "hidden": 48}.items()]
    proc = subprocess.run(
        [sys.executable, "-c", "import sys; from tactile.training.commands.train import main; "
         "sys.exit(main())", str(dataset), "--out", str(run), "--quiet", *sets],
        capture_output=True, text=True, timeout=600, preexec_fn=limit_files)
    assert proc.returncode == 4 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.splitlines()[-1] == (f"tactile-train: error: {run / fails}: cannot "
                                            "write (File too large); the run is not saved")
    assert not run.exists()  # no cut-short or temporary file: the folder made is removed
    assert train_main([str(dataset), "--out", str(run), "--quiet", *sets]) == 0
    assert (run / "checkpoint.pt").stat().st_size > limit


def test_a_run_file_the_folder_cannot_take_is_exit_1_and_removes_the_run(dataset, tmp_path,
                                                                          capsys):
    """A folder in the way of confusion.txt: not a full disk, so exit 1, naming that file; the
    files written before it are removed (metrics.json made the folder look like a run)."""
    run = tmp_path / "run"
    (run / "confusion.txt").mkdir(parents=True)
    sets = [f"--set={k}={v}" for k, v in {**SMALL, "epochs": 1}.items()]
    assert train_main([str(dataset), "--out", str(run), "--quiet", *sets]) == 1
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"tactile-train: error: {run / 'confusion.txt'}: cannot write (Is a directory); the "
        "run is not saved")
    assert sorted(p.name for p in run.iterdir()) == ["confusion.txt"]


def test_an_interrupted_run_whose_files_cannot_be_written_says_resume_pt_is_saved(
        dataset, tmp_path, monkeypatch):
    """Ctrl-C saves resume.pt, then the run's files; when those fail the line said only 'the
    run is not saved', and the resume hint was never printed."""
    import tactile.training.run_files as rf
    from tactile.errors import OutputError

    real = rf.write_whole

    def full_at_curves(path, data):
        if path.name == "curves.png":
            raise OutputError(f"{path}: cannot write (No space left on device)")
        real(path, data)

    monkeypatch.setattr(rf, "write_whole", full_at_curves)
    run = tmp_path / "run"
    cfg = TrainConfig(**{**SMALL, "epochs": 3})
    with pytest.raises(OutputError) as e:
        train(dataset, run, cfg, progress=False, on_epoch=sigint_after("fit", 1))
    assert str(e.value) == (f"{run / 'curves.png'}: cannot write (No space left on device); "
                            "the run is not saved, but resume.pt is (the state after fit epoch "
                            f"1): make room, then tactile-train --resume {run}")
    assert sorted(p.name for p in run.iterdir()) == ["resume.pt"]
    monkeypatch.setattr(rf, "write_whole", real)
    assert resume_run(run)["epochs_run"] == 3


def test_an_unhandled_ctrl_c_in_a_torch_command_is_one_line_and_130(capsys):
    from tactile.cli import command

    @command("tactile-train", interruptible=True)
    def starting(argv=None) -> int:
        raise KeyboardInterrupt  # as SIGINT does while torch imports

    assert starting() == EXIT_INTERRUPTED
    assert capsys.readouterr().err == "tactile-train: interrupted\n"


def test_sigint_after_the_last_epoch_still_saves_the_finished_run(dataset, tmp_path):
    # without a refit or the blend's fits (which a SIGINT stops: the test above), fit epoch 2
    # is the last step
    cfg = TrainConfig(**{**SMALL, "epochs": 2, "patience": 2, "refit": "off", "blend": "off"})
    m = train(dataset, tmp_path / "r", cfg, progress=False, on_epoch=sigint_after("fit", 2))
    assert m["interrupted"] is False and m["epochs_run"] == 2
    assert m["shifted"] == {"not_measured": "the hop (10 samples, 0.1 s) divides every shift, "
                                            "so the shifted windows are the test windows again"}
    assert (tmp_path / "r" / "checkpoint.pt").is_file()
    assert not (tmp_path / "r" / RESUME).exists()
    # with the default refit and blend the last epoch is the refit's last (the regression's
    # solve after it is not stopped)
    cfg = cfg.replace(refit="on", blend="auto")
    full = train(dataset, tmp_path / "full", cfg, progress=False)
    last = full["refit_epochs"]
    seen = []
    hook = sigint_after("refit", last)

    def on_epoch(p: str, e: int) -> None:
        seen.append((p, e))
        hook(p, e)

    m = train(dataset, tmp_path / "r2", cfg, progress=False, on_epoch=on_epoch)
    assert seen[-1] == ("refit", last) and last >= 1  # SIGINT came after the very last epoch
    assert m["interrupted"] is False and m["refit_epochs"] == last
    assert m["accuracy"] == full["accuracy"] and not (tmp_path / "r2" / RESUME).exists()


def test_a_resume_state_that_does_not_fit_is_one_line(dataset, tmp_path, capsys):
    run = tmp_path / "r"
    cfg = TrainConfig(**{**SMALL, "epochs": 2, "patience": 2})
    assert train(dataset, run, cfg, progress=False, on_epoch=sigint_after("fit", 1))[
        "interrupted"]
    capsys.readouterr()
    saved = torch.load(run / RESUME, weights_only=True)
    good_head = saved["state"]["head"]
    saved["state"]["head"] = {"lstm.weight_ih_l0": torch.zeros(2, 2)}
    torch.save(saved, run / RESUME)
    assert train_main(["--resume", str(run), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "resume.pt: the saved state does not fit this run" in err and err.count("\n") == 1
    for key, value in (("history", None), ("epoch", -5), ("stale", "x")):
        # a history of None was a TypeError traceback at the next epoch; epoch -5 restarted
        edited = torch.load(run / RESUME, weights_only=True)
        edited["state"] = {**saved["state"], "head": good_head, key: value}
        torch.save(edited, run / RESUME)
        assert train_main(["--resume", str(run), "--quiet"]) == 1, key
        err = capsys.readouterr().err
        assert "the saved state does not fit this run" in err and err.count("\n") == 1, err
    (run / RESUME).write_bytes(b"garbage")
    assert train_main(["--resume", str(run)]) == 1
    assert "not a readable resume state" in capsys.readouterr().err


def test_a_resume_on_other_takes_is_refused(dataset, tmp_path, capsys):
    """DATA given to --resume was read whatever it held: takes of the same names from another
    seed continued the run on other recordings, exit 0, mixing two datasets in one run."""
    import shutil

    run = tmp_path / "r"
    cfg = TrainConfig(**{**SMALL, "epochs": 2, "patience": 2})
    assert train(dataset, run, cfg, progress=False, on_epoch=sigint_after("fit", 1))[
        "interrupted"]
    other = tmp_path / "other"
    make_dataset(other, takes=5, textures=("non_contact", "paper", "nonwoven_cloth"),
                 seconds=8, seed=3)  # the same names, other recordings
    fewer = tmp_path / "fewer"
    shutil.copytree(dataset, fewer)
    for f in fewer.glob("paper-user004.*"):
        f.unlink()
    capsys.readouterr()
    for data, says in ((other, "other recordings in non_contact-user000.csv, "),
                       (fewer, "missing paper-user004.csv)")):
        assert train_main([str(data), "--resume", str(run), "--quiet"]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"{data}: not the takes this run started on (" in err[0], err
        assert says in err[0] and err[0].endswith("give the dataset it was started on"), err
    assert (run / RESUME).is_file()  # nothing lost: the right data still continues it
    assert train_main([str(dataset), "--resume", str(run), "--quiet"]) == 0


def test_a_state_saved_before_select_existed_keeps_stopping_on_the_loss(dataset, tmp_path):
    run = tmp_path / "r"
    cfg = TrainConfig(**{**SMALL, "epochs": 3, "patience": 3})
    assert cfg.select == "accuracy"  # the default the old state must not silently switch to
    assert train(dataset, run, cfg, progress=False, on_epoch=sigint_after("fit", 1))[
        "interrupted"]
    assert load_resume(run)["config"]["select"] == "accuracy"  # saved as it was
    saved = torch.load(run / RESUME, weights_only=True)
    del saved["config"]["select"]
    torch.save(saved, run / RESUME)
    assert TrainConfig.from_dict(load_resume(run)["config"]).select == "loss"


def test_a_state_saved_before_the_wide_path_ensembles_and_blend_goes_on_as_one_plain_model(
        dataset, tmp_path):
    run = tmp_path / "r"
    cfg = TrainConfig(**{**SMALL, "epochs": 3, "patience": 3, "wide": False, "ensemble": 1,
                         "blend": "off"})
    assert train(dataset, run, cfg, progress=False, on_epoch=sigint_after("fit", 1))[
        "interrupted"]
    saved = torch.load(run / RESUME, weights_only=True)
    del saved["config"]["wide"], saved["config"]["ensemble"], saved["config"]["blend"]
    torch.save(saved, run / RESUME)
    old = TrainConfig.from_dict(load_resume(run)["config"])
    assert old.wide is False and old.ensemble == 1 and old.blend == "off"
    assert train_main(["--resume", str(run), "--quiet"]) == 0
    model, ck = load_checkpoint(run)
    assert model.head.wide is None and ck["config"]["wide"] is False
    assert ck["config"]["blend"] == "off" and "blend" not in json.loads(
        (run / "metrics.json").read_text())
    assert ck["config"]["ensemble"] == 1 and model.state_shape == (2, 12)


@contextlib.contextmanager
def _holding(folder):
    """Hold ``folder`` as a training that writes it does (an advisory lock on it)."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        yield
    finally:
        os.close(fd)


def test_a_second_training_into_a_folder_being_written_is_refused(dataset, tmp_path, capsys):
    """Two trainings started into one --out both found no run there, and their files mixed
    (one's config beside the other's weights). The folder is held while a training writes."""
    run = tmp_path / "run"
    run.mkdir()
    sets = [f"--set={k}={v}" for k, v in {**SMALL, "epochs": 1}.items()]
    for force in ([], ["--force"]):
        with _holding(run):  # as the first training holds it
            assert train_main([str(dataset), "--out", str(run), "--quiet", *sets, *force]) == 1
            assert capsys.readouterr().err == (f"tactile-train: error: --out {run}: another "
                                               "tactile-train is writing into it now: choose "
                                               "another --out\n")
            assert list(run.iterdir()) == []
    # the first one ended: the folder is free again
    assert train_main([str(dataset), "--out", str(run), "--quiet", *sets]) == 0
    assert (run / "checkpoint.pt").is_file()


def test_a_state_saved_before_the_class_by_class_draw_is_refused_where_it_matters(dataset,
                                                                                   tmp_path):
    """A run stopped before takes of one class each were drawn class by class (and a signal
    centred whole) drew another split: resumed now, its earlier epochs' takes could land in
    test. Such a state is refused, in one line; one whose split and centring are unchanged
    goes on."""
    data = tmp_path / "data"
    make_dataset(data, takes=4, textures=("non_contact", "paper"), seconds=4, seed=1)
    for p in data.glob("*.json"):  # takes without users: each its own group, one class each
        meta = json.loads(p.read_text())
        del meta["user"]
        p.write_text(json.dumps(meta))
    cfg = TrainConfig(**SMALL)
    train(data, tmp_path / "cut", cfg, progress=False, on_epoch=sigint_after("fit", 1))
    saved = torch.load(tmp_path / "cut" / RESUME, weights_only=True)
    assert saved["state"]["prep_version"] == 2
    del saved["state"]["prep_version"]
    torch.save(saved, tmp_path / "cut" / RESUME)
    from tactile.errors import RecordingError

    with pytest.raises(RecordingError, match="saved before takes of one class each were drawn "
                                             "class by class"):
        resume_run(tmp_path / "cut")
    # users holding every class: the same split as before, so the old state goes on
    train(dataset, tmp_path / "users", cfg, progress=False, on_epoch=sigint_after("fit", 1))
    saved = torch.load(tmp_path / "users" / RESUME, weights_only=True)
    del saved["state"]["prep_version"]
    torch.save(saved, tmp_path / "users" / RESUME)
    assert not resume_run(tmp_path / "users")["interrupted"]
