#!/usr/bin/env bash
# Set-up on a fresh machine: a virtualenv in .venv with the CPU build of PyTorch and the project
# (editable, with its [train,dev] extras). Re-running it is cheap: it reinstalls only when
# pyproject.toml changed.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then
  # Python 3.11 (the version the pinned PyTorch build is for); PYTHON=/path/to/python overrides.
  PY=${PYTHON:-$(command -v python3.11 || command -v python3 || echo python3)}
  if ! "$PY" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
    echo "setup: needs Python 3.11, found: $("$PY" -V 2>&1 || echo "no $PY");" \
      "set PYTHON=/path/to/python3.11" >&2
    exit 1
  fi
  "$PY" -m venv .venv
fi
stamp=.venv/.tactile-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  # torch first, pinned: the CPU build, 2.13.0+cpu, where pip finds it (a local wheel or a
  # configured index), else from PyTorch's CPU index. A bare "torch" requirement from PyPI would
  # pull a multi-GB CUDA build; the project itself only asks for torch>=2.4.
  # (pip's own failure stops the script: only the filter's "nothing left to print" is excused)
  if ! .venv/bin/python -m pip install -q "torch==2.13.0+cpu" 2>/dev/null; then
    .venv/bin/python -m pip install -q "torch==2.13.0" \
      --index-url https://download.pytorch.org/whl/cpu 2>&1 | { grep -v "is ignored" || true; }
  fi
  .venv/bin/python -m pip install -q -e ".[train,dev]" 2>&1 | { grep -v "is ignored" || true; }
  .venv/bin/python -c "import torch, onnxruntime, serial, PyEMD" # and so does a broken install
  touch "$stamp"
fi
