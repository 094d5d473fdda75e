#!/usr/bin/env bash
# The rig at one particle size and several steps for the collision models side by side, then one report per step
# (the tables of docs/validation.md's rig check, at full size):
#   MODEL=/path/to/contact_model scripts/rig_models.sh [OUT_DIR] [DT ...]
# defaults: OUT_DIR runs/rig_models, steps 1e-3 1e-4 7.14e-5; DIAMETER (315e-6) and END_TIME (0.02) from the
# environment, RIG_ARGS (extra options of every run, e.g. "--force" for a mixture model at one of its sizes). Each run
# is skipped when its log already says it finished; stops on the first failing run.
set -euo pipefail
cd "$(dirname "$0")/.."
: "${MODEL:?set MODEL to a contact-form model directory (hel-warp train --form contact)}"
out=${1:-runs/rig_models}
shift || true
steps=${*:-1e-3 1e-4 7.14e-5}
d=${DIAMETER:-315e-6}
t=${END_TIME:-0.02}
mkdir -p "$out"
for dt in $steps; do
  for spec in "dem" "surrogate --model $MODEL" "surrogate --model $MODEL --detection overlap" "ktgf" "none"; do
    name=${spec%% *}
    case "$spec" in *overlap*) name=surrogate-overlap;; esac
    run="$out/${name}_${dt}"
    if [ -f "$run.log" ] && grep -q "step wall clock" "$run.log"; then continue; fi
    echo "$(date +%T) $name dt=$dt"
    # shellcheck disable=SC2086
    python cases/colliding_streams.py --diameter "$d" --dt "$dt" --end-time "$t" --collisions $spec --out "$run" \
      --overwrite --no-vtk --no-progress ${RIG_ARGS:-} > "$run.log" 2>&1 || { echo "failed: $name dt=$dt (see $run.log)"; exit 1; }
  done
  hel-warp report "$out"/*_"$dt" --out "$out/report_$dt"
done
