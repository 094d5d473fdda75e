"""``hel-warp particle``: terminal velocity, response time and Stokes number of one particle in still gas.

Integrates eq. (4) for a single particle released from rest (no pressure-gradient and collision
terms, as the paper's section 8 does) with the engine's own push kernel and semi-implicit drag.

Stokes number: St = t_RT / t_F (particle response time over flow time). The paper writes
St = t_F / t_RT in section 8 but reports St > 1 with t_RT = 0.25 s for 475 um, which only the
ratio t_RT / t_F gives; we use t_RT / t_F, the usual definition.
"""

from __future__ import annotations

from hel_warp.cli.commands._common import add_json_flag, emit, finite_float


def add_parser(subparsers):
    p = subparsers.add_parser("particle", help="terminal velocity and response time of one particle (eq. 4)",
                              description=__doc__)
    p.add_argument("--diameter", type=finite_float, required=True, help="particle diameter, m")
    p.add_argument("--density", type=finite_float, required=True, help="particle density, kg/m^3")
    p.add_argument("--gas-density", type=finite_float, default=1.205, help="gas density, kg/m^3 (default 1.205)")
    p.add_argument("--gas-viscosity", type=finite_float, default=1.81e-5,
                   help="gas dynamic viscosity, Pa s (default 1.81e-5)")
    p.add_argument("--gravity", type=finite_float, default=9.80665, help="|g|, m/s^2 (default 9.80665)")
    p.add_argument("--drag", choices=("schiller-naumann", "gidaspow", "wen-yu"), default="schiller-naumann",
                   help="drag law (default schiller-naumann; a lone particle sees eps_s = 0, where gidaspow "
                        "and wen-yu reduce to it)")
    p.add_argument("--dt", type=finite_float, default=1e-3, help="time step, s (default 1e-3)")
    p.add_argument("--flow-time", type=finite_float, default=None,
                   help="characteristic flow time t_F, s; prints stokes_number = response_time / flow_time")
    add_json_flag(p)
    return p


def run(args) -> int:
    from hel_warp.cli.commands._common import require
    from hel_warp.errors import require_positive

    require_positive("--diameter", args.diameter, "m")
    require_positive("--density", args.density, "kg/m^3")
    require_positive("--gas-density", args.gas_density, "kg/m^3")
    require_positive("--gas-viscosity", args.gas_viscosity, "Pa s")
    require_positive("--gravity", args.gravity, "m/s^2")
    require_positive("--dt", args.dt, "s")
    if args.flow_time is not None:
        require_positive("--flow-time", args.flow_time, "s")
    require(args.density > args.gas_density,
            f"--density {args.density} kg/m^3 must exceed --gas-density {args.gas_density} kg/m^3 "
            "for the particle to settle")
    require(args.dt <= 0.1, f"--dt {args.dt} s is too long for a settling particle; give at most 0.1 s")

    from hel_warp._warp import init_warp

    init_warp()
    from hel_warp.parcels.coupling import PushConfig, single_particle_response

    config = PushConfig(drag=args.drag, fluid_density=args.gas_density, fluid_viscosity=args.gas_viscosity,
                        gravity=(0.0, 0.0, -args.gravity))
    r = single_particle_response(diameter=args.diameter, density=args.density, config=config, dt=args.dt)
    result = {"diameter": args.diameter, "density": args.density, "drag": args.drag, "dt": args.dt,
              "terminal_velocity": r["terminal_velocity"], "response_time": r["response_time"],
              "steps": r["steps"], "converged": r["converged"]}
    lines = [f"terminal velocity  {r['terminal_velocity']:.5g} m/s",
             f"response time      {r['response_time']:.5g} s  (63.2 % of terminal speed from rest)"]
    if args.flow_time is not None:
        result["flow_time"] = args.flow_time
        result["stokes_number"] = r["response_time"] / args.flow_time
        lines.append(f"Stokes number      {result['stokes_number']:.4g}  (= t_RT / t_F)")
    if not r["converged"]:
        lines.append("warning: speed still changing at the end of the run; terminal velocity is approximate")
    emit(result, args.json, lines)
    return 0
