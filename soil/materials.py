"""Contact materials and their pairing rules (docs/physics.md section 1)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import TypeGuard

import numpy as np

from .errors import SoilInputError, is_real


def restitution_of_damping_ratio(damping_ratio: float) -> float:
    """Coefficient of restitution of a Hertz contact with Lehr damping.

    The damping coefficient is c = 2 D sqrt(m* k) with the tangent stiffness
    k = dF/d(delta) = 2 E* sqrt(R* delta). In the dimensionless overlap y the impact obeys
    y'' = -y^1.5 - 2 sqrt(1.5) D y^0.25 y', y(0) = 0, y'(0) = 1, so e depends on D only:
    it is independent of the impact speed. The normal force is never tensile, so once it
    would turn negative the grain flies free until the overlap closes.

    damping_ratio: a finite number >= 0 (0: no damping, e = 1).
    """
    # checked before the cache, whose key would refuse an array with a bare TypeError; negative: a contact
    # that adds energy has no restitution below 1; inf: the ODE's force is nan (it gave 0 with warnings)
    if not (is_real(damping_ratio) and math.isfinite(damping_ratio) and damping_ratio >= 0.0):
        raise SoilInputError(
            f"damping_ratio must be >= 0, got {damping_ratio!r}: a finite number [-] (0: no damping, restitution 1)"
        )
    return _restitution_of_damping_ratio(damping_ratio)


@lru_cache(maxsize=256)
def _restitution_of_damping_ratio(damping_ratio: float) -> float:
    """restitution_of_damping_ratio of a checked damping ratio (cached: the ODE solve is slow)."""
    from scipy.integrate import solve_ivp

    if damping_ratio == 0.0:
        return 1.0
    beta = 2.0 * math.sqrt(1.5) * damping_ratio

    def rhs(_, s):
        y, v = s
        y = max(y, 0.0)
        force = y**1.5 + beta * y**0.25 * v
        return [v, -max(force, 0.0)]

    def closed(_, s):
        return s[0]

    # solve_ivp reads an event's settings off the function's attributes
    closed.terminal = True  # type: ignore[attr-defined]
    closed.direction = -1  # type: ignore[attr-defined]
    sol = solve_ivp(rhs, (0.0, 100.0), [1e-12, 1.0], events=closed, rtol=1e-10, atol=1e-13, max_step=0.01)
    return float(-sol.y_events[0][0][1]) if sol.t_events[0].size else 0.0


def damping_ratio_for_restitution(restitution: float) -> float:
    """Lehr damping ratio D that gives a Hertz contact the coefficient of restitution e (a number in (0, 1])."""
    # checked before the cache, whose key would refuse an array with a bare TypeError
    if not (is_real(restitution) and 0.0 < restitution <= 1.0):
        raise SoilInputError(f"restitution must be a number in (0, 1] [-], got {restitution!r}")
    return _damping_ratio_for_restitution(restitution)


@lru_cache(maxsize=256)
def _damping_ratio_for_restitution(restitution: float) -> float:
    """damping_ratio_for_restitution of a checked restitution (cached: each try solves an ODE)."""
    from scipy.optimize import brentq

    if restitution == 1.0:
        return 0.0
    high = 0.5
    while restitution_of_damping_ratio(high) > restitution:
        high *= 2.0
        if high > 1e3:
            raise SoilInputError(f"restitution {restitution} is too small to reach with Lehr damping")
    return float(brentq(lambda d: restitution_of_damping_ratio(d) - restitution, 0.0, high, xtol=1e-10))


MATERIAL_UNITS = {
    "youngs_modulus": "Pa",
    "poisson_ratio": "1",
    "density": "kg/m^3",
    "restitution": "1",
    "damping_ratio": "1",
    "stick_angle": "rad",
    "slip_angle": "rad",
    "stick_speed": "m/s",
    "rolling_friction": "1",
    "cohesion": "Pa",
}
"""The unit of each Material field (what a bed file's material table writes beside it)."""


@dataclass(frozen=True)
class Material:
    """A contact material. Angles in radians, all other quantities SI."""

    youngs_modulus: float = 1.0e8
    """Young's modulus [Pa]: a macroscopic stiffness for soils (paper eq. 10), not the grain's."""
    poisson_ratio: float = 0.3
    """Poisson's ratio [-], in (-1, 0.5)."""
    density: float = 2600.0
    """Grain density [kg/m^3] (boundaries ignore it)."""
    restitution: float | None = 0.5
    """Target normal coefficient of restitution [-] in (0, 1]; sets the Lehr damping ratio."""
    damping_ratio: float | None = None
    """Lehr damping ratio D [-], given directly; overrides `restitution` when set."""
    stick_angle: float = math.radians(30.0)
    """Stick friction angle phi_h [rad]: the Kelvin element sticks while |F_T| <= |F_N| tan(phi_h)."""
    slip_angle: float = math.radians(25.0)
    """Slip friction angle phi_g [rad]: sliding friction |F_T| = |F_N| tan(phi_g)."""
    stick_speed: float = 1.0e-3
    """Stick speed v_Tmin [m/s]: above this tangential speed a contact slips."""
    rolling_friction: float = 0.0
    """Rolling resistance coefficient mu_r [-]: the rolling torque is capped at mu_r R* |F_N|."""
    cohesion: float = 0.0
    """Cohesion energy density [Pa]: attractive force cohesion * pi R* delta (0 = off)."""

    def __post_init__(self):
        def check(name, ok, allowed):
            if not ok:
                raise SoilInputError(f"material.{name} must be a finite number {allowed}, got {getattr(self, name)!r}")

        check("youngs_modulus", _finite(self.youngs_modulus) and self.youngs_modulus > 0, "> 0 [Pa]")
        check("poisson_ratio", _finite(self.poisson_ratio) and -1.0 < self.poisson_ratio < 0.5, "in (-1, 0.5)")
        check("density", _finite(self.density) and self.density > 0, "> 0 [kg/m^3]")
        if self.damping_ratio is None:
            check("restitution", _finite(self.restitution) and 0.0 < self.restitution <= 1.0, "in (0, 1]")
        else:
            check("damping_ratio", _finite(self.damping_ratio) and self.damping_ratio >= 0, ">= 0")
        check("stick_angle", _finite(self.stick_angle) and 0.0 <= self.stick_angle < math.pi / 2, "in [0, pi/2) [rad]")
        check(
            "slip_angle",
            _finite(self.slip_angle) and 0.0 <= self.slip_angle <= self.stick_angle,
            "in [0, stick_angle] [rad] (sliding friction cannot exceed sticking friction)",
        )
        check("stick_speed", _finite(self.stick_speed) and self.stick_speed > 0, "> 0 [m/s]")
        check("rolling_friction", _finite(self.rolling_friction) and self.rolling_friction >= 0, ">= 0")
        check("cohesion", _finite(self.cohesion) and self.cohesion >= 0, ">= 0 [Pa]")

    @property
    def lehr_damping(self) -> float:
        """The Lehr damping ratio D [-] this material uses."""
        if self.damping_ratio is not None:
            return float(self.damping_ratio)
        assert self.restitution is not None  # __post_init__ requires one of the two
        return damping_ratio_for_restitution(float(self.restitution))

    @property
    def shear_modulus(self) -> float:
        """G = E / (2 (1 + nu)) [Pa]."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))

    def with_(self, **changes) -> Material:
        return replace(self, **changes)


STICK_SPEED_RATIO = 0.02
"""The default stick speed as a fraction of sqrt(|g| d) [-] (docs/physics.md section 1.3)."""


def stick_speed_for(gravity: float, grain_diameter: float) -> float:
    """The default stick speed v_Tmin = STICK_SPEED_RATIO sqrt(|g| d) [m/s] for gravity |g| [m/s^2]
    and mean grain diameter d [m]: the same fraction of the grains' speed scale at any gravity, so
    the gravity twin (speeds x sqrt(s)) keeps it."""
    if not (math.isfinite(gravity) and gravity > 0 and math.isfinite(grain_diameter) and grain_diameter > 0):
        raise SoilInputError(
            f"the default stick speed needs gravity > 0 and a grain diameter > 0 (got {gravity!r} m/s^2, "
            f"{grain_diameter!r} m): give the stick speed"
        )
    return STICK_SPEED_RATIO * math.sqrt(gravity * grain_diameter)


def _finite(x) -> TypeGuard[float]:
    # a real number first: math.isfinite raises a bare TypeError on a text or a complex, and takes True as 1
    return is_real(x) and math.isfinite(x)


# Columns of the pair-parameter table shared by the kernels.
(
    PAIR_E_STAR,
    PAIR_G_STAR,
    PAIR_DAMPING,
    PAIR_TAN_STICK,
    PAIR_TAN_SLIP,
    PAIR_STICK_SPEED,
    PAIR_ROLLING,
    PAIR_COHESION,
) = range(8)
PAIR_SHEAR_ROOT = 8
"""sqrt(k_T / k_N) = sqrt(4 G* / E*) [-]: the tangential damper is this times the normal one."""
PAIR_COLUMNS = 9
"""Columns of a pair row: PairProperties.row()'s eight (units as there) and PAIR_SHEAR_ROOT."""


@dataclass(frozen=True)
class PairProperties:
    """Contact parameters of one material pair."""

    effective_modulus: float  # E* [Pa]
    effective_shear_modulus: float  # G* [Pa]
    damping_ratio: float  # Lehr D [-]
    tan_stick: float  # tan(phi_h) [-]
    tan_slip: float  # tan(phi_g) [-]
    stick_speed: float  # v_Tmin [m/s]
    rolling_friction: float  # mu_r [-]
    cohesion: float  # [Pa]

    def row(self) -> list[float]:
        return [
            self.effective_modulus,
            self.effective_shear_modulus,
            self.damping_ratio,
            self.tan_stick,
            self.tan_slip,
            self.stick_speed,
            self.rolling_friction,
            self.cohesion,
        ]


def pair_properties(a: Material, b: Material) -> PairProperties:
    """Mix two materials: Hertz/Mindlin effective moduli; the weaker friction governs;
    mean damping and rolling resistance; the smaller cohesion and stick speed."""
    e_star = 1.0 / ((1 - a.poisson_ratio**2) / a.youngs_modulus + (1 - b.poisson_ratio**2) / b.youngs_modulus)
    g_star = 1.0 / ((2 - a.poisson_ratio) / a.shear_modulus + (2 - b.poisson_ratio) / b.shear_modulus)
    return PairProperties(
        effective_modulus=e_star,
        effective_shear_modulus=g_star,
        damping_ratio=0.5 * (a.lehr_damping + b.lehr_damping),
        tan_stick=min(math.tan(a.stick_angle), math.tan(b.stick_angle)),
        tan_slip=min(math.tan(a.slip_angle), math.tan(b.slip_angle)),
        stick_speed=min(a.stick_speed, b.stick_speed),
        rolling_friction=0.5 * (a.rolling_friction + b.rolling_friction),
        cohesion=min(a.cohesion, b.cohesion),
    )


@dataclass
class MaterialTable:
    """Materials by index, with optional per-pair overrides."""

    materials: list[Material] = field(default_factory=list)
    overrides: dict[tuple[int, int], dict] = field(default_factory=dict)

    def add(self, material: Material) -> int:
        if not isinstance(material, Material):
            raise SoilInputError(f"material must be a soil.Material, got {type(material).__name__}: {material!r}")
        for index, known in enumerate(self.materials):
            if known == material:
                return index
        self.materials.append(material)
        return len(self.materials) - 1

    def set_pair(self, i: int, j: int, **fields) -> None:
        """Override pair properties (PairProperties field names) for materials i and j."""
        allowed = set(PairProperties.__dataclass_fields__)
        for name in fields:
            if name not in allowed:
                raise SoilInputError(f"pair property {name!r} is unknown; allowed: {sorted(allowed)}")
        self.overrides[(min(i, j), max(i, j))] = dict(fields)

    def pair_table(self) -> np.ndarray:
        """Pair parameters, shape (material_count**2, PAIR_COLUMNS), row i * count + j."""
        count = len(self.materials)
        table = np.zeros((count * count, PAIR_COLUMNS), dtype=np.float64)
        for i in range(count):
            for j in range(count):
                props = pair_properties(self.materials[i], self.materials[j])
                extra = self.overrides.get((min(i, j), max(i, j)))
                if extra:
                    props = replace(props, **extra)
                table[i * count + j, :PAIR_SHEAR_ROOT] = props.row()
                table[i * count + j, PAIR_SHEAR_ROOT] = math.sqrt(
                    4.0 * props.effective_shear_modulus / props.effective_modulus
                )
        return table
