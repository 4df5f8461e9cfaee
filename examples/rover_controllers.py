"""A drive controller for `kind = "python"` rover drives (examples/phobos_rover_patch.toml).

A scene names it as "module:function"; the function is called once with wheel_count, wheel_radius
and the drive's args, and returns the controller: a callable (t, wheel_states, wrenches) ->
cosim.controllers.DriveCommand. A controller with state keeps it in state_dict / load_state_dict so
that `cosim resume` continues it exactly, and names its entries' units in state_dict_units (the checkpoint
carries them).
"""

import numpy as np

from cosim.controllers import DriveCommand


class SoftStart:
    """Wheel speed ramped from 0 to `speed` [rad/s] over `ramp_time` [s] from the drive's start."""

    def __init__(self, wheel_count: int, speed: float, ramp_time: float):
        self.wheel_count = wheel_count
        self.speed = float(speed)
        self.ramp_time = float(ramp_time)
        self.start = None
        """Time of the first call [s] (None: not called yet)."""

    def __call__(self, t, wheel_states, wrenches) -> DriveCommand:
        if self.start is None:
            self.start = t
        fraction = min(1.0, (t - self.start) / self.ramp_time) if self.ramp_time > 0 else 1.0
        return DriveCommand("speed", np.full(self.wheel_count, fraction * self.speed))

    def state_dict(self) -> dict:
        return {"start": np.nan if self.start is None else self.start}

    def state_dict_units(self) -> dict[str, str]:
        return {"start": "s"}

    def load_state_dict(self, state: dict) -> None:
        start = float(state["start"])
        self.start = None if np.isnan(start) else start


def soft_start(wheel_count: int, wheel_radius, speed: float = 0.075, ramp_time: float = 60.0) -> SoftStart:
    """The SoftStart controller of a scene's drive (wheel_radius [m] is not needed here)."""
    return SoftStart(wheel_count, speed, ramp_time)
