"""soil.advisor against hand calculations and against the measured stability limit."""

import math

import pytest

from helpers import effective_modulus, hertz_rest_overlap, sphere_on_plane
from soil import ContactLaw, JoltBeeman, Material, advisor, macroscopic_stiffness, rayleigh_time_step


def test_rayleigh_time_step_by_hand():
    # E = 1e8 Pa, nu = 0.3: G = 1e8 / 2.6 = 3.84615e7 Pa; sqrt(2600 / G) = 8.22192e-3 s/m;
    # pi * 2.5e-3 * 8.22192e-3 = 6.45750e-5; / (0.1631 * 0.3 + 0.8766 = 0.92553) = 6.97709e-5 s
    assert rayleigh_time_step(1e8, 0.3, 2600.0, 2.5e-3) == pytest.approx(6.97709e-5, rel=1e-5)
    # it scales as R sqrt(rho / E): 10x the radius, 100x the modulus -> the same step
    assert rayleigh_time_step(1e10, 0.3, 2600.0, 2.5e-2) == pytest.approx(6.97709e-5, rel=1e-5)


def test_macroscopic_stiffness_paper_eq10_by_hand():
    # z_h = 0.05 m, p = 10 Pa, u = 0.01, r = 2.5 mm, rho_p = 2600 kg/m^3
    # Phobos: 3p + z_h rho g = 30 + 0.05 * 2600 * 5.7e-3 = 30.741 Pa; * 0.05 / (3 * 0.01 * 2.5e-3) = 20494 Pa
    assert macroscopic_stiffness(0.05, 10.0, 0.01, 2.5e-3, 2600.0, 5.7e-3) == pytest.approx(20494.0, rel=1e-4)
    # Earth: 30 + 1275.3 = 1305.3 Pa -> 870200 Pa
    assert macroscopic_stiffness(0.05, 10.0, 0.01, 2.5e-3, 2600.0, 9.81) == pytest.approx(870200.0, rel=1e-4)
    # vectors along gravity give the same; no wheel (p = 0): 0.05 * 0.741 / 7.5e-5 = 494 Pa
    assert macroscopic_stiffness(0.05, (0, 0, -10.0), (0, 0, 0.01), 2.5e-3, 2600.0, (0, 0, -5.7e-3)) == pytest.approx(
        20494.0, rel=1e-4
    )
    assert macroscopic_stiffness(0.05, 0.0, 0.01, 2.5e-3, 2600.0, 5.7e-3) == pytest.approx(494.0, rel=1e-4)
    # the Phobos bed material of soil.bed (2e5 Pa) satisfies it with room for a 10 Pa wheel
    from soil.bed import PHOBOS_REGOLITH

    assert PHOBOS_REGOLITH.youngs_modulus >= macroscopic_stiffness(0.05, 10.0, 0.01, 2.5e-3, 2600.0, 5.7e-3)


def test_recommended_time_step_by_hand():
    """E = 1e7, nu = 0.3, r = 5 mm, rho = 2600, g = 9.81, H = 20 r: impact speed sqrt(2 g H);
    the critical step 2 / omega at the impact overlap; dt_max = 0.3 of it."""
    mat = Material(youngs_modulus=1e7, poisson_ratio=0.3, density=2600.0)
    r, g = 5e-3, 9.81
    advice = advisor.recommended_time_step(mat, radius=r, gravity=g)
    speed = math.sqrt(2 * g * 20 * r)  # 0.990454 m/s
    mass = 2600.0 * 4 / 3 * math.pi * r**3  # 1.36136e-3 kg
    e_star = 1e7 / (2 * (1 - 0.09))  # 5.49451e6 Pa
    k = 4 / 3 * e_star * math.sqrt(r / 2)  # 3.66300e5 N/m^1.5
    overlap = (5 * (mass / 2) * speed**2 / (4 * k)) ** 0.4
    omega = math.sqrt(2 * e_star * math.sqrt(r / 2 * overlap) / (mass / 2))
    assert advice.impact_speed == pytest.approx(speed, rel=1e-9)
    assert advice.impact_overlap == pytest.approx(overlap, rel=1e-9)
    assert advice.critical_step == pytest.approx(2 / omega, rel=1e-9)
    assert advice.dt_max == pytest.approx(0.3 * 2 / omega, rel=1e-9)
    assert advice.contact_time == pytest.approx(advisor.hertz_contact_time(1e7, 0.3, 2600.0, r, speed), rel=1e-12)
    # for an impact the explicit limit is about half the contact time
    assert 0.4 < advice.critical_step / advice.contact_time < 0.6
    assert advice.dt_min < advice.dt_max


def test_largest_stable_step_brackets_the_linear_limit():
    """The paper's search on a sphere resting on a plane (no damping): a fixed step explodes
    once it passes the linear limit 2 / omega of the resting Hertz contact,
    omega^2 = 2 E* sqrt(R delta_rest) / m. The search brackets it within one growth factor."""
    r, g = 5e-3, 9.81
    mat = Material(youngs_modulus=1e7, poisson_ratio=0.3, density=2600.0, damping_ratio=0.0)
    mass = 2600.0 * 4 / 3 * math.pi * r**3
    e_star = effective_modulus(mat, mat)
    rest = hertz_rest_overlap(mass, g, e_star, r)
    limit = 2.0 / math.sqrt(2 * e_star * math.sqrt(r * rest) / mass)

    def make():
        sim = sphere_on_plane(
            "cpu", "double", g, mat, radius=r, overlap=1.01 * rest, law=ContactLaw(damping=False, friction=False)
        )
        sim.integrator = JoltBeeman()
        return sim

    search = advisor.largest_stable_step(make, duration=300 * limit, dt_start=0.5 * limit, growth=1.2)
    assert search.largest_stable < limit * 1.02 < search.first_unstable * 1.2, search.tried
    assert search.first_unstable == pytest.approx(1.2 * search.largest_stable)
    assert search.recommended == pytest.approx(0.5 * search.largest_stable)
    assert "diverged" in search.tried[-1][2]
