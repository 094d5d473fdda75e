"""N-body DEM (hel_warp/collisions/dem.py) against conservation laws and closed forms."""

import math

import numpy as np
import pytest
import warp as wp

from hel_warp.collisions.dem import DEMConfig, DEMSolver
from hel_warp.errors import ConfigError
from hel_warp.material import Material
from hel_warp.parcels.particles import Particles, lattice_positions

GLASS_SOFT = dict(density=2500.0, youngs_modulus=1e8, poisson_ratio=0.3)


def hertz_energy(solver, material):
    """Kinetic (translation + rotation) + elastic Hertz energy 2/5 k_H delta^{5/2} of particle and wall
    contacts, float64 on the host, from positions alone (independent of the solver's forces)."""
    from scipy.spatial import cKDTree

    d = solver.particles.to_numpy(original_order=False)
    x, r = d["x"].astype(np.float64), d["radius"].astype(np.float64)
    m = solver.particles.mass_numpy()
    kinetic = 0.5 * np.sum(m * np.sum(d["v"].astype(np.float64) ** 2, axis=1))
    kinetic += 0.5 * np.sum(0.4 * m * r**2 * np.sum(d["omega"].astype(np.float64) ** 2, axis=1))
    i, j = cKDTree(x).query_pairs(2.0 * r.max(), output_type="ndarray").T
    overlap = np.maximum(r[i] + r[j] - np.linalg.norm(x[i] - x[j], axis=1), 0.0)
    E, nu = material.youngs_modulus, material.poisson_ratio
    e_pair = E / (2.0 * (1.0 - nu**2))  # 1/E* = 2 (1 - nu^2)/E, same material
    r_pair = r[i] * r[j] / (r[i] + r[j])
    elastic = np.sum(0.4 * 4.0 / 3.0 * e_pair * np.sqrt(r_pair) * overlap**2.5)
    lo, hi = np.asarray(solver.config.box_lo), np.asarray(solver.config.box_hi)
    wall_overlap = np.concatenate([np.maximum(r[:, None] - (x - lo), 0.0), np.maximum(r[:, None] - (hi - x), 0.0)], 1)
    elastic += np.sum(0.4 * 4.0 / 3.0 * (E / (1.0 - nu**2)) * np.sqrt(r[:, None]) * wall_overlap**2.5)  # rigid wall
    return kinetic + elastic


def elastic_gas(dt_fraction, n=300, seed=1):
    material = Material(**GLASS_SOFT, restitution=1.0, friction=0.0)
    lo, hi = (0.0, 0.0, 0.0), (0.02, 0.02, 0.02)
    rng = np.random.default_rng(seed)
    radius = rng.uniform(0.8e-3, 1.0e-3, n)
    x = lattice_positions(n, 2.5e-3, lo, hi, jitter=0.4e-3, seed=seed)
    p = Particles.from_numpy(x, radius, v=rng.normal(scale=1.0, size=(n, 3)), density=material.density,
                             box_lo=lo, box_hi=hi)
    dt = dt_fraction * material.time_step(radius.min()).chosen
    return DEMSolver(DEMConfig(material=material, box_lo=lo, box_hi=hi, gravity=(0, 0, 0), dt=dt), p), material


def test_elastic_gas_conserves_energy():
    """e = 1, mu = 0, no gravity: total energy (kinetic + Hertz elastic) is conserved.

    Velocity Verlet is second order: the relative energy error over a contact is O((dt/t_c)^2), with t_c
    the Hertz contact duration t_c = 2.868 (m*^2 / (R* E*^2 v))^{1/5} (Johnson 1985, §11.4) at the rms
    speed. Tolerance (dt/t_c)^2; halving dt must shrink the error (second order: ~4x; we ask > 2x).
    """
    errors = {}
    for fraction in (1.0, 0.5):
        solver, material = elastic_gas(fraction)
        e0 = hertz_energy(solver, material)
        n_steps = int(round(0.01 / solver.dt))  # ~10 collisions per particle
        worst = 0.0
        for _ in range(10):
            solver.simulate(n_steps // 10)
            worst = max(worst, abs(hertz_energy(solver, material) / e0 - 1.0))
        errors[fraction] = worst
        if fraction == 1.0:
            m = solver.particles.mass_numpy().min()
            r = solver.r_min
            e_star = material.youngs_modulus / (2.0 * (1.0 - material.poisson_ratio**2))
            t_c = 2.868 * ((m / 2.0) ** 2 / (r / 2.0 * e_star**2 * math.sqrt(3.0))) ** 0.2
            tolerance = (solver.dt / t_c) ** 2
            assert worst < tolerance, (worst, tolerance)
    assert errors[0.5] < errors[1.0] / 2.0, errors


N_STEPS_MOMENTUM = 400


def test_momentum_conserved_without_walls_or_gravity():
    """No walls, no gravity, friction and damping on: every contact force is equal and opposite, so
    total momentum stays at its initial value up to float32 round-off of the velocity updates."""
    n = 1000
    material = Material(**GLASS_SOFT, restitution=0.5, friction=0.4)
    rng = np.random.default_rng(3)
    x = lattice_positions(n, 2.1e-3, (0, 0, 0), (0.03, 0.03, 0.03), jitter=0.08e-3, seed=3)
    radius = rng.uniform(0.95e-3, 1.0e-3, n)
    v = -40.0 * (x - x.mean(axis=0)) + rng.normal(scale=0.2, size=(n, 3))  # converging cloud: many collisions
    p = Particles.from_numpy(x, radius, v=v, omega=rng.normal(scale=100.0, size=(n, 3)), density=material.density)
    solver = DEMSolver(DEMConfig(material=material, box_lo=(0, 0, 0), box_hi=(0.03, 0.03, 0.03), walls=(),
                                 gravity=(0, 0, 0)), p)
    m = material.density * 4.0 / 3.0 * np.pi * radius.astype(np.float32).astype(np.float64) ** 3  # original order
    p0 = (m[:, None] * v.astype(np.float32)).sum(axis=0)
    scale = np.sum(m * np.linalg.norm(v, axis=1))
    kinetic0 = 0.5 * np.sum(m * np.sum(v**2, axis=1))
    solver.simulate(N_STEPS_MOMENTUM)
    d = p.to_numpy()  # original order (the solver sorts the arrays spatially)
    p1 = (m[:, None] * d["v"].astype(np.float64)).sum(axis=0)
    f = solver.force.numpy().astype(np.float64)
    assert len(solver.touching_pairs()[0]) > 200  # contacts are active now ...
    assert 0.5 * np.sum(m * np.sum(d["v"].astype(np.float64) ** 2, axis=1)) < 0.8 * kinetic0  # ... and were
    np.testing.assert_allclose(p1, p0, atol=1e-5 * scale)
    # Newton's third law on the force array itself: the sum is round-off of the sum of |f|
    assert np.linalg.norm(f.sum(axis=0)) < 1e-5 * np.abs(f).sum()


def resting_sphere(sdf=None):
    r, material = 5e-3, Material(density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.3,
                                 friction=0.3)
    p = Particles.from_numpy([[0.02, 0.02, r]], r, density=material.density)
    walls = ("z-",) if sdf is None else ()
    cfg = DEMConfig(material=material, box_lo=(0, 0, 0), box_hi=(0.04, 0.04, 0.04), walls=walls,
                    sdf_walls=() if sdf is None else (sdf,), gravity=(0.0, 0.0, -9.81))
    solver = DEMSolver(cfg, p)
    solver.simulate(int(0.15 / solver.dt))
    overlap = r - float(p.x.numpy()[0, 2])
    m = float(p.mass_numpy()[0])
    e_star = material.youngs_modulus / (1.0 - material.poisson_ratio**2)  # rigid wall
    reference = (m * 9.81 / (4.0 / 3.0 * e_star * math.sqrt(r))) ** (2.0 / 3.0)  # Hertz static overlap
    return overlap, reference, float(np.linalg.norm(p.v.numpy()[0]))


def test_sphere_resting_on_floor_has_hertz_static_overlap():
    """delta = (m g / (4/3 E* sqrt(R)))^{2/3} (Hertz, Johnson 1985 §4.2) within 1 %."""
    overlap, reference, speed = resting_sphere()
    assert speed < 1e-4
    assert overlap == pytest.approx(reference, rel=0.01)


@wp.func
def floor_sdf(x: wp.vec3):
    return x[2]


def test_sphere_resting_on_sdf_floor_has_hertz_static_overlap():
    overlap, reference, _ = resting_sphere(sdf=floor_sdf)
    assert overlap == pytest.approx(reference, rel=0.01)


def small_column(n=800):
    material = Material(**GLASS_SOFT, restitution=0.5, friction=0.3)
    lo, hi = (0.0, 0.0, 0.0), (0.02, 0.02, 0.06)
    x = lattice_positions(n, 2.3e-3, lo, hi, jitter=0.2e-3, seed=5)
    radius = np.random.default_rng(5).uniform(0.9e-3, 1.0e-3, n)
    p = Particles.from_numpy(x, radius, density=material.density, box_lo=lo, box_hi=hi)
    return DEMSolver(DEMConfig(material=material, box_lo=lo, box_hi=hi, sort_every=2), p)


def test_determinism_bitwise():
    runs = []
    for _ in range(2):
        solver = small_column()
        solver.simulate(4000)
        d = solver.particles.to_numpy()
        runs.append(d)
        assert solver.rebuilds > 2
    for name in ("x", "v", "omega"):
        assert runs[0][name].tobytes() == runs[1][name].tobytes(), name


def test_time_step_above_stable_is_refused():
    material = Material(**GLASS_SOFT)
    stable = material.time_step(1e-3).chosen
    p = Particles.from_numpy([[0.01, 0.01, 0.01]], 1e-3, density=material.density)
    cfg = DEMConfig(material=material, box_lo=(0, 0, 0), box_hi=(0.02, 0.02, 0.02), dt=2.0 * stable)
    with pytest.raises(ConfigError, match="above the stable DEM step"):
        DEMSolver(cfg, p)
    solver = DEMSolver(DEMConfig(material=material, box_lo=(0, 0, 0), box_hi=(0.02, 0.02, 0.02)), p)
    assert solver.dt == pytest.approx(stable)  # default: eq. (12) for the smallest radius


@pytest.mark.parametrize("bad, match", [
    (dict(x=[[np.nan, 0.01, 0.01]]), "non-finite position"),
    (dict(radius=0.0), "radius"),
    (dict(x=[[0.01, 0.01, 0.01], [0.0105, 0.01, 0.01]]), "overlap by"),
    (dict(x=[[0.0005, 0.01, 0.01]]), "not fully inside"),
])
def test_particles_validation(bad, match):
    args = dict(x=[[0.01, 0.01, 0.01]], radius=1e-3)
    args.update(bad)
    with pytest.raises(ConfigError, match=match):
        Particles.from_numpy(args["x"], args["radius"], box_lo=(0, 0, 0), box_hi=(0.02, 0.02, 0.02))


@pytest.mark.slow
def test_settling_column_case_writes_zarr_and_vtk(tmp_path, full_size):
    """Settling column through the CLI: count conserved, zarr and .vtp read back with N points.
    CI size 1000 spheres for 0.01 s (~3 s); HEL_WARP_FULL=1: 1e5 spheres for 0.3 s (~40 min)."""
    import pyvista as pv

    from hel_warp.cli import main
    from hel_warp.runs.io import read_snapshot

    n = 100_000 if full_size else 1000
    end = 0.3 if full_size else 0.01
    out = tmp_path / "run"
    code = main(["dem", "settling_column", "--particles", str(n), "--end-time", str(end), "--snapshots", "2",
                 "--out", str(out), "--no-progress"])
    assert code == 0  # the case's check() passed
    arrays, attrs = read_snapshot(out)
    assert arrays["x"].shape == (n, 3) and attrs["count"] == n
    assert attrs["time"] == pytest.approx(end, rel=1e-3)
    np.testing.assert_array_equal(np.sort(arrays["particle_id"]), np.arange(n))
    first, _ = read_snapshot(out, 0)
    assert arrays["x"][:, 2].mean() < first["x"][:, 2].mean()  # the column fell
    mesh = pv.read(out / "vtk" / "particles_0002.vtp")
    assert mesh.n_points == n and "radius" in mesh.point_data
    series = pv.get_reader(str(out / "vtk" / "particles.pvd"))
    assert len(series.time_values) == 3


def wall_impact(theta_deg, restitution, friction, dt_fraction):
    """One sphere (r = 1 mm) hits the floor at 1 m/s, angle theta from the normal; no gravity."""
    r = 1e-3
    material = Material(**GLASS_SOFT, restitution=restitution, friction=friction)
    theta = math.radians(theta_deg)
    p = Particles.from_numpy([[0.01, 0.01, 1.0001 * r]], r, v=[math.sin(theta), 0.0, -math.cos(theta)],
                             density=material.density)
    dt = dt_fraction * material.time_step(r).chosen
    solver = DEMSolver(DEMConfig(material=material, box_lo=(0, 0, 0), box_hi=(0.02, 0.02, 0.02), walls=("z-",),
                                 gravity=(0, 0, 0), dt=dt), p)
    solver.simulate(int(3e-4 / dt))  # contact lasts ~8e-5 s
    d = p.to_numpy()
    return d["v"][0].astype(np.float64), d["omega"][0].astype(np.float64), math.sin(theta), math.cos(theta)


def test_wall_impact_restitution_and_gross_sliding():
    """Normal impact returns the material's e (damping c(e) of hel_warp.collisions.contact_law). Oblique impact in
    gross sliding (tan theta >= 3.5 mu (1+e)): e_t = 1 - mu (1+e) cot theta and w = 2.5 mu (1+e) v cos theta / R
    (docs/physics/references.md; Maw, Barber & Fawcett 1976). At dt = eq.(12)/4 (~60 steps per contact); measured at
    eq. (12) itself (~15 steps): e = 0.508 for 0.5."""
    e, mu = 0.5, 0.1
    v, _, _, cos_t = wall_impact(0.0, e, 0.3, 0.25)
    assert v[2] / cos_t == pytest.approx(e, rel=0.005)
    v, omega, sin_t, cos_t = wall_impact(60.0, e, mu, 0.25)
    assert math.tan(math.radians(60.0)) >= 3.5 * mu * (1 + e)
    assert v[2] / cos_t == pytest.approx(e, rel=0.005)
    assert v[0] / sin_t == pytest.approx(1.0 - mu * (1.0 + e) * cos_t / sin_t, rel=0.005)
    assert omega[1] == pytest.approx(2.5 * mu * (1.0 + e) * cos_t / 1e-3, rel=0.01)  # rolls forward (+y)


def test_run_writer_round_trip_with_changing_count(tmp_path):
    """io.RunWriter: snapshots of different particle counts and per-step series read back exactly."""
    import pyvista as pv
    import zarr

    from hel_warp.runs.io import RunWriter, read_snapshot

    rng = np.random.default_rng(0)
    writer = RunWriter(tmp_path, config={"case": "io", "dt": 1e-6})
    written = []
    for k, n in enumerate((5, 7)):
        arrays = {"x": rng.normal(size=(n, 3)), "radius": rng.uniform(1, 2, n).astype(np.float32),
                  "stream": np.arange(n, dtype=np.int32)}
        writer.write_snapshot(arrays, time=0.1 * k, step=10 * k)
        written.append(arrays)
        writer.append_series("contacts", np.array([k, k + 1], dtype=np.int64))
    for k, arrays in enumerate(written):
        back, attrs = read_snapshot(tmp_path, k)
        assert attrs == {"time": 0.1 * k, "step": 10 * k, "count": len(arrays["x"])}
        for name, arr in arrays.items():
            np.testing.assert_array_equal(back[name], arr)
        mesh = pv.read(tmp_path / "vtk" / f"particles_{k:04d}.vtp")
        np.testing.assert_allclose(mesh.points, arrays["x"], rtol=1e-6)
        np.testing.assert_array_equal(mesh.point_data["stream"], arrays["stream"])
    root = zarr.open_group(str(tmp_path / "run.zarr"), mode="r")
    np.testing.assert_array_equal(root["series"]["contacts"][...], [0, 1, 1, 2])
    np.testing.assert_array_equal(root["time"][...], [0.0, 0.1])
    assert root.attrs["config"] == {"case": "io", "dt": 1e-6}


def test_half_list_is_bit_identical_to_the_full_list():
    """The CPU path (half list, each pair computed once, two fused passes: kernels/dem_step.py) against the
    full list and separate kernels (the CUDA path, run here on the CPU): the contact law is odd under the
    exchange of the bodies to the last bit and the half list sums each particle's forces in the full list's
    order, so positions, velocities, spins and forces agree bitwise — with friction, rolling friction,
    walls, list rebuilds and spatial sorts (the sort moves pairs between owners' rows), and so do the onset
    counts."""
    from hel_warp.parcels.particles import lattice_positions

    def run(half):
        n = 700
        material = Material(**GLASS_SOFT, restitution=0.5, friction=0.4, rolling_friction=0.05)
        lo, hi = (0.0, 0.0, 0.0), (0.02, 0.02, 0.05)
        x = lattice_positions(n, 2.2e-3, lo, hi, jitter=0.2e-3, seed=11)
        x = x[np.random.default_rng(11).permutation(n)]  # memory order unrelated to space: the sort acts
        rng = np.random.default_rng(12)
        p = Particles.from_numpy(x, rng.uniform(0.9e-3, 1.0e-3, n), v=rng.normal(scale=0.5, size=(n, 3)),
                                 omega=rng.normal(scale=50.0, size=(n, 3)), density=material.density)
        solver = DEMSolver(DEMConfig(material=material, box_lo=lo, box_hi=hi, sort_every=2, half_list=half), p)
        solver.simulate(3000)
        return solver

    full, half = run(False), run(True)
    assert half.half_list and not full.half_list
    assert half.rebuilds > 4 and half.rebuilds == full.rebuilds
    a, b = full.particles.to_numpy(), half.particles.to_numpy()
    for name in ("x", "v", "omega"):
        assert a[name].tobytes() == b[name].tobytes(), name
    assert full.force.numpy().tobytes() == half.force.numpy().tobytes()
    assert full.torque.numpy().tobytes() == half.torque.numpy().tobytes()
    assert half.onset_counts()["collisions"] > 100 and half.onset_counts() == full.onset_counts()
    assert np.abs(b["omega"]).max() > 1.0
