"""FMU rover adapter: a RoverSide (cosim.contract) around an FMI 2.0 or 3.0 co-simulation FMU.

Variable naming convention (i = 0 .. wheel_count-1, all Real / Float64, SI units, world frame):

    inputs   wheel_<i>.force.{x,y,z} [N], wheel_<i>.torque.{x,y,z} [N m] (about the hub)
    outputs  wheel_<i>.position.{x,y,z} [m], wheel_<i>.orientation.{w,x,y,z} [-],
             wheel_<i>.velocity.{x,y,z} [m/s], wheel_<i>.angular_velocity.{x,y,z} [rad/s]
    gravity  gravity.{x,y,z} [m/s^2], a parameter or an input
    optional wheel_<i>.speed_command [rad/s], wheel_<i>.torque_command [N m] (inputs)

Step retry: when doStep answers Discard (or Error, with retry_on_error=True) and the FMU
declares canHandleVariableCommunicationStepSize, the step is retried as two halves,
recursively, down to max_halvings; the FMU is assumed to have left its state at the
start of the refused step (as FMI 2.0/3.0 co-simulation FMUs that discard do when they
report no progress; an FMI 3.0 lastSuccessfulTime beyond the start is honoured).
"""

from __future__ import annotations

import os
from typing import Sequence

import numpy as np

from cosim.contract import WheelKinematics, WheelWrench

from .fmu_session import FmuError, FmuSession, FmuStepError, FmuVariableError, instantiate_cosim

__all__ = ["FmuError", "FmuRover", "FmuStepError", "FmuVariableError"]

_INPUTS = [f"{q}.{a}" for q in ("force", "torque") for a in "xyz"]
_OUTPUTS = (
    [f"position.{a}" for a in "xyz"]
    + [f"orientation.{a}" for a in "wxyz"]
    + [f"velocity.{a}" for a in "xyz"]
    + [f"angular_velocity.{a}" for a in "xyz"]
)


class FmuRover(FmuSession):
    """A RoverSide backed by an FMU (FMI 2.0 or 3.0 co-simulation) through fmpy.

    Args:
        fmu: path of the .fmu file.
        wheel_count: wheels the scene expects; None accepts what the FMU has.
        gravity: optional gravity [m/s^2], shape (3,).
        start_values: {variable name: value} set during initialization (parameters).
        max_halvings: how often a refused step may be halved.
        retry_on_error: also retry on an Error answer (FMUs that report a step-size
            problem as Error); by default only Discard is retried.
        start_time: [s].
    """

    def __init__(
        self,
        fmu: str | os.PathLike,
        wheel_count: int | None = None,
        gravity: Sequence[float] | None = None,
        start_values: dict[str, float] | None = None,
        max_halvings: int = 8,
        retry_on_error: bool = False,
        start_time: float = 0.0,
        instance_name: str = "rover",
    ):
        super().__init__(fmu, max_halvings, retry_on_error, instance_name)
        found = sorted({int(n.split(".")[0][6:]) for n in self.variables
                        if n.startswith("wheel_") and n.split(".")[0][6:].isdigit()})
        if wheel_count is None:
            wheel_count = len(found)
        if wheel_count < 1 or found != list(range(wheel_count)):
            have = ", ".join(f"wheel_{i}" for i in found) or "none"
            raise FmuError(
                f"{self.path}: the scene expects {wheel_count} wheel(s) (wheel_0 .. wheel_{wheel_count - 1}), "
                f"the FMU has {len(found)} ({have}); a rover FMU needs wheel_<i>.* variables for i = 0 .. n-1; "
                f"the FMU has: {self._listing()}"
            )
        self.wheel_names = [f"wheel_{i}" for i in range(wheel_count)]
        """Wheel names in the FMU, wheel_0 .. wheel_<n-1>."""

        self._vr_in = np.array([[self._vr(f"{w}.{s}", ("input",)) for s in _INPUTS] for w in self.wheel_names])
        self._vr_out = np.array([[self._vr(f"{w}.{s}", ("output",)) for s in _OUTPUTS] for w in self.wheel_names])
        self._vr_gravity = [self._vr(f"gravity.{a}", ("parameter", "input")) for a in "xyz"]
        self._gravity_causality = self.variables["gravity.x"].causality
        self._gravity_variability = self.variables["gravity.x"].variability
        self._vr_speed = self._optional(".speed_command")
        self._vr_torque = self._optional(".torque_command")

        self.fmu, self._unzipdir, self._set, self._get = instantiate_cosim(self.path, self.md, instance_name, start_time)
        self._initializing = True
        self._time = float(start_time)
        for name, value in (start_values or {}).items():
            self._set([self._vr(name, None)], [float(value)])
        if gravity is not None:
            self.set_gravity(gravity)

    def _optional(self, suffix: str) -> list[int] | None:
        names = [w + suffix for w in self.wheel_names]
        if not all(n in self.variables for n in names):
            return None
        return [self._vr(n, ("input",)) for n in names]

    # --- RoverSide ---------------------------------------------------------------------

    @property
    def time(self) -> float:
        """Rover time [s]."""
        return self._time

    def set_gravity(self, gravity: Sequence[float]) -> None:
        g = [float(x) for x in np.asarray(gravity, dtype=np.float64).reshape(3)]
        if not self._initializing and self._gravity_causality == "parameter" and self._gravity_variability != "tunable":
            raise RuntimeError(f"{self.path}: gravity.* is a fixed parameter; set gravity before the first step")
        self._set(self._vr_gravity, g)

    def wheel_kinematics(self) -> list[WheelKinematics]:
        self._ready()
        values = np.array(self._get(list(self._vr_out.reshape(-1)))).reshape(self._vr_out.shape)
        return [
            WheelKinematics(position=v[0:3], orientation=v[3:7], linear_velocity=v[7:10], angular_velocity=v[10:13])
            for v in values
        ]

    def apply_wheel_wrenches(self, wrenches: Sequence[WheelWrench]) -> None:
        if len(wrenches) != len(self.wheel_names):
            raise ValueError(f"{len(wrenches)} wrenches for {len(self.wheel_names)} wheels")
        values = np.concatenate([np.concatenate([w.force, w.torque]) for w in wrenches])
        self._set(list(self._vr_in.reshape(-1)), [float(x) for x in values])

    def advance(self, t_end: float) -> None:
        """doStep from the current time to t_end [s] (retrying refused steps in halves)."""
        self._ready()
        t_end = float(t_end)
        if t_end < self._time:
            raise ValueError(f"cannot advance backwards: rover time {self._time}, t_end {t_end}")
        if t_end > self._time:
            self._step(self._time, t_end - self._time, 0)
        self._time = t_end

    # --- drive commands ----------------------------------------------------------------------

    def set_wheel_speeds(self, speeds: Sequence[float]) -> None:
        """Wheel speed commands [rad/s], shape (wheel_count,) (needs wheel_<i>.speed_command)."""
        if self._vr_speed is None:
            raise FmuVariableError(f"{self.path}: no wheel_<i>.speed_command inputs; the FMU has: {self._listing()}")
        self._set(self._vr_speed, [float(s) for s in np.asarray(speeds).reshape(-1)])

    def set_wheel_torques(self, torques: Sequence[float]) -> None:
        """Wheel torque commands [N m], shape (wheel_count,) (needs wheel_<i>.torque_command)."""
        if self._vr_torque is None:
            raise FmuVariableError(f"{self.path}: no wheel_<i>.torque_command inputs; the FMU has: {self._listing()}")
        self._set(self._vr_torque, [float(s) for s in np.asarray(torques).reshape(-1)])
