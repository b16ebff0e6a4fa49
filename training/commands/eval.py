"""Evaluate a trained run on a dataset: window and per-take accuracy, confusion, robustness.

    tactile-eval RUN/ DATA [--json] [--threads N]

prints the figures of :func:`tactile.training.evaluate.evaluate_run`: accuracy over windows, the
majority vote per take, per-class recall, the paper-style confusion table and the robustness
check on windows shifted by up to +/-0.2 s.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tactile.cli import Parser, add_debug, command, int_in, run


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="tactile-eval", description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path, help="run folder written by tactile-train")
    p.add_argument("data", type=Path, help="dataset folder")
    p.add_argument("--json", action="store_true", help="the figures as one JSON object")
    p.add_argument("--threads", type=int_in(1), metavar="N",
                   help="torch threads (default: the run's threads setting)")
    add_debug(p)
    return p


def _eval(args: argparse.Namespace) -> int:
    from tactile.training.evaluate import evaluate_run, shifted_line, table

    s = evaluate_run(args.run, args.data, args.threads)
    if args.json:
        print(json.dumps(s))
        return 0
    classes = tuple(s["classes"])
    print(f"evaluated on {s['scope']}")
    print(table(s, classes))
    print(f"per take (majority vote): {s['take_accuracy']:.3f} over {s['takes']} takes")
    print("recall: " + ", ".join(f"{c} {v:.3f}" for c, v in s["recall"].items()))
    print(shifted_line(s["shifted"]))
    return 0


@command("tactile-eval", interruptible=True)
def main(argv: list[str] | None = None) -> int:
    return run("tactile-eval", _eval, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["build_parser", "main"]
