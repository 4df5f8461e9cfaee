"""The PID step control on the device: the StepController's decision as a kernel, so that a macro
step with variable DEM substeps runs as one captured graph (docs/performance.md section 3).

A macro step of span T runs `wp.capture_while(running, substep)`; each substep

1. `propose`: h = the controller's next step, clamped to land on the macro step's end without a
   sliver of a last step (the rule of Simulation.run_adaptive), written where the kernels read
   their step length;
2. steps the current state into a trial buffer and reduces the error norm (JoltBeeman);
3. `decide`: the StepController's accept/reject rule (Soderlind's PID on the normalised
   error, soil.integrator.StepController) on the device; it counts the steps and keeps the
   step statistics;
4. accepted: the trial is copied over the current state (`wp.capture_if`); rejected: the
   current state was never written, so the next trial starts from it bit for bit.

The loop ends when the span is covered, when a trial overflowed the contact storage (the
host grows it and redoes the macro step from its start) or when a step at dt_min is still
non-finite (a divergence). Everything the host needs is in `values`, read once per macro
step with the report.

Worlds (soil.worlds) each have their own controller: a row of the control block, their own
step length, error norm and decision, in the same launches. When some worlds keep their trial
and others do not, `finish` marks the others, which take their current state back into the
trial (SoilState.copy_worlds; their pair history remapped onto a list rebuilt by the trial:
soil.neighbours) before the trial is copied over the current state; a world whose span is
covered tries steps it keeps nothing of until the last world is done. Each world then takes
the substeps it takes alone, bit for bit.
"""

import math

import numpy as np
import warp as wp

from . import status as status_columns
from .errors import InternalError, SoilInputError
from .integrator import (
    SUMMARY_MAX,
    SUMMARY_NONFINITE,
    SUMMARY_RMS,
    SUMMARY_SPEED,
    StepController,
)
from .precision import kernel_factory, kernel_module, soil_kernel

# Columns of the control block (float64). The first ones carry over from one macro step to the next.
NEXT_STEP = 0
"""The step the controller proposes next [s]."""
C_PREVIOUS = 1
"""c = (tolerance / err)^(1/k) of the last accepted step [-]."""
C_BEFORE = 2
"""c of the accepted step before it [-]."""
HISTORY = 3
"""How many of C_PREVIOUS, C_BEFORE hold values (0..2) [-]."""
SPEED_SEEN = 4
"""Largest grain speed seen so far [m/s] (a floor of the velocity scale V)."""
CARRIED = 5
"""Columns 0..CARRIED-1 are the controller's state between macro steps (checkpointed)."""
REMAINING = 5
"""Time left to the macro step's end [s]."""
ELAPSED = 6
"""Time since the macro step's start, of the accepted substeps [s]."""
STEP = 7
"""Length of the substep being tried [s]."""
ACCEPTED = 8
"""Substeps accepted in this macro step [-]."""
REJECTED = 9
"""Substeps computed and thrown away in this macro step [-]."""
FORCED = 10
"""Substeps accepted at dt_min although their error exceeded the tolerance [-]."""
SMALLEST = 11
"""Shortest accepted substep [s] (a landing substep included)."""
LARGEST = 12
"""Longest accepted substep [s]."""
DIVERGED = 13
"""1 when a substep at dt_min was still non-finite (the macro step stops; the host reports it)."""
OVERFLOW = 14
"""1 when a trial overflowed the contact storage (the host grows it and redoes the macro step)."""
COLUMNS = 15


@kernel_factory
def step_control_kernels(hi):
    """The substep proposal and decision for the precision type `hi` (the control in float64), one
    thread per world (soil.worlds: each world its own row of the control block; one for a scene alone)."""
    kernel = soil_kernel(kernel_module("step_control", hi))

    @kernel
    def begin(
        span: wp.float64,
        stepping: wp.array(dtype=wp.int32),
        control: wp.array2d(dtype=wp.float64),
        running_out: wp.array(dtype=wp.int32),
    ):
        """Start a macro step of `span` [s]: clear the world's per-macro-step columns (a world that does
        not step, stepping[w] == 0, has no span: it keeps its state)."""
        w = wp.tid()
        control[w, REMAINING] = span
        if stepping[w] == 0:
            control[w, REMAINING] = wp.float64(0.0)
        control[w, ELAPSED] = wp.float64(0.0)
        control[w, STEP] = wp.float64(0.0)
        for column in range(ACCEPTED, COLUMNS):
            control[w, column] = wp.float64(0.0)
        control[w, SMALLEST] = wp.float64(wp.inf)
        if w == 0:
            running_out[0] = 0
            if span > wp.float64(0.0):
                running_out[0] = 1

    @kernel
    def propose(
        control: wp.array2d(dtype=wp.float64),
        floor: wp.float64,
        step_length_out: wp.array(dtype=hi),
        step_length64_out: wp.array(dtype=wp.float64),
        tau_out: wp.array(dtype=hi),
        scale_floor_out: wp.array(dtype=hi),
    ):
        """The world's next substep h: the proposal, or the rest of the span when it is shorter, or half
        the rest when a full step would leave a sliver (a tiny step spoils the next jolt); and the floor
        of the error norm's velocity scale, max(floor, largest speed seen) [m/s]. A world whose span is
        covered while others go on tries its proposal from where it is, at its span's end, and keeps
        nothing of it (decide)."""
        w = wp.tid()
        dt = control[w, NEXT_STEP]
        remaining = control[w, REMAINING]
        h = dt
        if remaining <= wp.float64(0.0):
            h = dt
        elif remaining <= dt:
            h = remaining
        elif remaining < wp.float64(2.0) * dt:
            h = wp.float64(0.5) * remaining
        if remaining > wp.float64(0.0):
            control[w, STEP] = h
        step_length_out[w] = hi(h)
        step_length64_out[w] = h
        tau = control[w, ELAPSED]
        if remaining > wp.float64(0.0):
            tau = tau + h
        tau_out[w] = hi(tau)
        scale_floor_out[w] = hi(wp.max(floor, control[w, SPEED_SEEN]))

    @kernel
    def decide(
        summary: wp.array2d(dtype=hi),
        tolerance: wp.float64,
        dt_min: wp.float64,
        dt_max: wp.float64,
        order: wp.float64,
        b1: wp.float64,
        b2: wp.float64,
        b3: wp.float64,
        rho_min: wp.float64,
        rho_max: wp.float64,
        reject_below: wp.float64,
        normalise: int,
        max_norm: int,
        grain_factor: wp.float64,
        capacity: int,
        rigid_capacity: int,
        control: wp.array2d(dtype=wp.float64),
        status: wp.array(dtype=wp.int32),
        accepted_out: wp.array(dtype=wp.int32),
    ):
        """StepController.error and .decide for the world's substep just tried (a world whose span is
        covered keeps nothing: accepted_out 0)."""
        w = wp.tid()
        accepted_out[w] = 0
        if control[w, REMAINING] <= wp.float64(0.0):
            return
        h = control[w, STEP]
        err = wp.float64(wp.inf)
        nonfinite = summary[w, SUMMARY_NONFINITE] > hi(0.0) or not wp.isfinite(summary[w, SUMMARY_MAX])
        if not nonfinite:
            if normalise != 0:
                control[w, SPEED_SEEN] = wp.max(control[w, SPEED_SEEN], wp.float64(summary[w, SUMMARY_SPEED]))
            if max_norm != 0:
                err = wp.float64(summary[w, SUMMARY_MAX])
            else:
                err = wp.max(wp.float64(summary[w, SUMMARY_RMS]), wp.float64(summary[w, SUMMARY_MAX]) / grain_factor)
        accept = 0
        proposal = wp.max(dt_min, rho_min * h)
        if wp.isfinite(err):
            c = wp.pow(tolerance / wp.max(err, wp.float64(1.0e-3) * tolerance), wp.float64(1.0) / order)
            previous = wp.float64(1.0)
            if control[w, HISTORY] > wp.float64(0.0):
                previous = control[w, C_PREVIOUS]
            before = previous
            if control[w, HISTORY] > wp.float64(1.0):
                before = control[w, C_BEFORE]
            rho = wp.pow(c, b1) * wp.pow(previous, b2) * wp.pow(before, b3)
            rho = wp.min(wp.max(rho, rho_min), rho_max)
            if rho < reject_below and err > tolerance:
                proposal = wp.max(dt_min, h * wp.max(rho_min, wp.min(wp.float64(0.9) * c, wp.float64(0.9))))
            else:
                accept = 1
                control[w, C_BEFORE] = control[w, C_PREVIOUS]
                control[w, C_PREVIOUS] = c
                control[w, HISTORY] = wp.min(control[w, HISTORY] + wp.float64(1.0), wp.float64(2.0))
                proposal = wp.min(wp.max(rho * h, dt_min), dt_max)
        if accept == 0 and h <= dt_min * wp.float64(1.0 + 1.0e-9):
            accept = 1  # at dt_min every step is kept; a non-finite one is a divergence
            control[w, FORCED] = control[w, FORCED] + wp.float64(1.0)
            if nonfinite:
                control[w, DIVERGED] = wp.float64(1.0)
        if accept != 0:
            if h >= control[w, REMAINING]:
                control[w, REMAINING] = wp.float64(0.0)
            else:
                control[w, REMAINING] = control[w, REMAINING] - h
            control[w, ELAPSED] = control[w, ELAPSED] + h
            control[w, ACCEPTED] = control[w, ACCEPTED] + wp.float64(1.0)
            control[w, SMALLEST] = wp.min(control[w, SMALLEST], h)
            control[w, LARGEST] = wp.max(control[w, LARGEST], h)
            # a substep shortened to land on the macro step's end says nothing about the step allowed
            if h >= control[w, NEXT_STEP]:
                control[w, NEXT_STEP] = proposal
            else:
                control[w, NEXT_STEP] = wp.max(proposal, control[w, NEXT_STEP])
        else:
            control[w, REJECTED] = control[w, REJECTED] + wp.float64(1.0)
            control[w, NEXT_STEP] = proposal
        if status[status_columns.NEEDED_NEIGHBOURS] > capacity or status[status_columns.NEEDED_RIGID] > rigid_capacity:
            control[w, OVERFLOW] = wp.float64(1.0)
        accepted_out[w] = accept

    @kernel
    def finish(
        accepted: wp.array(dtype=wp.int32),
        worlds: int,
        control: wp.array2d(dtype=wp.float64),
        status: wp.array(dtype=wp.int32),
        running_out: wp.array(dtype=wp.int32),
        any_accepted_out: wp.array(dtype=wp.int32),
        any_restore_out: wp.array(dtype=wp.int32),
        restore_out: wp.array(dtype=wp.int32),
    ):
        """After every world's decision (one thread, the worlds in order): whether the loop goes on (a
        world still has span to cover, none diverged, the storage held), whether any world keeps its
        trial, and, when some do, which worlds take their state back into the trial (restore_out)
        before it is copied over the current state. A trial's non-finite grains are no state's unless
        a world diverged."""
        going = int(0)  # noqa: UP018 (Warp variables the loop changes: not constants)
        stop = int(0)  # noqa: UP018
        kept = int(0)  # noqa: UP018
        for w in range(worlds):
            if control[w, REMAINING] > wp.float64(0.0):
                going = 1
            if control[w, DIVERGED] != wp.float64(0.0) or control[w, OVERFLOW] != wp.float64(0.0):
                stop = 1
            kept = kept + accepted[w]
        restore = int(0)  # noqa: UP018
        for w in range(worlds):
            restore_out[w] = 0
            if kept > 0 and accepted[w] == 0:
                restore_out[w] = 1
                restore = 1
        diverged = int(0)  # noqa: UP018
        for w in range(worlds):
            if control[w, DIVERGED] != wp.float64(0.0):
                diverged = 1
        if diverged == 0:
            status[status_columns.NONFINITE] = 0
            status[status_columns.WORST] = -1
        running_out[0] = 0
        if going != 0 and stop == 0:
            running_out[0] = 1
        any_accepted_out[0] = 0
        if kept > 0:
            any_accepted_out[0] = 1
        any_restore_out[0] = restore

    return dict(begin=begin, propose=propose, decide=decide, finish=finish)


class DeviceStepControl:
    """The device arrays of the PID step control of one Simulation (one controller per world of
    soil.worlds), and its settings (a StepController whose dt_min/dt_max are resolved).

    The controller's state between macro steps (next step, the last two c values, the largest
    speed seen) lives in `control` on the device; state_dict() reads it (a checkpoint is a host
    operation anyway) and load_state_dict() writes it back, so a resumed run takes the same
    steps bit for bit.
    """

    def __init__(self, controller: StepController, precision, device, gravity_speed: float, worlds: int = 1):
        if controller.dt_max is None or controller.dt_min is None:
            raise InternalError("the step controller's dt_min and dt_max must be resolved (StepController.setup)")
        self.controller = controller
        self.worlds = int(worlds)
        """Worlds controlled, each by its own row of `control` [-]."""
        self.kernels = step_control_kernels(precision.hi)
        size = self.worlds * COLUMNS
        self.control = wp.zeros(size, dtype=wp.float64, device=device)
        """The control block: per world a row of the columns of soil.step_control, each in its unit (NEXT_STEP
        [s], ...), float64, shape (worlds * COLUMNS,)."""
        self.rows = self.control.reshape((self.worlds, COLUMNS))
        """`control` seen as a row per world (units by column), shape (worlds, COLUMNS) (the same memory: what
        the kernels index)."""
        self.control_start = wp.zeros(size, dtype=wp.float64, device=device)
        """The control block at the macro step's start (restored when the macro step is redone), units by
        column, shape (worlds * COLUMNS,), float64."""
        self.running = wp.zeros(1, dtype=wp.int32, device=device)
        """The substep loop's condition: 1 while the macro step goes on [-], shape (1,), int32."""
        self.accepted = wp.zeros(self.worlds, dtype=wp.int32, device=device)
        """1 where a world kept its last substep [-], shape (worlds,)."""
        self.any_accepted = wp.zeros(1, dtype=wp.int32, device=device)
        """1 when some world kept its last substep (the trial is then copied over the current state) [-], shape
        (1,)."""
        self.restore = wp.zeros(self.worlds, dtype=wp.int32, device=device)
        """1 where a world takes its current state back into the trial first (others kept theirs) [-], shape
        (worlds,)."""
        self.any_restore = wp.zeros(1, dtype=wp.int32, device=device)
        """1 when some world takes its state back (restore) [-], shape (1,)."""
        self.stepping = wp.ones(self.worlds, dtype=wp.int32, device=device)
        """1 where a world takes the next macro step (set_stepping; a world that left a batch keeps its state)
        [-], shape (worlds,)."""
        self.tau = wp.zeros(self.worlds, dtype=precision.hi, device=device)
        """End of each world's trial substep since the macro step's start [s] (where its wheels are posed),
        shape (worlds,)."""
        first = controller.dt if controller.dt is not None else 0.1 * controller.dt_max
        first = float(np.clip(controller.dt_initial or first, controller.dt_min, controller.dt_max))
        start = np.zeros(COLUMNS)
        start[NEXT_STEP] = first
        start[C_PREVIOUS] = start[C_BEFORE] = 1.0
        start[SPEED_SEEN] = controller.speed_seen if controller.normalise else 0.0
        self.control.assign(np.tile(start, self.worlds))
        self.floor = max(gravity_speed, controller.velocity_scale) if controller.normalise else 1.0
        """The floor of the velocity scale V before the speeds seen [m/s] (StepController.error_scales)."""

    def begin(self, span: float) -> None:
        """Start a macro step of span [s] (a launch before the captured loop) and keep its start."""
        device = self.control.device
        wp.launch(
            self.kernels.begin,
            dim=self.worlds,
            inputs=[float(span), self.stepping, self.rows],
            outputs=[self.running],
            device=device,
        )
        wp.copy(self.control_start, self.control)

    def set_stepping(self, worlds) -> None:
        """The worlds (indices) that take the following macro steps; the others keep their state."""
        flags = np.zeros(self.worlds, dtype=np.int32)
        flags[list(worlds)] = 1
        self.stepping.assign(flags)

    def redo(self) -> None:
        """Back to the control block of the macro step's start (the macro step is redone)."""
        wp.copy(self.control, self.control_start)
        self.running.fill_(1)

    def propose(self, step_length: wp.array, step_length64: wp.array, scale_floor: wp.array) -> None:
        wp.launch(
            self.kernels.propose,
            dim=self.worlds,
            inputs=[self.rows, self.floor],
            outputs=[step_length, step_length64, self.tau, scale_floor],
            device=self.control.device,
        )

    def decide(self, summary: wp.array, status: wp.array, capacity: int, rigid_capacity: int) -> None:
        """Every world's decision on its substep (summary: JoltBeeman.summary, a row per world), then
        whether the loop goes on and which worlds take their state back (finish)."""
        c = self.controller
        assert c.dt_min is not None and c.dt_max is not None  # resolved before (__init__)
        b1, b2, b3 = c.exponents
        device = self.control.device
        wp.launch(
            self.kernels.decide,
            dim=self.worlds,
            inputs=[
                summary,
                float(c.tolerance),
                float(c.dt_min),
                float(c.dt_max),
                float(c.order),
                b1,
                b2,
                b3,
                float(c.rho_min),
                float(c.rho_max),
                float(c.reject_below),
                int(c.normalise),
                int(c.norm == "max"),
                float(c.grain_factor) if math.isfinite(c.grain_factor) else 1e300,
                int(capacity),
                int(rigid_capacity),
                self.rows,
                status,
            ],
            outputs=[self.accepted],
            device=device,
        )
        wp.launch(
            self.kernels.finish,
            dim=1,
            inputs=[self.accepted, self.worlds, self.rows, status],
            outputs=[self.running, self.any_accepted, self.any_restore, self.restore],
            device=device,
        )

    def state_dict(self) -> dict:
        """The controller's settings (StepController.state_dict) and its device state (one read):
        'device' holds the carried columns, shape (CARRIED,) alone, (worlds, CARRIED) for worlds."""
        values = self.control.numpy().reshape(self.worlds, COLUMNS)[:, :CARRIED].copy()
        data = self.controller.state_dict()
        data["device"] = values[0] if self.worlds == 1 else values
        return data

    def state_dict_units(self) -> dict[str, str]:
        """{key of state_dict(): its unit}; 'device' holds columns of different units."""
        units = self.controller.state_dict_units()
        units["device"] = "by column: s, 1, 1, count, m/s (NEXT_STEP, C_PREVIOUS, C_BEFORE, HISTORY, SPEED_SEEN)"
        return units

    def load_state_dict(self, data: dict) -> None:
        carried = np.asarray(data["device"], dtype=np.float64)
        if carried.size % CARRIED:
            raise SoilInputError(f"step_control/device: {carried.size} values, not rows of {CARRIED}")
        carried = carried.reshape(-1, CARRIED)
        if carried.shape[0] not in (1, self.worlds):
            raise SoilInputError(
                f"step_control/device: the saved control of {carried.shape[0]} worlds does not fit a simulation of "
                f"{self.worlds} (a world's checkpoint holds one row)"
            )
        values = np.zeros((self.worlds, COLUMNS))
        values[:, :CARRIED] = carried
        self.control.assign(values.reshape(-1))
