"""A weight per species: ``--particles-per-parcel W1,W2`` in the cooling case and the rig, and the
cell detection's collisions between parcels of unequal weight (kernels/cell_collide.py, ``cell_restore``).

References (docs/developer/conventions.md rule 9):

- the real particles and their mass are those asked for, whatever the weights: N_k real = parcels_k x W_k;
- energy of an event between parcels of weights w_i != w_j: w_min real binary collisions with the impulse J of the
  representative pair change the kinetic energy by w_min (-J.g + |J|^2 / (2 mu)), g = v_i - v_j, mu the reduced
  mass of one particle each; the momentum-exact partial impulse alone (Boyd 1996) changes it by
  -w_min J.g + (w_min |J|)^2 / 2 (1/(w_i m_i) + 1/(w_j m_j)), i.e. loses w_min (1 - w_min/w) |J|^2 / (2 m) more for
  the heavier parcel: exact identities, checked to float32 round-off (J recovered from the velocity changes);
- the collision frequency of each pair type per real particle: the Enskog rate of a binary mixture
  n_i n_j g0_ij pi sigma_ij^2 sqrt(8/pi) sqrt(Theta_i + Theta_j) (the cooling case's kinetic theory, BMCSL g0), within
  4 standard errors of the parcel events (1/sqrt(C/min(W_i, W_j)));
- weight invariance: the species temperatures of a mixture of weights 1 and 8 follow those of weight 1 to 10 %
  (seed scatter plus the scheme's residual 3-5 %; without the energy put back the heavier species cooled several
  times too fast).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from tests.test_cell_collisions import make_gas, strategy
from tests.test_mixture import _rig_args, live_parcels
from tests.test_particle_spin import rough_constant_model  # noqa: F401 (a fixture)
from tests.test_swept import write_constant_contact_forest

ROOT = Path(__file__).resolve().parents[1]
D1, D2 = 315e-6, 475e-6
RHO = 1000.0


@pytest.fixture(scope="module")
def hc():
    from hel_warp.cli.commands._common import load_case_module

    return load_case_module(str(ROOT / "cases" / "homogeneous_cooling.py"))


@pytest.fixture(scope="module")
def cs():
    from hel_warp.cli.commands._common import load_case_module

    return load_case_module(str(ROOT / "cases" / "colliding_streams.py"))


@pytest.fixture(scope="module")
def constant_mixture_model(tmp_path_factory):
    """The constant contact-form forest of tests/test_swept.py (impulse_n = 1 + e, the guard for oblique impacts) with
    a metadata.json whose domain holds both sizes, so that the cooling case takes it as a mixture model."""
    root = tmp_path_factory.mktemp("constant_mixture_model")
    write_constant_contact_forest(root)
    meta = {"form": "contact", "material": {"density": RHO, "restitution": 0.9, "friction": 0.0},
            "defaults": {"d1": 0.5 * (D1 + D2), "d2": 0.5 * (D1 + D2), "rho1": RHO, "rho2": RHO},  # as train writes
            "domain": {"features": ["g_n", "g_t", "cos_angle", "d1", "size_ratio", "density_ratio"],
                       "lo": [0.0, 0.0, 0.0, 1e-6, 0.1, 0.1], "hi": [100.0, 100.0, 1.0, 1e-2, 10.0, 10.0]}}
    (root / "metadata.json").write_text(json.dumps(meta))
    return str(root)


# ------------------------------------------------------------------------------------------ the option
def test_weights_option_one_or_two_integers():
    from hel_warp.errors import ConfigError
    from hel_warp.collisions.mixture import species_weights

    assert species_weights("8", 2) == (8, 8) and species_weights("1,8", 2) == (1, 8)
    assert species_weights(" 8 , 1 ", 2) == (8, 1) and species_weights(1.0, 1) == (1,)
    assert species_weights("8.0", 1) == (8,)  # the rig's scripts pass floats
    for bad, needle in [("0", "integer >= 1"), ("1.5", "integer >= 1"), ("x", "integer >= 1"), ("1,,8", "two values"), (",8", "integer"),
                        ("1,8,2", "two values"), ("inf", "integer")]:
        with pytest.raises(ConfigError, match=needle):
            species_weights(bad, 2)
    with pytest.raises(ConfigError, match="need a second size"):
        species_weights("1,8", 1)


COOLING = ["--collisions", "none", "--dt", "1e-4", "--solids-fraction", "0.01", "--particles", "800", "--diameter",
           str(D1), "--granular-temperature", "1", "--end-time", "2e-4"]
MIXTURE = ["--diameter2", str(D2), "--number-fraction2", "0.3"]


@pytest.mark.parametrize("extra,needle", [
    (["--particles-per-parcel", "1,8"], "need a second size"),
    (MIXTURE + ["--particles-per-parcel", "0,8"], "integer >= 1"),
    (MIXTURE + ["--particles-per-parcel", "1,8,8"], "two values"),
    (MIXTURE + ["--particles-per-parcel", "3,8"], "W1 = 3 does not divide the 560 particles of species 1"),
    (MIXTURE + ["--particles-per-parcel", "1,7"], "W2 = 7 does not divide the 240 particles of species 2"),
    (MIXTURE + ["--particles-per-parcel", "1,8", "--collisions", "dem"], "resolves real spheres"),
])
def test_cooling_bad_weights_are_one_line_exit_2(hc, capsys, tmp_path, extra, needle):
    code = hc.main([*COOLING, *extra, "--out", str(tmp_path / "bad")])
    err = [line for line in capsys.readouterr().err.strip().splitlines() if line and "CUDA" not in line]
    assert code == 2 and len(err) == 1 and needle in err[0] and "error" in err[0], err
    assert not (tmp_path / "bad").exists()


@pytest.mark.parametrize("extra,needle", [
    (["--particles-per-parcel", "1,8"], "need a second size"),
    (["--particles-per-parcel", "0.5"], "integer >= 1"),
    (["--diameter2", str(D2), "--mass-fraction2", "0.5", "--particles-per-parcel", "2,4,8"], "two values"),
])
def test_rig_bad_weights_are_one_line_exit_2(cs, capsys, tmp_path, extra, needle):
    argv = ["--diameter", str(D1), "--dt", "1e-3", "--collisions", "none", "--end-time", "0.003", "--out",
            str(tmp_path / "bad"), "--no-progress", *extra]
    code = cs.main(argv)
    err = [line for line in capsys.readouterr().err.strip().splitlines() if line and "CUDA" not in line]
    assert code == 2 and len(err) == 1 and needle in err[0], err
    assert not (tmp_path / "bad").exists()


# ------------------------------------------------------------------------------------------ what reaches the parcels
@pytest.mark.parametrize("weights", [(1, 8), (8, 1), (4, 4)])
def test_cooling_parcels_carry_their_species_weight(hc, tmp_path, weights):
    """N_k real particles as asked (round(F N) of D2), parcels_k = N_k / W_k, each parcel of species k of weight W_k;
    the box and the real mass those of the N real particles; the mixture's Theta is exactly Theta0 at the start."""
    import argparse

    from hel_warp._warp import init_warp

    parser = argparse.ArgumentParser()
    hc.add_arguments(parser)
    args = parser.parse_args([*COOLING, *MIXTURE, "--particles-per-parcel", ",".join(map(str, weights)), "--out",
                              str(tmp_path / "x")])
    config = hc.make_config(args)
    n2 = round(0.3 * 800)
    assert config.species.counts == (800 - n2, n2) and config.weights == weights
    assert config.species.parcels == ((800 - n2) // weights[0], n2 // weights[1])
    assert config.parcels == sum(config.species.parcels)
    assert config.box_length == pytest.approx((math.pi * ((800 - n2) * D1**3 + n2 * D2**3) / (6 * 0.01)) ** (1 / 3))
    init_warp("cpu")
    sim, record = built_box(hc, args)
    particles = sim.solver.particles
    w = particles.weight.numpy().astype(np.float64)
    species = particles.stream.numpy()
    d = 2.0 * particles.radius.numpy().astype(np.float64)
    for k, dk in enumerate((D1, D2)):
        own = species == k
        assert int(own.sum()) == config.species.parcels[k] and np.all(w[own] == weights[k])
        assert np.allclose(d[own], dk, rtol=1e-6)
        assert w[own].sum() == config.species.counts[k]  # real particles of species k
    mass = (w * RHO * math.pi / 6.0 * d**3).sum()
    assert mass == pytest.approx(RHO * math.pi / 6.0 * ((800 - n2) * D1**3 + n2 * D2**3), rel=1e-5)
    assert record.theta()[0] == pytest.approx(1.0, rel=1e-5)  # the mass-weighted mixture Theta of the start
    v = particles.v.numpy().astype(np.float64)
    big_m = w * d**3  # zero momentum, to the float32 rounding of the velocities
    assert np.abs((big_m[:, None] * v).sum(axis=0)).max() <= 1e-6 * (big_m * np.linalg.norm(v, axis=1)).sum()


def built_box(hc, args):
    """The cooling box of ``args`` built through the case API (``hel_warp.case.build``), with the case's record of
    the velocity moments bound to it (its row 0: the start)."""
    from hel_warp.case.build import build

    flow = hc.CASE.build(args)
    record = hc.CoolingRecorder(args._cooling)
    sim = build(flow, hc.CASE.settings(args, flow), observers=[record])
    record.bind(sim)
    return sim, record


def test_cooling_summary_states_each_species_weight(hc, capsys, tmp_path):
    code = hc.main([*COOLING, *MIXTURE, "--particles-per-parcel", "1,8", "--json", "--no-progress", "--out",
                    str(tmp_path / "run")])
    s = json.loads(capsys.readouterr().out)
    assert code == 0 and s["check_errors"] == []
    assert s["particles_per_parcel"] == [1, 8] and s["species"]["particles_per_parcel"] == [1, 8]
    assert s["species"]["particles"] == [560, 240] and s["species"]["parcels"] == [560, 30] and s["parcels"] == 590
    assert s["particles"] == 800


def _rig_config(cs, *extra):
    import argparse

    parser = argparse.ArgumentParser()
    cs.add_arguments(parser)
    return cs.make_config(parser.parse_args(["--diameter", str(D1), "--dt", "1e-3", "--collisions", "none",
                                             "--end-time", "0.003", "--out", "unused", "--diameter2", str(D2),
                                             "--mass-fraction2", "0.5", *extra]))


def test_rig_mixture_keeps_the_real_mass_at_any_weights(cs):
    """50/50 by mass: the real particles per species (6,000 / 1,742 at weight 1) stay, parcels = real / W_k; the mass
    split and the Sauter mean (of the real particles) stay; cell detection by default once a weight exceeds 1."""
    one = _rig_config(cs)
    for weights in ("1,8", "8,1", "8"):
        c = _rig_config(cs, "--particles-per-parcel", weights)
        w1, w2 = c.weights()
        assert (c.particles, c.particles2) == (round(one.particles / w1), round(one.particles2 / w2))
        real = [c.particles * w1, c.particles2 * w2]
        assert real[0] == pytest.approx(one.particles, rel=0.01) and real[1] == pytest.approx(one.particles2, rel=0.01)
        assert cs.sauter_mean_of(c) == pytest.approx(cs.sauter_mean_of(one), rel=1e-3)
        assert c.detection == "cell" and c.mass_flow == one.mass_flow
    one_size = cs.make_config(_rig_args(cs, "--particles-per-parcel", "8"))
    assert one_size.particles == 12000 and one_size.weights() == [8.0]  # one size: the parcel count stays


def test_rig_holders_release_each_species_with_its_weight(cs):
    """A reduced rig at weights 1,8: after the release window every holder has put out its parcels of each species,
    each of its species' weight; the window is the holder's real mass over its mass flow; the layout and the
    summary fields name the weights."""
    from hel_warp.collisions.mixture import species_of

    config = _rig_config(cs, "--particles-per-parcel", "1,8", "--cells", "5000", "--max-particles", "120")
    rig = cs.CollidingStreams(config)
    S1, S2 = cs.PAPER_DIAMETER_STD[315e-6], cs.PAPER_DIAMETER_STD[475e-6]
    for side in (0, 1):
        holder_mass = sum((n // 2 if side == 0 else n - n // 2) * w * RHO * math.pi / 6 * (d**3 + 3 * d * sd**2)
                          for (d, sd, n), w in zip(config.species(), config.weights()))
        assert rig.release_window[side] == pytest.approx(holder_mass / config.mass_flow[side], rel=1e-9)
    while rig.solver.time < max(rig.release_window) + 1e-9:
        rig.step()
    snap = live_parcels(rig)
    kind = species_of(2.0 * snap["radius"], [D1, D2], [S1, S2])
    for k, (n, w) in enumerate(zip((config.particles, config.particles2), (1.0, 8.0))):
        assert np.all(snap["weight"][kind == k] == w)
        for side in (0, 1):
            assert int(np.sum((kind == k) & (snap["stream"] == side))) == (n // 2 if side == 0 else n - n // 2)
    assert [c["particles_per_parcel"] for c in rig.rig_layout()["size_classes"]] == [1.0, 8.0]
    assert cs.check(rig) == []


# ------------------------------------------------------------------------------------------ unequal-weight events
def _mixed_gas(device, seed, n=3000, eps=0.05):
    """n parcels, half 315 um of weight 1 and half 475 um of weight 8, uniformly in a periodic box at real eps."""
    from hel_warp.parcels.particles import Particles

    rng = np.random.default_rng(seed)
    species = rng.integers(0, 2, size=n)
    d = np.where(species == 0, D1, D2)
    w = np.where(species == 0, 1.0, 8.0)
    side = (float((w * math.pi * d**3 / 6.0).sum()) / eps) ** (1.0 / 3.0)
    x = rng.uniform(0.0, side, size=(n, 3))
    v = rng.normal(0.0, 1.0, size=(n, 3)) / ((d / D1) ** 1.5)[:, None]  # equipartition: Theta ~ 1/m
    m = w * d**3
    v -= (m[:, None] * v).sum(axis=0) / m.sum()
    p = Particles.from_numpy(x, 0.5 * d, v=v, density=RHO, weight=w, stream=species, check_overlap=False,
                             device=device)
    return p, side


def _one_step(model, device, seed, restore, dt):
    """One collision step of one sub-step (the events do not depend on the energy put back after it)."""
    from hel_warp.collisions.cells import CellConfig
    from hel_warp.collisions.models import SurrogateCollision

    p, side = _mixed_gas(device, seed)
    s = SurrogateCollision(model_dir=model, detection="cell", periodic_box=(side,) * 3, seed=seed,
                           cell=CellConfig(log_capacity=256, max_substeps=1, restore_energy=restore))
    before = p.v.numpy().astype(np.float64)
    s.collide(p, dt)
    return p, before, p.v.numpy().astype(np.float64), s.counts(), s.cells.event_log()


def test_unequal_weights_keep_the_energy_of_the_real_collisions(constant_mixture_model, device):
    """Events between weights 1 and 8 (and 1-1, 8-8): with the energy put back, the kinetic energy changes exactly as
    w_min real binary collisions would; without it, as the partial impulses alone (more loss, by the deficit);
    momentum exact in both. J of each event is read from its parcels' velocity changes in the run without the
    restoration (a seed whose events share no parcel, so each parcel took one impulse)."""
    dt = 2e-6
    for seed in range(40):
        p, v0, v_off, c_off, log = _one_step(constant_mixture_model, device, seed, False, dt)
        pairs = log["pair"]
        if 8 <= len(pairs) and len(np.unique(pairs)) == pairs.size:
            break
    else:
        pytest.fail("no seed with 8+ events of distinct parcels")
    w = p.weight.numpy().astype(np.float64)
    m = RHO * math.pi / 6.0 * (2.0 * p.radius.numpy().astype(np.float64)) ** 3  # one real particle
    big_m = w * m

    def energy(v):
        return 0.5 * float((big_m * (v**2).sum(axis=1)).sum())

    def momentum(v):
        return (big_m[:, None] * v).sum(axis=0)

    real = partial = deficit = 0.0
    mixed = 0
    for (i, j), g in zip(pairs, log["g"].astype(np.float64)):
        w_min = min(w[i], w[j])
        J = (v_off[j] - v0[j]) * big_m[j] / w_min  # the impulse of one real pair, on j
        assert np.allclose(J, -(v_off[i] - v0[i]) * big_m[i] / w_min, rtol=1e-4, atol=1e-12)
        mu = m[i] * m[j] / (m[i] + m[j])
        j2 = float(J @ J)
        real += w_min * (-float(J @ g) + j2 / (2.0 * mu))
        partial += -w_min * float(J @ g) + 0.5 * w_min**2 * j2 * (1.0 / big_m[i] + 1.0 / big_m[j])
        deficit += sum(w_min * (1.0 - w_min / w[k]) * j2 / (2.0 * m[k]) for k in (i, j))
        mixed += w[i] != w[j]
    assert mixed >= 3 and deficit > 0.0
    assert partial == pytest.approx(real - deficit, rel=1e-9)  # the algebra of the docstring
    scale = energy(v0)
    assert real < 0.0  # the guarded outcome dissipates
    assert energy(v_off) - energy(v0) == pytest.approx(partial, abs=1e-3 * abs(partial) + 1e-7 * scale)
    p_on, v0_on, v_on, c_on, log_on = _one_step(constant_mixture_model, device, seed, True, dt)
    assert np.array_equal(log_on["pair"], pairs) and np.array_equal(v0_on, v0)  # the same events
    assert c_on["cell_unrestored"] == 0 and c_on["cell_restored"] >= 1 and c_off["cell_restored"] == 0
    assert energy(v_on) - energy(v0) == pytest.approx(real, abs=1e-3 * abs(real) + 1e-7 * scale)
    speed = float((big_m * np.linalg.norm(v0, axis=1)).sum())
    for v in (v_off, v_on):
        assert np.abs(momentum(v) - momentum(v0)).max() <= 1e-6 * speed
    # the restoration touches only the heavier class: the weight-1 parcels moved by their own impulses only
    light = w == 1.0
    assert np.array_equal(v_on[light], v_off[light])


def _repeats(model, device, seed, approaching):
    """Events of a weights 1 / 8 box (``_mixed_gas``, 3,000 parcels) over 5 steps of 2e-4 s: per kind of pair, the
    events whose two parcels had met before in the run, and all events."""
    from hel_warp.collisions.cells import CellConfig
    from hel_warp.collisions.models import SurrogateCollision

    p, side = _mixed_gas(device, seed)
    s = SurrogateCollision(model_dir=model, detection="cell", periodic_box=(side,) * 3, seed=seed,
                           cell=CellConfig(log_capacity=100000, approaching=approaching))
    w = p.weight.numpy()
    met, repeats, events = set(), {}, {}
    for _ in range(5):
        s.collide(p, 2e-4)
        for i, j in s.cells.event_log()["pair"]:
            pair, kind = (min(i, j), max(i, j)), tuple(sorted((int(w[i]), int(w[j]))))
            events[kind] = events.get(kind, 0) + 1
            repeats[kind] = repeats.get(kind, 0) + (pair in met)
            met.add(pair)
    return repeats, events


def test_approach_filter_meets_a_partner_again_as_often_as_ntc(constant_mixture_model, device):
    """A weighted pair that met is exempt from the filter's position test (its next real collision is with another
    particle of the partner's cloud), but such a particle approaches one time in two, so the pair must meet again
    about as often as Bird's NTC pairs do, which are drawn without memory. Counted over two seeds, pairs with a
    weight-8 parcel, share of the events that repeat a pair: plain NTC 5.6 % (1-8) and 6.9 % (8-8); the filter 7.3 %
    and 8.6 % (1.3x, ~0.1 of it the counts' scatter); always eligible 11.6 % and
    13.4 % (2.1x and 1.9x)."""
    share = {}
    for approaching in (False, True):
        totals = {}
        for seed in (0, 1):
            repeats, events = _repeats(constant_mixture_model, device, seed, approaching)
            for kind in ((1, 8), (8, 8)):
                r, e = totals.get(kind, (0, 0))
                totals[kind] = (r + repeats[kind], e + events[kind])
        share[approaching] = {kind: r / e for kind, (r, e) in totals.items()}
    for kind in ((1, 8), (8, 8)):
        assert share[False][kind] > 0.02  # NTC itself draws a pair again now and then (a few per cent here)
        assert share[True][kind] < 1.65 * share[False][kind], (kind, share)


def test_restoration_over_many_steps_momentum_exact_energy_never_grows(constant_mixture_model, device):
    """A denser gas of weights 1 and 8 over several steps (many events per parcel): sum w m v to float32 round-off,
    the kinetic energy never above the start (the guarded outcome dissipates; the deficit put back is no more than
    the partial impulse lost), nearly every class restored."""
    from hel_warp.collisions.cells import CellConfig
    from hel_warp.collisions.models import SurrogateCollision

    p, side = _mixed_gas(device, 11, n=2000)
    s = SurrogateCollision(model_dir=constant_mixture_model, detection="cell", periodic_box=(side,) * 3, seed=3,
                           cell=CellConfig())
    big_m = (p.weight.numpy() * (2.0 * p.radius.numpy()) ** 3).astype(np.float64)
    v0 = p.v.numpy().astype(np.float64)
    scale = float((big_m * np.linalg.norm(v0, axis=1)).sum())
    restored = unrestored = 0
    for _ in range(4):
        before = p.v.numpy().astype(np.float64)
        s.collide(p, 1e-3)
        after = p.v.numpy().astype(np.float64)
        c = s.counts()
        restored += c["cell_restored"]
        unrestored += c["cell_unrestored"]
        assert np.abs((big_m[:, None] * (after - before)).sum(axis=0)).max() <= 1e-6 * scale
        assert (big_m * (after**2).sum(axis=1)).sum() <= (big_m * (before**2).sum(axis=1)).sum() * (1.0 + 1e-6)
    assert restored > 100 and unrestored <= 0.01 * restored


def _weighted_box(seed, large_weight, hot_x=1.0):
    """A periodic box at real eps_s = 0.05 of 12,000 single 315 um particles and 2,400 real 475 um ones in parcels of
    ``large_weight``; Maxwellian velocities with Theta ~ 1/m and T_x = ``hot_x`` T_y = ``hot_x`` T_z, no net
    momentum. Returns (rng, d, w, side, x, v)."""
    rng = np.random.default_rng(seed)
    n_small, n_large = 12000, 2400 // large_weight
    d = np.r_[np.full(n_small, D1), np.full(n_large, D2)]
    w = np.r_[np.ones(n_small), np.full(n_large, float(large_weight))]
    side = (float((w * math.pi * d**3 / 6.0).sum()) / 0.05) ** (1.0 / 3.0)
    x = rng.uniform(0.0, side, size=(d.size, 3))
    v = rng.normal(0.0, 1.0, size=(d.size, 3)) * np.array([math.sqrt(hot_x), 1.0, 1.0]) / ((d / D1) ** 1.5)[:, None]
    m = w * d**3
    v -= (m[:, None] * v).sum(axis=0) / m.sum()
    return rng, d, w, side, x, v


def _sixteen_per_cell(side, parcels):
    """The edge of a cube holding 16 of the box's parcels: both weights' boxes in cells of ~16 parcels, where these
    figures were measured (the automatic cells of the weight-8 box are larger, sized so
    that a pair of the heaviest parcels does not saturate)."""
    return (side**3 * 16.0 / parcels) ** (1.0 / 3.0)


def _anisotropy_decay(model, device, large_weight, seed, steps=4, dt=2e-4):
    """``_weighted_box`` with T_x = 3 T_y = 3 T_z, collided ``steps`` steps of ``dt`` with ~13 sub-steps each
    (``cfl`` 0.05): the large class's T_x / T_yz - 1 after each step."""
    from hel_warp.collisions.cells import CellConfig
    from hel_warp.collisions.models import SurrogateCollision
    from hel_warp.parcels.particles import Particles

    _, d, w, side, x, v = _weighted_box(seed, large_weight, hot_x=3.0)
    p = Particles.from_numpy(x, 0.5 * d, v=v, density=RHO, weight=w, stream=(d > D1).astype(int),
                             check_overlap=False, device=device)
    s = SurrogateCollision(model_dir=model, detection="cell", periodic_box=(side,) * 3, seed=seed,
                           cell=CellConfig(cfl=0.05, cell_size=_sixteen_per_cell(side, d.size)))
    large = d > D1
    out = []
    for _ in range(steps):
        s.collide(p, dt)
        assert s.cells.substeps >= 8
        vl = p.v.numpy().astype(np.float64)[large]
        t = ((vl - vl.mean(axis=0)) ** 2).mean(axis=0)
        out.append(t[0] / (0.5 * (t[1] + t[2])) - 1.0)
    return np.array(out)


def test_heavier_class_relaxes_its_anisotropy_as_at_weight_one(constant_mixture_model, device):
    """Weight invariance of the velocity tensor, not only of the energy: the 475 um class of the box above relaxes
    its anisotropy T_x / T_yz - 1 (from 2) as the same real particles do at weight 1, in log over steps 2-4 and
    three seeds (seed scatter: 0.1 at weight 1, 0.15-0.2 at weight 8 per seed). The real collisions give the
    heavier parcel's particles the second moment w_min |J|^2 / m along J that its partial impulse keeps only
    w_min / w of; the restoration puts it back along J. A restoration that mirrors the parcels'
    velocities about random planes at every sub-step gives log decay -1.21 +- 0.21 at weights 1,8 against -0.40 +-
    0.03 at weight 1 (mean of 6-9 seeds); at these three seeds -1.54 against -0.34, and -0.49 along J (seed 1 an outlier: -0.29 +- 0.09 over seeds 0-8). The 0.3 allowed is ~2.7
    standard errors of the difference of two 3-seed means."""
    decay = {}
    for weight in (1, 8):
        decay[weight] = float(np.mean([np.log(_anisotropy_decay(constant_mixture_model, device, weight, seed)[1:])
                                       for seed in (0, 1, 2)]))
    assert decay[1] < 0.0, decay  # the weight-1 reference relaxes (from log 2 = 0.69)
    assert abs(decay[8] - decay[1]) < 0.3, decay


def _spin_decay(model, device, large_weight, seed, restore=True, steps=4, dt=2e-4):
    """``_weighted_box`` (isotropic velocities) with organised spins, omega = (xi + z^) 2 / d (xi
    normal, sd 0.5), the rough constant forest and ``particle_spin``: the large class's mean omega_z after ``steps``
    steps, over its start."""
    import warp as wp

    from hel_warp.collisions.cells import CellConfig
    from hel_warp.collisions.models import SurrogateCollision
    from hel_warp.parcels.particles import Particles

    rng, d, w, side, x, v = _weighted_box(seed, large_weight)
    omega = (rng.normal(0.0, 0.5, size=(d.size, 3)) + np.array([0.0, 0.0, 1.0])) * (2.0 / d)[:, None]
    p = Particles.from_numpy(x, 0.5 * d, v=v, density=RHO, weight=w, stream=(d > D1).astype(int),
                             check_overlap=False, device=device)
    p.omega.assign(wp.array(omega.astype(np.float32), dtype=wp.vec3, device=p.x.device))
    s = SurrogateCollision(model_dir=model, detection="cell", periodic_box=(side,) * 3, seed=seed, particle_spin=True,
                           cell=CellConfig(cfl=0.05, restore_energy=restore,
                                           cell_size=_sixteen_per_cell(side, d.size)))
    for _ in range(steps):
        s.collide(p, dt)
    large = d > D1
    return float(p.omega.numpy()[large, 2].astype(np.float64).mean() / omega[large, 2].mean())


def test_heavier_class_keeps_its_organised_spin_through_the_restoration(rough_constant_model, device):
    """The spin spread put back at unequal weights is a random kick about the parcel's spin: the 475 um class's mean
    spin (all spinning about z at the start) decays as it does with no spread put back (within 0.1, two seeds; seed
    scatter ~0.03), and within 0.2 of the same real particles at weight 1 (the partial spin impulses at weights 1,8
    keep 0.68 of it after 4 steps against 0.56 at weight 1, with or without the restoration: a residual of the
    weighting, not of the restoration). A restoration that mirrors omega about random planes leaves the class -0.04
    of its mean spin."""
    seeds = (0, 1)
    on = np.mean([_spin_decay(rough_constant_model, device, 8, seed) for seed in seeds])
    off = np.mean([_spin_decay(rough_constant_model, device, 8, seed, restore=False) for seed in seeds])
    one = np.mean([_spin_decay(rough_constant_model, device, 1, seed) for seed in seeds])
    assert 0.3 < one < 0.9, one  # collisions with friction turn the spins, and not all the way
    assert abs(on - off) < 0.1, (on, off)
    assert abs(on - one) < 0.2, (on, one)


# ------------------------------------------------------------------------------------------ the physics of a run
def _cool(hc, capsys, tmp_path, model, weights, particles=4000, extra=()):
    argv = ["--collisions", "surrogate", "--model", model, "--detection", "cell", "--dt", "1e-3", "--solids-fraction",
            "0.01", "--particles", str(particles), "--diameter", str(D1), *MIXTURE, "--granular-temperature", "1",
            "--end-time", "0.02", "--particles-per-parcel", weights, "--json", "--no-progress", *extra, "--out",
            str(tmp_path / (weights.replace(",", "_") + "".join(extra)))]
    code = hc.main(argv)
    out = capsys.readouterr()
    assert code == 0, out.err
    return json.loads(out.out)


@pytest.mark.parametrize("extra", [(), ("--no-cell-approaching",)])
def test_mixed_weights_collide_and_cool_as_weight_one(hc, capsys, tmp_path, constant_mixture_model, extra):
    """The same 4,000 real particles (315 / 475 um, 30 % large) at weights 1,1 and 1,8: per pair type the collisions
    per real particle against the mixture's Enskog rate within 4 standard errors, and each species' Theta at the end
    within 15 % of the weight-1 run. The 15 %: the scheme leaves the 475 um species too hot at mixed weights, by
    +6.5 +- 1.4 % at the default and +6.3 +- 1.1 % with --no-cell-approaching (seeds 0-8, per-seed scatter 3-4 %;
    +9.4 +- 1.1 % with the filter's met pairs always eligible), and the 315 um species 3-4 % too cold; a 10 %
    bound holds at seed 0 only by luck (seeds 3, 7 and 8 are 11-17 % off with met pairs always eligible). Without the energy put back the
    weight-8 species ended at 13 % of the weight-1 Theta and the other at 60 %. The default (the approach
    filter with the collisional transfer at weights 1, 8; off at 1, 1) and plain NTC (--no-cell-approaching). The
    filter's redraw keeps the candidate's two weights (a transfer that took any
    approaching pair of the cell gave 0.946 +- 0.0125 of the small-small rate here), leaves
    pairs of single particles alone, and draws among the parcels of those weights (drawn from the whole cell,
    0.924 +- 0.012 of the small-large rate with the transfer)."""
    one = _cool(hc, capsys, tmp_path, constant_mixture_model, "1,1", extra=extra)
    mixed = _cool(hc, capsys, tmp_path, constant_mixture_model, "1,8", extra=extra)
    assert mixed["species"]["parcels"] == [2800, 150] and mixed["particles"] == one["particles"] == 4000
    for s in (one, mixed):
        assert s["check_errors"] == [] and s["momentum_drift"] < 1e-5
        for name, row in s["collision_pair_types"].items():
            assert abs(row["ratio"] - 1.0) < 4.0 * row["ratio_stderr"], (s["particles_per_parcel"], name, row)
    counts = mixed["strategy_counts"]
    # restorations are per block of cells, weight class and sub-step: ~1,050 in the box's ~16-parcel cells,
    # 250-320 in the larger cells it gets (a 475 um pair of weight 8 would saturate
    # 16-parcel cells)
    assert counts["cell_restored"] > 200 and counts["cell_unrestored"] <= 0.05 * counts["cell_restored"]
    for k in (1, 2):
        final = [s[f"granular_temperature_{k}_final"] for s in (one, mixed)]
        assert final[1] == pytest.approx(final[0], rel=0.15), (k, final)


@pytest.mark.parametrize("flag, says", [("--cell-approaching", "--[no-]cell-approaching"),
                                        ("--no-cell-approaching", "--[no-]cell-approaching")])
def test_cell_options_are_options_of_the_cell_detection(hc, capsys, tmp_path, constant_mixture_model, flag, says):
    """The cooling case's --[no-]cell-approaching: refused with one line (exit 2) where the cell detection is not
    used."""
    argv = ["--collisions", "surrogate", "--model", constant_mixture_model, "--detection", "swept", "--dt", "1e-3",
            "--solids-fraction", "0.01", "--particles", "400", "--diameter", str(D1), *MIXTURE,
            "--granular-temperature", "1", "--end-time", "0.002", flag, "--out", str(tmp_path / "x")]
    assert hc.main(argv) == 2
    assert f"{says} is an option of the surrogate's cell detection" in capsys.readouterr().err
