"""Wall events of the swept detection (kernels/collide.py ``wall_touch``, ``swept_resolve_walls``): a parcel whose
path crosses the wall within the step is reflected at the crossing, in time order with its collisions.

Reference: the hard-sphere closed form (the constant contact forest of tests/test_swept.py: impulse_n = 1 + e) and
the point reflection of kernels/reflect.py (v' = -e_n v_n + e_t v_t), written out by hand on straight paths.
Wall events are the default of the strategy (``wall_events=True``; False keeps the end-of-step reflection, see
its docstring).
"""

from __future__ import annotations

import numpy as np
import pytest

from kernels.sdf import SdfShapes as kf_SdfShapes
from tests.test_collision_models import D, make_particles
from tests.test_swept import E, hard_sphere_model  # noqa: F401  (fixture)

E_WALL = 0.8  # Table 1 wall restitution (normal and tangential), kernels/reflect.py's defaults
SIDE = 0.01  # the fluid: the box [0, SIDE]^3


def box_walls():
    from hel_warp.gas.grid import Box, Geometry
    from kernels.reflect import make_wall_params

    geometry = Geometry(shapes=(Box(lo=(0.0, 0.0, 0.0), hi=(SIDE, SIDE, SIDE)),))
    return geometry.shapes_struct(None), make_wall_params(restitution_normal=E_WALL, restitution_tangential=E_WALL)


def step(strategy, p, dt):
    """collide, the push's drift with the new velocities, the in-step position corrections (as HelSolver.push)."""
    strategy.collide(p, dt)
    p.x.assign(p.x.numpy() + p.v.numpy() * dt)
    strategy.correct_positions(p)


@pytest.mark.parametrize("wall_events", [True, False])
def test_a_parcel_reflected_by_the_wall_collides_on_its_way_back_within_the_step(hard_sphere_model, wall_events):
    # A flies at +4 m/s into the wall x = SIDE, comes back at -E_WALL * 4 and meets B at rest, head on, all within
    # one step of 1 ms; closed form: wall at t1 = 0.5 mm / 4 m/s, touch when x_A - x_B = D
    from hel_warp.collisions.models import SurrogateCollision

    dt = 1e-3
    xa0, xb0, va = SIDE - 0.5e-3, SIDE - 1.2e-3, 4.0
    x = [[xa0, 0.005, 0.005], [xb0, 0.005, 0.005]]
    v = [[va, 0.0, 0.0], [0.0, 0.0, 0.0]]
    p = make_particles(x, v)
    strategy = SurrogateCollision(model_dir=hard_sphere_model, wall_events=wall_events)
    strategy.set_walls(*box_walls())
    step(strategy, p, dt)
    c = strategy.counts()
    vb_wall = -E_WALL * va
    t1 = (SIDE - xa0) / va
    tc = t1 + (SIDE - xb0 - D) / -vb_wall
    va_new, vb_new = 0.5 * (1.0 - E) * vb_wall, 0.5 * (1.0 + E) * vb_wall
    if not wall_events:
        # the end-of-step rule: A's straight path runs through the wall past B, no collision in this step (the push's
        # reflection would bring it back afterwards)
        assert c["collisions"] == 0 and c["wall_events"] == 0
        np.testing.assert_allclose(p.v.numpy()[:, 0], [va, 0.0])
        return
    assert c["wall_events"] == 1 and c["collisions"] == 1, c
    np.testing.assert_allclose(p.v.numpy()[:, 0], [va_new, vb_new], rtol=1e-5, atol=1e-6)
    xa = SIDE + vb_wall * (tc - t1) + va_new * (dt - tc)
    xb = xb0 + vb_new * (dt - tc)
    np.testing.assert_allclose(p.x.numpy()[:, 0], [xa, xb], rtol=0, atol=2e-8)  # float32 positions near 1 cm
    assert (p.x.numpy() <= SIDE).all()


def test_oblique_wall_bounce_keeps_the_tangential_speed_times_e_t_and_the_path_continuous(hard_sphere_model):
    # one parcel at 30 deg onto the wall y = 0: the reflection of kernels/reflect.py at the crossing time; its end
    # position is the reflected straight path (nothing left outside, nothing moved along the normal afterwards)
    from hel_warp.collisions.models import SurrogateCollision

    dt = 1e-3
    v0 = np.array([2.0, -2.0 * np.tan(np.radians(60.0)), 0.0])
    x0 = np.array([0.004, 0.0015, 0.005])
    p = make_particles([x0], [v0])
    strategy = SurrogateCollision(model_dir=hard_sphere_model, wall_events=True)
    strategy.set_walls(*box_walls())
    step(strategy, p, dt)
    t1 = x0[1] / -v0[1]
    # tangential loss (1 - e_t)|v_t| = 0.4 m/s against the Coulomb cap mu (1 + e_n)|v_n| (mu 0: no cap)
    v1 = np.array([E_WALL * v0[0], -E_WALL * v0[1], 0.0])
    np.testing.assert_allclose(p.v.numpy()[0], v1, rtol=1e-5)
    np.testing.assert_allclose(p.x.numpy()[0], x0 + v0 * t1 + v1 * (dt - t1), rtol=0, atol=2e-8)
    assert strategy.counts()["wall_events"] == 1


def test_wall_events_in_time_order_with_collisions_match_the_sequential_reference(hard_sphere_model):
    # a gas of parcels in a small closed box, fast enough for several wall hits and collisions per parcel and step:
    # the parallel rounds give the strict event order's result (one event per round, the globally earliest), and
    # the strict order gives the same in the step's windows as in one
    from hel_warp.collisions.models import SurrogateCollision

    rng = np.random.default_rng(3)
    n = 60
    lattice = np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), -1).reshape(-1, 3)[:n]
    x = 0.001 + lattice * 2.5 * D + rng.uniform(-0.2, 0.2, (n, 3)) * D
    v = rng.normal(0.0, 1.5, (n, 3))
    side = 0.001 + 4 * 2.5 * D  # a closed box just around the lattice
    from hel_warp.gas.grid import Box, Geometry
    from kernels.reflect import make_wall_params

    shapes = Geometry(shapes=(Box(lo=(0.0, 0.0, 0.0), hi=(side, side, side)),)).shapes_struct(None)
    params = make_wall_params(restitution_normal=E_WALL, restitution_tangential=E_WALL)
    out = {}
    for ordering, windows in (("parallel", 6), ("sequential", 6), ("sequential", 1), ("serial", 6), ("serial", 1)):
        p = make_particles(x, v)
        strategy = SurrogateCollision(model_dir=hard_sphere_model, ordering=ordering, wall_events=True,
                                      windows=windows)
        strategy.set_walls(shapes, params)
        hits = collisions = 0
        for _ in range(3):
            step(strategy, p, 1e-3)
            c = strategy.counts()
            hits += c["wall_events"]
            collisions += c["collisions"]
        assert c["windows"] == windows
        out[(ordering, windows)] = (p.x.numpy(), p.v.numpy(), hits, collisions)
    (xp, vp, hp, cp), (xs, vs, hs, cs) = out[("parallel", 6)], out[("sequential", 6)]
    # the windows change the searches only: the strict order gives the same wall events and collisions with one
    for key in (("sequential", 1), ("serial", 6), ("serial", 1)):  # the serial queue: the strict order's bits
        (x1, v1, h1, c1) = out[key]
        assert (h1, c1) == (hs, cs) and np.array_equal(v1, vs) and np.array_equal(x1, xs), key
    assert hp > 5 and cp > 5, (hp, cp)
    assert (hp, cp) == (hs, cs)
    np.testing.assert_allclose(vp, vs, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(xp, xs, rtol=0, atol=1e-7)
    assert (xp >= 0.0).all() and (xp <= side).all()


def test_the_bisection_over_the_shapes_near_the_path_matches_the_whole_union():
    # wall_touch brackets a crossing by bisection over only the shapes that may hold a point of the path's segment
    # (kernels/collide.py shapes_near_segment): on the rig's five boxes (two of them rotated), random paths from the
    # fluid to beyond the wall must give the whole union's crossing bit for bit, and that crossing must lie on the
    # wall by an independent float64 distance of the boxes
    import warp as wp

    from cases.colliding_streams import RigDimensions, build_geometry
    from kernels.collide import bisect_crossing, shapes_near_segment

    @wp.kernel
    def crossings(shapes: kf_SdfShapes, start: wp.array(dtype=wp.vec3), end: wp.array(dtype=wp.vec3), extra: float,
                  culled: wp.array(dtype=float), full: wp.array(dtype=float), mask_out: wp.array(dtype=int)):
        k = wp.tid()
        v = end[k] - start[k]
        mask = shapes_near_segment(shapes, start[k], end[k], extra)
        mask_out[k] = mask
        culled[k] = bisect_crossing(shapes, start[k], v, extra, 0.0, 1.0, mask)
        full[k] = bisect_crossing(shapes, start[k], v, extra, 0.0, 1.0, -1)

    _, geometry, _ = build_geometry(RigDimensions())
    shapes = geometry.shapes_struct(None)
    oriented = [s.oriented() for s in geometry.shapes]

    def sdf64(p):
        d = np.full(len(p), np.inf)
        for centre, rotation, half, _ in oriented:
            q = np.abs((np.asarray(p) - centre) @ np.asarray(rotation).T) - half
            d = np.minimum(d, np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0))
        return d

    rng = np.random.default_rng(11)
    lo = np.min([c - np.abs(r).T @ h for c, r, h, _ in oriented], axis=0)
    hi = np.max([c + np.abs(r).T @ h for c, r, h, _ in oriented], axis=0)
    for extra in (0.0, 157.5e-6):  # centre walls, and walls that meet the parcel's surface
        a = rng.uniform(lo, hi, (60_000, 3))
        a = a[sdf64(a) + extra < -1e-5]
        b = a + rng.normal(0.0, 2e-3, a.shape)
        keep = sdf64(b) + extra > 1e-5
        a, b = a[keep].astype(np.float32), b[keep].astype(np.float32)
        assert len(a) > 1000
        culled, full = wp.zeros(len(a), dtype=float), wp.zeros(len(a), dtype=float)
        masks = wp.zeros(len(a), dtype=int)
        wp.launch(crossings, dim=len(a), inputs=[shapes, wp.array(a, dtype=wp.vec3), wp.array(b, dtype=wp.vec3),
                                                 extra, culled, full, masks])
        t_c, t_f, m = culled.numpy(), full.numpy(), masks.numpy()
        assert np.array_equal(t_c, t_f)
        bits = np.array([bin(int(x) & 0x7FFFFFFF).count("1") for x in m])
        assert (bits >= 1).all() and np.mean(bits < shapes.count) > 0.9  # most segments bisect over fewer shapes
        x = a.astype(np.float64) + (b.astype(np.float64) - a) * t_c.astype(np.float64)[:, None]
        np.testing.assert_allclose(sdf64(x) + extra, 0.0, atol=2e-6)
