"""Collision data set: configurations (eq. 16, Fig. 5 families) and the resumable zarr store.

References used below:
- ballistic first touch: ``|x2 - x1 + t (v2 - v1)| = r1 + r2`` has its first root at ``touch_time``;
- momentum: ``m1 v1 + m2 v2`` unchanged by equal and opposite contact forces;
- restitution: ``(u1 - u2).n = -e (v1 - v2).n`` for a central impact (docs/physics/references.md
  "Binary collision outcome"); the DEM calibrates its damping so the clipped contact gives ``e``.
"""

from __future__ import annotations

import numpy as np
import pytest

from surrogate.configurations import CONVERGING, HEAD_ON, PARALLEL, ConfigurationSpec, generate
from surrogate.dataset import DatasetError, Dataset, OUTPUT_COLUMNS, build_dataset, load_dataset, make_spec

SPEC = ConfigurationSpec(diameter_mean=315e-6, diameter_std=8.2e-6, touch_time=1e-7)


def analytic_stand_in(configs, spec):
    """STAND-IN, NOT THE DEM: the frictionless impulse of docs/physics/references.md "Binary collision outcome",
    ``v1' = v1 - (1+e) m2/(m1+m2) (g.n) n``, ``v2' = v2 + (1+e) m1/(m1+m2) (g.n) n``; no spin;
    elastic Hertz duration, overlap and force (Johnson 1985, section 11.4). Used to test the store
    fast and without warp; the DEM itself is checked in ``test_dem_rows_*``."""
    e = spec.material.restitution
    r1, r2 = configs.d1 / 2, configs.d2 / 2
    m1 = configs.rho1 * 4 / 3 * np.pi * r1**3
    m2 = configs.rho2 * 4 / 3 * np.pi * r2**3
    n = configs.normal
    gn = np.sum((configs.v1 - configs.v2) * n, axis=1)
    u1 = configs.v1 - ((1 + e) * m2 / (m1 + m2) * gn)[:, None] * n
    u2 = configs.v2 + ((1 + e) * m1 / (m1 + m2) * gn)[:, None] * n
    nu, youngs = spec.material.poisson_ratio, spec.material.youngs_modulus
    e_star = youngs / (2 * (1 - nu**2))
    r_star = r1 * r2 / (r1 + r2)
    m_star = m1 * m2 / (m1 + m2)
    delta = (15 * m_star * gn**2 / (16 * e_star * np.sqrt(r_star))) ** 0.4
    force = 4 / 3 * e_star * np.sqrt(r_star) * delta**1.5
    duration = 2.868 * (m_star**2 / (r_star * e_star**2 * gn)) ** 0.2
    zeros = np.zeros_like(u1)
    return np.column_stack([u1, u2, zeros, zeros, duration, delta, force])


def nan_stand_in(configs, spec):
    out = analytic_stand_in(configs, spec)
    out[3, 0] = np.nan
    return out


def small_spec(**kw):
    kw = {"samples": 50, "seed": 7, "diameter": 315e-6, "chunk_size": 16} | kw
    return make_spec(**kw)


# ---------------------------------------------------------------- configurations

def test_reproducible_and_independent_of_chunking():
    whole = generate(SPEC, 3, 0, 3000)
    again = generate(SPEC, 3, 0, 3000)
    assert np.array_equal(whole.inputs(), again.inputs()) and np.array_equal(whole.x1, again.x1)
    part = generate(SPEC, 3, 1000, 2500)  # crosses a 1024-row block boundary
    assert np.array_equal(part.inputs(), whole.inputs()[1000:2500])
    assert np.array_equal(part.config_id, np.arange(1000, 2500))
    other = generate(SPEC, 4, 0, 3000)
    assert not np.array_equal(other.inputs(), whole.inputs())


def test_every_configuration_starts_apart_and_touches_at_touch_time():
    c = generate(SPEC, 0, 0, 5000)
    r_sum = (c.d1 + c.d2) / 2
    dx, g = c.x2 - c.x1, c.v1 - c.v2
    assert np.all(np.linalg.norm(dx, axis=1) > r_sum)                       # apart at start
    at_touch = dx - c.touch_time * g                                         # x2 - x1 at t = touch_time
    np.testing.assert_allclose(np.linalg.norm(at_touch, axis=1), r_sum, rtol=1e-9)
    np.testing.assert_allclose(at_touch / r_sum[:, None], c.normal, atol=1e-9)   # stored normal = first touch
    assert np.all(np.sum(g * c.normal, axis=1) >= max(SPEC.min_normal_speed, 1e-12))  # approaching: it collides
    assert np.all(np.linalg.norm(g, axis=1) >= SPEC.min_relative_speed)
    # first root of |dx - t g| = r_sum is touch_time (the smaller root of the quadratic)
    a, b, cc = np.sum(g * g, 1), -2 * np.sum(dx * g, 1), np.sum(dx * dx, 1) - r_sum**2
    t_first = (-b - np.sqrt(b * b - 4 * a * cc)) / (2 * a)
    np.testing.assert_allclose(t_first, c.touch_time, rtol=1e-5)
    speeds = np.linalg.norm(np.concatenate([c.v1, c.v2]), axis=1)
    assert speeds.max() <= 20.0 and np.all(c.offset < 1) and np.all(c.offset >= 0)
    assert abs(np.mean(c.offset == 0) - SPEC.central_fraction) < 0.03      # central fraction
    assert set(np.unique(c.family)) == {0, 1, 2}
    assert abs(np.mean(c.d1) - 315e-6) < 1e-6 and abs(np.std(c.d1) - 8.2e-6) < 0.5e-6


def test_default_set_covers_every_impact_the_engine_meets():
    """Incidence 0-89.8 deg with grazing well represented, |g| down to 0.01 m/s, the three families."""
    c = generate(SPEC, 2, 0, 20000)
    g = c.v1 - c.v2
    g_mag = np.linalg.norm(g, axis=1)
    angle = np.degrees(np.arccos(np.clip(np.sum(g * c.normal, axis=1) / g_mag, -1, 1)))
    assert angle.max() > 89.5 and angle.max() <= 89.8 + 1e-9
    assert np.mean(angle >= 80) > 0.10          # random collisions alone put 3 % there (uniform b^2)
    assert np.mean(angle >= 89) > 0.005
    assert np.quantile(g_mag, 0.05) < 0.1 and g_mag.min() >= 0.01
    for fam in (CONVERGING, PARALLEL, HEAD_ON):
        assert np.mean(angle[c.family == fam] >= 80) > 0.08


def test_uniform_b_squared_share_matches_kinetic_theory():
    """Without the central and grazing shares, b^2 = offset^2 is uniform on [0, max_offset^2]
    (docs/physics/references.md: random collisions are uniform in b^2): Kolmogorov-Smirnov distance small.
    Parallel and head-on families only: a converging pair must also have its common point ahead of
    both particles, which rejects large offsets more often (that family leans to central impacts)."""
    spec = ConfigurationSpec(diameter_mean=315e-6, diameter_std=0.0, touch_time=1e-7, central_fraction=0.0,
                             grazing_fraction=0.0, slow_fraction=0.0, family_weights=(0.0, 0.5, 0.5))
    c = generate(spec, 4, 0, 8000)
    b2 = np.sort(c.offset**2) / spec.max_offset**2
    ks = np.max(np.abs(b2 - (np.arange(1, b2.size + 1) - 0.5) / b2.size))
    # rejection of normal speeds < 1e-3 m/s thins b -> 1 a little; KS critical value at 1 % is 1.63/sqrt(n) = 0.018
    assert ks < 0.02


def test_size_mixture_gives_equal_and_unequal_pairs():
    """--mixture 315e-6,475e-6: each particle's size from one of the paper's two distributions."""
    spec = make_spec(samples=10, seed=0, diameter=315e-6, mixture_diameters=(315e-6, 475e-6)).configurations
    c = generate(spec, 5, 0, 6000)
    for d in (c.d1, c.d2):
        small = d < 395e-6
        assert abs(small.mean() - 0.5) < 0.03
        assert abs(d[small].mean() - 315e-6) < 1e-6 and abs(d[small].std() - 8.2e-6) < 0.6e-6
        assert abs(d[~small].mean() - 475e-6) < 2e-6 and abs(d[~small].std() - 22e-6) < 1.5e-6
    ratio = c.d2 / c.d1
    assert abs(np.mean(np.abs(np.log(ratio)) < 0.2) - 0.5) < 0.03  # half the pairs of one size


def test_paper_like_options_keep_the_earlier_rules():
    from surrogate.configurations import paper_spec_options

    spec = ConfigurationSpec(diameter_mean=315e-6, diameter_std=8.2e-6, touch_time=1e-7, **paper_spec_options())
    c = generate(spec, 3, 0, 4000)
    g = c.v1 - c.v2
    assert abs(np.mean(c.offset == 0) - 0.5) < 0.03 and c.offset.max() <= 0.95
    assert np.all(np.sum(g * c.normal, axis=1) >= 0.05)


def test_families_have_their_geometry():
    c = generate(SPEC, 1, 0, 3000)
    unit = lambda v: v / np.linalg.norm(v, axis=1)[:, None]  # noqa: E731
    conv, par, head = c.family == CONVERGING, c.family == PARALLEL, c.family == HEAD_ON
    # converging: both velocities point at the common point (the origin) from the start positions
    for x, v in ((c.x1[conv], c.v1[conv]), (c.x2[conv], c.v2[conv])):
        np.testing.assert_allclose(unit(-x), unit(v), atol=1e-6)
    # parallel: the same direction, the rear particle faster
    d1, d2 = unit(c.v1[par]), unit(c.v2[par])
    np.testing.assert_allclose(d1, d2, atol=1e-12)
    s1, s2 = np.linalg.norm(c.v1[par], axis=1), np.linalg.norm(c.v2[par], axis=1)
    ahead_is_2 = np.sum((c.x2[par] - c.x1[par]) * d1, axis=1) > 0
    assert np.all(np.where(ahead_is_2, s1 > s2, s2 > s1))
    assert 0.3 < ahead_is_2.mean() < 0.7
    # head-on: opposite directions
    np.testing.assert_allclose(unit(c.v1[head]), -unit(c.v2[head]), atol=1e-12)


# ---------------------------------------------------------------- the store (analytic stand-in)

def _arrays(path):
    ds = load_dataset(path)
    return ds.inputs, ds.outputs, ds.config_id, ds.family, ds.attrs["dataset_hash"]


def test_build_load_and_rows_in_order(tmp_path):
    spec = small_spec()
    summary = build_dataset(tmp_path / "ds", spec, progress=False, runner=analytic_stand_in)
    ds = load_dataset(tmp_path / "ds")
    assert isinstance(ds, Dataset) and ds.inputs.shape == (50, 14) and ds.outputs.shape == (50, 15)
    assert np.array_equal(ds.config_id, np.arange(50))
    expected = generate(spec.configurations, spec.seed, 0, 50)
    assert np.array_equal(ds.inputs, expected.inputs()) and np.array_equal(ds.family, expected.family)
    assert ds.attrs["dataset_hash"] == summary["dataset_hash"] and ds.attrs["seed"] == 7
    assert ds.attrs["output_columns"] == list(OUTPUT_COLUMNS)


class Killed(Exception):
    pass


def test_kill_and_resume_is_byte_identical(tmp_path):
    spec = small_spec()
    build_dataset(tmp_path / "ref", spec, progress=False, runner=analytic_stand_in)

    def kill_after_second(k):
        if k == 1:
            raise Killed

    with pytest.raises(Killed):
        build_dataset(tmp_path / "run", spec, progress=False, runner=analytic_stand_in, after_chunk=kill_after_second)
    with pytest.raises(DatasetError, match="incomplete"):
        load_dataset(tmp_path / "run")
    # a half-written chunk: rows of chunk 2 written, its flag not set -> rewritten on resume
    import zarr
    group = zarr.open_group(str(tmp_path / "run"), mode="r+")
    group["outputs"][32:40] = 123.0
    summary = build_dataset(tmp_path / "run", spec, progress=False, runner=analytic_stand_in)
    assert summary["resumed"] and summary["computed_chunks"] == 2
    for a, b in zip(_arrays(tmp_path / "ref"), _arrays(tmp_path / "run")):
        assert np.array_equal(a, b)
    # every file of the store is byte-identical too
    ref_files = sorted(p.relative_to(tmp_path / "ref") for p in (tmp_path / "ref").rglob("*") if p.is_file())
    run_files = sorted(p.relative_to(tmp_path / "run") for p in (tmp_path / "run").rglob("*") if p.is_file())
    assert ref_files == run_files
    for rel in ref_files:
        assert (tmp_path / "ref" / rel).read_bytes() == (tmp_path / "run" / rel).read_bytes(), rel


def test_mismatched_resume_is_refused(tmp_path):
    build_dataset(tmp_path / "ds", small_spec(), progress=False, runner=analytic_stand_in)
    for other in (small_spec(seed=8), small_spec(samples=60), small_spec(chunk_size=8),
                  small_spec(diameter=475e-6), small_spec(contact_model="linear")):
        with pytest.raises(DatasetError, match="other parameters.*--overwrite"):
            build_dataset(tmp_path / "ds", other, progress=False, runner=analytic_stand_in)
    summary = build_dataset(tmp_path / "ds", small_spec(seed=8), progress=False, runner=analytic_stand_in,
                            overwrite=True)
    assert load_dataset(tmp_path / "ds").attrs["seed"] == 8 and summary["computed_chunks"] == 4


def test_resume_with_changed_physics_code_is_refused(tmp_path):
    import zarr

    spec = small_spec()
    with pytest.raises(Killed):
        build_dataset(tmp_path / "ds", spec, progress=False, runner=analytic_stand_in,
                      after_chunk=lambda k: (_ for _ in ()).throw(Killed()))
    group = zarr.open_group(str(tmp_path / "ds"), mode="r+")
    group.attrs["code_fingerprint"] = "0123456789abcdef"  # as if started by another version of the DEM
    with pytest.raises(DatasetError, match="other configuration/DEM code"):
        build_dataset(tmp_path / "ds", spec, progress=False, runner=analytic_stand_in)


def test_nan_rows_are_refused_and_corruption_detected(tmp_path):
    with pytest.raises(DatasetError, match="1 of 16 rows are NaN"):
        build_dataset(tmp_path / "nan", small_spec(), progress=False, runner=nan_stand_in)
    build_dataset(tmp_path / "ds", small_spec(), progress=False, runner=analytic_stand_in)
    import zarr
    group = zarr.open_group(str(tmp_path / "ds"), mode="r+")
    group["outputs"][5, 0] += 1.0
    with pytest.raises(DatasetError, match="corrupted"):
        load_dataset(tmp_path / "ds")
    with pytest.raises(DatasetError, match="not a data set"):
        load_dataset(tmp_path / "nowhere")


def test_unknown_diameter_needs_a_std():
    from hel_warp.errors import ConfigError

    with pytest.raises(ConfigError, match="--diameter-std"):
        make_spec(samples=10, seed=0, diameter=400e-6)
    assert make_spec(samples=10, seed=0, diameter=475e-6).configurations.diameter_std == 22e-6


# ---------------------------------------------------------------- the DEM rows

def _dem_rows(tmp_path, central_fraction, samples=192, contact_model="hertz"):
    import hel_warp.collisions.impact  # noqa: F401 - the DEM that writes the rows; missing, the test fails
    spec = make_spec(samples=samples, seed=11, diameter=315e-6, chunk_size=96, central_fraction=central_fraction,
                     grazing_fraction=min(0.3, 1.0 - central_fraction), contact_model=contact_model)
    build_dataset(tmp_path / "dem", spec, progress=False)
    ds = load_dataset(tmp_path / "dem")
    return spec, ds


def _masses(ds):
    d1, d2, rho1, rho2 = ds.inputs[:, 6], ds.inputs[:, 7], ds.inputs[:, 8], ds.inputs[:, 9]
    return rho1 * np.pi / 6 * d1**3, rho2 * np.pi / 6 * d2**3


def test_dem_runs_grazing_and_slow_rows_to_separation(tmp_path):
    """Rows at 85-89.8 deg and |g| down to 0.01 m/s complete their contact (touch, separate) in the
    data set's DEM, and none gains kinetic energy (float32 round-off aside)."""
    import hel_warp.collisions.impact  # noqa: F401 - the DEM that writes the rows; missing, the test fails
    spec = make_spec(samples=400, seed=12, diameter=315e-6, chunk_size=400, grazing_angle=85.0,
                     grazing_fraction=1.0, central_fraction=0.0, slow_fraction=0.5)
    build_dataset(tmp_path / "graze", spec, progress=False)  # refuses rows that did not touch or separate
    ds = load_dataset(tmp_path / "graze")
    g, gp = ds.inputs[:, 0:3] - ds.inputs[:, 3:6], ds.outputs[:, 0:3] - ds.outputs[:, 3:6]
    angle = np.degrees(np.arccos(np.clip(np.sum(g * ds.inputs[:, 10:13], axis=1) / np.linalg.norm(g, axis=1), -1, 1)))
    assert angle.min() >= 85 - 1e-9 and angle.max() > 89.5 and np.linalg.norm(g, axis=1).min() < 0.05
    assert np.all(np.sum(gp**2, axis=1) <= np.sum(g**2, axis=1) * (1 + 1e-5))


def test_dem_rows_conserve_momentum(tmp_path):
    spec, ds = _dem_rows(tmp_path, central_fraction=0.5)
    m1, m2 = _masses(ds)
    v1, v2, u1, u2 = ds.inputs[:, 0:3], ds.inputs[:, 3:6], ds.outputs[:, 0:3], ds.outputs[:, 3:6]
    before = m1[:, None] * v1 + m2[:, None] * v2
    after = m1[:, None] * u1 + m2[:, None] * u2
    # float32 DEM: each velocity carries ~1e-7 relative round-off per step, accumulated over ~100 steps
    scale = (m1 + m2) * np.maximum(np.linalg.norm(v1, axis=1), np.linalg.norm(v2, axis=1))
    assert np.all(np.linalg.norm(after - before, axis=1) <= 1e-5 * scale[:] + 1e-18)
    assert np.all(ds.outputs[:, 12] > 0)  # every row had a contact


def test_dem_central_rows_restitution(tmp_path):
    spec, ds = _dem_rows(tmp_path, central_fraction=1.0)
    n = ds.inputs[:, 10:13]
    g_pre = np.sum((ds.inputs[:, 0:3] - ds.inputs[:, 3:6]) * n, axis=1)
    g_post = np.sum((ds.outputs[:, 0:3] - ds.outputs[:, 3:6]) * n, axis=1)
    e = spec.material.restitution
    np.testing.assert_allclose(g_post / g_pre, -e, rtol=0.01)


def test_dask_scheduler_gives_the_same_bytes(tmp_path):
    distributed = pytest.importorskip("distributed")
    spec = small_spec()
    build_dataset(tmp_path / "local", spec, progress=False, runner=analytic_stand_in)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        summary = build_dataset(tmp_path / "dask", spec, scheduler=cluster.scheduler_address, progress=False,
                                runner=analytic_stand_in)
    assert summary["computed_chunks"] == spec.n_chunks
    for a, b in zip(_arrays(tmp_path / "local"), _arrays(tmp_path / "dask")):
        assert np.array_equal(a, b)


def test_unreachable_scheduler_is_a_clear_error(tmp_path):
    pytest.importorskip("distributed")
    from hel_warp.errors import ConfigError

    with pytest.raises(ConfigError, match="Dask scheduler"):
        build_dataset(tmp_path / "ds", small_spec(), scheduler="tcp://127.0.0.1:1", progress=False,
                      runner=analytic_stand_in, scheduler_timeout=1.0)


def test_cli_builds_resumes_and_refuses_other_parameters(tmp_path, capsys):
    import hel_warp.collisions.impact  # noqa: F401 - the DEM that writes the rows; missing, the test fails
    from hel_warp.cli import main

    out = str(tmp_path / "ds")
    args = ["dataset", "--out", out, "--samples", "300", "--chunk-size", "128", "--seed", "5", "--no-progress"]
    assert main(args) == 0
    first = capsys.readouterr().out
    assert "300 configurations in 3 chunks (3 computed now)" in first and "total time" in first
    assert main(args[:-3] + ["--seed", "5", "--no-progress"]) == 0          # rerun: nothing to compute
    assert "(0 computed now, resumed)" in capsys.readouterr().out
    assert main(args[:-3] + ["--seed", "6", "--no-progress"]) == 2          # other seed: one-line error
    err = capsys.readouterr().err
    assert err.startswith("hel-warp: error:") and "--overwrite" in err and "seed" in err
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "keep.txt").write_text("x")
    assert main(["dataset", "--out", str(tmp_path / "notes"), "--samples", "10", "--overwrite", "--no-progress"]) == 2
    assert (tmp_path / "notes" / "keep.txt").exists()                       # --overwrite never deletes other data
    assert load_dataset(out).inputs.shape == (300, 14)


def test_a_set_central_fraction_makes_the_unset_grazing_default_give_way(tmp_path, capsys):
    """`--central-fraction 1` (all central, the paper's form) is the user's choice; the grazing default (0.3)
    was not, so it shrinks to what is left, min(0.3, 1 - central). Both set explicitly and summing above 1 is
    still the user's contradiction and is refused."""
    from hel_warp.cli import main
    from hel_warp.errors import ConfigError

    assert make_spec(samples=10, seed=0, diameter=315e-6).configurations.grazing_fraction == 0.3  # default kept
    for central in (1.0, 0.8, 0.5):
        cfg = make_spec(samples=10, seed=0, diameter=315e-6, central_fraction=central).configurations
        assert cfg.central_fraction == central and cfg.grazing_fraction == pytest.approx(min(0.3, 1.0 - central))
    with pytest.raises(ConfigError, match="central_fraction"):
        make_spec(samples=10, seed=0, diameter=315e-6, central_fraction=1.0, grazing_fraction=0.3)

    out = tmp_path / "ds"
    assert main(["dataset", "--out", str(out), "--samples", "64", "--chunk-size", "64", "--central-fraction", "1",
                 "--no-progress"]) == 0
    capsys.readouterr()
    configuration = load_dataset(out).attrs["configuration"]
    assert configuration["central_fraction"] == 1.0 and configuration["grazing_fraction"] == 0.0
    assert main(["dataset", "--out", str(tmp_path / "both"), "--samples", "64", "--central-fraction", "1",
                 "--grazing-fraction", "0.3", "--no-progress"]) == 2
    assert capsys.readouterr().err.startswith("hel-warp: error:")
    assert not (tmp_path / "both").exists()
