"""What the device tells the host about the steps it took: one small int32 array, written by
the kernels (storage needs, non-finite states, rebuilds) and read once per macro step
(soil.simulation), never inside a step.
"""

import warp as wp

NEEDED_NEIGHBOURS = 0
"""Largest neighbour-list row a build needed [-] (above the capacity: the list overflowed)."""
NEEDED_RIGID = 1
"""Most rigid contacts (walls, wheels) a grain had [-] (above its slots: they overflowed)."""
NONFINITE = 2
"""1 if a grain's position, velocity or spin became NaN or inf."""
WORST = 3
"""Model index of a grain with a non-finite state (the largest such index), -1 if none."""
REBUILDS = 4
"""Neighbour-list builds since the status was cleared [-]."""
LOST_HISTORY = 5
"""1 if a world of a batch that took its state back (soil.step_control) had a contact that the
neighbour list then in use did not hold: that contact's history restarts."""
COLUMNS = 6


@wp.kernel(enable_backward=False)
def clear_status(status_out: wp.array(dtype=wp.int32)):
    """Reset every column (WORST to -1)."""
    column = wp.tid()
    value = 0
    if column == WORST:
        value = -1
    status_out[column] = value


def make_status(device) -> wp.array:
    """A cleared status array, shape (COLUMNS,), int32."""
    status = wp.empty(COLUMNS, dtype=wp.int32, device=device)
    clear(status)
    return status


def clear(status: wp.array) -> None:
    """Reset the status on the device (capturable)."""
    wp.launch(clear_status, dim=COLUMNS, outputs=[status], device=status.device)
