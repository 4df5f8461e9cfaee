"""Worlds (soil.worlds): K copies of a scene in one simulation, each world bit for bit its scene alone.

The worlds differ in summation order (order seed) and in how their wheel moves (one stands still,
so its neighbour list is rebuilt only because the others need it); the contact storage starts
too small, so it grows during the run (for one world, for all); one world leaves early. Every
wrench, every grain and the checkpoint of each world must equal those of the same scene run alone,
at a fixed step and under the PID step control, where each world takes the substeps it takes
alone (the worlds then take different numbers of substeps and reject different ones).
"""

import threading
import warnings

import numpy as np
import pytest
import warp as wp

from cosim.contract import WheelKinematics
from cosim.dem_soil import DemSoil, WallProximityWarning
from soil import GrouserWheel, Material, Simulation, SoilBuilder, StepController
from soil.bed import SavedBed
from soil.errors import SoilInputError
from soil.worlds import Worlds, join_worlds, open_bed_worlds

WHEEL = GrouserWheel(radius=0.02, width=0.012, grouser_count=8, grouser_height=0.002, grouser_thickness=0.0015)
SPEEDS = (0.05, 0.0, 0.08)
"""Forward speed of each world's wheel [m/s] (world 1's stands still, pressed in)."""
SEEDS = (3, 4, 5)
MACRO = 1e-3
STEPS = 24
LEAVES = {2: 12}
"""World 2 is done after 12 macro steps."""


def scene(device, precision, seed, storage="grain", fill=None, youngs_modulus=1e6, wheel=True):
    """Grains in a small box, a grousered wheel above them (finalize's arguments: one world); `fill`
    (a seed): another fill of the same box, its grains of radii 2.7-3.3 mm placed elsewhere."""
    builder = SoilBuilder(gravity=9.81)
    mat = builder.add_material(Material(youngs_modulus=youngs_modulus, restitution=0.3, rolling_friction=0.05))
    builder.add_container((0, 0, 0), (0.07, 0.03, 0.1), mat)
    rng = np.random.default_rng(2 if fill is None else fill)
    grid = np.stack(np.meshgrid(np.arange(10), np.arange(4), np.arange(3), indexing="ij"), -1).reshape(-1, 3)
    radii = 0.003 if fill is None else rng.uniform(0.0027, 0.0033, len(grid))
    builder.add_particles(0.0035 + grid * 0.0068 + rng.uniform(-2e-4, 2e-4, grid.shape), radii, mat)
    if wheel:
        builder.add_wheel(WHEEL, mat)
    return builder.finalize(device, precision, contact_capacity=2, rigid_capacity=1, order_seed=seed, storage=storage)


def kinematics(world, t):
    """World `world`'s wheel presses down into the grains while it rolls at its speed."""
    speed = SPEEDS[world]
    return [
        WheelKinematics(
            np.array([0.02 + speed * t, 0.015, 0.036 - 0.04 * t]),
            np.array([1.0, 0, 0, 0]),
            np.array([speed, 0.0, -0.04]),
            np.array([0.0, speed / 0.02, 0.0]),
        )
    ]


LIST_ALIGNED = ("neighbours", "neighbour_count", "build_position", "pair_touching", "pair_tangential", "pair_rolling")
"""Checkpoint arrays aligned with the neighbour list: a list rebuilt at another time holds other entries out
of contact (compared through `contacts`)."""


def contacts(saved):
    """(grain, partner) of every grain-grain contact in a checkpoint, and their history, sorted."""
    neighbours, touching = saved["state/neighbours"], saved["state/pair_touching"]
    grain, entry = np.nonzero(neighbours >= 0)
    bits = (touching[grain, entry // 32] >> (entry % 32).astype(np.uint32)) & 1
    grain, entry = grain[bits == 1], entry[bits == 1]
    partner = neighbours[grain, entry]
    order = np.lexsort((partner, grain))
    grain, entry, partner = grain[order], entry[order], partner[order]
    return grain, partner, saved["state/pair_tangential"][grain, entry], saved["state/pair_rolling"][grain, entry]


def drive(soil, world, steps, start=0):
    """(wrench rows, (rebuilds, substeps, rejected) per macro step) of `steps` macro steps from macro
    step `start`."""
    rows, rebuilds = [], []
    if start == 0:
        soil.place_wheels(kinematics(world, 0.0))
    for k in range(start, start + steps):
        w = soil.advance((k + 1) * MACRO, kinematics(world, k * MACRO))[0]
        rows.append(np.concatenate([w.force, w.torque, w.force_end, w.torque_end, [w.contact_count, w.work_on_soil]]))
        report = soil.last_report
        rebuilds.append((report.rebuilds, report.steps, report.rejected))
    return np.array(rows), rebuilds


def simulation(parts, step_control):
    """A Simulation of `parts` (finalize's results), with its PID step control when asked: a tolerance
    tight enough that substeps are rejected (Simulation.enable_step_control)."""
    sim = Simulation(*parts)
    if step_control == "pid":
        sim.enable_step_control(StepController(tolerance=2e-4, dt_max=1e-4))
    return sim


@pytest.mark.parametrize(
    "precision, storage, step_control",
    [
        ("mixed", "grain", "fixed"),
        ("double", "grain", "fixed"),
        ("mixed", "slot", "fixed"),
        ("double", "grain", "pid"),
        ("mixed", "slot", "pid"),
    ],
)
def test_each_world_steps_bit_for_bit_as_its_scene_alone(device, precision, storage, step_control):
    warnings.simplefilter("ignore", WallProximityWarning)
    alone = []
    for w, seed in enumerate(SEEDS):
        soil = DemSoil(simulation(scene(device, precision, seed, storage), step_control), 1e-4, surface_height=0.02)
        rows, rebuilds = drive(soil, w, LEAVES.get(w, STEPS))
        alone.append((rows, rebuilds, soil.sim.positions(), soil.sim.velocities(), soil.sim.state_dict()))
        if w == 0:
            continued = drive(soil, w, 4, start=STEPS)[0]

    worlds = Worlds(simulation(join_worlds([scene(device, precision, seed, storage) for seed in SEEDS]), step_control))
    soils = [DemSoil(worlds.world(w), 1e-4, surface_height=0.02) for w in range(len(SEEDS))]
    together: dict = {}

    def run(w):
        try:
            rows, rebuilds = drive(soils[w], w, LEAVES.get(w, STEPS))
            sim = soils[w].sim
            together[w] = (rows, rebuilds, sim.positions(), sim.velocities(), sim.state_dict())
        except BaseException as error:  # noqa: BLE001 - reported below
            together[w] = error
        finally:
            soils[w].sim.leave()

    threads = [threading.Thread(target=run, args=(w,)) for w in range(len(SEEDS))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=600)
    batch_rebuilds = []
    for w in range(len(SEEDS)):
        assert not isinstance(together[w], BaseException), together[w]
        rows, rebuilds, x, v, saved = together[w]
        rows_alone, rebuilds_alone, x_alone, v_alone, saved_alone = alone[w]
        assert np.array_equal(rows, rows_alone), f"world {w}: wrenches differ from its scene alone"
        steps, steps_alone = [r[1:] for r in rebuilds], [r[1:] for r in rebuilds_alone]
        assert steps == steps_alone, f"world {w}: substeps (taken, rejected) differ from its scene alone"
        assert np.array_equal(x, x_alone) and np.array_equal(v, v_alone), f"world {w}: grains differ"
        for key, value in saved_alone.items():
            if key.startswith(("state/", "control/")) and key.split("/")[1] not in LIST_ALIGNED:
                ours = saved[key]
                if key.split("/")[1].startswith("rigid_") and ours.ndim > 1:  # the batch's storage may be wider
                    ours, value = ours[:, : value.shape[1]], value[:, : ours.shape[1]]
                assert np.array_equal(ours, value), f"world {w}: checkpoint {key} differs"
            if key in ("steps", "accepted_steps", "rejected_steps", "forced_steps"):  # the world's own counts
                assert saved[key] == value, f"world {w}: checkpoint {key} differs"
            if key.startswith("step_control/"):  # the world's own controller, its settings and state
                same = np.array_equal(saved[key], value, equal_nan=np.asarray(value).dtype.kind == "f")
                assert same, f"world {w}: checkpoint {key} differs"
        for ours, theirs in zip(contacts(saved), contacts(saved_alone)):
            assert np.array_equal(ours, theirs), f"world {w}: the checkpoint's contacts differ"
        batch_rebuilds.append([r[0] for r in rebuilds])
        assert saved["capacity"] > 2, "the storage grew"
    # a world's checkpoint continues alone as its scene alone does
    resumed = DemSoil(simulation(scene(device, precision, SEEDS[0], storage), "fixed"), 1e-4, surface_height=0.02)
    resumed.sim.load_state_dict(together[0][4])  # with the world's step control, if it had one
    assert np.array_equal(drive(resumed, 0, 4, start=STEPS)[0], continued)
    # the standing wheel's world was rebuilt when it did not need it: the case the design is for
    assert any(b > 0 and a[0] == 0 for b, a in zip(batch_rebuilds[1], alone[1][1]))
    assert worlds.rounds == STEPS
    if step_control == "pid":  # the worlds' controllers chose apart: what the test is for
        # the world that left kept its state (under the PID step control it has no span of its own)
        assert np.array_equal(worlds.world(2).positions(), together[2][2])
        per_world = [[r[1:] for r in a[1]] for a in alone]
        assert any(len({per_world[w][k] for w in range(2)}) > 1 for k in range(STEPS)), (
            "the worlds took the same substeps"
        )
        assert sum(r[2] for a in alone for r in a[1]) > 0, "no substep was rejected"


def settled_fill(device, fill):
    """A bed of another fill (scene's `fill`), fallen 40 ms: its list and contact history saved."""
    sim = Simulation(*scene(device, "double", None, fill=fill, wheel=False))
    sim.run(0.04, 1e-4)
    return SavedBed.from_simulation(sim)


def test_worlds_on_beds_of_their_own_step_bit_for_bit_as_each_alone(device):
    """Replicas over beds: each world opens a bed of its own (other grains, other radii, so another
    largest grain than the batch's, whose skin and cells the batch uses), under an order seed other
    than the bed's, so the saved list's partners are renumbered; each world steps bit for bit as its
    bed alone. A grain sums its contacts in its row's order, so the opened list must list them in the
    order a build does (the batch rebuilds a world's list when another world needs it), and a list
    built with a narrower skin than the batch's is built again at once (else the batch's rebuild test
    would let a contact go unlisted)."""
    warnings.simplefilter("ignore", WallProximityWarning)
    beds = [settled_fill(device, fill) for fill in (11, 12)]
    assert beds[0].radius.max() != beds[1].radius.max()
    wheels = [(WHEEL, beds[0].materials[0])]
    alone = []
    for w, bed in enumerate(beds):
        soil = DemSoil(open_bed_worlds(bed, wheels, [SEEDS[w]], device=device, precision="mixed").world(0), 1e-4, 0.02)
        opened = soil.sim.state_dict()
        neighbours, count = opened["state/neighbours"], opened["state/neighbour_count"]
        for row, n in zip(neighbours, count):  # the opened list lists partners as a build does
            assert np.all(np.diff(row[:n]) > 0)
        assert sum(len(c) for c in contacts(opened)) > 0, "the bed's contact history came along"
        rows, rebuilds = drive(soil, w, STEPS)
        alone.append((rows, rebuilds, soil.sim.positions(), soil.sim.velocities()))
    worlds = open_bed_worlds(beds, wheels, list(SEEDS[:2]), device=device, precision="mixed")
    soils = [DemSoil(worlds.world(w), 1e-4, surface_height=0.02) for w in range(len(beds))]
    together: dict = {}

    def run(w):
        try:
            rows, rebuilds = drive(soils[w], w, STEPS)
            together[w] = (rows, rebuilds, soils[w].sim.positions(), soils[w].sim.velocities())
        except BaseException as error:  # noqa: BLE001 - reported below
            together[w] = error

    threads = [threading.Thread(target=run, args=(w,)) for w in range(len(beds))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=600)
    for w in range(len(beds)):
        assert not isinstance(together[w], BaseException), together[w]
        rows, rebuilds, x, v = together[w]
        assert rows[:, 12].max() > 0, f"world {w}: the wheel touched no grain"  # its contact count
        assert np.array_equal(rows, alone[w][0]), f"world {w}: wrenches differ from its bed alone"
        assert np.array_equal(x, alone[w][2]) and np.array_equal(v, alone[w][3]), f"world {w}: grains differ"


def two_grains(device, radius, gap, speed):
    """A saved bed of two grains `gap` [m] apart closing at 2 x `speed` [m/s], no gravity, its list built
    once (its skin 0.3 x `radius`)."""
    builder = SoilBuilder(gravity=0.0)
    mat = builder.add_material(Material(youngs_modulus=1e6, restitution=0.3))
    builder.add_container((0, 0, 0), (0.05, 0.05, 0.05), mat)
    x = np.array([[0.025 - radius - gap / 2, 0.025, 0.025], [0.025 + radius + gap / 2, 0.025, 0.025]])
    builder.add_particles(x, radius, mat, velocities=np.array([[speed, 0, 0], [-speed, 0, 0]]))
    sim = Simulation(*builder.finalize(device, "double"))
    sim.run(1e-5, 1e-5)
    return SavedBed.from_simulation(sim)


def test_a_world_whose_list_was_built_with_a_narrower_skin_than_the_batch_is_built_again(device):
    """A saved list holds every contact only while its grains move less than half the skin it was built
    with; the batch's rebuild test uses half its own (0.3 x the batch's largest grain). Two 1 mm grains
    0.5 mm apart (their list's skin 0.3 mm: not listed) closing at 20 mm/s, batched with a world of 3 mm
    grains (skin 0.9 mm): alone their list is built again after 0.15 mm each and they collide; in the
    batch the same, bit for bit, where a test against the batch's half skin (0.45 mm) alone would let
    them pass through each other."""
    small, large = two_grains(device, 0.001, 0.0005, 0.01), two_grains(device, 0.003, 0.01, 0.0)
    alone = open_bed_worlds(small, device=device).sim
    alone.run(0.04, 1e-5)
    assert alone.velocities()[0, 0] < 0 < alone.velocities()[1, 0], "alone, the grains bounced"
    batch = open_bed_worlds([large, small], order_seeds=[None, None], device=device)
    batch.sim.run(0.04, 1e-5)
    assert np.array_equal(batch.world(1).velocities(), alone.velocities())
    assert np.array_equal(batch.world(1).positions(), alone.positions())


def test_the_worlds_of_a_batch_are_copies_of_one_scene(device):
    one = scene(device, "double", 1)
    other = SoilBuilder(gravity=9.81)
    other.add_particles(np.array([[0.0, 0.0, 0.01]]), 0.003)
    with pytest.raises(ValueError, match="world 1 differs"):
        join_worlds([one, other.finalize(device, "double")])
    # one pair table serves every world: a world of other materials is refused
    with pytest.raises(ValueError, match="world 1 differs from world 0 in its materials"):
        join_worlds([one, scene(device, "double", 1, youngs_modulus=2e6)])
    # the host-side PID loop decides for one world: worlds take theirs on the device, each its own
    sim = Simulation(*join_worlds([scene(device, "double", 1), scene(device, "double", 2)]))
    with pytest.raises(SoilInputError, match="run_adaptive decides on the host for one world"):
        sim.run_adaptive(1e-3)


def test_a_world_that_diverges_stops_the_batch_and_each_world_keeps_its_last_good_state(device):
    """World 1's wheel is rammed into its grains at 30 m/s: the monitor finds it (in the step or in a
    health check), and both worlds' runs get SimulationDiverged with a last good state of their own grains,
    world 0's marked as found elsewhere."""
    from soil import SimulationDiverged

    warnings.simplefilter("ignore", WallProximityWarning)
    worlds = Worlds(Simulation(*join_worlds([scene(device, "double", seed) for seed in SEEDS[:2]])))
    soils = [DemSoil(worlds.world(w), 1e-4, surface_height=0.02) for w in range(2)]
    outcome: dict = {}

    def ram(t):
        return [WheelKinematics([0.035, 0.015, 0.036 - 30.0 * t], [1.0, 0, 0, 0], [0.0, 0.0, -30.0], [0.0, 0.0, 0.0])]

    def run(w):
        soil = soils[w]
        try:
            soil.place_wheels(kinematics(w, 0.0) if w == 0 else ram(0.0))
            soil.start_health_checks()
            for k in range(40):
                soil.advance((k + 1) * MACRO, kinematics(w, k * MACRO) if w == 0 else ram(k * MACRO))
                soil.check_health()
            outcome[w] = "no divergence"
        except SimulationDiverged as error:
            outcome[w] = error
        finally:
            soil.sim.leave()

    threads = [threading.Thread(target=run, args=(w,)) for w in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=600)
    n = worlds.model.world_size
    for w in range(2):
        assert isinstance(outcome[w], SimulationDiverged), outcome[w]
        assert outcome[w].last_good is not None and outcome[w].last_good["position"].shape == (n, 3)
    assert not np.array_equal(outcome[0].last_good["position"], outcome[1].last_good["position"])
    # world 0's own grains are sound: its run may be resumed alone (world 1's would diverge again)
    assert outcome[0].elsewhere and not outcome[1].elsewhere


def test_a_restore_onto_a_list_without_one_of_its_contacts_is_flagged(device):
    """A world that takes its state back onto a list built at the positions of the substep it threw
    away keeps its contacts' history if the list holds them; a contact the list lacks (a grain moved
    more than the skin in that substep) is flagged (status LOST_HISTORY, HistoryLostWarning on the host)."""
    from soil import status as status_columns
    from soil.state import SoilState

    builder = SoilBuilder(gravity=0.0)
    mat = builder.add_material(Material(youngs_modulus=1e6))
    builder.add_particles(np.array([[0.0, 0.0, 0.0], [0.0059, 0.0, 0.0]]), 0.003, mat)  # 0.1 mm overlap
    sim = Simulation(*builder.finalize(device, "double"))
    sim.advance_to(1e-6, 1e-7)
    assert sim.state.pair_touching.numpy().any(), "the two grains touch"
    every_world = wp.ones(1, dtype=wp.int32, device=device)
    skin = sim.neighbour_list.skin
    for shift, lost in ((0.5 * skin, 0), (3.0 * skin, 1)):
        trial = SoilState.for_model(sim.model, sim.state.capacity, layout=sim.state.layout)
        trial.assign(sim.state)
        x = sim.state.position.numpy()
        x[1, 0] += shift  # the second grain's position in the thrown-away substep
        trial.position.assign(x)
        status = status_columns.make_status(device)
        sim.neighbour_list.build(trial, status)  # the list that substep built, at its positions
        sim.neighbour_list.remap_worlds(sim.state, trial, every_world, status)
        assert status.numpy()[status_columns.LOST_HISTORY] == lost, shift
        assert trial.pair_touching.numpy().any() == (not lost)  # the contact's history carried, or not


def test_the_worlds_api_names_a_bad_index_or_step_and_a_refused_step_changes_nothing(device, tmp_path):
    """A world's index is an integer of the batch's range; a macro step that is refused (a time that is
    no time, a wheel path of the wrong shape, a second request before the first's report is taken) leaves
    the batch as it was: the next, valid, step runs."""
    from soil.errors import ArgumentError, InputError

    worlds = Worlds(Simulation(*join_worlds([scene(device, "double", seed, wheel=False) for seed in SEEDS[:2]])))
    for call in (worlds.leave, worlds.world, worlds.take, worlds.view):
        for bad in (5, -1, 1.0, True, "0"):
            with pytest.raises(ArgumentError, match=rf"world index must be an integer in 0 \.\. 1 .*got {bad!r}"):
                call(bad)
    assert worlds.active == {0, 1}
    for end, dt in ((float("nan"), 1e-4), (0.0, 1e-4), (MACRO, float("inf")), (MACRO, -1.0)):
        with pytest.raises(SoilInputError, match="world 0's macro step"):
            worlds.submit(0, end, dt, False, None)
    with pytest.raises(SoilInputError, match=r"world 0's wheel path's start position \[m\] must be .* shape \(0, 3\)"):
        worlds.submit(0, MACRO, 1e-4, True, (np.zeros((1, 3)), np.zeros((0, 4)), [], [], None))
    # the refused steps left nothing behind: the batch steps as asked
    worlds.submit(0, MACRO, 1e-4, False, None)
    # a second request before the first's report is taken (it replaced the first without a word)
    with pytest.raises(ArgumentError, match="world 0 has asked for a macro step already: take its report"):
        worlds.submit(0, 2 * MACRO, 1e-4, False, None)
    worlds.submit(1, MACRO, 1e-4, False, None)
    with pytest.raises(ArgumentError, match="world 1 has asked for a macro step already"):  # stepped, not taken
        worlds.submit(1, 2 * MACRO, 1e-4, False, None)
    reports = [worlds.take(w) for w in range(2)]
    assert all(r is not None and r.steps == 10 for r in reports) and worlds.sim.time == MACRO
    # a bed that is no file: the project's input error, naming the path
    missing = tmp_path / "no_bed.h5"
    with pytest.raises(InputError, match=f"world 0's bed '{missing}' cannot be read .*bed file not found"):
        open_bed_worlds(missing, order_seeds=[0, 1], device=device)
    with pytest.raises(SoilInputError, match="world 0's bed is int 12: a bed is a bed file's path"):
        open_bed_worlds(12, device=device)


def test_a_world_that_leaves_before_placing_its_wheels_lifts_them_clear_of_its_grains(device):
    """Built, a world's wheel lies where it was added (here in its box, among its grains): a world that
    leaves parked takes it out of reach, at rest, and its grains lie still while the other world steps."""
    worlds = Worlds(Simulation(*join_worlds([scene(device, "double", seed) for seed in SEEDS[:2]])))
    worlds.leave(0, park=True)
    parked = worlds.world(0)
    x, r = parked.positions(), parked.radii()
    reach = float(worlds.model.body_shape.numpy()[0, 5])
    hub = parked.body_positions()[0]
    assert hub[2] > x[:, 2].max() + reach and np.all(np.linalg.norm(x - hub, axis=1) > reach + r)
    assert not worlds.sim.control.body_velocity_host[0].any()
    before = parked.positions()
    for k in range(5):
        worlds.advance_to(1, (k + 1) * MACRO, 1e-4, False, None)
    assert np.abs(parked.positions() - before).max() < 1e-3  # settling a little, no wheel among them
    assert np.abs(parked.velocities()).max() < 0.5
