"""Parity: the ONNX graph in onnxruntime against the PyTorch model, on the same windows.

The reference is the model's ``forward`` (``TextureModel``, ``GranularModel``) in eager float32
torch, its EMDs in float64 as training's feature pass computed them (the model as trained and
evaluated; the file's EMD nodes compute in float64 on both paths), never onnxruntime itself,
run in batches of :data:`EVAL_BATCH` windows as ``tactile-eval`` runs it. onnxruntime runs
the same batches, and every window alone (batch 1, as ``tactile-run`` runs it): both must
match. Criterion
(``strict``, float32 files): every probability within :data:`ATOL` and identical labels, except
windows whose PyTorch top-two margin is below :data:`MARGIN` (a tie a rounding may break either
way). Window mode runs every window from a zero state; carry mode feeds each output state back,
window after window, along runs of at least :data:`MIN_CARRY` consecutive windows. An int8 file
(``int8`` criterion) passes when at least :data:`INT8_AGREEMENT` of its labels equal PyTorch's.
A model with sparse coders also has its graph's codes checked against scikit-learn's
(:mod:`tactile.export.codes`), and a window of it whose probabilities differ by more than
:data:`ATOL` is excused when the coders' float32 rounding explains it
(:mod:`tactile.export.ties`): near-tie atom flips between the graph's coders and PyTorch's, or
codes on the same atoms apart by no more than float32's accuracy for them, and PyTorch given
the graph's codes giving the graph's probabilities; on at most
:data:`~tactile.export.ties.MAX_EXCUSED` of the windows, both kinds together. The other
windows are held to :data:`ATOL`.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import asdict, dataclass

import numpy as np
import onnx
import onnxruntime as ort
import torch
from torch import nn

from tactile.contract import CUSTOM_DOMAIN
from tactile.errors import ModelContractError
from tactile.export.codes import (
    AGREEMENT,
    RESOLUTION_FACTOR,
    RTOL,
    TIE,
    code_parity,
    table_rows,
)
from tactile.export.session import session
from tactile.export.taps import coders
from tactile.export.ties import FLOAT32, MAX_EXCUSED, NEAR_TIE, Examined, Explainer
from tactile.export.windows import CARRY_STEPS, Probe, random_windows, simulated

ATOL = 1e-4
"""Largest allowed |p_onnx - p_torch| of any probability."""
MARGIN = 1e-4
"""Windows whose PyTorch top-two margin is below this may change label."""
MIN_CARRY = 20
"""Carried-state parity covers at least this many consecutive windows."""
INT8_AGREEMENT = 0.9
"""Least fraction of int8 labels equal to PyTorch's for an int8 export to pass."""
EVAL_BATCH = 512
"""Windows per PyTorch batch: what ``tactile-eval`` and training's test figures use."""


class ParityError(ModelContractError):
    """The ONNX graph does not compute what the PyTorch model computes (within tolerance)."""


@dataclass
class Parity:
    """The figures of one comparison (what the metadata's ``parity`` key holds)."""

    passed: bool
    criterion: str
    source: str
    windows: int
    max_abs_prob_diff: float
    max_abs_state_diff: float
    max_abs_prob_diff_batch1: float
    label_agreement: float
    labels_differ: int
    labels_differ_excused: int
    carry_runs: int
    carry_steps: int
    longest_carry_run: int
    atol: float = ATOL
    margin: float = MARGIN
    accuracy_torch: float | None = None
    accuracy_onnx: float | None = None
    reference: str = "torch float32 eager, TextureModel.forward"
    codes: list[dict] | None = None  # per coder: the graph's codes vs scikit-learn's
    # a model with coders: windows above atol excused (export/ties.py) by near-tie atom flips
    windows_excused: int = 0
    max_abs_prob_diff_excused: float | None = None
    # ... and by float32 code accuracy (the same atoms, codes apart within float32's accuracy)
    windows_excused_float32: int = 0
    max_abs_prob_diff_excused_float32: float | None = None
    max_excused: float | None = None  # the largest share of windows both kinds may excuse
    tie: float | None = None
    flips: dict | None = None  # Examined.to_dict(): what the windows above atol showed

    def to_dict(self) -> dict:
        return {k: (round(v, 9) if isinstance(v, float) else v) for k, v in asdict(self).items()}

    def table(self) -> str:
        acc = "-" if self.accuracy_onnx is None else (
            f"{self.accuracy_torch:.4f} torch, {self.accuracy_onnx:.4f} onnx")
        rows = [
            ("windows checked", f"{self.windows} ({self.source})"),
            ("carried state", f"{self.carry_runs} runs, {self.carry_steps} steps, longest "
             f"{self.longest_carry_run}" if self.carry_runs else "no (window mode)"),
            ("max |dp|", f"{self.max_abs_prob_diff:.3g} (limit {self.atol:g}"
             f"{'' if self.flips is None else ', windows not excused'})"
             if self.criterion == "strict" else f"{self.max_abs_prob_diff:.3g}"),
            ("  of which", f"{self.max_abs_prob_diff_batch1:.3g} onnx at batch 1 vs torch in "
             f"batches of up to {EVAL_BATCH}"),
            *self._flip_rows(),
            ("max |d state|", f"{self.max_abs_state_diff:.3g}"),
            ("label agreement", f"{self.label_agreement:.4f} ({self.labels_differ} differ, "
                                f"{self.labels_differ_excused} within margin {self.margin:g})"),
            ("accuracy", acc),
            ("criterion", self.criterion if self.criterion == "strict"
             else f"int8: agreement >= {INT8_AGREEMENT}"),
            *table_rows(self.codes or []),
            ("result", "PASS" if self.passed else "FAIL"),
        ]
        return "\n".join(f"{k:<16} {v}" for k, v in rows)

    def failures(self) -> list[str]:
        """What failed, in a few words each (empty when it passed)."""
        if self.passed:
            return []
        if self.criterion != "strict":
            return [f"label agreement {self.label_agreement:.4f} (at least {INT8_AGREEMENT})"]
        out = []
        if self.max_abs_prob_diff > self.atol:
            not_excused = "" if self.flips is None else " on windows not excused"
            out.append(f"max |dp| {self.max_abs_prob_diff:.3g} (limit {self.atol:g})"
                       f"{not_excused}")
        if self.labels_differ > self.labels_differ_excused:
            out.append(f"{self.labels_differ - self.labels_differ_excused} of {self.windows} "
                       f"labels differ (agreement {self.label_agreement:.4f})")
        if self.carry_runs and self.longest_carry_run < MIN_CARRY:
            out.append(f"longest carried run {self.longest_carry_run} (at least {MIN_CARRY})")
        excused = self.windows_excused + self.windows_excused_float32
        if self.max_excused is not None and excused > self.max_excused * self.windows:
            out.append(f"{excused} of {self.windows} windows excused ({self.windows_excused} "
                       f"near-tie flips, {self.windows_excused_float32} float32 code accuracy; "
                       f"at most {100 * self.max_excused:g}%)")
        for r in self.codes or []:
            if not r["passed"]:
                why = [f"{r['same_atoms']}/{r['rows']} rows the same atoms as scikit-learn"
                       + (f" (at least {AGREEMENT:.0%})" if r["agreement"] < AGREEMENT else "")]
                if r["explained"]["unexplained"]:
                    why.append(f"{r['explained']['unexplained']} others unexplained")
                if r["rows_over_rtol_unexcused"]:
                    why.append(f"{r['rows_over_rtol_unexcused']} above {RTOL:g} unexplained")
                out.append(f"codes {r['name']}: {', '.join(why)}")
        return out or ["see the table"]

    def _flip_rows(self) -> list[tuple[str, str]]:
        if self.flips is None:
            return []
        f = self.flips
        if not f["windows_examined"]:
            return [("excused", "none (no window above the limit)")]

        def worst(dp):
            return "" if dp is None else f", max |dp| {dp:.3g}"

        odd = "".join(f", {f[k]} {what}" for k, what in (
            ("rows_image_off", "code rows with other images than PyTorch's"),
            ("not_reproduced", "not reproduced by the tapped copy"),
            ("not_by_codes", "not reproduced by PyTorch given the graph's codes")) if f.get(k))
        beyond = (f" ({f['rows_beyond_float32']} rows beyond it)"
                  if f["rows_beyond_float32"] else "")
        cap = (f"{self.windows_excused + self.windows_excused_float32} of {self.windows} "
               f"windows excused (at most {100 * self.max_excused:g}%): "
               f"{f['windows_examined']} above the limit{odd}")
        return [
            ("excused", cap),
            ("  near-tie flips", f"{_windows(self.windows_excused)}"
             f"{worst(self.max_abs_prob_diff_excused)}; {f['rows_flipped']} code rows with "
             f"other atoms than PyTorch's, {f['rows_near_tie']} near-ties on the same image "
             f"(largest gap {f['max_tie_gap']:.2g}, at most {f['max_tie_ratio']:.2g} of the "
             f"tolerance: {self.tie:g} or {RESOLUTION_FACTOR:g} x float32's resolution)"),
            ("  float32 codes", f"{_windows(self.windows_excused_float32)}"
             f"{worst(self.max_abs_prob_diff_excused_float32)}; rows with PyTorch's atoms apart "
             f"by up to {f['max_code_diff']:.2g} of the code's norm, at most "
             f"{f['max_code_ratio']:.2g} of float32's accuracy for them{beyond}"),
        ]


def _windows(n: int) -> str:
    return f"{n} window" if n == 1 else f"{n} windows"


@torch.no_grad()
def compare(model: nn.Module, onnx_model: bytes | str, probe: Probe, ck: dict,
            criterion: str = "strict", native: bool = False) -> Parity:
    """Run ``probe`` through both and measure (carry mode also along each run); for a model
    with sparse coders also the graph's codes of the probe's windows against scikit-learn's
    (:func:`tactile.export.codes.code_parity`), which must pass too, and the windows above
    :data:`ATOL` explained by the coders' float32 rounding (:mod:`tactile.export.ties`).
    ``native``: run the file's ``ai.tactile`` nodes on the kernel library (the codes and their
    excuses are read from the portable bodies either way). PyTorch computes its EMDs in float64
    (:func:`tactile.training.feature_pass.feature_pass`: the features the model was trained on,
    and what the file's EMD nodes compute on either path), except on the portable path of a
    file whose EMD function is float32 (exported before it was float64: checked as it was
    exported); its coders stay float32, whose near-tie rules :mod:`tactile.export.ties`
    judges the graph's coders by."""
    from tactile.training.feature_pass import feature_pass

    emd64 = native or not _float32_emd(onnx_model)
    with feature_pass(emd=emd64, codes=False):
        return _compare(model, onnx_model, probe, ck, criterion, native, emd64)


def _float32_emd(onnx_model: bytes | str) -> bool:
    """Whether the file's ``EMD`` function computes in float32: its body does not cast its
    input to float64 first (:func:`tactile.export.emd_graph.portable_body`)."""
    graph = (onnx.load_from_string(onnx_model) if isinstance(onnx_model, bytes)
             else onnx.load(onnx_model, load_external_data=False))
    for fn in graph.functions:
        if fn.domain == CUSTOM_DOMAIN and fn.name == "EMD":
            return not any(n.op_type == "Cast" and n.input[0] == fn.input[0] and any(
                a.name == "to" and a.i == onnx.TensorProto.DOUBLE for a in n.attribute)
                for n in _nodes(fn.node))
    return False


def _nodes(nodes) -> list:
    """``nodes`` and those of their subgraphs (an ``If`` picking one of several bodies)."""
    out = []
    for n in nodes:
        out.append(n)
        for a in n.attribute:
            if a.type == onnx.AttributeProto.GRAPH:
                out += _nodes(a.g.node)
    return out


def _compare(model: nn.Module, onnx_model: bytes | str, probe: Probe, ck: dict,
             criterion: str, native: bool, emd64: bool) -> Parity:
    model = model.eval()
    sess = session(onnx_model, native=native)
    carry = model.cfg.state == "carry"
    if carry:
        probe = _with_long_run(probe, ck)
    explain = (Explainer(model, onnx_model, native=native)
               if criterion == "strict" and coders(model) else None)
    examined = Examined()
    p_t, p_o, p_1, s_diff = _window_mode(model, sess, probe.x, explain, examined)
    n = len(probe)  # window-mode rows come first, in probe order
    n_runs = steps = longest = 0
    if carry:
        c_t, c_o, c_diff, runs = _carry_mode(model, sess, probe, explain, examined, first=n)
        p_t, p_o = np.concatenate([p_t, c_t]), np.concatenate([p_o, c_o])
        s_diff = max(s_diff, c_diff)
        n_runs, steps, longest = len(runs), sum(map(len, runs)), max(map(len, runs))
    dev_1 = np.zeros(len(p_t))
    dev_1[:n] = np.abs(p_1 - p_t[:n]).max(1)  # onnx at batch 1 (window mode)
    dev = np.maximum(np.abs(p_t - p_o).max(1), dev_1)
    tie = examined.mask(len(p_t))  # excused: near-tie atom flips or float32 code accuracy
    flip, f32 = examined.mask(len(p_t), NEAR_TIE), examined.mask(len(p_t), FLOAT32)
    diff = float(dev[~tie].max(initial=0.0))
    diff_1 = float(dev_1[~tie].max(initial=0.0))
    diff_flip = float(dev[flip].max()) if flip.any() else None
    diff_f32 = float(dev[f32].max()) if f32.any() else None
    lab_t, lab_o = p_t.argmax(1), p_o.argmax(1)
    top2 = np.sort(p_t, axis=1)[:, -2:]
    differ = lab_t != lab_o
    differ[:n] |= p_1.argmax(1) != lab_t[:n]  # window mode: batch 1 or the same batches
    excused = differ & ((top2[:, 1] - top2[:, 0] < MARGIN) | tie)
    agreement = float((~differ).mean())
    if criterion == "strict":
        passed = (diff <= ATOL and not (differ & ~excused).any()
                  and (not carry or longest >= MIN_CARRY)
                  and int(tie.sum()) <= MAX_EXCUSED * len(p_t))
    else:
        passed = agreement >= INT8_AGREEMENT
    acc_t = acc_o = None
    if probe.y is not None:
        acc_t = float((lab_t[:n] == probe.y).mean())
        acc_o = float((lab_o[:n] == probe.y).mean())
    codes = None
    if criterion == "strict" and coders(model):
        graph = (onnx.load_from_string(onnx_model) if isinstance(onnx_model, bytes)
                 else onnx.load(onnx_model))
        codes = code_parity(model, graph, probe.x[: len(probe)])
        passed = passed and all(r["passed"] for r in codes)
    return Parity(passed, criterion, probe.source, len(p_t), diff, s_diff, diff_1, agreement,
                  int(differ.sum()), int(excused.sum()), n_runs, steps, longest,
                  accuracy_torch=acc_t, accuracy_onnx=acc_o,
                  reference=_reference(model, emd64), codes=codes,
                  **({} if explain is None else {
                      "windows_excused": int(flip.sum()), "max_abs_prob_diff_excused": diff_flip,
                      "windows_excused_float32": int(f32.sum()),
                      "max_abs_prob_diff_excused_float32": diff_f32,
                      "max_excused": MAX_EXCUSED, "tie": TIE, "flips": examined.to_dict()}))


def compare_on_kernels(model: nn.Module, graph: onnx.ModelProto | str, probe: Probe, ck: dict,
                       criterion: str = "strict") -> Parity:
    """:func:`compare` with the file's ``ai.tactile`` nodes on the kernel library (``graph``, or
    the file at that path)."""
    onnx_model = graph if isinstance(graph, str) else graph.SerializeToString()
    return compare(model, onnx_model, probe, ck, criterion=criterion, native=True)


def _reference(model: nn.Module, emd64: bool) -> str:
    name = f"torch float32 eager, {type(model).__name__}.forward"
    emds = getattr(getattr(model, "pre", None), "emds", None)
    return name + f", its EMDs in float{64 if emd64 else 32}" if emds else name


def _window_mode(model: nn.Module, sess: ort.InferenceSession, x: np.ndarray,
                 explain: Explainer | None = None, examined: Examined | None = None):
    """Every window from a zero state: PyTorch and onnxruntime in batches of
    :data:`EVAL_BATCH`, onnxruntime also one window at a time. Returns probabilities (N, K)
    x3 (torch, onnx batched, onnx batch 1) and the max state difference of either onnx run.
    With ``explain``, the windows above :data:`ATOL` go to ``examined``."""
    pt, po, p1, sd = [], [], [], 0.0
    for i in range(0, len(x), EVAL_BATCH):
        xb = torch.from_numpy(np.ascontiguousarray(x[i : i + EVAL_BATCH]))
        h, c = model.zero_state(len(xb))
        with explain.recording() if explain else nullcontext() as rec:
            p, h1, c1 = model(xb, h, c)
        o = sess.run(None, {"x": xb.numpy(), "h": h.numpy(), "c": c.numpy()})
        pt.append(p.numpy())
        po.append(o[0])
        sd = max(sd, float(np.abs(o[1] - h1.numpy()).max()), float(np.abs(o[2] - c1.numpy()).max()))
        h0, c0 = (t[:, :1].numpy() for t in (h, c))
        ones = []
        for k in range(len(xb)):
            o1 = sess.run(None, {"x": xb[k : k + 1].numpy(), "h": h0, "c": c0})
            ones.append(o1[0])
            sd = max(sd, float(np.abs(o1[1][:, 0] - h1[:, k].numpy()).max()),
                     float(np.abs(o1[2][:, 0] - c1[:, k].numpy()).max()))
        p1 += ones
        if explain is not None:
            _explain_batch(explain, rec, xb.numpy(), (h.numpy(), c.numpy()), p.numpy(), o[0],
                           np.concatenate(ones), i, examined)
    return np.concatenate(pt), np.concatenate(po), np.concatenate(p1), sd


def _explain_batch(explain: Explainer, rec, x: np.ndarray, state: tuple, p: np.ndarray,
                   o: np.ndarray, o1: np.ndarray, first: int, examined: Examined) -> None:
    """The windows of one batch above :data:`ATOL`: the tapped copy run as each comparison
    ran them (the batch; each window alone, from ``state`` (h, c)) against PyTorch's pass
    ``rec``."""
    n, (h, c) = len(x), state
    bad = np.flatnonzero(np.abs(o - p).max(1) > ATOL)
    if bad.size:
        probs, _, _, rows = explain.run(x, h, c)
        mix = explain.substituted(x[bad], h[:, bad], c[:, bad],
                                  [_windows_rows(r[1], bad, n) for r in rows])
        for j, w in enumerate(bad):
            f = explain.window(rec, w, n, rows, w, bool(np.array_equal(probs[w], o[w])))
            f.by_codes = mix is not None and float(np.abs(mix[0][j] - o[w]).max()) <= ATOL
            examined.add(first + w, f)
    for w in np.flatnonzero(np.abs(o1 - p).max(1) > ATOL):
        probs, _, _, rows = explain.run(x[w : w + 1], h[:, :1], c[:, :1])
        mix = explain.substituted(x[w : w + 1], h[:, :1], c[:, :1], [r[1] for r in rows])
        f = explain.window(rec, w, n, rows, 0, bool(np.array_equal(probs[0], o1[w])))
        f.by_codes = mix is not None and float(np.abs(mix[0][0] - o1[w]).max()) <= ATOL
        examined.add(first + w, f)


def _windows_rows(rows: np.ndarray, windows: np.ndarray, n: int) -> np.ndarray:
    """The rows (window-major, ``len(rows) // n`` per window) of ``windows`` of ``n``."""
    s = len(rows) // n
    return np.concatenate([rows[w * s : (w + 1) * s] for w in windows])


def _carry_mode(model: nn.Module, sess: ort.InferenceSession, probe: Probe,
                explain: Explainer | None = None, examined: Examined | None = None,
                first: int = 0):
    """Each run window after window, each side feeding back its own state. With
    ``explain``, the windows above :data:`ATOL` go to ``examined`` (rows from ``first``)."""
    pt, po, sd = [], [], 0.0
    runs = [r for r in probe.runs if len(r) >= 2]
    at = first
    for rows in runs:
        h, c = model.zero_state(1)
        ho, co = h.numpy(), c.numpy()
        recs, ps, os_ = [], [], []
        for r in rows:
            xb = torch.from_numpy(probe.x[r : r + 1])
            with explain.recording() if explain else nullcontext() as rec:
                p, h, c = model(xb, h, c)
            o, ho, co = sess.run(None, {"x": xb.numpy(), "h": ho, "c": co})
            recs.append(rec)
            ps.append(p.numpy())
            os_.append(o)
            sd = max(sd, float(np.abs(ho - h.numpy()).max()), float(np.abs(co - c.numpy()).max()))
        if explain is not None:
            _explain_run(explain, recs, probe.x[rows], np.concatenate(ps),
                         np.concatenate(os_), at, examined)
        pt += ps
        po += os_
        at += len(rows)
    return np.concatenate(pt), np.concatenate(po), sd, runs


def _explain_run(explain: Explainer, recs: list, x: np.ndarray, p: np.ndarray, o: np.ndarray,
                 first: int, examined: Examined) -> None:
    """The windows of one carried run above :data:`ATOL`: the tapped copy along the run
    (feeding back its own state) up to the last of them, and PyTorch's model given the graph's
    codes along it (feeding back its state); a window inherits the flips of the windows before
    it (its state carries them)."""
    bad = np.flatnonzero(np.abs(o - p).max(1) > ATOL)
    if not bad.size:
        return
    h = c = hm = cm = np.zeros((explain.state_shape[0], 1, explain.state_shape[1]), np.float32)
    so_far = None
    for j in range(int(bad[-1]) + 1):
        probs, h, c, rows = explain.run(x[j : j + 1], h, c)
        mix = explain.substituted(x[j : j + 1], hm, cm, [r[1] for r in rows])
        f = explain.window(recs[j], 0, 1, rows, 0, bool(np.array_equal(probs[0], o[j])))
        if mix is None:
            f.by_codes = False
        else:
            f.by_codes = float(np.abs(mix[0][0] - o[j]).max()) <= ATOL
            hm, cm = mix[1], mix[2]
        so_far = f if so_far is None else so_far + f
        if j in bad:
            examined.add(first + j, so_far)


def _with_long_run(probe: Probe, ck: dict) -> Probe:
    """Add simulated (or random) runs when no run of ``probe`` is :data:`MIN_CARRY` long."""
    if max(map(len, probe.runs)) >= MIN_CARRY:
        return probe
    try:
        extra = simulated(ck)
    except (ValueError, KeyError):
        extra = random_windows(ck)
    n = len(probe)
    return Probe(
        np.concatenate([probe.x, extra.x]),
        None if probe.y is None or extra.y is None else np.concatenate([probe.y, extra.y]),
        probe.runs + [r + n for r in extra.runs],
        f"{probe.source} + {extra.source} (runs of {CARRY_STEPS})",
    )
