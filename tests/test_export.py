"""Export: the ONNX contract, parity with PyTorch over a grid of runs, int8, tactile-check.

Every run is trained here on a small simulated dataset (nothing is skipped for a missing
artefact). The reference is always eager float32 PyTorch (``TextureModel.forward``), never
onnxruntime. Tolerances: probabilities within 1e-4 absolute, labels identical (except where
PyTorch's top-two margin is below 1e-4); int8 labels agree with PyTorch on >= 90% of windows.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

from tactile.contract import (
    BATCH,
    FLOAT,
    INPUTS,
    KEYS,
    OPSET,
    OUTPUTS,
    REQUIRED,
    ModelContract,
    TensorSpec,
)
from tactile.device.sim_cli import make_dataset
from tactile.errors import ModelContractError
from tactile.export.check import load_contract, signature
from tactile.export.check import main as check_main
from tactile.export.cli import export_run
from tactile.export.cli import main as export_main
from tactile.export.graph import split_forward
from tactile.export.parity import ATOL, INT8_AGREEMENT, MARGIN, MIN_CARRY, session
from tactile.export.windows import simulated
from tactile.training.config import TrainConfig
from tactile.training.train import load_checkpoint, train

torch.set_num_threads(1)

SMALL_EMD = {"emd_imfs": 2, "emd_sifts": 3, "emd_channels": ("accel_z",)}
GRID = {  # name -> TrainConfig overrides: EMD on/off, layers 1/2, hidden 8/16, both state
    # modes, window 50/30, and the linear head
    "lstm1": {"layers": 1},
    "lstm2-emd": {"layers": 2, **SMALL_EMD},
    "lstm1-h16-w30": {"layers": 1, "hidden": 16, "window": 30, "hop": 10},
    "carry1": {"layers": 1, "state": "carry", "hop": 50, "carry_steps": 2},
    "carry2-emd": {"layers": 2, "state": "carry", "hop": 50, "carry_steps": 2, **SMALL_EMD},
    "linear-emd": {"model": "linear", **SMALL_EMD},
}
BASE = {"epochs": 1, "hidden": 8, "threads": 1, "seed": 3}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim")
    make_dataset(out, takes=4, textures=("paper", "desk", "non_contact"), seconds=6, seed=2)
    return out


_CACHE: dict[str, tuple] = {}


def _build(name: str, overrides: dict, dataset: Path, root: Path) -> tuple:
    if name not in _CACHE:
        run = root / name
        train(dataset, run, TrainConfig(**{**BASE, **overrides}), progress=False)
        out = root / f"{name}.onnx"
        report = export_run(run, out, log=lambda s: None)
        model, ck = load_checkpoint(run)
        _CACHE[name] = (run, out, report, model, ck)
    return _CACHE[name]


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("runs")


@pytest.fixture(params=sorted(GRID), scope="module")
def exported(request, dataset, root):
    return _build(request.param, GRID[request.param], dataset, root)


@pytest.fixture(params=sorted(k for k, v in GRID.items() if v.get("state") == "carry"),
                scope="module")
def carried(request, dataset, root):
    return _build(request.param, GRID[request.param], dataset, root)


@pytest.fixture(params=sorted(k for k, v in GRID.items() if "emd_channels" in v), scope="module")
def composed(request, dataset, root):
    return _build(request.param, GRID[request.param], dataset, root)


# -- the contract module --------------------------------------------------------------------------


def _meta(**change) -> dict[str, str]:
    meta = ModelContract(
        classes=("desk", "paper"), channels=("a", "b"), units=("g", "N"), sample_rate_hz=100.0,
        window=50, hop=10, state_mode="window", model="lstm", state_layers=2, state_hidden=8,
        preprocessing={"mean": [0.0, 1.0], "std": [1.0, 2.0], "center": ["a"],
                       "emd": {"channels": ["b"], "imfs": 2, "sifts": 3}},
        package_version="0.1.0", training_metrics={"accuracy": 0.9},
        parity={"passed": True}, extra={"source_run": "r"},
    ).to_metadata()
    meta.update(change)  # a value None removes the key
    return {k: v for k, v in meta.items() if v is not None}


def test_contract_round_trip_and_keys():
    meta = _meta()
    c = ModelContract.from_metadata(meta)
    assert c.to_metadata() == meta
    assert set(REQUIRED) <= set(meta) and set(meta) <= set(KEYS)
    assert all(isinstance(v, str) for v in meta.values())
    assert c.inputs[0] == TensorSpec("x", (BATCH, 50, 2), FLOAT)
    assert [s.name for s in c.inputs] == list(INPUTS)
    assert [s.name for s in c.outputs] == list(OUTPUTS)
    assert c.outputs[1].dims == (2, BATCH, 8)


@pytest.mark.parametrize("key", REQUIRED)
def test_contract_names_every_missing_key(key):
    with pytest.raises(ModelContractError, match=f"'{key}' is missing"):
        ModelContract.from_metadata(_meta(**{key: None}))


@pytest.mark.parametrize("change, message", [
    ({"tactile.format": "other"}, "not a model made by tactile-export"),
    ({"tactile.format_version": "2"}, "understands 1..1"),
    ({"classes": "desk,paper"}, "'classes' is not valid JSON"),
    ({"classes": '["desk"]'}, "at least 2 classes"),
    ({"classes": '["a", "a"]'}, "unique"),
    ({"units": '["g"]'}, "1 units for 2 channels"),
    ({"window": "fifty"}, "'window' must be an integer"),
    ({"sample_rate_hz": "-1"}, "'sample_rate_hz'"),
    ({"state_mode": "stream"}, "allowed: window, carry"),
    ({"state_mode": "carry"}, "carry mode needs hop == window"),
    ({"preprocessing": '{"mean": [0], "std": [1, 1], "center": [], "emd": null}'},
     "'mean' must be a list of 2 numbers"),
    ({"preprocessing": '{"mean": [0, 0], "std": [1, 1], "center": ["z"], "emd": null}'},
     "'center' must list channel names"),
    ({"preprocessing_version": "9"}, "'preprocessing_version'"),
    ({"parity": "{}"}, "boolean 'passed'"),
    ({"quantization": "fp16"}, "allowed: none, int8-dynamic"),
])
def test_contract_names_bad_values(change, message):
    with pytest.raises(ModelContractError, match=message):
        ModelContract.from_metadata(_meta(**change))


def test_contract_checks_the_signature():
    c = ModelContract.from_metadata(_meta())
    ins = [("x", FLOAT, ["batch", 50, 2]), ("h", FLOAT, [2, "b", 8]), ("c", FLOAT, [2, None, 8])]
    outs = [("probs", FLOAT, ["batch", 2]), ("h_out", FLOAT, [2, "batch", 8]),
            ("c_out", FLOAT, [2, "batch", 8])]
    c.check_signature(ins, outs)
    with pytest.raises(ModelContractError, match="batch.*fixed to 1"):
        c.check_signature([("x", FLOAT, [1, 50, 2]), *ins[1:]], outs)
    with pytest.raises(ModelContractError, match="'x' has type tensor\\(double\\)"):
        c.check_signature([("x", "tensor(double)", ["batch", 50, 2]), *ins[1:]], outs)
    with pytest.raises(ModelContractError, match="'x' has rank 2"):
        c.check_signature([("x", FLOAT, ["batch", 100]), *ins[1:]], outs)
    with pytest.raises(ModelContractError, match=r"expected \(batch, 50, 2\)"):
        c.check_signature([("x", FLOAT, ["batch", 50, 3]), *ins[1:]], outs)
    with pytest.raises(ModelContractError, match="outputs are"):
        c.check_signature(ins, outs[:2])


def test_docs_list_every_metadata_key():
    doc = (Path(__file__).resolve().parents[1] / "docs" / "export.md").read_text()
    missing = [k for k in KEYS if f"| `{k}` |" not in doc]
    assert not missing, f"docs/export.md does not document {missing}"


def test_contract_module_needs_no_numpy_onnx_or_torch():
    code = ("import sys, tactile.contract; "
            "print(sorted(m for m in ('numpy', 'onnx', 'torch', 'onnxruntime') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


# -- the graph of every run in the grid -----------------------------------------------------------


def test_graph_passes_checker_and_shape_inference(exported):
    _, path, _, _, _ = exported
    model = onnx.load(path)
    onnx.checker.check_model(model, full_check=True)
    onnx.shape_inference.infer_shapes(model, check_type=True, strict_mode=True)
    assert {o.domain: o.version for o in model.opset_import}[""] == OPSET


def test_contract_of_every_export(exported):
    run, path, _, model, ck = exported
    graph, c = load_contract(path)
    cfg = ck["config"]
    ins, outs = signature(graph.graph.input, graph.graph.initializer), signature(graph.graph.output)
    assert [i[0] for i in ins] == list(INPUTS) and [o[0] for o in outs] == list(OUTPUTS)
    assert all(i[1] == FLOAT for i in ins + outs)
    layers, hidden = model.state_shape
    assert ins[0][2] == ["batch", cfg["window"], len(ck["channels"])]
    assert ins[1][2] == ins[2][2] == [layers, "batch", hidden]
    assert outs[0][2] == ["batch", len(ck["classes"])]
    meta = {p.key: p.value for p in graph.metadata_props}
    assert set(REQUIRED) <= set(meta) <= set(KEYS)
    assert c.classes == tuple(ck["classes"]) and c.channels == tuple(ck["channels"])
    assert c.units == tuple(ck["units"]) and c.sample_rate_hz == ck["sample_rate_hz"]
    assert (c.window, c.hop, c.state_mode, c.model) == (cfg["window"], cfg["hop"],
                                                        cfg["state"], cfg["model"])
    assert (c.state_layers, c.state_hidden) == (layers, hidden)
    assert c.preprocessing["mean"] == pytest.approx(ck["mean"])
    emd = c.preprocessing["emd"]
    assert (emd is None) == (not cfg["emd_channels"])
    assert c.training_metrics["accuracy"] == pytest.approx(ck["metrics"]["accuracy"])
    assert json.loads(meta["training_config"]) == cfg
    assert c.extra["source_run"] == run.name
    assert c.parity["passed"] is True and c.parity["max_abs_prob_diff"] <= ATOL
    if cfg["state"] == "carry":
        assert c.parity["longest_carry_run"] >= MIN_CARRY


def _labels_agree(p_t: np.ndarray, p_o: np.ndarray) -> None:
    top2 = np.sort(p_t, 1)[:, -2:]
    tie = top2[:, 1] - top2[:, 0] < MARGIN
    assert ((p_t.argmax(1) == p_o.argmax(1)) | tie).all()


@torch.no_grad()
def test_parity_at_batch_1_and_5(exported):
    _, path, _, model, ck = exported
    sess = session(str(path))
    x = simulated(ck).x[:: 3][:10]  # (10, T, C), every third window, mixed classes
    for b in (1, 5):
        for i in range(0, len(x), b):
            xb = torch.from_numpy(x[i : i + b])
            h, c = model.zero_state(len(xb))
            p_t, h_t, c_t = model(xb, h, c)
            p_o, h_o, c_o = sess.run(None, {"x": xb.numpy(), "h": h.numpy(), "c": c.numpy()})
            assert p_o.shape == (len(xb), len(ck["classes"])) and p_o.dtype == np.float32
            np.testing.assert_allclose(p_o, p_t.numpy(), rtol=0, atol=ATOL)
            np.testing.assert_allclose(h_o, h_t.numpy(), rtol=0, atol=1e-4)
            np.testing.assert_allclose(c_o, c_t.numpy(), rtol=0, atol=1e-4)
            _labels_agree(p_t.numpy(), p_o)


@torch.no_grad()
def test_carried_state_parity_over_24_steps(carried):
    _, path, _, model, ck = carried
    sess = session(str(path))
    x = simulated(ck).x[:24]  # 24 consecutive windows of one take
    h, c = model.zero_state(1)
    ho, co = h.numpy(), c.numpy()
    for k in range(24):
        xb = torch.from_numpy(x[k : k + 1])
        p_t, h, c = model(xb, h, c)
        p_o, ho, co = sess.run(None, {"x": xb.numpy(), "h": ho, "c": co})
        np.testing.assert_allclose(p_o, p_t.numpy(), rtol=0, atol=ATOL, err_msg=f"step {k}")
        _labels_agree(p_t.numpy(), p_o)
    np.testing.assert_allclose(ho, h.numpy(), rtol=0, atol=1e-4)


def test_composed_split_is_the_training_forward(composed):
    """The EMD graph is composed of pre + EMD + post: their eager sum is the training forward."""
    _, _, _, model, _ = composed
    x = torch.randn(4, model.cfg.window, model.pre.n_channels) * model.pre.std + model.pre.mean
    h, c = model.zero_state(4)
    with torch.no_grad():
        for a, b in zip(model(x, h, c), split_forward(model, x, h, c)):
            assert torch.equal(a, b)


# -- commands -------------------------------------------------------------------------------------


def test_export_cli_and_check_cli(dataset, root, capsys):
    run, _, _, _, _ = _build("lstm1", GRID["lstm1"], dataset, root)
    out = root / "cli.onnx"
    assert export_main([str(run), "-o", str(out), "--data", str(dataset)]) == 0
    text = capsys.readouterr().out
    assert "test split" in text and "PASS" in text and "kB; export took" in text
    assert check_main([str(out), "--run", str(run), "--data", str(dataset)]) == 0
    text = capsys.readouterr().out
    assert "contract ok" in text and "label agreement" in text and "PASS" in text
    assert check_main([str(out), "--data", str(dataset)]) == 0
    assert "accuracy" in capsys.readouterr().out


def test_export_fails_on_broken_parity(dataset, root, capsys, monkeypatch):
    import tactile.export.cli as cli
    from tactile.export.graph import build_graph

    def perturbed(model):
        g = build_graph(model)
        w = max(g.graph.initializer, key=lambda t: np.prod(t.dims))  # the largest weight
        arr = onnx.numpy_helper.to_array(w) + 0.5
        w.CopyFrom(onnx.numpy_helper.from_array(arr.astype(np.float32), w.name))
        return g

    monkeypatch.setattr(cli, "build_graph", perturbed)
    run, _, _, _, _ = _build("lstm1", GRID["lstm1"], dataset, root)
    out = root / "broken.onnx"
    assert export_main([str(run), "-o", str(out)]) == 3
    err = capsys.readouterr().err
    assert "float32 parity failed: max |dp|" in err and "limit 0.0001" in err
    assert not out.exists()


def _tamper(src: Path, dst: Path, edit) -> Path:
    m = onnx.load(src)
    edit(m)
    onnx.save(m, dst)
    return dst


def _drop_key(key):
    def edit(m):
        keep = [p for p in m.metadata_props if p.key != key]
        del m.metadata_props[:]
        m.metadata_props.extend(keep)
    return edit


def _set_key(key, value):
    def edit(m):
        for p in m.metadata_props:
            if p.key == key:
                p.value = value
    return edit


def _rename_x(m):
    m.graph.input[0].name = "samples"
    for n in m.graph.node:
        n.input[:] = ["samples" if v == "x" else v for v in n.input]


def test_check_names_what_is_wrong(dataset, root, capsys):
    _, good, _, _, ck = _build("lstm1", GRID["lstm1"], dataset, root)
    seven = json.dumps(ck["channels"][:7])
    cases = {
        "not_onnx": (lambda p: p.write_text("channel,value\n1,2\n"), "not an ONNX model"),
        "truncated": (lambda p: p.write_bytes(good.read_bytes()[:2000]), "not an ONNX model"),
        "no_metadata": (lambda p: _tamper(good, p, _drop_key("tactile.format")),
                        "'tactile.format' is missing: not a model made by tactile-export"),
        "no_classes": (lambda p: _tamper(good, p, _drop_key("classes")),
                       "metadata key 'classes' is missing"),
        "bad_parity": (lambda p: _tamper(good, p, _set_key("parity", "[")),
                       "'parity' is not valid JSON"),
        "seven_channels": (lambda p: _tamper(good, p, lambda m: (
            _set_key("channels", seven)(m), _set_key("units", json.dumps(ck["units"][:7]))(m))),
            "'mean' must be a list of 7 numbers"),
        "wrong_input": (lambda p: _tamper(good, p, _rename_x),
                        "graph inputs are \\['samples', 'h', 'c'\\], expected \\['x', 'h', 'c'\\]"),
    }
    for name, (make, message) in cases.items():
        path = root / f"{name}.onnx"
        make(path)
        assert check_main([str(path)]) == 3, name
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"tactile-check: error: {path}: "), err
        assert len(err.splitlines()) == 1, err
        assert re.search(message, err), (name, err)


def test_int8_is_smaller_and_mostly_agrees(dataset, root, capsys):
    run = root / "big"
    train(dataset, run, TrainConfig(**{**BASE, "hidden": 64, "layers": 2}), progress=False)
    f32, q = root / "big.onnx", root / "big-int8.onnx"
    export_run(run, f32, log=lambda s: None)
    report = export_run(run, q, int8=True, log=lambda s: None)
    t = report["int8"]
    assert q.stat().st_size < 0.5 * f32.stat().st_size
    assert t["label_agreement"] >= INT8_AGREEMENT
    assert t["latency_int8"]["p50_ms"] > 0
    _, c = load_contract(q)
    assert c.quantization == "int8-dynamic" and c.parity["criterion"] == "int8"
    assert c.parity["float32"]["passed"] is True
    assert check_main([str(q), "--run", str(run)]) == 0
    assert "int8: agreement >= 0.9" in capsys.readouterr().out
