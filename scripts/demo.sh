#!/usr/bin/env bash
# The main job: the runtime on the simulated pen. Sets up .venv, then runs tactile-run with the
# shipped model (models/pen-exp2.onnx: non-contact, paper, non-woven cloth, plastic folder,
# mouse pad) on simulated pens over a noisy link (garbage bytes, bit flips, dropped frames, a
# 3 s stall and an unplug), printing one label per window and an event line for each gap, stall
# and reconnect. Extra arguments go to tactile-run.
set -euo pipefail
# tactile-run stops cleanly on Ctrl-C (exit 0, its summary printed): the script stops with it
trap 'exit 130' INT
trap 'exit 143' TERM
cd "$(dirname "$0")/.."
./scripts/setup.sh
model=models/pen-exp2.onnx
for texture in plastic_folder mouse_pad; do
  echo "== a simulated user strokes: $texture (8 s of the run, the pen at 2x real time) ==" >&2
  .venv/bin/tactile-run --model "$model" --format text --seconds 8 --status-every 2 \
    --stall-timeout 1 "$@" \
    --port "sim://?texture=$texture&seed=8&speed=2&garbage=0.005&flip=0.00005&drop=0.002&stall=3:3&unplug=8:0.5"
done
