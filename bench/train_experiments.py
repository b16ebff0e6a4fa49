"""The pen paper's two experiments on the simulated pen, and the HapMat recordings, with and
without EMD features. Prints markdown tables (ours beside the paper's) for docs/results.md.

    python bench/train_experiments.py --out runs/experiments          # the full runs
    python bench/train_experiments.py --out /tmp/x --users 8 --seconds 20 --epochs 3   # a smoke run

Each simulated take is one user session of 60 s; users are split into train, validation and test,
so the test users are never seen in training. Training uses every core given by --threads.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from tactile.device.hapmat import import_hapmat
from tactile.device.sim_cli import make_dataset
from tactile.training.config import TrainConfig
from tactile.training.train import train

HAPMAT = (Path(__file__).resolve().parents[2] / "shared" / "datasets" / "hapmat"
          / "hapmat_stick_imu.npz")

# The pen paper's Tables 1 and 2 (row: label of input data, column: estimated class).
PAPER = {
    "exp1": (
        ("desk", "cardboard", "nonwoven_cloth", "paper"),
        [[0.865, 0.074, 0.026, 0.035],
         [0.008, 0.982, 0.006, 0.004],
         [0.025, 0.122, 0.811, 0.043],
         [0.02, 0.032, 0.005, 0.944]],
    ),
    "exp2": (
        ("non_contact", "paper", "nonwoven_cloth", "plastic_folder", "mouse_pad"),
        [[1.000, 0.000, 0.000, 0.000, 0.000],
         [0.000, 0.017, 0.017, 0.917, 0.050],
         [0.000, 0.102, 0.847, 0.000, 0.051],
         [0.000, 0.183, 0.000, 0.517, 0.300],
         [0.000, 0.153, 0.000, 0.017, 0.831]],
    ),
}
EMD_CHANNELS_PEN = ("pressure_0", "accel_x", "accel_y", "accel_z")
EMD_CHANNELS_HAPMAT = ("accel_x", "accel_y", "accel_z")


def paper_order(metrics: dict, order: tuple[str, ...]) -> np.ndarray:
    """Our row-normalised confusion matrix re-ordered into the paper's class order."""
    ours = metrics["classes"]
    norm = np.array(metrics["confusion_normalised"])
    idx = [ours.index(c) for c in order]
    return norm[np.ix_(idx, idx)]


def md_table(order: tuple[str, ...], ours: np.ndarray, paper: list | None) -> str:
    head = "| label of input data | " + " | ".join(order) + " |"
    lines = [head, "|---" * (len(order) + 1) + "|"]
    for i, c in enumerate(order):
        cells = []
        for j in range(len(order)):
            cell = f"{ours[i, j]:.3f}"
            if paper is not None:
                cell += f" ({paper[i][j]:.3f})"
            cells.append(cell)
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def run_one(name: str, data: Path, out: Path, cfg: TrainConfig) -> dict:
    t0 = time.perf_counter()
    m = train(data, out / name, cfg, progress=False)
    m["wall_seconds"] = round(time.perf_counter() - t0, 1)
    print(f"<!-- {name}: accuracy {m['accuracy']:.3f}, windows {m['split_windows']}, "
          f"{m['wall_seconds']} s -->", flush=True)
    return m


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--users", type=int, default=36, help="simulated users (takes per texture)")
    p.add_argument("--seconds", type=float, default=60.0, help="seconds per take")
    p.add_argument("--epochs", type=int, default=60)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--hapmat", type=Path, default=HAPMAT)
    p.add_argument("--only", choices=("exp1", "exp2", "hapmat"), action="append")
    args = p.parse_args()
    base = TrainConfig(epochs=args.epochs, threads=args.threads)
    todo = args.only or ["exp1", "exp2", "hapmat"]
    for exp in ("exp1", "exp2"):
        if exp not in todo:
            continue
        order, paper = PAPER[exp]
        data = args.out / f"data-{exp}"
        if not data.exists():
            make_dataset(data, args.users, order, args.seconds, seed=1)
        print(f"\n### Experiment {exp[-1]} (simulated pen, {args.users} users x {len(order)} "
              f"textures x {args.seconds:.0f} s)\n")
        # hop 25: about 20,000 training and 10,000 test windows, the pen paper's counts
        sim = base.replace(hop=25)
        for label, cfg in (("without EMD", sim),
                           ("with EMD", sim.replace(emd_channels=list(EMD_CHANNELS_PEN)))):
            m = run_one(f"{exp}-{label.replace(' ', '-')}", data, args.out, cfg)
            print(f"**{label}**: test accuracy {m['accuracy']:.3f} on {m['windows']} windows "
                  f"of unseen users (train {m['split_windows']['train']} windows); shifted "
                  f"+/-0.2 s: {m['shifted']['mean']:.3f}; {m['wall_seconds']} s on "
                  f"{args.threads} threads. Ours (paper's in brackets):\n")
            print(md_table(order, paper_order(m, order), paper) + "\n")
    if "hapmat" in todo:
        data = args.out / "data-hapmat"
        if not data.exists():
            import_hapmat(args.hapmat, data)
        print("\n### HapMat (real stick IMU, 5 materials; first 70% of each take trains, last "
              "30% tests)\n")
        hap = base.replace(split="time")
        rows = []
        for label, cfg in (("LSTM, without EMD", hap),
                           ("LSTM, with EMD", hap.replace(emd_channels=list(EMD_CHANNELS_HAPMAT))),
                           ("linear on EMD energies", hap.replace(
                               model="linear", emd_channels=list(EMD_CHANNELS_HAPMAT)))):
            m = run_one("hapmat-" + label.replace(" ", "-").replace(",", ""), data, args.out, cfg)
            rows.append((label, m))
        print("| model | test accuracy | shifted +/-0.2 s | windows (train/val/test) | time |")
        print("|---|---|---|---|---|")
        for label, m in rows:
            w = m["split_windows"]
            print(f"| {label} | {m['accuracy']:.3f} | {m['shifted']['mean']:.3f} | "
                  f"{w['train']}/{w['val']}/{w['test']} | {m['wall_seconds']} s |")
        order = tuple(rows[0][1]["classes"])
        print("\nLSTM without EMD, confusion on the test part:\n")
        print(md_table(order, paper_order(rows[0][1], order), None))


if __name__ == "__main__":
    main()
