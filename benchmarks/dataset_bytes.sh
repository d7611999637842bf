#!/bin/bash
# The same seed, the same dataset bytes (videos and labels) from two checkouts of gelsim.
#
#   benchmarks/dataset_bytes.sh OLD_TREE NEW_TREE [WORK_DIR]
#
# Generates five small datasets with each tree's code (through PYTHONPATH, with this checkout's .venv):
# the quick preset (fast, 30 sequences), balanced at 320x240 (12), fast at 960x720 (6), balanced at
# 960x720 (2) and the torch backend on the CPU (4, batch 3); then compares the sha256 of every video and
# label file. records/*.json (timings) and manifest.json (source digest, timings) are expected to differ.
# The torch backend's frames may differ where an optics change moves them within its stated tolerance;
# its labels may not.
set -u
OLD=$(cd "$1" && pwd); NEW=$(cd "$2" && pwd); W=${3:-$(mktemp -d)}
PY=$(cd "$(dirname "$0")/.." && pwd)/.venv/bin/python
gen() {  # tree, out, args...
  local t=$1 o=$2; shift 2
  # (run from the tree itself: `python -m` puts the working directory ahead of PYTHONPATH)
  (cd "$t" && PYTHONPATH=$t "$PY" -m gelsim generate --out "$o" --no-previews --workers 1 "$@" > "$o.log" 2>&1) || { echo "failed: $o (see $o.log)"; exit 1; }
}
status=0
while read -r name args; do
  gen "$OLD" "$W/old-$name" $args; gen "$NEW" "$W/new-$name" $args
  for part in videos labels; do
    a=$(cd "$W/old-$name" && find $part -type f | sort | xargs sha256sum | sha256sum | cut -c1-16)
    b=$(cd "$W/new-$name" && find $part -type f | sort | xargs sha256sum | sha256sum | cut -c1-16)
    n=$(cd "$W/new-$name" && find $part -type f | wc -l)
    same=$([ "$a" = "$b" ] && echo same || echo DIFFERENT)
    echo "$name $part ($n files): $same"
    [ "$same" = same ] || [ "$name $part" = "torch320 videos" ] || status=1
  done
done <<'CASES'
quick --preset quick
bal320 --fabrics 4 --sequences-per-fabric 3 --resolution 320x240 --fidelity balanced --seed 7
fast960 --fabrics 3 --sequences-per-fabric 2 --fidelity fast --seed 3
bal960 --fabrics 2 --sequences-per-fabric 1 --fidelity balanced --seed 5
torch320 --fabrics 2 --sequences-per-fabric 2 --resolution 320x240 --fidelity fast --backend torch --batch 3 --seed 11
CASES
exit $status
