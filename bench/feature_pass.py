"""Benchmark: training's feature pass (the EMD of every window) with and without the native
kernels, on the windows a config trains on.

    python bench/feature_pass.py DATA --config configs/granular/biotac-all-sf_rnn.toml
    python bench/feature_pass.py DATA --config CONFIG --windows 200 --repeats 3

DATA is a take folder (BioTac: ``tactile-import-biotac PATH/biotac-bolt/*.h5 --out DATA``).
The config's model is built as ``tactile-train`` builds it, and the EMD stage of its
preprocessing (``pre.decompose``: every modality with IMFs, the 2.2 kHz vibration included) runs
on the first ``--windows`` training windows, one torch thread, in three ways measured in the
same run (interleaved rounds, the fastest kept, thread CPU time):

* the feature pass with the kernels (``tactile.training.feature_pass``: float64, native);
* the feature pass with ``TACTILE_NATIVE=0`` (float64, torch): the same IMFs;
* the EMD in float32 torch outside the feature pass (what training ran before the kernels).

Prints ms per window, the ratios, and whether the two feature passes gave identical IMFs.
Issue target: the pass >= 10x faster with the kernel built.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    from tactile.cli import Parser, int_in

    p = Parser(prog="feature_pass.py", description=__doc__.split("\n\n")[0])
    p.add_argument("data", type=Path, help="take folder")
    p.add_argument("--config", type=Path, required=True, help="a tactile-train config (TOML)")
    p.add_argument("--windows", type=int_in(1), default=200, help="training windows timed")
    p.add_argument("--repeats", type=int_in(1), default=3, help="rounds (fastest kept)")
    args = p.parse_args(argv)

    import torch

    from tactile import native
    from tactile.device.recordings import load_dataset
    from tactile.training.config import TrainConfig
    from tactile.training.dist import Dist
    from tactile.training.feature_pass import feature_pass
    from tactile.training.log import Log
    from tactile.training.models import build_model
    from tactile.training.prepare import check_inputs, prepare

    if not native.available():
        print("feature_pass: the native kernels are not built", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    cfg = TrainConfig.from_toml(args.config)
    takes = load_dataset(args.data)
    classes, channels = check_inputs(args.data, takes, cfg)
    log = Log(False, True)
    prep = prepare(takes, classes, channels, cfg, log, Dist.from_env())
    norm = prep.norm
    model = build_model(prep.cfg, len(classes), torch.from_numpy(norm.mean),
                        torch.from_numpy(norm.std), channels=channels,
                        rate_hz=takes[0].info.sample_rate_hz, emd_index=norm.emd_index,
                        center_index=norm.center_index)
    pre = model.pre
    x = torch.from_numpy(prep.parts["train"].x[: args.windows])
    z = pre.normalise(x)

    def native_pass():
        with feature_pass():
            return pre.decompose(z)

    def torch_pass():
        os.environ["TACTILE_NATIVE"] = "0"
        try:
            with feature_pass():
                return pre.decompose(z)
        finally:
            del os.environ["TACTILE_NATIVE"]

    def float32_torch():
        return pre.decompose(z)

    fns = {"feature pass, native": native_pass, "feature pass, TACTILE_NATIVE=0": torch_pass,
           "float32 torch (before)": float32_torch}
    best = dict.fromkeys(fns, float("inf"))
    outs = {}
    with torch.no_grad():
        for _ in range(args.repeats):
            for name, fn in fns.items():
                t = time.thread_time()
                outs[name] = fn()
                best[name] = min(best[name], time.thread_time() - t)
    same = all(torch.equal(a, b) for a, b in zip(outs["feature pass, native"],
                                                 outs["feature pass, TACTILE_NATIVE=0"],
                                                 strict=True))
    n = len(x)
    shapes = ", ".join(f"{tuple(s.shape[1:])}" for s in pre.emd_inputs(z[:1]))
    print(f"{args.config.name}: EMD of {n} training windows (inputs {shapes} each; "
          f"{pre.emds[0].n_sifts} sifts), one thread, fastest of {args.repeats}")
    base = best["feature pass, native"]
    print(f"  {'pass':<32} {'ms/window':>10} {'x native':>9}")
    for name, s in best.items():
        print(f"  {name:<32} {1e3 * s / n:>10.3f} {s / base:>9.1f}")
    print(f"  the two feature passes' IMFs identical: {'yes' if same else 'NO'}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
