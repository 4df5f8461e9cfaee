"""What the lab tests share: fills, phases that run until a condition, replicas through
cosim.study.Executor, and the report files (CSV with units, summary JSON, figure)."""

from __future__ import annotations

import contextlib
import csv
import io
import logging
import math
import os
import time
import traceback
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from soil import Simulation, SimulationDiverged, quiet_warp
from soil.errors import RegolithError
from soil.files import atomic_write_text
from soil.memory import check_fits, estimate

from ..folders import write_json
from ..metrics import ensemble
from ..scene import SceneError
from ..study import Executor, check_executor, prepare_study
from .scene import LabPlan, lab_scene_from_text, resolve_lab

log = logging.getLogger("cosim.lab")

SCENE_FILE = "scene.toml"
SUMMARY_FILE = "summary.json"


# -- grains ---------------------------------------------------------------------------------


def replica_seeds(plan: LabPlan, replica: int) -> tuple[int, int]:
    """(fill seed, order_seed) of replica k: a new specimen (bed.seed + k) summed in its own order (k)."""
    return plan.seed + replica, replica


def lattice_fill(plan: LabPlan, lower, upper_xy, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """`count` grains on a jittered cubic lattice filling the footprint lower[:2] .. upper_xy
    from z = lower[2] upwards, layer by layer, not touching each other or the footprint's sides.

    Returns positions [m] shape (count, 3) and radii [m] shape (count,) (uniform in
    radius_mean (1 +- radius_spread))."""
    rng = np.random.default_rng(seed)
    r_max = plan.radius_max
    pitch = 2.04 * r_max
    lower = np.asarray(lower, dtype=np.float64)
    span = np.asarray(upper_xy, dtype=np.float64) - lower[:2]
    nx, ny = (int((s - 2 * r_max) // pitch) + 1 for s in span)
    if min(nx, ny) < 1:
        raise SceneError(
            [
                f"a fill region of {span[0]:.4g} x {span[1]:.4g} m cannot hold a grain of radius "
                f"{r_max:.4g} m (bed.radius_mean, bed.radius_spread)"
            ]
        )
    layers = -(-count // (nx * ny))
    grid = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(layers), indexing="ij"), -1).reshape(-1, 3)
    grid = grid[np.lexsort((grid[:, 1], grid[:, 0], grid[:, 2]))][:count]  # lowest layers first
    radii = plan.radius_mean * (1 + plan.radius_spread * rng.uniform(-1, 1, count))
    # centre the lattice in the footprint; each grain may move within its cell without touching a neighbour
    offset = lower + np.array([0.5 * (span[0] - (nx - 1) * pitch), 0.5 * (span[1] - (ny - 1) * pitch), r_max * 1.01])
    slack = 0.5 * pitch - radii[:, None]
    jitter = rng.uniform(-1, 1, (count, 3)) * slack
    jitter[:, 2] = np.abs(jitter[:, 2])  # never below the first layer's floor
    return offset + grid * pitch + jitter, radii


def grains_for(plan: LabPlan, volume: float, keys: str | None = None) -> int:
    """Grains of the mean size that fill `volume` [m^3] at the packing fraction of a random packing [-].
    Given `keys` (the scene keys that size the specimen: the check before the folder is made, not in each
    replica, where the others' memory is in use), SoilTooLargeError names them when one specimen cannot fit
    this machine's free memory (its arrays were allocated until a MemoryError, or for hours)."""
    from .scene import PACKING_FRACTION

    mean_volume = 4.0 / 3.0 * math.pi * plan.radius_mean**3 * (1 + plan.radius_spread**2)  # E[r^3] of a uniform r
    count = max(1, int(round(PACKING_FRACTION * volume / mean_volume)))
    if keys is not None:
        check_specimen_fits(plan, count, f"{keys}, bed.radius_mean")
    return count


def check_specimen_fits(plan: LabPlan, grains: int, keys: str) -> None:
    """SoilTooLargeError when one lab specimen of `grains` grains cannot fit this machine's free memory."""
    check_fits(estimate(grains, plan.precision, plan.device), f"a lab specimen of {grains:.3g} grains", keys)


def finalize(plan: LabPlan, builder, order_seed: int | None) -> Simulation:
    """A Simulation of the builder on the plan's device, precision and contact law."""
    model, state, control = builder.finalize(
        device=plan.device, precision=plan.precision, law=plan.law, order_seed=order_seed
    )
    return with_step_control(plan, Simulation(model, state, control))


def with_step_control(plan: LabPlan, sim: Simulation) -> Simulation:
    """`sim` with the scene's step control (run.step_control = "pid": PID substeps in every
    Simulation.run, the first one plan.dt long); fixed steps otherwise."""
    run = plan.scene.run
    if run.step_control == "pid":
        from soil import StepController

        sim.enable_step_control(
            StepController(tolerance=run.tolerance, dt_min=run.dt_min, dt_max=run.dt_max, dt_initial=plan.dt)
        )
    return sim


# -- phases ---------------------------------------------------------------------------------


def moving_energy(sim: Simulation) -> float:
    """Translational kinetic energy of the free grains [J]: whether grains still move (a grain
    spinning in place, which no twisting friction stops, does not change a heap)."""
    free = sim.free_grains()
    v = sim.velocities()[free]
    return float(0.5 * np.sum(sim.masses()[free] * np.sum(v * v, axis=1)))


def kinetic_threshold(sim: Simulation, ratio: float, g: float) -> float:
    """ratio * N m_mean |g| r_mean over the free grains [J]: 'still' on Earth and on Phobos alike."""
    free = sim.free_grains()
    mass = sim.masses()[free]
    radius = sim.radii()[free]
    return ratio * len(mass) * float(mass.mean()) * g * float(radius.mean())


def run_until(
    sim: Simulation, dt: float, done, max_time: float, chunk: float, min_time: float = 0.0, callback=None
) -> tuple[float, bool]:
    """Step in chunks of `chunk` [s] until done(sim) (checked after each chunk, not before
    min_time [s]) or max_time [s]. Returns (elapsed time [s], whether done)."""
    start = sim.time
    while sim.time - start < max_time - 0.5 * dt:
        sim.run(min(chunk, max_time - (sim.time - start)), dt, callback=callback)
        sim.check_finite()
        if sim.time - start >= min_time and done(sim):
            return sim.time - start, True
    return sim.time - start, False


def chunk_steps(plan: LabPlan, duration: float) -> float:
    """`duration` [s] rounded to whole DEM steps (at least one) [s]."""
    return max(1, round(duration / plan.dt)) * plan.dt


# -- replicas -------------------------------------------------------------------------------


def lab_task(task: dict) -> dict:
    """Run one lab task: task['runner'](plan, **task['arguments']), the plan from the task's
    scene_toml, base_dir and overrides; never raises (a failed replica is a result). Module
    level, and the runner a module-level function: picklable for dask workers."""
    import warp as wp

    wp.config.log_level = wp.LOG_ERROR
    started = time.perf_counter()
    out = {"label": task.get("label"), "replica": task.get("replica")}
    try:
        quiet_warp()
        plan = resolve_lab(lab_scene_from_text(task["scene_toml"], task.get("base_dir"), task.get("overrides")))
        result = task["runner"](plan, **task.get("arguments", {}))
        out.update(ok=True, result=result)
    except BaseException as error:  # noqa: BLE001 - reported with the others
        out.update(ok=False, error=f"{type(error).__name__}: {error}", traceback=traceback.format_exc(limit=6))
        out["diverged"] = isinstance(error, SimulationDiverged)
        if isinstance(error, KeyboardInterrupt):
            raise
    out["wall_time"] = time.perf_counter() - started
    return out


def map_tasks(
    plan: LabPlan,
    runner,
    arguments: list[dict],
    labels: list[str],
    executor="serial",
    scheduler: str | None = None,
    workers: int | None = None,
) -> list[dict]:
    """runner(plan, **arguments) once per arguments dict, through cosim.study.Executor: executor
    is 'dask' or 'serial' (an Executor is made for these tasks) or an Executor already open
    (a calibration keeps one cluster for all its evaluations)."""
    toml = plan.scene.to_toml()
    tasks = [
        {
            "runner": runner,
            "scene_toml": toml,
            "base_dir": plan.scene.base_dir,
            "arguments": a,
            "label": label,
            "replica": a.get("replica"),
        }
        for a, label in zip(arguments, labels)
    ]
    if isinstance(executor, Executor):
        return executor.map(lab_task, tasks)
    with Executor(executor, scheduler, workers) as ex:
        return ex.map(lab_task, tasks)


def map_until_stopped(
    plan: LabPlan,
    runner,
    arguments: list[dict],
    labels: list[str],
    executor="serial",
    scheduler: str | None = None,
    workers: int | None = None,
) -> tuple[list[dict], KeyboardInterrupt | None]:
    """map_tasks, but Ctrl-C or SIGTERM while the tasks run returns the results of those that finished
    and the interrupt itself: the caller writes their report, then raises it (exit 130 or 143), so the
    replicas that ran are not lost. With none finished the interrupt propagates at once."""
    try:
        return map_tasks(plan, runner, arguments, labels, executor, scheduler, workers), None
    except KeyboardInterrupt as stop:
        finished = [r for r in getattr(stop, "finished", None) or [] if r is not None]
        if not any(r.get("ok") for r in finished):
            raise
        log.warning(
            "interrupted after %d of %d tasks: their report is written, then the test stops",
            len(finished),
            len(arguments),
        )
        return finished, stop


def interrupted_notes(stopped: KeyboardInterrupt | None, finished: int, total: int, what: str) -> list[str]:
    """The report's note of a test interrupted after `finished` of `total` tasks (map_until_stopped)."""
    if stopped is None:
        return []
    return [f"interrupted after {finished} of {total} {what}: the values are over these only"]


def successful(results: list[dict], test: str) -> list[dict]:
    """The results of the replicas that ran; LabFailed when none did (the first error is named)."""
    good = [r["result"] for r in results if r.get("ok")]
    failed = [r for r in results if not r.get("ok")]
    for r in failed:
        log.warning("%s %s failed: %s", test, r.get("label"), r.get("error"))
    if not good:
        first = failed[0] if failed else {}
        if failed and all(r.get("diverged") for r in failed):
            raise LabDiverged(
                f"every {test} replica diverged (the DEM exploded during the lab test); the first: "
                f"{first.get('error')}. Lower run.dt_factor (or set a smaller run.dt), or soften the soil as "
                "`cosim advise` says"
            )
        raise LabFailed(f"every {test} replica failed; the first: {first.get('error')}\n{first.get('traceback', '')}")
    return good


class LabFailed(RegolithError, RuntimeError):
    """No replica of a lab test produced a result."""


class LabDiverged(LabFailed):
    """Every replica of a lab test diverged (exit 4 on the command line, like any divergence)."""


def statistics(values) -> dict:
    """Replica statistics of one measured value (cosim.metrics.ensemble: n, mean, std, ci95, min, max)."""
    stats = ensemble(list(values))
    return {k: stats[k] for k in ("n", "mean", "std", "ci95", "min", "max") if k in stats}


# -- report files -----------------------------------------------------------------------------


@contextlib.contextmanager
def prepare_folder(
    plan: LabPlan, out_dir: str, overwrite: bool, executor: str | Executor = "serial", scheduler: str | None = None
) -> Iterator[None]:
    """Hold the output folder while the test runs in it (`with prepare_folder(...)`: cosim.study.prepare_study,
    its lock and its rules for a non-empty folder) and write the scene as run, once the tasks can run where
    asked (an executor kind without dask.distributed installed is refused first)."""
    if not isinstance(executor, Executor):
        check_executor(executor, scheduler)
    with prepare_study(out_dir, overwrite):
        atomic_write_text(os.path.join(out_dir, SCENE_FILE), plan.scene.to_toml())  # a cut one would read as whole
        log.info("%s: %s", out_dir, phase_cost(plan))
        yield


def phase_cost(plan: LabPlan) -> str:
    """What a specimen's settling and resting phases may cost, said before they start (a soil of tiny
    grains settled for an hour without a word): each ends at its criterion or after lab.max_time_factor
    sqrt(d / |g|) (a plate's settling: bed.settle_max_time if longer), in DEM steps. A plate's press and
    a shear last their travel over their speed, which the test's own keys set."""
    longest = plan.max_phase_time(1.0)
    settling = max(longest, plan.scene.bed.settle_max_time)
    at = "the PID's first step" if plan.scene.run.step_control == "pid" else "the DEM step"
    return (
        f"{plan.scene.lab.replicas} replica(s); each settling or resting phase runs until its criterion, at most "
        f"{longest:.3g} s (lab.max_time_factor sqrt(d / |g|); a plate's settling up to {settling:.3g} s, "
        f"bed.settle_max_time if longer): up to about {longest / plan.dt:.3g} DEM steps a phase at {at} "
        f"{plan.dt:.3g} s; a press or a shear lasts its travel over its speed (plate.speed_ratio, "
        "shear.inertial_number)"
    )


def write_csv(path: str, columns: Sequence[tuple[str, str, Any]]) -> None:
    """A CSV file whose header names each column with its unit, 'name [unit]'; written whole or not at all
    (soil.files.atomic_write_text: a crash never leaves a table cut short, nor spoils the one there)."""
    arrays = [np.asarray(values).reshape(-1) for _, _, values in columns]
    length = max((len(a) for a in arrays), default=0)
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow([f"{name} [{unit}]" for name, unit, _ in columns])
    for i in range(length):
        writer.writerow([_cell(a[i]) if i < len(a) else "" for a in arrays])
    atomic_write_text(path, text.getvalue())


def _cell(value):
    if isinstance(value, (float, np.floating)):
        return "" if not np.isfinite(value) else f"{float(value):.10g}"
    return value.item() if isinstance(value, np.generic) else value


def write_summary(out_dir: str, summary: dict) -> str:
    path = os.path.join(out_dir, SUMMARY_FILE)
    write_json(path, summary)
    return path


def pyplot():
    """matplotlib's pyplot with the file backend, or None when matplotlib is missing (pip install .[plot])."""
    try:
        import matplotlib
    except ImportError:
        log.warning("matplotlib is not installed: no figure (pip install 'regolith-cosim[plot]')")
        return None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def soil_summary(plan: LabPlan) -> dict:
    """The soil under test, for the summaries (SI units, angles in degrees)."""
    s = plan.soil
    return {
        "youngs_modulus_pa": s.youngs_modulus,
        "poisson_ratio": s.poisson_ratio,
        "stick_angle_deg": math.degrees(s.stick_angle),
        "slip_angle_deg": math.degrees(s.slip_angle),
        "stick_speed_m_s": s.stick_speed,
        "rolling_friction": s.rolling_friction,
        "cohesion_pa": s.cohesion,
        "restitution": s.restitution,
        "damping_ratio": s.lehr_damping,
        "density_kg_m3": s.density,
        "radius_mean_m": plan.radius_mean,
        "radius_spread": plan.radius_spread,
        "law": {
            "damping": plan.law.damping,
            "friction": plan.law.friction,
            "rolling": plan.law.rolling,
            "cohesion": plan.law.cohesion,
            "twisting": plan.law.twisting,
        },
    }


def quasi_static(name: str, value: float, limit: float, meaning: str) -> dict:
    """One dimensionless number of a test against the limit that keeps it quasi-static."""
    return {
        "name": name,
        "value": float(value),
        "limit": float(limit),
        "ok": bool(value <= limit * (1 + 1e-9)),
        "meaning": meaning,
    }


def stiffness_number(plan: LabPlan, pressure: float) -> dict:
    """p / E* against 1e-3: the Hertz overlap of grains under the pressure stays below about 1 %
    of their radius (delta / r ~ (p / E*)^(2/3))."""
    e_star = plan.soil.youngs_modulus / (2 * (1 - plan.soil.poisson_ratio**2))
    return quasi_static(
        "stiffness p / E*",
        pressure / e_star,
        1e-3,
        "largest pressure over the contact modulus: overlaps stay small (rigid grains)",
    )
