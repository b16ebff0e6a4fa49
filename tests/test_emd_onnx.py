"""EMD exported to ONNX: the graph contract, node budgets, and onnxruntime parity.

onnxruntime (float32) is compared with the torch module (float32) and with PyEMD (float64)
on the parity windows of ``test_emd.py``. Tolerance: max abs difference <= 1e-4 x window std
with the same IMF count, on >= 99.5% of windows. Every window outside it must be explained by
a near-tie: two samples whose order decides an extremum (or a boundary case) closer than
``NEAR_TIE`` x std somewhere along PyEMD's own float64 trajectory; float32 carries ~1e-7
relative error per operation, ~1e-6 after 40 sifts, so such a pair can flip and the
decomposition then legitimately takes another branch.
"""

from __future__ import annotations

import importlib.util

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from conftest import REPO
from emd_cases import compare, near_tie_gap, parity_set, run_torch

from tactile.contract import OPSET
from tactile.errors import ConfigError
from tactile.export.emd_graph import build_emd_model, export_emd_onnx
from tactile.export.traced import trace_graph
from tactile.training.emd import EMD
from tactile.training.emd.spline import LARGE_ROWS


def _load_pieces():
    """bench/emd_pieces.py (the same code the benchmark imports): the pieces, node counts."""
    spec = importlib.util.spec_from_file_location("emd_pieces", REPO / "bench" / "emd_pieces.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_pieces = _load_pieces()
piece_examples, subgraphs, subgraph_nodes = (
    _pieces.piece_examples, _pieces.subgraphs, _pieces.subgraph_nodes)
sift_path_nodes, count_nodes = _pieces.sift_path_nodes, _pieces.count_nodes

TOL = 1e-4  # x window std
MIN_PASS = 0.995
NEAR_TIE = 1e-5  # x window std
# Node budgets per piece (opset 18, traced as exported); a sift runs them in this order ("head",
# then "strict" without ties or "plateau" with them, ...). Lower them when a piece gets leaner;
# a rise means a change added kernel launches to every sift.
BUDGET = {
    "head": 7,  # has_tie's min of |signs|: onnxruntime 1.19 has no float64 ReduceProd
    "strict": 4,
    "plateau": 31,
    "end_topk": 10,  # below LARGE_ROWS rows; from there on "counts", "end_extrema", "sides"
    "counts": 5,
    "end_extrema": 12,
    "sides": 2,
    "boundary": 38,
    "assemble": 13,
    "spacings": 5,  # Gathers rather than a Split on the leading axis: more nodes, less time
    "system": 20,
    "solve": 68,
    "segment": 6,
    "evaluate": 21,
    "finish": 35,
}
SIFT_SHORTEST = 189  # nodes run by one sift with few knots (later IMFs): PCR_ALWAYS steps
SIFT_LONGEST = 221  # ... and with many knots (every PCR step, an iteration of the PCR loop each)
SIFT_LARGE = (203, 235)  # the same from LARGE_ROWS rows on (the many-row layout)


def _session(model: onnx.ModelProto) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    return ort.InferenceSession(model.SerializeToString(), opts, providers=["CPUExecutionProvider"])


@pytest.fixture(scope="module")
def default_model(tmp_path_factory) -> tuple[onnx.ModelProto, int]:
    path = tmp_path_factory.mktemp("emd") / "emd.onnx"
    model = export_emd_onnx(path, n_imfs=4, n_sifts=10, n_channels=8, n_time=50)
    return model, path.stat().st_size


def test_graph_contract(default_model):
    model, size = default_model
    onnx.checker.check_model(model, full_check=True)
    assert [o.version for o in model.opset_import if o.domain in ("", "ai.onnx")] == [OPSET]
    (inp,) = model.graph.input
    assert inp.name == "x_in" and inp.type.tensor_type.elem_type == onnx.TensorProto.FLOAT
    dims = [d.dim_param or d.dim_value for d in inp.type.tensor_type.shape.dim]
    assert dims == ["batch", 8, 50]
    outs = {o.name: o.type.tensor_type.elem_type for o in model.graph.output}
    assert outs == {
        "imfs": onnx.TensorProto.FLOAT,
        "residue": onnx.TensorProto.FLOAT,
        "n_valid": onnx.TensorProto.INT64,
    }
    assert size < 5_000_000
    # The layout choice is an If on the row count; each branch holds the IMF Loop.
    assert "If" in {n.op_type for n in model.graph.node}
    bodies = subgraphs(model.graph)
    for name in ("layout_small", "layout_large"):
        assert [n.op_type for n in bodies[name].node] == ["Loop"]


def test_skipped_solver_steps_and_plateau_branch_change_nothing(default_model):
    """Per window, later IMFs skip PCR steps and windows without ties skip the plateau rule;
    in one batch every step and (with quantised windows) the plateau branch run. Bit for bit
    the same outputs."""
    from emd_cases import windows

    x = np.concatenate([windows(kind, 50, 16, 3) for kind in ("tones", "chirp", "quantised")])
    x = x.reshape(-1, 8, 50).astype(np.float32)  # (6, 8, 50): two windows of each kind
    sess = _session(default_model[0])
    whole = sess.run(None, {"x_in": x})
    for i in range(len(x)):
        single = sess.run(None, {"x_in": x[i : i + 1]})
        for a, b in zip(single, whole):
            np.testing.assert_array_equal(a[0], b[i])


@pytest.mark.parametrize("batch", [1, 7, 9])  # 8, 56 rows: few-row layout; 72 rows: many
def test_dynamic_batch_and_output_shapes(default_model, batch):
    model, _ = default_model
    x = np.random.default_rng(batch).standard_normal((batch, 8, 50)).astype(np.float32)
    imfs, residue, n_valid = _session(model).run(None, {"x_in": x})
    assert imfs.shape == (batch, 8, 4, 50) and residue.shape == (batch, 8, 50)
    assert n_valid.shape == (batch, 8) and n_valid.dtype == np.int64
    ref = EMD(4, 10)(torch.from_numpy(x))
    np.testing.assert_array_equal(n_valid, ref[2].numpy())
    np.testing.assert_allclose(imfs, ref[0].numpy(), rtol=0, atol=1e-5)


def test_piece_node_budgets():
    counts = {}
    for name, (fn, args) in piece_examples().items():
        outs = fn(*args)
        n_out = len(outs) if isinstance(outs, tuple) else 1
        model = trace_graph(
            fn, args, [f"i{i}" for i in range(len(args))], [f"o{i}" for i in range(n_out)], {}
        )
        counts[name] = len(model.graph.node)
    over = {k: (counts[k], BUDGET[k]) for k in BUDGET if counts[k] > BUDGET[k]}
    assert not over, f"node count over budget (got, budget): {over}"


def test_sift_body_and_total_node_counts(default_model):
    model, _ = default_model
    graphs = subgraph_nodes(model.graph)
    # The plateau rule is a Loop body (one iteration with ties, none without): its nodes plus
    # the loop's pass-through of the condition.
    assert graphs["plateau"] <= BUDGET["plateau"] + 1
    # Nodes one sift runs without ties: the body (head, strict rule, knots, system, the first
    # PCR steps, envelopes, update), then as many iterations of the PCR loop as the knots need.
    shortest, longest = sift_path_nodes(model, 50)
    assert shortest <= SIFT_SHORTEST and longest <= SIFT_LONGEST, (shortest, longest)
    # The sift loop stops once no row is active: its condition is computed, not passed through.
    sift_loop = next(n for n in subgraphs(model.graph)["imf"].node if n.op_type == "Loop")
    assert sift_loop.input[1], "the sift loop has no start condition"
    producer = {o: n for n in subgraphs(model.graph)["sift"].node for o in n.output}
    assert producer["s_c_out"].op_type != "Identity"
    # The large-batch body runs the same PCR steps, in the same loop, on its own layout.
    shortest, longest = sift_path_nodes(model, 50, large=True)
    assert shortest <= SIFT_LARGE[0] and longest <= SIFT_LARGE[1], (shortest, longest)
    large_ops = [n.op_type for n in subgraphs(model.graph)["sift_large"].node]
    small_ops = [n.op_type for n in subgraphs(model.graph)["sift"].node]
    # No If (onnxruntime runs an If for several microseconds, a Loop of no iteration for about
    # one): a Loop for the plateau rule and one for the later PCR steps.
    assert large_ops.count("If") == small_ops.count("If") == 0
    assert large_ops.count("Loop") == small_ops.count("Loop") == 2
    loops = sum(v for k, v in graphs.items() if k.startswith(("pcr", "plateau")))
    bodies = graphs["sift"] + graphs["sift_large"]
    # Beyond those: two IMF loop bodies (20 nodes each), the layout If's branches (a Loop
    # each) and the main graph (set-up with the tensors the bodies take from outside, the
    # row-count test, reshapes): 37 now.
    assert count_nodes(model.graph) <= bodies + loops + 2 * 20 + 2 + 37


@pytest.mark.parametrize("batch", [4, 30])  # 12 rows: few-row layout; 90 rows: many
def test_float64_graph_matches_torch_float64(batch):
    model = build_emd_model(4, 10, 3, 60, dtype=torch.float64)
    x = np.random.default_rng(3).standard_normal((batch, 3, 60))
    imfs, residue, n_valid = _session(model).run(None, {"x_in": x})
    ref = EMD(4, 10)(torch.from_numpy(x))
    np.testing.assert_array_equal(n_valid, ref[2].numpy())
    np.testing.assert_allclose(imfs, ref[0].numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(residue, ref[1].numpy(), rtol=0, atol=1e-12)


def test_a_models_emd_node_runs_float64_without_the_kernels():
    """An exported model's EMD node on a plain onnxruntime (no kernel library: a board without
    a compiler) runs its function, the float64 graph with a cast each way: the float64 graph's
    bits, within float32 output rounding of the float64 torch module; with two shapes in one
    function (an If picks the body) each its own."""
    from onnx import helper

    from tactile.export.custom_ops import function_of, opset_imports
    from tactile.export.emd_graph import emd_node_model, portable_body

    rng = np.random.default_rng(11)
    for c, t, k in ((2, 50, 4), (1, 300, 6)):
        x = np.cumsum(rng.standard_normal((3, c, t)), -1).astype(np.float32)
        node = _session(emd_node_model(k, 10, c, t)).run(None, {"x_in": x})
        g64 = _session(build_emd_model(k, 10, c, t, torch.float64)).run(
            None, {"x_in": x.astype(np.float64)})
        for a, b in zip(node, g64):
            assert a.dtype == (np.int64 if b.dtype == np.int64 else np.float32)
            np.testing.assert_array_equal(a, b.astype(a.dtype))
        ref = EMD(k, 10)(torch.from_numpy(x.astype(np.float64)))
        std = x.std(-1)[..., None]
        np.testing.assert_array_equal(node[2], ref[2].numpy())
        assert (np.abs(node[0] - ref[0].numpy()) / std[..., None]).max() <= 1e-6
    fn = function_of("EMD", [([2, 50, 4, 10], portable_body(4, 10, 2, 50)),
                             ([1, 300, 6, 10], portable_body(6, 10, 1, 300))])
    nodes = [helper.make_node("EMD", ["x1"], ["i1", "r1", "v1"], domain="ai.tactile",
                              n_imfs=4, n_sifts=10),
             helper.make_node("EMD", ["x2"], ["i2", "r2", "v2"], domain="ai.tactile",
                              n_imfs=6, n_sifts=10)]
    f32 = onnx.TensorProto.FLOAT
    graph = helper.make_graph(
        nodes, "two", [helper.make_tensor_value_info("x1", f32, ["b", 2, 50]),
                       helper.make_tensor_value_info("x2", f32, ["b", 1, 300])],
        [helper.make_tensor_value_info("i1", f32, ["b", 2, 4, 50]),
         helper.make_tensor_value_info("i2", f32, ["b", 1, 6, 300])])
    two = helper.make_model(graph, opset_imports=opset_imports(), functions=[fn])
    two.ir_version = 8
    onnx.checker.check_model(two, full_check=True)
    feed = {"x1": rng.standard_normal((3, 2, 50)).astype(np.float32),
            "x2": rng.standard_normal((3, 1, 300)).astype(np.float32)}
    both = _session(two).run(None, feed)
    for out, (name, k) in zip(both, (("x1", 4), ("x2", 6))):
        own = _session(build_emd_model(k, 10, *feed[name].shape[1:], torch.float64)).run(
            None, {"x_in": feed[name].astype(np.float64)})[0]
        np.testing.assert_array_equal(out, own.astype(np.float32))


@pytest.mark.parametrize("layout", ["large", "small"])
def test_onnxruntime_float32_parity(layout):
    """Over the 50- and 200-sample parity windows pooled (1900 windows), all in one call
    (the many-row layout) or in calls of fewer than LARGE_ROWS windows."""
    chunk = None if layout == "large" else LARGE_ROWS // 2
    ok_torch, ok_ref, unexplained, medians = [], [], [], []
    for n_time, per_kind in [(50, 300), (200, 80)]:
        x, refs = parity_set(n_time, per_kind)  # (W, N) float64, PyEMD's answers
        sess = _session(build_emd_model(4, 10, 1, n_time))
        x32 = x[:, None].astype(np.float32)
        step = chunk or len(x)
        parts = [sess.run(None, {"x_in": x32[i : i + step]}) for i in range(0, len(x), step)]
        outs = [np.concatenate(t) for t in zip(*parts)]
        imfs, residue = outs[0][:, 0].astype(float), outs[1][:, 0].astype(float)
        n_valid = outs[2][:, 0]
        # vs the torch module in float32, same calls
        t_imfs, t_res, t_nv = run_torch(x.astype(np.float32), torch.float32, chunk)
        std = np.where(x.std(1) > 0, x.std(1), 1.0)
        d = np.maximum(np.abs(imfs - t_imfs).max((1, 2)), np.abs(residue - t_res).max(1)) / std
        good_torch = (n_valid == t_nv) & (d <= TOL)
        # vs PyEMD in float64
        same, rel = compare(x, imfs, residue, n_valid, refs)
        good_ref = same & (rel <= TOL)
        outliers = np.nonzero(~(good_torch & good_ref))[0]
        unexplained += [(n_time, int(i)) for i in outliers if not near_tie_gap(x[i]) < NEAR_TIE]
        ok_torch.append(good_torch)
        ok_ref.append(good_ref)
        medians.append(np.median(rel[good_ref]))
    ok_torch, ok_ref = np.concatenate(ok_torch), np.concatenate(ok_ref)
    assert min(ok_torch.mean(), ok_ref.mean()) >= MIN_PASS, (ok_torch.mean(), ok_ref.mean())
    assert not unexplained, f"outliers without a near-tie (length, window): {unexplained}"
    # The typical window agrees far inside the tolerance (float32 rounding only).
    assert max(medians) < 1e-5


def test_export_rejects_bad_settings(tmp_path):
    with pytest.raises(ConfigError):
        export_emd_onnx(tmp_path / "x.onnx", n_imfs=0)
    with pytest.raises(ConfigError):
        export_emd_onnx(tmp_path / "x.onnx", n_time=2)
    with pytest.raises(ConfigError):
        build_emd_model(4, 10, 1, 50, dtype=torch.float16)


BATCHES = (1, 21, 22, 64, 65, 512)
"""Batch sizes around the layout switch (LARGE_ROWS = 64 rows: 21 / 22 windows of 3 channels,
64 / 65 of 1) and the evaluation's 512."""


def _random_walks(n_windows: int, n_channels: int, seed: int) -> np.ndarray:
    """(W, C, 50) coarse integer random walks (plateaus, like raw pressure counts), z-scored."""
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.integers(-5, 6, (n_windows, n_channels, 50)), -1).astype(np.float64)
    std = x.std(-1, keepdims=True)
    return ((x - x.mean(-1, keepdims=True)) / np.where(std > 0, std, 1.0)).astype(np.float32)


@pytest.mark.parametrize(("n_channels", "batches"), [(3, (21, 22, 512)), (1, (64, 65))])
def test_a_window_gets_the_same_bits_at_every_batch_size(n_channels, batches):
    """A window's decomposition must not depend on what else is in its batch: the runtime runs
    onnxruntime at batch 1, evaluation torch at 512. Tolerance 0: onnxruntime and torch at each
    batch size give the bits onnxruntime gives one window at a time (integer data makes
    near-tied samples, whose order a rounding difference flips, moving an extremum: the
    solvers' ~1e-6 differences became up to 1e-2)."""
    x = _random_walks(44 if n_channels == 3 else 130, n_channels, seed=2)
    sess = _session(build_emd_model(4, 10, n_channels, 50))
    emd = EMD(4, 10)
    torch.set_num_threads(1)
    one = [np.concatenate(o) for o in zip(*(sess.run(None, {"x_in": w[None]}) for w in x))]
    for w in range(0, len(x), len(x) // 3):  # torch one window at a time too (slow: a few)
        for got, want in zip(emd(torch.from_numpy(x[w : w + 1])), one):
            np.testing.assert_array_equal(got.numpy(), want[w : w + 1])
    for batch in batches:
        # every window in batches of `batch` (tiled to fill 512)
        xs = np.concatenate([x] * -(-batch // len(x)))[: max(batch, len(x))]
        idx = np.arange(len(xs)) % len(x)
        for name, run in (
            ("onnxruntime", lambda b: sess.run(None, {"x_in": b})),
            ("torch", lambda b: [t.numpy() for t in emd(torch.from_numpy(b))]),
        ):
            parts = [run(xs[i : i + batch]) for i in range(0, len(xs), batch)]
            for out, want in zip((np.concatenate(p) for p in zip(*parts)), one):
                diff = np.abs(out.astype(np.float64) - want[idx]).max()
                assert diff == 0, f"{name} at batch {batch}: max |d| {diff:.3g}"
