"""``tactile-run``: read the pen, print one label per window, keep going.

    tactile-run --model model.onnx --port /dev/ttyACM0
    tactile-run --model model.onnx --port "sim://?texture=paper&seed=3"
    tactile-run --model model.onnx --replay data/paper-....csv      # offline, as fast as it can

Labels and events (gaps, stalls, reconnects, changes of the stable label) go to stdout (JSON
Lines by default; ``--format text|csv``); each window's label is the raw one and, post-processed
(``--smooth``, ``--p-min``, ``--hold``, or the model's defaults; ``--raw``: none), a smoothed one
that is stable or ``uncertain``. Diagnostics go to stderr: a status line every few seconds, a
line for each stall and reconnection, and a summary at the end. Exit codes:
0 stopped cleanly (SIGINT/SIGTERM, end of replay or of ``--seconds``), 1 bad arguments, 2 port
cannot be opened or no pen found, 3 the model file is missing or not a usable model, or the
model or the device does not honour the contract, 4 stdout cannot be written (a full disk, an
I/O error: the summary still goes to stderr).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import TYPE_CHECKING

from tactile.cli import (
    Parser,
    add_debug,
    add_port_options,
    command,
    float_in,
    int_in,
    link_values,
    path_given,
    run,
    smooth_given,
)

if TYPE_CHECKING:  # the library is imported when the command runs, after its arguments
    from tactile.device.protocol import StreamDecoder
    from tactile.runtime.model import Model
    from tactile.runtime.runner import Runner, Summary
    from tactile.runtime.stream import Stream

FORMATS = ("jsonl", "text", "csv")
STATUS_EVERY = 5.0  # --status-every's default, s
CPUS = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def build_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="tactile-run",
        description="Read the pen, print one label per window (stdout), keep going.",
        epilog="exit codes: 0 stopped cleanly, 1 bad arguments, 2 port cannot be opened or no "
        "pen found, 3 model missing, not a usable model file, or model or device does not "
        "honour the contract, 4 stdout cannot be written (a full disk, an I/O error)",
    )
    p.add_argument("--model", required=True, type=path_given,
                   help="the .onnx file from tactile-export")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--port", help="device path or pyserial URL (sim://, socket://, ...); "
                     "default: the one likely pen attached")
    src.add_argument("--replay", type=path_given, metavar="TAKE", help="a recorded take (.csv)")
    p.add_argument("--wait", action="store_true",
                   help="if the port is absent at start, wait for it (as after an unplug) "
                   "instead of exiting with code 2; without --port, wait until one likely pen "
                   "is attached; for a service started before the pen is plugged in")
    p.add_argument("--hop", type=int_in(1),
                   help="samples between windows (default: the model's)")
    p.add_argument("--format", choices=FORMATS, default="jsonl",
                   help="jsonl (default): one JSON object per window or event; csv: a header, "
                   "one row per window or event; text: for people")
    post = p.add_argument_group(
        "post-processing of the labels",
        "each option replaces the model's default (its file's postprocess.* metadata, "
        "calibrated at export); a file without any runs raw unless an option is given")
    post.add_argument("--smooth", type=smooth_given, metavar="N|Ts",
                      help="average the class probabilities over the last N windows (e.g. 5), "
                      "or exponentially with a time constant of T seconds (e.g. 1.5s); the "
                      "metadata's ma:N and ema:T are taken too; default: the model's, else 1 "
                      "window")
    post.add_argument("--p-min", type=float_in(0.0, 1.0, low_open=False), metavar="P",
                      help="a label is stable only when its averaged probability is at least "
                      "P (0..1), else it is reported as 'uncertain'; default: the model's, else 0")
    post.add_argument("--hold", type=int_in(1, 100_000), metavar="K",
                      help="... and only once it has led for K consecutive windows (K hops: "
                      "--hop's, else the model's, which tactile-check shows: the shipped pen "
                      "model's 25 samples at 100 Hz are 0.25 s); default: the model's, else 1")
    post.add_argument("--raw", action="store_true",
                      help="no post-processing, whatever the model says: the raw label of "
                      "each window only")
    p.add_argument("--threads", type=int_in(1, CPUS), default=1,
                   help=f"onnxruntime threads, at most the {CPUS} cores (default 1)")
    p.add_argument("--status-every", type=float_in(0.0),
                   help=f"status line period, s (default {STATUS_EVERY:g})")
    p.add_argument("--no-native", action="store_true",
                   help="run the portable EMD/sparse-code graphs, not the C kernels")
    add_port_options(p, "the channels, labels and link")
    add_debug(p)
    return p


POST_OPTIONS = ("smooth", "p_min", "hold")
PORT_OPTIONS = ("baud", "stall_timeout", "status_every")  # a port's; --replay refuses them


def _run(args: argparse.Namespace) -> int:
    from tactile.device.protocol import StreamDecoder
    from tactile.errors import OutputError
    from tactile.runtime.model import Model
    from tactile.runtime.runner import Summary, post_processor, say
    from tactile.runtime.stream import Stream

    if args.no_native:
        from tactile.runtime import kernels
        kernels.disable()
    model = Model(args.model, threads=args.threads)
    c = model.contract
    hop = c.hop if args.hop is None else args.hop
    given = {k: getattr(args, k) for k in POST_OPTIONS if getattr(args, k) is not None}
    post = post_processor(model, "raw" if args.raw else given)
    if post is not None:
        said = "the model's" if not given else "the options'" if model.postprocess is None \
            else "the model's, with the options'"
        say(f"labels post-processed: {post.settings.describe()} ({said})")
    stream = Stream.for_model(model, hop, post)
    summary = Summary()
    decoder = StreamDecoder(csv_rate_hz=c.sample_rate_hz)
    counted = None if args.replay is not None else decoder  # a replay decodes no bytes
    try:
        _label(args, model, stream, summary, decoder, post is not None)
    except OutputError:  # stdout is full: stderr still tells what was labelled until then
        _summarise(summary, counted)
        raise
    _summarise(summary, counted)
    return 0


def _label(args: argparse.Namespace, model: Model, stream: Stream, summary: Summary,
           decoder: StreamDecoder, smoothed: bool) -> None:
    """Print the labels of the replay or the pen until the run ends, with the live page
    (``--serve``) beside them."""
    from tactile.runtime.runner import Printer, Runner, say

    printer = Printer(args.format, model.contract.classes, smoothed=smoothed)  # a CSV header
    runner = Runner(model, stream, printer, summary)
    found = None  # the one likely pen, looked for now: no pen is its error alone, before a
    # live page is announced (--wait looks for it while the page runs)
    if args.replay is None and args.port is None and not args.wait:
        from tactile.device.link.portlist import find_port

        found = find_port()
    live = None
    if args.serve:
        from tactile.runtime.live import serve_runner

        live = serve_runner(args.serve, runner, decoder, say)
    try:
        _read(args, runner, decoder, summary.started + args.seconds, found)
    finally:  # the page gets its end, stderr its last line, whatever stopped the run
        if live is not None:
            live.close()


def _summarise(summary: Summary, decoder: StreamDecoder | None) -> None:
    """The summary line; ``decoder`` None (a replay): its counters are null, not zeros."""
    stats = None if decoder is None else decoder.stats.as_dict()
    print("tactile-run: summary " + json.dumps(summary.to_dict(stats)), file=sys.stderr,
          flush=True)


def _read(args: argparse.Namespace, runner: Runner, decoder: StreamDecoder, deadline: float,
          found: str | None = None) -> None:
    """Until stopped or ``deadline`` (monotonic s): the replay, or the pen (``--port``, the
    one ``found``, or the one waited for)."""
    from tactile.device.link.connection import LinkSettings
    from tactile.runtime.runner import read_pen, replay, say, wait_for_pen
    from tactile.runtime.stop import stop_on_signals

    stop = stop_on_signals(say)
    if stop is None:  # a signal while starting
        return
    if args.replay:
        replay(args.replay, runner, stop, deadline)
        return
    auto = args.port is None  # found by auto-detection: after an unplug, look again
    port = args.port if args.port is not None else found
    status_every = STATUS_EVERY if args.status_every is None else args.status_every
    if port is None:  # --wait
        port = wait_for_pen(stop, deadline, status_every)
    if port is not None:  # None: stopped while waiting for a pen
        baud, stall_timeout = link_values(args)
        settings = LinkSettings(port, baud, auto=auto, wait=args.wait,
                                stall_timeout=stall_timeout, status_every=status_every)
        read_pen(runner, decoder, settings, stop, deadline)


@command("tactile-run", guarded=True)
def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.replay is not None:
        if args.wait:
            parser.error("argument --wait: not allowed with --replay (a take needs no port to "
                         "wait for)")
        for key in PORT_OPTIONS:
            if getattr(args, key) is not None:
                parser.error(f"argument --{key.replace('_', '-')}: not allowed with --replay "
                             "(a setting of the port, which a take does not read)")
    if args.raw and any(getattr(args, k) is not None for k in POST_OPTIONS):
        parser.error("argument --raw: not allowed with --smooth, --p-min or --hold (it turns "
                     "the post-processing off)")
    return run("tactile-run", _run, args)


if __name__ == "__main__":
    sys.exit(main())
