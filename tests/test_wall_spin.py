"""Rough-sphere walls with spin (``WallParams.spin``, ``HelConfig.wall_spin``; kernels/reflect.py ``reflect_spin``):
the wall acts at the parcel's contact point, so its spin changes at an impact and a sphere rolling along the wall
keeps its speed.

References, independent of the kernel: the rigid-body closed forms of a solid sphere (I = 2/5 m r^2) at a wall
(Walton 1993): a sticking impact without spin leaves v_t' = (1 - 2/7 (1 + beta)) v_t with the contact point at
-beta times its old tangential velocity, a sliding one loses mu (1 + e_n) v_n; the angular momentum about the contact
point is conserved (the wall's impulse acts there); kinetic energy (with rotation) never grows; the dem strategy's
Hertz-Mindlin wall (``hel_warp.collisions.dem`` via ``hel-warp impact --target wall``) on a sphere rolling into the wall.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.test_collision_models import D, make_particles
from tests.test_swept import hard_sphere_model  # noqa: F401  (fixture)
from tests.test_swept_walls import SIDE, step

R = 0.5 * D
MU = 0.3
E_N = 0.8


def reflect(v, omega, n, beta=0.0, friction=MU, e_n=E_N, radius=R):
    """reflect_spin on a batch of impacts, through a one-off kernel: (v', omega') as float64 arrays."""
    import warp as wp

    from kernels.reflect import reflect_spin

    @wp.kernel
    def run(v: wp.array(dtype=wp.vec3), w: wp.array(dtype=wp.vec3), n: wp.array(dtype=wp.vec3), r: float,
            e_n: float, beta: float, mu: float, v_out: wp.array(dtype=wp.vec3), w_out: wp.array(dtype=wp.vec3)):
        i = wp.tid()
        a, b = reflect_spin(v[i], w[i], n[i], r, e_n, beta, mu)
        v_out[i] = a
        w_out[i] = b

    m = len(v)
    arr = lambda a: wp.array(np.asarray(a, np.float32).reshape(m, 3), dtype=wp.vec3)  # noqa: E731
    vo, wo = wp.zeros(m, dtype=wp.vec3), wp.zeros(m, dtype=wp.vec3)
    wp.launch(run, dim=m, inputs=[arr(v), arr(omega), arr(n), float(radius), float(e_n), float(beta), float(friction),
                                  vo, wo])
    return vo.numpy().astype(np.float64), wo.numpy().astype(np.float64)


@pytest.mark.parametrize("beta", [0.0, 0.4])
def test_a_sticking_impact_without_spin_leaves_the_sphere_rolling_as_the_closed_form(beta):
    # the wall below: n = (0, 0, -1) points out of the fluid into the wall, the sphere moves down onto it; 20 degrees
    # from the normal: sticking for mu = 0.3
    vt, vn = 2.0 * np.sin(np.radians(20)), 2.0 * np.cos(np.radians(20))
    v2, w2 = reflect([[vt, 0, -vn]], [[0, 0, 0]], [[0, 0, -1]], beta=beta)
    assert v2[0, 2] == pytest.approx(E_N * vn, rel=1e-6)
    assert v2[0, 0] == pytest.approx((1 - 2 / 7 * (1 + beta)) * vt, rel=1e-6)
    # contact point at -R z: u = v + omega x (-R z) -> u_x = v_x - R omega_y
    u_after = v2[0, 0] - R * w2[0, 1]
    assert u_after == pytest.approx(-beta * vt, abs=1e-6 * vt)


def test_a_sphere_rolling_along_the_wall_keeps_its_speed_and_spin():
    # rolling: u = v_x - R omega_y = 0; a small normal approach (gravity pressing it on) is reflected only
    vt, vn = 2.5, 0.05
    v2, w2 = reflect([[vt, 0, -vn]], [[0, vt / R, 0]], [[0, 0, -1]])
    assert v2[0, 0] == pytest.approx(vt, rel=1e-6)
    assert w2[0, 1] == pytest.approx(vt / R, rel=1e-6)


def test_a_sliding_impact_loses_the_coulomb_bound_and_spins_up():
    # 80 degrees from the normal: (2/7) v_t > mu (1 + e_n) v_n, sliding
    vt, vn = 2.0 * np.sin(np.radians(80)), 2.0 * np.cos(np.radians(80))
    v2, w2 = reflect([[vt, 0, -vn]], [[0, 0, 0]], [[0, 0, -1]])
    dv = MU * (1 + E_N) * vn
    assert v2[0, 0] == pytest.approx(vt - dv, rel=1e-5)
    # omega' = (5 / (2 R)) n x dv_t, n = -z, dv_t = -dv x -> omega_y = -(5/(2R)) dv ... sign: n x dv_t
    expected = 2.5 / R * np.cross([0, 0, -1], [-dv, 0, 0])
    np.testing.assert_allclose(w2[0], expected, rtol=1e-5, atol=1e-3)


def test_angular_momentum_about_the_contact_point_is_conserved_and_energy_never_grows():
    rng = np.random.default_rng(3)
    m = 400
    n = rng.normal(size=(m, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = rng.normal(0.0, 2.0, size=(m, 3))
    v += (np.abs(np.sum(v * n, axis=1)) - np.sum(v * n, axis=1) + 0.05)[:, None] * n  # moving into the wall
    omega = rng.normal(0.0, 1.0, size=(m, 3)) / R
    for beta in (-1.0, 0.0, 0.5, 1.0):
        v2, w2 = reflect(v, omega, n, beta=beta)
        mass, inertia = 1.0, 0.4 * R * R
        # about the contact point c = x + R n: L = I omega + m (x - c) x v = I omega - m R n x v
        l1 = inertia * omega - mass * R * np.cross(n, v)
        l2 = inertia * w2 - mass * R * np.cross(n, v2)
        # the normal impulse acts along n through c: only the tangential components of L are conserved
        t1 = l1 - np.sum(l1 * n, axis=1)[:, None] * n
        t2 = l2 - np.sum(l2 * n, axis=1)[:, None] * n
        scale = mass * R * np.linalg.norm(v, axis=1)[:, None]
        np.testing.assert_allclose(t2 / scale, t1 / scale, atol=2e-5)
        e1 = 0.5 * mass * np.sum(v * v, axis=1) + 0.5 * inertia * np.sum(omega * omega, axis=1)
        e2 = 0.5 * mass * np.sum(v2 * v2, axis=1) + 0.5 * inertia * np.sum(w2 * w2, axis=1)
        assert np.all(e2 <= e1 * (1 + 1e-5))


def test_a_rolling_sphere_meets_the_wall_as_the_dem_hertz_mindlin_wall_does():
    # independent reference: our DEM (Hertz-Mindlin sphere-wall contact, spin, mu = 0.3, wall e_n = 0.8) on a sphere
    # rolling at 1 m/s that bounces on the wall at 0.3 m/s normal speed: it keeps its rolling speed (within 2 %),
    # where the spinless Table 1 law takes 20 % (e_t = 0.8) or the Coulomb bound mu (1 + e_n) v_n = 0.16 m/s
    from tests.test_impact_cli import _json

    vt, vn = 1.0, 0.3
    dem = _json("--target", "wall", "--diameter", str(D), "--restitution", str(E_N), "--friction", str(MU),
                "--velocity", f"{vt},0,{-vn}", "--omega", f"0,{vt / R},0")
    v2, w2 = reflect([[vt, 0, -vn]], [[0, vt / R, 0]], [[0, 0, -1]])
    assert dem["velocity_after"][0] == pytest.approx(vt, rel=0.02)
    assert v2[0, 0] == pytest.approx(dem["velocity_after"][0], rel=0.02)
    assert w2[0, 1] == pytest.approx(dem["omega_after"][1], rel=0.02)


def test_the_push_and_the_swept_wall_events_carry_the_spin(hard_sphere_model):
    import warp as wp

    from hel_warp.collisions.models import SurrogateCollision
    from hel_warp.gas.grid import Box, Geometry
    from kernels.reflect import make_wall_params, reflect_at_walls

    geometry = Geometry(shapes=(Box(lo=(0.0, 0.0, 0.0), hi=(SIDE, SIDE, SIDE)),))
    shapes = geometry.shapes_struct(None)
    params = make_wall_params(restitution_normal=E_N, friction=MU, surface=True, spin=True)
    vt, vn = 2.0 * np.sin(np.radians(20)), 2.0 * np.cos(np.radians(20))
    # the push's reflection: a sphere past the floor z = 0 (surface contact), moving down and along +x
    p = make_particles([[0.005, 0.005, 0.8 * R]], [[vt, 0.0, -vn]])
    hits = wp.zeros(1, dtype=wp.int32)
    reflect_at_walls(shapes, params, p.alive, p.x, p.v, hits, p.radius, particle_omega=p.omega)
    v_ref, w_ref = reflect([[vt, 0, -vn]], [[0, 0, 0]], [[0, 0, -1]])
    np.testing.assert_allclose(p.v.numpy()[0], v_ref[0], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(p.omega.numpy()[0], w_ref[0], rtol=1e-5, atol=1e-3)
    with pytest.raises(ValueError, match="omega"):
        reflect_at_walls(shapes, params, p.alive, p.x, p.v, hits, p.radius)
    # the swept detection's wall event: the same impact within the step
    p = make_particles([[0.005, 0.005, R + 0.2e-3]], [[vt, 0.0, -vn]])
    strategy = SurrogateCollision(model_dir=hard_sphere_model, wall_events=True)
    strategy.set_walls(shapes, params)
    step(strategy, p, 1e-3)
    assert strategy.counts()["wall_events"] == 1
    np.testing.assert_allclose(p.v.numpy()[0], v_ref[0], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(p.omega.numpy()[0], w_ref[0], rtol=1e-5, atol=1e-3)


def test_wall_spin_is_validated():
    from hel_warp.errors import ConfigError
    from hel_warp.hel import HelConfig
    from kernels.reflect import make_wall_params

    with pytest.raises(ConfigError, match="wall_spin_restitution"):
        HelConfig(dt=1e-3, wall_spin=True, wall_spin_restitution=1.5)
    with pytest.raises(ValueError, match="spin_restitution"):
        make_wall_params(spin=True, spin_restitution=-2.0)
