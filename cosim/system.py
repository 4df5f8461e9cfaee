"""One builder from a run plan and a settled bed to the coupled system.

    system = CoupledSystem.build(plan, bed)
    record = system.coupler.step()

The system holds the soil side (a cosim.contract.SoilSide: the DEM soil, cosim.dem_soil.DemSoil,
with its simulation and, for a rover on a moving patch, its patch; or another terrain model),
the rover side (the single-wheel testbed, or a rover model with its drive:
cosim.rover.RoverDriver) and the Coupler. Each of them owns its checkpoint state (`state_dict` /
`load_state_dict`); the system only gathers them under prefixes, so a checkpoint is a flat
dict of numpy arrays. Runs, studies, sweeps and advice all build through here.

Terrain models ([terrain] model) are registered in TERRAIN_MODELS: a builder of the soil side
from the plan (and, for the DEM, its settled bed). Adding one is a SoilSide implementation and
one entry there; the runner, the records and the results writer read only the contract.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from soil.bed import open_bed
from soil.control import quaternion_to_matrix
from soil.integrator import make_integrator
from soil.patch import SoilPatch, Tile

from . import advice
from .advice import Finding
from .beds import Bed
from .contract import SoilSide
from .coupler import Coupler
from .dem_soil import DemSoil
from .metrics import WheelGeometry
from .plan import RunPlan, SceneError, enable_step_control
from .rover import RoverDriver, drive_label, make_controller, open_rover
from .scm_calibration import warn_gravity
from .scm_soil import CompositeSoil, ScmSoil, scm_settings, scm_steps
from .single_wheel import SingleWheelRig
from .terrain import WRENCH_SAMPLES, SpringDamperTerrain

START_GAP = 0.05
"""Gap between the wheel and the highest grain under it at the start, in mean grain radii [-]:
a wheel pressed into the grains would be shot off them in milli-g."""


@dataclass
class CoupledSystem:
    """The parts of a coupled run, built from a plan (and, on a DEM terrain, its bed)."""

    plan: RunPlan
    bed: Bed | None
    """The settled bed the soil was opened from (None: a terrain without a bed)."""
    soil: SoilSide
    rover: SingleWheelRig | RoverDriver
    """The rover side: the testbed's rig, or a rover and its drive."""
    coupler: Coupler

    @classmethod
    def build(cls, plan: RunPlan, bed: Bed | None, soil: SoilSide | None = None) -> CoupledSystem:
        """The system of `plan` on its terrain model (TERRAIN_MODELS); `bed`: the settled bed of a
        terrain that needs one (`needs_bed`), else None; `soil`: a soil side built already (a world
        of a batch, cosim.batch), its wheels not yet placed."""
        if soil is None:
            soil = TERRAIN_MODELS[plan.terrain.model].build(plan, bed)
        if plan.rover is None:
            return cls._on_testbed(plan, bed, soil)
        return cls._with_rover(plan, bed, soil)

    @classmethod
    def _on_testbed(cls, plan: RunPlan, bed: Bed | None, soil: SoilSide) -> CoupledSystem:
        """The single-wheel testbed on the soil, its wheel just clear of the highest point under it."""
        hub = plan.hub_start(soil.surface_height)
        highest = soil.highest_point_under(0, hub)
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
    def _with_rover(cls, plan: RunPlan, bed: Bed | None, soil: SoilSide) -> CoupledSystem:
        """A rover on the soil, lowered until its lowest wheel just clears the highest point under
        it, braked for the landing."""
        r = plan.rover
        assert r is not None
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
                            f"{soil.surface_height:.4g} m)"
                        ]
                    )
            else:
                z = rover.body_kinematics().position[2] + lift
                rover.close()
                rover = open_rover(plan, start_z=z)
        else:
            rover.move_base(np.array([0.0, 0.0, lift]))
        body = rover.body_id(r.body) if r.model != "fmu" else None
        drive = r.drive
        driver = RoverDriver(
            rover,
            make_controller(plan),
            takes_speed=r.takes_speed,
            body=body,
            landed=not plan.landing.enabled,
            label=drive_label(plan),
            user_code=drive.kind == "python",
        )
        soil.place_wheels(driver.wheel_kinematics())
        coupler = Coupler(
            soil, driver, plan.macro_step, scheme=plan.scheme, gravity=plan.gravity, controller=driver.command
        )
        return cls(plan, bed, soil, driver, coupler)

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

    def state_dict_units(self) -> dict[str, str]:
        """{key of state_dict(): its unit}, from each part's `state_dict_units()` where it has one."""
        out = {}
        for prefix, part in self._parts():
            units = part.state_dict_units() if hasattr(part, "state_dict_units") else {}
            out.update({f"{prefix}/{key}": unit for key, unit in units.items()})
        return out

    def load_state_dict(self, state: dict) -> None:
        for prefix, part in self._parts():
            head = prefix + "/"
            part.load_state_dict({k[len(head) :]: v for k, v in state.items() if k.startswith(head)})

    def boundaries(self) -> dict | None:
        """The soil's walls as built (cosim.contract.WALL_NAMES; cosim.output), None without walls."""
        return self.soil.walls()

    def wheel_mesh(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Display mesh of the wheels (wheel_display_mesh)."""
        return wheel_display_mesh(self.plan)

    def posed_wheel_vertices(self, vertices: np.ndarray, owner: np.ndarray) -> np.ndarray:
        """The display mesh at the wheels' current poses [m], shape (V, 3)."""
        position, rotation = self.soil.wheel_poses()
        return np.einsum("vij,vj->vi", rotation[owner], vertices) + position[owner]

    def close(self) -> None:
        """Free what the rover side holds (FMU instances)."""
        if hasattr(self.rover, "close"):
            self.rover.close()


def _lift(soil: SoilSide, kinematics, plan: RunPlan) -> float:
    """How far to raise the rover [m] so its lowest wheel clears the highest point under it by START_GAP."""
    gap = START_GAP * plan.bed.spec.radius_mean
    lift = -np.inf
    for i, (k, wheel) in enumerate(zip(kinematics, plan.wheels)):
        axle = quaternion_to_matrix(k.orientation)[:, 1]
        top = soil.highest_point_under(i, k.position, axle)
        top = max(top, soil.surface_height)
        lift = max(lift, top + wheel.outer_radius + gap - k.position[2])
    return float(lift)


# ------------------------------------------------------------------------------------
# terrain models


def _dem_soil(plan: RunPlan, bed: Bed | None, indices: list[int] | None = None) -> DemSoil:
    """The DEM soil: the settled bed's grains with one body per wheel (the testbed's one wheel, or
    a rover's on the bed or on a patch of tiles of it); `indices`: only these wheels (a mixed terrain)."""
    assert bed is not None  # the DEM terrain needs its bed (TerrainModel.needs_bed)
    if plan.rover is None:
        sim = open_bed(
            bed.saved,
            [(plan.wheel.shape, plan.wheel.material)],
            device=plan.device,
            precision=plan.precision,
            law=plan.law,
            order_seed=plan.order_seed,
            integrator=make_integrator(plan.integrator),
            storage=plan.storage,
        )
        enable_step_control(plan, sim)
        return DemSoil(sim, plan.dt, bed.surface_height)
    r = plan.rover
    wheels = [(w.shape, w.material) for w in plan.wheels]
    if indices is not None:
        wheels = [wheels[i] for i in indices]
    patch = None
    if plan.patch is not None:
        p, spec = plan.patch, plan.bed.spec
        tile = Tile.load(bed.saved, (spec.length, spec.width), plan.precision, p.tile_margin)
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
        sim = open_bed(
            bed.saved,
            wheels,
            device=plan.device,
            precision=plan.precision,
            law=plan.law,
            order_seed=plan.order_seed,
            integrator=make_integrator(plan.integrator),
            storage=plan.storage,
            gravity=plan.gravity,  # settled on the floor; now the slope
        )
        enable_step_control(plan, sim)
        surface = bed.surface_height
    return DemSoil(sim, plan.dt, surface, patch=patch)


def _analytic_soil(plan: RunPlan, bed: Bed | None) -> SpringDamperTerrain:
    """The analytic test terrain (cosim.terrain): flat spring-damper ground, wheels as discs of
    their rim radius, with the [terrain] section's parameters."""
    parameters = dict(plan.terrain.parameters)
    z0 = parameters.pop("surface_height", 0.0)
    return SpringDamperTerrain([w.rim_radius for w in plan.wheels], len(plan.wheels), z0=z0, **parameters)


def _scm_soil(plan: RunPlan, bed: Bed | None) -> ScmSoil:
    """The SCM terrain (soil.scm) under every wheel, with the [terrain] section's parameters."""
    surface = dict(plan.terrain.parameters).get("surface_height", 0.0)
    return _scm_part(plan, list(range(len(plan.wheels))), surface)


def _scm_part(plan: RunPlan, indices: list[int], surface: float) -> ScmSoil:
    if plan.terrain.calibration_gravity is not None:
        section = plan.scene.terrain
        warn_gravity(plan.terrain.calibration_gravity, plan.g, str(section.calibration if section else ""))
    settings = scm_settings(plan, indices, surface)
    wheels = [plan.wheels[i] for i in indices]
    return ScmSoil.build(
        settings, [w.shape for w in wheels], [w.rim_radius for w in wheels], plan.device, plan.precision
    )


def _mixed_soil(plan: RunPlan, bed: Bed | None) -> CompositeSoil:
    """terrain.wheels: the "dem" wheels on the bed's grains (and patch), the others on SCM at the
    DEM's surface height."""
    models = plan.terrain.wheel_models
    dem = [i for i, m in enumerate(models) if m == "dem"]
    scm = [i for i, m in enumerate(models) if m == "scm"]
    grains = _dem_soil(plan, bed, dem)
    return CompositeSoil([(grains, dem), (_scm_part(plan, scm, grains.surface_height), scm)])


def _scm_validity(plan: RunPlan, surface_height=None, measured=None) -> list:
    """cosim.advice.scm_check: where SCM cannot represent the wheel test."""
    return advice.scm_check(plan, measured)


def _mixed_validity(plan: RunPlan, surface_height=None, measured=None) -> list:
    """The DEM's checks (on the DEM wheels' deepest tips) and SCM's."""
    dem = [i for i, m in enumerate(plan.terrain.wheel_models) if m == "dem"]
    tips = advice.deepest(measured, "sinkage_tips", dem)
    spins, longest = (measured or {}).get("wheel_spin"), (measured or {}).get("dt_max")
    return advice.check(plan, surface_height, tips, spins, longest, dem) + advice.scm_check(plan, measured)


def _dem_validity(plan: RunPlan, surface_height=None, measured=None) -> list:
    """cosim.advice.check: the DEM's grain scales against the wheel, the bed and the (deepest wheel's) sinkage."""
    tips = advice.deepest(measured, "sinkage_tips")
    spins, longest = (measured or {}).get("wheel_spin"), (measured or {}).get("dt_max")
    return advice.check(plan, surface_height, tips, spins, longest)


def _no_findings(plan: RunPlan, surface_height=None, measured=None) -> list:
    """A terrain with no validity checks of its own (the analytic spring-damper: a test terrain, no soil
    model to be out of range of): nothing checked, and its verdict says so (cosim.advice.verdict)."""
    return []


@dataclass(frozen=True)
class TerrainModel:
    """How the builder makes the soil side of one terrain model."""

    build: Callable[[RunPlan, Bed | None], SoilSide]
    """The soil side of a plan, its wheels not yet placed (the builder places them)."""
    needs_bed: bool
    """The terrain opens a settled DEM bed: the run settles or reuses one first (cosim.beds)."""
    validity: Callable[..., list[Finding]]
    """The validity checks of a run on it: (plan, surface_height [m] or None, the run summary's
    measured values or None) -> findings (cosim.advice.check for the DEM's grain scales)."""
    steps: Callable[[RunPlan], tuple[float, int]]
    """(dt [s], steps per macro step) of the soil's own stepping (results.h5's dt and substeps)."""


def _dem_steps(plan: RunPlan) -> tuple[float, int]:
    """The DEM's step and substeps (the PID varies them); a mixed terrain's too."""
    return plan.dt, plan.substeps


def _analytic_steps(plan: RunPlan) -> tuple[float, int]:
    """The analytic terrain's wrench samples per macro step (it simulates no grains)."""
    return plan.macro_step / WRENCH_SAMPLES, WRENCH_SAMPLES


TERRAIN_MODELS: dict[str, TerrainModel] = {
    "dem": TerrainModel(_dem_soil, needs_bed=True, validity=_dem_validity, steps=_dem_steps),
    "analytic": TerrainModel(_analytic_soil, needs_bed=False, validity=_no_findings, steps=_analytic_steps),
    "scm": TerrainModel(_scm_soil, needs_bed=False, validity=_scm_validity, steps=scm_steps),
    "mixed": TerrainModel(_mixed_soil, needs_bed=True, validity=_mixed_validity, steps=_dem_steps),
}
"""The terrain models by [terrain] model name."""


def wheel_display_mesh(plan: RunPlan) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Display mesh of a plan's wheels, as results.h5 keeps it (wheels/mesh): vertices [m] (V, 3) in wheel
    frames, triangles (F, 3), owner wheel (V,); a mesh wheel's own scaled vertices and triangles."""
    vertices, triangles, owners = [], [], []
    count = 0
    for index, wheel in enumerate(plan.wheels):
        shape = wheel.shape
        v, t = shape.to_mesh(arc_segments=240) if hasattr(shape, "to_mesh") else (shape.vertices, shape.triangles)
        vertices.append(np.asarray(v, dtype=np.float64))
        triangles.append(np.asarray(t) + count)
        owners.append(np.full(len(v), index, dtype=np.int32))
        count += len(v)
    return np.concatenate(vertices), np.concatenate(triangles), np.concatenate(owners)


def used_mesh(mesh: tuple[np.ndarray, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A display mesh (vertices, triangles, owners: wheel_display_mesh) less the vertices no triangle uses,
    the triangles renumbered: one wheel whether its reader kept such vertices or not (results.h5 written
    before MeshWheel.load dropped them holds them)."""
    vertices, triangles, owners = mesh
    used = np.unique(triangles)
    index = np.full(len(vertices), -1, dtype=np.int64)
    index[used] = np.arange(len(used))
    return vertices[used], index[triangles], owners[used]


def validity(plan: RunPlan, surface_height: float, measured: dict | None = None) -> list[Finding]:
    """The validity findings of a run of `plan` on its terrain (cosim.advice.Finding), at its start
    (measured None) or from its summary (`measured`: its 'sinkage' and 'sinkage_tips' [m], 'slip' [-])."""
    return TERRAIN_MODELS[plan.terrain.model].validity(plan, surface_height, measured or {})


def needs_bed(plan: RunPlan) -> bool:
    """Whether the plan's terrain opens a settled bed (settled or reused before the system is built)."""
    return TERRAIN_MODELS[plan.terrain.model].needs_bed
