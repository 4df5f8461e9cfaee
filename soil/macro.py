"""A macro step's capture and report: its steps replayed from captured graphs, the wheels'
wrench sums kept on the device, and the one array the host reads after it.

Each DEM step of a macro step is captured once as a graph (`wp.ScopedCapture`: a CUDA graph on
a GPU, Warp's recorded replay on the CPU) and replayed (StepGraphs). During the steps the
wrench of the soil on every body is summed on the device (MacroSums.accumulate); after the
last step one kernel packs the status, the grains' box, the sums and the boundaries'
displacement into one array (MacroSums.read), and MacroSums.report turns it into the
MacroStepReport a caller gets.
"""

import math
import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from . import status as status_columns
from . import step_control
from .errors import RegolithWarning
from .precision import kernel_factory, kernel_module, soil_kernel

REPORT_BOUNDS = status_columns.COLUMNS
"""Report columns after the status (soil.status): the grains' box at the last list build,
lower corner [m] (3) then upper corner [m] (3)."""
REPORT_BODIES = REPORT_BOUNDS + 6
"""First report column of the bodies: per body the force sum [N] (3) and torque sum [N m] (3)
over the macro step's steps, force and torque at its end (6), work done on the soil [J] (1),
grains touching at its end (1); then per boundary its displacement at the end [m] (3)."""
BODY_COLUMNS = 14
MAX_GRAPHS = 32
"""Captured steps kept at most; the oldest is dropped first (a caller that keeps changing the
step length would otherwise hold ever more graphs)."""


class CaptureWarning(RegolithWarning):
    """The device could not capture a step as a graph; steps are launched one by one."""


@kernel_factory
def macro_kernels(hi):
    """Kernels of a macro step's bookkeeping for the precision type `hi` (sums in float64)."""
    kernel = soil_kernel(kernel_module("macro", hi))
    vec_hi = wp.types.vector(3, hi)

    @kernel
    def accumulate_wrench(
        force: wp.array(dtype=vec_hi),
        torque: wp.array(dtype=vec_hi),
        velocity: wp.array(dtype=vec_hi),
        angular_velocity: wp.array(dtype=vec_hi),
        step_length: wp.array(dtype=wp.float64),
        weighted: int,
        active: wp.array(dtype=wp.int32),
        bodies_per_world: int,
        force_sum_out: wp.array(dtype=wp.vec3d),
        torque_sum_out: wp.array(dtype=wp.vec3d),
        work_out: wp.array(dtype=wp.float64),
    ):
        """Add a step's wrench on body b to the macro step's sums (one thread per body: a fixed
        order), weighted by the step's length when the steps vary (weighted != 0), for the bodies of
        the worlds whose step counts (active[world] != 0: a world's substep accepted); the soil's
        force does -F.v - T.w work on the soil side's books."""
        b = wp.tid()
        world = b // bodies_per_world  # type: ignore[operator]  # b: a Warp int (wp.tid)
        if active[world] == 0:
            return
        dt = step_length[world]
        f = wp.vec3d(wp.float64(force[b][0]), wp.float64(force[b][1]), wp.float64(force[b][2]))
        t = wp.vec3d(wp.float64(torque[b][0]), wp.float64(torque[b][1]), wp.float64(torque[b][2]))
        v = wp.vec3d(wp.float64(velocity[b][0]), wp.float64(velocity[b][1]), wp.float64(velocity[b][2]))
        w = wp.vec3d(
            wp.float64(angular_velocity[b][0]), wp.float64(angular_velocity[b][1]), wp.float64(angular_velocity[b][2])
        )
        if weighted != 0:
            force_sum_out[b] = force_sum_out[b] + f * dt
            torque_sum_out[b] = torque_sum_out[b] + t * dt
        else:
            force_sum_out[b] = force_sum_out[b] + f
            torque_sum_out[b] = torque_sum_out[b] + t
        # Warp's stubs do not list vec3d among the vector types wp.dot takes
        work_out[b] = work_out[b] - (wp.dot(f, v) + wp.dot(t, w)) * dt  # type: ignore[call-overload]

    @kernel
    def fill_report(
        status: wp.array(dtype=wp.int32),
        grid: wp.array(dtype=hi),
        force_sum: wp.array(dtype=wp.vec3d),
        torque_sum: wp.array(dtype=wp.vec3d),
        work: wp.array(dtype=wp.float64),
        force: wp.array(dtype=vec_hi),
        torque: wp.array(dtype=vec_hi),
        contacts: wp.array(dtype=wp.int32),
        boundary_displacement: wp.array(dtype=vec_hi),
        report_out: wp.array(dtype=wp.float64),
    ):
        """Everything the host needs after a macro step, in one array (read once)."""
        for c in range(status_columns.COLUMNS):
            report_out[c] = wp.float64(status[c])
        for axis in range(3):
            report_out[REPORT_BOUNDS + axis] = wp.float64(grid[axis])
            report_out[REPORT_BOUNDS + 3 + axis] = wp.float64(grid[6 + axis])
        for b in range(force.shape[0]):
            base = REPORT_BODIES + BODY_COLUMNS * b
            for axis in range(3):
                report_out[base + axis] = force_sum[b][axis]
                report_out[base + 3 + axis] = torque_sum[b][axis]
                report_out[base + 6 + axis] = wp.float64(force[b][axis])
                report_out[base + 9 + axis] = wp.float64(torque[b][axis])
            report_out[base + 12] = work[b]
            report_out[base + 13] = wp.float64(contacts[b])
        walls = REPORT_BODIES + BODY_COLUMNS * force.shape[0]
        for b in range(boundary_displacement.shape[0]):
            for axis in range(3):
                report_out[walls + 3 * b + axis] = wp.float64(boundary_displacement[b][axis])

    return dict(accumulate_wrench=accumulate_wrench, fill_report=fill_report)


@dataclass
class MacroStepReport:
    """What a macro step (Simulation.macro_step) returns, read from the device at once.

    Bodies' arrays are world frame, float64, one row per body."""

    steps: int
    """DEM steps taken [-]."""
    dt: float
    """Their length [s]."""
    body_force: np.ndarray
    """Mean force of the soil on each body over the steps [N], shape (body_count, 3)."""
    body_torque: np.ndarray
    """Mean torque of the soil on each body about its hub [N m], shape (body_count, 3)."""
    body_force_end: np.ndarray
    """Force of the soil on each body at the end [N], shape (body_count, 3)."""
    body_torque_end: np.ndarray
    """Torque at the end [N m], shape (body_count, 3)."""
    body_work: np.ndarray
    """Work done on the soil by each body over the steps [J], shape (body_count,) (sum of -F.v dt - T.w dt)."""
    body_contacts: np.ndarray
    """Grains touching each body at the end [-], shape (body_count,), int64."""
    boundary_displacement: np.ndarray
    """Translation of each boundary from its initial geometry at the end [m], shape (boundary_count, 3)."""
    rebuilds: int
    """Neighbour-list builds during the macro step [-]."""
    redone: int
    """How often the macro step was redone after the contact storage grew [-]."""
    rejected: int = 0
    """Substeps the step control computed and threw away [-] (0 with fixed steps)."""
    forced: int = 0
    """Substeps accepted at dt_min although their error exceeded the tolerance [-]."""
    dt_min: float = math.nan
    """Shortest step taken [s] (with fixed steps: dt)."""
    dt_max: float = math.nan
    """Longest step taken [s] (with fixed steps: dt)."""
    evaluations: int = 0
    """Force evaluations of the macro step, rejected substeps included [-]."""
    world_steps: tuple = ()
    """With the step control in worlds (soil.worlds): each world's own steps, dt, rejected, forced,
    dt_min, dt_max and evaluations (dicts of those fields; the fields above are then the batch's:
    the most steps any world took, the rejected and forced ones of all); empty otherwise."""


class StepGraphs:
    """The captured steps of one Simulation, by key (which buffers, path or not, integrator).

    A graph holds the addresses of the arrays it was captured with; `check` drops every graph
    when any of them changed (storage grown, buffers replaced). At most MAX_GRAPHS are kept.

    device: where the steps run. enabled: replay captured graphs (False: every kernel is
    launched from the host; both give bitwise the same results).
    """

    def __init__(self, device, enabled: bool = True):
        self.device = device
        self.enabled = bool(enabled)
        """Whether steps are replayed from captured graphs (False after a failed capture)."""
        self._graphs: dict = {}
        self._signature: tuple | None = None
        self._modules_loaded = False

    def clear(self) -> None:
        """Forget every captured graph (they hold arrays or settings that changed)."""
        self._graphs.clear()

    def check(self, signature: tuple) -> None:
        """Drop the graphs when `signature` (the identity of every array a step uses) changed."""
        if signature != self._signature:
            self._graphs.clear()
            self._signature = signature

    def load_modules(self, namespaces) -> None:
        """Load (compile) the modules of every kernel in `namespaces` (kernel_factory results) before a
        graph is captured: a GPU driver older than CUDA 12.3 cannot load modules during a capture."""
        if self._modules_loaded or not wp.get_device(self.device).is_cuda:
            return
        modules = {
            value.module for space in namespaces for value in vars(space).values() if isinstance(value, wp.Kernel)
        }
        for module in modules:
            module.load(wp.get_device(self.device))
        self._modules_loaded = True

    def replay(self, key: tuple, body, contacts) -> int | None:
        """Run `body` from its captured graph (captured at its first use): the force evaluations
        one replay counts (`contacts`, the ContactSolver, counts them), or None when the device
        cannot capture (then run `body` yourself)."""
        if not self.enabled:
            return None
        entry = self._graphs.get(key)
        if entry is None:
            if len(self._graphs) >= MAX_GRAPHS:
                del self._graphs[next(iter(self._graphs))]
            evaluations = contacts.evaluations
            try:
                with wp.ScopedCapture(device=self.device) as capture:
                    body()
                entry = self._graphs[key] = (capture.graph, contacts.evaluations - evaluations)
            except Exception as error:  # e.g. a GPU driver without conditional graph nodes
                warnings.warn(
                    f"steps cannot be captured as graphs on {self.device} ({error}); launching them one by one",
                    CaptureWarning,
                    stacklevel=4,
                )
                self.enabled = False
                self._graphs.clear()
            contacts.evaluations = evaluations  # counted when the graph runs
        if entry is None:
            return None
        graph, evaluations = entry
        wp.capture_launch(graph)
        return evaluations


class MacroSums:
    """The device side of a macro step's report: the bodies' wrench and work sums, and the
    report array the host reads once (columns REPORT_BOUNDS, REPORT_BODIES, then the step
    control's block from `steps_column`)."""

    def __init__(self, model):
        self.model = model
        device = model.device
        bodies = max(model.body_count, 1)
        self.force_sum = wp.zeros(bodies, dtype=wp.vec3d, device=device)
        """Sum of each body's force over the steps [N] (or [N s], weighted by the steps' lengths), shape (bodies,)."""
        self.torque_sum = wp.zeros(bodies, dtype=wp.vec3d, device=device)
        """Sum of each body's torque [N m] (or [N m s]), shape (bodies,)."""
        self.work = wp.zeros(bodies, dtype=wp.float64, device=device)
        """Work done on the soil by each body [J], shape (bodies,)."""
        self.every_world = wp.ones(model.world_count, dtype=wp.int32, device=device)
        """accumulate's `active` when every world's step counts (all 1) [-], shape (worlds,)."""
        self.steps_column = REPORT_BODIES + BODY_COLUMNS * model.body_count + 3 * model.boundary_count
        """First report column of the step control's block (soil.step_control columns)."""
        self.values = wp.zeros(
            self.steps_column + step_control.COLUMNS * model.world_count, dtype=wp.float64, device=device
        )
        """The report array on the device, each column in its unit (REPORT_*, BODY_COLUMNS' and the step
        control's columns), shape (steps_column + soil.step_control.COLUMNS x worlds,)."""

    def clear(self) -> None:
        """Zero the sums (at a macro step's start)."""
        for array in (self.force_sum, self.torque_sum, self.work):
            array.zero_()

    def accumulate(self, state, step_length64: wp.array, weighted: bool, active: wp.array | None = None) -> None:
        """Add the bodies' wrench of `state` (a SoilState at a step's end, with the bodies' velocities
        the wrench works against) to the sums (capturable): step_length64 [s] shape (worlds,), float64
        (soil.worlds; one value for a scene alone); weighted: multiply by the step's length (variable
        steps); active: int32 (worlds,), the worlds whose bodies count (None: all)."""
        if not self.model.body_count:
            return
        wp.launch(
            macro_kernels(self.model.precision.hi).accumulate_wrench,
            dim=self.model.body_count,
            inputs=[
                state.body_force,
                state.body_torque,
                state.body_velocity,
                state.body_angular_velocity,
                step_length64,
                int(weighted),
                self.every_world if active is None else active,
                self.model.bodies_per_world,
            ],
            outputs=[self.force_sum, self.torque_sum, self.work],
            device=self.model.device,
        )

    def read(self, status: wp.array, grid: wp.array, current, steps=None) -> np.ndarray:
        """Pack what the host needs after a macro step into one array (with the step control's
        block when `steps`, a DeviceStepControl, is given) and read it: the one read of the macro
        step. status: soil.status columns; grid: the neighbour list's grid (its box); current: the
        state at the macro step's end."""
        wp.launch(
            macro_kernels(self.model.precision.hi).fill_report,
            dim=1,
            inputs=[
                status,
                grid,
                self.force_sum,
                self.torque_sum,
                self.work,
                current.body_force,
                current.body_torque,
                current.body_contacts,
                current.boundary_displacement,
            ],
            outputs=[self.values],
            device=self.model.device,
        )
        if steps is not None:
            wp.copy(self.values, steps.control, dest_offset=self.steps_column, count=steps.control.shape[0])
        return self.values.numpy().copy()

    def report(self, values: np.ndarray, averaged_over: float, **fields) -> MacroStepReport:
        """The macro step's report from the array read back: the wheels' wrench sums divided by
        `averaged_over` (the step count, or the span [s] where the sums are weighted by each
        substep's length), their end values, work and contacts, the walls' displacement, and
        `fields` (the step counts and lengths)."""
        model = self.model
        walls = REPORT_BODIES + BODY_COLUMNS * model.body_count
        bodies = values[REPORT_BODIES:walls].reshape(model.body_count, BODY_COLUMNS)
        return MacroStepReport(
            body_force=bodies[:, 0:3] / averaged_over,
            body_torque=bodies[:, 3:6] / averaged_over,
            body_force_end=bodies[:, 6:9].copy(),
            body_torque_end=bodies[:, 9:12].copy(),
            body_work=bodies[:, 12].copy(),
            body_contacts=bodies[:, 13].astype(np.int64),
            boundary_displacement=values[walls : self.steps_column].reshape(model.boundary_count, 3),
            **fields,
        )


def grain_box(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The grains' box at the last list build from a report array: (lower, upper) corners [m], (3,) each."""
    return values[REPORT_BOUNDS : REPORT_BOUNDS + 3], values[REPORT_BOUNDS + 3 : REPORT_BOUNDS + 6]
