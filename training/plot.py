"""``tactile-plot``: a take's channels over time, or a dataset's minutes per class and user.

    tactile-plot data/sim/paper-user000.csv -o take.png     # channels in units, gaps marked
    tactile-plot data/sim --summary -o summary.png         # minutes and gaps per class and user

Needs matplotlib (the ``[train]`` extra).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only: no display on a server or in CI
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from tactile.cli import Parser, add_debug, run  # noqa: E402
from tactile.device.recording import Take, load_dataset, read_take  # noqa: E402
from tactile.errors import ConfigError  # noqa: E402
from tactile.training.summary import summarise  # noqa: E402

LEGEND_MAX = 8
"""A panel with more channels than this names them in its label instead of a legend."""


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
    fig.savefig(out, dpi=110)
    plt.close(fig)


def plot_summary(folder: Path, out: Path) -> None:
    """Minutes recorded per class and per user, gaps written on each bar."""
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
    fig.savefig(out, dpi=110)
    plt.close(fig)


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="tactile-plot", description="Plot a take's channels over time, or with "
               "--summary a dataset's minutes and gaps per class and user.")
    p.add_argument("source", type=Path, help="a take's .csv file, or a dataset folder with "
                   "--summary")
    p.add_argument("-o", "--out", type=Path, required=True, help="image file to write (.png)")
    p.add_argument("--summary", action="store_true", help="plot a dataset folder's summary")
    add_debug(p)
    return p


def _main(args: argparse.Namespace) -> int:
    if args.out.is_dir() or not args.out.parent.is_dir():
        raise ConfigError(f"-o {args.out}: give an image file in a folder that exists")
    kinds = plt.figure().canvas.get_supported_filetypes()
    plt.close("all")
    if args.out.suffix.lower().lstrip(".") not in kinds:
        raise ConfigError(f"-o {args.out}: name an image file ending in .png, .svg or .pdf "
                          f"(or any of {', '.join(sorted(kinds))})")
    if args.summary:
        plot_summary(args.source, args.out)
    else:
        if args.source.is_dir():
            raise ConfigError(f"{args.source}: a folder; give a take's .csv, or add --summary")
        take = read_take(args.source)
        if len(take.seq) == 0:
            raise ConfigError(f"{args.source}: the take holds no samples")
        plot_take(take, args.out)
    print(args.out)
    return 0


def main(argv: list[str] | None = None) -> int:
    return run("tactile-plot", _main, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["main", "plot_take", "plot_summary"]
