"""Throughput of the flattened Warp forest vs XGBoost's own predictor on the same model and rows.

    python scripts/bench_forest.py --model MODEL_DIR [--samples 200000] [--repeats 7] [--device cpu|cuda]
                                   [--xgboost-device cpu|cuda] [--json]

Without ``--model`` a model is trained first on the analytic TEST FIXTURE data
(surrogate.features.synthetic_collisions; a few trials) — pass a real MODEL_DIR to measure
the model you use. Rows: ``--samples`` impacts of the fixture (features of the model's form).
CPU: Warp kernel (one CPU thread; Warp runs CPU kernels serially) vs
``Booster.inplace_predict`` with ``nthread=1``. CUDA: the Warp kernel on the GPU vs XGBoost
with ``device="cuda"`` (input already on the device as a CuPy array when CuPy is installed,
else a NumPy array); ``--xgboost-device`` sets XGBoost's side apart (its CUDA branch runs on any machine: without
a GPU XGBoost falls back to its CPU predictor, and ``xgboost_device_used`` in the result says where it ran). Each figure is the median of ``--repeats`` timed runs after one warm-up, the contenders
called in turn (round-robin) so that a shared machine's load falls on all of them alike;
all targets of the model are evaluated. Warp is timed with the features already on the device
(``kernel``) and including the host->device copy and the result copy back (``end-to-end``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))


def _interleaved_times(fns, repeats: int) -> list[dict]:
    """Wall-clock and process CPU time of each of ``fns``, called round-robin ``repeats`` times after
    one warm-up each (interleaving spreads the load of a shared machine evenly over the contenders).
    Per function: median and minimum of wall and CPU seconds."""
    for fn in fns:
        fn()
    wall = [[] for _ in fns]
    cpu = [[] for _ in fns]
    for _ in range(repeats):
        for j, fn in enumerate(fns):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            wall[j].append(time.perf_counter() - t0)
            cpu[j].append(time.process_time() - c0)
    return [{"wall": statistics.median(w), "cpu": statistics.median(c), "wall_min": min(w), "cpu_min": min(c)}
            for w, c in zip(wall, cpu)]


def xgboost_inputs(boosters, xs: np.ndarray, device: str):
    """Point every booster's predictor at ``device`` ("cpu": one thread, "cuda": XGBoost's CUDA predictor) and
    return ``(rows, sync)``: the standardised rows as XGBoost should receive them (a CuPy array on CUDA when CuPy is
    installed and XGBoost was built with CUDA, else the NumPy array) and the call that waits for the device."""
    import xgboost

    params = {"device": "cuda"} if device == "cuda" else {"nthread": 1, "device": "cpu"}
    for b in boosters:
        b.set_param(params)
    # an XGBoost without a CUDA build (the xgboost-cpu wheel) falls back to its CPU predictor for NumPy rows, but
    # fails on device rows ("not compiled with GPU support"; seen on an H200): give it NumPy, the result names "cpu"
    if device == "cuda" and xgboost.build_info().get("USE_CUDA", False):
        try:
            import cupy

            return cupy.asarray(xs), cupy.cuda.runtime.deviceSynchronize
        except ImportError:
            pass
    return xs, (lambda: None)


def xgboost_device_used(booster) -> str:
    """The device XGBoost's predictor actually used (it falls back to "cpu", with a warning, where no GPU is seen)."""
    return str(json.loads(booster.save_config())["learner"]["generic_param"]["device"])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", help="model directory (default: train a small one on the test fixture)")
    parser.add_argument("--samples", type=int, default=200_000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--rows-per-thread", type=int, default=None,
                        help="rows per Warp thread, explicit layout (default 64 on CPU, 1 on CUDA); the perfect "
                             "layout always uses kernels.forest.BLOCK_ROWS")
    parser.add_argument("--layout", default="auto", choices=("auto", "perfect", "explicit"),
                        help="device layout of the forest (default auto: perfect when depth <= 12)")
    parser.add_argument("--xgboost-device", default=None, choices=("cpu", "cuda"),
                        help="device of XGBoost's predictor (default: --device)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)

    import warp as wp
    import xgboost as xgb

    from hel_warp.collisions.forest import ForestPredictor, load_forest, quiet_warp
    from kernels.forest import eval_forest
    from surrogate.artifact import load_artifact
    from surrogate.features import (CANONICAL_FEATURES, form_rows, scale_predictions, standardize,
                                    synthetic_collisions)

    quiet_warp()
    model_dir = args.model
    if model_dir is None:
        from surrogate.train import TrainConfig, train

        model_dir = os.path.join(tempfile.mkdtemp(prefix="bench_forest_"), "model")
        train(synthetic_collisions(20_000, seed=1), model_dir,
              TrainConfig(form="contact", trials=4, progress=False, report=False), log=lambda *_: None)
    art = load_artifact(model_dir, boosters=True)
    flat = load_forest(model_dir)
    rows = form_rows(art.form, synthetic_collisions(args.samples if art.form == "contact" else args.samples,
                                                    seed=123, central_fraction=0.5 if art.form == "contact" else 1.0,
                                                    polydisperse="d1" in art.features))
    raw = np.ascontiguousarray(rows.features[: args.samples])
    cols = [CANONICAL_FEATURES[art.form].index(f) for f in art.features]
    xs = standardize(raw[:, cols], art.scaler_mean, art.scaler_std)
    n = raw.shape[0]

    predictor = ForestPredictor(flat, device=args.device, rows_per_thread=args.rows_per_thread, layout=args.layout)
    device = predictor.device
    x_dev = wp.array(raw, dtype=wp.float32, device=device)
    out_dev = wp.zeros((n, len(flat.targets)), dtype=wp.float32, device=device)

    def warp_kernel():
        eval_forest(predictor.forest, x_dev, out_dev, rows_per_thread=predictor.rows_per_thread)
        wp.synchronize_device(device)

    def warp_end_to_end():
        predictor.predict_features(raw)

    boosters = [art.boosters[t] for t in art.targets]
    xgb_device = args.xgboost_device or args.device
    x_in, sync = xgboost_inputs(boosters, xs, xgb_device)

    def xgb_predict():
        for b in boosters:
            b.inplace_predict(x_in)
        sync()

    # correctness first: the two must agree
    warp_kernel()
    preds = [b.inplace_predict(x_in) for b in boosters]
    ref = np.column_stack([p.get() if hasattr(p, "get") else np.asarray(p) for p in preds])
    # a model fitted per a target scale (surrogate/features.py TARGET_SCALE): its targets are XGBoost's tree sums
    # times the scale, a float32 product per row (not timed: the same O(N) for both contenders)
    ref = scale_predictions(ref, art.target_scale, raw)
    max_diff = float(np.max(np.abs(out_dev.numpy() - ref)))
    xgb_used = xgboost_device_used(boosters[0])

    kernel, e2e, xg = _interleaved_times((warp_kernel, warp_end_to_end, xgb_predict), args.repeats)
    t_kernel, c_kernel, t_e2e, c_e2e, t_xgb, c_xgb = (kernel["wall"], kernel["cpu"], e2e["wall"], e2e["cpu"],
                                                      xg["wall"], xg["cpu"])
    result = {
        "model": model_dir, "form": art.form, "device": str(device), "samples": n,
        "targets": len(boosters), "trees": flat.n_trees, "nodes": flat.n_nodes, "max_depth": flat.max_depth,
        "rows_per_thread": predictor.rows_per_thread, "repeats": args.repeats,
        "warp_kernel_samples_per_s": n / t_kernel, "warp_end_to_end_samples_per_s": n / t_e2e,
        "xgboost_samples_per_s": n / t_xgb,
        "xgboost": f"inplace_predict, {'device=cuda' if xgb_device == 'cuda' else 'nthread=1'}, xgboost "
                   f"{xgb.__version__}",
        "xgboost_device_requested": xgb_device, "xgboost_device_used": xgb_used,
        "xgboost_input": type(x_in).__module__.split(".")[0],
        "ratio_kernel": t_xgb / t_kernel, "ratio_end_to_end": t_xgb / t_e2e,
        "layout": predictor.layout,
        # CPU seconds of this process: the fair figure on a shared machine (both run on one thread)
        "warp_kernel_samples_per_cpu_s": n / c_kernel, "xgboost_samples_per_cpu_s": n / c_xgb,
        "warp_end_to_end_samples_per_cpu_s": n / c_e2e,
        "ratio_kernel_cpu_time": c_xgb / c_kernel, "ratio_end_to_end_cpu_time": c_xgb / c_e2e,
        # best of the repeats (least disturbed by other processes), process CPU time
        "ratio_kernel_cpu_time_min": xg["cpu_min"] / kernel["cpu_min"],
        "max_abs_diff_vs_xgboost": max_diff,
    }
    if args.json:
        print(json.dumps(result))
    else:
        print(f"model {model_dir}: {art.form} form, {flat.n_trees} trees, {flat.n_nodes} nodes, "
              f"depth <= {flat.max_depth}, {len(boosters)} targets; {n} samples, median of {args.repeats}")
        print(f"Warp forest ({device}, {predictor.layout} layout): "
              f"{result['warp_kernel_samples_per_s']:.3e} samples/s kernel, "
              f"{result['warp_end_to_end_samples_per_s']:.3e} end-to-end")
        print(f"XGBoost {result['xgboost']}: {result['xgboost_samples_per_s']:.3e} samples/s")
        print(f"ratio Warp/XGBoost (wall): {result['ratio_kernel']:.2f}x kernel, {result['ratio_end_to_end']:.2f}x "
              f"end-to-end; (process CPU time): {result['ratio_kernel_cpu_time']:.2f}x kernel, "
              f"{result['ratio_end_to_end_cpu_time']:.2f}x end-to-end "
              f"(best of {args.repeats}: {result['ratio_kernel_cpu_time_min']:.2f}x kernel); max |diff| = {max_diff:.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
