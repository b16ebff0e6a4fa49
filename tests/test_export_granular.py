"""The granular models end to end: trained by ``train``, exported, checked, run by the runtime.

Tiny synthetic takes that declare a high-rate signal (``sig``: 4 sub-samples per frame) beside a
pressure channel and two electrodes; each model (sf_rnn, f_rnn, sparse_linear, linear with
modalities) is trained for one epoch and exported with ``--data``. References: eager float32
PyTorch for the probabilities (within 1e-4, labels equal), scikit-learn's transform for the
codes (``tactile.export.codes``: >= 99% of rows the same atoms, the rest explained). Nothing is
skipped: every artefact is built here. The BioTac replay test (an sf_rnn over a real trial,
through ``tactile-run --replay``) skips when ``../shared/datasets/biotac-bolt/`` is absent.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import onnx
import pytest
import torch
from conftest import SHARED

from tactile.contract import CUSTOM_DOMAIN, ModalitySpec, SignalSpec
from tactile.device.protocol import ChannelSpec, DeviceInfo
from tactile.device.recordings import TakeWriter, load_dataset, read_take
from tactile.export.check import load_contract
from tactile.export.commands.check import main as check_main
from tactile.export.exporter import export_run
from tactile.export.parity import ATOL
from tactile.export.session import native_available
from tactile.runtime.commands.run import main as run_main
from tactile.runtime.model import Model
from tactile.training.checkpoint import load_checkpoint
from tactile.training.config import TrainConfig
from tactile.training.feature_pass import feature_pass
from tactile.training.train import train

torch.set_num_threads(1)

SIGNAL = ("sig_0", "sig_1", "sig_2", "sig_3")
CHANNELS = (*SIGNAL, "pdc", "ele_0", "ele_1")
CLASSES = ("coarse", "fine", "smooth")
VIB = {"channels": ["sig"], "imfs": 2, "steps": 6, "atoms": 12, "nonzero": 2}
PRESSURE = {"channels": ["pdc"], "imfs": 2, "steps": 3, "atoms": 8, "nonzero": 1}
ELECTRODES = {"channels": ["ele_*"], "imfs": 0, "steps": 3, "atoms": 8, "nonzero": 2}
BASE = {"window": 20, "hop": 20, "epochs": 1, "epoch_windows": 64, "batch_size": 32,
        "threads": 1, "seed": 0, "emd_sifts": 4, "layers": 1, "hidden": 8, "split": "user"}
RUNS = {  # name -> config (TOML's shapes)
    "sf_rnn": {"model": "sf_rnn", "hop": 10,
               "modalities": {"vibration": VIB, "pressure": PRESSURE, "electrodes": ELECTRODES}},
    "f_rnn": {"model": "f_rnn", "modalities": {"vibration": VIB, "electrodes": ELECTRODES}},
    "sparse_linear": {"model": "sparse_linear",
                      "modalities": {"vibration": VIB, "electrodes": ELECTRODES}},
    "linear": {"model": "linear",
               "modalities": {"vibration": VIB, "pressure": PRESSURE, "electrodes": ELECTRODES}},
}


def write_takes(out: Path, channels: tuple[ChannelSpec, ...], signals: dict[str, list[str]],
                frames: int = 300, users: int = 3, seed: int = 0) -> Path:
    """Takes of 3 classes x ``users``: per class a tone on each signal (its frequency and
    level by class), a pressure level and drift, noisy electrodes; raw integer counts."""
    rng = np.random.default_rng(seed)
    info = DeviceInfo(100.0, channels, device="synthetic")
    names = [c.name for c in channels]
    for k, label in enumerate(CLASSES):
        for u in range(users):
            raw = 2000 + 20 * rng.standard_normal((frames, len(names)))
            for sig in signals.values():
                idx = [names.index(c) for c in sig]
                r = len(idx)
                t = np.arange(frames * r) / (100.0 * r)
                wave = (200 + 150 * k) * np.sin(2 * np.pi * (30 + 40 * k) * t
                                                + rng.uniform(0, 6))
                raw[:, idx] += (wave + 30 * rng.standard_normal(len(t))).reshape(frames, r)
            for i, n in enumerate(names):
                if "pdc" in n:
                    raw[:, i] += 300 * k + 100 * np.sin(np.arange(frames) / (7 + 5 * k))
            with TakeWriter(out, label, info, "synthetic", name=f"{label}_{u}",
                            extra={"signals": signals, "user": f"u{u}"}) as w:
                w.write(0, 0, np.clip(np.round(raw), 0, 4095).astype(np.int64))
    return out


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    chans = tuple(ChannelSpec(n, "count") for n in CHANNELS)
    return write_takes(tmp_path_factory.mktemp("granular"), chans, {"sig": list(SIGNAL)})


_CACHE: dict[str, tuple] = {}


@pytest.fixture(params=sorted(RUNS), scope="module")
def exported(request, dataset, tmp_path_factory):
    return _exported(request.param, dataset, tmp_path_factory)


def _exported(name: str, dataset: Path, tmp_path_factory) -> tuple:
    """Train and export run ``name`` once per module."""
    if name not in _CACHE:
        root = tmp_path_factory.mktemp(name)
        cfg = TrainConfig.from_dict({**BASE, **RUNS[name]})
        train(dataset, root / "run", cfg, progress=False)
        lines: list[str] = []
        report = export_run(root / "run", root / "model.onnx", data=dataset, log=lines.append)
        model, ck = load_checkpoint(root / "run")
        _CACHE[name] = (name, root, report, model, ck, "\n".join(lines))
    return _CACHE[name]


def test_export_parity_and_contract(exported, dataset):
    name, root, report, model, ck, log = exported
    p = report["parity"]
    assert p["passed"] and p["max_abs_prob_diff"] <= ATOL and p["labels_differ"] == 0, p
    assert p["reference"] == "torch float32 eager, GranularModel.forward, its EMDs in float64"
    assert log.startswith("portable graph:\nwindows checked")  # a file of two paths: each named
    _, contract = load_contract(root / "model.onnx")
    assert contract.model == name and contract.format_version == 2
    assert contract.preprocessing_version == 2 and contract.preprocessing["sifts"] == 4
    assert (contract.state_layers, contract.state_hidden) == model.state_shape
    if name == "f_rnn":
        assert contract.state_hidden == 16  # one LSTM of 8 per modality
    coded = name in ("sf_rnn", "sparse_linear")
    vib = ModalitySpec("vibration", SIGNAL, True, 400.0, 2, 6, 12 if coded else 0,
                       2 if coded else 0)
    assert contract.modalities[0] == vib
    assert contract.signals == (SignalSpec("sig", SIGNAL, 400.0),)
    if "electrodes" in RUNS[name]["modalities"]:
        ele = contract.modalities[-1]
        assert ele.channels == ("ele_0", "ele_1") and not ele.signal and ele.rate_hz == 100.0
    meta = json.loads(contract.to_metadata()["modalities"])
    assert [m["name"] for m in meta] == list(RUNS[name]["modalities"])


def test_codes_parity_of_the_coded_models(exported):
    name, _, report, model, _, log = exported
    codes = report["parity"]["codes"]
    if name not in ("sf_rnn", "sparse_linear"):
        assert codes is None
        return
    assert [c["name"] for c in codes] == list(RUNS[name]["modalities"])
    steps = model.pre.steps
    windows = report["parity"]["windows"]
    for c in codes:
        assert c["rows"] == windows * steps and c["passed"], c
        assert c["same_atoms"] >= 0.99 * c["rows"] and c["explained"]["unexplained"] == 0
        assert c["max_rel_diff"] <= 1e-4 or c["rows_over_rtol_unexcused"] == 0
        assert f"codes {c['name']}" in log


def test_the_runtime_runs_them_like_the_pens(exported, dataset):
    """Model (the runtime's loader, no torch) on the test windows equals PyTorch."""
    name, root, _, model, ck, _ = exported
    rt = Model(root / "model.onnx")
    takes = load_dataset(dataset)
    cols = [takes[0].channels.index(c) for c in ck["channels"]]  # those its modalities read
    assert ("pdc" in ck["channels"]) == ("pressure" in RUNS[name]["modalities"])
    x = np.stack([t.values()[s : s + 20, cols] for t in takes[:3] for s in (0, 37, 120)])
    x = x.astype(np.float32)
    h, c = rt.zero_state(len(x))
    p_o, h_o, _ = rt.classify(x, h, c)
    with torch.no_grad():
        p_t, h_t, _ = model(torch.from_numpy(x), *model.zero_state(len(x)))
    assert np.abs(p_o - p_t.numpy()).max() <= ATOL
    assert np.abs(h_o - h_t.numpy()).max() <= 1e-3


@pytest.fixture
def own_kernel_state(monkeypatch):
    """--no-native switches the kernels off for the process: this test's switch only."""
    from tactile.runtime import kernels

    monkeypatch.setattr(kernels, "_state", {"disabled": False, "said": False})


def test_check_data_measures_a_granular_model(exported, dataset, capsys, own_kernel_state):
    """On the path tactile-run takes here (the kernels where built), and it says which."""
    name, root, _, _, _, _ = exported
    assert check_main([str(root / "model.onnx"), "--data", str(dataset)]) == 0
    out = capsys.readouterr().out
    assert "contract ok (format 2" in out and "accuracy" in out
    # the state's shape, and for the F-RNN (hidden 8, 2 modalities) what makes its width
    assert {"f_rnn": "f_rnn (1 x 16: 2 modalities' LSTMs of 1 x 8)", "sf_rnn": "sf_rnn (1 x 8)",
            "linear": "linear (1 x 1)", "sparse_linear": "sparse_linear (1 x 1)"}[name] in out
    path = "on the native kernels" if native_available() else "on the portable graph"
    assert f"one window at a time, {path})" in out
    assert check_main([str(root / "model.onnx"), "--data", str(dataset), "--no-native"]) == 0
    assert "one window at a time, on the portable graph)" in capsys.readouterr().out


@pytest.mark.skipif(not native_available(), reason="the native kernels are not built")
def test_check_run_compares_both_paths_where_the_kernels_run(exported, capsys,
                                                              own_kernel_state):
    """--run on a file with custom nodes: the portable graph's table and the kernels' table,
    both passing; --no-native: the portable graph's alone."""
    name, root, _, _, _, _ = exported
    model = str(root / "model.onnx")
    assert check_main([model, "--run", str(root / "run"), "--windows", "16"]) == 0
    out = capsys.readouterr().out
    assert "portable graph:\nwindows checked  16" in out
    assert "native kernels:\nwindows checked  16" in out
    assert out.count("result           PASS") == 2
    assert check_main([model, "--run", str(root / "run"), "--windows", "16", "--no-native"]) == 0
    out = capsys.readouterr().out
    assert "native kernels:" not in out and out.count("result           PASS") == 1
    assert "portable graph:\nwindows checked  16" in out  # the path it checked, named


# -- an SF-RNN over a replayed BioTac trial ------------------------------------------------------

BOLT = SHARED / "datasets" / "biotac-bolt"
BT_SF = {"model": "sf_rnn", "window": 10, "hop": 10, "frame": 5, "frame_hop": 5, "epochs": 1,
         "epoch_windows": 32, "batch_size": 16, "threads": 1, "seed": 0, "emd_sifts": 3,
         "layers": 1, "hidden": 8, "split": "user",
         "modalities": {
             "vibration": {"channels": ["f0_pac"], "imfs": 2, "steps": 22, "atoms": 12,
                           "nonzero": 2},
             "pressure": {"channels": ["f0_pdc"], "imfs": 1, "steps": 3, "atoms": 6,
                          "nonzero": 1},
             "electrodes": {"channels": ["f0_ele_*"], "imfs": 0, "steps": 2, "atoms": 8,
                            "nonzero": 2}}}


def _small_trial(src: Path, dst: Path, frames: int) -> str:
    """One trial of ``src`` cut to its first ``frames`` frames, in the BOLT layout."""
    with h5py.File(src) as f, h5py.File(dst, "w") as g:
        group = sorted(f)[0]
        out = g.create_group(group)

        def copy(name, obj):
            if isinstance(obj, h5py.Dataset):
                out.create_dataset(name, data=obj[:frames])
        f[group].visititems(copy)
    return group


@pytest.mark.skipif(not BOLT.is_dir(), reason=f"{BOLT} is absent (BioTac BOLT recordings)")
def test_sf_rnn_labels_a_replayed_biotac_trial(tmp_path, capsys):
    from tactile.device.commands import import_biotac
    from tactile.device.recordings import biotac

    data = write_takes(tmp_path / "synthetic", biotac.channels(), biotac.signals(),
                       frames=120, users=3)
    cfg = TrainConfig.from_dict(BT_SF)
    train(data, tmp_path / "run", cfg, progress=False)
    export_run(tmp_path / "run", tmp_path / "bt.onnx", data=data, log=lambda s: None)
    group = _small_trial(BOLT / "cork.h5", tmp_path / "cork.h5", 150)
    assert import_biotac.main([str(tmp_path / "cork.h5"), "--out", str(tmp_path / "real")]) == 0
    take_path = tmp_path / "real" / f"{group}.csv"
    capsys.readouterr()
    assert run_main(["--model", str(tmp_path / "bt.onnx"), "--replay", str(take_path)]) == 0
    lines = [json.loads(s) for s in capsys.readouterr().out.splitlines()]
    labels = [d for d in lines if "label" in d]
    assert [d["seq"] for d in labels] == list(range(9, 150, 10))  # window 10, hop 10
    take = read_take(take_path)
    model, ck = load_checkpoint(tmp_path / "run")
    cols = [take.channels.index(c) for c in ck["channels"]]  # finger 0's 42 of the 88
    assert len(cols) == 42
    x = np.stack([take.values()[d["seq"] - 9 : d["seq"] + 1, cols]
                  for d in labels]).astype(np.float32)
    with torch.no_grad(), feature_pass(emd=True, codes=False):  # as compare()
        p_t = model(torch.from_numpy(x), *model.zero_state(len(x)))[0].numpy()
    classes = list(ck["classes"])
    p_run = np.array([[d["probs"][k] for k in classes] for d in labels])
    assert np.abs(p_run - p_t).max() <= ATOL  # stdout rounds to 6 decimals
    assert [d["label"] for d in labels] == [classes[i] for i in p_t.argmax(1)]


@pytest.mark.skipif(not BOLT.is_dir(), reason=f"{BOLT} is absent (BioTac BOLT recordings)")
def test_a_model_of_one_finger_runs_on_a_take_of_both(tmp_path, capsys):
    """Trained on finger 0's pressure, vibration and electrodes (a ``channels`` setting), the
    default model reads them by name from a real BOLT take's 88 channels, as PyTorch does."""
    from tactile.device.commands import import_biotac
    from tactile.device.recordings import biotac

    names = [c.name for c in biotac.channels()]
    finger0 = tuple(n for n in names if n == "f0_pdc" or n.startswith(("f0_pac_", "f0_ele_")))
    data = write_takes(tmp_path / "synthetic", biotac.channels(), biotac.signals(),
                       frames=120, users=3)
    cfg = TrainConfig.from_dict({"window": 10, "hop": 10, "frame": 5, "frame_hop": 5,
                                 "epochs": 1, "epoch_windows": 32,
                                 "batch_size": 16, "threads": 1, "seed": 0, "layers": 1,
                                 "hidden": 8, "split": "user", "channels": list(finger0)})
    train(data, tmp_path / "run", cfg, progress=False)
    export_run(tmp_path / "run", tmp_path / "f0.onnx", data=data, log=lambda s: None)
    group = _small_trial(BOLT / "cork.h5", tmp_path / "cork.h5", 150)
    assert import_biotac.main([str(tmp_path / "cork.h5"), "--out", str(tmp_path / "real")]) == 0
    take_path = tmp_path / "real" / f"{group}.csv"
    capsys.readouterr()
    assert run_main(["--model", str(tmp_path / "f0.onnx"), "--replay", str(take_path)]) == 0
    out = capsys.readouterr()
    assert f"the model reads {len(finger0)} of the device's 88 channels; unused: " in out.err
    labels = [d for d in map(json.loads, out.out.splitlines()) if "label" in d]
    assert [d["seq"] for d in labels] == list(range(9, 150, 10))
    take = read_take(take_path)
    cols = [names.index(n) for n in finger0]
    x = np.stack([take.values()[d["seq"] - 9 : d["seq"] + 1][:, cols] for d in labels])
    model, ck = load_checkpoint(tmp_path / "run")
    with torch.no_grad(), feature_pass(emd=True, codes=False):  # as compare()
        p_t = model(torch.from_numpy(x.astype(np.float32)), *model.zero_state(len(x)))[0]
    classes = list(ck["classes"])
    p_run = np.array([[d["probs"][k] for k in classes] for d in labels])
    assert np.abs(p_run - p_t.numpy()).max() <= ATOL  # stdout rounds to 6 decimals


def test_int8_of_a_granular_model(dataset, tmp_path_factory):
    """Two EMD graphs whose loop bodies read main-graph values: the quantiser's reordering
    must not leave a file that onnx.checker refuses (it did before export/compose.toposorted).
    The sf_rnn: both EMDs and the coders."""
    _, root, _, _, _, _ = _exported("sf_rnn", dataset, tmp_path_factory)
    report = export_run(root / "run", root / "int8.onnx", data=dataset, int8=True,
                        log=lambda s: None)
    assert report["int8"]["label_agreement"] >= 0.9
    _, contract = load_contract(root / "int8.onnx")  # onnx.checker, shape inference, contract
    assert contract.quantization == "int8-dynamic" and contract.model == "sf_rnn"
    assert contract.parity["criterion"] == "int8" and contract.parity["passed"]
    # the int8 file keeps its custom nodes and their fallback functions (the quantiser's
    # pre-process would inline the functions): the kernel path where built, the portable one
    # anywhere, each checked
    def custom(path):
        m = onnx.load(path)
        return (sorted(n.op_type for n in m.graph.node if n.domain == CUSTOM_DOMAIN),
                sorted(f.name for f in m.functions))

    assert custom(root / "int8.onnx") == custom(root / "model.onnx")
    assert custom(root / "int8.onnx")[1] == ["EMD", "SparseCode"]
    if native_available():
        assert report["int8_native"]["passed"]
        # the file records its figures on the kernels, as a float32 file does, and its
        # latency was timed on the path tactile-run takes here
        assert contract.parity["native"] == report["int8_native"]
        assert report["int8"]["latency_path"] == "native kernels"
    else:
        assert "native" not in contract.parity
        assert report["int8"]["latency_path"] == "portable graph"
