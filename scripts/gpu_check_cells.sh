#!/usr/bin/env bash
# The cell detection on a GPU, as one time-capped run that keeps going past a failed step, so that a single
# short GPU run names every failure: device report, CUDA kernel compilation, the device-agnostic cell tests on the
# device, the cooling box (frequency / Enskog, cooling / Haff at weights 1, 8, 64; a second run of weight 8 with the
# same seed for determinism), the particle-dominated box (DEM / HELSCM at weights 1, 8, 64, 102,400 real particles)
# the rig bench (DEM / HELSCM at weights 1, 8, 64) and the profiles of a box and a rig step (scripts/profile_step.py);
# at the end DIR.tgz holds all of DIR (the device tool returns at most 8 files: fetch that one).
#
#   scripts/gpu_check_cells.sh [--dry-run] [--out DIR]
#
# Without --dry-run every step runs on Warp's "cuda" device at full size; --dry-run runs the same sequence on the CPU
# at the smallest sizes (what tests/test_gpu_check.py runs). DIR (default gpu_cells_out/) gets one JSON and one .log
# per step, steps.tsv (name, exit code, seconds, command) and summary.json. Exit 0 only if every step passed.
# Environment: MODEL=DIR the rig's contact-form model, COOL_MODEL=DIR the boxes' (frictionless for Haff's law; default
# MODEL; both default to the tests' tiny one, trained into HEL_WARP_TINY_MODELS or DIR/models); STEP_TIMEOUT=S caps
# each step (default 240 s), TOTAL_TIMEOUT=S the whole check (default 540 s on the GPU, 900 s dry: a step gets what
# is left, none starts after it); PYTHON (default: .venv/bin/python where there is one, else python).
#
# On a lent GPU machine without the project's packages (warp-lang, xgboost, zarr), carry them as a prepared
# site-packages folder (scripts/gpu_bundle.sh builds it; docs/gpu.md) and put it on
# PYTHONPATH; PYTHON=python3 there. Carry a kernel cache compiled here (scripts/gpu_kernel_cache.py) and set
# WARP_CACHE_PATH to it, or the kernels step compiles every CUDA module there (~120 s).
set -uo pipefail
. "$(dirname "$0")/gpu_check_common.sh"
gpu_check_args gpu_check_cells gpu_cells_out 20 "$@"
step_timeout=${STEP_TIMEOUT:-240}
kill_grace=10

tests=(tests/test_cell_collisions.py tests/test_cell_list.py tests/test_device_paths.py tests/test_coupling.py
       tests/test_gas.py tests/test_forest.py)
if [ "$dry" = 1 ]; then
  device=cpu
  cool_n=512; box_n=4096; box_dem_steps=1; rig_end=0.002; rig_extra=(--cells 5000 --max-particles 192)
  profile_rig_extra=(--cells 5000 --max-particles 192 --release-steps 1 --warmup 1 --steps 1)
  tests=(tests/test_cell_list.py)
  total_timeout=${TOTAL_TIMEOUT:-900}
else
  device=cuda
  cool_n=32768; box_n=102400; box_dem_steps=2; rig_end=0.02; rig_extra=()
  profile_rig_extra=()
  total_timeout=${TOTAL_TIMEOUT:-540}
fi

started=$(date +%s.%N)
failed=0
# step NAME JSON|- COMMAND...: one step (gpu_check_run), its stdout to NAME.json (JSON given) or NAME.log; a failure
# is recorded and the check goes on.
step() {
  local name=$1 json=$2
  shift 2
  gpu_check_run "$name" "$([ "$json" != - ] && echo "$out/$json")" "$@"
  if [ "$step_rc" != 0 ]; then
    failed=1
    if [ "$step_rc" = 124 ] || [ "$step_rc" = 137 ]; then
      echo "gpu_check_cells: step '$name' ran out of time (STEP_TIMEOUT=$step_timeout s," \
        "TOTAL_TIMEOUT=$total_timeout s in all)" >&2
    fi
    echo "gpu_check_cells: step '$name' failed (exit $step_rc); its output: $out/$name.log" >&2
  fi
  return 0
}

step device - "$py" scripts/gpu_check.py device --device "$device" --out "$out/device.json"
step kernels - env HEL_GPU_CHECK_CPU_KERNELS=0 "$py" scripts/gpu_check.py kernels --device "$device" \
  --out "$out/kernels.json"
models=${HEL_WARP_TINY_MODELS:-$out/models}
[ -f "$models/model_contact/forest.json" ] || step models - "$py" scripts/gpu_check.py models "$models" \
  --out "$out/models.json"
model=${MODEL:-$models/model_contact}
cool_model=${COOL_MODEL:-$model}
# -v: each test's name is in tests.log before it runs (a segmentation fault otherwise leaves no test named)
step tests - env HEL_WARP_DEVICE="$device" HEL_WARP_TINY_MODELS="$models" "$py" -m pytest -v -p no:cacheprovider \
  "${tests[@]}" --basetemp "$out/pytest" --junitxml "$out/tests.xml"
[ -f "$out/tests.xml" ] && step tests_json - "$py" scripts/gpu_check.py junit "$out/tests.xml" --out "$out/tests.json"

# cooling box at eps 0.05 (material: COOL_MODEL's metadata, frictionless for Haff's law; the tiny model is),
# dt 1e-3 s, weights 1 / 8 / 64; weight 8 twice for determinism
cool=(cases/homogeneous_cooling.py --collisions surrogate --model "$cool_model" --detection cell --dt 1e-3
      --solids-fraction 0.05 --particles "$cool_n" --diameter 315e-6 --granular-temperature 1 --end-time 0.02
      --seed 3 --device "$device" --json --overwrite)
for w in 1 8 64; do
  step "cool_w$w" "cool_w$w.json" "$py" "${cool[@]}" --particles-per-parcel "$w" --out "$out/run_cool_w$w"
done
step cool_w8_again cool_w8_again.json "$py" "${cool[@]}" --particles-per-parcel 8 --out "$out/run_cool_w8_again"

# particle-dominated box: eps 0.01, Theta0 = 1; DEM a few steps of 1e-4 s (its cost per Hertz sub-step does not
# depend on the time simulated), HELSCM 10 steps of 1e-3 s
box=(cases/homogeneous_cooling.py --solids-fraction 0.01 --particles "$box_n" --diameter 315e-6
     --granular-temperature 1 --seed 1 --device "$device" --json --overwrite --model "$cool_model")
step box_dem box_dem.json "$py" "${box[@]}" --collisions dem --dt 1e-4 \
  --end-time "$(awk -v n="$box_dem_steps" 'BEGIN { printf "%g", n * 1e-4 }')" --out "$out/run_box_dem"
for w in 1 8 64; do
  step "box_w$w" "box_w$w.json" "$py" "${box[@]}" --collisions surrogate --detection cell --dt 1e-3 --end-time 0.01 \
    --particles-per-parcel "$w" --out "$out/run_box_w$w"
done

# the rig: DEM / HELSCM wall clock at weights 1, 8, 64 (the same real particles)
step rig_bench rig_bench.json "$py" scripts/bench_rig.py --models ktgf dem --model "$model" --weights 1 8 64 \
  --end-time "$rig_end" --device "$device" "${rig_extra[@]}" --json

# where the steps' time goes (scripts/profile_step.py: Warp's activity timing; on the CPU the wall clock only)
step profile_box profile_box.json "$py" scripts/profile_step.py box --device "$device" --model "$cool_model" \
  --particles "$box_n" --weights 1 8 64 --json
step profile_rig profile_rig.json "$py" scripts/profile_step.py rig --device "$device" --model "$model" \
  --models surrogate_w64 --linear-solver native "${profile_rig_extra[@]}" --json
# the native CG's device-side loop (GasConfig.pcg_device_loop, a CUDA while node), apart: it has not run on a GPU
step profile_rig_loop profile_rig_loop.json "$py" scripts/profile_step.py rig --device "$device" --model "$model" \
  --models surrogate_w64 --pcg-loop host device "${profile_rig_extra[@]}" --json

"$py" scripts/gpu_check_cells.py "$out" > "$out/summary.json" 2> "$out/summary.log" || failed=1
# one archive of everything (the device tool returns at most 8 files)
tar -czf "$out.tgz" -C "$(dirname "$out")" "$(basename "$out")" 2>/dev/null || true
wall=$(awk -v a="$started" -v b="$(date +%s.%N)" 'BEGIN { printf "%.1f", b - a }')
if [ "$failed" = 0 ]; then
  echo "gpu_check_cells: every step passed on $device in $wall s; figures in $out/summary.json"
else
  echo "gpu_check_cells: some steps failed on $device ($wall s); see $out/steps.tsv and the steps' .log" >&2
fi
exit "$failed"
