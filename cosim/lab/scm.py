"""SCM parameters from the DEM's own virtual tests at the scene's gravity (`cosim calibrate-scm`).

    calibration = calibrate_scm(lab_plan, out_dir)      # plate and shear tests, fits
    cosim.scm_calibration.write_calibration("terrain.toml", calibration)

The fits (scipy.optimize.curve_fit; each parameter's standard error is the square root of the
diagonal of its covariance):

- pressure-sinkage p = (k_c / b + k_phi) z^n over plates of two or more widths b: k_c, k_phi, n
  (cosim.lab.plate.bekker_fit);
- the plate's unloading from its deepest sinkage: the elastic stiffness K_e, the slope dp/dz of
  the unloading branch's upper half (a line through it);
- direct shear tau = c + sigma tan(phi) at the peaks: c, phi (c held >= 0);
- each shear curve tau(j) = tau_peak (1 - exp(-j / K)) up to its peak: Janosi-Hanamoto's K (one K
  for all curves, each curve scaled by its own peak).

The fits pool every replica's points. With two or more replicas (beds and specimens, lab.replicas)
each replica is also fitted alone, and a parameter's error is the larger of the pooled fit's and
the replicas' standard error of the mean (combine_errors): the scatter between beds can be several
times a pooled fit's error.
"""

from __future__ import annotations

import math

import numpy as np

from ..scene import SceneError
from ..scm_calibration import SOIL_KEYS, SOIL_UNITS
from .common import LabFailed


def fit_bekker(curves, fit_from: float = 0.0) -> dict:
    """k_c [Pa m^(1-n)], k_phi [Pa m^(-n)], n and their standard errors from pressure-sinkage
    curves [(plate width b [m], sinkage z [m] (S,), pressure p [Pa] (S,))] of two or more widths
    (cosim.lab.plate.bekker_fit: scipy's curve_fit from a log-log start)."""
    from .plate import bekker_fit

    if len({round(float(b), 12) for b, _, _ in curves}) < 2:
        raise LabFailed("k_c and k_phi need plates of two or more widths")
    fit = bekker_fit([(float(b), np.asarray(z), np.asarray(p)) for b, z, p in curves], fit_from)
    out = {k: fit.get(k, math.nan) for k in ("k_c", "k_phi", "n", "k_c_se", "k_phi_se", "n_se", "r_squared")}
    if not all(math.isfinite(out[k]) for k in ("k_c", "k_phi", "n")):
        raise LabFailed(f"the Bekker fit did not converge on {fit['points']} points")
    if out["k_c"] < 0 or out["k_phi"] < 0:
        # the widths' difference is within the scatter: one modulus, held >= 0 (SCM's moduli are)
        from scipy.optimize import curve_fit

        b = np.concatenate([np.full(len(z), float(w)) for w, z, _ in curves])
        z = np.concatenate([np.asarray(z, dtype=float) for _, z, _ in curves])
        p = np.concatenate([np.asarray(p, dtype=float) for _, _, p in curves])
        use = (z >= fit_from) & (p > 0)
        frictional = out["k_c"] < 0
        shape = (lambda x, k, n: k * x[0] ** n) if frictional else (lambda x, k, n: k / x[1] * x[0] ** n)
        start = (max(out["k_phi"], 1.0), out["n"]) if frictional else (max(out["k_c"], 1e-3), out["n"])
        (k, n), covariance = curve_fit(shape, (z[use], b[use]), p[use], p0=start, maxfev=20000)
        se = np.sqrt(np.diag(covariance))
        kept, dropped = ("k_phi", "k_c") if frictional else ("k_c", "k_phi")
        out.update({kept: float(k), f"{kept}_se": float(se[0]), dropped: 0.0, f"{dropped}_se": math.nan})
        out[f"{dropped}_note"] = (
            f"held at its bound 0 (the fit over both widths gave a negative {dropped}: the widths' difference is "
            "within the scatter), so it has no error"
        )
        out.update(n=float(n), n_se=float(se[1]))
    return out


def fit_unloading(sinkage, pressure) -> dict:
    """The elastic stiffness K_e [Pa/m] (and its standard error) of an unloading branch: sinkage z [m]
    and pressure p [Pa]: the plate held at its deepest point (the first sample), then rising. A line
    p = K_e (z - z_p) through the rising samples of the branch's upper half (p above half the held
    pressure; the held point itself carries no damping force and is left out): its slope (scipy
    curve_fit)."""
    from scipy.optimize import curve_fit

    z, p = np.asarray(sinkage, dtype=float), np.asarray(pressure, dtype=float)
    upper = p >= 0.5 * p[0]
    upper[0] = False
    if upper.sum() < 3:
        raise LabFailed("the unloading branch has fewer than three points above half its load")
    z, p = z[upper], p[upper]
    slope0 = (p[0] - p[-1]) / max(z[0] - z[-1], 1e-30)
    (slope, offset), covariance = curve_fit(lambda x, k, c: k * x + c, z, p, p0=(slope0, p[0] - slope0 * z[0]))
    return {"elastic_stiffness": float(slope), "elastic_stiffness_se": float(math.sqrt(covariance[0, 0]))}


def fit_mohr_coulomb(sigma, tau) -> dict:
    """Cohesion c [Pa], friction angle phi [deg] and their standard errors from (sigma_n, tau) [Pa]
    points (a line tau = c + sigma tan(phi), scipy curve_fit); c is held >= 0 (a negative intercept
    of a cohesionless soil's scatter is no cohesion: then c = 0 and phi through the origin)."""
    import warnings

    from scipy.optimize import OptimizeWarning, curve_fit

    sigma, tau = np.asarray(sigma, dtype=float), np.asarray(tau, dtype=float)
    notes = {}
    if len(np.unique(sigma)) >= 2:
        with warnings.catch_warnings():  # two points: no covariance, said in the notes below instead
            warnings.simplefilter("ignore", OptimizeWarning)
            (c, tan_phi), covariance = curve_fit(lambda s, c, t: c + s * t, sigma, tau, p0=(0.0, 0.5))
        c_se, tan_se = math.sqrt(covariance[0, 0]), math.sqrt(covariance[1, 1])
        if len(sigma) <= 2:  # a line through two points leaves no scatter to estimate its errors from
            c_se = tan_se = math.nan
            notes = dict.fromkeys(
                ("cohesion_note", "friction_angle_deg_note"),
                "two shear points for two parameters: the line passes through both, so no error is left to "
                "estimate (three or more shear.normal_stresses, or --replicas 2 or more, give one)",
            )
    else:
        c = -1.0
    if c < 0:
        with warnings.catch_warnings():  # one point: no covariance, said in the notes below instead
            warnings.simplefilter("ignore", OptimizeWarning)
            (tan_phi,), covariance = curve_fit(lambda s, t: s * t, sigma, tau, p0=(0.5,))
        c, c_se, tan_se = 0.0, math.nan, math.sqrt(covariance[0, 0])
        tan_se = tan_se if len(sigma) > 1 else math.nan
        notes = {
            "cohesion_note": "held at its bound 0 (the shear points' line met the stress axis below the origin, "
            "a cohesionless soil's scatter, or one normal stress): phi is fitted through the origin and c has "
            "no error"
        }
        if len(sigma) <= 1:
            notes["friction_angle_deg_note"] = "one shear point: no scatter to estimate its error from"
    phi = math.degrees(math.atan(tan_phi))
    phi_se = math.degrees(tan_se / (1 + tan_phi**2))
    return {
        "cohesion": float(c),
        "cohesion_se": c_se,
        "friction_angle_deg": phi,
        "friction_angle_deg_se": phi_se,
        **notes,
    }


def fit_janosi(curves) -> dict:
    """Janosi-Hanamoto's K [m] (and its standard error) from shear curves [(displacement j [m] (S,),
    tau [Pa] (S,))]: tau = tau_max,i (1 - exp(-j / K)) fitted to every curve i up to its peak, one K
    for all, each curve its own tau_max (scipy curve_fit)."""
    from scipy.optimize import curve_fit

    xs: list[np.ndarray] = []
    ys: list[np.ndarray] = []
    owner: list[np.ndarray] = []
    for j, tau in curves:
        j, tau = np.asarray(j, dtype=float), np.asarray(tau, dtype=float)
        peak = int(np.argmax(tau))
        if peak < 2 or tau[peak] <= 0:
            continue
        xs.append(j[: peak + 1] - j[0])
        ys.append(tau[: peak + 1])
        owner.append(np.full(peak + 1, len(owner)))
    if not xs:
        raise LabFailed("no shear curve rises to a peak: K cannot be fitted")
    x, y, index = np.concatenate(xs), np.concatenate(ys), np.concatenate(owner)
    peaks = [float(part.max()) for part in ys]
    scaled = np.concatenate([part / part.max() for part in ys])
    start = max(float(np.median(x[(scaled > 0.5) & (scaled < 0.75)])) if np.any(scaled > 0.5) else x.max() / 3, 1e-9)

    def model(u, k, *tau_max):
        return np.asarray(tau_max)[index] * (1 - np.exp(-u / k))

    values, covariance = curve_fit(model, x, y, p0=(start, *peaks), bounds=(1e-12, np.inf), maxfev=20000)
    return {"janosi_k": float(values[0]), "janosi_k_se": float(math.sqrt(covariance[0, 0]))}


def fit_plates(plates, fit_from: float) -> tuple[dict, list[dict]]:
    """The plates' fits (k_c, k_phi, n, the elastic stiffness and their standard errors; the
    unloading fit of each plate) from calibrate_scm's plate records (width [m], sinkage [m] and
    pressure [Pa] of the loading; the unloading branch), pooled. The elastic stiffness is the
    plates' mean; its error the scatter between plates, or the fits' own where there is one plate."""
    bekker = fit_bekker([(r["width"], r["sinkage"], r["pressure"]) for r in plates], fit_from)
    unloads = [
        fit_unloading(r["unload_sinkage"], r["unload_pressure"]) for r in plates if len(r["unload_sinkage"]) >= 3
    ]
    if not unloads:
        raise LabFailed("no plate's unloading curve has three points: the elastic stiffness cannot be fitted")
    stiffness = np.array([u["elastic_stiffness"] for u in unloads])
    errors = np.array([u["elastic_stiffness_se"] for u in unloads])
    spread = float(stiffness.std(ddof=1) / math.sqrt(len(stiffness))) if len(stiffness) > 1 else 0.0
    unloading = {
        "elastic_stiffness": float(stiffness.mean()),
        "elastic_stiffness_se": max(spread, float(np.sqrt(np.sum(errors**2))) / len(errors)),
    }
    return {**bekker, **unloading}, unloads


def fit_shear(sheared) -> dict:
    """The shear box's fits (c, phi, Janosi's K and their standard errors) from calibrate_scm's shear
    records (peak sigma and tau [Pa]; the curve: displacement [m], tau [Pa]), pooled."""
    strength = fit_mohr_coulomb([r["peak_sigma"] for r in sheared], [r["peak_tau"] for r in sheared])
    return {**strength, **fit_janosi([(r["displacement"], r["tau"]) for r in sheared])}


PLATE_KEYS = ("k_c", "k_phi", "n", "elastic_stiffness")
"""The SOIL_KEYS the plates give (the rest: the shear box's)."""


def replica_fits(plates, sheared, fit_from: float) -> dict[str, list[float]]:
    """SOIL_KEYS -> each replica's own fit (its bed's plates for PLATE_KEYS, its specimen's shear for
    the rest; nan where that replica's fit failed), for the keys two or more replicas measured."""
    import warnings

    from scipy.optimize import OptimizeWarning

    out: dict[str, list[float]] = {}
    groups = (
        (PLATE_KEYS, plates, lambda own: fit_plates(own, fit_from)[0]),
        (tuple(k for k in SOIL_KEYS if k not in PLATE_KEYS), sheared, fit_shear),
    )
    for keys, records, fit in groups:
        replicas = sorted({int(r["replica"]) for r in records})
        if len(replicas) < 2:
            continue
        for k in keys:
            out[k] = []
        for replica in replicas:
            try:
                with warnings.catch_warnings():  # a replica's own covariance is not used (two stresses: none)
                    warnings.simplefilter("ignore", OptimizeWarning)
                    values = fit([r for r in records if int(r["replica"]) == replica])
            except (LabFailed, RuntimeError, ValueError):  # curve_fit's: no fit on this replica alone
                values = {k: math.nan for k in keys}
            for k in keys:
                out[k].append(float(values[k]))
    return out


def combine_errors(fit_errors: dict, per_replica: dict) -> dict:
    """SOIL_KEYS -> the larger of the pooled fit's standard error and the replicas' standard error
    of the mean (their fits' scatter / sqrt(R), over the R that converged): a pooled fit's error
    counts its points' scatter, not the scatter between beds and specimens, which can be larger."""
    from ..metrics import ensemble

    out = {}
    for k in SOIL_KEYS:
        replicas = ensemble(per_replica.get(k, []))  # over the finite values
        between = replicas["std"] / math.sqrt(replicas["n"]) if replicas["n"] >= 2 else math.nan
        # no spread at all: every replica held at the same bound (k_c or c at 0), which says nothing
        known = [e for e in (fit_errors.get(k, math.nan), between) if math.isfinite(e) and e > 0]
        out[k] = max(known) if known else math.nan
    return out


# -- the DEM tests -------------------------------------------------------------------------------

SMALL_TESTS = {
    "plate.speed_ratio": 0.1,
    "shear.length_diameters": 10.0,
    "shear.height_diameters": 6.0,
    "plate.max_sinkage_depth": 0.3,
}
"""calibrate-scm's default sizes where the scene sets none (CPU minutes): the plates sink at the lab's
quasi-static bound v / sqrt(g d) = 0.1 to 0.3 x the bed's fill depth (plates at least 3.2 and 4.6
grain diameters wide); a shear box 10 grain
diameters square and 6 high. --set any lab key (docs/lab.md) to make them bigger."""


def small_tests(scene) -> list[str]:
    """Overrides (KEY=VALUE) that size a lab scene's plate and shear tests to SMALL_TESTS where it sets nothing."""
    d = 2 * scene.bed.radius_mean
    out = []
    plate, shear = scene.plate, scene.shear
    if plate.widths is None:  # the lab's, but at least three grain diameters and four apart
        side = min(scene.bed.length, scene.bed.width)
        out.append(f"plate.widths=[{max(0.25 * side, 3.2 * d)!r}, {max(0.4 * side, 4.6 * d)!r}]")
    if plate.speed is None and plate.speed_ratio is None:
        out.append(f"plate.speed_ratio={SMALL_TESTS['plate.speed_ratio']}")
    if plate.max_sinkage is None:
        out.append(f"plate.max_sinkage={SMALL_TESTS['plate.max_sinkage_depth'] * scene.bed.depth!r}")
    for key in ("length", "width"):
        if getattr(shear, key) is None:
            out.append(f"shear.{key}={SMALL_TESTS['shear.length_diameters'] * d!r}")
    if shear.height is None:
        out.append(f"shear.height={SMALL_TESTS['shear.height_diameters'] * d!r}")
    return out


def calibrate_scm(plan, out_dir: str, overwrite: bool = False, executor="serial", scheduler=None, workers=None):
    """Run the DEM tests of a lab plan's soil at its gravity (plates of every plate.widths with their
    unloading; direct shear at every shear.normal_stresses) and fit the SCM parameters. Writes
    plate.csv, shear.csv and summary.json into out_dir; returns a cosim.scm_calibration.ScmCalibration."""
    import os

    from ..scm_calibration import ScmCalibration
    from . import common, plate, shear

    plate.check(plan)
    sides = plate.widths(plan)
    if len(sides) < 2:
        raise SceneError([f"plate.widths: k_c and k_phi need two or more plate widths, got {list(sides)}"])
    geometry = shear.box(plan, check_memory=True)  # every test's geometry is checked before the folder is touched
    with common.prepare_folder(plan, out_dir, overwrite, executor, scheduler):
        replicas = plan.scene.lab.replicas if plan.scene.bed.bed_file is None else 1
        ready, plates, _, stopped = plate.press_plates(
            plan, out_dir, sides, replicas, executor, scheduler, workers, unload=True
        )
        if stopped is not None:  # a calibration needs every plate: no partial fit
            raise stopped
        fit_from = plan.scene.plate.fit_from if plan.scene.plate.fit_from is not None else 0.25 * plan.diameter
        plate_fits, unloads = fit_plates(plates, fit_from)  # before the shear tests: a failed fit stops here

        specimens_folder = os.path.join(out_dir, "specimens")
        os.makedirs(specimens_folder, exist_ok=True)
        paths = [os.path.join(specimens_folder, f"replica_{k}.h5") for k in range(plan.scene.lab.replicas)]
        specimens = common.successful(
            common.map_tasks(
                plan,
                shear.run_replica,
                [{"replica": k, "stage": "specimen", "specimen": p} for k, p in enumerate(paths)],
                [f"specimen {k}" for k in range(len(paths))],
                executor,
                scheduler,
                workers,
            ),
            "shear specimen",
        )
        shear_jobs = [
            {"replica": s["replica"], "stage": "shear", "specimen": s["path"], "stress": sigma, "top": s["top"]}
            for s in specimens
            for sigma in geometry.stresses
        ]
        sheared = common.successful(
            common.map_tasks(
                plan,
                shear.run_replica,
                shear_jobs,
                [f"replica {j['replica']}, sigma {j['stress']:.4g} Pa" for j in shear_jobs],
                executor,
                scheduler,
                workers,
            ),
            "shear",
        )
        fits = {**plate_fits, **fit_shear(sheared)}
        parameters = {k: float(fits[k]) for k in SOIL_KEYS}
        fit_errors = {k: float(fits.get(f"{k}_se", math.nan)) for k in SOIL_KEYS}
        per_replica = replica_fits(plates, sheared, fit_from)
        standard_errors = combine_errors(fit_errors, per_replica)
        # why an error is nan, said beside it rather than left a bare "+- nan"
        not_estimated = {
            k: fits[f"{k}_note"] for k in SOIL_KEYS if math.isnan(standard_errors[k]) and f"{k}_note" in fits
        }

        common.write_csv(
            os.path.join(out_dir, "plate.csv"),
            _columns(
                [
                    ("replica", "1", [r["replica"] for r in plates for _ in r["sinkage"]]),
                    ("plate_width", "m", [r["width"] for r in plates for _ in r["sinkage"]]),
                    ("sinkage", "m", [z for r in plates for z in r["sinkage"]]),
                    ("pressure", "Pa", [p for r in plates for p in r["pressure"]]),
                ]
            ),
        )
        common.write_csv(
            os.path.join(out_dir, "shear.csv"),
            _columns(
                [
                    ("replica", "1", [r["replica"] for r in sheared for _ in r["tau"]]),
                    ("normal_stress_nominal", "Pa", [r["stress"] for r in sheared for _ in r["tau"]]),
                    ("displacement", "m", [u for r in sheared for u in r["displacement"]]),
                    ("shear_stress", "Pa", [t for r in sheared for t in r["tau"]]),
                ]
            ),
        )
        scene = plan.scene
        # the tests' own quasi-static numbers (as `cosim lab plate` and `lab shear` judge them): a scene on this
        # calibration is told when they were out of range (cosim.advice.scm_check: scm_calibration_lab)
        largest = max(float(np.max(r["pressure"])) for r in plates)
        lab_checks = [
            {"test": test, **{k: number[k] for k in ("name", "value", "limit", "ok")}}
            for test, numbers in (
                (
                    "plate",
                    plate.quasi_static_numbers(
                        plan,
                        plate.plate_speed(plan),
                        [(r["width"], r["sinkage"], r["pressure"]) for r in plates],
                        largest,
                        {"k": math.nan, **plate_fits},
                        fit_from,
                    ),
                ),
                ("shear", shear.quasi_static_numbers(plan, geometry)),
            )
            for number in numbers
        ]
        source = {
            "scene": plan.name,
            "gravity_vector": [float(g) for g in plan.gravity],
            # the other keys end in their unit (_m, _s, _pa) or are counts
            "units": {
                "gravity_vector": "m/s^2",
                "replica_fits": SOIL_UNITS,
                "standard_error_of_fit": SOIL_UNITS,
                "lab_checks": {"value": "1", "limit": "1"},
                "shear.still_rising": "each [replica [1], normal stress [Pa]]",
            },
            "lab_checks": lab_checks,
            "soil": common.soil_summary(plan),
            "grain": {
                "radius_mean_m": scene.bed.radius_mean,
                "radius_spread": scene.bed.radius_spread,
                "diameter_m": plan.diameter,
            },
            "dem": {"precision": plan.precision, "dt_s": plan.dt, "replicas": replicas},
            # each bed's and specimen's own fit, and the pooled fit's own errors: [standard_error] is the
            # larger of those and the replicas' scatter / sqrt(R) (combine_errors)
            "replica_fits": per_replica,
            "standard_error_of_fit": fit_errors,
            "error_not_estimated": not_estimated,
            "plate": {
                "widths_m": list(sides),
                "speed_m_s": plate.plate_speed(plan),
                "max_sinkage_m": plate.max_sinkage(plan, float(np.mean([b["surface"] for b in ready]))),
                "fit_from_m": fit_from,
                "bed_m": [scene.bed.length, scene.bed.width, scene.bed.depth],
                "surface_m": [b["surface"] for b in ready],
                "steps": [r["steps"] for r in plates],
                "bekker_r_squared": plate_fits.get("r_squared", math.nan),
                "unloading_stiffness_pa_m": [u["elastic_stiffness"] for u in unloads],
            },
            "shear": {
                "box_m": [geometry.length, geometry.width, geometry.height],
                "grains": geometry.count,
                "normal_stresses_pa": list(geometry.stresses),
                "speed_m_s": geometry.speed,
                "displacement_m": geometry.displacement,
                "peak_sigma_pa": [r["peak_sigma"] for r in sheared],
                "peak_tau_pa": [r["peak_tau"] for r in sheared],
                # (replica, sigma_n [Pa]) of each curve still climbing at the end of its travel (shear.strength)
                "still_rising": [[int(r["replica"]), float(r["stress"])] for r in sheared if r.get("rising_at_end")],
                "steps": [r["steps"] for r in sheared],
            },
        }
        calibration = ScmCalibration(parameters, standard_errors, plan.g, source)
        common.write_summary(
            out_dir,
            {
                "test": "calibrate-scm",
                "parameters": parameters,
                "standard_errors": standard_errors,
                **source,
                "units": {**source["units"], "parameters": SOIL_UNITS, "standard_errors": SOIL_UNITS},
            },
        )
        return calibration


def _columns(columns):
    """write_csv's columns from (name, unit, values)."""
    return [(name, unit, list(values)) for name, unit, values in columns]
