"""bench/label_time.py --profile: where a window's time goes, node by node."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

onnx = pytest.importorskip("onnx")

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "models" / "pen-exp2.onnx"


def _bench():
    spec = importlib.util.spec_from_file_location("label_time", ROOT / "bench" / "label_time.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_profile_names_each_operator_type_with_its_node_count():
    bench = _bench()
    from tactile.runtime.model import Model

    windows = bench._windows(Model(SHIPPED).contract, None, 2.0)
    parts = dict(bench.profile(SHIPPED, windows))
    graph = onnx.load(str(SHIPPED)).graph
    lstms = sum(n.op_type == "LSTM" for n in graph.node)
    assert lstms >= 1
    label = f"LSTM ({lstms} node{'s' if lstms > 1 else ''})"
    assert label in parts, sorted(parts)
    assert all(t > 0 for t in parts.values())


def test_profile_option_prints_the_parts():
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "label_time.py"), str(SHIPPED),
                        "--profile", "--rounds", "1", "--seconds", "1"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "profile, kernel time per window" in r.stdout
    assert "LSTM (" in r.stdout


@pytest.mark.parametrize("args, code, says", [
    (["missing.onnx"], 3, "missing.onnx: no such model file"),
    (["README.md"], 3, "README.md: not a loadable ONNX model"),
    ([str(SHIPPED), "--data", "no-such-folder"], 1, "no-such-folder: not a folder"),
    ([str(SHIPPED), "--rounds", "0"], 1, "--rounds"),
    ([str(SHIPPED), "--seconds", "inf"], 1, "--seconds"),
    ([], 1, "give one or more .onnx files"),
])
def test_bad_input_is_one_line_and_an_exit_code(args, code, says, tmp_path):
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "label_time.py"), *args],
                       capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert r.returncode == code, r.stderr
    assert says in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_windows_take_the_models_channels_by_name_from_a_take_with_more(tmp_path):
    """A take that carries the model's channels among others, in another order (a BioTac
    take of both fingers for a model of one): its windows hold the model's channels by name,
    in the model's order, at the model's hop, not Gaussian stand-ins."""
    import numpy as np

    from tactile.device.protocol import ChannelSpec, DeviceInfo
    from tactile.device.recordings import TakeWriter
    from tactile.runtime.model import Model

    bench = _bench()
    c = Model(SHIPPED).contract
    names = ("extra", *reversed(c.channels))
    rows = c.window + 3 * c.hop
    raw = np.arange(rows * len(names)).reshape(rows, len(names)) % 997
    info = DeviceInfo(c.sample_rate_hz, tuple(ChannelSpec(n, "count") for n in names),
                      device="synthetic")
    with TakeWriter(tmp_path, "paper", info, "synthetic", name="t0") as w:
        w.write(0, 0, raw)
    got = bench._windows(c, tmp_path, 4 * c.hop / c.sample_rate_hz)
    assert got.shape == (4, c.window, len(c.channels))
    from tactile.device.recordings import load_dataset

    values = np.asarray(load_dataset(tmp_path)[0].values(), np.float32)
    want = values[:, [names.index(n) for n in c.channels]]
    for i in range(4):
        np.testing.assert_array_equal(got[i], want[i * c.hop : i * c.hop + c.window])
