#!/usr/bin/env bash
# The robustness benchmark of issue 43 at full size (docs/nuisance.md, "Robustness benchmark"): the cpu
# preset's 2,000 sequences rendered at the camera's 960x720, nuisance copies at the camera and handheld
# levels and at handheld severities 0.5 and 2, each swept by `stam experiment --preset cpu` (CNN, CNN+SA,
# STAM; n = 2..7; clean and noisy; 3 seeds) on one backbone pretrained on the stage-free data; onset
# agreement per copy; paired comparisons against the stage-free run; accuracy against severity.
# Expected on 2 idle cores (not run): generation 34 min (measured 33.5 min for this plan, README); each
# copy 30-60 min (estimated: 6-7.5 min per 1,000 sequences at 320x240 under a load of 10 here, times the
# 9x pixels less the fixed costs); pretraining about 32 min once; each sweep about 50 min (README's
# 960x720 sweep); the onset pass about 40 min. About 7-9 h in all.
# Usage: benchmarks/nuisance_robustness.sh DATA_DIR OUT_DIR
set -euo pipefail
D=${1:?data dir}; O=${2:?out dir}
PY=${PY:-.venv/bin/python}
.venv/bin/gelsim generate --preset cpu --resolution 960x720 --out "$D/none" --no-previews
for spec in camera:1 handheld:0.5 handheld:1 handheld:2; do
  lvl=${spec%:*}; sev=${spec#*:}
  [ -d "$D/$lvl-$sev" ] || $PY benchmarks/nuisance_dataset.py "$D/none" "$D/$lvl-$sev" --level "$lvl" --severity "$sev"
done
$PY benchmarks/nuisance_effects.py "$D/none" "$D"/camera-1 "$D"/handheld-0.5 "$D"/handheld-1 "$D"/handheld-2 \
    --json "$O/effects.json"
.venv/bin/stam experiment --data "$D/none" --out "$O/none" --preset cpu
for c in camera-1 handheld-0.5 handheld-1 handheld-2; do
  mkdir -p "$O/$c/pretrain" && cp "$O/none/pretrain/backbone.pt" "$O/$c/pretrain/"   # one backbone for all
  .venv/bin/stam experiment --data "$D/$c" --out "$O/$c" --preset cpu
  .venv/bin/stam compare "$O/none" "$O/$c" --out "$O/${c}_vs_none.md"
done
$PY benchmarks/nuisance_plot.py 0="$O/none" 0.5="$O/handheld-0.5" 1="$O/handheld-1" 2="$O/handheld-2" \
    --out "$O/severity.png" --title "handheld level, 960x720, cpu preset"
