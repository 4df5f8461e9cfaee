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
    coupling_step   the macro step H as the phase of the wheel's bounce on one grain, omega H <=
                    DEM_BOUNCE_LIMIT: the exchange moves the wheel as if it were infinitely heavy for
                    a macro step, and a bounce it does not resolve gains energy
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

import numpy as np

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
DEM_BOUNCE_LIMIT = 2.0
"""Largest macro step for a wheel on the DEM as the phase of its bounce on one grain, omega H [rad]:
Gauss-Seidel's exchange of a mass on a linear spring is stable up to 2 rad (tests/test_coupler.py); on
the tiny scene's bed a wheel landed up to 3.5 rad by this measure and gained energy at each bounce from
4.4 rad (docs/validity.md, "The coupling step")."""


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


def _step_map(omega_dt: float, gamma_dt: float, integrator: str) -> np.ndarray:
    """One fixed step of `integrator` on a damped oscillator a = -omega^2 x - gamma v, as a matrix on the
    state in units of dt: jolt-Beeman (x, v dt, a dt^2, a(t - dt) dt^2), its damping seen at the predicted
    velocity (benchmarks/jolt_beeman_damped_stability.py); velocity Verlet (x, v dt, a dt^2), its damping
    at the half step's velocity (soil/integrator.py)."""
    w2, g = omega_dt**2, gamma_dt
    columns = []
    for unit in np.eye(4 if integrator == "jolt-beeman" else 3):
        if integrator == "jolt-beeman":
            x, v, a, a_minus = unit
            x_new = x + v + (4 * a - a_minus) / 6
            a_new = -w2 * x_new - g * (v + (3 * a - a_minus) / 2)
            columns.append([x_new, v + (2 * a_new + 5 * a - a_minus) / 6, a_new, a])
        else:
            x, v, a = unit
            half = v + a / 2
            x_new = x + half
            a_new = -w2 * x_new - g * half
            columns.append([x_new, half + a_new / 2, a_new])
    return np.array(columns).T


def stable_step(omega: float, gamma: float, integrator: str) -> float:
    """The longest fixed step [s] at which `integrator` keeps a mode of angular frequency `omega` [rad/s]
    and damping rate `gamma` [1/s] stable (the one-step map's spectral radius <= 1; tests/test_validity.py
    collides two grains at half and at twice it)."""

    def stable(dt: float) -> bool:
        return max(abs(np.linalg.eigvals(_step_map(omega * dt, gamma * dt, integrator)))) <= 1.0 + 1e-9

    low, high = 0.0, 4.0 / max(omega, 0.5 * gamma)  # unstable beyond: the undamped bound 2 / omega, or 2 / gamma
    for _ in range(60):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if stable(middle) else (low, middle)
    return low


def _stiff_mode_findings(
    plan: RunPlan, radius: float, speed: float, fall: str, dt: float, integrator: str, dt_key: str
) -> list[Finding]:
    """The damped contact modes and the rolling spring of an impact of the smallest grains at `speed` [m/s],
    judged at the fixed step `dt` [s] of `integrator` (its key `dt_key`): either outruns the step the
    normal spring is resolved with once the damping or the rolling resistance is large (an overdamped
    soil, mu_r of 1e3), which diverged naming other keys (or, short of that, realised another restitution
    than the scene's, or a stuck grain's spin grew: BENCHMARKS.md). From soil/contact.py, for a grain on a
    grain (m* = m / 2, R* = r / 2) and on a wall of the soil's stiffness (m* = m, R* = r; a wheel's
    contacts are not judged): normal, the Lehr dashpot 2 D sqrt(m* k_N), gamma = 2 D omega_N;
    tangential while a contact sticks (friction on), the Kelvin spring k_T = 8 G* sqrt(R* delta) and its
    dashpot 2 D sqrt(m* k_T) on the inverse mass 3.5 / m* of the grains' sliding and turning (a wall's too:
    1 / m + r^2 / I), omega_T = sqrt(3.5 k_T / m*), gamma_T = 7 D sqrt(k_T / m*); rolling, k_r = 2.25
    mu_r^2 R*^2 k_N and the damper 1.5 sqrt(1.4) mu_r R*^2 times the normal one, on the law's I* = 1.4
    m* R*^2 between grains (the pair's true 1.6 m* R*^2 gives a 7 % longer step: a bound), the grain's
    own 0.4 m r^2 on a wall (omega_r = 2.37 mu_r omega_N, gamma_r = 8.87 D mu_r omega_N). The stable
    step of a mode shrinks as 1 / mu_r for rolling, as 1 / D for a heavily damped one."""
    material = plan.soil_material
    nu = material.poisson_ratio
    mass = material.density * 4.0 / 3.0 * math.pi * radius**3
    e_star = material.youngs_modulus / (2.0 * (1.0 - nu**2))
    speed = max(speed, 1e-12)
    normal = {  # omega_N [rad/s] of the impact: two grains, a grain on a wall
        "grain on grain": 2.0 / advisor.hertz_impact(e_star, 0.5 * radius, 0.5 * mass, speed).critical_step,
        "grain on a wall": 2.0 / advisor.hertz_impact(e_star, radius, mass, speed).critical_step,
    }
    damping = material.lehr_damping if plan.law.damping else 0.0
    rolling = material.rolling_friction if plan.law.rolling else 0.0
    modes: dict[str, dict[str, tuple[float, float]]] = {"damping_step": {}, "rolling_step": {}}  # by check, where
    for where, omega in normal.items():
        if damping > 0:
            modes["damping_step"][where] = (omega, 2.0 * damping * omega)
        if damping > 0 and plan.law.friction:  # the stuck contact's Kelvin element, the grains turning too
            shear = 2.0 * (1.0 - nu) / (2.0 - nu)  # k_T / k_N = 4 G* / E*, G* = G / (2 (2 - nu)) (soil.materials)
            modes["damping_step"][f"{where}, stuck"] = (
                math.sqrt(3.5 * shear) * omega,
                7.0 * damping * math.sqrt(shear) * omega,
            )
        if rolling > 0 and where == "grain on grain":  # I* = 1.4 m* R*^2: the damper keeps the ratio D
            omega_r = 1.5 / math.sqrt(1.4) * rolling * omega
            gamma_r = 2.0 * damping * omega_r
        elif rolling > 0:  # the grain alone turns (0.4 m r^2) where the law counts 1.4 m r^2: 1.87 D
            omega_r = math.sqrt(2.25 / 0.4) * rolling * omega
            gamma_r = 2.0 * damping * 1.5 * math.sqrt(1.4) / 0.4 * rolling * omega
        if rolling > 0:
            modes["rolling_step"][where] = (omega_r, gamma_r)
    at = f"{dt:.3g} s ({dt_key}, {integrator}), an impact of the smallest grains at {speed:.3g} m/s{fall}"
    findings = []
    for check, cases in modes.items():
        if not cases:
            continue
        longest = {where: stable_step(omega, gamma, integrator) for where, (omega, gamma) in cases.items()}
        where = min(longest, key=lambda k: longest[k])
        share = dt / longest[where]
        mode = (
            f"the damped {'tangential' if where.endswith('stuck') else 'normal'} mode (D = {damping:.3g}, {where})"
            if check == "damping_step"
            else f"the rolling spring (mu_r = {rolling:g}, D = {damping:.3g}, {where})"
        )
        remedy = (
            "raise soil.restitution (or lower soil.damping_ratio)"
            if check == "damping_step"
            else "lower soil.rolling_friction (the stable step grows as 1 / mu_r)"
        )
        keys = "soil.restitution, soil.damping_ratio" if check == "damping_step" else "soil.rolling_friction"
        text = f"the step {at} is {share:.3g} x the longest that keeps {mode} stable ({longest[where]:.3g} s)"
        findings.append(
            _finding(check, share, 1.0, share <= 1.0, text, f"{text}: {remedy}, or lower {dt_key}", f"{keys}, {dt_key}")
        )
    return findings


SINGLE_OVERLAP_SPACINGS = 100
"""The fewest float32 spacings a wheel's grain contact must overlap by in single precision [count]: a
spacing's error in the overlap is 1.5 / this of the Hertz force (1.5 %)."""


def _single_precision_finding(plan: RunPlan) -> Finding:
    """Single precision holds positions in float32: the overlap of a grain carrying the wheel's ground
    pressure (its share on (2r)^2) must span many float32 spacings at the bed's coordinates, or the
    contact force is rounding (the paper's milli-g trap: docs/physics.md section 3)."""
    spec, material = plan.bed.spec, plan.soil_material
    r = spec.radius_mean
    e_star = material.youngs_modulus / (2.0 * (1.0 - material.poisson_ratio**2))
    force = ground_pressure(plan) * (2.0 * r) ** 2
    overlap = (3.0 * force / (4.0 * e_star * math.sqrt(0.5 * r))) ** (2.0 / 3.0)
    extent = max(spec.length, spec.width, spec.depth)  # the bed's grains lie within it of the origin
    where = f"{extent:.3g} m from the origin"
    if plan.patch is not None:  # a patch moves its grains with the rover, in the world's coordinates
        speeds = plan.wheel_speeds
        wheels = plan.wheels or (plan.wheel,)
        rims = [abs(float(v)) * w.outer_radius for v, w in zip(speeds, wheels)] if speeds is not None else []
        travel = plan.scene.run.duration * max(rims, default=0.0)
        extent += travel
        where = f"{extent:.3g} m from the origin after the drive" if rims else f"{where}, at the patch's start"
    spacing = float(np.spacing(np.float32(extent)))
    spacings = overlap / spacing
    what = (
        f"{spacings:.3g} float32 spacings ({spacing:.2g} m at {where}) in the overlap "
        f"{overlap:.3g} m of a grain under the wheel's {ground_pressure(plan):.3g} Pa"
    )
    return _finding(
        "single_precision",
        spacings,
        SINGLE_OVERLAP_SPACINGS,
        spacings >= SINGLE_OVERLAP_SPACINGS,
        what,
        f"only {what}: single precision rounds the contacts that carry the wheel; set scene.precision = "
        '"mixed" (float64 positions, float32 contacts) or "double"',
        "scene.precision",
    )


def stiff_mode_hint(plan: RunPlan, settling: bool = False) -> str:
    """The damping_step and rolling_step findings that fail for a plan on the grains, for a divergence's
    message ('' when both pass, or under the PID): the keys the message names otherwise do not cover them.
    settling: judged at the bed's settling step (bed.settle_dt_factor, velocity Verlet) and a fall through
    the fill height, else at the run's step as `check` judges them."""
    if plan.step_control == "pid":
        return ""
    if settling:
        spec = plan.bed.spec
        speed = math.sqrt(2.0 * plan.g * max(spec.depth, spec.radius_min))
        fall = f": a fall through the fill height {spec.depth:.3g} m"
        step, integrator = plan.bed.settle_dt, "velocity-verlet"  # soil.bed.make_settled_bed's fixed steps
        found = _stiff_mode_findings(plan, spec.radius_min, speed, fall, step, integrator, "bed.settle_dt_factor")
    else:  # a mixed terrain's DEM wheels only, as its validity judges them
        wheels = getattr(plan.terrain, "wheel_models", None)
        dem = [i for i, m in enumerate(wheels) if m == "dem"] if plan.terrain.model == "mixed" and wheels else None
        found = [f for f in check(plan, indices=dem) if f.check in ("damping_step", "rolling_step")]
    return "".join(f"; {f.check}: {f.message}" for f in found if not f.ok)


def _judged(plan: RunPlan, indices=None) -> list[int]:
    """The indices of the wheels a check judges: `indices` (a mixed terrain's wheels of one model), or all."""
    count = len(plan.wheels or (plan.wheel,))
    return list(range(count)) if indices is None else [int(i) for i in indices]


def ground_pressure(plan: RunPlan, indices=None) -> float:
    """Wheel ground pressure [Pa]: the load over the width times a contact length 2 sqrt(2 R s)
    at a sinkage s of one mean grain radius; a rover's highest (its narrowest, smallest wheel) among
    the wheels `indices` (None: all)."""
    wheels = plan.wheels or (plan.wheel,)

    def pressure(w) -> float:
        length = 2.0 * math.sqrt(2.0 * w.outer_radius * plan.bed.spec.radius_mean)
        return plan.wheel_load / (w.width * length)

    return max(pressure(wheels[i]) for i in _judged(plan, indices))


def _omega_key(plan: RunPlan) -> str:
    """The scene key that sets the drive's wheel speeds: the testbed's omega, a speed drive's speed, a slip
    controller's omega_max, a torque drive's torque, or the controller itself (an FMU or Python drive)."""
    if plan.testbed is not None:
        return "testbed.omega"
    assert plan.rover is not None and plan.scene.rover is not None  # a plan has a testbed or a rover
    named = isinstance(plan.scene.rover.drive, str)
    base = f"rover.controllers.{plan.rover.drive.name}" if named else "rover.drive"
    key = {"slip": "omega_max", "speed": "speed", "torque": "torque"}.get(plan.rover.drive.kind)
    return f"{base}.{key}" if key else base


def _froude_finding(
    plan: RunPlan, spins, how: str, check: str = "froude", advice: str = "", indices=None
) -> Finding | None:
    """Froude's number of the fastest of the wheels `indices` (None: all; omega^2 r / |g|, each wheel at its
    |omega| in `spins` [rad/s], one per wheel of the plan; a nan speed is not known), or None when no speed
    of them is known."""
    wheels = plan.wheels or (plan.wheel,)
    if spins is None or len(spins) != len(wheels):
        return None
    known = [i for i in _judged(plan, indices) if math.isfinite(float(spins[i]))]
    if not known:
        return None
    g = plan.g
    numbers = {i: float(spins[i]) ** 2 * wheels[i].outer_radius / g if g > 0 else math.inf for i in known}
    k = max(known, key=lambda i: numbers[i])
    fr, radius = numbers[k], wheels[k].outer_radius
    notes = ([f"wheel {k}, the fastest"] if len(wheels) > 1 else []) + ([how] if how else [])
    which = f" ({'; '.join(notes)})" if notes else ""
    key = _omega_key(plan)
    slower = (
        "without gravity no speed is quasi-static (nothing holds the wheel to the soil): give scene.gravity"
        if g <= 0
        else f"lower {key} to <= {math.sqrt(FROUDE_LIMIT * g / radius):.3g} rad/s"
        if key.endswith(("omega", "speed", "omega_max"))
        else f"slow the drive ({key}) to <= {math.sqrt(FROUDE_LIMIT * g / radius):.3g} rad/s"
    )
    return _finding(
        check,
        fr,
        FROUDE_LIMIT,
        fr <= FROUDE_LIMIT,
        f"Froude number omega^2 r_outer / g = {fr:.3g}{which} <= {FROUDE_LIMIT}: quasi-static"
        + (", as SCM's laws are" if check == "scm_froude" else ""),
        f"Froude number omega^2 r_outer / g = {fr:.3g}{which} > {FROUDE_LIMIT}: "
        + (
            advice
            or "not quasi-static at this speed and gravity (the slip depends on the speed; faster, the wheel hops); "
            + slower
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
    indices=None,
) -> list[Finding]:
    """The validity findings of a plan on the DEM, judging the wheels `indices` (None: all; a mixed
    terrain's DEM wheels); the settled surface height [m], the measured tip sinkage [m] (the deepest judged
    wheel's), the measured wheel speeds [rad/s] (W,) and under the PID step control the longest substep it
    took [s] sharpen the depth, floor, Froude and contact checks when known. Under the PID, contact_steps
    is judged before the run at its longest substep allowed (run.dt_max) when the contact passes there;
    else it waits for the substeps taken (its error control, not the bound, sets them). Where the drive
    sets the wheels' speeds as it goes (torque, FMU, Python) and none were measured, contact_steps is
    judged only when it fails at still rims (faster rims shorten a contact): a pass waits for the run."""
    spec, t = plan.bed.spec, plan.testbed
    every = plan.wheels or (plan.wheel,)
    chosen = _judged(plan, indices)
    wheels = [every[i] for i in chosen]
    narrowest = min(wheels, key=lambda w: w.width)  # the fewest grains across
    largest = max(wheels, key=lambda w: w.outer_radius)  # the deepest stress bulb
    diameter = 2.0 * spec.radius_mean
    findings = []
    drive = plan.wheel_speeds
    speeds = [float(v) for v in drive] if drive is not None else None
    how = "" if plan.testbed is not None else "at the slip controller's omega_max" if _is_slip(plan) else ""
    froude = _froude_finding(plan, speeds, how, indices=chosen)
    if froude is None and wheel_spins is not None and len(wheel_spins) == len(every):
        speeds = [abs(_number(v)) for v in wheel_spins]
        froude = _froude_finding(plan, speeds, "at the measured wheel speeds", indices=chosen)
    if froude is not None:
        findings.append(froude)
    rims = [float(speeds[i]) * every[i].outer_radius for i in chosen] if speeds is not None else []
    rim_speed = max((v for v in rims if math.isfinite(v)), default=0.0)

    g = plan.g
    material = plan.soil_material
    smallest = spec.radius_min
    depth_now = surface_height if surface_height is not None else spec.depth
    speed = math.sqrt(2 * g * max(depth_now, smallest)) + rim_speed
    # a grain's fall through the bed plus the rims' speed; before settling, through the fill height (higher)
    fall = (
        f": a fall through {'the settled bed' if surface_height is not None else 'the fill height'} "
        f"{depth_now:.3g} m plus the rims' {rim_speed:.3g} m/s"
        if g > 0
        else f": the rims' {rim_speed:.3g} m/s (no gravity, no fall)"
    )
    contact = advisor.hertz_contact_time(
        material.youngs_modulus, material.poisson_ratio, material.density, smallest, max(speed, 1e-12)
    )
    if plan.step_control != "pid":
        dt, dt_key, step_name = plan.dt, plan.dt_setting, "DEM steps"
        if speeds is None and contact / dt >= CONTACT_STEPS:  # faster rims shorten the contact: not passed yet
            dt = math.nan
    elif longest_substep is not None and math.isfinite(longest_substep) and longest_substep > 0:
        dt, dt_key = float(longest_substep), "run.dt_max, run.tolerance"
        step_name = f"of the PID's longest substeps ({dt:.3g} s, taken)"
    else:  # before the run: run.dt_max, judged only when it resolves a contact (shorter substeps may)
        dt, dt_key = plan.dt_max if plan.dt_max is not None else math.nan, "run.dt_max"
        step_name = f"of the PID's longest substeps allowed ({dt:.3g} s)"
        if not contact / dt >= CONTACT_STEPS or speeds is None:  # unset (the advisor's limit) too; rims unknown
            dt = math.nan
    if math.isfinite(dt):
        steps = contact / dt
        findings.append(
            _finding(
                "contact_steps",
                steps,
                CONTACT_STEPS,
                steps >= CONTACT_STEPS,
                f"{steps:.3g} {step_name} per contact time ({contact:.3g} s at {speed:.3g} m/s{fall})",
                f"only {steps:.3g} {step_name} per contact time ({contact:.3g} s at {speed:.3g} m/s{fall}): contacts "
                "are under-resolved; "
                f"lower {dt_key} so the step is <= {contact / CONTACT_STEPS:.3g} s",
                dt_key,
            )
        )

    if plan.step_control != "pid":  # the PID's error control shortens the substeps a stiff mode needs
        findings += _stiff_mode_findings(plan, smallest, speed, fall, plan.dt, plan.integrator, plan.dt_setting)
    bounce = _dem_bounce_finding(plan, wheels, rim_speed)
    if bounce is not None:
        findings.append(bounce)
    if plan.precision == "single":
        findings.append(_single_precision_finding(plan))

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
    # bed.depth is the fill height: the settled bed is the measured fraction of it (before settling, unknown:
    # the fill is judged as it is, and named as such)
    settled_fraction = surface_height / spec.depth if surface_height is not None and spec.depth > 0 else 1.0
    settled = settled_fraction > 0 and surface_height is not None  # a bed settled to nothing: no fraction to take
    settled_fraction = settled_fraction if settled else 1.0
    fill = (
        f"bed.depth (the fill height: the bed settles to {settled_fraction:.2g} x it here)"
        if settled
        else "bed.depth (the fill height; the bed settles lower, which the run judges)"
    )
    radii = depth / wheel.outer_radius
    findings.append(
        _finding(
            "bed_depth",
            radii,
            DEPTH_RADII,
            radii >= DEPTH_RADII,
            f"bed depth {depth:.3g} m = {radii:.3g} wheel radii{estimated}",
            f"the bed is {depth:.3g} m deep{estimated}, {radii:.3g} wheel radii: the floor carries part of the "
            f"wheel's load; deepen {fill} to >= {DEPTH_RADII * wheel.outer_radius / settled_fraction:.3g} m",
            "bed.depth",
        )
    )

    sink = max(sinkage_tips or 0.0, 0.0)
    clearance = (depth - sink) / diameter
    when = f"at the measured tip sinkage {sink:.3g} m" if sinkage_tips is not None else f"at the start{estimated}"
    findings.append(
        _finding(
            "floor_clearance",
            clearance,
            FLOOR_GRAINS,
            clearance >= FLOOR_GRAINS,
            f"{clearance:.3g} grain diameters between the grouser tips and the floor {when}",
            (
                f"only {clearance:.3g} grain diameters between the grouser tips and the floor {when}: the wheel feels "
                "the floor"
                if clearance >= 0
                else f"the grouser tips went {-clearance:.3g} grain diameters below the floor {when}: the wheel "
                "passed through it (it has no contact with the container, only with the grains), so the run "
                "measured no soil there"
            )
            + f"; deepen {fill} to >= {(FLOOR_GRAINS * diameter + sink) / settled_fraction:.3g} m",
            "bed.depth",
        )
    )

    if t is not None:
        side = (spec.width - wheel.width) / 2 / diameter
        # the hub's travel over the drive: the rim's speed in free mode (at most on level ground; a downhill
        # gravity can push the carriage faster, not reckoned here), the carriage's in slip mode (1 - slip of
        # it: a negative slip drives it faster than the rim), as the plan's wall check takes it
        speed = t.omega * wheel.outer_radius * ((1 - t.slip) if t.mode == "slip" else 1.0)
        end = (spec.length - (t.start_x + wheel.outer_radius + speed * plan.scene.run.duration)) / diameter
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

    pressure = ground_pressure(plan, chosen)
    bound = advisor.macroscopic_stiffness(depth, pressure, OVERLAP_RATIO, spec.radius_mean, material.density, g)
    ratio = material.youngs_modulus / bound if bound > 0 else math.inf
    findings.append(
        _finding(
            "overlap",
            ratio,
            1.0,
            ratio >= 1.0,
            f"E = {material.youngs_modulus:.3g} Pa is {ratio:.3g} x the eq. 10 bound {bound:.3g} Pa (overlaps <= "
            f"{OVERLAP_RATIO} r under the wheel's {pressure:.3g} Pa; z_h = {depth:.3g} m"
            + (", the fill height: the settled bed is lower)" if estimated else ", the settled bed)"),
            f"E = {material.youngs_modulus:.3g} Pa is below the eq. 10 bound {bound:.3g} Pa: overlaps exceed "
            f"{OVERLAP_RATIO} r under the wheel; raise soil.youngs_modulus",
            "soil.youngs_modulus",
        )
    )
    return findings


NOT_CHECKED = "not checked (the terrain model has no validity checks)"
"""The verdict of a run with no findings (the analytic terrain): nothing was found valid."""


def verdict(findings: list[Finding], not_judged: list[str] | tuple = ()) -> str:
    """'valid', 'out of range: ' and the failed checks, comma-separated, or NOT_CHECKED without findings;
    `not_judged`: the checks a run could not judge (judged_after_the_run's left after it: it measured
    nothing to judge them on, a wheel that never landed), named after it."""
    if not findings and not not_judged:
        return NOT_CHECKED
    failed = [f.check for f in findings if not f.ok]
    said = "valid" if not failed else "out of range: " + ", ".join(failed)
    if not_judged:
        said += f"; not judged: {', '.join(not_judged)} (the run measured nothing to judge them on)"
    return said


# -- the SCM tier ------------------------------------------------------------------------------

SCM_GROUSER_RATIO = 0.5
"""Largest grouser height / sinkage for SCM [-]: taller grousers carry the traction by shearing soil
between them, which a height field's surface shear does not represent."""
SCM_SINKAGE_GRAINS = 3.0
"""Shallowest sinkage for SCM, in grain diameters [-]: shallower, the wheel rides on a few grains and
the continuum's pressure-sinkage curve does not hold."""
SCM_SLIP_LIMIT = 0.5
"""Highest slip for SCM [-]: beyond it the wheel digs in (soil flows round it, sinkage by slip) and the
steady-state Bekker/Janosi model is outside the measured range. At slip 0.6 the DEM's wheel digs in for
the whole drive, and neither wheel fit to the DEM's 14 s tables gives its thrust (DP/W -0.02..-0.03
against +0.22..+0.24; of the earlier fits, to 10 s tables, one agreed there and the rest gave
+0.003..+0.19 against +0.24..+0.26); at 0.4 the Phobos fit lies inside the DEM's interval (BENCHMARKS.md,
"The steady window starts once the sinkage has settled"); 0.5 lies between."""
SCM_BOUNCE_LIMIT = 2.0
"""Largest coupling step for SCM as the phase of a wheel's elastic bounce on the soil, omega_e H [rad]:
the main job's forces are within 0.3 % of a fine step's up to 1 rad and 2-3 % off at 2 rad
(BENCHMARKS.md, "SCM's own coupling step"); 2 rad is also where an explicit exchange of a mass on a
spring (the wheel on K_e) stops being stable."""

LAB_CHECK_KEYS = {
    "plate speed": "plate.speed_ratio",
    "plate inertial number": "plate.speed_ratio",
    "plate stiffness": "plate.max_sinkage",
    "shear inertial number": "shear.inertial_number",
    "shear stiffness": "shear.normal_stresses",
}
"""The lab scene key that changes each quasi-static number calibrate-scm records (cosim.lab: plate, shear)."""


def lab_check_keys(failed) -> list[str]:
    """The lab scene keys that change the failed checks `failed` (cosim.scm_calibration.failed_lab_checks'
    texts), sorted; [] for a check no key is known for."""
    return sorted({key for text in failed for name, key in LAB_CHECK_KEYS.items() if text.startswith(name)})


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


def judged_after_the_run(plan: RunPlan, findings: list[Finding]) -> list[tuple[str, str]]:
    """(check, what it will compare) for each check that only the run's own measurements can judge,
    so that advice before a run names it instead of passing over it: Froude's number when the drive's
    controller sets the wheel speeds as it goes (torque, FMU, Python drives), SCM's slip limit when the
    drive sets no slip (a free wheel, a speed or torque drive) and a wheel fit's slips, the PID's contact
    resolution when its longest substep allowed does not resolve a contact, the calibration depth
    (`scm_calibration_depth`), on the run's rim sinkage. Bekker's closed form for a smooth wheel is
    given beside it; on a grousered wheel it overstates SCM's own sinkage (the main job: 2.5x).
    `findings`: those made before the run (cosim.system.validity's); a check among them is not listed."""
    from .scm_soil import bekker_wheel_sinkage, scm_settings

    made = {f.check for f in findings}
    pending = []
    indices, wheels = _scm_wheels(plan)
    if plan.terrain.model in ("dem", "mixed") and plan.step_control == "pid":
        pending.append(
            (
                "contact_steps",
                "the contact time against the longest substep the PID takes (its error control sets them; "
                "run.dt_max, unset or too long, does not resolve a contact by itself)",
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
        if plan.terrain.model in ("dem", "mixed") and plan.step_control != "pid":  # the PID's: listed above
            pending.append(
                (
                    "contact_steps",
                    "the contact time at the run's measured rim speeds against the DEM step (the drive sets "
                    "the speeds as it goes; faster rims make shorter contacts)",
                )
            )
    if wheels and _drive_slip(plan)[0] is None:
        pending.append(("scm_slip", f"the run's measured slip against |slip| <= {SCM_SLIP_LIMIT}"))
        if plan.terrain.calibration_slips is not None:
            low, high = plan.terrain.calibration_slips
            pending.append(
                ("scm_calibration_slips", f"the run's measured slip against the fit's {low:.3g} .. {high:.3g}")
            )
    tested = plan.terrain.calibration_sinkage
    if tested is not None and wheels:
        parameters = scm_settings(plan, indices, 0.0).parameters
        wheel = min(wheels, key=lambda w: w.width)
        closed_form = bekker_wheel_sinkage(parameters, plan.wheel_load, wheel.outer_radius, wheel.width)
        side = "beyond" if closed_form > tested else "within"
        pending.append(
            (
                "scm_calibration_depth",
                f"the run's rim sinkage against the {tested:.3g} m the calibration's DEM tests reached (Bekker's "
                f"closed form for a smooth wheel: {closed_form:.3g} m, {side} it)",
            )
        )
    return [(check, what) for check, what in pending if check not in made]


def _per_wheel(measured: dict, name: str, indices: list[int], count: int) -> list[float] | None:
    """The measured `name` of the wheels `indices`, in their order: a rover summary's wheel_<name> per wheel,
    else the summary's `name` for each (a single wheel); a value not measured is nan in its place; None
    when the run measured none of them."""
    each = measured.get(f"wheel_{name}")
    if each is not None and len(each) == count:
        values = [_number(each[i]) for i in indices]
    elif measured.get(name) is not None:
        values = [_number(measured[name])] * len(indices)
    else:
        return None
    return values if any(math.isfinite(v) for v in values) else None


def _number(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):  # a null of a JSON summary
        return math.nan


def _finite(values) -> list[float]:
    return [v for v in values if math.isfinite(v)]


def deepest(measured: dict | None, name: str, indices: list[int] | None = None) -> float | None:
    """The largest measured `name` ('sinkage', 'sinkage_tips' [m]) over the wheels `indices` (None: all) of a
    run summary (a rover's wheel_<name>, a single wheel's own); None when the run measured none."""
    measured = measured or {}
    each = measured.get(f"wheel_{name}")
    count = len(each) if each is not None else 1
    values = _per_wheel(measured, name, list(range(count)) if indices is None else indices, count)
    return max(_finite(values)) if values else None


def _wheel_fit_finding(plan: RunPlan, fit, indices: list[int], wheels: list) -> Finding:
    """`scm_calibration_wheel`: the SCM wheels against the wheel and load a wheel fit was fitted on
    (cosim.scm_calibration.FittedWheel), each wheel at the plan's load per wheel (a rover's: its weight over
    its wheels); the worst relative difference against WHEEL_FIT_TOLERANCE (inf for a wheel of another
    kind, another mesh, or grousers where it had none). A rover's message lists its worst wheel's."""
    from .scm_calibration import WHEEL_FIT_TOLERANCE, wheel_record

    limit = WHEEL_FIT_TOLERANCE * (1.0 + 1e-9)  # 10 % itself is within

    def differences(wheel) -> list[tuple[float, str]]:
        record = wheel_record(wheel)
        if record["type"] != fit.type:
            return [(math.inf, f"a {record['type']} wheel, the fit's a {fit.type} wheel")]
        out = []
        if fit.type == "mesh" and record["mesh_sha256"] != fit.mesh_sha256:
            out.append((math.inf, "another mesh or scale (its vertices differ from the fit's)"))
        for name, value, fitted, unit in (
            ("rim radius", record["rim_radius_m"], fit.rim_radius, " m"),
            ("width", record["width_m"], fit.width, " m"),
            ("grouser count", record["grouser_count"], fit.grouser_count, ""),
            ("grouser height", record["grouser_height_m"], fit.grouser_height, " m"),
            ("load", plan.wheel_load, fit.load, " N"),
        ):
            if value == fitted:
                continue
            relative = abs(value - fitted) / fitted if fitted > 0 else math.inf
            percent = f"{100.0 * relative:.4g}"
            if relative > limit and float(percent) <= 100.0 * WHEEL_FIT_TOLERANCE:  # never "10%" on a failure
                percent = f"{100.0 * relative:.12g}"
            off = f"{percent}% off" if math.isfinite(relative) else "none in the fit"
            out.append((relative, f"{name} {value:.4g}{unit} (the fit's {fitted:.4g}{unit}: {off})"))
        return out

    each = [(k, differences(w)) for k, w in zip(indices, wheels)]
    k, worst = max(each, key=lambda pair: max((d for d, _ in pair[1]), default=0.0))
    largest = max((d for d, _ in worst), default=0.0)
    beyond = [text for d, text in worst if d > limit]
    which = f"wheel {k}: " if len(plan.wheels) > 1 else ""
    if fit.type == "mesh":
        fitted = f"mesh wheel of outer radius {fit.rim_radius:.4g} m, width {fit.width:.4g} m"
    elif fit.grouser_count:
        grousers = f"{fit.grouser_count} grouser{'s' if fit.grouser_count > 1 else ''}"
        fitted = (
            f"wheel of rim radius {fit.rim_radius:.4g} m, width {fit.width:.4g} m, {grousers} "
            f"{fit.grouser_height:.4g} m tall"
        )
    else:
        fitted = f"smooth wheel of rim radius {fit.rim_radius:.4g} m, width {fit.width:.4g} m"
    if plan.rover is None:
        setting = "terrain.calibration, wheel, testbed.mass, scene.gravity"
    else:
        setting = "terrain.calibration, wheel, rover.wheel_shape, rover, scene.gravity"
    if not plan.g > 0:  # a wheel fit, and a lab calibration, need a load
        remedy = "a wheel fit needs a loaded wheel (gravity > 0): use the DEM"
    elif plan.rover is None:
        remedy = (
            "fit this one (cosim calibrate-scm SCENE --from-wheel on its slip study), use a lab calibration (cosim "
            "calibrate-scm SCENE) or the DEM"
        )
    else:
        remedy = (
            "fit this wheel on a single-wheel scene at this rover's load per wheel "
            f"({plan.wheel_load:.4g} N: testbed.mass = {plan.wheel_load / plan.g:.4g} kg) with cosim calibrate-scm "
            "--from-wheel, use a lab calibration (cosim calibrate-scm SCENE) or the DEM"
        )
    return _finding(
        "scm_calibration_wheel",
        largest,
        WHEEL_FIT_TOLERANCE,
        largest <= limit,
        f"{which}the wheel and load the wheel fit was fitted on, within {WHEEL_FIT_TOLERANCE:.0%} (a {fitted} at "
        f"{fit.load:.4g} N)",
        f"{which}{'; '.join(beyond)}: not the wheel and load the wheel fit was fitted on (a {fitted} at "
        f"{fit.load:.4g} N; {WHEEL_FIT_TOLERANCE:.0%} either way is taken for it): its fitted keys compensate SCM's "
        f"errors for that wheel; {remedy}",
        setting,
    )


def wheel_bounce(plan: RunPlan, wheel, rim_speed: float) -> tuple[float, float, float]:
    """(omega [rad/s], mass [kg], impact speed [m/s]) of a wheel (a WheelPlan) bouncing on one grain of the
    DEM: the largest grain (its Hertz contact the stiffest) held as a wall under the wheel's share of the load
    as a mass (the testbed's mass, a rover's mass over its wheels: a rigid rover's heave; a sprung wheel's
    own mass is less), struck at a fall of one grain diameter (the wheel starts on the grains' tops, which
    straddle the surface by about that) plus `rim_speed` [m/s] (the grousers strike grains at it), omega =
    2 / soil.advisor.hertz_impact(...).critical_step (the tangent stiffness at the impact's deepest overlap).
    A measure calibrated on the DEM (docs/validity.md, "The coupling step"), not a bound: a wheel resting
    on several grains held as walls is stiffer, the grains' own give softer. omega nan without gravity."""
    from soil.materials import pair_properties

    mass = plan.testbed.mass if plan.rover is None and plan.testbed is not None else math.nan
    if plan.rover is not None:
        mass = plan.rover.mass / len(plan.wheels or (plan.wheel,))
    spec, g = plan.bed.spec, plan.g
    speed = math.sqrt(2.0 * g * 2.0 * spec.radius_mean) + rim_speed
    if not (g > 0 and mass > 0 and math.isfinite(mass) and speed > 0):
        return math.nan, mass, speed
    e_star = pair_properties(plan.soil_material, wheel.material).effective_modulus
    impact = advisor.hertz_impact(e_star, spec.radius_max, mass, speed)
    return 2.0 / impact.critical_step, mass, speed


def _dem_bounce_finding(plan: RunPlan, wheels, rim_speed: float) -> Finding | None:
    """coupling_step: the macro step H against the DEM wheels' bounce on a grain (`wheel_bounce`; the
    stiffest wheel), omega H <= DEM_BOUNCE_LIMIT; None without gravity. The remedy names the key the scene
    sets H by (run.substeps, or run.macro_step: a whole number of a given run.dt)."""
    omega, mass, speed = max((wheel_bounce(plan, w, rim_speed) for w in wheels), key=lambda b: b[0])
    if not math.isfinite(omega):
        return None
    phase, step = omega * plan.macro_step, plan.macro_step
    longest = _three_digits_down(DEM_BOUNCE_LIMIT / omega)
    what = (
        f"the macro step {step:.4g} s is omega H = {phase:.4g} rad of the wheel's bounce on a grain (omega "
        f"{omega:.4g} rad/s: {mass:.3g} kg of load per wheel on one Hertz contact struck at {speed:.3g} m/s)"
    )
    run = plan.scene.run
    substeps = math.floor(DEM_BOUNCE_LIMIT / (omega * plan.dt) * (1.0 + 1e-9))  # at the DEM step as it is
    if substeps < 1:
        remedy = f"not even one DEM step ({plan.dt:.3g} s) resolves it: load the wheel more, or soften the soil"
    elif run.macro_step is None:
        remedy = f"set run.substeps <= {substeps}"
    elif run.dt is not None:  # H a whole number of the given steps
        remedy = f"set run.macro_step <= {substeps * plan.dt:.6g} s ({substeps} x run.dt)"
    else:  # the DEM step shrinks to make H whole
        remedy = f"set run.macro_step <= {longest:.3g} s"
    return _finding(
        "coupling_step",
        phase,
        DEM_BOUNCE_LIMIT,
        phase <= DEM_BOUNCE_LIMIT,
        f"{what}: <= {DEM_BOUNCE_LIMIT:g} rad",
        f"{what}, above {DEM_BOUNCE_LIMIT:g} rad: the soil moves the wheel as if it were infinitely heavy for a "
        "macro step, so the exchange does not resolve its bounce and the wheel can gain energy at each (a light "
        f"wheel bounces off the soil); {remedy}",
        "run.macro_step, run.substeps",
        "rad",
    )


def _three_digits_down(value: float) -> float:
    """`value` > 0 rounded down to three significant digits (a bound to print that its own text meets)."""
    scale = 10.0 ** (math.floor(math.log10(value)) - 2)
    return math.floor(value / scale) * scale


def _bounce_finding(plan: RunPlan, parameters, wheels) -> Finding | None:
    """scm_coupling_step: the macro step H against the SCM wheels' elastic bounce on the soil, omega_e H
    <= SCM_BOUNCE_LIMIT (cosim.scm_soil.elastic_bounce; the stiffest wheel); None without gravity or load."""
    from .scm_soil import BOUNCE_PHASE, elastic_bounce

    if not (plan.g > 0 and plan.wheel_load > 0):
        return None
    omega = max(elastic_bounce(parameters, w, plan.wheel_load, plan.g)[0] for w in wheels)
    phase, step = omega * plan.macro_step, plan.macro_step
    return _finding(
        "scm_coupling_step",
        phase,
        SCM_BOUNCE_LIMIT,
        phase <= SCM_BOUNCE_LIMIT,
        f"the macro step {step:.4g} s is omega_e H = {phase:.4g} rad of the wheel's elastic bounce on the soil "
        f"(omega_e {omega:.4g} rad/s): <= {SCM_BOUNCE_LIMIT:g} rad",
        f"the macro step {step:.4g} s is omega_e H = {phase:.4g} rad of the wheel's elastic bounce on the soil "
        f"(omega_e {omega:.4g} rad/s), above {SCM_BOUNCE_LIMIT:g} rad: the exchange does not resolve the bounce "
        f"(forces 2-3 % off a fine step's at 2 rad already, and an explicit exchange of a stiff contact can go "
        f"unstable); set run.macro_step <= {_three_digits_down(SCM_BOUNCE_LIMIT / omega):.3g} s"
        + ("" if plan.terrain.model == "mixed" else f", or leave it unset (SCM's own step, {BOUNCE_PHASE:g} rad)"),
        "run.macro_step",
        "rad",
    )


def scm_check(plan: RunPlan, measured: dict | None = None) -> list[Finding]:
    """Where the SCM tier cannot represent the run (each failed finding says what to do: use the DEM,
    or refine the grid, calibrate again): grouser-dominated traction (grouser height >
    SCM_GROUSER_RATIO x sinkage), a grid that samples the grousers instead of resolving them (node
    spacing > the thinnest grouser / NODES_ACROSS_GROUSER: `scm_grouser_grid`), a sinkage below
    SCM_SINKAGE_GRAINS grain diameters, a slip above SCM_SLIP_LIMIT, a Froude number above
    FROUDE_LIMIT, a macro step above SCM_BOUNCE_LIMIT of the wheel's elastic bounce
    (`scm_coupling_step`), a calibration made at another gravity, a wheel fit made on another grid
    (`scm_calibration_grid`) or for another wheel or load (`scm_calibration_wheel`), and after a run a
    rim sinkage deeper than the calibration's DEM tests reached (`scm_calibration_depth`), and a slip
    outside those a wheel fit was fitted on
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
    count = len(plan.wheels or (plan.wheel,))
    # each SCM wheel's sinkage at its tips: measured (a rover's per wheel, nan where not measured), or
    # Bekker's closed form for its load
    tips = _per_wheel(measured, "sinkage_tips", indices, count)
    if tips is not None:
        sinkages, how = tips, "measured"
    else:
        sinkages = [bekker_wheel_sinkage(parameters, plan.wheel_load, w.outer_radius, w.width) for w in wheels]
        how = "Bekker's closed form"
    findings = []

    def grouser_of(w) -> float:
        return float(getattr(w.shape, "grouser_height", 0.0)) if getattr(w.shape, "grouser_count", 0) else 0.0

    ratios = [grouser_of(w) / max(z, 1e-12) if math.isfinite(z) else math.nan for w, z in zip(wheels, sinkages)]
    known = [i for i in range(len(wheels)) if math.isfinite(ratios[i])]
    if known and any(grouser_of(w) > 0 for w in wheels):
        k = max(known, key=lambda i: ratios[i])  # the wheel whose grousers carry the most
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
    sinkage = min(_finite(sinkages), default=math.nan)  # the shallowest wheel rides on the fewest grains
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
    key = key or "testbed.slip, rover.controllers"
    found = _per_wheel(measured, "slip", indices, count)  # each SCM wheel's own (a rover's wheel_slip)
    if found is not None:
        slips, slip_how = [(indices[k], v) for k, v in enumerate(found) if math.isfinite(v)], "measured"
    else:
        slips, slip_how = ([(i, float(target)) for i in indices] if target is not None else []), "set"
    if slips:
        wheel, slip = max(slips, key=lambda pair: abs(pair[1]))  # the wheel that slips or skids the most
        which = f" of wheel {wheel}" if count > 1 and slip_how == "measured" else ""
        findings.append(
            _finding(
                "scm_slip",
                slip,
                SCM_SLIP_LIMIT,
                abs(slip) <= SCM_SLIP_LIMIT,
                f"slip{which} {slip:.3g} ({slip_how}): |slip| <= {SCM_SLIP_LIMIT}",
                f"slip{which} {slip:.3g} ({slip_how}): |slip| > {SCM_SLIP_LIMIT}: the wheel digs in (slip sinkage, "
                "soil flowing round it), "
                f"outside SCM's steady Bekker-Janosi model; {USE_DEM}",
                key,
            )
        )
        fitted = plan.terrain.calibration_slips
        if fitted is not None:
            low, high = fitted

            def beyond(pair) -> float:
                return max(low - pair[1], pair[1] - high)  # > 0 outside the fitted slips

            wheel, slip = max(slips, key=beyond)
            which = f" of wheel {wheel}" if count > 1 and slip_how == "measured" else ""
            findings.append(
                _finding(
                    "scm_calibration_slips",
                    slip,
                    high if slip > high else low,
                    beyond((wheel, slip)) <= 1e-9,
                    f"slip{which} {slip:.3g} ({slip_how}) within the slips the wheel fit was fitted on ({low:.3g} .. "
                    f"{high:.3g})",
                    f"slip{which} {slip:.3g} ({slip_how}) outside the slips the wheel fit was fitted on ({low:.3g} .. "
                    f"{high:.3g}): its fitted keys are extrapolated there; fit over slips that include it (cosim "
                    "calibrate-scm SCENE --from-wheel on a slip study over them) or use the DEM",
                    "terrain.calibration, " + key,
                )
            )
    dynamic = "a dynamic regime (soil inertia, the wheel hops) that SCM's quasi-static laws do not hold; " + USE_DEM
    froude = _froude_finding(plan, plan.wheel_speeds, "", "scm_froude", dynamic, indices)
    if froude is None and measured.get("wheel_spin") is not None:
        spins = [abs(_number(v)) for v in measured["wheel_spin"]]
        froude = _froude_finding(plan, spins, "at the measured wheel speeds", "scm_froude", dynamic, indices)
    if froude is not None:
        findings.append(froude)
    bounce = _bounce_finding(plan, parameters, wheels)
    if bounce is not None:
        findings.append(bounce)
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
    lab = plan.terrain.calibration_lab_failed
    if lab is not None:
        keys = lab_check_keys(lab)
        carried = (
            "the keys the wheel fit kept from them (k_c, cohesion, elastic_stiffness) carry their error"
            if plan.terrain.calibration_slips is not None
            else "its parameters carry their error"
        )
        findings.append(
            _finding(
                "scm_calibration_lab",
                len(lab),
                0,
                not lab,
                "the calibration's DEM lab tests were quasi-static (every number it records within its limit)",
                f"the calibration's DEM lab tests were out of range ({'; '.join(lab)}): {carried}; calibrate again "
                f"with {', '.join(keys) or 'other tests'} changed (cosim calibrate-scm) or use the DEM",
                "terrain.calibration",
                unit="count",
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
    fit = plan.terrain.calibration_wheel
    if fit is not None:
        findings.append(_wheel_fit_finding(plan, fit, indices, wheels))
    # judged on the run's own rim sinkage: Bekker's closed form for a smooth wheel is no estimate of
    # a grousered wheel's on SCM (the main job: 2.5x SCM's own)
    # a run without a window's sinkage (no landing: a wheel sinking on) is judged on the deepest its rims reached
    count = len(plan.wheels or (plan.wheel,))
    rims, what = _per_wheel(measured, "sinkage", indices, count), "rim sinkage"
    if rims is None:
        rims, what = (
            _per_wheel(measured, "deepest_sinkage", indices, count),
            "deepest rim sinkage (no window's sinkage)",
        )
    tested, rim = plan.terrain.calibration_sinkage, max(_finite(rims)) if rims is not None else None  # the deepest
    if tested is not None and rim is not None and math.isfinite(rim):
        findings.append(
            _finding(
                "scm_calibration_depth",
                rim / tested,
                1.0,
                rim <= tested,
                f"{what} {rim:.3g} m within the {tested:.3g} m the calibration's DEM tests reached",
                f"{what} {rim:.3g} m is beyond the {tested:.3g} m the calibration's DEM tests reached: "
                "Bekker's law is extrapolated; calibrate deeper (cosim calibrate-scm SCENE --set "
                "plate.max_sinkage=..., --from-wheel) or use the DEM",
                "terrain.calibration",
            )
        )
    return findings
