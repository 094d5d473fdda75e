"""Volume injection never starts an overlap (paper sec. 4.1: overlapped starts are what a DEM turns into
~100 m/s particles): parcels of one release keep |x_i - x_j| >= r_i + r_j among themselves and from the live
parcels already in the box. Reference: the O(N^2) distance test over all pairs. Also count, mass, speed,
determinism, the blocked-site kernel against brute force, and the refusal of a release that does not fit.
"""

import math

import numpy as np
import pytest

from hel_warp.errors import ConfigError
from hel_warp.parcels.pool import ParcelPool, VolumeInjection

BOX_LO, BOX_HI = (0.0, 0.0, 0.0), (6e-3, 4e-3, 3e-3)


def pool_with_parcels(n_old: int, *, capacity: int = 4000, radius: float = 1.5e-4, seed: int = 5) -> ParcelPool:
    """A pool whose first ``n_old`` slots hold live parcels at uniform random points of the box (overlaps
    among them allowed: the state an MP-PIC run can be in); every third one is dead (it must not block)."""
    pool = ParcelPool.empty(capacity)
    rng = np.random.default_rng(seed)
    p = pool.particles
    x = np.zeros((capacity, 3), np.float32)
    x[:n_old] = rng.uniform(BOX_LO, BOX_HI, size=(n_old, 3))
    p.x.assign(x)
    p.radius.assign(np.full(capacity, radius, np.float32))
    alive = np.zeros(capacity, np.int32)
    alive[:n_old] = 1
    alive[:n_old:3] = 0
    p.alive.assign(alive)
    pool.used = n_old
    return pool


def closest_pair_gap(x_new, r_new, x_old, r_old):
    """min over pairs (new-new and new-old) of |x_i - x_j| / (r_i + r_j), O(N^2) brute force in float64."""
    x_new, x_old = x_new.astype(np.float64), x_old.astype(np.float64)
    r_new, r_old = r_new.astype(np.float64), r_old.astype(np.float64)
    dist = np.linalg.norm(x_new[:, None] - x_new[None], axis=2)
    ratio = dist / (r_new[:, None] + r_new[None])
    np.fill_diagonal(ratio, np.inf)
    worst = ratio.min()
    if len(x_old):
        dist = np.linalg.norm(x_new[:, None] - x_old[None], axis=2)
        worst = min(worst, (dist / (r_new[:, None] + r_old[None])).min())
    return worst


def test_releases_into_an_occupied_box_never_overlap_anything_alive():
    pool = pool_with_parcels(150)
    used = [pool.used]
    for seed, std in ((1, 0.0), (2, 3e-5), (3, 3e-5)):
        inj = VolumeInjection(box_lo=BOX_LO, box_hi=BOX_HI, diameter_mean=2.5e-4, diameter_std=std, count=120,
                              speed=3.0, direction=(0.0, 1.0, 0.0), seed=seed)
        assert pool.inject(inj) == 120
        used.append(pool.used)
    p = pool.particles.to_numpy()
    alive = p["alive"][:pool.used].astype(bool)
    new = slice(used[0], pool.used)
    old = np.flatnonzero(alive[:used[0]])
    assert closest_pair_gap(p["x"][new], p["radius"][new], p["x"][old], p["radius"][old]) >= 1.0
    # and the dead slots were not treated as obstacles: some new parcel sits where only a dead one overlaps
    dead = np.flatnonzero(~alive[:used[0]])
    assert closest_pair_gap(p["x"][new], p["radius"][new], p["x"][dead], p["radius"][dead]) < 1.0
    # count, box, speed, stream as before
    assert np.all(p["x"][new] >= np.float32(BOX_LO)) and np.all(p["x"][new] <= np.float32(BOX_HI))
    np.testing.assert_allclose(p["v"][new], np.tile([0.0, 3.0, 0.0], (pool.used - used[0], 1)), atol=1e-6)
    assert p["alive"][new].all()


def test_diameters_and_mass_do_not_depend_on_the_obstacles():
    """The RNG draws diameters before positions: the release's sizes (and hence the mass bookkeeping in
    HelSolver, which calls sample() without obstacles) are those of sample()."""
    inj = VolumeInjection(box_lo=BOX_LO, box_hi=BOX_HI, diameter_mean=2.5e-4, diameter_std=2e-5, mass=2e-7,
                          density=1000.0, seed=9)
    pool = pool_with_parcels(200)
    n = pool.inject(inj)
    r = pool.particles.radius.numpy()[200:200 + n]
    free = inj.sample()
    np.testing.assert_array_equal(r, free["radius"].astype(np.float32))
    masses = 1000.0 * 4.0 / 3.0 * math.pi * free["radius"] ** 3
    assert 2e-7 <= masses.sum() < 2e-7 + masses.max()
    assert closest_pair_gap(free["x"], free["radius"], np.empty((0, 3)), np.empty(0)) >= 1.0


def test_same_seed_and_pool_give_bit_identical_positions():
    inj = VolumeInjection(box_lo=BOX_LO, box_hi=BOX_HI, diameter_mean=2.5e-4, diameter_std=2e-5, count=150,
                          seed=4)
    runs = []
    for _ in range(2):
        pool = pool_with_parcels(200)
        pool.inject(inj)
        runs.append(pool.particles.x.numpy()[200:350].copy())
    np.testing.assert_array_equal(runs[0], runs[1])
    pool = pool_with_parcels(200)
    pool.inject(VolumeInjection(**{**inj.__dict__, "seed": 5}))
    assert not np.array_equal(runs[0], pool.particles.x.numpy()[200:350])


def test_blocked_site_kernel_matches_brute_force():
    pool = pool_with_parcels(300, radius=1e-4)
    blocked = pool._blocked_sites()
    rng = np.random.default_rng(0)
    sites = rng.uniform(BOX_LO, BOX_HI, size=(500, 3)).astype(np.float32)
    radius = rng.uniform(5e-5, 1.5e-4, size=500).astype(np.float32)
    flags = blocked(sites, radius)
    p = pool.particles.to_numpy()
    live = p["alive"][:300].astype(bool)
    xo, ro = p["x"][:300][live].astype(np.float64), p["radius"][:300][live].astype(np.float64)
    dist = np.linalg.norm(sites[:, None].astype(np.float64) - xo[None], axis=2)
    cut = (radius[:, None].astype(np.float64) + ro[None]) * (1.0 + 1e-3)
    expected = (dist < cut).any(axis=1)
    assert 50 < expected.sum() < 450  # both outcomes are exercised
    # float32 kernel vs float64 reference: only pairs within round-off of the cut may differ
    near_cut = (np.abs(dist - cut) < 1e-6 * cut).any(axis=1)
    assert np.array_equal(flags[~near_cut], expected[~near_cut])


def test_a_release_that_does_not_fit_names_the_fix():
    # 6 x 4 x 3 mm at d = 0.99 mm: 6*4*3 = 72 places
    pool = ParcelPool.empty(200)
    with pytest.raises(ConfigError, match="72 places.*longer injection window.*enlarge the box"):
        pool.inject(VolumeInjection(box_lo=BOX_LO, box_hi=BOX_HI, diameter_mean=0.99e-3, count=73))
    assert pool.inject(VolumeInjection(box_lo=BOX_LO, box_hi=BOX_HI, diameter_mean=0.99e-3, count=60)) == 60
    with pytest.raises(ConfigError, match="free of the parcels already there.*longer injection window"):
        pool.inject(VolumeInjection(box_lo=BOX_LO, box_hi=BOX_HI, diameter_mean=0.99e-3, count=20, seed=1))
    assert pool.used == 60  # a refused release adds nothing
