"""Boundaries: the grains' force and torque on walls, moving walls, loaded walls (soil.boundaries)."""

import math

import numpy as np
import pytest

from helpers import effective_modulus, hertz_impact_overlap, hertz_rest_overlap
from soil import ContactLaw, Material, Simulation, SoilBuilder
from soil.bed import open_bed, read_bed, save_bed

G = 9.81
R = 4e-3


def coulomb(mu, **kw):
    """A soft material with Coulomb friction mu (stick and slip angle atan(mu))."""
    angle = math.atan(mu)
    kw = {"youngs_modulus": 1e7, "poisson_ratio": 0.3, "density": 2600.0, "restitution": 0.3, **kw}
    return Material(stick_angle=angle, slip_angle=angle, **kw)


def sphere_mass(radius, density=2600.0):
    return density * 4.0 / 3.0 * math.pi * radius**3


# -- forces and torques on resting grains --------------------------------------------------


def test_resting_sphere_loads_plane_and_box_with_its_weight_and_lever(device):
    """A sphere resting off-centre on a plane, another on a box: each boundary carries
    F = (0, 0, -m g) and, about its reference point (plane: its point; box: its centre),
    the torque r x F with r from that point to the contact point."""
    radius = 5e-3
    material = coulomb(0.3)
    builder = SoilBuilder(gravity=G)
    mat = builder.add_material(material)
    plane_point = np.array([0.03, -0.02, 0.0])
    plane = builder.add_plane(plane_point, (0, 0, 1), mat)
    lower, upper = np.array([0.2, 0.0, 0.0]), np.array([0.26, 0.04, 0.02])
    box = builder.add_box(lower, upper, mat)
    e_star = effective_modulus(material, material)
    overlap = hertz_rest_overlap(sphere_mass(radius), G, e_star, radius)
    on_plane = np.array([0.1, 0.05, radius - overlap])
    on_box = np.array([0.245, 0.008, upper[2] + radius - overlap])
    builder.add_particles([on_plane, on_box], radius, mat)
    model, state, control = builder.finalize(device, "double")
    sim = Simulation(model, state, control)
    sim.run(0.02, 2e-5)
    force, torque, contacts = sim.boundary_wrenches()
    weight = np.array([0.0, 0.0, -sphere_mass(radius) * G])
    np.testing.assert_allclose(force, [weight, weight], rtol=1e-6, atol=1e-12)
    assert list(contacts) == [1, 1]
    x = sim.positions()
    contact = x - np.array([0.0, 0.0, radius - overlap])  # contact points, just below the centres
    expected = [np.cross(contact[0] - plane_point, weight), np.cross(contact[1] - 0.5 * (lower + upper), weight)]
    np.testing.assert_allclose(torque[[plane, box]], expected, rtol=1e-6, atol=1e-12)
    assert abs(torque[0, 0]) > 1e-4  # the lever is not trivial


def test_torque_on_the_floor_includes_the_rolling_resistance(device):
    """A sphere rolling on a plane with rolling resistance mu_r slows down. About a point of
    the plane, weight and normal force cancel and friction has no lever, so its angular
    momentum L changes by the rolling torque alone: dL/dt = -mu_r R m g. The plane's torque
    (the reaction, about its point) must close the balance dL/dt = T_gravity - T_plane,
    which it cannot without the rolling torque."""
    radius, v0, mu_r = 5e-3, 0.2, 0.05
    material = coulomb(0.5, rolling_friction=mu_r)
    builder = SoilBuilder(gravity=G)
    mat = builder.add_material(material)
    point = np.array([-0.01, 0.0, 0.0])
    builder.add_plane(point, (0, 0, 1), mat)
    overlap = hertz_rest_overlap(sphere_mass(radius), G, effective_modulus(material, material), radius)
    builder.add_particle(
        (0, 0, radius - overlap), radius, mat, velocity=(v0, 0, 0), angular_velocity=(0, v0 / (radius - overlap), 0)
    )
    model, state, control = builder.finalize(device, "double")
    sim = Simulation(model, state, control)
    dt = 1e-5
    sim.run(0.005, dt)
    mass = float(model.mass_numpy()[0])
    inertia = 0.4 * mass * radius**2

    def angular_momentum():
        x, v, w = sim.positions()[0], sim.velocities()[0], sim.angular_velocities()[0]
        return mass * np.cross(x - point, v) + inertia * w

    wall_torque, gravity_torque = [], []

    def record(s):
        wall_torque.append(s.boundary_wrenches()[1][0])
        gravity_torque.append(np.cross(s.positions()[0] - point, mass * np.array([0, 0, -G])))

    l0, t0 = angular_momentum(), sim.time
    sim.run(0.02, dt, callback=record)
    rate = (angular_momentum() - l0) / (sim.time - t0)
    balance = np.mean(gravity_torque, axis=0) - np.mean(wall_torque, axis=0)
    rolling = mu_r * radius * mass * G
    assert rate[1] == pytest.approx(-rolling, rel=0.01)
    assert rate[1] == pytest.approx(balance[1], abs=1e-3 * rolling)


# -- beds: the floor carries the weight ------------------------------------------------------


def column(device, wall_friction, columns=4, layers=16, order_seed=None, top=1.0, closed=False):
    """Grains on a jittered lattice in a narrow container (floor at z = 0, walls up to `top`,
    closed by a lid plane there if `closed`); walls of their own material with friction
    wall_friction. Returns (simulation, wall indices floor, -x, +x, -y, +y (, lid), width)."""
    builder = SoilBuilder(gravity=G)
    grain = builder.add_material(coulomb(0.5, youngs_modulus=1e6, restitution=0.2))
    wall = builder.add_material(coulomb(wall_friction, youngs_modulus=1e6, restitution=0.2))
    width = columns * 2.2 * R
    walls = builder.add_container((0, 0, 0), (width, width, top), wall, open_top=not closed)
    rng = np.random.default_rng(1)
    grid = np.stack(np.meshgrid(np.arange(columns), np.arange(columns), np.arange(layers), indexing="ij"), -1).reshape(
        -1, 3
    )
    positions = 1.1 * R + grid * 2.2 * R + rng.uniform(-0.05 * R, 0.05 * R, grid.shape)
    builder.add_particles(positions, R * rng.uniform(0.85, 1.0, len(grid)), grain)
    model, state, control = builder.finalize(device, "double", order_seed=order_seed)
    return Simulation(model, state, control), walls, width


def mean_wrenches(sim, duration, dt):
    """Boundary forces [N] averaged over every step of `duration` [s] (wall friction chatters
    from step to step: single samples scatter by a few percent). Their sum differs from the
    weight by the bed's rate of momentum change, which the tests let die out first."""
    forces = []
    sim.run(duration, dt, callback=lambda s: forces.append(s.boundary_wrenches()[0]))
    return np.mean(forces, axis=0)


def test_floor_carries_the_weight_with_frictionless_walls(device):
    sim, walls, _ = column(device, wall_friction=0.0)
    sim.run(0.6, 1e-4)  # the column's slow bounce dies out (0.5 % of its weight left at 0.5 s)
    force = mean_wrenches(sim, 0.2, 1e-4)
    weight = float(sim.model.mass_numpy().sum()) * G
    floor, sides = walls[0], walls[1:]
    assert -force[floor, 2] == pytest.approx(weight, rel=0.01)
    assert np.all(force[sides, 2] == 0.0)  # frictionless walls push horizontally only
    # the grains press the side walls outwards (+x on the +x wall, ...)
    outward = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0]])
    assert np.all(np.einsum("ij,ij->i", force[sides], outward) > 0)


def test_floor_and_frictional_walls_share_the_weight(device):
    """Wall friction carries part of a narrow column (Janssen): the floor gets less than the
    weight, floor and walls together get all of it."""
    sim, walls, _ = column(device, wall_friction=0.5)
    sim.run(0.6, 1e-4)
    force = mean_wrenches(sim, 0.2, 1e-4)
    weight = float(sim.model.mass_numpy().sum()) * G
    floor, sides = walls[0], walls[1:]
    assert -force[floor, 2] < 0.97 * weight  # measured 0.91-0.94 over order_seed replicas
    assert -force[sides, 2].sum() > 0.03 * weight
    assert -force[:, 2].sum() == pytest.approx(weight, rel=0.01)


def test_loaded_lid_on_a_settled_bed_is_carried_by_the_grains(device, tmp_path):
    """A lid plane added to a saved bed and pressed down with a dead load L settles where the
    grains push it back with L, and the (frictionless-walled) floor then carries L + the
    grains' weight."""
    sim, walls, width = column(device, wall_friction=0.0, layers=8, top=0.2)
    sim.run(0.3, 1e-4)
    save_bed(tmp_path / "bed.h5", sim)
    builder = read_bed(tmp_path / "bed.h5").builder()
    top = float(np.max(sim.positions()[:, 2] + sim.model.radius_numpy()))
    lid = builder.add_plane((0, 0, top + 0.2 * R), (0, 0, -1), builder.add_material(coulomb(0.0, youngs_modulus=1e6)))
    model, state, control = builder.finalize(device, "double")
    lidded = Simulation(model, state, control)
    weight = float(model.mass_numpy().sum()) * G
    load = 2.0 * weight
    control.set_boundary_load(lid, load, direction=(0, 0, -1), mass=0.05, damping=2.0)
    lidded.run(0.3, 1e-4)
    force = mean_wrenches(lidded, 0.1, 1e-4)
    assert force[lid, 2] == pytest.approx(load, rel=0.01)
    assert -force[walls[0], 2] == pytest.approx(load + weight, rel=0.01)
    assert lidded.boundary_displacements()[lid, 2] < -0.2 * R  # it came down onto the grains


# -- moving walls -------------------------------------------------------------------------------


def test_wall_moving_into_a_resting_sphere_is_a_hertz_impact(device):
    """A plane moving at V hits a free sphere (no gravity, elastic, frictionless): in the
    wall's frame it is a sphere hitting a wall at V, so the sphere leaves at 2 V after the
    Hertz contact time 2.9432 delta_max / V with the peak force k delta_max^1.5 on the wall."""
    radius, speed = 5e-3, 0.5
    material = Material(youngs_modulus=1e7, poisson_ratio=0.3, density=2600.0, damping_ratio=0.0)
    builder = SoilBuilder(gravity=0.0)
    mat = builder.add_material(material)
    wall = builder.add_plane((0, 0, 0), (1, 0, 0), mat)
    builder.add_particle((radius + 1e-4, 0, 0), radius, mat)
    model, state, control = builder.finalize(device, "double", law=ContactLaw(damping=False, friction=False))
    sim = Simulation(model, state, control)
    control.set_boundary_velocity(wall, (speed, 0, 0))
    e_star = effective_modulus(material, material)
    mass = float(model.mass_numpy()[0])
    delta_max = hertz_impact_overlap(mass, speed, e_star, radius)
    contact_time = 2.9432 * delta_max / speed
    dt = contact_time / 2000
    touch, release, peak = None, None, 0.0
    while release is None and sim.time < 0.05:
        sim.step(dt)
        force, _, contacts = sim.boundary_wrenches()
        if contacts[0]:
            touch = sim.time if touch is None else touch
            peak = max(peak, -force[0, 0])  # the grain pushes back against the motion
        elif touch is not None:
            release = sim.time
    assert release is not None, "the sphere never left the wall"
    assert release - touch == pytest.approx(contact_time, rel=0.01)
    assert peak == pytest.approx(4.0 / 3.0 * e_star * math.sqrt(radius) * delta_max**1.5, rel=0.01)
    assert sim.velocities()[0, 0] == pytest.approx(2 * speed, rel=1e-3)
    # the wall's geometry moved on the device by V t
    assert sim.boundary_displacements()[0] == pytest.approx([speed * sim.time, 0, 0], rel=1e-9)
    assert sim.boundary_geometry()[0, 0] == pytest.approx(speed * sim.time, rel=1e-9)


@pytest.mark.parametrize("rolls", [True, False], ids=["rolling", "locked"])
def test_sphere_on_a_conveyor_plane(device, rolls):
    """A sphere at rest put on a belt moving at V (friction mu) slides with acceleration
    mu g; a free sphere starts rolling at t = 2 V / (7 mu g) and keeps 2/7 V; a sphere that
    cannot turn reaches the belt speed V at t = V / (mu g) and sticks to it."""
    mu, speed, radius = 0.3, 0.2, 5e-3
    material = coulomb(mu)
    builder = SoilBuilder(gravity=G)
    mat = builder.add_material(material)
    belt = builder.add_plane((0, 0, 0), (0, 0, 1), mat)
    overlap = hertz_rest_overlap(sphere_mass(radius), G, effective_modulus(material, material), radius)
    builder.add_particle((0, 0, radius - overlap), radius, mat, lock_rotation=not rolls)
    model, state, control = builder.finalize(device, "double")
    sim = Simulation(model, state, control)
    dt = 2e-5
    sim.run(0.005, dt)  # the normal contact settles first
    control.set_boundary_velocity(belt, (speed, 0, 0))
    t0 = sim.time
    final = 2.0 / 7.0 * speed if rolls else speed
    times, velocities = [], []
    sim.run(
        0.04 if rolls else 0.09,
        dt,
        callback=lambda s: (times.append(s.time - t0), velocities.append(s.velocities()[0, 0])),
    )
    times, velocities = np.array(times), np.array(velocities)
    slide = final / (mu * G)
    sliding = (times > 0.1 * slide) & (times < 0.8 * slide)
    acceleration = np.polyfit(times[sliding], velocities[sliding], 1)[0]
    assert acceleration == pytest.approx(mu * G, rel=0.005)
    t_catch = times[np.argmax(velocities >= 0.995 * final)]
    assert t_catch == pytest.approx(slide, rel=0.02)
    # after the slide: the belt's speed (stuck) or 2/7 of it (rolling; the stick/slip switch
    # at v_Tmin = 1 mm/s leaves a ripple of that order)
    late = times > 1.3 * slide
    assert np.mean(velocities[late]) == pytest.approx(final, rel=0.01)
    force = sim.boundary_wrenches()[0][belt]
    assert force[2] == pytest.approx(-sphere_mass(radius) * G, rel=1e-3)


def test_walls_moved_together_carry_a_sphere_along(device):
    """Four thin box walls (a frame, like a shear box's upper half) moved together at V
    around a sphere on a frictionless floor: the walls keep their shape, the sphere stays
    inside the frame and so travels with it at V on average."""
    radius, speed, gap = 5e-3, 0.05, 2e-3
    builder = SoilBuilder(gravity=G)
    grain = builder.add_material(coulomb(0.3))
    slick = builder.add_material(coulomb(0.0))
    builder.add_plane((0, 0, 0), (0, 0, 1), slick)
    inner, wall = radius + gap, 1e-3
    frame = [
        builder.add_box((-inner - wall, -inner - wall, 0.001), (-inner, inner + wall, 0.02), grain),
        builder.add_box((inner, -inner - wall, 0.001), (inner + wall, inner + wall, 0.02), grain),
        builder.add_box((-inner, -inner - wall, 0.001), (inner, -inner, 0.02), grain),
        builder.add_box((-inner, inner, 0.001), (inner, inner + wall, 0.02), grain),
    ]
    builder.add_particle((0, 0, radius), radius, grain)
    model, state, control = builder.finalize(device, "double")
    sim = Simulation(model, state, control)
    control.set_boundary_velocity(frame, (speed, 0, 0))
    sim.run(0.2, 5e-5)
    shift = sim.boundary_displacements()
    np.testing.assert_allclose(shift[frame], np.tile([speed * sim.time, 0, 0], (4, 1)), rtol=1e-9, atol=1e-15)
    assert shift[0] == pytest.approx([0, 0, 0])
    assert abs(sim.positions()[0, 0] - speed * sim.time) < gap + 1e-6
    assert sim.boundary_wrenches()[2][frame].sum() <= 1


# -- loaded walls --------------------------------------------------------------------------------


@pytest.mark.parametrize("integrator", ["verlet", "jolt-beeman"])
def test_loaded_lid_rests_at_the_hertz_overlap(device, integrator):
    """A lid of mass M pressed down with a load L on a sphere on the floor: at rest the lid
    overlaps the sphere by the Hertz overlap of L, the floor by that of L + m g, and the
    grain pushes the lid back with L."""
    radius, load = 5e-3, 1.0
    material = coulomb(0.3)
    builder = SoilBuilder(gravity=G)
    mat = builder.add_material(material)
    floor = builder.add_plane((0, 0, 0), (0, 0, 1), mat)
    lid_height = 2 * radius + 1e-4
    lid = builder.add_plane((0, 0, lid_height), (0, 0, -1), mat)
    builder.add_particle((0, 0, radius), radius, mat)
    model, state, control = builder.finalize(device, "double")
    sim = Simulation(model, state, control)
    control.set_boundary_load(lid, load, direction=(0, 0, -2), mass=0.1, damping=20.0)
    if integrator == "verlet":
        sim.run(0.15, 4e-5)  # 1/40 of the grain's contact period
    else:
        sim.run_adaptive(0.15)
    e_star = effective_modulus(material, material)
    weight = sphere_mass(radius) * G
    z = sim.positions()[0, 2]
    lid_z = lid_height + sim.boundary_displacements()[lid, 2]
    hertz = lambda force: hertz_rest_overlap(force / G, G, e_star, radius)  # noqa: E731
    assert radius - (lid_z - z) == pytest.approx(hertz(load), rel=1e-3)
    assert radius - z == pytest.approx(hertz(load + weight), rel=1e-3)
    force = sim.boundary_wrenches()[0]
    assert force[lid, 2] == pytest.approx(load, rel=1e-3)
    assert -force[floor, 2] == pytest.approx(load + weight, rel=1e-3)
    assert abs(sim.boundary_velocities()[lid, 2]) < 1e-5


def test_loaded_wall_needs_a_reporting_boundary_and_valid_input(device):
    builder = SoilBuilder(gravity=G)
    silent = builder.add_plane((0, 0, 0), (0, 0, 1), report=False)
    wall = builder.add_plane((0, 0, 0.1), (0, 0, -1))
    builder.add_particle((0, 0, 0.05), 5e-3)
    model, state, control = builder.finalize(device, "double")
    with pytest.raises(ValueError, match="report=False"):
        control.set_boundary_load(silent, 1.0, direction=(0, 0, 1), mass=1.0)
    with pytest.raises(ValueError, match="mass"):
        control.set_boundary_load(wall, 1.0, direction=(0, 0, -1))
    with pytest.raises(ValueError, match="mass"):
        control.set_boundary_load(wall, 1.0, direction=(0, 0, -1), mass=0.0)
    with pytest.raises(ValueError, match="direction"):
        control.set_boundary_load(wall, 1.0, direction=(0, 0, 0), mass=1.0)
    with pytest.raises(IndexError, match="boundary index"):
        control.set_boundary_velocity([wall, 5], (0, 0, 1))
    with pytest.raises(ValueError, match="velocity"):
        control.set_boundary_velocity(wall, (0, 0))
    sim = Simulation(model, state, control)
    sim.run(0.01, 1e-4)
    assert sim.boundary_wrenches()[2][silent] == 0  # not summed, reads zero


# -- determinism and checkpoints ------------------------------------------------------------------


def _wrench_arrays(sim):
    state = sim.state
    return [
        a.numpy()
        for a in (
            state.boundary_force,
            state.boundary_torque,
            state.boundary_contacts,
            state.boundary_displacement,
            state.boundary_velocity,
        )
    ]


def test_boundary_wrenches_repeat_bit_for_bit_and_do_not_depend_on_the_order(device):
    """The same run twice gives identical wall forces; permuting the grains (order_seed:
    another summation order) changes them by rounding only (the bed is still falling into
    place after 30 ms, before chaos can amplify the rounding)."""
    runs = []
    for seed in (None, None, 7):
        sim, walls, _ = column(device, wall_friction=0.5, columns=3, layers=6, order_seed=seed)
        sim.run(0.03, 1e-4)
        runs.append(_wrench_arrays(sim))
    for first, second in zip(runs[0], runs[1]):
        np.testing.assert_array_equal(first, second)
    force, torque, contacts = runs[0][:3]
    assert contacts[walls[0]] > 0 and np.abs(force[walls[0], 2]) > 0
    np.testing.assert_allclose(runs[2][0], force, rtol=1e-9, atol=1e-12 * np.abs(force).max())
    np.testing.assert_allclose(runs[2][1], torque, rtol=1e-9, atol=1e-12 * np.abs(torque).max())
    np.testing.assert_array_equal(runs[2][2], contacts)


@pytest.mark.parametrize("integrator", ["verlet", "jolt-beeman"])
def test_state_dict_resume_is_bitwise(device, tmp_path, integrator):
    """Run, save Simulation.state_dict() to an .npz (no pickles), load it into a freshly
    built simulation, continue: every array equals the uninterrupted run's, bit for bit
    (moving and loaded walls, contact history, the step controller's state included)."""

    def build():
        # the lid (closing the top) starts on the highest grains
        sim, walls, _ = column(device, wall_friction=0.3, columns=3, layers=4, top=8.7 * R, closed=True)
        control = sim.control
        control.set_boundary_load(walls[-1], 0.5, direction=(0, 0, -1), mass=0.02, damping=0.5)
        control.set_boundary_velocity(walls[1], (0.1, 0, 0))  # the -x wall pushes in
        return sim

    def advance(sim):
        if integrator == "verlet":
            sim.run(0.008, 1e-4)
        else:
            sim.run_adaptive(0.008)

    reference = build()
    advance(reference)
    assert np.all(reference.boundary_wrenches()[2][[1, 5]] > 0)  # the moving wall and the lid touch grains
    saved = reference.state_dict()
    advance(reference)
    np.savez(tmp_path / "state.npz", **saved)
    with np.load(tmp_path / "state.npz", allow_pickle=False) as f:
        loaded = {key: f[key] for key in f.files}
    resumed = build()
    resumed.load_state_dict(loaded)
    advance(resumed)
    assert resumed.steps == reference.steps and resumed.time == reference.time
    for name, array in reference.state.arrays.items():
        np.testing.assert_array_equal(getattr(resumed.state, name).numpy(), array.numpy(), err_msg=name)
    assert np.any(reference.boundary_displacements() != 0)


def test_a_saved_bed_keeps_its_walls_where_they_moved(device, tmp_path):
    """save_bed writes moved walls at their current place (the bed's new initial geometry):
    the reloaded bed feels the same wall forces."""
    sim, walls, width = column(device, wall_friction=0.3, columns=3, layers=3)
    sim.control.set_boundary_velocity(walls[1], (0.05, 0, 0))  # the -x wall squeezes the grains
    sim.run(0.03, 1e-4)
    save_bed(tmp_path / "bed.h5", sim)
    reloaded = open_bed(tmp_path / "bed.h5", device=device, precision="double")
    model = reloaded.model
    np.testing.assert_allclose(model.boundary_geometry_numpy(), sim.boundary_geometry(), rtol=0, atol=1e-15)
    assert np.all(reloaded.boundary_displacements() == 0)
    assert model.boundary_geometry_numpy()[walls[1], 0] == pytest.approx(0.05 * 0.03, rel=1e-9)
    sim.refresh_forces()  # the same evaluation on both (a refresh sees the end-of-step velocities)
    reloaded.refresh_forces()
    force, torque, contacts = reloaded.boundary_wrenches()
    assert contacts[walls[1]] > 0
    np.testing.assert_allclose(force, sim.boundary_wrenches()[0], rtol=1e-9, atol=1e-12)
