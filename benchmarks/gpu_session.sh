#!/usr/bin/env bash
# The GPU checks of issue 45 (the whole frame on the device) in one prepared run, for a machine lent for a few
# minutes. Every step is bounded by `timeout`; the whole run ends within DEADLINE seconds (default 420):
#   1. the machine (GPU, CPU, versions);
#   2. the CUDA tests: the device imprint, markers and whole frame against the numpy path on this machine
#      (the torch kernels' tests -k cuda), and the torch optics' CUDA tests;
#   3. benchmarks/bench_device.py: imprint and whole-frame frames/s at 320x240 and 960x720 (sequences in step on
#      the GPU; physics and patches prepared on the CPU, their CPU cost per frame reported beside);
#   4. benchmarks/bench_device.py --sensors: batched MuJoCo sensor renders/s at N = 1, 16, 256, 1024, 4096, 320x240;
#   5. two bounded `gelsim generate --backend torch --device cuda` runs of one dataset (GPU_SESSION_FABRICS fabrics x
#      5 sequences, 960x720, GPU_SESSION_WORKERS workers, default all cores) for end-to-end frames/s with their stage
#      times: `--stages optics` (the torch optics, the numpy imprint: the baseline), then `--stages all` (the whole
#      frame on the GPU, a fabric's sequences in step; docs/device.md);
#   6. if at least 45 s are left, one epoch of `stam train --preset paper` on what step 5 made, for its epoch time;
#   7. a summary table, printed last (also $OUT/summary.txt).
# Everything lands in $OUT (at most 8 files): machine.txt, cuda_tests.txt, bench_frame.json, bench_sensor.json,
# generate.txt, stam.txt, summary.txt, session.log (this script's own output, when run through `tee`).
#
# Usage, from the repository root (the lead runs it through the `run` device tool):
#   bash benchmarks/gpu_session.sh 2>&1 | tee "$OUT/session.log"
# Switches (environment): GPU_SESSION_DEVICE (cuda; cpu runs every step on the CPU, for checking the script
# here), GPU_SESSION_SMALL=1 (tiny sizes: the script's own test), DEADLINE (seconds, default 420),
# GPU_SESSION_FABRICS (default 20), GPU_SESSION_WORKERS (generate's, default nproc), PY (default python3).
#
# A bare machine lacks mujoco and av: they travel as Python 3.12 wheels in .whl/ (ignored by git; name ".whl"
# in the run's carry), fetched here with
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
#     --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d .whl mujoco==4.0.0 mujoco-core==4.0.0 av==18.1.0
# (mujoco-studio, glfw and PyOpenGL are not needed: mujoco imports its renderers only if they are there).
set -u
START=$SECONDS
DEADLINE=${DEADLINE:-420}
OUT=${OUT:-out/gpu_session}
DEV=${GPU_SESSION_DEVICE:-cuda}
SMALL=${GPU_SESSION_SMALL:-0}
FABRICS=${GPU_SESSION_FABRICS:-20}
PY=${PY:-python3}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" MPLBACKEND=Agg
left() { echo $((DEADLINE - (SECONDS - START))); }
# bound a step by BUDGET seconds, never past the deadline less RESERVE (what the later steps need)
budget() { local b=$1 reserve=${2:-0} l; l=$(( $(left) - reserve )); [ "$l" -lt "$b" ] && b=$l; [ "$b" -lt 1 ] && b=1; echo "$b"; }
STATUS=()
note() { STATUS+=("$1"); }

# the carried wheels, where this Python lacks what they bring
if compgen -G ".whl/*.whl" >/dev/null && ! $PY -c "import mujoco, av" 2>/dev/null; then
  timeout 60 $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || { echo "wheel install failed"; exit 3; }
  export PYTHONPATH="$PYTHONPATH:/tmp/site"
fi

echo "== machine ($((SECONDS - START)) s)"
{ date -u; nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>&1 | head -2
  lscpu | grep -E "^Model name|^CPU\(s\)"
  $PY -c "import sys, numpy, scipy, cv2, numba, torch, mujoco, av; print('python', sys.version.split()[0], 'numpy', numpy.__version__, 'scipy', scipy.__version__, 'opencv', cv2.__version__, 'numba', numba.__version__, 'torch', torch.__version__, 'cuda', torch.cuda.is_available(), 'mujoco', mujoco.__version__, 'av', av.__version__)"
} >"$OUT/machine.txt" 2>&1
cat "$OUT/machine.txt"
$PY -c "import gelsim, gelsim.gel.twoscale_torch, gelsim.mujoco" || { echo "imports failed"; exit 3; }

if [ "$SMALL" = 1 ]; then
  RESOLUTIONS="160x120"; BATCH=4; DISTINCT=2; FRAMES=5; SENSORS="1,4"; SEQ=2; REPS=1
else
  RESOLUTIONS="320x240,960x720"; BATCH=64; DISTINCT=8; FRAMES=8; SENSORS="1,16,256,1024,4096"; SEQ=5; REPS=2
fi

echo "== tests on $DEV ($((SECONDS - START)) s)"
if [ "$DEV" = cuda ]; then
  SEL="cuda"; FILES="tests/gelsim/test_twoscale_torch.py tests/gelsim/test_markers_torch.py tests/gelsim/test_scene_torch.py tests/gelsim/test_device_frame.py tests/gelsim/test_mujoco_batch.py tests/gelsim/test_torch_backend.py tests/gelsim/test_dataset_device.py"
else
  SEL="cpu and not slow"; FILES="tests/gelsim/test_markers_torch.py tests/gelsim/test_device_frame.py"
fi
T=$(budget 100 320)
timeout -s INT "$T" $PY -m pytest -q -p no:cacheprovider $FILES -k "$SEL" >"$OUT/cuda_tests.txt" 2>&1
rc=$?; tail -3 "$OUT/cuda_tests.txt"; note "tests ($SEL): exit $rc, $(tail -1 "$OUT/cuda_tests.txt" | tr -d '=')"

echo "== bench_device frames ($((SECONDS - START)) s)"
T=$(budget 100 220)
timeout -s INT "$T" $PY benchmarks/bench_device.py --device "$DEV" --resolutions "$RESOLUTIONS" --batch "$BATCH" \
  --distinct "$DISTINCT" --frames "$FRAMES" --reps "$REPS" --out "$OUT/bench_frame.json"
note "bench frames: exit $?"

echo "== bench_device sensors ($((SECONDS - START)) s)"
T=$(budget 50 170)
timeout -s INT "$T" $PY benchmarks/bench_device.py --device "$DEV" --resolutions "" --sensors "$SENSORS" --reps "$REPS" \
  --out "$OUT/bench_sensor.json"
note "bench sensors: exit $?"

# Two runs of the same dataset: --stages optics (the torch optics, the numpy imprint: the baseline) into
# /tmp/gpu_gen (stam's input below), then --stages all (the whole frame on the device) into /tmp/gpu_gen_all.
gen_run() {  # NAME DIR BUDGET RESERVE EXTRA...
  local name=$1 dir=$2 b=$3 r=$4; shift 4
  echo "== generate --backend torch --device $DEV $* ($((SECONDS - START)) s)"
  rm -rf "$dir"
  local T; T=$(budget "$b" "$r")
  local gstart=$SECONDS
  { echo "-- $name"
    timeout -s INT "$T" $PY -m gelsim generate $GEN_RES --sequences-per-fabric "$SEQ" --backend torch --device "$DEV" \
      --workers "$GEN_WORKERS" "$@" --out "$dir" --no-previews 2>&1 | tail -5
    echo "exit ${PIPESTATUS[0]} after $((SECONDS - gstart)) s"
    $PY - "$((SECONDS - gstart))" "$dir" "$name" <<'EOF'
import json, sys
from pathlib import Path
from gelsim.dataset import load_manifest, summarize_timings
wall, root, name = float(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
m = load_manifest(root)
t = summarize_timings(root, m)
t.update(name=name, wall_s=wall, complete=m.get("complete"), frames_per_s=round(t.get("frames", 0) / wall, 1),
         render=m.get("render"))
print("GENERATE", json.dumps(t))
EOF
  } >>"$OUT/generate.txt" 2>&1
  tail -3 "$OUT/generate.txt"
  note "generate $name: $(grep -E '^exit' "$OUT/generate.txt" | tail -1)"
}
GEN_RES=$([ "$SMALL" = 1 ] && echo "--resolution 160x120 --fabrics 2" || echo "--fabrics $FABRICS")
GEN_WORKERS=${GPU_SESSION_WORKERS:-$(nproc)}
: >"$OUT/generate.txt"
gen_run optics /tmp/gpu_gen 60 110 --stages optics
gen_run all /tmp/gpu_gen_all 60 50 --stages all

if [ "$(left)" -ge 45 ] && grep -q '"name": "optics".*"complete": true' "$OUT/generate.txt"; then
  echo "== stam train --preset paper, one epoch ($((SECONDS - START)) s)"
  T=$(budget 200 8)
  { timeout -s INT "$T" $PY -m stam train --preset paper --data /tmp/gpu_gen --out /tmp/stam_paper --model stam --frames 2 \
      --epochs 1 --pretrained none 2>&1 | tail -8
    echo "exit ${PIPESTATUS[0]}"; cat /tmp/stam_paper/log.csv 2>/dev/null; } >"$OUT/stam.txt" 2>&1
  tail -3 "$OUT/stam.txt"
  note "stam: $(grep -E '^exit' "$OUT/stam.txt")"
else
  note "stam: skipped ($(left) s left, or generate incomplete)"
fi

echo "== summary ($((SECONDS - START)) s)"
{ printf '%s\n' "${STATUS[@]}"
  $PY - "$OUT" <<'EOF'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
rows = []
for name in ("bench_frame.json", "bench_sensor.json"):
    p = out / name
    if not p.exists():
        rows.append(f"{name}: missing")
        continue
    d = json.loads(p.read_text())
    m = d["machine"]
    rows.append(f"{name}: {m.get('gpu', m['cpu'])}, {m['cpus']} CPUs, torch {m['torch']}")
    for r in d["rows"]:
        if "error" in r:
            rows.append(f"  {r['what']}: FAILED {r['error']}")
        elif "renders_per_s" in r:
            rows.append(f"  sensors {r['resolution']} N={r['n']:>5}: {r['renders_per_s']:>10} renders/s  ({r['ms_per_call']} ms per call)")
        elif "fps" in r:
            rows.append(f"  {r['what']:<8} {r['resolution']} batch {r['batch']}: {r['fps']:>8} frames/s  {r['ms_per_frame_by_stage']}")
        else:
            rows.append(f"  {r['what']} {r['resolution']}: {r['ms_per_frame']} ms/frame on one core")
g = out / "generate.txt"
if g.exists():
    for line in g.read_text().splitlines():
        if line.startswith("GENERATE "):
            t = json.loads(line[9:])
            st = t.get("stages_ms_per_frame", {})
            rows.append(f"generate --stages {t.get('name')} on {(t.get('render') or {}).get('devices')}: "
                        f"{t.get('frames')} frames in {t.get('wall_s')} s = {t.get('frames_per_s')} frames/s; "
                        "per frame per worker, ms: " + ", ".join(f"{k} {v:.1f}" for k, v in st.items()))
s = out / "stam.txt"
if s.exists():
    rows.append("stam: " + " | ".join(s.read_text().splitlines()[-3:]))
print("\n".join(rows))
EOF
  echo "total $((SECONDS - START)) s of $DEADLINE"
} | tee "$OUT/summary.txt"
