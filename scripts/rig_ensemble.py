"""Stream metrics of an ensemble: runs that differ only in their seed, pooled, against a (pooled) reference.

A run of W particles per parcel carries the real particles of a weight-1 run in 1/W of the parcels, so one run's
per-section crossing and transverse rms rest on W times fewer samples (``scripts/rig_metric_subsample.py``
measures that noise). Runs of the same case with different ``--seed`` are independent samples of the same flow:
pooling their snapshots (each snapshot time, the parcels of every run, weights divided by the number of runs so
the real mass is one run's) gives the metrics of W x more parcels at no change of physics. The reference (``dem``
runs, one or several seeds) is pooled the same way (issue 12, docs/FIGURES.md):

    python scripts/rig_ensemble.py --reference runs/dem_s0 runs/dem_s1 --runs runs/w8_s* --label cell_w8
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

import numpy as np


def pooled(runs, label: str | None = None):
    """One run whose snapshot k holds the parcels of snapshot k of every run, weights / len(runs).

    The runs must share their snapshot times (same dt, output interval and end time); the pooled run has the first
    run's config and label (or ``label``)."""
    from hel_warp.errors import ConfigError

    if not runs:
        raise ConfigError("no runs to pool")
    n = len(runs[0].times)
    for r in runs[1:]:
        if len(r.times) != n or not np.allclose(r.times, runs[0].times, rtol=0.0, atol=1e-9):
            raise ConfigError(f"{r.path}: snapshot times differ from {runs[0].path}; pool runs of one case "
                              "(same --dt, --output-interval, --end-time) that differ in --seed only")
    scale = 1.0 / len(runs)
    snaps = []
    for k in range(n):
        parts = [r.snapshots[k] for r in runs]
        count = [len(np.asarray(p["x"])) for p in parts]
        out = {}
        for name, a in parts[0].items():
            arrays = [p.get(name) for p in parts]
            if all(isinstance(b, np.ndarray) and b.shape[:1] == (c,) for b, c in zip(arrays, count)):
                out[name] = np.concatenate(arrays)
            else:
                out[name] = a
        out["weight"] = np.asarray(out["weight"], dtype=np.float64) * scale
        snaps.append(out)
    return dataclasses.replace(runs[0], snapshots=snaps, times=np.asarray(runs[0].times[:n]),
                               label=label or runs[0].label)


def fixed_sections(m: dict, ref: dict, sections) -> dict:
    """Crossing difference and relative v_y rms difference over the given sections (1-based) only, as
    ``stream_metrics_vs`` computes them (mean of the per-section crossing differences; relative difference of the
    mean v_y rms): ensembles of different sizes fill different sections, and the whole-run figure moves with the
    set; None when a section lacks a value on either side."""
    idx = [k - 1 for k in sections]
    if any(k < 0 or k >= len(m["sections"]) for k in idx):
        return {"sections": list(sections), "stream_crossing_vs_dem": None, "transverse_velocity_rms_vs_dem": None}
    a = [m["sections"][k] for k in idx]
    b = [ref["sections"][k] for k in idx]
    if any(x["stream_crossing"] is None or y["stream_crossing"] is None or x["transverse_velocity_rms"] is None
           or y["transverse_velocity_rms"] is None for x, y in zip(a, b)):
        return {"sections": list(sections), "stream_crossing_vs_dem": None, "transverse_velocity_rms_vs_dem": None}
    crossing = float(np.mean([x["stream_crossing"] - y["stream_crossing"] for x, y in zip(a, b)]))
    vy_a = float(np.mean([x["transverse_velocity_rms"] for x in a]))
    vy_b = float(np.mean([y["transverse_velocity_rms"] for y in b]))
    return {"sections": list(sections), "stream_crossing_vs_dem": crossing,
            "transverse_velocity_rms_vs_dem": vy_a / vy_b - 1.0}


def ensemble_metrics(paths, reference_paths, min_samples: int = 10, label: str | None = None,
                     sections=None, jackknife: bool = False) -> dict:
    """Crossing and transverse rms of the pooled ``paths`` against the pooled ``reference_paths`` (and over the
    fixed ``sections``, 1-based, when given: ``fixed``); ``jackknife``: their standard errors (``jackknife``)."""
    from hel_warp.report import load_run

    runs = [load_run(p) for p in paths]
    refs = [load_run(p) for p in reference_paths]
    out = pooled_metrics(runs, refs, min_samples, label, sections)
    if jackknife:
        out["jackknife"] = jackknife_errors(runs, refs, min_samples, out)
    return out


JACKKNIFE_KEYS = ("stream_crossing_vs_dem", "transverse_velocity_rms_vs_dem")


def _jackknife_values(m: dict) -> dict:
    """The compared figures of a ``pooled_metrics`` result, flat: whole run and each size class."""
    vals = {k: m[k] for k in JACKKNIFE_KEYS}
    for c in m.get("size_classes", []):
        for k in JACKKNIFE_KEYS:
            vals[f"{1e6 * c['diameter']:.0f}um_{k}"] = c[k]
    return vals


def _leave_one_out_error(estimates: list[dict]) -> dict:
    """Jackknife standard error sqrt((n - 1) / n sum (t_i - t_mean)^2) of each figure over leave-one-out estimates
    (None where any estimate lacks it or fewer than two)."""
    out = {}
    for key in estimates[0]:
        v = [e.get(key) for e in estimates]
        if len(v) < 2 or any(x is None for x in v):
            out[key] = None
            continue
        a = np.asarray(v, dtype=np.float64)
        out[key] = float(np.sqrt((len(a) - 1) / len(a) * np.sum((a - a.mean()) ** 2)))
    return out


def jackknife_errors(runs, refs, min_samples: int, full: dict) -> dict:
    """Standard errors of the ``*_vs_dem`` figures (whole run and per size class) from the seed-to-seed spread:
    leave one run out of the ensemble (``runs``), and of the reference (``refs``) when it holds two or more runs;
    ``combined`` adds the two in quadrature. A difference from the reference smaller than ~2 combined errors is not
    resolved by these ensembles."""
    base = _jackknife_values(full)
    out = {"runs": None, "reference": None}
    if len(runs) >= 2:
        out["runs"] = _leave_one_out_error([_jackknife_values(pooled_metrics(runs[:k] + runs[k + 1:], refs,
                                                                             min_samples))
                                            for k in range(len(runs))])
    if len(refs) >= 2:
        out["reference"] = _leave_one_out_error([_jackknife_values(pooled_metrics(runs, refs[:k] + refs[k + 1:],
                                                                                  min_samples))
                                                 for k in range(len(refs))])
    combined = {}
    for key in base:
        parts = [src[key] for src in (out["runs"], out["reference"]) if src is not None]
        combined[key] = None if not parts or any(x is None for x in parts) else float(np.hypot.reduce(parts))
    out["combined"] = combined
    return out


def pooled_metrics(runs, refs, min_samples: int = 10, label: str | None = None, sections=None) -> dict:
    """``ensemble_metrics`` of runs already loaded (``hel_warp.report.load_run``)."""
    from hel_warp.report import DEFAULT_BOXES, size_class_view, size_classes, stream_metrics, stream_metrics_vs

    ref_run = pooled(refs)
    run = pooled(runs, label)

    def compare(r, q) -> dict:
        m = stream_metrics(r, DEFAULT_BOXES, min_samples=min_samples)
        ref = stream_metrics(q, DEFAULT_BOXES, min_samples=min_samples)
        vs = stream_metrics_vs(m, ref, DEFAULT_BOXES, min_samples=min_samples)
        extra = {"fixed": fixed_sections(m, ref, sections)} if sections else {}
        return {**extra, "stream_crossing": m["stream_crossing"], "reference_stream_crossing": ref["stream_crossing"],
                "stream_crossing_vs_dem": vs["stream_crossing_vs_dem"]["difference"],
                "transverse_velocity_rms": m["transverse_velocity_rms"],
                "reference_transverse_velocity_rms": ref["transverse_velocity_rms"],
                "transverse_velocity_rms_vs_dem": vs["transverse_velocity_rms_vs_dem"]["relative_difference"],
                "crossing_per_section": [s.get("stream_crossing") for s in m.get("sections", [])],
                "reference_crossing_per_section": [s.get("stream_crossing") for s in ref.get("sections", [])]}

    out = {"label": run.label, "runs": len(runs), "reference_runs": len(refs), **compare(run, ref_run)}
    classes = size_classes(run)
    if classes is not None and size_classes(ref_run) is not None:  # a mixture: each size class against its own
        out["size_classes"] = [{"diameter": float(c["diameter"]),
                                **compare(size_class_view(run, k), size_class_view(ref_run, k))}
                               for k, c in enumerate(classes)]
    return out


def main(argv=None) -> int:
    from hel_warp.errors import ConfigError

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", nargs="+", required=True, help="run directories of one case, different --seed")
    p.add_argument("--reference", nargs="+", required=True, help="reference run directories (dem), pooled alike")
    p.add_argument("--label", default=None, help="name of the ensemble in the output")
    p.add_argument("--min-samples", type=int, default=10, help="as hel-warp report --min-samples")
    p.add_argument("--sections", type=int, nargs="+", default=None,
                   help="also compare over these sections only (1-based, e.g. 1 2 3 4), the same set for every "
                        "ensemble")
    p.add_argument("--jackknife", action="store_true",
                   help="also the standard errors of the *_vs_dem figures, leaving one run (and one reference run) "
                        "out at a time (one pooled evaluation per run)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args(argv)
    try:
        out = ensemble_metrics(args.runs, args.reference, args.min_samples, args.label, args.sections,
                               jackknife=args.jackknife)
    except ConfigError as exc:
        print(f"rig_ensemble: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(out))
        return 0

    def num(x, spec):
        return "-" if x is None else format(x, spec)

    def line(name, m):
        return (f"{name}: crossing {num(m['stream_crossing'], '.3f')} vs {num(m['reference_stream_crossing'], '.3f')} "
                f"({num(m['stream_crossing_vs_dem'], '+.3f')}), v_y rms {num(m['transverse_velocity_rms'], '.3f')} vs "
                f"{num(m['reference_transverse_velocity_rms'], '.3f')} m/s "
                f"({num(None if m['transverse_velocity_rms_vs_dem'] is None else 100 * m['transverse_velocity_rms_vs_dem'], '+.1f')} %)")

    def fixed(m):
        f = m.get("fixed")
        if not f:
            return ""
        vy = f["transverse_velocity_rms_vs_dem"]
        return (f"; sections {','.join(str(k) for k in f['sections'])}: crossing "
                f"{num(f['stream_crossing_vs_dem'], '+.3f')}, v_y rms {num(None if vy is None else 100 * vy, '+.1f')} %")

    def errors(prefix=""):
        jk = out.get("jackknife")
        if not jk:
            return ""
        c = jk["combined"]
        x, v = c.get(prefix + JACKKNIFE_KEYS[0]), c.get(prefix + JACKKNIFE_KEYS[1])
        return (f"; standard error (runs and reference, jackknife): crossing {num(x, '.3f')}, v_y rms "
                f"{num(None if v is None else 100 * v, '.1f')} %")

    print(line(f"{out['label']} ({out['runs']} runs) vs reference ({out['reference_runs']} runs)", out) + fixed(out)
          + errors())
    for c in out.get("size_classes", []):
        print("  " + line(f"{1e6 * c['diameter']:.0f} um", c) + fixed(c) + errors(f"{1e6 * c['diameter']:.0f}um_"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
