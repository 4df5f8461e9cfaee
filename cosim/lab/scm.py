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
"""

from __future__ import annotations

import math

import numpy as np

from ..scm_calibration import SOIL_KEYS


def fit_bekker(curves, fit_from: float = 0.0) -> dict:
    """k_c [Pa m^(1-n)], k_phi [Pa m^(-n)], n and their standard errors from pressure-sinkage
    curves [(plate width b [m], sinkage z [m] (S,), pressure p [Pa] (S,))] of two or more widths
    (cosim.lab.plate.bekker_fit: scipy's curve_fit from a log-log start)."""
    from .plate import bekker_fit

    if len({round(float(b), 12) for b, _, _ in curves}) < 2:
        raise ValueError("k_c and k_phi need plates of two or more widths")
    fit = bekker_fit([(float(b), np.asarray(z), np.asarray(p)) for b, z, p in curves], fit_from)
    return {
        "k_c": fit["k_c"],
        "k_phi": fit["k_phi"],
        "n": fit["n"],
        "k_c_se": fit.get("k_c_se", math.nan),
        "k_phi_se": fit.get("k_phi_se", math.nan),
        "n_se": fit.get("n_se", math.nan),
    }


def fit_unloading(sinkage, pressure) -> dict:
    """The elastic stiffness K_e [Pa/m] (and its standard error) of an unloading branch: sinkage z [m]
    and pressure p [Pa] from the deepest point on, the plate rising. A line p = K_e (z - z_p) through
    the branch's upper half (p above half its start): its slope (scipy curve_fit)."""
    from scipy.optimize import curve_fit

    z, p = np.asarray(sinkage, dtype=float), np.asarray(pressure, dtype=float)
    upper = p >= 0.5 * p[0]
    if upper.sum() < 3:
        raise ValueError("the unloading branch has fewer than three points above half its load")
    z, p = z[upper], p[upper]
    slope0 = (p[0] - p[-1]) / max(z[0] - z[-1], 1e-30)
    (slope, offset), covariance = curve_fit(lambda x, k, c: k * x + c, z, p, p0=(slope0, p[0] - slope0 * z[0]))
    return {"elastic_stiffness": float(slope), "elastic_stiffness_se": float(math.sqrt(covariance[0, 0]))}


def fit_mohr_coulomb(sigma, tau) -> dict:
    """Cohesion c [Pa], friction angle phi [deg] and their standard errors from (sigma_n, tau) [Pa]
    points (a line tau = c + sigma tan(phi), scipy curve_fit); c is held >= 0 (a negative intercept
    of a cohesionless soil's scatter is no cohesion: then c = 0 and phi through the origin)."""
    from scipy.optimize import curve_fit

    sigma, tau = np.asarray(sigma, dtype=float), np.asarray(tau, dtype=float)
    if len(np.unique(sigma)) >= 2:
        (c, tan_phi), covariance = curve_fit(lambda s, c, t: c + s * t, sigma, tau, p0=(0.0, 0.5))
        c_se, tan_se = math.sqrt(covariance[0, 0]), math.sqrt(covariance[1, 1])
    else:
        c = -1.0
    if c < 0:
        (tan_phi,), covariance = curve_fit(lambda s, t: s * t, sigma, tau, p0=(0.5,))
        c, c_se, tan_se = 0.0, math.nan, math.sqrt(covariance[0, 0])
    phi = math.degrees(math.atan(tan_phi))
    phi_se = math.degrees(tan_se / (1 + tan_phi**2))
    return {"cohesion": float(c), "cohesion_se": c_se, "friction_angle_deg": phi, "friction_angle_deg_se": phi_se}


def fit_janosi(curves) -> dict:
    """Janosi-Hanamoto's K [m] (and its standard error) from shear curves [(displacement j [m] (S,),
    tau [Pa] (S,))]: tau / tau_peak = 1 - exp(-j / K) fitted to every curve up to its peak (scipy curve_fit)."""
    from scipy.optimize import curve_fit

    xs, ys = [], []
    for j, tau in curves:
        j, tau = np.asarray(j, dtype=float), np.asarray(tau, dtype=float)
        peak = int(np.argmax(tau))
        if peak < 2 or tau[peak] <= 0:
            continue
        xs.append(j[: peak + 1] - j[0])
        ys.append(tau[: peak + 1] / tau[peak])
    if not xs:
        raise ValueError("no shear curve rises to a peak: K cannot be fitted")
    x, y = np.concatenate(xs), np.concatenate(ys)
    start = max(float(np.interp(0.63, np.maximum.accumulate(y), x)), 1e-9)
    (k,), covariance = curve_fit(lambda u, k: 1 - np.exp(-u / k), x, y, p0=(start,), bounds=(1e-12, np.inf))
    return {"janosi_k": float(k), "janosi_k_se": float(math.sqrt(covariance[0, 0]))}


def assemble(bekker: dict, unloading: dict, strength: dict, janosi: dict) -> tuple[dict, dict]:
    """(parameters, standard errors) over SOIL_KEYS from the four fits."""
    fits = {**bekker, **unloading, **strength, **janosi}
    return {k: float(fits[k]) for k in SOIL_KEYS}, {k: float(fits.get(f"{k}_se", math.nan)) for k in SOIL_KEYS}
