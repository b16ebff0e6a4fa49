"""The kernels on another architecture: ``fuzz/edge_main.c`` with the kernels (and the
onnxruntime custom-op file, compiled along to show it builds there), cross-compiled statically
for aarch64 (the boards') with ``aarch64-linux-gnu-gcc`` and run under ``qemu-aarch64-static``:
every edge case passes there as on this machine.

The tools are Debian's ``gcc-aarch64-linux-gnu`` and ``qemu-user-static``: installed with
apt-get when missing and running as root; otherwise the test skips saying why (and fails
under ``CI=true``).
"""

from __future__ import annotations

import os
import platform
import shutil
import subprocess

import pytest
from test_native import NATIVE, SAN_MAIN, WARNINGS

CC = "aarch64-linux-gnu-gcc"
QEMU = "qemu-aarch64-static"
PACKAGES = ("gcc-aarch64-linux-gnu", "libc6-dev-arm64-cross", "qemu-user-static")


def _tools() -> str | None:
    """None when both tools are there (installing them if root), else why not."""
    if shutil.which(CC) and shutil.which(QEMU):
        return None
    if hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("apt-get"):
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        subprocess.run(["apt-get", "install", "-y", "-q", *PACKAGES], capture_output=True,
                       env=env, timeout=1200)
        if shutil.which(CC) and shutil.which(QEMU):
            return None
        return f"apt-get could not install {' '.join(PACKAGES)}"
    return f"no {CC} or {QEMU} (apt-get install {' '.join(PACKAGES)} as root)"


@pytest.mark.skipif(platform.system() != "Linux", reason="qemu user mode needs Linux")
def test_edge_cases_pass_on_aarch64_under_qemu(tmp_path):
    why = _tools()
    if why:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(why)
        pytest.skip(why)
    exe = tmp_path / "edge_aarch64"
    sources = [NATIVE / "emd.c", NATIVE / "omp.c", SAN_MAIN]
    build = subprocess.run(
        [CC, *WARNINGS, "-O2", "-ffp-contract=off", "-static", f"-I{NATIVE}",
         *map(str, sources), "-o", str(exe), "-lm"], capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stderr[-2000:]
    ops = subprocess.run([CC, *WARNINGS, "-O2", "-fPIC", "-c", f"-I{NATIVE}",
                          str(NATIVE / "ort_ops.c"), "-o", str(tmp_path / "ort_ops.o")],
                         capture_output=True, text=True, timeout=300)
    assert ops.returncode == 0, ops.stderr[-2000:]
    kind = subprocess.run(["file", str(exe)], capture_output=True, text=True).stdout \
        if shutil.which("file") else "aarch64"
    assert "aarch64" in kind or "ARM" in kind, kind
    run = subprocess.run([QEMU, str(exe)], capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, (run.stdout + run.stderr)[-3000:]
    assert run.stdout.strip().splitlines()[-1].startswith("edge cases passed:"), run.stdout[-500:]


def test_custom_op_file_builds_warning_free(tmp_path):
    """``ort_ops.c`` and its API declarations compile under the sanitizer build's warnings."""
    cc = shutil.which(os.environ.get("CC", "gcc") or "gcc")
    if cc is None:
        pytest.skip("no C compiler")
    out = subprocess.run([cc, *WARNINGS, "-fsyntax-only", f"-I{NATIVE}",
                          str(NATIVE / "ort_ops.c")], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
