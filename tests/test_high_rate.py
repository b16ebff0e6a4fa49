"""High-rate signals in the default model: the front end that frames a declared signal at its
own rate (``tactile.training.frontend``) against a numpy reference, the model's input layout
and the contract with and without a signal, and a BioTac take through training and export."""

from __future__ import annotations

import json

import numpy as np
import onnx
import pytest
import torch

from tactile.training.config import TrainConfig
from tactile.training.frontend import (
    BANDS_PER_OCTAVE,
    LOG_FLOOR,
    HighRateFront,
    band_bins,
    band_edges_hz,
)
from tactile.training.models import build_model

RATE, R = 100.0, 22  # frames/s, sub-samples a frame: a 2.2 kHz signal
PAC = tuple(f"f0_pac_{i:02d}" for i in range(R))
CHANNELS = ("f0_pdc", *PAC, *(f"f0_ele_{i:02d}" for i in range(19)))
SIGNAL = (("f0_pac", PAC),)


def reference(s: np.ndarray, frame: int, hop: int, rate: float) -> np.ndarray:
    """(n,) signal -> (frames, bands + 1): per frame the band powers (bins whose frequency
    lies in each band of ``band_edges_hz``, of the Hann-tapered frame's rfft, scaled to the
    mean square of a tone) as logs, then the frame's mean."""
    edges = band_edges_hz(frame, rate)
    freqs = np.fft.rfftfreq(frame, 1.0 / rate)
    w = np.hanning(frame)
    rows = []
    for a in range(0, len(s) - frame + 1, hop):
        seg = s[a : a + frame]
        scale = 2.0 / (frame * np.sum(w**2))
        p = np.abs(np.fft.rfft(w * seg)) ** 2 * scale
        inside = [(freqs >= lo) & ((freqs < hi) | (hi == rate / 2) & (freqs == hi))
                  for lo, hi in edges]
        bands = np.array([p[b].sum() for b in inside])
        floor = np.array([LOG_FLOOR * scale * b.sum() for b in inside])  # per bin
        rows.append([*np.log(bands + floor), seg.mean()])
    return np.array(rows)


def test_bands_are_third_octaves_up_to_nyquist_at_any_rate():
    for frame, rate in ((440, 2200.0), (20, 100.0), (1000, 8000.0)):
        edges = band_edges_hz(frame, rate)
        assert edges[0][0] == pytest.approx(rate / frame)  # from the first bin
        assert edges[-1][1] == pytest.approx(rate / 2)  # to Nyquist
        assert all(b[0] == a[1] for a, b in zip(edges, edges[1:], strict=False))
        wide = [hi / lo for lo, hi in edges if hi - lo > 1.5 * rate / frame]
        assert max(wide) <= 2 ** (1 / BANDS_PER_OCTAVE) * 1.5  # (rounded to whole bins)
    assert band_bins(221)[-1] == (204, 221)  # the last band holds the Nyquist bin (220)


def test_a_tone_lands_in_its_band_at_its_level():
    """A 300 Hz tone of amplitude 2 in a 2.2 kHz signal given as 22 sub-sample channels: the
    front end's log band powers equal the numpy reference and put log(2^2 / 2) in the band
    holding 300 Hz (Hann leakage stays inside it), far below elsewhere."""
    t = np.arange(50 * R) / (RATE * R)
    s = 2.0 * np.sin(2 * np.pi * 300.0 * t) + 0.5
    x = torch.tensor(s.reshape(1, 50, R), dtype=torch.float32)
    front = HighRateFront([list(range(R))], frame=20, hop=10)
    got = front(x)[0].numpy()  # (T', nb + 1)
    want = reference(s, 20 * R, 10 * R, RATE * R)
    assert got.shape == want.shape == (4, len(band_edges_hz(440, 2200.0)) + 1)
    np.testing.assert_allclose(got, want, atol=2e-3)
    edges = band_edges_hz(440, 2200.0)
    k = next(i for i, (lo, hi) in enumerate(edges) if lo <= 300.0 < hi)
    assert np.all(np.argmax(got[:, :-1], axis=1) == k)
    np.testing.assert_allclose(got[:, k], np.log(2.0), atol=0.01)  # A^2 / 2 = 2
    others = np.delete(got[:, :-1], [0, k], axis=1)  # band 0 (5-10 Hz): the mean's leakage
    assert np.all(others < np.log(2.0) - 10) and np.all(got[:, 0] < np.log(2.0) - 3)
    np.testing.assert_allclose(got[:, -1], 0.5, atol=0.01)  # the frame's mean


def test_the_front_end_sees_the_signal_not_its_aliases():
    """Two tones 100 Hz apart alias to the same frequency in every 100 Hz sub-sample channel;
    at the signal's rate they land in different bands."""
    t = np.arange(50 * R) / (RATE * R)
    front = HighRateFront([list(range(R))], frame=20, hop=10)
    out = [front(torch.tensor(np.sin(2 * np.pi * f * t).reshape(1, 50, R),
                              dtype=torch.float32))[0, :, :-1].argmax(1) for f in (210, 610)]
    assert not torch.equal(out[0], out[1])


def _model(cfg: TrainConfig):
    emd = [CHANNELS.index(c) for c in cfg.emd_channels]
    return build_model(cfg, 5, torch.zeros(len(CHANNELS)), torch.ones(len(CHANNELS)),
                       channels=CHANNELS, rate_hz=RATE, emd_index=emd)


def test_a_declared_signal_changes_the_input_layout():
    plain = _model(TrainConfig(channels=CHANNELS))
    high = _model(TrainConfig(channels=CHANNELS, signals=SIGNAL))
    nb = len(band_bins(20 * R // 2 + 1))
    k = 20 // 2 + 1  # the plain front's bins
    assert plain.head.recurrent.lstm.input_size == len(CHANNELS) * (k + 1)
    assert high.head.recurrent.lstm.input_size == (len(CHANNELS) - R) * (k + 1) + nb + 1
    x = torch.randn(3, 50, len(CHANNELS))
    for m in (plain.eval(), high.eval()):
        p, _, _ = m(x, *m.zero_state(3))
        assert p.shape == (3, 5) and torch.allclose(p.sum(1), torch.ones(3))
    # the model's input is still (B, T, C) frames: the signal's channels are a reshape away
    none = _model(TrainConfig(channels=CHANNELS, signals=SIGNAL, front="none"))
    assert none.head.recurrent.lstm.input_size == len(CHANNELS)


def biotac_takes(tmp_path, objects=("cork", "glass_bottle"), frames: int = 120):
    """A dataset folder of BioTac takes as the importer writes them (88 channels, f0_pac and
    f1_pac declared): repetitions 1-3 of each object (skips without h5py)."""
    pytest.importorskip("h5py")
    from test_biotac import write_h5

    from tactile.device.recordings.biotac import import_biotac

    for obj in objects:
        write_h5(tmp_path / f"{obj}.h5",
                 {f"{obj}_pdc100_1cm_{r:02d}": frames for r in (1, 2, 3)}, seed=len(obj))
    data = tmp_path / "data"
    import_biotac(sorted(tmp_path.glob("*.h5")), data)
    return data


def test_a_biotac_take_trains_and_exports_with_parity(tmp_path, capsys):
    """88 channels as the importer writes them (the takes declare f0_pac and f1_pac), the
    default model with no setting but a short run: one epoch, exported with parity; the
    contract names both signals and how the front end frames them."""
    from tactile.contract import ModelContract
    from tactile.export.exporter import export_run
    from tactile.training.checkpoint import load_checkpoint
    from tactile.training.train import train

    data = biotac_takes(tmp_path)
    run = tmp_path / "run"
    train(data, run, TrainConfig(epochs=1, threads=1, batch_size=16), progress=False)
    model, ck = load_checkpoint(run)
    assert len(ck["channels"]) == 88
    assert [n for n, _ in ck["config"]["signals"].items()] == ["f0_pac", "f1_pac"]
    assert len(model.head.recurrent.high) == 1 and model.head.recurrent.high[0].n_signals == 2
    out = tmp_path / "model.onnx"
    report = export_run(run, out, log=lambda s: None)
    assert report["parity"]["passed"]
    meta = {p.key: p.value for p in onnx.load(str(out)).metadata_props}
    contract = ModelContract.from_metadata(meta)
    assert [(s.name, s.rate_hz, len(s.channels)) for s in contract.signals] == [
        ("f0_pac", 2200.0, R), ("f1_pac", 2200.0, R)]
    high = json.loads(meta["preprocessing"])["high_rate"]
    assert [(h["signal"], h["frame"], h["hop"]) for h in high] == [
        ("f0_pac", 440, 220), ("f1_pac", 440, 220)]
    assert high[0]["bands_hz"][-1][1] == 1100.0
    from tactile.export.commands.check import main as check_main  # shows the signals too

    assert check_main([str(out)]) == 0
    text = capsys.readouterr().out
    assert "  emd       none\n  signal    f0_pac: 22 sub-samples per frame (f0_pac_00.." \
        "f0_pac_21), 2200 Hz\n  signal    f1_pac: 22" in text, text
    # the blended regression reads every channel by itself, the signals' sub-samples too
    blend = json.loads(meta["training_metrics"])["blend"]
    assert blend["mix"] in (0, .25, .5, .75, 1)
    assert (f"  blend     {blend['mix']:g} x a logistic regression (C {blend['c']:g}) on "
            "whole-window features: 88 channels each by itself (mean, log std, 5 band "
            "energies)\n" if blend["mix"] else
            "  blend     mix 0: the recurrent model alone") in text, text


def test_the_linear_head_adds_the_signals_bands_over_the_window():
    cfg = TrainConfig(channels=CHANNELS, signals=SIGNAL, model="linear",
                      emd_channels=("f0_pdc",), emd_imfs=2, emd_sifts=2)
    m = _model(cfg).eval()
    nb = len(band_bins(50 * R // 2 + 1))  # one frame: the whole window at 2.2 kHz
    assert m.head.out.in_features == 2 + nb + 1
    p, _, _ = m(torch.randn(2, 50, len(CHANNELS)), *m.zero_state(2))
    assert p.shape == (2, 5)
    assert _model(cfg.replace(signals={})).head.out.in_features == 2


def test_gain_augmentation_keeps_a_signal_whole():
    """One random gain for all of a signal's sub-samples (a gain per sub-sample would
    modulate the signal at the frame rate); the plain channels keep their own; without a
    signal the gains are those of every other model, draw for draw."""
    high = _model(TrainConfig(channels=CHANNELS, signals=SIGNAL))
    plain = _model(TrainConfig(channels=CHANNELS))
    f = torch.ones(4, 2, 50, len(CHANNELS))
    g = high.augment_gain(f, 0.3, torch.Generator().manual_seed(0))
    sub = g[..., 1 : 1 + R]
    assert torch.equal(sub, sub[..., :1].expand_as(sub))
    assert len(torch.unique(g[0, 0, 0])) == len(CHANNELS) - R + 1
    want = super(type(plain), plain).augment_gain(f, 0.3, torch.Generator().manual_seed(0))
    assert torch.equal(plain.augment_gain(f, 0.3, torch.Generator().manual_seed(0)), want)


def test_channels_in_another_order_keep_a_signals_time_order(tmp_path, capsys):
    """`channels` listing a signal's sub-samples in another order (here reversed) fed the model
    each frame's samples in that order, and the contract named them so; the signal is the
    takes' declaration, in time order, whatever the order of `channels`. Some sub-samples but
    not all: read as plain channels, and a warning now says so (it was silent)."""
    from tactile.training.checkpoint import load_checkpoint
    from tactile.training.models import signal_index
    from tactile.training.train import train

    data = biotac_takes(tmp_path)
    mixed = ("f0_pdc", *reversed(PAC), *(f"f0_ele_{i:02d}" for i in range(19)))
    run = tmp_path / "run"
    train(data, run, TrainConfig(channels=mixed, epochs=1, threads=1, batch_size=16),
          progress=False)
    model, ck = load_checkpoint(run)
    assert ck["channels"] == list(mixed)
    assert ck["config"]["signals"] == {"f0_pac": list(PAC)}
    assert signal_index(model.cfg, mixed) == [[mixed.index(c) for c in PAC]]
    assert "some but not all" not in capsys.readouterr().err
    few = ("f0_pdc", "f0_pac_00", "f0_pac_01")
    train(data, tmp_path / "few", TrainConfig(channels=few, epochs=1, threads=1,
                                              batch_size=16), progress=False)
    err = capsys.readouterr().err
    assert ("warning: channels holds some but not all sub-samples of the takes' signal f0_pac "
            "(2 of 22): read as plain channels at 100 Hz, not as the signal") in err, err
    assert "signals" not in load_checkpoint(tmp_path / "few")[1]["config"] or not \
        load_checkpoint(tmp_path / "few")[1]["config"]["signals"]


def test_channels_patterns_pick_in_recording_order(tmp_path):
    """`channels` took exact names only (one fingertip of a BioTac: 42 names to type); a
    shell-style pattern picks the channels it matches in recording order, exact names keep
    the order given, and the run records the names picked."""
    from tactile.device.recordings import load_dataset
    from tactile.errors import ConfigError
    from tactile.training.data import pick_channels

    take = load_dataset(biotac_takes(tmp_path, ("cork",), 30))[0]
    assert pick_channels(take, ("f0_ele_*", "f0_pdc", "f0_pac_*")) == (
        *(f"f0_ele_{i:02d}" for i in range(19)), "f0_pdc", *PAC)
    assert pick_channels(take, ("f0_pdc", "f1_pdc")) == ("f0_pdc", "f1_pdc")
    assert pick_channels(take, ()) == tuple(take.channels)
    with pytest.raises(ConfigError, match=r"channels pattern 'f9_\*' matches none of the "
                                          r"recordings' channels: f0_pac_00, "):
        pick_channels(take, ("f9_*",))
    with pytest.raises(ConfigError, match=r"channels picks 'f0_pdc' twice \('f0_\*' again\)"):
        pick_channels(take, ("f0_pdc", "f0_*"))
    with pytest.raises(ConfigError, match=r"channels \['f9'\] not in the recordings'"):
        pick_channels(take, ("f9",))


def test_a_channel_named_like_a_pattern_is_picked_by_its_name():
    """Channel names may hold * ? [ (a run records them as exact names): the name is looked up
    first, a pattern only when no channel has that name; every missing name is listed."""
    from types import SimpleNamespace

    from tactile.errors import ConfigError
    from tactile.training.data import pick_channels

    take = SimpleNamespace(channels=("p[0]", "p0", "a*", "ab", "b"))
    assert pick_channels(take, ("p[0]", "b")) == ("p[0]", "b")
    assert pick_channels(take, ("a*",)) == ("a*",)
    assert pick_channels(take, ("a?",)) == ("a*", "ab")
    with pytest.raises(ConfigError, match=r"channels \['x', 'y'\] not in the recordings'"):
        pick_channels(take, ("x", "b", "y"))


def test_config_signal_patterns_join_the_sub_samples_in_recording_order(tmp_path):
    """[signals] patterns in another order (f0_pac_1*, then 0*, then 2*) made the signal
    10..19, 00..09, 20, 21; the docs say recording order, which the run now records."""
    from tactile.training.checkpoint import load_checkpoint
    from tactile.training.models import signal_index
    from tactile.training.train import train

    data = biotac_takes(tmp_path)
    run = tmp_path / "run"
    channels = ("f0_pdc", *PAC)
    cfg = TrainConfig(channels=channels, epochs=1, threads=1, batch_size=16,
                      signals=(("f0_pac", ("f0_pac_1*", "f0_pac_0*", "f0_pac_2*")),))
    train(data, run, cfg, progress=False)
    model, ck = load_checkpoint(run)
    assert ck["config"]["signals"] == {"f0_pac": list(PAC)}
    assert signal_index(model.cfg, channels) == [list(range(1, 23))]


def test_a_take_declaring_another_time_order_is_refused(tmp_path, capsys):
    """A take whose JSON declares a signal's sub-samples in another time order than the
    model's was read without a word: channels go by name, so each frame's samples reached the
    model reordered (here reversed). Replay (exit 3), evaluation and the export's windows now
    refuse it naming the first pair; training refuses it against a [signals] setting (which
    reads the recording order)."""
    import shutil

    from tactile.errors import ConfigError, RecordingError
    from tactile.export.windows import from_dataset
    from tactile.runtime.commands.run import main as run_main
    from tactile.training.checkpoint import load_checkpoint
    from tactile.training.evaluate import evaluate_run
    from tactile.training.train import train

    data = biotac_takes(tmp_path, frames=60)
    run = tmp_path / "run"
    channels = ("f0_pdc", *PAC)
    train(data, run, TrainConfig(channels=channels, epochs=1, threads=1, batch_size=16),
          progress=False)
    flipped = tmp_path / "flipped"
    shutil.copytree(data, flipped)
    for meta_path in flipped.glob("*.json"):
        meta = json.loads(meta_path.read_text())
        meta["signals"]["f0_pac"] = meta["signals"]["f0_pac"][::-1]
        meta_path.write_text(json.dumps(meta))
    take = sorted(flipped.glob("*.csv"))[0]
    said = (f"{take}: its signal 'f0_pac' has f0_pac_01 before f0_pac_00, the model's signal "
            "'f0_pac' f0_pac_00 before f0_pac_01 (sub-samples in time order)")
    _, ck = load_checkpoint(run)
    with pytest.raises(RecordingError) as e:
        evaluate_run(run, flipped)
    assert str(e.value) == said
    with pytest.raises(RecordingError) as e:
        from_dataset(ck, flipped)
    assert str(e.value) == said
    with pytest.raises(ConfigError, match="the config's signal 'f0_pac' f0_pac_00 before "
                                          "f0_pac_01 .* in the order the takes record them"):
        train(flipped, tmp_path / "run2", TrainConfig(
            channels=channels, epochs=1, threads=1, batch_size=16,
            signals=(("f0_pac", ("f0_pac_*",)),)), progress=False)
    from tactile.export.exporter import export_run

    model = tmp_path / "m.onnx"
    export_run(run, model, log=lambda s: None)
    capsys.readouterr()
    assert run_main(["--model", str(model), "--replay", str(take)]) == 3
    assert capsys.readouterr().err == f"tactile-run: error: {said}\n"
    assert run_main(["--model", str(model), "--replay", str(sorted(data.glob("*.csv"))[0])]) == 0
    from tactile.export.commands.check import main as check_main  # the file's own contract

    capsys.readouterr()
    assert check_main([str(model), "--data", str(flipped)]) == 1
    assert capsys.readouterr().err == f"tactile-check: error: {said}\n"


def test_a_centred_signal_loses_one_mean_not_one_per_sub_sample(tmp_path, capsys):
    """`center` patterns matching a signal's sub-samples (accel_z_00.. under the default
    accel_*) removed each sub-sample's own window mean: a comb at every multiple of the frame
    rate cut out of the signal. The signal is now centred whole, on the mean of all its
    samples in the window (against a numpy reference), in PyTorch and in the exported file;
    a checkpoint saved before keeps its per-sub-sample centring."""
    from tactile.export.exporter import export_run
    from tactile.training.checkpoint import load_checkpoint
    from tactile.training.train import train

    cfg = TrainConfig(channels=CHANNELS, signals=SIGNAL)
    pac = [CHANNELS.index(c) for c in PAC]
    model = build_model(cfg, 3, torch.zeros(len(CHANNELS)), torch.ones(len(CHANNELS)),
                        channels=CHANNELS, center_index=[0, pac[3]])
    assert model.pre.center_groups == [pac]
    x = np.random.default_rng(0).normal(size=(2, 50, len(CHANNELS))) + 5.0
    ref = x.copy()
    ref[..., 0] -= x[..., 0].mean(axis=1, keepdims=True)
    ref[..., pac] -= x[..., pac].mean(axis=(1, 2), keepdims=True)
    z = model.pre.normalise(torch.tensor(x, dtype=torch.float32)).numpy()
    np.testing.assert_allclose(z, ref, atol=1e-5)

    data = biotac_takes(tmp_path, frames=60)
    run = tmp_path / "run"
    train(data, run, TrainConfig(channels=("f0_pdc", *PAC), center=("f0_pac_*",), epochs=1,
                                 threads=1, batch_size=16), progress=True)
    assert "center: f0_pac as whole signals" in capsys.readouterr().err
    loaded, ck = load_checkpoint(run)
    assert ck["center_groups"] == [list(range(1, 23))] == loaded.pre.center_groups
    report = export_run(run, tmp_path / "m.onnx", log=lambda s: None)
    assert report["parity"]["passed"]
    meta = {p.key: p.value for p in onnx.load(str(tmp_path / "m.onnx")).metadata_props}
    pre = json.loads(meta["preprocessing"])
    assert pre["center_groups"] == [list(PAC)] and pre["center"] == list(PAC)
    # int8: the centring stays float (a MatMul there would be quantised with the weights)
    export_run(run, tmp_path / "q.onnx", int8=True, log=lambda s: None)
    nodes = onnx.load(str(tmp_path / "q.onnx")).graph.node
    assert not [n.name for n in nodes if n.op_type in ("MatMulInteger", "DynamicQuantizeLinear")
                and "/pre/" in n.name]
    del ck["center_groups"]  # a checkpoint saved before: each sub-sample centred by itself
    torch.save(ck, run / "checkpoint.pt")
    assert load_checkpoint(run)[0].pre.center_groups == []


def test_a_model_that_reads_sub_samples_as_channels_takes_them_in_any_order(tmp_path):
    """An lstm with front='none' reads a signal's sub-samples as plain channels (its config
    keeps [signals] as written: for gains and centring, in no time order); tactile-eval
    checked the takes' declared order against that written list and refused takes the model
    reads correctly."""
    from tactile.training.evaluate import evaluate_run
    from tactile.training.train import train

    data = biotac_takes(tmp_path, frames=60)
    run = tmp_path / "run"
    train(data, run, TrainConfig(channels=("f0_pdc", *PAC), front="none", epochs=1, threads=1,
                                 batch_size=16, signals=(("f0_pac", tuple(reversed(PAC))),)),
          progress=False)
    assert evaluate_run(run, data)["windows"] > 0  # the takes declare 00..21, the config 21..00
