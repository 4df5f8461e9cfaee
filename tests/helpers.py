"""Helpers shared by the tests: closed-form physics setups and a tiny single-wheel scene."""

import math

import numpy as np

from soil import ContactLaw, Material, Simulation, SoilBuilder


def hertz_rest_overlap(mass, gravity, e_star, radius):
    """Static Hertz overlap of a sphere on a plane: (3 m g / (4 E* sqrt(R)))^(2/3) [m]."""
    return (3.0 * mass * gravity / (4.0 * e_star * math.sqrt(radius))) ** (2.0 / 3.0)


def sphere_on_plane(
    device,
    precision,
    gravity,
    material,
    radius=5e-3,
    origin=(0.0, 0.0, 0.0),
    velocity=(0, 0, 0),
    spin=(0, 0, 0),
    law=None,
    lock_rotation=False,
    plane_material=None,
    overlap=0.0,
):
    """A sphere touching (or pressed `overlap` [m] into) the plane z = origin_z; returns a Simulation."""
    builder = SoilBuilder(gravity=gravity)
    soil = builder.add_material(material)
    wall = builder.add_material(plane_material) if plane_material else soil
    origin = np.asarray(origin, dtype=float)
    builder.add_plane(origin, (0, 0, 1), wall)
    builder.add_particle(
        origin + (0, 0, radius - overlap),
        radius,
        soil,
        velocity=velocity,
        angular_velocity=spin,
        lock_rotation=lock_rotation,
    )
    model, state, control = builder.finalize(device=device, precision=precision, law=law)
    return Simulation(model, state, control)


def effective_modulus(a: Material, b: Material):
    return 1.0 / ((1 - a.poisson_ratio**2) / a.youngs_modulus + (1 - b.poisson_ratio**2) / b.youngs_modulus)


def frictionless(**kw):
    return ContactLaw(friction=False, **kw)


def hertz_impact_overlap(mass_eff, closing_speed, e_star, radius_eff):
    """Largest overlap of an elastic Hertz impact: (5 m* v^2 / (4 k))^(2/5), k = 4/3 E* sqrt(R*) [m]."""
    k = 4.0 / 3.0 * e_star * math.sqrt(radius_eff)
    return (5.0 * mass_eff * closing_speed**2 / (4.0 * k)) ** 0.4


def drive(soil, rig, duration, macro_step):
    """Couple a DEM soil side and a single-wheel rig for `duration` [s] with the product's Coupler, and
    return the records as arrays plus the quantities of cosim.metrics (wheel 0): time, slip,
    drawbar_pull, normal_force, sinkage, hub_velocity (S, 3)."""
    from cosim.coupler import Coupler, stack_records
    from cosim.metrics import WheelGeometry, wheel_quantities

    rig.time = soil.time  # the rig joins the soil's clock
    coupler = Coupler(soil, rig, macro_step, gravity=soil.sim.model.gravity)
    start = rig.position.copy()
    records = coupler.run(coupler.time + duration)
    shape = soil.sim.model.bodies[0]
    geometry = WheelGeometry(rig.radius, shape.outer_radius, soil.surface_height)
    quantities = [wheel_quantities(r.kinematics[0], r.wrenches[0], geometry, start) for r in records]
    out = stack_records(records)
    for name in quantities[0]:
        out[name] = np.array([q[name] for q in quantities])
    out["hub_velocity"] = out["linear_velocity"][:, 0]
    return out


# -- the tiny single-wheel scene of the tool tests ------------------------------------------
# About 300 grains and under a second simulated. It is deliberately coarse (3 grains across
# the wheel: `cosim advise` says so): the tool tests need a run that lands, drives and writes
# every output in seconds, not a valid traction number.
TINY_SCENE = """
[scene]
name = "tiny"
gravity = "moon"
precision = "mixed"

[soil]
youngs_modulus = 1.0e6

[bed]
length = 0.12
width = 0.06
depth = 0.026
radius_mean = 0.0035
settle_max_time = 1.0
settle_ke_ratio = 0.005

[wheel]
radius = 0.025
width = 0.02
grouser_count = 8
grouser_height = 0.003
grouser_thickness = 0.002

[testbed]
mass = 0.3
omega = 1.0

[landing]
max_time = 1.5

[run]
duration = 0.12
macro_step = 0.0017

[output]
snapshot_interval = 0.03
checkpoint_interval = 0.03
flush_every = 7
"""


def write_tiny(folder, extra: str = "", name: str = "tiny.toml") -> str:
    """Write the tiny scene (plus `extra` TOML) to folder/name; returns the path."""
    path = folder / name
    path.write_text(TINY_SCENE + extra)
    return str(path)


def assert_every_number_has_its_unit(summary: dict) -> None:
    """Every number (or list of numbers) of a run's summary has its unit in the summary's `units`."""
    numbers = [
        key
        for key, value in summary.items()
        if key != "units"
        and (isinstance(value, (int, float)) or (isinstance(value, list) and value and not isinstance(value[0], dict)))
    ]
    missing = [key for key in numbers if key not in summary["units"]]
    assert numbers and not missing, missing


def assert_checkpoint_units(path) -> dict:
    """Every array of a checkpoint has a unit in its units table (soil.stability.UNITS_KEY); returns
    the table."""
    import json

    from soil.stability import CHECKSUM_KEY, UNITS_KEY

    with np.load(path) as data:
        names = set(data.files) - {CHECKSUM_KEY, UNITS_KEY}
        units = json.loads(str(data[UNITS_KEY]))
    missing = sorted(names - set(units))
    assert names and not missing, missing
    assert all(isinstance(units[name], str) and units[name] for name in names)
    return units


SCM_TERRAIN = """
[terrain]
model = "scm"
k_c = 2.0e3
k_phi = 8.0e5
n = 1.1
cohesion = 50.0
friction_angle_deg = 30.0
janosi_k = 0.002
elastic_stiffness = 2.0e7
"""
"""A [terrain] on SCM with every soil key given (no calibration file): the tiny scene's SCM twin."""
