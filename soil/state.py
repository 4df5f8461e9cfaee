"""The mutable soil state: what changes every step."""

from __future__ import annotations

import numpy as np
import warp as wp


class SoilState:
    """Particle kinematics, the latest forces and the per-contact history.

    Contact history is stored per particle in `capacity` slots keyed by the partner:
    a particle index, or particle_count + boundary index for boundaries. Because the
    key is the partner, history survives any rebuild of the neighbour grid.
    """

    def __init__(self, particle_count: int, capacity: int, vec_hi, device: str, body_count: int = 0,
                 boundary_count: int = 0):
        n = particle_count
        scalar = vec_hi._wp_scalar_type_
        self.position = wp.zeros(n, dtype=vec_hi, device=device)
        """Particle centre positions [m], shape (particle_count,)."""
        self.velocity = wp.zeros(n, dtype=vec_hi, device=device)
        """Particle velocities [m/s], shape (particle_count,)."""
        self.angular_velocity = wp.zeros(n, dtype=vec_hi, device=device)
        """Particle angular velocities [rad/s], shape (particle_count,)."""
        self.force = wp.zeros(n, dtype=vec_hi, device=device)
        """Contact + external force on each particle at the state's time [N], shape (particle_count,)."""
        self.torque = wp.zeros(n, dtype=vec_hi, device=device)
        """Contact torque on each particle about its centre [N m], shape (particle_count,)."""
        self.contact_partner = wp.full((n, capacity), -1, dtype=wp.int32, device=device)
        """Partner key per history slot [-], shape (particle_count, capacity)."""
        self.contact_tangential = wp.zeros((n, capacity), dtype=vec_hi, device=device)
        """Accumulated tangential displacement per slot [m], shape (particle_count, capacity)."""
        self.contact_rolling = wp.zeros((n, capacity), dtype=vec_hi, device=device)
        """Accumulated rolling angle per slot [rad], shape (particle_count, capacity)."""
        self.contact_count = wp.zeros(n, dtype=wp.int32, device=device)
        """Number of used history slots (= contacts) per particle, shape (particle_count,)."""
        self.force_previous = wp.zeros(n, dtype=vec_hi, device=device)
        """Force of the previous step's state (time - step_previous) [N], shape (particle_count,).
        Multi-step integrators (jolt-Beeman) take the jolt from it."""
        self.torque_previous = wp.zeros(n, dtype=vec_hi, device=device)
        """Torque of the previous step's state [N m], shape (particle_count,)."""
        self.step_previous = wp.zeros(1, dtype=scalar, device=device)
        """Length of the step that produced this state [s], shape (1,); 0 = no history
        (start-up: jolt-Beeman then assumes zero jolt)."""
        self.body_force = wp.zeros(body_count, dtype=vec_hi, device=device)
        """Soil force on each body (wheel) at the state's time, world [N], shape (body_count,)."""
        self.body_torque = wp.zeros(body_count, dtype=vec_hi, device=device)
        """Soil torque on each body about its hub, world [N m], shape (body_count,)."""
        self.body_contacts = wp.zeros(body_count, dtype=wp.int32, device=device)
        """Number of particles touching each body, shape (body_count,)."""
        nb = boundary_count
        self.boundary_displacement = wp.zeros(nb, dtype=vec_hi, device=device)
        """Translation of each boundary from its initial geometry (model.boundary_geometry) [m],
        shape (boundary_count,)."""
        self.boundary_velocity = wp.zeros(nb, dtype=vec_hi, device=device)
        """Translation velocity of each boundary [m/s], shape (boundary_count,)."""
        self.boundary_acceleration = wp.zeros(nb, dtype=scalar, device=device)
        """Acceleration of each loaded boundary along its free direction at the state's time [m/s^2],
        shape (boundary_count,); 0 for prescribed motion (soil.boundaries)."""
        self.boundary_acceleration_previous = wp.zeros(nb, dtype=scalar, device=device)
        """boundary_acceleration of the previous step's state [m/s^2], shape (boundary_count,) (jolt-Beeman)."""
        self.boundary_force = wp.zeros(nb, dtype=vec_hi, device=device)
        """Force of the grains on each boundary at the state's time, world [N], shape (boundary_count,);
        zero for boundaries built with report=False."""
        self.boundary_torque = wp.zeros(nb, dtype=vec_hi, device=device)
        """Torque of the grains on each boundary about its reference point (a plane's point, a box's
        centre, both displaced with the boundary), world [N m], shape (boundary_count,); rolling
        resistance torques included."""
        self.boundary_contacts = wp.zeros(nb, dtype=wp.int32, device=device)
        """Number of particles touching each boundary, shape (boundary_count,)."""
        self.time = 0.0
        """Simulated time [s] (a Python float, i.e. double precision)."""
        self.forces_valid = False
        """True when force/torque/history belong to the positions (after a step or a restore)."""

    @classmethod
    def for_model(cls, model, capacity: int) -> "SoilState":
        """A zero state sized for `model` (particles, bodies, boundaries) with `capacity` history slots."""
        return cls(model.particle_count, capacity, model.precision.vec_hi, model.device, model.body_count,
                   model.boundary_count)

    @property
    def boundary_count(self) -> int:
        return int(self.boundary_force.shape[0])

    @property
    def capacity(self) -> int:
        return int(self.contact_partner.shape[1])

    @property
    def arrays(self) -> dict[str, wp.array]:
        return {name: value for name, value in vars(self).items() if isinstance(value, wp.array)}

    def assign(self, other: "SoilState") -> None:
        """Copy every array and the time from `other` (same shapes)."""
        for name, array in self.arrays.items():
            source = getattr(other, name)
            if source.shape != array.shape:
                raise ValueError(f"state.{name}: shape {source.shape} does not match {array.shape}")
            wp.copy(array, source)
        self.time = other.time
        self.forces_valid = other.forces_valid

    def grow_capacity(self, capacity: int) -> None:
        """Widen the history storage to `capacity` slots per particle, keeping the history."""
        old = self.capacity
        if capacity <= old:
            return
        device = self.position.device
        for name, fill in (("contact_partner", -1), ("contact_tangential", 0), ("contact_rolling", 0)):
            array = getattr(self, name)
            values = array.numpy()
            wider = np.full((values.shape[0], capacity) + values.shape[2:], fill, dtype=values.dtype)
            wider[:, :old] = values
            setattr(self, name, wp.array(wider, dtype=array.dtype, device=device))

    def to_numpy(self) -> dict[str, np.ndarray]:
        """Every array as a numpy copy (on the CPU .numpy() is a view that later steps overwrite) and the time."""
        data = {name: array.numpy().copy() for name, array in self.arrays.items()}
        data["time"] = np.float64(self.time)
        return data

    def load_numpy(self, data: dict) -> None:
        """Fill this state from `to_numpy()` output (history capacity may differ: it is grown).

        Boundary arrays missing from `data` (files written before boundaries moved) are zero:
        the boundaries are at their initial geometry, at rest.
        """
        capacity = data["contact_partner"].shape[1]
        if capacity > self.capacity:
            self.grow_capacity(capacity)
        for name, array in self.arrays.items():
            if name not in data:
                if name.startswith("boundary_"):
                    array.zero_()
                    continue
                raise KeyError(f"state data has no {name!r} array")
            values = np.asarray(data[name])
            if values.shape[:1] != tuple(array.shape[:1]):
                raise ValueError(f"state.{name}: saved shape {values.shape} does not fit {array.shape} "
                                 "(a different scene?)")
            if name.startswith("contact_") and values.ndim >= 2 and values.shape[1] < array.shape[1]:
                fill = -1 if name == "contact_partner" else 0
                padded = np.full(array.shape + ((3,) if values.ndim == 3 else ()), fill, dtype=values.dtype)
                padded[:, : values.shape[1]] = values
                values = padded
            array.assign(values.astype(array.numpy().dtype, copy=False))
        self.time = float(data["time"])
        self.forces_valid = True  # a saved state carries the forces of its own step
