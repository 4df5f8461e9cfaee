"""The contact model against closed-form theory (docs/physics.md, section 4)."""

import math

import numpy as np
import pytest

from helpers import effective_modulus, hertz_rest_overlap, sphere_on_plane
from soil import ContactLaw, Material, Simulation, SoilBuilder, damping_ratio_for_restitution

GLASS = Material(youngs_modulus=48e9, poisson_ratio=0.2, density=2800.0, damping_ratio=0.0)


def hertz_impact_theory(radius, e_modulus, nu, density, closing_speed):
    """Max overlap, peak force and contact time of two equal elastic spheres (Hertz)."""
    e_star = 1.0 / (2 * (1 - nu**2) / e_modulus)
    r_eff = radius / 2
    m_eff = density * 4 / 3 * math.pi * radius**3 / 2
    k = 4.0 / 3.0 * e_star * math.sqrt(r_eff)
    max_overlap = (5 * m_eff * closing_speed**2 / (4 * k)) ** 0.4
    peak_force = k * max_overlap**1.5
    # contact time: 2 * integral_0^dmax d(delta)/sqrt(v^2 - 4k/(5m) delta^2.5) = 2.94 dmax / v
    contact_time = 2.9432 * max_overlap / closing_speed
    return max_overlap, peak_force, contact_time


@pytest.mark.parametrize("precision", ["double", "mixed", "single"])
def test_hertz_impact_matches_theory(device, precision):
    radius, speed = 0.01, 10.0
    theory = hertz_impact_theory(radius, 48e9, 0.2, 2800.0, 2 * speed)
    # the reference values (docs/physics.md, section 4) agree with the closed form
    assert theory[0] == pytest.approx(274.1e-6, rel=1e-3)
    assert theory[1] == pytest.approx(10.70e3, rel=1e-3)
    assert theory[2] == pytest.approx(40.34e-6, rel=1e-3)

    builder = SoilBuilder(gravity=0.0)
    builder.add_material(GLASS)
    builder.add_particle((0, 0, 0), radius, velocity=(speed, 0, 0))
    builder.add_particle((2 * radius + 1e-7, 0, 0), radius, velocity=(-speed, 0, 0))
    model, state, control = builder.finalize(device, precision, law=ContactLaw(damping=False, friction=False))
    sim = Simulation(model, state, control)
    dt = theory[2] / 4000
    max_overlap = peak = 0.0
    t_start = t_end = None
    for _ in range(8000):
        sim.step(dt)
        x = sim.positions()
        overlap = 2 * radius - (x[1, 0] - x[0, 0])
        if overlap > 0:
            t_start = sim.time if t_start is None else t_start
            max_overlap = max(max_overlap, overlap)
            peak = max(peak, abs(float(sim.state.force.numpy()[0, 0])))
        elif t_start is not None:
            t_end = sim.time
            break
    assert t_end is not None, "the spheres never separated"
    assert max_overlap == pytest.approx(theory[0], rel=0.01)
    assert peak == pytest.approx(theory[1], rel=0.01)
    assert t_end - t_start == pytest.approx(theory[2], rel=0.01)
    # elastic: the spheres leave with the speed they came in with
    assert sim.velocities()[1, 0] == pytest.approx(speed, rel=1e-3)


REGOLITH = Material(youngs_modulus=1e8, poisson_ratio=0.3, density=2600.0, restitution=0.1)


def settle_sphere(sim, gravity, steps):
    """Run a resting sphere until it is still; returns its overlap with the plane z=z0 (hi precision)."""
    # contact period at the static overlap sets the step
    dt = sim_period(sim, gravity) / 40
    sim.run(steps * dt, dt)
    return sim


def sim_period(sim, gravity):
    model = sim.model
    radius = float(model.radius_numpy()[0])
    mass = float(model.mass_numpy()[0])
    e_star = effective_modulus(REGOLITH, REGOLITH)
    delta = hertz_rest_overlap(mass, gravity, e_star, radius)
    stiffness = 2 * e_star * math.sqrt(radius * delta)
    return 2 * math.pi * math.sqrt(mass / stiffness)


@pytest.mark.parametrize("precision", ["double", "mixed"])
@pytest.mark.parametrize("gravity", [9.81, 5.7e-3])
def test_rest_overlap_matches_hertz(device, precision, gravity):
    radius = 5e-3
    sim = sphere_on_plane(device, precision, gravity, REGOLITH, radius=radius, origin=(0.3, -0.2, 0.5))
    settle_sphere(sim, gravity, 1500)
    mass = float(sim.model.mass_numpy()[0])
    expected = hertz_rest_overlap(mass, gravity, effective_modulus(REGOLITH, REGOLITH), radius)
    overlap = radius - (sim.positions()[0, 2] - 0.5)
    assert overlap == pytest.approx(expected, rel=0.02)
    # and the plane carries the weight
    assert float(sim.state.force.numpy()[0, 2]) == pytest.approx(mass * gravity, rel=0.02)


def test_single_precision_cannot_resolve_phobos_rest_but_mixed_can(device):
    """docs/physics.md, section 3: ~10 nm overlap vs float32 spacing of 6e-8 m at 0.5 m from the origin."""
    radius, gravity = 5e-3, 5.7e-3
    origin = (0.0, 0.0, 0.5)
    errors = {}
    for precision in ("single", "mixed"):
        sim = sphere_on_plane(device, precision, gravity, REGOLITH, radius=radius, origin=origin)
        settle_sphere(sim, gravity, 1500)
        mass = float(sim.model.mass_numpy()[0])
        expected = hertz_rest_overlap(mass, gravity, effective_modulus(REGOLITH, REGOLITH), radius)
        assert expected < np.spacing(np.float32(0.5)), "the scene must sit below float32 resolution"
        overlap = radius - (float(sim.state.position.numpy()[0, 2]) - 0.5)
        errors[precision] = abs(overlap / expected - 1.0)
    assert errors["mixed"] < 0.02
    assert errors["single"] > 0.5, f"single precision unexpectedly resolved the contact: {errors}"


def test_restitution_matches_target_for_every_speed(device):
    """e from 0.1 to 0.9 at impact speeds 0.01, 0.1, 1 m/s: all spheres in one scene."""
    targets = [0.1, 0.3, 0.5, 0.7, 0.9]
    speeds = [0.01, 0.1, 1.0]
    radius = 5e-3
    builder = SoilBuilder(gravity=0.0)
    floor = builder.add_material(Material(youngs_modulus=1e8, restitution=1.0, damping_ratio=0.0))
    builder.add_plane((0, 0, 0), (0, 0, 1), floor)
    cases = []
    for target in targets:
        # the floor has D = 0, the pair takes the mean: give the grain 2 D so the pair has D
        grain = builder.add_material(
            Material(youngs_modulus=1e8, damping_ratio=2 * damping_ratio_for_restitution(target))
        )
        for speed in speeds:
            x = 3 * radius * len(cases)
            builder.add_particle((x, 0, radius + 1e-9), radius, grain, velocity=(0, 0, -speed))
            cases.append((target, speed))
    model, state, control = builder.finalize(device, "double", law=ContactLaw(friction=False))
    sim = Simulation(model, state, control)
    # Hertz contact time grows as v^-1/5; resolve the fastest contact with 200 steps
    mass = float(model.mass_numpy()[0])
    e_star = 1 / (2 * (1 - 0.3**2) / 1e8)
    k = 4 / 3 * e_star * math.sqrt(radius)
    fast_time = 2.94 * (5 * mass * 1.0**2 / (4 * k)) ** 0.4 / 1.0
    slow_time = fast_time * (0.01 / 1.0) ** -0.2
    dt = fast_time / 200
    sim.run(4 * slow_time, dt)
    assert np.all(sim.positions()[:, 2] > radius), "every sphere has left the floor"
    measured = sim.velocities()[:, 2] / np.array([s for _, s in cases])
    for (target, speed), e in zip(cases, measured):
        assert e == pytest.approx(target, abs=0.01), f"target {target} at {speed} m/s gave {e}"


@pytest.mark.parametrize("precision", ["double", "mixed"])
def test_box_boundary_with_its_own_material(device, precision):
    """A grain resting on a solid box whose material is 10x stiffer: the overlap is the
    Hertz overlap for the mixed pair E* (1/E* = (1-nu_g^2)/E_g + (1-nu_b^2)/E_b)."""
    radius, gravity = 5e-3, 9.81
    stiff = Material(youngs_modulus=1e9, poisson_ratio=0.25, restitution=0.1)
    builder = SoilBuilder(gravity=gravity)
    grain = builder.add_material(REGOLITH)
    box = builder.add_material(stiff)
    builder.add_box((-0.02, -0.02, -0.01), (0.02, 0.02, 0.1), box)
    builder.add_particle((0.001, 0.002, 0.1 + radius), radius, grain)
    model, state, control = builder.finalize(device, precision)
    sim = Simulation(model, state, control)
    e_star = effective_modulus(REGOLITH, stiff)
    mass = float(model.mass_numpy()[0])
    expected = hertz_rest_overlap(mass, gravity, e_star, radius)
    stiffness = 2 * e_star * math.sqrt(radius * expected)
    dt = 2 * math.pi * math.sqrt(mass / stiffness) / 40
    sim.run(1500 * dt, dt)
    overlap = radius - (sim.positions()[0, 2] - 0.1)
    assert overlap == pytest.approx(expected, rel=0.02)
    # the same grain beside the box (touching its +x face) feels a sideways push only
    builder = SoilBuilder(gravity=0.0)
    grain = builder.add_material(REGOLITH)
    box = builder.add_material(stiff)
    builder.add_box((-0.02, -0.02, -0.01), (0.02, 0.02, 0.1), box)
    builder.add_particle((0.02 + radius - 1e-5, 0.0, 0.05), radius, grain)
    sim = Simulation(*builder.finalize(device, precision))
    force = sim.state.force.numpy()[0]
    assert force[0] == pytest.approx(4 / 3 * e_star * math.sqrt(radius) * (1e-5) ** 1.5, rel=1e-4)
    assert abs(force[1]) < 1e-12 and abs(force[2]) < 1e-12
