"""Sparse codes by orthogonal matching pursuit as fixed-shape tensor ops, as scikit-learn makes.

``SparseCoder(dictionary, n_nonzero)`` computes what scikit-learn's default transform computes
for that dictionary (``MiniBatchDictionaryLearning(...).transform`` and
``sklearn.decomposition.SparseCoder``: ``transform_algorithm='omp'``), namely
``orthogonal_mp_gram(D D^T, D x, n_nonzero_coefs=n_nonzero)`` for every row ``x``:

1. pick the atom whose correlation with the residual is largest in magnitude;
2. stop early (the row keeps the atoms it has) if that atom is already chosen, if its
   correlation squared is below the float32 epsilon, or if it depends linearly on the chosen
   ones (the new Cholesky pivot is below epsilon): scikit-learn's three early exits. At the
   first step only the correlation is tested, as in scikit-learn: an atom of tiny norm (squared
   norm below epsilon) is taken there, with its large coefficient;
3. least squares on the chosen atoms; the residual correlations follow; repeat ``n_nonzero``
   times.

Step 3 is the Cholesky update of scikit-learn's ``_gram_omp`` written as Gram-Schmidt in the
dictionary's Gram metric, so that each step is a handful of whole-tensor ops: the new Cholesky
row is a gather from the projections already made, and the code is accumulated as
``sum_s z_s r_s`` (``r_s`` the orthonormalised atom in atom coordinates). Rows that stopped are
masked, never branched on: the graph is the same for every input, with no ``NonZero``, no
data-dependent Python control flow, and the dictionary and its Gram matrix are constants.
``torch.onnx.export(..., dynamo=False)`` at opset 18 captures it (``tactile.export.coder_graph``).

scikit-learn's default number of non-zeros (``transform_n_nonzero_coefs=None``) is
``int(min(max(features / 10, 1), atoms))``: :func:`default_n_nonzero`.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from tactile import native
from tactile.errors import ConfigError
from tactile.training import feature_pass

EPS = float(np.finfo(np.float32).eps)
"""scikit-learn's early-exit threshold for float32 data: ``np.finfo(Gram.dtype).eps``."""


def default_n_nonzero(features: int, atoms: int) -> int:
    """scikit-learn's non-zeros when ``transform_n_nonzero_coefs`` is None (``_sparse_encode``):
    a tenth of the features, at least 1, at most the number of atoms."""
    return int(min(max(features / 10, 1), atoms))


class SparseCoder(nn.Module):
    """Orthogonal matching pursuit with a fixed number of non-zeros.

    Args:
        dictionary: (atoms, features) as scikit-learn stores it (``components_``, in any
            memory order); rows of any norm (dictionary learning keeps them at norm <= 1).
            Copied into C-ordered float32 constants of the module's own.
        n_nonzero: atoms per code, 1 .. atoms (scikit-learn's limit). Beyond ``features`` the
            residual vanishes and a row stops early, as in scikit-learn.

    Input ``(batch, features)`` float32 (scikit-learn's thresholds for float32 windows);
    output codes ``(batch, atoms)`` float32, at most ``n_nonzero`` non-zero per row.
    """

    def __init__(self, dictionary: np.ndarray | Tensor, n_nonzero: int) -> None:
        super().__init__()
        # a C-ordered copy of its own: scikit-learn's ``components_`` may be Fortran-ordered,
        # and another memory layout takes other matmul kernels, whose float32 rounding
        # differs in the last bits (a checkpoint restores C order)
        d = torch.as_tensor(np.array(dictionary, dtype=np.float64, order="C"))
        if d.ndim != 2 or d.shape[0] < 1 or d.shape[1] < 1:
            raise ConfigError(f"dictionary of shape {tuple(d.shape)}: must be (atoms, features)")
        if not torch.isfinite(d).all():
            raise ConfigError("dictionary holds NaN or inf")
        if isinstance(n_nonzero, bool) or not isinstance(n_nonzero, (int, np.integer)) or not (
                1 <= n_nonzero <= d.shape[0]):
            raise ConfigError(f"n_nonzero {n_nonzero!r}: must be an integer in 1..{d.shape[0]} "
                              "(the number of atoms)")
        self.n_nonzero = int(n_nonzero)
        gram = d @ d.T  # (K, K), float64 then rounded once, as scikit-learn rounds it to X's
        self.register_buffer("dictionary", d.float())  # (K, F)
        self.register_buffer("gram", gram.float())  # (K, K)
        self.register_buffer("gram_diag", torch.diagonal(gram).float().clone())  # (K,)

    @property
    def atoms(self) -> int:
        return self.dictionary.shape[0]

    @property
    def features(self) -> int:
        return self.dictionary.shape[1]

    def forward(self, x: Tensor) -> Tensor:
        """x: (batch, features) -> codes (batch, atoms). In training's feature pass
        (:func:`~tactile.training.feature_pass.feature_pass`) the pursuit runs in float64 (the
        same epsilon), by the native kernel where it is built, and the codes come back in
        ``x``'s dtype."""
        exporting = torch.jit.is_tracing() or torch.onnx.is_in_onnx_export()
        if not exporting and not x.requires_grad and feature_pass.active("codes"):
            if x.device.type == "cpu" and native.available():
                g = self.gram.numpy()
                codes = native.omp(x.detach().float().numpy(), self.dictionary.numpy(), g,
                                   self.n_nonzero)
                return torch.from_numpy(codes).to(x.dtype)
            return self.encode(x.detach().double())[0].to(x.dtype)
        return self.encode(x)[0]

    def encode(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Codes (batch, atoms) and the atoms chosen, in order (batch, n_nonzero) int64, -1
        where a row stopped early."""
        d, gram = self.dictionary.to(x.dtype), self.gram.to(x.dtype)
        diag = self.gram_diag.to(x.dtype)
        cov = x @ d.T  # (B, K) correlations of the input with every atom
        alpha = cov  # (B, K) correlations of the residual
        atom_ids = torch.arange(self.atoms, device=x.device)
        active = torch.zeros_like(cov)  # (B, K) 1 where chosen
        live = torch.ones_like(cov[:, :1])  # (B, 1) 1 while the row goes on
        # per step s, stacked on dim 1: <q_s, d_k> for every atom k (B, s, K); q_s in atom
        # coordinates (B, s, K); <q_s, x> (B, s, 1); q_s the s-th orthonormalised chosen atom
        proj = coef = z = None
        order = []
        for s in range(self.n_nonzero):
            lam = torch.argmax(alpha.abs(), dim=1, keepdim=True)  # (B, 1)
            pick = (atom_ids[None, :] == lam).to(x.dtype)  # (B, K) one-hot
            a_lam = torch.gather(alpha, 1, lam)  # (B, 1)
            c_lam = torch.gather(cov, 1, lam)
            g_lam = gram[lam[:, 0]]  # (B, K): Gram row of the picked atom
            pivot = diag[lam]  # (B, 1)
            if s:
                w = proj @ pick[:, :, None]  # (B, s, 1): the new Cholesky row
                wt = w.transpose(1, 2)  # (B, 1, s)
                pivot = pivot - (wt @ w)[:, 0]
                p_new = g_lam - (wt @ proj)[:, 0]
                r_new = pick - (wt @ coef)[:, 0]
                z_new = c_lam - (wt @ z)[:, 0]
            else:
                p_new, r_new, z_new = g_lam, pick, c_lam
            go = a_lam * a_lam >= EPS
            if s:  # nothing is chosen yet at step 0, and scikit-learn tests no pivot there
                again = torch.gather(active, 1, lam)  # 1 if the atom is already chosen
                go = go & (again == 0) & (pivot > EPS)
            live = live * go.to(x.dtype)
            inv = live / torch.sqrt(torch.where(live > 0, pivot, torch.ones_like(pivot)))
            p_s, r_s, z_s = p_new * inv, r_new * inv, z_new * inv  # (B, K), (B, K), (B, 1)
            alpha = alpha - z_s * p_s
            active = active + pick * live
            order.append(torch.where(live > 0, lam, torch.full_like(lam, -1)))
            if s == 0:
                proj, coef, z = p_s[:, None], r_s[:, None], z_s[:, None]
            else:
                proj = torch.cat([proj, p_s[:, None]], 1)
                coef = torch.cat([coef, r_s[:, None]], 1)
                z = torch.cat([z, z_s[:, None]], 1)
        codes = (z.transpose(1, 2) @ coef)[:, 0]  # (B, K): sum_s z_s q_s in atom coordinates
        return codes, torch.cat(order, 1)


__all__ = ["EPS", "SparseCoder", "default_n_nonzero"]
