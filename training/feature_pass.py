"""Training's feature pass: the EMD and sparse codes of every window, computed once, exact.

Inside :func:`feature_pass` the toolkit's ``EMD`` modules and ``SparseCoder`` s compute in
float64 (their inputs and outputs keep their dtype) and call the native kernels
(:mod:`tactile.native`) when they are built and enabled, torch otherwise. Both compute the
same thing in the same precision, so a feature pass gives the same features, within float64
rounding before the cast back, whether the kernels are built or not (the kernels are the
fast path, 10-15x torch's on a BioTac window); in float32 a near-tie of two extrema or two
atoms can decide a knot or an atom, and float64 is also closer to the references (PyEMD,
scikit-learn). Export's parity check runs its PyTorch reference inside one with the EMD alone
(what the exported file's EMD nodes compute on either path). Outside (export's traced graph,
gradients) the modules compute in their input's dtype.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

_on = {"emd": 0, "codes": 0}


@contextmanager
def feature_pass(emd: bool = True, codes: bool = True) -> Iterator[None]:
    """Within: EMD (``emd``) and sparse coding (``codes``) in float64, through the native
    kernels where built. Export's parity check takes the EMD alone: the graph's portable
    coders run float32 arithmetic's near-tie rules, which :mod:`tactile.export.ties` judges
    against PyTorch's float32 coders."""
    kinds = [k for k, on in (("emd", emd), ("codes", codes)) if on]
    for k in kinds:
        _on[k] += 1
    try:
        yield
    finally:
        for k in kinds:
            _on[k] -= 1


def active(kind: str) -> bool:
    """True inside a :func:`feature_pass` that covers ``kind`` ("emd" or "codes")."""
    return _on[kind] > 0


def backend() -> str:
    """What a feature pass runs on this machine, for the training log."""
    from tactile import native

    return "the native kernels" if native.available() else "torch (no native kernels)"


__all__ = ["active", "backend", "feature_pass"]
