"""Small scene makers shared by the physics tests (closed-form setups only)."""

import math

import numpy as np

from soil import ContactLaw, Material, Simulation, SoilBuilder


def hertz_rest_overlap(mass, gravity, e_star, radius):
    """Static Hertz overlap of a sphere on a plane: (3 m g / (4 E* sqrt(R)))^(2/3) [m]."""
    return (3.0 * mass * gravity / (4.0 * e_star * math.sqrt(radius))) ** (2.0 / 3.0)


def sphere_on_plane(device, precision, gravity, material, radius=5e-3, origin=(0.0, 0.0, 0.0),
                    velocity=(0, 0, 0), spin=(0, 0, 0), law=None, lock_rotation=False, plane_material=None,
                    overlap=0.0):
    """A sphere touching (or pressed `overlap` [m] into) the plane z = origin_z; returns a Simulation."""
    builder = SoilBuilder(gravity=gravity)
    soil = builder.add_material(material)
    wall = builder.add_material(plane_material) if plane_material else soil
    origin = np.asarray(origin, dtype=float)
    builder.add_plane(origin, (0, 0, 1), wall)
    builder.add_particle(origin + (0, 0, radius - overlap), radius, soil, velocity=velocity, angular_velocity=spin,
                         lock_rotation=lock_rotation)
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
