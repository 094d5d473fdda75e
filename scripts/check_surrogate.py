"""A contact-form surrogate against the verified DEM over incidence angle and speed (the model's acceptance figure).

    python scripts/check_surrogate.py --model MODEL_DIR [--json] [--diameter D] [--size-ratio R ...] [--spin]

Sphere-sphere impacts at incidence 0-89.5 deg and |g| 0.1-20 m/s, equal sizes and one unequal
size ratio inside the model's training domain (or ``--size-ratio``), run by the batched DEM of
``hel-warp impact`` (one launch) and predicted by the engine's path (domain clamp + admissibility
guard) and by the bare trees. Prints the error of the post-collision relative velocity in % of
|g| per angle band (max and 99th percentile), and the DEM outcome's own distance to the guard's
admissible set (surrogate/sweep.py). The material and contact law are the model's (metadata.json).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))


def main(argv=None) -> int:
    from hel_warp.errors import HelWarpError

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", required=True, help="contact-form model directory (hel-warp train --out)")
    parser.add_argument("--diameter", type=float, default=None, help="d1, m (default: the training mean)")
    parser.add_argument("--size-ratio", type=float, nargs="+", default=None,
                        help="d2/d1 values (default: 1 and an unequal ratio inside the training domain)")
    parser.add_argument("--diameter2", type=float, default=None,
                        help="d2, m: the cross-size pairs of a mixture (= --size-ratio d2/d1 with --diameter d1), "
                             "e.g. --diameter 315e-6 --diameter2 475e-6")
    parser.add_argument("--device", default="cpu", help="Warp device of the surrogate (default cpu)")
    parser.add_argument("--spin", action="store_true",
                        help="also the spinning impacts (surrogate.sweep.spin_sweep_against_dem: random spins of "
                             "surface speed up to 0.1 / 0.3 / 1 / 2 |g|, the engine's particle_spin path and the "
                             "spins-ignored path against the DEM with the spins)")
    parser.add_argument("--json", action="store_true", help="print the sweep as one JSON object")
    args = parser.parse_args(argv)
    try:
        from hel_warp._warp import init_warp
        from hel_warp.errors import ConfigError
        from hel_warp.collisions.forest import load_forest
        from surrogate.sweep import format_table, sweep_against_dem

        init_warp()
        flat = load_forest(args.model)
        meta_path = os.path.join(args.model, "metadata.json")
        try:
            with open(meta_path) as fh:
                meta = json.load(fh)
        except (OSError, json.JSONDecodeError) as exc:
            raise ConfigError(f"cannot read {meta_path} ({exc}); give a model directory written by hel-warp train")
        material = meta.get("material")
        if not material:
            raise ConfigError(f"{args.model} records no DEM material (trained on a data set without one); "
                              "train on a `hel-warp dataset` set")
        defaults = meta.get("defaults", {})
        if args.diameter2 is not None:
            if args.size_ratio is not None or args.diameter is None or not args.diameter2 > 0:
                raise ConfigError("--diameter2 needs --diameter (d1 > 0) and replaces --size-ratio")
            args.size_ratio = [args.diameter2 / args.diameter]
        sweep = sweep_against_dem(flat, material, contact_model=meta.get("contact_model") or "hertz",
                                  diameter=args.diameter or float(defaults.get("d1", 315e-6)),
                                  density=float(defaults.get("rho1", material.get("density", 1000.0))),
                                  size_ratios=args.size_ratio, device=args.device)
        spin = None
        if args.spin:
            from surrogate.sweep import spin_sweep_against_dem

            spin = spin_sweep_against_dem(flat, material, contact_model=meta.get("contact_model") or "hertz",
                                          diameter=args.diameter or float(defaults.get("d1", 315e-6)),
                                          density=float(defaults.get("rho1", material.get("density", 1000.0))),
                                          size_ratios=sweep["size_ratios"], device=args.device)
    except HelWarpError as exc:
        print(f"check_surrogate: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(sweep if spin is None else {**sweep, "spin": spin}))
    else:
        print(format_table(sweep))
        if spin is not None:
            from surrogate.sweep import format_spin_table

            print(format_spin_table(spin))
    return 0


if __name__ == "__main__":
    sys.exit(main())
