"""What a soil FMU carries: the settled bed and the soil configuration (resources/soil.json).

`soil_config_from(path)` is the one place that reads a scene file or a run folder;
`soil_from_config(config)` builds the DemSoil the soil server steps.
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
    from soil import ContactLaw, GrouserWheel, Material, MeshWheel

CONFIG_FORMAT = "regolith-cosim soil FMU 1"


@dataclass
class SoilFmuConfig:
    """Everything an exported soil FMU needs (SI units)."""

    bed_file: str
    """A settled bed saved by soil.bed.save_bed (its grains, walls, materials and gravity)."""
    wheel: GrouserWheel | MeshWheel
    """Shape of every wheel: soil.GrouserWheel or soil.MeshWheel."""
    wheel_material: Material
    """soil.Material of the wheels."""
    dem_step: float
    """DEM step [s]; a macro step is split into whole DEM steps of at most this length."""
    surface_height: float
    """Undisturbed soil surface z [m] (sinkage is measured from it)."""
    law: ContactLaw | None = None
    """soil.ContactLaw switches; None: rolling and cohesion on when a material uses them."""
    precision: str = "mixed"
    """Floating-point mode of the DEM: single, double or mixed."""
    device: str = "cpu"
    """Warp device of the soil server by default: cpu, cuda or cuda:N."""
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

    def __post_init__(self):
        if not (isinstance(self.dem_step, (int, float)) and math.isfinite(self.dem_step) and self.dem_step > 0):
            raise ArgumentError(f"dem_step must be > 0 [s], got {self.dem_step!r}")
        if self.precision not in ("single", "double", "mixed"):
            raise ArgumentError(f"precision must be single, double or mixed, got {self.precision!r}")
        if self.macro_step is not None and not self.macro_step > 0:
            raise ArgumentError(f"macro_step must be > 0 [s], got {self.macro_step!r}")
        if not os.path.isfile(self.bed_file):
            raise FileNotFoundError(f"bed file not found: {self.bed_file!r}")


def soil_config_from(path, bed_folder=None) -> SoilFmuConfig:
    """The soil FMU configuration of a scene file (TOML) or a run folder (`cosim run --out`).

    Both go through the run layer: the scene is resolved into a plan (cosim.plan), and the bed
    is the run's (a run folder: the bed its run.json names, else its bed.h5) or the plan's
    (its bed.bed_file, or a bed settled now in `bed_folder`, cached there by the bed key).
    """
    from cosim.beds import bed_from_file, settled_bed
    from cosim.plan import load_plan

    path = os.fspath(path)
    if os.path.isdir(path):
        scene_file = os.path.join(path, "scene.toml")
        if not os.path.isfile(scene_file):
            raise FileNotFoundError(f"{path!r} is not a run folder: it has no scene.toml")
        plan = load_plan(scene_file)
        bed_path = os.path.join(path, "bed.h5")
        run_file = os.path.join(path, "run.json")
        if os.path.isfile(run_file):
            with open(run_file) as f:
                bed_path = json.load(f).get("bed", {}).get("path") or bed_path
        if not os.path.isfile(bed_path):
            raise FileNotFoundError(f"the run folder {path!r} has no settled bed ({bed_path!r} is missing)")
        bed = bed_from_file(bed_path)
    else:
        plan = load_plan(path)
        _require_single_wheel(plan, path)  # before a bed is settled
        if bed_folder is None and not plan.bed.bed_file:
            raise ArgumentError("a scene without bed.bed_file needs a bed_folder to settle its bed in")
        bed = settled_bed(plan, os.fspath(bed_folder) if bed_folder else "")
    _require_single_wheel(plan, path)
    assert plan.testbed is not None
    return SoilFmuConfig(
        bed_file=os.path.abspath(bed.path),
        wheel=plan.wheel.shape,
        wheel_material=plan.wheel.material,
        dem_step=plan.dt,
        surface_height=bed.surface_height,
        law=plan.law,
        precision=plan.precision,
        device=plan.device,
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


def bed_surface_height(bed_file) -> float:
    """The saved height metric of a bed file [m] (soil.bed.bed_metrics)."""
    from soil.bed import read_bed_header

    metrics = read_bed_header(bed_file)["metrics"]
    if "height" not in metrics:
        raise ArgumentError(f"the bed file {bed_file!r} has no height metric: give surface_height [m]")
    return float(metrics["height"])


# -- resources/soil.json --------------------------------------------------------------------


def config_to_json(config: SoilFmuConfig, wheel_count: int) -> dict:
    """The soil server's configuration (resources/soil.json); the bed travels as resources/bed.h5."""
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
    return {
        "format": CONFIG_FORMAT,
        "name": config.name,
        "wheel_count": int(wheel_count),
        "wheel": wheel,
        "wheel_material": asdict(config.wheel_material),
        "law": asdict(config.law) if config.law else None,
        "dem_step": float(config.dem_step),
        "surface_height": float(config.surface_height),
        "precision": config.precision,
        "device": config.device,
        "order_seed": config.order_seed,
        "gravity": _bed_gravity(config.bed_file),
        "step_control": config.step_control,
        "extra": config.extra,
    }


def _bed_gravity(bed_file) -> list[float]:
    from soil.bed import read_bed_header

    return [float(g) for g in read_bed_header(bed_file)["gravity"]]


def soil_from_config(data: dict, bed_file, dem_step: float | None = None, device: str | None = None):
    """The DemSoil of a soil.json configuration on `bed_file` (what the soil server steps)."""
    from cosim.dem_soil import DemSoil
    from soil import ContactLaw, GrouserWheel, Material, MeshWheel

    if data.get("format") != CONFIG_FORMAT:
        raise DamagedFileError(
            f"not a soil FMU configuration (format {data.get('format')!r}, expected {CONFIG_FORMAT!r}): "
            "export the FMU again with this regolith-cosim"
        )
    wheel = dict(data["wheel"])
    kind = wheel.pop("type")
    shape: GrouserWheel | MeshWheel
    if kind == "grouser":
        shape = GrouserWheel(**wheel)
    else:
        shape = MeshWheel(np.asarray(wheel["vertices"]), np.asarray(wheel["triangles"]), name=wheel.get("name", "mesh"))
    law = ContactLaw(**data["law"]) if data.get("law") else None
    soil = DemSoil.from_bed(
        bed_file,
        [shape] * int(data["wheel_count"]),
        Material(**data["wheel_material"]),
        dem_step if dem_step is not None else float(data["dem_step"]),
        surface_height=float(data["surface_height"]),
        device=device or data["device"],
        precision=data["precision"],
        order_seed=data.get("order_seed"),
        law=law,
    )
    if data.get("step_control"):  # PID substeps in every macro step, the first one dem_step long
        from soil import StepController

        soil.sim.enable_step_control(StepController(**data["step_control"], dt_initial=soil.dt))
    return soil


def _require_single_wheel(plan, path) -> None:
    """A soil FMU serves the wheels of a [testbed] scene; a rover scene ([rover]) is refused."""
    if plan.testbed is None:
        from ..scene import SceneError

        raise SceneError(
            [
                "testbed: a soil FMU is exported from a single-wheel scene ([testbed]); "
                "this scene drives a rover ([rover]): run it with `cosim run`"
            ],
            os.fspath(path),
        )
