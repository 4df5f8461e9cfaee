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
        # per-particle wheel wrenches, summed per body in a fixed order (deterministic)
        bodies = max(model.body_count, 1)
        vec_hi = prec.vec_hi
        self._body_force = wp.zeros((model.particle_count, bodies), dtype=vec_hi, device=model.device)
        self._body_torque = wp.zeros((model.particle_count, bodies), dtype=vec_hi, device=model.device)
        self._body_contact = wp.zeros((model.particle_count, bodies), dtype=wp.int32, device=model.device)
        self._chunk = 256
        chunks = (model.particle_count + self._chunk - 1) // self._chunk
        self._partial_force = wp.zeros((chunks, bodies), dtype=vec_hi, device=model.device)
        self._partial_torque = wp.zeros((chunks, bodies), dtype=vec_hi, device=model.device)
        self._partial_contact = wp.zeros((chunks, bodies), dtype=wp.int32, device=model.device)
        self.evaluations = 0
        """Number of force evaluations so far (the cost unit of integrators)."""

    def compute(self, state_in: SoilState, state_out: SoilState, control: SoilControl, dt: float) -> None:
        """Forces at state_out's positions/velocities; history read from state_in, written to state_out.

        state_in and state_out must be different objects (history is double-buffered).
        """
        model = self.model
        hi = model.precision.hi
        self.grid.build(state_out.position, model.search_radius)
        control.push()
        wp.launch(
            self.kernels["contact_forces"],
            dim=model.particle_count,
            inputs=[
                self.grid.id, state_out.position, state_out.velocity, state_out.angular_velocity,
                model.radius, model.mass, model.inv_mass, model.material, model.pair, model.material_count,
                model.boundary_kind, model.boundary_geometry, model.boundary_material,
                control.external_force, model.body_kind, model.body_shape, model.body_mesh, model.body_material,
                model.mesh_points, model.mesh_indices, model.body_point_offset, model.body_index_offset,
                control.body_position, control.body_rotation, control.body_velocity, control.body_angular_velocity,
                hi(model.search_radius), hi(dt),
                state_in.contact_partner, state_in.contact_tangential, state_in.contact_rolling,
                state_in.contact_count,
            ],
            outputs=[
                state_out.force, state_out.torque, state_out.contact_partner, state_out.contact_tangential,
                state_out.contact_rolling, state_out.contact_count, self.overflow,
                self._body_force, self._body_torque, self._body_contact,
            ],
            device=model.device,
        )
        if model.body_count:
            self._sum_body_wrenches(state_out)
        self.evaluations += 1

    def _sum_body_wrenches(self, state_out: SoilState) -> None:
        model = self.model
        wp.launch(self.kernels["body_wrench_partial"], dim=(self._partial_force.shape[0], model.body_count),
                  inputs=[self._body_force, self._body_torque, self._body_contact, self._chunk],
                  outputs=[self._partial_force, self._partial_torque, self._partial_contact], device=model.device)
        wp.launch(self.kernels["body_wrench_total"], dim=model.body_count,
                  inputs=[self._partial_force, self._partial_torque, self._partial_contact],
                  outputs=[state_out.body_force, state_out.body_torque, state_out.body_contacts],
                  device=model.device)

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
