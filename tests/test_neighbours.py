"""The Verlet neighbour list, the storage order and the macro step against brute force and
against themselves: exact contact sets, bitwise repeats, an overflow redone bitwise."""

import warnings

import numpy as np
import pytest
from scipy.spatial import cKDTree

from soil import ContactLaw, Material, NeighbourSettings, Simulation, SoilBuilder

SIZE = 0.05  # box side [m]


def rain(
    device,
    n_side=7,
    skin=None,
    reorder=None,
    capture=True,
    capacity=16,
    rigid_capacity=4,
    seed=0,
    precision="double",
    law=None,
):
    """n_side^3 grains of radii 1.5 .. 4 mm (a size ratio of 2.7) thrown about in a closed box."""
    rng = np.random.default_rng(seed)
    grid = np.stack(np.meshgrid(*[np.arange(n_side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    pitch = SIZE / n_side
    positions = (grid + 0.5) * pitch + rng.uniform(-0.05, 0.05, grid.shape) * pitch
    radii = rng.uniform(1.5e-3, 4e-3, len(grid))
    builder = SoilBuilder(gravity=9.81)
    mat = builder.add_material(Material(youngs_modulus=1e6, restitution=0.6, rolling_friction=0.05))
    builder.add_container((0, 0, 0), (SIZE, SIZE, SIZE), mat, open_top=False)
    builder.add_particles(positions, radii, mat, velocities=rng.normal(0, 0.4, grid.shape))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a few grains start pressed together: on purpose
        model, state, control = builder.finalize(
            device, precision, contact_capacity=capacity, rigid_capacity=rigid_capacity, law=law
        )
    return Simulation(model, state, control, neighbours=NeighbourSettings(skin=skin, reorder=reorder), capture=capture)


def brute_force_contacts(sim):
    """Touching grain pairs {(i, j)} and per-grain wall contacts, from positions in float64."""
    x = sim.positions()
    r = sim.model.radius_numpy()
    pairs = cKDTree(x).query_pairs(2 * r.max(), output_type="ndarray")
    touching = np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1) < r[pairs[:, 0]] + r[pairs[:, 1]]
    walls = ((x - r[:, None] < 0) | (x + r[:, None] > SIZE)).sum(axis=1)
    return {tuple(p) for p in pairs[touching]}, walls


def listed_contacts(sim):
    """Touching pairs {(i, j)}, i < j, as the state records them, each seen from both grains."""
    data = sim.state.to_numpy()
    seen = set()
    for i in range(sim.model.particle_count):
        for k in range(int(data["neighbour_count"][i])):
            if data["pair_touching"][i, k // 32] >> np.uint32(k % 32) & np.uint32(1):
                seen.add((i, int(data["neighbours"][i, k])))
    mirrored = {(j, i) for i, j in seen}
    assert seen == mirrored, "each contact is kept by both of its grains"
    return {(i, j) for i, j in seen if i < j}, data


@pytest.mark.parametrize("skin", [1e-4, None, 4e-3])
def test_the_list_finds_exactly_the_contacts_of_brute_force(device, skin):
    """After every macro step (grains flying, colliding, rebuilding, reordered in memory), the
    contacts the kernels evaluated are exactly the overlapping pairs of a brute-force search,
    and every list row holds exactly the grains within r_i + r_j + skin of its build."""
    sim = rain(device, skin=skin, reorder=True)
    rebuilds = 0
    for _ in range(6):
        report = sim.macro_step(40, 2e-5)
        rebuilds += report.rebuilds
        expected, walls = brute_force_contacts(sim)
        found, data = listed_contacts(sim)
        assert found == expected
        pair_count = np.bincount(np.array(sorted(found)).ravel(), minlength=sim.model.particle_count)
        np.testing.assert_array_equal(sim.contact_counts(), pair_count + walls)
        # the rows against brute force at the build positions
        built = data["build_position"]
        r = sim.model.radius_numpy()
        reach = 2 * r.max() + sim.neighbour_list.skin
        candidates = cKDTree(built).query_pairs(reach, output_type="ndarray")
        gap = np.linalg.norm(built[candidates[:, 0]] - built[candidates[:, 1]], axis=1)
        within = gap < r[candidates[:, 0]] + r[candidates[:, 1]] + sim.neighbour_list.skin
        rows = {(i, int(j)) for i in range(len(r)) for j in data["neighbours"][i, : data["neighbour_count"][i]]}
        assert rows == {tuple(p) for p in candidates[within]} | {tuple(p[::-1]) for p in candidates[within]}
        assert all(np.all(np.diff(data["neighbours"][i, : data["neighbour_count"][i]]) > 0) for i in range(len(r)))
    assert rebuilds > (5 if skin == 1e-4 else 0), "the list was rebuilt along the way"


def test_runs_repeat_bitwise_whatever_the_storage_order_and_capture(device):
    """The same run four ways (grains reordered in memory or not, steps replayed from captured
    graphs or launched one by one): bit for bit the same grains and wall forces."""
    results = []
    for reorder, capture in ((True, True), (True, True), (False, True), (True, False)):
        sim = rain(device, skin=5e-4, reorder=reorder, capture=capture)
        rebuilds = sum(sim.macro_step(50, 2e-5).rebuilds for _ in range(5))
        assert rebuilds >= 3
        results.append((sim.positions(), sim.velocities(), sim.angular_velocities(), sim.boundary_wrenches()[0]))
    reference = results[0]
    for other in results[1:]:
        for a, b in zip(reference, other):
            np.testing.assert_array_equal(a, b)


TWISTING = ContactLaw(rolling=True, twisting=True)
"""Rolling and twisting resistance: the spin history then has a 4th component (the twist)."""


@pytest.mark.parametrize("law", [None, TWISTING], ids=["default", "twisting"])
def test_an_overflow_is_redone_bitwise_equal_to_ample_storage(device, law):
    """Sparse grains (one neighbour slot and one wall slot per grain are enough at the start)
    fall and pile up: the storage overflows inside macro steps, grows, and each such macro step
    is redone from its start; the result is bit for bit that of ample storage from the start."""
    tight = rain(device, n_side=4, reorder=True, capacity=1, rigid_capacity=1, law=law)
    assert tight.state.capacity == 1 and tight.state.rigid_capacity == 1
    ample = rain(device, n_side=4, reorder=True, capacity=48, rigid_capacity=6, law=law)
    redone = 0
    for _ in range(10):
        redone += tight.macro_step(500, 2e-5).redone
        assert ample.macro_step(500, 2e-5).redone == 0
    assert redone >= 1 and tight.state.capacity > 1 and tight.state.rigid_capacity > 1
    np.testing.assert_array_equal(tight.positions(), ample.positions())
    np.testing.assert_array_equal(tight.velocities(), ample.velocities())
    for a, b in zip(tight.boundary_wrenches(), ample.boundary_wrenches()):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("law", [None, TWISTING], ids=["default", "twisting"])
def test_a_checkpoint_continues_bitwise_in_another_storage_order(device, law):
    """state_dict() is in model order: a run saved with reordering on continues, loaded into a
    simulation that never reorders, bit for bit as the original."""
    reference = rain(device, skin=5e-4, reorder=True, law=law)
    reference.macro_step(100, 2e-5)
    saved = reference.state_dict()
    reference.macro_step(100, 2e-5)
    resumed = rain(device, skin=5e-4, reorder=False, law=law)
    resumed.load_state_dict(saved)
    resumed.macro_step(100, 2e-5)
    np.testing.assert_array_equal(resumed.positions(), reference.positions())
    np.testing.assert_array_equal(resumed.angular_velocities(), reference.angular_velocities())
    assert not np.array_equal(reference.state.layout.order.numpy(), np.arange(reference.model.particle_count))


LATTICE = (2e-3, 2e-3 * (1 - 1e-3) * 2, (6, 6, 3))
"""The standing lattice: grain radius [m], pitch [m] (0.1 % less than a diameter), grains per axis."""


def standing_lattice(device, wheels=()):
    """Grains on a simple cubic lattice (LATTICE), pressed 0.1 % together in a box they fill,
    at Phobos gravity: a bed that stands still from the first step. Each wheel of `wheels` is
    (shape, hub [m]), posed after the Simulation is made, as a user placing a wheel would.
    Returns the simulation and the box's upper corner [m]."""
    radius, pitch, n = LATTICE
    grid = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1).reshape(-1, 3)
    box = [n[0] * pitch, n[1] * pitch, 0.1]
    builder = SoilBuilder(gravity="phobos")
    mat = builder.add_material(Material(youngs_modulus=1e6, restitution=0.3))
    builder.add_container((0, 0, 0), box, mat)
    builder.add_particles(0.5 * pitch + grid * pitch, radius, mat)
    for shape, _ in wheels:
        builder.add_wheel(shape, mat)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the lattice starts pressed: on purpose
        model, state, control = builder.finalize(device, "double")
    sim = Simulation(model, state, control)
    for b, (_, hub) in enumerate(wheels):
        sim.control.set_body_motion(b, hub, (1, 0, 0, 0), (0, 0, 0), (0, 0, 0))
    return sim, np.array(box)


def test_a_parked_or_resting_wheel_rebuilds_the_list_no_more_often_than_no_wheel(device):
    """A standing bed with a wheel resting on it (its bottom grouser pressed 10 um into a top
    grain) and a wheel parked far away keeps its neighbour list as long as the same bed
    without wheels: wheels that do not stir the grains do not make the list stale. (A wheel
    sat at the origin until posed, inside the bed's corner, when the Simulation computed its
    first forces: the first step blew the corner apart and the list was rebuilt at every step.)"""
    from soil import GrouserWheel

    wheel = GrouserWheel(radius=0.012, width=0.01, grouser_count=8, grouser_height=0.001, grouser_thickness=0.001)
    radius, pitch, n = LATTICE
    plain, box = standing_lattice(device)
    top = (n[2] - 0.5) * pitch + radius
    hub = (2.5 * pitch, 0.5 * box[1], top + wheel.outer_radius - 1e-5)  # above the third column of grains
    wheeled, _ = standing_lattice(device, [(wheel, hub), (wheel, (10.0, 10.0, 10.0))])
    dt = 2e-5
    rebuilds = {"plain": 0, "wheeled": 0}
    for _ in range(5):
        rebuilds["plain"] += plain.macro_step(20, dt).rebuilds
        report = wheeled.macro_step(20, dt)
        rebuilds["wheeled"] += report.rebuilds
    assert rebuilds["wheeled"] <= rebuilds["plain"], rebuilds
    assert report.body_contacts[0] > 0 and report.body_contacts[1] == 0, "one wheel rests on the bed, one is away"
    # the grains stand: none moved more than the skin's half (the list's own criterion)
    moved = np.linalg.norm(wheeled.positions() - plain.positions(), axis=1)
    assert moved.max() < 0.5 * wheeled.neighbour_list.skin


@pytest.mark.parametrize("order_seed", [None, 5])
def test_a_bed_opened_under_an_order_seed_keeps_every_contact_history_through_its_rebuild(device, order_seed):
    """A build lists a grain's partners in model-index order and carries the history of the old list
    into the new one in one merge pass over both rows. A bed opened under an order seed renumbers
    its grains, so the opened list must list them in that order too: else the first rebuild drops
    the tangential springs of the contacts its merge passes over (the settled bed then loses its
    static friction at that instant and slides). Rebuilt at once, every contact keeps its history."""
    from soil.bed import SavedBed, open_bed
    from soil.state import UNBUILT

    settling = rain(device, n_side=5)
    settling.run(0.3, 1e-4)
    sim = open_bed(SavedBed.from_simulation(settling), device=device, order_seed=order_seed)
    before, data = listed_contacts(sim)
    assert len(before) > 50
    springs = {}
    for i in range(sim.model.particle_count):
        for k in range(int(data["neighbour_count"][i])):
            springs[(i, int(data["neighbours"][i, k]))] = data["pair_tangential"][i, k]
    saved = sim.state_dict()
    saved["state/build_position"] = np.full_like(saved["state/build_position"], UNBUILT)
    sim.load_state_dict(saved)  # the list to be built again at the next step
    sim.step(1e-12)
    after, data = listed_contacts(sim)
    assert after == before
    for i in range(sim.model.particle_count):
        for k in range(int(data["neighbour_count"][i])):
            pair = (i, int(data["neighbours"][i, k]))
            if min(pair) == pair[0] and pair in before:
                np.testing.assert_allclose(data["pair_tangential"][i, k], springs[pair], rtol=0.01)


def test_a_start_state_of_positions_and_an_empty_list_opens_under_an_order_seed(device):
    """SoilBuilder.start_from takes a state of positions and a neighbour list alone (the rest starts
    fresh): its rows are put in partner order without the history it does not have."""
    builder = SoilBuilder(gravity=0.0)
    mat = builder.add_material(Material(youngs_modulus=1e6))
    positions = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.02, 0.0, 0.0]])
    builder.add_particles(positions, 0.004, mat)
    neighbours = np.array([[1, -1], [2, 0], [1, -1]], dtype=np.int32)  # row 1 descends
    builder.start_from({"position": positions, "neighbours": neighbours})
    sim = Simulation(*builder.finalize(device, "double", order_seed=3))
    sim.step(1e-6)
    assert np.isfinite(sim.positions()).all()
