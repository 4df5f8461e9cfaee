"""Ensembles of runs, on dask.distributed (a LocalCluster, or --scheduler ADDRESS), or serially.

- replicas (`cosim run --replicas K`): K runs that differ only in the summation order
  (run.order_seed = the scene's run.order_seed (0 when unset) + replica index: a permutation of the
  grain indices) on one settled
  bed; mean, standard deviation and 95 % interval of each steady-state metric, and
  whether the result is macroscopically deterministic (cosim.metrics.ensemble). With
  `--vary-bed` (vary='bed') replica k also settles a bed of its own from bed.seed + k:
  the scatter between beds of one soil, which the summation order's on one bed understates.
  Wheels on SCM take replica k's soil from the calibration's bed k (`calibrate-scm --replicas R`:
  [source] replica_fits), so an SCM run's error bar is its calibration's scatter between beds.
- precision: the paper's experiment (its figures 3, 4): replicas per precision; the
  scatter and wall time per precision, as a table (study.csv, study.json) and plots.
- slip: the drawbar-pull/slip curve: replicas at each imposed slip, after landing;
  DP, DP/W, driving torque and sinkage against slip with error bars.
- timestep: the largest stable DEM step (the step grows from the scene's until it
  explodes, a bounded number of tries) next to the advisor's recommended range.
- sweep: a grid over scene keys (--param wheel.radius=0.03,0.04 ...), one run per point.

Warp's CPU kernels are single-threaded, so the cluster uses processes with one thread
each. On a GPU, replicas, slip studies and each precision of a precision study run as worlds of
one simulation instead (cosim.batch, `--batched`; each run bit for bit as alone; replicas over beds
too, each world on its own bed). A replica that
fails is reported; the others still finish. Each row, point and set of replicas carries its runs'
validity verdict (`validity`: ensemble_validity, run_validity), as their run.json findings give it.
Tasks carry the scene as TOML text plus overrides, and each worker resolves its own plan.
"""

from __future__ import annotations

import collections
import contextlib
import csv
import functools
import io
import ipaddress
import itertools
import json
import logging
import math
import os
import re
import shutil
import signal
import time
import traceback
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib

from soil import quiet_warp
from soil.errors import ArgumentError, DamagedFileError, InternalError, RegolithError
from soil.files import atomic_write_text

from . import advice, metrics, stop_signals
from .beds import BED_FILE, BED_INFO_FILE, settled_bed, settling_cost
from .folders import RESULTS_FILE, RUN_FILE, SCENE_FILE, RunFolder, finite_or_null, read_json, write_json
from .launch import FINISHED
from .plan import MAX_PHASE_STEPS, RunPlan, resolve
from .runner import RunInterrupted

if TYPE_CHECKING:  # dask is imported when a study runs on it
    from dask.distributed import Client, LocalCluster
from .scene import INT64_MAX, SceneError, is_number, key_unit, scene_from_text

log = logging.getLogger(__name__)

PRECISION_ORDER = ("single", "mixed", "double")

METRIC_UNITS = metrics.SUMMARY_UNITS
"""The unit of each metric a study tabulates: the run summary's (cosim.metrics)."""


# ------------------------------------------------------------------------------------
# tasks (module-level functions: picklable for dask workers)


def task_plan(task: dict) -> RunPlan:
    """The plan of a task: its scene text with its overrides (relative to the scene's folder `base_dir`)."""
    return resolve(scene_from_text(task["scene_toml"], base_dir=task.get("base_dir"), overrides=task.get("overrides")))


def run_task(task: dict) -> dict:
    """Run one scene (task: scene_toml, overrides, out_dir, label, overwrite); never raises."""
    from .launch import run_plan

    started = time.perf_counter()
    out = {"label": task.get("label"), "out_dir": task["out_dir"], "overrides": task.get("overrides", {})}
    try:
        quiet_warp()
        result = run_plan(task_plan(task), task["out_dir"], overwrite=task.get("overwrite", False))
        out.update(ok=True, status=result.status, summary=result.summary)
    except BaseException as error:  # noqa: BLE001 - a failed replica is a result, not a crash
        stopped = isinstance(error, (KeyboardInterrupt, RunInterrupted))
        out.update(
            ok=False,
            status="interrupted" if stopped else "failed",
            error=f"{type(error).__name__}: {error}",
            traceback=traceback.format_exc(limit=5),
        )
        if stopped:  # a stop asked for stops the study (serial)
            raise
    out["wall_time"] = time.perf_counter() - started
    return out


def settle_task(task: dict) -> dict:
    """Settle the bed of a scene into task['folder'] (cached there)."""
    quiet_warp()
    os.makedirs(task["folder"], exist_ok=True)
    bed = settled_bed(task_plan(task), task["folder"])
    return {"path": bed.path, "info": bed.info}


# ------------------------------------------------------------------------------------
# execution


MAX_WORKERS_PER_CORE = 4
"""Most LocalCluster workers a CPU core may have (--workers): more only wait, each a process to start."""


def check_workers(workers: int | None) -> None:
    """ArgumentError unless `workers` (--workers) is None or 1 .. MAX_WORKERS_PER_CORE a CPU core."""
    most = MAX_WORKERS_PER_CORE * (os.cpu_count() or 1)
    if workers is not None and not 1 <= workers <= most:
        raise ArgumentError(
            f"--workers must be 1 .. {most} ({MAX_WORKERS_PER_CORE} a CPU core: each is a process with its "
            f"own Warp and soil), got {workers}"
        )


def check_executor(kind: str, scheduler: str | None) -> None:
    """ArgumentError unless the tasks can run where asked: 'serial', or 'dask' with dask.distributed
    installed; and a scheduler address, if given, of a form dask connects to (check_scheduler)."""
    if kind not in ("dask", "serial"):
        raise ArgumentError(f"executor must be 'dask' or 'serial', got {kind!r}")
    if kind == "dask":
        _addressing()
    check_scheduler(scheduler)


def _addressing():
    """dask.distributed's address parsers; ArgumentError naming the extra to install when it is missing."""
    try:
        from distributed.comm.addressing import parse_address, parse_host_port
    except ImportError as error:
        raise ArgumentError(
            f"running the tasks on dask needs dask.distributed ({error}): pip install 'regolith-cosim[study]', "
            "or run them here with --serial"
        ) from None
    return parse_address, parse_host_port


def check_scheduler(scheduler: str | None) -> tuple[str, int] | None:
    """ArgumentError for a --scheduler that is empty or no address dask connects to: a malformed one, a port
    or an IPv4 address out of range was tried for dask's 30 s connect timeout, then an OS error.
    Returns the (host, port) a TCP connection goes to (tcp, tls, ws, wss), None for none or another scheme."""
    if scheduler is None:
        return None
    where = f"--scheduler {scheduler!r}"
    if not isinstance(scheduler, str) or not scheduler.strip():
        raise ArgumentError(
            f"{where}: give the dask scheduler's address, e.g. tcp://HOST:8786 (without it a LocalCluster starts here)"
        )
    parse_address, parse_host_port = _addressing()
    try:
        scheme, location = parse_address(scheduler)
        if scheme in ("tcp", "tls", "ws", "wss"):
            web_port = {"ws": 80, "wss": 443}.get(scheme)  # a websocket address may leave its port out
            host, port = parse_host_port(location, default_port=web_port) if web_port else parse_host_port(location)
            if not 0 < int(port) < 65536:
                raise ValueError(f"port {port} is not in 1..65535")
            if re.fullmatch(r"[0-9.]+", str(host)):
                ipaddress.ip_address(host)  # 256.1.1.1
            return str(host), int(port)
    except ValueError as error:
        raise ArgumentError(f"{where}: not a dask scheduler address ({error}), e.g. tcp://HOST:8786") from None
    return None


SCHEDULER_REACH_TIMEOUT = 10.0
"""How long [s] a command waits for a --scheduler's host to take a connection before it refuses the address."""


def reach_scheduler(scheduler: str | None, timeout: float = SCHEDULER_REACH_TIMEOUT) -> None:
    """ArgumentError unless something takes a TCP connection at the --scheduler's address within `timeout` [s].

    Called by the command line before it makes a folder: dask itself waits its 30 s connect timeout and then
    fails with an OS error, after the run folder was made (the same command again was refused: not empty).
    Whether it is a dask scheduler is dask's to find when the tasks start; a scheme other than tcp, tls, ws
    and wss is not tried here."""
    import socket

    place = check_scheduler(scheduler)
    if place is None:
        return
    host, port = place
    try:
        with socket.create_connection((host, port), timeout=timeout):
            pass
    except TimeoutError:
        why = f"nothing answered within {timeout:g} s"
    except socket.gaierror as error:
        why = f"the host {host!r} is not known here ({error.strerror or error})"
    except OSError as error:
        why = f"nothing takes a connection at {host}:{port} ({error.strerror or error})"
    else:
        return
    raise ArgumentError(
        f"--scheduler {scheduler!r}: {why}; start the scheduler first (`dask scheduler`), or leave --scheduler "
        "out to start a LocalCluster here"
    )


class Executor:
    """Maps tasks over a dask cluster (or serially). Use as a context manager."""

    def __init__(self, kind: str = "dask", scheduler: str | None = None, workers: int | None = None):
        check_executor(kind, scheduler)
        check_workers(workers)
        self.kind = kind
        self.scheduler = scheduler
        self.workers = workers or os.cpu_count() or 1
        self.client: Client | None = None
        self.cluster: LocalCluster | None = None
        self._levels: dict[str, int] = {}  # the dask loggers' levels before __enter__

    _DASK_LOGGERS = ("distributed", "tornado")
    """The loggers of dask.distributed and its network layer: their INFO lines (workers registered,
    streams closed) are the cluster's business, shown with --verbose (cosim's DEBUG) only."""

    def __enter__(self):
        if self.kind == "serial":
            return self
        from dask.distributed import Client, LocalCluster

        self._levels = {name: logging.getLogger(name).level for name in self._DASK_LOGGERS}
        if not log.isEnabledFor(logging.DEBUG):
            for name in self._DASK_LOGGERS:
                logging.getLogger(name).setLevel(logging.WARNING)
        with _signals_held() as held:  # a cluster stopped half-built fails dask's own cleanup at exit
            if self.scheduler:
                try:
                    self.client = Client(self.scheduler)
                except (ValueError, TypeError) as error:  # a malformed address (a refused one: OSError)
                    where = f"--scheduler {self.scheduler!r}"
                    raise ArgumentError(f"{where}: not a dask scheduler address ({error})") from None
            else:
                self.cluster = LocalCluster(
                    n_workers=self.workers, threads_per_worker=1, processes=True, dashboard_address=None
                )
                self.client = Client(self.cluster)
        if held:  # Ctrl-C or SIGTERM while it started: close it whole, then stop as the signal asks
            self.__exit__(None, None, None)
            signal.raise_signal(held[0])
        log.info("dask: %s", self.client)
        return self

    def __exit__(self, *exc):
        # Closing while tasks still run (a study stopped by an error) makes the scheduler log the
        # workers' closed streams with tracebacks: noise after the error that ended the study, so the
        # teardown is quiet unless --verbose.
        quiet = not log.isEnabledFor(logging.DEBUG)
        if quiet:
            for name in self._DASK_LOGGERS:
                logging.getLogger(name).setLevel(logging.CRITICAL + 1)
        try:
            if self.client is not None:
                self.client.close()
            if self.cluster is not None:
                self.cluster.close()
        finally:
            for name, level in self._levels.items():
                logging.getLogger(name).setLevel(level)
        return False

    def map(self, function, tasks: list[dict], reraise: tuple[type[BaseException], ...] = ()) -> list[dict]:
        """Results in task order; a task whose worker died becomes {'ok': False, 'error': ...}, except that
        an error of a type in `reraise` propagates as itself, as it does from a serial task. Ctrl-C or
        SIGTERM (KeyboardInterrupt) propagates with the results so far as its `finished` attribute (a
        result per task, None for those not finished), so a caller can report the tasks that ran."""
        results: list = [None] * len(tasks)
        try:
            self._map(function, tasks, reraise, results)
        except KeyboardInterrupt as stop:
            stop.finished = results  # type: ignore[attr-defined]
            raise
        return results

    def _map(self, function, tasks: list[dict], reraise: tuple[type[BaseException], ...], results: list) -> None:
        """Executor.map into `results` (a result per task, as each finishes)."""
        if self.kind == "serial":
            for i, task in enumerate(tasks):
                results[i] = function(task)
                _report(results[i], task.get("label"), i + 1, len(tasks))
            return
        from dask.distributed import as_completed

        assert self.client is not None  # __enter__ connected it
        futures = self.client.map(function, tasks, pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        for done, future in enumerate(as_completed(futures), 1):
            i = index[future.key]
            try:
                results[i] = future.result()
            except reraise:
                self.client.cancel(futures)  # the study stops here: its other tasks are not wanted
                raise
            except Exception as error:  # the worker itself failed
                results[i] = {
                    "label": tasks[i].get("label"),
                    "ok": False,
                    "status": "failed",
                    "error": f"{type(error).__name__}: {error}",
                    "out_dir": tasks[i].get("out_dir"),
                }
            _report(results[i], tasks[i].get("label"), done, len(tasks))


@contextlib.contextmanager
def _signals_held():
    """Hold the stop signals (cosim.stop_signals) back while the block runs (in the main thread): yields
    the list of those that arrived, in order (a second one raises KeyboardInterrupt at once); the former
    handlers are back when it ends."""
    held: list[int] = []

    def hold(signum, frame):
        if held:  # asked twice: stop at once, as a second Ctrl-C does in a run
            raise KeyboardInterrupt(signal.Signals(signum).name)
        held.append(signum)

    former = stop_signals.install(hold)
    try:
        yield held
    finally:
        stop_signals.restore(former)


def _report(result, label, done, total):
    if not isinstance(result, dict) or "ok" not in result:
        return
    state = result.get("status", "ok") if result.get("ok") else f"FAILED: {result.get('error')}"
    wall = result.get("wall_time")
    log.info("[%d/%d] %s: %s%s", done, total, label, state, f" ({wall:.1f} s)" if wall else "")


STUDY_MARK = ".cosim-study"
"""An empty file in each folder a study, sweep, set of replicas or lab test writes: --overwrite empties
only a folder that holds it (or a single run's), never one of other files, an input scene among them."""


@contextlib.contextmanager
def prepare_study(out_dir: str, overwrite: bool) -> Iterator[None]:
    """Hold the study folder while the study runs in it (`with prepare_study(...)`): make it and take its
    lock (FolderInUseError while another process holds it: a second study, lab test or set of replicas
    writing there, or a run; it had emptied their folders under them), then refuse a non-empty folder
    unless overwrite, and even then one that neither a study marked nor a single run wrote (a settled bed
    is kept)."""
    from .folders import LOCK_FILE

    folder = RunFolder(out_dir)
    folder.create()
    if not os.path.exists(folder.file(LOCK_FILE)):  # one there may be held: that is said first
        _study_folder_files(out_dir, overwrite)  # a refused folder is left as it was, without a lock file
    with folder.locked():
        present = _study_folder_files(out_dir, overwrite)  # again: another process may have written since
        _refuse_held_locks(out_dir, present)
        for name in present:
            path = os.path.join(out_dir, name)
            shutil.rmtree(path) if os.path.isdir(path) else os.remove(path)
        with open(os.path.join(out_dir, STUDY_MARK), "w"):
            pass
        yield


def _refuse_held_locks(out_dir: str, names: list[str]) -> None:
    """FolderInUseError when a run folder among `names` (or below them) is in use: its lock held by another
    process (a `cosim run --out STUDY/replica_000`), whose files the study would remove under it."""
    from filelock import FileLock, Timeout

    from .folders import LOCK_FILE, FolderInUseError

    for name in names:
        top = os.path.join(out_dir, name)
        for root, _, files in os.walk(top) if os.path.isdir(top) else ():
            if LOCK_FILE in files:
                lock = FileLock(os.path.join(root, LOCK_FILE))
                try:
                    lock.acquire(timeout=0)
                except Timeout:
                    raise FolderInUseError(
                        f"output folder {root!r} is in use by another process (a run holds its {LOCK_FILE}); "
                        f"--overwrite of {out_dir!r} would remove it: wait for it to finish, stop it, or choose "
                        "another --out"
                    ) from None
                lock.release()


def _study_folder_files(out_dir: str, overwrite: bool) -> list[str]:
    """The files a study in `out_dir` replaces (OutputExistsError when it may not)."""
    from .beds import BED_DIVERGED_FILE
    from .folders import LOCK_FILE, RUN_OUTPUTS, OutputExistsError

    keep = (BED_FILE, BED_INFO_FILE, BED_DIVERGED_FILE, "beds", LOCK_FILE, STUDY_MARK)
    present = sorted(n for n in os.listdir(out_dir) if n not in keep)
    if present and not overwrite:
        raise OutputExistsError(
            f"study folder {out_dir!r} is not empty ({', '.join(present[:6])}); nothing "
            "is overwritten: choose another --out or pass --overwrite (the settled bed is kept)"
        )
    # a run's folder holds its record or results and nothing else: a lone scene.toml is the user's input
    a_run = (RUN_FILE in present or RESULTS_FILE in present) and all(n in RUN_OUTPUTS for n in present)
    if present and not a_run and not os.path.exists(os.path.join(out_dir, STUDY_MARK)):
        raise OutputExistsError(
            f"study folder {out_dir!r} holds files that no study marked as its own ({', '.join(present[:6])}): "
            f"--overwrite empties only a folder a study, sweep, lab test or set of replicas wrote (it leaves a "
            f"{STUDY_MARK} file; one written before 2026-12-06 has none) or a single run's, so nothing was "
            "removed: choose another --out, or empty it yourself"
        )
    return present


VARIATIONS = ("order", "bed")
"""What replicas differ in: 'order', the summation order on one settled bed (run.order_seed = k);
'bed' (--vary-bed), the bed too: replica k settles its own from bed.seed + k (as the lab's specimens), and
its SCM wheels run on the soil fitted on the calibration's bed k."""


def _settle(ex: Executor, plans: list[RunPlan], folders: list[str]) -> list[str]:
    """The beds of `plans`, settled (or found cached) in `folders` on the executor, in parallel; a bed
    that fails raises (nothing has run yet): the project's own error as itself (SettlingDiverged: exit 4),
    any other naming its folder."""
    tasks = [
        {
            "scene_toml": p.scene.to_toml(),
            "folder": f,
            "label": f"bed {os.path.basename(f)}",
            "base_dir": p.scene.base_dir,
        }
        for p, f in zip(plans, folders)
    ]
    paths = []
    for task, result in zip(tasks, ex.map(settle_task, tasks, reraise=(RegolithError,))):
        if not isinstance(result, dict) or "path" not in result:
            error = result.get("error") if isinstance(result, dict) else result
            raise InternalError(f"settling the bed in {task['folder']} failed: {error}")
        paths.append(result["path"])
    return paths


def _shared_bed(plan: RunPlan, out_dir: str, ex: Executor) -> str | None:
    """The settled bed every run of a study starts from (None: the terrain model needs none)."""
    from .system import needs_bed

    if not needs_bed(plan):
        return None
    if plan.bed.bed_file:
        return plan.bed.bed_file
    log.info("settling the shared bed: %s ...", settling_cost(plan))  # its worker's own log is not shown
    return _settle(ex, [plan], [out_dir])[0]


def calibration_beds(plan: RunPlan) -> tuple[str, list[dict[str, float]]] | None:
    """The scene's SCM calibration file and, for each bed it was calibrated on ([source] replica_fits and
    [source.wheel] replica_fits, cosim.scm_calibration.bed_soils), that bed's soil keys the scene does
    not set itself; None without SCM wheels or a calibration file, (file, []) when the file holds no
    beds' own fits of a key the scene leaves to it (every bed's soil would be the same)."""
    section = plan.scene.terrain
    if plan.terrain.model not in ("scm", "mixed") or section is None or section.calibration is None:
        return None
    from .scm_calibration import SOIL_KEYS, bed_soils, read_calibration

    path = section.calibration
    own = section.model_fields_set
    soils = bed_soils(read_calibration(path), path)
    soils = [{k: soil[k] for k in SOIL_KEYS if k not in own} for soil in soils]
    return path, soils if any(soil != soils[0] for soil in soils) else []


def _check_variation(plan: RunPlan, vary: str, replicas: int = 0) -> list[dict[str, float]]:
    """Refuse, naming the option, what replicas cannot vary in for this scene (on SCM alone, which sums
    in a fixed order, the summation order); for 'bed', the SCM soil
    of each replica's calibration bed ([] when the SCM wheels, if any, keep one soil): replica k's SCM
    wheels run on the soil fitted on calibration bed k, as its DEM wheels on the grains of bed.seed + k."""
    from .scm_calibration import out_of_range
    from .system import needs_bed

    if vary not in VARIATIONS:
        raise SceneError([f"vary: {vary!r} is not a variation; allowed: {', '.join(VARIATIONS)}"])
    if vary != "bed" and replicas >= 2 and plan.terrain.model == "scm":
        raise SceneError(
            [
                f"--replicas {replicas} (a study's default is 3): terrain.model 'scm' sums in a fixed order, so "
                "replicas over summation orders are one run K times (an error bar of 0); an SCM run's error bar "
                "is its calibration's: add --vary-bed (replica k on the soil its calibration fitted on bed k; "
                "docs/scm.md), or give --replicas 1 for one run"
            ]
        )
    if vary != "bed":
        return []
    grains = needs_bed(plan)
    found = calibration_beds(plan)
    path, soils = found if found is not None else ("", [])
    if not grains and not soils:
        why = (
            f"its calibration {path} holds no beds' own fits ([source] replica_fits): calibrate over beds, "
            "`cosim calibrate-scm SCENE --out FILE --replicas 3` (a wheel fit: `--from-wheel --wheel-runs` a slip "
            "study made with --vary-bed; fits of keys the scene sets itself do not count)"
            if path
            else "and no calibration file of beds' own fits ([terrain] calibration)"
        )
        raise SceneError([f"--vary-bed: terrain.model {plan.terrain.model!r} settles no bed of grains to vary, {why}"])
    if grains and plan.bed.bed_file:
        raise SceneError(
            [
                f"--vary-bed: bed.bed_file = {plan.bed.bed_file!r} fixes one bed, and each replica settles its own "
                "(bed.seed + k): remove bed.bed_file, or leave out --vary-bed (replicas on that one bed)"
            ]
        )
    last_seed = plan.bed.spec.seed + max(replicas, 1) - 1
    if grains and last_seed > INT64_MAX:
        raise SceneError(
            [
                f"--vary-bed --replicas {replicas}: replica k settles its bed from bed.seed + k, and bed.seed = "
                f"{plan.bed.spec.seed} takes the last past the largest seed (2^63 - 1); allowed: bed.seed <= "
                f"{INT64_MAX - max(replicas, 1) + 1}"
            ]
        )
    if soils and replicas > len(soils):
        raise SceneError(
            [
                f"--vary-bed --replicas {replicas}: the SCM calibration {path} was fitted on {len(soils)} beds "
                f"([source] replica_fits): at most {len(soils)} replicas, or calibrate over more beds (--replicas)"
            ]
        )
    problems = [
        f"--vary-bed: {path}: calibration bed {bed}'s [source.replica_fits] {problem}, outside what SCM takes "
        f"(terrain.{key} in the scene wins over the file's)"
        for bed, soil in enumerate(soils[:replicas])
        for key, problem in out_of_range(soil).items()
    ]
    if problems:
        raise SceneError(problems)
    return soils


def _replica_beds(plan: RunPlan, out_dir: str, ex: Executor, replicas: int, vary: str) -> list[str | None]:
    """Replica k's bed file: the shared bed (vary 'order'), or its own (vary 'bed'), settled from
    bed.seed + k into out_dir/beds/seed_S (the K beds in parallel on the executor)."""
    from .system import needs_bed

    if vary == "order":
        return [_shared_bed(plan, out_dir, ex)] * replicas
    if not needs_bed(plan):  # SCM alone: its replicas vary in the calibration's beds (_check_variation)
        return [None] * replicas
    seeds = [plan.bed.spec.seed + k for k in range(replicas)]
    log.info("settling %d beds, bed.seed %d to %d, each %s ...", replicas, seeds[0], seeds[-1], settling_cost(plan))
    folders = [os.path.join(out_dir, "beds", f"seed_{s}") for s in seeds]
    return list(_settle(ex, [plan.with_changes(**{"bed.seed": s}) for s in seeds], folders))


MAX_REPLICAS = 10_000
"""Most replicas a study takes (--replicas): each is a run folder and a task; a count beyond it is a slip
of the keyboard (10^9 filled 23 GB of memory with tasks before a run started)."""


def check_replicas(plan: RunPlan, replicas: int, least: int, why: str = "") -> None:
    """SceneError naming --replicas unless least <= replicas <= MAX_REPLICAS and every replica's order seed
    (run.order_seed + k, replica_order_seed) is a seed."""
    if not least <= replicas <= MAX_REPLICAS:
        raise SceneError([f"--replicas: must be {least} to {MAX_REPLICAS}{why}, got {replicas}"])
    base = plan.order_seed or 0
    if base + replicas - 1 > INT64_MAX:
        raise SceneError(
            [
                f"--replicas {replicas}: replica k sums in order run.order_seed + k, and run.order_seed = {base} takes "
                f"the last past the largest seed (2^63 - 1); allowed: run.order_seed <= {INT64_MAX - replicas + 1}"
            ]
        )


def replica_order_seed(plan: RunPlan, k: int) -> int:
    """Replica k's summation order: the scene's run.order_seed (0 when it sets none) + k."""
    return (plan.order_seed or 0) + k


def _replica_overrides(k: int, bed: str | None, vary: str, plan: RunPlan, soils: list[dict] | None = None) -> dict:
    """Replica k's overrides: its summation order (replica_order_seed), its bed (and that bed's seed when
    beds vary), and its SCM wheels' soil when beds vary and the calibration was fitted on beds (`soils`,
    _check_variation)."""
    from .system import needs_bed

    seed = {"bed.seed": plan.bed.spec.seed + k} if vary == "bed" and needs_bed(plan) else {}
    soil = {f"terrain.{key}": value for key, value in soils[k].items()} if soils else {}
    return {"run.order_seed": replica_order_seed(plan, k), **seed, **_bed_override(bed), **soil}


def _variation(plan: RunPlan, vary: str, soils: list[dict] | None) -> tuple[str, dict]:
    """What the replicas varied in, for a report's title, and the SCM calibration beds' soils they ran on
    (for the report's 'calibration_beds'; {} when the SCM wheels, if any, kept one soil)."""
    from .scm_calibration import SOIL_UNITS
    from .system import needs_bed

    if vary == "order":
        return "summation order, one bed", {}
    parts = [f"a bed each, bed.seed {plan.bed.spec.seed}+k"] if needs_bed(plan) else []
    if not soils:
        return "; ".join(parts) or "a bed each", {}
    section = plan.scene.terrain
    path = str(section.calibration) if section is not None else ""
    parts.append(f"SCM on calibration bed k's soil, {os.path.basename(path)}")
    keys = sorted(soils[0])
    beds = {"file": path, "soils": soils, "units": {k: SOIL_UNITS[k] for k in keys}}
    return "; ".join(parts), beds


def _batching(
    plan: RunPlan,
    batched: bool | None,
    executor: str = "dask",
    scheduler: str | None = None,
    workers: int | None = None,
) -> bool:
    """Whether a study's runs go as worlds of one simulation (cosim.batch): as asked (refused, naming why,
    when the scene cannot be batched), or, None, when the device is a GPU and the scene can be and no
    executor was asked for (--serial, --scheduler, --workers: the runs go there). Batched runs use no
    executor: one asked for together with --batched is refused (ArgumentError)."""
    from .batch import batch_problem

    problem = batch_problem(plan)
    if batched and problem is not None:
        raise SceneError([f"--batched: {problem}"])
    asked = "--serial" if executor == "serial" else "--scheduler" if scheduler is not None else "--workers"
    if executor != "serial" and scheduler is None and workers is None:
        asked = ""
    if batched and asked:
        raise ArgumentError(
            f"{asked}: batched runs are worlds of one simulation in this process, on no executor; leave out "
            f"--batched to run them as separate runs there, or {asked} to batch them"
        )
    return batched_by_default(plan) and not asked if batched is None else bool(batched)


def batched_by_default(plan: RunPlan) -> bool:
    """Whether a study of this plan's runs goes as worlds of one simulation when nothing is asked: on a GPU,
    when the scene can be batched (cosim.batch.batch_problem)."""
    from .batch import batch_problem

    return plan.device.startswith("cuda") and batch_problem(plan) is None


def _run_tasks(ex: Executor, tasks: list[dict], batched: bool) -> list[dict]:
    """The tasks' runs (run_task's results, in task order): on the executor, or as worlds of one simulation."""
    if not batched:
        return ex.map(run_task, tasks)
    from soil.memory import SoilTooLargeError

    from .batch import run_batched
    from .beds import check_memory

    # one simulation, each world on its task's bed (replicas over beds: a bed each, of one shape); where
    # they do not fit one device together, a simulation per bed
    plans = [task_plan(t) for t in tasks]
    groups: list[list[int]] = [list(range(len(tasks)))]
    try:
        check_memory(plans[0], len(tasks))
    except SoilTooLargeError:
        by_bed: dict[Any, list[int]] = {}
        for i, task in enumerate(tasks):
            by_bed.setdefault(task.get("overrides", {}).get("bed.bed_file"), []).append(i)
        groups = list(by_bed.values())
    results: list[dict] = [{}] * len(tasks)
    for members in groups:
        log.info("%d runs as worlds of one simulation", len(members))
        ran = run_batched(
            [plans[i] for i in members],
            [str(tasks[i]["out_dir"]) for i in members],
            overwrite=bool(tasks[0].get("overwrite")),
        )
        for i, r in zip(members, ran):
            results[i] = {**r, "label": tasks[i].get("label"), "overrides": tasks[i].get("overrides", {})}
        stopped = [r for r in ran if r.get("status") == "interrupted" or r.get("stop_received")]
        if stopped:  # Ctrl-C or SIGTERM stopped the batch's runs (each with a checkpoint): no further batch starts
            name = stopped[0].get("signal") or stopped[0].get("stop_received") or "SIGINT"
            stop = KeyboardInterrupt(f"{name}: the batched runs stopped, each with its checkpoint")
            stop.signal = name  # type: ignore[attr-defined]
            raise stop
    return results


def _same_value(a, b) -> bool:
    """Whether two values of a --param give the same scene: numbers by value (1 and 1.0 alike: the scene
    coerces them), lists item by item, anything else (a name, a flag: true is not 1) by type and value."""
    if is_number(a) and is_number(b):
        return bool(a == b)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same_value(x, y) for x, y in zip(a, b))
    return type(a) is type(b) and a == b


def _repeated(values) -> list:
    """The values that occur more than once, in order of their first occurrence."""
    return [value for value, count in collections.Counter(values).items() if count > 1]


def _bed_override(bed: str | None) -> dict:
    """A task's override that starts it from the shared bed (none without one)."""
    return {} if bed is None else {"bed.bed_file": bed}


def _tolerances(plan: RunPlan) -> dict[str, float]:
    """Absolute floors of the 'deterministic' criterion per metric (metrics.ensemble): what a
    user sizing a wheel cannot tell apart anyway."""
    r = plan.bed.spec.radius_mean
    rim = plan.drive_omega * plan.wheel.rim_radius
    rim = rim if math.isfinite(rim) else 0.0  # a controller sets the speed: relative tolerances only
    return {
        "slip": 0.02,
        "sinkage": 0.25 * r,
        "sinkage_tips": 0.25 * r,
        "landing_sinkage": 0.25 * r,
        "drawbar_pull": 0.01 * plan.wheel_load,
        "dp_over_w": 0.01,
        "driving_torque": 0.01 * plan.wheel_load * plan.wheel.rim_radius,
        "travel": 0.05 * rim * plan.scene.run.duration,
        "forward_speed": 0.02 * rim,
    }


COUNT_UNITS = {"replicas": "count", "steady": "count", "averaged": "count", "failed": "count"}
"""The unit of a study row's counts of runs."""


def failed_run(result: dict) -> bool:
    """Whether a study's run failed: it raised (run_task's 'failed') or diverged (a run.json's status),
    and gives no result; a run still running or interrupted has not failed (it has not finished)."""
    return not result.get("ok") and result.get("status") in ("failed", "diverged")


VALID = "valid"
"""The verdict of a run, row or ensemble whose runs passed every validity check (cosim.advice.verdict)."""
OUT_OF_RANGE = "out of range: "
"""How the verdict of a run, row or ensemble that failed a validity check starts (cosim.advice.verdict)."""
NOT_JUDGED = "; not judged: "
"""What follows a verdict when some run could not judge a check (cosim.advice.verdict): the checks, each
with how many of the runs that give a verdict could not judge it in a row's or an ensemble's."""


def failed_checks(result: dict) -> list[str] | None:
    """The validity checks a run failed, as its summary's findings say ([] for a valid run; the summary's
    `validity` text where it holds no findings); None for a run that gives none (failed, or a record of
    neither)."""
    summary = result.get("summary") if result.get("ok") else None
    if not isinstance(summary, dict):
        return None
    findings = summary.get("findings")
    if isinstance(findings, list) and findings and all(isinstance(f, dict) and "check" in f for f in findings):
        return list(dict.fromkeys(str(f["check"]) for f in findings if not f.get("ok")))
    if findings == []:  # nothing checked (an analytic run's, whatever verdict an older one wrote)
        return None
    verdict = summary.get("validity")
    verdict = verdict.split(NOT_JUDGED)[0] if isinstance(verdict, str) else verdict  # judged checks only
    if verdict == VALID:
        return []
    if isinstance(verdict, str) and verdict.startswith(OUT_OF_RANGE):
        return [c.strip() for c in verdict[len(OUT_OF_RANGE) :].split(",") if c.strip()]
    return None


def unjudged_checks(result: dict) -> list[str]:
    """The validity checks a finished run could not judge (its summary's `not_judged`: it measured nothing
    to judge them on, cosim.advice.verdict); [] for a run that judged every check or gives no verdict."""
    summary = result.get("summary") if result.get("ok") else None
    named = summary.get("not_judged") if isinstance(summary, dict) else None
    return [str(check) for check in named] if isinstance(named, list) else []


def _not_checked(result: dict) -> bool:
    """Whether a finished run's terrain had no validity checks (cosim.advice.NOT_CHECKED: the analytic one;
    its summary holds no findings, and one written before the verdict said so reads 'valid')."""
    summary = result.get("summary") if result.get("ok") else None
    if not isinstance(summary, dict):
        return False
    return summary.get("validity") == advice.NOT_CHECKED or summary.get("findings") == []


def run_validity(result: dict) -> str | None:
    """A run's verdict as its run.json gives it: 'valid', 'out of range: CHECK, ...' or advice.NOT_CHECKED,
    followed by '; not judged: CHECK, ...' when it could not judge some (unjudged_checks); None for a run
    that gives none (failed_checks)."""
    checks = failed_checks(result)
    if checks is None:
        return advice.NOT_CHECKED if _not_checked(result) else None
    unjudged = unjudged_checks(result)
    said = OUT_OF_RANGE + ", ".join(checks) if checks else VALID
    return said + (NOT_JUDGED + ", ".join(unjudged) if unjudged else "")


def ensemble_validity(results: list[dict]) -> str | None:
    """The verdict of the runs behind a row or an ensemble: 'valid' when every run that gives one is
    valid, else 'out of range: CHECK (k/n), ...', each failed check with how many of the n runs that
    give a verdict failed it (a failed run gives none), then '; not judged: CHECK (k/n), ...' when some
    run could not judge a check; advice.NOT_CHECKED when the runs' terrain has no checks; None when no
    run gives one."""
    giving = [r for r in results if failed_checks(r) is not None]
    if not giving:
        return advice.NOT_CHECKED if any(map(_not_checked, results)) else None
    n = len(giving)
    counts = collections.Counter(check for r in giving for check in failed_checks(r) or [])
    unjudged = collections.Counter(check for r in giving for check in unjudged_checks(r))
    said = OUT_OF_RANGE + ", ".join(f"{check} ({k}/{n})" for check, k in counts.items()) if counts else VALID
    return said + (NOT_JUDGED + ", ".join(f"{check} ({k}/{n})" for check, k in unjudged.items()) if unjudged else "")


def out_of_range(validity: str | None) -> bool:
    """Whether a verdict (run_validity, ensemble_validity) says some run failed a validity check."""
    return isinstance(validity, str) and validity.startswith(OUT_OF_RANGE)


def ensemble_table(results: list[dict], plan: RunPlan, states=(metrics.STEADY,)) -> dict:
    """metrics.ensemble of every REPLICA_METRIC over the runs whose steady_state is in `states` (the
    steady ones; with metrics.SINKING and RISING too, the runs whose traction is steady and sinkage still
    drifts, down or up),
    and the runs' validity (ensemble_validity: over every run that gives a verdict)."""
    averaged = [r for r in results if r.get("ok") and r.get("summary", {}).get("steady_state") in states]
    steady = [r for r in results if r.get("ok") and r.get("summary", {}).get("steady_state") == metrics.STEADY]
    floors = _tolerances(plan)
    table = {
        name: metrics.ensemble([r["summary"].get(name) for r in averaged], absolute_tolerance=floors[name])
        for name in metrics.REPLICA_METRICS
    }
    wall = metrics.ensemble([r["summary"].get("wall_time") for r in results if r.get("ok")])
    table["wall_time"] = {**wall, "deterministic": None}  # a clock's reading: no physics to repeat
    return {
        "replicas": len(results),
        "steady": len(steady),
        "averaged": len(averaged),
        "validity": ensemble_validity(results),
        "metrics": table,
    }


def _ensemble_text(stats: dict, title: str, judged: str = "deterministic") -> str:
    """The table of an ensemble; `judged`: what the last column's criterion means for these replicas."""
    lines = [
        title,
        f"  {stats['steady']} of {stats['replicas']} replicas reached a steady state",
        _validity_line(stats.get("validity")),
        f"  {'metric':16s} {'n':>3s} {'mean':>11s} {'std':>10s} {'95% CI +-':>10s} {'min':>11s} {'max':>11s}  unit  "
        + judged,
    ]
    for name, row in stats["metrics"].items():
        if row.get("n", 0) == 0:
            continue
        if name == "wall_time":
            det = ""
        elif row["n"] < 2:  # no scatter to judge: neither yes nor NO
            det = "n/a (one replica)"
        else:
            det = "yes" if row["deterministic"] else f"NO (std > {row['tolerance']:.3g})"
        lines.append(
            f"  {name:16s} {row['n']:3d} {row['mean']:11.5g} {row['std']:10.3g} {row['ci95']:10.3g} "
            f"{row['min']:11.5g} {row['max']:11.5g}  {METRIC_UNITS.get(name, ''):4s}  {det}"
        )
    return "\n".join(lines)


def _validity_line(validity: str | None) -> str:
    """An ensemble's verdict as its printed table gives it (a ! line when out of range)."""
    if validity is None:
        return "  validity: none (no replica finished)"
    if out_of_range(validity):
        return f"  ! {validity}: of the replicas that finished, how many failed each check (run.json says why)"
    return f"  validity: {validity}"


def column_units(keys: list[str], units: dict[str, str]) -> dict[str, str]:
    """The unit of each column of `keys` that has one: its metric's (a '_mean', '_std', '_ci95', '_min' or
    '_max' column: the metric's); what a study's CSV header and its JSON's `units` say."""
    found = {}
    for key in keys:
        base = key.rsplit("_", 1)[0] if key.rsplit("_", 1)[-1] in ("mean", "std", "ci95", "min", "max") else key
        unit = units.get(key, units.get(base))
        if unit is not None:
            found[key] = unit
    return found


def nested_units(rows: list[dict], runs: list[dict]) -> dict:
    """study.json's units of the numbers its rows and runs nest: each row's `stats` by metric (as
    ensemble.json's `units`), each run's wall time and the scene keys it ran with (cosim.scene.key_unit;
    each run's `summary` carries its own `units`)."""
    names = sorted({m for row in rows for m in (row.get("stats") or {}).get("metrics", {})})
    keys = sorted({k for run in runs for k in (run.get("overrides") or {})})
    return {
        "stats.metrics": column_units(names, METRIC_UNITS),
        "runs.wall_time": "s",
        "runs.overrides": {k: unit for k in keys if (unit := key_unit(k)) is not None},
    }


def _write_csv(path: str, rows: list[dict], keys: list[str], units: dict[str, str]) -> None:
    """A CSV whose header names each column with its unit, e.g. 'slip_mean [1]'."""
    known = column_units(keys, units)

    def header(key):
        return f"{key} [{known[key]}]" if key in known else key

    def cell(value):  # a list value (a swept body size) as JSON in one quoted cell
        return "" if value is None else json.dumps(value) if isinstance(value, (list, dict)) else value

    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")  # quotes a value holding a comma (a list, a path)
    writer.writerow([header(k) for k in keys])
    writer.writerows([cell(r.get(k)) for k in keys] for r in rows)
    atomic_write_text(path, text.getvalue())


def _flat(stats: dict) -> dict:
    row = {}
    for name, values in stats["metrics"].items():
        for key in ("mean", "std", "ci95", "min", "max"):
            if key in values:
                row[f"{name}_{key}"] = values[key]
    return row


# ------------------------------------------------------------------------------------
# replicas of one scene


def replica_run(
    plan: RunPlan,
    out_dir: str,
    replicas: int,
    overwrite: bool = False,
    executor: str = "dask",
    scheduler: str | None = None,
    workers: int | None = None,
    batched: bool | None = None,
    vary: str = "order",
) -> dict:
    """K replicas of a scene with error bars (module docstring): vary 'order', they differ only in
    summation order on one settled bed (that bed's scatter); 'bed', each on a bed of its own too,
    settled from bed.seed + k (the scatter between beds, which a wheel's sizing needs), its SCM wheels
    on the soil fitted on the calibration's bed k (at most as many replicas as the file has beds).

    batched: run the replicas as worlds of one simulation on one device (cosim.batch; each replica
    bit for bit its run alone; over beds too, each world on its own bed); None: when the device is a
    GPU and the scene can be batched.
    Returns {'ok' (every replica steady and the statistics exist), 'stats', 'results', 'text'}."""
    check_replicas(plan, replicas, 2, " for error bars")
    soils = _check_variation(plan, vary, replicas)
    batched = _batching(plan, batched, executor, scheduler, workers)
    out_dir = os.path.abspath(out_dir)
    tasks_run = Executor("serial" if batched else executor, scheduler, workers)  # refused before the folder is made
    with prepare_study(out_dir, overwrite):
        recipe = {
            "kind": "replicas",
            "out_dir": out_dir,
            "scene_toml": plan.scene.to_toml(),
            "base_dir": plan.scene.base_dir,
            "replicas": replicas,
            "vary": vary,
            "batched": bool(batched),
            "soils": soils,  # each replica's SCM soil keys (--vary-bed over a calibration's beds), kept as run
        }
        _write_recipe(out_dir, recipe)  # before the beds: `cosim resume` finishes them
        with tasks_run as ex:
            try:
                beds = _replica_beds(plan, out_dir, ex, replicas, vary)
                _write_recipe(out_dir, {**recipe, "beds": beds})  # the beds the runs use, never settled again
                tasks = _replica_tasks(plan, out_dir, beds, vary, soils)
                results = _run_tasks(ex, tasks, batched)
            except (KeyboardInterrupt, RunInterrupted) as stop:
                raise _replicas_stopped(stop, out_dir) from None
        with _said_stopped(out_dir):  # a stop while the ensemble is written: a resume writes it
            return _ensemble_report(plan, out_dir, results, vary, soils, beds, bool(batched))


REPLICAS_FILE = "replicas.json"  # RECIPES["replicas"]
"""A set of replicas' recipe (its folder, scene as run, base folder, count, variation, SCM soils, then its
beds once settled, and a digest of it all), written before its beds settle: `cosim resume OUT` finishes
what an interruption left and writes the ensemble (resume_replicas)."""


def _replica_tasks(plan: RunPlan, out_dir: str, beds: list, vary: str, soils: list[dict]) -> list[dict]:
    """The replicas' tasks (run_task's), replica k into out_dir/replica_k on bed k."""
    text = plan.scene.to_toml()
    return [
        {
            "scene_toml": text,
            "out_dir": os.path.join(out_dir, f"replica_{k:03d}"),
            "overrides": _replica_overrides(k, bed, vary, plan, soils),
            "label": f"replica_{k:03d}",
            "base_dir": plan.scene.base_dir,
        }
        for k, bed in enumerate(beds)
    ]


def _replicas_stopped(
    stop: BaseException, out_dir: str, what: str = "the replicas", writes: str = "the ensemble"
) -> KeyboardInterrupt:
    """The stop of a set of runs (Ctrl-C, SIGTERM, SIGHUP), saying how to finish them; its `signal` is the name."""
    name = stop_signals.stop_name(stop)
    error = KeyboardInterrupt(
        f"{name}: {what} stopped (each run that began keeps its checkpoint); `cosim resume {out_dir}` "
        f"finishes them and writes {writes}"
    )
    error.signal = name  # type: ignore[attr-defined]
    return error


@contextlib.contextmanager
def _said_stopped(out_dir: str, what: str = "the replicas", writes: str = "the ensemble") -> Iterator[None]:
    """A stop (Ctrl-C, SIGTERM) in the block raised as _replicas_stopped says it: how to finish the set."""
    try:
        yield
    except (KeyboardInterrupt, RunInterrupted) as stop:
        raise _replicas_stopped(stop, out_dir, what, writes) from None


def _ensemble_report(
    plan: RunPlan,
    out_dir: str,
    results: list[dict],
    vary: str,
    soils: list[dict],
    beds: list,
    batched: bool,
    resumed: bool = False,
) -> dict:
    """The replicas' statistics written as ensemble.json and ensemble.csv; replica_run's report (`resumed`:
    resume_replicas finished them)."""
    replicas = len(results)
    stats = ensemble_table(results, plan)
    varied, calibration = _variation(plan, vary, soils[:replicas])
    text = plan.scene.to_toml()
    report = {
        "kind": "replicas",
        "vary": vary,
        "calibration_beds": calibration,  # SCM wheels over beds: each replica's soil keys (file, soils, units)
        "batched": batched,
        "resumed": resumed,
        "scene_toml": text,
        "bed_file": beds[0] if vary == "order" else None,
        "bed_files": beds,
        "stats": stats,
        "validity": stats["validity"],  # the replicas' (ensemble_validity)
        "results": results,
        "criterion": "a metric is macroscopically deterministic (vary 'order'; over beds: the same on any bed) "
        "when its replica std is <= max(5 % of its mean, its absolute floor) (cosim.study._tolerances)",
        "units": column_units(list(stats["metrics"]), METRIC_UNITS),  # stats' mean, std, ... of each metric
        "summary_rule": metrics.SUMMARY_RULE,  # its runs' summaries' steady-window rule (each one's resume made)
    }
    write_json(os.path.join(out_dir, "ensemble.json"), report)
    _write_csv(
        os.path.join(out_dir, "ensemble.csv"),
        [
            {"metric": k, **v, "unit": METRIC_UNITS.get(k, ""), "validity": stats["validity"]}
            for k, v in stats["metrics"].items()
        ],
        ["metric", "unit", "n", "mean", "std", "ci95", "min", "max", "tolerance", "deterministic", "validity"],
        {},
    )  # one metric per row: its unit is a column (mean, std, ci95, min, max, tolerance are in it); validity: the
    # replicas' verdict, the same on every row
    judged = "deterministic" if vary == "order" else "same on any bed"
    report["text"] = _ensemble_text(stats, f"{plan.name}: {replicas} replicas ({varied}), {out_dir}", judged)
    report["ok"] = stats["steady"] == replicas and stats["steady"] >= 2
    return report


def _recipe_digest(recipe: dict) -> str:
    """SHA-256 of a replicas recipe's content as written (its 'digest' left out): an edit is seen before a
    resume acts."""
    import hashlib

    content = finite_or_null({k: v for k, v in recipe.items() if k != "digest"})
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()


RECIPES = {
    "replicas": ("replicas.json", ("out_dir", "scene_toml", "base_dir", "replicas", "vary", "batched", "soils")),
    "sweep": ("sweep.json", ("out_dir", "scene_toml", "base_dir", "params", "plot")),
    "precision": (
        "precision_study.json",
        ("out_dir", "scene_toml", "base_dir", "replicas", "precisions", "batched", "plot"),
    ),
    "slip": (
        "slip_study.json",
        ("out_dir", "scene_toml", "base_dir", "slips", "replicas", "vary", "batched", "soils", "plot"),
    ),
}
"""Each kind of set of runs `cosim resume OUT` finishes: its recipe's file in OUT and the keys it holds."""


def _write_recipe(out_dir: str, recipe: dict) -> None:
    """A set of runs' recipe (RECIPES, by its 'kind'), with its digest (written whole: atomically)."""
    write_json(os.path.join(out_dir, RECIPES[recipe["kind"]][0]), {**recipe, "digest": _recipe_digest(recipe)})


def _read_recipe(out_dir: str, kind: str = "replicas") -> dict:
    """The recipe (RECIPES[kind]) of the set of runs in out_dir, checked whole (its digest) and where it was
    made; DamagedFileError or ArgumentError naming the file or the folder."""
    name, keys = RECIPES[kind]
    path = os.path.join(out_dir, name)
    what = {"replicas": "set of replicas", "sweep": "sweep", "slip": "slip study", "precision": "precision study"}[kind]
    try:
        with open(path) as f:
            recipe = json.load(f)
        if not isinstance(recipe, dict) or recipe.get("kind") != kind:
            raise ValueError(f"no table of kind {kind!r}")
        if recipe.get("digest") != _recipe_digest(recipe):
            raise ValueError(f"its content no longer matches its digest: edited or damaged since the {what} began")
        absent = [k for k in keys if k not in recipe]
        if absent:
            raise ValueError(f"it has no {', '.join(absent)}")
    except (OSError, ValueError) as error:
        raise DamagedFileError(
            f"{path}: not the recipe its {what} wrote ({error}); its runs' folders each resume alone "
            "(cosim resume OUT/RUN)"
        ) from None
    if os.path.realpath(recipe["out_dir"]) != os.path.realpath(out_dir):
        raise ArgumentError(
            f"{out_dir}: the {what} was made in {recipe['out_dir']}, and its runs name their beds there by "
            "path: resume it there (move the folder back)"
        )
    return recipe


def resume_replicas(out_dir: str) -> dict:
    """Finish a set of replicas an interruption (or a kill) left (its REPLICAS_FILE): its beds settled
    if the stop came while they settled (no run had begun), else the recipe's own, never settled again;
    each run that finished, or diverged there, taken as it is, each other one with a checkpoint resumed
    (cosim.launch.resume: to the result an uninterrupted run gives; a batched world that stopped because
    another diverged, too), each that never began run; then the ensemble is written as replica_run
    writes it. One run at a time, in this process."""
    out_dir = os.path.abspath(out_dir)
    recipe = _read_recipe(out_dir, "replicas")
    vary, replicas, soils = recipe["vary"], int(recipe["replicas"]), recipe["soils"]
    plan = resolve(scene_from_text(recipe["scene_toml"], base_dir=recipe["base_dir"]))  # its errors name the key
    # its runs went on one at a time here, alone (each bit for bit as in a batch): 'resumed'
    return _finish_set(
        out_dir,
        recipe,
        ("the replicas", "the ensemble"),
        lambda ex: _replica_beds(plan, out_dir, ex, replicas, vary),
        lambda beds: _replica_tasks(plan, out_dir, beds, vary, soils),
        lambda tasks, results, beds: _ensemble_report(
            plan, out_dir, results, vary, soils, beds, bool(recipe["batched"]), resumed=True
        ),
    )


def _finish_set(out_dir: str, recipe: dict, said: tuple[str, str], settle, make_tasks, report) -> dict:
    """What every resume of a set of runs does (resume_replicas, resume_sweep, resume_slip_study,
    resume_precision_study), its folder locked: the recipe's beds (a list; settled now by settle(executor)
    and kept in the recipe when the set stopped while they settled), each bed still there; each of
    make_tasks(beds) finished (_finish_replica), one at a time; then report(tasks, results, beds). A stop
    says how to finish the set: said = (the set, what it writes)."""
    results: list[dict] = []
    with RunFolder(out_dir).locked():
        try:
            beds = recipe.get("beds")
            if beds is None:  # stopped while the beds settled, before any run: settled (the rest) now
                with Executor("serial") as ex:
                    beds = settle(ex)
                _write_recipe(out_dir, {**{k: v for k, v in recipe.items() if k != "digest"}, "beds": beds})
            if not isinstance(beds, list):
                raise DamagedFileError(
                    f"{os.path.join(out_dir, RECIPES[recipe['kind']][0])}: its beds are no list (a recipe of another "
                    "version); resume each run alone (cosim resume OUT/RUN), or run the set again"
                )
            missing = [bed for bed in beds if bed is not None and not os.path.isfile(bed)]
            if missing:
                raise DamagedFileError(f"{missing[0]}: a bed {said[0]} ran on is gone; run them again")
            tasks = make_tasks(beds)
            for done, task in enumerate(tasks, 1):
                results.append(_finish_replica(task))
                _report(results[-1], task["label"], done, len(tasks))
        except (KeyboardInterrupt, RunInterrupted) as stop:
            raise _replicas_stopped(stop, out_dir, *said) from None
        with _said_stopped(out_dir, *said):
            return report(tasks, results, beds)


def _foreign_run(task: dict, folder: RunFolder) -> str:
    """'' when the replica's folder holds no run, or the task's own (its scene with the task's overrides,
    order seed, bed and soil included; the device aside); else why the run there is not this replica's (a
    run made there while the set was stopped: the set's lock covers its folder, not each replica's). The
    run's scene is its results.h5's record (scene.toml may be edited: a resume keeps an edit aside); a
    folder whose scene cannot be read is not judged here (resuming it says what is wrong)."""
    text = _recorded_scene(folder)
    if text is None:
        return ""
    try:
        theirs = scene_from_text(text, base_dir=folder.path)
    except SceneError:
        return ""
    ours = scene_from_text(task["scene_toml"], base_dir=task.get("base_dir"), overrides=task.get("overrides"))
    keys = _scenes_differ(_flat_scene(ours, skipped=("scene.device",)), _flat_scene(theirs, skipped=("scene.device",)))
    if not keys:
        return ""
    return (
        f"{folder.path} holds a run of another scene than this replica's ({', '.join(keys[:6])}"
        f"{', ...' if len(keys) > 6 else ''} differ): not counted; move it away and resume the set again to "
        "run the replica"
    )


def _recorded_scene(folder: RunFolder) -> str | None:
    """The scene text a run in `folder` ran: its results.h5's `scene_toml`, else its scene.toml; None
    when there is neither or it cannot be read."""
    from .output import check_results

    if os.path.isfile(folder.results):
        try:
            text = check_results(folder.results, data=False).get("scene_toml")
            if text:
                return str(text)
        except (OSError, ValueError):  # damaged (DamagedFileError): resuming it says so
            pass
    try:
        with open(folder.file(SCENE_FILE)) as f:
            return f.read()
    except (OSError, UnicodeDecodeError):
        return None


def _finish_replica(task: dict) -> dict:
    """resume_replicas' result of one replica (run_task's form): taken as it is, resumed, or run; a replica
    that fails here (damaged files, a divergence) is a failed result, named, and the others go on."""
    from .launch import diverged_here, resume

    started = time.perf_counter()
    folder = RunFolder(task["out_dir"])
    record = read_json(folder.file(RUN_FILE))  # {} where none, or unreadable: the run has not finished
    status, kept = record.get("status"), os.path.isfile(folder.checkpoint)
    base = {"label": task["label"], "out_dir": folder.path, "overrides": task["overrides"]}
    try:
        foreign = _foreign_run(task, folder)
        if foreign:  # a run put in its folder by hand or by another command: not this set's replica
            result = {**base, "ok": False, "status": "failed", "error": foreign}
        elif status in FINISHED and not kept and not metrics.summary_is_current(record.get("summary")):
            error = (
                f"{stale_summary(folder.path)}, and its checkpoint is gone: move the folder away and resume the set "
                "again (it runs the replica anew)"
            )
            result = {**base, "ok": False, "status": "failed", "error": error}
        elif (status == "diverged" and diverged_here(folder.results)) or (status in FINISHED and not kept):
            result = {**base, "ok": status in FINISHED, "status": status, "summary": record.get("summary", {})}
            if status not in FINISHED:  # a diverged run's resume would diverge again
                result["error"] = record.get("message", "")
        elif kept:  # a finished run's resume returns its result; another's continues it
            log.info("%s: resuming its checkpoint", task["label"])
            done = resume(folder.path)
            result = {**base, "ok": True, "status": done.status, "summary": done.summary}
        else:  # it never began, or was stopped before its first checkpoint
            log.info("%s: running from its start (no checkpoint to resume; partial results replaced)", task["label"])
            result = run_task({**task, "overwrite": True})
    except (KeyboardInterrupt, RunInterrupted):  # a stop asked for (a RegolithError too): the resume stops
        raise
    except (RegolithError, OSError) as error:  # damaged, or diverged again: this replica's failure
        result = {**base, "ok": False, "status": "failed", "error": f"{type(error).__name__}: {error}"}
    if not result.get("ok") and result.get("error"):
        log.error("%s: %s", task["label"], result["error"])
    return {**result, "wall_time": time.perf_counter() - started}


# ------------------------------------------------------------------------------------
# precision study


def precision_study(
    plan: RunPlan,
    out_dir: str,
    replicas: int = 3,
    precisions=PRECISION_ORDER,
    executor: str = "dask",
    scheduler: str | None = None,
    workers: int | None = None,
    overwrite: bool = False,
    plot: bool = True,
    batched: bool | None = None,
) -> dict:
    """The paper's replica experiment per precision; returns {'rows', 'replicas', ...}.

    batched: each precision's replicas as worlds of one simulation (cosim.batch; a simulation has one
    precision, so one batch per precision; each replica bit for bit its run alone, its wall_time its
    time within the batch, about the batch's); None: when the device is a GPU and the scene can be batched."""
    precisions = list(precisions)
    problems = [
        f"--precisions: unknown precision {p!r}; allowed: {', '.join(PRECISION_ORDER)}"
        for p in precisions
        if p not in PRECISION_ORDER
    ]
    problems += [f"--precisions: {p} given twice (its runs would share folders)" for p in _repeated(precisions)]
    if not precisions:
        problems.append(f"--precisions: give at least one of {', '.join(PRECISION_ORDER)}")
    if problems:
        raise SceneError(problems)
    check_replicas(plan, replicas, 1)
    batched = _batching(plan, batched, executor, scheduler, workers)
    out_dir = os.path.abspath(out_dir)
    tasks_run = Executor("serial" if batched else executor, scheduler, workers)  # refused before the folder is made
    with prepare_study(out_dir, overwrite):
        text = plan.scene.to_toml()
        recipe = {
            "kind": "precision",
            "out_dir": out_dir,
            "scene_toml": text,
            "base_dir": plan.scene.base_dir,
            "replicas": replicas,
            "precisions": precisions,
            "batched": bool(batched),
            "plot": bool(plot),
        }
        _write_recipe(out_dir, recipe)  # before the bed: `cosim resume` finishes the study
        with tasks_run as ex:
            try:
                bed = _shared_bed(plan, out_dir, ex)
                _write_recipe(out_dir, {**recipe, "beds": [bed]})  # the bed the runs use, never settled again
                tasks = _precision_tasks(plan, text, out_dir, precisions, replicas, bed)
                started = time.perf_counter()
                if batched:  # one batch per precision, in the tasks' order
                    results = [
                        r for p in precisions for r in _run_tasks(ex, [t for t in tasks if t["precision"] == p], True)
                    ]
                else:
                    results = ex.map(run_task, tasks)
                wall = time.perf_counter() - started
            except (KeyboardInterrupt, RunInterrupted) as stop:
                raise _replicas_stopped(stop, out_dir, "the precision study", "its table") from None
        with _said_stopped(out_dir, "the precision study", "its table"):
            return _precision_report(plan, out_dir, precisions, tasks, results, wall, bed, text, plot, bool(batched))


PRECISION_FILE = RECIPES["precision"][0]
"""A precision study's recipe (its folder, scene as run, base folder, replicas, precisions, batching,
plotting, then its bed once settled, and a digest of it all), written before its bed settles: `cosim resume
OUT` finishes what an interruption left and writes the table (resume_precision_study)."""


def _precision_tasks(plan: RunPlan, text: str, out_dir: str, precisions: list[str], replicas: int, bed) -> list[dict]:
    """A run task per precision and replica (run_task's form, with its 'precision' and 'replica')."""
    return [
        {
            "scene_toml": text,
            "out_dir": os.path.join(out_dir, precision, f"replica_{k:03d}"),
            "overrides": {
                "scene.precision": precision,
                "run.order_seed": replica_order_seed(plan, k),
                **_bed_override(bed),
            },
            "label": f"{precision}/replica_{k:03d}",
            "precision": precision,
            "replica": k,
            "base_dir": plan.scene.base_dir,
        }
        for precision in precisions
        for k in range(replicas)
    ]


def resume_precision_study(out_dir: str) -> dict:
    """Finish a precision study an interruption (or a kill) left (its PRECISION_FILE), as resume_replicas
    finishes a set of replicas (_finish_set); then its table written as precision_study writes it, marked
    `resumed`, its wall_time null: the runs' wall times mix a batch's (those that had finished in it), a
    run's alone over its sessions (those resumed) and this process's (those run here)."""
    out_dir = os.path.abspath(out_dir)
    recipe = _read_recipe(out_dir, "precision")
    text, replicas, precisions = recipe["scene_toml"], int(recipe["replicas"]), [str(p) for p in recipe["precisions"]]
    plan = resolve(scene_from_text(text, base_dir=recipe["base_dir"]))  # its errors name the key
    return _finish_set(
        out_dir,
        recipe,
        ("the precision study", "its table"),
        lambda ex: [_shared_bed(plan, out_dir, ex)],  # one bed for every run (None: a terrain without grains)
        lambda beds: _precision_tasks(plan, text, out_dir, precisions, replicas, beds[0]),
        lambda tasks, results, beds: _precision_report(
            plan,
            out_dir,
            precisions,
            tasks,
            results,
            None,
            beds[0],
            text,
            bool(recipe["plot"]),
            bool(recipe["batched"]),
            resumed=True,
        ),
    )


def _precision_report(
    plan, out_dir, precisions, tasks, results, wall, bed, text, plot, batched, resumed: bool = False
) -> dict:
    """A precision study's table (study.json, study.csv, plots) of its tasks' results; its report."""
    rows = []
    for precision in precisions:
        members = [r for t, r in zip(tasks, results) if t["precision"] == precision]
        stats = ensemble_table(members, plan)
        rows.append(
            {
                "precision": precision,
                "replicas": stats["replicas"],
                "steady": stats["steady"],
                "failed": sum(1 for r in members if not r.get("ok")),
                "validity": stats["validity"],
                **_flat(stats),
                **{  # the paper's question, as the printed table answers it (None: under two replicas)
                    f"{m}_deterministic": row.get("deterministic") if row.get("n", 0) >= 2 else None
                    for m, row in stats["metrics"].items()
                    if m != "wall_time"
                },
                "stats": stats,
            }
        )
    for task, result in zip(tasks, results):
        result.update(precision=task["precision"], replica=task["replica"])
    report = {
        "kind": "precision",
        "batched": bool(batched),
        "resumed": resumed,
        "replicas": results,
        "rows": rows,
        "wall_time": wall,
        "bed_file": bed,
        "scene_toml": text,
        "summary_rule": metrics.SUMMARY_RULE,
    }
    keys = ["precision", "replicas", "steady", "failed", "validity"] + [
        f"{m}_{k}" for m in ("wall_time",) + metrics.REPLICA_METRICS for k in ("mean", "std", "ci95", "min", "max")
    ]
    keys += [f"{m}_deterministic" for m in metrics.REPLICA_METRICS]
    units = {**METRIC_UNITS, **COUNT_UNITS}
    report["units"] = {**column_units(keys, units), "wall_time": "s", **nested_units(rows, results)}
    write_json(os.path.join(out_dir, "study.json"), report)
    _write_csv(os.path.join(out_dir, "study.csv"), rows, keys, units)
    for row in rows:
        log.info("%s", _ensemble_text(row["stats"], f"precision {row['precision']}"))
    if plot:
        from .plots import plot_output, plot_scatter

        try:
            written = plot_output(out_dir) + [plot_scatter(out_dir, rows, "precision")]
            log.info("plots: %s", ", ".join(written))
        except ArgumentError as error:  # no results.h5 under out_dir: every run failed
            log.warning("%s", error)
    return report


# ------------------------------------------------------------------------------------
# drawbar pull / slip


def check_slips(plan: RunPlan, slips, least: int = 1) -> list[float]:
    """The slips of a slip study as numbers, each in (-1, 1), none twice to 3 decimals, at least `least`
    of them, each a valid scene (SceneError naming --slips otherwise): checked before anything runs."""
    try:
        if any(isinstance(s, bool) for s in slips):  # true is no slip of 1
            raise TypeError
        slips = [float(s) for s in slips]
    except (TypeError, ValueError):
        raise SceneError([f"--slips: {list(slips)!r} must be numbers in (-1, 1)"]) from None
    problems = [f"--slips: {s} must be in (-1, 1)" for s in slips if not -1 < s < 1]
    problems += [
        f"--slips: {s} given twice (to 3 decimals: its runs would share a folder)"
        for s in _repeated(f"{s:+.3f}" for s in slips)
    ]
    if len(slips) < least:
        problems.append(f"--slips: give at least {least} slip{'s' if least > 1 else ''}")
    if problems:
        raise SceneError(problems)
    for s in slips:  # every point must be a valid scene before anything runs
        plan.with_changes(**{"testbed.mode": "slip", "testbed.slip": s})
    return slips


def slip_study(
    plan: RunPlan,
    out_dir: str,
    slips,
    replicas: int = 1,
    executor: str = "dask",
    scheduler: str | None = None,
    workers: int | None = None,
    overwrite: bool = False,
    plot: bool = True,
    batched: bool | None = None,
    vary: str = "order",
) -> dict:
    """Imposed slips after landing: DP, DP/W, torque and sinkage against slip, with error bars.

    vary: what the replicas at each slip differ in (replica_run): 'order' on one bed, or 'bed', replica
    k on bed.seed + k at every slip (the slips compared on the same K beds).
    batched: every slip's replicas as worlds of one simulation (cosim.batch; each run bit for bit as
    alone; over beds too, world k of each slip on bed k); None: when the device is a GPU and the
    scene can be batched."""
    check_replicas(plan, replicas, 1)
    slips = check_slips(plan, slips)
    soils = _check_variation(plan, vary, replicas)
    batched = _batching(plan, batched, executor, scheduler, workers)
    out_dir = os.path.abspath(out_dir)
    tasks_run = Executor("serial" if batched else executor, scheduler, workers)  # refused before the folder is made
    with prepare_study(out_dir, overwrite):
        text = plan.scene.to_toml()
        recipe = {
            "kind": "slip",
            "out_dir": out_dir,
            "scene_toml": text,
            "base_dir": plan.scene.base_dir,
            "slips": slips,
            "replicas": replicas,
            "vary": vary,
            "batched": bool(batched),
            "soils": soils,
            "plot": bool(plot),
        }
        _write_recipe(out_dir, recipe)  # before the beds: `cosim resume` finishes the study
        with tasks_run as ex:
            try:
                beds = _replica_beds(plan, out_dir, ex, replicas, vary)
                _write_recipe(out_dir, {**recipe, "beds": beds})  # the beds the runs use, never settled again
                tasks = _slip_tasks(plan, text, out_dir, slips, replicas, beds, vary, soils)
                results = _run_tasks(ex, tasks, batched)
            except (KeyboardInterrupt, RunInterrupted) as stop:
                raise _replicas_stopped(stop, out_dir, "the slip study", "its table") from None
        with _said_stopped(out_dir, "the slip study", "its table"):
            return _slip_study_report(plan, out_dir, slips, tasks, results, text, plot, vary, beds, soils[:replicas])


SLIP_FILE = RECIPES["slip"][0]
"""A slip study's recipe (its folder, scene as run, base folder, slips, replicas, variation, batching, SCM
soils, plotting, then its beds once settled, and a digest of it all), written before its beds settle:
`cosim resume OUT` finishes what an interruption left and writes the table (resume_slip_study)."""


def _slip_tasks(
    plan: RunPlan, text: str, out_dir: str, slips, replicas: int, beds: list, vary: str, soils: list
) -> list[dict]:
    """A run task per slip and replica (run_task's form, with its 'slip')."""
    return [
        {
            "scene_toml": text,
            "out_dir": os.path.join(out_dir, f"slip_{s:+.3f}", f"replica_{k:03d}"),
            "overrides": {
                "testbed.mode": "slip",
                "testbed.slip": s,
                **_replica_overrides(k, beds[k], vary, plan, soils),
            },
            "label": f"slip {s:+.3f} replica {k}",
            "slip": s,
            "base_dir": plan.scene.base_dir,
        }
        for s in slips
        for k in range(replicas)
    ]


def _slip_study_report(plan, out_dir, slips, tasks, results, text, plot, vary, beds, soils) -> dict:
    """The slip study's table of its tasks' results (_slip_report), its bed named when the replicas share one."""
    shared = beds[0] if vary == "order" else None
    return _slip_report(
        plan, out_dir, slips, [t["slip"] for t in tasks], results, text, shared, plot, vary=vary, beds=beds, soils=soils
    )


def resume_slip_study(out_dir: str) -> dict:
    """Finish a slip study an interruption (or a kill) left (its SLIP_FILE), as resume_replicas finishes a
    set of replicas (_finish_set); then its table written as slip_study writes it."""
    out_dir = os.path.abspath(out_dir)
    recipe = _read_recipe(out_dir, "slip")
    text, vary, soils = recipe["scene_toml"], recipe["vary"], recipe["soils"]
    slips, replicas = [float(s) for s in recipe["slips"]], int(recipe["replicas"])
    plan = resolve(scene_from_text(text, base_dir=recipe["base_dir"]))  # its errors name the key
    return _finish_set(
        out_dir,
        recipe,
        ("the slip study", "its table"),
        lambda ex: _replica_beds(plan, out_dir, ex, replicas, vary),
        lambda beds: _slip_tasks(plan, text, out_dir, slips, replicas, beds, vary, soils),
        lambda tasks, results, beds: _slip_study_report(
            plan, out_dir, slips, tasks, results, text, bool(recipe["plot"]), vary, beds, soils[:replicas]
        ),
    )


def slip_study_from_runs(
    folders,
    out_dir: str,
    overwrite: bool = False,
    plot: bool = True,
    include_sinking: bool = False,
    scene=None,
) -> dict:
    """The slip study's table from runs already made (FOLDER/slip_*/replica_*/run.json under each of
    `folders`: a study stopped before its end, or run in parts), written to out_dir like slip_study's
    (a new folder: never one of `folders`, a folder holding one, or a folder inside one). include_sinking:
    average the runs whose traction is steady and whose sinkage still drifts too (a wheel digging in at
    high slip), each row's `averaged` counting them; the sinkage is then its mean over the window.
    scene: the cosim.scene.Scene the table is said to be of (`cosim study slip SCENE`), compared with the
    runs' own (None: not compared).

    Every run is read and checked before out_dir is touched: the runs must be of one scene (their
    scene.toml alike but for what a slip study's runs differ in: testbed.slip, run.order_seed, the bed's
    seed and file, and the SCM soil over calibration beds), and no run may be counted twice (a copy: the
    same run_id; a part run again: the same slip, order seed and bed, which repeats a replica bit for bit
    instead of adding one); ArgumentError naming the folders and keys."""
    import glob
    import json

    out_dir = os.path.abspath(out_dir)
    real = [os.path.realpath(folder) for folder in folders]
    repeated = sorted({folder for folder in real if real.count(folder) > 1})
    if repeated:  # its runs would be counted twice
        raise ArgumentError(f"--from-runs: {repeated[0]} given twice")
    out_real = os.path.realpath(out_dir)
    for source in real:
        common = os.path.commonpath([out_real, source])
        if common == out_real:
            raise ArgumentError(f"--out {out_dir}: holds the runs of {source}; tabulate into another folder")
        if common == source:  # --overwrite would empty a run the table reads
            raise ArgumentError(
                f"--out {out_dir}: lies inside {source}, whose runs it reads; tabulate into a folder outside it"
            )
    found = []
    for folder in folders:
        for run_json in sorted(glob.glob(os.path.join(os.path.abspath(folder), "slip_*", "replica_*", "run.json"))):
            try:
                with open(run_json) as f:
                    record = json.load(f)
                slip = float(os.path.basename(os.path.dirname(os.path.dirname(run_json)))[len("slip_") :])
                _check_run_record(record)
            except (OSError, ValueError) as error:
                raise ArgumentError(f"{run_json}: not a slip run's record ({error})") from None
            if record.get("status") in FINISHED and not metrics.summary_is_current(record.get("summary")):
                raise ArgumentError(
                    f"{stale_summary(os.path.dirname(run_json))}: `cosim resume` it (or the study that ran it) "
                    "to make it again from its results, then tabulate"
                )
            found.append((slip, os.path.dirname(run_json), record))
    if not found:
        raise ArgumentError(f"no slip runs (slip_*/replica_*/run.json) under {', '.join(map(str, folders))}")
    texts, scenes = _run_scenes([path for _, path, _ in found])
    _check_one_study(found, scenes, scene)
    plan = resolve(scenes[0])
    results = [
        # a run that did not finish (running, interrupted: its summary is of part of the drive) or diverged
        # gives no result; a diverged or failed one is counted as failed
        {"label": os.path.relpath(path, out_dir), "out_dir": path, **record, "ok": record.get("status") in FINISHED}
        for _, path, record in found
    ]
    slips = sorted({slip for slip, _, _ in found})
    states = (metrics.STEADY, metrics.SINKING, metrics.RISING) if include_sinking else (metrics.STEADY,)
    beds = [record.get("bed", {}).get("path") for _, _, record in found]
    soils = _run_soils([path for _, path, _ in found])
    # the runs' own beds (by what they were settled from, not where they lie: a part of a study settles its
    # own copy of the same bed) and their SCM wheels' soils say what their replicas varied in
    vary = "bed" if len({_bed_identity(bed) for bed in beds}) > 1 or soils else "order"
    with prepare_study(out_dir, overwrite):
        return _slip_report(
            plan, out_dir, slips, [s for s, _, _ in found], results, texts[0], None, plot, states, vary, beds, soils
        )


STUDY_RUN_KEYS = ("testbed.mode", "testbed.slip", "run.order_seed", "bed.seed", "bed.bed_file", "scene.device")
"""The scene keys a slip study's runs differ in, or may (its overrides; the device of a part run on another
machine), besides the SCM soil over calibration beds and the paths of files: a table from runs
(slip_study_from_runs) compares the rest."""


def _run_scenes(paths: list[str]) -> tuple[list[str], list]:
    """(texts, cosim.scene.Scene) of the runs' scene.toml; ArgumentError naming the folder that has none
    this version reads."""
    texts, scenes = [], []
    for path in paths:
        file = os.path.join(path, "scene.toml")
        try:
            with open(file) as f:
                text = f.read()
            scenes.append(scene_from_text(text, base_dir=path))
        except (OSError, UnicodeDecodeError, SceneError) as error:
            raise ArgumentError(f"{path}: not a slip run's folder ({file}: {error})") from None
        texts.append(text)
    return texts, scenes


UNREADABLE = ("file", None)
"""A file key's value in _flat_scene when its file cannot be read here (a part run on another machine):
compared with nothing."""


@functools.lru_cache(maxsize=256)
def _digest(path: str, size: int, mtime: float) -> str:
    """SHA-256 of a file's bytes, read in chunks (cached by path, size and time: a study's runs name the same
    files)."""
    import hashlib

    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _file_content(path: str):
    """('file', SHA-256 of the file's bytes), or UNREADABLE (none here, not a regular file, unreadable)."""
    import stat

    try:
        info = os.stat(path)
        if not stat.S_ISREG(info.st_mode):  # a folder, a FIFO (whose read would block)
            return UNREADABLE
        return ("file", _digest(os.path.realpath(path), info.st_size, info.st_mtime))
    except OSError:
        return UNREADABLE


def _flat_scene(scene, skipped: tuple[str, ...] | None = None) -> dict:
    """A scene's keys (dotted) and values, less `skipped` (default: STUDY_RUN_KEYS and the SCM soil's keys);
    a key naming a file by its path (an absolute path is how a scene keeps one) by the file's content
    (_file_content: a part run on another machine, or a scene given beside its runs, names the same file from
    elsewhere)."""
    from .scm_calibration import SOIL_KEYS

    flat: dict = {}

    def walk(value, prefix):
        if isinstance(value, dict):
            for key, item in value.items():
                walk(item, f"{prefix}.{key}" if prefix else key)
        else:
            flat[prefix] = value

    walk(scene.to_dict(), "")
    if skipped is None:  # a study's runs: those they differ in
        skipped = (*STUDY_RUN_KEYS, *(f"terrain.{key}" for key in SOIL_KEYS))
    return {
        k: _file_content(v) if isinstance(v, str) and os.path.isabs(v) else v
        for k, v in flat.items()
        if k not in skipped
    }


def _scenes_differ(ours: dict, theirs: dict) -> list[str]:
    """The keys in which two _flat_scene differ (a file unreadable on either side: not judged)."""
    return sorted(
        k
        for k in ours.keys() | theirs.keys()
        if ours.get(k) != theirs.get(k) and UNREADABLE not in (ours.get(k), theirs.get(k))
    )


def _check_one_study(found: list, scenes: list, given) -> None:
    """Refuse runs of other scenes, and runs counted twice (slip_study_from_runs's docstring)."""
    paths = [path for _, path, _ in found]
    first = _flat_scene(scenes[0])
    for path, scene in zip(paths[1:], scenes[1:]):
        keys = _scenes_differ(first, _flat_scene(scene))
        if keys:
            raise ArgumentError(
                f"--from-runs: {path} ran another scene than {paths[0]} ({', '.join(keys[:6])}"
                f"{', ...' if len(keys) > 6 else ''} differ): a slip table averages the replicas of one scene"
            )
    if given is not None:
        keys = _scenes_differ(_flat_scene(given), first)
        if keys:
            raise ArgumentError(
                f"--from-runs: the runs ({paths[0]} ...) are not of the scene given ({', '.join(keys[:6])}"
                f"{', ...' if len(keys) > 6 else ''} differ): give the scene the study ran"
            )
    _check_one_mesh(paths, scenes[0], given)
    seen: dict = {}
    for (slip, path, record), scene in zip(found, scenes):
        run_id = record.get("run_id")
        if run_id is not None:
            if ("id", run_id) in seen:
                raise ArgumentError(
                    f"--from-runs: {path} is a copy of {seen['id', run_id]} (run_id {run_id}): counted once only"
                )
            seen["id", run_id] = path
        bed, seed = _bed_identity(record.get("bed", {}).get("path")), scene.run.order_seed or 0
        replica = ("replica", slip, seed, bed, _scm_soil(scene))
        if replica in seen:
            raise ArgumentError(
                f"--from-runs: {path} repeats {seen[replica]} (slip {slip:g}, run.order_seed {seed}, the same bed): "
                "the same replica run again, not another one; run a further part with --set run.order_seed=N "
                "past the seeds already run"
            )
        seen[replica] = path


def _check_one_mesh(paths: list[str], scene, given) -> None:
    """Refuse runs of a mesh wheel that drove different meshes (its file changed between them: the scenes
    name the same path, whose content now says nothing of what each drove), or another mesh than the scene
    given names now: each run's results.h5 keeps the wheel it drove (wheels/mesh; a file unreadable: not
    judged)."""
    if scene.wheel is None or scene.wheel.type != "mesh":
        return
    from types import SimpleNamespace

    from .output import stored_wheel_mesh
    from .scm_calibration import mesh_digest
    from .system import used_mesh, wheel_display_mesh

    def digest(mesh) -> str:  # the digest a study and a wheel fit record (mesh_digest), of the vertices used
        vertices, triangles, _ = used_mesh(mesh)  # one wheel: its owners are all 0
        return mesh_digest(SimpleNamespace(vertices=vertices, triangles=triangles))

    driven = {}
    for path in paths:
        try:
            driven[path] = digest(stored_wheel_mesh(os.path.join(path, RESULTS_FILE)))
        except (DamagedFileError, OSError):
            continue
    if len(set(driven.values())) > 1:
        first, *_ = driven
        other = next(path for path in driven if driven[path] != driven[first])
        raise ArgumentError(
            f"--from-runs: {other} drove another wheel mesh than {first} (their results.h5 keep each; "
            f"wheel.file {scene.wheel.file} changed between them): a slip table averages the replicas of one wheel"
        )
    if given is not None and driven:
        path, mesh = next(iter(driven.items()))
        if digest(wheel_display_mesh(resolve(given))) != mesh:
            raise ArgumentError(
                f"--from-runs: the runs ({path} ...) drove another wheel mesh than the scene given names now "
                f"(wheel.file {given.wheel.file}): give the scene the study ran, with the mesh it ran"
            )


def _scm_soil(scene) -> tuple:
    """The SCM soil keys a run's [terrain] sets (runs over calibration beds differ in them), as a tuple."""
    from .scm_calibration import SOIL_KEYS

    terrain = scene.to_dict().get("terrain", {})
    return tuple((key, terrain.get(key)) for key in SOIL_KEYS)


def _bed_identity(path) -> str | None:
    """What a run's bed was settled from: its file's key (soil.bed.save_bed: the bed's keys and seed), else
    its path (a file unread: none, or not a bed's)."""
    from soil.bed import read_bed_header
    from soil.errors import InputError

    if not path:
        return None
    try:
        return read_bed_header(path)["key"] or os.path.realpath(path)
    except (InputError, OSError):
        return os.path.realpath(path)


def stale_summary(run_folder: str) -> str:
    """What to say of a finished run whose summary was made under an older steady-window rule."""
    return (
        f"{run_folder}: its summary was made under an older steady-window rule than this code's "
        f"(cosim.metrics.SUMMARY_RULE {metrics.SUMMARY_RULE}: the window starts once the sinkage has settled too)"
    )


def _check_run_record(record) -> None:
    """ValueError naming what of a run.json the slip table cannot read: an object whose summary (if any)
    is an object of numbers or nulls for the averaged metrics and a steady_state name, whose bed (if any)
    is an object with a path."""
    if not isinstance(record, dict):
        raise ValueError(f"a JSON object expected, got {type(record).__name__}")
    summary, bed = record.get("summary", {}), record.get("bed", {})
    if not isinstance(summary, dict):
        raise ValueError(f"summary must be an object, got {summary!r:.60}")
    for name in (*metrics.REPLICA_METRICS, "wall_time"):
        if summary.get(name) is not None and not is_number(summary[name]):
            raise ValueError(f"summary.{name} must be a number or null, got {summary[name]!r:.60}")
    if summary.get("steady_state") is not None and not isinstance(summary["steady_state"], str):
        raise ValueError(f"summary.steady_state must be a name, got {summary['steady_state']!r:.60}")
    if not isinstance(bed, dict) or not isinstance(bed.get("path", ""), (str, type(None))):
        raise ValueError(f"bed must be an object with a path, got {bed!r:.60}")


def _run_soils(paths: list[str]) -> list[dict[str, float]]:
    """The SCM soil keys of replica 0, 1, ... of runs made over calibration beds (each run folder's
    scene.toml [terrain]; --vary-bed on SCM), [] when the runs share one soil or have no SCM wheels."""
    from .scm_calibration import SOIL_KEYS

    by_replica: dict[int, dict[str, float]] = {}
    for path in paths:
        try:
            with open(os.path.join(path, "scene.toml"), "rb") as f:
                terrain = tomllib.load(f).get("terrain", {})
            replica = replica_index(path)
            if replica is None:
                raise ValueError("its folder is named replica_NNN")
        except (OSError, ValueError, tomllib.TOMLDecodeError) as error:
            raise ArgumentError(f"{path}: not a slip run's folder ({error})") from None
        by_replica.setdefault(replica, {k: terrain[k] for k in SOIL_KEYS if k in terrain})
    soils = [by_replica[k] for k in sorted(by_replica)]
    varied = len(soils) > 1 and any(soil != soils[0] for soil in soils)
    return soils if varied and all(soils) else []


def _paired_covariance(row1: dict, row2: dict, n1: int, n2: int) -> float:
    """The covariance of two rows' mean DP/W [-] from their replicas paired by index (replica k of each
    ran on the same bed under --vary-bed, and in the same summation order): cov_k(d1k, d2k) x m / (n1 n2)
    over the m replicas averaged in both (n1, n2: each mean's count); 0 with fewer than 2 pairs."""
    by1, by2 = row1.get("dp_over_w_by_replica") or {}, row2.get("dp_over_w_by_replica") or {}
    common = sorted(set(by1) & set(by2))
    if len(common) < 2:
        return 0.0
    import numpy as np

    first, second = np.array([by1[k] for k in common]), np.array([by2[k] for k in common])
    return float(np.cov(first, second, ddof=1)[0, 1]) * len(common) / (n1 * n2)


def by_replica(members: list[dict], name: str, states) -> dict[str, float]:
    """{replica index: the summary's `name`} of the runs averaged (steady_state in `states`), the index read
    from each run's folder (replica_NNN): what pairs two rows' replicas (zero_pull_slip)."""
    out = {}
    for run in members:
        summary = run.get("summary") or {}
        index, value = replica_index(str(run.get("out_dir", ""))), summary.get(name)
        if run.get("ok") and summary.get("steady_state") in states and index is not None and value is not None:
            if math.isfinite(value):
                out[str(index)] = float(value)
    return out


def replica_index(path: str) -> int | None:
    """k of a replica's folder `.../replica_k` (_replica_tasks' naming), None for another name."""
    found = re.fullmatch(r"replica_(\d+)", os.path.basename(os.path.normpath(path)))
    return int(found.group(1)) if found else None


def zero_pull_slip(rows: list[dict]) -> dict:
    """The slip where the mean DP/W crosses zero (the wheel pulls its own load: self-propelled), from a
    slip study's rows: linear between the two measured slips around the first crossing (none is
    extrapolated), with the 95 % half-width of the delta method over the two means' standard errors and,
    where their replicas pair by index (a row's `dp_over_w_by_replica`), their covariance (t at the
    smaller replica count less one). Returns {'slip' [-] or None, 'ci95' [-] (nan: an
    interval needs two replicas at both points), 'between' [slip, slip] [-], 'crossings' [count], 'note',
    'validity': 'valid' when both rows it uses are valid, 'out of range: slip S: CHECK (k/n), ...' naming
    each of them that is not (their rows' `validity`), None without a crossing or a verdict of either}."""
    from scipy import stats as scipy_stats

    points = []
    for row in rows:
        stat = row.get("stats", {}).get("metrics", {})
        pull, slip = stat.get("dp_over_w", {}), stat.get("slip", {})
        if pull.get("n", 0) == 0:
            continue
        x = slip.get("mean") if slip.get("n", 0) and math.isfinite(slip.get("mean", math.nan)) else row["slip_set"]
        error = pull["std"] / math.sqrt(pull["n"]) if pull["n"] > 1 else math.nan
        points.append((x, pull["mean"], error, pull["n"], row))
    points.sort(key=lambda point: point[:4])
    crossings = [k for k in range(len(points) - 1) if (points[k][1] < 0) != (points[k + 1][1] < 0)]
    out: dict = {"slip": None, "ci95": math.nan, "between": None, "crossings": len(crossings), "validity": None}
    if not crossings:
        span = f"{min(p[1] for p in points):.3g} .. {max(p[1] for p in points):.3g}" if points else "none measured"
        out["note"] = f"DP/W does not cross zero within the measured slips (DP/W {span}): none is extrapolated"
        return out
    (s1, d1, e1, n1, row1), (s2, d2, e2, n2, row2) = points[crossings[0]], points[crossings[0] + 1]
    out["slip"] = s1 + (s2 - s1) * d1 / (d1 - d2)
    out["between"] = [s1, s2]
    # d slip / d d1 = -(s2 - s1) d2 / (d1 - d2)^2, d slip / d d2 = (s2 - s1) d1 / (d1 - d2)^2; replica k of
    # both rows ran on one bed (--vary-bed: bed k), so the two means covary: a bed's offset moves both
    g1, g2 = -(s2 - s1) * d2 / (d1 - d2) ** 2, (s2 - s1) * d1 / (d1 - d2) ** 2
    variance = (g1 * e1) ** 2 + (g2 * e2) ** 2 + 2.0 * g1 * g2 * _paired_covariance(row1, row2, n1, n2)
    error = math.sqrt(max(variance, 0.0)) if math.isfinite(variance) else math.nan
    if math.isfinite(error):
        out["ci95"] = float(scipy_stats.t.ppf(0.975, min(n1, n2) - 1) * error)
    out["note"] = f"linear between the measured slips {s1:.3g} and {s2:.3g}" + (
        f"; DP/W crosses zero {len(crossings)} times, the first is given" if len(crossings) > 1 else ""
    )
    verdicts = [row1.get("validity"), row2.get("validity")]
    failed = [
        f"slip {row.get('slip_set', x):.3g}: {row['validity'].split(NOT_JUDGED)[0][len(OUT_OF_RANGE) :]}"
        for row, x in ((row1, s1), (row2, s2))
        if out_of_range(row.get("validity"))
    ]
    unjudged = [
        f"slip {row.get('slip_set', x):.3g}: {row['validity'].split(NOT_JUDGED)[1]}"
        for row, x in ((row1, s1), (row2, s2))
        if isinstance(row.get("validity"), str) and NOT_JUDGED in row["validity"]
    ]
    said = NOT_JUDGED + "; ".join(unjudged) if unjudged else ""  # after every failed row: never read as one
    if failed:
        out["validity"] = OUT_OF_RANGE + "; ".join(failed) + said
        out["note"] += "; a row it is interpolated from is out of range"
    elif all(isinstance(v, str) and v.split(NOT_JUDGED)[0] == VALID for v in verdicts):
        out["validity"] = VALID + said
    return out


def _slip_report(
    plan,
    out_dir,
    slips,
    run_slips,
    results,
    text,
    bed,
    plot,
    states=(metrics.STEADY,),
    vary="order",
    beds=None,
    soils=None,
) -> dict:
    """Tabulate, write (study.json, study.csv, plots) and describe a slip study's runs."""
    rows = []
    for s in sorted(slips):  # in the order of the curve (the plot joins its points in row order)
        members = [r for slip, r in zip(run_slips, results) if slip == s]
        stats = ensemble_table(members, plan, states)
        rows.append(
            {
                "slip_set": s,
                "replicas": stats["replicas"],
                "steady": stats["steady"],
                "averaged": stats["averaged"],
                "failed": sum(1 for r in members if failed_run(r)),
                "validity": stats["validity"],
                **_flat(stats),
                "dp_over_w_by_replica": by_replica(members, "dp_over_w", states),
                "stats": stats,
            }
        )
    from .scm_calibration import wheel_record

    varied, calibration = _variation(plan, vary, soils)
    report = {
        "kind": "slip",
        "vary": vary,
        "calibration_beds": calibration,
        "bed_files": beds,
        "averaged_states": list(states),
        "rows": rows,
        "runs": results,
        "scene_toml": text,
        "bed_file": bed,
        "wheel_load": plan.wheel_load,
        "wheel": wheel_record(plan.wheel),  # a mesh's digest too: the wheel fit checks its runs drove this one
        "summary_rule": metrics.SUMMARY_RULE,  # its runs' steady-window rule: a wheel fit refuses another
    }
    crossing = zero_pull_slip(rows)
    report["zero_pull_slip"], report["zero_pull_slip_ci95"] = crossing["slip"], crossing["ci95"]
    report["zero_pull_slip_between"], report["zero_pull_slip_note"] = crossing["between"], crossing["note"]
    report["zero_pull_slip_validity"] = crossing["validity"]
    keys = ["slip_set", "replicas", "steady", "averaged", "failed", "validity"] + [
        f"{m}_{k}"
        for m in ("slip", "drawbar_pull", "dp_over_w", "driving_torque", "sinkage", "sinkage_tips")
        for k in ("mean", "std", "ci95")
    ]
    units = {**METRIC_UNITS, **COUNT_UNITS, "slip_set": "1", "dp_over_w_by_replica": "1"}
    columns = list(dict.fromkeys(key for row in rows for key in row if key != "stats"))  # study.json's, all
    report["units"] = {
        **column_units(columns, units),
        **nested_units(rows, results),
        "wheel_load": "N",
        "wheel": {"rim_radius_m": "m", "width_m": "m", "grouser_count": "count", "grouser_height_m": "m"},
        "zero_pull_slip": "1",
        "zero_pull_slip_ci95": "1",
        "zero_pull_slip_between": "1",
    }
    write_json(os.path.join(out_dir, "study.json"), report)
    _write_csv(os.path.join(out_dir, "study.csv"), rows, keys, units)
    # one run a slip varies in nothing (an SCM run sums in one order): no replicas to describe
    runs_each = f"replicas: {varied}" if max((row["replicas"] for row in rows), default=0) > 1 else "one run a slip"
    lines = [
        f"{plan.name}: drawbar pull against imposed slip (W = {plan.wheel_load:.4g} N; {runs_each}"
        + ("; mean +- its 95 % interval over the averaged runs" if runs_each != "one run a slip" else "")
        + f"), {out_dir}",
        f"  {'slip':>6s} {'steady':>7s} {'DP [N]':>12s} {'DP/W':>14s} {'torque [N m]':>14s} {'sinkage [mm]':>13s}"
        "  validity",
    ]
    notes: dict[str, int] = {}  # each out-of-range verdict's footnote number

    def validity(row) -> str:
        verdict = row.get("validity")
        if not out_of_range(verdict) and NOT_JUDGED not in (verdict or ""):
            return verdict or "- (no run finished)"
        said = "out of range" if out_of_range(verdict) else verdict.split(NOT_JUDGED)[0]
        return f"{said} [{notes.setdefault(verdict, len(notes) + 1)}]"

    def averaged(row) -> str:
        said = "" if row["averaged"] == row["steady"] else f" ({row['averaged']} averaged)"
        said += " (one run: no error bar)" if row["averaged"] == 1 else ""  # its numbers stand alone
        return said + (f" ({row['failed']} failed)" if row.get("failed") else "")  # a row of another kind's: none

    for row in rows:

        def cell(name, scale=1.0, row=row):
            mean, ci = row.get(f"{name}_mean"), row.get(f"{name}_ci95")
            if mean is None:
                return "-"
            return f"{mean * scale:.4g}" + (f"+-{ci * scale:.2g}" if ci is not None and ci == ci else "")

        lines.append(
            f"  {row['slip_set']:6.3f} {row['steady']:3d}/{row['replicas']:<3d}{averaged(row)} "
            f"{cell('drawbar_pull'):>12s} "
            f"{cell('dp_over_w'):>14s} {cell('driving_torque'):>14s} {cell('sinkage', 1e3):>13s}  {validity(row)}"
        )
    for verdict, number in notes.items():
        lines.append(f"  [{number}] {verdict}")
    if notes:
        lines.append(
            "      (k/n): failed (or not judged) by k of the n replicas that finished; each one's run.json says why"
        )
    if crossing["slip"] is None:
        lines.append(f"  {crossing['note']}")
    else:
        interval = " (no interval: one replica)"
        if math.isfinite(crossing["ci95"]):
            interval = f" +- {crossing['ci95']:.2g} (95 %)"
        lines.append(f"  DP/W = 0 (self-propelled) at slip {crossing['slip']:.3g}{interval}, {crossing['note']}")
        if out_of_range(crossing["validity"]):
            lines.append(f"  ! the self-propelled slip is {crossing['validity']}")
        elif NOT_JUDGED in (crossing["validity"] or ""):
            lines.append(f"  the self-propelled slip is {crossing['validity']}")
    report["text"] = "\n".join(lines)
    report["ok"] = all(row["steady"] == row["replicas"] for row in rows)
    if plot:
        from .plots import plot_slip_curve

        report["text"] += "\n  plot: " + plot_slip_curve(out_dir, rows)
    return report


# ------------------------------------------------------------------------------------
# sweep


def parse_params(params: list[str]) -> dict[str, list]:
    """['wheel.radius=0.03,0.04', ...] -> {'wheel.radius': [0.03, 0.04], ...} (values read as TOML). Values
    that are lists themselves are given as one TOML array of them: 'rover.mmx.body_size=[[0.1, 0.08, 0.04],
    [0.2, 0.1, 0.05]]' (a text that starts with '[' is that array, so '[0.03, 0.04]' is two values too)."""
    from .scene import parse_list, parse_value

    grid = {}
    for text in params:
        if "=" not in text:
            raise SceneError([f"--param {text!r}: expected key=v1,v2,..."])
        key, values = text.split("=", 1)
        if key.strip() in grid:  # the later one would replace the first without a word
            raise SceneError([f"--param {key.strip()}: given twice; give its values once, comma-separated"])
        if values.strip().startswith("["):  # one TOML array of the values: the way to sweep list values
            entries = parse_value(values)
            if not isinstance(entries, list) or not entries:
                raise SceneError(
                    [
                        f"--param {key.strip()}: {values.strip()!r} is no TOML array of values, "
                        "e.g. [[0.1, 0.2], [0.3, 0.4]]"
                    ]
                )
        else:
            entries = parse_list(values, f"--param {key.strip()}")
        twice = [v for i, v in enumerate(entries) if any(_same_value(v, w) for w in entries[:i])]
        if twice:  # the same run twice, counted as two points
            hint = (
                f" (one list value is given as an array of it: {key.strip()}=[{values.strip()}])"
                if values.strip().startswith("[") and not isinstance(twice[0], list)
                else ""
            )
            raise SceneError([f"--param {key.strip()}: the value {twice[0]!r} is given twice{hint}"])
        grid[key.strip()] = entries
    points = math.prod(len(v) for v in grid.values())
    if points > MAX_SWEEP_POINTS:
        raise SceneError([f"--param: {points} points (the product of the value counts), more than {MAX_SWEEP_POINTS}"])
    return grid


MAX_SWEEP_POINTS = 1000
"""Most runs a sweep's grid may hold [-]: each is checked as a scene before any runs."""


def _folder_label(value) -> str:
    """A sweep value as part of a folder name: letters, digits and . + - only (a path value's separators
    and '..' must not lead out of the sweep's folder), at most 40 characters."""
    return re.sub(r"[^A-Za-z0-9.+-]", "_", str(value)).lstrip(".")[:40] or "_"


SWEEP_FILE = RECIPES["sweep"][0]
"""A sweep's recipe (its folder, scene as run, base folder, --param texts, whether it plots, then its beds once
settled, and a digest of it all), written before its beds settle: `cosim resume OUT` finishes what an
interruption left and writes the table (resume_sweep)."""


def _sweep_points(text: str, base_dir: str | None, params: list[str]) -> tuple[dict, list[dict], list[RunPlan]]:
    """(grid, points, their plans) of a sweep of the scene `text` over `params`; SceneError naming every point
    that is no scene, and every key no point reads."""
    grid = parse_params(params)
    if not grid:
        raise SceneError(["--param: give at least one key=v1,v2,..."])
    points = [dict(zip(grid, values)) for values in itertools.product(*grid.values())]
    plans, problems = [], []
    for point in points:  # validate every point before running any
        try:
            plans.append(resolve(scene_from_text(text, base_dir=base_dir, overrides=point)))
        except SceneError as error:
            problems += [f"point {point}: {p}" for p in error.problems]
    if problems:
        raise SceneError(problems)
    for key in grid:  # a key no point reads: every run the same scene (the sweep's rows told no difference)
        unused = [p.scene.testbed.unused_keys().get(key) if p.scene.testbed is not None else None for p in plans]
        if all(unused):
            problems.append(f"--param {key}: no point of the sweep reads it ({unused[0]})")
    if problems:
        raise SceneError(problems)
    return grid, points, plans


def _sweep_beds(plans: list[RunPlan], out_dir: str, ex: Executor) -> list[str | None]:
    """The settled bed of each point (out_dir/beds/KEY: points with one bed key share it), in point order;
    None for a point that settles none (its own bed.bed_file, or a terrain without grains). By point, not
    by key: a resume on another device class, or after the contact law changed, reckons other keys."""
    from .system import needs_bed

    beds: dict[str, RunPlan] = {}
    for p in plans:
        if not p.bed.bed_file and needs_bed(p):
            beds.setdefault(p.bed.key, p)
    folders = [os.path.join(out_dir, "beds", key) for key in beds]
    settled = dict(zip(beds, _settle(ex, list(beds.values()), folders)))
    return [settled[p.bed.key] if not p.bed.bed_file and needs_bed(p) else None for p in plans]


def _sweep_tasks(
    text: str, base_dir: str | None, points: list[dict], out_dir: str, beds: list[str | None]
) -> list[dict]:
    """A run task per point (run_task's form, with its 'point'), each on its settled bed (_sweep_beds)."""
    tasks: list[dict[str, Any]] = []
    for i, (point, bed) in enumerate(zip(points, beds)):
        overrides = dict(point)
        if bed is not None:
            overrides["bed.bed_file"] = bed
        name = f"{i:03d}_" + "_".join(f"{_folder_label(k.split('.')[-1])}={_folder_label(v)}" for k, v in point.items())
        tasks.append(
            {
                "scene_toml": text,
                "overrides": overrides,
                "out_dir": os.path.join(out_dir, name),
                "label": name,
                "point": point,
                "base_dir": base_dir,
            }
        )
    return tasks


def sweep(
    plan: RunPlan,
    out_dir: str,
    params: list[str],
    executor: str = "dask",
    scheduler: str | None = None,
    workers: int | None = None,
    overwrite: bool = False,
    plot: bool = True,
) -> dict:
    """One run per point of the grid; points that share a bed share one settled bed (a point on a
    terrain without grains, SCM or the analytic one, settles none). Stopped (Ctrl-C, SIGTERM, a kill), it
    is finished by `cosim resume OUT` (resume_sweep: its SWEEP_FILE recipe)."""
    text = plan.scene.to_toml()
    grid, points, plans = _sweep_points(text, plan.scene.base_dir, params)
    out_dir = os.path.abspath(out_dir)
    tasks_run = Executor(executor, scheduler, workers)  # refused before the folder is made
    with prepare_study(out_dir, overwrite):
        recipe = {
            "kind": "sweep",
            "out_dir": out_dir,
            "scene_toml": text,
            "base_dir": plan.scene.base_dir,
            "params": list(params),
            "plot": bool(plot),
        }
        _write_recipe(out_dir, recipe)  # before the beds: `cosim resume` finishes them
        with tasks_run as ex:
            try:
                beds = _sweep_beds(plans, out_dir, ex)
                _write_recipe(out_dir, {**recipe, "beds": beds})  # the beds the runs use, never settled again
                tasks = _sweep_tasks(text, plan.scene.base_dir, points, out_dir, beds)
                results = ex.map(run_task, tasks)
            except (KeyboardInterrupt, RunInterrupted) as stop:
                raise _replicas_stopped(stop, out_dir, "the sweep", "its table") from None
        with _said_stopped(out_dir, "the sweep", "its table"):
            return _sweep_report(plan, out_dir, grid, tasks, results, text, plot)


def resume_sweep(out_dir: str) -> dict:
    """Finish a sweep an interruption (or a kill) left (its SWEEP_FILE), as resume_replicas finishes a set
    of replicas (_finish_set); then its table written as sweep writes it."""
    out_dir = os.path.abspath(out_dir)
    recipe = _read_recipe(out_dir, "sweep")
    text, base_dir = recipe["scene_toml"], recipe["base_dir"]
    plan = resolve(scene_from_text(text, base_dir=base_dir))  # its errors name the key
    grid, points, plans = _sweep_points(text, base_dir, recipe["params"])

    def tasks(beds):
        if len(beds) != len(points):
            raise DamagedFileError(
                f"{os.path.join(out_dir, SWEEP_FILE)}: its beds are not one per point ({len(points)}: a recipe of "
                "another version); resume each point's run alone (cosim resume OUT/000_...), or run the sweep again"
            )
        return _sweep_tasks(text, base_dir, points, out_dir, beds)

    return _finish_set(
        out_dir,
        recipe,
        ("the sweep", "its table"),
        lambda ex: _sweep_beds(plans, out_dir, ex),
        tasks,
        lambda tasks, results, beds: _sweep_report(plan, out_dir, grid, tasks, results, text, bool(recipe["plot"])),
    )


def _sweep_report(
    plan: RunPlan, out_dir: str, grid: dict, tasks: list[dict], results: list[dict], text: str, plot: bool
) -> dict:
    """A sweep's table of its runs' results, written as study.json, study.csv and plots; its report."""
    from .plots import plot_table

    columns: tuple[str, ...] = (
        "steady_state",
        "slip",
        "travel",
        "sinkage",
        "drawbar_pull",
        "driving_torque",
        "wall_time",
    )
    if plan.rover is not None:  # drive controllers side by side
        columns = (
            "steady_state",
            "slip",
            "travel",
            "forward_speed",
            "sinkage",
            "net_traction",
            "net_traction_over_weight",
            "power",
            "energy_per_metre",
            "time_immobile",
            "stuck",
            "stalled",
            "wall_time",
        )
    rows = []
    for task, result in zip(tasks, results):
        row = {
            **task["point"],
            "ok": result.get("ok"),
            "status": result.get("status"),
            "validity": run_validity(result),
        }
        row.update({k: result.get("summary", {}).get(k) for k in columns})
        if not result.get("ok"):
            row["error"] = result.get("error")
        rows.append(row)
    keys = list(grid) + ["ok", "status", "validity", *columns]
    swept = {key: unit for key in grid if (unit := key_unit(key)) is not None}  # as cosim/scene.py documents them
    units = {**METRIC_UNITS, **swept}
    table_units = column_units(keys, units)
    report: dict = {"kind": "sweep", "grid": grid, "rows": rows, "runs": results, "scene_toml": text}
    report["summary_rule"] = metrics.SUMMARY_RULE
    report["units"] = {**table_units, **nested_units(rows, results)}
    write_json(os.path.join(out_dir, "study.json"), report)
    log.info("%s", plot_table(rows, keys, table_units))
    _write_csv(os.path.join(out_dir, "study.csv"), rows, keys, units)
    for r in rows:
        if r.get("error"):
            log.warning("failed: %s", r["error"])
    if plot:
        from .plots import plot_output

        try:
            log.info("plots: %s", ", ".join(plot_output(out_dir)))
        except ArgumentError as error:  # no results.h5 under out_dir: every run failed
            log.warning("%s", error)
    return report


# ------------------------------------------------------------------------------------
# time-step study


MAX_TRY_DURATION = 60.0
"""Longest try of the stable-step search [s]: an explosion shows within a few contact times."""

MAX_TRIES = 40
"""Most tries of the stable-step search [-]: 1.5^40 (about 1e7) times the scene's step either way."""

MIN_TRY_STEPS = 100
"""Fewest DEM steps of the search's first try (the scene's own step): an unstable step needs steps to
grow into an explosion; a try of one step explodes at no step, and its 'largest stable step' means nothing."""


def timestep_study(
    plan: RunPlan,
    out_dir: str,
    duration: float = 0.05,
    growth: float = 1.5,
    max_tries: int = 8,
    overwrite: bool = False,
) -> dict:
    """The largest stable DEM step for the scene's bed with the wheel resting on it and turning.

    The search starts at the scene's own step and grows it by `growth` until a run of
    `duration` [s] explodes (or shrinks it while even that explodes), at most `max_tries`
    runs, each logged as it ends. The answer is the last stable step times 0.5."""
    from soil import advisor

    from .dem_soil import DemSoil
    from .system import CoupledSystem

    if not (0 < duration <= MAX_TRY_DURATION and growth > 1 and max_tries >= 1):
        raise SceneError(
            [
                f"--duration, growth, --max-tries: need 0 < duration <= {MAX_TRY_DURATION:g} s, > 1, >= 1 "
                f"(got {duration}, {growth}, {max_tries})"
            ]
        )
    if duration < MIN_TRY_STEPS * plan.dt:
        raise SceneError(
            [
                f"--duration {duration:g} s: a try of {duration / plan.dt:.3g} DEM steps of the scene's "
                f"{plan.dt:.3g} s cannot show an instability; at least {MIN_TRY_STEPS} steps: "
                f"--duration >= {MIN_TRY_STEPS * plan.dt:.3g} s"
            ]
        )
    # a scene whose own step explodes is searched downwards: its last try takes growth^(tries - 1) x the
    # steps of the first, which must stay a run that ends
    most_steps = duration / plan.dt * growth ** (min(max_tries, MAX_TRIES + 1) - 1)  # no float overflow
    if max_tries > MAX_TRIES or most_steps > MAX_PHASE_STEPS:
        raise SceneError(
            [
                f"--max-tries {max_tries}, --duration {duration:g} s: at most {MAX_TRIES} tries, and a search that "
                f"shrinks the step at every try must end with a try of at most {MAX_PHASE_STEPS:.0e} DEM steps "
                f"(here {most_steps:.3g} or more): fewer tries or a shorter duration"
            ]
        )
    if plan.terrain.model != "dem":  # checked before the study's folder is touched
        raise SceneError(
            [f"terrain.model: the stable-step search is of the DEM step; this scene runs on {plan.terrain.model}"]
        )
    out_dir = os.path.abspath(out_dir)
    with prepare_study(out_dir, overwrite):
        bed = settled_bed(plan, out_dir)
        assert plan.testbed is not None, "the stable-step search turns the single-wheel testbed's wheel"
        omega = plan.testbed.omega
        rim = omega * plan.wheel.outer_radius

        def make_simulation():
            system = CoupledSystem.build(plan, bed)
            assert isinstance(system.soil, DemSoil), "the stable-step search is of the DEM step"
            sim = system.soil.sim
            hub = system.rover.position
            sim.set_body_motion(0, hub, [1, 0, 0, 0], [rim, 0, 0], [0, omega, 0])
            sim.refresh_forces()
            return sim

        ended = [time.perf_counter()]  # when each try ended (the first entry: the search's start)

        def log_try(dt, ok, message):
            ended.append(time.perf_counter())
            log.info(
                "try %d/%d: dt = %.4g s (%.3g x the scene's): %s (%.1f s wall)",
                len(ended) - 1,
                max_tries,
                dt,
                dt / plan.dt,
                "stable" if ok else "UNSTABLE",
                ended[-1] - ended[-2],
            )

        search = advisor.largest_stable_step(
            make_simulation,
            duration,
            dt_start=plan.dt,
            growth=growth,
            safety=0.5,
            max_runs=max_tries,
            check_every=20,
            progress=log_try,
        )
        largest, first_bad, tries = search.largest_stable, search.first_unstable, search.tried
        advice = advisor.recommended_time_step(make_simulation())
        report = {
            "kind": "timestep",
            "scene_dt": plan.dt,
            "duration": duration,
            "largest_stable": largest,
            "first_unstable": first_bad,
            "recommended": search.recommended,
            "tried": [{"dt": d, "stable": ok, "message": m} for d, ok, m in tries],
            "advisor": {
                "dt_min": advice.dt_min,
                "dt_max": advice.dt_max,
                "critical_step": advice.critical_step,
                "contact_time": advice.contact_time,
            },
            "units": dict.fromkeys(  # every number above is a time
                ("scene_dt", "duration", "largest_stable", "first_unstable", "recommended", "tried.dt", "advisor"), "s"
            ),
        }
        if largest is not None and first_bad is None:  # the tries ended before one exploded
            report["note"] = (
                f"no try was unstable ({len(tries)} of --max-tries): the largest stable step is at least "
                f"{largest:.4g} s (not found), and the recommended one is half of that bound; --max-tries for more"
            )
        write_json(os.path.join(out_dir, "study.json"), report)
        if "note" in report:
            log.warning("%s", report["note"])
        if largest is None:
            log.error(
                "no stable step found in %d tries down to %.4g s: the scene is unstable at any step tried; check "
                "`cosim advise` (stiffness, overlaps)",
                len(tries),
                tries[-1][0],
            )
        else:
            log.info(
                "largest stable step %s s, first unstable %s s, recommended %s s; the advisor says %.4g .. %.4g s; "
                "the scene uses %.4g s",
                _s(largest),
                _s(first_bad),
                _s(report["recommended"]),
                advice.dt_min,
                advice.dt_max,
                plan.dt,
            )
        return report


def _s(value) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.4g}"


__all__ = [
    "Executor",
    "ensemble_table",
    "precision_study",
    "replica_run",
    "run_task",
    "slip_study",
    "sweep",
    "timestep_study",
]
