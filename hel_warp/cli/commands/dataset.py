"""``hel-warp dataset``: the collision data set of paper section 4.1 (eq. 16 configurations run through
the batched binary DEM) written to a zarr group chunk by chunk; kill it and rerun the same command
to resume. The defaults cover every impact the engine meets: the paper's three families, 10 % central,
30 % grazing (incidence 60-89.8 deg), the rest uniform in b^2 (as random collisions), 30 % of the rows
at relative speeds log-uniform down to 0.01 m/s; --paper-set gives the earlier paper-like set (half
central, offsets <= 0.95, normal approach speed >= 0.05 m/s). A size mixture: --diameters D1,D2
--diameter-stds S1,S2 --mass-fractions W1,W2 puts same-size and cross-size pairs in the proportion the mixture
meets them (number fractions from the mass fractions by d^3, times the cross-section (d_i + d_j)^2;
surrogate/configurations.py); --density-std applies to every species."""

from __future__ import annotations

from hel_warp.cli.commands._common import add_json_flag, add_material_options, emit, finite_float, int_at_least


def add_parser(subparsers):
    p = subparsers.add_parser("dataset", help="collision data set (DEM binary impacts) in a resumable zarr group",
                              description=__doc__)
    p.add_argument("--out", required=True, help="output directory (zarr group); an existing one is resumed")
    p.add_argument("--samples", type=int_at_least(1), default=60000, help="number of configurations (default 60000)")
    p.add_argument("--diameter", type=finite_float, default=None, help="mean particle diameter, m (default 315e-6)")
    p.add_argument("--diameter-std", type=finite_float, default=None,
                   help="diameter standard deviation, m (default: the paper's 8.2e-6 for 315e-6, 22e-6 for 475e-6)")
    p.add_argument("--diameters", default=None, metavar="D1,D2[,...]",
                   help="a size mixture: mean diameter of each species, m (e.g. 315e-6,475e-6); same-size and "
                        "cross-size pairs in the proportion the mixture meets them (number fractions from "
                        "--mass-fractions by d^3, times the cross-section (d_i + d_j)^2; see "
                        "surrogate/configurations.py); replaces --diameter/--diameter-std")
    p.add_argument("--diameter-stds", default=None, metavar="S1,S2[,...]",
                   help="with --diameters: diameter standard deviation of each species, m (default: the paper's "
                        "8.2e-6 for 315e-6, 22e-6 for 475e-6)")
    p.add_argument("--mass-fractions", default=None, metavar="W1,W2[,...]",
                   help="with --diameters: mass fraction of each species, each > 0, summing to 1 (default: equal)")
    p.add_argument("--mixture", default=None, metavar="D1,D2",
                   help="DEPRECATED (use --diameters): each particle's species drawn with equal chance (pair "
                        "types 1/4, 1/2, 1/4 whatever the mixture); kept so earlier sets resume byte for byte")
    p.add_argument("--density-std", type=finite_float, default=0.0,
                   help="particle density standard deviation, kg/m^3 (default 0)")
    p.add_argument("--seed", type=int_at_least(0), default=0, help="random seed (default 0)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="Dask distributed scheduler address (e.g. tcp://host:8786); default: compute locally")
    p.add_argument("--chunk-size", type=int_at_least(1), default=None,
                   help="rows per chunk (default 4096, or the stored value when resuming)")
    p.add_argument("--model", choices=("hertz", "linear"), default="hertz", help="DEM contact law (default hertz)")
    p.add_argument("--paper-set", action="store_true",
                   help="the earlier paper-like set: --central-fraction 0.5 --grazing-fraction 0 --max-offset 0.95 "
                        "--slow-fraction 0 --min-normal-speed 0.05 (options given explicitly still win)")
    p.add_argument("--central-fraction", type=finite_float, default=None,
                   help="fraction of central impacts, offset 0 as in the paper (default 0.1); the rest are "
                        "grazing (--grazing-fraction) or uniform in b^2 (1 - central - grazing)")
    p.add_argument("--grazing-fraction", type=finite_float, default=None,
                   help="fraction of rows with incidence angle uniform in [--grazing-angle, asin(--max-offset)] "
                        "(default 0.3, or 1 - --central-fraction when that is smaller: --central-fraction 1 "
                        "alone gives an all-central set; both given must sum to <= 1)")
    p.add_argument("--grazing-angle", type=finite_float, default=None,
                   help="smallest incidence angle of the grazing rows, degrees (default 60)")
    p.add_argument("--max-offset", type=finite_float, default=None,
                   help="largest impact offset b/(r1+r2) of oblique impacts, in [0, 1) (default sin 89.8 deg)")
    p.add_argument("--slow-fraction", type=finite_float, default=None,
                   help="fraction of rows with |g| log-uniform in [--min-relative-speed, |g|] (default 0.3)")
    p.add_argument("--min-relative-speed", type=finite_float, default=None,
                   help="smallest relative speed |v1 - v2|, m/s (default 0.01)")
    p.add_argument("--min-normal-speed", type=finite_float, default=None,
                   help="smallest normal approach speed, m/s (default 1e-3; the paper-like set 0.05)")
    p.add_argument("--spin-fraction", type=finite_float, default=0.0,
                   help="fraction of rows whose spheres spin before the impact, in [0, 1] (default 0: spinless). "
                        "The training set of a `--form contact_spin` model, for the engine's particle_spin "
                        "(e.g. 0.7)")
    p.add_argument("--spin-ratio", type=finite_float, default=1.5,
                   help="largest surface speed r|omega| of a spinning sphere, in units of the relative speed "
                        "(default 1.5)")
    p.add_argument("--dt-factor", type=finite_float, default=0.5,
                   help="DEM time step as a fraction of the eq. (12) stable step, in (0, 1] (default 0.5)")
    add_material_options(p)
    p.add_argument("--restitution", type=finite_float, default=0.9, help="normal restitution e (default 0.9)")
    p.add_argument("--friction", type=finite_float, default=0.3, help="sliding friction mu (default 0.3)")
    p.add_argument("--overwrite", action="store_true", help="delete an existing --out first")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_json_flag(p)
    return p


def _stored_chunk_size(out: str) -> int | None:
    import json
    from pathlib import Path

    meta = Path(out) / "zarr.json"
    if not meta.exists():
        return None
    try:
        return int(json.loads(meta.read_text())["attributes"]["chunk_size"])
    except (ValueError, KeyError, TypeError):
        return None


def _number_list(flag: str, text: str, *, positive: bool) -> tuple[float, ...]:
    """``A,B,...`` -> floats, each finite and > 0 (``positive``) or >= 0; a ConfigError names ``flag``."""
    import math

    from hel_warp.errors import ConfigError

    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"{flag} must be numbers separated by commas (got {text!r})") from None
    bad = [v for v in values if not math.isfinite(v) or (v <= 0 if positive else v < 0)]
    if bad:
        raise ConfigError(f"{flag} values must be finite and {'> 0' if positive else '>= 0'} (got {text!r})")
    return values


def _size_options(args) -> tuple[float, float | None, dict]:
    """(diameter, diameter_std, make_spec mixture keywords) from --diameter/--diameter-std, --diameters/
    --diameter-stds/--mass-fractions, or the deprecated --mixture (a warning on stderr)."""
    import sys

    import numpy as np

    from hel_warp.errors import ConfigError
    from surrogate.configurations import paper_diameter_std

    if args.mixture is not None and args.diameters is not None:
        raise ConfigError("give --diameters (or the deprecated --mixture), not both")
    if args.diameters is None:
        if args.diameter_stds is not None or args.mass_fractions is not None:
            raise ConfigError("--diameter-stds and --mass-fractions go with --diameters D1,D2")
        diameter = 315e-6 if args.diameter is None else args.diameter
        if args.mixture is None:
            return diameter, args.diameter_std, {}
        print("hel-warp dataset: warning: --mixture is deprecated: it draws each particle's size with equal chance "
              "(pair types 1/4, 1/2, 1/4); use --diameters D1,D2 --mass-fractions W1,W2 for the pair types of a "
              "mixture", file=sys.stderr)
        return diameter, args.diameter_std, {"mixture_diameters": _number_list("--mixture", args.mixture,
                                                                                positive=True)}
    if args.diameter is not None or args.diameter_std is not None:
        raise ConfigError("--diameters replaces --diameter and --diameter-std (give the stds with --diameter-stds)")
    diameters = _number_list("--diameters", args.diameters, positive=True)
    if len(diameters) < 2:
        raise ConfigError(f"--diameters needs at least two sizes (got {args.diameters!r}); one size is --diameter")
    if len(set(diameters)) != len(diameters):
        raise ConfigError(f"--diameters lists a size twice ({args.diameters!r})")
    if args.diameter_stds is not None:
        stds = _number_list("--diameter-stds", args.diameter_stds, positive=False)
    else:
        stds = tuple(paper_diameter_std(d) for d in diameters)
        if None in stds:
            raise ConfigError(f"no size distribution known for {args.diameters!r} (the paper gives 315e-6 and "
                              "475e-6); give --diameter-stds")
    if len(stds) != len(diameters):
        raise ConfigError(f"--diameter-stds has {len(stds)} values for {len(diameters)} --diameters")
    if args.mass_fractions is not None:
        fractions = _number_list("--mass-fractions", args.mass_fractions, positive=True)
        if len(fractions) != len(diameters):
            raise ConfigError(f"--mass-fractions has {len(fractions)} values for {len(diameters)} --diameters")
        if abs(sum(fractions) - 1.0) > 1e-6:
            raise ConfigError(f"--mass-fractions must sum to 1 (got {args.mass_fractions!r}, sum {sum(fractions):g})")
    else:
        fractions = tuple(1.0 / len(diameters) for _ in diameters)
    # the set's one-size summary: the number-weighted mean and standard deviation of the mixture's sizes
    mu, sd, w = (np.asarray(v, float) for v in (diameters, stds, fractions))
    x = w / (mu**3 + 3.0 * mu * sd**2)
    x /= x.sum()
    mean = float((x * mu).sum())
    std = float(np.sqrt((x * (sd**2 + mu**2)).sum() - mean**2))
    return mean, std, {"mixture_diameters": diameters, "mixture_diameter_stds": stds,
                       "mixture_mass_fractions": fractions}


def run(args) -> int:
    from hel_warp._warp import init_warp
    from hel_warp.material import Material
    from surrogate.configurations import paper_spec_options
    from surrogate.dataset import DEFAULT_CHUNK_SIZE, build_dataset, make_spec

    init_warp()  # no greeting or per-module load lines around the progress bar
    chunk_size = args.chunk_size
    if chunk_size is None:
        chunk_size = (None if args.overwrite else _stored_chunk_size(args.out)) or DEFAULT_CHUNK_SIZE
    material = Material(density=args.density, youngs_modulus=args.youngs, poisson_ratio=args.poisson,
                        restitution=args.restitution, friction=args.friction)
    offsets = paper_spec_options() if args.paper_set else {}
    for name in ("central_fraction", "grazing_fraction", "grazing_angle", "max_offset", "slow_fraction",
                 "min_relative_speed", "min_normal_speed"):
        if getattr(args, name) is not None:
            offsets[name] = getattr(args, name)
    diameter, diameter_std, mixture = _size_options(args)
    spec = make_spec(samples=args.samples, seed=args.seed, diameter=diameter, diameter_std=diameter_std,
                     density_std=args.density_std, material=material, contact_model=args.model,
                     chunk_size=chunk_size, dt_factor=args.dt_factor, spin_fraction=args.spin_fraction,
                     spin_ratio=args.spin_ratio, **mixture, **offsets)
    summary = build_dataset(args.out, spec, scheduler=args.scheduler, overwrite=args.overwrite,
                            progress=not args.no_progress and not args.json)
    emit(summary, args.json, [
        f"data set {summary['out']}: {summary['samples']} configurations in {summary['chunks']} chunks "
        f"({summary['computed_chunks']} computed now{', resumed' if summary['resumed'] else ''})",
        f"dataset_hash {summary['dataset_hash']}",
        f"total time {summary['seconds']:.2f} s",
    ])
    return 0
