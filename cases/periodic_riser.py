"""Periodic riser: the suspension of a circulating bed's riser in a triply periodic box, tiled to any size.

The riser benchmark MFIX-Exa uses for its performance figures (BENCH04 "riser flow"; Liu et al. 2016,
NREL/TP-2C00-65637). One tile is a triply periodic box of 0.8 x 10 x 0.8 mm (x, y, z; y is the riser's axis,
gravity along -y) on 4 x 50 x 4 cubic cells of 0.2 mm, holding 224 spheres of d = 100 um, rho_p = 2000 kg/m^3
(solids fraction eps_s = 224 (pi d^3 / 6) / V = 0.01833), in a gas of rho_f = 1.0 kg/m^3 and mu = 2e-5 Pa s
(laminar: no sub-grid viscosity). ``--tiles K`` repeats the tile 2^K times along x and along z, 4^K tiles:
K = 5 is 229,376 particles on 128 x 50 x 128 cells. ``--particles-per-parcel W`` carries them as weighted parcels
(224 4^K / W parcels).

Driving pressure gradient. The gas is driven along +y by an imposed mean gradient of the modified pressure
p' = p - rho_f g . x (``Gas(mean_pressure_gradient=...)``): dp'/dy = -(rho_p - rho_f) eps_s |g| = -359.3 Pa/m,
i.e. 3.59 Pa over the tile's 10 mm. In a periodic box nothing else holds the mixture: the total axial momentum
of gas and particles changes at V (-dp'/dy - (rho_p - rho_f) eps_s |g|), so only this value, the suspension's
buoyant weight, gives a statistically steady state (the mixture's centre of mass at rest, the gas rising
through the falling solids at the slip velocity). The benchmark's 2 Pa over 10 mm (200 Pa/m) is a performance
setting: below the weight, the whole suspension would accelerate downwards without end. Starting from rest, the
gas rises through the settling solids (at K = 1 after 0.1-0.2 s: gas +0.48 m/s, solids -2.4 cm/s; the mixture's
momentum stays near zero, its residue ~1 % of the weight's impulse: parcels feel the interpolated pressure
gradient, not the transpose of the deposit); the slip velocity is Galilean invariant, so a net up-flow would not
change it.

Collision models (``--collisions``): ``none``; ``ktgf`` (the HEL granular pressure); ``surrogate`` (HELSCM:
swept detection at one particle per parcel, cell detection for weighted parcels; ``--model`` a contact-form
model for these particles, or without it one built on first use and cached); ``dem`` (the CFD-DEM reference).
The reference's contact is the benchmark's linear spring-dashpot: k_n = 10 N/m, e = 0.8, no friction
(``kernels.hertz.MODEL_LINEAR``, the dashpot calibrated for e = 0.8 with the clipped force), at a DEM step of
a twentieth of its contact duration pi sqrt(m*/k_n) = 22.7 us. The material's Young's modulus (which the linear
DEM does not use) is the Hertz modulus of the same contact duration at a 1 m/s approach, E = 1.08 MPa (nu = 0.3),
so that the surrogate's data set of Hertz impacts and the DEM's eq. (12) step describe the same soft spheres;
frictionless spheres leave a collision with (1 + e) m* g_n whatever the law, so the surrogate's outcomes and the
reference's agree.

Summary (``OUT/summary.json``, ``--json``): beside every case's keys (``particles``, ``parcels``,
``fluid_cells``, ``steps``, ``wall_clock_s``: the steps only, no compilation, ``parcel_steps_per_second``):
``slip_velocity`` (m/s: the eps_f-weighted mean gas minus the mass-weighted mean solids axial velocity, averaged
over samples in the second half of the run), ``solids_flux`` (kg/m^2/s: the solids' axial momentum per box
volume, rho_p <eps_s v_s>, second half; up is positive), ``solids_fraction_variance`` (the variance of the cells'
eps_s over the cells and the second half's samples: clustering; ``solids_fraction_variance_normalised`` divides
it by the mean eps_s squared), ``launches_per_step``, ``graph_launches_per_step`` and ``device_reads_per_step``
(medians over the steady steps, ``hel_warp.runs.counters``), ``device_bytes`` and ``bytes_per_particle`` (the Warp
arrays the run holds), ``pressure_gradient`` (Pa/m), ``solids_fraction``.

    python cases/periodic_riser.py --collisions ktgf --tiles 1 --dt 1e-4 --end-time 0.05 --out runs/riser_ktgf --json
    python cases/periodic_riser.py --collisions dem --tiles 1 --dt 1e-4 --end-time 0.05 --out runs/riser_dem
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

if str(Path(__file__).resolve().parents[1]) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hel_warp import case as hc  # noqa: E402

TILE = (0.8e-3, 10e-3, 0.8e-3)
"""One tile's box, m (x, y = riser axis, z)."""
TILE_CELLS = (4, 50, 4)
"""Gas cells per tile (0.2 mm cubes)."""
TILE_PARTICLES = 224
"""Spheres per tile."""
DIAMETER = 100e-6
"""Particle diameter, m."""
PARTICLE_DENSITY = 2000.0
"""rho_p, kg/m^3."""
GAS_DENSITY = 1.0
"""rho_f, kg/m^3."""
GAS_VISCOSITY = 2.0e-5
"""mu_f, Pa s."""
GRAVITY = 9.80665
"""|g|, m/s^2, along -y."""
LINEAR_STIFFNESS = 10.0
"""k_n of the reference's linear spring-dashpot, N/m."""
RESTITUTION = 0.8
"""Normal restitution of particle-particle impacts."""
POISSON = 0.3
DEM_STEPS_PER_CONTACT = 20
"""DEM sub-steps per linear contact duration."""
MAX_TILES = 8
"""--tiles at most (K = 8: 14.7 million particles)."""


def particle_mass() -> float:
    return PARTICLE_DENSITY * math.pi / 6.0 * DIAMETER**3


def solids_fraction() -> float:
    """eps_s of every tiling: 224 spheres per tile volume."""
    return TILE_PARTICLES * math.pi / 6.0 * DIAMETER**3 / float(np.prod(TILE))


def pressure_gradient() -> float:
    """dp'/dy, Pa/m, that holds the suspension's buoyant weight (module docstring): negative, gas driven up."""
    return -(PARTICLE_DENSITY - GAS_DENSITY) * solids_fraction() * GRAVITY


def contact_duration() -> float:
    """Elastic duration pi sqrt(m*/k_n) of the linear contact of two equal spheres, s."""
    return math.pi * math.sqrt(0.5 * particle_mass() / LINEAR_STIFFNESS)


def equivalent_youngs_modulus(speed: float = 1.0) -> float:
    """E (Pa, at Poisson ratio POISSON) whose Hertz contact lasts ``contact_duration()`` at ``speed`` m/s:
    t_c = 2.868 (m*^2 / (R* E*^2 v))^(1/5) (Johnson 1985), E* = E / (2 (1 - nu^2)) for equal spheres."""
    m_eff, r_eff = 0.5 * particle_mass(), 0.25 * DIAMETER
    e_eff = math.sqrt(m_eff**2 / (r_eff * speed * (contact_duration() / 2.868) ** 5))
    return 2.0 * (1.0 - POISSON**2) * e_eff


def material() -> hc.Material:
    return hc.Material(density=PARTICLE_DENSITY, youngs_modulus=equivalent_youngs_modulus(), poisson_ratio=POISSON,
                       restitution=RESTITUTION, friction=0.0, wall_restitution_normal=RESTITUTION,
                       wall_restitution_tangential=1.0)


def options(groups) -> None:
    groups.case.add_argument("--tiles", type=int, default=0,
                             help="K: the tile repeated 2^K times along x and z (4^K tiles, 224 4^K particles; "
                                  "default 0)")
    groups.output.add_argument("--samples", type=int, default=50,
                               help="statistics samples over the second half of the run (default 50)")


def check_tiles(tiles: int) -> None:
    from hel_warp.errors import ConfigError

    if not 0 <= tiles <= MAX_TILES:
        raise ConfigError(f"--tiles must lie in 0..{MAX_TILES} (got {tiles}); K tiles the box 4^K times")


def build(args):
    """The tiled periodic box, filled at random (no overlaps) with 224 4^K spheres at rest, the gas at rest."""
    from hel_warp.case import weights_of
    from hel_warp.errors import ConfigError

    check_tiles(args.tiles)
    if args.samples < 1:
        raise ConfigError(f"--samples must be >= 1 (got {args.samples})")
    repeat = 2**args.tiles
    hi = (TILE[0] * repeat, TILE[1], TILE[2] * repeat)
    cells = (TILE_CELLS[0] * repeat, TILE_CELLS[1], TILE_CELLS[2] * repeat)
    weight = weights_of(args)[0]
    real = TILE_PARTICLES * 4**args.tiles
    if weight > real:
        raise ConfigError(f"--particles-per-parcel {weight} exceeds the {real} particles of --tiles {args.tiles}")
    gas = hc.Gas(density=GAS_DENSITY, viscosity=GAS_VISCOSITY, smagorinsky_constant=0.0,
                 mean_pressure_gradient=(0.0, pressure_gradient(), 0.0), exchange_pressure=False,
                 inlet_superficial=False)
    flow = hc.Flow("periodic_riser", lo=(0.0, 0.0, 0.0), hi=hi, cells=cells, periodic=(True, True, True),
                   gravity=(0.0, -GRAVITY, 0.0), gas=gas,
                   collision_defaults={"dem": {"dt_dem": contact_duration() / DEM_STEPS_PER_CONTACT,
                                               "max_speed": 2.0}},
                   attrs={"riser": {"tiles": int(args.tiles), "tile": list(TILE), "tile_cells": list(TILE_CELLS),
                                    "pressure_gradient": pressure_gradient(), "solids_fraction": solids_fraction(),
                                    "linear_stiffness": LINEAR_STIFFNESS, "restitution": RESTITUTION}})
    flow.species("solids", DIAMETER, material=material(), weight=float(weight))
    flow.fill("solids", ((0.0, 0.0, 0.0), hi), count=real, packing="random")
    return flow


# ------------------------------------------------------------------------------------------ observers
def use_linear_contact(strategy) -> None:
    """The ``dem`` strategy's particle-particle contact made the benchmark's linear spring-dashpot."""
    from hel_warp.collisions.contact_law import damping_coefficient
    from kernels.hertz import MODEL_LINEAR

    strategy.params.model = MODEL_LINEAR
    strategy.params.linear_stiffness = LINEAR_STIFFNESS
    strategy.params.normal_damping = float(damping_coefficient(RESTITUTION, "linear"))
    strategy.params.friction = 0.0


class LinearContacts:
    """Gives the ``dem`` reference the benchmark's linear spring-dashpot once the simulation is built: the case
    API's ``dem`` strategy sets up Hertz contacts from the material, and its kernels also hold the linear law
    (``kernels.hertz.MODEL_LINEAR``) with k_n and a damping calibrated for e."""

    def bind(self, sim) -> None:
        if sim.settings.collisions != "dem":
            return
        use_linear_contact(sim.solver.collision)

    def after_step(self, solver) -> None:
        pass


def momentum(solver) -> dict:
    """Axial (y) momentum of the gas (faces: rho_f eps_f u_y h^3, the periodic face counted once) and of the
    particles (sum of w m v_y), kg m/s."""
    gas = solver.gas
    h3 = solver.grid.spacing**3
    u = gas.face_velocity.y.numpy()[:, :-1, :].astype(np.float64)
    eps = gas.face_eps.y.numpy()[:, :-1, :].astype(np.float64)
    p = solver.pool.particles
    alive = p.alive.numpy().astype(bool)
    r = p.radius.numpy()[alive].astype(np.float64)
    m = p.weight.numpy()[alive] * p.density.numpy()[alive] * math.pi / 6.0 * (2.0 * r) ** 3
    return {"gas": float(GAS_DENSITY * np.sum(eps * u) * h3),
            "solids": float(np.sum(m * p.v.numpy()[alive, 1].astype(np.float64)))}


class Statistics:
    """Samples, in the second half of the run, the mean gas and solids axial velocities, the solids' axial
    momentum and the cells' eps_s (the reads paused for the launch and read counters); also the per-step
    launch and read counts (``hel_warp.runs.counters.PerStep``)."""

    def __init__(self, end_time: float, dt: float, samples: int):
        from hel_warp.runs.counters import PerStep

        total = max(1, int(round(end_time / dt)))
        self.first = total // 2
        span = max(1, total - self.first)
        self.every = max(1, span // max(1, samples))
        self.rows = []
        self.eps_var = []
        self.eps_mean = []
        self.counts = PerStep()

    def after_step(self, solver) -> None:
        from hel_warp.runs import counters

        self.counts.after_step(solver)
        step = solver.step_count
        if step <= self.first or (step - self.first) % self.every:
            return
        with counters.paused():
            eps_s = solver.fields.cell_eps_s.numpy().astype(np.float64)
            eps_f = solver.gas.cell_eps_f.numpy().astype(np.float64)
            u_g = solver.gas.cell_velocity.numpy()[..., 1].astype(np.float64)
            mom = momentum(solver)
            p = solver.pool.particles
            alive = p.alive.numpy().astype(bool)
            r = p.radius.numpy()[alive].astype(np.float64)
            m = p.weight.numpy()[alive] * p.density.numpy()[alive] * (2.0 * r) ** 3
            v_s = float(np.sum(m * p.v.numpy()[alive, 1]) / np.sum(m))
        volume = float(np.prod(np.asarray(solver.grid.shape) * solver.grid.spacing))
        gas_mean = float(np.sum(eps_f * u_g) / np.sum(eps_f))
        self.rows.append((solver.time, gas_mean, v_s, mom["solids"] / volume))
        self.eps_var.append(float(np.var(eps_s)))
        self.eps_mean.append(float(np.mean(eps_s)))

    def state(self) -> dict:
        return {"rows": np.asarray(self.rows, np.float64).reshape(-1, 4), "eps_var": np.asarray(self.eps_var),
                "eps_mean": np.asarray(self.eps_mean)}

    def set_state(self, state: dict) -> None:
        if "rows" in state:
            self.rows = [tuple(r) for r in np.asarray(state["rows"])]
            self.eps_var = list(np.asarray(state["eps_var"]))
            self.eps_mean = list(np.asarray(state["eps_mean"]))


def observers(args, flow) -> list:
    from hel_warp.runs import counters

    counters.start()  # stopped in summary(); the counts are per step, so what came before does not matter
    return [LinearContacts(), Statistics(args.end_time, args.dt, args.samples)]


def device_bytes(device) -> int:
    """Bytes of the Warp arrays that own memory on ``device`` (each allocation once)."""
    import gc

    import warp as wp

    device = wp.get_device(device)
    seen = {}
    for obj in gc.get_objects():
        if isinstance(obj, wp.array) and getattr(obj, "deleter", None) is not None and obj.ptr and \
                obj.device == device:
            seen[obj.ptr] = max(seen.get(obj.ptr, 0), int(obj.capacity))
    return int(sum(seen.values()))


def summary(run) -> dict:
    from hel_warp.runs import counters

    stats = run.solver.observers[1]
    counts = stats.counts.medians()
    counters.stop()
    rows = np.asarray(stats.rows, np.float64).reshape(-1, 4)
    eps_mean = float(np.mean(stats.eps_mean)) if stats.eps_mean else None
    variance = float(np.mean(stats.eps_var)) if stats.eps_var else None
    if stats.eps_mean:  # pooled over cells and samples: the mean of the variances plus the variance of the means
        variance += float(np.var(stats.eps_mean))
    used = device_bytes(run.args.device)
    particles = float(np.sum(run.solver.pool.particles.weight.numpy()[run.solver.pool.particles.alive.numpy() > 0]))
    out = {
        "tiles": int(run.args.tiles), "pressure_gradient": pressure_gradient(), "solids_fraction": solids_fraction(),
        "slip_velocity": float(np.mean(rows[:, 1] - rows[:, 2])) if len(rows) else None,
        "gas_velocity": float(np.mean(rows[:, 1])) if len(rows) else None,
        "solids_velocity": float(np.mean(rows[:, 2])) if len(rows) else None,
        "solids_flux": float(np.mean(rows[:, 3])) if len(rows) else None,
        "solids_fraction_variance": variance,
        "solids_fraction_variance_normalised": variance / eps_mean**2 if variance is not None and eps_mean else None,
        "statistics_samples": int(len(rows)),
        "statistics_from": float(rows[0, 0]) if len(rows) else None,
        "series": {"time": rows[:, 0].tolist(), "slip_velocity": (rows[:, 1] - rows[:, 2]).tolist(),
                   "solids_fraction_variance": list(stats.eps_var)},
        "device_bytes": used, "bytes_per_particle": used / particles if particles else None,
        "momentum": momentum(run.solver),
        **counts,
    }
    strategy = run.solver.collision
    if getattr(strategy, "name", None) == "dem":
        out["dem_step"] = float(strategy.dt_dem or 0.0)
        out["dem_contact"] = {"model": "linear", "k_n": LINEAR_STIFFNESS, "restitution": RESTITUTION,
                              "contact_duration": contact_duration()}
    return out


def check(run) -> list:
    """Physical facts: every parcel alive and inside the periodic box, the real particles those of the fill."""
    p = run.solver.pool.particles
    alive = p.alive.numpy().astype(bool)
    x = p.x.numpy()[alive]
    hi = np.asarray(run.sim.flow.hi)
    errors = []
    expected = TILE_PARTICLES * 4**run.args.tiles
    real = float(np.sum(p.weight.numpy()[alive]))
    if abs(real - expected) > 0.5 * float(np.max(p.weight.numpy()[alive])):
        errors.append(f"{real:g} real particles alive, the fill placed {expected}")
    if np.any(x < 0.0) or np.any(x >= hi * (1.0 + 1e-6)):
        errors.append("a parcel lies outside the periodic box")
    return errors


def report(run, s: dict) -> str:
    slip = "n/a" if s["slip_velocity"] is None else f"{s['slip_velocity']:.4f} m/s"
    return (f"periodic_riser [{s['collision_model']}] K = {s['tiles']}: {s['parcels']} parcels, {s['steps']} steps, "
            f"{s['parcel_steps_per_second'] or 0:.3g} parcel-steps/s, slip {slip}, "
            f"launches/step {s['launches_per_step']}, reads/step {s['device_reads_per_step']} -> {run.out}")


CASE = hc.Case("periodic_riser", build, doc=__doc__, options=options, summary=summary, check=check,
               observers=observers, report=report, models=("none", "ktgf", "surrogate", "dem"),
               defaults={"dt": 1e-4, "end_time": 0.02})


def main(argv=None) -> int:
    return CASE.main(argv)


if __name__ == "__main__":
    sys.exit(main())
