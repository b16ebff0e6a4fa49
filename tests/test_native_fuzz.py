"""A short coverage-guided fuzz run of the native kernels (``bench/fuzz_native.py``, libFuzzer
with ASan and UBSan): about 20 s from the seed corpus, which replays first the inputs that once
found a defect (``tactile/native/fuzz/regressions/``), no finding. clang is installed when
missing (apt-get, as root); without it the test skips saying so, and fails under ``CI=true``."""

from __future__ import annotations

import importlib.util
import os
import subprocess

import pytest
from conftest import REPO

SECONDS = 20


def _bench():
    spec = importlib.util.spec_from_file_location("fuzz_native", REPO / "bench" / "fuzz_native.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_short_fuzz_run_finds_nothing(tmp_path):
    bench = _bench()
    clang = bench.install_clang()
    if clang is None:
        msg = "no clang (and it could not be installed: not root, no apt-get or no registry)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    try:
        exe = bench.build(clang, tmp_path)
    except subprocess.CalledProcessError as err:  # e.g. a clang without libFuzzer's runtime
        msg = f"{clang} cannot build a libFuzzer target here: {err.stderr[-300:]}"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    corpus = tmp_path / "corpus"
    bench.seed_corpus(corpus)
    assert (corpus / "regression-omp-all-nan-residuals-16-atoms").is_file()  # replayed first
    stats = bench.fuzz(exe, corpus, SECONDS)
    assert stats["returncode"] == 0 and not stats["found"], stats["log"]
    assert stats.get("executions", 0) > 100 and stats.get("cov", 0) > 100, stats["log"]
