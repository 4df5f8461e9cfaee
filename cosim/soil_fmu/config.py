"""What a soil FMU carries: the soil configuration (resources/soil.json) and, on the DEM, the
settled bed (resources/bed.h5).

`soil_config_from(path)` is the one place that reads a scene file or a run folder;
`soil_from_config(config)` builds the soil the soil server steps: a DemSoil on the bed's grains,
or an ScmSoil (the Soil Contact Model, [terrain] model = "scm": no bed, its parameters in soil.json).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from soil.errors import ArgumentError, DamagedFileError

if TYPE_CHECKING:  # soil (and Warp) load only when a soil is built
    from cosim.scm_soil import ScmSettings
    from soil import ContactLaw, GrouserWheel, Material, MeshWheel

CONFIG_FORMAT = "regolith-cosim soil FMU 2"
"""The format of resources/soil.json: 2 names its terrain ('dem' or 'scm') and carries the SCM terrain."""
READABLE_FORMATS = ("regolith-cosim soil FMU 1", CONFIG_FORMAT)
"""The formats a soil server reads (format 1: a DEM soil)."""
TERRAINS = ("dem", "scm")
"""The terrain models a soil FMU steps (cosim.system.TERRAIN_MODELS' 'dem' and 'scm')."""
SCM_WHEEL_SPACING = 4.0
"""Distance between the hubs of neighbouring wheels at the start on one SCM terrain, in outer radii [-]
(their patches and rims apart); the SCM window is lengthened along x by their span."""


@dataclass
class SoilFmuConfig:
    """Everything an exported soil FMU needs (SI units)."""

    bed_file: str | None
    """A settled bed saved by soil.bed.save_bed (its grains, walls, materials and gravity); None on
    the SCM terrain (no grains)."""
    wheel: GrouserWheel | MeshWheel
    """Shape of every wheel: soil.GrouserWheel or soil.MeshWheel."""
    wheel_material: Material | None
    """soil.Material of the wheels (the DEM's contacts; SCM does not use it)."""
    dem_step: float
    """The soil's inner step [s]: a macro step is split into whole DEM steps of at most this length
    (on SCM: into equal SCM steps of at most this length)."""
    surface_height: float
    """Undisturbed soil surface z [m] (sinkage is measured from it)."""
    law: ContactLaw | None = None
    """soil.ContactLaw switches; None: rolling and cohesion on when a material uses them."""
    precision: str = "mixed"
    """Floating-point mode of the DEM: single, double or mixed."""
    device: str = "cpu"
    """Warp device of the soil server by default: 'default' (a GPU on the machine that runs the soil, if it
    has one, else the CPU), 'cpu', 'cuda' or 'cuda:N'."""
    order_seed: int | None = None
    """Permutation of the grain order (summation order only), as in the scene."""
    macro_step: float | None = None
    """Communication step of the default experiment [s]; None: 10 DEM steps."""
    duration: float = 1.0
    """Stop time of the default experiment [s]."""
    start_x: float | None = None
    """Hub x of a single wheel at the start [m]; None: outer radius + 6 grain radii from the bed's end."""
    name: str = "soil"
    """Label (modelDescription description)."""
    step_control: dict | None = None
    """The PID step control of the DEM (run.step_control = "pid"): {'tolerance' [-], 'dt_min' [s]
    or None, 'dt_max' [s] or None} (soil.StepController); None: fixed steps of dem_step."""
    python: str | None = None
    """The soil server's Python by default; None: the Python that exports."""
    extra: dict = field(default_factory=dict)
    """Free-form notes stored with the configuration."""
    terrain: str = "dem"
    """The terrain the server steps: 'dem' (the bed's grains, cosim.dem_soil.DemSoil) or 'scm' (the
    Soil Contact Model of `scm`, cosim.scm_soil.ScmSoil)."""
    scm: ScmSettings | None = None
    """terrain 'scm': its parameters, node window [m] and surface height [m] (cosim.scm_soil.ScmSettings;
    its time_step is ignored: dem_step is the SCM step)."""
    gravity: tuple[float, ...] | None = None
    """terrain 'scm': the scene's gravity vector [m/s^2], at which the SCM parameters hold (the DEM's
    gravity is its bed's)."""
    findings: list[dict] | None = None
    """The scene's validity findings (cosim.advice.Finding.as_dict, as run.json stores them): those a
    run of the scene starts with (cosim.system.validity: the DEM's grain scales, SCM's checks), or a
    run folder's own; None: not judged (a configuration made by hand). soil.json carries them and
    their verdict, the export warns of those out of range and the FMU at its initialization."""
    unjudged: list[str] | None = None
    """The checks a run judges on its own measurements only (cosim.advice.judged_after_the_run: e.g. the PID
    step control's contact resolution, SCM's calibration depth), which no one judges for the FMU: its
    verdict names them, so that "valid" is never said of them."""

    def __post_init__(self):
        if not (isinstance(self.dem_step, (int, float)) and math.isfinite(self.dem_step) and self.dem_step > 0):
            raise ArgumentError(f"dem_step must be > 0 [s], got {self.dem_step!r}")
        if self.precision not in ("single", "double", "mixed"):
            raise ArgumentError(f"precision must be single, double or mixed, got {self.precision!r}")
        if self.macro_step is not None and not self.macro_step > 0:
            raise ArgumentError(f"macro_step must be > 0 [s], got {self.macro_step!r}")
        if self.terrain not in TERRAINS:
            raise ArgumentError(f"terrain must be one of {', '.join(TERRAINS)}, got {self.terrain!r}")
        if self.terrain == "scm":
            if self.scm is None:
                raise ArgumentError("terrain 'scm' needs scm (cosim.scm_soil.ScmSettings: its parameters and window)")
            gravity = np.asarray(self.gravity if self.gravity is not None else [], dtype=np.float64)
            if gravity.shape != (3,) or not np.all(np.isfinite(gravity)):
                raise ArgumentError(f"terrain 'scm' needs gravity, 3 finite numbers [m/s^2], got {self.gravity!r}")
        else:
            if self.bed_file is None or not os.path.isfile(self.bed_file):
                raise FileNotFoundError(f"bed file not found: {self.bed_file!r}")
            if self.wheel_material is None:
                raise ArgumentError("the DEM soil needs wheel_material (soil.Material of the wheels)")


def soil_config_from(path, bed_folder=None) -> SoilFmuConfig:
    """The soil FMU configuration of a scene file (TOML) or a run folder (`cosim run --out`).

    Both go through the run layer: the scene is resolved into a plan (cosim.plan). On the DEM the
    bed is the run's (a run folder: the bed its run.json names, else its bed.h5) or the plan's
    (its bed.bed_file, or a bed settled now in `bed_folder`, cached there by the bed key); on SCM
    ([terrain] model = "scm") there is no bed: the plan's SCM terrain goes into the configuration.
    The configuration's findings are the scene's validity checks at the start of a run (a run
    folder's: those its run.json holds).
    """
    from cosim.beds import bed_from_file, settled_bed
    from cosim.plan import load_plan

    path = os.fspath(path)
    run_folder = os.path.isdir(path)
    scene_file = os.path.join(path, "scene.toml") if run_folder else path
    if run_folder and not os.path.isfile(scene_file):
        raise ArgumentError(f"{path!r} is not a run folder: it has no scene.toml")
    plan = load_plan(scene_file)
    _require_fmu_scene(plan, path)  # before a bed is settled
    assert plan.testbed is not None
    if plan.terrain.model == "scm":
        from cosim.scm_soil import check_scm_grid

        check_scm_grid(plan, memory=False)  # the server allocates it, on its own machine
        config = _scm_config(plan)
        config.findings = _findings(plan, config.surface_height, path if run_folder else None)
        config.unjudged = _unjudged(plan, config.findings)
        return config
    if run_folder:
        bed_path = os.path.join(path, "bed.h5")
        run_file = os.path.join(path, "run.json")
        if os.path.isfile(run_file):
            with open(run_file) as f:
                bed_path = json.load(f).get("bed", {}).get("path") or bed_path
        if not os.path.isfile(bed_path):
            raise FileNotFoundError(f"the run folder {path!r} has no settled bed ({bed_path!r} is missing)")
        bed = bed_from_file(bed_path)
    else:
        if bed_folder is None and not plan.bed.bed_file:
            raise ArgumentError("a scene without bed.bed_file needs a bed_folder to settle its bed in")
        bed = settled_bed(plan, os.fspath(bed_folder) if bed_folder else "")
    findings = _findings(plan, bed.surface_height, path if run_folder else None)
    return SoilFmuConfig(
        findings=findings,
        unjudged=_unjudged(plan, findings),
        bed_file=os.path.abspath(bed.path),
        wheel=plan.wheel.shape,
        wheel_material=plan.wheel.material,
        dem_step=plan.dt,
        surface_height=bed.surface_height,
        law=plan.law,
        precision=plan.precision,
        device=plan.scene.scene.device,  # resolved where the soil runs ('default': a GPU there if any)
        order_seed=plan.order_seed,
        macro_step=plan.macro_step,
        duration=plan.scene.run.duration,
        start_x=plan.testbed.start_x,
        name=plan.name,
        step_control=(
            dict(tolerance=plan.tolerance, dt_min=plan.dt_min, dt_max=plan.dt_max)
            if plan.step_control == "pid"
            else None
        ),
    )


def _findings(plan, surface_height: float, run_folder: str | None) -> list[dict]:
    """The validity findings (dicts) of a run of `plan` at its start, on a bed whose surface is at
    `surface_height` [m] (cosim.system.validity, as cosim.launch judges a run); a run folder's own from
    its run.json: a finished run's summary's (judged on what it measured) or, for a run that did not
    finish (diverged, interrupted: its summary judged part of a run), those it started with."""
    from cosim.advice import Finding
    from cosim.system import validity

    if run_folder is not None:
        try:
            with open(os.path.join(run_folder, "run.json")) as f:
                record = json.load(f)
            from cosim.launch import FINISHED

            summary = record.get("summary") if record.get("status") in FINISHED else None  # judged on a whole run
            stored = summary.get("findings") if isinstance(summary, dict) else None
            stored = stored if isinstance(stored, list) and stored else record.get("findings")
            if isinstance(stored, list):
                return [Finding(**finding).as_dict() for finding in stored]  # a garbled entry: judged again
        except (OSError, ValueError, TypeError, AttributeError):
            pass  # no run.json, or not the one a run wrote: judge the scene again
    return [finding.as_dict() for finding in validity(plan, surface_height)]


def _unjudged(plan, findings: list[dict]) -> list[str]:
    """The checks only a run's measurements judge that `findings` do not hold (a finished run's hold them)."""
    from cosim.advice import Finding, judged_after_the_run

    return [check for check, _ in judged_after_the_run(plan, [Finding(**f) for f in findings])]


def verdict(findings: list[dict] | None, unjudged: list[str] | None = None) -> str | None:
    """'valid', 'out of range: CHECK, ...' (cosim.advice.verdict) of findings as dicts, followed by the
    checks not judged without a run's measurements (`unjudged`); None for None."""
    if findings is None:
        return None
    from cosim.advice import Finding
    from cosim.advice import verdict as judged

    text = judged([Finding(**finding) for finding in findings])
    return f"{text} (not judged without a run's measurements: {', '.join(unjudged)})" if unjudged else text


def _scm_config(plan) -> SoilFmuConfig:
    """The SCM soil FMU of a single-wheel plan on [terrain] model = "scm": the run's SCM terrain
    (cosim.scm_soil.scm_settings, as cosim.system builds it), its step the FMU's dem_step."""
    from cosim.scm_calibration import warn_gravity
    from cosim.scm_soil import scm_settings

    assert plan.testbed is not None
    surface = float(dict(plan.terrain.parameters).get("surface_height", 0.0))
    extra = {}
    if plan.terrain.calibration_gravity is not None:  # provenance: the soil's parameters came from a calibration
        section = plan.scene.terrain
        calibration = str(section.calibration if section else "")
        warn_gravity(plan.terrain.calibration_gravity, plan.g, calibration)
        extra = {"scm_calibration": calibration, "scm_calibration_gravity": plan.terrain.calibration_gravity}
    settings = scm_settings(plan, [0], surface)
    return SoilFmuConfig(
        bed_file=None,
        wheel=plan.wheel.shape,
        wheel_material=plan.wheel.material,
        dem_step=settings.time_step,
        surface_height=settings.surface_height,
        precision=plan.precision,
        device=plan.scene.scene.device,  # resolved where the soil runs ('default': a GPU there if any)
        macro_step=plan.macro_step,
        duration=plan.scene.run.duration,
        start_x=plan.testbed.start_x,
        name=plan.name,
        terrain="scm",
        scm=settings,
        gravity=tuple(float(g) for g in plan.gravity),
        extra=extra,
    )


def bed_surface_height(bed_file) -> float:
    """The saved height metric of a bed file [m] (soil.bed.bed_metrics)."""
    from soil.bed import read_bed_header

    metrics = read_bed_header(bed_file)["metrics"]
    if "height" not in metrics:
        raise ArgumentError(f"the bed file {bed_file!r} has no height metric: give surface_height [m]")
    return float(metrics["height"])


# -- resources/soil.json --------------------------------------------------------------------


def config_to_json(config: SoilFmuConfig, wheel_count: int) -> dict:
    """The soil server's configuration (resources/soil.json); a DEM's bed travels as resources/bed.h5."""
    from soil import GrouserWheel

    shape = config.wheel
    if isinstance(shape, GrouserWheel):
        wheel = {"type": "grouser", **asdict(shape)}
    else:
        wheel = {
            "type": "mesh",
            "name": shape.name,
            "vertices": shape.vertices.tolist(),
            "triangles": shape.triangles.tolist(),
        }
    from soil.geometry import GROUSER_WHEEL_UNITS
    from soil.materials import MATERIAL_UNITS
    from soil.scm.terrain import SCM_PARAMETER_UNITS

    units: dict = {
        "wheel_count": "count",
        "wheel": GROUSER_WHEEL_UNITS if isinstance(shape, GrouserWheel) else {"vertices": "m", "triangles": "1"},
        "dem_step": "s",
        "surface_height": "m",
        "gravity": "m/s^2",
    }
    data = {
        "format": CONFIG_FORMAT,
        "units": units,  # of every number below (SI; "1": flags and indices); readers pass it over
        "terrain": config.terrain,
        "name": config.name,
        "wheel_count": int(wheel_count),
        "wheel": wheel,
        "dem_step": float(config.dem_step),
        "surface_height": float(config.surface_height),
        "precision": config.precision,
        "device": config.device,
        "extra": config.extra,
    }
    if config.findings is not None:  # what `cosim advise` says of the scene, for the FMU's user
        from cosim.folders import finite_or_null

        # a number that is not finite as null, as run.json writes it (strict JSON readers refuse NaN)
        data.update(
            findings=finite_or_null(config.findings),
            unjudged=list(config.unjudged or []),
            validity=verdict(config.findings, config.unjudged),
        )
        units["findings"] = "each finding's own unit (of its value and limit)"
        units["unjudged"] = "none: names of validity checks"
    if config.terrain == "scm":
        assert config.scm is not None and config.gravity is not None  # SoilFmuConfig checks them
        length, width = config.scm.window
        data.update(
            scm={
                "parameters": asdict(config.scm.parameters),
                "window": [float(length + scm_wheels_span(shape, wheel_count)), float(width)],
            },
            rim_radius=rim_radius(shape),
            gravity=[float(g) for g in config.gravity],
        )
        units.update(scm={"parameters": SCM_PARAMETER_UNITS, "window": "m"}, rim_radius="m")
        return data
    data.update(
        wheel_material=asdict(config.wheel_material) if config.wheel_material else None,
        law=asdict(config.law) if config.law else None,
        order_seed=config.order_seed,
        gravity=_bed_gravity(config.bed_file),
        step_control=config.step_control,
    )
    units.update(
        wheel_material=MATERIAL_UNITS,
        law=dict.fromkeys(asdict(config.law) if config.law else (), "1"),  # switches
        order_seed="1",
        step_control={"tolerance": "1", "dt_min": "s", "dt_max": "s"},
    )
    return data


def rim_radius(shape) -> float:
    """The rim radius [m] of a wheel shape, as the run plan takes it (the sinkage's reference): a
    grousered wheel's rim, a mesh wheel's outer radius (cosim.plan.WheelPlan)."""
    from soil import GrouserWheel

    return float(shape.radius if isinstance(shape, GrouserWheel) else shape.outer_radius)


def scm_server_grid(config, wheel_count: int) -> dict:
    """The SCM grid an exported FMU's server allocates for `wheel_count` wheels (its window holds them
    side by side, scm_wheels_span): refused here when Warp cannot index it (soil.scm.check_grid; its
    memory is judged where the server runs). Returns nodes [-], window [m] (length, width),
    gpu_bytes and gpu_host_bytes [B] (a server on a GPU: device memory and the host's copies) and
    cpu_bytes [B] (a server on the CPU: all of it in host memory), as soil.scm.grid_memory counts them."""
    from soil.scm import check_grid, grid_memory, grid_shape

    assert config.scm is not None
    length, width = config.scm.window
    window = (float(length + scm_wheels_span(config.wheel, wheel_count)), float(width))
    spacing = float(config.scm.parameters.node_spacing)
    check_grid(
        window,
        spacing,
        config.precision,
        config.device,
        what=f"the FMU's SCM grid for {wheel_count} wheel(s) (window {window[0]:.4g} x {window[1]:.4g} m at "
        f"spacing {spacing:.3g} m)",
        keys=("terrain.node_spacing", "terrain.window_length, terrain.window_width, or fewer --wheels"),
        memory=False,
    )
    rows, columns = grid_shape(window, spacing)
    nodes = rows * columns
    gpu_bytes, gpu_host_bytes = grid_memory(nodes, config.precision, "cuda")
    cpu_bytes = grid_memory(nodes, config.precision, "cpu")[1]
    return {
        "nodes": nodes,
        "window": window,
        "gpu_bytes": gpu_bytes,
        "gpu_host_bytes": gpu_host_bytes,
        "cpu_bytes": cpu_bytes,
    }


def scm_wheels_span(shape, wheel_count: int) -> float:
    """The distance along x [m] from the first to the last wheel's hub at the start on one SCM terrain."""
    return (wheel_count - 1) * SCM_WHEEL_SPACING * float(shape.outer_radius)


def _bed_gravity(bed_file) -> list[float]:
    from soil.bed import read_bed_header

    return [float(g) for g in read_bed_header(bed_file)["gravity"]]


def _wheel_shape(wheel: dict):
    from soil import GrouserWheel, MeshWheel

    wheel = dict(wheel)
    kind = wheel.pop("type")
    if kind == "grouser":
        return GrouserWheel(**wheel)
    shape = MeshWheel(np.asarray(wheel["vertices"]), np.asarray(wheel["triangles"]), name=wheel.get("name", "mesh"))
    shape.check_wheel_shape()  # as a scene's mesh is judged when read (an FMU exported before could hold another)
    return shape


def soil_from_config(data: dict, bed_file, dem_step: float | None = None, device: str | None = None):
    """The soil of a soil.json configuration (what the soil server steps): a DemSoil on `bed_file`,
    or, for terrain 'scm', an ScmSoil (`bed_file` unused, may be None). `dem_step` [s]: the inner step
    (DEM or SCM) instead of the configuration's; `device`: the Warp device instead of its own."""
    if data.get("format") not in READABLE_FORMATS:
        raise DamagedFileError(
            f"not a soil FMU configuration (format {data.get('format')!r}, expected {CONFIG_FORMAT!r}): "
            "export the FMU again with this regolith-cosim"
        )
    terrain = data.get("terrain", "dem")
    if terrain not in TERRAINS:
        raise DamagedFileError(
            f"the soil FMU configuration names terrain {terrain!r}, this regolith-cosim steps {', '.join(TERRAINS)}"
        )
    from cosim.probe import resolve_device

    step = dem_step if dem_step is not None else float(data["dem_step"])
    shape = _wheel_shape(data["wheel"])
    device = resolve_device(device or data["device"], "device")  # the configuration's may be 'default'

    if terrain == "scm":
        return _scm_soil(data, shape, step, device)
    from cosim.dem_soil import DemSoil
    from soil import ContactLaw, Material

    law = ContactLaw(**data["law"]) if data.get("law") else None
    soil = DemSoil.from_bed(
        bed_file,
        [shape] * int(data["wheel_count"]),
        Material(**data["wheel_material"]),
        step,
        surface_height=float(data["surface_height"]),
        device=device,
        precision=data["precision"],
        order_seed=data.get("order_seed"),
        law=law,
    )
    if data.get("step_control"):  # PID substeps in every macro step, the first one dem_step long
        from soil import StepController

        soil.sim.enable_step_control(StepController(**data["step_control"], dt_initial=soil.dt))
    return soil


def _scm_soil(data: dict, shape, time_step: float, device: str):
    """The ScmSoil of an SCM configuration: every wheel of `shape` on one terrain, in SCM steps of at
    most `time_step` [s]."""
    from cosim.scm_soil import ScmSettings, ScmSoil
    from soil.scm import ScmParameters

    scm = data["scm"]
    length, width = (float(size) for size in scm["window"])
    settings = ScmSettings(
        ScmParameters(**scm["parameters"]), (length, width), time_step, float(data["surface_height"])
    )
    count = int(data["wheel_count"])
    return ScmSoil.build(settings, [shape] * count, [float(data["rim_radius"])] * count, device, data["precision"])


def _require_fmu_scene(plan, path) -> None:
    """A soil FMU serves the wheels of a [testbed] scene on one terrain model, the DEM or SCM: a rover
    scene ([rover]), per-wheel terrains (terrain.wheels) and the analytic terrain are refused."""
    from ..scene import SceneError

    problems = []
    if plan.terrain.model == "mixed":
        problems.append(
            "terrain.wheels: a soil FMU steps one terrain model for all its wheels; this scene puts some "
            'wheels on the DEM and others on SCM: export one FMU per model ([terrain] model = "dem" or "scm")'
        )
    elif plan.terrain.model not in TERRAINS:
        problems.append(
            f"terrain.model: a soil FMU steps the DEM or SCM terrain, not {plan.terrain.model!r} "
            '([terrain] model = "dem" or "scm")'
        )
    if plan.testbed is None:
        problems.append(
            "testbed: a soil FMU is exported from a single-wheel scene ([testbed]); "
            "this scene drives a rover ([rover]): run it with `cosim run`"
        )
    if problems:
        raise SceneError(problems, os.fspath(path))
