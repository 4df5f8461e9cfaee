"""The mutable soil state: what changes every step, and where each grain is stored.

Grains are stored in an order of their own (soil.neighbours sorts them along a
space-filling curve so that near grains sit near each other in memory). Every array of a
SoilState is in that storage order; `GrainLayout.order` names the model index of the grain
in each slot. What leaves the state (`to_numpy`, checkpoints, beds, Simulation.positions())
is in model order, with contact partners named by model index, so the storage order is
invisible outside; the physics does not depend on it either (docs/performance.md).
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import warp as wp

from .errors import SoilInputError

UNBUILT = 1.0e30
"""Build position [m] of a grain whose neighbour list was never built: any check finds it
far from there and rebuilds the list."""


PAIR_HISTORY = ("pair_touching", "pair_tangential", "pair_rolling")
"""State arrays aligned with the neighbour list's rows (remapped, not copied, across lists)."""

STATE_UNITS: dict[str, str] = {
    "position": "m",
    "velocity": "m/s",
    "angular_velocity": "rad/s",
    "force": "N",
    "torque": "N m",
    "force_previous": "N",
    "torque_previous": "N m",
    "contact_count": "count",
    "pair_touching": "1",  # bits: entry k of the grain's neighbour row in contact
    "pair_tangential": "m",
    "pair_rolling": "rad",
    "rigid_key": "1",  # an index: the wall, or boundary_count + the body
    "rigid_count": "count",
    "rigid_tangential": "m",
    "rigid_rolling": "rad",
    "step_previous": "s",
    "body_force": "N",
    "body_torque": "N m",
    "body_contacts": "count",
    "body_position": "m",
    "body_rotation": "1",
    "body_velocity": "m/s",
    "body_angular_velocity": "rad/s",
    "body_posed": "1",
    "boundary_displacement": "m",
    "boundary_velocity": "m/s",
    "boundary_acceleration": "m/s^2",
    "boundary_acceleration_previous": "m/s^2",
    "boundary_force": "N",
    "boundary_torque": "N m",
    "boundary_contacts": "count",
    "neighbours": "1",  # model indices, -1 past neighbour_count
    "neighbour_count": "count",
    "build_position": "m",
    "time": "s",
    "step": "count",  # the DEM steps taken (a divergence monitor's last good state)
}
"""The unit of each array of a soil state as it leaves the state (SoilState.to_numpy, a bed file's
state group, a last good state's file): SI, "1" for dimensionless values, indices and flags, "count"
for counts; what each array is: SoilState's attributes of the same names."""


@wp.kernel(enable_backward=False)
def copy_world_words(
    source: wp.array(dtype=wp.uint32),
    words_per_element: int,
    inner: int,
    rows: int,
    rows_per_world: int,
    worlds: wp.array(dtype=wp.int32),
    target_out: wp.array(dtype=wp.uint32),
):
    """Copy the words of the rows (grains, walls, wheels or worlds) whose world is flagged in
    `worlds`: word t is in element t // words_per_element, which lies in row (element // inner) %
    rows (inner: the elements of a row that follow one another, 1 where the row is the fastest
    index), of world row // rows_per_world. A copy by bits: every type, every precision."""
    t = wp.tid()
    row = (t // words_per_element // inner) % rows  # type: ignore[operator]  # t: a Warp int (wp.tid)
    if worlds[row // rows_per_world] != 0:
        target_out[t] = source[t]


def _word_view(array: wp.array) -> wp.array:
    """A uint32 view of the memory of a contiguous array (no copy; it does not own the memory)."""
    size = wp.types.type_size_in_bytes(array.dtype)
    if size % 4 or not array.is_contiguous:
        raise TypeError(f"copy_worlds copies whole 32-bit words of contiguous arrays, not {array.dtype} {array.shape}")
    return wp.array(ptr=array.ptr, dtype=wp.uint32, shape=(array.size * size // 4,), device=array.device)


def _resize_like(target, source: wp.array) -> wp.array:
    """`target` if it has the shape and type of `source`, else a new array that has them."""
    if (
        target is not None
        and target.shape == source.shape
        and target.dtype == source.dtype
        and target.device == source.device
    ):
        return target
    return wp.empty(source.shape, dtype=source.dtype, device=source.device)


class GrainLayout:
    """Where each grain is stored, its constants in storage order, and the grains near it.

    Shared by the state buffers of a Simulation (they are always in the same storage
    order). Two neighbour lists: a state's pair history is aligned with the list its
    `list_index` names; a rebuild writes the other one, so a step never overwrites the
    list its input state needs (soil.neighbours).
    """

    def __init__(self, model, capacity: int):
        n = model.particle_count
        device = model.device
        prec = model.precision
        self.model = model
        self.order: wp.array = wp.array(np.arange(n, dtype=np.int32), dtype=wp.int32, device=device)
        """Model index of the grain stored in each slot [-], shape (particle_count,), int32."""
        self.slot: wp.array = wp.array(np.arange(n, dtype=np.int32), dtype=wp.int32, device=device)
        """Storage slot of each model index [-], shape (particle_count,), int32."""
        self.radius = wp.clone(model.radius)
        """Radius of the grain in each slot [m], shape (particle_count,), dtype lo."""
        self.mass = wp.clone(model.mass)
        """Mass of the grain in each slot [kg], shape (particle_count,), dtype lo."""
        self.inv_mass = wp.clone(model.inv_mass)
        """Inverse mass of the grain in each slot [1/kg], shape (particle_count,), dtype lo; 0: fixed."""
        self.inv_inertia = wp.clone(model.inv_inertia)
        """Inverse moment of inertia of the grain in each slot [1/(kg m^2)], shape (particle_count,), dtype lo."""
        self.material = wp.clone(model.material)
        """Material index of the grain in each slot [-], shape (particle_count,), int32."""
        self.slot_major = bool(getattr(model, "slot_major", False))
        """Whether the lists and the pair history are stored slot by slot (entry k of every grain
        side by side: what neighbouring GPU threads read together) instead of grain by grain."""
        self.neighbours = wp.full(
            (2, capacity, n) if self.slot_major else (2, n, capacity), -1, dtype=wp.int32, device=device
        )
        """Two neighbour lists: slots of the grains within r_i + r_j + skin of each grain at the
        list's build [-], shape (2, particle_count, capacity), int32 (-1 past the count); slot-major:
        (2, capacity, particle_count)."""
        self.neighbour_count = wp.zeros((2, n), dtype=wp.int32, device=device)
        """Entries used in each row of the two lists [-], shape (2, particle_count), int32."""
        self.build_position = wp.full((2, n), prec.vec_hi(UNBUILT, UNBUILT, UNBUILT), dtype=prec.vec_hi, device=device)
        """Position of each grain when the list was built [m], shape (2, particle_count)."""

    @property
    def capacity(self) -> int:
        """Neighbour slots per grain [-]."""
        return int(self.neighbours.shape[1 if self.slot_major else 2])

    def gather_constants(self, model) -> None:
        """Take the grains' constants from the model again (after the model's arrays changed,
        e.g. masses restored from a bed)."""
        self.model = model
        order = self.order.numpy()
        for name in ("radius", "mass", "inv_mass", "inv_inertia", "material"):
            getattr(self, name).assign(getattr(model, name).numpy()[order])

    @property
    def arrays(self) -> dict[str, wp.array]:
        return {name: value for name, value in vars(self).items() if isinstance(value, wp.array)}

    def grow(self, capacity: int) -> None:
        """Widen both lists to `capacity` slots per grain, keeping their entries."""
        old = self.capacity
        if capacity <= old:
            return
        values = self.neighbours.numpy()
        if self.slot_major:
            wider = np.full((2, capacity, values.shape[2]), -1, dtype=np.int32)
            wider[:, :old] = values
        else:
            wider = np.full(values.shape[:2] + (capacity,), -1, dtype=np.int32)
            wider[:, :, :old] = values
        self.neighbours = wp.array(wider, dtype=wp.int32, device=self.neighbours.device)

    def assign(self, other: GrainLayout) -> None:
        """Copy `other` into this layout (arrays are reshaped to other's)."""
        self.model = other.model
        self.slot_major = other.slot_major
        for name, array in other.arrays.items():
            target = _resize_like(getattr(self, name, None), array)
            wp.copy(target, array)
            setattr(self, name, target)

    def bytes_per_grain(self) -> float:
        """Device memory of the layout per grain [B]."""
        n = max(int(self.order.shape[0]), 1)
        return sum(a.capacity for a in self.arrays.values()) / n


class SoilState:
    """Particle kinematics, the latest forces and the per-contact history, in storage order.

    Contact history: a grain's contacts with other grains keep theirs in `pair_*`, aligned
    with the grain's row of its neighbour list (GrainLayout.neighbours[list_index]); a bit
    in `pair_touching` marks the entries in contact. Contacts with rigid partners (walls,
    boxes, wheels) keep theirs in `rigid_*` slots keyed by the partner: boundary index b,
    or boundary_count + body index. History that the contact law does not use (friction or
    rolling off) has zero width: it is neither stored, read nor written.

    Types (soil.precision): positions, velocities, forces and wrenches are `vec_hi`; spins,
    torques and the contact history are `vec_mid` (float32 in mixed; `vec_hi` when not given).
    """

    def __init__(
        self,
        particle_count: int,
        capacity: int,
        vec_hi,
        device: str,
        body_count: int = 0,
        boundary_count: int = 0,
        *,
        rigid_capacity: int = 4,
        friction: bool = True,
        rolling: bool = True,
        twisting: bool = False,
        layout: GrainLayout | None = None,
        vec_mid=None,
        slot_major: bool = False,
        worlds: int = 1,
    ):
        n = particle_count
        self.slot_major = bool(slot_major)
        """Whether the contact history is stored slot-major (shape (slots, particle_count)) instead of per
        grain (particle_count, slots): every per-grain history array below is then transposed."""

        def per_slot(slots: int) -> tuple[int, int]:
            return (slots, n) if self.slot_major else (n, slots)

        scalar = vec_hi._wp_scalar_type_
        vec_mid = vec_mid or vec_hi  # the stored type of spins, torques and history (soil.precision)
        tangential = capacity if friction else 0
        keeps_spin = rolling or twisting
        spin = capacity if keeps_spin else 0
        vec_spin = wp.types.vector(4 if twisting else 3, vec_mid._wp_scalar_type_)  # contact.spin_history_type
        self.layout = layout
        """Storage order, grain constants and neighbour lists (shared with the other buffers of a Simulation)."""
        self.position = wp.zeros(n, dtype=vec_hi, device=device)
        """Particle centre positions [m], shape (particle_count,)."""
        self.velocity = wp.zeros(n, dtype=vec_hi, device=device)
        """Particle velocities [m/s], shape (particle_count,)."""
        self.angular_velocity = wp.zeros(n, dtype=vec_mid, device=device)
        """Particle angular velocities [rad/s], shape (particle_count,), dtype mid."""
        self.force = wp.zeros(n, dtype=vec_hi, device=device)
        """Contact + external force on each particle at the state's time [N], shape (particle_count,)."""
        self.torque = wp.zeros(n, dtype=vec_mid, device=device)
        """Contact torque on each particle about its centre [N m], shape (particle_count,), dtype mid."""
        self.force_previous = wp.zeros(n, dtype=vec_hi, device=device)
        """Force of the previous step's state (time - step_previous) [N], shape (particle_count,).
        Multi-step integrators (jolt-Beeman) take the jolt from it."""
        self.torque_previous = wp.zeros(n, dtype=vec_mid, device=device)
        """Torque of the previous step's state [N m], shape (particle_count,), dtype mid."""
        self.contact_count = wp.zeros(n, dtype=wp.int32, device=device)
        """Contacts of each particle (grains, walls, wheels) at the state's time [-], shape (particle_count,)."""
        self._pair_capacity = int(capacity)
        self.pair_touching = wp.zeros(per_slot(_words(capacity)), dtype=wp.uint32, device=device)
        """Bit k of word k // 32: neighbour-list entry k is in contact [-], shape
        (particle_count, ceil(capacity / 32)), uint32."""
        self.pair_tangential = wp.zeros(per_slot(tangential), dtype=vec_mid, device=device)
        """Accumulated tangential displacement per neighbour-list entry [m], shape (particle_count, capacity),
        dtype mid (width 0 without friction)."""
        self.pair_rolling = wp.zeros(per_slot(spin), dtype=vec_spin, device=device)
        """Spin history per neighbour-list entry: the accumulated rolling angle [rad] (3 components)
        and, with twisting resistance, the twist angle about the normal [rad] (a 4th), shape
        (particle_count, capacity), dtype mid (width 0 without rolling or twisting resistance)."""
        self.rigid_key = wp.full(per_slot(rigid_capacity), -1, dtype=wp.int32, device=device)
        """Rigid partner of each rigid-contact slot [-] (boundary b, or boundary_count + body), shape
        (particle_count, rigid_capacity), int32, -1 past rigid_count."""
        self.rigid_count = wp.zeros(n, dtype=wp.int32, device=device)
        """Used rigid-contact slots of each particle [-], shape (particle_count,)."""
        self.rigid_tangential = wp.zeros(per_slot(rigid_capacity if friction else 0), dtype=vec_mid, device=device)
        """Accumulated tangential displacement per rigid-contact slot [m], shape (particle_count, rigid_capacity),
        dtype mid."""
        self.rigid_rolling = wp.zeros(per_slot(rigid_capacity if keeps_spin else 0), dtype=vec_spin, device=device)
        """Spin history per rigid-contact slot [rad] (as pair_rolling), shape (particle_count, rigid_capacity)."""
        self.step_previous = wp.zeros(max(int(worlds), 1), dtype=scalar, device=device)
        """Length of the step that produced each world's state [s], shape (worlds,) (soil.worlds; one for a
        scene alone); 0 = no history (start-up: jolt-Beeman then assumes zero jolt)."""
        self.body_force = wp.zeros(body_count, dtype=vec_hi, device=device)
        """Soil force on each body (wheel) at the state's time, world [N], shape (body_count,)."""
        self.body_torque = wp.zeros(body_count, dtype=vec_hi, device=device)
        """Soil torque on each body about its hub, world [N m], shape (body_count,)."""
        self.body_contacts = wp.zeros(body_count, dtype=wp.int32, device=device)
        """Number of particles touching each body [-], shape (body_count,)."""
        self.body_position = wp.zeros(body_count, dtype=vec_hi, device=device)
        """Hub position of each body at the state's time, world [m], shape (body_count,)."""
        self.body_rotation = wp.zeros(body_count, dtype=wp.types.matrix((3, 3), scalar), device=device)
        """Rotation body -> world of each body at the state's time [-], shape (body_count,) of 3x3."""
        self.body_velocity = wp.zeros(body_count, dtype=vec_hi, device=device)
        """Velocity of each hub, world [m/s], shape (body_count,)."""
        self.body_angular_velocity = wp.zeros(body_count, dtype=vec_hi, device=device)
        """Angular velocity of each body, world [rad/s], shape (body_count,)."""
        self.body_posed = wp.zeros(body_count, dtype=wp.int32, device=device)
        """1 once a body has been posed, else 0 [-], shape (body_count,), int32: a body not yet posed
        touches nothing (its placeholder pose, the origin, may lie inside the grains)."""
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
        """Number of particles touching each boundary [-], shape (boundary_count,)."""
        self.list_index = wp.zeros(1, dtype=wp.int32, device=device)
        """Which of the layout's two neighbour lists the pair history is aligned with [-], shape (1,), int32."""
        self.time = 0.0
        """Simulated time [s] (a Python float, i.e. double precision)."""
        self.forces_valid = False
        """True when force/torque/history belong to the positions (after a step or a restore)."""

    @classmethod
    def for_model(cls, model, capacity: int, rigid_capacity: int = 4, layout: GrainLayout | None = None) -> SoilState:
        """A zero state sized for `model` (particles, bodies, boundaries) with `capacity` neighbour
        slots and `rigid_capacity` rigid-contact slots per grain; a new layout unless one is given."""
        layout = layout or GrainLayout(model, capacity)
        return cls(
            model.particle_count,
            layout.capacity,
            model.precision.vec_hi,
            model.device,
            model.body_count,
            model.boundary_count,
            rigid_capacity=rigid_capacity,
            friction=model.law.friction,
            rolling=model.law.rolling,
            twisting=model.law.twisting,
            layout=layout,
            vec_mid=model.precision.vec_mid,
            slot_major=bool(getattr(model, "slot_major", False)),
            worlds=model.world_count,
        )

    @property
    def boundary_count(self) -> int:
        return int(self.boundary_force.shape[0])

    @property
    def capacity(self) -> int:
        """Neighbour-list slots per grain [-]."""
        return self._pair_capacity

    @property
    def rigid_capacity(self) -> int:
        """Rigid-contact slots per grain [-]."""
        return int(self.rigid_key.shape[0 if self.slot_major else 1])

    @property
    def arrays(self) -> dict[str, wp.array]:
        """The state's physical arrays by name, in storage order (the list index and the layout excluded)."""
        return {
            name: value for name, value in vars(self).items() if isinstance(value, wp.array) and name != "list_index"
        }

    def bytes_per_grain(self) -> float:
        """Device memory of this buffer per grain [B] (the shared layout not included)."""
        n = max(int(self.position.shape[0]), 1)
        return sum(a.capacity for a in self.arrays.values()) / n

    # -- copies and growth -------------------------------------------------------------
    BODY_MOTION = ("body_position", "body_rotation", "body_velocity", "body_angular_velocity", "body_posed")
    """The arrays of the bodies' pose and velocity (set by the control, carried from step to step)."""

    def copy_bodies(self, other: SoilState) -> None:
        """Take the bodies' pose, velocity and posed flags from `other` (device to device; capturable):
        a step carries them to its output state, where a path may then move them."""
        for name in self.BODY_MOTION:
            wp.copy(getattr(self, name), getattr(other, name))

    def assign(self, other: SoilState) -> None:
        """Copy every array, the list index and the time from `other`; arrays are reshaped to
        other's (e.g. after its storage grew). A state with its own layout gets a copy of other's."""
        for name, array in other.arrays.items():
            target = _resize_like(getattr(self, name, None), array)
            wp.copy(target, array)
            setattr(self, name, target)
        wp.copy(self.list_index, other.list_index)
        self._pair_capacity = other._pair_capacity
        self.slot_major = other.slot_major
        if other.layout is not None and self.layout is not other.layout:
            if self.layout is None:
                self.layout = GrainLayout.__new__(GrainLayout)
            self.layout.assign(other.layout)
        self.time = other.time
        self.forces_valid = other.forces_valid

    def copy_worlds(self, other: SoilState, worlds: wp.array, model) -> None:
        """Take from `other` (a state of the same shape) the rows of the worlds flagged in `worlds`
        (int32 (model.world_count,), soil.worlds) of every array but the pair history (PAIR_HISTORY,
        which NeighbourList.remap_worlds carries over: the lists may differ). On the device; capturable."""
        n, count = model.particle_count, model.world_count
        for name, array in self.arrays.items():
            if name in PAIR_HISTORY or array.size == 0:
                continue
            if name == "step_previous":
                rows, per_world, inner = count, 1, 1
            elif name.startswith("body_"):
                rows, per_world, inner = model.body_count, model.bodies_per_world, 1
            elif name.startswith("boundary_"):
                rows, per_world, inner = model.boundary_count, model.walls_per_world, 1
            else:  # one row per grain; a per-grain 2D array (n, slots) keeps a row's slots together
                rows, per_world = n, model.world_size
                inner = array.shape[1] if array.ndim == 2 and not self.slot_major else 1
            words = _word_view(array)
            wp.launch(
                copy_world_words,
                dim=words.shape[0],
                inputs=[
                    _word_view(getattr(other, name)),
                    words.shape[0] // array.size,
                    inner,
                    rows,
                    per_world,
                    worlds,
                ],
                outputs=[words],
                device=array.device,
            )

    def grow_capacity(self, capacity: int | None = None, rigid_capacity: int | None = None) -> None:
        """Widen the neighbour slots to `capacity` and the rigid-contact slots to `rigid_capacity`
        per grain, keeping the history (and the layout's lists)."""
        if capacity is not None and capacity > self._pair_capacity:
            self._widen("pair_touching", _words(capacity), 0)
            for name in ("pair_tangential", "pair_rolling"):
                if self._slots(name):
                    self._widen(name, capacity, 0)
            self._pair_capacity = int(capacity)
        if capacity is not None and self.layout is not None:
            self.layout.grow(capacity)
        if rigid_capacity is not None and rigid_capacity > self.rigid_capacity:
            self._widen("rigid_key", rigid_capacity, -1)
            for name in ("rigid_tangential", "rigid_rolling"):
                if self._slots(name):
                    self._widen(name, rigid_capacity, 0)

    def _slots(self, name: str) -> int:
        """Width of a per-grain history array [slots] (0: history the law does not keep)."""
        return int(getattr(self, name).shape[0 if self.slot_major else 1])

    def _widen(self, name: str, width: int, fill) -> None:
        array = getattr(self, name)
        values = _grain_major(array.numpy(), self.slot_major)
        wider = np.full((values.shape[0], width) + values.shape[2:], fill, dtype=values.dtype)
        wider[:, : values.shape[1]] = values
        stored = _grain_major(wider, self.slot_major)  # the same swap stores it back
        setattr(self, name, wp.array(np.ascontiguousarray(stored), dtype=array.dtype, device=array.device))

    # -- model order -------------------------------------------------------------------
    def to_numpy(self) -> dict[str, np.ndarray]:
        """Every array as a numpy copy in model order, and the time.

        Per-grain rows are in model order; the neighbour list of the state (`neighbours`
        [-] (n, capacity), model indices, -1 past `neighbour_count`; `build_position` [m]
        (n, 3)) is given with it, since the pair history is aligned with its rows.
        """
        layout = self.layout
        assert layout is not None, "a state read in model order needs its layout"
        order = layout.order.numpy()
        data = {}
        for name, array in self.arrays.items():
            values = array.numpy()
            if per_grain(name):
                if array.ndim == 2:
                    values = _grain_major(values, self.slot_major)
                model_order = np.empty_like(values)
                model_order[order] = values
                values = model_order
            data[name] = values.copy()  # on the CPU .numpy() is a view that later steps overwrite
        which = int(self.list_index.numpy()[0])
        neighbours = _grain_major(layout.neighbours.numpy()[which], layout.slot_major)
        counts = layout.neighbour_count.numpy()[which]
        used = np.arange(neighbours.shape[1])[None, :] < counts[:, None]
        ids = np.where(used, order[np.clip(neighbours, 0, len(order) - 1)], -1).astype(np.int32)
        for name, values in (
            ("neighbours", ids),
            ("neighbour_count", counts),
            ("build_position", layout.build_position.numpy()[which]),
        ):
            model_order = np.empty_like(values)
            model_order[order] = values
            data[name] = model_order
        data["time"] = np.float64(self.time)
        return data

    def load_numpy(self, data: dict) -> None:
        """Fill this state from `to_numpy()` output (model order; storage may be grown).

        The neighbour list goes into the layout's first list. Data written before the
        neighbour list existed (a `contact_partner` array of keyed history slots) is
        converted: its contacts keep their history, and the list is rebuilt at the first step.
        Boundary arrays missing from `data` are zero: the boundaries are at their initial
        geometry, at rest.
        """
        data = current_format(data, len(self.position))
        layout = self.layout
        assert layout is not None, "a state filled in model order needs its layout"
        order = layout.order.numpy()
        slot = layout.slot.numpy()
        neighbours = np.asarray(data["neighbours"])
        self.grow_capacity(neighbours.shape[1], np.asarray(data["rigid_key"]).shape[1])
        for name, array in self.arrays.items():
            if name not in data:
                if name.startswith(("boundary_", "body_")):  # bodies: posed by the control before a step
                    array.zero_()
                    continue
                raise SoilInputError(f"the saved state has no {name!r} array (state/{name})")
            values = np.asarray(data[name])
            rows = (len(order),) if per_grain(name) else tuple(array.shape[:1])
            if values.shape[:1] != rows:
                raise SoilInputError(
                    f"state.{name}: saved shape {values.shape} does not fit {array.shape} (a different scene?)"
                )
            if per_grain(name):
                values = values[order]
                width = self._slots(name) if array.ndim >= 2 else 0
                if array.ndim >= 2 and values.shape[1] != width:
                    values = _fit_width(values, width, -1 if name == "rigid_key" else 0)
                components = getattr(array.dtype, "_length_", 0)  # of a Warp vector type
                if name in SPIN_HISTORY and values.shape[2:] != (components,):
                    values = _fit_components(values, components)
                if array.ndim == 2:
                    values = np.ascontiguousarray(_grain_major(values, self.slot_major))
            array.assign(values.astype(array.numpy().dtype, copy=False))
        rows = neighbours[order]
        slots = np.where(rows >= 0, slot[np.maximum(rows, 0)], -1).astype(np.int32)
        lists = layout.neighbours.numpy()
        lists[0] = _grain_major(_fit_width(slots, layout.capacity, -1), layout.slot_major)
        layout.neighbours.assign(lists)
        counts = layout.neighbour_count.numpy()
        counts[0] = np.asarray(data["neighbour_count"])[order]
        layout.neighbour_count.assign(counts)
        built = layout.build_position.numpy()
        built[0] = np.asarray(data["build_position"])[order]
        layout.build_position.assign(built.astype(built.dtype))
        self.list_index.zero_()
        self.time = float(data["time"])
        self.forces_valid = True  # a saved state carries the forces of its own step


def storage_functions(module: str, slot_major: bool) -> SimpleNamespace:
    """The kernels' access to per-grain entries (neighbour-list rows, contact history) in either storage
    order, compiled into the Warp module `module` of the kernels that use them:

    entry(rows, t, i, k) / set_entry(rows, t, i, k, value): entry k of grain i in list t of a layout's
    neighbours; at(a, i, k) / put(a, i, k, value): slot k of grain i of a history array; list_capacity(rows),
    slots(a): the entries per grain. Grain-major arrays are indexed [.., i, k], slot-major ones [.., k, i]."""
    SLOT = bool(slot_major)

    @wp.func(module=module)
    def entry(rows: wp.array3d(dtype=wp.int32), t: int, i: int, k: int):
        if wp.static(SLOT):
            return rows[t, k, i]
        return rows[t, i, k]

    @wp.func(module=module)
    def set_entry(rows: wp.array3d(dtype=wp.int32), t: int, i: int, k: int, value: int):
        if wp.static(SLOT):
            rows[t, k, i] = value
        else:
            rows[t, i, k] = value

    @wp.func(module=module)
    def list_capacity(rows: wp.array3d(dtype=wp.int32)):
        if wp.static(SLOT):
            return rows.shape[1]
        return rows.shape[2]

    @wp.func(module=module)
    def at(a: wp.array2d(dtype=Any), i: int, k: int):
        if wp.static(SLOT):
            return a[k, i]
        return a[i, k]

    @wp.func(module=module)
    def put(a: wp.array2d(dtype=Any), i: int, k: int, value: Any):
        if wp.static(SLOT):
            a[k, i] = value
        else:
            a[i, k] = value

    @wp.func(module=module)
    def slots(a: wp.array2d(dtype=Any)):
        if wp.static(SLOT):
            return a.shape[0]
        return a.shape[1]

    return SimpleNamespace(entry=entry, set_entry=set_entry, list_capacity=list_capacity, at=at, put=put, slots=slots)


def per_grain(name: str) -> bool:
    """Whether a state array (or to_numpy() entry) has one row per grain."""
    return not (name.startswith(("boundary_", "body_")) or name in ("step_previous", "time"))


def current_format(data: dict, particle_count: int) -> dict:
    """State data (to_numpy() layout, model order) from data of any version: keyed history
    slots (`contact_partner`, written before the neighbour list existed) are converted."""
    data = dict(data)
    if "contact_partner" in data:
        data = _from_keyed_history(data, particle_count)
    return data


def _grain_major(values: np.ndarray, slot_major: bool) -> np.ndarray:
    """A per-grain history array as rows per grain (its first two axes swapped when stored slot-major;
    the same swap stores rows per grain slot-major)."""
    return np.swapaxes(values, 0, 1) if slot_major else values


def _words(capacity: int) -> int:
    return max(1, (int(capacity) + 31) // 32)


def _fit_width(values: np.ndarray, width: int, fill) -> np.ndarray:
    """values with axis 1 cut or padded (with fill) to `width`."""
    out = np.full((values.shape[0], width) + values.shape[2:], fill, dtype=values.dtype)
    keep = min(width, values.shape[1])
    out[:, :keep] = values[:, :keep]
    return out


SPIN_HISTORY = ("pair_rolling", "rigid_rolling")
"""State arrays of spin history: 3 components (rolling), 4 with twisting (docs/physics.md section 1)."""


def _fit_components(values: np.ndarray, components: int) -> np.ndarray:
    """Spin history of another contact law (with or without the twist angle) cut or padded with
    zeros to `components`: a contact loaded into a law with twisting starts untwisted."""
    out = np.zeros(values.shape[:2] + (components,), dtype=values.dtype)
    keep = min(components, values.shape[2] if values.ndim == 3 else 0)
    out[..., :keep] = values[..., :keep]
    return out


def _from_keyed_history(data: dict, n: int) -> dict:
    """Convert state data with keyed history slots (`contact_partner`: a particle index, or
    particle_count + boundary index) to neighbour rows and rigid slots, model order."""
    partner = np.asarray(data.pop("contact_partner"))
    tangential = np.asarray(data.pop("contact_tangential"))
    rolling = np.asarray(data.pop("contact_rolling"))
    used = np.asarray(data.pop("contact_count"))
    slots = partner.shape[1]
    is_pair = (partner >= 0) & (partner < n) & (np.arange(slots)[None, :] < used[:, None])
    is_rigid = (partner >= n) & (np.arange(slots)[None, :] < used[:, None])
    width = max(int(is_pair.sum(axis=1).max(initial=0)), 1)
    rigid_width = max(int(is_rigid.sum(axis=1).max(initial=0)), 4)
    neighbours = np.full((n, width), -1, dtype=np.int32)
    pair_t = np.zeros((n, width, 3), dtype=tangential.dtype)
    pair_r = np.zeros((n, width) + rolling.shape[2:], dtype=rolling.dtype)
    touching = np.zeros((n, _words(width)), dtype=np.uint32)
    rigid_key = np.full((n, rigid_width), -1, dtype=np.int32)
    rigid_t = np.zeros((n, rigid_width, 3), dtype=tangential.dtype)
    rigid_r = np.zeros((n, rigid_width) + rolling.shape[2:], dtype=rolling.dtype)
    counts = np.zeros(n, dtype=np.int32)
    rigid_counts = np.zeros(n, dtype=np.int32)
    for i in np.flatnonzero(is_pair.any(axis=1) | is_rigid.any(axis=1)):
        k = r = 0
        for s in range(int(used[i])):
            if is_pair[i, s]:
                neighbours[i, k], pair_t[i, k], pair_r[i, k] = partner[i, s], tangential[i, s], rolling[i, s]
                touching[i, k // 32] |= np.uint32(1 << (k % 32))
                k += 1
            elif is_rigid[i, s]:
                rigid_key[i, r], rigid_t[i, r], rigid_r[i, r] = partner[i, s] - n, tangential[i, s], rolling[i, s]
                r += 1
        counts[i], rigid_counts[i] = k, r
    data.update(
        neighbours=neighbours,
        neighbour_count=counts,
        pair_touching=touching,
        pair_tangential=pair_t,
        pair_rolling=pair_r,
        rigid_key=rigid_key,
        rigid_count=rigid_counts,
        rigid_tangential=rigid_t,
        rigid_rolling=rigid_r,
        contact_count=used.astype(np.int32),
        build_position=np.full((n, 3), UNBUILT),
    )
    return data
