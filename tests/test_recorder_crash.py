"""Crash test: SIGKILL the real ``tactile-record`` at many points and check every take it leaves
against what the simulated pen sent.

Each kill runs ``tactile-record`` (the console entry point, in a subprocess) on a ``sim://`` pen
that reboots (an unplug), falls silent (a stall) or garbles its link, and kills it at a point
derived from what the recorder has reported, never from a clock: so many rows in its CSV, so
many rows after the pen's reboot, or its "no data for N s" line. The verdict holds wherever the
kill lands:

* the take reads back (``read_take``), whatever state the kill left it in;
* every row is the pen's sample for that seq, in order, none twice: rows before a ``restart``
  gap are the first boot's samples, rows after it the next boot's (a take that misses a reboot
  fails here: its later rows are not the samples their seq would say);
* every jump in seq is a recorded gap of that size, so ``Take.segments()`` never spans a break;
* no row the recorder had written when the kill was decided is missing;
* killed during a silence, the take holds every sample the pen sent before it.

CI runs :data:`CI_KILLS` kills; ``python tests/test_recorder_crash.py --kills 200`` runs a longer
series and prints the figures quoted in docs/reliability.md.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest

from tactile.device.recordings import read_take
from tactile.device.sim import PenSimulator
from tactile.errors import RecordingError

RATE = 100.0
ENTRY = "import sys; from tactile.device.commands.record import main; sys.exit(main())"
DEADLINE_S = 120.0  # a kill point never reached fails the case (a hang guard, not a measure)


@dataclass(frozen=True)
class Case:
    """One recorder run and where to kill it.

    ``kind``: ``rows`` (kill once the CSV holds ``n`` rows), ``reboot`` (once it holds ``n``
    rows after the pen's reboot: its ``restart`` gap line, or the recorder's "reconnected to"
    line if that comes first, then ``n`` rows) or ``silence``
    (once the recorder says it has had no data for ``n`` s or more; for ``n`` = 0, also once
    its clock has rewritten the JSON with every sample sent before the silence).
    """

    kind: str
    n: float
    seed: int
    query: str  # the sim:// options beside texture and seed

    @property
    def url(self) -> str:
        return f"sim://?texture=paper&seed={self.seed}&{self.query}"


SILENCE_AT = 1.5  # s of stream before the pen's stall in the silence cases: 150 samples
SILENCE = f"speed=2&stall={SILENCE_AT}:60"


def cases(kills: int, seed: int = 0) -> list[Case]:
    """``kills`` cases cycling through the kinds, their kill points drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    made: list[Case] = []
    faults = ("", "&drop=0.02", "&garbage=0.02&drop=0.01", "&flip=0.0005")
    for i in range(kills):
        s = int(rng.integers(0, 1000))
        fault = faults[i % len(faults)]
        kind = ("reboot", "reboot", "rows", "silence", "reboot", "rows")[i % 6]
        if kind == "reboot":  # the first rows after the reboot are the crash-prone ones
            n = int(rng.choice([0, 1, 2, 3, 5, 10, 20, 50, 150]))
            made.append(Case("reboot", n, s, f"speed=4&unplug={rng.uniform(0.5, 2):.2f}:0.3"
                                               + fault))
        elif kind == "rows":
            n = int(rng.integers(1, 3000))
            made.append(Case("rows", n, s, "speed=max&stall=4:0.5&unplug=12:0.2" + fault))
        else:  # at the silence's start, or seconds into it
            n = float(rng.choice([0.0, 2.0, 3.0, 4.0]))
            made.append(Case("silence", n, s, SILENCE))
    return made


CI_KILLS = 14
CI_CASES = cases(CI_KILLS)


@lru_cache(maxsize=8)
def _truth(seed: int, n: int) -> np.ndarray:
    return PenSimulator("paper", seed, RATE).read(n)


def truth(seed: int, n: int) -> np.ndarray:
    """The pen's first ``n`` samples (at least), (n, 8) int16: one generator per seed."""
    size = 1 << max(12, int(np.ceil(np.log2(max(n, 1)))))
    return _truth(seed, size)


@dataclass
class Killed:
    """What a kill left, and what the recorder had shown before it."""

    case: Case
    folder: Path
    seen_rows: list[int] = field(default_factory=list)  # seqs the CSV held at the kill
    stderr: str = ""


def _csv_rows(path: Path) -> tuple[list[int], int | None]:
    """(seqs of the complete data rows, index among them of the first row after the first
    restart gap line or None) of a CSV being written."""
    seqs, after = [], None
    with open(path, "rb") as f:
        f.readline()
        for line in f:
            if not line.endswith(b"\n"):
                break
            if line.startswith(b"#"):
                if b"reason=restart" in line and after is None:
                    after = len(seqs)
                continue
            seqs.append(int(line.split(b",", 1)[0]))
    return seqs, after


def _json_samples(folder: Path) -> int:
    """The ``samples`` count of the take's JSON as last rewritten (0 if none yet)."""
    for path in folder.glob("*.json"):
        try:
            return int(json.loads(path.read_text())["samples"])
        except (OSError, ValueError, KeyError):
            return 0
    return 0


def kill_at(case: Case, folder: Path) -> Killed:
    """Run the recorder on the case's pen; SIGKILL it at the case's point."""
    args = ["--port", case.url, "--label", "paper", "--out", str(folder)]
    proc = subprocess.Popen([sys.executable, "-c", ENTRY, *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    killed = Killed(case, folder)
    silent = re.compile(r"no data for (\d+(?:\.\d+)?) s")
    deadline = time.monotonic() + DEADLINE_S
    reconnected_at = None  # rows in the CSV when the recorder said it had reconnected
    try:
        while True:
            if proc.poll() is not None:
                raise AssertionError(f"{case}: the recorder ended before its kill point "
                                     f"(exit {proc.returncode}): {''.join(lines)[-2000:]}")
            if time.monotonic() > deadline:
                raise AssertionError(f"{case}: kill point not reached in {DEADLINE_S} s: "
                                     f"{''.join(lines)[-2000:]}")
            csvs = list(folder.glob("*.csv"))
            if case.kind == "silence":
                said = [float(m[1]) for ln in list(lines) for m in [silent.search(ln)] if m]
                if (said and max(said) >= case.n) or (case.n == 0 and _json_samples(folder)
                                                      >= round(SILENCE_AT * RATE)):
                    killed.seen_rows = _csv_rows(csvs[0])[0] if csvs else []
                    break
            elif csvs:
                seqs, after = _csv_rows(csvs[0])
                if after is None and case.kind == "reboot" and any(
                        "reconnected to" in ln for ln in list(lines)):
                    # no restart gap line (yet): count from the recorder's word instead
                    reconnected_at = len(seqs) if reconnected_at is None else reconnected_at
                    after = reconnected_at
                if (case.kind == "rows" and len(seqs) >= case.n) or (
                        case.kind == "reboot" and after is not None
                        and len(seqs) - after >= case.n):
                    killed.seen_rows = seqs
                    break
            time.sleep(0.002)
        proc.send_signal(signal.SIGKILL)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(30)
        reader.join(30)
    killed.stderr = "".join(lines)
    return killed


def verify(k: Killed) -> tuple[int, int, list[str]]:
    """Check every take the kill left against the pen: (takes, rows checked, failures)."""
    failures: list[str] = []
    takes = rows = 0
    paths = sorted(k.folder.glob("*.csv"))
    if len(paths) != 1:
        return 0, 0, [f"{k.case}: {len(paths)} takes, expected 1"]
    for path in paths:
        takes += 1
        try:
            take = read_take(path)
        except RecordingError as e:
            failures.append(f"{k.case}: take unreadable: {e}")
            continue
        rows += len(take.seq)
        failures += [f"{k.case}: {f}" for f in _check_take(take, k)]
    return takes, rows, failures


def _check_take(take, k: Killed) -> list[str]:
    seq, n = take.seq, len(take.seq)
    fails = []
    if take.meta["complete"]:
        fails.append("a killed take says it is complete")
    if seq[: len(k.seen_rows)].tolist() != k.seen_rows:
        fails.append(f"{len(k.seen_rows)} rows were in the file at the kill; the take has "
                     f"{n}, or others")
    # where each gap falls: the reader says so ("row"), or it is before the first row at or
    # after the gap's seq
    at = {id(g): g.get("row", int(np.searchsorted(seq, g["seq"]))) for g in take.meta["gaps"]}
    # runs between restart gaps: each must be one boot's samples, at one offset from seq
    cuts = [at[id(g)] for g in take.meta["gaps"]
            if g["reason"] == "restart" and 0 < at[id(g)] < n]
    reboots = 1 if "unplug=" in k.case.query else 0  # the simulated pen unplugs once at most
    if len(cuts) > reboots:
        fails.append(f"{len(cuts)} restart gaps for {reboots} reboots of the pen")
    for a, b in zip([0, *cuts], [*cuts, n], strict=True):
        if b <= a:
            continue
        if a == 0:
            offset = 0  # the first boot: the pen's counter is the simulator's index
        else:  # a later boot: the hand moved on while the cable was out; find where
            first = take.raw[a]
            pen = truth(k.case.seed, int(seq[a]) + 10_000)
            hits = np.flatnonzero(np.all(pen == first, axis=1))
            offset = int(hits[0] - seq[a]) if len(hits) == 1 else None
            if offset is None:
                fails.append(f"rows {a}..{b}: first row found {len(hits)} times in the pen")
                continue
        idx = seq[a:b] + offset
        pen = truth(k.case.seed, int(idx.max()) + 1)
        if not np.array_equal(take.raw[a:b], pen[idx]):
            bad = int(np.flatnonzero(np.any(take.raw[a:b] != pen[idx], axis=1))[0]) + a
            fails.append(f"row {bad} (seq {seq[bad]}) is not the pen's sample: a reboot the "
                         "take does not know about, or an invented row")
    jumps = {int(seq[i + 1]): int(seq[i + 1] - seq[i] - 1)
             for i in np.flatnonzero(np.diff(seq) != 1)}
    known = {g["seq"]: g["missing"] for g in take.meta["gaps"] if 0 < at[id(g)] < n}
    if any(known.get(s) != m for s, m in jumps.items()):
        fails.append(f"seq jumps {jumps} not all recorded as gaps {known}")
    segs = take.segments()
    if any(np.any(np.diff(seq[a:b]) != 1) for a, b in segs) or any(c not in
                                                                     {a for a, _ in segs}
                                                                     for c in cuts):
        fails.append("a segment spans a gap")
    if k.case.kind == "silence":  # every sample sent before the stall (the same burst may
        # bring a few from after it: those are checked above like any other row)
        before = round(SILENCE_AT * RATE)
        if seq[seq < before].tolist() != list(range(before)):
            fails.append(f"killed {k.case.n} s into a silence: {int(np.sum(seq < before))} of "
                         f"the {before} samples sent before it are in the take")
    return fails


@pytest.mark.parametrize("case", CI_CASES, ids=[f"{c.kind}-{c.n:g}-{c.seed}" for c in CI_CASES])
def test_killed_recorder_leaves_a_take_true_to_the_pen(case, tmp_path):
    killed = kill_at(case, tmp_path)
    takes, rows, failures = verify(killed)
    assert failures == [] and takes == 1, (failures, killed.stderr[-2000:])
    assert rows >= len(killed.seen_rows)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="SIGKILL tactile-record at many points; print "
                                            "kills, takes and rows checked, failures.")
    p.add_argument("--kills", type=int, default=100)
    p.add_argument("--seed", type=int, default=1)
    args = p.parse_args(argv)
    totals = {"kills": 0, "takes": 0, "rows": 0, "failures": 0}
    kinds: dict[str, int] = {}
    t0 = time.monotonic()
    for case in cases(args.kills, args.seed):
        with tempfile.TemporaryDirectory() as d:
            try:
                killed = kill_at(case, Path(d))
                takes, rows, failures = verify(killed)
            except AssertionError as e:
                takes, rows, failures = 0, 0, [str(e)]
        totals["kills"] += 1
        totals["takes"] += takes
        totals["rows"] += rows
        totals["failures"] += len(failures)
        kinds[case.kind] = kinds.get(case.kind, 0) + 1
        for f in failures:
            print(f"FAIL {f}", file=sys.stderr)
    print(" ".join(f"{k} {v}" for k, v in totals.items())
          + f" (kill points: {', '.join(f'{k} {v}' for k, v in sorted(kinds.items()))};"
          f" {time.monotonic() - t0:.0f} s)")
    return 1 if totals["failures"] else 0


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.exit(main())
