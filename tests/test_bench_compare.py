"""bench/compare_models.py: two files side by side, and one line (exit 2) for files it cannot
compare."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "models" / "pen-exp2.onnx"


def compare(*args: str):
    return subprocess.run([sys.executable, str(ROOT / "bench" / "compare_models.py"), *args],
                          capture_output=True, text=True, timeout=300)


def test_a_file_against_itself_prints_a_ratio():
    r = compare(str(SHIPPED), str(SHIPPED), "--rounds", "3")
    assert r.returncode == 0, r.stderr
    ratio = float(r.stdout.split("B / A")[1].split()[0])
    assert ratio > 0  # its value is the machine's noise between rounds: no test of timing


def test_files_it_cannot_compare_are_one_line(tmp_path):
    other = tmp_path / "other.onnx"
    x = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 3])
    out = helper.make_tensor_value_info("z", TensorProto.FLOAT, [1, 3])
    graph = helper.make_graph([helper.make_node("Identity", ["y"], ["z"])], "g", [x], [out])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)]), other)
    for args, says in (((str(SHIPPED), str(other)), "take different inputs"),
                       ((str(tmp_path / "none.onnx"), str(SHIPPED)), "none.onnx"),
                       ((str(SHIPPED), str(SHIPPED), "--rounds", "0"), "--rounds")):
        r = compare(*args)
        assert r.returncode == 1 and says in r.stderr and "Traceback" not in r.stderr, r.stderr
        assert r.stderr.count("\n") == 1
        assert r.stdout == ""


def _graph(path: Path, x_shape: list, h_shape: list) -> str:
    """A graph of inputs x and h (h's shape: a state's) whose output is x's sum."""
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, x_shape)
    h = helper.make_tensor_value_info("h", TensorProto.FLOAT, h_shape)
    out = helper.make_tensor_value_info("p", TensorProto.FLOAT, None)
    node = helper.make_node("ReduceSum", ["x"], ["p"], keepdims=0)
    graph = helper.make_graph([node], "g", [x, h], [out])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)]), path)
    return str(path)


def test_states_of_other_shapes_compare_windows_must_match(tmp_path):
    """An ensemble's state is larger than one model's: each file gets its own; the window x
    must be the same."""
    one = _graph(tmp_path / "one.onnx", ["batch", 50, 8], [2, "batch", 64])
    two = _graph(tmp_path / "two.onnx", ["batch", 50, 8], [4, "batch", 64])
    r = compare(one, two, "--rounds", "2")
    assert r.returncode == 0 and "B / A" in r.stdout, r.stderr
    other = _graph(tmp_path / "w30.onnx", ["batch", 30, 8], [2, "batch", 64])
    r = compare(one, other)
    assert r.returncode == 1 and r.stdout == "" and "take different inputs" in r.stderr
    assert "x ['batch', 50, 8]" in r.stderr and "x ['batch', 30, 8]" in r.stderr


def test_files_run_as_the_runtime_runs_them(tmp_path):
    """The kernels were never registered, so a file with ai.tactile nodes was timed on its
    portable graph (5 ms a window where tactile-run takes 0.2): each file now runs the path
    tactile-run takes, and the line says which."""
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        from compare_models import _session
    finally:
        sys.path.remove(str(ROOT / "bench"))
    from tactile.export.emd_graph import export_emd_onnx
    from tactile.runtime import kernels

    path = tmp_path / "emd.onnx"
    export_emd_onnx(path, n_imfs=2, n_sifts=2, n_channels=1, n_time=20, native=True)
    assert _session(str(SHIPPED))[1] == "standard operators"
    assert _session(str(path))[1] == ("native kernels" if kernels.library_path()
                                      else "portable graph")
    r = compare(str(SHIPPED), str(SHIPPED), "--rounds", "1")
    assert "(standard operators); B " in r.stdout, r.stdout
