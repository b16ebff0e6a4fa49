"""A slice of bench/fuzz.py (the same code, imported): corrupted streams against ground truth."""

from __future__ import annotations

import importlib.util
import random
import sys

import pytest
from conftest import REPO

from tactile.device.decoder import Samples, StreamDecoder


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
    from tactile.device.protocol import _SuffixSearch

    inputs = fuzz.adversarial_inputs(20_000)
    assert inputs["0x01 run (no delimiter)"][1] == b"\x01" * 20_000
    mode, crafted = inputs["crafted frame starts"]
    chunk = crafted.split(b"\x00")[0]
    search = _SuffixSearch(chunk, None)
    starts = [i for i in search._starts() if i % 13 == 0]  # the crafted ones
    # the crafted chunk's candidates each have the length their counts ask for
    assert len(starts) > 20
    assert all(search._walk(i) == 13 + 2 * chunk[i + 10] * chunk[i + 11] for i in starts)


# Cases of the 1,000,000-case run (seed 1) that failed; each names what it caught.
_FOUND = [
    # mix: a frame swapped with the one after it and a header with other names put between
    # them: the late frame came after a header and before every frame remembered, and was taken
    # for a restarted device although its count (~3e9) is no fresh device's and its time fits
    451760,
    528369,  # the same, frames of 2 samples of 32 channels
    250737,  # mix: a frame truncated to nothing, then a delete in it (the fuzz raised)
    178661,  # the same family: a bit flip in an item a truncate emptied
]


@pytest.mark.parametrize("index", _FOUND)
def test_found_case_has_no_failures(index):
    t = fuzz.Totals()
    fuzz.run_case(1, index, t)
    assert {f: getattr(t, f) for f in fuzz.FAILURES} == dict.fromkeys(fuzz.FAILURES, 0), \
        t.first_failure


@pytest.mark.xfail(strict=True, reason="ambiguous input: the oracle demands a reading no decoder "
                   "can tell from a quick second restart")
def test_found_case_swapped_first_frames_of_a_restart_across_a_header():
    """Seed 1 case 280077 (mix): after a reboot the device's frames with counts 1 and 0 arrive
    swapped, a header with other names between them. The decoder takes count 0 for a second
    restart (count and clock of a fresh device, after a header) and delivers it after count 1;
    the oracle wants it dropped as late. The same bytes come from a device that restarted twice
    within a second (its boot clock as deterministic as the fuzz's own reboots, 0-20 ms), where
    dropping it would lose an intact frame: the decoder keeps the reading that loses nothing.
    Open: the fuzz should not demand one reading here."""
    t = fuzz.Totals()
    fuzz.run_case(1, 280077, t)
    assert {f: getattr(t, f) for f in fuzz.FAILURES} == dict.fromkeys(fuzz.FAILURES, 0), \
        t.first_failure
