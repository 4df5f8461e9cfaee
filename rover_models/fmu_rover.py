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
import shutil
from typing import Sequence

import numpy as np
from fmpy import extract, read_model_description
from fmpy.fmi1 import FMICallException

from cosim.contract import WheelKinematics, WheelWrench

_DISCARD, _ERROR = 2, 3

_INPUTS = [f"{q}.{a}" for q in ("force", "torque") for a in "xyz"]
_OUTPUTS = (
    [f"position.{a}" for a in "xyz"]
    + [f"orientation.{a}" for a in "wxyz"]
    + [f"velocity.{a}" for a in "xyz"]
    + [f"angular_velocity.{a}" for a in "xyz"]
)


class FmuVariableError(KeyError):
    """A variable the convention needs is missing or has the wrong type/causality."""

    def __str__(self):  # KeyError would print the message with quotes
        return str(self.args[0])


class FmuStepError(RuntimeError):
    """The FMU refused a step and it could not be retried."""


def read_cosim_description(path: str | os.PathLike):
    """fmpy model description of a co-simulation FMU; ValueError unless FMI 2.0 or 3.0 co-simulation."""
    path = os.fspath(path)
    md = read_model_description(path)
    if md.coSimulation is None:
        raise ValueError(f"{path} is not a co-simulation FMU")
    if md.fmiVersion not in ("2.0", "3.0"):
        raise ValueError(f"{path}: FMI {md.fmiVersion} is not supported (2.0 and 3.0 are)")
    return md


def instantiate_cosim(path: str | os.PathLike, md, instance_name: str, start_time: float):
    """Unpack and instantiate a co-simulation FMU (model description `md`) and enter
    initialization mode at start_time [s].

    Returns (slave, unzip directory, set_real, get_real): the fmpy FMU2Slave/FMU3Slave and
    its Real (2.0) / Float64 (3.0) setter and getter.
    """
    unzipdir = extract(os.fspath(path))
    kwargs = dict(guid=md.guid, unzipDirectory=unzipdir,
                  modelIdentifier=md.coSimulation.modelIdentifier, instanceName=instance_name)
    if md.fmiVersion == "2.0":
        from fmpy.fmi2 import FMU2Slave

        fmu = FMU2Slave(**kwargs)
        fmu.instantiate()
        fmu.setupExperiment(startTime=start_time)
        fmu.enterInitializationMode()
        return fmu, unzipdir, fmu.setReal, fmu.getReal
    from fmpy.fmi3 import FMU3Slave

    fmu = FMU3Slave(**kwargs)
    fmu.instantiate()
    fmu.enterInitializationMode(startTime=start_time)
    return fmu, unzipdir, fmu.setFloat64, fmu.getFloat64


class FmuSession:
    """What every FMU side shares: the model description, variable lookup by name with
    clear errors, lazy exit from initialization, doStep with retries in halves, and
    cleanup. FmuRover and cosim.fmu_controller.FmuController build on it; the subclass
    instantiates the FMU (instantiate_cosim) into `fmu`, `_unzipdir`, `_set`, `_get`."""

    def __init__(self, fmu: str | os.PathLike, max_halvings: int, retry_on_error: bool, instance_name: str):
        self.path = os.fspath(fmu)
        self.md = read_cosim_description(self.path)
        self.fmi_version = self.md.fmiVersion
        """'2.0' or '3.0'."""
        self._real_type = "Real" if self.fmi_version == "2.0" else "Float64"
        self.variables = {v.name: v for v in self.md.modelVariables}
        """FMU variables by name (fmpy ScalarVariable)."""
        self.can_vary_step = bool(self.md.coSimulation.canHandleVariableCommunicationStepSize)
        """Whether the FMU accepts communication steps of varying size (needed for retries)."""
        self.max_halvings = int(max_halvings)
        self.retry_on_error = bool(retry_on_error)
        self.instance_name = instance_name
        self.fmu = None
        """The fmpy slave; None before instantiation and after close()."""
        self._unzipdir = None
        self._initializing = False

    def _listing(self) -> str:
        return "; ".join(f"{v.name} ({v.causality}, {v.type})" for v in self.md.modelVariables)

    def _vr(self, name: str, causalities: tuple[str, ...] | None) -> int:
        v = self.variables.get(name)
        if v is None:
            raise FmuVariableError(f"{self.path}: no variable {name!r}; the FMU has: {self._listing()}")
        if v.type != self._real_type:
            raise FmuVariableError(f"{self.path}: variable {name!r} is {v.type}, expected {self._real_type}; "
                                   f"the FMU has: {self._listing()}")
        if causalities is not None and v.causality not in causalities:
            raise FmuVariableError(f"{self.path}: variable {name!r} has causality {v.causality}, expected "
                                   f"{' or '.join(causalities)}; the FMU has: {self._listing()}")
        return v.valueReference

    def _ready(self) -> None:
        """Leave initialization mode on first use (parameters can be set until then)."""
        if self._initializing:
            self.fmu.exitInitializationMode()
            self._initializing = False

    def _step(self, t: float, h: float, depth: int) -> None:
        try:
            result = self.fmu.doStep(currentCommunicationPoint=t, communicationStepSize=h)
        except FMICallException as err:
            retryable = err.status == _DISCARD or (self.retry_on_error and err.status == _ERROR)
            if not retryable:
                raise
            if not self.can_vary_step:
                raise FmuStepError(
                    f"{self.path}: doStep(t={t:g} s, H={h:g} s) refused (status {err.status}) and the FMU "
                    f"cannot handle variable communication step sizes, so it cannot be retried with smaller steps"
                ) from err
            if depth >= self.max_halvings:
                raise FmuStepError(
                    f"{self.path}: doStep(t={t:g} s) still refused after {depth} halvings (H={h:g} s)"
                ) from err
            self._step(t, h / 2, depth + 1)
            self._step(t + h / 2, h / 2, depth + 1)
            return
        if self.fmi_version == "3.0":
            _, terminate, early, last = result
            if terminate:
                raise FmuStepError(f"{self.path}: the FMU asked to terminate at t={last:g} s")
            if early and last < t + h:  # FMI 3.0 early return: go on from where it stopped
                self._step(last, t + h - last, depth)

    def close(self) -> None:
        """Terminate and free the FMU instance, remove the unpacked files."""
        if self.fmu is not None:
            try:
                self._ready()
                self.fmu.terminate()
            finally:
                self.fmu.freeInstance()
                self.fmu = None
                shutil.rmtree(self._unzipdir, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


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
        if found != list(range(wheel_count)):
            have = ", ".join(f"wheel_{i}" for i in found) or "none"
            raise ValueError(
                f"{self.path}: the scene expects {wheel_count} wheel(s) (wheel_0 .. wheel_{wheel_count - 1}), "
                f"the FMU has {len(found)} ({have})"
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
