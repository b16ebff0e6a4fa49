"""Decoder fuzzing: corrupted streams against ground truth, and the decoder's worst-case speed.

    python bench/fuzz.py --cases N [--seed S] [--first I] [--jobs J] [--out F] [--no-speed]
    python bench/fuzz.py --summary CHUNK.json ...

Each case is a short stream, binary frames or CSV lines, built from samples whose contents say
which sample they are (binary: channel 0 holds its index in the case; CSV: the first field), then
corrupted in one or more of the ways a serial link and a hostile device do it, and fed to a
``StreamDecoder`` in reads of random sizes. What came out is checked against the truth; the
failure columns (each should be 0) are:

* ``exceptions``: ``feed()`` raised;
* ``invented``: a sample delivered that was never sent, or with other contents;
* ``duplicated``: a sample delivered twice;
* ``reordered``: a sample delivered after one sent later, or a timestamp that went back (but
  for the one reading ``device/PROTOCOL.md`` documents, "Restart": a frame behind its whole
  run, with a count below 4,096 and a header since the sample delivered before it, delivered
  after a restart gap: the bytes of a device restarting again, see :func:`restart_reading`);
* ``bad_gaps``: the host sequence jumps without gaps that account for it, a gap where nothing
  was lost (a phantom drop or restart), or a device restart with no restart gap;
* ``unhonoured``: a sample delivered after a header of a protocol version the decoder refuses;
* ``unrecovered``: a sample of an intact frame (its bytes and its delimiter all there, whatever
  was glued in front of them) or of an intact CSV row not delivered, when no intact frame sent
  after it came before it.

Then the throughput: the decoder on adversarial inputs (noise, runs of 0x01 and 0x02, a MB
without a delimiter, all-comma lines, ...) in reads of several sizes, each against clean frames
decoded in the same run at the same read size (the reference). ``--cases`` splits across
``--jobs`` processes; case ``i`` depends only on ``(seed, i)``, so a long run can be cut into
chunks (``--first``, ``--out``) whose totals ``--summary`` adds up, checking that they cover one
seed's cases without a hole or an overlap.
"""

from __future__ import annotations

import argparse
import json
import random
import sys
import time
import traceback
from dataclasses import asdict, dataclass, field, fields
from functools import cache

import numpy as np

from tactile.device.protocol import (
    MAX_ENCODED,
    REPLAY_WINDOW,
    SEQ_MODULO,
    ChannelSpec,
    DeviceInfo,
    Gap,
    Samples,
    StreamDecoder,
    encode_header,
    encode_samples,
)

BINARY_KINDS = ("flip", "burst", "insert", "delete", "dup", "swap", "drop", "truncate",
                "header", "reboot", "midstart", "mix", "noise")
CSV_KINDS = ("csv_long_row", "csv_long_name", "csv_midline", "csv_numbers", "csv_garbage",
             "csv_mix")
KINDS = BINARY_KINDS + CSV_KINDS
FAILURES = ("exceptions", "invented", "duplicated", "reordered", "bad_gaps", "unhonoured",
            "unrecovered")


@dataclass
class Totals:
    cases: int = 0
    samples_sent: int = 0
    samples_expected: int = 0  # samples of intact frames/rows the decoder must deliver
    samples_delivered: int = 0
    bytes_fed: int = 0
    exceptions: int = 0
    invented: int = 0
    duplicated: int = 0
    reordered: int = 0
    bad_gaps: int = 0
    unhonoured: int = 0
    unrecovered: int = 0
    by_kind: dict = field(default_factory=dict)  # kind -> cases
    first_failure: str = ""  # "seed:index kind column" of the first failing case
    failing: list = field(default_factory=list)  # "index kind column" of failing cases (<= 100)

    def add(self, other: Totals) -> None:
        for f in fields(self):
            if f.name == "by_kind":
                for k, v in other.by_kind.items():
                    self.by_kind[k] = self.by_kind.get(k, 0) + v
            elif f.name == "first_failure":
                self.first_failure = self.first_failure or other.first_failure
            elif f.name == "failing":
                self.failing = sorted(self.failing + other.failing,
                                      key=lambda x: int(x.split()[0]))[:100]
            else:
                setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))

    @property
    def failures(self) -> int:
        return sum(getattr(self, f) for f in FAILURES)


# ---------------------------------------------------------------------------------------------
# Binary cases


@dataclass
class Item:
    """A piece of the stream: a frame (with what it carries) or inserted bytes."""

    data: bytes
    kind: str  # "samples", "header", "bad_header" (unsupported version) or "garbage"
    ids: tuple[int, int] = (0, 0)  # samples: [first, end) indices in the case
    session: int = 0
    damaged: bool = False  # set once the ops are done: see binary_case
    orig: bytes = b""  # the frame as sent (with its delimiter); garbage: empty

    def __post_init__(self) -> None:
        if not self.orig and self.kind != "garbage":
            self.orig = self.data


@cache
def _device(width: int, version: int = 1, tag: str = "") -> DeviceInfo:
    chans = tuple(ChannelSpec(f"{tag}c{i}", "u", 1.0) for i in range(width))
    return DeviceInfo(100.0, chans, "fuzz", version)


@cache
def _header(width: int) -> bytes:
    return encode_header(_device(width))


def _noise(r: random.Random, n: int, zeros: bool = True) -> bytes:
    blob = r.randbytes(n)
    return blob if zeros else blob.replace(b"\x00", bytes([r.randint(1, 255)]))


def _pick(r: random.Random, n: int) -> int:
    """A position in ``n`` bytes; 0 when there are none (an item a truncate emptied)."""
    return r.randrange(n) if n else 0


def binary_case(r: random.Random, kind: str):
    """(items, truth rows (n, C) int16, session of each sample, device seq of each)."""
    width = 8 if r.random() < 0.7 else r.randint(1, 32)
    per = r.choice((1, 1, 1, 2, 4, r.randint(1, 32)))
    n = r.randint(1, 90)
    every = r.choice((10, 50, 100))
    head = _header(width)
    raw = np.random.default_rng(r.getrandbits(64)).integers(-32768, 32768, (n, width),
                                                             dtype=np.int16)
    raw[:, 0] = np.arange(n)
    reboot = r.randint(1, n - 1) if kind in ("reboot", "mix") and n >= 2 else None
    session = np.zeros(n, np.int64)
    devseq = np.zeros(n, np.int64)
    items: list[Item] = []
    seq = r.choice((0, r.randrange(SEQ_MODULO)))
    t = r.randrange(SEQ_MODULO)
    sess, since = 0, 0
    s = 0
    while s < n:
        if s == reboot:
            sess, seq, t, since = 1, 0, r.randrange(20_000), 0
        if since % every == 0 or s == reboot:
            items.append(Item(head, "header", session=sess))
        k = min(per, n - s, (reboot - s) if reboot is not None and s < reboot else n)
        items.append(Item(encode_samples(seq, t, raw[s : s + k]), "samples", (s, s + k), sess))
        session[s : s + k] = sess
        devseq[s : s + k] = seq + np.arange(k)  # unwrapped: `seq` counts on past 2**32
        seq += k
        t += k * 10_000
        since += k
        s += k
    ops = [kind] if kind != "mix" else r.sample(
        [k for k in BINARY_KINDS if k not in ("mix", "noise", "reboot")], r.randint(2, 4))
    flips = 0
    for op in ops:
        if not items:  # all dropped
            break
        j = r.randrange(len(items))
        it = items[j]
        if op in ("flip", "burst") and flips < 3 and it.data:  # (a truncate may empty it)
            flips += 1
            b = bytearray(it.data)
            pos = r.randrange(len(b))
            if op == "flip":
                b[pos] ^= 1 << r.randrange(8)
            else:  # a burst of at most 16 bits: always caught by CRC-16 within a frame
                start = pos * 8 + r.randrange(8)
                length = r.randint(2, 16)
                for bit in range(start, min(start + length, len(b) * 8)):
                    if bit in (start, start + length - 1) or r.random() < 0.5:
                        b[bit // 8] ^= 0x80 >> (bit % 8)
            it.data = bytes(b)
        elif op == "insert":
            blob = _noise(r, r.randint(1, 40), zeros=r.random() < 0.5)
            if r.random() < 0.5:  # between frames
                items.insert(j, Item(blob, "garbage"))
            else:  # inside a frame
                pos = _pick(r, len(it.data))
                it.data = it.data[:pos] + blob + it.data[pos:]
        elif op == "delete":
            pos = _pick(r, len(it.data))
            cut = r.randint(1, 20)
            it.data = it.data[:pos] + it.data[pos + cut :]
        elif op == "truncate":  # a frame cut short, its delimiter lost: glued to the next
            it.data = it.data[: _pick(r, len(it.data))]
        elif op == "dup":  # re-sent, right away or up to ~300 frames later (not past a reboot:
            # a link does not carry a frame from before a device restart after it)
            later = min(len(items), j + 1 + r.choice((0, 0, r.randint(0, 300))))
            for m in range(j + 1, later):
                if items[m].kind in ("samples", "header") and items[m].session != it.session:
                    later = m
                    break
            items.insert(later, Item(it.data, it.kind, it.ids, it.session, orig=it.orig))
        elif op == "swap" and j + 1 < len(items) and it.session == items[j + 1].session:
            # (not across a reboot: a link does not deliver the rebooted device's frames first)
            items[j], items[j + 1] = items[j + 1], items[j]
        elif op == "drop":
            del items[j]
        elif op == "header":  # crafted: a protocol version we do not read, or other names
            if r.random() < 0.5:
                bad = encode_header(_device(width, version=r.choice((0, 2, 99, 255))))
                items.insert(j, Item(bad, "bad_header"))
            else:
                items.insert(j, Item(encode_header(_device(width, tag="x")), "header"))
        elif op == "midstart":  # the port opened in the middle of a frame
            cut = _pick(r, len(items[0].data))
            items[0].data = items[0].data[cut:]
    if kind == "noise":
        items = [Item(_noise(r, r.randint(1, 3000)), "garbage")]
    for it in items:
        # intact: the frame's bytes and its delimiter are all there, whatever was glued in
        # front of them (bytes inserted at its start, a cut that removed nothing)
        it.damaged = it.kind != "garbage" and not it.data.endswith(it.orig)
    return items, raw, session, devseq


def _expected_binary(items: list[Item], n: int):
    """Samples the decoder must deliver and samples it must not (refused)."""
    must = np.zeros(n, bool)
    refused = np.zeros(n, bool)
    honoured = np.zeros(n, bool)
    refusing = False
    top = -1  # highest index of an intact, honoured samples frame so far
    for it in items:
        if it.damaged:
            continue
        if it.kind == "bad_header":
            refusing = True
        elif it.kind == "header":
            refusing = False
        elif it.kind == "samples":
            a, b = it.ids
            if refusing:
                refused[a:b] = True
                continue
            honoured[a:b] = True
            lo = max(a, top + 1)
            must[lo:b] = True
            top = max(top, b - 1)
    return must, refused & ~honoured


def restart_reading(items: list[Item], devseq: np.ndarray):
    """What the stream shows of the documented reading of an ambiguous frame
    (``device/PROTOCOL.md``, "Restart"): a frame that went back behind its whole run, with a
    count a fresh device has (below ``REPLAY_WINDOW``) and a header since the last delivered
    frame, is the first frame of a restarted device, as the same bytes are when a device
    restarts again. Returns ``reads_as_restart(prev_id, sid)``: sample ``sid`` is the first of
    an intact frame sent with such a count, and a header came after the first intact frame
    carrying ``prev_id`` (the sample delivered before it) and before it."""
    copies: dict[int, list[int]] = {}  # sample id -> positions of intact frames carrying it
    heads = [pos for pos, it in enumerate(items)
             if not it.damaged and it.kind in ("header", "bad_header")]
    for pos, it in enumerate(items):
        if it.kind == "samples" and not it.damaged:
            for i in range(*it.ids):
                copies.setdefault(i, []).append(pos)

    def reads_as_restart(prev_id: int, sid: int) -> bool:
        if devseq[sid] % SEQ_MODULO >= REPLAY_WINDOW or not copies.get(prev_id):
            return False
        first = copies[prev_id][0]
        return any(first < h < f for f in copies.get(sid, ()) for h in heads)

    return reads_as_restart


def check_binary(events, raw, session, devseq, must, refused, t: Totals,
                 reads_as_restart=None) -> str:
    """Add one case's failures to ``t``; returns the first failing column's name or ''.

    ``reads_as_restart`` (from :func:`restart_reading`), when given, accepts the documented
    reading of a frame that went back after a header as a restarted device's first frame."""
    before = {f: getattr(t, f) for f in FAILURES}
    n = len(raw)
    seen = np.zeros(n, bool)
    last_id = -1
    run_min = n  # smallest id delivered since the last restart gap
    prev = None  # (host seq, id) of the previous delivered sample
    pending: list[Gap] = []
    last_t = None
    for ev in events:
        if isinstance(ev, Gap):
            pending.append(ev)
            continue
        if not isinstance(ev, Samples):
            continue
        if last_t is not None and ev.t_us < last_t:
            t.reordered += 1
        last_t = ev.t_us
        for k in range(len(ev.raw)):
            row = ev.raw[k]
            host = ev.seq + k
            sid = int(row[0])
            t.samples_delivered += 1
            if not (0 <= sid < n) or not np.array_equal(row, raw[sid]):
                t.invented += 1
                continue
            if refused[sid]:
                t.unhonoured += 1
            if seen[sid]:
                t.duplicated += 1
                continue
            seen[sid] = True
            restart = any(g.reason == "restart" for g in pending)
            # the documented reading: a frame behind its whole run, read as a restarted device's
            restarted = (sid < last_id and restart and sid < run_min and k == 0
                         and reads_as_restart is not None and prev is not None
                         and reads_as_restart(prev[1], sid))
            if restarted:
                last_id = sid
            elif sid < last_id:
                t.reordered += 1
            last_id = max(last_id, sid)
            run_min = sid if restart else min(run_min, sid)
            if prev is not None:
                p_host, p_id = prev
                jump = host - p_host - 1
                accounted = sum(g.missing for g in pending if g.reason in ("drop", "rejected"))
                if session[sid] == session[p_id] and not restarted:
                    dev_jump = int(devseq[sid] - devseq[p_id]) - 1
                    if restart or jump != dev_jump or accounted != jump:
                        t.bad_gaps += 1
                elif not restart or accounted != jump:
                    t.bad_gaps += 1
            prev = (host, sid)
            pending = []
    t.unrecovered += int(np.count_nonzero(must & ~seen))
    t.samples_expected += int(np.count_nonzero(must))
    for f in FAILURES:
        if getattr(t, f) != before[f]:
            return f
    return ""


# ---------------------------------------------------------------------------------------------
# CSV cases

_ODD_NUMBERS = ("1_0", "0x10", "inf", "-inf", "nan", "NaN", "1e400", "\u0661", "1.2.3", "--1",
                "1e", "e5", ".", "+", "1,5e3f", "0b11", "١٢", "  ", "1 2")


def csv_case(r: random.Random, kind: str):
    """(lines as bytes, truth values (n, C), which lines are intact rows and their ids)."""
    width = r.choice((1, 2, 3, 8, 8, r.randint(1, 32)))
    n = r.randint(3, 60)
    vals = [[float(i)] + [float(f"{r.uniform(-1e3, 1e3):.6g}") for _ in range(width - 1)]
            for i in range(n)]
    rows = [(",".join(f"{v:.7g}" if j else str(int(v)) for j, v in enumerate(row)) + "\n")
            .encode() for row in vals]
    lines: list[tuple[bytes, int | None]] = []  # (line, id of an intact row)
    if r.random() < 0.7:
        lines.append(((",".join(f"n{i}" for i in range(width)) + "\n").encode(), None))
    lines += [(row, i) for i, row in enumerate(rows)]
    ops = [kind] if kind != "csv_mix" else r.sample(
        [k for k in CSV_KINDS if k != "csv_mix"], r.randint(2, 4))
    for op in ops:
        j = r.randrange(len(lines) + 1)
        if op == "csv_long_row":
            k = r.choice((33, 34, 100, 2000))
            lines.insert(j, ((",".join(["1"] * k) + "\n").encode(), None))
        elif op == "csv_long_name":
            names = [f"n{i}" for i in range(width)]
            names[r.randrange(width)] = "x" * r.randint(33, 300)
            lines.insert(j, ((",".join(names) + "\n").encode(), None))
        elif op == "csv_numbers":
            for _ in range(r.randint(1, 5)):
                row = [str(r.randint(0, 9)) for _ in range(width)]
                row[r.randrange(width)] = r.choice(_ODD_NUMBERS)
                lines.insert(r.randrange(len(lines) + 1), ((",".join(row) + "\n").encode(), None))
        elif op == "csv_garbage":
            for _ in range(r.randint(1, 4)):
                # unreadable lines (CSV has no checksum: a garbled line that still reads as a
                # row of the right width cannot be told from one)
                blob = r.choice((b",,,,,,,,,,\n", b",\n", b"\xff\xfe\n", b"boot: ok!\n", b"\r\n",
                                 b"\x80" + _noise(r, r.randint(0, 40)).replace(b"\n", b"") + b"\n"))
                lines.insert(r.randrange(len(lines) + 1), (blob, None))
    data = b"".join(line for line, _ in lines)
    ids = [i for _, i in lines]
    cut = 0
    if kind in ("csv_midline", "csv_mix") and r.random() < 0.8:
        cut = r.randrange(len(lines[0][0]))  # the port opened within the first line
    # a clean tail: the stream goes on after the damage
    tail_rows = [[float(n + i)] + [float(f"{r.uniform(-1e3, 1e3):.6g}") for _ in range(width - 1)]
                 for i in range(3)]
    tail = b"".join((",".join(f"{v:.7g}" if j else str(int(v)) for j, v in enumerate(row))
                     + "\n").encode() for row in tail_rows)
    vals += tail_rows
    return data[cut:] + tail, np.array(vals), ids, [n, n + 1, n + 2], cut


def check_csv(events, vals, must_ids, t: Totals) -> str:
    before = {f: getattr(t, f) for f in FAILURES}
    n = len(vals)
    seen = np.zeros(n, bool)
    last_id = -1
    for ev in events:
        if not isinstance(ev, Samples):
            continue
        for row in ev.raw:
            t.samples_delivered += 1
            sid = int(row[0]) if row[0] == int(row[0]) else -1
            if not (0 <= sid < n and len(row) == vals.shape[1] and np.array_equal(row, vals[sid])):
                t.invented += 1
                continue
            if seen[sid]:
                t.duplicated += 1
                continue
            seen[sid] = True
            if sid < last_id:
                t.reordered += 1
            last_id = sid
    must = np.zeros(n, bool)
    must[must_ids] = True
    t.unrecovered += int(np.count_nonzero(must & ~seen))
    t.samples_expected += int(np.count_nonzero(must))
    for f in FAILURES:
        if getattr(t, f) != before[f]:
            return f
    return ""


# ---------------------------------------------------------------------------------------------
# Running cases


def feed_in_reads(dec: StreamDecoder, data: bytes, r: random.Random) -> list:
    events = []
    i = 0
    sizes = r.choice(((1, 8), (1, 64), (16, 300), (16, 300), (1000, 5000), (1000, 5000)))
    while i < len(data):
        k = r.randint(*sizes)
        events += dec.feed(data[i : i + k])
        i += k
    return events + dec.finish()  # the stream ends: what it still holds back


def run_case(seed: int, index: int, t: Totals) -> None:
    r = random.Random(seed * 1_000_003 + index)
    kind = KINDS[r.randrange(len(KINDS))]
    t.cases += 1
    t.by_kind[kind] = t.by_kind.get(kind, 0) + 1
    failed = ""
    try:
        if kind.startswith("csv"):
            data, vals, ids, tail_ids, cut = csv_case(r, kind)
            line_start = cut == 0 and r.random() < 0.5  # a file, or a port opened in a line
            dec = StreamDecoder(r.choice(("auto", "csv")), line_start=line_start)
            t.samples_sent += len(vals)
            t.bytes_fed += len(data)
            events = feed_in_reads(dec, data, r)
            # every intact row but the first line when the stream may begin within it
            must = [i for i in ids[0 if line_start else 1 :] if i is not None] + tail_ids
            failed = check_csv(events, vals, must, t)
        else:
            items, raw, session, devseq = binary_case(r, kind)
            data = b"".join(it.data for it in items)
            must, refused = _expected_binary(items, len(raw))
            dec = StreamDecoder(r.choice(("auto", "binary")))
            t.samples_sent += len(raw)
            t.bytes_fed += len(data)
            events = feed_in_reads(dec, data, r)
            failed = check_binary(events, raw, session, devseq, must, refused, t,
                                  restart_reading(items, devseq))
    except Exception:  # noqa: BLE001 - the column counts them
        t.exceptions += 1
        failed = "exceptions: " + traceback.format_exc(limit=3).replace("\n", " | ")
    if failed and not t.first_failure:
        t.first_failure = f"seed {seed} case {index} ({kind}): {failed}"
    if failed and len(t.failing) < 100:
        t.failing.append(f"{index} {kind} {failed.split(':')[0]}")


def run_range(seed: int, start: int, stop: int) -> Totals:
    t = Totals()
    for i in range(start, stop):
        run_case(seed, i, t)
    return t


def _run_range_args(args) -> Totals:
    return run_range(*args)


def run(cases: int, seed: int = 0, jobs: int = 1, first: int = 0) -> Totals:
    """Run cases ``first..first+cases-1`` of ``seed``, split over ``jobs`` processes."""
    if jobs <= 1:
        return run_range(seed, first, first + cases)
    import multiprocessing

    step = max(1, min(10_000, cases // (jobs * 8)))
    stop = first + cases
    parts = [(seed, a, min(a + step, stop)) for a in range(first, stop, step)]
    total = Totals()
    with multiprocessing.get_context("fork").Pool(jobs) as pool:
        for part in pool.imap_unordered(_run_range_args, parts):
            total.add(part)
            print(f"  ... {total.cases} cases, {total.failures} failures", file=sys.stderr,
                  flush=True)
    return total


# ---------------------------------------------------------------------------------------------
# Throughput


def clean_frames(nbytes: int) -> bytes:
    """The pen's stream (8 channels, 1 sample per frame, a header per 100), about ``nbytes``."""
    rng = np.random.default_rng(0)
    head = _header(8)
    out = bytearray()
    s = 0
    while len(out) < nbytes:
        if s % 100 == 0:
            out += head
        out += encode_samples(s, s * 10_000, rng.integers(-2000, 2000, (1, 8)))
        s += 1
    return bytes(out)


def _crafted(nbytes: int) -> bytes:
    """Chunks in which every 13th byte starts a valid COBS chain to the chunk's end with a
    samples frame's type, channel and sample counts that give exactly that length: each
    candidate passes every test but the CRC (the search's worst case)."""
    units = (MAX_ENCODED // 13) * 13
    chunk = bytearray(b"\x0d\x02" + b"\x01" * 8 + b"\x01\x01\x01") * (units // 13)
    for i in range(0, units, 13):
        length = units - i - 1  # decoded length of chunk[i:]
        pairs = [(c, k) for c in range(1, 33) for k in range(1, 33) if 13 + 2 * c * k == length]
        if pairs:
            chunk[i + 10], chunk[i + 11] = pairs[0]
    return (bytes(chunk) + b"\x00") * (nbytes // (units + 1) + 1)


def adversarial_inputs(nbytes: int) -> dict[str, tuple[str, bytes]]:
    """name -> (decoder mode, bytes)."""
    rng = np.random.default_rng(1)
    noise = rng.integers(0, 256, nbytes, dtype=np.uint8).tobytes()
    csv_noise = rng.choice(np.frombuffer(b"0123456789,.-e\n ", np.uint8), nbytes).tobytes()
    big = (b"1" * 4000 + b"\n") * (nbytes // 4001 + 1)
    return {
        "uniform noise": ("auto", noise),
        "noise without 0x00": ("auto", noise.replace(b"\x00", b"\x01")),
        "0x01 run (no delimiter)": ("auto", b"\x01" * nbytes),
        "0x01 x 2573 + 0x00": ("binary", (b"\x01" * MAX_ENCODED + b"\x00") * (nbytes // 2574)),
        "0x02 x 60 + 0x00": ("binary", (b"\x02" * 60 + b"\x00") * (nbytes // 61)),
        "0x02 x 2573 + 0x00": ("binary", (b"\x02" * MAX_ENCODED + b"\x00") * (nbytes // 2574)),
        "03 01 01 repeated + 0x00": ("binary", (b"\x03\x01\x01" * 857 + b"\x00")
                                     * (nbytes // 2572)),
        "crafted frame starts": ("binary", _crafted(nbytes)),
        "all-comma lines": ("auto", (b"," * 4000 + b"\n") * (nbytes // 4001)),
        "short comma lines": ("auto", b",,,,,,,,\n" * (nbytes // 9)),
        "4000-digit lines": ("csv", big[:nbytes]),
        "CSV-like noise": ("auto", csv_noise),
    }


def _rate(data: bytes, mode: str, read: int, min_s: float = 0.3) -> tuple[float, float]:
    """(kB per wall-clock second, kB per CPU second) of feeding ``data`` in ``read``-byte reads
    (repeated for at least ``min_s`` of wall-clock time). On a shared machine the wall-clock
    rate falls with the share of a core the process gets; the CPU rate much less."""
    total, wall, cpu = 0, 0.0, 0.0
    while wall < min_s:
        dec = StreamDecoder(mode)
        t0, c0 = time.perf_counter(), time.process_time()
        for i in range(0, len(data), read):
            dec.feed(data[i : i + read])
        wall += time.perf_counter() - t0
        cpu += time.process_time() - c0
        total += len(data)
    return total / wall / 1e3, total / max(cpu, 1e-6) / 1e3


def throughput(nbytes: int = 1_000_000, reads=(1, 64, 4096), rounds: int = 3) -> list[dict]:
    """Rows of (input, mode, read size, kB/s, clean frames' kB/s at that read size, ratio, and
    the same per CPU second). The reference, the pen's clean stream at the same read size, is
    measured right beside each input, alternating ``rounds`` times; each rate is the best of
    its rounds (the least disturbed by other work). One-byte reads take a tenth of the bytes."""
    rows = []
    clean = clean_frames(nbytes)
    for name, (mode, data) in adversarial_inputs(nbytes).items():
        for read in reads:
            n = nbytes if read > 1 else nbytes // 10
            best = [0.0] * 4  # input wall, input cpu, clean wall, clean cpu
            for _ in range(rounds):
                rates = _rate(data[:n], mode, read) + _rate(clean[:n], "auto", read)
                best = [max(x, y) for x, y in zip(best, rates, strict=True)]
            kbs, cpu, ref, ref_cpu = best
            rows.append({"input": name, "mode": mode, "read": read, "kB/s": round(kbs),
                         "clean kB/s": round(ref), "ratio": round(kbs / ref, 2),
                         "cpu kB/s": round(cpu), "clean cpu kB/s": round(ref_cpu)})
    return rows


def _print_totals(t: Totals, what: str) -> None:
    print(f"cases {t.cases} ({what}): "
          f"{t.samples_sent} samples sent, {t.samples_expected} expected, "
          f"{t.samples_delivered} delivered, {t.bytes_fed / 1e6:.1f} MB fed")
    print("  " + "  ".join(f"{f} {getattr(t, f)}" for f in FAILURES))
    print("  kinds: " + ", ".join(f"{k} {v}" for k, v in sorted(t.by_kind.items())))
    if t.first_failure:
        print("  first failure: " + t.first_failure)
    if t.failing:
        print("  failing cases: " + ", ".join(t.failing))


def summary(paths: list[str]) -> int:
    """Merge chunk files written by ``--out``: one seed, ranges that neither overlap nor leave
    a hole. Prints the merged totals; exit status 1 on a failure or a bad set of chunks."""
    chunks = []
    for path in paths:
        with open(path) as f:
            d = json.load(f)
        chunks.append((d["first"], d["first"] + d["totals"]["cases"], d["seed"], path, d))
    chunks.sort()
    seeds = {c[2] for c in chunks}
    if len(seeds) != 1:
        print(f"chunks of seeds {sorted(seeds)}: a summary is of one seed", file=sys.stderr)
        return 1
    total, end = Totals(), chunks[0][0]
    for a, b, _, path, d in chunks:
        if a != end:
            print(f"{path}: starts at case {a}, the chunks before end at {end}", file=sys.stderr)
            return 1
        end = b
        total.add(Totals(**d["totals"]))
    spent = sum(c[4]["seconds"] for c in chunks)
    _print_totals(total, f"seed {seeds.pop()}, cases {chunks[0][0]}..{end - 1}, "
                         f"{len(chunks)} chunks, {spent:.0f} s")
    return 1 if total.failures else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=10_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--first", type=int, default=0, help="index of the first case to run")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--out", help="also write the totals to this JSON file (a chunk)")
    ap.add_argument("--summary", nargs="+", metavar="CHUNK",
                    help="merge chunk files written by --out and print their totals (no run)")
    ap.add_argument("--no-speed", action="store_true", help="skip the throughput part")
    ap.add_argument("--speed-bytes", type=int, default=1_000_000)
    args = ap.parse_args(argv)
    if args.summary:
        return summary(args.summary)
    t0 = time.perf_counter()
    t = run(args.cases, args.seed, args.jobs, args.first)
    dt = time.perf_counter() - t0
    _print_totals(t, f"seed {args.seed}, cases {args.first}..{args.first + args.cases - 1}, "
                     f"{dt:.0f} s, {args.jobs} jobs")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"seed": args.seed, "first": args.first, "seconds": round(dt, 1),
                       "totals": asdict(t)}, f)
    if not args.no_speed:
        rows = throughput(args.speed_bytes)
        print(f"{'input':28s} {'mode':6s} {'read':>5s} {'kB/s':>8s} {'clean':>8s} {'ratio':>6s}"
              f" {'cpu kB/s':>9s} {'clean cpu':>9s}")
        for row in rows:
            print(f"{row['input']:28s} {row['mode']:6s} {row['read']:5d} {row['kB/s']:8d} "
                  f"{row['clean kB/s']:8d} {row['ratio']:6.2f} {row['cpu kB/s']:9d} "
                  f"{row['clean cpu kB/s']:9d}")
        worst = min(rows, key=lambda x: x["ratio"])
        print(f"worst: {worst['input']} ({worst['mode']}, {worst['read']}-byte reads) "
              f"{worst['kB/s']} kB/s, {worst['ratio']} x clean frames; slowest per CPU second: "
              f"{min(row['cpu kB/s'] for row in rows)} kB/s")
        print(json.dumps({"worst": worst}))
    return 1 if t.failures else 0


if __name__ == "__main__":
    sys.exit(main())
