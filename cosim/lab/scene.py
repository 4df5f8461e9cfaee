"""The lab's scene: a wheel scene's soil sections plus one section per lab test, validated.

A lab scene is any scene file (cosim.scene: [scene], [soil], [bed], [run], ...) with
optional lab sections; every key has a default, so `cosim lab repose SCENE` measures the
soil of a wheel scene as it stands. The lab reads

    [scene]   gravity (along -Z, > 0 for the repose and plate tests), precision, device, name
    [soil]    the grain material and contact-law switches (what the lab measures)
    [bed]     radius_mean, radius_spread, seed (the grains); the plate test's bed (length, width,
              depth, settle_ke_ratio, settle_max_time, settle_dt_factor, bed_file)
    [run]     dt or dt_factor (the DEM step, as for a wheel run)
    [lab]     replicas, rest_ke_ratio, max_time_factor
    [repose]  the heap (cosim.lab.repose)
    [shear]   the direct shear box (cosim.lab.shear)
    [plate]   the pressure-sinkage plate (cosim.lab.plate)

and ignores the wheel's sections. Lengths left out default to multiples of the mean grain
diameter d; speeds left out follow from a dimensionless number (docs/lab.md), so the same
scene runs quasi-statically at any gravity. Every number must be finite and in range and
unknown keys are errors, as in cosim.scene; `resolve_lab` makes the checks that need
several sections and raises SceneError naming the key to change.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import ConfigDict, Field, model_validator

from soil import ContactLaw, Material, gravity_vector
from soil.bed import radius_range
from soil.builder import grain_range_problem

from ..plan import MAX_PHASE_STEPS, RAYLEIGH_KEYS, default_stick_speed, dem_time_step, to_material
from ..probe import resolve_device
from ..scene import (
    INT64_MAX,
    NumbersChecked,
    Scene,
    SceneError,
    apply_overrides,
    load_scene,
    scene_from_text,
    validate_scene,
)

PACKING_FRACTION = 0.6
"""Solid fraction assumed when a fill height is turned into a grain count [-] (random packing of spheres)."""


class _LabSection(NumbersChecked):
    # as cosim.scene: no inf / nan, no number out of its range, no boolean for a number, unknown keys refused
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


def _exclusive(section, absolute: str, relative: str):
    if getattr(section, absolute) is not None and getattr(section, relative) is not None:
        raise ValueError(f"{absolute}: give {absolute} or {relative}, not both")
    return section


class LabSection(_LabSection):
    """What all lab tests share."""

    replicas: int = Field(1, ge=1, le=1000)
    """Specimens per test [-]: replica k is filled with seed bed.seed + k and permuted with order_seed k."""
    rest_ke_ratio: float = Field(1e-4, gt=0)
    """A heap is at rest when its grains' translational kinetic energy < ratio * N m |g| r (gravity-scaled) [-]."""
    max_time_factor: float = Field(400.0, gt=0)
    """Longest phase (settling, lifting, resting) in units of sqrt(d / |g|) [-]; a phase cut short is reported."""


class ReposeSection(_LabSection):
    """Angle of repose: a square tube of grains lifted off a rough base (cosim.lab.repose)."""

    tube_width: float | None = Field(None, gt=0)
    """Inner width of the square tube [m]; default 10 mean grain diameters."""
    fill_height: float | None = Field(None, gt=0)
    """Height of the settled column in the tube [m]; default 1.5 tube widths."""
    lift_speed: float | None = Field(None, gt=0)
    """Speed the tube is lifted at [m/s]; or lift_ratio."""
    lift_ratio: float | None = Field(None, gt=0)
    """Lift speed over sqrt(|g| d) [-] (default 0.1): small keeps the heap quasi-static."""
    base: Literal["grains", "plane"] = "grains"
    """'grains': a layer of fixed grains (a rough floor); 'plane': the flat floor (a sphere without rolling
    friction rolls away on it)."""
    base_width: float | None = Field(None, gt=0)
    """Side of the square base [m]; default: the footprint of the heap at 10 degrees plus 3 d."""
    wall_friction_deg: float = Field(0.0, ge=0, lt=90)
    """Friction angle of the tube and side walls [deg] (0: smooth)."""
    sectors: int = Field(16, ge=4, le=72)
    """Angular sectors of the surface profile [-]."""
    fit_range: list[float] = Field(default_factory=lambda: [0.1, 0.9])
    """Part of the heap's flank the line is fitted to, as fractions of its height above the toe [-]."""

    @model_validator(mode="after")
    def _checks(self):
        _exclusive(self, "lift_speed", "lift_ratio")
        low, high = (self.fit_range + [math.nan, math.nan])[:2]
        if len(self.fit_range) != 2 or not 0 <= low < high <= 1:
            raise ValueError(f"fit_range: must be [low, high] with 0 <= low < high <= 1 (got {self.fit_range})")
        return self


class ShearSection(_LabSection):
    """Direct shear box (cosim.lab.shear)."""

    length: float | None = Field(None, gt=0)
    """Inner length of the box along the shear direction X [m]; default 12 d."""
    width: float | None = Field(None, gt=0)
    """Inner width of the box [m]; default 12 d."""
    height: float | None = Field(None, gt=0)
    """Height of the settled sample [m], split in two halves by the shear plane; default 8 d."""
    normal_stresses: list[float] | None = None
    """Normal stresses of the tests [Pa], each > 0; default Young's modulus x (2.5e-4, 5e-4, 1e-3)."""
    speed: float | None = Field(None, gt=0)
    """Shear speed of the upper half [m/s]; or inertial_number."""
    inertial_number: float | None = Field(None, gt=0)
    """I = gamma_dot d / sqrt(sigma / rho) at the lowest normal stress (default 1e-3), gamma_dot = speed /
    (10 d), the usual shear-band width [-]."""
    displacement: float | None = Field(None, gt=0)
    """Shear displacement [m]; default 0.2 x length."""
    gap: float | None = Field(None, gt=0)
    """Gap between the two halves of the box [m]; default 1.5 smallest grain radii: as wide as it can be
    without letting a grain out, so the frames' edges plough few grains."""
    wall_friction_deg: float = Field(0.0, ge=0, lt=90)
    """Friction angle of the box walls [deg] (0: smooth; the lid and floor are rough: the soil's own)."""

    @model_validator(mode="after")
    def _checks(self):
        _exclusive(self, "speed", "inertial_number")
        if self.normal_stresses is not None:
            if not self.normal_stresses or not all(math.isfinite(s) and s > 0 for s in self.normal_stresses):
                raise ValueError(
                    f"normal_stresses: must be a non-empty list of finite stresses > 0 [Pa] "
                    f"(got {self.normal_stresses})"
                )
            if len(set(self.normal_stresses)) != len(self.normal_stresses):  # the same test twice, one point
                raise ValueError(f"normal_stresses: each stress once (got {self.normal_stresses})")
        return self


class PlateSection(_LabSection):
    """Pressure-sinkage: square plates pushed into the bed at a constant speed (cosim.lab.plate)."""

    widths: list[float] | None = None
    """Plate sides b [m], each > 0; two or more separate Bekker's k_c and k_phi; default 0.25 and 0.4 x the
    smaller bed side."""
    speed: float | None = Field(None, gt=0)
    """Sinking speed [m/s]; or speed_ratio."""
    speed_ratio: float | None = Field(None, gt=0)
    """Sinking speed over sqrt(|g| d) [-] (default 0.05)."""
    max_sinkage: float | None = Field(None, gt=0)
    """Deepest sinkage [m]; default 0.4 x the settled bed depth."""
    friction_deg: float | None = Field(None, ge=0, lt=90)
    """Friction angle of the plate [deg]; default: the soil's stick angle (a rough plate)."""
    wall_friction_deg: float = Field(0.0, ge=0, lt=90)
    """Friction angle of the bed's walls [deg] when the bed is settled here (0: smooth)."""
    fit_from: float | None = Field(None, ge=0)
    """Smallest sinkage in the Bekker fit [m]; default a quarter grain diameter (the first contacts)."""

    @model_validator(mode="after")
    def _checks(self):
        _exclusive(self, "speed", "speed_ratio")
        if self.widths is not None:
            if not self.widths or not all(math.isfinite(b) and b > 0 for b in self.widths):
                raise ValueError(f"widths: must be a non-empty list of finite widths > 0 [m] (got {self.widths})")
            if len(set(self.widths)) != len(self.widths):
                raise ValueError(f"widths: each width once (got {self.widths})")
        return self


class LabScene(Scene):
    """A scene with the lab's sections (every one optional)."""

    lab: LabSection = LabSection()
    repose: ReposeSection = ReposeSection()
    shear: ShearSection = ShearSection()
    plate: PlateSection = PlateSection()


def validate_lab_scene(data: dict, base_dir: str | None = None, source: str | None = None) -> LabScene:
    """Validate a lab scene dictionary; SceneError lists every problem found."""
    return _lab(validate_scene(data, base_dir, source, model=LabScene))


def load_lab_scene(path, overrides=None) -> LabScene:
    """Read, override (['a.b=1', ...] or {'a.b': 1}) and validate a lab scene file."""
    return _lab(load_scene(path, overrides, model=LabScene))


def lab_scene_from_text(text: str, base_dir: str | None = None, overrides=None) -> LabScene:
    """Validate a lab scene given as TOML text (what lab tasks carry to their workers)."""
    return _lab(scene_from_text(text, base_dir, overrides, model=LabScene))


def _lab(scene: Scene) -> LabScene:
    assert isinstance(scene, LabScene)  # validated as one
    return scene


# ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LabPlan:
    """What every lab test needs, resolved once from a LabScene."""

    scene: LabScene
    name: str
    device: str
    precision: str
    gravity: tuple[float, float, float]
    """Gravity vector [m/s^2] (along -Z)."""
    law: ContactLaw
    soil: Material
    """The grain material under test."""
    radius_mean: float
    """Mean grain radius [m]."""
    radius_spread: float
    """Relative half-width of the uniform radius distribution [-]."""
    seed: int
    """Fill seed of replica 0 [-]."""
    dt: float
    """DEM step [s]."""

    @property
    def g(self) -> float:
        """|g| [m/s^2]."""
        return float(np.linalg.norm(self.gravity))

    @property
    def radius_min(self) -> float:
        """Smallest grain radius [m]: radius_mean (1 - radius_spread) (soil.bed.radius_range)."""
        return radius_range(self.radius_mean, self.radius_spread)[0]

    @property
    def radius_max(self) -> float:
        """Largest grain radius [m]: radius_mean (1 + radius_spread) (soil.bed.radius_range)."""
        return radius_range(self.radius_mean, self.radius_spread)[1]

    @property
    def diameter(self) -> float:
        """Mean grain diameter d [m]."""
        return 2.0 * self.radius_mean

    @property
    def time_scale(self) -> float:
        """sqrt(d / |g|) [s] (inf without gravity)."""
        return math.sqrt(self.diameter / self.g) if self.g > 0 else math.inf

    def max_phase_time(self, fallback: float) -> float:
        """Longest phase [s]: lab.max_time_factor sqrt(d / |g|) (`fallback` [s] without gravity)."""
        scale = self.time_scale if self.g > 0 else fallback
        return self.scene.lab.max_time_factor * scale

    def wall_material(self, friction_deg: float) -> Material:
        """The soil with its friction angles capped at `friction_deg` [deg] and no cohesion: a wall
        (the weaker friction of a pair governs, so a wall never grips harder than the soil)."""
        angle = math.radians(friction_deg)
        return self.soil.with_(
            stick_angle=min(angle, self.soil.stick_angle), slip_angle=min(angle, self.soil.slip_angle), cohesion=0.0
        )

    def with_changes(self, overrides: dict) -> LabPlan:
        """The plan of the same scene with {'a.b': value} applied."""
        data = apply_overrides(self.scene.to_dict(), overrides)
        return resolve_lab(validate_lab_scene(data, self.scene.base_dir))


def resolve_lab(scene: LabScene, needs_gravity: bool = False, test: str = "lab") -> LabPlan:
    """The lab plan of a scene; SceneError names every problem (gravity along -Z, > 0 when
    `needs_gravity`; a device that exists)."""
    problems = []
    gravity = gravity_vector(scene.scene.gravity)
    g = float(np.linalg.norm(gravity))
    if g > 0 and not np.allclose(gravity[:2], 0.0, atol=1e-12 * g):
        problems.append(f"scene.gravity: the lab tests need gravity along -Z (got {list(gravity)} m/s^2)")
    elif gravity[2] > 0:
        problems.append(f"scene.gravity: must point down (-Z) (got {list(gravity)} m/s^2)")
    if needs_gravity and g == 0:
        problems.append(f"scene.gravity: the {test} test needs gravity (got 0): grains must settle")
    soil = to_material(scene.soil, default_stick_speed=default_stick_speed(scene))
    device = resolve_device(scene.scene.device)
    law_section = scene.soil.law
    law = ContactLaw(
        damping=law_section.damping,
        friction=law_section.friction,
        rolling=law_section.rolling if law_section.rolling is not None else soil.rolling_friction > 0,
        cohesion=law_section.cohesion if law_section.cohesion is not None else soil.cohesion > 0,
        twisting=law_section.twisting,
    )
    bed = scene.bed
    dt, dt_key = dem_time_step(scene, soil)
    longest = scene.lab.max_time_factor * math.sqrt(2.0 * bed.radius_mean / g) if g > 0 else 0.0
    if longest / dt > MAX_PHASE_STEPS:  # a step far below the scene's scale: a test that never ends
        step = f"run.dt_factor x {RAYLEIGH_KEYS}"
        problems.append(
            f"{dt_key}: a phase of up to {longest:.3g} s (lab.max_time_factor sqrt(d / |g|)) is {longest / dt:.3g} "
            f"DEM steps of {dt:.3g} s, more than {MAX_PHASE_STEPS:.0e} (a day even at 10 us a step): the step "
            f"{'(' + step + ') ' if dt_key == 'run.dt_factor' else ''}is far below the scene's scale"
        )
    grains = grain_range_problem(bed.radius_min, soil.density, scene.scene.precision)
    if grains:
        problems.append(f"bed.radius_mean: {grains}")
    if bed.seed + scene.lab.replicas - 1 > INT64_MAX:
        problems.append(
            f"bed.seed: replica k is filled with bed.seed + k, and {bed.seed} + {scene.lab.replicas - 1} (lab.replicas "
            f"- 1) passes the largest seed (2^63 - 1); allowed: bed.seed <= {INT64_MAX - scene.lab.replicas + 1}"
        )
    if problems:
        raise SceneError(problems)
    return LabPlan(
        scene=scene,
        name=scene.scene.name,
        device=device,
        precision=scene.scene.precision,
        gravity=(float(gravity[0]), float(gravity[1]), float(gravity[2])),
        law=law,
        soil=soil,
        radius_mean=bed.radius_mean,
        radius_spread=bed.radius_spread,
        seed=bed.seed,
        dt=dt,
    )


def load_lab_plan(path, overrides=None, needs_gravity: bool = False, test: str = "lab") -> LabPlan:
    """Read, validate and resolve a lab scene file."""
    scene = load_lab_scene(path, overrides)
    try:
        return resolve_lab(scene, needs_gravity, test)
    except SceneError as error:
        raise SceneError(error.problems, os.fspath(path)) from None
