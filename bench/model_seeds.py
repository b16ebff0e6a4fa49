"""An exported model on simulated users it never saw: window accuracy per simulator seed.

    python bench/model_seeds.py models/pen-exp2.onnx                 # seeds 0-7, 60 s each
    python bench/model_seeds.py model.onnx --seeds 0,1,2 --seconds 20

For each seed, each of the model's classes is simulated as ``sim://?texture=T&seed=S`` streams it
(``PenSimulator(T, seed=S)``: one simulated user's session), cut into the model's windows every
``--hop`` samples and classified with onnxruntime from a zero state (the runtime's package only).
Prints one row per seed (accuracy, and the recall of each class) and the mean.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from tactile.device.sim import PenSimulator
from tactile.runtime.model import Model


def seed_recalls(model: Model, seed: int, seconds: float, hop: int) -> dict[str, float]:
    """{class: fraction of its windows read as that class} for one simulator seed."""
    c = model.contract
    out = {}
    for k, texture in enumerate(c.classes):
        sim = PenSimulator(texture, seed=seed, rate_hz=c.sample_rate_hz)
        n = round(seconds * c.sample_rate_hz)
        raw = sim.read(n).astype(np.float64)
        scale = np.array([ch.scale for ch in sim.info.channels])
        offset = np.array([ch.offset for ch in sim.info.channels])
        names = list(sim.info.channel_names)
        values = (raw * scale + offset)[:, [names.index(ch) for ch in c.channels]]
        starts = np.arange(0, n - c.window + 1, hop)
        x = values[starts[:, None] + np.arange(c.window)[None, :]].astype(np.float32)
        h, cc = model.zero_state(len(x))
        probs, _, _ = model.classify(x, h, cc)
        out[texture] = float((probs.argmax(1) == k).mean())
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("model", type=Path)
    p.add_argument("--seeds", default="0,1,2,3,4,5,6,7")
    p.add_argument("--seconds", type=float, default=60.0, help="seconds per class and seed")
    p.add_argument("--hop", type=int, default=25)
    args = p.parse_args(argv)
    model = Model(args.model)
    classes = list(model.contract.classes)
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    print("| seed | accuracy | " + " | ".join(f"{c} recall" for c in classes) + " |")
    print("|---" * (len(classes) + 2) + "|")
    accs = []
    for s in seeds:
        r = seed_recalls(model, s, args.seconds, args.hop)
        accs.append(np.mean(list(r.values())))
        print(f"| {s} | {accs[-1]:.3f} | " + " | ".join(f"{r[c]:.3f}" for c in classes) + " |",
              flush=True)
    worst = int(np.argmin(accs))
    print(f"\nmean {np.mean(accs):.3f}, lowest {accs[worst]:.3f} (seed {seeds[worst]})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
