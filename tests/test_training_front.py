"""The spectral front end (against numpy's FFT) and the epoch's window sampling."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tactile.errors import ConfigError
from tactile.training.config import TrainConfig
from tactile.training.model import Ensemble, LSTMHead, SpectralFront, member_loss
from tactile.training.sampling import epoch_order


def reference_frames(x: np.ndarray, frame: int, hop: int) -> np.ndarray:
    """(B, T, F) float64 -> (B, T', F * (K + 1)) with numpy: per frame and feature the log power
    of each rfft bin of the Hann-tapered frame, then the frame's mean (the order of the front)."""
    b, t, f = x.shape
    taper = np.hanning(frame)  # symmetric, as torch.hann_window(periodic=False)
    starts = range(0, t - frame + 1, hop)
    out = []
    for s in starts:
        seg = x[:, s : s + frame]  # (B, frame, F)
        power = np.abs(np.fft.rfft(seg * taper[None, :, None], axis=1)) ** 2  # (B, K, F)
        feats = np.concatenate([np.log(power + SpectralFront.LOG_FLOOR),
                                seg.mean(axis=1, keepdims=True)], axis=1)  # (B, K + 1, F)
        out.append(feats.transpose(0, 2, 1).reshape(b, -1))  # feature-major, as the front
    return np.stack(out, axis=1)


@pytest.mark.parametrize("frame, hop", [(20, 10), (7, 3), (50, 1)])
def test_spectral_front_matches_numpy_fft(frame, hop):
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3, 50, 4)) * np.array([1.0, 0.1, 3.0, 0.01])
    front = SpectralFront(4, frame, hop).eval()  # batch norm untrained: y = x / sqrt(1 + eps)
    with torch.no_grad():
        got = front(torch.tensor(x, dtype=torch.float32)).double().numpy()
    want = reference_frames(x, frame, hop) / np.sqrt(1 + front.norm.eps)
    assert got.shape == want.shape == (3, (50 - frame) // hop + 1, 4 * (frame // 2 + 2))
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=2e-4)


def test_a_gain_on_a_channel_only_shifts_its_log_powers():
    """log(g^2 P) = log P + 2 log g: a user's signal level is an offset, not a new shape."""
    rng = np.random.default_rng(1)
    x = torch.tensor(rng.normal(size=(2, 50, 1)), dtype=torch.float32)
    front = SpectralFront(1, 20, 10).eval()
    front.LOG_FLOOR = 0.0
    with torch.no_grad():
        a, b = front(x), front(3 * x)
    k = front.n_bins
    shift = (b - a).reshape(2, -1, k + 1)
    np.testing.assert_allclose(shift[..., :k].numpy(), 2 * np.log(3) / np.sqrt(1 + 1e-5),
                               atol=1e-3)


def test_epoch_order_draws_without_replacement_and_is_deterministic():
    units = np.arange(100) * 7
    full = epoch_order(units, 0, torch.Generator().manual_seed(1))
    assert sorted(full) == sorted(units)  # every unit once
    assert sorted(epoch_order(units, 500, torch.Generator().manual_seed(1))) == sorted(units)
    part = epoch_order(units, 30, torch.Generator().manual_seed(1))
    assert len(part) == 30 and len(set(part)) == 30 and set(part) <= set(units)
    again = epoch_order(units, 30, torch.Generator().manual_seed(1))
    np.testing.assert_array_equal(part, again)
    np.testing.assert_array_equal(part, full[:30])  # the same draw as a full epoch's start
    runs = np.arange(40).reshape(10, 4)  # carried state: (S, steps) runs stay whole
    got = epoch_order(runs, 3, torch.Generator().manual_seed(2))
    assert got.shape == (3, 4) and all((r[1:] - r[:-1] == 1).all() for r in got)


def test_front_settings_are_checked():
    with pytest.raises(ConfigError, match="front must be one of"):
        TrainConfig(front="fft")
    with pytest.raises(ConfigError, match="frame must be 2..window"):
        TrainConfig(frame=60)
    with pytest.raises(ConfigError, match="epoch_windows"):
        TrainConfig(epoch_windows=-1)


@pytest.mark.parametrize("front", ["spectral", "none"])
def test_the_wide_path_adds_a_linear_map_of_the_mean_lstm_input(front):
    """logits = the LSTM's last output through ``out`` + ``wide`` on the mean over steps of
    what the LSTM reads (the front's frames, or the samples with front='none'); numpy
    reference for the frames and the linear map."""
    rng = np.random.default_rng(2)
    x = rng.normal(size=(3, 50, 4))
    torch.manual_seed(0)
    head = LSTMHead(4, 5, hidden=6, layers=2, dropout=0.4, front=front, wide=True).eval()
    h = torch.zeros(2, 3, 6)
    with torch.no_grad():
        got, _, _ = head(torch.tensor(x, dtype=torch.float32), h, h.clone())
        w, b = head.wide.weight.double().numpy(), head.wide.bias.double().numpy()
        head.wide.weight.zero_(), head.wide.bias.zero_()
        deep, _, _ = head(torch.tensor(x, dtype=torch.float32), h, h.clone())
    steps = (reference_frames(x, 20, 10) / np.sqrt(1 + head.front.norm.eps)
             if front == "spectral" else x)
    want = deep.double().numpy() + steps.mean(axis=1) @ w.T + b
    np.testing.assert_allclose(got.double().numpy(), want, rtol=1e-4, atol=1e-4)
    assert w.shape == (5, steps.shape[2]) and np.abs(steps.mean(axis=1) @ w.T).max() > 0.01
    assert LSTMHead(4, 5, 6, 2, 0.4, front=front).wide is None  # wide=False: no such weights
    assert TrainConfig().wide and not TrainConfig(wide=False).wide


def test_an_ensemble_averages_its_members_probabilities_and_stacks_their_states():
    """Eval: softmax of the ensemble's logits = the mean of the members' softmax, each member
    run alone on its own share of the state (its layers of the stacked h, c), and the states
    it returns stacked in member order. Training: each member's logits, (B, members, classes);
    the loss is the sum of each member's own loss."""
    torch.manual_seed(0)
    members = [LSTMHead(4, 5, hidden=6, layers=2, dropout=0.4, front="spectral", wide=True)
               for _ in range(3)]
    ens = Ensemble(members).eval()
    assert (ens.layers, ens.hidden) == (6, 6)
    x = torch.randn(3, 50, 4)
    h, c = torch.randn(6, 3, 6), torch.randn(6, 3, 6)
    with torch.no_grad():
        logits, h_out, c_out = ens(x, h, c)
        alone = [m(x, h[2 * k : 2 * k + 2], c[2 * k : 2 * k + 2]) for k, m in enumerate(members)]
    want = np.mean([torch.softmax(a[0], 1).numpy() for a in alone], axis=0)
    np.testing.assert_allclose(torch.softmax(logits, 1).numpy(), want, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(h_out.numpy(), torch.cat([a[1] for a in alone]).numpy())
    np.testing.assert_array_equal(c_out.numpy(), torch.cat([a[2] for a in alone]).numpy())
    assert np.abs(want - torch.softmax(alone[0][0], 1).numpy()).max() > 1e-3  # members differ

    ens.train()
    torch.manual_seed(1)
    per_member, _, _ = ens(x, h, c)
    assert per_member.shape == (3, 3, 5)
    y = torch.tensor([0, 3, 4])
    ce = torch.nn.CrossEntropyLoss()
    with torch.no_grad():  # the loss as a number: no graph to keep
        want_loss = sum(float(ce(per_member[:, k], y)) for k in range(3))
        assert float(member_loss(ce, per_member, y)) == pytest.approx(want_loss, rel=1e-6)
        assert float(member_loss(ce, per_member[:, 0], y)) == pytest.approx(
            float(ce(per_member[:, 0], y)), rel=1e-6)  # one model: its own loss
    assert TrainConfig().ensemble == 1 and TrainConfig(ensemble=2).ensemble == 2
