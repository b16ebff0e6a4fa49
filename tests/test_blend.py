"""The blended regression (``blend='auto'``): its window features against numpy's FFT, its
solver against scikit-learn, the weight chosen on the validation windows, the refit's
regression against scikit-learn on the run's own windows, and the mix the model outputs."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
import torch

from tactile.device.recordings import load_dataset
from tactile.device.sim import make_dataset
from tactile.errors import ConfigError, RecordingError
from tactile.training import blend
from tactile.training.checkpoint import load_checkpoint
from tactile.training.config import TrainConfig
from tactile.training.data import classes_of, split_windows
from tactile.training.evaluate import predict
from tactile.training.model import Blend, WindowRegression
from tactile.training.train import train

FLOOR = WindowRegression.FLOOR


def reference_features(z: np.ndarray, n_bands: int = 5) -> np.ndarray:
    """(N, T, C) float64 -> (N, C * (2 + n_bands)) with numpy: per channel the mean, the log
    standard deviation, then per band (equal bands up to half the sample rate, the last
    holding Nyquist's bin) the log energy of the mean-free, Hann-tapered window."""
    mean = z.mean(axis=1)
    d = z - mean[:, None]
    log_std = 0.5 * np.log(d.var(axis=1) + FLOOR)
    n = z.shape[1]
    power = np.abs(np.fft.rfft(d * np.hanning(n)[None, :, None], axis=1)) ** 2
    k = np.arange(power.shape[1])  # bin k: k / n cycles a sample; band b: b / (2 n_bands) up
    lower = [b * n for b in range(n_bands)] + [np.inf]  # ... compared as 2 n_bands k >= b n
    bands = [np.log(power[:, (2 * n_bands * k >= lo) & (2 * n_bands * k < hi)].sum(axis=1)
                    + FLOOR) for lo, hi in zip(lower[:-1], lower[1:], strict=True)]
    return np.concatenate([mean, log_std, *bands], axis=1)


@pytest.mark.parametrize("window", [50, 37])
def test_window_features_match_numpy(window):
    rng = np.random.default_rng(0)
    z = rng.normal(size=(4, window, 3)) * np.array([0.1, 0.05, 3.0]) + np.array([0.5, -2, 0])
    t = np.arange(window)
    z[:, :, 0] += 4 * np.sin(2 * np.pi * 0.35 * t)  # a tone at 0.35 cycles a sample: band 3
    reg = WindowRegression(3, window, 2)
    with torch.no_grad():
        got = reg.features(torch.tensor(z, dtype=torch.float32)).double().numpy()
    want = reference_features(z)
    assert got.shape == want.shape == (4, 3 * 7)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-3)
    tone_bands = got[:, 6:].reshape(4, 5, 3)[:, :, 0]  # channel 0's band energies
    assert (tone_bands.argmax(axis=1) == 3).all()
    if window == 50:  # the band (bins 15-19) holds the main lobe (bins 15.5-19.5) whole
        # Parseval: a Hann-tapered tone of amplitude A over n samples, one side of its
        # spectrum: n A^2 / 4 sum(hann^2); the noise (std 0.1) moves it by a per cent or two
        level = np.log(window * 4**2 / 4 * (np.hanning(window) ** 2).sum())
        assert np.all(np.abs(tone_bands[:, 3] - level) < 0.05), tone_bands[:, 3] - level


def test_a_steady_level_keeps_its_small_variation_in_float32():
    """A channel held far above its variation within the window (a pressure held steady: level
    5, variation 1e-3 on the normalised scale): the float32 features stay within 2e-5 of
    numpy's float64 features of the same float32 window (the mean's rounding left in every
    sample had moved the lowest band's log energy by 5e-4, and a blended model's parity with
    it)."""
    rng = np.random.default_rng(0)
    t = np.arange(50)
    z = (5.0 + 1e-3 * rng.normal(size=(8, 50, 2))
         + 1e-3 * np.sin(2 * np.pi * 0.02 * t)[None, :, None]).astype(np.float32)
    want = reference_features(z.astype(np.float64))
    with torch.no_grad():
        got = WindowRegression(2, 50, 2).features(torch.from_numpy(z)).double().numpy()
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-5)


def test_the_solution_gives_every_class_its_logit():
    """scikit-learn's layouts (one logit for two classes, only the classes present) as one
    logit per class: the probabilities scikit-learn's own model gives, 0 for an absent class."""
    from sklearn.linear_model import LogisticRegression

    rng = np.random.default_rng(1)
    x = rng.normal(size=(300, 6))
    y = (x[:, 0] + 0.5 * x[:, 1] + rng.normal(scale=0.8, size=300) > 0).astype(int)
    y[x[:, 2] > 1.0] = 3  # classes 0, 1, 3 of 4
    for labels in (y, np.where(y == 3, 1, y) * 2):  # three classes of 4; then two (0 and 2)
        coef, intercept = blend.solve(x, labels, 4, 1.0)
        ours = torch.softmax(torch.from_numpy(x @ coef + intercept), dim=1).numpy()
        ref = LogisticRegression(C=1.0, max_iter=2000).fit(x, labels)
        absent = np.setdiff1d(np.arange(4), ref.classes_)
        np.testing.assert_allclose(ours[:, ref.classes_], ref.predict_proba(x), atol=1e-6)
        assert ours[:, absent].max() < 1e-30
        warm = blend.solve(x, labels, 4, 10.0, start=(coef, intercept))  # going on from it
        ref10 = LogisticRegression(C=10.0, max_iter=2000, tol=1e-8).fit(x, labels)
        got = torch.softmax(torch.from_numpy(x @ warm[0] + warm[1]), dim=1).numpy()
        # (both stop at scikit-learn's tolerance: near the optimum, not on it)
        np.testing.assert_allclose(got[:, ref.classes_], ref10.predict_proba(x), atol=1e-2)
        assert np.abs(got - ours).max() > 0.02  # it went on: C = 10 is not C = 1's fit


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    make_dataset(out, takes=6, textures=("non_contact", "paper", "nonwoven_cloth"),
                 seconds=12, seed=1)
    return out


CFG = TrainConfig(epochs=3, hidden=8, layers=1, threads=1, seed=2)


@pytest.fixture(scope="module")
def run(dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    return out, train(dataset, out, CFG, progress=False)


def _windows(dataset, ck):
    cfg = TrainConfig.from_dict(ck["config"])
    takes = load_dataset(dataset)
    _, parts = split_windows(takes, classes_of(takes), tuple(ck["channels"]), cfg)
    return parts


def scikit_learn_refit(parts: dict, normalised, c: float) -> np.ndarray:
    """The refit's reference: scikit-learn's regression (``C = c``, solved far tighter than
    the model's) on the numpy features of the normalised training + validation windows
    (``normalised``: windows in units -> the model's normalised channels), standardised, a
    feature that never varies left out (a centred channel's mean); its probabilities of the
    test windows."""
    from sklearn.linear_model import LogisticRegression

    feats = {k: reference_features(normalised(parts[k].x.astype(np.float64)))
             for k in ("train", "val", "test")}
    both = np.concatenate([feats["train"], feats["val"]])
    mean, std = both.mean(axis=0), both.std(axis=0)
    kept = std > 1e-6
    ref = LogisticRegression(C=c, tol=1e-10, max_iter=10_000).fit(
        ((both - mean) / np.where(kept, std, 1))[:, kept],
        np.concatenate([parts["train"].y, parts["val"].y]))
    return ref.predict_proba(((feats["test"] - mean) / np.where(kept, std, 1))[:, kept])


def test_the_refit_regression_is_scikit_learns_on_training_and_validation_windows(dataset, run):
    out, metrics = run
    choice = metrics["blend"]
    assert choice["c"] in blend.CS and choice["mix"] in blend.WEIGHTS
    model, ck = load_checkpoint(out)
    assert isinstance(model.head, Blend) and float(model.head.mix) == choice["mix"]
    parts = _windows(dataset, ck)

    def normalised(x):  # the model's normalisation, in numpy: the regression's input
        z = (x - np.array(ck["mean"])) / np.array(ck["std"])
        centred = z - z.mean(axis=1, keepdims=True)
        mask = np.isin(np.arange(z.shape[2]), ck["center_index"])
        return np.where(mask, centred, z)

    want = scikit_learn_refit(parts, normalised, choice["c"])
    with torch.no_grad():
        got = torch.softmax(model.head.regression(model.pre(torch.from_numpy(parts["test"].x))),
                            dim=1).double().numpy()
    # (both scikit-learn's fits stop near the optimum, not on it: the model's from a warm start)
    diff = np.abs(got - want).max(axis=1)  # per window (here: median 1e-5, max 0.05)
    assert np.median(diff) < 1e-3 and diff.max() < 0.1
    assert (got.argmax(1) == want.argmax(1)).mean() > 0.99


def test_the_model_outputs_the_weighted_mix(dataset, run):
    out, _ = run
    model, ck = load_checkpoint(out)
    w = _windows(dataset, ck)["test"]
    mixed = predict(model, w)
    weight = float(model.head.mix)
    model.head.mix.zero_()
    recurrent = predict(model, w)
    with torch.no_grad():
        reg = torch.log_softmax(model.head.regression(model.pre(torch.from_numpy(w.x))), 1)
    want = torch.softmax((1 - weight) * torch.log(torch.from_numpy(recurrent))
                         + weight * reg, dim=1).numpy()
    np.testing.assert_allclose(mixed, want, atol=1e-5)


class _Fixed:
    """``predict`` replaced: the LSTM's validation probabilities given, mixed as the model
    mixes them at its current ``mix`` with its regression's."""

    def __init__(self, probs: np.ndarray) -> None:
        self.probs = probs

    def __call__(self, model, w, batch=512, feats=None):
        mix = float(model.head.mix)
        with torch.no_grad():
            reg = torch.log_softmax(model.head.regression(feats).double(), 1)
        lstm = torch.log(torch.from_numpy(self.probs).double() + 1e-300)
        return torch.softmax((1 - mix) * lstm + mix * reg, 1).float().numpy()


def test_the_weight_is_chosen_on_validation_windows(dataset, run, monkeypatch):
    """An LSTM that knows nothing (uniform probabilities): the regression gets weight and the
    mix labels the validation windows as the regression does; one that is always right keeps
    weight 0."""
    out, _ = run
    model, ck = load_checkpoint(out)
    parts = _windows(dataset, ck)
    feats = {k: model.pre(torch.from_numpy(parts[k].x)).detach() for k in ("train", "val")}
    from tactile.training.dist import Dist

    n, k = len(parts["val"]), model.n_classes
    monkeypatch.setattr(blend, "predict", _Fixed(np.full((n, k), 1.0 / k, np.float32)))
    got = blend.choose(model, parts, feats, Dist.from_env())
    assert got["mix"] > 0 and got["val_acc"] == pytest.approx(got["regression_val_acc"])
    assert got["recurrent_val_acc"] == pytest.approx(float((parts["val"].y == 0).mean()))
    right = np.eye(k, dtype=np.float32)[parts["val"].y]
    monkeypatch.setattr(blend, "predict", _Fixed(right))
    got = blend.choose(model, parts, feats, Dist.from_env())
    assert got["mix"] == 0 and got["val_acc"] == 1.0 and float(model.head.mix) == 0


def test_blend_off_is_the_lstm_alone_and_old_checkpoints_load_so(dataset, tmp_path):
    run = tmp_path / "off"
    m = train(dataset, run, CFG.replace(blend="off", epochs=1), progress=False)
    assert "blend" not in m
    ck = torch.load(run / "checkpoint.pt", weights_only=True)
    assert not any(".regression." in k or k == "head.mix" for k in ck["state_dict"])
    del ck["config"]["blend"]  # saved before the setting: the LSTM alone
    torch.save(ck, run / "checkpoint.pt")
    model, _ = load_checkpoint(run)
    assert not isinstance(model.head, Blend)
    with pytest.raises(ConfigError, match="blend must be one of auto, on, off"):
        TrainConfig(blend="yes")


def test_a_blended_checkpoint_without_the_key_is_one_line(run, tmp_path):
    out, _ = run
    ck = torch.load(out / "checkpoint.pt", weights_only=True)
    del ck["config"]["blend"]
    torch.save(ck, tmp_path / "checkpoint.pt")
    with pytest.raises(RecordingError, match="'state_dict' does not fit its config"):
        load_checkpoint(tmp_path)


def test_a_blended_model_exports_with_parity(dataset, run, tmp_path):
    """The mix in the ONNX file (weight 0.5, so that both parts count): parity, and its
    probabilities on the test windows those of the checkpoint's model."""
    from tactile.export.exporter import export_run
    from tactile.runtime.model import Model

    out, _ = run
    ck = torch.load(out / "checkpoint.pt", weights_only=True)
    ck["state_dict"]["head.mix"] = torch.tensor(0.5)
    half = tmp_path / "half"
    half.mkdir()
    torch.save(ck, half / "checkpoint.pt")
    report = export_run(half, tmp_path / "half.onnx", log=lambda s: None)
    assert report["parity"]["passed"]
    model, _ = load_checkpoint(half)
    w = _windows(dataset, ck)["test"]
    want = predict(model, w)
    onnx_model = Model(tmp_path / "half.onnx")
    got = np.concatenate([onnx_model.classify(w.x[i : i + 64], *onnx_model.zero_state(
        len(w.x[i : i + 64])))[0] for i in range(0, len(w), 64)])
    np.testing.assert_allclose(got, want, atol=1e-4)
    # tactile-check says what the regression reads and how much it weighs
    from tactile.export.check import describe

    text = describe(tmp_path / "half.onnx", onnx_model.contract)
    assert (f"  blend     0.5 x a logistic regression (C {ck['metrics']['blend']['c']:g}) on "
            "whole-window features: 8 channels each by itself (mean, log std, 5 band "
            "energies)\n") in text, text


def test_a_mix_of_0_exports_the_lstm_alone_and_keeps_parity(run, tmp_path):
    """Mix 0: the regression's nodes are left out of the graph (the same probabilities
    without its work), the file is as small as the LSTM's and parity against the blended
    model still holds; mix 0.5 keeps them."""
    from tactile.export.exporter import export_run

    out, _ = run
    ck = torch.load(out / "checkpoint.pt", weights_only=True)
    nodes, sizes = {}, {}
    for mix in (0.0, 0.5):
        ck["state_dict"]["head.mix"] = torch.tensor(mix)
        folder = tmp_path / f"mix{mix}"
        folder.mkdir()
        torch.save(ck, folder / "checkpoint.pt")
        report = export_run(folder, tmp_path / f"mix{mix}.onnx", log=lambda s: None)
        assert report["parity"]["passed"]
        graph = onnx.load(str(tmp_path / f"mix{mix}.onnx")).graph
        nodes[mix] = [n.name for n in graph.node if "/regression/" in n.name]
        sizes[mix] = (tmp_path / f"mix{mix}.onnx").stat().st_size
    assert nodes[0.0] == [] and len(nodes[0.5]) > 10
    assert sizes[0.5] - sizes[0.0] > 4 * 50 * 26 * 2  # the DFT basis alone: 2,600 floats


def test_int8_keeps_the_regression_in_float32(run):
    """``--int8`` quantises the LSTM's weights, not the regression's products (its DFT basis,
    band sums and weights feed logs): no quantised node under the regression, and at mix 1
    (the regression alone) the int8 graph gives the float32 model's probabilities."""
    from tactile.export.graph import build_graph
    from tactile.export.quantize import quantize_int8
    from tactile.export.session import session

    out, _ = run
    model, ck = load_checkpoint(out)
    model.head.mix.fill_(1.0)
    q = quantize_int8(build_graph(model))
    quantised = [n.name for n in q.graph.node if "/regression/" in n.name
                 and n.op_type in ("MatMulInteger", "DynamicQuantizeLinear", "QLinearMatMul")]
    assert quantised == [] and any("/regression/" in n.name for n in q.graph.node)
    x = np.random.default_rng(0).normal(size=(16, 50, len(ck["channels"]))).astype(np.float32)
    x = x * np.array(ck["std"], np.float32) + np.array(ck["mean"], np.float32)
    h, c = model.zero_state(16)
    got = session(q.SerializeToString()).run(None, {"x": x, "h": h.numpy(), "c": c.numpy()})[0]
    with torch.no_grad():
        want = model(torch.from_numpy(x), h, c)[0].numpy()
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_without_scikit_learn_the_blend_is_refused_before_training(dataset, tmp_path,
                                                                    monkeypatch):
    """The solver missing: one line naming the way out, before any epoch (not after a long
    training); blend=off trains without it."""
    import sys

    monkeypatch.setitem(sys.modules, "sklearn.linear_model", None)  # import raises
    epochs = []
    with pytest.raises(ConfigError, match=r"blend='auto' solves its regression with "
                       r"scikit-learn, which does not import .*or set blend=off"):
        train(dataset, tmp_path / "r", CFG, progress=False,
              on_epoch=lambda phase, e: epochs.append(e))
    assert epochs == []
    m = train(dataset, tmp_path / "off", CFG.replace(blend="off", epochs=1), progress=False)
    assert "blend" not in m


def test_a_carried_state_is_never_mixed_away(dataset, run, monkeypatch):
    """An LSTM always wrong: the regression alone (mix 1) labels the most validation windows
    right, and is chosen; with state='carry' the mix stops at 0.75, where the carried state
    still counts."""
    from tactile.training.dist import Dist

    out, _ = run
    model, ck = load_checkpoint(out)
    parts = _windows(dataset, ck)
    feats = {k: model.pre(torch.from_numpy(parts[k].x)).detach() for k in ("train", "val")}
    k = model.n_classes
    wrong = np.eye(k, dtype=np.float32)[(parts["val"].y + 1) % k]
    monkeypatch.setattr(blend, "predict", _Fixed(wrong))
    assert blend.choose(model, parts, feats, Dist.from_env())["mix"] == 1.0
    model.cfg = model.cfg.replace(state="carry", hop=model.cfg.window)
    assert blend.weights(model) == (0.0, 0.25, 0.5, 0.75)
    assert blend.choose(model, parts, feats, Dist.from_env())["mix"] <= 0.75


def test_a_checkpoint_that_stored_the_constants_loads(run, tmp_path):
    """Checkpoints written while the regression's DFT basis and band sums were stored (they
    are rebuilt with the module now) load, the stored copies set aside."""
    out, _ = run
    ck = torch.load(out / "checkpoint.pt", weights_only=True)
    model, _ = load_checkpoint(out)
    reg = model.head.regression
    ck["state_dict"]["head.regression.dft"] = reg.window.dft.clone()
    ck["state_dict"]["head.regression.bands"] = reg.window.bands.clone()
    torch.save(ck, tmp_path / "checkpoint.pt")
    again, _ = load_checkpoint(tmp_path)
    assert torch.equal(again.head.regression.window.dft, reg.window.dft)
    assert torch.equal(again.head.regression.coef, reg.coef)
