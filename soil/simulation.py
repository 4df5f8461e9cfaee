"""A soil simulation: model + double-buffered state + control + integrator."""

from __future__ import annotations

import numpy as np

from .control import SoilControl
from .integrator import VelocityVerlet
from .model import SoilModel
from .solver import ContactSolver
from .state import SoilState


class SimulationDiverged(RuntimeError):
    """The simulation became unstable; `last_good` holds the last good state as numpy arrays."""

    def __init__(self, message: str, last_good: dict | None = None):
        super().__init__(message)
        self.last_good = last_good


class Simulation:
    """Steps a soil model in time.

    `state` is always the current state; a step writes into a second buffer and swaps,
    so a step that fails (history overflow, divergence) leaves `state` untouched.
    """

    def __init__(self, model: SoilModel, state: SoilState, control: SoilControl | None = None, integrator=None):
        self.model = model
        self.control = control or SoilControl(model.particle_count, model.precision.vec_hi, model.device,
                                              model.body_count)
        self.integrator = integrator or VelocityVerlet()
        self.contacts = ContactSolver(model)
        self.state = state
        self._next = SoilState(model.particle_count, state.capacity, model.precision.vec_hi, model.device,
                               model.body_count)
        self.steps = 0
        if not state.forces_valid:  # a restored state keeps its own forces: restarts stay bit-identical
            self.refresh_forces()

    @property
    def time(self) -> float:
        """Simulated time [s]."""
        return self.state.time

    def refresh_forces(self) -> None:
        """Recompute forces (and contact list) of the current state without moving it."""
        while True:
            self._next.assign(self.state)
            self.contacts.compute(self.state, self._next, self.control, 0.0)
            if not self._overflowed():
                break
        self.state, self._next = self._next, self.state
        self.state.forces_valid = True

    def _overflowed(self) -> bool:
        if not self.contacts.take_overflow():
            return False
        capacity = 2 * self.state.capacity
        self.state.grow_capacity(capacity)
        self._next.grow_capacity(capacity)
        return True

    def step(self, dt: float) -> None:
        """Advance by dt [s]."""
        if not dt > 0:
            raise ValueError(f"dt must be > 0 [s], got {dt!r}")
        while True:
            self.integrator.step(self.model, self.state, self._next, self.control, dt, self.contacts)
            if not self._overflowed():
                break  # else: more contacts than history slots; slots were widened, redo the step
        self.state, self._next = self._next, self.state
        self.state.forces_valid = True
        self.steps += 1

    def run(self, duration: float, dt: float, callback=None, check_every: int = 200) -> None:
        """Advance by `duration` [s] with fixed steps dt [s]; callback(sim) after each step."""
        steps = int(round(duration / dt))
        for k in range(steps):
            self.step(dt)
            if callback is not None:
                callback(self)
            if (k + 1) % check_every == 0:
                self.check_finite()

    def check_finite(self) -> None:
        """Raise SimulationDiverged if any particle position or velocity is not finite."""
        x = self.state.position.numpy()
        v = self.state.velocity.numpy()
        bad = ~(np.isfinite(x).all(axis=1) & np.isfinite(v).all(axis=1))
        if bad.any():
            raise SimulationDiverged(
                f"non-finite particle state at t = {self.time:.6g} s (step {self.steps}), "
                f"{int(bad.sum())} particle(s), first index {int(np.argmax(bad))}")

    # -- diagnostics (host side) ------------------------------------------------
    def positions(self) -> np.ndarray:
        """Particle positions [m], shape (particle_count, 3), float64."""
        return self.state.position.numpy().astype(np.float64)

    def velocities(self) -> np.ndarray:
        """Particle velocities [m/s], shape (particle_count, 3), float64."""
        return self.state.velocity.numpy().astype(np.float64)

    def angular_velocities(self) -> np.ndarray:
        """Particle angular velocities [rad/s], shape (particle_count, 3), float64."""
        return self.state.angular_velocity.numpy().astype(np.float64)

    def kinetic_energy(self) -> float:
        """Translational + rotational kinetic energy of the free particles [J]."""
        mass = self.model.mass_numpy()
        free = self.model.inv_mass.numpy() > 0
        radius = self.model.radius_numpy()
        v = self.velocities()
        w = self.angular_velocities()
        rotating = self.model.inv_inertia.numpy() > 0
        trans = 0.5 * np.sum(mass[free] * np.sum(v[free] ** 2, axis=1))
        rot = 0.5 * np.sum((0.4 * mass * radius**2)[rotating] * np.sum(w[rotating] ** 2, axis=1))
        return float(trans + rot)

    def gravity_energy(self) -> float:
        """Potential energy in gravity, -sum m g.x [J] (zero at the origin)."""
        free = self.model.inv_mass.numpy() > 0
        mass = self.model.mass_numpy()
        return float(-np.sum(mass[free] * (self.positions()[free] @ self.model.gravity)))

    def elastic_energy(self) -> float:
        """Hertz strain energy in all contacts [J]."""
        return self.contacts.elastic_energy(self.state)

    def total_energy(self) -> float:
        """Kinetic + gravity + elastic energy [J]."""
        return self.kinetic_energy() + self.gravity_energy() + self.elastic_energy()
