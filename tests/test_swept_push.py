"""The swept detection and the push's velocity change (drag, gravity) in one step.

- In a ``HelSolver`` (``SurrogateCollision.accelerate`` / ``advance``, ``kick_first``, the default) the push's
  velocities come first and the collisions act on the paths the parcels then take; the step ends at the swept
  paths' ends (kernels/collide.py ``drift_swept``).
- A caller that collides and then pushes (``kick_first=False``, the cooling case's ballistic move): the push's
  velocity change acts from a parcel's last collision in the step on, not over the part of its path before it
  (``add_swept_shift``, ``SurrogateCollision.correct_positions``).

Reference: the hard-sphere closed form (the constant contact forest of tests/test_swept.py, impulse_n = 1 + e) on
straight paths, then the push's new velocity over the rest of the step, written out by hand.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.test_collision_models import D, make_particles
from tests.test_swept import E, hard_sphere_model  # noqa: F401  (fixture)

DT = 1e-3
KEEP = 0.5  # the push keeps half of each velocity: a drag with dt / tau = 1 towards still gas (semi-implicit)


def push_and_correct(strategy, p, keep=KEEP):
    """The push of HelSolver: v *= keep (drag towards gas at rest), x += v dt, then the in-step corrections."""
    v = p.v.numpy() * keep
    p.v.assign(v)
    p.x.assign(p.x.numpy() + v * DT)
    strategy.correct_positions(p)


def test_a_late_collision_under_strong_drag_leaves_the_pair_apart_on_its_new_paths(hard_sphere_model):
    from hel_warp.collisions.models import SurrogateCollision

    # A and B head on at 2 m/s each, touching at t* = 0.8 dt; C alone (no event): the push alone moves it
    u = 2.0
    t_star = 0.8 * DT
    gap = 2.0 * u * t_star
    x = [[0.0, 0.0, 0.0], [D + gap, 0.0, 0.0], [0.0, 5e-3, 0.0]]
    v = [[u, 0.0, 0.0], [-u, 0.0, 0.0], [1.0, 0.0, 0.0]]
    p = make_particles(x, v)
    strategy = SurrogateCollision(model_dir=hard_sphere_model)
    strategy.collide(p, DT)
    assert strategy.counts()["collisions"] == 1
    va, vb = -E * u, E * u  # equal masses, head on: the relative velocity reversed times e
    np.testing.assert_allclose(p.v.numpy()[:2, 0], [va, vb], rtol=1e-5)
    push_and_correct(strategy, p)
    xa = u * t_star + KEEP * va * (DT - t_star)
    xb = D + gap - u * t_star + KEEP * vb * (DT - t_star)
    np.testing.assert_allclose(p.x.numpy()[:, 0], [xa, xb, KEEP * 1.0 * DT], rtol=0, atol=2e-9)
    assert p.x.numpy()[1, 0] - p.x.numpy()[0, 0] > D  # apart, as the pair leaves its contact
    # the same push applied over the whole step (x0 + v_push dt + the swept shift) would leave them overlapping:
    # the scenario does test the rule
    old_a = KEEP * va * DT + (u - va) * t_star
    old_b = D + gap + KEEP * vb * DT + (-u - vb) * t_star
    assert old_b - old_a < D


def test_without_a_velocity_change_in_the_push_the_end_positions_are_the_swept_paths(hard_sphere_model):
    from hel_warp.collisions.models import SurrogateCollision

    u, t_star = 3.0, 0.3 * DT
    x = [[0.0, 0.0, 0.0], [D + 2.0 * u * t_star, 0.0, 0.0]]
    p = make_particles(x, [[u, 0.0, 0.0], [-u, 0.0, 0.0]])
    strategy = SurrogateCollision(model_dir=hard_sphere_model)
    strategy.collide(p, DT)
    push_and_correct(strategy, p, keep=1.0)
    xa = u * t_star - E * u * (DT - t_star)
    xb = D + u * t_star + E * u * (DT - t_star)
    np.testing.assert_allclose(p.x.numpy()[:, 0], [xa, xb], rtol=0, atol=2e-9)


class KickSolver:
    """A HelSolver stand-in for the strategy interface: no walls, no gas; its push keeps KEEP of each velocity (a
    drag with dt / tau = 1 towards still gas) and drifts x += v_push dt, as the engine's backward-Euler push."""

    def __init__(self, particles, keep=KEEP):
        from types import SimpleNamespace

        import warp as wp

        self.pool = SimpleNamespace(particles=particles)
        self.config = SimpleNamespace(dt=DT, walls=False)
        self.fields = SimpleNamespace(parcel_a_coll=wp.zeros(particles.x.shape[0], dtype=wp.vec3))
        self.grid = None
        self.keep = keep
        self.pushes = 0

    def fluid_push(self, *, particle_x_out=None, particle_v_out=None):
        p = self.pool.particles
        v = p.v.numpy() * self.keep
        (p.v if particle_v_out is None else particle_v_out).assign(v)
        (p.x if particle_x_out is None else particle_x_out).assign(p.x.numpy() + v * DT)
        self.pushes += 1

    def step(self, strategy):
        strategy.accelerate(self)  # HelSolver.collide
        strategy.advance(self)  # HelSolver.push
        strategy.after_push(self)


def test_the_kick_comes_first_so_the_swept_paths_are_the_pushed_paths(hard_sphere_model):
    from hel_warp.collisions.models import SurrogateCollision

    # A and B head on at 2 m/s: on their start velocities they would touch at 0.6 dt, on the pushed ones (1 m/s
    # each) at 1.2 dt, i.e. not in this step: no collision, each drifts by v_push dt
    u = 2.0
    gap = 2.0 * u * 0.6 * DT
    x0 = np.array([[0.0, 0.0, 0.0], [D + gap, 0.0, 0.0]])
    p = make_particles(x0, [[u, 0.0, 0.0], [-u, 0.0, 0.0]])
    solver = KickSolver(p)
    strategy = SurrogateCollision(model_dir=hard_sphere_model)
    solver.step(strategy)
    assert solver.pushes == 1 and strategy.counts()["collisions"] == 0
    np.testing.assert_allclose(p.v.numpy()[:, 0], [KEEP * u, -KEEP * u], rtol=1e-6)
    np.testing.assert_allclose(p.x.numpy()[:, 0], [KEEP * u * DT, D + gap - KEEP * u * DT], rtol=0, atol=2e-9)
    # a closer pair touches on the pushed paths at t* = gap / (2 KEEP u) and leaves with -e times them
    gap = 2.0 * KEEP * u * 0.7 * DT
    p = make_particles([[0.0, 0.0, 0.0], [D + gap, 0.0, 0.0]], [[u, 0.0, 0.0], [-u, 0.0, 0.0]])
    solver = KickSolver(p)
    solver.step(strategy)
    assert strategy.counts()["collisions"] == 1
    t_star = 0.7 * DT
    w = KEEP * u
    np.testing.assert_allclose(p.v.numpy()[:, 0], [-E * w, E * w], rtol=1e-5)
    xa = w * t_star - E * w * (DT - t_star)
    xb = D + gap - w * t_star + E * w * (DT - t_star)
    np.testing.assert_allclose(p.x.numpy()[:, 0], [xa, xb], rtol=0, atol=2e-9)
    # kick_first=False: collide on the start velocities (touch at 0.35 dt), then push the collided ones
    p = make_particles([[0.0, 0.0, 0.0], [D + gap, 0.0, 0.0]], [[u, 0.0, 0.0], [-u, 0.0, 0.0]])
    solver = KickSolver(p)
    late = SurrogateCollision(model_dir=hard_sphere_model, kick_first=False)
    solver.step(late)
    assert late.counts()["collisions"] == 1
    np.testing.assert_allclose(p.v.numpy()[:, 0], [-KEEP * E * u, KEEP * E * u], rtol=1e-5)


@pytest.mark.parametrize("kick_first", [True, False])
def test_a_hel_step_with_strong_drag_ends_with_nothing_overlapping(hard_sphere_model, kick_first):
    # 1,500 light parcels (dt / tau ~ 1 in still air) at random speeds in the closed box of tests/test_hel_step.py,
    # five full HEL steps with the swept surrogate and wall events: with the kick first the step ends on the swept
    # paths, so no pair overlaps by more than float32 round-off; collide-then-push (the last-event rule) leaves
    # pairs the detection saw on paths the parcels do not take (measured: up to 0.8 of the contact distance)
    from scipy.spatial import cKDTree

    from hel_warp.collisions.models import SurrogateCollision
    from tests.test_hel_step import BOX_HI, make_solver

    rng = np.random.default_rng(11)
    radius = 0.1e-3
    n = 1500
    x = rng.uniform([3 * radius] * 3, np.asarray(BOX_HI) - 3 * radius, (n, 3))
    keep = np.ones(n, bool)
    for i in range(n):  # a non-overlapping start
        if keep[i]:
            d = np.linalg.norm(x - x[i], axis=1)
            keep &= (d >= 2.05 * radius) | (np.arange(n) <= i)
    x = x[keep]
    v = rng.normal(0.0, 2.0, (len(x), 3))
    strategy = SurrogateCollision(model_dir=hard_sphere_model, kick_first=kick_first)
    solver = make_solver(x=x, v=v, radius=radius, density=10.0, collision=strategy, gravity=(0.0, 0.0, 0.0))
    collisions = 0
    worst = 0.0
    for _ in range(5):
        solver.step()
        collisions += strategy.counts()["collisions"]
        p = solver.pool.particles
        xs = p.x.numpy().astype(np.float64)
        pairs = cKDTree(xs).query_pairs(2.0 * radius, output_type="ndarray")
        if len(pairs):
            depth = 2.0 * radius - np.linalg.norm(xs[pairs[:, 0]] - xs[pairs[:, 1]], axis=1)
            worst = max(worst, float(depth.max()) / (2.0 * radius))
    assert collisions > 50  # the gas is dense enough to test the rule
    if kick_first:
        assert worst < 1e-4
    else:
        assert worst > 1e-3  # the order matters here, so the first assertion can fail
