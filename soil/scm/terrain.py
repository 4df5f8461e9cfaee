"""The SCM terrain's host side: its parameters, state and stepping (soil.scm explains the model)."""

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import warp as wp

from ..control import quaternion_integrate, quaternion_to_matrix
from ..devices import warp_device
from ..errors import SoilInputError, is_real
from ..geometry import GrouserWheel, MeshWheel
from ..memory import SoilTooLargeError, format_bytes, free_device_memory, free_host_memory
from ..precision import get_precision
from .kernels import GROUSER_WHEEL, MESH_WHEEL, scm_kernels

CHUNK = 256
"""Nodes per partial sum of a wheel's wrench and patch extents (fixed: the sums are deterministic)."""

NO_KEY = 2147483647
"""A node key no grid node has: a slot holding it is reset when a step first works it."""

NO_BOX = -(2**30)
"""First node of a wheel's box before the first step (with no nodes: the first step releases none)."""

STATE_VERSION = 2

_SOIL_STATE = (
    "k_c",
    "k_phi",
    "n",
    "cohesion",
    "friction_angle",
    "janosi_k",
    "elastic_stiffness",
    "damping",
    "bulldozing",
    "bulldozing_fraction",
    "erosion_angle",
    "erosion_iterations",
)
"""The ScmParameters a state_dict keeps (as numbers) and load_state_dict requires of its terrain."""

MAX_ADVANCE_STEPS = 1e10
"""Most steps one ScmTerrain.advance takes (the scene's limit on a phase's steps, cosim.scene)."""

MAX_EROSION_ITERATIONS = 100
"""Most slope-limiting passes a step takes [count]: each moves soil one node further down a slope, a few
a step suffice (2 here, 3 in common SCM implementations); a step of many more costs as many grid passes
and is better bought as a shorter step."""


SCM_PARAMETER_UNITS = {
    "k_c": "Pa m^(1-n)",
    "k_phi": "Pa m^(-n)",
    "n": "1",
    "cohesion": "Pa",
    "friction_angle": "deg",
    "janosi_k": "m",
    "elastic_stiffness": "Pa/m",
    "node_spacing": "m",
    "damping": "Pa s/m",
    "bulldozing": "1",
    "bulldozing_fraction": "1",
    "erosion_angle": "deg",
    "erosion_iterations": "count",
}
"""The unit of each ScmParameters field."""


@dataclass(frozen=True)
class ScmParameters:
    """The soil's SCM parameters (SI units; the angles, friction_angle and erosion_angle, in DEGREES as
    the scene's keys, unlike soil.Material's angles, which are in radians). Wong's dry sand (Theory of
    Ground Vehicles) is
    ScmParameters(k_c=0.99e3, k_phi=1528.43e3, n=1.1, cohesion=1.04e3, friction_angle=28,
    janosi_k=0.02, elastic_stiffness=4e8, node_spacing=0.005)."""

    k_c: float
    """Bekker cohesive modulus k_c [Pa m^(1-n)] (>= 0)."""
    k_phi: float
    """Bekker frictional modulus k_phi [Pa m^(-n)] (>= 0; k_c + k_phi > 0)."""
    n: float
    """Bekker sinkage exponent n [-] (> 0)."""
    cohesion: float
    """Mohr-Coulomb cohesion c [Pa] (>= 0)."""
    friction_angle: float
    """Mohr-Coulomb internal friction angle phi in DEGREES [deg] (in [0, 90); soil.Material's angles are
    in radians)."""
    janosi_k: float
    """Janosi-Hanamoto shear deformation modulus K [m] (> 0)."""
    elastic_stiffness: float
    """Unloading/reloading stiffness K_e [Pa/m] (> 0); larger than the Bekker curve's slope where
    the soil is loaded, so that unloading is stiffer than loading. Only > 0 is checked: that slope,
    n (k_c / b + k_phi) z^(n - 1), depends on the patch width b and the sinkage z of a run (a smaller
    K_e leaves the soil elastic up to where K_e z meets the Bekker curve)."""
    node_spacing: float
    """Grid node spacing h [m] (> 0)."""
    damping: float = 0.0
    """Normal damping R [Pa s/m] (>= 0) on the wheel surface's speed into the soil."""
    bulldozing: bool = False
    """Move the soil that a wheel's patch displaces (its plastic sinkage) to the patch's rims (the nodes
    out of contact next to it, shared equally), then let slopes steeper than the erosion angle slide."""
    bulldozing_fraction: float = 1.0
    """Fraction of the displaced volume moved to the rims [-] (in [0, 1]; the rest is compaction)."""
    erosion_angle: float = 30.0
    """Steepest slope the moved soil keeps between free nodes [deg] (in (0, 90))."""
    erosion_iterations: int = 2
    """Slope-limiting passes per step over the nodes out of contact (0 .. MAX_EROSION_ITERATIONS)."""

    def __post_init__(self):
        def number(name: str) -> float:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise SoilInputError(f"ScmParameters.{name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise SoilInputError(f"ScmParameters.{name} must be finite, got {value!r}")
            return float(value)

        def check(name: str, ok: bool, allowed: str) -> None:
            if not ok:
                raise SoilInputError(f"ScmParameters.{name} must be {allowed}, got {getattr(self, name)!r}")

        for name in ("k_c", "k_phi", "cohesion", "damping"):
            check(name, number(name) >= 0, ">= 0")
        check("k_phi", self.k_c + self.k_phi > 0, "> 0 when k_c is 0 (k_c + k_phi > 0)")
        for name in ("n", "janosi_k", "elastic_stiffness", "node_spacing"):
            check(name, number(name) > 0, "> 0")
        check("n", number("n") < 3, "< 3 (a wheel's Bekker sinkage has 3 - n; soils measure 0.2-1.5)")
        check("friction_angle", 0 <= number("friction_angle") < 90, "in [0, 90) [deg]")
        check("bulldozing", isinstance(self.bulldozing, bool), "True or False")
        check("bulldozing_fraction", 0 <= number("bulldozing_fraction") <= 1, "in [0, 1]")
        check("erosion_angle", 0 < number("erosion_angle") < 90, "in (0, 90) [deg]")
        iterations = self.erosion_iterations
        check(
            "erosion_iterations",
            isinstance(iterations, (int, np.integer))
            and not isinstance(iterations, bool)
            and 0 <= iterations <= MAX_EROSION_ITERATIONS,
            f"an integer in [0, {MAX_EROSION_ITERATIONS}]",
        )

    def bekker_pressure(self, sinkage, width):
        """Bekker pressure (k_c / b + k_phi) z^n [Pa] at sinkage z [m] under a patch of width b [m]."""
        return (self.k_c / width + self.k_phi) * np.power(sinkage, self.n)


class WheelContact(NamedTuple):
    """The soil's push on each wheel (world frame), arrays over the wheels."""

    force: np.ndarray
    """Force [N], shape (k, 3)."""
    torque: np.ndarray
    """Torque about the hub [N m], shape (k, 3)."""
    contacts: np.ndarray
    """Nodes in contact [-], shape (k,) (a mean over the steps for `wheel_contact(mean=True)`)."""
    sinkage: np.ndarray
    """Deepest sinkage of a contact node below its reference level [m], shape (k,)."""


PATH_COLUMNS = 13
"""Columns of a wheel's path row: position (3), orientation (w, x, y, z) (4), velocity (3), angular velocity (3)."""

_NODE_STATE = ("key_i", "key_j", "reference", "plastic", "shear")
"""The per-node arrays a run carries from step to step (the rest is rewritten where a step reads it)."""

MAX_NODES = 2**31 - 1
"""The most nodes a grid may have: Warp indexes an array with a signed 32-bit integer."""


def grid_shape(window: Sequence[float], node_spacing: float) -> tuple[int, int]:
    """Nodes along x and y of a grid window (length, width) [m] at `node_spacing` [m] (whole nodes, at least 2)."""
    if not (is_real(node_spacing) and math.isfinite(node_spacing) and node_spacing > 0):
        raise SoilInputError(f"node_spacing must be a finite number > 0 [m], got {node_spacing!r}")
    if not (_is_pair(window) and all(is_real(s) and math.isfinite(s) and s > 0 for s in window)):
        raise SoilInputError(f"window must be two sizes > 0 (length along x, width along y) [m], got {window!r}")
    along = (window[0] / node_spacing, window[1] / node_spacing)
    if not all(math.isfinite(a) for a in along):
        raise SoilInputError(
            f"a window of {window[0]:.4g} x {window[1]:.4g} m at node spacing {node_spacing:.3g} m has more nodes than "
            "a number holds"
        )
    return max(2, int(round(along[0]))), max(2, int(round(along[1])))


def _count(number: int) -> str:
    """A node count in words: digits with thousands' commas, or 3 digits and an exponent past 1e15."""
    if number < 10**15:
        return f"{number:,}"
    digits = str(number)  # not float(): a count past 1e308 overflows it
    return f"{digits[0]}.{digits[1:3]}e+{len(digits) - 1}"


def window_reach(nodes: int, node_spacing: float) -> float:
    """The least distance [m] from a following window's centre to its edge along an axis of `nodes` nodes,
    wherever in its node the centre falls (the window starts nodes // 2 nodes below the centre's node and
    spans nodes - 1 spacings, as ScmTerrain places it): a footprint reaching no further stays inside."""
    return min(nodes // 2, nodes - 2 - nodes // 2) * node_spacing


def grid_memory(node_count: int, precision: str, device: str) -> tuple[int, int]:
    """(device, host) bytes an ScmTerrain of `node_count` nodes needs for what grows with its grid [B]:
    on the device the Nodes arrays and the next step's reference heights; on the host the copy of the
    node state that a checkpoint or a height field takes (with its slot index), plus the device's bytes
    when the device is the CPU. The per-wheel and per-chunk arrays (a few kB) are left out."""
    prec = get_precision(precision)
    nodes = scm_kernels(prec.hi).Nodes.vars
    size = wp.types.type_size_in_bytes
    on_device = sum(size(var.type.dtype) for var in nodes.values()) + size(prec.hi)
    copied = sum(size(nodes[name].type.dtype) for name in (*_NODE_STATE, "wheel")) + 8
    device_bytes, host_bytes = int(node_count) * on_device, int(node_count) * copied
    if not str(device).startswith("cuda"):
        host_bytes += device_bytes
    return device_bytes, host_bytes


def check_grid(
    window: Sequence[float],
    node_spacing: float,
    precision: str,
    device: str,
    *,
    what: str,
    keys: tuple[str, str],
    reserved: tuple[int, int] = (0, 0),
    memory: bool = True,
) -> None:
    """Refuse, before anything is allocated, a grid of `window` (length, width) [m] at `node_spacing` [m]
    that Warp cannot index (more than MAX_NODES nodes: SoilInputError) or, with `memory`, that does not
    fit this machine's free memory less `reserved` (device, host) bytes [B] that something else of the
    same run takes (soil.memory.SoilTooLargeError). `what` names the grid; `keys` are the names of the
    node spacing and of the window's sizes, for the smallest spacing the message says is allowed."""
    spacing_key, window_keys = keys
    fix = f"or a smaller window ({window_keys})"
    along = (window[0] / node_spacing, window[1] / node_spacing)
    if not all(math.isfinite(a) for a in along):  # more nodes than a float counts (1e300 m, 1e-300 m)
        least = math.sqrt(window[0]) * math.sqrt(window[1]) / math.sqrt(MAX_NODES)
        raise SoilInputError(
            f"{what}: more nodes than a number holds, more than Warp indexes ({MAX_NODES:,}); "
            f"{spacing_key} must be at least about {least:.3g} m on this window, {fix}"
        )
    shape = grid_shape(window, node_spacing)
    count = shape[0] * shape[1]
    if count > MAX_NODES:
        least = node_spacing * math.sqrt(shape[0] / MAX_NODES) * math.sqrt(shape[1])
        raise SoilInputError(
            f"{what}: {_count(shape[0])} x {_count(shape[1])} = {_count(count)} nodes, more than Warp indexes "
            f"({MAX_NODES:,}); "
            f"{spacing_key} must be at least about {least:.3g} m on this window, {fix}"
        )
    if not memory:
        return
    device_bytes, host_bytes = grid_memory(count, precision, device)
    cuda = str(device).startswith("cuda")
    need = {"device": device_bytes, "host": host_bytes}
    free = {"device": free_device_memory(device) if cuda else None, "host": free_host_memory()}
    left = {w: max(0, f - r) for (w, f), r in zip(free.items(), reserved) if f is not None}
    if all(need[w] <= left[w] for w in left):  # free memory not reported: nothing to judge
        return
    fits = min(left[w] / need[w] for w in left) * count
    least = node_spacing * math.sqrt(count / max(fits, 1.0))
    on = (
        f"{format_bytes(device_bytes)} on {device} ({format_bytes(left.get('device'))} free for it) and "
        if cuda
        else ""
    )
    raise SoilTooLargeError(
        f"{what}: {count:,} nodes need about {on}{format_bytes(host_bytes)} of host memory "
        f"({format_bytes(left.get('host'))} free for it); {spacing_key} must be at least about {least:.3g} m on this "
        f"window, {fix}, or use a machine with more memory"
    )


def _is_pair(value) -> bool:
    """Whether `value` is a sequence of two items (a tuple, a list, an array), not one number nor a text."""
    if isinstance(value, (str, bytes)):
        return False
    try:
        return len(value) == 2
    except TypeError:  # a number, a 0-d array
        return False


class ScmTerrain:
    """An SCM terrain: a flat soil surface at height `surface_height` (world z up) under a window of
    nodes that follows the wheels, and the wheels pressed into it.

    Each step evaluates the wheels at their pose at the start of the step (on constant-velocity
    paths from the start of `advance`, like soil.control's body paths) and updates the nodes.
    """

    def __init__(
        self,
        parameters: ScmParameters,
        wheels: Sequence[GrouserWheel | MeshWheel],
        *,
        window: tuple[float, float] = (1.0, 0.5),
        surface_height: float = 0.0,
        centre: tuple[float, float] | None = None,
        device: str = "cpu",
        precision: str = "double",
    ):
        """
        parameters: the soil (ScmParameters).
        wheels: the wheels' shapes (soil.geometry), in the order of every per-wheel array.
        window: the grid window's size along world x and y [m] (rounded to whole nodes); it must hold
            every wheel's contact patch, so a rover's window spans its wheelbase and track.
        surface_height: the undisturbed surface's height [m].
        centre: a fixed window centre (x, y) [m]; None: the window follows the wheels' mean hub position.
        device, precision: Warp device; "single", "double" or "mixed" (the SCM uses the `hi` type).
        """
        if not isinstance(parameters, ScmParameters):
            raise SoilInputError(f"parameters must be ScmParameters, got {type(parameters).__name__}")
        if isinstance(wheels, (GrouserWheel, MeshWheel)):  # one shape where the list of them goes
            raise SoilInputError(f"wheels must be a list of wheel shapes: [{type(wheels).__name__}(...)]")
        wheels = list(wheels)
        if not wheels:
            raise SoilInputError("wheels must name at least one wheel (GrouserWheel or MeshWheel)")
        for index, wheel in enumerate(wheels):
            if not isinstance(wheel, (GrouserWheel, MeshWheel)):
                raise SoilInputError(f"wheels[{index}] must be a GrouserWheel or MeshWheel, got {type(wheel).__name__}")
        # a pair first: len() of one number is a bare TypeError
        if not (_is_pair(window) and all(is_real(s) and math.isfinite(s) and s > 0 for s in window)):
            raise SoilInputError(f"window must be two sizes > 0 (length along x, width along y) [m], got {window!r}")
        if not (is_real(surface_height) and math.isfinite(surface_height)):
            raise SoilInputError(f"surface_height must be a finite number [m], got {surface_height!r}")
        if centre is not None and not (_is_pair(centre) and all(is_real(c) and math.isfinite(c) for c in centre)):
            raise SoilInputError(f"centre must be None or two finite numbers (x, y) [m], got {centre!r}")
        self.parameters = parameters
        self.wheels = wheels
        self.device = wp.get_device(warp_device(device))
        self.precision = get_precision(precision)
        self.surface_height = float(surface_height)
        spacing = parameters.node_spacing
        check_grid(
            window,
            spacing,
            self.precision.name,
            str(self.device),
            what=f"the SCM grid of window {window[0]:.4g} x {window[1]:.4g} m at node spacing {spacing:.3g} m",
            keys=("parameters.node_spacing", "window"),
        )
        self.shape = grid_shape(window, spacing)
        self.node_count = self.shape[0] * self.shape[1]
        self._chunks = (self.node_count + CHUNK - 1) // CHUNK
        reach = max(math.hypot(*cylinder_of(wheel)) for wheel in wheels)
        self.box_size = int(math.floor(2 * reach / spacing)) + 5
        """The most nodes along x or y of a wheel's box (kernels.place_window: the nodes under the footprint
        of the cylinder that holds the wheel, plus one spacing round it, at any orientation; the
        footprint's reach along x or y is at most the cylinder's half diagonal). A step works the
        boxes' nodes only: its cost is that of the wheels' footprints, not of the window."""
        self.kernels = scm_kernels(self.precision.hi)
        self._follow = centre is None
        self._footprint_bound = np.array([math.hypot(*cylinder_of(wheel)) for wheel in wheels])
        """Per wheel: the largest reach of its footprint along x or y at any orientation [m]."""
        self.time = 0.0
        self.steps = 0
        self._summed_steps = 0
        self._build_arrays(centre)
        self._record_launches()

    # -- set-up ------------------------------------------------------------------------------
    def _build_arrays(self, centre) -> None:
        prec, device = self.precision, self.device
        hi, np_hi = prec.hi, prec.np_hi
        count = len(self.wheels)
        zeros = lambda n, dtype: wp.zeros(n, dtype=dtype, device=device)  # noqa: E731
        kinds, shapes, mesh_ids, point_offsets, index_offsets, points, indices = [], [], [], [], [], [], []
        self._meshes = []
        n_points = n_indices = 0
        for wheel in self.wheels:
            point_offsets.append(n_points)
            index_offsets.append(n_indices)
            if isinstance(wheel, GrouserWheel):
                kinds.append(GROUSER_WHEEL)
                shapes.append(wheel.shape_row())
                mesh_ids.append(0)
                continue
            kinds.append(MESH_WHEEL)
            shapes.append([0, 0, 0, 0, 0, wheel.bounding_radius])
            mesh = wp.Mesh(
                points=wp.array(wheel.vertices.astype(np.float32), dtype=wp.vec3, device=device),
                indices=wp.array(wheel.triangles.reshape(-1), dtype=wp.int32, device=device),
            )
            self._meshes.append(mesh)
            mesh_ids.append(mesh.id)
            points.append(wheel.vertices)
            indices.append(wheel.triangles.reshape(-1))
            n_points += len(wheel.vertices)
            n_indices += wheel.triangles.size
        bundle = self.kernels.Wheels()
        bundle.kind = wp.array(np.array(kinds, dtype=np.int32), dtype=wp.int32, device=device)
        bundle.shape = wp.array(np.array(shapes, dtype=np_hi).reshape(-1, 6), dtype=hi, device=device)
        bundle.mesh = wp.array(np.array(mesh_ids, dtype=np.uint64), dtype=wp.uint64, device=device)
        bundle.mesh_points = wp.array(
            (np.concatenate(points) if points else np.zeros((1, 3))).astype(np_hi), dtype=prec.vec_hi, device=device
        )
        bundle.mesh_indices = wp.array(
            (np.concatenate(indices) if indices else np.zeros(3)).astype(np.int32), dtype=wp.int32, device=device
        )
        bundle.point_offset = wp.array(np.array(point_offsets, dtype=np.int32), dtype=wp.int32, device=device)
        bundle.index_offset = wp.array(np.array(index_offsets, dtype=np.int32), dtype=wp.int32, device=device)
        bundle.cylinder = wp.array(
            np.array([cylinder_of(wheel) for wheel in self.wheels], dtype=np_hi), dtype=hi, device=device
        )
        bundle.position = zeros(count, prec.vec_hi)
        bundle.rotation = wp.array(np.tile(np.eye(3, dtype=np_hi), (count, 1, 1)), dtype=prec.mat_hi, device=device)
        bundle.velocity = zeros(count, prec.vec_hi)
        bundle.angular_velocity = zeros(count, prec.vec_hi)
        self._wheels = bundle
        path = np.zeros((count, PATH_COLUMNS), dtype=np_hi)
        path[:, 3] = 1.0
        self._host_path = path.astype(np.float64)
        self._path = wp.zeros(path.shape, dtype=hi, device=device)
        self._path.assign(path)
        self._path_start = 0.0
        self._clock = wp.zeros(1, dtype=hi, device=device)

        p = self.parameters
        soil = self.kernels.Soil()
        soil.k_c, soil.k_phi, soil.n = hi(p.k_c), hi(p.k_phi), hi(p.n)
        soil.cohesion, soil.tan_phi = hi(p.cohesion), hi(math.tan(math.radians(p.friction_angle)))
        soil.janosi_k, soil.elastic_stiffness, soil.damping = hi(p.janosi_k), hi(p.elastic_stiffness), hi(p.damping)
        soil.spacing, soil.surface = hi(p.node_spacing), hi(self.surface_height)
        soil.nx, soil.ny = self.shape
        soil.box = self.box_size
        self._soil = soil
        self._centre = wp.zeros(2, dtype=hi, device=device)
        # the host's copy of a fixed centre, as the device holds it: the window check reads no device array
        self._centre_host = np.zeros(2) if centre is None else np.array(centre, dtype=np_hi).astype(np.float64)
        if centre is not None:
            self._centre.assign(np.array(centre, dtype=np_hi))
        self._origin = wp.zeros(2, dtype=wp.int32, device=device)
        no_box = np.tile(np.array([NO_BOX, NO_BOX, 0, 0], dtype=np.int32), (count, 1))
        self._boxes: wp.array = wp.array(no_box, dtype=wp.int32, device=device)
        self._boxes_before: wp.array = wp.array(no_box, dtype=wp.int32, device=device)

        n = self.node_count
        nodes = self.kernels.Nodes()
        nodes.key_i = wp.full(n, NO_KEY, dtype=wp.int32, device=device)
        nodes.key_j = wp.full(n, NO_KEY, dtype=wp.int32, device=device)
        nodes.reference = zeros(n, hi)
        nodes.plastic = zeros(n, hi)
        nodes.shear = zeros(n, hi)
        nodes.wheel = wp.full(n, -1, dtype=wp.int32, device=device)
        nodes.rim = wp.full(n, -1, dtype=wp.int32, device=device)
        nodes.hit = zeros(n, prec.vec_hi)
        nodes.normal = zeros(n, prec.vec_hi)
        nodes.pressure = zeros(n, hi)
        nodes.flow = zeros(n, hi)
        nodes.force = zeros(n, prec.vec_hi)
        nodes.torque = zeros(n, prec.vec_hi)
        self._nodes = nodes
        self._reference_next = zeros(n, hi)

        chunks = self._chunks
        self._low = wp.zeros((count, 2 * chunks), dtype=hi, device=device)
        self._high = wp.zeros((count, 2 * chunks), dtype=hi, device=device)
        self._width = zeros(count, hi)
        self._force_part = wp.zeros((count, chunks), dtype=prec.vec_hi, device=device)
        self._torque_part = wp.zeros((count, chunks), dtype=prec.vec_hi, device=device)
        self._count_part = wp.zeros((count, chunks), dtype=wp.int32, device=device)
        self._deepest_part = wp.zeros((count, chunks), dtype=hi, device=device)
        self._flow_part = wp.zeros((count, chunks), dtype=hi, device=device)
        self._rim_part = wp.zeros((count, chunks), dtype=wp.int32, device=device)
        self._raise_by = zeros(count, hi)
        self._totals = wp.zeros((count, 8), dtype=hi, device=device)
        self._sums = wp.zeros((count, 8), dtype=hi, device=device)

    @property
    def wheel_count(self) -> int:
        return len(self.wheels)

    # -- kinematics --------------------------------------------------------------------------
    def set_wheels(self, position, orientation, velocity=None, angular_velocity=None) -> None:
        """The wheels' hub positions [m] (k, 3), orientations (w, x, y, z) (k, 4) (wheel -> world; the
        axle is the wheel's local Y), velocities [m/s] (k, 3) and angular velocities [rad/s] (k, 3),
        world frame, at the current time: the start of a path of constant velocities that the next
        steps follow. Velocities default to zero."""
        count = self.wheel_count

        def rows(name, value, width):
            array = np.asarray(value, dtype=np.float64)
            if array.shape != (count, width) or not np.all(np.isfinite(array)):
                raise SoilInputError(f"{name} must be finite, shape ({count}, {width}), got {array.shape}")
            return array

        position = rows("position", position, 3)
        orientation = rows("orientation", orientation, 4)
        norms = np.linalg.norm(orientation, axis=1)
        if np.any(norms < 1e-12):
            raise SoilInputError("orientation must hold unit quaternions (w, x, y, z), got a zero row")
        orientation = orientation / norms[:, None]
        velocity = rows("velocity", np.zeros((count, 3)) if velocity is None else velocity, 3)
        spin = rows("angular_velocity", np.zeros((count, 3)) if angular_velocity is None else angular_velocity, 3)
        path = np.concatenate([position, orientation, velocity, spin], axis=1).astype(self.precision.np_hi)
        self._path.assign(path)
        self._host_path = path.astype(np.float64)
        self._path_start = self.time
        self._check_window(0.0)
        self._clock.zero_()
        self._pose(0.0)

    def _check_window(self, tau: float) -> None:
        """Refuse a pose (the path's at tau [s] after its start) with a wheel's footprint outside the
        window: the nodes it would press on are not held. The footprint is that of the cylinder round
        the wheel (its outer radius, its width) about its axle."""
        path = self._host_path
        hubs = path[:, 0:3] + path[:, 7:10] * tau
        h, (nx, ny) = self.parameters.node_spacing, self.shape
        centre = hubs[:, :2].mean(axis=0) if self._follow else self._centre_host
        low = (np.floor(centre / h) - np.array([nx // 2, ny // 2])) * h
        high = low + (np.array([nx, ny]) - 1) * h
        bound = self._footprint_bound[:, None]  # no axle turns a footprint beyond it (Cauchy-Schwarz)
        if np.all(hubs[:, :2] - bound >= low) and np.all(hubs[:, :2] + bound <= high):
            return  # every footprint inside at any orientation: the per-wheel turn need not be computed
        for index, (hub, wheel) in enumerate(zip(hubs, self.wheels)):
            orientation = quaternion_integrate(path[index, 3:7], path[index, 10:13], tau)
            axle = quaternion_to_matrix(orientation)[:2, 1]  # its world x and y parts
            radius, half_width = cylinder_of(wheel)
            reach = radius * np.sqrt(np.clip(1 - axle**2, 0, 1)) + half_width * np.abs(axle)
            if np.any(hub[:2] - reach < low) or np.any(hub[:2] + reach > high):
                raise SoilInputError(
                    f"wheel {index} (hub at x={hub[0]:.4g}, y={hub[1]:.4g} m, reach {reach[0]:.4g} x {reach[1]:.4g} m) "
                    f"leaves the SCM window [{low[0]:.4g}, {high[0]:.4g}] x [{low[1]:.4g}, {high[1]:.4g}] m at "
                    f"t={self._path_start + tau:.6g} s: enlarge `window` (it must hold every wheel's footprint)"
                )

    def _pose(self, dt: float) -> None:
        """Pose the wheels at the path's clock + dt [s] and move the clock on by dt (no host read)."""
        launch = self._launch
        if not dt:
            launch["pose_now"].launch()
            return
        self._set_step(dt)
        launch["pose_next"].launch()
        launch["tick"].launch()

    def _record_launches(self) -> None:
        """The step's kernel launches, recorded once (wp.launch(record_cmd=True)) and replayed: their arrays
        and structs stay where they are for the terrain's life, and on the CPU packing the arguments of
        a launch costs about as much as a small kernel. Only the step length changes (_set_step)."""
        kernels, device, hi, p = self.kernels, self.device, self.precision.hi, self.parameters
        nodes, wheels, soil = self._nodes, self._wheels, self._soil
        count, chunks, n = self.wheel_count, self._chunks, self.node_count
        boxes, boxes_before, origin = self._boxes, self._boxes_before, self._origin
        box = (count, self.box_size, self.box_size)

        def record(kernel, dim, inputs, outputs=()):
            return wp.launch(kernel, dim=dim, inputs=inputs, outputs=list(outputs), device=device, record_cmd=True)

        pose = [wheels.position, wheels.rotation, wheels.velocity, wheels.angular_velocity]
        self._launch = {
            "place_window": record(
                kernels.place_window, 1, [wheels, int(self._follow), self._centre, soil], [origin, boxes, boxes_before]
            ),
            "enter_window": record(kernels.enter_window, n, [soil, origin, nodes]),
            "release": record(kernels.release, box, [soil, origin, boxes, boxes_before, nodes]),
            "find_contacts": record(kernels.find_contacts, box, [wheels, soil, origin, boxes, nodes]),
            "patch_partial": record(
                kernels.patch_partial, (count, chunks), [wheels, nodes, soil, boxes, n, CHUNK], [self._low, self._high]
            ),
            "patch_width": record(kernels.patch_width, count, [self._low, self._high, chunks, soil], [self._width]),
            "contact_stress": record(
                kernels.contact_stress, box, [wheels, soil, origin, boxes, self._width, hi(0.0), nodes]
            ),
            "mark_rim": record(kernels.mark_rim, n, [soil, origin, nodes]),
            "flow_partial": record(
                kernels.flow_partial, (count, chunks), [nodes, n, CHUNK], [self._flow_part, self._rim_part]
            ),
            "flow_total": record(
                kernels.flow_total,
                count,
                [self._flow_part, self._rim_part, chunks, hi(p.bulldozing_fraction)],
                [self._raise_by],
            ),
            "bulldoze": record(kernels.bulldoze, n, [self._raise_by, nodes]),
            "erode": record(
                kernels.erode,
                n,
                [soil, origin, hi(p.node_spacing * math.tan(math.radians(p.erosion_angle))), nodes],
                [self._reference_next],
            ),
            "wrench_partial": record(
                kernels.wrench_partial,
                (count, chunks),
                [nodes, soil, boxes, n, CHUNK],
                [self._force_part, self._torque_part, self._count_part, self._deepest_part],
            ),
            "wrench_total": record(
                kernels.wrench_total,
                count,
                [self._force_part, self._torque_part, self._count_part, self._deepest_part, chunks],
                [self._totals, self._sums],
            ),
            "pose_now": record(kernels.follow_path, count, [self._path, self._clock, hi(0.0)], pose),
            "pose_next": record(kernels.follow_path, count, [self._path, self._clock, hi(0.0)], pose),
            "tick": record(kernels.tick, 1, [self._clock, hi(0.0)]),
        }
        self._step_length = 0.0

    def _set_step(self, dt: float) -> None:
        """The step length dt [s] of the recorded launches that take it."""
        if dt != self._step_length:
            value = self.precision.hi(dt)
            for name in ("contact_stress", "pose_next", "tick"):
                self._launch[name].set_param_by_name("dt", value)
            self._step_length = dt

    # -- stepping ----------------------------------------------------------------------------
    def step(self, dt: float) -> None:
        """One step of dt [s] with the wheels at their pose at the current time; then the time moves on and
        the wheels follow their path (its clock is on the device). No host read: the launches of a step
        can be captured in a CUDA graph and replayed for a fixed dt (the checks below are on the host)."""
        if not (is_real(dt) and math.isfinite(dt) and dt >= 0):  # 0: the wrench where the wheels stand
            raise SoilInputError(f"dt must be >= 0 [s], got {dt!r}")
        self._check_window(self.time + dt - self._path_start)  # as advance: a wheel out of it pressed nothing
        self._evaluate(dt)
        self._pose(dt)
        self.time += dt

    def _evaluate(self, dt: float) -> None:
        """The step's kernels: contacts, stresses and node updates over dt [s], the wheels' wrenches. The
        wheels' boxes (the nodes under their footprints) are worked; with bulldozing, every node too."""
        launch, p = self._launch, self.parameters
        self._set_step(dt)
        launch["place_window"].launch()
        if p.bulldozing:  # its kernels read every node: every slot must hold its node
            launch["enter_window"].launch()
        for name in ("release", "find_contacts", "patch_partial", "patch_width", "contact_stress"):
            launch[name].launch()
        if p.bulldozing:
            # the soil the patches displaced this step goes to their rims, shared equally
            for name in ("mark_rim", "flow_partial", "flow_total", "bulldoze"):
                launch[name].launch()
            for _ in range(p.erosion_iterations):
                launch["erode"].launch()
                wp.copy(self._nodes.reference, self._reference_next)
        launch["wrench_partial"].launch()
        launch["wrench_total"].launch()
        self.steps += 1
        self._summed_steps += 1

    def advance(
        self,
        end_time: float,
        dt: float,
        position=None,
        orientation=None,
        velocity=None,
        angular_velocity=None,
    ) -> int:
        """Run from the current time to `end_time` [s] in equal steps of at most dt [s]; the wheels start
        from the given kinematics (see set_wheels; None: they go on along their current path). Returns
        the number of steps. `wheel_contact(mean=True)` then gives the means over these steps."""
        if not (is_real(dt) and math.isfinite(dt) and dt > 0):
            raise SoilInputError(f"dt must be > 0 [s], got {dt!r}")
        if not is_real(end_time):  # float() would read a text of digits as a time
            raise SoilInputError(
                f"end_time must be a number [s], after the current time {self.time!r} s, got {end_time!r}"
            )
        span = float(end_time) - self.time
        if not math.isfinite(span) or span <= 0:
            raise SoilInputError(f"end_time must be after the current time {self.time!r} s, got {end_time!r}")
        if position is not None or orientation is not None:
            if position is None or orientation is None:
                raise SoilInputError("advance needs both position and orientation (or neither)")
            self.set_wheels(position, orientation, velocity, angular_velocity)
        self._check_window(float(end_time) - self._path_start)
        if span / dt > MAX_ADVANCE_STEPS:  # a loop on the device that no Ctrl-C ends in a lifetime
            raise SoilInputError(
                f"advance to end_time {end_time!r} s in steps of at most dt = {dt!r} s is {span / dt:.3g} steps, "
                f"more than {MAX_ADVANCE_STEPS:.0e}: a dt far below the span's scale"
            )
        steps = max(1, math.ceil(span / dt - 1e-9))
        step = span / steps
        start = self.time
        self._sums.zero_()
        self._summed_steps = 0
        for k in range(1, steps + 1):
            self._evaluate(step)
            self._pose(step)
            self.time = start + k * step if k < steps else float(end_time)
        return steps

    # -- results -----------------------------------------------------------------------------
    def wheel_contact(self, mean: bool = False) -> WheelContact:
        """The soil's push on each wheel at the last step (mean=True: the mean over the steps of the last
        `advance`; the sinkage is then the mean of the steps' deepest sinkage)."""
        if mean:
            data = self._sums.numpy().astype(np.float64) / max(1, self._summed_steps)
        else:
            data = self._totals.numpy().astype(np.float64)
        return WheelContact(data[:, 0:3].copy(), data[:, 3:6].copy(), data[:, 6].copy(), data[:, 7].copy())

    def patch_width(self) -> np.ndarray:
        """The Bekker width b of each wheel's contact patch at the last step [m], shape (k,) (inf: no contact)."""
        width = self._width.numpy().astype(np.float64)
        return np.where(width > 1e29, np.inf, width)

    def window_origin(self) -> tuple[int, int]:
        """The grid indices (I0, J0) of the window's first node (node (I, J) is at (I h, J h))."""
        origin = self._origin.numpy()
        return int(origin[0]), int(origin[1])

    def _window_nodes(self) -> dict:
        """The per-node state (_NODE_STATE and `wheel`, numpy arrays by slot) of the window's nodes: a slot
        that still holds a node the window left (no wheel's box has reached the slot since) reads as the
        undisturbed soil under NO_KEY, as before any step (a step resets it when a box reaches it)."""
        nodes = self._nodes
        data = {name: getattr(nodes, name).numpy().copy() for name in (*_NODE_STATE, "wheel")}
        (i0, j0), (nx, ny) = self.window_origin(), self.shape
        slot = np.arange(self.node_count)
        stale = (data["key_i"] != i0 + (slot // ny - i0) % nx) | (data["key_j"] != j0 + (slot % ny - j0) % ny)
        data["key_i"][stale] = NO_KEY
        data["key_j"][stale] = NO_KEY
        data["reference"][stale] = self.surface_height
        for name in ("plastic", "shear"):
            data[name][stale] = 0
        data["wheel"][stale] = -1
        return data

    def height_field(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The soil surface in the window: x [m] (nx,), y [m] (ny,), height [m] (nx, ny), in grid order.
        Under a wheel the surface is the wheel's; elsewhere the plastic surface (after elastic rebound).
        Slots that no step has reached yet show the undisturbed surface."""
        nodes = self._window_nodes()
        key_i, key_j = nodes["key_i"], nodes["key_j"]
        surface = nodes["reference"].astype(np.float64) - nodes["plastic"]
        hit = self._nodes.hit.numpy()[:, 2].astype(np.float64)
        surface = np.where(nodes["wheel"] >= 0, np.minimum(surface, hit), surface)
        surface = np.where(key_i == NO_KEY, self.surface_height, surface)
        i0, j0 = self.window_origin()
        nx, ny = self.shape
        field = np.full((nx, ny), self.surface_height)
        seen = key_i != NO_KEY
        field[key_i[seen] - i0, key_j[seen] - j0] = surface[seen]
        h = self.parameters.node_spacing
        return (i0 + np.arange(nx)) * h, (j0 + np.arange(ny)) * h, field

    def surface_height_at(self, x, y) -> np.ndarray:
        """The soil surface's height [m] at world points (x, y) [m] (arrays of one shape), bilinear between
        nodes; the undisturbed height outside the window. Non-finite coordinates are refused (a nan became a
        node index through an invalid cast, with a warning, and read the undisturbed height)."""
        points = []
        for name, value in (("x", x), ("y", y)):
            try:
                array = np.asarray(value)
                ok = array.dtype.kind in "iuf" and bool(np.all(np.isfinite(array)))
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise SoilInputError(f"{name} must be finite numbers [m] (a number or an array), got {value!r}")
            points.append(np.asarray(value, dtype=np.float64))
        try:
            x, y = np.broadcast_arrays(*points)
        except ValueError:
            raise SoilInputError(
                f"x and y must have one shape (or broadcast to one), got shapes {points[0].shape} and {points[1].shape}"
            ) from None
        xs, ys, field = self.height_field()
        h = self.parameters.node_spacing
        u, v = (x - xs[0]) / h, (y - ys[0]) / h
        i, j = np.floor(u).astype(int), np.floor(v).astype(int)
        inside = (i >= 0) & (j >= 0) & (i < len(xs) - 1) & (j < len(ys) - 1)
        i, j = np.clip(i, 0, len(xs) - 2), np.clip(j, 0, len(ys) - 2)
        a, b = u - i, v - j
        value = (
            (1 - a) * (1 - b) * field[i, j]
            + a * (1 - b) * field[i + 1, j]
            + (1 - a) * b * field[i, j + 1]
            + a * b * field[i + 1, j + 1]
        )
        return np.where(inside, value, self.surface_height)

    def memory_bytes(self) -> int:
        """Bytes of the device arrays the terrain holds (fixed at construction: independent of the distance)."""
        arrays = [getattr(self._nodes, name) for name in self.kernels.Nodes.vars]
        arrays += [self._reference_next, self._low, self._high, self._width, self._force_part, self._torque_part]
        arrays += [
            self._flow_part,
            self._rim_part,
            self._raise_by,
            self._count_part,
            self._deepest_part,
            self._totals,
            self._sums,
            self._path,
            self._origin,
            self._boxes,
            self._boxes_before,
            self._clock,
        ]
        return int(sum(a.capacity for a in arrays))

    # -- checkpoints -------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """Everything a resumed run needs to continue bit for bit (numpy arrays and numbers)."""
        nodes = self._window_nodes()
        data = {name: nodes[name] for name in _NODE_STATE}
        data.update(
            version=np.int64(STATE_VERSION),
            shape=np.array(self.shape, dtype=np.int64),
            node_spacing=np.float64(self.parameters.node_spacing),
            precision=np.array(self.precision.name),
            time=np.float64(self.time),
            steps=np.int64(self.steps),
            summed_steps=np.int64(self._summed_steps),
            path=self._path.numpy().copy(),
            path_start=np.float64(self._path_start),
            clock=self._clock.numpy().copy(),
            origin=self._origin.numpy().copy(),
            boxes=self._boxes.numpy().copy(),
            totals=self._totals.numpy().copy(),
            sums=self._sums.numpy().copy(),
            width=self._width.numpy().copy(),
            soil=np.array([float(getattr(self.parameters, name)) for name in _SOIL_STATE], dtype=np.float64),
        )
        return data

    STATE_UNITS = {
        "key_i": "1",  # grid indices of the node a slot holds
        "key_j": "1",
        "reference": "m",  # the node's undisturbed height
        "plastic": "m",  # its plastic sinkage
        "shear": "m",  # the Janosi-Hanamoto shear displacement j
        "version": "1",
        "shape": "count",
        "node_spacing": "m",
        "precision": "text",
        "time": "s",
        "steps": "count",
        "summed_steps": "count",
        "path": "by column: m (3), 1 (4, quaternion), m/s (3), rad/s (3) (PATH_COLUMNS)",
        "path_start": "s",
        "clock": "s",
        "origin": "1",
        "boxes": "1",
        "totals": "by column: N (3), N m (3), count, m (force, torque, contact nodes, sinkage)",
        "sums": "by column: N (3), N m (3), count, m, each summed over summed_steps steps",
        "width": "m",
        "soil": "by entry: Pa m^(1-n), Pa m^(-n), 1, Pa, deg, m, Pa/m, Pa s/m, 1, 1, deg, count (_SOIL_STATE)",
    }
    """The unit of each entry of state_dict()."""

    def state_dict_units(self) -> dict[str, str]:
        """{key of state_dict(): its unit}."""
        return dict(self.STATE_UNITS)

    def load_state_dict(self, data: dict) -> None:
        """Restore a state_dict of a terrain built alike (same parameters, wheels, window, precision)."""
        if int(data.get("version", -1)) != STATE_VERSION:
            raise SoilInputError(f"SCM state version {data.get('version')!r} is not {STATE_VERSION}")
        # every array a restore writes, present and of this terrain's shape, before anything is written (a
        # missing key was a bare KeyError, a wrong shape a half-restored terrain)
        arrays = {name: getattr(self._nodes, name) for name in _NODE_STATE}
        arrays.update(clock=self._clock, origin=self._origin, boxes=self._boxes, totals=self._totals)
        arrays.update(sums=self._sums, width=self._width, path=self._path)
        scalars = ("shape", "precision", "time", "steps", "summed_steps", "path_start")
        missing = [name for name in (*scalars, *arrays) if name not in data]
        if missing:
            raise SoilInputError(
                f"SCM state lacks {', '.join(missing)}: a damaged checkpoint (a terrain's state_dict holds them all)"
            )
        # a state written before it was kept (None) is judged by its window's shape alone
        spacing = float(data["node_spacing"]) if "node_spacing" in data else None
        if spacing is not None and spacing != self.parameters.node_spacing:
            raise SoilInputError(
                f"SCM state is of a grid of node spacing {spacing:.6g} m, this terrain's is "
                f"{self.parameters.node_spacing:.6g} m (set terrain.node_spacing = {spacing!r} to continue it)"
            )
        if tuple(int(s) for s in data["shape"]) != self.shape or str(data["precision"]) != self.precision.name:
            raise SoilInputError(
                f"SCM state is of a {tuple(int(s) for s in data['shape'])} window in {data['precision']} precision, "
                "this terrain's "
                f"is {self.shape} in {self.precision.name} (a window of another shape: another terrain.node_spacing "
                "or window size)"
            )
        if np.asarray(data["path"]).shape != (self.wheel_count, PATH_COLUMNS):
            raise SoilInputError(f"SCM state has {len(data['path'])} wheels, this terrain has {self.wheel_count}")
        wrong = [
            f"{name} {np.shape(data[name])} (this terrain's {tuple(array.shape)})"
            for name, array in arrays.items()
            if np.shape(data[name]) != tuple(array.shape)
        ]
        if wrong:
            raise SoilInputError(f"SCM state's arrays are of other shapes: {', '.join(wrong)}: a damaged checkpoint")
        if "soil" in data:  # a state written before the soil was kept is not judged on it
            kept = np.asarray(data["soil"], dtype=np.float64)
            now = [float(getattr(self.parameters, name)) for name in _SOIL_STATE]
            if kept.shape != (len(_SOIL_STATE),):
                raise SoilInputError(
                    f"SCM state's soil holds {kept.size} values, {len(_SOIL_STATE)} expected: a damaged checkpoint"
                )

            def said(old, new):  # the digits that tell them apart
                return f"{old:.6g} -> {new:.6g}" if f"{old:.6g}" != f"{new:.6g}" else f"{old!r} -> {new!r}"

            # derived values (a default damping from the wheel's Bekker sinkage) may differ in the last bit
            # on another machine's libm: the same soil within 1e-12
            changed = [
                f"{name} {said(old, new)}"
                for name, old, new in zip(_SOIL_STATE, kept, now)
                if not math.isclose(old, new, rel_tol=1e-12, abs_tol=0.0)
            ]
            if changed:
                raise SoilInputError(
                    "SCM state is of another soil than this terrain's ("
                    + ", ".join(changed)
                    + "): its parameters (terrain.calibration's file or the [terrain] keys) changed since the state "
                    "was written; put the run's soil back to continue it"
                )
        for name in _NODE_STATE:
            getattr(self._nodes, name).assign(np.asarray(data[name]))
        # no contact anywhere, as in a terrain just built: the next step writes its boxes' nodes and
        # releases the restored boxes' (a step taken since, e.g. of zero length to read the wrench at
        # a new pose, may have marked contacts outside both)
        self._nodes.wheel.fill_(-1)
        self.time = float(data["time"])
        self.steps = int(data["steps"])
        self._summed_steps = int(data["summed_steps"])
        self._path.assign(np.asarray(data["path"]))
        self._host_path = np.asarray(data["path"], dtype=np.float64)
        self._path_start = float(data["path_start"])
        self._clock.assign(np.asarray(data["clock"]))
        self._origin.assign(np.asarray(data["origin"]))
        self._boxes.assign(np.asarray(data["boxes"]))
        self._totals.assign(np.asarray(data["totals"]))
        self._sums.assign(np.asarray(data["sums"]))
        self._width.assign(np.asarray(data["width"]))
        self._pose(0.0)


def cylinder_of(wheel: GrouserWheel | MeshWheel) -> tuple[float, float]:
    """Radius and half width [m] of the cylinder about the axle (local Y) that holds the wheel."""
    if isinstance(wheel, GrouserWheel):
        return wheel.outer_radius, 0.5 * wheel.width
    return wheel.outer_radius, float(np.abs(wheel.vertices[:, 1]).max())
