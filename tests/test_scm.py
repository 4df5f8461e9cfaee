"""The Soil Contact Model terrain (soil.scm) against closed-form answers computed here.

Stress model of the implementation, and so of the reference integrals: each node's pressure
comes from its own sinkage (Bekker's curve on loading, K_e on unloading and reloading), acts
along the wheel surface's normal on the surface above the node, and the shear stress
(Mohr-Coulomb, Janosi-Hanamoto) opposes the wheel surface's slip over the node. For a rigid
wheel at a fixed sinkage that is the Wong-Reece integral over the contact arc with the local
sinkage z(theta) = r (cos(theta) - cos(theta_1)) on the front arc, an elastic rebound behind
the bottom (from the plastic sinkage the bottom left), and the shear displacement of a node
fixed in the ground: j(theta) = int_theta^theta_1 (r omega - v cos(t)) r cos(t) / v dt.
"""

import math

import numpy as np
import pytest
from scipy import integrate

from soil import GrouserWheel, MeshWheel
from soil.errors import SoilInputError
from soil.scm import ScmParameters, ScmTerrain

SPACING = 0.002
SAND = dict(k_c=2.0e4, k_phi=5.0e5, n=1.1, cohesion=1.0e3, friction_angle=30.0, janosi_k=0.01, elastic_stiffness=2.0e7)
UPRIGHT = [[1.0, 0.0, 0.0, 0.0]]


def parameters(**changes) -> ScmParameters:
    return ScmParameters(**{**SAND, "node_spacing": SPACING, **changes})


def plate(length: float, width: float, thickness: float = 0.01) -> MeshWheel:
    """A flat box plate, `length` along x and `width` along y, as a closed mesh (12 triangles)."""
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    corners *= [length, width, thickness]
    faces = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1)]
    faces += [(2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)]
    return MeshWheel(corners, np.array(faces), name="plate")


def centred(size: float) -> float:
    """A centre coordinate that puts exactly size / h nodes under a span of `size` (none on its edges)."""
    nodes = round(size / SPACING)
    return 0.0 if nodes % 2 else 0.5 * SPACING


class PlateRig:
    """A plate pressed quasi-statically: its bottom face at a given depth below the surface."""

    def __init__(self, length: float, width: float, soil: ScmParameters, device: str = "cpu"):
        self.thickness = 0.01
        self.area = length * width
        self.centre = (centred(length), centred(width))
        shape = plate(length, width, self.thickness)
        self.terrain = ScmTerrain(soil, [shape], window=(0.1, 0.08), centre=self.centre, device=device)

    def press(self, depth: float) -> float:
        """Vertical force [N] with the plate's bottom `depth` [m] below the undisturbed surface."""
        terrain = self.terrain
        position = [[self.centre[0], self.centre[1], 0.5 * self.thickness - depth]]
        terrain.advance(terrain.time + 1e-3, 1e-3, position, UPRIGHT)
        return float(terrain.wheel_contact().force[0, 2])


def test_plate_sinkage_is_bekkers_at_two_widths(device):
    soil = parameters()
    for width in (0.02, 0.04):
        rig = PlateRig(0.06, width, soil, device)
        for depth in (0.002, 0.005, 0.01):
            expected = rig.area * (soil.k_c / width + soil.k_phi) * depth**soil.n
            assert rig.press(depth) == pytest.approx(expected, rel=1e-12)
        assert rig.terrain.patch_width()[0] == pytest.approx(width, rel=1e-12)


def sink_under(rig: PlateRig, load: float, start: float) -> float:
    """Lower the plate from `start` [m] in half secant steps (never past the balance: the force curve
    is convex or straight) until the soil carries `load` [N]; returns the depth [m]."""
    previous = (start, rig.press(start))
    depth = start + 1e-5
    force = rig.press(depth)
    while load - force > 1e-10 * load:
        slope = (force - previous[1]) / (depth - previous[0])
        previous = (depth, force)
        depth += 0.5 * (load - force) / slope
        force = rig.press(depth)
    return depth


def test_plate_under_a_load_sinks_to_bekkers_depth():
    soil = parameters()
    width, length, load = 0.02, 0.06, 10.0
    rig = PlateRig(length, width, soil)
    expected = (load / (rig.area * (soil.k_c / width + soil.k_phi))) ** (1 / soil.n)
    assert sink_under(rig, load, 0.0) == pytest.approx(expected, rel=1e-8)


def test_unloading_is_elastic_and_reloading_retraces_it():
    soil = parameters()
    rig = PlateRig(0.06, 0.02, soil)
    bekker = lambda z: rig.area * soil.bekker_pressure(z, 0.02)  # noqa: E731
    top = rig.press(0.008)
    assert top == pytest.approx(bekker(0.008), rel=1e-12)
    lift = 2e-5
    assert rig.press(0.008 - lift) == pytest.approx(top - rig.area * soil.elastic_stiffness * lift, rel=1e-9)
    assert rig.press(0.008) == pytest.approx(top, rel=1e-9)  # back up the same line
    assert rig.press(0.009) == pytest.approx(bekker(0.009), rel=1e-12)  # and on along Bekker's curve


def test_ruts_persist_and_a_second_load_sinks_no_deeper():
    soil = parameters()
    rig = PlateRig(0.06, 0.02, soil)
    load = rig.press(0.008)
    assert rig.press(-0.005) == 0.0  # lifted clear
    rut = 0.008 - load / rig.area / soil.elastic_stiffness  # the plastic sinkage under the plate
    x, y = rig.centre
    assert rig.terrain.surface_height_at(x, y) == pytest.approx(-rut, rel=1e-9)
    assert rig.terrain.surface_height_at(x + 0.045, y) == 0.0  # beside the plate: untouched
    # the same load again: the soil carries it on the unloading line, at no more sinkage
    assert sink_under(rig, load, rut) <= 0.008 * (1 + 1e-9)


def wheel_run(wheel, sinkage, slip, soil, radius=0.1, width=0.04, travel=0.08, wheels=1, gap=0.22, device="cpu"):
    """Wheels of `radius` and `width` in a line along +x (`gap` apart) at hub height radius - sinkage,
    driven at slip `slip` over `travel` [m]; returns the terrain and the mean contact over the next
    node spacing of travel (the mean over the ripple of nodes entering the patch)."""
    speed, dt = 0.02, 0.01
    spin = speed / (radius * (1 - slip))
    hubs = [[-k * gap, centred(width), radius - sinkage] for k in range(wheels)]
    terrain = ScmTerrain(soil, [wheel] * wheels, window=(0.3 + gap * (wheels - 1), 0.1), device=device)
    end = travel / speed
    terrain.advance(end, dt, hubs, UPRIGHT * wheels, [[speed, 0, 0]] * wheels, [[0, spin, 0]] * wheels)
    terrain.advance(end + SPACING / speed, dt)
    return terrain, terrain.wheel_contact(mean=True)


def wong_reece(radius: float, width: float, sinkage: float, slip: float, soil: ScmParameters):
    """(W, DP, T) [N, N, N m] of the stress model above, by scipy quadrature over the contact arc."""
    r, n, elastic = radius, soil.n, soil.elastic_stiffness
    k = soil.k_c / width + soil.k_phi
    entry = math.acos(1 - sinkage / r)
    plastic = sinkage - k * sinkage**n / elastic
    rear = -math.acos(math.cos(entry) + plastic / r)  # where the rebounding soil lets go

    def sigma(theta):
        z = r * (math.cos(theta) - math.cos(entry))
        return k * z**n if theta >= 0 else max(0.0, elastic * (z - plastic))

    def tau(theta):
        j = integrate.quad(lambda t: (1 / (1 - slip) - math.cos(t)) * r * math.cos(t), theta, entry)[0]
        strength = soil.cohesion + sigma(theta) * math.tan(math.radians(soil.friction_angle))
        return strength * (1 - math.exp(-j / soil.janosi_k))

    def arc(f):
        return sum(integrate.quad(f, a, b, epsabs=0, epsrel=1e-10, limit=200)[0] for a, b in ((rear, 0), (0, entry)))

    load = r * width * arc(lambda t: sigma(t) * math.cos(t) + tau(t) * math.sin(t))
    pull = r * width * arc(lambda t: tau(t) * math.cos(t) - sigma(t) * math.sin(t))
    torque = r * r * width * arc(tau)
    return load, pull, torque


@pytest.mark.parametrize("slip", [0.1, 0.4])
def test_rigid_wheel_matches_the_wong_reece_integrals(slip, device):
    soil = parameters()
    wheel = GrouserWheel(radius=0.1, width=0.04)
    terrain, contact = wheel_run(wheel, 0.015, slip, soil, device=device)
    load, pull, torque = wong_reece(0.1, 0.04, 0.015, slip, soil)
    assert terrain.patch_width()[0] == pytest.approx(0.04, rel=1e-9)
    force, moment = contact.force[0], contact.torque[0]
    assert force[2] == pytest.approx(load, rel=2e-3)
    assert force[0] == pytest.approx(pull, rel=1e-2)
    assert -moment[1] == pytest.approx(torque, rel=5e-3)  # the soil resists the wheel's spin about +y
    assert abs(force[1]) < 1e-9 * load and abs(moment[0]) < 1e-9 * torque
    sag = SPACING**2 / (8 * 0.1)  # the deepest node is at most h / 2 from the bottom: r (1 - cos(h / 2r))
    assert 0.015 - sag <= contact.sinkage[0] <= 0.015 * (1 + 1e-12)


def test_a_mesh_wheel_matches_the_same_parametric_wheel():
    soil = parameters()
    wheel = GrouserWheel(radius=0.1, width=0.04)
    mesh = MeshWheel(*wheel.to_mesh(arc_segments=720))
    smooth = wheel_run(wheel, 0.015, 0.2, soil)[1]
    meshed = wheel_run(mesh, 0.015, 0.2, soil)[1]
    np.testing.assert_allclose(meshed.force, smooth.force, rtol=5e-3, atol=1e-3)
    np.testing.assert_allclose(meshed.torque, smooth.torque, rtol=5e-3, atol=1e-4)


def test_a_wheel_in_a_rut_carries_less_at_the_same_height():
    """A second wheel in the first one's rut, at the same hub height: the rut has yielded already."""
    terrain, contact = wheel_run(GrouserWheel(0.1, 0.04), 0.015, 0.2, parameters(), travel=0.32, wheels=2)
    front, rear = contact.force[:, 2]
    assert 0 < rear < 0.5 * front


def grousered_run(steps_before: int, steps_after: int, resume: bool, precision: str = "double", device: str = "cpu"):
    soil = parameters(bulldozing=True)
    wheel = GrouserWheel(radius=0.08, width=0.04, grouser_count=12, grouser_height=0.006, grouser_thickness=0.003)

    def build():
        return ScmTerrain(soil, [wheel], window=(0.3, 0.1), precision=precision, device=device)

    terrain = build()
    dt = 0.01
    terrain.advance(steps_before * dt, dt, [[0, 0.001, 0.07]], UPRIGHT, [[0.02, 0, 0]], [[0, 0.4, 0.01]])
    if resume:
        state = terrain.state_dict()
        terrain = build()
        terrain.load_state_dict(state)
    if steps_after:
        terrain.advance((steps_before + steps_after) * dt, dt)
    return terrain


def test_runs_repeat_and_resume_bit_for_bit(device):
    first = grousered_run(30, 30, resume=False, device=device)
    again = grousered_run(30, 30, resume=False, device=device)
    resumed = grousered_run(30, 30, resume=True, device=device)
    reference = first.state_dict()
    assert first.wheel_contact().contacts[0] > 0
    for other in (again, resumed):
        state = other.state_dict()
        for name, value in reference.items():
            assert np.array_equal(state[name], value), name
        for mine, theirs in zip(first.wheel_contact(mean=True), other.wheel_contact(mean=True)):
            assert np.array_equal(mine, theirs)


def test_a_state_is_refused_by_a_terrain_of_another_grid_naming_the_spacing():
    """A checkpoint continues only on the grid it was stepped on: another node spacing is refused with
    both spacings and the key that sets it (a run begun under another default grid, say), before
    anything is restored; a state of the same grid loads."""
    from dataclasses import replace

    from soil.errors import SoilInputError

    state = grousered_run(5, 0, resume=False).state_dict()
    assert state["node_spacing"] == SPACING
    wheel = GrouserWheel(radius=0.08, width=0.04, grouser_count=12, grouser_height=0.006, grouser_thickness=0.003)
    other = ScmTerrain(replace(parameters(bulldozing=True), node_spacing=0.8 * SPACING), [wheel], window=(0.3, 0.1))
    before = other.state_dict()
    with pytest.raises(
        SoilInputError, match=r"node spacing 0\.002 m, this terrain's is 0\.0016 m.*terrain\.node_spacing"
    ):
        other.load_state_dict(state)
    assert all(np.array_equal(other.state_dict()[k], v) for k, v in before.items())


def test_a_state_is_refused_by_a_terrain_of_another_soil_naming_the_parameter():
    """A stopped SCM run whose calibration file was edited before `cosim resume` went on, on the new soil,
    without a word: its steady window spanned two soils. The state keeps the soil it was stepped on, and
    a terrain of another soil refuses it before anything is restored, naming what changed."""
    state = grousered_run(5, 0, resume=False).state_dict()
    wheel = GrouserWheel(radius=0.08, width=0.04, grouser_count=12, grouser_height=0.006, grouser_thickness=0.003)
    other = ScmTerrain(parameters(bulldozing=True, k_phi=8.0e5), [wheel], window=(0.3, 0.1))
    before = other.state_dict()
    with pytest.raises(SoilInputError, match=r"another soil than this terrain's \(k_phi 500000 -> 800000\)"):
        other.load_state_dict(state)
    assert all(np.array_equal(other.state_dict()[k], v) for k, v in before.items())
    same = ScmTerrain(parameters(bulldozing=True), [wheel], window=(0.3, 0.1))
    same.load_state_dict(state)  # the soil it was stepped on: continues
    assert same.time == pytest.approx(0.05)
    same.load_state_dict({**state, "soil": state["soil"] * (1 + 4e-16)})  # a derived value's last bit, elsewhere
    with pytest.raises(SoilInputError, match="soil holds 1 values, 12 expected: a damaged checkpoint"):
        same.load_state_dict({**state, "soil": np.float64(1.0)})  # a 0-d entry was a TypeError


def test_grids_and_spans_past_what_a_number_counts_are_refused_in_words():
    """A window of 1e300 m (or a spacing of 1e-300 m) raised a bare OverflowError, a zero-size window was a
    grid of 2 nodes, and advance(1e12 s) at dt = 1e-3 s ran 1e15 steps, deaf to Ctrl-C."""
    from soil.scm.terrain import grid_shape

    wheel = GrouserWheel(0.1, 0.04)
    for window, spacing in (((1e300, 1e300), SPACING), ((0.5, 0.2), 1e-300)):
        with pytest.raises(SoilInputError, match="more than Warp indexes"):
            ScmTerrain(parameters(node_spacing=spacing), [wheel], window=window)
    for window, spacing in (((0.0, 1.0), 0.01), ((1.0, 1.0), -0.01), ((math.nan, 1.0), 0.01)):
        with pytest.raises(SoilInputError, match="window|node_spacing"):
            grid_shape(window, spacing)
    assert grid_shape((0.3, 0.1), 0.01) == (30, 10)
    terrain = ScmTerrain(parameters(), [wheel], window=(0.5, 0.2), centre=(0.0, 0.0))
    with pytest.raises(SoilInputError, match="more than 1e\\+10"):
        terrain.advance(1e12, 1e-3, [[0, 0, 0.09]], UPRIGHT)
    assert terrain.time == 0.0


def test_bulldozing_moves_the_ruts_volume_to_its_rims():
    """The raised rims hold the rut's plastic volume (fraction 1; the slope limiting moves soil, keeps it)."""
    terrain = grousered_run(40, 0, resume=False)
    _, _, field = terrain.height_field()
    state = terrain.state_dict()
    raised = np.sum(state["reference"] - terrain.surface_height)
    assert raised > 0 and raised == pytest.approx(np.sum(state["plastic"]), rel=1e-9)
    assert field.max() > 0.001 and field.min() < -0.005  # rims above the surface beside a rut


def test_single_precision_runs_the_same_kernels():
    single = grousered_run(20, 0, resume=False, precision="single").wheel_contact()
    double = grousered_run(20, 0, resume=False).wheel_contact()
    np.testing.assert_allclose(single.force, double.force, rtol=0.05, atol=0.05 * abs(double.force[0, 2]))


def test_the_window_scrolls_with_the_wheel_in_fixed_memory():
    soil = parameters()
    wheel = GrouserWheel(radius=0.1, width=0.04)
    terrain = ScmTerrain(soil, [wheel], window=(0.3, 0.1))
    memory, shape = terrain.memory_bytes(), terrain.shape
    speed, spin, dt = 0.1, 0.1 / (0.1 * 0.8), 0.01
    terrain.set_wheels([[0.0, 0.0, 0.085]], UPRIGHT, [[speed, 0, 0]], [[0, spin, 0]])
    means = []
    for end in (1.0, 8.0):  # 0.1 m and 0.8 m of travel: far beyond the window's 0.3 m
        terrain.advance(end, dt)
        terrain.advance(end + SPACING / speed, dt)
        means.append(terrain.wheel_contact(mean=True))
    assert terrain.memory_bytes() == memory and terrain.shape == shape
    np.testing.assert_allclose(means[1].force, means[0].force, rtol=1e-6, atol=1e-9)
    hub = 0.8 + SPACING
    x0, _ = terrain.window_origin()
    assert x0 * SPACING == pytest.approx(hub - 0.15, abs=2 * SPACING)
    assert terrain.surface_height_at(hub - 0.12, 0.0) < -0.005  # the rut behind the wheel, in the window
    assert terrain.surface_height_at(hub - 0.5, 0.0) == 0.0  # out of the window: forgotten


@pytest.mark.parametrize("precision", ["single", "double"])
def test_a_grids_memory_is_known_before_it_is_allocated(precision, monkeypatch):
    """grid_memory's device bytes are what a terrain's node arrays take, to the byte per node (two
    grids' terrains differ by the estimate's difference, up to the per-chunk sums); a grid Warp cannot
    index, or one larger than the free memory left beside what else the run holds, is refused before
    any allocation, naming the grid and the smallest node spacing that fits."""
    import soil.scm.terrain as terrain_module
    from soil.memory import SoilTooLargeError
    from soil.scm import check_grid, grid_memory

    wheel = GrouserWheel(radius=0.1, width=0.04)
    small = ScmTerrain(parameters(), [wheel], window=(0.1, 0.1), precision=precision)
    large = ScmTerrain(parameters(), [wheel], window=(0.4, 0.3), precision=precision)
    estimated = grid_memory(large.node_count, precision, "cpu")[0] - grid_memory(small.node_count, precision, "cpu")[0]
    measured = large.memory_bytes() - small.memory_bytes()
    per_node = estimated / (large.node_count - small.node_count)
    assert per_node == (88 if precision == "single" else 160)  # 13 node arrays and the next reference heights
    assert abs(measured - estimated) <= 0.01 * estimated
    device, host = grid_memory(1000, precision, "cuda:0")
    assert device == 1000 * per_node and host < device  # on a GPU the host keeps only a checkpoint's copy
    with pytest.raises(SoilInputError, match=r"75,000 x 60,000 = 4,500,000,000 nodes, more than Warp indexes"):
        ScmTerrain(parameters(node_spacing=2e-5), [wheel], window=(1.5, 1.2), precision=precision)
    # the free memory as a machine reports it: 1 GB on the host, 2 GB on the GPU
    monkeypatch.setattr(terrain_module, "free_host_memory", lambda: 10**9)
    monkeypatch.setattr(terrain_module, "free_device_memory", lambda device: 2 * 10**9)
    names = dict(what="the grid", keys=("grid.h", "grid.size"))
    fits_host = 10**9 / grid_memory(1, precision, "cpu")[1]  # nodes
    side = math.sqrt(fits_host) * 0.01  # [m] at 0.01 m a node
    check_grid((0.95 * side, 0.95 * side), 0.01, precision, "cpu", **names)  # fits
    with pytest.raises(
        SoilTooLargeError, match=r"the grid: .* of host memory \(1 GB free for it\); grid.h must be"
    ) as refused:
        check_grid((1.05 * side, 1.05 * side), 0.01, precision, "cpu", **names)
    least = float(str(refused.value).split("must be at least about ")[1].split(" m")[0])
    assert 0.0105 <= least <= 0.0111  # the spacing at which the same window fits
    with pytest.raises(SoilTooLargeError, match=r"\(500 MB free for it\)"):  # beside grains that take half
        check_grid((0.8 * side, 0.8 * side), 0.01, precision, "cpu", reserved=(0, 5 * 10**8), **names)
    fits_device = 2 * 10**9 / per_node
    side = math.sqrt(fits_device) * 0.01
    with pytest.raises(SoilTooLargeError, match=r"on cuda:0 \(2 GB free for it\)"):
        check_grid((1.05 * side, 1.05 * side), 0.01, precision, "cuda:0", **names)
    check_grid((1.05 * side, 1.05 * side), 0.01, precision, "cuda:0", memory=False, **names)  # the index only
    monkeypatch.setattr(terrain_module, "free_host_memory", lambda: None)
    check_grid((10.0, 10.0), 0.01, precision, "cpu", **names)  # free memory not reported: not judged


@pytest.mark.parametrize(
    "field, value",
    [
        ("k_c", -1.0),
        ("k_phi", float("nan")),
        ("n", 0.0),
        ("cohesion", -5.0),
        ("friction_angle", 90.0),
        ("janosi_k", 0.0),
        ("elastic_stiffness", -1.0),
        ("node_spacing", 0.0),
        ("damping", -1.0),
        ("bulldozing_fraction", 1.5),
        ("erosion_iterations", 1.5),
        ("n", "1.1"),
    ],
)
def test_bad_parameters_are_refused_naming_the_field(field, value):
    with pytest.raises(SoilInputError, match=rf"ScmParameters\.{field} must be"):
        parameters(**{field: value})


def test_bad_terrain_inputs_are_refused():
    with pytest.raises(SoilInputError, match="window"):
        ScmTerrain(parameters(), [GrouserWheel(0.1, 0.04)], window=(0.0, 0.1))
    terrain = ScmTerrain(parameters(), [GrouserWheel(0.1, 0.04)], window=(0.1, 0.1))
    with pytest.raises(SoilInputError, match="position"):
        terrain.set_wheels([[0, 0]], UPRIGHT)
    with pytest.raises(SoilInputError, match="dt"):
        terrain.advance(1.0, 0.0)
    with pytest.raises(SoilInputError, match="wheel 0 .* leaves the SCM window"):
        terrain.advance(1.0, 0.01, [[0, 0, 0.09]], UPRIGHT)  # 0.1 m wide: too small for a 0.2 m wheel
    wide = ScmTerrain(parameters(), [GrouserWheel(0.1, 0.04)], window=(0.5, 0.2), centre=(0.0, 0.0))
    with pytest.raises(SoilInputError, match="leaves the SCM window"):  # driven out of a fixed window
        wide.advance(10.0, 0.01, [[0, 0, 0.09]], UPRIGHT, [[0.1, 0, 0]])


def test_a_single_step_is_checked_as_advance_is():
    """step(dt) took a negative or nan dt (the terrain's time turned nan) and drove a wheel out of a fixed
    window to a force of 0 without a word; numpy's float32 steps and sizes were refused as not numbers;
    one wheel shape where the list goes was "'GrouserWheel' object is not iterable"."""
    wide = ScmTerrain(parameters(), [GrouserWheel(0.1, 0.04)], window=(0.5, 0.2), centre=(0.0, 0.0))
    wide.set_wheels([[0, 0, 0.09]], UPRIGHT, [[0.1, 0, 0]])
    for dt in (-0.01, math.nan, math.inf):
        with pytest.raises(SoilInputError, match="dt must be >= 0"):
            wide.step(dt)
    assert wide.time == 0.0
    wide.step(np.float32(0.01))  # a numpy step is a step
    with pytest.raises(SoilInputError, match="leaves the SCM window"):
        for _ in range(2000):  # 0.1 m/s out of a window 0.5 m long: out within 1.5 s
            wide.step(0.01)
    assert wide.time < 1.6
    ScmTerrain(
        parameters(), [GrouserWheel(0.1, 0.04)], window=(np.float32(0.5), np.int64(1)), surface_height=np.float32(0)
    )
    with pytest.raises(SoilInputError, match=r"wheels must be a list of wheel shapes: \[GrouserWheel"):
        ScmTerrain(parameters(), GrouserWheel(0.1, 0.04), window=(0.5, 0.2))


@pytest.mark.parametrize("damage", ["missing", "shape"])
def test_a_damaged_state_is_refused_naming_its_keys_before_anything_is_restored(damage):
    """A state without one of its arrays was a bare KeyError ({'version': 2} alone: 'shape'), one of
    another shape a terrain restored halfway; both are refused naming the key, the terrain unchanged."""
    state = grousered_run(5, 0, resume=False).state_dict()
    wheel = GrouserWheel(radius=0.08, width=0.04, grouser_count=12, grouser_height=0.006, grouser_thickness=0.003)
    other = ScmTerrain(parameters(bulldozing=True), [wheel], window=(0.3, 0.1))
    before = other.state_dict()
    if damage == "missing":
        with pytest.raises(SoilInputError, match=r"SCM state lacks shape, precision, time.*a damaged checkpoint"):
            other.load_state_dict({"version": state["version"]})
        damaged = {k: v for k, v in state.items() if k != "plastic"}
        named = r"lacks plastic:"
    else:
        damaged = {**state, "sums": state["sums"][:-1]}
        named = r"other shapes: sums \(\d+,"
    with pytest.raises(SoilInputError, match=named):
        other.load_state_dict(damaged)
    assert all(np.array_equal(other.state_dict()[k], v) for k, v in before.items())
    other.load_state_dict(state)  # the whole state still loads
    assert other.time == pytest.approx(state["time"])
