"""Control: what the user prescribes from outside the soil, and the wheels' paths on the device."""

import numpy as np
import warp as wp

from .boundaries import MOTION_LOADED
from .errors import SoilInputError
from .precision import kernel_factory, kernel_module, soil_kernel

PATH_COLUMNS = 28
"""Columns of a body path row: start position [m] (3), orientation (w, x, y, z) [-] (4), velocity [m/s]
(3), angular velocity [rad/s] (3), the same at the end (13), span [s] (1), 1 if the end is given [-] (1)."""


def quaternion_multiply(a, b) -> np.ndarray:
    """Hamilton product a b of quaternions (w, x, y, z)."""
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def quaternion_integrate(q, omega, dt: float) -> np.ndarray:
    """Rotate q (body -> world) by a constant world-frame angular velocity omega [rad/s] for dt [s]."""
    omega = np.asarray(omega, dtype=np.float64)
    rate = np.linalg.norm(omega)
    angle = float(rate) * dt
    if angle < 1e-15:
        return np.array(q, dtype=np.float64)
    axis = omega / rate
    sine = np.sin(angle / 2)
    turn = np.array([np.cos(angle / 2), sine * axis[0], sine * axis[1], sine * axis[2]])
    turned = quaternion_multiply(turn, q)  # world frame: from the left
    return turned / np.linalg.norm(turned)


def quaternion_slerp(q0, q1, a: float) -> np.ndarray:
    """Spherical interpolation between unit quaternions, a in [0, 1] (the short way round)."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        out = q0 + a * (q1 - q0)
        return out / np.linalg.norm(out)
    theta = np.arccos(dot)
    return (np.sin((1 - a) * theta) * q0 + np.sin(a * theta) * q1) / np.sin(theta)


def _finite(value, shape: tuple[int, ...], what: str) -> np.ndarray:
    """`value` as a float64 array of `shape`; SoilInputError naming `what` when it has another shape or a
    value that is not a finite real number."""
    try:
        raw = np.asarray(value)
    except ValueError:  # ragged
        raw = np.asarray(None)
    array = raw.astype(np.float64) if raw.dtype.kind in "iuf" else None  # no complex, boolean or text
    if array is None or array.shape != shape or not np.all(np.isfinite(array)):
        raise SoilInputError(f"{what} must be finite real numbers of shape {shape}, got {value!r}")
    return array


PATH_NAMES = ("position [m]", "orientation quaternion (w, x, y, z)", "velocity [m/s]", "angular velocity [rad/s]")
PATH_WIDTHS = (3, 4, 3, 3)


def checked_body_path(count: int, position, orientation, velocity, angular_velocity, end=None, what: str = "the path"):
    """set_body_path's arrays for `count` bodies as float64 arrays: (start, finish), finish None when `end`
    is; SoilInputError naming the array when one has another shape, a value that is not a finite real
    number, or an orientation that is no unit quaternion."""
    start = [
        _finite(a, (count, width), f"{what}'s start {name}")
        for a, width, name in zip((position, orientation, velocity, angular_velocity), PATH_WIDTHS, PATH_NAMES)
    ]
    if end is not None and (not isinstance(end, (tuple, list)) or len(end) != 4):
        raise SoilInputError(f"{what}'s end is None or (position, orientation, velocity, angular velocity)")
    finish = (
        None
        if end is None
        else [
            _finite(a, (count, width), f"{what}'s end {name}") for a, width, name in zip(end, PATH_WIDTHS, PATH_NAMES)
        ]
    )
    for which, arrays in (("start", start), ("end", finish)):
        if arrays is None:
            continue
        norms = np.linalg.norm(arrays[1], axis=1)
        if not np.all((norms > 0.5) & (norms < 2.0)):
            body = int(np.argmax(~((norms > 0.5) & (norms < 2.0))))
            raise SoilInputError(
                f"body {body}'s orientation at {what}'s {which} must be a unit quaternion (w, x, y, z), "
                f"got {arrays[1][body].tolist()}"
            )
    return start, finish


def quaternion_to_matrix(q) -> np.ndarray:
    """Rotation matrix (body -> world), shape (3, 3), of a unit quaternion (w, x, y, z)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


@kernel_factory
def path_kernels(hi):
    """The body-path kernels for the precision type `hi`."""
    kernel = soil_kernel(kernel_module("path", hi))
    vec_hi = wp.types.vector(3, hi)
    vec4_hi = wp.types.vector(4, hi)
    mat_hi = wp.types.matrix((3, 3), hi)

    @wp.func
    def quaternion_product(a: vec4_hi, b: vec4_hi):
        """Hamilton product a b of quaternions (w, x, y, z)."""
        return vec4_hi(
            a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
            a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
            a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
            a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
        )

    @wp.func
    def rotation_of(q: vec4_hi):
        """Rotation matrix (body -> world) of a unit quaternion (w, x, y, z)."""
        q = q / wp.length(q)
        w, x, y, z = q[0], q[1], q[2], q[3]
        one, two = hi(1.0), hi(2.0)
        return mat_hi(
            one - two * (y * y + z * z),
            two * (x * y - w * z),
            two * (x * z + w * y),
            two * (x * y + w * z),
            one - two * (x * x + z * z),
            two * (y * z - w * x),
            two * (x * z - w * y),
            two * (y * z + w * x),
            one - two * (x * x + y * y),
        )

    @kernel
    def follow_path(
        path: wp.array2d(dtype=hi),
        step: wp.array(dtype=wp.int32),
        step_length: wp.array(dtype=hi),
        tau_in: wp.array(dtype=hi),
        timed: int,
        bodies_per_world: int,
        position_out: wp.array(dtype=vec_hi),
        rotation_out: wp.array(dtype=mat_hi),
        velocity_out: wp.array(dtype=vec_hi),
        angular_velocity_out: wp.array(dtype=vec_hi),
    ):
        """Pose and velocities of body b at the end of the path's next step, tau = (step + 1) dt
        (fixed steps) or tau_in (timed != 0: variable steps):
        constant velocities from the start, or interpolated towards the end pose (the same
        rules as soil.control.quaternion_integrate / quaternion_slerp on the host)."""
        b = wp.tid()
        world = b // bodies_per_world  # type: ignore[operator]  # b: a Warp int (wp.tid)
        tau = hi(step[0] + 1) * step_length[world]
        if timed != 0:  # variable steps: the time since the path's start, kept by each world's step control
            tau = tau_in[world]
        p0 = vec_hi(path[b, 0], path[b, 1], path[b, 2])
        q0 = vec4_hi(path[b, 3], path[b, 4], path[b, 5], path[b, 6])
        v0 = vec_hi(path[b, 7], path[b, 8], path[b, 9])
        w0 = vec_hi(path[b, 10], path[b, 11], path[b, 12])
        position = p0 + v0 * tau
        orientation = q0
        velocity = v0
        spin = w0
        if path[b, 27] > hi(0.0):
            a = tau / path[b, 26]
            p1 = vec_hi(path[b, 13], path[b, 14], path[b, 15])
            q1 = vec4_hi(path[b, 16], path[b, 17], path[b, 18], path[b, 19])
            velocity = (hi(1.0) - a) * v0 + a * vec_hi(path[b, 20], path[b, 21], path[b, 22])
            spin = (hi(1.0) - a) * w0 + a * vec_hi(path[b, 23], path[b, 24], path[b, 25])
            position = (hi(1.0) - a) * p0 + a * p1
            dot = wp.dot(q0, q1)
            if dot < hi(0.0):
                q1 = -q1
                dot = -dot
            if dot > hi(0.9995):
                orientation = q0 + a * (q1 - q0)
                orientation = orientation / wp.length(orientation)
            else:
                theta = wp.acos(dot)
                orientation = (wp.sin((hi(1.0) - a) * theta) * q0 + wp.sin(a * theta) * q1) / wp.sin(theta)
        else:
            angle = wp.length(w0) * tau
            if angle >= hi(1.0e-15):
                axis = w0 / wp.length(w0)
                half = hi(0.5) * angle
                turn = vec4_hi(wp.cos(half), wp.sin(half) * axis[0], wp.sin(half) * axis[1], wp.sin(half) * axis[2])
                orientation = quaternion_product(turn, q0)
                orientation = orientation / wp.length(orientation)
        position_out[b] = position
        rotation_out[b] = rotation_of(orientation)
        velocity_out[b] = velocity
        angular_velocity_out[b] = spin

    @kernel
    def next_step(step: wp.array(dtype=wp.int32)):
        """Count a step of the path."""
        step[0] = step[0] + 1

    return dict(follow_path=follow_path, next_step=next_step, rotation_of=rotation_of)


class SoilControl:
    """External inputs of a step: extra particle forces, the prescribed motion of bodies
    (wheels: a pose held, or a path over a macro step) and of boundaries (walls, boxes:
    prescribed velocity or a load).

    Motion is set on the host (`set_body_motion`, `set_body_path`, `set_boundary_velocity`,
    `set_boundary_load`) and sent to the device by `push()`; the Simulation pushes before
    each force evaluation when something changed, never inside a step's kernels. The bodies'
    pose and velocity themselves live in the state (SoilState.body_*): push() writes a held
    pose there, and a path poses them there at every step; the control keeps host copies of
    what it prescribed (body_*_host).
    """

    def __init__(
        self,
        particle_count: int,
        vec_hi,
        device: str,
        body_count: int = 0,
        boundary_count: int = 0,
        boundary_reports=None,
    ):
        self.external_force = wp.zeros(particle_count, dtype=vec_hi, device=device)
        """Extra force on each particle [N], shape (particle_count,); zero by default."""
        scalar = vec_hi._wp_scalar_type_
        self.body_position_host = np.zeros((body_count, 3))
        """Hub position of each body, world [m], shape (body_count, 3) (host copy)."""
        self.body_rotation_host = np.tile(np.eye(3), (body_count, 1, 1))
        """Rotation body -> world of each body [-], shape (body_count, 3, 3) (host copy)."""
        self.body_velocity_host = np.zeros((body_count, 3))
        """Velocity of each hub, world [m/s], shape (body_count, 3) (host copy)."""
        self.body_angular_velocity_host = np.zeros((body_count, 3))
        """Angular velocity of each body, world [rad/s], shape (body_count, 3) (host copy)."""
        self.body_posed_host = np.zeros(body_count, dtype=np.int32)
        """1 once a body has been posed (set_body_motion with a position, or set_body_path), else 0 [-],
        shape (body_count,), int32 (host copy). A body not yet posed touches nothing: its placeholder
        pose (the origin) may lie inside the grains, whose forces would then be computed with it."""
        self._scalar = scalar

        nb = boundary_count
        self.boundary_reports = (
            np.ones(nb, dtype=bool)
            if boundary_reports is None
            else np.asarray(boundary_reports, dtype=bool).reshape(nb)
        )
        """Whether each boundary's grain force is summed (model.boundary_reports) [-], shape (boundary_count,)."""
        self.boundary_mode_host = np.zeros(nb, dtype=np.int32)
        """MOTION_PRESCRIBED or MOTION_LOADED per boundary (soil.boundaries) [-], shape (boundary_count,) (host
        copy)."""
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
        """Device copy of boundary_mode_host [-], shape (boundary_count,), int32."""
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
        self.external_force_used = False
        """Whether external_force is applied (set_external_force); when False the kernels skip it."""
        self.body_path = wp.zeros((body_count, PATH_COLUMNS), dtype=scalar, device=device)
        """The bodies' path over a macro step (set_body_path), each column in its unit (PATH_COLUMNS), shape
        (body_count, PATH_COLUMNS), on the device."""
        self.path_step = wp.zeros(1, dtype=wp.int32, device=device)
        """Steps taken along the path so far [-], shape (1,), int32 (counted on the device)."""
        self.path_active = False
        """True while the bodies follow body_path (the steps then pose them on the device)."""
        self._dirty = body_count > 0 or nb > 0  # host copies changed since the last push()
        self._posed_dirty = False  # body_posed_host changed by a path (sent at the next push())

    @classmethod
    def for_model(cls, model) -> "SoilControl":
        """A control sized for `model`: no external forces, bodies not yet posed (at the origin,
        touching nothing), boundaries fixed."""
        return cls(
            model.particle_count,
            model.precision.vec_hi,
            model.device,
            model.body_count,
            model.boundary_count,
            model.boundary_reports,
        )

    @property
    def body_count(self) -> int:
        return len(self.body_position_host)

    @property
    def boundary_count(self) -> int:
        return len(self.boundary_mode_host)

    def set_external_force(self, force) -> None:
        """Extra force on every particle [N], shape (particle_count, 3), model order (None: none)."""
        if force is None:
            self.external_force.zero_()
            self.external_force_used = False
            return
        force = np.asarray(force, dtype=np.float64)
        if force.shape != tuple(self.external_force.shape) + (3,) or not np.all(np.isfinite(force)):
            raise SoilInputError(
                f"external force must be finite, shape ({self.external_force.shape[0]}, 3) [N], got shape {force.shape}"
            )
        self.external_force.assign(force.astype(self.external_force.numpy().dtype))
        self.external_force_used = bool(np.any(force))

    def set_body_path(self, span: float, position, orientation, velocity, angular_velocity, end=None) -> None:
        """Let every body follow a path over the next `span` [s], posed on the device at each step:
        with constant velocity and angular velocity from the start pose (end None), or
        interpolated towards `end` = (position, orientation, velocity, angular_velocity) (linear,
        orientation by slerp). Arrays: position [m] (body_count, 3), orientation quaternion
        (w, x, y, z) (body_count, 4), velocity [m/s] (body_count, 3), angular velocity [rad/s]
        (body_count, 3), world frame. One copy to the device; the host copies of the motion
        (body_*_host) are set to the path's end. Ends with set_body_motion or clear_body_path.
        """
        count = self.body_count
        start, finish = checked_body_path(count, position, orientation, velocity, angular_velocity, end)
        if finish is None:
            finish = start
        rows = np.zeros((count, PATH_COLUMNS))
        rows[:, :13] = np.hstack(start)
        rows[:, 13:26] = np.hstack(finish)
        rows[:, 26] = span
        rows[:, 27] = 0.0 if end is None else 1.0
        self.body_path.assign(rows.astype(np.float64 if self.body_path.dtype is wp.float64 else np.float32))
        self.path_step.zero_()
        self.path_active = True
        if not self.body_posed_host.all():  # the first path poses the bodies (one copy, once)
            self.body_posed_host[:] = 1
            self._posed_dirty = True
        for b in range(count):
            p0, q0, v0, w0 = (part[b] for part in start)
            if end is None:
                pose = (p0 + v0 * span, quaternion_integrate(q0, w0, span), v0, w0)
            else:
                pose = tuple(part[b] for part in finish)
            self.body_position_host[b] = pose[0]
            self.body_rotation_host[b] = quaternion_to_matrix(pose[1])
            self.body_velocity_host[b] = pose[2]
            self.body_angular_velocity_host[b] = pose[3]

    def clear_body_path(self) -> None:
        """Stop following the path: the device poses are the host copies again (at the next push)."""
        self.path_active = False
        self._dirty = True

    def follow_path(self, state, dt: wp.array, tau: wp.array | None = None) -> None:
        """Pose the bodies of `state` (a SoilState, the step's output) for the end of the path's next
        step (on the device; capturable): of length dt[w] [s] after `path_step` steps, or, with
        `tau`, at tau[w] [s] after the path's start (variable steps), w the body's world. Both arrays
        hold one value per world (soil.worlds; one for a scene alone) of the path's precision."""
        kernels = path_kernels(self.body_path.dtype)
        wp.launch(
            kernels.follow_path,
            dim=self.body_count,
            inputs=[
                self.body_path,
                self.path_step,
                dt,
                dt if tau is None else tau,
                int(tau is not None),
                max(self.body_count // dt.shape[0], 1),  # dt: one value per world
            ],
            outputs=[state.body_position, state.body_rotation, state.body_velocity, state.body_angular_velocity],
            device=self.body_path.device,
        )

    def count_path_step(self) -> None:
        """Count the step just taken along the path (on the device; capturable)."""
        wp.launch(
            path_kernels(self.body_path.dtype).next_step, dim=1, inputs=[self.path_step], device=self.body_path.device
        )

    def set_body_motion(
        self, body: int, position=None, orientation=None, velocity=None, angular_velocity=None, rotation=None
    ) -> None:
        """Prescribe a body's pose and velocity: position [m] (3,), orientation quaternion
        (w, x, y, z) or rotation matrix (3, 3), velocity [m/s] (3,), angular velocity [rad/s] (3,).

        A body touches the grains once it has a position. Forces already computed (a
        Simulation computes them when it is made) stay those of the earlier pose until the
        next force evaluation: call Simulation.refresh_forces() after placing a body by hand."""
        if not 0 <= body < self.body_count:
            raise IndexError(f"body index must be in [0, {self.body_count}), got {body}")
        # every argument checked before any is kept: a NaN pose or a zero quaternion left the body out of
        # reach of every grain (no force, no error) and its rotation NaN
        position, velocity, angular_velocity = (
            None if value is None else _finite(value, (3,), f"body {body}'s {name}")
            for value, name in (
                (position, "position [m]"),
                (velocity, "velocity [m/s]"),
                (angular_velocity, "angular velocity [rad/s]"),
            )
        )
        if orientation is not None and rotation is not None:
            raise SoilInputError(f"body {body}: give its orientation as a quaternion or a rotation matrix, not both")
        if orientation is not None:
            quaternion = _finite(orientation, (4,), f"body {body}'s orientation quaternion (w, x, y, z)")
            if not 0.5 < np.linalg.norm(quaternion) < 2.0:
                raise SoilInputError(
                    f"body {body}'s orientation must be a unit quaternion (w, x, y, z), got {orientation!r}"
                )
            rotation = quaternion_to_matrix(quaternion)
        elif rotation is not None:
            rotation = _finite(rotation, (3, 3), f"body {body}'s rotation matrix")
            if np.abs(rotation.T @ rotation - np.eye(3)).max() > 1e-5 or np.linalg.det(rotation) < 0:
                raise SoilInputError(
                    f"body {body}'s rotation must be a proper rotation matrix (orthonormal, det +1), "
                    f"got {rotation.tolist()}"
                )
        if position is not None:
            self.body_position_host[body] = position
            self.body_posed_host[body] = 1
        if rotation is not None:
            self.body_rotation_host[body] = rotation
        if velocity is not None:
            self.body_velocity_host[body] = velocity
        if angular_velocity is not None:
            self.body_angular_velocity_host[body] = angular_velocity
        self.path_active = False
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
            raise SoilInputError(f"boundary velocity must be a finite 3-vector [m/s], got {velocity!r}")
        self.boundary_velocity_host[indices] = velocity
        self._dirty = True

    def set_boundary_load(
        self, boundary: int, load: float, direction=None, mass: float | None = None, damping: float | None = None
    ) -> None:
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
            raise SoilInputError(
                f"boundary {index} was built with report=False: a loaded boundary needs its grain "
                "force (build it with report=True)"
            )
        loaded = self.boundary_mode_host[index] == MOTION_LOADED
        if direction is None and not loaded:
            raise SoilInputError(f"boundary {index} is not loaded yet: give its free direction (a 3-vector)")
        if mass is None and not loaded:
            raise SoilInputError(f"boundary {index} is not loaded yet: give its mass [kg]")
        load = float(load)
        if not np.isfinite(load):
            raise SoilInputError(f"boundary load must be finite [N], got {load!r}")
        if direction is not None:
            direction = np.asarray(direction, dtype=np.float64)
            length = np.linalg.norm(direction) if direction.shape == (3,) else np.nan
            if not (np.isfinite(length) and length > 0):
                raise SoilInputError(f"boundary direction must be a non-zero finite 3-vector, got {direction!r}")
            self.boundary_direction_host[index] = direction / length
        if mass is not None:
            if not (np.isfinite(mass) and mass > 0):
                raise SoilInputError(f"boundary mass must be finite and > 0 [kg], got {mass!r}")
            self.boundary_mass_host[index] = mass
        if damping is not None:
            if not (np.isfinite(damping) and damping >= 0):
                raise SoilInputError(f"boundary damping must be finite and >= 0 [N s/m], got {damping!r}")
            self.boundary_damping_host[index] = damping
        self.boundary_load_host[index] = load
        self.boundary_mode_host[index] = MOTION_LOADED
        self._dirty = True

    def push(self, state) -> None:
        """Send the host motion to the device (only when it changed; between steps, never inside one):
        the boundaries' motion into the control's device arrays, the bodies' pose and velocity into
        `state` (the current SoilState; a step carries them on, a path moves them)."""
        if self._posed_dirty and not self._dirty and self.body_count:
            state.body_posed.assign(self.body_posed_host)
        self._posed_dirty = False
        if not self._dirty:
            return
        np_type = np.float64 if self._scalar is wp.float64 else np.float32
        if self.body_count:
            state.body_posed.assign(self.body_posed_host)
        if self.body_count and not self.path_active:
            state.body_position.assign(self.body_position_host.astype(np_type))
            state.body_rotation.assign(self.body_rotation_host.astype(np_type))
            state.body_velocity.assign(self.body_velocity_host.astype(np_type))
            state.body_angular_velocity.assign(self.body_angular_velocity_host.astype(np_type))
        if self.boundary_count:
            self.boundary_mode.assign(self.boundary_mode_host)
            self.boundary_velocity.assign(self.boundary_velocity_host.astype(np_type))
            self.boundary_direction.assign(self.boundary_direction_host.astype(np_type))
            self.boundary_mass.assign(self.boundary_mass_host.astype(np_type))
            self.boundary_load.assign(self.boundary_load_host.astype(np_type))
            self.boundary_damping.assign(self.boundary_damping_host.astype(np_type))
        self._dirty = False

    # -- snapshots (Simulation.snapshot) -------------------------------------------------
    def snapshot(self) -> dict:
        """The control now, without a device read: numpy copies of the host motion (as state_dict)
        and body_posed, a device copy of external_force, and external_force_used."""
        data = {name: getattr(self, f"{name}_host").copy() for name in self._HOST}
        data["body_posed"] = self.body_posed_host.copy()
        data["external_force"] = wp.clone(self.external_force)
        data["external_force_used"] = self.external_force_used
        return data

    def restore(self, data: dict) -> None:
        """Back to a snapshot() of this control (device to device); the motion is sent at the next push()."""
        for name in self._HOST:
            getattr(self, f"{name}_host")[...] = data[name]
        self.body_posed_host[...] = data["body_posed"]
        wp.copy(self.external_force, data["external_force"])
        self.external_force_used = bool(data["external_force_used"])
        self.path_active = False
        self._dirty = True

    # -- checkpoints -------------------------------------------------------------------
    _HOST = (
        "body_position",
        "body_rotation",
        "body_velocity",
        "body_angular_velocity",
        "boundary_mode",
        "boundary_velocity",
        "boundary_direction",
        "boundary_mass",
        "boundary_load",
        "boundary_damping",
    )

    STATE_UNITS = {
        "body_position": "m",
        "body_rotation": "1",
        "body_velocity": "m/s",
        "body_angular_velocity": "rad/s",
        "boundary_mode": "1",  # MOTION_PRESCRIBED or MOTION_LOADED
        "boundary_velocity": "m/s",
        "boundary_direction": "1",
        "boundary_mass": "kg",
        "boundary_load": "N",
        "boundary_damping": "N s/m",
        "external_force": "N",
        "external_force_used": "1",
        "body_posed": "1",
    }
    """The unit of each entry of state_dict() (the attributes of the same names, without _host)."""

    def state_dict_units(self) -> dict[str, str]:
        """{key of state_dict(): its unit}."""
        return dict(self.STATE_UNITS)

    def state_dict(self) -> dict:
        """The control as numpy arrays: the host copies of body and boundary motion (names
        without _host), external_force [N] (particle_count, 3) and body_posed [-] (body_count,)."""
        data = {name: getattr(self, f"{name}_host").copy() for name in self._HOST}
        data["external_force"] = self.external_force.numpy().copy()  # a view on the CPU otherwise
        data["external_force_used"] = np.bool_(self.external_force_used)
        data["body_posed"] = self.body_posed_host.copy()
        return data

    def load_state_dict(self, data: dict) -> None:
        """Restore from state_dict(); the device copies follow at the next push()."""
        for name in self._HOST:
            target = getattr(self, f"{name}_host")
            values = np.asarray(data[name])
            if values.shape != target.shape:
                raise SoilInputError(f"control.{name}: saved shape {values.shape} does not fit {target.shape}")
            target[...] = values
        force = np.asarray(data["external_force"])
        if force.shape[0] != self.external_force.shape[0]:
            raise SoilInputError(
                f"control.external_force: saved {force.shape[0]} particles, the model has "
                f"{self.external_force.shape[0]}"
            )
        self.external_force.assign(force.astype(self.external_force.numpy().dtype, copy=False))
        self.external_force_used = bool(data.get("external_force_used", np.any(force)))
        # saved before bodies could be unposed: every body counted as posed
        self.body_posed_host[...] = np.asarray(data.get("body_posed", np.ones_like(self.body_posed_host)))
        self.path_active = False
        self._dirty = True
