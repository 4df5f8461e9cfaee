"""The single-wheel test (the paper's experiment): a loaded wheel driven over a soil bed.

The rig is a small RoverSide of its own: a wheel under a vertical load (a mass), turned
at a set angular speed omega about its axle (Y), on a carriage that is either free along
the track (mode 'free': travel and slip emerge) or driven at a set slip (mode 'slip':
the soil's horizontal force is the drawbar pull). The soil is the DEM (cosim.dem_soil).

Definitions (checked in tests/test_single_wheel.py):
    slip s = 1 - v / (omega r), r = rim radius; travel = x - x0;
    sinkage = undisturbed surface height - lowest rim point (hub z - r);
    drawbar pull = soil force on the wheel along +X; driving torque = -(soil torque about the hub)_Y.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from .contract import WheelKinematics, WheelWrench


class SingleWheelRig:
    """RoverSide of the single-wheel testbed (one wheel, named 'wheel').

    Args:
        mass: vertical load mass, wheel included [kg]; its weight m |g| presses the wheel down.
        radius: rim radius r [m] (for slip).
        omega: wheel angular speed about +Y [rad/s] (> 0 drives towards +X).
        hub: initial hub position [m], shape (3,).
        mode: 'free' (carriage free along X) or 'slip' (carriage driven at v = omega r (1 - slip)).
        slip: the set slip in mode 'slip' [-].
        drawbar_load: constant force resisting the carriage in mode 'free' [N] (0: none).
    """

    wheel_names = ["wheel"]

    def __init__(self, mass: float, radius: float, omega: float, hub: Sequence[float], mode: str = "free",
                 slip: float = 0.0, drawbar_load: float = 0.0, gravity=(0.0, 0.0, -9.81)):
        if mode not in ("free", "slip"):
            raise ValueError(f"testbed.mode must be 'free' or 'slip', got {mode!r}")
        if not (mass > 0 and math.isfinite(mass)):
            raise ValueError(f"testbed.mass must be > 0 [kg], got {mass!r}")
        if not (radius > 0):
            raise ValueError(f"wheel radius must be > 0 [m], got {radius!r}")
        if mode == "slip" and not -1.0 < slip < 1.0:
            raise ValueError(f"testbed.slip must be in (-1, 1), got {slip!r}")
        self.mass = float(mass)
        self.radius = float(radius)
        self.omega = float(omega)
        self.mode = mode
        self.slip = float(slip)
        self.drawbar_load = float(drawbar_load)
        self.gravity = np.asarray(gravity, dtype=np.float64)
        self.position = np.asarray(hub, dtype=np.float64).copy()
        """Hub position [m], shape (3,)."""
        self.velocity = np.zeros(3)
        """Hub velocity [m/s], shape (3,)."""
        if mode == "slip":
            self.velocity[0] = self.omega * self.radius * (1 - self.slip)
        self.angle = 0.0
        """Wheel rotation about +Y [rad]."""
        self.time = 0.0
        self._wrench = WheelWrench()

    def set_gravity(self, gravity) -> None:
        self.gravity = np.asarray(gravity, dtype=np.float64).reshape(3)

    def wheel_kinematics(self) -> list[WheelKinematics]:
        half = 0.5 * self.angle
        return [WheelKinematics(self.position.copy(), [math.cos(half), 0.0, math.sin(half), 0.0],
                                self.velocity.copy(), [0.0, self.omega, 0.0])]

    def apply_wheel_wrenches(self, wrenches: Sequence[WheelWrench]) -> None:
        if len(wrenches) != 1:
            raise ValueError(f"the single-wheel rig has 1 wheel, got {len(wrenches)} wrenches")
        self._wrench = wrenches[0]

    def advance(self, t_end: float) -> None:
        h = float(t_end) - self.time
        if h < 0:
            raise ValueError(f"t_end {t_end!r} s is before the rig's time {self.time!r} s")
        force = self._wrench.force
        # exact for a wrench held constant over the step
        acceleration = np.zeros(3)
        acceleration[2] = force[2] / self.mass + self.gravity[2]
        if self.mode == "free":
            resist = -self.drawbar_load * np.sign(self.velocity[0]) if self.velocity[0] else 0.0
            acceleration[0] = (force[0] + resist) / self.mass + self.gravity[0]
        self.position += self.velocity * h + 0.5 * acceleration * h * h
        self.velocity += acceleration * h
        self.angle += self.omega * h
        self.time = float(t_end)


@dataclass
class SingleWheelResult:
    """Time series of a single-wheel run, one row per macro step (S rows)."""

    time: np.ndarray
    """End time of each macro step [s], shape (S,)."""
    travel: np.ndarray
    """Hub travel along X since the drive started [m], shape (S,)."""
    slip: np.ndarray
    """Slip 1 - v/(omega r) [-], shape (S,)."""
    sinkage: np.ndarray
    """Sinkage of the lowest rim point below the undisturbed surface [m], shape (S,)."""
    drawbar_pull: np.ndarray
    """Soil force on the wheel along +X (macro-step average) [N], shape (S,)."""
    vertical_force: np.ndarray
    """Soil force on the wheel along +Z (macro-step average) [N], shape (S,)."""
    driving_torque: np.ndarray
    """Torque the drive supplies against the soil about +Y [N m], shape (S,)."""
    contact_count: np.ndarray
    """Grains touching the wheel [-], shape (S,)."""
    hub_position: np.ndarray
    """Hub position [m], shape (S, 3)."""
    hub_velocity: np.ndarray
    """Hub velocity [m/s], shape (S, 3)."""
    info: dict = field(default_factory=dict)

    def summary(self, last_fraction: float = 0.5) -> dict:
        """Means over the last part of the run (the steady state) and final values."""
        n = len(self.time)
        tail = slice(int(n * (1 - last_fraction)), n)
        return {
            "simulated_time": float(self.time[-1]) if n else 0.0,
            "travel": float(self.travel[-1]) if n else 0.0,
            "mean_slip": float(np.mean(self.slip[tail])) if n else float("nan"),
            "mean_sinkage": float(np.mean(self.sinkage[tail])) if n else float("nan"),
            "mean_drawbar_pull": float(np.mean(self.drawbar_pull[tail])) if n else float("nan"),
            "mean_driving_torque": float(np.mean(self.driving_torque[tail])) if n else float("nan"),
            **self.info,
        }

    def as_arrays(self) -> dict[str, np.ndarray]:
        return {k: v for k, v in vars(self).items() if isinstance(v, np.ndarray)}


def slip_of(velocity_x: np.ndarray, omega: float, radius: float) -> np.ndarray:
    """Slip s = 1 - v / (omega r) [-]."""
    rim = omega * radius
    if rim == 0:
        return np.zeros_like(np.asarray(velocity_x, dtype=float))
    return 1.0 - np.asarray(velocity_x, dtype=float) / rim


def drive(soil, rig: SingleWheelRig, duration: float, macro_step: float, scheme: str = "gauss-seidel",
          callback=None) -> SingleWheelResult:
    """Couple the DEM soil and the rig for `duration` [s]; returns the time series."""
    from .coupler import Coupler

    rig.time = soil.time  # the rig joins the soil's clock
    coupler = Coupler(soil, rig, macro_step, scheme=scheme, gravity=soil.sim.model.gravity)
    x0 = float(rig.position[0])
    coupler.run(coupler.time + duration, callback=callback)
    rec = coupler.records()
    position = rec["position"][:, 0, :]
    velocity = rec["linear_velocity"][:, 0, :]
    force = rec["force"][:, 0, :]
    torque = rec["torque"][:, 0, :]
    return SingleWheelResult(
        time=rec["time"], travel=position[:, 0] - x0, slip=slip_of(velocity[:, 0], rig.omega, rig.radius),
        sinkage=rec["sinkage"][:, 0], drawbar_pull=force[:, 0], vertical_force=force[:, 2],
        driving_torque=-torque[:, 1], contact_count=rec["contact_count"][:, 0], hub_position=position,
        hub_velocity=velocity,
        info={"coupling_energy_created": coupler.energy_created, "macro_steps": coupler.step_count})
