"""Two-way coupling: cloud-in-cell weights (partition of unity, exact for linear fields), deposition
conserving volume and momentum (sum over cells = sum over parcels), the same weights for deposit and
interpolation, determinism, injection/outlet bookkeeping, and hindered settling of a uniform
suspension against the drag-law force balance solved independently."""

import math

import numpy as np
import pytest
import warp as wp
from scipy.optimize import brentq

from hel_warp.parcels.coupling import (CouplingFields, GridSpec, PushConfig, deposit_parcels, parcel_grid, interpolate_gas,
                               ktgf_collision, push_parcels)
from hel_warp.errors import ConfigError, HelWarpError
from hel_warp.parcels.pool import ParcelPool, VolumeInjection
from hel_warp.parcels.particles import Particles
from kernels.interp import CellGrid as CellGridStruct
from kernels.interp import (cloud_support, interpolate_scalar, interpolate_vec3, interpolate_vec3_parcels,
                           spread_half_width, stencil_weights)

GRID = GridSpec(origin=(-0.01, 0.02, 0.0), spacing=0.005, shape=(6, 5, 4))


def random_parcels(n, seed=0, margin=-0.004, weight=None):
    """Parcels uniformly in the grid box widened by ``margin`` (negative: also outside the grid)."""
    rng = np.random.default_rng(seed)
    lo = np.array(GRID.origin) + margin
    hi = np.array(GRID.origin) + GRID.spacing * np.array(GRID.shape) - margin
    x = lo + rng.uniform(size=(n, 3)) * (hi - lo)
    w = rng.integers(1, 9, n) if weight is None else weight
    return Particles.from_numpy(x, rng.uniform(100e-6, 300e-6, n), v=rng.normal(0, 1, (n, 3)),
                                density=rng.uniform(900, 2500, n), weight=w, check_overlap=False), rng


def test_weights_are_a_partition_of_unity():
    parts, _ = random_parcels(500)
    cells = wp.zeros((500, 8), dtype=wp.vec3i)
    weights = wp.zeros((500, 8), dtype=wp.float64)
    stencil_weights(GRID.cell_grid(), parts.x, cells, weights)
    w = weights.numpy()
    assert np.all(w >= 0) and np.all(w <= 1)
    assert np.allclose(w.sum(axis=1), 1.0, rtol=0, atol=1e-14)
    c = cells.numpy()
    assert c.min() >= 0 and np.all(c.max(axis=(0, 1)) < np.array(GRID.shape))


def test_linear_field_is_interpolated_exactly_between_cell_centres():
    # f(x) = a + b.x sampled at cell centres; trilinear interpolation reproduces it inside the centre hull
    a, b = 0.7, np.array([3.0, -2.0, 5.0])
    i, j, k = np.meshgrid(*[np.arange(n) for n in GRID.shape], indexing="ij")
    centres = np.stack([i, j, k], -1) * GRID.spacing + np.array(GRID.origin) + 0.5 * GRID.spacing
    scalar = (a + centres @ b).astype(np.float32)
    vector = np.stack([a + centres @ b, 2 * a - centres @ b, centres[..., 2]], -1).astype(np.float32)
    parts, _ = random_parcels(300, margin=0.5 * GRID.spacing + 1e-6)  # inside the hull of the centres
    x = parts.x.numpy().astype(np.float64)
    s_out = wp.zeros(300, dtype=float)
    v_out = wp.zeros(300, dtype=wp.vec3)
    interpolate_scalar(GRID.cell_grid(), parts.x, wp.array(scalar, dtype=float), s_out)
    interpolate_vec3(GRID.cell_grid(), parts.x, wp.array(vector, dtype=wp.vec3), v_out)
    assert np.allclose(s_out.numpy(), a + x @ b, rtol=0, atol=2e-6)
    expect = np.stack([a + x @ b, 2 * a - x @ b, x[:, 2]], -1)
    assert np.allclose(v_out.numpy(), expect, rtol=0, atol=2e-6)


def _deposit_random(seed=1, n=400):
    parts, rng = random_parcels(n, seed=seed)
    fields = CouplingFields.allocate(GRID, n)
    impulse = rng.normal(0, 1e-6, (n, 3))
    fields.parcel_drag_impulse.assign(impulse)
    fields.parcel_drag_coeff.assign(rng.uniform(0, 1e-3, n))
    alive = np.ones(n, np.int32)
    alive[::7] = 0  # dead parcels deposit nothing
    parts.alive.assign(alive)
    deposit_parcels(GRID, parts, fields)
    return parts, fields, impulse, alive


def test_deposit_conserves_volume_momentum_and_drag_coefficient():
    parts, fields, impulse, alive = _deposit_random()
    live = alive == 1
    r = parts.radius.numpy().astype(np.float64)
    w = parts.weight.numpy().astype(np.float64)
    volume = w * 4.0 / 3.0 * math.pi * r**3
    assert fields.cell_solid_volume.numpy().sum() == pytest.approx(volume[live].sum(), rel=1e-13, abs=0)
    # momentum given to the gas = minus the drag impulses of the live parcels (sum over cells vs parcels)
    src = fields.cell_momentum_source.numpy().reshape(-1, 3).sum(axis=0)
    total = impulse[live].sum(axis=0)
    assert np.allclose(src, -total, rtol=0, atol=1e-13 * np.abs(impulse).sum())
    assert fields.cell_drag_coeff.numpy().sum() == pytest.approx(fields.parcel_drag_coeff.numpy()[live].sum(),
                                                                  rel=1e-13, abs=0)
    mass = volume * parts.density.numpy()
    mom = (mass[:, None] * parts.v.numpy())[live].sum(axis=0)
    assert np.allclose(fields.cell_solid_momentum.numpy().reshape(-1, 3).sum(axis=0), mom, rtol=1e-12, atol=0)
    eps = fields.cell_eps_s.numpy().astype(np.float64)
    assert eps.sum() * GRID.cell_volume == pytest.approx(volume[live].sum(), rel=1e-6, abs=0)


def test_deposit_and_interpolation_use_the_same_weights():
    # Work of the exchange: sum_c S_c . u_c = -sum_p I_p . u_f(x_p) holds only when the gas velocity is read
    # with the weights the source was spread with (the discrete "equal and opposite").
    parts, fields, impulse, alive = _deposit_random(seed=5)
    rng = np.random.default_rng(9)
    u_cells = rng.normal(0, 1, GRID.shape + (3,)).astype(np.float32)
    u_f = wp.zeros(parts.count, dtype=wp.vec3)
    # weights 1..8: the heavier parcels spread over wider tents (the deposit's cloud widths, GridSpec.cloud_density),
    # read alike through the step's grid
    assert fields.cloud_on
    interpolate_vec3_parcels(parcel_grid(GRID, fields), parts.x, parts.weight, wp.array(u_cells, dtype=wp.vec3), u_f)
    lhs = np.sum(fields.cell_momentum_source.numpy() * u_cells.astype(np.float64))
    rhs = -np.sum((impulse * u_f.numpy().astype(np.float64))[alive == 1])
    assert lhs == pytest.approx(rhs, rel=1e-6)  # u_f stored in float32


def test_deposit_is_deterministic():
    _, a, _, _ = _deposit_random(seed=11, n=2000)
    _, b, _, _ = _deposit_random(seed=11, n=2000)
    for name in ("cell_solid_volume", "cell_momentum_source", "cell_drag_coeff", "cell_solid_momentum"):
        assert np.array_equal(getattr(a, name).numpy(), getattr(b, name).numpy()), name


def test_parcel_at_a_cell_centre_deposits_into_that_cell_only():
    # the weight rule keeps parcels below w = 3.95 trilinear (a cloud of three alone would spread: cloud_density)
    grid = GridSpec(origin=GRID.origin, spacing=GRID.spacing, shape=GRID.shape, cloud_density=False)
    x = np.array(GRID.origin) + GRID.spacing * np.array([2.5, 1.5, 3.5])
    parts = Particles.from_numpy(x[None, :], 200e-6, density=1500.0, weight=3.0, check_overlap=False)
    fields = CouplingFields.allocate(grid, 1)
    deposit_parcels(grid, parts, fields)
    vol = fields.cell_solid_volume.numpy()
    expect = 3.0 * 4.0 / 3.0 * math.pi * float(np.float32(200e-6)) ** 3  # radius is stored in float32
    # positions are float32: the parcel sits within ~1e-9 m of the centre, leaving ~1e-6 of its volume aside
    assert vol.sum() == pytest.approx(expect, rel=1e-12, abs=0)
    assert vol[2, 1, 3] == pytest.approx(expect, rel=1e-6, abs=0)


def test_coupled_step_conserves_gas_plus_particle_momentum():
    # push then deposit: d(particle momentum) - m dt a_body + (momentum given to the gas) = 0
    parts, rng = random_parcels(300, seed=4, margin=0.0)
    fields = CouplingFields.allocate(GRID, 300)
    u_cells = rng.normal(0, 2, GRID.shape + (3,)).astype(np.float32)
    zero_grad = np.zeros(GRID.shape + (3,), np.float32)
    deposit_parcels(GRID, parts, fields)  # eps_s for the drag law
    interpolate_gas(GRID, parts, wp.array(u_cells, dtype=wp.vec3), wp.array(zero_grad, dtype=wp.vec3), fields)
    cfg = PushConfig(drag="gidaspow", gravity=(0.0, 0.0, 0.0))  # body forces off: drag is the only exchange
    m = parts.mass_numpy() * parts.weight.numpy()
    p_before = (m[:, None] * parts.v.numpy()).sum(axis=0)
    push_parcels(parts, fields, cfg.params(1e-3))
    p_after = (m[:, None] * parts.v.numpy()).sum(axis=0)
    deposit_parcels(GRID, parts, fields)
    gas_gain = fields.cell_momentum_source.numpy().reshape(-1, 3).sum(axis=0)
    scale = np.abs(m[:, None] * parts.v.numpy()).sum()
    assert np.abs(p_after - p_before + gas_gain).max() <= 1e-6 * scale  # float32 particle velocities


def _beta_balance_slip(eps_s, d, rho_p, rho_f, mu, g):
    """Slip w solving beta(eps_s, w) w = eps_s eps_f (rho_p - rho_f) g with Gidaspow's beta (written here again)."""
    ef = 1.0 - eps_s

    def beta(w):
        if ef <= 0.8:
            return 150.0 * eps_s**2 * mu / (ef * d * d) + 1.75 * rho_f * eps_s * w / d
        re = ef * rho_f * w * d / mu
        cd = 24.0 / re * (1 + 0.15 * re**0.687) if re <= 1000 else 0.44
        return 0.75 * cd * eps_s * ef * rho_f * w * ef**-2.65 / d

    return brentq(lambda w: beta(w) * w - eps_s * ef * (rho_p - rho_f) * g, 1e-9, 50.0, xtol=1e-14, rtol=1e-13)


@pytest.mark.parametrize("eps_s", [0.05, 0.1, 0.3, 0.45])
def test_hindered_settling_matches_drag_force_balance(eps_s):
    # Uniform suspension, gas at rest on average: volume continuity eps_f u_f + eps_s u_s = 0, mean
    # modified-pressure gradient grad p' = grad p - rho_f g = eps_s (rho_p - rho_f) g (mixture weight).
    # Steady parcel: F_D (u_f - v) + g (rho_p - rho_f)/rho_p - grad p'/rho_p = 0
    #   =>  beta |v - u_f| = eps_s eps_f (rho_p - rho_f) |g|.
    d, rho_p, g = 315e-6, 1000.0, 9.80665
    cfg = PushConfig(drag="gidaspow", gravity=(0.0, 0.0, -g))
    expect = _beta_balance_slip(eps_s, d, rho_p, cfg.fluid_density, cfg.fluid_viscosity, g)
    grid = GridSpec(origin=(0, 0, 0), spacing=0.01, shape=(3, 3, 3))
    n = 200
    rng = np.random.default_rng(2)
    parts = Particles.from_numpy(rng.uniform(0.0, 0.03, (n, 3)), d / 2, density=rho_p, check_overlap=False)
    fields = CouplingFields.allocate(grid, n)
    fields.cell_eps_s.fill_(eps_s)
    grad_p = np.zeros(grid.shape + (3,), np.float32)
    grad_p[..., 2] = -eps_s * (rho_p - cfg.fluid_density) * g
    grad_p = wp.array(grad_p, dtype=wp.vec3)
    u_gas = wp.zeros(grid.shape, dtype=wp.vec3)
    params = cfg.params(1e-3)
    for _ in range(1500):
        interpolate_gas(grid, parts, u_gas, grad_p, fields)
        push_parcels(parts, fields, params)
        v_mean = parts.v.numpy().astype(np.float64).mean(axis=0)
        u_gas.fill_(wp.vec3(*(-eps_s * v_mean / (1.0 - eps_s))))
    slip = parts.v.numpy()[:, 2].astype(np.float64) - (-eps_s * v_mean[2] / (1.0 - eps_s))
    assert np.allclose(-slip, expect, rtol=0.02)
    assert np.allclose(-slip, expect, rtol=1e-3)


def test_ktgf_cells_and_collision_acceleration_on_a_sheared_slab():
    # Cells along z with a peaked eps_s profile under simple shear u_x = gamma z (D_xz = gamma/2, tr D = 0,
    # D:D = gamma^2/2). The algebraic root is then Theta = 2 K3 D:D / (K4 eps_s) (MFIX form, written here
    # again), p_s follows from Lun et al.; a_coll = -grad p_s/(eps_s rho_p) pushes parcels away from the peak.
    from kernels.ktgf import make_ktgf_params

    h, gamma, rho, d, e, emax = 0.002, 20.0, 1000.0, 300e-6, 0.9, 0.63
    grid = GridSpec(origin=(0, 0, 0), spacing=h, shape=(1, 1, 9))
    eps = np.array([0.02, 0.05, 0.1, 0.2, 0.4, 0.2, 0.1, 0.05, 0.02])
    zc = (np.arange(9) + 0.5) * h
    z = np.concatenate([np.linspace(0.5 * h, 2.5 * h, 20), np.linspace(6.5 * h, 8.5 * h, 20)])
    x = np.stack([np.full(z.size, 0.001), np.full(z.size, 0.001), z], -1)
    parts = Particles.from_numpy(x, d / 2, density=rho, check_overlap=False)
    fields = CouplingFields.allocate(grid, z.size)
    fields.cell_eps_s.assign(eps.reshape(1, 1, 9).astype(np.float32))
    u = np.zeros((1, 1, 9, 3), np.float32)
    u[0, 0, :, 0] = gamma * zc
    fields.cell_solid_velocity.assign(u)
    ktgf_collision(grid, parts, fields, make_ktgf_params(particle_diameter=d, particle_density=rho))
    g0 = 1.0 / (1.0 - (eps / emax) ** (1.0 / 3.0))
    sp = math.sqrt(math.pi)
    k3 = d * rho / 2 * (sp / (3 * (3 - e)) * (0.5 * (3 * e + 1) + 0.4 * (1 + e) * (3 * e - 1) * eps * g0)
                        + 8 * eps * g0 * (1 + e) / (5 * sp))
    k4 = 12 * (1 - e * e) * rho * g0 / (d * sp)
    theta = 2 * k3 * (gamma**2 / 2) / (k4 * eps)
    p_s = eps * rho * theta * (1 + 2 * (1 + e) * eps * g0)
    assert np.allclose(fields.cell_theta.numpy().ravel(), theta, rtol=1e-4)
    assert np.allclose(fields.cell_p_s.numpy().ravel(), p_s, rtol=1e-4)
    a = fields.parcel_a_coll.numpy()
    assert np.all(a[:20, 2] < 0) and np.all(a[20:, 2] > 0)
    assert np.allclose(a[:, :2], 0.0)


def test_volume_injection_by_mass_count_and_outlet_removal():
    # the paper's 315 um case: 0.000196 kg of 1000 kg/m^3 spheres = 12000 particles (weight 1)
    pool = ParcelPool.empty(13000)
    inj = VolumeInjection(box_lo=(0, 0, 0), box_hi=(0.01, 0.02, 0.005), diameter_mean=315e-6, mass=0.000196,
                          speed=5.0, direction=(1.0, 1.0, 0.0), seed=1)
    n = pool.inject(inj)
    m_p = 1000.0 * math.pi / 6.0 * (315e-6) ** 3
    assert n == math.ceil(0.000196 / m_p - 1e-9)
    p = pool.particles.to_numpy()
    x = p["x"][:n]
    assert np.all(x >= 0) and np.all(x <= [0.01, 0.02, 0.005])
    assert np.allclose(p["v"][:n], [5 / math.sqrt(2), 5 / math.sqrt(2), 0], rtol=1e-6)
    assert p["alive"][:n].all() and not p["alive"][n:].any()
    pool2 = ParcelPool.empty(5000)
    pool2.inject(VolumeInjection(box_lo=(0, 0, 0), box_hi=(1, 1, 1), diameter_mean=400e-6, diameter_std=40e-6,
                                 count=4000, seed=2))
    d = 2 * pool2.particles.radius.numpy()[:4000].astype(np.float64)
    assert d.mean() == pytest.approx(400e-6, abs=4 * 40e-6 / math.sqrt(4000))
    assert d.std() == pytest.approx(40e-6, rel=0.05)
    pool2.remove_beyond_plane((0.5, 0, 0), (1, 0, 0))
    xs = pool2.particles.x.numpy()[:4000, 0]
    assert pool2.removed_count() == int((xs > 0.5).sum())
    assert pool2.alive_count() == int((xs <= 0.5).sum())
    with pytest.raises(ConfigError, match="capacity"):
        pool2.inject(VolumeInjection(box_lo=(0, 0, 0), box_hi=(1, 1, 1), diameter_mean=1e-3, count=2000))


@pytest.mark.parametrize("kwargs,field", [({"count": 10, "mass": 1.0}, "exactly one"),
                                          ({"count": 10, "diameter_mean": -1.0}, "diameter_mean"),
                                          ({"count": 10, "box_hi": (0, 1, 1)}, "box_hi"),
                                          ({"count": 10, "direction": (0, 0, 0)}, "direction")])
def test_bad_injection_is_refused(kwargs, field):
    base = dict(box_lo=(0, 0, 0), box_hi=(1, 1, 1), diameter_mean=1e-3)
    with pytest.raises(ConfigError, match=field):
        VolumeInjection(**(base | kwargs))


def test_periodic_axis_wraps_the_stencil():
    # Periodic x: a parcel a quarter cell above the lower face sits between cell n-1 (image at -h/2) and
    # cell 0: weights 1/4 and 3/4 on that axis. Bounded y, z: clamped, still a partition of unity.
    grid = GridSpec(origin=(0, 0, 0), spacing=0.01, shape=(5, 3, 3), periodic=(True, False, False))
    x = np.array([[0.0025, 0.015, 0.015], [0.0525, 0.015, 0.015], [-0.0475, 0.015, 0.015]])
    parts = Particles.from_numpy(x, 1e-4, check_overlap=False)
    cells = wp.zeros((3, 8), dtype=wp.vec3i)
    weights = wp.zeros((3, 8), dtype=wp.float64)
    stencil_weights(grid.cell_grid(), parts.x, cells, weights)
    c, w = cells.numpy(), weights.numpy()
    for p in range(3):  # the three positions are periodic images of one another
        wx = {}
        for corner in range(8):
            wx[c[p, corner, 0]] = wx.get(c[p, corner, 0], 0.0) + w[p, corner]
        assert wx[4] == pytest.approx(0.25, abs=1e-6) and wx[0] == pytest.approx(0.75, abs=1e-6)
        assert w[p].sum() == pytest.approx(1.0, abs=1e-14)
    fields = CouplingFields.allocate(grid, 3)
    deposit_parcels(grid, parts, fields)
    vol = fields.cell_solid_volume.numpy()
    assert vol.sum() == pytest.approx(3 * 4 / 3 * math.pi * float(np.float32(1e-4)) ** 3, rel=1e-12, abs=0)
    assert vol[4].sum() == pytest.approx(vol.sum() / 4, rel=1e-5)


def periodic_suspension(eps_s, *, gravity=(0.0, 0.0, 0.0), mean_pressure_gradient=(0.0, 0.0, 0.0), v0=None,
                        coupling="implicit", per_axis=12, d=315e-6, rho_p=1000.0, dt=1e-3):
    """A triply periodic box of 4^3 cells of 2 mm with the engine's gas solver and a uniform suspension of
    ``per_axis``^3 parcels on a lattice (solid fraction ``eps_s`` in every cell, velocity ``v0``), Gidaspow drag.
    Returns (HelSolver, GasField, grid, push config, parcel masses m_p weight)."""
    from hel_warp.gas.solver import GasConfig, GasField, GasSolver
    from hel_warp.gas.grid import Box, Geometry, Grid
    from hel_warp.hel import HelConfig, HelSolver, NoCollision

    n, h = 4, 2e-3
    side = n * h
    push = PushConfig(drag="gidaspow", gravity=gravity)
    grid = Grid(spacing=h, shape=(n, n, n), periodic=(True, True, True))
    domain = Geometry(shapes=(Box(lo=(-1, -1, -1), hi=(1, 1, 1)),)).build(grid)
    solver = GasSolver(domain, GasConfig(density=push.fluid_density, viscosity=push.fluid_viscosity,
                                         mean_pressure_gradient=mean_pressure_gradient))
    gas = GasField(domain)
    c = (np.arange(per_axis) + 0.5) * side / per_axis
    x = np.stack(np.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)
    v_p = math.pi / 6 * float(np.float32(d / 2) * 2) ** 3
    weight = eps_s * side**3 / (x.shape[0] * v_p)
    pool = ParcelPool.empty(x.shape[0])
    pool.inject(VolumeInjection(box_lo=(0, 0, 0), box_hi=(side,) * 3, diameter_mean=d, density=rho_p,
                                count=x.shape[0], weight=weight))
    pool.particles.x.assign(x.astype(np.float32))  # lattice instead of random positions
    if v0 is not None:
        pool.particles.v.assign(np.tile(np.float32(v0), (x.shape[0], 1)))
    hel = HelSolver(pool=pool, gas_solver=solver, gas=gas,
                    config=HelConfig(dt=dt, push=push, walls=False, coupling=coupling), collision=NoCollision())
    return hel, gas, grid, push, pool.particles.mass_numpy() * weight


def gas_momentum(gas, grid, push, eps_s):
    """Gas momentum (N s, per axis) of the periodic box: rho_f eps_f V_cell sum of the face velocities."""
    u = gas.face_arrays()
    inner = tuple(slice(0, k) for k in grid.shape)
    return np.array([push.fluid_density * (1 - eps_s) * grid.cell_volume * u[a][inner].sum() for a in range(3)])


def test_hel_solver_with_gas_hindered_settling_conserves_momentum():
    # Periodic box, uniform suspension (parcels on a lattice, eps_s = 0.1 in every cell), the engine's gas
    # solver, mean grad p' = eps_s (rho_p - rho_f) g balancing the mixture weight. External forces then sum to
    # zero, so particles + gas keep zero momentum (up to the impulse of the last push, still owed to the gas),
    # and the slip tends to the Gidaspow (Wen-Yu branch) balance beta |slip| = eps_s eps_f (rho_p - rho_f) g.
    eps_s, d, rho_p, g = 0.1, 315e-6, 1000.0, 9.80665
    grad = -eps_s * (rho_p - PushConfig().fluid_density) * g
    hel, gas, grid, push, m = periodic_suspension(eps_s, gravity=(0.0, 0.0, -g),
                                                  mean_pressure_gradient=(0.0, 0.0, grad))
    for _ in range(30):  # the light gas relaxes within ~5 steps (measured), the particles barely move
        hel.step()
    v = hel.pool.particles.v.numpy().astype(np.float64)
    gas_p = gas_momentum(gas, grid, push, eps_s)
    total = (m[:, None] * v).sum(axis=0) + gas_p + hel.momentum_in_flight()
    # float32 gas and particle velocities; the scale is the gas momentum (the larger one here)
    assert np.abs(total).max() <= 1e-4 * np.abs(gas_p).max()
    # the slip the drag acts on: against the exchange velocity u_eq (gas and parcels relaxed together)
    slip = v[:, 2].mean() - hel.fields.parcel_u_eq.numpy()[:, 2].astype(np.float64).mean()
    expect = _beta_balance_slip(eps_s, d, rho_p, push.fluid_density, push.fluid_viscosity, g)
    assert -slip == pytest.approx(expect, rel=0.02)


def test_hel_solver_refuses_gas_properties_that_differ_from_the_gas_solver():
    from hel_warp.gas.solver import GasConfig, GasField, GasSolver
    from hel_warp.gas.grid import Box, Geometry, Grid
    from hel_warp.hel import HelConfig, HelSolver

    grid = Grid(spacing=1e-3, shape=(3, 3, 3), periodic=(True, True, True))
    domain = Geometry(shapes=(Box(lo=(-1, -1, -1), hi=(1, 1, 1)),)).build(grid)
    solver = GasSolver(domain, GasConfig(density=1.0))
    with pytest.raises(ConfigError, match="density"):
        HelSolver(pool=ParcelPool.empty(4), gas_solver=solver, gas=GasField(domain),
                  config=HelConfig(push=PushConfig(fluid_density=1.205)))
    assert GridSpec.of(grid) == GridSpec(origin=(0.0, 0.0, 0.0), spacing=1e-3, shape=(3, 3, 3),
                                         periodic=(True, True, True))


@pytest.mark.parametrize("coupling", ["implicit", "explicit"])
def test_dense_suspension_relaxes_to_the_mixture_velocity_without_overshoot(coupling):
    # Periodic box, no gravity, eps_s = 0.3 (250 times the gas mass), parcels at 5 m/s, gas at rest. Drag is an
    # internal force: gas and parcels must relax to the mixture velocity U = m_p v0 / (m_p + m_g) (momentum
    # conservation), the gas monotonically from 0 to U. dt K_sg / (eps_f rho_f) ~ 30 here: the explicit hand-back
    # of the parcels' impulses overshoots U many times over (kept as the discriminating case).
    eps_s, v0 = 0.3, 5.0
    hel, gas, grid, push, m = periodic_suspension(eps_s, v0=(v0, 0.0, 0.0), coupling=coupling)
    m_p = float(m.sum())
    m_g = push.fluid_density * (1 - eps_s) * grid.cell_volume * np.prod(grid.shape)
    mixture = m_p * v0 / (m_p + m_g)
    inner = tuple(slice(0, k) for k in grid.shape)
    gas_peak = 0.0
    try:
        for _ in range(40):
            hel.step()
            u = gas.face_arrays()[0][inner].astype(np.float64)
            gas_peak = max(gas_peak, float(np.nan_to_num(np.abs(u), nan=np.inf).max()))
    except HelWarpError:  # the gas solve met NaN/inf: the explicit hand-back blew up
        gas_peak = math.inf
    if coupling == "explicit":
        assert gas_peak > 2.0 * mixture  # the hazard the implicit exchange removes
        return
    assert gas_peak <= mixture * (1 + 1e-4)
    v = hel.pool.particles.v.numpy()[:, 0].astype(np.float64)
    assert v.mean() == pytest.approx(mixture, rel=1e-3)
    assert u.mean() == pytest.approx(mixture, rel=2e-3)


def test_closed_periodic_box_momentum_change_is_the_gravity_impulse():
    # Triply periodic box (closed: nothing enters or leaves), no imposed pressure gradient, a uniform suspension
    # (eps_s = 0.05) falling from rest with the gas. In the modified pressure p' = p - rho_f g.x the gas weight is
    # carried by the hydrostatic part, so the only net external force is the parcels' buoyancy-corrected weight:
    # d/dt (P_gas + P_parcels) = sum m_p (1 - rho_f/rho_p) g. Checked after 20 steps, drag exchange implicit.
    eps_s, rho_p, g, steps, dt = 0.05, 1000.0, 9.80665, 20, 1e-3
    hel, gas, grid, push, m = periodic_suspension(eps_s, gravity=(0.0, 0.0, -g), per_axis=10, dt=dt)
    for _ in range(steps):
        hel.step()
    v = hel.pool.particles.v.numpy().astype(np.float64)
    gas_p = gas_momentum(gas, grid, push, eps_s)
    total = (m[:, None] * v).sum(axis=0) + gas_p + hel.momentum_in_flight()
    impulse = m.sum() * (1 - push.fluid_density / rho_p) * g * steps * dt
    assert total[2] == pytest.approx(-impulse, rel=1e-5)
    assert np.abs(total[:2]).max() <= 1e-6 * impulse
    # the gas is dragged along, never faster than the parcels: it holds at most its mass share of the impulse
    mass_share = push.fluid_density * (1 - eps_s) / (eps_s * rho_p)
    assert gas_p[2] < 0.0 and abs(gas_p[2]) <= mass_share * impulse * 1.001


def cloud_half_width(weight):
    """The half-width K (cells) of the tent whose per-axis variance K^2 h^2 / 6 is nearest that of w real particles
    standing for a cube of w cells (edge w^(1/3) h, variance w^(2/3) h^2 / 12), each read trilinearly (h^2 / 6)."""
    return max(1, round(math.sqrt(6.0 * (weight ** (2.0 / 3.0) / 12.0 + 1.0 / 6.0))))


@wp.kernel
def _half_width_kernel(grid: CellGridStruct, weight: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.int32)):
    tid = wp.tid()
    out[tid] = spread_half_width(grid, weight[tid])


def test_the_host_knows_each_tent_before_the_launch(device):
    """``spread_half_width_host`` (what sizes the deterministic deposit's per-thread records on CUDA) is the kernel's
    ``spread_half_width`` at every weight, and never below it at the rounding boundaries K + 1/2 (float32 there);
    ``Particles.live_extremes`` (whose largest weight sizes it) skips removed parcels; and the CPU needs no
    reservation (its atomics keep no records)."""
    from hel_warp.parcels.coupling import reserve_tent_records
    from kernels.deposit import TRILINEAR_RECORDS
    from kernels.interp import spread_half_width_host

    edges = [(2.0 * ((k + 0.5) ** 2 - 1.0)) ** 1.5 for k in range(1, 12)]  # weights where K steps up
    weights = np.concatenate([np.arange(1, 5001, dtype=np.float64),
                              np.outer(edges, [1 - 1e-6, 1.0, 1 + 1e-6]).ravel(), [3.95, 3.9528, 3.96]])
    weights = weights.astype(np.float32)
    grid = GridSpec(origin=(0.0, 0.0, 0.0), spacing=1e-3, shape=(4, 4, 4))
    for spread in (True, False):
        g = GridSpec(origin=grid.origin, spacing=grid.spacing, shape=grid.shape, spread=spread).cell_grid()
        out = wp.zeros(len(weights), dtype=wp.int32, device=device)
        wp.launch(_half_width_kernel, dim=len(weights), inputs=[g, wp.array(weights, device=device)], outputs=[out],
                  device=device)
        host = np.array([spread_half_width_host(spread, float(w)) for w in weights])
        kernel = out.numpy()
        near_step = np.abs(np.sqrt(0.5 * weights.astype(np.float64) ** (2.0 / 3.0) + 1.0) % 1.0 - 0.5) < 1e-5
        assert np.all(host >= kernel)  # a bound: never fewer cells than the kernel adds into
        assert np.array_equal(host[~near_step], kernel[~near_step]) and np.all(host - kernel <= 1)
        if spread:
            assert 5 <= near_step.sum() <= 40  # the edges were sampled
    for w in (64.0, 1000.0, 5000.0):  # the cloud's K (7 at 1000: the docs'), 1 without tents
        assert spread_half_width_host(True, w) == cloud_half_width(w) and spread_half_width_host(False, w) == 1
    removed = Particles.from_numpy(np.full((3, 3), 2e-3), 100e-6, weight=np.array([3.0, 900.0, 8.0]),
                                   check_overlap=False, device=device)
    removed.alive.assign(np.array([1, 0, 1], np.int32))
    assert removed.live_extremes()[1] == 8.0
    if not wp.get_device(device).is_cuda:
        parts = Particles.from_numpy(np.full((2, 3), 2e-3), 100e-6, weight=64.0, check_overlap=False, device=device)
        assert reserve_tent_records(grid, parts) == TRILINEAR_RECORDS


@pytest.mark.parametrize("weight, half_width", [(8.0, 2), (27.0, 2), (64.0, 3), (216.0, 4)])
def test_heavy_parcels_spread_over_tents_that_grow_with_their_weight(weight, half_width):
    """A parcel of w real particles couples through a tent with the second moment of its w particles: its (2K)^3
    weights are a partition of unity, centred on the parcel (a linear field is read exactly away from the sides), the
    deposit keeps its volume, its per-axis variance about the parcel, averaged over positions in a cell, is the
    continuous tent's K^2 h^2 / 6 with K the cloud's (``cloud_half_width``), and a parcel at a cell centre spreads
    over (2K - 1)^3 cells (the tent's zeros at +-K); with ``spread=False`` the same parcel deposits trilinearly (one
    cell)."""
    assert cloud_half_width(weight) == half_width
    grid = GridSpec(origin=(0.0, 0.0, 0.0), spacing=1e-3, shape=(16, 16, 16), cloud_density=False)  # the weight rule
    rng = np.random.default_rng(4)
    n = 200
    x = rng.uniform(half_width + 0.5, 16 - half_width - 0.5, size=(n, 3)) * 1e-3  # K cells from the sides
    parts = Particles.from_numpy(x, 100e-6, density=2000.0, weight=weight, check_overlap=False)
    a, b = 0.3, np.array([2.0, -1.0, 4.0])
    i, j, k = np.meshgrid(*[np.arange(16)] * 3, indexing="ij")
    centres = (np.stack([i, j, k], -1) + 0.5) * 1e-3
    field = (a + centres @ b).astype(np.float32)
    out = wp.zeros(n, dtype=float)
    from kernels.interp import interpolate_scalar_parcels

    interpolate_scalar_parcels(grid.cell_grid(), parts.x, parts.weight, wp.array(field, dtype=float), out)
    xs = parts.x.numpy().astype(np.float64)
    assert np.allclose(out.numpy(), a + xs @ b, rtol=0, atol=2e-6)
    fields = CouplingFields.allocate(grid, n)
    deposit_parcels(grid, parts, fields)
    volume = weight * 4.0 / 3.0 * math.pi * float(np.float32(100e-6)) ** 3 * n
    assert fields.cell_solid_volume.numpy().sum() == pytest.approx(volume, rel=1e-12)
    variances = []
    for q in range(40):  # positions across one cell along x (midpoint rule over the cell)
        xp = np.array([8.0 + (q + 0.5) / 40.0, 8.5, 8.5]) * 1e-3
        single = Particles.from_numpy(xp[None, :], 100e-6, density=2000.0, weight=weight, check_overlap=False)
        f1 = CouplingFields.allocate(grid, 1)
        deposit_parcels(grid, single, f1)
        vol = f1.cell_solid_volume.numpy().astype(np.float64)
        share = vol / vol.sum()
        xp64 = single.x.numpy().astype(np.float64)[0]
        variances.append(float((share * (centres[..., 0] - xp64[0]) ** 2).sum()) / 1e-6)
    # the sampled tent's variance about the parcel (cells^2), averaged over its position in the cell: the continuous
    # tent's int (K - |s|) s^2 ds / K^2 = K^2 / 6, with K the cloud's (checked above)
    assert np.mean(variances) == pytest.approx(half_width**2 / 6.0, rel=2e-3)
    centre = np.array([[7.5e-3, 8.5e-3, 6.5e-3]])
    one = Particles.from_numpy(centre, 100e-6, density=2000.0, weight=weight, check_overlap=False)
    for spread, cells in ((True, (2 * half_width - 1) ** 3), (False, 1)):
        g = GridSpec(origin=(0.0, 0.0, 0.0), spacing=1e-3, shape=(16, 16, 16), spread=spread, cloud_density=False)
        f = CouplingFields.allocate(g, 1)
        deposit_parcels(g, one, f)
        vol = f.cell_solid_volume.numpy()
        assert np.count_nonzero(vol > 1e-6 * vol.max()) == cells
        assert vol.sum() == pytest.approx(weight * 4.0 / 3.0 * math.pi * float(np.float32(100e-6)) ** 3, rel=1e-12)


def test_a_heavy_parcels_tent_keeps_to_the_fluid_next_to_a_wall():
    """A weight-64 parcel (tent of half-width 4 cells) 1.5 cells from a wall: with the fluid mask its tent's weights
    lie on fluid cells only and sum to 1, so it deposits nothing into the solid cells and reads a uniform fluid
    velocity exactly (the solid cells hold 0, which the unmasked tent would average in); the weight-1 parcel
    beside it keeps its trilinear stencil."""
    from kernels.interp import interpolate_vec3_parcels

    shape = (16, 16, 16)
    grid = GridSpec(origin=(0.0, 0.0, 0.0), spacing=1e-3, shape=shape)
    fluid = np.ones(shape, np.int32)
    fluid[:, :, :3] = 0  # a wall: the cells below z = 3 mm are solid
    mask = wp.array(fluid, dtype=wp.int32)
    x = np.array([[8.2e-3, 7.9e-3, 4.5e-3], [8.2e-3, 7.9e-3, 4.5e-3]])  # 1.5 cells above the wall
    parts = Particles.from_numpy(x, 100e-6, density=2000.0, weight=np.array([64.0, 1.0]), check_overlap=False)
    u_cells = np.zeros(shape + (3,), np.float32)
    u_cells[fluid == 1] = (3.0, -1.0, 0.5)
    u = wp.zeros(2, dtype=wp.vec3)
    interpolate_vec3_parcels(grid.cell_grid(mask), parts.x, parts.weight, wp.array(u_cells, dtype=wp.vec3), u)
    assert np.allclose(u.numpy()[0], (3.0, -1.0, 0.5), rtol=0, atol=1e-6)
    interpolate_vec3_parcels(grid.cell_grid(), parts.x, parts.weight, wp.array(u_cells, dtype=wp.vec3), u)
    assert u.numpy()[0, 0] < 0.9 * 3.0  # without the mask the tent averages in the solid cells' zeros
    fields = CouplingFields.allocate(grid, 2)
    deposit_parcels(grid, parts, fields, mask)
    vol = fields.cell_solid_volume.numpy()
    v_p = 4.0 / 3.0 * math.pi * float(np.float32(100e-6)) ** 3
    assert vol.sum() == pytest.approx(65.0 * v_p, rel=1e-12)
    assert vol[fluid == 0].sum() == 0.0  # the trilinear parcel 1.5 cells up does not reach the wall either


@pytest.mark.parametrize("b", [0.4, 1.09, 1.73, 2.44, 3.87])
def test_a_cloud_stencil_has_the_moments_of_its_cloud(b):
    """A parcel coupling through a cloud of width b (``kernels/interp.py`` ``cloud_weight``; ``GridSpec.cloud_density``)
    stands for its particles spread uniformly over b cells per axis, each read trilinearly: its (2K)^3 weights sum
    to 1, their centroid is the parcel (a linear field is read exactly away from the sides), and their per-axis
    variance about it, averaged over positions in a cell, is the uniform cloud's b^2 / 12 plus one trilinear
    stencil's 1 / 6 (cells^2); the weights reach no further than b / 2 + 1 cells."""
    from kernels.interp import interpolate_scalar_parcels, make_cell_grid

    n_cells = 16
    rng = np.random.default_rng(7)
    n = 400
    x = np.column_stack([8.0 + (np.arange(n) + rng.uniform(size=n)) / n,  # every position across one cell in x
                         rng.uniform(6.0, 10.0, n), rng.uniform(6.0, 10.0, n)]) * 1e-3
    parts = Particles.from_numpy(x, 100e-6, density=2000.0, weight=64.0, check_overlap=False)
    cloud = wp.array(np.full(n, b, np.float32), dtype=wp.float32)
    grid = make_cell_grid((0.0, 0.0, 0.0), 1e-3, (n_cells,) * 3, spread=True, cloud=cloud)
    centres = (np.indices((n_cells,) * 3).transpose(1, 2, 3, 0) + 0.5) * 1e-3

    def read(field):
        out = wp.zeros(n, dtype=float)
        interpolate_scalar_parcels(grid, parts.x, parts.weight, wp.array(field.astype(np.float32), dtype=float), out)
        return out.numpy().astype(np.float64)

    xs = parts.x.numpy().astype(np.float64)
    assert np.allclose(read(np.ones((n_cells,) * 3)), 1.0, rtol=0, atol=1e-6)
    a0, grad = 0.3, np.array([2.0, -1.0, 4.0])
    assert np.allclose(read(a0 + centres @ grad), a0 + xs @ grad, rtol=0, atol=2e-6)
    # variance along x in cells^2 (the field read relative to a nearby origin keeps float32 exact enough)
    u = (centres[..., 0] - 8.5e-3) / 1e-3
    variance = read(u * u) - ((xs[:, 0] - 8.5e-3) / 1e-3) ** 2
    assert np.mean(variance) == pytest.approx(b * b / 12.0 + 1.0 / 6.0, rel=3e-3)
    # support: cells further than b / 2 + 1 from the parcel get nothing
    far = (np.abs(centres[..., 0] - xs[0, 0]) >= (0.5 * b + 1.0) * 1e-3 + 1e-9).astype(np.float64)
    assert read(far)[0] == 0.0


def _bath(per_cell, n_cells, radius):
    """``per_cell`` weight-1 particles at every cell centre of an n_cells^3 grid of 1 mm cells."""
    centres = (np.indices((n_cells,) * 3).reshape(3, -1).T + 0.5) * 1e-3
    return np.repeat(centres, per_cell, axis=0)


@pytest.mark.parametrize("weight", [8.0, 27.0, 64.0])
@pytest.mark.parametrize("per_cell", [0, 1, 8, 27])
def test_a_parcels_cloud_takes_the_number_density_of_the_particles_around_it(weight, per_cell):
    """A parcel of w real particles in a bath of ``per_cell`` single particles per cell (n h^3 = per_cell, uniform:
    one at each cell centre) gets the cloud of w particles at the bath's spacing h n^(-1/3), per-axis variance
    (w^(2/3) - 1) h^2 n^(-2/3) / 12, i.e. width b = sqrt(w^(2/3) - 1) (n h^3)^(-1/3) cells; with one particle per
    cell or fewer around it the spacing is h (b = sqrt(w^(2/3) - 1)), also when the parcel is alone: its own
    particles do not make the density it is spread at."""
    n_cells = 12
    radius = 100e-6
    rng = np.random.default_rng(int(weight) + 100 * per_cell)
    probe = (6.0 + rng.uniform(0.0, 1.0, 3)) * 1e-3
    bath = _bath(per_cell, n_cells, radius)
    x = np.vstack([probe[None, :], bath])
    w = np.concatenate([[weight], np.ones(len(bath))])
    parts = Particles.from_numpy(x, radius, density=2000.0, weight=w, check_overlap=False)
    grid = GridSpec(origin=(0.0, 0.0, 0.0), spacing=1e-3, shape=(n_cells,) * 3, periodic=(True, True, True))
    fields = CouplingFields.allocate(grid, len(x))
    deposit_parcels(grid, parts, fields)
    assert fields.cloud_on
    b = fields.parcel_cloud.numpy()
    expect = math.sqrt(weight ** (2.0 / 3.0) - 1.0) * min(1.0, max(per_cell, 1e-30) ** (-1.0 / 3.0))
    assert b[0] == pytest.approx(expect, rel=2e-5)
    assert np.all(b[1:] == 0.0)  # the single particles stay trilinear
    volume = w.sum() * 4.0 / 3.0 * math.pi * float(np.float32(radius)) ** 3
    assert fields.cell_solid_volume.numpy().sum() == pytest.approx(volume, rel=1e-12)


def test_weight_one_is_trilinear_with_either_cloud_rule():
    """Without weighted parcels the cloud rule computes nothing and the deposit is the trilinear one, bit for bit."""
    parts, _ = random_parcels(300, seed=3, weight=1.0)
    out = []
    for density in (True, False):
        grid = GridSpec(origin=GRID.origin, spacing=GRID.spacing, shape=GRID.shape, cloud_density=density)
        fields = CouplingFields.allocate(grid, parts.count)
        deposit_parcels(grid, parts, fields)
        assert not fields.cloud_on
        out.append(fields.cell_solid_volume.numpy())
    assert np.array_equal(out[0], out[1])


@wp.kernel
def _cloud_support_kernel(b: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.int32)):
    tid = wp.tid()
    out[tid] = cloud_support(wp.float64(b[tid]))


def test_the_host_knows_each_cloud_before_the_launch():
    """The host's bound on a cloud's stencil (what sizes the deterministic deposit's records on CUDA,
    ``coupling.tent_support_host``) is the kernel's ``cloud_support`` for every float32 width, the widest cloud a
    weight can get (alone) is ``cloud_width_host``'s, and the bound covers both rules' stencils."""
    from hel_warp.parcels.coupling import tent_support_host
    from kernels.interp import cloud_support_host, cloud_width_host, spread_half_width_host

    widths = np.concatenate([np.linspace(0.0, 12.0, 2401), np.float32([2.0, 4.0, 6.0]) + np.float32(1e-6)])
    widths = widths.astype(np.float32)
    out = wp.zeros(len(widths), dtype=wp.int32)
    wp.launch(_cloud_support_kernel, dim=len(widths), inputs=[wp.array(widths, dtype=wp.float32)], outputs=[out])
    assert np.array_equal(out.numpy(), [cloud_support_host(float(b)) for b in widths])
    grid = GridSpec(origin=(0.0, 0.0, 0.0), spacing=1e-3, shape=(12, 12, 12), periodic=(True, True, True))
    for weight in (2.0, 8.0, 27.0, 64.0, 1000.0):
        alone = Particles.from_numpy(np.full((1, 3), 6.3e-3), 100e-6, weight=weight, check_overlap=False)
        fields = CouplingFields.allocate(grid, 1)
        deposit_parcels(grid, alone, fields)
        assert fields.parcel_cloud.numpy()[0] == pytest.approx(cloud_width_host(weight), rel=1e-6)
        k = tent_support_host(grid, weight)
        assert k >= cloud_support_host(cloud_width_host(weight)) and k >= spread_half_width_host(True, weight)
