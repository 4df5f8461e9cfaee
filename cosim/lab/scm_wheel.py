"""SCM parameters fitted to the DEM's own single-wheel runs (`cosim calibrate-scm --from-wheel`).

    targets = wheel_targets(run_wheel_tests(plan, folder, slips=(0.05, 0.1, 0.2, 0.4, 0.6), replicas=3))
    parameters, errors, report = fit_to_wheel(plan, targets, start=lab_calibration.parameters)

The DEM gives, at each imposed slip s, the steady-state sinkage z(s), drawbar pull DP(s) and
driving torque T(s) of the scene's wheel under its load W (`cosim study slip`: replicas, means and
95 % intervals). The SCM wheel is held at the DEM's sinkage and driven at the DEM's speeds and slip
over fresh soil (soil.scm.ScmTerrain, the run's grid and damping); its mean vertical force, pull
and torque over whole grouser pitches are compared with W, DP and T. scipy's least_squares moves
the parameters the wheel runs determine (FITTED: k_phi, n, phi, K) from the lab's values (the
virtual plate and shear tests, cosim.lab.scm) and holds the rest (k_c: one wheel width cannot
separate it from k_phi; c and K_e). A soil that carries W at the DEM's sinkage sinks to it when
the wheel is free, so the fit matches sinkage through W. The residuals, per slip:
(W_scm - W) / W, (DP_scm - DP) / W and (T_scm - T) / (W r) (W: the wheel's load); the standard errors are the square
roots of the diagonal of (J^T J)^-1 times the residuals' variance (J in the fitted coordinates).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass

import numpy as np

from ..scm_calibration import SOIL_KEYS
from .common import LabFailed

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


def run_wheel_tests(plan, out_dir: str, slips, replicas: int, executor="serial", scheduler=None, workers=None) -> str:
    """The DEM single-wheel runs of a testbed plan at each slip (cosim.study.slip_study) into out_dir;
    returns out_dir (its study.json holds the results)."""
    from ..study import slip_study

    slip_study(plan, out_dir, slips, replicas, executor, scheduler, workers, overwrite=True, plot=False)
    return out_dir


def wheel_targets(study_folder: str) -> list[WheelTarget]:
    """The WheelTargets of a slip study's folder (its study.json; cosim study slip), slips with at
    least one steady replica; LabFailed names the file when there are none."""
    path = os.path.join(study_folder, "study.json")
    try:
        with open(path) as f:
            study = json.load(f)
    except (OSError, json.JSONDecodeError) as error:
        raise LabFailed(f"{path}: not a readable slip study ({error})") from error
    if study.get("kind") != "slip":
        raise LabFailed(f"{path}: a {study.get('kind')!r} study, --wheel-runs needs a slip study (cosim study slip)")
    load = study.get("wheel_load")
    if not (isinstance(load, (int, float)) and load > 0):
        raise LabFailed(f"{path}: no wheel_load > 0 [N]; the wheel fit needs the wheel's load")
    targets = []
    for row in study.get("rows", []):
        averaged = int(row.get("averaged", row.get("steady", 0)))  # a table --include-sinking averaged
        if not averaged:
            continue

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
            )
        )
    if len(targets) < 2:
        raise LabFailed(f"{path}: {len(targets)} slips reached a steady state; the wheel fit needs two or more")
    return targets


def scm_wheel_forces(plan, soil: dict, sinkage: float, slip: float) -> tuple[float, float, float]:
    """(vertical force W [N], drawbar pull DP [N], driving torque T [N m]) of the plan's wheel held with
    its rim `sinkage` [m] below the SCM surface and driven at the plan's spin and `slip` over fresh
    soil: the means over two grouser pitches after one and a half contact lengths of travel."""
    from soil.scm import ScmTerrain

    from ..scm_soil import STEPS_PER_NODE, scm_settings

    wheel = plan.wheel
    rim = wheel.rim_radius
    omega = plan.drive_omega
    speed = omega * rim * (1.0 - slip)
    # a window of 4 outer radii round the one wheel: the nodes under it are the run's (the lattice is
    # fixed in the world), three times fewer to step than the run's window
    window = {"window_length": 4.0 * wheel.outer_radius, "window_width": wheel.width + 2.0 * wheel.outer_radius}
    base = scm_settings(plan, [0], 0.0, {**window, **soil})
    spacing = base.parameters.node_spacing
    step = spacing / (STEPS_PER_NODE * omega * wheel.outer_radius)  # the fastest surface speed: the tips
    contact = 2.0 * math.sqrt(max(2.0 * rim * sinkage, spacing**2))
    pitch = 2.0 * math.pi * wheel.outer_radius / max(1, getattr(wheel.shape, "grouser_count", 0) or 1)
    terrain = ScmTerrain(base.parameters, [wheel.shape], window=base.window, device="cpu", precision="double")
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


def fit_to_wheel(plan, targets: list[WheelTarget], start: dict, max_evaluations: int = 80):
    """SCM parameters (SOIL_KEYS) fitted to the DEM wheel `targets`, moving FITTED from the values in
    `start` (a calibration's parameters) and holding the rest. Returns (parameters, standard errors,
    report) with the report's per-slip SCM and DEM values."""
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

    def forces(x):
        values = {**held, **_from_coordinates(x)}
        return [scm_wheel_forces(plan, values, t.sinkage, t.slip) for t in targets]

    def residuals(x):
        out = []
        for t, (w, pull, torque) in zip(targets, forces(x)):
            out += [(w - t.vertical_force) / load, (pull - t.drawbar_pull) / load, (torque - t.driving_torque) / lever]
        return np.array(out)

    x0 = _to_coordinates(floor)
    lower = np.array([x0[0] - 12.0, 0.05, math.tan(math.radians(2.0)), x0[3] - 8.0])
    upper = np.array([x0[0] + 12.0, 2.0, math.tan(math.radians(70.0)), x0[3] + 8.0])
    x0 = np.clip(x0, lower + 1e-9, upper - 1e-9)
    result = least_squares(residuals, x0, bounds=(lower, upper), diff_step=0.02, max_nfev=max_evaluations)
    fitted = _from_coordinates(result.x)
    parameters = {**held, **fitted}
    dof = max(1, result.fun.size - result.x.size)
    variance = float(result.fun @ result.fun) / dof
    try:
        covariance = np.linalg.inv(result.jac.T @ result.jac) * variance
        se_x = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    except np.linalg.LinAlgError:
        se_x = np.full(result.x.size, math.nan)
    errors = {k: math.nan for k in SOIL_KEYS}
    errors["k_phi"] = fitted["k_phi"] * se_x[0]
    errors["n"] = float(se_x[1])
    errors["friction_angle_deg"] = math.degrees(se_x[2] / (1.0 + result.x[2] ** 2))
    errors["janosi_k"] = fitted["janosi_k"] * se_x[3]
    scm = forces(result.x)
    report = {
        "fitted": list(FITTED),
        "held": held,
        "start": {k: float(v) for k, v in floor.items()},
        "wheel_load_n": load,
        "evaluations": int(result.nfev),
        "rms_residual": math.sqrt(float(np.mean(result.fun**2))),
        "slips": [
            {
                **asdict(t),
                "scm_vertical_force": w,
                "scm_drawbar_pull": pull,
                "scm_driving_torque": torque,
            }
            for t, (w, pull, torque) in zip(targets, scm)
        ],
    }
    return parameters, errors, report
