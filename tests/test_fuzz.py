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
