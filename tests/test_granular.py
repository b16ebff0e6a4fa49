"""The granular-media models: config tables, modalities and high-rate signals, data images,
dictionaries from training windows only, the four models on a separable toy set, checkpoints.

Every test uses small synthetic takes written here; the BioTac round trip uses a small HDF5 file
in the BOLT layout (no shared data needed).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from conftest import SHARED
from test_biotac import write_h5

from tactile import native
from tactile.device.protocol import ChannelSpec, DeviceInfo
from tactile.device.recordings import TakeWriter, load_dataset, read_take
from tactile.device.recordings.biotac import import_biotac
from tactile.errors import ConfigError, RecordingError
from tactile.training import granular
from tactile.training import train as train_mod
from tactile.training.checkpoint import load_checkpoint
from tactile.training.commands.train import main as train_main
from tactile.training.config import Modality, TrainConfig
from tactile.training.data import classes_of, split_windows
from tactile.training.evaluate import evaluate_run, predict
from tactile.training.granular import GranularPre, pooled_stats, sample_rows
from tactile.training.modality import resolve, resolve_signals, signals_of_takes
from tactile.training.resume import AUGMENT_VERSION
from tactile.training.train import train

BIOTAC_TOML = """
model = "sf_rnn"
window = 50
hop = 50
[signals]
f0_pac = ["f0_pac_*"]
[modalities.vibration]
channels = ["f0_pac"]
imfs = 8
steps = 22
atoms = 200
[modalities.pressure]
channels = ["f0_pdc"]
imfs = 5
steps = 5
atoms = 100
[modalities.electrodes]
channels = ["f0_ele_*"]
imfs = 0
steps = 5
atoms = 100
"""


def biotac_names() -> tuple[str, ...]:
    from tactile.device.recordings.biotac import channels

    return tuple(c.name for c in channels())


# --- config ---------------------------------------------------------------------------------

def test_the_toml_tables_round_trip_through_to_dict(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(BIOTAC_TOML)
    cfg = TrainConfig.from_toml(path)
    assert cfg.signals == (("f0_pac", ("f0_pac_*",)),)
    assert cfg.modalities == (
        Modality("vibration", ("f0_pac",), imfs=8, steps=22, atoms=200, nonzero=0),
        Modality("pressure", ("f0_pdc",), imfs=5, steps=5, atoms=100),
        Modality("electrodes", ("f0_ele_*",), imfs=0, steps=5, atoms=100))
    d = cfg.to_dict()
    assert list(d["modalities"]) == ["vibration", "pressure", "electrodes"]  # order kept
    assert d["modalities"]["pressure"] == {"channels": ["f0_pdc"], "imfs": 5, "steps": 5,
                                           "atoms": 100, "nonzero": 0}
    assert d["signals"] == {"f0_pac": ["f0_pac_*"]}
    assert TrainConfig.from_dict(json.loads(json.dumps(d))) == cfg  # plain data both ways
    assert cfg.replace(hidden=7).modalities == cfg.modalities


@pytest.mark.parametrize("change, message", [
    ({"model": "sf_rnn", "modalities": {}}, "model='sf_rnn' needs modalities"),
    ({"model": "lstm"}, "modalities are for model="),
    ({"modalities": {"v": {"channels": ["a"], "imfs": 17}}},
     r"modalities.v.imfs=17: must be an integer 0..16"),
    ({"modalities": {"v": {"channels": ["a"], "steps": 0}}},
     r"modalities.v.steps=0: must be an integer 1..1000000"),
    ({"modalities": {"v": {"channels": ["a"], "atoms": 10, "nonzero": 11}}},
     r"modalities.v.nonzero=11: must be at most atoms=10"),
    ({"modalities": {"v": {"channels": ["a"], "atom": 10}}},
     r"modalities.v: unknown key\(s\) \['atom'\]"),
    ({"modalities": {"v": {"imfs": 2}}}, r"modalities.v: give channels"),
    ({"modalities": {"v": {"channels": []}}}, r"modalities.v.channels=\[\]: must be a non-emp"),
    ({"modalities": {"v": {"channels": "a"}}}, r"modalities.v.channels='a'"),
    ({"modalities": {"v": 3}}, r"modalities.v=3: must be a table"),
    ({"modalities": {"2v": {"channels": ["a"]}}}, r"modality name '2v'"),
    ({"modalities": ["a"]}, r"modalities=\['a'\]: must be tables"),
    ({"signals": {"s": "a_*"}}, r"signals.s='a_\*': must be a non-empty list"),
    ({"signals": ["a_*"]}, r"signals=\['a_\*'\]: must be a table"),
    ({"emd_channels": ["a"]}, r"emd_channels=\['a'\] is for the pen's models"),
])
def test_bad_tables_are_one_line_errors_naming_the_value(change, message):
    base = {"model": "sf_rnn", "modalities": {"v": {"channels": ["a"]}}}
    with pytest.raises(ConfigError, match=message) as e:
        TrainConfig.from_dict({**base, **change})
    assert "\n" not in str(e.value)


def test_set_does_not_reach_the_tables():
    from tactile.training.overrides import parse_sets

    for key in ("signals", "modalities"):
        with pytest.raises(ConfigError, match=f"--set {key}: a table .* give it in the --config"):
            parse_sets([f"{key}=a"], TrainConfig())


def test_a_bad_modality_in_a_config_file_is_exit_1_and_one_line(tmp_path, capsys):
    path = tmp_path / "c.toml"
    path.write_text(BIOTAC_TOML.replace("imfs = 8", "imfs = 80"))
    assert train_main([str(tmp_path), "--config", str(path), "--out", str(tmp_path / "r")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"tactile-train: error: {path}: modalities.vibration.imfs=80: must be an "
                   "integer 0..16"]


# --- modalities and signals resolved --------------------------------------------------------

def test_the_biotac_layout_is_the_designs():
    cfg = TrainConfig.from_dict(__import__("tomllib").loads(BIOTAC_TOML))
    vib, pdc, ele = resolve(cfg, biotac_names(), 100.0)
    assert (vib.index, vib.n, vib.r, vib.rate_hz, vib.features) == (
        tuple(range(22)), 1, 22, 2200.0, 176)
    assert vib.signal and vib.units == ("f0_pac",) and vib.frames == 1
    assert (pdc.index, pdc.n, pdc.r, pdc.features) == ((22,), 1, 1, 25)
    assert (ele.index, ele.n, ele.r, ele.features) == (tuple(range(23, 42)), 19, 1, 95)
    pre = GranularPre((vib, pdc, ele), torch.zeros(88), torch.ones(88), 50, 10, "codes")
    assert pre.steps == 46 and pre.n_features == 400 and len(pre.emds) == 2
    assert [c.n_nonzero for c in pre.coders] == [17, 2, 9]  # scikit-learn's int(features/10)


@pytest.mark.parametrize("tables, message", [
    ({"v": {"channels": ["f0_pac", "nope*"]}},
     r"modalities.v.channels: pattern 'nope\*' matches none of: f0_pac, f1_pac, f0_pdc"),
    ({"v": {"channels": ["f0_pac_0*"]}},
     r"pattern 'f0_pac_0\*' matches only sub-samples of the high-rate signal 'f0_pac': name"),
    ({"a": {"channels": ["f0_pdc"]}, "b": {"channels": ["f0_*"]}},
     r"modalities.b.channels: 'f0_pdc' is in modalities 'a' and 'b'"),
    ({"v": {"channels": ["f0_pac", "f0_pdc"]}},
     r"modalities.v.channels: mixes rates \(f0_pac \(x22\), f0_pdc \(x1\)\)"),
    ({"v": {"channels": ["f0_pdc"], "steps": 51}},
     r"modalities.v.steps=51: longer than the window \(50 frames x 1 = 50 samples at 100 Hz\)"),
    ({"v": {"channels": ["f0_pac"], "steps": 1101}},
     r"modalities.v.steps=1101: longer than the window \(50 frames x 22 = 1100 samples"),
])
def test_layout_errors_name_the_bad_value(tables, message):
    cfg = TrainConfig.from_dict({"model": "f_rnn", "modalities": tables,
                                 "signals": {"f0_pac": ["f0_pac_*"], "f1_pac": ["f1_pac_*"]}})
    with pytest.raises(ConfigError, match=message) as e:
        resolve(cfg, biotac_names(), 100.0)
    assert "\n" not in str(e.value)


def test_signal_patterns_resolve_in_recording_order_and_refuse_overlaps():
    names = ("b_1", "a", "b_0", "b_2")
    assert resolve_signals((("b", ("b_*",)),), names) == (("b", ("b_1", "b_0", "b_2")),)
    # exact names (a run's record, in time order) keep their order, whatever names' order
    assert resolve_signals((("b", ("b_2", "b_0", "b_1")),), names) == (
        ("b", ("b_2", "b_0", "b_1")),)
    with pytest.raises(ConfigError, match=r"signals.x: pattern 'z\*' matches none of: b_1"):
        resolve_signals((("x", ("z*",)),), names)
    with pytest.raises(ConfigError, match="signals.c: channel 'b_0' is already in signal 'b'"):
        resolve_signals((("b", ("b_*",)), ("c", ("b_0",))), names)
    with pytest.raises(ConfigError, match="signals.a: a channel has that name"):
        resolve_signals((("a", ("b_*",)),), names)


# --- high-rate declarations: import -> JSON -> resolve -> the signal ----------------------

def test_the_biotac_declaration_round_trips_to_the_2200_hz_signal(tmp_path):
    written = write_h5(tmp_path / "cork.h5", {"cork_pdc100_1cm_01": 30})
    import_biotac([tmp_path / "cork.h5"], tmp_path / "data")
    meta = json.loads((tmp_path / "data" / "cork_pdc100_1cm_01.json").read_text())
    assert meta["signals"] == {f"f{k}_pac": [f"f{k}_pac_{i:02d}" for i in range(22)]
                               for k in (0, 1)}
    takes = load_dataset(tmp_path / "data")
    channels = takes[0].channels
    signals = signals_of_takes(takes, channels)
    assert signals == tuple((f"f{k}_pac", tuple(f"f{k}_pac_{i:02d}" for i in range(22)))
                            for k in (0, 1))
    cfg = TrainConfig(model="f_rnn", window=30, modalities=(
        Modality("vibration", ("f*_pac",), imfs=0, steps=22),))
    (vib,) = resolve(cfg, channels, 100.0, signals)
    assert vib.units == ("f0_pac", "f1_pac") and vib.r == 22 and vib.rate_hz == 2200.0
    pre = GranularPre((vib,), torch.zeros(88), torch.ones(88), 30, 10, "images")
    x = torch.from_numpy(takes[0].values()).float()[None]  # (1, 30, 88)
    sig = pre._units(pre.normalise(x), 0)  # (1, n = 2, 30 x 22)
    group = written["cork_pdc100_1cm_01"]
    for k in (0, 1):  # the 660 samples of each finger: frame after frame, sub-samples in order
        assert sig[0, k].numpy().tolist() == group[f"finger_{k}/pac"].reshape(-1).tolist()


def _bad_signals_take(tmp_path, signals):
    info = DeviceInfo(100.0, (ChannelSpec("v_0", ""), ChannelSpec("v_1", ""),
                              ChannelSpec("p", "")))
    with TakeWriter(tmp_path, "a", info, name="t", extra={"signals": signals}) as w:
        w.write(0, 0, np.zeros((5, 3), np.int64))
    return tmp_path / "t.csv"


@pytest.mark.parametrize("signals, message", [
    ({"v": ["v_0", "v_9"]}, r"key 'signals.v': channel 'v_9' is not one of the take's"),
    ({"v": ["v_0", "v_1"], "w": ["v_1"]}, r"key 'signals.w': channel 'v_1' is in signal 'v'"),
    ({"p": ["v_0", "v_1"]}, r"key 'signals.p': a channel has that name"),
    ({"v": []}, r"key 'signals' must be an object of signal name -> non-empty list"),
    ({"v": "v_0"}, r"key 'signals' must be an object of signal name -> non-empty list"),
])
def test_a_bad_declaration_is_a_recording_error_naming_the_file(tmp_path, signals, message):
    path = _bad_signals_take(tmp_path, signals)
    with pytest.raises(RecordingError, match=message) as e:
        read_take(path)
    assert str(e.value).startswith(str(tmp_path / "t.json"))


def test_a_bad_declaration_stops_training_with_exit_1(tmp_path, capsys):
    _bad_signals_take(tmp_path, {"v": ["v_0", "nope"]})
    assert train_main([str(tmp_path), "--out", str(tmp_path / "run"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "key 'signals.v': channel 'nope'" in err[0]


def test_takes_that_declare_other_signals_are_refused(tmp_path):
    takes = []
    for name, sig in (("t1", {"v": ["v_0", "v_1"]}), ("t2", {"v": ["v_1", "v_0"]})):
        folder = tmp_path / name
        folder.mkdir()
        _bad_signals_take(folder, sig)
        takes.append(read_take(folder / "t.csv"))
    with pytest.raises(ConfigError, match=r"t.csv: declares signals \{'v': \('v_1', 'v_0'\)\}"):
        signals_of_takes(takes, takes[0].channels)


# --- images: shapes and order against hand-computed examples --------------------------------

def _layout(tables: dict, channels: tuple[str, ...], window: int, signals=None):
    cfg = TrainConfig.from_dict({"model": "f_rnn", "window": window, "modalities": tables,
                                 "signals": signals or {}})
    return resolve(cfg, channels, 100.0)


def test_images_hold_the_last_steps_samples_at_each_modalitys_rate():
    # a signal s of 3 sub-samples per frame (300 Hz) with images of 4 samples (spanning 2
    # frames), a plain channel c with images of 2 frames; T = 4 -> S = 4 - 2 + 1 = 3 steps
    channels = ("s_0", "s_1", "s_2", "c")
    layout = _layout({"sig": {"channels": ["s"], "steps": 4}, "chan": {"channels": ["c"],
                      "steps": 2}}, channels, 4, {"s": ["s_*"]})
    pre = GranularPre(layout, torch.zeros(4), torch.ones(4), 4, 10, "images")
    t = torch.arange(4.0)[:, None]
    x = torch.cat([100 * t + torch.arange(3.0), 1000 + t], 1)[None]  # s: 100 t + j, c: 1000 + t
    f = pre(x)
    assert f.shape == (1, 3, 6) and pre.n_features == 6
    assert f[0].tolist() == [[2, 100, 101, 102, 1000, 1001],
                             [102, 200, 201, 202, 1001, 1002],
                             [202, 300, 301, 302, 1002, 1003]]


def test_image_features_are_unit_then_imf_then_time():
    layout = _layout({"m": {"channels": ["c*"], "imfs": 2, "steps": 3}}, ("c0", "c1"), 4)
    pre = GranularPre(layout, torch.zeros(2), torch.ones(2), 4, 10, "images")
    n, k, el = torch.meshgrid(torch.arange(2.0), torch.arange(2.0), torch.arange(4.0),
                              indexing="ij")
    imfs = (1000 * n + 100 * k + el)[None]  # (1, n=2, K=2, L=4): unit, IMF, sample
    f = pre.finish(torch.zeros(1, 4, 2), [imfs])  # S = 4 - 3 + 1 = 2 steps of 3 samples
    assert f[0].tolist() == [[0, 1, 2, 100, 101, 102, 1000, 1001, 1002, 1100, 1101, 1102],
                             [1, 2, 3, 101, 102, 103, 1001, 1002, 1003, 1101, 1102, 1103]]


def test_energy_features_are_log_imf_energies_and_mean_log_std():
    layout = _layout({"a": {"channels": ["c0"], "imfs": 2}, "b": {"channels": ["c1"]}},
                     ("c0", "c1"), 5)
    pre = GranularPre(layout, torch.zeros(2), torch.ones(2), 5, 10, "energy")
    rng = np.random.default_rng(0)
    imfs = rng.normal(size=(1, 1, 2, 5))
    z = rng.normal(size=(1, 5, 2))
    f = pre.finish(torch.from_numpy(z).float(), [torch.from_numpy(imfs).float()])
    want = [math.log((imfs[0, 0, 0] ** 2).mean() + 1e-6), math.log((imfs[0, 0, 1] ** 2).mean()
            + 1e-6), z[0, :, 1].mean(), 0.5 * math.log(z[0, :, 1].var() + 1e-6)]
    assert f.shape == (1, 1, 4) == (1, 1, pre.n_features)
    np.testing.assert_allclose(f[0, 0].numpy(), want, rtol=1e-5, atol=1e-6)


def test_a_signal_shares_one_pooled_mean_and_std():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(7, 10, 3)) * [1.0, 3.0, 5.0] + [0.0, 10.0, -4.0]
    mean, std = pooled_stats(x, ("s_0", "s_1", "c"), (("s", ("s_0", "s_1")),))
    both = x[:, :, :2].reshape(-1)
    np.testing.assert_allclose(mean, [both.mean(), both.mean(), x[:, :, 2].mean()], rtol=1e-5)
    np.testing.assert_allclose(std, [both.std(), both.std(), x[:, :, 2].std()], rtol=1e-5)


@pytest.mark.parametrize("mode", ["images", "codes", "energy"])
def test_a_gain_on_the_features_is_the_gain_on_the_channels(mode):
    """augment_gain on the features computed once (GranularModel.augment_gain) is what the
    features of the window with each modality's channels scaled about their training mean
    would be: a 2-unit modality with IMFs (one gain for both), a high-rate signal with IMFs,
    and channels without (their mean scales, their log std shifts). Reference: the features
    recomputed from the scaled window, EMD and codes included."""
    channels = ("a0", "a1", "s_0", "s_1", "e0", "e1", "e2")
    tables = {"acc": {"channels": ["a*"], "imfs": 3, "steps": 4, "atoms": 12},
              "sig": {"channels": ["s"], "imfs": 2, "steps": 6, "atoms": 10},
              "ele": {"channels": ["e*"], "steps": 3, "atoms": 8}}
    layout = _layout(tables, channels, 30, {"s": ["s_*"]})
    rng = np.random.default_rng(7)
    mean = torch.tensor([5.0, -3.0, 40.0, 40.0, 900.0, 1100.0, 1000.0])
    std = torch.tensor([2.0, 1.0, 8.0, 8.0, 30.0, 20.0, 25.0])
    pre = GranularPre(layout, mean, std, 30, 6, mode)
    if mode == "codes":  # random unit-norm atoms
        pre.set_dictionaries([d / np.linalg.norm(d, axis=1, keepdims=True) for d in (
            rng.normal(size=(m.atoms, m.features)).astype(np.float32) for m in layout)])
    t = np.arange(30)[None, :, None]
    x = mean.numpy() + std.numpy() * (np.sin(0.7 * t + rng.uniform(0, 6, (5, 1, 7)))
                                      + 0.5 * rng.normal(size=(5, 30, 7)))
    x = torch.from_numpy(x.astype(np.float32))  # (5 windows, 30 frames, 7 channels)
    gains = torch.tensor([[0.7, 1.25, 1.1], [1.3, 0.8, 0.75], [1.0, 1.0, 1.0],
                          [0.9, 1.15, 1.28], [1.2, 0.72, 0.95]])  # (5, modalities)
    per_channel = gains[:, [0, 0, 1, 1, 2, 2, 2]]  # each channel's modality
    scaled = mean + per_channel[:, None, :] * (x - mean)
    with torch.no_grad():
        want = pre(scaled)
        got = pre.apply_gain(pre(x), gains[:, None, :])
    assert got.shape == want.shape == (5, 1 if mode == "energy" else 27, pre.n_features)
    # float32 EMD and coding on both sides: 1e-4 of each window's feature scale
    scale = want.abs().amax(dim=(1, 2), keepdim=True)
    assert ((got - want).abs() / scale).max() < 1e-4
    assert ((pre(x) - want).abs() / scale).max() > 0.05  # the gains do change the features


def test_augment_gain_draws_one_gain_per_window_and_modality():
    layout = _layout({"a": {"channels": ["c0"], "imfs": 2, "steps": 2},
                      "b": {"channels": ["c1", "c2"], "steps": 2}}, ("c0", "c1", "c2"), 6)
    cfg = TrainConfig.from_dict({"model": "f_rnn", "window": 6, "layers": 1, "hidden": 4,
                                 "modalities": {"a": {"channels": ["c0"], "imfs": 2, "steps": 2},
                                                "b": {"channels": ["c1", "c2"], "steps": 2}}})
    model = granular.GranularModel(cfg, 2, layout, torch.zeros(3), torch.ones(3))
    f = torch.ones(4, 1, 5, model.pre.n_features)  # (B, S, steps, F): every feature 1
    out = model.augment_gain(f, 0.3, torch.Generator().manual_seed(0))
    a, b = out[..., :4], out[..., 4:]  # modality a: 1 unit x 2 IMFs x 2; b: 2 units x 2
    assert torch.equal(a, a[..., :1].expand_as(a)) and torch.equal(b, b[..., :1].expand_as(b))
    assert torch.equal(out, out[:, :, :1].expand_as(out))  # the same gain at every step
    g = torch.cat([a[:, 0, 0, 0], b[:, 0, 0, 0]])
    assert ((g - 1).abs() <= 0.3).all() and len(set(g.tolist())) == 8  # drawn per window


def test_input_scale_is_the_median_window_rms_of_each_feature():
    rng = np.random.default_rng(3)
    n, steps = 41, 6
    loud = np.where(rng.random(n) < 0.1, 40.0, 1.0)  # heavy-tailed: a few loud windows
    f = rng.normal(size=(n, steps, 4)) * loud[:, None, None] * [1.0, 0.01, 1.0, 1.0]
    f[: n // 2 + 1, :, 2] = 0.0  # zero in most windows: the RMS over all windows instead
    f[:, :, 3] = 0.0  # always zero: 1
    got = granular.input_scale(torch.from_numpy(f).float()).numpy()
    rms = np.sqrt((f ** 2).mean(axis=1))  # (N, F), float64
    want = [np.median(rms[:, 0]), np.median(rms[:, 1]), np.sqrt((rms[:, 2] ** 2).mean()), 1.0]
    np.testing.assert_allclose(got, want, rtol=1e-5)
    assert got[0] < 0.2 * f[:, :, 0].std()  # the typical window, not the loud ones' scale


def test_forget_bias_lstm_starts_its_forget_gates_at_1_and_keeps_it_on_reset():
    torch.manual_seed(0)
    lstm = granular.ForgetBiasLSTM(5, 4, 3, batch_first=True)
    plain = torch.nn.LSTM(5, 4, 3, batch_first=True)
    assert list(lstm.state_dict()) == list(plain.state_dict())  # exports as nn.LSTM
    for _ in range(2):  # as built, and after a refit's reset_parameters
        for k in range(3):
            b_ih, b_hh = getattr(lstm, f"bias_ih_l{k}"), getattr(lstm, f"bias_hh_l{k}")
            assert torch.equal(b_ih[4:8], torch.ones(4)) and torch.equal(b_hh[4:8], torch.zeros(4))
            assert b_ih[:4].abs().max() > 0 and b_ih[8:].abs().max() > 0  # the others: random
        lstm.reset_parameters()


def test_a_4_layer_f_rnn_carries_its_input_to_the_top_at_initialisation():
    """The cause of the F-RNN runs that never left the untrained loss: with forget-gate bias 0
    each of the 4 LSTM layers passed about a quarter of its input's variation on, so the top
    layer's output hardly depended on the window and the loss gradient on the input weights
    was smaller than the weight decay's. With bias 1 the top layer's output varies over
    windows several times more (median over 5 initialisations, 4 x 50, 46 steps)."""
    x = torch.randn(64, 46, 20, generator=torch.Generator().manual_seed(0))

    def top_variation(cls, seed):
        torch.manual_seed(seed)
        with torch.no_grad():
            y, _ = cls(20, 50, 4, batch_first=True)(x)
        return float(y[:, -1].std(0).mean())  # over windows, at the last step

    ratios = [top_variation(granular.ForgetBiasLSTM, s) / top_variation(torch.nn.LSTM, s)
              for s in range(5)]
    assert np.median(ratios) > 3, ratios


def test_sample_rows_is_capped_seeded_and_without_repeats():
    a, b = sample_rows(1000, 300, 4), sample_rows(1000, 300, 4)
    assert len(a) == 300 == len(set(a.tolist())) and np.array_equal(a, b)
    assert not np.array_equal(a, sample_rows(1000, 300, 5))
    assert sample_rows(50, 300, 4).tolist() == list(range(50))


# --- training on a separable toy set --------------------------------------------------------

TOY = ("a", "b")


def _toy_dataset(folder, takes_per_class: int = 5, frames: int = 240, seed: int = 0):
    """Two classes: ``a`` vibrates (a 25 Hz tone plus noise on the 400 Hz signal v), presses
    harder and lifts electrode e0; ``b`` only has noise. Signals declared in the JSON."""
    rng = np.random.default_rng(seed)
    chans = ([ChannelSpec(f"v_{i}", "count") for i in range(4)]
             + [ChannelSpec("p", "count"), ChannelSpec("e0", "count"), ChannelSpec("e1", "count")])
    info = DeviceInfo(100.0, tuple(chans))
    for label in TOY:
        for k in range(takes_per_class):
            t = np.arange(frames * 4) / 400.0
            vib = rng.normal(0, 20, frames * 4)
            if label == "a":
                vib += 60 * np.sin(2 * np.pi * 25 * t + rng.uniform(0, 6))
            p = 500 + rng.normal(0, 10, frames) + (60 if label == "a" else 0)
            e = rng.normal(1000, 10, (frames, 2)) + ([50, 0] if label == "a" else [0, 0])
            raw = np.column_stack([vib.reshape(frames, 4), p, e]).round().astype(np.int64)
            with TakeWriter(folder, label, info, name=f"{label}_{k}",
                            extra={"signals": {"v": [f"v_{i}" for i in range(4)]}}) as w:
                w.write(0, 0, raw)
    return folder


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    return _toy_dataset(tmp_path_factory.mktemp("toy"))


def _cfg(model: str, **kw) -> TrainConfig:
    return TrainConfig.from_dict({
        "model": model, "window": 20, "hop": 10, "split": "take", "test": "name:*_4",
        "val": "name:*_3", "epochs": 15, "patience": 15, "layers": 1, "hidden": 16,
        "batch_size": 32, "lr": 1e-2, "augment_gain": 0.0, "dropout": 0.1, "threads": 1,
        "emd_sifts": 5,
        "modalities": {"vibration": {"channels": ["v"], "imfs": 3, "steps": 8, "atoms": 20},
                       "pressure": {"channels": ["p"], "imfs": 2, "steps": 4, "atoms": 10},
                       "electrodes": {"channels": ["e*"], "steps": 3, "atoms": 10}}, **kw})


@pytest.fixture(scope="module")
def runs(toy, tmp_path_factory):
    """Each model trained on the toy set, with the model object as it was saved."""
    out = {}
    saved = {}
    real = train_mod.write_run

    def spy(run_dir, cfg, model, *args, **kwargs):
        saved[cfg.model] = model
        return real(run_dir, cfg, model, *args, **kwargs)

    train_mod.write_run = spy
    try:
        for model in ("sf_rnn", "f_rnn", "sparse_linear", "linear"):
            run = tmp_path_factory.mktemp(model)
            metrics = train(toy, run, _cfg(model), progress=False)
            out[model] = (run, metrics, saved[model])
    finally:
        train_mod.write_run = real
    return out


@pytest.mark.parametrize("model", ["sf_rnn", "f_rnn", "sparse_linear", "linear"])
def test_each_model_beats_chance_on_a_separable_toy_set(runs, model):
    _, m, _ = runs[model]
    assert m["windows"] == 46  # 2 takes x 23 windows of 20 frames every 10
    assert m["accuracy"] >= 0.9, m["accuracy"]  # chance: 0.5
    # a hop of 10 frames divides every shift: the shifted windows would be the test windows
    assert set(m["shifted"]) == {"not_measured"}


@pytest.mark.parametrize("model", ["sf_rnn", "f_rnn", "sparse_linear", "linear"])
def test_the_checkpoint_rebuilds_the_model_exactly(runs, toy, model):
    run, metrics, trained = runs[model]
    loaded, ck = load_checkpoint(run)
    assert ck["config"]["modalities"]["vibration"]["atoms"] == 20
    assert ck["config"]["signals"] == {"v": ["v_0", "v_1", "v_2", "v_3"]}  # from the takes
    takes = load_dataset(toy)
    _, parts = split_windows(takes, classes_of(takes), loaded.cfg.channels, loaded.cfg)
    trained.eval()
    x = torch.from_numpy(parts["test"].x)
    h, c = loaded.zero_state(len(x))
    with torch.no_grad():
        assert torch.equal(loaded(x, h, c)[0], trained(x, h, c)[0])
    if model in ("sf_rnn", "sparse_linear"):  # the learned dictionaries came back
        for a, b in zip(loaded.pre.coders, trained.pre.coders):
            assert torch.equal(a.dictionary, b.dictionary) and a.dictionary.abs().sum() > 0
    probs = predict(loaded, parts["test"])
    assert float((probs.argmax(1) == parts["test"].y).mean()) == metrics["accuracy"]


def test_an_f_rnn_saved_before_the_input_scale_is_refused_in_one_line(runs, tmp_path):
    """An F-RNN checkpoint with the batch normalisations the input scale replaced (its keys
    renamed as they were) is a RecordingError that says what to do, not a key dump."""
    run, _, _ = runs["f_rnn"]
    ck = torch.load(run / "checkpoint.pt", weights_only=True)
    sd = ck["state_dict"]
    scale = sd.pop("head.scale")
    sd["head.norms.0.weight"], sd["head.norms.0.bias"] = torch.ones_like(scale), 0 * scale
    torch.save(ck, tmp_path / "checkpoint.pt")
    with pytest.raises(RecordingError, match="an F-RNN saved before its input scale replaced "
                       "batch normalisation: train it again") as e:
        load_checkpoint(tmp_path)
    assert "\n" not in str(e.value)


def test_an_f_rnn_resume_state_from_before_the_input_scale_is_refused(toy, tmp_path):
    """The resume path's check of the same old F-RNN head: one line, not a key dump."""
    import signal

    from tactile.training.checkpoint import RESUME, load_resume

    def stop_after_first(phase, epoch):
        if (phase, epoch) == ("fit", 1):
            signal.raise_signal(signal.SIGINT)

    run = tmp_path / "r"
    cfg = _cfg("f_rnn", epochs=3)
    assert train(toy, run, cfg, progress=False, on_epoch=stop_after_first)["interrupted"]
    saved = torch.load(run / RESUME, weights_only=True)
    head = saved["state"]["head"]
    scale = head.pop("scale")
    head["norms.0.weight"], head["norms.0.bias"] = torch.ones_like(scale), 0 * scale
    torch.save(saved, run / RESUME)
    r = load_resume(run)
    with pytest.raises(RecordingError, match="an F-RNN saved before its input scale replaced "
                       "batch normalisation: train it again") as e:
        train(toy, run, TrainConfig.from_dict(r["config"]), progress=False, resume=r["state"])
    assert "\n" not in str(e.value)


def test_a_granular_resume_state_from_before_per_modality_gains_is_refused(toy, tmp_path):
    """Granular models now draw one gain per window and modality: a resume state without the
    augmentation's version, with gains on, cannot continue the run it started; without gains
    it can."""
    import signal

    from tactile.training.checkpoint import RESUME, load_resume

    def stop_after_first(phase, epoch):
        if (phase, epoch) == ("fit", 1):
            signal.raise_signal(signal.SIGINT)

    run = tmp_path / "r"
    cfg = _cfg("sparse_linear", epochs=3, augment_gain=0.3)
    assert train(toy, run, cfg, progress=False, on_epoch=stop_after_first)["interrupted"]
    assert load_resume(run)["state"]["augment_version"] == AUGMENT_VERSION
    saved = torch.load(run / RESUME, weights_only=True)
    del saved["state"]["augment_version"]
    torch.save(saved, run / RESUME)
    with pytest.raises(RecordingError, match="saved before granular models drew one gain per "
                       "window and modality"):
        load_resume(run)
    saved["config"]["augment_gain"] = 0.0  # no gains: nothing changed for it
    torch.save(saved, run / RESUME)
    assert load_resume(run)["config"]["augment_gain"] == 0.0


def test_a_linear_run_resumes_its_full_batch_fit_and_refuses_an_adam_state(toy, tmp_path):
    """The linear model's L-BFGS fit stopped by Ctrl-C after an epoch continues from its saved
    optimiser state to the weights of an uninterrupted run; a state saved with Adam (by a
    version that trained it so) is refused in one line."""
    import signal

    from tactile.training.checkpoint import RESUME, load_resume

    def stop_after_first(phase, epoch):
        if (phase, epoch) == ("fit", 1):
            signal.raise_signal(signal.SIGINT)

    cfg = _cfg("linear", epochs=4, patience=4)
    whole = tmp_path / "whole"
    train(toy, whole, cfg, progress=False)
    run = tmp_path / "r"
    assert train(toy, run, cfg, progress=False, on_epoch=stop_after_first)["interrupted"]
    r = load_resume(run)
    assert r["state"]["optimizer"] == "LBFGS"
    saved = torch.load(run / RESUME, weights_only=True)
    train(toy, run, TrainConfig.from_dict(r["config"]), progress=False, resume=r["state"])
    a = torch.load(whole / "checkpoint.pt", weights_only=True)["state_dict"]
    b = torch.load(run / "checkpoint.pt", weights_only=True)["state_dict"]
    for k in a:
        assert torch.equal(a[k], b[k]), k
    del saved["state"]["optimizer"]  # as saved before the key: Adam's
    run2 = tmp_path / "r2"
    run2.mkdir()
    with pytest.raises(RecordingError, match="trained this model with Adam, this one trains it "
                       "with LBFGS: train it again") as e:
        train(toy, run2, TrainConfig.from_dict(saved["config"]), progress=False,
              resume=saved["state"])
    assert "\n" not in str(e.value)


def test_the_f_rnn_input_scale_comes_from_the_training_windows(runs, toy):
    _, _, model = runs["f_rnn"]
    takes = load_dataset(toy)
    _, parts = split_windows(takes, classes_of(takes), model.cfg.channels, model.cfg)
    with torch.no_grad():
        images = {k: model.pre(torch.from_numpy(w.x)).double().numpy() for k, w in parts.items()}
    # the median of an even count is the lower of the two middle values
    median_rms = {k: np.sort(np.sqrt((v ** 2).mean(axis=1)), axis=0)[(len(v) - 1) // 2]
                  for k, v in images.items()}
    got = model.head.scale.numpy()
    np.testing.assert_allclose(got, median_rms["train"], rtol=1e-5)  # float32 images
    for other in ("val", "test"):  # the toy's splits differ enough to tell them apart
        assert np.abs(got / median_rms[other] - 1).max() > 1e-3


def test_tactile_eval_reads_a_granular_run(runs, toy):
    run, metrics, _ = runs["sf_rnn"]
    s = evaluate_run(run, toy, threads=1)
    assert s["accuracy"] == metrics["accuracy"] and s["shifted"] == metrics["shifted"]


def test_dictionaries_are_learned_from_training_windows_only(toy, tmp_path, monkeypatch):
    fitted = []
    real = granular.fit_dictionary

    def spy(rows, m, seed):
        fitted.append((m.name, rows.copy()))
        return real(rows, m, seed)

    monkeypatch.setattr(granular, "fit_dictionary", spy)
    cfg = _cfg("sparse_linear", epochs=1)
    train(toy, tmp_path / "run", cfg, progress=False)
    model, _ = load_checkpoint(tmp_path / "run")
    takes = load_dataset(toy)
    _, parts = split_windows(takes, classes_of(takes), model.cfg.channels, model.cfg)
    with torch.no_grad():
        images = {k: model.pre.images(torch.from_numpy(w.x)) for k, w in parts.items()}
    assert [name for name, _ in fitted] == ["vibration", "pressure", "electrodes"]
    at = 0
    for (name, rows), m in zip(fitted, model.layout):
        flat = {k: v[:, :, at : at + m.features].reshape(-1, m.features).numpy()
                for k, v in images.items()}
        train_rows = flat["train"]
        assert len(rows) == len(train_rows)  # every training row (fewer than the cap)
        for split in ("val", "test"):
            other = flat[split]
            near = np.abs(rows[:, None, :] - other[None, :, :]).max(2).min(1)
            assert near.min() > 1e-3, (name, split)  # no row of theirs was learned from
        near = np.abs(rows[:, None, :] - train_rows[None, :, :]).max(2).min(1)
        assert near.max() < 1e-4, name  # each is a training row
        at += m.features


def test_two_processes_share_rank_0s_dictionaries(toy, tmp_path):
    """torchrun, 2 processes (gloo on loopback): rank 0 learns the dictionaries from the whole
    training split and broadcasts them; each process codes its share of the windows with them.
    The run's test figures must then be what one process computes from the checkpoint."""
    import os
    import subprocess
    import sys

    from test_train_ddp import free_port

    # test takes of both classes in each process's half of the test windows (rows 0-34:
    # a_3, a_4; 35-68: a_4, b_4), so that codes made with other dictionaries in one of the
    # processes would change the run's figures
    cfg = _cfg("sf_rnn", epochs=8, test="name:a_3,a_4,b_4", val="name:a_2,b_2")
    toml = tmp_path / "c.toml"
    toml.write_text(_toml(cfg.to_dict()))
    env = {**os.environ, "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", "2",
           "--master-addr", "127.0.0.1", "--master-port", str(free_port()),
           "-m", "tactile.training.commands.train", str(toy), "--out", str(tmp_path / "run"),
           "--config", str(toml), "--quiet"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    model, ck = load_checkpoint(tmp_path / "run")
    assert ck["metrics"]["processes"] == 2
    s = evaluate_run(tmp_path / "run", toy, threads=1)  # one process, the saved dictionaries
    assert s["confusion"] == ck["metrics"]["confusion"]
    assert s["accuracy"] >= 0.9, s["accuracy"]


def _toml(d: dict) -> str:
    """A config dict as TOML (flat keys, then [signals] and [modalities.NAME] tables)."""
    def value(v):
        return json.dumps(v) if not isinstance(v, bool) else str(v).lower()

    lines = [f"{k} = {value(v)}" for k, v in d.items() if k not in ("signals", "modalities")]
    if d["signals"]:
        lines += ["[signals]"] + [f"{k} = {value(v)}" for k, v in d["signals"].items()]
    for name, m in d["modalities"].items():
        lines += [f"[modalities.{name}]"] + [f"{k} = {value(v)}" for k, v in m.items()]
    return "\n".join(lines) + "\n"


@pytest.mark.skipif(not (SHARED / "datasets" / "biotac-bolt").is_dir(),
                    reason=f"BioTac BOLT recordings absent ({SHARED / 'datasets' / 'biotac-bolt'})")
def test_a_real_trial_gives_the_designs_images(tmp_path):
    """One real trial (copied into a temporary file): its take declares the vibration signal,
    and a window's images are the normalised sub-samples and electrode values of the right
    frames (imfs = 0 here, so that the values can be checked against the HDF5 file)."""
    import tomllib

    import h5py

    bolt, group = SHARED / "datasets" / "biotac-bolt", "cork_pdc150_1cm_04"
    with h5py.File(bolt / "cork.h5", "r") as src, h5py.File(tmp_path / "cork.h5", "w") as dst:
        src.copy(src[group], dst, name=group)
        pac = src[group]["finger_0/pac"][()].astype(np.float64)  # (T, 22)
        ele = src[group]["finger_0/electrodes"][()].astype(np.float64)  # (T, 19)
    import_biotac([tmp_path / "cork.h5"], tmp_path / "data")
    takes = load_dataset(tmp_path / "data")
    d = tomllib.loads(BIOTAC_TOML)
    del d["signals"]  # the take's own declaration
    d["modalities"]["vibration"]["imfs"] = 0
    cfg = TrainConfig.from_dict(d)
    channels = takes[0].channels
    layout = resolve(cfg, channels, 100.0, signals_of_takes(takes, channels))
    x = takes[0].values()[None, 100:150].astype(np.float32)  # frames 100..149
    mean, std = pooled_stats(takes[0].values()[None], channels, signals_of_takes(takes, channels))
    pre = GranularPre(layout, torch.from_numpy(mean), torch.from_numpy(std), 50, 10, "images")
    f = pre(torch.from_numpy(x))[0].numpy()
    assert f.shape == (46, 22 + 25 + 95)  # vibration 1 x 22, pressure 5 IMFs x 5, 19 x 5
    for s in (0, 17, 45):  # step s ends with frame 100 + 4 + s
        t = 104 + s
        np.testing.assert_allclose(f[s, :22], (pac[t] - pac.mean()) / pac.std(), atol=1e-4)
        want = ((ele[t - 4 : t + 1] - ele.mean(0)) / ele.std(0)).T.reshape(-1)  # (unit, time)
        np.testing.assert_allclose(f[s, 47:], want, atol=1e-4)


@pytest.mark.skipif(not native.available(), reason="the native kernels are not built")
def test_training_does_not_depend_on_whether_the_kernels_are_built(toy, tmp_path, monkeypatch):
    """The feature pass (EMD and codes of every window) runs in float64 on the kernels or in
    torch: the same run twice, once with TACTILE_NATIVE=0, gives the same weights bit for bit
    and the same figures; the first run's EMDs and codes come from the kernels, the second's
    from torch."""
    calls = {"emd": 0, "omp": 0}

    def counted(name):
        kernel = getattr(native, name)

        def call(*args, **kwargs):
            calls[name] += 1
            return kernel(*args, **kwargs)
        return call

    for name in calls:
        monkeypatch.setattr(native, name, counted(name))
    cfg = _cfg("sf_rnn", epochs=3, patience=3, refit="off")
    fast = train(toy, tmp_path / "kernels", cfg, progress=False)
    assert calls["emd"] > 0 and calls["omp"] > 0, calls
    monkeypatch.setenv("TACTILE_NATIVE", "0")
    assert not native.available()
    before = dict(calls)
    slow = train(toy, tmp_path / "torch", cfg, progress=False)
    assert calls == before, calls
    a, _ = load_checkpoint(tmp_path / "kernels")
    b, _ = load_checkpoint(tmp_path / "torch")
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    for k in sa:
        assert torch.equal(sa[k], sb[k]), k
    for k in ("accuracy", "val_accuracy", "best_epoch"):
        assert fast[k] == slow[k], k


@pytest.mark.parametrize("r,steps", [(22, 22), (22, 5), (1, 5), (2, 3), (5, 12), (1, 20)])
def test_images_cut_with_slices_are_each_steps_samples(r, steps):
    """A modality's image of step s holds the ``steps`` samples that end with frame
    ``first + s``: cut with slices of whole frames (an image of at most MAX_SLICES frames) or
    one gather (longer ones), each the same numbers as indexing those samples directly."""
    window, n, k = 30, 3, 4
    q = -(-steps // r)  # frames one image spans
    first = q + 1  # another modality's longer images start the steps later
    n_steps = window - first
    start = (first + 1) * r - steps
    x = torch.randn(2, n, k, window * r)
    want = torch.stack([x[..., start + r * s : start + r * s + steps]
                        for s in range(n_steps)], dim=1)  # (B, S, n, K, steps)
    m = type("Layout", (), {"r": r, "steps": steps, "n": n, "imfs": k})()
    pre = type("Pre", (), {"layout": [m], "steps": n_steps, "image_starts": [start],
                           "image_0": torch.arange(0)})()
    if q > granular.MAX_SLICES:  # the gather path reads the image positions
        pre.image_0 = (start + r * torch.arange(n_steps)[:, None]
                       + torch.arange(steps)).flatten()
    got = granular.GranularPre._image(pre, x, 0)
    assert torch.equal(got, want.reshape(2, n_steps, n * k * steps))


def test_the_linear_model_is_fitted_to_the_optimum_of_its_objective():
    """model = "linear" (mean-pooled features, one linear layer) trains full-batch with L-BFGS:
    after a few epochs its weights minimise cross-entropy + weight_decay / 2 x |weights|^2 on
    the standardised features, the optimum that scipy's L-BFGS-B finds on the same objective
    written in numpy (an independent reference). Mini-batch Adam stops short of it."""
    from scipy.optimize import minimize

    from tactile.training.dist import Dist
    from tactile.training.log import Log
    from tactile.training.loop import Context, Phase, _full_batch_epoch, full_batch
    from tactile.training.resume import Live

    rng = np.random.default_rng(4)
    n, steps, feats, classes, decay = 600, 3, 7, 4, 1e-3
    centres = rng.standard_normal((classes, feats)) * 0.8
    y = rng.integers(0, classes, n)
    f = torch.tensor(centres[y][:, None, :] + rng.standard_normal((n, steps, feats)) * 1.5,
                     dtype=torch.float32)  # (N, S, F): overlapping classes
    torch.manual_seed(0)
    head = granular.PooledLinearHead(feats, classes, "mean")
    assert head.full_batch and not granular.PooledLinearHead(feats, classes, "abs_mean").full_batch
    cfg = TrainConfig(weight_decay=decay, augment_gain=0.0)
    model = type("M", (), {"head": head, "offset_scale": lambda self: None})()
    assert full_batch(model, cfg, Dist())
    pooled = head.pooled(f)
    head.set_norm(pooled)
    opt = torch.optim.LBFGS(head.parameters(), lr=1.0, max_iter=20, history_size=20,
                            line_search_fn="strong_wolfe")
    live = Live(head, opt, None, torch.Generator(), torch.Generator())
    data = Phase(None, torch.nn.CrossEntropyLoss(), n, None, np.arange(n)[:, None], f,
                 torch.from_numpy(y).long())
    ctx = Context(cfg, Log(False), Dist(), torch.device("cpu"))
    for _ in range(10):
        _full_batch_epoch(live, data, pooled, ctx)

    # the reference: the same objective in numpy, minimised by scipy
    z = pooled.double().numpy()
    z = (z - z.mean(0)) / np.sqrt(z.var(0, ddof=1) + head.norm.eps)

    def objective(theta):
        w, b = theta[: classes * feats].reshape(classes, feats), theta[classes * feats :]
        logits = z @ w.T + b
        logits -= logits.max(1, keepdims=True)
        logp = logits - np.log(np.exp(logits).sum(1, keepdims=True))
        p = np.exp(logp)
        onehot = np.eye(classes)[y]
        loss = -(logp * onehot).sum() / n + 0.5 * decay * (theta @ theta)
        g_logits = (p - onehot) / n
        grad = np.concatenate([(g_logits.T @ z).ravel(), g_logits.sum(0)]) + decay * theta
        return loss, grad

    ref = minimize(objective, np.zeros(classes * (feats + 1)), jac=True, method="L-BFGS-B",
                   options={"maxiter": 5000, "gtol": 1e-10, "ftol": 1e-15})
    ours = np.concatenate([head.out.weight.detach().double().numpy().ravel(),
                           head.out.bias.detach().double().numpy()])
    assert objective(ours)[0] <= ref.fun + 1e-6, (objective(ours)[0], ref.fun)
    np.testing.assert_allclose(ours, ref.x, atol=2e-3)

    # mini-batch Adam at the toolkit's rate, 10 epochs of batches of 128: short of it
    torch.manual_seed(0)
    adam_head = granular.PooledLinearHead(feats, classes, "mean")
    adam_head.set_norm(pooled)
    adam_head.norm.eval()
    adam = torch.optim.Adam(adam_head.parameters(), lr=3e-3, weight_decay=decay)
    for _ in range(10):
        for rows in torch.randperm(n).split(128):
            adam.zero_grad()
            torch.nn.functional.cross_entropy(adam_head.classify(pooled[rows]),
                                              torch.from_numpy(y[rows.numpy()]).long()).backward()
            adam.step()
    theta = np.concatenate([adam_head.out.weight.detach().double().numpy().ravel(),
                            adam_head.out.bias.detach().double().numpy()])
    assert objective(theta)[0] > ref.fun + 1e-3


def test_only_mini_batch_refits_are_judged_by_their_loss(toy, tmp_path, monkeypatch):
    """The linear model's refit (an L-BFGS fit of a convex objective, converged in its first
    epochs) is kept without a look at its loss, which is over other windows than the first
    training's; a mini-batch model's refit is judged (here by a stand-in that rejects it)."""
    import tactile.training.loop as tr

    judged = []
    monkeypatch.setattr(tr, "refit_failed", lambda *a: judged.append(a) or "a stand-in reason")
    m = train(toy, tmp_path / "linear", _cfg("linear", epochs=3, refit="on"), progress=False)
    assert m["refit_kept"] is True and judged == []
    m = train(toy, tmp_path / "sparse", _cfg("sparse_linear", epochs=2, refit="on"),
              progress=False)
    assert m["refit_kept"] is False and len(judged) == 1


def test_tactile_check_says_when_run_is_another_models(runs, tmp_path, capsys):
    """A file checked against the run of another model kind (same classes and channels) is
    one line naming both kinds, exit 3, not an error about a coder's scope in the graph."""
    from tactile.export.commands.check import main as check_main
    from tactile.export.commands.export import main as export_main

    linear, _, _ = runs["linear"]
    out = tmp_path / "linear.onnx"
    assert export_main([str(linear), "-o", str(out)]) == 0
    capsys.readouterr()
    assert check_main([str(out), "--run", str(runs["sf_rnn"][0])]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "differ in model: linear vs sf_rnn" in err[0], err
