"""Gas step: projection, laminar duct flow against the analytic series, junction mass balance,
momentum balance of the particle source, error paths.

References: continuity d(eps_f)/dt + div(eps_f u) = 0 (paper eq. 1); fully developed laminar
flow in a rectangular duct (White, *Viscous Fluid Flow*, 3rd ed., eq. 3-48); conservation of
mass (junction) and momentum (source impulse).
"""

import dataclasses
import math

import numpy as np
import pytest
import warp as wp

from hel_warp.errors import ConfigError, HelWarpError
from hel_warp.gas.solver import GasConfig, GasField, GasSolver
import hel_warp.gas.solver as gas_module
from hel_warp.gas.multigrid import COARSEST_ROWS_CUDA
from hel_warp.gas.grid import Box, Channel, Geometry, Grid, Patch
from kernels import gas as K
from kernels import gas_cpu


def continuity_residual(grid, fluid, face_u, cell_eps_f, cell_eps_prev, dt):
    """div(eps_f u) + d eps_f/dt per cell, recomputed in numpy from the face velocities.

    Face eps_f = mean of the adjacent fluid cells (periodic wrap), independent of the kernels.
    """
    h = grid.spacing
    div = (cell_eps_f - cell_eps_prev) / dt
    for axis in range(3):
        u = face_u[axis].astype(np.float64)
        eps_cell = np.where(fluid, cell_eps_f, 0.0)
        count = fluid.astype(np.float64)
        if grid.periodic[axis]:
            eps_lo, cnt_lo = np.roll(eps_cell, 1, axis), np.roll(count, 1, axis)
        else:
            pad = [(0, 0)] * 3
            pad[axis] = (1, 0)
            eps_lo = np.pad(eps_cell, pad)[tuple(slice(0, n) for n in eps_cell.shape)]
            cnt_lo = np.pad(count, pad)[tuple(slice(0, n) for n in count.shape)]
        # face eps at the low face of every cell
        eps_face_lo = np.where(cnt_lo + count > 0, (eps_lo + eps_cell) / np.maximum(cnt_lo + count, 1), 1.0)
        if grid.periodic[axis]:
            eps_face_hi = np.roll(eps_face_lo, -1, axis)
        else:
            pad = [(0, 0)] * 3
            pad[axis] = (0, 1)
            eps_hi_cell = np.pad(eps_cell, pad)[tuple(slice(1, n + 1) if a == axis else slice(None)
                                                       for a, n in enumerate(eps_cell.shape))]
            cnt_hi = np.pad(count, pad)[tuple(slice(1, n + 1) if a == axis else slice(None)
                                              for a, n in enumerate(count.shape))]
            eps_face_hi = np.where(cnt_hi + count > 0, (eps_hi_cell + eps_cell) / np.maximum(cnt_hi + count, 1), 1.0)
        lo = [slice(None)] * 3
        lo[axis] = slice(0, -1)
        hi = [slice(None)] * 3
        hi[axis] = slice(1, None)
        div = div + (eps_face_hi * u[tuple(hi)] - eps_face_lo * u[tuple(lo)]) / h
    return np.where(fluid, div, 0.0)


def inlet_duct_20ms():
    """A 5 mm square duct 25 mm long on h = 1.25 mm cells (20 x 4 x 4), 20 m/s inlet, outlet opposite."""
    h, width, length = 1.25e-3, 5e-3, 25e-3
    grid = Grid(spacing=h, shape=(20, 4, 4))
    geometry = Geometry(shapes=(Box(lo=(-1e-3, 0, 0), hi=(length + 1e-3, width, width)),),
                        patches=(Patch(name="in", kind="inlet", axis=0, side="min", velocity=(20.0, 0, 0)),
                                 Patch(name="out", kind="outlet", axis=0, side="max")))
    return geometry.build(grid)


@pytest.mark.parametrize("case,linear_solver,preconditioner,relaxation", [
    ("periodic", "native", "multigrid", 0.0), ("walls", "native", "multigrid", 0.0), ("walls", "native", "ic", 0.97),
    ("walls", "native", "ic", 0.0), ("walls", "warp", "multigrid", 0.0), ("walls", "warp", "ic", 0.0)])
def test_projection_divergence_free(case, linear_solver, preconditioner, relaxation):
    """After the projection, div(eps_f u) + d eps_f/dt = 0 to the CG tolerance.

    The CG stops at ||r|| <= tol ||b|| with r = (rho h^2/dt)(continuity residual) and
    b = (rho h^2/dt)(residual before, mean removed), so ||after|| <= tol ||before|| plus
    float32 rounding of the stored face velocities (~1e-7 |u|/h per cell).
    """
    rng = np.random.default_rng(1)
    periodic = case == "periodic"
    grid = Grid(spacing=1e-3, shape=(12, 10, 8), periodic=(periodic,) * 3)
    if periodic:
        geometry = Geometry(shapes=(Box(lo=(-1, -1, -1), hi=(1, 1, 1)),))
    else:  # a closed L-shaped cavity: box + inclined channel, no-slip walls
        geometry = Geometry(shapes=(Box(lo=(1e-3, 1e-3, 1e-3), hi=(7e-3, 9e-3, 7e-3)),
                                    Channel(start=(4e-3, 5e-3, 4e-3), end=(11e-3, 8e-3, 4e-3),
                                            width=3.5e-3, height=5e-3)))
    domain = geometry.build(grid)
    tol = 1e-6
    solver = GasSolver(domain, GasConfig(pressure_tolerance=tol, linear_solver=linear_solver,
                                         pressure_preconditioner=preconditioner,
                                         pressure_preconditioner_relaxation=relaxation))
    gas = GasField(domain)
    gas.set_face_velocity([rng.normal(size=a.shape) for a in gas.face_arrays()])
    eps_s = rng.uniform(0.0, 0.7, size=grid.shape).astype(np.float32)  # clipped at 0.63 inside
    gas.cell_eps_s.assign(eps_s)
    dt = 1e-3
    solver.update_cell_state(gas)
    fluid = domain.cell_fluid.numpy().astype(bool)
    eps_f = gas.cell_eps_f.numpy().astype(np.float64)
    assert np.allclose(eps_f[fluid], np.clip(1 - eps_s[fluid], 0.37, 1.0), atol=1e-7)
    assert eps_f[fluid].min() < 0.5 < eps_f[fluid].max()  # eps_f really varies
    # eps_f of the previous step: a zero-mean change, so the total gas volume of the closed
    # (or periodic) box is conserved and the continuity problem is solvable
    change = rng.uniform(-0.05, 0.05, size=grid.shape)
    change = np.where(fluid, change - change[fluid].mean(), 0.0)
    eps_prev = eps_f - change
    gas.cell_eps_f_prev.assign(eps_prev.astype(np.float32))
    eps_prev = gas.cell_eps_f_prev.numpy().astype(np.float64)

    before = continuity_residual(grid, fluid, gas.face_arrays(), eps_f, eps_prev, dt)
    before = np.where(fluid, before - before[fluid].mean(), 0.0)  # the compatible part
    solver.project(gas, dt)
    after = continuity_residual(grid, fluid, gas.face_arrays(), eps_f, eps_prev, dt)
    u_max = max(np.abs(a).max() for a in gas.face_arrays())
    rounding = 4 * 6e-8 * u_max / grid.spacing * math.sqrt(fluid.sum())
    ratio = np.linalg.norm(after) / np.linalg.norm(before)
    assert np.linalg.norm(after) <= tol * np.linalg.norm(before) + rounding, ratio
    assert ratio < 1e-5
    print(f"{case}/{linear_solver}/{preconditioner}/{relaxation}: |continuity residual| after/before = {ratio:.2e} "
          f"({solver.last_iterations['pressure']} CG iterations)")


def duct_series(y, z, a, b, dpdx, mu, terms=201):
    """Fully developed laminar flow in the duct -a<y<a, -b<z<b (White, eq. 3-48):

    u = 16 a^2 (-dp/dx) / (mu pi^3) sum_{n=1,3,..} (-1)^((n-1)/2) / n^3
        [1 - cosh(n pi z / 2a) / cosh(n pi b / 2a)] cos(n pi y / 2a).
    """
    u = np.zeros(np.broadcast(y, z).shape)
    for n in range(1, 2 * terms, 2):
        k = n * math.pi / (2 * a)
        # cosh ratio written with exponentials to avoid overflow
        ratio = np.exp(k * (np.abs(z) - b)) * (1 + np.exp(-2 * k * np.abs(z))) / (1 + np.exp(-2 * k * b))
        u += (-1) ** ((n - 1) // 2) / n**3 * (1 - ratio) * np.cos(k * y)
    return 16 * a**2 * (-dpdx) / (mu * math.pi**3) * u


def test_duct_series_reference():
    """The reference itself against White's flow-rate series (eq. 3-49):
    Q = 4 b a^3 (-G) / (3 mu) [1 - 192 a / (pi^5 b) sum_{n odd} tanh(n pi b / 2a) / n^5],
    and the known centre value 0.2947 (-G) a^2 / mu of the square duct."""
    a, b, mu, G = 1.0, 0.5, 1.0, -1.0
    series = sum(math.tanh(n * math.pi * b / (2 * a)) / n**5 for n in range(1, 400, 2))
    flow = 4 * b * a**3 * (-G) / (3 * mu) * (1 - 192 * a / (math.pi**5 * b) * series)
    m = 400  # midpoint rule, error ~ (2b/m)^2 / 24 relative to the curvature: < 1e-4
    y = -a + (np.arange(m) + 0.5) * 2 * a / m
    z = -b + (np.arange(m) + 0.5) * 2 * b / m
    yy, zz = np.meshgrid(y, z, indexing="ij")
    midpoint = duct_series(yy, zz, a, b, G, mu, terms=100).sum() * (2 * a / m) * (2 * b / m)
    assert midpoint == pytest.approx(flow, rel=1e-4)
    assert duct_series(0.0, 0.0, a, a, G, mu) == pytest.approx(0.2947, abs=2e-4)


@pytest.mark.slow
def test_square_duct_poiseuille(full_size):
    """Periodic square duct driven by a mean pressure gradient matches the series within 2 %.

    Resolution: the wall condition (ghost value -u at h/2) interpolates a parabola linearly,
    an error h^2 u''/8 = h^2 G/(8 mu) on a profile of amplitude ~G a^2/(2 mu) (plane flow),
    i.e. ~ (h/2a)^2 = 1/N^2 of the peak: N >= 8 cells across keeps it below 2 %, N = 12 gives
    ~0.7 %. Backward-Euler steps with dt = 0.05 s damp the slowest mode (rate nu pi^2/(2 a^2))
    by 1/(1 + rate dt) per step, so 60 steps reach the discrete steady state to < 1e-9.
    """
    n = 24 if full_size else 12
    side = 4e-3
    h = side / n
    mu, rho, G = 1.81e-5, 1.205, -1.0
    grid = Grid(spacing=h, shape=(3, n, n), periodic=(True, False, False))
    geometry = Geometry(shapes=(Box(lo=(-1.0, 0.0, 0.0), hi=(1.0, side, side), name="duct"),))
    domain = geometry.build(grid)
    solver = GasSolver(domain, GasConfig(density=rho, viscosity=mu, smagorinsky_constant=0.0,
                                         mean_pressure_gradient=(G, 0.0, 0.0)))
    gas = GasField(domain)
    for _ in range(60):
        solver.step(gas, 0.05)
    u = gas.face_arrays()[0][1]  # x-faces of the middle slab, at cell centres in (y, z)
    centres = (np.arange(n) + 0.5) * h - side / 2
    yy, zz = np.meshgrid(centres, centres, indexing="ij")
    exact = duct_series(yy, zz, side / 2, side / 2, G, mu)
    error = np.abs(u - exact).max() / exact.max()
    print(f"duct N={n}: max error {error:.4%} of the peak, centre {u.max():.5f} vs {exact.max():.5f} m/s")
    assert error < 0.02
    # the gradient reported to the particles is the imposed one (fully developed flow)
    grad_p = gas.cell_grad_p.numpy()
    assert np.allclose(grad_p[..., 0], G, rtol=1e-4)
    assert np.abs(grad_p[..., 1:]).max() < 1e-3 * abs(G)
    assert np.abs(gas.face_arrays()[1]).max() < 1e-6 * exact.max()


@pytest.mark.slow
def test_junction_mass_balance(full_size):
    """Y junction: main inlet (-x side) + inclined side inlet (+y side) -> outlet (+x side).

    At steady state the outlet mass flow equals the sum of the inlets within 0.5 %.
    """
    h = 1e-3 if full_size else 1.25e-3
    width = 5e-3
    length, top = 24e-3, 14e-3
    grid = Grid(spacing=h, shape=(round(length / h), round(top / h), round(width / h)))
    direction = np.array([1.0, -1.0, 0.0]) / math.sqrt(2.0)
    u_main, u_side = 2.0, 1.5
    geometry = Geometry(
        shapes=(Box(lo=(-1e-3, 0.0, 0.0), hi=(length + 1e-3, width, width), name="main"),
                Channel(start=(4e-3, top + 2e-3, width / 2), end=(4e-3 + top + 2e-3 - width / 2, width / 2, width / 2),
                        width=width, height=width, name="branch")),
        patches=(Patch(name="main_in", kind="inlet", axis=0, side="min", velocity=(u_main, 0, 0)),
                 Patch(name="side_in", kind="inlet", axis=1, side="max", velocity=tuple(u_side * direction)),
                 Patch(name="out", kind="outlet", axis=0, side="max", pressure=0.0)))
    domain = geometry.build(grid)
    solver = GasSolver(domain, GasConfig())
    gas = GasField(domain)
    steps = 150 if full_size else 80  # ~5 transit times of the main channel at 1e-3 s
    flows = []
    for _ in range(steps):
        solver.step(gas, 1e-3)
        faces, eps = gas.face_arrays(), gas.face_arrays(gas.face_eps)
        flows.append([domain.patch_mass_flow(name, faces, eps, 1.205) for name in ("main_in", "side_in", "out")])
    m_main, m_side, m_out = flows[-1]
    assert m_main < 0 and m_side < 0 and m_out > 0
    # inlet flows are fixed: u_normal * h^2 * faces
    assert -m_main == pytest.approx(1.205 * u_main * h * h * domain.patch_faces["main_in"][1].sum(), rel=1e-6)
    imbalance = abs(m_out + m_main + m_side) / (-(m_main + m_side))
    print(f"junction: inlets {-m_main:.4e} + {-m_side:.4e} kg/s, outlet {m_out:.4e} kg/s, imbalance {imbalance:.2e}")
    assert imbalance < 0.005
    # steady: the outlet flow changed by < 0.1 % over the last 10 steps
    assert abs(flows[-1][2] - flows[-10][2]) / m_out < 1e-3
    cell_u = gas.cell_velocity.numpy()
    assert np.isfinite(cell_u).all() and np.abs(cell_u).max() < 5 * u_main


def test_momentum_source_balance():
    """Periodic box, uniform eps_f: the gas momentum rho sum eps V u grows by exactly the
    impulse deposited (Newton's third law with the particles), projection and viscosity included."""
    rng = np.random.default_rng(3)
    grid = Grid(spacing=1e-3, shape=(8, 8, 8), periodic=(True, True, True))
    domain = Geometry(shapes=(Box(lo=(-1, -1, -1), hi=(1, 1, 1)),)).build(grid)
    rho = 1.205
    solver = GasSolver(domain, GasConfig(density=rho))
    gas = GasField(domain)
    gas.cell_eps_s.fill_(0.2)
    impulse = rng.normal(scale=1e-9, size=grid.shape + (3,)).astype(np.float32)
    gas.cell_momentum_source.assign(impulse)
    solver.step(gas, 1e-3)
    u = gas.face_arrays()
    momentum = [rho * 0.8 * grid.cell_volume * u[a][tuple(slice(0, n) for n in grid.shape)].sum() for a in range(3)]
    expected = impulse.astype(np.float64).sum(axis=(0, 1, 2))
    assert np.allclose(momentum, expected, rtol=1e-4, atol=1e-6 * np.abs(impulse).sum())


def test_nonconvergence_names_the_fix():
    grid = Grid(spacing=1e-3, shape=(8, 8, 8), periodic=(True, True, True))
    domain = Geometry(shapes=(Box(lo=(-1, -1, -1), hi=(1, 1, 1)),)).build(grid)
    solver = GasSolver(domain, GasConfig(pressure_max_iterations=2, pressure_tolerance=1e-12))
    gas = GasField(domain)
    gas.set_face_velocity([np.random.default_rng(0).normal(size=a.shape) for a in gas.face_arrays()])
    with pytest.raises(HelWarpError, match="pressure_max_iterations"):
        solver.step(gas, 1e-3)


def test_nan_input_is_reported():
    grid = Grid(spacing=1e-3, shape=(6, 6, 6), periodic=(True, True, True))
    domain = Geometry(shapes=(Box(lo=(-1, -1, -1), hi=(1, 1, 1)),)).build(grid)
    solver = GasSolver(domain, GasConfig())
    gas = GasField(domain)
    source = np.zeros(grid.shape + (3,), dtype=np.float32)
    source[2, 2, 2, 0] = np.nan
    gas.cell_momentum_source.assign(source)
    with pytest.raises(HelWarpError, match="NaN"):
        solver.step(gas, 1e-3)


def test_config_errors():
    with pytest.raises(ConfigError, match="smagorinsky"):
        GasConfig(smagorinsky_constant=-0.1)
    with pytest.raises(ConfigError, match="pressure_multigrid_scale"):
        GasConfig(pressure_multigrid_scale=2.2)
    with pytest.raises(ConfigError, match="dt"):
        grid = Grid(spacing=1e-3, shape=(4, 4, 4), periodic=(True, True, True))
        domain = Geometry(shapes=(Box(lo=(-1, -1, -1), hi=(1, 1, 1)),)).build(grid)
        GasSolver(domain).step(GasField(domain), 0.0)


def test_stable_at_high_cfl():
    """Paper conditions: 20 m/s inlets, dt = 1e-3 s on h = 1.25 mm (CFL = 16), Smagorinsky on.

    Semi-Lagrangian advection interpolates (no new extrema) and the viscous step is backward
    Euler, so the speed stays bounded by a small multiple of the inlet speed (the projection can
    accelerate the flow where it is squeezed, never without bound) and mass balances at every step.
    """
    domain = inlet_duct_20ms()
    solver = GasSolver(domain, GasConfig())
    gas = GasField(domain)
    for _ in range(30):
        solver.step(gas, 1e-3)
        faces = gas.face_arrays()
        m_in, m_out = (domain.patch_mass_flow(name, faces, None, 1.205) for name in ("in", "out"))
        assert abs(m_in + m_out) <= 1e-5 * abs(m_in)
        assert max(np.abs(a).max() for a in faces) < 3 * 20.0
    assert gas.cell_nu_t.numpy().max() > 0.0  # the sub-grid viscosity is active in the sheared flow


def test_step_is_deterministic():
    """Two runs from the same state give bit-identical fields (the CG dot products use
    atomic sums; on the CPU they run in a fixed order)."""
    def run():
        rng = np.random.default_rng(7)
        grid = Grid(spacing=1e-3, shape=(8, 6, 6), periodic=(True, True, True))
        domain = Geometry(shapes=(Box(lo=(-1, -1, -1), hi=(1, 1, 1)),)).build(grid)
        solver, gas = GasSolver(domain, GasConfig()), GasField(domain)
        gas.set_face_velocity([rng.normal(size=a.shape) for a in gas.face_arrays()])
        gas.cell_eps_s.assign(rng.uniform(0, 0.5, size=grid.shape).astype(np.float32))
        for _ in range(3):
            solver.step(gas, 1e-3)
        return gas.cell_velocity.numpy(), gas.cell_grad_p.numpy()
    (u1, g1), (u2, g2) = run(), run()
    assert np.array_equal(u1, u2) and np.array_equal(g1, g2)


def test_pressure_carries_a_uniform_particle_force():
    """Closed box, gas at rest, eps_f = 0.7, particles pushing the gas down with a uniform force
    density S (N/m^3): the steady solution of eq. (2) is u = 0 with eps_f grad p' = S, i.e.
    grad p' = S / eps_f in every cell (the bed's pressure drop), wall cells included. The
    incremental projection makes this balance a fixed point of the step."""
    grid = Grid(spacing=1e-3, shape=(6, 6, 10))
    domain = Geometry(shapes=(Box(lo=(0, 0, 0), hi=(6e-3, 6e-3, 10e-3)),)).build(grid)
    solver, gas = GasSolver(domain, GasConfig()), GasField(domain)
    dt, force_density, eps_s = 1e-3, np.array([0.0, 30.0, -100.0]), 0.3
    gas.cell_eps_s.fill_(eps_s)
    impulse = np.broadcast_to(force_density * grid.cell_volume * dt, grid.shape + (3,)).astype(np.float32)
    gas.cell_momentum_source.assign(impulse)
    speeds = []
    for _ in range(12):
        solver.step(gas, dt)
        speeds.append(max(np.abs(a).max() for a in gas.face_arrays()))
    grad_p = gas.cell_grad_p.numpy()
    expected = force_density / (1.0 - eps_s)
    assert np.allclose(grad_p, expected, rtol=1e-3, atol=1e-3 * np.abs(expected).max())
    # the start-up splitting error (first step: p^0 = 0, viscous step before projection) leaves
    # a weak flow that decays: below 5 % of the velocity the force alone would give in one step
    unbalanced = np.abs(force_density).max() * dt / (1.205 * (1.0 - eps_s))
    assert speeds[-1] < 0.05 * unbalanced and speeds[-1] < 0.6 * speeds[0]


def _gas_fields(gas):
    """Every array of a GasField, by name (face structs as name.x/y/z), as float64 host copies."""
    out = {}
    for name, value in vars(gas).items():
        if isinstance(value, wp.array):
            out[name] = value.numpy().astype(np.float64)
        elif isinstance(getattr(value, "x", None), wp.array):
            out.update({f"{name}.{a}": getattr(value, a).numpy().astype(np.float64) for a in "xyz"})
    return out


@pytest.mark.parametrize("case", ["inlet_outlet", "periodic"])
@pytest.mark.parametrize("linear_solver", ["native", "warp"])
def test_fluid_launches_match_the_whole_box(case, linear_solver):
    """The cell and face kernels launched over the fluid cells and solved faces only (``launch_over='fluid'``,
    the default) give the fields of the same kernels launched over every cell and face of the box, step after
    step, on a masked box: the same arithmetic per entry, so equal up to the order of the atomic sums of the
    pressure right-hand side (float64, on a GPU), far below float32 round-off of the stored fields. The solid
    cells hold the constants the interpolation to parcels reads: eps_f 1, velocity 0, grad p' the imposed
    mean gradient."""
    domain, config = _masked_case(case, linear_solver)
    grid = domain.grid
    fluid = domain.cell_fluid.numpy().astype(bool)
    assert 0.3 < fluid.mean() < 0.9  # a real mask
    runs = {}
    for launch_over in ("box", "fluid"):
        solver = GasSolver(domain, config, launch_over=launch_over)
        runs[launch_over] = _three_steps(solver, domain), solver.last_iterations
    assert runs["box"][1] == runs["fluid"][1]  # the same CG iterations
    for box, fluid_only in zip(runs["box"][0], runs["fluid"][0]):
        assert box.keys() == fluid_only.keys()
        for name, expected in box.items():
            scale = max(np.abs(expected).max(), 1e-30)
            assert np.allclose(fluid_only[name], expected, rtol=1e-6, atol=1e-6 * scale), name
    last = runs["fluid"][0][-1]
    assert np.all(last["cell_eps_f"][~fluid] == 1.0) and np.all(last["cell_velocity"][~fluid] == 0.0)
    imposed = np.asarray(config.mean_pressure_gradient)
    assert np.allclose(last["cell_grad_p"][~fluid], imposed, rtol=1e-6, atol=0.0)


def _masked_case(case, linear_solver):
    """The masked boxes of ``test_fluid_launches_match_the_whole_box``: (domain, config)."""
    if case == "inlet_outlet":  # a box with an inclined channel, an inlet and an outlet: walls, inlet, outlet faces
        grid = Grid(spacing=1e-3, shape=(14, 10, 8))
        geometry = Geometry(shapes=(Box(lo=(0, 1e-3, 1e-3), hi=(14e-3, 8e-3, 7e-3)),
                                    Channel(start=(4e-3, 5e-3, 4e-3), end=(11e-3, 8e-3, 4e-3), width=3.5e-3,
                                            height=5e-3)),
                            patches=(Patch(name="in", kind="inlet", axis=0, side="min", velocity=(0.3, 0.05, 0.0)),
                                     Patch(name="out", kind="outlet", axis=0, side="max")))
        config = GasConfig(linear_solver=linear_solver)
    else:  # periodic in x and z (alias faces) with solid walls in y, driven by a mean pressure gradient
        grid = Grid(spacing=1e-3, shape=(12, 9, 7), periodic=(True, False, True))
        geometry = Geometry(shapes=(Box(lo=(-1, 1e-3, -1), hi=(1, 7e-3, 1)),
                                    Box(lo=(3e-3, 0, 2e-3), hi=(6e-3, 9e-3, 5e-3))))
        config = GasConfig(linear_solver=linear_solver, mean_pressure_gradient=(-2.0, 0.0, 0.5))
    return geometry.build(grid), config


def _three_steps(solver, domain, count=3, after_step=None):
    """Three (``count``) steps of ``solver`` from random face velocities with random eps_s and particle sources
    (seeded): the GasField arrays after each (``_gas_fields``); ``after_step(solver)`` runs after each step."""
    rng = np.random.default_rng(5)
    gas, shape = GasField(domain), domain.grid.shape
    gas.set_face_velocity([rng.normal(0.0, 0.2, size=a.shape) for a in gas.face_arrays()])
    fields = []
    for _ in range(count):
        gas.cell_eps_s.assign(rng.uniform(0.0, 0.4, shape).astype(np.float32))
        gas.cell_momentum_source.assign(rng.normal(0.0, 1e-9, shape + (3,)).astype(np.float32))
        solver.step(gas, 1e-3)
        fields.append(_gas_fields(gas))
        if after_step is not None:
            after_step(solver)
    return fields


@pytest.mark.parametrize("case", ["inlet_outlet", "periodic"])
@pytest.mark.parametrize("linear_solver", ["native", "warp"])
def test_native_cpu_loops_give_the_warp_kernels_step(case, linear_solver, monkeypatch):
    """On the CPU ``GasSolver`` and its V-cycle launch kernels/gas_cpu.py's native loops (solvers, advection,
    pressure right-hand side, Smagorinsky, the projection's cell pass); with them switched off
    (``gas_cpu.for_device`` handing back the Warp kernels) three steps on a masked box with walls, an inlet and an
    outlet, or periodic axes, give every GasField array bit for bit and the same CG iterations."""
    domain, config = _masked_case(case, linear_solver)
    native_solver = GasSolver(domain, config)
    native = _three_steps(native_solver, domain)
    monkeypatch.setattr(gas_cpu, "for_device", lambda kernel, dim, device, arguments: (kernel, dim))
    warp_solver = GasSolver(domain, config)
    reference = _three_steps(warp_solver, domain)
    assert native_solver.last_iterations == warp_solver.last_iterations
    for step_native, step_warp in zip(native, reference):
        for name, expected in step_warp.items():
            assert np.array_equal(step_native[name], expected, equal_nan=True), name


@pytest.mark.parametrize("case", ["inlet_outlet", "periodic"])
def test_the_gpus_dot_chunks_give_the_cpus_step_to_the_solver_tolerance(case, monkeypatch):
    """A GPU's native PCG sums DOT_CHUNK_CUDA rows per thread where the CPU sums DOT_CHUNK, and its V-cycle coarsens
    to COARSEST_ROWS_CUDA rows (``device_tuning``): the same CG in another order of additions, with a coarser last
    level. Run on the CPU with the Warp kernels (as on CUDA) and the GPU's shapes, three steps on the masked boxes give the CPU's fields to the solvers' tolerance (every field within 1e-6
    of its largest value; the periodic box's pressure, whose level nothing fixes, up to a constant) and the last step's CG iterations within one; the recorded dot-product launches are over
    ceil(rows / DOT_CHUNK_CUDA) threads."""
    domain, config = _masked_case(case, "native")
    cpu = GasSolver(domain, config)
    reference = _three_steps(cpu, domain)
    monkeypatch.setattr(gas_cpu, "for_device", lambda kernel, dim, device, arguments: (kernel, dim))
    monkeypatch.setattr(gas_module, "device_tuning", lambda device: {"dot_chunk": K.DOT_CHUNK_CUDA,
                                                                      "coarsest_rows": COARSEST_ROWS_CUDA})
    solver = GasSolver(domain, config)
    assert solver.dot_chunk == K.DOT_CHUNK_CUDA
    gpu_levels, cpu_levels = solver._pressure_mg.rows_per_level, cpu._pressure_mg.rows_per_level
    assert gpu_levels[:len(cpu_levels)] == cpu_levels  # the CPU's levels, then coarser ones where the grid allows
    assert gpu_levels[-1] <= cpu_levels[-1]
    if case == "inlet_outlet":
        assert len(gpu_levels) > len(cpu_levels)
    fields = _three_steps(solver, domain)
    rows = solver._systems["pressure"][0].shape[0]
    start = solver._pcg_recorded["pressure"]["r = b - A x, b.b, r.r"]
    assert start.bounds.shape[0] == (rows + K.DOT_CHUNK_CUDA - 1) // K.DOT_CHUNK_CUDA
    assert solver.last_iterations["pressure"] > 0
    assert abs(solver.last_iterations["pressure"] - cpu.last_iterations["pressure"]) <= 1
    assert all(abs(a - b) <= 1 for a, b in zip(solver.last_iterations["viscous"], cpu.last_iterations["viscous"]))
    for step, step_ref in zip(fields, reference):
        for name, expected in step_ref.items():
            scale = float(np.nanmax(np.abs(expected))) or 1.0
            actual = step[name]
            if "pressure" in name and "grad" not in name and case == "periodic":  # no level fixed: up to a constant
                fluid = domain.cell_fluid.numpy().astype(bool).reshape(-1)
                flat = actual.reshape(-1) if actual.size == fluid.size else None
                if flat is not None:
                    shift = float(np.mean(flat[fluid] - expected.reshape(-1)[fluid]))
                    actual = np.where(fluid, flat - shift, flat).reshape(actual.shape)
            np.testing.assert_allclose(actual, expected, rtol=0, atol=1e-6 * scale, err_msg=name)


@pytest.mark.parametrize("case", ["inlet_outlet", "periodic"])
@pytest.mark.parametrize("preconditioners", [("multigrid", "red_black"), ("ic", "ic0"), ("multigrid", "jacobi")],
                         ids=["multigrid-red_black", "ic-ic0", "multigrid-jacobi"])
def test_the_device_side_cg_loop_gives_the_host_loops_bits(case, preconditioners):
    """``GasConfig.pcg_device_loop``: each CG as one captured graph, the stop test on the device in a
    ``wp.capture_while`` loop (one read-back per solve), against the host loop that reads ||r|| after every captured
    iteration: three steps on the masked boxes give every GasField array bit for bit and the same iterations, with
    every preconditioner of the pressure and the viscous systems."""
    domain, config = _masked_case(case, "native")
    config = dataclasses.replace(config, pressure_preconditioner=preconditioners[0],
                                 viscous_preconditioner=preconditioners[1])
    host = GasSolver(domain, config)
    assert not host.device_loop  # the default
    reference = _three_steps(host, domain)
    device = GasSolver(domain, dataclasses.replace(config, pcg_device_loop=True))
    assert device.device_loop
    fields = _three_steps(device, domain)
    assert device.last_iterations == host.last_iterations and host.last_iterations["pressure"] > 0
    assert len(device._pcg_solve_graphs) >= 2 and not host._pcg_solve_graphs
    for step, step_ref in zip(fields, reference):
        for name, expected in step_ref.items():
            assert np.array_equal(step[name], expected, equal_nan=True), name


@pytest.mark.parametrize("where", ["guess", "rhs"])
def test_the_device_side_cg_loop_reports_nan_as_the_host_loop_does(where):
    """A NaN in the first guess or the right-hand side: the device-side loop returns the host loop's (iterations,
    ||r||, bound) - one iteration for a NaN residual, a NaN bound for a NaN ||b|| - and the same solution bits, for
    the pressure (V-cycle) and a viscous (red-black) system; the step's own check then raises. After more steps the
    device loop still holds one captured graph per system (its stop test reads tol, atol_floor and maxiter from
    the device)."""
    domain, config = _masked_case("inlet_outlet", "native")
    results = {}
    for loop in (False, True):
        solver = GasSolver(domain, dataclasses.replace(config, pcg_device_loop=loop))
        _three_steps(solver, domain)
        if loop:
            graphs = len(solver._pcg_solve_graphs)
            _three_steps(solver, domain)
            assert len(solver._pcg_solve_graphs) == graphs == 4  # pressure and three viscous systems
        out = []
        for system, kwargs in (("pressure", {"multigrid": solver._pressure_mg, "atol_floor": 1e-12}),
                               (0, {"preconditioner": "red_black"})):
            n = solver._systems[system][0].shape[0]
            rng = np.random.default_rng(2)
            rhs, guess = rng.normal(size=n), rng.normal(size=n)
            (guess if where == "guess" else rhs)[n // 2] = np.nan
            solver._c_rhs.assign(np.concatenate([rhs, np.zeros(solver._c_rhs.shape[0] - n)]))
            solver._c_x.assign(np.concatenate([guess, np.zeros(solver._c_x.shape[0] - n)]))
            if kwargs.get("multigrid") is not None:
                kwargs["multigrid"].setup(solver._stencils[system])
            got = solver._native_pcg(system, n, solver._stencils[system], 1e-8, 50, **kwargs)
            out.append((tuple(repr(float(v)) for v in got), solver._c_x.numpy()[:n].copy()))
        results[loop] = out
    for (host_result, host_x), (device_result, device_x) in zip(results[False], results[True]):
        assert device_result == host_result
        assert np.array_equal(device_x, host_x, equal_nan=True)
    assert results[True][0][0][0] == "1.0"  # a NaN residual takes one iteration


def test_launch_over_is_checked():
    grid = Grid(spacing=1e-3, shape=(4, 4, 4), periodic=(True, True, True))
    domain = Geometry(shapes=(Box(lo=(-1, -1, -1), hi=(1, 1, 1)),)).build(grid)
    with pytest.raises(ConfigError, match="launch_over"):
        GasSolver(domain, launch_over="solid")


@wp.kernel
def _first_stage_pair(g: K.GridInfo, axis: int, faces: wp.array(dtype=wp.vec3i), vel: K.FaceFloat,
                      # outputs
                      direct: wp.array(dtype=wp.vec3), sampled: wp.array(dtype=wp.vec3)):
    f = faces[wp.tid()]
    direct[wp.tid()] = K.velocity_at_face(g, vel, axis, f)
    sampled[wp.tid()] = K.sample_velocity(g, vel, K.face_position(g, axis, f))


@pytest.mark.parametrize("periodic", [(False, False, False), (True, False, True), (True, True, True)])
def test_velocity_at_face_is_the_trilinear_sample_there(periodic):
    """The advection's first RK2 stage takes the velocity at a face from the face and its neighbours
    (``velocity_at_face``); the reference is the trilinear ``sample_velocity`` at the face's position, whose weights
    are 0, 1/2 and 1 there, equal up to the float32 round-off of the sample's grid coordinate s = (x - origin)/h
    (|ds| <= ~2 ulp(|x|) / h, each of the 8 weights off by that much: |du| <= 8 |ds| max|u| + a few ulp of u), on
    every face of a box with walls, odd periodic counts and the alias faces (synced, as a GasField holds them), away
    from the origin."""
    grid = Grid(spacing=1e-3, shape=(7, 5, 6), periodic=periodic, origin=(0.1, -0.02, 0.3))
    domain = Geometry(shapes=(Box(lo=(-1, -1, -1), hi=(1, 1, 1)),)).build(grid)
    gas = GasField(domain)
    rng = np.random.default_rng(3)
    gas.set_face_velocity([rng.normal(0.0, 1.0, size=a.shape) for a in gas.face_arrays()])
    faces = gas.face_velocity
    x_max = max(abs(o) + n * grid.spacing for o, n in zip(grid.origin, grid.shape))
    ds = 2.0 * float(np.spacing(np.float32(x_max))) / grid.spacing
    u_max = max(np.abs(a).max() for a in gas.face_arrays())
    for axis in range(3):
        shape = list(grid.shape)
        shape[axis] += 1
        every = wp.array(np.argwhere(np.ones(shape, dtype=bool)).astype(np.int32), dtype=wp.vec3i)
        direct, sampled = (wp.zeros(every.shape[0], dtype=wp.vec3) for _ in range(2))
        wp.launch(_first_stage_pair, dim=every.shape[0], inputs=[grid.info(), axis, every, faces],
                  outputs=[direct, sampled])
        assert np.allclose(direct.numpy(), sampled.numpy(), rtol=0.0, atol=8.0 * ds * u_max + 1e-6), axis


@pytest.mark.parametrize("periodic", [(False, False, False), (True, False, True)], ids=["walled", "periodic"])
def test_native_advection_equals_the_warp_kernel(periodic):
    """kernels/gas_cpu.py's native advection (what ``GasSolver`` launches on the CPU) gives the face velocities of
    kernels/gas.py's ``ADVECT_KERNELS`` bit for bit, on every face of a box (walls and alias faces keep their value)
    with back-traces of up to ~4 cells that leave the box (clamped) or wrap (periodic axes, odd counts)."""
    grid = Grid(spacing=1e-3, shape=(7, 5, 6), periodic=periodic, origin=(0.1, -0.02, 0.3))
    domain = Geometry(shapes=(Box(lo=(-1, -1, -1), hi=(1, 1, 1)),)).build(grid)
    gas = GasField(domain)
    rng = np.random.default_rng(8)
    gas.set_face_velocity([rng.normal(0.0, 1.0, size=a.shape) for a in gas.face_arrays()])
    for axis in range(3):
        shape = list(grid.shape)
        shape[axis] += 1
        every = wp.array(np.argwhere(np.ones(shape, dtype=bool)).astype(np.int32), dtype=wp.vec3i)
        native, dim = gas_cpu.for_device(K.ADVECT_KERNELS[axis], 3, "cpu", [])
        assert native is not K.ADVECT_KERNELS[axis]
        results = []
        for kernel in (K.ADVECT_KERNELS[axis], native):
            out = GasField._faces(grid, None, fill=np.nan)
            wp.launch(kernel, dim=(every.shape[0] + 15) // 16,
                      inputs=[16, grid.info(), every, domain.face_type, gas.face_velocity, 4e-3, out])
            results.append((out.x, out.y, out.z)[axis].numpy())
        assert np.isfinite(results[0]).all() and np.array_equal(results[0], results[1]), axis


def _stencil_system(shape, periodic, seed):
    """A 7-point SPD system on the cells of ``shape`` with a random mask (the compact rows of ``GasSolver``:
    ascending flat order, slots -x, +x, -y, +y, -z, +z, an unused slot coef 0 pointing at its own row): random
    positive couplings, diagonal = mass + their sum (a viscous-like M + K)."""
    rng = np.random.default_rng(seed)
    fluid = rng.uniform(size=shape) < 0.8
    rows = np.flatnonzero(fluid.ravel())
    row_of = np.full(fluid.size, -1)
    row_of[rows] = np.arange(rows.size)
    coords = np.stack(np.unravel_index(rows, shape), axis=1)
    n = rows.size
    coef = np.zeros((n, 6))
    neighbour = np.repeat(np.arange(n)[:, None], 6, axis=1)
    for a in range(3):
        for side in range(2):
            c = coords.copy()
            c[:, a] += 2 * side - 1
            inside = (c[:, a] >= 0) & (c[:, a] < shape[a])
            if periodic[a]:
                c[:, a] %= shape[a]
                inside[:] = True
            nb = np.full(n, -1)
            nb[inside] = row_of[np.ravel_multi_index(c[inside].T, shape)]
            coupled = nb >= 0
            neighbour[coupled, 2 * a + side] = nb[coupled]
    # symmetric couplings: one random value per pair of neighbours (slot m of r, the opposite slot of j)
    for r in range(n):
        for m in range(6):
            j = neighbour[r, m]
            if j != r and coef[r, m] == 0.0:
                value = rng.uniform(0.2, 1.0)
                coef[r, m] = value
                back = (m // 2) * 2 + (1 - m % 2)
                if neighbour[j, back] == r:
                    coef[j, back] = value
    diag = rng.uniform(0.5, 2.0, n) + coef.sum(axis=1)
    A = K.make_stencil(wp.array(diag, dtype=wp.float64), wp.array(coef, dtype=wp.float64),
                       wp.array(neighbour.astype(np.int32), dtype=wp.int32))
    return A, n, rng


@pytest.mark.parametrize("periodic", [(False, False, False), (True, False, True)])
def test_fused_pcg_kernels_equal_the_separate_passes(periodic):
    """The native PCG's fused passes compute the numbers of the passes they replace, bit for bit on the CPU (the
    same operations on every row, the dot products in the same chunks and partial sums): A p with p.Ap; r = b - A x
    with b.b and r.r; the step x += alpha p, r -= alpha Ap inside IC(0)'s forward substitution, with the slot
    reading of a system without a periodic axis (``ordered``) and with the index tests."""
    A, n, rng = _stencil_system((9, 7, 6), periodic, seed=4)
    coef, neighbour = A.coef.numpy(), A.neighbour.numpy()
    back = [1, 0, 3, 2, 5, 4]
    assert all(coef[neighbour[r, m], back[m]] == coef[r, m] for r in range(n) for m in range(6) if coef[r, m])
    vec = lambda: wp.array(rng.normal(size=n), dtype=wp.float64)  # noqa: E731
    dots = (n + K.DOT_CHUNK - 1) // K.DOT_CHUNK
    one, zero = wp.float64(1.0), wp.float64(0.0)

    p, ap_fused, ap = vec(), wp.zeros(n, dtype=wp.float64), wp.zeros(n, dtype=wp.float64)
    fused, separate = wp.zeros(6, dtype=wp.float64), wp.zeros(6, dtype=wp.float64)
    wp.launch(K.pcg_matvec_dot_kernel, dim=dots, inputs=[A, p, 1, K.DOT_CHUNK], outputs=[ap_fused, fused])
    wp.launch(K.stencil_matvec_kernel, dim=n, inputs=[A, p, p, one, zero], outputs=[ap])
    wp.launch(K.pcg_dot_kernel, dim=dots, inputs=[p, ap, 1, K.DOT_CHUNK], outputs=[separate])
    assert np.array_equal(ap_fused.numpy(), ap.numpy()) and np.array_equal(fused.numpy(), separate.numpy())

    x, b, r_fused = vec(), vec(), wp.zeros(n, dtype=wp.float64)
    fused.zero_()
    separate.zero_()
    wp.launch(K.pcg_residual_start_kernel, dim=dots, inputs=[A, x, b, K.DOT_CHUNK], outputs=[r_fused, fused])
    wp.launch(K.stencil_matvec_kernel, dim=n, inputs=[A, x, b, one, zero], outputs=[ap])
    r = wp.array(b.numpy() - ap.numpy(), dtype=wp.float64)
    wp.launch(K.pcg_dot_kernel, dim=dots, inputs=[b, b, 1, K.DOT_CHUNK], outputs=[separate])
    wp.launch(K.pcg_dot_kernel, dim=dots, inputs=[r, r, 3, K.DOT_CHUNK], outputs=[separate])
    assert np.array_equal(r_fused.numpy(), r.numpy()) and np.array_equal(fused.numpy(), separate.numpy())

    pivot, pivot_inverse = wp.zeros(n, dtype=wp.float64), wp.zeros(n, dtype=wp.float64)
    wp.launch(K.ic0_factor_kernel, dim=1, inputs=[A, n, wp.float64(0.0)], outputs=[pivot, pivot_inverse])
    scalars = wp.array([0.0, 0.0, 0.0, 0.0, 0.37, 0.0], dtype=wp.float64)  # alpha in slot 4
    x0, r0, ap = x.numpy(), r.numpy(), vec()
    x_ref, r_ref, z_ref = wp.array(x0, dtype=wp.float64), wp.array(r0, dtype=wp.float64), wp.zeros(n, dtype=wp.float64)
    wp.launch(K.pcg_step_kernel, dim=n, inputs=[p, ap, scalars], outputs=[x_ref, r_ref])
    wp.launch(K.ic0_apply_kernel, dim=1, inputs=[pivot_inverse, A, r_ref, n], outputs=[z_ref])
    for ordered in (0, 1) if periodic == (False, False, False) else (0,):
        x_f, r_f = wp.array(x0, dtype=wp.float64), wp.array(r0, dtype=wp.float64)
        z_f = wp.array(np.full(n, np.nan), dtype=wp.float64)  # stale values: the slot reading must not see them
        wp.launch(K.ic0_step_apply_kernel, dim=1, inputs=[pivot_inverse, A, p, ap, scalars, n, ordered],
                  outputs=[x_f, r_f, z_f])
        for fused_v, ref in ((x_f, x_ref), (r_f, r_ref), (z_f, z_ref)):
            assert np.array_equal(fused_v.numpy(), ref.numpy()), ordered


@pytest.mark.parametrize("periodic", [(False, False, False), (True, False, True)], ids=["walled", "periodic"])
def test_native_cpu_loops_equal_the_warp_kernels(periodic):
    """kernels/gas_cpu.py's native row loops (what ``GasSolver`` and the V-cycle launch on the CPU) give the numbers
    of the Warp kernels they stand for, bit for bit: the same operations on every row in the same order, the dot
    products in the same chunks and partial sums; the IC(0) factor plain and modified, its substitutions with the
    slot reading (``ordered``) and the index tests, and the V-cycle's passes on a two-level aggregation."""
    from hel_warp.gas.multigrid import AggregationMultigrid

    shape = (9, 7, 6)
    A, n, rng = _stencil_system(shape, periodic, seed=5)
    vec = lambda: rng.normal(size=n)  # noqa: E731
    dots = (n + K.DOT_CHUNK - 1) // K.DOT_CHUNK

    def both(name, dim, inputs, outputs):
        """Run kernels/gas.py's ``name`` and its native version on copies of ``outputs`` (numpy); compare."""
        results = []
        for kernel, threads in ((getattr(K, name), dim), gas_cpu.for_device(getattr(K, name), dim, "cpu", inputs)):
            outs = [wp.array(o, dtype=wp.int32 if o.dtype == np.int32 else wp.float64) for o in outputs]
            wp.launch(kernel, dim=threads, inputs=inputs, outputs=outs)
            results.append([o.numpy() for o in outs])
        assert gas_cpu.for_device(getattr(K, name), dim, "cpu", inputs)[0] is not getattr(K, name)
        for warp_out, native_out in zip(*results):
            assert np.array_equal(warp_out, native_out, equal_nan=True), name
        return results[0]

    f64 = lambda a: wp.array(a, dtype=wp.float64)  # noqa: E731
    p, x, b = f64(vec()), f64(vec()), f64(vec())
    scalars = np.array([0.3, 0.0, 0.0, 0.0, 0.37, 0.61])  # alpha in slot 4, beta in slot 5
    both("pcg_matvec_dot_kernel", dots, [A, p, 1, K.DOT_CHUNK], [np.zeros(n), scalars])
    both("pcg_residual_start_kernel", dots, [A, x, b, K.DOT_CHUNK], [np.zeros(n), scalars])
    both("pcg_dot_pair_kernel", dots, [p, b, 2, 3, K.DOT_CHUNK], [scalars])
    both("pcg_step_kernel", n, [p, b, f64(scalars)], [vec(), vec()])
    both("pcg_direction_kernel", n, [x, f64(scalars)], [vec()])
    for relaxation in (0.0, 0.97):
        pivot, pivot_inverse = both("ic0_factor_kernel", 1, [A, n, wp.float64(relaxation)], [np.zeros(n), np.zeros(n)])
    pivot_inverse = f64(pivot_inverse)
    both("ic0_apply_kernel", 1, [pivot_inverse, A, b, n], [np.full(n, np.nan)])
    for ordered in (0, 1) if periodic == (False, False, False) else (0,):
        both("ic0_step_apply_kernel", 1, [pivot_inverse, A, p, b, f64(scalars), n, ordered],
             [vec(), vec(), np.full(n, np.nan)])

    rows = np.flatnonzero(np.random.default_rng(5).uniform(size=shape) < 0.8)  # _stencil_system's mask
    mg = AggregationMultigrid(rows, shape, periodic, "cpu")
    mg.setup(A)
    fine, coarse = mg.levels[0], mg.levels[1]
    inverse_diag = fine.inverse_diag
    coarse_matrices = []
    native = gas_cpu.for_device(K.mg_coarsen_kernel, coarse.n, "cpu", [A])
    for kernel, threads in ((K.mg_coarsen_kernel, coarse.n), native):
        Ac = K.make_stencil(wp.zeros(coarse.n, dtype=wp.float64), wp.zeros((coarse.n, 6), dtype=wp.float64),
                            wp.zeros((coarse.n, 6), dtype=wp.int32))
        wp.launch(kernel, dim=threads, inputs=[coarse.child_start, coarse.children, fine.parent, A], outputs=[Ac])
        coarse_matrices.append([Ac.diag.numpy(), Ac.coef.numpy(), Ac.neighbour.numpy()])
    for warp_out, native_out in zip(*coarse_matrices):
        assert np.array_equal(warp_out, native_out)
    z = vec()
    for colour_rows in fine.colour_rows:
        both("mg_smooth_kernel", colour_rows.shape[0], [A, inverse_diag, colour_rows, b], [z])
    both("mg_smooth_from_zero_kernel", n, [inverse_diag, fine.colour, b], [z])
    both("mg_residual_restrict_kernel", coarse.n,
         [coarse.child_start, coarse.children, fine.parent, A, b, f64(z), fine.colour, fine.n_colours - 1], [np.zeros(coarse.n)])
    both("mg_prolong_kernel", n, [fine.parent, f64(rng.normal(size=coarse.n)), wp.float64(1.7)], [z])


@pytest.mark.parametrize("case", ["inlet_outlet", "periodic", "periodic_even"])
@pytest.mark.parametrize("preconditioner", ["jacobi", "red_black"])
def test_viscous_preconditioners_meet_the_tolerance(case, preconditioner, monkeypatch):
    """``viscous_preconditioner`` 'jacobi' and 'red_black': every viscous solve of three steps on the masked boxes
    meets ||b - A u|| <= viscous_tolerance ||b||, recomputed here in numpy from the compact system (the true residual,
    not CG's recursive one; for 'red_black' it includes the eliminated rows); and the native loops give the Warp
    kernels' fields bit for bit and the same iterations (``test_native_cpu_loops_give_the_warp_kernels_step``).
    The red-black split exists where every coupling joins faces of opposite parity: all three systems of the
    walled box and of the periodic box with even counts (couplings across the wrap); the periodic box with 7 cells
    in z has none (it takes IC(0))."""
    if case == "periodic_even":  # the periodic box with 8 cells in z
        _, config = _masked_case("periodic", "native")
        domain = Geometry(shapes=(Box(lo=(-1, 1e-3, -1), hi=(1, 7e-3, 1)),
                                  Box(lo=(3e-3, 0, 2e-3), hi=(6e-3, 9e-3, 5e-3)))).build(
            Grid(spacing=1e-3, shape=(12, 9, 8), periodic=(True, False, True)))
    else:
        domain, config = _masked_case(case, "native")
    config = dataclasses.replace(config, viscous_preconditioner=preconditioner)
    solver = GasSolver(domain, config)
    assert [split is not None for split in solver._red_black] == [case != "periodic"] * 3
    residuals = []
    solve = solver._solve

    def checked(system, what, tol, maxiter, *args, **kwargs):
        iterations = solve(system, what, tol, maxiter, *args, **kwargs)
        if system in (0, 1, 2):
            m = solver._systems[system][0].shape[0]
            S = solver._stencils[system]
            d, c, nb = S.diag.numpy()[:m], S.coef.numpy()[:m], S.neighbour.numpy()[:m]
            b, x = solver._c_rhs.numpy()[:m], solver._c_x.numpy()[:m]
            residuals.append((np.linalg.norm(b - (d * x - (c * x[nb]).sum(axis=1))) / np.linalg.norm(b), tol))
        return iterations

    monkeypatch.setattr(solver, "_solve", checked)
    native = _three_steps(solver, domain)
    assert len(residuals) == 9 and all(relative <= tol for relative, tol in residuals), residuals
    monkeypatch.setattr(gas_cpu, "for_device", lambda kernel, dim, device, arguments: (kernel, dim))
    warp_solver = GasSolver(domain, config)
    reference = _three_steps(warp_solver, domain)
    assert solver.last_iterations == warp_solver.last_iterations
    for step_native, step_warp in zip(native, reference):
        for name, expected in step_warp.items():
            assert np.array_equal(step_native[name], expected, equal_nan=True), name


def test_native_cpu_module_compiles_for_cuda(tmp_path):
    """kernels/gas_cpu.py only runs on the CPU, but ``wp.force_load(device=...)`` on a GPU (hel_warp/runs/run.py
    ``load_kernels``, scripts/gpu_check.py) builds every module for it: the native snippets must be valid CUDA C++
    as well (compiled here with NVRTC for sm_90 where the toolkit is present, without a GPU)."""
    wp.init()
    if getattr(wp._src.context.runtime, "toolkit_version", None) is None:
        pytest.skip("no CUDA toolkit (NVRTC) in this Warp build")
    artifacts = wp.compile_aot_module(gas_cpu, arch=90, module_dir=str(tmp_path), use_ptx=True)
    assert artifacts and all(path.stat().st_size > 0 for path in artifacts)


def test_viscous_tolerance_keeps_the_float32_field():
    """The default viscous tolerance is float32's unit round-off (2^-24): the step's face velocities then differ
    from those of a solve converged far below round-off (tolerance 1e-13) by no more than a few float32 ulps of
    the largest velocity. Reference: backward-Euler viscous systems with off-diagonal sums up to ~0.8 of the
    diagonal have a condition number <= (1 + 0.8) / (1 - 0.8) = 9, so a relative residual of 2^-24 bounds the
    relative error of the solution by 9 * 2^-24 = 5.4e-7 (~4.5 ulp at the largest velocity)."""
    domain = inlet_duct_20ms()
    assert GasConfig().viscous_tolerance == 2.0**-24
    fields, iterations = {}, {}
    for tol in (GasConfig().viscous_tolerance, 1e-13):
        solver, gas = GasSolver(domain, GasConfig(viscous_tolerance=tol)), GasField(domain)
        for _ in range(5):
            solver.step(gas, 1e-3)
        fields[tol], iterations[tol] = gas.face_arrays(), sum(solver.last_iterations["viscous"])
    default, tight = fields[2.0**-24], fields[1e-13]
    u_max = max(np.abs(a).max() for a in tight)
    error = max(np.abs(d.astype(np.float64) - t).max() for d, t in zip(default, tight))
    print(f"viscous tolerance 2^-24 vs 1e-13: max |du| {error:.3e} m/s = {error / u_max:.2e} of max |u|, "
          f"iterations {iterations[2.0**-24]} vs {iterations[1e-13]}")
    assert error <= 9.0 * 2.0**-24 * u_max + 4 * float(np.spacing(np.float32(u_max)))
    assert iterations[2.0**-24] < iterations[1e-13]


def test_the_device_side_cg_loop_keeps_its_v_cycle_across_steps():
    """The device-side CG loop captures the V-cycle inside its graph. Recorded inside the capture, the CPU
    smoother's colour schedules were copied from host buffers freed before the graph's next replay, so from the
    second step on the pressure's preconditioner read whatever reused that memory (a riser step then took ~105 CG
    iterations against the host loop's 6). Here the host memory is churned between steps (small int32 arrays
    full of 7, the size of a colour schedule): the device loop must still give the host loop's iterations and
    bits at every step."""
    domain, config = _masked_case("periodic", "native")
    config = dataclasses.replace(config, pressure_preconditioner="multigrid", viscous_preconditioner="red_black")
    results = {}
    for loop in (False, True):
        iterations = []

        def churn(solver):
            iterations.append(solver.last_iterations["pressure"])
            del solver
            junk = [np.full(k % 40 + 1, 7, np.int32) for k in range(20000)]
            del junk

        solver = GasSolver(domain, dataclasses.replace(config, pcg_device_loop=loop))
        results[loop] = list(zip(iterations, _three_steps(solver, domain, count=5, after_step=churn)))
    for (it_host, host), (it_device, device) in zip(results[False], results[True]):
        assert it_device == it_host
        for name, expected in host.items():
            assert np.array_equal(device[name], expected, equal_nan=True), name


@pytest.mark.parametrize("fault", ["nan", "not_converged"])
def test_deferred_checks_raise_at_the_check_what_the_step_raises_at_once(fault):
    """``GasConfig.deferred_checks`` (with the device-side loop): a NaN face velocity, or a pressure solve cut off at one
    iteration, lets the steps run without a read, and ``check()`` then raises the error the per-step checks raise
    in the step itself; after the check (the log cleared) clean steps check clean."""
    domain, config = _masked_case("inlet_outlet", "native")
    if fault == "not_converged":
        config = dataclasses.replace(config, pressure_max_iterations=1)
    rng = np.random.default_rng(5)
    shape = domain.grid.shape
    eps = rng.uniform(0.0, 0.4, shape).astype(np.float32)
    faces = [rng.normal(0.0, 0.2, size=a.shape) for a in GasField(domain).face_arrays()]
    if fault == "nan":
        faces[0][7, 5, 4] = np.nan  # a face inside the channel
    errors = {}
    for deferred in (False, True):
        solver = GasSolver(domain, dataclasses.replace(config, pcg_device_loop=True, deferred_checks=deferred))
        gas = GasField(domain)
        gas.set_face_velocity(faces)
        gas.cell_eps_s.assign(eps)
        with pytest.raises(HelWarpError) as caught:
            solver.step(gas, 1e-3)
            solver.step(gas, 1e-3)
            solver.check()
        errors[deferred] = str(caught.value)
    word = "NaN" if fault == "nan" else "did not converge"
    assert word in errors[False] and word in errors[True]
    assert "since the last check" in errors[True]
    # the log starts afresh after a check: a clean step then checks clean
    solver = GasSolver(domain, dataclasses.replace(config, pcg_device_loop=True, deferred_checks=True,
                                                   pressure_max_iterations=1000))
    gas = GasField(domain)
    gas.cell_eps_s.assign(rng.uniform(0.0, 0.4, shape).astype(np.float32))
    solver.step(gas, 1e-3)
    solver.check()
    assert solver.last_iterations["pressure"] >= 0
