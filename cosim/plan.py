"""A scene resolved once into a frozen run plan.

`resolve(scene)` turns a validated Scene (cosim.scene) into a RunPlan: the device, the
materials and contact-law switches, the wheel shape and its extents (built or loaded
once), the DEM step and macro step, the landing and drive phases, the bed to settle or
load. It also makes the checks that need several sections at once (the wheel fits the
bed, the drive stays clear of the far wall, a bed file matches the scene's soil and
gravity, the device exists) and raises SceneError naming the field to change. Everything
after this point (cosim.system, cosim.runner, studies, advice) reads the plan, never the
raw scene.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, field

import numpy as np

from soil import ContactLaw, GrouserWheel, Material, MeshWheel, gravity_vector
from soil.advisor import rayleigh_time_step
from soil.bed import BedSpec

from .scene import MaterialSection, OutputSection, Scene, SceneError


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
class RunPlan:
    """Everything a run needs, resolved from a scene (see the module docstring)."""

    scene: Scene
    """The validated scene, kept for provenance (scene.toml, HDF5 attributes)."""
    name: str
    device: str
    """Warp device name, resolved ('cpu', 'cuda:0', ...)."""
    precision: str
    gravity: tuple[float, float, float]
    """Gravity vector [m/s^2]."""
    law: ContactLaw
    soil_material: Material
    bed: BedPlan
    wheel: WheelPlan
    testbed: TestbedPlan
    landing: LandingPlan
    dt: float
    """DEM step [s]."""
    macro_step: float
    """Coupling step H = substeps x dt [s]."""
    substeps: int
    """DEM steps per macro step [-]."""
    drive_steps: int
    """Macro steps of the drive phase [-]."""
    scheme: str
    order_seed: int | None
    output: OutputSection
    dt_setting: str = field(default="run.dt_factor")
    """The scene key that sets the DEM step (named in divergence messages)."""

    @property
    def g(self) -> float:
        """|g| [m/s^2]."""
        return float(np.linalg.norm(self.gravity))

    @property
    def wheel_load(self) -> float:
        """Vertical wheel load W = m |g| [N]."""
        return self.testbed.mass * self.g

    @property
    def froude_number(self) -> float:
        """omega^2 r / |g| of the drive [-] (inf without gravity)."""
        return self.testbed.omega**2 * self.wheel.outer_radius / self.g if self.g > 0 else math.inf

    def hub_start(self, surface_height: float) -> np.ndarray:
        """Hub position [m], shape (3,), with the wheel's lowest point on the surface."""
        return np.array([self.testbed.start_x, self.testbed.start_y, surface_height + self.wheel.outer_radius])

    def with_changes(self, **overrides) -> "RunPlan":
        """The plan of the same scene with `overrides` ({'a.b': value}) applied, resolved again."""
        from .scene import validate_scene

        data = self.scene.to_dict()
        for key, value in overrides.items():
            node = data
            *path, last = key.split(".")
            for part in path:
                node = node.setdefault(part, {})
            node[last] = value
        return resolve(validate_scene(data, self.scene.base_dir))


# ------------------------------------------------------------------------------------


def to_material(section: MaterialSection, default_modulus: float | None = None) -> Material:
    """A soil.Material from a material section (restitution 0.3 when neither it nor damping is given)."""
    restitution = section.restitution if section.damping_ratio is None else None
    if restitution is None and section.damping_ratio is None:
        restitution = 0.3
    return Material(youngs_modulus=section.youngs_modulus or default_modulus, poisson_ratio=section.poisson_ratio,
                    density=section.density, restitution=restitution, damping_ratio=section.damping_ratio,
                    stick_angle=math.radians(section.stick_angle_deg), slip_angle=math.radians(section.slip_angle_deg),
                    stick_speed=section.stick_speed, rolling_friction=section.rolling_friction,
                    cohesion=section.cohesion)


def resolve_device(name: str) -> str:
    """A Warp device name for a scene's device ('default' -> the first GPU, else 'cpu'); SceneError if absent."""
    import warp as wp

    wp.init()
    if name == "default":
        return str(wp.get_device())
    if name == "cpu":
        return "cpu"
    count = wp.get_cuda_device_count() if wp.is_cuda_available() else 0
    index = 0 if name == "cuda" else int(name[5:])
    if index >= count:
        have = ", ".join(["cpu"] + [f"cuda:{i}" for i in range(count)])
        raise SceneError([f"scene.device: {name!r} asked for, but this machine has no such CUDA device "
                          f"(it has: {have}); use 'default' (a GPU when present, else the CPU) or 'cpu'"])
    return f"cuda:{index}"


def _wheel(scene: Scene, soil_modulus: float) -> WheelPlan:
    w = scene.wheel
    material = to_material(w.material, soil_modulus)
    if w.type == "grouser":
        shape = GrouserWheel(radius=w.radius, width=w.width, grouser_count=w.grouser_count,
                             grouser_height=w.grouser_height, grouser_thickness=w.grouser_thickness)
        return WheelPlan(shape, material, shape.outer_radius, w.radius, w.width)
    path = scene.resolve(w.file)
    if not os.path.isfile(path):
        raise SceneError([f"wheel.file: mesh file not found: {path!r} (paths are relative to the scene file)"])
    try:
        shape = MeshWheel.load(path, scale=w.scale)
    except (ValueError, OSError) as error:
        raise SceneError([f"wheel.file: {error}"]) from None
    width = float(shape.vertices[:, 1].max() - shape.vertices[:, 1].min())
    return WheelPlan(shape, material, shape.outer_radius, shape.outer_radius, width)


def _time_steps(scene: Scene, material: Material) -> tuple[float, float, int, str]:
    """(dt [s], macro step H [s], substeps, the key that set dt): H is exactly substeps x dt."""
    r = scene.run
    smallest = scene.bed.radius_mean * (1 - scene.bed.radius_spread)
    if r.dt is not None:
        dt, key = r.dt, "run.dt"
    else:
        factor = r.dt_factor if r.dt_factor is not None else 0.2
        dt, key = factor * rayleigh_time_step(material.youngs_modulus, material.poisson_ratio, material.density,
                                              smallest), "run.dt_factor"
    if r.macro_step is not None:
        substeps = max(1, int(round(r.macro_step / dt)))
        if r.dt is None:  # dt from the factor: shrink it so H is a whole number of steps
            substeps = max(1, math.ceil(r.macro_step / dt - 1e-9))
        return r.macro_step / substeps, r.macro_step, substeps, key
    substeps = r.substeps or 10
    return dt, dt * substeps, substeps, key


def bed_key(scene: Scene, material: Material, gravity: np.ndarray, device: str) -> str:
    """Hash of everything a settled bed depends on."""
    parts = {"bed": scene.bed.model_dump(exclude={"bed_file"}), "soil": scene.soil.model_dump(exclude={"law"}),
             "gravity": [float(g) for g in gravity], "device": "cpu" if device == "cpu" else "cuda", "format": 2,
             "material": repr(material)}
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
        problems.append(f"bed.bed_file: the bed was settled under gravity {list(header['gravity'])} m/s^2, the scene "
                        f"asks for {list(gravity)}: settle a bed under the scene's gravity (remove bed.bed_file)")
    saved = header["spec"] or {}
    for key in ("length", "width", "depth", "radius_mean", "radius_spread", "seed"):
        if key in saved and saved[key] != getattr(bed, key):
            problems.append(f"bed.{key}: the bed file has {key} = {saved[key]!r}, the scene says {getattr(bed, key)!r}; "
                            "make [bed] match the file (or remove bed.bed_file to settle a new bed)")
    grains = header["materials"][0] if header["materials"] else None
    if grains is not None and grains != material:
        differ = [name for name in material.__dataclass_fields__ if getattr(grains, name) != getattr(material, name)]
        shown = ", ".join(f"{n} {getattr(grains, n)!r} in the file vs {getattr(material, n)!r} in [soil]"
                          for n in differ)
        problems.append(f"bed.bed_file: the bed's grains are a different soil material ({shown}); make [soil] match "
                        "the bed or remove bed.bed_file to settle a bed of the scene's soil")
    return problems


def resolve(scene: Scene) -> RunPlan:
    """The run plan of a validated scene; SceneError lists every cross-section problem."""
    problems: list[str] = []
    soil_material = to_material(scene.soil)
    gravity = gravity_vector(scene.scene.gravity)
    device = resolve_device(scene.scene.device)
    wheel = _wheel(scene, soil_material.youngs_modulus)
    section = scene.soil.law
    materials = (soil_material, wheel.material)
    law = ContactLaw(damping=section.damping, friction=section.friction,
                     rolling=section.rolling if section.rolling is not None else any(m.rolling_friction > 0
                                                                                     for m in materials),
                     cohesion=section.cohesion if section.cohesion is not None else any(m.cohesion > 0
                                                                                       for m in materials))
    b = scene.bed
    spec = BedSpec(length=b.length, width=b.width, depth=b.depth, radius_mean=b.radius_mean,
                   radius_spread=b.radius_spread, material=soil_material, seed=b.seed)
    bed_file = scene.resolve(b.bed_file)
    if bed_file is not None:
        problems += _check_bed_file(bed_file, soil_material, gravity, b)
    settle_dt = b.settle_dt_factor * rayleigh_time_step(soil_material.youngs_modulus, soil_material.poisson_ratio,
                                                        soil_material.density, b.radius_mean * (1 - b.radius_spread))
    bed = BedPlan(spec, settle_dt, b.settle_ke_ratio, b.settle_max_time, bed_file,
                  bed_key(scene, soil_material, gravity, device))

    t = scene.testbed
    clearance = 2 * b.radius_mean
    start_x = t.start_x if t.start_x is not None else wheel.outer_radius + 6 * b.radius_mean
    testbed = TestbedPlan(t.mass, t.omega, t.mode, t.slip, t.drawbar_load, t.drawbar_ramp, start_x, 0.5 * b.width)
    if wheel.width >= b.width:
        problems.append(f"wheel.width: the wheel ({wheel.width:.4g} m) is wider than the bed (bed.width = {b.width} m)")
    elif (b.width - wheel.width) / 2 < clearance:
        problems.append(f"wheel.width: the wheel is too close to the side walls: gap {(b.width - wheel.width) / 2:.4g} "
                        f"m per side; allowed: >= 2 mean grain radii = {clearance:.4g} m (widen bed.width)")
    if start_x - wheel.outer_radius < clearance:
        problems.append(f"testbed.start_x: the wheel ({start_x} m, outer radius {wheel.outer_radius:.4g} m) starts "
                        f"too close to the x = 0 wall; allowed: start_x >= {wheel.outer_radius + clearance:.4g} m")
    rim_speed = t.omega * wheel.outer_radius * ((1 - t.slip) if t.mode == "slip" else 1.0)
    reach = rim_speed * scene.run.duration
    if start_x + reach + wheel.outer_radius > b.length - clearance:
        longest = max(0.0, (b.length - clearance - wheel.outer_radius - start_x) / max(rim_speed, 1e-30))
        problems.append(f"run.duration: at the wheel's rim speed it may travel {reach:.4g} m from x = {start_x:.4g} m "
                        f"and hit the far wall (bed.length = {b.length} m); allowed: duration <= {longest:.4g} s, "
                        "or a longer bed")

    dt, macro_step, substeps, dt_key = _time_steps(scene, soil_material)
    if macro_step > scene.run.duration:
        problems.append(f"run.macro_step: the macro step ({macro_step:.4g} s) is longer than run.duration "
                        f"({scene.run.duration} s)")
    if scene.output.checkpoint_interval < macro_step:
        problems.append(f"output.checkpoint_interval: {scene.output.checkpoint_interval} s is shorter than the "
                        f"macro step {macro_step:.4g} s")
    g = float(np.linalg.norm(gravity))
    land = scene.landing
    if land.enabled and g == 0:
        problems.append("landing.enabled: a wheel cannot land without gravity; set landing.enabled = false")
    scale_time = math.sqrt(wheel.outer_radius / g) if g > 0 else 0.0
    hold = land.hold_time if land.hold_time is not None else scale_time
    landing = LandingPlan(land.enabled, max(1, int(math.ceil(land.max_time / macro_step))),
                          land.speed_ratio * math.sqrt(g * wheel.outer_radius),
                          max(1, int(math.ceil(hold / macro_step))))
    if problems:
        raise SceneError(problems)
    return RunPlan(scene=scene, name=scene.scene.name, device=device, precision=scene.scene.precision,
                   gravity=tuple(float(v) for v in gravity), law=law, soil_material=soil_material, bed=bed,
                   wheel=wheel, testbed=testbed, landing=landing, dt=dt, macro_step=macro_step, substeps=substeps,
                   drive_steps=max(1, int(round(scene.run.duration / macro_step))), scheme=scene.run.scheme,
                   order_seed=scene.run.order_seed, output=scene.output, dt_setting=dt_key)


def load_plan(path, overrides=None) -> RunPlan:
    """Read, validate and resolve a scene file."""
    from .scene import load_scene

    scene = load_scene(path, overrides)
    try:
        return resolve(scene)
    except SceneError as error:
        raise SceneError(error.problems, os.fspath(path)) from None
