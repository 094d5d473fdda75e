"""Neighbour search and contact lists (kernels/contacts.py) against an O(N^2) brute force."""

import numpy as np
import pytest
import warp as wp

from hel_warp.collisions.dem import ContactList, ContactOverflowError, DEMConfig, DEMSolver
from hel_warp.material import Material
from hel_warp.parcels.particles import Particles
from kernels import contacts as kc
from kernels.integrate import sphere_arrays


def random_polydisperse(n, seed, box=0.02, r_lo=0.4e-3, r_hi=1.2e-3):
    rng = np.random.default_rng(seed)
    x = rng.uniform(r_hi, box - r_hi, size=(n, 3))
    radius = rng.uniform(r_lo, r_hi, size=n)
    return x, radius


def brute_force_rows(x, radius, cutoff_extra):
    """Reference: for every i the sorted set {j != i : |x_i - x_j| < r_i + r_j + extra} (O(N^2), float64)."""
    d = np.linalg.norm(x[:, None, :] - x[None, :, :], axis=2)
    within = d < radius[:, None] + radius[None, :] + cutoff_extra
    np.fill_diagonal(within, False)
    return [np.flatnonzero(row) for row in within]


def build_list(particles, skin, capacity, old=None):
    n = particles.count
    r_max = float(particles.radius.numpy().max())
    grid = wp.HashGrid(16, 16, 16)  # the test run's device (conftest)
    grid.build(particles.x, 2.0 * r_max + skin)
    new = ContactList.empty(n, capacity, None)
    if old is None:
        old = ContactList.empty(n, capacity, None)
    x_at_build = wp.zeros(n, dtype=wp.vec3)
    overflow = wp.zeros(1, dtype=wp.int32)
    kc.launch_build_contact_list(grid, sphere_arrays(particles), r_max, skin, old.rows(), new.rows(), x_at_build,
                                 overflow)
    return new, x_at_build, int(overflow.numpy()[0])


def rows_of(contacts):
    partner, count = contacts.partner.numpy(), contacts.count.numpy()
    return [partner[i, : count[i]] for i in range(len(count))]


def float32_positions(x):
    return x.astype(np.float32).astype(np.float64)


def test_hash_grid_list_equals_brute_force():
    x, radius = random_polydisperse(1500, seed=1)
    skin = 0.2e-3
    p = Particles.from_numpy(x, radius, check_overlap=False)
    contacts, _, overflow = build_list(p, skin, capacity=64)
    assert overflow == 0
    ref = brute_force_rows(float32_positions(x), radius.astype(np.float32).astype(np.float64), skin)
    got = rows_of(contacts)
    assert sum(len(r) for r in ref) > 3000  # the packing really has neighbours
    for i in range(len(x)):
        np.testing.assert_array_equal(got[i], ref[i])  # same partners, sorted by id


def test_verlet_guarantee_and_rebuild_after_moves():
    """After moves below skin/2 the old list still holds every touching pair (no rebuild flagged);
    after a larger move the flag is raised and the rebuilt list equals the brute force again."""
    x, radius = random_polydisperse(1200, seed=2)
    skin = 0.3e-3
    p = Particles.from_numpy(x, radius, check_overlap=False)
    contacts, x_at_build, _ = build_list(p, skin, capacity=64)
    rng = np.random.default_rng(3)
    direction = rng.normal(size=x.shape)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    small = x + direction * 0.49 * skin / 2.0 * rng.uniform(0, 1, size=(len(x), 1))
    p.x.assign(small.astype(np.float32))
    flag = wp.zeros(1, dtype=wp.int32)
    kc.launch_flag_rebuild(sphere_arrays(p), x_at_build, 0.5 * skin, flag)
    assert int(flag.numpy()[0]) == 0
    touching = brute_force_rows(float32_positions(small), radius, 0.0)
    got = rows_of(contacts)
    for i in range(len(x)):
        assert set(touching[i]) <= set(got[i])

    large = x + direction * 0.8 * skin
    p.x.assign(large.astype(np.float32))
    kc.launch_flag_rebuild(sphere_arrays(p), x_at_build, 0.5 * skin, flag)
    assert int(flag.numpy()[0]) == 1
    rebuilt, _, _ = build_list(p, skin, capacity=64, old=contacts)
    ref = brute_force_rows(float32_positions(large), radius.astype(np.float32).astype(np.float64), skin)
    for i, row in enumerate(rows_of(rebuilt)):
        np.testing.assert_array_equal(row, ref[i])


def tag_shear_with_pair(rows, marker: float):
    """Set the shear history of every entry (i, k) of ``rows`` to (i, partner j, marker); returns (partner, count)."""
    partner, count = rows.partner.numpy(), rows.count.numpy()
    tags = np.zeros(partner.shape + (3,), np.float32)
    for i in range(partner.shape[0]):
        for k in range(count[i]):
            tags[i, k] = (i, partner[i, k], marker)
    rows.shear.assign(tags)
    return partner, count


def test_shear_history_and_touching_flag_carried_by_partner_id():
    x, radius = random_polydisperse(800, seed=4)
    skin = 0.3e-3
    p = Particles.from_numpy(x, radius, check_overlap=False)
    old, _, _ = build_list(p, skin, capacity=64)
    # tag each history entry with its (i, j) pair, each touching flag with the parity of i + j
    partner, count = tag_shear_with_pair(old, 0.5)
    old.touching.assign(((np.arange(len(x))[:, None] + partner) % 2 * (partner >= 0)).astype(np.int32))
    # move so that some partners leave and new ones enter, then rebuild
    rng = np.random.default_rng(5)
    moved = x + rng.normal(scale=0.5e-3, size=x.shape)
    p.x.assign(moved.astype(np.float32))
    new, _, _ = build_list(p, skin, capacity=64, old=old)
    old_sets = [set(r) for r in rows_of(old)]
    shear, touching = new.shear.numpy(), new.touching.numpy()
    kept = fresh = 0
    for i, row in enumerate(rows_of(new)):
        for k, j in enumerate(row):
            if j in old_sets[i]:
                np.testing.assert_array_equal(shear[i, k], [i, j, 0.5])
                assert touching[i, k] == (i + j) % 2
                kept += 1
            else:
                np.testing.assert_array_equal(shear[i, k], [0.0, 0.0, 0.0])
                assert touching[i, k] == 0  # a new entry: not touching before
                fresh += 1
    assert kept > 100 and fresh > 100  # both cases were exercised


def test_gather_rows_follow_a_permutation():
    """Spatial-sort kernel: rows move with their particle, partners are renumbered, rows stay sorted."""
    x, radius = random_polydisperse(700, seed=6)
    p = Particles.from_numpy(x, radius, check_overlap=False)
    old, _, _ = build_list(p, 0.3e-3, capacity=64)
    partner, count = tag_shear_with_pair(old, 2.0)
    new_to_old = np.random.default_rng(9).permutation(len(x)).astype(np.int32)
    old_to_new = np.argsort(new_to_old).astype(np.int32)
    dst = ContactList.empty(len(x), 64, None)
    touching = np.zeros(old.touching.shape, np.int32)
    for i in range(len(x)):
        touching[i, : count[i]] = (partner[i, : count[i]] + i) % 2  # a tag the gather must carry with the row
    old.touching.assign(touching)
    kc.launch_gather_contact_rows(old.rows(), wp.array(new_to_old), wp.array(old_to_new), dst.rows())
    partner2, count2, shear2 = dst.partner.numpy(), dst.count.numpy(), dst.shear.numpy()
    touching2 = dst.touching.numpy()
    for k in range(len(x)):
        i = new_to_old[k]
        row = partner2[k, : count2[k]]
        assert np.all(np.diff(row) > 0)
        np.testing.assert_array_equal(np.sort(new_to_old[row]), partner[i, : count[i]])
        for c, j_new in enumerate(row):
            np.testing.assert_array_equal(shear2[k, c], [i, new_to_old[j_new], 2.0])
            assert touching2[k, c] == (i + new_to_old[j_new]) % 2


def _frictional_heap(sort_every):
    from hel_warp.parcels.particles import lattice_positions

    n = 800
    x = lattice_positions(n, 2.3e-3, (0, 0, 0), (0.02, 0.02, 0.2), jitter=0.2e-3, seed=6)
    x = x[np.random.default_rng(6).permutation(n)]  # memory order unrelated to space
    material = Material(density=2500.0, youngs_modulus=1e8, poisson_ratio=0.3, restitution=0.5, friction=0.5)
    p = Particles.from_numpy(x, 1e-3, density=2500.0)
    cfg = DEMConfig(material=material, box_lo=(0, 0, 0), box_hi=(0.02, 0.02, 0.2), sort_every=sort_every,
                    gravity=(0.0, 0.0, -9.81))
    return DEMSolver(cfg, p)


def test_spatial_sort_changes_order_not_physics():
    """Same run with and without spatial sorting (every rebuild): equal trajectories in original order,
    up to float32 round-off of the different summation order. The sorted run must really be permuted."""
    plain, sorted_ = _frictional_heap(0), _frictional_heap(1)
    for solver in (plain, sorted_):
        solver.simulate(3000)
    assert sorted_.rebuilds > 3
    assert not np.array_equal(sorted_.particles.particle_id.numpy(), np.arange(800))
    a, b = plain.particles.to_numpy(), sorted_.particles.to_numpy()
    # particles fell ~ g t^2 / 2 and collided (friction active); round-off only -> 1e-6 m agreement
    np.testing.assert_allclose(a["x"], b["x"], atol=1e-6)
    np.testing.assert_allclose(a["v"], b["v"], atol=2e-3)
    assert np.abs(a["omega"]).max() > 1.0  # contacts with friction happened


def test_overflow_is_reported():
    x, radius = random_polydisperse(1000, seed=7)
    skin = 0.2e-3
    ref = brute_force_rows(float32_positions(x), radius.astype(np.float32).astype(np.float64), skin)
    most = max(len(r) for r in ref)
    p = Particles.from_numpy(x, radius, check_overlap=False)
    _, _, overflow = build_list(p, skin, capacity=4)
    assert overflow == most  # the counter names the capacity needed
    # the solver refuses to run with a truncated list
    grid_x = np.stack(np.meshgrid(*[np.arange(6) * 2.02e-3 + 1.5e-3] * 3, indexing="ij"), -1).reshape(-1, 3)
    dense = Particles.from_numpy(grid_x, 1e-3, density=2500.0)
    with pytest.raises(ContactOverflowError, match="contact_capacity >= 6"):
        DEMSolver(DEMConfig(material=Material(density=2500.0), box_lo=(0, 0, 0), box_hi=(0.016, 0.016, 0.016),
                            contact_capacity=3, skin=0.3e-3), dense)


def test_touching_pair_list_equals_brute_force():
    x, radius = random_polydisperse(1000, seed=8)
    p = Particles.from_numpy(x, radius, check_overlap=False, density=2500.0)
    cfg = DEMConfig(material=Material(density=2500.0), box_lo=(0, 0, 0), box_hi=(0.02, 0.02, 0.02), walls=(),
                    gravity=(0, 0, 0), contact_capacity=64)
    solver = DEMSolver(cfg, p)
    ids = p.particle_id.numpy()  # device order may be spatially sorted: compare in original ids
    di, dj = solver.touching_pairs()
    pi, pj = np.minimum(ids[di], ids[dj]), np.maximum(ids[di], ids[dj])
    xf = float32_positions(x)
    d = np.linalg.norm(xf[:, None] - xf[None], axis=2)
    rf = radius.astype(np.float32).astype(np.float64)
    ii, jj = np.nonzero(np.triu(d < rf[:, None] + rf[None, :], k=1))
    assert len(ii) > 300
    assert set(zip(pi.tolist(), pj.tolist())) == set(zip(ii.tolist(), jj.tolist()))
    assert len(pi) == len(ii) and np.all(di < dj)
    gi, gj, gcount = solver.touching_pairs(as_numpy=False)  # device form for collision-rate kernels
    assert int(gcount.numpy()[0]) == len(ii)
    np.testing.assert_array_equal(gi.numpy()[: len(ii)], di)
    np.testing.assert_array_equal(gj.numpy()[: len(ii)], dj)



def test_packed_rows_hold_the_padded_rows_back_to_back():
    """The packed layout (row i right after row i - 1, built by threads in tid order) holds the same rows, shear
    history and touching flags as the padded one, full and half list, rebuilt from an old list of its own layout."""
    x, radius = random_polydisperse(900, seed=8)
    skin = 0.3e-3
    p = Particles.from_numpy(x, radius, check_overlap=False)
    n, capacity = len(x), 64
    r_max = float(p.radius.numpy().max())
    grid = wp.HashGrid(16, 16, 16)
    moved = x + np.random.default_rng(10).normal(scale=0.4e-3, size=x.shape)

    def build(positions, old, half, packed):
        p.x.assign(positions.astype(np.float32))
        grid.build(p.x, 2.0 * r_max + skin)
        new = ContactList.empty(n, capacity, None)
        kc.launch_build_contact_list(grid, sphere_arrays(p), r_max, skin, old.rows(), new.rows(),
                                     wp.zeros(n, dtype=wp.vec3), wp.zeros(1, dtype=wp.int32), half=half, packed=packed)
        return new

    for half in (False, True):
        result = {}
        for packed in (False, True):
            first = build(x, ContactList.empty(n, capacity, None), half, packed)
            # tag every entry with its pair (shear) and the parity of i + j (touching flag), in its own layout
            start, count = first.start.numpy(), first.count.numpy()
            partner = first.partner.numpy().reshape(-1)
            shear = np.zeros((n * capacity, 3), np.float32)
            touching = np.zeros(n * capacity, np.int32)
            for i in range(n):
                e = np.arange(start[i], start[i] + count[i])
                shear[e] = np.column_stack([np.full(len(e), i), partner[e], np.ones(len(e))])
                touching[e] = (i + partner[e]) % 2
            first.shear.assign(shear.reshape(n, capacity, 3))
            first.touching.assign(touching.reshape(n, capacity))
            second = build(moved, first, half, packed)
            start, count = second.start.numpy(), second.count.numpy()
            expected = np.concatenate([[0], np.cumsum(count)[:-1]]) if packed else np.arange(n) * capacity
            np.testing.assert_array_equal(start, expected)
            result[packed] = second.padded()
        a, b = result[False], result[True]
        assert a["count"].sum() > 2000 and np.count_nonzero(a["touching"]) > 100  # rows and carried history
        for name in ("count", "partner", "shear", "touching"):
            np.testing.assert_array_equal(a[name], b[name], err_msg=f"{name}, half={half}")
