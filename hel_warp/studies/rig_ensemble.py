"""Stream metrics of an ensemble of rig runs: runs that differ only in their seed, pooled, against a (pooled)
reference.

A run of W particles per parcel carries the real particles of a weight-1 run in 1/W of the parcels, so one run's
per-section crossing and transverse rms rest on W times fewer samples (``scripts/rig_metric_subsample.py``
measures that noise). Runs of the same case with different ``--seed`` are independent samples of the same flow:
pooling their snapshots (each snapshot time, the parcels of every run, weights divided by the number of runs so
the real mass is one run's) gives the metrics of W x more parcels at no change of physics, which the mean of the
runs' own figures does not (a section of a weighted run often holds too few parcels for a figure at all). The
reference (``dem`` runs, one or several seeds) is pooled the same way.

``hel-warp ensemble cases/colliding_streams.py ...`` calls ``case_hook`` (the rig's ``pooled_metrics``) once per
parameter combination; the same figures for run folders made otherwise:

    python -m hel_warp.studies.rig_ensemble --reference runs/dem_s0 runs/dem_s1 --runs runs/w8_s* --label cell_w8

``--jackknife`` adds standard errors from the seed-to-seed spread (``--jackknife-groups G`` for ensembles of
hundreds of runs: G evaluations instead of one per run); every ensemble also reports its mean real collision rate
against the reference's, in total and per stream pair.
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
                     sections=None, jackknife: bool = False, groups: int | None = None) -> dict:
    """Crossing and transverse rms of the pooled ``paths`` against the pooled ``reference_paths`` (and over the
    fixed ``sections``, 1-based, when given: ``fixed``); the real collision rates of both (``collisions``);
    ``jackknife``: the standard errors of the compared figures (``jackknife``), leaving out one run at a time or,
    with ``groups``, one of that many groups of runs."""
    from hel_warp.runs.report import load_run

    runs = [load_run(p) for p in paths]
    refs = [load_run(p) for p in reference_paths]
    out = pooled_metrics(runs, refs, min_samples, label, sections)
    out["collisions"] = ensemble_collisions(runs, refs)
    if jackknife:
        out["jackknife"] = jackknife_errors(runs, refs, min_samples, out, sections=sections, groups=groups)
    return out


def ensemble_collisions(runs, refs) -> dict:
    """Real binary collisions per simulated second (``hel_warp.runs.report.collision_rates``), the mean over the runs
    and over the reference runs, in total and per stream pair, and their ratio (runs / reference; None where the
    reference has none or a side does not count collisions): how often the model collides, beside what the
    collisions do to the streams. Collisions are a rate of each run, not of the pooled parcels, so they are
    averaged, not pooled."""
    from hel_warp.runs.report import collision_rates

    def mean_rates(group):
        rates = [collision_rates(r) for r in group]
        if not rates or any(r["collision_rate"] is None for r in rates):
            return None, None
        total = float(np.mean([r["collision_rate"] for r in rates]))
        pairs = sorted(set().union(*(r["collision_rate_per_stream_pair"] or {} for r in rates)))
        per_pair = {k: float(np.mean([(r["collision_rate_per_stream_pair"] or {}).get(k, 0.0) for r in rates]))
                    for k in pairs}
        return total, per_pair

    def ratio(a, b):
        return None if a is None or b is None or b <= 0.0 else a / b

    total, per_pair = mean_rates(runs)
    ref_total, ref_pair = mean_rates(refs)
    out = {"collision_rate": total, "reference_collision_rate": ref_total,
           "collision_rate_vs_dem": ratio(total, ref_total),
           "collision_rate_per_stream_pair": per_pair, "reference_collision_rate_per_stream_pair": ref_pair,
           "collision_rate_per_stream_pair_vs_dem": None}
    if per_pair is not None and ref_pair is not None:
        out["collision_rate_per_stream_pair_vs_dem"] = {k: ratio(per_pair.get(k), ref_pair.get(k))
                                                        for k in sorted(set(per_pair) | set(ref_pair))}
    return out


JACKKNIFE_KEYS = ("stream_crossing_vs_dem", "transverse_velocity_rms_vs_dem")


def _jackknife_values(m: dict) -> dict:
    """The compared figures of a ``pooled_metrics`` result, flat: whole run (and over the fixed sections,
    ``fixed_*``) and each size class."""

    def figures(r: dict, prefix: str) -> dict:
        vals = {prefix + k: r[k] for k in JACKKNIFE_KEYS}
        if "fixed" in r:
            vals.update({f"{prefix}fixed_{k}": r["fixed"][k] for k in JACKKNIFE_KEYS})
        return vals

    vals = figures(m, "")
    for c in m.get("size_classes", []):
        vals.update(figures(c, f"{1e6 * c['diameter']:.0f}um_"))
    return vals


def leave_out_groups(n: int, groups: int | None) -> list[list[int]]:
    """Indices 0..n-1 in the groups a jackknife leaves out in turn: one each (``groups`` None or >= n), else
    ``groups`` contiguous groups of near-equal size (the delete-a-group jackknife: with runs in seed order, each
    group a block of seeds)."""
    if groups is None or groups >= n:
        return [[k] for k in range(n)]
    if groups < 2:
        from hel_warp.errors import ConfigError

        raise ConfigError(f"a jackknife needs at least 2 groups (got {groups})")
    bounds = np.linspace(0, n, groups + 1).round().astype(int)
    return [list(range(a, b)) for a, b in zip(bounds[:-1], bounds[1:])]


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


def jackknife_errors(runs, refs, min_samples: int, full: dict, sections=None, groups: int | None = None) -> dict:
    """Standard errors of the ``*_vs_dem`` figures (whole run, over the fixed ``sections`` when given, per size
    class) from the seed-to-seed spread: leave one run out of the ensemble (``runs``; with ``groups``, one of that
    many contiguous groups of runs at a time, the delete-a-group jackknife, which costs ``groups`` evaluations
    instead of one per run), and one run of the reference (``refs``) when it holds two or more runs; ``combined``
    adds the two in quadrature. A difference from the reference smaller than ~2 combined errors is not resolved by
    these ensembles."""
    base = _jackknife_values(full)
    out = {"runs": None, "reference": None, "groups": None}

    def without(group, leave):
        drop = set(leave)
        return [r for k, r in enumerate(group) if k not in drop]

    if len(runs) >= 2:
        parts = leave_out_groups(len(runs), groups)
        out["groups"] = len(parts)
        out["runs"] = _leave_one_out_error([_jackknife_values(pooled_metrics(without(runs, leave), refs, min_samples,
                                                                             sections=sections))
                                            for leave in parts])
    if len(refs) >= 2:
        out["reference"] = _leave_one_out_error([_jackknife_values(pooled_metrics(runs, without(refs, [k]),
                                                                                  min_samples, sections=sections))
                                                 for k in range(len(refs))])
    combined = {}
    for key in base:
        parts = [src[key] for src in (out["runs"], out["reference"]) if src is not None]
        combined[key] = None if not parts or any(x is None for x in parts) else float(np.hypot.reduce(parts))
    out["combined"] = combined
    return out


def pooled_metrics(runs, refs, min_samples: int = 10, label: str | None = None, sections=None) -> dict:
    """``ensemble_metrics`` of runs already loaded (``hel_warp.runs.report.load_run``)."""
    from hel_warp.runs.report import DEFAULT_BOXES, size_class_view, size_classes, stream_metrics, stream_metrics_vs

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
                "reference_crossing_per_section": [s.get("stream_crossing") for s in ref.get("sections", [])],
                "transverse_velocity_rms_per_section": [s.get("transverse_velocity_rms")
                                                        for s in m.get("sections", [])],
                "reference_transverse_velocity_rms_per_section": [s.get("transverse_velocity_rms")
                                                                  for s in ref.get("sections", [])]}

    out = {"label": run.label, "runs": len(runs), "reference_runs": len(refs), **compare(run, ref_run)}
    classes = size_classes(run)
    if classes is not None and size_classes(ref_run) is not None:  # a mixture: each size class against its own
        out["size_classes"] = [{"diameter": float(c["diameter"]),
                                **compare(size_class_view(run, k), size_class_view(ref_run, k))}
                               for k, c in enumerate(classes)]
    return out


HOOK_SECTIONS = (1, 2, 3, 4, 5, 6, 7)
"""The fixed sections of ``case_hook``'s ``fixed_*`` figures: the sections every ensemble of the rig fills (a
whole-run figure moves with the set of filled sections, so ensembles of different sizes compare over these)."""
HOOK_MIN_SAMPLES = 10
"""Parcels a section needs for a figure (as ``hel-warp report --min-samples``)."""
HOOK_LEAVE_ONE_OUT = 32
"""Up to this many runs the jackknife leaves one run out at a time; beyond, one of ``HOOK_GROUPS`` blocks."""
HOOK_GROUPS = 24


def _alone_values(runs, min_samples: int, sections) -> dict:
    """The pooled figures of runs without a reference: crossing and v_y rms over the whole run and over
    ``sections``, per section, per size class."""
    from hel_warp.runs.report import DEFAULT_BOXES, size_class_view, size_classes, stream_metrics

    run = pooled(runs)

    def figures(r, prefix: str) -> dict:
        m = stream_metrics(r, DEFAULT_BOXES, min_samples=min_samples)
        secs = m.get("sections", [])
        vals = {prefix + "stream_crossing": m["stream_crossing"],
                prefix + "transverse_velocity_rms": m["transverse_velocity_rms"]}
        if sections:
            picked = [secs[k - 1] if 0 < k <= len(secs) else {} for k in sections]
            for key in ("stream_crossing", "transverse_velocity_rms"):
                v = [x.get(key) for x in picked]
                vals[f"{prefix}fixed_{key}"] = None if any(x is None for x in v) else float(np.mean(v))
        vals[prefix + "crossing_per_section"] = [x.get("stream_crossing") for x in secs]
        vals[prefix + "transverse_velocity_rms_per_section"] = [x.get("transverse_velocity_rms") for x in secs]
        return vals

    out = figures(run, "")
    for k, c in enumerate(size_classes(run) or []):
        out.update(figures(size_class_view(run, k), f"{1e6 * float(c['diameter']):.0f}um_"))
    return out


def case_hook(member_dirs, reference_dirs=None, *, min_samples: int = HOOK_MIN_SAMPLES,
              sections=HOOK_SECTIONS) -> dict:
    """The rig's ``pooled_metrics`` for ``hel-warp ensemble``: its figures pooled over the members' snapshots.

    With reference folders (the ``--reference`` ensemble's matching members, e.g. the CFD-DEM seeds):
    ``ensemble_metrics`` with the fixed ``sections`` and the jackknife (whole run, sections, per size class, per
    section, collision rates and their ratio to the reference's); without: the pooled crossing and v_y rms of the
    members alone, with the jackknife over the members. The jackknife leaves one run out up to
    ``HOOK_LEAVE_ONE_OUT`` runs, else one of ``HOOK_GROUPS`` blocks. Returns ``{"metrics": flat figures,
    "stderr": their standard errors where the jackknife gives one, "detail": the full result}``."""
    runs = list(member_dirs)
    groups = None if len(runs) <= HOOK_LEAVE_ONE_OUT else HOOK_GROUPS
    if reference_dirs:
        full = ensemble_metrics(runs, list(reference_dirs), min_samples, sections=sections, jackknife=True,
                                groups=groups)
        keys = ("stream_crossing", "reference_stream_crossing", "stream_crossing_vs_dem", "transverse_velocity_rms",
                "reference_transverse_velocity_rms", "transverse_velocity_rms_vs_dem", "crossing_per_section",
                "reference_crossing_per_section", "transverse_velocity_rms_per_section",
                "reference_transverse_velocity_rms_per_section")

        def flat(m: dict, prefix: str) -> dict:
            vals = {prefix + k: m.get(k) for k in keys}
            vals.update({f"{prefix}fixed_{k}": v for k, v in (m.get("fixed") or {}).items() if k != "sections"})
            return vals

        metrics = flat(full, "")
        for c in full.get("size_classes", []):
            metrics.update(flat(c, f"{1e6 * c['diameter']:.0f}um_"))
        col = full["collisions"]
        metrics.update({k: col[k] for k in ("collision_rate", "reference_collision_rate", "collision_rate_vs_dem")})
        for k, v in (col.get("collision_rate_per_stream_pair_vs_dem") or {}).items():
            metrics[f"collision_rate_vs_dem_{k}"] = v
        return {"metrics": metrics, "stderr": full["jackknife"]["combined"], "detail": full}
    from hel_warp.runs.report import collision_rates, load_run

    loaded = [load_run(p) for p in runs]
    metrics = _alone_values(loaded, min_samples, sections)
    rates = [collision_rates(r)["collision_rate"] for r in loaded]
    metrics["collision_rate"] = None if any(r is None for r in rates) else float(np.mean(rates))
    stderr = None
    if len(loaded) >= 2:
        scalar = lambda vals: {k: v for k, v in vals.items() if not isinstance(v, list)}  # noqa: E731
        parts = leave_out_groups(len(loaded), groups)
        stderr = _leave_one_out_error([scalar(_alone_values([r for k, r in enumerate(loaded) if k not in set(g)],
                                                            min_samples, sections)) for g in parts])
    return {"metrics": metrics, "stderr": stderr or {}, "detail": {"runs": len(loaded), "groups": groups,
                                                                   "sections": list(sections)}}


def main(argv=None) -> int:
    from hel_warp.errors import ConfigError

    p = argparse.ArgumentParser(prog="python -m hel_warp.studies.rig_ensemble", description=__doc__.split("\n\n")[0])
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
    p.add_argument("--jackknife-groups", type=int, default=None, metavar="G",
                   help="with --jackknife: leave out one of G contiguous groups of runs at a time instead of one run "
                        "(G evaluations instead of one per run; for ensembles of hundreds of runs)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args(argv)
    if args.jackknife_groups is not None and args.jackknife_groups < 2:
        print(f"hel-warp: error: --jackknife-groups must be >= 2 (got {args.jackknife_groups})", file=sys.stderr)
        return 2
    try:
        out = ensemble_metrics(args.runs, args.reference, args.min_samples, args.label, args.sections,
                               jackknife=args.jackknife, groups=args.jackknife_groups)
    except ConfigError as exc:
        print(f"hel-warp: error: {exc}", file=sys.stderr)
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

    def fixed(m, prefix=""):
        f = m.get("fixed")
        if not f:
            return ""
        vy = f["transverse_velocity_rms_vs_dem"]
        jk = (out.get("jackknife") or {}).get("combined") or {}
        ex, ev = jk.get(prefix + "fixed_" + JACKKNIFE_KEYS[0]), jk.get(prefix + "fixed_" + JACKKNIFE_KEYS[1])
        se = (f" (+- {num(ex, '.3f')} / {num(None if ev is None else 100 * ev, '.1f')} %)"
              if out.get("jackknife") else "")
        return (f"; sections {','.join(str(k) for k in f['sections'])}: crossing "
                f"{num(f['stream_crossing_vs_dem'], '+.3f')}, v_y rms {num(None if vy is None else 100 * vy, '+.1f')} %"
                + se)

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
        name = f"{1e6 * c['diameter']:.0f}um_"
        print("  " + line(f"{1e6 * c['diameter']:.0f} um", c) + fixed(c, name) + errors(name))
    col = out["collisions"]
    if col["collision_rate"] is not None:
        ratios = col["collision_rate_per_stream_pair_vs_dem"] or {}
        print(f"  real collisions per second (mean of the runs): {col['collision_rate']:.4g}, "
              f"{num(col['collision_rate_vs_dem'], '.3f')} of the reference's; per stream pair "
              + ", ".join(f"{k} {num(v, '.3f')}" for k, v in ratios.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
