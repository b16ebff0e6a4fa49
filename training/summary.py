"""``tactile-data DATA [--json]``: what a dataset folder holds, per class and per user.

    tactile-data data/sim                 # a table: takes, users, minutes, windows, gaps
    tactile-data data/sim --json          # the same figures as one JSON object

Windows are counted as training cuts them (inside gap-free segments) at the training defaults'
window and hop, or at ``--window``/``--hop``. Needs numpy only (no torch).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

from tactile.cli import Parser, add_debug, int_in, run
from tactile.device.recording import Take, load_dataset
from tactile.training.config import TrainConfig


def user_of(take: Take) -> str:
    """The take's ``user`` field as text, or ``-`` when the take does not say."""
    return str(take.meta["user"]) if "user" in take.meta else "-"


def windows_in(take: Take, window: int, hop: int) -> int:
    """Windows of ``window`` samples every ``hop`` that fit inside the take's gap-free segments."""
    return int(sum((b - a - window) // hop + 1 for a, b in take.segments() if b - a >= window))


def _row() -> dict:
    return {"takes": 0, "users": set(), "classes": set(), "minutes": 0.0, "windows": 0,
            "gaps": 0, "samples_lost": 0}


def summarise(takes: list[Take], window: int, hop: int) -> dict:
    """The dataset's figures: totals, then per class and per user (takes, minutes, windows at
    ``window``/``hop``, gaps: the decoder's gap events and seq jumps between segments)."""
    rate = takes[0].info.sample_rate_hz
    total, by_class, by_user = _row(), defaultdict(_row), defaultdict(_row)
    for t in takes:
        segments = t.segments()
        lost = int(sum(t.seq[a] - t.seq[a - 1] - 1 for a, _ in segments[1:]))
        figures = {"minutes": len(t.seq) / rate / 60, "windows": windows_in(t, window, hop),
                   "gaps": max(len(segments) - 1, 0), "samples_lost": lost}
        for row in (total, by_class[t.label], by_user[user_of(t)]):
            row["takes"] += 1
            row["users"].add(user_of(t))
            row["classes"].add(t.label)
            for k, v in figures.items():
                row[k] += v

    def plain(row: dict) -> dict:
        return {**row, "users": len(row["users"]), "classes": len(row["classes"]),
                "minutes": round(row["minutes"], 3)}

    first = takes[0].info
    return {
        "takes": len(takes), "classes": sorted(by_class), "users": sorted(by_user),
        "channels": [{"name": c.name, "unit": c.unit} for c in first.channels],
        "sample_rate_hz": rate, "window": window, "hop": hop, "total": plain(total),
        "per_class": {k: plain(v) for k, v in sorted(by_class.items())},
        "per_user": {k: plain(v) for k, v in sorted(by_user.items())},
    }


def text(s: dict, folder: Path) -> str:
    """The summary as the lines ``tactile-data`` prints."""
    t = s["total"]
    lines = [
        f"{folder}: {s['takes']} takes, {len(s['classes'])} classes, {len(s['users'])} users, "
        f"{t['minutes']:.1f} min, {t['gaps']} gaps ({t['samples_lost']} samples lost)",
        f"{len(s['channels'])} channels at {s['sample_rate_hz']:g} Hz: "
        + ", ".join(f"{c['name']} ({c['unit']})" for c in s["channels"]),
        f"{t['windows']} windows of {s['window']} samples every {s['hop']}",
    ]
    for title, rows in (("class", s["per_class"]), ("user", s["per_user"])):
        width = max(len(title), *(len(k) for k in rows))
        lines += ["", f"{title:<{width}}  takes  users  classes  minutes  windows  gaps"]
        lines += [f"{k:<{width}}  {r['takes']:5d}  {r['users']:5d}  {r['classes']:7d}  "
                  f"{r['minutes']:7.1f}  {r['windows']:7d}  {r['gaps']:4d}"
                  for k, r in rows.items()]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    defaults = TrainConfig()
    p = Parser(prog="tactile-data", description="Print what a dataset folder holds: classes, "
               "users, takes, minutes, windows, gaps, channels and rate.")
    p.add_argument("data", type=Path, help="dataset folder (takes: .csv + .json)")
    p.add_argument("--window", type=int_in(1), default=defaults.window,
                   help=f"window length in samples (default {defaults.window}, as training)")
    p.add_argument("--hop", type=int_in(1), default=defaults.hop,
                   help=f"samples between windows (default {defaults.hop}, as training)")
    p.add_argument("--json", action="store_true", help="the figures as one JSON object")
    add_debug(p)
    return p


def _main(args: argparse.Namespace) -> int:
    s = summarise(load_dataset(args.data), args.window, args.hop)
    print(json.dumps(s) if args.json else text(s, args.data))
    return 0


def main(argv: list[str] | None = None) -> int:
    return run("tactile-data", _main, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["main", "summarise", "text", "windows_in", "user_of"]
