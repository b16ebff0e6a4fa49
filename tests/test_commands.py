"""Command-line consistency: --version everywhere, output paths checked before any work, one
message for a missing model, refused labels, no silent overwrite; tactile-data and tactile-plot."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import tomllib
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO

from tactile import __version__
from tactile.device.protocol import pen_info
from tactile.device.recordings import TakeWriter, check_label, read_take
from tactile.device.recordings.summary import natural
from tactile.device.sim import make_dataset
from tactile.errors import RecordingError

SCRIPTS = sorted(tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"])
BIN = Path(sys.executable).parent


def cli(name: str, *args: str, timeout: float = 120) -> tuple[int, str, str]:
    """Run an installed console script; (exit code, stdout, stderr)."""
    p = subprocess.run([str(BIN / name), *args], capture_output=True, text=True, timeout=timeout)
    return p.returncode, p.stdout, p.stderr


@pytest.mark.parametrize("name", SCRIPTS)
def test_every_command_has_version(name):
    code, out, err = cli(name, "--version")
    assert (code, out.strip()) == (0, f"{name} {__version__}"), err


@pytest.mark.parametrize("module, body, argv", [
    ("tactile.export.commands.export", "_export", ["RUN", "-o", "m.onnx"]),
    ("tactile.export.commands.check", "_check", ["m.onnx"]),
    ("tactile.device.commands.import_biotac", "_main", ["a.h5", "--out", "D"]),
    ("tactile.device.commands.import_hapmat", "_main", ["SRC", "--out", "D"]),
    ("tactile.device.commands.data", "_main", ["D"]),
    ("tactile.device.commands.sim", "_main", ["--dataset", "D"]),
])
def test_ctrl_c_in_a_command_is_one_line_and_130(module, body, argv, monkeypatch, capsys):
    """Ctrl-C in tactile-export --data (calibrating), say, was an 80-line traceback."""
    import importlib

    mod = importlib.import_module(module)

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(mod, body, interrupted)
    assert mod.main(argv) == 130
    err = capsys.readouterr().err
    assert err.endswith(": interrupted\n") and err.count("\n") == 1, err


def test_ctrl_c_while_a_command_imports_is_held_until_the_imports_end():
    """A Ctrl-C inside a library's import left the library half-built: tactile-export then
    died of numpy's RecursionError (a traceback), not with its one line. The command's imports
    hold SIGINT (and SIGTERM where the command takes it as Ctrl-C) and raise it when they end;
    a caller's own handler is left alone; the handlers are put back."""
    from tactile import cli

    was = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        signal.signal(signal.SIGINT, signal.default_int_handler)  # Python's own
        done = []
        with pytest.raises(KeyboardInterrupt), cli.holding_signals():
            signal.raise_signal(signal.SIGINT)  # (its handler runs before this returns)
            done.append("the rest of the imports")
        assert done == ["the rest of the imports"]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        with cli.holding_signals():  # no signal: nothing raised
            done.append("quiet")
        assert done[-1] == "quiet"

        signal.signal(signal.SIGTERM, cli._terminate)  # a command(terminable=True)'s
        with pytest.raises(cli.Terminated), cli.holding_signals():
            signal.raise_signal(signal.SIGTERM)
            done.append("term")
        assert done[-1] == "term" and signal.getsignal(signal.SIGTERM) is cli._terminate

        with pytest.raises(ModuleNotFoundError), cli.holding_signals():  # the block's error
            signal.raise_signal(signal.SIGINT)
            raise ModuleNotFoundError("no module named 'h5py'")
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler

        seen = []
        signal.signal(signal.SIGINT, lambda signum, frame: seen.append(signum))  # a caller's
        with cli.holding_signals():
            signal.raise_signal(signal.SIGINT)
            assert seen == [signal.SIGINT]  # its handler ran at once
        signal.signal(signal.SIGINT, signal.default_int_handler)

        def off_main():  # another thread cannot set handlers: the block runs as it is
            with cli.holding_signals():
                seen.append(signal.getsignal(signal.SIGINT))

        thread = threading.Thread(target=off_main)
        thread.start()
        thread.join()
        assert seen[-1] is signal.default_int_handler
    finally:
        for s, handler in was.items():
            signal.signal(s, handler)


def test_ctrl_c_after_a_command_line_command_returned_does_not_change_its_exit(tmp_path):
    """Ctrl-C in the interpreter's teardown after tactile-export had written its file ended it
    by SIGINT, with no line (7 of 8 tries in that half second): the process's command (its
    console script, or python -m) ignores SIGINT once it has returned its code; a script
    that calls main() itself, and any in-process call, keeps its handlers; SIGTERM is left
    alone (torchrun's agent ends its workers by it)."""
    module = tmp_path / "fakecmd.py"
    module.write_text("from tactile.cli import command\n"
                      "@command('tactile-x', interruptible=True, files=True)\n"
                      "def main(argv=None):\n"
                      "    return 3\n")
    after = ("import os, signal, sys\n"
             "print('exit', code, signal.getsignal(signal.SIGINT) is signal.SIG_IGN,\n"
             "      signal.getsignal(signal.SIGTERM) is signal.SIG_DFL, flush=True)\n"
             "os.kill(os.getpid(), signal.SIGINT)\n"
             "sys.exit(code)\n")
    as_process = tmp_path / "tactile-x"  # the console script's name
    as_process.write_text(f"import sys\nsys.path.insert(0, {str(tmp_path)!r})\n"
                          "from fakecmd import main\n"
                          "main([])\n"  # in-process, argv given: nothing changes
                          "import signal\n"
                          "assert signal.getsignal(signal.SIGINT) is signal.default_int_handler\n"
                          "code = main()\n" + after)
    proc = subprocess.run([sys.executable, str(as_process)], capture_output=True, text=True,
                          timeout=60)
    assert (proc.returncode, proc.stdout, proc.stderr) == (3, "exit 3 True True\n", "")

    as_module = tmp_path / "fakemod.py"  # python -m MODULE
    as_module.write_text(module.read_text() + "if __name__ == '__main__':\n"
                         "    code = main()\n" + "".join(f"    {line}\n"
                                                      for line in after.splitlines()))
    proc = subprocess.run([sys.executable, "-m", "fakemod"], capture_output=True, text=True,
                          timeout=60, cwd=tmp_path)
    assert (proc.returncode, proc.stdout, proc.stderr) == (3, "exit 3 True True\n", "")

    script = tmp_path / "my_script.py"  # a user's script calling main(): its handlers stay
    script.write_text(f"import sys\nsys.path.insert(0, {str(tmp_path)!r})\n"
                      "from fakecmd import main\n"
                      "code = main()\n" + after)
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          timeout=60)
    assert (proc.returncode, proc.stdout) == (-signal.SIGINT, "exit 3 False True\n")


def test_a_second_ctrl_c_while_imports_hold_the_first_ends_the_process_by_it():
    """An import stuck on a slow disk can still be stopped: the second signal kills."""
    code = ("import os, signal\n"
            "from tactile.cli import holding_signals\n"
            "with holding_signals():\n"
            "    os.kill(os.getpid(), signal.SIGINT)\n"
            "    print('held', flush=True)\n"
            "    os.kill(os.getpid(), signal.SIGINT)\n"
            "    print('not reached', flush=True)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60)
    assert (proc.returncode, proc.stdout) == (-signal.SIGINT, "held\n"), proc.stderr


@pytest.mark.parametrize("name, args, option", [
    ("tactile-data", [""], "data"),
    ("tactile-sim", ["--dataset", "", "--takes", "1"], "--dataset"),
    ("tactile-record", ["--port", "loop://", "--label", "paper", "--out", ""], "--out"),
    ("tactile-import-hapmat", ["", "--out", "D"], "source"),
    ("tactile-import-biotac", ["a.h5", "--out", ""], "--out"),
    ("tactile-plot", ["", "-o", "p.png"], "source"),
    ("tactile-train", ["", "--out", "R"], "data"),
    ("tactile-eval", ["R", ""], "data"),
    ("tactile-export", ["R", "-o", ""], "-o/--out"),
    ("tactile-check", ["m.onnx", "--data", ""], "--data"),
    ("tactile-run", ["--model", "m.onnx", "--replay", ""], "--replay"),
])
def test_an_empty_path_is_a_usage_error(name, args, option, tmp_path):
    """Path("") is the current folder: `tactile-sim --dataset ''` wrote its takes there and
    `tactile-data ''` read it."""
    code, out, err = cli(name, *args)
    assert (code, out) == (1, ""), err
    assert err == f"{name}: error: argument {option}: an empty path (see --help)\n", err


@pytest.mark.parametrize("option, value, says", [
    ("--p-min", "2", "2 must be >= 0.0 and <= 1.0"), ("--hold", "0", "0 must be in 1..100000"),
    ("--hold", "x", "'x' is not an integer"), ("--smooth", "bogus", "'bogus': expected N"),
])
def test_eval_label_stream_options_are_checked_as_tactile_run_checks_them(tmp_path, option,
                                                                          value, says):
    """tactile-eval read --p-min, --hold and --smooth as any number or text and checked them
    after its run folder: a line without the option's name (`p_min 2.0: must be a number from
    0 to 1`), after loading; now argparse's line naming the option, before anything is read."""
    code, out, err = cli("tactile-eval", str(tmp_path / "run"), str(tmp_path / "data"), option,
                         value)
    assert (code, out) == (1, "")
    assert err.startswith(f"tactile-eval: error: argument {option}: {says}"), err


def test_a_value_that_starts_with_a_dash_is_told_to_go_after_an_equals_sign():
    """`--smooth -1s` said only argparse's "expected one argument" (it takes -1s for an
    option); the line now shows the form that passes the value. A forgotten value followed by
    another option keeps argparse's line alone."""
    code, _, err = cli("tactile-run", "--model", "m.onnx", "--replay", "t.csv", "--smooth",
                       "-1s")
    assert code == 1 and err == (
        "tactile-run: error: argument --smooth: expected one argument; a value that starts "
        "with '-' goes after '=': --smooth=-1s (see --help)\n"), err
    code, _, err = cli("tactile-run", "--model", "m.onnx", "--replay", "--smooth", "1s")
    assert code == 1 and err == (
        "tactile-run: error: argument --replay: expected one argument (see --help)\n"), err
    code, _, err = cli("tactile-eval", "r", "d", "--smooth", "--data")  # not an option either
    assert code == 1 and "goes after" not in err, err


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full on this system")
@pytest.mark.parametrize("name, args", [("data", ["--json"]), ("sim", ["--pty", "--seconds",
                                                                      "1"])])
def test_stdout_on_a_full_disk_is_exit_4_outside_tactile_run_too(tmp_path, name, args):
    """tactile-data (as tactile-eval, tactile-monitor: the mapping is tactile.cli's, shared by
    every command) whose stdout is on a full disk exited 1, 'bad input'; a full disk is 4, the
    code a service may restart on. The line said '[Errno 28] No space left on device', not
    what could not be written; tactile-sim's stdout is wrapped twice (a command of files)."""
    make_dataset(tmp_path, takes=1, textures=("paper",), seconds=1)
    with open("/dev/full", "w") as full:
        proc = subprocess.run([sys.executable, "-m", f"tactile.device.commands.{name}",
                               *([str(tmp_path)] if name == "data" else []), *args],
                              stdout=full, stderr=subprocess.PIPE, text=True, timeout=60)
    assert proc.returncode == 4 and proc.stderr == (
        f"tactile-{name}: error: stdout: cannot write (No space left on device)\n"), proc.stderr


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full on this system")
def test_a_stderr_that_cannot_be_written_stops_no_command(tmp_path):
    """stderr on a full disk (`2>/dev/full`): tactile-record exited 1 ('bad input') with its
    take done, tactile-run printed no label and exited 1. Diagnostics that cannot be written
    are dropped, as on a closed stderr: the work and its exit code stay."""
    take = make_dataset(tmp_path / "d", takes=1, textures=("paper",), seconds=3)[0]
    model = str(REPO / "models" / "pen-exp2.onnx")
    run = [sys.executable, "-m", "tactile.runtime.commands.run", "--model", model, "--replay",
           str(take)]
    plain = subprocess.run(run, capture_output=True, text=True, timeout=120)
    assert plain.returncode == 0 and plain.stdout.count('"label"') >= 5, plain.stderr
    rec = [sys.executable, "-m", "tactile.device.commands.record", "--port",
           "sim://?texture=paper&seed=1&speed=max", "--label", "paper", "--out",
           str(tmp_path / "rec"), "--seconds", "1"]
    with open("/dev/full", "w") as full:
        labels = subprocess.run(run, stdout=subprocess.PIPE, stderr=full, text=True,
                                timeout=120)
        recorded = subprocess.run(rec, stdout=subprocess.PIPE, stderr=full, text=True,
                                  timeout=120)
    assert labels.returncode == 0 and labels.stdout.count('"label"') == plain.stdout.count(
        '"label"')
    (got,) = (tmp_path / "rec").glob("*.csv")
    assert recorded.returncode == 0 and recorded.stdout.strip() == str(got)
    assert len(read_take(got).raw) == 100 and read_take(got).meta["complete"] is True


def test_a_callers_stderr_without_a_descriptor_that_fails_is_dropped_too():
    """An in-process caller's stderr (no file descriptor to point at the null device) whose
    write fails: the line is dropped and so are the rest, instead of the wrapper's own error."""
    import io

    from tactile.cli import _ReaderMayGo

    class Full(io.StringIO):
        def write(self, text):
            raise OSError(28, "No space left on device")

    class Busy(io.StringIO):  # a non-blocking stream that may take the line later
        def write(self, text):
            raise BlockingIOError(11, "Resource temporarily unavailable")

    err = _ReaderMayGo(Full(), any_final=True)
    assert err.write("a line\n") == 7 and err.write("another\n") == 8
    err.flush()
    with pytest.raises(BlockingIOError):  # not a reason to drop every line after it
        _ReaderMayGo(Busy(), any_final=True).write("a line\n")


def test_a_reader_of_stderr_that_goes_away_does_not_stop_a_recording(tmp_path):
    """`tactile-record ... 2>&1 >list | head -1`: the reader of stderr went at the first
    progress line and the recording stopped there, exit 0, 100 of 250 samples."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "tactile.device.commands.record", "--port",
         "sim://?texture=paper&seed=1", "--label", "paper", "--out", str(tmp_path / "rec"),
         "--seconds", "2.5"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    proc.stderr.readline()  # the first line, then the reader goes away
    proc.stderr.close()
    assert proc.wait(timeout=120) == 0
    (got,) = (tmp_path / "rec").glob("*.csv")
    assert len(read_take(got).raw) == 250 and read_take(got).meta["complete"] is True


def test_a_path_that_is_not_utf8_is_printed_as_its_bytes(tmp_path):
    """A folder named with a byte that is no UTF-8, under a strict UTF-8 stdout (a UTF-8
    locale's, or PYTHONIOENCODING=utf-8): tactile-sim --dataset wrote one of two takes, then
    failed printing its path ('surrogates not allowed'), exit 1."""
    folder = os.fsencode(tmp_path) + b"/nb\xff"
    proc = subprocess.run([sys.executable, "-m", "tactile.device.commands.sim", "--dataset",
                           folder, "--takes", "1", "--seconds", "1", "--textures", "paper,desk"],
                          capture_output=True, env={**os.environ, "PYTHONIOENCODING": "utf-8"},
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == [folder + b"/paper-user000.csv",
                                        folder + b"/desk-user000.csv"]
    assert sorted(os.listdir(folder)) == [b"desk-user000.csv", b"desk-user000.json",
                                          b"paper-user000.csv", b"paper-user000.json"]


def _closing(fd: int):
    return lambda: os.close(fd)  # in the child, before the command starts: `>&-` or `2>&-`


def test_a_closed_stdout_is_the_null_device_not_a_traceback(tmp_path):
    """Started with stdout closed (`>&-`: Python leaves sys.stdout None), every command
    ended at its first line with a traceback, exit 1. The recorder records the take whole."""
    out = tmp_path / "rec"
    proc = subprocess.run([str(BIN / "tactile-record"), "--port",
                           "sim://?texture=paper&seed=3&speed=max", "--label", "paper",
                           "--seconds", "1", "--out", str(out)], stderr=subprocess.PIPE,
                          text=True, timeout=120, preexec_fn=_closing(1))
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    [take] = [read_take(p) for p in out.glob("*.csv")]
    assert len(take.seq) >= 100 and (np.diff(take.seq) == 1).all()
    assert (out / take.path.name).read_text().startswith("seq,t_us,")
    proc = subprocess.run([str(BIN / "tactile-data"), str(out)], stderr=subprocess.PIPE,
                          text=True, timeout=60, preexec_fn=_closing(1))
    assert (proc.returncode, proc.stderr) == (0, "")


def test_a_script_that_runs_commands_twice_with_stdout_closed(tmp_path):
    """The first command filled the closed descriptor and its ``finally`` put sys.stdout back
    to None: the second saw an open descriptor and ended at its first line, a traceback."""
    make_dataset(tmp_path, takes=1, textures=("paper",), seconds=1)
    script = ("import sys\nfrom tactile.device.commands.data import main\n"
              f"codes = [main([{str(tmp_path)!r}]) for _ in range(2)]\n"
              "print(codes, file=sys.stderr)\n")
    proc = subprocess.run([sys.executable, "-c", script], stderr=subprocess.PIPE, text=True,
                          timeout=60, preexec_fn=_closing(1))
    assert (proc.returncode, proc.stderr) == (0, "[0, 0]\n"), proc.stderr


def test_a_closed_stderr_keeps_its_lines_out_of_the_label_stream(tmp_path):
    """With stderr closed (`2>&-`: sys.stderr None), print(file=sys.stderr) writes to stdout:
    tactile-run's notes and summary went into the JSON lines of its labels."""
    make_dataset(tmp_path, takes=1, textures=("paper",), seconds=3, seed=2)
    [take] = tmp_path.glob("*.csv")
    proc = subprocess.run([str(BIN / "tactile-run"), "--model",
                           str(REPO / "models" / "pen-exp2.onnx"), "--replay", str(take)],
                          stdout=subprocess.PIPE, text=True, timeout=120,
                          preexec_fn=_closing(2))
    lines = proc.stdout.splitlines()
    assert proc.returncode == 0 and len(lines) > 5
    assert all(isinstance(json.loads(line), dict) for line in lines), lines[:3]


def test_stdout_that_fails_with_an_io_error_is_exit_4_in_every_command(tmp_path, monkeypatch,
                                                                       capsys):
    """README: exit 4 when stdout cannot be written; an I/O error (not a full disk) gave 1
    outside tactile-run, whose label writer says 4."""
    from tactile.device.commands.data import main

    class Failing:
        def write(self, text):
            raise OSError(5, "Input/output error")

        def flush(self):
            pass

    make_dataset(tmp_path, takes=1, textures=("paper",), seconds=1)
    monkeypatch.setattr(sys, "stdout", Failing())
    assert main([str(tmp_path)]) == 4
    assert capsys.readouterr().err == "tactile-data: error: stdout: cannot write " \
                                      "(Input/output error)\n"


def test_export_checks_its_output_path_before_any_work(tmp_path):
    # the run folder does not exist either: the output is checked first, and nothing is made
    code, _, err = cli("tactile-export", str(tmp_path / "run"), "-o", str(tmp_path))
    assert code == 1 and "a folder" in err and len(err.strip().splitlines()) == 1
    code, _, err = cli("tactile-export", str(tmp_path / "run"), "-o",
                       str(tmp_path / "no" / "such" / "x.onnx"))
    assert code == 1 and "no folder" in err
    assert not (tmp_path / "no").exists()
    # a name of another kind: -o RUN/checkpoint.pt replaced the run it exported, exit 0
    (tmp_path / "checkpoint.pt").write_bytes(b"keep")
    code, _, err = cli("tactile-export", str(tmp_path / "run"), "-o",
                       str(tmp_path / "checkpoint.pt"))
    assert code == 1 and err.strip() == (f"tactile-export: error: -o {tmp_path}/checkpoint.pt: "
                                         f"name an .onnx file, e.g. {tmp_path}/checkpoint.onnx")
    assert (tmp_path / "checkpoint.pt").read_bytes() == b"keep"
    if Path("/proc/self").is_dir():  # /proc: root may "write" by os.access, but makes no file
        code, _, err = cli("tactile-export", str(tmp_path / "run"), "-o", "/proc/x.onnx")
        assert code == 1 and err.strip().startswith(
            "tactile-export: error: -o /proc/x.onnx: cannot write in /proc ("), err


@pytest.mark.parametrize("kind", ["missing", "folder"])
def test_a_bad_model_path_reads_the_same_in_run_and_check(tmp_path, kind):
    path = tmp_path / "model.onnx"
    if kind == "folder":
        path.mkdir()
    run = cli("tactile-run", "--model", str(path), "--port", "loop://")
    check = cli("tactile-check", str(path))
    want = "no such model file" if kind == "missing" else "a folder, not a model file"
    for (code, _, err), prog in ((run, "tactile-run"), (check, "tactile-check")):
        assert code == 3, err
        assert err.strip() == f"{prog}: error: {path}: {want}" + (
            " (give the .onnx file)" if kind == "folder" else "")


def test_replay_of_a_folder_names_what_was_typed(tmp_path):
    model = REPO / "models" / "pen-exp2.onnx"
    code, _, err = cli("tactile-run", "--model", str(model), "--replay", str(tmp_path))
    assert code == 1 and f"{tmp_path}: a folder, not a take" in err
    code, _, err = cli("tactile-run", "--model", str(model), "--replay", str(tmp_path / "x"))
    assert code == 1 and f"{tmp_path / 'x'}: not a take" in err and "x.csv" not in err


def test_importer_and_recorder_say_what_is_wrong_with_their_paths(tmp_path):
    code, _, err = cli("tactile-import-hapmat", str(tmp_path / "nothere"), "--out",
                       str(tmp_path / "out"))
    assert code == 1 and "nothere: no such file or folder" in err
    a_file = tmp_path / "file"
    a_file.write_text("x")
    # the port would fail with exit 2: exit 1 shows the folder was checked before it opened
    code, _, err = cli("tactile-record", "--port", "/dev/no-such-pen", "--label", "paper",
                       "--out", str(a_file))
    assert code == 1 and f"{a_file}: not a folder" in err


@pytest.mark.parametrize("label", ["", " ", "a\tb", "a:b", "a*b", "a?b", 'a"b', "a<b", "a>b",
                                   "a|b", "a/b", "a\\b", "a,b", "a\nb", ".hidden", " lead",
                                   "trail ", "x" * 65])
def test_labels_that_cards_or_csv_refuse_are_refused(label, tmp_path):
    with pytest.raises(RecordingError, match="must be 1-64 characters"):
        check_label(label)
    with pytest.raises(RecordingError):
        TakeWriter(tmp_path, label, pen_info())
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("label", ["paper", "mouse_pad", "Non-woven cloth 2", "café", "x" * 64])
def test_ordinary_labels_pass(label):
    assert check_label(label) == label


def test_recorder_refuses_a_bad_label_before_opening_the_port(tmp_path):
    code, _, err = cli("tactile-record", "--port", "/dev/no-such-pen", "--label", "a:b",
                       "--out", str(tmp_path))
    assert code == 1 and "label 'a:b'" in err and ": * ?" in err


def test_recorder_refuses_the_label_the_label_stream_reserves(tmp_path):
    """``--label uncertain`` recorded a take that training then refused (the label stream
    reports ``uncertain`` for no stable label); it is refused before the port opens."""
    code, _, err = cli("tactile-record", "--port", "/dev/no-such-pen", "--label", "uncertain",
                       "--out", str(tmp_path))
    assert code == 1 and err.strip() == (
        "tactile-record: error: label 'uncertain': the label stream reserves it for no stable "
        "label, so a model cannot have that class: choose another"), err
    assert not list(tmp_path.iterdir())


def test_sim_dataset_neither_overwrites_nor_duplicates(tmp_path):
    args = ("--dataset", str(tmp_path), "--takes", "1", "--seconds", "1", "--textures",
            "paper,desk")
    assert cli("tactile-sim", *args)[0] == 0
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    code, _, err = cli("tactile-sim", *args, "--seed", "5")
    assert code == 1 and "already exist" in err and "--force" in err
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # untouched
    assert cli("tactile-sim", *args, "--seed", "5", "--force")[0] == 0
    after = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert sorted(after) == sorted(before)  # replaced, no "-2" copies
    assert after["paper-user000.csv"] != before["paper-user000.csv"]  # another seed's data
    # another user range adds to the folder
    assert cli("tactile-sim", *args, "--first-take", "1")[0] == 0
    assert len(list(tmp_path.glob("*.csv"))) == 4


@pytest.mark.parametrize("args, says", [
    (("--textures", "paper,paper"), "texture 'paper' given twice"),
    (("--textures", ","), "no texture given: give one or more of desk, "),
    (("--seconds", "0.001"), "--seconds 0.001 at 100 Hz: not one sample a take"),
    (("--seconds", "inf"), "--seconds inf: a take needs a finite length"),
    # not a disk filled a take at a time: 7 x 1e302 rows of at least 30 + 302 + 306 bytes
    (("--seconds", "1e300"), "--seconds 1e+300 x 7 takes at 100 Hz: at least 4.47e+290 PB, "
                             "and the disk of "),
    (("--seconds", "1e307"), "--seconds 1e+307 at 100 Hz: more samples than a take can count"),
    (("--texture", "desk"), "--texture is not an option of --dataset"),
    (("--link", "drop=0.5"), "--link is not an option of --dataset"),
    (("--speed", "4"), "--speed is not an option of --dataset"),
])
def test_sim_dataset_refuses_what_it_would_not_do(tmp_path, args, says):
    """Nothing written, one line, exit 1: a texture twice would be the same takes twice, and
    a pty option would be ignored (all textures written for --texture desk)."""
    code, out, err = cli("tactile-sim", "--dataset", str(tmp_path / "d"), "--takes", "1",
                         "--seconds", "1", *args)
    assert code == 1 and says in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "d").exists() or not any((tmp_path / "d").iterdir())


@pytest.mark.parametrize("seconds, rate", [(60, 100.0), (0.5, 100.0), (20, 1000.0)])
def test_the_disk_check_counts_fewer_bytes_than_a_take_writes(tmp_path, seconds, rate):
    """A dataset that fits is never refused: the check's count is below every texture's take
    (the quietest, non_contact, writes the shortest rows)."""
    from tactile.device.sim.dataset import least_take_bytes

    assert cli("tactile-sim", "--dataset", str(tmp_path), "--takes", "1", "--seconds",
               str(seconds), "--rate", str(rate))[0] == 0
    sizes = {p.stem: p.stat().st_size for p in tmp_path.glob("*.csv")}
    assert len(sizes) == 7
    least = least_take_bytes(seconds, rate)
    assert least < min(sizes.values()) < 1.5 * least, (least, sizes)


def test_takes_of_another_rate_or_channels_are_not_written_into_a_dataset(tmp_path):
    """tactile-sim --rate 50 (or an importer of another sensor) into a folder of 100 Hz pen
    takes wrote them, exit 0: every later command on the folder then failed."""
    from tactile.device.recordings import load_dataset

    d = str(tmp_path / "d")
    assert cli("tactile-sim", "--dataset", d, "--takes", "1", "--seconds", "1",
               "--textures", "paper")[0] == 0
    code, _, err = cli("tactile-sim", "--dataset", d, "--takes", "1", "--seconds", "1",
                       "--textures", "desk", "--rate", "50")
    assert code == 1 and err.strip() == (
        f"tactile-sim: error: {d}: holds takes of another device (paper-user000.json: "
        "100 Hz, these takes 50 Hz): a dataset's takes share channels, units and rate; choose "
        "another folder"), err
    assert [t.path.name for t in load_dataset(d)] == ["paper-user000.csv"]
    assert cli("tactile-sim", "--dataset", d, "--takes", "1", "--seconds", "1",
               "--textures", "desk")[0] == 0  # the same pen: added


def ctrl_c_at_write(monkeypatch, n: int) -> None:
    """A Ctrl-C (KeyboardInterrupt) from TakeWriter.write at its ``n``-th call."""
    from tactile.device.recordings.writer import TakeWriter

    real, calls = TakeWriter.write, []

    def write(self, *a, **k):
        calls.append(1)
        if len(calls) == n:
            raise KeyboardInterrupt
        return real(self, *a, **k)

    monkeypatch.setattr(TakeWriter, "write", write)


def test_a_derived_take_stopped_half_way_is_removed(tmp_path, monkeypatch):
    """Ctrl-C in an import (or a simulated dataset) left its last take cut, `complete: false`,
    read later as if it were a recording. Whole takes stay; the half-written one goes."""
    ctrl_c_at_write(monkeypatch, 3)  # the second take's first chunk: its files are open
    with pytest.raises(KeyboardInterrupt):
        make_dataset(tmp_path, takes=1, textures=("paper", "desk"), seconds=70)  # 2 chunks
    assert sorted(p.name for p in tmp_path.iterdir()) == ["paper-user000.csv",
                                                          "paper-user000.json"]


def test_force_stopped_half_way_leaves_every_take_old_or_new(tmp_path, monkeypatch):
    """--force deleted every take it was to replace before writing the first: Ctrl-C in an
    import (or a simulated dataset) with --force left the folder without the takes not yet
    rewritten. Now each is replaced when its new take is whole; the one being written when
    it stopped is the old one again, byte for byte."""
    textures = ("paper", "desk", "mouse_pad")
    make_dataset(tmp_path, takes=1, textures=textures, seconds=2, seed=1)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    ctrl_c_at_write(monkeypatch, 2)  # the second take's first chunk: its files are open
    with pytest.raises(KeyboardInterrupt):
        make_dataset(tmp_path, takes=1, textures=textures, seconds=2, seed=2, force=True)
    after = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert sorted(after) == sorted(before)  # six files: no take missing, nothing aside
    changed = sorted(n for n in after if after[n] != before[n])
    assert changed == ["paper-user000.csv", "paper-user000.json"]  # the one written whole
    monkeypatch.undo()  # the writer as it is
    make_dataset(tmp_path, takes=1, textures=textures, seconds=2, seed=2, force=True)
    assert all(p.read_bytes() != before[p.name] for p in tmp_path.iterdir()
               if p.suffix == ".csv")


def test_a_take_put_aside_by_a_killed_replacing_run_is_never_overwritten(tmp_path):
    """A run killed (kill -9, a power cut) while it replaced a take leaves the old take as
    NAME.csv.replaced beside a cut new one; a second --force run moved its own cut take onto
    it, and the only whole copy was gone. Now any run writing that name stops first."""
    make_dataset(tmp_path, takes=1, textures=("paper",), seconds=1, seed=1)
    for suffix in (".csv", ".json"):  # as the killed run left them (its new take not begun)
        (tmp_path / f"paper-user000{suffix}").rename(tmp_path / f"paper-user000{suffix}.replaced")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    for force in (False, True):
        with pytest.raises(RecordingError, match=r"paper-user000.csv.replaced: left by a run "
                           r"that was replacing take paper-user000 with --force and was killed: "
                           r"if paper-user000.csv is missing or cut short"):
            make_dataset(tmp_path, takes=1, textures=("paper",), seconds=1, seed=2, force=force)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_a_take_half_moved_aside_is_put_back(tmp_path, monkeypatch):
    """An error between moving a take's two files aside (the disk, or a signal before they were
    held) left its .json without its .csv: a take no reader takes."""
    from tactile.device.recordings.take import whole_take

    make_dataset(tmp_path, takes=1, textures=("paper",), seconds=1, seed=1)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    real, calls = os.replace, []

    def replace(a, b):
        calls.append(a)
        if len(calls) == 2:
            raise OSError(5, "Input/output error")
        return real(a, b)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(OSError, match="Input/output error"):
        with whole_take(tmp_path, "paper-user000", replace=True):
            raise AssertionError("not reached: the moves failed")
    monkeypatch.setattr(os, "replace", real)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    with pytest.raises(RecordingError, match=r"paper-user000.csv: written since the folder was "
                       r"checked .* --force to replace it"):
        with whole_take(tmp_path, "paper-user000"):  # no --force: a take there is not replaced
            raise AssertionError("not reached")
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_ctrl_c_while_a_take_is_moved_aside_puts_it_back(tmp_path, monkeypatch):
    """The Ctrl-C held while the take's files moved aside was raised after the code that puts
    them back on an error: the take stayed aside, and every later run refused its name."""
    from tactile.device.recordings.take import whole_take

    make_dataset(tmp_path, takes=1, textures=("paper",), seconds=1, seed=1)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    real, sent = os.replace, []

    def replace(a, b):  # the user presses Ctrl-C once, as the first file moves
        if not sent:
            sent.append(a)
            os.kill(os.getpid(), signal.SIGINT)
        return real(a, b)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(KeyboardInterrupt):
        with whole_take(tmp_path, "paper-user000", replace=True):
            raise AssertionError("not reached: the signal ends it first")
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_a_take_another_program_writes_meanwhile_is_left_alone(tmp_path):
    """The writer took NAME-2 when NAME appeared after the check, and on an error the clean-up
    deleted the other program's NAME. Now the derived take is that name or nothing, and both
    the other program's take and the one being replaced stay."""
    from tactile.device.recordings.take import whole_take
    from tactile.device.recordings.writer import TakeWriter
    from tactile.device.sim import PenSimulator

    make_dataset(tmp_path, takes=1, textures=("paper",), seconds=1, seed=1)
    old = (tmp_path / "paper-user000.csv").read_bytes()
    info = PenSimulator("paper").info
    with pytest.raises(RecordingError, match=r"paper-user000.csv: written since the folder was "
                       r"checked .*; the take it was to replace waits as "
                       r"paper-user000.csv.replaced"):
        with whole_take(tmp_path, "paper-user000", replace=True):
            for suffix in (".csv", ".json"):  # the other program's take
                (tmp_path / f"paper-user000{suffix}").write_text("theirs")
            with TakeWriter(tmp_path, "paper", info, name="paper-user000", exact=True) as w:
                w.write(0, 0, np.zeros((3, 8), np.int16))
    assert (tmp_path / "paper-user000.csv").read_text() == "theirs"
    assert (tmp_path / "paper-user000.csv.replaced").read_bytes() == old
    assert not list(tmp_path.glob("paper-user000-*"))


def test_a_take_of_the_same_name_in_a_sub_folder_is_refused_even_with_force(tmp_path):
    """A second simulated dataset (or import) into the parent folder of one wrote takes of the
    same names beside it, and no command could then read the parent as a dataset."""
    from tactile.device.recordings import load_dataset

    nest = tmp_path / "nest"
    args = ("--takes", "1", "--seconds", "2", "--textures", "paper")
    assert cli("tactile-sim", "--dataset", str(nest / "old"), *args)[0] == 0
    for force in ((), ("--force",)):
        code, _, err = cli("tactile-sim", "--dataset", str(nest), *args, *force)
        assert code == 1 and err == (
            f"tactile-sim: error: {nest / 'old' / 'paper-user000.csv'}: a take of that name in "
            f"a sub-folder of {nest} (a dataset's takes need names of their own): choose "
            "another folder\n"), err
    assert [t.path for t in load_dataset(nest)] == [nest / "old" / "paper-user000.csv"]
    assert cli("tactile-sim", "--dataset", str(nest), "--takes", "1", "--seconds", "2",
               "--textures", "desk")[0] == 0  # other names: added beside it


def test_sigterm_in_a_simulated_dataset_removes_the_take_being_written(tmp_path):
    """``timeout`` or a service manager stops with SIGTERM, which left the take being written
    behind, cut (``complete: false``), and a rerun refused the folder; now as for Ctrl-C: the
    half-written take goes, one line, exit 143."""
    import signal
    import time

    out = tmp_path / "d"
    proc = subprocess.Popen([sys.executable, "-m", "tactile.device.commands.sim", "--dataset",
                             str(out), "--takes", "1", "--seconds", "100000", "--textures",
                             "paper"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        csv = out / "paper-user000.csv"
        end = time.monotonic() + 120  # only turns a hang into a failure
        while not (csv.exists() and csv.stat().st_size > 100_000):
            assert proc.poll() is None and time.monotonic() < end, proc.communicate()
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 143, err
    assert err.splitlines().count("tactile-sim: terminated (SIGTERM)") == 1, err
    assert list(out.iterdir()) == []


@pytest.mark.skipif(not Path("/proc/self").exists(), reason="no /proc on this system")
def test_sim_dataset_on_a_filesystem_without_a_disk_is_not_called_full():
    """`--dataset /proc/zz` said "the disk of /proc/zz has 0 bytes free": /proc has no disk
    at all; the folder's own error names what is wrong."""
    code, _, err = cli("tactile-sim", "--dataset", "/proc/zz", "--takes", "1", "--seconds", "1")
    assert code == 1 and err == ("tactile-sim: error: /proc/zz: cannot make the dataset folder "
                                 "(No such file or directory)\n"), err


def test_sim_dataset_prints_each_take_as_it_is_written(tmp_path):
    """tactile-sim --dataset printed nothing on stdout (the importers print each take's path as
    it is whole, so that a run stopped half-way says which takes stay)."""
    d = tmp_path / "d"
    code, out, err = cli("tactile-sim", "--dataset", str(d), "--takes", "2", "--seconds", "1",
                         "--textures", "paper,desk")
    assert code == 0, err
    assert out.splitlines() == [str(d / f"{t}-user{k:03d}.csv") for k in range(2)
                                for t in ("paper", "desk")]
    assert err.startswith(f"tactile-sim: 4 takes in {d} (")


def test_a_simulated_take_that_cannot_be_written_is_removed_and_the_line_says_so(tmp_path):
    """A write refused by the operating system (RLIMIT_FSIZE: EFBIG, as a full disk gives
    ENOSPC) removes the derived take being written, as the docs say; the line said "the take
    keeps what came before" (the recorder's words: its take is kept)."""
    import resource
    import signal

    def limit_files():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails instead of killing
        resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))

    out = tmp_path / "d"
    proc = subprocess.run([sys.executable, "-m", "tactile.device.commands.sim", "--dataset",
                           str(out), "--takes", "1", "--seconds", "2",
                           "--textures", "paper"], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr  # a short take fits under the limit
    proc = subprocess.run([sys.executable, "-m", "tactile.device.commands.sim", "--dataset",
                           str(out), "--takes", "1", "--seconds", "60", "--textures", "desk"],
                          capture_output=True, text=True, timeout=120, preexec_fn=limit_files)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr == (f"tactile-sim: error: {out / 'desk-user000.csv'}: cannot write (File "
                           "too large); the take is removed (the folder keeps whole takes "
                           "only)\n")
    assert sorted(p.name for p in out.iterdir()) == ["paper-user000.csv", "paper-user000.json"]


@pytest.mark.parametrize("link, says", [
    ("rate=200", "--link rate=...: give --rate instead (an option of its own)"),
    ("garbage=0.01&seconds=3", "--link seconds=...: give --seconds instead"),
    ("garbage=0.01&garbage=0.02", "sim:// option 'garbage' given twice"),
])
def test_sim_pty_refuses_a_link_key_given_twice_or_with_its_own_option(link, says):
    """--rate 300 --link rate=200 streamed at 200 Hz: the last key won, in silence."""
    code, _, err = cli("tactile-sim", "--pty", "--rate", "300", "--seconds", "0.1",
                       "--link", link)
    assert code == 1 and says in err and err.count("\n") == 1, err


def test_sim_pty_passes_a_number_with_an_exponent_to_the_link():
    """--seconds 1e20 reached the link as '1e 20' (a + in a query is a space): exit 1."""
    from tactile.device.commands.sim import PTY_ONLY, build_parser, link_query
    from tactile.device.sim.simlink import LinkConfig

    args = build_parser().parse_args(["--pty", "--seconds", "1e20", "--link", "garbage=0.01"])
    args.texture, args.speed = PTY_ONLY["texture"], PTY_ONLY["speed"]  # as main() fills them
    cfg = LinkConfig.from_query(link_query(args))
    assert (cfg.seconds, cfg.garbage, cfg.rate) == (1e20, 0.01, 100.0)


@pytest.mark.parametrize("option", [("--takes", "3"), ("--textures", "paper"),
                                    ("--first-take", "0"), ("--force",)])
def test_sim_pty_refuses_dataset_options(option):
    # --seconds: were an option let through, the pty would stream for 0.1 s, not forever
    code, _, err = cli("tactile-sim", "--pty", "--seconds", "0.1", *option)
    assert code == 1 and f"{option[0]} is not an option of --pty" in err, err


def _take(folder: Path, label: str, user: int, seqs: list[range]) -> None:
    """A take whose rows are the given seq ranges (the jumps between them are gaps)."""
    with TakeWriter(folder, label, pen_info(), "test", name=f"{label}-{user}",
                    extra={"user": user}) as w:
        for r in seqs:
            w.write(r.start, r.start * 10_000, np.zeros((len(r), 8), np.int16))


def test_data_summary_counts_takes_minutes_windows_and_gaps(tmp_path):
    _take(tmp_path, "paper", 0, [range(0, 120)])                   # 1 segment of 120
    _take(tmp_path, "paper", 1, [range(0, 60), range(70, 130)])    # 2 x 60, 10 lost (60..69)
    _take(tmp_path, "desk", 1, [range(0, 49), range(50, 150)])  # 49 (no window) + 100, 1 lost
    code, out, err = cli("tactile-data", str(tmp_path), "--json", "--window", "50", "--hop",
                         "25")
    assert code == 0, err
    s = json.loads(out)
    # windows by hand: (120-50)//25+1 = 3; 2 x ((60-50)//25+1) = 2; 0 + (100-50)//25+1 = 3
    assert s["total"]["windows"] == 8
    assert s["per_class"]["paper"]["windows"] == 5 and s["per_class"]["desk"]["windows"] == 3
    assert s["total"]["gaps"] == 2 and s["total"]["samples_lost"] == 11
    assert s["per_user"]["1"]["takes"] == 2 and s["per_user"]["1"]["classes"] == 2
    assert s["total"]["minutes"] == pytest.approx((120 + 120 + 149) / 100 / 60, abs=1e-3)
    assert s["sample_rate_hz"] == 100 and len(s["channels"]) == 8
    code, out, _ = cli("tactile-data", str(tmp_path), "--window", "50", "--hop", "25")
    assert code == 0 and "3 takes, 2 classes, 2 users" in out and "8 windows" in out
    code, _, err = cli("tactile-data", str(tmp_path / "none"))
    assert code == 1 and "not a folder" in err


def test_data_summary_counts_one_of_a_kind_in_the_singular(tmp_path):
    """`1 takes`, `1 gaps`: the counts now agree with their nouns."""
    _take(tmp_path, "paper", 0, [range(0, 60), range(70, 130)])
    code, out, err = cli("tactile-data", str(tmp_path))
    assert code == 0, err
    assert out.splitlines()[0] == (f"{tmp_path}: 1 take, 1 class, 1 user, 0.0 min, 1 gap "
                                   "(10 samples lost)"), out
    assert out.splitlines()[2] == "4 windows of 50 samples every 10", out


def test_data_summary_names_the_declared_high_rate_signals(tmp_path):
    """tactile-data listed a BioTac's 22 vibration sub-samples as 22 channels at 100 Hz and
    said nothing of the 2.2 kHz signal the takes declare."""
    from tactile.device.protocol import ChannelSpec, DeviceInfo

    info = DeviceInfo(100.0, tuple(ChannelSpec(n, "g") for n in ("p", "v_0", "v_1", "v_2")))
    for k in range(2):
        with TakeWriter(tmp_path, "paper", info, "test", name=f"t{k}",
                        extra={"signals": {"v": ["v_0", "v_1", "v_2"]}}) as w:
            w.write(0, 0, np.zeros((60, 4), np.int16))
    code, out, err = cli("tactile-data", str(tmp_path))
    assert code == 0 and out.splitlines()[2] == (
        "high-rate signals: v (3 sub-samples a frame, 300 Hz)"), out
    code, out, _ = cli("tactile-data", str(tmp_path), "--json")
    assert json.loads(out)["signals"] == [{"name": "v", "channels": 3, "rate_hz": 300.0}]
    meta = json.loads((tmp_path / "t1.json").read_text())
    del meta["signals"]
    (tmp_path / "t1.json").write_text(json.dumps(meta))
    code, out, _ = cli("tactile-data", str(tmp_path))
    assert out.splitlines()[2] == "high-rate signals: the takes declare different ones", out


def test_data_summary_lists_users_in_number_order(tmp_path):
    """Users were sorted as text (10 before 2, user10 before user2) in ``tactile-data`` and
    ``tactile-plot --summary``; runs of digits now sort as numbers."""
    for user in (10, 2, 1):
        _take(tmp_path, "paper", user, [range(0, 60)])
    code, out, err = cli("tactile-data", str(tmp_path), "--json")
    assert code == 0, err
    s = json.loads(out)
    assert s["users"] == list(s["per_user"]) == ["1", "2", "10"]
    code, out, _ = cli("tactile-data", str(tmp_path))
    rows = [line.split()[0] for line in out.splitlines()[out.splitlines().index(
        next(line for line in out.splitlines() if line.startswith("user "))) + 1:]]
    assert rows[:3] == ["1", "2", "10"], out
    assert sorted(["user10", "user2", "b", "a3", "a10", "bob2", "bob", "user", "7", "-"],
                  key=natural) == ["7", "-", "a3", "a10", "b", "bob", "bob2", "user", "user2",
                                   "user10"]


def test_plot_writes_pictures_and_refuses_what_it_cannot_plot(tmp_path):
    _take(tmp_path, "paper", 0, [range(0, 60), range(70, 130)])
    png = tmp_path / "take.png"
    code, out, err = cli("tactile-plot", str(tmp_path / "paper-0.csv"), "-o", str(png))
    assert code == 0, err
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    code, _, err = cli("tactile-plot", str(tmp_path), "--summary", "-o", str(tmp_path / "s.png"))
    assert code == 0 and (tmp_path / "s.png").stat().st_size > 10_000, err
    code, _, err = cli("tactile-plot", str(tmp_path), "-o", str(tmp_path / "x.png"))
    assert code == 1 and "add --summary" in err
    code, _, err = cli("tactile-plot", str(tmp_path / "paper-0.csv"), "-o",
                       str(tmp_path / "no" / "x.png"))
    assert code == 1 and "folder that exists" in err


def _hapmat_npz(path: Path, nan_in: str | None = None) -> Path:
    """A small file of the bundled HapMat form: 2 materials x 300 samples x 6 channels."""
    from tactile.device.recordings.hapmat import SOURCE_COLUMNS

    x = np.random.default_rng(0).normal(size=(2, 300, len(SOURCE_COLUMNS)))
    classes = np.array(["Paper", "Wood"])
    if nan_in is not None:
        x[list(classes).index(nan_in), 10, 0] = np.nan
    np.savez(path, X=x, classes=classes, channels=np.array(SOURCE_COLUMNS), fs_hz=100.0)
    return path


def test_an_import_stopped_half_way_lists_the_takes_it_wrote(tmp_path, monkeypatch, capsys):
    """Ctrl-C in an import said `interrupted` and nothing else: the paths went to stdout at
    the end only, so the takes it had written whole (which stay) were not listed."""
    from tactile.device.commands.import_hapmat import main

    ctrl_c_at_write(monkeypatch, 2)  # the second take
    out = tmp_path / "out"
    assert main([str(_hapmat_npz(tmp_path / "h.npz")), "--out", str(out)]) == 130
    said = capsys.readouterr()
    assert said.out == f"{out / 'hapmat-paper.csv'}\n" and said.err.endswith("interrupted\n")
    assert sorted(p.name for p in out.iterdir()) == ["hapmat-paper.csv", "hapmat-paper.json"]


def test_import_force_replaces_nothing_when_an_input_is_bad(tmp_path):
    out = tmp_path / "out"
    good = _hapmat_npz(tmp_path / "good.npz")
    assert cli("tactile-import-hapmat", str(good), "--out", str(out))[0] == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert sorted(before) == ["hapmat-paper.csv", "hapmat-paper.json", "hapmat-wood.csv",
                              "hapmat-wood.json"]
    bad = _hapmat_npz(tmp_path / "bad.npz", nan_in="Wood")  # the second material is bad
    code, _, err = cli("tactile-import-hapmat", str(bad), "--out", str(out), "--force")
    assert code == 1 and "Wood holds NaN" in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # nothing deleted


@pytest.mark.parametrize("classes, x_shape, message", [
    (["Paper", "Wood", "Cork", "Felt"], (5, 300, 6), "classes has 4 names for the 5 materials "
                                                     "of X (5, 300, 6)"),
    (["Paper", "Wood", "Cork", "Felt", "Silk", "Wool"], (5, 300, 6),
     "classes has 6 names for the 5 materials of X (5, 300, 6)"),
    ([["Paper", "Wood"]], (2, 300, 6), "classes is <U5 of shape (1, 2), expected a list of "
                                       "names (strings)"),
    (["Paper", "Wood"], (300, 6), "X is float64 of shape (300, 6), expected real numbers of "
                                  "shape (materials, samples, channels)"),
    (["Paper", "Wood", "paper"], (3, 300, 6), "more than one recording of one material: "
     "classes[0] 'Paper' and classes[2] 'paper' (one take per material; names that differ only "
     "in case or Unicode form are one class)"),
    (["Wood", "Paper", "Paper"], (3, 300, 6), "more than one recording of one material: "
     "classes[1] 'Paper' and classes[2] 'Paper' (one take per material; names that differ only "
     "in case or Unicode form are one class)"),
])
def test_import_hapmat_refuses_classes_that_do_not_match_x(tmp_path, classes, x_shape, message):
    """4 names for 5 materials dropped one material without a word, 6 names were an
    IndexError traceback, a 2-D classes wrote one take named after the array's repr, an X
    that is not 3-D was an IndexError traceback, and 'Paper' beside 'paper' (or 'Paper'
    twice) wrote hapmat-paper and hapmat-paper-2 of one label, and hapmat-paper-3 on a --force
    rerun. Each is one line naming the file, exit 1, and the takes already there stay."""
    from tactile.device.recordings.hapmat import SOURCE_COLUMNS

    out = tmp_path / "out"
    assert cli("tactile-import-hapmat", str(_hapmat_npz(tmp_path / "good.npz")), "--out",
               str(out))[0] == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    bad = tmp_path / "bad.npz"
    x = np.random.default_rng(1).normal(size=x_shape)
    np.savez(bad, X=x, classes=np.array(classes), channels=np.array(SOURCE_COLUMNS),
             fs_hz=100.0)
    for force in ((), ("--force",)):
        code, printed, err = cli("tactile-import-hapmat", str(bad), "--out", str(out), *force)
        assert (code, printed, err) == (1, "", f"tactile-import-hapmat: error: {bad}: "
                                        f"{message}\n")
        assert {p.name: p.read_bytes() for p in out.iterdir()} == before


@pytest.mark.parametrize("how, message", [
    ("npy", "not the HapMat .npz (not a .npz file: a .npz is a zip of numpy arrays)"),
    ("text", "not the HapMat .npz (not a .npz file: a .npz is a zip of numpy arrays)"),
    ("cut", "not the HapMat .npz (File is not a zip file)"),
    ("complex", "X is complex128 of shape (2, 30, 6), expected real numbers of shape "
                "(materials, samples, channels)"),
    ("empty", "X of shape (2, 0, 6) holds no samples"),
    ("bytes", "classes is |S5 of shape (2,), expected a list of names (strings)"),
    ("channels", "channels has 6 names for the 7 channels of X (2, 30, 7)"),
    ("channel twice", "channels names 'accel_x' twice"),
    ("label", "classes[1] 'Wo/od': label 'wo/od': must be 1-64 characters"),
])
def test_import_hapmat_refuses_an_npz_not_as_described(tmp_path, how, message):
    """Each was a traceback (IndexError, BadZipFile), a take of a wrong name or of the wrong
    column, or a line that did not name the file."""
    from tactile.device.recordings import import_hapmat
    from tactile.device.recordings.hapmat import SOURCE_COLUMNS

    x = np.zeros((2, 30, 6))
    arrays = {"X": x, "classes": np.array(["Paper", "Wood"]),
              "channels": np.array(SOURCE_COLUMNS), "fs_hz": 100.0}
    path = tmp_path / "bad.npz"
    if how == "npy":
        np.save(tmp_path / "bad.npy", x)
        path = tmp_path / "bad.npy"
    elif how == "text":  # numpy's own error advised loading it with allow_pickle
        path.write_text("not numpy\n")
    elif how == "cut":
        np.savez(path, **arrays)
        path.write_bytes(path.read_bytes()[:200])
    else:
        if how == "complex":
            arrays["X"] = x + 1j
        elif how == "empty":
            arrays["X"] = x[:, :0]
        elif how == "bytes":
            arrays["classes"] = np.array([b"Paper", b"Wood"])
        elif how == "channels":
            arrays["X"] = np.zeros((2, 30, 7))
        elif how == "channel twice":
            arrays["X"] = np.zeros((2, 30, 7))
            arrays["channels"] = np.array([*SOURCE_COLUMNS, "accel_x"])
        elif how == "label":
            arrays["classes"] = np.array(["Paper", "Wo/od"])
        np.savez(path, **arrays)
    with pytest.raises(RecordingError) as e:
        import_hapmat(path, tmp_path / "out")
    assert str(e.value).startswith(f"{path}: {message}"), e.value
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("fs_hz, message", [
    (0.0, "fs_hz 0: the sample rate must be in (0, 1e+06] Hz"),
    (-5.0, "fs_hz -5: the sample rate must be in (0, 1e+06] Hz"),
    (float("nan"), "fs_hz nan: the sample rate must be in (0, 1e+06] Hz"),
    (float("inf"), "fs_hz inf: the sample rate must be in (0, 1e+06] Hz"),
    (2e6, "fs_hz 2e+06: the sample rate must be in (0, 1e+06] Hz"),
    (np.array([100.0, 50.0]), "fs_hz is float64 of shape (2,), expected one number (the sample "
                              "rate, Hz)"),
])
def test_import_hapmat_refuses_a_bad_rate_as_a_bad_file(tmp_path, fs_hz, message):
    """An fs_hz of 0, -5 or NaN was the device's FrameError, exit code 2 (kept for ports and
    pens) and a line without the file; two rates were a TypeError traceback. Now exit 1, one
    line naming the file, and --force replaces nothing."""
    from tactile.device.recordings.hapmat import SOURCE_COLUMNS

    out = tmp_path / "out"
    assert cli("tactile-import-hapmat", str(_hapmat_npz(tmp_path / "good.npz")), "--out",
               str(out))[0] == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    bad = tmp_path / "bad.npz"
    np.savez(bad, X=np.zeros((2, 30, 6)), classes=np.array(["Paper", "Wood"]),
             channels=np.array(SOURCE_COLUMNS), fs_hz=fs_hz)
    code, printed, err = cli("tactile-import-hapmat", str(bad), "--out", str(out), "--force")
    assert (code, printed, err) == (1, "", f"tactile-import-hapmat: error: {bad}: {message}\n")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


@pytest.mark.parametrize("times, message", [
    ([0.0] * 10, "Paper 1.csv: time column does not rise (0 then 0 at line 3)"),
    ([1 - k / 100 for k in range(10)], "Paper 1.csv: time column does not rise (1 then 0.99 at "
                                       "line 3)"),
    ([k * 1e-7 for k in range(10)], "sample rate 10000000.0 Hz: must be in (0, 1e+06]"),
])
def test_import_hapmat_refuses_a_csv_whose_time_gives_no_rate(tmp_path, times, message):
    """A time column that stands still gave an infinite rate, the device's FrameError and exit
    code 2; one that falls gave a negative rate ('sample rates differ (Paper -100 Hz)'); one
    that gives a rate above the toolkit's limit, exit 2 too. Now one line naming the file (the
    folder for the rate), exit 1."""
    folder = tmp_path / "HapMat dataset"
    folder.mkdir()
    rows = "".join(f"{t!r},0,0,1,0,0,0\n" for t in times)
    (folder / "Paper 1.csv").write_text("time,accel_x,accel_y,accel_z,rota_x,rota_y,rota_z\n"
                                        + rows)
    code, printed, err = cli("tactile-import-hapmat", str(folder), "--out", str(tmp_path / "o"))
    assert (code, printed, err) == (1, "", f"tactile-import-hapmat: error: {folder}"
                                           f"{'/' if 'Paper' in message else ': '}{message}\n")
    assert not (tmp_path / "o").exists()


def test_plot_groups_many_channels_into_panels():
    from tactile.device.protocol import ChannelSpec, DeviceInfo
    from tactile.device.recordings.plot import LEGEND_MAX, panels

    names = ([f"f0_pac_{i:02d}" for i in range(22)] + ["f0_pdc", "f0_tac", "f0_tdc"]
             + [f"f0_ele_{i:02d}" for i in range(19)])
    info = DeviceInfo(100.0, tuple(ChannelSpec(n, "count", 1.0) for n in names))
    groups = {(p.name, p.unit): p.index for p in panels(info.channels)}
    assert {k: len(v) for k, v in groups.items()} == {
        ("f0_pac", "count"): 22, ("f0", "count"): 3, ("f0_ele", "count"): 19}
    assert sorted(i for v in groups.values() for i in v) == list(range(len(names)))
    assert len(groups[("f0", "count")]) <= LEGEND_MAX < len(groups[("f0_pac", "count")])
    pen = {(p.name, p.unit): len(p.index) for p in panels(pen_info().channels)}
    assert pen == {("pressure", "N"): 2, ("accel", "g"): 3, ("gyro", "deg/s"): 3}


def test_plot_of_too_many_panels_is_one_line_and_channels_choose_them(tmp_path):
    """A take of 200 channels that share no name prefix (the format allows 2,048) was drawn
    as one panel each: minutes and gigabytes, then nothing. More than MAX_PANELS is one line
    naming --channels, which picks the channels to draw (a declared signal whole, or its
    chosen sub-samples as plain channels)."""
    from tactile.device.protocol import ChannelSpec, DeviceInfo
    from tactile.device.recordings.plot import MAX_PANELS, _only, chosen, panels

    names = [f"c{i}" for i in range(200)] + ["v_0", "v_1"]
    info = DeviceInfo(100.0, tuple(ChannelSpec(n, "V", 1.0) for n in names))
    with TakeWriter(tmp_path, "x", info, "test", name="x",
                    extra={"signals": {"v": ["v_0", "v_1"]}}) as w:
        w.write(0, 0, np.zeros((60, len(names)), np.int16))
    png, take = tmp_path / "x.png", str(tmp_path / "x.csv")
    code, _, err = cli("tactile-plot", take, "-o", str(png))
    assert code == 1 and not png.exists() and err == (
        f"tactile-plot: error: x.csv: 201 panels (channels grouped by name before their last "
        f"'_part'), more than a picture shows ({MAX_PANELS}): choose some with --channels "
        "(e.g. --channels 'c0')\n"), err
    code, _, err = cli("tactile-plot", take, "-o", str(png), "--channels", "c1?,v_*")
    assert code == 0 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", err
    keep = chosen(info.channels, ("c1?", "v_0"))  # c10..c19; one sub-sample of the signal
    shown = _only(panels(info.channels, {}), keep)
    assert [(p.name, p.index) for p in shown] == [(f"c1{k}", [10 + k]) for k in range(10)] + [
        ("v", [200])]
    assert chosen(info.channels, ("v",), {"v": ["v_0", "v_1"]}) == {200, 201}  # by its name
    code, _, err = cli("tactile-plot", take, "-o", str(png), "--channels", "zz*")
    assert code == 1 and "--channels 'zz*' matches none of the take's channels: c0, c1" in err


def test_plot_draws_a_declared_high_rate_signal_as_one_trace_at_its_rate(tmp_path):
    """A BioTac's 2.2 kHz vibration was drawn as 22 overlapping 100 Hz traces (each every 22nd
    sample); a declared signal is now one trace, its sub-samples at their times in the order the
    declaration gives (here not the columns' order)."""
    from tactile.device.protocol import ChannelSpec, DeviceInfo
    from tactile.device.recordings.plot import _traces, panels

    r, rate, tone = 4, 100.0, 70.0  # 400 Hz signal; a 70 Hz tone aliases at 100 Hz
    order = [f"v_{k}" for k in range(r)]
    cols = ["p", *order[::-1]]  # columns: p, v_3, v_2, v_1, v_0
    info = DeviceInfo(rate, tuple(ChannelSpec(n, "g", 1.0) for n in cols))
    shown = panels(info.channels, {"v": order})
    assert [(p.name, p.index, p.signal) for p in shown] == [("p", [0], False),
                                                            ("v", [4, 3, 2, 1], True)]
    seq = np.r_[0:30, 40:70]  # a gap of 10 frames
    t = seq / rate
    values = np.zeros((len(seq), len(cols)))
    for k in range(r):  # sub-sample k of frame n is at n / rate + k / (r * rate)
        values[:, cols.index(f"v_{k}")] = np.sin(2 * np.pi * tone * (t + k / (r * rate)))
    segments = [(0, 30), (30, 60)]
    [(label, ts, ys)] = list(_traces(shown[1], info.channels, values, t, segments, rate))
    assert label == "v (4 per frame, 400 Hz)"
    assert len(ts) == len(ys) == 60 * r + 2 and np.isnan(ys[30 * r]) and np.isnan(ts[30 * r])
    ok = ~np.isnan(ts)
    assert np.all(np.diff(ts[:30 * r]) > 0) and np.all(np.diff(ts[30 * r + 1:-1]) > 0)
    np.testing.assert_allclose(np.diff(ts[:30 * r]), 1 / (r * rate), atol=1e-12)
    np.testing.assert_allclose(ys[ok], np.sin(2 * np.pi * tone * ts[ok]), atol=1e-12)
    with TakeWriter(tmp_path, "x", info, "test", name="x",
                    extra={"signals": {"v": order}}) as w:
        w.write(0, 0, np.round(values[:30] * 1000).astype(np.int16))
    png = tmp_path / "x.png"
    code, _, err = cli("tactile-plot", str(tmp_path / "x.csv"), "-o", str(png))
    assert code == 0 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", err


@pytest.mark.parametrize("name", ["noext", "x.txt"])
def test_plot_refuses_an_output_it_cannot_write_before_reading(tmp_path, name):
    code, _, err = cli("tactile-plot", str(tmp_path / "none.csv"), "-o", str(tmp_path / name))
    assert code == 1 and "name an image file ending in .png" in err  # not the missing take


@pytest.mark.parametrize("suffix", ["png", "pdf"])
def test_plot_to_a_file_the_system_refuses_is_one_line_naming_it_and_exit_4(tmp_path, suffix):
    """An image the operating system will not let grow (RLIMIT_FSIZE: EFBIG, as a full disk
    gives ENOSPC) said only '[Errno 27] File too large' and left a cut-short image (a PDF:
    a zlib traceback, exit 1)."""
    import resource
    import signal

    def limit_files():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails instead of killing
        resource.setrlimit(resource.RLIMIT_FSIZE, (2_000, 2_000))

    make_dataset(tmp_path / "d", takes=1, textures=("paper",), seconds=2, seed=0)
    png = tmp_path / f"p.{suffix}"
    proc = subprocess.run([sys.executable, "-m", "tactile.device.commands.plot",
                           str(tmp_path / "d" / "paper-user000.csv"), "-o", str(png)],
                          capture_output=True, text=True, timeout=120, preexec_fn=limit_files)
    assert proc.returncode == 4, proc.stderr
    assert proc.stderr == f"tactile-plot: error: {png}: cannot write (File too large)\n"
    assert list(tmp_path.glob("p.*")) == []  # no cut-short image, no temporary file
