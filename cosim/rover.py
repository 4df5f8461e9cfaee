"""A rover run's rover side: the rover model (MJCF through MuJoCo, or an FMU), braked while it lands,
then driven by its controller.

    rover = open_rover(plan)                         # MujocoRover or FmuRover, not yet placed
    driver = RoverDriver(rover, make_controller(plan), takes_speed=plan.rover.takes_speed)
    coupler = Coupler(soil, driver, H, controller=driver.command)

While landing, `command` holds the wheels at zero speed (or zero torque when the rover takes no
speed commands); after `start_drive` it asks the scene's controller. The last command is kept
for the records. `state_dict` gathers the phase, the last command, the rover model's state and
the controller's (a controller without state_dict is taken to be stateless).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np

from soil.errors import InputError

from .contract import WheelKinematics, WheelWrench
from .controllers import ConstantSpeed, ConstantTorque, DriveCommand, SlipController
from .plan import RunPlan, SceneError
from .probe import import_callable
from .single_wheel import PHASE_DRIVING, PHASE_LANDING


def open_rover(plan: RunPlan, start_z: float | None = None):
    """The plan's rover model at its start heading and horizontal position: a MujocoRover (moved there)
    or an FmuRover (its start.* parameters set; start_z [m] sets start.z)."""
    r = plan.rover
    assert r is not None
    x, y, heading = r.start
    if r.model == "fmu":
        from rover_models.fmu_rover import FmuRover

        values = dict(r.start_values)
        if r.start_parameters:
            values.update({"start.x": x, "start.y": y, "start.heading": heading})
            if start_z is not None:
                values["start.z"] = start_z
        return FmuRover(r.source, len(r.wheel_names), gravity=plan.gravity, start_values=values, prefix=r.prefix)
    from rover_models.mujoco_rover import MujocoRover

    rover = MujocoRover(r.source, list(r.wheel_names), gravity=plan.gravity)
    origin = rover.body_kinematics(rover.body_id()).position
    rover.move_base(np.array([x - origin[0], y - origin[1], 0.0]), heading)
    return rover


class ControllerError(InputError, ValueError):
    """The drive's controller failed while driving, or commanded what no wheel takes (not a DriveCommand,
    another wheel count, a value that is not finite): the message names it and the time."""


def drive_label(plan: RunPlan) -> str:
    """How an error names the plan's drive: its scene key and what it runs (a function, an FMU, a kind)."""
    assert plan.rover is not None and plan.scene.rover is not None
    drive = plan.rover.drive
    key = f"rover.controllers.{drive.name}" if isinstance(plan.scene.rover.drive, str) else "rover.drive"
    if drive.kind == "python":
        return f"{key} ({drive.section.function})"
    return f"{key} ({drive.kind} {os.path.basename(drive.file)})" if drive.file else f"{key} ({drive.kind})"


def make_controller(plan: RunPlan):
    """The drive's controller (cosim.controllers.Controller) for the plan's rover."""
    r = plan.rover
    assert r is not None
    section = r.drive.section
    n = len(r.wheel_names)
    radii = tuple(w.rim_radius for w in plan.wheels)
    # the drive section's validator requires each kind's own keys
    if section.kind == "speed":
        assert section.speed is not None
        return ConstantSpeed(section.speed, n)
    if section.kind == "torque":
        assert section.torque is not None
        return ConstantTorque(section.torque, n)
    if section.kind == "slip":
        omega_max = section.omega_max
        assert section.target_slip is not None and omega_max is not None
        return SlipController(
            section.target_slip,
            radii,
            n,
            kp=1.0 if section.kp is None else section.kp,
            ki=20.0 if section.ki is None else section.ki,
            omega_min=0.1 * omega_max if section.omega_min is None else section.omega_min,
            omega_max=omega_max,
        )
    if section.kind == "fmu":
        from .fmu_controller import FmuController

        assert r.drive.file is not None
        return FmuController(r.drive.file, n, mode=section.mode, start_values=section.start_values)
    assert section.function is not None
    factory = import_callable(section.function, plan.scene.base_dir)
    try:
        controller = factory(wheel_count=n, wheel_radius=radii, **(section.args or {}))
    except Exception as error:  # the user's factory: its arguments or its own failure, named
        raise SceneError(
            [
                f"rover.drive.function: {section.function}(wheel_count, wheel_radius, **args) with args "
                f"{dict(section.args or {})!r} raised {type(error).__name__}: {error}"
            ]
        ) from error
    if not callable(controller):
        raise SceneError(
            [
                f"rover.drive.function: {section.function} returned {type(controller).__name__}, not a "
                "controller (a callable (t, wheel_states, wrenches) -> DriveCommand)"
            ]
        )
    return controller


class RoverDriver:
    """RoverSide of a rover run (module docstring): delegates to the rover model, adds the phases, the
    drive commands and the rover body's kinematics.

    Args:
        rover: a MujocoRover or FmuRover.
        controller: the drive's controller.
        takes_speed: brake the wheels with zero speed commands while landing (else zero torques).
        body: MuJoCo body id reported as the rover's pose (MJCF; None: the base).
        landed: start in the driving phase (no landing).
    """

    state_columns = ["x", "y", "z", "vx", "vy", "vz", "heading"]
    """Columns of `state_row()`: body position [m], body velocity [m/s], heading about +z [rad]."""
    state_units = ["m", "m", "m", "m/s", "m/s", "m/s", "rad"]

    def __init__(
        self,
        rover,
        controller,
        takes_speed: bool = True,
        body: int | None = None,
        landed: bool = False,
        label: str = "the drive's controller",
        user_code: bool = False,
    ):
        self.rover = rover
        self.controller = controller
        self.label = label
        """What names the controller in an error (its scene key and name)."""
        self.user_code = user_code
        """Whether the controller is a user's Python (a python drive): any error of it is named as its own."""
        self.wheel_names = list(rover.wheel_names)
        self.brake = "speed" if takes_speed else "torque"
        self._body = body
        self.phase = PHASE_LANDING
        self.drive_start = math.nan
        """Time the drive started [s] (nan while landing)."""
        self.last_command = DriveCommand(self.brake, np.zeros(len(self.wheel_names)))
        """The command held over the last macro step."""
        if landed:
            self.start_drive()

    # -- RoverSide ---------------------------------------------------------------------
    @property
    def time(self) -> float:
        return self.rover.time

    def set_gravity(self, gravity: Sequence[float]) -> None:
        self.rover.set_gravity(gravity)

    def wheel_kinematics(self) -> list[WheelKinematics]:
        return self.rover.wheel_kinematics()

    def apply_wheel_wrenches(self, wrenches: Sequence[WheelWrench]) -> None:
        self.rover.apply_wheel_wrenches(wrenches)

    def advance(self, t_end: float) -> None:
        self.rover.advance(t_end)

    def set_wheel_speeds(self, speeds) -> None:
        self.rover.set_wheel_speeds(speeds)

    def set_wheel_torques(self, torques) -> None:
        self.rover.set_wheel_torques(torques)

    # -- phases and commands -----------------------------------------------------------
    def command(self, t: float, wheel_states, wrenches) -> DriveCommand:
        """The coupler's controller: brakes while landing, the scene's controller while driving."""
        if self.phase == PHASE_LANDING:
            command = DriveCommand(self.brake, np.zeros(len(self.wheel_names)))
        else:
            try:
                command = self.controller(t, wheel_states, wrenches)
            except Exception as error:
                from rover_models.fmu_session import FmuStepError

                if isinstance(error, FmuStepError):  # a controller FMU that failed: named with the drive's key
                    raise ControllerError(f"{self.label} at t = {t:.6g} s: {error}") from error
                if not self.user_code:  # the project's own controllers: their errors as they are
                    raise
                # a user's controller: its failure (a DriveCommand it built wrongly too) named, not a bug of ours
                raise ControllerError(
                    f"{self.label} raised {type(error).__name__}: {error} at t = {t:.6g} s"
                ) from error
            problem = self._command_problem(command)
            if problem:
                raise ControllerError(f"{self.label} {problem} at t = {t:.6g} s")
        self.last_command = command
        return command

    def _command_problem(self, command) -> str | None:
        """What makes a controller's answer no command for this rover's wheels (None: it is one)."""
        if not isinstance(command, DriveCommand):
            return f"returned {type(command).__name__}, not a cosim.controllers.DriveCommand"
        if len(command.values) != len(self.wheel_names):
            return f"commanded {len(command.values)} wheels, the rover has {len(self.wheel_names)}"
        if not np.all(np.isfinite(command.values)):
            return f"commanded {command.mode}s {command.values.tolist()}: every value must be finite"
        return None

    def start_drive(self) -> None:
        """End the landing: from the next macro step on the controller drives."""
        self.phase = PHASE_DRIVING
        self.drive_start = self.time

    def command_row(self) -> tuple[np.ndarray, np.ndarray]:
        """(speed commands [rad/s], torque commands [N m]) of the last macro step, shape (W,) each; nan
        where the other kind was commanded."""
        values = np.asarray(self.last_command.values, dtype=np.float64)
        nan = np.full(len(values), np.nan)
        return (values, nan) if self.last_command.mode == "speed" else (nan, values)

    # -- the body ---------------------------------------------------------------------
    def body_kinematics(self) -> WheelKinematics:
        """Pose and velocity of the rover body (its frame origin), world frame."""
        if hasattr(self.rover, "body_id"):
            return self.rover.body_kinematics(self.rover.body_id() if self._body is None else self._body)
        return self.rover.body_kinematics()

    @property
    def position(self) -> np.ndarray:
        """Body position [m], shape (3,)."""
        return self.body_kinematics().position

    def state_row(self) -> np.ndarray:
        """`state_columns` [SI], shape (7,)."""
        body = self.body_kinematics()
        w, x, y, z = body.orientation
        heading = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        return np.r_[body.position, body.linear_velocity, heading]

    # -- checkpoints ------------------------------------------------------------------
    def state_dict(self) -> dict:
        out = {
            "phase": self.phase,
            "drive_start": self.drive_start,
            "command_torque": self.last_command.mode == "torque",
            "command": np.asarray(self.last_command.values, dtype=np.float64),
        }
        out.update({f"model/{k}": v for k, v in self.rover.state_dict().items()})
        if hasattr(self.controller, "state_dict"):
            out.update({f"controller/{k}": v for k, v in self.controller.state_dict().items()})
        return out

    def state_dict_units(self) -> dict[str, str]:
        """{key of state_dict(): its unit}; the rover model's and the controller's where they say
        (a `state_dict_units()` method)."""
        torque = self.last_command.mode == "torque"
        units = {"phase": "1", "drive_start": "s", "command_torque": "1", "command": "N m" if torque else "rad/s"}
        for prefix, part in (("model", self.rover), ("controller", self.controller)):
            if hasattr(part, "state_dict_units"):
                units.update({f"{prefix}/{k}": v for k, v in part.state_dict_units().items()})
        return units

    def load_state_dict(self, state: dict) -> None:
        self.phase = int(state["phase"])
        self.drive_start = float(state["drive_start"])
        self.last_command = DriveCommand(
            "torque" if bool(state["command_torque"]) else "speed", np.array(state["command"])
        )
        self.rover.load_state_dict({k[6:]: v for k, v in state.items() if k.startswith("model/")})
        if hasattr(self.controller, "load_state_dict"):
            self.controller.load_state_dict({k[11:]: v for k, v in state.items() if k.startswith("controller/")})

    def close(self) -> None:
        for part in (self.rover, self.controller):
            if hasattr(part, "close"):
                part.close()
