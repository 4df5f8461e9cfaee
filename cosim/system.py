"""One builder from a run plan and a settled bed to the coupled system.

    system = CoupledSystem.build(plan, bed)
    record = system.coupler.step()

The system holds the soil simulation (soil.Simulation), the DEM soil side
(cosim.dem_soil.DemSoil), the rover side (the single-wheel testbed, or a rover model with its
drive: cosim.rover.RoverDriver), the Coupler, and for a rover on a moving patch the patch
(soil.patch.SoilPatch). Each of them owns its checkpoint state (`state_dict` /
`load_state_dict`); the system only gathers them under prefixes, so a checkpoint is a flat
dict of numpy arrays. Runs, studies, sweeps and advice all build through here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from soil import Simulation
from soil.bed import load_bed, restore_state
from soil.control import quaternion_to_matrix
from soil.patch import SoilPatch, Tile

from .beds import Bed
from .coupler import Coupler
from .dem_soil import DemSoil
from .metrics import WheelGeometry
from .plan import RunPlan, SceneError, enable_step_control, make_integrator
from .rover import RoverDriver, make_controller, open_rover
from .single_wheel import SingleWheelRig

START_GAP = 0.05
"""Gap between the wheel and the highest grain under it at the start, in mean grain radii [-]:
a wheel pressed into the grains would be shot off them in milli-g."""


@dataclass
class CoupledSystem:
    """The parts of a coupled run, built from a plan and a bed."""

    plan: RunPlan
    bed: Bed
    soil: DemSoil
    rover: SingleWheelRig | RoverDriver
    """The rover side: the testbed's rig, or a rover and its drive."""
    coupler: Coupler
    patch: SoilPatch | None = None

    @property
    def sim(self) -> Simulation:
        """The soil simulation now (a moving patch replaces it when it moves)."""
        return self.soil.sim

    @classmethod
    def build(cls, plan: RunPlan, bed: Bed) -> CoupledSystem:
        if plan.rover is not None:
            return cls._build_rover(plan, bed)
        builder, saved = load_bed(bed.path)
        builder.add_wheel(plan.wheel.shape, plan.wheel.material)
        model, state, control = builder.finalize(
            device=plan.device, precision=plan.precision, law=plan.law, order_seed=plan.order_seed
        )
        restore_state(model, state, saved)
        sim = Simulation(model, state, control, integrator=make_integrator(plan.integrator))
        enable_step_control(plan, sim)
        soil = DemSoil(sim, plan.dt, bed.surface_height)
        hub = plan.hub_start(bed.surface_height)
        highest = soil.highest_grain_under(0, hub)
        hub[2] = max(hub[2], highest + plan.wheel.outer_radius + START_GAP * plan.bed.spec.radius_mean)
        t = plan.testbed
        assert t is not None  # a plan without a rover has a testbed
        rover = SingleWheelRig(
            t.mass,
            plan.wheel.rim_radius,
            t.omega,
            hub,
            mode=t.mode,
            slip=t.slip,
            drawbar_load=t.drawbar_load,
            drawbar_ramp=t.drawbar_ramp,
            gravity=plan.gravity,
            landed=not plan.landing.enabled,
        )
        soil.place_wheels(rover.wheel_kinematics())
        coupler = Coupler(soil, rover, plan.macro_step, scheme=plan.scheme, gravity=plan.gravity)
        return cls(plan, bed, soil, rover, coupler)

    @classmethod
    def _build_rover(cls, plan: RunPlan, bed: Bed) -> CoupledSystem:
        """A rover on the bed (or on a patch of tiles of it), lowered until its lowest wheel just clears
        the highest grain under it, braked for the landing."""
        r = plan.rover
        assert r is not None
        wheels = [(w.shape, w.material) for w in plan.wheels]
        patch = None
        if plan.patch is not None:
            p, spec = plan.patch, plan.bed.spec
            tile = Tile.load(bed.path, (spec.length, spec.width), plan.precision, p.tile_margin)
            patch = SoilPatch(
                tile,
                p.length,
                p.width,
                p.band,
                p.recentre_distance,
                wheels,
                plan.gravity,
                plan.device,
                plan.precision,
                plan.law,
                plan.order_seed,
            )
            centre = np.asarray(r.start[:2]) + r.hub_offsets[:, :2].mean(axis=0)
            sim = patch.start(centre, make_integrator(plan.integrator))
            enable_step_control(plan, sim)
            surface = patch.surface_height(sim)
        else:
            builder, saved = load_bed(bed.path)
            builder.gravity = np.asarray(plan.gravity, dtype=np.float64)  # settled on the floor; now the slope
            for shape, material in wheels:
                builder.add_wheel(shape, material)
            model, state, control = builder.finalize(
                device=plan.device, precision=plan.precision, law=plan.law, order_seed=plan.order_seed
            )
            restore_state(model, state, saved)
            sim = Simulation(model, state, control, integrator=make_integrator(plan.integrator))
            enable_step_control(plan, sim)
            surface = bed.surface_height
        soil = DemSoil(sim, plan.dt, surface, patch=patch)
        rover = open_rover(plan)
        lift = _lift(soil, rover.wheel_kinematics(), plan)
        if r.model == "fmu":
            if not r.start_parameters:
                if lift > 0:
                    rover.close()
                    raise SceneError(
                        [
                            f"rover.file: the FMU starts with a wheel {lift:.4g} m in the soil and has no "
                            "start.z parameter to lift it; start it above the soil (surface at z = "
                            f"{surface:.4g} m)"
                        ]
                    )
            else:
                z = rover.body_kinematics().position[2] + lift
                rover.close()
                rover = open_rover(plan, start_z=z)
        else:
            rover.move_base(np.array([0.0, 0.0, lift]))
        body = rover.body_id(r.body) if r.model != "fmu" else None
        driver = RoverDriver(
            rover, make_controller(plan), takes_speed=r.takes_speed, body=body, landed=not plan.landing.enabled
        )
        soil.place_wheels(driver.wheel_kinematics())
        coupler = Coupler(
            soil, driver, plan.macro_step, scheme=plan.scheme, gravity=plan.gravity, controller=driver.command
        )
        return cls(plan, bed, soil, driver, coupler, patch)

    @property
    def geometries(self) -> list[WheelGeometry]:
        """What cosim.metrics needs of each wheel and the ground, in wheel order."""
        return [WheelGeometry(w.rim_radius, w.outer_radius, self.soil.surface_height) for w in self.plan.wheels]

    @property
    def geometry(self) -> WheelGeometry:
        """The first wheel's geometry (the testbed's only wheel)."""
        return self.geometries[0]

    def _parts(self):
        return (("soil", self.soil), ("rover", self.rover), ("coupler", self.coupler))

    def state_dict(self) -> dict:
        """Every part's checkpoint state, flattened under 'soil/' (the DEM soil side, its simulation and
        moving patch included), 'rover/' and 'coupler/'."""
        out = {}
        for prefix, part in self._parts():
            for key, value in part.state_dict().items():
                out[f"{prefix}/{key}"] = np.asarray(value)
        return out

    def load_state_dict(self, state: dict) -> None:
        for prefix, part in self._parts():
            head = prefix + "/"
            part.load_state_dict({k[len(head) :]: v for k, v in state.items() if k.startswith(head)})

    def boundaries(self) -> dict:
        """The soil's walls as built: 'kind' (B,), 'geometry' (B, 6) [m], 'report' (B,) (cosim.output)."""
        model = self.sim.model
        return {
            "kind": model.boundary_kind.numpy(),
            "geometry": model.boundary_geometry_numpy(),
            "report": model.boundary_reports,
        }

    def wheel_mesh(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Display mesh of the wheels: vertices [m] (V, 3) in wheel frames, triangles (F, 3), owner wheel (V,)."""
        vertices, triangles, owners = [], [], []
        count = 0
        for index, wheel in enumerate(self.plan.wheels):
            shape = wheel.shape
            v, t = shape.to_mesh(arc_segments=240) if hasattr(shape, "to_mesh") else (shape.vertices, shape.triangles)
            vertices.append(np.asarray(v, dtype=np.float64))
            triangles.append(np.asarray(t) + count)
            owners.append(np.full(len(v), index, dtype=np.int32))
            count += len(v)
        return np.concatenate(vertices), np.concatenate(triangles), np.concatenate(owners)

    def posed_wheel_vertices(self, vertices: np.ndarray, owner: np.ndarray) -> np.ndarray:
        """The display mesh at the wheels' current poses [m], shape (V, 3)."""
        control = self.sim.control
        return np.einsum("vij,vj->vi", control.body_rotation_host[owner], vertices) + control.body_position_host[owner]

    def close(self) -> None:
        """Free what the rover side holds (FMU instances)."""
        if hasattr(self.rover, "close"):
            self.rover.close()


def _lift(soil: DemSoil, kinematics, plan: RunPlan) -> float:
    """How far to raise the rover [m] so its lowest wheel clears the highest grain under it by START_GAP."""
    gap = START_GAP * plan.bed.spec.radius_mean
    lift = -np.inf
    for i, (k, wheel) in enumerate(zip(kinematics, plan.wheels)):
        axle = quaternion_to_matrix(k.orientation)[:, 1]
        top = soil.highest_grain_under(i, k.position, axle)
        top = max(top, soil.surface_height)
        lift = max(lift, top + wheel.outer_radius + gap - k.position[2])
    return float(lift)
