"""Adaptive stepping of a Simulation: jolt-Beeman steps whose length a PID controller chooses.

Two ways, both behind Simulation methods:

- `macro_step_adaptive` (Simulation.macro_step_adaptive): the substep loop with its
  accept/reject decision runs on the device as one captured graph (`wp.capture_while`), the
  decision made by the device step control (soil.step_control.DeviceStepControl, whose
  kernels it launches); the host reads one report at the end.
- `run_adaptive` (Simulation.run_adaptive): the StepController decides on the host after
  each step from an error norm reduced on the device (one small read per step).

A rejected step is never made current: the state it started from is untouched, so the retry
starts from it bit for bit. The worlds of soil.worlds each have their own step control in the
same launches (soil.step_control): a world that keeps nothing of a substep others kept takes
its state back into the trial before the trial becomes current.
"""

import functools
import math
import warnings
from collections.abc import Callable

import numpy as np
import warp as wp

from . import status as status_columns
from . import step_control
from .errors import RegolithWarning, SoilInputError
from .integrator import JoltBeeman, StepController, VelocityVerlet
from .macro import MacroStepReport, grain_box
from .state import SoilState
from .step_control import DeviceStepControl


class HistoryLostWarning(RegolithWarning):
    """A world of a batch took its state back onto a neighbour list, built by a substep it threw away,
    that lacked one of its contacts (a grain had moved more than the list's skin in that substep):
    the contact's tangential and rolling history restarts, and the world no longer steps bit for bit
    as its scene alone."""


def use_jolt_beeman(sim, purpose: str) -> None:
    """Install a JoltBeeman integrator in `sim` if it still has its default VelocityVerlet and has
    not stepped; TypeError if it has another integrator (`purpose` names who needs it)."""
    if not isinstance(sim.integrator, JoltBeeman):
        if isinstance(sim.integrator, VelocityVerlet) and sim.steps == 0:
            sim.integrator = JoltBeeman()
        else:
            raise SoilInputError(
                f"{purpose} needs the JoltBeeman integrator, not {type(sim.integrator).__name__} (a simulation that "
                "stepped with another: build it with integrator='jolt-beeman')"
            )


def enable_step_control(sim, controller: StepController | None = None) -> DeviceStepControl:
    """The device step control of `sim` with `controller`'s settings (Simulation.enable_step_control)."""
    use_jolt_beeman(sim, "step control")
    controller = controller or StepController()
    controller.setup(sim)
    sim.graphs.clear()  # a captured substep loop holds the old controller's settings and arrays
    sim.step_control = DeviceStepControl(
        controller,
        sim.model.precision,
        sim.model.device,
        controller.error_scales()["scale_floor"],
        worlds=sim.model.world_count,
    )
    return sim.step_control


def substep(sim, current: SoilState, trial: SoilState, path: bool, weights: dict):
    """One substep of the macro step's loop (captured inside it), as a function of no arguments:
    step current -> trial, decide on the device (each world), copy a trial that a world kept over
    current, the worlds that kept nothing of it taking their own state back into it first.
    weights: StepController.error_scales()."""
    control = sim.step_control
    integrator = sim.integrator
    assert control is not None and isinstance(integrator, JoltBeeman)  # enable_step_control saw to both
    integrator.bind(sim.model)
    scale_floor, summary = integrator.scale_floor, integrator.summary
    assert scale_floor is not None and summary is not None
    capacity, rigid_capacity = sim.state.capacity, sim.state.rigid_capacity

    def restore():
        trial.copy_worlds(current, control.restore, sim.model)
        sim.neighbour_list.remap_worlds(current, trial, control.restore, sim.status)

    def accept():
        sim._accumulate_wrench(trial, weighted=True, worlds=control.accepted)
        current.assign(trial)

    def one_substep():
        control.propose(sim._step_length, sim._step_length64, scale_floor)
        trial.copy_bodies(current)
        if path:
            sim.control.follow_path(trial, sim._step_length, control.tau)
        integrator.step(sim.model, current, trial, sim.control, sim._step_length, sim.contacts)
        integrator.reduce_error(trial, sim.status, weights["position_weight"], scale_floor, weights["use_speed"])
        control.decide(summary, sim.status, capacity, rigid_capacity)
        if control.worlds > 1:  # alone a world keeps its trial or nothing changes: no restore
            wp.capture_if(control.any_restore, on_true=restore)
        wp.capture_if(control.any_accepted, on_true=accept)

    return one_substep


def macro_step_adaptive(sim, span: float, path: bool, meanwhile: Callable[[], None] | None = None) -> MacroStepReport:
    """Simulation.macro_step_adaptive (its docstring); span [s] already checked."""
    control = sim.step_control
    if control is None:
        raise SoilInputError("macro_step_adaptive needs a step control: call enable_step_control() first")
    controller = control.controller
    sim._maybe_reorder()
    if not path:
        sim.control.path_active = False
    sim.control.push(sim.state)
    redone = 0
    start = sim.state
    evaluations_before = sim.contacts.evaluations
    control.begin(span)
    weights = controller.error_scales()
    while True:
        sim._prepare()
        current, trial = sim._spares()
        status_columns.clear(sim.status)
        sim.sums.clear()
        sim.neighbour_list.save(start)
        current.assign(start)

        # substeps until the span is covered
        loop = functools.partial(wp.capture_while, control.running, substep(sim, current, trial, path, weights))

        key = ("adaptive", id(current), id(trial), path, type(sim.integrator))
        per_substep = sim.graphs.replay(key, loop, sim.contacts)
        if per_substep is None:
            loop()  # launched (the host reads the condition at every substep)
        if meanwhile is not None:  # while the device steps; once (a redo below does not repeat it)
            work, meanwhile = meanwhile, None
            work()
        values = sim.sums.read(sim.status, sim.neighbour_list.grid, current, control)
        steps = values[sim.sums.steps_column :].reshape(control.worlds, step_control.COLUMNS)
        if per_substep is not None:  # the loop ran as long as the world that tried most substeps
            tried = steps[:, step_control.ACCEPTED] + steps[:, step_control.REJECTED]
            sim.contacts.evaluations += per_substep * int(tried.max())
        growth = sim._needs_growth(values)
        if growth is None:
            break
        sim.neighbour_list.restore(start)
        sim._grow(*growth)
        control.redo()
        redone += 1
    accepted = steps[:, step_control.ACCEPTED].astype(np.int64)
    rejected = steps[:, step_control.REJECTED].astype(np.int64)
    forced = steps[:, step_control.FORCED].astype(np.int64)
    sim.state = current
    sim.state.time = start.time + span
    sim.state.forces_valid = True
    sim.steps += int(accepted.max())
    sim.accepted_steps += int(accepted.sum())
    sim.rejected_steps += int(rejected.sum())
    sim.forced_steps += int(forced.sum())
    rebuilds = int(values[status_columns.REBUILDS])
    sim._rebuilds_since_reorder += rebuilds
    sim._bounds = grain_box(values)
    if values[status_columns.LOST_HISTORY] > 0:
        warnings.warn(
            f"a world of the batch lost a contact's history in the macro step to t = {sim.state.time:.6g} s: a grain "
            "moved more than the neighbour list's skin in a substep that world threw away; from here it is no longer "
            "bit for bit its run alone (a larger skin, NeighbourSettings, or the runs one by one avoid it)",
            HistoryLostWarning,
            stacklevel=4,
        )
    if (steps[:, step_control.DIVERGED] > 0).any() or values[status_columns.NONFINITE] > 0:
        sim.monitor.fail(
            sim,
            f"non-finite particle state (NaN or inf) even at dt_min = {controller.dt_min:.4g} s",
            int(values[status_columns.WORST]),
        )
    evaluations = sim.contacts.evaluations - evaluations_before
    tried = accepted + rejected
    per_world = tuple(
        dict(
            steps=int(accepted[w]),
            dt=span / max(int(accepted[w]), 1),
            rejected=int(rejected[w]),
            forced=int(forced[w]),
            dt_min=float(steps[w, step_control.SMALLEST]),
            dt_max=float(steps[w, step_control.LARGEST]),
            evaluations=int(round(evaluations * tried[w] / max(int(tried.max()), 1))),
        )
        for w in range(control.worlds)
    )
    if control.worlds == 1:
        return sim.sums.report(values, span, rebuilds=rebuilds, redone=redone, **per_world[0])
    return sim.sums.report(  # the batch as a whole; each world's own figures in world_steps
        values,
        span,
        steps=int(accepted.max()),
        dt=span / max(int(accepted.max()), 1),
        rebuilds=rebuilds,
        redone=redone,
        rejected=int(rejected.sum()),
        forced=int(forced.sum()),
        dt_min=float(steps[:, step_control.SMALLEST].min()),
        dt_max=float(steps[:, step_control.LARGEST].max()),
        evaluations=evaluations,
        world_steps=per_world,
    )


def run_adaptive(
    sim, duration: float, controller: StepController | None = None, callback=None, check_every: int = 100
) -> dict:
    """Simulation.run_adaptive (its docstring)."""
    if not (isinstance(duration, (int, float, np.floating, np.integer)) and math.isfinite(duration) and duration >= 0):
        raise SoilInputError(f"duration must be finite and >= 0 [s], got {duration!r}")
    if sim.model.world_count > 1:
        raise SoilInputError(
            "run_adaptive decides on the host for one world; worlds (soil.worlds) take their PID substeps each "
            "under its own controller on the device: enable_step_control(), then macro steps"
        )
    use_jolt_beeman(sim, "run_adaptive")
    controller = controller if controller is not None else sim._controller or StepController()
    sim._controller = controller
    controller.setup(sim)
    assert controller.dt is not None and controller.dt_min is not None  # setup() resolved them
    if not sim.monitor.armed:
        sim.monitor.arm(sim)
    sim.control.path_active = False
    sim.control.push(sim.state)
    sim.integrator.bind(sim.model)
    counts: dict[str, float] = dict(accepted=0, rejected=0, forced=0, evaluations=sim.contacts.evaluations)
    smallest, largest = math.inf, 0.0
    t_end = sim.time + duration
    dt = controller.dt
    while t_end - sim.time > 1e-9 * controller.dt_min:
        remaining = t_end - sim.time
        # land on t_end without a sliver of a last step (a tiny step spoils the next jolt)
        h = remaining if remaining <= dt else (0.5 * remaining if remaining < 2.0 * dt else dt)
        while True:
            following = sim._spares()[0]
            sim.contacts.reserve(sim.state.rigid_capacity)
            status_columns.clear(sim.status)
            sim._set_step(h)
            following.copy_bodies(sim.state)
            sim.integrator.step(sim.model, sim.state, following, sim.control, sim._step_length, sim.contacts)
            following.time = sim.state.time + h
            summary = sim.integrator.read_summary(following, sim.status, **controller.error_scales())
            growth = sim._needs_growth(summary["status"])
            if growth is None:
                break
            sim._grow(*growth)
        sim._rebuilds_since_reorder += int(summary["status"][status_columns.REBUILDS])
        err = controller.error(summary)
        accepted, proposal = controller.decide(err, h)
        if not accepted and h <= controller.dt_min * (1.0 + 1e-9):
            if summary["nonfinite"]:
                sim.monitor.fail(
                    sim,
                    f"non-finite state even at dt_min = {controller.dt_min:.4g} s",
                    summary["worst"],
                    state=following,
                )
            accepted = True
            counts["forced"] += 1
            sim.forced_steps += 1
        if not accepted:
            counts["rejected"] += 1
            sim.rejected_steps += 1
            dt = proposal
            continue
        sim.state = following
        sim.state.forces_valid = True
        sim.steps += 1
        sim.accepted_steps += 1
        counts["accepted"] += 1
        smallest, largest = min(smallest, h), max(largest, h)
        # a step shortened to land on t_end says nothing about the step the scene allows
        dt = proposal if h >= dt else max(proposal, dt)
        sim.monitor.check_speed(sim, summary["speed"])
        if callback is not None:
            callback(sim)
        if counts["accepted"] % check_every == 0:
            sim.monitor.check(sim)
            sim._maybe_reorder()
    controller.dt = dt
    sim.monitor.check(sim)
    counts["evaluations"] = sim.contacts.evaluations - counts["evaluations"]
    counts.update(dt_smallest=smallest, dt_largest=largest, dt_next=dt)
    return counts
