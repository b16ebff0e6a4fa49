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
from conftest import not_utf8

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
from tactile.device.sim import make_dataset
from tactile.errors import ModelContractError
from tactile.export.check import load_contract, signature
from tactile.export.commands.check import main as check_main
from tactile.export.commands.export import main as export_main
from tactile.export.exporter import export_run
from tactile.export.graph import split_forward
from tactile.export.parity import ATOL, INT8_AGREEMENT, MARGIN, MIN_CARRY
from tactile.export.session import session
from tactile.export.windows import simulated
from tactile.training.checkpoint import load_checkpoint
from tactile.training.config import TrainConfig
from tactile.training.train import train

torch.set_num_threads(1)

SMALL_EMD = {"emd_imfs": 2, "emd_sifts": 3, "emd_channels": ("accel_z",)}
GRID = {  # name -> TrainConfig overrides: EMD on/off, layers 1/2, hidden 8/16, both state
    # modes, window 50/30, the linear head, ensembles of two and the LSTM without the blend
    "lstm1": {"layers": 1},
    "lstm1-alone": {"layers": 1, "blend": "off"},  # the LSTM alone: its every weight counts
    "lstm2-emd": {"layers": 2, **SMALL_EMD},
    "lstm1-h16-w30": {"layers": 1, "hidden": 16, "window": 30, "hop": 10},
    "carry1": {"layers": 1, "state": "carry", "hop": 50, "carry_steps": 2},
    "carry2-emd": {"layers": 2, "state": "carry", "hop": 50, "carry_steps": 2, **SMALL_EMD},
    "linear-emd": {"model": "linear", **SMALL_EMD},
    "ensemble2": {"layers": 1, "ensemble": 2},
    "carry2-ensemble2": {"layers": 2, "state": "carry", "hop": 50, "carry_steps": 2,
                         "ensemble": 2},
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
    ({"tactile.format_version": "3"}, "understands 1..2"),
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
    ({"parity": '{"passed": false}'}, "records a failed parity check"),
    ({"classes": '["pa\\nper", "desk"]'}, "holds a control character"),
    ({"sample_rate_hz": "2e6"}, r"must be a number in \(0, 1e\+06\], got 2000000.0"),
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
    with pytest.raises(SystemExit) as stop:  # --windows without --run: it did nothing
        check_main([str(out), "--data", str(dataset), "--windows", "5"])
    assert stop.value.code == 1
    assert capsys.readouterr().err == ("tactile-check: error: argument --windows: only with "
                                       "--run (the windows of the parity check) (see --help)\n")
    # another run of the same shape (its weights moved): the failure names the file's run
    other = root / "another-run"
    other.mkdir(exist_ok=True)
    ck = torch.load(run / "checkpoint.pt", weights_only=True)
    ck["state_dict"] = {k: v + 0.5 for k, v in ck["state_dict"].items()}
    torch.save(ck, other / "checkpoint.pt")
    assert check_main([str(out), "--run", str(other), "--windows", "16"]) == 3
    assert capsys.readouterr().err == (
        f"tactile-check: error: {out}: parity against {other} failed (table above); the file "
        f"says it was exported from a run named {run.name!r}, not 'another-run'\n")


def test_export_fails_on_broken_parity(dataset, root, capsys, monkeypatch):
    import tactile.export.exporter as cli
    from tactile.export.graph import build_graph

    def perturbed(model):
        g = build_graph(model)
        for w in g.graph.initializer:  # every weight of the LSTM and of the regression
            if w.data_type == onnx.TensorProto.FLOAT and ("LSTM" in w.name
                                                          or "coef" in w.name):
                arr = onnx.numpy_helper.to_array(w) * 2 + 0.5
                w.CopyFrom(onnx.numpy_helper.from_array(arr.astype(np.float32), w.name))
        return g

    monkeypatch.setattr(cli, "build_graph", perturbed)
    run, _, _, _, _ = _build("lstm1", GRID["lstm1"], dataset, root)
    out = root / "broken.onnx"
    assert export_main([str(run), "-o", str(out)]) == 3
    err = capsys.readouterr().err
    assert "float32 parity failed: max |dp|" in err and "limit 0.0001" in err
    assert not out.exists()


def test_a_disk_that_fills_while_the_file_is_written_is_exit_4_naming_out(dataset, root,
                                                                         capsys, monkeypatch):
    """A write that failed (a full disk) was '[Errno 28] ...' naming the temporary file, exit 1.
    Now one line naming -o, exit 4, and no file (the temporary one is removed)."""
    import errno

    run, _, _, _, _ = _build("lstm1", GRID["lstm1"], dataset, root)
    folder = root / "full"
    folder.mkdir(exist_ok=True)
    out = folder / "m.onnx"
    real = Path.write_bytes

    def full(self, data):
        if self.parent == folder:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, data)

    monkeypatch.setattr(Path, "write_bytes", full)
    assert export_main([str(run), "-o", str(out)]) == 4
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"tactile-export: error: -o {out}: cannot be written (No space left on device)")
    assert list(folder.iterdir()) == []


def test_a_file_that_fails_its_contract_when_written_is_named_as_out(dataset, root, capsys,
                                                                    monkeypatch):
    """The last check reads the file back from a temporary name beside -o: its error named
    that temporary file, which the user never asked for and which is gone."""
    import tactile.export.exporter as cli
    from tactile.errors import ModelContractError

    def refuse(path):
        raise ModelContractError(f"{path}: metadata key 'channels': names must be unique")

    run, _, _, _, _ = _build("lstm1", GRID["lstm1"], dataset, root)
    monkeypatch.setattr(cli, "load_contract", refuse)
    out = root / "refused.onnx"
    assert export_main([str(run), "-o", str(out)]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (f"tactile-export: error: {out}: metadata key 'channels': names must be "
                       "unique"), err
    assert not out.exists() and not list(root.glob("tmp*.onnx"))


def _tamper(src: Path, dst: Path, edit) -> Path:
    """``src`` edited by hand into ``dst``: ``edit``, and its ``sha256`` key removed (which
    would otherwise name every edit as damage)."""
    m = onnx.load(src)
    _drop_key("sha256")(m)
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
        "not_utf8": (lambda p: p.write_bytes(not_utf8(  # a node input's name, in a file
            _tamper(good, p, lambda m: None).read_bytes(), b"/pre/Sub_output_0", nth=1)),
            "fails onnx.checker: 'utf-8' codec can't decode"),  # without a sha256 key
        "damaged": (lambda p: p.write_bytes(not_utf8(good.read_bytes(), b"/pre/Sub_output_0",
                                                     nth=1)),  # the same in the file as made
                    "damaged: the file's bytes give sha256 "),
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


def test_a_custom_ops_key_that_does_not_describe_the_graph_is_refused(dataset, root, capsys):
    """The key removed, emptied, or with other attributes than the graph's EMD node: accepted
    before (tactile-check then printed no kernels line)."""
    _, good, _, _, _ = _build("lstm2-emd", GRID["lstm2-emd"], dataset, root)
    key = json.loads({p.key: p.value for p in onnx.load(good).metadata_props}["custom_ops"])
    other = json.loads(json.dumps(key))
    other["nodes"][0]["attributes"]["n_imfs"] += 1
    cases = {
        "no_key": (_drop_key("custom_ops"), r"'custom_ops' lists none where the graph has EMD"),
        "empty": (_set_key("custom_ops", json.dumps({**key, "nodes": []})),
                  r"'nodes' must be a non-empty list"),
        "no_nodes": (_set_key("custom_ops", "{}"), r"not a JSON object with a 'nodes' list"),
        "attributes": (_set_key("custom_ops", json.dumps(other)),
                       r"or their attributes differ"),
    }
    for name, (edit, message) in cases.items():
        path = _tamper(good, root / f"ops_{name}.onnx", edit)
        assert check_main([str(path)]) == 3, name
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and re.search(message, err), (name, err)


def test_int8_is_smaller_and_mostly_agrees(dataset, root, capsys):
    run = root / "big"
    train(dataset, run, TrainConfig(**{**BASE, "hidden": 64, "layers": 2}), progress=False)
    f32, q = root / "big.onnx", root / "big-int8.onnx"
    export_run(run, f32, log=lambda s: None)
    report = export_run(run, q, int8=True, log=lambda s: None)
    t = report["int8"]
    assert q.stat().st_size < 0.5 * f32.stat().st_size
    assert t["label_agreement"] >= INT8_AGREEMENT
    # the learned weights become int8; the spectral front's fixed DFT basis stays float32 (in
    # int8 it moved the weak bins' log power enough to change 12% of a trained model's labels)
    ops = {n.op_type for n in onnx.load(q).graph.node}
    assert {"DynamicQuantizeLSTM", "MatMulInteger", "Conv"} <= ops and "ConvInteger" not in ops
    assert t["latency_int8"]["p50_ms"] > 0
    _, c = load_contract(q)
    assert c.quantization == "int8-dynamic" and c.parity["criterion"] == "int8"
    assert c.parity["float32"]["passed"] is True
    assert check_main([str(q), "--run", str(run)]) == 0
    assert "int8: agreement >= 0.9" in capsys.readouterr().out


# -- the file's own checksum ----------------------------------------------------------------------

def test_a_damaged_copy_is_refused_by_its_checksum(dataset, root, tmp_path, capsys):
    """One flipped byte in a weight: onnxruntime loads the copy and it gives other
    probabilities. Its bytes no longer give the sha256 the export recorded (computed here with
    the onnx package and hashlib, not the exporter's code), so Model, tactile-check and
    tactile-run refuse it: one line, exit 3. A file whose key was removed after an edit runs,
    and tactile-check says it cannot tell a damaged copy."""
    import hashlib

    from tactile.runtime.commands.run import main as run_main
    from tactile.runtime.model import Model

    _, out, _, _, _ = _build("lstm1-alone", GRID["lstm1-alone"], dataset, root)
    data = out.read_bytes()
    proto = onnx.load_model_from_string(data)
    meta = {p.key: p.value for p in proto.metadata_props}
    assert list(meta)[-1] == "sha256" and re.fullmatch(r"[0-9a-f]{64}", meta["sha256"])
    for p in proto.metadata_props:
        if p.key == "sha256":
            p.value = "0" * 64
    assert hashlib.sha256(proto.SerializeToString()).hexdigest() == meta["sha256"]
    assert check_main([str(out)]) == 0
    assert f"  file      sha256 {meta['sha256'][:16]}... verified" in capsys.readouterr().out

    weight = max((i for i in proto.graph.initializer if i.raw_data), key=lambda i: len(i.raw_data))
    at = data.index(weight.raw_data) + len(weight.raw_data) // 8 * 4 + 3  # a float's top byte
    bad = tmp_path / "damaged.onnx"
    bad.write_bytes(data[:at] + bytes([data[at] ^ 0x40]) + data[at + 1:])
    with pytest.raises(ModelContractError, match=r"damaged: the file's bytes give sha256 "):
        Model(bad)
    for prog, main, argv in [("tactile-check", check_main, [str(bad)]),
                             ("tactile-run", run_main, ["--model", str(bad), "--port",
                                                        "sim://?texture=paper"])]:
        assert main(argv) == 3, prog
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"{prog}: error: {bad}: damaged: "), err

    # the same damage with the key removed (as after an edit): it runs, other probabilities
    edited = onnx.load_model_from_string(bad.read_bytes())
    keep = [(p.key, p.value) for p in edited.metadata_props if p.key != "sha256"]
    del edited.metadata_props[:]
    onnx.helper.set_model_props(edited, dict(keep))
    unsealed = tmp_path / "unsealed.onnx"
    onnx.save(edited, unsealed)
    x = np.random.default_rng(0).normal(size=(1, 50, 8)).astype(np.float32)
    good, damaged = Model(out), Model(unsealed)
    p_good = good.classify(x, *good.zero_state())[0]
    assert not np.allclose(p_good, damaged.classify(x, *damaged.zero_state())[0], atol=1e-6)
    assert check_main([str(unsealed)]) == 0
    assert "  file      no sha256 key (exported before files carried one, or removed after " \
        "an edit): a damaged copy cannot be told" in capsys.readouterr().out


@pytest.mark.parametrize("value, message", [
    ("abc", r"metadata key 'sha256' is 'abc': not 64 lower-case hex digits"),
    ("A" * 64, r"not 64 lower-case hex digits"),
])
def test_a_bad_checksum_value_is_named(dataset, root, tmp_path, value, message):
    from tactile.runtime.model import Model

    _, out, _, _, _ = _build("lstm1", GRID["lstm1"], dataset, root)
    proto = onnx.load(out)
    for p in proto.metadata_props:
        if p.key == "sha256":
            p.value = value
    path = tmp_path / "bad.onnx"
    onnx.save(proto, path)
    for load in (Model, load_contract):
        with pytest.raises(ModelContractError, match=message):
            load(path)


# -- untrusted model files: outputs that break their declared shapes ----------------------------


def _lying_model(path: Path, probs_width: int = 2, hidden_out: int = 8,
                 fixed_batch: bool = False) -> Path:
    """A hand-built graph honouring _meta()'s contract on paper (2 classes, 2 channels, state
    2 x 8, dynamic batch) whose outputs really have ``probs_width`` columns, ``hidden_out`` state
    columns, or (``fixed_batch``) always batch 1. The widths are Tile counts computed from the
    input's values (0 * sum(h) + k), which no shape inference can know: onnx.checker and
    onnxruntime's declared signature both pass the file."""
    from onnx import TensorProto, helper, numpy_helper

    def const(name, values, dtype=np.int64):
        return numpy_helper.from_array(np.asarray(values, dtype), name)

    nodes = [
        # a data-dependent zero (a (1,) int64), so the counts below are unknown until run
        helper.make_node("ReduceSum", ["h"], ["hs"], keepdims=0),
        helper.make_node("Mul", ["hs", "fzero"], ["hz"]),
        helper.make_node("Reshape", ["hz", "one"], ["hz1"]),
        helper.make_node("Cast", ["hz1"], ["z"], to=TensorProto.INT64),
        helper.make_node("Add", ["z", "wide"], ["wide_n"]),
        helper.make_node("Add", ["z", "copies"], ["copies_n"]),
        # probs: the mean of x over time (batch, 2), first column tiled to probs_width, softmaxed
        helper.make_node("ReduceMean", ["x", "one"], ["xm"], keepdims=0),
        helper.make_node("Slice", ["xm", "zero", "one", "one"], ["x1"]),  # (batch, 1)
        helper.make_node("Concat", ["one", "wide_n"], ["reps"], axis=0),
        helper.make_node("Tile", ["x1", "reps"], ["xt"]),
        helper.make_node("Softmax", ["xt"], ["p_all"], axis=1),
        helper.make_node("Slice", ["p_all", "zero", "one", "zero"], ["probs"])
        if fixed_batch else helper.make_node("Identity", ["p_all"], ["probs"]),
        # h and c: the state tiled to hidden_out columns (hidden_out / 8 copies)
        helper.make_node("Concat", ["one", "one", "copies_n"], ["sreps"], axis=0),
        helper.make_node("Tile", ["h", "sreps"], ["h_out"]),
        helper.make_node("Tile", ["c", "sreps"], ["c_out"]),
    ]
    f = TensorProto.FLOAT
    graph = helper.make_graph(
        nodes, "lying",
        [helper.make_tensor_value_info("x", f, ["batch", 50, 2]),
         helper.make_tensor_value_info("h", f, [2, "batch", 8]),
         helper.make_tensor_value_info("c", f, [2, "batch", 8])],
        [helper.make_tensor_value_info("probs", f, ["batch", 2]),
         helper.make_tensor_value_info("h_out", f, [2, "batch", 8]),
         helper.make_tensor_value_info("c_out", f, [2, "batch", 8])],
        initializer=[const("zero", [0]), const("one", [1]), const("fzero", 0.0, np.float32),
                     const("wide", [probs_width]), const("copies", [hidden_out // 8])],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 8
    onnx.helper.set_model_props(model, _meta())
    onnx.checker.check_model(model, full_check=True)  # the lie is invisible statically
    onnx.save(model, path)
    return path


LIES = {
    "wide_probs": ({"probs_width": 3}, "output 'probs' has width 3, the contract declares 2"),
    "wide_state": ({"hidden_out": 16}, "output 'h_out' has width 16, the contract declares 8"),
    "fixed_batch": ({"fixed_batch": True},
                    r"output 'probs' has shape \(1, 2\), the contract declares \(2, 2\) "
                    r"\(batch 2\)"),
}


def test_a_well_formed_hand_built_graph_loads(tmp_path):
    from tactile.runtime.model import Model

    model = Model(_lying_model(tmp_path / "honest.onnx"))
    probs, h, c = model.classify(np.zeros((1, 50, 2), np.float32), *model.zero_state())
    assert probs.shape == (1, 2) and h.shape == c.shape == (2, 1, 8)


@pytest.mark.parametrize("lie", sorted(LIES))
def test_outputs_wider_than_declared_are_refused_at_load(tmp_path, capsys, lie):
    """tactile-check and tactile-run both refuse the file in one line, exit 3, naming the
    output and its real width, before any data is read (no port is opened: sim:// would
    stream forever). A fixed batch of 1 is what the runtime runs: tactile-check and
    Model.classify at batch 2 refuse it."""
    from tactile.runtime.commands.run import main as run_main
    from tactile.runtime.model import Model

    kwargs, message = LIES[lie]
    path = _lying_model(tmp_path / f"{lie}.onnx", **kwargs)
    if lie == "fixed_batch":
        model = Model(path)
        with pytest.raises(ModelContractError, match=message):
            model.classify(np.zeros((2, 50, 2), np.float32), *model.zero_state(2))
    else:
        with pytest.raises(ModelContractError, match=message):
            Model(path)
    runs = [("tactile-check", check_main, [str(path)])]
    if lie != "fixed_batch":
        runs.append(("tactile-run", run_main, ["--model", str(path), "--port",
                                               "sim://?texture=paper"]))
    for prog, main, argv in runs:
        assert main(argv) == 3, prog
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and err.startswith(f"{prog}: error: {path}: "), err
        assert re.search(message, err), err


def test_stream_refuses_a_classify_function_returning_the_wrong_width():
    """Mid-stream (a classify function not checked at load): one ModelContractError naming
    the width, not an IndexError."""
    from tactile.runtime.stream import Stream

    def classify(x, h, c):
        return np.full((1, 3), 1 / 3, np.float32), h, c

    stream = Stream(classify, ("desk", "paper"), 5, 5, 1, False, (1, 4))
    stream.accept(np.zeros((5, 1), np.float32), 0, 0, period_us=10_000)
    with pytest.raises(ModelContractError, match=r"probs \(1, 3\).*\(1, 2\) \(2 classes\)"):
        stream.classify()


# -- which windows parity and tactile-check measure -----------------------------------------------


def test_test_takes_are_recognised_by_content(dataset, tmp_path):
    from tactile.device.recordings import load_dataset
    from tactile.training.data import find_test_split

    takes = load_dataset(dataset)
    names = [t.path.name for t in takes]
    test_rows = {names[0]: [0, 300], names[2]: [100, 400]}
    fps = {n: takes[names.index(n)].fingerprint() for n in test_rows}
    rows, scope, verified = find_test_split(takes, test_rows, fps, "d")
    assert verified and rows == {0: (0, 300), 2: (100, 400)}, scope
    assert scope.startswith("the run's test split in d (2 takes, matched by content)")
    # another folder with takes of the same names: other recordings, so every take
    other = tmp_path / "other"
    make_dataset(other, takes=4, textures=("paper", "desk", "non_contact"), seconds=6, seed=9)
    others = load_dataset(other)
    assert [t.path.name for t in others] == names
    rows, scope, verified = find_test_split(others, test_rows, fps, "other")
    assert rows is None and not verified and "hold other recordings" in scope
    # a run that recorded no fingerprints: the named rows, said to be unverified
    rows, scope, verified = find_test_split(others, test_rows, None, "other")
    assert rows == {0: (0, 300), 2: (100, 400)} and not verified and "not verified" in scope
    # malformed records count as absent, never a traceback
    for bad in ([1], {names[0]: "x"}, {names[0]: [0]}, {names[0]: [0.5, 3]}, {}, None):
        rows, scope, _ = find_test_split(takes, bad, fps, "d")
        assert rows is None and scope.startswith("every take of d"), bad


def test_check_data_says_what_it_measured(dataset, root, tmp_path, capsys):
    from tactile.device.recordings import load_dataset
    from tactile.training.checkpoint import CHECKPOINT

    src, _, _, _, _ = _build("lstm1", GRID["lstm1"], dataset, root)
    run = tmp_path / "run"
    run.mkdir()
    ck = torch.load(src / CHECKPOINT, weights_only=True)
    by_name = {t.path.name: t for t in load_dataset(dataset)}
    ck["test_fingerprints"] = {n: by_name[n].fingerprint() for n in ck["test_rows"]}
    torch.save(ck, run / CHECKPOINT)  # what the training side records
    out = tmp_path / "m.onnx"
    export_run(run, out, log=lambda s: None)
    assert check_main([str(out)]) == 0
    text = capsys.readouterr().out
    assert "test accuracy" not in text
    assert re.search(r"training  accuracy \d\.\d{4} on \d+ windows of the run's test split "
                     r"\(measured at training, in PyTorch\)", text), text
    n_test = ck["metrics"]["windows"]
    assert check_main([str(out), "--data", str(dataset)]) == 0
    text = capsys.readouterr().out
    assert f"measured on      the run's test split in {dataset.name}" in text
    assert f": {n_test} windows" in text and "not comparable" not in text, text
    other = tmp_path / "other"
    make_dataset(other, takes=4, textures=("paper", "desk", "non_contact"), seconds=6, seed=9)
    assert check_main([str(out), "--data", str(other)]) == 0
    text = capsys.readouterr().out
    assert "measured on      every take of other (12 takes;" in text
    assert "hold other recordings" in text and "not comparable" in text, text


def _probe_of(n_classes: int, takes_per_class: int, runs_per_take: int, run_len: int):
    from tactile.export.windows import Probe

    ys, tk, runs, n = [], [], [], 0
    for c in range(n_classes):
        for t in range(takes_per_class):
            for _ in range(runs_per_take):
                runs.append(np.arange(n, n + run_len))
                n += run_len
                ys += [c] * run_len
                tk += [c * takes_per_class + t] * run_len
    x = np.arange(n, dtype=np.float32)[:, None, None]  # each window holds its own index
    return Probe(x, np.array(ys), runs, "file order", np.array(tk))


@pytest.mark.parametrize("block", [1, 24])
def test_parity_windows_are_a_stratified_seeded_sample(block):
    """20 classes x 3 takes x 2 runs of 30 windows in file order: the first 256 were 5 classes.
    The sample covers every class (equal shares to one window), at least one take per class
    and, with 1-window blocks, every take; runs are consecutive windows of one original run;
    the same input gives the same sample."""
    from tactile.export.windows import stratified

    p = _probe_of(20, 3, 2, 30)
    q = stratified(p, 256, block)
    counts = np.bincount(q.y, minlength=20)
    assert len(q) == 256 and counts.min() >= 12 and counts.max() - counts.min() <= (
        1 if block == 1 else 12), counts
    assert len(np.unique(q.take)) == (60 if block == 1 else 22)
    assert "stratified sample over 20 classes" in q.source
    idx = q.x[:, 0, 0].astype(int)
    assert len(set(idx)) == len(idx)
    for r in q.runs:  # consecutive original windows of one original run
        assert (np.diff(idx[r]) == 1).all() and len({i // 30 for i in idx[r]}) == 1
    assert np.array_equal(stratified(p, 256, block).x, q.x)
    assert np.array_equal(p.y[idx], q.y) and np.array_equal(p.take[idx], q.take)


def test_check_describes_an_ensemble_by_its_members(dataset, root):
    """tactile-check's window line: an ensemble's state rows are its members' layers, said
    as members x (layers x hidden), not as one deeper LSTM."""
    from tactile.contract import ModelContract
    from tactile.export.check import describe

    for name, want in (("ensemble2", "lstm (2 members x (1 x 8))"),
                       ("carry2-ensemble2", "lstm (2 members x (2 x 8))"),
                       ("lstm1", "lstm (1 x 8)")):
        _, out, _, _, _ = _build(name, GRID[name], dataset, root)
        meta = {p.key: p.value for p in onnx.load(out).metadata_props}
        assert want in describe(out, ModelContract.from_metadata(meta), None)


# -- the label stream's defaults, calibrated at export --------------------------------------------


@pytest.fixture(scope="module")
def calibrated_export(tmp_path_factory):
    """A tiny run on a dataset whose validation user has 40 s of each class (2 min of stream),
    exported with ``--data``: (run, file, report, dataset)."""
    root = tmp_path_factory.mktemp("calib")
    data = root / "data"
    make_dataset(data, takes=4, textures=("paper", "desk", "non_contact"), seconds=40, seed=2)
    train(data, root / "run", TrainConfig(**CALIBRATED), progress=False)
    out = root / "m.onnx"
    report = export_run(root / "run", out, data=data, log=lambda s: None)
    return root / "run", out, report, data


CALIBRATED = {**BASE, "epochs": 8}  # a first training good enough for defaults (1 epoch is not)


def test_export_with_data_writes_the_calibrated_defaults(calibrated_export, capsys):
    from tactile.device.recordings import load_dataset
    from tactile.postprocess.smoothing import KEYS, figures_from_metadata
    from tactile.runtime.model import Model
    from tactile.training.label_stream import validation_rows

    run, out, report, data = calibrated_export
    model = Model(out)
    assert model.postprocess is not None and set(KEYS) <= set(model.metadata)
    figures = figures_from_metadata(model.metadata)
    assert figures == report["postprocess"] and figures["setting"] == model.postprocess.describe()
    # calibrated on the validation takes, never the test ones
    net, ck = load_checkpoint(run)
    takes = load_dataset(data)
    rows, why = validation_rows(takes, ck, net.cfg, data.name)
    assert rows and not why
    assert not {takes[i].path.name for i in rows} & set(ck["test_rows"])
    # each user's validation rows joined into one stream of samples, windowed as a pen does
    per_user: dict[str, int] = {}
    for i, (a, b) in rows.items():
        user = str(takes[i].meta.get("user", "-"))
        per_user[user] = per_user.get(user, 0) + b - a
    assert figures["streams"] == len(per_user)
    assert figures["raw"]["windows"] == sum(
        (n - net.cfg.window) // net.cfg.hop + 1 for n in per_user.values())
    assert check_main([str(out)]) == 0
    text = capsys.readouterr().out
    assert f"  labels    {figures['setting']} (calibrated on " in text


def test_a_refit_run_calibrates_on_its_first_trainings_labels(calibrated_export, tmp_path,
                                                              capsys):
    """With refit (the default) the final model has trained on the validation takes, so its
    own labels of them calibrated the label stream in-sample (a BioTac finger-0 run: 94 %
    'correct stable labels' there, 76 % validation accuracy, and a setting that did worse than
    raw on the test takes). The checkpoint keeps the first training's labels of the validation
    streams, export calibrates on them and says so. They are checked against the same run
    trained without the refit (same seed and split: its model is the first training's best
    epoch), its validation streams made again here."""
    from tactile.device.recordings import load_dataset
    from tactile.postprocess.calibration import calibrate
    from tactile.training.evaluate import predict
    from tactile.training.label_stream import (
        pieces,
        run_streams,
        stored_streams,
        validation_rows,
    )

    run, out, report, data = calibrated_export
    net, ck = load_checkpoint(run)
    held = stored_streams(ck)
    assert held and ck["metrics"]["refit_epochs"] >= 1
    assert report["postprocess"]["labelled_by"] == "first_training"
    off = tmp_path / "off"
    train(data, off, TrainConfig(**CALIBRATED, refit="off"), progress=False)
    first, ck_off = load_checkpoint(off)
    takes = load_dataset(data)
    rows, why = validation_rows(takes, ck_off, first.cfg, data.name)
    assert rows and not why
    classes, channels = tuple(ck["classes"]), tuple(ck["channels"])
    rate = float(ck["sample_rate_hz"])
    again = run_streams(pieces(takes, rows, classes, channels, rate), classes, rate,
                        first.cfg.window, first.cfg.hop, lambda w: predict(first, w))
    assert len(again) == len(held)
    for a, b in zip(again, held, strict=True):
        np.testing.assert_array_equal(a.t, b.t)
        np.testing.assert_array_equal(a.truth, b.truth)
        np.testing.assert_allclose(a.probs, b.probs, rtol=0, atol=1e-5)
    # the final model's own labels of the validation takes differ: it refit on them
    final = run_streams(pieces(takes, rows, classes, channels, rate), classes, rate,
                        net.cfg.window, net.cfg.hop, lambda w: predict(net, w))
    assert max(np.abs(a.probs - b.probs).max() for a, b in zip(final, held)) > 1e-3
    figures = calibrate(held, max_uncertain=0.5).figures  # export's cap on uncertain windows
    assert report["postprocess"]["setting"] == figures["setting"]
    assert report["postprocess"]["raw"] == pytest.approx(figures["raw"])
    assert check_main([str(out)]) == 0
    assert "labelled by the first training's model (the final one refit on them)" in \
        capsys.readouterr().out


def test_a_refit_run_without_kept_labels_is_said_to_calibrate_in_sample(calibrated_export,
                                                                       tmp_path, capsys):
    """A refit run saved before runs kept their first training's labels: export and eval
    calibrate on the final model's own labels of takes it refit on, and now say so."""
    import shutil

    import torch

    from tactile.training.commands.eval import main as eval_main

    run, _, _, data = calibrated_export
    old = tmp_path / "old"
    shutil.copytree(run, old)
    ck = torch.load(old / "checkpoint.pt", weights_only=True)
    del ck["held_out_streams"]
    torch.save(ck, old / "checkpoint.pt")
    capsys.readouterr()
    export_run(old, tmp_path / "old.onnx", data=data, log=lambda s: None)
    err = capsys.readouterr().err
    assert ("tactile-export: warning: label stream calibrated on the final model's own labels "
            "of takes it refit on (a run saved before runs kept their first training's "
            "labels): figures in-sample") in err, err
    assert eval_main([str(old), str(data), "--json"]) == 0
    source = json.loads(capsys.readouterr().out)["label_stream"]["source"]
    assert "the final model's own labels of takes it refit on" in source, source


def test_calibrated_defaults_round_trip_through_the_contract(calibrated_export):
    from tactile import contract as contract_module
    from tactile.postprocess.smoothing import settings_from_metadata, settings_to_metadata

    _, out, _, _ = calibrated_export
    model, contract = load_contract(out)
    meta = {p.key: p.value for p in model.metadata_props}
    assert all(k in contract_module.OPTIONAL for k in meta if k.startswith("postprocess."))
    again = ModelContract.from_metadata(meta).to_metadata()
    assert {k: v for k, v in again.items() if k.startswith("postprocess.")} == \
        {k: v for k, v in meta.items() if k.startswith("postprocess.")}
    settings = settings_from_metadata(again)
    assert settings_from_metadata(settings_to_metadata(settings)) == settings


def test_export_without_validation_data_writes_no_defaults(dataset, root, tmp_path, capsys):
    """Without --data the file has no postprocess.* keys and runs raw; with a dataset whose
    validation takes make less than a minute of stream, neither, and one stderr line says so."""
    from tactile.runtime.model import Model
    from tactile.runtime.runner import post_processor

    run, out, report, _, _ = _build("lstm1", GRID["lstm1"], dataset, root)
    model = Model(out)
    assert report["postprocess"] is None and model.postprocess is None
    assert not [k for k in model.metadata if k.startswith("postprocess.")]
    assert post_processor(model) is None  # an old file without the keys: raw labels
    capsys.readouterr()
    short = export_run(run, tmp_path / "short.onnx", data=dataset, log=lambda s: None)
    err = capsys.readouterr().err
    assert short["postprocess"] is None and Model(tmp_path / "short.onnx").postprocess is None
    assert err.count("\n") == 1 and "too little validation data" in err


def test_a_setting_that_labels_fewer_windows_right_than_raw_is_not_written(
        calibrated_export, tmp_path, monkeypatch, capsys):
    """A grid whose only setting leaves windows uncertain (p_min 0.999) where no window may be
    (the limit set to 0 here: outside the limits): the calibration picks it, but it labels
    fewer windows right than the raw stream, so the file gets no defaults and runs raw, and one
    stderr line says why."""
    import tactile.training.label_stream as cal_module  # export's rule lives there
    from tactile.postprocess.calibration import calibrate
    from tactile.postprocess.smoothing import SmoothingSettings
    from tactile.runtime.model import Model

    cautious = SmoothingSettings(n=1, p_min=0.999, hold=3)
    monkeypatch.setattr(cal_module, "calibrate", lambda streams, **limits: calibrate(
        streams, (cautious,), **{**limits, "max_uncertain": 0.0}))
    run, _, _, data = calibrated_export
    capsys.readouterr()
    report = export_run(run, tmp_path / "raw.onnx", data=data, log=lambda s: None)
    err = capsys.readouterr().err
    assert report["postprocess"] is None and Model(tmp_path / "raw.onnx").postprocess is None
    assert err.count("\n") == 1 and "fewer correct stable labels than the raw stream" in err
    assert "ma:1 p_min=0.999 hold=3" in err
