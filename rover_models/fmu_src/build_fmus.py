"""Build the test/example rover FMUs from the sources in this folder (nothing downloaded).

- build_rig_fmu2(dest): rig_fmu.py -> FMI 2.0 co-simulation FMU with pythonfmu.
- build_rig_fmu3(dest): rig_fmu3.c -> FMI 3.0 co-simulation source FMU, compiled with the
  local C compiler (gcc) against the FMI 3.0 headers that ship with fmpy; the FMU also
  carries its sources.

Both model the single-wheel rig of rover_models.mjcf.single_wheel_rig_xml.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import uuid
import zipfile
from pathlib import Path

HERE = Path(__file__).resolve().parent

# FMI 3.0 variables of rig_fmu3.c: (name, valueReference, causality, start or None).
_PARAMETERS = [
    ("gravity.x", 0.0), ("gravity.y", 0.0), ("gravity.z", -9.81), ("total_mass", 15.0),
    ("vertical_mass", 10.0), ("wheel_inertia", 0.005), ("motor_kv", 20.0), ("hub_height", 0.1),
    ("internal_step", 1.0e-3), ("max_step", 0.0),
]
_INPUTS = [f"wheel_0.{q}.{a}" for q in ("force", "torque") for a in "xyz"] + ["wheel_0.speed_command"]
_OUTPUTS = (
    [f"wheel_0.position.{a}" for a in "xyz"]
    + [f"wheel_0.orientation.{a}" for a in "wxyz"]
    + [f"wheel_0.velocity.{a}" for a in "xyz"]
    + [f"wheel_0.angular_velocity.{a}" for a in "xyz"]
)


def build_rig_fmu2(dest: str | os.PathLike, variable_steps: bool = True, name: str | None = None) -> Path:
    """FMI 2.0 rig FMU built by pythonfmu into folder `dest`; returns its path.

    variable_steps False marks it canHandleVariableCommunicationStepSize="false".
    """
    from pythonfmu.builder import FmuBuilder

    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    target = dest / (name or ("RigFmu.fmu" if variable_steps else "RigFmuFixedStep.fmu"))
    return Path(
        FmuBuilder.build_FMU(
            HERE / "rig_fmu.py",
            dest=target,
            canHandleVariableCommunicationStepSize=variable_steps,
            needsExecutionTool=False,
        )
    )


def _model_description_fmi3(model_identifier: str) -> str:
    rows = ['    <Float64 name="time" valueReference="0" causality="independent" variability="continuous"/>']
    vr = 1
    for name, start in _PARAMETERS:
        rows.append(f'    <Float64 name="{name}" valueReference="{vr}" causality="parameter" variability="tunable" start="{start!r}"/>')
        vr += 1
    for name in _INPUTS:
        rows.append(f'    <Float64 name="{name}" valueReference="{vr}" causality="input" start="0.0"/>')
        vr += 1
    first_output = vr
    for name in _OUTPUTS:
        rows.append(f'    <Float64 name="{name}" valueReference="{vr}" causality="output"/>')
        vr += 1
    outputs = "\n".join(f'    <Output valueReference="{i}"/>' for i in range(first_output, vr))
    unknowns = "\n".join(f'    <InitialUnknown valueReference="{i}"/>' for i in range(first_output, vr))
    variables = "\n".join(rows)
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="3.0" modelName="{model_identifier}" instantiationToken="{{{uuid.uuid4()}}}"
    description="Single-wheel test rig (regolith-cosim)" generationTool="regolith-cosim" variableNamingConvention="structured">
  <CoSimulation modelIdentifier="{model_identifier}" canHandleVariableCommunicationStepSize="true"
      fixedInternalStepSize="0.001" canReturnEarlyAfterIntermediateUpdate="false"/>
  <DefaultExperiment startTime="0" stopTime="1" stepSize="0.001"/>
  <ModelVariables>
{variables}
  </ModelVariables>
  <ModelStructure>
{outputs}
{unknowns}
  </ModelStructure>
</fmiModelDescription>
"""


def build_rig_fmu3(dest: str | os.PathLike, compiler: str = "gcc") -> Path:
    """FMI 3.0 rig FMU compiled from rig_fmu3.c into folder `dest`; returns its path."""
    import fmpy

    model_identifier = "RigFmu3"
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    if shutil.which(compiler) is None:
        raise RuntimeError(f"C compiler {compiler!r} not found; it is needed to build the FMI 3.0 test FMU")
    include = Path(fmpy.__file__).parent / "c-code"  # fmi3Functions.h & co ship with fmpy
    platform = fmpy.platform_tuple  # e.g. x86_64-linux
    suffix = {"windows": ".dll", "darwin": ".dylib"}.get(fmpy.system, ".so")
    with tempfile.TemporaryDirectory(prefix="rig_fmu3_") as tmp:
        library = Path(tmp) / f"{model_identifier}{suffix}"
        subprocess.run(
            [compiler, "-shared", "-fPIC", "-O2", "-std=c99", "-Wall", "-Wno-unused-parameter",
             f"-I{include}", str(HERE / "rig_fmu3.c"), "-o", str(library), "-lm"],
            check=True, capture_output=True, text=True,
        )
        target = dest / f"{model_identifier}.fmu"
        with zipfile.ZipFile(target, "w") as fmu:
            fmu.writestr("modelDescription.xml", _model_description_fmi3(model_identifier))
            fmu.write(library, f"binaries/{platform}/{model_identifier}{suffix}")
            fmu.write(HERE / "rig_fmu3.c", "sources/rig_fmu3.c")
    return target
