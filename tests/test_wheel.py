"""Wheels in the soil and the single-wheel testbed."""

import math

import numpy as np
import pytest

from cosim.contract import WheelKinematics
from cosim.dem_soil import DemSoil, WallProximityWarning
from cosim.metrics import slip_of
from cosim.single_wheel import SingleWheelRig
from helpers import drive
from soil import GrouserWheel, Material, MeshWheel, Simulation, SoilBuilder
from soil.bed import BedSpec, SavedBed, bed_metrics, build_bed, open_bed, read_bed, save_bed, settle

WHEEL = GrouserWheel(radius=0.03, width=0.02, grouser_count=10, grouser_height=0.003, grouser_thickness=0.002)


def upright(position, velocity=(0, 0, 0), spin=(0, 0, 0)):
    return WheelKinematics(position, (1, 0, 0, 0), velocity, spin)


# -- geometry -------------------------------------------------------------------------
def wheel_contacts(device, shape, points, velocity=(0, 0, 0), spin=(0, 0, 0)):
    """Soil force on the wheel from one grain at each point (wheel frame), one scene per point."""
    radius = GRAIN
    builder = SoilBuilder(gravity=0.0)
    builder.add_material(Material(youngs_modulus=1e7))
    spacing = 0.3
    for k, p in enumerate(points):
        builder.add_particle(np.asarray(p) + (spacing * k, 0, 0), radius)
        builder.add_wheel(shape)
    model, state, control = builder.finalize(device, "double")
    for k in range(len(points)):
        control.set_body_motion(k, (spacing * k, 0, 0), (1, 0, 0, 0), velocity, spin)
    sim = Simulation(model, state, control)
    return sim.state.body_force.numpy(), sim.state.body_torque.numpy()


GRAIN = 0.001  # small enough to touch a grouser face without touching the rim


def probe_points(wheel, depth=1e-4, grain=GRAIN):
    """Grain centres pressed `depth` into the rim between grousers, a grouser face, a grouser tip and the side."""
    pitch = 2 * math.pi / wheel.grouser_count
    between = 0.5 * pitch
    rim = (wheel.radius + grain - depth) * np.array([math.sin(between), 0, math.cos(between)])
    face = np.array([0.5 * wheel.grouser_thickness + grain - depth, 0.0, wheel.radius + 0.5 * wheel.grouser_height])
    tip = np.array([0.0, 0.0, wheel.radius + wheel.grouser_height + grain - depth])
    side = np.array([0.0, 0.5 * wheel.width + grain - depth, 0.5 * wheel.radius])
    return [rim, face, tip, side]


@pytest.mark.parametrize(
    "bad",
    [
        {"position": (np.nan, 0.0, 0.0)},
        {"orientation": (0.0, 0.0, 0.0, 0.0)},
        {"orientation": (np.nan, 0.0, 0.0, 0.0)},
        {"rotation": np.zeros((3, 3))},
        {"rotation": 3 * np.eye(3)},
        {"rotation": np.diag([1.0, 1.0, -1.0])},
        {"velocity": (0.0, 0.0)},
        {"angular_velocity": (0.0, 1j, 0.0)},
    ],
    ids=["nan position", "zero quaternion", "nan quaternion", "zero matrix", "scaled", "mirror", "2-vector", "complex"],
)
def test_a_body_pose_that_is_no_pose_is_refused_and_the_last_one_kept(device, bad):
    """A NaN position or a zero quaternion was kept: the wheel reached no grain (zero force, no error)
    and its rotation turned NaN. Refused naming the body and the argument, before any of them is kept."""
    from soil.errors import SoilInputError

    builder = SoilBuilder(gravity=0.0)
    builder.add_material(Material(youngs_modulus=1e7))
    builder.add_particle(probe_points(WHEEL)[0], GRAIN)
    builder.add_wheel(WHEEL)
    model, state, control = builder.finalize(device, "double")
    control.set_body_motion(0, (0, 0, 0), (1, 0, 0, 0), (0, 0, 0), (0, 0, 0))
    sim = Simulation(model, state, control)
    pressed = sim.state.body_force.numpy()[0].copy()
    assert np.linalg.norm(pressed) > 0
    with pytest.raises(SoilInputError, match="body 0's"):
        control.set_body_motion(0, **{"position": (0.0, 0.0, 0.0), **bad})
    sim.refresh_forces()
    np.testing.assert_array_equal(sim.state.body_force.numpy()[0], pressed)
    assert np.all(np.isfinite(control.body_rotation_host))
    # the path a coupled run sets each macro step: the same checks on its start and end
    pose = {"position": (0.0, 0.0, 0.0), "orientation": (1.0, 0.0, 0.0, 0.0), "velocity": (0.0, 0.0, 0.0)}
    pose.update(angular_velocity=(0.0, 0.0, 0.0))
    if "rotation" not in bad:
        path = [np.array([{**pose, **bad}[name]]) for name in pose]
        with pytest.raises(SoilInputError, match="the path's start|body 0's orientation at the path's start"):
            control.set_body_path(1e-3, *path)
        with pytest.raises(SoilInputError, match="the path's end|body 0's orientation at the path's end"):
            control.set_body_path(1e-3, *[np.array([pose[name]]) for name in pose], end=path)
    with pytest.raises(SoilInputError, match="as a quaternion or a rotation matrix, not both"):
        control.set_body_motion(0, orientation=(1.0, 0.0, 0.0, 0.0), rotation=np.eye(3))


def test_mesh_wheel_and_parametric_wheel_give_the_same_contact_forces(device):
    points = probe_points(WHEEL)
    vertices, triangles = WHEEL.to_mesh(arc_segments=3600)
    mesh = MeshWheel(vertices, triangles)
    # a turning, moving wheel: normal and tangential forces both enter
    kw = dict(velocity=(0.01, 0, -0.002), spin=(0, 0.5, 0))
    f_param, t_param = wheel_contacts(device, WHEEL, points, **kw)
    f_mesh, t_mesh = wheel_contacts(device, mesh, points, **kw)
    assert np.all(np.linalg.norm(f_param, axis=1) > 0), "every probe touches the wheel"
    # at rest, the grouser face pushes with the Hertz force of a 0.1 mm overlap on a flat face
    e_star = 1 / (2 * (1 - 0.3**2) / 1e7)
    hertz = 4 / 3 * e_star * math.sqrt(GRAIN) * (1e-4) ** 1.5
    f_static, _ = wheel_contacts(device, WHEEL, points)
    np.testing.assert_allclose(f_static[1], [-hertz, 0, 0], rtol=1e-6, atol=1e-9 * hertz)
    # the rim is polygonal in the mesh: 3600 segments put it within ~1e-8 m of the circle
    np.testing.assert_allclose(f_mesh, f_param, rtol=2e-3, atol=1e-6 * hertz)
    np.testing.assert_allclose(t_mesh, t_param, rtol=2e-3, atol=1e-6 * hertz * WHEEL.radius)


def test_wheel_mesh_is_closed_and_has_the_right_volume():
    vertices, triangles = WHEEL.to_mesh(arc_segments=3600)
    mesh = MeshWheel(vertices, triangles)
    v = mesh.vertices[mesh.triangles]
    volume = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6
    grousers = WHEEL.grouser_count * WHEEL.grouser_thickness * WHEEL.grouser_height * WHEEL.width
    expected = math.pi * WHEEL.radius**2 * WHEEL.width + grousers
    assert volume == pytest.approx(expected, rel=1e-3)


def test_mesh_file_round_trip_and_bad_meshes(tmp_path):
    vertices, triangles = WHEEL.to_mesh(arc_segments=360)
    for suffix in (".obj", ".stl"):
        path = tmp_path / f"wheel{suffix}"
        MeshWheel(vertices, triangles).save(path)
        loaded = MeshWheel.load(path)
        assert loaded.outer_radius == pytest.approx(WHEEL.outer_radius, rel=1e-6)
    with pytest.raises(ValueError, match="not closed"):
        MeshWheel(vertices, triangles[:-1])
    # a mesh 5 m off its axle (another origin or unit) swept a 10 m circle: every grid and bed sized by it
    with pytest.raises(ValueError, match=r"its centre lies 5 m from the axle .* centre the mesh on it"):
        MeshWheel(vertices + [5.0, 0.0, 0.0], triangles)
    # off its hub along the axle: the wheel ran against a side wall the clearance check placed elsewhere;
    # the axle along the file's X axis: a paddle, not a wheel (read as a wheel: other bodies are not judged)
    width = float(np.ptp(vertices[:, 1]))
    for name, moved, words in (
        ("off.obj", (vertices + [0.0, 0.3 * width, 0.0], triangles), r"along the axle from the hub, more than 0.25"),
        ("turned.obj", (vertices[:, [1, 0, 2]], triangles[:, ::-1]), r"not round about the axle .* rotate the mesh"),
    ):
        MeshWheel(*moved).save(tmp_path / name)
        with pytest.raises(ValueError, match=words):
            MeshWheel.load(tmp_path / name)
    # a closed mesh with a zero-area triangle and a repeated one, and a stray vertex: read as the wheel it is
    path = tmp_path / "degenerate.obj"
    MeshWheel(vertices, triangles).save(path)
    lines = path.read_text().splitlines()
    faces = [line for line in lines if line.startswith("f ")]
    stray = f"v {10 * WHEEL.outer_radius} 0 0"
    path.write_text("\n".join(lines + ["f 1 1 2", faces[0], stray]) + "\n")
    loaded = MeshWheel.load(path)
    assert len(loaded.triangles) == len(triangles) and loaded.outer_radius == pytest.approx(
        WHEEL.outer_radius, rel=1e-6
    )
    with pytest.raises(FileNotFoundError, match="not found"):
        MeshWheel.load(tmp_path / "missing.obj")
    with pytest.raises(ValueError, match=".obj or .stl"):
        MeshWheel.load(tmp_path / "wheel.ply")
    with pytest.raises(ValueError, match="wheel.radius"):
        GrouserWheel(radius=-0.1, width=0.02)
    with pytest.raises(ValueError, match="grouser_thickness"):
        GrouserWheel(radius=0.03, width=0.02, grouser_count=100, grouser_height=0.003, grouser_thickness=0.002)


def test_a_mesh_kept_with_unused_vertices_is_the_same_wheel():
    """results.h5 written before the reader dropped unused vertices holds them: a resume or a slip table from
    runs compared it with the mesh read now and called the unchanged file changed. Compared by the vertices
    the triangles use, the two are one wheel; another wheel is still another."""
    from cosim.system import used_mesh

    vertices, triangles = WHEEL.to_mesh(arc_segments=36)
    owners = np.zeros(len(vertices), dtype=np.int32)
    stray = np.vstack([[[1.0, 2.0, 3.0]], vertices])  # an unused vertex first: every index moves by one
    kept = used_mesh((stray, triangles + 1, np.zeros(len(stray), dtype=np.int32)))
    now = used_mesh((vertices, triangles, owners))
    assert all(np.array_equal(a, b) for a, b in zip(kept, now))
    larger = used_mesh((vertices * 1.1, triangles, owners))
    assert not np.array_equal(larger[0], now[0])


def test_torque_about_the_hub_moves_with_the_hub(device):
    """The same wheel surface described about two hubs d apart: T_2 = T_1 + (p_1 - p_2) x F."""
    points = probe_points(WHEEL)
    vertices, triangles = WHEEL.to_mesh(arc_segments=3600)
    offset = np.array([0.004, 0.001, -0.006])
    centred = MeshWheel(vertices, triangles)
    shifted = MeshWheel(vertices - offset, triangles)  # its hub sits at +offset in the old frame
    # translation only: a spin about a different hub would be a different motion
    f1, t1 = wheel_contacts(device, centred, points, velocity=(0.01, 0, -0.003))
    f2, t2 = wheel_contacts(device, shifted, [p - offset for p in points], velocity=(0.01, 0, -0.003))
    np.testing.assert_allclose(f2, f1, rtol=1e-6, atol=1e-12)
    expected = t1 + np.cross(-offset, f1)
    np.testing.assert_allclose(t2, expected, rtol=1e-5, atol=1e-9 * np.abs(t1).max())


# -- testbed definitions -------------------------------------------------------------------
def test_slip_and_sinkage_definitions_on_a_prescribed_motion():
    omega, r = 0.5, 0.04
    for slip in (-0.2, 0.0, 0.3, 0.9):
        rig = SingleWheelRig(
            mass=1.0, radius=r, omega=omega, hub=(0, 0, 0.1), mode="slip", slip=slip, gravity=(0, 0, 0), landed=True
        )
        rig.advance(2.0)
        v = (rig.position[0] - 0.0) / 2.0
        assert slip_of(v, omega, r) == pytest.approx(slip, abs=1e-12)
        assert v == pytest.approx(omega * r * (1 - slip))
    # a rolling wheel with no slip advances omega r per second
    assert slip_of(np.array([omega * r]), omega, r)[0] == pytest.approx(0.0)


def bed_and_wheel(device, gravity, youngs_modulus, spec=None, wheel=WHEEL, settle_time=None):
    """A small settled bed (stiffness scaled with gravity) with the wheel added."""
    spec = spec or BedSpec(
        length=0.12,
        width=0.05,
        depth=0.025,
        radius_mean=3e-3,
        radius_spread=0.15,
        material=Material(
            youngs_modulus=youngs_modulus,
            poisson_ratio=0.3,
            density=2600,
            restitution=0.2,
            stick_angle=math.radians(30),
            slip_angle=math.radians(25),
            rolling_friction=0.1,
        ),
    )
    builder = build_bed(spec, gravity)
    model, state, control = builder.finalize(device, "double")
    sim = Simulation(model, state, control)
    dt = 0.2 * math.pi * 2.55e-3 * math.sqrt(2600 / spec.material.shear_modulus) / (0.1631 * 0.3 + 0.8766)
    report = settle(sim, dt, ke_ratio=1e-3, max_time=settle_time or 60 * math.sqrt(0.003 / abs(gravity)))
    assert report["settled"], report
    return spec, sim, dt


@pytest.mark.parametrize("gravity", [9.81, 5.7e-3])
def test_wheel_on_a_settled_bed_carries_its_weight(device, gravity, tmp_path):
    """A loaded wheel set on a settled bed stands still from 25 time units sqrt(r/g) on:
    its vertical speed stays below v_stand = 0.1 sqrt(2 g d) (d = grain diameter: its
    vertical kinetic energy is below 1 % of m g d), so, the rig's momentum changing by
    exactly the soil's impulse minus its weight, the mean soil force is m g within
    2 m v_stand / T over the window T; the wheel keeps touching the soil and has sunk in.

    The bed is chaotic: over 8 replicas (order_seed None, 1..7; CPU, double) the largest
    |v_z| / v_stand was 0.097 at g = 9.81 (0.008 to 0.097: rare grain rearrangements under
    the wheel) and 0.0007 at 5.7e-3; |F / (m g) - 1| <= 9.7e-4 against the bound 0.027;
    at least 6 grains touched the wheel; sinkage 3.3 mm (9.81) and 1.7 mm (5.7e-3)."""
    # stiffness scaled with g (paper eq. 10: E ~ load) keeps overlap/radius and the step count equal
    spec, sim, dt = bed_and_wheel(device, gravity, 1e7 * gravity / 9.81)
    surface = bed_metrics(sim, spec)["height"]
    save_bed(tmp_path / "bed.h5", sim, spec)
    wheel_sim = open_bed(
        tmp_path / "bed.h5",
        [(WHEEL, Material(youngs_modulus=1e7 * gravity / 9.81, restitution=0.2))],
        device=device,
        precision="double",
    )
    soil = DemSoil(wheel_sim, dt, surface_height=surface, wall_clearance=0.0)
    mass = 0.05
    rig = SingleWheelRig(
        mass=mass,
        radius=WHEEL.radius,
        omega=0.0,
        hub=(0.06, 0.025, surface + WHEEL.outer_radius),
        gravity=(0, 0, -gravity),
    )
    soil.place_wheels(rig.wheel_kinematics())
    t_scale = math.sqrt(0.003 / gravity)
    result = drive(soil, rig, duration=40 * t_scale, macro_step=5 * dt)
    tail = result["time"] > 25 * t_scale
    window = result["time"][-1] - result["time"][np.argmax(tail) - 1]
    v_stand = 0.1 * math.sqrt(2 * gravity * 2 * spec.radius_mean)
    assert np.max(np.abs(result["hub_velocity"][tail, 2])) < v_stand, "the wheel is not at rest"
    assert np.mean(result["normal_force"][tail]) == pytest.approx(mass * gravity, abs=2 * mass * v_stand / window)
    assert np.all(result["contact_count"][tail, 0] > 0), "the wheel lost the soil"
    assert result["sinkage_tips"][-1] > 0, "the wheel (its grouser tips) sank into the bed"


def rigid_ground(device, gravity, mu):
    """A rigid, rough floor: a lattice of fixed grains; the wheel rolls on their tops."""
    builder = SoilBuilder(gravity=gravity)
    angle = math.atan(mu)
    mat = builder.add_material(
        Material(youngs_modulus=1e8, restitution=0.2, stick_angle=angle, slip_angle=angle, stick_speed=1e-3)
    )
    r = 0.001
    xs, ys = np.meshgrid(np.arange(0, 0.4, 2 * r), np.arange(-0.012, 0.012, 2 * r), indexing="ij")
    builder.add_particles(np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)]), r, mat, fixed=True)
    smooth = GrouserWheel(radius=0.03, width=0.02)
    builder.add_wheel(smooth, mat)
    model, state, control = builder.finalize(device, "double")
    return Simulation(model, state, control), smooth, r


@pytest.mark.parametrize("load_ratio", [0.5, 1.5])
def test_rigid_wheel_on_rigid_ground_rolls_below_and_spins_above_the_traction_limit(device, load_ratio):
    """Driven at omega against a drawbar load F: below mu m g it rolls without slip
    (s ~ 0), above it the wheel cannot transmit F and spins (the carriage is pushed back).
    Below the limit the elastic contacts pass the load on through their springs, with a creep of
    under 1 % and a drawbar pull that swings about F over about 0.1 s: it is averaged over 0.2 s."""
    g, mu, mass, omega = 9.81, 0.5, 2.0, 10.0
    sim, wheel, r = rigid_ground(device, g, mu)
    soil = DemSoil(sim, 2e-5, surface_height=r, wall_clearance=0.0)
    rig = SingleWheelRig(
        mass=mass,
        radius=wheel.radius,
        omega=omega,
        hub=(0.05, 0.0, r + wheel.radius - 2e-5),
        drawbar_load=load_ratio * mu * mass * g,
        gravity=(0, 0, -g),
        landed=True,
    )
    rig.velocity[0] = omega * wheel.radius  # start rolling
    soil.place_wheels(rig.wheel_kinematics())
    result = drive(soil, rig, duration=0.3 if load_ratio < 1 else 0.1, macro_step=1e-4)
    tail = result["time"] > (0.1 if load_ratio < 1 else 0.05)
    slip = np.mean(result["slip"][tail])
    if load_ratio < 1:
        assert abs(slip) < 0.02, f"slip {slip} below the traction limit"
        assert np.mean(result["drawbar_pull"][tail]) == pytest.approx(load_ratio * mu * mass * g, rel=0.05)
    else:
        assert slip > 0.2, f"slip {slip} above the traction limit"
        # the ground delivers its full sliding friction, no more
        assert np.mean(result["drawbar_pull"][tail]) == pytest.approx(mu * mass * g, rel=0.05)


def test_saved_bed_reloads_bit_identically_and_runs_the_same(device, tmp_path):
    spec = BedSpec(
        length=0.06,
        width=0.04,
        depth=0.02,
        radius_mean=3e-3,
        radius_spread=0.15,
        material=Material(youngs_modulus=1e6, restitution=0.3),
    )
    builder = build_bed(spec, 9.81)
    model, state, control = builder.finalize(device, "mixed")
    sim = Simulation(model, state, control)
    sim.run(0.02, 1e-4)
    save_bed(tmp_path / "bed.h5", sim, spec)
    sim2 = open_bed(tmp_path / "bed.h5", device=device, precision="mixed")
    for name, array in sim.state.arrays.items():
        np.testing.assert_array_equal(getattr(sim2.state, name).numpy(), array.numpy(), err_msg=name)
    sim.run(0.02, 1e-4)
    sim2.run(0.02, 1e-4)
    np.testing.assert_array_equal(sim2.positions(), sim.positions())
    # and a file that is not a bed is refused clearly
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    with pytest.raises(ValueError, match="junk.h5.*not a readable HDF5 bed file"):
        read_bed(tmp_path / "junk.h5")


def test_a_bed_opens_the_same_from_memory_and_from_its_file(device, tmp_path):
    """The bed file is a lossless cache of the bed in memory: every array comes back with its values
    and dtype, and open_bed on either gives the same simulation to the last bit (positions,
    velocities, contact history), before and after steps, with a wheel and permuted grains. Opening
    leaves the bed in memory as it was, so one bed opens any number of simulations."""
    spec = BedSpec(
        length=0.06,
        width=0.04,
        depth=0.02,
        radius_mean=3e-3,
        radius_spread=0.15,
        material=Material(youngs_modulus=1e6, restitution=0.3, rolling_friction=0.1),
    )
    sim = Simulation(*build_bed(spec, 9.81).finalize(device, "double"))
    sim.run(0.02, 1e-4)
    in_memory = SavedBed.from_simulation(sim, spec, bed_metrics(sim, spec), key="k")
    in_memory.write(tmp_path / "bed.h5")
    from_file = read_bed(tmp_path / "bed.h5")

    def arrays(bed):
        named = {name: value for name, value in vars(bed).items() if isinstance(value, np.ndarray)}
        return {**named, **{f"state/{name}": np.asarray(value) for name, value in bed.state.items()}}

    before = {name: value.copy() for name, value in arrays(in_memory).items()}
    assert arrays(from_file).keys() == before.keys()
    for name, value in arrays(from_file).items():
        assert value.dtype == before[name].dtype, name
        np.testing.assert_array_equal(value, before[name], err_msg=name)
    assert (from_file.materials, from_file.pair_overrides, from_file.precision, from_file.spec, from_file.key) == (
        in_memory.materials,
        in_memory.pair_overrides,
        in_memory.precision,
        in_memory.spec,
        in_memory.key,
    )
    assert from_file.metrics == pytest.approx(in_memory.metrics)

    wheel = [(WHEEL, Material(youngs_modulus=1e6, restitution=0.2))]
    opened = [
        open_bed(bed, wheel, device=device, precision="mixed", order_seed=3) for bed in (in_memory, tmp_path / "bed.h5")
    ]
    for a in opened:
        a.control.set_body_motion(0, (0.03, 0.02, 0.05), (1, 0, 0, 0), (0, 0, -0.1), (0, 2.0, 0))
    for run in range(2):
        first, second = (s.state.to_numpy() for s in opened)
        assert first.keys() == second.keys()
        for name in first:
            np.testing.assert_array_equal(first[name], second[name], err_msg=f"{name} after {run} runs")
        assert first["pair_tangential"].any(), "the bed carries contact history"
        for a in opened:
            a.run(0.005, 1e-4)
    for name, value in arrays(in_memory).items():
        np.testing.assert_array_equal(value, before[name], err_msg=f"opening changed the bed's {name}")


def test_wall_proximity_warns(device):
    sim, wheel, r = rigid_ground(device, 9.81, 0.5)
    builder = SoilBuilder(gravity=9.81)
    builder.add_container((0, 0, 0), (0.1, 0.05, 0.1))
    builder.add_particle((0.05, 0.025, 0.002), 0.002)
    builder.add_wheel(wheel)
    model, state, control = builder.finalize(device, "double")
    soil = DemSoil(Simulation(model, state, control), 1e-4)
    with pytest.warns(WallProximityWarning, match="container wall"):
        soil.advance(1e-4, [upright((0.02, 0.025, 0.05))])
