"""SCM parameters fitted to the DEM's own single-wheel runs (`cosim calibrate-scm --from-wheel`).

    folder = run_wheel_tests(plan, folder, slips=(0.05, 0.1, 0.2, 0.4, 0.6), replicas=3)  # over 3 beds
    parameters, errors, report = fit_to_wheel(plan, wheel_targets(folder), start=lab_calibration.parameters, runs=runs)
    beds = fit_beds(plan, bed_wheel_targets(folder), [{**parameters, **held_k} ...], runs)  # each bed alone

The DEM gives, at each imposed slip s, the steady-state sinkage z(s), drawbar pull DP(s) and
driving torque T(s) of the scene's wheel under its load W, and the sinkage z_L of the landed wheel
at rest before the drive (`cosim study slip`: replicas, means and 95 % intervals). scipy's
least_squares moves the parameters the wheel runs determine (FITTED: k_phi, n, phi, K) from the
lab's values (the virtual plate and shear tests, cosim.lab.scm) and holds the rest (k_c: one wheel
width cannot separate it from k_phi; c and K_e), in two stages:

1. the held wheel (fast, milliseconds per slip): the SCM wheel held at the DEM's sinkage and
   driven at the DEM's speeds over fresh soil (soil.scm.ScmTerrain, the run's grid and damping)
   must carry W, pull DP and need T, and at rest at z_L it must carry W (a soil that carries W
   at rest at z_L lands there, as the DEM's wheel did);
2. with a folder `runs`, the SCM runs of the DEM's own protocol (scm_free_runs: the scene on SCM,
   landing and then the drive for the DEM's duration, one run per slip, seconds each): their
   z, DP and T must be the DEM's. The held wheel of stage 1 rolls on fresh soil; the runs drive
   from their landing rut and travel less than a contact length in the DEM's 10 s, which stage 1
   does not see (at slip 0.4 its DP/W is 0.15 where the run's is 0.05).

Each residual is in units of the trade's agreement (benchmarks/scm_trade.py): the larger of the
DEM's 95 % half-interval and RELATIVE_TOLERANCE of the DEM's value (the held wheel's W:
RELATIVE_TOLERANCE of W), so a residual under one is a slip where SCM agrees. The standard errors
are the square roots of the diagonal of (J^T J)^-1 times the residuals' variance (J in the fitted
coordinates) of the last stage.

Over beds (a study made with `--vary-bed`, as run_wheel_tests makes it), the fit to the beds' means
is then repeated on each bed's own runs (fit_beds, from the means' fit, bed k holding its own lab
values where the lab file fitted each bed): the beds' fits give the fitted keys the scatter between
beds, kept whole per bed (k_phi and n move together), so `cosim run --replicas K --vary-bed` gives
a wheel-fitted SCM scene its error bar as it does a lab-fitted one.
"""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import asdict, dataclass, replace

import numpy as np

from soil.errors import DamagedFileError

from ..metrics import SUMMARY_RULE, summary_is_current
from ..scm_calibration import SOIL_KEYS
from .common import LabFailed

RELATIVE_TOLERANCE = 0.15
"""The relative difference from the DEM that counts as agreement (with its 95 % interval) [-]; the
trade (benchmarks/scm_trade.py) counts with it too."""

MISSING_RESIDUAL = 10.0
"""The residual of a quantity an SCM run gave no value of (no landing, airborne) [tolerances]."""

MAX_FRICTION_ANGLE_DEG = 80.0
"""The fit's upper bound on phi [deg]: the wheel fits take phi far above a soil's (tan phi and K act
together on the shear of a wheel's short drive), a response, not a measurement of the soil."""

FREE_STEP = 0.05
"""The forward-difference step of the fit to the runs, in the fit's coordinates (log k_phi, n, tan phi,
log K) [-]."""

FITTED = ("k_phi", "n", "friction_angle_deg", "janosi_k")
"""The SCM parameters the wheel runs move (the others keep the lab's values)."""


@dataclass(frozen=True)
class WheelTarget:
    """The DEM's steady state at one imposed slip (means and 95 % half-intervals over replicas; SI)."""

    slip: float
    sinkage: float
    sinkage_ci95: float
    drawbar_pull: float
    drawbar_pull_ci95: float
    driving_torque: float
    driving_torque_ci95: float
    replicas: int
    vertical_force: float
    """The soil's vertical push on the wheel [N]: its load in a steady state (the carriage's weight)."""
    landing_sinkage: float = math.nan
    """The rim's sinkage as the drive starts [m] (the landed wheel's, at rest under its load; nan: not
    recorded)."""
    landing_sinkage_ci95: float = math.nan
    duration: float = math.nan
    """The DEM runs' driving time after landing [s] (their run.duration; nan: not recorded)."""


def run_wheel_tests(plan, out_dir: str, slips, replicas: int, executor=None, scheduler=None, workers=None) -> str:
    """The DEM single-wheel runs of a testbed plan at each slip (cosim.study.slip_study) into out_dir,
    replica k on a bed of its own (bed.seed + k; one bed's summation orders miss the scatter between
    beds; a scene on a bed file has one bed); returns out_dir (its study.json holds the results).
    executor None: as worlds of one simulation where the study batches by itself (a GPU), else serially."""
    from ..study import batched_by_default, slip_study

    if executor is None:
        executor = "dask" if batched_by_default(plan) else "serial"  # "dask" is no executor asked for

    vary = "bed" if replicas >= 2 and not plan.bed.bed_file else "order"
    slip_study(plan, out_dir, slips, replicas, executor, scheduler, workers, overwrite=True, plot=False, vary=vary)
    return out_dir


def _read_study(study_folder: str) -> tuple[str, dict]:
    """(path, content) of a slip study's study.json; DamagedFileError names the file when it is not one."""
    path = os.path.join(study_folder, "study.json")
    try:
        with open(path) as f:
            study = json.load(f)
    except (OSError, json.JSONDecodeError) as error:
        raise DamagedFileError(f"{path}: not a readable slip study ({error})") from error
    if not isinstance(study, dict) or study.get("kind") != "slip":
        kind = study.get("kind") if isinstance(study, dict) else None
        raise DamagedFileError(f"{path}: a {kind!r} study, --wheel-runs needs a slip study (cosim study slip)")
    load = study.get("wheel_load")
    if not (isinstance(load, (int, float)) and load > 0):
        raise DamagedFileError(f"{path}: no wheel_load > 0 [N]; the wheel fit needs the wheel's load")
    problem = _study_shape_problem(study)
    if problem:
        raise DamagedFileError(f"{path}: not a slip study's table: {problem} (cosim study slip writes it)")
    if not summary_is_current(study):  # its rows' means are of another window than the fit's own SCM runs
        from soil.errors import ArgumentError

        raise ArgumentError(
            f"{path}: a table of runs summarized under an older steady-window rule than this code's "
            f"(summary_rule {study.get('summary_rule', 'none')}, this code's {SUMMARY_RULE}: the window starts once "
            "the sinkage has settled too); `cosim resume` the study (or each of its runs, then tabulate them "
            "again with --from-runs) to make its table again"
        )
    return path, study


def check_study_scene(study_folder: str, plan) -> None:
    """Refuse a slip study whose runs were another wheel, wheel load or gravity than the RunPlan `plan`'s
    (ArgumentError naming --wheel-runs and its study.json): its targets would be fitted as this wheel's,
    the fit then quietly far off (a drawbar pull divided by another load)."""
    from soil.errors import ArgumentError
    from soil.gravity import gravity_vector

    from ..scene import SceneError, scene_from_text

    path, study = _read_study(study_folder)
    differ = []
    wheel_named = False  # the scene's [wheel] keys already differ (a mesh's scale among them)
    if not math.isclose(float(study["wheel_load"]), plan.wheel_load, rel_tol=1e-9):
        differ.append(f"a wheel load of {study['wheel_load']:.6g} N (the scene's {plan.wheel_load:.6g} N)")
    text = study.get("scene_toml")
    if isinstance(text, str):
        try:
            scene = scene_from_text(text)
        except SceneError as error:
            raise DamagedFileError(f"{path}: its scene_toml is no scene this version reads ({error})") from None
        gravity = gravity_vector(scene.scene.gravity)
        if not np.allclose(gravity, plan.gravity, rtol=1e-9, atol=0):
            differ.append(f"gravity {gravity.tolist()} m/s^2 (the scene's {np.asarray(plan.gravity).tolist()})")
        # the wheel (a mesh's file aside: its digest is compared below, the path may have moved or been
        # overwritten), its spin (the fit drives the scene's), and the soil's grains
        for section in ("wheel", "soil"):
            theirs, own = (getattr(s, section).model_dump(exclude={"file"}) for s in (scene, plan.scene))
            changed = sorted(k for k in own if theirs.get(k) != own[k])
            if changed:
                differ.append(f"another {section} ({section}.{f', {section}.'.join(changed)})")
                wheel_named = wheel_named or section == "wheel"
        if (
            scene.testbed is not None
            and plan.scene.testbed is not None
            and scene.testbed.omega != plan.scene.testbed.omega
        ):
            differ.append(f"testbed.omega = {scene.testbed.omega!r} rad/s (the scene's {plan.scene.testbed.omega!r})")
    from ..scm_calibration import is_mesh_digest, wheel_record

    theirs_wheel, own_wheel = study.get("wheel"), wheel_record(plan.wheel)
    # a mesh by its digest: its file's path names where it was, not what it held; a study written before
    # the wheel was recorded is not judged on it
    if theirs_wheel is not None and not (
        isinstance(theirs_wheel, dict)
        and (theirs_wheel.get("type") != "mesh" or is_mesh_digest(theirs_wheel.get("mesh_sha256")))
    ):
        raise DamagedFileError(
            f"{path}: its wheel is no wheel record (a mesh's with its mesh_sha256): {theirs_wheel!r:.80}"
        )
    recorded = theirs_wheel or {}
    mesh = own_wheel["type"] == "mesh" == recorded.get("type")
    if mesh and recorded["mesh_sha256"] != own_wheel["mesh_sha256"] and not wheel_named:
        differ.append("another mesh (wheel.file: its scaled vertices and triangles differ from the scene's)")
    if differ:
        raise ArgumentError(
            f"--wheel-runs {path}: the slip study ran {'; '.join(differ)}: its runs are not this scene's wheel; "
            "run `cosim study slip SCENE` on this scene, or give the scene the study ran"
        )


def _study_shape_problem(study: dict) -> str | None:
    """What in a slip study's content the wheel fit cannot read (None: it reads it): rows and runs lists
    of objects, the rows' slip_set numbers and averaged / steady counts, averaged_states a list of names."""
    from ..scene import is_number

    for key in ("rows", "runs"):
        if not isinstance(study.get(key, []), list) or not all(isinstance(r, dict) for r in study.get(key, [])):
            return f"{key!r} must be a list of objects"
    for k, row in enumerate(study.get("rows", [])):
        if not is_number(row.get("slip_set")):
            return f"rows[{k}].slip_set must be a number, got {row.get('slip_set')!r:.60}"
        for count in ("averaged", "steady"):
            if count in row and not (isinstance(row[count], int) and not isinstance(row[count], bool)):
                return f"rows[{k}].{count} must be a count, got {row[count]!r:.60}"
    states = study.get("averaged_states")
    if states is not None and not (isinstance(states, list) and all(isinstance(x, str) for x in states)):
        return f"'averaged_states' must be a list of names, got {states!r:.60}"
    return None


def _averaged_rows(study: dict) -> list[dict]:
    """The rows of a slip study with at least one run averaged (steady, or still sinking or rising in a
    table made with --include-sinking)."""
    return [row for row in study.get("rows", []) if int(row.get("averaged", row.get("steady", 0)))]


def wheel_targets(study_folder: str) -> list[WheelTarget]:
    """The WheelTargets of a slip study's folder (its study.json; cosim study slip), slips with at
    least one steady replica; LabFailed names the file when there are none."""
    return _study_targets(*_read_study(study_folder))


def _study_targets(path: str, study: dict) -> list[WheelTarget]:
    """wheel_targets of a study already read (path: its study.json, for the errors)."""
    load = study["wheel_load"]
    duration = math.nan
    if isinstance(study.get("scene_toml"), str):
        from ..scene import scene_from_text

        duration = float(scene_from_text(study["scene_toml"]).run.duration)
    targets = []
    for row in _averaged_rows(study):
        averaged = int(row.get("averaged", row.get("steady", 0)))  # a table --include-sinking averaged

        def value(name: str, key: str = "mean", row=row) -> float:
            number = row.get(f"{name}_{key}")
            return float(number) if isinstance(number, (int, float)) and math.isfinite(number) else 0.0

        targets.append(
            WheelTarget(
                slip=value("slip"),
                sinkage=value("sinkage"),
                sinkage_ci95=value("sinkage", "ci95"),
                drawbar_pull=value("drawbar_pull"),
                drawbar_pull_ci95=value("drawbar_pull", "ci95"),
                driving_torque=value("driving_torque"),
                driving_torque_ci95=value("driving_torque", "ci95"),
                replicas=averaged,
                vertical_force=float(load),
                landing_sinkage=value("landing_sinkage") or math.nan,
                landing_sinkage_ci95=value("landing_sinkage", "ci95") or math.nan,
                duration=duration,
            )
        )
    if len(targets) < 2:
        raise LabFailed(f"{path}: {len(targets)} slips reached a steady state; the wheel fit needs two or more")
    return targets


def bed_wheel_targets(study_folder: str) -> list[list[WheelTarget]]:
    """Each bed's own WheelTargets of a slip study over beds (`cosim study slip --vary-bed`: replica k on
    bed k at every slip), in bed order: at each slip of wheel_targets, the one run on that bed, with
    the study's 95 % half-intervals over the beds as its residual units (a bed's fit is judged by the
    same yardstick as the fit to the beds' means). [] when the study's replicas did not vary beds or
    it has fewer than two beds; a bed with fewer than two slips averaged gets [] (its fit is left out).
    """
    path, study = _read_study(study_folder)
    pooled = _study_targets(path, study)
    if study.get("vary") != "bed":
        return []
    states = set(study.get("averaged_states") or ["steady"])
    runs: dict[tuple[str, int], dict] = {}  # (slip folder, replica) -> the run's summary
    for run in study.get("runs", []):
        summary = run.get("summary") if isinstance(run, dict) else None
        folder = str(run.get("out_dir", "")) if isinstance(run, dict) else ""
        name = os.path.basename(os.path.normpath(folder))
        if not (isinstance(summary, dict) and name.startswith("replica_") and run.get("ok")):
            continue
        if summary.get("steady_state") not in states:
            continue
        try:
            replica = int(name[len("replica_") :])
        except ValueError:
            raise DamagedFileError(f"{path}: run folder {folder!r} is not slip_S/replica_K") from None
        runs[(os.path.basename(os.path.dirname(os.path.normpath(folder))), replica)] = summary
    beds = sorted({replica for _, replica in runs})
    if len(beds) < 2:
        return []
    rows = _averaged_rows(study)

    def number(summary: dict, key: str) -> float:
        value = summary.get(key)
        return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else math.nan

    out = []
    for bed in range(max(beds) + 1):
        targets = []
        for row, target in zip(rows, pooled):
            summary = runs.get((f"slip_{float(row['slip_set']):+.3f}", bed))
            if summary is None:
                continue
            values = {k: number(summary, k) for k in ("sinkage", "drawbar_pull", "driving_torque", "landing_sinkage")}
            if not all(math.isfinite(values[k]) for k in ("sinkage", "drawbar_pull", "driving_torque")):
                continue
            targets.append(
                replace(
                    target,
                    sinkage=values["sinkage"],
                    drawbar_pull=values["drawbar_pull"],
                    driving_torque=values["driving_torque"],
                    landing_sinkage=values["landing_sinkage"],
                    replicas=1,
                )
            )
        out.append(targets if len(targets) >= 2 else [])
    return out


def _wheel_terrain(plan, soil: dict):
    """Fresh SCM soil `soil` round the plan's one wheel (soil.scm.ScmTerrain, double, on the CPU) and
    its node spacing [m]: a window of 4 outer radii round the wheel (the nodes under it are the
    run's: the lattice is fixed in the world), three times fewer to step than the run's window."""
    from soil.scm import ScmTerrain

    from ..scm_soil import scm_settings

    wheel = plan.wheel
    window = {"window_length": 4.0 * wheel.outer_radius, "window_width": wheel.width + 2.0 * wheel.outer_radius}
    base = scm_settings(plan, [0], 0.0, {**window, **soil})
    terrain = ScmTerrain(base.parameters, [wheel.shape], window=base.window, device="cpu", precision="double")
    return terrain, base.parameters.node_spacing


def landing_sinkage(targets: list[WheelTarget]) -> float | None:
    """The DEM's landing sinkage [m]: the replica-weighted mean over the targets that record it (None
    when none does: a study from before it was recorded)."""
    known = [t for t in targets if math.isfinite(t.landing_sinkage) and t.landing_sinkage > 0]
    if not known:
        return None
    return sum(t.landing_sinkage * t.replicas for t in known) / sum(t.replicas for t in known)


def scm_wheel_forces(plan, soil: dict, sinkage: float, slip: float) -> tuple[float, float, float]:
    """(vertical force W [N], drawbar pull DP [N], driving torque T [N m]) of the plan's wheel held with
    its rim `sinkage` [m] below the SCM surface and driven at the plan's spin and `slip` over fresh
    soil: the means over two grouser pitches after one and a half contact lengths of travel."""
    from ..scm_soil import STEPS_PER_NODE

    wheel = plan.wheel
    rim = wheel.rim_radius
    omega = plan.drive_omega
    speed = omega * rim * (1.0 - slip)
    terrain, spacing = _wheel_terrain(plan, soil)
    step = spacing / (STEPS_PER_NODE * omega * wheel.outer_radius)  # the fastest surface speed: the tips
    contact = 2.0 * math.sqrt(max(2.0 * rim * sinkage, spacing**2))
    pitch = 2.0 * math.pi * wheel.outer_radius / max(1, getattr(wheel.shape, "grouser_count", 0) or 1)
    start = (1.5 * contact + spacing) / speed  # every node under the wheel came in through its front
    terrain.advance(
        start,
        step,
        [[0.0, 0.0, rim - sinkage]],
        [[1.0, 0.0, 0.0, 0.0]],
        [[speed, 0.0, 0.0]],
        [[0.0, omega, 0.0]],
    )
    terrain.advance(start + 2.0 * pitch / (omega * rim), step)
    mean = terrain.wheel_contact(mean=True)
    return float(mean.force[0, 2]), float(mean.force[0, 0]), float(-mean.torque[0, 1])


def scm_static_force(plan, soil: dict, sinkage: float) -> float:
    """The vertical force [N] of the plan's wheel at rest, as it lands (not turned, grousers where the
    run starts them), pressed with its rim `sinkage` [m] into fresh SCM soil: the soil's plastic
    pressure over the whole footprint, front and rear."""
    from ..scm_soil import STEPS_PER_NODE

    terrain, spacing = _wheel_terrain(plan, soil)
    step = spacing / (STEPS_PER_NODE * plan.drive_omega * plan.wheel.outer_radius)  # any step: at rest
    zero = [[0.0, 0.0, 0.0]]
    terrain.advance(2.0 * step, step, [[0.0, 0.0, plan.wheel.rim_radius - sinkage]], [[1.0, 0.0, 0.0, 0.0]], zero, zero)
    return float(terrain.wheel_contact().force[0, 2])


def scm_free_runs(plan, soil: dict, targets: list[WheelTarget], folder: str) -> list[dict]:
    """The plan's own run on SCM soil `soil` at each target's slip (landing, then the drive for the DEM
    runs' duration; cosim.launch.run_plan into folder/slip_S, replaced each time): the runs the trade
    compares with the DEM. Returns each run's summary (sinkage, drawbar_pull, driving_torque, ...)."""
    from ..launch import run_plan

    terrain = {f"terrain.{k}": float(v) for k, v in soil.items()}
    summaries = []
    runs_log = logging.getLogger("cosim")
    level = runs_log.level
    runs_log.setLevel(logging.ERROR)  # each run's progress lines and findings: in its run.json
    try:
        for t in targets:
            changes = {"terrain.model": "scm", **terrain, "testbed.mode": "slip", "testbed.slip": t.slip}
            if math.isfinite(t.duration):
                changes["run.duration"] = t.duration
            folder_t = os.path.join(folder, f"slip_{t.slip:+.3f}")
            summaries.append(run_plan(plan.with_changes(**changes), folder_t, overwrite=True).summary)
    finally:
        runs_log.setLevel(level)
    return summaries


def _to_coordinates(values: dict) -> np.ndarray:
    """The fit's coordinates: log k_phi, n, tan(phi), log K (each of order one and unbounded in sign where
    the parameter is positive)."""
    return np.array(
        [
            math.log(values["k_phi"]),
            values["n"],
            math.tan(math.radians(values["friction_angle_deg"])),
            math.log(values["janosi_k"]),
        ]
    )


def _from_coordinates(x: np.ndarray) -> dict:
    return {
        "k_phi": math.exp(x[0]),
        "n": float(x[1]),
        "friction_angle_deg": math.degrees(math.atan(x[2])),
        "janosi_k": math.exp(x[3]),
    }


def fit_to_wheel(
    plan,
    targets: list[WheelTarget],
    start: dict,
    max_evaluations: int = 80,
    runs: str | None = None,
    max_runs: int = 30,
):
    """SCM parameters (SOIL_KEYS) fitted to the DEM wheel `targets`, moving FITTED from the values in
    `start` (a calibration's parameters) and holding the rest: first to the held wheel's forces
    (scm_wheel_forces, scm_static_force: at most max_evaluations), then, with a folder `runs`, to the
    SCM runs of the DEM's own protocol (scm_free_runs: at most max_runs evaluations of one run per
    slip). Returns (parameters, standard errors, report) with the report's per-slip SCM and DEM values."""
    from scipy.optimize import least_squares

    missing = [k for k in SOIL_KEYS if k not in start]
    if missing:
        raise LabFailed(f"the wheel fit starts from a calibration that lacks {', '.join(missing)}")
    load = plan.wheel_load
    if not load > 0:
        raise LabFailed("the wheel fit needs a loaded wheel (testbed.mass and a gravity > 0)")
    lever = load * plan.wheel.rim_radius
    held = {k: v for k, v in start.items() if k not in FITTED}  # SOIL_KEYS and any other terrain key (node_spacing)
    floor = {k: v for k, v in start.items() if k in FITTED}
    floor["k_phi"] = max(float(floor["k_phi"]), 1e-6 * load / plan.wheel.width)  # log needs > 0
    floor["janosi_k"] = max(float(floor["janosi_k"]), 1e-6 * plan.wheel.rim_radius)
    landing = landing_sinkage(targets)

    def soil(x) -> dict:
        return {**held, **_from_coordinates(x)}

    def tolerance(value: float, ci95: float, scale: float) -> float:
        """A residual's unit: the DEM's 95 % half-interval or RELATIVE_TOLERANCE of its value, whichever
        is wider (the trade's agreement), at least 1 % of `scale` (a value near zero)."""
        return max(ci95, RELATIVE_TOLERANCE * abs(value), 0.01 * scale)

    def forces(x):
        return [scm_wheel_forces(plan, soil(x), t.sinkage, t.slip) for t in targets]

    def static(x) -> float:
        return scm_static_force(plan, soil(x), landing) if landing else math.nan

    def held_residuals(x):
        out = []
        for t, (w, pull, torque) in zip(targets, forces(x)):
            out += [
                (w - t.vertical_force) / (RELATIVE_TOLERANCE * load),
                (pull - t.drawbar_pull) / tolerance(t.drawbar_pull, t.drawbar_pull_ci95, load),
                (torque - t.driving_torque) / tolerance(t.driving_torque, t.driving_torque_ci95, lever),
            ]
        if landing:  # the landed wheel at rest carries its load at the DEM's landing sinkage
            out.append((static(x) - load) / (RELATIVE_TOLERANCE * load))
        return np.array(out)

    free: dict = {"evaluations": 0, "cap": max_runs, "best": None, "last": None, "jac": None}

    def free_residuals(x):
        if free["last"] is not None and np.array_equal(free["last"][0], x):
            return free["last"][1]
        if free["evaluations"] >= free["cap"]:
            raise _OutOfRuns
        free["evaluations"] += 1
        summaries = scm_free_runs(plan, soil(x), targets, str(runs))
        values: list[float] = []
        for t, run in zip(targets, summaries):
            scm = [run.get(k, math.nan) for k in ("sinkage", "drawbar_pull", "driving_torque")]
            units = [
                tolerance(t.sinkage, t.sinkage_ci95, plan.wheel.rim_radius),
                tolerance(t.drawbar_pull, t.drawbar_pull_ci95, load),
                tolerance(t.driving_torque, t.driving_torque_ci95, lever),
            ]
            dem = [t.sinkage, t.drawbar_pull, t.driving_torque]
            # a run with no result (no landing, airborne) is as far off as MISSING_RESIDUAL tolerances
            values += [(s - d) / u if math.isfinite(s) else MISSING_RESIDUAL for s, d, u in zip(scm, dem, units)]
        out = np.array(values)
        free["last"] = (x.copy(), out, summaries)
        if free["best"] is None or _robust_cost(out) < _robust_cost(free["best"][1]):
            free["best"] = free["last"]
        return out

    def free_jacobian(x):
        """Forward differences of the runs' residuals, a step of FREE_STEP in each coordinate (into
        the bounds): the runs' results move in steps of the node grid, the step is well above them."""
        f0 = free_residuals(x)
        jac = np.empty((f0.size, x.size))
        for i in range(x.size):
            h = FREE_STEP if x[i] + FREE_STEP <= upper[i] else -FREE_STEP
            shifted = x.copy()
            shifted[i] += h
            jac[:, i] = (free_residuals(shifted) - f0) / h
        free["jac"] = jac
        return jac

    x0 = _to_coordinates(floor)
    lower = np.array([x0[0] - 12.0, 0.05, math.tan(math.radians(2.0)), x0[3] - 8.0])
    upper = np.array([x0[0] + 12.0, 2.0, math.tan(math.radians(MAX_FRICTION_ANGLE_DEG)), x0[3] + 8.0])
    x0 = np.clip(x0, lower + 1e-9, upper - 1e-9)
    result = least_squares(held_residuals, x0, bounds=(lower, upper), diff_step=0.02, max_nfev=max_evaluations)
    held_result = result
    x, fun, jac = result.x, result.fun, result.jac
    if runs is not None and max_runs > 0:
        try:
            # soft_l1 on residuals in tolerances: a slip SCM cannot represent (the DEM's thrust at high
            # slip, say) does not pull the others out of agreement
            result = least_squares(
                free_residuals, x, jac=free_jacobian, bounds=(lower, upper), loss="soft_l1", f_scale=1.0
            )
            x, fun, jac = result.x, result.fun, result.jac
        except _OutOfRuns:  # the best soil the runs met, with the last Jacobian the fit made
            x, fun = free["best"][0], free["best"][1]
            jac = free["jac"]
    fitted = _from_coordinates(x)
    parameters = {**held, **fitted}
    dof = max(1, fun.size - x.size)
    variance = float(fun @ fun) / dof
    try:
        covariance = np.linalg.inv(jac.T @ jac) * variance
        se_x = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    except (np.linalg.LinAlgError, AttributeError):
        se_x = np.full(x.size, math.nan)
    errors = {k: math.nan for k in SOIL_KEYS}
    errors["k_phi"] = fitted["k_phi"] * se_x[0]
    errors["n"] = float(se_x[1])
    errors["friction_angle_deg"] = math.degrees(se_x[2] / (1.0 + x[2] ** 2))
    errors["janosi_k"] = fitted["janosi_k"] * se_x[3]
    scm = forces(x)
    summaries: list[dict] = [{}] * len(targets)
    spent = free["evaluations"]
    if runs is not None and max_runs > 0:
        free["cap"] += 1  # the folder is left with the fitted soil's runs (one more when the best was not last)
        free_residuals(x)
        summaries = free["last"][2]
    from ..scm_calibration import wheel_record
    from ..scm_soil import scm_settings

    report = {
        "fitted": list(FITTED),
        "held": held,
        "start": {k: float(v) for k, v in floor.items()},
        "wheel_load_n": load,
        "geometry": wheel_record(plan.wheel),  # the wheel the keys were fitted on (scm_calibration_wheel)
        # the grid of the fit's SCM wheel: its forces (a grousered wheel's above all) depend on it
        "node_spacing_m": float(scm_settings(plan, [0], 0.0, parameters).parameters.node_spacing),
        "evaluations": int(held_result.nfev),
        "run_evaluations": spent,
        "rms_residual": math.sqrt(float(np.mean(fun**2))),
        "residual_unit": "the larger of the DEM's 95 % half-interval and RELATIVE_TOLERANCE of its value",
        "landing": {"sinkage": landing, "scm_vertical_force": static(x)} if landing else None,
        "slips": [
            {
                **asdict(t),
                "scm_vertical_force": w,
                "scm_drawbar_pull": pull,
                "scm_driving_torque": torque,
                **{f"run_{k}": run.get(k, math.nan) for k in ("sinkage", "drawbar_pull", "driving_torque")},
                "run_steady_state": run.get("steady_state"),
            }
            for t, (w, pull, torque), run in zip(targets, scm, summaries)
        ],
        "units": {  # held and start: the [units] of the file's [scm]
            "landing.sinkage": "m",
            "landing.scm_vertical_force": "N",
            **{f"slips.{key}": unit for key, unit in SLIP_UNITS.items()},
        },
    }
    return parameters, errors, report


def fit_beds(
    plan,
    bed_targets: list[list[WheelTarget]],
    starts: list[dict],
    runs: str | None,
    max_runs: int = 30,
    executor="serial",
    scheduler=None,
    workers=None,
) -> list[dict]:
    """fit_to_wheel on each bed's own targets (bed_wheel_targets) from starts[k] (the fit to the beds'
    means, with bed k's own lab values of the held keys), bed k's SCM runs in runs/bed_K: the beds'
    scatter of the fitted keys, which the fit to their means does not see. One task per bed (a dask
    worker each with executor 'dask'). Returns per bed {ok, parameters, rms_residual, run_evaluations}
    or {ok: False, error} (a bed without two averaged slips: not fitted)."""
    from ..study import Executor

    tasks = [
        {
            "scene_toml": plan.scene.to_toml(),
            "base_dir": plan.scene.base_dir,
            "targets": targets,
            "start": start,
            "runs": os.path.join(runs, f"bed_{k}") if runs else None,
            "max_runs": max_runs,
            "label": f"wheel fit on bed {k}",
        }
        for k, (targets, start) in enumerate(zip(bed_targets, starts))
    ]
    with Executor(executor, scheduler, workers) as ex:
        return ex.map(_bed_fit_task, tasks)


def _bed_fit_task(task: dict) -> dict:
    """One bed's wheel fit (fit_beds' task: module level, for dask workers); raises only a stop asked for."""
    from soil import quiet_warp

    from ..runner import RunInterrupted
    from ..study import task_plan

    if not task["targets"]:
        return {"label": task["label"], "ok": False, "error": "fewer than two slips averaged on this bed"}
    try:
        quiet_warp()  # Warp's banner and module lines: once per worker, not the user's business
        parameters, _, report = fit_to_wheel(
            task_plan(task), task["targets"], task["start"], runs=task["runs"], max_runs=task["max_runs"]
        )
    except RunInterrupted:  # a stop asked for (Ctrl-C, SIGTERM in a serial fit's runs) stops every bed's fit
        raise
    except Exception as error:  # noqa: BLE001 - a bed whose fit fails is a result: the others' stand
        return {"label": task["label"], "ok": False, "error": f"{type(error).__name__}: {error}"}
    return {
        "label": task["label"],
        "ok": True,
        "parameters": parameters,
        "rms_residual": report["rms_residual"],
        "run_evaluations": report["run_evaluations"],
    }


SLIP_UNITS = {
    "slip": "1",
    "sinkage": "m",
    "sinkage_ci95": "m",
    "drawbar_pull": "N",
    "drawbar_pull_ci95": "N",
    "driving_torque": "N m",
    "driving_torque_ci95": "N m",
    "replicas": "count",
    "vertical_force": "N",
    "landing_sinkage": "m",
    "landing_sinkage_ci95": "m",
    "duration": "s",
    "scm_vertical_force": "N",
    "scm_drawbar_pull": "N",
    "scm_driving_torque": "N m",
    "run_sinkage": "m",
    "run_drawbar_pull": "N",
    "run_driving_torque": "N m",
}
"""The units of a wheel fit's [[source.wheel.slips]] entries."""


def _robust_cost(residuals: np.ndarray) -> float:
    """scipy's soft_l1 cost of residuals (f_scale 1): sum of 2 (sqrt(1 + r^2) - 1)."""
    return float(np.sum(2.0 * (np.sqrt(1.0 + residuals**2) - 1.0)))


class _OutOfRuns(Exception):
    """The fit to the runs has spent max_runs evaluations."""
