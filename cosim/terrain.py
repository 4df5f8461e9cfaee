"""Analytic terrain standing in for the DEM soil (a SoilSide for tests and examples).

`SpringDamperTerrain` is flat ground at height z0. Each wheel is a thin disc of radius r
(its spin axis is a body-frame axis, +y by default); the soil touches it at the rim's
lowest point only:

- normal: penalty spring-damper on the penetration delta = z0 - z_contact,
  F_n = max(0, k delta + c d(delta)/dt), only while delta > 0 (no adhesion);
- tangential at the contact point, either
  * 'coulomb': regularized Coulomb, F_t = -mu F_n v_t / sqrt(|v_t|^2 + v_eps^2), or
  * 'slip': a slip-ratio traction law in the wheel's rolling direction,
    F_long = mu F_n sign(s) (1 - exp(-|s| / s0)) with s = (omega r - v) / max(|omega r|, |v|, v_eps)
    (Janosi-Hanamoto shaped, so a held slip s gives a known traction), plus a
    regularized Coulomb force against lateral sliding.

Everything is a smooth, deterministic function of the wheel state, so two rover models
fed the same states get the same wrenches (used to compare MuJoCo with FMU rovers).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from soil.control import quaternion_integrate, quaternion_slerp, quaternion_to_matrix
from soil.errors import ArgumentError, is_real

from .contract import SoilBooks, SoilSideDefaults, WheelKinematics, WheelWrench, wheel_frame

_EZ = np.array([0.0, 0.0, 1.0])


def slip_ratio(v_forward: float, rim_speed: float, v_eps: float) -> float:
    """Longitudinal slip s = (omega r - v) / max(|omega r|, |v|, v_eps) [-].

    Equals the usual driving slip 1 - v / (omega r) when omega r >= v > 0 and the
    braking slip when v > omega r; |s| <= 2, and s = 0 for a wheel rolling freely.
    v_eps [m/s] keeps it finite for a wheel at rest.
    """
    return (rim_speed - v_forward) / max(abs(rim_speed), abs(v_forward), v_eps)


# --- the terrain --------------------------------------------------------------------


WRENCH_SAMPLES = 8
"""The analytic terrain's default wrench samples per macro step (its `substeps`) [-]."""


class SpringDamperTerrain(SoilSideDefaults):
    """Flat analytic ground with a spring-damper normal law and a friction/traction law.

    Implements the SoilSide protocol of cosim.contract (no walls, no particles: a continuum
    whose state is its time and the wheels' poses). Wheels are discs of radius
    `wheel_radius` (one value or one per wheel) whose spin axis is `axis_local` in the
    wheel body frame; the hub is the body frame origin.

    Within a macro step the wheel motion is interpolated between `start` and `end`
    kinematics (or extrapolated at constant velocity from `start`), the wrench is sampled
    at the midpoints of `substeps` equal sub-intervals and averaged.
    """

    def __init__(
        self,
        wheel_radius: float | Sequence[float],
        wheel_count: int,
        stiffness: float = 2.0e4,
        damping: float = 500.0,
        friction: float = 0.6,
        traction: str = "coulomb",
        slip_scale: float = 0.1,
        slip_velocity: float = 1.0e-3,
        z0: float = 0.0,
        axis_local: Sequence[float] = (0.0, 1.0, 0.0),
        substeps: int = WRENCH_SAMPLES,
        time: float = 0.0,
    ):
        if traction not in ("coulomb", "slip"):
            raise ArgumentError(f"traction must be 'coulomb' or 'slip', got {traction!r}")
        # a negative stiffness let the rover fall through the ground, a negative friction pushed it on
        for name, value, strict, unit in (
            ("stiffness", stiffness, True, "N/m"),
            ("damping", damping, False, "N s/m"),
            ("friction", friction, False, "-"),
            ("slip_scale", slip_scale, True, "-"),
            ("slip_velocity", slip_velocity, True, "m/s"),
        ):
            if not is_real(value) or not np.isfinite(value) or value < 0 or (strict and value == 0):
                raise ArgumentError(
                    f"{name} must be a finite number {'>' if strict else '>='} 0 [{unit}], got {value!r}"
                )
        if isinstance(substeps, bool) or not isinstance(substeps, (int, np.integer)) or substeps < 1:
            raise ArgumentError(f"substeps must be a whole number >= 1, got {substeps!r}")
        self.wheel_count = int(wheel_count)
        self.wheel_radius = np.broadcast_to(np.asarray(wheel_radius, dtype=np.float64), (self.wheel_count,)).copy()
        """Wheel radii [m], shape (wheel_count,)."""
        self.stiffness = float(stiffness)
        """Normal penalty stiffness per wheel [N/m]."""
        self.damping = float(damping)
        """Normal damping per wheel [N s/m]."""
        self.friction = float(friction)
        """Friction / traction coefficient mu [-]."""
        self.traction = traction
        """'coulomb' (regularized Coulomb on the contact slip velocity) or 'slip' (slip-ratio law)."""
        self.slip_scale = float(slip_scale)
        """Slip s0 at which the 'slip' law reaches 63% of mu F_n [-]."""
        self.slip_velocity = float(slip_velocity)
        """Regularisation velocity v_eps of the friction laws [m/s]."""
        self.z0 = float(z0)
        """Ground height [m]."""
        self.axis_local = np.asarray(axis_local, dtype=np.float64) / np.linalg.norm(axis_local)
        """Wheel spin axis in the wheel body frame [-], shape (3,)."""
        self.substeps = int(substeps)
        """Wrench samples per macro step [-]."""
        self.time = float(time)
        """Current soil time [s]."""
        self.gravity = np.array([0.0, 0.0, -9.81])
        """Scene gravity [m/s^2], shape (3,). Kept for the contract; the analytic ground needs none."""
        self._hub_position = np.zeros((self.wheel_count, 3))
        self._hub_rotation = np.tile(np.eye(3), (self.wheel_count, 1, 1))

    def set_gravity(self, gravity: Sequence[float]) -> None:
        self.gravity = np.asarray(gravity, dtype=np.float64).reshape(3).copy()

    @property
    def surface_height(self) -> float:
        """The ground's height z0 [m]."""
        return self.z0

    def static_sinkage(self, load: float) -> float:
        """Sinkage [m] of a wheel at rest under a vertical load [N]: the spring's load / stiffness."""
        return float(load) / self.stiffness

    def place_wheels(self, kinematics: Sequence[WheelKinematics]) -> None:
        for i, k in enumerate(kinematics):
            self._set_pose(i, k.position, k.orientation)

    def wheel_poses(self) -> tuple[np.ndarray, np.ndarray]:
        return self._hub_position.copy(), self._hub_rotation.copy()

    def highest_point_under(self, wheel: int, hub: ArrayLike, axle: ArrayLike = (0.0, 1.0, 0.0)) -> float:
        return self.z0  # flat ground

    def books(self) -> SoilBooks:
        return SoilBooks(element_count=0, mass=0.0)

    def state_dict(self) -> dict:
        """The terrain's time [s] and the wheels' poses (its laws hold no other state)."""
        return {"time": self.time, "hub_position": self._hub_position.copy(), "hub_rotation": self._hub_rotation.copy()}

    def state_dict_units(self) -> dict[str, str]:
        return {"time": "s", "hub_position": "m", "hub_rotation": "1"}

    def load_state_dict(self, data: dict) -> None:
        self.time = float(data["time"])
        self._hub_position = np.array(data["hub_position"], dtype=np.float64)
        self._hub_rotation = np.array(data["hub_rotation"], dtype=np.float64)

    def _set_pose(self, wheel: int, position, orientation) -> None:
        self._hub_position[wheel] = position
        self._hub_rotation[wheel] = quaternion_to_matrix(orientation)

    # The contact law at one instant ------------------------------------------------

    def contact(self, i: int, position, orientation, velocity, omega) -> tuple[np.ndarray, np.ndarray, float]:
        """Force [N] and torque about the hub [N m] (world, shape (3,) each) and sinkage [m] of wheel i."""
        r = self.wheel_radius[i]
        axis, forward = wheel_frame(orientation, self.axis_local)
        # Lowest rim point: from the hub, the direction of -z projected onto the wheel plane.
        down = -_EZ + axis[2] * axis
        norm = np.linalg.norm(down)
        down = down / norm if norm > 1e-9 else -_EZ
        arm = r * down
        contact_point = position + arm
        delta = self.z0 - contact_point[2]
        if delta <= 0.0:
            return np.zeros(3), np.zeros(3), 0.0
        v_contact = velocity + np.cross(omega, arm)
        f_n = max(0.0, self.stiffness * delta - self.damping * v_contact[2])
        v_t = np.array([v_contact[0], v_contact[1], 0.0])
        eps = self.slip_velocity
        if self.traction == "coulomb" or not forward.any():
            f_t = -self.friction * f_n * v_t / np.sqrt(v_t @ v_t + eps * eps)
        else:
            lateral = np.cross(_EZ, forward)
            s = slip_ratio(velocity @ forward, (omega @ axis) * r, eps)
            f_long = self.friction * f_n * np.sign(s) * (1.0 - np.exp(-abs(s) / self.slip_scale))
            v_lat = v_t @ lateral
            f_lat = -self.friction * f_n * v_lat / np.sqrt(v_lat * v_lat + eps * eps)
            f_t = f_long * forward + f_lat * lateral
        force = f_t + f_n * _EZ
        return force, np.cross(arm, force), delta

    # SoilSide ---------------------------------------------------------------------------

    def advance(
        self,
        t_end: float,
        start: Sequence[WheelKinematics],
        end: Sequence[WheelKinematics] | None = None,
    ) -> list[WheelWrench]:
        if len(start) != self.wheel_count or (end is not None and len(end) != self.wheel_count):
            raise ArgumentError(f"expected kinematics of {self.wheel_count} wheels, got {len(start)}")
        span = float(t_end) - self.time
        if span <= 0.0:
            raise ArgumentError(f"t_end={t_end} must be after the soil time {self.time}")
        h = span / self.substeps
        out = []
        for i, k0 in enumerate(start):
            k1 = None if end is None else end[i]
            force_sum = np.zeros(3)
            torque_sum = np.zeros(3)
            work_on_wheel = 0.0
            for j in range(self.substeps):
                state = self._state_at(k0, k1, (j + 0.5) * h, span)
                f, tau, _ = self.contact(i, *state)
                force_sum += f
                torque_sum += tau
                # Power into the wheel: F . v_hub + tau_hub . omega.
                work_on_wheel += (f @ state[2] + tau @ state[3]) * h
            at_end = self._state_at(k0, k1, span, span)
            f_end, tau_end, sinkage = self.contact(i, *at_end)
            self._set_pose(i, at_end[0], at_end[1])
            out.append(
                WheelWrench(
                    force=force_sum / self.substeps,
                    torque=torque_sum / self.substeps,
                    force_end=f_end,
                    torque_end=tau_end,
                    contact_count=int(sinkage > 0.0),
                    sinkage=sinkage,
                    work_on_soil=-work_on_wheel,
                )
            )
        self.time = float(t_end)
        return out

    @staticmethod
    def _state_at(k0: WheelKinematics, k1: WheelKinematics | None, tau: float, span: float):
        """Wheel (position, orientation, velocity, omega) at tau [s] into the macro step."""
        if k1 is None:
            return (
                k0.position + k0.linear_velocity * tau,
                quaternion_integrate(k0.orientation, k0.angular_velocity, tau),
                k0.linear_velocity,
                k0.angular_velocity,
            )
        a = tau / span
        return (
            (1 - a) * k0.position + a * k1.position,
            quaternion_slerp(k0.orientation, k1.orientation, a),
            (1 - a) * k0.linear_velocity + a * k1.linear_velocity,
            (1 - a) * k0.angular_velocity + a * k1.angular_velocity,
        )
