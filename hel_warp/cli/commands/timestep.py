"""``hel-warp timestep``: the Rayleigh, Hertz and Cundall time steps and the chosen DEM step (eqs. 12-15)."""

from __future__ import annotations

from hel_warp.cli.commands._common import add_json_flag, add_material_options, emit, finite_float


def add_parser(subparsers):
    p = subparsers.add_parser("timestep", help="DEM time steps of eqs. (12)-(15) for a material and size",
                              description=__doc__)
    p.add_argument("--diameter", type=finite_float, default=315e-6, help="particle diameter, m (default 315e-6)")
    add_material_options(p)
    p.add_argument("--max-speed", type=finite_float, default=20.0, help="V_max of the Hertz step, m/s (default 20)")
    p.add_argument("--normk", type=finite_float, default=0.001, help="Cundall penalty NORMK (default 0.001)")
    p.add_argument("--factor", type=finite_float, default=0.2, help="safety factor of eq. (12) (default 0.2)")
    add_json_flag(p)
    return p


def run(args) -> int:
    from hel_warp.errors import require_positive
    from hel_warp.material import Material

    require_positive("--diameter", args.diameter, "m")
    material = Material(density=args.density, youngs_modulus=args.youngs, poisson_ratio=args.poisson)
    step = material.time_step(args.diameter / 2.0, max_speed=args.max_speed, normk=args.normk, factor=args.factor)
    result = {"diameter": args.diameter, **step.as_dict()}
    emit(result, args.json, [
        f"Rayleigh  {step.rayleigh:.4e} s",
        f"Hertz     {step.hertz:.4e} s   (V_max = {args.max_speed} m/s)",
        f"Cundall   {step.cundall:.4e} s   (NORMK = {args.normk})",
        f"chosen    {step.chosen:.4e} s   = {args.factor} x min, eq. (12)",
    ])
    return 0
