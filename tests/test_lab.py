"""The soil lab (cosim.lab): scene checks, the measurements on known shapes, the direct shear
test against the physics of friction, the plate test's Bekker fit.

The DEM runs here are small (a few hundred grains, under a second simulated); where the
outcome is chaotic the assertions are bounds far outside the scatter measured over
replicas (numbers in each docstring). Wall forces adding up to the weight and the load are
tests/test_boundaries.py's."""

import json
import math
import os

import numpy as np
import pytest

from cosim.cli import main
from cosim.lab import bekker_fit, measure_heap, mohr_coulomb
from cosim.lab.plate import bekker_pressure, plate_test
from cosim.lab.plate import check as plate_check
from cosim.lab.scene import lab_scene_from_text, load_lab_plan, resolve_lab
from cosim.lab.shear import shear_test
from cosim.scene import SceneError

# -- scenes --------------------------------------------------------------------------------


def test_a_wheel_scene_is_a_lab_scene_and_measures_its_own_soil():
    """`cosim lab repose examples/phobos_single_wheel.toml` measures that scene's soil and grains."""
    from cosim.plan import load_plan

    lab = load_lab_plan("examples/phobos_single_wheel.toml", ['scene.device="cpu"'], needs_gravity=True)
    wheel = load_plan("examples/phobos_single_wheel.toml", ['scene.device="cpu"'])
    assert lab.soil == wheel.soil_material
    assert lab.radius_mean == wheel.bed.spec.radius_mean and lab.g == pytest.approx(5.7e-3)
    assert lab.dt == pytest.approx(wheel.dt)


def test_the_plate_inertial_number_is_taken_where_the_fitted_pressure_is_lowest():
    """I = (v / b) d / sqrt(p / rho) is largest at the lowest pressure: it was taken at the largest pressure
    measured, and passed tests too fast at the start of the fitted range. Now at the lowest fitted Bekker
    pressure over the points the fit uses (z >= fit_from, p > 0: the shallowest, or with n < 0 the deepest),
    the largest over the plates; where the fit gives none above 0 (a failed fit), the lowest measured there."""
    from cosim.lab.plate import bekker_pressure, quasi_static_numbers

    plan = load_lab_plan("examples/phobos_lab.toml", ['scene.device="cpu"'], needs_gravity=True)
    speed, fit_from, largest = 1e-4, 1e-3, 5.0
    z = np.linspace(0.0, 0.01, 41)  # 0.25 mm apart: fit_from is a point

    def inertial(fit, curves) -> dict:
        (number,) = [
            n for n in quasi_static_numbers(plan, speed, curves, largest, fit, fit_from) if "inertial" in n["name"]
        ]
        return number

    def at(width, pressure) -> float:
        return speed / width * plan.diameter / math.sqrt(pressure / plan.soil.density)

    fit = {"k": math.nan, "k_c": 0.05, "k_phi": 6.0, "n": 0.5}
    curves = [(b, z, bekker_pressure(fit, b, z)) for b in (0.02, 0.03)]
    expected = max(at(b, float(bekker_pressure(fit, b, fit_from))) for b in (0.02, 0.03))
    number = inertial(fit, curves)
    assert number["value"] == pytest.approx(expected, rel=1e-12) and "fitted" in number["meaning"]
    assert expected > 2 * at(0.02, largest)  # what the old number understated (4.3 x here)
    falling = {**fit, "n": -0.5}  # a pressure falling with depth: lowest at the deepest point
    expected = max(at(b, float(bekker_pressure(falling, b, z.max()))) for b in (0.02, 0.03))
    assert inertial(falling, curves)["value"] == pytest.approx(expected, rel=1e-12)
    failed = {"k": math.nan, "k_c": math.nan, "k_phi": math.nan, "n": math.nan}
    lowest = min(float(p[(z >= fit_from) & (p > 0)].min()) for _, _, p in curves[:1])
    number = inertial(failed, curves[:1])
    assert number["value"] == pytest.approx(at(0.02, lowest), rel=1e-12) and "measured" in number["meaning"]


@pytest.mark.parametrize(
    "text, named",
    [
        ("[repose]\ntube_widht = 0.02", "repose.tube_widht: unknown key"),
        ("[repose]\nlift_speed = 0.01\nlift_ratio = 0.1", "repose.lift_speed: give lift_speed or lift_ratio"),
        ("[repose]\nfit_range = [0.9, 0.1]", "repose.fit_range"),
        ("[shear]\nnormal_stresses = [100.0, -5.0]", "shear.normal_stresses"),
        ("[shear]\ninertial_number = nan", "shear.inertial_number"),
        ("[plate]\nwidths = [0.02, 0.02]", "plate.widths: each width once"),
        ("[shear]\nnormal_stresses = [1000.0, 1000.0]", "shear.normal_stresses: each stress once"),
        ("[lab]\nreplicas = 0", "lab.replicas"),
        ("[repose]\nfill_height = true", "repose.fill_height: must be a number, not true or false"),
        ("[shear]\nnormal_stresses = [100.0, 1e300]", "shear.normal_stresses: [1]: must be 0 or of magnitude"),
    ],
)
def test_bad_lab_keys_are_named(text, named):
    with pytest.raises(SceneError) as error:
        lab_scene_from_text(text)
    assert named in str(error.value)


@pytest.mark.parametrize(
    "gravity, named",
    [(0.0, "needs gravity"), ("[1.0, 0.0, -9.81]", "along -Z"), ("[0.0, 0.0, 9.81]", "must point down")],
)
def test_gravity_must_point_down(gravity, named):
    scene = lab_scene_from_text(f"[scene]\ngravity = {gravity}\ndevice = 'cpu'")
    with pytest.raises(SceneError, match=named):
        resolve_lab(scene, needs_gravity=True, test="repose")


def test_a_step_far_below_the_scenes_scale_is_refused():
    """A stiffness of 1e29 Pa makes the Rayleigh step 4e-16 s: a repose phase of 410 s would never end."""
    scene = lab_scene_from_text("[scene]\ngravity = 'phobos'\ndevice = 'cpu'\n[soil]\nyoungs_modulus = 1e29")
    with pytest.raises(SceneError, match=r"run.dt_factor: .* DEM steps .*soil.youngs_modulus"):
        resolve_lab(scene, needs_gravity=True, test="repose")
    resolve_lab(lab_scene_from_text("[scene]\ngravity = 'phobos'\ndevice = 'cpu'"), needs_gravity=True)


def test_lab_commands_fail_cleanly_on_bad_input(tmp_path, capsys):
    assert main(["lab", "repose", str(tmp_path / "missing.toml")]) == 2
    scene = tmp_path / "lab.toml"
    scene.write_text("[scene]\ndevice = 'cpu'\n")
    for command in (["lab", "repose"], ["calibrate-scm"]):  # named by the option given, not lab.replicas
        arguments = [
            *command,
            str(scene),
            "--replicas",
            "0",
            *(["--out", str(tmp_path / "x.toml")] * (len(command) == 1)),
        ]
        assert main(arguments) == 2
        err = capsys.readouterr().err
        assert "--replicas: specimens (and beds) per test, at least 1, got 0" in err and "lab.replicas" not in err, err
    assert main(["calibrate", str(scene), "--target", "angle=30", "--vary", "soil.rolling_friction=0:0.3"]) == 2
    assert "unknown target 'angle'" in capsys.readouterr().err
    assert main(["calibrate", str(scene), "--target", "repose=30", "--vary", "soil.rolling_friction=0.3:0"]) == 2
    assert "LOW < HIGH" in capsys.readouterr().err
    # targets and keys the loop cannot use are named before anything runs (true was read as 1 deg, a count
    # failed at the optimiser's first fractional value, a wheel key was varied without effect)
    rolling = ["--vary", "soil.rolling_friction=0:0.3"]
    for argv, named in (
        (["--target", "repose=true", *rolling], "must be a finite number"),
        (["--target", "cohesion=-5", *rolling], "a cohesion is >= 0 Pa"),
        (["--target", "repose=30", "--target", "repose=31", *rolling], "repose is given twice"),
        (["--target", "repose=30", *rolling, "--tolerance", "repose=1", "--tolerance", "repose=2"], "given twice"),
        (["--target", "repose=30", *rolling, "--vary", "soil.rolling_friction,soil.cohesion=0:1"], "varied twice"),
        (["--target", "repose=30", "--vary", "wheel.radius=0.01:0.1"], "not a key the repose test reads"),
        (["--target", "friction=25", "--vary", "repose.lift_ratio=0.1:1"], "not a key the shear test reads"),
        (["--target", "repose=30", "--vary", "lab.replicas=1:5"], "lab.replicas: takes no real number"),
        (["--target", "cohesion=5", "--vary", "soil.rolling_friction,soil.cohesion=0:1"], "must share a unit"),
    ):
        out = tmp_path / "refused"
        assert main(["calibrate", str(scene), "--serial", "--out", str(out), *argv]) == 2, argv
        assert named in capsys.readouterr().err, argv
        assert not out.exists()
    # a range whose end is no valid scene is refused before anything runs
    assert (
        main(
            [
                "calibrate",
                str(scene),
                "--serial",
                "--out",
                str(tmp_path / "out"),
                "--target",
                "repose=30",
                "--vary",
                "soil.slip_angle_deg=10:40",
            ]
        )
        == 2
    )
    assert "slip_angle_deg" in capsys.readouterr().err
    # a Bekker fit from below the deepest sinkage has no point to fit (it ended with k and n nan, exit 0)
    plate = ["--set", "plate.fit_from=0.05", "--set", "plate.max_sinkage=0.01", "--out", str(tmp_path / "plate")]
    assert main(["lab", "plate", str(scene), "--serial", *plate]) == 2
    assert "plate.fit_from: (0.05 m) must be below the deepest sinkage plate.max_sinkage" in capsys.readouterr().err
    assert not (tmp_path / "plate").exists()


@pytest.mark.parametrize(
    "test, key, value, named",
    [
        ("repose", "repose.fill_height", "1e4", "repose.tube_width, repose.fill_height, bed.radius_mean"),
        ("shear", "shear.length", "1e4", "shear.length, shear.width, shear.height, bed.radius_mean"),
        ("plate", "bed.length", "1e4", "bed.length, bed.width, bed.depth, bed.radius_mean"),
    ],
)
def test_a_lab_specimen_too_large_for_this_machine_is_refused_by_its_keys(tmp_path, capsys, test, key, value, named):
    """A lab specimen had no memory check, where `cosim run` has one: 69 million grains in the repose
    tube were allocated until a MemoryError (exit 1, each replica in turn), nanometre grains asked
    numpy for 2.6 PiB (exit 1). Refused with the estimate and the keys that size it (exit 2), before
    the folder is made."""
    scene = tmp_path / "lab.toml"
    scene.write_text("[scene]\ndevice = 'cpu'\n")
    out = tmp_path / "out"
    assert main(["lab", test, str(scene), "--serial", "--out", str(out), "--set", f"{key}={value}"]) == 2
    err = capsys.readouterr().err
    assert "a lab specimen of" in err and "does not fit this machine" in err and named in err, err
    assert not out.exists()


@pytest.mark.parametrize("command", ["lab shear", "run", "advise"])
def test_grains_whose_constants_overflow_the_precision_are_named(tmp_path, capsys, command):
    """Nanometre grains: their inverse inertia (7e41 SI) overflowed float32 to inf, the first steps made
    a NaN state, and the run or every lab replica "diverged" (numpy's overflow warning the only hint).
    Named by key, with what to change, before anything is made; in double they can be stepped."""
    from soil import Material, SoilBuilder
    from soil.builder import grain_range_problem
    from soil.errors import SoilInputError

    scene = tmp_path / "lab.toml"
    scene.write_text("[scene]\ndevice = 'cpu'\n")
    out = tmp_path / "out"
    tiny = ["--set", "bed.radius_mean=1e-9"]
    argv = command.split() + [str(scene)] + (["--out", str(out)] if command != "advise" else []) + tiny
    assert main(argv + (["--serial"] if command.startswith("lab") else [])) == 2
    err = capsys.readouterr().err
    assert "bed.radius_mean: grains of radius 8e-10 m have an inverse inertia of 7.01e+41" in err, err
    assert "beyond mixed precision's range (3.4e+38)" in err and "precision 'double'" in err, err
    assert not out.exists()
    # the bound itself: 1/I = 1 / (0.4 m r^2) against float32's largest number, float64 far above
    for radius, single in ((1e-9, False), (1e-7, True)):
        inertia = 0.4 * 2650 * 4 / 3 * np.pi * radius**3 * radius**2
        assert (1 / inertia < float(np.finfo(np.float32).max)) == single
        assert (grain_range_problem(radius, 2650, "single") is None) == single
        assert grain_range_problem(radius, 2650, "double") is None
    builder = SoilBuilder()
    builder.add_material(Material(density=2650.0))
    builder.add_particles(np.zeros((1, 3)), 1e-9)
    with pytest.raises(SoilInputError, match="inverse inertia"):
        builder.finalize(device="cpu", precision="single")


# -- measurements on known shapes -------------------------------------------------------------


@pytest.mark.parametrize("angle", [15.0, 30.0, 40.0])
def test_heap_angle_of_a_cone(angle):
    """Grains whose tops lie on a cone of slope `angle`, on a one-grain layer around it: the
    profile measurement returns the cone's angle (the cells' tops are sampled at their inner
    edge, the same offset for every bin, so the slope is exact up to the grid)."""
    r = 1e-3
    spacing = 0.7 * r
    coords = np.arange(-0.09, 0.09, spacing)
    x, y = np.meshgrid(coords, coords, indexing="ij")
    rho = np.hypot(x, y)
    top = np.maximum(0.02 - math.tan(math.radians(angle)) * rho, 2 * r)
    keep = rho < 0.085
    positions = np.stack([x[keep], y[keep], top[keep] - r], axis=1)
    heap = measure_heap(positions, np.full(len(positions), r), (0.0, 0.0), 0.0, 2 * r)
    assert heap["angle"] == pytest.approx(angle, abs=0.5)
    assert heap["angle_profile"] == pytest.approx(angle, abs=0.5)
    assert heap["height"] == pytest.approx(0.02, abs=2 * r) and heap["toe"] == pytest.approx(2 * r, abs=0.1 * r)


def test_a_failed_replica_is_printed_with_the_values_it_is_left_out_of():
    """A lab test whose replica diverged printed "2 replicas" and no note: the failure was a log line
    and summary.json's "failed" only. Each failed replica is now a "!" line of the printed summary."""
    from cosim.cli import lab_lines

    stats = {"n": 2, "mean": 31.0, "ci95": 1.5, "min": 30.0, "max": 32.0}
    summary = {
        "test": "repose",
        "repose_angle_deg": stats,
        "notes": [],
        "failed": [
            {"label": "replica 2", "error": "Traceback ...\nSimulationDiverged: simulation diverged at t = 1 s"}
        ],
    }
    lines = lab_lines(summary)
    assert "2 replicas" in lines[0]
    assert (
        lines[-1]
        == "! replica 2 failed, left out of the values above: SimulationDiverged: simulation diverged at t = 1 s"
    )


def test_a_shear_line_through_two_points_is_printed_without_an_error_bar_and_says_why():
    """Two normal stresses, one replica: the Mohr-Coulomb line passes through both points (R^2 1), and the
    summary printed its angle and cohesion bare, as if exact; one stress with three replicas printed
    "+- nan". Each value carries an error bar only where the fit has one, and a '!' line says why not."""
    from cosim.cli import lab_lines

    for sigma, tau in (([500.0, 1000.0], [300.0, 480.0]), ([500.0] * 3, [300.0, 310.0, 290.0])):
        fit = mohr_coulomb(np.array(sigma), np.array(tau))
        lines = lab_lines({"test": "shear", "peak": fit, "residual": fit, "notes": []})
        assert not any("nan" in line for line in lines if "+-" in line), lines
        assert any(line.startswith("! no error bar on the Mohr-Coulomb line") for line in lines), lines
    fit = mohr_coulomb(np.array([500.0, 1000.0, 1500.0]), np.array([300.0, 480.0, 690.0]))
    lines = lab_lines({"test": "shear", "peak": fit, "residual": fit, "notes": []})
    assert "(s.e.)" in lines[0] and not any(line.startswith("! no error bar") for line in lines), lines


def test_mohr_coulomb_fit_recovers_a_known_line():
    sigma = np.array([100.0, 200.0, 400.0, 100.0, 200.0, 400.0])
    tau = 50.0 + sigma * math.tan(math.radians(28.0)) + np.array([2.0, -2.0, 1.0, -2.0, 2.0, -1.0])
    fit = mohr_coulomb(sigma, tau)
    assert fit["friction_angle_deg"] == pytest.approx(28.0, abs=0.3)
    assert fit["cohesion_pa"] == pytest.approx(50.0, abs=3.0)
    assert fit["points"] == 6 and fit["cohesion_se_pa"] > 0
    one_stress = mohr_coulomb([100.0, 100.0], [50.0, 60.0])
    assert math.isnan(one_stress["friction_angle_deg"])  # no line through one stress ...
    assert one_stress["friction_angle_origin_deg"] == pytest.approx(math.degrees(math.atan(0.55)))  # ... but c = 0


def test_bekker_fit_recovers_known_parameters():
    """Curves p = (k_c / b + k_phi) z^n of two plates with 3 % noise: the fit returns k_c,
    k_phi and n; one plate alone gives k = k_c / b + k_phi and n."""
    rng = np.random.default_rng(3)
    k_c, k_phi, n = 2.0e3, 4.0e5, 0.8
    z = np.linspace(0.0, 0.02, 200)
    curves = [(b, z, (k_c / b + k_phi) * z**n * (1 + 0.03 * rng.standard_normal(len(z)))) for b in (0.05, 0.1)]
    fit = bekker_fit(curves, fit_from=1e-3)
    assert fit["k_c"] == pytest.approx(k_c, rel=0.15)
    assert fit["k_phi"] == pytest.approx(k_phi, rel=0.05)
    assert fit["n"] == pytest.approx(n, abs=0.02)
    assert fit["r_squared"] > 0.99
    single = bekker_fit(curves[:1], fit_from=1e-3)
    assert math.isnan(single["k_c"])
    assert single["k"] == pytest.approx(k_c / 0.05 + k_phi, rel=0.05) and single["n"] == pytest.approx(n, abs=0.02)
    np.testing.assert_allclose(bekker_pressure(single, 0.05, z[1:]), (k_c / 0.05 + k_phi) * z[1:] ** n, rtol=0.08)


# -- direct shear -------------------------------------------------------------------------------

SHEAR = """
[scene]
name = "shear"
gravity = "earth"
precision = "double"
device = "cpu"
[soil]
youngs_modulus = 5.0e6
poisson_ratio = 0.3
restitution = 0.3
stick_speed = 1000.0
[bed]
radius_mean = 0.002
settle_ke_ratio = 3e-3
[shear]
length = 0.028
width = 0.028
height = 0.02
displacement = 0.006
normal_stresses = [1000.0, 2000.0]
inertial_number = 0.01
"""


def shear_angle(tmp_path, name, friction_deg, rolling, law="", replicas=1) -> dict:
    text = SHEAR + f"[soil.law]\n{law}\n" if law else SHEAR
    scene = lab_scene_from_text(
        text,
        overrides={
            "soil.stick_angle_deg": friction_deg,
            "soil.slip_angle_deg": friction_deg,
            "soil.rolling_friction": rolling,
            "lab.replicas": replicas,
        },
    )
    return shear_test(resolve_lab(scene), str(tmp_path / name))


def test_shear_friction_angle_rises_with_grain_friction_and_rolling_resistance(tmp_path):
    """Direct shear of one box (7 x 7 x 5 grains) at 1 and 2 kPa: the residual friction angle of
    a cohesionless soil (tau = sigma tan(phi) through the origin) is small for frictionless
    spheres and rises with the grains' friction and again with rolling resistance.

    Measured over single specimens (new fills and summation orders, before and after the
    neighbour list): 9-12 deg frictionless (a periodic cell without walls gives 6 deg: Peyneau
    & Roux, Phys. Rev. E 78, 011307, 2008; the frames and the short displacement of a box this
    small add dilation), 23-28 deg with friction 0.5, 31-43 deg (mean 37, sd 4) with rolling
    friction 0.3 as well. One specimen's scatter is as large as the rolling step, so the two
    frictional cases fit two specimens each; the bounds leave about two scatters. The shear
    force on the upper half comes back on the lower half (the grains' momentum barely changes):
    within 10 % over the residual window."""
    frictionless = shear_angle(tmp_path, "mu0", 0.0, 0.0, "friction = false")
    frictional = shear_angle(tmp_path, "mu05", math.degrees(math.atan(0.5)), 0.0, replicas=2)
    rolling = shear_angle(tmp_path, "mu05_roll", math.degrees(math.atan(0.5)), 0.3, replicas=2)
    angles = [s["residual"]["friction_angle_origin_deg"] for s in (frictionless, frictional, rolling)]
    assert 0.0 <= angles[0] < 18.0
    assert angles[1] > angles[0] + 5.0
    assert angles[2] > angles[1] + 4.0
    for name, summary, specimens in (("mu0", frictionless, 1), ("mu05", frictional, 2), ("mu05_roll", rolling, 2)):
        assert len(summary["points"]) == 2 * specimens and all(p["consolidated"] for p in summary["points"])
        curves = np.genfromtxt(tmp_path / name / "shear.csv", delimiter=",", names=True)
        late = curves["displacement_m"] >= 0.5 * curves["displacement_m"].max()
        upper, lower = curves["shear_stress_Pa"][late].mean(), curves["shear_stress_lower_half_Pa"][late].mean()
        assert lower == pytest.approx(upper, rel=0.1)
    assert frictional["quasi_static"][0]["value"] == pytest.approx(0.01)


# -- pressure-sinkage -----------------------------------------------------------------------------

PLATE = """
[scene]
name = "plate"
gravity = "moon"
precision = "double"
device = "cpu"
[soil]
youngs_modulus = 1.0e6
poisson_ratio = 0.3
restitution = 0.3
stick_angle_deg = 26.565
slip_angle_deg = 26.565
rolling_friction = 0.1
[bed]
length = 0.048
width = 0.048
depth = 0.04
radius_mean = 0.002
settle_ke_ratio = 3e-3
[plate]
widths = [0.012, 0.016]
speed_ratio = 0.2
"""


def test_plate_bekker_fit_reproduces_its_curves(tmp_path):
    """Two square plates (3 and 4 grain diameters) pushed 7 mm into a lunar-gravity bed: the
    pressure rises with sinkage, and Bekker's law fitted to both curves at once follows each
    of them: over every third of the sinkage range the fitted mean pressure is within 25 % of
    the measured one. A few grains under a plate make the curve jump as the grains under it give
    way (R^2 0.29-0.76 between machines and laws): the fit follows the trend, which is what the
    bound checks, not the jumps. Measured: within 6 % with the former stick/slip switch; with the
    passive switch the soil holds longer before a grain gives way and the 16 mm plate's curve
    jumps from 487 to 876 Pa between its first two thirds, the fit within 0.88-1.19 of them."""
    summary = plate_test(
        resolve_lab(lab_scene_from_text(PLATE, overrides={"lab.replicas": 2})), str(tmp_path / "plate")
    )
    fit = summary["bekker"]
    assert 0.2 < fit["n"] < 1.5 and fit["k_phi"] > 0
    data = np.genfromtxt(tmp_path / "plate" / "plate.csv", delimiter=",", names=True)
    assert data.dtype.names[:5] == ("replica_1", "plate_width_m", "time_s", "sinkage_m", "pressure_Pa")
    fit_from = summary["geometry"]["fit_from_m"]
    for width in (0.012, 0.016):
        mine = (data["plate_width_m"] == width) & (data["sinkage_m"] >= fit_from)
        z, p = data["sinkage_m"][mine], data["pressure_Pa"][mine]
        edges = np.linspace(z.min(), z.max(), 4)
        means = []
        for low, high in zip(edges[:-1], edges[1:]):
            part = (z >= low) & (z <= high)
            means.append(p[part].mean())
            assert bekker_pressure(fit, width, z[part]).mean() == pytest.approx(p[part].mean(), rel=0.25)
        assert means[2] > 1.1 * means[0]  # deeper is harder (pooled thirds measured 1.19-1.6 x)
    assert (tmp_path / "plate" / "plate.png").is_file() and (tmp_path / "plate" / "summary.json").is_file()
    # the report says its plates are only 3 and 4 grains wide: the jumps above are theirs
    for width, across in ((0.012, 3), (0.016, 4)):
        assert any(
            note.startswith(f"plate {width:.3g} m is {across:.3g} grain diameters wide") for note in summary["notes"]
        )
    units = json.loads((tmp_path / "plate" / "summary.json").read_text())["units"]
    assert {f"bekker.{k}" for k in fit if k != "per_width"} <= set(units) and units["bekker.rms_pa"] == "Pa"
    assert units["gravity"] == "m/s^2" and units["bekker.k_phi"] == "N/m^(n+2)"  # p = (k_c / b + k_phi) z^n
    # a saved bed is reused only for the soil and gravity it was settled with
    bed = tmp_path / "plate" / "beds" / "replica_0.h5"
    other = lab_scene_from_text(PLATE, overrides={"bed.bed_file": str(bed), "soil.rolling_friction": 0.2})
    with pytest.raises(SceneError, match="bed.bed_file: the bed's grains are not the scene's"):
        plate_check(resolve_lab(other))
    plate_check(resolve_lab(lab_scene_from_text(PLATE, overrides={"bed.bed_file": str(bed)})))


SMALL_HEAP = (
    "[scene]\ngravity = 'earth'\nprecision = 'double'\ndevice = 'cpu'\n[soil]\nyoungs_modulus = 1e5\n"
    "[bed]\nradius_mean = 0.002\n[lab]\nmax_time_factor = 2.0\n"
    "[repose]\ntube_width = 0.02\nfill_height = 0.01\nlift_ratio = 0.3\nbase_width = 0.04\n"
)
"""A heap too small to measure (its phases cut short): seconds a replica."""


def test_cosim_lab_repose_writes_its_report(tmp_path, capsys):
    """The command end to end on a heap too small to measure (phases cut short): every file written,
    the CSV headers with units, the notes saying what was cut short, and what its phases may cost said
    before they ran. No replica measured an angle: exit 6 and a line saying there is no result (it
    printed "angle of repose nan deg" and exited 0)."""
    scene = tmp_path / "heap.toml"
    scene.write_text(SMALL_HEAP)
    out = tmp_path / "out"
    assert main(["lab", "repose", str(scene), "--serial", "--out", str(out)]) == 6
    captured = capsys.readouterr()
    printed = captured.out
    assert "angle of repose" in printed and "lift speed v / sqrt(g d) = 0.3" in printed
    assert "hit lab.max_time_factor" in printed
    assert json.loads((out / "summary.json").read_text())["repose_angle_deg"]["n"] == 0
    assert "! no replica measured the angle of repose: the test gives no result" in printed
    # what its phases may cost was said before they ran (a lab test settled without a word on it)
    from cosim.lab.common import phase_cost
    from cosim.lab.scene import load_lab_plan

    plan = load_lab_plan(str(scene), [], needs_gravity=True, test="repose")
    longest = plan.scene.lab.max_time_factor * math.sqrt(plan.diameter / plan.g)
    assert f"at most {longest:.3g} s" in phase_cost(plan) and f"{longest / plan.dt:.3g} DEM steps" in phase_cost(plan)
    assert f"{out}: {phase_cost(plan)}" in captured.err
    for name in ("scene.toml", "summary.json", "repose.csv", "repose_grains.csv", "repose_history.csv", "repose.png"):
        assert (out / name).is_file(), name
    assert json.loads((out / "summary.json").read_text())["units"] == {"gravity": "m/s^2"}
    assert (out / "repose.csv").read_text().splitlines()[0] == (
        "replica [1],radius [m],surface_height [m],sectors_filled [1]"
    )
    assert main(["lab", "repose", str(scene), "--serial", "--out", str(out)]) == 3  # nothing is overwritten


def test_a_shear_curve_still_rising_at_the_end_of_its_travel_is_told_from_one_that_peaked():
    """A curve still rising at the end of the box's travel gave its last value as the peak, unflagged: the
    friction angle from it is a lower bound and its second half no residual. Janosi-Hanamoto curves
    tau = tau_max (1 - exp(-u / K)) with a drop after a peak at 40 % of the travel; without one and still
    rising at the end (K near the travel, K = travel / 3), or a smooth peak just beyond the travel; and
    levelled off (K = travel / 25, noisy or not: its largest value is at the end, its second half at it)."""
    from cosim.lab.shear import strength

    u = np.linspace(0.0, 0.005, 400)
    sigma = np.full_like(u, 100.0)
    rising = 60.0 * (1 - np.exp(-u / 0.004))  # K near the travel: still climbing at its end
    peaked = np.where(u < 0.002, 60.0 * (1 - np.exp(-u / 0.0003)), 0.0)
    peaked = np.where(u < 0.002, peaked, 60.0 * (1 - np.exp(-0.002 / 0.0003)) - 4000.0 * (u - 0.002))
    assert strength(u, rising, sigma)["rising_at_end"]
    assert strength(u, 60.0 * (1 - np.exp(-u / (0.005 / 3))), sigma)["rising_at_end"]  # 95 % of its plateau
    beyond = 60.0 * (1 - ((u - 0.0055) / 0.0055) ** 2)  # a smooth peak at 1.1 x the travel: flat at its end
    assert strength(u, beyond, sigma)["rising_at_end"]
    levelled = 60.0 * (1 - np.exp(-u / 0.0002))  # a loose soil's plateau, still creeping up: no peak to miss
    noise = np.random.default_rng(7).normal(0.0, 0.6, u.size)  # 1 % of the plateau
    assert (
        not strength(u, levelled, sigma)["rising_at_end"] and not strength(u, levelled + noise, sigma)["rising_at_end"]
    )

    # the shapes of DEM boxes' curves (their means over each tenth of the travel [Pa], 40 samples a tenth): the
    # main job's lab example at 20 Pa, a plateau whose largest value fell at 92 % of the travel (the first
    # rule's false alarm); a short travel's climb whose last tenth dips below the one before; a curve that
    # peaked at 14 % and recovers a little
    def shaped(tenths):
        return np.repeat(tenths, 40) + np.random.default_rng(3).normal(0.0, 0.02 * max(tenths), 400)

    plateau = shaped([5.47, 10.4, 11.6, 9.97, 11.0, 12.4, 12.4, 12.0, 11.8, 12.1])
    climb = shaped([27.8, 25.6, 36.4, 39.2, 45.4, 53.0, 61.8, 69.4, 80.0, 77.9])
    recovering = shaped([37.3, 67.5, 67.8, 38.7, 24.1, 12.7, 16.8, 17.5, 17.9, 18.8])
    assert [strength(u, c, sigma)["rising_at_end"] for c in (plateau, climb, recovering)] == [False, True, False]
    fit = strength(u, peaked, sigma)
    assert not fit["rising_at_end"] and fit["peak_displacement"] == pytest.approx(0.002, abs=2e-4)


def test_a_lab_test_without_its_value_says_so_and_one_normal_stress_still_measures():
    """What makes a lab test a result: a repose angle from some replica, a peak friction angle (one normal
    stress gives no Mohr-Coulomb line but its angle through the origin, docs/lab.md), Bekker's n."""
    from cosim.cli import lab_result_missing

    nan = math.nan
    assert lab_result_missing({"test": "repose", "repose_angle_deg": {"n": 0}}) == "angle of repose"
    assert lab_result_missing({"test": "repose", "repose_angle_deg": {"n": 2, "mean": 31.0}}) is None
    one_stress = {"friction_angle_deg": nan, "friction_angle_origin_deg": 33.0}
    assert lab_result_missing({"test": "shear", "peak": one_stress}) is None
    none = {"friction_angle_deg": nan, "friction_angle_origin_deg": nan}
    assert lab_result_missing({"test": "shear", "peak": none}) == "peak friction angle"
    assert lab_result_missing({"test": "plate", "bekker": {"n": nan}}) == "Bekker exponent n"
    assert lab_result_missing({"test": "plate", "bekker": {"n": 1.1}}) is None


def test_an_interrupted_lab_test_reports_the_replicas_that_finished(tmp_path, capsys, monkeypatch):
    """Ctrl-C (or SIGTERM) after some replicas had finished left only scene.toml: hours of heaps lost.
    The finished replicas' report is written, its note saying over how many, then the command stops as
    asked (exit 130)."""
    import cosim.lab.repose as repose

    run_replica = repose.run_replica

    def stopped_at_the_third(plan, replica=0):
        if replica == 2:
            raise KeyboardInterrupt
        return run_replica(plan, replica)

    monkeypatch.setattr(repose, "run_replica", stopped_at_the_third)
    scene = tmp_path / "heap.toml"
    scene.write_text(SMALL_HEAP.replace("[lab]\n", "[lab]\nreplicas = 4\n"))
    out = tmp_path / "out"
    assert main(["lab", "repose", str(scene), "--serial", "--out", str(out)]) == 130
    summary = json.loads((out / "summary.json").read_text())
    assert [r["replica"] for r in summary["replicas"]] == [0, 1]  # the two heaps that finished, measured
    assert "interrupted after 2 of 4 replicas: the values are over these only" in summary["notes"]
    assert {int(line.split(",")[0]) for line in (out / "repose.csv").read_text().splitlines()[1:]} == {0, 1}


def test_calibrate_that_measured_nothing_writes_no_calibrated_scene(tmp_path, capsys, monkeypatch):
    """Every evaluation measured nan (heaps too small to measure): the "best" was the first by the
    order nan compares in, and its values were written as calibrated.toml. Now no calibrated scene,
    the message says why, exit 6 (no result), and the evaluations' table is kept."""
    import importlib

    lab_calibrate = importlib.import_module("cosim.lab.calibrate")
    calls = []

    def nothing(plan, tests, folder, run_on):
        calls.append(folder)
        return {"repose": math.nan}

    monkeypatch.setattr(lab_calibrate, "measure", nothing)
    scene = tmp_path / "lab.toml"
    scene.write_text("[scene]\ndevice = 'cpu'\n")
    out = tmp_path / "out"
    args = ["--serial", "--out", str(out), "--target", "repose=30", "--vary", "soil.rolling_friction=0:0.3"]
    assert main(["calibrate", str(scene), *args, "--max-evaluations", "3"]) == 6
    printed = capsys.readouterr().out
    assert "no evaluation measured repose" in printed and "calibrated scene: none written" in printed, printed
    assert len(calls) == 2 and not (out / "calibrated.toml").exists()  # brentq's two ends, both nan
    summary = json.loads((out / "summary.json").read_text(), parse_constant=lambda c: math.nan)
    assert summary["calibrated_scene"] is None and not summary["converged"]
    assert (out / "history.csv").is_file()


def test_a_calibrated_scene_says_whether_it_met_its_targets(tmp_path, capsys, monkeypatch):
    """The target lies outside what the range measures (35 and 40 deg at its ends, target 30): the best
    evaluation was written as calibrated.toml with nothing in it saying that it missed, and the progress
    lines gave the values without units. The file's header says it missed, by what; it still loads."""
    import importlib

    import tomllib

    lab_calibrate = importlib.import_module("cosim.lab.calibrate")
    measured = iter([35.0, 40.0])
    monkeypatch.setattr(lab_calibrate, "measure", lambda plan, tests, folder, run_on: {"repose": next(measured)})
    scene = tmp_path / "lab.toml"
    scene.write_text("[scene]\ndevice = 'cpu'\n")
    out = tmp_path / "out"
    args = ["--serial", "--out", str(out), "--target", "repose=30", "--vary", "soil.rolling_friction=0:0.3"]
    assert main(["calibrate", str(scene), *args]) == 6
    text = (out / "calibrated.toml").read_text()
    assert text.startswith("# cosim calibrate: evaluation 1 of 2, NOT within its targets: the target repose = 30 ")
    assert "# repose measured 35 deg, target 30 +- 1 deg\n" in text
    assert tomllib.loads(text)["soil"]["rolling_friction"] == 0.0  # the best end, a scene as before
    logged = capsys.readouterr().err  # the progress lines
    assert "soil.rolling_friction = 0.3 1" in logged and "repose 40 deg (target 30 deg)" in logged, logged


def test_calibrate_on_one_shear_value_reports_that_value_only(tmp_path, capsys, monkeypatch):
    """A shear test gives four values (peak and residual friction and cohesion): calibrating on one of them
    printed its evaluations, then ended in KeyError 'friction_residual' (exit 1, no calibrated scene named),
    the others carried into the summary without a target, tolerance or unit. Only the targets are
    measured, printed and kept; every number of the summary has its unit."""
    import importlib

    import cosim.lab.shear

    lab_calibrate = importlib.import_module("cosim.lab.calibrate")
    angles = iter([25.0, 35.0, 30.2])

    def shear(plan, folder, overwrite=False, **kwargs):  # a shear test's summary, as shear_test writes it
        angle = next(angles, 30.0)
        return {
            "peak": {"friction_angle_deg": angle, "cohesion_pa": 80.0},
            "residual": {"friction_angle_deg": angle - 4.0, "cohesion_pa": 20.0},
        }

    monkeypatch.setattr(cosim.lab.shear, "shear_test", shear)
    scene = tmp_path / "lab.toml"
    scene.write_text("[scene]\ndevice = 'cpu'\n")
    out = tmp_path / "out"
    args = ["--serial", "--out", str(out), "--target", "friction=30", "--vary", "soil.rolling_friction=0:0.3"]
    assert main(["calibrate", str(scene), *args]) == 0
    printed = capsys.readouterr().out
    assert "friction measured" in printed and "30.2 deg (target 30 +- 1 deg)" in printed, printed
    assert "calibrated scene: " in printed and "residual" not in printed
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["best"]["measured"]) == {"friction"} and summary["units"]["friction"] == "deg"
    assert lab_calibrate.TARGETS["friction_residual"].test == "shear"  # the value the shear test also gives


def test_an_interrupted_calibrate_reports_its_finished_evaluations(tmp_path, capsys, monkeypatch):
    """SIGTERM during the third evaluation: the two finished ones were lost with the report (only each
    evaluation's own folder kept its tests). Now summary.json and history.csv hold them, no calibrated
    scene is written (an unfinished search's best is no calibration), and the command exits 143."""
    import importlib

    lab_calibrate = importlib.import_module("cosim.lab.calibrate")
    calls = []

    def measured(plan, tests, folder, run_on):
        calls.append(folder)
        if len(calls) == 3:
            raise KeyboardInterrupt("SIGTERM")
        return {"repose": 20.0 + 10.0 * len(calls)}  # 30 at the first end, 40 at the second: 32 lies between

    monkeypatch.setattr(lab_calibrate, "measure", measured)
    scene = tmp_path / "lab.toml"
    scene.write_text("[scene]\ndevice = 'cpu'\n")
    out = tmp_path / "out"
    args = ["--serial", "--out", str(out), "--target", "repose=32", "--vary", "soil.rolling_friction=0:0.3"]
    assert main(["calibrate", str(scene), *args]) == 143
    assert len(calls) == 3 and not (out / "calibrated.toml").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["message"].startswith("interrupted after 2 finished evaluations") and not summary["converged"]
    assert [row["evaluation"] for row in summary["evaluations"]] == [1, 2] and summary["calibrated_scene"] is None
    assert len((out / "history.csv").read_text().splitlines()) == 1 + 2  # its header and the two rows


def test_calibrate_prints_each_value_with_its_unit(tmp_path, capsys, monkeypatch):
    """`cosim calibrate` prints the best values and the measured targets with the units of the summary
    (cosim.lab.calibrate: a parameter's from the scene key's documentation, a target's from TARGETS)."""
    import importlib

    lab_calibrate = importlib.import_module("cosim.lab.calibrate")  # the module (cosim.lab.calibrate: its function)

    def calibrated(plan, out, targets, parameters, tolerances, **kwargs):
        names = [p.name for p in parameters]
        return {
            "method": "brentq",
            "message": "every target is within its tolerance",
            "converged": True,
            "targets": targets,
            "tolerances": tolerances,
            "best": {"values": dict.fromkeys(names, 0.1), "measured": {"repose": 30.4}},
            "evaluations": [{}],
            "calibrated_scene": str(tmp_path / "calibrated.toml"),
            "units": {**{name: lab_calibrate.TARGETS[name].unit for name in targets}, **dict.fromkeys(names, "1")},
        }

    monkeypatch.setattr(lab_calibrate, "calibrate", calibrated)
    scene = tmp_path / "lab.toml"
    scene.write_text("[scene]\ndevice = 'cpu'\ngravity = [0.0, 0.0, -1.625]\n")
    args = ["--serial", "--out", str(tmp_path / "out"), "--target", "repose=30"]
    args += ["--vary", "soil.rolling_friction=0:0.3"]
    assert main(["calibrate", str(scene), *args]) == 0
    printed = capsys.readouterr().out
    assert "soil.rolling_friction" in printed and "0.1 1\n" in printed
    assert "repose measured" in printed and "30.4 deg (target 30 +- 1 deg)" in printed


def test_an_interrupted_plate_test_notes_only_the_plates_that_pushed():
    """An interrupted plate test's notes named every plate of the scene (3 grains wide, walls near it),
    also those that never ran: only the plates that pushed are named, and the note says it was interrupted."""
    from cosim.lab.plate import plate_notes

    plan = resolve_lab(lab_scene_from_text(PLATE, overrides={"lab.replicas": 2}))
    ready = [{"replica": 0, "settled": True}, {"replica": 1, "settled": True}]
    surface = 0.03
    everything = plate_notes(plan, ready, [{"width": 0.012}, {"width": 0.016}] * 2, 4, None, surface)
    assert any(n.startswith("plate 0.012 m is 3 grain") for n in everything)
    assert any(n.startswith("plate 0.016 m is 4 grain") for n in everything)
    cut = plate_notes(plan, ready, [{"width": 0.012}], 4, KeyboardInterrupt(), surface)
    assert any(n.startswith("plate 0.012 m is 3 grain") for n in cut)
    assert not [n for n in cut if "0.016" in n], cut
    assert "interrupted after 1 of 4 plate tests: the values are over these only" in cut


def test_a_plate_test_with_fewer_replicas_leaves_no_bed_of_the_earlier_one(tmp_path, monkeypatch):
    """`lab plate --replicas 2`, then `--replicas 1 --overwrite`: the second settled bed 0 again and left
    the first's bed 1 (beds/replica_1.h5) as if it were its own; every bed is settled anew, so the ones
    past the replicas asked are removed, other files left."""
    from cosim.lab import common, plate

    folder = tmp_path / "beds"
    folder.mkdir()
    for name in ("replica_0.h5", "replica_1.h5", "replica_12.h5", "notes.txt"):
        (folder / name).write_text("an earlier test's")
    settled = []
    monkeypatch.setattr(common, "map_tasks", lambda plan, run, tasks, *a: settled.extend(tasks) or [])
    monkeypatch.setattr(common, "map_until_stopped", lambda *a: ([], None))
    with pytest.raises(common.LabFailed):  # no bed settled (none is, here)
        plate.press_plates(None, str(tmp_path), [0.02], 1)
    assert sorted(os.listdir(folder)) == ["notes.txt", "replica_0.h5"]
    assert [task["bed"] for task in settled] == [str(folder / "replica_0.h5")]  # settled again
