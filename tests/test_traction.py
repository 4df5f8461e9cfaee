"""Traction numbers a user can trust: validity advice on a known-bad scene, error bars over replicas
of a real run, a drawbar-pull/slip curve that rises with slip, and the gravity twin."""

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from cosim import advice, metrics
from cosim.cli import main
from cosim.plan import load_plan
from cosim.scene import scene_from_text
from cosim.study import METRIC_UNITS
from helpers import write_tiny

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"

# The single-wheel scene that was once the main job: 4 cm wheel at 0.25 rad/s on Phobos on a
# bed of 3 mm grains 14.5 mm deep once settled. Every fault below was found by hand in it.
OLD_MAIN = """
[scene]
gravity = "phobos"
[soil]
youngs_modulus = 2.0e5
[bed]
length = 0.24
width = 0.08
depth = 0.03
radius_mean = 3.0e-3
[wheel]
radius = 0.04
width = 0.03
grouser_count = 12
grouser_height = 0.004
grouser_thickness = 0.002
[testbed]
mass = 6.0
omega = 0.25
[run]
duration = 5.0
dt_factor = 0.2
substeps = 10
"""


def test_advice_names_the_faults_of_a_bad_wheel_test():
    """Fr = 0.25^2 x 0.044 / 0.0057 = 0.48 (the wheel hops), 5 grains across the wheel, a settled bed of
    14.5 mm = 0.33 wheel radii, 2.4 grain diameters under the grouser tips before the wheel sinks at all."""
    from cosim.plan import resolve

    plan = resolve(scene_from_text(OLD_MAIN))
    findings = {f.check: f for f in advice.check(plan, surface_height=0.0145)}
    assert findings["froude"].value == pytest.approx(0.25**2 * plan.wheel.outer_radius / 5.7e-3)
    assert not findings["froude"].ok and "testbed.omega" in findings["froude"].message
    assert not findings["grains_across"].ok and findings["grains_across"].value == pytest.approx(5.0)
    assert not findings["bed_depth"].ok and findings["bed_depth"].value == pytest.approx(
        0.0145 / plan.wheel.outer_radius
    )
    assert not findings["floor_clearance"].ok and findings["floor_clearance"].value == pytest.approx(
        (0.0145 - 0.0) / 0.006, rel=1e-3
    )
    assert findings["overlap"].ok  # E = 2e5 Pa was adapted to milli-g (eq. 10): that part was right
    assert advice.verdict(list(findings.values())).startswith("out of range: froude")
    for finding in findings.values():  # every warning names the setting to change
        assert finding.setting and (finding.ok or finding.setting.split(",")[0].split(".")[0] in finding.message)


def test_replicas_give_error_bars_on_a_real_run(tmp_path, tiny_bed, capsys):
    """`cosim run --replicas 3`: three summation orders of the same scene at an imposed slip of
    0.3 (after landing, about one wheel turn over the grousers' pitch, 0.8 s). Measured: every
    replica steady, with drawbar pulls 0.008, -0.001, 0.010 N; a replica can miss the steady
    state (its window would start late), so two of three must reach it. The statistics are
    those of the steady replicas' summaries, and the scatter is real (the runs differ)."""
    scene = write_tiny(tmp_path)
    out = tmp_path / "replicas"
    settings = [
        f'bed.bed_file="{tiny_bed}"',
        "run.duration=0.8",
        'testbed.mode="slip"',
        "testbed.slip=0.3",
        "testbed.omega=2.0",
    ]
    code = main(
        ["run", scene, "--out", str(out), "--replicas", "3", "--serial"]
        + [arg for setting in settings for arg in ("--set", setting)]
    )
    text = capsys.readouterr().out
    report = json.loads((out / "ensemble.json").read_text())
    assert report["units"] == {name: METRIC_UNITS[name] for name in report["stats"]["metrics"]}  # each metric's
    steady = [r["summary"] for r in report["results"] if r["summary"]["steady_state"] == "steady"]
    assert len(steady) >= 2, [r["summary"]["steady_state"] for r in report["results"]]
    assert code == 0 or len(steady) < 3, text  # a replica that is not steady makes the run unsteady
    for metric in ("drawbar_pull", "sinkage"):
        values = np.array([s[metric] for s in steady])
        stats = report["stats"]["metrics"][metric]
        assert stats["n"] == len(steady) and stats["mean"] == pytest.approx(values.mean())
        assert stats["std"] == pytest.approx(values.std(ddof=1)) and stats["std"] > 0  # the orders do differ
        t = {2: 12.706, 3: 4.303}[len(steady)]  # Student t(0.975, n - 1)
        assert stats["ci95"] == pytest.approx(t * stats["std"] / math.sqrt(len(steady)), rel=1e-3)
    assert all(s["slip"] == pytest.approx(0.3, abs=1e-9) for s in steady)
    assert "drawbar_pull" in text and "95% CI" in text
    header = (out / "ensemble.csv").read_text().splitlines()[0]
    assert header.startswith("metric,unit,n,mean,std,ci95")
    units = {line.split(",")[0]: line.split(",")[1] for line in (out / "ensemble.csv").read_text().splitlines()[1:]}
    assert units["drawbar_pull"] == "N" and units["sinkage"] == "m" and units["slip"] == "1"


def test_drawbar_pull_rises_with_slip(tmp_path, tiny_bed, capsys):
    """`cosim study slip`: after landing, the wheel is driven at slip 0.05 and 0.6; the soil's forward
    force on the wheel rises with slip (terramechanics: more shear displacement, more thrust),
    by more than the within-run standard errors. The drive is 1 s: at slip 0.6 the wheel digs in
    for about half of it (measured with the passive stick/slip switch, one run each: DP -0.038 +-
    0.012 N at 0.05 and 0.133 +- 0.022 N at 0.6 over 1 s; after 0.5 s the rise was still hidden)."""
    scene = write_tiny(tmp_path)
    out = tmp_path / "slip"
    main(
        [
            "study",
            "slip",
            scene,
            "--slips",
            "0.05,0.6",
            "--replicas",
            "1",
            "--serial",
            "--out",
            str(out),
            "--set",
            f'bed.bed_file="{tiny_bed}"',
            "--set",
            "run.duration=1.0",
        ]
    )
    report = json.loads((out / "study.json").read_text())
    low, high = (r["summary"] for r in report["runs"])
    assert report["units"]["drawbar_pull_mean"] == "N" and report["units"]["wheel_load"] == "N"
    assert low["slip"] == pytest.approx(0.05, abs=1e-9) and high["slip"] == pytest.approx(0.6, abs=1e-9)
    rise = high["drawbar_pull"] - low["drawbar_pull"]
    assert rise > 3 * math.hypot(low["drawbar_pull_sem"], high["drawbar_pull_sem"]), (low, high)
    assert high["driving_torque"] > low["driving_torque"]
    assert (out / "plots" / "dbp_slip.png").is_file() and "DP/W" in capsys.readouterr().out


def test_the_gravity_twin_scales_every_derived_quantity_exactly(tmp_path):
    """Moon -> Earth: s = 9.80665 / 1.625; E and loads x s, speeds x sqrt(s), times / sqrt(s); the
    dimensionless numbers (Froude, steps per contact, overlap ratio, ...) are the same."""
    from cosim.similarity import write_gravity_twin

    scene = write_tiny(tmp_path)
    twin_path, s = write_gravity_twin(scene, "earth", str(tmp_path / "twin.toml"))
    assert s == pytest.approx(9.80665 / 1.625, rel=1e-15)
    a, b = load_plan(scene), load_plan(twin_path)
    assert np.linalg.norm(b.gravity) == pytest.approx(9.80665, rel=1e-14)
    assert b.soil_material.youngs_modulus == pytest.approx(a.soil_material.youngs_modulus * s, rel=1e-14)
    assert b.wheel.material.youngs_modulus == pytest.approx(a.wheel.material.youngs_modulus * s, rel=1e-14)
    assert b.testbed.omega == pytest.approx(a.testbed.omega * math.sqrt(s), rel=1e-14)
    # the tiny scene gives no stick speed: the default 0.02 sqrt(|g| d) scales by itself
    for material_a, material_b in ((a.soil_material, b.soil_material), (a.wheel.material, b.wheel.material)):
        assert material_a.stick_speed == pytest.approx(0.02 * math.sqrt(1.625 * 2 * 0.0035), rel=1e-12)
        assert material_b.stick_speed == pytest.approx(material_a.stick_speed * math.sqrt(s), rel=1e-12)
    for name in ("dt", "macro_step"):
        assert getattr(b, name) == pytest.approx(getattr(a, name) / math.sqrt(s), rel=1e-12), name
    assert (b.substeps, b.drive_steps, b.landing.max_steps, b.landing.hold_steps) == (
        a.substeps,
        a.drive_steps,
        a.landing.max_steps,
        a.landing.hold_steps,
    )
    assert b.landing.speed_limit == pytest.approx(a.landing.speed_limit * math.sqrt(s), rel=1e-12)
    assert b.froude_number == pytest.approx(a.froude_number, rel=1e-12)
    for fa, fb in zip(advice.check(a), advice.check(b)):
        assert fb.value == pytest.approx(fa.value, rel=1e-9), fa.check
    assert b.bed.bed_file is None  # a bed settled at the other gravity cannot serve the twin
    with pytest.raises(Exception, match="exists"):
        write_gravity_twin(scene, "earth", twin_path)


def test_the_gravity_twin_scales_the_pid_steps_and_the_other_terrains_keys(tmp_path):
    """The twin left the PID's dt_max and dt_min and every SCM and analytic terrain key as they were: its
    PID took 44 x the critical step at Earth, and its SCM soil, 1720 x too soft, sank 62 m where the
    original sinks 11 mm. Times / sqrt(s), pressures and forces x s, damping x sqrt(s): the PID's bound
    against the critical step, Bekker's closed-form sinkage of the wheel (theory: z0 depends on W / k)
    and the analytic ground's static sinkage W / k are the original's."""
    from cosim.scm_soil import bekker_wheel_sinkage, scm_settings
    from cosim.similarity import write_gravity_twin
    from cosim.system import validity

    pid = write_tiny(tmp_path, "", "pid.toml")
    text = Path(pid).read_text().replace("[run]\n", '[run]\nstep_control = "pid"\ndt_max = 2.0e-4\ndt_min = 1.0e-7\n')
    open(pid, "w").write(text)
    twin, s = write_gravity_twin(pid, "earth", str(tmp_path / "pid_earth.toml"))
    a, b = load_plan(pid), load_plan(twin)
    assert (b.dt_max, b.dt_min) == pytest.approx((a.dt_max / math.sqrt(s), a.dt_min / math.sqrt(s)), rel=1e-12)
    for fa, fb in zip(advice.check(a), advice.check(b)):
        assert (fb.check, fb.ok) == (fa.check, fa.ok) and fb.value == pytest.approx(fa.value, rel=1e-9), fa.check

    scm = write_tiny(
        tmp_path,
        '\n[terrain]\nmodel = "scm"\nk_c = 2.0e3\nk_phi = 8.0e5\nn = 1.1\ncohesion = 50.0\nfriction_angle_deg = 30.0\n'
        "janosi_k = 0.002\nelastic_stiffness = 2.0e7\npressure_damping = 40.0\ntime_step = 5.0e-4\n",
        "scm.toml",
    )
    twin, s = write_gravity_twin(scm, "earth", str(tmp_path / "scm_earth.toml"))
    a, b = load_plan(scm), load_plan(twin)
    pa, pb = scm_settings(a, [0], 0.0).parameters, scm_settings(b, [0], 0.0).parameters
    for key in ("k_c", "k_phi", "cohesion", "elastic_stiffness"):
        assert getattr(pb, key) == pytest.approx(getattr(pa, key) * s, rel=1e-12), key
    for key in ("n", "friction_angle", "janosi_k", "node_spacing"):
        assert getattr(pb, key) == getattr(pa, key), key
    assert pb.damping == pytest.approx(pa.damping * math.sqrt(s), rel=1e-12) and pa.damping == 40.0
    assert dict(b.terrain.parameters)["time_step"] == pytest.approx(5.0e-4 / math.sqrt(s), rel=1e-12)
    wheel = a.wheel
    sunk = [bekker_wheel_sinkage(p, plan.wheel_load, wheel.outer_radius, wheel.width) for p, plan in ((pa, a), (pb, b))]
    assert sunk[1] == pytest.approx(sunk[0], rel=1e-9) and 0 < sunk[0] < wheel.outer_radius
    surface = 0.0
    for fa, fb in zip(validity(a, surface), validity(b, surface)):
        assert (fb.check, fb.ok) == (fa.check, fa.ok) and fb.value == pytest.approx(fa.value, rel=1e-9), fa.check

    analytic = write_tiny(
        tmp_path, '\n[terrain]\nmodel = "analytic"\nstiffness = 2.0\ndamping = 0.05\nslip_velocity = 1.0e-4\n', "a.toml"
    )
    defaults = write_tiny(tmp_path, '\n[terrain]\nmodel = "analytic"\n', "d.toml")  # the defaults: scaled as given
    twin, s = write_gravity_twin(defaults, "earth", str(tmp_path / "d_earth.toml"))
    given = dict(load_plan(twin).terrain.parameters)
    assert (given["stiffness"], given["damping"], given["slip_velocity"]) == pytest.approx(
        (2.0e4 * s, 500.0 * math.sqrt(s), 1.0e-3 * math.sqrt(s)), rel=1e-12
    )
    twin, s = write_gravity_twin(analytic, "earth", str(tmp_path / "a_earth.toml"))
    ta, tb = (dict(load_plan(p).terrain.parameters) for p in (analytic, twin))
    assert (tb["stiffness"], tb["damping"], tb["slip_velocity"]) == pytest.approx(
        (2.0 * s, 0.05 * math.sqrt(s), 1.0e-4 * math.sqrt(s)), rel=1e-12
    )
    loads = [load_plan(p).wheel_load for p in (analytic, twin)]
    assert loads[1] / tb["stiffness"] == pytest.approx(loads[0] / ta["stiffness"], rel=1e-12)  # W / k, in metres


def test_cosim_scale_refuses_a_calibration_of_another_gravity_and_a_gravity_vector(tmp_path, capsys):
    """A twin kept the original's terrain.calibration, measured at the original's gravity (its soil 1720 x too
    soft at Earth, found only by a later advise); a vector --gravity lost its direction silently; the twin
    kept the original's scene.name (its runs went into the original's folder). The calibration is refused
    unless calibrated at the twin's gravity, a vector is refused, and the twin is named after its file."""
    from cosim.scm_calibration import ScmCalibration, write_calibration
    from cosim.similarity import write_gravity_twin

    values = dict(k_c=2.0e3, k_phi=8.0e5, n=1.1, cohesion=50.0, friction_angle_deg=30.0, janosi_k=0.002)
    for name, g in (("moon.toml", 1.625), ("earth.toml", 9.80665)):
        write_calibration(str(tmp_path / name), ScmCalibration({**values, "elastic_stiffness": 2e7}, {}, g, {}))
    scene = write_tiny(tmp_path, '\n[terrain]\nmodel = "scm"\ncalibration = "moon.toml"\n')
    out = tmp_path / "twin.toml"
    assert main(["scale", scene, "--gravity", "earth", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "terrain.calibration" in err and "moon.toml" in err and "1.625" in err and "9.807" in err, err
    assert "the shipped example: terrain/earth_twin_regolith_scm_beds.toml" in err and not out.exists()
    # to the Moon's gravity: the shipped Earth calibration is no example (it was named whatever the gravity)
    at_earth = write_tiny(tmp_path, '\n[terrain]\nmodel = "scm"\ncalibration = "earth.toml"\n', "at_earth.toml")
    assert main(["scale", at_earth, "--gravity", "moon", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "earth.toml is calibrated at |g| = 9.807" in err and "none is shipped at this gravity" in err, err
    assert "earth_twin" not in err and not out.exists()
    assert main(["scale", at_earth, "--gravity", "phobos", "--out", str(out)]) == 2  # the one shipped there
    assert "the shipped example: terrain/phobos_regolith_scm_beds.toml" in capsys.readouterr().err
    earth = ["--set", "terrain.calibration='earth.toml'"]
    before = (tmp_path / "earth.toml").read_bytes()  # the calibration it reads is never its --out
    assert (
        main(["scale", scene, "--gravity", "earth", "--out", str(tmp_path / "earth.toml"), "--overwrite", *earth]) == 2
    )
    assert "is the calibration (terrain.calibration) the command reads" in capsys.readouterr().err
    assert (tmp_path / "earth.toml").read_bytes() == before
    assert main(["scale", scene, "--gravity", "earth", "--out", str(out), *earth]) == 0
    assert load_plan(str(out)).terrain.calibration_gravity == pytest.approx(9.80665)
    big = ["--set", "soil.cohesion=1e27", "--out", str(tmp_path / "big.toml")]  # in range, its twin's is not
    assert main(["scale", write_tiny(tmp_path, "", "plain.toml"), "--gravity", "1e5", *big]) == 2
    assert "invalid scene in the twin of" in capsys.readouterr().err
    assert main(["scale", scene, "--gravity", "[9.81, 0, 0]", "--out", str(tmp_path / "v.toml")]) == 2
    assert "--gravity: a preset name or a magnitude" in capsys.readouterr().err
    assert not (tmp_path / "v.toml").exists()
    # the remedy the refusal names: the shipped SCM example with its soil calibrated on the Earth twin
    shipped = EXAMPLES / "phobos_single_wheel_scm.toml"
    earth = 'terrain.calibration="terrain/earth_twin_regolith_scm_beds.toml"'
    twin, s = write_gravity_twin(str(shipped), "earth", str(tmp_path / "scm_twin.toml"), overrides=[earth])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no CalibrationGravityWarning: the calibration is the twin's gravity's
        assert load_plan(twin).terrain.calibration_gravity == pytest.approx(9.80665)
    twin, _ = write_gravity_twin(write_tiny(tmp_path), "earth", str(tmp_path / "tiny_at_earth.toml"))
    assert load_plan(twin).name == "tiny_at_earth"
    named = write_gravity_twin(write_tiny(tmp_path), "earth", str(tmp_path / "n.toml"), overrides=["scene.name='mine'"])
    assert load_plan(named[0]).name == "mine"
    twin, _ = write_gravity_twin(write_tiny(tmp_path), "earth", str(tmp_path / ".hidden.toml"))
    assert load_plan(twin).name == "tiny_twin"  # a name scene.name refuses: the original's, marked


def test_cosim_scale_refuses_an_out_that_is_no_scene_file_before_writing(tmp_path, capsys):
    """--out a folder or a name without .toml: exit 2 naming --out (a folder was an 'Is a directory'
    OSError, exit 5, after the scene was read); an existing file: exit 3 unless --overwrite."""
    from cosim.cli import main

    scene = str(write_tiny(tmp_path))
    for out in (str(tmp_path), str(tmp_path / "twin.txt")):
        assert main(["scale", scene, "--gravity", "earth", "--out", out, "--overwrite"]) == 2
        assert f"--out {out!r}" in capsys.readouterr().err
    assert not (tmp_path / "twin.txt").exists()
    twin = tmp_path / "new" / "twin.toml"
    assert main(["scale", scene, "--gravity", "earth", "--out", str(twin)]) == 0 and twin.is_file()
    assert main(["scale", scene, "--gravity", "earth", "--out", str(twin)]) == 3
    assert [p.name for p in twin.parent.iterdir()] == ["twin.toml"]  # no temporary left beside it


@pytest.mark.slow
def test_the_gravity_twin_gives_the_same_dimensionless_results(tmp_path):
    """The moon scene and its Earth twin, 3 beds each (bed.seed + k), at an imposed slip of 0.3 (as
    in the replica test): sinkage, sinkage of the grouser tips (lengths are not scaled) and
    DP/W, each averaged over the second half of the drive (the same stretch of dimensionless
    time on both sides), agree within the scatter between beds (their 95 % intervals overlap), as
    the similarity says. Each side settles its own beds, the same in exact arithmetic, other
    packings in floating point: the scatter to compare with is the beds', which summation orders
    on one bed do not sample over a drive this short (their sinkages agree to 0.02 mm). The similarity
    holds along the whole drive, so every replica counts, whether
    or not its run found a steady-state window in 0.8 s (measured on one machine: 3 of 4 moon and
    2 of 4 Earth replicas did; a test needing two steady ones per side failed there)."""
    from cosim.output import read_series
    from cosim.similarity import write_gravity_twin
    from cosim.single_wheel import PHASE_DRIVING
    from cosim.study import replica_run

    scene = write_tiny(tmp_path)
    twin, s = write_gravity_twin(scene, "earth", str(tmp_path / "twin.toml"))
    sides = []
    for path, out, time_scale in ((scene, "moon", 1.0), (twin, "earth", 1.0 / math.sqrt(s))):
        settings = [
            f"run.duration={0.8 * time_scale!r}",
            'testbed.mode="slip"',
            "testbed.slip=0.3",
            f"testbed.omega={2.0 / time_scale!r}",
            "bed.seed=3",  # beds 3-5: the wheel lands on each within landing.max_time (on bed 2 it does not)
        ]
        plan = load_plan(path, settings)
        results = replica_run(plan, str(tmp_path / out), 3, executor="serial", vary="bed")["results"]
        replicas = {"sinkage": [], "sinkage_tips": [], "dp_over_w": []}
        for result in results:
            assert result["ok"], result.get("error")
            series = read_series(f"{result['out_dir']}/results.h5")
            driving = series["time"][series["phase"] == PHASE_DRIVING]
            half = (series["phase"] == PHASE_DRIVING) & (series["time"] >= 0.5 * (driving[0] + driving[-1]))
            assert half.sum() > 20
            replicas["sinkage"].append(series["sinkage"][half, 0].mean())
            replicas["sinkage_tips"].append(series["sinkage_tips"][half, 0].mean())
            replicas["dp_over_w"].append(series["drawbar_pull"][half, 0].mean() / plan.wheel_load)
        sides.append({name: metrics.ensemble(values) for name, values in replicas.items()})
    moon, earth = sides
    for name in ("sinkage", "sinkage_tips", "dp_over_w"):
        a, b = moon[name], earth[name]
        assert a["n"] == b["n"] == 3, (name, a, b)
        assert abs(a["mean"] - b["mean"]) <= a["ci95"] + b["ci95"], (name, a, b)
