"""Plots of recordings (``tactile-plot``): a take's channels over time, or a dataset's minutes
per class and user.

Needs matplotlib (the ``[train]`` extra), imported by the functions that draw: importing this
module does not need it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tactile.device.recordings.reader import load_dataset
from tactile.device.recordings.summary import summarise
from tactile.device.recordings.take import Take
from tactile.files import figure_bytes, write_whole

LEGEND_MAX = 8
"""A panel with more channels than this names them in its label instead of a legend."""


def _pyplot():
    """matplotlib's pyplot, drawing to files only (no display on a server or in CI)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def image_formats() -> dict[str, str]:
    """The image file types matplotlib can write here: extension -> description."""
    plt = _pyplot()
    kinds = plt.figure().canvas.get_supported_filetypes()
    plt.close("all")
    return kinds


def panels(channels) -> dict[tuple[str, str], list[int]]:
    """Channel indices grouped into panels by (name without its last ``_part``, unit): the pen's
    pressure / accel / gyro, a BioTac finger's ``f0_pac_*`` / ``f0_ele_*`` / the rest."""
    groups: dict[tuple[str, str], list[int]] = {}
    for i, c in enumerate(channels):
        groups.setdefault((c.name.rsplit("_", 1)[0], c.unit or "-"), []).append(i)
    return groups


def plot_take(take: Take, out: Path) -> None:
    """One panel per group of channels (:func:`panels`), values in their units, time in seconds
    from the first sample, every gap a red band over all panels; the title names the label and
    source."""
    plt = _pyplot()
    rate = take.info.sample_rate_hz
    t = (take.seq - take.seq[0]) / rate if len(take.seq) else np.zeros(0)
    values = take.values()
    groups = panels(take.info.channels)
    fig, axes = plt.subplots(len(groups), 1, figsize=(10, 1.8 + 1.6 * len(groups)),
                             sharex=True, squeeze=False)
    segments = take.segments()
    for ax, ((_, unit), idx) in zip(axes[:, 0], groups.items()):
        for i in idx:
            y = values[:, i].astype(float).copy()
            ys = np.full(len(y) + len(segments), np.nan)  # NaN between segments: no line
            ts = np.full(len(y) + len(segments), np.nan)
            k = 0
            for a, b in segments:
                ys[k:k + b - a], ts[k:k + b - a] = y[a:b], t[a:b]
                k += b - a + 1
            ax.plot(ts, ys, lw=0.7, label=take.info.channels[i].name)
        for (_, b), (a, _) in zip(segments[:-1], segments[1:]):
            ax.axvspan(t[b - 1], t[a], color="red", alpha=0.25, lw=0)
        names = [take.info.channels[i].name for i in idx]
        if len(idx) <= LEGEND_MAX:
            ax.set_ylabel(unit)
            ax.legend(loc="upper right", fontsize=7, ncol=min(len(idx), 4))
        else:
            ax.set_ylabel(f"{unit}\n{names[0]}..{names[-1]}", fontsize=7)
    axes[-1, 0].set_xlabel("time (s)")
    gaps = max(len(segments) - 1, 0)
    fig.suptitle(f"{take.path.name}: label {take.label!r}, source {take.meta.get('source', '')!r}"
                 f"\n{len(take.seq)} samples at {rate:g} Hz, {gaps} gaps (red)", fontsize=9)
    fig.tight_layout()
    _save(fig, out)


def plot_summary(folder: Path, out: Path) -> None:
    """Minutes recorded per class and per user, gaps written on each bar."""
    plt = _pyplot()
    s = summarise(load_dataset(folder), 50, 50)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, (title, rows) in zip(axes, (("class", s["per_class"]), ("user", s["per_user"]))):
        names = list(rows)
        minutes = [rows[k]["minutes"] for k in names]
        bars = ax.barh(names, minutes, color="tab:blue")
        for bar, k in zip(bars, names):
            ax.text(bar.get_width(), bar.get_y() + bar.get_height() / 2,
                    f" {rows[k]['takes']} takes, {rows[k]['gaps']} gaps", va="center", fontsize=7)
        ax.set_xlabel("minutes recorded")
        ax.set_title(f"per {title}")
        ax.invert_yaxis()
        ax.margins(x=0.35)
    t = s["total"]
    fig.suptitle(f"{folder}: {s['takes']} takes, {t['minutes']:.1f} min, {t['gaps']} gaps, "
                 f"{len(s['channels'])} channels at {s['sample_rate_hz']:g} Hz", fontsize=9)
    fig.tight_layout()
    _save(fig, out)


def _save(fig, out: Path) -> None:
    """The figure into ``out`` (its format by the name's ending), whole or not at all: drawn in
    memory, then written (:func:`~tactile.files.write_whole`: a full disk is one line naming
    ``out``, exit 4, and no cut-short image; matplotlib writing into the file left one)."""
    import matplotlib.pyplot as plt

    data = figure_bytes(fig, out.suffix.lstrip(".").lower(), 110)
    plt.close(fig)
    write_whole(out, data)


__all__ = ["LEGEND_MAX", "image_formats", "panels", "plot_summary", "plot_take"]
