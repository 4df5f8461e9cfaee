"""Replicas batched on one device: K runs of one scene as K worlds of one DEM simulation.

    results = run_batched(plans, out_dirs)        # cosim.study.replica_run(..., batched=True)

Each replica is a world of one soil.worlds.Worlds (the same bed, or with `--vary-bed` a bed of its
own of the same shape; its own order seed, wheel, rig or rover, results folder, checkpoints). The
simulation lives in this process, which serves it; each run (its rig or rover, coupler, records and
results writer: cosim.runner.Runner, the path of a run alone) runs in a process of its own, whose
soil side is a `RemoteWorld`: the Simulation interface cosim.dem_soil.DemSoil drives, over a pipe. So the K
runs' host work goes on K cores at once instead of one after the other under one interpreter lock
(docs/performance.md section 6): per macro step a run sends its wheels' path and gets its report and
what it reads after the step (`Worlds.view`: its wheels' poses and its walls' loads, read from the
device once for all worlds); the DEM steps every world in the same launches once every run has
asked. A world's results are bit for bit those of its run alone (tests/test_batch.py), and each
folder is an ordinary run folder: `cosim resume FOLDER` continues it alone.

What a batch cannot run (`batch_problem` says why, and the replicas then run one by one): a
terrain other than the DEM, a moving soil patch, an FMU rover (its replicas run one by one).
Under the PID step control (run.step_control = 'pid') each world has its own controller and takes
the substeps its run takes alone (soil.step_control). Shared by the worlds: the clock, the DEM
step at fixed steps, the divergence monitor (a world that diverges stops the batch; each run
reports it with its own last good state). Ctrl-C, SIGTERM or SIGHUP to this process reaches every run,
which stops after its macro step with a checkpoint (a second one: at once); a run whose process
dies leaves the batch (its result says so), the others go on; if this process dies, every run
stops with the error. The runs' folders (one per plan, each its own, none holding a run unless
overwrite, none in use) are checked before anything is settled or run; a run that still fails before
its wheels are placed leaves the batch with them lifted clear of its grains (Worlds.leave(park=True)),
so the others run on, as alone.
"""

from __future__ import annotations

import contextlib
import logging
import os
import pickle
import signal
import socket
import subprocess
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import replace
from multiprocessing.connection import Connection, wait

import numpy as np

from soil.bed import read_bed_header
from soil.errors import ArgumentError, RegolithError
from soil.integrator import make_integrator
from soil.macro import MacroStepReport
from soil.sdf import displaced_geometry
from soil.worlds import World, Worlds, open_bed_worlds

from . import stop_signals
from .beds import Bed, check_memory, settled_bed
from .dem_soil import DemSoil
from .folders import LOCK_FILE, RunFolder
from .launch import open_run
from .plan import RunPlan, enable_step_control
from .runner import RunInterrupted, Runner

log = logging.getLogger(__name__)


def batch_problem(plan: RunPlan) -> str | None:
    """Why the replicas of `plan` cannot run as worlds of one simulation (None: they can)."""
    if plan.terrain.model != "dem":
        return f"terrain.model {plan.terrain.model!r}: only the DEM terrain is batched"
    if plan.patch is not None:
        return "a moving soil patch (rover.patch) changes its grains: its replicas run one by one"
    if plan.rover is not None and plan.rover.model == "fmu":
        return "an FMU rover: its replicas run one by one"
    return None


SOIL_FIELDS = (
    "wheels",
    "device",
    "precision",
    "storage",
    "contact law",
    "integrator",
    "dt",
    "macro step",
    "step control",
)
"""What the worlds of one batch share (their plans must agree on it; their beds, each its own or one
shared, must hold as many grains of the same materials: _beds)."""


def _soil_of(plan: RunPlan) -> tuple:
    wheels = plan.wheels if plan.rover else [plan.wheel]
    return (
        repr([(w.shape, w.material) for w in wheels]),
        plan.device,
        plan.precision,
        plan.storage,
        plan.law,
        plan.integrator,
        plan.dt,
        plan.macro_step,
        (plan.step_control, plan.tolerance, plan.dt_min, plan.dt_max),
    )


def run_batched(plans: list[RunPlan], out_dirs: list[str], overwrite: bool = False) -> list[dict]:
    """Run `plans` (replicas of one scene: any order seeds, any rigs, each on its bed: the same bed
    or beds of one shape, as replicas over beds have) as worlds of one simulation into `out_dirs`;
    returns one result per run as cosim.study.run_task does (label, out_dir, ok,
    status, summary, wall_time, error), each with the batch's figures ('batch': worlds, wall_seconds,
    rounds, step_seconds: the host clock of the macro steps themselves, round_ends: the host clock
    [s] at the end of each, round_steps: each one's step_seconds, serve_seconds: the serving process's
    own host work, its loop's wall less its waits for the runs and the macro steps, and serve_marks:
    that work so far [s] as each macro step's reports have gone out, one per round)."""
    plans, out_dirs = list(plans), list(out_dirs)
    _check_folders(plans, out_dirs, overwrite)  # before any bed is settled or any run starts
    first = plans[0]
    problem = batch_problem(first)
    if problem is not None:
        raise ArgumentError(f"cannot batch these runs: {problem}")
    for k, plan in enumerate(plans[1:], start=1):
        for name, ours, theirs in zip(SOIL_FIELDS, _soil_of(plan), _soil_of(first)):
            if ours != theirs:
                raise ArgumentError(
                    f"run {k} cannot share the soil of run 0: its {name} is {ours!r}, run 0's {theirs!r} "
                    "(batched runs differ only in their order seed and their rig or rover)"
                )
    started = time.perf_counter()
    beds = _beds(plans, out_dirs)
    # a run opens its bed's file, not a bed settled on its own
    plans = [replace(p, bed=replace(p.bed, bed_file=os.path.abspath(b.path))) for p, b in zip(plans, beds)]
    check_memory(plans[0], len(plans))  # the K worlds must fit: checked before they are allocated
    wheels = [(w.shape, w.material) for w in (first.wheels if first.rover else [first.wheel])]
    worlds = open_bed_worlds(
        [bed.saved for bed in beds],
        wheels,
        [p.order_seed for p in plans],
        device=first.device,
        precision=first.precision,
        law=first.law,
        integrator=make_integrator(first.integrator),
        gravity=first.gravity if first.rover else None,
        storage=first.storage,
    )
    enable_step_control(first, worlds.sim)  # PID substeps: a controller per world
    hosts: list[_Host] = []
    try:
        for k, (plan, out, bed) in enumerate(zip(plans, out_dirs, beds)):
            world = worlds.world(k)
            hosts.append(_Host.start(k, world, (plan, out, overwrite, _description(world), bed.surface_height)))
        results, serve_seconds, serve_marks, received = _serve(worlds, hosts)
    finally:
        for host in hosts:
            host.close()
    wall = time.perf_counter() - started
    log.info("%d replicas as one batch of worlds: %.1f s, %d macro steps together", len(plans), wall, worlds.rounds)
    batch = {
        "worlds": len(plans),
        "wall_seconds": wall,
        "rounds": worlds.rounds,
        "step_seconds": worlds.step_seconds,
        "round_ends": list(worlds.round_ends),
        "round_steps": list(worlds.round_steps),
        "serve_seconds": serve_seconds,
        "serve_marks": serve_marks,
    }
    # a stop that arrived, even once every run had ended, is said with every result: a caller that checks
    # it (cosim.study._run_tasks) stops too
    stop = {"stop_received": received[0]} if received else {}
    return [
        {**r, "label": f"replica_{k:03d}", "wall_time": wall, "batch": batch, **stop} for k, r in enumerate(results)
    ]


def _check_folders(plans: list[RunPlan], out_dirs: list[str], overwrite: bool) -> None:
    """A folder per run, distinct and free (none holding a run unless `overwrite`, none in use by
    another process): refused before anything is settled, written or run (a run that could not start
    would leave the batch, the others run on without it)."""
    if not plans:
        raise ArgumentError("run_batched: no plans given: a batch runs one world per plan (at least one)")
    if len(plans) != len(out_dirs):
        raise ArgumentError(
            f"run_batched: {len(plans)} plans for {len(out_dirs)} out_dirs: give one output folder per plan"
        )
    seen: dict[str, int] = {}
    for k, out in enumerate(out_dirs):
        try:
            path = os.path.normcase(os.path.realpath(os.fspath(out)))
        except TypeError:
            raise ArgumentError(f"run_batched: out_dirs[{k}] is {out!r}: an output folder is a path") from None
        if path in seen:
            raise ArgumentError(
                f"run_batched: runs {seen[path]} and {k} have the same output folder {os.fspath(out)!r}: "
                "each run of a batch writes a folder of its own"
            )
        seen[path] = k
    for out in out_dirs:
        folder = RunFolder(out)
        if os.path.lexists(folder.path) and not os.path.isdir(folder.path):
            folder.create()  # names the file in the way
        if os.path.isdir(folder.path):
            folder.check_free(overwrite)
            if os.path.exists(folder.file(LOCK_FILE)):
                with folder.locked():  # FolderInUseError while another process runs in it
                    pass


def _beds(plans: list[RunPlan], out_dirs: list[str]) -> list[Bed]:
    """Each run's bed (cosim.beds.settled_bed: a bed that several runs share is read, or settled in the
    first one's folder, once), refused unless each holds as many grains of the same materials as run
    0's: the worlds of a batch are copies of one scene's shape."""
    found: dict[str, Bed] = {}
    beds = []
    for plan, folder in zip(plans, out_dirs):
        key = plan.bed.bed_file or plan.bed.key
        if key not in found:
            found[key] = settled_bed(plan, folder)
        beds.append(found[key])
    headers = [read_bed_header(bed.path) for bed in beds]
    for k, (bed, header) in enumerate(zip(beds, headers)):
        for name, what in (("particle_count", "grain count"), ("materials", "materials")):
            if header[name] != headers[0][name]:
                raise ArgumentError(
                    f"run {k} cannot share a simulation with run 0: its bed {bed.path} differs from run 0's "
                    f"{beds[0].path} in its {what} ({header[name]!r} against {headers[0][name]!r}); the worlds "
                    "of a batch hold beds of one scene, settled from any seed"
                )
    return beds


# -- the serving side: this process, which owns the simulation ----------------------------------------


_PACKAGES = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
"""Where cosim and soil are found (a run's process imports them from there, installed or not)."""


class _Host:
    """A run's process as the server sees it: a Python of its own (not a fork: the device's context
    would be copied; not multiprocessing's spawn: it would run the caller's script again), its end of a
    socket pair passed as a descriptor, in a session of its own (see _forward_stop_signals)."""

    def __init__(self, index: int, world: World, connection: Connection, process: subprocess.Popen, out_dir: str):
        self.index = index
        self.world = world
        self.connection = connection
        self.process = process
        self.out_dir = out_dir
        self.result: dict | None = None
        self.waiting = False
        """It asked for a macro step and waits for its report."""
        self.ready = False
        """Its run is set up (its wheels placed): the worlds' first forces wait for every run."""

    @classmethod
    def start(cls, index: int, world: World, job: tuple) -> _Host:
        """Start world `index`'s process and send it its job (_run_world's arguments)."""
        ours, theirs = socket.socketpair()
        path = os.pathsep.join(filter(None, [_PACKAGES, os.environ.get("PYTHONPATH")]))
        with theirs:
            process = subprocess.Popen(
                [sys.executable, "-c", "from cosim.batch import world_process; world_process()", str(theirs.fileno())],
                pass_fds=(theirs.fileno(),),
                start_new_session=True,
                env={**os.environ, "PYTHONPATH": path},
            )
        host = cls(index, world, Connection(ours.detach()), process, job[1])
        _send(host, ("job", *job))
        return host

    def close(self) -> None:
        self.connection.close()
        try:
            self.process.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


CALLS = (
    "radii",
    "masses",
    "positions",
    "velocities",
    "boundary_displacements",
    "boundary_wrenches",
    "body_positions",
    "body_rotations",
    "body_wrenches",
    "set_body_motion",
    "refresh_forces",
    "arm_monitor",
    "monitor_armed",
    "check_divergence",
    "state_dict",
    "state_dict_units",
)
"""What a run's process may ask its world for (World's methods of these names)."""


def _description(world: World) -> dict:
    """What a world is and never changes in a run (RemoteWorld keeps it)."""
    return {
        "index": world.index,
        "time": world.time,
        "gravity": world.gravity,
        "particle_count": world.particle_count,
        "body_count": world.body_count,
        "boundary_count": world.boundary_count,
        "body_shapes": world.body_shapes,
        "boundary_kinds": world.boundary_kinds(),
        "boundary_reports": world.boundary_reports(),
        "initial_boundary_geometry": world.initial_boundary_geometry(),
    }


def _sendable(error: BaseException) -> BaseException:
    """The error itself when it crosses a pipe intact, else a RuntimeError naming it."""
    try:
        pickle.loads(pickle.dumps(error))
        return error
    except Exception:  # noqa: BLE001 - any error that does not pickle is named instead
        return RuntimeError(f"{type(error).__name__}: {error}")


def _serve(worlds: Worlds, hosts: list[_Host]) -> tuple[list[dict], float, list[float], list[str]]:
    """Answer the runs' requests until every run is done; returns their results in order, this
    process's own host work [s] (the loop's wall less its waits for messages and the macro steps),
    that work so far at the end of each round (once its reports have gone out), and the names of the
    stop signals that arrived."""
    received: list[str] = []
    previous = _forward_stop_signals(hosts, received)
    started = False
    begun, waited, stepped = time.perf_counter(), 0.0, worlds.step_seconds
    marks: list[float] = []
    rounds = worlds.rounds

    def busy() -> float:
        return time.perf_counter() - begun - waited - (worlds.step_seconds - stepped)

    try:
        while True:
            open_hosts = {h.connection: h for h in hosts if h.result is None}
            if not open_hosts:
                break
            before = time.perf_counter()
            ready = wait(list(open_hosts), timeout=0.5)
            waited += time.perf_counter() - before
            for connection in ready:
                _answer(worlds, open_hosts[connection])  # type: ignore[index]
            if not started and all(h.ready or h.result is not None for h in hosts):
                worlds.ensure_forces()  # every world's wheels placed: their forces once, as alone
                started = True
                for host in hosts:
                    if host.result is None:
                        _send(host, ("go",))
            for host in hosts:
                if host.waiting:
                    try:
                        report = worlds.take(host.index)
                    except BaseException as error:  # noqa: BLE001 - the batch's failure, as this world sees it
                        host.waiting = False
                        _send(host, ("error", _sendable(error)))
                        continue
                    if report is not None:
                        host.waiting = False
                        _send(host, ("report", report, worlds.view(host.index)))
            if worlds.rounds != rounds:
                rounds = worlds.rounds
                marks.append(busy())
    finally:
        stop_signals.restore(previous)
    return [h.result or {} for h in hosts], busy(), marks, received


def _answer(worlds: Worlds, host: _Host) -> None:
    """One message of a run's process."""
    try:
        message = host.connection.recv()
    except (EOFError, OSError):
        with contextlib.suppress(subprocess.TimeoutExpired):
            host.process.wait(timeout=5.0)
        _finish(
            worlds,
            host,
            {
                "out_dir": host.out_dir,
                "ok": False,
                "status": "failed",
                "error": f"the process of world {host.index} ended without a result (exit code "
                f"{host.process.returncode}); its last checkpoint is in {host.out_dir}",
            },
        )
        return
    kind = message[0]
    if kind == "call":
        name, args, kwargs = message[1:]
        try:
            if name not in CALLS:
                raise ArgumentError(f"a world is not asked for {name!r}: allowed {', '.join(CALLS)}")
            value = host.world.monitor.armed if name == "monitor_armed" else getattr(host.world, name)(*args, **kwargs)
            _send(host, ("value", value))
        except BaseException as error:  # noqa: BLE001 - the run's process raises it
            _send(host, ("error", _sendable(error)))
    elif kind == "advance":
        try:
            worlds.submit(host.index, *message[1:])
            host.waiting = True
        except BaseException as error:  # noqa: BLE001
            _send(host, ("error", _sendable(error)))
    elif kind == "ready":
        host.ready = True
    elif kind == "done":
        _finish(worlds, host, message[1])


def _finish(worlds: Worlds, host: _Host, result: dict) -> None:
    host.result = result
    host.waiting = False
    # a run that ended before it was set up (its folder refused, its rig failed to build) has not placed
    # its wheels: they are lifted clear of its grains, which then lie still, as settled, beside the others
    worlds.leave(host.index, park=not host.ready)


def _send(host: _Host, message: tuple) -> None:
    try:
        host.connection.send(message)
    except (BrokenPipeError, OSError):  # its process is gone: the next wait sees its end
        pass


def _forward_stop_signals(hosts: list[_Host], received: list[str]) -> dict:
    """A stop signal here (Ctrl-C, SIGTERM, SIGHUP: cosim.stop_signals) reaches every run's process (each
    has a session of its own, so a terminal's Ctrl-C or hangup arrives once): each stops after its macro
    step with a checkpoint, or at once on a second one; each signal's name is appended to `received`.
    Returns the handlers it replaced."""

    def handler(signum, frame):
        name = signal.Signals(signum).name
        received.append(name)
        log.warning("%s: every run of the batch stops after its macro step with a checkpoint", name)
        for host in hosts:
            if host.result is None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(host.process.pid, signum)

    return stop_signals.install(handler)


# -- a run's side: its own process -----------------------------------------------------------------------


def world_process() -> None:
    """The entry of a run's process (_Host.start): its job from the descriptor in argv[1], then _run_world."""
    connection = Connection(int(sys.argv[1]))
    try:
        _, *job = connection.recv()
    except (EOFError, OSError):
        return
    _run_world(connection, *job)


def _run_world(connection: Connection, plan: RunPlan, out_dir: str, overwrite: bool, description: dict, surface):
    """A run's process: its run alone, on a RemoteWorld; its result goes back as its last message."""
    world = RemoteWorld(connection, description)
    out: dict = {"out_dir": os.path.abspath(out_dir)}
    try:
        soil = DemSoil(world, plan.dt, surface)
        with open_run(plan, out_dir, overwrite=overwrite, soil=soil) as (system, writer, folder):
            runner = Runner(system, writer, folder)
            out["out_dir"] = folder.path
            world.wait_for_start()
            result = runner.run()
        out.update(ok=True, status=result.status, summary=result.summary)
    except BaseException as error:  # noqa: BLE001 - a failed replica is a result
        stopped = isinstance(error, (KeyboardInterrupt, RunInterrupted))  # after its checkpoint, as asked
        out.update(
            ok=False,
            status="interrupted" if stopped else "failed",
            error=f"{type(error).__name__}: {error}",
            traceback=traceback.format_exc(5),
        )
        if stopped:
            out["signal"] = stop_signals.stop_name(error)
    with contextlib.suppress(BrokenPipeError, OSError):
        connection.send(("done", out))
    connection.close()


class BatchServerGone(RegolithError, RuntimeError):
    """The process serving a batch's simulation ended before the run did."""


class _RemoteMonitor:
    def __init__(self, world: RemoteWorld):
        self._world = world

    @property
    def armed(self) -> bool:
        return bool(self._world._call("monitor_armed"))


class RemoteWorld:
    """A world of a batch served by another process (run_batched), with the Simulation interface
    cosim.dem_soil.DemSoil drives (soil.worlds.World's): what never changes is kept, a macro step is one
    request and its answer brings what the run reads after it (Worlds.view); the rest is asked."""

    def __init__(self, connection: Connection, description: dict):
        self._connection = connection
        self.index = int(description["index"])
        self.time = float(description["time"])
        self.gravity = np.asarray(description["gravity"])
        """The world's gravity vector [m/s^2], shape (3,)."""
        self.particle_count = int(description["particle_count"])
        self.body_count = int(description["body_count"])
        self.boundary_count = int(description["boundary_count"])
        self.body_shapes = description["body_shapes"]
        self._kinds = description["boundary_kinds"]
        self._reports = description["boundary_reports"]
        self._initial = description["initial_boundary_geometry"]
        self._path: tuple | None = None
        self._view: dict | None = None
        self.monitor = _RemoteMonitor(self)

    def _exchange(self, message: tuple, meanwhile: Callable[[], None] | None = None):
        try:
            self._connection.send(message)
        except (EOFError, OSError) as error:
            raise self._gone(error) from None
        try:
            if meanwhile is not None:  # the run's own work while the batch steps
                meanwhile()
        finally:  # the answer is read whatever that work met: the next exchange stays in step
            try:
                answer = self._connection.recv()
            except (EOFError, OSError) as error:
                raise self._gone(error) from None
        if answer[0] == "error":
            raise answer[1]
        return answer

    def _gone(self, error: BaseException) -> BatchServerGone:
        return BatchServerGone(
            f"the process serving world {self.index}'s batch ended ({type(error).__name__}); this run's last "
            "checkpoint continues it alone (cosim resume)"
        )

    def _call(self, name: str, *args, **kwargs):
        return self._exchange(("call", name, args, kwargs))[1]

    def wait_for_start(self) -> None:
        """Tell the server this run is set up; return when every run of the batch is."""
        self._exchange(("ready",))

    # -- what the world is ----------------------------------------------------------------
    def boundary_kinds(self) -> np.ndarray:
        return self._kinds.copy()

    def boundary_reports(self) -> np.ndarray:
        return self._reports.copy()

    def initial_boundary_geometry(self) -> np.ndarray:
        return self._initial.copy()

    def boundary_geometry(self, displacement=None) -> np.ndarray:
        shift = self.boundary_displacements() if displacement is None else displacement
        return displaced_geometry(self._kinds, self._initial, shift)

    def radii(self) -> np.ndarray:
        return self._call("radii")

    def masses(self) -> np.ndarray:
        return self._call("masses")

    def positions(self) -> np.ndarray:
        return self._call("positions")

    def velocities(self) -> np.ndarray:
        return self._call("velocities")

    # -- read after a macro step: from its answer ---------------------------------------------
    def _seen(self, name: str):
        return None if self._view is None else self._view[name]

    def boundary_displacements(self) -> np.ndarray:
        seen = self._seen("boundary_displacements")
        return self._call("boundary_displacements") if seen is None else seen.copy()

    def boundary_wrenches(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        seen = self._seen("boundary_wrenches")
        return self._call("boundary_wrenches") if seen is None else tuple(v.copy() for v in seen)

    def body_positions(self) -> np.ndarray:
        seen = self._seen("body_positions")
        return self._call("body_positions") if seen is None else seen.copy()

    def body_rotations(self) -> np.ndarray:
        seen = self._seen("body_rotations")
        return self._call("body_rotations") if seen is None else seen.copy()

    def body_wrenches(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self._call("body_wrenches")

    # -- wheels -------------------------------------------------------------------------------
    def set_body_motion(self, body: int, *args, **kwargs) -> None:
        self._view = None
        self._call("set_body_motion", body, *args, **kwargs)

    def refresh_forces(self) -> None:
        self._view = None
        self._call("refresh_forces")

    def set_body_path(self, span: float, position, orientation, velocity, angular_velocity, end=None) -> None:
        self._path = (position, orientation, velocity, angular_velocity, end)

    def advance_to(
        self, end_time: float, dt: float, path: bool = False, meanwhile: Callable[[], None] | None = None
    ) -> MacroStepReport:
        """The macro step: the request goes out, `meanwhile` (the run's own host work of the step before:
        its records and writer) runs while the batch steps, then the answer is read."""
        body_path, self._path = self._path, None
        self._view = None
        _, report, view = self._exchange(
            ("advance", float(end_time), float(dt), bool(path), body_path), meanwhile=meanwhile
        )
        self._view = view
        self.time = float(view["time"])
        return report

    # -- health and checkpoints ---------------------------------------------------------------
    def arm_monitor(self) -> None:
        self._call("arm_monitor")

    def check_divergence(self) -> None:
        self._call("check_divergence")

    def state_dict(self) -> dict:
        return self._call("state_dict")

    def state_dict_units(self) -> dict[str, str]:
        return self._call("state_dict_units")

    def load_state_dict(self, data: dict) -> None:
        raise ArgumentError("a world of a batch is not loaded from a checkpoint: resume its run on its own")
