"""Bad arguments to public functions of soil and cosim get a clear error (SoilInputError, ArgumentError)
that names the argument and what is allowed, raised before anything changes; no bare TypeError, no
silent truncation, no nan or inf answer."""

import math
import warnings

import numpy as np
import pytest

from cosim.contract import WheelKinematics
from cosim.dem_soil import DemSoil, WallProximityWarning
from cosim.scm_soil import ScmSoil, bekker_wheel_sinkage
from soil import GrouserWheel, Material, Simulation, SoilBuilder, advisor
from soil.errors import ArgumentError, SoilInputError
from soil.materials import damping_ratio_for_restitution, restitution_of_damping_ratio
from soil.scm import ScmParameters, ScmTerrain

DRY_SAND = ScmParameters(
    k_c=0.99e3,
    k_phi=1528.43e3,
    n=1.1,
    cohesion=1.04e3,
    friction_angle=28,
    janosi_k=0.02,
    elastic_stiffness=4e8,
    node_spacing=0.005,
)
"""Wong's dry sand (ScmParameters' docstring)."""


# -- soil.Material and the restitution <-> damping conversions -----------------------------------
@pytest.mark.parametrize("value", ["1e7", 1e7 + 1j, np.array([1e7, 2e7]), True, None])
def test_material_modulus_must_be_a_real_number(value):
    with pytest.raises(SoilInputError, match=r"material\.youngs_modulus must be a finite number > 0 \[Pa\]"):
        Material(youngs_modulus=value)


def test_material_restitution_must_be_a_real_number():
    with pytest.raises(SoilInputError, match=r"material\.restitution must be a finite number in \(0, 1\]"):
        Material(restitution="0.5")


@pytest.mark.parametrize("value", ["0.5", [0.5], None])
def test_damping_ratio_for_restitution_names_a_bad_restitution(value):
    with pytest.raises(SoilInputError, match=r"restitution must be a number in \(0, 1\]"):
        damping_ratio_for_restitution(value)


@pytest.mark.parametrize("value", ["a", math.inf, math.nan, -1.0, [0.1]])
def test_restitution_of_damping_ratio_takes_a_finite_ratio(value):
    """inf gave 0.0 with scipy's RuntimeWarnings; a text a bare TypeError."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning on the way to the error
        with pytest.raises(SoilInputError, match="damping_ratio must be >= 0, got .*a finite number"):
            restitution_of_damping_ratio(value)


def test_valid_restitution_and_damping_are_unchanged():
    assert restitution_of_damping_ratio(0.0) == 1.0
    assert damping_ratio_for_restitution(1.0) == 0.0
    damping = damping_ratio_for_restitution(0.5)
    assert restitution_of_damping_ratio(damping) == pytest.approx(0.5, abs=1e-8)


# -- SoilBuilder.add_particles / add_material ----------------------------------------------------
def builder_with_material():
    builder = SoilBuilder(gravity=9.81)
    builder.add_material(Material(youngs_modulus=1e6))
    return builder


def assert_unchanged(builder, particles=0, materials=1):
    assert builder.particle_count == particles
    assert len(builder.materials.materials) == materials


@pytest.mark.parametrize("material", [0.7, "steel", True, math.nan])
def test_a_material_index_must_be_an_integer(material):
    """0.7 was cut to index 0; 'steel' gave int()'s bare ValueError."""
    builder = builder_with_material()
    with pytest.raises(SoilInputError, match=r"material must be a soil\.Material or a material index"):
        builder.add_particles([(0.0, 0.0, 0.0)], 0.01, material=material)
    assert_unchanged(builder)


def test_a_bad_material_index_adds_no_default_material():
    builder = SoilBuilder(gravity=9.81)
    with pytest.raises(SoilInputError, match="material must be"):
        builder.add_particles([(0.0, 0.0, 0.0)], 0.01, material="steel")
    assert_unchanged(builder, materials=0)
    with pytest.raises(SoilInputError, match=r"material index must be in \[0, 1\)"):
        builder.add_particles([(0.0, 0.0, 0.0)], 0.01, material=3)
    assert_unchanged(builder, materials=0)


@pytest.mark.parametrize(
    "positions, radii, name",
    [
        ("abc", 0.01, "positions"),
        ([(0.0, 0.0, 0.0), (0.0, 0.0)], 0.01, "positions"),  # ragged: numpy's "inhomogeneous shape"
        ([(0.0, 0.0, 0.0)], "0.01", "radii"),  # numpy reads a text of digits as a number
        ([(0.0, 0.0, 0.0)], [[0.01], [0.01, 0.02]], "radii"),
    ],
)
def test_positions_and_radii_must_be_real_numbers(positions, radii, name):
    builder = builder_with_material()
    with pytest.raises(SoilInputError, match=f"{name} must be real numbers"):
        builder.add_particles(positions, radii)
    assert_unchanged(builder)


def test_velocities_must_be_real_numbers():
    builder = builder_with_material()
    with pytest.raises(SoilInputError, match=r"velocities \[m/s\] must be real numbers"):
        builder.add_particles([(0.0, 0.0, 0.0)], 0.01, velocities="abc")
    assert_unchanged(builder)


@pytest.mark.parametrize("fixed", ["yes", [2, 0], [0.5, 1.0], [[1], [0, 1]]])
def test_fixed_flags_are_booleans_or_zero_and_one(fixed):
    """'yes' and [2, 0] were taken as flags (any text or non-zero number read as true)."""
    builder = builder_with_material()
    with pytest.raises(SoilInputError, match="fixed must be"):
        builder.add_particles([(0.0, 0.0, 0.0), (0.1, 0.0, 0.0)], 0.01, fixed=fixed)
    with pytest.raises(SoilInputError, match="lock_rotation must be"):
        builder.add_particles([(0.0, 0.0, 0.0), (0.1, 0.0, 0.0)], 0.01, lock_rotation=fixed)
    assert_unchanged(builder)


def test_valid_flags_and_indices_are_kept():
    builder = builder_with_material()
    builder.add_particles([(0.0, 0.0, 0.0), (0.1, 0.0, 0.0)], 0.01, material=np.int64(0), fixed=[1, 0])
    builder.add_particles([(0.2, 0.0, 0.0)], [0.01], material=[0], fixed=True, lock_rotation=0)
    assert [f.tolist() for f in builder._fixed] == [[True, False], [True]]
    assert builder.particle_count == 3


def test_add_material_names_a_non_material():
    """It raised a plain TypeError."""
    builder = builder_with_material()
    with pytest.raises(SoilInputError, match=r"material must be a soil\.Material, got str"):
        builder.add_material("x")
    assert_unchanged(builder)


# -- cosim.dem_soil.DemSoil ----------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_sim():
    builder = SoilBuilder(gravity=9.81)
    builder.add_material(Material(youngs_modulus=1e6))
    builder.add_container((0, 0, 0), (0.1, 0.05, 0.1))
    builder.add_particle((0.05, 0.025, 0.002), 0.002)
    builder.add_wheel(GrouserWheel(0.01, 0.01))
    return Simulation(*builder.finalize("cpu", "double"))


@pytest.mark.parametrize(
    "arguments, name",
    [
        (dict(dt=math.inf), "dt"),
        (dict(dt="1e-4"), "dt"),
        (dict(dt=None), "dt"),
        (dict(dt=1e-4, surface_height=math.nan), "surface_height"),
        (dict(dt=1e-4, surface_height="0"), "surface_height"),
        (dict(dt=1e-4, wall_clearance=-1.0), "wall_clearance"),
        (dict(dt=1e-4, wall_clearance=math.inf), "wall_clearance"),
    ],
)
def test_dem_soil_arguments_are_checked(small_sim, arguments, name):
    with pytest.raises(ArgumentError, match=f"^{name} must be"):
        DemSoil(small_sim, **arguments)


def test_a_wheel_outside_the_container_is_said_to_be_outside(small_sim):
    """The warning read "wheel 0 is -4.74 m from a container wall"."""
    soil = DemSoil(small_sim, 1e-4)
    hub = (-0.5, 0.025, 0.05)  # 0.5 m beyond the -x wall
    with pytest.warns(WallProximityWarning, match=r"wheel 0 lies outside the container: its hub is 0\.5 m beyond"):
        soil.advance(small_sim.time + 1e-4, [WheelKinematics(hub, (1, 0, 0, 0), (0, 0, 0), (0, 0, 0))])


def test_dem_soil_takes_a_simulation_and_a_finite_end_time(small_sim):
    """DemSoil(None, dt) was an AttributeError; advance(inf) set the wheels' path over an infinite span
    (numpy's invalid-value warnings) before Warp's OverflowError."""
    with pytest.raises(ArgumentError, match=r"^sim must be a soil.Simulation .* got NoneType"):
        DemSoil(None, 1e-4)
    soil = DemSoil(small_sim, 1e-4)
    still = WheelKinematics((0.05, 0.025, 0.05), (1, 0, 0, 0), (0, 0, 0), (0, 0, 0))
    before = small_sim.state_dict()
    for end in (math.inf, math.nan, "0.1"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no numpy warning from a path over an infinite span
            with pytest.raises(ArgumentError, match=r"^t_end must be a finite time \[s\]"):
                soil.advance(end, [still])
    after = small_sim.state_dict()
    for key in before:  # nothing moved, the wheels' path included (nan where unset: equal as nan)
        np.testing.assert_array_equal(before[key], after[key], err_msg=key)


# -- cosim.scm_soil ------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "load, radius, width, name",
    [
        (100.0, -0.1, 0.1, "radius"),
        (100.0, 0.0, 0.1, "radius"),
        (100.0, math.inf, 0.1, "radius"),
        (100.0, 0.1, 0.0, "width"),
        (100.0, 0.1, "0.1", "width"),
        (math.nan, 0.1, 0.1, "load"),
        (math.inf, 0.1, 0.1, "load"),
        (None, 0.1, 0.1, "load"),
    ],
)
def test_bekker_wheel_sinkage_arguments(load, radius, width, name):
    with pytest.raises(ArgumentError, match=f"^{name} must be a finite number"):
        bekker_wheel_sinkage(DRY_SAND, load, radius, width)


def test_bekker_wheel_sinkage_of_valid_loads_is_unchanged():
    assert bekker_wheel_sinkage(DRY_SAND, 0.0, 0.1, 0.1) == 0.0
    base = 3.0 * 100.0 / ((3.0 - 1.1) * (0.99e3 + 0.1 * 1528.43e3) * math.sqrt(0.2))
    assert bekker_wheel_sinkage(DRY_SAND, 100.0, 0.1, 0.1) == base ** (2.0 / 3.2)
    assert "rolling form" in bekker_wheel_sinkage.__doc__ and "not a check of a wheel at rest" in (
        bekker_wheel_sinkage.__doc__
    )


@pytest.fixture(scope="module")
def terrain():
    return ScmTerrain(DRY_SAND, [GrouserWheel(0.1, 0.05)], window=(1.0, 0.5))


@pytest.mark.parametrize("terrain_argument", [None, "terrain", 1.0])
def test_scm_soil_names_a_terrain_that_is_none(terrain_argument):
    """ScmSoil(None, ...) raised a bare AttributeError."""
    with pytest.raises(ArgumentError, match=r"^terrain must be a soil\.scm\.ScmTerrain"):
        ScmSoil(terrain_argument, 1e-3, [0.1])


def test_scm_soil_rim_radii_must_be_a_sequence(terrain):
    with pytest.raises(ArgumentError, match="^rim_radii must be a sequence"):
        ScmSoil(terrain, 1e-3, 0.1)


# -- soil.advisor --------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "arguments, name",
    [
        ((math.inf, 0.3, 2600.0, 2.5e-3), "youngs_modulus"),  # gave 0.0
        ((1e8, 0.3, 2600.0, math.inf), "radius"),  # gave inf
        (("1e8", 0.3, 2600.0, 2.5e-3), "youngs_modulus"),
        ((1e8, "0.3", 2600.0, 2.5e-3), "poisson_ratio"),
        ((1e8, 0.3, math.nan, 2.5e-3), "density"),
    ],
)
def test_rayleigh_time_step_names_a_bad_argument(arguments, name):
    with pytest.raises(SoilInputError, match=f"{name} must be a finite number"):
        advisor.rayleigh_time_step(*arguments)


@pytest.mark.parametrize(
    "arguments, name",
    [
        ((0.05, 10.0, 0.01, 2.5e-3, -2600.0, 5.7e-3), "density"),
        ((0.05, math.nan, 0.01, 2.5e-3, 2600.0, 5.7e-3), "pressure"),
        ((0.05, 10.0, 0.01, math.inf, 2600.0, 5.7e-3), "radius"),
        ((0.05, 10.0, 0.01, 2.5e-3, 2600.0, (0, 0, math.nan)), "gravity"),
        ((0.05, 10.0, "0.01", 2.5e-3, 2600.0, 5.7e-3), "overlap_factor"),
        ((math.inf, 10.0, 0.01, 2.5e-3, 2600.0, 5.7e-3), "soil_height"),
    ],
)
def test_macroscopic_stiffness_names_a_bad_argument(arguments, name):
    with pytest.raises(SoilInputError, match=f"^{name} must be"):
        advisor.macroscopic_stiffness(*arguments)


@pytest.mark.parametrize(
    "arguments, name",
    [
        (dict(radius=-1.0, gravity=9.81), "radius"),  # math domain error
        (dict(radius=1e-3, gravity=9.81, safety=-1.0), "safety"),  # negative dt_min, dt_max
        (dict(radius=1e-3, gravity=math.nan), "gravity"),  # read as "no gravity and nothing moving"
        (dict(radius=1e-3, gravity=9.81, height=-1.0), "height"),
        (dict(radius=1e-3, gravity=9.81, impact_speed=math.inf), "impact_speed"),
        (dict(radius=1e-3, gravity=9.81, pressure=math.nan), "pressure"),
    ],
)
def test_recommended_time_step_names_a_bad_argument(arguments, name):
    with pytest.raises(SoilInputError, match=f"^{name} must be "):
        advisor.recommended_time_step(Material(), **arguments)


def test_recommended_time_step_needs_a_scene():
    """'x' raised a bare AttributeError."""
    with pytest.raises(
        SoilInputError, match=r"^scene must be a soil\.Simulation, a soil\.SoilModel or a soil\.Material"
    ):
        advisor.recommended_time_step("x")


# -- soil.scm ------------------------------------------------------------------------------------
@pytest.mark.parametrize("x, y, name", [(math.nan, 0.0, "x"), (0.0, math.inf, "y"), ("a", 0.0, "x")])
def test_surface_height_at_refuses_non_finite_points(terrain, x, y, name):
    """nan gave 0.0 with numpy's cast RuntimeWarning."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(SoilInputError, match=f"^{name} must be finite numbers"):
            terrain.surface_height_at(x, y)


def test_surface_height_at_names_mismatched_shapes(terrain):
    with pytest.raises(SoilInputError, match=r"x and y must have one shape.*\(3,\) and \(2,\)"):
        terrain.surface_height_at(np.zeros(3), np.zeros(2))
    assert terrain.surface_height_at(0.0, np.zeros(2)).tolist() == [0.0, 0.0]  # broadcasting still works


@pytest.mark.parametrize("window", [1.0, np.float64(1.0), (1.0,)])
def test_scm_window_must_be_two_sizes(window):
    """window=1.0 raised "object of type 'float' has no len()"."""
    with pytest.raises(SoilInputError, match=r"^window must be two sizes > 0"):
        ScmTerrain(DRY_SAND, [GrouserWheel(0.1, 0.05)], window=window)


def test_scm_centre_must_be_two_numbers():
    with pytest.raises(SoilInputError, match=r"^centre must be None or two finite numbers"):
        ScmTerrain(DRY_SAND, [GrouserWheel(0.1, 0.05)], window=(1.0, 0.5), centre=0.0)


def test_scm_advance_end_time_must_be_a_number(terrain):
    """'0.1' was read as 0.1 s."""
    before = (terrain.time, terrain.steps)
    with pytest.raises(SoilInputError, match="^end_time must be a number"):
        terrain.advance("0.1", 1e-3, position=[[0, 0, 0.08]], orientation=[[1, 0, 0, 0]])
    assert (terrain.time, terrain.steps) == before


def test_scm_friction_angle_is_documented_in_degrees():
    assert "DEGREES" in ScmParameters.__doc__
    assert "in radians" in ScmParameters.__doc__
    assert ScmParameters(**{**DRY_SAND.__dict__, "friction_angle": 89.9}).friction_angle == 89.9  # still allowed


def test_the_scm_module_example_runs_as_written():
    """It used ScmParameters(...) literally (seven required arguments missing)."""
    import textwrap

    import soil.scm

    doc = soil.scm.__doc__
    assert "ScmParameters(...)" not in doc
    code = textwrap.dedent(doc[doc.index("    from soil import GrouserWheel") :])
    scope: dict = {}
    exec(code, scope)
    assert scope["contact"].force[0, 2] > 0  # the soil carries the wheel
