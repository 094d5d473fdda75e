"""Collision strategies of hel_warp/collisions/models.py: surrogate (pairwise, paper) and dem.

References (docs/developer/conventions.md rule 9): XGBoost's own ``predict`` of the trained boosters with the numpy
contact-form impulse of surrogate/features.py; the closed-form frictionless binary collision
(docs/physics/references.md "Binary collision outcome"); momentum conservation; an O(N^2) brute-force pair search.
The model is a tiny contact-form (and paper-form) XGBoost trained once per test run on a few thousand
frictionless Hertz DEM impacts (surrogate/dataset.py + surrogate/train.py, 1 trial).
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

D = 315e-6  # paper's small particles, m
RHO = 1000.0  # polyethylene, kg/m^3
E_REST = 0.9  # Material() restitution, the data set's DEM calibrates it to < 0.3 % (surrogate/dataset.py)


def train_tiny_models(root) -> dict:
    """{"contact": dir, "paper": dir}: models trained on 3000 frictionless DEM binary impacts (once per root)."""
    from hel_warp.material import Material
    from surrogate import train as T
    from surrogate.dataset import build_dataset, make_spec
    from surrogate.features import load_collision_data

    out = {form: str(root / f"model_{form}") for form in ("contact", "paper")}
    if all((root / f"model_{form}" / "forest.json").exists() for form in out):
        return out
    spec = make_spec(samples=3000, seed=0, diameter=D, diameter_std=0.0, material=Material(friction=0.0),
                     chunk_size=3000)
    build_dataset(root / "data", spec, progress=False, overwrite=True)
    data = load_collision_data(str(root / "data"))
    saved = T.SEARCH_SPACE["n_estimators"]
    T.SEARCH_SPACE["n_estimators"] = (100, 150)  # small forests: CI time
    try:
        for form in ("contact", "paper"):
            T.train(data, out[form], T.TrainConfig(form=form, trials=1, jobs=1, progress=False, report=False))
    finally:
        T.SEARCH_SPACE["n_estimators"] = saved
    return out


@pytest.fixture(scope="session")
def trained_models(tmp_path_factory):
    """Tiny contact- and paper-form models, cached in pytest's base temp dir (shared across modules), or in
    HEL_WARP_TINY_MODELS when set (scripts/gpu_check.sh trains them once for its tests and its rig runs)."""
    import os
    from pathlib import Path

    cache = os.environ.get("HEL_WARP_TINY_MODELS")
    root = Path(cache) if cache else tmp_path_factory.getbasetemp() / "tiny_collision_models"
    root.mkdir(parents=True, exist_ok=True)
    return train_tiny_models(root)


def xgboost_targets(model_dir, form, v1, v2, n, d1, d2, rho1, rho2):
    """Reference: XGBoost's own predict of the ``form``'s targets from its raw features (n None: paper form)."""
    from surrogate.artifact import load_artifact
    from surrogate.features import raw_features

    art = load_artifact(model_dir, boosters=True)
    return art.predict(raw_features(form, v1, v2, n, d1, d2, rho1, rho2).astype(np.float32))


def xgboost_pairwise(model_dir, v1, v2, n, d1, d2, rho1, rho2):
    """Reference: XGBoost's own predict on the contact features, then the numpy equal-and-opposite impulse."""
    from surrogate.features import apply_contact_model

    targets = xgboost_targets(model_dir, "contact", v1, v2, n, d1, d2, rho1, rho2)
    return apply_contact_model(v1, v2, n, d1, d2, rho1, rho2, targets)


def xgboost_paper(model_dir, v1, v2, d1, d2, rho1, rho2):
    """Reference: XGBoost's own predict of u, v, w from the paper features (v1, v2, d1, d2, rho1, rho2)."""
    return xgboost_targets(model_dir, "paper", v1, v2, None, d1, d2, rho1, rho2)


def impulse_mae(model_dir, target: str) -> float:
    """The model's test MAE of one contact target (metrics.json)."""
    import json
    import os

    with open(os.path.join(model_dir, "metadata.json")) as fh:
        return float(json.load(fh)["metrics"]["targets"][target]["mae"])


def impulse_n_mae(model_dir) -> float:
    return impulse_mae(model_dir, "impulse_n")


def dem_outcome(v1, v2, n):
    """The project's DEM (hel_warp.collisions.impact, the data set's material: Material(friction=0), D, RHO) on the impact of
    v1, v2 whose first-touch normal from 1 to 2 is n: the post-collision velocities (v1', v2')."""
    from hel_warp.collisions.impact import place_just_apart, simulate_pairs, stable_time_step
    from hel_warp.material import Material

    m = Material(friction=0.0)
    dt = float(stable_time_step(0.5 * D, RHO, m.youngs_modulus, m.poisson_ratio, float(np.linalg.norm(v1 - v2))))
    x1, x2 = place_just_apart(normal=n, velocity1=v1, velocity2=v2, radius1=0.5 * D, radius2=0.5 * D, dt=dt)
    res = simulate_pairs(x1=x1, x2=x2, v1=v1, v2=v2, radius1=0.5 * D, density1=RHO, youngs1=m.youngs_modulus,
                         poisson1=m.poisson_ratio, restitution=m.restitution, friction=0.0)
    assert bool(res.separated[0])
    return np.asarray(res.velocity1[0], np.float64), np.asarray(res.velocity2[0], np.float64)


def make_particles(x, v, *, radius=0.5 * D, density=RHO, weight=1.0, stream=0):
    from hel_warp.parcels.particles import Particles

    return Particles.from_numpy(np.asarray(x, float), radius, v=np.asarray(v, float), density=density,
                                weight=weight, stream=stream, check_overlap=False, device=None)  # the test run's device


def momentum(p) -> np.ndarray:
    """Parcel momentum sum w m v, float64 (N s)."""
    m = p.mass_numpy() * p.weight.numpy().astype(np.float64)
    return (m[:, None] * p.v.numpy().astype(np.float64)).sum(axis=0)


def closed_form(v1, v2, n, e):
    """Frictionless binary collision of equal masses: v1' = v1 - (1+e)/2 (g.n) n, v2' = v2 + (1+e)/2 (g.n) n."""
    g_n = float(np.dot(np.subtract(v1, v2), n))
    return np.asarray(v1) - 0.5 * (1 + e) * g_n * np.asarray(n), np.asarray(v2) + 0.5 * (1 + e) * g_n * np.asarray(n)


def pair_case(trained_models, offset_angle_deg):
    """Two spheres overlapping by 10 % of d, centre line at ``offset_angle_deg`` to the relative velocity."""
    from hel_warp.collisions.models import SurrogateCollision

    a = math.radians(offset_angle_deg)
    n = np.array([math.cos(a), math.sin(a), 0.0])
    x = np.array([[0.0, 0.0, 0.0], 0.9 * D * n])
    v = np.array([[2.0, 0.3, 0.0], [-2.0, 0.3, 0.0]])
    p = make_particles(x, v)
    strategy = SurrogateCollision(model_dir=trained_models["contact"], detection="overlap")
    p0 = momentum(p)
    strategy.collide(p)
    return p, v, n, p0, strategy


@pytest.mark.parametrize("angle", [0.0, 35.0])
def test_pairwise_binary_collision_matches_xgboost_and_the_closed_form(trained_models, angle):
    p, v, n, p0, strategy = pair_case(trained_models, angle)
    after = p.v.numpy().astype(np.float64)
    # exact reference: XGBoost's own predict + the numpy impulse (float32 features/velocities in the engine)
    r1, r2 = xgboost_pairwise(trained_models["contact"], v[:1], v[1:], n[None], D, D, RHO, RHO)
    g = np.linalg.norm(v[0] - v[1])
    assert np.abs(after - np.vstack([r1, r2])).max() <= 1e-5 * g
    # physics: the model's error on the impulse (test MAE of both targets, 5x for one point) scales by m*|g|/m =
    # |g|/2 in the velocities; against the data set's DEM on this impact (the soft frictionless spheres turn their
    # centre line during the contact: at 35 deg the DEM's impulse is 1.4 % below the hard-sphere closed form, and
    # has a tangential part), and against the closed form at head-on incidence (plus the DEM's restitution
    # calibration, 0.3 %)
    tol = g * 0.5 * 5.0 * (impulse_n_mae(trained_models["contact"]) + impulse_mae(trained_models["contact"], "impulse_t"))
    d1, d2 = dem_outcome(v[0], v[1], n)
    assert np.abs(after[0] - d1).max() <= tol and np.abs(after[1] - d2).max() <= tol
    if angle == 0.0:
        c1, c2 = closed_form(v[0], v[1], n, E_REST)
        assert np.abs(after[0] - c1).max() <= tol + 0.003 * g and np.abs(after[1] - c2).max() <= tol + 0.003 * g
    # momentum: equal and opposite impulses (float32 velocity round-off)
    assert np.abs(momentum(p) - p0).max() <= 1e-6 * np.abs(p.mass_numpy()[0] * v).sum()
    c = strategy.counts()
    assert (c["detected_pairs"], c["surrogate_calls"], c["separating_skipped"], c["collisions"]) == (1, 1, 0, 1)


def test_separating_overlapping_pair_is_not_collided(trained_models):
    from hel_warp.collisions.models import SurrogateCollision

    x = [[0.0, 0.0, 0.0], [0.8 * D, 0.0, 0.0]]
    v = np.array([[-1.0, 0.2, 0.0], [1.0, 0.0, 0.0]], np.float32)
    p = make_particles(x, v)
    strategy = SurrogateCollision(model_dir=trained_models["contact"], detection="overlap")
    strategy.collide(p)
    assert np.array_equal(p.v.numpy(), v)
    c = strategy.counts()
    assert (c["detected_pairs"], c["surrogate_calls"], c["separating_skipped"]) == (1, 0, 1)


def test_three_body_cluster_overlap_resolved_in_order_until_no_pair_approaches(trained_models):
    # A - B - C on a line, A and C approach B; A and C do not touch. Overlap detection = paths of zero length: at
    # t = 0 every overlapping approaching pair is an event, taken one at a time in key order (lowest pair (i, j)
    # first), each with the velocities the earlier ones left, until no overlapping pair approaches, a pair never
    # twice in a row for either parcel (here A-B, then B-C; B bounced back towards A, but A's last partner is B).
    # Reference: XGBoost's own predict applied in that order.
    from hel_warp.collisions.models import SurrogateCollision

    x = np.array([[0.0, 0.0, 0.0], [0.9 * D, 0.0, 0.0], [1.8 * D, 0.05 * D, 0.0]])
    v = np.array([[3.0, 0.0, 0.0], [0.0, 0.0, 0.0], [-2.0, 0.1, 0.0]])
    p = make_particles(x, v, stream=np.array([0, 1, 1]))
    strategy = SurrogateCollision(model_dir=trained_models["contact"], detection="overlap")
    p0 = momentum(p)
    strategy.collide(p)
    after = p.v.numpy().astype(np.float64)

    ref = v.astype(np.float32).astype(np.float64)
    order, last = [], [-1, -1, -1]
    while True:
        pending = [(i, j) for i, j in ((0, 1), (1, 2)) if np.dot(ref[j] - ref[i], x[j] - x[i]) < 0
                   and last[i] != j and last[j] != i]
        if not pending or len(order) > 10:
            break
        i, j = pending[0]
        n = (x[j] - x[i]) / np.linalg.norm(x[j] - x[i])
        a, b = xgboost_pairwise(trained_models["contact"], ref[i:i + 1], ref[j:j + 1], n[None], D, D, RHO, RHO)
        ref[i], ref[j] = a[0], b[0]
        order.append((i, j))
        last[i], last[j] = j, i
    assert order == [(0, 1), (1, 2)]
    assert np.abs(after - ref).max() <= 1e-5 * 5.0 * len(order)
    assert np.abs(momentum(p) - p0).max() <= 1e-6 * np.abs(p.mass_numpy()[0] * v).sum()
    c = strategy.counts()
    assert c["detected_pairs"] == 2 and c["collisions"] == c["surrogate_calls"] == len(order)
    assert (c["detected_pairs_0_1"], c["detected_pairs_1_1"], c["detected_pairs_0_0"]) == (1, 1, 0)
    assert c["collisions_0_1"] == order.count((0, 1)) and c["collisions_1_1"] == order.count((1, 2))


def test_weighted_parcels_conserve_parcel_momentum(trained_models):
    # w_i = 3, w_j = 1: one real binary collision per particle of parcel j, so parcel j gets the binary
    # velocity change and parcel i a third of its own binary change; sum w m v is conserved.
    from hel_warp.collisions.models import SurrogateCollision

    x = [[0.0, 0.0, 0.0], [0.9 * D, 0.0, 0.0]]
    v = np.array([[2.0, 0.0, 0.0], [-2.0, 0.5, 0.0]])
    p = make_particles(x, v, weight=np.array([3.0, 1.0]))
    strategy = SurrogateCollision(model_dir=trained_models["contact"], detection="overlap")
    p0 = momentum(p)
    strategy.collide(p)
    after = p.v.numpy().astype(np.float64)
    r1, r2 = xgboost_pairwise(trained_models["contact"], v[:1], v[1:], np.array([[1.0, 0, 0]]), D, D, RHO, RHO)
    assert np.abs(after[1] - r2[0]).max() <= 1e-5 * 4
    assert np.abs(after[0] - (v[0] + (r1[0] - v[0]) / 3.0)).max() <= 1e-5 * 4
    m = p.mass_numpy()[0]
    assert np.abs(momentum(p) - p0).max() <= 1e-6 * m * 4 * 4.0
    assert strategy.counts()["collisions"] == 1  # min(3, 1) real collisions


def random_cloud(n=3000, seed=1, side=4e-3):
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.0, side, size=(n, 3))
    v = rng.normal(0.0, 2.0, size=(n, 3))
    radius = 0.5 * D * rng.uniform(0.7, 1.3, n)
    density = RHO * rng.uniform(0.8, 1.25, n)
    weight = rng.integers(1, 4, n).astype(float)
    stream = rng.integers(0, 3, n)
    return make_particles(x, v, radius=radius, density=density, weight=weight, stream=stream)


def test_many_random_particles_momentum_exact_and_pairs_match_brute_force(trained_models):
    # Collision only (no gas, no walls): 3000 polydisperse weighted parcels, ~30 % solids by volume.
    from hel_warp.collisions.models import SurrogateCollision

    p = random_cloud()
    x = p.x.numpy().astype(np.float64)
    r = p.radius.numpy().astype(np.float64)
    strategy = SurrogateCollision(model_dir=trained_models["contact"], detection="overlap")
    p0 = momentum(p)
    m = p.mass_numpy() * p.weight.numpy()
    scale = float(np.sum(m * np.linalg.norm(p.v.numpy().astype(np.float64), axis=1)))
    # O(N^2) brute force of |x_i - x_j| < r_i + r_j (float32 positions as the kernel sees them), and of the
    # approaching ones among them, (v_j - v_i).(x_j - x_i) < 0, before any collision
    xf, vf = p.x.numpy(), p.v.numpy()
    d = xf[None, :, :] - xf[:, None, :]
    dist = np.linalg.norm(d, axis=2)
    cut = (p.radius.numpy()[:, None] + p.radius.numpy()[None, :])
    i, j = np.nonzero(np.triu(dist < cut, k=1))
    closing = np.einsum("kc,kc->k", vf[j] - vf[i], d[i, j]) < 0
    strategy.collide(p)
    c = strategy.counts()
    assert c["detected_pairs"] == i.size > 500 and c["rounds"] >= 2
    assert c["separating_skipped"] == int(np.count_nonzero(~closing))
    # every pair approaching at the start is resolved at least once (later ones may join after a collision)
    assert c["surrogate_calls"] >= int(np.count_nonzero(closing)) and c["round_cap_hit"] == 0
    # each update rounds one float32 velocity (relative 6e-8); a parcel is updated once per partner
    assert np.abs(momentum(p) - p0).max() <= 1e-6 * scale
    assert np.all(np.isfinite(p.v.numpy()))
    del x, r


def test_pairwise_is_deterministic(trained_models):
    from hel_warp.collisions.models import SurrogateCollision

    results = []
    for _ in range(2):
        p = random_cloud(n=2000, seed=3)
        strategy = SurrogateCollision(model_dir=trained_models["contact"], detection="overlap")
        strategy.collide(p)
        results.append((p.v.numpy().copy(), strategy.counts()))
    assert all(isinstance(k, str) and isinstance(v, int) for k, v in results[0][1].items())  # {name: int}
    assert np.array_equal(results[0][0], results[1][0])
    assert results[0][1] == results[1][1]


@pytest.mark.parametrize("mode", ["pairwise", "paper"])
def test_batched_prediction_changes_nothing(trained_models, mode):
    # The batched prediction (pairwise: per round; paper: all clustered particles) is a shortcut: it must
    # give bit for bit what inline walks give (same features, same float32 summation order), in clusters
    # of several partners too.
    from hel_warp.collisions.models import SurrogateCollision

    results = []
    for batched in (False, True):
        p = random_cloud(n=3000, seed=4)
        # swept named: the cloud's parcels weigh 1-3, for which the default is the cell detection
        strategy = SurrogateCollision(model_dir=trained_models["contact" if mode == "pairwise" else "paper"],
                                      mode=mode, batched=batched, detection="swept")
        v0 = p.v.numpy().copy()
        strategy.collide(p, 1e-4)
        results.append((p.v.numpy().copy(), strategy.counts()))
    assert results[0][1] == results[1][1]
    assert results[0][1]["surrogate_calls"] > 300
    if mode == "pairwise":
        assert results[0][1]["rounds"] >= 2
    assert not np.array_equal(results[0][0], v0)
    assert np.array_equal(results[0][0], results[1][0])
    assert strategy.batch_forest is not None  # the tiny model fits the perfect layout: the batch path ran


def test_paper_mode_uses_the_cluster_averaged_partner_velocity(trained_models):
    # B overlaps A and C: its partner velocity is the mean of A's and C's; A and C see B only.
    from hel_warp.collisions.models import SurrogateCollision

    x = np.array([[0.0, 0.0, 0.0], [0.9 * D, 0.0, 0.0], [1.8 * D, 0.0, 0.0]])
    v = np.array([[3.0, 0.0, 0.0], [0.0, 0.5, 0.0], [-2.0, 0.0, 0.0]])
    p = make_particles(x, v)
    strategy = SurrogateCollision(model_dir=trained_models["paper"], mode="paper")
    strategy.collide(p)
    partner = np.array([v[1], 0.5 * (v[0] + v[2]), v[1]])
    ref = xgboost_paper(trained_models["paper"], v, partner, D, D, RHO, RHO)
    assert np.abs(p.v.numpy() - ref).max() <= 1e-5 * 5
    c = strategy.counts()
    assert c["detected_pairs"] == 2 and c["surrogate_calls"] == 2


def test_mode_and_model_form_must_agree_and_hel_resolves_the_names(trained_models):
    from hel_warp.collisions.models import DemCollision, SurrogateCollision, SurrogatePaperCollision, make_collision
    from hel_warp.errors import ConfigError
    from hel_warp.hel import collision_model

    with pytest.raises(ConfigError, match="contact"):
        SurrogateCollision(model_dir=trained_models["paper"])
    with pytest.raises(ConfigError, match="paper"):
        make_collision("surrogate-paper", model_dir=trained_models["contact"])
    assert make_collision("surrogate", model_dir=trained_models["contact"]).name == "surrogate"
    assert isinstance(collision_model("surrogate", model_dir=trained_models["contact"]), SurrogateCollision)
    paper = collision_model("surrogate-paper", model_dir=trained_models["paper"])
    assert isinstance(paper, SurrogatePaperCollision) and paper.mode == "paper" and paper.name == "surrogate-paper"
    assert isinstance(collision_model("dem"), DemCollision)


# ------------------------------------------------------------------------------------------ dem


def dem_solver_stub(particles, dt, gravity=(0.0, 0.0, 0.0)):
    """What DemCollision.advance reads of HelSolver: pool.particles, fields, push_params, config.dt, fluid_push."""
    from hel_warp.parcels.coupling import CouplingFields, GridSpec, PushConfig

    from kernels.interp import parcel_arrays
    from kernels.push import push

    fields = CouplingFields.allocate(GridSpec(origin=(0, 0, 0), spacing=1.0, shape=(1, 1, 1)), particles.count,
                                     device=particles.device)
    params = PushConfig(gravity=gravity, drag="schiller-naumann").params(dt)
    p, f = particles, fields

    def fluid_push(*, particle_x_out, particle_v_out):  # HelSolver's explicit push (still gas: no exchange)
        push(params, parcel_arrays(p), f.parcel_u_f, f.parcel_grad_p, f.parcel_eps_s, f.parcel_a_coll,
             f.parcel_drag_impulse, f.parcel_drag_coeff, particle_x_out=particle_x_out,
             particle_v_out=particle_v_out)

    return SimpleNamespace(pool=SimpleNamespace(particles=particles), fields=fields, push_params=params,
                           config=SimpleNamespace(dt=dt), fluid_push=fluid_push)


def test_dem_head_on_restitution_and_momentum_with_drag():
    # Two spheres 1 um apart approach at 2 m/s each in still gas, frictionless; one fluid step of 1e-4 s.
    # Closed form: relative normal velocity reverses with e (drag over 1e-4 s changes it by < 0.3 %:
    # F_D ~ 13 1/s at Re ~ 80); momentum change = sum of the recorded drag impulses + gravity impulse.
    from hel_warp.collisions.models import DemCollision
    from hel_warp.material import Material

    dt = 1e-4
    gravity = (0.0, 0.0, -9.80665)
    x = [[0.0, 0.0, 0.0], [D + 1e-6, 0.0, 0.0]]
    v = np.array([[2.0, 0.0, 0.0], [-2.0, 0.0, 0.0]])
    p = make_particles(x, v)
    solver = dem_solver_stub(p, dt, gravity)
    strategy = DemCollision(material=Material(friction=0.0))
    p0 = momentum(p)
    strategy.accelerate(solver)
    strategy.advance(solver)
    after = p.v.numpy().astype(np.float64)
    g_after = (after[0] - after[1])[0]
    assert g_after == pytest.approx(-E_REST * 4.0, rel=0.01)
    m = p.mass_numpy()
    drag = solver.fields.parcel_drag_impulse.numpy().sum(axis=0)
    expected = drag + m.sum() * np.asarray(gravity) * (1 - 1.205 / RHO) * dt
    assert np.abs(momentum(p) - p0 - expected).max() <= 1e-6 * m[0] * 4.0
    assert strategy.substeps >= math.ceil(dt / Material().time_step(0.5 * D).chosen)
    # the particles really moved by the DEM: x advanced by ~ v dt minus the rebound
    assert np.all(np.isfinite(p.x.numpy()))


def test_dem_refuses_weighted_parcels():
    from hel_warp.collisions.models import DemCollision
    from hel_warp.errors import ConfigError

    p = make_particles([[0, 0, 0], [2 * D, 0, 0]], [[0, 0, 0], [0, 0, 0]], weight=2.0)
    with pytest.raises(ConfigError, match="weight 1"):
        DemCollision().advance(dem_solver_stub(p, 1e-4))


# ------------------------------------------------------------------------------------------ inside HelSolver


class UniformGas:
    """Stand-in of the gas solver: uniform fixed air velocity ``u``, no pressure gradient, step does nothing.

    The momentum handed to the gas is then read from the parcels' recorded drag impulses alone.
    """

    def __init__(self, grid, u):
        import warp as wp

        shape = grid.shape
        self.domain = SimpleNamespace(grid=grid, geometry=None)
        self.cell_velocity = wp.array(np.tile(np.asarray(u, np.float32), shape + (1,)), dtype=wp.vec3)
        self.cell_grad_p = wp.zeros(shape, dtype=wp.vec3)
        self.cell_pressure = wp.zeros(shape, dtype=float)
        self.cell_eps_s = wp.zeros(shape, dtype=float)
        self.cell_momentum_source = wp.zeros(shape, dtype=wp.vec3)
        self.cell_drag_coeff = wp.zeros(shape, dtype=float)

    def step(self, gas, dt):
        pass


@pytest.mark.parametrize("name", ["surrogate", "dem"])
def test_hel_step_particle_momentum_change_is_the_drag_impulse_handed_to_the_gas(trained_models, name):
    # 216 parcels on a 1.05 d lattice with random velocities (many collisions per step), air at 0.5 m/s,
    # no gravity: over HelSolver steps (deposit, interpolate, collide, push or the dem advance) the parcels'
    # momentum changes by exactly the drag impulses recorded for the gas (contacts are internal forces).
    from hel_warp.parcels.coupling import PushConfig
    from hel_warp.gas.grid import Grid
    from hel_warp.hel import HelConfig, HelSolver, collision_model
    from hel_warp.material import Material
    from hel_warp.parcels.pool import ParcelPool, VolumeInjection

    grid = Grid(spacing=1e-3, shape=(4, 4, 4))
    gas = UniformGas(grid, (0.5, 0.0, 0.0))
    per_axis = 6
    c = 2e-3 + (np.arange(per_axis) - (per_axis - 1) / 2) * 1.05 * D
    x = np.stack(np.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)
    rng = np.random.default_rng(5)
    pool = ParcelPool.empty(x.shape[0])
    pool.inject(VolumeInjection(box_lo=(1e-3,) * 3, box_hi=(3e-3,) * 3, diameter_mean=D, density=RHO,
                                count=x.shape[0]))
    pool.particles.x.assign(x.astype(np.float32))
    pool.particles.v.assign(rng.normal(0.0, 1.0, x.shape).astype(np.float32))
    kwargs = {"model_dir": trained_models["contact"]} if name == "surrogate" else {"material": Material()}
    strategy = collision_model(name, **kwargs)
    hel = HelSolver(pool=pool, gas_solver=gas, gas=gas,
                    config=HelConfig(dt=1e-4, push=PushConfig(gravity=(0.0, 0.0, 0.0)), walls=False),
                    collision=strategy)
    p = pool.particles
    p0 = momentum(p)
    handed = np.zeros(3)
    calls = 0
    for _ in range(3):
        hel.step()
        handed += hel.fields.parcel_drag_impulse.numpy().sum(axis=0)
        calls += strategy.counts()["surrogate_calls"] if name == "surrogate" else strategy.counts()["dem_substeps"]
    scale = float(np.sum(p.mass_numpy() * np.linalg.norm(p.v.numpy().astype(np.float64), axis=1)))
    assert calls > 0
    # float32 velocities: each update of a parcel's velocity rounds by at most 6e-8 of it; surrogate: a few
    # updates per step (collision rounds, push); dem: two half kicks per sub-step
    updates = 2 * calls if name == "dem" else 3 * 10
    tol = updates * 6e-8 * scale
    assert np.abs(handed).max() > 10.0 * tol  # a lost drag impulse would show
    assert np.abs(momentum(p) - p0 - handed).max() <= tol


def test_a_pair_overlapping_over_several_steps_is_collided_once_pairwise_but_repeatedly_in_paper_mode(
        trained_models):
    # Head-on at 0.4 m/s relative, detected 30 % overlapped, small steps (2e-5 s: 8 um of relative motion
    # per step): the pair stays overlapped for several steps after the collision. Pairwise: one model call
    # (the pair separates afterwards, sec. 8's repeated-detection fix); paper mode: a call every step while
    # overlapped (the flaw the paper reports).
    from hel_warp.collisions.models import SurrogateCollision

    dt = 2e-5
    calls = {}
    for mode, model in (("pairwise", "contact"), ("paper", "paper")):
        p = make_particles([[0.0, 0.0, 0.0], [0.7 * D, 0.0, 0.0]], [[0.2, 0.0, 0.0], [-0.2, 0.0, 0.0]])
        strategy = SurrogateCollision(model_dir=trained_models[model], mode=mode, detection="overlap")
        calls[mode], overlapped = [], []
        for _ in range(6):
            x = p.x.numpy()
            overlapped.append(int(np.linalg.norm(x[1] - x[0]) < D))
            strategy.collide(p)
            calls[mode].append(strategy.counts()["surrogate_calls"])
            p.x.assign(x + dt * p.v.numpy())
        if mode == "pairwise":
            assert overlapped == [1] * 6  # detected at every step ...
            assert calls[mode] == [1, 0, 0, 0, 0, 0]  # ... collided once
        else:
            assert calls[mode] == overlapped and sum(overlapped) >= 2  # a call at every overlapped step


def test_dem_parcel_bounces_off_the_geometry_wall_with_its_radius_and_the_wall_restitution():
    # One parcel thrown at 2 m/s normally at the x = 0 wall of a box geometry in still gas, no gravity.
    # Sphere-wall Hertz contact in the DEM sub-steps: the rebound speed is e_w = Material.wall_restitution_normal
    # times the impact speed (drag over the ~60 us changes it by < 0.1 %), and the centre never comes closer to
    # the wall than r - delta_max, the undamped Hertz overlap (15 m v^2 / (16 E* sqrt(r)))^(2/5) (R* = r, m* = m,
    # wall of the particle material: E* = E / (2 (1 - nu^2))). The point reflection is not needed and skipped.
    from hel_warp.collisions.models import DemCollision
    from hel_warp.gas.grid import Box, Geometry
    from hel_warp.hel import HelSolver
    from hel_warp.material import Material

    r = 0.5 * D
    v0 = 2.0
    mat = Material()
    p = make_particles([[r + 20e-6, 2e-3, 2e-3]], [[-v0, 0.0, 0.0]])
    dt = 1e-6
    solver = dem_solver_stub(p, dt)
    solver.config.walls = True
    solver.shapes = Geometry(shapes=(Box(lo=(0.0, 0.0, 0.0), hi=(4e-3, 4e-3, 4e-3)),)).shapes_struct("cpu")
    strategy = DemCollision(material=mat)
    assert strategy.handles_walls
    gaps = []
    for _ in range(60):
        strategy.accelerate(solver)
        strategy.advance(solver)
        gaps.append(float(p.x.numpy()[0, 0]))
    v = p.v.numpy()[0].astype(np.float64)
    assert v[0] > 0.0 and v[0] == pytest.approx(mat.wall_restitution_normal * v0, rel=0.02)
    assert abs(v[1]) < 1e-6 and abs(v[2]) < 1e-6
    m = p.mass_numpy()[0]
    e_star = mat.youngs_modulus / (2.0 * (1.0 - mat.poisson_ratio**2))
    delta_max = (15.0 * m * v0**2 / (16.0 * e_star * math.sqrt(r))) ** 0.4
    assert min(gaps) >= r - 1.05 * delta_max  # met the wall with its radius, Hertz overlap only
    assert min(gaps) <= r - 0.3 * delta_max  # ... and the contact did happen at the sampled steps
    assert gaps[-1] > r  # left the wall

    # HelSolver's point reflection leaves a strategy with handles_walls alone (a centre past the wall stays)
    p.x.assign(np.array([[-1e-5, 2e-3, 2e-3]], np.float32))
    hel = SimpleNamespace(config=SimpleNamespace(walls=True), collision=strategy, pool=solver.pool)
    HelSolver.reflect_at_walls(hel)
    assert p.x.numpy()[0, 0] == pytest.approx(-1e-5)
