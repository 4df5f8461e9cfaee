"""Pressure-sinkage (bevameter): square plates pushed into the bed at a constant speed; the
pressure-sinkage curves and Bekker's p = (k_c / b + k_phi) z^n fitted to them.

    bed:    the scene's [bed] (settled here, its walls smooth unless plate.wall_friction_deg,
            or bed.bed_file), one bed per replica (seed bed.seed + k), shared by the plates;
    plate:  a rigid square box of side b (each of plate.widths), centred over the bed, starts
            just above the highest grain under it and moves down at the speed v until its
            sinkage z (the bed's mean surface minus the plate's underside) reaches max_sinkage;
    read:   pressure p = F_z / b^2, F_z the grains' force on the plate (boundary wrench).

The fit (scipy.optimize.curve_fit) takes every point with z >= plate.fit_from of every
plate and replica: with two or more widths it gives k_c [N/m^(n+1)], k_phi [N/m^(n+2)] and
n; with one width only k = k_c / b + k_phi and n. Quasi-static when v / sqrt(g d) and the
inertial number (v / b) d / sqrt(p / rho) are small (docs/lab.md).
"""

from __future__ import annotations

import logging
import math
import os
import re
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from soil.bed import BedSpec, bed_metrics, build_bed, grain_count, read_bed, read_bed_header, save_bed
from soil.memory import BED_KEYS

from ..plots import save_figure
from . import common
from .scene import LabPlan, SceneError

log = logging.getLogger("cosim.lab")

RECORDS = 400
"""Samples of a pressure-sinkage curve [-]."""
UNLOAD_HOLD_STEPS = 200
UNLOAD_HOLD_TIME = 0.2
"""Before an unloading the plate stands still for the longer of UNLOAD_HOLD_STEPS DEM steps and
UNLOAD_HOLD_TIME x sqrt(d / |g|) [-]."""
UNLOAD_SPEED_FRACTION = 0.05
"""The plate rises at this fraction of its loading speed [-]: the contacts' damping force, which
flips sign with the plate's velocity, then shifts the unloading branch by a few percent of the held
pressure instead of half of it (measured on the Earth twin at v / sqrt(g d) = 0.1: 57 % at the
loading speed), and the elastic rebound spans many DEM steps."""


def widths(plan: LabPlan) -> tuple[float, ...]:
    """plate.widths, or 0.25 and 0.4 x the smaller bed side [m]."""
    given = plan.scene.plate.widths
    if given is not None:
        return tuple(sorted(given))
    side = min(plan.scene.bed.length, plan.scene.bed.width)
    return (0.25 * side, 0.4 * side)


PLATE_GRAINS_ACROSS = 8
"""Fewest grain diameters across a plate without a note (as across a wheel: cosim.advice.GRAINS_ACROSS) [-]."""


def plate_speed(plan: LabPlan) -> float:
    """plate.speed, or plate.speed_ratio (default 0.05) x sqrt(|g| d) [m/s]."""
    section = plan.scene.plate
    if section.speed is not None:
        return section.speed
    return (section.speed_ratio if section.speed_ratio is not None else 0.05) * math.sqrt(plan.g * plan.diameter)


def bed_spec(plan: LabPlan, replica: int) -> BedSpec:
    """The bed of replica k (seed bed.seed + k; smooth walls unless plate.wall_friction_deg)."""
    bed = plan.scene.bed
    seed, _ = common.replica_seeds(plan, replica)
    return BedSpec(
        length=bed.length,
        width=bed.width,
        depth=bed.depth,
        radius_mean=bed.radius_mean,
        radius_spread=bed.radius_spread,
        material=plan.soil,
        wall_material=plan.wall_material(plan.scene.plate.wall_friction_deg),
        seed=seed,
    )


def check(plan: LabPlan) -> None:
    """SceneError for plates that do not fit the bed or a bed file of another soil or gravity."""
    bed = plan.scene.bed
    d = plan.diameter
    problems = []
    side = min(bed.length, bed.width)
    for b in widths(plan):
        if b > side - 4 * d:
            problems.append(
                f"plate.widths: a {b:.4g} m plate leaves less than two grain diameters to the walls of "
                f"the {bed.length:.4g} x {bed.width:.4g} m bed (widen [bed] or narrow the plate)"
            )
        if b < 3 * d:
            problems.append(f"plate.widths: a {b:.4g} m plate is narrower than three grain diameters ({3 * d:.4g} m)")
    sinkage = plan.scene.plate.max_sinkage
    if sinkage is not None and sinkage > bed.depth - 2 * d:
        problems.append(
            f"plate.max_sinkage: ({sinkage:.4g} m) must leave two grain diameters of the bed "
            f"(bed.depth = {bed.depth:.4g} m) under the plate"
        )
    fit_from = plan.scene.plate.fit_from
    deepest = sinkage if sinkage is not None else 0.4 * bed.depth  # the default: 0.4 x the settled depth, less
    if fit_from is not None and fit_from >= deepest:  # no point to fit: Bekker's k and n were nan, exit 0
        problems.append(
            f"plate.fit_from: ({fit_from:.4g} m) must be below the deepest sinkage "
            + (
                f"plate.max_sinkage ({sinkage:.4g} m)"
                if sinkage is not None
                else f"(below 0.4 x bed.depth, {deepest:.4g} m)"
            )
        )
    path = plan.scene.resolve(bed.bed_file)
    if path is None:
        common.check_specimen_fits(plan, grain_count(bed_spec(plan, 0)), BED_KEYS)
    if path is not None:
        try:
            header = read_bed_header(path)
        except (OSError, ValueError) as error:
            problems.append(f"bed.bed_file: {error}")
        else:
            if header["materials"] and header["materials"][0] != plan.soil:
                problems.append("bed.bed_file: the bed's grains are not the scene's [soil]; the lab measures [soil]")
            if not np.allclose(header["gravity"], plan.gravity, rtol=1e-12, atol=0):
                problems.append(
                    f"bed.bed_file: settled under gravity {list(header['gravity'])} m/s^2, the scene "
                    f"has {list(plan.gravity)}"
                )
            if "height" not in header["metrics"]:
                problems.append("bed.bed_file: the bed has no surface height metric (soil.bed.save_bed with metrics)")
    if problems:
        raise SceneError(problems)


def _bed(plan: LabPlan, replica: int, path: str) -> dict:
    """Settle replica k's bed into `path` (or take bed.bed_file): its surface height [m], its
    centre (x, y) [m] and, per plate width, the top of the highest grain under the plate [m]."""
    given = plan.scene.resolve(plan.scene.bed.bed_file)
    if given is not None:
        saved = read_bed(given)
        model, state, _ = saved.builder().finalize(device=plan.device, precision=plan.precision, law=plan.law)
        saved_spec = saved.spec or {}
        centre = (
            0.5 * saved_spec.get("length", plan.scene.bed.length),
            0.5 * saved_spec.get("width", plan.scene.bed.width),
        )
        info = {
            "path": given,
            "surface": float(saved.metrics["height"]),
            "settled": True,
            "settle_time": 0.0,
            "source": "file",
        }
        positions, radii = state.position.numpy().astype(float), model.radius_numpy()
    else:
        spec = bed_spec(plan, replica)
        builder = build_bed(spec, np.asarray(plan.gravity))
        _, order_seed = common.replica_seeds(plan, replica)
        sim = common.finalize(plan, builder, order_seed)
        bed = plan.scene.bed
        threshold = common.kinetic_threshold(sim, bed.settle_ke_ratio, plan.g)
        settle_time, settled = common.run_until(
            sim,
            plan.dt,
            lambda s: common.moving_energy(s) < threshold,
            max(bed.settle_max_time, plan.max_phase_time(1.0)),
            common.chunk_steps(plan, plan.time_scale),
            5 * plan.time_scale,
        )
        metrics = bed_metrics(sim, spec)
        save_bed(path, sim, spec, metrics)
        centre = (0.5 * spec.length, 0.5 * spec.width)
        info = {
            "path": path,
            "surface": float(metrics["height"]),
            "settled": settled,
            "settle_time": settle_time,
            "packing_fraction": float(metrics["packing_fraction"]),
            "source": "settled",
        }
        positions, radii = sim.positions(), sim.radii()
    tops = {}
    for b in widths(plan):
        reach = 0.5 * b + radii
        under = (np.abs(positions[:, 0] - centre[0]) < reach) & (np.abs(positions[:, 1] - centre[1]) < reach)
        tops[str(b)] = float(np.max(positions[under, 2] + radii[under])) if under.any() else info["surface"]
    return {"replica": replica, "centre": centre, "tops": tops, **info}


def _press(
    plan: LabPlan, replica: int, path: str, surface: float, width: float, centre, top: float, unload: bool = False
) -> dict:
    """Push a plate of side `width` [m], centred at `centre` (x, y) [m], into the saved bed from
    just above `top` [m] (the highest grain under it); the pressure-sinkage curve. With `unload`, the
    plate then stands still, then rises at UNLOAD_SPEED_FRACTION of its loading speed until its
    pressure is a quarter of what it held (or it has risen half a grain diameter or half its
    sinkage): the unloading curve ('unload_sinkage' [m], 'unload_pressure' [Pa]; the held point,
    then one sample per DEM step)."""
    builder = read_bed(path).builder()
    half = 0.5 * width
    start = top + 0.1 * plan.radius_mean
    thickness = 2 * plan.diameter
    section = plan.scene.plate
    friction = section.friction_deg if section.friction_deg is not None else math.degrees(plan.soil.stick_angle)
    material = builder.add_material(plan.wall_material(friction))
    plate = builder.add_box(
        (centre[0] - half, centre[1] - half, start), (centre[0] + half, centre[1] + half, start + thickness), material
    )
    _, order_seed = common.replica_seeds(plan, replica)
    sim = common.finalize(plan, builder, order_seed)
    control = sim.control
    speed = plate_speed(plan)
    deepest = max_sinkage(plan, surface)
    duration = (start - (surface - deepest)) / speed
    control.set_boundary_velocity(plate, (0.0, 0.0, -speed))
    steps = int(math.ceil(duration / plan.dt))
    every = max(1, steps // RECORDS)
    rows = []
    for k in range(0, steps, every):
        sim.run(min(every, steps - k) * plan.dt, plan.dt)
        force = sim.boundary_wrenches()[0][plate]
        underside = start + sim.boundary_displacements()[plate, 2]
        rows.append((sim.time, surface - underside, force[2] / width**2, force[0], force[1]))
    unloading = []
    if unload:
        # held still first (the grains' damping forces of the loading die out), then raised slowly,
        # a sample every DEM step: the elastic rebound is a small fraction of the sinkage
        control.set_boundary_velocity(plate, (0.0, 0.0, 0.0))
        sim.run(max(UNLOAD_HOLD_STEPS * plan.dt, UNLOAD_HOLD_TIME * plan.time_scale), plan.dt)
        unloading.append(
            (
                surface - (start + sim.boundary_displacements()[plate, 2]),
                sim.boundary_wrenches()[0][plate][2] / width**2,
            )
        )
        control.set_boundary_velocity(plate, (0.0, 0.0, UNLOAD_SPEED_FRACTION * speed))
        for _ in range(int(math.ceil(steps / UNLOAD_SPEED_FRACTION))):
            sim.run(plan.dt, plan.dt)
            z = surface - (start + sim.boundary_displacements()[plate, 2])
            p = sim.boundary_wrenches()[0][plate][2] / width**2
            unloading.append((z, p))
            # the elastic rebound is done well within half a grain diameter of rise
            if p <= 0.25 * unloading[0][1] or z < unloading[0][0] - 0.5 * plan.diameter or z < 0.5 * deepest:
                break
    sim.check_finite()
    time, sinkage, pressure, fx, fy = (np.array(c) for c in zip(*rows))
    extra = {}
    if unload:
        extra = {
            "unload_sinkage": np.array([u[0] for u in unloading]),
            "unload_pressure": np.array([u[1] for u in unloading]),
        }
    return {
        **extra,
        "replica": replica,
        "width": width,
        "time": time,
        "sinkage": sinkage,
        "pressure": pressure,
        "side_force": np.hypot(fx, fy),
        "start_gap": start - surface,
        "speed": speed,
        "steps": int(sim.steps),
        "particles": int(sim.particle_count),
    }


def max_sinkage(plan: LabPlan, surface: float) -> float:
    """plate.max_sinkage, or 0.4 x the settled bed depth [m]."""
    given = plan.scene.plate.max_sinkage
    return given if given is not None else 0.4 * surface


def run_replica(
    plan: LabPlan,
    replica: int = 0,
    stage: str = "plate",
    bed: str = "",
    surface: float = 0.0,
    width: float = 0.0,
    centre=(0.0, 0.0),
    top: float = 0.0,
    unload: bool = False,
) -> dict:
    """One task: stage 'bed' settles replica k's bed into the file `bed`; stage 'plate' pushes a
    plate of side `width` [m] into it (surface: the bed's mean surface height [m]; centre: the
    plate's (x, y) [m]; top: the highest grain under it [m]; unload: then raise the plate, the unloading curve)."""
    if stage == "bed":
        return _bed(plan, replica, bed)
    return _press(plan, replica, bed, surface, width, centre, top, unload)


BEKKER_UNITS = {
    "k_c": "N/m^(n+1)",
    "k_c_se": "N/m^(n+1)",
    "k_phi": "N/m^(n+2)",
    "k_phi_se": "N/m^(n+2)",
    "k": "N/m^(n+2)",
    "n": "1",
    "n_se": "1",
    "r_squared": "1",
    "rms_pa": "Pa",
    "points": "count",
    "per_width": (
        "keys: plate width [m]; each that width's own log-log line, k [N/m^(n+2)] and n [1]: the fit's start "
        "guess, not the fit"
    ),
}
"""The units of bekker_fit's values (a plate test's summary.json)."""


def bekker_fit(curves: list[tuple[float, np.ndarray, np.ndarray]], fit_from: float) -> dict:
    """Bekker's p = (k_c / b + k_phi) z^n fitted to pressure-sinkage curves (b [m], z [m], p [Pa]).

    Points with z >= fit_from [m] and p > 0 count. Two or more widths: k_c [N/m^(n+1)], k_phi
    [N/m^(n+2)], n and their standard errors (scipy.optimize.curve_fit, started from a
    log-log regression per width); one width: k = k_c / b + k_phi [N/m^(n+2)] and n. Also
    r_squared and the rms residual [Pa] over the points fitted, and k, n per width.
    """
    from scipy import optimize, stats

    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    per_width: dict[float, dict] = {}
    for width, sinkage, pressure in curves:
        use = (np.asarray(sinkage) >= fit_from) & (np.asarray(pressure) > 0)
        parts.append((np.full(use.sum(), width), np.asarray(sinkage)[use], np.asarray(pressure)[use]))
    b, z, p = (np.concatenate([part[i] for part in parts]) for i in range(3))
    result = {
        "points": int(len(z)),
        "k_c": math.nan,
        "k_phi": math.nan,
        "k": math.nan,
        "n": math.nan,
        "k_c_se": math.nan,
        "k_phi_se": math.nan,
        "n_se": math.nan,
        "r_squared": math.nan,
        "rms_pa": math.nan,
        "per_width": per_width,
    }
    for width in np.unique(b):
        mine = b == width
        if mine.sum() >= 3:
            line = stats.linregress(np.log(z[mine]), np.log(p[mine]))
            per_width[float(width)] = {"k": float(math.exp(line.intercept)), "n": float(line.slope)}
    if len(per_width) == 0 or len(z) < 4:
        return result
    n0 = float(np.mean([w["n"] for w in per_width.values()]))
    if len(per_width) >= 2:
        inverse = np.array([1 / w for w in per_width])
        ks = np.array([w["k"] for w in per_width.values()])
        slope, intercept = np.polyfit(inverse, ks, 1)

        model: Callable[..., Any] = _bekker_widths
        start = [slope, intercept, n0]
    else:
        model = _bekker_one_width
        start = [next(iter(per_width.values()))["k"], n0]
    try:
        values, covariance = optimize.curve_fit(model, (z, b), p, p0=start, maxfev=20000)
    except (RuntimeError, optimize.OptimizeWarning) as error:
        log.warning("the Bekker fit did not converge: %s", error)
        return result
    errors = np.sqrt(np.diag(covariance)) if np.all(np.isfinite(covariance)) else np.full(len(values), math.nan)
    fitted = model((z, b), *values)
    residual = p - fitted
    result.update(
        r_squared=float(1 - np.sum(residual**2) / np.sum((p - p.mean()) ** 2)),
        rms_pa=float(np.sqrt(np.mean(residual**2))),
    )
    if len(values) == 3:
        result.update(
            k_c=float(values[0]),
            k_phi=float(values[1]),
            n=float(values[2]),
            k_c_se=float(errors[0]),
            k_phi_se=float(errors[1]),
            n_se=float(errors[2]),
        )
    else:
        result.update(k=float(values[0]), n=float(values[1]), n_se=float(errors[1]))
    return result


def _bekker_widths(x, k_c, k_phi, n):
    """p = (k_c / b + k_phi) z^n for x = (z, b)."""
    return (k_c / x[1] + k_phi) * x[0] ** n


def _bekker_one_width(x, k, n):
    """p = k z^n for x = (z, b)."""
    return k * x[0] ** n


def bekker_pressure(fit: dict, width: float, sinkage) -> np.ndarray:
    """The fitted Bekker pressure [Pa] of a plate of side `width` [m] at `sinkage` [m]."""
    k = fit["k"] if math.isnan(fit["k_c"]) else fit["k_c"] / width + fit["k_phi"]
    return k * np.maximum(np.asarray(sinkage, dtype=float), 0.0) ** fit["n"]


def quasi_static_numbers(
    plan: LabPlan,
    speed: float,
    curves: Sequence[tuple[float, np.ndarray, np.ndarray]],
    largest_pressure: float,
    fit: dict,
    fit_from: float,
) -> list[dict]:
    """The dimensionless numbers of a plate test (docs/lab.md). The inertial number (v / b) d / sqrt(p / rho)
    is largest where the pressure is lowest over the points the fit uses (z >= fit_from, p > 0: each
    plate's `curves` (width [m], sinkage [m], pressure [Pa])): the fitted Bekker pressure at the
    shallowest and the deepest of them (the lower of the two: n < 0 turns it round), or, where the fit
    gives none above 0 there, the lowest pressure measured among them; the largest over the plates. A
    failed fit (k or n nan) takes the lowest pressure measured there too."""
    inertial, how = 0.0, "fitted"
    for width, sinkage, pressure in curves:
        z, p = np.asarray(sinkage, dtype=float), np.asarray(pressure, dtype=float)
        used = (z >= fit_from) & (p > 0)
        if not used.any():
            continue
        ends = [float(bekker_pressure(fit, width, z[used].min())), float(bekker_pressure(fit, width, z[used].max()))]
        lowest = min(ends)
        if not (math.isfinite(lowest) and lowest > 0):
            lowest, how = float(p[used].min()), "measured"
        inertial = max(inertial, speed / width * plan.diameter / math.sqrt(lowest / plan.soil.density))
    where = (
        "at the lowest pressure the fit uses (the fitted Bekker pressure at its shallowest or deepest point)"
        if how == "fitted"
        else "at the lowest pressure measured among the points the fit uses (the fit gives none there)"
    )
    return [
        common.quasi_static(
            "plate speed v / sqrt(g d)",
            speed / math.sqrt(plan.g * plan.diameter),
            0.1,
            "slow against the grains' own fall speed over one diameter",
        ),
        common.quasi_static(
            "inertial number I",
            inertial,
            1e-3,
            f"(v / b) d / sqrt(p / rho) {where}: quasi-static flow under the plate",
        ),
        common.stiffness_number(plan, largest_pressure),
    ]


def press_plates(
    plan: LabPlan,
    out_dir: str,
    sides: Sequence[float],
    replicas: int,
    executor: str = "serial",
    scheduler: str | None = None,
    workers: int | None = None,
    unload: bool = False,
) -> tuple[list[dict], list[dict], list[dict], KeyboardInterrupt | None]:
    """Settle `replicas` beds (into out_dir/beds) and push every plate width of `sides` [m] into each
    (through cosim.study.Executor); with `unload`, each plate is then held and raised (the unloading
    branch). Returns (the settled beds, the plates' results, the failed tasks of either stage, and the
    Ctrl-C or SIGTERM that stopped the plates after some had finished: raise it once they are reported)."""
    folder = os.path.join(out_dir, "beds")
    os.makedirs(folder, exist_ok=True)
    # every bed is settled again here: one of an earlier test with more replicas (kept by --overwrite, as a
    # study's cached beds are) would read as this test's
    for name in os.listdir(folder):
        match = re.fullmatch(r"replica_(\d+)\.h5", name)
        if match and int(match[1]) >= replicas:
            os.remove(os.path.join(folder, name))
    beds = common.map_tasks(
        plan,
        run_replica,
        [{"replica": k, "stage": "bed", "bed": os.path.join(folder, f"replica_{k}.h5")} for k in range(replicas)],
        [f"bed {k}" for k in range(replicas)],
        executor,
        scheduler,
        workers,
    )
    ready = common.successful(beds, "plate bed")
    jobs = [
        {
            "replica": bed["replica"],
            "stage": "plate",
            "bed": bed["path"],
            "surface": bed["surface"],
            "width": b,
            "centre": bed["centre"],
            "top": bed["tops"][str(b)],
            **({"unload": True} if unload else {}),
        }
        for bed in ready
        for b in sides
    ]
    labels = [f"replica {j['replica']}, plate {j['width']:.3g} m" for j in jobs]
    results, stopped = common.map_until_stopped(plan, run_replica, jobs, labels, executor, scheduler, workers)
    failed = [r for r in beds + results if not r.get("ok")]
    return ready, common.successful(results, "plate"), failed, stopped


def plate_notes(
    plan: LabPlan, ready: list[dict], done: list[dict], total: int, stopped: KeyboardInterrupt | None, surface: float
) -> list[str]:
    """The report's notes on what limits a plate test: beds not settled, walls near a plate, plates only a
    few grains wide, an interruption, a floor near the deepest plate. A plate note names only plates that
    pushed (`done`, each with its `width` [m]): an interrupted test's other plates never ran."""
    notes = [f"bed {bed['replica']}: not settled within the time limit" for bed in ready if not bed["settled"]]
    pushed = sorted({float(r["width"]) for r in done})
    side = min(plan.scene.bed.length, plan.scene.bed.width)
    notes += [
        f"plate {b:.3g} m: the walls are {(side - b) / 2:.3g} m from its edge, less than its width; the walls "
        "may carry part of the load (a wider bed)"
        for b in pushed
        if (side - b) / 2 < b
    ]
    notes += [  # measured: plates of 3 and 4 diameters fit with R^2 0.29-0.76 (tests/test_lab.py)
        f"plate {b:.3g} m is {b / plan.diameter:.3g} grain diameters wide, under {PLATE_GRAINS_ACROSS}: its "
        "curve jumps as single grains under it give way, and the fit follows their trend (wider plates, or "
        "replicas, average over more grains)"
        for b in pushed
        if b < PLATE_GRAINS_ACROSS * plan.diameter
    ]
    notes += common.interrupted_notes(stopped, len(done), total, "plate tests")
    if surface - max_sinkage(plan, surface) < 3 * plan.diameter:
        notes.append("the plate ends less than three grain diameters above the floor: the floor stiffens the curve")
    return notes


def plate_test(
    plan: LabPlan,
    out_dir: str,
    overwrite: bool = False,
    executor: str = "serial",
    scheduler: str | None = None,
    workers: int | None = None,
) -> dict:
    """Settle lab.replicas beds, push every plate into each (through cosim.study.Executor), fit
    Bekker and write the report into out_dir (plate.csv, summary.json, plate.png)."""
    check(plan)
    with common.prepare_folder(plan, out_dir, overwrite, executor, scheduler):
        sides = widths(plan)
        replicas = plan.scene.lab.replicas if plan.scene.bed.bed_file is None else 1
        speed = plate_speed(plan)
        log.info(
            "plate: widths %s m at %.3g m/s into a %.3g x %.3g m bed; %d replica(s)",
            ", ".join(f"{b:.3g}" for b in sides),
            speed,
            plan.scene.bed.length,
            plan.scene.bed.width,
            replicas,
        )
        ready, done, failed, stopped = press_plates(plan, out_dir, sides, replicas, executor, scheduler, workers)
        fit_from = plan.scene.plate.fit_from if plan.scene.plate.fit_from is not None else 0.25 * plan.diameter
        fit = bekker_fit([(r["width"], r["sinkage"], r["pressure"]) for r in done], fit_from)
        largest = max(float(np.max(r["pressure"])) for r in done)
        curves = [(r["width"], r["sinkage"], r["pressure"]) for r in done]
        numbers = quasi_static_numbers(plan, speed, curves, largest, fit, fit_from)
        surface = float(np.mean([bed["surface"] for bed in ready]))
        notes = plate_notes(plan, ready, done, replicas * len(sides), stopped, surface)
        summary = {
            "test": "plate",
            "name": plan.name,
            "gravity": plan.g,
            "units": {  # the other numbers: counts, or a unit in their key
                "gravity": "m/s^2",
                **{f"bekker.{k}": u for k, u in BEKKER_UNITS.items()},
                "beds.surface": "m",
                "beds.settle_time": "s",
            },
            "soil": common.soil_summary(plan),
            "bekker": fit,
            "curves": [
                {
                    "replica": r["replica"],
                    "width_m": r["width"],
                    "max_sinkage_m": float(r["sinkage"].max()),
                    "max_pressure_pa": float(r["pressure"].max()),
                    "steps": r["steps"],
                }
                for r in done
            ],
            "beds": [{k: bed[k] for k in ("replica", "surface", "settled", "settle_time", "source")} for bed in ready],
            "failed": [{"label": r.get("label"), "error": r.get("error")} for r in failed],
            "geometry": {
                "widths_m": list(sides),
                "speed_m_s": speed,
                "max_sinkage_m": max_sinkage(plan, surface),
                "surface_m": surface,
                "bed_length_m": plan.scene.bed.length,
                "bed_width_m": plan.scene.bed.width,
                "fit_from_m": fit_from,
                "grain_diameter_m": plan.diameter,
                "dt_s": plan.dt,
            },
            "quasi_static": numbers,
            "notes": notes,
        }
        rows = [
            (r["replica"], r["width"], t, z, p, f)
            for r in done
            for t, z, p, f in zip(r["time"], r["sinkage"], r["pressure"], r["side_force"])
        ]
        names = [
            ("replica", "1"),
            ("plate_width", "m"),
            ("time", "s"),
            ("sinkage", "m"),
            ("pressure", "Pa"),
            ("side_force", "N"),
        ]
        common.write_csv(
            os.path.join(out_dir, "plate.csv"),
            [(n, unit, [row[i] for row in rows]) for i, (n, unit) in enumerate(names)],
        )
        summary["figure"] = _figure(out_dir, done, fit, fit_from)
        common.write_summary(out_dir, summary)
        if stopped is not None:  # the finished tests' report is written: now stop as asked
            raise stopped
        return summary


def _figure(out_dir: str, done: list[dict], fit: dict, fit_from: float) -> str | None:
    plt = common.pyplot()
    if plt is None:
        return None
    fig, (linear, logarithmic) = plt.subplots(1, 2, figsize=(12, 4.5))
    sides = sorted({r["width"] for r in done})
    colours = {b: plt.cm.tab10(i % 10) for i, b in enumerate(sides)}
    for r in done:
        label = f"b = {r['width'] * 1e3:.3g} mm" if r["replica"] == done[0]["replica"] else None
        for ax in (linear, logarithmic):
            ax.plot(r["sinkage"] * 1e3, r["pressure"], ".", ms=2, color=colours[r["width"]], label=label)
    if np.isfinite(fit["n"]):
        for b in sides:
            z = np.linspace(fit_from, max(r["sinkage"].max() for r in done), 100)
            for ax in (linear, logarithmic):
                ax.plot(z * 1e3, bekker_pressure(fit, b, z), "-", color=colours[b])
    if math.isnan(fit["k_c"]):
        title = f"Bekker: k = {fit['k']:.3g} N/m^(n+2), n = {fit['n']:.3g}"
    else:
        title = f"Bekker: k_c = {fit['k_c']:.3g}, k_phi = {fit['k_phi']:.3g}, n = {fit['n']:.3g}"
    linear.set_title(title + f" (R^2 {fit['r_squared']:.3f})", fontsize=9)
    for ax in (linear, logarithmic):
        ax.set_xlabel("sinkage [mm]")
        ax.set_ylabel("pressure [Pa]")
    logarithmic.set_xscale("log")
    logarithmic.set_yscale("log")
    logarithmic.set_xlim(left=max(fit_from * 1e3 * 0.5, 1e-3))
    linear.legend(fontsize=8)
    fig.tight_layout()
    path = os.path.join(out_dir, "plate.png")
    save_figure(fig, path, 120)
    plt.close(fig)
    return path
