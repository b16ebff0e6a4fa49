"""Plots of recordings (``tactile-plot``): a take's channels over time, or a dataset's minutes
per class and user.

Needs matplotlib (the ``[train]`` extra), imported by the functions that draw: importing this
module does not need it.
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from tactile.device.recordings.reader import load_dataset
from tactile.device.recordings.summary import summarise
from tactile.device.recordings.take import Take
from tactile.errors import ConfigError
from tactile.files import figure_bytes, write_whole

LEGEND_MAX = 8
"""A panel with more channels than this names them in its label instead of a legend."""
MAX_PANELS = 48
"""The most panels one picture draws (a two-finger BioTac take is 6, the pen 3; each panel adds
1.6 inches: 2,048 channels of distinct names took minutes and gigabytes before failing)."""


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


@dataclass(frozen=True)
class Panel:
    """One panel of a take's plot: ``index`` its channels' columns; ``signal``: they are one
    high-rate signal's sub-samples in time order (one trace at ``len(index)`` x the frame
    rate), else separate channels (one trace each)."""

    name: str
    unit: str
    index: list[int]
    signal: bool


def panels(channels, signals: dict[str, list[str]] | None = None) -> list[Panel]:
    """The panels of a take's plot: each declared high-rate signal (``signals``: name -> its
    sub-sample channels in time order, as a take's JSON declares them) one panel of its own, drawn
    as one trace at its true rate; the other channels grouped by (name without its last
    ``_part``, unit): the pen's pressure / accel / gyro, a BioTac finger's ``f0_ele_*`` / the
    rest. Panels come in the order of their first column in the take."""
    index = {c.name: i for i, c in enumerate(channels)}
    out: list[Panel] = []
    taken: set[int] = set()
    for name, names in (signals or {}).items():
        idx = [index[c] for c in names]
        units = list(dict.fromkeys(channels[i].unit or "-" for i in idx))
        out.append(Panel(name, "/".join(units), idx, True))
        taken.update(idx)
    groups: dict[tuple[str, str], list[int]] = {}
    for i, c in enumerate(channels):
        if i not in taken:
            groups.setdefault((c.name.rsplit("_", 1)[0], c.unit or "-"), []).append(i)
    out += [Panel(name, unit, idx, False) for (name, unit), idx in groups.items()]
    return sorted(out, key=lambda panel: min(panel.index))  # in the take's column order


def _only(shown: list[Panel], keep: set[int]) -> list[Panel]:
    """``shown`` narrowed to the columns of ``keep``: a signal whole or not at all, a group to
    its chosen channels."""
    out = []
    for p in shown:
        if p.signal:
            out += [p] if keep.issuperset(p.index) else []
        elif idx := [i for i in p.index if i in keep]:
            out.append(replace(p, index=idx))
    return out


def _traces(panel: Panel, channels, values: np.ndarray, t: np.ndarray, segments, rate: float):
    """(label, times, values) of each trace of ``panel``, NaN between gap-free segments (no line
    drawn across a gap). A signal's ``r`` sub-samples of the frame at time ``t`` are at
    ``t + k / (r x rate)``."""
    cols = [panel.index] if panel.signal else [[i] for i in panel.index]
    r = len(panel.index) if panel.signal else 1
    offsets = np.arange(r) / (r * rate)
    for c in cols:
        ys, ts = [np.zeros(0)], [np.zeros(0)]  # (a take with no rows: an empty trace)
        for a, b in segments:
            ys += [values[a:b][:, c].astype(float).reshape(-1), [np.nan]]
            ts += [(t[a:b, None] + offsets).reshape(-1), [np.nan]]
        label = (f"{panel.name} ({r} per frame, {r * rate:g} Hz)" if panel.signal
                 else channels[c[0]].name)
        yield label, np.concatenate(ts), np.concatenate(ys)


def chosen(channels, patterns: tuple[str, ...],
           signals: dict[str, list[str]] | None = None) -> set[int]:
    """The columns whose channel names match any of ``patterns`` (shell-style, ``f0_*``, or
    exact names, or a declared signal's name for all its sub-samples; none: all); a pattern
    that matches nothing is a :class:`ConfigError`."""
    if not patterns:
        return set(range(len(channels)))
    names = [c.name for c in channels]
    out: set[int] = set()
    for p in patterns:
        hit = {i for i, c in enumerate(channels)
               if c.name == p or fnmatch.fnmatchcase(c.name, p)}
        hit |= {names.index(c) for c in (signals or {}).get(p, [])}
        if not hit:
            shown = ", ".join(names[:6]) + (f", ... ({len(names)} in all)" if len(names) > 6
                                             else "")
            raise ConfigError(f"--channels {p!r} matches none of the take's channels: {shown}")
        out |= hit
    return out


def plot_take(take: Take, out: Path, patterns: tuple[str, ...] = ()) -> None:
    """One panel per group of channels or declared high-rate signal (:func:`panels`), values in
    their units, time in seconds from the first sample, every gap a red band over all panels;
    the title names the label and source. ``patterns``: only the channels they match (a
    declared signal when all of its sub-samples are among them). More panels than
    :data:`MAX_PANELS` is a :class:`ConfigError` before anything is drawn."""
    rate = take.info.sample_rate_hz
    t = (take.seq - take.seq[0]) / rate if len(take.seq) else np.zeros(0)
    values = take.values()
    channels = take.info.channels
    declared = take.meta.get("signals", {})
    keep = chosen(channels, patterns, declared)
    names = [c.name for c in channels]
    # a signal partly chosen: its chosen sub-samples as plain channels
    signals = {n: c for n, c in declared.items() if all(names.index(x) in keep for x in c)}
    shown = _only(panels(channels, signals), keep)
    if len(shown) > MAX_PANELS:
        raise ConfigError(f"{take.path.name}: {len(shown)} panels (channels grouped by name "
                          f"before their last '_part'), more than a picture shows "
                          f"({MAX_PANELS}): choose some with --channels (e.g. "
                          f"--channels '{channels[0].name}')")
    plt = _pyplot()
    fig, axes = plt.subplots(len(shown), 1, figsize=(10, 1.8 + 1.6 * len(shown)),
                             sharex=True, squeeze=False)
    segments = take.segments()
    for ax, panel in zip(axes[:, 0], shown):
        for label, ts, ys in _traces(panel, channels, values, t, segments, rate):
            ax.plot(ts, ys, lw=0.7 if not panel.signal else 0.4, label=label)
        for (_, b), (a, _) in zip(segments[:-1], segments[1:]):
            ax.axvspan(t[b - 1], t[a], color="red", alpha=0.25, lw=0)
        if panel.signal or len(panel.index) <= LEGEND_MAX:
            ax.set_ylabel(panel.unit)
            ax.legend(loc="upper right", fontsize=7, ncol=min(len(panel.index), 4))
        else:
            names = [channels[i].name for i in panel.index]
            ax.set_ylabel(f"{panel.unit}\n{names[0]}..{names[-1]}", fontsize=7)
    axes[-1, 0].set_xlabel("time (s)")
    gaps = max(len(segments) - 1, 0)
    fast = "".join(f", {name} at {len(names) * rate:g} Hz" for name, names in signals.items())
    fig.suptitle(f"{take.path.name}: label {take.label!r}, source {take.meta.get('source', '')!r}"
                 f"\n{len(take.seq)} samples at {rate:g} Hz{fast}, {gaps} gaps (red)",
                 fontsize=9)
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


__all__ = ["LEGEND_MAX", "Panel", "image_formats", "panels", "plot_summary", "plot_take"]
