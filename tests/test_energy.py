"""Energy conservation without damping and friction (docs/physics.md, section 4)."""

import numpy as np
import pytest

from soil import ContactLaw, Material, Simulation, SoilBuilder


def bouncing_box(device, precision):
    builder = SoilBuilder(gravity=9.81)
    mat = builder.add_material(Material(youngs_modulus=1e7, damping_ratio=0.0))
    builder.add_container((0, 0, 0), (0.04, 0.04, 0.04), mat, open_top=False)
    rng = np.random.default_rng(7)
    grid = np.stack(np.meshgrid(*[np.arange(3)] * 3, indexing="ij"), -1).reshape(-1, 3)
    positions = 0.008 + grid * 0.012 + rng.uniform(-1e-3, 1e-3, grid.shape)
    builder.add_particles(
        positions, rng.uniform(0.004, 0.005, len(grid)), mat, velocities=rng.normal(0, 0.3, grid.shape)
    )
    model, state, control = builder.finalize(device, precision, law=ContactLaw(damping=False, friction=False))
    return Simulation(model, state, control)


@pytest.mark.parametrize("precision", ["double", "mixed"])
def test_energy_drift_small_and_shrinking_with_dt(device, precision):
    drifts = []
    for dt in (4e-5, 2e-5):
        sim = bouncing_box(device, precision)
        e0 = sim.total_energy()
        worst = 0.0
        for _ in range(int(round(0.2 / dt / 20))):
            sim.run(20 * dt, dt)
            worst = max(worst, abs(sim.total_energy() - e0))
        drifts.append(worst / sim.kinetic_energy())
    assert drifts[0] < 0.02, drifts
    # velocity Verlet is second order: halving dt cuts the error about four times
    assert drifts[1] < 0.5 * drifts[0], drifts
