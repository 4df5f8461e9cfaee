"""The device-resident macro step of the coupled soil side: one device->host read per macro
step, wheel poses computed on the device as the host would, wrench sums as step-by-step sums."""

import warnings

import numpy as np
import warp as wp

from cosim.contract import WheelKinematics
from cosim.dem_soil import DemSoil, WallProximityWarning
from soil import GrouserWheel, Material, Simulation, SoilBuilder
from soil.control import quaternion_integrate, quaternion_slerp

WHEEL = GrouserWheel(radius=0.02, width=0.012, grouser_count=8, grouser_height=0.002, grouser_thickness=0.0015)


def soil(device, precision="double"):
    """Three layers of grains and a grousered wheel above them."""
    builder = SoilBuilder(gravity=9.81)
    mat = builder.add_material(Material(youngs_modulus=1e6, restitution=0.3))
    builder.add_container((0, 0, 0), (0.09, 0.03, 0.1), mat)
    rng = np.random.default_rng(2)
    grid = np.stack(np.meshgrid(np.arange(13), np.arange(4), np.arange(3), indexing="ij"), -1).reshape(-1, 3)
    builder.add_particles(0.0035 + grid * 0.0068 + rng.uniform(-2e-4, 2e-4, grid.shape), 0.003, mat)
    builder.add_wheel(WHEEL, mat)
    model, state, control = builder.finalize(device, precision)
    return DemSoil(Simulation(model, state, control), 1e-4, surface_height=0.02)


def pose(t):
    """The wheel rolls along +x, pressing down, and yaws a little."""
    return WheelKinematics(
        np.array([0.03 + 0.05 * t, 0.015, 0.0415 - 0.3 * t]),
        quaternion_integrate([1.0, 0, 0, 0], np.array([0, 0, 0.3]), t),
        np.array([0.05, 0.0, -0.3]),
        np.array([0.0, 2.5, 0.3]),
    )


class ReadCounter:
    """Counts device->host reads (wp.array.numpy: a copy from a GPU; the same call on the CPU)."""

    def __init__(self, monkeypatch):
        self.count = 0
        original = wp.array.numpy

        def counted(array):
            self.count += 1
            return original(array)

        monkeypatch.setattr(wp.array, "numpy", counted)


def test_a_coupled_macro_step_reads_the_device_once(device, monkeypatch):
    """Ten DEM steps per macro step, the wheel working in the grains: at most one device->host
    read per DemSoil.advance (before: three per DEM step)."""
    side = soil(device)
    counter = ReadCounter(monkeypatch)
    reads = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WallProximityWarning)
        for k in range(8):
            before = counter.count
            wrench = side.advance((k + 1) * 1e-3, [pose(k * 1e-3)])[0]
            reads.append(counter.count - before)
    assert wrench.contact_count > 0, "the wheel works in the grains"
    assert max(reads) <= 1, reads


def test_device_wheel_path_and_wrench_sums_match_stepping_from_the_host(device):
    """advance() poses the wheel on the device along the macro step's path and sums its wrench
    there; stepping the same path from the host (pose set before each step, wrench read after
    each) gives the same wrench, work and end pose (to rounding of the pose arithmetic)."""
    on_device, on_host = soil(device), soil(device)
    h = 1e-4
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WallProximityWarning)
        for k in range(6):
            t0, t1 = k * 1e-3, (k + 1) * 1e-3
            start, end = pose(t0), (pose(t1) if k % 2 else None)  # constant velocity, then interpolated
            wrench = on_device.advance(t1, [start], None if end is None else [end])[0]
            sim = on_host.sim
            force, torque, work = np.zeros(3), np.zeros(3), 0.0
            for step in range(1, 11):
                tau = step * h
                if end is None:
                    position = start.position + start.linear_velocity * tau
                    orientation = quaternion_integrate(start.orientation, start.angular_velocity, tau)
                    velocity, spin = start.linear_velocity, start.angular_velocity
                else:
                    a = tau / 1e-3
                    position = (1 - a) * start.position + a * end.position
                    orientation = quaternion_slerp(start.orientation, end.orientation, a)
                    velocity = (1 - a) * start.linear_velocity + a * end.linear_velocity
                    spin = (1 - a) * start.angular_velocity + a * end.angular_velocity
                sim.control.set_body_motion(0, position, orientation, velocity, spin)
                sim.step(h)
                f = sim.state.body_force.numpy()[0].astype(np.float64)
                t = sim.state.body_torque.numpy()[0].astype(np.float64)
                force, torque, work = force + f, torque + t, work - (f @ velocity + t @ spin) * h
            scale = np.linalg.norm(force / 10) + 1e-12
            np.testing.assert_allclose(wrench.force, force / 10, rtol=0, atol=1e-6 * scale)
            np.testing.assert_allclose(wrench.torque, torque / 10, rtol=0, atol=1e-6 * scale * 0.02)
            assert abs(wrench.work_on_soil - work) <= 1e-6 * abs(work) + 1e-15
            np.testing.assert_allclose(
                on_device.sim.state.body_position.numpy()[0], sim.state.body_position.numpy()[0], rtol=0, atol=1e-12
            )
            np.testing.assert_allclose(
                on_device.sim.state.body_rotation.numpy()[0], sim.state.body_rotation.numpy()[0], rtol=0, atol=1e-12
            )
    assert wrench.contact_count > 0


def test_macro_steps_of_whole_dem_steps_step_with_dt_and_keep_the_coupler_clock(device, monkeypatch):
    """A coupler's macro step of ten DEM steps, its times summed in floats as a coupler sums
    them (late in a long run, where the clock's last bit is 7e-15 s): every DEM step is the
    scene's dt itself, not a length that changes in its last bits from one macro step to the
    next (each new length is a new captured step), and the soil's time is the coupler's."""
    side = soil(device)
    side.sim.state.time = 37.0  # a late start: a coarse clock
    lengths = []
    macro_step = side.sim.macro_step

    def recording(steps, dt, **kwargs):
        lengths.append(dt)
        return macro_step(steps, dt, **kwargs)

    monkeypatch.setattr(side.sim, "macro_step", recording)
    t, macro = 37.0, 10 * 1e-4
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WallProximityWarning)
        for k in range(12):
            start = pose(k * macro)
            t += macro
            side.advance(t, [start])
            assert side.time == t
    assert lengths == [1e-4] * 12, lengths
