"""Pictures of bubbling-bed runs (``cases/bubbling_bed.py``), one run or several models side by side.

For one run (called by the case at its end, into the run directory):

- ``bed_snapshots.png``: the parcels seen through the depth (x-z), coloured by speed, at up to six instants;
- ``bed_solids_fraction.png``: the solids fraction averaged over the depth and over the gas snapshots of the
  last level's second half;
- ``bed_history.png``: the pressure drop across the bed and the bed height over time, with the bed's weight per
  area and the level windows;
- ``bed_fluidization.png``: the pressure drop of each level against its velocity, with Ergun's line at the settled
  voidage, the weight per area and the Wen-Yu minimum fluidization velocity.

Several runs (e.g. one per model) into ``--out``: the solids-fraction maps on one colour scale, the fluidization
curves of every run on one plot, and the histories together; with a reference (``--reference RUN``, by default the
``dem`` run among them) ``comparison.md`` / ``.json``: each run beside it at its last level (bed height, pressure
drop and frequency, the RMS distance of the solids-fraction profiles at 10, 20 and 40 mm, cost)::

    python scripts/bed_report.py runs/bed_dem runs/bed_ktgf runs/bed_surrogate --out runs/bed_report
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

CMAP = "viridis"
EPS_RANGE = (0.0, 0.65)
"""One colour range for every solids-fraction map: empty to random close packing."""


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def stamp(fig) -> None:
    """Commit and date in the corner, so a picture says what made it."""
    import datetime
    import subprocess

    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).resolve().parents[1], timeout=10).stdout.strip() or "?"
    except (OSError, subprocess.SubprocessError):
        commit = "?"
    fig.text(0.995, 0.005, f"hel_warp {commit}, {datetime.date.today().isoformat()}", ha="right", va="bottom",
             fontsize=6, color="0.5")


def _save(fig, path: Path) -> None:
    """Stamp, write and close a figure."""
    stamp(fig)
    fig.savefig(path, dpi=110)
    _plt().close(fig)


def _load(run_dir: Path):
    import zarr

    root = zarr.open_group(str(run_dir / "run.zarr"), mode="r")
    summary = json.loads((run_dir / "summary.json").read_text()) if (run_dir / "summary.json").exists() else \
        dict(root.attrs.get("summary", {}))
    return root, summary


def _label(summary: dict) -> str:
    return str(summary.get("collision_model", summary.get("collisions", "?")))


def _window(summary: dict):
    levels = summary.get("levels") or []
    return tuple(levels[-1]["window"]) if levels else None


def mean_solids_map(root, summary):
    """Depth- and time-averaged eps_s (nx, nz) over the gas snapshots in the last level's second half (all
    snapshots after the first if no level finished)."""
    gas = root["gas"] if "gas" in root else None
    if gas is None:
        return None
    keys = sorted(gas.group_keys())
    window = _window(summary)
    chosen = [k for k in keys if window and window[0] - 1e-9 <= gas[k].attrs["time"] <= window[1] + 1e-9]
    if not chosen:
        chosen = keys[1:] or keys
    if not chosen or "cell_eps_s" not in gas[chosen[0]]:
        return None
    return np.mean([np.asarray(gas[k]["cell_eps_s"][...], np.float64).mean(axis=1) for k in chosen], axis=0), len(chosen)


def draw_snapshots(root, summary, path: Path, count: int = 6) -> None:
    plt = _plt()
    snaps = root["snapshots"]
    keys = sorted(snaps.group_keys())
    if not keys:
        return
    pick = [keys[int(round(i))] for i in np.linspace(0, len(keys) - 1, min(count, len(keys)))]
    box = summary.get("box") or [None, None, None]
    fig, axes = plt.subplots(1, len(pick), figsize=(2.2 * len(pick) + 1.2, 5.2), sharey=True, squeeze=False)
    speeds = [np.linalg.norm(np.asarray(snaps[k]["v"][...], np.float64), axis=1) for k in pick]
    vmax = max(float(np.percentile(s, 99)) if s.size else 0.0 for s in speeds) or 1.0
    for ax, k, s in zip(axes[0], pick, speeds):
        x = np.asarray(snaps[k]["x"][...], np.float64)
        sc = ax.scatter(x[:, 0] * 1e3, x[:, 2] * 1e3, c=s, s=1.5, cmap="plasma", vmin=0.0, vmax=vmax,
                        rasterized=True)
        ax.set_title(f"t = {snaps[k].attrs['time']:.2f} s", fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlabel("x, mm")
        if box[0]:
            ax.set_xlim(0, box[0] * 1e3)
            ax.set_ylim(0, min(box[2], 0.08) * 1e3)
    axes[0][0].set_ylabel("height above the distributor z, mm")
    fig.colorbar(sc, ax=axes[0].tolist(), label="parcel speed, m/s", shrink=0.8)
    fig.suptitle(f"Bubbling bed, {_label(summary)}: parcels through the depth, coloured by speed")
    _save(fig, path)


def draw_solids_maps(runs, path: Path) -> None:
    """One map per run, the same colour range (``EPS_RANGE``)."""
    plt = _plt()
    maps = [(summary, mean_solids_map(root, summary)) for root, summary in runs]
    maps = [(s, m) for s, m in maps if m is not None]
    if not maps:
        return
    fig, axes = plt.subplots(1, len(maps), figsize=(2.6 * len(maps) + 1.2, 5.2), sharey=True, squeeze=False)
    for ax, (summary, (eps, n)) in zip(axes[0], maps):
        box = summary["box"]
        im = ax.imshow(eps.T, origin="lower", extent=(0, box[0] * 1e3, 0, box[2] * 1e3), cmap=CMAP,
                       vmin=EPS_RANGE[0], vmax=EPS_RANGE[1], aspect="equal")
        ax.set_ylim(0, min(box[2], 0.08) * 1e3)
        ax.set_xlabel("x, mm")
        window = _window(summary)
        when = f"{window[0]:.2f}-{window[1]:.2f} s" if window else "whole run"
        ax.set_title(f"{_label(summary)}\n{n} snapshots, {when}", fontsize=9)
    axes[0][0].set_ylabel("height z, mm")
    fig.colorbar(im, ax=axes[0].tolist(), label="solids fraction (depth and time average)", shrink=0.8)
    fig.suptitle("Bubbling bed: time-averaged solids fraction")
    _save(fig, path)


def draw_history(runs, path: Path) -> None:
    plt = _plt()
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    weight = None
    for root, summary in runs:
        if "probes" not in root:
            continue
        pr = root["probes"]
        if "bed_pressure_drop" in pr:
            g = pr["bed_pressure_drop"]
            a1.plot(g["time"][...], g["pressure_drop"][...], lw=0.8, label=_label(summary))
        if "bed_height" in pr:
            g = pr["bed_height"]
            a2.plot(g["time"][...], np.asarray(g["bed_height"][...]) * 1e3, lw=0.8, label=_label(summary))
        weight = summary.get("bed_weight_per_area", weight)
        for lv in summary.get("levels") or []:
            a1.axvspan(*lv["window"], color="0.92", zorder=0)
    if weight:
        a1.axhline(weight, color="k", ls="--", lw=1, label=f"bed weight / area ({weight:.0f} Pa)")
    a1.set_ylabel("pressure drop across the bed, Pa")
    a1.legend(fontsize=8, loc="lower right")
    a1.set_title("Bubbling bed: pressure drop and bed height (shaded: the levels' averaging windows)")
    a2.set_ylabel("bed height (eps_s > 0.1), mm")
    a2.set_xlabel("time, s")
    a2.legend(fontsize=8)
    fig.tight_layout()
    _save(fig, path)


def draw_fluidization(runs, path: Path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 5))
    first = runs[0][1]
    umax = max(max((lv["velocity"] for lv in s.get("levels") or []), default=0.0) for _, s in runs) or 1.0
    u = np.linspace(0.0, 1.1 * umax, 200)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "cases"))
    from bubbling_bed import FLUIDIZED_FRACTION, ergun, measured_umf

    d = first.get("diameter", 1.2e-3)
    erg = [ergun(v, first["settled_height"], 1 - first["settled_solids_fraction"], d) for v in u]
    ax.plot(u, erg, "k-", lw=1, label=f"Ergun, settled bed (eps_s = {first['settled_solids_fraction']:.3f})")
    ax.axhline(first["bed_weight_per_area"], color="k", ls="--", lw=1, label="bed weight / area")
    ax.axvline(first["minimum_fluidization_velocity_wen_yu"], color="0.5", ls=":", lw=1,
               label="U_mf, Wen-Yu")
    layered_label = "Ergun through the level's own layers (fixed levels)"
    for marker, (_, s) in zip("osD^v<>", runs):
        levels = s.get("levels") or []
        # the case's own reading of the curve, from the levels (a summary written by an older run may differ)
        umf = measured_umf([lv["velocity"] for lv in levels], [lv["pressure_drop"] for lv in levels],
                           s["bed_weight_per_area"]) if levels else None
        bars = ax.errorbar([lv["velocity"] for lv in levels],
                           [np.nan if lv["pressure_drop"] is None else lv["pressure_drop"] for lv in levels],
                           yerr=[np.nan if lv["pressure_drop_std"] is None else lv["pressure_drop_std"]
                                 for lv in levels], fmt=marker, capsize=3,
                           label=_label(s) + (f", U_mf {umf:.3f} m/s" if umf else ""))
        if umf:  # where this model's fixed branch meets its plateau
            ax.plot([umf], [s["bed_weight_per_area"]], marker="|", ms=18, mew=2, color=bars[0].get_color())
        fixed = [lv for lv in levels if lv.get("ergun_pressure_drop_layers") and lv["pressure_drop"] is not None
                 and lv["pressure_drop"] < FLUIDIZED_FRACTION * s["bed_weight_per_area"]]
        if fixed:
            ax.plot([lv["velocity"] for lv in fixed], [lv["ergun_pressure_drop_layers"] for lv in fixed], "x",
                    ms=7, color=bars[0].get_color(), label=layered_label)
            layered_label = None
    highest = max((lv["pressure_drop"] for _, s in runs for lv in s.get("levels") or []
                   if lv["pressure_drop"] is not None), default=0.0)
    ax.set_ylim(0, max(1.6 * first["bed_weight_per_area"], 1.1 * highest))
    ax.set_xlabel("superficial gas velocity U, m/s")
    ax.set_ylabel("pressure drop across the bed, Pa")
    ax.set_title("Bubbling bed: fluidization curve (bars: std of the fluctuations)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    _save(fig, path)


def draw_run(run_dir, summary=None) -> list:
    """The four pictures of one run into its directory; returns their paths."""
    run_dir = Path(run_dir)
    root, stored = _load(run_dir)
    summary = summary or stored
    paths = [run_dir / f"bed_{name}.png" for name in ("snapshots", "solids_fraction", "history", "fluidization")]
    draw_snapshots(root, summary, paths[0])
    draw_solids_maps([(root, summary)], paths[1])
    draw_history([(root, summary)], paths[2])
    if summary.get("levels"):
        draw_fluidization([(root, summary)], paths[3])
    return [p for p in paths if p.exists()]


def _matching_level(summary: dict, velocity: float):
    """The level of ``summary`` whose velocity is nearest ``velocity`` (None when it is more than 2 % away)."""
    levels = summary.get("levels") or []
    if not levels:
        return None
    level = min(levels, key=lambda lv: abs(lv["velocity"] - velocity))
    return level if abs(level["velocity"] - velocity) <= 0.02 * max(velocity, 1e-12) else None


def profile_distance(profile, reference) -> float:
    """RMS over the reference's x of (eps_s - eps_s_ref), the profile interpolated onto the reference's points."""
    x_ref, e_ref = (np.asarray(v, np.float64) for v in zip(*reference))
    x, e = (np.asarray(v, np.float64) for v in zip(*profile))
    return float(np.sqrt(np.mean((np.interp(x_ref, x, e) - e_ref) ** 2)))


def profile_noise(root, level, height: str) -> float | None:
    """Statistical error of a level's time-averaged solids-fraction profile at ``height`` (m, as in the summary's
    keys), RMS across the width: the averages over the two halves of the level's window differ by twice the error
    of the whole window's average (each half's error is sqrt(2) times the whole's, and they are independent), so
    RMS(half 1 - half 2) / 2. None without the probe's series."""
    if root is None or "probes" not in root or not level.get("window"):
        return None
    name = f"profile_{float(height) * 1e3:g}mm"
    if name not in root["probes"]:
        return None
    g = root["probes"][name]
    t = np.asarray(g["time"][...], np.float64)
    e = np.asarray(g["solids_fraction"][...], np.float64)
    start, end = level["window"]
    mid = 0.5 * (start + end)
    first, second = (t >= start) & (t < mid), (t >= mid) & (t <= end)
    if first.sum() < 2 or second.sum() < 2:
        return None
    return float(np.sqrt(np.mean((e[first].mean(axis=0) - e[second].mean(axis=0)) ** 2)) / 2.0)


def compare(runs, reference: int) -> dict:
    """Each run beside the reference run (e.g. the CFD-DEM) at the reference's last level: bed height, pressure
    drop and its standard deviation, dominant pressure frequency, the RMS distance of the solids-fraction profiles
    at each height from the reference's and the noise floor of that distance (``profile_noise`` of the run and of
    the reference in quadrature: the distance two independent averages of these lengths would show by chance), wall
    clock per simulated second and its ratio to the reference's."""
    ref_summary = runs[reference][1]
    ref_level = (ref_summary.get("levels") or [None])[-1]
    if ref_level is None:
        raise ValueError("the reference run holds no finished level")
    velocity = ref_level["velocity"]

    def cost(summary):
        t = summary.get("simulated_time") or summary.get("end_time")
        return summary["wall_clock_s"] / t if summary.get("wall_clock_s") and t else None

    ref_cost = cost(ref_summary)
    ref_noise = {h: profile_noise(runs[reference][0], ref_level, h) for h in ref_level["solids_fraction_profiles"]}
    rows = []
    for k, (root, summary) in enumerate(runs):
        level = _matching_level(summary, velocity)
        if level is None:
            continue
        distances = {h: profile_distance(p, ref_level["solids_fraction_profiles"][h])
                     for h, p in level["solids_fraction_profiles"].items()
                     if h in ref_level["solids_fraction_profiles"]}
        floors = {}
        for h in distances if k != reference else ():
            own = profile_noise(root, level, h)
            if own is not None and ref_noise[h] is not None:
                floors[h] = float(math.hypot(own, ref_noise[h]))
        c = cost(summary)
        rows.append({"run": _label(summary), "reference": k == reference, "velocity": level["velocity"],
                     "bed_height": level["bed_height"], "mean_height_x2": level["mean_height_x2"],
                     "pressure_drop": level["pressure_drop"], "pressure_drop_std": level["pressure_drop_std"],
                     "pressure_drop_error": level.get("pressure_drop_error"),
                     "pressure_frequency": level["pressure_frequency"],
                     "profile_rms": distances, "profile_noise_floor": floors,
                     "profile_rms_mean": float(np.mean(list(distances.values()))) if distances else None,
                     "wall_clock_per_simulated_s": c,
                     "reference_cost_ratio": ref_cost / c if c and ref_cost else None})
    return {"velocity": velocity, "reference": _label(ref_summary), "weight_per_area": ref_summary.get(
        "bed_weight_per_area"), "runs": rows}


def comparison_table(result: dict) -> str:
    """``compare``'s result as a Markdown table with a line on each column."""
    heights = sorted({h for r in result["runs"] for h in r["profile_rms"]}, key=float)
    head = ["run", "bed height, mm", "2 x mean height, mm", "pressure drop, Pa", "pressure frequency, Hz",
            *[f"eps_s RMS at {float(h) * 1e3:g} mm" for h in heights], "wall clock per simulated s",
            f"{result['reference']} / run"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in result["runs"]:
        cells = [r["run"] + (" (reference)" if r["reference"] else ""), f"{r['bed_height'] * 1e3:.1f}",
                 f"{r['mean_height_x2'] * 1e3:.1f}", f"{r['pressure_drop']:.1f} ± {r['pressure_drop_std']:.1f}"
                 + ("" if r.get("pressure_drop_error") is None else f" (mean ± {r['pressure_drop_error']:.1f})"),
                 f"{r['pressure_frequency']:.2f}",
                 *[(f"{r['profile_rms'][h]:.3f}" + (f" ({r['profile_noise_floor'][h]:.3f})"
                                                     if h in r.get("profile_noise_floor", {}) else ""))
                   if h in r["profile_rms"] else "" for h in heights],
                 "" if r["wall_clock_per_simulated_s"] is None else f"{r['wall_clock_per_simulated_s']:.0f} s",
                 "" if r["reference_cost_ratio"] is None else f"{r['reference_cost_ratio']:.1f}"]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", f"At U = {result['velocity']:g} m/s, each level's second half. Bed height: the highest layer above "
              "eps_s = 0.1; 2 x mean height: twice the mean particle height; the pressure drop's mean and standard "
              "deviation across the bed, and in brackets the standard error of its mean (the bed weight per area is "
              f"{result['weight_per_area']:.1f} Pa); pressure frequency: the dominant frequency of its fluctuations. "
              "eps_s RMS: the root mean square distance of the time-averaged solids-fraction profile across the width "
              f"from the {result['reference']}'s at that height (0: the same profile; smaller is closer), and in "
              "brackets its noise floor: the distance two independent averages of these lengths show by chance, from "
              "the difference of each run's averages over the two halves of its window (a distance at or below it "
              "does not tell the run from the reference). "
              "Wall clock of the steps per simulated second, and the reference's divided by the run's."]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="bubbling-bed run directories")
    parser.add_argument("--out", required=True, help="directory of the pictures")
    parser.add_argument("--reference", default=None,
                        help="the run the others are compared with at its last level (default: the dem run, if "
                             "any): comparison.md and comparison.json in --out")
    args = parser.parse_args(argv)
    runs = []
    for r in args.runs:
        path = Path(r)
        if not (path / "run.zarr").exists():
            print(f"hel-warp: error: {r} is not a run directory (no run.zarr)", file=sys.stderr)
            return 2
        runs.append(_load(path))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    draw_solids_maps(runs, out / "bed_solids_fraction.png")
    draw_history(runs, out / "bed_history.png")
    draw_fluidization(runs, out / "bed_fluidization.png")
    for (root, summary), r in zip(runs, args.runs):
        draw_snapshots(root, summary, out / f"bed_snapshots_{Path(r).name}.png")
    reference = None
    if args.reference is not None:
        matches = [k for k, r in enumerate(args.runs) if Path(r).resolve() == Path(args.reference).resolve()]
        if not matches:
            print(f"hel-warp: error: --reference {args.reference} is not one of the runs given", file=sys.stderr)
            return 2
        reference = matches[0]
    else:
        dem = [k for k, (_, summary) in enumerate(runs) if _label(summary) == "dem"]
        reference = dem[0] if dem else None
    if reference is not None and len(runs) > 1:
        try:
            result = compare(runs, reference)
        except ValueError as exc:
            print(f"hel-warp: error: {exc}", file=sys.stderr)
            return 2
        table = comparison_table(result)
        (out / "comparison.md").write_text(table + "\n")
        (out / "comparison.json").write_text(json.dumps(result, indent=1) + "\n")
        print(table)
    print("\n".join(str(p) for p in sorted(out.glob("*.png"))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
