"""Is a scene a valid wheel test? Its dimensionless numbers against what the physics needs.

`check(plan, surface_height=None, result=None)` returns one Finding per check; each names
the scene setting that changes it. `cosim advise` prints them, every run logs them at its
start and stores them in results.h5 and run.json, and after a run the measured sinkage
is checked against the floor.

    froude          Fr = omega^2 r_outer / |g| <= FROUDE_LIMIT: above it the result depends on the
                    wheel's speed, and further up the wheel hops (measured: docs/validity.md)
    contact_steps   Hertz contact time of two grains at the impact speed / dt >= CONTACT_STEPS
    grains_across   wheel width / grain diameter >= GRAINS_ACROSS
    bed_depth       settled bed depth / wheel outer radius >= DEPTH_RADII (the stress bulb under
                    a wheel reaches about one wheel radius into the soil)
    floor_clearance soil between the grouser tips and the floor, at the start and at the measured
                    sinkage, >= FLOOR_GRAINS grain diameters
    wall_clearance  side gap wheel-wall >= WALL_GRAINS grain diameters; far wall after the drive
    overlap         Young's modulus >= the paper's eq. 10 bound for overlaps <= OVERLAP_RATIO r
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from soil import advisor

from .plan import WALL_GRAINS, RunPlan

FROUDE_LIMIT = 0.1
"""Largest Froude number omega^2 r / |g| of a quasi-static wheel test [-]: measured on the testbed,
the slip at Fr 0.1 matches the slowest run's, at Fr 0.2 it is half as large again
(benchmarks/froude_hop.py, docs/validity.md)."""
CONTACT_STEPS = 10
"""Fewest DEM steps per grain-grain contact time [-]."""
GRAINS_ACROSS = 8
"""Fewest grain diameters across the wheel width [-]."""
DEPTH_RADII = 1.0
"""Shallowest settled bed, in wheel outer radii [-]."""
FLOOR_GRAINS = 4
"""Fewest grain diameters between the grouser tips and the floor [-]."""
OVERLAP_RATIO = 0.01
"""Largest static overlap / radius the stiffness should allow (eq. 10's u) [-]."""


@dataclass(frozen=True)
class Finding:
    """One validity check."""

    check: str
    value: float
    limit: float
    ok: bool
    message: str
    setting: str
    """The scene key(s) to change."""
    unit: str = "1"
    """The unit of value and limit ("1": a dimensionless number, as most checks are)."""

    def as_dict(self) -> dict:
        return asdict(self)


def _finding(check, value, limit, ok, good, bad, setting, unit: str = "1") -> Finding:
    return Finding(check, float(value), float(limit), bool(ok), good if ok else bad, setting, unit)


def ground_pressure(plan: RunPlan) -> float:
    """Wheel ground pressure [Pa]: the load over the width times a contact length 2 sqrt(2 R s)
    at a sinkage s of one mean grain radius."""
    w = plan.wheel
    length = 2.0 * math.sqrt(2.0 * w.outer_radius * plan.bed.spec.radius_mean)
    return plan.wheel_load / (w.width * length)


def check(plan: RunPlan, surface_height: float | None = None, sinkage_tips: float | None = None) -> list[Finding]:
    """The validity findings of a plan; the settled surface height [m] and the measured tip
    sinkage [m] sharpen the depth and floor checks when known."""
    spec, t = plan.bed.spec, plan.testbed
    # a rover: judge its narrowest wheel with the largest outer radius
    wheel = min(plan.wheels or (plan.wheel,), key=lambda w: w.width)
    diameter = 2.0 * spec.radius_mean
    g = plan.g
    findings = []
    omega = plan.drive_omega
    if t is not None:
        omega_key = "testbed.omega"
    else:
        assert plan.rover is not None and plan.scene.rover is not None  # a plan has a testbed or a rover
        named = isinstance(plan.scene.rover.drive, str)
        omega_key = f"rover.controllers.{plan.rover.drive.name}.speed" if named else "rover.drive.speed"

    fr = plan.froude_number
    if math.isfinite(omega):
        findings.append(
            _finding(
                "froude",
                fr,
                FROUDE_LIMIT,
                fr <= FROUDE_LIMIT,
                f"Froude number omega^2 r / g = {fr:.3g} <= {FROUDE_LIMIT}: quasi-static",
                f"Froude number omega^2 r / g = {fr:.3g} > {FROUDE_LIMIT}: not quasi-static at this speed and gravity "
                "(the slip depends on the speed; faster, the wheel hops); "
                f"lower {omega_key} to <= {math.sqrt(FROUDE_LIMIT * g / wheel.outer_radius):.3g} rad/s",
                omega_key,
            )
        )

    material = plan.soil_material
    smallest = spec.radius_min
    depth_now = surface_height if surface_height is not None else spec.depth
    speed = math.sqrt(2 * g * max(depth_now, smallest)) + (omega if math.isfinite(omega) else 0.0) * wheel.outer_radius
    contact = advisor.hertz_contact_time(
        material.youngs_modulus, material.poisson_ratio, material.density, smallest, max(speed, 1e-12)
    )
    steps = contact / plan.dt
    findings.append(
        _finding(
            "contact_steps",
            steps,
            CONTACT_STEPS,
            steps >= CONTACT_STEPS,
            f"{steps:.3g} DEM steps per contact time ({contact:.3g} s at {speed:.3g} m/s)",
            f"only {steps:.3g} DEM steps per contact time ({contact:.3g} s): contacts are under-resolved; lower "
            f"{plan.dt_setting} so dt <= {contact / CONTACT_STEPS:.3g} s",
            plan.dt_setting,
        )
    )

    across = wheel.width / diameter
    findings.append(
        _finding(
            "grains_across",
            across,
            GRAINS_ACROSS,
            across >= GRAINS_ACROSS,
            f"{across:.3g} grain diameters across the wheel",
            f"only {across:.3g} grain diameters across the wheel width: the grains are too coarse for the wheel "
            f"(>= {GRAINS_ACROSS} needed); lower bed.radius_mean to <= {wheel.width / (2 * GRAINS_ACROSS):.3g} m or "
            "widen the wheel",
            "bed.radius_mean, wheel.width",
        )
    )

    depth = surface_height if surface_height is not None else spec.depth
    estimated = "" if surface_height is not None else " (fill height; the settled bed is lower)"
    radii = depth / wheel.outer_radius
    findings.append(
        _finding(
            "bed_depth",
            radii,
            DEPTH_RADII,
            radii >= DEPTH_RADII,
            f"bed depth {depth:.3g} m = {radii:.3g} wheel radii{estimated}",
            f"the bed is {depth:.3g} m deep{estimated}, {radii:.3g} wheel radii: the floor carries part of the "
            f"wheel's load; deepen bed.depth to >= {DEPTH_RADII * wheel.outer_radius / 0.85:.3g} m",
            "bed.depth",
        )
    )

    sink = max(sinkage_tips or 0.0, 0.0)
    clearance = (depth - sink) / diameter
    when = f"at the measured tip sinkage {sink:.3g} m" if sinkage_tips is not None else "at the start"
    findings.append(
        _finding(
            "floor_clearance",
            clearance,
            FLOOR_GRAINS,
            clearance >= FLOOR_GRAINS,
            f"{clearance:.3g} grain diameters between the grouser tips and the floor {when}",
            f"only {clearance:.3g} grain diameters between the grouser tips and the floor {when}: the wheel feels the "
            "floor; deepen bed.depth",
            "bed.depth",
        )
    )

    if t is not None:
        side = (spec.width - wheel.width) / 2 / diameter
        end = (
            spec.length - (t.start_x + wheel.outer_radius + t.omega * wheel.outer_radius * plan.scene.run.duration)
        ) / diameter
        walls = min(side, end)
        findings.append(
            _finding(
                "wall_clearance",
                walls,
                WALL_GRAINS,
                walls >= WALL_GRAINS,
                f"wheel-wall clearance >= {walls:.3g} grain diameters (side {side:.3g}, far end {end:.3g})",
                f"the wheel comes within {walls:.3g} grain diameters of a wall (side {side:.3g}, far end after the "
                f"drive {end:.3g}): widen bed.width or lengthen bed.length",
                "bed.width, bed.length",
            )
        )
    elif plan.patch is not None:
        gap = plan.patch.clearance / diameter
        findings.append(
            _finding(
                "wall_clearance",
                gap,
                WALL_GRAINS,
                gap >= WALL_GRAINS,
                f"the wheels keep >= {gap:.3g} grain diameters from the patch's frozen band",
                f"the wheels may come within {gap:.3g} grain diameters of the patch's frozen band: raise "
                "patch.clearance (and the window size)",
                "patch.clearance, patch.length, patch.width",
            )
        )

    pressure = ground_pressure(plan)
    bound = advisor.macroscopic_stiffness(depth, pressure, OVERLAP_RATIO, spec.radius_mean, material.density, g)
    ratio = material.youngs_modulus / bound if bound > 0 else math.inf
    findings.append(
        _finding(
            "overlap",
            ratio,
            1.0,
            ratio >= 1.0,
            f"E = {material.youngs_modulus:.3g} Pa is {ratio:.3g} x the eq. 10 bound {bound:.3g} Pa (overlaps <= "
            f"{OVERLAP_RATIO} r under the wheel's {pressure:.3g} Pa)",
            f"E = {material.youngs_modulus:.3g} Pa is below the eq. 10 bound {bound:.3g} Pa: overlaps exceed "
            f"{OVERLAP_RATIO} r under the wheel; raise soil.youngs_modulus",
            "soil.youngs_modulus",
        )
    )
    return findings


def verdict(findings: list[Finding]) -> str:
    """'valid' or the failed checks, comma-separated."""
    failed = [f.check for f in findings if not f.ok]
    return "valid" if not failed else "out of range: " + ", ".join(failed)


# -- the SCM tier ------------------------------------------------------------------------------

SCM_GROUSER_RATIO = 0.5
"""Largest grouser height / sinkage for SCM [-]: taller grousers carry the traction by shearing soil
between them, which a height field's surface shear does not represent."""
SCM_SINKAGE_GRAINS = 3.0
"""Shallowest sinkage for SCM, in grain diameters [-]: shallower, the wheel rides on a few grains and
the continuum's pressure-sinkage curve does not hold."""
SCM_SLIP_LIMIT = 0.6
"""Highest slip for SCM [-]: beyond it the wheel digs in (soil flows round it, sinkage by slip) and the
steady-state Bekker/Janosi model is outside the measured range."""

USE_DEM = 'use the DEM there (terrain.model = "dem", or "dem" for that wheel in terrain.wheels)'


def _scm_wheels(plan: RunPlan) -> tuple[list[int], list]:
    """The indices of the plan's wheels on SCM, and those wheels."""
    from .scm_soil import scm_wheel_indices

    indices = scm_wheel_indices(plan)
    return indices, [plan.wheels[i] for i in indices]


def _drive_slip(plan: RunPlan) -> tuple[float | None, str]:
    """The slip the drive asks for (the testbed's slip mode, a slip controller) and its key; None if it sets none."""
    t = plan.testbed
    if t is not None:
        return (t.slip, "testbed.slip") if t.mode == "slip" else (None, "")
    assert plan.rover is not None and plan.scene.rover is not None
    section = plan.rover.drive.section
    target = getattr(section, "target_slip", None)
    if target is None:
        return None, ""
    named = isinstance(plan.scene.rover.drive, str)
    key = f"rover.controllers.{plan.rover.drive.name}.target_slip" if named else "rover.drive.target_slip"
    return float(target), key


def judged_after_the_run(plan: RunPlan) -> list[tuple[str, str]]:
    """(check, what it will compare) for each SCM check that only the run's own measurements can judge,
    so that advice before a run names it instead of passing over it: the calibration depth
    (`scm_calibration_depth`), on the run's rim sinkage. Bekker's closed form for a smooth wheel is
    given beside it; on a grousered wheel it overstates SCM's own sinkage (the main job: 2.5x)."""
    from .scm_soil import bekker_wheel_sinkage, scm_settings

    tested = plan.terrain.calibration_sinkage
    indices, wheels = _scm_wheels(plan)
    if tested is None or not wheels:
        return []
    parameters = scm_settings(plan, indices, 0.0).parameters
    wheel = min(wheels, key=lambda w: w.width)
    closed_form = bekker_wheel_sinkage(parameters, plan.wheel_load, wheel.outer_radius, wheel.width)
    side = "beyond" if closed_form > tested else "within"
    return [
        (
            "scm_calibration_depth",
            f"the run's rim sinkage against the {tested:.3g} m the calibration's DEM tests reached (Bekker's "
            f"closed form for a smooth wheel: {closed_form:.3g} m, {side} it)",
        )
    ]


def scm_check(plan: RunPlan, measured: dict | None = None) -> list[Finding]:
    """Where the SCM tier cannot represent the run (each failed finding says what to do: use the DEM,
    or refine the grid, calibrate again): grouser-dominated traction (grouser height >
    SCM_GROUSER_RATIO x sinkage), a grid that samples the grousers instead of resolving them (node
    spacing > the thinnest grouser / NODES_ACROSS_GROUSER: `scm_grouser_grid`), a sinkage below
    SCM_SINKAGE_GRAINS grain diameters, a slip above SCM_SLIP_LIMIT, a Froude number above
    FROUDE_LIMIT, a calibration made at another gravity, a wheel fit made on another grid
    (`scm_calibration_grid`), and after a run a rim sinkage deeper than the calibration's DEM tests
    reached (`scm_calibration_depth`). `measured`: a run summary's
    'sinkage_tips', 'sinkage' [m] and 'slip' [-]; before a run the sinkage is Bekker's closed form
    for the wheel's load and the slip the drive's imposed or target slip."""
    from .scm_calibration import same_gravity
    from .scm_soil import NODES_ACROSS_GROUSER, bekker_wheel_sinkage, grouser_thickness, scm_settings

    indices, wheels = _scm_wheels(plan)
    if not wheels:
        return []
    parameters = scm_settings(plan, indices, 0.0).parameters
    wheel = min(wheels, key=lambda w: w.width)
    measured = measured or {}
    sinkage_tips, slip = measured.get("sinkage_tips"), measured.get("slip")
    if sinkage_tips is not None:
        sinkage, how = float(sinkage_tips), "measured"
    else:
        sinkage = bekker_wheel_sinkage(parameters, plan.wheel_load, wheel.outer_radius, wheel.width)
        how = "Bekker's closed form"
    findings = []
    grouser = float(getattr(wheel.shape, "grouser_height", 0.0)) if getattr(wheel.shape, "grouser_count", 0) else 0.0
    if grouser > 0:
        findings.append(
            _finding(
                "scm_grousers",
                grouser / max(sinkage, 1e-12),
                SCM_GROUSER_RATIO,
                grouser <= SCM_GROUSER_RATIO * sinkage,
                f"grouser height {grouser:.3g} m <= {SCM_GROUSER_RATIO} x sinkage {sinkage:.3g} m ({how}): SCM's "
                "surface shear carries the traction",
                f"grouser height {grouser:.3g} m > {SCM_GROUSER_RATIO} x sinkage {sinkage:.3g} m ({how}): the "
                f"grousers carry the traction, which SCM does not represent; {USE_DEM}",
                "wheel.grouser_height, terrain.model",
            )
        )
    thickness = grouser_thickness(wheels)
    if math.isfinite(thickness):
        spacing, finest = parameters.node_spacing, thickness / NODES_ACROSS_GROUSER
        findings.append(
            _finding(
                "scm_grouser_grid",
                spacing / thickness,
                1.0 / NODES_ACROSS_GROUSER,
                spacing <= finest * (1.0 + 1e-9),
                f"node spacing {spacing:.3g} m <= grouser thickness {thickness:.3g} m / {NODES_ACROSS_GROUSER}: "
                "the grid resolves the grousers",
                f"node spacing {spacing:.3g} m > grouser thickness {thickness:.3g} m / {NODES_ACROSS_GROUSER}: "
                "the nodes sample the grousers, which fall between them at some phases, and the wheel's forces beat "
                f"with the grid (docs/scm.md); set terrain.node_spacing <= {finest:.3g} m",
                "terrain.node_spacing",
            )
        )
    diameter = 2.0 * plan.bed.spec.radius_mean
    findings.append(
        _finding(
            "scm_sinkage_grains",
            sinkage / diameter,
            SCM_SINKAGE_GRAINS,
            sinkage >= SCM_SINKAGE_GRAINS * diameter,
            f"sinkage {sinkage:.3g} m ({how}) = {sinkage / diameter:.3g} grain diameters: a continuum",
            f"sinkage {sinkage:.3g} m ({how}) is {sinkage / diameter:.3g} grain diameters, below "
            f"{SCM_SINKAGE_GRAINS}: the wheel rides on single grains, no continuum; {USE_DEM}",
            "terrain.model, bed.radius_mean",
        )
    )
    target, key = _drive_slip(plan)
    slip_how = "measured" if slip is not None and math.isfinite(slip) else "set"
    slip = slip if slip_how == "measured" else target
    if slip is not None:
        findings.append(
            _finding(
                "scm_slip",
                slip,
                SCM_SLIP_LIMIT,
                abs(slip) <= SCM_SLIP_LIMIT,
                f"slip {slip:.3g} ({slip_how}) <= {SCM_SLIP_LIMIT}",
                f"slip {slip:.3g} ({slip_how}) > {SCM_SLIP_LIMIT}: the wheel digs in (slip sinkage, soil flowing "
                "round it), "
                f"outside SCM's steady Bekker-Janosi model; {USE_DEM}",
                key,
            )
        )
    fr = plan.froude_number
    if math.isfinite(fr):
        findings.append(
            _finding(
                "scm_froude",
                fr,
                FROUDE_LIMIT,
                fr <= FROUDE_LIMIT,
                f"Froude number {fr:.3g} <= {FROUDE_LIMIT}: quasi-static, as SCM's laws are",
                f"Froude number {fr:.3g} > {FROUDE_LIMIT}: a dynamic regime (soil inertia, the wheel hops) that "
                f"SCM's quasi-static laws do not hold; {USE_DEM}",
                "testbed.omega, rover.controllers",
            )
        )
    calibrated = plan.terrain.calibration_gravity
    if calibrated is not None:
        findings.append(
            _finding(
                "scm_calibration_gravity",
                calibrated,
                plan.g,
                same_gravity(calibrated, plan.g),
                f"calibrated at the scene's gravity ({plan.g:.4g} m/s^2)",
                f"calibrated at |g| = {calibrated:.4g} m/s^2, the scene's is {plan.g:.4g} m/s^2: the soil's response "
                "depends on gravity; calibrate at the scene's (cosim calibrate-scm SCENE) or use the DEM",
                "terrain.calibration",
                unit="m/s^2",
            )
        )
    fitted_grid = plan.terrain.calibration_node_spacing
    if fitted_grid is not None:
        spacing = parameters.node_spacing
        findings.append(
            _finding(
                "scm_calibration_grid",
                spacing,
                fitted_grid,
                abs(spacing - fitted_grid) <= 1e-6 * fitted_grid,
                f"on the grid the wheel fit ran on (node spacing {fitted_grid:.3g} m)",
                f"node spacing {spacing:.3g} m, the wheel fit ran on {fitted_grid:.3g} m: its fitted keys carry that "
                f"grid's wheel forces; set terrain.node_spacing = {fitted_grid!r} or fit on this grid (cosim "
                "calibrate-scm SCENE --from-wheel)",
                "terrain.node_spacing, terrain.calibration",
                unit="m",
            )
        )
    # judged on the run's own rim sinkage: Bekker's closed form for a smooth wheel is no estimate of
    # a grousered wheel's on SCM (the main job: 2.5x SCM's own)
    tested, rim = plan.terrain.calibration_sinkage, measured.get("sinkage")
    if tested is not None and rim is not None and math.isfinite(rim):
        findings.append(
            _finding(
                "scm_calibration_depth",
                rim / tested,
                1.0,
                rim <= tested,
                f"rim sinkage {rim:.3g} m within the {tested:.3g} m the calibration's DEM tests reached",
                f"rim sinkage {rim:.3g} m is beyond the {tested:.3g} m the calibration's DEM tests reached: "
                "Bekker's law is extrapolated; calibrate deeper (cosim calibrate-scm SCENE --set "
                "plate.max_sinkage=..., --from-wheel) or use the DEM",
                "terrain.calibration",
            )
        )
    return findings
