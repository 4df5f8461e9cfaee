"""Warp kernels of the jolt-Beeman integrator and of the divergence checks.

Same pattern as soil.kernels: `make_integrator_kernels(hi, lo, law)` closes over the
precision types and is cached per combination. Inputs first, then outputs (_out).
No `from __future__ import annotations` here: Warp reads the annotations as types.

Summary arrays (reductions) use wp.atomic_max only: a maximum does not depend on the
order in which threads arrive, so the reductions are deterministic on GPU too.
"""

import warp as wp

from .contact import ContactLaw
from .kernels import make_kernels

# Columns of the per-step summary written by `beeman_correct` (shape (SUMMARY_COLUMNS,), dtype hi).
SUMMARY_POSITION_GAP = 0
"""max_i |x_corrected - x_predicted| / r_i [-]."""
SUMMARY_VELOCITY_GAP = 1
"""max_i max(|v_corr - v_pred|, r_i |w_corr - w_pred|) [m/s]."""
SUMMARY_SPEED = 2
"""max_i max(|v_i|, r_i |w_i|) after the step [m/s]."""
SUMMARY_NONFINITE = 3
"""1 if any position, velocity or spin is NaN/inf after the step, else 0."""
SUMMARY_WORST = 4
"""Index of a particle with a non-finite state (when flagged), else -1 (as hi)."""
SUMMARY_COLUMNS = 5

# Columns of the divergence-check summary (shape (CHECK_COLUMNS,), dtype hi).
CHECK_SPEED = 0
"""max_i max(|v_i|, r_i |w_i|) [m/s]."""
CHECK_OVERLAP = 1
"""max over contacts of overlap / radius [-] (particle-particle and boundaries)."""
CHECK_NONFINITE = 2
"""1 if any particle state is not finite."""
CHECK_COLUMNS = 3

_cache: dict = {}


def make_integrator_kernels(hi, lo, law: ContactLaw):
    """The jolt-Beeman and check kernels for precision types (hi, lo)."""
    key = (hi, lo, law)
    if key in _cache:
        return _cache[key]
    vec_hi = wp.types.vector(3, hi)
    soil_kernels = make_kernels(hi, lo, law)
    boundary_contact = soil_kernels["boundary_contact"]
    acceleration = soil_kernels["acceleration_of"]  # (force, inv_mass as lo, gravity) -> [m/s^2]

    @wp.func
    def backward_step(a: vec_hi, a_previous: vec_hi, ratio: hi):
        """Acceleration one step of the NEW length dt before t, with constant jolt.

        The jolt is (a - a_previous) / dt_previous; extrapolated back by dt it gives
        a(t - dt) = a - (dt / dt_previous) (a - a_previous). With this `a_minus` the
        fixed-step Beeman formulas are exact for a constant jolt at any step ratio.
        ratio = 0 (no history) means zero jolt: a_minus = a.
        """
        return a - ratio * (a - a_previous)

    @wp.kernel(module="unique")
    def beeman_predict(
        x_in: wp.array(dtype=vec_hi),
        v_in: wp.array(dtype=vec_hi),
        w_in: wp.array(dtype=vec_hi),
        force_in: wp.array(dtype=vec_hi),
        torque_in: wp.array(dtype=vec_hi),
        force_previous_in: wp.array(dtype=vec_hi),
        torque_previous_in: wp.array(dtype=vec_hi),
        step_previous_in: wp.array(dtype=hi),
        inv_mass: wp.array(dtype=lo),
        inv_inertia: wp.array(dtype=lo),
        gravity: vec_hi,
        dt: hi,
        # outputs
        x_out: wp.array(dtype=vec_hi),
        v_out: wp.array(dtype=vec_hi),
        w_out: wp.array(dtype=vec_hi),
        force_previous_out: wp.array(dtype=vec_hi),
        torque_previous_out: wp.array(dtype=vec_hi),
        step_previous_out: wp.array(dtype=hi),
    ):
        """Explicit jolt-Beeman prediction (no force evaluation).

        x+ = x + v dt + (4 a - a_minus) dt^2 / 6   (Beeman; = Taylor with constant jolt)
        v_pred = v + (3 a - a_minus) dt / 2        (Taylor with constant jolt; the forces
                                                    of the new state see this velocity)
        """
        i = wp.tid()
        h_prev = step_previous_in[0]
        ratio = hi(0.0)
        if h_prev > hi(0.0):
            ratio = dt / h_prev
        inv_i = hi(inv_inertia[i])
        a = acceleration(force_in[i], inv_mass[i], gravity)
        a_minus = backward_step(a, acceleration(force_previous_in[i], inv_mass[i], gravity), ratio)
        alpha = torque_in[i] * inv_i
        alpha_minus = backward_step(alpha, torque_previous_in[i] * inv_i, ratio)
        v = v_in[i]
        x_out[i] = x_in[i] + dt * v + (dt * dt / hi(6.0)) * (hi(4.0) * a - a_minus)
        v_out[i] = v + (hi(0.5) * dt) * (hi(3.0) * a - a_minus)
        w_out[i] = w_in[i] + (hi(0.5) * dt) * (hi(3.0) * alpha - alpha_minus)
        force_previous_out[i] = force_in[i]
        torque_previous_out[i] = torque_in[i]
        if i == 0:
            step_previous_out[0] = dt

    @wp.kernel(module="unique")
    def beeman_correct(
        v_in: wp.array(dtype=vec_hi),
        w_in: wp.array(dtype=vec_hi),
        x_new: wp.array(dtype=vec_hi),
        force_in: wp.array(dtype=vec_hi),
        torque_in: wp.array(dtype=vec_hi),
        force_previous_in: wp.array(dtype=vec_hi),
        torque_previous_in: wp.array(dtype=vec_hi),
        step_previous_in: wp.array(dtype=hi),
        force_new: wp.array(dtype=vec_hi),
        torque_new: wp.array(dtype=vec_hi),
        inv_mass: wp.array(dtype=lo),
        inv_inertia: wp.array(dtype=lo),
        radius: wp.array(dtype=lo),
        gravity: vec_hi,
        dt: hi,
        # outputs
        v_out: wp.array(dtype=vec_hi),
        w_out: wp.array(dtype=vec_hi),
        summary_out: wp.array(dtype=hi),
        gaps_out: wp.array2d(dtype=hi),
    ):
        """Beeman correction with the new forces, and the predictor/corrector gap.

        v+ = v + (2 a+ + 5 a - a_minus) dt / 6. The gap to the prediction is
        v+ - v_pred = (a+ - 2 a + a_minus) dt / 3 (a second difference: O(dt^3) where
        the motion is smooth); the position the new acceleration would give,
        x + v dt + (a+ + 2 a) dt^2 / 6, differs from the predicted x+ by half that
        times dt. Positions stay as predicted, so the new forces belong to them.
        """
        i = wp.tid()
        h_prev = step_previous_in[0]
        ratio = hi(0.0)
        if h_prev > hi(0.0):
            ratio = dt / h_prev
        inv_i = hi(inv_inertia[i])
        a = acceleration(force_in[i], inv_mass[i], gravity)
        a_minus = backward_step(a, acceleration(force_previous_in[i], inv_mass[i], gravity), ratio)
        a_plus = acceleration(force_new[i], inv_mass[i], gravity)
        alpha = torque_in[i] * inv_i
        alpha_minus = backward_step(alpha, torque_previous_in[i] * inv_i, ratio)
        alpha_plus = torque_new[i] * inv_i
        v = v_in[i] + (dt / hi(6.0)) * (hi(2.0) * a_plus + hi(5.0) * a - a_minus)
        w = w_in[i] + (dt / hi(6.0)) * (hi(2.0) * alpha_plus + hi(5.0) * alpha - alpha_minus)
        v_out[i] = v
        w_out[i] = w

        r = hi(radius[i])
        second = a_plus - hi(2.0) * a + a_minus
        velocity_gap = wp.length(second) * dt / hi(3.0)
        spin_gap = wp.length(alpha_plus - hi(2.0) * alpha + alpha_minus) * dt / hi(3.0) * r
        position_gap = hi(0.5) * dt * velocity_gap / r
        gaps_out[i, 0] = position_gap  # per particle, for the RMS error norm
        gaps_out[i, 1] = wp.max(velocity_gap, spin_gap)
        wp.atomic_max(summary_out, SUMMARY_POSITION_GAP, position_gap)
        wp.atomic_max(summary_out, SUMMARY_VELOCITY_GAP, wp.max(velocity_gap, spin_gap))
        wp.atomic_max(summary_out, SUMMARY_SPEED, wp.max(wp.length(v), r * wp.length(w)))
        if not (wp.isfinite(v) and wp.isfinite(w) and wp.isfinite(x_new[i])
                and wp.isfinite(velocity_gap) and wp.isfinite(spin_gap)):
            wp.atomic_max(summary_out, SUMMARY_NONFINITE, hi(1.0))
            wp.atomic_max(summary_out, SUMMARY_WORST, hi(i))

    @wp.kernel(module="unique")
    def divergence_metrics(
        grid: wp.uint64,
        x_in: wp.array(dtype=vec_hi),
        v_in: wp.array(dtype=vec_hi),
        w_in: wp.array(dtype=vec_hi),
        radius: wp.array(dtype=lo),
        inv_mass: wp.array(dtype=lo),
        boundary_kind: wp.array(dtype=wp.int32),
        boundary_geometry: wp.array2d(dtype=hi),
        boundary_displacement: wp.array(dtype=vec_hi),
        search_radius: hi,
        # outputs
        speed_out: wp.array(dtype=hi),
        overlap_out: wp.array(dtype=hi),
        summary_out: wp.array(dtype=hi),
    ):
        """Per particle: speed [m/s] and the largest overlap / radius [-]; maxima into summary_out.

        A non-finite particle gets speed = overlap = +inf so that the host can locate it.
        """
        i = wp.tid()
        xi = x_in[i]
        ri = hi(radius[i])
        if not (wp.isfinite(xi) and wp.isfinite(v_in[i]) and wp.isfinite(w_in[i])):
            inf = hi(wp.inf)
            speed_out[i] = inf
            overlap_out[i] = inf
            wp.atomic_max(summary_out, CHECK_NONFINITE, hi(1.0))
            return
        worst = hi(0.0)
        for j in wp.hash_grid_query(grid, xi, search_radius):
            if j != i:
                rj = hi(radius[j])
                overlap = ri + rj - wp.length(x_in[j] - xi)
                worst = wp.max(worst, overlap / wp.min(ri, rj))
        if inv_mass[i] > lo(0.0):
            for b in range(boundary_kind.shape[0]):
                overlap, n = boundary_contact(boundary_kind[b], boundary_geometry, b, xi - boundary_displacement[b], ri)
                worst = wp.max(worst, overlap / ri)
        speed = wp.max(wp.length(v_in[i]), ri * wp.length(w_in[i]))  # spin counts at the surface
        speed_out[i] = speed
        overlap_out[i] = worst
        wp.atomic_max(summary_out, CHECK_SPEED, speed)
        wp.atomic_max(summary_out, CHECK_OVERLAP, worst)

    kernels = dict(beeman_predict=beeman_predict, beeman_correct=beeman_correct,
                   divergence_metrics=divergence_metrics)
    _cache[key] = kernels
    return kernels
