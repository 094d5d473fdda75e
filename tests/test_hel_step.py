"""The HEL step after the push: SDF wall reflection, scheduled injection, outlet removal; input checks;
the collision-strategy interface (optional ``advance`` replaces the push, optional ``counts``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hel_warp.errors import ConfigError, HelWarpError

E_N = E_T = 0.8  # Table 1 wall restitution (Material defaults)
BOX_HI = (0.012, 0.006, 0.010)  # closed box of fluid, m; floor at z = 0
H = 1.0e-3


def make_solver(x=None, v=None, *, capacity=None, radius=0.5e-3, density=8000.0, injectors=(), outlets=(),
                collision=None, gravity=(0.0, 0.0, -9.80665), walls=True, material=None, sort_every=0, dt=1e-3,
                wall_friction=None, wall_contact="point"):
    """A closed box of still air (grid = geometry, 12 x 6 x 10 cells of 1 mm) with parcels at ``x``."""
    import warp as wp

    from hel_warp.parcels.coupling import PushConfig
    from hel_warp.gas.solver import GasConfig, GasField, GasSolver
    from hel_warp.gas.grid import Box, Geometry, Grid
    from hel_warp.hel import HelConfig, HelSolver
    from hel_warp.material import Material
    from hel_warp.parcels.pool import ParcelPool

    grid = Grid(spacing=H, shape=tuple(int(round(b / H)) for b in BOX_HI))
    domain = Geometry(shapes=(Box(lo=(0.0, 0.0, 0.0), hi=BOX_HI),)).build(grid)
    push = PushConfig(drag="schiller-naumann", gravity=gravity)
    gas_solver = GasSolver(domain, GasConfig(density=push.fluid_density, viscosity=push.fluid_viscosity))
    gas = GasField(domain)
    n = 0 if x is None else len(x)
    pool = ParcelPool.empty(capacity or max(n, 1))
    if n:
        p = pool.particles
        p.x.assign(np.asarray(x, np.float32))
        p.v.assign(np.zeros((n, 3), np.float32) if v is None else np.asarray(v, np.float32))
        p.radius.assign(np.full(n, radius, np.float32))
        p.density.assign(np.full(n, density, np.float32))
        p.alive.assign(np.ones(n, np.int32))
        p.particle_id.assign(np.arange(n, dtype=np.int32))
        pool.used = n
    config = HelConfig(dt=dt, push=push, material=material or Material(), injectors=injectors,
                       outlets=outlets, walls=walls, sort_every=sort_every, wall_friction=wall_friction,
                       wall_contact=wall_contact)
    return HelSolver(pool=pool, gas_solver=gas_solver, gas=gas, config=config, collision=collision)


def test_wall_reflection_closed_form_in_one_step():
    """v' = -e_n v_n + e_t v_t and x' = x - (1 + e_n) d n for a parcel that crossed the floor (d = -z)."""
    solver = make_solver(x=[(0.004, 0.003, 0.0004)], v=[(0.3, 0.0, -1.0)], gravity=(0.0, 0.0, 0.0))
    p = solver.pool.particles
    solver.deposit(), solver.gas_step(), solver.interpolate(), solver.collide(), solver.push()
    x_pre, v_pre = p.x.numpy()[0].astype(np.float64), p.v.numpy()[0].astype(np.float64)
    assert x_pre[2] < 0.0  # the push carried the centre through the floor
    solver.remove_at_outlets()
    solver.reflect_at_walls()
    x_post, v_post = p.x.numpy()[0].astype(np.float64), p.v.numpy()[0].astype(np.float64)
    # float32 state: relative round-off ~1e-7
    np.testing.assert_allclose(v_post, [E_T * v_pre[0], E_T * v_pre[1], -E_N * v_pre[2]], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(x_post[:2], x_pre[:2], rtol=0, atol=1e-9)
    assert x_post[2] == pytest.approx(-E_N * x_pre[2], rel=1e-5)
    assert x_post[2] > 0.0
    assert solver.wall_hit_count() == 1


def test_dropped_parcel_rebounds_with_e_n_and_e_t_and_never_ends_in_the_wall():
    """Full steps in still air with gravity: at every wall hit the velocity leaving the reflection is the closed
    form of the one arriving (-e_n normal, e_t tangential); after every step the centre is in the fluid."""
    solver = make_solver(x=[(0.002, 0.003, 0.004)], v=[(0.1, 0.0, 0.0)])
    p = solver.pool.particles
    hits = []
    reflect = solver.reflect_at_walls

    def recording_reflect():
        v_in = p.v.numpy()[0].astype(np.float64)
        reflect()
        v_out = p.v.numpy()[0].astype(np.float64)
        if not np.array_equal(v_in, v_out):
            hits.append((v_in, v_out))

    solver.reflect_at_walls = recording_reflect
    lowest = math.inf
    for _ in range(80):
        solver.step()
        lowest = min(lowest, float(p.x.numpy()[0, 2]))
    assert lowest >= 0.0, f"the parcel ended inside the floor (z = {lowest})"
    assert len(hits) >= 2  # it bounced, and bounced again
    for v_in, v_out in hits:
        assert v_in[2] < 0.0 < v_out[2]
        assert v_out[2] == pytest.approx(-E_N * v_in[2], rel=1e-6)
        assert v_out[0] == pytest.approx(E_T * v_in[0], rel=1e-6)
    # first impact at the free-fall speed from 4 mm (sqrt(2 g h) = 0.280 m/s), to the step's O(dt g) accuracy
    assert -hits[0][0][2] == pytest.approx(math.sqrt(2 * 9.80665 * 0.004), abs=2 * 9.80665e-3)
    assert solver.wall_hit_count() == len(hits)


def test_grazing_wall_impact_loses_at_most_the_coulomb_share():
    # v = (5, 0, -0.1) m/s onto the floor, e_n = e_t = 0.8, mu = 0.3 (Material.friction): the bare e_t would
    # take 1.0 m/s of the tangential speed, more than mu times the normal impulse allows:
    # |dv_t| = mu (1 + e_n) |v_n| = 0.3 * 1.8 * 0.1 = 0.054 m/s.
    solver = make_solver(x=[(0.004, 0.003, 0.00005)], v=[(5.0, 0.0, -0.1)], gravity=(0.0, 0.0, 0.0))
    p = solver.pool.particles
    solver.deposit(), solver.gas_step(), solver.interpolate(), solver.collide(), solver.push()
    v_pre = p.v.numpy()[0].astype(np.float64)
    assert p.x.numpy()[0, 2] < 0.0
    solver.reflect_at_walls()
    v_post = p.v.numpy()[0].astype(np.float64)
    assert v_post[2] == pytest.approx(-E_N * v_pre[2], rel=1e-6)
    assert v_post[0] == pytest.approx(v_pre[0] - 0.3 * (1 + E_N) * abs(v_pre[2]), rel=1e-6)


@pytest.mark.parametrize("wall_friction", [None, 0.0])
def test_parcel_sliding_on_a_wall_slows_by_coulomb_friction_at_any_step(wall_friction):
    # A parcel resting on the floor (centre on the wall) launched along it at 0.25 m/s under gravity, in still
    # air, for T = 0.03 s at dt = 1e-3 and 1e-4 s. Gravity presses it into the floor every step or two. Momentum
    # along z is exact bookkeeping whatever the integrator: the floor's normal impulse per unit mass over the run is
    # J = g T + v_z(T) - v_z(0), v_z(0) = 0 (the z drag adds < 1e-5 m/s: |v_z| < 0.01 m/s at a rate of 0.08 /s).
    # Sliding throughout (mu (1 + e_n) |v_z| << v_x at every hit), the Coulomb cap takes mu times each normal
    # impulse from v_x, so v_x(T) = v0 - mu J - (drag loss), and the drag loss lies between 0 (gas dragged along
    # with the parcel) and the still-air Schiller-Naumann loss at the launch slip, v0 T F(v0) (F falls with the
    # slip): 6.2e-4 m/s here, 8000 kg/m^3 and 1 mm. Float32 state over 300 steps: 1e-5 m/s of round-off.
    # With the bare e_t (wall_friction = 0) each hit keeps 0.8 of v_x: at most v0 e_t^hits is left.
    v0, T, mu, g = 0.25, 0.03, 0.3, 9.80665
    rho_f, mu_f, d, rho_p = 1.205, 1.81e-5, 1e-3, 8000.0  # PushConfig's air; make_solver's parcel
    # Schiller & Naumann (1933): F = 18 mu_f (1 + 0.15 Re^0.687) / (rho_p d^2) per unit slip
    re = rho_f * v0 * d / mu_f
    drag_bound = v0 * T * 18.0 * mu_f * (1.0 + 0.15 * re**0.687) / (rho_p * d**2)
    for dt in (1e-3, 1e-4):
        solver = make_solver(x=[(0.001, 0.003, 1e-7)], v=[(v0, 0.0, 0.0)], dt=dt, wall_friction=wall_friction)
        for _ in range(int(round(T / dt))):
            solver.step()
        v_x, v_z = (float(c) for c in solver.pool.particles.v.numpy()[0, [0, 2]])
        if wall_friction is None:
            coulomb = v0 - mu * (g * T + v_z)
            assert coulomb - drag_bound - 1e-5 <= v_x <= coulomb + 1e-5, (dt, v_x, coulomb, drag_bound)
        else:
            hits = solver.wall_hit_count()
            assert hits >= 10 and v_x <= v0 * E_T**hits + 1e-6, (dt, v_x, hits)


def test_wall_restitution_comes_from_the_material():
    from hel_warp.material import Material

    solver = make_solver(x=[(0.004, 0.003, 0.0004)], v=[(0.3, 0.0, -1.0)], gravity=(0.0, 0.0, 0.0),
                         material=Material(wall_restitution_normal=0.5, wall_restitution_tangential=1.0))
    p = solver.pool.particles
    solver.deposit(), solver.gas_step(), solver.interpolate(), solver.collide(), solver.push()
    v_pre = p.v.numpy()[0].astype(np.float64)
    solver.reflect_at_walls()
    np.testing.assert_allclose(p.v.numpy()[0], [v_pre[0], 0.0, -0.5 * v_pre[2]], rtol=1e-6, atol=1e-7)


def test_parcel_in_a_corner_ends_inside_both_walls():
    solver = make_solver(x=[(0.0003, 0.003, 0.0003)], v=[(-1.0, 0.0, -1.0)], gravity=(0.0, 0.0, 0.0))
    solver.step()
    x, v = solver.pool.particles.x.numpy()[0], solver.pool.particles.v.numpy()[0]
    assert x[0] > 0.0 and x[2] > 0.0
    assert v[0] > 0.0 and v[2] > 0.0  # reflected off both walls


def test_injection_count_window_speed_and_box():
    from hel_warp.hel import ScheduledInjection
    from hel_warp.parcels.pool import VolumeInjection

    box_lo, box_hi = (0.002, 0.001, 0.005), (0.006, 0.005, 0.008)
    inj = VolumeInjection(box_lo=box_lo, box_hi=box_hi, diameter_mean=2e-4, count=1000, speed=2.0,
                          direction=(0.0, 0.0, -1.0), stream=3, seed=7)
    solver = make_solver(capacity=1500, injectors=(ScheduledInjection(injection=inj, t_start=0.0, t_end=0.005),))
    assert solver.pool.used == 0  # a window starting at 0 has released nothing at t = 0
    p = solver.pool.particles
    for k in range(1, 8):
        used_before = solver.pool.used
        solver.step()
        assert solver.pool.used == round(1000 * min(k * 1e-3 / 0.005, 1.0))  # uniform rate, then stops
        new = slice(used_before, solver.pool.used)
        x, v = p.x.numpy()[new], p.v.numpy()[new]
        assert np.all(x >= np.float32(box_lo)) and np.all(x <= np.float32(box_hi))
        np.testing.assert_allclose(v, np.tile([0.0, 0.0, -2.0], (len(x), 1)), atol=1e-7)
        assert np.all(p.stream.numpy()[new] == 3) and np.all(p.alive.numpy()[new] == 1)
    assert solver.injected() == [{"count": 1000, "mass": pytest.approx(1000 * 1000 * math.pi / 6 * 2e-4**3)}]


def test_injection_by_mass_at_once():
    """Mass mode: the released real-particle mass reaches the request and exceeds it by less than one parcel."""
    from hel_warp.hel import ScheduledInjection
    from hel_warp.parcels.pool import VolumeInjection

    mass = 2.0e-6  # kg
    inj = VolumeInjection(box_lo=(0.002, 0.001, 0.002), box_hi=(0.010, 0.005, 0.008), diameter_mean=3e-4,
                          diameter_std=3e-5, density=1000.0, mass=mass, speed=1.0, direction=(1.0, 1.0, 0.0))
    solver = make_solver(capacity=400, injectors=(ScheduledInjection(injection=inj, t_start=0.0),))
    p = solver.pool.particles
    n = solver.pool.used
    r = p.radius.numpy()[:n].astype(np.float64)
    masses = 1000.0 * 4.0 / 3.0 * math.pi * r**3
    assert mass <= masses.sum() < mass + masses.max() * (1 + 1e-6)
    assert solver.injected()[0]["mass"] == pytest.approx(masses.sum(), rel=1e-6)
    np.testing.assert_allclose(p.v.numpy()[:n], np.tile([math.sqrt(0.5), math.sqrt(0.5), 0.0], (n, 1)), atol=1e-6)


def test_outlet_removes_exactly_the_parcels_past_the_plane():
    from hel_warp.hel import Outlet

    rng = np.random.default_rng(3)
    n = 200
    x = np.column_stack([rng.uniform(0.004, 0.0079, n), rng.uniform(0.001, 0.005, n), rng.uniform(0.002, 0.008, n)])
    v = np.column_stack([rng.uniform(0.0, 2.0, n), np.zeros(n), np.zeros(n)])
    solver = make_solver(x=x, v=v, radius=5e-5, density=1000.0,
                         outlets=(Outlet(point=(0.008, 0.0, 0.0), normal=(2.0, 0.0, 0.0)),))
    p = solver.pool.particles
    solver.deposit(), solver.gas_step(), solver.interpolate(), solver.collide(), solver.push()
    past = p.x.numpy()[:, 0] > np.float32(0.008)
    assert 0 < past.sum() < n
    solver.remove_at_outlets()
    np.testing.assert_array_equal(p.alive.numpy() == 0, past)
    assert solver.pool.removed_count() == past.sum()


def test_parcels_or_injector_boxes_outside_the_fluid_are_refused():
    from hel_warp.hel import ScheduledInjection
    from hel_warp.parcels.pool import VolumeInjection

    with pytest.raises(ConfigError, match="outside the fluid.*place the parcels inside"):
        make_solver(x=[(0.004, 0.003, 0.005), (0.004, 0.003, -0.001)])
    inj = VolumeInjection(box_lo=(0.010, 0.001, 0.002), box_hi=(0.014, 0.005, 0.004), diameter_mean=2e-4, count=10)
    with pytest.raises(ConfigError, match="injector 0.*outside the fluid.*move or shrink the box"):
        make_solver(injectors=(ScheduledInjection(injection=inj),))
    with pytest.raises(ConfigError, match="t_end"):
        ScheduledInjection(injection=inj, t_start=0.2, t_end=0.1)


def test_grid_too_coarse_for_the_geometry_names_the_spacing():
    from hel_warp.gas.grid import Channel, Geometry, Grid

    geometry = Geometry(shapes=(Channel(start=(0, 0.01, 0.01), end=(0.05, 0.01, 0.01), width=0.004, height=0.004),))
    with pytest.raises(ConfigError, match="too coarse.*use spacing <="):
        geometry.build(Grid(spacing=2e-3, shape=(25, 10, 10)))


def test_nan_in_a_field_is_found_on_the_device_and_named():
    solver = make_solver(x=[(0.004, 0.003, 0.005)])
    solver.step()
    solver.check_finite()  # all finite: no error
    u = solver.gas.cell_velocity.numpy()
    u[3, 2, 4, 1] = np.nan
    solver.gas.cell_velocity.assign(u)
    with pytest.raises(HelWarpError, match="NaN/inf.*gas cell_velocity \\(1 entries\\).*reduce dt"):
        solver.check_finite()


class _Mover:
    """A strategy that integrates the parcels itself: x += dt * (1, 0, 0) m/s; counts its calls."""

    name = "mover"

    def __init__(self):
        self.accelerated = 0
        self.advanced = 0

    def accelerate(self, solver):
        self.accelerated += 1
        solver.fields.parcel_a_coll.zero_()

    def advance(self, solver):
        self.advanced += 1
        x = solver.pool.particles.x.numpy()
        x[:, 0] += solver.config.dt
        solver.pool.particles.x.assign(x)
        solver.fields.parcel_drag_impulse.zero_()

    def counts(self):
        return {"pairs": 5 * self.advanced}


def test_strategy_advance_replaces_the_push_and_counts_are_reported():
    mover = _Mover()
    solver = make_solver(x=[(0.004, 0.003, 0.005)], v=[(0.0, 0.0, 0.0)], collision=mover)
    x0 = solver.pool.particles.x.numpy()[0].copy()
    for _ in range(3):
        solver.step()
    x, v = solver.pool.particles.x.numpy()[0], solver.pool.particles.v.numpy()[0]
    assert mover.accelerated == mover.advanced == 3
    # the push would have given the parcel a downward velocity under gravity; advance() moved it in x only
    np.testing.assert_array_equal(v, [0.0, 0.0, 0.0])
    assert x[0] == pytest.approx(x0[0] + 3e-3, abs=1e-7) and x[2] == x0[2]
    assert solver.collision_counts() == {"pairs": 15}
    gas_phases = {"gas_update_cell_state", "gas_advect", "gas_add_forces_and_diffuse", "gas_project"}
    assert set(solver.timings) == {"deposit", "gas_step", "interpolate", "collide", "push", "remove_at_outlets",
                                   "reflect_at_walls", "inject"} | gas_phases
    # the gas phases are timed inside the gas step
    assert 0.0 < sum(solver.timings[k] for k in gas_phases) <= solver.timings["gas_step"]


def test_collision_model_factory_names_the_valid_models():
    from hel_warp.hel import COLLISION_MODELS, NoCollision, collision_model

    assert isinstance(collision_model("none"), NoCollision)
    assert {"none", "ktgf", "surrogate", "surrogate-paper", "dem"} <= set(COLLISION_MODELS)
    with pytest.raises(ConfigError, match="unknown collision model 'surogate'; choose one of none, ktgf, surrogate"):
        collision_model("surogate")


def test_reflection_off_an_inclined_channel_floor_uses_the_sdf_normal():
    """Rotated box (channel along (1,0,1)/sqrt 2): the floor normal is n = (1,0,-1)/sqrt 2 out of the fluid;
    v' = -e_n (v.n) n + e_t v_t and the centre comes back to e_n times its depth past the floor."""
    import warp as wp

    from hel_warp.gas.grid import Channel, Geometry
    from kernels.reflect import make_wall_params, reflect_at_walls

    channel = Channel(start=(0.0, 0.0, 0.0), end=(0.1, 0.0, 0.1), width=0.02, height=0.01)
    shapes = Geometry(shapes=(channel,)).shapes_struct()
    d, _, e3 = channel.axes()
    n = -e3
    np.testing.assert_allclose(n, np.array([1.0, 0.0, -1.0]) / math.sqrt(2.0), atol=1e-12)
    centre = np.array([0.05, 0.0, 0.05])
    depth = 2e-4
    x = centre + 0.01 * d + (0.5 * 0.01 + depth) * n
    v = 0.7 * d + 1.3 * n  # into the floor, with a tangential part
    px = wp.array(x[None].astype(np.float32), dtype=wp.vec3)
    pv = wp.array(v[None].astype(np.float32), dtype=wp.vec3)
    hits = wp.zeros(1, dtype=wp.int32)
    reflect_at_walls(shapes, make_wall_params(), wp.ones(1, dtype=wp.int32), px, pv, hits)
    np.testing.assert_allclose(pv.numpy()[0], -E_N * 1.3 * n + E_T * 0.7 * d, atol=2e-6)
    height_above_floor = float(np.dot(px.numpy()[0] - centre, -n)) + 0.5 * 0.01  # > 0 inside the fluid
    assert height_above_floor == pytest.approx(E_N * depth, rel=1e-3)
    assert int(hits.numpy()[0]) == 1


@pytest.mark.parametrize("strategy", ["none", "dem"])
def test_sorting_parcels_by_cell_changes_nothing_but_the_slot_order(strategy):
    # 300 small parcels (some dead) resting in a closed box, 8 steps with a sort before every step vs never: each
    # parcel id ends in the same state (float32 round-off: the deposit adds in another order), the slots are
    # in cell order with the dead ones last, and `used` is kept. `dem` carries contact histories through it.
    from hel_warp.hel import NoCollision

    rng = np.random.default_rng(3)
    n = 300
    d = 0.4e-3
    lattice = np.stack(np.meshgrid(*(np.arange(k) for k in (10, 5, 6)), indexing="ij"), -1).reshape(-1, 3)
    # a pile of touching spheres on the floor: gravity keeps the contacts closed
    x = np.array([2e-3, 1.5e-3, d / 2]) + lattice * d
    v = rng.normal(0.0, 1e-3, (n, 3))
    runs = {}
    for every in (0, 1):
        if strategy == "dem":
            from hel_warp.collisions.models import DemCollision

            collision = DemCollision(dt_dem=2e-5)
        else:
            collision = NoCollision()
        solver = make_solver(x=x, v=v, radius=d / 2, density=1000.0, collision=collision, sort_every=every)
        p = solver.pool.particles
        dead = np.ones(n, np.int32)
        dead[::7] = 0
        p.alive.assign(dead)
        contacts = 0
        for _ in range(8):
            solver.step()
            contacts += solver.collision_counts().get("detected_pairs", 0)
        if strategy == "dem":
            assert contacts > 100  # the sort moved live contact histories
        ids = p.particle_id.numpy()
        order = np.argsort(ids)
        runs[every] = {k: getattr(p, k).numpy()[order] for k in ("x", "v", "alive", "stream")}
        if every:
            alive = p.alive.numpy().astype(bool)
            assert solver.pool.used == n and sorted(ids.tolist()) == list(range(n))
            n_alive = int(alive.sum())
            assert alive[:n_alive].all() and not alive[n_alive:].any()  # dead slots last
            cell = np.floor(p.x.numpy()[:n_alive].astype(np.float64) / H).astype(int)
            # the slot order was cell order at the start of the last step (parcels moved < 1 cell since)
            assert (np.abs(np.diff(cell[:, 0])) <= 1).mean() > 0.9
    assert np.array_equal(runs[0]["alive"], runs[1]["alive"])
    # dem: the contact forces add in another partner order (float32), which the stiff contacts amplify to
    # 1.4e-7 m / 2.8e-4 m/s here (measured); dropping the contact histories in the sort gives 3.4e-6 m / 4.4e-3 m/s
    assert np.allclose(runs[0]["x"], runs[1]["x"], atol=5e-7, rtol=0)
    assert np.allclose(runs[0]["v"], runs[1]["v"], atol=1e-3, rtol=0)
