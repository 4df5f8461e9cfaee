"""Jolt-Beeman integration and PID step control against Hertz theory (docs/physics.md, section 2)."""

import math

import numpy as np
import pytest

from soil import ContactLaw, JoltBeeman, Material, Simulation, SoilBuilder, StepController, VelocityVerlet, advisor

GLASS = Material(youngs_modulus=48e9, poisson_ratio=0.2, density=2800.0, damping_ratio=0.0)
RADIUS, SPEED = 0.01, 1.0
MASS = GLASS.density * 4.0 / 3.0 * math.pi * RADIUS**3
IMPACT = advisor.hertz_impact(
    GLASS.youngs_modulus / (2 * (1 - GLASS.poisson_ratio**2)), RADIUS / 2, MASS / 2, 2 * SPEED
)
CONTACT_TIME = IMPACT.contact_time
GAP = 2 * SPEED * 5 * CONTACT_TIME  # free flight of 5 contact times before the impact
DURATION = GAP / (2 * SPEED) + 11 * CONTACT_TIME  # ... and 10 after it


def two_spheres(device, integrator=None):
    """Two glass spheres closing at 2 x 1 m/s, no damping, no friction, no gravity."""
    builder = SoilBuilder(gravity=0.0)
    builder.add_material(GLASS)
    builder.add_particle((0, 0, 0), RADIUS, velocity=(SPEED, 0, 0))
    builder.add_particle((2 * RADIUS + GAP, 0, 0), RADIUS, velocity=(-SPEED, 0, 0))
    model, state, control = builder.finalize(device, "double", law=ContactLaw(damping=False, friction=False))
    return Simulation(model, state, control, integrator=integrator)


def impact_error(sim):
    """Error against Hertz theory: after an elastic impact the spheres separate at 2 v,
    delayed by the contact time. max(separation error / max overlap, speed error / 2 v)."""
    separation_theory = 2 * RADIUS + 2 * SPEED * (sim.time - GAP / (2 * SPEED) - CONTACT_TIME)
    x, v = sim.positions(), sim.velocities()
    return max(
        abs(x[1, 0] - x[0, 0] - separation_theory) / IMPACT.max_overlap,
        abs(v[1, 0] - v[0, 0] - 2 * SPEED) / (2 * SPEED),
    )


def adaptive_run(device, tolerance):
    sim = two_spheres(device, JoltBeeman())
    stats = sim.run_adaptive(
        DURATION, StepController(tolerance=tolerance, dt_max=CONTACT_TIME, dt_min=1e-5 * CONTACT_TIME)
    )
    assert sim.time == pytest.approx(DURATION, rel=1e-12)
    return sim, stats


def test_theory_values_of_the_impact():
    # the closed form the tests compare with (the Hertz impact of docs/physics.md, section 4, at 2 x 10 m/s)
    fast = advisor.hertz_impact(48e9 / (2 * (1 - 0.04)), 0.005, MASS / 2, 20.0)
    assert fast.max_overlap == pytest.approx(274.1e-6, rel=1e-3)
    assert fast.peak_force == pytest.approx(10.70e3, rel=1e-3)
    assert fast.contact_time == pytest.approx(40.34e-6, rel=1e-3)


def test_fixed_step_beeman_positions_equal_verlet(device):
    """Beeman's positions are Verlet's (same recurrence x+ = 2x - x- + a dt^2): with a fixed
    step both integrators give the same trajectory up to rounding."""
    dt = CONTACT_TIME / 50
    sims = [two_spheres(device, integrator) for integrator in (JoltBeeman(), VelocityVerlet())]
    for sim in sims:
        sim.run(DURATION, dt)
    np.testing.assert_allclose(sims[0].positions(), sims[1].positions(), rtol=0, atol=1e-12)
    assert impact_error(sims[0]) < 2e-3


def test_variable_steps_keep_second_order(device):
    """The variable-step form (a_minus rescaled by dt/dt_previous) keeps the global order 2:
    a sphere oscillating in a Hertz contact under gravity (pressed to 1.6x its rest overlap,
    never leaving the plane), random step ratios in [0.5, 2], the sequence halved twice:
    the error against an independent solution (scipy, rtol 1e-12) falls ~4x per halving.
    (Using the previous acceleration unscaled would make it first order.)"""
    from scipy.integrate import solve_ivp

    from helpers import hertz_rest_overlap, sphere_on_plane

    g, r = 9.81, 5e-3
    mat = Material(youngs_modulus=1e7, poisson_ratio=0.3, density=2600.0, damping_ratio=0.0)
    e_star = 1.0 / (2 * (1 - 0.3**2) / 1e7)
    mass = 2600.0 * 4 / 3 * math.pi * r**3
    rest = hertz_rest_overlap(mass, g, e_star, r)
    k = 4.0 / 3.0 * e_star * math.sqrt(r)
    period = 2 * math.pi / math.sqrt(1.5 * k * math.sqrt(rest) / mass)
    duration = 3 * period
    exact = solve_ivp(
        lambda t, s: [s[1], -g + k * max(-s[0], 0.0) ** 1.5 / mass],
        (0, duration),
        [-1.6 * rest, 0.0],
        rtol=1e-12,
        atol=1e-18,
        method="DOP853",
    ).y[:, -1]
    pattern = np.random.default_rng(5).uniform(0.5, 2.0, 64)
    errors = []
    for base in (period / 40, period / 80, period / 160):
        sim = sphere_on_plane(
            device, "double", g, mat, radius=r, overlap=1.6 * rest, law=ContactLaw(damping=False, friction=False)
        )
        sim.integrator = JoltBeeman()
        step = 0
        while duration - sim.time > 1e-15:
            sim.step(min(base * pattern[step % len(pattern)], duration - sim.time))
            step += 1
        z, vz = sim.positions()[0, 2] - r, sim.velocities()[0, 2]
        errors.append(max(abs(z - exact[0]) / rest, abs(vz - exact[1]) * period / rest))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all((orders > 1.7) & (orders < 2.4)), (errors, orders)


def test_error_falls_as_tolerance_tightens(device):
    """Hertz impact, tolerance 1e-3 .. 1e-6: the error against theory falls (>= 20x over
    the three decades, and at every decade from 1e-4 on) while the work grows."""
    errors, evaluations = [], []
    for tolerance in (1e-3, 1e-4, 1e-5, 1e-6):
        sim, stats = adaptive_run(device, tolerance)
        errors.append(impact_error(sim))
        evaluations.append(stats["evaluations"])
        assert stats["evaluations"] == stats["accepted"] + stats["rejected"]
    assert errors[3] < errors[0] / 20, errors
    assert errors[1] > errors[2] > errors[3], errors
    assert evaluations == sorted(evaluations), evaluations
    assert errors[3] < 1e-4, errors


def test_adaptive_needs_fewer_evaluations_than_fixed_step_at_equal_accuracy(device):
    """At tolerance 1e-6 the adaptive run reaches an error E_a. The largest fixed step
    (jolt-Beeman, dt = T_c / n, n on a sqrt(2) ladder) that reaches E_a costs at least 5x as
    many force evaluations: flight (10 of 11 contact times) is crossed in a few long steps.
    Measured here: about 255 evaluations adaptive vs about 2,800 fixed (ratio ~11)."""
    sim, stats = adaptive_run(device, 1e-6)
    target = impact_error(sim)
    fixed = None
    for n in (25 * 2 ** (k / 2) for k in range(12)):
        dt = CONTACT_TIME / n
        steps = int(math.ceil(DURATION / dt))
        candidate = two_spheres(device, JoltBeeman())
        candidate.run(DURATION, DURATION / steps)
        if impact_error(candidate) <= target:
            fixed = candidate.contacts.evaluations
            break
    assert fixed is not None, "no fixed step reached the adaptive accuracy"
    ratio = fixed / stats["evaluations"]
    print(f"adaptive {stats['evaluations']} evaluations (error {target:.3g}), fixed {fixed}: ratio {ratio:.1f}")
    assert ratio > 5, (fixed, stats)


def sliding_pile(device, capacity=16):
    """Three grains on a plane with friction: contact history (tangential springs) everywhere."""
    builder = SoilBuilder(gravity=9.81)
    mat = builder.add_material(Material(youngs_modulus=1e7, restitution=0.5, stick_speed=0.05))
    builder.add_plane((0, 0, 0), (0, 0, 1), mat)
    r = 5e-3
    builder.add_particles(
        [(0, 0, r * 0.999), (2 * r * 0.999, 0, r * 0.999), (r * 0.999, 0, r * (1 + 1.7305))],
        r,
        mat,
        velocities=[(0.02, 0, 0), (0.01, 0.01, 0), (0.0, 0.02, -0.01)],
    )
    model, state, control = builder.finalize(device, "double", contact_capacity=capacity)
    return Simulation(model, state, control, integrator=JoltBeeman())


class RecordingBeeman(JoltBeeman):
    """Records the input state of every attempted step (to see what a rejection left behind)."""

    def __init__(self):
        super().__init__()
        self.calls = []

    def step(self, model, state_in, state_out, control, dt, contacts):
        self.calls.append((float(dt.numpy()[0]), state_in.to_numpy()))  # dt: the device array the kernels read
        super().step(model, state_in, state_out, control, dt, contacts)


@pytest.mark.parametrize("capacity", [16, 1])
def test_rejected_step_restores_whole_state_bitwise(device, capacity):
    """A rejected step leaves the state (contact history included) bit for bit as it was,
    and a run with rejections equals a replay of only its accepted steps, bit for bit.
    capacity = 1 also exercises the history-overflow regrow inside adaptive steps."""
    sim = sliding_pile(device, capacity)
    sim.integrator = RecordingBeeman()
    accepted_dts = []
    stats = sim.run_adaptive(
        0.003,
        StepController(tolerance=1e-7, dt_max=2e-5, dt_initial=2e-5),
        callback=lambda s: accepted_dts.append(s.state.step_previous.numpy()[0]),
    )
    assert stats["rejected"] > 0 and stats["accepted"] > 10, stats
    assert np.any(sim.state.contact_count.numpy() > 0)
    calls = sim.integrator.calls
    retries = 0
    for (dt_a, before), (dt_b, after) in zip(calls, calls[1:]):
        if after["time"] == before["time"]:  # the step was rejected (or redone after an overflow)
            retries += 1
            assert dt_b <= dt_a
            for name in before:
                np.testing.assert_array_equal(after[name], before[name], err_msg=name)
    assert retries >= stats["rejected"]

    replay = sliding_pile(device, capacity)
    for dt in accepted_dts:
        replay.step(float(dt))
    final, replayed = sim.state.to_numpy(), replay.state.to_numpy()
    for name in final:
        np.testing.assert_array_equal(replayed[name], final[name], err_msg=name)


@pytest.mark.parametrize("gamma_dt, expected", [(0.5, 0.855), (0.7, 1.196)])
def test_damped_contact_grows_or_decays_as_the_linear_analysis_says(device, gamma_dt, expected):
    """Jolt-Beeman evaluates damping at the PREDICTED velocity, so a damped mode is stable
    only for gamma dt <= 0.60 (benchmarks/jolt_beeman_damped_stability.py). A sphere at
    rest on a plane, Lehr damping D = 1 (gamma = 2 D omega at the rest overlap, so omega dt
    = gamma dt / 2), nudged: the analysis gives a dominant per-step factor -0.855 at
    gamma dt = 0.5 (the nudge decays) and -1.196 at 0.7 (it grows, alternating sign); the
    run must show the same."""
    from helpers import effective_modulus, hertz_rest_overlap

    material = Material(youngs_modulus=1e7, poisson_ratio=0.3, density=2600.0, damping_ratio=1.0)
    radius, gravity = 5e-3, 9.81
    mass = material.density * 4.0 / 3.0 * math.pi * radius**3
    e_star = effective_modulus(material, material)
    rest = hertz_rest_overlap(mass, gravity, e_star, radius)
    omega = math.sqrt(2 * e_star * math.sqrt(radius * rest) / mass)
    dt = gamma_dt / (2 * 1.0 * omega)
    nudge = 1e-2 if expected < 1 else 1e-8  # relative to the rest overlap: stays linear for 80 steps
    builder = SoilBuilder(gravity=gravity)
    builder.add_material(material)
    builder.add_plane((0, 0, 0), (0, 0, 1))
    builder.add_particle((0, 0, radius - rest), radius, velocity=(0, 0, nudge * rest * omega))
    model, state, control = builder.finalize(device, "double", law=ContactLaw(friction=False))
    sim = Simulation(model, state, control, integrator=JoltBeeman())
    displacement = []
    for _ in range(80):
        sim.run(dt, dt)
        displacement.append(sim.positions()[0, 2] - (radius - rest))
    displacement = np.array(displacement)
    if expected < 1:  # stable: the nudge dies out (to the rounding of the rest position)
        assert np.abs(displacement[-10:]).max() < 1e-3 * np.abs(displacement[:10]).max()
        return
    assert np.all(np.sign(displacement[50:-1]) != np.sign(displacement[51:])), "the period-2 mode of the analysis"
    growth_per_step = (np.abs(displacement[70:80]).max() / np.abs(displacement[40:50]).max()) ** (1 / 30)
    assert growth_per_step == pytest.approx(expected, rel=0.02)
