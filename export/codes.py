"""Code parity: the sparse codes the exported graph computes, against scikit-learn's.

A model whose preprocessing holds :class:`~tactile.training.sparse.SparseCoder` modules (the
``sf_rnn`` and ``sparse_linear`` models: one coder per modality) has each coder traced into the
graph's ``post`` part as a sub-graph: the nodes whose scope is the coder's module (the
exporter names a node ``.../<scope>/<op>``, the scope being the coder's qualified name in the
model, or its tail). Its one input from outside the scope is the images ``(rows, features)``
(rows = windows x steps) and its one output used outside is the codes ``(rows, atoms)``.

To observe them, the file's own graph is copied with those two values added as outputs (the
nodes are the file's, unchanged) and run by onnxruntime on the parity windows. scikit-learn's
transform with the coder's dictionary (``sklearn.decomposition.SparseCoder(D,
transform_algorithm='omp', transform_n_nonzero_coefs=n)``, as ``MiniBatchDictionaryLearning``
transforms) codes the same images, and :func:`tactile.training.sparse_check.compare` measures:
the same non-zero atoms on at least :data:`AGREEMENT` of the rows, max |difference| at most
:data:`RTOL` x the code's norm where they agree, and every disagreement a near-tie (the float64
correlations of scikit-learn's pick and of the graph's differ by less than :data:`TIE` of the
largest).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import onnx
from onnx import TensorProto, helper
from torch import nn

from tactile.errors import ModelContractError
from tactile.training.sparse import SparseCoder

AGREEMENT = 0.99
"""Least share of rows whose non-zero atoms equal scikit-learn's."""
RTOL = 1e-4
"""Largest max |code - scikit-learn's| / ||scikit-learn's code|| where the atoms agree."""
TIE = 1e-4
"""A disagreement is excused when scikit-learn's pick and the graph's are this close (float64
residual correlations, relative to the largest): float32 rounding may decide it either way."""
MAX_ROWS = 8192
"""At most this many rows (a seeded sample) per coder go to scikit-learn."""


class CoderNotFound(ModelContractError):
    """A coder of the model could not be located in the graph."""


@dataclass(frozen=True)
class CoderTap:
    """Where one coder sits in the graph: its module path in the model, the value it reads
    (images, rows x features) and the value it writes (codes, rows x atoms), its node count."""

    path: str
    coder: SparseCoder
    x: str
    codes: str
    nodes: tuple[onnx.NodeProto, ...]


def coders(model: nn.Module) -> list[tuple[str, SparseCoder]]:
    """The model's coders with their qualified names, in module order."""
    return [(p, m) for p, m in model.named_modules() if isinstance(m, SparseCoder)]


def _scope(node: onnx.NodeProto) -> str:
    """The last scope segment of a traced node's name (``/pre/coders.0/MatMul`` ->
    ``coders.0``; composed graphs prefix ``post/``)."""
    parts = node.name.split("/")
    return parts[-2] if len(parts) >= 3 else ""


def find_coders(model: nn.Module, graph: onnx.ModelProto) -> list[CoderTap]:
    """Locate every coder of ``model`` in ``graph``: :class:`CoderNotFound` unless each has
    exactly one outside input and one output used outside its scope."""
    g = graph.graph
    consts = {i.name for i in g.initializer}
    consts |= {o for n in g.node if n.op_type == "Constant" for o in n.output}
    found = coders(model)
    taps = []
    for path, coder in found:
        comps = path.split(".")
        tails = {".".join(comps[i:]) for i in range(len(comps) - 1)} or {path}
        nodes = [n for n in g.node if _scope(n) in tails]
        if not nodes:
            raise CoderNotFound(f"coder {path!r}: no node of its scope in the graph")
        inside = {id(n) for n in nodes}
        made = {o for n in nodes for o in n.output}
        ins = {v for n in nodes for v in n.input if v and v not in made and v not in consts}
        used = {v for n in g.node if id(n) not in inside for v in n.input}
        used |= {o.name for o in g.output}
        outs = [v for v in dict.fromkeys(o for n in nodes for o in n.output) if v in used]
        if len(ins) != 1 or len(outs) != 1:
            raise CoderNotFound(f"coder {path!r}: its sub-graph reads {sorted(ins)} and "
                                f"writes {outs}; expected one input and one output")
        taps.append(CoderTap(path, coder, ins.pop(), outs[0], tuple(nodes)))
    names = [t.x for t in taps] + [t.codes for t in taps]
    if len(set(names)) != len(names):
        raise CoderNotFound("two coders share a scope in the graph (name the modules apart)")
    return taps


def tapped(graph: onnx.ModelProto, taps: list[CoderTap]) -> onnx.ModelProto:
    """A copy of ``graph`` that also outputs each coder's images and codes (same nodes)."""
    out = onnx.ModelProto()
    out.CopyFrom(graph)
    del out.metadata_props[:]
    for t in taps:
        out.graph.output.extend([helper.make_tensor_value_info(t.x, TensorProto.FLOAT, None),
                                 helper.make_tensor_value_info(t.codes, TensorProto.FLOAT, None)])
    return out


def sklearn_codes(dictionary: np.ndarray, n_nonzero: int, x: np.ndarray) -> np.ndarray:
    """scikit-learn's transform of ``x`` (rows, features) float32 with ``dictionary``."""
    from sklearn.decomposition import SparseCoder as SkSparseCoder

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "Orthogonal matching pursuit ended prematurely"
        return SkSparseCoder(dictionary, transform_algorithm="omp",
                             transform_n_nonzero_coefs=n_nonzero).transform(x)


def code_parity(model: nn.Module, graph: onnx.ModelProto, windows: np.ndarray,
                max_rows: int = MAX_ROWS, seed: int = 0) -> list[dict]:
    """Per coder of ``model``: the graph's codes of ``windows`` (N, T, C) float32 (zero state)
    against scikit-learn's on the same images. One dict per coder: ``coder`` (module path),
    ``rows`` compared, ``atoms``, ``features``, ``nonzero``, ``same_atoms`` (rows),
    ``agreement``, ``max_rel_diff`` (where the atoms agree), ``disagreements``,
    ``worst_tie_gap`` (the largest gap of a disagreement, or None), ``passed``."""
    from tactile.export.parity import session
    from tactile.training.sparse_check import compare

    taps = find_coders(model, graph)
    if not taps:
        return []
    sess = session(tapped(graph, taps).SerializeToString())
    layers, hidden = model.state_shape
    names = [v for t in taps for v in (t.x, t.codes)]
    got: dict[str, list[np.ndarray]] = {v: [] for v in names}
    for i in range(0, len(windows), 256):
        xb = np.ascontiguousarray(windows[i : i + 256], np.float32)
        h = np.zeros((layers, len(xb), hidden), np.float32)
        outs = sess.run(names, {"x": xb, "h": h, "c": h})
        for v, o in zip(names, outs):
            got[v].append(o)
    rng = np.random.default_rng(seed)
    report = []
    for t in taps:
        x, codes = np.concatenate(got[t.x]), np.concatenate(got[t.codes])
        d = t.coder.dictionary.numpy()
        if x.ndim != 2 or x.shape[1] != d.shape[1] or codes.shape != (len(x), d.shape[0]):
            raise CoderNotFound(f"coder {t.path!r}: the graph's values {t.x!r} {x.shape} and "
                                f"{t.codes!r} {codes.shape} are not (rows, {d.shape[1]}) and "
                                f"(rows, {d.shape[0]})")
        if len(x) > max_rows:
            keep = np.sort(rng.choice(len(x), max_rows, replace=False))
            x, codes = x[keep], codes[keep]
        n = t.coder.n_nonzero
        stats = compare(sklearn_codes(d, n, x), codes, d, x, n)
        gaps = stats["gaps"]
        passed = (stats["agree"] >= AGREEMENT and stats["max_rel"] <= RTOL
                  and all(0 <= g < TIE for g in gaps))
        report.append({
            "coder": t.path, "rows": stats["windows"], "atoms": int(d.shape[0]),
            "features": int(d.shape[1]), "nonzero": n, "same_atoms": stats["same"],
            "agreement": round(stats["agree"], 6), "max_rel_diff": float(f"{stats['max_rel']:.3g}"),
            "disagreements": len(gaps),
            "worst_tie_gap": float(f"{max(gaps):.3g}") if gaps else None, "passed": passed,
        })
    return report


def table_rows(report: list[dict]) -> list[tuple[str, str]]:
    """Lines for the parity table: one per coder."""
    rows = []
    for r in report:
        tie = "" if not r["disagreements"] else (
            f", {r['disagreements']} near-ties (largest gap {r['worst_tie_gap']:.2g})")
        rows.append((f"codes {r['coder']}",
                     f"{r['same_atoms']}/{r['rows']} rows same atoms ({r['agreement']:.4f}), "
                     f"max |dc|/|c| {r['max_rel_diff']:.2g} (limit {RTOL:g}){tie} vs "
                     f"scikit-learn; {'PASS' if r['passed'] else 'FAIL'}"))
    return rows
