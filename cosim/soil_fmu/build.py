"""Build the soil FMU: compile the front end (local C compiler, FMI headers from fmpy), write
the modelDescription (FMI 2.0 or 3.0) and pack the bed and configuration as resources.

Nothing is downloaded. The FMU holds:

    modelDescription.xml
    binaries/<platform>/RegolithSoil.so     the compiled front end (soil_fmu.c + fmi2.c or fmi3.c)
    resources/frontend.txt                  instantiation token, wheel count, default server Python, start values
    resources/soil.json                     the soil configuration (cosim.soil_fmu.config)
    resources/bed.h5                        the settled bed (the DEM soil; an SCM soil has none)
    sources/                                the front end's C sources (declared: FMI 2.0 SourceFiles, FMI 3.0
                                            sources/buildDescription.xml), so `fmpy compile` rebuilds it
"""

from __future__ import annotations

import logging
import shutil
import subprocess
import sys
import tempfile
import uuid
import zipfile
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from soil.errors import ArgumentError, SetupError

log = logging.getLogger("cosim.soil_fmu")

HERE = Path(__file__).resolve().parent
MODEL_IDENTIFIER = "RegolithSoil"
SOURCES = {2: ["soil_fmu.h", "soil_fmu.c", "fmi2.c"], 3: ["soil_fmu.h", "soil_fmu.c", "fmi3.c"]}

# value references (the same as in soil_fmu.h)
VR_WHEEL = 100
START_TIMEOUT = 600.0
"""Default longest wait for the server to start [s] (the first start on a machine compiles the DEM kernels)."""
STEP_TIMEOUT = 300.0
"""Default longest wait for one doStep [s]."""

UNITS = {
    "1": {},
    "s": {"s": 1},
    "m": {"m": 1},
    "m/s": {"m": 1, "s": -1},
    "m/s2": {"m": 1, "s": -2},
    "rad/s": {"rad": 1, "s": -1},
    "N": {"kg": 1, "m": 1, "s": -2},
    "N.m": {"kg": 1, "m": 2, "s": -2},
    "J": {"kg": 1, "m": 2, "s": -2},
}
LOG_CATEGORIES = {
    "logStatusError": "errors: the server could not start, died, timed out or failed",
    "logStatusWarning": "warnings",
    "logStatusDiscard": "steps the soil refused (diverging): retry shorter",
    "logServer": "the soil server's messages (its warnings always, the rest with logging on)",
    "logEvents": "server start, stop and set-up (with logging on)",
}


TERRAIN_TEXT = {
    "dem": {
        "soil": "DEM regolith soil",
        "dem_step": "DEM step: each doStep is split into whole DEM steps of at most this length",
        "gravity": "gravity of the settled bed (another value is an error)",
        "contact_count": "grains touching the wheel at the step's end",
    },
    "scm": {
        "soil": "SCM (Soil Contact Model) soil",
        "dem_step": "SCM step: each doStep is split into equal SCM steps of at most this length",
        "gravity": "gravity the SCM parameters hold at, the scene's (another value is an error)",
        "contact_count": "SCM nodes pressing on the wheel at the step's end",
    },
}
"""The descriptions that name what the soil is, by terrain (cosim.soil_fmu.config.TERRAINS)."""


@dataclass
class Variable:
    name: str
    vr: int
    type: str  # Float64, Int32 or String
    causality: str
    variability: str
    description: str
    unit: str | None = None
    start: float | str | None = None


def variables(wheel_count: int, dem_step: float, gravity, starts: np.ndarray, terrain: str = "dem") -> list[Variable]:
    """Every variable of the FMU; `starts` [W, 13] are the wheel inputs' start values; `terrain`
    ('dem' or 'scm') words the descriptions (the variables are the same)."""
    words = TERRAIN_TEXT[terrain]
    fixed = ("parameter", "fixed")
    rows = [
        Variable("time", 0, "Float64", "independent", "continuous", "simulation time", "s"),
        Variable(
            "dem_step",
            1,
            "Float64",
            *fixed,
            words["dem_step"],
            "s",
            float(dem_step),
        ),
    ]
    for k, axis in enumerate("xyz"):
        rows.append(
            Variable(
                f"gravity.{axis}",
                2 + k,
                "Float64",
                *fixed,
                words["gravity"],
                "m/s2",
                float(gravity[k]),
            )
        )
    rows += [
        Variable(
            "server_start_timeout",
            5,
            "Float64",
            *fixed,
            "longest wait for the soil server to start",
            "s",
            START_TIMEOUT,
        ),
        Variable(
            "server_step_timeout",
            6,
            "Float64",
            *fixed,
            "longest wait for the soil server's answer to one doStep",
            "s",
            STEP_TIMEOUT,
        ),
        Variable(
            "python",
            7,
            "String",
            *fixed,
            "the soil server's Python (with regolith-cosim); empty: "
            "$REGOLITH_SOIL_PYTHON, else the exporting Python (resources/frontend.txt)",
            start="",
        ),
        Variable(
            "device",
            8,
            "String",
            *fixed,
            "the soil server's Warp device (default: a GPU if the machine has one, else the CPU; cpu, cuda, "
            "cuda:N); empty: $REGOLITH_SOIL_DEVICE, else the scene's device",
            start="",
        ),
    ]
    inputs = [
        ("position", "xyz", "m", "hub position, world frame"),
        ("orientation", "wxyz", "1", "unit quaternion body -> world"),
        ("velocity", "xyz", "m/s", "hub velocity, world frame"),
        ("angular_velocity", "xyz", "rad/s", "angular velocity, world frame"),
    ]
    outputs = [
        ("force", "xyz", "N", "soil force on the wheel, mean over the step"),
        ("torque", "xyz", "N.m", "soil torque about the hub, mean over the step"),
        ("force_end", "xyz", "N", "soil force on the wheel at the step's end"),
        ("torque_end", "xyz", "N.m", "soil torque about the hub at the step's end"),
    ]
    for i in range(wheel_count):
        vr = VR_WHEEL * (i + 1)
        k = 0
        for quantity, axes, unit, text in inputs:
            for axis in axes:
                rows.append(
                    Variable(
                        f"wheel_{i}.{quantity}.{axis}",
                        vr,
                        "Float64",
                        "input",
                        "continuous",
                        text,
                        unit,
                        float(starts[i, k]),
                    )
                )
                vr += 1
                k += 1
        for quantity, axes, unit, text in outputs:
            for axis in axes:
                rows.append(Variable(f"wheel_{i}.{quantity}.{axis}", vr, "Float64", "output", "continuous", text, unit))
                vr += 1
        rows.append(
            Variable(
                f"wheel_{i}.sinkage",
                vr,
                "Float64",
                "output",
                "continuous",
                "depth of the rim's bottom below the undisturbed surface",
                "m",
            )
        )
        rows.append(
            Variable(
                f"wheel_{i}.work_on_soil",
                vr + 1,
                "Float64",
                "output",
                "continuous",
                "work done by the wheel on the soil during the step",
                "J",
            )
        )
        rows.append(
            Variable(
                f"wheel_{i}.contact_count",
                vr + 2,
                "Int32",
                "output",
                "discrete",
                words["contact_count"],
            )
        )
    return rows


def _number(value: float | str) -> str:
    """A Float64 start value as the exact text of a float."""
    return repr(float(value))


def _units_xml() -> str:
    rows = []
    for name, exponents in UNITS.items():
        base = " ".join(f'{k}="{v}"' for k, v in exponents.items())
        rows.append(f'    <Unit name="{name}"><BaseUnit {base}/></Unit>'.replace("<BaseUnit />", "<BaseUnit/>"))
    return "\n".join(rows)


def _categories_xml() -> str:
    return "\n".join(
        f"    <Category name={quoteattr(n)} description={quoteattr(d)}/>" for n, d in LOG_CATEGORIES.items()
    )


def model_description(
    fmi_version: int, rows: list[Variable], token: str, description: str, macro_step: float, duration: float
) -> str:
    """modelDescription.xml text for FMI `fmi_version` (2 or 3)."""
    head = (
        f'modelName="{MODEL_IDENTIFIER}" description={quoteattr(description)} generationTool="regolith-cosim" '
        'variableNamingConvention="structured"'
    )
    experiment = (
        f'  <DefaultExperiment startTime="0.0" stopTime="{_number(duration)}" stepSize="{_number(macro_step)}"/>'
    )
    common = (
        f"  <UnitDefinitions>\n{_units_xml()}\n  </UnitDefinitions>\n"
        f"  <LogCategories>\n{_categories_xml()}\n  </LogCategories>\n{experiment}\n"
    )
    outputs = [v for v in rows if v.causality == "output"]
    if fmi_version == 2:
        rows = [v for v in rows if v.causality != "independent"]  # FMI 2.0 has no time variable
        index = {v.vr: i + 1 for i, v in enumerate(rows)}
        variables_xml = "\n".join(_scalar_variable(v) for v in rows)
        structure = (
            "    <Outputs>\n"
            + "\n".join(f'      <Unknown index="{index[v.vr]}" dependencies=""/>' for v in outputs)
            + "\n    </Outputs>\n    <InitialUnknowns>\n"
            + "\n".join(f'      <Unknown index="{index[v.vr]}"/>' for v in outputs)
            + "\n    </InitialUnknowns>"
        )
        return (
            f'<?xml version="1.0" encoding="UTF-8"?>\n<fmiModelDescription fmiVersion="2.0" {head} '
            f'guid="{token}" numberOfEventIndicators="0">\n'
            f'  <CoSimulation modelIdentifier="{MODEL_IDENTIFIER}" needsExecutionTool="true" '
            'canHandleVariableCommunicationStepSize="true" canNotUseMemoryManagementFunctions="true" '
            'canGetAndSetFMUstate="true" canSerializeFMUstate="false">\n'
            "    <SourceFiles>\n"
            + "".join(f'      <File name="{name}"/>\n' for name in SOURCES[2] if name.endswith(".c"))
            + "    </SourceFiles>\n  </CoSimulation>\n"
            f"{common}  <ModelVariables>\n{variables_xml}\n  </ModelVariables>\n"
            f"  <ModelStructure>\n{structure}\n  </ModelStructure>\n</fmiModelDescription>\n"
        )
    variables_xml = "\n".join(_variable_fmi3(v) for v in rows)
    structure = (
        "\n".join(f'    <Output valueReference="{v.vr}" dependencies=""/>' for v in outputs)
        + "\n"
        + "\n".join(f'    <InitialUnknown valueReference="{v.vr}"/>' for v in outputs)
    )
    return (
        f'<?xml version="1.0" encoding="UTF-8"?>\n<fmiModelDescription fmiVersion="3.0" {head} '
        f'instantiationToken="{token}">\n'
        f'  <CoSimulation modelIdentifier="{MODEL_IDENTIFIER}" needsExecutionTool="true" '
        'canHandleVariableCommunicationStepSize="true" canReturnEarlyAfterIntermediateUpdate="false" '
        'hasEventMode="false" providesIntermediateUpdate="false" canGetAndSetFMUState="true" '
        'canSerializeFMUState="false"/>\n'
        f"{common}  <ModelVariables>\n{variables_xml}\n  </ModelVariables>\n"
        f"  <ModelStructure>\n{structure}\n  </ModelStructure>\n</fmiModelDescription>\n"
    )


def build_description() -> str:
    """sources/buildDescription.xml of the FMI 3.0 FMU: the front end's sources, so that an importer
    (`fmpy compile`) can build its binary for another platform. (FMI 2.0 lists them in SourceFiles.)"""
    files = "".join(f'      <SourceFile name="{name}"/>\n' for name in SOURCES[3] if name.endswith(".c"))
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n<fmiBuildDescription fmiVersion="3.0">\n'
        f'  <BuildConfiguration modelIdentifier="{MODEL_IDENTIFIER}">\n'
        f'    <SourceFileSet language="C99">\n{files}    </SourceFileSet>\n'
        "  </BuildConfiguration>\n</fmiBuildDescription>\n"
    )


def _scalar_variable(v: Variable) -> str:
    head = (
        f'    <ScalarVariable name={quoteattr(v.name)} valueReference="{v.vr}" causality="{v.causality}" '
        f'variability="{v.variability}" description={quoteattr(v.description)}>'
    )
    if v.type == "Float64":
        start = f' start="{_number(v.start)}"' if v.start is not None else ""
        return f'{head}<Real unit="{v.unit}"{start}/></ScalarVariable>'
    if v.type == "Int32":
        return f"{head}<Integer/></ScalarVariable>"
    assert isinstance(v.start, str)  # every String variable has a start text
    return f"{head}<String start={quoteattr(v.start)}/></ScalarVariable>"


def _variable_fmi3(v: Variable) -> str:
    head = (
        f'    <{v.type} name={quoteattr(v.name)} valueReference="{v.vr}" causality="{v.causality}" '
        f'variability="{v.variability}" description={quoteattr(v.description)}'
    )
    if v.type == "Float64":
        start = f' start="{_number(v.start)}"' if v.start is not None else ""
        return f'{head} unit="{v.unit}"{start}/>'
    if v.type == "Int32":
        return f"{head}/>"
    assert isinstance(v.start, str)  # every String variable has a start text
    return f"{head}><Start value={quoteattr(v.start)}/></String>"


def frontend_text(rows: list[Variable], token: str, wheel_count: int, python: str) -> str:
    """resources/frontend.txt: what the front end reads at instantiation (soil_fmu.c, read_frontend)."""
    if "\n" in python:
        raise ArgumentError(f"the server's Python path must not contain a line break: {python!r}")
    lines = [
        "# soil FMU front end: instantiation token, wheel count, default server Python, start values",
        f"token {token}",
        f"wheels {wheel_count}",
        f"python {python}",
    ]
    lines += [f"real {v.vr} {_number(v.start)}" for v in rows if v.type == "Float64" and v.start is not None]
    return "\n".join(lines) + "\n"


# -- the compiled front end -------------------------------------------------------------------


def _platform(fmi_version: int) -> tuple[str, str]:
    """(binaries folder name, library suffix) of this machine for FMI `fmi_version`."""
    import fmpy

    suffix = {"windows": ".dll", "darwin": ".dylib"}.get(fmpy.system, ".so")
    return (fmpy.platform if fmi_version == 2 else fmpy.platform_tuple), suffix


def build_frontend(fmi_version: int, folder, compiler: str = "gcc") -> Path:
    """Compile the front end for FMI `fmi_version` (2 or 3) into `folder`; returns the library's path.

    Uses the local C compiler and the FMI headers that ship with fmpy; POSIX systems only.
    """
    import fmpy

    if fmi_version not in SOURCES:
        raise ArgumentError(f"fmi_version must be 2 or 3, got {fmi_version!r}")
    if fmpy.system == "windows":
        raise SetupError("the soil FMU front end needs a POSIX system (Linux, macOS)")
    if shutil.which(compiler) is None:
        raise SetupError(f"C compiler {compiler!r} not found: it builds the soil FMU's front end")
    _, suffix = _platform(fmi_version)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    library = folder / f"{MODEL_IDENTIFIER}_fmi{fmi_version}{suffix}"
    include = Path(fmpy.__file__).parent / "c-code"
    sources = [str(HERE / name) for name in SOURCES[fmi_version] if name.endswith(".c")]
    command = [
        compiler,
        "-shared",
        "-fPIC",
        "-fvisibility=hidden",
        "-O2",
        "-std=c99",
        "-Wall",
        "-Wno-unused-parameter",
        f"-I{include}",
        *sources,
        "-o",
        str(library),
        "-lm",
    ]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SetupError(f"compiling the soil FMU front end failed ({' '.join(command)}):\n{done.stderr}")
    return library


# -- wheel start poses --------------------------------------------------------------------------


def wheel_start_positions(config, wheel_count: int) -> np.ndarray:
    """Hub positions [m], shape (wheel_count, 3): along the bed's centre line, each wheel's lowest
    point resting on the highest grain under it (touching, not pressed in).

    One wheel sits at config.start_x (default: outer radius + 6 mean grain radii from the bed's
    x-start wall); several are spread evenly between such margins at both ends. On SCM (no grains)
    the wheels rest on the undisturbed surface along y = 0, the first at config.start_x (default
    0), the others SCM_WHEEL_SPACING outer radii apart along x.
    """
    from soil.bed import read_bed
    from soil.sdf import BOUNDARY_PLANE

    from .config import SCM_WHEEL_SPACING

    shape = config.wheel
    outer = float(shape.outer_radius)
    if config.terrain == "scm":
        x0 = config.start_x if config.start_x is not None else 0.0
        xs = x0 + SCM_WHEEL_SPACING * outer * np.arange(wheel_count)
        return np.column_stack([xs, np.zeros(wheel_count), np.full(wheel_count, config.surface_height + outer)])
    width = float(getattr(shape, "width", 0.0)) or float(np.ptp(shape.vertices[:, 1]))
    bed = read_bed(config.bed_file)
    x = bed.state["position"].astype(np.float64)
    r = bed.radius.astype(np.float64)
    geometry = bed.boundary_geometry.astype(np.float64)
    lo = np.min(x - r[:, None], axis=0)
    hi = np.max(x + r[:, None], axis=0)
    for kind, g in zip(bed.boundary_kind, geometry):  # side walls of the container bound the bed where present
        point, normal = g[:3], g[3:6]
        for axis in (0, 1):
            if kind == BOUNDARY_PLANE and abs(abs(normal[axis]) - 1.0) < 1e-9:
                if normal[axis] > 0:
                    lo[axis] = point[axis]
                else:
                    hi[axis] = point[axis]
    margin = outer + 6.0 * float(r.mean())
    if wheel_count == 1:
        xs = [config.start_x if config.start_x is not None else lo[0] + margin]
    else:
        spacing = (hi[0] - lo[0] - 2.0 * margin) / (wheel_count - 1)
        if spacing < 2.0 * outer * 1.05:
            raise ArgumentError(
                f"the bed ({hi[0] - lo[0]:.4g} m long) cannot hold {wheel_count} wheels of outer radius "
                f"{outer:.4g} m side by side with {margin:.4g} m margins: use fewer wheels (--wheels) or a "
                "longer bed"
            )
        xs = [lo[0] + margin + i * spacing for i in range(wheel_count)]
    y = 0.5 * (lo[1] + hi[1])
    positions = []
    for hub_x in xs:
        z = config.surface_height + outer
        under = (np.abs(x[:, 0] - hub_x) < outer + r) & (np.abs(x[:, 1] - y) < 0.5 * width + r)
        if under.any():
            dx = np.abs(x[under, 0] - hub_x)
            reach = np.sqrt(np.maximum((outer + r[under]) ** 2 - dx**2, 0.0))  # hub height that just touches
            z = max(z, float(np.max(x[under, 2] + reach)) + 1e-6 * outer)
        positions.append([hub_x, y, z])
    return np.asarray(positions)


# -- the FMU ----------------------------------------------------------------------------------------


def failed_findings(data: dict) -> list[dict]:
    """The findings out of range of a soil.json configuration (none where it holds no findings)."""
    findings = data.get("findings")
    return [f for f in findings if isinstance(f, dict) and not f.get("ok", True)] if isinstance(findings, list) else []


def warn_validity(data: dict, destination) -> None:
    """Log a warning for each finding of the configuration out of range, naming the check and what to
    change (the finding's own text), then the verdict: the FMU's user never runs `cosim advise`."""
    failed = failed_findings(data)
    for finding in failed:
        log.warning("validity: %s: %s", finding.get("check"), finding.get("message"))
    if failed:
        log.warning(
            "validity: %s: %s carries these findings (resources/soil.json: findings, validity) and warns of "
            "them when an instance is initialized",
            data.get("validity"),
            destination,
        )


def export_soil_fmu(
    config,
    destination,
    fmi_version: int = 2,
    wheel_count: int = 1,
    python: str | None = None,
    library=None,
    compiler: str = "gcc",
    replace: bool = True,
) -> Path:
    """Write the soil FMU of `config` (a cosim.soil_fmu.SoilFmuConfig) to `destination` (.fmu).

    fmi_version: 2 or 3. wheel_count: wheels in one instance (all of config.wheel's shape, on
    one bed, or on one SCM terrain whose window holds them all). python: the soil server's
    default Python (default config.python, else this Python; an FMU user overrides it with the
    `python` parameter or REGOLITH_SOIL_PYTHON).
    library: a front end already compiled by build_frontend for this FMI version (else compiled now).
    replace False: a file at `destination` (one that appeared while the FMU was made) is kept, the FMU
    written beside it (FileExistsError naming both: soil.files.place_new).
    Returns the FMU's path.
    """
    import json

    from soil.files import atomic_path

    from .config import config_to_json, scm_server_grid

    if fmi_version not in SOURCES:
        raise ArgumentError(f"fmi_version must be 2 or 3, got {fmi_version!r}")
    if not (isinstance(wheel_count, (int, np.integer)) and 1 <= wheel_count <= 10000):
        raise ArgumentError(f"wheel_count must be an integer in [1, 10000], got {wheel_count!r}")
    python = python or config.python or sys.executable
    if shutil.which(python) is None:  # a path or a name on PATH (the front end spawns it so); maybe another machine's
        log.warning(
            "the soil server's Python %r is no executable on this machine: the FMU starts it where it runs "
            "(its `python` parameter or REGOLITH_SOIL_PYTHON overrides it there)",
            python,
        )
    if config.terrain == "scm":
        scm_server_grid(config, wheel_count)  # refused here if Warp cannot index it, not when the FMU starts
    data = config_to_json(config, wheel_count)
    warn_validity(data, destination)
    starts = np.zeros((wheel_count, 13))
    starts[:, 0:3] = wheel_start_positions(config, wheel_count)
    starts[:, 3] = 1.0  # orientation (1, 0, 0, 0): axle along the world's y axis
    rows = variables(wheel_count, config.dem_step, data["gravity"], starts, config.terrain)
    token = "{" + str(uuid.uuid4()) + "}"
    macro_step = config.macro_step or 10 * config.dem_step
    soil = TERRAIN_TEXT[config.terrain]["soil"]
    description = (
        f"{soil} '{config.name}' (regolith-cosim): wheel kinematics in, wheel wrenches out; "
        f"{wheel_count} wheel(s); needs the soil server's Python (docs/fmu.md)"
    )
    if data.get("validity"):
        description += f"; validity: {data['validity']} (resources/soil.json)"
    platform, suffix = _platform(fmi_version)
    destination = Path(destination)
    destination.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="soil_fmu_") as folder:
        if library is None:
            library = build_frontend(fmi_version, folder, compiler)
        with atomic_path(destination, ".fmu.tmp", replace=replace) as temporary:
            with zipfile.ZipFile(temporary, "w", zipfile.ZIP_DEFLATED) as fmu:
                fmu.writestr(
                    "modelDescription.xml",
                    model_description(fmi_version, rows, token, description, macro_step, config.duration),
                )
                fmu.write(library, f"binaries/{platform}/{MODEL_IDENTIFIER}{suffix}")
                fmu.writestr("resources/frontend.txt", frontend_text(rows, token, wheel_count, python))
                fmu.writestr("resources/soil.json", json.dumps(data, indent=1))
                if config.terrain == "dem":
                    fmu.write(config.bed_file, "resources/bed.h5")
                for name in SOURCES[fmi_version]:
                    fmu.write(HERE / name, f"sources/{name}")
                if fmi_version == 3:
                    fmu.writestr("sources/buildDescription.xml", build_description())
    return destination


__all__ = ["build_frontend", "export_soil_fmu", "model_description", "variables", "wheel_start_positions"]
