"""A soil simulation: model + state buffers + control + integrator, stepped in macro steps.

A macro step is a run of fixed DEM steps that stays on the device: each step is captured
once as a graph (`wp.ScopedCapture`: a CUDA graph on a GPU, Warp's recorded replay on the
CPU) and replayed; the neighbour-list rebuild is a device-side branch inside it; wheel
poses along a path and the wheel wrench sums are computed on the device. After the macro
step the host reads one small report (status flags, storage needs, wheel wrenches). If
the contact storage overflowed, it grows and the macro step is redone from its start,
which three rotating state buffers keep untouched, so the result equals a run that had
enough storage from the start (docs/performance.md).

The capture cache and the report live in soil.macro, adaptive (PID) stepping in
soil.adaptive, snapshots in soil.snapshot; Simulation is the surface over them.
"""

import math
from collections.abc import Callable, Mapping
from types import SimpleNamespace

import numpy as np
import warp as wp

from . import adaptive, step_control
from . import snapshot as snapshot_module
from . import status as status_columns
from .boundaries import boundary_kernels
from .control import SoilControl, path_kernels
from .errors import SoilInputError, is_real
from .integrator import JoltBeeman, StepController, VelocityVerlet, integrator_kernels, make_integrator
from .macro import (  # noqa: F401 (CaptureWarning and the report's columns re-exported)
    BODY_COLUMNS,
    REPORT_BODIES,
    REPORT_BOUNDS,
    CaptureWarning,
    MacroStepReport,
    MacroSums,
    StepGraphs,
    grain_box,
    macro_kernels,
)
from .model import SoilModel
from .neighbours import NeighbourList, NeighbourSettings
from .reduction import reduction_kernels
from .sdf import displaced_geometry
from .snapshot import SimulationSnapshot
from .solver import ContactSolver
from .stability import DivergenceMonitor, SimulationDiverged  # noqa: F401 (SimulationDiverged re-exported)
from .state import STATE_UNITS, GrainLayout, SoilState, copy_world_words
from .step_control import DeviceStepControl


class Simulation:
    """Steps a soil model in time.

    `state` is always the current state; a step writes into another buffer and only then
    becomes current, so a step or macro step that fails (storage overflow, divergence)
    leaves `state` untouched.

    The public surface:

    - stepping: macro_step (fixed steps), advance_to (a macro step landing on an end time),
      macro_step_adaptive and enable_step_control (PID substeps), step, run, run_adaptive,
      refresh_forces;
    - the bodies: set_body_motion, set_body_path, body_positions, body_rotations,
      body_velocities, body_angular_velocities, body_wrenches, body_count, body_shapes;
    - the grains and walls (model order, host copies): positions, velocities,
      angular_velocities, forces, contact_counts, contact_history, radii, masses, free_grains, particle_count,
      boundary_wrenches, boundary_displacements, boundary_velocities, boundary_geometry,
      initial_boundary_geometry, boundary_reports, boundary_count, boundary_kinds, kinetic_energy,
      gravity_energy, elastic_energy, total_energy, check_finite,
      bytes_per_grain;
    - state as a whole: snapshot / restore (in memory, on the device), state_dict /
      load_state_dict (checkpoints), arm_monitor / check_divergence (soil.stability);
    - attributes: model, state (the current SoilState), control (SoilControl), integrator,
      monitor (DivergenceMonitor), step_control, time, steps and the step counters, gravity,
      device, precision_name.

    neighbours: how the neighbour list is kept (soil.neighbours.NeighbourSettings).
    capture: replay captured graphs of the steps (True, the default) or launch every kernel
    from the host (for comparison; both give bitwise the same results).
    """

    def __init__(
        self,
        model: SoilModel,
        state: SoilState,
        control: SoilControl | None = None,
        integrator=None,
        monitor: DivergenceMonitor | None = None,
        checkpoint_path=None,
        neighbours: NeighbourSettings | None = None,
        capture: bool = True,
    ):
        if not isinstance(model, SoilModel) or not isinstance(state, SoilState):
            raise SoilInputError(
                f"Simulation(model, state, ...) takes a soil.SoilModel and its soil.SoilState (SoilBuilder.finalize "
                f"returns both), got {type(model).__name__} and {type(state).__name__}"
            )
        if not (integrator is None or isinstance(integrator, (str, VelocityVerlet, JoltBeeman))):
            raise SoilInputError(
                f"integrator must be None (VelocityVerlet), 'velocity-verlet', 'jolt-beeman' or a soil.VelocityVerlet "
                f"or soil.JoltBeeman, got {integrator!r}"
            )
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
        # a scene's name ('jolt-beeman') is taken as the integrator it names
        self.integrator = make_integrator(integrator) if isinstance(integrator, str) else integrator or VelocityVerlet()
        self.graphs = StepGraphs(model.device, capture)
        """The captured steps (soil.macro.StepGraphs)."""
        if state.layout is None:
            state.layout = GrainLayout(model, state.capacity)
        state.layout.gather_constants(model)
        self.status = status_columns.make_status(model.device)
        """Step status on the device (soil.status's columns: flags and counts) [-], shape (soil.status.COLUMNS,),
        int32; cleared at each macro step."""
        self.neighbour_list = NeighbourList(model, neighbours, positions=state.position.numpy())
        self.contacts = ContactSolver(model, self.neighbour_list, self.status)
        self.state = state
        self._buffers = [state] + [
            SoilState.for_model(model, state.capacity, state.rigid_capacity, layout=state.layout) for _ in range(2)
        ]
        self.steps = 0
        self._controller: StepController | None = None  # run_adaptive's, kept between calls
        self._rebuilds_since_reorder = 0
        self._bounds: tuple | None = None
        # the boundaries' kinds and initial geometry, read once (their motion is in the state)
        self._boundaries = (model.boundary_kind.numpy().copy(), model.boundary_geometry_numpy())
        device = model.device
        self.sums = MacroSums(model)
        """The macro step's wrench sums and report on the device (soil.macro.MacroSums)."""
        hi = model.precision.hi
        worlds = model.world_count
        self._step_length = wp.zeros(worlds, dtype=hi, device=device)
        """The DEM step the kernels read [s], one per world (soil.worlds), shape (worlds,): on the device,
        so that a step's length can be decided there (step control) and one captured graph serves
        every length."""
        self._step_length64 = wp.zeros(worlds, dtype=wp.float64, device=device)
        """The same step in float64 (the wrench sums and the work)."""
        self._no_step = wp.zeros(worlds, dtype=hi, device=device)
        self.step_control: DeviceStepControl | None = None
        """The PID step control of macro_step_adaptive (enable_step_control), or None."""
        if not state.forces_valid:  # a restored state keeps its own forces: restarts stay bit-identical
            self.refresh_forces()

    @property
    def time(self) -> float:
        """Simulated time [s]."""
        return self.state.time

    @property
    def capture(self) -> bool:
        """Whether steps are replayed from captured graphs (False after the device failed to capture)."""
        return self.graphs.enabled

    # -- what the model holds, for callers that only hold the simulation ----------------------
    @property
    def particle_count(self) -> int:
        """Grains simulated [-]."""
        return self.model.particle_count

    @property
    def body_count(self) -> int:
        """Bodies (wheels) [-]."""
        return self.model.body_count

    @property
    def body_shapes(self) -> list:
        """The shape of every body (soil.GrouserWheel, soil.MeshWheel), in body order."""
        return list(self.model.bodies)

    @property
    def gravity(self) -> np.ndarray:
        """Gravity [m/s^2], shape (3,), float64 (a copy)."""
        return np.array(self.model.gravity, dtype=np.float64)

    @property
    def device(self) -> str:
        """The Warp device the simulation runs on."""
        return str(self.model.device)

    @property
    def precision_name(self) -> str:
        """The precision it runs in (soil.PRECISIONS: 'single', 'mixed', 'double')."""
        return self.model.precision.name

    def radii(self) -> np.ndarray:
        """Grain radii [m], shape (particle_count,), float64, model order."""
        return self.model.radius_numpy()

    def masses(self) -> np.ndarray:
        """Grain masses [kg], shape (particle_count,), float64, model order."""
        return self.model.mass_numpy()

    def free_grains(self) -> np.ndarray:
        """Which grains move (False for grains held fixed: zero inverse mass) [-], shape (particle_count,), bool."""
        return self.model.inv_mass.numpy() > 0

    @property
    def boundary_count(self) -> int:
        """Boundaries (walls, lids, plates) [-]."""
        return self.model.boundary_count

    def initial_boundary_geometry(self) -> np.ndarray:
        """Geometry rows of every boundary as built [m], shape (boundary_count, 6), float64 (boundary_geometry
        without displacement)."""
        return self._boundary_rows()[1].copy()

    def boundary_reports(self) -> np.ndarray:
        """Whether each boundary reports its wrench (built with report=True) [-], shape (boundary_count,), bool."""
        return np.asarray(self.model.boundary_reports)

    def boundary_kinds(self) -> np.ndarray:
        """The kind of every boundary (soil.sdf.BOUNDARY_PLANE, BOUNDARY_BOX) [-], shape (boundary_count,), int32."""
        return self._boundary_rows()[0].copy()

    def _boundary_rows(self) -> tuple[np.ndarray, np.ndarray]:
        """(kinds, initial geometry rows) of the boundaries."""
        return self._boundaries

    # -- the bodies: prescribed motion (host side) and the soil's wrench on them ----------------
    def set_body_motion(
        self, body: int, position=None, orientation=None, velocity=None, angular_velocity=None, rotation=None
    ) -> None:
        """Prescribe a body's pose and velocity (SoilControl.set_body_motion): position [m] (3,),
        orientation quaternion (w, x, y, z) or rotation matrix (3, 3), velocity [m/s] (3,), angular
        velocity [rad/s] (3,), world frame. Call refresh_forces() to have the forces of the new pose
        before the next step."""
        self.control.set_body_motion(body, position, orientation, velocity, angular_velocity, rotation)

    def set_body_path(self, span: float, position, orientation, velocity, angular_velocity, end=None) -> None:
        """Let every body follow a path over the next `span` [s] (SoilControl.set_body_path: arrays
        (body_count, 3) [m], (body_count, 4) quaternions, (body_count, 3) [m/s] and [rad/s], world
        frame; end: the same four at the span's end, or None for constant velocities). The next
        macro step with path=True poses the bodies along it on the device."""
        self.control.set_body_path(span, position, orientation, velocity, angular_velocity, end=end)

    def body_positions(self) -> np.ndarray:
        """Hub position of every body as last prescribed (set_body_motion, or the end of the path of
        set_body_path) [m], shape (body_count, 3), float64, world frame (a copy; no device read)."""
        return self.control.body_position_host.copy()

    def body_rotations(self) -> np.ndarray:
        """Rotation body -> world of every body as last prescribed [-], shape (body_count, 3, 3), float64 (a copy)."""
        return self.control.body_rotation_host.copy()

    def body_velocities(self) -> np.ndarray:
        """Hub velocity of every body as last prescribed [m/s], shape (body_count, 3), float64 (a copy)."""
        return self.control.body_velocity_host.copy()

    def body_angular_velocities(self) -> np.ndarray:
        """Angular velocity of every body as last prescribed [rad/s], shape (body_count, 3), float64 (a copy)."""
        return self.control.body_angular_velocity_host.copy()

    def body_wrenches(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The soil's wrench on every body at the current time: (force [N] shape (body_count, 3), torque
        [N m] about its hub shape (body_count, 3), grains touching it [-] shape (body_count,) int64),
        float64, world frame."""
        state = self.state
        return (
            state.body_force.numpy().astype(np.float64).reshape(-1, 3),
            state.body_torque.numpy().astype(np.float64).reshape(-1, 3),
            state.body_contacts.numpy().astype(np.int64),
        )

    # -- divergence checks -----------------------------------------------------------------
    def arm_monitor(self) -> None:
        """Let the divergence monitor take the scene's scales from the current state (e.g. after the
        bodies were placed) and keep it as the last good state (DivergenceMonitor.arm)."""
        self.monitor.arm(self)

    def check_divergence(self) -> None:
        """Check the current state against the monitor's bounds (NaN, speed, overlap, energy; arming
        it first if it is not armed); raises SimulationDiverged (DivergenceMonitor.check)."""
        self.monitor.check(self)

    # -- snapshots -------------------------------------------------------------------------
    def snapshot(self, into: SimulationSnapshot | None = None) -> SimulationSnapshot:
        """The whole simulation now, to go back to with restore(): the state (time, grains, contact
        history, storage order and lists, walls' motion), the control (bodies' and boundaries'
        motion, external forces), the step counters, the divergence monitor's bounds and the step
        controller's state. Device to device, no host read. `into`: an earlier snapshot of this
        simulation whose device buffers are reused (it is overwritten)."""
        controller = None if self._controller is None else self._controller.state_dict()
        return snapshot_module.take(self, controller, (self._rebuilds_since_reorder, self._bounds), into)

    def restore(self, snapshot: SimulationSnapshot) -> None:
        """Put the simulation back to `snapshot` (from this simulation's snapshot()): the next step
        gives the same bits as if nothing had happened since. Contact storage grown since stays
        grown; the force evaluation count (work done) and captured graphs are kept; the monitor's
        last good state is not rolled back. A snapshot taken before run_adaptive's first call drops
        the controller made since (the repeat makes a fresh one; one passed to run_adaptive again
        is used as it is then)."""
        snapshot_module.put_back(self, snapshot)  # checks the snapshot before anything is put back
        if snapshot.controller is None:  # run_adaptive made or took one since: it starts afresh again
            self._controller = None
        elif self._controller is not None:
            self._controller.load_state_dict(snapshot.controller)
        self._rebuilds_since_reorder, self._bounds = snapshot.reorder

    # -- buffers ---------------------------------------------------------------------
    def _spares(self) -> list[SoilState]:
        if not any(b is self.state for b in self._buffers):  # the state was replaced from outside
            self._buffers = [self.state] + [
                SoilState.for_model(
                    self.model, self.state.capacity, self.state.rigid_capacity, layout=self.state.layout
                )
                for _ in range(2)
            ]
        spares = [b for b in self._buffers if b is not self.state]
        for spare in spares:
            spare.layout = self.state.layout
            spare.grow_capacity(self.state.capacity, self.state.rigid_capacity)
        return spares

    def _grow(self, capacity: int, rigid_capacity: int) -> None:
        """Widen the contact storage of every buffer (and the layout) to at least these slots per grain."""
        capacity = max(capacity, self.state.capacity)
        rigid_capacity = max(rigid_capacity, self.state.rigid_capacity)
        for buffer in self._buffers:
            buffer.grow_capacity(capacity, rigid_capacity)

    def _needs_growth(self, values) -> tuple[int, int] | None:
        """New (capacity, rigid capacity) if the status shows an overflow, else None (with headroom)."""
        needed = int(values[status_columns.NEEDED_NEIGHBOURS])
        rigid = int(values[status_columns.NEEDED_RIGID])
        if needed <= self.state.capacity and rigid <= self.state.rigid_capacity:
            return None
        return (
            max(self.state.capacity, needed + 4 if needed > self.state.capacity else 0),
            max(self.state.rigid_capacity, rigid + 1 if rigid > self.state.rigid_capacity else 0),
        )

    def bytes_per_grain(self) -> dict:
        """Device memory per grain [B]: each state buffer, the layout (order, constants, two
        neighbour lists), the grains' constants (radius, mass, inverse mass and inertia, material)
        and the control's external force, the contact solver's and the list build's scratch, the
        integrator's, the monitor's last good state, and the total."""
        n = max(self.model.particle_count, 1)
        layout = self.state.layout
        assert layout is not None  # every state of a Simulation has its layout
        gaps = getattr(self.integrator, "gaps", None)
        constants = [getattr(self.model, name) for name in ("radius", "mass", "inv_mass", "inv_inertia", "material")]
        parts = {
            "state buffers (3)": sum(b.bytes_per_grain() for b in self._buffers),
            "grain constants and external force": (
                sum(a.capacity for a in constants) + self.control.external_force.capacity
            )
            / n,
            "layout": layout.bytes_per_grain(),
            "contact scratch": self.contacts.bytes_per_grain(),
            "list build scratch": self.neighbour_list.bytes_per_grain(),
            "integrator": gaps.capacity / n if gaps is not None else 0.0,
            "monitor snapshot": self.monitor.bytes_per_grain(),
        }
        parts["total"] = sum(parts.values())
        return parts

    # -- forces without moving ------------------------------------------------------------
    def refresh_forces(self) -> None:
        """Recompute forces (and the contact list) of the current state without moving it."""
        self.control.push(self.state)
        while True:
            spare = self._spares()[0]
            self.contacts.reserve(self.state.rigid_capacity)
            spare.assign(self.state)
            status_columns.clear(self.status)
            self.contacts.compute(self.state, spare, self.control, self._no_step)
            values = self.status.numpy()
            growth = self._needs_growth(values)
            if growth is None:
                break
            self._grow(*growth)
        self._rebuilds_since_reorder += int(values[status_columns.REBUILDS])
        self.state = spare
        self.state.forces_valid = True

    # -- macro steps -----------------------------------------------------------------------
    def _signature(self) -> tuple:
        """Identity of every array a captured step uses: a graph is valid while it holds."""
        layout = self.state.layout
        assert layout is not None  # every state of a Simulation has its layout
        arrays: list = []
        for buffer in self._buffers:
            arrays += list(buffer.arrays.values()) + [buffer.list_index]
        arrays += list(layout.arrays.values())
        arrays += self.contacts.device_arrays()
        arrays += [getattr(self.integrator, "gaps", None)]
        return (
            tuple(id(b) for b in self._buffers),
            tuple(None if a is None else a.ptr for a in arrays),
            self.control.external_force_used,
            self.neighbour_list.dims,
        )

    def _set_step(self, dt: float) -> None:
        """Write the step length the kernels read (a host-to-device copy, no read)."""
        self._step_length.fill_(float(dt))
        self._step_length64.fill_(float(dt))

    def _accumulate_wrench(self, state: SoilState, weighted: bool, worlds: wp.array | None = None) -> None:
        """Add the bodies' wrench of `state` to the macro step's sums (capturable); worlds: int32 (worlds,),
        those whose step counts (None: all)."""
        self.sums.accumulate(state, self._step_length64, weighted, worlds)

    def _run_step(self, dt: float, state_in: SoilState, state_out: SoilState, path: bool) -> None:
        """One DEM step state_in -> state_out of the length in _step_length (dt [s]): replayed from
        its graph, or launched."""

        def body():
            state_out.copy_bodies(state_in)
            if path:
                self.control.follow_path(state_out, self._step_length)
            self.integrator.step(self.model, state_in, state_out, self.control, self._step_length, self.contacts)
            self._accumulate_wrench(state_out, weighted=False)
            if path:
                self.control.count_path_step()

        evaluations = self.graphs.replay(
            (id(state_in), id(state_out), path, type(self.integrator)), body, self.contacts
        )
        if evaluations is None:
            body()
        else:
            self.contacts.evaluations += evaluations
        state_out.time = state_in.time + dt

    def _prepare(self) -> None:
        """Allocate everything a captured step touches, and drop graphs whose arrays changed."""
        prec = self.model.precision
        self.graphs.load_modules(
            [
                integrator_kernels(prec.hi, prec.mid, prec.lo, self.model.law),
                boundary_kernels(prec.hi),
                path_kernels(prec.hi),
                macro_kernels(prec.hi),
                step_control.step_control_kernels(prec.hi),
                self.contacts.kernels,
                self.neighbour_list.kernels,
                SimpleNamespace(copy_world_words=copy_world_words),  # the worlds' restore (soil.step_control)
                *(reduction_kernels(dtype) for dtype in (prec.hi, prec.vec_hi, wp.int32)),  # the sums' trees
            ]
        )
        self._spares()
        self.contacts.reserve(self.state.rigid_capacity)
        self.integrator.bind(self.model)
        self.graphs.check(self._signature())

    def _maybe_reorder(self) -> None:
        """Between macro steps: move the grains into the list's curve order when it was rebuilt
        (and re-plan the grid when the grains' box has outgrown it)."""
        neighbours = self.neighbour_list
        if self._bounds is not None and neighbours.wants_plan(*self._bounds):
            neighbours.plan(np.vstack(self._bounds))
            self._bounds = None
        if not neighbours.reorder_enabled or self._rebuilds_since_reorder < neighbours.settings.reorder_every:
            return
        spare = self._spares()[0]
        neighbours.reorder(self.state, spare)
        self.state = spare
        self._rebuilds_since_reorder = 0

    def macro_step(
        self, steps: int, dt: float, path: bool = False, meanwhile: Callable[[], None] | None = None
    ) -> MacroStepReport:
        """Advance by `steps` fixed steps of dt [s], on the device, with one read at the end.

        path: the bodies follow the path set by control.set_body_path (posed on the device
        at each step); otherwise they keep the motion the control holds. meanwhile: the
        caller's own host work, called once after the steps are launched and before the read
        (on a GPU it runs while the device steps; it must neither touch this simulation nor
        raise: an error of its own is the caller's to keep and raise after the step). Raises
        SimulationDiverged if a grain's state became non-finite (the state is then the last
        step's, for the report).
        """
        steps = _check_count(steps, "steps")
        dt = _check_step(dt)
        self._maybe_reorder()
        if not path:
            self.control.path_active = False
        self.control.push(self.state)
        redone = 0
        start = self.state
        evaluations_before = self.contacts.evaluations
        while True:
            self._prepare()
            spares = self._spares()
            status_columns.clear(self.status)
            self.sums.clear()
            if path:
                self.control.path_step.zero_()
            self.neighbour_list.save(start)
            self._set_step(dt)
            current = start
            for k in range(steps):
                target = spares[k % 2]
                self._run_step(dt, current, target, path)
                current = target
            if meanwhile is not None:  # while the device steps; once (a redo below does not repeat it)
                work, meanwhile = meanwhile, None
                work()
            values = self.sums.read(self.status, self.neighbour_list.grid, current)
            growth = self._needs_growth(values)
            if growth is None:
                break
            self.neighbour_list.restore(start)
            self._grow(*growth)
            redone += 1
        self.state = current
        self.state.forces_valid = True
        self.steps += steps
        evaluations = self.contacts.evaluations - evaluations_before
        rebuilds = int(values[status_columns.REBUILDS])
        self._rebuilds_since_reorder += rebuilds
        self._bounds = grain_box(values)
        if values[status_columns.NONFINITE] > 0:
            self.monitor.fail(self, "non-finite particle state (NaN or inf)", int(values[status_columns.WORST]))
        return self.sums.report(
            values,
            steps,
            steps=steps,
            dt=dt,
            rebuilds=rebuilds,
            redone=redone,
            dt_min=dt,
            dt_max=dt,
            evaluations=evaluations,
        )

    def advance_to(
        self, end_time: float, dt: float, path: bool = False, meanwhile: Callable[[], None] | None = None
    ) -> MacroStepReport:
        """Advance to `end_time` [s] in one macro step that lands on it exactly: the state's time is
        then float(end_time) itself, not the sum of the steps (which differs from it by rounding), so
        a caller's clock and the soil's agree to the last bit.

        Fixed steps: the span is split into the fewest whole steps no longer than dt [s] (up to a
        rounding of 1e-9 steps), of dt itself when the span is a whole number of dt up to the clock's
        rounding (a length that changed in its last bits from one macro step to the next would be a
        new captured graph). With a step control (enable_step_control): PID substeps over the span
        (macro_step_adaptive). path, meanwhile: as macro_step. Raises SoilInputError unless end_time
        is after the current time.
        """
        dt = _check_step(dt)
        t0 = self.time
        if not (is_real(end_time) and math.isfinite(end_time)):
            raise SoilInputError(f"end_time must be a finite time [s] after the soil's time {t0!r} s, got {end_time!r}")
        span = float(end_time) - t0
        if not span > 0:
            raise SoilInputError(f"end_time {end_time!r} s must be after the soil's time {t0!r} s")
        if self.step_control is not None:
            report = self.macro_step_adaptive(span, path=path, meanwhile=meanwhile)
        else:
            steps = max(1, int(np.ceil(span / dt - 1e-9)))
            h = span / steps
            if abs(steps * dt - span) <= 64 * np.spacing(max(abs(float(end_time)), span)):
                h = dt
            report = self.macro_step(steps, h, path=path, meanwhile=meanwhile)
        self.state.time = float(end_time)
        return report

    # -- step control on the device -------------------------------------------------------
    def enable_step_control(self, controller: StepController | None = None) -> DeviceStepControl:
        """Use the PID step control (StepController; default settings when None) in
        macro_step_adaptive. The integrator must be a JoltBeeman (one is installed if the
        simulation still has its default VelocityVerlet and has not stepped): its
        predictor/corrector gap is the error estimate."""
        return adaptive.enable_step_control(self, controller)

    def macro_step_adaptive(
        self, span: float, path: bool = False, meanwhile: Callable[[], None] | None = None
    ) -> MacroStepReport:
        """Advance by `span` [s] in as many jolt-Beeman substeps as the PID step control needs,
        landing exactly on the span's end, on the device with one read at the end.

        The substep loop with its accept/reject decision is one captured graph
        (`wp.capture_while`, soil.step_control): each substep steps the current state into a
        trial buffer, the decision runs on the device, and an accepted trial is copied over
        the current state; a rejected one leaves it untouched (contact history and list
        included), so the retry starts from it bit for bit. The wheels' wrench sums are
        weighted by the substeps' lengths (the report's means are time means). Needs
        enable_step_control() first. Raises SimulationDiverged if a substep at dt_min is
        still non-finite. (soil.adaptive)
        """
        return adaptive.macro_step_adaptive(self, _check_step(span), path, meanwhile)

    def step(self, dt: float) -> None:
        """Advance by dt [s]."""
        self.macro_step(1, dt)

    def run(self, duration: float, dt: float, callback=None, check_every: int = 200) -> None:
        """Advance by `duration` [s] with fixed steps dt [s]; callback(sim) after each step.

        The steps are whole: duration / dt rounded to the nearest integer of them (Python's round), so
        the clock moves by a multiple of dt within dt / 2 of `duration` (advance_to lands on an end
        time exactly); a duration > 0 shorter than half a step is refused, not run as none.

        The steps run as macro steps of `check_every` steps (one host read each; with a
        callback, of one step). Every `check_every` steps and at the end the DivergenceMonitor
        checks the state (NaN, speed, overlap, energy) and raises SimulationDiverged on failure.
        With a step control (enable_step_control) the macro steps of check_every x dt take PID
        substeps instead (macro_step_adaptive; the callback runs after each macro step).
        """
        dt = _check_step(dt)
        if not (
            isinstance(duration, (int, float, np.floating, np.integer)) and math.isfinite(duration) and duration >= 0
        ):
            raise SoilInputError(f"duration must be finite and >= 0 [s], got {duration!r}")
        check_every = _check_count(check_every, "check_every")
        if not self.monitor.armed:
            self.monitor.arm(self)
        steps = int(round(duration / dt))
        if duration > 0 and steps == 0:
            raise SoilInputError(
                f"duration {duration!r} s is less than half a step (dt = {dt!r} s): run takes whole steps; shorten dt, "
                "or use advance_to to land on an end time"
            )
        if self.step_control is not None:
            chunks = -(-steps // check_every)
            for _ in range(chunks):
                self.macro_step_adaptive(duration / chunks)
                if callback is not None:
                    callback(self)
                self.monitor.check(self)
            return
        done = 0
        while done < steps:
            chunk = 1 if callback is not None else min(check_every - done % check_every, steps - done)
            self.macro_step(chunk, dt)
            done += chunk
            if callback is not None:
                callback(self)
            if done % check_every == 0 or done == steps:
                self.monitor.check(self)

    def run_adaptive(
        self, duration: float, controller: StepController | None = None, callback=None, check_every: int = 100
    ) -> dict:
        """Advance by `duration` [s] with jolt-Beeman steps chosen by a PID StepController.

        The integrator must be a JoltBeeman (one is installed if the simulation still has
        its default VelocityVerlet and has not stepped). A rejected step is simply not
        made current: `state` (positions, velocities, forces, previous forces, contact
        history) stays bit-for-bit what it was, and the step is redone shorter. The
        controller decides on the host after each step, from an error norm reduced on the
        device (one small read per step). The controller keeps its state between calls
        (pass the same one to continue). callback(sim) runs after each accepted step; every
        `check_every` accepted steps the DivergenceMonitor checks the state (the speed is
        checked after every step). (soil.adaptive)

        Returns {'accepted', 'rejected', 'forced', 'evaluations', 'dt_smallest', 'dt_largest', 'dt_next'}
        for this call (steps, evaluations [-], steps [s]).
        """
        return adaptive.run_adaptive(self, duration, controller, callback, check_every)

    def check_finite(self) -> None:
        """Raise SimulationDiverged if any particle position or velocity is not finite."""
        x = self.positions()
        v = self.velocities()
        bad = ~(np.isfinite(x).all(axis=1) & np.isfinite(v).all(axis=1))
        if bad.any():
            self.monitor.fail(self, f"non-finite particle state in {int(bad.sum())} particle(s)", int(np.argmax(bad)))

    # -- checkpoints -------------------------------------------------------------
    def state_dict(self) -> dict:
        """Everything a bit-for-bit continuation needs, as numpy arrays and scalars (no pickles).

        Keys: 'state/<array>' and 'state/time' (SoilState.to_numpy, model order: particles,
        contact history with the neighbour list it is aligned with, forces, bodies' and
        boundaries' wrenches and motion: 'state/body_position', 'body_rotation', 'body_velocity',
        'body_angular_velocity', 'body_posed'; on loading, the pose the control prescribed is
        sent into the state before the next step, so checkpoints written before the pose was
        part of the state, which lack these keys, load as they always did), 'control/<name>'
        (SoilControl.state_dict), 'steps',
        'accepted_steps', 'rejected_steps', 'forced_steps', 'evaluations' [-], 'capacity' and
        'rigid_capacity' (contact slots per grain), 'integrator' (its name), 'precision',
        'controller/<field>' (StepController, after run_adaptive), 'step_control/<field>' (the
        settings of the device step control and its state, 'step_control/device'), 'monitor/<field>'
        (DivergenceMonitor). The model is not included: load into a Simulation built from the
        same scene (builder, device, precision, order_seed). The storage order is not part of
        it: the physics does not depend on it.
        """
        data = {f"state/{k}": np.asarray(v) for k, v in self.state.to_numpy().items()}
        data.update({f"control/{k}": v for k, v in self.control.state_dict().items()})
        for name in ("steps", "accepted_steps", "rejected_steps", "forced_steps"):
            data[name] = np.int64(getattr(self, name))
        data["evaluations"] = np.int64(self.contacts.evaluations)
        data["capacity"] = np.int64(self.state.capacity)
        data["rigid_capacity"] = np.int64(self.state.rigid_capacity)
        data["integrator"] = np.str_(self.integrator.name)
        data["precision"] = np.str_(self.model.precision.name)
        if self._controller is not None:
            data.update({f"controller/{k}": v for k, v in self._controller.state_dict().items()})
        if self.step_control is not None:
            data.update({f"step_control/{k}": v for k, v in self.step_control.state_dict().items()})
        data.update({f"monitor/{k}": v for k, v in self.monitor.state_dict().items()})
        return data

    def state_dict_units(self) -> dict[str, str]:
        """{key of state_dict(): its unit} (SI; "1" for flags and indices, "count" for counts, "text" for
        names)."""
        units = {f"state/{k}": v for k, v in STATE_UNITS.items()}
        units.update({f"control/{k}": v for k, v in self.control.state_dict_units().items()})
        counters = ("steps", "accepted_steps", "rejected_steps", "forced_steps", "evaluations")
        units.update(dict.fromkeys(counters, "count"))
        units.update(capacity="count", rigid_capacity="count", integrator="text", precision="text")
        if self._controller is not None:
            units.update({f"controller/{k}": v for k, v in self._controller.state_dict_units().items()})
        if self.step_control is not None:
            units.update({f"step_control/{k}": v for k, v in self.step_control.state_dict_units().items()})
        units.update({f"monitor/{k}": v for k, v in self.monitor.state_dict_units().items()})
        return units

    def load_state_dict(self, data: dict) -> None:
        """Continue from state_dict() output (e.g. loaded from an .npz): the next step is
        bit-for-bit the step the saved simulation would have taken."""
        model = self.model
        self._check_saved(data)
        precision = str(data["precision"])
        if precision != model.precision.name:
            raise SoilInputError(
                f"the saved simulation ran in {precision!r} precision, this one in {model.precision.name!r}"
            )
        saved = data["state/position"].shape[0]
        if saved != model.particle_count:
            raise SoilInputError(f"the saved simulation has {saved} particles, this model {model.particle_count}")
        integrators: dict[str, type[VelocityVerlet] | type[JoltBeeman]] = {
            VelocityVerlet.name: VelocityVerlet,
            JoltBeeman.name: JoltBeeman,
        }
        name = str(data["integrator"])
        if name not in integrators:
            raise SoilInputError(f"saved integrator {name!r} is unknown; known: {sorted(integrators)}")
        capacity = int(data.get("capacity", data.get("next_capacity", self.state.capacity)))
        rigid_capacity = int(data.get("rigid_capacity", self.state.rigid_capacity))
        self._spares()
        self._grow(capacity, rigid_capacity)
        self.state.load_numpy({k[len("state/") :]: v for k, v in data.items() if k.startswith("state/")})
        self._grow(self.state.capacity, self.state.rigid_capacity)
        self.control.load_state_dict({k[len("control/") :]: v for k, v in data.items() if k.startswith("control/")})
        for key in ("steps", "accepted_steps", "rejected_steps", "forced_steps"):
            setattr(self, key, int(data[key]))
        self.contacts.evaluations = int(data["evaluations"])
        if self.integrator.name != name:
            self.integrator = integrators[name]()
        controller = {k[len("controller/") :]: v for k, v in data.items() if k.startswith("controller/")}
        self._controller = None
        if controller:
            self._controller = StepController()
            self._controller.load_state_dict(controller)
        steps = {k[len("step_control/") :]: v for k, v in data.items() if k.startswith("step_control/")}
        if steps:
            settings = StepController()
            settings.load_state_dict({k: v for k, v in steps.items() if k != "device"})
            self.enable_step_control(settings).load_state_dict(steps)
        self.monitor.load_state_dict({k[len("monitor/") :]: v for k, v in data.items() if k.startswith("monitor/")})
        if self.monitor.armed:
            self.monitor.snapshot(self)

    def _check_saved(self, data: Mapping) -> None:
        """SoilInputError naming what a state_dict to load lacks or holds wrong (a key, a shape, a grain
        that is not finite), before anything of this simulation changes."""
        if not isinstance(data, Mapping):  # state_dict()'s dict, or the .npz it was saved to (np.load)
            raise SoilInputError(f"load_state_dict takes what state_dict() returns, got {type(data).__name__}")
        needed = ["precision", "integrator", "state/position", "state/time", "steps", "evaluations"]
        needed += ["accepted_steps", "rejected_steps", "forced_steps"]
        missing = [key for key in needed if key not in data]
        if missing:
            raise SoilInputError(f"the saved simulation lacks {', '.join(missing)}: not a Simulation.state_dict()")
        for name in ("position", "velocity", "angular_velocity"):
            values = np.asarray(data.get(f"state/{name}", np.zeros((len(data["state/position"]), 3))))
            if values.ndim != 2 or values.shape[1] != 3 or values.dtype.kind not in "fiu":
                raise SoilInputError(
                    f"state/{name}: the saved grains' {name} has shape {values.shape} ({values.dtype}), "
                    "expected (particle_count, 3) numbers"
                )
            bad = ~np.isfinite(values).all(axis=1)
            if bad.any():
                raise SoilInputError(
                    f"state/{name}: {int(bad.sum())} saved grain(s) not finite (the first: grain "
                    f"{int(np.argmax(bad))}): a diverged state cannot be continued"
                )

    # -- diagnostics (host side, model order) ---------------------------------------------
    def _model_order(self, array: wp.array) -> np.ndarray:
        values = array.numpy()
        out = np.empty(values.shape, dtype=np.float64)
        layout = self.state.layout
        assert layout is not None  # every state of a Simulation has its layout
        out[layout.order.numpy()] = values
        return out

    def positions(self) -> np.ndarray:
        """Particle positions [m], shape (particle_count, 3), float64, model order."""
        return self._model_order(self.state.position)

    def velocities(self) -> np.ndarray:
        """Particle velocities [m/s], shape (particle_count, 3), float64, model order."""
        return self._model_order(self.state.velocity)

    def angular_velocities(self) -> np.ndarray:
        """Particle angular velocities [rad/s], shape (particle_count, 3), float64, model order."""
        return self._model_order(self.state.angular_velocity)

    def forces(self) -> np.ndarray:
        """Contact + external force on each particle [N], shape (particle_count, 3), float64, model order."""
        return self._model_order(self.state.force)

    def contact_counts(self) -> np.ndarray:
        """Contacts of each particle (grains, walls, wheels) [-], shape (particle_count,), int64, model order."""
        return self._model_order(self.state.contact_count).astype(np.int64)

    def contact_history(self, particle: int) -> list[dict]:
        """The contacts of one particle (model index) with their history: a list of
        {'partner': ('grain', model index) or ('boundary', index) or ('body', index),
        'tangential' [m] (3,), 'rolling' [rad] (3,), 'twist' [rad]} (zero for switched-off terms)."""
        data = self.state.to_numpy()
        if not 0 <= particle < self.model.particle_count:
            raise IndexError(f"particle must be in [0, {self.model.particle_count}), got {particle}")
        contacts = []
        touching = data["pair_touching"][particle]
        for k in range(int(data["neighbour_count"][particle])):
            if touching[k // 32] >> np.uint32(k % 32) & np.uint32(1):
                contacts.append(
                    {
                        "partner": ("grain", int(data["neighbours"][particle, k])),
                        "tangential": _row(data["pair_tangential"], particle, k),
                        "rolling": _row(data["pair_rolling"], particle, k),
                        "twist": _twist(data["pair_rolling"], particle, k),
                    }
                )
        walls = self.model.boundary_count
        for s in range(int(data["rigid_count"][particle])):
            key = int(data["rigid_key"][particle, s])
            partner = ("boundary", key) if key < walls else ("body", key - walls)
            contacts.append(
                {
                    "partner": partner,
                    "tangential": _row(data["rigid_tangential"], particle, s),
                    "rolling": _row(data["rigid_rolling"], particle, s),
                    "twist": _twist(data["rigid_rolling"], particle, s),
                }
            )
        return contacts

    def boundary_wrenches(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The grains' force and torque on every boundary at the current time:
        (force [N] shape (boundary_count, 3), torque [N m] about each boundary's reference
        point (a plane's point, a box's centre; displaced with the boundary) shape
        (boundary_count, 3), contacts [-] shape (boundary_count,) int64), float64, world frame.
        Boundaries built with report=False read zero."""
        state = self.state
        return (
            state.boundary_force.numpy().astype(np.float64).reshape(-1, 3),
            state.boundary_torque.numpy().astype(np.float64).reshape(-1, 3),
            state.boundary_contacts.numpy().astype(np.int64),
        )

    def boundary_displacements(self) -> np.ndarray:
        """Translation of every boundary from its initial geometry [m], shape (boundary_count, 3), float64."""
        return self.state.boundary_displacement.numpy().astype(np.float64).reshape(-1, 3)

    def boundary_velocities(self) -> np.ndarray:
        """Translation velocity of every boundary [m/s], shape (boundary_count, 3), float64."""
        return self.state.boundary_velocity.numpy().astype(np.float64).reshape(-1, 3)

    def boundary_geometry(self, displacement=None) -> np.ndarray:
        """Geometry rows of every boundary [m], shape (boundary_count, 6), float64: a plane's (point,
        unit normal), a box's (lower corner, upper corner) (soil.sdf), displaced by `displacement`
        [m], shape (boundary_count, 3) (e.g. a MacroStepReport's boundary_displacement; default: the
        current displacement, read from the device)."""
        kinds, initial = self._boundary_rows()
        return displaced_geometry(
            kinds, initial, self.boundary_displacements() if displacement is None else displacement
        )

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


def _row(values: np.ndarray, particle: int, k: int) -> np.ndarray:
    return values[particle, k, :3].astype(np.float64) if values.shape[1] else np.zeros(3)


def _twist(values: np.ndarray, particle: int, k: int) -> float:
    return float(values[particle, k, 3]) if values.shape[1] and values.shape[2] == 4 else 0.0


def _check_step(dt) -> float:
    """dt as a float, or SoilInputError: a step must be finite and > 0 [s]."""
    if not (isinstance(dt, (int, float, np.floating, np.integer)) and math.isfinite(dt) and dt > 0):
        raise SoilInputError(f"dt must be finite and > 0 [s], got {dt!r}")
    return float(dt)


def _check_count(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise SoilInputError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)
