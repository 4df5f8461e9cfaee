"""Drive controllers for the coupler's controller hook.

A controller is any callable

    controller(t, wheel_states, wrenches) -> DriveCommand

called by the Coupler at the start of every macro step with the time t [s], the wheels'
current kinematics (list of WheelKinematics) and the wrenches of the previous macro step
(list of WheelWrench). The command is held by the rover over the macro step.

A controller with internal state also has `state_dict()` / `load_state_dict(state)` (numpy
arrays and scalars) so that a run continued from a checkpoint gives the same commands; one
without them is taken to be stateless.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from soil.errors import ArgumentError

from .contract import WheelKinematics, WheelWrench, wheel_frame


@dataclass
class DriveCommand:
    """Per-wheel drive command held over one macro step."""

    mode: str
    """'speed' (wheel hinge rate [rad/s]) or 'torque' (wheel hinge torque [N m])."""
    values: np.ndarray
    """The speeds [rad/s] or torques [N m], shape (wheel_count,)."""

    def __post_init__(self):
        if self.mode not in ("speed", "torque"):
            raise ArgumentError(f"DriveCommand mode must be 'speed' or 'torque', got {self.mode!r}")
        values = np.asarray(self.values, dtype=np.float64)
        if values.ndim > 1:  # a matrix is no list of wheels, even when its size is the wheel count
            raise ArgumentError(f"DriveCommand values must be one per wheel, shape (wheel_count,), got {values.shape}")
        self.values = values.reshape(-1)


@runtime_checkable
class Controller(Protocol):
    def __call__(
        self, t: float, wheel_states: Sequence[WheelKinematics], wrenches: Sequence[WheelWrench]
    ) -> DriveCommand: ...


def apply_command(rover, command: DriveCommand) -> None:
    """Send a DriveCommand to a rover (needs set_wheel_speeds / set_wheel_torques)."""
    if not isinstance(command, DriveCommand):  # a controller's wrong return, named rather than an AttributeError
        raise ArgumentError(
            f"a drive controller must return a DriveCommand, got {type(command).__name__}: {command!r:.80}"
        )
    method = "set_wheel_speeds" if command.mode == "speed" else "set_wheel_torques"
    if not hasattr(rover, method):
        raise TypeError(f"{type(rover).__name__} has no {method}(); it cannot take {command.mode} commands")
    getattr(rover, method)(command.values)


def _per_wheel(name: str, values, wheel_count: int, unit: str) -> np.ndarray:
    """`values` (one finite number, or one per wheel) as an array of shape (wheel_count,); ArgumentError
    naming `name` otherwise."""
    try:
        array = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):  # text, ragged lists: not numbers
        array = np.full(2, np.nan)
    if array.ndim > 1 or (array.ndim == 1 and len(array) != wheel_count) or not np.all(np.isfinite(array)):
        raise ArgumentError(
            f"{name} must be one finite number [{unit}] or one per wheel ({wheel_count}), got {values!r}"
        )
    return np.broadcast_to(array, (wheel_count,)).copy()


class ConstantSpeed:
    """Every wheel at a constant hinge rate [rad/s] (one value or one per wheel)."""

    def __init__(self, speed: float | Sequence[float], wheel_count: int):
        self.speed = _per_wheel("speed", speed, wheel_count, "rad/s")
        """Wheel speeds [rad/s], shape (wheel_count,)."""

    def __call__(self, t, wheel_states, wrenches) -> DriveCommand:
        return DriveCommand("speed", self.speed)

    def state_dict(self) -> dict:
        return {}

    def state_dict_units(self) -> dict[str, str]:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


class ConstantTorque:
    """Every wheel at a constant hinge torque [N m] (one value or one per wheel)."""

    def __init__(self, torque: float | Sequence[float], wheel_count: int):
        self.torque = _per_wheel("torque", torque, wheel_count, "N m")
        """Wheel torques [N m], shape (wheel_count,)."""

    def __call__(self, t, wheel_states, wrenches) -> DriveCommand:
        return DriveCommand("torque", self.torque)

    def state_dict(self) -> dict:
        return {}

    def state_dict_units(self) -> dict[str, str]:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


class SlipController:
    """Traction control: hold the driving slip s = 1 - v / (omega r) at a target.

    Per wheel, v is the measured hub velocity along the wheel's rolling direction and
    omega its measured spin about its axis. At the target slip the hub should move at
    v* = (1 - s*) omega r; the velocity error e = v - v* drives a PI loop on top of the
    feed-forward speed v / ((1 - s*) r):

        omega_cmd = [v + kp e + ki integral(e dt)] / ((1 - s*) r),  clamped to [omega_min, omega_max].

    The feed-forward alone gives the target slip for a perfect motor; the PI removes the
    lag of a real (velocity-actuator) motor under load. omega_min starts a rover at rest
    (there, v = 0 and any spin is slip 1). The integral is frozen while the command is
    clamped (anti-windup).
    """

    def __init__(
        self,
        target_slip: float,
        wheel_radius: float | Sequence[float],
        wheel_count: int,
        kp: float = 1.0,
        ki: float = 20.0,
        omega_min: float = 1.0,
        omega_max: float = 100.0,
        axis_local: Sequence[float] = (0.0, 1.0, 0.0),
    ):
        if not 0.0 <= target_slip < 1.0:
            raise ArgumentError(f"target_slip must be in [0, 1), got {target_slip}")
        self.target_slip = float(target_slip)
        """Target driving slip s* [-]."""
        self.wheel_radius = np.broadcast_to(np.asarray(wheel_radius, dtype=np.float64), (wheel_count,)).copy()
        """Wheel radii [m], shape (wheel_count,)."""
        self.kp = float(kp)
        """Proportional gain on the hub velocity error [-]."""
        self.ki = float(ki)
        """Integral gain on the hub velocity error [1/s]."""
        self.omega_min = float(omega_min)
        """Lowest commanded speed [rad/s]."""
        self.omega_max = float(omega_max)
        """Highest commanded speed [rad/s]."""
        self.axis_local = np.asarray(axis_local, dtype=np.float64)
        """Wheel spin axis in the wheel body frame [-], shape (3,)."""
        self.integral = np.zeros(wheel_count)
        """Integrated velocity error per wheel [m], shape (wheel_count,)."""
        self.slip = np.zeros(wheel_count)
        """Last measured slip per wheel [-], shape (wheel_count,)."""
        self._t_prev: float | None = None

    def __call__(self, t, wheel_states, wrenches) -> DriveCommand:
        dt = 0.0 if self._t_prev is None else t - self._t_prev
        self._t_prev = t
        s_star = self.target_slip
        out = np.empty(len(wheel_states))
        for i, k in enumerate(wheel_states):
            axis, forward = wheel_frame(k.orientation, self.axis_local)
            r = self.wheel_radius[i]
            v = float(k.linear_velocity @ forward)
            rim = float(k.angular_velocity @ axis) * r
            self.slip[i] = 1.0 - v / rim if abs(rim) > 1e-12 else 0.0
            error = v - (1.0 - s_star) * rim
            raw = (v + self.kp * error + self.ki * (self.integral[i] + error * dt)) / ((1.0 - s_star) * r)
            out[i] = min(max(raw, self.omega_min), self.omega_max)
            if out[i] == raw:  # anti-windup: integrate only while unclamped
                self.integral[i] += error * dt
        return DriveCommand("speed", out)

    def state_dict(self) -> dict:
        """The integrals, the last slips and the time of the last call (nan: none yet)."""
        return {
            "integral": self.integral.copy(),
            "slip": self.slip.copy(),
            "t_prev": np.nan if self._t_prev is None else self._t_prev,
        }

    def state_dict_units(self) -> dict[str, str]:
        return {"integral": "m", "slip": "1", "t_prev": "s"}

    def load_state_dict(self, state: dict) -> None:
        self.integral = np.array(state["integral"], dtype=np.float64)
        self.slip = np.array(state["slip"], dtype=np.float64)
        t_prev = float(state["t_prev"])
        self._t_prev = None if np.isnan(t_prev) else t_prev
