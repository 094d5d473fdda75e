"""The swept detection's windows (hel_warp/collisions/models.py ``windows``, kernels/collide.py ``swept_window``).

A step may be resolved in windows, one after the other, each with searches of the window's reach; the paths, event
times and outcomes are those of the whole step. References (docs/developer/conventions.md rule 9): the strict event order in one window
(tests/test_swept.py ``test_windows_change_the_searches_not_the_events``, tests/test_swept_walls.py with walls); here
the automatic choice of the window count against its rule, the checkpoint round trip of what drives it, and a HEL run
(gas, walls, injection) that switches to windows restarting bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.test_cell_collisions import run_straight_and_restarted, small_walled_hel
from tests.test_collision_models import D, make_particles
from tests.test_swept import periodic_gas, write_constant_contact_forest


@pytest.fixture(scope="module")
def constant_model(tmp_path_factory):
    return write_constant_contact_forest(tmp_path_factory.mktemp("constant_model"))


def test_auto_windows_follow_the_last_step_rounds_and_the_reach(constant_model):
    # One window while the last step needed few rounds (a dilute gas: each window's full search would cost more
    # than it saves); after a step of many rounds, windows of a mean reach of WINDOW_REACH radii: ceil(reach_mean /
    # (WINDOW_REACH r_max)), capped at ceil(WINDOWS_PER_ROOT_ROUND sqrt(rounds)) and MAX_WINDOWS. The rounds survive
    # the checkpoint (state / set_state).
    import hel_warp.collisions.models as cm

    x, v, side = periodic_gas(1000, 0.01, seed=2)
    dt = 1e-3
    strategy = cm.SurrogateCollision(model_dir=constant_model, periodic_box=(side,) * 3, ordering="parallel")
    p = make_particles(x, v)
    strategy.collide(p, dt)
    assert strategy.counts()["windows"] == 1  # no history: one window
    rounds = strategy.counts()["rounds"]
    assert int(strategy.state()["swept_rounds"]) == max(0, rounds - 1) < cm.WINDOW_ROUNDS
    reach_mean = float(np.mean(np.linalg.norm(v - v.mean(axis=0), axis=1))) * dt / 2.0
    by_reach = math.ceil(reach_mean / (cm.WINDOW_REACH * 0.5 * D))
    assert by_reach > 6
    for last in (cm.WINDOW_ROUNDS, 10_000):  # few windows after a step of 30 rounds, the reach's after 10,000
        expected = min(cm.MAX_WINDOWS, by_reach, math.ceil(cm.WINDOWS_PER_ROOT_ROUND * math.sqrt(last)))
        fresh = cm.SurrogateCollision(model_dir=constant_model, periodic_box=(side,) * 3, ordering="parallel")
        fresh.set_state({**strategy.state(), "swept_rounds": np.array(last, np.int64)})
        p = make_particles(x, v)
        fresh.collide(p, dt)
        assert fresh.counts()["windows"] == expected > 1
    # the serial queue (the CPU's default): its rounds are its events. ceil(WINDOWS_SERIAL reach / r_max
    # sqrt(events per parcel)) windows: the first as many for the forecast (the last step's events, grown as from
    # the step before, at most SERIAL_GROWTH times), each later one cut from the rest of the step by the rule for
    # the events so far (extrapolated to the step, never below the forecast)
    def rule(per_parcel):
        return min(cm.MAX_WINDOWS, max(1, math.ceil(cm.WINDOWS_SERIAL * reach_mean / (0.5 * D)
                                                    * math.sqrt(per_parcel))))

    for last, prev in ((0, 0), (50, 0), (5_000, 0), (500, 100), (5_000, 4_000)):
        serial = cm.SurrogateCollision(model_dir=constant_model, periodic_box=(side,) * 3, ordering="serial")
        serial.set_state({"swept_rounds": np.array(last, np.int64), "swept_rounds_prev": np.array(prev, np.int64)})
        p = make_particles(x, v)
        serial.collide(p, dt)
        forecast = last / len(x) * (min(cm.SERIAL_GROWTH, max(1.0, last / prev)) if prev else 1.0)
        bounds = serial.window_bounds
        first = rule(forecast)
        np.testing.assert_allclose(bounds[1], dt / first, rtol=1e-12)
        for k, events in enumerate(serial.window_events, start=1):
            done = bounds[k] / dt
            left = max(1, round(rule(max(events / len(x) / done, forecast)) * (1.0 - done)))
            np.testing.assert_allclose(bounds[k + 1] - bounds[k], (dt - bounds[k]) / left, rtol=1e-9)
        assert bounds[-1] == dt and len(serial.window_events) == len(bounds) - 2
        windows = serial.counts()["windows"]
        assert windows == len(bounds) - 1
        assert int(serial.state()["swept_rounds"]) == serial.counts()["rounds"] - windows  # its events
        assert int(serial.state()["swept_rounds_prev"]) == last
    assert first > 4 and windows > 4
    with pytest.raises(Exception, match="windows must be"):
        cm.SurrogateCollision(model_dir=constant_model, windows=0)


def test_hel_run_that_switches_to_windows_restarts_bitwise(constant_model, tmp_path, monkeypatch):
    """A HEL run (gas, walls, injection) of single-particle parcels under the swept detection, the window rule made to
    switch on after any step with a round (``WINDOW_ROUNDS`` = 1): 2N steps in one go == N steps, an interruption,
    a restart from the checkpoint at N (the last step's rounds are in it), N more."""
    import hel_warp.collisions.models as cm
    from hel_warp.hel import collision_model
    from hel_warp.parcels.pool import VolumeInjection

    monkeypatch.setattr(cm, "WINDOW_ROUNDS", 1)
    dt, n = 1e-3, 4
    windows = []

    def build():
        strategy = collision_model("surrogate", model_dir=constant_model)
        counts = strategy.counts

        def logged_counts():
            c = counts()
            windows.append(c.get("windows", 1))
            return c

        strategy.counts = logged_counts
        injection = VolumeInjection(box_lo=(0.001, 0.001, 0.001), box_hi=(0.004, 0.004, 0.004), diameter_mean=D,
                                    count=600, speed=1.5, direction=(1.0, 0.3, -1.0), seed=5)
        return small_walled_hel(strategy, injection, 1200, dt)

    straight, resumed = run_straight_and_restarted(build, tmp_path, dt, n)
    assert straight.collision.detection == "swept"
    assert max(windows) > 1  # the run switched to windows
    a, b = straight.state(), resumed.state()
    assert a.keys() == b.keys() and "collision/swept_rounds" in a
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
