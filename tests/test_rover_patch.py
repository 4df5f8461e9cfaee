"""The moving soil patch (soil.patch): a move keeps the grains that stay and their contact history,
the mass placed and removed is booked, a rover drives many patch lengths with a bounded grain count,
and the wheel feels the same soil as on a long static bed."""

import json
import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from cosim.beds import patch_grain_count, settled_bed
from cosim.launch import run_plan
from cosim.output import read_series
from cosim.plan import load_plan
from cosim.single_wheel import PHASE_DRIVING
from helpers import assert_every_number_has_its_unit
from rover_helpers import MOON, RIG_BALLAST, RIG_WHEEL, write_rig

pytest.importorskip("mujoco")

PATCH = """
[patch]
length = {size}
width = {size}
band = {band}
clearance = {band}
"""
FINE = {"length": 0.1, "width": 0.1, "extra": PATCH.format(size=0.12, band=0.0081)}
"""A tile cut from a 10 x 10 cm bed of 3.5 mm grains, a 12 cm window, a band and a clearance of one largest
grain diameter."""
COARSE = {"length": 0.1, "width": 0.1, "radius": 0.005, "extra": PATCH.format(size=0.12, band=0.0115)}
"""The same with 5 mm grains (fewer grains, longer steps: the long drive)."""


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("patch")


@pytest.fixture(scope="module")
def tile(folder):
    """A settled 10 x 10 cm bed of the tests' soil, the tile (cosim.beds caches it in `folder`)."""
    plan = load_plan(write_rig(folder, name="tile", **FINE))
    return plan, settled_bed(plan, str(folder / "tile_bed"))


@pytest.fixture(scope="module")
def coarse_tile(folder):
    plan = load_plan(write_rig(folder, name="coarse_tile", **COARSE))
    return plan, settled_bed(plan, str(folder / "coarse_tile_bed"))


def test_a_move_keeps_the_grains_that_stay_and_their_contact_history(tile):
    """Move the window of a soil at rest: the grains far from every change feel the same force before
    and after (to rounding: the summation order changes with the grain count), which needs every
    contact partner renumbered and every history slot kept; the mass is booked exactly; placed grains
    press no deeper into the ones that stay than grains of the tile into each other."""
    from soil.patch import SoilPatch, Tile
    from soil.precision import get_precision

    plan, bed = tile
    spec = plan.bed.spec
    tile_grains = Tile.load(bed.path, (spec.length, spec.width), plan.precision, plan.patch.tile_margin)
    wheel = plan.wheels[0]
    patch = SoilPatch(
        tile_grains,
        0.15,
        0.12,
        0.008,
        0.01,
        [(wheel.shape, wheel.material)],
        plan.gravity,
        "cpu",
        plan.precision,
        plan.law,
    )
    sim = patch.start((0.0, 0.0))
    sim.control.set_body_motion(0, (0.0, 0.0, 0.2), (1.0, 0.0, 0.0, 0.0))  # the wheel far above the soil
    sim.refresh_forces()
    sim.run(0.05, plan.dt)  # the grains settle into the lattice's seams: histories develop
    sim.refresh_forces()
    before_ids, before_x = patch.ids.copy(), sim.positions()
    before_force, before_frozen = sim.state.force.numpy().copy(), patch.frozen.copy()
    moved = patch.recentre(sim, (0.031, 0.013))
    assert moved.model.particle_count == patch.particle_count != sim.model.particle_count

    books = patch.books()
    assert books["soil_mass"] == pytest.approx(
        books["mass_initial"] + books["mass_added"] - books["mass_removed"], rel=1e-14
    )
    assert float(np.sum(moved.model.mass_numpy())) == pytest.approx(books["soil_mass"], rel=1e-12)
    assert books["mass_added"] > 0 and books["mass_removed"] > 0

    common, i0, i1 = np.intersect1d(before_ids, patch.ids, return_indices=True)
    x1 = moved.positions()
    gone = np.setdiff1d(np.arange(len(before_ids)), i0)
    new = np.setdiff1d(np.arange(len(patch.ids)), i1)
    refrozen = i1[before_frozen[i0] != patch.frozen[i1]]
    changed = np.concatenate([before_x[gone], x1[new], x1[refrozen], x1[patch.frozen]])
    distance, _ = cKDTree(changed).query(x1[i1])
    far = (distance > 4 * 2 * spec.radius_mean * (1 + spec.radius_spread)) & ~patch.frozen[i1]
    assert far.sum() > 50
    force_after = moved.state.force.numpy()[i1][far]
    scale = np.abs(before_force[i0][far]).max()
    # the history is stored in the precision's `mid` type (float32 in mixed): a move rewrites it, so
    # the forces agree to that type's rounding of the springs (a lost slot would be off by O(scale))
    stored = np.finfo(get_precision(plan.precision).np_mid).eps
    np.testing.assert_allclose(force_after, before_force[i0][far], rtol=0, atol=max(1e-12, 4 * stored) * scale)

    def deepest(x, r, pairs_from=None):
        pairs = cKDTree(x).query_pairs(2.5 * r.max(), output_type="ndarray")
        if pairs_from is not None:
            pairs = pairs[np.isin(pairs[:, 0], pairs_from) ^ np.isin(pairs[:, 1], pairs_from)]
        gap = np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1) - r[pairs[:, 0]] - r[pairs[:, 1]]
        return -gap.min()

    tile_overlap = deepest(tile_grains.state["position"], tile_grains.radius.astype(float))
    assert deepest(x1, moved.model.radius_numpy(), pairs_from=new) <= 1.01 * tile_overlap


def test_a_rover_drives_five_patch_lengths_on_a_bounded_patch(folder, coarse_tile):
    """A one-wheel rover turned 30 deg off the x axis (the window moves in x and in y) drives more than
    five window lengths. The grain count stays within 25 % of the first window's (the lattice's grain
    density times the window area, up to the grains along its edges) while more than four windows of
    soil are placed and removed; the books hold at every step; the soil carries the wheel's load all
    the way: the mean normal force over the drive is (ballast + wheel) g within 4 batch standard errors
    and 2 % (a fixed-point tolerance for the rig's O(H) coupling error); the wheel touches the soil
    at more than 90 % of the steps (it hops a little at Fr = 0.2: measured 94.6 % with the passive
    stick/slip switch, 95-97 % before) and never sinks a radius deep."""
    _, bed = coarse_tile
    scene = write_rig(folder, name="long_drive", heading=30.0, speed=4.0, duration=12.0, **COARSE)
    plan = load_plan(scene, [f'bed.bed_file="{bed.path}"'])
    result = run_plan(plan, str(folder / "long_drive"))
    s = read_series(folder / "long_drive" / "results.h5")
    summary = result.summary
    driving = s["phase"] == PHASE_DRIVING
    position = s["rover_position"][driving]
    advance = position[-1] - position[0]
    assert np.linalg.norm(advance[:2]) > 5 * plan.patch.length, summary["travel"]
    assert advance[0] > 0 and advance[1] > 0  # along its heading, in x and y

    count = s["soil_particle_count"]
    first = count[0]
    assert count.max() <= 1.25 * first and count.min() >= 0.75 * first
    # the memory check counts the window's grains at the bed's grains per area (cosim.beds)
    from soil.bed import read_bed_header

    estimated = patch_grain_count(plan, read_bed_header(bed.path)["particle_count"])
    assert 0.8 * count.max() <= estimated <= 1.25 * count.max(), (estimated, count.max())
    assert summary["soil_mass_added"] > 4 * summary["soil_mass_initial"]
    assert_every_number_has_its_unit(summary)  # a rover's and a moving patch's numbers too
    assert summary["patch_moves"] >= 5 * plan.patch.length / plan.patch.recentre_distance
    booked = summary["soil_mass_initial"] + s["soil_mass_added"] - s["soil_mass_removed"]
    np.testing.assert_allclose(s["soil_mass"], booked, rtol=1e-12)

    normal = s["normal_force"][driving, 0]
    weight = (RIG_BALLAST + RIG_WHEEL) * MOON
    batches = normal[: len(normal) // 10 * 10].reshape(10, -1).mean(axis=1)
    sem = batches.std(ddof=1) / math.sqrt(10)
    assert abs(normal.mean() - weight) < 4 * sem + 0.02 * weight, (normal.mean(), weight, sem)
    assert np.mean(s["contact_count"][driving, 0] > 0) > 0.9  # it hops a little at this speed (Fr 0.2)
    assert s["sinkage"][driving, 0].max() < 0.02


def _replicas(folder, name, bed, seeds=(0, 1, 2), **settings):
    out = []
    for seed in seeds:
        scene = write_rig(folder, name=name, duration=2.0, **settings)
        plan = load_plan(scene, [f'bed.bed_file="{bed}"', f"run.order_seed={seed}"])
        out.append(run_plan(plan, str(folder / f"{name}_{seed}")).summary)
    return out


def test_the_wheel_feels_the_same_soil_on_the_patch_as_on_a_long_bed(folder, coarse_tile):
    """The same rig on the moving patch (tiles cut from a 10 x 10 cm bed, a 12 cm window, 5 mm grains) and on a
    20 cm static bed of the same grains whose side walls are where the patch's frozen band is, driven 2 s:
    steady-state wheel load and sinkage agree within the scatter of summation-order replicas
    (|difference of the means| <= 3 standard errors of that difference from 3 + 3 replicas) plus what a
    user cannot tell apart (the floors of cosim.study's replica criterion: a quarter grain radius of
    sinkage; for the load 2 % of the weight: a wheel crossing a seam of the tiles sinks a little faster
    for a while, measured 1.3 %); the load is the rig's weight within 3 % on both."""
    _, tile_bed = coarse_tile
    width = 0.12 - 2 * 0.0115
    long_plan = load_plan(write_rig(folder, name="long_bed", length=0.2, width=width, radius=0.005))
    long_bed = settled_bed(long_plan, str(folder / "long_bed_bed")).path
    on_patch = _replicas(folder, "on_patch", tile_bed.path, **COARSE)
    on_bed = _replicas(folder, "on_bed", long_bed, length=0.2, width=width, radius=0.005)
    weight = (RIG_BALLAST + RIG_WHEEL) * MOON
    report = {}
    for name, floor in (("normal_force", 0.02 * weight), ("sinkage", 0.25 * 0.005)):
        a = np.array([r[name] for r in on_patch])
        b = np.array([r[name] for r in on_bed])
        error = math.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
        report[name] = (a.mean(), b.mean(), error)
        assert abs(a.mean() - b.mean()) <= 3 * error + floor, json.dumps(report)
    assert report["normal_force"][0] == pytest.approx(weight, rel=0.03)
    assert report["normal_force"][1] == pytest.approx(weight, rel=0.03)
