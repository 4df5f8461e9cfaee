"""What a run writes about itself: each macro step's row, the results file's attributes, the summary.

    facts = step_facts(system)       # at the step's end: what the row reads of the two sides
    row = step_row(system, record, phase, rover_state, drive_start, previous_body, body_travel, facts)
    attrs = attributes(plan, system, source, findings)
    summary = run_summary(plan, system, results_path, landed, wall, session_wall, steps_done)

A row holds every series of results.h5 (cosim.output: /wheels, /rover, /soil and, for a soil
with walls, /boundaries) for one macro step, computed from the coupler's MacroStepRecord with
the quantities of cosim.metrics. The soil's part of it comes through the SoilSide contract
(cosim.contract): its books, its inner-step statistics and its walls' loads. The summary is
computed from what was written (cosim.metrics.summarize / summarize_rover) plus the run's facts.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from . import advice, metrics
from .contract import StepStatistics, wheel_frame
from .coupler import MacroStepRecord
from .output import read_series, series_until
from .plan import RunPlan
from .system import TERRAIN_MODELS, CoupledSystem, validity


def step_facts(system: CoupledSystem) -> dict:
    """What a step's row reads of the two sides, read at the step's end (the row itself may be made
    later, while the next step runs): the rover's 'command' (speed [rad/s] (W,), torque [N m] (W,))
    and 'body' kinematics, the soil's 'books', inner-step 'statistics' and 'wall_loads' (None
    without walls)."""
    rover, soil = system.rover, system.soil
    speed, torque = (np.array(v, dtype=np.float64) for v in rover.command_row())
    return {
        "command": (speed, torque),
        "body": rover.body_kinematics(),
        "books": soil.books(),
        "statistics": soil.step_statistics(),
        "wall_loads": soil.wall_loads(),
    }


def step_row(
    system: CoupledSystem,
    record: MacroStepRecord,
    phase: int,
    rover_state: np.ndarray,
    drive_start: np.ndarray | None,
    previous_body: np.ndarray | None,
    body_travel: float,
    facts: dict,
) -> dict:
    """One macro step's row for ResultsWriter.append_step.

    phase: the rover's phase over the step (cosim.single_wheel.PHASE_LANDING / PHASE_DRIVING);
    rover_state: its state row (K,) at the end of the step; drive_start: each wheel's hub position [m]
    (W, 3) where the drive started (None: it has not, travel stays 0); previous_body: the rover body's
    position [m] (3,) at the previous row while driving (None before); body_travel: its path so far
    [m]; facts: step_facts(system) as read at the step's end. The row's
    'rover_position' and 'rover_travel' are what the next row takes as previous_body and
    body_travel."""
    row: dict[str, Any] = {"time": record.time, "phase": phase, "rover_state": rover_state}
    per_wheel = [
        metrics.wheel_quantities(k, w, g, None if drive_start is None else drive_start[i])
        for i, (k, w, g) in enumerate(zip(record.kinematics, record.wrenches, system.geometries))
    ]
    for name in metrics.WHEEL_UNITS:
        row[name] = np.array([q[name] for q in per_wheel])
    row["speed_command"], row["torque_command"] = facts["command"]
    body = facts["body"]
    spins = [
        float(k.angular_velocity @ wheel_frame(k.orientation, g.axis_local)[0])
        for k, g in zip(record.kinematics, system.geometries)
    ]
    radii = [g.rim_radius for g in system.geometries]
    quantities = metrics.rover_quantities(body, per_wheel, record.wrenches, radii, spins, previous_body, body_travel)
    for name, value in (
        ("position", body.position),
        ("orientation", body.orientation),
        ("linear_velocity", body.linear_velocity),
        ("angular_velocity", body.angular_velocity),
        *quantities.items(),
    ):
        row[f"rover_{name}"] = value
    books = facts["books"]
    soil_row = {
        "particle_count": books.element_count,
        "mass": books.mass,
        "mass_added": books.mass_added,
        "mass_removed": books.mass_removed,
        "moves": books.moves,
        **step_statistics(facts["statistics"], system.plan.macro_step),
    }
    for name, value in soil_row.items():
        row[f"soil_{name}"] = value
    row["position"] = np.array([k.position for k in record.kinematics])
    row["orientation"] = np.array([k.orientation for k in record.kinematics])
    row["linear_velocity"] = np.array([k.linear_velocity for k in record.kinematics])
    row["angular_velocity"] = np.array([k.angular_velocity for k in record.kinematics])
    for name in ("force", "torque", "force_end", "torque_end"):
        row[name] = np.array([getattr(w, name) for w in record.wrenches])
    row["contact_count"] = np.array([w.contact_count for w in record.wrenches])
    row["work_on_rover"] = record.work_on_rover
    row["work_on_soil"] = record.work_on_soil
    loads = facts["wall_loads"]
    if loads is not None:
        row.update({f"boundary_{name}": value for name, value in loads.items()})
    return row


def step_statistics(statistics: StepStatistics | None, span: float) -> dict:
    """The soil's inner steps over a macro step of `span` [s] (None: none yet, or a soil without
    them): steps, rejected substeps, dt min/mean/max [s] and force evaluations, as the SOIL_SERIES
    of results.h5 name them."""
    if statistics is None:
        return dict(
            dem_steps=0, dem_steps_rejected=0, dt_min=np.nan, dt_mean=np.nan, dt_max=np.nan, force_evaluations=0
        )
    return dict(
        dem_steps=statistics.steps,
        dem_steps_rejected=statistics.rejected,
        dt_min=statistics.dt_min,
        dt_mean=span / max(statistics.steps, 1),
        dt_max=statistics.dt_max,
        force_evaluations=statistics.evaluations,
    )


def step_summary(series: dict) -> dict:
    """The run's DEM steps from results.h5's series: dem_steps, dem_steps_rejected,
    force_evaluations [-] in total and dt_min, dt_mean, dt_max [s] over the macro steps."""
    steps = series.get("soil_dem_steps")
    if steps is None or not len(steps) or not np.sum(steps):
        return {}
    taken = steps > 0
    span = float(np.sum(series["soil_dt_mean"][taken] * steps[taken]))
    return dict(
        dem_steps=int(np.sum(steps)),
        dem_steps_rejected=int(np.sum(series["soil_dem_steps_rejected"])),
        force_evaluations=int(np.sum(series["soil_force_evaluations"])),
        dt_min=float(np.min(series["soil_dt_min"][taken])),
        dt_mean=span / float(np.sum(steps)),
        dt_max=float(np.max(series["soil_dt_max"][taken])),
    )


def attributes(plan: RunPlan, system: CoupledSystem, source: str, findings) -> dict:
    """The root attributes of a new results.h5 (cosim.output's layout) for a run of `plan`;
    source: the scene file's text; findings: the validity checks at the start (cosim.advice)."""
    rover = plan.rover
    if rover is None:
        assert plan.testbed is not None  # a plan has a testbed or a rover
        mode = plan.testbed.mode
    else:
        mode = rover.drive.kind
    dt, substeps = soil_step(plan)
    out = {
        "name": plan.name,
        "scene_toml": plan.scene.to_toml(),
        "scene_source": source,
        "precision": plan.precision,
        "device": plan.device,
        "scheme": plan.scheme,
        "integrator": plan.integrator,
        "order_seed": -1 if plan.order_seed is None else plan.order_seed,
        "dt": dt,
        "macro_step": plan.macro_step,
        "substeps": substeps,
        "duration": plan.scene.run.duration,
        "gravity": np.asarray(plan.gravity),
        "surface_height": system.soil.surface_height,
        "start_position": system.rover.position.copy(),
        "omega": plan.drive_omega,
        "rim_radius": plan.wheel.rim_radius,
        "outer_radius": plan.wheel.outer_radius,
        "wheel_load": plan.wheel_load,
        "mode": mode,
        "particle_count": system.soil.books().element_count,
        "wheel_names": json.dumps(list(system.rover.wheel_names)),
        "bed": json.dumps({} if system.bed is None else system.bed.info, default=float),
        "findings": json.dumps([f.as_dict() for f in findings]),
        "kind": "testbed" if rover is None else "rover",
        "rim_radii": np.array([w.rim_radius for w in plan.wheels]),
        "outer_radii": np.array([w.outer_radius for w in plan.wheels]),
    }
    if rover is not None:
        out.update(
            rover_model=rover.model,
            rover_mass=rover.mass,
            drive=rover.drive.name,
            stuck_slip=rover.stuck_slip,
            slope=plan.slope,
        )
    out["units"] = json.dumps({key: ATTRIBUTE_UNITS[key] for key in out if key in ATTRIBUTE_UNITS})
    return out


def soil_step(plan: RunPlan) -> tuple[float, int]:
    """(dt [s], steps per macro step) of the soil a run steps, as its terrain model says
    (cosim.system.TerrainModel.steps): the DEM's (plan.dt, plan.substeps; the PID varies them), SCM's own
    on SCM alone, the analytic terrain's wrench samples."""
    return TERRAIN_MODELS[plan.terrain.model].steps(plan)


ATTRIBUTE_UNITS = {
    "order_seed": "1",
    "dt": "s",
    "macro_step": "s",
    "substeps": "count",
    "duration": "s",
    "gravity": "m/s^2",
    "surface_height": "m",
    "start_position": "m",
    "omega": "rad/s",
    "rim_radius": "m",
    "outer_radius": "m",
    "wheel_load": "N",
    "particle_count": "count",
    "rim_radii": "m",
    "outer_radii": "m",
    "rover_mass": "kg",
    "stuck_slip": "1",
    "slope": "rad",
}
"""The units of results.h5's numeric root attributes (its `units` attribute, JSON)."""


def _froude_number(plan: RunPlan, findings) -> float:
    """The run's Froude number [-]: at the drive's speeds (RunPlan.froude_number), or, where its controller
    sets them as it goes, the validity check's at the measured wheel speeds (nan without one)."""
    if np.isfinite(plan.froude_number):
        return plan.froude_number
    measured = [f.value for f in findings if f.check in ("froude", "scm_froude")]  # a mixed terrain's: both
    return float(max(measured)) if measured else float("nan")


def run_summary(
    plan: RunPlan,
    system: CoupledSystem,
    results: str,
    landed: bool,
    wall: float,
    session_wall: float,
    steps_done: int,
    last_good_time: float | None = None,
    forced_steps: int = 0,
    diverged_elsewhere: bool = False,
) -> dict:
    """The run's summary, computed from results.h5 at `results` (cosim.metrics.summarize or
    summarize_rover) plus run facts: landed: the landing ended at rest; wall [s]: the run's wall
    time over all its sessions; session_wall [s] and steps_done: this session's wall time and
    macro steps (its throughput); last_good_time [s]: a diverged run's last good state, the rows
    after it left out of the metrics (they stay in the file) and the time in the summary;
    forced_steps: the PID's substeps kept at run.dt_min over the tolerance (dem_steps_forced);
    diverged_elsewhere: the run stopped as another world of its batch diverged (its own soil sound)."""
    written = read_series(results)
    series = written if last_good_time is None else series_until(written, last_good_time + 1e-9 * plan.macro_step)
    out: dict[str, Any]
    if not len(series["time"]):
        out = {"steady_state": metrics.TOO_SHORT}
    elif plan.rover is None:
        assert plan.testbed is not None  # a plan has a testbed or a rover
        out = metrics.summarize(
            series,
            rim_radius=plan.wheel.rim_radius,
            wheel_load=plan.wheel_load,
            mode=plan.testbed.mode,
            landed=landed,
            grain_radius=plan.bed.spec.radius_mean,
            grouser_count=plan.wheel.grouser_count,
            ramped=plan.testbed.mode == "free" and plan.testbed.drawbar_ramp > 0,
        )
    else:
        out = metrics.summarize_rover(
            series,
            rim_radii=[w.rim_radius for w in plan.wheels],
            weight=plan.rover.mass * plan.g,
            stuck_slip=plan.rover.stuck_slip,
            landed=landed,
            grain_radius=plan.bed.spec.radius_mean,
            grouser_counts=[w.grouser_count for w in plan.wheels],
        )
    soil = system.soil
    books = soil.books()
    if books.moving:
        out.update(
            patch_moves=books.moves,
            soil_mass_added=books.mass_added,
            soil_mass_removed=books.mass_removed,
            soil_mass=books.mass,
            soil_mass_initial=books.mass_initial,
            particle_count_max=int(np.max(series["soil_particle_count"])) if len(series["time"]) else 0,
        )
    stepped = step_summary(series)  # the PID's longest substep judges its contact resolution (cosim.advice.check)
    findings = validity(plan, soil.surface_height, {**out, **stepped})
    not_judged = [check for check, _ in advice.judged_after_the_run(plan, findings)]  # nothing measured for them
    if not_judged:
        out["not_judged"] = not_judged
    out.update(
        simulated_time=float(system.coupler.time),
        macro_steps=int(system.coupler.step_count),
        wall_time=float(wall),
        particle_count=int(books.element_count),
        dt=soil_step(plan)[0],
        step_control=plan.step_control,
        **stepped,
        macro_step=plan.macro_step,
        froude_number=_froude_number(plan, findings),
        coupling_energy_created=float(system.coupler.energy_created),
        coupling_energy_exchanged=float(system.coupler.energy_exchanged),
        coupling_energy_over_tolerance=bool(system.coupler.energy_over_tolerance),
        validity=advice.verdict(findings, not_judged),
        findings=[f.as_dict() for f in findings],
    )
    if session_wall > 0 and steps_done:
        # DEM steps of this session's macro steps: the PID's vary (the last `steps_done` rows of the series)
        taken = written.get("soil_dem_steps")  # every row of this session, a diverged run's last ones too
        steps = (
            float(np.sum(taken[-steps_done:]))
            if taken is not None and len(taken) >= steps_done
            else soil_step(plan)[1] * steps_done
        )
        out["particle_steps_per_second"] = float(books.element_count * steps / session_wall)
    if last_good_time is not None:
        out["last_good_time"] = float(last_good_time)
    if diverged_elsewhere:
        out["diverged_elsewhere"] = True
    if plan.step_control == "pid":
        out["dem_steps_forced"] = int(forced_steps)
    out["summary_rule"] = metrics.SUMMARY_RULE  # the steady-window rule it was made under
    out["units"] = metrics.summary_units(out)  # run.json and results.h5 carry each number's unit
    return out
