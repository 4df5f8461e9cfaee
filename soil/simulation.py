"""A soil simulation: model + double-buffered state + control + integrator."""

from __future__ import annotations

import math

import numpy as np

from .control import SoilControl
from .integrator import JoltBeeman, StepController, VelocityVerlet
from .kernels import BOUNDARY_BOX
from .model import SoilModel
from .solver import ContactSolver
from .stability import DivergenceMonitor, SimulationDiverged  # noqa: F401 (SimulationDiverged re-exported)
from .state import SoilState


class Simulation:
    """Steps a soil model in time.

    `state` is always the current state; a step writes into a second buffer and swaps,
    so a step that fails (history overflow, divergence) leaves `state` untouched.
    """

    def __init__(self, model: SoilModel, state: SoilState, control: SoilControl | None = None, integrator=None,
                 monitor: DivergenceMonitor | None = None, checkpoint_path=None):
        self.model = model
        self.monitor = monitor or DivergenceMonitor()
        """Divergence checks of run() and run_adaptive() (soil.stability)."""
        self.checkpoint_path = checkpoint_path
        """Where the last good state is written (.npz, atomically) when the simulation diverges; None: not written."""
        self.accepted_steps = 0
        """Steps accepted by run_adaptive (all steps taken count in `steps`)."""
        self.rejected_steps = 0
        """Steps run_adaptive computed and threw away (their force evaluations still count)."""
        self.forced_steps = 0
        """Steps accepted at dt_min although their error exceeded the tolerance."""
        self.control = control or SoilControl.for_model(model)
        self.integrator = integrator or VelocityVerlet()
        self.contacts = ContactSolver(model)
        self.state = state
        self._next = SoilState.for_model(model, state.capacity)
        self.steps = 0
        self._controller = None  # run_adaptive's StepController, kept between calls
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
        """Advance by `duration` [s] with fixed steps dt [s]; callback(sim) after each step.

        Every `check_every` steps and at the end the DivergenceMonitor checks the state
        (NaN, speed, overlap, energy) and raises SimulationDiverged on failure.
        """
        if not self.monitor.armed:
            self.monitor.arm(self)
        steps = int(round(duration / dt))
        for k in range(steps):
            self.step(dt)
            if callback is not None:
                callback(self)
            if (k + 1) % check_every == 0 or k + 1 == steps:
                self.monitor.check(self)

    def run_adaptive(self, duration: float, controller: StepController | None = None, callback=None,
                     check_every: int = 100) -> dict:
        """Advance by `duration` [s] with jolt-Beeman steps chosen by a PID StepController.

        The integrator must be a JoltBeeman (one is installed if the simulation still has
        its default VelocityVerlet and has not stepped). A rejected step is simply not
        swapped in: `state` (positions, velocities, forces, previous forces, contact
        history) stays bit-for-bit what it was, and the step is redone shorter.
        The controller keeps its state between calls (pass the same one to continue).
        callback(sim) runs after each accepted step; every `check_every` accepted steps the
        DivergenceMonitor checks the state (the speed is checked after every step).

        Returns {'accepted', 'rejected', 'forced', 'evaluations', 'dt_smallest', 'dt_largest', 'dt_next'}
        for this call (steps, evaluations [-], steps [s]).
        """
        if not isinstance(self.integrator, JoltBeeman):
            if isinstance(self.integrator, VelocityVerlet) and self.steps == 0:
                self.integrator = JoltBeeman()
            else:
                raise TypeError(f"run_adaptive needs the JoltBeeman integrator, not {type(self.integrator).__name__}")
        controller = controller if controller is not None else self._controller or StepController()
        self._controller = controller
        controller.setup(self)
        if not self.monitor.armed:
            self.monitor.arm(self)
        counts = dict(accepted=0, rejected=0, forced=0, evaluations=self.contacts.evaluations)
        smallest, largest = math.inf, 0.0
        t_end = self.time + duration
        dt = controller.dt
        while t_end - self.time > 1e-9 * controller.dt_min:
            remaining = t_end - self.time
            # land on t_end without a sliver of a last step (a tiny step spoils the next jolt)
            h = remaining if remaining <= dt else (0.5 * remaining if remaining < 2.0 * dt else dt)
            while True:
                self.integrator.step(self.model, self.state, self._next, self.control, h, self.contacts)
                if not self._overflowed():
                    break
            summary = self.integrator.read_summary()
            err = controller.error(summary)
            accepted, proposal = controller.decide(err, h)
            if not accepted and h <= controller.dt_min * (1.0 + 1e-9):
                if summary["nonfinite"]:
                    self.monitor.fail(self, f"non-finite state even at dt_min = {controller.dt_min:.4g} s",
                                      summary["worst"], state=self._next)
                accepted = True
                counts["forced"] += 1
                self.forced_steps += 1
            if not accepted:
                counts["rejected"] += 1
                self.rejected_steps += 1
                dt = proposal
                continue
            self.state, self._next = self._next, self.state
            self.state.forces_valid = True
            self.steps += 1
            self.accepted_steps += 1
            counts["accepted"] += 1
            smallest, largest = min(smallest, h), max(largest, h)
            # a step shortened to land on t_end says nothing about the step the scene allows
            dt = proposal if h >= dt else max(proposal, dt)
            self.monitor.check_speed(self, summary["speed"])
            if callback is not None:
                callback(self)
            if counts["accepted"] % check_every == 0:
                self.monitor.check(self)
        controller.dt = dt
        self.monitor.check(self)
        counts["evaluations"] = self.contacts.evaluations - counts["evaluations"]
        counts.update(dt_smallest=smallest, dt_largest=largest, dt_next=dt)
        return counts

    def check_finite(self) -> None:
        """Raise SimulationDiverged if any particle position or velocity is not finite."""
        x = self.state.position.numpy()
        v = self.state.velocity.numpy()
        bad = ~(np.isfinite(x).all(axis=1) & np.isfinite(v).all(axis=1))
        if bad.any():
            self.monitor.fail(self, f"non-finite particle state in {int(bad.sum())} particle(s)", int(np.argmax(bad)))

    # -- checkpoints -------------------------------------------------------------
    def state_dict(self) -> dict:
        """Everything a bit-for-bit continuation needs, as numpy arrays and scalars (no pickles).

        Keys: 'state/<array>' and 'state/time' (SoilState.to_numpy: particles, contact
        history, forces, bodies' and boundaries' wrenches and motion), 'control/<name>'
        (SoilControl.state_dict), 'steps', 'accepted_steps', 'rejected_steps', 'forced_steps',
        'evaluations' [-], 'next_capacity' (history slots of the second buffer), 'integrator'
        (its name), 'precision', 'controller/<field>' (StepController, after run_adaptive),
        'monitor/<field>' (DivergenceMonitor). The model is not included: load into a
        Simulation built from the same scene (builder, device, precision, order_seed).
        """
        data = {f"state/{k}": np.asarray(v) for k, v in self.state.to_numpy().items()}
        data.update({f"control/{k}": v for k, v in self.control.state_dict().items()})
        for name in ("steps", "accepted_steps", "rejected_steps", "forced_steps"):
            data[name] = np.int64(getattr(self, name))
        data["evaluations"] = np.int64(self.contacts.evaluations)
        data["next_capacity"] = np.int64(self._next.capacity)
        data["integrator"] = np.str_(self.integrator.name)
        data["precision"] = np.str_(self.model.precision.name)
        if self._controller is not None:
            data.update({f"controller/{k}": v for k, v in self._controller.state_dict().items()})
        data.update({f"monitor/{k}": v for k, v in self.monitor.state_dict().items()})
        return data

    def load_state_dict(self, data: dict) -> None:
        """Continue from state_dict() output (e.g. loaded from an .npz): the next step is
        bit-for-bit the step the saved simulation would have taken."""
        model = self.model
        precision = str(data["precision"])
        if precision != model.precision.name:
            raise ValueError(f"the saved simulation ran in {precision!r} precision, this one in "
                             f"{model.precision.name!r}")
        saved = data["state/position"].shape[0]
        if saved != model.particle_count:
            raise ValueError(f"the saved simulation has {saved} particles, this model {model.particle_count}")
        integrators = {VelocityVerlet.name: VelocityVerlet, JoltBeeman.name: JoltBeeman}
        name = str(data["integrator"])
        if name not in integrators:
            raise ValueError(f"saved integrator {name!r} is unknown; known: {sorted(integrators)}")
        self.state.load_numpy({k[len("state/"):]: v for k, v in data.items() if k.startswith("state/")})
        self._next.grow_capacity(max(int(data["next_capacity"]), self.state.capacity))
        self.control.load_state_dict({k[len("control/"):]: v for k, v in data.items() if k.startswith("control/")})
        for key in ("steps", "accepted_steps", "rejected_steps", "forced_steps"):
            setattr(self, key, int(data[key]))
        self.contacts.evaluations = int(data["evaluations"])
        if self.integrator.name != name:
            self.integrator = integrators[name]()
        controller = {k[len("controller/"):]: v for k, v in data.items() if k.startswith("controller/")}
        self._controller = None
        if controller:
            self._controller = StepController()
            self._controller.load_state_dict(controller)
        self.monitor.load_state_dict({k[len("monitor/"):]: v for k, v in data.items() if k.startswith("monitor/")})
        if self.monitor.armed:
            self.monitor.snapshot(self)

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

    def boundary_wrenches(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The grains' force and torque on every boundary at the current time:
        (force [N] shape (boundary_count, 3), torque [N m] about each boundary's reference
        point (a plane's point, a box's centre; displaced with the boundary) shape
        (boundary_count, 3), contacts [-] shape (boundary_count,) int64), float64, world frame.
        Boundaries built with report=False read zero."""
        state = self.state
        return (state.boundary_force.numpy().astype(np.float64).reshape(-1, 3),
                state.boundary_torque.numpy().astype(np.float64).reshape(-1, 3),
                state.boundary_contacts.numpy().astype(np.int64))

    def boundary_displacements(self) -> np.ndarray:
        """Translation of every boundary from its initial geometry [m], shape (boundary_count, 3), float64."""
        return self.state.boundary_displacement.numpy().astype(np.float64).reshape(-1, 3)

    def boundary_velocities(self) -> np.ndarray:
        """Translation velocity of every boundary [m/s], shape (boundary_count, 3), float64."""
        return self.state.boundary_velocity.numpy().astype(np.float64).reshape(-1, 3)

    def boundary_geometry(self) -> np.ndarray:
        """Current geometry rows of every boundary [m], shape (boundary_count, 6), float64: a plane's
        (point, unit normal), a box's (lower corner, upper corner), displaced (soil.kernels)."""
        rows = self.model.boundary_geometry_numpy().copy()
        shift = self.boundary_displacements()
        kinds = self.model.boundary_kind.numpy()
        rows[:, :3] += shift
        rows[kinds == BOUNDARY_BOX, 3:] += shift[kinds == BOUNDARY_BOX]
        return rows

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
