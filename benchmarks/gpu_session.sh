#!/usr/bin/env bash
# The GPU checks of issue #16 in one prepared run, for a machine lent for a few minutes:
#   1. the CUDA tests (torch backend on CUDA equals the CPU; `generate --device cuda` writes the fast
#      backend's labels byte for byte, frames within tolerance, same bytes for any --batch);
#   2. benchmarks/bench_torch.py: optics frames/s at 640x480 and 960x720, CPU and CUDA rows;
#   3. `gelsim generate --fabrics 100 --backend torch --device cuda` on all cores, stopped at the
#      deadline if it has not finished (then the rate so far is what is reported);
#   4. if it finished with time to spare, one epoch of `stam train --preset paper` (STAM, n = 2, backbone
#      from scratch) on it, stopped at STAM_END: the paper preset runs on the GPU, and its epoch time.
# Everything it measures lands in $OUT (default out/gpu_session). Usage, from the repository root:
#   benchmarks/gpu_session.sh [DEADLINE_S [STAM_END_S]]   # defaults 480 and 570: seconds from the start
# On a machine without our dependencies, wheels in .whl/ (mujoco, mujoco-core, av, pyopengl, for its
# Python) are installed into /tmp/site first; see README "Rendering in batches, on a GPU".
set -u
DEADLINE=${1:-480}
STAM_END=${2:-570}
OUT=${OUT:-out/gpu_session}
FABRICS=${GPU_SESSION_FABRICS:-100}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
if compgen -G ".whl/*.whl" >/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || { echo "wheel install failed"; exit 3; }
  export PYTHONPATH="$PYTHONPATH:/tmp/site"
fi
PY=${PY:-python3}
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader; lscpu | grep -E "^Model name|^CPU\(s\)|^Thread"; } \
  >"$OUT/machine.txt" 2>&1
cat "$OUT/machine.txt"
$PY -c "import gelsim, mujoco, av, torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), 'mujoco', mujoco.__version__)" \
  || { echo "imports failed"; exit 3; }

echo "== CUDA tests ($SECONDS s)"
# bounded: a hang here (as on 2026-11-26, before the pool spawned its workers under CUDA) must not
# take the whole lease
timeout -s INT 150 $PY -m pytest -q -p no:cacheprovider tests/gelsim/test_torch_backend.py tests/gelsim/test_dataset.py -k cuda 2>&1 \
  | tee "$OUT/cuda_tests.txt" | tail -5

echo "== bench_torch ($SECONDS s)"
$PY benchmarks/bench_torch.py --out "$OUT/bench_torch.json" 2>&1 | tail -15

left=$((DEADLINE - SECONDS))
echo "== generate --fabrics $FABRICS --device cuda, stopped after ${left} s ($SECONDS s)"
rm -rf /tmp/gpu_full
start=$SECONDS
timeout -s INT "$left" /usr/bin/time -v $PY -m gelsim generate --fabrics "$FABRICS" --backend torch --device cuda \
  --out /tmp/gpu_full --no-previews >"$OUT/generate.log" 2>"$OUT/generate.err"
echo "exit $? after $((SECONDS - start)) s" | tee -a "$OUT/generate.log"
$PY - "$((SECONDS - start))" <<'EOF' | tee "$OUT/generate_summary.json"
import json, sys
from pathlib import Path
from gelsim.dataset import load_manifest, summarize_timings
root, wall = Path("/tmp/gpu_full"), float(sys.argv[1])
m = load_manifest(root)
t = summarize_timings(root, m)
t.update(wall_s=wall, complete=m.get("complete"), planned_frames=sum(s.get("num_frames", 0) for s in m["sequences"]),
         frames_per_s=round(t.get("frames", 0) / wall, 1))
print(json.dumps(t, indent=1))
EOF
grep -E "Elapsed|Maximum resident|User time|System time|Percent of CPU" "$OUT/generate.err"
tail -c 400 "$OUT/generate.err"

if [ "$(python3 -c 'import json;print(json.load(open("/tmp/gpu_full/manifest.json")).get("complete"))' 2>/dev/null)" = True ] \
   && [ $((STAM_END - SECONDS)) -ge 45 ]; then
  echo "== stam train --preset paper, one epoch, stopped after $((STAM_END - SECONDS)) s ($SECONDS s)"
  timeout -s INT $((STAM_END - SECONDS)) $PY -m stam train --preset paper --data /tmp/gpu_full --out /tmp/stam_paper \
    --model stam --frames 2 --epochs 1 --pretrained none >"$OUT/stam_paper.log" 2>&1
  echo "exit $?" >>"$OUT/stam_paper.log"
  cp /tmp/stam_paper/log.csv "$OUT/stam_paper_log.csv" 2>/dev/null
  tail -5 "$OUT/stam_paper.log"
fi
echo "== done ($SECONDS s)"
