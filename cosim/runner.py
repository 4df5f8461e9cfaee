"""The run loop: a coupled system stepped through its landing and drive, macro step by macro step.

    Runner(system, writer, folder).run()       # cosim.launch builds these and calls it

`Runner` steps the system (cosim.system): a landing phase until the wheel rests on the soil,
then the drive; each step's row (cosim.records) goes to results.h5 (cosim.output); snapshots
and checkpoints follow the scene's intervals, and the soil's health is checked every
CHECK_EVERY macro steps and at each checkpoint. A step's row is made and written while the soil
computes the next step (Coupler.step's `meanwhile`: on a GPU the host's records overlap the
device's steps), except where the file must hold it first: before a snapshot or a checkpoint (so
also at a stop and at the end, which write both). At the end the summary is computed from what was written
(cosim.records.run_summary). A first Ctrl-C (or SIGTERM, or SIGHUP: cosim.stop_signals) finishes the macro step,
writes a checkpoint and stops cleanly; a second one stops at once. After the run has ended, a first one
lets its files be finished (results.h5, run.json, the export), then stops. The runner reads the soil
only through the SoilSide contract (cosim.contract).
"""

from __future__ import annotations

import logging
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from soil import SimulationDiverged
from soil.control import quaternion_to_matrix
from soil.errors import RegolithError
from soil.stability import write_checkpoint
from soil.state import STATE_UNITS

from . import metrics, records, stop_signals
from .contract import Particles, RoverDiverged
from .coupler import MacroStepRecord
from .folders import DIVERGED_FILE, RUN_FILE, VTKHDF_FILE, RunFolder, read_json, write_json
from .output import ResultsWriter
from .plan import RunPlan
from .single_wheel import PHASE_LANDING
from .stop_signals import SIGNAL_WORDS
from .system import CoupledSystem, needs_bed, validity
from .vtkhdf import write_vtkhdf

log = logging.getLogger(__name__)

LANDING_FLICKER = 3.0
"""How far the hub's heights over a landing's hold may spread, in multiples of the drift it allows [-]:
a tuned value, not the edge of a measured gap. A wheel rebounding while it touches the soil can meet the
drift at the hold's two ends, the hold lasting about one period of its heave: the tiny scene's default
run lands in such a heave at 2.2 x (kept: it lands at the same step), its other beds' first rebounds
spread 3.1-4.7 x and a restitution of 0.999 6.4 x (refused now: they land later); the main job's hub
sinks steadily, its spread its drift (1 x)."""

CHECK_EVERY = 10
"""Macro steps between full health checks of the soil (SoilSide.check_health)."""

NO_PARTICLES = Particles(np.zeros((0, 3)), np.zeros((0, 3), np.float32), np.zeros(0))
"""The snapshot of a soil without particles (SoilSide.particles() is None)."""


def _relative(path: str, start: str) -> str:
    """`path` relative to `start`, or '' where it has none (another drive)."""
    try:
        return os.path.relpath(path, start)
    except ValueError:
        return ""


class RunDiverged(RegolithError, RuntimeError):
    """The soil (soil.SimulationDiverged) or the rover (cosim.contract.RoverDiverged) diverged; the message
    names where and what to change, and the last checkpoint (a diverged soil's last good state is saved)."""


class RunInterrupted(RegolithError):
    """The run was stopped on request (Ctrl-C, SIGTERM, SIGHUP) after a checkpoint; `cosim resume OUT` continues it.
    A stop asked during the run's last step or while its files were finished (complete, diverged, failed)
    comes after them: the message says how the run ended (a finished run: nothing is left to resume)."""

    def __init__(self, message: str, signal: str = "SIGINT"):
        super().__init__(message)
        self.signal = signal
        """The signal's name: SIGINT (exit 130), SIGTERM (143) or SIGHUP (129)."""


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
        hooks: {'step': f(runner), 'checkpoint': f(runner)} called after each macro step / checkpoint
            (at a 'step' call that step's row may still be unwritten: it is written while the next
            step computes, or before a snapshot or checkpoint).
    """

    def __init__(
        self,
        system: CoupledSystem,
        writer: ResultsWriter,
        folder: RunFolder,
        loop: dict | None = None,
        progress: bool = False,
        hooks: dict | None = None,
        run_id: str | None = None,
    ):
        self.system = system
        self.plan: RunPlan = system.plan
        self.writer = writer
        self.folder = folder
        self.progress = progress
        self.hooks = hooks or {}
        self.stop_requested = False
        self.closing = False
        """The run has ended and its files are being finished: a first stop signal lets them be."""
        self._pending: _Deferred | None = None
        """The last step's row, made and written while the soil computes the next step (or sooner)."""
        self.stop_signal = "SIGINT"
        """The signal that asked for the stop (SIGINT: Ctrl-C, SIGTERM: a scheduler or container, SIGHUP: the
        terminal closed)."""
        self.mesh = system.wheel_mesh()
        loop = loop or {}
        rover = system.rover
        self.drive_start_step = int(loop.get("drive_start_step", -1 if rover.phase == PHASE_LANDING else 0))
        hubs = np.array([k.position for k in rover.wheel_kinematics()], dtype=float)
        # a checkpoint written before the hubs were kept holds the body's position, (3,): what its rows used
        self.drive_start_position = np.broadcast_to(
            np.array(loop.get("drive_start_position", hubs), dtype=float), hubs.shape
        ).copy()
        """Each wheel's hub position when the drive started (or now, before it) [m], shape (W, 3)."""
        self.body_position = np.array(loop.get("body_position", rover.body_kinematics().position), dtype=float)
        """The rover body's position at the last record [m], shape (3,)."""
        self.body_travel = float(loop.get("body_travel", 0.0))
        """The body's horizontal path since the drive started [m]."""
        self.rest_heights = [float(z) for z in np.atleast_1d(loop.get("rest_heights", []))]
        """The hub's height at each landing record [m] (a list: the landing's test of rest reads them)."""
        self.landing_failed = bool(loop.get("landing_failed", False))
        self.next_snapshot = float(loop.get("next_snapshot", system.coupler.time))
        self.next_checkpoint = float(
            loop.get("next_checkpoint", system.coupler.time + self.plan.output.checkpoint_interval)
        )
        self.wall_before = float(loop.get("wall_time", 0.0))
        self.steps_at_start = system.coupler.step_count
        self.last_checkpoint_time = system.coupler.time
        self.session_start_time = system.coupler.time
        """When this session started [s] (a resumed run: its checkpoint's time)."""
        self.forced_steps = int(loop.get("forced_steps", 0))
        """PID substeps kept at run.dt_min over the tolerance, over every session [count]."""
        self.last_good_time: float | None = None
        """A diverged run's last good soil state's time [s]; None while the run has not diverged."""
        self.diverged_elsewhere = False
        """The run stopped because another world of its batch diverged (it may be resumed alone)."""
        self.run_id = run_id or str(read_json(folder.file(RUN_FILE)).get("run_id", ""))
        """Ties every checkpoint to this run (run.json, results.h5 and checkpoint.npz carry it); a resumed
        run's is its checkpoint's (a damaged run.json loses none)."""

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
            system.soil.start_health_checks()
            if self.writer.snapshots == 0:
                self._snapshot()
            while not self.done:
                pending, self._pending = self._pending, None
                try:
                    record = coupler.step(meanwhile=pending)
                except BaseException:
                    self._pending = pending  # the row is still written (below), whatever the step met
                    raise
                if pending is not None:  # done while the soil computed (or now); what its writing met is raised
                    pending.settle()
                self._after_step(record)
                self._count_forced(system.soil.step_statistics())
                if "step" in self.hooks:
                    self.hooks["step"](self)
                last = self.done
                snapshot = last or (
                    plan.output.snapshot_interval > 0 and coupler.time >= self.next_snapshot - 1e-9 * plan.macro_step
                )
                scheduled = last or coupler.time >= self.next_checkpoint - 1e-9 * plan.macro_step
                # a snapshot and a checkpoint read the state anyway: checked first, none holds a diverging soil
                if coupler.step_count % CHECK_EVERY == 0 or snapshot or scheduled:
                    system.soil.check_health()
                if snapshot:
                    self._snapshot()
                if scheduled or self.stop_requested:
                    if scheduled:  # a stop on request checks nothing extra: the check times stay those
                        # of an uninterrupted run (the bounds track them)
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
            if error.elsewhere:  # another world of the batch: this run's soil is sound, its rows too
                self.diverged_elsewhere = True
                message = f"the run stopped during the {self._phase()}: {error}; this run's own soil is sound. " + (
                    f"Its last checkpoint (t = {self.last_checkpoint_time:.6g} s) continues it alone: "
                    f"cosim resume {self.folder.path}"
                    if os.path.isfile(self.folder.checkpoint)
                    else "It has no checkpoint yet: run it again"
                )
                raise RunDiverged(message) from error
            # the rows after the last good state are the diverging steps': the summary stops before them
            good = error.last_good
            self.last_good_time = float(good["time"]) if good is not None else self.session_start_time
            from .advice import stiff_mode_hint

            hint = stiff_mode_hint(plan) if needs_bed(plan) else ""
            message = (
                f"the run diverged during the {self._phase()}: {error}. Lower {plan.step_keys}, soften or stiffen "
                f"the soil as `cosim advise` says, or shorten run.macro_step, and run the scene again (a resume "
                f"would repeat the same steps){hint}"
            )
            if error.last_good is not None:
                write_checkpoint(self.folder.file(DIVERGED_FILE), error.last_good, STATE_UNITS)
                message += f"; the last good soil state is {self.folder.file(DIVERGED_FILE)}"
            raise RunDiverged(message) from error
        except RoverDiverged as error:
            status = "diverged"
            message = (
                f"the rover diverged during the {self._phase()}: {error}. Run the scene again with a shorter "
                "run.macro_step or a gentler drive (a resume would repeat the same steps)"
            )
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
            self.closing = True  # a first stop signal from here lets the run's files be finished (seconds)
            try:
                if bar is not None:
                    bar.close()
                status, summary = self._close(status, message, started)
            finally:
                stop_signals.restore(previous_handlers)
            if self.stop_requested and status != "interrupted":  # asked as the run ended: the caller stops too
                words = SIGNAL_WORDS.get(self.stop_signal, self.stop_signal)
                if status in ("complete", "unsteady"):
                    ended = f"the run had ended ({status}) and its files are finished; nothing to resume"
                else:  # its own message says what follows (a change to run it again, or a resume)
                    ended = f"the run had ended ({status}: {message}) and its files are finished"
                    if status == "failed" and os.path.isfile(self.folder.checkpoint):
                        ended += f"; cosim resume {self.folder.path} continues it from its last checkpoint"
                raise RunInterrupted(f"{words}: {ended}", signal=self.stop_signal)
        return RunResult(self.folder.path, status, summary)

    def _close(self, status: str, message: str, started: float) -> tuple[str, dict]:
        """The run's closing work, whatever ended it: the last step's row, results.h5 closed and marked with
        the status and the summary, run.json, then (a finished run) the VTKHDF export. Returns (status,
        summary). A step that fails (a full disk) after the run stopped for another reason is logged, that
        reason being the one reported; after a finished run it makes the run 'failed', run.json says so,
        and it is raised once run.json is written."""
        failure: list[Exception] = []

        def failed(what: str, error: Exception) -> None:
            nonlocal status, message
            if status in ("complete", "unsteady"):  # the closing's own failure is the run's
                status, message = "failed", f"{what}: {type(error).__name__}: {error}"
                failure.append(error)
            else:  # the reason the run stopped is reported; this one is said
                log.warning("%s: %s failed too: %s: %s", self.folder.path, what, type(error).__name__, error)

        def attempt(what: str, action) -> None:
            try:
                action()
            except Exception as error:
                failed(what, error)

        wall = self.wall_before + time.perf_counter() - started
        if self._pending is not None:  # a run stopped by an error still writes its last step's row
            pending, self._pending = self._pending, None
            pending()
            if pending.error is not None:
                log.warning("%s: the last step's row was not written: %s", self.folder.path, pending.error)
        attempt("closing results.h5", self.writer.close)
        try:
            summary = self.summary(wall, time.perf_counter() - started)
        except Exception as error:  # a summary must not hide why the run stopped
            summary = {"error": f"no summary: {type(error).__name__}: {error}"}
            failed("the summary", error)
        if status == "complete" and summary.get("steady_state") != metrics.STEADY:
            status = "unsteady"
            message = f"no steady-state result: {summary.get('steady_state')}"
            log.warning("%s: %s", self.folder.path, message)
        attempt("marking results.h5", lambda: self.writer.mark(status, message, summary, xdmf=False))
        try:  # a view derived from results.h5: a failure is said, the run's status stays its own
            self.writer.update_xdmf()
        except Exception as error:
            log.warning(
                "%s: results.xdmf not brought up to date (%s: %s); results.h5 holds every record (`cosim export "
                "vtkhdf` writes a ParaView file from it)",
                self.folder.path,
                type(error).__name__,
                error,
            )
        info = read_json(self.folder.file(RUN_FILE))
        # what a garbled run.json lost, written again from the run itself (its findings are in results.h5)
        for key, value in (
            ("run_id", self.run_id),
            ("device", self.plan.device),
            ("precision", self.plan.precision),
        ):
            info.setdefault(key, value)
        info.update(status=status, message=message, summary=summary, wall_time=wall)
        info["units"] = {**info.get("units", {}), "wall_time": "s"}  # the summary's own: summary.units
        attempt("writing run.json", lambda: write_json(self.folder.file(RUN_FILE), info))
        if status in ("complete", "unsteady"):  # a stopped run: `cosim export vtkhdf` when wanted
            self._export_vtkhdf()
        if failure:
            raise failure[0]
        return status, summary

    def _export_vtkhdf(self) -> None:
        """results.vtkhdf from the closed results.h5; a failed export is logged, never hides how the run ended."""
        if self.writer.snapshots == 0:
            return
        try:
            write_vtkhdf(self.folder.results)
        except Exception as error:
            log.warning("%s not written (`cosim export vtkhdf %s` retries): %s", VTKHDF_FILE, self.folder.path, error)

    def _after_step(self, record: MacroStepRecord) -> None:
        """The landing's decision now (it sets the next step's command); what the step's row reads of
        the two sides now; the row itself made and written later (_pending), in step order."""
        system = self.system
        rover = system.rover
        phase, state = rover.phase, rover.state_row()  # over the step: the landing below may end it
        driving = self.drive_start_step >= 0  # the step that ends the landing still belongs to it
        if phase == PHASE_LANDING:
            self._landing(record)
        drive_start = self.drive_start_position if self.drive_start_step >= 0 else None
        facts = records.step_facts(system)

        def write_row() -> None:
            row = records.step_row(
                system,
                record,
                phase,
                state,
                drive_start,
                self.body_position if driving else None,
                self.body_travel,
                facts,
            )
            self.body_position, self.body_travel = row["rover_position"].copy(), row["rover_travel"]
            self.writer.append_step(row)

        self._pending = _Deferred(write_row)

    def _count_forced(self, statistics) -> None:
        """Count the PID's substeps kept at run.dt_min over the tolerance; the first is warned of (the run
        then does not meet its tolerance, and may take very many substeps)."""
        if statistics is None or not statistics.forced:
            return
        if not self.forced_steps:
            plan = self.plan
            shortest = f"{plan.dt_min:.3g} s" if plan.dt_min is not None else "run.dt_max x 1e-4"
            log.warning(
                "%s: at t = %.6g s the PID kept %d substeps at its shortest step (run.dt_min: %s) with an error "
                "over run.tolerance (%g): the tolerance is not met there; loosen run.tolerance or lower "
                "run.dt_min (the summary counts them: dem_steps_forced)",
                self.folder.path,
                self.system.coupler.time,
                statistics.forced,
                shortest,
                plan.tolerance,
            )
        self.forced_steps += statistics.forced

    def _settle_row(self) -> None:
        """Make and write the last step's row now (raising what its writing met)."""
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.settle()

    def _landing(self, record: MacroStepRecord) -> None:
        """The wheel has landed when, over the last `hold_steps` macro steps, it touched the soil at
        every step, its hubs sank by less than speed_limit x the hold time (grains rearranging under it
        make the vertical speed flicker, so the drift over the window is the criterion) and their
        heights over the window spanned less than LANDING_FLICKER times that (a wheel bouncing on the
        soil while touching it can meet the drift at the window's two ends). Then the drive starts."""
        landing = self.plan.landing
        touching = all(w.contact_count > 0 for w in record.wrenches)
        self.rest_heights = (self.rest_heights + [min(k.position[2] for k in record.kinematics)]) if touching else []
        self.rest_heights = self.rest_heights[-(landing.hold_steps + 1) :]
        hold_time = landing.hold_steps * self.plan.macro_step
        if (
            len(self.rest_heights) > landing.hold_steps
            and abs(self.rest_heights[-1] - self.rest_heights[0]) < landing.speed_limit * hold_time
            and max(self.rest_heights) - min(self.rest_heights) < LANDING_FLICKER * landing.speed_limit * hold_time
        ):
            rover = self.system.rover
            rover.start_drive()
            self.drive_start_step = self.system.coupler.step_count
            self.drive_start_position = np.array([k.position for k in record.kinematics], dtype=float)
            log.info("landed at t = %.4g s; driving for %.4g s", record.time, self.plan.scene.run.duration)
        elif self.system.coupler.step_count >= landing.max_steps:
            self.landing_failed = True
            what = "wheel" if self.plan.rover is None else "rover"
            advice = "raise landing.max_time, or lighten it if it keeps sinking"
            if not touching:  # a wheel in the air: a bounce the macro step does not resolve gains energy
                unresolved = [
                    f
                    for f in validity(self.plan, self.system.soil.surface_height)
                    if f.check in ("coupling_step", "scm_coupling_step") and not f.ok
                ]
                off = "a wheel was off the soil at the end"
                advice = (
                    f"{off}, bouncing: {unresolved[0].check}: {unresolved[0].message}"
                    if unresolved
                    else f"{off}; {advice}"
                )
            log.warning(
                "the %s was not at rest on the soil after landing.max_time = %g s (%s)",
                what,
                self.plan.scene.landing.max_time,
                advice,
            )

    def _snapshot(self) -> None:
        self._settle_row()  # the file holds the step's row before its snapshot
        system = self.system
        vertices, _, owner = self.mesh
        posed = system.posed_wheel_vertices(vertices, owner)
        body = system.rover.body_kinematics()
        particles = system.soil.particles()
        if particles is None:  # a soil without particles: snapshots of the wheels and the rover only
            particles = NO_PARTICLES
        ragged = particles.ids is not None
        self.writer.add_snapshot(
            system.coupler.time,
            particles.position,
            particles.velocity.astype(np.float32),
            posed.astype(np.float32),
            rover_pose=(body.position, quaternion_to_matrix(body.orientation)),
            radius=particles.radius if ragged else None,
            ids=particles.ids,
        )
        if self.plan.output.snapshot_interval > 0:
            self.next_snapshot = self.system.coupler.time + self.plan.output.snapshot_interval

    LOOP_UNITS = {
        "drive_start_step": "count",
        "drive_start_position": "m",
        "body_position": "m",
        "body_travel": "m",
        "rest_heights": "m",
        "landing_failed": "1",
        "next_snapshot": "s",
        "next_checkpoint": "s",
        "wall_time": "s",
        "steps": "count",
        "snapshots": "count",
        "forced_steps": "count",
    }
    """The unit of each entry of loop_state()."""

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
            "forced_steps": self.forced_steps,
        }

    def _phase(self) -> str:
        """'landing' or 'drive': the phase the run is in (for its messages)."""
        return "landing" if self.drive_start_step < 0 else "drive"

    def _checkpoint(self, wall: float) -> None:
        self._settle_row()  # the checkpoint's loop state (rows, travel) counts the step's row
        self.writer.flush()
        data = self.system.state_dict()
        data.update({f"loop/{k}": np.asarray(v) for k, v in self.loop_state(wall).items()})
        data["scene_toml"] = np.array(self.plan.scene.to_toml())
        data["scene_base_dir"] = np.array(self.plan.scene.base_dir or "")
        data["bed_path"] = np.array("" if self.system.bed is None else self.system.bed.path)
        # the bed seen from the run's folder too: a run folder moved whole resumes on the bed it carries
        data["bed_path_from_folder"] = np.array(
            _relative(self.system.bed.path, self.folder.path) if self.system.bed else ""
        )
        data["run_id"] = np.array(self.run_id)
        units = self.system.state_dict_units()
        units.update({f"loop/{k}": v for k, v in self.LOOP_UNITS.items()})
        texts = ("scene_toml", "scene_base_dir", "bed_path", "bed_path_from_folder", "run_id")
        units.update(dict.fromkeys(texts, "text"))
        write_checkpoint(self.folder.checkpoint, data, units)
        self.last_checkpoint_time = self.system.coupler.time

    # -- progress and summary --------------------------------------------------------------
    def _bar(self):
        if not self.progress:
            return None
        from tqdm import tqdm

        landing = self.drive_start_step < 0
        return tqdm(
            total=self.plan.landing.max_steps if landing else self.plan.drive_steps,
            desc="landing (ends at rest)" if landing else "driving",
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
            bar.total, bar.n = self.plan.drive_steps, coupler.step_count - self.drive_start_step
        else:  # the landing's steps so far, of the most it may take (it ends when the wheels rest)
            bar.set_description_str("landing (ends at rest)", refresh=False)
            bar.total, bar.n = self.plan.landing.max_steps, coupler.step_count
        wall = time.perf_counter() - started
        done = coupler.step_count - self.steps_at_start
        dt, steps = records.soil_step(self.plan)
        elements = self.system.soil.books().element_count
        said = f", {elements * steps * done / max(wall, 1e-9):.3g} particle-steps/s" if elements else ""  # SCM: none
        bar.set_postfix_str(f"t = {coupler.time:.4g} s sim, dt {dt:.3g} s{said}", refresh=False)
        bar.refresh()

    def summary(self, wall: float, session_wall: float) -> dict:
        """The run's summary (cosim.records.run_summary): wall [s] over all sessions, session_wall [s] this one's."""
        return records.run_summary(
            self.plan,
            self.system,
            self.writer.path,
            landed=not self.landing_failed,
            wall=wall,
            session_wall=session_wall,
            steps_done=self.system.coupler.step_count - self.steps_at_start,
            last_good_time=self.last_good_time,
            forced_steps=self.forced_steps,
            diverged_elsewhere=self.diverged_elsewhere,
        )


class _Deferred:
    """Work done once, when called (Coupler.step calls it while the soil computes) or at `settle`; an
    error it meets is kept (the soil's step goes on) and raised by `settle`. A KeyboardInterrupt (a
    second Ctrl-C: stop at once) is not kept: it stops the step too."""

    def __init__(self, work: Callable[[], None]):
        self.work = work
        self.done = False
        self.error: BaseException | None = None

    def __call__(self) -> None:
        if self.done:
            return
        self.done = True
        try:
            self.work()
        except Exception as error:  # noqa: BLE001 - raised by settle, after the soil's step
            self.error = error

    def settle(self) -> None:
        self()
        if self.error is not None:
            raise self.error


def _install_stop_handlers(runner: Runner) -> dict:
    """First stop signal (Ctrl-C, SIGTERM, SIGHUP: cosim.stop_signals): stop cleanly after the macro step
    (with a checkpoint); a second: at once. Returns the handlers it replaced (empty outside the main thread,
    where Python allows none)."""

    def handler(signum, frame):
        name = signal.Signals(signum).name
        if runner.stop_requested:
            raise KeyboardInterrupt(f"{name} twice: stopped at once")
        runner.stop_requested = True
        runner.stop_signal = name
        words = SIGNAL_WORDS.get(name, name)
        # once the run has ended its files are finished first (results.h5, run.json)
        doing = (
            "the run has ended; finishing its files"
            if runner.closing
            else "finishing the macro step and writing a checkpoint"
        )
        log.warning("%s: %s (%s again to stop at once)", words, doing, words)

    return stop_signals.install(handler)
