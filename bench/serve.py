"""What ``--serve`` costs: tactile-run's event handling (decoded events -> labels) over the same
120 s of a simulated pen, without the live page, with it and no viewer, and with two viewers
reading /events. CPU time, not wall time (the figures hold on a loaded machine): the loop's own
thread (what the serial loop waits for: the loop only queues) and the whole process (the
viewers' threads too, which write to the sockets; until close() has sent them everything).

Run: python bench/serve.py [--seconds 120] [--repeat 5]
"""

from __future__ import annotations

import argparse
import io
import threading
import time
import urllib.request
from pathlib import Path

from tactile.device.protocol import StreamDecoder
from tactile.runtime.live import serve_runner
from tactile.runtime.model import Model
from tactile.runtime.runner import Printer, Runner, Summary
from tactile.runtime.stream import Stream

MODEL = Path(__file__).resolve().parents[1] / "models" / "pen-exp2.onnx"


def pen_bytes(seconds: float) -> bytes:
    """The bytes of a simulated pen (paper, seed 1), read 4096 at a time as tactile-run does."""
    import serial

    import tactile.device  # noqa: F401  (registers sim://)

    link = serial.serial_for_url(f"sim://?texture=paper&seed=1&speed=max&seconds={seconds}",
                                 timeout=0.05)
    out = bytearray()
    while chunk := link.read(4096):
        out += chunk
    return bytes(out)


def run_once(model: Model, data: bytes, serve: bool, viewers: int
             ) -> tuple[float, float, int]:
    """CPU seconds of the loop's thread in Runner.handle over ``data`` (4096-byte reads), of the
    process from the first event to the end of close(), and the windows made."""
    runner = Runner(model, Stream.for_model(model), Printer("jsonl", model.contract.classes,
                                                            io.StringIO()), Summary())
    decoder = StreamDecoder()
    live, readers = None, []
    if serve:
        live = serve_runner("127.0.0.1:0", runner, decoder, lambda m: None)
        for _ in range(viewers):
            r = threading.Thread(target=lambda: urllib.request.urlopen(
                live.url + "events", timeout=60).read(), daemon=True)
            r.start()
            readers.append(r)
        while live.viewers < viewers:
            time.sleep(0.01)
    spent, p0 = 0.0, time.process_time()
    for i in range(0, len(data), 4096):
        events = decoder.feed(data[i:i + 4096])
        t0 = time.thread_time()
        runner.handle(events)
        spent += time.thread_time() - t0
    if live is not None:
        live.close()
        if live.dropped:
            print(f"  ({live.dropped} messages dropped for viewers)")
    return spent, time.process_time() - p0, runner.summary.windows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=120.0, help="seconds of pen data")
    ap.add_argument("--repeat", type=int, default=5, help="runs of each case (minimum kept)")
    args = ap.parse_args()
    model = Model(MODEL)
    data = pen_bytes(args.seconds)
    cases = {"no --serve": (False, 0), "--serve, no viewer": (True, 0),
             "--serve, 2 viewers": (True, 2)}
    best = {name: [float("inf")] * 2 for name in cases}
    for _ in range(args.repeat):  # interleaved, so that a load change hits every case alike
        for name, (serve, viewers) in cases.items():
            loop, process, windows = run_once(model, data, serve, viewers)
            best[name] = [min(best[name][0], loop), min(best[name][1], process)]
    ref = best["no --serve"]
    print(f"{args.seconds:g} s of pen data, {len(data)} B, {windows} windows; CPU time, "
          f"minimum of {args.repeat} runs")
    print(f"{'':<20} {'loop thread':>12} {'ratio':>6} {'process':>10} {'ratio':>6}")
    for name, (loop, process) in best.items():
        print(f"{name:<20} {loop * 1e3:9.1f} ms {loop / ref[0]:5.2f}x {process * 1e3:7.1f} ms "
              f"{process / ref[1]:5.2f}x")


if __name__ == "__main__":
    main()
