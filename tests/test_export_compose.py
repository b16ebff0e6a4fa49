"""Export composition for any preprocessing with the three-stage interface, and code parity.

A toy granular model (``tests/granular_toy.py``: two EMDs of different IMF counts, sifts and
lengths, a high-rate signal unpacked by a reshape, data images, one ``SparseCoder`` per
modality, an LSTM head) stands in for the training code's models, so that the composition and
the parity machinery are tested on their own. References: eager float32 PyTorch for the
probabilities (within 1e-4), scikit-learn's transform for the codes (the same non-zero atoms on
>= 99% of rows, max |difference| <= 1e-4 x the code's norm where they agree, every
disagreement a near-tie).
"""

from __future__ import annotations

import dataclasses

import granular_toy as toy
import numpy as np
import onnx
import pytest
import torch

from tactile.export.coder_graph import coder_graph
from tactile.export.codes import AGREEMENT, RTOL, code_parity
from tactile.export.graph import build_graph, split_forward
from tactile.export.parity import ATOL, compare
from tactile.export.session import session
from tactile.export.taps import find_coders
from tactile.export.windows import Probe
from tactile.training.feature_pass import feature_pass

torch.set_num_threads(1)

# Nodes of an exported coder other than Constant, per non-zero count (tests/test_sparse.py's
# budget for the coder's own graph (coder_graph), which folds its constants into initializers).
NODE_BUDGET = {1: 27, 2: 77, 3: 129}


@pytest.fixture(scope="module")
def coded():
    model = toy.build(coded=True)
    return model, build_graph(model)


@pytest.fixture(scope="module")
def plain():
    model = toy.build(coded=False, seed=1)
    return model, build_graph(model)


def _probe(n: int = 24, seed: int = 7) -> Probe:
    x = toy.windows(n, seed=seed)
    return Probe(x, None, [np.arange(n)], "toy windows", np.zeros(n, np.int64))


@pytest.mark.parametrize("which", ["coded", "plain"])
def test_split_forward_is_the_model_forward_bit_for_bit(which, request):
    model, _ = request.getfixturevalue(which)
    x = torch.from_numpy(toy.windows(6, seed=3))
    h, c = model.zero_state(6)
    with torch.no_grad():
        for a, b in zip(model(x, h, c), split_forward(model, x, h, c)):
            assert torch.equal(a, b)


def test_building_the_graph_leaves_the_model_in_evaluation_mode():
    """The composed export traces wrappers around the model's modules; the exporter restores
    the wrappers' mode afterwards, which must not put the model's batch norms and dropout
    back into training mode (a model used after build_graph gave other probabilities)."""
    model = toy.build(coded=False, seed=3)
    model.head.drop.p = 0.5  # in training mode it would zero half the LSTM's outputs
    x = torch.from_numpy(toy.windows(4, seed=12))
    with torch.no_grad():
        before = model(x, *model.zero_state(4))[0]
        build_graph(model)
        assert [n for n, m in model.named_modules() if m.training] == []
        assert torch.equal(model(x, *model.zero_state(4))[0], before)


@pytest.mark.parametrize("which", ["coded", "plain"])
def test_one_emd_graph_per_emd_and_a_valid_file(which, request):
    model, graph = request.getfixturevalue(which)
    onnx.checker.check_model(graph, full_check=True)
    onnx.shape_inference.infer_shapes(graph, check_type=True, strict_mode=True)
    # one ai.tactile EMD node per EMD module, each under its own prefix; the model-local
    # function holds one EMD graph per shape (its Loop nests sit in If nodes)
    prefixes = sorted({o.split("/")[0] for n in graph.graph.node if n.op_type == "EMD"
                       for o in n.output[1:]})
    assert prefixes == [f"emd{k}" for k in range(len(model.pre.emds))] == ["emd0", "emd1"]
    (fn,) = [f for f in graph.functions if f.name == "EMD"]
    assert sum(n.op_type == "If" for n in fn.node) == 1  # the pick between the two shapes
    sess = session(graph.SerializeToString())
    x = toy.windows(5, seed=11)
    h, c = (t.numpy() for t in model.zero_state(5))
    with torch.no_grad(), feature_pass(emd=True, codes=False):  # as compare()
        p_t = model(torch.from_numpy(x), *model.zero_state(5))[0].numpy()
    p_o = sess.run(None, {"x": x, "h": h, "c": c})[0]
    assert np.abs(p_o - p_t).max() <= ATOL
    p_1 = np.concatenate([sess.run(None, {"x": x[i : i + 1], "h": h[:, :1], "c": c[:, :1]})[0]
                          for i in range(5)])
    assert np.abs(p_1 - p_t).max() <= ATOL


def test_the_emd_graphs_have_their_own_sizes(coded):
    model, graph = coded
    shapes = {}
    for k, emd in enumerate(model.pre.emds):
        x = torch.zeros(2, model.cfg.window, len(toy.CHANNELS))
        sel = model.pre.emd_inputs(model.pre.normalise(x))[k]
        shapes[k] = (emd.n_imfs, emd.n_sifts, tuple(sel.shape[1:]))
    assert shapes == {0: (3, 4, (1, 80)), 1: (2, 3, (1, 20))}
    inferred = onnx.shape_inference.infer_shapes(graph)
    dims = {v.name: [d.dim_value or d.dim_param for d in v.type.tensor_type.shape.dim]
            for v in inferred.graph.value_info}
    assert dims["imfs0"][1:] == [1, 3, 80] and dims["imfs1"][1:] == [1, 2, 20]


def test_coders_trace_into_the_graph_as_their_own_nodes(coded):
    """Inside the post part each coder is the node sequence of its own coder_graph() (same op
    types in the same order; the traced part keeps its Constant nodes, which coder_graph folds),
    with a dynamic row axis (batch x steps) and within the coder's node budget."""
    model, graph = coded
    taps = find_coders(model, graph)
    assert [t.path for t in taps] == ["pre.coders.0", "pre.coders.1", "pre.coders.2"]
    for t in taps:
        ops = [n.op_type for n in t.nodes if n.op_type != "Constant"]
        own = [n.op_type for n in coder_graph(t.coder).graph.node if n.op_type != "Constant"]
        assert ops == own, t.path
        assert len(ops) <= NODE_BUDGET[t.coder.n_nonzero], (t.path, len(ops))
        assert "NonZero" not in ops and "Loop" not in ops and "If" not in ops


def test_coders_without_emd_are_found_in_a_single_trace():
    mods = tuple(dataclasses.replace(m, imfs=0) for m in toy.MODS)
    orig = toy.MODS
    toy.MODS = mods
    try:
        model = toy.build(coded=True, seed=2)
    finally:
        toy.MODS = orig
    graph = build_graph(model)
    assert not [n for n in graph.graph.node if n.op_type == "Loop"]
    report = code_parity(model, graph, toy.windows(20, seed=4))
    assert [r["coder"] for r in report] == ["pre.coders.0", "pre.coders.1", "pre.coders.2"]
    assert all(r["passed"] and r["rows"] == 20 * model.pre.s for r in report), report


def test_code_parity_against_sklearn(coded):
    model, graph = coded
    report = code_parity(model, graph, toy.windows(100, seed=5))
    for r in report:
        assert r["rows"] == 100 * model.pre.s
        assert r["same_atoms"] / r["rows"] >= AGREEMENT and r["max_rel_diff"] <= RTOL, r
        assert r["passed"] and r["explained"]["unexplained"] == 0, r


def test_parity_reports_and_requires_the_codes(coded):
    model, graph = coded
    p = compare(model, graph.SerializeToString(), _probe(), {"config": {"state": "window"}})
    assert p.passed and p.max_abs_prob_diff <= ATOL
    assert [r["coder"] for r in p.codes] == ["pre.coders.0", "pre.coders.1", "pre.coders.2"]
    assert p.to_dict()["codes"][0]["rows"] == 24 * model.pre.s
    assert "codes pre.coders.0" in p.table()  # the toy has no layout: named by module path
    assert p.reference == "torch float32 eager, ToyModel.forward, its EMDs in float64"


def test_a_file_with_a_float32_emd_function_is_checked_as_it_was_exported(plain, monkeypatch):
    """A file exported before the portable EMD computed in float64: its portable path is
    compared with PyTorch's float32 EMDs (the reference it passed at export), the kernels'
    with the float64 EMD they compute; a float64 reference would blame the file for
    float32's near-ties. Two EMDs of different shapes: the function picks its body by an If."""
    import tactile.export.graph as graph_module
    from tactile.export.emd_graph import build_emd_model

    model, _ = plain
    monkeypatch.setattr(graph_module, "portable_body", lambda m, s, c, t: build_emd_model(
        m, s, c, t, torch.float32).graph)
    old = build_graph(model).SerializeToString()
    ck = {"config": {"state": "window"}}
    p = compare(model, old, _probe(), ck)
    assert p.passed and p.max_abs_prob_diff <= ATOL
    assert p.reference == "torch float32 eager, ToyModel.forward, its EMDs in float32"
    monkeypatch.undo()
    p = compare(model, plain[1].SerializeToString(), _probe(), ck)  # today's file
    assert p.passed and p.reference == "torch float32 eager, ToyModel.forward, its EMDs in float64"


@pytest.mark.parametrize("tamper, what", [
    (lambda c: setattr(c, "n_nonzero", c.n_nonzero + 1), "agreement"),  # sklearn takes more
    (lambda c: c.dictionary.mul_(1.01), "max_rel_diff"),  # sklearn's codes 1 % smaller
])
def test_code_parity_fails_when_the_graph_codes_otherwise(coded, tamper, what):
    """The graph keeps its coder; the reference's dictionary or non-zeros change."""
    model, graph = coded
    changed = toy.build(coded=True)
    tamper(changed.pre.coders[0])
    report = code_parity(changed, graph, toy.windows(40, seed=6))
    assert not report[0]["passed"]
    if what == "agreement":  # every row has one atom fewer than scikit-learn's: no excuse
        assert report[0]["agreement"] < AGREEMENT
        assert report[0]["explained"]["unexplained"] == report[0]["rows"]
    else:  # 1 % off on every row, and the graph is not closer to float64 than scikit-learn
        assert report[0]["max_rel_diff"] > RTOL
        assert report[0]["rows_over_rtol_unexcused"] == report[0]["rows"]
    p = compare(changed, graph.SerializeToString(), _probe(), {"config": {"state": "window"}})
    assert not p.passed and "FAIL" in p.table()


def test_a_model_without_coders_has_no_code_parity(plain):
    model, graph = plain
    assert code_parity(model, graph, toy.windows(4)) == []
    p = compare(model, graph.SerializeToString(), _probe(8), {"config": {"state": "window"}})
    assert p.passed and p.codes is None
