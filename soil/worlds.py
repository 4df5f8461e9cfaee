"""Worlds: K copies of one soil scene stepped by the same launches, each exactly as it runs alone.

    worlds = open_bed_worlds(bed, wheels, order_seeds=range(20), device="cuda:0")
    worlds = open_bed_worlds([bed_0, bed_1], wheels, order_seeds=[0, 1])   # a bed each (replicas over beds)
    sim = worlds.world(3)           # world 3 as a Simulation-like object (what cosim.dem_soil.DemSoil drives)

Replicas of a small scene leave most of a GPU idle; K of them in one simulation fill it. The worlds
are copies of one scene's shape (grain, wall and wheel counts, materials, gravity, precision); their
grains may differ (beds settled from other seeds). World w
holds grains w * n .. (w + 1) * n - 1 (model order), and its walls and wheels likewise
(SoilModel.world_count). A grain's neighbour search covers only its world's cells (the world's
bits above the Morton code of the sort key, soil.neighbours), its rigid partners are its world's
walls and wheels, and a world's wheel wrenches are summed over chunks that start at the world's
first grain (soil.solver). Every sum a world sees is then the sum it sees alone: the rows are in
model-index order and entries out of contact add nothing, so a list rebuilt when another world
needed it holds the same contacts in the same order, and storage grown for one world changes no
value of another. Each world steps bit for bit as its scene alone (tests/test_worlds.py).

Shared by the worlds: the clock (each macro step), storage growth and the divergence monitor (a
world that diverges stops them all). The DEM step is the same for all at fixed steps; under the PID
step control (Simulation.enable_step_control on the worlds' simulation) each world has its own
controller and takes its own substeps, those it takes alone (soil.step_control).

Stepping: each world asks for its macro step (World.advance_to) with its wheels' path; the step
runs once every active world has asked, and a world that is done leaves (Worlds.leave; its wheels
then hold still). The worlds may be driven from one thread each (advance_to: the requests meet in
a condition variable and every access to the shared simulation holds `Worlds.lock`) or served by
one loop that answers them (submit, take, view: cosim.batch, each run in a process of its own).
"""

from __future__ import annotations

import math
import numbers
import os
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace

import numpy as np
import warp as wp

from .control import SoilControl, checked_body_path
from .errors import ArgumentError, DamagedFileError, SoilInputError, is_real
from .macro import MacroStepReport
from .model import SoilModel
from .stability import SimulationDiverged
from .state import UNBUILT, SoilState, per_grain

_PER_GRAIN_MODEL = ("radius", "mass", "inv_mass", "inv_inertia", "material")
_PER_BODY_MODEL = ("body_kind", "body_shape", "body_mesh", "body_material")
_PER_WALL_MODEL = ("boundary_kind", "boundary_geometry", "boundary_material")


def join_worlds(parts: Sequence[tuple[SoilModel, SoilState, SoilControl]]):
    """One (model, state, control) holding the worlds `parts` (each a finalized scene of one world,
    all of the same shape: grain, wall and wheel counts, materials, gravity, precision, law, device)
    side by side. Their grains, walls' places and wheels may differ: each world keeps its own."""
    if not parts:
        raise ArgumentError("join_worlds needs at least one world")
    models = [p[0] for p in parts]
    first = models[0]
    count = len(parts)
    for w, m in enumerate(models):
        shape = (m.particle_count, m.boundary_count, m.body_count, m.precision.name, m.slot_major, m.law, m.device)
        expected = (
            first.particle_count,
            first.boundary_count,
            first.body_count,
            first.precision.name,
            first.slot_major,
        )
        if shape[:5] != expected or m.law != first.law or m.device != first.device or m.world_count != 1:
            raise SoilInputError(
                f"world {w} differs from world 0 (grains, walls, wheels, precision, storage, law, device: {shape} vs "
                f"{expected + (first.law, first.device)}): the worlds of a batch are copies of one scene"
            )
        # one pair table and one gravity serve every world
        if m.materials != first.materials or not np.array_equal(m.gravity, first.gravity):
            raise SoilInputError(
                f"world {w} differs from world 0 in its materials or gravity: "
                "the worlds of a batch are copies of one scene"
            )
    n, walls, bodies = first.particle_count, first.boundary_count, first.body_count
    device, prec = first.device, first.precision

    def values(m: SoilModel, name: str) -> np.ndarray:
        array = getattr(m, name)
        assert array is not None, f"a finalized model has its {name}"
        return array.numpy()

    def joined(name: str) -> wp.array:
        return wp.array(
            np.concatenate([values(m, name) for m in models]), dtype=getattr(first, name).dtype, device=device
        )

    def offsets(name: str, counts: str) -> wp.array:
        starts = np.cumsum([0] + [len(values(m, counts)) for m in models])
        rows = [values(m, name) + starts[w] for w, m in enumerate(models)]
        return wp.array(np.concatenate(rows).astype(np.int32), dtype=wp.int32, device=device)

    reports = np.concatenate([m.boundary_reports for m in models])
    model = SoilModel(
        device=device,
        precision=prec,
        law=first.law,
        materials=first.materials,
        gravity=first.gravity.copy(),
        particle_count=count * n,
        **{name: joined(name) for name in _PER_GRAIN_MODEL + _PER_WALL_MODEL},
        pair=first.pair,
        boundary_column=wp.array(
            np.where(reports, np.cumsum(reports) - 1, -1).astype(np.int32), dtype=wp.int32, device=device
        ),
        max_radius=max(m.max_radius for m in models),
        particle_order=np.concatenate(
            [(m.particle_order if m.particle_order is not None else np.arange(n)) + w * n for w, m in enumerate(models)]
        ),
        bodies=[shape for m in models for shape in m.bodies],
        **{name: joined(name) for name in _PER_BODY_MODEL if bodies},
        mesh_points=joined("mesh_points"),
        mesh_indices=joined("mesh_indices"),
        body_point_offset=offsets("body_point_offset", "mesh_points"),
        body_index_offset=offsets("body_index_offset", "mesh_indices"),
        meshes=[mesh for m in models for mesh in m.meshes],
        slot_major=first.slot_major,
        world_count=count,
    )
    capacity = max(p[1].capacity for p in parts)
    rigid_capacity = max(p[1].rigid_capacity for p in parts)
    datas = []
    for _, s, _ in parts:
        s.grow_capacity(capacity, rigid_capacity)
        datas.append(s.to_numpy())
    state_data = {}
    for name, first_values in datas[0].items():
        if name == "time":
            state_data[name] = first_values
            continue
        rows = []
        for w, data in enumerate(datas):
            v = np.asarray(data[name])
            if name == "neighbours":
                v = np.where(v >= 0, v + w * n, -1).astype(np.int32)
            elif name == "rigid_key":
                v = _rigid_keys_to_batch(v, w, walls, bodies, count)
            elif name == "build_position" and models[w].max_radius < model.max_radius:
                # its list was built with its own skin (0.3 x its largest grain), narrower than the one the
                # batch's rebuild test assumes: built again at the first step (its history carried over)
                v = np.full_like(v, UNBUILT)
            rows.append(v)
        state_data[name] = np.concatenate(rows)
    state = SoilState.for_model(model, capacity, rigid_capacity)
    state.load_numpy(state_data)
    state.forces_valid = all(p[1].forces_valid for p in parts)
    control = SoilControl.for_model(model)
    controls = [p[2].state_dict() for p in parts]
    control.load_state_dict(
        {
            name: np.concatenate([c[name] for c in controls])
            if np.ndim(values)
            else np.any([c[name] for c in controls])
            for name, values in controls[0].items()
        }
    )
    return model, state, control


def _rigid_keys_to_batch(keys: np.ndarray, world: int, walls: int, bodies: int, count: int) -> np.ndarray:
    """A world's rigid partner keys (wall b, or walls + wheel) as keys of the batch."""
    out = np.where(keys < walls, keys + world * walls, keys - walls + count * walls + world * bodies)
    return np.where(keys >= 0, out, -1).astype(np.int32)


def _rigid_keys_to_world(keys: np.ndarray, world: int, walls: int, bodies: int, count: int) -> np.ndarray:
    """The batch's rigid partner keys of world `world`'s grains as that world's own keys."""
    total_walls = count * walls
    out = np.where(keys < total_walls, keys - world * walls, keys - total_walls - world * bodies + walls)
    return np.where(keys >= 0, out, -1).astype(np.int32)


def world_state_dict(data: dict, world: int, model: SoilModel) -> dict:
    """World `world`'s part of a batch's Simulation.state_dict() (or a monitor's last good state), in
    the format of its scene alone: a solo Simulation of the same scene and order seed loads it and
    continues bit for bit (the divergence monitor's bounds are the batch's)."""
    n, walls, bodies, count = model.world_size, model.walls_per_world, model.bodies_per_world, model.world_count
    grains = slice(world * n, (world + 1) * n)
    wall_rows = slice(world * walls, (world + 1) * walls)
    body_rows = slice(world * bodies, (world + 1) * bodies)
    out = {}
    for key, value in data.items():
        part, _, name = key.partition("/")
        if key == "step_control/device" and np.ndim(value) == 2:  # the worlds' controllers: a row each
            out[key] = np.asarray(value)[world].copy()
            continue
        if part not in ("state", "control") or not name:
            out[key] = value
            continue
        v = np.asarray(value)
        if name == "step_previous":
            v = v[world : world + 1]
        elif name.startswith("body_"):
            v = v[body_rows]
        elif name.startswith("boundary_"):
            v = v[wall_rows]
        elif part == "control" and name == "external_force":
            v = v[grains]
        elif part == "state" and per_grain(name) and v.ndim and v.shape[0] == model.particle_count:
            v = v[grains]
            if name == "neighbours":
                v = np.where(v >= 0, v - world * n, -1).astype(np.int32)
            elif name == "rigid_key":
                v = _rigid_keys_to_world(v, world, walls, bodies, count)
        out[key] = v
    return out


def open_bed_worlds(
    bed,
    wheels=(),
    order_seeds: Iterable[int | None] = (None,),
    *,
    device: str | None = None,
    precision="double",
    law=None,
    integrator=None,
    gravity=None,
    storage: str = "grain",
) -> Worlds:
    """Worlds of settled beds (soil.bed.open_bed's arguments), one per order seed: world w is the
    simulation open_bed(beds[w], ..., order_seed=order_seeds[w]) gives. `bed`: one bed (a path or a
    SavedBed) for every world, or a sequence of them, one per order seed (beds of one shape: the same
    grain count, walls and materials, as beds of one scene settled from other seeds are)."""
    from .bed import SavedBed, read_bed, wheel_pairs
    from .simulation import Simulation

    pairs = wheel_pairs(wheels)  # checked once, a generator read once: every world gets them
    seeds = list(order_seeds)
    beds = list(bed) if isinstance(bed, (list, tuple)) else [bed] * len(seeds)
    if len(beds) != len(seeds):
        raise ArgumentError(f"open_bed_worlds: {len(beds)} beds for {len(seeds)} order seeds (one bed per world)")
    read: dict[str, SavedBed] = {}  # a bed file given for several worlds is read once
    parts = []
    for k, (one, seed) in enumerate(zip(beds, seeds)):
        if not isinstance(one, SavedBed):
            path = _bed_path(one, k)
            if path not in read:
                try:
                    read[path] = read_bed(path)
                except DamagedFileError:
                    raise
                except OSError as error:  # missing, a folder: named, as the project's error
                    raise SoilInputError(
                        f"open_bed_worlds: world {k}'s bed {path!r} cannot be read ({error}); a bed is a bed file "
                        "(soil.bed.save_bed, a run's bed.h5) or a SavedBed"
                    ) from None
            one = read[path]
        builder = one.builder(gravity)
        for shape, material in pairs:
            builder.add_wheel(shape, material)
        parts.append(builder.finalize(device=device, precision=precision, law=law, order_seed=seed, storage=storage))
    model, state, control = join_worlds(parts)
    return Worlds(Simulation(model, state, control, integrator=integrator))


def _bed_path(bed, world: int) -> str:
    """A bed given by its path, as a str; SoilInputError naming the world when it is no path."""
    try:
        return os.fspath(bed)
    except TypeError:
        raise SoilInputError(
            f"open_bed_worlds: world {world}'s bed is {type(bed).__name__} {bed!r}: a bed is a bed file's path "
            "(soil.bed.save_bed, a run's bed.h5) or a SavedBed"
        ) from None


class Worlds:
    """The worlds of one Simulation (its model's world_count), stepped together (module docstring)."""

    def __init__(self, sim):
        self.sim = sim
        self.model: SoilModel = sim.model
        self.count = self.model.world_count
        self.lock = threading.RLock()
        """Held by every access to the shared simulation."""
        self._changed = threading.Condition(self.lock)
        self.active = set(range(self.count))
        """The worlds that still step (a world leaves when its run is done)."""
        self._requests: dict[int, tuple] = {}
        self._reports: dict[int, MacroStepReport] = {}
        self._round = 0
        self._failure: BaseException | None = None
        self._refresh = False
        self.rounds = 0
        """Macro steps taken together [-]."""
        self.round_ends: list[float] = []
        """Host clock (time.perf_counter) [s] at the end of each of those macro steps."""
        self.round_steps: list[float] = []
        """Host clock spent in each of them [s] (as step_seconds)."""
        self._last_step_seconds = 0.0
        self._checked = -1  # the round the divergence monitor last checked
        self._view_round = -1  # the round whose walls `view` read
        self._view: tuple = ()
        counters = ("steps", "accepted_steps", "rejected_steps", "forced_steps")
        self._own_steps = np.tile([getattr(sim, name) for name in counters], (self.count, 1)).astype(np.int64)
        """Each world's own step counters (Simulation's steps, accepted, rejected, forced), shape (worlds, 4):
        under the PID step control each world takes its own substeps (World.state_dict gives them)."""
        self.step_seconds = 0.0
        """Host clock spent in those macro steps [s] (each ends with its report's read: the device's time);
        the rest of a batch's wall is the worlds' own host work (rovers, records, writers)."""

    def world(self, index: int) -> World:
        return World(self, self._index(index))

    def _index(self, world) -> int:
        """A world's index as an int; ArgumentError naming it and the range allowed unless it is one."""
        if isinstance(world, bool) or not isinstance(world, numbers.Integral) or not 0 <= int(world) < self.count:
            raise ArgumentError(
                f"world index must be an integer in 0 .. {self.count - 1} (the batch has {self.count} worlds), "
                f"got {world!r}"
            )
        return int(world)

    def body_rows(self, world: int) -> slice:
        per = self.model.bodies_per_world
        return slice(world * per, (world + 1) * per)

    def wall_rows(self, world: int) -> slice:
        per = self.model.walls_per_world
        return slice(world * per, (world + 1) * per)

    def step_counts(self, world: int) -> dict:
        """World `world`'s own step counters in Simulation.state_dict's keys (steps, accepted_steps,
        rejected_steps, forced_steps) [-]: under the PID step control each world counts its own."""
        world = self._index(world)
        names = ("steps", "accepted_steps", "rejected_steps", "forced_steps")
        with self.lock:
            return {name: np.int64(value) for name, value in zip(names, self._own_steps[world])}

    def grain_rows(self, world: int) -> slice:
        n = self.model.world_size
        return slice(world * n, (world + 1) * n)

    # -- forces of new poses: once, when a world first needs them --------------------------
    def refresh_later(self) -> None:
        with self.lock:
            self._refresh = True
            self._view_round = -1

    def ensure_forces(self) -> None:
        """The forces of the bodies' poses as prescribed (a pending refresh_forces, done once for all worlds)."""
        with self.lock:
            if self._refresh:
                self._refresh = False
                self.sim.refresh_forces()

    def check_divergence(self, world: int) -> None:
        """The divergence monitor's full check of the whole batch, once per macro step whichever world asks
        first (it reads every grain); a divergence it finds reaches every world (with its own last good state)."""
        world = self._index(world)
        with self.lock:
            if self._failure is None and self._checked != self.rounds:
                self._checked = self.rounds
                try:
                    self.sim.check_divergence()
                except SimulationDiverged as error:
                    self._fail(error)
            if self._failure is not None:
                raise self._world_failure(world)

    # -- stepping together --------------------------------------------------------------
    def leave(self, world: int, park: bool = False) -> None:
        """World `world` steps no more: its wheels hold still; the others step without waiting for it.
        park: its wheels are first lifted clear of its grains, at rest (a world that leaves before its
        run placed them: where they were built they may lie inside its bed, whose grains, still stepped
        at fixed steps, would be thrown out by them and stop every world as a divergence)."""
        world = self._index(world)
        with self._changed:
            if park and world in self.active:
                self._park(world)
            self.active.discard(world)
            self._requests.pop(world, None)
            self._maybe_step()
            self._changed.notify_all()

    def _park(self, world: int) -> None:
        """World `world`'s wheels at rest above its grains (against gravity; +z without), each its own
        reach and a grain apart from them and from one another, out of contact (holding the lock)."""
        rows = self.body_rows(world)
        if rows.start == rows.stop:
            return
        x = self.sim.positions()[self.grain_rows(world)]
        x = x[np.isfinite(x).all(axis=1)]
        low, high = (x.min(axis=0), x.max(axis=0)) if len(x) else (np.zeros(3), np.zeros(3))
        g = np.asarray(self.model.gravity, dtype=np.float64)
        up = -g / np.linalg.norm(g) if np.linalg.norm(g) > 0 else np.array([0.0, 0.0, 1.0])
        side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
        side /= np.linalg.norm(side)
        shapes = self.model.body_shape
        assert shapes is not None, "a world with body rows has body shapes"
        reach = float(np.max(shapes.numpy()[rows, 5]))
        gap = 2.0 * reach + 4.0 * self.model.max_radius
        above = (low + high) / 2.0 + up * (float(np.linalg.norm(high - low)) + gap)
        for k, body in enumerate(range(rows.start, rows.stop)):
            self.sim.set_body_motion(body, above + side * k * gap, [1.0, 0.0, 0.0, 0.0], np.zeros(3), np.zeros(3))
        self.refresh_later()

    def advance_to(
        self,
        world: int,
        end_time: float,
        dt: float,
        path: bool,
        body_path: tuple | None,
        meanwhile: Callable[[], None] | None = None,
    ):
        """World `world`'s macro step to end_time [s] (its bodies along body_path: set_body_path's
        arguments for its bodies, or None); returns its part of the report once every active world
        has asked for the same step (the worlds' threads wait here for one another). meanwhile: the
        caller's own host work (Simulation.macro_step's), done after asking, without the lock."""
        self.submit(world, end_time, dt, path, body_path)
        try:
            if meanwhile is not None:
                meanwhile()
        finally:  # the report is taken whatever that work met: no stale report is left for the next step
            with self._changed:
                while (report := self.take(world)) is None:
                    self._changed.wait()
        return report

    def submit(self, world: int, end_time: float, dt: float, path: bool, body_path: tuple | None) -> None:
        """World `world` asks for its macro step (advance_to's arguments) without waiting: the step runs
        as soon as every active world has asked; `take` then gives its report."""
        world = self._index(world)
        with self._changed:
            if world not in self.active:
                raise ArgumentError(f"world {world} has left the batch")
            if self._failure is not None:
                raise self._world_failure(world)
            if world in self._requests or world in self._reports:  # it replaced the first, unsaid
                raise ArgumentError(
                    f"world {world} has asked for a macro step already: take its report before asking again"
                )
            # checked before it is asked: a refused request leaves the batch as it was (one that failed in
            # the step would stop every world)
            if not (is_real(dt) and math.isfinite(dt) and dt > 0):
                raise SoilInputError(f"world {world}'s macro step: dt must be finite and > 0 [s], got {dt!r}")
            if not (is_real(end_time) and math.isfinite(end_time) and end_time > self.sim.time):
                raise SoilInputError(
                    f"world {world}'s macro step: end_time must be a finite time after the soil's time "
                    f"{self.sim.time!r} s, got {end_time!r}"
                )
            if body_path is not None:
                body_path = self._checked_path(world, body_path)
            self._requests[world] = (float(end_time), float(dt), bool(path), body_path)
            self._maybe_step()

    def _checked_path(self, world: int, body_path) -> tuple:
        """A world's wheel path (set_body_path's position, orientation, velocity, angular velocity and end)
        as float arrays of its wheels' count (soil.control.checked_body_path); SoilInputError unless each
        holds finite numbers of the shape its wheels need."""
        what = f"world {world}'s wheel path"
        if not isinstance(body_path, (tuple, list)) or len(body_path) != 5:
            raise SoilInputError(
                f"{what} is (position, orientation, velocity, angular velocity, end), got {type(body_path).__name__}"
            )
        position, orientation, velocity, angular_velocity, end = body_path
        start, finish = checked_body_path(
            self.model.bodies_per_world, position, orientation, velocity, angular_velocity, end, what
        )
        return (*start, None if finish is None else tuple(finish))

    def take(self, world: int) -> MacroStepReport | None:
        """World `world`'s part of the report of the step it asked for (submit); None while other worlds
        have still to ask. Raises the batch's failure as this world sees it."""
        world = self._index(world)
        with self._changed:
            if world in self._reports:
                return self._reports.pop(world)
            if self._failure is not None:
                raise self._world_failure(world)
            if world not in self._requests:
                raise ArgumentError(f"world {world} has not asked for a macro step")
            return None

    def view(self, world: int) -> dict:
        """What world `world`'s run reads between its macro steps, read from the device once per step for
        all worlds: 'time' [s]; its wheels' 'body_positions' [m] (bodies, 3) and 'body_rotations' (bodies, 3,
        3) as posed; its walls' 'boundary_displacements' [m] (walls, 3) and 'boundary_wrenches' (force [N]
        (walls, 3), torque [N m] (walls, 3), contacts [-] (walls,)), as World's methods of those names give."""
        world = self._index(world)
        with self.lock:
            if self._view_round != self.rounds:
                self.ensure_forces()
                self._view = (self.sim.boundary_wrenches(), self.sim.boundary_displacements())
                self._view_round = self.rounds
            (force, torque, contacts), shift = self._view
            bodies, walls = self.body_rows(world), self.wall_rows(world)
            control = self.sim.control
            return {
                "time": self.sim.time,
                "body_positions": control.body_position_host[bodies].copy(),
                "body_rotations": control.body_rotation_host[bodies].copy(),
                "boundary_displacements": shift[walls],
                "boundary_wrenches": (force[walls], torque[walls], contacts[walls]),
            }

    def _world_failure(self, world: int) -> BaseException:
        """The batch's failure as world `world` sees it: a divergence carries that world's last good state."""
        failure = self._failure
        assert failure is not None
        if isinstance(failure, SimulationDiverged) and failure.last_good is not None:
            part = world_state_dict({f"state/{k}": v for k, v in failure.last_good.items()}, world, self.model)
            n = self.model.world_size
            where = (
                ""
                if failure.particle is None
                else f" (world {failure.particle // n}'s particle {failure.particle % n})"
            )
            return SimulationDiverged(  # a new one per world (a copy could share the batch's attributes)
                f"{failure} [a batch of {self.count} worlds{where}]",
                {k[len("state/") :]: v for k, v in part.items()},
                time=failure.time,
                step=failure.step,
                particle=failure.particle,
                position=failure.position,
                reason=failure.reason,
                checkpoint=failure.checkpoint,
                elsewhere=failure.particle is not None and failure.particle // n != world,
            )
        return failure

    def _maybe_step(self) -> None:
        """Step when every active world has asked (holding the lock); nothing steps after a failure."""
        if self._failure is not None or not self._requests or set(self._requests) != self.active:
            return
        requests, self._requests = self._requests, {}
        ends = {(r[0], r[1], r[2]) for r in requests.values()}
        if len(ends) != 1:
            self._fail(ArgumentError(f"the worlds asked for different macro steps (end, dt, path): {sorted(ends)}"))
            return
        end_time, dt, path = ends.pop()
        try:
            self._step(end_time, dt, path, requests)
        except BaseException as error:  # every waiting world gets it
            self._fail(error)
            return
        self._round += 1
        self.rounds += 1
        self.round_ends.append(time.perf_counter())
        self.round_steps.append(self._last_step_seconds)
        self._changed.notify_all()

    def _fail(self, error: BaseException) -> None:
        self._failure = error
        self._round += 1
        self._changed.notify_all()

    def _step(self, end_time: float, dt: float, path: bool, requests: dict) -> None:
        self.ensure_forces()  # a step starts from the forces of the poses as placed, as alone
        sim, control = self.sim, self.sim.control
        span = end_time - sim.time
        if path:
            paths = {w: r[3] for w, r in requests.items() if r[3] is not None}
            if len({body_path[4] is None for body_path in paths.values()}) > 1:
                raise ArgumentError("the worlds' wheel paths mix constant velocities and end poses in one macro step")
            towards = any(body_path[4] is not None for body_path in paths.values())
            # a world without a path (done) holds its wheels still where they are
            count = self.model.body_count
            start = [
                control.body_position_host.copy(),
                np.zeros((count, 4)),
                np.zeros((count, 3)),
                np.zeros((count, 3)),
            ]
            start[1][:, 0] = 1.0
            for w in range(self.count):
                if w not in paths:
                    for b in range(self.body_rows(w).start, self.body_rows(w).stop):
                        start[1][b] = _quaternion(control.body_rotation_host[b])
            end = [a.copy() for a in start]
            for w, body_path in paths.items():
                rows = self.body_rows(w)
                for column, values in zip(start, body_path[:4]):
                    column[rows] = values
                for column, values in zip(end, body_path[4] if towards else body_path[:4]):
                    column[rows] = values
            sim.set_body_path(span, *start, end=end if towards else None)
        if sim.step_control is not None:  # a world that left keeps its state (no span of its own)
            sim.step_control.set_stepping(requests)
        started = time.perf_counter()
        report = sim.advance_to(end_time, dt, path=path)
        self._last_step_seconds = time.perf_counter() - started
        self.step_seconds += self._last_step_seconds
        for w in requests:
            bodies, walls = self.body_rows(w), self.wall_rows(w)
            own = report.world_steps[w] if report.world_steps else {}  # the step control's figures of world w
            counted = own.get("steps", report.steps)
            self._own_steps[w] += (counted, counted if own else 0, own.get("rejected", 0), own.get("forced", 0))
            self._reports[w] = replace(
                report,
                **own,
                world_steps=(),
                body_force=report.body_force[bodies],
                body_torque=report.body_torque[bodies],
                body_force_end=report.body_force_end[bodies],
                body_torque_end=report.body_torque_end[bodies],
                body_work=report.body_work[bodies],
                body_contacts=report.body_contacts[bodies],
                boundary_displacement=report.boundary_displacement[walls],
            )


def _quaternion(rotation: np.ndarray) -> np.ndarray:
    """The unit quaternion (w, x, y, z) of a rotation matrix (3, 3)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(rotation).as_quat()
    return np.array([w, x, y, z])


class World:
    """One world of a Worlds batch with the Simulation interface a run layer uses (cosim.dem_soil.DemSoil):
    its grains, walls and wheels by their own indices, its state_dict in its scene's own format."""

    def __init__(self, worlds: Worlds, index: int):
        self.worlds = worlds
        self.index = index
        self._sim = worlds.sim
        self._grains = worlds.grain_rows(index)
        self._bodies = worlds.body_rows(index)
        self._walls = worlds.wall_rows(index)
        self._path: tuple | None = None
        self.monitor = self._sim.monitor
        """The batch's divergence monitor (shared)."""

    # -- what the world is ------------------------------------------------------------
    @property
    def time(self) -> float:
        return self._sim.time

    @property
    def gravity(self) -> np.ndarray:
        return self._sim.gravity

    @property
    def particle_count(self) -> int:
        return self.worlds.model.world_size

    @property
    def body_count(self) -> int:
        return self.worlds.model.bodies_per_world

    @property
    def boundary_count(self) -> int:
        return self.worlds.model.walls_per_world

    @property
    def body_shapes(self) -> list:
        return self._sim.body_shapes[self._bodies]

    def _read(self, method, rows):
        with self.worlds.lock:
            return method()[rows]

    def radii(self) -> np.ndarray:
        return self._read(self._sim.radii, self._grains)

    def masses(self) -> np.ndarray:
        return self._read(self._sim.masses, self._grains)

    def positions(self) -> np.ndarray:
        return self._read(self._sim.positions, self._grains)

    def velocities(self) -> np.ndarray:
        return self._read(self._sim.velocities, self._grains)

    # -- walls ---------------------------------------------------------------------------
    def boundary_kinds(self) -> np.ndarray:
        return self._sim.boundary_kinds()[self._walls]

    def boundary_reports(self) -> np.ndarray:
        return self._sim.boundary_reports()[self._walls]

    def initial_boundary_geometry(self) -> np.ndarray:
        return self._sim.initial_boundary_geometry()[self._walls]

    def boundary_displacements(self) -> np.ndarray:
        return self._read(self._sim.boundary_displacements, self._walls)

    def boundary_geometry(self, displacement=None) -> np.ndarray:
        with self.worlds.lock:
            shift = self._sim.boundary_displacements()
            if displacement is not None:
                shift[self._walls] = np.asarray(displacement, dtype=np.float64).reshape(-1, 3)
            return self._sim.boundary_geometry(shift)[self._walls]

    def boundary_wrenches(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        with self.worlds.lock:
            self.worlds.ensure_forces()
            return tuple(values[self._walls] for values in self._sim.boundary_wrenches())

    # -- wheels --------------------------------------------------------------------------
    def set_body_motion(self, body: int, *args, **kwargs) -> None:
        with self.worlds.lock:
            self._sim.set_body_motion(self._bodies.start + body, *args, **kwargs)

    def refresh_forces(self) -> None:
        """The forces of the new poses are computed once for all worlds, when first needed."""
        self.worlds.refresh_later()

    def set_body_path(self, span: float, position, orientation, velocity, angular_velocity, end=None) -> None:
        self._path = (position, orientation, velocity, angular_velocity, end)

    def advance_to(
        self, end_time: float, dt: float, path: bool = False, meanwhile: Callable[[], None] | None = None
    ) -> MacroStepReport:
        body_path, self._path = self._path, None
        return self.worlds.advance_to(self.index, end_time, dt, path, body_path, meanwhile)

    def leave(self) -> None:
        self.worlds.leave(self.index)

    def _control_rows(self, name: str) -> np.ndarray:
        with self.worlds.lock:
            return getattr(self._sim.control, name)[self._bodies].copy()

    def body_positions(self) -> np.ndarray:
        return self._control_rows("body_position_host")

    def body_rotations(self) -> np.ndarray:
        return self._control_rows("body_rotation_host")

    def body_wrenches(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        with self.worlds.lock:
            self.worlds.ensure_forces()
            return tuple(values[self._bodies] for values in self._sim.body_wrenches())

    # -- health and checkpoints ------------------------------------------------------------
    def arm_monitor(self) -> None:
        with self.worlds.lock:
            self.worlds.ensure_forces()
            if not self.monitor.armed:
                self._sim.arm_monitor()

    def check_divergence(self) -> None:
        self.worlds.check_divergence(self.index)

    def state_dict(self) -> dict:
        """This world's state in its scene's own format (world_state_dict), with its own step counters:
        `cosim resume` continues it alone."""
        with self.worlds.lock:
            self.worlds.ensure_forces()
            data = world_state_dict(self._sim.state_dict(), self.index, self.worlds.model)
            if self._sim.step_control is not None:
                data.update(self.worlds.step_counts(self.index))
            return data

    def state_dict_units(self) -> dict[str, str]:
        """{key of state_dict(): its unit}: a world's state has its scene's keys."""
        return self._sim.state_dict_units()

    def load_state_dict(self, data: dict) -> None:
        raise ArgumentError("a world of a batch is not loaded from a checkpoint: resume its run on its own")
