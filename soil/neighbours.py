"""The Verlet neighbour list: which grains each grain may touch, rebuilt only when needed.

A grain's row lists every grain j within r_i + r_j + skin of it when the list was built.
While no grain has moved more than skin / 2 since the build, every contact is a pair in
the list (two grains closing by at most one skin), so a step only loops over its row. The
check runs on the device after each step's prediction (LAMMPS' `neigh_modify check yes`)
and the rebuild is a device-side branch (`wp.capture_if`), so a step never asks the host.

A build sorts the grains into cells of a grid whose cells are sized per axis from the
grains' bounding box (at least 2 r_max + skin, so a grain's partners lie in its own and the
26 adjacent cells; the cell counts per axis follow the domain's shape, so a wide, shallow
bed is not aliased onto a cube). The sort key is the cell's Morton code (a space-filling
curve); ties go by model index. A row lists its partners cell by cell in a fixed order, so
the list, and every sum over it, depends on positions and model indices only, not on the
storage order.

`reorder` moves the grains in memory into that same curve order (between steps): near
grains then share cache lines. The history is remapped at every build (a pair keeps its
tangential and rolling history from one list to the next) and carried along by a reorder.
Design notes and measurements: docs/performance.md.
"""

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from . import status as status_columns
from .contact import ContactLaw, spin_history_type
from .errors import SoilInputError
from .precision import kernel_factory, kernel_module, soil_kernel
from .reduction import WorldTree, leaf_span
from .state import GrainLayout, SoilState, storage_functions

REORDER_FROM = 4096
"""Grains from which the storage is reordered by default (below it all of them fit in cache)."""
MAX_CELLS_PER_AXIS = 1024
"""Cells per axis at most (10 bits of the Morton key each)."""
MORTON_BITS = 30
"""Bits of a cell's Morton code in the sort key; the world index (soil.worlds) sits above them."""
MORTON_MASK = (1 << MORTON_BITS) - 1


@dataclass(frozen=True)
class NeighbourSettings:
    """How the neighbour list is kept.

    skin: extra reach of the list beyond contact [m]; None: 0.3 x the largest grain radius.
    A larger skin rebuilds less often and loops over more pairs per step.
    reorder: sort the grains in memory along the space-filling curve when the list is
    rebuilt (between macro steps); None: when there are at least REORDER_FROM grains.
    reorder_every: reorder after this many rebuilds [-].
    """

    skin: float | None = None
    reorder: bool | None = None
    reorder_every: int = 1

    def __post_init__(self):
        if self.skin is not None and not (
            isinstance(self.skin, (int, float)) and math.isfinite(self.skin) and self.skin > 0
        ):
            raise SoilInputError(f"neighbour skin must be finite and > 0 [m], got {self.skin!r}")
        if not (isinstance(self.reorder_every, int) and self.reorder_every >= 1):
            raise SoilInputError(f"reorder_every must be an integer >= 1, got {self.reorder_every!r}")


@wp.func
def spread_bits(v: int):
    """The low 10 bits of v, moved to every third bit (Morton interleave)."""
    v = v & 0x3FF
    v = (v | (v << 16)) & 0x030000FF
    v = (v | (v << 8)) & 0x0300F00F
    v = (v | (v << 4)) & 0x030C30C3
    v = (v | (v << 2)) & 0x09249249
    return v


@wp.func
def compact_bits(v: int):
    """Inverse of spread_bits: every third bit of v gathered into the low 10 bits."""
    v = v & 0x09249249
    v = (v | (v >> 2)) & 0x030C30C3
    v = (v | (v >> 4)) & 0x0300F00F
    v = (v | (v >> 8)) & 0x030000FF
    v = (v | (v >> 16)) & 0x3FF
    return v


@wp.kernel(enable_backward=False)
def gather_1d(source: wp.array(dtype=Any), origin: wp.array(dtype=wp.int32), target_out: wp.array(dtype=Any)):
    """target[q] = source[origin[q]]."""
    q = wp.tid()
    target_out[q] = source[origin[q]]


@wp.kernel(enable_backward=False)
def gather_2d(source: wp.array2d(dtype=Any), origin: wp.array(dtype=wp.int32), target_out: wp.array2d(dtype=Any)):
    """target[q, k] = source[origin[q], k]."""
    q, k = wp.tid()
    target_out[q, k] = source[origin[q], k]


@wp.kernel(enable_backward=False)
def gather_columns(source: wp.array2d(dtype=Any), origin: wp.array(dtype=wp.int32), target_out: wp.array2d(dtype=Any)):
    """target[k, q] = source[k, origin[q]] (a slot-major array)."""
    k, q = wp.tid()
    target_out[k, q] = source[k, origin[q]]


@kernel_factory
def neighbour_kernels(hi, mid, lo, law: ContactLaw, slot_major: bool = False):
    """The neighbour-list kernels for precision types (hi, mid, lo), the contact-law switches (the
    pair history is stored in mid: soil.precision) and the storage order (soil.state)."""
    module = kernel_module("neighbours", hi, mid, lo, law, *(("slot",) if slot_major else ()))
    kernel = soil_kernel(module)
    storage = storage_functions(module, slot_major)
    entry, set_entry, list_capacity = storage.entry, storage.set_entry, storage.list_capacity
    at, put, slots = storage.at, storage.put, storage.slots
    vec_hi = wp.types.vector(3, hi)
    FRICTION, SPIN = law.friction, law.spin
    vec_mid = wp.types.vector(3, mid)
    vec_spin = spin_history_type(mid, law)

    @wp.func
    def cell_of(x: vec_hi, grid: wp.array(dtype=hi), dims: wp.vec3i):
        """Cell coordinates of x, clamped into the grid (a NaN lands in cell 0)."""
        cell = wp.vec3i()
        for axis in range(3):
            f = (x[axis] - grid[axis]) / grid[3 + axis]
            c = int(0)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
            if f >= hi(dims[axis] - 1):
                c = dims[axis] - 1
            elif f >= hi(0.0):  # False for NaN
                c = int(f)
            cell[axis] = c
        return cell

    @kernel
    def begin_check(
        list_index_in: wp.array(dtype=wp.int32),
        list_index_out: wp.array(dtype=wp.int32),
        rebuild_out: wp.array(dtype=wp.int32),
        rebuilt_out: wp.array(dtype=wp.int32),
    ):
        """Before a step's check: the output state keeps its input's list unless it is rebuilt."""
        list_index_out[0] = list_index_in[0]
        rebuild_out[0] = 0
        rebuilt_out[0] = 0

    @kernel
    def check_moved(
        position: wp.array(dtype=vec_hi),
        build_position: wp.array2d(dtype=vec_hi),
        list_index: wp.array(dtype=wp.int32),
        half_skin: hi,
        rebuild_out: wp.array(dtype=wp.int32),
    ):
        """Flag a rebuild when a grain has moved more than half the skin since the build
        (the same value from every thread that writes it: no atomics needed)."""
        i = wp.tid()
        d = position[i] - build_position[list_index[0], i]
        if not (wp.dot(d, d) <= half_skin * half_skin):  # NaN moves too
            rebuild_out[0] = 1

    @kernel
    def bounds_partial(position: wp.array(dtype=vec_hi), bounds_out: wp.array2d(dtype=vec_hi)):
        """The tree's leaves (soil.reduction, maxima only): per LEAF grains in storage order, the
        largest finite coordinates (column 0) and the largest negated ones (column 1: minus the
        lower corner). Maxima do not depend on the order."""
        c = wp.tid()
        big = hi(1.0e30)
        upper = vec_hi(-big, -big, -big)
        lower_negated = vec_hi(-big, -big, -big)
        span = leaf_span(c, bounds_out.shape[0], position.shape[0])  # one world: every grain
        for i in range(span[0], span[1]):
            x = position[i]
            if wp.isfinite(x):
                upper = wp.max(upper, x)
                lower_negated = wp.max(lower_negated, -x)
        bounds_out[c, 0] = upper
        bounds_out[c, 1] = lower_negated

    @kernel
    def bounds_total(
        bounds_in: wp.array2d(dtype=vec_hi),
        cell_min: hi,
        dims: wp.vec3i,
        grid_out: wp.array(dtype=hi),
    ):
        """The grid from the tree's last rows: origin [m] (3), cell size [m] per axis (3), at least
        cell_min, covering the box, and the box's upper corner [m] (3)."""
        big = hi(1.0e30)
        upper = vec_hi(-big, -big, -big)
        lower_negated = vec_hi(-big, -big, -big)
        for c in range(bounds_in.shape[0]):
            upper = wp.max(upper, bounds_in[c, 0])
            lower_negated = wp.max(lower_negated, bounds_in[c, 1])
        lower = -lower_negated
        for axis in range(3):
            origin = lower[axis]
            extent = upper[axis] - lower[axis]
            if not (extent >= hi(0.0)):  # no finite grain at all
                origin = hi(0.0)
                extent = hi(0.0)
            grid_out[axis] = origin
            grid_out[3 + axis] = wp.max(cell_min, extent * hi(1.000001) / hi(dims[axis]))
            grid_out[6 + axis] = origin + extent

    @kernel
    def cell_keys(
        position: wp.array(dtype=vec_hi),
        slot: wp.array(dtype=wp.int32),
        grid: wp.array(dtype=hi),
        dims: wp.vec3i,
        world_size: int,
        keys_out: wp.array(dtype=wp.int64),
        values_out: wp.array(dtype=wp.int32),
    ):
        """Key of each grain's cell: its world (soil.worlds) above the cell's Morton code, listed by
        model index (so that the stable sort breaks ties by model index, whatever the storage order)."""
        p = wp.tid()
        cell = cell_of(position[slot[p]], grid, dims)
        morton = spread_bits(cell[0]) | (spread_bits(cell[1]) << 1) | (spread_bits(cell[2]) << 2)
        keys_out[p] = (wp.int64(p // world_size) << wp.int64(MORTON_BITS)) | wp.int64(morton)
        values_out[p] = p

    @kernel
    def cell_ranges(
        keys: wp.array(dtype=wp.int64),
        values: wp.array(dtype=wp.int32),
        slot: wp.array(dtype=wp.int32),
        count: int,
        dims: wp.vec3i,
        cell_start_out: wp.array(dtype=wp.int32),
        cell_end_out: wp.array(dtype=wp.int32),
        cell_slot_out: wp.array(dtype=wp.int32),
    ):
        """Where each occupied cell's grains start and end in the sorted order, and their slots
        (world w's cells are w * cells .. (w + 1) * cells - 1)."""
        q = wp.tid()
        key = keys[q]
        world = int(key >> wp.int64(MORTON_BITS))
        morton = int(key & wp.int64(MORTON_MASK))
        cells = dims[0] * dims[1] * dims[2]
        cell = (
            world * cells
            + compact_bits(morton)
            + dims[0] * (compact_bits(morton >> 1) + dims[1] * compact_bits(morton >> 2))
        )
        first = q == 0
        if not first:
            first = keys[q - 1] != key
        if first:
            cell_start_out[cell] = q
        last = q == count - 1
        if not last:
            last = keys[q + 1] != key
        if last:
            cell_end_out[cell] = q + 1
        cell_slot_out[q] = slot[values[q]]

    @kernel
    def build_rows(
        position: wp.array(dtype=vec_hi),
        radius: wp.array(dtype=lo),
        inv_mass: wp.array(dtype=lo),
        order: wp.array(dtype=wp.int32),
        grid: wp.array(dtype=hi),
        dims: wp.vec3i,
        cell_start: wp.array(dtype=wp.int32),
        cell_end: wp.array(dtype=wp.int32),
        cell_slot: wp.array(dtype=wp.int32),
        skin: hi,
        target: wp.array(dtype=wp.int32),
        world_size: int,
        neighbours_out: wp.array3d(dtype=wp.int32),
        neighbour_count_out: wp.array2d(dtype=wp.int32),
        build_position_out: wp.array2d(dtype=vec_hi),
        status_out: wp.array(dtype=wp.int32),
    ):
        """Row of grain i in list `target`: the grains of its world within r_i + r_j + skin, in
        ascending model index (so the row, and every sum over it, depends neither on the storage
        order nor on the grid, nor on other worlds). Two fixed grains never pair."""
        i = wp.tid()
        first_cell = (order[i] // world_size) * dims[0] * dims[1] * dims[2]
        t = target[0]
        capacity = list_capacity(neighbours_out)
        x = position[i]
        ri = hi(radius[i])
        free = inv_mass[i] > lo(0.0)
        home = cell_of(x, grid, dims)
        count = int(0)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
        for dz in range(-1, 2):
            cz = home[2] + dz
            if cz < 0 or cz >= dims[2]:
                continue
            for dy in range(-1, 2):
                cy = home[1] + dy
                if cy < 0 or cy >= dims[1]:
                    continue
                for dx in range(-1, 2):
                    cx = home[0] + dx
                    if cx < 0 or cx >= dims[0]:
                        continue
                    cell = first_cell + cx + dims[0] * (cy + dims[1] * cz)
                    for q in range(cell_start[cell], cell_end[cell]):
                        j = cell_slot[q]
                        if j != i and (free or inv_mass[j] > lo(0.0)):
                            gap = position[j] - x
                            reach = ri + hi(radius[j]) + skin
                            if wp.dot(gap, gap) < reach * reach:
                                if count < capacity:
                                    set_entry(neighbours_out, t, i, count, j)
                                count += 1
        stored = wp.min(count, capacity)
        for k in range(1, stored):  # insertion sort by model index (rows are short)
            j = entry(neighbours_out, t, i, k)
            key = order[j]
            m = k - 1
            while m >= 0:  # (no short-circuit `and` in kernels: test the index first)
                if order[entry(neighbours_out, t, i, m)] > key:
                    set_entry(neighbours_out, t, i, m + 1, entry(neighbours_out, t, i, m))
                    m -= 1
                else:
                    break
            set_entry(neighbours_out, t, i, m + 1, j)
        neighbour_count_out[t, i] = stored
        build_position_out[t, i] = x
        if count > capacity:
            wp.atomic_max(status_out, status_columns.NEEDED_NEIGHBOURS, count)

    @kernel
    def remap_history(
        neighbours: wp.array3d(dtype=wp.int32),
        neighbour_count: wp.array2d(dtype=wp.int32),
        list_index_in: wp.array(dtype=wp.int32),
        target: wp.array(dtype=wp.int32),
        order: wp.array(dtype=wp.int32),
        touching_in: wp.array2d(dtype=wp.uint32),
        tangential_in: wp.array2d(dtype=vec_mid),
        rolling_in: wp.array2d(dtype=vec_spin),
        touching_old: wp.array2d(dtype=wp.uint32),
        worlds: wp.array(dtype=wp.int32),
        world_size: int,
        count_lost: int,
        touching_out: wp.array2d(dtype=wp.uint32),
        tangential_out: wp.array2d(dtype=vec_mid),
        rolling_out: wp.array2d(dtype=vec_spin),
        status_out: wp.array(dtype=wp.int32),
    ):
        """Carry each pair's history from its entry in the old row to its entry in the new one
        (both rows ascend in model index: one merge pass).

        Entries out of contact hold zero in every buffer (their bit is clear), so the history
        arrays are a function of the contacts alone: entries the output held before
        (touching_old) and that carry nothing now are cleared. Only the grains of the worlds
        flagged in `worlds` (soil.worlds) are remapped. count_lost != 0: a contact of the old row
        that the new one lacks is flagged (status LOST_HISTORY): the new list was built at other
        positions than the contacts' (a world's restore, soil.step_control)."""
        i = wp.tid()
        if worlds[i // world_size] == 0:
            return
        old = list_index_in[0]
        new = target[0]
        old_count = neighbour_count[old, i]
        new_count = neighbour_count[new, i]
        capacity = list_capacity(neighbours)
        kk = int(0)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
        carried = int(0)  # noqa: UP018
        for word in range(slots(touching_out)):
            bits = wp.uint32(0)
            for k in range(word * 32, wp.min(word * 32 + 32, new_count)):
                key = order[entry(neighbours, new, i, k)]
                while kk < old_count:
                    if order[entry(neighbours, old, i, kk)] < key:
                        kk += 1
                    else:
                        break
                if kk < old_count:
                    if entry(neighbours, old, i, kk) == entry(neighbours, new, i, k):
                        if (at(touching_in, i, kk >> 5) >> wp.uint32(kk & 31)) & wp.uint32(1) != wp.uint32(0):
                            bits = bits | (wp.uint32(1) << wp.uint32(k & 31))
                            carried += 1
                            if wp.static(FRICTION):
                                put(tangential_out, i, k, at(tangential_in, i, kk))
                            if wp.static(SPIN):
                                put(rolling_out, i, k, at(rolling_in, i, kk))
            clear = at(touching_old, i, word) & ~bits
            if clear != wp.uint32(0):
                for k in range(word * 32, wp.min(word * 32 + 32, capacity)):
                    if (clear >> wp.uint32(k & 31)) & wp.uint32(1) != wp.uint32(0):
                        if wp.static(FRICTION):
                            put(tangential_out, i, k, vec_mid())
                        if wp.static(SPIN):
                            put(rolling_out, i, k, vec_spin())
            put(touching_out, i, word, bits)
        if count_lost != 0:
            touching = int(0)  # noqa: UP018
            for k in range(old_count):
                if (at(touching_in, i, k >> 5) >> wp.uint32(k & 31)) & wp.uint32(1) != wp.uint32(0):
                    touching += 1
            if carried < touching:
                status_out[status_columns.LOST_HISTORY] = 1

    @kernel
    def finish_build(
        target: wp.array(dtype=wp.int32),
        list_index_out: wp.array(dtype=wp.int32),
        rebuilt_out: wp.array(dtype=wp.int32),
        status_out: wp.array(dtype=wp.int32),
    ):
        """The output state's history is now aligned with the new list."""
        list_index_out[0] = target[0]
        rebuilt_out[0] = 1
        status_out[status_columns.REBUILDS] = status_out[status_columns.REBUILDS] + 1

    @kernel
    def other_list(list_index_in: wp.array(dtype=wp.int32), target_out: wp.array(dtype=wp.int32)):
        """The list a build writes: the one the input state does not use."""
        target_out[0] = 1 - list_index_in[0]

    @kernel
    def new_slots(values: wp.array(dtype=wp.int32), new_slot_out: wp.array(dtype=wp.int32)):
        """New storage slot of each model index: its place in the sorted order."""
        q = wp.tid()
        new_slot_out[values[q]] = q

    @kernel
    def storage_origin(
        values: wp.array(dtype=wp.int32), slot: wp.array(dtype=wp.int32), origin_out: wp.array(dtype=wp.int32)
    ):
        """Old slot of the grain that moves to new slot q."""
        q = wp.tid()
        origin_out[q] = slot[values[q]]

    @kernel
    def relabel_rows(
        neighbours: wp.array3d(dtype=wp.int32),
        neighbour_count: wp.array2d(dtype=wp.int32),
        build_position: wp.array2d(dtype=vec_hi),
        list_index_in: wp.array(dtype=wp.int32),
        origin: wp.array(dtype=wp.int32),
        order: wp.array(dtype=wp.int32),
        new_slot: wp.array(dtype=wp.int32),
        neighbours_out: wp.array3d(dtype=wp.int32),
        neighbour_count_out: wp.array2d(dtype=wp.int32),
        build_position_out: wp.array2d(dtype=vec_hi),
        list_index_out: wp.array(dtype=wp.int32),
    ):
        """Move each row of the current list to its grain's new slot (into the other list), naming
        the partners by their new slots."""
        q = wp.tid()
        c = list_index_in[0]
        t = 1 - c
        old = origin[q]
        count = neighbour_count[c, old]
        for k in range(count):
            set_entry(neighbours_out, t, q, k, new_slot[order[entry(neighbours, c, old, k)]])
        neighbour_count_out[t, q] = count
        build_position_out[t, q] = build_position[c, old]
        if q == 0:
            list_index_out[0] = t

    @kernel
    def relabel_layout(
        values: wp.array(dtype=wp.int32),
        radius: wp.array(dtype=lo),
        mass: wp.array(dtype=lo),
        inv_mass: wp.array(dtype=lo),
        inv_inertia: wp.array(dtype=lo),
        material: wp.array(dtype=wp.int32),
        order_out: wp.array(dtype=wp.int32),
        slot_out: wp.array(dtype=wp.int32),
        radius_out: wp.array(dtype=lo),
        mass_out: wp.array(dtype=lo),
        inv_mass_out: wp.array(dtype=lo),
        inv_inertia_out: wp.array(dtype=lo),
        material_out: wp.array(dtype=wp.int32),
    ):
        """The layout in the new order: model index per slot, its inverse, and the grains'
        constants gathered from the model (model order)."""
        q = wp.tid()
        p = values[q]
        order_out[q] = p
        slot_out[p] = q
        radius_out[q] = radius[p]
        mass_out[q] = mass[p]
        inv_mass_out[q] = inv_mass[p]
        inv_inertia_out[q] = inv_inertia[p]
        material_out[q] = material[p]

    @kernel
    def copy_list(
        neighbours: wp.array3d(dtype=wp.int32),
        neighbour_count: wp.array2d(dtype=wp.int32),
        build_position: wp.array2d(dtype=vec_hi),
        source: wp.array(dtype=wp.int32),
        target: wp.array(dtype=wp.int32),
        neighbours_out: wp.array3d(dtype=wp.int32),
        neighbour_count_out: wp.array2d(dtype=wp.int32),
        build_position_out: wp.array2d(dtype=vec_hi),
    ):
        """Copy grain i's row of list source[0] into list target[0] of the output arrays."""
        i = wp.tid()
        s = source[0]
        t = target[0]
        count = neighbour_count[s, i]
        for k in range(count):
            set_entry(neighbours_out, t, i, k, entry(neighbours, s, i, k))
        neighbour_count_out[t, i] = count
        build_position_out[t, i] = build_position[s, i]

    return dict(
        copy_list=copy_list,
        begin_check=begin_check,
        check_moved=check_moved,
        bounds_partial=bounds_partial,
        bounds_total=bounds_total,
        cell_keys=cell_keys,
        cell_ranges=cell_ranges,
        build_rows=build_rows,
        remap_history=remap_history,
        finish_build=finish_build,
        other_list=other_list,
        new_slots=new_slots,
        storage_origin=storage_origin,
        relabel_rows=relabel_rows,
        relabel_layout=relabel_layout,
    )


class NeighbourList:
    """Keeps the layout's neighbour lists of a model (see the module docstring)."""

    def __init__(self, model, settings: NeighbourSettings | None = None, positions: np.ndarray | None = None):
        self.model = model
        self.settings = settings or NeighbourSettings()
        prec = model.precision
        self.kernels = neighbour_kernels(prec.hi, prec.mid, prec.lo, model.law, model.slot_major)
        self.skin = float(self.settings.skin if self.settings.skin is not None else 0.3 * model.max_radius)
        """Extra reach of the list beyond contact [m]."""
        self.cell_min = 2.0 * model.max_radius + self.skin
        """Smallest cell size [m]: the largest pair reach."""
        n = model.particle_count
        self.reorder_enabled = bool(self.settings.reorder if self.settings.reorder is not None else n >= REORDER_FROM)
        """Whether the storage follows the space-filling curve (reordered between macro steps)."""
        device = model.device
        self._bounds = WorldTree(1, n, 2, prec.vec_hi, device)
        """The grains' box over a tree (soil.reduction): upper corner, minus the lower corner [m]."""
        self.grid = wp.zeros(9, dtype=prec.hi, device=device)
        """Of the last build: the grid origin = the grains' lower corner [m] (3), the cell size per
        axis [m] (3) and the grains' upper corner [m] (3); shape (9,)."""
        self._keys = wp.zeros(2 * n, dtype=wp.int64, device=device)
        self._values = wp.zeros(2 * n, dtype=wp.int32, device=device)
        self._cell_slot = wp.zeros(n, dtype=wp.int32, device=device)
        self._target = wp.zeros(1, dtype=wp.int32, device=device)
        self._rebuild = wp.zeros(1, dtype=wp.int32, device=device)
        self._every_world = wp.ones(model.world_count, dtype=wp.int32, device=device)
        self.rebuilt = wp.zeros(1, dtype=wp.int32, device=device)
        """1 when the last check rebuilt the list (the output state's history is then remapped) [-], shape (1,),
        int32."""
        self._origin = wp.zeros(n, dtype=wp.int32, device=device)
        self._new_slot = wp.zeros(n, dtype=wp.int32, device=device)
        self._zero = wp.zeros(1, dtype=wp.int32, device=device)
        self._saved = None
        self.dims = (1, 1, 1)
        self._cell_start = self._cell_end = None
        self.plan(positions)

    # -- the grid ---------------------------------------------------------------------
    def plan(self, positions: np.ndarray | None) -> None:
        """Cell counts per axis from the grains' bounding box (host positions [m], (n, 3)):
        about one cell of the largest pair reach per grain diameter, at most 4 cells per grain of
        a world; every world (soil.worlds) has its own cells of this grid."""
        n = self.model.world_size
        if positions is None or not np.isfinite(positions).all():
            extent = np.full(3, self.cell_min * max(1.0, n ** (1 / 3)))
        else:
            extent = positions.max(axis=0) - positions.min(axis=0)
        dims = np.clip(np.floor(extent / self.cell_min), 1, MAX_CELLS_PER_AXIS).astype(np.int64)
        while dims.prod() > max(4 * n, 64):
            dims = np.maximum(1, dims // 2)
        dims = tuple(int(d) for d in dims)
        if dims == self.dims and self._cell_start is not None:
            return
        self.dims = dims
        cells = int(np.prod(dims)) * self.model.world_count
        self._cell_start = wp.zeros(cells, dtype=wp.int32, device=self.model.device)
        self._cell_end = wp.zeros(cells, dtype=wp.int32, device=self.model.device)

    def wants_plan(self, lower: np.ndarray, upper: np.ndarray) -> bool:
        """Whether the grains' box (lower, upper [m]) has drifted from the grid's plan by a factor of 2."""
        ideal = np.clip(np.floor((upper - lower) / self.cell_min), 1, MAX_CELLS_PER_AXIS)
        return bool(np.any(ideal > 2 * np.asarray(self.dims)) or np.any(2 * ideal < np.asarray(self.dims)))

    def device_arrays(self) -> list:
        """The scratch arrays a captured step uses (a graph stays valid while they do)."""
        return [self._keys, self._values, self._cell_slot, self._cell_start, self._cell_end, self.grid]

    def bytes_per_grain(self) -> float:
        """Device memory of the build's scratch and of the list saved at a macro step's start per grain [B]."""
        n = max(self.model.particle_count, 1)
        arrays = (
            self._keys,
            self._values,
            self._cell_slot,
            self._origin,
            self._new_slot,
            self._cell_start,
            self._cell_end,
        )
        saved = sum(a.capacity for a in self._saved) if self._saved is not None else 0  # every macro step's start
        return (sum(a.capacity for a in arrays) + self._bounds.capacity + saved) / n

    # -- steps ------------------------------------------------------------------------
    def update(self, state_in: SoilState, state_out: SoilState, status: wp.array) -> None:
        """Inside a step, after state_out's positions are predicted: rebuild the list when a grain
        has moved more than half the skin since the build of state_in's list, remapping the pair
        history of state_in into state_out; otherwise state_out keeps state_in's list. No host
        read: the rebuild is a device-side branch (capturable)."""
        k = self.kernels
        device = self.model.device
        wp.launch(
            k.begin_check,
            dim=1,
            inputs=[state_in.list_index],
            outputs=[state_out.list_index, self._rebuild, self.rebuilt],
            device=device,
        )
        wp.launch(
            k.check_moved,
            dim=self.model.particle_count,
            inputs=[
                state_out.position,
                state_in.layout.build_position,
                state_in.list_index,
                self.model.precision.hi(0.5 * self.skin),
            ],
            outputs=[self._rebuild],
            device=device,
        )
        wp.capture_if(self._rebuild, on_true=lambda: self._build(state_out.position, state_in, state_out, status))

    def build(self, state: SoilState, status: wp.array) -> None:
        """Build the list from `state`'s positions now (the other list; history remapped into
        place) and align `state` with it: for a state whose list is stale or was never built."""
        layout = state.layout
        k = self.kernels
        device = self.model.device
        wp.launch(k.other_list, dim=1, inputs=[state.list_index], outputs=[self._target], device=device)
        self._sort(state.position, layout)
        self._rows(state.position, layout, status)
        # history: from copies of the state's entries into entries aligned with the new rows
        touching = wp.clone(state.pair_touching)
        wp.launch(
            k.remap_history,
            dim=self.model.particle_count,
            inputs=[
                layout.neighbours,
                layout.neighbour_count,
                state.list_index,
                self._target,
                layout.order,
                touching,
                wp.clone(state.pair_tangential),
                wp.clone(state.pair_rolling),
                touching,
                self._every_world,
                self.model.world_size,
                0,
            ],
            outputs=[state.pair_touching, state.pair_tangential, state.pair_rolling, status],
            device=device,
        )
        wp.launch(
            k.finish_build,
            dim=1,
            inputs=[self._target],
            outputs=[state.list_index, self.rebuilt, status],
            device=device,
        )

    def build_other(self, state: SoilState, status: wp.array) -> None:
        """Build the list `state` does not use from its positions, leaving the state as it is
        (for diagnostics of a state whose own list is stale)."""
        wp.launch(
            self.kernels.other_list, dim=1, inputs=[state.list_index], outputs=[self._target], device=self.model.device
        )
        self._sort(state.position, state.layout)
        self._rows(state.position, state.layout, status)

    def stale(self, state: SoilState) -> bool:
        """Whether a grain of `state` has moved more than half the skin since its list was built (host read)."""
        k = self.kernels
        self._rebuild.zero_()
        wp.launch(
            k.check_moved,
            dim=self.model.particle_count,
            inputs=[
                state.position,
                state.layout.build_position,
                state.list_index,
                self.model.precision.hi(0.5 * self.skin),
            ],
            outputs=[self._rebuild],
            device=self.model.device,
        )
        return bool(self._rebuild.numpy()[0])

    def _build(self, position, state_in: SoilState, state_out: SoilState, status) -> None:
        k = self.kernels
        device = self.model.device
        layout = state_in.layout
        wp.launch(k.other_list, dim=1, inputs=[state_in.list_index], outputs=[self._target], device=device)
        self._sort(position, layout)
        self._rows(position, layout, status)
        wp.launch(
            k.remap_history,
            dim=self.model.particle_count,
            inputs=[
                layout.neighbours,
                layout.neighbour_count,
                state_in.list_index,
                self._target,
                layout.order,
                state_in.pair_touching,
                state_in.pair_tangential,
                state_in.pair_rolling,
                state_out.pair_touching,
                self._every_world,
                self.model.world_size,
                0,
            ],
            outputs=[state_out.pair_touching, state_out.pair_tangential, state_out.pair_rolling, status],
            device=device,
        )
        wp.launch(
            k.finish_build,
            dim=1,
            inputs=[self._target],
            outputs=[state_out.list_index, self.rebuilt, status],
            device=device,
        )

    def remap_worlds(self, source: SoilState, target: SoilState, worlds: wp.array, status: wp.array) -> None:
        """Carry the pair history of `source` (aligned with its list) into `target` (aligned with
        target's list, the same one or one built since) for the grains of the worlds flagged in
        `worlds` (int32 (world_count,)): those worlds' entries then hold source's contacts in
        target's rows (soil.step_control: a world that keeps nothing of a substep another world
        kept). A contact of source that target's list lacks (built where a grain had moved more
        than the skin) is flagged in `status` (LOST_HISTORY). On the device; capturable."""
        wp.launch(
            self.kernels.remap_history,
            dim=self.model.particle_count,
            inputs=[
                source.layout.neighbours,
                source.layout.neighbour_count,
                source.list_index,
                target.list_index,
                source.layout.order,
                source.pair_touching,
                source.pair_tangential,
                source.pair_rolling,
                target.pair_touching,
                worlds,
                self.model.world_size,
                1,
            ],
            outputs=[target.pair_touching, target.pair_tangential, target.pair_rolling, status],
            device=self.model.device,
        )

    def _sort(self, position, layout: GrainLayout) -> None:
        """The grid from the grains' box, and the grains sorted by (cell key, model index)."""
        k = self.kernels
        device = self.model.device
        n = self.model.particle_count
        hi = self.model.precision.hi
        dims = wp.vec3i(*self.dims)
        bounds = self._bounds
        wp.launch(
            k.bounds_partial, dim=bounds.leaves.shape[0], inputs=[position], outputs=[bounds.leaves], device=device
        )
        bounds.fold(summed_columns=0)
        wp.launch(
            k.bounds_total,
            dim=1,
            inputs=[bounds.last, hi(self.cell_min), dims],
            outputs=[self.grid],
            device=device,
        )
        wp.launch(
            k.cell_keys,
            dim=n,
            inputs=[position, layout.slot, self.grid, dims, self.model.world_size],
            outputs=[self._keys, self._values],
            device=device,
        )
        world_bits = int(self.model.world_count - 1).bit_length()
        wp.utils.radix_sort_pairs(self._keys, self._values, n, 0, MORTON_BITS + world_bits)

    def _rows(self, position, layout: GrainLayout, status) -> None:
        k = self.kernels
        device = self.model.device
        n = self.model.particle_count
        dims = wp.vec3i(*self.dims)
        self._cell_start.zero_()
        self._cell_end.zero_()
        wp.launch(
            k.cell_ranges,
            dim=n,
            inputs=[self._keys, self._values, layout.slot, n, dims],
            outputs=[self._cell_start, self._cell_end, self._cell_slot],
            device=device,
        )
        wp.launch(
            k.build_rows,
            dim=n,
            inputs=[
                position,
                layout.radius,
                layout.inv_mass,
                layout.order,
                self.grid,
                dims,
                self._cell_start,
                self._cell_end,
                self._cell_slot,
                self.model.precision.hi(self.skin),
                self._target,
                self.model.world_size,
            ],
            outputs=[layout.neighbours, layout.neighbour_count, layout.build_position, status],
            device=device,
        )

    # -- saving a list (a macro step redone from its start needs the start's list) -----------
    def save(self, state: SoilState) -> None:
        """Keep a copy of `state`'s current list (restore() puts it back)."""
        layout = state.layout
        n = self.model.particle_count
        if self._saved is None or self._saved[0].shape != (1, *layout.neighbours.shape[1:]):
            device = self.model.device
            self._saved = (
                wp.zeros((1, *layout.neighbours.shape[1:]), dtype=wp.int32, device=device),
                wp.zeros((1, n), dtype=wp.int32, device=device),
                wp.zeros((1, n), dtype=self.model.precision.vec_hi, device=device),
            )
        wp.launch(
            self.kernels.copy_list,
            dim=n,
            inputs=[layout.neighbours, layout.neighbour_count, layout.build_position, state.list_index, self._zero],
            outputs=list(self._saved),
            device=self.model.device,
        )

    def restore(self, state: SoilState) -> None:
        """Put the list saved by save() back where `state` expects it."""
        layout = state.layout
        wp.launch(
            self.kernels.copy_list,
            dim=self.model.particle_count,
            inputs=[*self._saved, self._zero, state.list_index],
            outputs=[layout.neighbours, layout.neighbour_count, layout.build_position],
            device=self.model.device,
        )

    # -- reordering (between steps) ------------------------------------------------------
    def reorder(self, state: SoilState, spare: SoilState) -> None:
        """Store the grains of `state` in the order of the space-filling curve, into `spare`
        (which becomes the current state: the caller swaps them). The layout (order,
        constants, current list) follows. Changes no value, only where values are stored."""
        layout = state.layout
        model = self.model
        k = self.kernels
        device = model.device
        n = model.particle_count
        self._sort(state.position, layout)
        wp.launch(k.new_slots, dim=n, inputs=[self._values], outputs=[self._new_slot], device=device)
        wp.launch(k.storage_origin, dim=n, inputs=[self._values, layout.slot], outputs=[self._origin], device=device)
        wp.launch(
            k.relabel_rows,
            dim=n,
            inputs=[
                layout.neighbours,
                layout.neighbour_count,
                layout.build_position,
                state.list_index,
                self._origin,
                layout.order,
                self._new_slot,
            ],
            outputs=[layout.neighbours, layout.neighbour_count, layout.build_position, spare.list_index],
            device=device,
        )
        for name, array in state.arrays.items():
            target = getattr(spare, name)
            if name.startswith(("boundary_", "body_")) or name == "step_previous":
                wp.copy(target, array)
            elif array.ndim == 1:
                wp.launch(gather_1d, dim=n, inputs=[array, self._origin], outputs=[target], device=device)
            elif array.shape[0 if state.slot_major else 1]:
                gather = gather_columns if state.slot_major else gather_2d
                wp.launch(gather, dim=array.shape, inputs=[array, self._origin], outputs=[target], device=device)
        wp.launch(
            k.relabel_layout,
            dim=n,
            inputs=[self._values, model.radius, model.mass, model.inv_mass, model.inv_inertia, model.material],
            outputs=[
                layout.order,
                layout.slot,
                layout.radius,
                layout.mass,
                layout.inv_mass,
                layout.inv_inertia,
                layout.material,
            ],
            device=device,
        )
        spare.time = state.time
        spare.forces_valid = state.forces_valid
