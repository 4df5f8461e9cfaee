"""Build the test/example FMUs from the sources in this folder (nothing downloaded).

- build_rig_fmu2(dest): rig_fmu.py -> FMI 2.0 co-simulation FMU with pythonfmu.
- build_rig_fmu3(dest): rig_fmu3.c -> FMI 3.0 co-simulation source FMU, compiled with the
  local C compiler (gcc) against the FMI 3.0 headers that ship with fmpy; the FMU also
  carries its sources.
  Both model the single-wheel rig of rover_models.mjcf.single_wheel_rig_xml.
- build_rover_fmu(dest): rover_fmu.py -> the MMX-like rover of rover_models.mjcf.mmx_rover_xml
  as an FMI 2.0 FMU (pythonfmu) that can save its state.
- build_slip_controller_fmu(dest, wheel_count): slip_controller_fmu.py -> a PI traction
  controller FMU for cosim.fmu_controller.

    python -m rover_models.fmu_src.build_fmus --out fmus     # all of them into ./fmus
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import uuid
import zipfile
from pathlib import Path

from soil.errors import ArgumentError, SetupError

HERE = Path(__file__).resolve().parent

# FMI 3.0 variables of rig_fmu3.c: (name, valueReference, causality, start or None).
_PARAMETERS = [
    ("gravity.x", 0.0),
    ("gravity.y", 0.0),
    ("gravity.z", -9.81),
    ("total_mass", 15.0),
    ("vertical_mass", 10.0),
    ("wheel_inertia", 0.005),
    ("motor_kv", 20.0),
    ("hub_height", 0.1),
    ("internal_step", 1.0e-3),
    ("max_step", 0.0),
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


def build_rover_fmu(dest: str | os.PathLike) -> Path:
    """The MMX-like rover FMU (FMI 2.0, pythonfmu, state save/restore) built into folder `dest`; returns its path."""
    from pythonfmu.builder import FmuBuilder

    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    return Path(
        FmuBuilder.build_FMU(
            HERE / "rover_fmu.py",
            dest=dest / "MmxRoverFmu.fmu",
            needsExecutionTool=False,
            canGetAndSetFMUstate=True,
            canSerializeFMUstate=True,
        )
    )


def build_slip_controller_fmu(dest: str | os.PathLike, wheel_count: int = 4) -> Path:
    """The slip-controller FMU for `wheel_count` wheels (FMI 2.0, pythonfmu) built into folder `dest`;
    returns its path (SlipControllerFmu<n>.fmu)."""
    from pythonfmu.builder import FmuBuilder

    if int(wheel_count) < 1:
        raise ArgumentError(f"wheel_count must be >= 1, got {wheel_count}")
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    name = f"SlipControllerFmu{int(wheel_count)}"
    source = (HERE / "slip_controller_fmu.py").read_text()
    # pythonfmu imports the slave module by name: one module and class name per wheel count
    source = source.replace("WHEELS = 4\n", f"WHEELS = {int(wheel_count)}\n", 1)
    source = source.replace("class SlipControllerFmu(", f"class {name}(", 1)
    with tempfile.TemporaryDirectory(prefix="slip_fmu_") as tmp:
        script = Path(tmp) / f"{name.lower()}.py"
        script.write_text(source)
        return Path(
            FmuBuilder.build_FMU(
                script,
                dest=dest / f"{name}.fmu",
                needsExecutionTool=False,
                canGetAndSetFMUstate=True,
                canSerializeFMUstate=True,
            )
        )


def main(argv=None) -> None:
    import argparse

    parser = argparse.ArgumentParser(description="build the project's FMUs from their sources")
    parser.add_argument("--out", default="fmus", help="folder to write the FMUs into")
    parser.add_argument("--wheels", type=int, default=4, help="wheel count of the slip-controller FMU")
    args = parser.parse_args(argv)
    built = [build_rover_fmu(args.out), build_slip_controller_fmu(args.out, args.wheels), build_rig_fmu2(args.out)]
    if shutil.which("gcc"):
        built.append(build_rig_fmu3(args.out))
    for path in built:
        print(path)


def _model_description_fmi3(model_identifier: str) -> str:
    rows = ['    <Float64 name="time" valueReference="0" causality="independent" variability="continuous"/>']
    vr = 1
    for name, start in _PARAMETERS:
        rows.append(
            f'    <Float64 name="{name}" valueReference="{vr}" causality="parameter" variability="tunable" '
            f'start="{start!r}"/>'
        )
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
    description="Single-wheel test rig (regolith-cosim)" generationTool="regolith-cosim"
    variableNamingConvention="structured">
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
        raise SetupError(f"C compiler {compiler!r} not found; it is needed to build the FMI 3.0 test FMU")
    include = Path(fmpy.__file__).parent / "c-code"  # fmi3Functions.h & co ship with fmpy
    platform = fmpy.platform_tuple  # e.g. x86_64-linux
    suffix = {"windows": ".dll", "darwin": ".dylib"}.get(fmpy.system, ".so")
    with tempfile.TemporaryDirectory(prefix="rig_fmu3_") as tmp:
        library = Path(tmp) / f"{model_identifier}{suffix}"
        subprocess.run(
            [
                compiler,
                "-shared",
                "-fPIC",
                "-O2",
                "-std=c99",
                "-Wall",
                "-Wno-unused-parameter",
                f"-I{include}",
                str(HERE / "rig_fmu3.c"),
                "-o",
                str(library),
                "-lm",
            ],
            check=True,
            capture_output=True,
            text=True,
        )
        target = dest / f"{model_identifier}.fmu"
        with zipfile.ZipFile(target, "w") as fmu:
            fmu.writestr("modelDescription.xml", _model_description_fmi3(model_identifier))
            fmu.write(library, f"binaries/{platform}/{model_identifier}{suffix}")
            fmu.write(HERE / "rig_fmu3.c", "sources/rig_fmu3.c")
    return target


if __name__ == "__main__":
    main()
