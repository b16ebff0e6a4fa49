#!/usr/bin/env bash
# Set-up on a fresh machine: a virtualenv in .venv with the CPU build of PyTorch and the project
# (editable, with its [train,dev] extras). Re-running it is cheap: it reinstalls only when
# pyproject.toml changed.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.tactile-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  # torch first, pinned: the CPU build. A bare "torch" requirement would pull a multi-GB CUDA
  # build; the project itself only asks for torch>=2.4, which this pin satisfies.
  .venv/bin/python -m pip install -q "torch==2.13.0" 2>&1 | grep -v "is ignored" || true
  .venv/bin/python -m pip install -q -e ".[train,dev]" 2>&1 | grep -v "is ignored" || true
  .venv/bin/python -c "import torch, onnxruntime, serial, PyEMD" # fail here if an install failed
  touch "$stamp"
fi
