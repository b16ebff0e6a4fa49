"""The kernels inside onnxruntime: the ``ai.tactile`` custom-op library (``ort_ops.c``) and the
model-local functions that stand in for it where it is not registered.

Tiny models hold one custom node and a FunctionProto of the same domain and name. With the
library registered the kernel runs (a fallback whose body computes something else proves which
ran); without it the function runs; on real bodies both paths agree: the EMD's (float64 on
both) within float32 output rounding, the coder's (float32 graph, float64 kernel) on the atoms
where no near-tie decides. Bad shapes, types and settings give an
onnxruntime error, never a crash. The paths run again in onnxruntime 1.19.2, the oldest
supported, in a virtualenv the test makes once under the user's cache folder, or in the
interpreters ``TACTILE_ORT_PYTHONS`` names (space-separated).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from conftest import HAPMAT, SHARED
from onnx import TensorProto, helper, numpy_helper

from tactile import native
from tactile.export.coder_graph import coder_graph, coder_node_model
from tactile.export.custom_ops import function_of, opset_imports
from tactile.export.emd_graph import build_emd_model, emd_node_model
from tactile.training.emd import EMD
from tactile.training.sparse import SparseCoder

pytestmark = pytest.mark.skipif(not native.available(), reason="native kernels not built")


def _session(model: onnx.ModelProto, library: bool) -> ort.InferenceSession:
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.log_severity_level = 3
    if library:
        so.register_custom_ops_library(str(native.library_path()))
    return ort.InferenceSession(model.SerializeToString(), so,
                                providers=["CPUExecutionProvider"])


def _vi(name, shape, elem=TensorProto.FLOAT):
    return helper.make_tensor_value_info(name, elem, shape)


def _marker_coder(d: np.ndarray, n_nonzero: int) -> onnx.ModelProto:
    """A SparseCode node whose fallback is NOT OMP: codes = x @ dictionary^T (dense)."""
    fn = helper.make_function(
        "ai.tactile", "SparseCode", ["x", "dictionary", "gram"], ["codes"],
        [helper.make_node("Transpose", ["dictionary"], ["dt"]),
         helper.make_node("MatMul", ["x", "dt"], ["codes"])],
        [helper.make_opsetid("", 18)], attributes=["n_nonzero"])
    node = helper.make_node("SparseCode", ["x", "d", "g"], ["codes"], domain="ai.tactile",
                            n_nonzero=n_nonzero)
    gram = (d.astype(np.float64) @ d.astype(np.float64).T).astype(np.float32)
    graph = helper.make_graph([node], "marker", [_vi("x", ["b", d.shape[1]])],
                              [_vi("codes", ["b", d.shape[0]])],
                              initializer=[numpy_helper.from_array(d, "d"),
                                           numpy_helper.from_array(gram, "g")])
    model = helper.make_model(graph, opset_imports=opset_imports(), functions=[fn])
    model.ir_version = 8
    onnx.checker.check_model(model, full_check=True)
    return model


def test_registered_library_runs_the_kernel_and_the_function_runs_without_it():
    rng = np.random.default_rng(0)
    d = rng.standard_normal((6, 9)).astype(np.float32)
    x = rng.standard_normal((4, 9)).astype(np.float32)
    model = _marker_coder(d, 2)
    plain = _session(model, False).run(None, {"x": x})[0]
    kernel = _session(model, True).run(None, {"x": x})[0]
    np.testing.assert_allclose(plain, x @ d.T, rtol=1e-5, atol=1e-5)  # the function's body
    gram = (d.astype(np.float64) @ d.astype(np.float64).T).astype(np.float32)
    np.testing.assert_array_equal(kernel, native.omp(x, d, gram, 2))  # the C kernel
    assert ((kernel != 0).sum(1) <= 2).all()


@pytest.mark.parametrize("shape", [(1, 1, 50), (3, 2, 50), (2, 1, 1100)])
def test_emd_node_paths_agree(shape):
    batch, channels, n_time = shape
    n_imfs = 8 if n_time > 100 else 4
    model = emd_node_model(n_imfs, 10, channels, n_time)
    assert [n.op_type for n in model.graph.node] == ["EMD"]
    t = np.linspace(0, 1, n_time)
    rng = np.random.default_rng(n_time)
    x = (np.sin(2 * np.pi * 7 * t) + 0.5 * np.sin(2 * np.pi * 23 * t)
         + 0.1 * rng.standard_normal((batch, channels, n_time))).astype(np.float32)
    portable = _session(model, False).run(None, {"x_in": x})
    kernel = _session(model, True).run(None, {"x_in": x})
    graph = _session(build_emd_model(n_imfs, 10, channels, n_time, torch.float64), False).run(
        None, {"x_in": x.astype(np.float64)})
    for a, b in zip(portable, graph):
        np.testing.assert_array_equal(a, b.astype(a.dtype))  # the float64 graph, bit for bit
    assert [a.dtype for a in kernel] == [np.float32, np.float32, np.int64]
    assert [a.dtype for a in portable] == [np.float32, np.float32, np.int64]
    assert [a.shape for a in kernel] == [a.shape for a in portable]
    np.testing.assert_array_equal(kernel[2], portable[2])
    std = x.std(-1)[..., None]
    # both compute in float64: the float64 torch module up to float32 output rounding
    ref = EMD(n_imfs, 10)(torch.from_numpy(x.astype(np.float64)))
    for out in (kernel, portable):
        np.testing.assert_array_equal(out[2], ref[2].numpy())
        assert (np.abs(out[0] - ref[0].numpy()) / std[..., None]).max() <= 1e-6
        assert (np.abs(out[1] - ref[1].numpy()) / std).max() <= 1e-6


def _standardised(windows: np.ndarray) -> np.ndarray:
    """Each non-constant window centred and scaled to unit std, in float32 (as a model's
    normalisation leaves the EMD's input: other units, the same shapes)."""
    w = np.asarray(windows, np.float64)
    w = w[w.std(1) > 0]
    return ((w - w.mean(1, keepdims=True)) / w.std(1, keepdims=True)).astype(np.float32)


def _real_windows(source: str) -> tuple[np.ndarray, int]:
    """Windows of real or simulated sensor data and the IMF count models use on them: 50
    samples of the simulated pen's and HapMat's channels (4 IMFs, the pen's), 1,100 samples
    (0.5 s at 2.2 kHz) of BioTac BOLT finger 0's vibration (8 IMFs, the paper's); skipped,
    saying why, where the shared data are absent."""
    if source == "simulated pen":
        from tactile.device.sim import TEXTURES, PenSimulator

        out = []
        for i, texture in enumerate(TEXTURES):
            raw = PenSimulator(texture, seed=i).read(50 * 24)
            out += [raw[j * 50:(j + 1) * 50, j % raw.shape[1]] for j in range(24)]
        return _standardised(out), 4
    if source == "HapMat":
        if not HAPMAT.is_file():
            pytest.skip(f"shared HapMat data not found at {HAPMAT.name} beside the repository")
        x = np.load(HAPMAT)["X"]  # (materials, samples, channels)
        return _standardised([x[m, j:j + 50, (j // 250) % x.shape[2]] for m in range(len(x))
                              for j in range(0, x.shape[1] - 50, 250)]), 4
    h5py = pytest.importorskip("h5py", reason="the [biotac] extra (h5py) is not installed")
    files = sorted((SHARED / "datasets" / "biotac-bolt").glob("*.h5"))
    if not files:
        pytest.skip("shared BioTac BOLT data (biotac-bolt/*.h5) not found beside the repository")
    out = []
    for path in files:
        with h5py.File(path, "r") as f:
            for trial in sorted(f)[::3]:
                pac = f[trial]["finger_0/pac"][()].reshape(-1)  # 22 sub-samples a frame, in order
                out += [pac[s:s + 1100] for s in range(0, len(pac) - 1100, 1100 * 18)]
    return _standardised(out), 8


@pytest.mark.parametrize("source", ["simulated pen", "HapMat", "BioTac BOLT"])
def test_emd_paths_agree_on_real_windows(source):
    """The kernel against the portable graph, both in onnxruntime, on float32 windows of real
    data: both compute in float64, so the same IMF count on every window and IMFs and residue
    within float32 output rounding (1e-6 x std) on every window. (In float32 the graph had
    moved a knot on a near-tie of two extrema: 7 of 200 BioTac vibration windows by more than
    1e-3 x std, docs/emd.md.)"""
    x, n_imfs = _real_windows(source)
    model = emd_node_model(n_imfs, 10, 1, x.shape[1])
    feed = {"x_in": x[:, None]}
    kernel = _session(model, True).run(None, feed)
    portable = _session(model, False).run(None, feed)
    np.testing.assert_array_equal(kernel[2], portable[2])
    std = x.astype(np.float64).std(1)
    rel = np.maximum(np.abs(kernel[0] - portable[0]).max(axis=(1, 2, 3)),
                     np.abs(kernel[1] - portable[1]).max(axis=(1, 2))) / std
    assert len(x) >= 100
    assert rel.max() <= 1e-6, f"{(rel > 1e-6).sum()} of {len(x)} windows off, up to {rel.max():.3g}"
    print(f"\n{source}: {len(x)} x {x.shape[1]}, {n_imfs} IMFs: IMF counts identical; "
          f"median {np.median(rel):.2g}, max {rel.max():.2g} x std")


def test_coder_node_paths_agree():
    rng = np.random.default_rng(3)
    d = rng.standard_normal((46, 30))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    coder = SparseCoder(d, 5)
    model = coder_node_model(coder)
    x = rng.standard_normal((46, 30)).astype(np.float32)
    portable = _session(model, False).run(None, {"x": x})[0]
    kernel = _session(model, True).run(None, {"x": x})[0]
    np.testing.assert_array_equal(portable, _session(coder_graph(coder), False).run(
        None, {"x": x})[0])
    # the same atoms on every row: random rows hold no near-tie of correlations that float32
    # rounding could decide (near-ties are excused against scikit-learn in test_native)
    assert ((portable != 0) == (kernel != 0)).all()
    assert np.abs(portable - kernel).max() <= 1e-4 * max(1.0, np.abs(portable).max())


def test_two_emd_shapes_share_one_function():
    g1 = build_emd_model(4, 10, 2, 50).graph
    g2 = build_emd_model(3, 5, 1, 30).graph
    fn = function_of("EMD", [([2, 50, 4, 10], g1), ([1, 30, 3, 5], g2)])
    nodes = [helper.make_node("EMD", ["x1"], ["i1", "r1", "v1"], domain="ai.tactile",
                              n_imfs=4, n_sifts=10),
             helper.make_node("EMD", ["x2"], ["i2", "r2", "v2"], domain="ai.tactile",
                              n_imfs=3, n_sifts=5)]
    graph = helper.make_graph(nodes, "two", [_vi("x1", ["b", 2, 50]), _vi("x2", ["b", 1, 30])],
                              [_vi("i1", ["b", 2, 4, 50]), _vi("i2", ["b", 1, 3, 30])])
    model = helper.make_model(graph, opset_imports=opset_imports(), functions=[fn])
    model.ir_version = 8
    onnx.checker.check_model(model, full_check=True)
    rng = np.random.default_rng(5)
    feed = {"x1": rng.standard_normal((3, 2, 50)).astype(np.float32),
            "x2": rng.standard_normal((3, 1, 30)).astype(np.float32)}
    portable = _session(model, False).run(None, feed)
    kernel = _session(model, True).run(None, feed)
    for k, (n_imfs, n_sifts, c, t) in enumerate([(4, 10, 2, 50), (3, 5, 1, 30)]):
        own = _session(build_emd_model(n_imfs, n_sifts, c, t), False).run(
            None, {"x_in": feed[f"x{k + 1}"]})[0]
        np.testing.assert_array_equal(portable[k], own)
        np.testing.assert_allclose(kernel[k], own, rtol=0, atol=1e-5)


def _loose(op: str, inputs, outputs, **attrs) -> onnx.ModelProto:
    """A one-node model whose inputs have no declared shape: only the kernel checks them."""
    node = helper.make_node(op, [i for i, _ in inputs], [o for o, _ in outputs],
                            domain="ai.tactile", **attrs)
    vis = [helper.make_tensor_value_info(i, e, None) for i, e in inputs]
    outs = [helper.make_tensor_value_info(o, e, None) for o, e in outputs]
    model = helper.make_model(helper.make_graph([node], "loose", vis, outs),
                              opset_imports=opset_imports())
    model.ir_version = 8
    return model


F, I64 = TensorProto.FLOAT, TensorProto.INT64
EMD_IO = ([("x", F)], [("i", F), ("r", F), ("v", I64)])
CODE_IO = ([("x", F), ("d", F), ("g", F)], [("c", F)])
_f = np.float32


@pytest.mark.parametrize("op, io, attrs, feed, message", [
    ("EMD", EMD_IO, {"n_imfs": 4, "n_sifts": 10}, {"x": np.zeros((2, 50), _f)},
     "(batch, channels, time)"),
    ("EMD", EMD_IO, {"n_imfs": 4, "n_sifts": 10}, {"x": np.zeros((1, 1, 1, 5), _f)},
     "(batch, channels, time)"),
    ("EMD", EMD_IO, {"n_imfs": 0, "n_sifts": 10}, {"x": np.zeros((1, 1, 50), _f)},
     "out of range"),
    ("EMD", EMD_IO, {"n_imfs": 4, "n_sifts": 5000}, {"x": np.zeros((1, 1, 50), _f)},
     "out of range"),
    ("EMD", EMD_IO, {"n_imfs": 4}, {"x": np.zeros((1, 1, 50), _f)}, "n_sifts"),
    ("SparseCode", CODE_IO, {"n_nonzero": 2},
     {"x": np.zeros((3, 5), _f), "d": np.zeros((4, 6), _f), "g": np.zeros((4, 4), _f)},
     "features"),
    ("SparseCode", CODE_IO, {"n_nonzero": 2},
     {"x": np.zeros((3, 5), _f), "d": np.zeros((4, 5), _f), "g": np.zeros((4, 3), _f)},
     "gram"),
    ("SparseCode", CODE_IO, {"n_nonzero": 9},
     {"x": np.zeros((3, 5), _f), "d": np.zeros((4, 5), _f), "g": np.zeros((4, 4), _f)},
     "n_nonzero"),
    ("SparseCode", CODE_IO, {"n_nonzero": 2},
     {"x": np.zeros((3, 5, 1), _f), "d": np.zeros((4, 5), _f), "g": np.zeros((4, 4), _f)},
     "2-d float32"),
    ("SparseCode", CODE_IO, {"n_nonzero": 2},
     {"x": np.zeros((3, 0), _f), "d": np.zeros((4, 0), _f), "g": np.zeros((4, 4), _f)},
     "features"),
])
def test_bad_inputs_give_an_onnxruntime_error(op, io, attrs, feed, message):
    model = _loose(op, *io, **attrs)
    with pytest.raises((ort.capi.onnxruntime_pybind11_state.Fail,
                        ort.capi.onnxruntime_pybind11_state.InvalidArgument,
                        ort.capi.onnxruntime_pybind11_state.RuntimeException)) as err:
        _session(model, True).run(None, feed)
    assert message in str(err.value)


def test_empty_batch_and_non_finite_rows():
    model = _loose("EMD", *EMD_IO, n_imfs=3, n_sifts=4)
    sess = _session(model, True)
    imfs, res, nv = sess.run(None, {"x": np.zeros((0, 2, 40), _f)})
    assert imfs.shape == (0, 2, 3, 40) and res.shape == (0, 2, 40) and nv.shape == (0, 2)
    x = np.random.default_rng(0).standard_normal((1, 2, 40)).astype(_f)
    x[0, 1, 7] = np.nan
    imfs, res, nv = sess.run(None, {"x": x})  # the kernels' defined result for that row
    assert nv[0, 1] == 0 and not imfs[0, 1].any()
    np.testing.assert_array_equal(res[0, 1], x[0, 1])
    assert nv[0, 0] > 0


_OTHER = """
import sys, numpy as np, onnxruntime as ort
lib, folder = sys.argv[1], sys.argv[2]
z = np.load(folder + "/io.npz")
outs = {}
for use in (0, 1):
    so = ort.SessionOptions()
    if use:
        so.register_custom_ops_library(lib)
    for name in ("emd", "marker"):
        s = ort.InferenceSession(folder + "/" + name + ".onnx", so,
                                 providers=["CPUExecutionProvider"])
        outs[f"{name}{use}"] = s.run(None, {s.get_inputs()[0].name: z[name]})[0]
    try:
        s = ort.InferenceSession(folder + "/bad.onnx", so, providers=["CPUExecutionProvider"])
        s.run(None, {"x": np.zeros((2, 50), np.float32)})
        outs[f"bad{use}"] = np.array("no error")
    except Exception as e:
        outs[f"bad{use}"] = np.array(str(e))
np.savez(folder + "/out.npz", version=np.array(ort.__version__), **outs)
"""


ORT_OLDEST = "1.19.2"  # the oldest onnxruntime pyproject.toml allows (>=1.19)


def _other_pythons() -> list[str]:
    """``TACTILE_ORT_PYTHONS``, else a virtualenv with onnxruntime :data:`ORT_OLDEST` made once
    under the user's cache folder (a minute, from the package index); this interpreter runs
    the newest installed here."""
    if os.environ.get("TACTILE_ORT_PYTHONS"):
        return os.environ["TACTILE_ORT_PYTHONS"].split()
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    venv = cache / "tactile-ort" / ORT_OLDEST
    python = venv / "bin" / "python"
    check = [str(python), "-c", f"import onnxruntime as o; assert o.__version__ == {ORT_OLDEST!r}"]
    if python.exists() and subprocess.run(check, capture_output=True).returncode == 0:
        return [str(python)]
    subprocess.run([sys.executable, "-m", "venv", "--clear", str(venv)], check=True)
    made = subprocess.run([str(python), "-m", "pip", "install", "-q",
                           f"onnxruntime=={ORT_OLDEST}", "numpy"],
                          capture_output=True, text=True, timeout=900)
    if made.returncode != 0:
        why = f"could not install onnxruntime {ORT_OLDEST}: {made.stderr.strip()[-300:]}"
        if os.environ.get("CI") == "true":
            pytest.fail(why)
        pytest.skip(why)
    return [str(python)]


def test_other_onnxruntime_versions(tmp_path):
    pythons = _other_pythons()
    rng = np.random.default_rng(9)
    d = rng.standard_normal((6, 9)).astype(np.float32)
    emd = emd_node_model(4, 10, 1, 50)
    onnx.save(emd, tmp_path / "emd.onnx")
    onnx.save(_marker_coder(d, 2), tmp_path / "marker.onnx")
    onnx.save(_loose("EMD", *EMD_IO, n_imfs=4, n_sifts=10), tmp_path / "bad.onnx")
    x_emd = rng.standard_normal((2, 1, 50)).astype(np.float32)
    x_code = rng.standard_normal((4, 9)).astype(np.float32)
    np.savez(tmp_path / "io.npz", emd=x_emd, marker=x_code)
    (tmp_path / "other.py").write_text(_OTHER)
    want_emd = _session(emd, False).run(None, {"x_in": x_emd})[0]
    gram = (d.astype(np.float64) @ d.astype(np.float64).T).astype(np.float32)
    for python in pythons:
        run = subprocess.run([python, str(tmp_path / "other.py"), str(native.library_path()),
                              str(tmp_path)], capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr[-2000:]
        z = np.load(tmp_path / "out.npz")
        version = str(z["version"])
        np.testing.assert_array_equal(z["emd0"], want_emd, err_msg=version)
        np.testing.assert_allclose(z["emd1"], want_emd, rtol=0, atol=1e-5, err_msg=version)
        np.testing.assert_allclose(z["marker0"], x_code @ d.T, rtol=1e-5, atol=1e-5)
        np.testing.assert_array_equal(z["marker1"], native.omp(x_code, d, gram, 2))
        assert "(batch, channels, time)" in str(z["bad1"]), version
        print(f"onnxruntime {version}: both paths agree", file=sys.stderr)


# -- the runtime and tactile-check on an exported file ------------------------------------------


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    from test_export_bytes import write_checkpoint

    from tactile.export.exporter import export_run

    run = tmp_path_factory.mktemp("run")
    write_checkpoint("lstm-emd", run)
    out = run / "model.onnx"
    report = export_run(run, out, log=lambda s: None)
    assert report["parity_native"]["passed"]  # the exporter measured the kernels too
    return out


@pytest.fixture
def fresh_kernels(monkeypatch):
    from tactile.runtime import kernels

    monkeypatch.setattr(kernels, "_state", {"disabled": False, "said": False})
    return kernels


def test_contract_records_the_custom_nodes(exported):
    from tactile.runtime.model import Model

    c = Model(exported).contract
    assert [(n["op"], n["name"]) for n in c.custom_ops] == [("EMD", "emd0")]
    assert c.custom_ops[0]["attributes"] == {"n_imfs": 2, "n_sifts": 3}
    assert c.parity["native"]["passed"]
    # the key names the domain and the fallback, and the file holds that fallback: a
    # model-local function of the node's domain and name
    m = onnx.load(exported)
    key = json.loads({p.key: p.value for p in m.metadata_props}["custom_ops"])
    assert (key["domain"], key["version"]) == ("ai.tactile", 1)
    assert key["fallback"].startswith("model-local function of the same domain and name")
    assert {(f.domain, f.name) for f in m.functions} >= {("ai.tactile", "EMD")}
    assert [(n.domain, n.op_type) for n in m.graph.node if n.domain] == [("ai.tactile", "EMD")]


def test_runtime_runs_the_kernel_and_falls_back_saying_so_once(exported, fresh_kernels,
                                                               monkeypatch, capsys):
    from tactile.runtime.model import Model

    assert fresh_kernels.library_path() == native.library_path()
    fast = Model(exported)
    assert fast.native and capsys.readouterr().err == ""
    monkeypatch.setenv("TACTILE_NATIVE", "0")
    assert fresh_kernels.library_path() is None
    slow, again = Model(exported), Model(exported)
    assert not slow.native and not again.native
    err = capsys.readouterr().err
    assert err.count("portable") == 1 and "disabled" in err
    x = np.random.default_rng(0).standard_normal(
        (4, fast.contract.window, len(fast.contract.channels))).astype(np.float32)
    h, c = fast.zero_state(4)
    p_fast = fast.session.run(None, {"x": x, "h": h, "c": c})[0]
    p_slow = slow.session.run(None, {"x": x, "h": h, "c": c})[0]
    assert np.abs(p_fast - p_slow).max() <= 1e-4


@pytest.mark.parametrize("value, off", [("0", True), ("false", True), ("OFF", True),
                                        ("no", True), ("1", False), ("yes", False),
                                        ("true", False), ("", False)])
def test_tactile_native_off_and_on_values(fresh_kernels, monkeypatch, capsys, value, off):
    monkeypatch.setenv("TACTILE_NATIVE", value)
    assert (fresh_kernels.library_path() is None) is off
    assert native.disabled_by_env() is off
    assert capsys.readouterr().err == ""


def test_an_unknown_tactile_native_value_keeps_the_kernels_and_says_so_once(
        fresh_kernels, monkeypatch, capsys):
    """A typo must not stop a board's label stream, nor pass unnoticed."""
    monkeypatch.setattr(native, "_warned", set())
    monkeypatch.setenv("TACTILE_NATIVE", "disable")
    assert fresh_kernels.library_path() == native.library_path() is not None
    native.disabled_by_env()
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "TACTILE_NATIVE='disable'" in err and "stay on" in err


def test_disable_forces_the_portable_path(fresh_kernels):
    fresh_kernels.disable()
    assert fresh_kernels.library_path() is None


@pytest.mark.parametrize("flag, line", [([], "EMD: native kernel"),
                                        (["--no-native"], "EMD: portable graph")])
def test_check_names_the_path_of_each_custom_op(exported, fresh_kernels, capsys, flag, line):
    from tactile.export.commands.check import main

    assert main([str(exported), *flag]) == 0
    assert f"kernels   {line}" in capsys.readouterr().out


def test_check_of_a_file_without_custom_ops_says_whether_the_library_is_built(
        fresh_kernels, monkeypatch, capsys):
    """The shipped pen model has no EMD: its check still says whether a board's install built
    the library (the one line a user has to tell the two installs apart)."""
    from tactile.export.commands.check import main

    shipped = str(Path(__file__).resolve().parents[1] / "models" / "pen-exp2.onnx")
    built = native.library_path()
    assert built is not None  # the test install builds it
    for setup, want in (
            (lambda: None, f"none needed by this file (no EMD or sparse-code node); the kernel "
                           f"library is built ({built.name})"),
            (fresh_kernels.disable, "none needed by this file (no EMD or sparse-code node); "
                                    "native kernels disabled"),
            (lambda: monkeypatch.setattr(native, "library_path", lambda: None),
             "none needed by this file (no EMD or sparse-code node); no kernel library: the "
             "package was installed without a C compiler")):
        fresh_kernels._state.update(disabled=False, said=False)
        setup()
        assert main([shipped]) == 0
        out = capsys.readouterr().out
        assert [ln for ln in out.splitlines() if ln.startswith("  kernels")] == [
            f"  kernels   {want}"], out


def test_tactile_run_no_native_runs_the_portable_graphs(exported, fresh_kernels, tmp_path,
                                                       capsys):
    """``tactile-run --no-native`` on a replayed take: the portable graphs, said once on
    stderr, and the kernels' labels (their probabilities agree within the export's 1e-4)."""
    from tactile.device.sim import make_dataset
    from tactile.runtime.commands.run import main

    take = make_dataset(tmp_path / "d", 1, ("paper",), seconds=3.0, seed=5)[0]
    outs = {}
    for flag in ([], ["--no-native"]):
        fresh_kernels._state.update(disabled=False, said=False)
        assert main(["--model", str(exported), "--replay", str(take), "--raw", *flag]) == 0
        out, err = capsys.readouterr()
        outs[bool(flag)] = [json.loads(ln) for ln in out.splitlines()]
        said = err.count("tactile-run: running the portable EMD/sparse-code graphs (native "
                         "kernels disabled)")  # named as the command's lines are
        assert said == (1 if flag else 0), err
    fast, slow = outs[False], outs[True]
    assert len(fast) == len(slow) >= 20
    for a, b in zip(fast, slow):
        assert a["seq"] == b["seq"] and a["label"] == b["label"]
        assert abs(a["p"] - b["p"]) <= 1e-4


def test_without_a_built_library_the_runtime_says_so_once(exported, fresh_kernels, monkeypatch,
                                                          capsys):
    """An install without a C compiler: no library, the portable graphs, one stderr line."""
    from tactile.runtime.model import Model

    monkeypatch.setattr(native, "library_path", lambda: None)
    assert fresh_kernels.library_path() is None
    models = [Model(exported), Model(exported)]
    assert not any(m.native for m in models)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "installed without a C compiler" in err
    assert fresh_kernels.paths(models[0].contract.custom_ops, False) == [
        "EMD: portable graph (no kernel library)"]


_SANITIZED = """
import sys, numpy as np, onnxruntime as ort
lib, folder = sys.argv[1], sys.argv[2]
so = ort.SessionOptions()
so.register_custom_ops_library(lib)
rng = np.random.default_rng(3)
ran = 0
shapes = {"emd50": (2, 2, 50), "emd3": (2, 1, 3), "emd1": (2, 1, 1), "code": (5, 12)}
for name, shape in shapes.items():
    s = ort.InferenceSession(f"{folder}/{name}.onnx", so, providers=["CPUExecutionProvider"])
    first = s.get_inputs()[0]
    for kind in ("noise", "nan", "inf", "huge", "tiny", "constant", "walk", "empty"):
        x = rng.standard_normal(shape).astype(np.float32)
        if kind == "nan": x.flat[::7] = np.nan
        if kind == "inf": x.flat[::5] = np.inf
        if kind == "huge": x *= np.float32(3e37)
        if kind == "tiny": x *= np.float32(1e-38)
        if kind == "constant": x[:] = 1.5
        if kind == "walk": x = np.cumsum(x, axis=-1, dtype=np.float32)
        if kind == "empty": x = x[:0]
        for _ in range(3):  # repeated calls: per-call allocations must be freed
            s.run(None, {first.name: x})
            ran += 1
print("runs", ran)
"""


def test_custom_ops_inside_onnxruntime_under_address_and_undefined_sanitizers(tmp_path):
    """The custom-op library built with ASan and UBSan, loaded into onnxruntime in a Python
    whose allocator ASan intercepts (LD_PRELOAD), runs both ops on noise, NaN, inf, huge, tiny,
    constant, random-walk and empty inputs at lengths 50, 3 and 1, three calls each: no
    sanitizer report. (LeakSanitizer stays off: the interpreter itself holds memory at exit;
    the kernels' own leak check is the C test of tests/test_native.py.)"""
    import shutil

    gcc = shutil.which("gcc")
    if gcc is None or sys.platform != "linux":
        msg = "needs gcc on Linux to build the sanitized library"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    src = Path(native.__file__).parent
    lib = tmp_path / "libtactile_asan.so"
    build = subprocess.run(
        [gcc, "-std=c99", "-shared", "-fPIC", "-O1", "-g", "-fno-omit-frame-pointer",
         "-fsanitize=address,undefined", "-fno-sanitize-recover=all", "-ffp-contract=off",
         f"-I{src}", str(src / "emd.c"), str(src / "omp.c"), str(src / "ort_ops.c"),
         "-o", str(lib), "-lm"], capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stderr[-2000:]
    runtime = subprocess.run([gcc, "-print-file-name=libasan.so"], capture_output=True,
                             text=True).stdout.strip()
    ubsan = subprocess.run([gcc, "-print-file-name=libubsan.so"], capture_output=True,
                           text=True).stdout.strip()
    assert Path(runtime).exists(), runtime
    for name, (c, t) in (("emd50", (2, 50)), ("emd3", (1, 3))):
        onnx.save(emd_node_model(4, 10, c, t), tmp_path / f"{name}.onnx")
    onnx.save(_loose("EMD", *EMD_IO, n_imfs=4, n_sifts=10), tmp_path / "emd1.onnx")  # < 3
    d = np.random.default_rng(0).standard_normal((20, 12))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    onnx.save(coder_node_model(SparseCoder(d.astype(np.float32), 3)), tmp_path / "code.onnx")
    (tmp_path / "run.py").write_text(_SANITIZED)
    env = {**os.environ, "LD_PRELOAD": f"{runtime} {ubsan}" if Path(ubsan).exists() else runtime,
           "ASAN_OPTIONS": "detect_leaks=0:halt_on_error=1:abort_on_error=0",
           "UBSAN_OPTIONS": "print_stacktrace=1:halt_on_error=1"}
    run = subprocess.run([sys.executable, str(tmp_path / "run.py"), str(lib), str(tmp_path)],
                         capture_output=True, text=True, timeout=600, env=env)
    report = run.stdout + run.stderr
    assert run.returncode == 0, report[-3000:]
    assert "Sanitizer" not in report and "runtime error" not in report, report[-3000:]
    assert "runs 96" in run.stdout, report[-1000:]
