"""The settled bed of a run: a saved bed file, or one settled now and cached in a folder.

A bed settled for a plan is written to FOLDER/bed.h5 with FOLDER/bed.json beside it
(its cache key, settling report and metrics). A later run whose plan has the same bed
key (bed geometry, grains, soil material, gravity, device kind) reuses it. Within one
process the bed stays in memory (Bed.saved): the file is the cache between processes.
A bed that explodes while settling leaves its last good state in FOLDER/bed_diverged.npz
(a soil checkpoint, soil.stability.read_checkpoint), removed when a bed settles there.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import math
import os
import time
from dataclasses import dataclass, field

from soil.bed import METRIC_UNITS, SavedBed, read_bed
from soil.errors import RegolithError
from soil.stability import SimulationDiverged, write_checkpoint
from soil.state import STATE_UNITS

from .folders import write_json
from .plan import RunPlan
from .scene import SceneError

BED_FILE = "bed.h5"
BED_INFO_FILE = "bed.json"
BED_DIVERGED_FILE = "bed_diverged.npz"

log = logging.getLogger(__name__)


class SettlingDiverged(RegolithError, RuntimeError):
    """The bed exploded while it settled (before any run): the message names the phase, the time, the
    grain and the scene keys to change (exit 4 on the command line, like any divergence)."""

    def __init__(self, error: SimulationDiverged, plan: RunPlan, kept: str | None = None):
        """kept: the file holding the settling's last good state (None: there was none to keep)."""
        where = f", grain {error.particle}" if error.particle is not None else ""
        if error.position is not None:
            where += " at ({:.4g}, {:.4g}, {:.4g}) m".format(*error.position)
        time = f"t = {error.time:.6g} s" if error.time is not None else "the start"
        if plan.step_control == "pid":  # the PID settles the bed too: its keys set the settling's substeps
            step = f"Lower {plan.step_keys}"
        else:
            step = f"Lower bed.settle_dt_factor (the settling step is {plan.bed.settle_dt:.3g} s)"
        kept_text = (
            "no bed was written"
            if kept is None
            else f"no bed was written; the settling's last good state (t = {_good_time(error):.6g} s) is {kept}"
        )
        from .advice import stiff_mode_hint

        super().__init__(
            f"the bed diverged while settling, at {time} of the settling{where}: {error.reason or error}. {step}, "
            f"check scene.gravity (|g| = {plan.g:.4g} m/s^2) and the friction angles (soil.stick_angle_deg, "
            f"soil.slip_angle_deg){stiff_mode_hint(plan, settling=True)}; {kept_text}"
        )


def _good_time(error: SimulationDiverged) -> float:
    """The simulated time of a divergence's last good state [s]."""
    assert error.last_good is not None
    return float(error.last_good["time"])


def _keep_last_good(error: SimulationDiverged, folder: str) -> str | None:
    """Write the settling's last good state to folder/bed_diverged.npz (atomically); its path, or None when
    the divergence kept no state (before the monitor's first check) or the file cannot be written (logged)."""
    if error.last_good is None:
        return None
    path = os.path.join(folder, BED_DIVERGED_FILE)
    try:
        return write_checkpoint(path, error.last_good, STATE_UNITS)
    except OSError as problem:  # the divergence is the error to report; this one is logged beside it
        log.error("the settling's last good state could not be saved to %s: %s", path, problem)
        return None


@dataclass(frozen=True)
class Bed:
    """A settled bed: on disk, and in memory once settled or read in this process."""

    path: str
    """The bed file (HDF5, soil.bed.save_bed)."""
    surface_height: float
    """Undisturbed surface z [m] (the bed's height metric)."""
    info: dict = field(default_factory=dict)
    """source ('file' | 'cache' | 'settled'), metrics, settling report, wall time [s]."""
    settled: SavedBed | None = field(default=None, repr=False, compare=False)
    """The bed as settled in this process (None: it is read from `path` when first needed)."""

    @functools.cached_property
    def saved(self) -> SavedBed:
        """The bed in memory (soil.bed.open_bed opens it): the one settled in this process, else the
        file read once (what it holds is what was settled, to the last bit)."""
        return self.settled if self.settled is not None else read_bed(self.path)


def bed_from_file(path: str, setting: str = "bed.bed_file") -> Bed:
    """A saved bed; SceneError naming `setting` when it is unreadable or has no height metric."""
    from soil.bed import read_bed_header

    try:
        header = read_bed_header(path)
    except (OSError, ValueError) as error:
        raise SceneError([f"{setting}: {error}"]) from None
    if "height" not in header["metrics"]:
        raise SceneError(
            [f"{setting}: {path!r} has no surface height metric (save beds with soil.bed.save_bed and bed metrics)"]
        )
    return Bed(
        path,
        float(header["metrics"]["height"]),
        {
            "source": "file",
            "path": path,
            "metrics": {k: _plain(v) for k, v in header["metrics"].items()},
            "particle_count": header["particle_count"],
            "units": {
                **{f"metrics.{k}": METRIC_UNITS[k] for k in header["metrics"] if k in METRIC_UNITS},
                "particle_count": "count",
            },
        },
    )


def _plain(value):
    return value.item() if hasattr(value, "item") else value


def memory_estimate(plan: RunPlan, worlds: int = 1):
    """soil.memory.MemoryEstimate of the plan's largest soil: the settling (double precision) unless a bed
    file is given, else the run in its precision (`worlds` copies of it: replicas batched, cosim.batch);
    grains counted without allocating them. A [patch] runs on its window of the bed's packing, as many
    grains as the window's area holds at the bed's grains per area (soil.patch)."""
    from soil.bed import grain_count, read_bed_header
    from soil.memory import estimate

    if plan.bed.bed_file:
        try:
            grains = read_bed_header(plan.bed.bed_file)["particle_count"]
        except (OSError, ValueError):
            grains = 0  # an unreadable bed file is reported where it is read
    else:
        grains = grain_count(plan.bed.spec)
    running = worlds * (patch_grain_count(plan, grains) if plan.patch is not None else grains)
    run = estimate(running, plan.precision, plan.device)
    if plan.bed.bed_file:
        return run
    double = estimate(grains, "double", plan.device)
    return double if double.device_bytes >= run.device_bytes else run


def patch_grain_count(plan: RunPlan, bed_grains: int) -> int:
    """Grains in the plan's patch window [-]: the bed's `bed_grains` per bed area times the window's area."""
    spec, patch = plan.bed.spec, plan.patch
    assert patch is not None
    return math.ceil(bed_grains * (patch.length * patch.width) / (spec.length * spec.width))


def check_memory(plan: RunPlan, worlds: int = 1) -> None:
    """Refuse a scene whose soil (`worlds` copies of it with a bed file) cannot fit this machine's free
    memory (soil.memory.SoilTooLargeError)."""
    from soil.memory import check_fits

    what = f"the soil of scene {plan.name!r}" + (f" as {worlds} batched replicas" if worlds > 1 else "")
    check_fits(memory_estimate(plan, worlds), what)


def settled_bed(plan: RunPlan, folder: str, progress: bool = False, save: bool = True) -> Bed:
    """The plan's bed: its bed_file, else a cached bed in `folder` with the same key, else
    one settled now (double precision, on the plan's device) and saved there (save False: kept in memory
    only, for save_bed_cache to write once the folder's previous run, whose bed the cache holds, is gone)."""
    if plan.bed.bed_file:
        return bed_from_file(plan.bed.bed_file)
    path = os.path.join(folder, BED_FILE)
    info_path = os.path.join(folder, BED_INFO_FILE)
    if os.path.isfile(path) and os.path.isfile(info_path):
        try:
            with open(info_path) as f:
                info = json.load(f)
        except (OSError, ValueError):
            info = {}
        if info.get("key") == plan.bed.key:
            check_cached_bed(path, plan.bed.key, info)
            log.info("reusing the settled bed %s (key %s)", path, plan.bed.key)
            return Bed(path, float(info["metrics"]["height"]), {**info, "source": "cache", "path": path})
    check_memory(plan)  # studies and sweeps settle here first: refuse before allocating the grains
    return _settle(plan, path, info_path, progress, save)


def check_cached_bed(path: str, key: str, info: dict) -> None:
    """Refuse a cached bed.h5 that is not the bed bed.json describes (replaced by another scene's bed,
    damaged): DamagedFileError naming the file; a run must never go on with other grains than planned."""
    from soil.bed import read_bed_header
    from soil.errors import DamagedFileError

    header = read_bed_header(path)  # DamagedFileError when it is not a readable bed
    remedy = f"delete it and {BED_INFO_FILE} beside it to settle the bed again"
    if header["key"] and header["key"] != key:
        raise DamagedFileError(
            f"{path}: the cached bed was made for another scene (bed key {header['key']}, "
            f"{BED_INFO_FILE} and the scene say {key}); {remedy}"
        )
    expected = info.get("particle_count")
    if expected is not None and int(expected) != header["particle_count"]:
        raise DamagedFileError(
            f"{path}: the cached bed holds {header['particle_count']} grains, {BED_INFO_FILE} says {expected} "
            f"(the file was replaced); {remedy}"
        )


def settling_cost(plan: RunPlan) -> str:
    """What settling the plan's bed costs, said before it starts (a soil of tiny grains settled for an
    hour without a word under --no-progress): its DEM steps, bed.settle_max_time over its step (fixed
    steps: up to about that, the last check interval may pass it; the PID: at its first step only)."""
    bed = plan.bed
    steps = bed.settle_max_time / bed.settle_dt
    where = f"bed.settle_max_time = {bed.settle_max_time:g} s at {bed.settle_dt:.3g} s"
    if plan.step_control == "pid":
        return f"about {steps:.3g} DEM steps at the PID's first step ({where}; it takes others as it goes)"
    return f"up to about {steps:.3g} DEM steps ({where})"


def _settle_step_control(plan: RunPlan):
    """The PID controller that settles the bed (run.step_control = 'pid'), or None: fixed steps."""
    if plan.step_control != "pid":
        return None
    from soil import StepController

    return StepController(
        tolerance=plan.tolerance, dt_min=plan.dt_min, dt_max=plan.dt_max, dt_initial=plan.bed.settle_dt
    )


def _settle(plan: RunPlan, path: str, info_path: str, progress: bool, save: bool = True) -> Bed:
    from soil.bed import bed_metrics, make_settled_bed

    bed = plan.bed
    control = _settle_step_control(plan)
    log.info("settling the bed: %s", settling_cost(plan))
    bar = _SettleBar(bed.settle_max_time, progress)
    start = time.perf_counter()
    try:
        sim, report, metrics = make_settled_bed(
            bed.spec,
            plan.settle_gravity,
            device=plan.device,
            precision="double",
            dt=bed.settle_dt,
            ke_ratio=bed.settle_ke_ratio,
            max_time=bed.settle_max_time,
            progress=bar.update,
            step_control=control,
        )
    except SimulationDiverged as error:
        raise SettlingDiverged(error, plan, _keep_last_good(error, os.path.dirname(path))) from None
    finally:
        bar.close()
    wall = time.perf_counter() - start
    if not report["settled"] and not report["threshold"] > 0:  # g = 0: no weight, no threshold to fall below
        log.warning(
            "without gravity the bed has no kinetic-energy threshold to settle to (it scales with the grains' "
            "weight); it is used as it lies after bed.settle_max_time = %g s (KE %.3g J)",
            bed.settle_max_time,
            report["kinetic_energy"],
        )
    elif not report["settled"]:
        log.warning(
            "the bed did not reach the kinetic-energy threshold in bed.settle_max_time = %g s (KE %.3g J >= "
            "%.3g J); it is used as it is (raise bed.settle_max_time or bed.settle_ke_ratio)",
            bed.settle_max_time,
            report["kinetic_energy"],
            report["threshold"],
        )
    metrics = bed_metrics(sim, bed.spec)
    saved = SavedBed.from_simulation(sim, bed.spec, metrics, key=bed.key)
    info = {
        "key": bed.key,
        "report": report,
        "metrics": metrics,
        "dt": bed.settle_dt,
        "wall_time": wall,
        "particle_count": sim.particle_count,
        "units": {
            "report.time": "s",
            "report.kinetic_energy": "J",
            "report.threshold": "J",
            **{f"metrics.{name}": unit for name, unit in METRIC_UNITS.items()},
            "dt": "s",
            "wall_time": "s",
            "particle_count": "count",
        },
    }
    settled = Bed(path, float(metrics["height"]), {**info, "source": "settled", "path": path}, saved)
    if save:
        save_bed_cache(settled)
    log.info(
        "settled %d grains in %.1f s wall (%.3g s simulated); surface at z = %.4g m, packing %.3f",
        sim.particle_count,
        wall,
        report["time"],
        metrics["height"],
        metrics["packing_fraction"],
    )
    return settled


def save_bed_cache(bed: Bed) -> None:
    """Write a bed settled in this process to its cache (bed.path, bed.json beside it). The old bed.json is removed
    first: a kill between the two files leaves a bed.h5 that no bed.json describes (settled again by the next run),
    never a bed.json of one bed beside another bed's bed.h5 (refused as damaged)."""
    assert bed.settled is not None, "only a bed settled in this process is written"
    folder = os.path.dirname(bed.path)
    info_path = os.path.join(folder, BED_INFO_FILE)
    with contextlib.suppress(FileNotFoundError):
        os.remove(info_path)
    bed.settled.write(bed.path)
    write_json(info_path, {k: v for k, v in bed.info.items() if k not in ("source", "path")})
    with contextlib.suppress(FileNotFoundError):  # an earlier explosion's state describes no bed here now
        os.remove(os.path.join(folder, BED_DIVERGED_FILE))


class _SettleBar:
    """tqdm progress of the settling (simulated seconds, KE against its threshold)."""

    def __init__(self, total: float, enabled: bool):
        self.bar = None
        self._last = 0.0
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(
                total=total,
                desc="settling bed",
                unit="s",
                bar_format="{desc}: {n:.2f}/{total:.2f} s sim [{elapsed}, {postfix}]",
                leave=True,
            )

    def update(self, t, energy, threshold):
        if self.bar is not None:
            self.bar.update(t - self._last)
            self._last = t
            self.bar.set_postfix_str(f"KE/threshold {energy / max(threshold, 1e-300):.3g}")

    def close(self):
        if self.bar is not None:
            self.bar.close()
