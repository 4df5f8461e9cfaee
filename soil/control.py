"""Control: what the user prescribes from outside the soil."""

from __future__ import annotations

import numpy as np
import warp as wp


def quaternion_to_matrix(q) -> np.ndarray:
    """Rotation matrix (body -> world), shape (3, 3), of a unit quaternion (w, x, y, z)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


class SoilControl:
    """External inputs of a step: extra particle forces and the prescribed motion of bodies (wheels).

    Body motion is set on the host with `set_body_motion` and sent to the device by
    `push()` (the Simulation pushes before each step when something changed).
    """

    def __init__(self, particle_count: int, vec_hi, device: str, body_count: int = 0):
        self.external_force = wp.zeros(particle_count, dtype=vec_hi, device=device)
        """Extra force on each particle [N], shape (particle_count,); zero by default."""
        scalar = vec_hi._wp_scalar_type_
        mat_hi = wp.types.matrix((3, 3), scalar)
        self.body_position_host = np.zeros((body_count, 3))
        """Hub position of each body, world [m], shape (body_count, 3) (host copy)."""
        self.body_rotation_host = np.tile(np.eye(3), (body_count, 1, 1))
        """Rotation body -> world of each body [-], shape (body_count, 3, 3) (host copy)."""
        self.body_velocity_host = np.zeros((body_count, 3))
        """Velocity of each hub, world [m/s], shape (body_count, 3) (host copy)."""
        self.body_angular_velocity_host = np.zeros((body_count, 3))
        """Angular velocity of each body, world [rad/s], shape (body_count, 3) (host copy)."""
        self.body_position = wp.zeros(body_count, dtype=vec_hi, device=device)
        """Device copy of body_position_host [m], shape (body_count,)."""
        self.body_rotation = wp.zeros(body_count, dtype=mat_hi, device=device)
        """Device copy of body_rotation_host [-], shape (body_count,)."""
        self.body_velocity = wp.zeros(body_count, dtype=vec_hi, device=device)
        """Device copy of body_velocity_host [m/s], shape (body_count,)."""
        self.body_angular_velocity = wp.zeros(body_count, dtype=vec_hi, device=device)
        """Device copy of body_angular_velocity_host [rad/s], shape (body_count,)."""
        self._dirty = body_count > 0

    @property
    def body_count(self) -> int:
        return len(self.body_position_host)

    def set_body_motion(self, body: int, position=None, orientation=None, velocity=None, angular_velocity=None,
                        rotation=None) -> None:
        """Prescribe a body's pose and velocity: position [m] (3,), orientation quaternion
        (w, x, y, z) or rotation matrix (3, 3), velocity [m/s] (3,), angular velocity [rad/s] (3,)."""
        if not 0 <= body < self.body_count:
            raise IndexError(f"body index must be in [0, {self.body_count}), got {body}")
        if position is not None:
            self.body_position_host[body] = position
        if orientation is not None:
            self.body_rotation_host[body] = quaternion_to_matrix(orientation)
        if rotation is not None:
            self.body_rotation_host[body] = rotation
        if velocity is not None:
            self.body_velocity_host[body] = velocity
        if angular_velocity is not None:
            self.body_angular_velocity_host[body] = angular_velocity
        self._dirty = True

    def push(self) -> None:
        """Send the host body motion to the device (only when it changed)."""
        if not self._dirty:
            return
        dtype = self.body_position.dtype._wp_scalar_type_
        np_type = np.float64 if dtype is wp.float64 else np.float32
        self.body_position.assign(self.body_position_host.astype(np_type))
        self.body_rotation.assign(self.body_rotation_host.astype(np_type))
        self.body_velocity.assign(self.body_velocity_host.astype(np_type))
        self.body_angular_velocity.assign(self.body_angular_velocity_host.astype(np_type))
        self._dirty = False

    def state_dict(self) -> dict:
        """The prescribed body motion (host copies), numpy arrays."""
        return {name: getattr(self, name).copy() for name in ("body_position_host", "body_rotation_host",
                                                               "body_velocity_host", "body_angular_velocity_host")}

    def load_state_dict(self, data: dict) -> None:
        for name, value in data.items():
            getattr(self, name)[...] = value
        self._dirty = True
        self.push()
