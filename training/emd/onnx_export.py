"""ONNX export of :class:`EMD`: the sifts run inside ONNX ``Loop`` nodes.

Exporter path (pinned): each small step (the parts of one sift, closing an IMF, the set-up
and the final reshapes) is traced with ``torch.onnx.export(..., dynamo=False)`` at opset
:data:`OPSET` with a dynamic row axis, constant-folded by ``onnxscript.optimizer``, and the
pieces are wired together here with two nested ``Loop`` nodes (IMFs outside, sifts inside)
and two more inside the sift that run zero or more times (the plateau rule only when there are
ties; PCR steps only while a system is still coupled). onnxruntime runs the ~200-node sift body
up to 40 times
instead of holding 40 unrolled copies: the file stays small and session creation fast. The
sift loop stops as soon as no row is active (a stopped row is left unchanged, so the skipped
sifts would change nothing). An ``If`` on the row count picks one of two such loop nests:
from :data:`spline.LARGE_ROWS` rows on, the sift lays out the end extrema and the boundary rule
for large tensors, as :func:`sift.prepare` chooses in torch; both solve the spline systems by
the same PCR steps, so a row's result does not depend on the batch. Each sift cuts the knots
to the width the batch needs (:func:`spline.knot_width`, bit for bit the same result). The
same torch functions run in eager mode, so the graph computes exactly what
:func:`decompose.decompose` computes.

Graph contract: input ``x_in`` (batch, channels, time) float32/float64 with a dynamic batch axis;
outputs ``imfs`` (batch, channels, n_imfs, time), ``residue`` (batch, channels, time) and
``n_valid`` (batch, channels) int64.
"""

from __future__ import annotations

import io
import logging
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import onnx
import onnxscript.optimizer
import torch
from onnx import TensorProto, helper, numpy_helper
from onnx.reference import ReferenceEvaluator
from torch import Tensor, nn

from tactile.errors import ConfigError

from .decompose import imf_update
from .extrema import has_tie, plateau_marks, signs, strict_marks
from .knots import end_base, n_slots, slot_base
from .module import EMDConfig
from .sift import finish, prepare_knots, prepare_system
from .spline import (
    LARGE_ROWS,
    more_steps,
    pcr_rows,
    pcr_step,
    pcr_steps,
    slot_rows,
)

OPSET = 18
"""ONNX opset of the exported graph (ScatterElements with reduction needs >= 16)."""

_DTYPES = {torch.float32: TensorProto.FLOAT, torch.float64: TensorProto.DOUBLE}


class _Fn(nn.Module):
    """Wrap a function so the tracer sees a module."""

    def __init__(self, fn: Callable[..., tuple[Tensor, ...]]) -> None:
        super().__init__()
        self.fn = fn

    def forward(self, *args: Tensor) -> tuple[Tensor, ...]:
        return self.fn(*args)


def export_traced(
    module: nn.Module,
    args: Sequence[Tensor],
    inputs: Sequence[str],
    outputs: Sequence[str],
    dynamic: dict[str, dict[int, str]],
) -> onnx.ModelProto:
    """``module`` traced to ONNX by the pinned exporter path (TorchScript, opset :data:`OPSET`).

    The one place the project calls ``torch.onnx.export``: the EMD pieces and the deployable
    graph (``tactile.export.graph``) are both traced here.
    """
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notice
        torch.onnx.export(
            module,
            tuple(args),
            buf,
            dynamo=False,
            opset_version=OPSET,
            input_names=list(inputs),
            output_names=list(outputs),
            dynamic_axes=dynamic,
            do_constant_folding=True,
        )
    return onnx.load_from_string(buf.getvalue())


def trace_graph(
    fn: Callable[..., tuple[Tensor, ...]],
    args: Sequence[Tensor],
    inputs: Sequence[str],
    outputs: Sequence[str],
    dynamic: dict[str, dict[int, str]],
) -> onnx.ModelProto:
    """Trace ``fn`` to a constant-folded ONNX model (the pinned exporter path)."""
    traced = export_traced(_Fn(fn), args, inputs, outputs, dynamic)
    folder = logging.getLogger("onnxscript.optimizer._constant_folding")
    folder.addFilter(_folded_if_shapes)
    try:
        model = onnxscript.optimizer.optimize(traced)
    finally:
        folder.removeFilter(_folded_if_shapes)
    return _rank_constants(_drop_update_slices(_fold_constants(model)))


def _folded_if_shapes(record: logging.LogRecord) -> bool:
    """Drop only the optimizer's "cannot merge shapes" warning, keep every other record.

    The exporter wraps a scatter with a reduction in ``If`` nodes for 0-d inputs. The optimizer
    folds them away (ours have rank 3), warning on the way that the 0-d branch's flattened
    shape does not merge with the result's: harmless, the branch is gone, but it would reach
    the log of everyone who exports a model.
    """
    return "Cannot merge shapes" not in record.getMessage()


def _drop_update_slices(model: onnx.ModelProto) -> onnx.ModelProto:
    """Remove the ``Shape``/``Slice`` pair the exporter puts on every ``scatter_add`` source.

    It trims the source to the index's shape; in this package they always have equal shapes
    (asserted by the eager code paths), so the pair is a no-op costing two kernels per call.
    """
    graph = model.graph
    producer = {o: node for node in graph.node for o in node.output}
    drop: set[int] = set()
    for node in graph.node:
        if node.op_type != "ScatterElements":
            continue
        sl = producer.get(node.input[2])
        if sl is None or sl.op_type != "Slice" or len(sl.input) < 3:
            continue
        shape = producer.get(sl.input[2])
        if shape is None or shape.op_type != "Shape" or shape.input[0] != node.input[1]:
            continue
        node.input[2] = sl.input[0]
        drop.update((id(sl), id(shape)))
    users = {v for node in graph.node if id(node) not in drop for v in node.input}
    kept = [n for n in graph.node if id(n) not in drop or any(o in users for o in n.output)]
    del graph.node[:]
    graph.node.extend(kept)
    _drop_unused_initializers(graph)
    return model


def _drop_unused_initializers(graph: onnx.GraphProto) -> None:
    """Remove the initializers no node (nor any subgraph of one) reads."""
    used = {v for n in graph.node for v in n.input}
    used |= {v for n in graph.node for v in _subgraph_inputs(n)}
    inits = [init for init in graph.initializer if init.name in used]
    del graph.initializer[:]
    graph.initializer.extend(inits)


def _fold_constants(model: onnx.ModelProto) -> onnx.ModelProto:
    """Evaluate every node whose inputs are all initializers, keeping only the result.

    The TorchScript exporter builds ``Pad``'s pads (and a few constants) from small chains of
    ``ConstantOfShape``/``Concat``/``Reshape``/``Transpose`` nodes that the optimizer leaves
    in place; each would cost a kernel launch per sift.
    """
    graph = model.graph
    known = {init.name: numpy_helper.to_array(init) for init in graph.initializer}
    kept = []
    for node in graph.node:
        has_graph = any(a.type == onnx.AttributeProto.GRAPH for a in node.attribute)
        if (
            not has_graph
            and node.op_type not in ("Shape", "Size")
            and node.input
            and all(v in known for v in node.input if v)
        ):
            inputs = [v for v in node.input if v]
            values = ReferenceEvaluator(_single_node(node, inputs, known)).run(
                None, {v: known[v] for v in inputs}
            )
            for out, val in zip(node.output, values):
                known[out] = np.asarray(val)
            continue
        kept.append(node)
    used = {v for node in kept for v in node.input} | {o.name for o in graph.output}
    used |= {v for node in kept for v in _subgraph_inputs(node)}
    del graph.node[:]
    graph.node.extend(kept)
    del graph.initializer[:]
    inits = [numpy_helper.from_array(known[v], v) for v in sorted(known) if v in used]
    graph.initializer.extend(inits)
    return model


_BROADCASTING = {
    "Add", "Sub", "Mul", "Div", "Pow", "Max", "Min", "Mod", "Equal", "Less", "LessOrEqual",
    "Greater", "GreaterOrEqual", "And", "Or", "Xor", "Where",
}


def _rank_constants(model: onnx.ModelProto) -> onnx.ModelProto:
    """Give every constant operand of a broadcasting node the rank of the node's output.

    The tracer writes scalars as 0-d tensors. onnxruntime's CPU kernels broadcast a 0-d
    operand against a tensor with size-1 axes (the (2, R, 2, 1)-shaped boundary quantities,
    ``j1`` of shape (2, R, 1)) one element at a time, about 10 ns an element, but a constant of
    shape (1, ..., 1) at full speed (about 0.1 ns): at 2,048 rows that is 40 us against 0.4 us
    per node. Leading size-1 axes change nothing in the arithmetic (numpy broadcasting).
    """
    graph = model.graph
    inferred = onnx.shape_inference.infer_shapes(model).graph
    rank = {
        v.name: len(v.type.tensor_type.shape.dim)
        for v in [*inferred.value_info, *inferred.output, *inferred.input]
        if v.type.tensor_type.HasField("shape")
    }
    known = {init.name: init for init in graph.initializer}
    added: dict[str, onnx.TensorProto] = {}
    for node in graph.node:
        if node.op_type not in _BROADCASTING or node.output[0] not in rank:
            continue
        r = rank[node.output[0]]
        for i, v in enumerate(node.input):
            init = known.get(v)
            if init is None or len(init.dims) >= r:
                continue
            new = f"{v}_rank{r}"
            if new not in added:
                arr = numpy_helper.to_array(init)
                shaped = arr.reshape((1,) * (r - arr.ndim) + arr.shape)
                added[new] = numpy_helper.from_array(shaped, new)
            node.input[i] = new
    graph.initializer.extend(added.values())
    _drop_unused_initializers(graph)
    return model


def _single_node(node: onnx.NodeProto, inputs: list[str], known: dict) -> onnx.ModelProto:
    ins = [
        helper.make_tensor_value_info(v, helper.np_dtype_to_tensor_dtype(known[v].dtype), None)
        for v in inputs
    ]
    outs = [helper.make_tensor_value_info(v, TensorProto.UNDEFINED, None) for v in node.output]
    g = helper.make_graph([node], "fold", ins, outs)
    return helper.make_model(g, opset_imports=[helper.make_opsetid("", OPSET)])


def _subgraph_inputs(node: onnx.NodeProto) -> set[str]:
    names: set[str] = set()
    for attr in node.attribute:
        if attr.type == onnx.AttributeProto.GRAPH:
            for inner in attr.g.node:
                names.update(inner.input)
                names |= _subgraph_inputs(inner)
    return names


def _inline(
    model: onnx.ModelProto, prefix: str, rename: dict[str, str]
) -> tuple[list[onnx.NodeProto], list[onnx.TensorProto]]:
    """Nodes and initializers of ``model`` with every internal name prefixed.

    ``rename`` maps the model's input and output names to names in the enclosing graph.
    """

    def name(v: str) -> str:
        return v if not v else rename.get(v, prefix + v)

    def rename_graph(graph: onnx.GraphProto) -> None:
        for value in [*graph.input, *graph.output, *graph.value_info]:
            value.name = name(value.name)
        for init in graph.initializer:
            init.name = name(init.name)
        for node in graph.node:
            node.name = prefix + node.name
            node.input[:] = [name(v) for v in node.input]
            node.output[:] = [name(v) for v in node.output]
            for attr in node.attribute:
                if attr.type == onnx.AttributeProto.GRAPH:
                    rename_graph(attr.g)

    nodes = []
    for node in model.graph.node:
        new = onnx.NodeProto()
        new.CopyFrom(node)
        nodes.append(new)
    holder = helper.make_graph(nodes, "holder", [], [])
    rename_graph(holder)
    nodes = list(holder.node)
    inits = []
    for init in model.graph.initializer:
        new = onnx.TensorProto()
        new.CopyFrom(init)
        new.name = name(init.name)
        inits.append(new)
    return nodes, inits


def _t(name: str, elem: int, shape: list) -> onnx.ValueInfoProto:
    return helper.make_tensor_value_info(name, elem, shape)


def _loop_body(
    name: str,
    prefix: str,
    nodes: list[onnx.NodeProto],
    carried: list[tuple[str, int, list]],
    scans: Sequence[tuple[str, int, list]] = (),
    cond_out: bool = False,
) -> onnx.GraphProto:
    """An ONNX ``Loop`` body around ``nodes``.

    Inputs: ``{prefix}_i`` (iteration), ``{prefix}_c`` (condition), then the ``carried``
    values (name, element type, shape); outputs: the condition (passed through unless
    ``cond_out``: then ``nodes`` compute ``{prefix}_c_out``), each carried value as
    ``{name}_out``, then the ``scans`` (one entry per iteration).
    """
    cond = f"{prefix}_c"
    keep = [] if cond_out else [helper.make_node("Identity", [cond], [f"{cond}_out"])]
    return helper.make_graph(
        [*nodes, *keep],
        name,
        [_t(f"{prefix}_i", TensorProto.INT64, []), _t(cond, TensorProto.BOOL, []),
         *[_t(*v) for v in carried]],
        [_t(f"{cond}_out", TensorProto.BOOL, []),
         *[_t(f"{n}_out", e, shape) for n, e, shape in carried], *[_t(*v) for v in scans]],
    )


def _head(h: Tensor) -> tuple[Tensor, Tensor]:
    sg = signs(h)
    return sg, has_tie(sg)


PCR_ALWAYS = 3
"""PCR steps every sift runs; the later steps run in a ``Loop``, as many as some system still
needs (:func:`spline.more_steps`, :func:`spline.decoupled_after`): the few-knot envelopes of
later IMFs skip them, with bit-identical results. With 50-sample windows nearly every sift
needs 3 steps or more (``docs/emd.md``)."""


def _sift_graph(
    h: Tensor, act: Tensor, elem: int, n_time: int, rows: dict[int, str], large: bool = False
) -> tuple[onnx.GraphProto, list[onnx.TensorProto]]:
    """The Loop body of one sift.

    Differences; the strict extremum rule, replaced by the plateau rule in a ``Loop`` that runs
    once when a difference is zero (none otherwise); knots and spline system with the first
    :data:`PCR_ALWAYS` solver steps; a ``Loop`` of the remaining steps the knot width needs,
    then the solution; envelopes and the update.
    With ``large``, the body for :data:`spline.LARGE_ROWS` rows or more: the many-row layouts
    of :func:`sift.prepare` and :func:`sift.finish` (the same arithmetic), and its subgraphs'
    names end in ``_large``.
    Loop-carried names: ``s_h``, ``s_a`` in, ``s_h_out``, ``s_a_out`` out.
    """
    suffix = "_large" if large else ""
    k = n_slots(n_time)
    steps = pcr_steps(k)
    always = min(PCR_ALWAYS, steps - 1)
    sg = signs(h)
    marks = strict_marks(sg)
    base = slot_base(h)
    # Examples at the full K slots (the traced constants must hold for every knot width).
    xy, j1, ks, n_ext, _ = prepare_knots(h, marks, base)
    slot = slot_rows(k, h.dtype)
    sys, hk, sl = prepare_system(xy, j1, n_time, slot)
    m = sys[2:3]
    sys = pcr_rows(sys)  # the example the PCR steps are traced on
    r1 = {1: "rows"}
    r2 = {2: "rows"}
    rw = {2: "rows", 3: "width"}  # knots and spline: (a, 2, R, W), W = spline.knot_width

    def pre_knots(h: Tensor, marks: Tensor, *made: Tensor) -> tuple[Tensor, ...]:
        # made: slot_base's four tensors, then (small body) the end samples for TopK.
        ends = None if large else made[4]
        *knots, width = prepare_knots(h, marks, made[:4], ends=ends, large=large)
        return (*knots, width, more_steps(width, always, steps))

    def pre_system(xy: Tensor, j1: Tensor, slot: Tensor) -> tuple[Tensor, ...]:
        sys, hk, sl = prepare_system(xy, j1, n_time, slot)
        sys = pcr_rows(sys)
        for step in range(always):
            sys = pcr_step(sys, 1 << step)
        return sys, hk, sl

    head = trace_graph(_head, [h], ["h"], ["sg", "tie"], {"h": rows, "sg": rows})
    strict = trace_graph(strict_marks, [sg], ["sg"], ["marks"], {"sg": rows, "marks": r1})
    plateau = trace_graph(plateau_marks, [sg], ["sg"], ["marks"], {"sg": rows, "marks": r1})
    # The large body finds the end extrema by running count: it takes no end samples.
    made = _MADE[:4] if large else _MADE
    made_examples = [*base] if large else [*base, end_base(h)]
    prep = trace_graph(
        pre_knots,
        [h, marks, *made_examples],
        ["h", "marks", *made],
        ["xy", "j1", "ks", "n_ext", "width", "pcr_n"],
        {"h": rows, "marks": r1, "low": r2, "dummies": r2, "slots": r1, "cands": r1, "ends": r1,
         "xy": r2, "j1": r1, "ks": r1, "n_ext": {0: "rows"}},
    )
    system = trace_graph(
        pre_system,
        [xy, j1, slot],
        ["xy", "j1", "slot"],
        ["sys", "hk", "sl"],
        {"xy": rw, "j1": r1, "slot": {1: "width"}, "sys": rw, "hk": rw, "sl": rw},
    )
    solved = trace_graph(lambda sys: sys[2:3], [sys], ["sys"], ["m"], {"sys": rw, "m": rw})
    # One PCR step traced at the first shift the loop runs; the loop gives its two Pads the
    # shifts of each later step (_pcr_loop_body).
    step_model = trace_graph(
        lambda sys: pcr_step(sys, 1 << always), [sys], ["sys"], ["out"], {"sys": rw, "out": rw}
    )
    tail = trace_graph(
        _finish_sift,
        [h, act, xy, m, j1, ks, n_ext, hk, sl],
        ["h", "act", "xy", "m", "j1", "ks", "n_ext", "hk", "sl"],
        ["h_out", "act_out", "go"],
        {"h": rows, "act": rows, "xy": rw, "m": rw, "j1": r1, "ks": r1,
         "n_ext": {0: "rows"}, "hk": rw, "sl": rw, "h_out": rows, "act_out": rows},
    )

    inits: list[onnx.TensorProto] = []

    def add(model: onnx.ModelProto, prefix: str, rename: dict[str, str]) -> list[onnx.NodeProto]:
        # Initializers live in the main graph: the two bodies' names must differ.
        nodes, more = _inline(model, ("large/" if large else "") + prefix, rename)
        inits.extend(more)
        return nodes

    nodes = add(head, "head/", {"h": "s_h", "sg": "s_sg", "tie": "s_tie"})
    # The extremum rule: the strict marks, replaced by the plateau rule's in a Loop that runs
    # once when some difference is zero and not at all otherwise (onnxruntime 1.32 runs a
    # Loop of no iteration for about a microsecond, an If for several).
    nodes += add(strict, "strict/", {"sg": "s_sg", "marks": "s_strict"})
    p_nodes = add(plateau, "plateau/", {"sg": "s_sg", "marks": "s_tie_marks_out"})
    nodes += [
        helper.make_node("Cast", ["s_tie"], ["s_tie_n"], to=TensorProto.INT64),
        helper.make_node(
            "Loop", ["s_tie_n", "", "s_strict"], ["s_marks"],
            body=_loop_body("plateau" + suffix, "s_tie", p_nodes,
                            [("s_tie_marks", elem, [2, "rows", n_time])]),
        ),
    ]
    # What depends only on the shape is made once, outside the loops.
    outer = {"h": "s_h", "marks": "s_marks", "xy": "s_xy_all"}
    outer.update({v: f"made_{v}" for v in made})
    outer.update({v: f"s_{v}" for v in ["j1", "ks", "n_ext", "width", "pcr_n"]})
    nodes += add(prep, "prep/", outer)
    # The knots and spline.slot_rows cut to the knot width (spline.knot_width).
    pfx = "large/" if large else ""
    inits += [helper.make_tensor(f"{pfx}cut_start", TensorProto.INT64, [1], [0]),
              helper.make_tensor(f"{pfx}cut_axis", TensorProto.INT64, [1], [3]),
              helper.make_tensor(f"{pfx}cut_axis1", TensorProto.INT64, [1], [1])]
    nodes += [
        helper.make_node("Slice", ["s_xy_all", f"{pfx}cut_start", "s_width", f"{pfx}cut_axis"],
                         ["s_xy"]),
        helper.make_node("Slice", ["made_slot_rows", f"{pfx}cut_start", "s_width",
                                   f"{pfx}cut_axis1"], ["s_slot_rows"]),
    ]
    outer = {"xy": "s_xy", "j1": "s_j1", "slot": "s_slot_rows", "sys": "s_sys"}
    outer.update({v: f"s_{v}" for v in ["hk", "sl"]})
    nodes += add(system, "system/", outer)
    # The remaining PCR steps, as many as the knot width needs (spline.more_steps), then the
    # solution: bit for bit what every step would give (spline.decoupled_after).
    body, body_inits = _pcr_loop_body(step_model, pfx, always, steps, elem, suffix)
    inits += body_inits
    nodes.append(helper.make_node("Loop", ["s_pcr_n", "", "s_sys"], ["s_sys_end"], body=body))
    nodes += add(solved, "solved/", {"sys": "s_sys_end", "m": "s_m"})
    nodes += add(
        tail,
        "sift/",
        {"h": "s_h", "act": "s_a", "m": "s_m", "h_out": "s_h_out", "act_out": "s_a_out",
         "go": "s_c_out", **{v: f"s_{v}" for v in ["xy", "j1", "ks", "n_ext", "hk", "sl"]}},
    )
    carried = [("s_h", elem, ["rows", n_time]), ("s_a", TensorProto.BOOL, ["rows", 1])]
    graph = _loop_body("sift" + suffix, "s", nodes, carried, cond_out=True)
    return graph, inits


def _pcr_loop_body(
    step_model: onnx.ModelProto, pfx: str, first: int, steps: int, elem: int, suffix: str
) -> tuple[onnx.GraphProto, list[onnx.TensorProto]]:
    """The body of the PCR ``Loop``: iteration ``i`` runs step ``first + i``.

    ``step_model`` is :func:`spline.pcr_step` traced at shift ``2^first``; its two ``Pad``
    nodes (row ``j - st`` and row ``j + st``, each with a zero row appended) get the pads of
    step ``first + i`` from a table instead of their traced constants, and nothing else
    changes, so every iteration runs the arithmetic of :func:`spline.pcr_step`.
    """
    known = {init.name: numpy_helper.to_array(init) for init in step_model.graph.initializer}
    pads = [n for n in step_model.graph.node if n.op_type == "Pad"]
    st = 1 << first
    traced = [list(known.get(n.input[1], [])) if len(n.input) > 1 else [] for n in pads]
    want = [[0, 0, 0, st, 1, 0, 0, -st], [0, 0, 0, -st, 1, 0, 0, st]]
    if traced != want:
        raise RuntimeError(f"unexpected traced PCR step: Pad pads {traced}, expected {want}")
    table = np.array([[[0, 0, 0, s, 1, 0, 0, -s], [0, 0, 0, -s, 1, 0, 0, s]]
                      for s in (1 << k for k in range(first, steps))], dtype=np.int64)
    prefix = f"{pfx}pcr/"
    nodes, inits = _inline(step_model, prefix, {"sys": "p_sys", "out": "p_sys_out"})
    inits.append(numpy_helper.from_array(table[:, 0], f"{prefix}pads_lo"))
    inits.append(numpy_helper.from_array(table[:, 1], f"{prefix}pads_hi"))
    gathers = [
        helper.make_node("Gather", [f"{prefix}pads_{side}", "p_i"], [f"{prefix}step_{side}"],
                         axis=0)
        for side in ("lo", "hi")
    ]
    for node, side in zip((n for n in nodes if n.op_type == "Pad"), ("lo", "hi")):
        node.input[1] = f"{prefix}step_{side}"
    _drop_unused_initializers_list(gathers + nodes, inits)
    shape = [4, 2, "rows", "width"]
    return _loop_body("pcr" + suffix, "p", gathers + nodes, [("p_sys", elem, shape)]), inits


def _drop_unused_initializers_list(
    nodes: list[onnx.NodeProto], inits: list[onnx.TensorProto]
) -> None:
    """Keep only the initializers ``nodes`` read (in place)."""
    used = {v for n in nodes for v in n.input}
    inits[:] = [i for i in inits if i.name in used]


def _finish_sift(*args: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`sift.finish`, and whether any row is still active (the sift loop's condition:
    a row that stopped stays unchanged, so the remaining sifts can be skipped exactly)."""
    h, active = finish(*args)
    return h, active, active.any()


_MADE = ["low", "dummies", "slots", "cands", "ends"]  # what _init makes for the sift bodies


def _init(x3: Tensor) -> tuple[Tensor, ...]:
    x = x3.reshape(-1, x3.shape[-1])  # (R, N)
    alive = x[:, :1] == x[:, :1]  # (R, 1) all true for finite input
    nv = torch.zeros_like(x[:, :1], dtype=torch.int64)
    return x, x * 0.0, alive, nv, *slot_base(x), end_base(x)


def _close(x: Tensor, acc: Tensor, h: Tensor, active: Tensor, n_valid: Tensor):
    imf, acc, alive = imf_update(x, acc, h, active)
    return imf, acc, alive, n_valid + active.long()


def _finish(x3: Tensor, imfs: Tensor, acc: Tensor, n_valid: Tensor):
    b, c, t = x3.shape
    imfs = imfs.transpose(0, 1).reshape(b, c, imfs.shape[0], t)  # (M, R, N) -> (B, C, M, N)
    return imfs, x3 - acc.reshape(b, c, t), n_valid.reshape(b, c)


def build_emd_model(
    n_imfs: int,
    n_sifts: int,
    n_channels: int,
    n_time: int,
    dtype: torch.dtype = torch.float32,
    large_rows: int = LARGE_ROWS,
) -> onnx.ModelProto:
    """The EMD graph for windows of ``n_channels`` x ``n_time`` (dynamic batch).

    From ``large_rows`` rows (batch x channels) on, the sift body lays its tensors out for many
    rows, as :func:`sift.prepare` does at its default; another value only serves to benchmark
    the two layouts (``bench/emd.py --layouts``). The results are the same bits either way.
    """
    EMDConfig(n_imfs=n_imfs, n_sifts=n_sifts)  # validates
    if n_time < 3:
        raise ConfigError(f"EMD export needs windows of at least 3 samples, got {n_time}")
    if n_channels < 1:
        raise ConfigError(f"EMD export needs at least 1 channel, got {n_channels}")
    if dtype not in _DTYPES:
        raise ConfigError(f"EMD export dtype must be float32 or float64, got {dtype}")
    elem = _DTYPES[dtype]
    r = 3 * n_channels  # example rows: any value > 1 keeps the row axis symbolic
    h = torch.randn(r, n_time, dtype=dtype)
    act = torch.ones(r, 1, dtype=torch.bool)
    nv = torch.zeros(r, 1, dtype=torch.int64)
    x3 = torch.randn(3, n_channels, n_time, dtype=dtype)
    rows = {0: "rows"}

    init = trace_graph(
        _init, [x3], ["x3"], ["x", "acc", "alive", "nv", *_MADE], {"x3": {0: "batch"}}
    )
    close = trace_graph(
        _close,
        [h, h, h, act, nv],
        ["x", "acc", "h", "act", "nv"],
        ["imf", "acc_out", "alive_out", "nv_out"],
        {k: rows for k in ["x", "acc", "h", "act", "nv", "imf", "acc_out", "alive_out", "nv_out"]},
    )
    imfs_ex = torch.zeros(n_imfs, r, n_time, dtype=dtype)
    finish = trace_graph(
        _finish,
        [x3, imfs_ex, h, nv],
        ["x3", "imfs", "acc", "nv"],
        ["imfs_out", "residue", "n_valid"],
        {
            "x3": {0: "batch"},
            "imfs": {1: "rows"},
            "acc": rows,
            "nv": rows,
            "imfs_out": {0: "batch"},
            "residue": {0: "batch"},
            "n_valid": {0: "batch"},
        },
    )

    inits: list[onnx.TensorProto] = []
    c_nodes, c_inits = _inline(
        close,
        "close/",
        {
            "x": "x",
            "acc": "i_acc",
            "h": "i_h",
            "act": "i_act",
            "nv": "i_nv",
            "imf": "i_imf",
            "acc_out": "i_acc_out",
            "alive_out": "i_alive_out",
            "nv_out": "i_nv_out",
        },
    )
    inits += c_inits
    loop_outs = ["acc", "alive", "nv", "imfs_scan"]
    loop_types = [elem, TensorProto.BOOL, TensorProto.INT64, elem]
    loop_shapes = [["rows", n_time], ["rows", 1], ["rows", 1], [n_imfs, "rows", n_time]]
    branches = {}
    for large in (False, True):
        # Inner loop: one sift per iteration.
        sift_graph, s_inits = _sift_graph(h, act, elem, n_time, rows, large)
        inits += s_inits
        sifts = [
            helper.make_node(
                "Loop", ["n_sifts", "i_go", "i_h0", "i_alive"], ["i_h", "i_act"], body=sift_graph
            )
        ]
        # Rows that stopped are left as they are, so no sift runs once no row is alive.
        imf_nodes = [
            helper.make_node("Sub", ["x", "i_acc"], ["i_h0"]),  # PyEMD restarts from S - sum(IMF)
            helper.make_node("Cast", ["i_alive"], ["i_alive_f"], to=TensorProto.FLOAT),
            helper.make_node("ReduceMax", ["i_alive_f"], ["i_alive_max"], keepdims=0),
            helper.make_node("Cast", ["i_alive_max"], ["i_go"], to=TensorProto.BOOL),
            *sifts,
            *c_nodes,  # make_graph copies them into each body
        ]
        suffix = "_large" if large else ""
        imf_graph = _loop_body(
            "imf" + suffix,
            "i",
            imf_nodes,
            [("i_acc", elem, ["rows", n_time]), ("i_alive", TensorProto.BOOL, ["rows", 1]),
             ("i_nv", TensorProto.INT64, ["rows", 1])],
            scans=[("i_imf", elem, ["rows", n_time])],
        )
        # Outer loop: one IMF per iteration, inside one branch of the layout choice.
        outs = [f"{v}{suffix or '_small'}" for v in loop_outs]
        branches[large] = helper.make_graph(
            [helper.make_node("Loop", ["n_imfs", "", "acc0", "alive0", "nv0"], outs,
                              body=imf_graph)],
            "layout" + (suffix or "_small"),
            [],
            [_t(o, e, sh) for o, e, sh in zip(outs, loop_types, loop_shapes)],
        )
    # The graph input is `x_in`; the loop bodies read its (R, N) view `x` from the outer scope.
    i_nodes, i_inits = _inline(
        init,
        "init/",
        {"x3": "x_in", "x": "x", "acc": "acc0", "alive": "alive0", "nv": "nv0",
         **{v: f"made_{v}" for v in _MADE}},
    )
    f_nodes, f_inits = _inline(
        finish,
        "finish/",
        {
            "x3": "x_in",
            "imfs": "imfs_scan",
            "acc": "acc",
            "nv": "nv",
            "imfs_out": "imfs",
            "residue": "residue",
            "n_valid": "n_valid",
        },
    )
    inits += i_inits + f_inits
    # spline.slot_rows, cut to the knot width in every sift (sift.prepare_system).
    rows_k = slot_rows(n_slots(n_time), dtype).numpy()
    inits.append(numpy_helper.from_array(rows_k, "made_slot_rows"))
    inits.append(helper.make_tensor("n_imfs", TensorProto.INT64, [], [n_imfs]))
    inits.append(helper.make_tensor("n_sifts", TensorProto.INT64, [], [n_sifts]))
    inits.append(helper.make_tensor("large_rows", TensorProto.INT64, [], [large_rows]))
    inits.append(helper.make_tensor("row_axis", TensorProto.INT64, [], [0]))
    main_nodes = [
        *i_nodes,
        # The layout follows the row count, as sift.prepare and sift.finish choose in torch.
        helper.make_node("Shape", ["x"], ["x_shape"]),
        helper.make_node("Gather", ["x_shape", "row_axis"], ["n_rows"], axis=0),
        helper.make_node("GreaterOrEqual", ["n_rows", "large_rows"], ["use_large"]),
        helper.make_node(
            "If", ["use_large"], loop_outs, then_branch=branches[True],
            else_branch=branches[False],
        ),
        *f_nodes,
    ]
    graph = helper.make_graph(
        main_nodes,
        "emd",
        [_t("x_in", elem, ["batch", n_channels, n_time])],
        [
            _t("imfs", elem, ["batch", n_channels, n_imfs, n_time]),
            _t("residue", elem, ["batch", n_channels, n_time]),
            _t("n_valid", TensorProto.INT64, ["batch", n_channels]),
        ],
        initializer=inits,
    )
    model = helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="tactile.training.emd"
    )
    model.ir_version = 8
    onnx.checker.check_model(model, full_check=True)
    return model


def export_emd_onnx(
    path: str | Path,
    n_imfs: int = 4,
    n_sifts: int = 10,
    n_channels: int = 8,
    n_time: int = 50,
    dtype: torch.dtype = torch.float32,
) -> onnx.ModelProto:
    """Write the EMD graph to ``path`` and return it. Input name ``x_in``."""
    model = build_emd_model(n_imfs, n_sifts, n_channels, n_time, dtype)
    onnx.save(model, str(path))
    return model


def subgraphs(graph: onnx.GraphProto) -> dict[str, onnx.GraphProto]:
    """Every subgraph (Loop bodies such as ``imf`` and ``sift``, If branches) by name, nested
    ones included."""
    out: dict[str, onnx.GraphProto] = {}
    for node in graph.node:
        for attr in node.attribute:
            if attr.type == onnx.AttributeProto.GRAPH:
                out[attr.g.name] = attr.g
                out.update(subgraphs(attr.g))
    return out


def subgraph_nodes(graph: onnx.GraphProto) -> dict[str, int]:
    """Node count of every subgraph by name (:func:`subgraphs`)."""
    return {name: len(g.node) for name, g in subgraphs(graph).items()}


def sift_path_nodes(model: onnx.ModelProto, n_time: int, large: bool = False) -> tuple[int, int]:
    """Nodes one sift runs on input without ties: (fewest, most); ``large``: in the body for
    :data:`spline.LARGE_ROWS` rows or more.

    Fewest: the loop body alone (the :data:`PCR_ALWAYS` steps, the solution taken after them);
    most: with every remaining PCR step, an iteration of the PCR loop each.
    """
    graphs = subgraph_nodes(model.graph)
    suffix = "_large" if large else ""
    steps = pcr_steps(n_slots(n_time))
    always = min(PCR_ALWAYS, steps - 1)
    base = graphs["sift" + suffix]
    return base, base + (steps - always) * graphs["pcr" + suffix]


def count_nodes(graph: onnx.GraphProto) -> int:
    """Nodes in ``graph`` and all its subgraphs (each Loop body counted once)."""
    total = 0
    for node in graph.node:
        total += 1
        for attr in node.attribute:
            if attr.type == onnx.AttributeProto.GRAPH:
                total += count_nodes(attr.g)
    return total
