"""The DEM soil exported as an FMI 2.0 co-simulation FMU, loaded and stepped with fmpy."""

import json
import math

import numpy as np
import pytest

pytest.importorskip("pythonfmu")
fmpy = pytest.importorskip("fmpy")

from soil import GrouserWheel, Material, Simulation  # noqa: E402
from soil.bed import BedSpec, bed_metrics, build_bed, save_bed, settle  # noqa: E402
from cosim.contract import WheelKinematics  # noqa: E402
from cosim.soil_fmu import export_soil_fmu, make_dem_soil  # noqa: E402

WHEEL = GrouserWheel(radius=0.02, width=0.015, grouser_count=8, grouser_height=0.002, grouser_thickness=0.0015)
WHEEL_MATERIAL = Material(youngs_modulus=1e6, restitution=0.3)


@pytest.fixture(scope="module")
def soil_fmu(tmp_path_factory):
    folder = tmp_path_factory.mktemp("soil_fmu")
    spec = BedSpec(length=0.07, width=0.04, depth=0.015, radius_mean=3e-3, radius_spread=0.1,
                   material=Material(youngs_modulus=1e6, restitution=0.3))
    sim = Simulation(*build_bed(spec, 9.81).finalize("cpu", "double"))
    settle(sim, 5e-5, ke_ratio=1e-2, max_time=0.5)
    surface = bed_metrics(sim, spec, margin=0.0)["height"]
    save_bed(folder / "bed.h5", sim, spec)
    path = export_soil_fmu(folder / "bed.h5", [WHEEL], WHEEL_MATERIAL, 5e-5, folder / "soil.fmu", surface,
                           precision="double", device="cpu")
    return path, folder / "bed.h5", surface


def test_soil_fmu_describes_wheel_variables(soil_fmu):
    path, _, _ = soil_fmu
    description = fmpy.read_model_description(str(path))
    assert description.fmiVersion == "2.0"
    assert description.coSimulation.canHandleVariableCommunicationStepSize
    by_name = {v.name: v for v in description.modelVariables}
    for name in ("wheel_0.position.z", "wheel_0.orientation.w", "wheel_0.angular_velocity.y"):
        assert by_name[name].causality == "input"
    for name in ("wheel_0.force.z", "wheel_0.torque.y", "wheel_0.sinkage", "wheel_0.contact_count"):
        assert by_name[name].causality == "output"
    assert by_name["gravity.z"].causality == "parameter"


def test_soil_fmu_steps_like_the_soil_in_process(soil_fmu):
    """The FMU, stepped by fmpy, gives the same wrenches as the same soil used directly:
    a wheel pressed into the bed and pulled along; the bed pushes it up."""
    from fmpy.fmi2 import FMU2Slave
    from fmpy import extract

    path, bed, surface = soil_fmu
    description = fmpy.read_model_description(str(path))
    refs = {v.name: v.valueReference for v in description.modelVariables}
    unzipped = extract(str(path))
    fmu = FMU2Slave(guid=description.guid, unzipDirectory=unzipped,
                    modelIdentifier=description.coSimulation.modelIdentifier, instanceName="soil")
    hub = np.array([0.035, 0.02, surface + WHEEL.radius - 1e-3])
    velocity = np.array([0.01, 0.0, 0.0])
    spin = np.array([0.0, 0.5, 0.0])
    fmu.instantiate()
    fmu.setupExperiment(startTime=0.0)
    fmu.enterInitializationMode()

    def set_inputs(t):
        position = hub + velocity * t
        half = 0.5 * spin[1] * t
        values = {**{f"wheel_0.position.{a}": position[k] for k, a in enumerate("xyz")},
                  **{f"wheel_0.velocity.{a}": velocity[k] for k, a in enumerate("xyz")},
                  **{f"wheel_0.angular_velocity.{a}": spin[k] for k, a in enumerate("xyz")},
                  "wheel_0.orientation.w": math.cos(half), "wheel_0.orientation.x": 0.0,
                  "wheel_0.orientation.y": math.sin(half), "wheel_0.orientation.z": 0.0}
        fmu.setReal([refs[k] for k in values], list(values.values()))

    set_inputs(0.0)
    fmu.exitInitializationMode()
    macro = 5e-4
    fmu_forces = []
    for step in range(4):
        t = step * macro
        set_inputs(t)
        fmu.doStep(currentCommunicationPoint=t, communicationStepSize=macro)
        fmu_forces.append(fmu.getReal([refs[f"wheel_0.force.{a}"] for a in "xyz"]))
    contacts = fmu.getInteger([refs["wheel_0.contact_count"]])[0]
    fmu.terminate()
    fmu.freeInstance()

    with open(f"{unzipped}/resources/regolith_soil.json") as f:
        config = json.load(f)
    soil = make_dem_soil(bed, config, 5e-5)

    def kinematics(t):
        half = 0.5 * spin[1] * t
        return [WheelKinematics(hub + velocity * t, (math.cos(half), 0, math.sin(half), 0), velocity, spin)]

    soil.place_wheels(kinematics(0.0))
    direct = [soil.advance((step + 1) * macro, kinematics(step * macro))[0].force for step in range(4)]
    assert contacts > 0
    assert fmu_forces[-1][2] > 0, "the bed pushes the wheel up"
    np.testing.assert_allclose(np.array(fmu_forces), np.array(direct), rtol=1e-12, atol=1e-15)
