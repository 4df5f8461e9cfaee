"""Calibration: tune scene keys (contact parameters) until the lab tests measure target bulk values.

    cosim calibrate SCENE --target repose=30 --vary soil.rolling_friction=0:0.3
    cosim calibrate SCENE --target friction=25 --target cohesion=200 \\
        --vary soil.stick_angle_deg,soil.slip_angle_deg=10:40 --vary soil.cohesion=0:2000

Targets (what the lab measures):
    repose             angle of repose [deg]                  (repose test, mean over replicas)
    friction           peak Mohr-Coulomb friction angle [deg] (shear test)
    friction_residual  residual friction angle [deg]          (shear test)
    cohesion           peak Mohr-Coulomb cohesion [Pa]        (shear test)
    cohesion_residual  residual cohesion [Pa]                 (shear test)

Each --vary names one scene key, or several joined by commas that take one value together
(a stick and a slip angle moved as one friction angle), and its range LOW:HIGH.

The loop (one evaluation = the lab tests the targets need, with lab.replicas replicas,
run through cosim.study.Executor; each in OUT/evaluations/NNN/):
- one key, one target: Brent's method (scipy.optimize.brentq) on measured - target over
  [LOW, HIGH]; both ends are measured first and must bracket the target;
- otherwise: Nelder-Mead (scipy.optimize.minimize, bounded) on the sum of squared misfits,
  each over its tolerance, in the keys scaled to [0, 1], from the scene's values.
Both stop at the first evaluation whose every target is within its tolerance (--tolerance
NAME=VALUE; defaults 1 deg, and 10 % or 1 Pa for cohesion) or after --max-evaluations.
The measurements are chaotic: replicas (lab.replicas) average the scatter that the
tolerance must exceed. Output: history.csv, summary.json, calibrate.png, and
calibrated.toml, the scene with the best values found.
"""

from __future__ import annotations

import logging
import math
import os
import typing
from dataclasses import dataclass

import numpy as np

from soil.files import atomic_write_text

from ..plots import save_figure
from ..scene import SceneError, is_number, key_field, key_unit, parse_value
from ..study import Executor
from . import common
from .scene import LabPlan

log = logging.getLogger("cosim.lab")


@dataclass(frozen=True)
class Target:
    """A bulk value the lab measures."""

    name: str
    test: str
    """'repose' or 'shear'."""
    unit: str
    key: tuple[str, str]
    """Where the value sits in the test's summary."""


TARGETS = {
    "repose": Target("repose", "repose", "deg", ("repose_angle_deg", "mean")),
    "friction": Target("friction", "shear", "deg", ("peak", "friction_angle_deg")),
    "friction_residual": Target("friction_residual", "shear", "deg", ("residual", "friction_angle_deg")),
    "cohesion": Target("cohesion", "shear", "Pa", ("peak", "cohesion_pa")),
    "cohesion_residual": Target("cohesion_residual", "shear", "Pa", ("residual", "cohesion_pa")),
}


@dataclass(frozen=True)
class Parameter:
    """Scene keys that take one value together, and their range."""

    keys: tuple[str, ...]
    low: float
    high: float

    @property
    def name(self) -> str:
        return ",".join(self.keys)


class _Converged(Exception):
    """Every target is within its tolerance: the optimiser stops here."""


class _OutOfEvaluations(Exception):
    """--max-evaluations evaluations were made: the optimiser stops here."""


VARIED_KEYS = ("soil.*", "lab.*", "bed.radius_mean", "bed.radius_spread", "run.dt", "run.dt_factor")
"""The keys a calibration may vary besides the tests' own sections (repose.*, shear.*): what the repose
and shear tests read (a wheel scene's [wheel], [testbed] or the bed's size they do not)."""


def check_parameters(parameters: list[Parameter], tests: set[str]) -> None:
    """SceneError naming a --vary key the tests `tests` do not read (VARIED_KEYS and their own sections) or
    one that takes no real number (a count, a switch: the optimiser's values are real numbers)."""
    from .scene import LabScene

    allowed = (*VARIED_KEYS, *(f"{test}.*" for test in sorted(tests)))
    for p in parameters:
        for key in p.keys:
            field = key_field(key, LabScene)
            if field is None:
                raise SceneError([f"--vary {key}: no such scene key"])
            if not any(key == a or (a.endswith(".*") and key.startswith(a[:-1])) for a in allowed):
                what = " and ".join(sorted(tests))
                raise SceneError([f"--vary {key}: not a key the {what} test reads; allowed: {', '.join(allowed)}"])
            if float not in {field.annotation, *typing.get_args(field.annotation)}:
                raise SceneError([f"--vary {key}: takes no real number (a count, a switch or a name)"])


def parse_targets(texts: list[str]) -> dict[str, float]:
    """['repose=30', ...] -> {'repose': 30.0}; SceneError names a bad one."""
    targets = {}
    for text in texts or []:
        name, _, value = text.partition("=")
        name = name.strip()
        if name not in TARGETS:
            raise SceneError([f"--target {text!r}: unknown target {name!r}; allowed: {', '.join(TARGETS)}"])
        number = parse_value(value)
        if not is_number(number) or not math.isfinite(number):
            raise SceneError([f"--target {text!r}: the value must be a finite number ({TARGETS[name].unit})"])
        if TARGETS[name].unit == "deg" and not 0 < number < 90:
            raise SceneError([f"--target {text!r}: an angle must be in (0, 90) deg"])
        if number < 0:
            raise SceneError([f"--target {text!r}: a cohesion is >= 0 Pa"])
        if name in targets:
            raise SceneError([f"--target {text!r}: {name} is given twice; give each target once"])
        targets[name] = float(number)
    if not targets:
        raise SceneError(["--target: give at least one target, e.g. --target repose=30"])
    return targets


def parse_parameters(texts: list[str]) -> list[Parameter]:
    """['soil.rolling_friction=0:0.3', 'soil.stick_angle_deg,soil.slip_angle_deg=10:40'] -> Parameters."""
    parameters: list[Parameter] = []
    for text in texts or []:
        keys, _, bounds = text.partition("=")
        low, _, high = bounds.partition(":")
        low, high = parse_value(low), parse_value(high)
        names = tuple(k.strip() for k in keys.split(",") if k.strip())
        if not names or not all(is_number(v) and math.isfinite(v) for v in (low, high)) or low >= high:
            raise SceneError(
                [f"--vary {text!r}: expected KEY[,KEY...]=LOW:HIGH with LOW < HIGH, e.g. soil.rolling_friction=0:0.3"]
            )
        taken = [key for p in parameters for key in p.keys] + list(names)
        twice = sorted({key for key in taken if taken.count(key) > 1})
        if twice:
            raise SceneError([f"--vary {text!r}: {twice[0]} is varied twice; give each key once"])
        units = {key: key_unit(key) or "1" for key in names}
        if len(set(units.values())) > 1:  # one value cannot be a number and a pressure
            raise SceneError(
                [
                    f"--vary {text!r}: keys that take one value together must share a unit; "
                    + ", ".join(f"{key} [{unit}]" for key, unit in units.items())
                    + ": vary each with its own --vary"
                ]
            )
        parameters.append(Parameter(names, float(low), float(high)))
    if not parameters:
        raise SceneError(["--vary: give at least one scene key to vary, e.g. --vary soil.rolling_friction=0:0.3"])
    return parameters


def default_tolerance(name: str, target: float) -> float:
    """1 deg for an angle; for a cohesion 10 % of the target, at least 1 Pa."""
    return 1.0 if TARGETS[name].unit == "deg" else max(0.1 * abs(target), 1.0)


def parse_tolerances(texts: list[str], targets: dict[str, float]) -> dict[str, float]:
    """Tolerances per target: --tolerance NAME=VALUE, else default_tolerance."""
    tolerances = {name: default_tolerance(name, value) for name, value in targets.items()}
    given: set[str] = set()
    for text in texts or []:
        name, _, value = text.partition("=")
        number = parse_value(value)
        if name not in targets or not is_number(number) or not 0 < number < math.inf:
            raise SceneError(
                [f"--tolerance {text!r}: expected NAME=VALUE > 0 for one of the targets ({', '.join(targets)})"]
            )
        if name in given:
            raise SceneError([f"--tolerance {text!r}: {name} is given twice; give each tolerance once"])
        given.add(name)
        tolerances[name] = float(number)
    return tolerances


def _overrides(parameters: list[Parameter], values) -> dict:
    return {key: float(v) for p, v in zip(parameters, values) for key in p.keys}


def check_geometry(plan: LabPlan, tests: set[str]) -> None:
    """SceneError naming what cannot be built in the lab tests `tests` of a plan (the repose tube and
    base, the shear box)."""
    from .repose import geometry
    from .shear import box

    builders = {"repose": lambda: geometry(plan, 0, check_memory=True), "shear": lambda: box(plan, check_memory=True)}
    for test in sorted(tests):
        builders[test]()


def measure(plan: LabPlan, tests: set[str], out_dir: str, executor: dict) -> dict[str, float]:
    """Run the lab tests `tests` on a plan into out_dir/<test>; the measured value of every target
    those tests give."""
    from .repose import repose_test
    from .shear import shear_test

    runners = {"repose": repose_test, "shear": shear_test}
    measured = {}
    for test in sorted(tests):
        summary = runners[test](plan, os.path.join(out_dir, test), overwrite=True, **executor)
        for target in TARGETS.values():
            if target.test == test:
                section, field = target.key
                measured[target.name] = float(summary[section].get(field, math.nan))
    return measured


def calibrate(
    plan: LabPlan,
    out_dir: str,
    targets: dict[str, float],
    parameters: list[Parameter],
    tolerances: dict[str, float] | None = None,
    max_evaluations: int = 12,
    overwrite: bool = False,
    executor: str = "serial",
    scheduler: str | None = None,
    workers: int | None = None,
) -> dict:
    """Tune `parameters` until the lab measures `targets` (module docstring); returns the summary
    (also OUT/summary.json) with the best values, what they measure and whether every target is
    within its tolerance."""
    if max_evaluations < 2:
        raise SceneError([f"--max-evaluations: must be >= 2 (got {max_evaluations})"])
    tolerances = tolerances or {name: default_tolerance(name, value) for name, value in targets.items()}
    tests = {TARGETS[name].test for name in targets}
    check_parameters(parameters, tests)
    # the scene and both ends of every range must be valid scenes (a slip angle above the stick angle, ...)
    # whose tests can be built (a tube that holds its grains, ...), before the folder is touched
    ends = [plan.with_changes(_overrides([p], [value])) for p in parameters for value in (p.low, p.high)]
    for each in [plan, *ends]:
        check_geometry(each, tests)
    with common.prepare_folder(plan, out_dir, overwrite, executor, scheduler):
        with Executor(executor, scheduler, workers) as cluster:  # one cluster for every evaluation
            return _calibrate(
                plan, out_dir, targets, parameters, tolerances, max_evaluations, tests, {"executor": cluster}
            )


def _calibrate(
    plan: LabPlan,
    out_dir: str,
    targets: dict,
    parameters: list[Parameter],
    tolerances: dict,
    max_evaluations: int,
    tests: set[str],
    run_on: dict,
) -> dict:
    """The optimisation loop of `calibrate` (run_on: the executor the lab tests use)."""
    from scipy import optimize

    history: list[dict] = []
    unit_of = {p.name: key_unit(p.keys[0]) or "1" for p in parameters} | {n: TARGETS[n].unit for n in targets}
    scale = np.array([p.high - p.low for p in parameters])
    low = np.array([p.low for p in parameters])

    def evaluate(values) -> dict:
        values = [float(v) for v in values]
        for row in history:  # an optimiser may ask twice for the same point
            if np.allclose(row["values"], values, rtol=0, atol=1e-12 * scale.max()):
                return row
        number = len(history) + 1
        folder = os.path.join(out_dir, "evaluations", f"{number:03d}")
        log.info(
            "calibrate: evaluation %d: %s",
            number,
            ", ".join(f"{p.name} = {v:.6g} {unit_of[p.name]}" for p, v in zip(parameters, values)),
        )
        given = measure(plan.with_changes(_overrides(parameters, values)), tests, folder, run_on)
        # the targets only: a shear test gives all four of its values, and the others have no target,
        # tolerance or unit in the summary (`cosim calibrate --target friction=30` ended in a KeyError)
        measured = {name: given[name] for name in targets}
        misfit = {name: measured[name] - targets[name] for name in targets}
        cost = float(sum((misfit[n] / tolerances[n]) ** 2 for n in targets))
        within = all(abs(misfit[n]) <= tolerances[n] for n in targets)
        row = {
            "evaluation": number,
            "values": values,
            "measured": measured,
            "misfit": misfit,
            "cost": cost,
            "within": within,
            "folder": folder,
        }
        history.append(row)
        log.info(
            "calibrate: evaluation %d measured %s",
            number,
            ", ".join(f"{n} {measured[n]:.4g} {unit_of[n]} (target {targets[n]:.4g} {unit_of[n]})" for n in targets),
        )
        if within:
            raise _Converged
        if len(history) >= max_evaluations:
            raise _OutOfEvaluations
        return row

    method = "brentq" if len(parameters) == 1 and len(targets) == 1 else "nelder-mead"
    message = ""
    stopped: KeyboardInterrupt | None = None
    try:
        if method == "brentq":
            (name,) = targets
            p = parameters[0]
            at_low, at_high = evaluate([p.low]), evaluate([p.high])
            unmeasured = [v for v, row in ((p.low, at_low), (p.high, at_high)) if not math.isfinite(row["cost"])]
            if unmeasured:  # brentq cannot start from nan
                message = (
                    f"{name} was not measured (nan) at {p.name} = {', '.join(f'{v:g}' for v in unmeasured)}, an end of "
                    "its range: the root search needs both ends"
                )
            elif np.sign(at_low["misfit"][name]) == np.sign(at_high["misfit"][name]):
                message = (
                    f"the target {name} = {targets[name]:g} is not between what the ends of {p.name} measure "
                    f"({at_low['measured'][name]:.4g} at {p.low:g}, {at_high['measured'][name]:.4g} at "
                    f"{p.high:g}): widen the range or vary another key"
                )
            else:
                optimize.brentq(
                    lambda v: evaluate([v])["misfit"][name],
                    p.low,
                    p.high,
                    xtol=1e-4 * (p.high - p.low),
                    maxiter=max_evaluations,
                )
        else:
            start = []
            for p in parameters:
                current = plan.scene.to_dict()
                for part in p.keys[0].split("."):
                    current = current.get(part, {}) if isinstance(current, dict) else {}
                value = current if isinstance(current, (int, float)) else 0.5 * (p.low + p.high)
                start.append(min(max((value - p.low) / (p.high - p.low), 0.0), 1.0))
            optimize.minimize(
                lambda u: evaluate(low + scale * np.asarray(u))["cost"],
                np.asarray(start),
                method="Nelder-Mead",
                bounds=[(0.0, 1.0)] * len(parameters),
                options={
                    "maxfev": max_evaluations,
                    "xatol": 1e-3,
                    "fatol": 0.1,
                    "initial_simplex": _simplex(np.asarray(start)),
                },
            )
    except _Converged:
        message = "every target is within its tolerance"
    except _OutOfEvaluations:
        message = f"stopped after --max-evaluations {max_evaluations} evaluations"
    except RuntimeError as error:  # brentq without convergence
        message = f"the optimiser stopped: {error}"
    except KeyboardInterrupt as stop:  # Ctrl-C or SIGTERM: the finished evaluations' report, then stop
        if not history:
            raise
        stopped = stop
        message = (
            f"interrupted after {len(history)} finished evaluation{'s' if len(history) > 1 else ''} (each one's "
            "folder keeps its tests): no calibrated scene"
        )
    best = min(history, key=lambda row: row["cost"] if math.isfinite(row["cost"]) else math.inf)
    converged = best["within"]
    path: str | None = os.path.join(out_dir, "calibrated.toml")
    if not math.isfinite(best["cost"]):  # nan measured every time: no value is better than another
        message = (
            f"no evaluation measured {', '.join(targets)} (each gave nan; their summary.json notes say why): "
            "no calibrated scene"
        )
        path = None
    if stopped is not None:  # an unfinished search: its best so far is no calibration
        path = None
    if not message:
        message = "every target is within its tolerance" if converged else "the optimiser ended outside the tolerance"
    if path is not None:  # the scene says what it is, and whether it met its targets, to whoever opens it
        said = "; ".join(
            f"{n} measured {best['measured'][n]:.4g} {unit_of[n]}, target {targets[n]:g} +- {tolerances[n]:g} "
            f"{unit_of[n]}"
            for n in targets
        )
        header = (
            f"# cosim calibrate: evaluation {best['evaluation']} of {len(history)}, "
            f"{'within every target' if converged else 'NOT within its targets'}: {' '.join(message.split())}\n"
            f"# {said}\n"
            f"# (summary.json and history.csv beside this file)\n"
        )
        scene_text = plan.with_changes(_overrides(parameters, best["values"])).scene.to_toml()
        atomic_write_text(path, header + scene_text)
    summary = {
        "test": "calibrate",
        "name": plan.name,
        "method": method,
        "converged": converged,
        "message": message,
        "targets": targets,
        "tolerances": tolerances,
        "parameters": [{"keys": list(p.keys), "low": p.low, "high": p.high} for p in parameters],
        "best": {
            "evaluation": best["evaluation"],
            "values": dict(zip([p.name for p in parameters], best["values"])),
            "measured": best["measured"],
            "misfit": best["misfit"],
        },
        "calibrated_scene": path,
        "evaluations": [
            {k: row[k] for k in ("evaluation", "values", "measured", "misfit", "cost", "within")} for row in history
        ],
        "units": {  # of targets, tolerances, measured and misfit by target; of values and limits by parameter
            **{name: TARGETS[name].unit for name in targets},
            **{p.name: key_unit(p.keys[0]) or "1" for p in parameters},
        },
    }
    columns = [("evaluation", "1", [row["evaluation"] for row in history])]
    for i, p in enumerate(parameters):
        columns.append((p.name, key_unit(p.keys[0]) or "1", [row["values"][i] for row in history]))
    for name in targets:
        unit = TARGETS[name].unit
        columns.append((f"{name}_measured", unit, [row["measured"][name] for row in history]))
        columns.append((f"{name}_target", unit, [targets[name]] * len(history)))
    columns.append(("cost", "1", [row["cost"] for row in history]))
    common.write_csv(os.path.join(out_dir, "history.csv"), columns)
    summary["figure"] = _figure(out_dir, history, parameters, targets, tolerances)
    common.write_summary(out_dir, summary)
    log.info(
        "calibrate: %s; best (evaluation %d): %s",
        message,
        best["evaluation"],
        ", ".join(f"{p.name} = {v:.6g}" for p, v in zip(parameters, best["values"])),
    )
    if stopped is not None:  # the report is written: now stop as asked
        raise stopped
    return summary


def _simplex(start: np.ndarray) -> np.ndarray:
    """The first Nelder-Mead simplex: the start and a step of 0.25 (of each range) along each key,
    inwards from a bound."""
    points = [start]
    for i in range(len(start)):
        point = start.copy()
        point[i] += 0.25 if start[i] <= 0.75 else -0.25
        points.append(point)
    return np.asarray(points)


def _figure(out_dir: str, history: list[dict], parameters: list[Parameter], targets: dict, tolerances: dict):
    plt = common.pyplot()
    if plt is None or not history:
        return None
    from matplotlib.ticker import MaxNLocator

    fig, axes = plt.subplots(1, len(targets) + 1, figsize=(5 * (len(targets) + 1), 4), squeeze=False)
    for ax in axes[0]:
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    numbers = [row["evaluation"] for row in history]
    for ax, name in zip(axes[0], targets):
        ax.plot(numbers, [row["measured"][name] for row in history], "o-")
        ax.axhspan(
            targets[name] - tolerances[name],
            targets[name] + tolerances[name],
            color="tab:green",
            alpha=0.2,
            label="target +- tolerance",
        )
        ax.set_xlabel("evaluation")
        ax.set_ylabel(f"{name} [{TARGETS[name].unit}]")
        ax.legend(fontsize=8)
    ax = axes[0][-1]
    for i, p in enumerate(parameters):
        ax.plot(numbers, [(row["values"][i] - p.low) / (p.high - p.low) for row in history], "o-", label=p.name)
    ax.set_xlabel("evaluation")
    ax.set_ylabel("value within its range [-]")
    ax.set_ylim(-0.05, 1.05)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = os.path.join(out_dir, "calibrate.png")
    save_figure(fig, path, 120)
    plt.close(fig)
    return path
