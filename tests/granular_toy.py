"""A toy granular model following the three-stage interface export composes (for tests).

Independent of the training code's granular models: two EMDs of different IMF counts, sifts
and lengths (a high-rate signal of ``R`` sub-samples per frame, unpacked by a reshape, and a
plain channel), data images of the last ``steps`` samples at each modality's rate ending with
each frame, a :class:`SparseCoder` per coded modality over the ``(B*S, features)`` images, and
an LSTM head over the S steps. Channels: ``sig_0..sig_{R-1}`` (the signal), ``pdc``, ``ele``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from tactile.training.emd import EMD
from tactile.training.model import LSTMHead
from tactile.training.sparse import SparseCoder

R = 4  # sub-samples per frame of the signal
CHANNELS = (*(f"sig_{i}" for i in range(R)), "pdc", "ele")


@dataclass(frozen=True)
class ToyCfg:
    window: int = 20
    hop: int = 20
    state: str = "window"


@dataclass(frozen=True)
class Mod:
    name: str
    index: tuple[int, ...]
    r: int
    imfs: int
    sifts: int
    steps: int
    atoms: int
    nonzero: int

    @property
    def n(self) -> int:
        return len(self.index) // self.r

    @property
    def features(self) -> int:
        return self.n * max(self.imfs, 1) * self.steps


MODS = (
    Mod("vibration", tuple(range(R)), R, 3, 4, 6, 24, 3),  # EMD of T*R = 80 samples, 3 IMFs
    Mod("pressure", (R,), 1, 2, 3, 3, 12, 2),  # EMD of T = 20 samples, 2 IMFs
    Mod("electrodes", (R + 1,), 1, 0, 5, 3, 8, 1),  # no EMD: the normalised values
)


class ToyPre(nn.Module):
    """(B, T, C) -> codes (B, S, sum atoms) (``coded``) or images (B, S, sum features)."""

    def __init__(self, mods: tuple[Mod, ...], window: int, mean: Tensor, std: Tensor,
                 dictionaries: list[np.ndarray] | None) -> None:
        super().__init__()
        self.mods, self.window = mods, window
        self.register_buffer("mean", mean.float().clone())
        self.register_buffer("std", std.float().clone())
        self.emds = nn.ModuleList([EMD(m.imfs, m.sifts) for m in mods if m.imfs])
        self.s = window - max(math.ceil(m.steps / m.r) for m in mods) + 1
        for k, m in enumerate(mods):  # sample index of each step's image: (S, steps)
            ends = (torch.arange(window - self.s, window) + 1) * m.r
            idx = ends[:, None] - m.steps + torch.arange(m.steps)[None, :]
            self.register_buffer(f"steps{k}", idx)
        self.coders = nn.ModuleList(
            [SparseCoder(d, m.nonzero) for d, m in zip(dictionaries, mods)]
            if dictionaries is not None else [])
        self.n_features = sum(m.atoms if dictionaries is not None else m.features for m in mods)

    def normalise(self, x: Tensor) -> Tensor:
        return (x - self.mean) / self.std

    def _signal(self, z: Tensor, m: Mod) -> Tensor:
        """(B, T, C) -> (B, n, T * r): the modality's channels, signals unpacked."""
        b, t, _ = z.shape
        sel = z[:, :, list(m.index)].reshape(b, t, m.n, m.r)
        return sel.permute(0, 2, 1, 3).reshape(b, m.n, t * m.r)

    def emd_inputs(self, z: Tensor) -> list[Tensor]:
        return [self._signal(z, m) for m in self.mods if m.imfs]

    def images(self, z: Tensor, imfs: list[Tensor]) -> list[Tensor]:
        """Per modality (B, S, n * max(imfs, 1) * steps), order (signal, IMF, time)."""
        out, k = [], 0
        for i, m in enumerate(self.mods):
            if m.imfs:
                sig, k = imfs[k], k + 1  # (B, n, K, L)
            else:
                sig = self._signal(z, m)[:, :, None]  # (B, n, 1, L)
            img = sig[:, :, :, getattr(self, f"steps{i}")]  # (B, n, K, S, steps)
            b = img.shape[0]
            out.append(img.permute(0, 3, 1, 2, 4).reshape(b, self.s, m.features))
        return out

    def finish(self, z: Tensor, imfs: list[Tensor]) -> Tensor:
        imgs = self.images(z, imfs)
        if not len(self.coders):
            return torch.cat(imgs, dim=2)
        codes = []
        for img, coder in zip(imgs, self.coders):
            b, s, f = img.shape
            codes.append(coder(img.reshape(b * s, f)).reshape(b, s, coder.atoms))
        return torch.cat(codes, dim=2)

    def forward(self, x: Tensor) -> Tensor:
        z = self.normalise(x)
        return self.finish(z, [e(s)[0] for e, s in zip(self.emds, self.emd_inputs(z))])


class ToyModel(nn.Module):
    """The TextureModel interface: cfg, pre, head, state_shape, zero_state, forward."""

    def __init__(self, pre: ToyPre, n_classes: int, hidden: int = 8, layers: int = 1,
                 cfg: ToyCfg | None = None) -> None:
        super().__init__()
        self.cfg = cfg or ToyCfg(window=pre.window, hop=pre.window)
        self.pre = pre
        self.head = LSTMHead(pre.n_features, n_classes, hidden, layers, 0.0)

    @property
    def state_shape(self) -> tuple[int, int]:
        return self.head.layers, self.head.hidden

    def zero_state(self, batch: int) -> tuple[Tensor, Tensor]:
        layers, hidden = self.state_shape
        z = torch.zeros(layers, batch, hidden)
        return z, z.clone()

    def forward(self, x: Tensor, h: Tensor, c: Tensor):
        logits, h, c = self.head(self.pre(x), h, c)
        return torch.softmax(logits, dim=1), h, c


def windows(n: int, window: int = 20, seed: int = 0) -> np.ndarray:
    """(n, window, C) float32: a decaying tone on the signal, slow pressure, noisy electrode."""
    rng = np.random.default_rng(seed)
    t = np.arange(window * R) / (100.0 * R)
    f = rng.uniform(20, 150, (n, 1))
    sig = np.sin(2 * np.pi * f * t + rng.uniform(0, 6, (n, 1))) * rng.uniform(0.5, 2, (n, 1))
    sig = sig + 0.1 * rng.standard_normal(sig.shape)
    frames = sig.reshape(n, window, R) * 300 + 2000
    tf = np.arange(window) / 100.0
    pdc = 1000 + 200 * np.sin(2 * np.pi * rng.uniform(0.5, 3, (n, 1)) * tf) \
        + 5 * rng.standard_normal((n, window))
    ele = 3000 + 40 * rng.standard_normal((n, window))
    return np.concatenate([frames, pdc[..., None], ele[..., None]], axis=2).astype(np.float32)


def build(coded: bool = True, seed: int = 0, n_classes: int = 3, hidden: int = 8,
          layers: int = 1) -> ToyModel:
    """A toy model with statistics from its own windows; dictionaries learned by scikit-learn's
    ``MiniBatchDictionaryLearning`` on the images of training windows (``coded``)."""
    torch.manual_seed(seed)
    x = torch.from_numpy(windows(64, seed=seed))
    mean, std = x.mean((0, 1)), x.std((0, 1))
    mean[:R], std[:R] = mean[:R].mean(), x[:, :, :R].std()  # the signal's pooled statistics
    dicts = None
    if coded:
        from sklearn.decomposition import MiniBatchDictionaryLearning

        plain = ToyPre(MODS, 20, mean, std, None)
        with torch.no_grad():
            z = plain.normalise(x)
            imgs = plain.images(z, [e(s)[0] for e, s in zip(plain.emds, plain.emd_inputs(z))])
        dicts = []
        for img, m in zip(imgs, MODS):
            data = img.reshape(-1, m.features).numpy()
            mb = MiniBatchDictionaryLearning(n_components=m.atoms, batch_size=64, max_iter=5,
                                             random_state=seed).fit(data)
            dicts.append(mb.components_.astype(np.float32))
    return ToyModel(ToyPre(MODS, 20, mean, std, dicts), n_classes, hidden, layers).eval()
