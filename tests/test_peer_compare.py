"""Our soil against LAMMPS (GRANULAR) on the same scene: the same physics class must
give the same macroscopic bed (DESIGN.md section 7)."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.peers import lammps_peer  # noqa: E402
from soil import ContactLaw, Material, Simulation, SoilBuilder  # noqa: E402

pytestmark = pytest.mark.skipif(not lammps_peer.lammps_available(), reason="LAMMPS not installed (pip install .[peer])")


def test_settled_bed_matches_lammps():
    """400 spheres dropped into the same box from the same positions, Hertz-Mindlin with
    Coulomb friction (stick = slip angle, no stick speed limit), e = 0.5, settled for 0.25 s:
    the grains' mean height, the height deciles and the kinetic energy left agree with LAMMPS."""
    density, youngs, poisson, mu, e = 2600.0, 1e7, 0.3, 0.5, 0.5
    box_hi = np.array([0.06, 0.06, 0.3])
    positions, radii = lammps_peer.make_random_fill(400, 2.5e-3, 0.2, (0, 0, 0), box_hi, seed=4)
    dt = 0.2 * lammps_peer.rayleigh_time_step(radii.min(), density, youngs, poisson)
    steps = int(0.25 / dt)
    peer = lammps_peer.run_bed(positions, radii, density, youngs, poisson, mu, e, 0.0, (0, 0, 0), box_hi,
                               (0, 0, -9.81), dt, steps)

    builder = SoilBuilder(gravity=9.81)
    angle = math.atan(mu)
    mat = builder.add_material(Material(youngs_modulus=youngs, poisson_ratio=poisson, density=density,
                                        restitution=e, stick_angle=angle, slip_angle=angle, stick_speed=1e9))
    builder.add_container((0, 0, 0), box_hi, mat)
    builder.add_particles(positions, radii, mat)
    model, state, control = builder.finalize("cpu", "double", law=ContactLaw())
    sim = Simulation(model, state, control)
    sim.run(steps * dt, dt)
    ours = sim.positions()[np.argsort(model.particle_order)]

    theirs = peer["positions"]
    mean_height = (ours[:, 2].mean(), theirs[:, 2].mean())
    assert mean_height[0] == pytest.approx(mean_height[1], rel=0.02), mean_height
    # the height profile through the bed, not one grain on top: deciles of z
    deciles = np.linspace(10, 90, 9)
    np.testing.assert_allclose(np.percentile(ours[:, 2], deciles), np.percentile(theirs[:, 2], deciles), rtol=0.04)
    # both settled: little kinetic energy compared with the potential energy released
    mass = density * 4 / 3 * math.pi * radii**3
    released = float(np.sum(mass * 9.81 * (positions[:, 2] - ours[:, 2])))
    assert sim.kinetic_energy() < 1e-3 * released
    assert peer["kinetic_energy"] < 1e-3 * released
