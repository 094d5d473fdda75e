"""``hel-warp predict``: post-collision velocities from a trained model, evaluated by the Warp forest kernel.

Reads one JSON object per line on stdin:
``{"v1": [vx, vy, vz], "v2": [...], "d1": m, "d2": m, "rho1": kg/m^3, "rho2": kg/m^3,
"normal": [nx, ny, nz]}`` — velocities in m/s; ``normal`` (unit contact normal from particle 1
to particle 2) is required by the contact-form model and ignored by the paper form;
``d1``/``d2``/``rho1``/``rho2`` default to the model's training means.
Prints one JSON object per input line: ``{"velocity1_after": [...], "velocity2_after": [...]}``.
Contact form: as in the engine, the features are clamped into the model's training domain and the
predicted impulse made physically admissible (separating along the normal, Coulomb bound, no
kinetic-energy gain; kernels/forest.py ``admissible_impulse``); the counts of this call go to stderr
as one line (``--no-guard``: the bare trees). The pairs must approach: ``(v1 - v2).normal > 0``.
Needs no XGBoost: it reads MODEL_DIR/forest.json.
"""

from __future__ import annotations

from hel_warp.cli.commands._common import add_json_flag


def add_parser(subparsers):
    p = subparsers.add_parser("predict", help="predict post-collision velocities (JSON lines on stdin)",
                              description=__doc__)
    p.add_argument("--model", required=True, help="model directory written by `hel-warp train`")
    p.add_argument("--device", default="cpu", help="Warp device (default cpu)")
    p.add_argument("--no-guard", action="store_true",
                   help="contact form: the bare trees, no domain clamp or admissibility guard")
    add_json_flag(p)
    return p


def _parse_lines(lines, form: str, defaults: dict):
    import json
    import math

    from hel_warp.errors import ConfigError

    rows = []
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            obj = json.loads(line)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"stdin line {number} is not JSON ({exc})") from None
        if not isinstance(obj, dict):
            raise ConfigError(f"stdin line {number}: expected a JSON object")
        unknown = set(obj) - {"v1", "v2", "d1", "d2", "rho1", "rho2", "normal"}
        if unknown:
            raise ConfigError(f"stdin line {number}: unknown key(s) {sorted(unknown)}")
        row = {}
        for key in ("v1", "v2") + (("normal",) if form == "contact" else ()):
            vec = obj.get(key)
            if not (isinstance(vec, list) and len(vec) == 3):
                raise ConfigError(f"stdin line {number}: {key!r} must be a list of three numbers")
            row[key] = vec
        for key in ("d1", "d2", "rho1", "rho2"):
            row[key] = obj.get(key, defaults[key])
        values = [float(x) for key in row for x in (row[key] if isinstance(row[key], list) else [row[key]])]
        if not all(math.isfinite(x) for x in values):
            raise ConfigError(f"stdin line {number}: every value must be a finite number")
        if min(row["d1"], row["d2"], row["rho1"], row["rho2"]) <= 0:
            raise ConfigError(f"stdin line {number}: diameters and densities must be > 0")
        if form == "contact":
            norm = math.sqrt(sum(x * x for x in row["normal"]))
            if abs(norm - 1.0) > 1e-3:
                raise ConfigError(f"stdin line {number}: 'normal' must be a unit vector (|n| = {norm:.4g})")
            row["normal"] = [x / norm for x in row["normal"]]
            approach = sum((a - b) * n for a, b, n in zip(row["v1"], row["v2"], row["normal"]))
            if not approach > 0:
                raise ConfigError(f"stdin line {number}: the pair does not approach ((v1 - v2).normal = "
                                  f"{approach:.4g} m/s); give the normal from particle 1 to particle 2 of a colliding pair")
        rows.append(row)
    return rows


def run(args) -> int:
    import json
    import os
    import sys

    import numpy as np

    from hel_warp._warp import init_warp
    from hel_warp.collisions.forest import ForestPredictor, load_forest

    flat = load_forest(args.model)
    defaults = {"d1": 315e-6, "d2": 315e-6, "rho1": 1000.0, "rho2": 1000.0}
    meta_path = os.path.join(args.model, "metadata.json")
    if os.path.isfile(meta_path):
        with open(meta_path) as fh:
            defaults.update(json.load(fh).get("defaults", {}))
    rows = _parse_lines(sys.stdin, flat.form, defaults)
    if not rows:
        return 0
    col = lambda key: np.asarray([r[key] for r in rows], dtype=np.float64)
    init_warp(args.device)  # stdout carries the predictions: no Warp greeting; a missing device is a ConfigError
    predictor = ForestPredictor(flat, device=args.device)
    v1_after, v2_after = predictor.predict_pairs(col("v1"), col("v2"), col("d1"), col("d2"), col("rho1"),
                                                 col("rho2"), normal=col("normal") if flat.form == "contact" else None,
                                                 guard=not args.no_guard)
    for a, b in zip(v1_after.tolist(), v2_after.tolist()):
        if args.json:
            print(json.dumps({"velocity1_after": a, "velocity2_after": b}))
        else:
            print(f"v1' = {a[0]:.6g} {a[1]:.6g} {a[2]:.6g}   v2' = {b[0]:.6g} {b[1]:.6g} {b[2]:.6g}")
    counts = predictor.last_counts
    if "guard_any" in counts:
        print(f"hel-warp predict: {counts['pairs']} pairs, {counts['clamped']} clamped into the training domain, "
              f"guard corrections: separation {counts['guard_separation']}, Coulomb {counts['guard_coulomb']}, "
              f"energy {counts['guard_energy']} ({counts['guard_any']} pairs)", file=sys.stderr)
    return 0
