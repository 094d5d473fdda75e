"""Parcels that meet the wall with their surface (``WallParams.surface``, ``HelConfig.wall_contact="surface"``):
the wall acts where the centre is a particle radius from it, in the push's reflection (kernels/reflect.py) and in
the swept detection's wall events (kernels/collide.py ``wall_distance``).

Reference: the point reflection v' = -e_n v_n + e_t v_t and the mirror of the depth travelled past the contact
plane, written out by hand with the plane moved in by the radius; the same bounce in time order with a collision
against the hard-sphere closed form (the constant contact forest of tests/test_swept.py).
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.test_collision_models import D, make_particles
from tests.test_swept import E, hard_sphere_model  # noqa: F401  (fixture)
from tests.test_swept_walls import E_WALL, SIDE, step

R = 0.5 * D


def surface_walls():
    from hel_warp.gas.grid import Box, Geometry
    from kernels.reflect import make_wall_params

    geometry = Geometry(shapes=(Box(lo=(0.0, 0.0, 0.0), hi=(SIDE, SIDE, SIDE)),))
    return geometry.shapes_struct(None), make_wall_params(restitution_normal=E_WALL, restitution_tangential=E_WALL,
                                                          surface=True)


def test_the_push_reflection_acts_a_radius_from_the_wall():
    import warp as wp

    from kernels.reflect import reflect_at_walls

    shapes, params = surface_walls()
    # A: centre 0.2 r short of the wall, surface 0.8 r past it, moving in: reflected about the plane x = SIDE - r;
    # B: centre 1.2 r from the wall, surface inside: untouched; C: past the contact plane but moving away: moved
    # back onto it, its velocity kept
    x = np.array([[SIDE - 0.2 * R, 0.005, 0.005], [SIDE - 1.2 * R, 0.004, 0.005], [SIDE - 0.5 * R, 0.006, 0.005]])
    v = np.array([[3.0, 1.0, 0.0], [3.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    px = wp.array(x.astype(np.float32), dtype=wp.vec3)
    pv = wp.array(v.astype(np.float32), dtype=wp.vec3)
    radius = wp.array(np.full(3, R, np.float32), dtype=float)
    hits = wp.zeros(1, dtype=wp.int32)
    reflect_at_walls(shapes, params, wp.ones(3, dtype=wp.int32), px, pv, hits, radius)
    depth = 0.8 * R
    np.testing.assert_allclose(pv.numpy()[0], [-E_WALL * 3.0, E_WALL * 1.0, 0.0], rtol=1e-6)
    assert px.numpy()[0, 0] == pytest.approx(SIDE - R - E_WALL * depth, abs=1e-9)
    np.testing.assert_array_equal(px.numpy()[1], x[1].astype(np.float32))
    assert px.numpy()[2, 0] == pytest.approx(SIDE - R, abs=1e-8)
    np.testing.assert_allclose(pv.numpy()[2], v[2], rtol=0)
    assert int(hits.numpy()[0]) == 1
    with pytest.raises(ValueError, match="radius"):
        reflect_at_walls(shapes, params, wp.ones(3, dtype=wp.int32), px, pv, hits)


def test_a_wall_event_at_the_surface_then_a_collision_within_the_step(hard_sphere_model):
    # as tests/test_swept_walls.py's bounce-then-collide, with the wall acting at SIDE - r: A at +4 m/s reaches the
    # contact plane at t1 = (SIDE - r - xa0) / 4, comes back at -E_WALL 4 and meets B at rest head on
    from hel_warp.collisions.models import SurrogateCollision

    dt = 1e-3
    xa0, xb0, va = SIDE - R - 0.5e-3, SIDE - R - 1.2e-3, 4.0
    p = make_particles([[xa0, 0.005, 0.005], [xb0, 0.005, 0.005]], [[va, 0.0, 0.0], [0.0, 0.0, 0.0]])
    strategy = SurrogateCollision(model_dir=hard_sphere_model)  # wall events: the default
    strategy.set_walls(*surface_walls())
    step(strategy, p, dt)
    c = strategy.counts()
    assert c["wall_events"] == 1 and c["collisions"] == 1, c
    wall = SIDE - R
    vb_wall = -E_WALL * va
    t1 = (wall - xa0) / va
    tc = t1 + (wall - xb0 - D) / -vb_wall
    va_new, vb_new = 0.5 * (1.0 - E) * vb_wall, 0.5 * (1.0 + E) * vb_wall
    np.testing.assert_allclose(p.v.numpy()[:, 0], [va_new, vb_new], rtol=1e-5, atol=1e-6)
    xa = wall + vb_wall * (tc - t1) + va_new * (dt - tc)
    xb = xb0 + vb_new * (dt - tc)
    np.testing.assert_allclose(p.x.numpy()[:, 0], [xa, xb], rtol=0, atol=2e-8)
    assert (p.x.numpy()[:, 0] <= wall + 1e-8).all()  # no surface past the wall


def test_wall_contact_is_validated():
    from hel_warp.errors import ConfigError
    from hel_warp.hel import HelConfig

    assert HelConfig(dt=1e-3).wall_contact == "point"
    with pytest.raises(ConfigError, match="wall_contact must be 'point' or 'surface'"):
        HelConfig(dt=1e-3, wall_contact="sphere")


def test_the_push_reflection_at_a_concave_corner_uses_the_face_its_path_crossed():
    """A dead end (box A, x < 10 mm) beside a longer, lower box B (y < 2 mm): a parcel at y = 3 mm moving +x ends the
    step at x = 12 mm, past A's end face but nearer B's top face (1 mm against 2 mm). Reflected at its end point's
    nearest wall, its velocity is along that face and it is only moved down into B: it has passed through A's end
    wall. With the step's start positions the reflection is against the face the path crossed (the plane x = 10 mm):
    v' = -e_n v, and the depth 2 mm comes back shortened by e_n, x' = 10 - e_n 2 mm (hand-written reference)."""
    import warp as wp

    from hel_warp.gas.grid import Box, Geometry
    from kernels.reflect import make_wall_params, reflect_at_walls

    mm = 1e-3
    geometry = Geometry(shapes=(Box(lo=(0.0, 0.0, 0.0), hi=(10 * mm, 10 * mm, 10 * mm)),
                                Box(lo=(0.0, -10 * mm, 0.0), hi=(20 * mm, 2 * mm, 10 * mm))))
    shapes = geometry.shapes_struct(None)
    params = make_wall_params(restitution_normal=E_WALL, restitution_tangential=E_WALL)
    start = np.array([[9.0 * mm, 3.0 * mm, 5.0 * mm]], np.float32)
    end = np.array([[12.0 * mm, 3.0 * mm, 5.0 * mm]], np.float32)
    v = np.array([[3.0, 0.0, 0.0]], np.float32)
    results = []
    for with_start in (False, True):
        px = wp.array(end, dtype=wp.vec3)
        pv = wp.array(v, dtype=wp.vec3)
        hits = wp.zeros(1, dtype=wp.int32)
        reflect_at_walls(shapes, params, wp.ones(1, dtype=wp.int32), px, pv, hits,
                         particle_x_start=wp.array(start, dtype=wp.vec3) if with_start else None)
        results.append((px.numpy()[0], pv.numpy()[0], int(hits.numpy()[0])))
    (x_old, v_old, _), (x_new, v_new, hits_new) = results
    assert x_old[0] > 10 * mm and v_old[0] > 0.0  # the old way: through A's end wall, still moving on
    np.testing.assert_allclose(v_new, [-E_WALL * 3.0, 0.0, 0.0], rtol=1e-6)
    assert x_new[0] == pytest.approx(10 * mm - E_WALL * 2 * mm, abs=1e-8) and hits_new == 1
    np.testing.assert_allclose(x_new[1:], end[0, 1:], atol=1e-9)
