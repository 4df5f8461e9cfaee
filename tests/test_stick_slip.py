"""The stick/slip switch holds and is passive; twisting resistance (docs/physics.md sections 1.3, 1.4)."""

import math

import numpy as np
import pytest
import warp as wp

from helpers import sphere_on_plane
from soil import ContactLaw, Material, NeighbourSettings, Simulation, SoilBuilder
from soil.contact import contact_functions
from soil.materials import MaterialTable

PHOBOS = 5.7e-3

# The two settings of the squeeze: a stiff grain under Earth gravity, and PHOBOS_REGOLITH's
# grain (E = 2e5 Pa, r = 2 mm, stick/slip 25/20 deg) at Phobos gravity, each at its own step.
SQUEEZE = {
    9.81: dict(youngs_modulus=5e6, radius=2.5e-3, angles=(16.7, 16.7), dt=1e-5, duration=0.5),
    PHOBOS: dict(youngs_modulus=2e5, radius=2e-3, angles=(25.0, 20.0), dt=2e-4, duration=25.0),
}


def squeezed_sphere(partner, gravity, stick_speed, nudge, precision="double"):
    """A sphere pressed 1 % of its radius between two vertical walls (or two fixed grains) of its
    own material, released at `nudge` [m/s] upwards; returns (simulation, grain mass)."""
    case = SQUEEZE[gravity]
    r = case["radius"]
    material = Material(
        youngs_modulus=case["youngs_modulus"],
        poisson_ratio=0.3,
        density=2600.0,
        restitution=0.5,
        stick_angle=math.radians(case["angles"][0]),
        slip_angle=math.radians(case["angles"][1]),
        stick_speed=stick_speed,
    )
    builder = SoilBuilder(gravity=(0, 0, -gravity))
    soil = builder.add_material(material)
    if partner == "wall":
        builder.add_plane((-0.99 * r, 0, 0), (1, 0, 0), soil)
        builder.add_plane((0.99 * r, 0, 0), (-1, 0, 0), soil)
    else:
        builder.add_particles([(-1.98 * r, 0, 0), (1.98 * r, 0, 0)], r, soil, fixed=True)
    builder.add_particle((0, 0, 0), r, soil, velocity=(0, 0, nudge))
    model, state, control = builder.finalize(device="cpu", precision=precision)
    return Simulation(model, state, control), 2600.0 * 4.0 / 3.0 * math.pi * r**3


@pytest.mark.parametrize("gravity", [9.81, PHOBOS], ids=["earth", "phobos"])
@pytest.mark.parametrize("stick_speed", [1e-4, 1e-3])
@pytest.mark.parametrize("partner", ["wall", "grain"])
def test_a_squeezed_sphere_comes_to_rest_with_each_side_carrying_half_its_weight(partner, stick_speed, gravity):
    """The sides can hold several times the weight (their Coulomb limit F_N tan(phi) is 4-900 x
    m g), so a pressed sphere must stop, and statics then splits its weight evenly. It starts
    moving up at 1 mm/s (above either stick speed): it has to come back into stick."""
    case = SQUEEZE[gravity]
    sim, mass = squeezed_sphere(partner, gravity, stick_speed, nudge=1e-3)
    sim.run(case["duration"], case["dt"])
    speed = np.linalg.norm(sim.velocities()[-1])
    spin = np.linalg.norm(sim.angular_velocities()[-1])
    assert speed < 1e-3 * stick_speed
    assert spin * case["radius"] < 1e-3 * stick_speed
    if partner == "wall":
        force, _, _ = sim.boundary_wrenches()
        carried = -force[:, 2]  # the grain pushes each wall down by what the wall carries
    else:
        carried = -sim.forces()[:2, 2]
    np.testing.assert_allclose(carried, mass * gravity / 2, rtol=0.01)


def tilted_block(gravity, stick_speed, theta_deg, precision="double", youngs_modulus=1e7):
    """A rotation-locked sphere (a block) at rest on a plane at its static Hertz overlap, with the
    downhill pull m g sin(theta) of a slope of theta still to come (as an external force); stick/slip
    angles 30/20 deg. Returns (simulation, mass, step)."""
    theta, radius = math.radians(theta_deg), 5e-3
    mass = 2600 * 4 / 3 * math.pi * radius**3
    e_star = 1 / (2 * (1 - 0.3**2) / youngs_modulus)
    overlap = (3 * mass * gravity * math.cos(theta) / (4 * e_star * math.sqrt(radius))) ** (2 / 3)
    material = Material(
        youngs_modulus=youngs_modulus,
        restitution=0.1,
        stick_angle=math.radians(30),
        slip_angle=math.radians(20),
        stick_speed=stick_speed,
    )
    g = (0.0, 0.0, -gravity * math.cos(theta))
    sim = sphere_on_plane("cpu", precision, g, material, radius=radius, lock_rotation=True, overlap=overlap)
    # the Hertz period grows as g^(-1/3) and shrinks as E^(-1/3)
    return sim, mass, 2e-5 * (9.81 / gravity) ** (1 / 3) * (1e7 / youngs_modulus) ** (1 / 3)


def tilt(sim, mass, gravity, theta_deg, duration, dt, increments=100):
    """Raise the downhill pull to m g sin(theta) in equal increments over `duration`, as a table
    tilted slowly: each increment's elastic transient stays far below the stick speed."""
    pull = mass * gravity * math.sin(math.radians(theta_deg))
    for k in range(1, increments + 1):
        sim.control.set_external_force(np.array([[pull * k / increments, 0.0, 0.0]]))
        sim.run(duration / increments, dt)


@pytest.mark.parametrize("gravity", [9.81, PHOBOS], ids=["earth", "phobos"])
@pytest.mark.parametrize("stick_speed", [1e-4, 1e-3])
def test_a_block_sticks_below_the_stick_angle_and_slides_above_at_the_coulomb_rate(gravity, stick_speed):
    """Tilted slowly to tan(theta) < tan(phi_h) the Kelvin element holds it; above, it breaks loose
    and slides with a = g (sin theta - tan(phi_g) cos theta)."""
    duration = 0.05 * math.sqrt(9.81 / gravity)  # the same in units of the grain's time at any g
    sim, mass, dt = tilted_block(gravity, stick_speed, 28.0)
    tilt(sim, mass, gravity, 28.0, duration, dt)
    sim.run(duration, dt)
    assert abs(sim.velocities()[0, 0]) < 1e-3 * stick_speed
    sim, mass, dt = tilted_block(gravity, stick_speed, 32.0)
    tilt(sim, mass, gravity, 32.0, duration, dt)
    sim.run(duration / 2, dt)
    v1, t1 = sim.velocities()[0, 0], sim.time
    sim.run(duration, dt)
    acceleration = (sim.velocities()[0, 0] - v1) / (sim.time - t1)
    theta = math.radians(32.0)
    expected = gravity * (math.sin(theta) - math.tan(math.radians(20)) * math.cos(theta))
    assert acceleration == pytest.approx(expected, rel=0.01)


# -- passivity: one contact driven through prescribed motions ------------------------------------------


def drive_one_contact(law, material, overlap, radius, mass, normals, velocities, spins, dt):
    """Evaluate the contact law along a prescribed history (double precision): normals (S, 3), the
    relative velocity of the contact point (S, 3) [m/s] and relative spin (S, 3) [rad/s] per step.
    Returns force (S, 3) [N], torque (S, 3) [N m], tangential spring (S, 3) [m], spin history (S, k)."""
    functions = contact_functions(wp.float64, wp.float64, law)
    vec = wp.types.vector(3, wp.float64)
    spin_type = wp.types.vector(4 if law.twisting else 3, wp.float64)
    contact_law = functions.contact_law

    @wp.kernel(enable_backward=False, module="unique")
    def along(
        normals: wp.array(dtype=vec),
        velocities: wp.array(dtype=vec),
        spins: wp.array(dtype=vec),
        pair: wp.array2d(dtype=wp.float64),
        overlap: wp.float64,
        radius: wp.float64,
        mass: wp.float64,
        dt: wp.float64,
        force: wp.array(dtype=vec),
        torque: wp.array(dtype=vec),
        spring: wp.array(dtype=vec),
        spin_history: wp.array(dtype=spin_type),
    ):
        t = vec()
        s = spin_type()
        for k in range(normals.shape[0]):
            f, m, t, s = contact_law(normals[k], overlap, velocities[k], spins[k], radius, mass, pair, 0, t, s, dt)
            force[k] = f
            torque[k] = m
            spring[k] = t
            spin_history[k] = s

    table = MaterialTable()
    table.add(material)
    steps = len(normals)
    out = [wp.zeros(steps, dtype=vec), wp.zeros(steps, dtype=vec), wp.zeros(steps, dtype=vec)]
    out.append(wp.zeros(steps, dtype=spin_type))
    wp.launch(
        along,
        dim=1,
        inputs=[
            wp.array(normals, dtype=vec),
            wp.array(velocities, dtype=vec),
            wp.array(spins, dtype=vec),
            wp.array(table.pair_table(), dtype=wp.float64),
            overlap,
            radius,
            mass,
            dt,
        ],
        outputs=out,
        device="cpu",
    )
    return [a.numpy() for a in out]


def random_history(rng, steps, stick_speed, angular_scale):
    """A wandering normal, and tangential velocities and spins whose speeds cross the stick speed
    often (log-uniform over four decades), in bursts of a few steps."""
    normal = np.array([0.0, 0.0, 1.0])
    normals, velocities, spins = [], [], []
    while len(normals) < steps:
        burst = int(rng.integers(1, 20))
        speed = stick_speed * 10 ** rng.uniform(-2, 2)
        direction = rng.normal(size=3)
        spin = angular_scale * 10 ** rng.uniform(-2, 2) * rng.normal(size=3)
        for _ in range(burst):
            normal = normal + 0.01 * rng.normal(size=3)
            normal /= np.linalg.norm(normal)
            v = direction - direction.dot(normal) * normal
            normals.append(normal.copy())
            velocities.append(speed * v / max(np.linalg.norm(v), 1e-30))
            spins.append(spin)
    return np.array(normals[:steps]), np.array(velocities[:steps]), np.array(spins[:steps])


def element_energy(law, material, overlap, radius, spring, spin_history):
    """Energy stored in the tangential, rolling and twisting springs [J] (their stiffnesses as in
    soil/contact.py, fixed for a fixed overlap)."""
    table = MaterialTable()
    table.add(material)
    e_star, g_star = table.pair_table()[0, :2]
    sqrt_rd = math.sqrt(radius * overlap)
    kt = 8 * g_star * sqrt_rd
    energy = 0.5 * kt * (spring**2).sum(axis=1)
    if law.rolling:
        kr = 2.25 * material.rolling_friction**2 * radius**2 * 2 * e_star * sqrt_rd
        energy += 0.5 * kr * (spin_history[:, :3] ** 2).sum(axis=1)
    if law.twisting:
        energy += 0.5 * (4 * g_star * sqrt_rd * radius * overlap) * spin_history[:, 3] ** 2
    return energy


@pytest.mark.parametrize(
    "law",
    [ContactLaw(), ContactLaw(rolling=True, twisting=True), ContactLaw(damping=False, rolling=True, twisting=True)],
    ids=["friction", "rolling-twisting", "undamped"],
)
def test_the_tangential_element_never_returns_more_energy_than_it_stored(law):
    """Along random motions with stick/slip switches, what the element gives back to the motion,
    -sum(F_T . v_T + M . w) dt, never exceeds what it stores (the springs start unloaded):
    E_stored(t) + sum(F_T . v_T + M . w) dt <= 0 at every step, and each step dissipates."""
    material = Material(
        youngs_modulus=1e6,
        stick_angle=math.radians(30),
        slip_angle=math.radians(20),
        stick_speed=1e-3,
        rolling_friction=0.2,
    )
    radius, overlap, mass, dt = 2e-3, 2e-6, 1e-4, 1e-5
    rng = np.random.default_rng(7)
    normals, velocities, spins = random_history(rng, 4000, material.stick_speed, material.stick_speed / radius)
    force, torque, spring, spin_history = drive_one_contact(
        law, material, overlap, radius, mass, normals, velocities, spins, dt
    )
    tangential_force = force - (force * normals).sum(axis=1)[:, None] * normals
    power = (tangential_force * velocities).sum(axis=1) + (torque * spins).sum(axis=1)
    balance = element_energy(law, material, overlap, radius, spring, spin_history) + np.cumsum(power * dt)
    roundoff = 1e-12 * float(np.sum(np.abs(power) * dt))
    assert np.all(np.diff(balance) <= roundoff)
    assert balance[-1] < 0
    # the check can fail: the switch this law replaced (on slipping, the spring set to hold the
    # full slip force) makes energy out of nothing along the same motions
    old_force, old_spring = former_switch(material, overlap, radius, normals, velocities, dt)
    old_power = (old_force * velocities).sum(axis=1)
    no_spin = np.zeros((len(normals), 3))
    old_balance = element_energy(ContactLaw(), material, overlap, radius, old_spring, no_spin)
    old_balance += np.cumsum(old_power * dt)
    table = MaterialTable()
    table.add(material)
    e_star, g_star = table.pair_table()[0, :2]
    slip_force = 4 / 3 * e_star * math.sqrt(radius) * overlap**1.5 * math.tan(material.slip_angle)
    slip_energy = slip_force**2 / (2 * 8 * g_star * math.sqrt(radius * overlap))  # a spring at the slip force
    assert np.diff(old_balance).max() > 0.01 * slip_energy


def former_switch(material, overlap, radius, normals, velocities, dt):
    """The tangential element before the passive switch, undamped, in numpy: on slipping (by force
    or by speed) the spring was set to hold the full slip force against the sliding."""
    table = MaterialTable()
    table.add(material)
    e_star, g_star = table.pair_table()[0, :2]
    fn = 4 / 3 * e_star * math.sqrt(radius) * overlap**1.5
    kt = 8 * g_star * math.sqrt(radius * overlap)
    spring, forces, springs = np.zeros(3), [], []
    for n, v in zip(normals, velocities):
        length = np.linalg.norm(spring)
        spring = spring - spring.dot(n) * n
        if np.linalg.norm(spring) > 0:
            spring *= length / np.linalg.norm(spring)
        trial = spring + v * dt
        kelvin = -kt * trial
        speed = np.linalg.norm(v)
        if np.linalg.norm(kelvin) <= fn * math.tan(material.stick_angle) and speed <= material.stick_speed:
            force, spring = kelvin, trial
        else:
            force = -fn * math.tan(material.slip_angle) * v / speed
            spring = -force / kt
        forces.append(force)
        springs.append(spring)
    return np.array(forces), np.array(springs)


@pytest.mark.parametrize("partner", ["wall", "grain"])
def test_twisting_resistance_stops_a_spinning_sphere_at_the_coulomb_rate(partner):
    """A sphere spinning about the normal of its contact: tangential friction sees no sliding, so
    without twisting resistance it spins for ever. With it, the plastic moment 2/3 a F_N tan(phi_g)
    (a = sqrt(R* delta), the static Hertz patch) stops it at I dw/dt = -M. On a fixed grain the
    neighbour list is rebuilt every step (a skin of 1e-12 m): the twist angle must survive it."""
    radius, g, w0 = 5e-3, 9.81, 20.0
    material = Material(youngs_modulus=1e7, restitution=0.3, stick_angle=0.5, slip_angle=0.4)
    mass = 2600 * 4 / 3 * math.pi * radius**3
    e_star = 1 / (2 * (1 - 0.3**2) / 1e7)
    r_eff = radius if partner == "wall" else radius / 2
    overlap = (3 * mass * g / (4 * e_star * math.sqrt(r_eff))) ** (2 / 3)
    moment = 2 / 3 * math.sqrt(r_eff * overlap) * mass * g * math.tan(0.4)
    deceleration = moment / (0.4 * mass * radius**2)
    spins = {}
    for twisting in (False, True):
        builder = SoilBuilder(gravity=g)
        soil = builder.add_material(material)
        if partner == "wall":
            builder.add_plane((0, 0, 0), (0, 0, 1), soil)
            builder.add_particle((0, 0, radius - overlap), radius, soil, angular_velocity=(0, 0, w0))
        else:
            builder.add_particle((0, 0, -radius), radius, soil, fixed=True)
            builder.add_particle((0, 0, radius - overlap), radius, soil, angular_velocity=(0, 0, w0))
        model, state, control = builder.finalize("cpu", "double", law=ContactLaw(twisting=twisting))
        sim = Simulation(model, state, control, neighbours=NeighbourSettings(skin=1e-12))
        sim.run(0.5 * w0 / deceleration, 1e-5)
        spins[twisting] = sim.angular_velocities()[-1, 2]
    assert spins[False] == pytest.approx(w0, rel=1e-6)
    assert spins[True] == pytest.approx(0.5 * w0, rel=0.02)


def test_a_state_saved_without_twisting_loads_into_a_law_with_it_and_back():
    """Spin histories of 3 (rolling) and 4 (rolling and twist) components convert on load: a bed
    settled without twisting can be driven with it; the twist starts at zero, the rolling is kept."""
    from test_neighbours import rain

    plain = rain("cpu", n_side=3, law=ContactLaw(rolling=True))
    plain.macro_step(200, 2e-5)
    saved = plain.state_dict()
    twisting = rain("cpu", n_side=3, law=ContactLaw(rolling=True, twisting=True))
    twisting.load_state_dict(saved)
    rolling = twisting.state.to_numpy()["pair_rolling"]
    assert rolling.shape[2] == 4 and np.all(rolling[..., 3] == 0)
    np.testing.assert_array_equal(rolling[..., :3], plain.state.to_numpy()["pair_rolling"])
    twisting.macro_step(200, 2e-5)
    back = rain("cpu", n_side=3, law=ContactLaw(rolling=True))
    back.load_state_dict(twisting.state_dict())
    assert back.state.to_numpy()["pair_rolling"].shape[2] == 3
