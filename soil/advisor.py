"""Stiffness and time-step advice (docs/physics.md section 2, paper sections 4 and 5).

    from soil import advisor
    advisor.rayleigh_time_step(1e8, 0.3, 2600.0, 2.5e-3)            # [s]
    advisor.hertz_impact(e_star, r_star, m_star, speed).contact_time  # [s]
    advisor.macroscopic_stiffness(0.05, 10.0, 0.01, 2.5e-3, 2600.0, 5.7e-3)   # paper eq. 10 [Pa]
    advice = advisor.recommended_time_step(sim)   # a Simulation, a SoilModel or a Material
    search = advisor.largest_stable_step(make_simulation, duration=0.05, dt_start=1e-5)

Which step limits an explicit DEM step? The contact: a Hertz contact of tangent stiffness
k_t = 2 E* sqrt(R* delta) between masses m* oscillates at omega = sqrt(k_t / m*), and
an explicit scheme is stable for dt < 2 / omega (the linear limit). The stiffness grows
with the overlap, and the overlap with the load: impacts (speed from the fall height,
sqrt(2 g H)) and the weight of the soil column plus the wheel pressure. At milli-g both
are tiny, so the contacts are soft and the stable step is long; the Rayleigh step
(elastic wave speed through a grain, independent of the load) is reported for reference
(industrial DEM uses 0.1 - 0.3 dt_R) but is far too strict for soft, lightly loaded
contacts, and the paper's milli-g steps (2e-4 .. 5e-4 s) exceed it for stiff grains.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import SoilInputError, is_real
from .materials import Material


def _check_number(name: str, value, allowed: str, ok) -> None:
    """Refuse `value` unless it is a finite real number for which ok(value) holds; the message names the
    argument and what is `allowed` (a text or None would reach a comparison as a bare TypeError)."""
    if not (is_real(value) and math.isfinite(value) and ok(value)):
        raise SoilInputError(f"{name} must be a finite number {allowed}, got {value!r}")


def _finite_array(name: str, value, allowed: str) -> np.ndarray:
    """`value` (a number or a vector) as a float array of finite numbers, or a SoilInputError naming `name`."""
    try:
        array = np.atleast_1d(np.asarray(value))
        if array.dtype.kind in "iuf" and np.all(np.isfinite(array)):
            return np.asarray(array, dtype=float)
    except (TypeError, ValueError):
        pass
    raise SoilInputError(f"{name} must be {allowed} of finite numbers, got {value!r}")


HERTZ_TIME_FACTOR = 2.0 * math.gamma(1.4) * math.sqrt(math.pi) / math.gamma(0.9)
"""Hertz contact time = HERTZ_TIME_FACTOR * max overlap / closing speed (= 2.9432): twice
the integral of du / sqrt(1 - u^(5/2)) from 0 to 1."""


def rayleigh_time_step(youngs_modulus: float, poisson_ratio: float, density: float, radius: float) -> float:
    """Rayleigh time step dt_R = pi R sqrt(rho / G) / (0.1631 nu + 0.8766) [s], G = E / (2 (1 + nu)).

    E [Pa], nu [-], rho [kg/m^3], R [m] (use the smallest grain)."""
    # finite too: an inf E gave a step of 0, an inf R one of inf; a text gave a bare TypeError
    for name, value, allowed, ok in (
        ("youngs_modulus", youngs_modulus, "E > 0 [Pa]", lambda v: v > 0),
        ("poisson_ratio", poisson_ratio, "-1 < nu < 0.5", lambda v: -1.0 < v < 0.5),
        ("density", density, "rho > 0 [kg/m^3]", lambda v: v > 0),
        ("radius", radius, "R > 0 [m]", lambda v: v > 0),
    ):
        if not (is_real(value) and math.isfinite(value) and ok(value)):
            raise SoilInputError(
                f"rayleigh_time_step needs E > 0, rho > 0, R > 0 and -1 < nu < 0.5: {name} must be a finite number "
                f"{allowed}, got {value!r} (E = {youngs_modulus!r} Pa, nu = {poisson_ratio!r}, "
                f"rho = {density!r} kg/m^3, R = {radius!r} m)"
            )
    shear = youngs_modulus / (2.0 * (1.0 + poisson_ratio))
    return math.pi * radius * math.sqrt(density / shear) / (0.1631 * poisson_ratio + 0.8766)


@dataclass(frozen=True)
class HertzImpact:
    """Elastic Hertz impact at a closing speed (no damping)."""

    max_overlap: float
    """delta_max = (5 m* v^2 / (4 K))^(2/5), K = 4/3 E* sqrt(R*) [m]."""
    peak_force: float
    """K delta_max^(3/2) [N]."""
    contact_time: float
    """2.9432 delta_max / v [s]."""
    critical_step: float
    """2 / omega at the deepest overlap, omega^2 = 2 E* sqrt(R* delta_max) / m* [s]:
    the linear stability limit of an explicit step (about 0.5 contact_time)."""


def hertz_impact(e_star: float, r_star: float, m_star: float, speed: float) -> HertzImpact:
    """Hertz impact of effective modulus E* [Pa], radius R* [m] and mass m* [kg] closing at `speed` [m/s].

    Two equal spheres (E, nu, r, m): E* = E / (2 (1 - nu^2)), R* = r / 2, m* = m / 2.
    A sphere on a wall of the same material: R* = r, m* = m."""
    if not speed > 0:
        raise SoilInputError(f"impact speed must be > 0 [m/s], got {speed!r}")
    k = 4.0 / 3.0 * e_star * math.sqrt(r_star)
    overlap = (5.0 * m_star * speed**2 / (4.0 * k)) ** 0.4
    omega = math.sqrt(2.0 * e_star * math.sqrt(r_star * overlap) / m_star)
    return HertzImpact(overlap, k * overlap**1.5, HERTZ_TIME_FACTOR * overlap / speed, 2.0 / omega)


def hertz_contact_time(
    youngs_modulus: float, poisson_ratio: float, density: float, radius: float, speed: float
) -> float:
    """Contact time [s] of two equal elastic spheres (E [Pa], nu, rho [kg/m^3], r [m]) closing at speed [m/s]."""
    mass = density * 4.0 / 3.0 * math.pi * radius**3
    e_star = youngs_modulus / (2.0 * (1.0 - poisson_ratio**2))
    return hertz_impact(e_star, 0.5 * radius, 0.5 * mass, speed).contact_time


def macroscopic_stiffness(
    soil_height: float, pressure, overlap_factor, radius: float, density: float, gravity
) -> float:
    """Smallest macroscopic particle stiffness (paper eq. 10) [Pa]:

        E_mP >= z_h |3 p + z_h rho_p g| / (3 |u| r)

    soil_height z_h [m]; pressure p: wheel ground pressure [Pa] (scalar or vector, along
    gravity); overlap_factor u [-] (scalar or vector): the allowed overlap relative to the
    radius; radius r [m]; density rho_p [kg/m^3] (particle density); gravity g [m/s^2]
    (scalar or vector). Vectors enter as in the paper: |3 p + z_h rho_p g| and |u|."""
    # all finite: a nan pressure or an inf radius gave a nan or 0 bound, a negative density a wrong one
    _check_number("soil_height", soil_height, ">= 0 [m]", lambda v: v >= 0)
    _check_number("radius", radius, "> 0 [m]", lambda v: v > 0)
    _check_number("density", density, "> 0 [kg/m^3]", lambda v: v > 0)
    p = _finite_array("pressure", pressure, "a number or a vector [Pa]")
    g = _finite_array("gravity", gravity, "a number or a vector [m/s^2]")
    u = float(np.linalg.norm(_finite_array("overlap_factor", overlap_factor, "a number or a vector [-]")))
    if not (u > 0 and radius > 0 and soil_height >= 0):
        raise SoilInputError("overlap_factor and radius must be > 0 and soil_height >= 0")
    load = float(np.linalg.norm(3.0 * p + soil_height * density * g))
    return soil_height * load / (3.0 * u * radius)


@dataclass(frozen=True)
class TimeStepAdvice:
    """What recommended_time_step found, all in SI units."""

    dt_min: float
    """Lower end of the recommended range [s]: the fastest impact resolved by 100 steps;
    smaller steps buy no accuracy, only more rounding (paper eq. 9)."""
    dt_max: float
    """Upper end, the advised limit [s]: safety * critical_step."""
    critical_step: float
    """Linear stability limit 2 / omega of the stiffest expected contact [s]."""
    rayleigh: float
    """Rayleigh time step of the smallest grain [s] (reference only)."""
    contact_time: float
    """Hertz contact time at the impact speed [s]."""
    impact_speed: float
    """Impact speed used [m/s]."""
    static_overlap: float
    """Overlap of a grain under the soil column (and wheel pressure) [m]."""
    impact_overlap: float
    """Max overlap of the impact [m]."""
    inputs: dict = field(default_factory=dict)
    """The scene values used (radius, mass, E*, gravity, height, pressure)."""

    @property
    def overlap_ratio(self) -> float:
        """The deeper expected overlap (static or impact) over the smallest radius [-]. From about
        0.8 no step helps: the grains sink into each other, far outside the Hertz law, and the
        divergence monitor's overlap bound (0.5 r) stops the run at any step, PID included (the
        stability map, BENCHMARKS.md: every point where the advised step failed had >= 0.89, none
        with <= 0.73 failed); stiffen the soil (cosim advise: eq. 10)."""
        return max(self.static_overlap, self.impact_overlap) / self.inputs["radius"]


def _scene_values(scene, radius, gravity, height):
    """(r_min [m], m of that grain [kg], largest E* [Pa], poisson, density, |g| [m/s^2], H [m], speed0 [m/s])."""
    speed0 = 0.0
    if isinstance(scene, Material):
        if radius is None or gravity is None:
            raise SoilInputError("with a Material, give radius [m] and gravity [m/s^2]")
        g = float(np.linalg.norm(np.atleast_1d(gravity)))
        mass = scene.density * 4.0 / 3.0 * math.pi * radius**3
        e_star = scene.youngs_modulus / (2.0 * (1.0 - scene.poisson_ratio**2))
        return radius, mass, e_star, g, height if height is not None else 20.0 * radius, speed0
    sim = scene if hasattr(scene, "model") else None  # a Simulation (duck-typed: no import cycle)
    model = sim.model if sim is not None else scene
    radii = model.radius_numpy()
    i = int(np.argmin(radii))
    r = float(radii[i]) if radius is None else float(radius)
    mass = float(model.mass_numpy()[i]) * (r / float(radii[i])) ** 3
    e_star = float(model.pair.numpy()[:, 0].max())  # the stiffest pair, walls included
    g = float(np.linalg.norm(model.gravity)) if gravity is None else float(np.linalg.norm(np.atleast_1d(gravity)))
    if height is None:
        height = 20.0 * float(radii.mean())
        if sim is not None and g > 0:
            along = sim.positions() @ (-model.gravity / np.linalg.norm(model.gravity))
            height = float(along.max() - along.min()) + 2.0 * model.max_radius
    if sim is not None:
        speed0 = float(np.max(np.linalg.norm(sim.velocities(), axis=1)))
    return r, mass, e_star, g, height, speed0


def recommended_time_step(
    scene,
    *,
    radius: float | None = None,
    gravity=None,
    height: float | None = None,
    impact_speed: float | None = None,
    pressure: float = 0.0,
    safety: float = 0.3,
) -> TimeStepAdvice:
    """Recommended step range for a scene: a Simulation, a SoilModel, or a Material (then give radius, gravity).

    The stiffest expected contact is the deeper of (a) an impact of two of the smallest
    grains at impact_speed (default: sqrt(2 |g| H) + the fastest grain now, H the height
    span of the grains, or 20 mean radii without positions), (b) the static overlap of a
    grain carrying the soil column, force (pressure + 0.6 rho |g| H) (2r)^2 (packing
    fraction 0.6, one contact per (2r)^2). dt_max = safety * 2 / omega of that contact.

    safety = 0.3: measured on small piles for g = 1e-4 .. 30 m/s^2 and E = 1e5 .. 1e10 Pa,
    fixed steps stay stable up to about 0.8 x 2/omega and explode from about 1.3 x 2/omega
    (tests/test_stability.py), so half the advised step is safe and five times it is not.
    """
    # every argument checked before any is used: a radius < 0 reached sqrt as "math domain error", a nan
    # gravity read as "no gravity", a safety < 0 gave negative steps
    if not (isinstance(scene, Material) or hasattr(scene, "model") or hasattr(scene, "radius_numpy")):
        raise SoilInputError(
            f"scene must be a soil.Simulation, a soil.SoilModel or a soil.Material, got {type(scene).__name__}"
        )
    if radius is not None:
        _check_number("radius", radius, "> 0 [m] (or None)", lambda v: v > 0)
    if gravity is not None:
        _finite_array("gravity", gravity, "None, a magnitude or a vector [m/s^2]")
    if height is not None:
        _check_number("height", height, ">= 0 [m] (or None)", lambda v: v >= 0)
    if impact_speed is not None:
        _check_number("impact_speed", impact_speed, "> 0 [m/s] (or None)", lambda v: v > 0)
    _check_number("pressure", pressure, "[Pa]", lambda v: True)
    _check_number("safety", safety, "> 0", lambda v: v > 0)
    r, mass, e_star, g, h, speed0 = _scene_values(scene, radius, gravity, height)
    density = mass / (4.0 / 3.0 * math.pi * r**3)
    if impact_speed is None:
        impact_speed = math.sqrt(2.0 * g * h) + speed0
    if not impact_speed > 0:
        raise SoilInputError("no gravity and nothing moving: give impact_speed [m/s] (or dt_max directly)")
    r_star, m_star = 0.5 * r, 0.5 * mass
    impact = hertz_impact(e_star, r_star, m_star, impact_speed)
    column_force = (pressure + 0.6 * density * g * h) * (2.0 * r) ** 2
    static_overlap = (3.0 * column_force / (4.0 * e_star * math.sqrt(r_star))) ** (2.0 / 3.0)
    overlap = max(impact.max_overlap, static_overlap)
    omega = math.sqrt(2.0 * e_star * math.sqrt(r_star * overlap) / m_star)
    critical = 2.0 / omega
    # Rayleigh from E* back to E with the grain's own Poisson ratio unknown here: nu = 0.3 is typical
    nu = scene.poisson_ratio if isinstance(scene, Material) else 0.3
    rayleigh = rayleigh_time_step(e_star * 2.0 * (1.0 - nu**2), nu, density, r)
    dt_max = safety * critical
    return TimeStepAdvice(
        dt_min=min(impact.contact_time / 100.0, dt_max),
        dt_max=dt_max,
        critical_step=critical,
        rayleigh=rayleigh,
        contact_time=impact.contact_time,
        impact_speed=impact_speed,
        static_overlap=static_overlap,
        impact_overlap=impact.max_overlap,
        inputs=dict(radius=r, mass=mass, e_star=e_star, gravity=g, height=h, pressure=pressure),
    )


@dataclass
class StableStepSearch:
    """Result of largest_stable_step."""

    largest_stable: float | None
    """Largest step that ran without divergence [s] (None: even dt_start diverged)."""
    first_unstable: float | None
    """Smallest step found unstable [s] (None: none found up to dt_stop)."""
    recommended: float | None
    """safety * largest_stable [s]."""
    tried: list = field(default_factory=list)
    """(dt [s], stable: bool, message) for every run, in order."""


def largest_stable_step(
    make_simulation,
    duration: float,
    dt_start: float,
    growth: float = 1.5,
    safety: float = 0.5,
    dt_stop: float | None = None,
    max_runs: int = 30,
    check_every: int = 20,
    progress=None,
) -> StableStepSearch:
    """The paper's search (section 5): raise the step geometrically until the scene explodes.

    make_simulation() -> a fresh Simulation of the scene (called once per try);
    each try runs `duration` [s] with a fixed step dt (Simulation.run, divergence checks
    every `check_every` steps); dt starts at dt_start [s] and grows by `growth` until
    SimulationDiverged (or dt_stop [s] / max_runs). The answer is the last stable step
    times `safety`. If dt_start already diverges the search goes down by `growth`.
    progress(dt [s], stable: bool, message) is called after each try, when given.
    """
    from .stability import SimulationDiverged

    if not (growth > 1 and 0 < safety <= 1 and dt_start > 0 and duration > 0):
        raise SoilInputError("need growth > 1, 0 < safety <= 1, dt_start > 0, duration > 0")

    def stable(dt):
        sim = make_simulation()
        try:
            sim.run(duration, dt, check_every=check_every)
            ok, message = True, ""
        except SimulationDiverged as error:
            ok, message = False, str(error)
        if progress is not None:
            progress(dt, ok, message)
        return ok, message

    tried = []
    dt = dt_start
    ok, message = stable(dt)
    tried.append((dt, ok, message))
    largest = first_bad = None
    if ok:
        largest = dt
        while len(tried) < max_runs and (dt_stop is None or dt * growth <= dt_stop):
            dt *= growth
            ok, message = stable(dt)
            tried.append((dt, ok, message))
            if not ok:
                first_bad = dt
                break
            largest = dt
    else:
        first_bad = dt
        while len(tried) < max_runs:
            dt /= growth
            ok, message = stable(dt)
            tried.append((dt, ok, message))
            if ok:
                largest = dt
                break
            first_bad = dt
    return StableStepSearch(largest, first_bad, None if largest is None else safety * largest, tried)
