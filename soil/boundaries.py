"""Moving boundaries: translation of walls and boxes, prescribed or under a load, on the device.

A boundary (plane or box, soil.sdf) keeps its initial geometry in the model; the
state carries where it is now and how it moves (soil.state):

    boundary_displacement  d [m]      from the initial geometry,
    boundary_velocity      v [m/s]    translation velocity (the contact law sees it),
    boundary_acceleration  a [m/s^2]  along the free direction of a loaded boundary.

The control (soil.control) sets each boundary's motion:

- prescribed (MOTION_PRESCRIBED, the default, at zero velocity = fixed): v = V, the
  velocity the control prescribes; every step d += V dt.
- loaded (MOTION_LOADED): a rigid body of mass M free along a unit direction e (a lid
  under a dead load, a plate pushed with a set force). Along e it obeys

      M a = L + F . e - c (v . e),

  L the load [N] along e, F the grains' force on the boundary [N] (state.boundary_force),
  c a linear damper [N s/m] (optional; the grains' contact damping assumes an immovable
  wall, so a heavy lid on stiff grains rings unless c or the grains damp it). Across e
  the boundary follows the prescribed velocity's part perpendicular to e (e.g. a
  shear box's lid moving with its upper frame). The wall's own weight is not added:
  put it into L if it should count.

A loaded boundary is integrated with the particles' scheme: velocity Verlet (half kicks
with the acceleration of the state, drift with the half-step velocity) or jolt-Beeman
(predict with the acceleration and the previous one, correct with the new one). The new
acceleration is computed with the forces (ContactSolver.compute), at the velocity the
forces saw (Verlet: half step; jolt-Beeman: predicted), exactly as the grains' damping
forces are. The jolt-Beeman error estimate covers the grains only.

Every kernel here runs on `boundary_count` threads and reads nothing on the host: the
steps stay graph-capturable.
"""

import warp as wp

from .precision import kernel_factory, kernel_module, soil_kernel

MOTION_PRESCRIBED = 0
"""The boundary moves with the velocity the control prescribes (zero: fixed)."""
MOTION_LOADED = 1
"""The boundary is a rigid body free along a direction, pushed by a load (see the module docstring)."""


@kernel_factory
def boundary_kernels(hi):
    """The boundary-motion kernels for the precision's `hi` type."""
    kernel = soil_kernel(kernel_module("boundaries", hi))
    vec_hi = wp.types.vector(3, hi)

    @wp.func
    def across(velocity: vec_hi, direction: vec_hi):
        """The part of `velocity` perpendicular to `direction` (unit)."""
        return velocity - wp.dot(velocity, direction) * direction

    @kernel
    def boundary_acceleration(
        mode: wp.array(dtype=wp.int32),
        direction: wp.array(dtype=vec_hi),
        mass: wp.array(dtype=hi),
        load: wp.array(dtype=hi),
        damping: wp.array(dtype=hi),
        velocity_in: wp.array(dtype=vec_hi),
        force_in: wp.array(dtype=vec_hi),
        # outputs
        acceleration_out: wp.array(dtype=hi),
    ):
        """a = (L + F . e - c v . e) / M for a loaded boundary, 0 otherwise [m/s^2]."""
        b = wp.tid()
        a = hi(0.0)
        if mode[b] == MOTION_LOADED:
            e = direction[b]
            a = (load[b] + wp.dot(force_in[b], e) - damping[b] * wp.dot(velocity_in[b], e)) / mass[b]
        acceleration_out[b] = a

    @kernel
    def verlet_kick_drift(
        mode: wp.array(dtype=wp.int32),
        prescribed: wp.array(dtype=vec_hi),
        direction: wp.array(dtype=vec_hi),
        displacement_in: wp.array(dtype=vec_hi),
        velocity_in: wp.array(dtype=vec_hi),
        acceleration_in: wp.array(dtype=hi),
        step_length: wp.array(dtype=hi),
        walls_per_world: int,
        # outputs
        displacement_out: wp.array(dtype=vec_hi),
        velocity_out: wp.array(dtype=vec_hi),
    ):
        """Velocity Verlet, first half: half kick along e (loaded), then a full drift."""
        b = wp.tid()
        world = b // walls_per_world
        dt = step_length[world]
        velocity = prescribed[b]
        if mode[b] == MOTION_LOADED:
            e = direction[b]
            along = wp.dot(velocity_in[b], e) + hi(0.5) * dt * acceleration_in[b]
            velocity = across(velocity, e) + along * e
        displacement_out[b] = displacement_in[b] + dt * velocity
        velocity_out[b] = velocity

    @kernel
    def verlet_kick(
        mode: wp.array(dtype=wp.int32),
        direction: wp.array(dtype=vec_hi),
        acceleration_new: wp.array(dtype=hi),
        step_length: wp.array(dtype=hi),
        walls_per_world: int,
        # in/out
        velocity_io: wp.array(dtype=vec_hi),
    ):
        """Velocity Verlet, second half kick along e with the new acceleration."""
        b = wp.tid()
        world = b // walls_per_world
        dt = step_length[world]
        if mode[b] == MOTION_LOADED:
            velocity_io[b] = velocity_io[b] + (hi(0.5) * dt * acceleration_new[b]) * direction[b]

    @kernel
    def beeman_predict(
        mode: wp.array(dtype=wp.int32),
        prescribed: wp.array(dtype=vec_hi),
        direction: wp.array(dtype=vec_hi),
        displacement_in: wp.array(dtype=vec_hi),
        velocity_in: wp.array(dtype=vec_hi),
        acceleration_in: wp.array(dtype=hi),
        acceleration_previous_in: wp.array(dtype=hi),
        step_previous_in: wp.array(dtype=hi),
        step_length: wp.array(dtype=hi),
        walls_per_world: int,
        # outputs
        displacement_out: wp.array(dtype=vec_hi),
        velocity_out: wp.array(dtype=vec_hi),
        acceleration_previous_out: wp.array(dtype=hi),
    ):
        """Jolt-Beeman prediction along e (same formulas and step-ratio rule as the grains')."""
        b = wp.tid()
        world = b // walls_per_world
        dt = step_length[world]
        velocity = prescribed[b]
        moved = dt * velocity
        if mode[b] == MOTION_LOADED:
            e = direction[b]
            ratio = hi(0.0)
            if step_previous_in[world] > hi(0.0):
                ratio = dt / step_previous_in[world]
            a = acceleration_in[b]
            a_minus = a - ratio * (a - acceleration_previous_in[b])
            along = wp.dot(velocity_in[b], e)
            moved = dt * across(velocity, e) + (along * dt + (dt * dt / hi(6.0)) * (hi(4.0) * a - a_minus)) * e
            velocity = across(velocity, e) + (along + (hi(0.5) * dt) * (hi(3.0) * a - a_minus)) * e
        displacement_out[b] = displacement_in[b] + moved
        velocity_out[b] = velocity
        acceleration_previous_out[b] = acceleration_in[b]

    @kernel
    def beeman_correct(
        mode: wp.array(dtype=wp.int32),
        direction: wp.array(dtype=vec_hi),
        velocity_in: wp.array(dtype=vec_hi),
        acceleration_in: wp.array(dtype=hi),
        acceleration_previous_in: wp.array(dtype=hi),
        step_previous_in: wp.array(dtype=hi),
        acceleration_new: wp.array(dtype=hi),
        step_length: wp.array(dtype=hi),
        walls_per_world: int,
        # in/out
        velocity_io: wp.array(dtype=vec_hi),
    ):
        """Beeman correction along e: v+ = v + (2 a+ + 5 a - a_minus) dt / 6."""
        b = wp.tid()
        world = b // walls_per_world
        dt = step_length[world]
        if mode[b] == MOTION_LOADED:
            e = direction[b]
            ratio = hi(0.0)
            if step_previous_in[world] > hi(0.0):
                ratio = dt / step_previous_in[world]
            a = acceleration_in[b]
            a_minus = a - ratio * (a - acceleration_previous_in[b])
            along = wp.dot(velocity_in[b], e) + (dt / hi(6.0)) * (hi(2.0) * acceleration_new[b] + hi(5.0) * a - a_minus)
            velocity_io[b] = across(velocity_io[b], e) + along * e

    return dict(
        boundary_acceleration=boundary_acceleration,
        verlet_kick_drift=verlet_kick_drift,
        verlet_kick=verlet_kick,
        beeman_predict=beeman_predict,
        beeman_correct=beeman_correct,
    )


def _motion(control):
    return [control.boundary_mode, control.boundary_velocity, control.boundary_direction]


def update_acceleration(model, state, control) -> None:
    """state.boundary_acceleration from state.boundary_force and state.boundary_velocity."""
    if not model.boundary_count:
        return
    kernels = boundary_kernels(model.precision.hi)
    wp.launch(
        kernels.boundary_acceleration,
        dim=model.boundary_count,
        inputs=[
            control.boundary_mode,
            control.boundary_direction,
            control.boundary_mass,
            control.boundary_load,
            control.boundary_damping,
            state.boundary_velocity,
            state.boundary_force,
        ],
        outputs=[state.boundary_acceleration],
        device=model.device,
    )


def verlet_first_half(model, state_in, state_out, control, dt: wp.array) -> None:
    """Move the boundaries over a velocity-Verlet step (before the forces of state_out)."""
    if not model.boundary_count:
        return
    kernels = boundary_kernels(model.precision.hi)
    wp.launch(
        kernels.verlet_kick_drift,
        dim=model.boundary_count,
        inputs=_motion(control)
        + [
            state_in.boundary_displacement,
            state_in.boundary_velocity,
            state_in.boundary_acceleration,
            dt,
            model.walls_per_world,
        ],
        outputs=[state_out.boundary_displacement, state_out.boundary_velocity],
        device=model.device,
    )
    # Verlet keeps no previous acceleration (a later jolt-Beeman step starts with zero jolt)
    state_out.boundary_acceleration_previous.zero_()


def verlet_second_half(model, state_out, control, dt: wp.array) -> None:
    """Second half kick of the loaded boundaries with state_out's new acceleration."""
    if not model.boundary_count:
        return
    kernels = boundary_kernels(model.precision.hi)
    wp.launch(
        kernels.verlet_kick,
        dim=model.boundary_count,
        inputs=[
            control.boundary_mode,
            control.boundary_direction,
            state_out.boundary_acceleration,
            dt,
            model.walls_per_world,
        ],
        outputs=[state_out.boundary_velocity],
        device=model.device,
    )


def beeman_predict(model, state_in, state_out, control, dt: wp.array) -> None:
    """Jolt-Beeman prediction of the boundaries' motion into state_out."""
    if not model.boundary_count:
        return
    kernels = boundary_kernels(model.precision.hi)
    wp.launch(
        kernels.beeman_predict,
        dim=model.boundary_count,
        inputs=_motion(control)
        + [
            state_in.boundary_displacement,
            state_in.boundary_velocity,
            state_in.boundary_acceleration,
            state_in.boundary_acceleration_previous,
            state_in.step_previous,
            dt,
            model.walls_per_world,
        ],
        outputs=[
            state_out.boundary_displacement,
            state_out.boundary_velocity,
            state_out.boundary_acceleration_previous,
        ],
        device=model.device,
    )


def beeman_correct(model, state_in, state_out, control, dt: wp.array) -> None:
    """Jolt-Beeman correction of the loaded boundaries' velocity with state_out's new acceleration."""
    if not model.boundary_count:
        return
    kernels = boundary_kernels(model.precision.hi)
    wp.launch(
        kernels.beeman_correct,
        dim=model.boundary_count,
        inputs=[
            control.boundary_mode,
            control.boundary_direction,
            state_in.boundary_velocity,
            state_in.boundary_acceleration,
            state_in.boundary_acceleration_previous,
            state_in.step_previous,
            state_out.boundary_acceleration,
            dt,
            model.walls_per_world,
        ],
        outputs=[state_out.boundary_velocity],
        device=model.device,
    )
