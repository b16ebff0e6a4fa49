"""The models: preprocessing (normalisation + EMD features) and the classifier heads.

Everything here is torch ops that export to ONNX unchanged, so the deployed graph computes the
very features training used. Shapes: B batch, T time (window), C channels, F features,
K IMFs per EMD channel, H hidden size, L LSTM layers.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from tactile.training.config import TrainConfig
from tactile.training.emd import EMD
from tactile.training.frontend import HighRateFront

LOG_EPS = 1e-6


class Preprocess(nn.Module):
    """(B, T, C) values in the channels' units -> (B, T, C + Ce*K) features.

    Each channel is normalised with the training split's mean and std (and the ``center_index``
    channels have their mean over the window removed; the channels of each of
    ``center_groups``, a high-rate signal's sub-samples, the one mean of all their samples in
    the window: a mean per sub-sample would notch the signal at every multiple of the frame
    rate); the IMFs of the
    normalised ``emd_index`` channels (``EMD(n_imfs, n_sifts)``, over the window) are appended.

    The three stages every preprocessing module exposes (export composes them, running each
    entry of ``emds`` as a hand-built ONNX EMD graph): :meth:`normalise`, :meth:`emd_inputs`
    (one ``(B, n_k, L_k)`` tensor per entry of ``emds``), :meth:`finish` (the features from the
    normalised window and the IMFs); ``forward(x) == finish(z, [emd(s)[0] ...])``.
    """

    def __init__(
        self, mean: Tensor, std: Tensor, emd_index: list[int], n_imfs: int, n_sifts: int,
        center_index: list[int] | None = None, center_groups: list[list[int]] | None = None,
    ) -> None:
        super().__init__()
        n = int(mean.numel())
        mask = torch.zeros(n)
        mask[list(center_index or [])] = 1.0
        self.register_buffer("center_mask", mask)  # (C,) 1 where the window mean is removed
        # the groups' means by elementwise products and sums (no MatMul, which an int8 export
        # would quantise): (G, C) weights 1/len over each group, (G, C) 1 on its channels
        self.center_groups = [list(g) for g in center_groups or []]
        if self.center_groups:
            weight = torch.zeros(len(self.center_groups), n)
            for k, g in enumerate(self.center_groups):
                weight[k, g] = 1.0 / len(g)
            self.register_buffer("group_weight", weight, persistent=False)
            self.register_buffer("group_mask", (weight > 0).float(), persistent=False)
            own = mask.clone()
            own[[i for g in self.center_groups for i in g]] = 0.0
            self.register_buffer("own_mask", own, persistent=False)
        self.register_buffer("mean", mean.float().clone())  # (C,)
        self.register_buffer("std", std.float().clone())  # (C,)
        self.register_buffer("emd_index", torch.tensor(emd_index, dtype=torch.long))  # (Ce,)
        # EMD has no parameters or buffers: the state dict's keys are those of the single `emd`
        self.emds = nn.ModuleList([EMD(n_imfs, n_sifts)] if emd_index else [])
        self.n_channels = int(mean.numel())
        self.n_emd = len(emd_index) * n_imfs

    @property
    def n_features(self) -> int:
        return self.n_channels + self.n_emd

    def normalise(self, x: Tensor) -> Tensor:
        """x (B, T, C) in units -> z (B, T, C) normalised, the centre channels centred."""
        z = (x - self.mean) / self.std  # (B, T, C)
        # offsets (gravity on a tilted pen, a gyroscope's bias) say little of the surface
        if self.center_groups:  # a signal's sub-samples share one mean
            m = z.mean(dim=1, keepdim=True)  # (B, 1, C)
            shared = (m.unsqueeze(2) * self.group_weight).sum(-1)  # (B, 1, G)
            return z - m * self.own_mask - (shared.unsqueeze(-1) * self.group_mask).sum(2)
        return z - z.mean(dim=1, keepdim=True) * self.center_mask

    @property
    def centred_alone(self) -> Tensor:
        """(C,) 1 on the channels centred on their own mean (whose window mean is then 0);
        a group's channels share one mean, so each keeps its own."""
        return self.own_mask if self.center_groups else self.center_mask

    def emd_inputs(self, z: Tensor) -> list[Tensor]:
        """z (B, T, C) -> [(B, Ce, T)]: the EMD channels (empty list without EMD)."""
        if not len(self.emds):
            return []
        return [torch.index_select(z, 2, self.emd_index).transpose(1, 2)]

    def finish(self, z: Tensor, imfs: list[Tensor]) -> Tensor:
        """z (B, T, C), imfs [(B, Ce, K, T)] -> features (B, T, C + Ce*K) (z without EMD)."""
        if not imfs:
            return z
        feats = imfs[0].flatten(1, 2).transpose(1, 2)  # (B, T, Ce*K)
        return torch.cat([z, feats.to(z.dtype)], dim=2)

    def forward(self, x: Tensor) -> Tensor:
        z = self.normalise(x)
        imfs = [emd(s)[0] for emd, s in zip(self.emds, self.emd_inputs(z), strict=True)]
        return self.finish(z, imfs)


class SpectralFront(nn.Module):
    """(B, T, F) features -> (B, T', F * (K + 1)) frame features, T' = (T - frame) // hop + 1.

    In frames of ``frame`` samples every ``hop`` samples, per feature: the log power in each of
    the K = frame // 2 + 1 DFT bins of the Hann-tapered frame (``log(power + LOG_FLOOR)``; a
    gain on a channel becomes an offset), and the frame's mean (the level). A fixed grouped
    convolution (no trainable weights) followed by a trainable batch normalisation of each
    frame feature, which puts log powers and levels of every channel on one scale.
    """

    LOG_FLOOR = 1e-4  # power floor of the normalised (unit-variance) channels

    def __init__(self, n_in: int, frame: int, hop: int) -> None:
        super().__init__()
        t = torch.arange(frame, dtype=torch.float64)
        taper = torch.hann_window(frame, periodic=False, dtype=torch.float64)
        self.n_bins = frame // 2 + 1
        rows = []
        for k in range(self.n_bins):
            rows += [torch.cos(2 * math.pi * k * t / frame) * taper,
                     torch.sin(2 * math.pi * k * t / frame) * taper]
        rows.append(torch.full((frame,), 1.0 / frame, dtype=torch.float64))  # the mean
        basis = torch.stack(rows).float()  # (2K + 1, frame)
        # one copy per input feature, for a grouped convolution: (F * (2K + 1), 1, frame)
        self.register_buffer("basis", basis.repeat(n_in, 1).unsqueeze(1))
        self.n_in, self.hop = n_in, hop
        self.n_out = n_in * (self.n_bins + 1)
        self.norm = nn.BatchNorm1d(self.n_out)

    def forward(self, f: Tensor) -> Tensor:
        y = nn.functional.conv1d(f.transpose(1, 2), self.basis, stride=self.hop,
                                 groups=self.n_in)  # (B, F * (2K + 1), T')
        b, _, frames = y.shape
        y = y.reshape(b, self.n_in, 2 * self.n_bins + 1, frames)
        re, im = y[:, :, 0 : 2 * self.n_bins : 2], y[:, :, 1 : 2 * self.n_bins : 2]
        log_power = torch.log(re * re + im * im + self.LOG_FLOOR)  # (B, F, K, T')
        z = torch.cat([log_power, y[:, :, 2 * self.n_bins :]], dim=2)  # (B, F, K + 1, T')
        return self.norm(z.reshape(b, self.n_out, frames)).transpose(1, 2)


class LSTMHead(nn.Module):
    """(B, T, F) features + state (L, B, H) x 2 -> logits (B, classes) after the last step.

    With ``front='spectral'`` the LSTM runs over the :class:`SpectralFront`'s frames (dropout on
    its input too), else over the samples. With ``wide``, a linear map of the mean over the
    steps of what the LSTM reads (before its input dropout) is added to the logits.

    ``signals`` (with ``front='spectral'``): per high-rate signal the indices into F of its
    sub-sample channels, in time order. Those channels then skip the :class:`SpectralFront`
    (which would see aliases of the signal) and go to a :class:`HighRateFront` per sub-sample
    count instead (their band powers at the signal's own rate, in the same frames,
    batch-normalised); the LSTM reads the plain channels' frame features, then the signals'.
    """

    def __init__(self, n_in: int, n_classes: int, hidden: int, layers: int, dropout: float,
                 front: str = "none", frame: int = 20, frame_hop: int = 10, wide: bool = False,
                 signals: list[list[int]] | None = None):
        super().__init__()
        self.layers, self.hidden = layers, hidden
        signals = signals if front == "spectral" else None
        taken = {i for s in signals or [] for i in s}
        plain = [i for i in range(n_in) if i not in taken]
        self.front = (SpectralFront(len(plain), frame, frame_hop)
                      if front == "spectral" and plain else None)
        n_lstm = self.front.n_out if self.front is not None else (0 if signals else n_in)
        if signals:
            rates = sorted({len(s) for s in signals})
            self.high = nn.ModuleList([HighRateFront([s for s in signals if len(s) == r],
                                                     frame, frame_hop) for r in rates])
            n_high = sum(h.n_out for h in self.high)
            self.high_norm = nn.BatchNorm1d(n_high)
            self.register_buffer("plain_index", torch.tensor(plain, dtype=torch.long))
            n_lstm += n_high
        self.signals = bool(signals)
        self.in_drop = nn.Dropout(dropout if front == "spectral" else 0.0)
        self.lstm = nn.LSTM(
            n_lstm, hidden, layers, batch_first=True, dropout=dropout if layers > 1 else 0.0
        )
        self.drop = nn.Dropout(dropout)
        self.out = nn.Linear(hidden, n_classes)
        self.wide = nn.Linear(n_lstm, n_classes) if wide else None

    def frames(self, f: Tensor) -> Tensor:
        """(B, T, F) features -> (B, T', F') what the LSTM reads with a spectral front."""
        if not self.signals:
            return self.front(f)
        high = torch.cat([h(f) for h in self.high], dim=2)  # (B, T', S * (nb + 1))
        parts = [self.high_norm(high.transpose(1, 2)).transpose(1, 2)]
        if self.front is not None:
            parts.insert(0, self.front(torch.index_select(f, 2, self.plain_index)))
        return torch.cat(parts, dim=2)

    def forward(self, f: Tensor, h: Tensor, c: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        x = f
        if self.front is not None or self.signals:
            f = self.frames(f)  # (B, T', F')
            x = self.in_drop(f)
        y, (h, c) = self.lstm(x, (h, c))  # y: (B, T, H)
        logits = self.out(self.drop(y[:, -1]))
        if self.wide is not None:
            logits = logits + self.wide(f.mean(dim=1))
        return logits, h, c


class Ensemble(nn.Module):
    """``members`` heads of one kind (each an :class:`LSTMHead` of ``layers`` x ``hidden``) as
    one head. Their states are stacked on the layer axis: h, c (members * layers, B, hidden).

    In eval mode the logits are the log of the members' mean probabilities (the classifier's
    softmax then gives that mean); in training mode each member's own logits, (B, members,
    classes), so that each member is trained on its own loss (:func:`member_loss`).
    """

    def __init__(self, members: list[nn.Module]) -> None:
        super().__init__()
        self.members = nn.ModuleList(members)
        self.layers = sum(m.layers for m in members)
        self.hidden = members[0].hidden

    def forward(self, f: Tensor, h: Tensor, c: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        sizes = [m.layers for m in self.members]
        outs, hs, cs = zip(*(m(f, hk, ck) for m, hk, ck in
                             zip(self.members, h.split(sizes), c.split(sizes), strict=True)))
        stacked = torch.stack(outs, 1)  # (B, members, classes)
        if not self.training:
            log_p = torch.log_softmax(stacked, dim=2)
            stacked = torch.logsumexp(log_p, dim=1) - math.log(len(self.members))
        return stacked, torch.cat(hs), torch.cat(cs)


def member_loss(loss_fn, logits: Tensor, y: Tensor) -> Tensor:
    """The training loss of ``logits`` (..., classes) or an ensemble's (..., members,
    classes) against labels ``y`` (...): with members, the sum of each member's mean loss, so
    that each member's weights get the gradient of its own loss (training's norm clipping
    still takes all members' gradients together)."""
    if logits.dim() == y.dim() + 1:
        return loss_fn(logits.flatten(0, -2), y.flatten())
    members = logits.shape[-2]
    y = y.unsqueeze(-1).expand(*y.shape, members)
    return loss_fn(logits.flatten(0, -2), y.flatten()) * members


class LinearHead(nn.Module):
    """Baseline: logits from the log mean energy of each IMF over the window (B, Ce*K), and
    with ``signals`` (per high-rate signal the indices of its sub-sample channels) each
    signal's log band powers over the whole window at its own rate and its mean
    (:class:`HighRateFront` with one frame of ``window`` frames).

    The state passes through untouched so that both heads share one interface.
    """

    def __init__(self, n_channels: int, n_emd: int, n_classes: int,
                 signals: list[list[int]] | None = None, window: int = 0):
        super().__init__()
        self.n_channels = n_channels
        n_in = n_emd
        if signals:
            rates = sorted({len(s) for s in signals})
            self.high = nn.ModuleList([HighRateFront([s for s in signals if len(s) == r],
                                                     window, window) for r in rates])
            n_in += sum(h.n_out for h in self.high)
        self.signals = bool(signals)
        self.out = nn.Linear(n_in, n_classes)

    def forward(self, f: Tensor, h: Tensor, c: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        imfs = f[:, :, self.n_channels :]  # (B, T, Ce*K)
        energy = torch.log(imfs.pow(2).mean(dim=1) + LOG_EPS)  # (B, Ce*K)
        if self.signals:
            energy = torch.cat([energy, *(hf(f)[:, 0] for hf in self.high)], dim=1)
        return self.out(energy), h, c


class WindowFeatures(nn.Module):
    """(B, T, C) normalised channels -> (B, C * (2 + BANDS)) whole-window features: per
    channel the window's mean, log standard deviation and log energy of the mean-free,
    Hann-tapered window in :data:`BANDS` equal bands up to the Nyquist frequency, grouped
    (the means, the log standard deviations, then each band's log energies), each group
    channel by channel. No state: its DFT basis and band sums are rebuilt with the module."""

    BANDS = 5
    FLOOR = 1e-8  # of variances and band energies, on the unit-variance normalised scale

    def __init__(self, n_channels: int, window: int) -> None:
        super().__init__()
        t = torch.arange(window, dtype=torch.float64)
        k = torch.arange(window // 2 + 1, dtype=torch.float64)
        taper = torch.hann_window(window, periodic=False, dtype=torch.float64)
        angle = 2 * math.pi * k[:, None] * t[None, :] / window  # (K, T)
        # (T, 2K): the tapered cosines then sines, one product for both
        self.register_buffer("dft", (torch.cat([torch.cos(angle), torch.sin(angle)]) * taper)
                             .T.float().contiguous(), persistent=False)
        self.n_bins = len(k)
        # bin k (k / window cycles a sample) in band b when b <= 2 BANDS k / window < b + 1
        # (in integers: no edge lost to rounding), Nyquist's bin in the last band
        band = torch.clamp(torch.arange(window // 2 + 1) * 2 * self.BANDS // window,
                           max=self.BANDS - 1)
        self.register_buffer("bands", nn.functional.one_hot(band, self.BANDS).T.float(),
                             persistent=False)
        self.n_channels = n_channels
        self.n_features = n_channels * (2 + self.BANDS)

    def forward(self, z: Tensor) -> Tensor:
        # the mean-free window from the differences to its first sample: a level far above the
        # window's variation (a pressure held steady) would otherwise leave float32's rounding
        # of the mean in every sample, which the taper turns into energy at the lowest bins
        u = z - z[:, :1]
        du = u.mean(dim=1)  # (B, C)
        mean = z[:, 0] + du
        d = u - du.unsqueeze(1)
        log_std = 0.5 * torch.log((d * d).mean(dim=1) + self.FLOOR)
        y = d.transpose(1, 2) @ self.dft  # (B, C, 2K)
        re, im = y[..., : self.n_bins], y[..., self.n_bins :]
        energy = (re * re + im * im) @ self.bands.T  # (B, C, BANDS)
        bands = torch.log(energy + self.FLOOR).transpose(1, 2).flatten(1)
        return torch.cat([mean, log_std, bands], dim=1)


class WindowRegression(nn.Module):
    """(B, T, F) features -> (B, classes) logits of a logistic regression on the
    :class:`WindowFeatures` of the C normalised channels, standardised with the training
    windows' statistics (a feature that does not vary there is left out). Everything is a
    buffer: it is solved on all training windows at once (:mod:`tactile.training.blend`),
    not trained by the loop.

    ``given``: None when the first C of F are the normalised channels (the LSTM's features);
    else the column of F where the window's :class:`WindowFeatures` start, computed by the
    preprocessing and repeated at every step (a granular model's features are images or codes,
    not the window: :class:`tactile.training.granular.GranularPre`), read at the last step.
    """

    BANDS = WindowFeatures.BANDS
    FLOOR = WindowFeatures.FLOOR

    def __init__(self, n_channels: int, window: int, n_classes: int,
                 given: int | None = None) -> None:
        super().__init__()
        self.given = given
        n_features = n_channels * (2 + self.BANDS)
        if given is None:
            self.window = WindowFeatures(n_channels, window)
        self.n_channels, self.n_features = n_channels, n_features
        self.register_buffer("feature_mean", torch.zeros(n_features))
        self.register_buffer("feature_scale", torch.zeros(n_features))  # 1 / std, or 0
        self.register_buffer("coef", torch.zeros(n_features, n_classes))
        self.register_buffer("intercept", torch.zeros(n_classes))
        self._register_load_state_dict_pre_hook(_without_constants)

    def features(self, f: Tensor) -> Tensor:
        """(B, T, F) -> (B, C * (2 + BANDS)): :class:`WindowFeatures`."""
        if self.given is not None:
            return f[:, -1, self.given : self.given + self.n_features]
        return self.window(f[:, :, : self.n_channels])

    def forward(self, f: Tensor) -> Tensor:
        x = (self.features(f) - self.feature_mean) * self.feature_scale
        return x @ self.coef + self.intercept


def _without_constants(state: dict, prefix: str, *args) -> None:
    """A state dict saved while :class:`WindowRegression` stored its constants (the DFT basis
    and the band sums, rebuilt with the module) loads without them."""
    for name in ("dft", "bands"):
        state.pop(prefix + name, None)


class Blend(nn.Module):
    """A recurrent head and a :class:`WindowRegression`, their log-probabilities mixed:
    ``(1 - mix) * log_softmax(head) + mix * log_softmax(regression)`` in eval mode (the
    classifier's softmax then gives their normalised weighted geometric mean); in training
    mode the head's own logits (the regression is solved apart). ``mix``, the regression's
    weight (a buffer), is chosen on the validation windows (:mod:`tactile.training.blend`); 0
    until then. The state is the head's. The head reads the features before the regression's
    own (:attr:`n_head`).
    """

    def __init__(self, head: nn.Module, regression: WindowRegression) -> None:
        super().__init__()
        self.recurrent, self.regression = head, regression
        self.layers, self.hidden = head.layers, head.hidden
        self.register_buffer("mix", torch.zeros(()))

    @property
    def n_head(self) -> int | None:
        """How many features the head reads: those before the window's features a granular
        model appends (:class:`WindowRegression`'s ``given``); None: all of them."""
        return self.regression.given

    @property
    def state_shape(self) -> tuple[int, int]:
        return getattr(self.recurrent, "state_shape", (self.layers, self.hidden))

    def forward(self, f: Tensor, h: Tensor, c: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        # (contiguous: the head computes as it would without the regression's features)
        head_f = f if self.n_head is None else f[..., : self.n_head].contiguous()
        logits, h, c = self.recurrent(head_f, h, c)
        if self.training:
            return logits, h, c
        mixed = ((1 - self.mix) * torch.log_softmax(logits, dim=1)
                 + self.mix * torch.log_softmax(self.regression(f), dim=1))
        return mixed, h, c


class Classifier(nn.Module):
    """What every model shares: ``pre`` (window -> features), ``head`` (features + state ->
    logits + state), ``n_classes`` and ``state_shape`` (set by the subclass); the zero state,
    the logits and ``forward(x, h, c) -> (probabilities (B, classes), h, c)``."""

    pre: nn.Module
    head: nn.Module
    n_classes: int

    @property
    def state_shape(self) -> tuple[int, int]:
        raise NotImplementedError

    def zero_state(self, batch: int) -> tuple[Tensor, Tensor]:
        layers, width = self.state_shape
        z = torch.zeros(layers, batch, width)
        return z, z.clone()

    def logits(self, x: Tensor, h: Tensor, c: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return self.head(self.pre(x), h, c)

    def fit_features(self, train: Tensor) -> None:
        """Statistics of the training windows' features that the model keeps, computed once
        before training (none here; a granular F-RNN's input scale)."""

    def augment_gain(self, f: Tensor, amount: float, gen: torch.Generator) -> Tensor:
        """Training's gain augmentation (``augment_gain``) on the features ``f (B, S, T, F)``
        of B units of S windows computed once by ``pre``: a random gain in ``1 +/- amount``
        (drawn with ``gen``) per window and feature."""
        shape = (*f.shape[:2], 1, f.shape[-1])
        return f * (1 + amount * (2 * torch.rand(shape, generator=gen) - 1)).to(f.device)

    def offset_scale(self) -> Tensor | None:
        """(F,) the half-widths of training's random offsets (``augment_offset``) on the
        features ``pre`` computes; None when no feature takes one (here: the granular models,
        whose features are images or codes, not channel levels)."""
        return None

    def forward(self, x: Tensor, h: Tensor, c: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        logits, h, c = self.logits(x, h, c)
        return torch.softmax(logits, dim=1), h, c


class TextureModel(Classifier):
    """The whole classifier: raw window in units -> class probabilities, with explicit state.

    ``forward(x, h, c)``: x (B, T, C) float32 in the channels' units, h and c (L, B, H);
    returns probabilities (B, classes) and the new h, c. In ``window`` state mode callers pass
    zeros; in ``carry`` mode the previous window's h, c.
    """

    def __init__(self, cfg: TrainConfig, n_classes: int, mean: Tensor, std: Tensor,
                 emd_index: list[int], center_index: list[int] | None = None,
                 signals: list[list[int]] | None = None,
                 center_groups: list[list[int]] | None = None):
        super().__init__()
        self.cfg, self.n_classes = cfg, n_classes
        self.signals = [list(s) for s in signals or []]
        # a signal with a centred sub-sample is centred whole, on the mean of all its samples
        # (center_groups: as a checkpoint recorded them; [] in one saved before, which
        # centred each sub-sample by itself)
        centred = set(center_index or [])
        groups = ([s for s in self.signals if centred & set(s)] if center_groups is None
                  else [list(g) for g in center_groups])
        centred |= {i for g in groups for i in g}
        self.pre = Preprocess(mean, std, emd_index, cfg.emd_imfs, cfg.emd_sifts,
                              sorted(centred), groups)
        if cfg.model == "lstm":
            heads = [LSTMHead(self.pre.n_features, n_classes, cfg.hidden, cfg.layers,
                              cfg.dropout, cfg.front, cfg.frame, cfg.frame_hop, cfg.wide,
                              signals)
                     for _ in range(cfg.ensemble)]
            self.head = heads[0] if cfg.ensemble == 1 else Ensemble(heads)
            if cfg.blends:
                self.head = Blend(self.head, WindowRegression(self.pre.n_channels, cfg.window,
                                                              n_classes))
        else:
            self.head = LinearHead(self.pre.n_channels, self.pre.n_emd, n_classes, signals,
                                   cfg.window)

    def augment_gain(self, f: Tensor, amount: float, gen: torch.Generator) -> Tensor:
        """:meth:`Classifier.augment_gain`, with one gain for all the sub-sample channels of
        each high-rate signal (that of its first): a gain per sub-sample would modulate the
        signal at the frame rate, lines at every multiple of it that the signal never had."""
        shape = (*f.shape[:2], 1, f.shape[-1])
        gain = 1 + amount * (2 * torch.rand(shape, generator=gen) - 1)
        for idx in self.signals:
            gain[..., idx] = gain[..., idx[:1]]
        return f * gain.to(f.device)

    @property
    def state_shape(self) -> tuple[int, int]:
        """(layers, hidden) of the state tensors (an ensemble's members' layers stacked);
        (1, 1) for the linear head."""
        if isinstance(self.head, (LSTMHead, Ensemble, Blend)):
            return self.head.layers, self.head.hidden
        return 1, 1

    def offset_scale(self) -> Tensor | None:
        """``augment_offset`` on the normalised channels whose level the model sees, 0 on the
        centred ones (their window mean is removed before the model, so no offset reaches it
        at test) and on the EMD features (oscillations about zero); None when nothing moves
        (off, or every channel centred)."""
        if not self.cfg.augment_offset:
            return None
        scale = torch.zeros(self.pre.n_features)
        scale[: self.pre.n_channels] = self.cfg.augment_offset * (1 - self.pre.center_mask)
        return scale if bool(scale.any()) else None
