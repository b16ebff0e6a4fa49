"""Soak: tactile-run on simulated pen data with a fault mix, checked against ground truth.

    python bench/soak.py --seconds 3600        # an hour of pen data, at the link's full speed

Runs the real command (``python -m tactile.runtime.commands.run``) on a ``sim://`` port at
``speed=max`` whose pen is hit by garbage bytes, bit flips, dropped frames, stalls and unplugs
(many of each), and compares what it prints with the ground truth of the same link, replayed
here (:class:`~tactile.device.sim.PenLink` with ``trace=True`` gives the fate of every
sample; its faults do not depend on how the port is read):

* windows: the sequence number of every window's last sample (the receiver's numbering, which
  cannot count the samples lost across an unplug), and each window's label and probabilities
  against :class:`~tactile.runtime.stream.Stream` fed with the simulator's samples directly,
  run by run (a run: consecutive samples that arrived intact, between two breaks);
* gaps: each gap event (samples missing, reason) against the break between two runs;
* labels back one window after each break: the first window after a break ends exactly
  ``window`` samples into the new run;
* the resident memory (RSS) of the tactile-run process, sampled every ``--rss-every`` s.

Prints figures; exits 1 if anything differs from the ground truth.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def fault_url(args: argparse.Namespace) -> str:
    return (f"sim://?texture={args.texture}&seed={args.seed}&speed=max&seconds={args.seconds:g}"
            f"&garbage={args.garbage:g}&flip={args.flip:g}&drop={args.drop:g}"
            f"&stall=20:{args.stall_s:g}&stall_every={args.stall_every:g}"
            f"&unplug=30:{args.unplug_s:g}&unplug_every={args.unplug_every:g}")


def ground_truth(query: str):
    """Replay the link (replugging at each unplug, as a reader that reconnects does): the link
    (its counts and intact headers), the fate of each sample (1 = arrived intact), the bytes
    sent and where each unplug fell (stream index)."""
    from tactile.device.sim import LinkConfig, PenLink

    link = PenLink(LinkConfig.from_query(query), trace=True)
    sent, unplugs = 0, []
    while not link.finished:
        out_for = link.unplug_due()
        if out_for is not None:
            unplugs.append(link.sim.n_read)  # the first sample the pen did not make
            link.restart(link.stream_time + out_for)
            continue
        sent += len(link.produce(4096))
    return link, np.frombuffer(bytes(link.delivered), np.uint8), sent, unplugs


def runs_of(delivered: np.ndarray, start: int) -> list[tuple[int, int]]:
    """Maximal runs [a, b) of consecutive delivered samples from ``start`` on."""
    ok = np.concatenate([[0], delivered[start:].astype(np.int8), [0]])
    edges = np.flatnonzero(np.diff(ok))
    return [(int(a) + start, int(b) + start) for a, b in zip(edges[::2], edges[1::2])]


def reference(model_path: Path, texture: str, seed: int, n: int, runs):
    """{end index: probabilities} of every window, from the simulator's samples fed run by run
    to a Stream (no link, no decoder)."""
    from tactile.device.sim import PenSimulator
    from tactile.runtime.model import Model
    from tactile.runtime.stream import Stream

    model = Model(model_path)
    sim = PenSimulator(texture, seed)
    raw = sim.read(n)
    # the model's channels by name, in its order (as tactile-run takes them from the pen)
    names = [c.name for c in sim.info.channels]
    used = [names.index(name) for name in model.contract.channels]
    raw = raw[:, used]
    scale = np.array([sim.info.channels[i].scale for i in used])
    offset = np.array([sim.info.channels[i].offset for i in used])
    stream = Stream.for_model(model)
    out = {}
    for a, b in runs:
        stream.reset()
        stream.accept((raw[a:b] * scale + offset).astype(np.float32), a, a * 10_000)
        while stream.ready():
            lab = stream.classify()
            out[lab.seq] = np.array([lab.probabilities[c] for c in model.contract.classes])
    return out, model.contract.classes


def rss_mb(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/status") as f:
            kb = next(int(ln.split()[1]) for ln in f if ln.startswith("VmRSS:"))
    except (OSError, StopIteration):
        return None
    return kb / 1024


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=3600.0, help="pen data, stream seconds")
    p.add_argument("--model", type=Path, default=REPO / "models" / "pen-exp2.onnx")
    p.add_argument("--texture", default="paper")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--garbage", type=float, default=0.02,
                   help="probability of 1-32 random bytes before a frame")
    p.add_argument("--flip", type=float, default=1e-4,
                   help="probability of a flipped bit, per byte")
    p.add_argument("--drop", type=float, default=0.002, help="probability of a lost frame")
    p.add_argument("--stall-s", type=float, default=0.5, help="each stall's length, s")
    p.add_argument("--stall-every", type=float, default=30.0, help="stream s between stalls")
    p.add_argument("--unplug-s", type=float, default=0.3, help="each unplug's length, s")
    p.add_argument("--unplug-every", type=float, default=60.0, help="stream s between unplugs")
    p.add_argument("--idle", type=float, default=30.0,
                   help="give up after this long without output, s")
    p.add_argument("--rss-every", type=float, default=1.0, help="RSS sampling period, s")
    args = p.parse_args(argv)

    url = fault_url(args)
    query = url.split("?", 1)[1]
    t0 = time.perf_counter()
    link, delivered, sent, unplugs = ground_truth(query)
    n = link.sim.n_read
    inj = link.injected
    from tactile.runtime.model import Model

    contract = Model(args.model).contract
    window, hop = contract.window, contract.hop
    runs = runs_of(delivered, link.headers[0] if link.headers else n)
    # the receiver numbers samples (host seq) without the ones lost across an unplug, which
    # it cannot count: host seq = stream index - what the unplugs before it cost
    lost_unseen, cost = [], 0
    for (_, b0), (a1, _) in zip([(0, 0), *runs], runs):
        if any(b0 <= u < a1 for u in unplugs):
            cost += a1 - b0
        lost_unseen.append(cost)
    host = {a: off for (a, _), off in zip(runs, lost_unseen)}
    want_ends = [e for a, b in runs for e in range(a + window - 1, b, hop)]
    want_seqs = [e - host[a] for a, b in runs for e in range(a + window - 1, b, hop)]
    ref, classes = reference(args.model, args.texture, args.seed, n, runs)
    t_truth = time.perf_counter() - t0

    cmd = [sys.executable, "-m", "tactile.runtime.commands.run", "--model", str(args.model),
           "--port", url, "--stall-timeout", f"{min(0.2, args.stall_s / 2):g}",
           "--status-every", "3600"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    t1 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)
    rss: list[tuple[float, float]] = []
    done = threading.Event()

    def sample() -> None:
        while not done.wait(args.rss_every):
            mb = rss_mb(proc.pid)
            if mb is not None:
                rss.append((time.perf_counter() - t1, mb))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    got: dict[int, dict] = {}
    order: list[int] = []
    gaps: list[tuple[int, str]] = []
    events: dict[str, int] = {}
    last = want_seqs[-1] if want_seqs else -1
    # stop once the last window is out, or when nothing has come for --idle s (a window
    # never printed: the comparison below says which)
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(ln) for ln in proc.stdout] + [lines.put("")],
                     daemon=True).start()
    while True:
        try:
            line = lines.get(timeout=args.idle)
        except queue.Empty:
            break
        if not line:
            break
        x = json.loads(line)
        if "event" in x:
            events[x["event"]] = events.get(x["event"], 0) + 1
            if x["event"] == "gap":
                gaps.append((x["missing"], x["reason"]))
            continue
        got[x["seq"]] = x
        order.append(x["seq"])
        if x["seq"] >= last:
            break
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    done.set()
    sampler.join()
    wall = time.perf_counter() - t1
    summary = json.loads(err.split("tactile-run: summary ", 1)[1].splitlines()[0])

    # windows (by host seq) and their probabilities (by stream index)
    same_windows = order == want_seqs
    pairs = [(s, e) for s, e in zip(want_seqs, want_ends) if s in got]
    worst = max((float(np.abs(np.array([got[s]["probs"][c] for c in classes]) - ref[e]).max())
                 for s, e in pairs), default=0.0)
    same_labels = all(got[s]["label"] == classes[int(ref[e].argmax())] for s, e in pairs)
    # breaks: between two runs, a restart gap if the pen was unplugged in between (the
    # receiver cannot know how many samples that cost), else a drop gap of the samples lost
    want_gaps = [(0, "restart") if any(b0 <= u < a1 for u in unplugs) else (a1 - b0, "drop")
                 for (_, b0), (a1, _) in zip(runs, runs[1:])]
    breaks = len(want_gaps)
    gap_ok = gaps == want_gaps
    drops = sum(r == "drop" for _, r in gaps)
    first_after = sum(1 for a, b in runs[1:] if b - a >= window)
    back_in_one = sum(1 for a, b in runs[1:]
                      if b - a >= window and a + window - 1 - host[a] in got)
    corrupted = inj.garbage_bytes + inj.flipped_bytes

    print(f"command: python bench/soak.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    print(f"link: {url}")
    print(f"pen data: {n / 100:.0f} s ({n:,} samples), {sent / 1e6:.1f} MB sent; corrupted "
          f"bytes {corrupted / sent:.2%} (garbage {inj.garbage_bytes:,}, flipped "
          f"{inj.flipped_bytes:,}); dropped frames {inj.dropped_frames:,}; stalls "
          f"{inj.stalls} ({inj.stalled_samples:,} samples); unplugs {inj.unplugs} "
          f"({inj.unplugged_samples:,} samples)")
    print(f"tactile-run: {wall:.0f} s wall ({n / 100 / wall:.0f}x real time); ground truth "
          f"{t_truth:.0f} s")
    print(f"breaks (ground truth): {breaks:,}; tactile-run: gaps {summary['gaps']:,}, "
          f"reconnects {summary['reconnects']}, stall events {summary['stalls']}")
    print(f"windows: ground truth {len(want_ends):,}, tactile-run {len(order):,}; identical "
          f"positions: {'yes' if same_windows else 'NO'}; labels equal: "
          f"{'yes' if same_labels else 'NO'}; largest probability difference {worst:.1e}")
    print(f"gaps identical to the breaks: {'yes' if gap_ok else 'NO'} ({len(gaps):,} gap "
          f"events: {drops:,} drop, {len(gaps) - drops} restart)")
    print(f"labels back one window after each break: {back_in_one:,} of {first_after:,} runs "
          "long enough for a window")
    if rss:
        mbs = [m for _, m in rss]
        print(f"RSS of tactile-run: start {mbs[0]:.1f} MB, max {max(mbs):.1f} MB, end "
              f"{mbs[-1]:.1f} MB ({len(mbs)} samples over {rss[-1][0]:.0f} s)")
        tenths = [mbs[min(len(mbs) - 1, k * len(mbs) // 10)] for k in range(1, 10)]
        print("RSS at each tenth of the run: " + ", ".join(f"{m:.1f}" for m in tenths) + " MB")
    ok = same_windows and same_labels and worst < 1e-5 and gap_ok and \
        back_in_one == first_after and summary["reconnects"] == inj.unplugs
    if not same_windows:
        extra = sorted(set(order) - set(want_seqs))[:5]
        missing = sorted(set(want_seqs) - set(order))[:5]
        print(f"  windows not in the ground truth: {extra}; missing: {missing}")
    if not gap_ok:
        bad = next(i for i, (g, w) in enumerate(zip(gaps + [None] * len(want_gaps), want_gaps))
                   if g != w)
        print(f"  gap {bad}: tactile-run {gaps[bad:bad + 3]}, ground truth "
              f"{want_gaps[bad:bad + 3]}")
    print("result:", "identical to ground truth" if ok else "DIFFERS from ground truth")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
