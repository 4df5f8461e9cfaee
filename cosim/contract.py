"""The soil <-> rover coupling contract (docs/coupling.md, "The contract").

Per wheel, world frame, Z up, SI units. The rover side hands the soil side the hub
kinematics of every wheel; the soil side answers with the wrench on every wheel.
Both sides implement a small protocol so that any soil (DEM, analytic test terrain,
an FMU) can be coupled to any rover (MuJoCo, FMU).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np


def _vec(value, size: int, name: str) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64).reshape(-1)
    if array.shape != (size,) or not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be {size} finite numbers, got {value!r}")
    return array


@dataclass
class WheelKinematics:
    """Hub kinematics of one wheel at one instant (rover -> soil)."""

    position: np.ndarray
    """Hub position in the world frame [m], shape (3,)."""
    orientation: np.ndarray
    """Unit quaternion (w, x, y, z), body -> world [-], shape (4,)."""
    linear_velocity: np.ndarray
    """Velocity of the hub point in the world frame [m/s], shape (3,)."""
    angular_velocity: np.ndarray
    """Angular velocity in the world frame [rad/s], shape (3,)."""

    def __post_init__(self):
        self.position = _vec(self.position, 3, "position")
        self.orientation = _vec(self.orientation, 4, "orientation")
        norm = np.linalg.norm(self.orientation)
        if not 0.5 < norm < 2.0:
            raise ValueError(f"orientation must be a unit quaternion (w, x, y, z), got {self.orientation}")
        self.orientation = self.orientation / norm
        self.linear_velocity = _vec(self.linear_velocity, 3, "linear_velocity")
        self.angular_velocity = _vec(self.angular_velocity, 3, "angular_velocity")


@dataclass
class WheelWrench:
    """Soil wrench on one wheel over one macro step (soil -> rover)."""

    force: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Macro-step average force on the wheel, world frame [N], shape (3,)."""
    torque: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Macro-step average torque about the hub, world frame [N m], shape (3,)."""
    force_end: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Force at the end of the macro step, world frame [N], shape (3,)."""
    torque_end: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Torque about the hub at the end of the macro step, world frame [N m], shape (3,)."""
    contact_count: int = 0
    """Number of soil contacts on the wheel at the end of the step [-]."""
    sinkage: float = 0.0
    """Depth of the wheel's lowest point below the undisturbed soil surface [m]."""
    work_on_soil: float = 0.0
    """Work done by the wheel on the soil during the macro step [J]."""


@runtime_checkable
class SoilSide(Protocol):
    """Anything that answers wheel kinematics with wheel wrenches."""

    wheel_count: int

    @property
    def time(self) -> float:
        """The soil's time [s] (read only: `advance` moves it)."""

    def set_gravity(self, gravity: Sequence[float]) -> None:
        """Set the scene's gravity vector [m/s^2], shape (3,)."""

    def advance(
        self,
        t_end: float,
        start: Sequence[WheelKinematics],
        end: Sequence[WheelKinematics] | None = None,
    ) -> list[WheelWrench]:
        """Advance the soil to t_end [s].

        The wheels move from `start` (kinematics at self.time) to `end` (kinematics at
        t_end) by interpolation; with `end` None the motion is extrapolated from `start`
        at constant velocity. Returns one WheelWrench per wheel.
        """


@runtime_checkable
class RoverSide(Protocol):
    """A multibody rover model that carries wheels."""

    wheel_names: list[str]

    @property
    def time(self) -> float:
        """The rover's time [s] (read only: `advance` moves it)."""

    def set_gravity(self, gravity: Sequence[float]) -> None:
        """Set the scene's gravity vector [m/s^2], shape (3,)."""

    def wheel_kinematics(self) -> list[WheelKinematics]:
        """Current hub kinematics of every wheel, in wheel_names order."""

    def apply_wheel_wrenches(self, wrenches: Sequence[WheelWrench]) -> None:
        """Hold these wrenches (their `force`/`torque`) on the wheels until replaced."""

    def advance(self, t_end: float) -> None:
        """Advance the rover to t_end [s]."""
