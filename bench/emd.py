"""Benchmark: EMD as tensor ops (torch eager, onnxruntime) against PyEMD, one thread.

    python bench/emd.py [--repeats 3] [--pieces]

Prints, for 8-channel 50-sample windows and 1-channel 1000-sample windows (4 IMFs x 10 sifts,
the same windows for every implementation, measured in this run): milliseconds per window and
the speed-up over PyEMD ``EMD(FIXE=10).emd(x, max_imf=4)`` looping over channels; then the ONNX
graph's export time, node counts, file size and session creation time. Each timing is the
fastest of ``--repeats`` runs (PyEMD's too): on a shared machine, interference only ever adds
time, so the minimum is the steadiest estimate of what the code costs. ``--pieces`` instead
times each piece of one sift on its own at batch 1 (where the sift's time goes).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch
from PyEMD import EMD as PyEMD

from tactile.training.emd import EMD
from tactile.training.emd.onnx_export import count_nodes, export_emd_onnx, sift_path_nodes

N_IMFS, N_SIFTS = 4, 10


def signal_windows(n_windows: int, n_channels: int, n_time: int, seed: int = 0) -> np.ndarray:
    """(W, C, T) z-scored windows of EMD_SPEC §5's test signal (three tones plus noise)."""
    rng = np.random.default_rng(seed)
    fs = 100.0
    t = np.arange(n_windows * n_time) / fs
    out = np.empty((n_windows, n_channels, n_time))
    for c in range(n_channels):
        ph = rng.uniform(0, 2 * np.pi, 3)
        s = (
            np.sin(2 * np.pi * 1.3 * t + ph[0])
            + 0.6 * np.sin(2 * np.pi * 5.7 * t + ph[1])
            + 0.4 * np.sin(2 * np.pi * 17 * t + ph[2])
            + 0.25 * rng.standard_normal(t.size)
        )
        w = s.reshape(n_windows, n_time)
        out[:, c] = (w - w.mean(1, keepdims=True)) / w.std(1, keepdims=True)
    return out


def timed(fn, repeats: int) -> float:
    """Fewest seconds ``fn()`` took over ``repeats`` runs (after one warm-up run)."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def session(path: Path) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.log_severity_level = 3
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def bench_shape(n_channels: int, n_time: int, n_ref: int, repeats: int, tmp: Path) -> list[str]:
    x = signal_windows(256, n_channels, n_time)
    x32 = x.astype(np.float32)
    ref = PyEMD(FIXE=N_SIFTS, spline_kind="cubic", nbsym=2, extrema_detection="simple")

    def pyemd_loop():
        for w in x[:n_ref]:
            for ch in w:
                ref.emd(ch, max_imf=N_IMFS)

    t_ref = timed(pyemd_loop, repeats) / n_ref * 1e3
    model = EMD(N_IMFS, N_SIFTS)
    torch_1 = timed(lambda: [model(torch.from_numpy(x32[i : i + 1])) for i in range(8)], repeats)
    torch_256 = timed(lambda: model(torch.from_numpy(x32)), repeats)

    start = time.perf_counter()
    path = tmp / f"emd_{n_channels}x{n_time}.onnx"
    onnx_model = export_emd_onnx(path, N_IMFS, N_SIFTS, n_channels, n_time)
    t_export = time.perf_counter() - start
    start = time.perf_counter()
    sess = session(path)
    t_session = time.perf_counter() - start
    ort_1 = timed(lambda: [sess.run(None, {"x_in": x32[i : i + 1]}) for i in range(32)], repeats)
    ort_256 = timed(lambda: sess.run(None, {"x_in": x32}), repeats)
    rows = [
        ("PyEMD, loop over channels", t_ref),
        ("torch eager, batch 1", torch_1 / 8 * 1e3),
        ("torch eager, batch 256", torch_256 / 256 * 1e3),
        ("onnxruntime, batch 1", ort_1 / 32 * 1e3),
        ("onnxruntime, batch 256", ort_256 / 256 * 1e3),
    ]
    fewest, most = sift_path_nodes(onnx_model, n_time)
    lines = [
        f"## {n_channels} channel(s) x {n_time} samples, {N_IMFS} IMFs x {N_SIFTS} sifts",
        "",
        "| implementation | ms / window | x PyEMD |",
        "|---|---:|---:|",
    ]
    lines += [f"| {name} | {ms:.3f} | {t_ref / ms:.1f} |" for name, ms in rows]
    lines += [
        "",
        f"ONNX: export {t_export:.1f} s, {count_nodes(onnx_model.graph)} nodes "
        f"(one sift runs {fewest} to {most}, in a Loop), file {path.stat().st_size / 1e6:.3f} MB, "
        f"session creation {t_session:.3f} s",
        "",
    ]
    return lines


def bench_pieces(repeats: int, rows: int = 8) -> list[str]:
    """Each piece of one sift traced alone (float32, ``rows`` rows of 50 samples), run by
    onnxruntime: microseconds per run, less the cost of running an empty graph."""
    from tactile.training.emd.onnx_export import trace_graph
    from tactile.training.emd.pieces import piece_examples

    def per_run(sess: ort.InferenceSession, feed: dict) -> float:
        return timed(lambda: [sess.run(None, feed) for _ in range(200)], repeats) / 200 * 1e6

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    lines = ["## Pieces of one sift, traced alone (8 rows x 50 samples, batch 1)", "",
             "| piece | nodes | us per run |", "|---|---:|---:|"]
    examples = piece_examples(rows=rows, dtype=torch.float32)
    # The fixed cost of one run: a one-node graph on the first piece's input.
    probe = trace_graph(lambda x: x * 2.0, [examples["head"][1][0]], ["i0"], ["o0"], {})
    probe.ir_version = 8
    probe_sess = ort.InferenceSession(probe.SerializeToString(), opts,
                                      providers=["CPUExecutionProvider"])
    empty = per_run(probe_sess, {"i0": examples["head"][1][0].numpy()})
    for name, (fn, args) in examples.items():
        outs = fn(*args)
        names = [f"i{i}" for i in range(len(args))]
        n_out = len(outs) if isinstance(outs, tuple) else 1
        model = trace_graph(fn, args, names, [f"o{i}" for i in range(n_out)], {})
        model.ir_version = 8
        sess = ort.InferenceSession(model.SerializeToString(), opts,
                                    providers=["CPUExecutionProvider"])
        used = {i.name for i in sess.get_inputs()}
        feed = {k: a.numpy() for k, a in zip(names, args) if k in used}
        lines.append(f"| {name} | {len(model.graph.node)} | {per_run(sess, feed) - empty:.1f} |")
    return [*lines, ""]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per measurement")
    parser.add_argument("--pieces", action="store_true",
                        help="only time each piece of one sift on its own (batch 1)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    print(f"torch {torch.__version__}, onnxruntime {ort.__version__}, one thread", file=sys.stderr)
    if args.pieces:
        print("\n".join(bench_pieces(args.repeats)))
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        lines = bench_shape(8, 50, 20, args.repeats, Path(tmp))
        lines += bench_shape(1, 1000, 20, args.repeats, Path(tmp))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
