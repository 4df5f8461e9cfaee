"""The SCM terrain (soil.scm, the Soil Contact Model) as a SoilSide, and a soil side that routes
each wheel to its own terrain model (CompositeSoil: some wheels on the DEM, the others on SCM).

    soil = ScmSoil(ScmTerrain(parameters, shapes, window=(0.6, 0.4)), time_step=1e-3, rim_radii=[0.1])
    wrenches = soil.advance(t_end, start_kinematics, end_kinematics)

Within a macro step ScmTerrain moves each wheel along a path of constant velocities from its
start pose. Given the end kinematics too, the path is the chord from the start pose to the end
pose (velocity (p1 - p0) / H, the angular velocity that turns q0 into q1 over H): the wheel then
ends the macro step exactly where the rover says it is, as it does on the DEM.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from soil.control import quaternion_integrate, quaternion_multiply, quaternion_to_matrix
from soil.errors import ArgumentError, is_real
from soil.geometry import GrouserWheel
from soil.scm import ScmParameters, ScmTerrain, check_grid

from .contract import (
    Particles,
    SoilBooks,
    SoilSide,
    SoilSideDefaults,
    StepStatistics,
    WheelKinematics,
    WheelWrench,
    advance_soil,
)


def chord_angular_velocity(q0: np.ndarray, q1: np.ndarray, span: float) -> np.ndarray:
    """The constant world-frame angular velocity [rad/s] (3,) that turns unit quaternion q0 into q1
    in `span` [s] (the short way round): quaternion_integrate(q0, result, span) == q1."""
    conjugate = np.array([q0[0], -q0[1], -q0[2], -q0[3]])
    turn = quaternion_multiply(q1, conjugate)  # q1 = turn q0: the rotation in the world frame
    if turn[0] < 0:
        turn = -turn
    sine = float(np.linalg.norm(turn[1:]))
    if sine < 1e-15:
        return np.zeros(3)
    angle = 2.0 * math.atan2(sine, float(turn[0]))
    return turn[1:] / sine * (angle / span)


@dataclass(frozen=True)
class ScmSettings:
    """What the run layer gives an SCM terrain besides the wheels."""

    parameters: ScmParameters
    window: tuple[float, float]
    """The node window's size along world x and y [m]."""
    time_step: float
    """The SCM step [s] (each macro step is split into equal steps of at most this)."""
    surface_height: float = 0.0
    """The undisturbed surface [m]."""


DAMPING_RATIO = 0.2
"""Default pressure damping as a fraction of a wheel's critical elastic damping [-]."""
NODES_ACROSS = 12
"""Default nodes across the narrowest wheel's width [-]."""
NODES_ACROSS_GROUSER = 1.5
"""Default node spacings across the thinnest grouser (its thickness / the spacing) [-]. Each node samples
the wheel with one ray, so a grouser thinner than a spacing falls between nodes at some phases of its
travel and the forces beat at T_g / dist(p / h, nearest integer) (p the grousers' pitch on the ground,
T_g their passage period): on the main job's wheel (2 mm grousers) at h = 1.33 t, DP/W swings by
0.07-0.13 W in beats of 14-31 s and their sidebands, and the sinkage at slips 0.4-0.6 falls 0.5-1 mm
short of a fine grid's; at h = t / 1.5, 0.04 W and 0.1-0.3 mm (BENCHMARKS.md, "SCM's grid against the
grousers"). Mesh wheels are not judged: their grousers, if any, are not known as such."""
BOUNCE_PHASE = 0.2
"""Default coupling step of a scene on SCM alone, as the phase of a wheel's elastic bounce on the
soil it spans, omega_e H [rad]: the main job on its wheel-fitted soil (slip 0.2) gives DP/W within
0.0007 and sinkage and torque within 0.13 % of H = 3.3 ms (the DEM's macro step) at 0.2, within
0.3 % up to 1 rad, DP/W 0.01 and torque 2-3 % off at 2 rad (BENCHMARKS.md, "SCM's own coupling step")."""
STEPS_PER_NODE = 4
"""Default SCM steps per node spacing of the fastest wheel surface's travel (the grouser tips) [-]:
the main job's held wheel gives forces within 0.2 % of 8 steps per node, 1-3 % at 2."""


def bekker_wheel_sinkage(parameters: ScmParameters, load: float, radius: float, width: float) -> float:
    """Bekker's closed-form sinkage [m] of a rigid smooth wheel of `radius` and `width` [m] rolling
    under `load` [N] (the front half of the rim in contact; Wong, Theory of Ground Vehicles):
    z0 = (3 W / ((3 - n) (k_c + b k_phi) sqrt(D)))^(2 / (2 n + 1)).

    This is the rolling form: with only the front half of the rim carrying the load it sinks
    2^(2 / (2 n + 1)) times (about 1.5: 1.59 at n = 1, 1.54 at n = 1.1) the static sinkage of the same
    wheel standing with the whole arc in contact, so it is not a check of a wheel at rest.

    radius and width: finite numbers > 0 [m]; load: a finite number [N] (0 or less: no sinkage).
    """
    for name, value in (("radius", radius), ("width", width)):
        if not (is_real(value) and math.isfinite(value) and value > 0):
            raise ArgumentError(f"{name} must be a finite number > 0 [m], got {value!r}")
    # a lifted wheel (load <= 0, e.g. under a gravity tilted past 90 degrees) sinks nothing
    if not (is_real(load) and math.isfinite(load)):
        raise ArgumentError(f"load must be a finite number [N] (a load <= 0 sinks nothing), got {load!r}")
    p = parameters
    if load <= 0:
        return 0.0
    base = 3.0 * load / ((3.0 - p.n) * (p.k_c + width * p.k_phi) * math.sqrt(2.0 * radius))
    return base ** (2.0 / (2.0 * p.n + 1.0))


def grouser_thickness(wheels) -> float:
    """The thinnest grouser of `wheels` (WheelPlans) [m]; inf without grousers (smooth or mesh wheels)."""
    thicknesses = [
        w.shape.grouser_thickness for w in wheels if isinstance(w.shape, GrouserWheel) and w.shape.grouser_count > 0
    ]
    return min(thicknesses, default=math.inf)


def node_spacing(values: dict, wheels) -> float:
    """[terrain] node_spacing, or the smaller of the narrowest of `wheels` (WheelPlans)' widths / NODES_ACROSS
    and their thinnest grouser / NODES_ACROSS_GROUSER [m]."""
    if "node_spacing" in values:
        return values["node_spacing"]
    return min(min(w.width for w in wheels) / NODES_ACROSS, grouser_thickness(wheels) / NODES_ACROSS_GROUSER)


def elastic_bounce(parameters: ScmParameters, wheel, load: float, g: float) -> tuple[float, float]:
    """(omega_e [rad/s], A [m^2]): the angular frequency of a wheel (a WheelPlan) bouncing on the
    soil's elastic stiffness K_e under `load` [N], omega_e = sqrt(K_e A / m) with m = load / |g| and A
    its width times the contact length at Bekker's sinkage (at least two node spacings); 0 without a load."""
    sinkage = bekker_wheel_sinkage(parameters, load, wheel.outer_radius, wheel.width)
    length = 2.0 * math.sqrt(max(2.0 * wheel.outer_radius * sinkage, parameters.node_spacing**2))
    area = wheel.width * length
    return (math.sqrt(parameters.elastic_stiffness * area * g / load) if load > 0 else 0.0), area


def scm_macro_step(values: dict, wheels, load: float, g: float, rim_speed: float) -> float:
    """A scene on SCM alone: its own coupling step [s] (no grain time scale bounds it), the smaller of
    BOUNCE_PHASE / omega_e (`elastic_bounce` of each of `wheels`, WheelPlans, under `load` [N] at
    |g| = `g` [m/s^2]) and a node spacing / (STEPS_PER_NODE x `rim_speed` [m/s], the fastest wheel
    surface's speed); nan where either is unknown (no gravity, no load, no speed: keep the DEM's)."""
    if not (g > 0 and load > 0 and rim_speed > 0 and math.isfinite(load * rim_speed)):
        return math.nan
    parameters = scm_parameters({"pressure_damping": 0.0, **values, "node_spacing": node_spacing(values, wheels)})
    bounce = max(elastic_bounce(parameters, wheel, load, g)[0] for wheel in wheels)
    return min(BOUNCE_PHASE / bounce, parameters.node_spacing / (STEPS_PER_NODE * rim_speed))


def scm_parameters(values: dict) -> ScmParameters:
    """ScmParameters from [terrain] keys (scene.SCM_KEYS; the angles in degrees, the grid's spacing given)."""
    optional = {
        "pressure_damping": "damping",
        "bulldozing": "bulldozing",
        "bulldozing_fraction": "bulldozing_fraction",
        "erosion_angle_deg": "erosion_angle",
        "erosion_iterations": "erosion_iterations",
    }
    return ScmParameters(
        k_c=values["k_c"],
        k_phi=values["k_phi"],
        n=values["n"],
        cohesion=values["cohesion"],
        friction_angle=values["friction_angle_deg"],
        janosi_k=values["janosi_k"],
        elastic_stiffness=values["elastic_stiffness"],
        node_spacing=values["node_spacing"],
        **{name: values[key] for key, name in optional.items() if key in values},
    )


def scm_steps(plan) -> tuple[float, int]:
    """(step [s], steps per macro step) of SCM in a run plan: each macro step in equal steps of at most
    [terrain] time_step (default: the macro step), as soil.scm.ScmTerrain.advance splits it."""
    longest = float(dict(plan.terrain.parameters).get("time_step", plan.macro_step))
    steps = max(1, math.ceil(plan.macro_step / longest - 1e-9))
    return plan.macro_step / steps, steps


def scm_settings(plan, wheels: Sequence[int], surface_height: float, soil: dict | None = None) -> ScmSettings:
    """The SCM terrain of a run plan's wheels `wheels` (indices; cosim.plan.RunPlan) from its [terrain]
    keys (`soil`: SOIL_KEYS values that replace the plan's, as a calibration trying parameters does),
    with the defaults of the keys not given:

    - node_spacing: the narrowest wheel's width / NODES_ACROSS, or the thinnest grouser / NODES_ACROSS_GROUSER
      where that is finer;
    - window: the wheels' hub span (a rover's hubs at any heading: twice their largest distance from
      the rover's centre) plus 8 outer radii along x and 4 outer radii and a wheel width along y;
    - time_step: the macro step;
    - pressure_damping: DAMPING_RATIO of critical for a wheel's elastic bounce: R = 2 zeta sqrt(K_e m / A),
      with m the wheel's load over |g| and A its width times the contact length at Bekker's sinkage (on
      the far softer Bekker branch the same R is near critical: the wheel sinks without bouncing).
    """
    values = {**dict(plan.terrain.parameters), **(soil or {})}
    chosen = [plan.wheels[i] for i in wheels]
    values["node_spacing"] = node_spacing(values, chosen)
    outer = max(w.outer_radius for w in chosen)
    width = max(w.width for w in chosen)
    span = hub_span(plan, wheels)
    window = (values.pop("window_length", span + 8 * outer), values.pop("window_width", span + width + 4 * outer))
    time_step = values.pop("time_step", plan.macro_step)
    if "pressure_damping" not in values:
        values["pressure_damping"] = 0.0
        parameters = scm_parameters(values)
        if plan.g > 0:
            _, area = elastic_bounce(parameters, chosen[0], plan.wheel_load, plan.g)
            mass = plan.wheel_load / plan.g
            values["pressure_damping"] = 2.0 * DAMPING_RATIO * math.sqrt(parameters.elastic_stiffness * mass / area)
    values.pop("surface_height", None)
    return ScmSettings(scm_parameters(values), (float(window[0]), float(window[1])), float(time_step), surface_height)


def scm_wheel_indices(plan) -> list[int]:
    """The indices of the plan's wheels on SCM (every wheel on an SCM terrain, terrain.wheels' "scm"
    ones on a mixed one; none on another terrain)."""
    if plan.terrain.model not in ("scm", "mixed"):
        return []
    models = plan.terrain.wheel_models
    return [i for i in range(len(plan.wheels)) if not models or models[i] == "scm"]


def hub_span(plan, indices) -> float:
    """Twice the largest distance of the wheels `indices`' hubs from a rover's centre [m] (their span at
    any heading); 0 for the testbed's one wheel."""
    if plan.rover is None:
        return 0.0
    return 2.0 * float(np.max(np.hypot(*plan.rover.hub_offsets[list(indices), :2].T)))


def _check_window_holds_wheels(plan, indices: list[int], settings: ScmSettings) -> None:
    """SceneError naming terrain.window_length or window_width when the node window, centred on the wheels
    (to a node), cannot hold their footprints as ScmTerrain checks them at each step: a rover's at any
    heading (its hubs' span plus each footprint's largest reach, soil.scm.terrain.cylinder_of), the
    testbed's wheel with its axle along y (its outer radius along x, its half width along y)."""
    from soil.scm.terrain import cylinder_of, grid_shape, window_reach

    from .scene import SceneError

    spacing = settings.parameters.node_spacing
    span = hub_span(plan, indices)
    if plan.rover is not None:
        reach = max(math.hypot(*cylinder_of(plan.wheels[i].shape)) for i in indices)
        reaches, heading = (reach, reach), " at any heading"
    else:
        reaches, heading = cylinder_of(plan.wheel.shape), ""
    problems = []
    shape = grid_shape(settings.window, spacing)
    for key, size, nodes, reach in zip(("window_length", "window_width"), settings.window, shape, reaches):
        if window_reach(nodes, spacing) < 0.5 * span + reach:
            least = (2 * math.ceil((0.5 * span + reach) / spacing) + 4) * spacing  # an even count holds it
            problems.append(
                f"terrain.{key}: the SCM window ({size:.4g} m, {nodes} nodes of {spacing:.3g} m) must hold the "
                f"wheels' footprints{heading} (hub span {span:.4g} m, reach {reach:.4g} m each side); "
                f"allowed: >= {least:.4g} m"
            )
    if problems:
        raise SceneError(problems)


def check_scm_grid(plan, reserved: tuple[int, int] = (0, 0), memory: bool = True) -> None:
    """Refuse, before anything is allocated or written, the SCM grid of a plan's SCM wheels when Warp
    cannot index it or (with `memory`) this machine cannot hold it beside `reserved` (device, host)
    bytes [B] the run's grains take, if any (soil.scm.check_grid), naming the keys that size it.
    Without `memory`: the grid is allocated elsewhere (an exported FMU's server checks it there)."""
    indices = scm_wheel_indices(plan)
    if not indices:
        return
    settings = scm_settings(plan, indices, 0.0)
    spacing, (length, width) = settings.parameters.node_spacing, settings.window
    check_grid(
        settings.window,
        spacing,
        plan.precision,
        plan.device,
        what=f"scene {plan.name!r}: the SCM grid of window {length:.4g} x {width:.4g} m at spacing {spacing:.3g} m",
        keys=("terrain.node_spacing", "terrain.window_length, terrain.window_width"),
        reserved=reserved,
        memory=memory,
    )
    _check_window_holds_wheels(plan, indices, settings)  # after: a grid past counting is named by its keys there


class ScmSoil(SoilSideDefaults):
    """SoilSide over a soil.scm.ScmTerrain: one terrain for all its wheels (their patches may share
    nodes: the lowest surface presses a node), a window of nodes following their mean hub.

    Args:
        terrain: the SCM terrain with the wheels' shapes, in wheel order.
        time_step: the SCM step [s].
        rim_radii: each wheel's rim radius [m] (the sinkage is the rim bottom's depth below the
            undisturbed surface, as on the DEM).
    """

    def __init__(self, terrain: ScmTerrain, time_step: float, rim_radii: Sequence[float]):
        if not isinstance(terrain, ScmTerrain):  # read for its wheel count below: say which argument it is
            raise ArgumentError(f"terrain must be a soil.scm.ScmTerrain, got {type(terrain).__name__}: {terrain!r}")
        if not is_real(time_step):
            raise ArgumentError(f"time_step must be a number > 0 [s], got {time_step!r}")
        if not (math.isfinite(time_step) and time_step > 0):
            raise ArgumentError(f"time_step must be > 0 [s], got {time_step!r}")
        if isinstance(rim_radii, (str, bytes)) or not hasattr(rim_radii, "__len__"):
            raise ArgumentError(f"rim_radii must be a sequence of rim radii > 0 [m], one per wheel, got {rim_radii!r}")
        if len(rim_radii) != terrain.wheel_count:
            raise ArgumentError(f"rim_radii: {len(rim_radii)} radii for {terrain.wheel_count} wheels")
        if not all(is_real(r) and math.isfinite(r) and r > 0 for r in rim_radii):
            raise ArgumentError(f"rim_radii must be rim radii > 0 [m], got {list(rim_radii)!r}")  # sinkage's datum
        self.terrain = terrain
        self.time_step = float(time_step)
        self.wheel_count = terrain.wheel_count
        self.rim_radii = np.asarray(rim_radii, dtype=np.float64)
        """Each wheel's rim radius, the reference of its sinkage [m], shape (wheel_count,)."""
        self.gravity = np.zeros(3)
        """The scene's gravity vector [m/s^2], shape (3,) (set_gravity)."""
        self._steps = 0
        self._step = 0.0
        count = self.wheel_count
        self._position = np.zeros((count, 3))
        self._orientation = np.tile([1.0, 0.0, 0.0, 0.0], (count, 1))

    @classmethod
    def build(cls, settings: ScmSettings, shapes, rim_radii, device: str = "cpu", precision: str = "double"):
        """An ScmSoil of these wheel shapes (soil.geometry GrouserWheel / MeshWheel) on `settings`."""
        terrain = ScmTerrain(
            settings.parameters,
            list(shapes),
            window=settings.window,
            surface_height=settings.surface_height,
            device=device,
            precision=precision,
        )
        return cls(terrain, settings.time_step, rim_radii)

    @property
    def time(self) -> float:
        return self.terrain.time

    @property
    def surface_height(self) -> float:
        return self.terrain.surface_height

    def set_gravity(self, gravity: Sequence[float]) -> None:
        """SoilSide: kept for the record only: SCM's pressure-sinkage law holds the gravity it was
        calibrated at (cosim.scm_calibration warns when that is another one)."""
        self.gravity = np.asarray(gravity, dtype=np.float64).reshape(3).copy()

    @staticmethod
    def _stack(kinematics: Sequence[WheelKinematics]):
        return tuple(
            np.array([getattr(k, name) for k in kinematics], dtype=np.float64)
            for name in ("position", "orientation", "linear_velocity", "angular_velocity")
        )

    def place_wheels(self, kinematics: Sequence[WheelKinematics]) -> None:
        """SoilSide: the wheels at these poses (the start of a constant-velocity path), not advanced."""
        position, orientation, velocity, spin = self._stack(kinematics)
        self.terrain.set_wheels(position, orientation, velocity, spin)
        self._position, self._orientation = position, orientation / np.linalg.norm(orientation, axis=1)[:, None]

    def advance(
        self,
        t_end: float,
        start: Sequence[WheelKinematics],
        end: Sequence[WheelKinematics] | None = None,
        meanwhile: Callable[[], None] | None = None,
    ) -> list[WheelWrench]:
        """SoilSide: SCM steps of at most time_step to t_end [s], the wheels on the chord from `start`
        to `end` (or on `start`'s constant velocities); the mean wrench over the steps and the last.
        meanwhile (SoilSide.advance): called once the steps are launched, before their wrench is read."""
        if len(start) != self.wheel_count or (end is not None and len(end) != self.wheel_count):
            raise ArgumentError(f"expected kinematics of {self.wheel_count} wheels")
        span = float(t_end) - self.time
        if not span > 0:
            raise ArgumentError(f"t_end {t_end!r} s must be after the soil's time {self.time!r} s")
        position, orientation, velocity, spin = self._stack(start)
        orientation = orientation / np.linalg.norm(orientation, axis=1)[:, None]
        if end is not None:
            position_end, orientation_end, _, _ = self._stack(end)
            velocity = (position_end - position) / span
            spin = np.array([chord_angular_velocity(q0, q1, span) for q0, q1 in zip(orientation, orientation_end)])
        steps = self.terrain.advance(t_end, self.time_step, position, orientation, velocity, spin)
        self._steps, self._step = steps, span / steps
        self._position = position + velocity * span
        self._orientation = np.array([quaternion_integrate(q, w, span) for q, w in zip(orientation, spin)])
        if meanwhile is not None:
            meanwhile()
        mean = self.terrain.wheel_contact(mean=True)
        last = self.terrain.wheel_contact(mean=False)
        # the work the wheels did on the soil: the mean wrench against the path's (constant) velocities
        work = -(np.einsum("ij,ij->i", mean.force, velocity) + np.einsum("ij,ij->i", mean.torque, spin)) * span
        return [
            WheelWrench(
                force=mean.force[b],
                torque=mean.torque[b],
                force_end=last.force[b],
                torque_end=last.torque[b],
                contact_count=int(last.contacts[b]),
                sinkage=self._sinkage(b),
                work_on_soil=float(work[b]),
            )
            for b in range(self.wheel_count)
        ]

    def current_wrenches(self) -> list[WheelWrench]:
        """The wrench on every wheel at its pose now (e.g. after place_wheels), the soil left as it is:
        the wrench of an SCM step of zero length (the nodes the wheels reach now, at their sinkage,
        plastic state and shear displacement), taken on the terrain and then undone by restoring its
        state (state_dict). As DemSoil.current_wrenches: the mean and end wrench alike, no work."""
        kept = self.state_dict()
        self.terrain.step(0.0)
        now = self.terrain.wheel_contact(mean=False)
        self.load_state_dict(kept)
        return [
            WheelWrench(
                force=now.force[b],
                torque=now.torque[b],
                force_end=now.force[b].copy(),
                torque_end=now.torque[b].copy(),
                contact_count=int(now.contacts[b]),
                sinkage=self._sinkage(b),
                work_on_soil=0.0,
            )
            for b in range(self.wheel_count)
        ]

    def _sinkage(self, wheel: int) -> float:
        """Depth of the wheel's rim bottom below the undisturbed surface [m] (as DemSoil's)."""
        return self.surface_height - float(self._position[wheel, 2] - self.rim_radii[wheel])

    def wheel_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """SoilSide: hub positions [m] (W, 3) and rotations (W, 3, 3) where the last advance left them."""
        return self._position.copy(), np.array([quaternion_to_matrix(q) for q in self._orientation])

    def highest_point_under(self, wheel: int, hub: ArrayLike, axle: ArrayLike = (0.0, 1.0, 0.0)) -> float:
        """SoilSide: the highest node of the height field inside the wheel's footprint (its outer
        radius along the ground, its width along the axle); the undisturbed surface outside the window."""
        if not 0 <= wheel < self.terrain.wheel_count:
            raise ArgumentError(f"wheel must be in [0, {self.terrain.wheel_count}), got {wheel!r}")
        shape = self.terrain.wheels[wheel]
        reach = shape.outer_radius
        half_width = 0.5 * shape.width if isinstance(shape, GrouserWheel) else float(np.abs(shape.vertices[:, 1]).max())
        a = np.asarray(axle, dtype=np.float64)
        across = a[:2] / np.hypot(a[0], a[1])
        along = np.array([across[1], -across[0]])
        xs, ys, field = self.terrain.height_field()
        x, y = np.meshgrid(xs, ys, indexing="ij")
        centre = np.asarray(hub, dtype=np.float64)
        offset = np.stack([x - centre[0], y - centre[1]], axis=-1)
        inside = (np.abs(offset @ along) <= reach) & (np.abs(offset @ across) <= half_width)
        return float(field[inside].max()) if inside.any() else self.surface_height

    def books(self) -> SoilBooks:
        """SoilSide: no grains (a continuum: its nodes are no mass of soil simulated)."""
        return SoilBooks(element_count=0, mass=0.0)

    def step_statistics(self) -> StepStatistics | None:
        """SoilSide: the SCM steps of the last advance (all equal, none rejected)."""
        if not self._steps:
            return None
        return StepStatistics(self._steps, 0, self._step, self._step, self._steps)

    def state_dict(self) -> dict:
        """SoilSide: the terrain's state under 'scm/' and the wheels' last poses."""
        data = {f"scm/{k}": v for k, v in self.terrain.state_dict().items()}
        data.update(
            position=self._position.copy(),
            orientation=self._orientation.copy(),
            gravity=self.gravity.copy(),
            last_steps=np.int64(self._steps),
            last_step=np.float64(self._step),
        )
        return data

    def state_dict_units(self) -> dict[str, str]:
        """SoilSide: {key of state_dict(): its unit}."""
        units = {f"scm/{k}": v for k, v in self.terrain.state_dict_units().items()}
        units.update(position="m", orientation="1", gravity="m/s^2", last_steps="count", last_step="s")
        return units

    def load_state_dict(self, data: dict) -> None:
        """SoilSide: continue from state_dict() output (into an ScmSoil built from the same scene)."""
        self.terrain.load_state_dict({k[len("scm/") :]: v for k, v in data.items() if k.startswith("scm/")})
        self._position = np.asarray(data["position"], dtype=np.float64).copy()
        self._orientation = np.asarray(data["orientation"], dtype=np.float64).copy()
        self.gravity = np.asarray(data["gravity"], dtype=np.float64).copy()
        self._steps, self._step = int(data["last_steps"]), float(data["last_step"])


class CompositeSoil(SoilSideDefaults):
    """A SoilSide that routes each wheel to one of several soil sides (e.g. one wheel on the DEM, the
    others on SCM): `parts` is [(soil, wheel indices)], every wheel in exactly one part, each part's
    wheels in the order of its own wheel arrays.

    The surface height is the first part's (the builder puts every part's surface there); the
    grains, walls, health checks and inner-step statistics are those of the first part that has
    them (the DEM part), the books the sum of the parts'.
    """

    def __init__(self, parts: Sequence[tuple[SoilSide, Sequence[int]]]):
        indices = sorted(i for _, wheels in parts for i in wheels)
        if indices != list(range(len(indices))) or not indices:
            raise ArgumentError(f"the parts must hold every wheel 0..W-1 once, got {indices}")
        for soil, wheels in parts:
            if soil.wheel_count != len(wheels):
                raise ArgumentError(f"a part of {soil.wheel_count} wheels is given {len(wheels)} wheel indices")
        self.parts = [(soil, list(wheels)) for soil, wheels in parts]
        self.wheel_count = len(indices)
        self._owner = {
            wheel: (k, local) for k, (_, wheels) in enumerate(self.parts) for local, wheel in enumerate(wheels)
        }

    def soil_of(self, wheel: int) -> SoilSide:
        """The soil side that wheel `wheel` runs on."""
        return self.parts[self._owner[wheel][0]][0]

    @property
    def time(self) -> float:
        return self.parts[0][0].time

    @property
    def surface_height(self) -> float:
        return self.parts[0][0].surface_height

    def set_gravity(self, gravity: Sequence[float]) -> None:
        for soil, _ in self.parts:
            soil.set_gravity(gravity)

    def place_wheels(self, kinematics: Sequence[WheelKinematics]) -> None:
        for soil, wheels in self.parts:
            soil.place_wheels([kinematics[i] for i in wheels])

    def advance(
        self,
        t_end: float,
        start: Sequence[WheelKinematics],
        end: Sequence[WheelKinematics] | None = None,
        meanwhile: Callable[[], None] | None = None,
    ) -> list[WheelWrench]:
        out: list[WheelWrench | None] = [None] * self.wheel_count
        for k, (soil, wheels) in enumerate(self.parts):
            wrenches = advance_soil(  # the caller's work while the first part computes
                soil,
                t_end,
                [start[i] for i in wheels],
                None if end is None else [end[i] for i in wheels],
                meanwhile if k == 0 else None,
            )
            for i, wrench in zip(wheels, wrenches):
                out[i] = wrench
        return [w for w in out if w is not None]

    def wheel_poses(self) -> tuple[np.ndarray, np.ndarray]:
        position, rotation = np.zeros((self.wheel_count, 3)), np.zeros((self.wheel_count, 3, 3))
        for soil, wheels in self.parts:
            p, r = soil.wheel_poses()
            position[wheels], rotation[wheels] = p, r
        return position, rotation

    def highest_point_under(self, wheel: int, hub: ArrayLike, axle: ArrayLike = (0.0, 1.0, 0.0)) -> float:
        part, local = self._owner[wheel]
        return self.parts[part][0].highest_point_under(local, hub, axle)

    def books(self) -> SoilBooks:
        books = [soil.books() for soil, _ in self.parts]
        moving = next((b for b in books if b.moving), None)
        if moving is not None:
            return moving
        return SoilBooks(
            element_count=sum(b.element_count for b in books),
            mass=sum(b.mass for b in books),
            mass_initial=sum(b.mass_initial for b in books),
        )

    def _first(self, name: str):
        for soil, _ in self.parts:
            value = getattr(soil, name)()
            if value is not None:
                return value
        return None

    def step_statistics(self) -> StepStatistics | None:
        return self._first("step_statistics")

    def start_health_checks(self) -> None:
        for soil, _ in self.parts:
            soil.start_health_checks()

    def check_health(self) -> None:
        for soil, _ in self.parts:
            soil.check_health()

    def walls(self) -> dict | None:
        return self._first("walls")

    def wall_loads(self) -> dict | None:
        return self._first("wall_loads")

    def particles(self) -> Particles | None:
        return self._first("particles")

    def state_dict(self) -> dict:
        """Each part's state under 'part{k}/'."""
        return {f"part{k}/{key}": v for k, (soil, _) in enumerate(self.parts) for key, v in soil.state_dict().items()}

    def state_dict_units(self) -> dict[str, str]:
        """Each part's units under 'part{k}/'."""
        parts = enumerate(self.parts)
        return {f"part{k}/{key}": v for k, (soil, _) in parts for key, v in soil.state_dict_units().items()}

    def load_state_dict(self, data: dict) -> None:
        for k, (soil, _) in enumerate(self.parts):
            head = f"part{k}/"
            soil.load_state_dict({key[len(head) :]: v for key, v in data.items() if key.startswith(head)})
