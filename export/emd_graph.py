"""The EMD graph: :class:`tactile.training.emd.EMD` as ONNX, its sifts inside ``Loop`` nodes.

Exporter path (pinned): each small step (the parts of one sift, closing an IMF, the set-up
and the final reshapes) is traced by :func:`tactile.export.traced.trace_graph` at opset
:data:`tactile.contract.OPSET` with a dynamic row axis and constant-folded, and the pieces are
wired together here with two nested ``Loop`` nodes (IMFs outside, sifts inside) and two more
inside the sift that run zero or more times (the plateau rule only when there are ties; PCR
steps only while a system is still coupled). onnxruntime runs the ~200-node sift body up to 40
times instead of holding 40 unrolled copies: the file stays small and session creation fast.
The sift loop stops as soon as no row is active (a stopped row is left unchanged, so the
skipped sifts would change nothing). An ``If`` on the row count picks one of two such loop
nests: from :data:`spline.LARGE_ROWS` rows on, the sift lays out the end extrema and the
boundary rule for large tensors, as :func:`sift.prepare` chooses in torch; both solve the
spline systems by the same PCR steps, so a row's result does not depend on the batch. Each
sift cuts the knots to the width the batch needs (:func:`spline.knot_width`, bit for bit the
same result). The same torch functions run in eager mode, so the graph computes exactly what
:func:`decompose.decompose` computes (the modules named here are
``tactile.training.emd``'s).

Graph contract: input ``x_in`` (batch, channels, time) float32/float64 with a dynamic batch axis;
outputs ``imfs`` (batch, channels, n_imfs, time), ``residue`` (batch, channels, time) and
``n_valid`` (batch, channels) int64.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper, numpy_helper
from torch import Tensor

from tactile.contract import IR_VERSION, OPSET
from tactile.errors import ConfigError
from tactile.export.traced import (
    inline,
    keep_used_initializers,
    loop_body,
    tensor_info,
    trace_graph,
)
from tactile.training.emd.decompose import imf_update
from tactile.training.emd.extrema import has_tie, plateau_marks, signs, strict_marks
from tactile.training.emd.knots import end_base, n_slots, slot_base
from tactile.training.emd.module import EMDConfig
from tactile.training.emd.sift import finish, prepare_knots, prepare_system
from tactile.training.emd.spline import (
    LARGE_ROWS,
    more_steps,
    pcr_rows,
    pcr_step,
    pcr_steps,
    slot_rows,
)

_DTYPES = {torch.float32: TensorProto.FLOAT, torch.float64: TensorProto.DOUBLE}

PCR_ALWAYS = 3
"""PCR steps every sift runs; the later steps run in a ``Loop``, as many as some system still
needs (:func:`spline.more_steps`, :func:`spline.decoupled_after`): the few-knot envelopes of
later IMFs skip them, with bit-identical results. With 50-sample windows nearly every sift
needs 3 steps or more (``docs/emd.md``)."""


def _head(h: Tensor) -> tuple[Tensor, Tensor]:
    sg = signs(h)
    return sg, has_tie(sg)


def _sift_pieces(
    h: Tensor, act: Tensor, n_time: int, rows: dict[int, str], large: bool, always: int,
    steps: int,
) -> dict[str, onnx.ModelProto]:
    """The parts of one sift, each traced on its own: ``head`` (differences and whether any is
    zero), ``strict`` and ``plateau`` (the extremum rules), ``prep`` (knots, knot width, PCR
    steps still needed), ``system`` (the spline system and its first ``always`` PCR steps),
    ``step`` (one PCR step at shift ``2^always``), ``solved`` (the solution) and ``tail``
    (envelopes, the update, whether any row is still active). ``h`` (R, N) and ``act`` (R, 1)
    are example inputs; ``large`` picks the many-row layouts of :func:`sift.prepare`."""
    k = n_slots(n_time)
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

    out = {"head": trace_graph(_head, [h], ["h"], ["sg", "tie"], {"h": rows, "sg": rows})}
    out["strict"] = trace_graph(strict_marks, [sg], ["sg"], ["marks"], {"sg": rows, "marks": r1})
    out["plateau"] = trace_graph(plateau_marks, [sg], ["sg"], ["marks"],
                                 {"sg": rows, "marks": r1})
    # The large body finds the end extrema by running count: it takes no end samples.
    made = _MADE[:4] if large else _MADE
    made_examples = [*base] if large else [*base, end_base(h)]
    out["prep"] = trace_graph(
        pre_knots,
        [h, marks, *made_examples],
        ["h", "marks", *made],
        ["xy", "j1", "ks", "n_ext", "width", "pcr_n"],
        {"h": rows, "marks": r1, "low": r2, "dummies": r2, "slots": r1, "cands": r1, "ends": r1,
         "xy": r2, "j1": r1, "ks": r1, "n_ext": {0: "rows"}},
    )
    out["system"] = trace_graph(
        pre_system,
        [xy, j1, slot],
        ["xy", "j1", "slot"],
        ["sys", "hk", "sl"],
        {"xy": rw, "j1": r1, "slot": {1: "width"}, "sys": rw, "hk": rw, "sl": rw},
    )
    out["solved"] = trace_graph(lambda sys: sys[2:3], [sys], ["sys"], ["m"],
                                {"sys": rw, "m": rw})
    # One PCR step traced at the first shift the loop runs; the loop gives its two Pads the
    # shifts of each later step (_pcr_loop_body).
    out["step"] = trace_graph(
        lambda sys: pcr_step(sys, 1 << always), [sys], ["sys"], ["out"], {"sys": rw, "out": rw}
    )
    out["tail"] = trace_graph(
        _finish_sift,
        [h, act, xy, m, j1, ks, n_ext, hk, sl],
        ["h", "act", "xy", "m", "j1", "ks", "n_ext", "hk", "sl"],
        ["h_out", "act_out", "go"],
        {"h": rows, "act": rows, "xy": rw, "m": rw, "j1": r1, "ks": r1,
         "n_ext": {0: "rows"}, "hk": rw, "sl": rw, "h_out": rows, "act_out": rows},
    )
    return out


def _sift_graph(
    h: Tensor, act: Tensor, elem: int, n_time: int, rows: dict[int, str], large: bool = False
) -> tuple[onnx.GraphProto, list[onnx.TensorProto]]:
    """The Loop body of one sift.

    Differences; the strict extremum rule, replaced by the plateau rule in a ``Loop`` that runs
    once when a difference is zero (none otherwise); knots and spline system with the first
    :data:`PCR_ALWAYS` solver steps; a ``Loop`` of the remaining steps the knot width needs,
    then the solution; envelopes and the update (the parts: :func:`_sift_pieces`).
    With ``large``, the body for :data:`spline.LARGE_ROWS` rows or more: the many-row layouts
    of :func:`sift.prepare` and :func:`sift.finish` (the same arithmetic), and its subgraphs'
    names end in ``_large``.
    Loop-carried names: ``s_h``, ``s_a`` in, ``s_h_out``, ``s_a_out`` out.
    """
    suffix = "_large" if large else ""
    steps = pcr_steps(n_slots(n_time))
    always = min(PCR_ALWAYS, steps - 1)
    piece = _sift_pieces(h, act, n_time, rows, large, always, steps)
    inits: list[onnx.TensorProto] = []

    def add(model: onnx.ModelProto, prefix: str, rename: dict[str, str]) -> list[onnx.NodeProto]:
        # Initializers live in the main graph: the two bodies' names must differ.
        nodes, more = inline(model, ("large/" if large else "") + prefix, rename)
        inits.extend(more)
        return nodes

    nodes = add(piece["head"], "head/", {"h": "s_h", "sg": "s_sg", "tie": "s_tie"})
    # The extremum rule: the strict marks, replaced by the plateau rule's in a Loop that runs
    # once when some difference is zero and not at all otherwise (onnxruntime 1.32 runs a
    # Loop of no iteration for about a microsecond, an If for several).
    nodes += add(piece["strict"], "strict/", {"sg": "s_sg", "marks": "s_strict"})
    p_nodes = add(piece["plateau"], "plateau/", {"sg": "s_sg", "marks": "s_tie_marks_out"})
    nodes += [
        helper.make_node("Cast", ["s_tie"], ["s_tie_n"], to=TensorProto.INT64),
        helper.make_node(
            "Loop", ["s_tie_n", "", "s_strict"], ["s_marks"],
            body=loop_body("plateau" + suffix, "s_tie", p_nodes,
                           [("s_tie_marks", elem, [2, "rows", n_time])]),
        ),
    ]
    # What depends only on the shape is made once, outside the loops.
    outer = {"h": "s_h", "marks": "s_marks", "xy": "s_xy_all"}
    outer.update({v: f"made_{v}" for v in (_MADE[:4] if large else _MADE)})
    outer.update({v: f"s_{v}" for v in ["j1", "ks", "n_ext", "width", "pcr_n"]})
    nodes += add(piece["prep"], "prep/", outer)
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
    nodes += add(piece["system"], "system/", outer)
    # The remaining PCR steps, as many as the knot width needs (spline.more_steps), then the
    # solution: bit for bit what every step would give (spline.decoupled_after).
    body, body_inits = _pcr_loop_body(piece["step"], pfx, always, steps, elem, suffix)
    inits += body_inits
    nodes.append(helper.make_node("Loop", ["s_pcr_n", "", "s_sys"], ["s_sys_end"], body=body))
    nodes += add(piece["solved"], "solved/", {"sys": "s_sys_end", "m": "s_m"})
    nodes += add(
        piece["tail"],
        "sift/",
        {"h": "s_h", "act": "s_a", "m": "s_m", "h_out": "s_h_out", "act_out": "s_a_out",
         "go": "s_c_out", **{v: f"s_{v}" for v in ["xy", "j1", "ks", "n_ext", "hk", "sl"]}},
    )
    carried = [("s_h", elem, ["rows", n_time]), ("s_a", TensorProto.BOOL, ["rows", 1])]
    graph = loop_body("sift" + suffix, "s", nodes, carried, cond_out=True)
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
    nodes, inits = inline(step_model, prefix, {"sys": "p_sys", "out": "p_sys_out"})
    inits.append(numpy_helper.from_array(table[:, 0], f"{prefix}pads_lo"))
    inits.append(numpy_helper.from_array(table[:, 1], f"{prefix}pads_hi"))
    gathers = [
        helper.make_node("Gather", [f"{prefix}pads_{side}", "p_i"], [f"{prefix}step_{side}"],
                         axis=0)
        for side in ("lo", "hi")
    ]
    for node, side in zip((n for n in nodes if n.op_type == "Pad"), ("lo", "hi")):
        node.input[1] = f"{prefix}step_{side}"
    keep_used_initializers(gathers + nodes, inits)
    shape = [4, 2, "rows", "width"]
    return loop_body("pcr" + suffix, "p", gathers + nodes, [("p_sys", elem, shape)]), inits




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



_LOOP_OUTS = ["acc", "alive", "nv", "imfs_scan"]  # the IMF loop's outputs, in either layout


def _checked(n_imfs: int, n_sifts: int, n_channels: int, n_time: int, dtype: torch.dtype) -> int:
    """The ONNX element type of ``dtype``; :class:`ConfigError` for settings it cannot export."""
    EMDConfig(n_imfs=n_imfs, n_sifts=n_sifts)  # validates
    if n_time < 3:
        raise ConfigError(f"EMD export needs windows of at least 3 samples, got {n_time}")
    if n_channels < 1:
        raise ConfigError(f"EMD export needs at least 1 channel, got {n_channels}")
    if dtype not in _DTYPES:
        raise ConfigError(f"EMD export dtype must be float32 or float64, got {dtype}")
    return _DTYPES[dtype]


def _outer_parts(
    x3: Tensor, h: Tensor, act: Tensor, nv: Tensor, n_imfs: int, rows: dict[int, str]
) -> dict[str, tuple[list[onnx.NodeProto], list[onnx.TensorProto]]]:
    """What runs around the sifts, traced on the examples ``x3`` (B, C, N), ``h`` (R, N),
    ``act``, ``nv`` (R, 1) and inlined under the main graph's names: ``init`` (the (R, N) view
    ``x`` of ``x_in``, the loop's start values, what the sift bodies take from the shape),
    ``close`` (an IMF's update, inside the IMF loop) and ``finish`` (the outputs)."""
    init = trace_graph(
        _init, [x3], ["x3"], ["x", "acc", "alive", "nv", *_MADE], {"x3": {0: "batch"}}
    )
    close_io = ["x", "acc", "h", "act", "nv", "imf", "acc_out", "alive_out", "nv_out"]
    close = trace_graph(
        _close,
        [h, h, h, act, nv],
        close_io[:5],
        close_io[5:],
        {k: rows for k in close_io},
    )
    imfs_ex = torch.zeros(n_imfs, h.shape[0], h.shape[1], dtype=h.dtype)
    finish = trace_graph(
        _finish,
        [x3, imfs_ex, h, nv],
        ["x3", "imfs", "acc", "nv"],
        ["imfs_out", "residue", "n_valid"],
        {"x3": {0: "batch"}, "imfs": {1: "rows"}, "acc": rows, "nv": rows,
         **{k: {0: "batch"} for k in ["imfs_out", "residue", "n_valid"]}},
    )
    # The graph input is `x_in`; the loop bodies read its (R, N) view `x` from the outer scope.
    return {
        "close": inline(close, "close/", {"x": "x", **{v: f"i_{v}" for v in close_io[1:]}}),
        "init": inline(init, "init/", {"x3": "x_in", "x": "x", "acc": "acc0", "alive": "alive0",
                                       "nv": "nv0", **{v: f"made_{v}" for v in _MADE}}),
        "finish": inline(finish, "finish/", {"x3": "x_in", "imfs": "imfs_scan",
                                             "imfs_out": "imfs", **{v: v for v in [
                                                 "acc", "nv", "residue", "n_valid"]}}),
    }


def _layout_branch(
    large: bool, close: list[onnx.NodeProto], h: Tensor, act: Tensor, elem: int, n_imfs: int,
    n_time: int, rows: dict[int, str],
) -> tuple[onnx.GraphProto, list[onnx.TensorProto]]:
    """One branch of the layout ``If``: the IMF loop (one IMF per iteration: the sift loop,
    then the ``close`` nodes) whose sift body is laid out for many rows with ``large``."""
    # Inner loop: one sift per iteration.
    sift_graph, inits = _sift_graph(h, act, elem, n_time, rows, large)
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
        *close,  # make_graph copies them into each body
    ]
    suffix = "_large" if large else ""
    imf_graph = loop_body(
        "imf" + suffix,
        "i",
        imf_nodes,
        [("i_acc", elem, ["rows", n_time]), ("i_alive", TensorProto.BOOL, ["rows", 1]),
         ("i_nv", TensorProto.INT64, ["rows", 1])],
        scans=[("i_imf", elem, ["rows", n_time])],
    )
    # Outer loop: one IMF per iteration, inside one branch of the layout choice.
    loop_types = [elem, TensorProto.BOOL, TensorProto.INT64, elem]
    loop_shapes = [["rows", n_time], ["rows", 1], ["rows", 1], [n_imfs, "rows", n_time]]
    outs = [f"{v}{suffix or '_small'}" for v in _LOOP_OUTS]
    branch = helper.make_graph(
        [helper.make_node("Loop", ["n_imfs", "", "acc0", "alive0", "nv0"], outs,
                          body=imf_graph)],
        "layout" + (suffix or "_small"),
        [],
        [tensor_info(o, e, sh) for o, e, sh in zip(outs, loop_types, loop_shapes)],
    )
    return branch, inits


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
    elem = _checked(n_imfs, n_sifts, n_channels, n_time, dtype)
    r = 3 * n_channels  # example rows: any value > 1 keeps the row axis symbolic
    h = torch.randn(r, n_time, dtype=dtype)
    act = torch.ones(r, 1, dtype=torch.bool)
    nv = torch.zeros(r, 1, dtype=torch.int64)
    x3 = torch.randn(3, n_channels, n_time, dtype=dtype)
    rows = {0: "rows"}
    parts = _outer_parts(x3, h, act, nv, n_imfs, rows)
    c_nodes, inits = parts["close"]
    branches = {}
    for large in (False, True):
        branches[large], s_inits = _layout_branch(large, c_nodes, h, act, elem, n_imfs, n_time,
                                                  rows)
        inits += s_inits
    (i_nodes, i_inits), (f_nodes, f_inits) = parts["init"], parts["finish"]
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
            "If", ["use_large"], _LOOP_OUTS, then_branch=branches[True],
            else_branch=branches[False],
        ),
        *f_nodes,
    ]
    graph = helper.make_graph(
        main_nodes,
        "emd",
        [tensor_info("x_in", elem, ["batch", n_channels, n_time])],
        [
            tensor_info("imfs", elem, ["batch", n_channels, n_imfs, n_time]),
            tensor_info("residue", elem, ["batch", n_channels, n_time]),
            tensor_info("n_valid", TensorProto.INT64, ["batch", n_channels]),
        ],
        initializer=inits,
    )
    model = helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="tactile.training.emd"
    )
    model.ir_version = IR_VERSION
    onnx.checker.check_model(model, full_check=True)
    return model


def portable_body(n_imfs: int, n_sifts: int, n_channels: int, n_time: int) -> onnx.GraphProto:
    """The ``ai.tactile::EMD`` node's portable graph: float32 in and out, as the node, and
    :func:`build_emd_model`'s float64 graph inside (a ``Cast`` each way), so that it computes
    what the native kernel and training's feature pass compute (float64; in float32 a near-tie
    of two extrema may place a knot elsewhere and move a window's features). It takes 1.07-1.13x
    the float32 graph's time at batch 1 (``bench/emd.py``, ``docs/emd.md``)."""
    from tactile.export.compose import renamed

    inner = {"x_in": "x_in/f64", "imfs": "imfs/f64", "residue": "residue/f64"}
    g = renamed(build_emd_model(n_imfs, n_sifts, n_channels, n_time, torch.float64), "", inner)
    f32 = TensorProto.FLOAT
    nodes = [helper.make_node("Cast", ["x_in"], ["x_in/f64"], to=TensorProto.DOUBLE), *g.node,
             helper.make_node("Cast", ["imfs/f64"], ["imfs"], to=f32),
             helper.make_node("Cast", ["residue/f64"], ["residue"], to=f32)]
    return helper.make_graph(
        nodes, "emd", [tensor_info("x_in", f32, ["batch", n_channels, n_time])],
        [tensor_info("imfs", f32, ["batch", n_channels, n_imfs, n_time]),
         tensor_info("residue", f32, ["batch", n_channels, n_time]),
         tensor_info("n_valid", TensorProto.INT64, ["batch", n_channels])],
        initializer=list(g.initializer),
    )


def emd_node_model(n_imfs: int, n_sifts: int, n_channels: int, n_time: int) -> onnx.ModelProto:
    """The EMD as one ``ai.tactile::EMD`` node (float32) whose model-local function holds
    :func:`portable_body` (:mod:`tactile.export.custom_ops`): the native kernel where
    onnxruntime has the library registered, the portable graph anywhere else; both compute in
    float64. Same input and outputs as :func:`build_emd_model`'s at float32."""
    from tactile.export.custom_ops import custom_node, function_of, opset_imports

    body = portable_body(n_imfs, n_sifts, n_channels, n_time)
    node = custom_node("EMD", ["x_in"], ["imfs", "residue", "n_valid"], "emd",
                       n_imfs=n_imfs, n_sifts=n_sifts)
    fn = function_of("EMD", [([n_channels, n_time, n_imfs, n_sifts], body)])
    graph = helper.make_graph([node], "emd", list(body.input), list(body.output))
    model = helper.make_model(graph, opset_imports=opset_imports(), functions=[fn],
                              producer_name="tactile.training.emd")
    model.ir_version = IR_VERSION
    onnx.checker.check_model(model, full_check=True)
    return model


def export_emd_onnx(
    path: str | Path,
    n_imfs: int = 4,
    n_sifts: int = 10,
    n_channels: int = 8,
    n_time: int = 50,
    dtype: torch.dtype = torch.float32,
    native: bool = False,
) -> onnx.ModelProto:
    """Write the EMD graph to ``path`` and return it. Input name ``x_in``. With ``native``
    (float32 only) the file holds :func:`emd_node_model`: one custom node, the graph as its
    fallback."""
    if native and dtype != torch.float32:
        raise ConfigError("the native EMD node is float32 only")
    model = (emd_node_model(n_imfs, n_sifts, n_channels, n_time) if native
             else build_emd_model(n_imfs, n_sifts, n_channels, n_time, dtype))
    onnx.save(model, str(path))
    return model


__all__ = ["PCR_ALWAYS", "build_emd_model", "emd_node_model", "export_emd_onnx", "portable_body"]
