#!/usr/bin/env bash
# The toolkit on a board's architecture: an arm64 Debian root run under qemu's user-mode
# emulation, with PyPI's aarch64 wheels and the package built from this checkout inside it, as a
# user on a board would install it. It runs every command's --version, tactile-check on the
# shipped model, tactile-run on the simulated pen through a pseudo-terminal, and tactile-run
# --replay of one take with an EMD model and a granular (SF-RNN) model, whose labels it compares
# with this machine's (identical labels, probabilities within 1e-4).
#
# Usage (as root: debootstrap, chroot and bind mounts need it):
#   scripts/aarch64-check.sh            # cold ~10 min; the root is kept and reused
# Environment: TACTILE_AARCH64_CACHE (default ~/.cache/tactile-aarch64) holds the root, the
# models and the takes; DEBIAN_MIRROR (default: the first Debian mirror apt uses here);
# PYTHON (default .venv/bin/python, with the [train] extra: it exports the models).
# Nothing outside the cache folder changes except the Debian packages it installs when missing
# (qemu-user-static, binfmt-support, debootstrap) and the mounts, which it undoes on exit, on
# failure and on Ctrl-C. Exit 0 when every step passed; else the failing step's code.
set -Eeuo pipefail  # -E: the ERR trap below in functions too
cd "$(dirname "$0")/.."
REPO=$PWD
CACHE=${TACTILE_AARCH64_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/tactile-aarch64}
ROOT=$CACHE/root
PYTHON=${PYTHON:-$REPO/.venv/bin/python}
SUITE=bookworm
VENV=/opt/tactile-venv   # inside the root
TOL=1e-4                 # largest probability difference allowed between the two machines

say() { printf 'aarch64-check: %s\n' "$*" >&2; }
die() { say "error: $*"; exit 1; }
declare -a TIMES=()
step_start=$SECONDS
step() {  # step NAME: closes the previous step's timer and starts NAME's
  [ -n "${STEP:-}" ] && TIMES+=("$(printf '%-34s %5d s' "$STEP" $((SECONDS - step_start)))")
  STEP=$1; step_start=$SECONDS; say "$1"
}

[ "$(id -u)" = 0 ] || die "needs root (debootstrap, chroot and bind mounts)"
[ -x "$PYTHON" ] || die "no Python with the [train] extra at $PYTHON (run ./scripts/setup.sh, or set PYTHON)"

# --- undo every mount on any exit ----------------------------------------------------------------
MOUNTED_BINFMT=0
cleanup() {
  local rc=$?
  if [ -n "${SIM_PID:-}" ]; then kill "$SIM_PID" 2>/dev/null || true; wait "$SIM_PID" 2>/dev/null || true; fi
  # deepest first: /proc/cpuinfo before /proc, /dev/pts before /dev
  awk -v r="$CACHE/" 'index($2, r) == 1 {print $2}' /proc/mounts | sort -r | while read -r m; do
    umount "$m" 2>/dev/null || umount -l "$m" || say "could not unmount $m"
  done
  if [ "$MOUNTED_BINFMT" = 1 ]; then umount /proc/sys/fs/binfmt_misc 2>/dev/null || true; fi
  exit "$rc"
}
trap cleanup EXIT
trap 'say "error: a command at line $LINENO failed (exit $?)"' ERR  # set -e ends the script
trap 'say "interrupted"; exit 130' INT
trap 'say "terminated"; exit 143' TERM

# --- 1. the host's tools ---------------------------------------------------------------------------
step "Debian packages (host)"
missing=()
for p in qemu-user-static binfmt-support debootstrap; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  say "installing ${missing[*]}"
  apt-get update -q >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -q "${missing[@]}" >/dev/null
fi
if ! mountpoint -q /proc/sys/fs/binfmt_misc; then
  mount binfmt_misc -t binfmt_misc /proc/sys/fs/binfmt_misc && MOUNTED_BINFMT=1
fi
update-binfmts --enable qemu-aarch64 2>/dev/null || true
[ -e /proc/sys/fs/binfmt_misc/qemu-aarch64 ] || die "qemu-aarch64 is not registered with binfmt_misc"

# --- 2. the arm64 root (kept between runs) ---------------------------------------------------------
step "arm64 root (debootstrap)"
mkdir -p "$CACHE"
if [ ! -f "$ROOT/.tactile-root" ]; then
  # the host's own Debian mirror, from whichever of the two source formats it has (a file that
  # is not there, or holds no mirror, is no error)
  mirror=${DEBIAN_MIRROR:-}
  for f in /etc/apt/sources.list.d/*.sources /etc/apt/sources.list; do
    [ -z "$mirror" ] && [ -f "$f" ] || continue
    mirror=$({ grep -hoE '^(URIs:|deb) +https?://[^ ]+/debian/?' "$f" || true; } \
      | awk 'NR == 1 {print $2}')
  done
  mirror=${mirror:-http://deb.debian.org/debian}
  rm -rf "$ROOT.tmp"
  say "debootstrap $SUITE from $mirror (about 5 minutes)"
  debootstrap --arch=arm64 --variant=minbase \
    --include=python3,python3-venv,python3-pip,python3-dev,gcc,libc6-dev,ca-certificates \
    "$SUITE" "$ROOT.tmp" "$mirror" >"$CACHE/debootstrap.log" 2>&1 \
    || die "debootstrap failed (log: $CACHE/debootstrap.log)"
  rm -rf "$ROOT" && mv "$ROOT.tmp" "$ROOT"
  touch "$ROOT/.tactile-root"
fi

# --- 3. mounts, network settings --------------------------------------------------------------------
step "mounts"
# qemu 7.2 shows the guest the host's x86 /proc/cpuinfo, and onnxruntime's aarch64 build then
# dies in its native module; a Cortex-A72's (Raspberry Pi 4) fields instead
cat >"$CACHE/cpuinfo" <<'EOF'
processor	: 0
BogoMIPS	: 108.00
Features	: fp asimd evtstrm crc32 cpuid
CPU implementer	: 0x41
CPU architecture: 8
CPU variant	: 0x0
CPU part	: 0xd08
CPU revision	: 3

processor	: 1
BogoMIPS	: 108.00
Features	: fp asimd evtstrm crc32 cpuid
CPU implementer	: 0x41
CPU architecture: 8
CPU variant	: 0x0
CPU part	: 0xd08
CPU revision	: 3
EOF
mount --bind /proc "$ROOT/proc"
mount --bind "$CACHE/cpuinfo" "$ROOT/proc/cpuinfo"
mount --bind /sys "$ROOT/sys"
mount --bind /dev "$ROOT/dev"
mount --bind /dev/pts "$ROOT/dev/pts"
cp /etc/resolv.conf "$ROOT/etc/resolv.conf" 2>/dev/null || true
# the same package index and certificates as this machine's pip
cp /etc/ssl/certs/ca-certificates.crt "$ROOT/etc/ssl/certs/ca-certificates.crt"
[ -f /etc/pip.conf ] && cp /etc/pip.conf "$ROOT/etc/pip.conf"
[ -f "$HOME/.config/pip/pip.conf" ] && mkdir -p "$ROOT/root/.config/pip" \
  && cp "$HOME/.config/pip/pip.conf" "$ROOT/root/.config/pip/pip.conf"

# in the root: a clean environment (the host's PIP_* may name folders the root lacks), the proxies
board() {
  local pass=()
  for v in http_proxy https_proxy no_proxy HTTP_PROXY HTTPS_PROXY NO_PROXY PIP_INDEX_URL PIP_CERT; do
    [ -n "${!v:-}" ] && pass+=("$v=${!v}")
  done
  chroot "$ROOT" /usr/bin/env -i PATH="$VENV/bin:/usr/bin:/bin" HOME=/root LANG=C.UTF-8 \
    PYTHONUNBUFFERED=1 "${pass[@]}" "$@"
}
[ "$(board uname -m)" = aarch64 ] || die "the root does not run as aarch64"

# --- 4. the runtime's dependencies from PyPI, and the package built from this checkout -----------
step "pip: numpy onnxruntime pyserial"
[ -x "$ROOT$VENV/bin/python" ] || board /usr/bin/python3 -m venv "$VENV"
deps=$("$PYTHON" -c 'import tomllib; print(" ".join(tomllib.load(open("pyproject.toml", "rb"))["project"]["dependencies"]))')
# shellcheck disable=SC2086  # one word per requirement
board "$VENV/bin/python" -m pip install -q $deps >"$CACHE/pip-deps.log" 2>&1 \
  || { tail -5 "$CACHE/pip-deps.log" >&2; die "pip could not install the runtime's dependencies"; }

step "build and install the package"
rm -rf "$ROOT/opt/tactile-src" && mkdir -p "$ROOT/opt/tactile-src"
git ls-files -z | xargs -0 cp --parents -t "$ROOT/opt/tactile-src"
board "$VENV/bin/python" -m pip install -q --no-deps --force-reinstall \
  /opt/tactile-src >"$CACHE/pip-build.log" 2>&1 \
  || { tail -5 "$CACHE/pip-build.log" >&2; die "the package did not build in the root"; }
board "$VENV/bin/python" -c 'import platform, onnxruntime, numpy, serial, sys
print(f"machine {platform.machine()}, Python {platform.python_version()}, onnxruntime "
      f"{onnxruntime.__version__}, numpy {numpy.__version__}, pyserial {serial.VERSION}")
assert "torch" not in sys.modules' | tee "$CACHE/versions.txt" >&2
# the native kernels, compiled by the root's own gcc while pip built the package
board "$VENV/bin/python" -c 'from tactile import native
assert native.available(), "the native kernel library was not built on the board"
print(f"native kernels: {native.library_path()}")' >&2 || die "no native kernel library on the board"

# --- 5. the kernels' parity tests, on the board ------------------------------------------------
step "native kernel tests (pytest)"
TESTVENV=/opt/tactile-test-venv   # a second venv: the runtime's stays as a board installs it
[ -x "$ROOT$TESTVENV/bin/python" ] || board /usr/bin/python3 -m venv "$TESTVENV"
# shellcheck disable=SC2086
board "$TESTVENV/bin/python" -m pip install -q $deps pytest "EMD-signal==1.10.0" scikit-learn \
  >"$CACHE/pip-test.log" 2>&1 && board "$TESTVENV/bin/python" -m pip install -q --no-deps \
  --force-reinstall /opt/tactile-src >>"$CACHE/pip-test.log" 2>&1 \
  || { tail -5 "$CACHE/pip-test.log" >&2; die "pip could not set up the test venv"; }
# ASan and LeakSanitizer need a real kernel's memory map: qemu's user mode cannot host them, so
# the sanitizer test runs on x86 only; torch is not installed here, so its comparisons skip
chroot "$ROOT" /usr/bin/env -i PATH="$TESTVENV/bin:/usr/bin:/bin" HOME=/root LANG=C.UTF-8 \
  sh -c "cd /opt/tactile-src && python -m pytest -q -p no:cacheprovider tests/test_native.py \
  -k 'not sanitizers'" >"$CACHE/pytest-native.txt" 2>&1 \
  || { tail -15 "$CACHE/pytest-native.txt" >&2; die "the native kernel tests failed on the board"; }
say "  $(tail -1 "$CACHE/pytest-native.txt")"

# --- 6. every command answers --version ---------------------------------------------------------------
step "every command --version"
for cmd in $("$PYTHON" -c 'import tomllib; print(" ".join(tomllib.load(open("pyproject.toml", "rb"))["project"]["scripts"]))'); do
  out=$(board "$VENV/bin/$cmd" --version) || die "$cmd --version failed on the board"
  say "  $out"
done

# --- 7. tactile-check on the shipped model -------------------------------------------------------
step "tactile-check (shipped model)"
mkdir -p "$ROOT/opt/check"
cp models/pen-exp2.onnx "$ROOT/opt/check/"
board "$VENV/bin/tactile-check" /opt/check/pen-exp2.onnx >&2 || die "tactile-check failed on the board"

# --- 8. tactile-run on the simulated pen through a pseudo-terminal --------------------------------
step "tactile-run on a pty (5 s)"
chroot "$ROOT" /usr/bin/env -i PATH="$VENV/bin:/usr/bin:/bin" HOME=/root PYTHONUNBUFFERED=1 \
  "$VENV/bin/tactile-sim" --pty --texture paper --seed 1 >"$CACHE/sim.out" 2>"$CACHE/sim.err" &
SIM_PID=$!
for _ in $(seq 600); do grep -q '^/dev/pts/' "$CACHE/sim.out" 2>/dev/null && break; sleep 0.1; done
pty=$(grep -m1 '^/dev/pts/' "$CACHE/sim.out") || die "tactile-sim --pty printed no device: $(cat "$CACHE/sim.err")"
board "$VENV/bin/tactile-run" --model /opt/check/pen-exp2.onnx --port "$pty" --seconds 5 \
  --format text >"$CACHE/run-pty.txt" 2>"$CACHE/run-pty.err" || die "tactile-run on $pty failed: $(tail -2 "$CACHE/run-pty.err")"
kill "$SIM_PID" 2>/dev/null || true; wait "$SIM_PID" 2>/dev/null || true; SIM_PID=
n=$(grep -c ' s  #' "$CACHE/run-pty.txt" || true)
[ "$n" -ge 1 ] || die "tactile-run on the pty printed no label"
say "  $n labels on $pty, e.g.: $(grep -m1 ' s  #' "$CACHE/run-pty.txt")"

# --- 9. the same take replayed here and there: EMD and SF-RNN models ---------------------------------
step "models to replay (exported here)"
"$PYTHON" scripts/aarch64_models.py "$CACHE/models" >&2 || die "could not make the models to replay"
rm -rf "$ROOT/opt/check/models" && cp -r "$CACHE/models" "$ROOT/opt/check/models"

step "tactile-check: the kernels' path on the board"
board "$VENV/bin/tactile-check" /opt/check/models/sf_rnn.onnx >"$CACHE/check-sf_rnn.txt" 2>&1 \
  || die "tactile-check of the SF-RNN model failed on the board: $(tail -2 "$CACHE/check-sf_rnn.txt")"
for op in EMD SparseCode; do
  grep -q "kernels   $op: native kernel" "$CACHE/check-sf_rnn.txt" \
    || die "tactile-check on the board does not run $op on the native kernel: $(grep kernels "$CACHE/check-sf_rnn.txt")"
done
grep 'kernels ' "$CACHE/check-sf_rnn.txt" | sed 's/^/aarch64-check:   /' >&2

step "replay parity (board vs this machine)"
for m in emd sf_rnn sf_rnn-portable; do
  take=/opt/check/models/take.csv
  file=${m%-portable}.onnx native=()
  [ "$m" != "${m%-portable}" ] && native=(--no-native)  # the same file's portable graphs
  "$(dirname "$PYTHON")/tactile-run" --model "$CACHE/models/$file" --replay "$CACHE/models/take.csv" \
    >"$CACHE/host-$m.jsonl" 2>/dev/null || die "tactile-run --replay ($m) failed on this machine"
  board "$VENV/bin/tactile-run" --model "/opt/check/models/$file" --replay "$take" "${native[@]}" \
    >"$CACHE/board-$m.jsonl" 2>"$CACHE/board-$m.err" || die "tactile-run --replay ($m) failed on the board: $(tail -1 "$CACHE/board-$m.err")"
  "$PYTHON" - "$CACHE/host-$m.jsonl" "$CACHE/board-$m.jsonl" "$m" "$TOL" <<'EOF' || die "the board's labels differ ($m)"
import json, sys
host, board, name, tol = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
def labels(path):
    rows = [json.loads(line) for line in open(path)]
    return [r for r in rows if "label" in r and "probs" in r]
a, b = labels(host), labels(board)
if len(a) != len(b) or not a:
    sys.exit(f"{name}: {len(a)} labels here, {len(b)} on the board")
same = sum(x["label"] == y["label"] for x, y in zip(a, b))
diff = max(abs(p - q) for x, y in zip(a, b) for p, q in zip(x["probs"].values(), y["probs"].values()))
print(f"aarch64-check:   {name}: {len(a)} windows, labels identical {same}/{len(a)}, "
      f"largest probability difference {diff:.2e}", file=sys.stderr)
sys.exit(0 if same == len(a) and diff <= tol else 1)
EOF
done
step "done"
say "step times (emulated: not a board's speed):"
for t in "${TIMES[@]}"; do say "  $t"; done
say "passed"
