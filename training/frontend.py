"""The high-rate front end: a declared signal's log band powers, framed at its own rate.

A high-rate signal reaches the model as ``r`` channels per frame (its consecutive sub-samples
in time order, ``tactile.training.modality``). Framing each of those channels at the frame
rate would see only aliases of the signal; :class:`HighRateFront` regroups them into the
signal ``(B, T * r)`` by a reshape, frames it with frames ``r`` times as long (so its frames
start and end with the window's frames) and gives, per frame, the log power in third-octave
bands up to the signal's Nyquist frequency and the frame's mean. Everything is a reshape, a
fixed convolution and a fixed matrix product: it traces to standard ONNX ops.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

BANDS_PER_OCTAVE = 3  # third-octave bands, as acoustics measures spectra
LOG_FLOOR = 1e-4
"""Floor of each DFT bin's power |X_k|^2 (the plain front's, ``SpectralFront.LOG_FLOOR``): a
band's floor is that of its bins in the band power's scale. On the unit-variance scale of the
normalised signal it sits far below a 12-bit sensor's quantisation noise (a BioTac's vibration,
std about 140 counts: per-bin powers 1e-6 to 1e-4 in the band scale, bin floors 3e-9)."""


def band_bins(n_bins: int, per_octave: int = BANDS_PER_OCTAVE) -> list[tuple[int, int]]:
    """The bands over DFT bins ``1 .. n_bins - 1`` (bin 0, the mean, is apart) as half-open
    bin ranges ``[a, b)``: edges at ``2 ** (j / per_octave)`` bins, rounded up, from bin 1 to
    past the last bin (Nyquist's, for an even frame), each band at least one bin wide (the low
    edges that would give an empty band are merged). The same rule at every rate: with frames
    ``N`` samples long at ``rate`` Hz, band edges sit at ``2 ** (j / per_octave) * rate / N``
    Hz."""
    top = n_bins - 1  # the last bin's index
    if top < 1:
        return []
    n = math.ceil(per_octave * math.log2(top + 1)) if top > 1 else 1
    edges = sorted({min(math.ceil(2 ** (j / per_octave) - 1e-9), top + 1)
                    for j in range(n + 1)} | {1, top + 1})
    return [(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]


def band_edges_hz(frame: int, rate_hz: float,
                  per_octave: int = BANDS_PER_OCTAVE) -> list[tuple[float, float]]:
    """The bands of a frame of ``frame`` samples at ``rate_hz`` as frequency ranges
    ``[lo, hi)`` in Hz (bin k is at ``k * rate_hz / frame``; the last band ends at Nyquist)."""
    df = rate_hz / frame
    return [(a * df, min(b * df, rate_hz / 2)) for a, b in band_bins(frame // 2 + 1, per_octave)]


class HighRateFront(nn.Module):
    """(B, T, F) features -> (B, T', S * (nb + 1)): per high-rate signal and frame, the log
    power in each of nb third-octave bands (:func:`band_bins`) and the frame's mean.

    ``signals``: per signal the indices into F of its ``r`` sub-sample channels, in time order
    (every signal of one front has the same ``r``); frames of ``frame * r`` samples every
    ``hop * r`` samples of the signal, so T' = (T - frame) // hop + 1, the plain channels'
    frames. Band power: ``2 / (N * sum(w ** 2)) * sum over the band's bins of |DFT(w * s)|^2``
    with ``w`` the Hann taper of N = frame * r samples, the mean square a tone lying wholly in
    the band contributes (a sine of amplitude A: A^2 / 2); features ``log(power + floor)``
    with ``floor = LOG_FLOOR * 2 / (N * sum(w ** 2)) * bins in the band``. No trainable
    weights (the caller's batch normalisation scales them).
    """

    def __init__(self, signals: list[list[int]], frame: int, hop: int) -> None:
        super().__init__()
        rs = {len(s) for s in signals}
        if len(rs) != 1:
            raise ValueError(f"signals of different sub-sample counts {sorted(rs)}")
        self.r = rs.pop()
        self.n_signals = len(signals)
        n = frame * self.r
        self.frame, self.hop = n, hop * self.r
        t = torch.arange(n, dtype=torch.float64)
        taper = torch.hann_window(n, periodic=False, dtype=torch.float64)
        n_bins = n // 2 + 1
        bands = band_bins(n_bins)
        self.n_bands = len(bands)
        used = range(1, bands[-1][1]) if bands else range(0)
        rows = []
        for k in used:
            rows += [torch.cos(2 * math.pi * k * t / n) * taper,
                     torch.sin(2 * math.pi * k * t / n) * taper]
        rows.append(torch.full((n,), 1.0 / n, dtype=torch.float64))  # the mean
        self.register_buffer("basis", torch.stack(rows).float().unsqueeze(1))  # (2K' + 1, 1, N)
        scale = 2.0 / (n * float((taper**2).sum()))
        pool = torch.zeros(self.n_bands, len(used), dtype=torch.float64)
        for j, (a, b) in enumerate(bands):
            pool[j, a - 1 : b - 1] = scale
        self.register_buffer("pool", pool.float())  # (nb, K'): bins -> band powers
        floor = [LOG_FLOOR * scale * (b - a) for a, b in bands]
        self.register_buffer("floor", torch.tensor(floor, dtype=torch.float32).unsqueeze(1))
        self.register_buffer("index", torch.tensor([i for s in signals for i in s],
                                                   dtype=torch.long))  # (S * r,)
        self.n_used = len(used)
        self.n_out = self.n_signals * (self.n_bands + 1)

    def forward(self, f: Tensor) -> Tensor:
        b, t, _ = f.shape
        x = torch.index_select(f, 2, self.index).reshape(b, t, self.n_signals, self.r)
        s = x.permute(0, 2, 1, 3).reshape(b * self.n_signals, 1, t * self.r)  # the signals
        y = nn.functional.conv1d(s, self.basis, stride=self.hop)  # (B * S, 2K' + 1, T')
        frames = y.shape[2]
        re, im = y[:, 0 : 2 * self.n_used : 2], y[:, 1 : 2 * self.n_used : 2]
        power = torch.matmul(self.pool, re * re + im * im)  # (B * S, nb, T')
        z = torch.cat([torch.log(power + self.floor), y[:, 2 * self.n_used :]], dim=1)
        return z.reshape(b, self.n_out, frames).transpose(1, 2)  # (B, T', S * (nb + 1))


__all__ = ["HighRateFront", "band_bins", "band_edges_hz", "BANDS_PER_OCTAVE", "LOG_FLOOR"]
