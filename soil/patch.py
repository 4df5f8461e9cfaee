"""A soil patch that follows the rover, so a traverse can be longer than any bed (docs/rover.md).

The soil is a lattice of copies of one settled tile: the scene's [bed], settled in its box and
saved, without the grains next to its side walls (`Tile.load`: the walls order the packing
near them), and without the few grains that would overlap a grain of the neighbouring copy.
The grains of the copy in cell (i, j) sit at the tile's grains shifted by (i a_x, j a_y) from
the lattice origin. Only the grains inside a window, an axis-aligned rectangle centred near
the rover's wheels, are simulated: the patch. A band of grains along the window's edge is frozen
(inverse mass 0), a rough wall that holds the soil in; the floor z = 0 is a plane.

When the wheels' centre has moved more than `recentre_distance` from the window's centre along x
or y, the window is moved onto it (`follow`, between two macro steps, on the host: no device read
inside a DEM step). Then

- grains whose centre is outside the new window are removed (behind the rover), and so are the
  strays that flew over the band into the part of the new window that was not simulated;
- the lattice's grains in that part are placed, with their settled velocities, spins and
  contact history, from the tile (ahead of the rover);
- the band is frozen again where the new window's edge is (grains there keep their place and
  lose their speed) and unfrozen elsewhere;
- the contact history is carried over: partners are renumbered, contacts with grains that left
  are dropped, a placed grain keeps its tile history with grains placed with it and with the
  floor;
- a new soil model and state are built (SoilBuilder.start_from: the state is in before anything
  can step) and the forces are recomputed at the current state (Simulation.refresh_forces).

Everything is numpy on the host in a fixed order, so a run with a moving patch repeats bit for
bit and continues bitwise from a checkpoint (`state_dict` holds the patch's grains and books).
The mass placed and removed is booked: mass now = initial mass + added - removed.

Limits: the seams of the lattice are cuts through a settled packing: a few grains are missing
there and the grains across a seam start without contact history; a grain thrown over the band
lands outside the window and
is removed at the next move; the band is at rest, not a moving soil (a rover must keep its
clearance from it).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from .bed import SavedBed, read_bed
from .builder import SoilBuilder
from .errors import SoilInputError
from .grains import append_grains, grain_rows, renumber_history, select_grains
from .sdf import BOUNDARY_PLANE
from .simulation import Simulation
from .state import UNBUILT


@dataclass
class Tile:
    """The settled tile: its grains in tile coordinates (0 <= x < size_x, 0 <= y < size_y), the
    constants and the state they were saved with."""

    size: np.ndarray
    """Tile size along x and y [m], shape (2,)."""
    state: dict
    """Per-grain state arrays (grain_rows), rows in tile order, neighbours by tile index."""
    radius: np.ndarray
    """Grain radii [m], shape (n,)."""
    material: np.ndarray
    """Material index per grain [-], shape (n,), int32."""
    mass: np.ndarray
    """Masses [kg], shape (n,)."""
    inv_mass: np.ndarray
    """Inverse masses of the free grains [1/kg], shape (n,)."""
    inv_inertia: np.ndarray
    """Inverse moments of inertia of the free grains [1/(kg m^2)], shape (n,)."""
    floor_key: int
    """Rigid-contact key of the tile's floor (its boundary index) [-]."""
    floor_material: int
    """Material index of the floor [-]."""
    materials: list
    """soil.Material by index."""
    overrides: dict
    """Pair overrides of the material table."""

    @property
    def count(self) -> int:
        return len(self.radius)

    @classmethod
    def load(cls, bed, size, precision: str, margin: float) -> Tile:
        """The tile cut from a settled bed (a soil.bed.SavedBed, or the path of its file: its floor the
        plane z = 0, its box spanning 0 .. size along x and y [m]): the grains whose centres lie more
        than `margin` [m] from its side walls, where the walls ordered the packing. The tile's period
        is size - 2 margin. A grain that would overlap a grain of a neighbouring copy deeper than any
        two grains of the tile overlap is left out (the later one in the bed's order), so the copies
        fit without a jolt."""
        from scipy.spatial import cKDTree

        saved = bed if isinstance(bed, SavedBed) else read_bed(bed)
        name = "the bed" if isinstance(bed, SavedBed) else os.fspath(bed)  # for the messages
        model, state, control = saved.builder().finalize(device="cpu", precision=precision)
        kinds = model.boundary_kind.numpy()
        geometry = model.boundary_geometry_numpy()
        floors = [
            b
            for b, (kind, row) in enumerate(zip(kinds, geometry))
            if kind == BOUNDARY_PLANE and np.allclose(row[3:], (0.0, 0.0, 1.0)) and abs(row[2]) < 1e-12
        ]
        if not floors:
            raise SoilInputError(f"{name}: the bed has no floor plane z = 0 to stand a patch on")
        data = state.to_numpy()
        x = data["position"].astype(np.float64)
        r = model.radius_numpy()
        period = np.asarray(size, dtype=np.float64) - 2.0 * margin
        if np.any(period <= 4.0 * r.max()):
            raise SoilInputError(
                f"{name}: the bed ({size[0]} x {size[1]} m) leaves no tile {2 * margin} m in from its walls"
            )
        keep = _inside(x[:, :2], np.full(2, margin), margin + period)
        tree = cKDTree(x[keep])
        inner = tree.query_pairs(2.0 * r.max(), output_type="ndarray")
        kept_index = np.flatnonzero(keep)
        rk = r[kept_index]
        if len(inner):
            gap = (
                np.linalg.norm(x[kept_index][inner[:, 0]] - x[kept_index][inner[:, 1]], axis=1)
                - rk[inner[:, 0]]
                - rk[inner[:, 1]]
            )
            allowed = max(0.0, -float(gap.min()))
        else:
            allowed = 0.0
        dropped = np.zeros(len(kept_index), dtype=bool)
        for ix in (-1, 0, 1):
            for iy in (-1, 0, 1):
                if ix == iy == 0:
                    continue
                shifted = x[kept_index] + np.array([ix * period[0], iy * period[1], 0.0])
                for i, neighbours in enumerate(tree.query_ball_point(shifted, 2.0 * r.max())):
                    for j in neighbours:
                        if dropped[i] or dropped[j]:
                            continue
                        overlap = rk[i] + rk[j] - float(np.linalg.norm(shifted[i] - x[kept_index][j]))
                        if overlap > allowed:
                            dropped[max(i, j)] = True
        rows = kept_index[~dropped]
        grains = select_grains(grain_rows(data), rows)
        grains["position"][:, :2] -= margin
        return cls(
            size=period,
            state=grains,
            radius=model.radius.numpy()[rows],
            material=model.material.numpy()[rows],
            mass=model.mass.numpy()[rows],
            inv_mass=model.inv_mass.numpy()[rows],
            inv_inertia=model.inv_inertia.numpy()[rows],
            floor_key=floors[0],
            floor_material=int(model.boundary_material.numpy()[floors[0]]),
            materials=list(model.materials.materials),
            overrides=dict(model.materials.overrides),
        )


def _inside(xy: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Points [m], shape (n, 2), in the half-open box low <= p < high."""
    return np.all((xy >= low) & (xy < high), axis=1)


class SoilPatch:
    """The moving window of soil (module docstring). Build the first soil with `start`, then call
    `follow` before every macro step; a move returns a new Simulation.

    Args:
        tile: the settled tile.
        length, width: window size along x and y [m].
        band: width of the frozen band at the window's edge [m].
        recentre_distance: the window moves when the wheels' centre is farther than this from its
            centre along x or y [m].
        wheels: (shape, soil.Material) of every wheel body, in wheel order.
        gravity: [m/s^2], shape (3,).
        device, precision, law: as SoilBuilder.finalize.
        order_seed: permute the grains placed at each move (summation order, for replicas).
    """

    def __init__(
        self,
        tile: Tile,
        length: float,
        width: float,
        band: float,
        recentre_distance: float,
        wheels,
        gravity,
        device: str,
        precision: str,
        law,
        order_seed: int | None = None,
    ):
        self.tile = tile
        self.half = 0.5 * np.array([length, width], dtype=np.float64)
        """Half the window's size along x, y [m], shape (2,)."""
        self.band = float(band)
        """Frozen band width [m]."""
        self.recentre_distance = float(recentre_distance)
        """[m]"""
        self.wheels = list(wheels)
        self.gravity = np.asarray(gravity, dtype=np.float64).reshape(3)
        """The scene's gravity vector [m/s^2], shape (3,)."""
        self.device, self.precision, self.law, self.order_seed = device, precision, law, order_seed
        self.centre = np.zeros(2)
        """Window centre [m], shape (2,)."""
        self.origin = np.zeros(2)
        """Lattice origin: the lower corner of the tile copy (0, 0) [m], shape (2,)."""
        self.moves = 0
        """How often the window moved [-]."""
        self.mass_initial = 0.0
        """Soil mass of the first window [kg]."""
        self.mass_added = 0.0
        """Soil mass placed ahead so far [kg]."""
        self.mass_removed = 0.0
        """Soil mass removed so far [kg]."""
        self.grains_added = 0
        self.grains_removed = 0
        self.next_id = 0
        # per grain, model order: identity, constants, frozen flag
        self.ids = np.zeros(0, dtype=np.int64)
        """Grain id (unique over the run) per model particle [-], shape (N,)."""
        self.radius = np.zeros(0)
        """Grain radii [m], shape (N,)."""
        self.material = np.zeros(0, dtype=np.int32)
        """Material index per grain [-], shape (N,), int32."""
        self.mass = np.zeros(0)
        """Grain masses [kg], shape (N,)."""
        self.free_inv_mass = np.zeros(0)
        """Inverse mass of each grain when free (a frozen grain's is 0 in the model) [1/kg], shape (N,)."""
        self.free_inv_inertia = np.zeros(0)
        """Inverse moment of inertia of each grain when free [1/(kg m^2)], shape (N,)."""
        self.frozen = np.zeros(0, dtype=bool)
        """Whether each grain is in the frozen band [-], shape (N,)."""

    # -- the window ---------------------------------------------------------------------
    def window(self, centre=None) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) corners of the window around `centre` (default: the current one) [m], shape (2,) each."""
        centre = self.centre if centre is None else np.asarray(centre, dtype=np.float64)
        return centre - self.half, centre + self.half

    @property
    def particle_count(self) -> int:
        return len(self.ids)

    @property
    def soil_mass(self) -> float:
        """Mass of the grains in the patch now [kg]."""
        return float(np.sum(self.mass, dtype=np.float64))

    def books(self) -> dict:
        """particle_count [-], soil_mass, mass_initial, mass_added, mass_removed [kg], moves [-]."""
        return {
            "particle_count": self.particle_count,
            "soil_mass": self.soil_mass,
            "mass_initial": self.mass_initial,
            "mass_added": self.mass_added,
            "mass_removed": self.mass_removed,
            "moves": self.moves,
        }

    def _lattice(self, low: np.ndarray, high: np.ndarray, old: tuple | None):
        """Tile grains of the lattice whose centres lie in [low, high) and not in the old window:
        (tile index, cell offset [m] (k, 2)), cells in (i, j) order, grains in tile order."""
        size = self.tile.size
        first = np.floor((low - self.origin) / size).astype(int)
        last = np.floor((high - self.origin) / size).astype(int)
        xy = self.tile.state["position"][:, :2]
        picks, offsets = [], []
        for i in range(first[0], last[0] + 1):
            for j in range(first[1], last[1] + 1):
                shift = self.origin + size * (i, j)
                points = xy + shift
                take = _inside(points, low, high)
                if old is not None:
                    take &= ~_inside(points, *old)
                index = np.flatnonzero(take)
                picks.append(index)
                offsets.append(np.broadcast_to(shift, (len(index), 2)))
        return np.concatenate(picks), np.concatenate(offsets) if offsets else np.zeros((0, 2))

    def surface_height(self, sim: Simulation) -> float:
        """Undisturbed surface z of the patch [m]: the mean top (z + r) of the highest grain in each column
        of a grid of one mean grain diameter over the free part of the window (as soil.bed.bed_metrics
        measures a bed). It is the lattice's own surface: the tile's seams make it differ from the tile's."""
        low, high = self.window()
        x = sim.positions()
        r = sim.model.radius_numpy()
        free = _inside(x[:, :2], low + self.band, high - self.band)
        cell = 2.0 * float(r.mean())
        column = np.floor((x[free, :2] - low) / cell).astype(np.int64)
        tops = x[free, 2] + r[free]
        keys = column[:, 0] * 1_000_003 + column[:, 1]
        order = np.lexsort((tops, keys))
        last = np.r_[keys[order][1:] != keys[order][:-1], True]
        return float(np.mean(tops[order][last]))

    def _permute(self, count: int) -> np.ndarray:
        if self.order_seed is None:
            return np.arange(count)
        return np.random.default_rng([self.order_seed, self.moves]).permutation(count)

    # -- building ----------------------------------------------------------------------------
    def start(self, centre, integrator=None) -> Simulation:
        """The first patch: the lattice's grains in the window around `centre` [m] (x, y), the band frozen."""
        self.centre = np.asarray(centre, dtype=np.float64).reshape(2).copy()
        self.origin = self.centre - self.half
        return self._assemble(
            None,
            self._lattice(*self.window(), None),
            time=0.0,
            steps=0,
            control=None,
            monitor=None,
            integrator=integrator,
        )

    def follow(self, sim: Simulation, point) -> Simulation | None:
        """Move the window when the wheels' centre `point` [m] (x, y) is too far from its centre; returns
        the new simulation, or None when the window stays."""
        point = np.asarray(point, dtype=np.float64).reshape(2)
        if np.all(np.abs(point - self.centre) <= self.recentre_distance):
            return None
        return self.recentre(sim, point)

    def recentre(self, sim: Simulation, centre) -> Simulation:
        """Move the window onto `centre` [m] (x, y) (module docstring); returns the new simulation."""
        old = self.window()
        self.centre = np.asarray(centre, dtype=np.float64).reshape(2).copy()
        self.moves += 1
        moved = self._assemble(
            sim,
            self._lattice(*self.window(), old),
            time=sim.time,
            steps=sim.steps,
            control=sim.control.state_dict(),
            monitor=sim.monitor,
            integrator=sim.integrator,
            old_window=old,
        )
        moved.step_control = sim.step_control  # the PID step control's state goes on with the soil
        return moved

    @staticmethod
    def _control(control: dict, kept: np.ndarray, placed: int) -> dict:
        """The control's state for the new grains: per-grain external forces of the kept grains, none on
        the placed ones; the wheels' and the floor's motion as they were."""
        out = dict(control)
        force = np.asarray(control["external_force"])
        out["external_force"] = np.concatenate([force[kept], np.zeros((placed, *force.shape[1:]), force.dtype)])
        return out

    def _assemble(self, sim, placed, time, steps, control, monitor, integrator, old_window=None) -> Simulation:
        tile = self.tile
        low, high = self.window()
        wheels = len(self.wheels)
        # grains kept (inside the new window, not strays in its new part), in their model order
        if sim is not None:
            state = sim.state.to_numpy()
            xy = state["position"][:, :2]
            inside = _inside(xy, low, high)
            keep = inside & _inside(xy, *old_window)
            kept = np.flatnonzero(keep)
            gone = np.flatnonzero(~keep)
            self.mass_removed += float(np.sum(self.mass[gone], dtype=np.float64))
            self.grains_removed += len(gone)
        else:
            state, kept = None, np.zeros(0, dtype=np.int64)
        picks, shifts = placed
        order = self._permute(len(picks))
        picks, shifts = picks[order], shifts[order]
        n_kept, n_new = len(kept), len(kept) + len(picks)
        # the new model's grains: kept 0 .. n_kept-1, placed after them; rigid keys: the floor 0, wheels 1 + b
        parts = []
        if state is not None:
            parts.append(select_grains(grain_rows(state), kept))
        # a placed grain keeps its history with grains of its own tile copy placed with it, and with the floor
        copy = np.full((len(picks), tile.count), -1, dtype=np.int64)
        for shift in np.unique(shifts, axis=0):
            members = np.flatnonzero(np.all(shifts == shift, axis=1))
            in_copy = np.full(tile.count, -1, dtype=np.int64)
            in_copy[picks[members]] = n_kept + members
            copy[members] = in_copy
        rows = np.arange(len(picks))[:, None]
        placed_rows = renumber_history(
            {k: v[picks] for k, v in tile.state.items()},
            lambda j: copy[np.broadcast_to(rows, j.shape), j],
            lambda key: np.where(key == tile.floor_key, 0, -1),
        )
        placed_rows["position"][:, :2] += shifts
        parts.append(placed_rows)
        arrays = append_grains(parts)

        # constants per grain
        def joined(mine, theirs):
            return np.concatenate([mine[kept], theirs[picks]])

        self.ids = np.concatenate([self.ids[kept], self.next_id + np.arange(len(picks), dtype=np.int64)])
        self.next_id += len(picks)
        self.radius = joined(self.radius, tile.radius)
        self.material = joined(self.material, tile.material)
        self.mass = joined(self.mass, tile.mass)
        self.free_inv_mass = joined(self.free_inv_mass, tile.inv_mass)
        self.free_inv_inertia = joined(self.free_inv_inertia, tile.inv_inertia)
        added = float(np.sum(tile.mass[picks], dtype=np.float64))
        if sim is None:
            self.mass_initial = added
        else:
            self.mass_added += added
            self.grains_added += len(picks)
        # the band: grains within `band` of the window's edge are frozen, the others free
        self.frozen = ~_inside(arrays["position"][:, :2], low + self.band, high - self.band)
        arrays["velocity"][self.frozen] = 0.0
        arrays["angular_velocity"][self.frozen] = 0.0
        if control is not None:
            control = self._control(control, kept, len(picks))
        new = self._simulation(arrays, time, steps, control, monitor, integrator, arm=True)
        assert new.model.particle_count == n_new and new.model.body_count == wheels
        return new

    def _simulation(self, arrays: dict, time: float, steps: int, control, monitor, integrator, arm: bool) -> Simulation:
        """A Simulation of the patch's grains (model order = the patch's order) with `arrays` as state."""
        tile = self.tile
        builder = SoilBuilder(gravity=self.gravity)
        for material in tile.materials:
            builder.add_material(material)
        for (i, j), values in tile.overrides.items():
            builder.materials.set_pair(i, j, **values)
        builder.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), tile.floor_material, report=False)
        # one call per run of equal materials, so the builder's order is the patch's order
        cuts = np.flatnonzero(np.diff(self.material)) + 1
        for rows in np.split(np.arange(len(self.material)), cuts):
            if len(rows):
                builder.add_particles(arrays["position"][rows], self.radius[rows], int(self.material[rows[0]]))
        for shape, material in self.wheels:
            builder.add_wheel(shape, material)
        inv_mass = np.where(self.frozen, 0, self.free_inv_mass).astype(self.free_inv_mass.dtype)
        inv_inertia = np.where(self.frozen, 0, self.free_inv_inertia).astype(self.free_inv_inertia.dtype)
        builder.start_from(  # builder order = the patch's order (no order_seed): no permutation
            {**arrays, "step_previous": np.zeros(1)},
            {"mass": self.mass, "inv_mass": inv_mass, "inv_inertia": inv_inertia},
            time=time,
        )
        model, state, soil_control = builder.finalize(
            device=self.device,
            precision=self.precision,
            law=self.law,
            contact_capacity=max(1, arrays["neighbours"].shape[1]),
            rigid_capacity=max(1, arrays["rigid_key"].shape[1]),
        )
        if control is not None:
            soil_control.load_state_dict(control)
        # the same settings; armed again below on the new grains (their own height)
        kept_monitor = None if monitor is None else monitor.for_new_grains()
        sim = Simulation(model, state, soil_control, integrator=integrator, monitor=kept_monitor)
        sim.steps = int(steps)
        sim.refresh_forces()
        if arm and monitor is not None and monitor.armed:
            sim.monitor.arm(sim)
        return sim

    # -- checkpoints -----------------------------------------------------------------------------
    STATE_UNITS = {
        "centre": "m",
        "origin": "m",
        "moves": "count",
        "mass_initial": "kg",
        "mass_added": "kg",
        "mass_removed": "kg",
        "grains_added": "count",
        "grains_removed": "count",
        "next_id": "1",
        "ids": "1",
        "radius": "m",
        "material": "1",  # an index into the materials table
        "mass": "kg",
        "free_inv_mass": "1/kg",
        "free_inv_inertia": "1/(kg m^2)",
        "frozen": "1",
    }
    """The unit of each entry of state_dict()."""

    def state_dict_units(self) -> dict[str, str]:
        """{key of state_dict(): its unit}."""
        return dict(self.STATE_UNITS)

    def state_dict(self) -> dict:
        """The window, the books and the patch's grains (ids, constants, band, positions)."""
        return {
            "centre": self.centre.copy(),
            "origin": self.origin.copy(),
            "moves": self.moves,
            "mass_initial": self.mass_initial,
            "mass_added": self.mass_added,
            "mass_removed": self.mass_removed,
            "grains_added": self.grains_added,
            "grains_removed": self.grains_removed,
            "next_id": self.next_id,
            "ids": self.ids.copy(),
            "radius": self.radius.copy(),
            "material": self.material.copy(),
            "mass": self.mass.copy(),
            "free_inv_mass": self.free_inv_mass.copy(),
            "free_inv_inertia": self.free_inv_inertia.copy(),
            "frozen": self.frozen.copy(),
        }

    def load_state_dict(self, state: dict, sim: Simulation) -> Simulation:
        """Take a checkpoint's patch back; returns a simulation of its grains (its state is then loaded
        by Simulation.load_state_dict over it)."""
        self.centre = np.array(state["centre"], dtype=np.float64)
        self.origin = np.array(state["origin"], dtype=np.float64)
        self.moves = int(state["moves"])
        self.mass_initial = float(state["mass_initial"])
        self.mass_added = float(state["mass_added"])
        self.mass_removed = float(state["mass_removed"])
        self.grains_added = int(state["grains_added"])
        self.grains_removed = int(state["grains_removed"])
        self.next_id = int(state["next_id"])
        for name in ("ids", "radius", "material", "mass", "free_inv_mass", "free_inv_inertia", "frozen"):
            setattr(self, name, np.array(state[name]))
        n = len(self.ids)
        arrays = {
            name: np.zeros((n, *values.shape[1:]), dtype=values.dtype)
            for name, values in grain_rows(sim.state.to_numpy()).items()
        }
        for name in ("neighbours", "rigid_key"):
            arrays[name][:] = -1
        arrays["build_position"][:] = UNBUILT
        # grains far apart until the checkpoint's state is loaded over them: nothing touches
        arrays["position"][:, 2] = 4 * np.arange(n) * float(self.radius.max())
        return self._simulation(arrays, sim.time, sim.steps, None, sim.monitor, sim.integrator, arm=False)


__all__ = ["SoilPatch", "Tile"]
