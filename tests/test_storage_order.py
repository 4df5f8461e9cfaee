"""The storage order of the neighbour lists and contact history (soil.state: per grain or per slot, the
layout a GPU reads coalesced) changes where values live, never a value: a coupled run in either order is
the same to the last bit, storage growth and reordering included, and a checkpoint of one order continues
in the other."""

import warnings

import numpy as np
import pytest
from test_worlds import STEPS, contacts, drive, scene

from cosim.dem_soil import DemSoil, WallProximityWarning
from soil import Simulation
from soil.errors import SoilInputError
from soil.neighbours import NeighbourSettings


def soil_in(device, precision, storage):
    """The worlds test's scene (storage grows from 2 slots), reordered at every rebuild."""
    sim = Simulation(*scene(device, precision, 7, storage), neighbours=NeighbourSettings(reorder=True))
    return DemSoil(sim, 1e-4, surface_height=0.02)


@pytest.mark.parametrize("precision", ["mixed", "double"])
def test_both_storage_orders_give_the_same_run_to_the_last_bit(device, precision):
    warnings.simplefilter("ignore", WallProximityWarning)
    runs = {}
    for storage in ("grain", "slot"):
        soil = soil_in(device, precision, storage)
        assert soil.sim.state.slot_major == (storage == "slot")
        rows, rebuilds = drive(soil, 0, STEPS)
        runs[storage] = (soil, rows, rebuilds)
    (grain, rows_g, rebuilds_g), (slot, rows_s, rebuilds_s) = runs["grain"], runs["slot"]
    assert rebuilds_s == rebuilds_g
    # the lists were rebuilt, the storage grew
    assert sum(r[0] for r in rebuilds_g) > 0 and grain.sim.state.capacity > 2
    n = slot.sim.particle_count
    layout = slot.sim.state.layout
    assert layout.neighbours.shape[2] == n and slot.sim.state.pair_tangential.shape[1] == n  # stored per slot
    assert not np.array_equal(layout.order.numpy(), np.arange(n))  # and reordered along the curve
    assert np.array_equal(rows_g, rows_s)
    assert np.array_equal(grain.sim.positions(), slot.sim.positions())
    assert np.array_equal(grain.sim.velocities(), slot.sim.velocities())
    saved_g, saved_s = grain.sim.state_dict(), slot.sim.state_dict()
    for ours, theirs in zip(contacts(saved_g), contacts(saved_s)):
        assert np.array_equal(ours, theirs)
    # a checkpoint of one order continues in the other as it does in its own
    tail = drive(grain, 0, 4, start=STEPS)[0]
    crossed = soil_in(device, precision, "slot")
    crossed.sim.load_state_dict(saved_g)
    assert np.array_equal(drive(crossed, 0, 4, start=STEPS)[0], tail)


def test_an_unknown_storage_order_is_refused(device):
    with pytest.raises(SoilInputError, match="storage must be one of grain, slot"):
        scene(device, "double", 1, storage="column")
