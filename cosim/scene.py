"""Scene files: one TOML file describes a single-wheel co-simulation run.

    [scene]    name, gravity (preset name | magnitude [m/s^2] along -Z | 3-vector), precision, device
    [soil]     grain material (youngs_modulus, poisson_ratio, density, restitution or damping_ratio,
               stick_angle_deg, slip_angle_deg, stick_speed, rolling_friction, cohesion)
    [soil.law] contact-law switches (damping, friction, rolling, cohesion; rolling/cohesion
               default to "on when the material uses them")
    [bed]      length, width, depth, radius_mean, radius_spread, seed, settle_ke_ratio,
               settle_max_time, settle_dt_factor, bed_file (reuse a saved bed)
    [wheel]    type = "grouser" (radius, width, grouser_count, grouser_height, grouser_thickness)
               or type = "mesh" (file, scale); [wheel.material]
    [testbed]  mass, omega, mode ("free" | "slip"), slip, drawbar_load, start_x
    [run]      duration, dt | dt_factor (x Rayleigh step), macro_step | substeps, scheme, order_seed,
               max_speed
    [output]   snapshot_interval, checkpoint_interval, flush_every

Every section and key is optional (defaults: the Phobos single-wheel job); unknown keys
are errors. `load_scene(path, overrides)` returns a validated `Scene`; any problem raises
`SceneError` whose message names each bad field and what is allowed.
All units SI; angles in degrees where the key says `_deg`.
"""

from __future__ import annotations

import json
import math
import os
import re

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

GRAVITY_PRESET_NAMES = ("earth", "mars", "moon", "phobos", "phobos_min", "phobos_max", "deimos")


class SceneError(ValueError):
    """A scene file is invalid; `problems` lists one message per bad field."""

    def __init__(self, problems: list[str], source: str | None = None):
        self.problems = list(problems)
        self.source = source
        where = f" in {source}" if source else ""
        super().__init__(f"invalid scene{where}:\n" + "\n".join(f"  - {p}" for p in self.problems))


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


PositiveFloat = Field(gt=0)


class SceneSection(_Section):
    name: str = "scene"
    """A label for the run (plots, HDF5 attributes)."""
    gravity: str | float | list[float] = "phobos"
    """A preset name, a magnitude along -Z [m/s^2] or a 3-vector [m/s^2]."""
    precision: Literal["single", "double", "mixed"] = "mixed"
    """Floating-point mode of the DEM (DESIGN.md section 4)."""
    device: str = Field("default", validate_default=True)
    """Warp device: 'default' (CUDA when a GPU is present, else the CPU), 'cpu', 'cuda' or 'cuda:N'."""

    @field_validator("gravity")
    @classmethod
    def _gravity(cls, value):
        if isinstance(value, str):
            if value not in GRAVITY_PRESET_NAMES:
                raise ValueError(f"unknown gravity preset {value!r}; allowed: {', '.join(GRAVITY_PRESET_NAMES)}, "
                                 "a magnitude [m/s^2] or a 3-vector")
        elif isinstance(value, list):
            if len(value) != 3 or not all(math.isfinite(v) for v in value):
                raise ValueError("a gravity vector must be 3 finite numbers [m/s^2]")
        elif not (math.isfinite(value) and value >= 0):
            raise ValueError("a gravity magnitude must be a finite number >= 0 [m/s^2]")
        return value

    @field_validator("device")
    @classmethod
    def _device(cls, value):
        if value == "default":
            import warp as wp

            return str(wp.get_device())  # Warp's default: the first GPU, else the CPU
        if value != "cpu" and value != "cuda" and not (value.startswith("cuda:") and value[5:].isdigit()):
            raise ValueError("device must be 'default', 'cpu', 'cuda' or 'cuda:N'")
        return value

    def gravity_vector(self):
        from soil import gravity_vector

        return gravity_vector(self.gravity)


class MaterialSection(_Section):
    """A contact material (the soil's grains or the wheel)."""

    youngs_modulus: float = Field(2.0e5, gt=0)
    """Macroscopic Young's modulus [Pa] (paper eq. 10; `cosim advise` computes the bound)."""
    poisson_ratio: float = Field(0.15, gt=-1, lt=0.5)
    density: float = Field(2600.0, gt=0)
    """[kg/m^3]"""
    restitution: float | None = Field(None, gt=0, le=1)
    """Target coefficient of restitution [-]; default 0.3 unless damping_ratio is given."""
    damping_ratio: float | None = Field(None, ge=0)
    """Lehr damping ratio D [-] (instead of restitution)."""
    stick_angle_deg: float = Field(25.0, ge=0, lt=90)
    slip_angle_deg: float = Field(20.0, ge=0, lt=90)
    stick_speed: float = Field(1.0e-4, gt=0)
    """[m/s]"""
    rolling_friction: float = Field(0.1, ge=0)
    cohesion: float = Field(0.0, ge=0)
    """[Pa]"""

    @model_validator(mode="after")
    def _angles(self):
        if self.slip_angle_deg > self.stick_angle_deg:
            raise ValueError(f"slip_angle_deg: must be <= stick_angle_deg ({self.stick_angle_deg}) since sliding "
                             f"friction cannot exceed sticking friction (got {self.slip_angle_deg})")
        if self.restitution is not None and self.damping_ratio is not None:
            raise ValueError("damping_ratio: give restitution or damping_ratio, not both")
        return self

    def to_material(self):
        from soil import Material

        restitution = self.restitution if self.damping_ratio is None else None
        if restitution is None and self.damping_ratio is None:
            restitution = 0.3
        return Material(youngs_modulus=self.youngs_modulus, poisson_ratio=self.poisson_ratio, density=self.density,
                        restitution=restitution, damping_ratio=self.damping_ratio,
                        stick_angle=math.radians(self.stick_angle_deg), slip_angle=math.radians(self.slip_angle_deg),
                        stick_speed=self.stick_speed, rolling_friction=self.rolling_friction, cohesion=self.cohesion)


class LawSection(_Section):
    damping: bool = True
    friction: bool = True
    rolling: bool | None = None
    """None: on when a material has rolling_friction > 0."""
    cohesion: bool | None = None
    """None: on when a material has cohesion > 0."""


class SoilSection(MaterialSection):
    law: LawSection = LawSection()


class WheelMaterialSection(MaterialSection):
    youngs_modulus: float | None = Field(None, gt=0)
    """None: the soil's Young's modulus."""
    poisson_ratio: float = Field(0.3, gt=-1, lt=0.5)
    stick_angle_deg: float = Field(30.0, ge=0, lt=90)
    slip_angle_deg: float = Field(25.0, ge=0, lt=90)
    rolling_friction: float = Field(0.0, ge=0)

    def to_material(self, soil_modulus: float = 2.0e5):
        base = self.model_copy(update={"youngs_modulus": self.youngs_modulus or soil_modulus})
        return MaterialSection.to_material(base)


class BedSection(_Section):
    length: float = Field(0.24, gt=0)
    """Bed length along X (travel) [m]."""
    width: float = Field(0.08, gt=0)
    """Bed width along Y [m]."""
    depth: float = Field(0.03, gt=0)
    """Height of the inserted grains before settling [m]."""
    radius_mean: float = Field(3.0e-3, gt=0)
    """Mean grain radius [m]."""
    radius_spread: float = Field(0.2, ge=0, lt=1)
    """Relative half-width of the uniform radius distribution [-]."""
    seed: int = 1
    """Random seed of the grain insertion."""
    settle_ke_ratio: float = Field(1e-3, gt=0)
    """Settled when kinetic energy < ratio * N m g r (gravity-scaled) [-]."""
    settle_max_time: float = Field(10.0, gt=0)
    """Longest settling time [s] (simulated)."""
    settle_dt_factor: float = Field(0.2, gt=0, le=1)
    """Settling step as a fraction of the Rayleigh step of the smallest grain [-]."""
    bed_file: str | None = None
    """A bed saved by soil.bed.save_bed (or a previous run's bed.h5) to use instead of settling one."""

    @model_validator(mode="after")
    def _grains_fit(self):
        smallest = 4 * self.radius_mean * (1 + self.radius_spread)
        for name in ("length", "width", "depth"):
            if getattr(self, name) < smallest:
                raise ValueError(f"{name}: ({getattr(self, name)} m) must hold at least two of the largest grains "
                                 f"(>= {smallest:.4g} m)")
        return self


class WheelSection(_Section):
    type: Literal["grouser", "mesh"] = "grouser"
    radius: float | None = Field(None, gt=0)
    """Rim radius [m] (grouser wheel; default 0.04)."""
    width: float | None = Field(None, gt=0)
    """Wheel width [m] (grouser wheel; default 0.03)."""
    grouser_count: int | None = Field(None, ge=0, le=360)
    grouser_height: float | None = Field(None, ge=0)
    grouser_thickness: float | None = Field(None, ge=0)
    file: str | None = None
    """OBJ or STL file (mesh wheel), relative to the scene file; axle along the file's Y axis."""
    scale: float | None = Field(None, gt=0)
    """Mesh units -> metres (mesh wheel; default 1)."""
    material: WheelMaterialSection = WheelMaterialSection()

    @model_validator(mode="after")
    def _by_type(self):
        grouser_keys = ("radius", "width", "grouser_count", "grouser_height", "grouser_thickness")
        mesh_keys = ("file", "scale")
        if self.type == "grouser":
            wrong = [k for k in mesh_keys if getattr(self, k) is not None]
            if wrong:
                raise ValueError(f"{wrong[0]}: {', '.join(wrong)} belong(s) to type = 'mesh'; a grouser wheel takes "
                                 f"{', '.join(grouser_keys)}")
            defaults = {"radius": 0.04, "width": 0.03, "grouser_count": 12, "grouser_height": 0.004,
                        "grouser_thickness": 0.002}
            for key, value in defaults.items():
                if getattr(self, key) is None:
                    object.__setattr__(self, key, value)
            if self.grouser_count:
                if not self.grouser_height > 0 or not self.grouser_thickness > 0:
                    raise ValueError("grouser_height: grouser_height and grouser_thickness must be > 0 [m] when grouser_count > 0")
                spacing = 2 * math.pi * self.radius / self.grouser_count
                if self.grouser_thickness >= min(spacing, self.radius):
                    raise ValueError(f"grouser_thickness: ({self.grouser_thickness} m) must be < the grouser spacing "
                                     f"{spacing:.4g} m and < radius")
        else:
            wrong = [k for k in grouser_keys if getattr(self, k) is not None]
            if wrong:
                raise ValueError(f"{wrong[0]}: {', '.join(wrong)} belong(s) to type = 'grouser'; a mesh wheel takes "
                                 f"{', '.join(mesh_keys)}")
            if not self.file:
                raise ValueError("file: is required for type = 'mesh' (an .obj or .stl file)")
            if os.path.splitext(self.file)[1].lower() not in (".obj", ".stl"):
                raise ValueError(f"file: must be an .obj or .stl file, got {self.file!r}")
            if self.scale is None:
                object.__setattr__(self, "scale", 1.0)
        return self


class TestbedSection(_Section):
    __test__ = False  # not a pytest class

    mass: float = Field(6.0, gt=0)
    """Load mass, wheel included [kg]."""
    omega: float = 0.25
    """Wheel angular speed about +Y [rad/s] (> 0 drives towards +X)."""
    mode: Literal["free", "slip"] = "free"
    slip: float = Field(0.0, gt=-1, lt=1)
    """Set slip in mode 'slip' [-]."""
    drawbar_load: float = Field(0.0, ge=0)
    """Constant force resisting the carriage in mode 'free' [N]."""
    start_x: float | None = None
    """Initial hub x [m]; default: wheel outer radius + 6 grain radii from the x = 0 wall."""


class RunSection(_Section):
    duration: float = Field(3.0, gt=0)
    """Driving time [s] (simulated, after settling)."""
    dt: float | None = Field(None, gt=0)
    """DEM step [s]; or give dt_factor."""
    dt_factor: float | None = Field(None, gt=0, le=2)
    """DEM step as a fraction of the Rayleigh step of the smallest grain [-] (default 0.2)."""
    macro_step: float | None = Field(None, gt=0)
    """Coupling step H [s]: a whole number of DEM steps."""
    substeps: int | None = Field(None, ge=1)
    """DEM steps per macro step (instead of macro_step; default 10)."""
    scheme: Literal["gauss-seidel", "jacobi"] = "gauss-seidel"
    order_seed: int | None = None
    """Permute particle indices (summation order only), for replica studies."""
    max_speed: float | None = Field(None, gt=0)
    """A grain faster than this [m/s] means the run exploded; default 50 x max(rim speed, sqrt(2 g depth))."""

    @model_validator(mode="after")
    def _exclusive(self):
        if self.dt is not None and self.dt_factor is not None:
            raise ValueError("dt: give dt or dt_factor, not both")
        if self.macro_step is not None and self.substeps is not None:
            raise ValueError("macro_step: give macro_step or substeps, not both")
        if self.dt is not None and self.macro_step is not None:
            ratio = self.macro_step / self.dt
            if abs(ratio - round(ratio)) > 1e-6 * max(1.0, ratio) or round(ratio) < 1:
                raise ValueError(f"macro_step: ({self.macro_step} s) must be a whole multiple (>= 1) of dt "
                                 f"({self.dt} s); macro_step / dt = {ratio:.6g}")
        return self


class OutputSection(_Section):
    snapshot_interval: float = Field(0.25, ge=0)
    """Particle snapshots every this much simulated time [s] (0: first and last only)."""
    checkpoint_interval: float = Field(0.5, gt=0)
    """Checkpoints every this much simulated time [s]."""
    flush_every: int = Field(50, ge=1)
    """Write buffered time-series records to results.h5 every N macro steps."""


class Scene(_Section):
    scene: SceneSection = SceneSection()
    soil: SoilSection = SoilSection()
    bed: BedSection = BedSection()
    wheel: WheelSection = WheelSection()
    testbed: TestbedSection = TestbedSection()
    run: RunSection = RunSection()
    output: OutputSection = OutputSection()

    base_dir: str | None = Field(None, exclude=True)
    """Folder that relative paths (wheel.file, bed.bed_file) are relative to; not a scene key."""

    # -- derived quantities ------------------------------------------------------
    def wheel_shape(self):
        from soil import GrouserWheel, MeshWheel

        w = self.wheel
        if w.type == "grouser":
            return GrouserWheel(radius=w.radius, width=w.width, grouser_count=w.grouser_count,
                                grouser_height=w.grouser_height, grouser_thickness=w.grouser_thickness)
        return MeshWheel.load(self.resolve(w.file), scale=w.scale)

    def resolve(self, path: str | None) -> str | None:
        if path is None:
            return None
        path = os.path.expanduser(path)
        if not os.path.isabs(path) and self.base_dir:
            path = os.path.join(self.base_dir, path)
        return os.path.abspath(path)

    def wheel_extent(self) -> tuple[float, float, float]:
        """(outer radius, width, rim radius for slip) of the wheel [m]."""
        if self.wheel.type == "grouser":
            shape = self.wheel_shape()
            return shape.outer_radius, self.wheel.width, self.wheel.radius
        shape = self.wheel_shape()
        width = float(shape.vertices[:, 1].max() - shape.vertices[:, 1].min())
        return shape.outer_radius, width, shape.outer_radius

    def soil_material(self):
        return self.soil.to_material()

    def wheel_material(self):
        return self.wheel.material.to_material(self.soil.youngs_modulus)

    def contact_law(self):
        from soil import ContactLaw

        law = self.soil.law
        materials = [self.soil_material(), self.wheel_material()]
        rolling = law.rolling if law.rolling is not None else any(m.rolling_friction > 0 for m in materials)
        cohesion = law.cohesion if law.cohesion is not None else any(m.cohesion > 0 for m in materials)
        return ContactLaw(damping=law.damping, friction=law.friction, rolling=rolling, cohesion=cohesion)

    def bed_spec(self):
        from soil.bed import BedSpec

        b = self.bed
        return BedSpec(length=b.length, width=b.width, depth=b.depth, radius_mean=b.radius_mean,
                       radius_spread=b.radius_spread, material=self.soil_material(), seed=b.seed)

    def rayleigh_step(self) -> float:
        """Rayleigh time step of the smallest grain [s]."""
        from soil.bed import rayleigh_time_step

        smallest = self.bed.radius_mean * (1 - self.bed.radius_spread)
        return rayleigh_time_step(self.soil_material(), smallest)

    def time_steps(self) -> tuple[float, float, int]:
        """(dt [s], macro step H [s], substeps): H is exactly substeps x dt."""
        r = self.run
        if r.dt is not None:
            dt = r.dt
        else:
            dt = (r.dt_factor if r.dt_factor is not None else 0.2) * self.rayleigh_step()
        if r.macro_step is not None:
            substeps = max(1, int(round(r.macro_step / dt)))
            if r.dt is None:  # dt from the factor: shrink it so H is a whole number of steps
                substeps = max(1, math.ceil(r.macro_step / dt - 1e-9))
            return r.macro_step / substeps, r.macro_step, substeps
        substeps = r.substeps or 10
        return dt, dt * substeps, substeps

    def macro_step_count(self) -> int:
        _, h, _ = self.time_steps()
        return max(1, int(round(self.run.duration / h)))

    def gravity_magnitude(self) -> float:
        import numpy as np

        return float(np.linalg.norm(self.scene.gravity_vector()))

    def start_position(self, surface_height: float) -> list[float]:
        outer, _, _ = self.wheel_extent()
        x = self.testbed.start_x if self.testbed.start_x is not None else outer + 6 * self.bed.radius_mean
        return [x, 0.5 * self.bed.width, surface_height + outer]

    def max_speed(self) -> float:
        if self.run.max_speed is not None:
            return self.run.max_speed
        outer, _, _ = self.wheel_extent()
        g = self.gravity_magnitude()
        return 50.0 * max(abs(self.testbed.omega) * outer, math.sqrt(2 * g * self.bed.depth), 1e-3)

    # -- text ----------------------------------------------------------------------
    def to_dict(self) -> dict:
        return json.loads(self.model_dump_json(exclude_none=True))

    def to_toml(self) -> str:
        return dump_toml(self.to_dict())


# ------------------------------------------------------------------------------------
# loading, overrides, cross-section checks


_PHRASES = (
    ("Input should be greater than or equal to", "must be >="),
    ("Input should be less than or equal to", "must be <="),
    ("Input should be greater than", "must be >"),
    ("Input should be less than", "must be <"),
    ("Input should be a valid", "must be a valid"),
    ("Input should be", "must be"),
)


def _format_errors(error: ValidationError) -> list[str]:
    problems = []
    for item in error.errors():
        loc = ".".join(str(p) for p in item["loc"] if not str(p).startswith("function-after"))
        kind = item["type"]
        message = item["msg"]
        if message.startswith("Value error, "):
            message = message[len("Value error, "):]
        named = re.match(r"^([a-z_]+): ", message)
        if named:
            loc = f"{loc}.{named.group(1)}" if loc else named.group(1)
            message = message[named.end():]
        for old, new in _PHRASES:
            message = message.replace(old, new)
        if kind == "extra_forbidden":
            problems.append(f"{loc}: unknown key (not a scene setting; check the spelling)")
            continue
        got = item.get("input")
        shown = "" if isinstance(got, dict) else f" (got {got!r})"
        if kind == "literal_error":
            message = message.replace("Input should be", "must be")
        problems.append(f"{loc or 'scene'}: {message}{shown}")
    return problems


def parse_override(text: str) -> tuple[list[str], Any]:
    """'wheel.radius=0.05' -> (['wheel', 'radius'], 0.05); the value is read as TOML, else a string."""
    if "=" not in text:
        raise SceneError([f"--set {text!r}: expected key=value, e.g. wheel.radius=0.05"])
    key, value = text.split("=", 1)
    key = key.strip()
    if not key or any(not part for part in key.split(".")):
        raise SceneError([f"--set {text!r}: bad key {key!r}"])
    try:
        parsed = tomllib.loads(f"v = {value.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value.strip()
    return key.split("."), parsed


def apply_overrides(data: dict, overrides: list[str] | dict | None) -> dict:
    """Set dotted keys in a scene dictionary (a copy); overrides: ['a.b=1', ...] or {'a.b': 1}."""
    data = json.loads(json.dumps(data))
    if not overrides:
        return data
    items = ([parse_override(o) for o in overrides] if isinstance(overrides, (list, tuple))
             else [(k.split("."), v) for k, v in overrides.items()])
    for path, value in items:
        node = data
        for part in path[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise SceneError([f"{'.'.join(path)}: {part} is not a section"])
        node[path[-1]] = value
    return data


def validate_scene(data: dict, base_dir: str | None = None, source: str | None = None,
                   check_files: bool = True) -> Scene:
    """Validate a scene dictionary; raises SceneError listing every problem found."""
    try:
        scene = Scene.model_validate({**data, "base_dir": base_dir})
    except ValidationError as error:
        raise SceneError(_format_errors(error), source) from None
    problems = cross_check(scene, check_files=check_files)
    if problems:
        raise SceneError(problems, source)
    return scene


def cross_check(scene: Scene, check_files: bool = True) -> list[str]:
    """Checks that need several sections (geometry of wheel vs bed, files, time steps)."""
    problems = []
    bed, wheel, run, testbed = scene.bed, scene.wheel, scene.run, scene.testbed
    if check_files:
        if wheel.type == "mesh":
            path = scene.resolve(wheel.file)
            if not os.path.isfile(path):
                problems.append(f"wheel.file: mesh file not found: {path!r} (paths are relative to the scene file)")
                return problems
        if bed.bed_file is not None and not os.path.isfile(scene.resolve(bed.bed_file)):
            problems.append(f"bed.bed_file: bed file not found: {scene.resolve(bed.bed_file)!r}")
    try:
        outer, width, _ = scene.wheel_extent()
    except Exception as error:  # a mesh that does not load, a bad grouser geometry
        problems.append(f"wheel: {error}")
        return problems
    clearance = 2 * bed.radius_mean
    if width >= bed.width:
        problems.append(f"wheel.width: the wheel ({width:.4g} m) is wider than the bed (bed.width = {bed.width} m)")
    elif (bed.width - width) / 2 < clearance:
        problems.append(f"wheel.width: the wheel is too close to the side walls: gap {(bed.width - width) / 2:.4g} m "
                        f"per side; allowed: >= 2 mean grain radii = {clearance:.4g} m (widen bed.width)")
    x0 = scene.start_position(0.0)[0]
    if x0 - outer < clearance:
        problems.append(f"testbed.start_x: the wheel ({x0} m, outer radius {outer:.4g} m) starts too close to the "
                        f"x = 0 wall; allowed: start_x >= {outer + clearance:.4g} m")
    reach = abs(testbed.omega) * outer * run.duration
    if testbed.mode == "slip":
        reach = abs(testbed.omega) * outer * (1 - testbed.slip) * run.duration
    if x0 + reach + outer > bed.length - clearance:
        problems.append(f"run.duration: at the wheel's rim speed it may travel {reach:.4g} m from x = {x0:.4g} m and "
                        f"hit the far wall (bed.length = {bed.length} m); allowed: duration <= "
                        f"{max(0.0, (bed.length - clearance - outer - x0) / max(abs(testbed.omega) * outer, 1e-30)):.4g} s,"
                        " or a longer bed")
    if 2 * outer > 2.5 * bed.length:
        problems.append(f"wheel: outer diameter {2 * outer:.4g} m does not fit the bed (bed.length = {bed.length} m)")
    try:
        dt, h, substeps = scene.time_steps()
    except Exception as error:
        problems.append(f"run: {error}")
        return problems
    if h > run.duration:
        problems.append(f"run.macro_step: the macro step ({h:.4g} s) is longer than run.duration ({run.duration} s)")
    if scene.output.checkpoint_interval < h:
        problems.append(f"output.checkpoint_interval: {scene.output.checkpoint_interval} s is shorter than the "
                        f"macro step {h:.4g} s")
    try:
        scene.soil_material()
        scene.wheel_material()
    except ValueError as error:
        problems.append(f"soil: {error}")
    return problems


def load_scene(path: str | os.PathLike, overrides: list[str] | dict | None = None, check_files: bool = True) -> Scene:
    """Read, override (--set key=value) and validate a TOML scene file."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise SceneError([f"scene file not found: {path!r}"])
    with open(path, "rb") as f:
        try:
            data = tomllib.load(f)
        except tomllib.TOMLDecodeError as error:
            raise SceneError([f"not valid TOML: {error}"], path) from None
    data = apply_overrides(data, overrides)
    return validate_scene(data, base_dir=os.path.dirname(os.path.abspath(path)), source=path,
                          check_files=check_files)


def scene_from_text(text: str, base_dir: str | None = None, overrides=None, check_files: bool = True) -> Scene:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise SceneError([f"not valid TOML: {error}"]) from None
    return validate_scene(apply_overrides(data, overrides), base_dir=base_dir, check_files=check_files)


# ------------------------------------------------------------------------------------
# a small TOML writer (tables of scalars, lists and sub-tables)


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def dump_toml(data: dict, prefix: str = "") -> str:
    lines = []
    tables = []
    for key, value in data.items():
        if isinstance(value, dict):
            tables.append((key, value))
        elif value is not None:
            lines.append(f"{key} = {_toml_value(value)}")
    out = ""
    if lines:
        out += (f"[{prefix}]\n" if prefix else "") + "\n".join(lines) + "\n\n"
    for key, value in tables:
        out += dump_toml(value, f"{prefix}.{key}" if prefix else key)
    return out
