"""Rovers coupled to the DEM soil (issue: co-simulation): weight carried, convergence in H,
slip control on a bed."""

import math

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

from soil import GrouserWheel, Material, Simulation  # noqa: E402
from soil.bed import BedSpec, bed_metrics, build_bed, save_bed, settle, rayleigh_time_step  # noqa: E402
from cosim.coupler import Coupler  # noqa: E402
from cosim.controllers import SlipController  # noqa: E402
from cosim.dem_soil import DemSoil  # noqa: E402
from cosim.single_wheel import SingleWheelRig  # noqa: E402
from rover_models.mjcf import MMX_WHEELS, mmx_rover_xml, single_wheel_rig_xml  # noqa: E402
from rover_models.mujoco_rover import MujocoRover  # noqa: E402

WHEEL = GrouserWheel(radius=0.03, width=0.02, grouser_count=10, grouser_height=0.003, grouser_thickness=0.002)


def soil_material(gravity):
    # stiffness scaled with gravity (paper eq. 10: E ~ load): same overlap/radius and
    # the same number of steps per settling time at every g
    return Material(youngs_modulus=1e7 * gravity / 9.81, poisson_ratio=0.3, density=2600, restitution=0.2,
                    stick_angle=math.radians(30), slip_angle=math.radians(25), rolling_friction=0.1)


_beds = {}


def settled_bed(tmp_path_factory, gravity, length, width, depth=0.02, radius=3.5e-3):
    """A settled bed saved to HDF5 (cached per test session); returns (path, surface, dt)."""
    key = (gravity, length, width, depth, radius)
    if key not in _beds:
        spec = BedSpec(length=length, width=width, depth=depth, radius_mean=radius, radius_spread=0.15,
                       material=soil_material(gravity))
        sim = Simulation(*build_bed(spec, gravity).finalize("cpu", "double"))
        dt = 0.2 * rayleigh_time_step(spec.material, radius * 0.85)
        report = settle(sim, dt, ke_ratio=1e-3, max_time=60 * math.sqrt(radius / gravity))
        assert report["settled"], report
        metrics = bed_metrics(sim, spec)
        path = tmp_path_factory.mktemp("bed") / "bed.h5"
        save_bed(path, sim, spec, metrics)
        _beds[key] = (path, metrics["height"], dt)
    return _beds[key]


def small_rover_xml(gravity):
    return mmx_rover_xml(wheel_radius=WHEEL.radius, wheel_width=WHEEL.width, body_mass=0.5, leg_mass=0.05,
                         wheel_mass=0.1, body_size=(0.12, 0.1, 0.05), wheelbase=0.12, track=0.14,
                         leg_drop=0.03, gravity=(0, 0, -gravity))


@pytest.mark.parametrize("gravity", [9.81, 5.7e-3])
def test_rover_standing_on_a_dem_bed_carries_its_weight_without_hopping(tmp_path_factory, gravity):
    bed, surface, dt = settled_bed(tmp_path_factory, gravity, 0.24, 0.22)
    soil = DemSoil.from_bed(bed, [WHEEL] * 4, soil_material(gravity), dt, surface, device="cpu", precision="double")
    rover = MujocoRover(small_rover_xml(gravity), list(MMX_WHEELS), gravity=(0, 0, -gravity))
    # put the rover over the bed centre, grouser tips on the surface, wheels held still
    rover.data.qpos[0:3] = [0.12, 0.11, surface + WHEEL.outer_radius + 0.03]
    mujoco.mj_forward(rover.model, rover.data)
    rover.set_wheel_speeds([0.0] * 4)
    soil.place_wheels(rover.wheel_kinematics())
    coupler = Coupler(soil, rover, 10 * dt, gravity=(0, 0, -gravity))
    t_scale = math.sqrt(3.5e-3 / gravity)
    coupler.run(30 * t_scale)
    rec = coupler.records()
    settled = rec["time"] > 15 * t_scale
    weight = rover.total_mass * gravity
    total_up = rec["force"][settled, :, 2].sum(axis=1)
    assert np.mean(total_up) == pytest.approx(weight, rel=0.05)
    # no hopping: every wheel keeps touching the soil, the body does not bounce up
    assert np.all(rec["contact_count"][settled] > 0)
    body_vz = rec["linear_velocity"][settled, :, 2]
    assert np.max(np.abs(body_vz)) < 0.02 * math.sqrt(gravity * 0.03), "the rover hops"


def test_coupled_result_converges_as_the_macro_step_shrinks(tmp_path_factory):
    """A loaded wheel dropped on the bed and driven: the hub path with macro step H
    approaches the H = h_DEM path as H shrinks."""
    gravity = 9.81
    bed, surface, dt = settled_bed(tmp_path_factory, gravity, 0.12, 0.06)
    paths = {}
    for substeps in (1, 2, 4, 8, 16):
        soil = DemSoil.from_bed(bed, [WHEEL], soil_material(gravity), dt, surface, device="cpu",
                                precision="double", wall_clearance=0.0)
        rig = SingleWheelRig(mass=0.1, radius=WHEEL.radius, omega=2.0, hub=(0.06, 0.03, surface + WHEEL.outer_radius),
                             gravity=(0, 0, -gravity))
        soil.place_wheels(rig.wheel_kinematics())
        coupler = Coupler(soil, rig, substeps * dt, gravity=(0, 0, -gravity))
        samples = []
        coupler.run(0.08, callback=lambda c: samples.append((c.time, *rig.position)) if c.step_count % (16 // substeps) == 0 else None)
        paths[substeps] = np.array(samples)
    reference = paths[1]
    errors = [np.max(np.abs(paths[s][:, 1:] - reference[:, 1:])) for s in (16, 8, 4, 2)]
    assert all(later < earlier for earlier, later in zip(errors, errors[1:])), errors
    assert errors[-1] < 0.5 * errors[0], errors


def test_slip_controller_holds_target_slip_on_a_bed(tmp_path_factory):
    gravity, target = 9.81, 0.3
    bed, surface, dt = settled_bed(tmp_path_factory, gravity, 0.3, 0.06)
    soil = DemSoil.from_bed(bed, [WHEEL], soil_material(gravity), dt, surface, device="cpu", precision="double")
    xml = single_wheel_rig_xml(wheel_radius=WHEEL.radius, wheel_width=WHEEL.width, wheel_mass=0.05,
                               carriage_mass=0.1, ballast_mass=0.15, motor_kv=0.5,
                               hub_height=surface + WHEEL.outer_radius - 0.001, gravity=(0, 0, -gravity))
    # the rig runs along y = 0; put it on the bed's centre line (the bed spans y in [0, 0.06])
    xml = xml.replace('<body name="carriage" pos="0 0 ', '<body name="carriage" pos="0 0.03 ', 1)
    rover = MujocoRover(xml, ["wheel"], gravity=(0, 0, -gravity))
    rover.data.qpos[0] = 0.06  # carriage: start near the bed start, clear of its end wall
    mujoco.mj_forward(rover.model, rover.data)
    soil.place_wheels(rover.wheel_kinematics())
    controller = SlipController(target, WHEEL.radius, 1, kp=1.0, ki=20.0, omega_min=1.0, omega_max=40.0)
    coupler = Coupler(soil, rover, 10 * dt, gravity=(0, 0, -gravity), controller=controller)
    slips = []
    coupler.run(0.6, callback=lambda c: slips.append((c.time, controller.slip[0])))
    slips = np.array(slips)
    steady = slips[slips[:, 0] > 0.3, 1]
    assert rover.wheel_kinematics()[0].position[0] < 0.3 - WHEEL.outer_radius, "stayed on the bed"
    assert abs(np.mean(steady) - target) < 0.05, np.mean(steady)
    assert np.all(np.abs(steady - target) < 0.15), (steady.min(), steady.max())
