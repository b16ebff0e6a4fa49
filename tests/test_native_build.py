"""The package's build of the native kernels: optional (a wheel builds without a C compiler,
just without the library), and the library it builds exports the kernels and needs nothing of
libpython (onnxruntime will load it as a custom-op library)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile

import pytest
from conftest import REPO

from tactile import native


def _wheel(tmp_path, env_extra: dict) -> list[str]:
    """The names in a wheel built from a copy of the checkout (as test_packaging does)."""
    src = tmp_path / "src"
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(
        ".*", "__pycache__", "build", "dist", "*.egg-info", "data", "runs", "tests", "bench",
        "_kernels*"))
    out = tmp_path / "wheel"
    run = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
         "-w", str(out), str(src)],
        capture_output=True, text=True, env={**os.environ, **env_extra}, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    (wheel,) = out.glob("tactile_pen-*.whl")
    with zipfile.ZipFile(wheel) as z:
        return z.namelist()


def test_wheel_builds_without_a_c_compiler(tmp_path):
    names = _wheel(tmp_path, {"CC": "/bin/false"})
    assert "tactile/native/__init__.py" in names and "tactile/native/emd.c" in names
    assert not [n for n in names if "_kernels" in n]


def test_wheel_holds_the_library_where_a_compiler_works(tmp_path):
    if shutil.which(os.environ.get("CC") or "cc") is None:
        pytest.skip("no C compiler here")
    names = _wheel(tmp_path, {})
    assert [n for n in names if n.startswith("tactile/native/_kernels") and n.endswith(".so")]


def test_library_exports_the_kernels_and_no_python():
    path = native.library_path()
    if path is None or shutil.which("nm") is None:
        msg = "no built library or no nm: the symbol table is not checked"
        if os.environ.get("CI", "").lower() == "true" and path is None:
            pytest.fail(msg)
        pytest.skip(msg)
    out = subprocess.run(["nm", "-D", "--defined-only", str(path)], capture_output=True,
                         text=True, check=True).stdout
    defined = {ln.split()[-1] for ln in out.splitlines() if " T " in ln}
    assert {"tactile_emd_f64", "tactile_emd_f32", "tactile_omp_f64", "tactile_omp_f32",
            "tactile_native_abi", "RegisterCustomOps"} <= defined
    undefined = subprocess.run(["nm", "-D", "--undefined-only", str(path)], capture_output=True,
                               text=True, check=True).stdout
    assert "Py" not in undefined, undefined  # no libpython symbol: loadable outside Python
    assert "Ort" not in undefined, undefined  # onnxruntime's C API only through its table
    assert not [s for s in defined if s.startswith("Py")]
