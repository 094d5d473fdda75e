"""Inlet schedules of the case API drive the gas: by continuity, the mean axial gas speed through any cross-section
of a closed column with one inlet and one outlet equals the inlet's speed at that time."""

import numpy as np
import pytest

from hel_warp import case as hc


def _column(velocity):
    flow = hc.Flow("column", lo=(0, 0, 0), hi=(0.01, 0.01, 0.04), spacing=2e-3, gravity=(0, 0, -9.81))
    flow.inlet("floor", "z-", velocity=velocity)
    flow.outlet("top", "z+")
    flow.species("a", 100e-6)
    flow.fill("a", ((0, 0, 0), (0.01, 0.01, 0.01)), count=10)
    return hc.build(flow, hc.Settings(collisions="none", dt=5e-4))


@pytest.mark.parametrize("velocity", [hc.Ramp(value=0.5, duration=0.01), hc.Levels([0.3, 0.6], hold=0.01)],
                         ids=["ramp", "levels"])
def test_the_gas_follows_the_inlet_schedule(velocity):
    sim = _column(velocity)
    solver = sim.solver
    for _ in range(30):  # 15 ms: into the ramp's plateau, into the second level
        solver.step()
        # the mean face velocity through the mid-height section (all fluid): continuity with the inlet
        mid = solver.gas.face_velocity.z.numpy()[:, :, 10].mean()
        assert mid == pytest.approx(velocity(solver.time), rel=1e-4, abs=1e-6)
    assert velocity(solver.time) > velocity(0.0)
