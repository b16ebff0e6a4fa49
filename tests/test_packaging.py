"""Packaging rules: the runtime is torch-free; the base requirements are the runtime's only."""

from __future__ import annotations

import subprocess
import sys
import tomllib

from conftest import REPO


def test_runtime_and_device_import_without_torch():
    code = (
        "import sys, tactile.runtime, tactile.runtime.cli, tactile.runtime.model, "
        "tactile.runtime.stream, tactile.contract, tactile.device, tactile.device.decoder, "
        "tactile.device.recorder, tactile.device.simlink\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'onnx', 'PyEMD'))\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"torch-side modules imported: {out.stdout}"


def test_base_requirements_are_the_runtime_only():
    meta = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    names = {r.split(">")[0].split("=")[0].split("!")[0].split("<")[0].strip()
             for r in meta["dependencies"]}
    assert names == {"numpy", "onnxruntime", "pyserial"}
    assert any(r.startswith("torch>=") for r in meta["optional-dependencies"]["train"])
    # the aarch64 wheel of onnxruntime 1.21.0 crashes on a Raspberry Pi 4
    assert any("!=1.21.0" in r for r in meta["dependencies"] if r.startswith("onnxruntime"))
