"""Contact detection + force evaluation on the neighbour grid."""

from __future__ import annotations

import numpy as np
import warp as wp

from .kernels import make_kernels
from .model import SoilModel
from .state import SoilState
from .boundaries import update_acceleration
from .control import SoilControl


def _grid_dim(particle_count: int) -> int:
    return int(np.clip(2 * round(particle_count ** (1.0 / 3.0)), 8, 128))


class ContactSolver:
    """Finds contacts with a Warp HashGrid and evaluates the contact law for every particle.

    The reactions on bodies (wheels) and boundaries (walls) are written per particle into
    scratch arrays of shape (particle_count, columns), one column per body and one per
    boundary built with report=True, then summed per column in a fixed order (chunks of
    particles, then the chunks): deterministic, no atomics. The scratch costs 52 bytes
    (double; 28 single) per particle per column, which is why walls that need no force
    can opt out (SoilBuilder.add_plane(..., report=False)).
    """

    def __init__(self, model: SoilModel):
        self.model = model
        prec = model.precision
        device = model.device
        self.kernels = make_kernels(prec.hi, prec.lo, model.law)
        dim = _grid_dim(model.particle_count)
        self.grid = wp.HashGrid(dim, dim, dim, device=device, dtype=prec.hi)
        self.overflow = wp.zeros(1, dtype=wp.int32, device=device)
        self._chunk = 256
        self._body = _WrenchScratch(model.particle_count, model.body_count, self._chunk, prec.vec_hi, device)
        self.body_column = wp.array(np.arange(model.body_count, dtype=np.int32), dtype=wp.int32, device=device)
        """Scratch column of each body (all of them), shape (body_count,), int32."""
        reports = model.boundary_reports
        columns = np.where(reports, np.cumsum(reports) - 1, -1).astype(np.int32)
        self.boundary_column = (model.boundary_column if model.boundary_column is not None
                                else wp.array(columns, dtype=wp.int32, device=device))
        """Scratch column of each boundary (-1: not reported), shape (boundary_count,), int32."""
        self._boundary = _WrenchScratch(model.particle_count, int(reports.sum()), self._chunk, prec.vec_hi, device)
        self.evaluations = 0
        """Number of force evaluations so far (the cost unit of integrators)."""

    def compute(self, state_in: SoilState, state_out: SoilState, control: SoilControl, dt: float) -> None:
        """Forces at state_out's positions/velocities (and boundary positions/velocities);
        history read from state_in, written to state_out. Then the wrenches on bodies and
        boundaries and the loaded boundaries' accelerations (soil.boundaries) of state_out.

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
                model.boundary_kind, model.boundary_geometry, model.boundary_material, self.boundary_column,
                state_out.boundary_displacement, state_out.boundary_velocity,
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
                self._body.force, self._body.torque, self._body.contact,
                self._boundary.force, self._boundary.torque, self._boundary.contact,
            ],
            device=model.device,
        )
        if model.body_count:
            self._sum(self._body, self.body_column, state_out.body_force, state_out.body_torque,
                      state_out.body_contacts)
        if model.boundary_count:
            self._sum(self._boundary, self.boundary_column, state_out.boundary_force, state_out.boundary_torque,
                      state_out.boundary_contacts)
            update_acceleration(model, state_out, control)
        self.evaluations += 1

    def _sum(self, scratch: "_WrenchScratch", column: wp.array, force_out, torque_out, contact_out) -> None:
        """Per-item totals from the scratch: chunk sums in index order, then the chunks in order."""
        device = self.model.device
        if scratch.columns:
            wp.launch(self.kernels["wrench_partial"], dim=(scratch.partial_force.shape[0], scratch.columns),
                      inputs=[scratch.force, scratch.torque, scratch.contact, self._chunk],
                      outputs=[scratch.partial_force, scratch.partial_torque, scratch.partial_contact],
                      device=device)
        wp.launch(self.kernels["wrench_total"], dim=column.shape[0],
                  inputs=[scratch.partial_force, scratch.partial_torque, scratch.partial_contact, column],
                  outputs=[force_out, torque_out, contact_out], device=device)

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
                    state.boundary_displacement, model.precision.hi(model.search_radius)],
            outputs=[energy], device=model.device)
        return float(np.sum(energy.numpy(), dtype=np.float64))


class _WrenchScratch:
    """Per-particle reactions, shape (particle_count, columns), and their chunk sums, shape
    (chunks, columns). With no columns the arrays shrink to one element (never written)."""

    def __init__(self, particle_count: int, columns: int, chunk: int, vec_hi, device: str):
        self.columns = columns
        rows = particle_count if columns else 1
        chunks = (particle_count + chunk - 1) // chunk if columns else 1
        width = max(columns, 1)
        self.force = wp.zeros((rows, width), dtype=vec_hi, device=device)
        self.torque = wp.zeros((rows, width), dtype=vec_hi, device=device)
        self.contact = wp.zeros((rows, width), dtype=wp.int32, device=device)
        self.partial_force = wp.zeros((chunks, width), dtype=vec_hi, device=device)
        self.partial_torque = wp.zeros((chunks, width), dtype=vec_hi, device=device)
        self.partial_contact = wp.zeros((chunks, width), dtype=wp.int32, device=device)
