#!/usr/bin/env bash
# The weighted rig in one command: seed ensembles of the cell detection at several weights beside weight 1
# (the swept detection, the default there, and the cell detection), pooled by scripts/rig_ensemble.py against the
# CFD-DEM seeds and, per weight, against the weight-1 cell ensemble (the same collision scheme with every particle its
# own parcel: what the weights must reproduce).
#
#   MODEL=/path/to/contact_model scripts/rig_weights.sh [OUT_DIR]
#
# Environment (defaults): WEIGHTS ("8 64"), SEEDS ("32 63": first and last seed of every cell ensemble), SWEPT_SEEDS
# ("32 37"), DEM_SEEDS ("0 1 2 3"), JOBS (2 runs at a time), DIAMETER (315e-6), DT (1e-3), END_TIME (0.02), RIG_ARGS
# (extra options of the weighted runs, e.g. "--cell-approaching"). Resumable: a run whose log says it finished is
# skipped. Cost on the 2-core machine: a CFD-DEM seed ~130 s, a weight-1 swept or cell run ~5 s of steps, a weighted
# run ~1-2 s (plus ~1 s of start-up each).
set -euo pipefail
cd "$(dirname "$0")/.."
: "${MODEL:?set MODEL to a contact-form model directory (hel-warp train --form contact)}"
out=${1:-runs/rig_weights}
weights=${WEIGHTS:-8 64}
read -r s0 s1 <<< "${SEEDS:-32 63}"
read -r w0 w1 <<< "${SWEPT_SEEDS:-32 37}"
dem_seeds=${DEM_SEEDS:-0 1 2 3}
jobs=${JOBS:-2}
d=${DIAMETER:-315e-6}
dt=${DT:-1e-3}
t=${END_TIME:-0.02}
mkdir -p "$out"
common="--diameter $d --dt $dt --end-time $t --no-vtk --no-gas-snapshots --no-progress --overwrite"

# one line per run: "<run dir>|<options>"; runs already finished are left out
jobs_list() {
  local name=$1 first=$2 last=$3 opts=$4 s
  for s in $(seq "$first" "$last"); do
    local run="$out/${name}_s$s"
    if [ -f "$run.log" ] && grep -q "step wall clock" "$run.log"; then continue; fi
    echo "$run|$opts --seed $s"
  done
}
# the run directories of one ensemble
dirs() { local s; for s in $(seq "$2" "$3"); do echo "$out/$1_s$s"; done; }
run_all() {
  # shellcheck disable=SC2016
  xargs -P "$jobs" -I{} bash -c 'run=${1%%|*}; opts=${1#*|}; python cases/colliding_streams.py $opts --out "$run" \
    > "$run.log" 2>&1 || { echo "failed: $run (see $run.log)"; exit 255; }' _ {}
}

echo "$(date +%T) CFD-DEM seeds: $dem_seeds"
for s in $dem_seeds; do jobs_list dem "$s" "$s" "$common --collisions dem"; done | run_all
model="$common --collisions surrogate --model $MODEL --real-particles 12000"
echo "$(date +%T) weight 1, swept, seeds $w0-$w1"
jobs_list swept_w1 "$w0" "$w1" "$model --particles-per-parcel 1" | run_all
echo "$(date +%T) weight 1, cell, seeds $s0-$s1"
jobs_list cell_w1 "$s0" "$s1" "$model --particles-per-parcel 1 --detection cell" | run_all
for w in $weights; do
  echo "$(date +%T) weight $w, cell, seeds $s0-$s1 ${RIG_ARGS:-}"
  jobs_list "cell_w$w" "$s0" "$s1" "$model --particles-per-parcel $w --detection cell ${RIG_ARGS:-}" | run_all
done

ref=$(for s in $dem_seeds; do dirs dem "$s" "$s"; done)
cell1=$(dirs cell_w1 "$s0" "$s1")
sections="1 2 3 4 5 6 7"
echo "== against the CFD-DEM (seeds $dem_seeds); whole run, then sections $sections (every ensemble fills them)"
# shellcheck disable=SC2086
python scripts/rig_ensemble.py --label "swept w1" --reference $ref --sections $sections --jackknife \
  --runs $(dirs swept_w1 "$w0" "$w1")
for w in 1 $weights; do
  # shellcheck disable=SC2046,SC2086
  python scripts/rig_ensemble.py --label "cell w$w" --reference $ref --sections $sections --jackknife \
    --runs $(dirs "cell_w$w" "$s0" "$s1")
done
echo "== against the weight-1 cell ensemble (the same collision scheme, one particle per parcel)"
for w in $weights; do
  # shellcheck disable=SC2046,SC2086
  python scripts/rig_ensemble.py --label "cell w$w" --reference $cell1 --sections $sections --jackknife \
    --runs $(dirs "cell_w$w" "$s0" "$s1")
done
