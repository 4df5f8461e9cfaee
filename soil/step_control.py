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
"""

import math

import numpy as np
import warp as wp

from . import status as status_columns
from .errors import InternalError
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
    """The substep proposal and decision for the precision type `hi` (the control in float64)."""
    kernel = soil_kernel(kernel_module("step_control", hi))

    @kernel
    def begin(span: wp.float64, control: wp.array(dtype=wp.float64), running_out: wp.array(dtype=wp.int32)):
        """Start a macro step of `span` [s]: clear the per-macro-step columns."""
        control[REMAINING] = span
        control[ELAPSED] = wp.float64(0.0)
        control[STEP] = wp.float64(0.0)
        for column in range(ACCEPTED, COLUMNS):
            control[column] = wp.float64(0.0)
        control[SMALLEST] = wp.float64(wp.inf)
        running_out[0] = 0
        if span > wp.float64(0.0):
            running_out[0] = 1

    @kernel
    def propose(
        control: wp.array(dtype=wp.float64),
        floor: wp.float64,
        step_length_out: wp.array(dtype=hi),
        step_length64_out: wp.array(dtype=wp.float64),
        tau_out: wp.array(dtype=hi),
        scale_floor_out: wp.array(dtype=hi),
    ):
        """The next substep h: the proposal, or the rest of the span when it is shorter, or half the
        rest when a full step would leave a sliver (a tiny step spoils the next jolt); and the floor
        of the error norm's velocity scale, max(floor, largest speed seen) [m/s]."""
        dt = control[NEXT_STEP]
        remaining = control[REMAINING]
        h = dt
        if remaining <= dt:
            h = remaining
        elif remaining < wp.float64(2.0) * dt:
            h = wp.float64(0.5) * remaining
        control[STEP] = h
        step_length_out[0] = hi(h)
        step_length64_out[0] = h
        tau_out[0] = hi(control[ELAPSED] + h)
        scale_floor_out[0] = hi(wp.max(floor, control[SPEED_SEEN]))

    @kernel
    def decide(
        summary: wp.array(dtype=hi),
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
        control: wp.array(dtype=wp.float64),
        status: wp.array(dtype=wp.int32),
        running_out: wp.array(dtype=wp.int32),
        accepted_out: wp.array(dtype=wp.int32),
    ):
        """StepController.error and .decide for the substep just tried (one thread)."""
        h = control[STEP]
        err = wp.float64(wp.inf)
        nonfinite = summary[SUMMARY_NONFINITE] > hi(0.0) or not wp.isfinite(summary[SUMMARY_MAX])
        if not nonfinite:
            if normalise != 0:
                control[SPEED_SEEN] = wp.max(control[SPEED_SEEN], wp.float64(summary[SUMMARY_SPEED]))
            if max_norm != 0:
                err = wp.float64(summary[SUMMARY_MAX])
            else:
                err = wp.max(wp.float64(summary[SUMMARY_RMS]), wp.float64(summary[SUMMARY_MAX]) / grain_factor)
        accept = 0
        proposal = wp.max(dt_min, rho_min * h)
        if wp.isfinite(err):
            c = wp.pow(tolerance / wp.max(err, wp.float64(1.0e-3) * tolerance), wp.float64(1.0) / order)
            previous = wp.float64(1.0)
            if control[HISTORY] > wp.float64(0.0):
                previous = control[C_PREVIOUS]
            before = previous
            if control[HISTORY] > wp.float64(1.0):
                before = control[C_BEFORE]
            rho = wp.pow(c, b1) * wp.pow(previous, b2) * wp.pow(before, b3)
            rho = wp.min(wp.max(rho, rho_min), rho_max)
            if rho < reject_below and err > tolerance:
                proposal = wp.max(dt_min, h * wp.max(rho_min, wp.min(wp.float64(0.9) * c, wp.float64(0.9))))
            else:
                accept = 1
                control[C_BEFORE] = control[C_PREVIOUS]
                control[C_PREVIOUS] = c
                control[HISTORY] = wp.min(control[HISTORY] + wp.float64(1.0), wp.float64(2.0))
                proposal = wp.min(wp.max(rho * h, dt_min), dt_max)
        if accept == 0 and h <= dt_min * wp.float64(1.0 + 1.0e-9):
            accept = 1  # at dt_min every step is kept; a non-finite one is a divergence
            control[FORCED] = control[FORCED] + wp.float64(1.0)
            if nonfinite:
                control[DIVERGED] = wp.float64(1.0)
        if accept != 0:
            if h >= control[REMAINING]:
                control[REMAINING] = wp.float64(0.0)
            else:
                control[REMAINING] = control[REMAINING] - h
            control[ELAPSED] = control[ELAPSED] + h
            control[ACCEPTED] = control[ACCEPTED] + wp.float64(1.0)
            control[SMALLEST] = wp.min(control[SMALLEST], h)
            control[LARGEST] = wp.max(control[LARGEST], h)
            # a substep shortened to land on the macro step's end says nothing about the step allowed
            if h >= control[NEXT_STEP]:
                control[NEXT_STEP] = proposal
            else:
                control[NEXT_STEP] = wp.max(proposal, control[NEXT_STEP])
        else:
            control[REJECTED] = control[REJECTED] + wp.float64(1.0)
            control[NEXT_STEP] = proposal
            # the thrown-away trial's non-finite grains are not the state's
            status[status_columns.NONFINITE] = 0
            status[status_columns.WORST] = -1
        if status[status_columns.NEEDED_NEIGHBOURS] > capacity or status[status_columns.NEEDED_RIGID] > rigid_capacity:
            control[OVERFLOW] = wp.float64(1.0)
        accepted_out[0] = accept
        running_out[0] = 0
        if control[REMAINING] > wp.float64(0.0) and control[DIVERGED] == wp.float64(0.0):
            if control[OVERFLOW] == wp.float64(0.0):
                running_out[0] = 1

    return dict(begin=begin, propose=propose, decide=decide)


class DeviceStepControl:
    """The device arrays of the PID step control of one Simulation, and its settings (a
    StepController whose dt_min/dt_max are resolved).

    The controller's state between macro steps (next step, the last two c values, the largest
    speed seen) lives in `control` on the device; state_dict() reads it (a checkpoint is a host
    operation anyway) and load_state_dict() writes it back, so a resumed run takes the same
    steps bit for bit.
    """

    def __init__(self, controller: StepController, precision, device, gravity_speed: float):
        if controller.dt_max is None or controller.dt_min is None:
            raise InternalError("the step controller's dt_min and dt_max must be resolved (StepController.setup)")
        self.controller = controller
        self.kernels = step_control_kernels(precision.hi)
        self.control = wp.zeros(COLUMNS, dtype=wp.float64, device=device)
        """The control block, columns of soil.step_control, float64."""
        self.control_start = wp.zeros(COLUMNS, dtype=wp.float64, device=device)
        """The control block at the macro step's start (restored when the macro step is redone)."""
        self.running = wp.zeros(1, dtype=wp.int32, device=device)
        """The substep loop's condition: 1 while the macro step goes on."""
        self.accepted = wp.zeros(1, dtype=wp.int32, device=device)
        """1 when the last substep was accepted."""
        self.tau = wp.zeros(1, dtype=precision.hi, device=device)
        """End of the trial substep since the macro step's start [s] (where the wheels are posed)."""
        first = controller.dt if controller.dt is not None else 0.1 * controller.dt_max
        first = float(np.clip(controller.dt_initial or first, controller.dt_min, controller.dt_max))
        start = np.zeros(COLUMNS)
        start[NEXT_STEP] = first
        start[C_PREVIOUS] = start[C_BEFORE] = 1.0
        start[SPEED_SEEN] = controller.speed_seen if controller.normalise else 0.0
        self.control.assign(start)
        self.floor = max(gravity_speed, controller.velocity_scale) if controller.normalise else 1.0
        """The floor of the velocity scale V before the speeds seen [m/s] (StepController.error_scales)."""

    def begin(self, span: float) -> None:
        """Start a macro step of span [s] (a launch before the captured loop) and keep its start."""
        device = self.control.device
        wp.launch(self.kernels.begin, dim=1, inputs=[float(span), self.control], outputs=[self.running], device=device)
        wp.copy(self.control_start, self.control)

    def redo(self) -> None:
        """Back to the control block of the macro step's start (the macro step is redone)."""
        wp.copy(self.control, self.control_start)
        self.running.fill_(1)

    def propose(self, step_length: wp.array, step_length64: wp.array, scale_floor: wp.array) -> None:
        wp.launch(
            self.kernels.propose,
            dim=1,
            inputs=[self.control, self.floor],
            outputs=[step_length, step_length64, self.tau, scale_floor],
            device=self.control.device,
        )

    def decide(self, summary: wp.array, status: wp.array, capacity: int, rigid_capacity: int) -> None:
        c = self.controller
        assert c.dt_min is not None and c.dt_max is not None  # resolved before (__init__)
        b1, b2, b3 = c.exponents
        wp.launch(
            self.kernels.decide,
            dim=1,
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
                self.control,
                status,
            ],
            outputs=[self.running, self.accepted],
            device=self.control.device,
        )

    def state_dict(self) -> dict:
        """The controller's settings (StepController.state_dict) and its device state (one read)."""
        values = self.control.numpy()
        data = self.controller.state_dict()
        data["device"] = values[:CARRIED].copy()
        return data

    def load_state_dict(self, data: dict) -> None:
        values = np.zeros(COLUMNS)
        values[:CARRIED] = np.asarray(data["device"], dtype=np.float64)
        self.control.assign(values)
