"""Deterministic per-world reductions over the grains: a fixed tree of short serial folds.

A reduction over a world's grains (the wrench on a wall or wheel, the step-error norms, the
grains' bounding box) runs in three stages of launches, with no atomics:

1. leaves: the caller's kernel folds LEAF consecutive model indices of one world per thread;
2. `fold_rows`: groups of FAN consecutive rows of a world fold into one row, level after level,
   while a world has more than FAN rows;
3. the caller's total kernel folds a world's last (at most FAN) rows.

Each world's leaves start at its first grain and its groups at its first row, so a world's tree
is the one it has alone (soil.worlds): batched worlds sum bit for bit as their runs alone. The
tree depends on model indices only, never on thread scheduling or the storage order.

Why a tree: a GPU runs a serial loop at the latency of its dependent loads, whatever the number
of grains, so the longest serial run sets a reduction's time. Chunks of 256 grains (the earlier
sums) made every step pay for 256 dependent loads in a row; LEAF and FAN keep the longest run at
32, at one or two more launches per step (docs/performance.md section 7).
"""

import warp as wp

from .precision import kernel_factory, kernel_module, soil_kernel

LEAF = wp.constant(32)
"""Consecutive model indices folded by one thread of a leaf kernel."""
FAN = wp.constant(32)
"""Rows folded into one at each level of the tree (and by a total kernel, at most)."""


def leaf_rows(world_size: int) -> int:
    """Leaf rows per world (at least 1: a world without grains still has its zero row)."""
    return max(1, -(-world_size // LEAF))


def level_rows(world_size: int) -> list[int]:
    """Rows per world at each level: the leaves first, then each fold's, the last at most FAN."""
    rows = [leaf_rows(world_size)]
    while rows[-1] > FAN:
        rows.append(-(-rows[-1] // FAN))
    return rows


@wp.func
def leaf_span(leaf: int, rows_per_world: int, world_size: int):
    """Model indices [begin, end) that leaf row `leaf` folds: LEAF consecutive ones of its world,
    counted from the world's first grain (world = leaf // rows_per_world)."""
    world = leaf // rows_per_world
    begin = world * world_size + (leaf - world * rows_per_world) * LEAF
    return wp.vec2i(begin, wp.min(begin + LEAF, (world + 1) * world_size))


@kernel_factory
def reduction_kernels(dtype):
    """`fold_rows` for one value type (float, vector or int32): a module of its own, loaded before a
    step is captured (soil.macro.StepGraphs.load_modules), as every kernel a captured step launches."""
    kernel = soil_kernel(kernel_module("reduction", wp.types.type_repr(dtype)))

    @kernel
    def fold_rows(
        rows_in: wp.array2d(dtype=dtype),
        rows_in_per_world: int,
        rows_out_per_world: int,
        summed_columns: int,
        rows_out: wp.array2d(dtype=dtype),
    ):
        """rows_out[r, k]: FAN consecutive rows of rows_in folded in order, within one world; the
        first `summed_columns` columns are summed, the others take the maximum."""
        r, k = wp.tid()  # type: ignore[misc]  # a 2-d launch: Warp returns a pair
        world = r // rows_out_per_world
        begin = world * rows_in_per_world + (r - world * rows_out_per_world) * FAN
        end = wp.min(begin + FAN, (world + 1) * rows_in_per_world)
        total = rows_in[begin, k]
        for j in range(begin + 1, end):
            if k < summed_columns:
                total = total + rows_in[j, k]
            else:
                total = wp.max(total, rows_in[j, k])
        rows_out[r, k] = total

    return dict(fold_rows=fold_rows)


class WorldTree:
    """The rows of one per-world reduction: leaves (written by the caller's leaf kernel) and the
    levels that `fold` fills. Allocated once (before a step is captured)."""

    def __init__(self, world_count: int, world_size: int, width: int, dtype, device):
        self.kernels = reduction_kernels(dtype)
        """The fold's kernel for these rows' type (for StepGraphs.load_modules)."""
        self.rows = level_rows(world_size)
        """Rows per world at each level (leaves first)."""
        self.levels = [wp.zeros((world_count * rows, max(width, 1)), dtype=dtype, device=device) for rows in self.rows]
        """Per level, an array of shape (world_count * rows, width) in the caller's units: world w's rows
        in one block."""

    @property
    def leaves(self) -> wp.array:
        return self.levels[0]

    @property
    def last(self) -> wp.array:
        """The last level: at most FAN rows per world, for the caller's total kernel."""
        return self.levels[-1]

    @property
    def last_rows(self) -> int:
        """Rows per world of the last level."""
        return self.rows[-1]

    def fold(self, summed_columns: int) -> None:
        """Fold the leaves level by level (no host read: capturable)."""
        for level in range(1, len(self.levels)):
            source, target = self.levels[level - 1], self.levels[level]
            wp.launch(
                self.kernels.fold_rows,
                dim=target.shape,
                inputs=[source, self.rows[level - 1], self.rows[level], summed_columns],
                outputs=[target],
                device=target.device,
            )

    @property
    def capacity(self) -> int:
        """Bytes of all levels."""
        return sum(a.capacity for a in self.levels)
