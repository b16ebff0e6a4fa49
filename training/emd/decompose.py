"""The decomposition: IMF after IMF, a fixed number of sifts each (EMD_SPEC §1.2, §4.9).

Matches PyEMD ``EMD(FIXE=n_sifts, spline_kind="cubic", nbsym=2, extrema_detection="simple")``
with ``emd(x, max_imf=n_imfs)``. A row stops for good when a sift finds 2 or fewer extrema
(that IMF is discarded and the un-sifted signal is the residue), or after an IMF when the
residue's range is below ``RANGE_THR`` or its absolute sum below ``POWER_THR``. Both
thresholds are absolute, in the input's units, exactly as in PyEMD: scale the input (e.g. to
unit variance) if its units are very small or very large.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .sift import sift

RANGE_THR = 1e-3
"""End of decomposition when ``max(res) - min(res)`` is below this (PyEMD ``range_thr``)."""
POWER_THR = 5e-3
"""End of decomposition when ``sum(|res|)`` is below this (PyEMD ``total_power_thr``)."""


def imf_update(x: Tensor, acc: Tensor, h: Tensor, active: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Close one IMF slot after its sifts.

    Args:
        x: (R, N) input; acc: (R, N) sum of the IMFs so far.
        h: (R, N) sifted proto-IMF; active: (R, 1) rows whose sifts all found > 2 extrema.

    Returns:
        imf: (R, N) ``h`` for active rows, 0 elsewhere.
        acc: (R, N) updated sum (PyEMD's ``np.sum(IMF, axis=0)``, added in the same order).
        alive: (R, 1) ``active`` and the residue ``x - acc`` is still above both thresholds.
    """
    imf = torch.where(active, h, torch.zeros((), dtype=h.dtype, device=h.device))
    acc = acc + imf
    res = x - acc  # (R, N)
    big = res.amax(-1, keepdim=True) - res.amin(-1, keepdim=True) >= RANGE_THR
    big = big & (res.abs().sum(-1, keepdim=True) >= POWER_THR)  # (R, 1)
    return imf, acc, active & big


def decompose(x: Tensor, n_imfs: int, n_sifts: int) -> tuple[Tensor, Tensor, Tensor]:
    """Fixed-shape EMD of every row.

    Args:
        x: (R, N) finite signals, N >= 3.
        n_imfs: IMF slots; n_sifts: sifts per IMF.

    Returns:
        imfs: (R, n_imfs, N), zero past ``n_valid``.
        residue: (R, N) ``x - sum(imfs)``.
        n_valid: (R,) int64 number of IMFs.
    """
    acc = torch.zeros_like(x)  # (R, N)
    alive = torch.ones_like(x[:, :1], dtype=torch.bool)  # (R, 1): a column selects rows
    n_valid = torch.zeros_like(x[:, :1], dtype=torch.int64)  # (R, 1)
    imfs = []
    for _ in range(n_imfs):
        h, active = x - acc, alive  # PyEMD restarts from S - sum(IMF)
        for _ in range(n_sifts):
            h, active = sift(h, active)
        imf, acc, alive = imf_update(x, acc, h, active)
        n_valid = n_valid + active.long()
        imfs.append(imf)
    return torch.stack(imfs, dim=1), x - acc, n_valid[:, 0]
