"""Contact onsets (real collisions) of the DEM, the triply periodic box and the wall-only reference.

References: free flight between contacts (the relative velocity before an onset is the one measured after
the previous one), the impact-parameter geometry of a sphere pair (normal approach speed |g| cos chi,
cos chi = sqrt(1 - b^2 / (r1 + r2)^2)), Hertz's static overlap (Johnson 1985, sec. 4.2), an O(N^2)
minimum-image brute force, and the same impact computed inside the box.
"""

import math
from types import SimpleNamespace

import numpy as np
import pytest
import warp as wp

from hel_warp.collisions.cfd_dem import DemCollision
from hel_warp.collisions.dem import DEMConfig, DEMSolver
from hel_warp.errors import ConfigError
from hel_warp.material import Material
from hel_warp.parcels.particles import Particles

D = 315e-6  # m, the rig's particles
R = 0.5 * D
FRICTIONLESS = Material(friction=0.0)


def pair(x, v, **kw):
    return Particles.from_numpy(np.asarray(x, float), R, v=np.asarray(v, float), density=1000.0,
                                check_overlap=False, **kw)


def free_solver(particles, walls_box=None):
    """What DemCollision.advance reads of HelSolver, with a gas that exerts nothing (the push is ballistic)."""
    n = particles.count
    fields = SimpleNamespace(parcel_a_coll=wp.zeros(n, dtype=wp.vec3))

    def fluid_push(*, particle_x_out, particle_v_out):
        wp.copy(particle_v_out, particles.v)
        wp.copy(particle_x_out, particles.x)

    config = SimpleNamespace(dt=None, walls=walls_box is not None)
    shapes = None
    if walls_box is not None:
        from hel_warp.gas.grid import Box, Geometry

        shapes = Geometry(shapes=(Box(lo=walls_box[0], hi=walls_box[1]),)).shapes_struct("cpu")
    return SimpleNamespace(pool=SimpleNamespace(particles=particles), fields=fields, config=config,
                           fluid_push=fluid_push, shapes=shapes)


# ------------------------------------------------------------------------------------------ onsets


@pytest.mark.parametrize("drift, dt, steps", [(0.0, 1e-6, 12), (15.0, 1e-5, 2)])
def test_head_on_pair_is_one_onset_at_the_approach_speed(drift, dt, steps):
    # Head-on at 2 m/s relative: exactly one onset, at speed |g| = 2 m/s (free flight before the touch: the
    # relative velocity is the initial one, float32 round-off only).
    # dt = 1 us, shorter than the Hertz contact (~4 us): the contact lasts over several steps, with a list
    # rebuild at each step start. dt = 10 us with a common drift of 15 m/s across the line of centres: the
    # pair moves ~60 um during the contact, more than skin/2 (24 um): list rebuilds inside the step, with
    # the contact closed (its touching flag carried by partner id).
    p = pair([[1e-3, 1e-3, 1e-3], [1e-3 + D + 1e-6, 1e-3, 1e-3]], [[1.0, drift, 0], [-1.0, drift, 0]],
             stream=[1, 2])
    strategy = DemCollision(material=FRICTIONLESS)
    rebuilds = []
    build = strategy._rebuild
    strategy._rebuild = lambda *a: (rebuilds.append(1), build(*a))
    collisions, overlapped, speeds = [], [], []
    for _ in range(steps):
        strategy.advance_free(p, dt)
        c = strategy.counts()
        collisions.append(c["collisions"])
        overlapped.append(c["detected_pairs"])
        speeds.extend(strategy.onset_speeds().tolist())
        assert c["collisions"] == c["collisions_1_2"] and c["collisions_0_0"] == 0
    assert sum(collisions) == 1
    if drift == 0.0:
        assert sum(overlapped) >= 2  # the contact was closed at >= 2 step ends: it persisted across rebuilds
    else:
        assert len(rebuilds) >= steps + 2  # rebuilds inside the steps (besides one at each step start)
    assert speeds == pytest.approx([2.0], rel=1e-6)
    assert p.v.numpy()[0, 0] < 0.0  # and it did rebound


@pytest.mark.parametrize("b", [0.0, 0.6, 0.95])
def test_oblique_onset_speed_is_the_normal_approach_speed(b):
    # Impact parameter b (r1 + r2): at first touch the normal approach speed is |g| sqrt(1 - b^2). The
    # onset is found at the first sub-step with overlap > 0, at most |g| h past the touch, which tilts the
    # centre line by <= |g| h / (r1 + r2) rad: tolerance |g| (|g| h / D) (+ float32 round-off).
    g = 2.0
    dx = math.sqrt(1.0 - b * b) * D + 2e-6  # 2 um (1 us) before the touch
    x = [[1e-3, 1e-3, 1e-3], [1e-3 + dx, 1e-3 + b * D, 1e-3]]
    p = pair(x, [[0.5 * g, 0, 0], [-0.5 * g, 0, 0]])
    strategy = DemCollision(material=FRICTIONLESS, onset_events=4)
    strategy.advance_free(p, 2e-5)
    ev = strategy.onset_events()
    assert strategy.counts()["collisions"] == 1 and len(ev["speed"]) == 1 and not ev["truncated"]
    assert (ev["particle_a"][0], ev["particle_b"][0]) == (0, 1)
    expected = g * math.sqrt(1.0 - b * b)
    tol = g * (g * strategy.dt_dem / D) + 1e-6 * g
    assert abs(float(ev["speed"][0]) - expected) <= tol
    assert strategy.counts()["impact_speed_sum"] == pytest.approx(float(ev["speed"][0]), rel=1e-6)
    # onset time: the straight-line touch |s0 + g_rel t| = r1 + r2 (docs/physics/references.md, swept detection), found
    # at the end of the sub-step that contains it
    s0 = np.array([dx, b * D, 0.0])
    grel = np.array([-g, 0.0, 0.0])
    sg, gg = s0 @ grel, grel @ grel
    t_touch = (-sg - math.sqrt(sg * sg - gg * (s0 @ s0 - D * D))) / gg
    assert t_touch <= float(ev["time"][0]) <= t_touch + strategy.dt_dem * (1 + 1e-6)


def test_periodic_pair_meets_exactly_k_times_each_at_the_free_flight_speed():
    # Two elastic frictionless spheres on the x axis of a periodic box (Lx = 6 D) approach at 4 m/s. Between
    # contacts the separation changes at |g| over 4 D (L - 2 D), alternately inside the box and across
    # the x faces: meetings at t_k = D / |g| + (k - 1) (4 D / |g| + t_c). Run to the middle between the 3rd
    # and the 4th: exactly 3 onsets; each at the relative speed of free flight measured before its step.
    g = 4.0
    L = (6 * D, 4 * D, 4 * D)
    p = pair([[1.0 * D, 2 * D, 2 * D], [3.0 * D, 2 * D, 2 * D]], [[0.5 * g, 0, 0], [-0.5 * g, 0, 0]])
    strategy = DemCollision(material=Material(restitution=1.0, friction=0.0), periodic_box=L)
    period = 4 * D / g
    end = D / g + 2.5 * period
    dt = period / 7.0
    total, times = 0, []
    for step in range(int(round(end / dt))):
        v = p.v.numpy().astype(np.float64)
        approach = abs(v[0, 0] - v[1, 0])
        strategy.advance_free(p, dt)
        ev = strategy.onset_events()
        total += strategy.counts()["collisions"]
        for speed, t in zip(ev["speed"], ev["time"]):
            assert float(speed) == pytest.approx(approach, rel=1e-5)
            times.append(step * dt + t)
        x = p.x.numpy()
        assert np.all((x >= 0.0) & (x < np.asarray(L, np.float32)))  # wrapped into the box
    assert total == 3
    t_c = 3.0 * 2.87 * ((1000.0 * math.pi / 6 * D**3 / 2) ** 2 / (R / 2 * (5e8 / (2 * (1 - 0.16))) ** 2 * g)) ** 0.2
    expected = [D / g + k * period for k in range(3)]
    np.testing.assert_allclose(times, expected, atol=t_c)  # t_c: the contact durations that shift the later ones


def test_resting_contact_over_many_rebuilds_is_not_an_onset():
    # A two-sphere stack on the floor, the pair placed at Hertz's static overlap under the top sphere's
    # weight (delta = (m g / (4/3 E* sqrt(R*)))^(2/3)), sliding frictionless at 0.5 m/s. After settling
    # (the bottom sphere sinks into the floor) the pair stays in contact while the neighbour list is rebuilt
    # every skin/2 of travel: zero onsets.
    mat = Material(density=2500.0, youngs_modulus=1e8, poisson_ratio=0.3, restitution=0.5, friction=0.0)
    r = 1e-3
    m = 2500.0 * 4.0 / 3.0 * math.pi * r**3
    e_pair = 1e8 / (2 * (1 - 0.09))
    d_pair = (m * 9.81 / (4 / 3 * e_pair * math.sqrt(r / 2))) ** (2 / 3)
    x = [[2e-3, 5e-3, r], [2e-3, 5e-3, 3 * r - d_pair]]
    p = Particles.from_numpy(x, r, v=[[0.5, 0, 0], [0.5, 0, 0]], density=2500.0, check_overlap=False)
    cfg = DEMConfig(material=mat, box_lo=(0, 0, 0), box_hi=(0.05, 0.01, 0.01), walls=("z-",),
                    gravity=(0, 0, -9.81), onset_events=8)
    solver = DEMSolver(cfg, p)
    solver.simulate(int(0.005 / solver.dt))  # settle
    solver.reset_onsets()
    rebuilds = solver.rebuilds
    solver.simulate(int(0.03 / solver.dt))
    assert solver.rebuilds - rebuilds >= 10
    assert solver.onset_counts()["collisions"] == 0 and len(solver.onset_events()["speed"]) == 0
    assert len(solver.touching_pairs()[0]) == 1  # still in contact


def test_standalone_dem_counts_onsets_per_stream_pair_and_resets():
    # DEMSolver shares the kernels: a head-on pair of streams 0 and 3 -> one onset under collisions_0_3 at
    # the approach speed; reset_onsets zeroes the counters; a second pair meeting later counts again.
    mat = Material(density=1000.0, friction=0.0)
    x = [[1e-3, 1e-3, 1e-3], [1e-3 + D + 1e-6, 1e-3, 1e-3], [1e-3, 3e-3, 1e-3], [1e-3 + D + 101e-6, 3e-3, 1e-3]]
    v = [[1.5, 0, 0], [-1.5, 0, 0], [0.5, 0, 0], [-0.5, 0, 0]]
    p = Particles.from_numpy(x, R, v=v, density=1000.0, stream=[0, 3, 1, 1])
    solver = DEMSolver(DEMConfig(material=mat, box_lo=(0, 0, 0), box_hi=(4e-3, 4e-3, 4e-3), walls=(),
                                 gravity=(0, 0, 0), onset_events=4), p)
    solver.simulate(int(2e-5 / solver.dt))  # first pair: touch after 0.33 us; second after 100 us
    c = solver.onset_counts()
    assert c["collisions"] == 1 and c["collisions_0_3"] == 1 and c["impact_speed_sum"] == pytest.approx(3.0)
    ev = solver.onset_events()
    assert ev["stream_a"].tolist() == [0] and ev["stream_b"].tolist() == [3]
    solver.reset_onsets()
    assert solver.onset_counts()["collisions"] == 0
    solver.simulate(int(1.2e-4 / solver.dt))
    c = solver.onset_counts()
    assert c["collisions"] == 1 and c["collisions_1_1"] == 1 and c["impact_speed_sum"] == pytest.approx(1.0)
    with pytest.raises(ConfigError, match="onset_events"):
        DEMSolver(DEMConfig(material=mat, box_lo=(0, 0, 0), box_hi=(4e-3, 4e-3, 4e-3), walls=(),
                            gravity=(0, 0, 0)), p).onset_events()


def random_periodic_gas(n, box, seed, speed=1.0, cells=(10, 8, 6)):
    """n spheres on random sites of a jittered lattice filling the periodic box (none overlapping, across the
    faces neither), Gaussian velocities; a quarter start shifted by whole box lengths (wrapped at the start)."""
    rng = np.random.default_rng(seed)
    cell = np.asarray(box) / np.asarray(cells)
    assert cell.min() > 1.1 * D  # with the jitter: centres >= 1.04 D apart
    sites = np.stack(np.meshgrid(*[np.arange(c) for c in cells], indexing="ij"), -1).reshape(-1, 3)
    sites = sites[rng.permutation(len(sites))[:n]]
    x = (sites + 0.5) * cell + rng.uniform(-0.08, 0.08, (n, 3)) * D
    x[: n // 4] += np.asarray(box) * rng.integers(-2, 3, (n // 4, 3))
    v = rng.normal(0.0, speed, (n, 3))
    return Particles.from_numpy(x, R, v=v, density=1000.0, check_overlap=False,
                                stream=rng.integers(0, 3, n))


def test_onset_counts_are_deterministic():
    # integer atomics for the counts, one writer per speed sum, the event list sorted: two identical runs
    # give identical counts, sums and events
    box = (12 * D, 10 * D, 8 * D)
    runs = []
    for _ in range(2):
        p = random_periodic_gas(300, box, seed=3, speed=3.0)
        s = DemCollision(material=FRICTIONLESS, periodic_box=box)
        out = []
        for _ in range(3):
            s.advance_free(p, 2e-5)
            ev = s.onset_events()
            out.append((s.counts(), ev["particle_a"].tobytes(), ev["speed"].tobytes()))
        runs.append(out)
    assert runs[0] == runs[1]
    assert sum(c["collisions"] for c, _, _ in runs[0]) > 20  # collisions did happen
    for c, a, speed in runs[0]:
        speeds = np.frombuffer(speed, np.float32)
        assert len(speeds) == c["collisions"] == sum(v for k, v in c.items() if k.startswith("collisions_"))
        assert float(speeds.astype(np.float64).sum()) == pytest.approx(c["impact_speed_sum"], rel=1e-6)


def test_a_full_event_list_is_flagged_and_the_counts_stay_exact():
    # the same run with a 2-entry and a 10^4-entry list: equal counts and speed sums; the short list says it
    # is truncated and holds 2 of the onsets of the long one
    box = (12 * D, 10 * D, 8 * D)
    out = []
    for capacity in (2, 10_000):
        p = random_periodic_gas(300, box, seed=4, speed=3.0)
        s = DemCollision(material=FRICTIONLESS, periodic_box=box, onset_events=capacity)
        s.advance_free(p, 4e-5)
        out.append((s.counts(), s.onset_events()))
    (c_short, ev_short), (c_long, ev_long) = out
    assert c_short == c_long and c_long["collisions"] > 2
    assert ev_short["truncated"] and len(ev_short["speed"]) == 2
    assert not ev_long["truncated"] and len(ev_long["speed"]) == c_long["collisions"]
    long_events = set(zip(ev_long["particle_a"].tolist(), ev_long["particle_b"].tolist(), ev_long["speed"].tolist()))
    assert set(zip(ev_short["particle_a"].tolist(), ev_short["particle_b"].tolist(),
                   ev_short["speed"].tolist())) <= long_events


# ------------------------------------------------------------------------------------------ periodic box


def brute_force_periodic(x, radius, box, extra):
    """O(N^2) float64 reference: pairs i < j with minimum-image distance < r_i + r_j + extra."""
    d = x[:, None, :] - x[None, :, :]
    d -= np.asarray(box) * np.round(d / np.asarray(box))
    dist = np.linalg.norm(d, axis=2)
    within = np.triu(dist < radius[:, None] + radius[None, :] + extra, k=1)
    return set(zip(*np.nonzero(within))), dist


def test_periodic_contact_list_and_overlaps_equal_the_minimum_image_brute_force():
    box = (9 * D, 11 * D, 7 * D)  # not a cube: each axis its own cell count
    n = 900
    rng = np.random.default_rng(7)
    x = rng.uniform(0.0, 1.0, (n, 3)) * np.asarray(box)
    x[:200] += np.asarray(box) * rng.integers(-2, 3, (200, 3))
    radius = rng.uniform(0.6, 1.0, n) * R
    p = Particles.from_numpy(x, radius, density=1000.0, check_overlap=False)
    s = DemCollision(material=FRICTIONLESS, periodic_box=box, contact_capacity=64)
    s._setup(p)
    n_sub, h, r_max, skin = s._prepare(p, 1e-9)
    s._rebuild(p, r_max, skin)
    xw = p.x.numpy().astype(np.float64)  # wrapped by the rebuild
    assert np.all((xw >= 0.0) & (xw < np.asarray(box)))
    rw = p.radius.numpy().astype(np.float64)
    ref, dist = brute_force_periodic(xw, rw, box, skin)
    partner, count = s.contacts.partner.numpy(), s.contacts.count.numpy()
    got = {(i, int(j)) for i in range(n) for j in partner[i, : count[i]] if j > i}
    assert got == ref
    assert sum(1 for i, j in ref if abs(xw[i] - xw[j]).max() > 0.5 * min(box)) > 20  # across the faces
    # rows are symmetric (a full list)
    assert sum(int(c) for c in count) == 2 * len(ref)
    # overlapping pairs at the end of a (tiny) step: detected_pairs against the brute force
    s.advance_free(p, 1e-9)
    xw = p.x.numpy().astype(np.float64)
    _, dist = brute_force_periodic(xw, rw, box, 0.0)
    touching = int(np.triu(dist < rw[:, None] + rw[None, :], k=1).sum())
    assert touching > 30 and s.counts()["detected_pairs"] == touching


def test_pair_meeting_across_a_face_collides_as_inside_the_box():
    # The same oblique impact (b = 0.4 (r1 + r2), 3 m/s) once in the middle of the box and once straddling
    # the x faces: the same post-collision velocities (restitution, deflection) and impact speed, up to the
    # float32 round-off of the positions (~1e-10 m against a ~1e-6 m peak overlap).
    L = (8 * D, 6 * D, 6 * D)
    results = []
    for x_first in (3.0 * D, L[0] - 0.6 * D):
        x = np.array([[x_first, 3 * D, 3 * D], [x_first + D + 3e-6, 3.4 * D, 3 * D]])
        p = pair(x, [[1.5, 0, 0], [-1.5, 0, 0]])
        s = DemCollision(material=Material(friction=0.3), periodic_box=L)
        s.advance_free(p, 3e-5)
        results.append((p.v.numpy().astype(np.float64), s.onset_speeds(), s.counts()["collisions"]))
    (v_in, speed_in, n_in), (v_face, speed_face, n_face) = results
    assert n_in == n_face == 1
    np.testing.assert_allclose(speed_face, speed_in, rtol=1e-4)
    np.testing.assert_allclose(v_face, v_in, atol=1e-4 * 3.0)
    g_n = -(v_in[0] - v_in[1])[0]
    assert 0.3 < g_n < 3.0  # it did rebound (the restitution is that of the Hertz contact, not 1)


def test_periodic_box_smaller_than_three_search_cells_is_refused():
    p = pair([[D, D, D], [3 * D, D, D]], [[0, 0, 0], [0, 0, 0]])
    with pytest.raises(ConfigError, match="3 contact-search cells"):
        DemCollision(periodic_box=(3 * D, 6 * D, 6 * D)).advance_free(p, 1e-6)
    with pytest.raises(ConfigError, match="periodic_box"):
        DemCollision(periodic_box=(1e-3, 1e-3))


# ------------------------------------------------------------------------------------------ walls only


def test_particle_contacts_off_gives_no_onsets_and_keeps_the_walls():
    # particle_contacts=False: a head-on pair passes through itself (velocities unchanged, no onset, the
    # overlap still reported by detected_pairs); a parcel thrown at the x = 0 wall rebounds with the wall
    # restitution e_w (Hertz sphere-wall contact, as with the contacts on).
    mat = Material(friction=0.0)
    box = ((0.0, 0.0, 0.0), (4e-3, 4e-3, 4e-3))
    x = [[2e-3, 1e-3, 2e-3], [2e-3 + D + 1e-6, 1e-3, 2e-3], [R + 20e-6, 3e-3, 2e-3]]
    v = [[1.0, 0, 0], [-1.0, 0, 0], [-2.0, 0, 0]]
    p = pair(x, v)
    solver = free_solver(p, walls_box=box)
    solver.config.dt = 2e-6
    s = DemCollision(material=mat, particle_contacts=False)
    onsets, overlapped = 0, 0
    for _ in range(40):
        s.accelerate(solver)
        s.advance(solver)
        onsets += s.counts()["collisions"]
        overlapped += s.counts()["detected_pairs"]
    vel = p.v.numpy().astype(np.float64)
    assert onsets == 0 and overlapped > 0
    np.testing.assert_allclose(vel[:2], np.asarray(v[:2]), atol=1e-6)  # passed through each other
    assert vel[2, 0] == pytest.approx(mat.wall_restitution_normal * 2.0, rel=0.02)
    # the same run with the contacts on: the pair collides once
    p2 = pair(x, v)
    solver2 = free_solver(p2, walls_box=box)
    solver2.config.dt = 2e-6
    s2 = DemCollision(material=mat)
    total = 0
    for _ in range(40):
        s2.accelerate(solver2)
        s2.advance(solver2)
        total += s2.counts()["collisions"]
    assert total == 1 and p2.v.numpy()[0, 0] < 0.0
