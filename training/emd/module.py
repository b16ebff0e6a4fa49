"""``EMD``: the torch module used by training and by the exported graph."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from tactile import native
from tactile.contract import MAX_IMFS, MAX_SIFTS
from tactile.errors import ConfigError
from tactile.training import feature_pass

from .decompose import decompose


@dataclass(frozen=True)
class EMDConfig:
    """EMD settings. Defaults suit 50-sample windows (4 IMFs of 10 sifts).

    Attributes:
        n_imfs: IMF slots, 1..16 (PyEMD ``max_imf``).
        n_sifts: sifts per IMF, 1..1000 (PyEMD ``FIXE``).
    """

    n_imfs: int = 4
    n_sifts: int = 10

    def __post_init__(self) -> None:
        for name, hi in (("n_imfs", MAX_IMFS), ("n_sifts", MAX_SIFTS)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise ConfigError(f"EMD {name} must be an int, got {type(value).__name__}")
            if not 1 <= value <= hi:
                raise ConfigError(f"EMD {name}={value} is out of range: allowed 1..{hi}")


class EMD(nn.Module):
    """Empirical mode decomposition as fixed-shape tensor ops (no parameters).

    Matches PyEMD ``EMD(FIXE=n_sifts, spline_kind="cubic", nbsym=2,
    extrema_detection="simple").emd(x, max_imf=n_imfs)`` window by window and channel by
    channel. Input must be finite: NaN/inf are rejected where data enters (the device decoder,
    the runtime); in eager mode this module also raises ``ValueError`` on them.

    Shapes:
        x: (B, C, T) float32 or float64.
        returns imfs (B, C, n_imfs, T) zero past the valid ones, residue (B, C, T) equal to
        ``x - imfs.sum(2)``, n_valid (B, C) int64. Windows with T < 3 have no IMFs.
    """

    def __init__(self, n_imfs: int = 4, n_sifts: int = 10) -> None:
        super().__init__()
        self.config = EMDConfig(n_imfs=n_imfs, n_sifts=n_sifts)

    @property
    def n_imfs(self) -> int:
        return self.config.n_imfs

    @property
    def n_sifts(self) -> int:
        return self.config.n_sifts

    def extra_repr(self) -> str:
        return f"n_imfs={self.n_imfs}, n_sifts={self.n_sifts}"

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        if x.dim() != 3:
            raise ValueError(f"EMD expects (batch, channels, time), got shape {tuple(x.shape)}")
        if x.dtype not in (torch.float32, torch.float64):
            raise ValueError(f"EMD expects float32 or float64 input, got {x.dtype}")
        exporting = torch.jit.is_tracing() or torch.onnx.is_in_onnx_export()
        if not exporting and not bool(torch.isfinite(x).all()):
            raise ValueError("EMD input contains NaN or inf")
        b, c, t = x.shape
        if t >= 3 and not exporting and not x.requires_grad and feature_pass.active("emd"):
            return self._float64(x)
        if t < 3:  # no sample can be an extremum: nothing to decompose
            imfs = x.new_zeros(b, c, self.n_imfs, t)
            return imfs, x.clone(), torch.zeros(b, c, dtype=torch.int64, device=x.device)
        imfs, residue, n_valid = decompose(x.reshape(-1, t), self.n_imfs, self.n_sifts)
        return self._shaped(imfs, residue, n_valid, b, c)

    def _float64(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The decomposition in float64 (training's feature pass), by the native kernel when
        it is built, else by torch; the IMFs and residue come back in ``x``'s dtype."""
        b, c, t = x.shape
        rows = x.detach().reshape(-1, t).to(torch.float64)
        if x.device.type == "cpu" and native.available():
            out = native.emd(rows.numpy(), self.n_imfs, self.n_sifts)
            imfs, residue, n_valid = (torch.from_numpy(a) for a in out)
        else:
            imfs, residue, n_valid = decompose(rows, self.n_imfs, self.n_sifts)
        return self._shaped(imfs.to(x.dtype), residue.to(x.dtype), n_valid, b, c)

    def _shaped(self, imfs: Tensor, residue: Tensor, n_valid: Tensor, b: int,
                c: int) -> tuple[Tensor, Tensor, Tensor]:
        t = imfs.shape[-1]
        return (
            imfs.reshape(b, c, self.n_imfs, t),
            residue.reshape(b, c, t),
            n_valid.reshape(b, c),
        )
