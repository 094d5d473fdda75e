"""Swept (continuous) detection of the ``surrogate`` strategy (hel_warp/collisions/models.py, kernels/collide.py).

References (docs/developer/conventions.md rule 9):
- the first touch of two straight paths against a brute-force time march of |s(t)| (no root formula involved);
- time-ordered resolution against the hard-sphere closed form: with a forest that predicts the constant normal
  impulse (1 + e) of a frictionless central impact (the contact form's exact answer at cos = 1; docs/physics/references.md
  "Binary collision outcome"), a head-on chain of three equal spheres has a closed-form sequence of collision
  times and velocities;
- the strict event-driven order (``ordering="sequential"``: one event per round, the globally earliest) for the
  parallel rounds on a dense periodic gas;
- periodic images against the same pair placed inside the box;
- the rounds' searches with a cut on the reach (the grid out to R_cut, the parcels above it listed) against the
  search out to the global maximum reach: bit for bit;
- momentum conservation and the step's end positions of the swept paths.
"""

from __future__ import annotations

import base64
import json
import math

import numpy as np
import pytest

from tests.test_collision_models import D, make_particles, momentum, trained_models  # noqa: F401  (fixture)

E = 0.9


def _array(values, dtype):
    arr = np.asarray(values, dtype=dtype)
    return {"dtype": np.dtype(dtype).str, "shape": list(arr.shape), "base64": base64.b64encode(arr.tobytes()).decode()}


def write_constant_contact_forest(root) -> str:
    """A contact-form forest of one leaf per target in directory ``root``: impulse_n = 1 + e, impulse_t = 0 (exact
    for central impacts, cos_angle = 1; an outcome without training a model); its domain covers every contact
    feature. Returns the directory."""
    doc = {"format": "hel_warp.forest", "version": 2, "form": "contact",
           "features": ["g_n", "g_t", "cos_angle", "d1", "size_ratio", "density_ratio"],
           "targets": ["impulse_n", "impulse_t"], "base_score": [1.0 + E, 0.0], "tree_start": [0, 1, 2],
           "max_depth": 0,
           "arrays": {"tree_root": _array([0, 1], "<i4"), "node_info": _array([-1, -1], "<i4"),
                      "node_value": _array([0.0, 0.0], "<f4"), "node_left": _array([-1, -1], "<i4")},
           "domain": {"features": ["g_n", "g_t", "cos_angle", "d1", "size_ratio", "density_ratio"],
                      "lo": [0.0, 0.0, 0.0, 1e-6, 0.1, 0.1], "hi": [100.0, 100.0, 1.0, 1e-2, 10.0, 10.0],
                      "friction": 0.0, "friction_bound": 0.0}}
    (root / "forest.json").write_text(json.dumps(doc))
    return str(root)


@pytest.fixture(scope="module")
def hard_sphere_model(tmp_path_factory):
    """The constant hard-sphere forest (``write_constant_contact_forest``)."""
    return write_constant_contact_forest(tmp_path_factory.mktemp("hard_sphere_model"))


def brute_force_touch(x1, x2, v1, v2, radius_sum, dt, steps=200000):
    """First t in [0, dt] on a fine grid with |s(t)| <= R while approaching (s.g < 0), else None."""
    t = np.linspace(0.0, dt, steps + 1)
    s = (x2 - x1)[None, :] + (v2 - v1)[None, :] * t[:, None]
    inside = np.einsum("ij,ij->i", s, s) <= radius_sum**2
    if not inside.any():
        return None, dt / steps
    k = int(np.argmax(inside))
    if k == 0 and np.dot(x2 - x1, v2 - v1) >= 0.0:
        return None, dt / steps
    return t[k], dt / steps


def test_first_touch_matches_a_brute_force_time_march(hard_sphere_model):
    from hel_warp.collisions.models import SurrogateCollision

    rng = np.random.default_rng(7)
    dt = 1e-3
    strategy = SurrogateCollision(model_dir=hard_sphere_model)
    hits = misses = 0
    for _ in range(60):
        x1 = np.zeros(3)
        x2 = rng.uniform(-1.0, 1.0, 3)
        x2 *= rng.uniform(1.05 * D, 8 * D) / np.linalg.norm(x2)
        v1, v2 = rng.normal(0.0, 2.0, 3), rng.normal(0.0, 2.0, 3)
        # aim a share of the pairs at each other so that both outcomes occur
        if rng.random() < 0.6:
            v2 = v1 - (x2 - x1) / dt * rng.uniform(0.2, 1.5) + rng.normal(0, 0.2, 3)
        p = make_particles([x1, x2], [v1, v2])
        xf, vf = p.x.numpy().astype(np.float64), p.v.numpy().astype(np.float64)
        expected, resolution = brute_force_touch(xf[0], xf[1], vf[0], vf[1], D, dt)
        strategy.collide(p, dt)
        c = strategy.counts()
        if expected is None:
            assert c["collisions"] == 0
            misses += 1
        else:
            assert c["collisions"] == 1
            t_last = strategy.swept.t_last.numpy()
            # the march brackets the root within one of its steps; float32 paths add ~1e-7 relative
            assert t_last[0] == t_last[1] and abs(t_last[0] - expected) <= resolution + 1e-6 * dt
            hits += 1
    assert hits >= 15 and misses >= 15


def test_head_on_chain_matches_the_hard_sphere_sequence(hard_sphere_model):
    # A -> B   C on the x axis, equal spheres, gaps g1 (A-B) and g2 (B-C), A at speed u, B and C at rest, e = 0.9.
    # Closed form: A-B at t1 = g1/u: vA = u(1-e)/2, vB = u(1+e)/2; B-C at t2 = t1 + g2/vB: vB' = vB(1-e)/2,
    # vC = vB(1+e)/2; A catches B at t3 (both then known straight lines); one step of dt covers all three.
    from hel_warp.collisions.models import SurrogateCollision

    u, g1, g2, dt = 3.0, 1.0e-3, 1.0e-5, 3.0e-3
    x = np.array([[0.0, 0.0, 0.0], [D + g1, 0.0, 0.0], [2 * D + g1 + g2, 0.0, 0.0]])
    v = np.array([[u, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    p = make_particles(x, v)
    p0 = momentum(p)
    strategy = SurrogateCollision(model_dir=hard_sphere_model)
    strategy.collide(p, dt)
    # closed form, in float64
    t1 = g1 / u
    va, vb = u * (1 - E) / 2, u * (1 + E) / 2
    xa1, xb1 = x[0, 0] + u * t1, x[1, 0]
    t2 = t1 + g2 / vb
    vb2, vc = vb * (1 - E) / 2, vb * (1 + E) / 2
    xa2, xb2 = xa1 + va * (t2 - t1), xb1 + vb * (t2 - t1)
    t3 = t2 + (xb2 - xa2 - D) / (va - vb2)  # A (faster) closes on B
    assert t3 < dt
    va3 = va - (1 + E) / 2 * (va - vb2)
    vb3 = vb2 + (1 + E) / 2 * (va - vb2)
    after = p.v.numpy()[:, 0].astype(np.float64)
    assert after == pytest.approx([va3, vb3, vc], rel=1e-5, abs=1e-6)
    c = strategy.counts()
    assert c["collisions"] == 3 and c["guard_separation"] == c["guard_energy"] == 0
    # end positions: the caller moves with the new velocities, then adds the in-step corrections
    p.x.assign(p.x.numpy() + p.v.numpy() * dt)
    strategy.correct_positions(p)
    xa3, xb3 = xa2 + va * (t3 - t2), xb2 + vb2 * (t3 - t2)
    end = np.array([xa3 + va3 * (dt - t3), xb3 + vb3 * (dt - t3), x[2, 0] + vc * (dt - t2)])
    assert p.x.numpy()[:, 0] == pytest.approx(end, abs=2e-9)
    assert np.all(np.diff(p.x.numpy()[:, 0]) >= D * (1 - 1e-5))  # nothing left overlapping
    assert np.abs(momentum(p) - p0).max() <= 1e-6 * p.mass_numpy()[0] * u



def test_the_event_log_holds_the_chain_in_time_order(hard_sphere_model):
    # the chain above with collision_events on: three entries at t1 < t2 < t3 with the normal approach speeds of the
    # closed form (u, then vB, then vA - vB'), ids ordered, same stream; the log changes nothing else
    from hel_warp.collisions.models import SurrogateCollision

    u, g1, g2, dt = 3.0, 1.0e-3, 1.0e-5, 3.0e-3
    x = np.array([[0.0, 0.0, 0.0], [D + g1, 0.0, 0.0], [2 * D + g1 + g2, 0.0, 0.0]])
    v = np.array([[u, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    plain, logged = make_particles(x, v), make_particles(x, v)
    SurrogateCollision(model_dir=hard_sphere_model).collide(plain, dt)
    strategy = SurrogateCollision(model_dir=hard_sphere_model, collision_events=True)
    strategy.collide(logged, dt)
    np.testing.assert_array_equal(logged.v.numpy(), plain.v.numpy())
    ev = strategy.collision_events()
    t1 = g1 / u
    va, vb = u * (1 - E) / 2, u * (1 + E) / 2
    t2 = t1 + g2 / vb
    vb2 = vb * (1 - E) / 2
    xa2, xb2 = u * t1 + va * (t2 - t1), D + g1 + vb * (t2 - t1)
    t3 = t2 + (xb2 - xa2 - D) / (va - vb2)
    assert ev["particle_a"].tolist() == [0, 1, 0] and ev["particle_b"].tolist() == [1, 2, 1]
    assert ev["time"] == pytest.approx([t1, t2, t3], rel=1e-4)
    assert ev["speed"] == pytest.approx([u, vb, va - vb2], rel=1e-5)
    assert not ev["truncated"] and ev["stream_a"].tolist() == ev["stream_b"].tolist() == [0, 0, 0]
    assert len(SurrogateCollision(model_dir=hard_sphere_model).collision_events()["speed"]) == 0


def periodic_gas(n, eps, seed=0, theta=1.0):
    """n spheres of D on a jittered lattice in a cube of solids fraction eps, Maxwellian velocities, zero momentum."""
    side = (n * math.pi * D**3 / 6.0 / eps) ** (1.0 / 3.0)
    rng = np.random.default_rng(seed)
    k = int(math.ceil(n ** (1.0 / 3.0)))
    g = (np.arange(k) + 0.5) * side / k
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)[:n]
    x = np.mod(x + rng.uniform(-0.5, 0.5, x.shape) * (side / k - 1.01 * D), side)
    v = rng.normal(0.0, math.sqrt(theta), (n, 3))
    return x, v - v.mean(axis=0), side


def test_parallel_rounds_equal_the_strict_event_order(trained_models):
    # 1000 spheres at eps = 0.05 for a step in which each collides ~0.5 times (chains of collisions in the step):
    # the rounds of causally safe events give exactly what one event at a time, globally earliest first, gives.
    from hel_warp.collisions.models import SurrogateCollision

    x, v, side = periodic_gas(1000, 0.05)
    results = []
    for ordering in ("parallel", "sequential"):
        p = make_particles(x, v)
        strategy = SurrogateCollision(model_dir=trained_models["contact"], periodic_box=(side,) * 3,
                                      ordering=ordering, max_rounds=100000)
        p0 = momentum(p)
        strategy.collide(p, 2e-4)
        results.append((p.v.numpy().copy(), strategy.counts()))
        assert np.abs(momentum(p) - p0).max() <= 1e-6 * float(np.sum(p.mass_numpy()[:, None] * np.abs(v)))
    (v_par, c_par), (v_seq, c_seq) = results
    assert c_seq["collisions"] == c_seq["rounds"] > 100  # one event per round
    assert c_par["collisions"] == c_seq["collisions"] and c_par["rounds"] < c_seq["rounds"] / 4
    assert np.array_equal(v_par, v_seq)


def test_collisions_across_periodic_faces_equal_those_inside(hard_sphere_model):
    # The same approaching pair once in the middle of a periodic box, once split across the x and y faces.
    from hel_warp.collisions.models import SurrogateCollision

    side, dt = 20 * D, 1e-3
    v = np.array([[1.5, 0.4, 0.0], [-1.5, 0.0, 0.1]])
    rel = np.array([1.6 * D, 0.3 * D, 0.0])
    outs = []
    for centre in (np.array([10 * D, 10 * D, 10 * D]), np.array([0.2 * D, 0.1 * D, 10 * D])):
        x = np.mod(np.stack([centre - rel / 2, centre + rel / 2]), side)
        p = make_particles(x, v)
        strategy = SurrogateCollision(model_dir=hard_sphere_model, periodic_box=(side,) * 3)
        strategy.collide(p, dt)
        outs.append((p.v.numpy().copy(), strategy.counts()["collisions"], strategy.swept.t_last.numpy().copy()))
    assert outs[0][1] == outs[1][1] == 1
    assert np.allclose(outs[0][0], outs[1][0], atol=1e-6) and np.allclose(outs[0][2], outs[1][2], rtol=1e-5)


def test_swept_frequency_does_not_depend_on_dt_and_overlap_misses_most(trained_models):
    # A dilute periodic gas (eps = 0.01): collisions found in one step of 1e-3 s equal ten steps of 1e-4 s within
    # the statistics, and the Enskog rate N/2 * 24 eps g0 sqrt(Theta) / (sqrt(pi) d) (Carnahan-Starling g0)
    # within 4 sigma of a Poisson count; overlap detection at step ends finds only a fraction at 1e-3 s.
    from hel_warp.collisions.models import SurrogateCollision

    n, eps, dt = 2000, 0.01, 1e-3
    x, v, side = periodic_gas(n, eps, seed=3)
    counts = {}
    for detection, step, steps in (("swept", dt, 1), ("swept", dt / 10, 10), ("overlap", dt, 1)):
        p = make_particles(x, v)
        strategy = SurrogateCollision(model_dir=trained_models["contact"], periodic_box=(side,) * 3,
                                      detection=detection)
        total = 0
        for _ in range(steps):
            strategy.collide(p, step)
            total += strategy.counts()["collisions"]
            p.x.assign(p.x.numpy() + p.v.numpy() * step)
            strategy.correct_positions(p)
            p.x.assign(np.mod(p.x.numpy(), side))
        counts[(detection, step)] = total
    theta = float(np.mean(np.sum(v**2, axis=1)) / 3.0)
    g0 = (1 - eps / 2) / (1 - eps) ** 3
    expected = 0.5 * n * 24 * eps * g0 * math.sqrt(theta) / (math.sqrt(math.pi) * D) * dt
    swept = counts[("swept", dt)]
    assert abs(swept - expected) <= 4 * math.sqrt(expected) + 0.03 * expected
    assert abs(counts[("swept", dt / 10)] - swept) <= 4 * math.sqrt(expected)
    assert counts[("overlap", dt)] < 0.3 * expected


def test_a_reach_grown_past_the_cut_is_still_searched(hard_sphere_model, monkeypatch):
    # B rests beside the path of A (fast): its reach is below the cut in round 0. A hits B at t ~ 0: B's reach grows
    # to ~|v_B| dt, far past the cut. Y pushes i (at rest 3r beside B's path, gap r) across B's path after that; B's
    # next event is with i, both of reach above the cut: the grid search skips them, only the list of large parcels
    # finds the pair. The same step searched out to the global maximum reach (the cut at infinity, nothing listed)
    # and in the strict event order: the same three collisions (A-B, Y-i, i-B), bit for bit. 40 parcels at rest far
    # away keep the mean reach, and so the cut, small.
    import hel_warp.collisions.models as cm

    r, dt, u, w = 0.5 * D, 1e-3, 4.0, 1.0
    cross = np.array([3.0e-3, 0.0, 0.0])
    x = np.array([[-2 * r - 0.1e-3, 0.0, 0.0], [0.0, 0.0, 0.0], [3.7e-3, 0.0, 0.0], cross + [0.0, 3 * r, 0.0],
                  cross + [0.0, 5 * r + 0.45e-3, 0.0]])  # A, B, X (at rest on B's path), i, Y
    v = np.array([[u, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, -w, 0.0]])
    far = 0.1 + np.stack(np.meshgrid(*(np.arange(4) * 3 * D,) * 3, indexing="ij"), -1).reshape(-1, 3)[:40]
    x, v = np.vstack([x, far]), np.vstack([v, np.zeros_like(far)])
    outcomes = []
    for factor, ordering in ((cm.REACH_CUT_FACTOR, "parallel"), (np.inf, "parallel"),
                             (cm.REACH_CUT_FACTOR, "sequential")):
        monkeypatch.setattr(cm, "REACH_CUT_FACTOR", factor)
        p = make_particles(x, v)
        strategy = cm.SurrogateCollision(model_dir=hard_sphere_model, ordering=ordering)
        strategy.collide(p, dt)
        a = strategy.swept
        outcomes.append((p.v.numpy().copy(), a.t_last.numpy().copy(), strategy.counts()))
        if np.isfinite(factor):
            u_f = np.linalg.norm(v.mean(axis=0))
            assert u_f * dt / 2 < a.reach_cut  # B's reach in round 0 (at rest in the moving frame: |u_f| dt/2)
            assert a.reach.numpy()[[1, 3]].min() > a.reach_cut  # B and i: large when they met
            assert a.last_partner.numpy()[[1, 3]].tolist() == [3, 1]
    (v_cut, t_cut, c_cut), (v_max, t_max, c_max), (v_seq, t_seq, c_seq) = outcomes
    assert c_cut["collisions"] == 3 and c_cut == c_max
    assert np.array_equal(v_cut, v_max) and np.array_equal(t_cut, t_max)
    assert np.array_equal(v_cut, v_seq) and np.array_equal(t_cut, t_seq) and c_seq["collisions"] == 3


@pytest.mark.parametrize("windows", [1, 3])
def test_searches_with_a_reach_cut_equal_the_search_to_the_maximum_reach(trained_models, monkeypatch, windows):
    # A dense periodic gas (eps = 0.05, chains of collisions in the step) with the cut at the mean reach (a large
    # share of the parcels listed, more after each round's collisions) against the cut at infinity (every search
    # out to the global maximum reach, the list empty): the same events in the same rounds, bit for bit, in one
    # window and in three.
    import hel_warp.collisions.models as cm

    x, v, side = periodic_gas(1000, 0.05)
    outcomes = []
    for factor in (1.0, np.inf):
        monkeypatch.setattr(cm, "REACH_CUT_FACTOR", factor)
        p = make_particles(x, v)
        strategy = cm.SurrogateCollision(model_dir=trained_models["contact"], periodic_box=(side,) * 3,
                                         windows=windows)
        strategy.collide(p, 2e-4)
        a = strategy.swept
        listed = int(a.large_count.numpy()[0])
        outcomes.append((p.v.numpy().copy(), a.t_last.numpy().copy(), a.shift.numpy().copy(), strategy.counts()))
        if np.isfinite(factor):
            # the last window's list: its reaches are |v - u_f| times half the window at its start
            started_large = int(np.count_nonzero(np.linalg.norm(v - v.mean(axis=0), axis=1) * 1e-4 / windows
                                                 > a.reach_cut))
            assert listed > 100 and (windows > 1 or listed > started_large > 100)  # more after collisions
        else:
            assert listed == 0
    (v_cut, t_cut, s_cut, c_cut), (v_max, t_max, s_max, c_max) = outcomes
    assert c_cut == c_max and c_cut["collisions"] > 100 and c_cut["rounds"] > 3
    assert np.array_equal(v_cut, v_max) and np.array_equal(t_cut, t_max) and np.array_equal(s_cut, s_max)


def test_windows_change_the_searches_not_the_events(trained_models):
    # A dense periodic gas (eps = 0.05) over a step in which each sphere meets ~1 partner and moves ~4 radii
    # (reach ~2 radii): resolved in 1, 2 and 7 windows (``windows``) and in the automatic count. The strict event
    # order (one event per round, the globally earliest) is the reference: the windows give it bit for bit, as
    # the window only bounds the searches (the paths, event times and outcomes are those of the whole step); the
    # parallel rounds in windows give it too, and so does the serial queue (``ordering="serial"``, the CPU's
    # default), in one window and in seven.
    from hel_warp.collisions.models import SurrogateCollision

    x, v, side = periodic_gas(2000, 0.05, seed=4)
    results = {}
    for ordering, windows in (("sequential", 1), ("sequential", 2), ("sequential", 7), ("parallel", 7),
                              ("parallel", "auto"), ("serial", 1), ("serial", 7), ("auto", "auto")):
        p = make_particles(x, v)
        strategy = SurrogateCollision(model_dir=trained_models["contact"], periodic_box=(side,) * 3,
                                      ordering=ordering, max_rounds=100000, windows=windows)
        if windows == "auto":
            strategy.set_state({"swept_rounds": np.array(10_000, np.int64)})  # as after a step of many rounds
        p0 = momentum(p)
        strategy.collide(p, 4e-4)
        c = strategy.counts()
        assert c["windows"] == (windows if windows != "auto" else c["windows"]) and c["windows"] >= 1
        results[(ordering, windows)] = (p.v.numpy().copy(), strategy.swept.t_last.numpy().copy(),
                                        strategy.swept.shift.numpy().copy(), c)
        assert np.abs(momentum(p) - p0).max() <= 1e-6 * float(np.sum(p.mass_numpy()[:, None] * np.abs(v)))
    v_ref, t_ref, s_ref, c_ref = results[("sequential", 1)]
    assert c_ref["collisions"] > 500 and c_ref["guard_late_overlap"] == 0
    assert results[("parallel", "auto")][3]["windows"] > 2
    for key, (v_k, t_k, s_k, c_k) in results.items():
        assert c_k["collisions"] == c_ref["collisions"], key
        assert np.array_equal(v_k, v_ref) and np.array_equal(t_k, t_ref) and np.array_equal(s_k, s_ref), key
