"""A whole simulation at one instant, kept on its device, to go back to (Simulation.snapshot).

A co-simulation that must refuse a step (an FMU's Discard, a retry with a shorter step) takes a
snapshot before the step and restores it after: the simulation is then what it was, and the
next step gives the same bits as if the refused one had never been taken. The grains' state
is copied device to device (no host read); the control, the counters and the divergence
monitor's bounds are host values.
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from .state import SoilState

COUNTERS = ("steps", "accepted_steps", "rejected_steps", "forced_steps")
"""The Simulation's step counters a snapshot keeps [-]."""


@dataclass
class SimulationSnapshot:
    """What Simulation.restore puts back (make it with Simulation.snapshot)."""

    model: object
    """The soil.SoilModel of the simulation it was taken from (a snapshot fits that simulation only)."""
    state: SoilState
    """A device copy of the current state (time, grains, contact history, wrenches, walls' motion) and,
    with its own layout, of the storage order and the neighbour lists."""
    control: dict
    """SoilControl.snapshot(): the bodies' and boundaries' motion, external forces."""
    counters: dict
    """The step counters by name (COUNTERS) [-]."""
    monitor: dict
    """DivergenceMonitor.state_dict(): its settings and bounds (its last good state is not part of it)."""
    controller: dict | None
    """The host StepController's state_dict() (run_adaptive), or None."""
    step_control: wp.array | None
    """A device copy of the device step control's block (macro_step_adaptive), each column in its unit
    (soil.step_control's columns), shape (worlds * COLUMNS,), float64; or None."""
    reorder: tuple
    """The storage-order bookkeeping between macro steps (list builds since the last reorder, the
    grains' box at the last build)."""


def take(sim, controller: dict | None, reorder: tuple, into: SimulationSnapshot | None = None) -> SimulationSnapshot:
    """Simulation.snapshot (its docstring): the simulation's public parts, with its host `controller` state
    and `reorder` bookkeeping, which it hands over (its own private fields)."""
    state = sim.state
    if into is None or into.model is not sim.model:
        copy = SoilState.for_model(sim.model, state.capacity, state.rigid_capacity)
    else:
        copy = into.state
    copy.assign(state)  # arrays (and its own layout) follow the state's shapes
    step_control = None
    if sim.step_control is not None:
        kept = into.step_control if into is not None and into.model is sim.model else None
        step_control = kept if kept is not None else wp.empty_like(sim.step_control.control)
        wp.copy(step_control, sim.step_control.control)
    return SimulationSnapshot(
        model=sim.model,
        state=copy,
        control=sim.control.snapshot(),
        counters={name: int(getattr(sim, name)) for name in COUNTERS},
        monitor=sim.monitor.state_dict(),
        controller=controller,
        step_control=step_control,
        reorder=reorder,
    )


def put_back(sim, snapshot: SimulationSnapshot) -> None:
    """Simulation.restore (its docstring): the public parts; the simulation puts back its controller and
    reorder bookkeeping (snapshot.controller, snapshot.reorder) itself."""
    from .errors import SoilInputError

    if not isinstance(snapshot, SimulationSnapshot):
        raise SoilInputError(f"restore takes what Simulation.snapshot() returned, got {type(snapshot).__name__}")
    if snapshot.model is not sim.model:
        raise SoilInputError("the snapshot was taken from another simulation (another model)")
    # storage grown since (the refused step widened the contact history) stays grown: every buffer
    # of the simulation keeps one width
    snapshot.state.grow_capacity(sim.state.capacity, sim.state.rigid_capacity)
    sim.state.assign(snapshot.state)
    sim.control.restore(snapshot.control)
    for name, value in snapshot.counters.items():
        setattr(sim, name, value)
    sim.monitor.load_state_dict(snapshot.monitor)
    if snapshot.step_control is not None and sim.step_control is not None:
        wp.copy(sim.step_control.control, snapshot.step_control)
