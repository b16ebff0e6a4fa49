#!/usr/bin/env bash
# The main job, end to end on the simulated pen: set up, then record takes from a simulated pen
# over its serial URL through a noisy link (garbage bytes, bit flips, dropped frames, a stall),
# and read them back. (When the runtime lands, this becomes tactile-run on the simulated pen.)
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/setup.sh
out=${1:-data/demo}
rm -rf "$out"
for texture in paper desk; do
  .venv/bin/tactile-record --label "$texture" --seconds 20 --out "$out" \
    --port "sim://?texture=$texture&seed=3&speed=max&garbage=0.01&flip=0.0005&drop=0.01&stall=8:0.5"
done
.venv/bin/python - "$out" <<'PY'
import sys
from tactile.device.recording import load_dataset
for take in load_dataset(sys.argv[1]):
    v = take.values()
    print(f"{take.path.name}: label={take.label} samples={len(v)} segments={len(take.segments())} "
          f"gaps={len(take.meta['gaps'])} mean pressure={v[:, 0].mean():.2f} N "
          f"mean |accel|={abs(v[:, 2:5]).mean():.2f} g")
PY
