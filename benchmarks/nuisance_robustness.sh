#!/usr/bin/env bash
# The robustness benchmark, now benchmarks/nuisance_study.py (issue 48, docs/stam_study.md). Until issue 48 this
# script pretrained ONE backbone on the level-free data and copied it into every level, so that no model ever
# adapted its features to a nuisance; the study pretrains each level's own, runs the positive control first,
# both training protocols and the position-aware models. This wrapper keeps the old command and variables:
#
# Usage: benchmarks/nuisance_robustness.sh DATA_DIR OUT_DIR
#   GEN         gelsim generate options shared by every dataset  [the study's small default set]
#   LEVELS      levels compared with none                       [handheld]
#   SEVERITIES  severities of the last level for the plot       [] (e.g. "0.5 2")
#   STUDY       further benchmarks/nuisance_study.py options    [] (e.g. "--frames 2 4 6 --seeds 2")
# (EXP, the `stam experiment` options of the old script, is gone: the study's --models, --frames, --seeds.)
set -euo pipefail
D=${1:?data dir}; O=${2:?out dir}
args=(--data "$D" --out "$O" --levels none ${LEVELS:-handheld})
[ -n "${GEN:-}" ] && args+=(--gen "$GEN")
[ -n "${SEVERITIES:-}" ] && args+=(--severities $SEVERITIES)
exec ${PY:-.venv/bin/python} benchmarks/nuisance_study.py "${args[@]}" ${STUDY:-}
