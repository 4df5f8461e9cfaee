"""A scene resolved once into a frozen run plan.

`resolve(scene)` turns a validated Scene (cosim.scene) into a RunPlan: the device, the
materials and contact-law switches, the wheel shape and its extents (built or loaded
once), the DEM step and macro step, the landing and drive phases, the bed to settle or
load. It also makes the checks that need several sections at once (the wheel fits the
bed, the drive stays clear of the far wall, a bed file matches the scene's soil and
gravity, the device exists) and raises SceneError naming the field to change. Everything
after this point (cosim.system, cosim.runner, studies, advice) reads the plan, never the
raw scene.

A rover scene is checked here too, before anything runs: cosim.probe opens what the scene
names (the MJCF compiled, the FMU instantiated at its start pose, the drive's controller
looked up) once, and resolve compares what it found with the rest of the scene (wheel counts,
command kinds) and checks that the rover fits its bed or patch.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from soil import ContactLaw, GrouserWheel, Material, MeshWheel, gravity_vector
from soil.advisor import rayleigh_time_step
from soil.bed import BedSpec
from soil.builder import grain_range_problem
from soil.contact import LAW_VERSION
from soil.materials import stick_speed_for

from . import probe
from .scene import DriveSection, MaterialSection, OutputSection, Scene, SceneError, WheelSection

if TYPE_CHECKING:
    from .scm_calibration import FittedWheel

log = logging.getLogger(__name__)

WALL_GRAINS = 4
"""Fewest mean grain diameters between a wheel and a wall (cosim.advice) and the default gap between a
rover's wheels and a patch's frozen band [-]."""


RAYLEIGH_KEYS = "the Rayleigh step of the smallest grain: soil.youngs_modulus, soil.density, bed.radius_mean"
"""What sets the DEM step with run.dt_factor, for the messages that name it."""

MAX_PHASE_STEPS = 1e10
"""Most steps a run's soil or coupling may take in one phase (settling, landing, driving) [count]: a day
even at 10 us a step, quicker than a GPU steps the smallest bed; beyond it a run never ends in practice
(a stiffness or a step far from the scene's scale)."""


@dataclass(frozen=True)
class WheelPlan:
    """The wheel's shape, material and extents."""

    shape: GrouserWheel | MeshWheel
    material: Material
    outer_radius: float
    """Radius over the grouser tips (mesh: largest vertex distance from the axle) [m]."""
    rim_radius: float
    """Rim radius r used for slip s = 1 - v / (omega r) and the rim sinkage [m] (mesh: outer radius)."""
    width: float
    """Width along the axle [m]."""

    @property
    def grouser_count(self) -> int:
        """Grousers round the rim (0: a smooth wheel, or a mesh, whose grousers are not known)."""
        return int(getattr(self.shape, "grouser_count", 0))


@dataclass(frozen=True)
class BedPlan:
    """The soil bed: settled from `spec`, or loaded from `bed_file`."""

    spec: BedSpec
    settle_dt: float
    """Settling step [s]."""
    settle_ke_ratio: float
    """Settled when KE < ratio N m |g| r [-]."""
    settle_max_time: float
    """Longest settling time [s]."""
    bed_file: str | None
    """Absolute path of a saved bed to use instead of settling one."""
    key: str
    """Hash of everything a settled bed depends on (the bed cache key)."""


@dataclass(frozen=True)
class TestbedPlan:
    """The single-wheel testbed's load and drive."""

    __test__ = False  # not a pytest class

    mass: float
    """Load mass, wheel included [kg]."""
    omega: float
    """Wheel angular speed while driving [rad/s]."""
    mode: str
    """'free' or 'slip'."""
    slip: float
    """Set slip in mode 'slip' [-]."""
    drawbar_load: float
    """Constant resisting force in mode 'free' [N]."""
    drawbar_ramp: float
    """Growth rate of the resisting force in mode 'free' [N/s]."""
    start_x: float
    """Initial hub x [m]."""
    start_y: float
    """Hub y (the bed's centre line) [m]."""


@dataclass(frozen=True)
class DrivePlan:
    """The rover's drive after the landing (cosim.rover.make_controller builds it)."""

    name: str
    """The controller's name ([rover.controllers]) or the kind for an inline drive."""
    section: DriveSection
    """Its scene section (kind and settings)."""
    file: str | None
    """kind 'fmu': the FMU's absolute path."""

    @property
    def kind(self) -> str:
        return self.section.kind


@dataclass(frozen=True)
class RoverPlan:
    """A rover on the soil: its model, wheels, start pose and drive, checked at plan time."""

    model: str
    """'mjcf', 'mmx' or 'fmu'."""
    source: str
    """MJCF: the file's absolute path, or the built-in rover's MJCF text; FMU: the file's absolute path."""
    wheel_names: tuple[str, ...]
    """Wheel names (MJCF bodies; FMU: <prefix>0 ..), in wheel order."""
    body: str | None
    """MJCF body reported as the rover's pose (None: its base)."""
    prefix: str
    """FMU wheel variable prefix."""
    start_values: tuple[tuple[str, float], ...]
    """FMU parameters set before the start."""
    start: tuple[float, float, float]
    """Start of the base's frame origin: x [m], y [m], heading about +z [rad]."""
    hub_offsets: np.ndarray
    """Hub positions relative to the base's frame origin at the start pose [m], shape (W, 3)."""
    footprint_radius: float
    """Largest horizontal distance from the wheels' centre to a wheel's outer rim, any heading [m]."""
    mass: float
    """Total mass [kg] (nan when the FMU does not say)."""
    takes_speed: bool
    """Whether the rover takes wheel speed commands (it is braked by them while landing)."""
    takes_torque: bool
    """Whether the rover takes wheel torque commands."""
    start_parameters: bool
    """FMU: whether it has start.x/y/z/heading parameters."""
    drive: DrivePlan
    stuck_slip: float
    """Stuck criterion's slip [-] (cosim.metrics)."""

    @property
    def nominal_omega(self) -> float:
        """Mean commanded wheel speed [rad/s] of a constant-speed drive; nan for other drives."""
        return _nominal_omega(self.drive.section, len(self.wheel_names))


def _wheel_speeds(section: DriveSection, wheel_count: int) -> np.ndarray | None:
    """|omega| [rad/s] (wheel_count,) of a constant-speed drive; None for other drives."""
    if section.kind != "speed" or (isinstance(section.speed, list) and len(section.speed) != wheel_count):
        return None
    return np.abs(np.broadcast_to(np.asarray(section.speed, dtype=float), (wheel_count,)))


def _nominal_omega(section: DriveSection, wheel_count: int) -> float:
    speeds = _wheel_speeds(section, wheel_count)
    return math.nan if speeds is None else float(np.mean(speeds))


@dataclass(frozen=True)
class PatchPlan:
    """The moving soil patch (soil.patch)."""

    length: float
    """Window size along x [m]."""
    width: float
    """Window size along y [m]."""
    band: float
    """Frozen band at the window's edge [m]."""
    clearance: float
    """Least gap between a wheel and the band [m]."""
    recentre_distance: float
    """The window moves when the wheels' centre is this far from its centre along x or y [m]."""
    tile_margin: float
    """The tile is the bed without the grains this close to its side walls [m]."""


@dataclass(frozen=True)
class LandingPlan:
    """The landing phase before the drive."""

    enabled: bool
    max_steps: int
    """Longest landing phase in macro steps [-]."""
    speed_limit: float
    """At rest below this vertical hub speed [m/s]."""
    hold_steps: int
    """... held for this many macro steps [-]."""


@dataclass(frozen=True)
class TerrainPlan:
    """The terrain model the wheels run on ([terrain]; cosim.system.TERRAIN_MODELS builds it)."""

    model: str = "dem"
    """'dem' (the grains of [bed]), 'scm' (soil.scm), 'mixed' (some wheels on the DEM, the others on
    SCM: `wheel_models`) or 'analytic' (cosim.terrain.SpringDamperTerrain)."""
    parameters: tuple[tuple[str, Any], ...] = ()
    """The model's own parameters given in the scene, (name, value) pairs (its defaults for the rest);
    SCM: the soil keys a calibration file gives are included."""
    wheel_models: tuple[str, ...] = ()
    """'mixed': each wheel's model ('dem' or 'scm'), in wheel order; () otherwise."""
    calibration_gravity: float | None = None
    """SCM from a calibration file: the |g| its DEM tests ran at [m/s^2]."""
    calibration_sinkage: float | None = None
    """SCM from a calibration file: the deepest sinkage its DEM tests reached [m] (None: not recorded)."""
    calibration_node_spacing: float | None = None
    """SCM from a wheel fit (`calibrate-scm --from-wheel`): the node spacing its SCM wheel ran on [m]
    (None: a lab calibration, or a fit that did not record it)."""
    calibration_slips: tuple[float, float] | None = None
    """SCM from a wheel fit: the lowest and highest slip of the DEM runs it was fitted on [-] (None: a lab
    calibration)."""
    calibration_lab_failed: tuple[str, ...] | None = None
    """SCM from a calibration file: its DEM lab tests' quasi-static numbers out of range, each as 'plate
    inertial number I = 0.0036 > 0.001' (None: the file does not record them)."""
    calibration_wheel: FittedWheel | None = None
    """SCM from a wheel fit: the wheel and load it was fitted on (cosim.scm_calibration.FittedWheel; None: a
    lab calibration, or a fit that did not record them)."""


@dataclass(frozen=True)
class RunPlan:
    """Everything a run needs, resolved from a scene (see the module docstring)."""

    scene: Scene
    """The validated scene, kept for provenance (scene.toml, HDF5 attributes)."""
    name: str
    device: str
    """Warp device name, resolved ('cpu', 'cuda:0', ...)."""
    precision: str
    storage: str
    """The DEM's storage order (scene.storage): 'grain' or 'slot'."""
    gravity: tuple[float, float, float]
    """Gravity vector [m/s^2]."""
    law: ContactLaw
    soil_material: Material
    bed: BedPlan
    wheel: WheelPlan
    """The shared wheel ([wheel]); a rover's wheels may differ: see `wheels`."""
    testbed: TestbedPlan | None
    """The single-wheel testbed (None for a rover)."""
    landing: LandingPlan
    dt: float
    """DEM step [s] (a scene on SCM alone without run.macro_step: the macro step, one substep)."""
    macro_step: float
    """Coupling step H = substeps x dt [s]."""
    substeps: int
    """DEM steps per macro step [-]."""
    drive_steps: int
    """Macro steps of the drive phase [-]."""
    scheme: str
    order_seed: int | None
    output: OutputSection
    integrator: str = "velocity-verlet"
    """The DEM integrator's name (run.integrator): 'velocity-verlet' or 'jolt-beeman'."""
    dt_setting: str = field(default="run.dt_factor")
    """The scene key that sets the DEM step (named in divergence messages); 'run.macro_step' on SCM
    alone (its own coupling step when the scene gives none: cosim.scm_soil.scm_macro_step)."""
    step_control: str = "fixed"
    """'fixed' (every DEM step dt) or 'pid' (run.step_control: the PID substeps of soil.step_control)."""
    tolerance: float = 1e-2
    """The PID's normalised local error per substep [-]."""
    dt_min: float | None = None
    """The PID's shortest substep [s] (None: dt_max x 1e-4)."""
    dt_max: float | None = None
    """The PID's longest substep [s] (None: the advisor's limit for the simulation)."""
    rover: RoverPlan | None = None
    """A rover (None: the testbed)."""
    patch: PatchPlan | None = None
    """A soil patch following the rover (None: the bed is the whole soil)."""
    wheels: tuple[WheelPlan, ...] = ()
    """Every wheel's plan, in wheel order (the testbed: its one wheel)."""
    terrain: TerrainPlan = TerrainPlan()
    """The terrain model (default: the DEM bed)."""

    @property
    def g(self) -> float:
        """|g| [m/s^2]."""
        return float(np.linalg.norm(self.gravity))

    @property
    def settle_gravity(self) -> tuple[float, float, float]:
        """Gravity the bed settles under [m/s^2]: the scene's for the testbed; |g| along -z for a rover,
        whose scene gravity may be tilted (a slope): the soil rests on the floor, then the slope is applied."""
        return self.gravity if self.rover is None else (0.0, 0.0, -self.g)

    @property
    def step_keys(self) -> str:
        """The scene keys that set the DEM step, with their values, for divergence messages: the PID's
        tolerance and longest substep, or the fixed step's key."""
        if self.step_control == "pid":
            longest = f"{self.dt_max:.3g} s" if self.dt_max is not None else "the advised limit"
            return f"run.tolerance (now {self.tolerance:g}) or run.dt_max (now {longest})"
        return f"{self.dt_setting} (the DEM step is now {self.dt:.3g} s)"

    @property
    def slope(self) -> float:
        """Angle between gravity and -z [rad] (the slope a tilted gravity vector makes)."""
        return math.acos(min(1.0, -self.gravity[2] / self.g)) if self.g > 0 else 0.0

    @property
    def wheel_load(self) -> float:
        """Load per wheel [N]: the testbed's m |g|; a rover's m |g| cos(slope) / wheel count."""
        if self.rover is None:
            assert self.testbed is not None
            return self.testbed.mass * self.g
        return self.rover.mass * self.g * math.cos(self.slope) / len(self.wheels)

    @property
    def drive_omega(self) -> float:
        """Wheel speed of the drive [rad/s] (nan when the controller sets it as it goes)."""
        if self.rover is not None:
            return self.rover.nominal_omega
        assert self.testbed is not None
        return self.testbed.omega

    @property
    def wheel_speeds(self) -> np.ndarray | None:
        """The drive's highest |omega| of each wheel [rad/s], shape (W,): the testbed's, a rover's constant
        speeds, a slip controller's omega_max; None when the controller sets them as it goes (torque, FMU,
        Python drives: the run measures them)."""
        if self.rover is None:
            assert self.testbed is not None
            return np.array([abs(self.testbed.omega)])
        section = self.rover.drive.section
        if section.kind == "slip" and section.omega_max is not None:
            return np.full(len(self.wheels), float(section.omega_max))
        return _wheel_speeds(section, len(self.wheels))

    @property
    def froude_number(self) -> float:
        """omega^2 r / |g| of the fastest wheel at the drive's speeds (wheel_speeds) [-] (inf without gravity;
        nan when the controller sets the speeds as it goes)."""
        speeds = self.wheel_speeds
        if not self.g > 0:
            return math.inf
        if speeds is None:
            return math.nan
        radii = np.array([w.outer_radius for w in self.wheels or (self.wheel,)])
        return float(np.max(speeds**2 * radii)) / self.g

    @property
    def outer_radius(self) -> float:
        """The largest wheel outer radius [m]."""
        return max(w.outer_radius for w in self.wheels)

    def hub_start(self, surface_height: float) -> np.ndarray:
        """Hub position [m], shape (3,), with the wheel's lowest point on the surface."""
        assert self.testbed is not None  # a single-wheel plan
        return np.array([self.testbed.start_x, self.testbed.start_y, surface_height + self.wheel.outer_radius])

    def with_changes(self, **overrides) -> RunPlan:
        """The plan of the same scene with `overrides` ({'a.b': value}) applied, resolved again; this
        plan itself when the overrides leave the scene as it is (nothing is opened or probed again)."""
        from .scene import validate_scene

        unchanged = self.scene.to_dict()
        data = self.scene.to_dict()
        for key, value in overrides.items():
            node = data
            *path, last = key.split(".")
            for part in path:
                node = node.setdefault(part, {})
            node[last] = value
        scene = validate_scene(data, self.scene.base_dir)
        return self if scene.to_dict() == unchanged else resolve(scene)


# ------------------------------------------------------------------------------------


def to_material(
    section: MaterialSection, default_modulus: float | None = None, default_stick_speed: float | None = None
) -> Material:
    """A soil.Material from a material section (restitution 0.3 when neither it nor damping is given;
    the stick speed `default_stick_speed` [m/s] when the section gives none)."""
    restitution = section.restitution if section.damping_ratio is None else None
    if restitution is None and section.damping_ratio is None:
        restitution = 0.3
    modulus = section.youngs_modulus or default_modulus
    assert modulus is not None  # a wheel's material falls back on the soil's modulus
    stick_speed = section.stick_speed or default_stick_speed
    assert stick_speed is not None  # resolve gives the scene's default
    return Material(
        youngs_modulus=modulus,
        poisson_ratio=section.poisson_ratio,
        density=section.density,
        restitution=restitution,
        damping_ratio=section.damping_ratio,
        stick_angle=math.radians(section.stick_angle_deg),
        slip_angle=math.radians(section.slip_angle_deg),
        stick_speed=stick_speed,
        rolling_friction=section.rolling_friction,
        cohesion=section.cohesion,
    )


ZERO_GRAVITY_STICK_SPEED = 1.0e-4
"""The default stick speed of a scene without gravity [m/s] (that of 2 mm grains at Phobos)."""


def default_stick_speed(scene: Scene) -> float:
    """The scene's stick speed where its soil gives none [m/s]: soil.materials.stick_speed_for its
    gravity and mean grain diameter (ZERO_GRAVITY_STICK_SPEED without gravity)."""
    if scene.soil.stick_speed is not None:
        return scene.soil.stick_speed
    g = float(np.linalg.norm(gravity_vector(scene.scene.gravity)))
    return stick_speed_for(g, 2 * scene.bed.radius_mean) if g > 0 else ZERO_GRAVITY_STICK_SPEED


def _wheel(scene: Scene, soil_modulus: float, w: WheelSection | None = None, key: str = "wheel") -> WheelPlan:
    w = scene.wheel if w is None else w
    material = to_material(w.material, soil_modulus, default_stick_speed(scene))
    if w.type == "grouser":
        # the section's validator filled in every grouser default
        assert w.radius is not None and w.width is not None and w.grouser_count is not None
        assert w.grouser_height is not None and w.grouser_thickness is not None
        shape = GrouserWheel(
            radius=w.radius,
            width=w.width,
            grouser_count=w.grouser_count,
            grouser_height=w.grouser_height,
            grouser_thickness=w.grouser_thickness,
        )
        return WheelPlan(shape, material, shape.outer_radius, w.radius, w.width)
    path = scene.resolve(w.file)
    assert path is not None and w.scale is not None  # the validator requires a mesh wheel's file, defaults its scale
    if not os.path.isfile(path):
        raise SceneError([f"{key}.file: mesh file not found: {path!r} (paths are relative to the scene file)"])
    try:
        mesh = MeshWheel.load(path, scale=w.scale)
    except (ValueError, OSError) as error:
        raise SceneError([f"{key}.file: {error}"]) from None
    width = float(mesh.vertices[:, 1].max() - mesh.vertices[:, 1].min())
    log.info(
        "wheel mesh %s: %d triangles, closed (watertight), consistently wound, volume %.4g m^3",
        path,
        len(mesh.triangles),
        mesh.volume,
    )
    return WheelPlan(mesh, material, mesh.outer_radius, mesh.outer_radius, width)


def dem_time_step(scene: Scene, material: Material) -> tuple[float, str]:
    """(dt [s], the key that set it): run.dt, else run.dt_factor (default 0.2) x the Rayleigh time step
    of the smallest grain of `material` (before a macro step rounds it: see `_time_steps`)."""
    r = scene.run
    if r.dt is not None:
        return r.dt, "run.dt"
    smallest = scene.bed.radius_min
    factor = r.dt_factor if r.dt_factor is not None else 0.2
    return (
        factor * rayleigh_time_step(material.youngs_modulus, material.poisson_ratio, material.density, smallest),
        "run.dt_factor",
    )


def _time_steps(scene: Scene, material: Material) -> tuple[float, float, int, str]:
    """(dt [s], macro step H [s], substeps, the key that set dt): H is exactly substeps x dt."""
    r = scene.run
    dt, key = dem_time_step(scene, material)
    if r.macro_step is not None:
        substeps = max(1, int(round(r.macro_step / dt)))
        if r.dt is None:  # dt from the factor: shrink it so H is a whole number of steps
            substeps = max(1, math.ceil(r.macro_step / dt - 1e-9))
        return r.macro_step / substeps, r.macro_step, substeps, key
    substeps = r.substeps or 10
    return dt, dt * substeps, substeps, key


def bed_key(scene: Scene, material: Material, gravity: np.ndarray, device: str) -> str:
    """Hash of everything a settled bed depends on."""
    parts = {
        "bed": scene.bed.model_dump(exclude={"bed_file"}),
        "soil": scene.soil.model_dump(exclude={"law"}),
        "gravity": [float(g) for g in gravity],
        "device": "cpu" if device == "cpu" else "cuda",
        "format": 2,
        "material": repr(material),
        "contact_law": LAW_VERSION,
    }
    if scene.run.step_control == "pid":  # a bed settled with PID substeps is another bed (fixed keys unchanged)
        parts["step_control"] = scene.run.model_dump(include={"step_control", "tolerance", "dt_min", "dt_max"})
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]


def _check_bed_file(path: str, material: Material, gravity: np.ndarray, bed) -> list[str]:
    """A saved bed must be readable, of the scene's bed geometry, made of the scene's soil under the
    scene's gravity."""
    from soil.bed import read_bed_header

    if not os.path.isfile(path):
        return [f"bed.bed_file: bed file not found: {path!r}"]
    try:
        header = read_bed_header(path)
    except (OSError, ValueError) as error:
        return [f"bed.bed_file: {error}"]
    problems = []
    if not np.allclose(header["gravity"], gravity, rtol=1e-12, atol=0):
        problems.append(
            f"bed.bed_file: the bed was settled under gravity {np.asarray(header['gravity']).tolist()} m/s^2, the "
            f"scene asks for {np.asarray(gravity).tolist()}: settle a bed under the scene's gravity (remove "
            "bed.bed_file)"
        )
    saved = header["spec"] or {}
    for key in ("length", "width", "depth", "radius_mean", "radius_spread", "seed"):
        if key in saved and saved[key] != getattr(bed, key):
            problems.append(
                f"bed.{key}: the bed file has {key} = {saved[key]!r}, the scene says {getattr(bed, key)!r}; "
                "make [bed] match the file (or remove bed.bed_file to settle a new bed)"
            )
    grains = header["materials"][0] if header["materials"] else None
    differ = [] if grains is None else [n for n in material.__dataclass_fields__ if not _same(grains, material, n)]
    if differ:
        shown = ", ".join(
            f"{n} {getattr(grains, n)!r} in the file vs {getattr(material, n)!r} in [soil]" for n in differ
        )
        problems.append(
            f"bed.bed_file: the bed's grains are a different soil material ({shown}); make [soil] match "
            "the bed or remove bed.bed_file to settle a bed of the scene's soil"
        )
    return problems


def _same(a: Material, b: Material, name: str) -> bool:
    """Field `name` of two materials agrees (floats to the last bits: a default derived from |g| of a
    tilted gravity vector may differ from the upright one's in the last digit)."""
    x, y = getattr(a, name), getattr(b, name)
    if isinstance(x, float) and isinstance(y, float):
        return math.isclose(x, y, rel_tol=1e-12, abs_tol=0.0)
    return x == y


def resolve(scene: Scene) -> RunPlan:
    """The run plan of a validated scene; SceneError lists every cross-section problem."""
    problems: list[str] = []
    soil_material = to_material(scene.soil, default_stick_speed=default_stick_speed(scene))
    gravity = gravity_vector(scene.scene.gravity)
    g = float(np.linalg.norm(gravity))
    device = probe.resolve_device(scene.scene.device)
    wheel = _wheel(scene, soil_material.youngs_modulus)
    rover = scene.rover
    if rover is not None:
        names: list[str] | None
        try:
            names = probe.rover_wheel_names(scene)
        except SceneError as error:  # an FMU rover that cannot be read: its drive is checked and named with it
            problems += error.problems
            names = None
            if rover.wheel_count:
                _check_drive(scene, (wheel,) * rover.wheel_count, None, problems)
            else:  # the wheels are the FMU's to say: the controller opened for any count
                probe.probe_drive(scene, rover.drive_section, _drive_key(scene), None, problems)
        shapes = rover.wheel_shape or {}
        unknown = sorted(set(shapes) - set(names or []))
        if names is not None and unknown:
            problems.append(
                f"rover.wheel_shape: no wheel named {', '.join(unknown)}; the wheels are {', '.join(names)}"
            )
        wheels = tuple(
            _wheel(scene, soil_material.youngs_modulus, shapes[n], f"rover.wheel_shape.{n}") if n in shapes else wheel
            for n in (names or [])
        )
    else:
        wheels = (wheel,)
    if g > 0 and -gravity[2] < 0.5 * g:  # upwards the grains leave the open box; sideways they pile on a wall
        problems.append(
            "scene.gravity: the soil lies on the plane z = 0 (the bed's floor, the terrain's datum), so gravity "
            f"must point down (-z) within 60 deg (a slope); got {gravity.tolist()} m/s^2"
        )
    section = scene.soil.law
    materials = (soil_material, *(w.material for w in wheels or (wheel,)))
    law = ContactLaw(
        damping=section.damping,
        friction=section.friction,
        rolling=section.rolling if section.rolling is not None else any(m.rolling_friction > 0 for m in materials),
        cohesion=section.cohesion if section.cohesion is not None else any(m.cohesion > 0 for m in materials),
        twisting=section.twisting,
    )
    b = scene.bed
    spec = BedSpec(
        length=b.length,
        width=b.width,
        depth=b.depth,
        radius_mean=b.radius_mean,
        radius_spread=b.radius_spread,
        material=soil_material,
        seed=b.seed,
    )
    settle_gravity = gravity if rover is None else np.array([0.0, 0.0, -g])
    bed_file = scene.resolve(b.bed_file)
    if bed_file is not None:
        problems += _check_bed_file(bed_file, soil_material, settle_gravity, b)
    settle_dt = b.settle_dt_factor * rayleigh_time_step(
        soil_material.youngs_modulus,
        soil_material.poisson_ratio,
        soil_material.density,
        b.radius_min,
    )
    grains = grain_range_problem(b.radius_min, soil_material.density, scene.scene.precision)
    if grains:
        problems.append(f"bed.radius_mean: {grains}")
    bed = BedPlan(
        spec,
        settle_dt,
        b.settle_ke_ratio,
        b.settle_max_time,
        bed_file,
        bed_key(scene, soil_material, settle_gravity, device),
    )

    testbed = rover_plan = patch = None
    walls = _on_grains(scene)
    if rover is None:
        testbed = _testbed(scene, wheel, problems, walls)
    elif names is not None:
        rover_plan, patch = _rover(scene, names, wheels, gravity, problems, walls)

    terrain = _terrain(scene, len(wheels), problems)
    problems += _drawbar_problems(scene, wheel, terrain)
    dt, macro_step, substeps, dt_key = _time_steps(scene, soil_material)
    macro_key: str | None = None  # the keys of the macro step: its own key, or dt's with run.substeps
    if terrain.model == "scm" and scene.run.macro_step is None:
        own = _scm_macro_step(terrain, list(wheels) or [wheel], testbed, rover_plan, g, gravity) if not problems else 0
        if math.isfinite(own) and own > 0:
            dt, macro_step, substeps, dt_key = own, own, 1, "run.macro_step"
            macro_key = (
                "run.macro_step, unset: SCM's own coupling step from terrain.elastic_stiffness, "
                "terrain.node_spacing and the wheels' load and speed"
            )
        else:  # not known (another problem, no load): the grains' step does not apply to SCM alone
            macro_key = ""
    shortest = scene.run.dt_min if scene.run.step_control == "pid" and _on_grains(scene) else None
    if shortest is not None and macro_step < shortest * (1 - 1e-9):  # every substep would be cut below it
        problems.append(
            f"run.macro_step: the macro step ({macro_step:.4g} s{', ' + macro_key if macro_key else ''}) is shorter "
            f"than the PID's shortest substep run.dt_min ({shortest:.4g} s), which the substeps landing on its end "
            "would break at every step: lengthen the macro step or lower run.dt_min"
        )
    if macro_step > scene.run.duration:
        problems.append(
            f"run.macro_step: the macro step ({macro_step:.4g} s) is longer than run.duration ({scene.run.duration} s)"
        )
    if scene.output.checkpoint_interval < macro_step:
        problems.append(
            f"output.checkpoint_interval: {scene.output.checkpoint_interval} s is shorter than the "
            f"macro step {macro_step:.4g} s"
        )
    if 0 < scene.output.snapshot_interval < macro_step * (1 - 1e-9):
        problems.append(
            f"output.snapshot_interval: {scene.output.snapshot_interval} s is shorter than the macro step "
            f"{macro_step:.4g} s ({macro_key or 'run.macro_step, run.substeps'}), and a snapshot is taken at "
            f"most once a macro step; allowed: 0 (first and last only) or >= {macro_step:.4g} s"
        )
    land = scene.landing
    problems += _step_count_problems(scene, dt, dt_key, macro_step, macro_key, settle_dt, bed_file is None)
    if land.enabled and g == 0:
        problems.append("landing.enabled: a wheel cannot land without gravity; set landing.enabled = false")
    outer = max([w.outer_radius for w in wheels] or [wheel.outer_radius])
    scale_time = math.sqrt(outer / g) if g > 0 else 0.0
    hold = land.hold_time if land.hold_time is not None else scale_time
    landing = LandingPlan(
        land.enabled,
        max(1, int(math.ceil(land.max_time / macro_step))),
        land.speed_ratio * math.sqrt(g * outer),
        max(1, int(math.ceil(hold / macro_step))),
    )
    if land.enabled and g > 0 and landing.hold_steps >= landing.max_steps:  # it would end "no landing", always
        held = "landing.hold_time" if land.hold_time is not None else "sqrt(r / |g|), landing.hold_time unset"
        problems.append(
            f"landing.max_time: a wheel has landed once it rested for {hold:.4g} s ({held}), which the landing's "
            f"{land.max_time:g} s cannot hold: every run would end 'no landing'; raise landing.max_time above "
            f"{hold + macro_step:.4g} s or shorten landing.hold_time"
        )
    if problems:
        raise SceneError(problems)
    return RunPlan(
        scene=scene,
        name=scene.scene.name,
        device=device,
        precision=scene.scene.precision,
        storage=scene.scene.storage,
        gravity=(float(gravity[0]), float(gravity[1]), float(gravity[2])),
        law=law,
        soil_material=soil_material,
        bed=bed,
        wheel=wheel,
        testbed=testbed,
        landing=landing,
        dt=dt,
        macro_step=macro_step,
        substeps=substeps,
        drive_steps=max(1, int(round(scene.run.duration / macro_step))),
        scheme=scene.run.scheme,
        integrator="jolt-beeman" if scene.run.step_control == "pid" else scene.run.integrator,
        step_control=scene.run.step_control,
        tolerance=scene.run.tolerance,
        dt_min=scene.run.dt_min,
        dt_max=scene.run.dt_max,
        order_seed=scene.run.order_seed,
        output=scene.output,
        dt_setting=dt_key,
        rover=rover_plan,
        patch=patch,
        wheels=wheels,
        terrain=terrain,
    )


def _terrain(scene: Scene, wheel_count: int, problems: list[str]) -> TerrainPlan:
    """The scene's terrain model and the parameters it gives for it (scene.TerrainSection); an SCM
    calibration file's soil parameters fill the soil keys the scene does not give."""
    section = scene.terrain
    if section is None:
        return TerrainPlan()
    given = section.model_dump(exclude={"model", "wheels", "calibration"}, exclude_none=True)
    if section.model != "scm":
        return TerrainPlan(section.model, tuple(sorted(given.items())))
    gravity = depth = grid = slips = lab = fitted = None
    if section.calibration is not None:
        from .scm_calibration import (
            CalibrationError,
            bed_soils,
            failed_lab_checks,
            fitted_node_spacing,
            fitted_slips,
            fitted_wheel,
            out_of_range,
            read_calibration,
            tested_sinkage,
        )

        try:
            calibration = read_calibration(section.calibration)
            depth = tested_sinkage(calibration, section.calibration)
            grid = fitted_node_spacing(calibration, section.calibration)
            slips = fitted_slips(calibration, section.calibration)
            lab = failed_lab_checks(calibration, section.calibration)
            fitted = fitted_wheel(calibration, section.calibration)
            bed_soils(calibration, section.calibration)  # its beds' record read now, not at a --vary-bed run
        except CalibrationError as error:
            problems.append(f"terrain.calibration: {error}")
        else:
            gravity = calibration.gravity
            for key, value in calibration.parameters.items():
                given.setdefault(key, value)
            # k_c [Pa m^(1-n)] and k_phi [Pa m^-n] hold only with the n they were fitted with
            together = "terrain.n, terrain.k_c and terrain.k_phi together: they were fitted together"
            for key, problem in out_of_range(given).items():  # the scene's own keys were checked with the scene
                if key not in section.model_fields_set:
                    wins = f"set {together}" if key == "n" else f"terrain.{key} in the scene wins over the file's"
                    problems.append(
                        f"terrain.calibration: {section.calibration}: [scm] {problem}, outside what SCM takes ({wins})"
                    )
            kept = sorted({"k_c", "k_phi"} - section.model_fields_set)
            if "n" in section.model_fields_set and kept:
                problems.append(
                    f"terrain.n: replaces the calibration's n ({calibration.parameters.get('n', math.nan):.4g}) while "
                    f"its {' and '.join(kept)}, fitted with that n, are kept from {section.calibration} (their "
                    f"units hold only with it); set {together}, or none"
                )
    if {"k_c", "k_phi"} & section.model_fields_set:  # named here, not as soil.ScmParameters at the run's start
        if "k_c" in given and "k_phi" in given and given["k_c"] + given["k_phi"] <= 0:
            problems.append(
                "terrain.k_c, terrain.k_phi: k_c + k_phi = 0: the Bekker moduli carry no load; set one of them > 0"
            )
    model = "scm"
    models: tuple[str, ...] = ()
    if section.wheels is not None:
        if wheel_count and len(section.wheels) != wheel_count:
            problems.append(
                f"terrain.wheels: names {len(section.wheels)} wheels' models, the scene has {wheel_count} wheels"
            )
        elif set(section.wheels) == {"dem"}:
            model = "dem"
        elif "dem" in section.wheels:
            model, models = "mixed", tuple(section.wheels)
    return TerrainPlan(model, tuple(sorted(given.items())), models, gravity, depth, grid, slips, lab, fitted)


def _scm_macro_step(terrain: TerrainPlan, wheels, testbed, rover, g: float, gravity) -> float:
    """A scene on SCM alone without run.macro_step: SCM's own coupling step [s] (cosim.scm_soil.
    scm_macro_step: the wheels' elastic bounce and the fastest wheel surface's travel over the grid,
    not the grains' Rayleigh time; run.dt and run.substeps do not apply). The speed: the testbed's
    omega at the outer radius (or the hub's, at a negative slip), a rover's fastest constant-speed
    wheel, else the fastest SCM holds (Froude number 0.1: omega^2 r / g); nan without gravity or a
    load (an FMU's)."""
    from .scm_soil import scm_macro_step

    outer = max(w.outer_radius for w in wheels)
    # a drive whose speed is not fixed (slip, torque, a controller): the fastest SCM holds, Froude 0.1
    omega = math.sqrt(0.1 * g / outer) if g > 0 else math.nan
    if testbed is not None:
        load = testbed.mass * g
        slip = testbed.slip if testbed.mode == "slip" else 0.0  # a free carriage's slip emerges: not read
        speed = abs(testbed.omega) * max(outer, wheels[0].rim_radius * (1.0 - slip))
    elif rover is not None:
        load = rover.mass * g * (-gravity[2] / g if g > 0 else 1.0) / len(wheels)
        fixed = _wheel_speeds(rover.drive.section, len(wheels))
        speed = (float(np.max(fixed)) if fixed is not None else omega) * outer
    else:
        return math.nan
    return scm_macro_step(dict(terrain.parameters), wheels, load, g, speed)


def _step_count_problems(
    scene: Scene,
    dt: float,
    dt_key: str,
    macro_step: float,
    macro_key: str | None,
    settle_dt: float,
    settles: bool,
) -> list[str]:
    """The phase with the most steps, where they exceed MAX_PHASE_STEPS, named by the keys that set its
    step: settling (grains settled here), landing and driving (the DEM's steps on grains, SCM's own
    where terrain.time_step is finer, the macro steps). `macro_key`: the keys of the macro step (None:
    run.macro_step or run.substeps x dt's; '': not known, not counted)."""
    on_grains = _on_grains(scene)
    terrain = scene.terrain
    scm_step = terrain.time_step if terrain is not None and terrain.model == "scm" else None
    dem_keys = f"run.dt_factor x {RAYLEIGH_KEYS}" if dt_key == "run.dt_factor" else dt_key
    if macro_key is None:
        macro_key = "run.macro_step" if scene.run.macro_step is not None else f"run.substeps x {dem_keys}"
    steps = []  # (count, rank on a tie: the finest step first, what, the keys that set the step)
    # the PID's substeps are at most run.dt_max long, settling included: one far below the scene's scale never
    # ends, and a macro step's substeps loop on the device, where no stop signal reaches them
    pid_longest = scene.run.dt_max if scene.run.step_control == "pid" else None
    if settles and on_grains:
        steps.append((scene.bed.settle_max_time / settle_dt, 2, "settling", f"bed.settle_dt_factor x {RAYLEIGH_KEYS}"))
    for phase, duration in (
        ("landing", scene.landing.max_time if scene.landing.enabled else 0.0),
        ("driving", scene.run.duration),
    ):
        if on_grains:
            steps.append((duration / dt, 2, f"{phase} (DEM steps)", dem_keys))
        if scm_step is not None:
            steps.append((duration / scm_step, 1, f"{phase} (SCM steps)", "terrain.time_step"))
        if macro_key:  # as many as the finer steps only with one substep: a macro step given caps dt then
            rank = 3 if scene.run.macro_step is not None else 0
            steps.append((duration / macro_step, rank, f"{phase} (macro steps)", macro_key))
        if on_grains and pid_longest is not None:
            steps.append((duration / pid_longest, 4, f"{phase} (PID substeps)", "run.dt_max"))
    if settles and on_grains and pid_longest is not None:
        steps.append((scene.bed.settle_max_time / pid_longest, 4, "settling (PID substeps)", "run.dt_max"))
    if not steps:
        return []
    count, _, what, keys = max(steps, key=lambda step: step[:2])
    if count <= MAX_PHASE_STEPS:
        return []
    key, _, origin = keys.partition(" ")
    return [
        f"{key.rstrip(',')}: {count:.3g} steps of {what}, more than {MAX_PHASE_STEPS:.0e} (a day even at 10 us "
        f"a step): the step {'(' + keys + ') ' if origin else ''}is far below the scene's scale"
    ]


def _on_grains(scene: Scene) -> bool:
    """Whether some wheel runs on the grains of [bed] (the DEM, alone or mixed): only then do the bed's
    walls bound the drive (SCM and the analytic terrain are unbounded: the bed only describes the soil)."""
    section = scene.terrain
    if section is None or section.model == "dem":
        return True
    return section.model == "scm" and section.wheels is not None and "dem" in section.wheels


DRAWBAR_LOAD_FACTOR = 10.0
"""How far a testbed's constant drawbar load may exceed the largest traction W + c A (a friction
coefficient of 1 and the cohesion c over the wheel's projected side A) [-]: a wide margin, since W
tan(phi) + c A bounds what any soil gives."""


def _drawbar_problems(scene: Scene, wheel: WheelPlan, terrain: TerrainPlan) -> list[str]:
    """A testbed's constant drawbar load beyond DRAWBAR_LOAD_FACTOR x the largest traction W + c A: the
    carriage would be dragged backwards from the first step, with nothing to measure."""
    t = scene.testbed
    if t is None or t.mode != "free":
        return []
    weight = t.mass * float(np.linalg.norm(gravity_vector(scene.scene.gravity)))
    cohesion = max(scene.soil.cohesion, float(dict(terrain.parameters).get("cohesion", 0.0)))
    largest = DRAWBAR_LOAD_FACTOR * (weight + cohesion * 2 * wheel.outer_radius * wheel.width)
    if t.drawbar_load <= largest:
        return []
    return [
        f"testbed.drawbar_load: {t.drawbar_load:.4g} N is more than {DRAWBAR_LOAD_FACTOR:g} x (W + c A) = "
        f"{largest:.4g} N (W = testbed.mass |g|, c the soil's cohesion, A = 2 outer radius x width), beyond any "
        "traction the soil gives: the carriage would be dragged backwards from the start (testbed.drawbar_ramp "
        f"finds the largest pull); allowed: <= {largest:.4g} N"
    ]


def _testbed(scene: Scene, wheel: WheelPlan, problems: list[str], walls: bool = True) -> TestbedPlan:
    """The testbed's plan; its wheel must fit the bed and stay clear of its walls (`walls`: on grains)."""
    t, b = scene.testbed, scene.bed
    assert t is not None
    clearance = 2 * b.radius_mean
    start_x = t.start_x if t.start_x is not None else wheel.outer_radius + 6 * b.radius_mean
    testbed = TestbedPlan(t.mass, t.omega, t.mode, t.slip, t.drawbar_load, t.drawbar_ramp, start_x, 0.5 * b.width)
    if not walls:
        return testbed
    if wheel.width >= b.width:
        problems.append(f"wheel.width: the wheel ({wheel.width:.4g} m) is wider than the bed (bed.width = {b.width} m)")
    elif (b.width - wheel.width) / 2 < clearance:
        problems.append(
            f"wheel.width: the wheel is too close to the side walls: gap {(b.width - wheel.width) / 2:.4g} "
            f"m per side; allowed: >= 2 mean grain radii = {clearance:.4g} m (widen bed.width)"
        )
    if start_x - wheel.outer_radius < clearance:
        problems.append(
            f"testbed.start_x: the wheel ({start_x} m, outer radius {wheel.outer_radius:.4g} m) starts "
            f"too close to the x = 0 wall; allowed: start_x >= {wheel.outer_radius + clearance:.4g} m"
        )
    rim_speed = t.omega * wheel.outer_radius * ((1 - t.slip) if t.mode == "slip" else 1.0)
    reach = rim_speed * scene.run.duration
    key = "wheel.scale" if scene.wheel.type == "mesh" else "wheel.radius"
    if start_x + wheel.outer_radius > b.length - clearance:  # too large to stand in the bed at all
        problems.append(
            f"{key}: the wheel (outer radius {wheel.outer_radius:.4g} m, its hub at x = {start_x:.4g} m) does not fit "
            f"the bed (bed.length = {b.length} m); allowed: bed.length >= "
            f"{start_x + wheel.outer_radius + clearance:.4g} m, or a smaller wheel"
        )
    elif start_x + reach + wheel.outer_radius > b.length - clearance:
        longest = max(0.0, (b.length - clearance - wheel.outer_radius - start_x) / max(rim_speed, 1e-30))
        problems.append(
            f"run.duration: at the wheel's rim speed it may travel {reach:.4g} m from x = {start_x:.4g} m "
            f"and hit the far wall (bed.length = {b.length} m); allowed: duration <= {longest:.4g} s, "
            "or a longer bed"
        )
    return testbed


# ------------------------------------------------------------------------------------
# rovers


def _drive_key(scene: Scene) -> str:
    """The scene key of the rover's drive: its named controller's section, or [rover.drive]."""
    assert scene.rover is not None
    drive = scene.rover.drive
    return f"rover.controllers.{drive}" if isinstance(drive, str) else "rover.drive"


def _check_drive(
    scene: Scene, wheels: tuple[WheelPlan, ...], layout: probe.RoverLayout | None, problems: list[str]
) -> DrivePlan:
    """The drive's controller must exist and fit the rover (wheel counts, command kinds)."""
    rover = scene.rover
    assert rover is not None
    section = rover.drive_section
    name = rover.drive if isinstance(rover.drive, str) else section.kind
    key = _drive_key(scene)
    n = len(wheels)
    file = None
    for value_key in ("speed", "torque"):
        value = getattr(section, value_key)
        if isinstance(value, list) and len(value) != n:
            problems.append(f"{key}.{value_key}: {len(value)} values for {n} wheels; give one value or one per wheel")
    wants = {"speed": "speed", "slip": "speed", "torque": "torque"}.get(section.kind)
    if section.kind == "fmu":
        file = scene.resolve(section.file)
    if section.kind in ("fmu", "python"):
        opened = probe.probe_drive(scene, section, key, n, problems)
        wants = opened if section.kind == "fmu" else wants
    if (
        section.kind == "slip"
        and section.omega_min is not None
        and section.omega_max is not None  # the validator requires it for a slip drive
        and section.omega_min > section.omega_max
    ):
        problems.append(f"{key}.omega_min: ({section.omega_min} rad/s) must be <= omega_max ({section.omega_max})")
    if wants is not None and layout is not None and not layout.takes(wants):
        what = (
            "velocity actuators on every wheel hinge (MJCF) or <prefix><i>.speed_command inputs (FMU)"
            if wants == "speed"
            else "a hinge on every wheel (MJCF) or <prefix><i>.torque_command inputs (FMU)"
        )
        problems.append(f"{key}.kind: a {section.kind!r} drive commands wheel {wants}s, but the rover has no {what}")
    return DrivePlan(name, section, file)


def _overlapping_wheels(hubs: np.ndarray, axles: np.ndarray, wheels, names: list[str]) -> list[str]:
    """Wheels whose cylinders (outer radius, width, about each wheel's own axle) overlap: they would press
    on the same soil from inside each other (a track or wheelbase smaller than the wheels, wheels steered
    into each other). hubs: [m], shape (W, 3); axles: unit [-], shape (W, 3); world frame at the start."""
    problems = []
    for i in range(len(wheels)):
        for j in range(i + 1, len(wheels)):
            a, b = wheels[i], wheels[j]
            offset = hubs[j] - hubs[i]
            if abs(float(axles[i] @ axles[j])) > 1.0 - 1e-9:  # axles parallel: side by side or in line
                along = float(offset @ axles[i])
                across = float(np.linalg.norm(offset - along * axles[i]))
                meet = abs(along) < 0.5 * (a.width + b.width) and across < a.outer_radius + b.outer_radius
                where, verb = f"hubs {abs(along):.4g} m apart along the axle, {across:.4g} m across it", "move"
            else:
                meet = _cylinder_points_inside(hubs[j], axles[j], b, hubs[i], axles[i], a) or _cylinder_points_inside(
                    hubs[i], axles[i], a, hubs[j], axles[j], b
                )
                angle = math.degrees(math.acos(min(1.0, abs(float(axles[i] @ axles[j])))))
                where, verb = f"steered: axles {angle:.3g} deg apart", "steer"
            if meet:
                problems.append(
                    f"rover: wheels {names[i]!r} and {names[j]!r} overlap ({where}; outer radii "
                    f"{a.outer_radius:.4g}, {b.outer_radius:.4g} m, widths {a.width:.4g}, {b.width:.4g} m): set the "
                    f"rover's track or wheelbase (rover.mmx.track, wheelbase) or {verb} its wheels apart"
                )
    return problems


def _cylinder_points_inside(hub, axle, wheel, other_hub, other_axle, other) -> bool:
    """Whether points spread through one wheel's cylinder (rings, spokes and slices) lie inside another's:
    two cylinders at an angle have no short closed-form test, and an overlap that no such point sees is a
    sliver under a tenth of the radius deep. hub [m], axle unit [-]: shape (3,) each."""
    spoke = np.cross(axle, [0.0, 0.0, 1.0] if abs(axle[2]) < 0.9 else [1.0, 0.0, 0.0])
    spoke /= np.linalg.norm(spoke)
    normal = np.cross(axle, spoke)
    angle, radius, offset = (
        g.ravel()[:, None]
        for g in np.meshgrid(
            np.linspace(0.0, 2.0 * math.pi, 48, endpoint=False),
            np.linspace(0.0, wheel.outer_radius, 6),
            np.linspace(-0.5 * wheel.width, 0.5 * wheel.width, 7),
            indexing="ij",
        )
    )
    points = hub + radius * np.cos(angle) * spoke + radius * np.sin(angle) * normal + offset * axle - other_hub
    along = points @ other_axle
    across = np.linalg.norm(points - along[:, None] * other_axle, axis=1)
    return bool(np.any((np.abs(along) < 0.5 * other.width) & (across < other.outer_radius)))


def _rover(
    scene: Scene,
    names: list[str],
    wheels: tuple[WheelPlan, ...],
    gravity: np.ndarray,
    problems: list[str],
    walls: bool = True,
):
    """The rover's plan and its patch's; the rover must fit its bed (or its patch's window); `walls`
    False (no wheel on the grains): the bed's walls do not bound it."""
    rover, b = scene.rover, scene.bed
    assert rover is not None
    heading = math.radians(rover.start.heading_deg)
    source: str | None
    if rover.model == "mmx":
        source = probe.mmx_xml(scene, gravity)
    else:
        source = scene.resolve(rover.file)
        assert source is not None  # the validator requires an MJCF's or an FMU's file
        if rover.model == "mjcf" and os.path.isdir(source):
            problems.append(f"rover.file: {source!r} is a folder; give the MJCF file")
            return None, None
        if rover.model == "mjcf" and not os.path.isfile(source):
            problems.append(f"rover.file: MJCF file not found: {source!r} (paths are relative to the scene file)")
            return None, None
    layout = probe.probe_rover(scene, source, names, gravity, problems)
    drive = _check_drive(scene, wheels, layout, problems)
    if layout is None:
        return None, None
    hubs = layout.hub_offsets
    problems += _overlapping_wheels(hubs, layout.axles, wheels, names)
    outer = np.array([w.outer_radius for w in wheels])
    centre = hubs[:, :2].mean(axis=0)
    footprint = float(
        np.max(
            np.linalg.norm(hubs[:, :2] - centre, axis=1)
            + np.maximum(outer, [math.hypot(w.outer_radius, w.width / 2) for w in wheels])
        )
    )
    diameter = 2 * b.radius_mean
    patch = None
    if scene.patch is not None:
        p = scene.patch
        band = p.band if p.band is not None else 4 * b.radius_max
        clearance = p.clearance if p.clearance is not None else WALL_GRAINS * diameter
        slack = 0.5 * min(p.length, p.width) - footprint - band - clearance
        if slack <= 0:
            least = 2 * (footprint + band + clearance) + 2 * diameter
            problems.append(
                f"patch.{'length' if p.length <= p.width else 'width'}: the window ({p.length} x {p.width} m) "
                "must hold the rover (footprint "
                f"radius {footprint:.4g} m, any heading), the clearance {clearance:.4g} m and the frozen "
                f"band {band:.4g} m on every side; allowed: patch.length and patch.width > {least:.4g} m"
            )
            slack = math.nan
        recentre = p.recentre_distance if p.recentre_distance is not None else slack
        if p.recentre_distance is not None and p.recentre_distance > slack:
            problems.append(
                f"patch.recentre_distance: ({p.recentre_distance} m) lets the wheels come closer than the "
                f"clearance to the frozen band; allowed: <= {slack:.4g} m"
            )
        largest = 2 * b.radius_max
        if band < largest:
            problems.append(
                f"patch.band: ({band} m) must be at least one largest grain diameter ({largest:.4g} m) "
                "to hold the soil in"
            )
        if clearance < largest:
            problems.append(
                f"patch.clearance: ({clearance} m) must be at least one largest grain diameter "
                f"({largest:.4g} m): a grain caught between a wheel and the frozen band has nowhere to go"
            )
        margin = p.tile_margin if p.tile_margin is not None else 2 * largest
        for key, size in (("length", b.length), ("width", b.width)):
            if size - 2 * margin < 2 * largest:
                problems.append(
                    f"bed.{key}: the tile is the bed {margin:.4g} m in from its walls (patch.tile_margin): "
                    f"bed.{key} = {size} m leaves too little; allowed: >= {2 * margin + 2 * largest:.4g} m"
                )
        patch = PatchPlan(p.length, p.width, band, clearance, recentre, margin)
        start_x = rover.start.x if rover.start.x is not None else 0.0
        start_y = rover.start.y if rover.start.y is not None else 0.0
    else:
        # on a bed the rover keeps its start heading: its wheels' bounding box at that heading
        clearance = diameter
        turn = np.array([[math.cos(heading), -math.sin(heading)], [math.sin(heading), math.cos(heading)]])
        corners = np.concatenate(
            [
                hub[:2]
                + np.array([[sx * w.outer_radius, sy * w.width / 2] for sx in (-1, 1) for sy in (-1, 1)]) @ turn.T
                for hub, w in zip(hubs, wheels)
            ]
        )
        box_low, box_high = corners.min(axis=0), corners.max(axis=0)
        start_x = rover.start.x if rover.start.x is not None else clearance + 6 * b.radius_mean - box_low[0]
        start_y = rover.start.y if rover.start.y is not None else 0.5 * b.width - 0.5 * (box_low[1] + box_high[1])
        low = np.array([start_x, start_y]) + box_low
        high = np.array([start_x, start_y]) + box_high
        if not walls:
            pass  # no grains under the wheels: the bed's walls are not there
        elif high[1] - low[1] + 2 * clearance > b.width:
            problems.append(
                f"bed.width: the rover ({high[1] - low[1]:.4g} m across its wheels) and a clearance of "
                f"{clearance:.4g} m to the side walls need bed.width >= "
                f"{high[1] - low[1] + 2 * clearance:.4g} m (or use a [patch])"
            )
        elif low[1] < clearance or high[1] > b.width - clearance:
            problems.append(
                f"rover.start.y: the rover ({low[1]:.4g} .. {high[1]:.4g} m across) comes closer than "
                f"{clearance:.4g} m to a side wall of the bed (0 .. {b.width} m)"
            )
        if walls and low[0] < clearance:
            problems.append(
                f"rover.start.x: the rover's rear reaches {low[0]:.4g} m, closer than {clearance:.4g} m "
                f"to the x = 0 wall; allowed: rover.start.x >= {start_x + clearance - low[0]:.4g} m"
            )
        omega = _nominal_omega(drive.section, len(names))
        if walls and math.isfinite(omega) and abs(math.cos(heading)) > 0:
            reach = omega * max(w.outer_radius for w in wheels) * scene.run.duration
            if high[0] + reach > b.length - clearance:
                problems.append(
                    f"run.duration: at its wheels' rim speed the rover may travel {reach:.4g} m and hit "
                    f"the far wall (bed.length = {b.length} m); shorten run.duration, lengthen the bed or "
                    "use a [patch]"
                )
    plan = RoverPlan(
        model=rover.model,
        source=source,
        wheel_names=tuple(names),
        body=rover.body,
        prefix=rover.wheel_prefix,
        start_values=tuple(sorted((rover.start_values or {}).items())),
        start=(float(start_x), float(start_y), heading),
        hub_offsets=hubs,
        footprint_radius=footprint,
        mass=float(layout.mass),
        takes_speed=layout.takes_speed,
        takes_torque=layout.takes_torque,
        start_parameters=layout.start_parameters,
        drive=drive,
        stuck_slip=rover.stuck_slip,
    )
    if not math.isfinite(plan.mass):
        problems.append(
            f"rover.file: the FMU {source} does not give the rover's mass (a total_mass parameter or "
            "output [kg]); the metrics per weight need it"
        )
    return plan, patch


def load_plan(path, overrides=None) -> RunPlan:
    """Read, validate and resolve a scene file."""
    from .scene import load_scene

    scene = load_scene(path, overrides)
    try:
        return resolve(scene)
    except SceneError as error:
        raise SceneError(error.problems, os.fspath(path)) from None


def enable_step_control(plan: RunPlan, sim) -> None:
    """Give a soil Simulation the plan's step control (nothing for fixed steps): the PID's first
    substep is the plan's fixed dt (within dt_min, dt_max)."""
    if plan.step_control != "pid":
        return
    from soil import StepController

    sim.enable_step_control(
        StepController(tolerance=plan.tolerance, dt_min=plan.dt_min, dt_max=plan.dt_max, dt_initial=plan.dt)
    )
