"""Evaluate a trained run on a dataset: window and per-take accuracy, confusion, robustness.

    tactile-eval RUN/ DATA [--json] [--threads N] [--smooth S --p-min P --hold K]

prints the figures of :func:`tactile.training.evaluate.evaluate_run`: accuracy over windows, the
majority vote per take, per-class recall, the paper-style confusion table and the robustness
check on windows shifted by up to +/-0.2 s; then the label stream (the test takes played as
streams, :mod:`tactile.training.label_stream`), raw and post-processed side by side, with the
setting calibrated on the run's validation takes, or the one the options give.
"""

from __future__ import annotations

import argparse
import json
import sys

from tactile.cli import (
    MAX_THREADS,
    Parser,
    add_debug,
    command,
    float_in,
    holding_signals,
    int_in,
    path_given,
    run,
    smooth_given,
)


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="tactile-eval", description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=path_given, help="run folder written by tactile-train")
    p.add_argument("data", type=path_given, help="dataset folder")
    p.add_argument("--json", action="store_true", help="the figures as one JSON object")
    p.add_argument("--threads", type=int_in(1, MAX_THREADS), metavar="N",
                   help=f"torch threads, at most {MAX_THREADS} (default: the run's threads "
                   "setting)")
    p.add_argument("--smooth", type=smooth_given, metavar="S", help="label stream: the "
                   "averaging (N windows, Ts, ma:N or ema:T) instead of the calibrated setting's")
    p.add_argument("--p-min", type=float_in(0.0, 1.0, low_open=False), metavar="P",
                   help="label stream: the stable label's least averaged probability (0..1)")
    p.add_argument("--hold", type=int_in(1, 100_000), metavar="K", help="label stream: windows "
                   "a class must lead before it is stable (1..100000)")
    add_debug(p)
    return p


def _eval(args: argparse.Namespace) -> int:
    with holding_signals():
        from tactile.postprocess.smoothing import override
        from tactile.training.evaluate import evaluate_run, per_take_line, shifted_line, table
        from tactile.training.label_stream import stream_table

    # a value given without the others: those of the raw stream (ma:1, p_min 0, hold 1)
    smoothing = override(None, args.smooth, args.p_min, args.hold)
    s = evaluate_run(args.run, args.data, args.threads, smoothing)
    if s["seen_takes"]:
        print(f"tactile-eval: warning: {len(s['seen_takes'])} of the takes evaluated are ones "
              f"the run trained or validated on (e.g. {s['seen_takes'][0]}): the figures are "
              "not a test", file=sys.stderr)
    if args.json:
        print(json.dumps(s))
        return 0
    classes = tuple(s["classes"])
    print(f"evaluated on {s['scope']}")
    print(table(s, classes))
    print(per_take_line(s))
    print("recall: " + ", ".join(f"{c} {'-' if v is None else f'{v:.3f}'}"
                                 for c, v in s["recall"].items()))
    print(shifted_line(s["shifted"]))
    print(stream_table(s["label_stream"]))
    return 0


@command("tactile-eval", interruptible=True)
def main(argv: list[str] | None = None) -> int:
    return run("tactile-eval", _eval, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["build_parser", "main"]
