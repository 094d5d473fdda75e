"""``cell`` detection of the surrogate (hel_warp/collisions/cells.py, kernels/cell_collide.py): Bird's NTC per cell.

References (docs/developer/conventions.md rule 9; docs/physics/references.md "Stochastic collisions of parcels", "Impact parameter", "Enskog
collision frequency"):

- the NTC candidate count ``1/2 N (N - 1) w_max chi_max (sigma g)_max dt / V`` per cell, and the expected accepted
  count, independent of the majorant: the sum over the cell's pairs of ``sigma_ij g_ij max(w_i, w_j) chi_ij dt / V``
  (chi_ij = g0 of the cell's solids fraction without the pair), computed here by brute force over the pairs;
- the impact geometry of kinetic theory: b^2 uniform on [0, (r_i + r_j)^2], the azimuth about g uniform, and the
  collisions weighted by |g| (Maxwellian gas: E_coll[|g|] = <g^2> / <g> = (3/2) sqrt(pi Theta));
- the Enskog frequency per real particle, omega = 24 eps g0 sqrt(Theta) / (sqrt(pi) d), at weights 1, 8 and 64 at
  the same real solids fraction (weight invariance);
- momentum sum w m v conserved to float32 round-off; no energy gain; determinism; a restart from ``state()``.

Statistical tolerances: the counts are sums of many rare independent events (Poisson): 4 standard errors.
The selection tests run with ``apply=False`` (counts and the event log only; velocities unchanged) on fresh
uniformly random positions every repetition, so they average over the cell occupancies as kinetic theory does.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.test_run_io import Interrupt, stop_at
from tests.test_swept import write_constant_contact_forest

D = 315e-6  # m
RHO = 1000.0  # kg/m^3
E = 0.9


@pytest.fixture(scope="module")
def constant_model(tmp_path_factory):
    """The constant contact-form forest of tests/test_swept.py (impulse_n = 1 + e, impulse_t = 0, every feature in its
    domain): an outcome for the conservation and determinism tests without training a model."""
    return write_constant_contact_forest(tmp_path_factory.mktemp("constant_model"))


def g0_cs(eps):
    """Carnahan-Starling g0 = (1 - eps/2) / (1 - eps)^3."""
    return (1.0 - 0.5 * eps) / (1.0 - eps) ** 3


def box_side(real_particles, eps):
    return (real_particles * math.pi * D**3 / (6.0 * eps)) ** (1.0 / 3.0)


def make_gas(n, side, weight, rng, device, theta=1.0):
    """n parcels uniformly in the periodic box, Maxwellian velocities at Theta (zero mean), weights ``weight``."""
    from hel_warp.parcels.particles import Particles

    x = rng.uniform(0.0, side, size=(n, 3))
    v = rng.normal(0.0, math.sqrt(theta), size=(n, 3))
    v -= v.mean(axis=0)
    return Particles.from_numpy(x, 0.5 * D, v=v, density=RHO, weight=weight, check_overlap=False, device=device)


def strategy(model, side, *, seed=0, log=0, **cell):
    from hel_warp.collisions.cells import CellConfig
    from hel_warp.collisions.models import SurrogateCollision

    return SurrogateCollision(model_dir=model, detection="cell", periodic_box=(side,) * 3, seed=seed,
                              cell=CellConfig(log_capacity=log, **cell))


def select(s, particles, dt):
    """One selection-only step (apply=False): counts and log, velocities unchanged."""
    s._setup(particles)
    s.cells.collide(particles, dt, s.forest, s.swept.domain, periodic_box=s.periodic_box, apply=False)
    return s.cells.counts()


def hard_sphere_compressibility(eps):
    """S(0) = (1 - eps)^4 / (1 + 4 eps + 4 eps^2 - 4 eps^3 + eps^4) (Carnahan-Starling: k T dn/dp)."""
    return (1.0 - eps) ** 4 / (1.0 + 4.0 * eps + 4.0 * eps**2 - 4.0 * eps**3 + eps**4)


def brute_force_expectation(particles, lattice, dt, approaching=False, redraw=0, transfer=False, by_weights=None):
    """Per the NTC formula and by brute force over every same-cell pair: (expected candidates, expected accepted,
    largest pair sigma g w_max chi over the largest majorant bound ratio) for one step. ``approaching``: a pair
    counts at twice its rate if its centres approach, (x_j - x_i) . (v_i - v_j) > 0 (nearest periodic image of the
    lattice's box), else not at all, against twice the majorant. ``redraw`` > 0 (with ``approaching``): NTC's
    candidates and test, an accepted pair that does not approach handing its collision to another pair (or keeping
    it): NTC's count, plain. ``transfer`` (the collisional transfer's count): the pairs N (N - 1) of a cell read
    as N (N - 1) + (1 - S) k N, S the hard-sphere compressibility at the cell's solids fraction, k = 1 - (3/8) d
    sum 1 / L_a the share of the excluded-volume hole inside a cell of edges L_a, the accepted sum scaled alike.
    ``by_weights``: a dict that collects the expected accepted count per pair of weights (w_min, w_max)."""
    origin, edges, shape = lattice
    x = particles.x.numpy().astype(np.float64)
    v = particles.v.numpy().astype(np.float64)
    r = particles.radius.numpy().astype(np.float64)
    w = particles.weight.numpy().astype(np.float64)
    vol_cell = float(np.prod(edges))
    ijk = np.clip(np.floor((x - origin) / edges).astype(int), 0, np.asarray(shape) - 1)
    cell = (ijk[:, 0] * shape[1] + ijk[:, 1]) * shape[2] + ijk[:, 2]
    order = np.argsort(cell, kind="stable")
    bounds = np.flatnonzero(np.diff(cell[order])) + 1
    candidates = accepted = 0.0
    worst = 0.0
    for members in np.split(order, bounds):
        n = len(members)
        if n < 2:
            continue
        solids = float((w[members] * 4.0 / 3.0 * math.pi * r[members] ** 3).sum())
        i, j = np.triu_indices(n, 1)
        a, b = members[i], members[j]
        g = np.linalg.norm(v[a] - v[b], axis=1)
        sigma = math.pi * (r[a] + r[b]) ** 2
        chi = g0_cs((solids - w[a] * 4 / 3 * math.pi * r[a] ** 3 - w[b] * 4 / 3 * math.pi * r[b] ** 3) / vol_cell)
        rate = sigma * g * np.maximum(w[a], w[b]) * chi
        factor = 1.0
        approach = np.ones(len(a), bool)
        if approaching:
            box = np.asarray(edges) * np.asarray(shape)
            dx = x[b] - x[a]
            dx -= box * np.round(dx / box)
            approach = np.einsum("ij,ij->i", dx, v[a] - v[b]) > 0.0
            if not redraw:
                rate = rate * 2.0 * approach
                factor = 2.0
        # the majorant of the NTC formula: sigma_max = pi (2 r_max)^2, g_max = 2 max |v - <v>|, w_max, g0 of the cell
        c = v[members].mean(axis=0)
        bound = (math.pi * (2 * r[members].max()) ** 2 * 2 * np.linalg.norm(v[members] - c, axis=1).max()
                 * w[members].max() * g0_cs(solids / vol_cell)) * factor
        kept = max(0.0, 1.0 - 0.375 * 2.0 * r[members].max() * float(np.sum(1.0 / np.asarray(edges))))
        scale = 1.0 + (1.0 - hard_sphere_compressibility(solids / vol_cell)) * kept / (n - 1) if transfer else 1.0
        m = 0.5 * n * (n - 1) * bound * dt / vol_cell * scale
        candidates += m
        accepted += rate.sum() * dt / vol_cell * scale
        if by_weights is not None:
            lo, hi = np.minimum(w[a], w[b]), np.maximum(w[a], w[b])
            for key in set(zip(lo.tolist(), hi.tolist())):
                mine = (lo == key[0]) & (hi == key[1])
                by_weights[key] = by_weights.get(key, 0.0) + float(rate[mine].sum()) * dt / vol_cell * scale
        worst = max(worst, float(rate.max() / bound))
    return candidates, accepted, worst


@pytest.mark.parametrize("eps, weights, dt, approaching, redraw, transfer",
                         [(0.01, (1.0,), 1e-3, False, 0, False),
                          (0.05, (1.0, 8.0, 64.0), 2e-4, False, 0, False),
                          (0.05, (1.0, 8.0, 64.0), 2e-4, False, 0, True),
                          (0.2, (1.0,), 1e-4, False, 0, True),
                          (0.05, (1.0,), 2e-4, True, 0, False),
                          (0.05, (8.0,), 2e-4, True, 64, False),
                          (0.05, (8.0,), 2e-4, True, 1, False)])
def test_candidates_and_acceptance_follow_the_ntc_formula(constant_model, device, eps, weights, dt, approaching,
                                                          redraw, transfer):
    """NTC's candidate count and acceptance against the formula summed by brute force over every pair of every
    cell; with ``approaching``, the doubled-rate rule (redraw 0), and the transfer of a receding accepted pair's
    collision (weight 8: the transfer leaves pairs of single particles alone): NTC's count with 64 draws (one
    loses some), the share of accepted pairs whose centres approach ~0.88 (the colliding particles are drawn from
    the clouds; a uniform box: half of the candidates recede); with the collisional transfer, the pair count
    N (N - 1) + (1 - S) k N."""
    rng = np.random.default_rng(1)
    n, reps = 2000, 12
    w = rng.choice(weights, size=n)
    side = box_side(w.sum(), eps)
    s = strategy(constant_model, side, max_substeps=1, approaching=approaching,  # one sampling at the start
                 approach_redraw=redraw, log=20000 if approaching else 0, collisional_transfer=transfer)
    drawn = accepted = exp_candidates = exp_accepted = 0.0
    worst = 0.0
    logged = approached = 0
    for _ in range(reps):
        p = make_gas(n, side, w, rng, device)
        c = select(s, p, dt)
        ec, ea, wr = brute_force_expectation(p, s.cells.lattice, dt, approaching, redraw, transfer)
        drawn += c["cell_candidates"]
        accepted += c["cell_accepted"]
        exp_candidates += ec
        exp_accepted += ea
        worst = max(worst, wr)
        assert c["cell_over_max"] == 0  # nothing rises above the majorant without collisions
        if approaching:  # the accepted pairs approach (nearest image)
            log = s.cells.event_log()
            x = p.x.numpy().astype(np.float64)
            dx = x[log["pair"][:, 1]] - x[log["pair"][:, 0]]
            dx -= side * np.round(dx / side)
            approach = np.einsum("ij,ij->i", dx, log["g"].astype(np.float64)) > 0.0
            assert len(dx) > 100
            logged += len(dx)
            approached += int(approach.sum())
            if redraw == 0:  # single particles, the doubled rule: every one
                assert np.all(approach)
    assert worst <= 1.0  # the majorant bounds every pair (acceptance probability <= 1)
    # Poisson-like counts: 4 standard errors (the integer draw of the candidates has less variance than Poisson)
    assert abs(drawn - exp_candidates) <= 4.0 * math.sqrt(exp_candidates), (drawn, exp_candidates)
    if approaching and 0 < redraw < 64:  # one draw often finds no approaching pair: collisions are lost
        assert accepted < exp_accepted - 4.0 * math.sqrt(exp_accepted), (accepted, exp_accepted)
    else:
        assert abs(accepted - exp_accepted) <= 4.0 * math.sqrt(exp_accepted), (accepted, exp_accepted)
    assert exp_accepted > 2000  # the check has statistics
    if approaching and redraw:  # the share of accepted pairs whose centres approach (plain NTC: one half)
        share = approached / logged
        assert share > 0.83, share


@pytest.mark.parametrize("approaching", [True, False])
def test_approach_filter_keeps_each_kind_of_pairs_count_where_a_weight_is_rare(constant_model, device, approaching):
    """One weighted parcel (w = 8, 475 um, Theta / 3) per cell of ~16 single 315 um particles, eps_s = 0.05, one
    sampling: per pair of weights (1-1, 1-8, 8-8) the accepted count against NTC's, summed by brute force over every
    pair of every cell. With the approach filter a receding accepted pair hands its collision to an approaching pair
    of its own two weights, drawn among the parcels of those weights (``draw_of_weight``). Drawn from the whole cell,
    64 draws often missed the one weight-8 parcel's pairs, and when no pair of
    the other weights was accepted either (small-small pairs pass the majorant of the large, 8-weighted pairs
    seldom), the collision would be lost: 4-5 % of the 1-8 collisions of a cooling weights 1 / 8 mixture."""
    from hel_warp.parcels.particles import Particles

    rng = np.random.default_rng(7)
    n, reps, dt, eps, d2 = 4000, 24, 2e-4, 0.05, 475e-6
    heavy_share = 1.0 / 16.0
    side = (n * math.pi / 6.0 * ((1 - heavy_share) * D**3 + heavy_share * 8.0 * d2**3) / eps) ** (1.0 / 3.0)
    s = strategy(constant_model, side, max_substeps=1, approaching=approaching, log=20000,
                 collisional_transfer=False)
    seen: dict = {}
    expected: dict = {}
    for _ in range(reps):
        heavy = rng.random(n) < heavy_share
        w = np.where(heavy, 8.0, 1.0)
        v = rng.normal(0.0, 1.0, size=(n, 3)) * np.where(heavy, 1.0 / math.sqrt(3.0), 1.0)[:, None]
        p = Particles.from_numpy(rng.uniform(0.0, side, size=(n, 3)), np.where(heavy, 0.5 * d2, 0.5 * D), v=v,
                                 density=RHO, weight=w, check_overlap=False, device=device)
        c = select(s, p, dt)
        assert c["cell_log_overflow"] == 0
        brute_force_expectation(p, s.cells.lattice, dt, approaching, 64 if approaching else 0, by_weights=expected)
        pair = s.cells.event_log()["pair"]
        lo, hi = np.minimum(w[pair[:, 0]], w[pair[:, 1]]), np.maximum(w[pair[:, 0]], w[pair[:, 1]])
        for key in set(zip(lo.tolist(), hi.tolist())):
            seen[key] = seen.get(key, 0) + int(np.sum((lo == key[0]) & (hi == key[1])))
    assert expected[(1.0, 8.0)] > 8000 and expected[(8.0, 8.0)] > 300  # the check has statistics
    for key, mean in expected.items():
        assert abs(seen.get(key, 0) - mean) <= 4.0 * math.sqrt(mean), (key, seen, expected)


def test_impact_geometry_is_that_of_kinetic_theory(constant_model, device):
    """b^2 / (r_i + r_j)^2 uniform, azimuth uniform in a frame the kernel does not use, |g|-weighted collisions."""
    from scipy import stats

    rng = np.random.default_rng(2)
    n, eps, dt = 3000, 0.02, 1e-3
    side = box_side(n, eps)
    s = strategy(constant_model, side, log=4000)
    g_all, n_all = [], []
    for _ in range(6):
        p = make_gas(n, side, 1.0, rng, device)
        c = select(s, p, dt)
        assert c["cell_log_overflow"] == 0
        log = s.cells.event_log()
        g_all.append(log["g"].astype(np.float64))
        n_all.append(log["normal"].astype(np.float64))
    g = np.concatenate(g_all)
    normal = np.concatenate(n_all)
    assert len(g) > 3000
    g_mag = np.linalg.norm(g, axis=1)
    g_hat = g / g_mag[:, None]
    cos_chi = np.einsum("ij,ij->i", g_hat, normal)
    assert np.all(cos_chi > 0.0)  # every sampled normal closes the pair
    assert np.allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-5)
    b2 = 1.0 - cos_chi**2
    assert stats.kstest(b2, "uniform").pvalue > 1e-3
    # azimuth of the normal's perpendicular part about g_hat, in a frame from (g_hat x z)
    e1 = np.cross(g_hat, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    e2 = np.cross(g_hat, e1)
    phi = np.arctan2(np.einsum("ij,ij->i", normal, e2), np.einsum("ij,ij->i", normal, e1))
    assert stats.kstest((phi + np.pi) / (2 * np.pi), "uniform").pvalue > 1e-3
    # collisions of a Maxwellian gas are |g|-weighted: E[|g|] = <g^2> / <g> = (3/2) sqrt(pi Theta) = 2.659 at Theta 1
    # (the unweighted mean would be 4 sqrt(Theta / pi) = 2.257); the stderr of the mean from the sample
    expected = 1.5 * math.sqrt(math.pi)
    assert abs(g_mag.mean() - expected) <= 4.0 * g_mag.std() / math.sqrt(len(g_mag)) + 0.01 * expected


@pytest.mark.parametrize("eps, nearest", [(0.01, 0), (0.05, 0), (0.05, 8)])
def test_frequency_per_real_particle_is_enskogs_at_any_weight(constant_model, device, eps, nearest):
    """Same real solids fraction, 1, 8 and 64 particles per parcel: 2 C_real / (N_real dt) against Enskog's omega
    with the gas's own Theta (velocities unchanged: selection only). Nearest-neighbour partners (``nearest`` > 0,
    Bird 2007; SPARTA ``nearcp``) change which pair collides, not how often: where positions carry no information
    on velocities the partner's g is a random pair's."""
    rng = np.random.default_rng(3)
    n, dt, reps = 2000, 2e-4, 10
    for weight in (1.0, 8.0, 64.0):
        side = box_side(n * weight, eps)
        s = strategy(constant_model, side, nearest=nearest)
        real = expected = 0.0
        for _ in range(reps):
            p = make_gas(n, side, weight, rng, device)
            v = p.v.numpy().astype(np.float64)
            theta = float(((v - v.mean(axis=0)) ** 2).sum() / (3 * n))
            omega = 24.0 * eps * g0_cs(eps) * math.sqrt(theta) / (math.sqrt(math.pi) * D)
            real += select(s, p, dt)["collisions"]
            expected += 0.5 * n * weight * omega * dt
        events = expected / weight  # the statistics are those of the parcel events
        assert abs(real / expected - 1.0) <= 4.0 / math.sqrt(events), (weight, real / expected)


def test_momentum_exact_no_energy_gain_at_mixed_weights(constant_model, device):
    rng = np.random.default_rng(4)
    n, eps, dt = 1500, 0.05, 1e-3
    w = rng.choice([1.0, 8.0, 64.0], size=n)
    side = box_side(w.sum(), eps)
    p = make_gas(n, side, w, rng, device)
    s = strategy(constant_model, side, seed=5)
    m = RHO * math.pi * D**3 / 6.0 * w
    v0 = p.v.numpy().astype(np.float64)
    scale = float((m[:, None] * np.abs(v0)).sum())
    for _ in range(3):
        before = p.v.numpy().astype(np.float64)
        s.collide(p, dt)
        after = p.v.numpy().astype(np.float64)
        c = s.counts()
        assert c["surrogate_calls"] > 500
        # sum w m v: float32 velocities, one rounding per update of each parcel
        drift = np.abs((m[:, None] * (after - before)).sum(axis=0)).max()
        assert drift <= 1e-6 * scale
        # kinetic energy never grows (guarded outcome; the heavier parcel's partial impulse only dissipates more)
        assert (m * (after**2).sum(axis=1)).sum() <= (m * (before**2).sum(axis=1)).sum() * (1.0 + 1e-6)


def weight8_gas(seed: int, device, n: int = 1000, eps: float = 0.05):
    """(side, fresh): a periodic box of n parcels of 8 at eps, and a function giving the same parcels anew."""
    rng = np.random.default_rng(seed)
    side = box_side(8 * n, eps)
    x = rng.uniform(0.0, side, size=(n, 3))
    v = rng.normal(size=(n, 3))

    def fresh():
        from hel_warp.parcels.particles import Particles

        return Particles.from_numpy(x, 0.5 * D, v=v, density=RHO, weight=8.0, check_overlap=False, device=device)

    return side, fresh


def test_same_seed_same_run_and_restart_is_exact(constant_model, device):
    n, dt = 1000, 1e-3
    side, fresh = weight8_gas(6, device, n)

    def advance(s, p, steps):
        for _ in range(steps):
            s.collide(p, dt)

    a, b = fresh(), fresh()
    sa, sb = strategy(constant_model, side, seed=7), strategy(constant_model, side, seed=7)
    advance(sa, a, 4)
    advance(sb, b, 4)
    assert np.array_equal(a.v.numpy(), b.v.numpy())
    assert sa.counts()["surrogate_calls"] > 0
    other = fresh()
    advance(strategy(constant_model, side, seed=8), other, 4)
    assert not np.array_equal(a.v.numpy(), other.v.numpy())  # the seed matters
    # restart: 2 steps, checkpoint (velocities + strategy state), a new strategy continues for 2
    c = fresh()
    sc = strategy(constant_model, side, seed=7)
    advance(sc, c, 2)
    state = {k: np.asarray(val).copy() for k, val in sc.state().items()}
    v_mid = c.v.numpy().copy()
    d = fresh()
    d.v.assign(v_mid)
    sd = strategy(constant_model, side, seed=0)
    sd.set_state(state)
    advance(sd, d, 2)
    assert np.array_equal(d.v.numpy(), a.v.numpy())


def test_the_device_planned_sub_step_loop_reads_nothing_and_gives_the_host_loops_bits(constant_model, device):
    """``CellDetection.collide(device_extremes=...)`` (``HelConfig.read_back`` 'output'): the sub-steps planned on the
    device from the live speeds and the last step's accepted events, run as one captured while loop. Parcels of 8
    with the approach filter at dt = 1e-3 s (many events, several sub-steps that grow with the events): step after
    step the same velocities, path shifts, sub-steps and events per parcel as the host loop, bit for bit, and from
    the second step on (the loop captured) one graph launch and no read per step."""
    import warp as wp

    from hel_warp.runs import counters

    n, dt = 1000, 1e-3
    side, fresh = weight8_gas(11, device, n)
    host, dev = fresh(), fresh()
    sh = strategy(constant_model, side, seed=3, approaching=True)
    sd = strategy(constant_model, side, seed=3, approaching=True)
    bounds = (8.0, 0.5 * D, n)
    substeps = []
    for step in range(4):
        sh.collide(host, dt)
        if step == 0:
            sd.collide(dev, dt, bounds=bounds)
        else:
            with counters.counting():
                before = counters.snapshot()
                sd.collide(dev, dt, bounds=bounds)
                d = counters.snapshot() - before
            assert (d.graph_launches, d.reads) == (1, 0), d
        assert sd.cells.device_loop_steps == step + 1
        assert np.array_equal(dev.v.numpy(), host.v.numpy())
        assert np.array_equal(sd.cells._shift.numpy(), sh.cells._shift.numpy())
        assert sd.cells.substeps == sh.cells.substeps
        assert sd.cells.events_per_parcel == sh.cells.events_per_parcel
        substeps.append(sh.cells.substeps)
        # the parcels move on (as the push would): x += v dt plus the sub-stepped paths' shift
        for p, s in ((host, sh), (dev, sd)):
            x = p.x.numpy() + p.v.numpy() * np.float32(dt)
            p.x.assign(np.mod(x, np.float32(side)).astype(np.float32))
            s.cells._shift_pending = False
    assert max(substeps) > substeps[0] > 1  # the events per parcel cut the later steps further
    assert sd.counts()["cell_accepted"] == sh.counts()["cell_accepted"] > 0
    # a checkpoint taken after device steps holds the device's events per parcel
    assert sd.state()["cell_events_per_parcel"] == sh.state()["cell_events_per_parcel"]
    wp.synchronize()


def test_approach_filter_cuts_the_step_by_the_last_steps_events_and_restarts_exactly(constant_model, device):
    """With ``approaching``, a step is cut into at least ceil(events per parcel of the last step / approach_events)
    sub-steps; that count is in the checkpoint, so a restart continues bit for bit (and without it, it would not)."""
    import math as _math

    n, dt = 1000, 1e-3
    side, fresh = weight8_gas(9, device, n)

    a = fresh()
    sa = strategy(constant_model, side, seed=7, approaching=True)
    sa.collide(a, dt)
    first = sa.cells.substeps
    events = sa.cells.events_per_parcel
    assert events == pytest.approx(2.0 * sa.counts()["cell_accepted"] / n) and events > 0.5
    state = {k: np.asarray(val).copy() for k, val in sa.state().items()}
    v_mid = a.v.numpy().copy()
    sa.collide(a, dt)
    assert sa.cells.substeps == max(first, _math.ceil(events / 0.25)) > first
    for keep in (True, False):
        d = fresh()
        d.v.assign(v_mid)
        sd = strategy(constant_model, side, seed=0, approaching=True)
        sd.set_state(state if keep else {k: val for k, val in state.items() if k != "cell_events_per_parcel"})
        sd.collide(d, dt)
        assert np.array_equal(d.v.numpy(), a.v.numpy()) == keep
    # the recent partners are each parcel's accepted partners, newest first, a repeat moved up (replayed from the log)
    e = fresh()
    se = strategy(constant_model, side, seed=7, approaching=True, log=200000)
    se.collide(e, dt)
    ring = [[] for _ in range(n)]
    for i, j in se.cells.event_log()["pair"].tolist():
        for p_, q_ in ((i, j), (j, i)):
            if q_ in ring[p_]:
                ring[p_].remove(q_)
            ring[p_] = ([q_] + ring[p_])[:16]
    want = np.full((n, 16), -1, np.int32)
    for p_, r in enumerate(ring):
        want[p_, :len(r)] = r
    assert np.array_equal(se.state()["cell_recent_partners"], want)
    # a checkpoint from before the ring (one last partner per parcel) restores as its first column
    from hel_warp.collisions.cells import CellCollisions

    old_state = CellCollisions()
    old_state.set_state({"cell_last_partner": want[:, 0]})
    np.testing.assert_array_equal(old_state.state()["cell_recent_partners"], want[:, :1])
    # the recent partners (the met exemption) are in the state too: without them the continuation differs
    assert state["cell_recent_partners"].shape == (n, 16) and (state["cell_recent_partners"][:, 1] >= 0).any()
    d = fresh()
    d.v.assign(v_mid)
    sd = strategy(constant_model, side, seed=0, approaching=True)
    sd.set_state({k: val for k, val in state.items() if k != "cell_recent_partners"})
    sd.collide(d, dt)
    assert not np.array_equal(d.v.numpy(), a.v.numpy())


def test_detection_defaults_to_cell_when_a_parcel_is_heavier_than_one(constant_model, device):
    from hel_warp.collisions.models import SurrogateCollision

    rng = np.random.default_rng(9)
    side = box_side(400, 0.02)
    for weight, want in ((1.0, "swept"), (8.0, "cell")):
        s = SurrogateCollision(model_dir=constant_model, periodic_box=(side,) * 3)
        s.collide(make_gas(400, side, weight, rng, device), 1e-4)
        assert s.detection == want


def test_cells_follow_the_solver_grid(constant_model, device):
    """With a HEL solver the collision cells are its grid cells (or sub-cells): a parcel collides only with parcels
    of its own cell."""
    import warp as wp
    from types import SimpleNamespace

    from hel_warp.collisions.cells import CellConfig
    from hel_warp.collisions.models import SurrogateCollision
    from hel_warp.parcels.coupling import GridSpec

    rng = np.random.default_rng(10)
    n = 800
    grid = GridSpec(origin=(0.0, 0.0, 0.0), spacing=2e-3, shape=(4, 3, 2))
    p = make_gas(n, 1.0, 4.0, rng, device)
    x = rng.uniform(0.0, 1.0, size=(n, 3)) * np.array([8e-3, 6e-3, 4e-3])
    p.x.assign(x)
    for subdivision in (1, 2):
        s = SurrogateCollision(model_dir=constant_model, seed=1,
                               cell=CellConfig(subdivision=subdivision, coarsen=1, log_capacity=5000, max_substeps=1))
        solver = SimpleNamespace(grid=grid, pool=SimpleNamespace(particles=p), config=SimpleNamespace(dt=2e-3),
                                 fields=SimpleNamespace(parcel_a_coll=wp.zeros(n, dtype=wp.vec3, device=device)))
        s.accelerate(solver)
        assert s.detection == "cell"
        origin, edges, shape = s.cells.lattice
        assert np.allclose(edges, 2e-3 / subdivision) and tuple(shape) == tuple(np.array(grid.shape) * subdivision)
        pairs = s.cells.event_log()["pair"]
        assert len(pairs) > 50
        cell = np.floor(x / (2e-3 / subdivision)).astype(int)
        assert np.array_equal(cell[pairs[:, 0]], cell[pairs[:, 1]])


def test_batched_rounds_equal_inline_walks(constant_model, device):
    """The batched forest rounds resolve the same pairs in the same order as the inline walks (one cell thread
    going through its candidates): identical velocities."""
    from hel_warp.collisions.cells import CellConfig
    from hel_warp.collisions.models import SurrogateCollision

    rng = np.random.default_rng(11)
    n, eps = 1500, 0.05
    side = box_side(8 * n, eps)
    x = rng.uniform(0.0, side, size=(n, 3))
    v = rng.normal(size=(n, 3))
    out = []
    for batched in (True, False):
        from hel_warp.parcels.particles import Particles

        p = Particles.from_numpy(x, 0.5 * D, v=v, density=RHO, weight=8.0, check_overlap=False, device=device)
        s = SurrogateCollision(model_dir=constant_model, detection="cell", periodic_box=(side,) * 3, seed=3,
                               batched=batched, cell=CellConfig())
        for _ in range(2):
            s.collide(p, 1e-3)
        assert (s.batch_forest is not None) == batched
        out.append((p.v.numpy().copy(), s.counts()))
    assert out[0][1]["surrogate_calls"] > 1000
    assert out[1][1]["rounds"] == 0 < out[0][1]["rounds"]
    assert {k: c for k, c in out[0][1].items() if k != "rounds"} == {k: c for k, c in out[1][1].items() if k != "rounds"}
    assert np.array_equal(out[0][0], out[1][0])


def test_rounds_cap_finishes_inline_with_the_same_result(constant_model, device):
    """Capping the batched rounds (dense cells finish inline) changes nothing but the rounds taken."""
    from hel_warp.collisions.cells import CellConfig
    from hel_warp.collisions.models import SurrogateCollision
    from hel_warp.parcels.particles import Particles

    rng = np.random.default_rng(12)
    n, eps = 1500, 0.05
    side = box_side(8 * n, eps)
    x = rng.uniform(0.0, side, size=(n, 3))
    v = rng.normal(size=(n, 3))
    out = []
    for cap in (1000, 3):
        p = Particles.from_numpy(x, 0.5 * D, v=v, density=RHO, weight=8.0, check_overlap=False, device=device)
        s = SurrogateCollision(model_dir=constant_model, detection="cell", periodic_box=(side,) * 3, seed=3,
                               cell=CellConfig(batched_rounds=cap, batched_min_rows=0, max_substeps=1))
        s.collide(p, 1e-3)
        out.append((p.v.numpy().copy(), s.counts()))
    assert out[1][1]["rounds"] == 3 < out[0][1]["rounds"]
    assert out[0][1]["surrogate_calls"] == out[1][1]["surrogate_calls"] > 1000
    assert np.array_equal(out[0][0], out[1][0])


def small_walled_hel(strategy, injection, capacity: int, dt: float = 1e-3):
    """A HEL solver in a closed 6 mm box (6^3 cells, gas, walls) with ``injection`` released over the first 2 ms: the
    restart tests' run."""
    from hel_warp.parcels.coupling import PushConfig
    from hel_warp.gas.solver import GasConfig, GasField, GasSolver
    from hel_warp.gas.grid import Box, Geometry, Grid
    from hel_warp.hel import HelConfig, HelSolver, ScheduledInjection
    from hel_warp.parcels.pool import ParcelPool

    grid = Grid(spacing=1e-3, shape=(6, 6, 6))
    domain = Geometry(shapes=(Box(lo=(0, 0, 0), hi=(0.006, 0.006, 0.006)),)).build(grid)
    push = PushConfig(drag="gidaspow")
    gas_solver = GasSolver(domain, GasConfig(density=push.fluid_density, viscosity=push.fluid_viscosity))
    config = HelConfig(dt=dt, push=push, injectors=(ScheduledInjection(injection=injection, t_end=0.002),))
    return HelSolver(pool=ParcelPool.empty(capacity), gas_solver=gas_solver, gas=GasField(domain), config=config,
                     collision=strategy)


def run_straight_and_restarted(build, out, dt: float, n: int):
    """``build()`` run 2n steps in one go, and again as n steps, an interruption, a restart from the checkpoint at n
    and n more: the two solvers."""
    from hel_warp.runs.run import Run, RunConfig

    def run_config(path, checkpoint_every=None):
        return RunConfig(out_dir=str(path), end_time=2 * n * dt, output_interval=2 * dt,
                         checkpoint_interval=None if checkpoint_every is None else checkpoint_every * dt, vtk=False)

    straight = build()
    Run(straight, run_config(out / "a")).run()
    first = build()
    with pytest.raises(Interrupt):
        Run(first, run_config(out / "b", checkpoint_every=n)).run(progress=stop_at(n + 2))
    resumed = build()
    Run(resumed, run_config(out / "b", checkpoint_every=n), restart=True).run()
    return straight, resumed


@pytest.mark.parametrize("transfer", [False, True])
def test_hel_run_with_cell_collisions_restarts_bitwise(constant_model, tmp_path, transfer):
    """A HEL run (gas, walls, injection) of parcels of 8 particles under the cell detection (the grid cells): 2N steps
    in one go == N steps, an interruption, a restart from the checkpoint at N (the random state is in it), N more;
    with and without the collisional transfer (its displacements live within a step)."""
    from hel_warp.collisions.cells import CellConfig
    from hel_warp.hel import collision_model
    from hel_warp.parcels.pool import VolumeInjection

    dt, n = 1e-3, 4

    def build():
        injection = VolumeInjection(box_lo=(0.001, 0.001, 0.001), box_hi=(0.004, 0.004, 0.004), diameter_mean=D,
                                    count=400, speed=1.0, direction=(1.0, 0.3, -1.0), weight=8.0, seed=5)
        strategy = collision_model("surrogate", model_dir=constant_model, seed=4,
                                   cell=CellConfig(collisional_transfer=transfer))
        return small_walled_hel(strategy, injection, 400, dt)

    straight, resumed = run_straight_and_restarted(build, tmp_path, dt, n)
    assert straight.collision.detection == "cell"
    a, b = straight.state(), resumed.state()
    assert a.keys() == b.keys() and "collision/cell_steps" in a
    assert int(a["collision/cell_steps"]) >= n  # steps with live parcels (the first injects them)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    import zarr

    series = zarr.open_group(str(tmp_path / "a" / "run.zarr"), mode="r")["series"]
    assert float(np.sum(series["collisions_collisions"][...])) > 0  # the run collided


def test_substeps_follow_the_paths_and_the_shift_closes_them(constant_model, device):
    """A step cut into sub-steps (parcels faster than a cell edge per step): the end positions after the caller's
    x += v_final dt and ``correct_positions`` are those of the straight paths with the velocities of each sub-step
    (a parcel that never collided moved by v0 dt, one that did not by v_final dt), the centre of mass moved by
    P dt / M (momentum is conserved in every sub-step), and momentum is exact."""
    from hel_warp.collisions.cells import CellConfig
    from hel_warp.collisions.models import SurrogateCollision
    from kernels.free_flight import drift

    rng = np.random.default_rng(13)
    n, eps, dt = 1500, 0.05, 2e-3
    side = box_side(8 * n, eps)
    p = make_gas(n, side, 8.0, rng, device)
    x0 = p.x.numpy().astype(np.float64)
    v0 = p.v.numpy().astype(np.float64)
    s = SurrogateCollision(model_dir=constant_model, detection="cell", periodic_box=(side,) * 3, seed=2,
                           cell=CellConfig(cfl=0.25))
    s.collide(p, dt)
    k = s.cells.substeps
    assert k >= 4
    v1 = p.v.numpy().astype(np.float64)
    assert np.abs((v1 - v0).sum(axis=0)).max() <= 1e-6 * np.abs(v0).sum()  # equal weights: sum v conserved
    drift(p.x, p.v, p.alive, dt)
    s.correct_positions(p)
    x1 = p.x.numpy().astype(np.float64)
    moved = x1 - x0
    # every parcel moved by a mean velocity between its start and end velocity per axis (a convex combination of
    # its sub-step velocities): the path, not v_final dt; and a parcel that never collided moved by v0 dt exactly
    untouched = np.all(v1 == v0, axis=1)
    assert untouched.any() and not untouched.all()
    assert np.allclose(moved[untouched], v0[untouched] * dt, rtol=0, atol=1e-7)  # float32 positions ~1e-2 m
    hit = ~untouched
    assert not np.allclose(moved[hit], v1[hit] * dt, rtol=0, atol=1e-7)  # the shift did something
    # the centre of mass moves by P dt / M exactly (momentum is conserved in every sub-step), whatever the paths
    assert np.allclose(moved.mean(axis=0), v0.mean(axis=0) * dt, rtol=0, atol=1e-8)


@pytest.fixture(scope="module")
def hard_sphere_model(tmp_path_factory):
    """The constant forest of ``constant_model`` with its normal impulse scaled by cos_angle: J_n = (1 + e) m* g_n
    at every incidence, frictionless - the smooth hard sphere of kinetic theory."""
    import json

    root = tmp_path_factory.mktemp("hard_sphere")
    write_constant_contact_forest(root)
    doc = json.loads((root / "forest.json").read_text())
    doc["target_scale"] = ["cos_angle", "none"]
    (root / "forest.json").write_text(json.dumps(doc))
    return str(root)


def beams_decay_rate(model, device, weight, cell_size, dt, steps, n_real=64000, eps=0.01, speed=2.0, seed=1):
    """Two cold beams of weight-``weight`` parcels at +-speed along x in a periodic box, cell detection with cubic
    collision cells of ``cell_size``, the parcels flown ballistically between steps: the fitted d(1/U)/dt (U = half
    the beams' mean velocity difference) over kinetic theory's initial (1 + e) chi n_2 sigma, and the strategy."""
    from hel_warp.parcels.particles import Particles

    n = n_real // int(weight)
    side = round(box_side(n_real, eps) / cell_size) * cell_size
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.0, side, size=(n, 3))
    v = np.zeros((n, 3))
    half = n // 2
    v[:half, 0], v[half:, 0] = speed, -speed
    p = Particles.from_numpy(x, 0.5 * D, v=v, density=RHO, weight=float(weight), check_overlap=False, device=device)
    s = strategy(model, side, seed=seed, cell_size=cell_size)
    u = [speed]
    for _ in range(steps):
        s.collide(p, dt)
        s.correct_positions(p)
        p.x.assign(np.mod(p.x.numpy() + p.v.numpy() * dt, side).astype(np.float32))
        vv = p.v.numpy().astype(np.float64)
        u.append(0.5 * (vv[:half, 0].mean() - vv[half:, 0].mean()))
    slope = np.polyfit(np.arange(steps + 1) * dt, 1.0 / np.asarray(u), 1)[0]
    n2 = 0.5 * n_real / side**3
    # cold beams, smooth hard spheres (J_n = (1 + e) m* g_n), b^2 uniform: <cos^2> = 1/2, so a beam-1
    # particle loses (1 + e) U / 2 per collision at the rate chi n_2 sigma 2U: dU/dt = -(1 + e) chi n_2 sigma U^2
    return slope / ((1.0 + E) * g0_cs(eps) * n2 * math.pi * D**2), s


def test_counter_streaming_beams_lose_momentum_at_kinetic_theorys_rate_unless_a_parcel_pair_saturates(
        hard_sphere_model, device, capsys):
    """Momentum exchange between two cold beams (the rig's crossing streams in their simplest form) against kinetic
    theory, and its bias at large weight: NTC collides a parcel pair with the rate of w real partners but turns the
    whole partner parcel each time, so once w sigma h / V (``pair_saturation``) nears 1 the pair re-collides with its
    own deflected self while it crosses a cell, and the exchange falls short. Weight 1 over 0.2 ms (U changes by 4 %:
    the initial rate) against kinetic theory; over 1 ms (a pair crosses a 2 mm cell side by side) weight 8 in 4 mm
    cells (saturation 0.16) against weight 1, and weight 64 in 2 mm cells (saturation 5) flagged with a warning and
    far short."""
    from hel_warp.collisions.cells import SATURATION_WARN

    model = hard_sphere_model
    initial, s1 = beams_decay_rate(model, device, 1, 2e-3, 1e-4, 2)
    assert abs(initial - 1.0) < 0.08, initial
    r1, s1 = beams_decay_rate(model, device, 1, 2e-3, 5e-4, 2)
    r8, s8 = beams_decay_rate(model, device, 8, 4e-3, 5e-4, 2)
    capsys.readouterr()
    r64, s64 = beams_decay_rate(model, device, 64, 2e-3, 5e-4, 2)
    warning = capsys.readouterr().err
    sigma = math.pi * D**2
    # the saturation number is w sigma h / V of the cubic cells (a closed form of the case)
    assert math.isclose(s8.cells.pair_saturation, 8 * sigma / 4e-3**2, rel_tol=1e-4)
    assert math.isclose(s64.cells.pair_saturation, 64 * sigma / 2e-3**2, rel_tol=1e-4)
    assert s1.cells.pair_saturation < s8.cells.pair_saturation < SATURATION_WARN < s64.cells.pair_saturation
    assert abs(r8 / r1 - 1.0) < 0.08, (r8, r1)
    assert r64 / r1 < 0.5, (r64, r1)
    assert "warning" in warning and "saturates" in warning and warning.count("\n") == 1
    print(f"beams: weight 1 {initial:.3f} of kinetic theory initially; over 1 ms weight 8 (saturation "
          f"{s8.cells.pair_saturation:.2f}) {r8 / r1:.3f} and weight 64 ({s64.cells.pair_saturation:.2f}) "
          f"{r64 / r1:.3f} of weight 1")


def test_no_saturation_warning_for_single_particles_in_small_cells(hard_sphere_model, device, capsys):
    """At weight 1 a parcel is one particle: in collision cells of 0.8 mm (w sigma h / V = 0.49 for 315 um
    spheres, above the warning's 0.3) no parcel re-collides with a deflected copy of itself and no lower weight
    exists, so no warning about saturated parcel pairs (a packed bed's dense cells at weight 1 would print it)."""
    from hel_warp.collisions.cells import SATURATION_WARN

    capsys.readouterr()
    _, s1 = beams_decay_rate(hard_sphere_model, device, 1, 0.8e-3, 1e-4, 1, n_real=4000)
    assert s1.cells.pair_saturation > SATURATION_WARN
    assert "saturates" not in capsys.readouterr().err


def test_heavy_parcels_cool_at_haffs_rate_in_the_periodic_boxs_own_cells(hard_sphere_model, device):
    """Weight 64 at eps_s = 0.05 (1,000 parcels, the reference cooling box), default lattice: the box's cells are
    sized for 16 parcels unless that would saturate a heavy pair, as grids coarsen. At 16 parcels per cell
    (6.9 mm, w sigma h / V = 0.42) a pair recollided with its own deflected self and the gas cooled 0.976 +- 0.002
    of Haff's rate over these 24 seeds (0.972 with the trained frictionless model over 8); in cells of at least
    sqrt(w sigma / 0.2) it cools at Haff's rate. Reference: Haff's law with Enskog's g0, d(Theta^-1/2)/dt =
    4 (1 - e^2) g0 eps / (d sqrt(pi)), fitted over 40 steps of 1e-3 s (Theta falls to ~6 % of its start)."""
    from hel_warp.collisions.cells import SATURATION_WARN

    weight, n, eps, dt, steps = 64.0, 1000, 0.05, 1e-3, 40
    side = box_side(n * weight, eps)
    haff = 4.0 * (1.0 - E**2) * g0_cs(eps) * eps / (D * math.sqrt(math.pi))
    ratios = []
    for seed in range(24):
        rng = np.random.default_rng(seed)
        p = make_gas(n, side, weight, rng, device)
        s = strategy(hard_sphere_model, side, seed=seed)
        theta = []
        for step in range(steps + 1):
            v = p.v.numpy().astype(np.float64)
            theta.append(((v - v.mean(axis=0)) ** 2).sum() / (3 * n))
            if step == steps:
                break
            s.collide(p, dt)
            s.correct_positions(p)
            p.x.assign(np.mod(p.x.numpy() + p.v.numpy() * dt, side).astype(np.float32))
        assert s.cells.pair_saturation < SATURATION_WARN
        ratios.append(np.polyfit(np.arange(steps + 1) * dt, 1.0 / np.sqrt(theta), 1)[0] / haff)
    mean, se = float(np.mean(ratios)), float(np.std(ratios, ddof=1) / math.sqrt(len(ratios)))
    assert abs(mean - 1.0) <= 0.02, (mean, se)


def test_weighted_parcels_get_collision_cells_coarse_enough_not_to_saturate(constant_model, device):
    """With a HEL grid the collision cells of weighted parcels merge k^3 grid cells, k the smallest with
    w sigma / (k h)^2 <= SATURATION_TARGET (closed form); pairs stay within one merged cell; an explicit coarsen and
    weight 1 keep the grid cells."""
    import warp as wp
    from types import SimpleNamespace

    from hel_warp.collisions.cells import SATURATION_TARGET, CellConfig
    from hel_warp.collisions.models import SurrogateCollision
    from hel_warp.parcels.coupling import GridSpec
    from hel_warp.errors import ConfigError

    rng = np.random.default_rng(12)
    n, h = 800, 1e-3
    grid = GridSpec(origin=(0.0, 0.0, 0.0), spacing=h, shape=(12, 9, 6))
    x = rng.uniform(0.0, 1.0, size=(n, 3)) * np.array([12e-3, 9e-3, 6e-3])
    for weight, coarsen in ((8.0, None), (64.0, None), (8.0, 2), (1.0, None)):
        p = make_gas(n, 1.0, weight, rng, device)
        p.x.assign(x)
        s = SurrogateCollision(model_dir=constant_model, seed=1, detection="cell",
                               cell=CellConfig(coarsen=coarsen, log_capacity=20000, max_substeps=1))
        solver = SimpleNamespace(grid=grid, pool=SimpleNamespace(particles=p), config=SimpleNamespace(dt=1e-3),
                                 fields=SimpleNamespace(parcel_a_coll=wp.zeros(n, dtype=wp.vec3, device=device)))
        s.accelerate(solver)
        origin, edges, shape = s.cells.lattice
        sigma = math.pi * D**2
        k = coarsen if coarsen is not None else (
            1 if weight == 1.0 else math.ceil(math.sqrt(weight * sigma / SATURATION_TARGET) / h))
        assert np.allclose(edges, k * h), (weight, coarsen, edges)
        merged = k > 1  # merged cells are shifted by a random offset (CellConfig.shift): one more cell per axis
        assert tuple(shape) == tuple(-(-np.array(grid.shape) // k) + (1 if merged else 0))
        offset = np.asarray(grid.origin) - np.asarray(origin)
        assert (np.all((offset >= 0.0) & (offset < k * h)) and np.any(offset > 0.0)) if merged else np.all(offset == 0)
        if coarsen is None and weight > 1.0:
            assert s.cells.pair_saturation <= SATURATION_TARGET < weight * sigma / ((k - 1) * h) ** 2
        pairs = s.cells.event_log()["pair"]
        assert len(pairs) > 20
        cell = np.floor((x - origin) / (k * h)).astype(int)
        assert np.array_equal(cell[pairs[:, 0]], cell[pairs[:, 1]])
    with pytest.raises(ConfigError):
        CellConfig(subdivision=2, coarsen=2)


def test_shifted_merged_cells_let_parcels_meet_across_a_fixed_face(constant_model, device):
    """Two slabs of weighted parcels on either side of a face of the merged (unshifted) lattice, each thinner than a
    cell: with a fixed lattice no pair can meet; with the random shift (Ihle & Kroll) a pair at separation dx meets
    when no shifted face falls between them, probability 1 - |dx| / (k h) along x (Boltzmann rate, any pair of a
    cell: no density or approach dependence): the accepted pairs' mean
    |dx| / (k h) is that of the tent kernel over the slabs' pairs, and the offsets of the steps
    are spread over [0, k h)."""
    import warp as wp
    from types import SimpleNamespace

    from hel_warp.collisions.cells import CellConfig
    from hel_warp.collisions.models import SurrogateCollision
    from hel_warp.parcels.coupling import GridSpec

    rng = np.random.default_rng(13)
    n, h, weight = 600, 1e-3, 8.0
    grid = GridSpec(origin=(0.0, 0.0, 0.0), spacing=h, shape=(8, 8, 8))
    x = rng.uniform(0.0, 1.0, size=(n, 3)) * np.array([2e-3, 8e-3, 8e-3])
    x[:, 0] += 3e-3  # the slabs 3-4 mm and 4-5 mm: the face x = 4 mm of the 4 mm merged cells between them
    left = x[:, 0] < 4e-3
    found = {}
    for shift in (False, True):
        dxs, offsets = [], []
        for step in range(12):
            p = make_gas(n, 1.0, weight, rng, device)
            p.x.assign(x)
            s = SurrogateCollision(model_dir=constant_model, seed=step, detection="cell",
                                   cell=CellConfig(coarsen=4, shift=shift, enskog=False, approaching=False,
                                                   log_capacity=20000, max_substeps=1))
            solver = SimpleNamespace(grid=grid, pool=SimpleNamespace(particles=p), config=SimpleNamespace(dt=1e-3),
                                     fields=SimpleNamespace(parcel_a_coll=wp.zeros(n, dtype=wp.vec3, device=device)))
            s.accelerate(solver)
            offsets.append(np.asarray(grid.origin) - s.cells.lattice[0])
            pairs = s.cells.event_log()["pair"]
            cross = left[pairs[:, 0]] != left[pairs[:, 1]]
            dxs.extend(np.abs(x[pairs[cross, 0], 0] - x[pairs[cross, 1], 0]) / (4 * h))
        found[shift] = (np.asarray(dxs), np.asarray(offsets))
    assert len(found[False][0]) == 0 and np.all(found[False][1] == 0.0)
    dx, offsets = found[True]
    assert len(dx) > 200 and np.all(dx < 1.0)
    assert np.all((offsets >= 0.0) & (offsets < 4 * h)) and offsets.std(axis=0).min() > 0.2 * 4 * h / math.sqrt(12)
    # every cross pair that shares a cell of a step's shifted lattice is equally likely to collide (the rate does not
    # depend on position): the expected mean dx over the steps' recorded offsets; over uniform offsets the weight of
    # a pair is the tent 1 - dx along x
    il, ir = np.flatnonzero(left), np.flatnonzero(~left)
    num = den = 0.0
    for off in offsets:
        c = np.floor((x + off) / (4 * h)).astype(int)
        same = np.all(c[il][:, None, :] == c[ir][None, :, :], axis=2)
        d = np.abs(x[il, 0][:, None] - x[ir, 0][None, :]) / (4 * h)
        num, den = num + float(d[same].sum()), den + float(same.sum())
    expected = num / den
    assert dx.mean() == pytest.approx(expected, abs=4 * dx.std() / math.sqrt(len(dx)))


def test_packing_stress_follows_harris_crighton_and_pushes_parcels_out_of_a_packed_cell(constant_model, device):
    """``CellConfig(packing_stress=True)`` (the default): tau = P eps^beta / max(eps_cp - eps, 1e-7 (1 - eps)) per cell (the
    closed form, evaluated here), and a parcel beside an overfull cell is pushed away from it (-grad tau)."""
    import warp as wp
    from types import SimpleNamespace

    from hel_warp.collisions.cells import CellConfig
    from hel_warp.collisions.models import SurrogateCollision
    from hel_warp.parcels.coupling import GridSpec
    from kernels.ktgf import packing_pressure

    eps = np.array([0.0, 0.1, 0.3, 0.5, 0.57, 0.6, 0.9], np.float32).reshape(7, 1, 1)
    out = wp.zeros(eps.shape, dtype=float, device=device)
    packing_pressure(wp.array(eps, dtype=float, device=device), out, p_solid=10.0, beta=2.0, packed=0.58, eps=1e-7)
    e = eps.astype(np.float64).ravel()
    expected = 10.0 * e**2 / np.maximum(0.58 - e, 1e-7 * (1.0 - e))
    np.testing.assert_allclose(out.numpy().ravel(), expected, rtol=2e-5)

    grid = GridSpec(origin=(0.0, 0.0, 0.0), spacing=1e-3, shape=(5, 5, 5))
    cell_eps = np.full((5, 5, 5), 0.05, np.float32)
    cell_eps[2, 2, 2] = 0.7  # overfull
    n = 2
    p = make_gas(n, 1.0, 1.0, np.random.default_rng(0), device)
    p.x.assign(np.array([[1.6e-3, 2.5e-3, 2.5e-3], [3.4e-3, 2.5e-3, 2.5e-3]], np.float32))  # either side along x
    fields = SimpleNamespace(cell_eps_s=wp.array(cell_eps, dtype=float, device=device),
                             cell_p_s=wp.zeros((5, 5, 5), dtype=float, device=device),
                             cell_grad_p_s=wp.zeros((5, 5, 5), dtype=wp.vec3, device=device),
                             parcel_a_coll=wp.zeros(n, dtype=wp.vec3, device=device))
    s = SurrogateCollision(model_dir=constant_model, seed=1, detection="cell", cell=CellConfig(packing_stress=True))
    solver = SimpleNamespace(grid=grid, pool=SimpleNamespace(particles=p), config=SimpleNamespace(dt=1e-3),
                             fields=fields)
    s._packing_stress(solver)
    a = fields.parcel_a_coll.numpy()
    assert a[0, 0] < 0.0 < a[1, 0]  # away from the packed cell on both sides
    on = a.copy()
    s_default = SurrogateCollision(model_dir=constant_model, seed=1, detection="cell")
    fields.parcel_a_coll.zero_()
    s_default._packing_stress(solver)
    np.testing.assert_array_equal(fields.parcel_a_coll.numpy(), on)  # on by default
    s_off = SurrogateCollision(model_dir=constant_model, seed=1, detection="cell",
                               cell=CellConfig(packing_stress=False))
    fields.parcel_a_coll.zero_()
    s_off._packing_stress(solver)
    assert not np.any(fields.parcel_a_coll.numpy())


@pytest.mark.parametrize("nearest", [0, 64])
def test_nearest_partners_stay_within_their_cluster(constant_model, device, nearest):
    """One cell holding two tight clusters of 12 parcels that fly apart (+-1 m/s along x, 0.05 m/s spread within a
    cluster): with nearest partners (all of the cell scanned) every accepted pair lies within a cluster; with random
    partners (Bird's NTC) most accepted pairs are the fast cross pairs."""
    rng = np.random.default_rng(22)
    side = 4e-3
    s = strategy(constant_model, side, nearest=nearest, cell_size=side, enskog=False, max_substeps=1, log=20000)
    cross = within = 0
    for _ in range(20):
        centre = np.repeat([[0.25 * side, 0.5 * side, 0.5 * side], [0.75 * side, 0.5 * side, 0.5 * side]], 12, axis=0)
        x = centre + rng.uniform(-0.05 * side, 0.05 * side, size=(24, 3))
        v = np.repeat([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]], 12, axis=0) + rng.normal(0.0, 0.05, size=(24, 3))
        from hel_warp.parcels.particles import Particles
        p = Particles.from_numpy(x, 0.5 * D, v=v, density=RHO, weight=1.0, check_overlap=False, device=device)
        select(s, p, 0.05)
        pairs = s.cells.event_log()["pair"]
        same = (pairs[:, 0] < 12) == (pairs[:, 1] < 12)
        within += int(same.sum())
        cross += int((~same).sum())
    if nearest:
        assert cross == 0 and within > 20
    else:
        assert cross > 4 * within and cross > 20


def box_fluid_volume(lo, hi, mask, grid_origin, h):
    """Fluid volume of the box [lo, hi) over a grid's fluid mask: the product of 1-d overlaps with every grid cell
    (an independent reference for ``kernels/cell_collide.py`` ``cell_fluid_volumes``)."""
    lengths = []
    for ax in range(3):
        faces = grid_origin[ax] + np.arange(mask.shape[ax] + 1) * h
        lengths.append(np.clip(np.minimum(hi[ax], faces[1:]) - np.maximum(lo[ax], faces[:-1]), 0.0, None))
    return float(np.einsum("i,j,k,ijk->", *lengths, mask.astype(np.float64)))


def test_collision_cells_take_the_fluid_volume_inside_them(device):
    """Each collision cell's volume is the fluid volume its box holds (exact: the mask's integral is trilinear inside a
    grid cell), at least FLUID_VOLUME_FLOOR of the box; a box wholly in fluid reads the cell volume itself."""
    import warp as wp

    from hel_warp.collisions.cells import CellCollisions
    from kernels.cell_collide import FLUID_VOLUME_FLOOR, CellArgs, fill_fluid_volumes

    rng = np.random.default_rng(1)
    mask = (rng.random((7, 5, 6)) < 0.6).astype(np.int32)
    mask[:3, :2, :4] = 1  # a wholly fluid box for the unshifted lattice's first cell (2.7 x 1.9 x 3.3 mm)
    h, grid_origin = 1e-3, np.array([0.01, -0.02, 0.003])
    edges = np.array([2.7e-3, 1.9e-3, 3.3e-3])  # merged cells not aligned with the grid, reaching past it
    origin = grid_origin + np.array([0.0, 0.0, 0.0])
    for shift in (np.zeros(3), np.array([-1.1e-3, -0.4e-3, -2.0e-3])):
        shape = np.array([4, 5, 3])
        a = CellArgs()
        a.cell_fluid_volume = wp.zeros(int(np.prod(shape)), dtype=wp.float32, device=device)
        a.use_fluid = 1
        a.fluid_integral = CellCollisions().fluid_integral(wp.array(mask, device=device), device)
        a.fluid_origin, a.fluid_spacing = tuple(grid_origin), h
        a.origin, a.cell_size, a.shape = tuple(origin + shift), tuple(edges), tuple(int(v) for v in shape)
        a.cell_volume = float(np.prod(edges))
        fill_fluid_volumes(a)
        got = a.cell_fluid_volume.numpy()
        full = float(np.prod(edges))
        floored = 0
        for cell in range(len(got)):
            idx = np.array([cell // (shape[1] * shape[2]), (cell // shape[2]) % shape[1], cell % shape[2]])
            lo = origin + shift + idx * edges
            fluid = box_fluid_volume(lo, lo + edges, mask, grid_origin, h)
            want = full if fluid >= full * (1 - 1e-6) else max(fluid, FLUID_VOLUME_FLOOR * full)
            floored += fluid < FLUID_VOLUME_FLOOR * full
            assert got[cell] == pytest.approx(want, rel=1e-6, abs=1e-6 * full), cell
        assert floored > 0
    assert got[0] < full and a.cell_fluid_volume.numpy()[0] <= full
    # the unshifted lattice's first cell lies in the all-fluid corner: exactly the cell volume
    a.origin = tuple(origin)
    fill_fluid_volumes(a)
    assert a.cell_fluid_volume.numpy()[0] == np.float32(full)


def test_candidates_use_the_fluid_volume_and_fluid_grid_cells_keep_their_bits(constant_model, device):
    """A walled grid: merged collision cells count their parcels' density over the fluid volume inside them (the NTC
    candidates grow by V / V_fluid, against the overlap reference), and the plain lattice of grid cells (weight 1's)
    gives the same pairs and velocities with or without the fluid volumes."""
    import warp as wp

    from hel_warp.collisions.cells import CellConfig
    from hel_warp.collisions.models import SurrogateCollision
    from hel_warp.parcels.coupling import GridSpec

    h = 1e-3
    grid = GridSpec(origin=(0.0, 0.0, 0.0), spacing=h, shape=(12, 6, 6))
    mask = np.zeros(grid.shape, np.int32)
    mask[:, 1:4, 1:3] = 1  # a 3 x 2 mm channel along x
    rng = np.random.default_rng(3)
    n = 3000
    x = np.column_stack([rng.uniform(0.0, 12e-3, n), rng.uniform(1e-3, 4e-3, n), rng.uniform(1e-3, 3e-3, n)])

    def run(**cell):
        p = make_gas(n, 1.0, 8.0, np.random.default_rng(4), device)
        p.x.assign(x)
        s = SurrogateCollision(model_dir=constant_model, detection="cell", seed=2,
                               cell=CellConfig(max_substeps=1, enskog=False, log_capacity=200000, **cell))
        s._setup(p)
        s.cells.collide(p, 1e-4, s.forest, s.swept.domain, grid=grid, fluid=wp.array(mask, device=device))
        return s, p

    for fluid_volume in (True, False):  # merged 6^3 cells, unshifted: two cells hold the channel
        s, _ = run(coarsen=6, shift=False, fluid_volume=fluid_volume)
        m = s.cells._args.cell_candidates.numpy()
        if fluid_volume:
            with_fluid = m
        else:
            whole = m
    origin, edges, shape = s.cells.lattice
    occupied = np.flatnonzero(whole > 0)
    assert len(occupied) == 2
    for cell in occupied:
        idx = np.array([cell // (shape[1] * shape[2]), (cell // shape[2]) % shape[1], cell % shape[2]])
        lo = np.asarray(origin) + idx * np.asarray(edges)
        fluid = box_fluid_volume(lo, lo + np.asarray(edges), mask, np.zeros(3), h)
        assert fluid == pytest.approx(6 * 3 * 2 * h**3)
        assert with_fluid[cell] / whole[cell] == pytest.approx(float(np.prod(edges)) / fluid, rel=1e-5)
    # grid cells (weight 1's lattice): every occupied cell is all fluid, so nothing changes, bit for bit
    a, pa = run(coarsen=1, shift=False, fluid_volume=True)
    b, pb = run(coarsen=1, shift=False, fluid_volume=False)
    assert a.cells.counts()["cell_accepted"] > 100 and a.cells.counts()["cell_log_overflow"] == 0
    # the same events (the log's order across cells is the threads': on CUDA it varies from run to run)
    pairs_a, pairs_b = (np.unique(run_.cells.event_log()["pair"], axis=0) for run_ in (a, b))
    assert np.array_equal(pairs_a, pairs_b)
    assert np.array_equal(pa.v.numpy(), pb.v.numpy())


def approach_gas_frequency(model, device, steps=20, eps=0.05, weight=64.0, n=1000, dt=1e-3, approaching=True,
                           **cell):
    """Collisions of a dense gas of weighted parcels under the approach filter (``approaching``; False: plain NTC),
    the parcels flown ballistically between steps and their velocities changed by the collisions: the real
    collisions over the steps against Enskog's frequency at each step's own Theta, sum over sum."""
    rng = np.random.default_rng(11)
    side = box_side(n * weight, eps)
    p = make_gas(n, side, weight, rng, device)
    s = strategy(model, side, seed=5, approaching=approaching, **cell)
    real = expected = 0.0
    for _ in range(steps):
        v = p.v.numpy().astype(np.float64)
        theta = float(((v - v.mean(axis=0)) ** 2).sum() / (3 * n))
        expected += 0.5 * n * weight * 24.0 * eps * g0_cs(eps) * math.sqrt(theta) / (math.sqrt(math.pi) * D) * dt
        s.collide(p, dt)
        real += s.counts()["collisions"]
        s.correct_positions(p)
        p.x.assign(np.mod(p.x.numpy() + p.v.numpy() * dt, side).astype(np.float32))
    return real / expected


def test_approach_filter_keeps_enskogs_frequency_in_a_dense_weighted_gas(hard_sphere_model, device):
    """Weight 64 at eps_s = 0.05, dt = 1e-3 s (~1 collision per parcel and step), the dense end of the filter's use,
    20 steps from a Maxwellian. Pairs that have collided recede, and in a cell they recede from the cell-mates too,
    so fewer than half of a cell's pairs approach, and those more slowly than the rest. The filter's transfer (a
    receding accepted pair hands its collision to an approaching one of the cell) keeps the frequency of plain NTC
    (Bird's, exact for the homogeneous gas) and of Enskog; the doubled-rate rule (approaching pairs at twice the
    rate, one partner remembered, whole steps) loses ~15 % here, and with 16 partners and
    <= 0.25 events per sub-step ~6 %. The same with the collisional transfer; the old rules' losses
    were measured without it (the displacement moves a collided pair apart along its normal, which changes which
    pairs of a cell approach: the doubled-rate rule loses less with it), so that ordering is checked without."""
    for transfer in (True, False):
        plain = approach_gas_frequency(hard_sphere_model, device, approaching=False, collisional_transfer=transfer)
        ratio = approach_gas_frequency(hard_sphere_model, device, collisional_transfer=transfer)
        assert 0.94 <= plain <= 1.03 and 0.94 <= ratio <= 1.03, (transfer, plain, ratio)
        assert abs(ratio - plain) <= 0.025, (transfer, plain, ratio)
    doubled = approach_gas_frequency(hard_sphere_model, device, approach_redraw=0, collisional_transfer=False)
    old = approach_gas_frequency(hard_sphere_model, device, approach_redraw=0, approach_memory=1, approach_events=1e9,
                                 collisional_transfer=False)
    assert old < doubled < ratio - 0.03, (old, doubled, ratio)


@pytest.mark.parametrize("wall_paths", [True, False])
def test_substep_paths_reflect_at_the_walls_as_the_push_does(constant_model, wall_paths):
    """A parcel heading into a wall within a step of 17 sub-steps, no partner in reach: with ``wall_paths`` its
    path turns at the wall in the sub-step that crosses it, so that the sub-steps after sample it on its side of the
    wall, moving away. Reference: the reflection law written out by hand (v' = -e_n v_n + e_t v_t, the path
    mirrored with e_n about the contact plane a radius from the wall: x = wall - e_n v_n (dt - t_hit), the tangential
    motion at its old speed to the end of the crossing sub-step, as the push's reflection); a parcel
    flying parallel to the wall moves by v dt. Without ``wall_paths`` (the earlier rule) the path runs straight
    through the wall, for the push's end-of-step reflection."""
    from hel_warp.collisions.cells import CellConfig
    from hel_warp.collisions.models import SurrogateCollision
    from kernels.free_flight import drift
    from tests.test_collision_models import make_particles
    from tests.test_swept_walls import E_WALL, SIDE
    from tests.test_wall_contact import surface_walls

    r, dt, u, w = 0.5 * D, 1e-3, 4.0, 1.0
    wall = SIDE - r  # the contact plane of a surface that meets the wall at x = SIDE
    xa0 = wall - 0.5e-3
    x = [[xa0, 0.005, 0.005], [0.002, 0.002, 0.002]]
    v = [[u, w, 0.0], [0.0, 3.0, 0.0]]
    p = make_particles(x, v)
    s = SurrogateCollision(model_dir=constant_model, detection="cell", seed=1,
                           cell=CellConfig(cell_size=2e-3, cfl=0.125, wall_paths=wall_paths, packing_stress=False))
    s.set_walls(*surface_walls())
    s.collide(p, dt)
    assert s.cells.substeps == math.ceil(math.hypot(u, w) * dt / 0.25e-3)  # 17
    c = s.counts()
    assert c["collisions"] == 0
    drift(p.x, p.v, p.alive, dt)
    s.correct_positions(p)
    xs, vs = p.x.numpy().astype(np.float64), p.v.numpy().astype(np.float64)
    np.testing.assert_allclose(xs[1], [0.002, 0.002 + 3.0 * dt, 0.002], rtol=0, atol=2e-8)
    if wall_paths:
        t_hit = (wall - xa0) / u
        assert c["cell_wall_hits"] == 1
        np.testing.assert_allclose(vs[0], [-E_WALL * u, E_WALL * w, 0.0], rtol=1e-5)
        # the reflection mirrors the depth past the plane along the normal only (kernels/reflect.py, as the push):
        # the tangential motion keeps its old speed to the end of the sub-step that crossed
        h = dt / s.cells.substeps
        t_sub = math.ceil(t_hit / h) * h
        np.testing.assert_allclose(xs[0], [wall - E_WALL * u * (dt - t_hit), 0.005 + w * t_sub + E_WALL * w *
                                           (dt - t_sub), 0.005], rtol=0, atol=2e-8)
    else:
        assert c["cell_wall_hits"] == 0
        np.testing.assert_allclose(vs[0], v[0], rtol=0)
        np.testing.assert_allclose(xs[0], np.asarray(x[0]) + np.asarray(v[0]) * dt, rtol=0, atol=2e-8)
        assert xs[0, 0] > wall  # through the wall until the push reflects it


def transfer_step(model, device, weights, dt, seed=3, n=1500, eps=0.05):
    """One collision step with the collisional transfer of a periodic gas (one sub-step), then the caller's
    x += v dt and ``correct_positions``: (displacement x_end - x_start - v_end dt of each parcel (nearest image),
    v_start, v_end, weights, event log, side)."""
    from kernels.free_flight import drift

    rng = np.random.default_rng(seed)
    w = rng.choice(weights, size=n)
    side = box_side(w.sum(), eps)
    p = make_gas(n, side, w, np.random.default_rng(seed + 1), device)
    x0, v0 = p.x.numpy().astype(np.float64), p.v.numpy().astype(np.float64)
    s = strategy(model, side, seed=9, log=20000, cfl=1e3, collisional_transfer=True)
    s.collide(p, dt)
    assert s.cells.substeps == 1
    assert s.counts()["cell_log_overflow"] == 0
    drift(p.x, p.v, p.alive, dt)
    s.correct_positions(p)
    x1, v1 = p.x.numpy().astype(np.float64), p.v.numpy().astype(np.float64)
    moved = x1 - x0 - v1 * dt
    moved -= side * np.round(moved / side)
    return moved, v0, v1, w, s.cells.event_log(), side


def test_collisional_transfer_moves_each_pair_apart_by_its_share_of_the_collision_virial(hard_sphere_model, device):
    """The consistent Boltzmann algorithm's displacement (Alexander, Garcia & Alder 1995; ``transfer_scale``): the
    momentum is unchanged; each event moves parcel i back along its sampled normal and j on, by
    c d m_other / (m_i + m_j) w_min / w, with c = J.n / (mu g'_n) = (1 + e) / e for the hard-sphere forest
    (J.n = mu (1 + e) g_n, g'_n = e g_n): written out by hand from the event log; the mass-weighted centre sum w m x
    does not move, nor does momentum change. On by default, with the approach filter too;
    the filter is on by default where a parcel weighs more than 1."""
    from hel_warp.collisions.cells import CellConfig

    assert CellConfig().transfer and CellConfig(approaching=True).transfer
    assert not CellConfig().approaching_at(1.0) and CellConfig().approaching_at(8.0)
    assert not CellConfig(approaching=False).approaching_at(64.0) and CellConfig(approaching=True).approaching_at(1.0)
    assert CellConfig(approaching=True, collisional_transfer=True).transfer
    assert not CellConfig(collisional_transfer=False).transfer
    moved, v0, v1, w, log, side = transfer_step(hard_sphere_model, device, [1.0, 8.0], 1e-3)
    assert np.abs((w[:, None] * (v1 - v0)).sum(axis=0)).max() <= 1e-6 * (w[:, None] * np.abs(v0)).sum()
    pairs, normal = log["pair"].astype(int), log["normal"].astype(np.float64)
    assert len(pairs) > 300
    c = (1.0 + E) / E
    expected = np.zeros_like(moved)
    for (i, j), nrm in zip(pairs, normal):
        w_min = min(w[i], w[j])
        expected[i] -= nrm * c * D * 0.5 * w_min / w[i]  # equal masses: each a half of c d
        expected[j] += nrm * c * D * 0.5 * w_min / w[j]
    assert np.abs(expected).max() > D  # a full weight-1 share is c d / 2 = 1.06 d
    np.testing.assert_allclose(moved, expected, rtol=0, atol=2e-8)  # float32 positions of a ~4 mm box
    np.testing.assert_allclose((w[:, None] * moved).sum(axis=0), 0.0, rtol=0, atol=2e-8 * w.sum())


def test_collisional_transfer_carries_enskogs_collisional_pressure(hard_sphere_model, device):
    """The momentum the displacements carry, P_c = sum_k m_k v_k' . dx_k / (3 V dt) over the parcels (v' after the
    step), against Enskog's collisional pressure of smooth inelastic spheres, p_c = 2 (1 + e) eps^2 rho_p g0 Theta
    (Lun et al. 1984; docs/physics/references.md "Enskog collision frequency") with the gas's own Theta. A short step (0.05
    events per parcel) so that few parcels collide twice (their second v' then stands for both displacements,
    about -2 %); the fresh box's positions are Poisson's, not the structured ones the transfer's pair count
    N (N - 1) + (1 - S) k N assumes, so its first step collides ~(1 - S) k / 16 = 1.5 % too often: 3 % allowed for
    the two; 4 standard errors of the event count besides. (c = 1 + e, the
    displacement that follows the real pair's trajectory, would carry e of it: 0.9.)"""
    eps, dt = 0.05, 2e-5
    m = RHO * math.pi * D**3 / 6.0
    flux = expected = events = 0.0
    for rep in range(24):
        moved, vin, v1, w, log, side = transfer_step(hard_sphere_model, device, [1.0], dt, seed=20 + rep, n=8000,
                                                     eps=eps)
        flux += float((m * np.einsum("ij,ij->i", v1, moved)).sum()) / (3.0 * side**3 * dt)
        theta = float(((vin - vin.mean(axis=0)) ** 2).sum() / (3 * len(vin)))
        expected += 2.0 * (1.0 + E) * eps**2 * RHO * g0_cs(eps) * theta
        events += len(log["pair"])
    assert events > 4000
    assert abs(flux / expected - 1.0) <= 4.0 / math.sqrt(events) + 0.03, flux / expected


def test_live_extremes_on_the_device_equal_numpys_over_the_live_parcels(device):
    """``kernels/interp.py`` ``live_extremes`` (``Particles.live_extremes``: what the cell step reads back instead
    of four arrays): max |v| equals numpy's float64 norm of the float32 velocities bit for bit on the CPU (within 1 ulp
    elsewhere: a GPU may fuse), the largest weight and radius and the count of the live parcels exactly; dead parcels
    (here the fastest, heaviest and largest) are left out; a live NaN or inf is counted apart."""
    import warp as wp

    from kernels.interp import launch_live_extremes

    rng = np.random.default_rng(7)
    n = 5000
    v = rng.normal(0.0, 3.0, (n, 3)).astype(np.float32)
    w = rng.uniform(1.0, 64.0, n).astype(np.float32)
    r = rng.uniform(1e-4, 3e-4, n).astype(np.float32)
    alive = (rng.random(n) < 0.7).astype(np.int32)
    dead = np.flatnonzero(alive == 0)[:3]
    v[dead[0]] = 100.0
    w[dead[1]] = 1000.0
    r[dead[2]] = 1.0
    out = wp.zeros(5, dtype=wp.float64, device=device)
    for _ in range(2):  # zeroed by the launch: a second call gives the same
        launch_live_extremes(wp.array(v, dtype=wp.vec3, device=device), wp.array(w, dtype=wp.float32, device=device),
                             wp.array(r, dtype=wp.float32, device=device),
                             wp.array(alive, dtype=wp.int32, device=device), out)
    got = out.numpy()
    live = alive.astype(bool)
    v_max = float(np.linalg.norm(v[live].astype(np.float64), axis=1).max())
    if wp.get_device(device).is_cpu:
        assert got[0] == v_max
    else:
        assert got[0] == pytest.approx(v_max, rel=2.3e-16)
    assert got[1] == float(w[live].max()) and got[2] == float(r[live].max())
    assert got[3] == float(live.sum()) and got[4] == 0.0
    v[np.flatnonzero(live)[5]] = np.nan  # a live NaN: a maximum passes it over, the fifth slot counts it
    w[np.flatnonzero(live)[6]] = np.inf
    launch_live_extremes(wp.array(v, dtype=wp.vec3, device=device), wp.array(w, dtype=wp.float32, device=device),
                         wp.array(r, dtype=wp.float32, device=device), wp.array(alive, dtype=wp.int32, device=device),
                         out)
    assert out.numpy()[4] == 2.0


def test_a_nan_velocity_stops_the_cell_collisions_with_a_clear_error(constant_model, device):
    """A live parcel with a NaN velocity: ``SurrogateCollision.collide`` (cell detection) raises HelWarpError
    naming it, instead of stepping on (the device reduction's maximum passes a NaN over)."""
    from hel_warp.collisions.models import SurrogateCollision
    from hel_warp.errors import HelWarpError

    rng = np.random.default_rng(3)
    p = make_gas(512, 4e-3, 8.0, rng, device)
    v = p.v.numpy()
    v[7] = np.nan
    p.v.assign(v)
    strategy = SurrogateCollision(model_dir=constant_model, detection="cell", periodic_box=(4e-3,) * 3, seed=1)
    with pytest.raises(HelWarpError, match="NaN or infinite velocity"):
        strategy.collide(p, 1e-4)


def _grid_gas_collisions(model, device, slabs, local, reps=10, weight=64.0, eps=0.05, dt=2e-4, seed=21):
    """Weight-64 parcels in a 20 mm periodic box of 1 mm HEL cells, the collision cells the 10 mm merged ones
    (k = 10, unshifted: two per axis, whole); eps_s = 0.05 over the box, or (``slabs``) the same parcels in the
    slabs x mod 10 mm < 5 mm, so at 0.10 in half of each collision cell. The coupling's deposit and interpolation
    give each parcel its eps_s (``CouplingFields.parcel_eps_s``). One step from a Maxwellian per repetition, the
    collisions applied: real collisions over all repetitions and over Enskog's at the occupied solids fraction
    (1/2 n omega dt per real particle); and the parcel events behind them."""
    import warp as wp
    from types import SimpleNamespace

    from hel_warp.collisions.cells import CellConfig
    from hel_warp.collisions.models import SurrogateCollision
    from hel_warp.parcels.coupling import CouplingFields, GridSpec, deposit_parcels, parcel_grid
    from kernels.interp import interpolate_scalar_parcels

    side, h = 20e-3, 1e-3
    grid = GridSpec(origin=(0.0, 0.0, 0.0), spacing=h, shape=(20, 20, 20), periodic=(True, True, True))
    n = int(round(eps * side**3 / (weight * math.pi * D**3 / 6.0)))
    rng = np.random.default_rng(seed)
    occupied = 2.0 * eps if slabs else eps
    real = expected = 0.0
    for rep in range(reps):
        p = make_gas(n, side, weight, rng, device)
        if slabs:
            x = p.x.numpy()
            x[:, 0] = np.floor(x[:, 0] / 10e-3) * 10e-3 + np.mod(x[:, 0], 10e-3) * 0.5
            p.x.assign(x)
        fields = CouplingFields.allocate(grid, n, device=device)
        deposit_parcels(grid, p, fields)
        eps_at = wp.zeros(n, dtype=float, device=device)
        interpolate_scalar_parcels(parcel_grid(grid, fields), p.x, p.weight, fields.cell_eps_s, eps_at)
        s = SurrogateCollision(model_dir=model, seed=seed + rep, detection="cell",
                               cell=CellConfig(coarsen=10, shift=False, local_density=local, max_substeps=1))
        solver = SimpleNamespace(grid=grid, pool=SimpleNamespace(particles=p), config=SimpleNamespace(dt=dt),
                                 fields=SimpleNamespace(parcel_a_coll=wp.zeros(n, dtype=wp.vec3, device=device),
                                                        parcel_eps_s=eps_at, cloud_on=fields.cloud_on,
                                                        parcel_cloud=fields.parcel_cloud))
        v = p.v.numpy().astype(np.float64)
        theta = float(((v - v.mean(axis=0)) ** 2).sum() / (3 * n))
        s.accelerate(solver)
        real += s.counts()["collisions"]
        omega = 24.0 * occupied * g0_cs(occupied) * math.sqrt(theta) / (math.sqrt(math.pi) * D)
        expected += 0.5 * n * weight * omega * dt
    return real / expected, real / weight


def test_merged_cells_collide_at_the_solids_fraction_around_the_parcels(hard_sphere_model, device):
    """Merged collision cells (heavy parcels on a HEL grid) average the number density over their volume and lose
    the collisions of structure inside them: parcels packed into half of each 10 mm cell collide at 0.44 of the rate
    of their own density (Enskog at eps_s 0.10 against 0.05) with the cell's mean. With ``local_density`` a pair's
    rate takes the coupling's deposited eps_s around its two parcels, less each parcel's own share: the uniform gas
    keeps Enskog's frequency (its own share would count a parcel as its own partner), and the slabs collide at more
    than the cell mean gives (0.80 over 30 repetitions) and at most at their own density's rate (the deposit smooths
    the slabs' edges)."""
    for local in (False, True):
        ratio, events = _grid_gas_collisions(hard_sphere_model, device, slabs=False, local=local)
        assert abs(ratio - 1.0) <= 4.0 / math.sqrt(events), (local, ratio, events)
    plain, events = _grid_gas_collisions(hard_sphere_model, device, slabs=True, local=False)
    mean_field = 0.5 * g0_cs(0.05) / g0_cs(0.10)  # the cell mean's rate over the slabs' own
    assert abs(plain / mean_field - 1.0) <= 4.0 / math.sqrt(events), (plain, mean_field)
    ratio, events = _grid_gas_collisions(hard_sphere_model, device, slabs=True, local=True)
    print(f"slabs: {plain:.3f} (cell mean) and {ratio:.3f} (local) of their own density's rate")
    assert mean_field + 0.2 < ratio <= 1.0 + 4.0 / math.sqrt(events), (ratio, mean_field)
