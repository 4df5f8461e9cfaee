"""Contact detection + force evaluation on the neighbour grid."""

from __future__ import annotations

import numpy as np
import warp as wp

from .kernels import make_kernels
from .model import SoilModel
from .state import SoilState
from .control import SoilControl


def _grid_dim(particle_count: int) -> int:
    return int(np.clip(2 * round(particle_count ** (1.0 / 3.0)), 8, 128))


class ContactSolver:
    """Finds contacts with a Warp HashGrid and evaluates the contact law for every particle."""

    def __init__(self, model: SoilModel):
        self.model = model
        prec = model.precision
        self.kernels = make_kernels(prec.hi, prec.lo, model.law)
        dim = _grid_dim(model.particle_count)
        self.grid = wp.HashGrid(dim, dim, dim, device=model.device, dtype=prec.hi)
        self.overflow = wp.zeros(1, dtype=wp.int32, device=model.device)
        self.evaluations = 0
        """Number of force evaluations so far (the cost unit of integrators)."""

    def compute(self, state_in: SoilState, state_out: SoilState, control: SoilControl, dt: float) -> None:
        """Forces at state_out's positions/velocities; history read from state_in, written to state_out.

        state_in and state_out must be different objects (history is double-buffered).
        """
        model = self.model
        hi = model.precision.hi
        self.grid.build(state_out.position, model.search_radius)
        wp.launch(
            self.kernels["contact_forces"],
            dim=model.particle_count,
            inputs=[
                self.grid.id, state_out.position, state_out.velocity, state_out.angular_velocity,
                model.radius, model.inv_mass, model.material, model.pair, model.material_count,
                model.boundary_kind, model.boundary_geometry, model.boundary_material,
                control.external_force, hi(model.search_radius), hi(dt),
                state_in.contact_partner, state_in.contact_tangential, state_in.contact_rolling,
                state_in.contact_count,
            ],
            outputs=[
                state_out.force, state_out.torque, state_out.contact_partner, state_out.contact_tangential,
                state_out.contact_rolling, state_out.contact_count, self.overflow,
            ],
            device=model.device,
        )
        self.evaluations += 1

    def take_overflow(self) -> bool:
        """True if a particle had more contacts than its history slots since the last call."""
        flag = bool(self.overflow.numpy()[0])
        if flag:
            self.overflow.zero_()
        return flag

    def elastic_energy(self, state: SoilState) -> float:
        """Hertz strain energy stored in all contacts [J]."""
        model = self.model
        energy = wp.zeros(model.particle_count, dtype=model.precision.hi, device=model.device)
        self.grid.build(state.position, model.search_radius)
        wp.launch(
            self.kernels["elastic_energy"], dim=model.particle_count,
            inputs=[self.grid.id, state.position, model.radius, model.material, model.pair, model.material_count,
                    model.boundary_kind, model.boundary_geometry, model.boundary_material,
                    model.precision.hi(model.search_radius)],
            outputs=[energy], device=model.device)
        return float(np.sum(energy.numpy(), dtype=np.float64))
