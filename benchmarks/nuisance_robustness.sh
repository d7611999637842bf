#!/usr/bin/env bash
# The robustness benchmark of issue 43 (docs/nuisance.md, section 4): one dataset per nuisance level, made
# with the same options and seed (so the same sequences, labels byte-identical), the onset detector's
# agreement on each (benchmarks/nuisance_effects.py), `stam experiment` (CNN and STAM, clean and noisy
# windows, 3 seeds) on each with ONE backbone, pretrained on the level-free data and copied into every
# run (so the runs differ in their data only), `stam compare` of each level against none (paired 95% CIs),
# and accuracy against severity (benchmarks/nuisance_plot.py, when SEVERITIES names more than one).
#
# Usage: benchmarks/nuisance_robustness.sh DATA_DIR OUT_DIR
# Environment (defaults: the small run of docs/nuisance.md, about 1 h 45 min on 2 shared cores):
#   GEN     gelsim generate options     [--preset cpu --sequences-per-fabric 10 --split 5:1:4]  (320x240, 400 test seqs)
#   LEVELS  nuisance levels to compare with none         [camera handheld]
#   SEVERITIES  handheld severities for the plot, besides 1   [] (e.g. "0.5 2")
#   EXP     stam experiment options     [--preset cpu --models cnn stam --frames 2 4 6]
# The issue's full run (960x720, cnn cnn_sa stam, n = 2..7, severities 0.5 1 2):
#   GEN="--preset cpu --resolution 960x720" EXP="--preset cpu" SEVERITIES="0.5 2" LEVELS="camera handheld"
#   estimated 7-9 h on 2 idle cores (generation 34 min per level, README; each sweep about 50 min), not run.
set -euo pipefail
D=${1:?data dir}; O=${2:?out dir}
GEN=${GEN:---preset cpu --sequences-per-fabric 10 --split 5:1:4}
LEVELS=${LEVELS:-camera handheld}
SEVERITIES=${SEVERITIES:-}
EXP=${EXP:---preset cpu --models cnn stam --frames 2 4 6}
PY=${PY:-.venv/bin/python}
gen() {  # gen NAME LEVEL [SEVERITY]
  local extra=""; [ -n "${3:-}" ] && extra="--nuisance-severity $3"
  [ -f "$D/$1/manifest.json" ] && grep -q '"complete": true' "$D/$1/manifest.json" && return
  .venv/bin/gelsim generate $GEN --nuisance "$2" $extra --out "$D/$1" --no-previews
}
gen none none
runs=()
for l in $LEVELS; do gen "$l" "$l"; runs+=("$l"); done
for s in $SEVERITIES; do gen "handheld-$s" handheld "$s"; runs+=("handheld-$s"); done
mkdir -p "$O"
$PY benchmarks/nuisance_effects.py "$D/none" $(for r in "${runs[@]}"; do echo "$D/$r"; done) --json "$O/effects.json"
.venv/bin/stam experiment --data "$D/none" --out "$O/none" $EXP
for r in "${runs[@]}"; do
  mkdir -p "$O/$r/pretrain" && cp "$O/none/pretrain/backbone.pt" "$O/$r/pretrain/"   # one backbone for all
  .venv/bin/stam experiment --data "$D/$r" --out "$O/$r" $EXP
  .venv/bin/stam compare "$O/none" "$O/$r" --out "$O/${r}_vs_none.md"
done
if [ -n "$SEVERITIES" ]; then
  plot=(0="$O/none" 1="$O/handheld")
  for s in $SEVERITIES; do plot+=("$s=$O/handheld-$s"); done
  $PY benchmarks/nuisance_plot.py "${plot[@]}" --out "$O/severity.png" --title "handheld level, accuracy against severity"
fi
