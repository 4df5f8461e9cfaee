"""Bad input to the soil API gets a clear error naming the argument and what is allowed."""

import math

import numpy as np
import pytest

from soil import Material, OverlapWarning, Simulation, SoilBuilder, SoilInputError
from soil.errors import RegolithError


def builder_with_box():
    builder = SoilBuilder(gravity=9.81)
    builder.add_material(Material(youngs_modulus=1e6))
    builder.add_container((0, 0, 0), (0.1, 0.1, 0.1))
    return builder


def test_positions_must_be_n_by_3():
    with pytest.raises(SoilInputError, match=r"positions must have shape \(n, 3\).*\(4, 2\)"):
        builder_with_box().add_particles(np.zeros((4, 2)), 0.01)
    with pytest.raises(SoilInputError, match=r"position must be 3 numbers"):
        builder_with_box().add_particle((0.05, 0.05), 0.01)


def test_complex_positions_are_refused_not_cut_to_their_real_part():
    with pytest.raises(SoilInputError, match="positions must be real numbers"):
        builder_with_box().add_particles(np.full((2, 3), 0.05 + 0.01j), 0.01)
    with pytest.raises(SoilInputError, match="position must be real numbers"):
        builder_with_box().add_particle((0.05, 0.05, 0.05j), 0.01)


def test_radii_must_match_positions():
    with pytest.raises(SoilInputError, match=r"radii must be one radius or shape \(n,\) = \(3,\).*\(2,\)"):
        builder_with_box().add_particles(np.full((3, 3), 0.05), [0.01, 0.01])


def test_a_bad_radius_is_named_with_its_value():
    radii = [0.002, 0.003, math.inf]
    with pytest.raises(SoilInputError, match=r"radii must be finite and > 0 \[m\].*radii\[2\] = inf"):
        builder_with_box().add_particles(np.full((3, 3), 0.05), radii)
    with pytest.raises(SoilInputError, match=r"radii\[0\] = -0.001"):
        builder_with_box().add_particles(np.full((1, 3), 0.05), -0.001)
    with pytest.raises(SoilInputError, match=r"positions must be finite.*positions\[1\]"):
        builder_with_box().add_particles([(0.05, 0.05, 0.05), (0.05, math.nan, 0.05)], 0.01)


@pytest.mark.parametrize("dt", [-1e-4, 0.0, math.nan, math.inf])
def test_a_step_must_be_finite_and_positive(dt):
    builder = builder_with_box()
    builder.add_particle((0.05, 0.05, 0.05), 0.01)
    sim = Simulation(*builder.finalize("cpu", "double"))
    for run in (lambda: sim.run(0.01, dt), lambda: sim.step(dt), lambda: sim.macro_step(3, dt)):
        with pytest.raises(SoilInputError, match=r"dt must be finite and > 0 \[s\]"):
            run()
    with pytest.raises(SoilInputError, match=r"duration must be finite and >= 0 \[s\]"):
        sim.run(-0.01, 1e-4)
    assert sim.steps == 0


def test_grains_created_inside_each_other_are_reported():
    """Two pairs pressed 50 % and 20 % into each other, one grain 30 % into the floor: a warning
    with the count and the deepest overlap."""
    builder = builder_with_box()
    r = 0.01
    builder.add_particles(
        [
            (0.02, 0.05, 0.05),
            (0.03, 0.05, 0.05),  # 1.0 r apart: overlap 1.0 r
            (0.06, 0.05, 0.05),
            (0.078, 0.05, 0.05),  # 1.8 r apart: overlap 0.2 r
            (0.05, 0.02, 0.007),
        ],
        r,
    )  # 0.3 r into the floor
    with pytest.warns(OverlapWarning, match=r"3 contact\(s\).*deepest: particles 0 and 1 by 0.01 m, 1 x its radius"):
        builder.finalize("cpu", "double")
    # a saved state this deep was pressed so by its load (a bed settled at 1e3 m/s^2): not "space them out"
    saved = builder_with_box()
    saved.add_particles([(0.02, 0.05, 0.05), (0.035, 0.05, 0.05)], r)  # 0.5 r
    with pytest.warns(OverlapWarning, match=r"space them out"):  # built so: spaced out they should be
        state = saved.finalize("cpu", "double")[1].to_numpy()
    saved.start_from(state)
    with pytest.warns(OverlapWarning, match=r"pressed this deep by their load: the soil is too soft for it"):
        saved.finalize("cpu", "double")
    spaced = builder_with_box()
    spaced.add_particles([(0.02, 0.05, 0.05), (0.0419, 0.05, 0.05)], r)  # 0.05 r: a settled contact, no warning
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", OverlapWarning)
        spaced.finalize("cpu", "double")


def test_grains_outside_the_container_are_refused():
    builder = builder_with_box()
    builder.add_particles([(0.05, 0.05, 0.05), (0.05, 0.12, 0.05)], 0.01)
    with pytest.raises(SoilInputError, match=r"1 grain\(s\) have their centre behind boundary 4.*particle 1"):
        builder.finalize("cpu", "double")
    box = builder_with_box()
    box.add_box((0.04, 0.04, 0.0), (0.06, 0.06, 0.02))
    box.add_particle((0.05, 0.05, 0.01), 0.005)
    with pytest.raises(RegolithError, match=r"inside boundary 5, the solid box"):
        box.finalize("cpu", "double")
    fixed = builder_with_box()  # a fixed grain may sit anywhere: walls do not act on it
    fixed.add_particle((0.05, 0.05, -0.05), 0.01, fixed=True)
    fixed.add_particle((0.05, 0.05, 0.05), 0.01)
    fixed.finalize("cpu", "double")


def test_a_boundary_row_a_material_per_grain_and_a_saved_state_are_checked():
    from soil.sdf import BOUNDARY_BOX, BOUNDARY_PLANE

    builder = builder_with_box()
    with pytest.raises(SoilInputError, match=r"boundary kind must be BOUNDARY_PLANE"):
        builder.add_boundary(7, [0, 0, 0, 0, 0, 1])
    with pytest.raises(SoilInputError, match=r"boundary geometry must be 6 finite numbers"):
        builder.add_boundary(BOUNDARY_PLANE, [0, 0, 0, 0, 1])
    with pytest.raises(SoilInputError, match=r"plane normal must be a non-zero"):
        builder.add_boundary(BOUNDARY_PLANE, [0, 0, 0, 0, 0, 0])
    with pytest.raises(SoilInputError, match=r"box upper corner must exceed"):
        builder.add_boundary(BOUNDARY_BOX, [0, 0, 0, 0.1, 0.1, 0])
    with pytest.raises(SoilInputError, match=r"material indices must be in \[0, 1\), got 0 .. 3"):
        builder.add_particles(np.full((2, 3), 0.05), 0.01, np.array([0, 3]))
    with pytest.raises(SoilInputError, match=r"an index per grain, shape \(2,\)"):
        builder.add_particles(np.full((2, 3), 0.05), 0.01, np.array([0, 0, 0]))
    assert builder.particle_count == 0  # a refused call adds nothing
    builder.add_particles([(0.03, 0.05, 0.05), (0.07, 0.05, 0.05)], 0.01, np.array([0, 0]))
    with pytest.raises(SoilInputError, match=r"needs SoilState.to_numpy"):
        builder.start_from({"velocity": np.zeros((2, 3))})
    builder.start_from({"position": np.zeros((3, 3)), "neighbours": np.full((3, 1), -1)})
    with pytest.raises(SoilInputError, match=r"the saved 'position' has 3 rows, the builder 2 grains"):
        builder.finalize("cpu", "double")


@pytest.mark.parametrize(
    "call, words",
    [
        (lambda b: b.finalize(device="gpu"), r"device 'gpu': this machine has cpu"),
        (lambda b: b.finalize(device="CPU"), r"device 'CPU': this machine has cpu"),
        (lambda b: b.finalize(device="cuda:99"), r"device 'cuda:99': this machine has cpu"),
        (lambda b: b.finalize(order_seed=-1), r"order_seed must be None or an integer >= 0, got -1"),
        (lambda b: b.finalize(order_seed=1.5), r"order_seed must be None or an integer >= 0, got 1.5"),
        (lambda b: b.add_container((0, 0), (1, 1)), r"container corners must be 3-vectors"),
    ],
    ids=["gpu", "upper-case CPU", "no such GPU", "negative seed", "fractional seed", "2-d container"],
)
def test_a_device_seed_or_container_that_is_none_is_named(call, words):
    """Warp's own 'Invalid device identifier' named no allowed device, numpy's seed errors no argument,
    and a 2-d container corner was a reshape error."""
    builder = builder_with_box()
    builder.add_particle((0.05, 0.05, 0.05), 0.01)
    with pytest.raises(SoilInputError, match=words):
        call(builder)


def test_a_simulation_takes_an_integrator_by_its_scene_name_and_helpers_refuse_what_has_no_answer():
    """Simulation(..., integrator='jolt-beeman') failed at the first step ('str' has no 'bind'); a negative
    radius gave 'math domain error' and a negative damping ratio a restitution of 1."""
    from soil import JoltBeeman, rayleigh_time_step, restitution_of_damping_ratio

    builder = builder_with_box()
    builder.add_particle((0.05, 0.05, 0.05), 0.01)
    sim = Simulation(*builder.finalize(device="cpu"), integrator="jolt-beeman")
    assert isinstance(sim.integrator, JoltBeeman)
    sim.run(1e-4, 1e-5)
    assert sim.state.position.numpy()[0, 2] < 0.05  # falling under gravity
    with pytest.raises(SoilInputError, match="integrator must be one of"):
        Simulation(*builder.finalize(device="cpu"), integrator="rk4")
    with pytest.raises(SoilInputError, match="rayleigh_time_step needs E > 0, rho > 0, R > 0"):
        rayleigh_time_step(1e6, 0.3, 2500.0, -0.001)
    with pytest.raises(SoilInputError, match="damping_ratio must be >= 0, got -1"):
        restitution_of_damping_ratio(-1)
    assert restitution_of_damping_ratio(0.0) == 1.0


def test_a_bed_folder_or_one_wheel_shape_given_to_from_bed_is_named(tmp_path):
    """DemSoil.from_bed on a run's folder said 'bed file not found'; one GrouserWheel where the list of
    wheels goes was "'GrouserWheel' object is not iterable"."""
    from cosim.dem_soil import DemSoil
    from soil import GrouserWheel

    wheel = GrouserWheel(radius=0.03, width=0.02, grouser_count=0, grouser_height=0.0, grouser_thickness=0.0)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "bed.h5").write_bytes(b"")
    with pytest.raises(IsADirectoryError, match=r"is a folder, not a bed file; its bed is '.*run/bed.h5'"):
        DemSoil.from_bed(str(tmp_path / "run"), [wheel], Material(), 1e-4, surface_height=0.0)
    with pytest.raises(ValueError, match=r"wheels must be a list of wheel shapes, one per wheel: \[GrouserWheel"):
        DemSoil.from_bed(str(tmp_path / "run" / "bed.h5"), wheel, Material(), 1e-4, surface_height=0.0)


def test_open_bed_names_wheels_that_are_not_a_list_of_shape_and_material_pairs():
    """soil.bed.open_bed took its wheels as (shape, material) pairs without a word on anything else: one
    shape, one pair unlisted or shapes without materials were numpy and unpacking TypeErrors. Each is named
    (checked before the bed is read: the bed path here does not exist)."""
    from soil import GrouserWheel
    from soil.bed import open_bed

    wheel = GrouserWheel(radius=0.03, width=0.02, grouser_count=0, grouser_height=0.0, grouser_thickness=0.0)
    for wheels, words in (
        ((wheel, Material()), r"wheels must be a list of \(shape, material\) pairs"),
        (wheel, r"wheels\[0\] must be a \(shape, material\) pair: .* got GrouserWheel"),
        ([wheel], r"wheels\[0\] must be a \(shape, material\) pair: .* got GrouserWheel"),
    ):
        with pytest.raises(ValueError, match=words):
            open_bed("no_such_bed.h5", wheels, device="cpu")
    from soil.worlds import open_bed_worlds  # the worlds of one batch take the same pairs, checked once

    with pytest.raises(ValueError, match=r"wheels\[0\] must be a \(shape, material\) pair"):
        open_bed_worlds("no_such_bed.h5", wheel, [0, 1], device="cpu")


def one_grain_simulation(**options):
    builder = builder_with_box()
    builder.add_particle((0.05, 0.05, 0.05), 0.01)
    return Simulation(*builder.finalize(device="cpu", precision="double"), **options)


def test_a_simulation_refuses_what_is_not_its_parts_and_run_takes_whole_steps():
    """Simulation(model, None) and integrator=42 failed at the first step with AttributeErrors, restore({})
    too; run(1e-4, dt=3e-4) moved the clock by nothing, silently; advance_to(inf) was an OverflowError."""
    builder = builder_with_box()
    builder.add_particle((0.05, 0.05, 0.05), 0.01)
    model, state, control = builder.finalize(device="cpu", precision="double")
    with pytest.raises(SoilInputError, match=r"takes a soil.SoilModel and its soil.SoilState .* NoneType"):
        Simulation(model, None)
    with pytest.raises(SoilInputError, match=r"integrator must be None .* got 42"):
        Simulation(model, state, control, integrator=42)
    sim = Simulation(model, state, control)
    with pytest.raises(SoilInputError, match=r"restore takes what Simulation.snapshot\(\) returned, got dict"):
        sim.restore({})
    with pytest.raises(SoilInputError, match=r"duration 0.0001 s is less than half a step \(dt = 0.0003 s\)"):
        sim.run(1e-4, 3e-4)
    assert sim.time == 0.0 and sim.steps == 0
    sim.run(1.4e-3, 1e-3)  # whole steps, the nearest number of them: within dt / 2 of the duration
    assert sim.steps == 1 and sim.time == pytest.approx(1e-3, rel=1e-12)
    for end in (math.inf, math.nan, "0.1", True):
        with pytest.raises(SoilInputError, match=r"end_time must be a finite time \[s\]"):
            sim.advance_to(end, 1e-4)
    assert sim.steps == 1
    with pytest.raises(SoilInputError, match=r"needs a step control: call enable_step_control\(\) first"):
        sim.macro_step_adaptive(1e-3)
    with pytest.raises(SoilInputError, match=r"needs the JoltBeeman integrator, not VelocityVerlet"):
        sim.run_adaptive(1e-3)  # it stepped with Verlet: no jolt-Beeman history to start from


def test_a_saved_state_that_is_not_one_is_named_before_anything_changes(tmp_path):
    """load_state_dict({}) was KeyError 'precision'; positions of shape (n, 2) a Warp RuntimeError; NaN
    positions were loaded silently (the next step diverged, far from the file that caused it)."""
    sim = one_grain_simulation()
    sim.run(1e-3, 1e-4)
    saved, before = sim.state_dict(), sim.positions()
    with pytest.raises(SoilInputError, match=r"lacks precision, integrator, state/position, state/time, steps"):
        sim.load_state_dict({})
    flat = {**saved, "state/position": saved["state/position"][:, :2]}
    with pytest.raises(SoilInputError, match=r"state/position: .* shape \(1, 2\) .* expected \(particle_count, 3\)"):
        sim.load_state_dict(flat)
    for name in ("position", "velocity"):
        broken = {**saved, f"state/{name}": np.full_like(saved[f"state/{name}"], np.nan)}
        with pytest.raises(SoilInputError, match=rf"state/{name}: 1 saved grain\(s\) not finite \(the first: grain 0"):
            sim.load_state_dict(broken)
    assert np.array_equal(sim.positions(), before) and sim.time == pytest.approx(1e-3)
    sim.load_state_dict(saved)  # the state it saved loads, and so does the .npz it was saved to
    np.savez(tmp_path / "state.npz", **saved)
    with np.load(tmp_path / "state.npz") as stored:
        sim.load_state_dict(stored)
    assert np.array_equal(sim.positions(), before)


def test_a_snapshot_from_before_the_first_adaptive_run_repeats_it_bit_for_bit():
    """The snapshot held no step controller (run_adaptive had made none yet), and restore left the one the
    run made since in place, mid-way: the repeat took other steps (positions 4e-3 m apart)."""
    sim = one_grain_simulation(integrator="jolt-beeman")
    sim.run(2e-3, 1e-4)  # falling: the PID has an error to control
    kept = sim.snapshot()
    sim.run_adaptive(5e-3)
    first = (sim.positions(), sim.velocities(), sim.accepted_steps)
    sim.restore(kept)
    sim.run_adaptive(5e-3)
    assert first[2] > 1
    assert np.array_equal(first[0], sim.positions()) and np.array_equal(first[1], sim.velocities())
    assert sim.accepted_steps == first[2]
