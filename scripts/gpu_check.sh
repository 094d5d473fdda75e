#!/usr/bin/env bash
# A GPU run as a confirmation: device report, kernel compilation, the device-agnostic tests on the
# device, the DEM / forest / HEL benches and a short rig run for ktgf, surrogate (swept detection, kick first, wall
# events), dem and surrogate at 8 particles per parcel (cell detection), every figure as JSON.
#
#   scripts/gpu_check.sh [--dry-run] [--out DIR]
#
# Without --dry-run everything runs on Warp's "cuda" device at bench sizes (DEM at 1e5 and 1e6 spheres, the forest
# beside XGBoost's CUDA predictor, the gas and parcel benches, the full rig); --dry-run runs the same sequence on the
# CPU at the smallest sizes (what the tests and CI run). DIR (default gpu_out/) gets one JSON file per step,
# steps.tsv, a .log per step and summary.json. Stops at the first failing step and names its command; exit 0 only if
# every step passed. Environment: MODEL=DIR runs the rig's surrogate with that contact-form model instead of the
# tests' tiny one; HEL_WARP_TINY_MODELS=DIR keeps the tests' tiny models there (trained once); STEP_TIMEOUT=S caps
# each step (default 300 s), TOTAL_TIMEOUT=S the whole check (default 450 s on the GPU, 900 s dry: no step starts
# after it and none runs past it, so the check ends within TOTAL_TIMEOUT + 10 s of kill grace + the summary); PYTHON
# (default: .venv/bin/python where there is one, else python).
set -uo pipefail
. "$(dirname "$0")/gpu_check_common.sh"
gpu_check_args gpu_check gpu_out 16 "$@"
step_timeout=${STEP_TIMEOUT:-300}
kill_grace=10  # a step still running this long after its SIGTERM gets SIGKILL (timeout -k)

# The device-agnostic tests the device run repeats (tests/conftest.py: HEL_WARP_DEVICE sets Warp's default device).
tests=(tests/test_device_paths.py tests/test_gas.py tests/test_multigrid.py tests/test_forest.py tests/test_contacts.py
       tests/test_swept.py tests/test_cell_list.py tests/test_swept_walls.py tests/test_swept_push.py
       tests/test_wall_contact.py tests/test_coupling.py)
if [ "$dry" = 1 ]; then
  device=cpu
  dem_args=(--cases --sizes 2000 --repeats 1 --budget 0.2)
  forest_args=(--samples 5000 --repeats 1)
  hel_args=(--cells 8 12 --parcels 1000 4000 --fixed-side 0 --repeats 1 --no-rig)  # the rig grid: minutes on a CPU
  rig_args=(--cells 5000 --max-particles 200 --end-time 0.002 --gas-warmup 0.001)
  tests=(tests/test_device_paths.py tests/test_multigrid.py)  # the rest of the subset runs on the CPU in the suite
  scale_args=(--dry-run --models ktgf)
  total_timeout=${TOTAL_TIMEOUT:-900}
else
  device=cuda
  dem_args=(--cases --sizes 100000 1000000 --repeats 3 --budget 2 --warp-example)
  forest_args=(--samples 1000000 --repeats 5)
  hel_args=(--repeats 3)
  rig_args=(--end-time 0.003 --gas-warmup 0.005)
  scale_args=(--max-tiles 7 --budget 40 --steps 8)  # the riser up to 3.7e6 particles while a run takes < 40 s
  total_timeout=${TOTAL_TIMEOUT:-450}  # a lent GPU has ~15 min in all, the machine's start included: < 8 min
fi

# the tests' tiny model is frictionless, the rig's material has mu = 0.3: the check runs the surrogate's paths with it
# (--force); a MODEL of the user's must fit the rig's particles
force=()
[ -z "${MODEL:-}" ] && force=(--force)

started=$(date +%s.%N)
finish() {
  "$py" scripts/gpu_check.py summary "$out" > /dev/null 2>&1
  local rc=$?
  local wall
  wall=$(awk -v a="$started" -v b="$(date +%s.%N)" 'BEGIN { printf "%.1f", b - a }')
  if [ "$rc" = 0 ]; then
    echo "gpu_check: every step passed on $device in $wall s; figures in $out (summary.json)"
  fi
  exit "$1"
}

# run NAME COMMAND...: one step, its output to NAME.log (and the terminal); stop at the first failure.
# run_json NAME COMMAND...: the same, the command's stdout (one JSON object) to NAME.json, its stderr to NAME.log.
run() { _step "$1" "" "${@:2}"; }
run_json() { _step "$1" "$out/$1.json" "${@:2}"; }
_step() {
  local name=$1 rc
  gpu_check_run "$@"
  rc=$step_rc
  if [ "$rc" != 0 ]; then
    if [ "$rc" = 124 ] || [ "$rc" = 137 ]; then
      echo "gpu_check: step '$name' ran out of time (STEP_TIMEOUT=$step_timeout s per step," \
        "TOTAL_TIMEOUT=$total_timeout s in all)" >&2
    fi
    shift 2
    echo "gpu_check: FAILED at step '$name' (exit $rc): $*" >&2
    echo "gpu_check: its output is in $out/$name.log" >&2
    finish 1
  fi
}

run device "$py" scripts/gpu_check.py device --device "$device" --out "$out/device.json"
run kernels "$py" scripts/gpu_check.py kernels --device "$device" --out "$out/kernels.json"
models=${HEL_WARP_TINY_MODELS:-$out/models}  # kept when already trained there (the test suite passes its own)
run models "$py" scripts/gpu_check.py models "$models" --out "$out/models.json"
model=${MODEL:-$models/model_contact}
# every test of the subset runs (no -x: one GPU run should name all failures), then a failure stops the check
run tests env HEL_WARP_DEVICE="$device" HEL_WARP_TINY_MODELS="$models" "$py" -m pytest -q -p no:cacheprovider \
  "${tests[@]}" --basetemp "$out/pytest" --junitxml "$out/tests.xml"
run tests_json "$py" scripts/gpu_check.py junit "$out/tests.xml" --out "$out/tests.json"

run bench_dem "$py" scripts/bench_dem.py --device "$device" "${dem_args[@]}" --json "$out/bench_dem.json"
run_json bench_forest "$py" scripts/bench_forest.py --model "$model" --device "$device" --xgboost-device "$device" \
  "${forest_args[@]}" --json
run_json bench_hel "$py" scripts/bench_hel.py --device "$device" "${hel_args[@]}" --json

for collisions in ktgf surrogate dem; do
  extra=()
  [ "$collisions" = surrogate ] && extra=(--model "$model" "${force[@]}")
  run "rig_$collisions" "$py" cases/colliding_streams.py --diameter 315e-6 --dt 1e-3 --collisions "$collisions" \
    "${extra[@]}" --device "$device" "${rig_args[@]}" --no-vtk --no-gas-snapshots --no-progress --overwrite \
    --out "$out/rig_$collisions"
  run "rig_${collisions}_json" "$py" scripts/gpu_check.py rig "$out/rig_$collisions" --out "$out/rig_$collisions.json"
done
# the cell detection: parcels of 8 particles collide per cell, its rounds with the batched forest
run rig_surrogate_cell "$py" cases/colliding_streams.py --diameter 315e-6 --dt 1e-3 --collisions surrogate \
  --particles-per-parcel 8 --model "$model" "${force[@]}" --device "$device" "${rig_args[@]}" --no-vtk \
  --no-gas-snapshots --no-progress --overwrite --out "$out/rig_surrogate_cell"
run rig_surrogate_cell_json "$py" scripts/gpu_check.py rig "$out/rig_surrogate_cell" \
  --out "$out/rig_surrogate_cell.json"
# the periodic riser's size ladder (docs/scale.md): every model at K = 0, 1, ... tiles, last (the longest step)
run bench_scale "$py" scripts/bench_scale.py --device "$device" --model "$model" "${force[@]}" "${scale_args[@]}" \
  --out "$out"
finish 0
