"""Coverage-guided fuzzing of the native kernels (EMD and OMP) with libFuzzer, ASan and UBSan.

    python bench/fuzz_native.py [--seconds N] [--corpus DIR] [--jobs J] [--install]

Builds ``tactile/native/fuzz/fuzz_kernels.c`` with the kernels by clang
(``-fsanitize=fuzzer,address,undefined``, every finding fatal), seeds a corpus (one input per
kernel, array type and value mode, and the inputs of ``tactile/native/fuzz/regressions/``, each
of which once found a defect) and runs libFuzzer for N seconds (default 600). The target
checks, beyond the sanitizers, each call's status, the documented outputs (n_valid range, zero
slots past it, non-zero count of the codes) and that a row gives the same bits alone as in its
batch. Prints the executions, the edge coverage (libFuzzer's ``cov``), the features, the corpus
and the speed; exits 1 on a finding (the reproducer is written as ``fuzz_native-crash-*``
beside the corpus folder, or in the current folder).
``--install`` installs clang with apt-get when it is missing (as root).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

NATIVE = Path(__file__).resolve().parents[1] / "tactile" / "native"
SOURCES = (NATIVE / "emd.c", NATIVE / "omp.c", NATIVE / "fuzz" / "fuzz_kernels.c")
FLAGS = ("-std=c99", "-g", "-O1", "-fsanitize=fuzzer,address,undefined",
         "-fno-sanitize-recover=all", "-fno-omit-frame-pointer")
FINAL = re.compile(r"#(\d+)\s+DONE\s+cov: (\d+) ft: (\d+) corp: (\d+)/(\S+).*exec/s: (\d+)")


def find_clang() -> str | None:
    """clang, or the newest clang-NN on the PATH."""
    if shutil.which("clang"):
        return "clang"
    for v in range(30, 10, -1):
        if shutil.which(f"clang-{v}"):
            return f"clang-{v}"
    return None


def install_clang(run=subprocess.run) -> str | None:
    """``apt-get update`` and ``apt-get install clang`` when clang is missing and we are root;
    returns clang's name or None (no root, no apt-get, or the install failed)."""
    if find_clang() or not hasattr(os, "geteuid") or os.geteuid() != 0 \
            or not shutil.which("apt-get"):
        return find_clang()
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for cmd, limit in ((["apt-get", "update", "-q"], 300),
                       (["apt-get", "install", "-y", "-q", "-o", "DPkg::Lock::Timeout=600",
                         "clang"], 900)):
        if run(cmd, env=env, capture_output=True, text=True, timeout=limit).returncode != 0:
            return None
    return find_clang()


def build(clang: str, out: Path) -> Path:
    """The fuzz target, built into ``out``; raises CalledProcessError with clang's message."""
    exe = out / "fuzz_kernels"
    cmd = [clang, *FLAGS, f"-I{NATIVE}", *map(str, SOURCES), "-o", str(exe), "-lm"]
    subprocess.run(cmd, check=True, capture_output=True, text=True, timeout=600)
    return exe


REGRESSIONS = NATIVE / "fuzz" / "regressions"
"""Inputs that once found a defect (named after it): part of every seed corpus."""


def seed_corpus(corpus: Path) -> None:
    """One small input per kernel, array type and value mode (byte 0's three bits), and the
    regression inputs."""
    corpus.mkdir(parents=True, exist_ok=True)
    for sel in range(8):
        body = bytes([sel, 2, 100, 1, 3, 4]) + bytes(range(1, 200, 3))
        (corpus / f"seed-{sel}").write_bytes(body)
    for f in sorted(p for p in REGRESSIONS.iterdir() if p.is_file()):
        shutil.copyfile(f, corpus / f"regression-{f.name}")


def fuzz(exe: Path, corpus: Path, seconds: int, jobs: int = 1,
         artifacts: Path | None = None) -> dict:
    """Run libFuzzer; returns its final figures and ``found``, the reproducers it wrote (named
    ``<artifacts>crash-*``, ``leak-*`` or ``timeout-*``; default beside the corpus)."""
    prefix = str(artifacts) if artifacts else f"{corpus.parent}/"
    args = [str(exe), f"-max_total_time={seconds}", "-print_final_stats=1",
            "-timeout=30", "-rss_limit_mb=2048", f"-artifact_prefix={prefix}"]
    if jobs > 1:
        args += [f"-fork={jobs}"]
    env = {**os.environ, "ASAN_OPTIONS": "detect_leaks=1",
           "UBSAN_OPTIONS": "print_stacktrace=1:halt_on_error=1"}
    t0 = time.perf_counter()
    run = subprocess.run([*args, str(corpus)], capture_output=True, text=True, env=env,
                         timeout=seconds + 300)
    wall = time.perf_counter() - t0
    log = run.stderr
    stats = {"returncode": run.returncode, "seconds": wall, "log": log[-4000:]}
    finals = FINAL.findall(log)
    if finals:
        m = ("",) + finals[-1]
        stats.update(executions=int(m[1]), cov=int(m[2]), ft=int(m[3]), corpus=int(m[4]),
                     exec_per_s=int(m[6]))
    runs = re.search(r"stat::number_of_executed_units:\s*(\d+)", log)
    if runs:
        stats["executions"] = int(runs[1])
    where, stem = Path(prefix + "x").parent, Path(prefix + "x").name[:-1]
    stats["found"] = sorted(str(p) for kind in ("crash", "leak", "timeout", "oom")
                            for p in where.glob(f"{stem}{kind}-*"))
    return stats


def main(argv: list[str] | None = None) -> int:
    from tactile.cli import Parser, int_in

    parser = Parser(prog="fuzz_native.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=int_in(1), default=600, help="fuzzing time (default 600)")
    parser.add_argument("--corpus", type=Path, help="corpus folder (default: a temporary one)")
    parser.add_argument("--jobs", type=int_in(1), default=1, help="libFuzzer -fork processes")
    parser.add_argument("--install", action="store_true", help="apt-get install clang if missing")
    args = parser.parse_args(argv)
    clang = install_clang() if args.install else find_clang()
    if clang is None:
        print("no clang: install it (apt-get install clang) or pass --install as root",
              file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        corpus = args.corpus or work / "work" / "corpus"
        seed_corpus(corpus)
        exe = build(clang, work)
        # reproducers outlive the temporary folder: beside a given corpus, else here
        artifacts = (args.corpus.resolve().parent if args.corpus else Path.cwd()) / "fuzz_native-"
        stats = fuzz(exe, corpus, args.seconds, args.jobs, artifacts)
    print(f"clang: {clang}; {args.seconds} s requested, {stats['seconds']:.0f} s run")
    for key in ("executions", "cov", "ft", "corpus", "exec_per_s"):
        print(f"{key:>11}: {stats.get(key, '?')}")
    if stats["found"] or stats["returncode"] != 0:
        print("FINDING:", *stats["found"], stats["log"][-2000:], sep="\n")
        return 1
    print("findings: none")
    return 0


if __name__ == "__main__":
    sys.exit(main())
