"""The run loop: scene -> plan -> coupled system -> loop -> writer.

    result = run_scene("examples/phobos_single_wheel.toml", "runs/phobos")
    result = resume("runs/phobos")

`run_scene` resolves the scene into a plan (cosim.plan), takes the output folder's lock
(cosim.folders), settles or reuses the bed (cosim.beds), builds the coupled system
(cosim.system) and only then replaces a previous run. `Runner` steps the system macro
step by macro step: a landing phase until the wheel rests on the soil, then the drive;
each step's record goes to results.h5 (cosim.output) with the quantities of
cosim.metrics; snapshots and checkpoints follow the scene's intervals. The summary is
computed from what was written. `resume` continues from checkpoint.npz to the result an
uninterrupted run gives (bitwise on the CPU). A first Ctrl-C finishes the macro step,
writes a checkpoint and stops cleanly; a second one stops at once.
"""

from __future__ import annotations

import logging
import os
import signal
import time
import uuid
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from soil import SimulationDiverged
from soil.errors import RegolithError
from soil.stability import read_checkpoint, write_checkpoint

from . import advice, metrics
from .beds import Bed, bed_from_file, check_memory, settled_bed, write_json
from .coupler import MacroStepRecord
from .folders import DIVERGED_FILE, RUN_FILE, SCENE_FILE, VTKHDF_FILE, RunFolder
from .output import ResultsWriter, read_series
from .plan import RunPlan, load_plan, resolve
from .scene import Scene, SceneError, scene_from_text
from .single_wheel import PHASE_LANDING
from .system import CoupledSystem
from .terrain import quat_to_matrix, wheel_frame
from .vtkhdf import write_vtkhdf

log = logging.getLogger(__name__)

CHECK_EVERY = 10
"""Macro steps between full divergence checks of the soil (soil.DivergenceMonitor)."""


class RunDiverged(RegolithError, RuntimeError):
    """The DEM exploded; the message names where and what to change, the last good state is saved."""


class RunInterrupted(RegolithError):
    """The run was stopped on request (Ctrl-C, SIGTERM) after a checkpoint; `cosim resume OUT` continues it."""

    def __init__(self, message: str, signal: str = "SIGINT"):
        super().__init__(message)
        self.signal = signal
        """The signal's name: SIGINT (exit 130) or SIGTERM (exit 143)."""


@dataclass
class RunResult:
    out_dir: str
    status: str
    """complete | unsteady (ran, but no steady state: summary['steady_state'] says why)."""
    summary: dict = field(default_factory=dict)


class Runner:
    """Steps a coupled system through landing and drive, writing records, snapshots and checkpoints.

    Args:
        system: the coupled system (cosim.system), at its start or restored from a checkpoint.
        writer: the results writer, new or resumed.
        folder: the run folder.
        loop: the loop's own state from a checkpoint (None: a new run).
        progress: show a tqdm bar.
        hooks: {'step': f(runner), 'checkpoint': f(runner)} called after each macro step / checkpoint.
    """

    def __init__(
        self,
        system: CoupledSystem,
        writer: ResultsWriter,
        folder: RunFolder,
        loop: dict | None = None,
        progress: bool = False,
        hooks: dict | None = None,
    ):
        self.system = system
        self.plan: RunPlan = system.plan
        self.writer = writer
        self.folder = folder
        self.progress = progress
        self.hooks = hooks or {}
        self.stop_requested = False
        self.stop_signal = "SIGINT"
        """The signal that asked for the stop (SIGINT: Ctrl-C, SIGTERM: a scheduler or container)."""
        self.mesh = system.wheel_mesh()
        loop = loop or {}
        rover = system.rover
        self.drive_start_step = int(loop.get("drive_start_step", -1 if rover.phase == PHASE_LANDING else 0))
        self.drive_start_position = np.array(loop.get("drive_start_position", rover.position.copy()), dtype=float)
        self.body_position = np.array(loop.get("body_position", rover.body_kinematics().position), dtype=float)
        """The rover body's position at the last record [m], shape (3,)."""
        self.body_travel = float(loop.get("body_travel", 0.0))
        """The body's horizontal path since the drive started [m]."""
        self.rest_heights = [float(z) for z in np.atleast_1d(loop.get("rest_heights", []))]
        self.landing_failed = bool(loop.get("landing_failed", False))
        self.next_snapshot = float(loop.get("next_snapshot", system.coupler.time))
        self.next_checkpoint = float(
            loop.get("next_checkpoint", system.coupler.time + self.plan.output.checkpoint_interval)
        )
        self.wall_before = float(loop.get("wall_time", 0.0))
        self.steps_at_start = system.coupler.step_count
        self.last_checkpoint_time = system.coupler.time
        self.run_id = str(_read_json(folder.file(RUN_FILE)).get("run_id", ""))
        """Ties every checkpoint to this run (run.json, results.h5 and checkpoint.npz carry it)."""

    # -- the loop ------------------------------------------------------------------------
    @property
    def done(self) -> bool:
        steps = self.system.coupler.step_count
        return self.landing_failed or (
            self.drive_start_step >= 0 and steps - self.drive_start_step >= self.plan.drive_steps
        )

    def run(self) -> RunResult:
        plan, system = self.plan, self.system
        coupler = system.coupler
        started = time.perf_counter()
        previous_handlers = _install_stop_handlers(self)
        bar = self._bar()
        status, message = "running", ""
        try:
            if not system.sim.monitor.armed:
                system.sim.monitor.arm(system.sim)
            if self.writer.snapshots == 0:
                self._snapshot()
            while not self.done:
                record = coupler.step()
                self._after_step(record)
                if "step" in self.hooks:
                    self.hooks["step"](self)
                if coupler.step_count % CHECK_EVERY == 0:
                    system.sim.monitor.check(system.sim)
                last = self.done
                if plan.output.snapshot_interval > 0 and coupler.time >= self.next_snapshot - 1e-9 * plan.macro_step:
                    self._snapshot()
                elif last:
                    self._snapshot()
                scheduled = last or coupler.time >= self.next_checkpoint - 1e-9 * plan.macro_step
                if scheduled or self.stop_requested:
                    if scheduled:  # a stop on request checks nothing extra: the check times stay those
                        system.sim.monitor.check(system.sim)  # of an uninterrupted run (the bounds track them)
                        self.next_checkpoint = coupler.time + plan.output.checkpoint_interval  # saved with it
                    self._checkpoint(time.perf_counter() - started)
                    if "checkpoint" in self.hooks:
                        self.hooks["checkpoint"](self)
                self._update_bar(bar, started)
                if self.stop_requested and not last:
                    words = SIGNAL_WORDS.get(self.stop_signal, self.stop_signal)
                    raise RunInterrupted(
                        f"{words}: stopped at t = {coupler.time:.6g} s after a checkpoint; continue with: "
                        f"cosim resume {self.folder.path}",
                        signal=self.stop_signal,
                    )
            status = "complete"
        except SimulationDiverged as error:
            status = "diverged"
            phase = "landing" if self.drive_start_step < 0 else "drive"
            message = (
                f"the run diverged during the {phase}: {error}. Change {plan.dt_setting} (the DEM step is now "
                f"{plan.dt:.3g} s), soften or stiffen the soil as `cosim advise` says, or shorten run.macro_step. "
                + (
                    f"The last checkpoint is {self.folder.checkpoint} (t = {self.last_checkpoint_time:.6g} s)"
                    if os.path.isfile(self.folder.checkpoint)
                    else "It diverged before the first checkpoint: there is none to resume from"
                )
            )
            if error.last_good is not None:
                write_checkpoint(self.folder.file(DIVERGED_FILE), error.last_good)
                message += f"; the last good soil state is {self.folder.file(DIVERGED_FILE)}"
            raise RunDiverged(message) from error
        except (KeyboardInterrupt, RunInterrupted) as error:
            status = "interrupted"
            message = str(error) or (
                f"interrupted at t = {coupler.time:.6g} s; resume continues from the checkpoint "
                f"at t = {self.last_checkpoint_time:.6g} s"
            )
            raise
        except BaseException as error:
            status, message = "failed", f"{type(error).__name__}: {error}"
            raise
        finally:
            for number, previous in previous_handlers.items():
                signal.signal(number, previous)
            if bar is not None:
                bar.close()
            wall = self.wall_before + time.perf_counter() - started
            self.writer.close()
            try:
                summary = self.summary(wall, time.perf_counter() - started)
            except Exception as error:  # a summary must not hide why the run stopped
                summary = {"error": f"no summary: {type(error).__name__}: {error}"}
                if status == "complete":
                    raise
            if status == "complete" and summary.get("steady_state") != metrics.STEADY:
                status = "unsteady"
                message = f"no steady-state result: {summary.get('steady_state')}"
                log.warning("%s: %s", self.folder.path, message)
            self.writer.mark(status, message, summary)
            if status in ("complete", "unsteady"):  # a stopped run: `cosim export vtkhdf` when wanted
                self._export_vtkhdf()
            info = _read_json(self.folder.file(RUN_FILE))
            info.update(status=status, message=message, summary=summary, wall_time=wall)
            write_json(self.folder.file(RUN_FILE), info)
        return RunResult(self.folder.path, status, summary)

    def _export_vtkhdf(self) -> None:
        """results.vtkhdf from the closed results.h5; a failed export is logged, never hides how the run ended."""
        if self.writer.snapshots == 0:
            return
        try:
            write_vtkhdf(self.folder.results)
        except Exception as error:
            log.warning("%s not written (`cosim export vtkhdf %s` retries): %s", VTKHDF_FILE, self.folder.path, error)

    def _after_step(self, record: MacroStepRecord) -> None:
        system = self.system
        rover = system.rover
        row = {"time": record.time, "phase": rover.phase, "rover_state": rover.state_row()}
        driving = self.drive_start_step >= 0  # the step that ends the landing still belongs to it
        if rover.phase == PHASE_LANDING:
            self._landing(record)
        drive_start = self.drive_start_position if self.drive_start_step >= 0 else None
        per_wheel = [
            metrics.wheel_quantities(k, w, g, drive_start)
            for k, w, g in zip(record.kinematics, record.wrenches, system.geometries)
        ]
        for name in metrics.WHEEL_UNITS:
            row[name] = np.array([q[name] for q in per_wheel])
        row["speed_command"], row["torque_command"] = rover.command_row()
        body = rover.body_kinematics()
        spins = [
            float(k.angular_velocity @ wheel_frame(k.orientation, g.axis_local)[0])
            for k, g in zip(record.kinematics, system.geometries)
        ]
        radii = [g.rim_radius for g in system.geometries]
        quantities = metrics.rover_quantities(
            body, per_wheel, record.wrenches, radii, spins, self.body_position if driving else None, self.body_travel
        )
        self.body_position, self.body_travel = body.position.copy(), quantities["travel"]
        for name, value in (
            ("position", body.position),
            ("orientation", body.orientation),
            ("linear_velocity", body.linear_velocity),
            ("angular_velocity", body.angular_velocity),
            *quantities.items(),
        ):
            row[f"rover_{name}"] = value
        books = self._soil_books()
        books.update(_step_statistics(system.soil.last_report, self.plan.macro_step))
        for name, value in books.items():
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
        if system.sim.model.boundary_count:
            force, torque, contacts = system.sim.boundary_wrenches()
            row.update(
                boundary_force=force,
                boundary_torque=torque,
                boundary_contact_count=contacts,
                boundary_displacement=system.sim.boundary_displacements(),
            )
        self.writer.append_step(row)

    def _soil_books(self) -> dict:
        """particle_count, mass [kg], mass_added, mass_removed [kg], moves: the soil's books now."""
        patch = self.system.patch
        if patch is not None:
            b = patch.books()
            return {
                "particle_count": b["particle_count"],
                "mass": b["soil_mass"],
                "mass_added": b["mass_added"],
                "mass_removed": b["mass_removed"],
                "moves": b["moves"],
            }
        sim = self.system.sim
        if not hasattr(self, "_static_mass"):
            self._static_mass = float(np.sum(sim.model.mass_numpy()))
        return {
            "particle_count": sim.model.particle_count,
            "mass": self._static_mass,
            "mass_added": 0.0,
            "mass_removed": 0.0,
            "moves": 0,
        }

    def _landing(self, record: MacroStepRecord) -> None:
        """The wheel has landed when, over the last `hold_steps` macro steps, it touched the soil at
        every step and its hubs sank by less than speed_limit x the hold time (grains rearranging
        under it make the vertical speed flicker, so the drift over the window is the criterion).
        Then the drive starts."""
        landing = self.plan.landing
        touching = all(w.contact_count > 0 for w in record.wrenches)
        self.rest_heights = (self.rest_heights + [min(k.position[2] for k in record.kinematics)]) if touching else []
        self.rest_heights = self.rest_heights[-(landing.hold_steps + 1) :]
        hold_time = landing.hold_steps * self.plan.macro_step
        if (
            len(self.rest_heights) > landing.hold_steps
            and abs(self.rest_heights[-1] - self.rest_heights[0]) < landing.speed_limit * hold_time
        ):
            rover = self.system.rover
            rover.start_drive()
            self.drive_start_step = self.system.coupler.step_count
            self.drive_start_position = rover.position.copy()
            log.info("landed at t = %.4g s; driving for %.4g s", record.time, self.plan.scene.run.duration)
        elif self.system.coupler.step_count >= landing.max_steps:
            self.landing_failed = True
            log.warning(
                "the %s was not at rest on the soil after landing.max_time = %g s (raise landing.max_time, "
                "or lighten it if it keeps sinking)",
                "wheel" if self.plan.rover is None else "rover",
                self.plan.scene.landing.max_time,
            )

    def _snapshot(self) -> None:
        system = self.system
        sim = system.sim
        vertices, _, owner = self.mesh
        posed = system.posed_wheel_vertices(vertices, owner)
        body = system.rover.body_kinematics()
        patch = system.patch
        self.writer.add_snapshot(
            system.coupler.time,
            sim.positions(),
            sim.velocities().astype(np.float32),
            posed.astype(np.float32),
            rover_pose=(body.position, quat_to_matrix(body.orientation)),
            radius=None if patch is None else sim.model.radius_numpy(),
            ids=None if patch is None else patch.ids,
        )
        if self.plan.output.snapshot_interval > 0:
            self.next_snapshot = self.system.coupler.time + self.plan.output.snapshot_interval

    def loop_state(self, wall: float) -> dict:
        """The loop's own state (what `Runner(..., loop=...)` takes back)."""
        return {
            "drive_start_step": self.drive_start_step,
            "drive_start_position": self.drive_start_position,
            "body_position": self.body_position,
            "body_travel": self.body_travel,
            "rest_heights": np.asarray(self.rest_heights, dtype=np.float64),
            "landing_failed": self.landing_failed,
            "next_snapshot": self.next_snapshot,
            "next_checkpoint": self.next_checkpoint,
            "wall_time": self.wall_before + wall,
            "steps": self.writer.steps,
            "snapshots": self.writer.snapshots,
        }

    def _checkpoint(self, wall: float) -> None:
        self.writer.flush()
        data = self.system.state_dict()
        data.update({f"loop/{k}": np.asarray(v) for k, v in self.loop_state(wall).items()})
        data["scene_toml"] = np.array(self.plan.scene.to_toml())
        data["scene_base_dir"] = np.array(self.plan.scene.base_dir or "")
        data["bed_path"] = np.array(self.system.bed.path)
        data["run_id"] = np.array(self.run_id)
        write_checkpoint(self.folder.checkpoint, data)
        self.last_checkpoint_time = self.system.coupler.time

    # -- progress and summary --------------------------------------------------------------
    def _bar(self):
        if not self.progress:
            return None
        from tqdm import tqdm

        return tqdm(
            total=self.plan.drive_steps,
            desc="landing",
            unit="step",
            leave=True,
            bar_format="{desc}: {n}/{total} macro steps [{elapsed}<{remaining}, {postfix}]",
        )

    def _update_bar(self, bar, started: float) -> None:
        if bar is None:
            return
        coupler = self.system.coupler
        if self.drive_start_step >= 0:
            bar.set_description_str("driving", refresh=False)
            bar.n = coupler.step_count - self.drive_start_step
        wall = time.perf_counter() - started
        done = coupler.step_count - self.steps_at_start
        rate = self.system.sim.model.particle_count * self.plan.substeps * done / max(wall, 1e-9)
        bar.set_postfix_str(
            f"t = {coupler.time:.4g} s sim, dt {self.plan.dt:.3g} s, {rate:.3g} particle-steps/s", refresh=False
        )
        bar.refresh()

    def summary(self, wall: float, session_wall: float) -> dict:
        """The run's summary, computed from results.h5 (cosim.metrics.summarize) plus run facts."""
        plan, system = self.plan, self.system
        series = read_series(self.writer.path)
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
                landed=not self.landing_failed,
                grain_radius=plan.bed.spec.radius_mean,
            )
        else:
            out = metrics.summarize_rover(
                series,
                rim_radii=[w.rim_radius for w in plan.wheels],
                weight=plan.rover.mass * plan.g,
                stuck_slip=plan.rover.stuck_slip,
                landed=not self.landing_failed,
            )
        if system.patch is not None:
            books = system.patch.books()
            out.update(
                patch_moves=books["moves"],
                soil_mass_added=books["mass_added"],
                soil_mass_removed=books["mass_removed"],
                soil_mass=books["soil_mass"],
                soil_mass_initial=books["mass_initial"],
                particle_count_max=int(np.max(series["soil_particle_count"])) if len(series["time"]) else 0,
            )
        findings = advice.check(plan, system.soil.surface_height, out.get("sinkage_tips"))
        out.update(
            simulated_time=float(system.coupler.time),
            macro_steps=int(system.coupler.step_count),
            wall_time=float(wall),
            particle_count=int(system.sim.model.particle_count),
            dt=plan.dt,
            step_control=plan.step_control,
            **step_summary(series),
            macro_step=plan.macro_step,
            froude_number=plan.froude_number,
            coupling_energy_created=float(system.coupler.energy_created),
            validity=advice.verdict(findings),
            findings=[f.as_dict() for f in findings],
        )
        done = system.coupler.step_count - self.steps_at_start
        if session_wall > 0 and done:
            # DEM steps of this session's macro steps: the PID's vary (the last `done` rows of the series)
            taken = series.get("soil_dem_steps")
            steps = float(np.sum(taken[-done:])) if taken is not None and len(taken) >= done else plan.substeps * done
            out["particle_steps_per_second"] = float(system.sim.model.particle_count * steps / session_wall)
        return out


def _step_statistics(report, span: float) -> dict:
    """The DEM steps of a macro step (soil.MacroStepReport; None before the first): steps, rejected
    substeps, dt min/mean/max [s] and force evaluations, as the SOIL_SERIES of results.h5 name them."""
    if report is None:
        return dict(
            dem_steps=0, dem_steps_rejected=0, dt_min=np.nan, dt_mean=np.nan, dt_max=np.nan, force_evaluations=0
        )
    return dict(
        dem_steps=report.steps,
        dem_steps_rejected=report.rejected,
        dt_min=report.dt_min,
        dt_mean=span / max(report.steps, 1),
        dt_max=report.dt_max,
        force_evaluations=report.evaluations,
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


def _read_json(path: str) -> dict:
    import json

    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError):
        return {}


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""Ctrl-C, and SIGTERM (what batch schedulers and `docker stop` send): both stop a run cleanly."""
SIGNAL_WORDS = {"SIGINT": "Ctrl-C"}
"""How a message names a stop signal."""


def _install_stop_handlers(runner: Runner) -> dict:
    """First Ctrl-C or SIGTERM: stop cleanly after the macro step (with a checkpoint); a second: at once.
    Returns the handlers it replaced (empty outside the main thread, where Python allows none)."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return {}

    def handler(signum, frame):
        name = signal.Signals(signum).name
        if runner.stop_requested:
            raise KeyboardInterrupt(f"{name} twice: stopped at once")
        runner.stop_requested = True
        runner.stop_signal = name
        words = SIGNAL_WORDS.get(name, name)
        log.warning("%s: finishing the macro step and writing a checkpoint (%s again to stop at once)", words, words)

    return {number: signal.signal(number, handler) for number in STOP_SIGNALS}


# ------------------------------------------------------------------------------------
# entry points


def _attributes(plan: RunPlan, system: CoupledSystem, source: str, findings) -> dict:
    import json

    rover = plan.rover
    if rover is None:
        assert plan.testbed is not None  # a plan has a testbed or a rover
        mode = plan.testbed.mode
    else:
        mode = rover.drive.kind
    out = {
        "name": plan.name,
        "scene_toml": plan.scene.to_toml(),
        "scene_source": source,
        "precision": plan.precision,
        "device": plan.device,
        "scheme": plan.scheme,
        "integrator": plan.integrator,
        "order_seed": -1 if plan.order_seed is None else plan.order_seed,
        "dt": plan.dt,
        "macro_step": plan.macro_step,
        "substeps": plan.substeps,
        "duration": plan.scene.run.duration,
        "gravity": np.asarray(plan.gravity),
        "surface_height": system.soil.surface_height,
        "start_position": system.rover.position.copy(),
        "omega": plan.drive_omega,
        "rim_radius": plan.wheel.rim_radius,
        "outer_radius": plan.wheel.outer_radius,
        "wheel_load": plan.wheel_load,
        "mode": mode,
        "particle_count": system.sim.model.particle_count,
        "wheel_names": json.dumps(list(system.rover.wheel_names)),
        "bed": json.dumps(system.bed.info, default=float),
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
    return out


def run_plan(
    plan: RunPlan,
    out_dir: str,
    overwrite: bool = False,
    progress: bool = False,
    hooks: dict | None = None,
    source: str = "",
) -> RunResult:
    """Run a resolved plan into `out_dir` (see the module docstring)."""
    check_memory(plan)  # before anything is allocated or written
    folder = RunFolder(out_dir)
    with folder.locked():
        folder.check_free(overwrite)
        bed = settled_bed(plan, folder.path, progress=progress)
        system = CoupledSystem.build(plan, bed)
        findings = advice.check(plan, system.soil.surface_height)
        for finding in findings:
            if not finding.ok:
                log.warning("validity: %s", finding.message)
        # everything is built: only now the previous run goes
        folder.clear_run()
        run_id = uuid.uuid4().hex
        with open(folder.file(SCENE_FILE), "w") as f:
            f.write(plan.scene.to_toml())
        write_json(
            folder.file(RUN_FILE),
            {
                "status": "running",
                "run_id": run_id,
                "device": plan.device,
                "precision": plan.precision,
                "bed": bed.info,
                "findings": [f.as_dict() for f in findings],
            },
        )
        try:
            writer = ResultsWriter.create(
                folder.results,
                attrs={**_attributes(plan, system, source, findings), "run_id": run_id},
                radius=system.sim.model.radius_numpy(),
                wheel_count=len(system.rover.wheel_names),
                mesh=system.wheel_mesh(),
                rover_columns=system.rover.state_columns,
                rover_units=system.rover.state_units,
                boundaries=system.boundaries(),
                flush_every=plan.output.flush_every,
                ragged=system.patch is not None,
            )
            return Runner(system, writer, folder, progress=progress, hooks=hooks).run()
        finally:
            system.close()


def run_scene(
    scene: Scene | str | os.PathLike,
    out_dir: str,
    overwrite: bool = False,
    progress: bool = False,
    hooks: dict | None = None,
    overrides=None,
) -> RunResult:
    """Run a scene (a Scene or a TOML path, with --set overrides) into `out_dir`."""
    source = ""
    if isinstance(scene, Scene):
        plan = resolve(scene)
    else:
        path = os.fspath(scene)
        plan = load_plan(path, overrides)
        with open(path) as f:
            source = f.read()
    return run_plan(absolute_paths(plan), out_dir, overwrite=overwrite, progress=progress, hooks=hooks, source=source)


def absolute_paths(plan: RunPlan) -> RunPlan:
    """The plan whose scene names wheel.file and bed.bed_file by absolute paths, so that the run
    folder's scene.toml does not depend on where the original scene file was."""
    scene = plan.scene
    changes = {}
    if scene.wheel.type == "mesh" and scene.wheel.file:
        changes["wheel.file"] = scene.resolve(scene.wheel.file)
    if scene.bed.bed_file:
        changes["bed.bed_file"] = scene.resolve(scene.bed.bed_file)
    rover = scene.rover
    if rover is not None:
        if rover.file:
            changes["rover.file"] = scene.resolve(rover.file)
        for name, shape in (rover.wheel_shape or {}).items():
            if shape.type == "mesh":
                changes[f"rover.wheel_shape.{name}.file"] = scene.resolve(shape.file)
        if not isinstance(rover.drive, str) and rover.drive.file:
            changes["rover.drive.file"] = scene.resolve(rover.drive.file)
        for name, drive in (rover.controllers or {}).items():
            if drive.file:
                changes[f"rover.controllers.{name}.file"] = scene.resolve(drive.file)
    return plan.with_changes(**changes) if changes else plan


def load_checkpoint(path: str) -> dict:
    """A checkpoint's arrays (numpy; no pickles), its checksum verified (DamagedFileError when damaged)."""
    return read_checkpoint(path)


FINISHED = ("complete", "unsteady")
"""The statuses of a run whose results are written to the end."""


def resume(out_dir: str, progress: bool = False, hooks: dict | None = None) -> RunResult:
    """Continue a run from its checkpoint to the result an uninterrupted run gives.

    Every file is checked before anything is changed: a damaged results.h5 or checkpoint, or a
    checkpoint of another run, is refused (DamagedFileError naming the file and what is left) and the
    folder stays as it was. A run whose drive is complete in the checkpoint but whose results were not
    finished (killed after its final checkpoint) gets its results finished: status, summary, run.json.
    """
    folder = RunFolder(out_dir)
    if not os.path.isdir(folder.path):
        raise FileNotFoundError(f"{folder.path!r} is not a folder: nothing to resume")
    needed = (SCENE_FILE, RUN_FILE, os.path.basename(folder.checkpoint), os.path.basename(folder.results))

    def check_files() -> None:
        for name in needed:
            if not os.path.isfile(folder.file(name)):
                raise FileNotFoundError(f"{folder.path!r} has no {name}: not a run folder that can be resumed")

    check_files()  # before the lock: a folder that is not a run gets no .lock either
    with folder.locked():
        check_files()
        checkpoint, info = _checked_inputs(folder)
        base_dir = str(checkpoint["scene_base_dir"]) if "scene_base_dir" in checkpoint else ""
        scene = scene_from_text(str(checkpoint["scene_toml"]), base_dir=base_dir or None)
        with open(folder.file(SCENE_FILE)) as f:
            if f.read() != scene.to_toml():
                log.warning("scene.toml was edited after the run started; the checkpoint's copy of the scene is used")
        plan = resolve(scene)
        steps = int(checkpoint["loop/steps"])
        if checkpoint["coupler/step_count"] and _finished(checkpoint, plan):
            if info.get("status") in FINISHED and _results_status(folder.results) == info["status"]:
                log.info("%s: the run is already complete", folder.path)
                return RunResult(folder.path, info["status"], info.get("summary", {}))
            log.info("%s: the drive is complete in the checkpoint; finishing the results", folder.path)
        bed_path = str(checkpoint["bed_path"])
        try:
            bed = bed_from_file(bed_path, "checkpoint bed")
        except SceneError as error:
            raise SceneError(error.problems + [f"the run's bed {bed_path!r} is needed to resume"]) from None
        _check_run_bed(bed_path, info.get("bed", {}))
        bed = Bed(bed.path, bed.surface_height, info.get("bed", bed.info))
        system = CoupledSystem.build(plan, bed)
        try:
            system.load_state_dict(checkpoint)
            writer = ResultsWriter.resume(
                folder.results, steps, int(checkpoint["loop/snapshots"]), flush_every=plan.output.flush_every
            )
            loop = {k[len("loop/") :]: v for k, v in checkpoint.items() if k.startswith("loop/")}
            return Runner(system, writer, folder, loop=loop, progress=progress, hooks=hooks).run()
        finally:
            system.close()


def _checked_inputs(folder: RunFolder) -> tuple[dict, dict]:
    """(checkpoint arrays, run.json) of a folder to resume, after checking that results.h5 is readable, that
    the checkpoint is intact and that both belong to the same run; DamagedFileError naming the file otherwise."""
    from soil.errors import DamagedFileError

    from .output import check_results

    unchanged = "; nothing was changed"
    try:
        checkpoint = load_checkpoint(folder.checkpoint)
    except DamagedFileError as error:
        raise DamagedFileError(f"{error}{unchanged}. {_recoverable(folder.results)}") from None
    at = f"t = {float(checkpoint.get('coupler/time', np.nan)):.6g} s"
    try:
        attrs = check_results(folder.results)
    except DamagedFileError as error:
        raise DamagedFileError(
            f"{error}{unchanged}. The checkpoint ({at}) is intact, but the records it continues are lost: "
            "start the run again with `cosim run SCENE --out FOLDER --overwrite`"
        ) from None
    info = _read_json(folder.file(RUN_FILE))
    run_id = str(checkpoint["run_id"]) if "run_id" in checkpoint else None
    expected = info.get("run_id") or attrs.get("run_id")
    if run_id is not None and expected is not None:
        same = run_id == expected
    else:  # a run written before run ids: its scene must be the checkpoint's
        same = str(checkpoint["scene_toml"]) == attrs.get("scene_toml", str(checkpoint["scene_toml"]))
    if not same:
        name = scene_from_text(str(checkpoint["scene_toml"])).scene.name
        raise DamagedFileError(
            f"{folder.checkpoint}: the checkpoint belongs to another run (scene {name!r}, run id {run_id}; "
            f"this folder's run is {expected}){unchanged}. Put back this run's checkpoint, or start it again "
            "with `cosim run SCENE --out FOLDER --overwrite`"
        )
    return checkpoint, info


def _recoverable(results: str) -> str:
    """What can still be read of a results.h5, in words (for a message about a damaged folder)."""
    from soil.errors import DamagedFileError

    from .output import check_results

    try:
        check_results(results)
        series = read_series(results)
    except (DamagedFileError, OSError, KeyError, ValueError, RuntimeError):
        return f"{results} is damaged too: nothing can be recovered; start the run again with --overwrite"
    count = len(series["time"])
    status = series["attrs"].get("status")
    if status in FINISHED:
        return f"{results} is intact and finished (status {status}, {count} macro steps): the run's result is kept"
    last = f" (up to t = {series['time'][-1]:.6g} s)" if count else ""
    return (
        f"{results} is readable: it holds {count} macro steps{last}, the results up to its last flush "
        "(cosim plot FOLDER shows them); to finish the run start it again with --overwrite"
    )


def _results_status(path: str) -> str:
    from .output import open_results

    with open_results(path) as f:
        status = f.attrs.get("status", "")
    return status.decode() if isinstance(status, bytes) else str(status)


def _check_run_bed(path: str, info: dict) -> None:
    """Refuse a run's bed that is not the one it started on (replaced since: another scene's bed)."""
    from soil.bed import read_bed_header
    from soil.errors import DamagedFileError

    key = info.get("key")
    if not key:
        return
    found = read_bed_header(path)
    if (found["key"] and found["key"] != key) or found["particle_count"] != info.get(
        "particle_count", found["particle_count"]
    ):
        raise DamagedFileError(
            f"{path}: the run's bed was replaced ({found['particle_count']} grains, key {found['key'] or 'none'}; "
            f"the run started on {info.get('particle_count')} grains, key {key}); nothing was changed"
        )


def _finished(checkpoint: dict, plan: RunPlan) -> bool:
    start = int(checkpoint["loop/drive_start_step"])
    return bool(checkpoint["loop/landing_failed"]) or (
        start >= 0 and int(checkpoint["coupler/step_count"]) - start >= plan.drive_steps
    )


def final_state(out_dir: str) -> dict:
    """The latest checkpoint's system state arrays (for comparisons)."""
    data = load_checkpoint(os.path.join(out_dir, "checkpoint.npz"))
    return {k: v for k, v in data.items() if k.split("/")[0] in ("soil", "rover", "coupler")}


__all__ = [
    "RunDiverged",
    "RunInterrupted",
    "RunResult",
    "Runner",
    "final_state",
    "load_checkpoint",
    "resume",
    "run_plan",
    "run_scene",
]
