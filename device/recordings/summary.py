"""What a dataset folder holds, per class and per user (``tactile-data``, ``tactile-plot
--summary``).

Windows are counted as training cuts them (inside gap-free segments), by default at the
training defaults' window and hop (:data:`WINDOW`, :data:`HOP`). Needs numpy only (no torch).
"""

from __future__ import annotations

import re
from collections import defaultdict
from pathlib import Path

from tactile.device.recordings.take import Take

# The window and hop training cuts by default (``TrainConfig`` takes them from here), so that
# the counts ``tactile-data`` prints by default are the windows training sees.
WINDOW = 50  # samples per window
HOP = 10  # samples from one window's start to the next


def user_of(take: Take) -> str:
    """The take's ``user`` field as text, or ``-`` when the take does not say."""
    return str(take.meta["user"]) if "user" in take.meta else "-"


def natural(name: str) -> tuple:
    """A sort key that puts ``user2`` before ``user10`` and ``9`` before ``10``: the name's runs
    of digits compare as numbers, the rest as text (the name itself breaks ties: ``07``, ``7``)."""
    parts = re.split(r"(\d+)", name)  # text, digits, text, ...: always text first
    return tuple((0, x) if i % 2 == 0 else (1, int(x)) for i, x in enumerate(parts)), name


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
    declared = dict(takes[0].declared_signals)
    agree = all(t.declared_signals == takes[0].declared_signals for t in takes)
    return {
        "takes": len(takes), "classes": sorted(by_class), "users": sorted(by_user, key=natural),
        "channels": [{"name": c.name, "unit": c.unit} for c in first.channels],
        # the high-rate signals the takes declare (null: the takes do not all declare the same)
        "signals": [{"name": k, "channels": len(v), "rate_hz": rate * len(v)}
                    for k, v in declared.items()] if agree else None,
        "sample_rate_hz": rate, "window": window, "hop": hop, "total": plain(total),
        "per_class": {k: plain(v) for k, v in sorted(by_class.items())},
        "per_user": {k: plain(by_user[k]) for k in sorted(by_user, key=natural)},
    }


def text(s: dict, folder: Path) -> str:
    """The summary as the lines ``tactile-data`` prints."""
    t = s["total"]

    def n(count: int, one: str, many: str = "") -> str:  # 1 take, 2 takes; 1 class, 2 classes
        return f"{count} {one if count == 1 else many or one + 's'}"

    lines = [
        f"{folder}: {n(s['takes'], 'take')}, {n(len(s['classes']), 'class', 'classes')}, "
        f"{n(len(s['users']), 'user')}, {t['minutes']:.1f} min, {n(t['gaps'], 'gap')} "
        f"({n(t['samples_lost'], 'sample')} lost)",
        f"{n(len(s['channels']), 'channel')} at {s['sample_rate_hz']:g} Hz: "
        + ", ".join(f"{c['name']} ({c['unit']})" for c in s["channels"]),
        *(["high-rate signals: the takes declare different ones"] if s["signals"] is None else
          ["high-rate signals: " + ", ".join(
              f"{g['name']} ({g['channels']} sub-samples a frame, {g['rate_hz']:g} Hz)"
              for g in s["signals"])] if s["signals"] else []),
        f"{n(t['windows'], 'window')} of {s['window']} samples every {s['hop']}",
    ]
    for title, rows in (("class", s["per_class"]), ("user", s["per_user"])):
        width = max(len(title), *(len(k) for k in rows))
        lines += ["", f"{title:<{width}}  takes  users  classes  minutes  windows  gaps"]
        lines += [f"{k:<{width}}  {r['takes']:5d}  {r['users']:5d}  {r['classes']:7d}  "
                  f"{r['minutes']:7.1f}  {r['windows']:7d}  {r['gaps']:4d}"
                  for k, r in rows.items()]
    return "\n".join(lines)


__all__ = ["WINDOW", "HOP", "natural", "summarise", "text", "windows_in", "user_of"]
