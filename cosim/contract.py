"""The soil <-> rover coupling contract (docs/coupling.md, "The contract").

Per wheel, world frame, Z up, SI units. The rover side hands the soil side the hub
kinematics of every wheel; the soil side answers with the wrench on every wheel.
Both sides implement a small protocol so that any soil (DEM, analytic test terrain,
an FMU) can be coupled to any rover (MuJoCo, FMU).

`SoilSide` is also everything the run layer (coupler, runner, records, results writer,
metrics, studies) knows of a soil: a terrain model is added by implementing it (and
registering its builder in cosim.system). Its optional capabilities (walls, particles,
health checks, inner-step statistics) have a defined "absent" answer; `SoilSideDefaults`
gives them all, so a terrain without walls or particles writes only what it has.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from soil.errors import ArgumentError, RegolithError


def _vec(value, size: int, name: str) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64).reshape(-1)
    if array.shape != (size,) or not np.all(np.isfinite(array)):
        raise ArgumentError(f"{name} must be {size} finite numbers, got {value!r}")
    return array


@dataclass
class WheelKinematics:
    """Hub kinematics of one wheel at one instant (rover -> soil)."""

    position: np.ndarray
    """Hub position in the world frame [m], shape (3,)."""
    orientation: np.ndarray
    """Unit quaternion (w, x, y, z), body -> world [-], shape (4,)."""
    linear_velocity: np.ndarray
    """Velocity of the hub point in the world frame [m/s], shape (3,)."""
    angular_velocity: np.ndarray
    """Angular velocity in the world frame [rad/s], shape (3,)."""

    def __post_init__(self):
        self.position = _vec(self.position, 3, "position")
        self.orientation = _vec(self.orientation, 4, "orientation")
        norm = np.linalg.norm(self.orientation)
        if not 0.5 < norm < 2.0:
            raise ArgumentError(f"orientation must be a unit quaternion (w, x, y, z), got {self.orientation}")
        self.orientation = self.orientation / norm
        self.linear_velocity = _vec(self.linear_velocity, 3, "linear_velocity")
        self.angular_velocity = _vec(self.angular_velocity, 3, "angular_velocity")


@dataclass
class WheelWrench:
    """Soil wrench on one wheel over one macro step (soil -> rover)."""

    force: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Macro-step average force on the wheel, world frame [N], shape (3,)."""
    torque: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Macro-step average torque about the hub, world frame [N m], shape (3,)."""
    force_end: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Force at the end of the macro step, world frame [N], shape (3,)."""
    torque_end: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Torque about the hub at the end of the macro step, world frame [N m], shape (3,)."""
    contact_count: int = 0
    """Number of soil contacts on the wheel at the end of the step [-]."""
    sinkage: float = 0.0
    """Depth of the wheel's lowest point below the undisturbed soil surface [m]."""
    work_on_soil: float = 0.0
    """Work done by the wheel on the soil during the macro step [J]."""

    def __post_init__(self):
        # shapes and types only: a soil's non-finite wrench is a divergence, judged where it is made
        for name in ("force", "torque", "force_end", "torque_end"):
            try:
                vector = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            except (TypeError, ValueError):
                vector = np.zeros(0)
            if vector.shape != (3,):
                raise ArgumentError(f"WheelWrench.{name} must be 3 numbers, got {getattr(self, name)!r}")
            setattr(self, name, vector)


WRENCH_UNITS = {
    "force": "N",
    "torque": "N m",
    "force_end": "N",
    "torque_end": "N m",
    "contact_count": "count",
    "sinkage": "m",
    "work_on_soil": "J",
}
"""The unit of each field of WheelWrench."""


def wheel_frame(orientation: ArrayLike, axis_local: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Spin axis and rolling (forward) direction of a wheel in the world frame.

    orientation: unit quaternion (w, x, y, z), body -> world, shape (4,); axis_local: the spin
    axis in the wheel body frame, shape (3,). Returns (axis, forward), unit vectors, shape (3,)
    each. forward = axis x z_up, so a positive spin about the axis rolls the wheel forward. A
    wheel lying flat (axis near vertical) has no rolling direction; forward is then the zero vector.

    The contract's wheel-frame convention, so it lives here; the quaternion maths is soil's
    (soil.control), imported when first needed: `import cosim` and the rover models that use
    this module pull in numpy only.
    """
    from soil.control import quaternion_to_matrix

    axis = quaternion_to_matrix(orientation) @ np.asarray(axis_local, dtype=np.float64)
    x, y, z = axis
    # axis x _UP written out (np.cross's products and differences: the same bits, without its overhead)
    forward = np.array([y * _UP[2] - z * _UP[1], z * _UP[0] - x * _UP[2], x * _UP[1] - y * _UP[0]])
    norm = np.linalg.norm(forward)
    return axis, (forward / norm if norm > 1e-9 else np.zeros(3))


_UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class StepStatistics:
    """How a soil's own inner steps went over its last `advance` (a DEM: its DEM steps)."""

    steps: int
    """Inner steps taken (PID step control: the accepted substeps) [count]."""
    rejected: int
    """Inner steps computed and thrown away (PID step control) [count]."""
    dt_min: float
    """Shortest inner step [s]."""
    dt_max: float
    """Longest inner step [s]."""
    evaluations: int
    """Force evaluations, rejected steps included [count]."""
    forced: int = 0
    """Inner steps kept at the shortest step allowed although their error exceeded the tolerance (PID
    step control) [count]."""


@dataclass(frozen=True)
class SoilBooks:
    """A soil's bookkeeping at one instant (results.h5 /soil and the run summary)."""

    element_count: int
    """Elements simulated: grains of a DEM, cells or nodes of a continuum, 0 for an analytic
    terrain [count]. Throughput is reported per element step."""
    mass: float
    """Mass of the soil simulated [kg] (0 for an analytic terrain)."""
    mass_initial: float = 0.0
    """The mass at the start of the run [kg] (a moving domain: it changes)."""
    mass_added: float = 0.0
    """Soil placed ahead by a moving domain so far [kg]."""
    mass_removed: float = 0.0
    """Soil removed behind a moving domain so far [kg]."""
    moves: int = 0
    """How often a moving domain moved so far [count]."""
    moving: bool = False
    """The soil domain follows the rover (a DEM's moving patch): the summary reports its books."""


@dataclass(frozen=True)
class Particles:
    """The soil's particles at one instant (results.h5 /particles), N particles."""

    position: np.ndarray
    """Centres, world frame [m], shape (N, 3), float64."""
    velocity: np.ndarray
    """Velocities, world frame [m/s], shape (N, 3)."""
    radius: np.ndarray
    """Radii [m], shape (N,)."""
    ids: np.ndarray | None = None
    """Particle ids unique over the run [-], shape (N,), when particles come and go (a moving patch;
    the file's ragged layout); None when the particles are the same all run (the fixed layout)."""


WALL_NAMES = ("kind", "geometry", "report")
"""Keys of `SoilSide.walls()`: 'kind' (B,) int (0 plane: point, unit normal; 1 box: lower, upper
corner), 'geometry' (B, 6) [m] as built, 'report' (B,) int (1: the wall's force is summed)."""

WALL_LOAD_NAMES = ("force", "torque", "contact_count", "displacement")
"""Keys of `SoilSide.wall_loads()`: 'force' (B, 3) [N] of the soil on each wall, 'torque' (B, 3)
[N m] about the wall's reference point, 'contact_count' (B,) [count], 'displacement' (B, 3) [m]
of each wall from its place at the start; at the end of the last macro step."""


@runtime_checkable
class SoilSide(Protocol):
    """Anything that answers wheel kinematics with wheel wrenches, and what the run layer reads of it.

    W = wheel_count, wheels in the rover's wheel order; world frame, Z up, SI units. The
    required members are the coupling itself (`time`, `set_gravity`, `advance`), the ground's
    height, the wheels' poses and a checkpoint; the optional ones (SoilSideDefaults gives
    their absent answer) are walls, particles, health checks and inner-step statistics.
    """

    wheel_count: int

    @property
    def time(self) -> float:
        """The soil's time [s] (read only: `advance` moves it)."""

    @property
    def surface_height(self) -> float:
        """Height z of the undisturbed soil surface [m]: the reference of sinkage."""

    def set_gravity(self, gravity: Sequence[float]) -> None:
        """Set the scene's gravity vector [m/s^2], shape (3,)."""

    def advance(
        self,
        t_end: float,
        start: Sequence[WheelKinematics],
        end: Sequence[WheelKinematics] | None = None,
    ) -> list[WheelWrench]:
        """Advance the soil to t_end [s].

        The wheels move from `start` (kinematics at self.time) to `end` (kinematics at
        t_end) by interpolation; with `end` None the motion is extrapolated from `start`
        at constant velocity. Returns one WheelWrench per wheel.

        Optional keyword `meanwhile` (a callable without arguments, or None): the caller's own
        host work, which a soil that computes on a device calls once after it has launched the
        step and before it waits for the result, so that the two overlap (cosim.dem_soil.DemSoil,
        cosim.scm_soil.ScmSoil). The callable neither touches the soil nor raises. A soil whose `advance` has no such
        keyword is driven as well: the coupler then does that work after `advance`.
        """

    def place_wheels(self, kinematics: Sequence[WheelKinematics]) -> None:
        """Put the wheels at these poses without advancing (before the first macro step)."""

    def wheel_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """The wheels' poses as the soil last moved them: hub positions [m] (W, 3) and rotations
        body -> world (W, 3, 3) (the display mesh of results.h5 is posed with them)."""

    def highest_point_under(self, wheel: int, hub: ArrayLike, axle: ArrayLike = (0.0, 1.0, 0.0)) -> float:
        """Top z [m] of the soil inside the wheel's horizontal footprint when its hub is at `hub` (3,)
        and its axle along `axle` (a horizontal unit vector, world); -inf where there is none. A wheel
        placed at this + its outer radius starts just touching the soil."""

    def books(self) -> SoilBooks:
        """The soil's bookkeeping now."""

    def state_dict(self) -> dict:
        """Everything needed to continue bit for bit, as numpy arrays and scalars (a checkpoint)."""

    def load_state_dict(self, data: dict) -> None:
        """Continue from `state_dict()` output (into a soil built from the same scene)."""

    # -- optional capabilities: SoilSideDefaults answers "absent" ---------------------------

    def state_dict_units(self) -> dict[str, str]:
        """{key of state_dict(): its unit} (SI; "1" for flags and indices, "count" for counts, "text"
        for names), written with a checkpoint; {} where the soil does not say (its entries then go
        without a unit)."""

    def step_statistics(self) -> StepStatistics | None:
        """How the inner steps of the last `advance` went; None before the first one, or for a
        soil without inner steps."""

    def start_health_checks(self) -> None:
        """Before the run's first macro step: take what later `check_health` calls compare with
        (a soil restored from a checkpoint keeps what its checkpoint took)."""

    def check_health(self) -> None:
        """Check that the soil has not diverged; raise soil.SimulationDiverged (with its last good
        state, where kept) when it has. The runner calls it every few macro steps and at checkpoints."""

    def walls(self) -> dict | None:
        """The soil container's walls as built (keys WALL_NAMES); None for a soil without walls."""

    def wall_loads(self) -> dict | None:
        """The walls' loads now (keys WALL_LOAD_NAMES); None for a soil without walls."""

    def particles(self) -> Particles | None:
        """The particles now (results.h5 snapshots); None for a soil without particles (a continuum)."""


def advance_soil(
    soil: SoilSide,
    t_end: float,
    start: Sequence[WheelKinematics],
    end: Sequence[WheelKinematics] | None = None,
    meanwhile: Callable[[], None] | None = None,
) -> list[WheelWrench]:
    """`soil.advance(t_end, start, end)` with the caller's `meanwhile` (a callable, or None) done while
    the soil computes when its `advance` takes that keyword (SoilSide.advance), else after it."""
    if meanwhile is None:
        return soil.advance(t_end, start, end)
    if _takes_meanwhile(soil.advance):
        return soil.advance(t_end, start, end, meanwhile=meanwhile)  # type: ignore[call-arg]
    wrenches = soil.advance(t_end, start, end)
    meanwhile()
    return wrenches


def _takes_meanwhile(advance: Callable) -> bool:
    """Whether a soil's `advance` takes `meanwhile`. A method is asked once per class's function, not
    once per macro step (inspect.signature costs tens of microseconds of the host's step); any other
    callable is asked each time."""
    function = getattr(advance, "__func__", None)
    if function is None:
        return "meanwhile" in inspect.signature(advance).parameters
    return _function_takes_meanwhile(function)


@functools.cache
def _function_takes_meanwhile(function: Callable) -> bool:
    return "meanwhile" in inspect.signature(function).parameters


class SoilSideDefaults:
    """The absent answers of SoilSide's optional capabilities: no walls, no particles, nothing
    to check, no inner steps. A terrain model derives from it and overrides what it has."""

    def step_statistics(self) -> StepStatistics | None:
        return None

    def state_dict_units(self) -> dict[str, str]:
        return {}

    def start_health_checks(self) -> None:
        return None

    def check_health(self) -> None:
        return None

    def walls(self) -> dict | None:
        return None

    def wall_loads(self) -> dict | None:
        return None

    def particles(self) -> Particles | None:
        return None


class RoverDiverged(RegolithError, RuntimeError):
    """The rover model became unstable (its accelerations not finite or huge): the run stops as when the
    soil diverges (exit 4), with its last checkpoint to resume from once the scene is changed."""


@runtime_checkable
class RoverSide(Protocol):
    """A multibody rover model that carries wheels."""

    wheel_names: list[str]

    @property
    def time(self) -> float:
        """The rover's time [s] (read only: `advance` moves it)."""

    def set_gravity(self, gravity: Sequence[float]) -> None:
        """Set the scene's gravity vector [m/s^2], shape (3,)."""

    def wheel_kinematics(self) -> list[WheelKinematics]:
        """Current hub kinematics of every wheel, in wheel_names order."""

    def apply_wheel_wrenches(self, wrenches: Sequence[WheelWrench]) -> None:
        """Hold these wrenches (their `force`/`torque`) on the wheels until replaced."""

    def advance(self, t_end: float) -> None:
        """Advance the rover to t_end [s]."""
