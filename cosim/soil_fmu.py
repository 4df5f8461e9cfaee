"""Export the DEM soil as an FMI 2.0 co-simulation FMU (built with pythonfmu).

An FMI tool then drives the soil like any other FMU: wheel kinematics in, wheel wrenches
out, one `doStep` per macro step. Variables, per wheel i (world frame, SI):

    inputs   wheel_<i>.position.{x,y,z} [m], wheel_<i>.orientation.{w,x,y,z} [-],
             wheel_<i>.velocity.{x,y,z} [m/s], wheel_<i>.angular_velocity.{x,y,z} [rad/s]
    outputs  wheel_<i>.force.{x,y,z} [N] and wheel_<i>.torque.{x,y,z} [N m] (about the hub,
             averaged over the step), wheel_<i>.sinkage [m], wheel_<i>.contact_count [-]
    params   gravity.{x,y,z} [m/s^2] (must match the bed), dem_step [s]

The FMU carries its settled bed (HDF5) and a JSON configuration as resources; it runs
in the importing tool's Python, which needs regolith-cosim installed. Build one with
`export_soil_fmu(...)`.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import asdict
from pathlib import Path

import numpy as np

CONFIG_NAME = "regolith_soil.json"
BED_NAME = "bed.h5"

_SCRIPT = '''"""regolith-cosim DEM soil as an FMI 2.0 co-simulation slave (generated)."""
from pythonfmu import Fmi2Slave

from cosim.soil_fmu import SoilFmuCore


class RegolithSoil(Fmi2Slave):
    author = "regolith-cosim"
    description = "DEM regolith soil: wheel kinematics in, wheel wrenches out"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.core = SoilFmuCore(self, self.resources)

    def exit_initialization_mode(self):
        self.core.initialize()

    def do_step(self, current_time, step_size):
        return self.core.do_step(current_time, step_size)
'''

AXES = ("x", "y", "z")


class SoilFmuCore:
    """Everything the generated slave does: variables, lazy soil set-up, stepping."""

    def __init__(self, slave, resources: str):
        from pythonfmu import Fmi2Causality, Fmi2Variability, Integer, Real

        with open(os.path.join(resources, CONFIG_NAME)) as f:
            self.config = json.load(f)
        self.resources = resources
        self.wheel_count = len(self.config["wheels"])
        n = self.wheel_count
        self.position = np.zeros((n, 3))
        self.orientation = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        self.velocity = np.zeros((n, 3))
        self.angular_velocity = np.zeros((n, 3))
        self.force = np.zeros((n, 3))
        self.torque = np.zeros((n, 3))
        self.sinkage = np.zeros(n)
        self.contacts = np.zeros(n, dtype=int)
        self.gravity = np.asarray(self.config["gravity"], dtype=float)
        self.dem_step = float(self.config["dem_step"])
        self.soil = None

        def real(name, array, index, causality, variability=None):
            def get():
                return float(array[index])

            def put(value):
                array[index] = value

            kwargs = dict(causality=causality, getter=get, setter=put)
            if variability is not None:
                kwargs["variability"] = variability
            slave.register_variable(Real(name, **kwargs))

        for i in range(n):
            for k, axis in enumerate(AXES):
                real(f"wheel_{i}.position.{axis}", self.position, (i, k), Fmi2Causality.input)
                real(f"wheel_{i}.velocity.{axis}", self.velocity, (i, k), Fmi2Causality.input)
                real(f"wheel_{i}.angular_velocity.{axis}", self.angular_velocity, (i, k), Fmi2Causality.input)
                real(f"wheel_{i}.force.{axis}", self.force, (i, k), Fmi2Causality.output)
                real(f"wheel_{i}.torque.{axis}", self.torque, (i, k), Fmi2Causality.output)
            for k, axis in enumerate(("w", "x", "y", "z")):
                real(f"wheel_{i}.orientation.{axis}", self.orientation, (i, k), Fmi2Causality.input)
            real(f"wheel_{i}.sinkage", self.sinkage, i, Fmi2Causality.output)
            slave.register_variable(Integer(f"wheel_{i}.contact_count", causality=Fmi2Causality.output,
                                            variability=Fmi2Variability.discrete,
                                            getter=lambda i=i: int(self.contacts[i])))
        for k, axis in enumerate(AXES):
            real(f"gravity.{axis}", self.gravity, k, Fmi2Causality.parameter, Fmi2Variability.tunable)
        slave.register_variable(Real("dem_step", causality=Fmi2Causality.parameter,
                                     variability=Fmi2Variability.tunable,
                                     getter=lambda: self.dem_step, setter=lambda v: setattr(self, "dem_step", v)))

    def initialize(self) -> None:
        """Load the bed, add the wheels and place them at the inputs' poses."""
        self.soil = make_dem_soil(os.path.join(self.resources, BED_NAME), self.config, self.dem_step)
        self.soil.set_gravity(self.gravity)
        self.soil.place_wheels(self._kinematics())

    def _kinematics(self):
        from .contract import WheelKinematics

        return [WheelKinematics(self.position[i], self.orientation[i], self.velocity[i], self.angular_velocity[i])
                for i in range(self.wheel_count)]

    def do_step(self, current_time: float, step_size: float) -> bool:
        if self.soil is None:
            self.initialize()
        wrenches = self.soil.advance(current_time + step_size, self._kinematics())
        for i, w in enumerate(wrenches):
            self.force[i] = w.force
            self.torque[i] = w.torque
            self.sinkage[i] = w.sinkage
            self.contacts[i] = w.contact_count
        return True


def make_dem_soil(bed_file, config: dict, dem_step: float):
    """A DemSoil from a saved bed plus the wheels described in `config` (see export_soil_fmu)."""
    from soil import GrouserWheel, Material, MeshWheel
    from .dem_soil import DemSoil

    shapes = [MeshWheel(np.asarray(w["vertices"]), np.asarray(w["triangles"])) if "vertices" in w
              else GrouserWheel(**w["shape"]) for w in config["wheels"]]
    return DemSoil.from_bed(bed_file, shapes, Material(**config["wheels"][0]["material"]), dem_step,
                            surface_height=config["surface_height"], device=config.get("device"),
                            precision=config["precision"], wall_clearance=config.get("wall_clearance"))


def export_soil_fmu(bed_file, wheels, wheel_material, dem_step: float, destination, surface_height: float,
                    precision: str = "mixed", device: str | None = "cpu") -> Path:
    """Build an FMI 2.0 co-simulation FMU of the DEM soil.

    bed_file: a settled bed saved with soil.bed.save_bed; wheels: GrouserWheel or MeshWheel
    shapes (one per FMU wheel); wheel_material: soil.Material of the wheels; dem_step: DEM
    step [s]; destination: the .fmu path; surface_height: undisturbed surface z [m].
    Returns the FMU path.
    """
    from pythonfmu.builder import FmuBuilder
    from soil import GrouserWheel
    from soil.bed import load_bed
    from soil.files import atomic_path

    _, saved = load_bed(bed_file)  # refuse a file that is not a bed, early
    if not wheels:
        raise ValueError("export_soil_fmu needs at least one wheel")
    if not dem_step > 0:
        raise ValueError(f"dem_step must be > 0 [s], got {dem_step!r}")
    import h5py

    with h5py.File(bed_file, "r") as f:
        gravity = [float(g) for g in f.attrs["gravity"]]
    described = []
    for shape in wheels:
        entry = {"material": asdict(wheel_material)}
        if isinstance(shape, GrouserWheel):
            entry["shape"] = asdict(shape)
        else:
            entry["vertices"] = shape.vertices.tolist()
            entry["triangles"] = shape.triangles.tolist()
        described.append(entry)
    config = {"wheels": described, "gravity": gravity, "dem_step": float(dem_step), "precision": precision,
              "device": device, "surface_height": float(surface_height)}
    destination = Path(destination)
    destination.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="regolith_fmu_") as folder:
        folder = Path(folder)
        script = folder / "RegolithSoil.py"
        script.write_text(_SCRIPT)
        (folder / CONFIG_NAME).write_text(json.dumps(config))
        shutil.copy2(bed_file, folder / BED_NAME)
        built = FmuBuilder.build_FMU(script, dest=folder / "out",
                                     project_files=[folder / CONFIG_NAME, folder / BED_NAME],
                                     canHandleVariableCommunicationStepSize=True)
        with atomic_path(destination, ".fmu.tmp") as temporary:
            shutil.copy2(built, temporary)
    return destination
