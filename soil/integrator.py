"""Time integrators and their kernels. Every integrator has
step(model, state_in, state_out, control, dt, contacts), which only launches device work
(no host read, no allocation): a step can be captured into a graph and replayed.

- VelocityVerlet: plain explicit velocity Verlet, fixed step.
- JoltBeeman: the jolt-Beeman predictor-corrector (docs/physics.md section 2), one force
  evaluation per step, with the predictor/corrector gap as local error estimate; used
  with a fixed step (Simulation.run) or with the PID StepController
  (Simulation.run_adaptive), whose error norm is reduced on the device.

make_integrator(name) makes one by its name in a scene ('velocity-verlet', 'jolt-beeman').

No `from __future__ import annotations` here: Warp reads the kernels' annotations as types.
"""

import math
import numbers
from dataclasses import dataclass, field, fields

import numpy as np
import warp as wp

from . import boundaries
from . import status as status_columns
from .contact import ContactLaw
from .control import SoilControl
from .errors import SoilInputError
from .model import SoilModel
from .precision import kernel_factory, kernel_module, soil_kernel
from .reduction import WorldTree, leaf_span
from .solver import ContactSolver
from .state import SoilState

# Columns of the per-step summary of JoltBeeman (shape (SUMMARY_COLUMNS,), dtype hi).
SUMMARY_POSITION_GAP = 0
"""max_i |x_corrected - x_predicted| / r_i [-]."""
SUMMARY_VELOCITY_GAP = 1
"""max_i max(|v_corr - v_pred|, r_i |w_corr - w_pred|) [m/s]."""
SUMMARY_SPEED = 2
"""max_i max(|v_i|, r_i |w_i|) after the step [m/s]."""
SUMMARY_NONFINITE = 3
"""1 if any position, velocity or spin is NaN/inf after the step, else 0 [-]."""
SUMMARY_WORST = 4
"""Model index of a particle with a non-finite state (when flagged), else -1 [-]."""
SUMMARY_RMS = 5
"""sqrt(mean_i e_i^2) of the per-grain error e_i (StepController) [-]."""
SUMMARY_MAX = 6
"""max_i e_i [-]."""
SUMMARY_STATUS = 7
"""First of the columns holding the step status (soil.status: flags and counts [-]) after the step."""
SUMMARY_COLUMNS = SUMMARY_STATUS + status_columns.COLUMNS


@kernel_factory
def integrator_kernels(hi, mid, lo, law: ContactLaw):
    """The velocity-Verlet and jolt-Beeman kernels for precision types (hi, mid, lo): spins and
    torques are stored in mid (soil.precision), read into hi, and the new spin rounded to mid."""
    kernel = soil_kernel(kernel_module("integrator", hi, mid, lo, law))
    vec_hi = wp.types.vector(3, hi)
    vec_mid = wp.types.vector(3, mid)

    @wp.func
    def acceleration_of(force: vec_hi, inv_mass: lo, gravity: vec_hi):
        """Acceleration [m/s^2] of a grain under `force`; fixed grains (inv_mass 0) feel no gravity."""
        inv_m = hi(inv_mass)
        acceleration = force * inv_m
        if inv_m > hi(0.0):
            acceleration = acceleration + gravity
        return acceleration

    @wp.func
    def flag_nonfinite(x: vec_hi, v: vec_hi, w: vec_hi, grain: int, status_out: wp.array(dtype=wp.int32)):
        """Mark a non-finite grain in the status (max of model indices: order-independent)."""
        if not (wp.isfinite(x) and wp.isfinite(v) and wp.isfinite(w)):
            status_out[status_columns.NONFINITE] = 1
            wp.atomic_max(status_out, status_columns.WORST, grain)

    @wp.func
    def backward_step(a: vec_hi, a_previous: vec_hi, ratio: hi):
        """Acceleration one step of the NEW length dt before t, with constant jolt.

        The jolt is (a - a_previous) / dt_previous; extrapolated back by dt it gives
        a(t - dt) = a - (dt / dt_previous) (a - a_previous). With this `a_minus` the
        fixed-step Beeman formulas are exact for a constant jolt at any step ratio.
        ratio = 0 (no history) means zero jolt: a_minus = a.
        """
        return a - ratio * (a - a_previous)

    @kernel
    def kick_drift(
        x_in: wp.array(dtype=vec_hi),
        v_in: wp.array(dtype=vec_hi),
        w_in: wp.array(dtype=vec_mid),
        force_in: wp.array(dtype=vec_hi),
        torque_in: wp.array(dtype=vec_mid),
        inv_mass: wp.array(dtype=lo),
        inv_inertia: wp.array(dtype=lo),
        gravity: vec_hi,
        step_length: wp.array(dtype=hi),
        world_size: int,
        # outputs
        x_out: wp.array(dtype=vec_hi),
        v_out: wp.array(dtype=vec_hi),
        w_out: wp.array(dtype=vec_mid),
    ):
        """Velocity Verlet, first half: half kick with the old forces, then a full drift."""
        i = wp.tid()
        dt = step_length[i // world_size]
        v_half = v_in[i] + hi(0.5) * dt * acceleration_of(force_in[i], inv_mass[i], gravity)
        v_out[i] = v_half
        w_out[i] = vec_mid(vec_hi(w_in[i]) + hi(0.5) * dt * hi(inv_inertia[i]) * vec_hi(torque_in[i]))
        x_out[i] = x_in[i] + dt * v_half

    @kernel
    def kick(
        force_in: wp.array(dtype=vec_hi),
        torque_in: wp.array(dtype=vec_mid),
        inv_mass: wp.array(dtype=lo),
        inv_inertia: wp.array(dtype=lo),
        order: wp.array(dtype=wp.int32),
        x_in: wp.array(dtype=vec_hi),
        gravity: vec_hi,
        step_length: wp.array(dtype=hi),
        world_size: int,
        # in/out
        v_io: wp.array(dtype=vec_hi),
        w_io: wp.array(dtype=vec_mid),
        status_out: wp.array(dtype=wp.int32),
    ):
        """Velocity Verlet, second half kick with the new forces; flags a non-finite grain."""
        i = wp.tid()
        dt = step_length[i // world_size]
        v = v_io[i] + hi(0.5) * dt * acceleration_of(force_in[i], inv_mass[i], gravity)
        w = vec_mid(vec_hi(w_io[i]) + hi(0.5) * dt * hi(inv_inertia[i]) * vec_hi(torque_in[i]))
        v_io[i] = v
        w_io[i] = w
        flag_nonfinite(x_in[i], v, vec_hi(w), order[i], status_out)

    @kernel
    def beeman_predict(
        x_in: wp.array(dtype=vec_hi),
        v_in: wp.array(dtype=vec_hi),
        w_in: wp.array(dtype=vec_mid),
        force_in: wp.array(dtype=vec_hi),
        torque_in: wp.array(dtype=vec_mid),
        force_previous_in: wp.array(dtype=vec_hi),
        torque_previous_in: wp.array(dtype=vec_mid),
        step_previous_in: wp.array(dtype=hi),
        inv_mass: wp.array(dtype=lo),
        inv_inertia: wp.array(dtype=lo),
        gravity: vec_hi,
        step_length: wp.array(dtype=hi),
        world_size: int,
        # outputs
        x_out: wp.array(dtype=vec_hi),
        v_out: wp.array(dtype=vec_hi),
        w_out: wp.array(dtype=vec_mid),
        force_previous_out: wp.array(dtype=vec_hi),
        torque_previous_out: wp.array(dtype=vec_mid),
        step_previous_out: wp.array(dtype=hi),
    ):
        """Explicit jolt-Beeman prediction (no force evaluation).

        x+ = x + v dt + (4 a - a_minus) dt^2 / 6   (Beeman; = Taylor with constant jolt)
        v_pred = v + (3 a - a_minus) dt / 2        (Taylor with constant jolt; the forces
                                                    of the new state see this velocity)
        """
        i = wp.tid()
        world = i // world_size  # a world's grains are one block of storage (soil.worlds)
        dt = step_length[world]
        h_prev = step_previous_in[world]
        ratio = hi(0.0)
        if h_prev > hi(0.0):
            ratio = dt / h_prev
        inv_i = hi(inv_inertia[i])
        a = acceleration_of(force_in[i], inv_mass[i], gravity)
        a_minus = backward_step(a, acceleration_of(force_previous_in[i], inv_mass[i], gravity), ratio)
        alpha = vec_hi(torque_in[i]) * inv_i
        alpha_minus = backward_step(alpha, vec_hi(torque_previous_in[i]) * inv_i, ratio)
        v = v_in[i]
        x_out[i] = x_in[i] + dt * v + (dt * dt / hi(6.0)) * (hi(4.0) * a - a_minus)
        v_out[i] = v + (hi(0.5) * dt) * (hi(3.0) * a - a_minus)
        w_out[i] = vec_mid(vec_hi(w_in[i]) + (hi(0.5) * dt) * (hi(3.0) * alpha - alpha_minus))
        force_previous_out[i] = force_in[i]
        torque_previous_out[i] = torque_in[i]
        if i % world_size == 0:
            step_previous_out[world] = dt

    @kernel
    def beeman_correct(
        v_in: wp.array(dtype=vec_hi),
        w_in: wp.array(dtype=vec_mid),
        x_new: wp.array(dtype=vec_hi),
        force_in: wp.array(dtype=vec_hi),
        torque_in: wp.array(dtype=vec_mid),
        force_previous_in: wp.array(dtype=vec_hi),
        torque_previous_in: wp.array(dtype=vec_mid),
        step_previous_in: wp.array(dtype=hi),
        force_new: wp.array(dtype=vec_hi),
        torque_new: wp.array(dtype=vec_mid),
        inv_mass: wp.array(dtype=lo),
        inv_inertia: wp.array(dtype=lo),
        radius: wp.array(dtype=lo),
        order: wp.array(dtype=wp.int32),
        gravity: vec_hi,
        step_length: wp.array(dtype=hi),
        world_size: int,
        # outputs
        v_out: wp.array(dtype=vec_hi),
        w_out: wp.array(dtype=vec_mid),
        gaps_out: wp.array2d(dtype=hi),
        status_out: wp.array(dtype=wp.int32),
    ):
        """Beeman correction with the new forces, and the predictor/corrector gap.

        v+ = v + (2 a+ + 5 a - a_minus) dt / 6. The gap to the prediction is
        v+ - v_pred = (a+ - 2 a + a_minus) dt / 3 (a second difference: O(dt^3) where
        the motion is smooth); the position the new acceleration would give,
        x + v dt + (a+ + 2 a) dt^2 / 6, differs from the predicted x+ by half that
        times dt. Positions stay as predicted, so the new forces belong to them.
        """
        i = wp.tid()
        world = i // world_size  # a world's grains are one block of storage (soil.worlds)
        dt = step_length[world]
        h_prev = step_previous_in[world]
        ratio = hi(0.0)
        if h_prev > hi(0.0):
            ratio = dt / h_prev
        inv_i = hi(inv_inertia[i])
        a = acceleration_of(force_in[i], inv_mass[i], gravity)
        a_minus = backward_step(a, acceleration_of(force_previous_in[i], inv_mass[i], gravity), ratio)
        a_plus = acceleration_of(force_new[i], inv_mass[i], gravity)
        alpha = vec_hi(torque_in[i]) * inv_i
        alpha_minus = backward_step(alpha, vec_hi(torque_previous_in[i]) * inv_i, ratio)
        alpha_plus = vec_hi(torque_new[i]) * inv_i
        v = v_in[i] + (dt / hi(6.0)) * (hi(2.0) * a_plus + hi(5.0) * a - a_minus)
        w = vec_mid(vec_hi(w_in[i]) + (dt / hi(6.0)) * (hi(2.0) * alpha_plus + hi(5.0) * alpha - alpha_minus))
        v_out[i] = v
        w_out[i] = w

        r = hi(radius[i])
        velocity_gap = wp.length(a_plus - hi(2.0) * a + a_minus) * dt / hi(3.0)
        spin_gap = wp.length(alpha_plus - hi(2.0) * alpha + alpha_minus) * dt / hi(3.0) * r
        gaps_out[i, 0] = hi(0.5) * dt * velocity_gap / r  # per grain, for the error norm
        gaps_out[i, 1] = wp.max(velocity_gap, spin_gap)
        flag_nonfinite(x_new[i], v, vec_hi(w), order[i], status_out)

    @wp.func
    def grain_error(gaps: wp.array2d(dtype=hi), i: int, position_weight: hi, scale: hi):
        """e_i = max(w |dx_i| / r_i, |dv_i| / V) (StepController), inf for a non-finite gap."""
        velocity = gaps[i, 1]
        e = hi(0.0)
        if scale > hi(0.0):
            e = velocity / scale
        elif velocity > hi(0.0):
            e = hi(wp.inf)
        e = wp.max(e, position_weight * gaps[i, 0])
        if not wp.isfinite(e):
            e = hi(wp.inf)
        return e

    @kernel
    def norm_partial(
        gaps: wp.array2d(dtype=hi),
        x_in: wp.array(dtype=vec_hi),
        v_in: wp.array(dtype=vec_hi),
        w_in: wp.array(dtype=vec_mid),
        radius: wp.array(dtype=lo),
        slot: wp.array(dtype=wp.int32),
        summary: wp.array2d(dtype=hi),
        position_weight: hi,
        pass_index: int,
        world_size: int,
        rows_per_world: int,
        partial_out: wp.array2d(dtype=hi),
    ):
        """The tree's leaves (soil.reduction): per LEAF model indices of one world, pass 0 the maxima
        of the gaps and of the speed, and whether a grain is non-finite; pass 1 the sum of e_i^2 and
        max e_i with the world's scale found by pass 0."""
        c = wp.tid()
        world = c // rows_per_world
        span = leaf_span(c, rows_per_world, world_size)
        first = hi(0.0)
        second = hi(0.0)
        third = hi(0.0)
        fourth = hi(0.0)
        scale = summary[world, SUMMARY_RMS]  # pass 1: the scale, parked there by norm_total's pass 0
        for p in range(span[0], span[1]):
            i = slot[p]
            if pass_index == 0:
                first = wp.max(first, gaps[i, 0])
                second = wp.max(second, gaps[i, 1])
                third = wp.max(third, wp.max(wp.length(v_in[i]), hi(radius[i]) * wp.length(vec_hi(w_in[i]))))
                if not (wp.isfinite(x_in[i]) and wp.isfinite(v_in[i]) and wp.isfinite(vec_hi(w_in[i]))):
                    fourth = hi(1.0)  # flag_nonfinite's test, per world
            else:
                e = grain_error(gaps, i, position_weight, scale)
                first = first + e * e
                second = wp.max(second, e)
        partial_out[c, 0] = first
        partial_out[c, 1] = second
        partial_out[c, 2] = third
        partial_out[c, 3] = fourth

    @kernel
    def norm_total(
        partial: wp.array2d(dtype=hi),
        status: wp.array(dtype=wp.int32),
        scale_floor_in: wp.array(dtype=hi),
        use_speed: int,
        pass_index: int,
        world_size: int,
        rows_per_world: int,
        summary_out: wp.array2d(dtype=hi),
    ):
        """Fold world w's last rows of the tree in order into its summary row (pass 0: maxima, and the velocity scale
        V = max(scale_floor, speed) parked in SUMMARY_RMS; pass 1: the RMS and the maximum)."""
        w = wp.tid()
        first = hi(0.0)
        second = hi(0.0)
        third = hi(0.0)
        fourth = hi(0.0)
        for c in range(w * rows_per_world, (w + 1) * rows_per_world):
            if pass_index == 0:
                first = wp.max(first, partial[c, 0])
                second = wp.max(second, partial[c, 1])
                third = wp.max(third, partial[c, 2])
                fourth = wp.max(fourth, partial[c, 3])
            else:
                first = first + partial[c, 0]
                second = wp.max(second, partial[c, 1])
        if pass_index == 0:
            summary_out[w, SUMMARY_POSITION_GAP] = first
            summary_out[w, SUMMARY_VELOCITY_GAP] = second
            summary_out[w, SUMMARY_SPEED] = third
            summary_out[w, SUMMARY_NONFINITE] = fourth
            summary_out[w, SUMMARY_WORST] = hi(status[status_columns.WORST])
            for column in range(status_columns.COLUMNS):
                summary_out[w, SUMMARY_STATUS + column] = hi(status[column])
            scale = scale_floor_in[w]
            if use_speed != 0:
                scale = wp.max(scale, third)
            summary_out[w, SUMMARY_RMS] = scale
        else:
            summary_out[w, SUMMARY_RMS] = wp.sqrt(first / hi(world_size))
            summary_out[w, SUMMARY_MAX] = second

    return dict(
        kick_drift=kick_drift,
        kick=kick,
        beeman_predict=beeman_predict,
        beeman_correct=beeman_correct,
        norm_partial=norm_partial,
        norm_total=norm_total,
        acceleration_of=acceleration_of,
    )


class VelocityVerlet:
    """Plain explicit velocity Verlet (kick-drift-kick), one force evaluation per step.

    Velocity-dependent forces (damping, friction) see the half-step velocity, as in
    LAMMPS' fix nve/sphere.
    """

    name = "verlet"

    def bind(self, model: SoilModel) -> None:
        """Allocate what the steps need (before a step is captured)."""

    def step(
        self,
        model: SoilModel,
        state_in: SoilState,
        state_out: SoilState,
        control: SoilControl,
        dt: wp.array,
        contacts: ContactSolver,
    ) -> None:
        prec = model.precision
        kernels = integrator_kernels(prec.hi, prec.mid, prec.lo, model.law)
        gravity = prec.vec_hi(*model.gravity)
        layout = state_in.layout
        wp.launch(
            kernels.kick_drift,
            dim=model.particle_count,
            inputs=[
                state_in.position,
                state_in.velocity,
                state_in.angular_velocity,
                state_in.force,
                state_in.torque,
                layout.inv_mass,
                layout.inv_inertia,
                gravity,
                dt,
                model.world_size,
            ],
            outputs=[state_out.position, state_out.velocity, state_out.angular_velocity],
            device=model.device,
        )
        boundaries.verlet_first_half(model, state_in, state_out, control, dt)
        contacts.compute(state_in, state_out, control, dt)
        wp.launch(
            kernels.kick,
            dim=model.particle_count,
            inputs=[
                state_out.force,
                state_out.torque,
                layout.inv_mass,
                layout.inv_inertia,
                layout.order,
                state_out.position,
                gravity,
                dt,
                model.world_size,
            ],
            outputs=[state_out.velocity, state_out.angular_velocity, contacts.status],
            device=model.device,
        )
        boundaries.verlet_second_half(model, state_out, control, dt)
        # Verlet keeps no multi-step history: a jolt-Beeman step after it starts afresh (zero jolt)
        state_out.step_previous.zero_()


class JoltBeeman:
    """Jolt-Beeman predictor-corrector, translation and rotation, one force evaluation per step.

    With a = a(t), a_minus = a(t - dt) and a+ = a(t + dt):

    1. predict (explicit, constant jolt (a - a_minus)/dt):
       x+ = x + v dt + (4 a - a_minus) dt^2/6,  v_pred = v + (3 a - a_minus) dt/2,
       and the same for the spin with the angular acceleration T / I;
    2. evaluate forces and torques at (x+, v_pred, w_pred) (the only force evaluation);
    3. correct: v+ = v + (2 a+ + 5 a - a_minus) dt/6 (Beeman), same for the spin.

    Variable steps: the state keeps the force of the previous state and the length of
    the step between them (SoilState.force_previous, step_previous). With a new step
    dt != dt_previous the constant-jolt line through a(t - dt_previous) and a(t) is
    extrapolated to t - dt: a_minus = a - (dt/dt_previous) (a - a(t - dt_previous)).
    Both Beeman formulas with that a_minus are exactly the Taylor/backward-Taylor
    expansions with constant jolt, so the scheme keeps its order at any step ratio
    (it is the variable-step Beeman form, written with a rescaled a_minus).
    The first step (step_previous = 0) assumes zero jolt: a_minus = a.

    Local error estimate (the predictor/corrector gap), per particle:
    |v+ - v_pred| = |a+ - 2 a + a_minus| dt/3 [m/s] (and r |w+ - w_pred| for the spin),
    and the position gap dt/2 of that, divided by the radius [-], in `gaps`.
    `read_summary()` reduces them on the device (chunks in model-index order, so the norm
    does not depend on the storage order) and reads the result once.
    """

    name = "jolt-beeman"
    error_order = 3
    """The error estimate scales as dt^3 where the motion is smooth."""

    def __init__(self):
        self.gaps = None
        """Per-grain gaps of the last step, storage order: [position gap / r, velocity gap m/s],
        shape (particle_count, 2), dtype hi."""
        self.summary = None
        """Reductions of the last step's error per world, each column in its unit (SUMMARY_*: gaps [-] and
        [m/s], speed [m/s], flags, index, errors [-]), shape (worlds, SUMMARY_COLUMNS), dtype hi (soil.worlds:
        one row for a scene alone)."""
        self._norms = None
        self._model = None
        self.scale_floor = None
        """The velocity scale's floor V of each world's error norm [m/s], shape (worlds,), dtype hi (read_summary
        fills it)."""

    def bind(self, model: SoilModel) -> None:
        """Allocate what the steps need (before a step is captured)."""
        n = model.particle_count
        if (
            self.gaps is not None
            and self.gaps.shape[0] == n
            and self.summary.shape[0] == model.world_count
            and self.gaps.device == wp.get_device(model.device)
            and self.gaps.dtype == model.precision.hi
        ):
            self._model = model
            return
        self._model = model
        worlds = model.world_count
        self.summary = wp.zeros((worlds, SUMMARY_COLUMNS), dtype=model.precision.hi, device=model.device)
        self.scale_floor = wp.zeros(worlds, dtype=model.precision.hi, device=model.device)
        self.gaps = wp.zeros((n, 2), dtype=model.precision.hi, device=model.device)
        self._norms = WorldTree(worlds, model.world_size, 4, model.precision.hi, model.device)

    def step(
        self,
        model: SoilModel,
        state_in: SoilState,
        state_out: SoilState,
        control: SoilControl,
        dt: wp.array,
        contacts: ContactSolver,
    ) -> None:
        prec = model.precision
        kernels = integrator_kernels(prec.hi, prec.mid, prec.lo, model.law)
        gravity = prec.vec_hi(*model.gravity)
        n = model.particle_count
        if self._model is not model:
            self.bind(model)
        layout = state_in.layout
        wp.launch(
            kernels.beeman_predict,
            dim=n,
            inputs=[
                state_in.position,
                state_in.velocity,
                state_in.angular_velocity,
                state_in.force,
                state_in.torque,
                state_in.force_previous,
                state_in.torque_previous,
                state_in.step_previous,
                layout.inv_mass,
                layout.inv_inertia,
                gravity,
                dt,
                model.world_size,
            ],
            outputs=[
                state_out.position,
                state_out.velocity,
                state_out.angular_velocity,
                state_out.force_previous,
                state_out.torque_previous,
                state_out.step_previous,
            ],
            device=model.device,
        )
        boundaries.beeman_predict(model, state_in, state_out, control, dt)
        contacts.compute(state_in, state_out, control, dt)
        wp.launch(
            kernels.beeman_correct,
            dim=n,
            inputs=[
                state_in.velocity,
                state_in.angular_velocity,
                state_out.position,
                state_in.force,
                state_in.torque,
                state_in.force_previous,
                state_in.torque_previous,
                state_in.step_previous,
                state_out.force,
                state_out.torque,
                layout.inv_mass,
                layout.inv_inertia,
                layout.radius,
                layout.order,
                gravity,
                dt,
                model.world_size,
            ],
            outputs=[state_out.velocity, state_out.angular_velocity, self.gaps, contacts.status],
            device=model.device,
        )
        boundaries.beeman_correct(model, state_in, state_out, control, dt)

    def reduce_error(
        self, state: SoilState, status: wp.array, position_weight: float, scale_floor: wp.array, use_speed: bool
    ) -> None:
        """Reduce the last step's gaps into each world's row of `summary` on the device (no host read:
        capturable), the velocity scale's floor V of world w read from scale_floor[w] [m/s] (see
        read_summary)."""
        model = self._model
        prec = model.precision
        kernels = integrator_kernels(prec.hi, prec.mid, prec.lo, model.law)
        layout = state.layout
        norms = self._norms
        for pass_index in (0, 1):
            wp.launch(
                kernels.norm_partial,
                dim=norms.leaves.shape[0],
                inputs=[
                    self.gaps,
                    state.position,
                    state.velocity,
                    state.angular_velocity,
                    layout.radius,
                    layout.slot,
                    self.summary,
                    prec.hi(position_weight),
                    pass_index,
                    model.world_size,
                    norms.rows[0],
                ],
                outputs=[norms.leaves],
                device=model.device,
            )
            norms.fold(summed_columns=pass_index)  # pass 0: maxima only; pass 1: the sum of e_i^2, then maxima
            wp.launch(
                kernels.norm_total,
                dim=model.world_count,
                inputs=[
                    norms.last,
                    status,
                    scale_floor,
                    int(use_speed),
                    pass_index,
                    model.world_size,
                    norms.last_rows,
                ],
                outputs=[self.summary],
                device=model.device,
            )

    def read_summary(
        self,
        state: SoilState,
        status: wp.array,
        position_weight: float = 1.0,
        scale_floor: float = 1.0,
        use_speed: bool = False,
    ) -> dict:
        """The last step's error norms, reduced on the device and read once: position_gap [-]
        (max |dx| / r), velocity_gap [m/s], speed [m/s] (max over grains), nonfinite (bool),
        worst (model index of a non-finite grain or -1), rms and max of the per-grain error
        e_i = max(position_weight |dx_i| / r_i, |dv_i| / V), V = max(scale_floor, speed if
        use_speed) (StepController.error), and status (the step status, soil.status columns)."""
        self.scale_floor.fill_(float(scale_floor))
        self.reduce_error(state, status, position_weight, self.scale_floor, use_speed)
        values = self.summary.numpy()[0].astype(np.float64)  # a scene alone: one world
        nonfinite = bool(values[SUMMARY_NONFINITE] > 0)
        return {
            "position_gap": float(values[SUMMARY_POSITION_GAP]),
            "velocity_gap": float(values[SUMMARY_VELOCITY_GAP]),
            "speed": float(values[SUMMARY_SPEED]),
            "nonfinite": nonfinite or not np.isfinite(values[SUMMARY_MAX]),
            "worst": int(values[SUMMARY_WORST]) if nonfinite else -1,
            "rms": float(values[SUMMARY_RMS]),
            "max": float(values[SUMMARY_MAX]),
            "status": values[SUMMARY_STATUS:].astype(np.int64),
        }


INTEGRATORS = ("velocity-verlet", "jolt-beeman")
"""The integrators by name (make_integrator)."""


def make_integrator(name: str) -> VelocityVerlet | JoltBeeman:
    """A new integrator object by name: 'velocity-verlet' (VelocityVerlet) or 'jolt-beeman' (JoltBeeman)."""
    if name not in INTEGRATORS:
        raise SoilInputError(f"integrator must be one of {list(INTEGRATORS)}, got {name!r}")
    return JoltBeeman() if name == "jolt-beeman" else VelocityVerlet()


@dataclass
class StepController:
    """PID step-size control in Soderlind's form (docs/physics.md section 2) on a NORMALISED error.

    The local error of a step is the jolt-Beeman predictor/corrector gap, made
    dimensionless with the scene's own scales:

        e_i = max( |dx_i| / r_i ,  |dv_i| / V ),
        V   = max( sqrt(|g| r_mean),  largest speed seen in this run,  velocity_scale ),
        err = max( sqrt(mean_i e_i^2), max_i e_i / grain_factor )   (norm='rms', default)
        err = max_i e_i                                              (norm='max'),

    so a scene scaled to another gravity (E ~ g, times ~ sqrt(r/g), speeds ~ sqrt(g r))
    gets the same errors and the same steps with the same tolerance; an absolute
    tolerance (the paper's) does not (`normalise=False` reproduces that: err in m/s).

    The RMS norm (Hairer's choice for large systems) keeps one chattering contact (a
    stick/slip switch makes a force jump, whose gap shrinks only like dt) from setting the
    step of a whole bed; the max norm bounds every grain's error. The RMS over N grains
    dilutes one grain's error by sqrt(N), so a grain going unstable could hide in a large
    bed (it did: 20k grains at twice the advised step, BENCHMARKS.md); the guard term
    keeps every grain within grain_factor x tolerance.

    With c = (tolerance / err)^(1/k) (k = error order, 3 for jolt-Beeman), the step
    factor is rho = c_n^b1 c_(n-1)^b2 c_(n-2)^b3, b1 = kI + kP + kD, b2 = -(kP + 2 kD),
    b3 = kD, limited to [rho_min, rho_max]; dt_next = rho dt within [dt_min, dt_max].
    A step is rejected (and redone with dt * min(0.9 c_n, 0.9), at least rho_min) when
    rho < reject_below AND err > tolerance: a step that met the tolerance is kept even if
    the controller slows down for the next one. At dt_min a step is always accepted
    (counted in `forced`); a non-finite error at dt_min is a divergence.

    Defaults kI = 0.4, kP = 0.3, kD = 0.05: the closed loop on a log-linear error model,
    z^3 + (b1 - 1) z^2 + b2 z + b3, has its roots at |z| <= 0.72 (smooth, no ringing);
    Gustafsson's PI (0.3, 0.4, 0) is the classic alternative.
    """

    tolerance: float = 1e-4
    """Normalised local error per step [-]."""
    dt_max: float | None = None
    """Largest step [s]; None: the advisor's recommended limit for the model (soil.advisor)."""
    dt_min: float | None = None
    """Smallest step [s]; None: dt_max * 1e-4."""
    dt_initial: float | None = None
    """First step [s]; None: dt_max / 10 (the first step has no jolt history)."""
    k_i: float = 0.4
    """Integral gain [-]."""
    k_p: float = 0.3
    """Proportional gain [-]."""
    k_d: float = 0.05
    """Derivative gain [-]."""
    order: float = 3.0
    """k: the error estimate scales as dt^k [-]."""
    rho_min: float = 0.2
    """Smallest step factor per decision [-]."""
    rho_max: float = 2.0
    """Largest step factor per decision [-]."""
    reject_below: float = 0.9
    """A step whose factor rho falls below this (and whose error exceeds the tolerance) is redone [-]."""
    velocity_scale: float = 0.0
    """Extra floor of the velocity scale V [m/s] (e.g. a wheel speed); 0: from gravity and motion only."""
    normalise: bool = True
    """False: absolute error in m/s (the paper's original controller, breaks at milli-g)."""
    norm: str = "rms"
    """'rms' (root mean square over grains) or 'max' (the worst grain)."""
    grain_factor: float = 10.0
    """With norm='rms': no single grain's error may exceed grain_factor x tolerance [-]; inf: pure RMS."""
    history: list = field(default_factory=list, repr=False)
    """c values of the last accepted steps, newest last (internal)."""
    dt: float | None = field(default=None, repr=False)
    """The step the controller proposes next [s] (internal; None before setup)."""
    speed_seen: float = field(default=0.0, repr=False)
    """Largest speed seen so far [m/s] (internal)."""

    def __post_init__(self):
        if not (math.isfinite(self.tolerance) and self.tolerance > 0):
            raise SoilInputError(f"tolerance must be > 0, got {self.tolerance!r}")
        if self.norm not in ("rms", "max"):
            raise SoilInputError(f"norm must be 'rms' or 'max', got {self.norm!r}")
        if not self.grain_factor >= 1.0:
            raise SoilInputError(f"grain_factor must be >= 1 (inf: pure RMS), got {self.grain_factor!r}")
        if not 0 < self.rho_min < self.reject_below <= 1.0 < self.rho_max:
            raise SoilInputError(
                "need 0 < rho_min < reject_below <= 1 < rho_max, got "
                f"{self.rho_min}, {self.reject_below}, {self.rho_max}"
            )
        for name in ("dt_max", "dt_min", "dt_initial"):  # an infinite dt_max ended a run at once, untimed
            value = getattr(self, name)
            if value is not None and not (isinstance(value, numbers.Real) and math.isfinite(value) and value > 0):
                raise SoilInputError(f"{name} must be a finite number > 0 [s] or None, got {value!r}")
        if self.dt_min is not None and self.dt_max is not None and not self.dt_min <= self.dt_max:
            raise SoilInputError(f"dt_min must be <= dt_max, got {self.dt_min!r} s and {self.dt_max!r} s")
        if not (math.isfinite(self.order) and self.order > 0):  # 0 divided by zero, < 0 turned the control over
            raise SoilInputError(f"order must be a finite number > 0 (3 for jolt-Beeman), got {self.order!r}")
        if not (math.isfinite(self.velocity_scale) and self.velocity_scale >= 0):
            raise SoilInputError(f"velocity_scale must be a finite number >= 0 [m/s], got {self.velocity_scale!r}")
        self._check_gains()

    def _check_gains(self) -> None:
        """The gains must make a closed loop that settles: on a log-linear error model the step's
        log obeys z^3 + (b1 - 1) z^2 + b2 z + b3 (the class docstring), whose roots must lie inside the
        unit circle; and k_i > 0, without which the error never returns to the tolerance (k_i = -1 held
        the step at dt_min for a million steps, k_i = k_p = k_d = 0 froze it at its first value)."""
        gains = {"k_i": self.k_i, "k_p": self.k_p, "k_d": self.k_d}
        bad = [f"{k} = {v!r}" for k, v in gains.items() if not math.isfinite(v)]
        if bad:
            raise SoilInputError(f"the PID gains must be finite numbers, got {', '.join(bad)}")
        if not self.k_i > 0:
            raise SoilInputError(
                f"k_i must be > 0 (the integral gain brings the error to the tolerance), got {self.k_i!r}"
            )
        b1, b2, b3 = self.k_i + self.k_p + self.k_d, -(self.k_p + 2 * self.k_d), self.k_d
        largest = float(np.max(np.abs(np.roots([1.0, b1 - 1.0, b2, b3]))))
        if not largest < 1.0:
            raise SoilInputError(
                f"the PID gains k_i = {self.k_i!r}, k_p = {self.k_p!r}, k_d = {self.k_d!r} make a step control that "
                f"does not settle (a root of z^3 + (b1 - 1) z^2 + b2 z + b3 at |z| = {largest:.3g} >= 1); the "
                "defaults (0.4, 0.3, 0.05) and Gustafsson's PI (0.3, 0.4, 0) settle"
            )

    _OPTIONAL = ("dt_max", "dt_min", "dt_initial", "dt")

    def state_dict_units(self) -> dict[str, str]:
        """{key of state_dict(): its unit} (the fields' documented units; the tolerance is in m/s only
        when normalise is False)."""
        seconds = {"dt_max", "dt_min", "dt_initial", "dt"}
        speeds = {"velocity_scale", "speed_seen"}
        units = {f.name: "s" if f.name in seconds else "m/s" if f.name in speeds else "1" for f in fields(self)}
        units["tolerance"] = "1" if self.normalise else "m/s"
        units["norm"] = "text"
        return units

    def state_dict(self) -> dict:
        """Settings and control state as numpy scalars/arrays (None stored as NaN)."""
        data = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "history":
                data[f.name] = np.asarray(value, dtype=np.float64).reshape(-1)
            elif value is None:
                data[f.name] = np.float64(np.nan)
            elif isinstance(value, str):
                data[f.name] = np.str_(value)
            else:
                data[f.name] = np.asarray(value)[()]
        return data

    def load_state_dict(self, data: dict) -> None:
        """Restore from state_dict() (unknown keys are an error; missing keys keep their value)."""
        known = {f.name for f in fields(self)}
        unknown = set(data) - known
        if unknown:
            raise SoilInputError(f"step controller: unknown fields {sorted(unknown)}")
        for name, value in data.items():
            value = np.asarray(value)
            if name == "history":
                setattr(self, name, [float(v) for v in value.reshape(-1)])
            elif name in self._OPTIONAL:
                setattr(self, name, None if np.isnan(value) else float(value))
            elif value.dtype.kind == "U":
                setattr(self, name, str(value))
            elif value.dtype.kind == "b":
                setattr(self, name, bool(value))
            else:
                setattr(self, name, float(value))
        self.__post_init__()

    @property
    def exponents(self) -> tuple[float, float, float]:
        """(b1, b2, b3) of the Soderlind form."""
        return (self.k_i + self.k_p + self.k_d, -(self.k_p + 2.0 * self.k_d), self.k_d)

    def setup(self, sim) -> None:
        """Resolve the defaults for a Simulation (once; later calls keep the state of the control)."""
        model = sim.model
        advised = self.dt_max is None
        if advised:
            from .advisor import recommended_time_step

            self.dt_max = recommended_time_step(sim).dt_max
        if self.dt_min is None:
            self.dt_min = 1e-4 * self.dt_max
        if not 0 < self.dt_min <= self.dt_max:
            unset = ", unset: the advised limit of this simulation (soil.recommended_time_step)" if advised else ""
            raise SoilInputError(
                f"need 0 < dt_min <= dt_max, got dt_min = {self.dt_min!r} s and dt_max = {self.dt_max!r} s{unset}; "
                "lower dt_min or give dt_max"
            )
        if self.dt is None:
            self.dt = float(np.clip(self.dt_initial or 0.1 * self.dt_max, self.dt_min, self.dt_max))
        self._gravity_speed = math.sqrt(float(np.linalg.norm(model.gravity)) * float(model.radius_numpy().mean()))

    def error_scales(self) -> dict:
        """How JoltBeeman.read_summary should weigh the per-grain gaps for this controller:
        position_weight [-], scale_floor [m/s] (the velocity scale V before this step's speed),
        use_speed (whether V grows with this step's largest speed)."""
        if not self.normalise:
            return dict(position_weight=0.0, scale_floor=1.0, use_speed=False)
        return dict(
            position_weight=1.0,
            scale_floor=max(self._gravity_speed, self.speed_seen, self.velocity_scale),
            use_speed=True,
        )

    def error(self, summary: dict) -> float:
        """Normalised error [-] of a step from JoltBeeman.read_summary(**error_scales())."""
        if summary["nonfinite"]:
            return math.inf
        if self.normalise:
            self.speed_seen = max(self.speed_seen, summary["speed"])
        if self.norm == "max":
            return summary["max"]
        # RMS over grains, raised to max / grain_factor where one grain stands out (it must not hide)
        return max(summary["rms"], summary["max"] / self.grain_factor)

    def decide(self, err: float, dt: float) -> tuple[bool, float]:
        """(accept, next step [s]) for a step of length dt [s] with normalised error err."""
        k = self.order
        if not math.isfinite(err):
            return False, max(self.dt_min, self.rho_min * dt)
        # an error ~0 (free flight) would make c huge and dominate the next decisions
        c = (self.tolerance / max(err, 1e-3 * self.tolerance)) ** (1.0 / k)
        previous = self.history[-1] if self.history else 1.0
        before = self.history[-2] if len(self.history) > 1 else previous
        b1, b2, b3 = self.exponents
        rho = float(np.clip(c**b1 * previous**b2 * before**b3, self.rho_min, self.rho_max))
        if rho < self.reject_below and err > self.tolerance:
            return False, max(self.dt_min, dt * max(self.rho_min, min(0.9 * c, 0.9)))
        self.history = (self.history + [c])[-2:]
        return True, float(np.clip(rho * dt, self.dt_min, self.dt_max))
