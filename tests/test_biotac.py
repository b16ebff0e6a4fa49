"""The BioTac importer and takes of more than 32 channels (recordings, decoder, training).

The importer is tested on small HDF5 files each test writes itself (so CI needs no shared data)
and on a slice of the real recordings (two trials copied into a temporary file), which is
skipped, saying so, when ``../shared/datasets/biotac-bolt/`` is absent.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import SHARED

from tactile.device.commands.import_biotac import main as biotac_main
from tactile.device.protocol import (
    MAX_CHANNELS,
    ChannelSpec,
    DeviceInfo,
    Header,
    Samples,
    decode,
    encode_header,
)
from tactile.device.recordings import TakeWriter, load_dataset, read_take
from tactile.device.recordings.biotac import channels, import_biotac, irregular
from tactile.errors import FrameError, RecordingError

BOLT = SHARED / "datasets" / "biotac-bolt"
WIDTHS = {"pac": 22, "pdc": None, "electrodes": 19, "tac": None, "tdc": None}


def write_h5(path: Path, trials: dict[str, int], seed: int = 0) -> dict:
    """A file in the BOLT layout: ``trials`` maps a group name to its frame count. Returns
    what was written, ``{group: {dataset path: array}}``."""
    rng = np.random.default_rng(seed)
    written = {}
    with h5py.File(path, "w") as f:
        for name, n in trials.items():
            g = f.create_group(name)
            data = {"timestamps": 1342573557 + np.arange(n) // 100}
            for k in (0, 1):
                for ds, w in WIDTHS.items():
                    shape = (n,) if w is None else (n, w)
                    data[f"finger_{k}/{ds}"] = rng.integers(0, 4096, shape)
            for ds, a in data.items():
                g.create_dataset(ds, data=a.astype(np.int64))
            written[name] = data
    return written


def test_channel_names_name_the_finger_and_modality():
    names = [c.name for c in channels()]
    assert len(names) == 88 == len(set(names))
    assert names[:3] == ["f0_pac_00", "f0_pac_01", "f0_pac_02"]
    assert names[21:25] == ["f0_pac_21", "f0_pdc", "f0_ele_00", "f0_ele_01"]
    assert names[41:46] == ["f0_ele_18", "f0_tac", "f0_tdc", "f1_pac_00", "f1_pac_01"]
    assert all(c.unit == "count" and c.scale == 1.0 and c.offset == 0.0 for c in channels())


def test_a_take_of_88_channels_round_trips(tmp_path):
    info = DeviceInfo(100.0, channels(), device="biotac-bolt")
    raw = np.random.default_rng(1).integers(0, 4096, (250, 88))
    with TakeWriter(tmp_path, "cork", info, name="t") as w:
        w.write(0, 0, raw[:100])
        w.write(100, 1_000_000, raw[100:])
    take = read_take(tmp_path / "t.csv")
    assert take.info == info and take.channels == info.channel_names
    assert take.raw.dtype == np.int64 and np.array_equal(take.raw, raw)
    assert take.seq.tolist() == list(range(250)) and take.segments() == [(0, 250)]


def test_the_wire_keeps_its_32_channel_frames_but_csv_lines_carry_more():
    info = DeviceInfo(100.0, channels(), device="biotac-bolt")
    with pytest.raises(FrameError, match="88 channels: a header frame carries 1..32"):
        encode_header(info)
    too_many = tuple(ChannelSpec(f"c{i}", "") for i in range(MAX_CHANNELS + 1))
    with pytest.raises(FrameError, match=f"{MAX_CHANNELS + 1} channels: must be 1..2048"):
        DeviceInfo(100.0, too_many)
    # a board printing 44 columns (one BioTac) as CSV lines: 32 was a hard stop before
    rows = np.arange(3 * 44).reshape(3, 44)
    events, stats = decode("".join(",".join(map(str, r)) + "\n" for r in rows).encode(), "csv")
    assert isinstance(events[0], Header) and len(events[0].info.channels) == 44
    got = np.concatenate([e.raw for e in events if isinstance(e, Samples)])
    assert np.array_equal(got, rows) and stats.samples == 3


def test_import_writes_one_take_per_trial(tmp_path, capsys):
    a = write_h5(tmp_path / "cork.h5", {"cork_pdc100_1cm_01": 120, "cork_pdc150_1cm_02": 90})
    b = write_h5(tmp_path / "metal_bar.h5", {"metal_bar_pdc200_1cm_05": 70}, seed=1)
    out = tmp_path / "data"
    assert biotac_main([str(tmp_path / "cork.h5"), str(tmp_path / "metal_bar.h5"),
                        "--out", str(out)]) == 0
    printed = capsys.readouterr().out.split()
    assert [Path(p).name for p in printed] == [
        "cork_pdc100_1cm_01.csv", "cork_pdc150_1cm_02.csv", "metal_bar_pdc200_1cm_05.csv"]
    takes = {t.path.stem: t for t in load_dataset(out)}
    names = list(takes["cork_pdc100_1cm_01"].channels)
    for group, data in {**a, **b}.items():
        take = takes[group]
        assert take.label == group.rsplit("_pdc", 1)[0]
        assert take.info.sample_rate_hz == 100.0 and take.info.device == "biotac-bolt"
        assert take.meta["complete"] and take.meta["samples"] == len(data["timestamps"])
        for k in (0, 1):  # every column is the dataset it names, frame for frame
            for ds, prefix in (("pac", "pac"), ("electrodes", "ele")):
                for i in range(WIDTHS[ds]):
                    col = take.raw[:, names.index(f"f{k}_{prefix}_{i:02d}")]
                    assert np.array_equal(col, data[f"finger_{k}/{ds}"][:, i])
            for ds in ("pdc", "tac", "tdc"):
                assert np.array_equal(take.raw[:, names.index(f"f{k}_{ds}")],
                                      data[f"finger_{k}/{ds}"])
    m = takes["cork_pdc150_1cm_02"].meta
    assert (m["trial"], m["object"], m["pdc_setting"], m["repetition"], m["user"], m["depth"]) \
        == ("cork_pdc150_1cm_02", "cork", 150, 2, 2, "1cm")
    assert m["recorded_utc"] == "2012-07-18T01:05:57Z"  # from timestamps[0] = 1342573557
    assert takes["metal_bar_pdc200_1cm_05"].label == "metal_bar"


def _run(*args: str) -> tuple[int, list[str]]:
    out = subprocess.run([sys.executable, "-m", "tactile.device.commands.import_biotac", *args],
                         capture_output=True, text=True)
    return out.returncode, out.stderr.strip().splitlines()


def _broken(tmp_path: Path, how: str) -> Path:
    path = tmp_path / f"{how}.h5"
    write_h5(path, {"cork_pdc100_1cm_01": 50, "cork_pdc100_1cm_02": 40})
    with h5py.File(path, "a") as f:
        g = f["cork_pdc100_1cm_02"]
        if how == "missing":
            del g["finger_1/pdc"]
        elif how == "short":
            del g["finger_1/pdc"]
            g.create_dataset("finger_1/pdc", data=np.zeros(39, np.int64))
        elif how == "shape":
            del g["finger_0/pac"]
            g.create_dataset("finger_0/pac", data=np.zeros((40, 21), np.int64))
        elif how == "float":
            del g["finger_0/tdc"]
            g.create_dataset("finger_0/tdc", data=np.zeros(40))
        elif how == "range":
            g["finger_0/electrodes"][7, 3] = 4096
        elif how == "name":
            f.move("cork_pdc100_1cm_02", "cork_trial_2")
        elif how == "empty":  # a trial of no frames: every dataset of length 0
            for ds in ["timestamps", *(f"finger_{k}/{d}" for k in (0, 1) for d in WIDTHS)]:
                shape = (0, *g[ds].shape[1:])
                del g[ds]
                g.create_dataset(ds, data=np.zeros(shape, np.int64))
        elif how == "external":  # links that lead nowhere
            del g["finger_1/pdc"]
            g["finger_1/pdc"] = h5py.ExternalLink("gone.h5", "/pdc")
        elif how == "soft":
            del g["timestamps"]
            g["timestamps"] = h5py.SoftLink("/nowhere")
        elif how == "finger":
            del g["finger_0"]
            g["finger_0"] = h5py.SoftLink("/nowhere")
        elif how == "trial":
            del f["cork_pdc100_1cm_02"]
            f["cork_pdc100_1cm_02"] = h5py.ExternalLink("gone.h5", "/cork_pdc100_1cm_02")
    return path


@pytest.mark.parametrize("how, message", [
    ("missing", "cork_pdc100_1cm_02/finger_1/pdc: missing"),
    ("short", "cork_pdc100_1cm_02/finger_1/pdc: 39 frames, but timestamps has 40"),
    ("shape", "cork_pdc100_1cm_02/finger_0/pac: shape (40, 21), expected (T, 22)"),
    ("float", "cork_pdc100_1cm_02/finger_0/tdc: dtype float64, expected integer counts"),
    ("range", "cork_pdc100_1cm_02/finger_0/electrodes: value 4096 at frame 7 is not a "
              "12-bit count (0..4095)"),
    ("name", "group 'cork_trial_2' is not named <object>_pdc<setting>_<depth>_<repetition>"),
    ("empty", "cork_pdc100_1cm_02/timestamps: no frames"),
])
def test_a_bad_file_is_one_line_naming_file_and_dataset_and_nothing_is_written(
        tmp_path, how, message):
    path = _broken(tmp_path, how)
    code, err = _run(str(path), "--out", str(tmp_path / "out"))
    assert code == 1 and len(err) == 1, err
    assert err[0] == f"tactile-import-biotac: error: {path}: {message}"
    # the good first trial was not written either: everything is checked first
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


@pytest.mark.parametrize("how, message", [
    ("external", "cork_pdc100_1cm_02/finger_1/pdc: a link to /pdc in gone.h5 that cannot be "
                 "followed ("),
    ("soft", "cork_pdc100_1cm_02/timestamps: a link to /nowhere that cannot be followed ("),
    ("finger", "cork_pdc100_1cm_02/finger_0/pac: finger_0 is a link to /nowhere that cannot be "
               "followed ("),
    ("trial", "cork_pdc100_1cm_02: a link to /cork_pdc100_1cm_02 in gone.h5 that cannot be "
              "followed ("),
])
def test_a_link_that_leads_nowhere_is_one_line_naming_file_trial_and_dataset(
        tmp_path, how, message):
    """An HDF5 external link to a missing file, or a soft link to a path the file lacks, in
    place of a dataset was a KeyError traceback from h5py naming neither the file nor the
    dataset. A link that does lead to the data is followed."""
    path = _broken(tmp_path, how)
    code, err = _run(str(path), "--out", str(tmp_path / "out"))
    assert code == 1 and len(err) == 1, err
    assert err[0].startswith(f"tactile-import-biotac: error: {path}: {message}"), err
    assert not (tmp_path / "out").exists()
    data = write_h5(tmp_path / "data.h5", {"cork_pdc100_1cm_09": 50}, seed=3)
    with h5py.File(path, "a") as f:  # links that lead to the data are followed
        g = f["cork_pdc100_1cm_01"]
        del g["finger_0/tdc"], g["timestamps"]
        g["finger_0/tdc"] = h5py.ExternalLink(str(tmp_path / "data.h5"),
                                              "/cork_pdc100_1cm_09/finger_0/tdc")
        g["seconds"] = np.full(50, 1342573557)
        g["timestamps"] = h5py.SoftLink("/cork_pdc100_1cm_01/seconds")
        del f["cork_pdc100_1cm_02"]
    assert _run(str(path), "--out", str(tmp_path / "out"))[0] == 0
    take = read_take(tmp_path / "out" / "cork_pdc100_1cm_01.csv")
    assert np.array_equal(take.raw[:, list(take.channels).index("f0_tdc")],
                          data["cork_pdc100_1cm_09"]["finger_0/tdc"])


@pytest.mark.parametrize("dataset, frame, value, rule", [
    ("finger_0/tdc", 3, 2**63 + 5, "not a 12-bit count (0..4095)"),
    ("timestamps", 7, 2**64 - 1, "not a time of 1970..2099 in whole Unix seconds"),
])
def test_a_uint64_value_out_of_range_is_reported_as_it_is(tmp_path, dataset, frame, value, rule):
    """A uint64 count of 2**63 + 5 was converted to int64 before the range check and reported
    as 'value -9223372036854775803'; the check is made on the values as stored now. In-range
    uint64 datasets import, value for value."""
    path = tmp_path / "u64.h5"
    data = write_h5(path, {"cork_pdc100_1cm_01": 30})["cork_pdc100_1cm_01"]
    with h5py.File(path, "a") as f:
        g = f["cork_pdc100_1cm_01"]
        for name in (dataset, "finger_1/pac"):
            del g[name]
            g.create_dataset(name, data=data[name].astype(np.uint64))
    out = tmp_path / "out"
    assert _run(str(path), "--out", str(out))[0] == 0
    take = read_take(out / "cork_pdc100_1cm_01.csv")
    assert np.array_equal(take.raw[:, 44:66], data["finger_1/pac"])
    with h5py.File(path, "a") as f:
        f[f"cork_pdc100_1cm_01/{dataset}"][frame] = np.uint64(value)
    code, err = _run(str(path), "--out", str(out), "--force")
    assert code == 1 and err == [f"tactile-import-biotac: error: {path}: cork_pdc100_1cm_01/"
                                 f"{dataset}: value {value} at frame {frame} is {rule}"], err
    assert len(read_take(out / "cork_pdc100_1cm_01.csv").raw) == 30


def test_a_damaged_dataset_is_one_line_naming_file_trial_and_dataset(tmp_path):
    """A compressed chunk that does not decompress was h5py's OSError ("Can't synchronously
    read data (filter returned failure during read)") naming neither the file nor the dataset;
    and with --force the old takes stay."""
    path = tmp_path / "damaged.h5"
    data = write_h5(path, {"cork_pdc100_1cm_01": 300})["cork_pdc100_1cm_01"]
    out = tmp_path / "out"
    import_biotac([path], out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    with h5py.File(path, "a") as f:
        g = f["cork_pdc100_1cm_01/finger_1"]
        del g["electrodes"]
        d = g.create_dataset("electrodes", data=data["finger_1/electrodes"], chunks=(100, 19),
                             compression="gzip")
        chunk = d.id.get_chunk_info(1)
    with open(path, "r+b") as f:  # the second chunk's bytes overwritten
        f.seek(chunk.byte_offset)
        f.write(b"\xff" * chunk.size)
    code, err = _run(str(path), "--out", str(out), "--force")
    assert code == 1 and len(err) == 1, err
    assert err[0].startswith(f"tactile-import-biotac: error: {path}: cork_pdc100_1cm_01/finger_1/"
                             "electrodes: cannot be read ("), err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_other_bad_inputs(tmp_path):
    text = tmp_path / "notes.h5"
    text.write_text("not hdf5\n")
    code, err = _run(str(text), "--out", str(tmp_path / "out"))
    assert code == 1 and len(err) == 1 and f"{text}: not an HDF5 file" in err[0], err
    code, err = _run(str(tmp_path / "absent.h5"), "--out", str(tmp_path / "out"))
    assert code == 1 and err == [f"tactile-import-biotac: error: {tmp_path / 'absent.h5'}: "
                                 "no such file"]
    code, err = _run(str(tmp_path), "--out", str(tmp_path / "out"))  # the dataset folder
    assert code == 1 and err == [f"tactile-import-biotac: error: {tmp_path}: a folder; give the "
                                 f".h5 files (e.g. {tmp_path / '*.h5'})"], err
    with h5py.File(tmp_path / "empty.h5", "w"):
        pass
    with pytest.raises(RecordingError, match="empty.h5: no trial groups"):
        import_biotac([tmp_path / "empty.h5"], tmp_path / "out")
    write_h5(tmp_path / "a.h5", {"cork_pdc100_1cm_01": 30})
    write_h5(tmp_path / "b.h5", {"cork_pdc100_1cm_01": 30}, seed=1)
    with pytest.raises(RecordingError, match=r"b.h5: trial cork_pdc100_1cm_01 also in .*a.h5"):
        import_biotac([tmp_path / "a.h5", tmp_path / "b.h5"], tmp_path / "out")
    assert not (tmp_path / "out").exists()
    (tmp_path / "sub").mkdir()
    for again in (tmp_path / "a.h5", tmp_path / "sub" / ".." / "a.h5"):  # any spelling
        with pytest.raises(RecordingError, match=r"a\.h5: given twice \(also as .*a\.h5\)"):
            import_biotac([tmp_path / "a.h5", again], tmp_path / "out")
    assert not (tmp_path / "out").exists()
    import_biotac([tmp_path / "a.h5"], tmp_path / "out")
    with pytest.raises(RecordingError, match=r"cork_pdc100_1cm_01.csv and 1 more files already "
                       "exist: choose another folder, or --force to replace them"):
        import_biotac([tmp_path / "a.h5"], tmp_path / "out")  # twice would duplicate the trial
    import_biotac([tmp_path / "b.h5"], tmp_path / "out", force=True)  # b's data replace a's
    assert len(list((tmp_path / "out").glob("*.csv"))) == 1
    take = read_take(tmp_path / "out" / "cork_pdc100_1cm_01.csv")
    with h5py.File(tmp_path / "b.h5", "r") as f:
        assert np.array_equal(take.raw[:, 0], f["cork_pdc100_1cm_01/finger_0/pac"][:, 0])
    (tmp_path / "file").write_text("")
    with pytest.raises(RecordingError, match="file: not a folder"):
        import_biotac([tmp_path / "a.h5"], tmp_path / "file")


@pytest.mark.parametrize("later", ["range", "label"])
def test_force_deletes_nothing_when_a_later_input_is_bad(tmp_path, later):
    """With --force the old takes go only once every input has passed its checks: here the
    first file would replace an imported trial, and a later file fails (a value out of range
    in its second trial, or an object name too long to be a label): the error is one line,
    exit code 1, and the folder holds the old takes, byte for byte, and nothing else."""
    write_h5(tmp_path / "old.h5", {"cork_pdc100_1cm_01": 30, "cork_pdc100_1cm_02": 30})
    out = tmp_path / "out"
    import_biotac([tmp_path / "old.h5"], out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert len(before) == 4
    write_h5(tmp_path / "new.h5", {"cork_pdc100_1cm_01": 50}, seed=1)  # replaces a take
    bad = tmp_path / "bad.h5"
    if later == "range":
        write_h5(bad, {"metal_bar_pdc100_1cm_01": 20, "metal_bar_pdc100_1cm_02": 20}, seed=2)
        with h5py.File(bad, "a") as f:
            f["metal_bar_pdc100_1cm_02/finger_1/tdc"][7] = 4096
        message = "metal_bar_pdc100_1cm_02/finger_1/tdc: value 4096 at frame 7"
    else:
        write_h5(bad, {"o" * 65 + "_pdc100_1cm_01": 20}, seed=2)
        message = "label '" + "o" * 65 + "': must be 1-64 characters"
    code, err = _run(str(tmp_path / "new.h5"), str(bad), "--out", str(out), "--force")
    assert code == 1 and len(err) == 1 and f"{bad}: " in err[0] and message in err[0], err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    # the same inputs without the bad one do replace the take
    assert biotac_main([str(tmp_path / "new.h5"), "--out", str(out), "--force"]) == 0
    assert len(read_take(out / "cork_pdc100_1cm_01.csv").raw) == 50
    assert (out / "cork_pdc100_1cm_02.csv").read_bytes() == before["cork_pdc100_1cm_02.csv"]


@pytest.mark.parametrize("frame, value", [(0, 2**62), (0, -1), (5, 4_102_444_800)])
def test_force_keeps_the_old_takes_when_a_timestamp_is_not_a_date(tmp_path, frame, value):
    """A timestamp of 2**62 passed the checks and failed only when the take's recorded_utc was
    made, in the writing pass: --force had already deleted the old takes, nothing new was
    written, and the error ('[Errno 75] Value too large...') named no file. Timestamps are
    checked with the rest now: one line naming the file, trial and dataset; the folder holds
    the old takes, byte for byte."""
    write_h5(tmp_path / "old.h5", {"cork_pdc100_1cm_01": 30, "cork_pdc100_1cm_02": 30})
    out = tmp_path / "out"
    import_biotac([tmp_path / "old.h5"], out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    new = tmp_path / "new.h5"
    write_h5(new, {"cork_pdc100_1cm_01": 40}, seed=1)
    with h5py.File(new, "a") as f:
        f["cork_pdc100_1cm_01/timestamps"][frame] = value
    code, err = _run(str(new), "--out", str(out), "--force")
    assert code == 1 and err == [
        f"tactile-import-biotac: error: {new}: cork_pdc100_1cm_01/timestamps: value {value} at "
        f"frame {frame} is not a time of 1970..2099 in whole Unix seconds"], err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    with h5py.File(new, "a") as f:  # the last second of 2099 is a date
        f["cork_pdc100_1cm_01/timestamps"][frame] = 4_102_444_799
    assert _run(str(new), "--out", str(out), "--force")[0] == 0
    take = read_take(out / "cork_pdc100_1cm_01.csv")
    assert len(take.raw) == 40
    assert take.meta["recorded_utc"] == ("2099-12-31T23:59:59Z" if frame == 0
                                         else "2012-07-18T01:05:57Z")


@pytest.mark.parametrize("stamps, said", [
    ([10, 10, 11, 11, 12], None),
    ([10, 11, 10, 11, 12], "go back from 11 to 10 at frame 2"),
    ([10, 11, 14, 14, 15], "jump from 11 to 14 at frame 2"),
    ([10, 9, 12, 11, 12], "go back from 10 to 9 at frame 1 (and 1 more); jump from 9 to "
                          "12 at frame 2"),
])
def test_irregular_names_where_timestamps_first_go_back_or_jump(stamps, said):
    assert irregular(np.array(stamps, np.int64)) == said


def test_timestamps_that_go_back_or_jump_import_in_file_order_with_a_warning(tmp_path, capsys):
    """Timestamps were checked for range only: a trial whose clock went back or skipped
    (frames lost, or the clock set) imported with no word. It imports as before, its frames
    in file order, and the command says which trial and frame, one line per trial."""
    path = tmp_path / "odd.h5"
    data = write_h5(path, {"cork_pdc100_1cm_01": 300, "cork_pdc100_1cm_02": 300})
    with h5py.File(path, "a") as f:
        stamps = f["cork_pdc100_1cm_02/timestamps"]
        stamps[150:] = stamps[150:] - 2  # the clock set back two seconds at frame 150
    out = tmp_path / "out"
    result = subprocess.run(
        [sys.executable, "-m", "tactile.device.commands.import_biotac", str(path), "--out",
         str(out)], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stderr.splitlines() == [
        f"tactile-import-biotac: warning: {path}: cork_pdc100_1cm_02/timestamps: go back from "
        "1342573558 to 1342573556 at frame 150 (imported in file order)"]
    for name in ("cork_pdc100_1cm_01", "cork_pdc100_1cm_02"):
        take = read_take(out / f"{name}.csv")
        assert np.array_equal(take.raw[:, list(take.channels).index("f0_pdc")],
                              data[name]["finger_0/pdc"])
    import_biotac([path], tmp_path / "out2")  # the library, no command running: no name
    said = capsys.readouterr().err.splitlines()
    assert len(said) == 1 and said[0].startswith(
        f"warning: {path}: cork_pdc100_1cm_02/timestamps: go ")


def test_without_h5py_the_command_names_its_extra():
    block = ("import sys\nclass Block:\n    def find_spec(self, name, path=None, target=None):\n"
             "        if name.split('.')[0] == 'h5py':\n"
             "            raise ModuleNotFoundError(f'No module named {name!r}', name=name)\n"
             "sys.meta_path.insert(0, Block())\n"
             "from tactile.device.commands.import_biotac import main\n"
             "sys.argv = ['tactile-import-biotac', 'x.h5', '--out', 'y']\n"
             "sys.exit(main())\n")
    out = subprocess.run([sys.executable, "-c", block], capture_output=True, text=True)
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 1 and lines == [
        "tactile-import-biotac: error: needs the [biotac] extra (no module named 'h5py'): "
        "pip install 'tactile-pen[biotac]'"], out.stderr


def two_objects(tmp_path: Path) -> Path:
    """Takes of two objects x three repetitions of 60 frames, imported into tmp_path/data."""
    for obj in ("cork", "glass_bottle"):
        write_h5(tmp_path / f"{obj}.h5",
                 {f"{obj}_pdc100_1cm_{r:02d}": 60 for r in (1, 2, 3)}, seed=len(obj))
    import_biotac(sorted(tmp_path.glob("*.h5")), tmp_path / "data")
    return tmp_path / "data"


def test_tactile_train_cuts_windows_from_88_channel_takes(tmp_path, capsys):
    """Two objects x three repetitions; split by user (= repetition): one each for train,
    validation and test. One epoch of a tiny LSTM: the point is that 88 channels go through."""
    from tactile.training.checkpoint import load_checkpoint
    from tactile.training.commands.train import main as train_main

    data = two_objects(tmp_path)
    run = tmp_path / "run"
    code = train_main([str(data), "--out", str(run), "--quiet", "--set", "epochs=1",
                       "--set", "window=20", "--set", "hop=10", "--set", "hidden=8",
                       "--set", "layers=1", "--set", "threads=1", "--set", "batch_size=16"])
    assert code == 0, capsys.readouterr().err
    model, ck = load_checkpoint(run)
    assert ck["channels"] == [c.name for c in channels()]
    assert len(ck["mean"]) == 88
    metrics = json.loads((run / "metrics.json").read_text())
    # 60 frames, window 20, hop 10: 5 windows a take; one test repetition of 2 objects
    assert sum(sum(row) for row in metrics["confusion"]) == 2 * 5


def test_a_granular_model_without_channels_reads_only_its_modalities_channels(tmp_path, capsys):
    """A config of modalities and no `channels` (export.md's example) made a model of all 88
    channels: it refused a device that sends one finger's, though it reads 23 of them."""
    from tactile.training.checkpoint import load_checkpoint
    from tactile.training.commands.train import main as train_main

    data = two_objects(tmp_path)
    config = tmp_path / "f0.toml"
    config.write_text('model = "f_rnn"\nwindow = 20\nhop = 10\nepochs = 1\nhidden = 4\n'
                      'layers = 1\nthreads = 1\n'
                      '[signals]\nf0_pac = ["f0_pac_*"]\nf1_pac = ["f1_pac_*"]\n'  # f1: unread
                      '[modalities.vibration]\nchannels = ["f0_pac"]\nimfs = 0\nsteps = 22\n'
                      '[modalities.pressure]\nchannels = ["f0_pdc"]\nimfs = 0\nsteps = 2\n')
    code = train_main([str(data), "--out", str(tmp_path / "run"), "--config", str(config)])
    err = capsys.readouterr().err
    assert code == 0, err
    _, ck = load_checkpoint(tmp_path / "run")
    assert ck["channels"] == [*(f"f0_pac_{i:02d}" for i in range(22)), "f0_pdc"]
    assert len(ck["mean"]) == 23
    assert "channels: the 23 the modalities read, of the takes' 88" in err
    code = train_main([str(data), "--out", str(tmp_path / "both"), "--config", str(config),
                       "--set", "channels=f0_pdc,f1_pdc,f0_pac_*,f1_pac_*", "--quiet"])
    assert code == 0, capsys.readouterr().err  # a `channels` setting is kept as it is
    assert load_checkpoint(tmp_path / "both")[1]["channels"] == [
        "f0_pdc", "f1_pdc", *(f"f{k}_pac_{i:02d}" for k in (0, 1) for i in range(22))]


@pytest.mark.skipif(not BOLT.is_dir(), reason=f"BioTac BOLT recordings absent ({BOLT})")
def test_import_a_slice_of_the_real_recordings(tmp_path):
    """Two real trials (copied into a temporary file: the data never enters the repository)
    come out frame for frame, with the real file's names parsed."""
    picks = {"cork.h5": "cork_pdc150_1cm_04", "glass_bottle.h5": "glass_bottle_pdc200_1cm_01"}
    for file, group in picks.items():
        with h5py.File(BOLT / file, "r") as src, h5py.File(tmp_path / file, "w") as dst:
            src.copy(src[group], dst, name=group)
    import_biotac([tmp_path / f for f in picks], tmp_path / "out")
    names = list(channels())
    for file, group in picks.items():
        take = read_take(tmp_path / "out" / f"{group}.csv")
        with h5py.File(BOLT / file, "r") as src:
            g = src[group]
            n = len(g["timestamps"])
            assert len(take.raw) == n and take.label == file.removesuffix(".h5")
            want = np.concatenate([
                g[f"finger_{k}/{ds}"][()].reshape(n, -1)
                for k in (0, 1) for ds in ("pac", "pdc", "electrodes", "tac", "tdc")], axis=1)
        assert np.array_equal(take.raw, want)
        assert [c.name for c in take.info.channels] == [c.name for c in names]
    take = read_take(tmp_path / "out" / "cork_pdc150_1cm_04.csv")
    assert (take.meta["pdc_setting"], take.meta["repetition"], take.meta["user"]) == (150, 4, 4)
    assert take.meta["recorded_utc"].startswith("2012-07")
    # every trial name of the real files parses (names only: cheap)
    from tactile.device.recordings.biotac import TRIAL
    groups = []
    for f in sorted(BOLT.glob("*.h5")):
        with h5py.File(f, "r") as src:
            groups += [(f.stem, g) for g in src]
    assert len(groups) == 74
    assert all(TRIAL.match(g)["object"] == stem for stem, g in groups)
