"""A slice of bench/fuzz.py (the same code, imported): corrupted streams against ground truth."""

from __future__ import annotations

import importlib.util
import random
import sys

import numpy as np
import pytest
from conftest import REPO

from tactile.device.protocol import Gap, Samples, StreamDecoder


def _load_fuzz():
    spec = importlib.util.spec_from_file_location("bench_fuzz", REPO / "bench" / "fuzz.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_fuzz"] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


fuzz = _load_fuzz()


@pytest.mark.parametrize("seed", [2, 3])
def test_fuzz_slice_has_no_failures(seed):
    t = fuzz.run_range(seed, 0, 10_000)
    assert t.cases == 10_000 and set(t.by_kind) == set(fuzz.KINDS)
    assert t.samples_expected > 100_000  # the cases do carry data to get right
    assert {f: getattr(t, f) for f in fuzz.FAILURES} == dict.fromkeys(fuzz.FAILURES, 0), \
        t.first_failure


def test_the_checker_sees_each_kind_of_failure():
    """The columns are not blind: a decoder that invents, repeats, reorders or loses samples,
    or makes up a gap, is caught."""
    r = random.Random(5)
    items, raw, session, devseq = fuzz.binary_case(r, "flip")
    must, refused = fuzz._expected_binary(items, len(raw))
    events = StreamDecoder().feed(b"".join(it.data for it in items))
    samples = [e for e in events if isinstance(e, Samples)]
    assert len(samples) >= 3

    def failures(evs):
        t = fuzz.Totals()
        fuzz.check_binary(evs, raw, session, devseq, must, refused, t)
        return {f: getattr(t, f) for f in fuzz.FAILURES if getattr(t, f)}

    assert failures(events) == {}
    a, b = samples[0], samples[1]
    bad = a.raw.copy()
    bad[0, 1] ^= 1
    assert "invented" in failures([Samples(a.seq, a.t_us, bad), *samples[1:]])
    assert "duplicated" in failures([a, *samples])
    assert "reordered" in failures([b, a, *samples[2:]])
    assert "unrecovered" in failures(samples[1:])
    shifted = [Samples(s.seq + 5, s.t_us, s.raw) for s in samples[1:]]
    assert "bad_gaps" in failures([a, *shifted])


def test_throughput_inputs_are_what_they_say():
    from tactile.device.protocol.codec import _SuffixSearch

    inputs = fuzz.adversarial_inputs(20_000)
    assert inputs["0x01 run (no delimiter)"][1] == b"\x01" * 20_000
    mode, crafted = inputs["crafted frame starts"]
    chunk = crafted.split(b"\x00")[0]
    search = _SuffixSearch(chunk, None)
    starts = [i for i in search._starts() if i % 13 == 0]  # the crafted ones
    # the crafted chunk's candidates each have the length their counts ask for
    assert len(starts) > 20
    assert all(search._walk(i) == 13 + 2 * chunk[i + 10] * chunk[i + 11] for i in starts)


# Cases that failed, each with what it caught: (seed, index).
_FOUND = [
    # seed 1 (the 1,000,000-case run), all mix:
    # a frame swapped with the one after it and a header with other names put between
    # them: the late frame came after a header and before every frame remembered, and was taken
    # for a restarted device although its count (~3e9) is no fresh device's and its time fits
    (1, 451760),
    (1, 528369),  # the same, frames of 2 samples of 32 channels
    (1, 250737),  # a frame truncated to nothing, then a delete in it (the fuzz raised)
    (1, 178661),  # the same family: a bit flip in an item a truncate emptied
    # after a reboot, the frames with counts 1 and 0 swapped and a header between them: the
    # bytes of a device restarting again, read as such (a restart gap, then count 0; see
    # test_decoder's test_a_frame_behind_its_whole_run_after_a_header_is_read_as_a_restart);
    # the oracle wanted count 0 dropped as late
    (1, 280077),
    (5, 4667),  # the same, 8 channels; the header between them of other names
    # one byte glued in front of frame 52-55, which came before frame 48-51 (swapped): the
    # decoder recovered 52-55 and dropped 48-51 as late, the oracle took 52-55 for damaged
    # and wanted 48-51
    (5, 7293),
]


@pytest.mark.parametrize(("seed", "index"), _FOUND)
def test_found_case_has_no_failures(seed, index):
    t = fuzz.Totals()
    fuzz.run_case(seed, index, t)
    assert {f: getattr(t, f) for f in fuzz.FAILURES} == dict.fromkeys(fuzz.FAILURES, 0), \
        t.first_failure


def test_the_restart_reading_is_accepted_only_where_the_rule_gives_it():
    """The oracle accepts a frame delivered behind its run after a restart gap only when the
    stream holds a header between it and the sample before it and its count is a fresh
    device's (device/PROTOCOL.md, "Restart"): the same decoder output is a failure without."""
    head = fuzz._header(8)
    raw = np.zeros((3, 8), np.int16)
    raw[:, 0] = np.arange(3)

    def items(count0, header):
        frames = [fuzz.Item(fuzz.encode_samples(count0 + 1, 27_582, raw[1:2]), "samples", (1, 2)),
                  fuzz.Item(fuzz.encode_samples(count0, 17_582, raw[0:1]), "samples", (0, 1))]
        return ([fuzz.Item(head, "header")] + frames[:1] + [fuzz.Item(head, "header")] * header
                + frames[1:])

    events = [Samples(1, 27_582, raw[1:2]), Gap(2, 0, "restart"), Samples(2, 37_582, raw[0:1])]
    session, must, refused = np.zeros(3, np.int64), np.zeros(3, bool), np.zeros(3, bool)
    for count0, header, ok in ((0, True, True), (0, False, False), (5000, True, False)):
        devseq = count0 + np.arange(3)
        t = fuzz.Totals()
        fuzz.check_binary(events, raw, session, devseq, must, refused, t,
                          fuzz.restart_reading(items(count0, header), devseq))
        assert (t.reordered, t.bad_gaps) == ((0, 0) if ok else (1, 1)), (count0, header)


def test_chunks_add_up_to_the_whole_run(tmp_path, capsys):
    """--first/--out chunks of one seed merge (--summary) to the totals of one run over their
    range; chunks that overlap, leave a hole or mix seeds are refused."""
    whole = fuzz.run_range(7, 0, 60)
    for first, cases in ((0, 25), (25, 35)):
        fuzz.main(["--seed", "7", "--first", str(first), "--cases", str(cases), "--no-speed",
                   "--out", str(tmp_path / f"c{first}.json")])
    fuzz.main(["--seed", "8", "--cases", "5", "--no-speed", "--out", str(tmp_path / "s8.json")])
    fuzz.main(["--seed", "7", "--first", "20", "--cases", "5", "--no-speed",
               "--out", str(tmp_path / "o20.json")])
    fuzz.main(["--seed", "7", "--first", "70", "--cases", "3", "--no-speed",
               "--out", str(tmp_path / "h70.json")])
    capsys.readouterr()
    assert fuzz.main(["--summary", str(tmp_path / "c25.json"), str(tmp_path / "c0.json")]) == 0
    out = capsys.readouterr().out
    assert out.startswith("cases 60 (seed 7, cases 0..59, 2 chunks, ")
    assert f"{whole.samples_sent} samples sent, {whole.samples_expected} expected, " \
           f"{whole.samples_delivered} delivered" in out
    for bad in (["c0.json", "s8.json"], ["c0.json", "o20.json"],
                ["c0.json", "c25.json", "h70.json"]):
        assert fuzz.main(["--summary", *(str(tmp_path / b) for b in bad)]) == 1
