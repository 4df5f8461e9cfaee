"""The SCM calibration (cosim.lab.scm, cosim.scm_calibration): the fits recover known parameters from
synthetic test curves with noise, within a few of their own standard errors; the calibration file
round-trips; a calibration used at another gravity warns naming both gravities."""

import math
import os
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from cosim.lab.scm import (
    combine_errors,
    fit_bekker,
    fit_janosi,
    fit_mohr_coulomb,
    fit_plates,
    fit_shear,
    fit_unloading,
    replica_fits,
)
from cosim.metrics import SUMMARY_RULE
from cosim.plan import load_plan
from cosim.scene import SceneError
from cosim.scm_calibration import (
    SOIL_KEYS,
    SOIL_UNITS,
    CalibrationError,
    CalibrationGravityWarning,
    ScmCalibration,
    read_calibration,
    tomllib,  # tomli before Python 3.11
    write_calibration,
)
from cosim.system import CoupledSystem
from helpers import write_tiny

RNG = np.random.default_rng(7)


def _close(value, error, truth, sigmas=4.0, rtol=0.05):
    """value within `sigmas` of its standard error of the truth, and the error itself small (rtol)."""
    assert math.isfinite(error) and error > 0
    assert abs(value - truth) <= sigmas * error, (value, error, truth)
    assert abs(value - truth) <= rtol * abs(truth), (value, truth)


def test_the_bekker_fit_recovers_known_moduli_from_two_widths():
    k_c, k_phi, n = 3.0e3, 6.0e5, 1.2
    curves = []
    for b in (0.03, 0.06, 0.09):
        z = np.linspace(1e-3, 0.015, 60)
        p = (k_c / b + k_phi) * z**n
        curves.append((b, z, p * (1 + 0.01 * RNG.standard_normal(len(z)))))
    fit = fit_bekker(curves)
    _close(fit["k_c"], fit["k_c_se"], k_c, rtol=0.15)
    _close(fit["k_phi"], fit["k_phi_se"], k_phi)
    _close(fit["n"], fit["n_se"], n, rtol=0.02)


def test_the_unloading_fit_recovers_the_elastic_stiffness():
    stiffness = 4.0e6
    z = np.linspace(0.010, 0.009, 40)
    p = stiffness * (z - 0.009) * (1 + 0.005 * RNG.standard_normal(len(z)))
    fit = fit_unloading(z, np.maximum(p, 0))
    _close(fit["elastic_stiffness"], fit["elastic_stiffness_se"], stiffness)


def test_the_shear_fits_recover_cohesion_friction_and_janosi_k():
    cohesion, phi, k = 120.0, 32.0, 1.5e-3
    sigma = np.repeat([100.0, 200.0, 400.0], 3)
    tau = (cohesion + sigma * math.tan(math.radians(phi))) * (1 + 0.01 * RNG.standard_normal(len(sigma)))
    strength = fit_mohr_coulomb(sigma, tau)
    _close(strength["cohesion"], strength["cohesion_se"], cohesion, rtol=0.2)
    _close(strength["friction_angle_deg"], strength["friction_angle_deg_se"], phi, rtol=0.03)
    curves = []
    for peak in (150.0, 300.0):
        j = np.linspace(0, 0.01, 200)
        curves.append((j, peak * (1 - np.exp(-j / k)) * (1 + 0.01 * RNG.standard_normal(len(j)))))
    janosi = fit_janosi(curves)
    _close(janosi["janosi_k"], janosi["janosi_k_se"], k)


def test_a_cohesionless_soil_is_fitted_through_the_origin():
    sigma = np.array([10.0, 20.0, 40.0])
    strength = fit_mohr_coulomb(sigma, sigma * 0.5 - np.array([0.5, 0.2, 0.4]))
    assert strength["cohesion"] == 0 and 24 < strength["friction_angle_deg"] < 27


def test_a_shear_fit_without_scatter_says_why_it_has_no_error(recwarn):
    """Two shear points fit their line exactly (tau = 10 + sigma tan 35 deg) and a cohesion held at 0 has
    no error: each error is nan with its reason, and no raw SciPy warning ("Covariance ... could not be
    estimated") reaches the user."""
    from scipy.optimize import OptimizeWarning

    sigma = np.array([100.0, 200.0])
    two = fit_mohr_coulomb(sigma, 10.0 + sigma * math.tan(math.radians(35.0)))
    assert two["cohesion"] == pytest.approx(10.0) and two["friction_angle_deg"] == pytest.approx(35.0)
    assert math.isnan(two["cohesion_se"]) and math.isnan(two["friction_angle_deg_se"])
    assert "two shear points for two parameters" in two["cohesion_note"] == two["friction_angle_deg_note"]
    held = fit_mohr_coulomb(sigma, sigma * 0.75 - 25.0)  # the line meets the stress axis above 0: c < 0
    assert held["cohesion"] == 0 and math.isnan(held["cohesion_se"]) and "bound 0" in held["cohesion_note"]
    assert math.isfinite(held["friction_angle_deg_se"]) and "friction_angle_deg_note" not in held
    assert not [w for w in recwarn if issubclass(w.category, OptimizeWarning)]


def _replica_records(k_phi, phi, rng):
    """calibrate_scm's plate and shear records of beds and specimens that differ: replica r's soil has
    k_phi[r] [Pa m^(-n)] and phi[r] [deg] (k_c 3e3 Pa m^(1-n), n 1.2, K_e 4e6 Pa/m, c 0, K 1.5 mm),
    each measured with 1 % noise."""
    plates, sheared = [], []
    for replica, (k_phi_r, phi_r) in enumerate(zip(k_phi, phi)):
        for b in (0.03, 0.06):
            z = np.linspace(1e-3, 0.015, 40)
            p = (3.0e3 / b + k_phi_r) * z**1.2 * (1 + 0.01 * rng.standard_normal(len(z)))
            unload_z = np.linspace(0.015, 0.0145, 20)
            unload_p = p[-1] + 4.0e6 * (unload_z - 0.015) * (1 + 0.01 * rng.standard_normal(len(unload_z)))
            plates.append(
                dict(replica=replica, width=b, sinkage=z, pressure=p, unload_sinkage=unload_z, unload_pressure=unload_p)
            )
        for sigma in (25.0, 50.0, 100.0):
            peak = sigma * math.tan(math.radians(phi_r)) * (1 + 0.01 * rng.standard_normal())
            j = np.linspace(0, 0.006, 120)
            tau = peak * (1 - np.exp(-j / 1.5e-3)) * (1 + 0.01 * rng.standard_normal(len(j)))
            sheared.append(dict(replica=replica, peak_sigma=sigma, peak_tau=float(tau.max()), displacement=j, tau=tau))
    return plates, sheared


def test_the_replicas_own_fits_carry_the_scatter_between_beds_into_the_error_bar():
    """Beds and specimens whose soils differ (k_phi by 10 %, phi by 2 deg between replicas, each
    measured with 1 % noise): over many draws of 4 replicas the replicas' own fits scatter by the
    soils' spread (their variance's mean within 3.5 of its sampling errors); the combined error bar
    covers the soils' mean at the t interval's 95 %, and the pooled fit's own (at 2 of them) less often."""
    rng = np.random.default_rng(11)
    replicas, draws = 4, 40
    truth, spread = {"k_phi": 6.0e5, "friction_angle_deg": 30.0}, {"k_phi": 6.0e4, "friction_angle_deg": 2.0}
    variances: dict = {key: [] for key in truth}
    covered, covered_by_fit = dict.fromkeys(truth, 0), dict.fromkeys(truth, 0)
    t95 = 3.182  # Student's t, 3 degrees of freedom, 97.5 %
    for _ in range(draws):
        soils = {key: truth[key] + spread[key] * rng.standard_normal(replicas) for key in truth}
        plates, sheared = _replica_records(soils["k_phi"], soils["friction_angle_deg"], rng)
        fits = {**fit_plates(plates, 0.0)[0], **fit_shear(sheared)}
        own = replica_fits(plates, sheared, 0.0)
        errors = combine_errors({k: fits[f"{k}_se"] for k in SOIL_KEYS}, own)
        assert set(own) == set(SOIL_KEYS) and all(len(v) == replicas for v in own.values())
        assert all(errors[k] >= fits[f"{k}_se"] for k in SOIL_KEYS if math.isfinite(fits[f"{k}_se"]))
        for key in truth:
            variances[key].append(np.var(own[key], ddof=1))
            covered[key] += abs(fits[key] - truth[key]) <= t95 * errors[key]
            covered_by_fit[key] += abs(fits[key] - truth[key]) <= 2.0 * fits[f"{key}_se"]
    sampling = math.sqrt(2 / (replicas - 1) / draws)  # relative standard error of a mean of sample variances
    for key in truth:
        assert abs(np.mean(variances[key]) / spread[key] ** 2 - 1) <= 3.5 * sampling, key
        assert covered[key] / draws >= 0.85, key  # 95 % expected; 0.85 is 3 binomial errors below
    assert covered_by_fit["friction_angle_deg"] < covered["friction_angle_deg"]
    # one bed for every plate (a scene's bed.bed_file): the plates' keys keep the pooled fit's error
    one_bed = [r for r in plates if r["replica"] == 0]
    own = replica_fits(one_bed, sheared, 0.0)
    assert set(own) == {"cohesion", "friction_angle_deg", "janosi_k"}
    assert combine_errors({k: fits[f"{k}_se"] for k in SOIL_KEYS}, own)["k_phi"] == fits["k_phi_se"]


def _calibration(gravity):
    values = dict(k_c=2.0e3, k_phi=8.0e5, n=1.1, cohesion=50.0, friction_angle_deg=30.0)
    values.update(janosi_k=0.002, elastic_stiffness=2.0e7)
    return ScmCalibration(values, {k: 0.1 for k in SOIL_KEYS}, gravity, {"soil": {"density": 2600.0}})


def test_a_calibration_file_round_trips_and_warns_at_another_gravity(tmp_path):
    path = tmp_path / "terrain.toml"
    write_calibration(str(path), _calibration(9.81))
    back = read_calibration(str(path))
    assert back.parameters == _calibration(9.81).parameters and back.gravity == 9.81
    assert back.source["soil"]["density"] == 2600.0
    scene = write_tiny(tmp_path, f'\n[terrain]\nmodel = "scm"\ncalibration = "{path.name}"\nk_c = 1.0e3\n')
    plan = load_plan(scene)
    assert dict(plan.terrain.parameters)["k_c"] == 1.0e3  # a scene key wins over the file's
    assert dict(plan.terrain.parameters)["k_phi"] == 8.0e5
    with pytest.warns(CalibrationGravityWarning, match=r"9\.81 m/s\^2.*1\.625 m/s\^2"):
        CoupledSystem.build(plan, None)
    (gravity,) = [f for f in _findings(plan) if f.check == "scm_calibration_gravity"]
    assert not gravity.ok and gravity.unit == "m/s^2" and (gravity.value, gravity.limit) == pytest.approx((9.81, 1.625))
    units = {f.check: f.unit for f in _findings(plan) if f.check != "scm_calibration_gravity"}
    assert units.pop("scm_coupling_step") == "rad" and set(units.values()) == {"1"}  # the others: ratios
    write_calibration(str(path), _calibration(plan.g))
    with warnings.catch_warnings():
        warnings.simplefilter("error", CalibrationGravityWarning)
        CoupledSystem.build(load_plan(scene), None)


@pytest.mark.parametrize(
    "damage, named",
    [
        ({"standard_error": {"k_c": "abc"}}, "[standard_error] k_c must be a number"),
        ({"standard_error": {"k_phi": -3.0}}, "[standard_error] k_phi must be a number >= 0"),
        ({"standard_error": [1, 2]}, "[standard_error] must be a table"),
        ({"scm": [1]}, "[scm] must be a table"),
        ({"gravity": math.inf}, "gravity must be a finite"),
        ({"gravity": True}, "gravity must be a finite"),
        ("utf-16", "not a readable calibration file"),
    ],
)
def test_a_calibration_file_of_the_wrong_types_is_refused_naming_the_file_and_key(tmp_path, damage, named):
    import tomli_w

    path = tmp_path / "terrain.toml"
    write_calibration(str(path), _calibration(9.81))
    if damage == "utf-16":
        path.write_bytes(path.read_text().encode("utf-16"))
    else:
        with open(path, "rb") as f:
            data = tomllib.load(f)
        path.write_text(tomli_w.dumps({**data, **damage}))
    with pytest.raises(CalibrationError) as error:
        read_calibration(str(path))
    assert str(path) in str(error.value) and named in str(error.value), str(error.value)


@pytest.mark.parametrize(
    "change, named",
    [
        (lambda d: d["scm"].update(k_C=5.0), "[scm] k_C: not an SCM soil key; allowed: k_c, "),
        (lambda d: d["standard_error"].update(bogus=1.0), "[standard_error] bogus: not an SCM soil key"),
        (lambda d: d["units"].update(k_c="kPa m^(1-n)"), "[units] k_c = 'kPa m^(1-n)': this version reads k_c in"),
        (lambda d: d["units"].update(friction_angle_deg="rad"), "[units] friction_angle_deg = 'rad'"),
        (lambda d: d.update(format=True), "format True, this version reads format"),
        (lambda d: d["scm"].update(k_c="0.094"), "[scm] k_c must be a finite number, got '0.094'"),
        (lambda d: d["scm"].pop("k_phi"), "[scm] lacks k_phi"),
    ],
    ids=["misspelt soil key", "unknown standard error", "k_c in kPa", "an angle in rad", "format true", "text", "none"],
)
def test_a_calibration_file_that_would_be_misread_is_refused_naming_the_key(tmp_path, change, named):
    """A misspelt key in [scm] or [standard_error] was dropped without a word, and [units] was never read:
    a k_c written in kPa was taken in Pa, an angle in radians as degrees; `format = true` passed as 1; a
    k_c written as a text was said to be missing."""
    import tomli_w

    path = tmp_path / "terrain.toml"
    write_calibration(str(path), _calibration(9.81))
    with open(path, "rb") as f:
        data = tomllib.load(f)
    change(data)
    path.write_text(tomli_w.dumps(data))
    with pytest.raises(CalibrationError) as error:
        read_calibration(str(path))
    assert str(path) in str(error.value) and named in str(error.value), str(error.value)


@pytest.mark.parametrize(
    "source, named",
    [
        ({"replica_fits": {"k_c": [True, False]}}, "[source.replica_fits] k_c: must be a list of numbers"),
        ({"replica_fits": {"k_c": [0.1, math.inf]}}, "[source.replica_fits] k_c: an infinite value (nan marks"),
        ({"wheel": {"fitted": 5}}, "[source.wheel] fitted must be a list of SCM keys, got 5"),
        ({"wheel": 5}, "[source] wheel must be a table"),
        ({"plate": "deep"}, "[source] plate must be a table"),
    ],
    ids=["booleans per bed", "an inf per bed", "fitted a number", "wheel a number", "plate a text"],
)
def test_a_calibrations_record_of_the_wrong_types_is_refused_when_the_scene_is_planned(tmp_path, source, named):
    """true / false in a bed's fits were read as 1.0 and 0.0 (a replica ran with k_c = 0); `fitted = 5`
    was a TypeError (exit 1) at a --vary-bed run, after advise had called the scene valid."""
    path = tmp_path / "terrain.toml"
    calibration = _calibration(1.625)
    calibration.source.update(source)
    write_calibration(str(path), calibration)
    scene = write_tiny(tmp_path, f'\n[terrain]\nmodel = "scm"\ncalibration = "{path.name}"\n')
    with pytest.raises(SceneError) as error:
        load_plan(scene)
    assert f"terrain.calibration: {path}: {named}" in str(error.value), str(error.value)


def test_a_calibration_path_that_is_no_regular_file_is_refused_without_reading_it(tmp_path):
    """A FIFO waited forever for a writer and /dev/zero was read until memory ran out; a folder and a
    missing path are named the same way."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    for path in (str(fifo), "/dev/zero", str(tmp_path), str(tmp_path / "missing.toml")):
        with pytest.raises(CalibrationError, match="not a calibration file"):
            read_calibration(path)


def test_a_calibration_outside_scms_range_is_refused_naming_the_file_unless_the_scene_overrides_it(tmp_path):
    """A fit of tests too small for the soil can give a negative n or friction angle: a scene on that
    file is bad input naming the file, the key, its value and SCM's bound (before anything runs); the
    scene's own key wins over the file's, and with it the scene loads."""
    from cosim.scm_calibration import out_of_range

    calibration = _calibration(1.625)
    calibration.parameters.update(n=-1.49, friction_angle_deg=-7.0)
    path = tmp_path / "terrain.toml"
    write_calibration(str(path), calibration)
    assert set(out_of_range(calibration.parameters)) == {"n", "friction_angle_deg"}
    assert out_of_range(_calibration(1.625).parameters) == {}
    assert set(out_of_range({**_calibration(1.625).parameters, "k_c": 0.0, "k_phi": 0.0})) == {"k_phi"}
    scm = f'\n[terrain]\nmodel = "scm"\ncalibration = "{path.name}"\n'
    with pytest.raises(SceneError) as refused:
        load_plan(write_tiny(tmp_path, scm))
    message = str(refused.value)
    assert "terrain.toml: [scm] n = -1.49: input should be greater than 0" in message
    assert "friction_angle_deg = -7 deg" in message and "terrain.friction_angle_deg in the scene wins" in message
    assert "(set terrain.n, terrain.k_c and terrain.k_phi together: they were fitted together)" in message
    bekker = "n = 0.8\nk_c = 2.0e3\nk_phi = 8.0e5\n"
    with pytest.raises(SceneError, match="friction_angle_deg = -7 deg") as refused:
        load_plan(write_tiny(tmp_path, scm + bekker))
    assert "[scm] n" not in str(refused.value)
    plan = load_plan(write_tiny(tmp_path, scm + bekker + "friction_angle_deg = 30.0\n"))
    assert dict(plan.terrain.parameters)["n"] == 0.8 and dict(plan.terrain.parameters)["k_phi"] == 8.0e5
    # n alone over the file's k_c and k_phi: refused (they were fitted with the file's n; the units of k_c and
    # k_phi hold only with it: a probe's n = 1 over k_c 1e22 fitted at n = 8.6 sank a wheel 1e-17 m, "valid")
    with pytest.raises(SceneError) as refused:
        load_plan(write_tiny(tmp_path, scm + "n = 0.8\nfriction_angle_deg = 30.0\n"))
    assert "terrain.n: replaces the calibration's n (-1.49) while its k_c and k_phi, fitted with that n" in str(
        refused.value
    )


def test_a_run_deeper_than_the_calibrations_tests_is_flagged(tmp_path):
    """scm_calibration_depth: a run's measured rim sinkage against the deepest sinkage the
    calibration's DEM tests reached (its plates' and its wheel runs' upper 95 % ends, whichever is
    deeper); not judged before a run, nor with a file that records none; a [source] that is not a
    number is refused naming the file."""
    from cosim.cli import advise_lines
    from cosim.scm_calibration import tested_sinkage
    from cosim.system import validity

    path = tmp_path / "terrain.toml"
    scene = write_tiny(tmp_path, f'\n[terrain]\nmodel = "scm"\ncalibration = "{path.name}"\n')
    for plate, wheel, deepest in ((0.02, 0.004, 0.02), (0.002, 0.01, 0.01 + 1e-4)):
        source = {"plate": {"max_sinkage_m": plate}, "wheel": {"slips": [{"sinkage": wheel, "sinkage_ci95": 1e-4}]}}
        write_calibration(str(path), ScmCalibration(_calibration(1.625).parameters, {}, 1.625, source))
        plan = load_plan(scene)
        assert plan.terrain.calibration_sinkage == pytest.approx(deepest, rel=1e-12)
        assert tested_sinkage(read_calibration(str(path))) == plan.terrain.calibration_sinkage
        assert not any(f.check == "scm_calibration_depth" for f in _findings(plan))  # before a run
        advice = advise_lines(plan)  # ... where `cosim advise` names it as waiting for the run
        (waiting,) = [line for line in advice if line.startswith("  [after the run] scm_calibration_depth: ")]
        assert f" {deepest:.3g} m the calibration's DEM tests reached" in waiting, waiting
        (verdict,) = [line for line in advice if line.startswith("verdict:")]
        assert verdict.endswith("scm_calibration_depth waiting for the run's measurements)"), verdict
        for rim, ok in ((0.9 * deepest, True), (1.1 * deepest, False)):
            (finding,) = [f for f in validity(plan, 0.0, {"sinkage": rim}) if f.check == "scm_calibration_depth"]
            assert finding.ok == ok and ("extrapolated" in finding.message) != ok
    write_calibration(str(path), _calibration(1.625))
    plan = load_plan(scene)
    assert not any(f.check == "scm_calibration_depth" for f in validity(plan, 0.0, {"sinkage": 1.0}))
    assert not any("scm_calibration_depth" in line for line in advise_lines(plan))
    source = {"plate": {"max_sinkage_m": "deep"}}
    write_calibration(str(path), ScmCalibration(_calibration(1.625).parameters, {}, 1.625, source))
    with pytest.raises(SceneError, match="terrain.toml: \\[source.plate\\] max_sinkage_m"):
        load_plan(scene)


def test_a_calibration_whose_lab_tests_were_out_of_range_flags_the_scenes_on_it(tmp_path):
    """scm_calibration_lab: calibrate-scm records its plate and shear tests' quasi-static numbers
    ([source] lab_checks); a scene on a calibration whose tests were too fast carried its parameters as
    valid (the shipped beds' plate test: an inertial number above 1e-3). A file that records none is not
    judged; a record of the wrong shape is refused naming the file."""
    from cosim.advice import scm_check

    path = tmp_path / "terrain.toml"
    scene = write_tiny(tmp_path, f'\n[terrain]\nmodel = "scm"\ncalibration = "{path.name}"\n')
    fast = {"test": "plate", "name": "inertial number I", "value": 0.0036, "limit": 0.001, "ok": False}
    slow = {"test": "shear", "name": "inertial number I", "value": 0.0009, "limit": 0.001, "ok": True}
    for checks, failed in (([fast, slow], ("plate inertial number I = 0.0036 > 0.001",)), ([slow], ())):
        write_calibration(str(path), ScmCalibration(_calibration(1.625).parameters, {}, 1.625, {"lab_checks": checks}))
        plan = load_plan(scene)
        assert plan.terrain.calibration_lab_failed == failed
        (finding,) = [f for f in scm_check(plan) if f.check == "scm_calibration_lab"]
        assert finding.ok == (not failed) and finding.value == len(failed)
        assert all(text in finding.message for text in failed) and finding.setting == "terrain.calibration"
        assert ("plate.speed_ratio" in finding.message) == bool(failed)  # the key that slows the plate
    # a check named after its test is not named twice ("plate plate speed ..."), as calibrate-scm records it
    speed = {"test": "plate", "name": "plate speed v / sqrt(g d)", "value": 0.3, "limit": 0.1, "ok": False}
    write_calibration(str(path), ScmCalibration(_calibration(1.625).parameters, {}, 1.625, {"lab_checks": [speed]}))
    assert load_plan(scene).terrain.calibration_lab_failed == ("plate speed v / sqrt(g d) = 0.3 > 0.1",)
    (finding,) = [f for f in scm_check(load_plan(scene)) if f.check == "scm_calibration_lab"]
    assert "plate.speed_ratio" in finding.message  # the key that slows the plate, named for this check too
    diverged = {**fast, "value": math.nan}  # a plate whose pressures were nan: a failed check, still a file
    write_calibration(str(path), ScmCalibration(_calibration(1.625).parameters, {}, 1.625, {"lab_checks": [diverged]}))
    assert load_plan(scene).terrain.calibration_lab_failed == ("plate inertial number I = nan > 0.001",)
    write_calibration(str(path), _calibration(1.625))
    assert not any(f.check == "scm_calibration_lab" for f in scm_check(load_plan(scene)))
    write_calibration(
        str(path),
        ScmCalibration(_calibration(1.625).parameters, {}, 1.625, {"lab_checks": [{**fast, "value": "fast"}]}),
    )
    with pytest.raises(SceneError, match=r"terrain.toml: \[source\] lab_checks must be tables"):
        load_plan(scene)


def test_a_wheel_fit_used_on_another_grid_is_flagged(tmp_path):
    """scm_calibration_grid: a wheel fit's keys carry the forces of the grid its SCM wheel ran on
    ([source.wheel] node_spacing_m); a scene on that grid passes, one on another fails naming the
    spacing to set; a file that records none (a lab calibration) is not judged; a spacing that is not
    a positive number is refused naming the file and the entry."""
    from cosim.scm_calibration import fitted_node_spacing

    path = tmp_path / "terrain.toml"
    scene = write_tiny(tmp_path, f'\n[terrain]\nmodel = "scm"\ncalibration = "{path.name}"\n')

    def written(spacing) -> None:
        source = {"wheel": {"node_spacing_m": spacing}}
        write_calibration(str(path), ScmCalibration(_calibration(1.625).parameters, {}, 1.625, source))

    write_calibration(str(path), _calibration(1.625))  # a lab calibration: no grid recorded, none judged
    default = load_plan(scene)
    assert default.terrain.calibration_node_spacing is None
    assert not any(f.check == "scm_calibration_grid" for f in _findings(default))
    grid = [f for f in _findings(default) if f.check == "scm_grouser_grid"]
    spacing = grid[0].value * default.wheel.shape.grouser_thickness  # the scene's own (default) grid
    written(spacing)
    plan = load_plan(scene)
    assert plan.terrain.calibration_node_spacing == fitted_node_spacing(read_calibration(str(path))) == spacing
    (finding,) = [f for f in _findings(plan) if f.check == "scm_calibration_grid"]
    assert finding.ok and finding.unit == "m"
    written(2.0 * spacing)
    (finding,) = [f for f in _findings(load_plan(scene)) if f.check == "scm_calibration_grid"]
    assert not finding.ok and f"terrain.node_spacing = {2.0 * spacing!r}" in finding.message
    written(-0.001)
    with pytest.raises(SceneError, match=r"terrain.toml: \[source.wheel\] node_spacing_m must be a node spacing"):
        load_plan(scene)


def test_a_wheel_fit_used_on_another_wheel_or_load_is_flagged(tmp_path):
    """scm_calibration_wheel: a wheel fit's keys compensate SCM's errors for the wheel and load it was
    fitted on ([source.wheel] geometry and wheel_load_n); used on the full-size rover's 0.1 m wheels at 20x
    the load, or at 1.67x the load, it was not judged. The shipped fit on its own wheel passes, and within
    10 % (10 % itself included); another radius, smooth rims, a load 1.67x, a rover of other wheels fail,
    naming what differs and, for a rover, the single-wheel load to fit at; on a mixed terrain only the SCM
    wheel is judged. A mesh fit knows its mesh by a digest of its scaled vertices and triangles, in any
    order: another mesh of the same radius and width fails, as do another scale and a grouser wheel. A lab
    calibration, or a fit that does not record its wheel, is not judged; a record of the wrong kind or
    contradicting itself is refused naming the file and the entry."""
    from types import SimpleNamespace

    from cosim.scm_calibration import FittedWheel, mesh_digest, wheel_record
    from soil import GrouserWheel, MeshWheel

    examples = os.path.join(os.path.dirname(__file__), "..", "examples")
    scm = os.path.join(examples, "phobos_single_wheel_scm.toml")
    fit = 'terrain.calibration="terrain/phobos_regolith_scm_wheel.toml"'

    def judged(scene, *overrides, calibration=fit):
        plan = load_plan(scene, [calibration, *overrides] if calibration else list(overrides))
        found = [f for f in _findings(plan) if f.check == "scm_calibration_wheel"]
        return found[0] if found else None

    plan = load_plan(scm, [fit])
    assert plan.terrain.calibration_wheel == FittedWheel("grouser", 0.03, 0.032, 10, 0.003, 0.00171)
    assert wheel_record(plan.wheel) == {
        "type": "grouser",
        "rim_radius_m": 0.03,
        "width_m": 0.032,
        "grouser_count": 10,
        "grouser_height_m": 0.003,
    }
    own = judged(scm)
    assert own.ok and own.value == pytest.approx(0.0, abs=1e-9) and own.limit == 0.1
    assert judged(scm, "testbed.mass=0.33").ok and judged(scm, "testbed.mass=0.27").ok  # 10 % either way
    heavier = judged(scm, "testbed.mass=0.5")
    assert not heavier.ok and heavier.value == pytest.approx(0.5 / 0.3 - 1.0, rel=1e-9)
    assert heavier.message.startswith("load 0.00285 N (the fit's 0.00171 N: 66.67% off): not the wheel")
    assert heavier.setting == "terrain.calibration, wheel, testbed.mass, scene.gravity"
    larger = judged(scm, "wheel.radius=0.05")
    assert not larger.ok and "rim radius 0.05 m (the fit's 0.03 m: 66.67% off)" in larger.message
    smooth = judged(scm, "wheel.grouser_count=0")
    assert not smooth.ok and "grouser count 0 (the fit's 10: 100% off)" in smooth.message
    rover = judged(os.path.join(examples, "phobos_rover_scm_traverse.toml"))
    assert not rover.ok and rover.message.startswith("wheel 0: rim radius 0.1 m") and "rover" in rover.setting
    assert "at this rover's load per wheel (0.03563 N: testbed.mass = 6.25 kg)" in rover.message
    boundary = judged(scm, "testbed.mass=0.3301")
    assert not boundary.ok and "10.03% off" in boundary.message  # not "10% off" beside a failed 10 %
    patch = os.path.join(examples, "phobos_rover_patch.toml")
    mixed = judged(patch, 'terrain.model="scm"', 'terrain.wheels=["dem", "dem", "dem", "scm"]')
    assert not mixed.ok and mixed.message.startswith("wheel 3: ")  # the DEM wheels, alike, are not judged
    assert judged(scm, 'terrain.calibration="terrain/phobos_regolith_scm_beds.toml"') is None  # a lab calibration

    path = tmp_path / "terrain.toml"
    grousered = GrouserWheel(radius=0.025, width=0.02, grouser_count=8, grouser_height=0.003, grouser_thickness=0.002)
    MeshWheel(*grousered.to_mesh(arc_segments=64)).save(tmp_path / "grousered.obj")
    MeshWheel(*GrouserWheel(radius=0.028, width=0.02).to_mesh(arc_segments=64)).save(tmp_path / "smooth.obj")
    scene = write_tiny(tmp_path, f'\n[terrain]\nmodel = "scm"\ncalibration = "{path.name}"\n')

    def written(wheel: dict) -> None:
        write_calibration(str(path), ScmCalibration(_calibration(1.625).parameters, {}, 1.625, {"wheel": wheel}))

    written({})  # a lab calibration first: the plan that gives the mesh's record reads the file
    meshed = load_plan(scene, ['wheel={type = "mesh", file = "grousered.obj"}'])
    record = wheel_record(meshed.wheel)
    assert record["type"] == "mesh" and len(record["mesh_sha256"]) == 64
    # the same mesh with its vertices and triangles listed in another order: the same digest
    shape = meshed.wheel.shape
    shuffle = np.random.default_rng(0).permutation(len(shape.vertices))
    rank = np.argsort(shuffle)
    turned = np.roll(rank[shape.triangles], 1, axis=1)[::-1]  # each triangle from another corner, reversed order
    assert mesh_digest(MeshWheel(shape.vertices[shuffle], turned)) == record["mesh_sha256"]
    assert mesh_digest(MeshWheel(shape.vertices, shape.triangles[:, ::-1])) != record["mesh_sha256"]  # inside out
    n = len(shape.vertices)  # vertex 0 twice (n its copy), one of its triangles on the copy: the copies swapped
    corners = shape.triangles.copy()
    first = np.flatnonzero((corners == 0).any(axis=1))[0]
    corners[first][corners[first] == 0] = n
    doubled = np.vstack([shape.vertices, shape.vertices[:1]])
    swapped = doubled[[n, *range(1, n), 0]]
    assert mesh_digest(SimpleNamespace(vertices=doubled, triangles=corners)) == mesh_digest(
        SimpleNamespace(vertices=swapped, triangles=corners)
    )
    written({"wheel_load_n": meshed.wheel_load, "geometry": record})
    assert judged(scene, 'wheel={type = "mesh", file = "grousered.obj"}', calibration=None).ok
    larger = judged(scene, 'wheel={type = "mesh", file = "grousered.obj", scale = 1.05}', calibration=None)
    assert not larger.ok and larger.message.startswith("another mesh or scale (its vertices differ")
    other = judged(scene, 'wheel={type = "mesh", file = "smooth.obj"}', calibration=None)
    assert not other.ok and other.message.startswith("another mesh or scale")
    kind = judged(scene, calibration=None)  # the tiny scene's own grouser wheel
    assert not kind.ok and kind.value == math.inf and "a grouser wheel, the fit's a mesh wheel" in kind.message
    smooth = {"type": "grouser", "rim_radius_m": 0.03, "width_m": 0.03, "grouser_count": 0, "grouser_height_m": 0.0}
    written({"wheel_load_n": 0.1})  # a fit made before its wheel was recorded
    assert load_plan(scene).terrain.calibration_wheel is None
    assert not any(f.check == "scm_calibration_wheel" for f in _findings(load_plan(scene)))
    for wheel, problem in (
        ({"wheel_load_n": 0.1, "geometry": {**smooth, "width_m": -1.0}}, r"geometry.width_m must be a finite"),
        ({"wheel_load_n": 0.1, "geometry": {**smooth, "grouser_count": 1.5}}, r"geometry.grouser_count must be"),
        ({"wheel_load_n": 0.1, "geometry": {**smooth, "grouser_count": -1, "grouser_height_m": 0.01}}, r"got -1$"),
        ({"wheel_load_n": "heavy", "geometry": smooth}, r"wheel_load_n must be a finite number > 0 \[N\]"),
        ({"geometry": smooth}, r"wheel_load_n must be a finite number > 0 \[N\] beside the geometry, got None"),
        ({"wheel_load_n": 0.1, "geometry": {**smooth, "type": "cone"}}, r"geometry.type must be 'grouser' or"),
        ({"wheel_load_n": 0.1, "geometry": {**smooth, "grouser_height_m": 0.003}}, r"contradict each other"),
        ({"wheel_load_n": 0.1, "geometry": {**smooth, "type": "mesh"}}, r"a mesh's geometry has grouser_count 0"),
        ({"wheel_load_n": 0.1, "geometry": {**record, "grouser_count": 4}}, r"a mesh's geometry has grouser_count"),
        ({"wheel_load_n": 0.1, "geometry": {**record, "type": "grouser"}}, r"mesh_sha256 belongs to a mesh"),
        ({"wheel_load_n": 0.1, "geometry": {**record, "mesh_sha256": "x" * 64}}, r"64 lower-case hexadecimal"),
    ):
        written(wheel)
        with pytest.raises(SceneError, match=r"terrain.toml: \[source.wheel\] .*" + problem):
            load_plan(scene)


def test_a_wheel_fit_refuses_the_runs_of_another_mesh(tmp_path):
    """--wheel-runs of a slip study whose mesh wheel was another mesh than the scene's: the wheel
    comparison leaves the mesh's file out (a path says where a mesh was, not what it held), so any mesh
    passed as this scene's wheel and the fit was recorded for it. The study records its wheel (a mesh's
    digest): another mesh is refused naming wheel.file; the same one passes; a study written before the
    wheel was recorded is not judged on it; a wheel record that is none is a damaged study."""
    import json

    from cosim.lab.scm_wheel import check_study_scene
    from cosim.scm_calibration import wheel_record
    from soil import GrouserWheel, MeshWheel
    from soil.errors import ArgumentError, DamagedFileError

    grousered = GrouserWheel(radius=0.025, width=0.02, grouser_count=8, grouser_height=0.003, grouser_thickness=0.002)
    MeshWheel(*grousered.to_mesh(arc_segments=64)).save(tmp_path / "grousered.obj")
    MeshWheel(*GrouserWheel(radius=0.028, width=0.02).to_mesh(arc_segments=64)).save(tmp_path / "smooth.obj")
    scene = write_tiny(tmp_path)
    plan = load_plan(scene, ['wheel={type = "mesh", file = "grousered.obj"}'])
    other = load_plan(scene, ['wheel={type = "mesh", file = "smooth.obj"}'])
    study = tmp_path / "study"
    study.mkdir()
    base = {
        "kind": "slip",
        "summary_rule": SUMMARY_RULE,
        "rows": [],
        "wheel_load": plan.wheel_load,
        "scene_toml": plan.scene.to_toml(),
    }
    for wheel, refused in ((wheel_record(other.wheel), True), (wheel_record(plan.wheel), False), (None, False)):
        (study / "study.json").write_text(json.dumps({**base, **({"wheel": wheel} if wheel else {})}))
        if refused:
            with pytest.raises(ArgumentError, match=r"another mesh \(wheel.file: its scaled vertices"):
                check_study_scene(str(study), plan)
        else:
            check_study_scene(str(study), plan)
    for damaged in ({**wheel_record(plan.wheel), "mesh_sha256": None}, "mesh"):
        (study / "study.json").write_text(json.dumps({**base, "wheel": damaged}))
        with pytest.raises(DamagedFileError, match=r"study.json: its wheel is no wheel record"):
            check_study_scene(str(study), plan)


def _findings(plan):
    from cosim.system import validity

    return validity(plan, 0.0)


def test_calibrate_scm_runs_the_dem_tests_and_writes_a_usable_file(tmp_path, capsys):
    """The command end to end on the tiny soil with tiny tests, two beds and specimens (its numbers are
    no soil's: plates of three grains, 4.5 mm deep; the file's provenance, its error bars and its use
    are what is checked)."""
    from cosim.cli import _error_bar_note, main

    scene = write_tiny(tmp_path)
    out = tmp_path / "terrain.toml"
    tiny = ["plate.widths=[0.0225,0.03]", "shear.normal_stresses=[25.0,50.0]", "shear.inertial_number=0.01"]
    tiny += ["shear.length=0.028", "shear.width=0.028", "shear.height=0.028", "shear.displacement=0.005"]
    tiny += ["plate.max_sinkage=0.0045"]
    options = ["--serial", "--replicas", "2", *[a for s in tiny for a in ("--set", s)]]
    assert main(["calibrate-scm", scene, "--out", str(out), *options]) == 0
    captured = capsys.readouterr()
    printed, printed_err = captured.out, captured.err  # each parameter with its unit
    assert "m/s^2" in printed
    reasons = read_calibration(str(out)).source["error_not_estimated"]
    for key in SOIL_KEYS:  # with its unit, and its error or the reason it has none
        line = next(line for line in printed.splitlines() if line.split()[:1] == [key])
        with_error = " +- " in line and line.endswith(f" {SOIL_UNITS[key]}")
        without = line.endswith(f" {SOIL_UNITS[key]}, no error bar: {reasons.get(key, 'not estimated')}")
        assert with_error != without, line
    assert "replicas' own fits' scatter / sqrt(R), R = 2" in printed  # what its +- holds
    assert "is not in it" in _error_bar_note({})  # and on one bed, what it leaves out
    calibration = read_calibration(str(out))
    assert set(calibration.parameters) == set(SOIL_KEYS) and all(
        math.isfinite(v) for v in calibration.parameters.values()
    )
    assert math.isfinite(calibration.standard_errors["n"]) and math.isfinite(calibration.standard_errors["janosi_k"])
    assert calibration.gravity == pytest.approx(1.625)
    source = calibration.source
    assert source["grain"]["radius_mean_m"] == 0.0035 and source["plate"]["widths_m"] == [0.0225, 0.03]
    assert source["shear"]["normal_stresses_pa"] == [25.0, 50.0] and source["dem"]["dt_s"] > 0
    assert source["dem"]["replicas"] == 2 and all(len(source["replica_fits"][k]) == 2 for k in SOIL_KEYS)
    # the tests' own quasi-static numbers, as `cosim lab plate` and `lab shear` judge them: each against its limit
    checks = source["lab_checks"]
    assert [(c["test"], c["name"]) for c in checks] == [
        ("plate", "plate speed v / sqrt(g d)"),
        ("plate", "inertial number I"),
        ("plate", "stiffness p / E*"),
        ("shear", "inertial number I"),
        ("shear", "stiffness p / E*"),
    ]
    assert all(c["ok"] == (c["value"] <= c["limit"] * (1 + 1e-9)) for c in checks)
    for key in SOIL_KEYS:  # the error bar holds the pooled fit's error
        fitted = source["standard_error_of_fit"][key]
        assert not math.isfinite(fitted) or calibration.standard_errors[key] >= fitted
    # the tiny tests' fits may fall outside SCM's range (a negative n): the command warns naming each, and
    # the scene's own keys for those make the file usable
    from cosim.scm_calibration import out_of_range

    outside = out_of_range(calibration.parameters)
    assert all(f"warning: {problem}" in printed_err for problem in outside.values())
    # and its lab tests out of their quasi-static range, named now (a scene's advise said them first)
    failed = [c for c in checks if not c["ok"]]
    named = [c["name"] if c["name"].startswith(c["test"]) else f"{c['test']} {c['name']}" for c in failed]
    assert all(f"quasi-static range: {n} = {c['value']:.3g}" in printed_err for n, c in zip(named, failed))
    rising = source["shear"]["still_rising"]  # each curve still climbing at its travel's end, named
    assert all(f"replica {r}, sigma {sigma:.4g} Pa" in printed_err for r, sigma in rising)
    assert printed_err.count("calibrate-scm: warning:") == len(outside) + len(failed) + bool(rising)
    fixed = dict(k_c=1.0, k_phi=1e3, n=0.8, cohesion=1.0, friction_angle_deg=30.0, janosi_k=1e-3, elastic_stiffness=1e5)
    bekker = {"k_c", "k_phi"} if "n" in outside else set()  # n is set with the k_c and k_phi fitted with it
    keys = "".join(f"{key} = {fixed[key]!r}\n" for key in sorted(set(outside) | bekker))
    scm = f'\n[terrain]\nmodel = "scm"\ncalibration = "{out.name}"\n{keys}'
    plan = load_plan(write_tiny(tmp_path, scm, "scm.toml"))
    assert plan.terrain.calibration_gravity == pytest.approx(1.625)


# -- the fit to the DEM's wheel runs (cosim.lab.scm_wheel) ----------------------------------------


def _wheel_plan():
    import os

    return load_plan(os.path.join(os.path.dirname(__file__), "..", "examples", "phobos_single_wheel.toml"))


def test_the_wheel_fit_recovers_known_parameters_from_held_wheel_forces():
    """Targets made by the SCM wheel at known parameters (2 slips, the main job's wheel; the soil's
    moduli scaled so it carries the wheel's load at slip 0.2; the forces at each slip taken as the
    DEM's) are fitted from a start 15 % to 60 % off: the fit returns the truth."""
    from cosim.lab.scm_wheel import FITTED, WheelTarget, fit_to_wheel, scm_wheel_forces

    plan = _wheel_plan()
    truth = dict(
        k_c=0.05, k_phi=4.0, n=0.4, cohesion=0.0, friction_angle_deg=28.0, janosi_k=1.0e-3, elastic_stiffness=2.0e4
    )
    truth["node_spacing"] = plan.wheel.width / 6  # a coarse grid: the fit's test, not the grid's (test_scm)
    sinkage = 0.006
    load, pull, torque = scm_wheel_forces(plan, truth, sinkage, 0.2)
    scale = plan.wheel_load / load  # the load the truth carries at this sinkage: k_phi, k_c scaled to it
    truth.update(k_c=truth["k_c"] * scale, k_phi=truth["k_phi"] * scale)
    targets = []
    for slip in (0.1, 0.5):
        w, dp, t = scm_wheel_forces(plan, truth, sinkage, slip)
        targets.append(WheelTarget(slip, sinkage, 1e-4, dp, 0.0, t, 0.0, 3, vertical_force=w))
    start = {**truth, "k_phi": 0.7 * truth["k_phi"], "n": 0.47, "friction_angle_deg": 23.0, "janosi_k": 1.6e-3}
    parameters, errors, report = fit_to_wheel(plan, targets, start)
    assert report["rms_residual"] < 0.02
    assert report["node_spacing_m"] == truth["node_spacing"]  # the grid the fit's wheel ran on, recorded
    assert {f"slips.{key}" for key in report["slips"][0]} - {"slips.run_steady_state"} <= set(report["units"])
    for key in FITTED:
        assert parameters[key] == pytest.approx(truth[key], rel=0.05), key
        assert math.isfinite(errors[key])
    assert parameters["k_c"] == truth["k_c"] and parameters["elastic_stiffness"] == truth["elastic_stiffness"]


WHEEL_TRUTH = dict(
    k_c=0.1, k_phi=8.0, n=0.5, cohesion=0.0, friction_angle_deg=40.0, janosi_k=5.0e-3, elastic_stiffness=6.0e4
)
"""A soil the closed-form runs below are made at."""


def _closed_form_runs(plan, soil, targets) -> list[dict]:
    """Stand-ins for the SCM runs of the DEM's protocol (scm_free_runs, seconds each: the SCM scenes' own
    tests run them): a smooth closed form in which each fitted parameter shows (sinkage from k_phi and
    n, DP and T from phi and K, as in Bekker and Janosi)."""
    load, rim = plan.wheel_load, plan.wheel.rim_radius
    out = []
    for t in targets:
        sinkage = 0.004 * (soil["k_phi"] / 8.0) ** -0.5 * (1.0 + 2.0 * t.slip * (soil["n"] - 0.3))
        thrust = math.tan(math.radians(soil["friction_angle_deg"])) * (
            1.0 - math.exp(-0.03 * t.slip / soil["janosi_k"])
        )
        out.append(
            {
                "sinkage": sinkage,
                "drawbar_pull": load * (thrust - 0.3),
                "driving_torque": load * rim * (thrust + 25.0 * sinkage),
            }
        )
    return out


def test_the_fit_to_the_runs_recovers_known_parameters_and_keeps_to_its_budget(tmp_path, monkeypatch):
    """The runs' stage on its own (the held-wheel stage left at its start: one evaluation), with the
    runs (scm_free_runs, seconds each: the SCM scenes' own tests run them) replaced by a smooth
    closed form in which each fitted parameter shows (sinkage from k_phi and n, DP and T from phi
    and K, as in Bekker and Janosi): targets made at known parameters are fitted from a start 30-60 %
    off back to them within 2 %, every residual within its tolerance; with a budget of 3 evaluations
    the fit stops there and returns the best soil it met (one more evaluation leaves the folder
    with that soil's runs)."""
    import dataclasses

    import cosim.lab.scm_wheel as scm_wheel
    from cosim.lab.scm_wheel import FITTED, WheelTarget, fit_to_wheel

    plan = _wheel_plan()
    load = plan.wheel_load
    truth = dict(WHEEL_TRUTH)
    calls = []

    def closed_form(plan, soil, targets, folder):
        calls.append(folder)
        return _closed_form_runs(plan, soil, targets)

    monkeypatch.setattr(scm_wheel, "scm_free_runs", closed_form)
    blank = WheelTarget(0.0, 0.0, 1e-4, 0.0, 1e-5, 0.0, 1e-7, 3, vertical_force=load)
    made = closed_form(plan, truth, [dataclasses.replace(blank, slip=s) for s in (0.1, 0.5)], None)
    targets = [
        dataclasses.replace(
            blank, slip=s, sinkage=r["sinkage"], drawbar_pull=r["drawbar_pull"], driving_torque=r["driving_torque"]
        )
        for s, r in zip((0.1, 0.5), made)
    ]
    start = {**truth, "k_phi": 4.0, "n": 0.7, "friction_angle_deg": 28.0, "janosi_k": 8.0e-3}
    parameters, errors, report = fit_to_wheel(plan, targets, start, max_evaluations=1, runs=str(tmp_path), max_runs=60)
    for key in FITTED:
        assert parameters[key] == pytest.approx(truth[key], rel=0.02), key
    assert report["rms_residual"] < 0.05 and report["run_evaluations"] <= 60
    # no grid in the start: the runs ran on the scene's default, the main job's grousers / 1.5
    assert report["node_spacing_m"] == pytest.approx(plan.wheel.shape.grouser_thickness / 1.5, rel=1e-12)
    assert report["geometry"]["rim_radius_m"] == plan.wheel.rim_radius and report["wheel_load_n"] == plan.wheel_load
    for row in report["slips"]:
        assert row["run_sinkage"] == pytest.approx(row["sinkage"], rel=0.15)
    _, _, first = fit_to_wheel(plan, targets, start, max_evaluations=1, runs=str(tmp_path), max_runs=1)
    calls.clear()
    _, _, short = fit_to_wheel(plan, targets, start, max_evaluations=1, runs=str(tmp_path), max_runs=3)
    assert short["run_evaluations"] == 3 and len(calls) == 4  # the budget, then the best soil's runs
    assert first["rms_residual"] > 1.0 and short["rms_residual"] <= first["rms_residual"]


def test_wheel_targets_read_a_slip_study_and_refuse_other_files(tmp_path):
    import json

    from cosim.lab.scm_wheel import wheel_targets
    from soil.errors import DamagedFileError

    rows = [
        {
            "slip_set": s,
            "steady": 2,
            "slip_mean": s,
            "sinkage_mean": 0.008,
            "sinkage_ci95": 5e-4,
            "drawbar_pull_mean": -3e-4,
            "drawbar_pull_ci95": 1e-4,
            "driving_torque_mean": 1.7e-5,
            "driving_torque_ci95": 1e-6,
        }
        for s in (0.1, 0.4)
    ]
    study = {
        "kind": "slip",
        "summary_rule": SUMMARY_RULE,
        "wheel_load": 1.7e-3,
        "rows": rows + [{"slip_set": 0.6, "steady": 0}],
    }
    (tmp_path / "study.json").write_text(json.dumps(study))
    targets = wheel_targets(str(tmp_path))
    assert [t.slip for t in targets] == [0.1, 0.4] and targets[0].sinkage == 0.008 and targets[1].replicas == 2
    assert targets[0].vertical_force == 1.7e-3
    (tmp_path / "study.json").write_text(json.dumps({"kind": "replicas", "rows": rows}))
    with pytest.raises(DamagedFileError, match="slip study"):  # another file: bad input, not a failed test
        wheel_targets(str(tmp_path))
    with pytest.raises(DamagedFileError, match="study.json"):
        wheel_targets(str(tmp_path / "nowhere"))
    # a table of runs summarized before the window rule of 2026-12-07 (no summary_rule): its means are of
    # another window than the fit's own SCM runs, and the fit would be fitted to them quietly
    from soil.errors import ArgumentError

    for stale in ({k: v for k, v in study.items() if k != "summary_rule"}, {**study, "summary_rule": 1}):
        (tmp_path / "study.json").write_text(json.dumps(stale))
        with pytest.raises(ArgumentError, match=r"study.json: a table of runs summarized under an older steady-window"):
            wheel_targets(str(tmp_path))


def test_calibrate_scm_from_wheel_writes_the_fit_and_refuses_misplaced_options(tmp_path, monkeypatch, capsys):
    """The command's plumbing (the fit itself: the test above): --from-wheel --lab --wheel-runs reads
    the lab file and the slip study, writes the fitted values with the lab's held ones and the
    wheel runs' record; --lab without --from-wheel, or a damaged --lab file, is bad input (exit 2) naming it."""
    import json
    import os

    import cosim.lab.scm_wheel as scm_wheel
    from cosim.cli import main
    from cosim.plan import load_plan

    scene = os.path.join(os.path.dirname(__file__), "..", "examples", "phobos_single_wheel.toml")
    lab_path = tmp_path / "lab.toml"
    lab = {k: 1.0 for k in SOIL_KEYS}
    write_calibration(str(lab_path), ScmCalibration(lab, {k: 0.1 for k in SOIL_KEYS}, 5.7e-3, {"scene": "x"}))
    rows = [{"slip_set": s, "steady": 2, "slip_mean": s, "sinkage_mean": 0.008} for s in (0.1, 0.4)]
    (tmp_path / "study").mkdir()
    load = load_plan(scene).wheel_load
    (tmp_path / "study" / "study.json").write_text(
        json.dumps({"kind": "slip", "summary_rule": SUMMARY_RULE, "wheel_load": load, "rows": rows})
    )
    seen = {}

    def fit(plan, targets, start, runs=None, max_runs=0):
        seen.update(slips=[t.slip for t in targets], start=start, runs=runs, max_runs=max_runs)
        report = {
            "slips": [],
            "rms_residual": 0.01,
            "evaluations": 3,
            "run_evaluations": 2,
            "wheel_load_n": plan.wheel_load,
        }
        return {**start, "k_phi": 2.5}, {k: 0.2 for k in SOIL_KEYS}, report

    monkeypatch.setattr(scm_wheel, "fit_to_wheel", fit)
    (tmp_path / "terrain").mkdir()
    out = tmp_path / "terrain" / "wheel.toml"
    args = ["--from-wheel", "--lab", str(lab_path), "--wheel-runs", str(tmp_path / "study")]
    assert main(["calibrate-scm", scene, "--out", str(out), *args]) == 0
    written = read_calibration(str(out))
    assert seen["slips"] == [0.1, 0.4] and seen["start"] == lab
    default_runs = tmp_path / "terrain" / "wheel_runs" / "wheel_scm"  # next to the file
    assert seen["max_runs"] == 30 and seen["runs"] == str(default_runs)
    assert written.parameters["k_phi"] == 2.5 and written.parameters["n"] == 1.0
    assert written.standard_errors["k_phi"] == 0.2 and written.standard_errors["k_c"] == 0.1  # held: the lab's
    # the record's paths are relative to the file's folder: the file and its runs move together
    assert written.source["wheel"]["runs"] == os.path.join("..", "study") and written.source["lab"] == os.path.join(
        "..", "lab.toml"
    )
    assert written.source["wheel"]["start_file"] == os.path.join("..", "lab.toml")
    # refitted into another folder, the wheel fit keeps its root lab file, its path made relative again
    assert (
        main(["calibrate-scm", scene, "--out", str(tmp_path / "refit.toml"), *args[:1], "--lab", str(out), *args[3:]])
        == 0
    )
    refit = read_calibration(str(tmp_path / "refit.toml"))
    assert refit.source["lab"] == "lab.toml" and refit.source["wheel"]["start_file"] == os.path.join(
        "terrain", "wheel.toml"
    )
    with open(out, "rb") as f:  # the file names the unit of every parameter (and of its standard error)
        assert tomllib.load(f)["units"] == {"gravity": "m/s^2", **{k: SOIL_UNITS[k] for k in SOIL_KEYS}}
    assert SOIL_UNITS["k_phi"] == "Pa m^(-n)" and SOIL_UNITS["friction_angle_deg"] == "deg"
    capsys.readouterr()
    before = lab_path.read_bytes()  # --out checked before the tests, not replaced at their end unasked
    assert main(["calibrate-scm", scene, "--out", str(lab_path)]) == 3 and lab_path.read_bytes() == before
    assert main(["calibrate-scm", scene, "--out", str(tmp_path)]) == 2
    assert "--out" in capsys.readouterr().err
    assert main(["calibrate-scm", scene, "--out", str(tmp_path / "x.toml"), "--lab", str(lab_path)]) == 2
    assert "--lab" in capsys.readouterr().err
    assert main(["calibrate-scm", scene, "--out", str(tmp_path / "x.toml"), *args, "--max-runs", "-1"]) == 2
    assert "--max-runs" in capsys.readouterr().err
    # --work the slip study it reads (or a folder in it), where the lab's tests run (no --lab): their
    # --overwrite emptied the study (a probe's)
    study = tmp_path / "study"
    files = sorted(p.relative_to(study) for p in study.rglob("*"))
    for work in (study, study / "runs"):
        command = ["calibrate-scm", scene, "--out", str(tmp_path / "x.toml"), "--from-wheel"]
        command += ["--wheel-runs", str(study), "--work", str(work)]
        assert main([*command, "--overwrite"]) == 2
        assert f"--work {str(work)!r} " in capsys.readouterr().err
    assert sorted(p.relative_to(study) for p in study.rglob("*")) == files
    damaged = tmp_path / "damaged.toml"
    damaged.write_text(lab_path.read_text()[:-40])  # a calibration file cut short: bad input, not a bug
    bad = ["--from-wheel", "--lab", str(damaged), "--wheel-runs", str(tmp_path / "study")]
    assert main(["calibrate-scm", scene, "--out", str(tmp_path / "y.toml"), *bad]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"cosim: error: {damaged}: ") and "unexpected" not in err, err
    assert not (tmp_path / "y.toml").exists()

    # a slip study of another wheel load, gravity or wheel: its drawbar pulls were divided by this
    # scene's load and the fit written without a word (exit 0, rms residual 762 tolerances)
    original = Path(scene).read_text()
    moon = original.replace('gravity = "phobos"', 'gravity = "moon"')
    for foreign, named in (
        ({"wheel_load": 2 * load}, "a wheel load of"),
        ({"wheel_load": load, "scene_toml": moon}, "gravity [0.0, 0.0, -1.62"),
        (
            {"wheel_load": load, "scene_toml": original.replace("radius = 0.03", "radius = 0.05")},
            "wheel.radius",
        ),
        (
            {"wheel_load": load, "scene_toml": original.replace("restitution = 0.3", "restitution = 0.9")},
            "soil.restitution",
        ),
        (
            {"wheel_load": load, "scene_toml": original.replace("omega = 0.12", "omega = 0.24")},
            "testbed.omega = 0.24",
        ),
    ):
        unchanged = Path(scene).read_text()
        assert all(w in unchanged for w in ('"phobos"', "radius = 0.03", "restitution = 0.3", "omega = 0.12"))
        (tmp_path / "study" / "study.json").write_text(
            json.dumps({"kind": "slip", "summary_rule": SUMMARY_RULE, "rows": rows, **foreign})
        )
        assert main(["calibrate-scm", scene, "--out", str(tmp_path / "z.toml"), *args]) == 2
        err = capsys.readouterr().err
        assert "--wheel-runs" in err and "its runs are not this scene's wheel" in err and named in err, err
    assert not (tmp_path / "z.toml").exists()
    # --out the file it reads (the scene, the lab file) is refused even with --overwrite: it was replaced
    for path in (scene_copy := tmp_path / "scene.toml", lab_path):
        scene_copy.write_text(Path(scene).read_text())
        before = path.read_bytes()
        assert main(["calibrate-scm", str(scene_copy), "--out", str(path), "--overwrite", *args]) == 2
        assert "the command reads; write to another file" in capsys.readouterr().err
        assert path.read_bytes() == before
    # what --from-wheel needs is checked before the lab's DEM tests (an hour), not after them
    work = tmp_path / "w_runs"
    for extra, named in (
        (["--slips", "0.1"], "--slips: give at least 2 slips"),
        (["--slips", "abc,0.2"], "--slips"),
        (["--slips", "0.1,1.5"], "--slips: 1.5 must be in (-1, 1)"),
        (["--slips", "0.1,0.1"], "given twice"),
    ):
        assert main(["calibrate-scm", scene, "--out", str(tmp_path / "w.toml"), "--from-wheel", *extra]) == 2
        assert named in capsys.readouterr().err and not work.exists()
    earth = tmp_path / "earth_lab.toml"
    write_calibration(str(earth), ScmCalibration(lab, {k: 0.1 for k in SOIL_KEYS}, 9.81, {"scene": "x"}))
    rover = os.path.join(os.path.dirname(scene), "phobos_rover_patch.toml")
    for command, named in (
        ([scene, "--from-wheel", "--start", str(earth)], "--start: calibrated at |g| = 9.81"),
        ([scene, "--from-wheel", "--lab", str(earth), "--wheel-runs", str(tmp_path / "study")], "--lab: calibrated"),
        ([rover, "--from-wheel"], "the scene has a [rover]"),
    ):
        assert main(["calibrate-scm", *command, "--out", str(tmp_path / "w.toml")]) == 2
        assert named in capsys.readouterr().err and not work.exists()


def test_a_calibration_file_is_written_whole_or_not_at_all(tmp_path, monkeypatch):
    """write_calibration makes its folder, and a write that fails half-way (a full disk, a kill) leaves
    the file that was there whole and no temporary beside it."""
    import cosim.scm_calibration as scm_calibration

    calibration = ScmCalibration({k: 1.0 for k in SOIL_KEYS}, {k: 0.1 for k in SOIL_KEYS}, 5.7e-3, {"scene": "x"})
    path = tmp_path / "new" / "folder" / "cal.toml"
    write_calibration(str(path), calibration)
    before = path.read_bytes()
    assert read_calibration(str(path)).parameters["k_phi"] == 1.0

    def dies_half_way(data, f):
        f.write(b"format = 1\n[scm]\nk_c = ")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(scm_calibration.tomli_w, "dump", dies_half_way)
    changed = ScmCalibration({k: 2.0 for k in SOIL_KEYS}, {k: 0.1 for k in SOIL_KEYS}, 5.7e-3, {"scene": "x"})
    with pytest.raises(OSError, match="cal.toml"):
        write_calibration(str(path), changed)
    assert path.read_bytes() == before and [p.name for p in path.parent.iterdir()] == ["cal.toml"]


BED_TRUTHS = [
    {**WHEEL_TRUTH, "k_phi": 6.0, "n": 0.45, "friction_angle_deg": 37.0, "janosi_k": 4.0e-3},
    {**WHEEL_TRUTH, "k_phi": 8.0, "n": 0.50, "friction_angle_deg": 40.0, "janosi_k": 5.0e-3},
    {**WHEEL_TRUTH, "k_phi": 11.0, "n": 0.56, "friction_angle_deg": 44.0, "janosi_k": 6.5e-3},
]
"""Three beds' soils, as far apart as the DEM's beds' wheel fits (k_phi and n moving together)."""


def _study_over_beds(folder, plan, truths, sinking: tuple = ()) -> None:
    """A slip study over beds (`cosim study slip --vary-bed`'s study.json) whose bed k's runs are the
    closed-form runs of truths[k]; the runs in `sinking` ((slip, bed) pairs) still sinking."""
    import json
    import os

    from cosim.lab.scm_wheel import WheelTarget

    slips = (0.1, 0.3, 0.5)
    blank = WheelTarget(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1, vertical_force=plan.wheel_load)
    made = [_closed_form_runs(plan, soil, [replace(blank, slip=s) for s in slips]) for soil in truths]
    runs, rows = [], []
    for i, slip in enumerate(slips):
        for k, bed in enumerate(made):
            state = "still sinking" if (slip, k) in sinking else "steady"
            out_dir = os.path.join(str(folder), f"slip_{slip:+.3f}", f"replica_{k:03d}")
            runs.append({"out_dir": out_dir, "ok": True, "summary": {**bed[i], "steady_state": state}})
        steady = [bed[i] for k, bed in enumerate(made) if (slip, k) not in sinking]
        row = {"slip_set": slip, "steady": len(steady), "slip_mean": slip}
        for key in ("sinkage", "drawbar_pull", "driving_torque"):
            values = [r[key] for r in steady]
            row[f"{key}_mean"] = float(np.mean(values))
            row[f"{key}_ci95"] = 1e-3 * abs(float(np.mean(values)))  # tight: the closed form has no noise
        rows.append(row)
    study = {
        "kind": "slip",
        "summary_rule": SUMMARY_RULE,
        "vary": "bed",
        "wheel_load": plan.wheel_load,
        "rows": rows,
        "runs": runs,
    }
    os.makedirs(str(folder), exist_ok=True)
    with open(os.path.join(str(folder), "study.json"), "w") as f:
        json.dump({**study, "averaged_states": ["steady"]}, f)


def test_each_beds_wheel_targets_are_its_own_runs_judged_by_the_studys_intervals(tmp_path):
    """bed_wheel_targets: bed k's targets are replica k's runs at each slip (a run still sinking left out
    of a table that averages steady runs only), with the study's 95 % half-intervals over the beds; a
    study whose replicas shared one bed gives none."""
    import json

    from cosim.lab.scm_wheel import bed_wheel_targets, wheel_targets

    plan = _wheel_plan()
    _study_over_beds(tmp_path / "study", plan, BED_TRUTHS, sinking={(0.3, 2)})
    pooled = wheel_targets(str(tmp_path / "study"))
    beds = bed_wheel_targets(str(tmp_path / "study"))
    assert [len(b) for b in beds] == [3, 3, 2]
    with open(tmp_path / "study" / "study.json") as f:
        runs = json.load(f)["runs"]
    assert beds[1][2].sinkage == runs[2 * 3 + 1]["summary"]["sinkage"]  # slip 0.5, replica 1
    assert beds[2][1].slip == pooled[2].slip and beds[2][1].drawbar_pull == runs[2 * 3 + 2]["summary"]["drawbar_pull"]
    assert beds[0][0].drawbar_pull_ci95 == pooled[0].drawbar_pull_ci95 and beds[0][0].replicas == 1
    assert np.mean([b[0].sinkage for b in beds]) == pytest.approx(pooled[0].sinkage, rel=1e-12)
    study = json.loads((tmp_path / "study" / "study.json").read_text())
    (tmp_path / "study" / "study.json").write_text(json.dumps({**study, "vary": "order"}))
    assert bed_wheel_targets(str(tmp_path / "study")) == []


def test_a_wheel_fit_over_beds_fits_each_bed_to_its_own_soil_and_its_error_holds_their_scatter(
    tmp_path, monkeypatch, capsys
):
    """calibrate-scm --from-wheel on a slip study over three beds whose runs are closed-form SCM runs of
    three known soils: the fit is repeated on each bed, which returns that bed's own soil within 2 %;
    each bed starts from the lab's own fit of that bed (its held keys); the file records the beds' fits
    with their units, gives each fitted key the larger of the fit's error and the beds' standard error
    of the mean, and bed_soils (what `cosim run --replicas 3 --vary-bed` runs on) gives bed k the wheel's
    fit on bed k and the lab's held keys of bed k. --start takes the fitted keys' start from another
    file (recorded); it is bad input without --from-wheel."""
    import os

    import cosim.lab.scm_wheel as scm_wheel
    from cosim.cli import main
    from cosim.lab.scm_wheel import FITTED
    from cosim.scm_calibration import bed_soils

    plan = _wheel_plan()
    started_from: dict[str, float] = {}

    def closed_form(plan, soil, targets, folder):
        started_from.setdefault(os.path.basename(folder), soil["k_c"])
        return _closed_form_runs(plan, soil, targets)

    monkeypatch.setattr(scm_wheel, "scm_free_runs", closed_form)
    # the held wheel's stage (real SCM, seconds per evaluation) gives nothing to fit: the runs' stage fits
    monkeypatch.setattr(scm_wheel, "scm_wheel_forces", lambda plan, soil, sinkage, slip: (plan.wheel_load, 0.0, 0.0))
    _study_over_beds(tmp_path / "study", plan, BED_TRUTHS)
    lab_k_c = [0.08, 0.1, 0.12]
    start = {**WHEEL_TRUTH, "k_phi": 9.0, "n": 0.48, "friction_angle_deg": 41.0, "janosi_k": 5.5e-3}
    lab = ScmCalibration(
        start,
        {k: 0.01 for k in SOIL_KEYS},
        plan.g,
        {"scene": "x", "replica_fits": {"k_c": lab_k_c, "k_phi": [1, 2, 3]}},
    )
    write_calibration(str(tmp_path / "lab.toml"), lab)
    out = tmp_path / "wheel.toml"
    scene = os.path.join(os.path.dirname(__file__), "..", "examples", "phobos_single_wheel.toml")
    args = ["--from-wheel", "--lab", str(tmp_path / "lab.toml"), "--wheel-runs", str(tmp_path / "study")]
    assert main(["calibrate-scm", scene, "--out", str(out), *args, "--serial", "--max-runs", "40"]) == 0
    assert "each bed alone (3 beds" in capsys.readouterr().out
    written = read_calibration(str(out))
    wheel = written.source["wheel"]
    for k, truth in enumerate(BED_TRUTHS):
        for key in FITTED:
            assert wheel["replica_fits"][key][k] == pytest.approx(truth[key], rel=0.02), (k, key)
    assert [started_from[f"bed_{k}"] for k in range(3)] == lab_k_c  # each bed held its own lab k_c
    for key in FITTED:
        between = np.std([t[key] for t in BED_TRUTHS], ddof=1) / math.sqrt(3)
        assert written.standard_errors[key] >= 0.9 * between, key
        assert written.standard_errors[key] >= wheel["standard_error_of_fit"][key]
    with open(out, "rb") as f:
        units = tomllib.load(f)["source"]["wheel"]["units"]
    assert units["replica_fits.k_phi"] == SOIL_UNITS["k_phi"] and units["standard_error_of_fit.n"] == "1"
    soils = bed_soils(written)
    assert len(soils) == 3
    for k, soil in enumerate(soils):
        assert soil["k_phi"] == wheel["replica_fits"]["k_phi"][k] and soil["k_c"] == lab_k_c[k]
    # --start: the fitted keys start from another file, the held ones stay the lab's
    other = ScmCalibration({**start, "k_phi": 7.0, "k_c": 5.0}, {k: 0.01 for k in SOIL_KEYS}, plan.g, {"scene": "y"})
    write_calibration(str(tmp_path / "former.toml"), other)
    again = ["--out", str(tmp_path / "w2.toml"), *args, "--serial", "--max-runs", "2", "--start"]
    assert main(["calibrate-scm", scene, *again, str(tmp_path / "former.toml")]) == 0
    refit = read_calibration(str(tmp_path / "w2.toml"))
    assert refit.source["wheel"]["start"]["k_phi"] == 7.0 and refit.parameters["k_c"] == start["k_c"]
    assert refit.source["wheel"]["start_file"] == "former.toml"
    capsys.readouterr()
    assert (
        main(["calibrate-scm", scene, "--out", str(tmp_path / "x.toml"), "--start", str(tmp_path / "former.toml")]) == 2
    )
    assert "--start" in capsys.readouterr().err


def test_the_plate_unloads_quasi_statically_and_its_stiffness_scales_with_the_gravity_twin(tmp_path):
    """The tiny soil at Phobos gravity and its Earth twin (cosim scale: E and pressures x s), a plate
    pushed at calibrate-scm's v / sqrt(g d) = 0.1, held, then raised: the rising plate's damping
    force shifts the branch by under 5 % of the held pressure (quasi-static: at the loading speed it
    was half of it on the Earth twin of the main job), the branch's upper half spans many DEM steps,
    and K_e / |g| agrees between the twins (DEM similarity; 35 % allows the two beds' own scatter,
    13 % measured)."""
    from cosim.lab import plate
    from cosim.lab.scene import load_lab_plan
    from cosim.similarity import write_gravity_twin

    phobos, _ = write_gravity_twin(write_tiny(tmp_path), "phobos", str(tmp_path / "phobos.toml"))
    earth, s = write_gravity_twin(phobos, "earth", str(tmp_path / "earth.toml"))
    stiffness = []
    for name, path in (("phobos", phobos), ("earth", earth)):
        plan = load_lab_plan(path, {"plate.widths": [0.0225, 0.03], "plate.speed_ratio": 0.1})
        _, (result,), _, _ = plate.press_plates(plan, str(tmp_path / name), [0.0225], 1, unload=True)
        z, p = result["unload_sinkage"], result["unload_pressure"]
        assert 0 < 1 - p[1] / p[0] < 0.05, (name, p[:3])
        assert (p >= 0.5 * p[0]).sum() >= 100, name
        assert np.all(np.diff(z) < 0), name  # the plate only rises
        stiffness.append(fit_unloading(z, p)["elastic_stiffness"] / plan.g)
    assert stiffness[0] > 0 and stiffness[1] == pytest.approx(stiffness[0], rel=0.35), (stiffness, s)


@pytest.mark.parametrize(
    "damage, named",
    [
        ({"rows": {"slip_set": 0.1}}, "'rows' must be a list of objects"),
        ({"rows": [[0.1, 2]]}, "'rows' must be a list of objects"),
        ({"rows": [{"slip_set": "0.1", "steady": 2}]}, "rows[0].slip_set must be a number"),
        ({"rows": [{"slip_set": 0.1, "steady": "two"}]}, "rows[0].steady must be a count"),
        ({"runs": "none"}, "'runs' must be a list of objects"),
        ({"averaged_states": "steady"}, "'averaged_states' must be a list of names"),
    ],
)
def test_a_slip_study_of_the_wrong_shape_is_named_for_the_wheel_fit(tmp_path, capsys, damage, named):
    """--wheel-runs of a study.json that is JSON of another shape (an edited or foreign file): exit 2 naming
    the file and the field, before any wheel test runs and nothing written (it was exit 1, a TypeError)."""
    import json
    import os

    from cosim.cli import main
    from cosim.plan import load_plan

    scene = os.path.join(os.path.dirname(__file__), "..", "examples", "phobos_single_wheel.toml")
    lab_path = tmp_path / "lab.toml"
    write_calibration(str(lab_path), ScmCalibration({k: 1.0 for k in SOIL_KEYS}, {}, 5.7e-3, {"scene": "x"}))
    rows = [{"slip_set": s, "steady": 2, "slip_mean": s, "sinkage_mean": 0.008} for s in (0.1, 0.4)]
    (tmp_path / "study").mkdir()
    study = {
        "kind": "slip",
        "summary_rule": SUMMARY_RULE,
        "wheel_load": load_plan(scene).wheel_load,
        "rows": rows,
        **damage,
    }
    (tmp_path / "study" / "study.json").write_text(json.dumps(study))
    args = ["--from-wheel", "--lab", str(lab_path), "--wheel-runs", str(tmp_path / "study")]
    assert main(["calibrate-scm", scene, "--out", str(tmp_path / "wheel.toml"), *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cosim: error:") and "study.json" in err and named in err, err
    assert not (tmp_path / "wheel.toml").exists()


def test_a_stop_asked_for_during_one_beds_wheel_fit_stops_every_bed(monkeypatch):
    """A bed whose fit fails is a result (the others' fits stand), but Ctrl-C or SIGTERM in a serial fit's
    SCM runs is a stop of the whole calibration, not a failed bed followed by the next bed's fit."""
    import os

    import cosim.lab.scm_wheel as scm_wheel
    from cosim.plan import load_plan
    from cosim.runner import RunInterrupted

    plan = load_plan(os.path.join(os.path.dirname(__file__), "..", "examples", "phobos_single_wheel.toml"))
    fits = []

    def fit(plan, targets, start, runs=None, max_runs=0):
        fits.append(start["k"])
        raise RunInterrupted("stopped by SIGTERM", "SIGTERM") if start["k"] == 0 else ValueError("no bracket")

    monkeypatch.setattr(scm_wheel, "fit_to_wheel", fit)
    targets = [[object()], [object()]]
    with pytest.raises(RunInterrupted):
        scm_wheel.fit_beds(plan, targets, [{"k": 0}, {"k": 1}], runs=None)
    assert fits == [0]  # bed 1 not fitted after the stop
    failed = scm_wheel.fit_beds(plan, targets[1:], [{"k": 1}], runs=None)
    assert failed[0]["ok"] is False and "ValueError: no bracket" in failed[0]["error"]


def test_a_scene_given_as_a_calibration_is_named_as_none(tmp_path):
    """A scene given as --lab or terrain.calibration said "format None, this version reads format 1"."""
    scene = write_tiny(tmp_path)
    with pytest.raises(CalibrationError, match=r"not an SCM calibration file \(no `format` key"):
        read_calibration(scene)


def test_the_error_bar_note_gives_each_replica_count_its_own_t_multiplier():
    """Keys fitted over 3 replicas: t(0.975, 2) = 4.303. A key with one converged replica has no interval
    between replicas (the note printed t with 1 degree of freedom, 12.7, for every key)."""
    from cosim.cli import _error_bar_note

    note = _error_bar_note({"n": [1.0, 1.1, 0.9], "k_phi": [5.0, 5.5, 4.0], "k_c": [5.0, math.nan, math.nan]})
    assert "R = 1/3" in note and "+- 4.3 of these at R = 3" in note and "12.7" not in note, note
    assert "R < 2: the pooled fit's error alone, no interval between replicas" in note, note
    assert "R < 2" not in _error_bar_note({"n": [1.0, 1.1], "k_phi": [5.0, 5.5]})


def test_the_shipped_calibrations_name_their_lab_and_start_files_beside_them():
    """A shipped calibration records the files it came from relative to itself ([source] lab, [source.wheel]
    start_file): each is a shipped file beside it, not the folder a fit happened to be written from (the
    Phobos wheel fit of 2026-12-07 named '../code3/examples/terrain/...'); its DEM runs are a user's
    runs/ folder (runs/ of the README's commands, from the repository's root)."""
    folder = Path(__file__).resolve().parent.parent / "examples" / "terrain"
    files = sorted(folder.glob("*.toml"))
    assert len(files) >= 4
    fits = 0
    for path in files:
        source = read_calibration(str(path)).source
        wheel = source.get("wheel", {})
        for key, named in (("lab", source.get("lab")), ("wheel.start_file", wheel.get("start_file"))):
            if named is not None:
                assert (folder / named).resolve().parent == folder and (folder / named).is_file(), (path.name, key)
        if wheel:  # a wheel fit records all three
            assert {"start_file", "runs"} <= set(wheel) and isinstance(source.get("lab"), str), path.name
            assert Path(wheel["runs"]).parts[:3] == ("..", "..", "runs"), (path.name, wheel["runs"])
            fits += 1
    assert fits == 2  # the Phobos and the Earth twin wheel fits
