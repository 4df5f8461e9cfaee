"""Tangential contact: Kelvin element with stick/slip, rolling, history (docs/physics.md, sections 1 and 4)."""

import math

import numpy as np
import pytest

from helpers import sphere_on_plane
from soil import ContactLaw, Material, NeighbourSettings, Simulation, SoilBuilder

MU = 0.3


def coulomb(mu, **kw):
    angle = math.atan(mu)
    return Material(
        youngs_modulus=1e7,
        poisson_ratio=0.3,
        density=2600.0,
        restitution=0.3,
        stick_angle=angle,
        slip_angle=angle,
        **kw,
    )


@pytest.mark.parametrize("precision", ["double", "mixed"])
def test_slide_to_roll(device, precision):
    """Solid sphere launched sliding at v0: rolls at 5/7 v0 after t = 2 v0/(7 mu g), d = 12 v0^2/(49 mu g)."""
    v0, g, radius = 1.0, 9.81, 5e-3
    sim = sphere_on_plane(device, precision, g, coulomb(MU), radius=radius, velocity=(v0, 0, 0))
    sim.run(0.002, 1e-5)  # let the normal contact settle first (tiny fraction of the slide)
    dt = 2e-5  # 1/250 of the ~5 ms contact period
    slide_end = None
    x_start = sim.positions()[0, 0] - v0 * 0.002  # the settle phase slid too: count from launch
    while sim.time < 0.15:
        sim.step(dt)
        v = sim.velocities()[0]
        w = sim.angular_velocities()[0]
        slip = v[0] - w[1] * sim.positions()[0, 2]  # contact point speed (w_y > 0 rolls towards +x)
        if slide_end is None and slip < 1e-3 * v0:
            slide_end = (sim.time, sim.positions()[0, 0])
    assert slide_end is not None
    t_slide = 2 * v0 / (7 * MU * g)
    d_slide = 12 * v0**2 / (49 * MU * g)
    assert sim.velocities()[0, 0] == pytest.approx(5 / 7 * v0, rel=0.005)
    assert slide_end[0] == pytest.approx(t_slide, rel=0.02)
    assert slide_end[1] - x_start == pytest.approx(d_slide, rel=0.02)


def tilted_gravity(theta, g=9.81):
    """Gravity for a plane tilted by theta about y: downhill is +x."""
    return (g * math.sin(theta), 0.0, -g * math.cos(theta))


@pytest.mark.parametrize("theta_deg", [30.0, 44.0, 49.0, 60.0])
def test_incline_rolls_without_slip_iff_tan_below_three_and_a_half_mu(device, theta_deg):
    theta = math.radians(theta_deg)
    g, radius = 9.81, 5e-3
    sim = sphere_on_plane(device, "double", tilted_gravity(theta, g), coulomb(MU), radius=radius)
    sim.run(0.01, 5e-6)
    v1, t1 = sim.velocities()[0, 0], sim.time
    sim.run(0.04, 5e-6)
    v2, t2 = sim.velocities()[0, 0], sim.time
    acceleration = (v2 - v1) / (t2 - t1)
    # the contact point sits at the centre's height z = R - delta below the centre
    slip_speed = v2 - sim.angular_velocities()[0, 1] * sim.positions()[0, 2]
    rolls = math.tan(theta) <= 3.5 * MU
    assert rolls == (theta_deg < 46.4)
    if rolls:
        assert acceleration == pytest.approx(5 / 7 * g * math.sin(theta), rel=0.01)
        assert abs(slip_speed) < 1e-3 * v2
    else:
        assert acceleration == pytest.approx(g * (math.sin(theta) - MU * math.cos(theta)), rel=0.01)
        assert slip_speed > 0.1 * v2


STICKY = Material(
    youngs_modulus=1e7,
    poisson_ratio=0.3,
    density=2600.0,
    restitution=0.1,
    stick_angle=math.radians(30),
    slip_angle=math.radians(20),
    stick_speed=0.01,
)


def sliding_block(device, theta_deg, v0):
    """A rotation-locked sphere (a sliding block) on an incline, launched downhill at v0."""
    theta, radius = math.radians(theta_deg), 5e-3
    # start at the static Hertz overlap under the normal load, so the normal force is there at once
    mass = 2600 * 4 / 3 * math.pi * radius**3
    e_star = 1 / (2 * (1 - 0.3**2) / 1e7)
    overlap = (3 * mass * 9.81 * math.cos(theta) / (4 * e_star * math.sqrt(radius))) ** (2 / 3)
    sim = sphere_on_plane(
        device,
        "double",
        tilted_gravity(theta),
        STICKY,
        radius=radius,
        lock_rotation=True,
        velocity=(v0, 0, 0),
        overlap=overlap,
    )
    sim.run(0.05, 2e-5)
    v1, t1 = sim.velocities()[0, 0], sim.time
    sim.run(0.05, 2e-5)
    return sim, (sim.velocities()[0, 0] - v1) / (sim.time - t1)


def test_stick_angle_holds_and_slip_angle_slides(device):
    """phi_h = 30 deg, phi_g = 20 deg, v_Tmin = 0.01 m/s: hysteresis between the two angles."""
    g = 9.81
    # 25 deg, at rest: below the stick angle it stays put
    sim, _ = sliding_block(device, 25.0, 0.0)
    assert abs(sim.velocities()[0, 0]) < 1e-6
    # 25 deg, launched above v_Tmin: it slips, and slip friction (phi_g) cannot stop it
    sim, a = sliding_block(device, 25.0, 0.05)
    expected = g * (math.sin(math.radians(25)) - math.tan(math.radians(20)) * math.cos(math.radians(25)))
    assert a == pytest.approx(expected, rel=0.01)
    # 25 deg, launched below v_Tmin: the Kelvin element catches it and it sticks (the
    # catching spring force v0 sqrt(m k_T) ~ 1e-4 N stays under the stick margin ~1e-3 N)
    sim, _ = sliding_block(device, 25.0, 0.0005)
    assert abs(sim.velocities()[0, 0]) < 1e-6
    # 35 deg, from rest: above the stick angle it breaks loose and slides with phi_g
    sim, a = sliding_block(device, 35.0, 0.0)
    expected = g * (math.sin(math.radians(35)) - math.tan(math.radians(20)) * math.cos(math.radians(35)))
    assert a == pytest.approx(expected, rel=0.01)


@pytest.mark.parametrize("partner", ["wall", "particle"])
def test_contact_history_survives_neighbour_rebuilds(device, partner):
    """A stuck block on a 20 deg incline holds with the Kelvin spring's static deflection
    F_T / k_T (Mindlin k_T = 8 G* sqrt(R* delta)). Were the history reset at a neighbour
    rebuild (every step here: a skin of 1e-12 m), only the dashpot would hold it and it would creep away."""
    theta = math.radians(20.0)
    g, radius = 9.81, 5e-3
    builder = SoilBuilder(gravity=tilted_gravity(theta, g))
    mat = builder.add_material(STICKY)
    if partner == "wall":
        builder.add_plane((0, 0, 0), (0, 0, 1), mat)
    else:  # a fixed sphere of the same size below
        builder.add_particle((0, 0, -radius), radius, mat, fixed=True)
    block = builder.add_particle((0, 0, radius if partner == "wall" else radius), radius, mat, lock_rotation=True)
    model, state, control = builder.finalize(device, "double")
    every_step = NeighbourSettings(skin=1e-12)
    sim = Simulation(model, state, control, neighbours=every_step)
    sim.run(0.1, 2e-5)
    x0 = sim.positions()[block, 0]
    sim.run(0.05, 2e-5)
    creep = abs(sim.positions()[block, 0] - x0)
    mass = float(model.mass_numpy()[block])
    # static state: normal and tangential load from the tilted gravity
    fn, ft = mass * g * math.cos(theta), mass * g * math.sin(theta)
    r_eff = radius if partner == "wall" else radius / 2
    e_star = 1 / (2 * (1 - 0.3**2) / 1e7)
    g_star = 1 / (2 * (2 - 0.3) / (1e7 / (2 * 1.3)))
    delta = (3 * fn / (4 * e_star * math.sqrt(r_eff))) ** (2 / 3)
    kt = 8 * g_star * math.sqrt(r_eff * delta)
    assert creep < 1e-3 * ft / kt, "the block creeps: tangential history was lost"
    history = state_history(sim, block)
    assert np.linalg.norm(history) == pytest.approx(ft / kt, rel=0.02)
    # and a brand-new solver (fresh grid, as after a restart) carries on from the same history
    sim2 = Simulation(model, sim.state, sim.control, neighbours=every_step)
    sim2.run(0.02, 2e-5)
    assert abs(sim2.positions()[block, 0] - x0) < 1e-3 * ft / kt


def state_history(sim, particle):
    contacts = sim.contact_history(particle)
    assert len(contacts) == 1
    return contacts[0]["tangential"]


def test_history_storage_grows_instead_of_dropping_contacts(device):
    """A dense cluster with one history slot per particle runs exactly like one with 32."""
    rng = np.random.default_rng(3)
    results = []
    for capacity in (1, 32):
        builder = SoilBuilder(gravity=9.81)
        mat = builder.add_material(STICKY)
        builder.add_container((-0.02, -0.02, 0), (0.02, 0.02, 0.1), mat)
        grid = np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), -1).reshape(-1, 3)
        positions = (grid - 1.5) * 0.0095 + (0, 0, 0.02)
        builder.add_particles(
            positions
            + rng.normal(0, 1e-4, positions.shape) * (capacity == 1) * 0
            + np.random.default_rng(5).normal(0, 1e-4, positions.shape),
            0.005,
            mat,
        )
        model, state, control = builder.finalize(device, "double", contact_capacity=capacity)
        sim = Simulation(model, state, control)
        sim.run(0.02, 5e-6)
        assert sim.state.capacity >= int(sim.state.contact_count.numpy().max())
        results.append(sim.positions())
    np.testing.assert_array_equal(results[0], results[1])


def test_rolling_resistance_stops_a_rolling_sphere(device):
    """With rolling friction mu_r the plastic rolling torque mu_r R |F_N| decelerates a
    rolling sphere at a = (5/7) mu_r g (torque / (I + m R^2) * R)."""
    mu_r, g, radius, v0 = 0.05, 9.81, 5e-3, 0.2
    material = coulomb(0.5, rolling_friction=mu_r)
    sim = sphere_on_plane(device, "double", g, material, radius=radius, velocity=(v0, 0, 0), spin=(0, v0 / radius, 0))
    sim.run(0.01, 2e-6)
    v1, t1 = sim.velocities()[0, 0], sim.time
    sim.run(0.05, 2e-6)
    deceleration = -(sim.velocities()[0, 0] - v1) / (sim.time - t1)
    assert deceleration == pytest.approx(5 / 7 * mu_r * g, rel=0.02)


def test_cohesion_holds_a_sphere_against_pull(device):
    """Cohesion c adds c pi R* delta of attraction: with gravity reversed below that pull
    the sphere stays on the ceiling, above it it falls."""
    radius, cohesion = 5e-3, 2e4
    material = Material(youngs_modulus=1e6, restitution=0.2, cohesion=cohesion)
    mass = 2600 * 4 / 3 * math.pi * radius**3
    e_star = 1 / (2 * (1 - 0.3**2) / 1e6)
    # equilibrium without gravity: 4/3 E* sqrt(R) d^1.5 = c pi R d  ->  d = (3 c pi sqrt(R) / (4 E*))^2
    delta0 = (3 * cohesion * math.pi * math.sqrt(radius) / (4 * e_star)) ** 2
    max_pull = cohesion * math.pi * radius * delta0  # the attraction at that overlap bounds the pull-off
    outcomes = {}
    for factor in (0.2, 3.0):
        g_pull = factor * max_pull / mass
        sim = sphere_on_plane(
            device, "double", (0, 0, g_pull), material, radius=radius, law=ContactLaw(friction=False, cohesion=True)
        )
        sim.run(0.05, 5e-6)
        outcomes[factor] = sim.positions()[0, 2] < 2 * radius
    assert outcomes == {0.2: True, 3.0: False}
