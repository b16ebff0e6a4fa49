"""The blended regression beside a granular model (``blend='on'`` with ``f_rnn``, ``sf_rnn``):
the window's features the preprocessing appends against numpy, the paper's models unblended by
default, the refit regression against scikit-learn, the mix the model outputs, and the export
(parity, the regression left out at mix 0, kept in float32 by ``--int8``).

Tiny synthetic takes of ``test_export_granular`` (a 400 Hz signal of 4 sub-samples a frame, a
pressure channel, two electrodes); references independent of the code under test: numpy's FFT
for the window's features (``test_blend.reference_features``), scikit-learn for the solution.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from test_blend import _windows, reference_features, scikit_learn_refit
from test_export_granular import BASE, CHANNELS, ELECTRODES, PRESSURE, SIGNAL, VIB, write_takes

from tactile.device.protocol import ChannelSpec
from tactile.errors import ConfigError
from tactile.training.checkpoint import load_checkpoint
from tactile.training.config import TrainConfig, unused
from tactile.training.evaluate import predict
from tactile.training.granular import FRNNHead, SFRNNHead
from tactile.training.model import Blend
from tactile.training.train import train

torch.set_num_threads(1)

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "granular"
MODELS = {
    "f_rnn": {"model": "f_rnn", "modalities": {"vibration": VIB, "electrodes": ELECTRODES}},
    "sf_rnn": {"model": "sf_rnn", "hop": 10,
               "modalities": {"vibration": VIB, "pressure": PRESSURE, "electrodes": ELECTRODES}},
}


def _cfg(name: str, **kw) -> TrainConfig:
    return TrainConfig.from_dict({**BASE, "epochs": 2, **MODELS[name], "blend": "on", **kw})


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    chans = tuple(ChannelSpec(n, "count") for n in CHANNELS)
    return write_takes(tmp_path_factory.mktemp("takes"), chans, {"sig": list(SIGNAL)})


_RUNS: dict[str, tuple] = {}


def _run(name: str, dataset: Path, tmp_path_factory) -> tuple:
    """Model ``name`` trained with the blend once per module: (name, run folder, metrics)."""
    if name not in _RUNS:
        out = tmp_path_factory.mktemp(name)
        _RUNS[name] = (name, out, train(dataset, out, _cfg(name), progress=False))
    return _RUNS[name]


@pytest.fixture(params=sorted(MODELS), scope="module")
def run(request, dataset, tmp_path_factory):
    return _run(request.param, dataset, tmp_path_factory)


def test_the_paper_models_stay_unblended_unless_asked():
    """``auto`` blends the LSTM only: the granular-media paper's models as published (every
    shipped config of theirs); ``on`` blends an F-RNN or SF-RNN; a model without a recurrent
    head refuses it in one line."""
    paper = [p for p in sorted(CONFIGS.glob("*.toml")) if "recommended" not in p.name]
    assert len(paper) >= 12
    for path in paper:
        assert not TrainConfig.from_toml(path).blends, path.name
    assert not TrainConfig.from_dict({**BASE, **MODELS["f_rnn"]}).blends
    assert _cfg("f_rnn").blends and _cfg("sf_rnn").blends and TrainConfig().blends
    for model in ("sparse_linear", "linear"):
        with pytest.raises(ConfigError, match=f"blend='on' needs a recurrent model .*"
                                              f"got model='{model}'"):
            _cfg("f_rnn", model=model)
    off = TrainConfig.from_dict({**BASE, **MODELS["f_rnn"], "model": "linear", "blend": "off"})
    assert "blend='off' (only model='lstm', 'f_rnn' or 'sf_rnn')" in unused(off), unused(off)


def test_the_window_features_follow_the_heads_at_every_step(run, dataset):
    """The preprocessing's output: the head's features as without the blend (the same
    images or codes), then at every step the normalised window's features, numpy's."""
    name, out, _ = run
    model, ck = load_checkpoint(out)
    w = _windows(dataset, ck)["test"]
    x = torch.from_numpy(w.x[:16])
    with torch.no_grad():
        f = model.pre(x).double().numpy()
        window_features = model.pre.window_features
        model.pre.window_features = None
        try:
            alone = model.pre(x).double().numpy()
        finally:
            model.pre.window_features = window_features
    n = model.pre.n_features
    assert f.shape == (*alone.shape[:2], n + len(ck["channels"]) * 7)  # the model's inputs
    np.testing.assert_array_equal(f[..., :n], alone)
    z = (w.x[:16].astype(np.float64) - model.pre.mean.double().numpy()) \
        / model.pre.std.double().numpy()  # the granular normalisation: no centring
    want = reference_features(z)
    for step in range(f.shape[1]):
        np.testing.assert_allclose(f[:, step, n:], want, rtol=1e-4, atol=1e-3)
    head = model.head
    assert isinstance(head, Blend) and head.n_head == n
    assert isinstance(head.recurrent, FRNNHead if name == "f_rnn" else SFRNNHead)
    # gain augmentation scales the head's features and leaves the window's as they are
    g = model.pre.apply_gain(torch.from_numpy(f).float(), torch.full((1, 1, len(model.layout)),
                                                                     2.0))
    np.testing.assert_allclose(g[..., :n].numpy(), 2 * f[..., :n], rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(g[..., n:].numpy(), f[..., n:].astype(np.float32))


def test_the_refit_regression_is_scikit_learns(run, dataset):
    name, out, metrics = run
    choice = metrics["blend"]
    model, ck = load_checkpoint(out)
    assert float(model.head.mix) == choice["mix"] and metrics["val_accuracy"] == choice["val_acc"]
    parts = _windows(dataset, ck)
    mean, std = model.pre.mean.double().numpy(), model.pre.std.double().numpy()
    # the granular normalisation: no centring
    want = scikit_learn_refit(parts, lambda x: (x - mean) / std, choice["c"])
    with torch.no_grad():
        got = torch.softmax(model.head.regression(model.pre(torch.from_numpy(parts["test"].x))),
                            dim=1).double().numpy()
    diff = np.abs(got - want).max(axis=1)
    assert np.median(diff) < 1e-3 and diff.max() < 0.1, (np.median(diff), diff.max())
    assert (got.argmax(1) == want.argmax(1)).mean() > 0.99


def test_the_model_outputs_the_weighted_mix(run, dataset):
    """At mix 0.5 (both parts count): the model's probabilities are the normalised geometric
    mean of the recurrent head's (mix 0) and the regression's."""
    _, out, _ = run
    model, ck = load_checkpoint(out)
    w = _windows(dataset, ck)["test"]
    model.head.mix.fill_(0.5)
    mixed = predict(model, w)
    model.head.mix.zero_()
    recurrent = predict(model, w)
    with torch.no_grad():
        reg = torch.log_softmax(model.head.regression(model.pre(torch.from_numpy(w.x))), 1)
    want = torch.softmax(0.5 * torch.log(torch.from_numpy(recurrent)) + 0.5 * reg, 1).numpy()
    np.testing.assert_allclose(mixed, want, atol=1e-5)
    assert np.abs(mixed - recurrent).max() > 1e-3  # the regression moved them


def test_the_recurrent_head_trains_as_without_the_blend(run, dataset, tmp_path):
    """The same seed with ``blend='off'``: the recurrent head's weights after training are
    the blended run's, bit for bit (the regression reads only its own features, solved after
    the training), and so are its validation figures."""
    name, out, metrics = run
    off = train(dataset, tmp_path / "off", _cfg(name, blend="off"), progress=False)
    blended, _ = load_checkpoint(out)
    alone, _ = load_checkpoint(tmp_path / "off")
    want = alone.head.state_dict()
    got = {k.removeprefix("recurrent."): v for k, v in blended.head.state_dict().items()
           if k.startswith("recurrent.")}
    assert sorted(got) == sorted(want)
    for k, v in want.items():
        assert torch.equal(got[k], v), k
    assert off["val_accuracy"] == metrics["blend"]["recurrent_val_acc"]
    assert "blend" not in off


def _with_mix(out: Path, folder: Path, mix: float) -> Path:
    ck = torch.load(out / "checkpoint.pt", weights_only=True)
    ck["state_dict"]["head.mix"] = torch.tensor(mix)
    folder.mkdir()
    torch.save(ck, folder / "checkpoint.pt")
    return folder


def test_it_exports_with_parity_and_mix_0_leaves_the_regression_out(run, dataset, tmp_path):
    """Mix 0.5: parity, and the ONNX file's probabilities the checkpoint's model's on the test
    windows; mix 0: neither the regression's nodes nor the window's features in the graph,
    parity against the blended model still."""
    from tactile.export.exporter import export_run
    from tactile.runtime.model import Model

    _, out, _ = run
    nodes = {}
    for mix in (0.0, 0.5):
        folder = _with_mix(out, tmp_path / f"mix{mix}", mix)
        path = tmp_path / f"mix{mix}.onnx"
        report = export_run(folder, path, data=dataset, log=lambda s: None)
        assert report["parity"]["passed"], report["parity"]
        nodes[mix] = [n.name for n in onnx.load(str(path)).graph.node
                      if "/regression/" in n.name or "/window_features/" in n.name]
    assert nodes[0.0] == [] and len(nodes[0.5]) > 10
    model, ck = load_checkpoint(tmp_path / "mix0.5")
    w = _windows(dataset, ck)["test"]
    onnx_model = Model(tmp_path / "mix0.5.onnx")
    got = np.concatenate([onnx_model.classify(w.x[i : i + 32], *onnx_model.zero_state(
        len(w.x[i : i + 32])))[0] for i in range(0, len(w), 32)])
    np.testing.assert_allclose(got, predict(model, w), atol=1e-4)


def test_int8_keeps_the_window_features_and_the_regression_in_float32(dataset,
                                                                      tmp_path_factory):
    """``--int8`` (of the F-RNN): no quantised node computes the window's features or the
    regression, and at mix 1 (the regression alone) the int8 graph gives the float32 model's
    probabilities."""
    from tactile.export.graph import build_graph
    from tactile.export.quantize import quantize_int8
    from tactile.export.session import session

    _, out, _ = _run("f_rnn", dataset, tmp_path_factory)
    model, _ = load_checkpoint(out)
    model.head.mix.fill_(1.0)
    q = quantize_int8(build_graph(model))
    scoped = [n for n in q.graph.node
              if "/regression/" in n.name or "/window_features/" in n.name]
    assert any("/window_features/" in n.name for n in scoped)
    assert any("/regression/" in n.name for n in scoped)
    assert not [n.name for n in scoped if n.op_type in (
        "MatMulInteger", "DynamicQuantizeLinear", "QLinearMatMul")]
    x = np.random.default_rng(0).normal(size=(8, 20, len(model.pre.mean))).astype(np.float32)
    x = x * model.pre.std.numpy() + model.pre.mean.numpy()
    h, c = model.zero_state(8)
    got = session(q.SerializeToString()).run(None, {"x": x, "h": h.numpy(), "c": c.numpy()})[0]
    with torch.no_grad():
        want = model(torch.from_numpy(x), h, c)[0].numpy()
    np.testing.assert_allclose(got, want, atol=1e-5)
