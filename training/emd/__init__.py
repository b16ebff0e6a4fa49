"""Empirical mode decomposition as fixed-shape tensor ops, exact against PyEMD.

``EMD(n_imfs, n_sifts)`` is a torch module; ``tactile.export.emd_graph.export_emd_onnx``
writes it as an ONNX graph whose sifts run inside ONNX ``Loop`` nodes (the export stage builds
every byte of ONNX; this package needs no onnx). The pieces, in pipeline order: extrema,
boundary knots, knot assembly, spline system and solve, envelope evaluation, one sift, the
decomposition. See ``docs/emd.md``.
"""

from .decompose import POWER_THR, RANGE_THR, decompose
from .module import EMD, EMDConfig

__all__ = ["EMD", "EMDConfig", "POWER_THR", "RANGE_THR", "decompose"]
