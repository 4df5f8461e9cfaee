"""FMU rover adapter: a RoverSide (cosim.contract) around an FMI 2.0 or 3.0 co-simulation FMU.

Variable naming convention (i = 0 .. wheel_count-1, all Real / Float64, SI units, world frame;
`<prefix>` is "wheel_" unless the FMU names its wheels otherwise):

    inputs   <prefix><i>.force.{x,y,z} [N], <prefix><i>.torque.{x,y,z} [N m] (about the hub)
    outputs  <prefix><i>.position.{x,y,z} [m], <prefix><i>.orientation.{w,x,y,z} [-],
             <prefix><i>.velocity.{x,y,z} [m/s], <prefix><i>.angular_velocity.{x,y,z} [rad/s]
    gravity  gravity.{x,y,z} [m/s^2], a parameter or an input
    optional <prefix><i>.speed_command [rad/s], <prefix><i>.torque_command [N m] (inputs);
             drive_mode (input: 0 the speed commands drive the wheels, 1 the torque commands);
             body.position.{x,y,z} [m], body.orientation.{w,x,y,z} [-], body.velocity.{x,y,z} [m/s],
             body.angular_velocity.{x,y,z} [rad/s] (outputs: the rover body's frame origin);
             start.x, start.y, start.z [m], start.heading [rad] (parameters: where the rover body
             starts, turned by heading about +z); total_mass [kg] (parameter or output)

Step retry: when doStep answers Discard (or Error, with retry_on_error=True) and the FMU
declares canHandleVariableCommunicationStepSize, the step is retried as two halves,
recursively, down to max_halvings; the FMU is assumed to have left its state at the
start of the refused step (as FMI 2.0/3.0 co-simulation FMUs that discard do when they
report no progress; an FMI 3.0 lastSuccessfulTime beyond the start is honoured).

Checkpoints: `state_dict` holds the FMU's serialized state when the FMU can save it
(canGetAndSetFMUstate and canSerializeFMUstate); otherwise a run with it cannot be resumed
and `load_state_dict` says so.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from cosim.contract import WheelKinematics, WheelWrench
from soil.errors import ArgumentError, InternalError

from .fmu_session import FmuError, FmuSession, FmuStepError, FmuVariableError, instantiate_cosim, read_cosim_description

__all__ = ["FmuError", "FmuRover", "FmuStepError", "FmuVariableError", "check_rover_fmu"]

_INPUTS = [f"{q}.{a}" for q in ("force", "torque") for a in "xyz"]
_OUTPUTS = (
    [f"position.{a}" for a in "xyz"]
    + [f"orientation.{a}" for a in "wxyz"]
    + [f"velocity.{a}" for a in "xyz"]
    + [f"angular_velocity.{a}" for a in "xyz"]
)
_START = ("start.x", "start.y", "start.z", "start.heading")


def _wheel_indices(names, prefix: str) -> list[int]:
    found = set()
    for name in names:
        head = name.split(".")[0]
        if head.startswith(prefix) and head[len(prefix) :].isdigit():
            found.add(int(head[len(prefix) :]))
    return sorted(found)


def check_rover_fmu(path: str | os.PathLike, wheel_count: int | None = None, prefix: str = "wheel_") -> dict:
    """Check an FMU against the convention without instantiating it; FmuError / FmuVariableError
    name what is missing (with the FMU's variable listing). Returns {'wheel_count', 'speed', 'torque'
    (whether every wheel has that command input), 'body' (body.* outputs present), 'start' (start.*
    parameters present), 'total_mass' (its start value or None)}."""
    md = read_cosim_description(path)
    variables = {v.name: v for v in md.modelVariables}
    real = "Real" if md.fmiVersion == "2.0" else "Float64"
    listing = "; ".join(f"{v.name} ({v.causality}, {v.type})" for v in md.modelVariables)
    found = _wheel_indices(variables, prefix)
    count = len(found) if wheel_count is None else int(wheel_count)
    if count < 1 or found != list(range(count)):
        have = ", ".join(f"{prefix}{i}" for i in found) or "none"
        raise FmuError(
            f"{path}: the scene expects {count} wheel(s) ({prefix}0 .. {prefix}{count - 1}), the FMU has "
            f"{len(found)} ({have}); a rover FMU needs {prefix}<i>.* variables for i = 0 .. n-1; the FMU "
            f"has: {listing}"
        )

    def need(name, causalities):
        v = variables.get(name)
        if v is None:
            raise FmuVariableError(f"{path}: no variable {name!r}; the FMU has: {listing}")
        if v.type != real or (causalities and v.causality not in causalities):
            raise FmuVariableError(
                f"{path}: variable {name!r} is {v.causality} {v.type}, expected "
                f"{' or '.join(causalities)} {real}; the FMU has: {listing}"
            )

    for i in range(count):
        for suffix in _INPUTS:
            need(f"{prefix}{i}.{suffix}", ("input",))
        for suffix in _OUTPUTS:
            need(f"{prefix}{i}.{suffix}", ("output",))
    for axis in "xyz":
        need(f"gravity.{axis}", ("parameter", "input"))
    mass = variables.get("total_mass")
    return {
        "wheel_count": count,
        "speed": all(f"{prefix}{i}.speed_command" in variables for i in range(count)),
        "torque": all(f"{prefix}{i}.torque_command" in variables for i in range(count)),
        "body": all(f"body.{s}" in variables for s in _OUTPUTS),
        "start": all(name in variables for name in _START),
        "total_mass": None if mass is None or mass.start is None else float(mass.start),
    }


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
        prefix: the wheels' variable prefix ("wheel_": wheel_0.force.x, ...).
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
        prefix: str = "wheel_",
    ):
        super().__init__(fmu, max_halvings, retry_on_error, instance_name)
        found = _wheel_indices(self.variables, prefix)
        if wheel_count is None:
            wheel_count = len(found)
        if wheel_count < 1 or found != list(range(wheel_count)):
            have = ", ".join(f"{prefix}{i}" for i in found) or "none"
            raise FmuError(
                f"{self.path}: the scene expects {wheel_count} wheel(s) ({prefix}0 .. {prefix}{wheel_count - 1}), "
                f"the FMU has {len(found)} ({have}); a rover FMU needs {prefix}<i>.* variables for i = 0 .. n-1; "
                f"the FMU has: {self._listing()}"
            )
        self.prefix = prefix
        self.wheel_names = [f"{prefix}{i}" for i in range(wheel_count)]
        """Wheel names in the FMU, <prefix>0 .. <prefix><n-1>."""

        self._vr_in = np.array([[self._vr(f"{w}.{s}", ("input",)) for s in _INPUTS] for w in self.wheel_names])
        self._vr_out = np.array([[self._vr(f"{w}.{s}", ("output",)) for s in _OUTPUTS] for w in self.wheel_names])
        self._vr_gravity = [self._vr(f"gravity.{a}", ("parameter", "input")) for a in "xyz"]
        self._gravity_causality = self.variables["gravity.x"].causality
        self._gravity_variability = self.variables["gravity.x"].variability
        self._vr_speed = self._optional(".speed_command")
        self._vr_torque = self._optional(".torque_command")
        self._vr_mode = [self._vr("drive_mode", ("input", "parameter"))] if "drive_mode" in self.variables else None
        self._vr_body = (
            [self._vr(f"body.{s}", ("output",)) for s in _OUTPUTS]
            if all(f"body.{s}" in self.variables for s in _OUTPUTS)
            else None
        )
        self.drive_mode = "speed"
        """'speed' or 'torque': which command inputs drive the wheels."""

        self.fmu, self._unzipdir, self._set, self._get = self._watched(
            instantiate_cosim(self.path, self.md, instance_name, start_time)
        )
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
            raise InternalError(f"{self.path}: gravity.* is a fixed parameter; set gravity before the first step")
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
            raise ArgumentError(f"{len(wrenches)} wrenches for {len(self.wheel_names)} wheels")
        values = np.concatenate([np.concatenate([w.force, w.torque]) for w in wrenches])
        self._set(list(self._vr_in.reshape(-1)), [float(x) for x in values])

    def advance(self, t_end: float) -> None:
        """doStep from the current time to t_end [s] (retrying refused steps in halves)."""
        self._ready()
        t_end = float(t_end)
        if t_end < self._time:
            raise ArgumentError(f"cannot advance backwards: rover time {self._time}, t_end {t_end}")
        if t_end > self._time:
            self._step(self._time, t_end - self._time, 0)
        self._time = t_end

    # --- the rover body ------------------------------------------------------------------

    def body_kinematics(self) -> WheelKinematics:
        """Pose and velocity of the rover body (body.* outputs); without them the wheels' centroid,
        their mean velocity and no rotation."""
        self._ready()
        if self._vr_body is None:
            wheels = self.wheel_kinematics()
            return WheelKinematics(
                np.mean([k.position for k in wheels], axis=0),
                np.array([1.0, 0.0, 0.0, 0.0]),
                np.mean([k.linear_velocity for k in wheels], axis=0),
                np.zeros(3),
            )
        v = np.array(self._get(self._vr_body))
        return WheelKinematics(v[0:3], v[3:7], v[7:10], v[10:13])

    @property
    def total_mass(self) -> float | None:
        """The rover's mass [kg] from its total_mass variable (None when it has none)."""
        if "total_mass" not in self.variables:
            return None
        self._ready()
        return float(self._get([self._vr("total_mass", None)])[0])

    # --- drive commands ----------------------------------------------------------------------

    def _mode(self, mode: str) -> None:
        if mode != self.drive_mode and self._vr_mode is not None:
            self._set(self._vr_mode, [1.0 if mode == "torque" else 0.0])
        self.drive_mode = mode

    def set_wheel_speeds(self, speeds: Sequence[float]) -> None:
        """Wheel speed commands [rad/s], shape (wheel_count,) (needs <prefix><i>.speed_command)."""
        if self._vr_speed is None:
            raise FmuVariableError(
                f"{self.path}: no {self.prefix}<i>.speed_command inputs; the FMU has: {self._listing()}"
            )
        self._mode("speed")
        self._set(self._vr_speed, [float(s) for s in np.asarray(speeds).reshape(-1)])

    def set_wheel_torques(self, torques: Sequence[float]) -> None:
        """Wheel torque commands [N m], shape (wheel_count,) (needs <prefix><i>.torque_command)."""
        if self._vr_torque is None:
            raise FmuVariableError(
                f"{self.path}: no {self.prefix}<i>.torque_command inputs; the FMU has: {self._listing()}"
            )
        self._mode("torque")
        self._set(self._vr_torque, [float(s) for s in np.asarray(torques).reshape(-1)])

    # --- checkpoints -------------------------------------------------------------------------

    def state_dict(self) -> dict:
        """The FMU's serialized state (empty when the FMU cannot save it), its time and drive mode."""
        saved = self.save_state() if self.can_save_state else np.zeros(0, dtype=np.uint8)
        return {"fmu_state": saved, "time": self._time, "torque_mode": self.drive_mode == "torque"}

    def state_dict_units(self) -> dict[str, str]:
        """{key of state_dict(): its unit}."""
        return {"fmu_state": "bytes (the FMU's serialized state)", "time": "s", "torque_mode": "1"}

    def load_state_dict(self, state: dict) -> None:
        self.load_state(state["fmu_state"])
        self._time = float(state["time"])
        self.drive_mode = "torque" if bool(state["torque_mode"]) else "speed"
