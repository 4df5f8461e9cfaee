"""A scene's validity (cosim.advice) judged on the wheel that fails first: a rover's fastest, largest,
narrowest or deepest wheel, the speeds its drive can reach, the substeps the PID step control takes, the
slips a wheel fit was fitted on; and a terrain with no checks is "not checked", never "valid"."""

import math
from pathlib import Path

import pytest

from cosim import advice
from cosim.cli import advise_lines, main
from cosim.plan import load_plan
from cosim.records import _froude_number
from cosim.system import validity
from helpers import write_tiny

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
PATCH = EXAMPLES / "phobos_rover_patch.toml"  # an MMX-like rover, four wheels, a speed drive of 0.07 rad/s
WHEEL_SHAPE = "{radius=0.12, width=0.06, grouser_count=12, grouser_height=0.006, grouser_thickness=0.004}"


def _found(findings) -> dict:
    return {f.check: f for f in findings}


def test_a_rover_is_judged_on_its_fastest_and_its_largest_wheel():
    """One larger wheel (12 cm instead of 5 cm): the bed depth counts in its radius, not the narrowest
    wheel's. Two faster wheels: Froude's number is the fastest wheel's omega^2 r / g, not the mean
    speed's (both passed: 1.25 radii, Fr 0.089)."""
    plan = load_plan(PATCH, [f"rover.wheel_shape.wheel_rl={WHEEL_SHAPE}", "patch.length=1.0", "patch.width=1.0"])
    radii = [w.outer_radius for w in plan.wheels]
    assert max(radii) > 2 * min(radii)
    depth = _found(advice.check(plan))["bed_depth"]
    assert depth.value == pytest.approx(plan.bed.spec.depth / max(radii), rel=1e-12)
    assert not depth.ok, depth.message

    speeds = [0.02, 0.02, 0.17, 0.17]
    plan = load_plan(PATCH, [f"rover.controllers.cruise.speed={speeds}"])
    froude = _found(advice.check(plan))["froude"]
    expected = max(v**2 * w.outer_radius for v, w in zip(speeds, plan.wheels)) / plan.g
    assert froude.value == pytest.approx(expected, rel=1e-12) and expected > advice.FROUDE_LIMIT
    assert not froude.ok and "rover.controllers.cruise.speed" in froude.message
    assert plan.froude_number == pytest.approx(expected, rel=1e-12)  # the summary's too


def test_a_slip_drive_is_judged_at_its_highest_speed_and_a_torque_drive_on_the_run_s_speeds():
    """A slip controller may command up to omega_max: its Froude number there (the check was silently
    left out, and the summary's froude_number nan). A torque drive's speeds are the run's: named as
    waiting for the run before it, judged on the measured wheel speeds after it."""
    plan = load_plan(PATCH, ["rover.drive=slip", "rover.controllers.slip.omega_max=1.0"])
    froude = _found(advice.check(plan))["froude"]
    assert froude.value == pytest.approx(max(w.outer_radius for w in plan.wheels) / plan.g, rel=1e-12)
    assert not froude.ok and "rover.controllers.slip.omega_max" in froude.message

    plan = load_plan(PATCH, ['rover.controllers.cruise={kind="torque", torque=0.001}'])
    assert math.isnan(plan.froude_number)
    assert "froude" not in _found(advice.check(plan))
    assert any(line.startswith("  [after the run] froude:") for line in advise_lines(plan))
    spins = [0.05, 0.05, 0.3, -0.3]  # measured [rad/s]: a wheel turning backwards counts at its |omega|
    froude = _found(advice.check(plan, wheel_spins=spins))["froude"]
    expected = max(v**2 * w.outer_radius for v, w in zip(spins, plan.wheels)) / plan.g
    assert froude.value == pytest.approx(expected, rel=1e-12) and "measured" in froude.message


def test_a_drive_that_sets_its_speeds_as_it_goes_waits_for_the_run_to_pass_its_contacts():
    """A torque drive's wheel speeds are unknown before the run: contact_steps was judged at still rims and
    said ok, then failed after the run at the measured rim speeds (faster rims, shorter contacts). A pass
    now waits for the run (named "[after the run]"); a fail at still rims, which faster rims only worsen,
    is said at once; after the run it is judged at the measured speeds."""
    torque = ['rover.controllers.cruise={kind="torque", torque=0.001}']
    plan = load_plan(PATCH, torque)
    assert "contact_steps" not in _found(advice.check(plan))
    assert any(line.startswith("  [after the run] contact_steps:") for line in advise_lines(plan))
    spins = [0.07] * 4  # measured [rad/s]
    found = _found(advice.check(plan, wheel_spins=spins))["contact_steps"]
    rims = max(0.07 * w.outer_radius for w in plan.wheels)
    assert f"plus the rims' {rims:.3g} m/s" in found.message, found.message
    still = _found(advice.check(plan, wheel_spins=[0.0] * 4))["contact_steps"]
    assert found.value < still.value  # the rims' speed shortens the contact
    coarse = load_plan(PATCH, torque + ["run.dt_factor=1.5"])  # fails already at still rims
    failed = _found(advice.check(coarse))["contact_steps"]
    assert not failed.ok and "plus the rims' 0 m/s" in failed.message
    assert not any(line.startswith("  [after the run] contact_steps") for line in advise_lines(coarse))


def test_advise_at_zero_gravity_gives_its_findings_and_names_what_no_gravity_leaves_open(tmp_path, capsys):
    """`advise` of a scene without gravity stopped at "no gravity and nothing moving: give impact_speed" (exit
    2, no scene key named) where the run's own checks judge it. The impact is the rims' speed when the drive
    sets one; the Froude check is out of range with a remedy that exists (no speed is quasi-static)."""
    scene = EXAMPLES / "phobos_single_wheel.toml"
    assert main(["advise", str(scene), "--set", "scene.gravity=0", "--set", "landing.enabled=false"]) == 0
    out = capsys.readouterr().out
    assert "no gravity: an impact at the rims' speed" in out
    (froude,) = [line for line in out.splitlines() if "froude:" in line]
    assert (
        "OUT OF RANGE" in froude and "without gravity no speed is quasi-static" in froude and "<= 0 rad" not in froude
    )
    assert "verdict: out of range: froude" in out
    assert "(no gravity, no fall)" in out and "(no eq. 10 bound without gravity" in out  # no fall, no load


def test_the_floor_is_judged_under_the_deepest_wheel():
    """After a run the floor clearance is taken at the deepest wheel's tips (the mean of four wheels, one
    of them dug in, hid it)."""
    plan = load_plan(PATCH)
    tips = [0.001, 0.001, 0.001, 0.03]
    found = _found(validity(plan, 0.07, {"sinkage_tips": sum(tips) / 4, "wheel_sinkage_tips": tips}))
    diameter = 2 * plan.bed.spec.radius_mean
    assert found["floor_clearance"].value == pytest.approx((0.07 - max(tips)) / diameter, rel=1e-12)
    # tips measured below the floor (a probe's frictionless grains): said as a passage through it, not as a
    # clearance of "-0.242 grain diameters"
    floor = _found(validity(plan, 0.07, {"sinkage_tips": 0.075, "wheel_sinkage_tips": [0.075] * 4}))["floor_clearance"]
    assert not floor.ok and floor.value < 0
    assert f"the grouser tips went {-floor.value:.3g} grain diameters below the floor" in floor.message, floor.message
    assert "passed through it" in floor.message and "only -" not in floor.message


def test_a_shallow_settled_bed_is_told_the_fill_height_that_makes_it_deep_enough():
    """The rover example fills its bed to 0.07 m, which settles to 0.044 m here: 0.785 wheel radii after
    the run, and the run said "deepen bed.depth to >= 0.0659 m", less than the 0.07 m it already had
    (bed.depth is the fill height; the advice assumed a bed settles to 0.85 of it). The advice takes the
    measured settled fraction: the fill whose settled bed holds DEPTH_RADII wheel radii, and the floor
    clearance's likewise; before the run (advise) the fill height is judged and named as such."""
    plan = load_plan(PATCH)
    fill, settled = plan.bed.spec.depth, 0.044
    outer = max(w.outer_radius for w in plan.wheels)
    found = _found(advice.check(plan, surface_height=settled, sinkage_tips=0.02))
    depth, floor = found["bed_depth"], found["floor_clearance"]
    assert not depth.ok and depth.value == pytest.approx(settled / outer, rel=1e-12)
    needed = advice.DEPTH_RADII * outer * fill / settled  # settles to DEPTH_RADII * outer
    assert needed > fill and f"to >= {needed:.3g} m" in depth.message, depth.message
    assert f"settles to {settled / fill:.2g} x it here" in depth.message
    diameter = 2 * plan.bed.spec.radius_mean
    assert not floor.ok and f"to >= {(advice.FLOOR_GRAINS * diameter + 0.02) * fill / settled:.3g} m" in floor.message
    before = _found(advice.check(plan))
    assert before["bed_depth"].ok and "(fill height; the settled bed is lower)" in before["bed_depth"].message
    assert "a fall through the fill height 0.07 m plus the rims' " in before["contact_steps"].message
    assert "z_h = 0.07 m, the fill height: the settled bed is lower)" in before["overlap"].message
    after = _found(advice.check(plan, surface_height=settled))
    assert "a fall through the settled bed 0.044 m plus the rims' " in after["contact_steps"].message
    assert "z_h = 0.044 m, the settled bed)" in after["overlap"].message
    # before settling the fill is judged as it is, and a failed check names a fill judged the same way
    shallow = load_plan(PATCH, [f"bed.depth={0.9 * outer}"])
    depth = _found(advice.check(shallow))["bed_depth"]
    assert not depth.ok and f"to >= {advice.DEPTH_RADII * outer:.3g} m" in depth.message
    assert "the fill height; the bed settles lower, which the run judges" in depth.message


def test_the_pid_s_contact_resolution_is_judged_on_the_substeps_it_takes():
    """Under the PID step control the fixed dt is not what the soil takes: contact_steps was judged on it
    (10.1 steps, valid, with run.dt_max at 9 x the critical step). Before the run it waits for the substeps
    the error control chooses; after, the contact time over the longest substep taken."""
    plan = load_plan(EXAMPLES / "phobos_single_wheel.toml", ['run.step_control="pid"', "run.dt_max=0.003"])
    assert "contact_steps" not in _found(advice.check(plan))
    lines = advise_lines(plan)
    assert any(line.startswith("  [after the run] contact_steps:") for line in lines), lines
    fixed_plan = load_plan(EXAMPLES / "phobos_single_wheel.toml")
    contact = _found(validity(fixed_plan, 0.05))["contact_steps"].value * fixed_plan.dt  # the contact time [s]
    for longest, ok in ((contact / 20, True), (0.003, False)):
        found = _found(validity(plan, 0.05, {"dt_max": longest}))["contact_steps"]
        assert found.value == pytest.approx(contact / longest, rel=1e-9) and found.ok == ok, found.message
    # a bound that resolves the contact passes before the run: the PID takes no longer substep
    bounded = load_plan(EXAMPLES / "phobos_single_wheel.toml", ['run.step_control="pid"', f"run.dt_max={contact / 20}"])
    found = _found(validity(bounded, 0.05))["contact_steps"]
    assert found.ok and found.value == pytest.approx(20.0, rel=1e-9) and "allowed" in found.message
    assert not any("contact_steps" in line for line in advise_lines(bounded) if "[after the run]" in line)


def test_a_slip_outside_the_wheel_fit_s_slips_is_flagged():
    """The wheel fit (examples/terrain/phobos_regolith_scm_wheel.toml) was fitted on DEM runs at slips
    0.05 .. 0.6 ([source.wheel] slips): a towed wheel (slip 0) or a braked one was "ok" under SCM's slip limit.
    A lab calibration records no slips and is not judged."""
    scm = EXAMPLES / "phobos_single_wheel_scm.toml"
    fit = "terrain.calibration='terrain/phobos_regolith_scm_wheel.toml'"
    runs = [r["slip"] for r in _wheel_runs(EXAMPLES / "terrain" / "phobos_regolith_scm_wheel.toml")]
    assert load_plan(scm, [fit]).terrain.calibration_slips == (min(runs), max(runs))
    for slip, ok in ((0.0, False), (-0.5, False), (0.3, True)):
        found = _found(advice.scm_check(load_plan(scm, [fit, f"testbed.slip={slip}"])))["scm_calibration_slips"]
        assert found.ok == ok and found.value == slip, found.message
    braked = _found(advice.scm_check(load_plan(scm, [fit, "testbed.slip=-0.7"])))["scm_slip"]
    assert not braked.ok and f"|slip| > {advice.SCM_SLIP_LIMIT}" in braked.message  # it said "slip -0.7 > 0.6"
    assert "scm_calibration_slips" not in _found(advice.scm_check(load_plan(scm)))


def _wheel_runs(path: Path) -> list:
    import tomllib

    return tomllib.loads(path.read_text())["source"]["wheel"]["slips"]


def test_a_rover_on_scm_is_judged_on_its_deepest_wheel_against_the_calibration():
    """The traverse on SCM: two wheels at 20 mm and two at 55 mm (mean 38 mm) against a calibration tested
    to 45 mm was "valid"; the deepest wheel is beyond it."""
    plan = load_plan(EXAMPLES / "phobos_rover_scm_traverse.toml")
    tested = plan.terrain.calibration_sinkage
    assert tested is not None
    rims = [0.4 * tested, 0.4 * tested, 1.2 * tested, 1.2 * tested]
    measured = {"sinkage": sum(rims) / 4, "wheel_sinkage": rims, "slip": 0.1}
    depth = _found(validity(plan, 0.0, measured))["scm_calibration_depth"]
    assert not depth.ok and depth.value == pytest.approx(1.2, rel=1e-12)
    measured["wheel_sinkage"] = [None, *rims[1:]]  # a wheel not measured (a JSON null) hides no other
    depth = _found(validity(plan, 0.0, measured))["scm_calibration_depth"]
    assert not depth.ok and depth.value == pytest.approx(1.2, rel=1e-12)


def test_a_terrain_without_checks_is_not_called_valid(tmp_path):
    """The analytic terrain has no validity checks: its verdict said "valid" where the same scene on the
    DEM fails four."""
    from helpers import write_tiny

    plan = load_plan(write_tiny(tmp_path, '\n[terrain]\nmodel = "analytic"\n'))
    assert validity(plan, 0.0) == []
    assert advice.verdict(validity(plan, 0.0)) == advice.NOT_CHECKED
    assert any(line.startswith(f"verdict: {advice.NOT_CHECKED}") for line in advise_lines(plan))


def test_a_mixed_terrain_judges_each_model_on_its_own_wheels():
    """Wheels 0, 1 on the DEM and 2, 3 on SCM, the SCM wheels fast: the DEM's Froude check failed on wheel 2
    (an SCM wheel), and the SCM's would fail on a DEM wheel telling it to "use the DEM there"."""
    mixed = [
        'terrain.model="scm"',
        'terrain.calibration="terrain/phobos_regolith_scm_beds.toml"',
        'terrain.wheels=["dem", "dem", "scm", "scm"]',
    ]
    for speeds, dem_fast in (([0.02, 0.02, 0.3, 0.3], False), ([0.3, 0.3, 0.02, 0.02], True)):
        plan = load_plan(PATCH, [*mixed, f"rover.controllers.cruise.speed={speeds}"])
        found = _found(validity(plan, 0.07))
        for check, wheels in (("froude", (0, 1)), ("scm_froude", (2, 3))):
            expected = max(speeds[i] ** 2 * plan.wheels[i].outer_radius for i in wheels) / plan.g
            assert found[check].value == pytest.approx(expected, rel=1e-12), found[check].message
            assert f"wheel {wheels[0]}" in found[check].message
        assert found["froude"].ok != dem_fast and found["scm_froude"].ok == dem_fast
    # under the PID the DEM's contact check is the DEM wheels' too: a bound that resolves their contacts
    # passes before the run and is not also listed as waiting for it (the SCM wheels are faster)
    slow_dem = load_plan(PATCH, [*mixed, "rover.controllers.cruise.speed=[0.02, 0.02, 0.3, 0.3]"])
    contact = _found(validity(slow_dem, 0.07))["contact_steps"].value * slow_dem.dt  # the contact time [s]
    pid = load_plan(
        PATCH,
        [
            *mixed,
            "rover.controllers.cruise.speed=[0.02, 0.02, 0.3, 0.3]",
            'run.step_control="pid"',
            f"run.dt_max={contact / 12}",
        ],
    )
    lines = advise_lines(pid)
    assert any(line.startswith("  [ok] contact_steps:") for line in lines), lines
    assert not any(line.startswith("  [after the run] contact_steps") for line in lines), lines
    torque = load_plan(PATCH, [*mixed, 'rover.controllers.cruise={kind="torque", torque=0.001}'])
    spins = [0.02, 0.02, 0.3, 0.3]
    found = validity(torque, 0.07, {"wheel_spin": spins})
    expected = max(v**2 * w.outer_radius for v, w in zip(spins, torque.wheels)) / torque.g
    assert _froude_number(torque, found) == pytest.approx(expected, rel=1e-12)  # the summary's: the SCM wheels'


def test_a_rover_on_scm_is_judged_on_each_wheel_s_slip_and_a_nan_speed_is_not_a_pass():
    """One SCM wheel at slip 0.9 among three at 0.1 (the rover's slip 0.3): scm_slip judged the rover's
    slip and passed. A wheel speed not measured (nan) dropped Froude's check, so the verdict said valid."""
    plan = load_plan(EXAMPLES / "phobos_rover_scm_traverse.toml")
    measured = {"slip": 0.3, "wheel_slip": [0.1, 0.1, 0.9, 0.1], "sinkage": 0.01, "sinkage_tips": 0.005}
    slip = _found(validity(plan, 0.0, measured))["scm_slip"]
    assert not slip.ok and slip.value == 0.9 and "wheel 2" in slip.message

    plan = load_plan(PATCH, ['rover.controllers.cruise={kind="torque", torque=0.001}'])
    froude = _found(advice.check(plan, wheel_spins=[math.nan, 0.05, 0.3, 0.3]))["froude"]
    assert not froude.ok and "wheel 2" in froude.message
    assert "the drive (rover.controllers.cruise.torque)" in froude.message  # a torque drive has no speed key


def test_an_older_analytic_run_in_a_study_is_not_checked():
    """A run on the analytic terrain written before its verdict said so (findings [], validity "valid"):
    a study over it read "valid"."""
    from cosim.study import ensemble_validity, failed_checks, run_validity

    older = {"ok": True, "summary": {"findings": [], "validity": "valid"}}
    assert failed_checks(older) is None
    assert run_validity(older) == ensemble_validity([older, older]) == advice.NOT_CHECKED


def test_the_far_wall_is_judged_at_the_carriages_travel_in_slip_mode():
    """At an imposed slip the carriage runs at omega r (1 - slip): at slip -0.9 it travels 1.9 x the rim's
    path, and `advise` judged the far wall at the rim's (10.3 grain diameters, "valid", where the carriage
    ends 2.9 from it). The clearance is the bed's length less the start, the outer radius and the travel."""
    base = EXAMPLES / "phobos_single_wheel.toml"
    for slip in (-0.9, 0.0, 0.5):
        plan = load_plan(base, ['testbed.mode="slip"', f"testbed.slip={slip}", "run.duration=10.3"])
        t, spec, outer = plan.scene.testbed, plan.bed.spec, plan.wheel.outer_radius
        travel = t.omega * outer * (1 - slip) * plan.scene.run.duration
        expected = (spec.length - (plan.testbed.start_x + outer + travel)) / (2 * spec.radius_mean)
        found = _found(advice.check(plan))["wall_clearance"]
        assert f"far end {expected:.3g})" in found.message or f"drive {expected:.3g})" in found.message, found.message
        if slip == -0.9:
            assert expected < advice.WALL_GRAINS and not found.ok, found.message


def _collision(damping: float, integrator: str):
    """Two 5 mm grains closing head-on at 0.1 m/s (no gravity, no friction) with Lehr damping D: a function
    of a share of the longest stable step (advice.stable_step of their normal mode: omega_N of the impact,
    gamma = 2 D omega_N) giving the restitution realised at that fixed step (inf where it diverged)."""
    from soil import Material, Simulation, SimulationDiverged, SoilBuilder, advisor

    radius, speed, modulus = 0.005, 0.1, 1e7
    material = Material(
        youngs_modulus=modulus, poisson_ratio=0.3, damping_ratio=damping, stick_angle=0.0, slip_angle=0.0
    )
    mass = material.density * 4.0 / 3.0 * math.pi * radius**3
    impact = advisor.hertz_impact(modulus / (2 * (1 - 0.3**2)), radius / 2, mass / 2, speed)
    omega = 2.0 / impact.critical_step
    longest = advice.stable_step(omega, 2.0 * damping * omega, integrator)

    def restitution(share: float) -> float:
        builder = SoilBuilder(gravity=(0.0, 0.0, 0.0))
        builder.add_material(material)
        velocities = [(speed / 2, 0, 0), (-speed / 2, 0, 0)]
        builder.add_particles([(0.0, 0, 0), (2 * radius + 1e-5, 0, 0)], radius, velocities=velocities)
        sim = Simulation(*builder.finalize("cpu", "double"), integrator=integrator)
        try:
            sim.run(20 * impact.contact_time, share * longest, check_every=10)
        except SimulationDiverged:
            return math.inf
        velocity = sim.velocities()
        return float((velocity[1, 0] - velocity[0, 0]) / speed)

    return restitution


@pytest.mark.parametrize("integrator", ["velocity-verlet", "jolt-beeman"])
def test_the_stable_step_of_a_damped_mode_is_where_a_collision_stops_giving_its_restitution(integrator):
    """advice.stable_step (the step map's spectral radius) against the collision itself: an overdamped soil
    (D = 3, e = 0.020) at half the step realises the Hertz-Lehr restitution (soil's
    restitution_of_damping_ratio) within 35 %; at twice it, three times that or more, or it diverges.
    The pure-damping bounds: gamma dt = 2 (velocity Verlet's half-step velocity: |1 - gamma dt| <= 1) and
    0.6 (jolt-Beeman's predicted velocity, benchmarks/jolt_beeman_damped_stability.py)."""
    from soil import restitution_of_damping_ratio

    restitution, target = _collision(3.0, integrator), restitution_of_damping_ratio(3.0)
    assert restitution(0.5) == pytest.approx(target, rel=0.35)
    assert restitution(2.0) > 3.0 * target
    pure = {"velocity-verlet": 2.0, "jolt-beeman": 0.6}[integrator]
    assert advice.stable_step(1e-9, 1.0, integrator) == pytest.approx(pure, rel=1e-3)
    assert advice.stable_step(1.0, 0.0, integrator) == pytest.approx(2.0, rel=1e-3)  # undamped: omega dt = 2


def test_an_overdamped_or_rolling_stiff_soil_is_named_before_and_when_it_diverges(tmp_path, capsys):
    """soil.damping_ratio = 100 and soil.rolling_friction = 1e3 passed advise, and the bed's divergence named
    the settling step, the gravity and the friction angles, not them."""
    scene = write_tiny(tmp_path)
    lines = "\n".join(advise_lines(load_plan(scene, ["soil.damping_ratio=100", 'run.integrator="jolt-beeman"'])))
    assert "[OUT OF RANGE] damping_step: the step " in lines and "run.dt_factor, jolt-beeman" in lines, lines
    assert "x the longest that keeps the damped tangential mode (D = 100, grain on grain, stuck)" in lines
    lines = "\n".join(advise_lines(load_plan(scene)))
    assert "[ok] damping_step" in lines and "[ok] rolling_step" in lines  # the tiny scene's own soil
    out = tmp_path / "rolling"
    assert main(["run", scene, "--out", str(out), "--no-progress", "--set", "soil.rolling_friction=1e3"]) == 4
    err = capsys.readouterr().err
    assert "the bed diverged while settling" in err and "rolling_step: the step " in err, err
    assert "(bed.settle_dt_factor, velocity-verlet)" in err and "lower soil.rolling_friction" in err


def test_single_precision_is_judged_on_the_overlap_under_the_wheel():
    """At Phobos a soil of E = 1e8 Pa carries the wheel's 2.3 Pa on overlaps of 7e-8 m, about four float32
    spacings at the bed's 0.16 m: single precision cannot resolve them (docs/physics.md section 3); the
    main job's E = 2e5 Pa overlaps 4e-6 m."""
    main_job = str(Path(__file__).parents[1] / "examples" / "phobos_single_wheel.toml")
    stiff = load_plan(main_job, ['scene.precision="single"', "soil.youngs_modulus=1e8"])
    (found,) = [f for f in advice.check(stiff) if f.check == "single_precision"]
    material = stiff.soil_material
    e_star = material.youngs_modulus / (2 * (1 - material.poisson_ratio**2))
    r = stiff.bed.spec.radius_mean
    overlap = float(found.message.split(" in the overlap ")[1].split(" m ")[0])
    hertz = 4.0 / 3.0 * e_star * math.sqrt(r / 2) * overlap**1.5  # the force that overlap carries
    assert hertz == pytest.approx(advice.ground_pressure(stiff) * (2 * r) ** 2, rel=1e-2)
    assert not found.ok and found.value < 10 and found.setting == "scene.precision"
    (found,) = [
        f for f in advice.check(load_plan(main_job, ['scene.precision="single"'])) if f.check == "single_precision"
    ]
    assert found.ok
    assert not [f for f in advice.check(load_plan(main_job)) if f.check == "single_precision"]  # mixed: not judged


def test_a_bed_without_gravity_is_not_said_to_miss_a_threshold_of_zero(tmp_path, caplog):
    """At g = 0 the settling's kinetic-energy threshold (a fraction of the grains' weight times a radius) is
    0 J: the log said 'KE 0 J > 0 J'. It says what a bed without weight does instead."""
    from cosim.beds import settled_bed

    overrides = ["scene.gravity=0", "landing.enabled=false", "bed.settle_max_time=0.02"]
    plan = load_plan(write_tiny(tmp_path), overrides)
    with caplog.at_level("WARNING", logger="cosim.beds"):
        settled_bed(plan, str(tmp_path))
    assert "without gravity the bed has no kinetic-energy threshold to settle to" in caplog.text, caplog.text
    assert "did not reach" not in caplog.text


@pytest.mark.parametrize("integrator", ["velocity-verlet", "jolt-beeman"])
def test_a_stuck_contact_s_spin_decays_below_the_tangential_mode_s_stable_step_and_grows_above(integrator):
    """The tangential mode damping_step judges (a stuck contact's Kelvin spring k_T = 4 G*/E* k_N and its
    dashpot on the inverse mass 3.5 / m of a grain sliding and turning on a wall): a 5 mm grain resting on
    the floor at Earth gravity, given a spin of 1e-3 rad/s, over 400 fixed steps at 0.9 x and 1.5 x
    advice.stable_step of that mode at its resting overlap: below, the damping takes the spin down; above,
    it grows past ten times its start (friction caps it short of a divergence: BENCHMARKS.md's grain
    thrown out of a bed)."""
    import numpy as np

    from soil import Material, Simulation, SoilBuilder

    radius, modulus, nu, damping, g = 0.005, 1e7, 0.3, 0.454, 9.81
    material = Material(youngs_modulus=modulus, poisson_ratio=nu, damping_ratio=damping)
    mass = material.density * 4.0 / 3.0 * math.pi * radius**3
    e_star = modulus / (2.0 * (1.0 - nu**2))
    overlap = (3.0 * mass * g / (4.0 * e_star * math.sqrt(radius))) ** (2.0 / 3.0)  # Hertz: resting on the floor
    omega = math.sqrt(2.0 * e_star * math.sqrt(radius * overlap) / mass)
    shear = 2.0 * (1.0 - nu) / (2.0 - nu)
    longest = advice.stable_step(math.sqrt(3.5 * shear) * omega, 7.0 * damping * math.sqrt(shear) * omega, integrator)

    def spin(share: float) -> float:
        builder = SoilBuilder(gravity=g)
        builder.add_material(material)
        builder.add_plane((0, 0, 0), (0, 0, 1))
        builder.add_particles([(0.0, 0.0, radius - overlap)], radius, angular_velocities=[(0.0, 1e-3, 0.0)])
        sim = Simulation(*builder.finalize("cpu", "double"), integrator=integrator)
        sim.run(400 * share * longest, share * longest, check_every=10)
        return float(np.abs(sim.angular_velocities()).max())

    assert spin(0.9) < 1e-3 < 1e-2 < spin(1.5)


@pytest.mark.parametrize("integrator", ["velocity-verlet", "jolt-beeman"])
def test_a_rolling_spring_on_a_wall_is_stable_to_the_step_rolling_step_names_and_no_further(integrator):
    """rolling_step's wall case against the physics: a 5 mm grain resting on the floor without friction
    (only its rolling spring k_r = 2.25 mu_r^2 r^2 k_N and damper hold its spin; the grain alone turns,
    0.4 m r^2: omega_r = 2.37 mu_r omega_N, gamma_r = 8.87 D mu_r omega_N), mu_r = 2, given a spin of
    1e-3 rad/s, 400 fixed steps: at 0.9 x advice.stable_step of that mode the spin dies out; at 1.1 x it
    grows past ten times its start."""
    import numpy as np

    from soil import ContactLaw, Material, Simulation, SoilBuilder

    radius, modulus, nu, damping, mu, g = 0.005, 1e7, 0.3, 0.454, 2.0, 9.81
    material = Material(
        youngs_modulus=modulus,
        poisson_ratio=nu,
        damping_ratio=damping,
        stick_angle=0.0,
        slip_angle=0.0,
        rolling_friction=mu,
    )
    mass = material.density * 4.0 / 3.0 * math.pi * radius**3
    e_star = modulus / (2.0 * (1.0 - nu**2))
    overlap = (3.0 * mass * g / (4.0 * e_star * math.sqrt(radius))) ** (2.0 / 3.0)  # Hertz: resting on the floor
    omega = math.sqrt(2.0 * e_star * math.sqrt(radius * overlap) / mass)
    omega_r = math.sqrt(2.25 / 0.4) * mu * omega
    gamma_r = 2.0 * damping * 1.5 * math.sqrt(1.4) / 0.4 * mu * omega
    longest = advice.stable_step(omega_r, gamma_r, integrator)

    def spin(share: float) -> float:
        builder = SoilBuilder(gravity=g)
        builder.add_material(material)
        builder.add_plane((0, 0, 0), (0, 0, 1))
        builder.add_particles([(0.0, 0.0, radius - overlap)], radius, angular_velocities=[(0.0, 1e-3, 0.0)])
        sim = Simulation(*builder.finalize("cpu", "double", law=ContactLaw(rolling=True)), integrator=integrator)
        sim.run(400 * share * longest, share * longest, check_every=10)
        return float(np.abs(sim.angular_velocities()).max())

    assert spin(0.9) < 1e-6 and spin(1.1) > 1e-2


def test_a_milli_g_fill_is_not_called_settled_before_it_has_fallen(tmp_path):
    """At 1e-3 m/s^2 the tiny scene's fill was 'settled' at 0.11 s: grains released from rest stay under
    the gravity-scaled threshold (ratio m g r) for sqrt(2 ratio r / g) of free fall, 0.14 s here, and the
    check began after 10 intervals, 0.1 s. In 1 s a grain falls 0.5 mm, a quarter of its radius: the bed
    cannot have settled, and settling says so; at the scene's own gravity it settles as before."""
    from soil.bed import make_settled_bed, still_time

    plan = load_plan(write_tiny(tmp_path), ["scene.gravity=1e-3", "landing.max_time=8"])
    bed = plan.bed
    sim, report, _ = make_settled_bed(
        bed.spec, plan.gravity, device="cpu", dt=bed.settle_dt, ke_ratio=bed.settle_ke_ratio, max_time=1.0
    )
    assert still_time(sim, bed.settle_ke_ratio) > 0.1  # the case: a free fall under the threshold past 10 intervals
    assert not report["settled"], report
    own = load_plan(write_tiny(tmp_path))
    _, report, _ = make_settled_bed(
        own.bed.spec, own.gravity, device="cpu", dt=own.bed.settle_dt, ke_ratio=own.bed.settle_ke_ratio
    )
    assert report["settled"], report


@pytest.mark.parametrize("macro_step", [0.0017, 0.0272])
def test_a_macro_step_that_does_not_resolve_the_wheel_s_bounce_on_a_grain_is_flagged_and_gains_energy(
    tmp_path, tiny_bed, caplog, macro_step
):
    """coupling_step on the DEM: a 10 g wheel on the tiny scene's bed, whose bounce on one grain (omega^2 =
    2 E* sqrt(R delta) / m at the deepest overlap of a Hertz impact, the largest grain held as a wall, struck
    at a fall of one grain diameter: computed here from Hertz's closed form) takes 0.70 rad of a 1.7 ms macro
    step and 11 rad of a 27.2 ms one. The first is valid, and the wheel lands: it never rises faster than it
    fell (the contacts dissipate). The second is flagged, naming the macro step that passes, and the exchange
    hands the wheel energy: it rises faster than it fell onto the soil and never comes to rest, and the run
    says it was bouncing (it used to advise lightening the wheel)."""
    import h5py

    from cosim.launch import run_scene
    from helpers import effective_modulus, hertz_impact_overlap

    overrides = {"testbed.mass": 0.01, "run.macro_step": macro_step, "landing.max_time": 0.8, "run.duration": 0.03}
    scene = write_tiny(tmp_path)
    plan = load_plan(scene, overrides)
    mass, spec = 0.01, plan.bed.spec
    speed = math.sqrt(2 * plan.g * 2 * spec.radius_mean) + plan.testbed.omega * plan.wheel.outer_radius
    e_star = effective_modulus(plan.soil_material, plan.wheel.material)
    deepest = hertz_impact_overlap(mass, speed, e_star, spec.radius_max)
    omega = math.sqrt(2 * e_star * math.sqrt(spec.radius_max * deepest) / mass)
    finding = _found(validity(plan, 0.0))["coupling_step"]
    assert finding.value == pytest.approx(omega * macro_step, rel=1e-9) and finding.unit == "rad"
    assert finding.ok == (omega * macro_step <= 2.0)
    if not finding.ok:
        named = float(finding.message.split("set run.macro_step <= ")[1].split(" s")[0])
        assert (
            named <= 2.0 / omega < named * 1.01
            and _found(validity(load_plan(scene, {**overrides, "run.macro_step": named}), 0.0))["coupling_step"].ok
        )

    out = tmp_path / "run"
    result = run_scene(
        scene, str(out), overrides=[f'bed.bed_file="{tiny_bed}"'] + [f"{k}={v}" for k, v in overrides.items()]
    )
    with h5py.File(out / "results.h5") as f:
        vz = f["wheels/linear_velocity"][:, 0, 2]
    fell, rose = -vz.min(), vz.max()
    if finding.ok:
        assert result.summary["landing_time"] is not None and rose < fell
    else:
        assert result.summary["steady_state"] == "no landing" and rose > 2 * fell
        assert "off the soil at the end, bouncing" in caplog.text


@pytest.mark.parametrize(
    "timing, key",
    [
        ({"run.macro_step": None, "run.substeps": 400}, "run.substeps"),  # H = substeps x dt
        ({"run.dt": 1e-4, "run.macro_step": 0.04}, "run.macro_step"),  # H a whole number of the given dt
        ({"run.macro_step": 0.04}, "run.macro_step"),  # dt shrinks to make H whole
    ],
)
def test_coupling_step_names_the_longest_step_the_scene_s_own_key_accepts(tmp_path, timing, key):
    """A failed coupling_step names the value of the key the scene sets its macro step by: run.substeps
    where it gives them, a whole number of run.dt where it gives that (another value is refused as a
    scene), else run.macro_step. The named value is accepted, passes, and one DEM step more fails."""
    scene = write_tiny(tmp_path)
    base = {"testbed.mass": 0.01, "output.checkpoint_interval": 0.1, "output.snapshot_interval": 0.1, **timing}

    def judged(**changes):
        return _found(validity(load_plan(scene, {**base, **changes}), 0.0))["coupling_step"]

    finding = judged()
    assert not finding.ok
    named = finding.message.split(f"set {key} <= ")[1].split(" ")[0]
    if key == "run.substeps":
        assert judged(**{key: int(named)}).ok and not judged(**{key: int(named) + 1}).ok
    else:
        plan = load_plan(scene, {**base, key: float(named)})
        assert judged(**{key: float(named)}).ok and not judged(**{key: float(named) + plan.dt}).ok


def test_a_wheel_bouncing_on_the_soil_while_touching_it_has_not_landed(tmp_path):
    """On a nearly elastic soil (restitution 0.999) the tiny scene's wheel bounced while it kept touching the
    grains; its hub was back at the same height at the two ends of the landing's hold, which alone was taken
    for a landing: the drive began with the wheel in the air ('airborne', landing sinkage -4.0 mm, the rim
    above the surface). Its heights over the hold spread 6.4 times the drift allowed; at rest they spread
    less than cosim.runner.LANDING_FLICKER times it. Now it lands in the soil and drives on it."""
    import h5py

    from cosim.launch import run_scene

    out = tmp_path / "run"
    result = run_scene(write_tiny(tmp_path), str(out), overrides=["soil.restitution=0.999"])
    summary = result.summary
    assert math.isfinite(summary["landing_time"]) and summary["landing_sinkage"] > 0, summary
    assert summary["steady_state"] != "airborne", summary
    with h5py.File(out / "results.h5") as f:
        driving = f["wheels/phase"][:] == 1
        contacts = f["wheels/contact_count"][:, 0][driving]
    assert (contacts[:10] > 0).all(), contacts[:10]  # on the soil from the drive's start
