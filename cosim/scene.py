"""Scene files: the TOML schema of a run, validated field by field.

    [scene]    name, gravity (preset | magnitude [m/s^2] along -Z | 3-vector), precision, storage, device
    [soil]     grain material (youngs_modulus, poisson_ratio, density, restitution or damping_ratio,
               stick_angle_deg, slip_angle_deg, stick_speed, rolling_friction, cohesion)
    [soil.law] contact-law switches (damping, friction, rolling, cohesion)
    [bed]      length, width, depth, radius_mean, radius_spread, seed, settle_ke_ratio,
               settle_max_time, settle_dt_factor, bed_file (reuse a saved bed)
    [wheel]    type = "grouser" (radius, width, grouser_count, grouser_height, grouser_thickness)
               or type = "mesh" (file, scale); [wheel.material]
    [testbed]  mass, omega, mode ("free" | "slip"), slip, drawbar_load, drawbar_ramp, start_x
    [rover]    instead of [testbed]: model ("mjcf" | "mmx" | "fmu"), file, wheels | wheel_count,
               wheel_prefix, body, start_values, drive, stuck_slip; [rover.start] x, y, heading_deg;
               [rover.mmx] the built-in rover's parameters; [rover.wheel_shape.<wheel>] a wheel's own
               shape (a [wheel] section); [rover.controllers.<name>] named drives (kind "speed" |
               "torque" | "slip" | "fmu" | "python")
    [terrain]  model ("dem" | "scm" | "analytic") and the model's keys (scm: the Bekker, Mohr-Coulomb and
               Janosi parameters or a calibration file, the grid; wheels: each wheel's model)
    [patch]    a soil patch that follows the rover (the [bed] is its settled tile): length, width,
               band, clearance, recentre_distance, tile_margin
    [landing]  enabled, max_time, speed_ratio, hold_time
    [run]      duration, dt | dt_factor, macro_step | substeps, scheme, integrator, order_seed,
               step_control (fixed | pid), tolerance, dt_min, dt_max
    [output]   snapshot_interval, checkpoint_interval, flush_every

This module only validates: every number must be a number (not true / false), finite, 0 or of
magnitude SCENE_NUMBER_RANGE, and in its range, unknown keys are errors, and `SceneError` names
each bad field and what it allows. Quantities derived from several fields (time steps, wheel
extents, start pose) and the checks between sections are made once, by `cosim.plan.resolve`.
All units SI; angles in degrees where the key says `_deg`.
"""

from __future__ import annotations

import json
import math
import os
import re
import types
import typing
from typing import Any, Literal

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib

import tomli_w
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from soil.bed import radius_range
from soil.errors import InputError, is_real
from soil.scm.terrain import MAX_EROSION_ITERATIONS

GRAVITY_PRESET_NAMES = ("earth", "mars", "moon", "phobos", "phobos_min", "phobos_max", "deimos")


class SceneError(InputError, ValueError):
    """A scene is invalid; `problems` lists one message per bad field."""

    def __init__(self, problems: list[str], source: str | None = None):
        self.problems = list(problems)
        self.source = source
        where = f" in {source}" if source else ""
        super().__init__(f"invalid scene{where}:\n" + "\n".join(f"  - {p}" for p in self.problems))


SCENE_NUMBER_RANGE = (1e-30, 1e30)
"""The magnitudes a scene number may have besides 0 (SI): far beyond any rover scene's quantities, and
narrow enough that what a run derives from them (powers up to the tenth) neither over- nor underflows."""

INT64_MAX = 2**63 - 1
"""The largest integer a scene may give (counts and seeds are written as 64-bit integers)."""


PASSED_THROUGH = ("start_values",)
"""Fields whose numbers go to a model as they are (an FMU's parameters: Modelica writes infinity as
1e60), which the run derives nothing from: finite, with no magnitude bound."""


def _entries(value) -> list[tuple[str, Any]]:
    """A field's numbers with where they sit: ('', itself), or each list item's or table value's place."""
    if isinstance(value, dict):
        return [(f"[{k!r}]", v) for k, v in value.items()]
    if isinstance(value, (list, tuple)):
        return [(f"[{i}]", v) for i, v in enumerate(value)]
    return [("", value)]


def _annotation_types(annotation) -> set:
    """The types a field's annotation names, its unions' and containers' members included."""
    return {annotation}.union(*(_annotation_types(a) for a in typing.get_args(annotation)))


def _number_kinds(model: type[BaseModel], name: str) -> set:
    field = model.model_fields.get(name)
    return set() if field is None else _annotation_types(field.annotation)


def is_number(value) -> bool:
    """A real number and not a boolean (Python counts true as the integer 1): soil.errors.is_real."""
    return is_real(value)


def reject_bool_for_number(model: type[BaseModel], name: str, value):
    """A before-validator's test: true / false where a field takes a number and no boolean is refused
    (pydantic would read it as 1 or 0: `gravity = true` as 1 m/s^2)."""
    kinds = _number_kinds(model, name)
    if kinds & {float, int} and bool not in kinds:
        for where, v in _entries(value):
            if isinstance(v, bool):
                raise ValueError(f"{where + ': ' if where else ''}must be a number, not true or false")
    return value


def _members(annotation) -> list:
    """The types a value of `annotation` may be, its unions spread out (None's type dropped)."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return [m for a in typing.get_args(annotation) for m in _members(a)]
    return [] if annotation is type(None) else [annotation]


def _text_for_number(members: list, value, where: str = "") -> str | None:
    """Where `value` holds a text that only a number may take there (pydantic would read "1e6" as a
    number), or None: a text is a text where the annotation takes one (a name, a preset, a Literal)."""
    if isinstance(value, str):
        numbers = any(m in (int, float) for m in members)
        text = any(m is str or typing.get_origin(m) is Literal for m in members)
        return where or "itself" if numbers and not text else None
    if isinstance(value, (list, tuple, dict)):
        index = 1 if isinstance(value, dict) else 0  # a dict's values, a list's items
        inner = [
            m
            for c in members
            if typing.get_origin(c) in ((dict,) if isinstance(value, dict) else (list, tuple))
            for a in typing.get_args(c)[index : index + 1 if isinstance(value, dict) else None]
            if a is not Ellipsis
            for m in _members(a)
        ]
        for place, item in _entries(value):
            found = _text_for_number(inner, item, f"{where}{place}") if inner else None
            if found:
                return found
    return None


def reject_text_for_number(model: type[BaseModel], name: str, value):
    """A before-validator's test: a text where only a number may stand is refused (pydantic would read
    `youngs_modulus = "1e6"` as 1e6 Pa and `gravity = [0, 0, "-9.81"]` as a vector: a number is written
    without quotes, as the README says)."""
    field = model.model_fields.get(name)
    if field is None:
        return value
    where = _text_for_number(_members(field.annotation), value)
    if where:
        at = "" if where == "itself" else f"{where}: "
        raise ValueError(f"{at}must be a number, not a text: write a TOML number, unquoted (0.12, 1e-4)")
    return value


def reject_non_bool_for_switch(model: type[BaseModel], name: str, value):
    """A before-validator's test: where a field takes true or false and no number or text, anything else
    is refused (pydantic would read "no" as false and 1 as true: a typo that silently switches)."""
    kinds = _number_kinds(model, name)
    if bool in kinds and not kinds & {float, int, str} and value is not None and not isinstance(value, bool):
        raise ValueError("must be true or false (TOML's, lower-case)")
    return value


def check_magnitude(model: type[BaseModel], name: str, value):
    """An after-validator's test on a field that takes numbers (not one of PASSED_THROUGH): every float
    is 0 or within SCENE_NUMBER_RANGE, every integer a 64-bit one."""
    if not _number_kinds(model, name) & {float, int} or name in PASSED_THROUGH:
        return value
    low, high = SCENE_NUMBER_RANGE
    for where, v in _entries(value):
        at = f"{where}: " if where else ""
        if isinstance(v, float) and v != 0 and not low <= abs(v) <= high:
            raise ValueError(
                f"{at}must be 0 or of magnitude {low:g} .. {high:g} (SI): beyond, what the run derives from it "
                "overflows or underflows"
            )
        if isinstance(v, int) and not isinstance(v, bool) and abs(v) > INT64_MAX:
            raise ValueError(f"{at}must be an integer of magnitude <= {INT64_MAX} (a 64-bit integer)")
    return value


class NumbersChecked(BaseModel):
    """A section whose numbers are numbers (reject_bool_for_number) of bounded magnitude (check_magnitude)
    and whose switches are true or false (reject_non_bool_for_switch): the scene's and the soil lab's."""

    @field_validator("*", mode="before")
    @classmethod
    def _no_bool_for_number(cls, value, info):
        value = reject_text_for_number(cls, info.field_name, value)
        return reject_non_bool_for_switch(cls, info.field_name, reject_bool_for_number(cls, info.field_name, value))

    @field_validator("*")
    @classmethod
    def _magnitude(cls, value, info):
        return check_magnitude(cls, info.field_name, value)


class _Section(NumbersChecked):
    # no inf / nan anywhere, and no number out of SCENE_NUMBER_RANGE: a scene number is a physical
    # quantity; a key's docstring is its description (its unit in brackets: key_unit)
    model_config = ConfigDict(
        extra="forbid", validate_assignment=True, allow_inf_nan=False, use_attribute_docstrings=True
    )


def is_device_name(value: str) -> bool:
    """Whether `value` names a Warp device as a scene may: 'default', 'cpu', 'cuda' or 'cuda:N'."""
    return value in ("default", "cpu", "cuda") or (value.startswith("cuda:") and value[5:].isdigit())


SCENE_NAME_BYTES = 128
"""The longest scene name, in UTF-8 bytes: folders named after it (runs/NAME_precision/double_r0) stay
under the 255 bytes a file name may have."""


class SceneSection(_Section):
    name: str = Field("scene", min_length=1)
    """A label for the run (plots, HDF5 attributes)."""
    gravity: str | float | list[float] = "phobos"
    """A preset name, a magnitude along -Z [m/s^2] or a 3-vector [m/s^2]."""
    precision: Literal["single", "double", "mixed"] = "mixed"
    """Floating-point mode of the DEM (docs/physics.md section 3)."""
    storage: Literal["grain", "slot"] = "grain"
    """Order of the DEM's neighbour lists and contact history in memory: per grain, or per slot (what
    neighbouring GPU threads read together); the same results to the last bit (docs/performance.md section 2)."""
    device: str = "default"
    """Warp device: 'default' (CUDA when a GPU is present, else the CPU), 'cpu', 'cuda' or 'cuda:N'."""

    @field_validator("name")
    @classmethod
    def _name(cls, value: str) -> str:
        # the name becomes a folder under runs/: a path in it would put the run elsewhere
        if "/" in value or "\\" in value or value in (".", "..") or value.startswith(".") or "\0" in value:
            raise ValueError(
                "must be a plain name, not a path (no '/', '\\', no leading '.'): the run goes to runs/NAME; "
                "choose another folder with --out"
            )
        if len(value.encode()) > SCENE_NAME_BYTES:
            raise ValueError(
                f"must be at most {SCENE_NAME_BYTES} bytes (got {len(value.encode())}): it names the run's folder "
                "and the studies' (NAME_slip/..., NAME_precision), which a file system caps at 255"
            )
        return value

    @field_validator("gravity", mode="before")
    @classmethod
    def _gravity_not_finite(cls, value):
        # before the union's members are tried: each would say its own line of a nan (a text, a list)
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError("a gravity magnitude must be a finite number >= 0 [m/s^2]")
        if isinstance(value, list) and any(isinstance(v, float) and not math.isfinite(v) for v in value):
            raise ValueError("a gravity vector must be 3 finite numbers [m/s^2]")
        return value

    @field_validator("gravity")
    @classmethod
    def _gravity(cls, value):
        if isinstance(value, str):
            if value not in GRAVITY_PRESET_NAMES:
                raise ValueError(
                    f"unknown gravity preset {value!r}; allowed: {', '.join(GRAVITY_PRESET_NAMES)}, "
                    "a magnitude [m/s^2] or a 3-vector"
                )
        elif isinstance(value, list):
            if len(value) != 3 or not all(math.isfinite(v) for v in value):
                raise ValueError("a gravity vector must be 3 finite numbers [m/s^2]")
        elif not (math.isfinite(value) and value >= 0):
            raise ValueError("a gravity magnitude must be a finite number >= 0 [m/s^2]")
        return value

    @field_validator("device")
    @classmethod
    def _device(cls, value):
        if not is_device_name(value):
            raise ValueError("must be 'default', 'cpu', 'cuda' or 'cuda:N'")
        return value


class MaterialSection(_Section):
    """A contact material (the soil's grains or the wheel)."""

    youngs_modulus: float = Field(2.0e5, gt=0)
    """Macroscopic Young's modulus [Pa] (paper eq. 10; `cosim advise` computes the bound)."""
    poisson_ratio: float = Field(0.15, gt=-1, lt=0.5)
    """[-]"""
    density: float = Field(2600.0, gt=0)
    """[kg/m^3]"""
    restitution: float | None = Field(None, gt=0, le=1)
    """Target coefficient of restitution [-]; default 0.3 unless damping_ratio is given."""
    damping_ratio: float | None = Field(None, ge=0)
    """Lehr damping ratio D [-] (instead of restitution)."""
    stick_angle_deg: float = Field(25.0, ge=0, lt=90)
    slip_angle_deg: float = Field(20.0, ge=0, lt=90)
    stick_speed: float | None = Field(None, gt=0)
    """Stick speed v_Tmin [m/s]; default 0.02 sqrt(|g| d) (d: the mean grain diameter), the same
    fraction of the grains' own speed scale at every gravity (1e-4 m/s for 2 mm grains at Phobos;
    docs/physics.md section 1.3). A wheel's material defaults to the soil's."""
    rolling_friction: float = Field(0.1, ge=0)
    """Rolling resistance coefficient mu_r [-]."""
    cohesion: float = Field(0.0, ge=0)
    """[Pa]"""

    @model_validator(mode="after")
    def _angles(self):
        if self.slip_angle_deg > self.stick_angle_deg:
            raise ValueError(
                f"slip_angle_deg: must be <= stick_angle_deg ({self.stick_angle_deg}) since sliding "
                f"friction cannot exceed sticking friction (got {self.slip_angle_deg})"
            )
        if self.restitution is not None and self.damping_ratio is not None:
            raise ValueError("damping_ratio: give restitution or damping_ratio, not both")
        return self


class LawSection(_Section):
    damping: bool = True
    friction: bool = True
    rolling: bool | None = None
    """None: on when a material has rolling_friction > 0."""
    cohesion: bool | None = None
    """None: on when a material has cohesion > 0."""
    twisting: bool = False
    """Twisting resistance about the contact normal (from the Mindlin patch; no parameter)."""


class SoilSection(MaterialSection):
    law: LawSection = LawSection()


class WheelMaterialSection(MaterialSection):
    youngs_modulus: float | None = Field(None, gt=0)  # type: ignore[assignment]
    """[Pa]; None: the soil's Young's modulus."""
    poisson_ratio: float = Field(0.3, gt=-1, lt=0.5)
    """[-]"""
    stick_angle_deg: float = Field(30.0, ge=0, lt=90)
    slip_angle_deg: float = Field(25.0, ge=0, lt=90)
    rolling_friction: float = Field(0.0, ge=0)
    """Rolling resistance coefficient mu_r [-]."""


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
    seed: int = Field(1, ge=0)
    """Random seed of the grain insertion [-] (>= 0)."""
    settle_ke_ratio: float = Field(1e-3, gt=0)
    """Settled when kinetic energy < ratio * N m g r (gravity-scaled) [-], judged only after 10 x the time a
    grain released from rest needs in free fall to reach that energy, sqrt(2 ratio r / g) (soil.bed.settle)."""
    settle_max_time: float = Field(10.0, gt=0)
    """Longest settling time [s] (simulated)."""
    settle_dt_factor: float = Field(0.2, gt=0, le=1)
    """Settling step as a fraction of the Rayleigh step of the smallest grain [-]."""
    bed_file: str | None = None
    """A bed saved by soil.bed.save_bed (or a previous run's bed.h5) to use instead of settling one."""

    @property
    def radius_min(self) -> float:
        """Smallest grain radius [m]: radius_mean (1 - radius_spread) (soil.bed.radius_range)."""
        return radius_range(self.radius_mean, self.radius_spread)[0]

    @property
    def radius_max(self) -> float:
        """Largest grain radius [m]: radius_mean (1 + radius_spread) (soil.bed.radius_range)."""
        return radius_range(self.radius_mean, self.radius_spread)[1]

    @model_validator(mode="after")
    def _grains_fit(self):
        smallest = 4 * self.radius_max
        for name in ("length", "width", "depth"):
            if getattr(self, name) < smallest:
                raise ValueError(
                    f"{name}: ({getattr(self, name)} m) must hold at least two of the largest grains "
                    f"(>= {smallest:.4g} m)"
                )
        return self


class WheelSection(_Section):
    type: Literal["grouser", "mesh"] = "grouser"
    radius: float | None = Field(None, gt=0)
    """Rim radius [m] (grouser wheel; default 0.04)."""
    width: float | None = Field(None, gt=0)
    """Wheel width [m] (grouser wheel; default 0.03)."""
    grouser_count: int | None = Field(None, ge=0, le=360)
    """[count]"""
    grouser_height: float | None = Field(None, ge=0)
    """[m]"""
    grouser_thickness: float | None = Field(None, ge=0)
    """[m]"""
    file: str | None = None
    """OBJ or STL file (mesh wheel), relative to the scene file; axle along the file's Y axis."""
    scale: float | None = Field(None, gt=0)
    """Mesh units -> metres [m] per mesh unit (mesh wheel; default 1)."""
    material: WheelMaterialSection = WheelMaterialSection()

    @model_validator(mode="after")
    def _by_type(self):
        grouser_keys = ("radius", "width", "grouser_count", "grouser_height", "grouser_thickness")
        mesh_keys = ("file", "scale")
        if self.type == "grouser":
            wrong = [k for k in mesh_keys if getattr(self, k) is not None]
            if wrong:
                raise ValueError(
                    f"{wrong[0]}: {', '.join(wrong)} belong(s) to type = 'mesh'; a grouser wheel takes "
                    f"{', '.join(grouser_keys)}"
                )
            defaults = {
                "radius": 0.04,
                "width": 0.03,
                "grouser_count": 12,
                "grouser_height": 0.004,
                "grouser_thickness": 0.002,
            }
            for key, value in defaults.items():
                if getattr(self, key) is None:
                    object.__setattr__(self, key, value)
            radius, count = self.radius, self.grouser_count
            height, thickness = self.grouser_height, self.grouser_thickness
            assert radius is not None and count is not None and height is not None and thickness is not None
            if count:
                if not height > 0 or not thickness > 0:
                    raise ValueError(
                        "grouser_height: grouser_height and grouser_thickness must be > 0 [m] when grouser_count > 0"
                    )
                spacing = 2 * math.pi * radius / count
                if thickness >= min(spacing, radius):
                    raise ValueError(
                        f"grouser_thickness: ({thickness} m) must be < the grouser spacing {spacing:.4g} m and < radius"
                    )
        else:
            wrong = [k for k in grouser_keys if getattr(self, k) is not None]
            if wrong:
                raise ValueError(
                    f"{wrong[0]}: {', '.join(wrong)} belong(s) to type = 'grouser'; a mesh wheel takes "
                    f"{', '.join(mesh_keys)}"
                )
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
    """Load mass, wheel included [kg]: the wheel load is W = mass |g|."""
    omega: float = Field(0.25, gt=0)
    """Wheel angular speed about +Y while driving [rad/s] (drives towards +X)."""
    mode: Literal["free", "slip"] = "free"
    """free: the carriage is free along X and slip emerges; slip: the carriage is driven at the set slip."""
    slip: float = Field(0.0, gt=-1, lt=1)
    """Set slip in mode 'slip' [-]."""
    drawbar_load: float = Field(0.0, ge=0)
    """Constant force resisting the carriage in mode 'free' [N]."""
    drawbar_ramp: float = Field(0.0, ge=0)
    """Growth rate of the resisting force in mode 'free' [N/s] (a drawbar-pull/slip curve in one run)."""
    start_x: float | None = None
    """Initial hub x [m]; default: wheel outer radius + 6 grain radii from the x = 0 wall."""

    def unused_keys(self) -> dict[str, str]:
        """{key: why it changes nothing} of the keys this mode does not read (a sweep over one of them
        runs the same scene at every point)."""
        if self.mode == "free":
            return {"testbed.slip": "testbed.mode is 'free': the slip emerges (set testbed.mode = \"slip\")"}
        why = "testbed.mode is 'slip': the carriage is driven at the set slip, no force resists it"
        return {"testbed.drawbar_load": why, "testbed.drawbar_ramp": why}


class DriveSection(_Section):
    """How the wheels are driven after the landing (cosim.controllers, cosim.fmu_controller)."""

    kind: Literal["speed", "torque", "slip", "fmu", "python"] = "speed"
    """speed: constant wheel speeds; torque: constant wheel torques; slip: the PI slip controller;
    fmu: a drive-controller FMU; python: a controller made by a Python callable."""
    speed: float | list[float] | None = None
    """kind 'speed': wheel speed about the axle [rad/s], one value or one per wheel."""
    torque: float | list[float] | None = None
    """kind 'torque': wheel torque about the axle [N m], one value or one per wheel."""
    target_slip: float | None = Field(None, ge=0, lt=1)
    """kind 'slip': the slip s = 1 - v / (omega r) to hold [-]."""
    kp: float | None = Field(None, ge=0)
    """kind 'slip': proportional gain on the hub velocity error [-] (default 1)."""
    ki: float | None = Field(None, ge=0)
    """kind 'slip': integral gain [1/s] (default 20)."""
    omega_min: float | None = Field(None, ge=0)
    """kind 'slip': lowest commanded speed [rad/s] (default: 0.1 x omega_max; >= 0: the wheels never turn
    backwards to hold a slip)."""
    omega_max: float | None = Field(None, gt=0)
    """kind 'slip': highest commanded speed [rad/s] (required)."""
    file: str | None = None
    """kind 'fmu': the controller FMU, relative to the scene file."""
    mode: Literal["speed", "torque"] | None = None
    """kind 'fmu': which command outputs to read (default: the ones the FMU has)."""
    start_values: dict[str, float] | None = None
    """kind 'fmu': FMU parameters {name: value}."""
    function: str | None = None
    """kind 'python': "module:function", called once as function(wheel_count=n, wheel_radius=(r, ...), **args);
    it returns the controller (cosim.controllers.Controller). The scene file's folder is searched first."""
    args: dict[str, Any] | None = None
    """kind 'python': keyword arguments of the function."""

    @model_validator(mode="after")
    def _by_kind(self):
        keys = {
            "speed": ("speed",),
            "torque": ("torque",),
            "slip": ("target_slip", "kp", "ki", "omega_min", "omega_max"),
            "fmu": ("file", "mode", "start_values"),
            "python": ("function", "args"),
        }
        wrong = [k for kind, names in keys.items() if kind != self.kind for k in names if getattr(self, k) is not None]
        if wrong:
            raise ValueError(
                f"{wrong[0]}: {', '.join(wrong)} do(es) not belong to kind = {self.kind!r}; it takes "
                f"{', '.join(keys[self.kind])}"
            )
        required = {"speed": "speed", "torque": "torque", "slip": "target_slip", "fmu": "file", "python": "function"}
        if getattr(self, required[self.kind]) is None:
            raise ValueError(f"{required[self.kind]}: is required for kind = {self.kind!r}")
        if self.kind == "slip" and self.omega_max is None:
            raise ValueError(
                "omega_max: is required for kind = 'slip' (the highest wheel speed it may command [rad/s])"
            )
        for name in ("speed", "torque"):
            value = getattr(self, name)
            values = value if isinstance(value, list) else [] if value is None else [value]
            if not all(math.isfinite(v) for v in values) or (isinstance(value, list) and not value):
                raise ValueError(f"{name}: must be a finite number or a non-empty list of them")
        if self.function is not None and not re.fullmatch(r"[A-Za-z_][\w.]*:[A-Za-z_]\w*", self.function):
            raise ValueError(f"function: must be 'module:function' (e.g. 'my_controllers:make'), got {self.function!r}")
        return self


class StartSection(_Section):
    """Where the rover starts (its base body's frame origin); its height is found: the lowest grouser
    tip just above the highest grain under it."""

    x: float | None = None
    """[m]; default: clear of the bed's x = 0 wall (a bed), 0 (a patch)."""
    y: float | None = None
    """[m]; default: the bed's centre line (a bed), 0 (a patch)."""
    heading_deg: float = 0.0
    """Turn of the rover about +z [deg] (0: as in its model, wheels rolling towards +x)."""


class MmxSection(_Section):
    """Parameters of the built-in MMX-like rover (rover_models.mjcf.mmx_rover_xml); the wheel radius
    and width are those of the [wheel] section."""

    body_mass: float = Field(17.0, gt=0)
    """[kg]"""
    leg_mass: float = Field(0.5, gt=0)
    """[kg]"""
    wheel_mass: float = Field(1.5, gt=0)
    """[kg]"""
    body_size: list[float] = [0.41, 0.37, 0.30]
    """Body box, full sizes along x, y, z [m]."""
    wheelbase: float = Field(0.40, gt=0)
    """Distance between the front and rear axles [m]."""
    track: float = Field(0.50, gt=0)
    """Distance between the left and right wheels [m]."""
    leg_drop: float = Field(0.15, ge=0)
    """Hubs below the body centre [m]."""
    motor_kv: float = Field(20.0, gt=0)
    """Velocity-motor gain [N m s/rad]."""
    timestep: float = Field(1.0e-3, gt=0)
    """MuJoCo's step [s]."""

    @field_validator("body_size")
    @classmethod
    def _size(cls, value):
        if len(value) != 3 or not all(math.isfinite(v) and v > 0 for v in value):
            raise ValueError("must be 3 finite sizes > 0 [m]")
        return value


class RoverSection(_Section):
    """A rover on the soil (instead of the single-wheel [testbed])."""

    model: Literal["mjcf", "mmx", "fmu"] = "mmx"
    """mjcf: an MJCF file; mmx: the built-in MMX-like rover ([rover.mmx]); fmu: a rover FMU."""
    file: str | None = None
    """The MJCF or FMU file, relative to the scene file."""
    wheels: list[str] | None = None
    """MJCF: the wheel body names (their order is the wheel order everywhere); default for 'mmx':
    wheel_fl, wheel_fr, wheel_rl, wheel_rr."""
    wheel_count: int | None = Field(None, ge=1)
    """FMU: how many wheels [count] (<prefix>0 .. <prefix>n-1); default: as many as the FMU has."""
    wheel_prefix: str = Field("wheel_", min_length=1)
    """FMU: the wheels' variable prefix (wheel_0.force.x, ...)."""
    body: str | None = None
    """MJCF: the body reported as the rover's pose (default: the base carrying the first wheel)."""
    start_values: dict[str, float] | None = None
    """FMU: parameters {name: value} set before it starts."""
    mmx: MmxSection | None = None
    start: StartSection = StartSection()
    wheel_shape: dict[str, WheelSection] | None = None
    """A wheel's own shape, by wheel name; the others use [wheel]."""
    drive: str | DriveSection = DriveSection(kind="speed", speed=0.0)
    """The drive: a table (kind = ...), or the name of one of [rover.controllers]."""
    controllers: dict[str, DriveSection] | None = None
    """Named drives; `drive = "<name>"` picks one (`cosim sweep --param rover.drive=a,b` compares them)."""
    stuck_slip: float = Field(0.9, gt=0, lt=1)
    """Stuck criterion: the rover is immobile while its slip over one radian of wheel turn is at least this [-]."""

    @field_validator("controllers")
    @classmethod
    def _controller_names(cls, value):
        # a drive's name becomes a folder of a sweep over drives (runs/NAME/<drive>)
        for name in value or {}:
            if not re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_.+-]{0,63}", name):
                raise ValueError(
                    f"[{name!r}]: a controller's name must be a plain name of 1 .. 64 letters, digits, '_', '.', "
                    "'+' or '-' (not starting with '.'): a sweep over drives names its run folders after it"
                )
        return value

    @model_validator(mode="after")
    def _by_model(self):
        if self.model in ("mjcf", "fmu") and not self.file:
            raise ValueError(f"file: is required for model = {self.model!r}")
        if self.model == "mmx" and self.file:
            raise ValueError("file: the built-in rover (model = 'mmx') takes no file; its parameters go in [rover.mmx]")
        if self.model == "mjcf" and not self.wheels:
            raise ValueError('wheels: name the MJCF\'s wheel bodies, e.g. wheels = ["wheel_fl", "wheel_fr"]')
        if self.model == "fmu" and self.wheels:
            raise ValueError("wheels: an FMU's wheels are numbered; give wheel_count and wheel_prefix instead")
        if self.model != "fmu":  # given but unused: refused, not silently ignored (a saved scene holds the defaults)
            given = {
                "wheel_count": self.wheel_count is not None,
                "start_values": bool(self.start_values),
                "wheel_prefix": self.wheel_prefix != type(self).model_fields["wheel_prefix"].default,
            }
            wrong = [key for key, set_ in given.items() if set_]
            if wrong:
                raise ValueError(f"{wrong[0]}: belongs to model = 'fmu'")
        if self.model != "mmx" and self.mmx is not None:
            raise ValueError("mmx: [rover.mmx] belongs to model = 'mmx'")
        if self.model == "fmu" and self.body is not None:
            raise ValueError("body: an FMU reports its body through body.* outputs; body names an MJCF body")
        if self.wheels is not None and len(set(self.wheels)) != len(self.wheels):
            raise ValueError(f"wheels: names a wheel twice: {self.wheels}")
        if self.file and self.model == "mjcf" and os.path.splitext(self.file)[1].lower() not in (".xml", ".mjcf"):
            raise ValueError(f"file: an MJCF file ends in .xml, got {self.file!r}")
        if self.file and self.model == "fmu" and os.path.splitext(self.file)[1].lower() != ".fmu":
            raise ValueError(f"file: an FMU file ends in .fmu, got {self.file!r}")
        if isinstance(self.drive, str) and self.drive not in (self.controllers or {}):
            names = ", ".join(sorted(self.controllers or {})) or "none are defined"
            raise ValueError(f"drive: unknown controller {self.drive!r}; [rover.controllers] has: {names}")
        return self

    @property
    def drive_section(self) -> DriveSection:
        """The drive in use (a named controller resolved)."""
        if isinstance(self.drive, str):
            assert self.controllers is not None  # the validator checked that the name is one of them
            return self.controllers[self.drive]
        return self.drive


class PatchSection(_Section):
    """A window of soil that follows the rover: grains far behind are removed, settled soil from the
    [bed] tile is placed ahead (docs/rover.md). The window is centred on the rover's wheels."""

    length: float = Field(..., gt=0)
    """Window size along x [m]."""
    width: float = Field(..., gt=0)
    """Window size along y [m]."""
    band: float | None = Field(None, gt=0)
    """Width of the frozen band at the window's edge that holds the soil in [m] (default 2 largest grain diameters)."""
    clearance: float | None = Field(None, ge=0)
    """Least gap between a wheel and the frozen band [m] (default 4 mean grain diameters; at least one
    largest grain diameter)."""
    recentre_distance: float | None = Field(None, gt=0)
    """The window moves when the wheels' centre is this far from its centre along x or y [m] (default: as
    far as the clearance allows)."""
    tile_margin: float | None = Field(None, ge=0)
    """The tile is the [bed] without the grains this close to its side walls [m] (default 2 largest grain
    diameters: the walls order the packing near them)."""


ANALYTIC_KEYS = ("stiffness", "damping", "friction", "traction", "slip_scale", "slip_velocity")
"""The [terrain] keys of model = "analytic" only."""

SCM_SOIL_KEYS = ("k_c", "k_phi", "n", "cohesion", "friction_angle_deg", "janosi_k", "elastic_stiffness")
"""The SCM soil's parameters: a scene on model = "scm" gives each, or a calibration file gives them."""

SCM_KEYS = SCM_SOIL_KEYS + (
    "pressure_damping",
    "node_spacing",
    "bulldozing",
    "bulldozing_fraction",
    "erosion_angle_deg",
    "erosion_iterations",
    "window_length",
    "window_width",
    "time_step",
    "calibration",
    "wheels",
)
"""The [terrain] keys of model = "scm" only."""

TERRAIN_WHEEL_MODELS = ("dem", "scm")
"""The models a wheel of terrain.wheels may name."""


MAX_SURFACE_HEIGHT = 1e6
"""The farthest an analytic or SCM ground may lie from z = 0 [m]: far beyond any terrain's relief, and near
enough that a sinkage, a difference of heights, keeps its digits (at 1e11 m it did not)."""


class TerrainSection(_Section):
    """The terrain the wheels run on: the DEM bed of [bed] (the default), the Soil Contact Model
    (model = "scm": soil.scm, a height field with Bekker pressure-sinkage and Janosi shear; docs/scm.md)
    or the analytic test terrain (cosim.terrain.SpringDamperTerrain: flat spring-damper ground, each
    wheel a disc of its rim radius). Unset keys take the model's defaults."""

    model: Literal["dem", "scm", "analytic"] = "dem"
    stiffness: float | None = Field(None, gt=0)
    """analytic: normal penalty stiffness per wheel [N/m] (default 2e4)."""
    damping: float | None = Field(None, ge=0)
    """analytic: normal damping per wheel [N s/m] (default 500)."""
    friction: float | None = Field(None, ge=0)
    """analytic: friction / traction coefficient [-] (default 0.6)."""
    traction: Literal["coulomb", "slip"] | None = None
    """analytic: 'coulomb' (regularised Coulomb, the default) or 'slip' (a slip-ratio traction law)."""
    slip_scale: float | None = Field(None, gt=0)
    """analytic: the slip at which the 'slip' law reaches 63 % of mu F_n [-] (default 0.1)."""
    slip_velocity: float | None = Field(None, gt=0)
    """analytic: regularisation velocity of the friction laws [m/s] (default 1e-3)."""
    surface_height: float | None = None
    """analytic, scm: height z of the undisturbed ground [m] (default 0; scm with DEM wheels: the bed's),
    within +-MAX_SURFACE_HEIGHT."""
    k_c: float | None = Field(None, ge=0)
    """scm: Bekker cohesive modulus k_c [Pa m^(1-n)]."""
    k_phi: float | None = Field(None, ge=0)
    """scm: Bekker frictional modulus k_phi [Pa m^(-n)]."""
    n: float | None = Field(None, gt=0, lt=3)
    """scm: Bekker sinkage exponent [-] (below 3: the wheel's closed-form sinkage has 3 - n)."""
    cohesion: float | None = Field(None, ge=0)
    """scm: Mohr-Coulomb cohesion [Pa]."""
    friction_angle_deg: float | None = Field(None, ge=0, lt=90)
    """scm: Mohr-Coulomb internal friction angle [deg]."""
    janosi_k: float | None = Field(None, gt=0)
    """scm: Janosi-Hanamoto shear deformation modulus K [m]."""
    elastic_stiffness: float | None = Field(None, gt=0)
    """scm: unloading/reloading stiffness K_e [Pa/m]."""
    pressure_damping: float | None = Field(None, ge=0)
    """scm: normal damping R [Pa s/m] on the wheel surface's speed into the soil (default: the
    critical damping of a wheel's elastic bounce, cosim.scm_soil.scm_settings)."""
    node_spacing: float | None = Field(None, gt=0)
    """scm: grid node spacing [m] (default: the narrowest wheel's width / 12, or its thinnest grouser / 1.5
    where that is finer: cosim.scm_soil.node_spacing)."""
    bulldozing: bool | None = None
    """scm: move the soil a wheel displaces to its rut's rims (default false)."""
    bulldozing_fraction: float | None = Field(None, ge=0, le=1)
    """scm: fraction of the displaced volume moved to the rims [-] (default 1)."""
    erosion_angle_deg: float | None = Field(None, gt=0, lt=90)
    """scm: steepest slope the moved soil keeps [deg] (default 30)."""
    erosion_iterations: int | None = Field(None, ge=0, le=MAX_EROSION_ITERATIONS)
    """scm: slope-limiting passes per step [count] (default 2; at most soil.scm.terrain.MAX_EROSION_ITERATIONS)."""
    window_length: float | None = Field(None, gt=0)
    """scm: the node window's size along x [m] (default: the hubs' span + 8 outer radii; it must hold the
    wheels' footprints, a rover's at any heading)."""
    window_width: float | None = Field(None, gt=0)
    """scm: the node window's size along y [m] (default: the hubs' span + the wheel width + 4 outer radii)."""
    time_step: float | None = Field(None, gt=0)
    """scm: the SCM step [s] (default: the macro step; each macro step is split into steps of at most this)."""
    calibration: str | None = Field(None, min_length=1)
    """scm: a calibration file (`cosim calibrate-scm`) giving the soil keys not given here."""
    wheels: list[Literal["dem", "scm"]] | None = None
    """scm: each wheel's model, in wheel order (e.g. ["dem", "scm", "scm", "scm"]): the "dem" wheels on
    the grains of [bed] (and [patch]), the others on SCM (default: every wheel on SCM)."""

    @model_validator(mode="after")
    def _keys_of_model(self):
        for keys, model in ((ANALYTIC_KEYS, "analytic"), (SCM_KEYS, "scm")):
            if self.model == model:
                continue
            given = [key for key in keys if getattr(self, key) is not None]
            if given:
                raise ValueError(
                    f"{given[0]}: a key of the {'analytic terrain' if model == 'analytic' else 'SCM terrain'} "
                    f'(model = "{model}"); model = {self.model!r} takes none of {", ".join(keys)}'
                )
        if self.model == "dem" and self.surface_height is not None:
            raise ValueError(
                'surface_height: the DEM\'s surface is its settled bed\'s; a key of model = "analytic" or "scm"'
            )
        if self.surface_height is not None and abs(self.surface_height) > MAX_SURFACE_HEIGHT:
            raise ValueError(
                f"surface_height: allowed within +-{MAX_SURFACE_HEIGHT:.0e} m, got {self.surface_height:.4g} m (a "
                "sinkage is a difference of heights, which far from the origin keeps too few digits: at 1e11 m "
                "the main job's SCM sinkage read 3.60 mm for 3.93): place the ground near z = 0"
            )
        if not self.bulldozing:  # the rims and their slopes are moved only by bulldozing: the keys would be ignored
            rim_keys = ("bulldozing_fraction", "erosion_angle_deg", "erosion_iterations")
            given = [k for k in rim_keys if getattr(self, k) is not None]
            if given:
                raise ValueError(
                    f"{given[0]}: a key of SCM's bulldozing, which is off (bulldozing = "
                    f"{'false' if self.bulldozing is False else 'unset, default false'}): set bulldozing = true, "
                    "or remove it"
                )
        if self.model == "scm" and self.calibration is None:
            missing = [key for key in SCM_SOIL_KEYS if getattr(self, key) is None]
            if missing:
                raise ValueError(
                    f'{missing[0]}: model = "scm" needs the soil\'s {", ".join(missing)} (or calibration = a file '
                    "written by `cosim calibrate-scm`)"
                )
        return self

    @property
    def dem_wheels(self) -> bool:
        """Some wheel runs on the DEM (model "dem", or "dem" in terrain.wheels)."""
        return self.model == "dem" or "dem" in (self.wheels or [])


class LandingSection(_Section):
    """The wheel lands before it drives: it settles onto the soil under its load, not turning."""

    enabled: bool = True
    max_time: float = Field(30.0, gt=0)
    """Longest landing phase [s] (simulated); a wheel not at rest by then ends the run 'no landing'."""
    speed_ratio: float = Field(0.02, gt=0)
    """At rest when the hub sinks at less than speed_ratio * sqrt(|g| r) on average (its heights over the hold
    spreading less than 3 x that drift: cosim.runner.LANDING_FLICKER) [-] ..."""
    hold_time: float | None = Field(None, gt=0)
    """... over this long [s], touching the soil all the while; default sqrt(r / |g|) (r: wheel outer radius)."""


class RunSection(_Section):
    duration: float = Field(3.0, gt=0)
    """Driving time after landing [s] (simulated)."""
    dt: float | None = Field(None, gt=0)
    """DEM step [s]; or give dt_factor."""
    dt_factor: float | None = Field(None, gt=0, le=2)
    """DEM step as a fraction of the Rayleigh step of the smallest grain [-] (default 0.2)."""
    macro_step: float | None = Field(None, gt=0)
    """Coupling step H [s]: a whole number of DEM steps."""
    substeps: int | None = Field(None, ge=1)
    """DEM steps per macro step [count] (instead of macro_step; default 10)."""
    scheme: Literal["gauss-seidel", "jacobi"] = "gauss-seidel"
    integrator: Literal["velocity-verlet", "jolt-beeman"] = "velocity-verlet"
    """The DEM integrator at the fixed step dt: velocity-verlet, or the paper's jolt-beeman
    predictor-corrector (its damped modes need gamma dt <= 0.6: docs/physics.md section 2).
    With step_control = "pid" the substeps are always jolt-beeman (its error estimate)."""
    order_seed: int | None = Field(None, ge=0)
    """Permute particle indices (summation order only), for replica studies [-] (>= 0)."""
    step_control: Literal["fixed", "pid"] = "fixed"
    """The DEM step inside each macro step (settling, landing and drive): fixed at dt, or the
    paper's PID step control (jolt-beeman substeps, as many as the error tolerance needs,
    landing on the macro step's end; docs/physics.md section 2)."""
    tolerance: float = Field(1e-2, gt=0, lt=1)
    """step_control = "pid": the normalised local error per substep [-] (soil.StepController; 1e-2
    settles frictional beds with fewer evaluations than the advised fixed step, BENCHMARKS.md)."""
    dt_min: float | None = Field(None, gt=0)
    """step_control = "pid": the shortest substep [s]; default dt_max x 1e-4."""
    dt_max: float | None = Field(None, gt=0)
    """step_control = "pid": the longest substep [s]; default the advisor's stability limit
    (soil.advisor.recommended_time_step)."""

    @model_validator(mode="after")
    def _exclusive(self):
        if self.step_control == "fixed":  # a PID key under fixed steps would be ignored: say so instead
            defaults = {key: type(self).model_fields[key].default for key in ("tolerance", "dt_min", "dt_max")}
            for key, default in defaults.items():  # by value: a scene written back holds every default
                if getattr(self, key) != default:
                    raise ValueError(
                        f'{key}: only the PID step control uses it (step_control = "pid"); the scene steps at the '
                        'fixed dt: remove it, or set step_control = "pid"'
                    )
        if self.dt_min is not None and self.dt_max is not None and self.dt_min > self.dt_max:
            raise ValueError(f"dt_min: ({self.dt_min} s) must not exceed dt_max ({self.dt_max} s)")
        if self.dt is not None and self.dt_factor is not None:
            raise ValueError("dt: give dt or dt_factor, not both")
        if self.macro_step is not None and self.substeps is not None:
            raise ValueError("macro_step: give macro_step or substeps, not both")
        if self.dt is not None and self.macro_step is not None:
            ratio = self.macro_step / self.dt
            if abs(ratio - round(ratio)) > 1e-6 * max(1.0, ratio) or round(ratio) < 1:
                raise ValueError(
                    f"macro_step: ({self.macro_step} s) must be a whole multiple (>= 1) of dt "
                    f"({self.dt} s); macro_step / dt = {ratio:.6g}"
                )
        return self


class OutputSection(_Section):
    snapshot_interval: float = Field(0.25, ge=0)
    """Particle snapshots every this much simulated time [s] (0: first and last only)."""
    checkpoint_interval: float = Field(0.5, gt=0)
    """Checkpoints every this much simulated time [s]."""
    flush_every: int = Field(50, ge=1)
    """Write buffered time-series records to results.h5 every N macro steps [count]."""


class Scene(_Section):
    scene: SceneSection = SceneSection()
    soil: SoilSection = SoilSection()
    bed: BedSection = BedSection()
    wheel: WheelSection = WheelSection()
    testbed: TestbedSection | None = None
    """The single-wheel testbed (the default when there is no [rover])."""
    rover: RoverSection | None = None
    """A rover (instead of the testbed)."""
    patch: PatchSection | None = None
    """A soil patch following the rover (rovers only)."""
    terrain: TerrainSection | None = None
    """The terrain model (default: the DEM bed of [bed])."""
    landing: LandingSection = LandingSection()
    run: RunSection = RunSection()
    output: OutputSection = OutputSection()

    base_dir: str | None = Field(None, exclude=True)
    """Folder that relative paths (wheel.file, bed.bed_file, rover files) are relative to; not a scene key.
    Validation makes every path of the scene absolute against it (the working directory when None)."""

    @model_validator(mode="after")
    def _one_rover(self):
        if self.rover is not None and self.testbed is not None:
            raise ValueError("rover: a scene has either a single-wheel [testbed] or a [rover], not both")
        if self.patch is not None and self.rover is None:
            raise ValueError("patch: a moving soil patch follows a [rover]; the single-wheel testbed runs on its bed")
        if self.patch is not None and self.terrain is not None and not self.terrain.dem_wheels:
            raise ValueError(
                "patch: a moving soil patch is a window of DEM grains; terrain.model must be 'dem' (or terrain.wheels "
                "name a 'dem' wheel)"
            )
        if self.rover is None and self.testbed is None:
            object.__setattr__(self, "testbed", TestbedSection())
        return self

    @model_validator(mode="after")
    def _absolute_paths(self):
        # Every file the scene names is made absolute once, here: the plan, the run folder's scene.toml
        # and a study's workers then read the same paths wherever the scene file was.
        sections = [self.wheel, self.bed]
        if self.rover is not None:
            sections += [self.rover, *(self.rover.wheel_shape or {}).values(), *(self.rover.controllers or {}).values()]
            if not isinstance(self.rover.drive, str) and self.rover.drive is not None:
                sections.append(self.rover.drive)
        for section in sections:
            key = "bed_file" if section is self.bed else "file"
            path = getattr(section, key)
            if path:  # set without validation: the section was validated with this file already
                object.__setattr__(section, key, self.resolve(path))
        if self.terrain is not None and self.terrain.calibration:
            object.__setattr__(self.terrain, "calibration", self.resolve(self.terrain.calibration))
        return self

    def resolve(self, path: str | None) -> str | None:
        """A path of the scene made absolute (relative paths are relative to the scene file)."""
        if path is None:
            return None
        path = os.path.expanduser(path)
        if not os.path.isabs(path) and self.base_dir:
            path = os.path.join(self.base_dir, path)
        return os.path.abspath(path)

    def to_dict(self) -> dict:
        return json.loads(self.model_dump_json(exclude_none=True))

    def to_toml(self) -> str:
        return tomli_w.dumps(self.to_dict())


# ------------------------------------------------------------------------------------
# loading, overrides, error messages


_PHRASES = (
    ("Input should be greater than or equal to", "must be >="),
    ("Input should be less than or equal to", "must be <="),
    ("Input should be greater than", "must be >"),
    ("Input should be less than", "must be <"),
    ("Input should be a finite number", "must be a finite number (inf and nan are not allowed)"),
    ("Input should be a valid", "must be a valid"),
    ("Input should be", "must be"),
)


_UNION_MEMBERS = ("str", "DriveSection", "float", "list[float]", "int")
"""Type names pydantic puts into an error's location for union fields."""


def key_field(key: str, model: type[BaseModel] | None = None):
    """The pydantic FieldInfo of a dotted key (e.g. 'wheel.radius') of `model` (default Scene), None where
    the key names no field of a section."""
    current: Any = model or Scene
    *sections, name = key.split(".")
    for section in sections:
        field = current.model_fields.get(section)
        kinds = () if field is None else (field.annotation, *typing.get_args(field.annotation))
        current = next((t for t in kinds if isinstance(t, type) and issubclass(t, BaseModel)), None)
        if current is None:
            return None
    return current.model_fields.get(name)


def key_unit(key: str) -> str | None:
    """The unit of a dotted scene key (e.g. 'wheel.radius': 'm') as its documentation gives it: the first
    bracket of its docstring that names no section ('[-]': '1'), 'deg' for a '_deg' key; None where it
    gives none (a word, a flag) or the key names no field of a section."""
    field = key_field(key)
    name = key.rsplit(".", 1)[-1]
    if field is None or not {float, int} & {field.annotation, *typing.get_args(field.annotation)}:
        return None  # not a key, or not a number
    if name.endswith("_deg"):
        return "deg"
    brackets = [b for b in re.findall(r"\[([^\]]+)\]", field.description or "") if b not in Scene.model_fields]
    return None if not brackets else ("1" if brackets[0] == "-" else brackets[0])  # ([bed]: a section, not a unit)


_LAB_SECTIONS = ("lab", "repose", "shear", "plate")
"""The soil lab's sections (cosim.lab.scene.LabScene), which a run's scene does not take."""


def _format_errors(error: ValidationError) -> list[str]:
    problems = []
    for item in error.errors():
        parts = [str(p) for p in item["loc"] if not str(p).startswith("function-after")]
        if "str" in parts and isinstance(item.get("input"), dict):
            continue  # a table given where a name or a table is allowed: the table's own errors say what is wrong
        loc = ".".join(p for p in parts if p not in _UNION_MEMBERS)
        message = item["msg"]
        if message.startswith("Value error, "):
            message = message[len("Value error, ") :]
        named = re.match(r"^([a-z_]+): ", message)
        if named:
            loc = f"{loc}.{named.group(1)}" if loc else named.group(1)
            message = message[named.end() :]
        for old, new in _PHRASES:
            message = message.replace(old, new)
        if item["type"] == "extra_forbidden":
            if loc in _LAB_SECTIONS:  # a lab file given where a run's scene is read
                problems.append(f"{loc}: a soil-lab section: this is a lab file, for `cosim lab` and `cosim calibrate`")
            else:
                problems.append(f"{loc}: unknown key (not a scene setting; check the spelling)")
            continue
        got = item.get("input")
        shown = "" if isinstance(got, dict) else f" (got {_shortened(repr(got))})"
        problems.append(f"{loc or 'scene'}: {message}{shown}")
    return problems


def _shortened(text: str, most: int = 200) -> str:
    """`text`, or its start and end around '...' when longer than `most` characters (a list of millions)."""
    return text if len(text) <= most else f"{text[: most // 2]} ... {text[-most // 2 :]}"


def parse_override(text: str) -> tuple[list[str], Any]:
    """'wheel.radius=0.05' -> (['wheel', 'radius'], 0.05); the value is read as TOML, else a string."""
    if "=" not in text:
        raise SceneError([f"--set {text!r}: expected key=value, e.g. wheel.radius=0.05"])
    key, value = text.split("=", 1)
    key = key.strip()
    if not key or any(not part for part in key.split(".")):
        raise SceneError([f"--set {text!r}: bad key {key!r}"])
    return key.split("."), parse_value(value)


def parse_value(text: str) -> Any:
    """A command-line value read as TOML (numbers, booleans, strings in quotes, lists), else the bare string."""
    try:
        return tomllib.loads(f"v = {text.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        return text.strip()


def parse_list(text: str, option: str) -> list[Any]:
    """'0.1,0.2' -> [0.1, 0.2], each entry read as parse_value does; SceneError names `option` (e.g.
    '--slips') when an entry is empty ('0.1,,0.2', a trailing comma): a value lost to a typo."""
    entries = [entry.strip() for entry in text.split(",")]
    if not all(entries):
        raise SceneError([f"{option} {text!r}: an empty entry; expected comma-separated values, e.g. 0.1,0.2"])
    return [parse_value(entry) for entry in entries]


NESTED_TOO_DEEP = "tables or lists nested too deep to be a scene"
"""What a scene whose nesting runs Python out of recursion is told."""


def _plain_copy(data: dict) -> dict:
    """A copy of a scene dictionary; SceneError names a value that is no number, string, boolean, list or
    table (a TOML date or time) and nesting too deep to be a scene."""
    try:
        return json.loads(json.dumps(data))
    except RecursionError:
        raise SceneError([NESTED_TOO_DEEP]) from None
    except TypeError:
        raise SceneError(
            [
                f"{_first_date(data) or 'scene'}: a date or time; scene values are numbers, strings, booleans, lists "
                "and tables"
            ]
        ) from None


def _first_date(value, where: str = "") -> str:
    """The dotted key of the first value in `value` that JSON cannot hold ('' when none is found)."""
    if isinstance(value, dict):
        items = [(f"{where}.{k}" if where else str(k), v) for k, v in value.items()]
    elif isinstance(value, list):
        items = [(f"{where}[{i}]", v) for i, v in enumerate(value)]
    else:
        return "" if isinstance(value, (str, int, float, bool, type(None))) else where or "scene"
    return next((found for key, item in items if (found := _first_date(item, key))), "")


def apply_overrides(data: dict, overrides: list[str] | dict | None) -> dict:
    """Set dotted keys in a scene dictionary (a copy); overrides: ['a.b=1', ...] or {'a.b': 1}."""
    data = _plain_copy(data)
    if not overrides:
        return data
    items = (
        [parse_override(o) for o in overrides]
        if isinstance(overrides, (list, tuple))
        else [(k.split("."), v) for k, v in overrides.items()]
    )
    for path, value in items:
        node = data
        for part in path[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise SceneError([f"{'.'.join(path)}: {part} is not a section"])
        node[path[-1]] = value
    return data


def validate_scene(
    data: dict, base_dir: str | None = None, source: str | None = None, model: type[Scene] | None = None
) -> Scene:
    """Validate a scene dictionary as a `model` (Scene, or a subclass with more sections; default Scene);
    raises SceneError listing every problem found."""
    model = Scene if model is None else model
    try:
        return model.model_validate({**data, "base_dir": base_dir})
    except ValidationError as error:
        raise SceneError(_format_errors(error), source) from None


def load_scene(
    path: str | os.PathLike, overrides: list[str] | dict | None = None, model: type[Scene] | None = None
) -> Scene:
    """Read, override (--set key=value) and validate a TOML scene file (as `model`: see validate_scene)."""
    path = os.fspath(path)
    if os.path.isdir(path):
        raise SceneError([f"{path!r} is a folder; give a scene file (TOML)"])
    if not os.path.isfile(path):
        raise SceneError([f"scene file not found: {path!r}"])
    try:
        with open(path, "rb") as f:
            # utf-8-sig: a byte-order mark (some Windows editors write one) is no TOML statement
            data = tomllib.loads(f.read().decode("utf-8-sig"))
    except tomllib.TOMLDecodeError as error:
        raise SceneError([f"not valid TOML: {error}"], path) from None
    except RecursionError:
        raise SceneError([NESTED_TOO_DEEP], path) from None
    except (OSError, UnicodeDecodeError) as error:
        raise SceneError([f"cannot read the scene file: {error}"], path) from None
    if not data and not overrides:  # a file cut to nothing (an editor's crash) would run every default silently
        raise SceneError(
            ["the file holds no keys (empty or only comments); a scene sets its keys, e.g. [scene] name"], path
        )
    try:
        data = apply_overrides(data, overrides)
    except SceneError as error:
        raise SceneError(error.problems, error.source or path) from None
    return validate_scene(data, base_dir=os.path.dirname(os.path.abspath(path)), source=path, model=model)


def scene_from_text(text: str, base_dir: str | None = None, overrides=None, model: type[Scene] | None = None) -> Scene:
    """Validate a scene given as TOML text (as `model`: see validate_scene)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise SceneError([f"not valid TOML: {error}"]) from None
    except RecursionError:
        raise SceneError([NESTED_TOO_DEEP]) from None
    return validate_scene(apply_overrides(data, overrides), base_dir=base_dir, model=model)
