"""The simulated link, the recorder and the recordings format, end to end."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import serial
from conftest import line_starting, listening, read_link, rows_in, start_and_signal

import tactile.device  # noqa: F401  (registers sim://)
from tactile.device.commands.record import main as record_main
from tactile.device.link import PortAbsent, open_port
from tactile.device.protocol import Gap, StreamDecoder, pen_info
from tactile.device.recordings import (
    Recorder,
    TakeWriter,
    import_hapmat,
    load_dataset,
    read_take,
    record,
)
from tactile.device.sim import LinkConfig, PenLink, PenSimulator, make_dataset
from tactile.device.sim.protocol_sim import forget_unplugs
from tactile.errors import ConfigError, DeviceError, RecordingError


def read_all(url: str) -> bytes:
    port = serial.serial_for_url(url, timeout=0.2)
    out = bytearray()
    while chunk := port.read(4096):
        out += chunk
    port.close()
    return bytes(out)


def assert_samples_are_the_pen(take, texture: str, seed: int, rate: float = 100.0):
    """Every stored row is the simulator's sample of that seq: nothing invented or reordered."""
    truth = PenSimulator(texture, seed, rate).read(int(take.seq.max()) + 1)
    np.testing.assert_array_equal(take.raw, truth[take.seq])


def test_sim_url_is_deterministic_and_complete():
    url = "sim://?texture=desk&seed=4&speed=max&seconds=3"
    a, b = read_all(url), read_all(url)
    assert a == b
    dec = StreamDecoder()
    dec.feed(a)
    assert dec.stats.samples == 300 and dec.stats.errors == 0 and dec.stats.header_frames == 3


@pytest.mark.parametrize(
    "url, message",
    [
        ("sim://?texture=velvet", "texture 'velvet'"),
        ("sim://?colour=red", "option 'colour' unknown"),
        ("sim://?seed=x", "seed='x'"),
        ("sim://?drop=2", "drop=2.0"),
    ],
)
def test_sim_url_rejects_bad_options(url, message):
    """A bad option is a ValueError, as pyserial raises for a bad setting: a port that can never
    open, not one that is absent for now (the tools do not wait for it)."""
    with pytest.raises(ConfigError, match=message):
        serial.serial_for_url(url)
    with pytest.raises(DeviceError, match=message) as err:
        open_port(url, 115200)
    assert not isinstance(err.value, PortAbsent)
    with pytest.raises(PortAbsent, match="cannot open /dev/no-such-pen"):
        open_port("/dev/no-such-pen", 115200)


def test_link_faults_are_counted_exactly_by_the_decoder():
    cfg = LinkConfig.from_query("texture=paper&seed=1&garbage=0.05&drop=0.03&seconds=30")
    link = PenLink(cfg)
    data = link.produce(10_000)
    dec = StreamDecoder()
    dec.feed(data + b"\x00")
    inj = link.injected
    assert inj.dropped_frames > 20 and inj.garbage_bytes > 500
    assert dec.stats.bytes_discarded == inj.garbage_bytes
    assert dec.stats.samples + dec.stats.samples_lost <= inj.samples
    # a dropped frame at the very end cannot be seen as a gap; all others are
    assert inj.dropped_samples - dec.stats.samples_lost in (0, 1)
    assert dec.stats.samples == inj.samples - inj.dropped_samples


@pytest.mark.parametrize("per_frame", [1, 4])
def test_the_link_gives_the_same_bytes_however_it_is_read(per_frame):
    """The bytes (and the faults) depend on the config only, not on how many samples each call
    asks for; a stall's samples count against ``seconds`` (one large call used to overshoot),
    and frames hold ``per_frame`` samples (only the stream's last may hold fewer)."""
    query = ("texture=desk&seed=8&garbage=0.05&drop=0.03&flip=0.001&stall=4:0.5&seconds=10"
             f"&per_frame={per_frame}")
    outputs = [read_link(query, chunk) for chunk in (1, 3, 7, 1000, 100_000)]
    assert all(o[:2] == outputs[0][:2] for o in outputs[1:])
    inj = outputs[0][1]
    assert inj.samples == 1000 and inj.stalled_samples == 50
    assert inj.frames == -(-950 // per_frame)
    sizes = outputs[-1][2]  # frames the decoder saw (dropped and garbled ones aside)
    assert set(sizes[:-1]) == {per_frame} and 1 <= sizes[-1] <= per_frame


def test_a_stall_ends_with_the_stream():
    """A stall past ``seconds`` loses only the samples before the end."""
    _, inj, _ = read_link("texture=desk&seed=1&stall=9.8:5&seconds=10", 1000)
    assert inj.samples == 1000 and inj.stalled_samples == 20


def test_recorder_over_sim_with_faults(tmp_path):
    url = "sim://?texture=mouse_pad&seed=5&speed=max&garbage=0.02&flip=0.0005&drop=0.02&stall=3:0.3"
    res = record(url, "mouse_pad", tmp_path, seconds=8, progress=False)
    assert len(res.takes) == 1
    take = read_take(res.takes[0])
    assert take.meta["complete"] and take.label == "mouse_pad" and not take.truncated
    assert take.channels == PenSimulator("paper").info.channel_names
    assert len(take.seq) >= 800
    assert_samples_are_the_pen(take, "mouse_pad", 5)
    gaps = take.meta["gaps"]
    assert any(g["missing"] == 30 for g in gaps), "the 0.3 s stall is a 30-sample gap"
    # every jump in seq is a recorded gap of exactly that size
    jumps = {int(take.seq[i + 1]): int(take.seq[i + 1] - take.seq[i] - 1)
             for i in np.flatnonzero(np.diff(take.seq) != 1)}
    assert jumps == {g["seq"]: g["missing"] for g in gaps}
    assert take.meta["decoder"]["crc_errors"] + take.meta["decoder"]["malformed"] > 0
    assert len(take.segments()) == len(gaps) + 1
    # the result counts what the take holds (the decoder's counters run on past its end)
    assert (res.samples, res.gaps, res.samples_lost) == (
        len(take.seq), len(gaps), sum(g["missing"] for g in gaps))


@pytest.mark.parametrize("fmt", ["binary", "csv"])
def test_recorder_survives_unplug(tmp_path, fmt):
    """The take goes on after the unplug, after a restart gap (a CSV board's rows carry no
    count: they joined the earlier rows as one run, without a break)."""
    forget_unplugs()
    url = f"sim://?texture=paper&seed=2&speed=max&unplug=2:0.4&format={fmt}"
    t0 = time.monotonic()
    res = record(url, "paper", tmp_path, seconds=5, progress=False)
    assert time.monotonic() - t0 >= 0.4  # it waited for the cable
    assert res.reconnects == 1
    take = read_take(res.takes[0])
    assert [g["reason"] for g in take.meta["gaps"]] == ["restart"]
    assert len(take.seq) >= 500 and np.all(np.diff(take.seq) > 0)
    assert len(take.segments()) == 2
    forget_unplugs()


def test_recorder_reads_csv_devices(tmp_path):
    res = record("sim://?texture=desk&seed=7&speed=max&format=csv", "desk", tmp_path, seconds=2,
                 progress=False)
    take = read_take(res.takes[0])
    assert take.channels[:2] == ("pressure_0", "pressure_1")  # from the names line
    assert len(take.seq) == 200
    sim = PenSimulator("desk", 7)
    scale = np.array([ch.scale for ch in sim.info.channels])
    offset = np.array([ch.offset for ch in sim.info.channels])
    truth = sim.read(200) * scale + offset  # a CSV device sends its values in units
    np.testing.assert_allclose(take.raw, truth, rtol=1e-6, atol=1e-9)  # 7 significant digits


def test_recorder_over_a_pty(tmp_path):
    sim = subprocess.Popen(
        [sys.executable, "-m", "tactile.device.commands.sim", "--pty", "--texture", "cardboard",
         "--seed", "9", "--speed", "4", "--seconds", "20",
         "--link", "garbage=0.02&flip=0.0005&drop=0.01"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        path = sim.stdout.readline().strip()
        assert path.startswith("/dev/")
        res = record(path, "cardboard", tmp_path, seconds=3, progress=False)
    finally:
        sim.send_signal(signal.SIGTERM)
        sim.wait(10)
    take = read_take(res.takes[0])
    assert len(take.seq) == 300 and take.meta["gaps"], "drops on the link are recorded gaps"
    assert take.meta["decoder"]["bytes_discarded"] > 0
    assert_samples_are_the_pen(take, "cardboard", 9)


def test_killed_recorder_leaves_a_readable_take(tmp_path):
    proc = subprocess.Popen(
        [sys.executable, "-m", "tactile.device.commands.record", "--port",
         "sim://?texture=paper&seed=1&speed=2", "--label", "paper", "--out", str(tmp_path),
         "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )
    try:  # killed once its CSV holds 250 rows (what it has written, not how long it ran)
        _wait_for(lambda: rows_in(tmp_path) >= 250, "250 rows in the CSV")
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(10)
    (csv,) = tmp_path.glob("*.csv")
    take = read_take(csv)
    assert not take.meta["complete"]
    assert len(take.seq) >= 250, len(take.seq)  # nothing it had written is lost
    assert_samples_are_the_pen(take, "paper", 1)


def test_ctrl_c_finishes_the_take(tmp_path):
    proc = subprocess.Popen(
        [sys.executable, "-m", "tactile.device.commands.record", "--port",
         "sim://?texture=desk&seed=1&speed=5", "--label", "desk", "--out", str(tmp_path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:  # interrupted once its CSV holds 101 rows
        _wait_for(lambda: rows_in(tmp_path) > 100, "101 rows in the CSV")
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    take = read_take(out.strip())
    assert take.meta["complete"] and len(take.seq) > 100


def test_ctrl_c_while_the_pen_is_unplugged_finishes_the_take(tmp_path, reap):
    proc = reap(subprocess.Popen(
        [sys.executable, "-m", "tactile.device.commands.record", "--port",
         "sim://?texture=desk&seed=1&speed=4&unplug=2:30", "--label", "desk", "--out",
         str(tmp_path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    ))
    for _ in range(500):  # until the pen is unplugged and the recorder waits for it
        line = proc.stderr.readline()
        if not line or "port lost" in line:
            break
    assert "port lost" in line
    proc.send_signal(signal.SIGINT)
    code = proc.wait(timeout=20)
    out, err = proc.stdout.read(), proc.stderr.read()
    assert code == 0 and "Traceback" not in err, err
    take = read_take(out.strip())
    assert take.meta["complete"] and 100 <= len(take.seq) <= 200  # before the unplug at 2 s


def test_one_stall_message_per_silence(tmp_path, capsys):
    """A 4 s silence with a 0.3 s stall timeout: one message when it starts and one when the
    data come back (it was one every 0.3 s), and no sample lost beyond the stall's own. (The
    silence is long so that a loaded machine still notices it: the loop runs at least once in
    the 3.7 s it has.)"""
    res = record("sim://?texture=paper&seed=3&speed=max&stall=0.5:4", "paper", tmp_path,
                 seconds=3.0, stall_timeout=0.3)
    err = capsys.readouterr().err
    starts = [ln for ln in err.splitlines() if ln.startswith("tactile-record: no data for")]
    ends = [ln for ln in err.splitlines() if ln.startswith("tactile-record: data again after")]
    assert len(starts) == 1 and len(ends) == 1, err
    assert float(ends[0].split()[5]) >= 3.7, ends  # the silence lasted 4 s (wall time)
    take = read_take(res.takes[0])
    assert res.stats["gaps"] == 1 and res.stats["samples_lost"] == 400
    assert len(take.seq) == 300


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc")
def test_a_signal_while_starting_stops_cleanly(tmp_path):
    """SIGINT while the recorder starts (from its imports on): exit 0, no take, no traceback,
    and the port is not opened (here it could not be: opening it anyway gave exit 2)."""
    code, out, err = start_and_signal(
        "tactile.device.commands.record:main", ["--port", "/dev/no-such-pen", "--label", "desk",
                                                "--out", str(tmp_path)], signal.SIGINT)
    assert code == 0 and out == "" and "Traceback" not in err, err
    assert err.splitlines()[-1] == "tactile-record: stopped by SIGINT before any data", err
    assert not list(tmp_path.glob("**/*.csv"))


def test_ctrl_c_before_any_data_is_a_stop_not_a_device_error(tmp_path, reap):
    """A port that gives nothing (loop://): Ctrl-C after the first stall message ends with exit
    0 and says no data came; without the signal, the same run would end as a device error."""
    proc = reap(subprocess.Popen(
        [sys.executable, "-m", "tactile.device.commands.record", "--port", "loop://", "--label",
         "desk", "--out", str(tmp_path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    # progress lines, then the stall message after 2 s without data
    line = line_starting(proc.stderr, "tactile-record: no data for")
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=20)
    assert line.startswith("tactile-record: no data for"), line
    assert proc.returncode == 0 and out == "", err
    assert err.splitlines()[-1] == "tactile-record: stopped by SIGINT before any data", err
    assert not list(tmp_path.glob("**/*.csv"))


def test_cli_errors_are_one_line(tmp_path, capsys):
    code = record_main(["--port", "sim://?texture=velvet", "--label", "x", "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "texture 'velvet'" in err[0]
    code = record_main(["--port", "/dev/does-not-exist", "--label", "x", "--out", str(tmp_path)])
    assert code == 2 and "does-not-exist" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:  # an argument error: argparse stops, with code 1
        record_main(["--port", "loop://", "--label", "x", "--out", str(tmp_path),
                     "--seconds", "-1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert stop.value.code == 1 and err == [
        "tactile-record: error: argument --seconds: -1 must be > 0.0 (see --help)"]


def test_dataset_of_simulated_users(tmp_path):
    paths = make_dataset(tmp_path, takes=2, textures=("paper", "non_contact"), seconds=2)
    assert len(paths) == 4
    takes = load_dataset(tmp_path)
    assert sorted((t.label, t.meta["user"]) for t in takes) == [
        ("non_contact", 0), ("non_contact", 1), ("paper", 0), ("paper", 1)]
    for t in takes:
        assert t.raw.shape == (200, 8) and t.meta["complete"]
    with pytest.raises(ConfigError, match="velvet"):
        make_dataset(tmp_path, 1, ("velvet",))


def test_a_finished_take_that_lost_rows_says_so(tmp_path, capsys):
    """A take its writer closed whose CSV lost rows since (a copy cut at a line's end): read,
    its rows kept, and what differs from its JSON named once, by whatever loads the dataset
    (tactile-data here; training, evaluation, export and plots alike)."""
    from tactile.device.commands.data import main as data_main

    (path,) = make_dataset(tmp_path, takes=1, textures=("paper",), seconds=2)
    assert read_take(path).mismatch is None  # as written: the JSON counts the rows
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(lines[:101]))  # the header and 100 of the 200 rows
    take = read_take(path)
    assert len(take.seq) == 100 and take.meta["complete"] and not take.truncated
    assert take.mismatch == ("holds 100 samples up to seq 99 where its JSON says the finished "
                             "take had 200 up to seq 199: rows were lost or added after "
                             "recording")
    assert data_main([str(tmp_path)]) == 0
    err = capsys.readouterr().err
    assert err == f"tactile-data: warning: {path}: {take.mismatch}\n"  # named as its errors
    load_dataset(tmp_path)
    assert capsys.readouterr().err == ""  # said once in a process
    meta = json.loads(path.with_suffix(".json").read_text())
    path.with_suffix(".json").write_text(json.dumps({**meta, "complete": False}))
    assert read_take(path).mismatch is None  # an unfinished take's JSON may lag: no claim


def test_tactile_plot_of_one_take_that_lost_rows_says_so(tmp_path, capsys):
    """tactile-plot TAKE.csv read the take by itself, without the line every dataset reader
    gives."""
    from tactile.device.commands.plot import main as plot_main

    (path,) = make_dataset(tmp_path, takes=1, textures=("desk",), seconds=2)
    path.write_text("".join(path.read_text().splitlines(keepends=True)[:101]))
    assert plot_main([str(path), "-o", str(tmp_path / "p.png")]) == 0
    err = capsys.readouterr().err
    assert err == f"tactile-plot: warning: {path}: {read_take(path).mismatch}\n"


def test_a_csv_without_its_json_is_named_not_skipped_silently(tmp_path, capsys):
    """A take whose JSON was lost (a copy that missed it) was left out of every command's
    dataset without a word."""
    make_dataset(tmp_path, takes=2, textures=("paper",), seconds=1)
    (tmp_path / "paper-user000.json").unlink()
    takes = load_dataset(tmp_path)
    assert [t.path.name for t in takes] == ["paper-user001.csv"]
    assert capsys.readouterr().err == (f"warning: {tmp_path / 'paper-user000.csv'}: a .csv "
                                       "without its .json, not read as a take\n")
    load_dataset(tmp_path)
    assert capsys.readouterr().err == ""  # said once in a process


def test_a_takes_json_without_its_csv_is_named(tmp_path, capsys):
    """A take whose CSV was lost left its JSON unread without a word. A run's metrics.json in
    a sub-folder is no take's and stays unnamed."""
    from tactile.device.commands.data import main as data_main

    make_dataset(tmp_path, takes=2, textures=("paper",), seconds=1)
    (tmp_path / "paper-user000.csv").unlink()
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "metrics.json").write_text('{"accuracy": 0.5}')
    assert data_main([str(tmp_path)]) == 0
    assert capsys.readouterr().err == (
        f"tactile-data: warning: {tmp_path / 'paper-user000.json'}: a .json without its .csv, "
        "no samples: not read as a take\n")


def test_a_take_copied_under_another_name_is_named(tmp_path, capsys):
    """A copied take was read twice without a word (one copy could train, the other test)."""
    import shutil

    make_dataset(tmp_path, takes=2, textures=("paper",), seconds=1)
    for suffix in (".csv", ".json"):
        shutil.copy(tmp_path / f"paper-user000{suffix}", tmp_path / f"paper-again{suffix}")
    assert len(load_dataset(tmp_path)) == 3  # read as it is
    assert capsys.readouterr().err == (
        f"warning: {tmp_path / 'paper-user000.csv'}: the same recording as "
        f"{tmp_path / 'paper-again.csv'} (label, samples and times): it is read twice\n")
    load_dataset(tmp_path)
    assert capsys.readouterr().err == ""  # said once in a process


def test_a_copied_take_that_lost_rows_gets_both_warnings(tmp_path, capsys):
    """The warnings shared one memory of the files they had named: a take that lost rows was
    never named as a copy too."""
    import shutil

    make_dataset(tmp_path, takes=1, textures=("paper",), seconds=1)
    csv = tmp_path / "paper-user000.csv"
    lines = csv.read_text().splitlines(keepends=True)
    csv.write_text("".join(lines[:-10]))  # the last 10 rows lost
    for suffix in (".csv", ".json"):
        shutil.copy(tmp_path / f"paper-user000{suffix}", tmp_path / f"paper-again{suffix}")
    load_dataset(tmp_path)
    err = capsys.readouterr().err.splitlines()
    assert sum("rows were lost or added after recording" in ln for ln in err) == 2, err
    assert sum("the same recording as" in ln for ln in err) == 1, err


def test_labels_that_differ_only_in_case_are_refused(tmp_path):
    """A take labelled 'Paper' beside takes labelled 'paper' trained as two classes of one
    surface, with no word; every command that reads the dataset now names both takes."""
    make_dataset(tmp_path, takes=2, textures=("paper", "desk"), seconds=1)
    meta = tmp_path / "paper-user001.json"
    doc = json.loads(meta.read_text())
    doc["label"] = "Paper"
    meta.write_text(json.dumps(doc))
    with pytest.raises(RecordingError, match=r"labels 'Paper' \(paper-user001\.csv\) and "
                       r"'paper' \(paper-user000\.csv\) differ only in case|labels 'paper' "
                       r"\(paper-user000\.csv\) and 'Paper' \(paper-user001\.csv\) differ"):
        load_dataset(tmp_path)
    doc["label"] = "paper"  # one spelling: read
    meta.write_text(json.dumps(doc))
    assert sorted({t.label for t in load_dataset(tmp_path)}) == ["desk", "paper"]
    # 'café' with an accented e and with an e and a combining accent look the same: one class
    for name, label in (("desk-user000", "caf\u00e9"), ("desk-user001", "cafe\u0301")):
        doc = json.loads((tmp_path / f"{name}.json").read_text())
        (tmp_path / f"{name}.json").write_text(json.dumps({**doc, "label": label}))
    with pytest.raises(RecordingError, match=r"differ only in case \(or Unicode form\)"):
        load_dataset(tmp_path)


def test_a_label_that_is_not_utf8_text_is_refused_before_the_port_opens(tmp_path, capsys):
    """`--label $'p\\xffx'` (a byte that is no UTF-8: Python keeps it as a lone surrogate) was
    recorded and read; training then failed at its end writing the class names."""
    code = record_main(["--port", "sim://?texture=paper&seed=1&speed=max", "--label",
                        "p\udcffx", "--out", str(tmp_path / "d"), "--seconds", "0.5"])
    assert code == 1 and not (tmp_path / "d").exists()
    assert "must be 1-64 characters of UTF-8 text" in capsys.readouterr().err


def test_hapmat_materials_that_differ_only_in_case_are_one_material(tmp_path):
    """"Paper 1.csv" and "paper 1.csv" both passed the check (before labels were lower-cased)
    and were written as hapmat-paper and hapmat-paper-2; with --force the second name's
    files were then deleted twice, ending the import half-way."""
    from tactile.device.recordings import import_hapmat

    src = tmp_path / "src"
    src.mkdir()
    rows = "\n".join(f"{k * 0.01:.2f},0,0,1,0,0,0" for k in range(10))
    for name in ("Paper 1.csv", "paper 1.csv", "Cork 1.csv"):
        (src / name).write_text("time,accel_x,accel_y,accel_z,rota_x,rota_y,rota_z\n" + rows
                                + "\n")
    with pytest.raises(RecordingError, match=r"more than one recording of one material"):
        import_hapmat(src, tmp_path / "out")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    (src / "paper 1.csv").unlink()
    assert len(import_hapmat(src, tmp_path / "out")) == 2
    assert len(import_hapmat(src, tmp_path / "out", force=True)) == 2


def test_hapmat_import(tmp_path):
    from conftest import HAPMAT

    if not HAPMAT.is_file():
        pytest.skip(f"shared HapMat data not found at {HAPMAT.name} beside the repository")
    import_hapmat(HAPMAT, tmp_path)
    takes = load_dataset(tmp_path)
    assert sorted(t.label for t in takes) == ["fabric", "leather", "metal", "paper", "wood"]
    raw = np.load(HAPMAT)["X"]
    fabric = next(t for t in takes if t.label == "fabric")
    assert fabric.meta["absent_channels"] == ["pressure_0", "pressure_1"]
    np.testing.assert_allclose(fabric.values()[:, :3], raw[0][:, :3], rtol=0, atol=0)
    np.testing.assert_allclose(fabric.values()[:, 3:], np.degrees(raw[0][:, 6:9].astype(float)))


def test_hapmat_import_from_the_upstream_csv_files(tmp_path):
    """The upstream folder (one `<Material> 1.csv` each, as in the source repository) gives the
    same takes as the bundled arrays, to the CSV text's 6 decimals."""
    from conftest import HAPMAT

    if not HAPMAT.is_file():
        pytest.skip(f"shared HapMat data not found at {HAPMAT.name} beside the repository")
    d = np.load(HAPMAT)
    folder = tmp_path / "HapMat dataset"
    folder.mkdir()
    names = ",".join(["time", *[str(c) for c in d["channels"]]])
    for k, material in enumerate(d["classes"]):
        rows = np.column_stack([d["t"], d["X"][k]])
        np.savetxt(folder / f"{material} 1.csv", rows, delimiter=",", header=names,
                   comments="", fmt=["%.2f"] + ["%.6f"] * d["X"].shape[2])
    import_hapmat(folder, tmp_path / "from_csv")
    import_hapmat(HAPMAT, tmp_path / "from_npz")
    a = {t.label: t for t in load_dataset(tmp_path / "from_csv")}
    b = {t.label: t for t in load_dataset(tmp_path / "from_npz")}
    assert sorted(a) == sorted(b) == ["fabric", "leather", "metal", "paper", "wood"]
    for label in a:
        assert a[label].info.sample_rate_hz == b[label].info.sample_rate_hz == 100.0
        assert a[label].channels == b[label].channels
        np.testing.assert_allclose(a[label].values(), b[label].values(), rtol=1e-6, atol=1e-4)
    (tmp_path / "empty_dir").mkdir()
    with pytest.raises(RecordingError, match="no .csv files"):
        import_hapmat(tmp_path / "empty_dir", tmp_path)
    (folder / "Paper 1.csv").write_text("t,ax\n0,1\n")
    with pytest.raises(RecordingError, match="not a HapMat recording"):
        import_hapmat(folder, tmp_path / "bad")


def _hapmat_folder(folder: Path, rates: dict[str, float], n: int = 300) -> dict:
    """A folder laid out as upstream's: `<Material> 1.csv`, a time column, 9 IMU columns."""
    folder.mkdir()
    rng = np.random.default_rng(5)
    cols = "time,accel_x,accel_y,accel_z,gyro_x,gyro_y,gyro_z,rota_x,rota_y,rota_z"
    data = {}
    for material, rate in rates.items():
        x = np.round(rng.normal(0, 0.1, (n, 9)), 6)
        rows = np.column_stack([np.arange(n) / rate, x])
        np.savetxt(folder / f"{material} 1.csv", rows, delimiter=",", header=cols,
                   comments="", fmt=["%.2f"] + ["%.6f"] * 9)
        data[material.lower()] = x
    return data


def test_hapmat_csv_folder_import_without_the_shared_data(tmp_path):
    data = _hapmat_folder(tmp_path / "HapMat dataset", {"Paper": 100.0, "Wood": 100.0})
    import_hapmat(tmp_path / "HapMat dataset", tmp_path / "out")
    takes = {t.label: t for t in load_dataset(tmp_path / "out")}
    assert sorted(takes) == ["paper", "wood"]
    for label, take in takes.items():
        assert take.info.sample_rate_hz == 100.0 and len(take.seq) == 300
        v = take.values()  # accel_x..z as they are, gyro_x..z from rota_x..z in deg/s
        np.testing.assert_allclose(v[:, :3], data[label][:, :3], rtol=0, atol=1e-12)
        np.testing.assert_allclose(v[:, 3:], np.degrees(data[label][:, 6:9]), rtol=1e-12)
    _hapmat_folder(tmp_path / "mixed", {"Paper": 100.0, "Wood": 50.0})
    with pytest.raises(RecordingError, match="sample rates differ"):
        import_hapmat(tmp_path / "mixed", tmp_path / "out2")
    short = tmp_path / "short"
    _hapmat_folder(short, {"Paper": 100.0})
    text = (short / "Paper 1.csv").read_text().splitlines()
    (short / "Paper 1.csv").write_text("\n".join([text[0], *(",".join(r.split(",")[:5])
                                                             for r in text[1:])]) + "\n")
    with pytest.raises(RecordingError, match="rows of 5 values under a header of 10"):
        import_hapmat(short, tmp_path / "out3")
    (short / "Paper 1.csv").write_text(text[0] + "\n")
    with pytest.raises(RecordingError, match="fewer than 2 data rows"):
        import_hapmat(short, tmp_path / "out4")


def test_hapmat_csv_folder_reads_csv_in_any_case(tmp_path):
    """'Paper 1.CSV' was skipped without a word (the folder was globbed for '*.csv'): that
    material was lost. It is read now, and refused when it and 'Paper 1.csv' would both be the
    paper take."""
    folder = tmp_path / "HapMat dataset"
    data = _hapmat_folder(folder, {"Paper": 100.0, "Wood": 100.0})
    (folder / "Paper 1.csv").rename(folder / "Paper 1.CSV")
    assert [p.name for p in import_hapmat(folder, tmp_path / "out")] == [
        "hapmat-paper.csv", "hapmat-wood.csv"]
    takes = {t.label: t for t in load_dataset(tmp_path / "out")}
    np.testing.assert_allclose(takes["paper"].values()[:, :3], data["paper"][:, :3], rtol=0,
                               atol=1e-12)
    (folder / "Paper 1.csv").write_text((folder / "Paper 1.CSV").read_text())
    with pytest.raises(RecordingError, match=r"more than one recording of one material: "
                       r"'Paper 1\.CSV' and 'Paper 1\.csv'"):
        import_hapmat(folder, tmp_path / "out2")
    assert not (tmp_path / "out2").exists()


def test_hapmat_csv_header_with_a_byte_order_mark_and_spaces(tmp_path):
    """A spreadsheet's CSV ('\ufefftime, accel_x, ...') was 'not a HapMat recording (no column
    'time')'."""
    folder = tmp_path / "HapMat dataset"
    data = _hapmat_folder(folder, {"Paper": 100.0})
    text = (folder / "Paper 1.csv").read_text().splitlines()
    (folder / "Paper 1.csv").write_bytes(
        "\n".join(["\ufeff" + ", ".join(text[0].split(",")), *text[1:]]).encode() + b"\n")
    import_hapmat(folder, tmp_path / "out")
    take = load_dataset(tmp_path / "out")[0]
    np.testing.assert_allclose(take.values()[:, :3], data["paper"][:, :3], rtol=0, atol=1e-12)


def test_hapmat_csv_folder_refuses_a_column_twice(tmp_path):
    """A header with a second accel_x had its first copy imported without a word."""
    folder = tmp_path / "HapMat dataset"
    _hapmat_folder(folder, {"Paper": 100.0, "Wood": 100.0})
    text = (folder / "Wood 1.csv").read_text().splitlines()
    (folder / "Wood 1.csv").write_text("\n".join(
        [text[0] + ",accel_x", *(row + ",5.0" for row in text[1:])]) + "\n")
    with pytest.raises(RecordingError) as e:
        import_hapmat(folder, tmp_path / "out3")
    assert str(e.value) == f"{folder / 'Wood 1.csv'}: column 'accel_x' appears twice in the header"
    assert not (tmp_path / "out3").exists()


def test_bad_recordings_are_refused(tmp_path):
    info = PenSimulator("paper").info
    with TakeWriter(tmp_path, "paper", info, name="t") as w:
        w.write(0, 0, np.zeros((5, 8), np.int16))
        with pytest.raises(RecordingError, match="out of order"):
            w.write(3, 0, np.zeros((1, 8), np.int16))
    csv = tmp_path / "t.csv"
    assert len(read_take(csv).seq) == 5
    text = csv.read_text()
    csv.write_text(text.replace("seq,t_us,pressure_0", "seq,t_us,pressure_9"))
    with pytest.raises(RecordingError, match=r"t.csv: its header does not match the metadata's "
                       r"channels: column 3 is 'pressure_9', the metadata says 'pressure_0' "
                       r"\(10 columns, the metadata 10\)$"):  # the first difference, named
        read_take(csv)
    csv.write_text("x" * 5000 + "\n" + text.split("\n", 1)[1])  # no take's header at all
    with pytest.raises(RecordingError, match=r"column 1 is 'x{60}'\.\.\. \(5000 chars\), the "
                       r"metadata says 'seq' \(1 column, the metadata 10\)"):  # cut, not all 5000
        read_take(csv)
    csv.write_text(text.replace(",gyro_z\n", "\n", 1))
    with pytest.raises(RecordingError, match=r"column 10 is missing, the metadata says 'gyro_z' "
                       r"\(9 columns"):
        read_take(csv)
    csv.write_text(text)  # the JSON's own list of the columns, edited (it was never read)
    meta_path = tmp_path / "t.json"
    meta = json.loads(meta_path.read_text())
    meta_path.write_text(json.dumps({**meta, "columns": meta["columns"][::-1]}))
    with pytest.raises(RecordingError, match=r"t.csv: key 'columns' differs from the CSV's "
                       r"header at column 1 \(10 names, the header 10\): one of the pair was "
                       r"edited$"):
        read_take(csv)
    for user in ([1, 2], None, "", " ", True):  # the split named "[1, 2]" and "None" users
        meta_path.write_text(json.dumps({**meta, "user": user}))
        with pytest.raises(RecordingError, match=r"key 'user' must be a non-empty string or an "
                           r"integer"):
            read_take(csv)
    meta_path.write_text(json.dumps(meta))
    csv.write_text(text + "2,0,1,1,1,1,1,1,1,1\n")
    with pytest.raises(RecordingError, match="seq not increasing"):
        read_take(csv)
    csv.write_text(text + "5,50000,1,1,1,nan,1,1,1,1\n")  # an integer take: refused, not cast
    with pytest.raises(RecordingError, match="NaN or inf"):
        read_take(csv)
    csv.write_text(text + "5,50000,1,1,1,1,1,1e300,1,1\n")  # finite, but not as float32
    with pytest.raises(RecordingError, match=r"data row 6 holds a value beyond float32's range "
                                             r"\(3.4e38\) in its unit: gyro_x = 1e\+300"):
        read_take(csv)
    csv.write_text(text + "5,50000,1,1,1,1,1,100000000000000000001,1,1\n")  # no int64 cast
    with pytest.raises(RecordingError, match=r"data row 6 holds a count beyond 2\^53 \(not read "
                                             r"exactly\): gyro_x = 1e\+20"):
        read_take(csv)
    csv.write_text(text + "\n" + "5,50000,1,1,1,1,1,1,1,1\n6,60000,1,1,1,1,1,1,1,12")
    cut = read_take(csv)  # a blank line before the cut last row changes nothing
    assert cut.truncated and cut.seq.tolist() == [0, 1, 2, 3, 4, 5]
    csv.write_text(text + "5,50000,1,1,1\n")
    with pytest.raises(RecordingError, match=r"data row 6 \(line 7\) has 5 values, expected 10"):
        read_take(csv)
    csv.write_text(text + "5,50000,1,1,1,x1,1,1,1,1\n")
    with pytest.raises(RecordingError, match=r"data row 6 \(line 7\): 'x1' is not a number"):
        read_take(csv)
    meta = json.loads((tmp_path / "t.json").read_text())
    (tmp_path / "t.json").write_text(json.dumps({**meta, "format": "other"}))
    with pytest.raises(RecordingError, match="not a tactile-recording"):
        read_take(csv)
    os.remove(tmp_path / "t.json")
    with pytest.raises(RecordingError, match="missing"):
        read_take(csv)
    with pytest.raises(RecordingError, match="no takes"):
        load_dataset(tmp_path)
    with pytest.raises(RecordingError, match="label"):
        TakeWriter(tmp_path, "a/b", info)


def test_a_value_past_float32_in_its_unit_is_refused(tmp_path):
    """The bound holds for count x scale: 1e30 counts of a channel scaled by 1e10."""
    from tactile.device.protocol import ChannelSpec, DeviceInfo

    info = DeviceInfo(100.0, (ChannelSpec("a", "N", 1.0), ChannelSpec("b", "N", 1e10)))
    with TakeWriter(tmp_path, "x", info, name="t") as w:
        w.write(0, 0, np.array([[1.5, 2.5], [1.5, 1e30], [3e38, 1.0]]))
    with pytest.raises(RecordingError, match=r"data row 2 holds a value beyond float32's range "
                                             r"\(3.4e38\) in its unit: b = 1e\+30"):
        read_take(tmp_path / "t.csv")


# -- crash consistency, the flush clock, hostile headers, full disks, untrusted takes ------------


def test_a_gap_is_in_the_take_as_soon_as_the_rows_after_it(tmp_path):
    """A restart (no seq jump) between two runs of rows: a reader that opens the take while the
    writer is still going (as after a SIGKILL) sees the rows and the gap between them."""
    info = pen_info()
    raw = np.arange(40 * 8, dtype=np.int16).reshape(40, 8)
    w = TakeWriter(tmp_path, "paper", info, name="live", flush_every_s=1e6)  # no clock tick
    try:
        w.write(0, 0, raw[:25])
        w.gap(Gap(25, 0, "restart"))
        w.write(25, 10_000, raw[25:])
        take = read_take(tmp_path / "live.csv")
    finally:
        w.close()
    assert not take.meta["complete"]
    assert take.seq.tolist() == list(range(40))
    np.testing.assert_array_equal(take.raw, raw)
    assert take.segments() == [(0, 25), (25, 40)]
    assert [(g["seq"], g["reason"], g["row"]) for g in take.meta["gaps"]] == [(25, "restart", 25)]
    assert "# gap seq=25 missing=0 reason=restart\n" in (tmp_path / "live.csv").read_text()


def _wait_for(predicate, what: str, seconds: float = 60.0):
    """Poll until ``predicate()`` is true; fail after ``seconds`` (a deadline, not a measure)."""
    deadline = time.monotonic() + seconds
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} did not happen within {seconds} s")
        time.sleep(0.01)


def test_the_clock_flushes_during_a_silence(tmp_path):
    """Rows written, then nothing more: the JSON catches up on the clock, not on a next write."""
    w = TakeWriter(tmp_path, "paper", pen_info(), name="quiet", flush_every_s=0.05)
    try:
        w.write(0, 0, np.ones((7, 8), np.int16))
        w.gap(Gap(7, 3, "drop"))
        meta = lambda: json.loads((tmp_path / "quiet.json").read_text())  # noqa: E731
        _wait_for(lambda: meta()["samples"] == 7 and meta()["gaps"], "a flush by the clock")
    finally:
        w.close()
    assert meta()["complete"] and meta()["gaps"] == [{"seq": 7, "missing": 3, "reason": "drop"}]


HOSTILE_NAMES = ("a,b", "x\ny", "q\"uote", "#hash", "100%", "tab\there", "ünïcødé", "雨", "ok")


def test_hostile_channel_names_round_trip(tmp_path):
    """Names with a comma, a newline, a quote, '#', '%', a tab or non-ASCII letters (a device
    header can say anything): the recorder writes a take its reader accepts, names intact."""
    from tactile.device.protocol import ChannelSpec, DeviceInfo, encode_header, encode_samples

    info = DeviceInfo(100.0, tuple(ChannelSpec(n, "ü") for n in HOSTILE_NAMES), device="ペン")
    raw = np.arange(30 * len(HOSTILE_NAMES), dtype=np.int16).reshape(30, -1)
    stream = encode_header(info) + b"".join(
        encode_samples(k, k * 10_000, raw[k : k + 1]) for k in range(30))
    rec, dec = Recorder(tmp_path, "paper", "test"), StreamDecoder()
    rec.handle(dec.feed(stream), dec)
    rec.close(dec)
    take = read_take(rec.result.takes[0])
    assert take.channels == HOSTILE_NAMES and take.meta["complete"]
    np.testing.assert_array_equal(take.raw, raw)
    head = rec.result.takes[0].read_text(encoding="utf-8").splitlines()[0]
    assert head == "seq,t_us,a%2Cb,x%0Ay,q%22uote,%23hash,100%25,tab%09here,ünïcødé,雨,ok"


@pytest.mark.parametrize("seconds, rows", [("1.1", 110), ("2.3", 230), ("0.29", 29),
                                           ("0.001", 1)])
def test_record_seconds_of_any_decimal_stops_with_the_samples_that_cover_them(
        tmp_path, seconds, rows):
    """--seconds 1.1 at 100 Hz is 110.00000000000001 samples: the take stopped at 110 while
    the goal stayed a fraction away, and the command never ended (2.3 kept 229). Run apart,
    so that a goal never reached fails by the timeout instead of hanging the suite."""
    out = tmp_path / "d"
    proc = subprocess.run(
        [sys.executable, "-m", "tactile.device.commands.record", "--port",
         "sim://?texture=paper&seed=1&speed=max", "--label", "paper", "--out", str(out),
         "--seconds", seconds, "--quiet"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    (take,) = out.glob("*.csv")
    got = read_take(take)
    assert len(got.raw) == rows and got.meta["complete"] is True


def test_record_seconds_beyond_what_a_float_counts_is_no_end():
    """--seconds 1e307 at 100 Hz: more samples than a float holds; math.ceil of inf raised
    (a traceback) where it had recorded until stopped."""
    from tactile.device.recordings.recorder import samples_for

    assert samples_for(1e307, 100.0) == samples_for(math.inf, 100.0) == math.inf
    assert samples_for(1.1, 100.0) == 110 and samples_for(2.3, 100.0) == 230


def test_record_keeps_the_user_and_the_metadata_given(tmp_path, capsys):
    """tactile-record wrote no `user` (training's default split then made each take its own
    group) and no session: a script had to edit each take. --user and --meta KEY=VALUE go into
    the take's JSON (a whole number as one, for ranges); a key of the format, one given twice
    or not KEY=VALUE is one line, exit 1, before the port opens."""
    out = tmp_path / "d"
    assert record_main(["--port", "sim://?texture=paper&seed=1&speed=max", "--label", "paper",
                        "--out", str(out), "--seconds", "0.5", "--user", "alice", "--meta",
                        "session=2", "--meta", "room=lab 1", "--quiet"]) == 0
    (take,) = out.glob("*.csv")
    meta = read_take(take).meta
    assert (meta["user"], meta["session"], meta["room"]) == ("alice", 2, "lab 1")
    capsys.readouterr()
    for args, says in ((["--meta", "label=desk"], "--meta label: the recordings format's own "
                                                  "key; choose another"),
                       (["--meta", "session"], "--meta 'session': expected KEY=VALUE"),
                       (["--user", "a", "--meta", "user=b"], "--meta user: give it as --user"),
                       (["--meta", "n=1", "--meta", "n=2"], "--meta n: given twice")):
        assert record_main(["--port", "sim://?texture=paper", "--label", "paper", "--out",
                            str(tmp_path / "no"), *args]) == 1
        err = capsys.readouterr().err
        assert err.startswith(f"tactile-record: error: {says}"), err
    assert not (tmp_path / "no").exists()


def test_a_csv_board_opened_mid_run_records_under_the_names_it_repeats(tmp_path):
    """A CSV board that repeats its names line, recorded from the middle of its run, gave a
    take of ch0..ch2 with a `rejected` gap at every names line (no sample was lost); now the
    take has the board's names and no gap. Rows still held for want of names when the
    recording ends are written, not dropped."""
    def rows(first, n):
        return b"".join(b"%d,%d,%d\n" % (i, -i, 2 * i) for i in range(first, first + n))

    rec, dec = Recorder(tmp_path / "named", "paper", "test"), StreamDecoder()
    rec.handle(dec.feed(b"7,-7,14\n" + rows(8, 92) + b"a,b,c\n" + rows(100, 100)
                        + b"a,b,c\n" + rows(200, 5)), dec)
    rec.close(dec)
    take = read_take(rec.result.takes[0])
    assert take.channels == ("a", "b", "c") and take.meta["gaps"] == []
    assert take.raw[:, 0].tolist() == list(range(8, 205)) and take.seq.tolist() == list(
        range(197))
    rec, dec = Recorder(tmp_path / "unnamed", "paper", "test"), StreamDecoder()
    assert rec.handle(dec.feed(b"7,-7,14\n" + rows(8, 40)), dec) == 0  # held for names
    rec.close(dec)
    take = read_take(rec.result.takes[0])
    assert take.channels == ("ch0", "ch1", "ch2") and take.raw[:, 0].tolist() == list(
        range(8, 48)) and take.meta["complete"]


def test_a_label_spelled_otherwise_in_the_folder_is_refused_before_the_port_opens(tmp_path):
    """`tactile-record --label Paper` into a folder of `paper` takes wrote its take, and left
    a folder every reader refuses ("differ only in case"); it now stops before the port opens,
    naming the spelling the folder has, and writes nothing."""
    pen = record("sim://?texture=paper&seed=1&speed=max", "paper", tmp_path, seconds=0.5,
                 progress=False).takes[0]
    with pytest.raises(RecordingError) as e:
        Recorder(tmp_path, "Paper", "test")
    assert str(e.value) == (f"{tmp_path}: holds takes labelled 'paper' ({pen.stem}.json), the "
                            "label 'Paper' but for case (or Unicode form): one class, which a "
                            "dataset spells one way; record it as 'paper'")
    assert record_main(["--port", "sim://?texture=paper&seed=1&speed=max", "--label", "PAPER",
                        "--out", str(tmp_path), "--seconds", "0.5"]) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == [pen.name, pen.with_suffix(".json").name]
    Recorder(tmp_path, "paper", "test")  # the folder's own spelling, and other classes: fine
    Recorder(tmp_path, "desk", "test")


def test_a_folder_of_another_devices_takes_is_refused_before_a_take(tmp_path, capsys):
    """Recording a 3-channel device into a folder of pen takes: refused at its header, before
    any take (exit 1, one line naming the folder and a take of it); the pen's take is
    untouched. A device that changes mid-recording gets its take written, with a warning."""
    from tactile.device.protocol import ChannelSpec, DeviceInfo, Header, Samples

    pen = record("sim://?texture=paper&seed=1&speed=max", "paper", tmp_path, seconds=0.5,
                 progress=False).takes[0]
    before = pen.read_bytes()
    other = DeviceInfo(200.0, tuple(ChannelSpec(n, "N") for n in ("a", "b", "c")))
    rec, dec = Recorder(tmp_path, "desk", "test"), StreamDecoder()
    with pytest.raises(RecordingError, match=rf"{tmp_path}: holds takes of another device "
                       rf"\({pen.stem}\.json: 8 channels, these takes 3\).*nothing recorded"):
        rec.handle([Samples(0, 0, np.ones((4, 3), np.int16)), Header(other)], dec)
    rec.close(dec)
    assert rec.result.takes == [] and rec.result.unrecorded == 4
    volts = pen_info()
    volts = DeviceInfo(100.0, (ChannelSpec(volts.channels[0].name, "V"), *volts.channels[1:]))
    with pytest.raises(RecordingError, match=r"\.json: pressure_0 in 'N', these takes in 'V'\)"):
        Recorder(tmp_path, "desk", "test").handle([Header(volts)], StreamDecoder())
    assert sorted(p.name for p in tmp_path.iterdir()) == [pen.name, pen.with_suffix(".json").name]
    assert pen.read_bytes() == before

    # the pen first, then the other device on the same port: both takes, one warning
    raw = np.arange(10 * 8, dtype=np.int16).reshape(10, 8)
    rec, dec = Recorder(tmp_path, "paper", "test"), StreamDecoder()
    rec.handle([Header(pen_info()), Samples(0, 0, raw), Header(other, changed=True),
                Samples(0, 0, np.ones((5, 3), np.int16))], dec)
    rec.close(dec)
    assert [read_take(p).raw.shape for p in rec.result.takes] == [(10, 8), (5, 3)]
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("tactile-record: warning: ") and \
        "the new take is written all the same" in err[0]


def test_samples_that_do_not_fit_the_header_are_a_gap_not_a_crash(tmp_path):
    """3-channel samples before the 8-channel header (and one after it): left out as a
    'rejected' gap of their size; the 8-channel samples are all kept; the take is complete."""
    from tactile.device.protocol import Header, Samples

    info = pen_info()
    raw = np.arange(20 * 8, dtype=np.int16).reshape(20, 8)
    rec, dec = Recorder(tmp_path, "paper", "test"), StreamDecoder()
    rec.handle([Samples(0, 0, np.ones((3, 3), np.int16)), Header(info),
                Samples(3, 30_000, raw[:10]), Samples(13, 130_000, np.ones((2, 3), np.int16)),
                Samples(15, 150_000, raw[10:])], dec)
    rec.close(dec)
    take = read_take(rec.result.takes[0])
    assert take.meta["complete"] and rec.result.samples == 20
    np.testing.assert_array_equal(take.raw, raw)
    assert take.seq.tolist() == [*range(3, 13), *range(15, 25)]
    assert [(g["seq"], g["missing"], g["reason"]) for g in take.meta["gaps"]] == [
        (3, 3, "rejected"), (15, 2, "rejected")]
    assert take.segments() == [(0, 10), (10, 20)]


def test_a_full_disk_names_the_file_and_keeps_what_was_written(tmp_path, monkeypatch, capsys):
    """The disk fills mid-take (writes fail with ENOSPC after 30 kB): exit 1, one line naming
    the CSV, no traceback; the take on disk reads back, is not complete, and every row in it is
    the pen's."""
    import errno

    from tactile.device.recordings import writer as recording

    real, room = recording._write_all, {"bytes": 30_000}

    def full_disk(fd, data):
        if len(data) > room["bytes"]:
            real(fd, bytes(data[: room["bytes"]]))
            room["bytes"] = 0
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        room["bytes"] -= len(data)
        real(fd, data)

    monkeypatch.setattr(recording, "_write_all", full_disk)
    code = record_main(["--port", "sim://?texture=paper&seed=3&speed=max", "--label", "paper",
                        "--out", str(tmp_path), "--seconds", "30", "--quiet"])
    err = capsys.readouterr().err
    (csv,) = tmp_path.glob("*.csv")
    assert code == 1 and "Traceback" not in err
    assert f"tactile-record: error: {csv}: cannot write (No space left on device)" in err
    monkeypatch.undo()
    take = read_take(csv)
    assert not take.meta["complete"] and len(take.seq) > 100
    assert csv.stat().st_size <= 30_000
    assert_samples_are_the_pen(take, "paper", 3)
    assert not list(tmp_path.glob("*.tmp"))


def _meta_of(tmp_path) -> dict:
    with TakeWriter(tmp_path, "paper", pen_info(), name="t") as w:
        w.write(0, 0, np.zeros((5, 8), np.int16))
    return json.loads((tmp_path / "t.json").read_text())


@pytest.mark.parametrize("edit, message", [
    (lambda m: "[" * 100_000 + "]" * 100_000, "not valid JSON (nested too deeply)"),
    (lambda m: "[1, 2]", "the top level must be an object, got a list of 2"),
    (lambda m: "3", "the top level must be an object, got 3"),
    (lambda m: "null", "the top level must be an object, got None"),
    # a key given twice kept its last value, the other dropped unseen
    (lambda m: json.dumps(m)[:-1] + ', "label": "desk"}',
     "key 'label' given twice in one object"),
    (lambda m: json.dumps(m).replace('"unit":', '"name": "x", "unit":', 1),
     "key 'name' given twice in one object"),
    (lambda m: '"\\ud800 x"', "the top level must be an object"),
    (lambda m: {**m, "version": True}, "key 'version' must be 1 or 2, got True"),
    (lambda m: {**m, "version": 3}, "not a tactile-recording file of version 1 or 2"),
    (lambda m: {k: v for k, v in m.items() if k != "device"}, "key 'device' missing"),
    (lambda m: {**m, "label": 7}, "key 'label' must be a non-empty string, got 7"),
    # the recorder's label rule, which an edited JSON escaped (a/b trained as a class)
    (lambda m: {**m, "label": "a/b"}, "key 'label': label 'a/b': must be 1-64 characters"),
    (lambda m: {**m, "label": " paper"}, "key 'label': label ' paper': must be"),
    (lambda m: {**m, "gaps": "many"}, "key 'gaps' must be a list, got 'many'"),
    (lambda m: {**m, "gaps": [3]}, "gaps[0] must be an object, got 3"),
    (lambda m: {**m, "gaps": [{"seq": "x", "missing": 0, "reason": "drop"}]},
     "key 'gaps[0].seq' must be an integer >= 0, got 'x'"),
    (lambda m: {**m, "gaps": [{"seq": 2, "reason": "drop"}]}, "key 'gaps[0].missing' missing"),
    (lambda m: {**m, "complete": "yes"}, "key 'complete' must be true or false"),
    (lambda m: {**m, "device": [1]}, "key 'device' must be an object"),
    (lambda m: {**m, "device": {**m["device"], "sample_rate_hz": -1}},
     "key 'device': sample rate -1.0 Hz"),
    (lambda m: {**m, "device": {**m["device"], "sample_rate_hz": "100"}},
     "key 'device.sample_rate_hz' must be a number, got '100'"),
    (lambda m: {**m, "device": {**m["device"], "channels": {}}},
     "key 'device.channels' must be a non-empty list"),
    (lambda m: {**m, "device": {**m["device"], "channels": [7]}},
     "device.channels[0] must be an object"),
    (lambda m: {**m, "device": {**m["device"], "channels": [{"name": "a", "unit": "N",
                                                             "gain": 2}]}},
     "key 'device.channels[0].gain' unknown"),
    (lambda m: {**m, "device": {**m["device"], "channels": [{"name": "a", "unit": "N",
                                                             "scale": 0}] * 8}},
     "key 'device': channel a: scale must be finite, non-zero"),
    (lambda m: {**m, "device": {**m["device"], "channels": [{"name": "\ud800", "unit": "N"}]}},
     "key 'device'"),
])
def test_untrusted_take_json_is_one_line_naming_file_and_key(tmp_path, edit, message):
    meta = _meta_of(tmp_path)
    new = edit(meta)
    (tmp_path / "t.json").write_text(new if isinstance(new, str) else json.dumps(new))
    with pytest.raises(RecordingError) as err:
        read_take(tmp_path / "t.csv")
    text = str(err.value)
    assert text.startswith(f"{tmp_path / 't.json'}: ") and message in text, text
    assert "\n" not in text


def test_bad_gap_lines_are_named(tmp_path):
    _meta_of(tmp_path)
    csv = tmp_path / "t.csv"
    text = csv.read_text()
    csv.write_text(text + "# gap seq=x missing=0 reason=drop\n")
    with pytest.raises(RecordingError, match=r"t.csv: line 7 is not a gap line"):
        read_take(csv)
    csv.write_text(text + "# gap seq=9 missing=4 reason=drop\n9,90000,1,1,1,1,1,1,1,1\n")
    take = read_take(csv)
    assert take.seq.tolist() == [0, 1, 2, 3, 4, 9] and take.segments() == [(0, 5), (5, 6)]
    assert take.raw.dtype == np.int64  # the gap line's letters do not make it a float take


def test_version_1_takes_still_read(tmp_path):
    """A take written before gap lines existed: its gaps come from the JSON, by seq."""
    _meta_of(tmp_path)
    meta = json.loads((tmp_path / "t.json").read_text())
    meta.update(version=1, gaps=[{"seq": 3, "missing": 0, "reason": "restart"}])
    (tmp_path / "t.json").write_text(json.dumps(meta))
    take = read_take(tmp_path / "t.csv")
    assert take.segments() == [(0, 3), (3, 5)]


def test_a_failed_clock_flush_is_raised_at_close(tmp_path, monkeypatch):
    """The JSON cannot be rewritten during a silence (only the clock runs then): close()
    raises it, naming the JSON, and the take is not marked complete; a block that raised does
    not mark its take complete either."""
    import errno

    from tactile.device.recordings import writer as recording

    def no_space(path, text):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    w = TakeWriter(tmp_path, "paper", pen_info(), name="q", flush_every_s=0.02)
    w.write(0, 0, np.ones((3, 8), np.int16))
    monkeypatch.setattr(recording, "_replace_file", no_space)
    _wait_for(lambda: w.error is not None, "a failed flush by the clock")
    with pytest.raises(RecordingError, match=r"q\.json: cannot write \(No space left"):
        w.close()
    monkeypatch.undo()
    take = read_take(tmp_path / "q.csv")
    assert not take.meta["complete"] and take.seq.tolist() == [0, 1, 2]
    with pytest.raises(ZeroDivisionError), TakeWriter(tmp_path, "paper", pen_info(), name="r") as w:
        w.write(0, 0, np.ones((3, 8), np.int16))
        1 / 0  # noqa: B018
    assert not read_take(tmp_path / "r.csv").meta["complete"]


@pytest.mark.parametrize("json_text", ['{"format": "tactile-recording", "version": 1, "label": '
                                       '"paper", "device": {"sample_rate_hz": -1, "channels": '
                                       '[{"name": "a", "unit": "N"}]}}', "[" * 100_000, "null"])
def test_a_command_reading_a_bad_take_says_one_line_and_exits_1(tmp_path, json_text):
    """A dataset command over a take whose JSON is hostile: exit 1 (bad input, not the device's
    2), one line naming the JSON, no traceback."""
    _meta_of(tmp_path)
    (tmp_path / "t.json").write_text(json_text)
    proc = subprocess.run([sys.executable, "-c", "import sys; from tactile.device.commands.data "
                           "import main; sys.exit(main())", str(tmp_path)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.count("\n") == 1 and str(tmp_path / "t.json") in proc.stderr


def test_frames_of_another_width_before_the_header_through_the_decoder(tmp_path):
    """The issue's case on the wire: 3-channel frames, then the 8-channel header and frames.
    Whatever the decoder makes of the first ones, the take is complete, holds all 8-channel
    samples, and says how many samples it left out."""
    from tactile.device.protocol import Samples, encode_header, encode_samples

    info = pen_info()
    raw = np.arange(40 * 8, dtype=np.int16).reshape(40, 8)
    stream = b"".join(encode_samples(k, k * 10_000, np.ones((1, 3), np.int16))
                      for k in range(5))
    stream += encode_header(info) + b"".join(
        encode_samples(k, k * 10_000, raw[k - 5 : k - 4]) for k in range(5, 45))
    rec, dec = Recorder(tmp_path, "paper", "test"), StreamDecoder()
    events = dec.feed(stream)
    narrow = sum(len(e.raw) for e in events if isinstance(e, Samples) and e.raw.shape[1] == 3)
    rec.handle(events, dec)
    rec.close(dec)
    take = read_take(rec.result.takes[0])
    assert take.meta["complete"]
    np.testing.assert_array_equal(take.raw, raw)
    assert sum(g["missing"] for g in take.meta["gaps"] if g["reason"] == "rejected") == narrow


def test_a_file_size_limit_stops_the_real_recorder_cleanly(tmp_path):
    """The operating system refuses the CSV's growth (RLIMIT_FSIZE at 20 kB, a real EFBIG from
    write(2), as a full disk gives ENOSPC): tactile-record exits 1 with one line naming the CSV;
    the take keeps the rows that fit, every one the pen's, and is not complete."""
    import resource

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails instead of killing
        resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))

    proc = subprocess.run(
        [sys.executable, "-c", "import sys; from tactile.device.commands.record import main; "
         "sys.exit(main())", "--port", "sim://?texture=desk&seed=4&speed=max",
         "--label", "desk", "--out", str(tmp_path), "--seconds", "60", "--quiet"],
        capture_output=True, text=True, timeout=120, preexec_fn=limit)
    (csv,) = tmp_path.glob("*.csv")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert f"tactile-record: error: {csv}: cannot write (File too large)" in proc.stderr
    take = read_take(csv)
    assert not take.meta["complete"] and len(take.seq) > 100
    assert_samples_are_the_pen(take, "desk", 4)


def test_samples_before_any_header_are_held_in_bounds_and_never_lost_silently(tmp_path,
                                                                             monkeypatch):
    """A device that sends samples frames and no header: what is held is counted in samples
    (here frames of 32), and one sample past the bound is an error that says none of them is
    recorded; a recording that ends before a header counts them as unrecorded; held samples
    that come before a reconnection are given up (whose header they were cannot be known),
    said, and counted; samples held when the header comes are all written."""
    from tactile.device.link import Reconnected
    from tactile.device.protocol import Header, Samples
    from tactile.device.recordings import recorder

    monkeypatch.setattr(recorder, "MAX_EARLY", 1000)
    frames = [Samples(32 * k, 0, np.full((32, 8), k, np.int16)) for k in range(32)]
    dec = StreamDecoder()
    rec = Recorder(tmp_path, "paper", "test")
    rec.handle(frames[:31], dec)  # 992 samples held
    assert rec.early_samples == 992
    with pytest.raises(DeviceError, match="no device header in the first 1024 samples: none "
                       "of them is recorded"):
        rec.handle(frames[31:], dec)
    rec.close(dec, complete=False)
    assert rec.result.unrecorded == 1024 and not rec.result.takes and not rec.early

    rec = Recorder(tmp_path, "paper", "test")
    rec.handle(frames[:5], dec)
    rec.close(dec)
    assert rec.result.unrecorded == 160 and not rec.result.takes

    rec = Recorder(tmp_path, "paper", "test")
    rec.handle([*frames[:3], Reconnected("p"), frames[3], Header(pen_info()), frames[4]], dec)
    rec.close(dec)
    assert rec.result.unrecorded == 96 and rec.result.reconnects == 1
    take = read_take(rec.result.takes[0])
    assert take.seq.tolist() == list(range(96, 160)) and take.raw[:, 0].tolist() == \
        [3] * 32 + [4] * 32


def test_a_pen_that_never_sends_its_header_ends_with_a_count_of_what_was_not_recorded(
        tmp_path, reap):
    """tactile-record on a socket device sending 1000 samples and no header: its progress says
    how many samples it holds; stopped, it exits 2 saying all 1000 were not recorded."""
    from tactile.device.protocol import encode_samples

    raw = PenSimulator("paper", seed=3).read(1000)
    data = b"".join(encode_samples(k, k * 10_000, raw[k : k + 1]) for k in range(1000))
    srv, url = listening()
    proc = reap(subprocess.Popen(
        [sys.executable, "-m", "tactile.device.commands.record", "--port", url, "--label", "paper",
         "--out", str(tmp_path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    try:
        conn, _ = srv.accept()
        with conn:  # its socket:// open is over once it says so
            assert proc.stderr.readline() == f"tactile-record: opened {url}\n"
            conn.sendall(data)
            for line in proc.stderr:  # progress lines, each second
                if "no device header yet: 1000 samples held" in line:
                    break
            proc.send_signal(signal.SIGINT)
            out, err = proc.communicate(timeout=30)
    finally:
        srv.close()
    assert proc.returncode == 2 and out == "", err
    assert "reconnects 0; 1000 before any device header, not recorded" in err
    assert err.splitlines()[-1] == (
        f"tactile-record: error: no take recorded from {url}: {len(data)} bytes read, 1000 samples "
        "decoded, 1000 of them before any device header and not recorded (a binary pen's "
        "samples need its header)"), err
    assert not list(tmp_path.glob("*.csv"))
