"""Is a scene a valid wheel test? Its dimensionless numbers against what the physics needs.

`check(plan, surface_height=None, sinkage_tips=None, wheel_spins=None)` returns one Finding per
check; each names the scene setting that changes it. `cosim advise` prints them, every run logs
them at its start and stores them in results.h5 and run.json, and after a run the measured
sinkage is checked against the floor (and a drive whose speeds its controller sets, Froude's
number on the measured speeds). A rover is judged on its worst wheel for each check: the
fastest (omega^2 r) for Froude, the narrowest for the grains across, the largest for the bed
depth, the deepest for the floor, the highest ground pressure for the overlaps.

    froude          Fr = omega^2 r_outer / |g| <= FROUDE_LIMIT: above it the result depends on the
                    wheel's speed, and further up the wheel hops (measured: docs/validity.md)
    contact_steps   Hertz contact time of two grains at the impact speed / the longest DEM step
                    (the fixed dt, or the PID's longest substep) >= CONTACT_STEPS
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
    at a sinkage s of one mean grain radius; a rover's highest (its narrowest, smallest wheel)."""

    def pressure(w) -> float:
        length = 2.0 * math.sqrt(2.0 * w.outer_radius * plan.bed.spec.radius_mean)
        return plan.wheel_load / (w.width * length)

    return max(pressure(w) for w in plan.wheels or (plan.wheel,))


def _omega_key(plan: RunPlan) -> str:
    """The scene key of the drive's wheel speeds."""
    if plan.testbed is not None:
        return "testbed.omega"
    assert plan.rover is not None and plan.scene.rover is not None  # a plan has a testbed or a rover
    named = isinstance(plan.scene.rover.drive, str)
    key = "omega_max" if plan.rover.drive.kind == "slip" else "speed"
    return f"rover.controllers.{plan.rover.drive.name}.{key}" if named else f"rover.drive.{key}"


def _froude_finding(plan: RunPlan, spins, how: str, check: str = "froude", advice: str = "") -> Finding | None:
    """Froude's number of the fastest wheel (omega^2 r / |g|, each wheel at its |omega| in `spins` [rad/s]),
    or None when no speed is known."""
    wheels = plan.wheels or (plan.wheel,)
    if spins is None or len(spins) != len(wheels) or not all(math.isfinite(float(v)) for v in spins):
        return None
    g = plan.g
    numbers = [float(v) ** 2 * w.outer_radius / g if g > 0 else math.inf for v, w in zip(spins, wheels)]
    k = max(range(len(wheels)), key=lambda i: numbers[i])
    fr, radius = numbers[k], wheels[k].outer_radius
    notes = ([f"wheel {k}, the fastest"] if len(wheels) > 1 else []) + ([how] if how else [])
    which = f" ({'; '.join(notes)})" if notes else ""
    key = _omega_key(plan)
    return _finding(
        check,
        fr,
        FROUDE_LIMIT,
        fr <= FROUDE_LIMIT,
        f"Froude number omega^2 r / g = {fr:.3g}{which} <= {FROUDE_LIMIT}: quasi-static"
        + (", as SCM's laws are" if check == "scm_froude" else ""),
        f"Froude number omega^2 r / g = {fr:.3g}{which} > {FROUDE_LIMIT}: "
        + (
            advice
            or "not quasi-static at this speed and gravity (the slip depends on the speed; faster, the wheel hops); "
            f"lower {key} to <= {math.sqrt(FROUDE_LIMIT * g / radius):.3g} rad/s"
        ),
        key,
    )


def _is_slip(plan: RunPlan) -> bool:
    return plan.rover is not None and plan.rover.drive.kind == "slip"


def check(
    plan: RunPlan,
    surface_height: float | None = None,
    sinkage_tips: float | None = None,
    wheel_spins=None,
    longest_substep: float | None = None,
) -> list[Finding]:
    """The validity findings of a plan; the settled surface height [m], the measured tip sinkage [m] (a
    rover's deepest wheel's), the measured wheel speeds [rad/s] (W,) and under the PID step control the
    longest substep it took [s] sharpen the depth, floor, Froude and contact checks when known (the PID's
    contact resolution is judged on the substeps it took only: its error control, not run.dt_max, sets
    them)."""
    spec, t = plan.bed.spec, plan.testbed
    wheels = plan.wheels or (plan.wheel,)
    narrowest = min(wheels, key=lambda w: w.width)  # the fewest grains across
    largest = max(wheels, key=lambda w: w.outer_radius)  # the deepest stress bulb
    diameter = 2.0 * spec.radius_mean
    findings = []
    drive = plan.wheel_speeds
    speeds = [float(v) for v in drive] if drive is not None else None
    how = "" if plan.testbed is not None else "at the slip controller's omega_max" if _is_slip(plan) else ""
    froude = _froude_finding(plan, speeds, how)
    if froude is None and wheel_spins is not None:
        speeds = [abs(float(v)) for v in wheel_spins]
        froude = _froude_finding(plan, speeds, "at the measured wheel speeds")
    if froude is not None:
        findings.append(froude)
    rims = [float(v) * w.outer_radius for v, w in zip(speeds, wheels)] if speeds is not None else []
    rim_speed = max((v for v in rims if math.isfinite(v)), default=0.0)

    g = plan.g
    material = plan.soil_material
    smallest = spec.radius_min
    depth_now = surface_height if surface_height is not None else spec.depth
    speed = math.sqrt(2 * g * max(depth_now, smallest)) + rim_speed
    contact = advisor.hertz_contact_time(
        material.youngs_modulus, material.poisson_ratio, material.density, smallest, max(speed, 1e-12)
    )
    pid = plan.step_control == "pid"
    measured_step = longest_substep is not None and math.isfinite(longest_substep) and longest_substep > 0
    if not pid or measured_step:
        dt, dt_key = (float(longest_substep or 0.0), "run.dt_max, run.tolerance") if pid else (plan.dt, plan.dt_setting)
        steps = contact / dt
        step_name = f"of the PID's longest substeps ({dt:.3g} s, taken)" if pid else "DEM steps"
        findings.append(
            _finding(
                "contact_steps",
                steps,
                CONTACT_STEPS,
                steps >= CONTACT_STEPS,
                f"{steps:.3g} {step_name} per contact time ({contact:.3g} s at {speed:.3g} m/s)",
                f"only {steps:.3g} {step_name} per contact time ({contact:.3g} s): contacts are under-resolved; "
                f"lower {dt_key} so the step is <= {contact / CONTACT_STEPS:.3g} s",
                dt_key,
            )
        )

    wheel = narrowest
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

    wheel = largest
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


NOT_CHECKED = "not checked (the terrain model has no validity checks)"
"""The verdict of a run with no findings (the analytic terrain): nothing was found valid."""


def verdict(findings: list[Finding]) -> str:
    """'valid', 'out of range: ' and the failed checks, comma-separated, or NOT_CHECKED without findings."""
    if not findings:
        return NOT_CHECKED
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
    """(check, what it will compare) for each check that only the run's own measurements can judge,
    so that advice before a run names it instead of passing over it: Froude's number when the drive's
    controller sets the wheel speeds as it goes (torque, FMU, Python drives), SCM's slip limit when the
    drive sets no slip (a free wheel, a speed or torque drive), the calibration depth
    (`scm_calibration_depth`), on the run's rim sinkage. Bekker's closed form for a smooth wheel is
    given beside it; on a grousered wheel it overstates SCM's own sinkage (the main job: 2.5x)."""
    from .scm_soil import bekker_wheel_sinkage, scm_settings

    pending = []
    indices, wheels = _scm_wheels(plan)
    if plan.step_control == "pid" and plan.terrain.model in ("dem", "mixed"):
        pending.append(
            (
                "contact_steps",
                "the contact time against the longest substep the PID takes (its error control sets them)",
            )
        )
    if plan.wheel_speeds is None:
        on = [
            c
            for c, there in (("froude", plan.terrain.model in ("dem", "mixed")), ("scm_froude", bool(wheels)))
            if there
        ]
        pending += [
            (c, "Froude's number at the run's measured wheel speeds (the drive sets them as it goes)") for c in on
        ]
    if wheels and _drive_slip(plan)[0] is None:
        pending.append(("scm_slip", f"the run's measured slip against |slip| <= {SCM_SLIP_LIMIT}"))
    tested = plan.terrain.calibration_sinkage
    if tested is None or not wheels:
        return pending
    parameters = scm_settings(plan, indices, 0.0).parameters
    wheel = min(wheels, key=lambda w: w.width)
    closed_form = bekker_wheel_sinkage(parameters, plan.wheel_load, wheel.outer_radius, wheel.width)
    side = "beyond" if closed_form > tested else "within"
    return pending + [
        (
            "scm_calibration_depth",
            f"the run's rim sinkage against the {tested:.3g} m the calibration's DEM tests reached (Bekker's "
            f"closed form for a smooth wheel: {closed_form:.3g} m, {side} it)",
        )
    ]


def _per_wheel(measured: dict, name: str, indices: list[int], count: int) -> list[float] | None:
    """The measured `name` of the wheels `indices` ([m]): a rover summary's wheel_<name> per wheel, else the
    summary's `name` for each (a single wheel); None when the run measured none."""
    each = measured.get(f"wheel_{name}")
    if each is not None and len(each) == count:
        values = [float(each[i]) for i in indices]
    elif measured.get(name) is not None:
        values = [float(measured[name])] * len(indices)
    else:
        return None
    finite = [v for v in values if math.isfinite(v)]
    return finite or None


def deepest(measured: dict | None, name: str, indices: list[int] | None = None) -> float | None:
    """The largest measured `name` ('sinkage', 'sinkage_tips' [m]) over the wheels `indices` (None: all) of a
    run summary (a rover's wheel_<name>, a single wheel's own); None when the run measured none."""
    measured = measured or {}
    each = measured.get(f"wheel_{name}")
    count = len(each) if each is not None else 1
    values = _per_wheel(measured, name, list(range(count)) if indices is None else indices, count)
    return max(values) if values else None


def scm_check(plan: RunPlan, measured: dict | None = None) -> list[Finding]:
    """Where the SCM tier cannot represent the run (each failed finding says what to do: use the DEM,
    or refine the grid, calibrate again): grouser-dominated traction (grouser height >
    SCM_GROUSER_RATIO x sinkage), a grid that samples the grousers instead of resolving them (node
    spacing > the thinnest grouser / NODES_ACROSS_GROUSER: `scm_grouser_grid`), a sinkage below
    SCM_SINKAGE_GRAINS grain diameters, a slip above SCM_SLIP_LIMIT, a Froude number above
    FROUDE_LIMIT, a calibration made at another gravity, a wheel fit made on another grid
    (`scm_calibration_grid`), and after a run a rim sinkage deeper than the calibration's DEM tests
    reached (`scm_calibration_depth`), and a slip outside those a wheel fit was fitted on
    (`scm_calibration_slips`). `measured`: a run summary's 'sinkage_tips', 'sinkage' [m] (a rover's
    per wheel: 'wheel_sinkage_tips', 'wheel_sinkage') and 'slip' [-]; before a run the sinkage is
    Bekker's closed form for each wheel's load and the slip the drive's imposed or target slip. A
    rover is judged on its worst SCM wheel: the shallowest for the grains under it, the one whose
    grousers are tallest for its sinkage, the deepest for the calibration's depth."""
    from .scm_calibration import same_gravity
    from .scm_soil import NODES_ACROSS_GROUSER, bekker_wheel_sinkage, grouser_thickness, scm_settings

    indices, wheels = _scm_wheels(plan)
    if not wheels:
        return []
    parameters = scm_settings(plan, indices, 0.0).parameters
    measured = measured or {}
    slip = measured.get("slip")
    # each SCM wheel's sinkage at its tips: measured (a rover's per wheel), or Bekker's closed form for its load
    tips = _per_wheel(measured, "sinkage_tips", indices, len(plan.wheels or (plan.wheel,)))
    if tips is not None:
        sinkages, how = tips, "measured"
    else:
        sinkages = [bekker_wheel_sinkage(parameters, plan.wheel_load, w.outer_radius, w.width) for w in wheels]
        how = "Bekker's closed form"
    findings = []

    def grouser_of(w) -> float:
        return float(getattr(w.shape, "grouser_height", 0.0)) if getattr(w.shape, "grouser_count", 0) else 0.0

    ratios = [grouser_of(w) / max(z, 1e-12) for w, z in zip(wheels, sinkages)]
    if any(grouser_of(w) > 0 for w in wheels):
        k = max(range(len(wheels)), key=lambda i: ratios[i])  # the wheel whose grousers carry the most
        grouser, sinkage = grouser_of(wheels[k]), sinkages[k]
        which = f"wheel {indices[k]}: " if len(plan.wheels) > 1 else ""
        findings.append(
            _finding(
                "scm_grousers",
                ratios[k],
                SCM_GROUSER_RATIO,
                grouser <= SCM_GROUSER_RATIO * sinkage,
                f"{which}grouser height {grouser:.3g} m <= {SCM_GROUSER_RATIO} x sinkage {sinkage:.3g} m ({how}): "
                "SCM's surface shear carries the traction",
                f"{which}grouser height {grouser:.3g} m > {SCM_GROUSER_RATIO} x sinkage {sinkage:.3g} m ({how}): the "
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
    sinkage = min(sinkages)  # the shallowest wheel rides on the fewest grains
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
                f"slip {slip:.3g} ({slip_how}): |slip| <= {SCM_SLIP_LIMIT}",
                f"slip {slip:.3g} ({slip_how}): |slip| > {SCM_SLIP_LIMIT}: the wheel digs in (slip sinkage, soil "
                "flowing round it), "
                f"outside SCM's steady Bekker-Janosi model; {USE_DEM}",
                key or "testbed.slip, rover.controllers",
            )
        )
        fitted = plan.terrain.calibration_slips
        if fitted is not None:
            low, high = fitted
            findings.append(
                _finding(
                    "scm_calibration_slips",
                    slip,
                    high if slip > high else low,
                    low - 1e-9 <= slip <= high + 1e-9,
                    f"slip {slip:.3g} ({slip_how}) within the slips the wheel fit was fitted on ({low:.3g} .. "
                    f"{high:.3g})",
                    f"slip {slip:.3g} ({slip_how}) outside the slips the wheel fit was fitted on ({low:.3g} .. "
                    f"{high:.3g}): its fitted keys are extrapolated there; fit over slips that include it (cosim "
                    "calibrate-scm SCENE --from-wheel on a slip study over them) or use the DEM",
                    "terrain.calibration, " + (key or "testbed.slip, rover.controllers"),
                )
            )
    dynamic = "a dynamic regime (soil inertia, the wheel hops) that SCM's quasi-static laws do not hold; " + USE_DEM
    froude = _froude_finding(plan, plan.wheel_speeds, "", "scm_froude", dynamic)
    if froude is None and measured.get("wheel_spin") is not None:
        spins = [abs(float(v)) for v in measured["wheel_spin"]]
        froude = _froude_finding(plan, spins, "at the measured wheel speeds", "scm_froude", dynamic)
    if froude is not None:
        findings.append(froude)
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
    rims = _per_wheel(measured, "sinkage", indices, len(plan.wheels or (plan.wheel,)))
    tested, rim = plan.terrain.calibration_sinkage, max(rims) if rims is not None else None  # the deepest wheel
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
