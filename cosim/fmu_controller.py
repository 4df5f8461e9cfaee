"""Drive controller backed by a co-simulation FMU (FMI 2.0 or 3.0) through fmpy.

An FmuController is a controller for the coupler's controller hook (cosim.controllers):

    command = controller(t, wheel_states, wrenches)   # -> DriveCommand

Variable naming convention (i = 0 .. wheel_count-1, Real / Float64, SI units, world
frame; the same names as rover_models.fmu_rover, with inputs and outputs swapped):

    inputs   (each optional: only those the FMU declares are set)
             wheel_<i>.velocity.{x,y,z} [m/s]          <- WheelKinematics.linear_velocity
             wheel_<i>.angular_velocity.{x,y,z} [rad/s] <- WheelKinematics.angular_velocity
             wheel_<i>.position.{x,y,z} [m]            <- WheelKinematics.position
             wheel_<i>.orientation.{w,x,y,z} [-]       <- WheelKinematics.orientation
             wheel_<i>.force.{x,y,z} [N]               <- WheelWrench.force (previous macro step)
             wheel_<i>.torque.{x,y,z} [N m]            <- WheelWrench.torque (previous macro step)
    outputs  wheel_<i>.speed_command [rad/s]  (mode 'speed')
             wheel_<i>.torque_command [N m]   (mode 'torque')

Timing: the FMU is instantiated and initialised at the time of the first call (inputs
set during initialization, outputs read right after it, no step). Every later call sets
the inputs measured at t, does one doStep from the previous call's time to t and reads
the command outputs, so a stateful controller integrates over [t_prev, t] seeing the
newest measurement (a controller that samples at t); a direct-feedthrough one answers
its formula of the inputs at t. A call at the same t again sets inputs and reads outputs
without stepping. Refused steps are retried in halves exactly as FmuRover does.

FMU loading, variable lookup (with the FMU's variable listing in every error), step
retry and close() are rover_models.fmu_session's, shared with the FMU rover, not copied.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from rover_models.fmu_session import (
    FmuSession,
    FmuStepError,  # noqa: F401  (re-exported: raised by calls whose step cannot be retried)
    FmuVariableError,
    instantiate_cosim,
)
from soil.errors import ArgumentError, InternalError

from .contract import WheelKinematics, WheelWrench
from .controllers import DriveCommand

# Per-wheel input suffixes and their slot in the 19 values gathered per wheel:
# position (3), orientation (4), linear velocity (3), angular velocity (3), force (3), torque (3).
_INPUTS = (
    [f"position.{a}" for a in "xyz"]
    + [f"orientation.{a}" for a in "wxyz"]
    + [f"velocity.{a}" for a in "xyz"]
    + [f"angular_velocity.{a}" for a in "xyz"]
    + [f"force.{a}" for a in "xyz"]
    + [f"torque.{a}" for a in "xyz"]
)
_COMMANDS = {"speed": "speed_command", "torque": "torque_command"}


class FmuController(FmuSession):
    """A drive controller (cosim.controllers.Controller) backed by a co-simulation FMU.

    Args:
        fmu: path of the .fmu file (FMI 2.0 or 3.0 co-simulation).
        wheel_count: wheels the scene has; None accepts the wheels the FMU has commands for.
        mode: 'speed' (read wheel_<i>.speed_command) or 'torque' (wheel_<i>.torque_command);
            None picks the one the FMU has for every wheel (an error if it has both).
        start_values: {variable name: value} set during initialization (parameters).
        max_halvings, retry_on_error: step retry, as for FmuRover.
        instance_name: FMU instance name.

    Raises FmuVariableError (listing the FMU's variables) when a command output is missing
    for a wheel, the FMU has commands for more wheels than the scene, or a variable of the
    convention has the wrong type or causality.
    """

    def __init__(
        self,
        fmu: str | os.PathLike,
        wheel_count: int | None = None,
        mode: str | None = None,
        start_values: dict[str, float] | None = None,
        max_halvings: int = 8,
        retry_on_error: bool = False,
        instance_name: str = "controller",
    ):
        super().__init__(fmu, max_halvings, retry_on_error, instance_name)
        self._time: float | None = None

        # Wheels: those with a command output; they must be wheel_0 .. wheel_<n-1>.
        found = {m: sorted(self._indices(suffix)) for m, suffix in _COMMANDS.items()}
        if mode is None:
            declared = [m for m, f in found.items() if f]
            if len(declared) == 2:
                raise ArgumentError(
                    f"{self.path}: the FMU has both wheel_<i>.speed_command and "
                    f"wheel_<i>.torque_command outputs; choose mode='speed' or mode='torque'"
                )
            mode = declared[0] if declared else "speed"
        if mode not in _COMMANDS:
            raise ArgumentError(f"mode must be 'speed' or 'torque' (or None), got {mode!r}")
        self.mode = mode
        """'speed' or 'torque': the kind of DriveCommand returned."""
        suffix, have = _COMMANDS[mode], found[mode]
        if wheel_count is None:
            wheel_count = len(have)
        expected = list(range(wheel_count))
        if not have or have != expected:
            missing = [f"wheel_{i}.{suffix}" for i in expected if i not in have]
            extra = [f"wheel_{i}.{suffix}" for i in have if i not in expected]
            problems = ([f"missing {', '.join(missing)}"] if missing else []) + (
                [f"unexpected {', '.join(extra)}"] if extra else []
            )
            raise FmuVariableError(
                f"{self.path}: a {mode} controller for {wheel_count or 'any'} wheel(s) needs outputs "
                f"wheel_<i>.{suffix} for i = 0 .. wheel_count-1; "
                f"{'; '.join(problems) or f'the FMU has no wheel_<i>.{suffix}'}; the FMU has: {self._listing()}"
            )
        self.wheel_count = wheel_count
        """Number of wheels [-]."""
        self.command_names = [f"wheel_{i}.{_COMMANDS[mode]}" for i in range(wheel_count)]
        """The FMU outputs read at every call, one per wheel."""
        self._vr_cmd = [self._vr(name, ("output",)) for name in self.command_names]

        # Inputs: whichever of the convention's names the FMU declares.
        slots, refs, names = [], [], []
        for i in range(wheel_count):
            for k, suffix in enumerate(_INPUTS):
                name = f"wheel_{i}.{suffix}"
                if name in self.variables:
                    refs.append(self._vr(name, ("input",)))
                    slots.append(i * len(_INPUTS) + k)
                    names.append(name)
        self.input_names = names
        """The FMU inputs set at every call (those of the convention the FMU has)."""
        self._vr_in = refs
        self._slots = np.array(slots, dtype=np.intp)
        self._start_values = [(self._vr(name, None), float(v)) for name, v in (start_values or {}).items()]

    def _indices(self, suffix: str) -> set[int]:
        out = set()
        for name in self.variables:
            head, _, rest = name.partition(".")
            if rest == suffix and head.startswith("wheel_") and head[6:].isdigit():
                out.add(int(head[6:]))
        return out

    @property
    def time(self) -> float | None:
        """Time of the last call [s] (None before the first)."""
        return self._time

    def __call__(
        self, t: float, wheel_states: Sequence[WheelKinematics], wrenches: Sequence[WheelWrench]
    ) -> DriveCommand:
        n = self.wheel_count
        if len(wheel_states) != n or len(wrenches) != n:
            raise ArgumentError(
                f"{len(wheel_states)} wheel states and {len(wrenches)} wrenches for a controller of {n} wheel(s)"
            )
        t = float(t)
        if self._slots.size:
            values = np.concatenate(
                [
                    np.concatenate(
                        [k.position, k.orientation, k.linear_velocity, k.angular_velocity, w.force, w.torque]
                    )
                    for k, w in zip(wheel_states, wrenches)
                ]
            )[self._slots]
        if self.fmu is None:
            if self._time is not None:
                raise InternalError(f"{self.path}: the controller is closed")
            self.fmu, self._unzipdir, self._set, self._get = self._watched(
                instantiate_cosim(self.path, self.md, self.instance_name, t)
            )
            self._initializing, self._time = True, t
            for vr, value in self._start_values:
                self._set([vr], [value])
            if self._slots.size:
                self._set(self._vr_in, [float(x) for x in values])
            self._ready()
        else:
            assert self._time is not None  # set when the FMU was instantiated
            if t < self._time:
                raise ArgumentError(f"cannot step backwards: controller time {self._time}, t {t}")
            if self._slots.size:
                self._set(self._vr_in, [float(x) for x in values])
            if t > self._time:
                self._step(self._time, t - self._time, 0)
        self._time = t
        return DriveCommand(self.mode, self._get(self._vr_cmd))

    # -- checkpoints ----------------------------------------------------------------------
    def state_dict(self) -> dict:
        """The time of the last call (nan: not called yet) and the FMU's serialized state (empty before
        the first call; FmuError when the FMU cannot save its state)."""
        if self.fmu is None:
            return {"time": np.nan, "fmu_state": np.zeros(0, dtype=np.uint8)}
        return {"time": self._time, "fmu_state": self.save_state()}

    def state_dict_units(self) -> dict[str, str]:
        """{key of state_dict(): its unit}."""
        return {"time": "s", "fmu_state": "bytes (the FMU's serialized state)"}

    def load_state_dict(self, state: dict) -> None:
        t = float(state["time"])
        if np.isnan(t):
            return
        if self.fmu is None:  # instantiate it as the first call would, then put the saved state in
            self.fmu, self._unzipdir, self._set, self._get = self._watched(
                instantiate_cosim(self.path, self.md, self.instance_name, t)
            )
            self._initializing = True
            for vr, value in self._start_values:
                self._set([vr], [value])
        self.load_state(state["fmu_state"])
        self._time = t
