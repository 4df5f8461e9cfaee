"""Replicas batched on one device: K runs of one scene as K worlds of one DEM simulation.

    results = run_batched(plans, out_dirs)        # cosim.study.replica_run(..., batched=True)

Each replica is a world of one soil.worlds.Worlds (the same bed, its own order seed, wheel, rig
or rover, results folder, checkpoints); the K runs are stepped from K threads that meet at each
macro step, where the DEM steps every world in the same launches. A world's results are bit for
bit those of its run alone (tests/test_batch.py), and each folder is an ordinary run folder:
`cosim resume FOLDER` continues it alone.

What a batch cannot run (`batch_problem` says why, and the replicas then run one by one): a
terrain other than the DEM, a moving soil patch, the PID step control (one step for all worlds),
an FMU rover (its instances are not shared across threads here). Shared by the worlds: the clock,
the DEM step, the divergence monitor (a world that diverges stops the batch; each run reports it
with its own last good state) and the wall time (each run's is the batch's).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
import traceback
from dataclasses import replace

from soil.errors import ArgumentError
from soil.integrator import make_integrator
from soil.worlds import Worlds, open_bed_worlds

from .beds import check_memory, settled_bed
from .dem_soil import DemSoil
from .launch import open_run
from .plan import RunPlan
from .runner import STOP_SIGNALS, Runner

log = logging.getLogger(__name__)


def batch_problem(plan: RunPlan) -> str | None:
    """Why the replicas of `plan` cannot run as worlds of one simulation (None: they can)."""
    if plan.terrain.model != "dem":
        return f"terrain.model {plan.terrain.model!r}: only the DEM terrain is batched"
    if plan.patch is not None:
        return "a moving soil patch (rover.patch) changes its grains: its replicas run one by one"
    if plan.step_control != "fixed":
        return "run.step_control = 'pid' sets one step per world: batched worlds share a fixed step"
    if plan.rover is not None and plan.rover.model == "fmu":
        return "an FMU rover: its replicas run one by one"
    return None


SOIL_FIELDS = ("bed", "wheels", "device", "precision", "storage", "contact law", "integrator", "dt", "macro step")
"""What the worlds of one batch share (their plans must agree on it)."""


def _soil_of(plan: RunPlan) -> tuple:
    wheels = plan.wheels if plan.rover else [plan.wheel]
    return (
        plan.bed.bed_file or plan.bed.key,
        repr([(w.shape, w.material) for w in wheels]),
        plan.device,
        plan.precision,
        plan.storage,
        plan.law,
        plan.integrator,
        plan.dt,
        plan.macro_step,
    )


def run_batched(
    plans: list[RunPlan], out_dirs: list[str], overwrite: bool = False, hooks: dict | None = None
) -> list[dict]:
    """Run `plans` (replicas of one scene: the same bed, any order seeds) as worlds of one simulation
    into `out_dirs`; returns one result per run as cosim.study.run_task does (label, out_dir, ok,
    status, summary, wall_time, error), each with the batch's figures ('batch': worlds, wall_seconds,
    rounds, step_seconds: the host clock of the macro steps themselves). hooks: each Runner's
    (cosim.runner.Runner), called from its thread."""
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
    with contextlib.ExitStack() as stack:
        bed = settled_bed(first, out_dirs[0])
        on_bed = replace(first, bed=replace(first.bed, bed_file=os.path.abspath(bed.path)))
        check_memory(on_bed, len(plans))  # the K worlds must fit: checked before they are allocated
        wheels = [(w.shape, w.material) for w in (first.wheels if first.rover else [first.wheel])]
        worlds = open_bed_worlds(
            bed.saved,
            wheels,
            [p.order_seed for p in plans],
            device=first.device,
            precision=first.precision,
            law=first.law,
            integrator=make_integrator(first.integrator),
            gravity=first.gravity if first.rover else None,
            storage=first.storage,
        )
        runners = []
        for k, (plan, out) in enumerate(zip(plans, out_dirs)):
            soil = DemSoil(worlds.world(k), plan.dt, bed.surface_height)
            system, writer, folder = stack.enter_context(open_run(plan, out, overwrite=overwrite, soil=soil))
            runners.append(Runner(system, writer, folder, hooks=hooks))
        worlds.ensure_forces()  # every world's wheels placed: their forces once
        results = _run_threads(worlds, runners)
    wall = time.perf_counter() - started
    log.info("%d replicas as one batch of worlds: %.1f s, %d macro steps together", len(plans), wall, worlds.rounds)
    batch = {"worlds": len(plans), "wall_seconds": wall, "rounds": worlds.rounds, "step_seconds": worlds.step_seconds}
    return [{**r, "label": f"replica_{k:03d}", "wall_time": wall, "batch": batch} for k, r in enumerate(results)]


def _run_threads(worlds: Worlds, runners: list[Runner]) -> list[dict]:
    """Each runner in its own thread (the worlds meet at every macro step); a stop signal stops them all
    cleanly after the macro step."""
    results: list[dict] = [{} for _ in runners]

    def run(k: int) -> None:
        runner = runners[k]
        out: dict = {"out_dir": runner.folder.path}
        try:
            result = runner.run()
            out.update(ok=True, status=result.status, summary=result.summary)
        except BaseException as error:  # noqa: BLE001 - a failed replica is a result
            out.update(
                ok=False, status="failed", error=f"{type(error).__name__}: {error}", traceback=traceback.format_exc(5)
            )
        finally:
            worlds.leave(k)
        results[k] = out

    threads = [threading.Thread(target=run, args=(k,), name=f"world-{k}") for k in range(len(runners))]
    previous = _stop_all_on_signal(runners)
    try:
        for thread in threads:
            thread.start()
        for thread in threads:
            while thread.is_alive():
                thread.join(timeout=0.5)
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
    return results


def _stop_all_on_signal(runners: list[Runner]) -> dict:
    """Ctrl-C or SIGTERM asks every run of the batch to stop after its macro step with a checkpoint (the
    runs' threads cannot take signals); returns the handlers it replaced."""
    if threading.current_thread() is not threading.main_thread():
        return {}

    def handler(signum, frame):
        name = signal.Signals(signum).name
        log.warning("%s: every run of the batch stops after its macro step with a checkpoint", name)
        for runner in runners:
            runner.stop_requested = True
            runner.stop_signal = name

    return {number: signal.signal(number, handler) for number in STOP_SIGNALS}
