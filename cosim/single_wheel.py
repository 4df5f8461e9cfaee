"""The single-wheel testbed (the paper's experiment) as a RoverSide.

A wheel under a vertical load (a mass) on a carriage. It runs in two phases:

- landing: the wheel does not turn and the carriage is held in X; the wheel settles onto
  the soil under its load (the runner ends the phase when it is at rest);
- driving: the wheel turns at omega about its axle (+Y); the carriage is either free
  along X against an optional drawbar load that may grow at a set rate (mode 'free':
  travel and slip emerge), or driven at the set slip (mode 'slip': v = omega r (1 - s)).

The quantities a user reads (slip, sinkage, drawbar pull, driving torque) are defined
once, in cosim.metrics.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from soil.errors import ArgumentError

from .contract import WheelKinematics, WheelWrench

PHASE_LANDING, PHASE_DRIVING = 0, 1
PHASES = ("landing", "driving")


class SingleWheelRig:
    """RoverSide of the single-wheel testbed (one wheel, named 'wheel').

    Args:
        mass: vertical load mass, wheel included [kg]; its weight m |g| presses the wheel down.
        radius: rim radius r [m] (for the set slip).
        omega: wheel angular speed about +Y while driving [rad/s].
        hub: initial hub position [m], shape (3,).
        mode: 'free' (carriage free along X) or 'slip' (carriage driven at v = omega r (1 - slip)).
        slip: the set slip in mode 'slip' [-].
        drawbar_load: force pulling the carriage backwards (-X) in mode 'free' [N] ...
        drawbar_ramp: ... growing at this rate from the start of the drive [N/s].
        gravity: [m/s^2], shape (3,).
        landed: start in the driving phase (no landing).
    """

    wheel_names = ["wheel"]
    state_columns = ["x", "y", "z", "vx", "vy", "vz", "angle", "omega", "drawbar_load"]
    """Columns of `state_row()`: hub position [m], hub velocity [m/s], wheel angle [rad],
    wheel speed [rad/s], resisting force on the carriage [N]."""
    state_units = ["m", "m", "m", "m/s", "m/s", "m/s", "rad", "rad/s", "N"]

    def __init__(
        self,
        mass: float,
        radius: float,
        omega: float,
        hub: ArrayLike,
        mode: str = "free",
        slip: float = 0.0,
        drawbar_load: float = 0.0,
        drawbar_ramp: float = 0.0,
        gravity=(0.0, 0.0, -9.81),
        landed: bool = False,
    ):
        if mode not in ("free", "slip"):
            raise ArgumentError(f"testbed.mode must be 'free' or 'slip', got {mode!r}")
        if not (mass > 0 and math.isfinite(mass)):
            raise ArgumentError(f"testbed.mass must be > 0 [kg], got {mass!r}")
        if not (radius > 0 and math.isfinite(radius)):
            raise ArgumentError(f"wheel radius must be > 0 [m], got {radius!r}")
        if mode == "slip" and not -1.0 < slip < 1.0:
            raise ArgumentError(f"testbed.slip must be in (-1, 1), got {slip!r}")
        self.mass = float(mass)
        self.radius = float(radius)
        self.drive_omega = float(omega)
        """Wheel speed of the driving phase [rad/s]."""
        self.mode = mode
        self.slip = float(slip)
        self.drawbar_load = float(drawbar_load)
        self.drawbar_ramp = float(drawbar_ramp)
        self.gravity = np.asarray(gravity, dtype=np.float64).reshape(3)
        """The scene's gravity vector [m/s^2], shape (3,)."""
        self.position = np.asarray(hub, dtype=np.float64).reshape(3).copy()
        """Hub position [m], shape (3,)."""
        self.velocity = np.zeros(3)
        """Hub velocity [m/s], shape (3,)."""
        self.angle = 0.0
        """Wheel rotation about +Y [rad]."""
        self.omega = 0.0
        """Current wheel speed about +Y [rad/s] (0 while landing)."""
        self.time = 0.0
        """Rig time [s]."""
        self.phase = PHASE_LANDING
        self.drive_start = math.nan
        """Time the drive started [s] (nan while landing)."""
        self.held = WheelWrench()
        """The soil wrench held over the current macro step."""
        if landed:
            self.start_drive()

    # -- phases ------------------------------------------------------------------------
    def start_drive(self) -> None:
        """End the landing: turn the wheel, and in mode 'slip' drive the carriage."""
        self.phase = PHASE_DRIVING
        self.drive_start = self.time
        self.omega = self.drive_omega
        self.velocity[0] = self.omega * self.radius * (1 - self.slip) if self.mode == "slip" else self.velocity[0]

    def resisting_force(self, t: float) -> float:
        """Drawbar load on the carriage at time t [N] (mode 'free', driving phase)."""
        if self.phase != PHASE_DRIVING or self.mode != "free":
            return 0.0
        return self.drawbar_load + self.drawbar_ramp * max(0.0, t - self.drive_start)

    # -- RoverSide ---------------------------------------------------------------------
    def set_gravity(self, gravity) -> None:
        self.gravity = np.asarray(gravity, dtype=np.float64).reshape(3)

    def wheel_kinematics(self) -> list[WheelKinematics]:
        half = 0.5 * self.angle
        return [
            WheelKinematics(
                self.position.copy(),
                np.array([math.cos(half), 0.0, math.sin(half), 0.0]),
                self.velocity.copy(),
                np.array([0.0, self.omega, 0.0]),
            )
        ]

    def apply_wheel_wrenches(self, wrenches: Sequence[WheelWrench]) -> None:
        if len(wrenches) != 1:
            raise ArgumentError(f"the single-wheel rig has 1 wheel, got {len(wrenches)} wrenches")
        self.held = wrenches[0]

    def advance(self, t_end: float) -> None:
        """Move the carriage to t_end [s] under the held wrench (exact for a wrench held constant)."""
        h = float(t_end) - self.time
        if h < 0:
            raise ArgumentError(f"t_end {t_end!r} s is before the rig's time {self.time!r} s")
        force = self.held.force
        acceleration = np.zeros(3)
        acceleration[2] = force[2] / self.mass + self.gravity[2]
        if self.phase == PHASE_DRIVING and self.mode == "free":
            # a drawbar load pulls backwards (-X) whatever the motion, like a weight on a line
            acceleration[0] = (force[0] - self.resisting_force(self.time + 0.5 * h)) / self.mass + self.gravity[0]
        self.position += self.velocity * h + 0.5 * acceleration * h * h
        self.velocity += acceleration * h
        self.angle += self.omega * h
        self.time = float(t_end)

    # -- records and checkpoints ---------------------------------------------------------
    def body_kinematics(self) -> WheelKinematics:
        """The carriage: the hub's position and velocity, no rotation."""
        return WheelKinematics(self.position.copy(), np.array([1.0, 0.0, 0.0, 0.0]), self.velocity.copy(), np.zeros(3))

    def command_row(self) -> tuple[np.ndarray, np.ndarray]:
        """(wheel speed [rad/s], torque nan) the rig turns the wheel at, shape (1,) each."""
        return np.array([self.omega]), np.array([np.nan])

    def state_row(self) -> np.ndarray:
        """The rig's state, `state_columns` [SI], shape (9,)."""
        return np.r_[self.position, self.velocity, self.angle, self.omega, self.resisting_force(self.time)]

    def state_dict(self) -> dict:
        held = self.held
        return {
            "position": self.position.copy(),
            "velocity": self.velocity.copy(),
            "angle": self.angle,
            "omega": self.omega,
            "time": self.time,
            "phase": self.phase,
            "drive_start": self.drive_start,
            "held_force": held.force.copy(),
            "held_torque": held.torque.copy(),
        }

    def state_dict_units(self) -> dict[str, str]:
        """{key of state_dict(): its unit}."""
        return {
            "position": "m",
            "velocity": "m/s",
            "angle": "rad",
            "omega": "rad/s",
            "time": "s",
            "phase": "1",
            "drive_start": "s",
            "held_force": "N",
            "held_torque": "N m",
        }

    def load_state_dict(self, state: dict) -> None:
        self.position = np.array(state["position"], dtype=np.float64)
        self.velocity = np.array(state["velocity"], dtype=np.float64)
        self.angle = float(state["angle"])
        self.omega = float(state["omega"])
        self.time = float(state["time"])
        self.phase = int(state["phase"])
        self.drive_start = float(state["drive_start"])
        self.held = WheelWrench(force=np.array(state["held_force"]), torque=np.array(state["held_torque"]))
