"""Control: what the user prescribes from outside the soil."""

from __future__ import annotations

import numpy as np
import warp as wp

from .boundaries import MOTION_LOADED, MOTION_PRESCRIBED


def quaternion_to_matrix(q) -> np.ndarray:
    """Rotation matrix (body -> world), shape (3, 3), of a unit quaternion (w, x, y, z)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


class SoilControl:
    """External inputs of a step: extra particle forces, the prescribed motion of bodies
    (wheels) and the motion of boundaries (walls, boxes: prescribed velocity or a load).

    Motion is set on the host (`set_body_motion`, `set_boundary_velocity`,
    `set_boundary_load`) and sent to the device by `push()`; the Simulation pushes before
    each force evaluation when something changed, never inside a step's kernels.
    """

    def __init__(self, particle_count: int, vec_hi, device: str, body_count: int = 0, boundary_count: int = 0,
                 boundary_reports=None):
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

        nb = boundary_count
        self.boundary_reports = (np.ones(nb, dtype=bool) if boundary_reports is None
                                 else np.asarray(boundary_reports, dtype=bool).reshape(nb))
        """Whether each boundary's grain force is summed (model.boundary_reports), shape (boundary_count,)."""
        self.boundary_mode_host = np.zeros(nb, dtype=np.int32)
        """MOTION_PRESCRIBED or MOTION_LOADED per boundary (soil.boundaries), shape (boundary_count,) (host copy)."""
        self.boundary_velocity_host = np.zeros((nb, 3))
        """Prescribed translation velocity of each boundary [m/s], shape (boundary_count, 3) (host copy);
        a loaded boundary takes only its part across the free direction."""
        self.boundary_direction_host = np.zeros((nb, 3))
        """Unit free direction of each loaded boundary [-], shape (boundary_count, 3) (host copy)."""
        self.boundary_mass_host = np.zeros(nb)
        """Mass of each loaded boundary [kg], shape (boundary_count,) (host copy)."""
        self.boundary_load_host = np.zeros(nb)
        """Applied force on each loaded boundary along its direction [N], shape (boundary_count,) (host copy)."""
        self.boundary_damping_host = np.zeros(nb)
        """Linear damper of each loaded boundary along its direction [N s/m], shape (boundary_count,) (host copy)."""
        self.boundary_mode = wp.zeros(nb, dtype=wp.int32, device=device)
        """Device copy of boundary_mode_host, shape (boundary_count,), int32."""
        self.boundary_velocity = wp.zeros(nb, dtype=vec_hi, device=device)
        """Device copy of boundary_velocity_host [m/s], shape (boundary_count,)."""
        self.boundary_direction = wp.zeros(nb, dtype=vec_hi, device=device)
        """Device copy of boundary_direction_host [-], shape (boundary_count,)."""
        self.boundary_mass = wp.zeros(nb, dtype=scalar, device=device)
        """Device copy of boundary_mass_host [kg], shape (boundary_count,)."""
        self.boundary_load = wp.zeros(nb, dtype=scalar, device=device)
        """Device copy of boundary_load_host [N], shape (boundary_count,)."""
        self.boundary_damping = wp.zeros(nb, dtype=scalar, device=device)
        """Device copy of boundary_damping_host [N s/m], shape (boundary_count,)."""
        self._dirty = body_count > 0 or nb > 0  # host copies changed since the last push()

    @classmethod
    def for_model(cls, model) -> "SoilControl":
        """A control sized for `model`: no external forces, bodies at the origin, boundaries fixed."""
        return cls(model.particle_count, model.precision.vec_hi, model.device, model.body_count,
                   model.boundary_count, model.boundary_reports)

    @property
    def body_count(self) -> int:
        return len(self.body_position_host)

    @property
    def boundary_count(self) -> int:
        return len(self.boundary_mode_host)

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

    # -- boundaries --------------------------------------------------------------------
    def _boundary_indices(self, boundaries) -> np.ndarray:
        indices = np.atleast_1d(np.asarray(boundaries))
        if indices.ndim != 1 or not np.issubdtype(indices.dtype, np.integer):
            raise TypeError(f"boundaries must be a boundary index or a sequence of indices, got {boundaries!r}")
        bad = (indices < 0) | (indices >= self.boundary_count)
        if bad.any():
            raise IndexError(f"boundary index must be in [0, {self.boundary_count}), got {indices[bad].tolist()}")
        return indices

    def set_boundary_velocity(self, boundaries, velocity) -> None:
        """Prescribe the translation velocity [m/s], shape (3,), of one boundary (an index) or of
        several moved together (a sequence of indices).

        Their geometry advances by velocity * dt on the device every step, and the contact law
        sees the wall's velocity. A loaded boundary (set_boundary_load) keeps its load along
        its free direction and takes only the velocity's part across it.
        """
        indices = self._boundary_indices(boundaries)
        velocity = np.asarray(velocity, dtype=np.float64)
        if velocity.shape != (3,) or not np.all(np.isfinite(velocity)):
            raise ValueError(f"boundary velocity must be a finite 3-vector [m/s], got {velocity!r}")
        self.boundary_velocity_host[indices] = velocity
        self._dirty = True

    def set_boundary_load(self, boundary: int, load: float, direction=None, mass: float | None = None,
                          damping: float | None = None) -> None:
        """Make a boundary a rigid body free along a unit `direction`, pushed by `load` [N]:

            mass * a = load + F_grains . direction - damping * v . direction

        direction: 3-vector (normalised here) [-]; mass [kg] > 0; damping [N s/m] >= 0
        (default 0). direction and mass are needed the first time; later calls may change
        the load alone (a ramp, a servo set point). A plane lid pressing down on a bed:
        direction (0, 0, -1), load = the normal force it should carry. Each loaded boundary
        is a body of its own (boundaries do not share a load). The boundary must report its
        force (built with report=True).
        """
        (index,) = self._boundary_indices(boundary)
        if not self.boundary_reports[index]:
            raise ValueError(f"boundary {index} was built with report=False: a loaded boundary needs its grain "
                             "force (build it with report=True)")
        loaded = self.boundary_mode_host[index] == MOTION_LOADED
        if direction is None and not loaded:
            raise ValueError(f"boundary {index} is not loaded yet: give its free direction (a 3-vector)")
        if mass is None and not loaded:
            raise ValueError(f"boundary {index} is not loaded yet: give its mass [kg]")
        load = float(load)
        if not np.isfinite(load):
            raise ValueError(f"boundary load must be finite [N], got {load!r}")
        if direction is not None:
            direction = np.asarray(direction, dtype=np.float64)
            length = np.linalg.norm(direction) if direction.shape == (3,) else np.nan
            if not (np.isfinite(length) and length > 0):
                raise ValueError(f"boundary direction must be a non-zero finite 3-vector, got {direction!r}")
            self.boundary_direction_host[index] = direction / length
        if mass is not None:
            if not (np.isfinite(mass) and mass > 0):
                raise ValueError(f"boundary mass must be finite and > 0 [kg], got {mass!r}")
            self.boundary_mass_host[index] = mass
        if damping is not None:
            if not (np.isfinite(damping) and damping >= 0):
                raise ValueError(f"boundary damping must be finite and >= 0 [N s/m], got {damping!r}")
            self.boundary_damping_host[index] = damping
        self.boundary_load_host[index] = load
        self.boundary_mode_host[index] = MOTION_LOADED
        self._dirty = True

    def remove_boundary_load(self, boundaries) -> None:
        """End the load control of one or several boundaries: they move with their prescribed
        velocity again (set_boundary_velocity; zero unless set)."""
        indices = self._boundary_indices(boundaries)
        self.boundary_mode_host[indices] = MOTION_PRESCRIBED
        self._dirty = True

    def push(self) -> None:
        """Send the host motion to the device (only when it changed)."""
        if not self._dirty:
            return
        dtype = self.body_position.dtype._wp_scalar_type_
        np_type = np.float64 if dtype is wp.float64 else np.float32
        if self.body_count:
            self.body_position.assign(self.body_position_host.astype(np_type))
            self.body_rotation.assign(self.body_rotation_host.astype(np_type))
            self.body_velocity.assign(self.body_velocity_host.astype(np_type))
            self.body_angular_velocity.assign(self.body_angular_velocity_host.astype(np_type))
        if self.boundary_count:
            self.boundary_mode.assign(self.boundary_mode_host)
            self.boundary_velocity.assign(self.boundary_velocity_host.astype(np_type))
            self.boundary_direction.assign(self.boundary_direction_host.astype(np_type))
            self.boundary_mass.assign(self.boundary_mass_host.astype(np_type))
            self.boundary_load.assign(self.boundary_load_host.astype(np_type))
            self.boundary_damping.assign(self.boundary_damping_host.astype(np_type))
        self._dirty = False

    # -- checkpoints -------------------------------------------------------------------
    _HOST = ("body_position", "body_rotation", "body_velocity", "body_angular_velocity", "boundary_mode",
             "boundary_velocity", "boundary_direction", "boundary_mass", "boundary_load", "boundary_damping")

    def state_dict(self) -> dict:
        """The control as numpy arrays: the host copies of body and boundary motion (names
        without _host) and external_force [N] (particle_count, 3)."""
        data = {name: getattr(self, f"{name}_host").copy() for name in self._HOST}
        data["external_force"] = self.external_force.numpy().copy()  # a view on the CPU otherwise
        return data

    def load_state_dict(self, data: dict) -> None:
        """Restore from state_dict(); the device copies follow at the next push()."""
        for name in self._HOST:
            target = getattr(self, f"{name}_host")
            values = np.asarray(data[name])
            if values.shape != target.shape:
                raise ValueError(f"control.{name}: saved shape {values.shape} does not fit {target.shape}")
            target[...] = values
        force = np.asarray(data["external_force"])
        if force.shape[0] != self.external_force.shape[0]:
            raise ValueError(f"control.external_force: saved {force.shape[0]} particles, the model has "
                             f"{self.external_force.shape[0]}")
        self.external_force.assign(force.astype(self.external_force.numpy().dtype, copy=False))
        self._dirty = True
