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


def test_the_built_wheel_requires_no_torch(tmp_path):
    """What `pip install tactile-pen` (no extras) asks for, read from the wheel pip would get."""
    import zipfile

    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
         "-w", str(tmp_path), str(REPO)],
        check=True, capture_output=True,
    )
    (wheel,) = tmp_path.glob("tactile_pen-*.whl")
    with zipfile.ZipFile(wheel) as z:
        meta = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
        lines = z.read(meta).decode().splitlines()
        names = z.namelist()
    base = [ln for ln in lines if ln.startswith("Requires-Dist:") and "extra ==" not in ln]
    base_names = {ln.split(":", 1)[1].strip().split()[0].split(">")[0].split("!")[0]
                  for ln in base}
    assert base_names == {"numpy", "onnxruntime", "pyserial"}, base
    extras = [ln for ln in lines if ln.startswith("Requires-Dist:") and "torch" in ln]
    assert extras and all("extra == \"train\"" in ln for ln in extras)
    # the wheel carries every stage and the protocol spec, not only what the editable install sees
    for module in ("tactile/runtime/cli.py", "tactile/training/emd/module.py",
                   "tactile/export/cli.py", "tactile/device/PROTOCOL.md", "tactile/contract.py"):
        assert module in names, module
