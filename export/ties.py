"""Near-tie atom flips and float32 code accuracy: the probability differences they excuse.

OMP picks, at every step, the atom whose residual correlation is largest. When two atoms'
correlations are nearly equal, float32 rounding decides, and PyTorch's coder and the graph's
(other kernels, other rounding) may decide differently: on the BioTac's vibration images (200
atoms, 17 non-zeros) on 20 of 70,100 rows of the 1,402 test windows. Such a row's code then
holds another atom and other coefficients, and its window's probabilities move by up to a few
hundredths, far beyond :data:`tactile.export.parity.ATOL`, although both sides computed what
they should. And where both pick the same atoms, their coefficients differ by float32's
rounding, which on an ill-conditioned atom set is large (up to 1.6e-4 of the code's norm on
loud BioTac vibration windows) and which a head's batch normalisation may multiply beyond
``ATOL`` on a window or two in a thousand.

So for a model with sparse coders a window whose probabilities differ by more than ``ATOL``
is excused when the coders' float32 rounding explains it, and only then:

* the graph's coders are observed on that window by a copy of the file's graph that also
  outputs each coder's images, codes and per-step picks (its ``ArgMax`` values:
  :func:`tactile.export.taps.tapped`), run as the window was run (in its batch, alone, or
  along its carried run); that copy's probabilities must equal the file's bit for bit;
* PyTorch's coders are observed on the same forward pass by forward hooks (:func:`recording`),
  the atoms each chose in order by its ``encode`` of the same batch, which must give its codes
  bit for bit;
* every one of the window's rows (any coder; in carry mode also the rows of the earlier
  windows of its run, whose state it inherits) codes the same image in the graph as in
  PyTorch (within :data:`IMAGE_RTOL` x its norm), and either has the same non-zero atoms with
  codes apart by no more than float32's accuracy for those atoms (twice
  :func:`tactile.export.codes.float32_bound`, the bound the code parity uses), or other atoms
  at a near-tie: at the step where the two OMP runs parted, the float64 residual correlations
  of their two picks (after the atoms both picked before) within
  :data:`tactile.export.codes.TIE` of the largest or
  :data:`~tactile.export.codes.RESOLUTION_FACTOR` x float32's resolution of the step
  (:func:`tactile.export.codes.parting`) (:func:`judge_rows`);
* PyTorch's model given the graph's codes gives the graph's probabilities within ``ATOL``
  (:meth:`Explainer.substituted`): the head is right, the codes make the difference.

A window with a flip is excused as a near-tie flip (:data:`NEAR_TIE`), one without as float32
code accuracy (:data:`FLOAT32`); each kind is counted. A wrong graph is not excused: a scaled
dictionary moves every code beyond float32's accuracy on the well-conditioned rows, an extra
non-zero adds an atom PyTorch never chose (no near-tie), a wrong normalisation codes other
images, a wrong head is not reproduced by PyTorch given the graph's codes. At most
:data:`MAX_EXCUSED` of the windows may be excused, of both kinds together.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import onnx
import torch
from torch import nn

from tactile.export.codes import float32_apart, parting
from tactile.export.taps import CoderTap, find_coders, graph_order, tap_session
from tactile.training.sparse_check import sklearn_order

IMAGE_RTOL = 1e-4
"""A row codes the same image when max |x_graph - x_torch| <= this x ||x_torch|| (the BioTac's
images are the same bits in both)."""
MAX_EXCUSED = 0.05
"""Largest share of the compared windows that may be excused, near-tie flips and float32 code
accuracy together. Measured on all 1,402 BioTac vibration test windows: 1.4 % excused for a
sparse linear model (every flip moves its pooled codes; no window for float32 accuracy), 0.6 %
+ 0.07 % for an SF-RNN; at 1.4 % a sample of 256 windows exceeds 5 % with probability 1e-4
(binomial), 2 % with probability 0.16. A wrong coder moves most windows."""
NEAR_TIE = "near-tie"
"""The kind of an excused window with an atom flip."""
FLOAT32 = "float32"
"""The kind of an excused window without one: the codes' float32 rounding."""


@dataclass
class Flips:
    """What the rows of a window show: ``rows`` compared, ``flipped`` (other non-zero atoms
    than PyTorch's), of which ``ties`` near-ties on the same image; ``max_gap`` the largest
    |gap| among the ties and ``max_ratio`` the largest |gap| / tolerance; ``image_off`` rows
    whose images differ by more than :data:`IMAGE_RTOL`; of the rows with the same atoms,
    ``beyond`` those whose codes differ by more than float32's accuracy for their atoms
    (:func:`~tactile.export.codes.float32_apart`), ``max_code_diff`` their largest
    max |dc| / ||c|| and ``max_code_ratio`` their largest max |dc| / ||c|| / tolerance;
    ``reproduced`` False when the tapped copy did not give the file's probabilities (or
    PyTorch's encode not its codes); ``by_codes`` False when PyTorch's model given the graph's
    codes did not give the graph's probabilities (within ``ATOL``). Nothing is then excused."""

    rows: int = 0
    flipped: int = 0
    ties: int = 0
    max_gap: float = 0.0
    max_ratio: float = 0.0
    reproduced: bool = True
    by_codes: bool = True
    image_off: int = 0
    beyond: int = 0
    max_code_diff: float = 0.0
    max_code_ratio: float = 0.0

    def __add__(self, other: Flips) -> Flips:
        return Flips(self.rows + other.rows, self.flipped + other.flipped,
                     self.ties + other.ties, max(self.max_gap, other.max_gap),
                     max(self.max_ratio, other.max_ratio),
                     self.reproduced and other.reproduced, self.by_codes and other.by_codes,
                     self.image_off + other.image_off, self.beyond + other.beyond,
                     max(self.max_code_diff, other.max_code_diff),
                     max(self.max_code_ratio, other.max_code_ratio))

    @property
    def kind(self) -> str | None:
        """What excuses the window: ``"near-tie"`` (it holds a flip, every flip a near-tie),
        ``"float32"`` (no flip), or None; either way every row's image is the same, every row
        with the same atoms within float32's accuracy, and the codes explain the
        probabilities."""
        if not (self.reproduced and self.by_codes and self.rows) or self.image_off or self.beyond:
            return None
        if not self.flipped:
            return FLOAT32
        return NEAR_TIE if self.ties == self.flipped else None

    @property
    def excuses(self) -> bool:
        """True when :attr:`kind` is not None."""
        return self.kind is not None


class Pass:
    """PyTorch's coders in one forward pass: per coder its calls' input images ``(rows,
    features)`` and output codes ``(rows, atoms)``, recorded by forward hooks."""

    def __init__(self, coders: list[nn.Module]) -> None:
        self.coders = coders
        self.calls: list[list[tuple[torch.Tensor, torch.Tensor]]] = [[] for _ in coders]
        self._rows: dict[int, tuple] = {}

    def rows(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Coder ``k``'s images, codes and the atoms chosen in order (-1 after an early stop;
        None when its ``encode`` of the same batch does not give the codes bit for bit), of
        its first call in the pass."""
        if k not in self._rows:
            x, codes = self.calls[k][0]
            with torch.no_grad():
                again, order = self.coders[k].encode(x)  # same batch, same kernels
            self._rows[k] = (x.numpy(), codes.numpy(),
                             order.numpy() if torch.equal(again, codes) else None)
        return self._rows[k]


@contextmanager
def recording(coders: list[nn.Module]):
    """Hooks on ``coders`` for the forward pass inside the block: yields its :class:`Pass`."""
    rec = Pass(coders)

    def hook(k):
        def record(module, inputs, output):
            rec.calls[k].append((inputs[0].detach().clone(), output.detach().clone()))
        return record

    handles = [c.register_forward_hook(hook(k)) for k, c in enumerate(coders)]
    try:
        yield rec
    finally:
        for h in handles:
            h.remove()


def judge_rows(d: np.ndarray, x_t: np.ndarray, c_t: np.ndarray, order_t: np.ndarray | None,
               x_g: np.ndarray, c_g: np.ndarray, order_g: np.ndarray | None,
               float64: bool = False) -> Flips:
    """Rows of one coder (dictionary ``d`` (atoms, features)): PyTorch's images ``x_t``,
    codes ``c_t`` and atoms in order ``order_t`` (rows, n; -1 after a stop), the graph's
    ``x_g``, ``c_g``, ``order_g``. Every row's images must agree (:data:`IMAGE_RTOL`). A row
    with the same non-zero atoms must have codes within float32's accuracy for those atoms
    (:func:`~tactile.export.codes.float32_apart`). A row whose non-zero atoms differ is a
    near-tie when the two runs parted at a step where their picks' float64 residual
    correlations differ by less than :data:`~tactile.export.codes.TIE` of the largest, or less
    than :data:`~tactile.export.codes.RESOLUTION_FACTOR` x float32's resolution of that
    step's correlations when that is coarser (:func:`~tactile.export.codes.parting` on
    PyTorch's image). Without the graph's order (``order_g`` None: its coder does not pick
    one atom per non-zero) no flip is a near-tie, unless ``float64``: the graph's coder is the
    native kernel, which computes OMP in float64: where it parted from PyTorch is found from
    its code (:func:`kernel_order`)."""
    img = np.abs(x_g.astype(np.float64) - x_t).max(1)
    same_image = img <= IMAGE_RTOL * np.linalg.norm(x_t.astype(np.float64), axis=1)
    differ = ((c_t != 0) != (c_g != 0)).any(1)
    flipped = np.flatnonzero(differ)
    out = Flips(rows=len(c_t), flipped=len(flipped), reproduced=order_t is not None,
                image_off=int((~same_image).sum()))
    if (~differ).any():
        rel, tol = float32_apart(d, c_g[~differ], c_t[~differ])
        ratio = np.where(rel == 0, 0.0, rel / np.maximum(tol, 1e-300))
        out.beyond = int((ratio > 1).sum())
        out.max_code_diff, out.max_code_ratio = float(rel.max()), float(ratio.max())
    if order_t is None or (order_g is None and not float64):
        return out
    for i in flipped:
        if not same_image[i]:
            continue
        if order_g is None:
            other = kernel_order(d, x_g[i], order_t[i].tolist(), c_g[i])
        else:
            other = order_g[i].tolist()
        gap, tolerance = parting(d, x_t[i], order_t[i].tolist(), other)
        if abs(gap) < tolerance:
            out.ties += 1
            out.max_gap = max(out.max_gap, abs(gap))
            out.max_ratio = max(out.max_ratio, abs(gap) / tolerance)
    return out


def kernel_order(d: np.ndarray, x: np.ndarray, order_t: list[int], code: np.ndarray
                 ) -> list[int]:
    """The native kernel's atoms for image ``x`` as far as a near-tie judgement needs them:
    its code shows which atoms it chose, not in which order. When OMP in float64 on the file's
    float32 Gram matrix (what the kernel computes) chose those atoms, its order. Otherwise:
    the atoms PyTorch picked (in
    ``order_t``, -1 after a stop) that the kernel's code also holds, up to the first one it
    lacks, are the two runs' common start (OMP's residual after a set of atoms does not depend
    on their order); at that step the kernel took, of its other atoms, the one with the largest
    float64 residual correlation after the common start (it computes OMP in float64), then
    -1s to the same length."""
    support = set(np.flatnonzero(code).tolist())
    n = len(order_t)
    path = _float64_order(d, x, n)
    if set(path) == support:  # the kernel's own run (same atoms): its order
        return path + [-1] * (n - len(path))
    common = []
    for a in order_t:
        if a < 0 or a not in support:
            break
        common.append(int(a))
    rest = sorted(support - set(common))
    if not rest:
        return common + [-1] * (n - len(common))
    d64, x64 = d.astype(np.float64), x.astype(np.float64)
    r = x64
    if common:
        sub = d64[common]
        r = x64 - sub.T @ np.linalg.lstsq(sub.T, x64, rcond=None)[0]
    pick = rest[int(np.argmax(np.abs(d64[rest] @ r)))]
    return common + [pick] + [-1] * (n - len(common) - 1)


def _float64_order(d: np.ndarray, x: np.ndarray, n: int) -> list[int]:
    """OMP's atoms in order for image ``x``, in float64 on ``D D^T`` rounded once to float32
    (the Gram matrix a file holds)."""
    d64 = d.astype(np.float64)
    gram = (d64 @ d64.T).astype(np.float32).astype(np.float64)
    return sklearn_order(d64, x.astype(np.float64), n, gram=gram)


class Explainer:
    """The graph's coders (a tapped copy of the file's graph) and PyTorch's (hooks) on the
    windows whose probabilities differ, for a model with coders."""

    def __init__(self, model: nn.Module, graph: bytes | str | onnx.ModelProto,
                 native: bool = False) -> None:
        if not isinstance(graph, onnx.ModelProto):
            graph = (onnx.load_from_string(graph) if isinstance(graph, bytes)
                     else onnx.load(graph))
        self.taps: list[CoderTap] = find_coders(model, graph)
        self.native = native  # the kernel library runs the coders: float64 OMP's picks
        self.sess, self.picks, tapped_names = tap_session(graph, self.taps, native=native)
        self.names = ["probs", "h_out", "c_out"] + tapped_names
        self.coders = [t.coder for t in self.taps]
        self.model = model
        self.state_shape = model.state_shape  # (layers, hidden)
        self.dicts = [c.dictionary.numpy() for c in self.coders]

    def recording(self):
        """Context manager around the model's forward: yields its :class:`Pass`."""
        return recording(self.coders)

    def run(self, x: np.ndarray, h: np.ndarray, c: np.ndarray):
        """The tapped copy on one call: probs, h, c and per coder (images, codes, atoms in
        order)."""
        out = self.sess.run(self.names, {"x": x, "h": h, "c": c})
        rows, at = [], 3 + 2 * len(self.taps)
        for k, t in enumerate(self.taps):
            codes, n = out[4 + 2 * k], t.coder.n_nonzero
            order = (None if self.picks is None
                     else graph_order(np.concatenate(out[at : at + n], axis=1), codes))
            rows.append((out[3 + 2 * k], codes, order))
            at += n
        return out[0], out[1], out[2], rows

    @torch.no_grad()
    def substituted(self, x: np.ndarray, h: np.ndarray, c: np.ndarray,
                    codes: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """PyTorch's model on windows ``x`` with each coder's output replaced by ``codes[k]``
        (the graph's codes of those windows, rows window-major): probs, h, c; None when the
        codes do not fit the coders' outputs."""
        fits = [True]

        def hook(k):
            def replace(module, inputs, output):
                if output.shape != codes[k].shape:
                    fits[0] = False
                    return output
                return torch.from_numpy(np.ascontiguousarray(codes[k]))
            return replace

        handles = [m.register_forward_hook(hook(k)) for k, m in enumerate(self.coders)]
        try:
            p, h1, c1 = self.model(*(torch.from_numpy(np.ascontiguousarray(v))
                                     for v in (x, h, c)))
        finally:
            for handle in handles:
                handle.remove()
        return (p.numpy(), h1.numpy(), c1.numpy()) if fits[0] else None

    def window(self, rec: Pass, w: int, n: int, graph_rows: list[tuple], g: int,
               reproduced: bool) -> Flips:
        """Window ``w`` of the ``n`` windows of PyTorch's pass ``rec`` against window ``g`` of
        the tapped run's ``graph_rows`` (per coder (images, codes, order), rows window-major);
        ``reproduced``: the tapped run gave that window the file's probabilities."""
        out = Flips(reproduced=reproduced)
        for k, d in enumerate(self.dicts):
            if len(rec.calls[k]) != 1:  # encode reproduces a call, not several
                return Flips(reproduced=False)
            x_t, c_t, order = rec.rows(k)
            x_g, c_g, order_g = graph_rows[k]
            s = len(c_t) // n
            if s * n != len(c_t) or len(c_g) % s:  # not rows of windows x steps
                return Flips(reproduced=False)
            t, r = slice(w * s, (w + 1) * s), slice(g * s, (g + 1) * s)
            out = out + judge_rows(d, x_t[t], c_t[t], None if order is None else order[t],
                                   x_g[r], c_g[r], None if order_g is None else order_g[r],
                                   float64=self.native)
        return out


class Examined:
    """The windows whose probabilities differed by more than the limit in some comparison
    (by their row in the parity's result), with the flips of the first comparison that
    examined each; a window is excused only if every comparison that examined it excuses it,
    as a near-tie flip if any of them saw a flip, else for float32 code accuracy."""

    def __init__(self) -> None:
        self.flips: dict[int, Flips] = {}
        self.excused: dict[int, bool] = {}
        self.flipped: dict[int, bool] = {}

    def add(self, w: int, flips: Flips) -> None:
        if w not in self.flips:
            self.flips[w], self.excused[w] = flips, flips.excuses
            self.flipped[w] = flips.flipped > 0
        else:
            self.excused[w] = self.excused[w] and flips.excuses
            self.flipped[w] = self.flipped[w] or flips.flipped > 0

    def kind(self, w: int) -> str | None:
        """What excused window ``w`` (:data:`NEAR_TIE`, :data:`FLOAT32`), None if nothing."""
        if not self.excused.get(w):
            return None
        return NEAR_TIE if self.flipped[w] else FLOAT32

    def mask(self, n: int, kind: str | None = None) -> np.ndarray:
        """(n,) True where a window is excused (of ``kind``, or of either)."""
        out = np.zeros(n, bool)
        out[[w for w in self.excused if self.kind(w) is not None
             and kind in (None, self.kind(w))]] = True
        return out

    def to_dict(self) -> dict:
        """``windows_examined``, ``rows_flipped`` (rows of theirs whose atoms differ from
        PyTorch's), ``rows_near_tie`` (of those, near-ties on the same image),
        ``max_tie_gap`` (the largest |gap| of a near-tie), ``max_tie_ratio`` (the largest
        |gap| / tolerance), ``rows_image_off`` (rows whose images differ), of the rows with the
        same atoms ``rows_beyond_float32`` (codes apart by more than float32's accuracy),
        ``max_code_diff`` (their largest max |dc| / ||c||) and ``max_code_ratio`` (largest
        max |dc| / ||c|| / tolerance), ``not_reproduced`` (windows whose tapped copy or
        encode did not reproduce the pass) and ``not_by_codes`` (windows whose probabilities
        PyTorch given the graph's codes did not reproduce)."""
        total = sum(self.flips.values(), Flips())
        return {"windows_examined": len(self.flips), "rows_flipped": total.flipped,
                "rows_near_tie": total.ties, "max_tie_gap": float(f"{total.max_gap:.3g}"),
                "max_tie_ratio": float(f"{total.max_ratio:.3g}"),
                "rows_image_off": total.image_off, "rows_beyond_float32": total.beyond,
                "max_code_diff": float(f"{total.max_code_diff:.3g}"),
                "max_code_ratio": float(f"{total.max_code_ratio:.3g}"),
                "not_reproduced": sum(not f.reproduced for f in self.flips.values()),
                "not_by_codes": sum(not f.by_codes for f in self.flips.values())}
