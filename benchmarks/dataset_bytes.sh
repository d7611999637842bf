#!/bin/bash
# The same seed, the same dataset bytes (videos, labels, nuisance records) from two checkouts of gelsim.
#
#   benchmarks/dataset_bytes.sh OLD_TREE NEW_TREE [WORK_DIR] [CASE...]
#
# Generates small datasets with each tree's code (through PYTHONPATH, with this checkout's .venv): the
# quick preset, balanced at 320x240 (12 sequences), fast at 960x720 (6), balanced at 960x720 (2), the torch
# backend on the CPU (4, batch 3), one fast 320x240 dataset at the nuisance levels none, webcam-restart and
# handheld, handheld at balanced (320x240, hairy fabrics: fibres and camera gains), handheld on the torch
# backend, and the whole frame on
# the device (--stages all, CPU); then compares the sha256 of every video and label file and of every
# per-frame nuisance record (nuisance/, where both trees write one). CASE names pick some of them (default:
# all). records/*.json (timings) and manifest.json (source digest, timings) are expected to differ. The torch
# backend's frames may differ where an optics change moves them within its stated tolerance, and --stages
# all's labels within gelsim's stated device tolerances (the tests check both); the numpy path's videos,
# labels and nuisance records may not differ. The cases none320, restart320 and hand320 are one dataset at
# three nuisance levels (webcam-restart: every recording catches the camera's start-up): their labels must be
# the same bytes as each other's (checked in NEW when all three ran).
# An OLD dataset already complete in WORK_DIR is reused (the old tree does not change); the NEW one is made
# afresh.
set -u
OLD=$(cd "$1" && pwd); NEW=$(cd "$2" && pwd); W=${3:-$(mktemp -d)}; shift $(( $# < 3 ? $# : 3 ))
PICK=" $* "
PY=$(cd "$(dirname "$0")/.." && pwd)/.venv/bin/python
gen() {  # tree, out, args...
  local t=$1 o=$2; shift 2
  # (run from the tree itself: `python -m` puts the working directory ahead of PYTHONPATH)
  (cd "$t" && PYTHONPATH=$t "$PY" -m gelsim generate --out "$o" --no-previews --workers 1 "$@" > "$o.log" 2>&1) || { echo "failed: $o (see $o.log)"; exit 1; }
}
complete() { grep -q '"complete": true' "$1/manifest.json" 2>/dev/null; }
status=0
while read -r name tolerated args; do
  [ "$PICK" = "  " ] || [[ "$PICK" == *" $name "* ]] || continue
  complete "$W/old-$name" || { rm -rf "$W/old-$name"; gen "$OLD" "$W/old-$name" $args; }
  rm -rf "$W/new-$name"; gen "$NEW" "$W/new-$name" $args
  for part in videos labels nuisance; do
    if [ "$part" = nuisance ] && { [ ! -d "$W/old-$name/nuisance" ] || [ ! -d "$W/new-$name/nuisance" ]; }; then
      echo "$name nuisance: not in both (OLD predates the per-frame record)"; continue
    fi
    a=$(cd "$W/old-$name" && find $part -type f | sort | xargs sha256sum | sha256sum | cut -c1-16)
    b=$(cd "$W/new-$name" && find $part -type f | sort | xargs sha256sum | sha256sum | cut -c1-16)
    n=$(cd "$W/new-$name" && find $part -type f | wc -l)
    if [ "$a" = "$b" ]; then same=same
    elif [[ ",$tolerated," == *",$part,"* ]]; then same="differ (within the stated tolerance: see the tests)"
    else same=DIFFERENT; status=1; fi
    echo "$name $part ($n files): $same"
  done
done <<'CASES'
quick - --preset quick
bal320 - --fabrics 4 --sequences-per-fabric 3 --resolution 320x240 --fidelity balanced --seed 7
fast960 - --fabrics 3 --sequences-per-fabric 2 --fidelity fast --seed 3
bal960 - --fabrics 2 --sequences-per-fabric 1 --fidelity balanced --seed 5
torch320 videos --fabrics 2 --sequences-per-fabric 2 --resolution 320x240 --fidelity fast --backend torch --batch 3 --seed 11
none320 - --fabrics 3 --sequences-per-fabric 2 --resolution 320x240 --fidelity fast --seed 13
restart320 - --fabrics 3 --sequences-per-fabric 2 --resolution 320x240 --fidelity fast --nuisance webcam-restart --seed 13
hand320 - --fabrics 3 --sequences-per-fabric 2 --resolution 320x240 --fidelity fast --nuisance handheld --seed 13
handbal320 - --fabrics 3 --sequences-per-fabric 1 --resolution 320x240 --fidelity balanced --nuisance handheld --seed 19
torchhand320 videos --fabrics 2 --sequences-per-fabric 2 --resolution 320x240 --fidelity fast --backend torch --batch 3 --nuisance handheld --seed 23
all320 videos,labels --fabrics 2 --sequences-per-fabric 2 --resolution 320x240 --fidelity fast --backend torch --stages all --device cpu --seed 17
CASES
labels() { (cd "$1" && find labels -type f | sort | xargs sha256sum | sha256sum | cut -c1-16); }
if [ -d "$W/new-none320/labels" ] && [ -d "$W/new-restart320/labels" ] && [ -d "$W/new-hand320/labels" ]; then
  a=$(labels "$W/new-none320"); b=$(labels "$W/new-restart320"); c=$(labels "$W/new-hand320")
  if [ "$a" = "$b" ] && [ "$a" = "$c" ]; then echo "labels across levels none, webcam-restart, handheld (NEW): same"
  else echo "labels across levels none, webcam-restart, handheld (NEW): DIFFERENT"; status=1; fi
fi
exit $status
