"""The granular-media paper's preprocessing: per-modality EMD, data images, sparse codes.

:class:`GranularPre` turns a window ``x (B, T, C)`` in the channels' units into the features
of the granular models, in three stages that export composes (``docs/granular.md``):

1. :meth:`~GranularPre.normalise`: ``z = (x - mean) / std`` with the training split's
   statistics; the channels of one high-rate signal share one pooled mean and std
   (:func:`pooled_stats`). No centring.
2. :meth:`~GranularPre.emd_inputs`: per modality with ``imfs > 0`` its units at the
   modality's rate, ``(B, n, T * r)`` (a high-rate signal unpacked by a reshape); the
   ``EMD(imfs, emd_sifts)`` modules in :attr:`~GranularPre.emds` decompose them.
3. :meth:`~GranularPre.finish`: the data images, one per step (one step per frame; steps whose
   image would start before the window are dropped: S = T - max ceil(steps / r) + 1): at step
   t a modality's image holds its last ``steps`` samples at its own rate ending with frame t,
   feature order (unit, IMF, time) flattened; imfs = 0 uses the normalised values. Then, by
   ``mode``: ``codes`` (sf_rnn, sparse_linear) one :class:`SparseCoder` per modality over
   the image, ``(B, S, sum atoms)``; ``images`` (f_rnn) the images ``(B, S, sum features)``;
   ``energy`` (linear) one row per window ``(B, 1, F)``: the log mean energy of each IMF of
   each unit (imfs = 0: the mean and the log standard deviation of each unit). With the
   blended regression (``blend='on'``) the window's whole-window features follow at every
   step (``window_features``): only the regression reads them.

Dictionaries are learned from training images only by scikit-learn's
``MiniBatchDictionaryLearning`` (:func:`learn_dictionaries`) and live in the coders' buffers,
so a checkpoint's state dict holds them.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from tactile.training.config import TrainConfig
from tactile.training.emd import EMD
from tactile.training.modality import ModalityLayout, Signals, n_steps
from tactile.training.model import Blend, Classifier, WindowFeatures, WindowRegression
from tactile.training.sparse import SparseCoder, default_n_nonzero

LOG_EPS = 1e-6
# Images spanning up to this many frames are cut from the signal with slices; longer ones with
# one gather (fewer nodes in the exported graph)
MAX_SLICES = 8
GAIN_SCALE, GAIN_LOG_ENERGY, GAIN_LOG_STD = 0, 1, 2  # how a gain reaches a feature
MODES = {"sf_rnn": "codes", "sparse_linear": "codes", "f_rnn": "images", "linear": "energy"}
DICTIONARY_ROWS = 20_000
"""At most this many training image rows (window, step) are drawn, seeded, to learn each
dictionary: 100 rows per atom for the largest dictionary (200 atoms) and far more than the
176 features of a vibration image, while one fit stays well under a minute on one core.
Consecutive steps of one window overlap (a pressure image shares 4 of its 5 frames with the
next), so more rows of the same windows add little."""


def pooled_stats(x: np.ndarray, channels: tuple[str, ...],
                 signals: Signals) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel mean and std (C,) float32 over training windows ``x (N, T, C)``, except
    that the channels of each high-rate signal share the mean and std of all their values
    pooled (per-sub-sample statistics would distort the signal). A constant unit gets std 1."""
    flat = x.reshape(-1, x.shape[-1]).astype(np.float64)
    mean, std = flat.mean(0), flat.std(0)
    for _, names in signals:
        idx = [channels.index(c) for c in names]
        mean[idx] = flat[:, idx].mean()
        std[idx] = flat[:, idx].std()
    std[std < 1e-8] = 1.0
    return mean.astype(np.float32), std.astype(np.float32)


class GranularPre(nn.Module):
    """(B, T, C) window in units -> features (see the module's text), for ``mode`` one of
    ``codes``, ``images``, ``energy``.

    Args:
        layout: the modalities (:func:`tactile.training.modality.resolve`).
        mean, std: (C,) normalisation (:func:`pooled_stats`).
        window: T, frames per window; emd_sifts: sifts per IMF.
        window_features: append the normalised window's
            :class:`~tactile.training.model.WindowFeatures` (over all C channels) to every
            step's features, after the head's :attr:`n_features` (what a blended model's
            regression reads: :class:`~tactile.training.model.WindowRegression`'s ``given``);
            not in ``energy`` mode.
    """

    def __init__(self, layout: tuple[ModalityLayout, ...], mean: Tensor, std: Tensor,
                 window: int, emd_sifts: int, mode: str, window_features: bool = False) -> None:
        super().__init__()
        self.layout, self.mode, self.window = tuple(layout), mode, window
        self.window_features = (WindowFeatures(int(mean.numel()), window)
                                if window_features and mode != "energy" else None)
        self.register_buffer("mean", mean.float().clone())  # (C,)
        self.register_buffer("std", std.float().clone())  # (C,)
        self.steps = n_steps(self.layout, window)  # S
        self.emds = nn.ModuleList(EMD(m.imfs, emd_sifts) for m in self.layout if m.imfs > 0)
        first = max(m.frames for m in self.layout) - 1  # the frame of the first step
        self.image_starts = []  # per modality, the first sample of the first step's image
        for k, m in enumerate(self.layout):
            self.register_buffer(f"index_{k}", torch.tensor(m.index, dtype=torch.long),
                                 persistent=False)
            # samples of each step's image at the modality's rate: (S * steps,)
            start = (first + 1) * m.r - m.steps
            self.image_starts.append(start)
            pos = start + m.r * torch.arange(self.steps)[:, None] + torch.arange(m.steps)
            self.register_buffer(f"image_{k}", pos.flatten(), persistent=False)
        self.coders = nn.ModuleList(
            SparseCoder(np.zeros((m.atoms, m.features), np.float32), self.n_nonzero(m))
            for m in self.layout) if mode == "codes" else None
        owner, kind = self._gain_map()
        self.register_buffer("gain_owner", owner, persistent=False)  # (F,) modality
        self.register_buffer("gain_kind", kind, persistent=False)  # (F,) GAIN_* of a feature

    def _gain_map(self) -> tuple[Tensor, Tensor]:
        """Per feature the head reads (:attr:`n_features` of :meth:`forward`'s output), the
        modality it comes from and how a gain g on that modality's normalised channels
        reaches it (:meth:`apply_gain`)."""
        owner, kind = [], []
        for k, m in enumerate(self.layout):
            if self.mode == "codes":
                kinds = [GAIN_SCALE] * m.atoms
            elif self.mode == "images":
                kinds = [GAIN_SCALE] * m.features
            elif m.imfs > 0:  # log mean energy of each IMF of each unit
                kinds = [GAIN_LOG_ENERGY] * (m.n * m.imfs)
            else:  # per unit: its mean, its log standard deviation
                kinds = [GAIN_SCALE, GAIN_LOG_STD] * m.n
            owner += [k] * len(kinds)
            kind += kinds
        return torch.tensor(owner, dtype=torch.long), torch.tensor(kind, dtype=torch.long)

    def apply_gain(self, f: Tensor, gains: Tensor) -> Tensor:
        """The features of a window whose channels were scaled about their training mean by
        one gain per modality, from the features ``f (..., F)`` of the window itself:
        ``gains (..., M)``, broadcast over f's other axes (e.g. (B, 1, M) for f (B, S, F)).

        Exact because every stage is scale-equivariant: ``z`` scales with the gain, so do
        the EMD's IMFs (sifting is linear in the signal and blind to an offset), the images,
        and the OMP codes (the atoms picked by the largest correlation stay the same, the
        coefficients scale); a log mean energy ``log(E + 1e-6)`` becomes
        ``log(g^2 E + 1e-6)``, a unit's mean scales, and its ``0.5 log(var + 1e-6)`` becomes
        ``0.5 log(g^2 var + 1e-6)``. Training applies it to the features computed once,
        instead of computing them again every batch. The window's features after the head's
        (``window_features``) pass unchanged: only the blended regression reads them, never
        in training."""
        g = torch.index_select(gains, -1, self.gain_owner)  # (..., F)
        if self.window_features is not None:
            n = self.n_features
            return torch.cat([f[..., :n] * g, f[..., n:]], dim=-1)
        if self.mode != "energy":  # codes and images scale
            return f * g
        kind = self.gain_kind
        out = torch.where(kind == GAIN_SCALE, f * g, f)
        # the energy under each log feature, scaled by g^2: log energies E, log std var
        power = torch.where(kind == GAIN_LOG_STD, 2 * f, f)
        energy = (torch.exp(power) - LOG_EPS).clamp_min(0) * g * g
        logged = torch.log(energy + LOG_EPS)
        return torch.where(kind == GAIN_LOG_ENERGY, logged,
                           torch.where(kind == GAIN_LOG_STD, 0.5 * logged, out))

    @staticmethod
    def n_nonzero(m: ModalityLayout) -> int:
        """The modality's non-zeros: its ``nonzero``, or scikit-learn's default."""
        return m.nonzero or default_n_nonzero(m.features, m.atoms)

    @property
    def image_features(self) -> tuple[int, ...]:
        return tuple(m.features for m in self.layout)

    @property
    def n_features(self) -> int:
        if self.mode == "codes":
            return sum(m.atoms for m in self.layout)
        if self.mode == "images":
            return sum(self.image_features)
        return sum(m.n * (m.imfs if m.imfs else 2) for m in self.layout)

    @property
    def needs_dictionaries(self) -> bool:
        return self.mode == "codes"

    # --- the three stages -----------------------------------------------------------------

    def normalise(self, x: Tensor) -> Tensor:
        """x (B, T, C) in units -> z (B, T, C)."""
        return (x - self.mean) / self.std

    def _units(self, z: Tensor, k: int) -> Tensor:
        """Modality k's units at its own rate: (B, T, C) -> (B, n, T * r)."""
        m = self.layout[k]
        sel = torch.index_select(z, 2, getattr(self, f"index_{k}"))  # (B, T, n * r)
        b, t = sel.shape[0], sel.shape[1]
        return sel.reshape(b, t, m.n, m.r).permute(0, 2, 1, 3).reshape(b, m.n, t * m.r)

    def emd_inputs(self, z: Tensor) -> list[Tensor]:
        """One (B, n_k, L_k) per entry of :attr:`emds`: the modalities with imfs > 0."""
        return [self._units(z, k) for k, m in enumerate(self.layout) if m.imfs > 0]

    def _signals(self, z: Tensor, imfs: list[Tensor]) -> list[Tensor]:
        """Per modality (B, n, max(imfs, 1), L): its IMFs, or its normalised units."""
        out, j = [], 0
        for k, m in enumerate(self.layout):
            if m.imfs > 0:
                out.append(imfs[j].to(z.dtype))
                j += 1
            else:
                out.append(self._units(z, k)[:, :, None, :])
        return out

    def _image(self, s: Tensor, k: int) -> Tensor:
        """(B, n, K, L) -> (B, S, n * K * steps), feature order (unit, IMF, time)."""
        m = self.layout[k]
        b, n, kk = _batch(s), m.n, max(m.imfs, 1)
        q = -(-m.steps // m.r)  # frames an image spans
        if q <= MAX_SLICES:  # slices of whole frames, no gather (a gather is slow on a last axis)
            # image_k's samples, start + r * step + (0 .. steps - 1), are the last steps
            # samples of frames step .. step + q - 1, counted from the frame at f0
            f0 = self.image_starts[k] + m.steps - q * m.r
            fr = s.narrow(3, f0, (self.steps + q - 1) * m.r)
            fr = fr.reshape(b, n, kk, self.steps + q - 1, m.r)
            img = fr.narrow(3, 0, self.steps) if q == 1 else torch.cat(
                [fr.narrow(3, i, self.steps) for i in range(q)], dim=4)
            img = img[..., q * m.r - m.steps :].permute(0, 3, 1, 2, 4)
        else:  # long images: each step's samples gathered
            img = torch.index_select(s, 3, getattr(self, f"image_{k}"))  # (B, n, K, S * steps)
            img = img.reshape(b, n, kk, self.steps, m.steps).permute(0, 3, 1, 2, 4)
        return img.reshape(b, self.steps, n * kk * m.steps)

    def images_from(self, z: Tensor, imfs: list[Tensor]) -> Tensor:
        """The data images of every modality, concatenated: (B, S, sum features)."""
        sig = self._signals(z, imfs)
        return torch.cat([self._image(s, k) for k, s in enumerate(sig)], dim=2)

    def with_window(self, images: Tensor, z: Tensor) -> Tensor:
        """The images (B, S, sum features), with ``window_features`` the window's
        :class:`~tactile.training.model.WindowFeatures` of ``z`` appended to every step."""
        if self.window_features is None:
            return images
        w = self.window_features(z.to(self.window_features.dft.dtype)).to(images.dtype)
        return torch.cat([images, w[:, None, :].expand(-1, images.shape[1], -1)], dim=2)

    def post(self, images: Tensor) -> Tensor:
        """(B, S, sum features) images -> the head's features: codes (B, S, sum atoms) in
        ``codes`` mode, the images themselves in ``images`` mode (the window's features after
        them, with ``window_features``, passed on as they are)."""
        if self.mode != "codes":
            return images
        # the sizes from the images' own shape, as the exporter traces them: the coders'
        # inputs keep unknown sizes in the graph (a SparseCode function of several coders holds
        # every coder's body) and the codes the sizes the exporter gives a pooled head
        b, s = images.shape[0], images.shape[1]
        if self.window_features is not None:  # the images alone, laid out as without them
            window, images = images[:, :, sum(self.image_features):], \
                images[:, :, : sum(self.image_features)].contiguous()
        flat = images.reshape(b * s, images.shape[2])
        out, at = [], 0
        for coder, f in zip(self.coders, self.image_features):
            out.append(coder(flat[:, at : at + f]).reshape(b, s, coder.atoms))
            at += f
        if self.window_features is not None:
            out.append(window)
        return torch.cat(out, dim=2)

    def energy(self, z: Tensor, imfs: list[Tensor]) -> Tensor:
        """(B, 1, F): per modality and unit, the log mean energy of each IMF over the window
        (imfs = 0: the unit's mean and log standard deviation)."""
        out = []
        for m, s in zip(self.layout, self._signals(z, imfs)):
            if m.imfs > 0:
                out.append(torch.log(s.pow(2).mean(dim=3) + LOG_EPS).flatten(1))  # (B, n*K)
            else:
                mu = s.mean(dim=3)  # (B, n, 1)
                var = (s - mu[..., None]).pow(2).mean(dim=3)
                out.append(torch.cat([mu, 0.5 * torch.log(var + LOG_EPS)], 2).flatten(1))
        return torch.cat(out, dim=1)[:, None, :]

    def finish(self, z: Tensor, imfs: list[Tensor]) -> Tensor:
        """z (B, T, C) and imfs[k] (B, n_k, K_k, L_k) (the EMDs of :meth:`emd_inputs`) ->
        features (B, S, n_features), or (B, 1, n_features) in ``energy`` mode; with
        ``window_features`` (B, S, n_features + its n_features), the window's after the
        head's."""
        if self.mode == "energy":
            return self.energy(z, imfs)
        return self.post(self.with_window(self.images_from(z, imfs), z))

    def decompose(self, z: Tensor) -> list[Tensor]:
        return [emd(s)[0] for emd, s in zip(self.emds, self.emd_inputs(z))]

    def images(self, x: Tensor) -> Tensor:
        """x (B, T, C) -> the data images (B, S, sum features), before any coding (the
        window's features after them, with ``window_features``)."""
        z = self.normalise(x)
        return self.with_window(self.images_from(z, self.decompose(z)), z)

    def forward(self, x: Tensor) -> Tensor:
        z = self.normalise(x)
        return self.finish(z, self.decompose(z))

    def set_dictionaries(self, dictionaries: list[np.ndarray]) -> None:
        """Put one learned dictionary (atoms_m, features_m) per modality into the coders."""
        self.coders = nn.ModuleList(  # each coder keeps a C-ordered copy, as a checkpoint
            SparseCoder(np.asarray(d, np.float32), self.n_nonzero(m))
            for d, m in zip(dictionaries, self.layout))


def _batch(x: Tensor) -> int:
    """The batch size for a reshape: x's, or -1 while the exporter traces, so that every other
    size of the shape is a constant of the graph (no shape arithmetic at run time)."""
    return -1 if torch.jit.is_tracing() else x.shape[0]


def sample_rows(n_rows: int, cap: int, seed: int) -> np.ndarray:
    """Sorted indices of ``min(cap, n_rows)`` rows drawn without replacement from ``seed``."""
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(n_rows, size=min(cap, n_rows), replace=False))


def fit_dictionary(rows: np.ndarray, m: ModalityLayout, seed: int) -> np.ndarray:
    """``MiniBatchDictionaryLearning`` on image rows (N, features) float32 -> the dictionary
    (atoms, features) float32 (``components_``)."""
    from sklearn.decomposition import MiniBatchDictionaryLearning

    mbdl = MiniBatchDictionaryLearning(
        n_components=m.atoms, transform_algorithm="omp",
        transform_n_nonzero_coefs=m.nonzero or None, random_state=seed)
    mbdl.fit(np.ascontiguousarray(rows, dtype=np.float32))
    return np.ascontiguousarray(mbdl.components_, dtype=np.float32)


def learn_dictionaries(pre: GranularPre, train_images: Tensor, seed: int, dist,
                       cap: int = DICTIONARY_ROWS) -> int:
    """Learn each modality's dictionary from the training split's images ``(N, S, sum
    features)`` (only those: the caller passes no other split) on rank 0, broadcast them, and
    put them into ``pre``'s coders. Returns how many image rows (window, step) each was
    learned from: the same rows for every modality."""
    n_rows = train_images.shape[0] * train_images.shape[1]
    pick = sample_rows(n_rows, cap, seed)
    dicts = []
    at = 0
    for m in pre.layout:
        if dist.is_main:
            flat = train_images.reshape(n_rows, -1)[:, at : at + m.features]
            dicts.append(fit_dictionary(flat[torch.from_numpy(pick)].numpy(), m, seed))
        else:
            dicts.append(np.zeros((m.atoms, m.features), np.float32))
        at += m.features
    pre.set_dictionaries(list(dist.broadcast(*dicts)))
    return len(pick)


# --- the heads: features (B, S, F) + state -> logits -------------------------------------


class SFRNNHead(nn.Module):
    """SF-RNN (the paper's sec. II.B-C, D.d): codes (B, S, sum atoms) -> batch normalisation
    of each code -> fully connected fusion layer (sum atoms -> hidden) with ReLU -> dropout ->
    LSTM (``layers`` x ``hidden``, dropout between layers) over the S steps -> the last step's
    output -> dropout -> linear -> logits. State (layers, B, hidden) x 2."""

    def __init__(self, n_in: int, n_classes: int, hidden: int, layers: int, dropout: float):
        super().__init__()
        self.layers, self.hidden = layers, hidden
        self.norm = nn.BatchNorm1d(n_in)
        self.fuse = nn.Linear(n_in, hidden)
        self.drop = nn.Dropout(dropout)
        self.lstm = nn.LSTM(hidden, hidden, layers, batch_first=True,
                            dropout=dropout if layers > 1 else 0.0)
        self.out = nn.Linear(hidden, n_classes)

    @property
    def state_shape(self) -> tuple[int, int]:
        return self.layers, self.hidden

    def forward(self, f: Tensor, h: Tensor, c: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        b, s, n = f.shape
        g = self.norm(f.reshape(b * s, n)).reshape(b, s, n)
        g = self.drop(torch.relu(self.fuse(g)))  # (B, S, H)
        y, (h, c) = self.lstm(g, (h, c))
        return self.out(self.drop(y[:, -1])), h, c


def input_scale(images: Tensor) -> Tensor:
    """The scale of each feature of the data images ``(N, S, F)`` of the training windows,
    ``(F,)``: the median over the windows (of an even count, the lower middle one) of the
    feature's RMS over the window's S steps; the RMS over every window instead where that
    median is below 1e-3 of it (a feature that is 0 in most windows, e.g. an IMF the
    decomposition seldom reaches), 1 where the feature is always 0.

    The median, not the standard deviation over all windows (batch normalisation's scale),
    because loudness is heavy-tailed across windows: on the BioTac's vibration the typical
    window's RMS is 1/35 of the standard deviation, which the few loud windows (contact,
    sliding) set; scaled by that, the typical window reaches the LSTM at 1/35 of unit size,
    where its gates are nearly linear and a zero-mean oscillation averages away."""
    # (N, F), in float64 a chunk of windows at a time (a copy of every image is ~0.4 GB)
    rms = torch.cat([c.double().pow(2).mean(dim=1) for c in images.split(4096)]).sqrt()
    overall = rms.pow(2).mean(dim=0).sqrt()  # (F,)
    typical = rms.median(dim=0).values if len(rms) else overall
    scale = torch.where(typical >= 1e-3 * overall, typical, overall)
    return torch.where(scale > 0, scale, torch.ones_like(scale)).float()


class ForgetBiasLSTM(nn.LSTM):
    """``nn.LSTM`` whose forget gates start with bias 1 (``bias_ih`` 1, ``bias_hh`` 0 in the
    forget rows), as TensorFlow's LSTM cells (``forget_bias=1.0``) and Jozefowicz et al.
    (2015); kept by ``reset_parameters``, so a refit starts the same way. The state dict and
    the exported ONNX ``LSTM`` node are those of ``nn.LSTM``."""

    FORGET_BIAS = 1.0

    def reset_parameters(self) -> None:
        super().reset_parameters()
        rows = slice(self.hidden_size, 2 * self.hidden_size)  # gate order i, f, g, o
        with torch.no_grad():
            for layer in range(self.num_layers):
                getattr(self, f"bias_ih_l{layer}")[rows].fill_(self.FORGET_BIAS)
                getattr(self, f"bias_hh_l{layer}")[rows].zero_()


class FRNNHead(nn.Module):
    """F-RNN (the paper's sec. II.D.c, after Jain et al.): per modality m its images
    (B, S, features_m), each feature divided by its input scale (``scale``,
    :func:`input_scale` of the training windows' images, set by :meth:`fit_scale` before
    training) -> its own LSTM (``layers`` x ``hidden``, dropout between layers, forget-gate
    bias 1: :class:`ForgetBiasLSTM`); at every step the M outputs concatenated -> fully
    connected fusion layer (M x hidden -> hidden) with ReLU; the last step's fused vector ->
    dropout -> linear -> logits. State (layers, B, M x hidden) x 2: modality m's LSTM state is
    the m-th block of ``hidden``."""

    def __init__(self, sizes: tuple[int, ...], n_classes: int, hidden: int, layers: int,
                 dropout: float):
        super().__init__()
        self.sizes, self.layers, self.hidden = tuple(sizes), layers, hidden
        self.register_buffer("scale", torch.ones(sum(self.sizes)))  # (F,) per feature
        self.lstms = nn.ModuleList(
            ForgetBiasLSTM(n, hidden, layers, batch_first=True,
                           dropout=dropout if layers > 1 else 0.0)
            for n in self.sizes)
        self.fuse = nn.Linear(len(self.sizes) * hidden, hidden)
        self.drop = nn.Dropout(dropout)
        self.out = nn.Linear(hidden, n_classes)

    @property
    def state_shape(self) -> tuple[int, int]:
        return self.layers, len(self.sizes) * self.hidden

    def fit_scale(self, f: Tensor) -> None:
        """Set the input scale of every feature from the training windows' images
        ``f (N, S, sum features)``."""
        self.scale.copy_(input_scale(f))

    def forward(self, f: Tensor, h: Tensor, c: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        f = f / self.scale
        ys, hs, cs, at = [], [], [], 0
        for k, (n, lstm) in enumerate(zip(self.sizes, self.lstms)):
            blk = slice(k * self.hidden, (k + 1) * self.hidden)
            y, (hk, ck) = lstm(f[:, :, at : at + n],
                               (h[:, :, blk].contiguous(), c[:, :, blk].contiguous()))
            ys.append(y)
            hs.append(hk)
            cs.append(ck)
            at += n
        fused = torch.relu(self.fuse(torch.cat(ys, dim=2)))  # (B, S, H)
        return self.out(self.drop(fused[:, -1])), torch.cat(hs, 2), torch.cat(cs, 2)


class PooledLinearHead(nn.Module):
    """A linear classifier on features pooled over the window's steps: ``abs_mean`` (sparse
    linear: the mean magnitude of each code over the S steps, (B, sum atoms)) or ``mean`` (the
    linear baseline: its single row (B, 1, F)). The pooled vector is standardised by a batch
    normalisation without learned scale or shift (in evaluation a fixed affine map, so the
    classifier stays linear in the pooled features), then one ``Linear`` -> logits. The state
    passes through untouched ((1, B, 1) x 2)."""

    def __init__(self, n_in: int, n_classes: int, pool: str):
        super().__init__()
        self.pool = pool
        # the linear baseline is fitted to convergence on all its training windows at once
        # (tactile.training.loop.full_batch): mini-batch Adam left it short of the optimum of
        # its convex objective (docs/granular.md); the sparse linear model's 400-odd pooled
        # codes train with Adam, whose early-stopped path regularises them
        self.full_batch = pool == "mean"
        self.norm = nn.BatchNorm1d(n_in, affine=False)
        self.out = nn.Linear(n_in, n_classes)

    @property
    def state_shape(self) -> tuple[int, int]:
        return 1, 1

    def pooled(self, f: Tensor) -> Tensor:
        """(B, S, F) features -> (B, F) pooled over the steps."""
        return f.abs().mean(dim=1) if self.pool == "abs_mean" else f.mean(dim=1)

    def set_norm(self, pooled: Tensor) -> None:
        """The standardisation's statistics set to those of ``pooled`` (N, F) exactly (what
        batch normalisation's running statistics approach over an epoch of batches)."""
        with torch.no_grad():
            self.norm.running_mean.copy_(pooled.mean(0))
            self.norm.running_var.copy_(pooled.var(0) if len(pooled) > 1
                                        else torch.ones_like(pooled[0]))

    def classify(self, pooled: Tensor) -> Tensor:
        """(B, F) pooled features -> logits (B, classes)."""
        return self.out(self.norm(pooled))

    def forward(self, f: Tensor, h: Tensor, c: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return self.classify(self.pooled(f)), h, c


class GranularModel(Classifier):
    """A granular-media model with :class:`~tactile.training.model.TextureModel`'s interface:
    ``forward(x, h, c)``: x (B, T, C) float32 in the channels' units, h and c
    ``(layers, B, width)`` (:attr:`state_shape`) -> probabilities (B, classes), h, c.

    Args:
        cfg: the run's config (``model`` one of sf_rnn, f_rnn, sparse_linear, linear, with
            ``modalities``); layout: its modalities resolved; mean, std: (C,).
    """

    def __init__(self, cfg: TrainConfig, n_classes: int, layout: tuple[ModalityLayout, ...],
                 mean: Tensor, std: Tensor) -> None:
        super().__init__()
        self.cfg, self.layout, self.n_classes = cfg, tuple(layout), n_classes
        self.pre = GranularPre(layout, mean, std, cfg.window, cfg.emd_sifts, MODES[cfg.model],
                               window_features=cfg.blends)
        n = self.pre.n_features
        if cfg.model == "sf_rnn":
            self.head = SFRNNHead(n, n_classes, cfg.hidden, cfg.layers, cfg.dropout)
        elif cfg.model == "f_rnn":
            self.head = FRNNHead(self.pre.image_features, n_classes, cfg.hidden, cfg.layers,
                                 cfg.dropout)
        else:
            self.head = PooledLinearHead(n, n_classes,
                                         "abs_mean" if cfg.model == "sparse_linear" else "mean")
        if self.pre.window_features is not None:  # blend: the regression beside the head
            self.head = Blend(self.head, WindowRegression(
                int(mean.numel()), cfg.window, n_classes, given=n))

    @property
    def state_shape(self) -> tuple[int, int]:
        return self.head.state_shape

    def fit_features(self, train: Tensor) -> None:
        """Statistics of the training windows' features ``(N, S, F)`` the head keeps (before
        training): the F-RNN's input scale of each feature."""
        head = self.head.recurrent if isinstance(self.head, Blend) else self.head
        if isinstance(head, FRNNHead):
            head.fit_scale(train[..., : self.pre.n_features])

    def augment_gain(self, f: Tensor, amount: float, gen: torch.Generator) -> Tensor:
        """Training's gain augmentation on the features ``f (B, S, T, F)`` computed once by
        ``pre``: a random gain in ``1 +/- amount`` (drawn with ``gen``) per window and
        modality, on the modality's channels before any feature (scaled about their training
        mean), applied to the features exactly by :meth:`GranularPre.apply_gain`."""
        g = 1 + amount * (2 * torch.rand((*f.shape[:2], 1, len(self.layout)), generator=gen) - 1)
        return self.pre.apply_gain(f, g.to(f.device))


__all__ = ["GranularPre", "GranularModel", "SFRNNHead", "FRNNHead", "PooledLinearHead",
           "ForgetBiasLSTM", "input_scale", "pooled_stats", "learn_dictionaries",
           "fit_dictionary", "sample_rows", "DICTIONARY_ROWS", "MODES"]
