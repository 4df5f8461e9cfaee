"""One builder from a run plan and a settled bed to the coupled system.

    system = CoupledSystem.build(plan, bed)
    record = system.coupler.step()

The system holds the soil simulation (soil.Simulation), the DEM soil side
(cosim.dem_soil.DemSoil), the rover side (here the single-wheel testbed) and the Coupler.
Each of them owns its checkpoint state (`state_dict` / `load_state_dict`); the system
only gathers them under prefixes, so a checkpoint is a flat dict of numpy arrays.
Runs, studies, sweeps and advice all build through here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from soil import Simulation
from soil.bed import load_bed, restore_state

from .beds import Bed
from .coupler import Coupler
from .dem_soil import DemSoil
from .metrics import WheelGeometry
from .plan import RunPlan
from .single_wheel import SingleWheelRig

START_GAP = 0.05
"""Gap between the wheel and the highest grain under it at the start, in mean grain radii [-]:
a wheel pressed into the grains would be shot off them in milli-g."""


@dataclass
class CoupledSystem:
    """The parts of a coupled run, built from a plan and a bed."""

    plan: RunPlan
    bed: Bed
    sim: Simulation
    soil: DemSoil
    rover: SingleWheelRig
    coupler: Coupler

    @classmethod
    def build(cls, plan: RunPlan, bed: Bed) -> "CoupledSystem":
        builder, saved = load_bed(bed.path)
        builder.add_wheel(plan.wheel.shape, plan.wheel.material)
        model, state, control = builder.finalize(device=plan.device, precision=plan.precision, law=plan.law,
                                                 order_seed=plan.order_seed)
        restore_state(model, state, saved)
        sim = Simulation(model, state, control)
        soil = DemSoil(sim, plan.dt, bed.surface_height)
        hub = plan.hub_start(bed.surface_height)
        highest = soil.highest_grain_under(0, hub)
        hub[2] = max(hub[2], highest + plan.wheel.outer_radius + START_GAP * plan.bed.spec.radius_mean)
        t = plan.testbed
        rover = SingleWheelRig(t.mass, plan.wheel.rim_radius, t.omega, hub, mode=t.mode, slip=t.slip,
                               drawbar_load=t.drawbar_load, drawbar_ramp=t.drawbar_ramp, gravity=plan.gravity,
                               landed=not plan.landing.enabled)
        soil.place_wheels(rover.wheel_kinematics())
        coupler = Coupler(soil, rover, plan.macro_step, scheme=plan.scheme, gravity=plan.gravity)
        return cls(plan, bed, sim, soil, rover, coupler)

    @property
    def geometry(self) -> WheelGeometry:
        """What cosim.metrics needs of the wheel and the ground."""
        w = self.plan.wheel
        return WheelGeometry(w.rim_radius, w.outer_radius, self.bed.surface_height)

    def state_dict(self) -> dict:
        """Every part's checkpoint state, flattened under 'soil/' (the DEM soil side, its simulation
        included), 'rover/' and 'coupler/'."""
        out = {}
        for prefix, part in (("soil", self.soil), ("rover", self.rover), ("coupler", self.coupler)):
            for key, value in part.state_dict().items():
                out[f"{prefix}/{key}"] = np.asarray(value)
        return out

    def load_state_dict(self, state: dict) -> None:
        for prefix, part in (("soil", self.soil), ("rover", self.rover), ("coupler", self.coupler)):
            head = prefix + "/"
            part.load_state_dict({k[len(head):]: v for k, v in state.items() if k.startswith(head)})

    def boundaries(self) -> dict:
        """The soil's walls as built: 'kind' (B,), 'geometry' (B, 6) [m], 'report' (B,) (cosim.output)."""
        model = self.sim.model
        return {"kind": model.boundary_kind.numpy(), "geometry": model.boundary_geometry_numpy(),
                "report": model.boundary_reports}

    def wheel_mesh(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Display mesh of the wheels: vertices [m] (V, 3) in wheel frames, triangles (F, 3), owner wheel (V,)."""
        shape = self.plan.wheel.shape
        vertices, triangles = shape.to_mesh(arc_segments=240) if hasattr(shape, "to_mesh") else (
            shape.vertices, shape.triangles)
        return vertices, triangles, np.zeros(len(vertices), dtype=np.int32)

    def posed_wheel_vertices(self, vertices: np.ndarray, owner: np.ndarray) -> np.ndarray:
        """The display mesh at the wheels' current poses [m], shape (V, 3)."""
        control = self.sim.control
        return (np.einsum("vij,vj->vi", control.body_rotation_host[owner], vertices)
                + control.body_position_host[owner])
