"""The DEM soil as a SoilSide: wheels moved by the rover's kinematics, wrenches back."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike

from soil.errors import ArgumentError, RegolithWarning, is_real
from soil.sdf import BOUNDARY_PLANE

from .contract import Particles, SoilBooks, StepStatistics, WheelKinematics, WheelWrench


class WallProximityWarning(RegolithWarning):
    """A wheel came within a few grain radii of a container wall: results feel the wall."""


class DemSoil:
    """SoilSide over a soil.Simulation whose bodies 0..W-1 are the wheels.

    Args:
        sim: a soil.Simulation built with one body per wheel.
        dt: DEM step [s]; each macro step is split into whole DEM steps that end
            exactly at the macro step's end.
        surface_height: undisturbed soil surface z [m], for the sinkage.
        wall_clearance: warn (WallProximityWarning) when a wheel's outer rim comes closer
            than this to a container wall [m]; default 5 mean grain radii.
        patch: a soil.patch.SoilPatch that follows the wheels; before each macro step it may
            move and replace `sim` (host side, between DEM steps).
    """

    def __init__(self, sim, dt: float, surface_height: float = 0.0, wall_clearance: float | None = None, patch=None):
        if not hasattr(sim, "body_count"):  # a soil.Simulation or a world of one (soil.worlds): what steps grains
            raise ArgumentError(f"sim must be a soil.Simulation with the wheels as bodies, got {type(sim).__name__}")
        if sim.body_count < 1:
            raise ArgumentError("the soil simulation has no wheel bodies (SoilBuilder.add_wheel)")
        # all checked before anything is set: a text or None would reach `>` as a bare TypeError, and an
        # inf step or a nan surface would pass a bare comparison
        if not (is_real(dt) and math.isfinite(dt) and dt > 0):
            raise ArgumentError(f"dt must be a finite number > 0 [s], got {dt!r}")
        if not (is_real(surface_height) and math.isfinite(surface_height)):
            raise ArgumentError(f"surface_height must be a finite number [m], got {surface_height!r}")
        if wall_clearance is not None and not (
            is_real(wall_clearance) and math.isfinite(wall_clearance) and wall_clearance >= 0
        ):
            raise ArgumentError(
                f"wall_clearance must be None (5 mean grain radii) or a finite number >= 0 [m], got {wall_clearance!r}"
            )
        self.sim = sim
        self.dt = float(dt)
        self.surface_height = float(surface_height)
        self.wheel_count = sim.body_count
        self.wall_clearance = 5 * float(sim.radii().mean()) if wall_clearance is None else float(wall_clearance)
        self._warned_wall = False
        self.patch = patch
        self.last_report = None
        """The soil.MacroStepReport of the last advance() (steps taken, rejected, dt range, evaluations)."""
        self._static_mass: float | None = None

    @classmethod
    def from_bed(
        cls,
        bed,
        wheels,
        wheel_material,
        dt: float,
        surface_height: float | None = None,
        device=None,
        precision: str = "mixed",
        order_seed: int | None = None,
        wall_clearance: float | None = None,
        law=None,
    ) -> DemSoil:
        """A DemSoil on a saved bed (a soil.bed.SavedBed, or the path of a bed file: soil.bed.open_bed)
        with one body per wheel shape (GrouserWheel/MeshWheel), all of `wheel_material`.

        surface_height [m]: undisturbed surface; None takes the bed's saved height metric.
        law: soil.ContactLaw switches; None: rolling and cohesion on when a material uses them.
        """
        from soil.bed import SavedBed, open_bed, read_bed
        from soil.geometry import GrouserWheel, MeshWheel

        if isinstance(wheels, (GrouserWheel, MeshWheel)):  # one shape given where a list of them goes
            raise ArgumentError(f"wheels must be a list of wheel shapes, one per wheel: [{type(wheels).__name__}(...)]")
        saved = bed if isinstance(bed, SavedBed) else read_bed(bed)
        if surface_height is None:
            if "height" not in saved.metrics:
                raise ArgumentError("the bed file has no height metric: pass surface_height [m]")
            surface_height = float(saved.metrics["height"])
        sim = open_bed(
            saved,
            [(shape, wheel_material) for shape in wheels],
            device=device,
            precision=precision,
            law=law,
            order_seed=order_seed,
        )
        return cls(sim, dt, surface_height, wall_clearance)

    @property
    def time(self) -> float:
        return self.sim.time

    def set_gravity(self, gravity: Sequence[float]) -> None:
        asked = np.asarray(gravity, dtype=np.float64).reshape(3)
        if not np.allclose(asked, self.sim.gravity, rtol=1e-12, atol=0):
            raise ArgumentError(
                f"the soil was settled under gravity {np.asarray(self.sim.gravity).tolist()} m/s^2, the scene asks "
                f"for {asked.tolist()}: settle the bed under the scene's gravity"
            )

    def highest_grain_under(self, wheel: int, hub: ArrayLike, axle: ArrayLike = (0.0, 1.0, 0.0)) -> float:
        """Top (z + r) [m] of the highest grain inside the wheel's horizontal footprint when
        its hub is at `hub` and its axle along `axle` (a horizontal unit vector, world); -inf if
        none. Place a wheel at max(...) + outer radius to start it just touching, not pressed
        into, the soil."""
        shape = self.sim.body_shapes[wheel]
        x = self.sim.positions()
        r = self.sim.radii()
        reach = shape.outer_radius
        half_width = 0.5 * getattr(shape, "width", 2 * reach)
        a = np.asarray(axle, dtype=np.float64)
        across = a[:2] / np.hypot(a[0], a[1])
        along = np.array([across[1], -across[0]])
        offset = x[:, :2] - np.asarray(hub, dtype=np.float64)[:2]
        inside = (np.abs(offset @ along) < reach + r) & (np.abs(offset @ across) < half_width + r)
        return float(np.max(x[inside, 2] + r[inside])) if inside.any() else -np.inf

    def place_wheels(self, kinematics: Sequence[WheelKinematics]) -> None:
        """Put the wheels at these poses without stepping (e.g. before the first macro step)."""
        for b, k in enumerate(kinematics):
            self.sim.set_body_motion(b, k.position, k.orientation, k.linear_velocity, k.angular_velocity)
        self.sim.refresh_forces()

    def advance(
        self,
        t_end: float,
        start: Sequence[WheelKinematics],
        end: Sequence[WheelKinematics] | None = None,
        meanwhile: Callable[[], None] | None = None,
    ) -> list[WheelWrench]:
        """Advance the soil to t_end [s] in whole DEM steps, the wheels moving from `start` with
        constant velocities (end None) or towards `end`; returns each wheel's wrench.

        The DEM steps run on the device as one macro step that lands on t_end
        (soil.Simulation.advance_to): the wheels are posed there at each step and their wrenches
        summed there; the host reads the result once. meanwhile (SoilSide.advance): called once
        the steps are launched, before that read.
        """
        if len(start) != self.wheel_count:
            raise ArgumentError(f"expected kinematics of {self.wheel_count} wheels, got {len(start)}")
        if end is not None and len(end) != self.wheel_count:
            raise ArgumentError(f"expected end kinematics of {self.wheel_count} wheels, got {len(end)}")
        t0 = self.sim.time
        if not (is_real(t_end) and math.isfinite(t_end)):  # before the patch moves or the wheels' path is set
            raise ArgumentError(f"t_end must be a finite time [s] after the soil's time {t0!r} s, got {t_end!r}")
        span = float(t_end) - t0
        if not span > 0:
            raise ArgumentError(f"t_end {t_end!r} s must be after the soil's time {t0!r} s")
        if self.patch is not None:  # the patch follows the wheels' centre, between macro steps
            moved = self.patch.follow(self.sim, np.mean([k.position[:2] for k in start], axis=0))
            if moved is not None:
                self.sim = moved
        sim = self.sim

        def stack(kinematics):
            return tuple(
                np.array([getattr(k, name) for k in kinematics], dtype=np.float64)
                for name in ("position", "orientation", "linear_velocity", "angular_velocity")
            )

        sim.set_body_path(span, *stack(start), end=None if end is None else stack(end))
        # whole DEM steps of about dt, or PID substeps with a step control; the soil's clock is t_end
        report = sim.advance_to(t_end, self.dt, path=True, meanwhile=meanwhile)
        self.last_report = report
        self._check_walls(sim.body_positions(), report.boundary_displacement)
        return [
            WheelWrench(
                force=report.body_force[b],
                torque=report.body_torque[b],
                force_end=report.body_force_end[b],
                torque_end=report.body_torque_end[b],
                contact_count=int(report.body_contacts[b]),
                sinkage=self._sinkage(b),
                work_on_soil=float(report.body_work[b]),
            )
            for b in range(self.wheel_count)
        ]

    def current_wrenches(self) -> list[WheelWrench]:
        """The wrench on every wheel at this instant (e.g. after place_wheels): force and torque
        are the instantaneous ones, the work is zero."""
        force, torque, contacts = self.sim.body_wrenches()
        return [
            WheelWrench(
                force=force[b],
                torque=torque[b],
                force_end=force[b].copy(),
                torque_end=torque[b].copy(),
                contact_count=int(contacts[b]),
                sinkage=self._sinkage(b),
            )
            for b in range(self.wheel_count)
        ]

    def _sinkage(self, wheel: int) -> float:
        """Depth of the wheel's rim bottom below the undisturbed surface [m]."""
        shape = self.sim.body_shapes[wheel]
        lowest = self.sim.body_positions()[wheel, 2] - getattr(shape, "radius", getattr(shape, "outer_radius", 0.0))
        return self.surface_height - float(lowest)

    # -- checkpoints -----------------------------------------------------------------
    def state_dict(self) -> dict:
        """Everything the soil side needs to continue bit for bit, as numpy arrays and scalars:
        its Simulation's state_dict() under 'simulation/', a moving patch's under 'patch/' and its
        own 'warned_wall' flag."""
        data = {f"simulation/{k}": v for k, v in self.sim.state_dict().items()}
        if self.patch is not None:
            data.update({f"patch/{k}": v for k, v in self.patch.state_dict().items()})
        data["warned_wall"] = np.bool_(self._warned_wall)
        return data

    def state_dict_units(self) -> dict[str, str]:
        """SoilSide: {key of state_dict(): its unit}."""
        units = {f"simulation/{k}": v for k, v in self.sim.state_dict_units().items()}
        if self.patch is not None:
            units.update({f"patch/{k}": v for k, v in self.patch.state_dict_units().items()})
        units["warned_wall"] = "1"
        return units

    def load_state_dict(self, data: dict) -> None:
        """Continue from state_dict() output (into a DemSoil built from the same scene and bed)."""
        if self.patch is not None:  # the patch's grains first: the simulation's state is loaded over them
            self.sim = self.patch.load_state_dict(
                {k[len("patch/") :]: v for k, v in data.items() if k.startswith("patch/")}, self.sim
            )
        self.sim.load_state_dict({k[len("simulation/") :]: v for k, v in data.items() if k.startswith("simulation/")})
        self._warned_wall = bool(data["warned_wall"])

    # -- walls ---------------------------------------------------------------------
    def _container_walls(self, displacement: np.ndarray):
        """(point, inward normal) of the side walls (vertical planes), displaced by
        `displacement` [m] (boundary_count, 3) from their initial geometry."""
        kinds = self.sim.boundary_kinds()
        geometry = self.sim.boundary_geometry(displacement)
        return [(g[:3], g[3:]) for kind, g in zip(kinds, geometry) if kind == BOUNDARY_PLANE and abs(g[5]) < 0.5]

    def _check_walls(self, positions: np.ndarray, displacement: np.ndarray) -> None:
        if self._warned_wall:
            return
        rotations = self.sim.body_rotations()
        walls = self._container_walls(displacement)
        for b, hub in enumerate(positions):
            shape = self.sim.body_shapes[b]
            for point, normal in walls:
                inside = float((hub - point) @ normal)  # the hub's distance inside the wall's plane
                gap = inside - _extent(shape, rotations[b], normal)
                if gap < self.wall_clearance:
                    # a negative distance reads as a typo: say where the wheel is instead
                    hub_at = f"hub at {np.round(hub, 4)}"
                    if inside < 0:
                        message = (
                            f"wheel {b} lies outside the container: its hub is {-inside:.4g} m beyond a container "
                            f"wall ({hub_at}); place the wheel inside the container, or make the bed larger"
                        )
                    elif gap < 0:
                        message = (
                            f"wheel {b} reaches {-gap:.4g} m through a container wall ({hub_at}): the wall "
                            "influences the result; make the bed larger"
                        )
                    else:
                        message = (
                            f"wheel {b} is {gap:.4g} m from a container wall ({hub_at}), closer than "
                            f"{self.wall_clearance:.3g} m: the wall influences the result; make the bed larger"
                        )
                    self._warned_wall = True
                    warnings.warn(message, WallProximityWarning, stacklevel=3)
                    return

    # -- the rest of the SoilSide contract (cosim.contract) ------------------------------
    def highest_point_under(self, wheel: int, hub: ArrayLike, axle: ArrayLike = (0.0, 1.0, 0.0)) -> float:
        """SoilSide: the top of the highest grain under the wheel (highest_grain_under)."""
        return self.highest_grain_under(wheel, hub, axle)

    def wheel_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """SoilSide: the wheel bodies' hub positions [m] (W, 3) and rotations (W, 3, 3) as the last
        DEM step (or place_wheels) left them."""
        return self.sim.body_positions(), self.sim.body_rotations()

    def books(self) -> SoilBooks:
        """SoilSide: the grains simulated and their mass; a moving patch's books when there is one."""
        if self.patch is not None:
            b = self.patch.books()
            return SoilBooks(
                element_count=b["particle_count"],
                mass=b["soil_mass"],
                mass_initial=b["mass_initial"],
                mass_added=b["mass_added"],
                mass_removed=b["mass_removed"],
                moves=b["moves"],
                moving=True,
            )
        if self._static_mass is None:  # a bed's grains stay the same: their mass is summed once
            self._static_mass = float(np.sum(self.sim.masses()))
        return SoilBooks(element_count=self.sim.particle_count, mass=self._static_mass, mass_initial=self._static_mass)

    def step_statistics(self) -> StepStatistics | None:
        """SoilSide: the DEM steps of the last macro step (soil.MacroStepReport); None before the first."""
        report = self.last_report
        if report is None:
            return None
        return StepStatistics(
            report.steps, report.rejected, report.dt_min, report.dt_max, report.evaluations, report.forced
        )

    def start_health_checks(self) -> None:
        """SoilSide: arm the simulation's divergence monitor (soil.DivergenceMonitor) unless a
        checkpoint armed it already."""
        if not self.sim.monitor.armed:
            self.sim.arm_monitor()

    def check_health(self) -> None:
        """SoilSide: the divergence monitor's full check (soil.SimulationDiverged with the last good state)."""
        self.sim.check_divergence()

    def walls(self) -> dict | None:
        """SoilSide: the container walls as built (cosim.contract.WALL_NAMES); None without walls."""
        sim = self.sim
        if not sim.boundary_count:
            return None
        return {
            "kind": sim.boundary_kinds(),
            "geometry": sim.initial_boundary_geometry(),
            "report": sim.boundary_reports(),
        }

    def wall_loads(self) -> dict | None:
        """SoilSide: the walls' loads now (cosim.contract.WALL_LOAD_NAMES); None without walls."""
        if not self.sim.boundary_count:
            return None
        force, torque, contacts = self.sim.boundary_wrenches()
        return {
            "force": force,
            "torque": torque,
            "contact_count": contacts,
            "displacement": self.sim.boundary_displacements(),
        }

    def particles(self) -> Particles:
        """SoilSide: the grains now; with a moving patch the grains come and go (ids given)."""
        sim = self.sim
        return Particles(
            position=sim.positions(),
            velocity=sim.velocities(),
            radius=sim.radii(),
            ids=None if self.patch is None else self.patch.ids,
        )


def _extent(shape, rotation: np.ndarray, direction: np.ndarray) -> float:
    """How far the wheel reaches from its hub against `direction` (world) [m]."""
    if hasattr(shape, "vertices"):
        return float(np.max(-(shape.vertices @ rotation.T) @ direction))
    axle = rotation[:, 1]
    along = abs(float(axle @ direction))
    return shape.outer_radius * float(np.sqrt(max(0.0, 1.0 - along * along))) + 0.5 * shape.width * along
