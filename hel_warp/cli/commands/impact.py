"""``hel-warp impact``: one isolated binary impact (sphere–sphere or sphere–wall), Hertz–Mindlin or linear.

Geometry: the contact normal is z. Sphere 2 is centred at the origin (a wall is the plane z = 0);
sphere 1 starts just above it (z > 0), placed so that it first touches after about two time
steps with the normal exactly -z (1 -> 2), never overlapping. Its velocity must therefore point
down relative to body 2 (``vz1 - vz2 < 0``). The wall is rigid unless --youngs2 / --poisson2 give
it a material. Runs ``hel_warp.collisions.impact.simulate_pairs`` with a batch of one.
"""

from __future__ import annotations

from hel_warp.cli.commands._common import add_json_flag, emit, finite_float, vector3


def add_parser(subparsers):
    from hel_warp.material import Material

    d = Material()
    p = subparsers.add_parser("impact", help="one isolated binary impact (sphere-sphere or sphere-wall)",
                              description=__doc__)
    p.add_argument("--target", choices=("sphere", "wall"), default="sphere", help="body 2 (default sphere)")
    p.add_argument("--diameter", type=finite_float, default=315e-6, help="diameter of sphere 1, m (default 315e-6)")
    p.add_argument("--diameter2", type=finite_float, default=None, help="diameter of sphere 2, m (default: --diameter)")
    p.add_argument("--density", type=finite_float, default=d.density, help="density of sphere 1, kg/m^3 (default 1000)")
    p.add_argument("--density2", type=finite_float, default=None, help="density of sphere 2 (default: --density)")
    p.add_argument("--youngs", type=finite_float, default=d.youngs_modulus, help="Young's modulus of sphere 1, Pa (default 5e8)")
    p.add_argument("--youngs2", type=finite_float, default=None,
                   help="Young's modulus of body 2, Pa (default: sphere 1's; a wall is rigid unless given)")
    p.add_argument("--poisson", type=finite_float, default=d.poisson_ratio, help="Poisson ratio of sphere 1 (default 0.4)")
    p.add_argument("--poisson2", type=finite_float, default=None, help="Poisson ratio of body 2 (default: sphere 1's)")
    p.add_argument("--restitution", type=finite_float, default=d.restitution,
                   help="normal restitution coefficient e in (0, 1] (default 0.9)")
    p.add_argument("--friction", type=finite_float, default=d.friction, help="Coulomb friction coefficient (default 0.3)")
    p.add_argument("--velocity", type=vector3, default=(0.0, 0.0, -1.0), metavar="VX,VY,VZ",
                   help="velocity of sphere 1, m/s (default 0,0,-1)")
    p.add_argument("--velocity2", type=vector3, default=None, metavar="VX,VY,VZ",
                   help="velocity of sphere 2, m/s (default 0,0,0; sphere target only)")
    p.add_argument("--omega", type=vector3, default=(0.0, 0.0, 0.0), metavar="WX,WY,WZ",
                   help="angular velocity of sphere 1, rad/s (default 0,0,0)")
    p.add_argument("--omega2", type=vector3, default=None, metavar="WX,WY,WZ",
                   help="angular velocity of sphere 2, rad/s (default 0,0,0; sphere target only)")
    p.add_argument("--dt", type=finite_float, default=None,
                   help="time step, s (default: the eq. (12) stable step of the smaller sphere, reduced where "
                        "needed to resolve the contact with 40 steps); a larger one than eq. (12) is refused")
    p.add_argument("--model", choices=("hertz", "linear"), default="hertz", help="normal contact model (default hertz)")
    add_json_flag(p)
    return p


def run(args) -> int:
    import numpy as np

    from hel_warp._warp import init_warp

    init_warp()  # stdout carries the result (one JSON object with --json): no greeting or module-load lines

    from hel_warp.errors import ConfigError, require_positive
    from hel_warp.collisions.impact import place_just_apart, simulate_pairs, stable_time_step

    wall = args.target == "wall"
    if wall:
        for name in ("diameter2", "density2", "velocity2", "omega2"):
            if getattr(args, name) is not None:
                raise ConfigError(f"--{name} applies to --target sphere only; a wall is fixed and rigid-bodied")
    require_positive("--diameter", args.diameter, "m")
    diameter2 = args.diameter if args.diameter2 is None else args.diameter2
    require_positive("--diameter2", diameter2, "m")
    r1, r2 = 0.5 * args.diameter, 0.5 * diameter2
    density2 = args.density if args.density2 is None else args.density2
    if wall:
        youngs2 = np.inf if args.youngs2 is None else args.youngs2
        poisson2 = args.poisson if args.poisson2 is None else args.poisson2
    else:
        youngs2 = args.youngs if args.youngs2 is None else args.youngs2
        poisson2 = args.poisson if args.poisson2 is None else args.poisson2
    v1 = np.array(args.velocity, dtype=np.float64)
    v2 = np.zeros(3) if args.velocity2 is None else np.array(args.velocity2, dtype=np.float64)
    w1 = np.array(args.omega, dtype=np.float64)
    w2 = np.zeros(3) if args.omega2 is None else np.array(args.omega2, dtype=np.float64)
    approach = -(v1[2] - v2[2])
    if not approach > 0.0:
        raise ConfigError(f"sphere 1 must move towards {'the wall' if wall else 'sphere 2'} along -z "
                          f"(vz1 - vz2 = {-approach:g} m/s): a receding pair would have to start overlapped; "
                          "give --velocity with a negative z component")

    common = dict(v1=v1, v2=v2, omega1=w1, omega2=w2, radius1=r1, radius2=r2, density1=args.density,
                  density2=density2, youngs1=args.youngs, poisson1=args.poisson, youngs2=youngs2,
                  poisson2=poisson2, restitution=args.restitution, friction=args.friction, model=args.model,
                  target=args.target)
    # door checks named after the options (simulate_pairs checks again, per pair)
    for flag, value, unit in (("--density", args.density, "kg/m^3"), ("--density2", density2, "kg/m^3"),
                              ("--youngs", args.youngs, "Pa"),
                              ("--youngs2", 1.0 if youngs2 == np.inf else youngs2, "Pa")):
        require_positive(flag, value, unit)
    if not 0.0 < args.restitution <= 1.0:
        raise ConfigError(f"--restitution must lie in (0, 1] (got {args.restitution}); 1 is elastic")
    if args.friction < 0.0:
        raise ConfigError(f"--friction must be >= 0 (got {args.friction})")
    for flag, value in (("--poisson", args.poisson), ("--poisson2", poisson2)):
        if not -1.0 < value < 0.5:
            raise ConfigError(f"{flag} must lie in (-1, 0.5) (got {value}); 0.3-0.45 is typical for polymers")
    if args.dt is not None:
        require_positive("--dt", args.dt, "s")
    max_speed = max(20.0, float(np.linalg.norm(v1 - v2)))
    stable = float(stable_time_step(r1, args.density, args.youngs, args.poisson, max_speed))
    if not wall:
        stable = min(stable, float(stable_time_step(r2, density2, youngs2, poisson2, max_speed)))
    x1, x2 = place_just_apart(normal=(0.0, 0.0, -1.0), velocity1=v1, velocity2=v2, radius1=r1, radius2=r2,
                              target=args.target, dt=args.dt if args.dt is not None else stable)
    res = simulate_pairs(x1=x1, x2=x2, dt=args.dt, **common)
    u1, u2 = res.velocity1[0], res.velocity2[0]
    result = {
        "target": args.target,
        "model": args.model,
        "contact_duration": float(res.contact_duration[0]),
        "max_overlap": float(res.max_overlap[0]),
        "max_normal_force": float(res.max_normal_force[0]),
        "velocity_after": [float(c) for c in u1],
        "velocity2_after": [float(c) for c in u2],
        "omega_after": [float(c) for c in res.omega1[0]],
        "omega2_after": [float(c) for c in res.omega2[0]],
        "restitution_measured": float((u1[2] - u2[2]) / approach),
        "dt": float(res.dt[0]),
        "dt_stable": stable,
        "steps": int(res.steps[0]),
        "touched": bool(res.touched[0]),
        "separated": bool(res.separated[0]),
    }
    emit(result, args.json, [
        f"{args.model} impact of a {args.diameter:.3e} m sphere on {'a wall' if wall else 'a sphere'}",
        f"contact duration   {result['contact_duration']:.4e} s",
        f"max overlap        {result['max_overlap']:.4e} m",
        f"max normal force   {result['max_normal_force']:.4e} N",
        f"velocity after     {', '.join(f'{c:.6g}' for c in u1)} m/s",
        f"velocity2 after    {', '.join(f'{c:.6g}' for c in u2)} m/s",
        f"omega after        {', '.join(f'{c:.6g}' for c in res.omega1[0])} rad/s",
        f"omega2 after       {', '.join(f'{c:.6g}' for c in res.omega2[0])} rad/s",
        f"restitution        {result['restitution_measured']:.6f} (measured)",
        f"dt                 {result['dt']:.4e} s in {result['steps']} steps (eq. (12) stable: {stable:.4e} s)",
    ])
    return 0
