"""Benchmark: EMD as tensor ops (torch eager, onnxruntime) against PyEMD, one thread.

    python bench/emd.py [--repeats 3] [--case CxTxM ...]
                        [--pieces | --profile | --node-costs | --layouts | --batches]

Prints, for 8-channel 50-sample windows and 1-channel 1000-sample windows (4 IMFs x 10 sifts)
and 1-channel 1100-sample windows (8 IMFs x 10 sifts: the BioTac's vibration, 0.5 s at 2.2 kHz),
the same windows for every implementation, measured in this run (``--case`` picks some):
milliseconds per window and the speed-up over PyEMD ``EMD(FIXE=10).emd(x, max_imf=M)`` looping
over channels (onnxruntime: ``export_emd_onnx``'s float32 graph, and an exported model's EMD
node on its portable path, the same graph in float64 inside); then the ONNX graph's export time,
node counts, file size and session creation time. The implementations are timed in ``--repeats``
rounds, each running every one of them in turn (after a warm-up round), and each timing is the
fastest of its rounds (PyEMD's too): on a shared machine, interference only ever adds time, so
the minimum is the steadiest estimate of what the code costs, and a slow spell of the host falls
on all of them alike. Instead of that:

* ``--pieces`` times each piece of one sift on its own, at batch 1 (8 rows of 50 samples) or,
  with ``--rows 2048``, at batch 256 (where element throughput, not node count, decides);
* ``--profile`` runs the 8 x 50 graph at batch 256 with onnxruntime's profiler (a warm-up run,
  then three) and prints each op type's and the top nodes' shares of kernel time;
* ``--node-costs`` measures what each node of the few-row sift body and of its PCR loop costs
  where it runs, at batch 1, on the first ``--case`` (default 1x1100x8): a variant of the graph
  computes the node ten more times, the copies kept alive by a ``Max`` that one consumer reads
  instead of the node's output, timed against a control with the ``Max`` alone, graph
  optimizations off in both, in CPU time (about 5 minutes);
* ``--layouts`` times the 8 x 50 graph at each batch size with the few-row and the many-row
  tensor layouts of the sift (the same arithmetic), interleaved, to place the switch between
  them (``spline.LARGE_ROWS``);
* ``--batches`` measures batch independence instead of speed: 512 windows (3 channels x 50
  samples) of coarse integer random walks and of the simulated pen, each decomposed by
  onnxruntime one window at a time (as ``tactile-run`` does) and by onnxruntime and torch in
  batches of 1, 21, 22, 64, 65 and 512 windows (torch at batch 1: the first 32 windows): the
  largest difference of any IMF value from the batch-1 onnxruntime one, in units of the
  window's std.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from emd_pieces import count_nodes, sift_path_nodes, subgraphs  # beside this script
from PyEMD import EMD as PyEMD

from tactile.contract import IR_VERSION
from tactile.export.emd_graph import build_emd_model, emd_node_model, export_emd_onnx
from tactile.runtime.model import session_options
from tactile.training.emd import EMD
from tactile.training.emd.spline import LARGE_ROWS

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


def options() -> ort.SessionOptions:
    """The runtime's settings (:func:`tactile.runtime.model.session_options`): one intra-op and
    one inter-op thread, sequential execution, no spinning, no memory arena, quiet."""
    return session_options(1)


def session(path: Path) -> ort.InferenceSession:
    opts = options()
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


CASES = ((8, 50, 4), (1, 1000, 4), (1, 1100, 8))
"""Default (channels, samples, IMFs) cases: the pen's 8 x 50 windows, a long window, and the
BioTac vibration's 0.5 s at 2.2 kHz with the granular models' 8 IMFs."""


def bench_shape(
    n_channels: int, n_time: int, n_ref: int, repeats: int, tmp: Path, n_imfs: int = N_IMFS
) -> list[str]:
    x = signal_windows(256, n_channels, n_time)
    x32 = x.astype(np.float32)
    ref = PyEMD(FIXE=N_SIFTS, spline_kind="cubic", nbsym=2, extrema_detection="simple")

    def pyemd_loop():
        for w in x[:n_ref]:
            for ch in w:
                ref.emd(ch, max_imf=n_imfs)

    start = time.perf_counter()
    path = tmp / f"emd_{n_channels}x{n_time}x{n_imfs}.onnx"
    onnx_model = export_emd_onnx(path, n_imfs, N_SIFTS, n_channels, n_time)
    t_export = time.perf_counter() - start
    start = time.perf_counter()
    sess = session(path)
    t_session = time.perf_counter() - start
    sess_2 = session(path)  # a session per batch size (docs/emd.md: onnxruntime runs a
    sess_256 = session(path)  # body slower at a batch size other than the first it ran)
    # An exported model's EMD node without the kernel library: the graph in float64 inside.
    node = ort.InferenceSession(
        emd_node_model(n_imfs, N_SIFTS, n_channels, n_time).SerializeToString(), options(),
        providers=["CPUExecutionProvider"])
    model = EMD(n_imfs, N_SIFTS)
    # Every implementation runs once in each round (after one warm-up round), and each keeps its
    # fastest round: a host that slows down for a while hits them all alike, so the ratios stay
    # fair (timed one after the other, a slow spell could fall on the reference alone).
    runs = {
        "ref": (pyemd_loop, n_ref),
        "torch_1": (lambda: [model(torch.from_numpy(x32[i : i + 1])) for i in range(8)], 8),
        "torch_256": (lambda: model(torch.from_numpy(x32)), 256),
        "ort_1": (lambda: [sess.run(None, {"x_in": x32[i : i + 1]}) for i in range(32)], 32),
        "node_1": (lambda: [node.run(None, {"x_in": x32[i : i + 1]}) for i in range(32)], 32),
        "ort_2": (lambda: [sess_2.run(None, {"x_in": x32[i : i + 2]}) for i in range(0, 32, 2)],
                  32),
        "ort_256": (lambda: sess_256.run(None, {"x_in": x32}), 256),
    }
    best = {name: float("inf") for name in runs}
    for round_ in range(repeats + 1):
        for name, (fn, n) in runs.items():
            start = time.perf_counter()
            fn()
            if round_:
                best[name] = min(best[name], (time.perf_counter() - start) / n * 1e3)
    t_ref = best["ref"]
    rows = [
        ("PyEMD, loop over channels", t_ref),
        ("torch eager, batch 1", best["torch_1"]),
        ("torch eager, batch 256", best["torch_256"]),
        ("onnxruntime, batch 1", best["ort_1"]),
        ("onnxruntime, a model's EMD node, portable (float64 inside), batch 1", best["node_1"]),
        ("onnxruntime, batch 2", best["ort_2"]),
        ("onnxruntime, batch 256", best["ort_256"]),
    ]
    fewest, most = sift_path_nodes(onnx_model, n_time)
    large = "{} to {}".format(*sift_path_nodes(onnx_model, n_time, large=True))
    lines = [
        f"## {n_channels} channel(s) x {n_time} samples, {n_imfs} IMFs x {N_SIFTS} sifts",
        "",
        "| implementation | ms / window | x PyEMD |",
        "|---|---:|---:|",
    ]
    lines += [f"| {name} | {ms:.3f} | {t_ref / ms:.1f} |" for name, ms in rows]
    lines += [
        "",
        f"ONNX: export {t_export:.1f} s, {count_nodes(onnx_model.graph)} nodes (one sift, in a "
        f"Loop, runs {fewest} to {most} below {LARGE_ROWS} rows, {large} from there on), "
        f"file {path.stat().st_size / 1e6:.3f} MB, session creation {t_session:.3f} s",
        "",
    ]
    return lines


def bench_pieces(repeats: int, rows: int = 8) -> list[str]:
    """Each piece of one sift traced alone (float32, ``rows`` rows of 50 samples), run by
    onnxruntime: microseconds per run, less the cost of running an empty graph."""
    from emd_pieces import piece_examples

    from tactile.export.traced import trace_graph

    def per_run(sess: ort.InferenceSession, feed: dict) -> float:
        return timed(lambda: [sess.run(None, feed) for _ in range(200)], repeats) / 200 * 1e6

    opts = options()
    batch = f"batch {rows // 8} of 8 channels" if rows % 8 == 0 else f"{rows} rows"
    lines = [f"## Pieces of one sift, traced alone ({rows} rows x 50 samples: {batch})", "",
             "| piece | nodes | us per run |", "|---|---:|---:|"]
    examples = piece_examples(rows=rows, dtype=torch.float32)
    # The fixed cost of one run: a one-node graph on the first piece's input.
    probe = trace_graph(lambda x: x * 2.0, [examples["head"][1][0]], ["i0"], ["o0"], {})
    probe.ir_version = IR_VERSION
    probe_sess = ort.InferenceSession(probe.SerializeToString(), opts,
                                      providers=["CPUExecutionProvider"])
    empty = per_run(probe_sess, {"i0": examples["head"][1][0].numpy()})
    for name, (fn, args) in examples.items():
        outs = fn(*args)
        names = [f"i{i}" for i in range(len(args))]
        n_out = len(outs) if isinstance(outs, tuple) else 1
        model = trace_graph(fn, args, names, [f"o{i}" for i in range(n_out)], {})
        model.ir_version = IR_VERSION
        sess = ort.InferenceSession(model.SerializeToString(), opts,
                                    providers=["CPUExecutionProvider"])
        used = {i.name for i in sess.get_inputs()}
        feed = {k: a.numpy() for k, a in zip(names, args) if k in used}
        lines.append(f"| {name} | {len(model.graph.node)} | {per_run(sess, feed) - empty:.1f} |")
    return [*lines, ""]


def bench_profile(tmp: Path, batch: int = 256, runs: int = 3) -> list[str]:
    """Shares of kernel time by op type and by node, 8 x 50 windows at ``batch``."""
    import collections
    import json

    path = tmp / "emd.onnx"
    export_emd_onnx(path, N_IMFS, N_SIFTS, 8, 50)
    opts = options()
    opts.enable_profiling = True
    opts.profile_file_prefix = str(tmp / "profile")
    sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    x = signal_windows(batch, 8, 50).astype(np.float32)
    for _ in range(runs + 1):
        sess.run(None, {"x_in": x})
    events = json.loads(Path(sess.end_profiling()).read_text())
    # The first run grows the memory arena: only the runs after it count.
    first = min((ev for ev in events if ev["name"] == "model_run"), key=lambda ev: ev["ts"])
    warm = first["ts"] + first["dur"]
    by_op: dict[str, float] = collections.defaultdict(float)
    by_node: dict[str, float] = collections.defaultdict(float)
    for ev in events:
        if ev.get("cat") != "Node" or not ev["name"].endswith("_kernel_time"):
            continue
        if ev["ts"] < warm:
            continue
        op = ev["args"].get("op_name", "")
        if op in ("Loop", "If"):  # their time is their bodies' nodes
            continue
        by_op[op] += ev["dur"]
        by_node[ev["name"][: -len("_kernel_time")]] += ev["dur"]
    total = sum(by_op.values())
    lines = [f"## Kernel time at batch {batch} (8 x 50, {runs} runs after a warm-up): "
             f"{total / runs / 1e3:.1f} ms per run", "", "| op type | share |", "|---|---:|"]
    lines += [f"| {op} | {t / total:.1%} |"
              for op, t in sorted(by_op.items(), key=lambda kv: -kv[1])[:15]]
    lines += ["", "| node | share |", "|---|---:|"]
    lines += [f"| {name} | {t / total:.1%} |"
              for name, t in sorted(by_node.items(), key=lambda kv: -kv[1])[:15]]
    return [*lines, ""]


def bench_node_costs(
    repeats: int, case: tuple[int, int, int] = (1, 1100, 8), copies: int = 10, top: int = 30
) -> list[str]:
    """CPU microseconds each node of the few-row sift body (and of its PCR loop body) costs
    where it runs, at batch 1, per sift (a window's cost spread over the sifts it runs).

    For each node, a variant of the graph computes it ``copies`` more times and keeps the copies
    alive with one ``Max`` (``Or`` for booleans) of the node's output and the copies, read by
    one of its consumers in place of the output (the same values); the control reads a ``Max``
    of the output with itself as many times. Graph optimizations are off in both, so that
    onnxruntime neither merges the copies nor drops them. CPU time of the process (one thread):
    the host's other load adds no waiting to it. onnxruntime's own profiler is not used: it adds
    several microseconds to every node it times, more than most nodes cost."""
    import copy

    from onnx import helper

    n_channels, n_time, n_imfs = case
    model = build_emd_model(n_imfs, N_SIFTS, n_channels, n_time)
    opts = options()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    x = signal_windows(4, n_channels, n_time).astype(np.float32)
    sifts = _sifts_run(x, n_imfs)
    # Element types of every value, subgraphs included (only float, int64 and bool are kept).
    inferred = onnx.shape_inference.infer_shapes(model)
    elem: dict[str, int] = {}
    for g in [inferred.graph, *subgraphs(inferred.graph).values()]:
        for v in [*g.value_info, *g.output, *g.input]:
            elem[v.name] = v.type.tensor_type.elem_type

    def variant(body_name: str, i: int, dup: bool) -> ort.InferenceSession | None:
        m = copy.deepcopy(model)
        body = subgraphs(m.graph)[body_name]
        node = body.node[i]
        out = node.output[0]
        users = [n for n in body.node if out in n.input]
        kind = elem.get(out)
        if not users or kind not in (onnx.TensorProto.FLOAT, onnx.TensorProto.INT64,
                                     onnx.TensorProto.BOOL):
            return None
        extra, names = [], []
        for c in range(copies):
            if dup:
                d = copy.deepcopy(node)
                d.name = f"{node.name}_copy{c}"
                del d.output[:]
                d.output.extend(f"{o}_copy{c}" for o in node.output)
                extra.append(d)
                names.append(d.output[0])
            else:
                names.append(out)
        if kind == onnx.TensorProto.BOOL:
            prev = out
            for c, v in enumerate(names):
                extra.append(helper.make_node("Or", [prev, v], [f"{out}_or{c}"]))
                prev = f"{out}_or{c}"
            live = prev
        else:
            live = f"{out}_max"
            extra.append(helper.make_node("Max", [out, *names], [live]))
        users[0].input[:] = [live if v == out else v for v in users[0].input]
        nodes = list(body.node)
        del body.node[:]
        body.node.extend(nodes[: i + 1] + extra + nodes[i + 1 :])
        return ort.InferenceSession(m.SerializeToString(), opts,
                                    providers=["CPUExecutionProvider"])

    def cpu(sess: ort.InferenceSession) -> float:
        start = time.process_time()
        for w in x:
            sess.run(None, {"x_in": w[None]})
        return (time.process_time() - start) / len(x)

    rows = []
    for body_name in ("sift", "pcr"):
        for i, node in enumerate(subgraphs(model.graph)[body_name].node):
            if node.op_type in ("If", "Loop"):
                continue
            control, dup = variant(body_name, i, False), variant(body_name, i, True)
            if control is None:
                continue
            t_control = t_dup = float("inf")
            for _ in range(repeats):  # interleaved: drift of the host hits both alike
                t_control, t_dup = min(t_control, cpu(control)), min(t_dup, cpu(dup))
            us = (t_dup - t_control) / sifts / copies * 1e6
            piece = node.name.split("/")[0] or "(wiring)"
            rows.append((us, node.op_type, f"{body_name}: {node.name or node.op_type}",
                         "pcr loop" if body_name == "pcr" else piece))
    plain = options()
    base = ort.InferenceSession(model.SerializeToString(), plain,
                                providers=["CPUExecutionProvider"])
    per_sift = min(cpu(base) for _ in range(repeats)) / sifts * 1e6
    c, t, m = case
    lines = [f"## Cost of each node where it runs ({c} x {t}, {m} IMFs, batch 1, "
             f"{copies} copies, CPU time)", "",
             f"{len(rows)} nodes measured ({sifts:.1f} sifts a window); a sift takes "
             f"{per_sift:.0f} us of CPU time; the PCR loop body's nodes are per sift too (they "
             "run 0 to a few times a sift)", "", "| node | op | us |", "|---|---|---:|"]
    lines += [f"| {name} | {op} | {us:.2f} |"
              for us, op, name, _ in sorted(rows, reverse=True)[:top]]
    for title, key in (("op type", 1), ("piece", 3)):
        groups: dict[str, list[float]] = {}
        for r in rows:
            groups.setdefault(r[key], []).append(r[0])
        lines += ["", f"| {title} | nodes | median us | total us |", "|---|---:|---:|---:|"]
        lines += [f"| {k} | {len(v)} | {float(np.median(v)):.2f} | {sum(v):.1f} |"
                  for k, v in sorted(groups.items(), key=lambda kv: -sum(kv[1]))]
    return [*lines, ""]


def bench_layouts(repeats: int, batches=(1, 2, 4, 6, 8, 16, 32, 256)) -> list[str]:
    """ms per window of the 8 x 50 graph with the few-row and the many-row layouts at every
    batch size."""
    x = signal_windows(256, 8, 50).astype(np.float32)
    opts = options()
    graphs = [build_emd_model(N_IMFS, N_SIFTS, 8, 50, large_rows=t).SerializeToString()
              for t in (2**62, 1)]
    lines = [
        f"## Sift layout by batch size (8 x 50; the graph switches at {LARGE_ROWS} rows)",
        "",
        "| batch | rows | few-row ms / window | many-row ms / window | few / many |",
        "|---:|---:|---:|---:|---:|",
    ]
    for b in batches:
        n = max(b, 32)  # windows per timed run
        # Fresh sessions for every batch size: a session that ran batch 1 first runs the small
        # body at batch 2-6 some 15% slower than a fresh one (onnxruntime 1.32; the TopK node
        # is involved: the same body without it shows no such effect).
        few, many = (ort.InferenceSession(g, opts, providers=["CPUExecutionProvider"])
                     for g in graphs)

        def run(sess: ort.InferenceSession, b: int = b, n: int = n) -> None:
            for i in range(0, n, b):
                sess.run(None, {"x_in": x[i : i + b]})

        times = {id(few): [], id(many): []}
        run(few)
        run(many)
        for _ in range(repeats):  # interleaved, so drift of the host hits both alike
            for sess in (few, many):
                start = time.perf_counter()
                run(sess)
                times[id(sess)].append((time.perf_counter() - start) / n * 1e3)
        t_few, t_many = min(times[id(few)]), min(times[id(many)])
        lines.append(f"| {b} | {8 * b} | {t_few:.3f} | {t_many:.3f} | {t_few / t_many:.2f} |")
    return lines


BATCHES = (1, 21, 22, 64, 65, 512)
"""Batch sizes of ``--batches``: around the layout switch (3 channels: 63 / 66 rows at 21 / 22
windows) and evaluation's 512."""


def random_walks(n_windows: int, n_channels: int, seed: int = 0) -> np.ndarray:
    """(W, C, 50) coarse integer random walks (steps -5..5: plateaus, like raw pressure
    counts), each row z-scored."""
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.integers(-5, 6, (n_windows, n_channels, 50)), -1).astype(np.float64)
    std = x.std(-1, keepdims=True)
    return (x - x.mean(-1, keepdims=True)) / np.where(std > 0, std, 1.0)


def pen_windows(n_windows: int, channels=("pressure_0", "accel_z", "gyro_x")) -> np.ndarray:
    """(W, 3, 50) windows of the simulated pen (hop 25, the textures in turn), each channel
    normalised by its mean and std over all of them, as a model's preprocessing does with the
    training split's."""
    from tactile.device.protocol import PEN_CHANNELS
    from tactile.device.sim import TEXTURES, PenSimulator

    names = [c.name for c in PEN_CHANNELS]
    idx = [names.index(c) for c in channels]
    per = -(-n_windows // len(TEXTURES))
    out = []
    for k, texture in enumerate(TEXTURES):
        values = PenSimulator(texture, seed=k).read(25 * per + 25)[:, idx].astype(np.float64)
        starts = np.arange(per) * 25
        out.append(values[starts[:, None] + np.arange(50)[None, :]])  # (per, 50, 3)
    x = np.concatenate(out)[:n_windows].transpose(0, 2, 1)  # (W, 3, 50)
    mean, std = x.mean((0, 2), keepdims=True), x.std((0, 2), keepdims=True)
    return (x - mean) / np.where(std > 0, std, 1.0)


def bench_batches(tmp: Path, n_windows: int = 512, torch_one: int = 32) -> list[str]:
    """Largest |IMF difference| (x window std) from onnxruntime at batch 1, per batch size."""
    path = tmp / "emd_3x50.onnx"
    export_emd_onnx(path, N_IMFS, N_SIFTS, 3, 50)
    sess = session(path)
    model = EMD(N_IMFS, N_SIFTS)
    lines = [f"## Batch independence: 3 channels x 50 samples, {n_windows} windows, "
             f"{N_IMFS} IMFs x {N_SIFTS} sifts", "",
             r"max \|IMF - IMF at batch 1 in onnxruntime\| in units of the window's std "
             f"(torch at batch 1: the first {torch_one} windows); windows that differ by more "
             "than 1e-4 in brackets", "",
             "| windows | batch | onnxruntime | torch |", "|---|---:|---:|---:|"]
    for name, x in (("random walk", random_walks(n_windows, 3)), ("simulated pen",
                                                                  pen_windows(n_windows))):
        x32 = x.astype(np.float32)
        std = np.where(x32.std(-1) > 0, x32.std(-1), 1.0)[:, :, None, None]  # (W, 3, 1, 1)
        ref = np.concatenate([sess.run(None, {"x_in": x32[i : i + 1]})[0]
                              for i in range(n_windows)])

        def worst(imfs: np.ndarray, n: int, ref: np.ndarray = ref, std: np.ndarray = std) -> str:
            d = (np.abs(imfs.astype(np.float64) - ref[:n]) / std[:n]).max((1, 2, 3))
            return f"{d.max():.2g} ({int((d > 1e-4).sum())})"

        for b in BATCHES:
            n_torch = torch_one if b == 1 else n_windows
            got_ort = np.concatenate([sess.run(None, {"x_in": x32[i : i + b]})[0]
                                      for i in range(0, n_windows, b)])
            with torch.no_grad():
                got_torch = torch.cat([model(torch.from_numpy(x32[i : i + b]))[0]
                                       for i in range(0, n_torch, b)]).numpy()
            lines.append(f"| {name} | {b} | {worst(got_ort, n_windows)} | "
                         f"{worst(got_torch, n_torch)} |")
    return [*lines, ""]


def _sifts_run(windows: np.ndarray, n_imfs: int = N_IMFS) -> float:
    """Sifts the graph runs per (C, T) window of ``windows``, one window at a time (the sift
    loop stops once no row is active; counted with the eager pieces)."""
    from tactile.training.emd.decompose import imf_update
    from tactile.training.emd.sift import sift

    count = 0
    for window in windows:
        x = torch.from_numpy(window.astype(np.float64))
        acc, alive = torch.zeros_like(x), torch.ones(x.shape[0], 1, dtype=torch.bool)
        for _ in range(n_imfs):
            h, active = x - acc, alive
            for _ in range(N_SIFTS):
                if not bool(active.any()):
                    break
                count += 1
                h, active = sift(h, active)
            _, acc, alive = imf_update(x, acc, h, active)
    return count / len(windows)


def main(argv: list[str] | None = None) -> int:
    from tactile.cli import Parser, int_in

    parser = Parser(prog="emd.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int_in(1), default=3, help="timed runs per measurement")
    parser.add_argument("--pieces", action="store_true",
                        help="only time each piece of one sift alone (batch 1; see --rows)")
    parser.add_argument("--rows", type=int_in(1),
                        help="rows (windows x 8 channels) for --pieces (default 8: batch 1)")
    parser.add_argument("--profile", action="store_true",
                        help="only profile the 8 x 50 graph at batch 256 (shares of kernel time)")
    parser.add_argument("--node-costs", action="store_true",
                        help="only measure each sift-body node's cost where it runs (batch 1, "
                        "the first --case, default 1x1100x8)")
    parser.add_argument("--layouts", action="store_true",
                        help="only time the few-row against the many-row layout at each batch size")
    parser.add_argument("--batches", action="store_true",
                        help="only measure how far a window's IMFs move with the batch size")
    parser.add_argument("--case", action="append", metavar="CxTxM",
                        help="time only this case: channels x samples x IMFs, e.g. 1x1100x8 "
                        "(repeatable; default: " + ", ".join("x".join(map(str, c)) for c in CASES)
                        + ")")
    args = parser.parse_args(argv)
    cases = CASES
    if args.case:
        try:
            cases = tuple(tuple(int(v) for v in c.lower().split("x")) for c in args.case)
            if any(len(c) != 3 or min(c) < 1 for c in cases):
                raise ValueError
        except ValueError:
            parser.error(f"--case takes channels x samples x IMFs, e.g. 1x1100x8, got {args.case}")
    if args.rows is not None and (not args.pieces or args.rows < 1):
        parser.error(f"--rows takes a count of at least 1 and goes with --pieces, got {args.rows}")
    torch.set_num_threads(1)
    print(f"torch {torch.__version__}, onnxruntime {ort.__version__}, one thread", file=sys.stderr)
    if args.pieces:
        print("\n".join(bench_pieces(args.repeats, rows=args.rows or 8)))
        return 0
    if args.layouts:
        print("\n".join(bench_layouts(args.repeats)))
        return 0
    if args.batches:
        with tempfile.TemporaryDirectory() as tmp:
            print("\n".join(bench_batches(Path(tmp))))
        return 0
    if args.node_costs:
        print("\n".join(bench_node_costs(args.repeats, cases[0] if args.case else (1, 1100, 8))))
        return 0
    if args.profile:
        with tempfile.TemporaryDirectory() as tmp:
            print("\n".join(bench_profile(Path(tmp))))
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        lines = []
        for n_channels, n_time, n_imfs in cases:
            lines += bench_shape(n_channels, n_time, 20, args.repeats, Path(tmp), n_imfs)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
