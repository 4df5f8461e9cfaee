"""The soil side's checkpoint state: DemSoil.state_dict() continues a coupled run bit for bit."""

import warnings

import numpy as np

from cosim.contract import WheelKinematics
from cosim.dem_soil import DemSoil, WallProximityWarning
from soil import GrouserWheel, Material, Simulation, SoilBuilder

WHEEL = GrouserWheel(radius=0.02, width=0.012, grouser_count=8, grouser_height=0.002, grouser_thickness=0.0015)


def soil_with_wheel(device):
    """A few layers of grains in a small container and a grousered wheel pressed into them;
    the container is so small that the wheel is near its walls (the warning flag is set)."""
    builder = SoilBuilder(gravity=9.81)
    mat = builder.add_material(Material(youngs_modulus=1e6, restitution=0.3))
    builder.add_container((0, 0, 0), (0.06, 0.03, 0.1), mat)
    rng = np.random.default_rng(2)
    grid = np.stack(np.meshgrid(np.arange(9), np.arange(4), np.arange(3), indexing="ij"), -1).reshape(-1, 3)
    builder.add_particles(0.0035 + grid * 0.0068 + rng.uniform(-2e-4, 2e-4, grid.shape), 0.003, mat)
    builder.add_wheel(WHEEL, mat)
    model, state, control = builder.finalize(device, "double")
    return DemSoil(Simulation(model, state, control), 1e-4, surface_height=0.02)


def kinematics(t):
    """The wheel rolls along +x while pressing down into the grains."""
    return [
        WheelKinematics(
            np.array([0.02 + 0.05 * t, 0.015, 0.04 - 0.05 * t]),
            np.array([1.0, 0, 0, 0]),
            np.array([0.05, 0.0, -0.05]),
            np.array([0.0, 2.5, 0.0]),
        )
    ]


def advance(soil, start, macro_steps, macro=1e-3):
    wrenches = []
    for k in range(start, start + macro_steps):
        wrenches.append(soil.advance((k + 1) * macro, kinematics(k * macro))[0])
    return wrenches


def test_dem_soil_state_dict_continues_bit_for_bit(device, tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WallProximityWarning)
        reference = soil_with_wheel(device)
        advance(reference, 0, 5)
        saved = reference.state_dict()
        assert saved["warned_wall"]  # the wheel is near a wall: the flag is part of the state
        tail = advance(reference, 5, 5)
        np.savez(tmp_path / "soil.npz", **saved)
        with np.load(tmp_path / "soil.npz", allow_pickle=False) as f:
            loaded = {key: f[key] for key in f.files}
        resumed = soil_with_wheel(device)
        resumed.load_state_dict(loaded)
        assert resumed.state_dict()["warned_wall"]
        resumed_tail = advance(resumed, 5, 5)
    assert any(w.contact_count > 0 for w in tail)  # the wheel works in the grains
    for a, b in zip(tail, resumed_tail):
        np.testing.assert_array_equal(a.force, b.force)
        np.testing.assert_array_equal(a.torque, b.torque)
        assert a.work_on_soil == b.work_on_soil
    for name, array in reference.sim.state.arrays.items():
        np.testing.assert_array_equal(getattr(resumed.sim.state, name).numpy(), array.numpy(), err_msg=name)
