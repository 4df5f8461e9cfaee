"""Mixed precision's layout (docs/physics.md section 3): float64 positions and velocities, float32
spins, torques and contact history; fewer bytes than double, the milli-g physics of double."""

import math

import numpy as np
import pytest
from test_stick_slip import PHOBOS, SQUEEZE, squeezed_sphere, tilt, tilted_block

from soil import ContactLaw, Material, Simulation, SoilBuilder
from soil.bed import BedSpec, build_bed

HI = ("position", "velocity", "force", "force_previous", "body_force", "body_torque", "boundary_force")
"""State arrays kept in float64 in mixed: rounding there would shift a milli-g overlap or velocity."""
MID = ("angular_velocity", "torque", "torque_previous", "pair_tangential", "pair_rolling", "rigid_tangential")
"""State arrays stored in float32 in mixed (the error analysis of docs/physics.md section 3)."""


def small_bed(precision, rolling=True, capacity=16):
    """A 616-grain bed in a box at lunar gravity, the divergence monitor armed: a Simulation."""
    spec = BedSpec(length=0.06, width=0.04, depth=0.03, radius_mean=0.002)
    builder = build_bed(spec, "moon")
    model, state, control = builder.finalize(
        device="cpu", precision=precision, law=ContactLaw(rolling=rolling), contact_capacity=capacity
    )
    sim = Simulation(model, state, control)
    sim.monitor.arm(sim)
    return sim


def scalar_type(array) -> type:
    return np.dtype(array.numpy().dtype).type


@pytest.mark.parametrize("rolling", [True, False], ids=["rolling", "no-rolling"])
def test_mixed_takes_at_most_three_quarters_of_the_bytes_of_double(rolling):
    """Measured on the allocated arrays (Simulation.bytes_per_grain), not from soil.memory's constants."""
    measured = {p: small_bed(p, rolling).bytes_per_grain()["total"] for p in ("single", "mixed", "double")}
    assert measured["mixed"] <= 0.75 * measured["double"], measured
    assert measured["single"] < measured["mixed"], measured


@pytest.mark.parametrize("precision", ["single", "mixed", "double"])
def test_each_precision_stores_what_its_error_analysis_allows(precision):
    sim = small_bed(precision)
    wide = np.float32 if precision == "single" else np.float64
    narrow = np.float64 if precision == "double" else np.float32
    for name in HI:
        assert scalar_type(getattr(sim.state, name)) is wide, name
    for name in (*MID, "rigid_rolling"):
        assert scalar_type(getattr(sim.state, name)) is narrow, name
    assert scalar_type(sim.state.layout.build_position) is wide


def test_a_mixed_state_with_float64_history_loads_and_continues():
    """A checkpoint or bed written while mixed kept its history in float64 loads: arrays are converted."""
    sim = small_bed("mixed")
    sim.run(0.2, 2e-4)
    data = sim.state_dict()
    assert np.count_nonzero(data["state/pair_tangential"]) > 0, "the bed must carry contact history"
    wide = {k: (v.astype(np.float64) if v.dtype == np.float32 else v) for k, v in data.items()}
    reference = small_bed("mixed")
    reference.load_state_dict(data)
    reference.run(5 * 2e-4, 2e-4)
    loaded = small_bed("mixed")
    loaded.load_state_dict(wide)
    assert scalar_type(loaded.state.pair_tangential) is np.float32
    loaded.run(5 * 2e-4, 2e-4)
    np.testing.assert_array_equal(loaded.positions(), reference.positions())


@pytest.mark.parametrize("partner", ["wall", "grain"])
def test_mixed_squeezed_sphere_at_phobos_comes_to_rest_carrying_half_its_weight_each_side(partner):
    """test_stick_slip's squeeze at Phobos gravity with the history in float32: stick must hold
    a grain whose tangential springs are stretched by nanometres."""
    stick_speed = 1e-4
    case = SQUEEZE[PHOBOS]
    sim, mass = squeezed_sphere(partner, PHOBOS, stick_speed, nudge=1e-3, precision="mixed")
    sim.run(case["duration"], case["dt"])
    assert np.linalg.norm(sim.velocities()[-1]) < 1e-3 * stick_speed
    assert np.linalg.norm(sim.angular_velocities()[-1]) * case["radius"] < 1e-3 * stick_speed
    if partner == "wall":
        force, _, _ = sim.boundary_wrenches()
        carried = -force[:, 2]
    else:
        carried = -sim.forces()[:2, 2]
    np.testing.assert_allclose(carried, mass * PHOBOS / 2, rtol=0.01)


def test_the_stiff_block_at_phobos_sticks_and_slides_in_mixed_as_in_double():
    """The precision experiment's stiff case (E = 1e8 Pa, not adapted to milli-g) in one contact: a
    block at Phobos gravity, its Hertz overlap 12 nm and its tangential spring 5 nm.
    Below the stick angle the float32 spring holds it as double's does; above, it slides at the
    Coulomb rate. Mixed's spring equals double's to float32 rounding, far below what the physics
    resolves."""
    stick_speed, stiff = 1e-4, 1e8
    duration = 0.05 * math.sqrt(9.81 / PHOBOS)
    springs = {}
    for precision in ("double", "mixed"):
        sim, mass, dt = tilted_block(PHOBOS, stick_speed, 28.0, precision, stiff)
        tilt(sim, mass, PHOBOS, 28.0, duration, dt)
        sim.run(duration, dt)
        assert abs(sim.velocities()[0, 0]) < 1e-3 * stick_speed, precision
        springs[precision] = sim.state.to_numpy()["rigid_tangential"][0, 0].astype(np.float64)
        overlap = float(sim.model.radius_numpy()[0]) - sim.positions()[0, 2]
        assert 0 < overlap < np.spacing(np.float32(0.5)), "the stiff block rests below float32 resolution at 0.5 m"
    spring = np.linalg.norm(springs["double"])
    assert 0 < spring < 1e-8
    np.testing.assert_allclose(springs["mixed"], springs["double"], rtol=0, atol=1e-5 * spring)

    sim, mass, dt = tilted_block(PHOBOS, stick_speed, 32.0, "mixed", stiff)
    tilt(sim, mass, PHOBOS, 32.0, duration, dt)
    sim.run(duration / 2, dt)
    v1, t1 = sim.velocities()[0, 0], sim.time
    sim.run(duration, dt)
    acceleration = (sim.velocities()[0, 0] - v1) / (sim.time - t1)
    theta = math.radians(32.0)
    expected = PHOBOS * (math.sin(theta) - math.tan(math.radians(20)) * math.cos(theta))
    assert acceleration == pytest.approx(expected, rel=0.01)


def block_on_grain(precision, youngs_modulus, theta_deg):
    """tilted_block's block resting on a fixed grain instead of a plane, both half a metre from the
    origin (where float32 positions are 6e-8 m apart): (simulation, block's mass, step)."""
    theta, radius = math.radians(theta_deg), 5e-3
    mass = 2600 * 4 / 3 * math.pi * radius**3
    e_star = 1 / (2 * (1 - 0.3**2) / youngs_modulus)
    overlap = (3 * mass * PHOBOS * math.cos(theta) / (4 * e_star * math.sqrt(radius / 2))) ** (2 / 3)
    material = Material(
        youngs_modulus=youngs_modulus,
        restitution=0.1,
        stick_angle=math.radians(30),
        slip_angle=math.radians(20),
        stick_speed=1e-4,
    )
    builder = SoilBuilder(gravity=(0.0, 0.0, -PHOBOS * math.cos(theta)))
    soil = builder.add_material(material)
    base = np.array([0.5, 0.0, 0.5])
    builder.add_particle(base, radius, soil, fixed=True)
    builder.add_particle(base + (0.0, 0.0, 2 * radius - overlap), radius, soil, lock_rotation=True)
    model, state, control = builder.finalize(device="cpu", precision=precision)
    step = 1.6e-5 * (9.81 / PHOBOS) ** (1 / 3) * (1e7 / youngs_modulus) ** (1 / 3)  # tilted_block's, R* halved
    return Simulation(model, state, control), mass, step


def test_a_stiff_grain_pair_at_phobos_sticks_in_mixed_as_in_double():
    """The stiff block of the test above on a grain: mixed evaluates a grain pair in float32 once its
    differences are taken in float64 (docs/physics.md section 3). Half a metre from the origin, with a
    Hertz overlap of nanometres, its spring must hold the block at 28 deg as double's does, and equal
    double's to float32 rounding."""
    stiff, theta = 1e8, 28.0
    duration = 0.05 * math.sqrt(9.81 / PHOBOS)
    springs = {}
    for precision in ("double", "mixed"):
        sim, mass, dt = block_on_grain(precision, stiff, theta)
        pull = mass * PHOBOS * math.sin(math.radians(theta))
        for k in range(1, 101):  # tilted slowly, as tilt() does
            sim.control.set_external_force(np.array([[0.0, 0.0, 0.0], [pull * k / 100, 0.0, 0.0]]))
            sim.run(duration / 100, dt)
        sim.run(duration, dt)
        velocity = sim.velocities()[1]
        assert np.linalg.norm(velocity) < 1e-3 * 1e-4, (precision, velocity)
        overlap = 2 * 5e-3 - float(np.linalg.norm(sim.positions()[1] - sim.positions()[0]))
        assert 0 < overlap < np.spacing(np.float32(0.5)), "the pair rests below float32 resolution at 0.5 m"
        rows = sim.state.to_numpy()["pair_tangential"].reshape(-1, 3).astype(np.float64)
        rows = rows[np.linalg.norm(rows, axis=1) > 0]
        springs[precision] = rows[np.argsort(rows[:, 0])]
        # Mindlin: the stuck spring carries the pull, k_T |xi| = m g sin(theta), k_T = 8 G* sqrt(R* delta).
        # The stuck block still rings (|v| < 1e-7 m/s, a damper force up to 3 % of the pull): 0.7 % measured.
        g_star = (stiff / (2 * 1.3)) / (2 * (2 - 0.3))
        k_t = 8 * g_star * math.sqrt(5e-3 / 2 * overlap)
        np.testing.assert_allclose(np.linalg.norm(rows, axis=1), pull / k_t, rtol=0.02)
    spring = np.linalg.norm(springs["double"][-1])
    assert springs["double"].shape == springs["mixed"].shape == (2, 3)
    assert 0 < spring < 1e-8
    np.testing.assert_allclose(springs["mixed"], springs["double"], rtol=0, atol=1e-5 * spring)
