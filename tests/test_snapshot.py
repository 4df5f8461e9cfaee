"""Simulation.snapshot / restore: a step taken and then refused leaves no trace, the next step
gives the same bits as a twin simulation that never took it."""

import warnings

import numpy as np
import pytest
from test_macro_step import pose, soil

from cosim.contract import WheelKinematics
from cosim.dem_soil import WallProximityWarning
from soil import SimulationDiverged, StepController

START = 7
"""Macro steps before the snapshot (the wheel is in the grains by then)."""


def wild(t):
    """A motion the good run never takes: the wheel plunges fast and spins the other way."""
    return WheelKinematics(
        np.array([0.03, 0.015, 0.0415 - 0.3 * t]),
        np.array([1.0, 0, 0, 0]),
        np.array([0.2, 0.0, -3.0]),
        np.array([0.0, -40.0, 0.0]),
    )


def assert_same(a, b):
    sa, sb = a.sim, b.sim
    assert sa.time == sb.time and sa.steps == sb.steps
    assert (sa.accepted_steps, sa.rejected_steps, sa.forced_steps) == (
        sb.accepted_steps,
        sb.rejected_steps,
        sb.forced_steps,
    )
    da, db = sa.state.to_numpy(), sb.state.to_numpy()
    assert da.keys() == db.keys()
    for name in da:
        np.testing.assert_array_equal(da[name], db[name], err_msg=name)
    for name, value in sa.monitor.state_dict().items():
        np.testing.assert_array_equal(value, sb.monitor.state_dict()[name], err_msg=f"monitor/{name}")
    if sa.step_control is not None:
        np.testing.assert_array_equal(sa.step_control.control.numpy(), sb.step_control.control.numpy())


@pytest.mark.parametrize("stepping", ["fixed", "pid"])
def test_restore_then_step_equals_never_having_taken_the_refused_step(device, stepping):
    twins = [soil(device), soil(device)]
    macro = 1e-3
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WallProximityWarning)
        for side in twins:
            if stepping == "pid":
                side.sim.enable_step_control(StepController(tolerance=1e-3, dt_max=2e-4, dt_min=1e-6))
            side.sim.arm_monitor()
            for k in range(START):
                side.advance((k + 1) * macro, [pose(k * macro)])
        refusing, reference = twins
        kept = refusing.sim.snapshot()
        kept = refusing.sim.snapshot(into=kept)  # a snapshot's buffers are reused
        before = refusing.sim.state.to_numpy()
        for k in range(START, START + 2):  # steps that are then refused (different wheel motion, more DEM steps)
            refusing.advance((k + 1) * macro, [wild(k * macro)])
            try:  # the soil FMU checks after each step: the bounds follow the faster wheel
                refusing.sim.check_divergence()
            except SimulationDiverged:
                break
        assert refusing.sim.steps > reference.sim.steps
        refusing.sim.restore(kept)
        after = refusing.sim.state.to_numpy()
        for name in before:
            np.testing.assert_array_equal(after[name], before[name], err_msg=name)
        for side in twins:  # the step both take
            wrench = side.advance((START + 1) * macro, [pose(START * macro)])[0]
            assert wrench.contact_count > 0, "the wheel works in the grains"
    assert_same(refusing, reference)
    a, b = refusing.last_report, reference.last_report
    for field in ("body_force", "body_torque", "body_force_end", "body_work", "boundary_displacement"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)


def test_a_snapshot_fits_its_own_simulation_only(device):
    from soil import SoilInputError

    one, other = soil(device), soil(device)
    with pytest.raises(SoilInputError):
        other.sim.restore(one.sim.snapshot())
