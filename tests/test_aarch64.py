"""The toolkit on an emulated aarch64 board (``scripts/aarch64-check.sh``): install, every
command, tactile-check, tactile-run on a pty, and the board's labels on a replayed take equal
to this machine's for an EMD and a granular model (on the kernels built there, and on the
portable graphs); the native kernels built by the board's own compiler and their tests.

Slow (about 10 minutes cold: an arm64 Debian root is built once and kept), so it runs under
``CI=true``, with ``TACTILE_AARCH64=1``, or when asked for with ``-m aarch64``; otherwise it
skips, saying so. Under ``CI=true`` a failing step fails the test, never skips it."""

from __future__ import annotations

import os
import re
import subprocess

import pytest
from conftest import REPO

CI = os.environ.get("CI") == "true"


@pytest.mark.aarch64
def test_the_board_installs_runs_and_labels_as_this_machine(request):
    asked = "aarch64" in (request.config.getoption("-m") or "")
    if not (CI or asked or os.environ.get("TACTILE_AARCH64") == "1"):
        pytest.skip("the emulated aarch64 board takes ~10 minutes: runs under CI=true, with "
                    "TACTILE_AARCH64=1 or -m aarch64")
    if os.geteuid() != 0:
        if CI:
            pytest.fail("the aarch64 check needs root (debootstrap, chroot, mounts)")
        pytest.skip("the aarch64 check needs root (debootstrap, chroot, mounts)")
    proc = subprocess.run(["bash", str(REPO / "scripts" / "aarch64-check.sh")], cwd=REPO,
                          capture_output=True, text=True, timeout=45 * 60)
    print(proc.stderr)  # the step times and the board's figures, shown with -s or on failure
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert re.search(r"machine aarch64, Python 3\.\d+\.\d+, onnxruntime \d", proc.stderr)
    for model in ("emd", "sf_rnn", "sf_rnn-portable"):
        m = re.search(rf"{model}: (\d+) windows, labels identical (\d+)/(\d+), largest "
                      rf"probability difference ([0-9.e+-]+)", proc.stderr)
        assert m, f"no parity line for {model}"
        assert int(m[1]) > 0 and m[2] == m[3] == m[1]
        assert float(m[4]) <= 1e-4
    assert re.search(r"\d+ labels on /dev/pts/\d+", proc.stderr)
    # the kernels built on the board by its own gcc, and the SF-RNN's custom nodes run on them
    assert "native kernels: " in proc.stderr and re.search(r"\d+ passed", proc.stderr)
    for op in ("EMD", "SparseCode"):
        assert f"kernels   {op}: native kernel" in proc.stderr
