"""The PID step control on the device (soil.step_control, Simulation.macro_step_adaptive):
against Hertz theory, bitwise rejection and resume, one read per macro step, and a scene
whose fixed step diverges."""

import json
import re
import warnings

import numpy as np
import pytest
from test_integrator import CONTACT_TIME, DURATION, impact_error, two_spheres
from test_macro_step import ReadCounter, pose, soil

from cosim.dem_soil import WallProximityWarning
from soil import JoltBeeman, StepController, adaptive, step_control


def pid_impact(device, tolerance, macro_steps=10):
    """The two-sphere Hertz impact in `macro_steps` PID macro steps; returns (sim, evaluations)."""
    sim = two_spheres(device, JoltBeeman())
    sim.enable_step_control(StepController(tolerance=tolerance, dt_max=CONTACT_TIME, dt_min=1e-5 * CONTACT_TIME))
    before = sim.contacts.evaluations
    for _ in range(macro_steps):
        report = sim.macro_step_adaptive(DURATION / macro_steps)
        assert report.steps >= 1 and report.dt_min <= report.dt_max <= CONTACT_TIME
    return sim, sim.contacts.evaluations - before


def test_pid_macro_steps_meet_the_hertz_impact_with_fewer_evaluations_than_the_fixed_step(device):
    """The impact's separation and rebound speed against Hertz theory: the PID macro steps land
    exactly on the macro steps' ends, meet a tolerance-sized error, and need fewer force
    evaluations than the largest fixed jolt-Beeman step that is as accurate (the free flight
    and the smooth contact let the PID step grow)."""
    sim, evaluations = pid_impact(device, 1e-6)
    assert sim.time == pytest.approx(DURATION, rel=1e-12)
    error = impact_error(sim)
    assert error < 3e-4
    fixed = None
    for per_contact in (25, 50, 100, 200, 400):
        reference = two_spheres(device, JoltBeeman())
        reference.run(DURATION, CONTACT_TIME / per_contact)
        if impact_error(reference) <= error:
            fixed = reference.contacts.evaluations
            break
    assert fixed is not None, "no fixed step up to contact time / 400 is as accurate"
    assert evaluations * 3 < fixed, (evaluations, fixed)


def test_a_rejected_substep_leaves_the_state_bit_for_bit(device):
    """A substep far too long for the bed is rejected on the device: the current state (grains,
    forces, contact history, list) is bit for bit what it was, and the shorter retry gives bit
    for bit the state that taking the short step first gives."""
    sides = [soil(device), soil(device)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WallProximityWarning)
        for side in sides:  # some contact history with the wheel first
            side.sim.integrator = JoltBeeman()
            for k in range(3):
                side.advance((k + 1) * 1e-3, [pose(k * 1e-3)])
    states = []
    for first in (1e-2, None):  # 1e-2 s is 30x the bed's Hertz time: the trial explodes
        sim = sides[len(states)].sim
        control = sim.enable_step_control(StepController(tolerance=1e-3, dt_max=1e-2, dt_min=1e-6))
        current, trial = sim._spares()
        current.assign(sim.state)
        substep = adaptive.substep(sim, current, trial, False, control.controller.error_scales())
        before = current.to_numpy()
        if first is not None:
            control.begin(1.0)
            control.control.assign(_block(control, next_step=first, remaining=1.0))
            substep()
            block = control.control.numpy()
            assert block[step_control.REJECTED] == 1 and block[step_control.ACCEPTED] == 0
            after = current.to_numpy()
            for name, values in before.items():
                np.testing.assert_array_equal(after[name], values, err_msg=name)
        control.control.assign(_block(control, next_step=2e-5, remaining=1.0))
        substep()
        assert control.control.numpy()[step_control.ACCEPTED] == 1
        states.append(current.to_numpy())
    for name, values in states[0].items():
        np.testing.assert_array_equal(values, states[1][name], err_msg=name)


def _block(control, next_step, remaining):
    values = control.control.numpy().copy()
    values[step_control.NEXT_STEP] = next_step
    values[step_control.REMAINING] = remaining
    return values


def _advance(side, start, count, macro=1e-3):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WallProximityWarning)
        for k in range(start, start + count):
            side.advance((k + 1) * macro, [pose(k * macro)])


def test_a_pid_run_resumes_bit_for_bit(device):
    """The step control's state (next step, PID history, speeds seen) is in the checkpoint: a
    soil side loaded from it takes the same substeps as the one that went on."""
    first = soil(device)
    first.sim.enable_step_control(StepController(tolerance=1e-2))
    _advance(first, 0, 3)
    saved = first.state_dict()
    units = first.state_dict_units()  # what the checkpoint carries: a unit for every entry
    assert set(saved) <= set(units)
    assert units["simulation/step_control/dt_max"] == "s" and units["simulation/step_control/tolerance"] == "1"
    resumed = soil(device)
    resumed.load_state_dict(saved)
    assert resumed.sim.step_control is not None
    _advance(first, 3, 3)
    _advance(resumed, 3, 3)
    assert resumed.last_report.steps == first.last_report.steps
    a, b = first.sim.state_dict(), resumed.sim.state_dict()
    for name in a:
        np.testing.assert_array_equal(np.asarray(a[name]), np.asarray(b[name]), err_msg=name)


def test_a_pid_macro_step_reads_the_device_once(device, monkeypatch):
    """With the PID on, the substeps and their accept/reject decisions stay on the device: one
    read per DemSoil.advance, whatever the substeps."""
    side = soil(device)
    side.sim.enable_step_control(StepController(tolerance=1e-2))
    _advance(side, 0, 1)  # captures the substep loop
    counter = ReadCounter(monkeypatch)
    reads, substeps = [], 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WallProximityWarning)
        for k in range(1, 5):
            before = counter.count
            side.advance((k + 1) * 1e-3, [pose(k * 1e-3)])
            reads.append(counter.count - before)
            substeps += side.last_report.steps + side.last_report.rejected
    assert substeps > 4 and max(reads) <= 1, (reads, substeps)


def test_a_scene_whose_fixed_step_diverges_completes_under_pid(tmp_path, tiny_bed):
    """The tiny scene at 8x its advised step diverges with fixed steps (exit 4 material); with
    the PID allowed that step as its dt_max it lands and drives to the end, and results.h5 and
    the summary carry the step statistics with their units."""
    import h5py

    from cosim.launch import run_scene
    from cosim.runner import RunDiverged
    from helpers import write_tiny

    scene = write_tiny(tmp_path, "")
    big = ["run.dt=0.0017", "run.duration=0.034", "landing.max_time=0.3", f'bed.bed_file="{tiny_bed}"']
    with pytest.raises(RunDiverged):
        run_scene(scene, str(tmp_path / "fixed"), overrides=big)
    result = run_scene(scene, str(tmp_path / "pid"), overrides=big + ["run.step_control=pid", "run.dt_max=0.0017"])
    assert result.status in ("complete", "unsteady")
    summary = json.loads((tmp_path / "pid" / "run.json").read_text())["summary"]
    assert summary["step_control"] == "pid"
    assert summary["dt_max"] <= 0.0017 and summary["dt_mean"] < 0.0017 / 2
    assert summary["force_evaluations"] >= summary["dem_steps"] + summary["dem_steps_rejected"]
    assert summary["dem_steps_forced"] == 0 and summary["units"]["dem_steps_forced"] == "count"
    with h5py.File(tmp_path / "pid" / "results.h5") as f:
        assert f["soil/dt_mean"].attrs["units"] == "s" and f["soil/dem_steps"].attrs["units"] == "count"
        steps = f["soil/dem_steps"][()]
        assert (steps[1:] >= 1).all() and int(steps.sum()) == summary["dem_steps"]


def test_a_tolerance_the_shortest_step_cannot_meet_is_warned_of_and_counted(tmp_path, tiny_bed, caplog):
    """A tolerance of 1e-12 with run.dt_min half of dt_max: every substep is kept at dt_min over the
    tolerance. That ran without a word (with the default dt_min, 1e4 x the steps: a run that seemed
    to hang); now the first is warned of, naming the keys, and the summary counts them."""
    import logging

    from cosim.launch import run_scene
    from helpers import write_tiny

    scene = write_tiny(tmp_path, "")
    settings = ["run.duration=0.0085", "landing.max_time=0.05", "landing.hold_time=0.02", "run.step_control=pid"]
    settings += [f'bed.bed_file="{tiny_bed}"']
    settings += ["run.dt_max=0.00034", "run.dt_min=0.00017", "run.tolerance=1e-12"]
    with caplog.at_level(logging.WARNING, logger="cosim"):
        run_scene(scene, str(tmp_path / "tight"), overrides=settings)
    summary = json.loads((tmp_path / "tight" / "run.json").read_text())["summary"]
    assert summary["dem_steps_forced"] > 0 and summary["dem_steps_forced"] <= summary["dem_steps"]
    warned = [r.getMessage() for r in caplog.records if "kept" in r.getMessage()]
    assert len(warned) == 1, warned  # the first, once
    assert "shortest step (run.dt_min: 0.00017 s) with an error over run.tolerance (1e-12)" in warned[0], warned


@pytest.mark.parametrize(
    "settings, words",
    [
        ({"k_i": -1.0}, "k_i must be > 0"),  # held the step at dt_min: a million steps
        ({"k_i": float("nan")}, "the PID gains must be finite numbers, got k_i = nan"),  # never returned
        ({"k_i": 0.0, "k_p": 0.0, "k_d": 0.0}, "k_i must be > 0"),  # froze the step at its first value
        ({"k_p": -5.0}, "does not settle"),
        ({"k_i": 2.1, "k_p": 0.0, "k_d": 0.0}, "|z| = 1.1 >= 1"),  # z^2 (z + 1.1): a root at -1.1
        ({"order": 0.0}, "order must be a finite number > 0"),  # a bare ZeroDivisionError
        ({"order": -3.0}, "order must be a finite number > 0"),  # never returned
        ({"dt_max": float("inf")}, "dt_max must be a finite number > 0"),  # returned at once, 0 steps
        ({"dt_initial": -1.0}, "dt_initial must be a finite number > 0"),  # silently clipped
        ({"velocity_scale": float("nan")}, "velocity_scale must be a finite number >= 0"),  # silently ignored
        ({"dt_min": 1e-3, "dt_max": 1e-4}, "dt_min must be <= dt_max"),
    ],
)
def test_step_controller_settings_that_cannot_control_are_refused_by_name(settings, words):
    """The closed loop of the gains (the class docstring's z^3 + (b1 - 1) z^2 + b2 z + b3) must settle:
    the defaults put its roots at |z| <= 0.72, Gustafsson's PI (0.3, 0.4, 0) at 0.8; k_i = 2.1 alone
    leaves z^2 (z - (1 - 2.1)), a root at -1.1, outside."""
    from soil.errors import SoilInputError

    with pytest.raises(SoilInputError, match=re.escape(words)):
        StepController(**settings)
    StepController(k_i=0.3, k_p=0.4, k_d=0.0)  # Gustafsson's PI
    StepController(dt_min=1e-5, dt_max=1e-4, dt_initial=np.float32(2e-5))
    StepController(dt_min=1e-4, dt_max=1e-4)  # a fixed substep under the PID's error check: the scene allows it


def test_the_soil_fmu_carries_the_step_control(tiny_bed):
    """run.step_control = 'pid' travels into the soil FMU's configuration (resources/soil.json),
    and the soil server's DemSoil takes PID substeps that land on the macro step's end."""
    from cosim.contract import WheelKinematics
    from cosim.soil_fmu.config import SoilFmuConfig, bed_surface_height, config_to_json, soil_from_config
    from soil import GrouserWheel, Material

    wheel = GrouserWheel(radius=0.025, width=0.02, grouser_count=8, grouser_height=0.003, grouser_thickness=0.002)
    config = SoilFmuConfig(
        bed_file=tiny_bed,
        wheel=wheel,
        wheel_material=Material(youngs_modulus=1e6),
        dem_step=1e-4,
        surface_height=bed_surface_height(tiny_bed),
        step_control=dict(tolerance=1e-2, dt_min=None, dt_max=None),
    )
    data = json.loads(json.dumps(config_to_json(config, 1)))
    side = soil_from_config(data, tiny_bed)
    assert side.sim.step_control is not None and side.sim.step_control.controller.tolerance == 1e-2
    hub = np.array([0.04, 0.03, config.surface_height + wheel.outer_radius + 0.002])
    start = WheelKinematics(hub, np.array([1.0, 0, 0, 0]), np.zeros(3), np.zeros(3))
    side.place_wheels([start])
    t_end = side.time + 1.7e-3
    side.advance(t_end, [start])
    assert side.time == t_end and side.last_report.steps >= 1


def test_simulation_run_takes_pid_substeps_once_a_step_control_is_on(device):
    """Simulation.run (settling, the lab) with a step control: macro steps of check_every x dt in
    PID substeps, ending on the duration, as accurate against Hertz theory as the PID needs."""
    sim = two_spheres(device, JoltBeeman())
    sim.enable_step_control(StepController(tolerance=1e-4, dt_max=CONTACT_TIME, dt_min=1e-5 * CONTACT_TIME))
    sim.run(DURATION, CONTACT_TIME / 50, check_every=80)
    assert sim.time == pytest.approx(DURATION, rel=1e-12)
    assert sim.contacts.evaluations < DURATION / (CONTACT_TIME / 50) / 4  # a quarter of the fixed steps'
    assert impact_error(sim) < 5e-3


def test_a_pid_scene_stopped_and_resumed_is_bit_for_bit_the_whole_run(tmp_path, tiny_bed):
    """`cosim resume` of a PID scene: stopped after a checkpoint and resumed, the run equals the
    uninterrupted one bit for bit (state, time series, summary): the substep sequence is part of
    the checkpoint."""
    import h5py
    from test_study import _assert_same_run

    from cosim.launch import resume, run_plan
    from cosim.plan import load_plan
    from cosim.runner import RunInterrupted
    from helpers import write_tiny

    settings = ["run.dt=0.0017", "run.duration=0.034", "landing.max_time=0.3", "output.checkpoint_interval=0.0085"]
    settings += [f'bed.bed_file="{tiny_bed}"', "run.step_control=pid", "run.dt_max=0.0017"]
    plan = load_plan(write_tiny(tmp_path), settings)
    whole, stopped = tmp_path / "whole", tmp_path / "stopped"
    assert run_plan(plan, str(whole)).status in ("complete", "unsteady")

    def request_stop(runner):
        if runner.system.coupler.step_count == 60:
            runner.stop_requested = True

    with pytest.raises(RunInterrupted):
        run_plan(plan, str(stopped), hooks={"step": request_stop})
    resume(str(stopped))
    _assert_same_run(whole, stopped)
    with h5py.File(whole / "results.h5", "r") as f:  # the PID did vary the steps
        assert f["soil/dt_min"][()][1:].min() < 0.0017
