"""Time integrators. Every integrator has step(model, state_in, state_out, control, dt, contacts)."""

from __future__ import annotations

import warp as wp

from .control import SoilControl
from .model import SoilModel
from .solver import ContactSolver
from .state import SoilState


class VelocityVerlet:
    """Plain explicit velocity Verlet (kick-drift-kick), one force evaluation per step.

    Velocity-dependent forces (damping, friction) see the half-step velocity, as in
    LAMMPS' fix nve/sphere.
    """

    name = "verlet"

    def step(self, model: SoilModel, state_in: SoilState, state_out: SoilState, control: SoilControl,
             dt: float, contacts: ContactSolver) -> None:
        prec = model.precision
        gravity = prec.vec_hi(*model.gravity)
        hi_dt = prec.hi(dt)
        wp.launch(contacts.kernels["kick_drift"], dim=model.particle_count,
                  inputs=[state_in.position, state_in.velocity, state_in.angular_velocity, state_in.force,
                          state_in.torque, model.inv_mass, model.inv_inertia, gravity, hi_dt],
                  outputs=[state_out.position, state_out.velocity, state_out.angular_velocity],
                  device=model.device)
        contacts.compute(state_in, state_out, control, dt)
        wp.launch(contacts.kernels["kick"], dim=model.particle_count,
                  inputs=[state_out.force, state_out.torque, model.inv_mass, model.inv_inertia, gravity, hi_dt],
                  outputs=[state_out.velocity, state_out.angular_velocity], device=model.device)
        state_out.time = state_in.time + dt
