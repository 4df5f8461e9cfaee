"""The per-world reduction tree (soil.reduction): every grain counted once, each world folded as it is
alone, and the wrench on a wall equal to the sum of its contacts' Hertz forces."""

import math

import numpy as np
import pytest
import warp as wp

from helpers import effective_modulus
from soil import Material, Simulation, SoilBuilder
from soil.reduction import FAN, LEAF, WorldTree, level_rows

WORLD_SIZES = (1, LEAF * FAN, LEAF * FAN + 1, 40_000)
"""Grains per world: one leaf; the most one level holds; one more (a fold); two folds."""


def folded(tree: WorldTree, leaves: np.ndarray, summed: int) -> np.ndarray:
    tree.leaves.assign(leaves)
    tree.fold(summed)
    return tree.last.numpy()


@pytest.mark.parametrize("world_size", WORLD_SIZES)
def test_the_tree_counts_every_row_once_within_its_world(device, world_size):
    """Integer-valued rows (sums exact in float64): a world's last rows add up to the sum of its
    leaves and hold their maximum, whatever the number of levels."""
    worlds = 3
    rows = level_rows(world_size)
    assert rows[-1] <= FAN and len(rows) == 1 + (world_size > LEAF * FAN) + (world_size > LEAF * FAN * FAN)
    tree = WorldTree(worlds, world_size, 2, wp.float64, device)
    leaves = np.random.default_rng(world_size).integers(-1000, 1000, size=(worlds * rows[0], 2)).astype(np.float64)
    last = folded(tree, leaves, summed=1).reshape(worlds, rows[-1], 2)
    by_world = leaves.reshape(worlds, rows[0], 2)
    np.testing.assert_array_equal(last[:, :, 0].sum(axis=1), by_world[:, :, 0].sum(axis=1))
    np.testing.assert_array_equal(last[:, :, 1].max(axis=1), by_world[:, :, 1].max(axis=1))


def test_a_world_folds_as_it_does_alone(device):
    """Rows whose sums round: world 1 of three folds to the same bits as the same rows alone."""
    world_size = 40_000
    rows = level_rows(world_size)[0]
    leaves = np.random.default_rng(7).normal(size=(3 * rows, 1))
    batched = folded(WorldTree(3, world_size, 1, wp.float64, device), leaves, summed=1)
    alone = folded(WorldTree(1, world_size, 1, wp.float64, device), leaves[rows : 2 * rows], summed=1)
    last = len(alone)
    np.testing.assert_array_equal(batched[last : 2 * last], alone)


def test_a_floor_carries_the_hertz_force_of_every_grain_on_it(device):
    """48 x 48 grains apart from one another, each pressed into the floor by the same overlap: the
    floor's force is minus the sum of the grains' forces (to rounding) and 2,304 times one grain's
    Hertz force 4/3 E* sqrt(R) delta^1.5 (to the material constants' float32 rounding), its contact
    count 2,304, its torque the sum of r x F about its point; the side walls carry nothing.
    2,304 grains make 72 leaves: the sum passes one fold."""
    radius, overlap, pitch, side = 2e-3, 1e-6, 5e-3, 48
    material = Material(youngs_modulus=1e7, poisson_ratio=0.3, density=2600.0, restitution=0.5)
    builder = SoilBuilder(gravity=9.81)
    mat = builder.add_material(material)
    walls = builder.add_container((0, 0, 0), (side * pitch, side * pitch, 0.05), mat)
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side), indexing="ij"), -1).reshape(-1, 2)
    positions = np.column_stack([(grid + 0.5) * pitch, np.full(len(grid), radius - overlap)])
    builder.add_particles(positions, radius, mat)
    assert level_rows(len(positions)) == [72, 3]
    model, state, control = builder.finalize(device, "double")
    sim = Simulation(model, state, control)
    sim.refresh_forces()
    force, torque, contacts = sim.boundary_wrenches()
    one = 4.0 / 3.0 * effective_modulus(material, material) * math.sqrt(radius) * overlap**1.5
    floor = walls[0]
    assert contacts[floor] == len(positions) and not np.any(np.delete(contacts, floor))
    grain_forces = sim.forces()
    np.testing.assert_allclose(force[floor], -grain_forces.sum(axis=0), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(force[floor], [0.0, 0.0, -len(positions) * one], rtol=1e-6, atol=1e-15)
    contact_points = sim.positions() - [0.0, 0.0, radius - overlap]
    expected = np.cross(contact_points, -grain_forces).sum(axis=0)
    np.testing.assert_allclose(torque[floor], expected, rtol=1e-10, atol=1e-12 * np.abs(expected).max())
    assert not np.any(np.delete(force, floor, axis=0))


def test_pid_steps_whose_sums_pass_a_fold_replay_from_their_graph_as_launched(device):
    """1,200 grains (38 leaves: the norm and wrench sums pass a fold) under the PID step control: the
    captured substep loop (the folds inside its conditional nodes) gives the launched run's grains
    and floor wrench bit for bit."""
    from benchmarks import beds
    from soil.integrator import JoltBeeman

    positions, radii, box_hi = beds.lattice_bed(1200, "shallow")
    assert len(level_rows(len(radii))) == 2
    runs = []
    for capture in (True, False):
        sim = beds.build(positions, radii, box_hi, device, "double", capture=capture)
        sim = Simulation(sim.model, sim.state, sim.control, integrator=JoltBeeman(), capture=capture)
        sim.enable_step_control()
        steps = sum(sim.macro_step_adaptive(6e-5).steps for _ in range(3))
        assert sim.capture == capture and steps > 3
        runs.append((sim.positions(), *sim.boundary_wrenches()))
    for captured, launched in zip(*runs):
        np.testing.assert_array_equal(captured, launched)
    assert runs[0][3][0] > 0  # grains on the floor


def test_the_neighbour_grid_spans_the_grains_box_found_over_the_tree(device):
    """2,000 grains at random (63 leaves: the box's maxima pass a fold): the grid of the list's build
    starts at the grains' lower corner and records their upper corner, exactly (maxima are exact)."""
    rng = np.random.default_rng(3)
    positions = rng.uniform(0.01, 0.3, size=(2000, 3)) * [1.0, 0.5, 0.2]
    builder = SoilBuilder(gravity=9.81)
    mat = builder.add_material(Material(youngs_modulus=1e6))
    builder.add_particles(positions, 1e-4, mat)
    assert level_rows(len(positions)) == [63, 2]
    model, state, control = builder.finalize(device, "double")
    sim = Simulation(model, state, control)
    grid = sim.neighbour_list.grid.numpy()
    np.testing.assert_array_equal(grid[:3], positions.min(axis=0))
    np.testing.assert_array_equal(grid[6:], positions.max(axis=0))
