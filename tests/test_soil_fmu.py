"""The soil FMU (compiled front end + soil server) loaded by masters that know nothing of
regolith-cosim: fmpy (FMI 2.0 and 3.0) and libcosim (FMI 2.0), each run in a Python whose
sys.path holds only fmpy, libcosimpy and their dependencies (tests/fmu_importer.py).

The peer of every comparison is the in-process DemSoil built from the scene's own objects.
"""

import ctypes
import dataclasses
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

fmpy = pytest.importorskip("fmpy")
from fmpy.validation import validate_fmu  # noqa: E402

if shutil.which("gcc") is None:
    pytest.skip("gcc is needed to build the soil FMU's front end", allow_module_level=True)
if not sys.platform.startswith("linux"):
    pytest.skip("the soil FMU tests inspect /proc (Linux)", allow_module_level=True)

from cosim.contract import WheelKinematics  # noqa: E402
from cosim.dem_soil import DemSoil  # noqa: E402
from cosim.plan import load_plan  # noqa: E402
from cosim.soil_fmu import build_frontend, export_soil_fmu, soil_config_from  # noqa: E402
from helpers import TINY_SCENE  # noqa: E402
from soil import GrouserWheel  # noqa: E402

HERE = Path(__file__).resolve().parent
H = 2.0**-9  # macro step [s]: a whole number of nanoseconds (libcosim's clock) and exact in binary
VELOCITY = np.array([0.02, 0.0, -0.002])  # hub velocity [m/s]: driving forward, sinking slowly
SPIN = 0.8  # about +Y [rad/s]: rolling forward
PRESS = 8e-3  # the hub starts this far below its resting height [m] (grousers 3 mm + a grain radius + 1.5 mm)
AXES = "xyz"
SMALL_WHEEL = GrouserWheel(radius=0.012, width=0.015, grouser_count=8, grouser_height=0.002, grouser_thickness=0.002)


# -- fixtures ---------------------------------------------------------------------------------------


@pytest.fixture(scope="session")
def frontends(tmp_path_factory):
    """The front end compiled once per session for each FMI version (local gcc, fmpy's headers)."""
    folder = tmp_path_factory.mktemp("frontend")
    return {version: build_frontend(version, folder) for version in (2, 3)}


@pytest.fixture(scope="session")
def tiny(tmp_path_factory, frontends):
    """The tiny scene on the CPU, its settled bed, and its soil FMUs (FMI 2.0 and 3.0, one wheel)."""
    folder = tmp_path_factory.mktemp("soil_fmu")
    scene_file = folder / "tiny.toml"
    scene_file.write_text(TINY_SCENE.replace('precision = "mixed"', 'precision = "mixed"\ndevice = "cpu"'))
    config = soil_config_from(scene_file, bed_folder=folder / "bed")
    fmus = {
        version: export_soil_fmu(config, folder / f"soil{version}.fmu", fmi_version=version, library=frontends[version])
        for version in (2, 3)
    }
    return {"folder": folder, "plan": load_plan(scene_file), "config": config, "fmus": fmus}


def _sandbox(folder: Path) -> Path:
    """A folder holding only fmpy, libcosimpy and their dependencies (symlinks to the installed packages)."""
    from importlib import metadata

    from packaging.markers import default_environment
    from packaging.requirements import Requirement

    environment = default_environment()
    environment["extra"] = ""
    todo, seen = ["fmpy", "libcosimpy"], set()
    while todo:
        name = todo.pop()
        key = re.sub(r"[-_.]+", "-", name).lower()
        if key in seen:
            continue
        seen.add(key)
        try:
            distribution = metadata.distribution(name)
        except metadata.PackageNotFoundError:
            continue
        for text in distribution.requires or []:
            requirement = Requirement(text)
            if requirement.marker is None or requirement.marker.evaluate(environment):
                todo.append(requirement.name)
        tops = {Path(str(f)).parts[0] for f in distribution.files or []}
        for top in tops:
            source = Path(distribution.locate_file(top))
            if top.endswith((".dist-info", ".egg-info", ".pth")) or top in ("..", "__pycache__") or not source.exists():
                continue
            target = folder / top
            if not target.exists():
                target.symlink_to(source)
    assert not (folder / "cosim").exists() and not (folder / "soil").exists() and not (folder / "warp").exists()
    return folder


@pytest.fixture(scope="session")
def importer(tmp_path_factory):
    """Run tests/fmu_importer.py in a Python that can import fmpy and libcosimpy, not regolith-cosim.

    Its working directory holds decoy cosim/ and soil/ packages: the soil server must not import them.
    """
    sandbox = _sandbox(tmp_path_factory.mktemp("bare_site"))
    workdir = tmp_path_factory.mktemp("importer")
    for name in ("cosim", "soil"):
        (workdir / name).mkdir()
        (workdir / name / "__init__.py").write_text(
            f"raise ImportError('the decoy {name} package in the importer's working directory was imported')\n"
        )
    counter = iter(range(10**6))

    def run(job: dict, env_extra: dict | None = None, timeout: float = 300.0, background: bool = False):
        n = next(counter)
        job = {"sandbox": str(sandbox), **job}
        for k, spec in enumerate(job["instances"]):
            spec.setdefault("name", f"soil{k}")
            spec.setdefault("unzip", str(workdir / f"unzipped{n}_{k}"))
        job_file, result_file = workdir / f"job{n}.json", workdir / f"result{n}.json"
        job_file.write_text(json.dumps(job))
        command = [sys.executable, "-I", "-S", str(HERE / "fmu_importer.py"), str(job_file), str(result_file)]
        env = {**{k: v for k, v in os.environ.items() if not k.startswith("REGOLITH_")}, **(env_extra or {})}
        if background:
            return subprocess.Popen(
                command, cwd=workdir, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
            )
        done = subprocess.run(command, cwd=workdir, env=env, capture_output=True, text=True, timeout=timeout)
        assert done.returncode == 0, f"the importer failed ({done.returncode}):\n{done.stdout}\n{done.stderr}"
        result = json.loads(result_file.read_text())
        assert not any(result["regolith_importable"].values()), result["regolith_importable"]
        result["stdout"] = done.stdout
        return result

    return run


# -- the motion and the in-process peer -----------------------------------------------------------------


def _start_hub(fmu) -> np.ndarray:
    description = fmpy.read_model_description(str(fmu))
    starts = {
        v.name: float(v.start)
        for v in description.modelVariables
        if v.start is not None and v.name.startswith("wheel_0.position")
    }
    return np.array([starts[f"wheel_0.position.{a}"] for a in AXES])


def _kinematics(hub0: np.ndarray, t: float) -> WheelKinematics:
    angle = SPIN * t
    return WheelKinematics(
        hub0 + VELOCITY * t, (math.cos(angle / 2), 0.0, math.sin(angle / 2), 0.0), VELOCITY, (0.0, SPIN, 0.0)
    )


def _inputs(k: WheelKinematics, wheel: int = 0) -> dict:
    values = {}
    for name, vector, axes in (
        ("position", k.position, AXES),
        ("orientation", k.orientation, "wxyz"),
        ("velocity", k.linear_velocity, AXES),
        ("angular_velocity", k.angular_velocity, AXES),
    ):
        values.update({f"wheel_{wheel}.{name}.{a}": float(v) for a, v in zip(axes, vector)})
    return values


def _in_process_soil(tiny) -> DemSoil:
    """The peer: a DemSoil built from the scene's own objects and the same bed file."""
    plan = tiny["plan"]
    return DemSoil.from_bed(
        tiny["config"].bed_file,
        [plan.wheel.shape],
        plan.wheel.material,
        plan.dt,
        surface_height=tiny["config"].surface_height,
        device="cpu",
        precision=plan.precision,
        law=plan.law,
        order_seed=plan.order_seed,
    )


def _as_outputs(w, wheel: int = 0) -> dict:
    out = {
        f"wheel_{wheel}.sinkage": w.sinkage,
        f"wheel_{wheel}.work_on_soil": w.work_on_soil,
        f"wheel_{wheel}.contact_count": w.contact_count,
    }
    for name in ("force", "torque", "force_end", "torque_end"):
        out.update({f"wheel_{wheel}.{name}.{a}": float(v) for a, v in zip(AXES, getattr(w, name))})
    return out


def _job(fmu, steps: int, master: str = "fmpy", start: dict | None = None) -> tuple[dict, list]:
    """A job driving one wheel along the motion for `steps` macro steps; returns (job, kinematics per step)."""
    hub0 = _start_hub(fmu) - np.array([0.0, 0.0, PRESS])
    motion = [_kinematics(hub0, k * H) for k in range(steps)]
    job = {
        "master": master,
        "instances": [{"fmu": str(fmu), "start": {**_inputs(motion[0]), **(start or {})}}],
        "steps": [{"h": H, "inputs": [_inputs(k)]} for k in motion],
    }
    return job, motion


# -- tests ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("version", [2, 3])
def test_model_description_validates_with_units_and_resting_wheels(tiny, version):
    """fmpy's validation passes; every real variable has a defined unit; the default experiment is the
    scene's; the start values put the wheel on the bed, inside its walls: touching no grain, but
    touching when lowered by the grouser height (the start pose rests the grouser tips' circle on
    the highest grain) plus half a grain radius."""
    fmu = tiny["fmus"][version]
    assert validate_fmu(str(fmu)) == []
    description = fmpy.read_model_description(str(fmu))
    assert description.fmiVersion == f"{version}.0"
    assert description.coSimulation.canHandleVariableCommunicationStepSize
    units = {u.name for u in description.unitDefinitions}
    reals = [v for v in description.modelVariables if v.type in ("Real", "Float64")]
    assert reals and all(v.unit in units for v in reals), [v.name for v in reals if v.unit not in units]
    by_name = {v.name: v for v in description.modelVariables}
    assert by_name["wheel_0.force.z"].unit == "N" and by_name["wheel_0.torque.y"].unit == "N.m"
    assert by_name["wheel_0.position.x"].unit == "m" and by_name["wheel_0.angular_velocity.y"].unit == "rad/s"
    macro_step = tiny["plan"].macro_step
    assert float(description.defaultExperiment.stepSize) == pytest.approx(macro_step, rel=1e-12)
    assert float(description.defaultExperiment.stopTime) == pytest.approx(tiny["plan"].scene.run.duration)

    hub = _start_hub(fmu)
    soil = _in_process_soil(tiny)
    grains = soil.sim.positions()
    assert grains[:, 0].min() < hub[0] < grains[:, 0].max() and grains[:, 1].min() < hub[1] < grains[:, 1].max()
    soil.place_wheels([WheelKinematics(hub, (1, 0, 0, 0), (0, 0, 0), (0, 0, 0))])
    resting = soil.current_wrenches()[0]
    wheel = tiny["plan"].scene.wheel
    lowered = hub - [0, 0, wheel.grouser_height + 0.5 * tiny["plan"].scene.bed.radius_mean]
    soil.place_wheels([WheelKinematics(lowered, (1, 0, 0, 0), (0, 0, 0), (0, 0, 0))])
    pressed = soil.current_wrenches()[0]
    assert resting.contact_count == 0 and not np.any(resting.force)
    assert pressed.contact_count > 0 and pressed.force[2] > 0


@pytest.mark.parametrize("master, version", [("fmpy", 2), ("fmpy", 3), ("libcosim", 2), ("libcosim", 3)])
def test_fmu_steps_bitwise_like_the_in_process_soil(tiny, importer, master, version):
    """A master without regolith-cosim steps the FMU and gets bitwise the wrenches of the in-process
    soil for the same step sequence (CPU); nothing of Warp reaches the importer's stdout."""
    if master == "libcosim":
        pytest.importorskip("libcosimpy", reason="libcosim is tested when libcosimpy is installed")
    steps = 4
    job, motion = _job(tiny["fmus"][version], steps, master)
    result = importer(job)
    if "Unsupported FMI version" in result.get("refused", ""):
        pytest.skip(f"this libcosim does not load FMI {version}.0 FMUs: {result['refused']}")
    assert "refused" not in result, result["refused"]

    soil = _in_process_soil(tiny)
    soil.place_wheels([motion[0]])
    expected = [_as_outputs(soil.advance(soil.time + H, [k])[0]) for k in motion]
    got = result["outputs"][1:] if master == "fmpy" else result["outputs"]
    assert all(s == ["ok"] for s in result["status"]), result["status"]
    assert len(got) == steps
    for k in range(steps):
        assert got[k][0] == expected[k], f"step {k}"
    assert expected[-1]["wheel_0.contact_count"] > 0 and expected[-1]["wheel_0.force.z"] > 0, (
        "the bed carries the wheel"
    )
    assert "Warp" not in result["stdout"] and "Module" not in result["stdout"], result["stdout"]


@pytest.fixture(scope="session")
def decimal_comma_locale(tmp_path_factory) -> dict:
    """The environment of a host whose numbers are written 0,001 (de_DE.UTF-8, compiled here with glibc's
    localedef into a folder of its own: LOCPATH); skipped where localedef or its sources are missing."""
    if shutil.which("localedef") is None or not Path("/usr/share/i18n/locales/de_DE").exists():
        pytest.skip("glibc's localedef and its de_DE source are needed to make a decimal-comma locale")
    folder = tmp_path_factory.mktemp("locales")
    made = subprocess.run(
        ["localedef", "-i", "de_DE", "-f", "UTF-8", str(folder / "de_DE.UTF-8")], capture_output=True, text=True
    )
    if not (folder / "de_DE.UTF-8" / "LC_NUMERIC").exists():
        pytest.skip(f"localedef could not make de_DE.UTF-8: {made.stderr.strip()[:200]}")
    return {"LOCPATH": str(folder), "LC_ALL": "de_DE.UTF-8", "LANG": "de_DE.UTF-8"}


@pytest.mark.parametrize("version", [2, 3])
def test_a_host_with_a_decimal_comma_locale_steps_the_fmu_bitwise_like_the_in_process_soil(
    tiny, importer, decimal_comma_locale, version
):
    """A master whose C library writes and reads numbers as 0,001 (setlocale from its user's environment): the
    front end reads its resources' numbers and writes the server's start line in the C locale, so the FMU
    starts and steps as the in-process soil does, bit for bit (read in the host's locale, the gravity's
    -0.0057 stopped at its comma: the front end refused its own file, and a step of 0,0001 reached the server)."""
    steps = 2
    job, motion = _job(tiny["fmus"][version], steps)
    job["locale"] = ""
    result = importer(job, env_extra=decimal_comma_locale)
    assert result["decimal_point"] == ",", "the host runs in the decimal-comma locale"
    assert all(s == ["ok"] for s in result["status"]), (result["status"], result["messages"])
    soil = _in_process_soil(tiny)
    soil.place_wheels([motion[0]])
    expected = [_as_outputs(soil.advance(soil.time + H, [k])[0]) for k in motion]
    assert [got[0] for got in result["outputs"][1:]] == expected


def test_diverging_step_is_discarded_and_the_soil_kept_at_its_start(tiny, importer):
    """A wheel rammed 2 cm into the bed in one step makes the DEM diverge: the FMU answers Discard,
    stays at the step's start, and the retried step gives bitwise the in-process soil's wrenches."""
    job, motion = _job(tiny["fmus"][3], 3)
    rammed = _inputs(WheelKinematics(motion[1].position, motion[1].orientation, (0.02, 0.0, -10.0), (0, SPIN, 0)))
    job["steps"].insert(1, {"h": H, "inputs": [rammed]})
    result = importer(job)
    assert [s[0] for s in result["status"]] == ["ok", "ok", "discard", "ok", "ok"]
    assert any(m[0] == "discard" and "diverged" in m[2] for m in result["messages"]), result["messages"]

    soil = _in_process_soil(tiny)
    soil.place_wheels([motion[0]])
    expected = [_as_outputs(soil.advance(soil.time + H, [k])[0]) for k in motion]
    got = [result["outputs"][i][0] for i in (1, 3, 4)]
    assert got == expected


@pytest.mark.parametrize("version", [2, 3])
def test_a_refused_input_or_step_leaves_the_instance_to_go_on_bitwise(tiny, importer, version):
    """A NaN communication point was stepped from (the soil's clock turned NaN, then any time was taken), a
    step of 1e300 s ran until the step timeout, and a NaN input or a zero quaternion reached the server,
    whose error ended the instance (not even an FMU state could be restored). Each is refused by the front
    end with a message naming it, the soil untouched: the master restores the FMU state it took, as FMI
    allows after an Error, sets right inputs and goes on, bitwise the in-process soil's wrenches. A master
    that sets a value or steps after an Error without restoring a state is refused too (it stepped on the
    refused input's old value)."""
    job, motion = _job(tiny["fmus"][version], 3)
    second = _inputs(motion[1])
    zero = dict(second, **{f"wheel_0.orientation.{a}": 0.0 for a in "wxyz"})
    nan = dict(second, **{"wheel_0.velocity.x": math.inf, "wheel_0.angular_velocity.y": math.nan})
    job["go_on_after_error"] = True
    job["steps"][1:2] = [
        {"h": H, "inputs": [second], "t_offset": math.nan, "save_state": True},
        {"h": 1e300, "inputs": [second], "restore_state": True},
        {"h": H, "inputs": [zero], "restore_state": True},
        {"h": H, "inputs": [nan], "restore_state": True},  # the step after the refused input: refused
        {"h": H, "inputs": [second], "restore_state": True},
    ]
    result = importer(job)
    statuses = [s[0] for s in result["status"]]
    assert statuses == ["ok", "ok", "error", "error", "error", "error", "ok", "ok"], result["messages"]
    # the infinite input refused, then every later value of that step
    names = list(nan)
    refused = names[names.index("wheel_0.velocity.x") :]
    assert result["set_errors"] == [[4, name] for name in refused], result
    errors = " | ".join(m[2] for m in result["messages"] if m[0] == "error")
    for words in (
        "currentCommunicationPoint must be finite [s], got nan",
        "more than 1e+10: it would not end",
        "input wheel_0.orientation must be a unit quaternion (w, x, y, z), got (0, 0, 0, 0)",
        "input wheel_0.velocity.x must be finite, got inf",
        "setting a value after an Error: restore an FMU state taken before it",
        "doStep after an Error: restore an FMU state taken before it",
    ):
        assert words in errors, errors
    assert "soil server error" not in errors and "failed before" not in errors, errors

    soil = _in_process_soil(tiny)
    soil.place_wheels([motion[0]])
    expected = [_as_outputs(soil.advance(soil.time + H, [k])[0]) for k in motion]
    assert [result["outputs"][i][0] for i in (1, 6, 7)] == expected
    assert result["servers_after_free"] == []


@pytest.mark.parametrize("version", [2, 3])
def test_a_reset_after_an_error_starts_the_soil_again_bitwise(tiny, importer, version):
    """After an Error the instance refuses to step until a state is restored or it is reset: a reset
    clears the Error, and the soil starts again from its start values, its first step bitwise the first
    step of a fresh instance."""
    job, motion = _job(tiny["fmus"][version], 2)
    first = job["steps"][0]
    job["go_on_after_error"] = True
    job["steps"] = [
        first,
        {"h": H, "inputs": first["inputs"], "t_offset": math.nan},  # an Error
        {"h": H, "inputs": first["inputs"]},  # refused: the instance is in the Error state
        {**first, "reset": True},
        job["steps"][1],
    ]
    result = importer(job)
    statuses = [s[0] for s in result["status"]]
    assert statuses == ["ok", "ok", "error", "error", "ok", "ok"], result["messages"]
    assert result["reset_status"] == ["ok"], result["messages"]
    errors = " | ".join(m[2] for m in result["messages"] if m[0] == "error")
    assert "doStep after an Error: restore an FMU state taken before it" in errors, errors
    assert result["outputs"][4] == result["outputs"][1]  # the first step again, bit for bit
    soil = _in_process_soil(tiny)
    soil.place_wheels([motion[0]])
    expected = [_as_outputs(soil.advance(soil.time + H, [k])[0]) for k in motion]
    assert [result["outputs"][i][0] for i in (4, 5)] == expected
    assert result["servers_after_free"] == []


@pytest.mark.parametrize(
    "line, refused",
    [
        ("real 1 abc", True),  # was read as dem_step 0: "dem_step must be > 0, got 0.0"
        ("real 99999 1.0", True),  # a variable the FMU has not: was ignored
        ("real 4294967396 1.0", True),  # sscanf's %u wrapped it to 100, wheel_0.position.x
        ("wheels 1000000000", True),  # was "is incomplete (wheels, python)"
        ("wheels 4294967297", True),  # %d read it as 1 wheel
        ("real 1 0.0001  ", False),  # an editor's trailing blanks: read (the export's own dem_step line later)
    ],
    ids=["not a number", "unknown variable", "wrapped reference", "too many wheels", "wrapped count", "blanks"],
)
def test_an_edited_frontend_file_is_refused_at_instantiation_naming_its_line(tiny, tmp_path, line, refused):
    """resources/frontend.txt holds the start values the front end reads: a line it cannot read whole is
    named, with the file, instead of being skipped, wrapped or read as 0."""
    from fmpy import extract, read_model_description
    from fmpy.fmi3 import FMU3Slave

    fmu = tiny["fmus"][3]
    unzip = Path(extract(str(fmu), unzipdir=str(tmp_path / "unzipped")))
    frontend = unzip / "resources" / "frontend.txt"
    lines = frontend.read_text().splitlines()
    lines.insert(4, line)
    if not refused:  # the export's own dem_step line given trailing blanks too: the value it holds is read
        own = next(k for k, text in enumerate(lines) if text.startswith("real 1 ") and k != 4)
        dem_step = float(lines[own].split()[2])
        lines[own] += " \t "
    frontend.write_text("\n".join(lines) + "\n")
    description = read_model_description(str(fmu))
    logged = []
    slave = FMU3Slave(
        guid=description.guid,
        unzipDirectory=str(unzip),
        modelIdentifier=description.coSimulation.modelIdentifier,
        instanceName="edited",
    )
    if not refused:
        slave.instantiate(logMessage=lambda env, status, category, message: logged.append(message.decode()))
        assert slave.getFloat64([1]) == [dem_step]  # dem_step (value reference 1) as its line says
        slave.freeInstance()
        return
    with pytest.raises(Exception, match="Failed to instantiate"):
        slave.instantiate(logMessage=lambda env, status, category, message: logged.append(message.decode()))
    assert any("frontend.txt line 5 is not one of" in m and line in m for m in logged), logged


@pytest.mark.parametrize("version", [2, 3])
def test_a_call_the_fmu_does_not_offer_is_a_logged_error_that_holds_until_a_reset(tiny, tmp_path, version):
    """A call the FMU does not offer (serialized FMU states, a Boolean variable, FMI 3.0 values of a wrong
    count) returned Error silently and left the instance as if nothing happened. FMI says an Error leaves
    an instance that may only be restored, reset or freed: each is logged naming the call and why, a value
    set afterwards is refused, and a reset clears it (no server is started: all before initialization)."""
    from fmpy import extract, read_model_description
    from fmpy.fmi1 import FMICallException
    from fmpy.fmi2 import FMU2Slave, defaultCallbacks, fmi2CallbackFunctions, fmi2CallbackLoggerTYPE
    from fmpy.fmi3 import FMU3Slave

    fmu = tiny["fmus"][version]
    description = read_model_description(str(fmu))
    slave = (FMU2Slave if version == 2 else FMU3Slave)(
        guid=description.guid,
        unzipDirectory=extract(str(fmu), unzipdir=str(tmp_path / "unzipped")),
        modelIdentifier=description.coSimulation.modelIdentifier,
        instanceName="refusing",
    )
    logged = []
    one = (ctypes.c_uint * 1)(1)  # value reference 1: the parameter dem_step
    if version == 2:
        callbacks = fmi2CallbackFunctions()
        callbacks.logger = fmi2CallbackLoggerTYPE(
            lambda env, name, status, category, message: logged.append((status, message.decode()))
        )
        callbacks.allocateMemory, callbacks.freeMemory = defaultCallbacks.allocateMemory, defaultCallbacks.freeMemory
        slave.instantiate(callbacks=callbacks)
        set_dem_step = lambda: slave.fmi2SetReal(slave.component, one, 1, (ctypes.c_double * 1)(1e-4))  # noqa: E731
        refusals = {
            "fmi2SerializedFMUstateSize: FMU states are not serializable": lambda: slave.fmi2SerializedFMUstateSize(
                slave.component, None, ctypes.byref(ctypes.c_size_t())
            ),
            "fmi2GetBoolean: this FMU has no Boolean variable": lambda: slave.fmi2GetBoolean(
                slave.component, one, 1, (ctypes.c_int * 1)()
            ),
        }
    else:
        slave.instantiate(logMessage=lambda env, status, category, message: logged.append((status, message.decode())))
        set_dem_step = lambda: slave.fmi3SetFloat64(slave.component, one, 1, (ctypes.c_double * 1)(1e-4), 1)  # noqa: E731
        refusals = {
            "fmi3SerializedFMUStateSize: FMU states are not serializable": lambda: slave.fmi3SerializedFMUStateSize(
                slave.component, None, ctypes.byref(ctypes.c_size_t())
            ),
            "fmi3GetBoolean: this FMU has no Boolean variable": lambda: slave.fmi3GetBoolean(
                slave.component, one, 1, (ctypes.c_bool * 1)(), 1
            ),
            "fmi3GetFloat64: every variable is a scalar: nValues must equal nValueReferences": lambda: (
                slave.fmi3GetFloat64(slave.component, one, 1, (ctypes.c_double * 2)(), 2)
            ),
        }

    def status(call) -> int:
        try:
            return call()
        except FMICallException as error:  # fmpy raises on Error
            return error.status

    try:
        assert status(set_dem_step) == 0  # OK
        for words, refuse in refusals.items():
            logged.clear()
            assert status(refuse) == 3  # Error
            assert status(set_dem_step) == 3, "an Error holds: a value set after it is refused"
            errors = [message for level, message in logged if level == 3]
            assert any(words in m for m in errors), errors
            assert any("setting a value after an Error: restore an FMU state taken before it" in m for m in errors)
            slave.reset()
            assert status(set_dem_step) == 0, "a reset clears the Error"
    finally:
        slave.freeInstance()


def _server_settings(tiny, folder):
    """The tiny DEM FMU unpacked into folder/fmu: (its resources folder, a soil server's settings for it)."""
    from cosim.soil_fmu.server import PROTOCOL_VERSION

    with zipfile.ZipFile(tiny["fmus"][2]) as z:
        z.extractall(folder / "fmu")
    resources = folder / "fmu" / "resources"
    gravity = tiny["config"].gravity if tiny["config"].gravity is not None else tiny["plan"].gravity
    return resources, {
        "protocol": str(PROTOCOL_VERSION),
        "resources": str(resources),
        "wheels": "1",
        "dem_step": repr(tiny["config"].dem_step),
        "gravity": " ".join(repr(float(g)) for g in gravity),
        "device": "cpu",
    }


def test_a_cut_soil_json_and_a_gravity_a_hair_off_are_named(tiny, tmp_path):
    """The soil server, in-process: a cut resources/soil.json was json's bare "Unterminated string"; a
    gravity parameter 1e-10 m/s^2 off the bed's printed both vectors alike ([0 0 -1.625] twice)."""
    from cosim.soil_fmu.server import SoilSession
    from soil.errors import ArgumentError, DamagedFileError

    resources, settings = _server_settings(tiny, tmp_path)
    gravity = [float(g) for g in settings["gravity"].split()]
    settings["gravity"] = " ".join(repr(g) for g in gravity[:2]) + f" {gravity[2] - 1e-10!r}"
    with pytest.raises(ArgumentError, match=rf"asks for \[.*{float(gravity[2]) - 1e-10!r}\]"):
        SoilSession(settings)
    text = (resources / "soil.json").read_text()
    (resources / "soil.json").write_text(text[: len(text) // 2])
    with pytest.raises(DamagedFileError, match=r"soil.json is not the JSON the export wrote"):
        SoilSession(settings)


def test_a_soil_json_mesh_that_is_not_a_wheel_about_its_hub_is_named(tiny, tmp_path):
    """A mesh wheel in resources/soil.json is judged as a scene's mesh is when read: one whose axle is its
    X axis (a paddle) is refused by the soil server by name, before any grain moves."""
    from cosim.soil_fmu.server import SoilSession
    from soil.errors import SoilInputError

    resources, settings = _server_settings(tiny, tmp_path)
    data = json.loads((resources / "soil.json").read_text())
    vertices, triangles = GrouserWheel(**{k: v for k, v in data["wheel"].items() if k != "type"}).to_mesh()
    for mesh, words in (
        ((vertices, triangles), None),  # the wheel itself as a mesh: a soil
        ((vertices[:, [1, 0, 2]], triangles[:, ::-1]), r"mesh 'paddle' is not round about the axle"),
    ):
        data["wheel"] = {"type": "mesh", "name": "paddle", "vertices": mesh[0].tolist(), "triangles": mesh[1].tolist()}
        data["units"]["wheel"] = {"vertices": "m", "triangles": "1"}
        (resources / "soil.json").write_text(json.dumps(data))
        if words is None:
            SoilSession(settings)
        else:
            with pytest.raises(SoilInputError, match=words):
                SoilSession(settings)


def test_killed_server_gives_an_error_at_the_next_step_and_the_importer_survives(tiny, importer):
    job, _ = _job(tiny["fmus"][2], 3, start={"server_step_timeout": 30.0})
    job["steps"][1]["before"] = "kill"
    result = importer(job)
    assert [s[0] for s in result["status"]] == ["ok", "ok", "error"]
    assert result["elapsed"][1] < 5.0, "a dead server is seen at once, long before the 30 s step timeout"
    assert any(m[0] == "error" and "killed by signal 9" in m[2] for m in result["messages"]), result["messages"]
    assert result["servers_after_free"] == []


def test_hung_server_times_out_with_an_error(tiny, importer):
    timeout = 2.0
    job, _ = _job(tiny["fmus"][3], 3, start={"server_step_timeout": timeout})
    job["steps"][1]["before"] = "stop"  # SIGSTOP: the server never answers
    result = importer(job)
    assert [s[0] for s in result["status"]] == ["ok", "ok", "error"]
    assert timeout <= result["elapsed"][1] < timeout + 10.0
    assert any(
        m[0] == "error" and "did not answer within 2 s (parameter server_step_timeout)" in m[2]
        for m in result["messages"]
    ), result["messages"]
    assert result["servers_after_free"] == [], "the hung server was killed"


def test_server_that_cannot_start_gives_an_error_naming_the_cause(tiny, importer):
    """A Python that does not exist, and one without regolith-cosim."""
    base = getattr(sys, "_base_executable", None) or shutil.which("python3")
    check = subprocess.run([base, "-E", "-c", "import cosim"], capture_output=True, cwd="/")
    job, _ = _job(tiny["fmus"][2], 1)
    job["instances"][0]["start"]["python"] = "/nonexistent/python3"
    if check.returncode != 0:
        job["instances"].append({"fmu": str(tiny["fmus"][2]), "start": {"python": base}})
        job["steps"][0]["inputs"].append({})
    result = importer(job)
    assert all(s == "error" for s in result["status"][0])
    errors = [m[2] for m in result["messages"] if m[0] == "error"]
    assert any("/nonexistent/python3" in e and "No such file" in e for e in errors), errors
    if check.returncode != 0:
        assert any("No module named 'cosim'" in e for e in errors), errors
    assert result["servers_after_free"] == []


def test_free_instance_leaves_no_process_and_no_temporary_file(tiny, importer, tmp_path):
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    job, _ = _job(tiny["fmus"][2], 2)
    result = importer(job, env_extra={"TMPDIR": str(tmp), "TMP": str(tmp), "TEMP": str(tmp)})
    assert result["server_pids"] and result["servers_after_free"] == []
    assert not any(Path(f"/proc/{pid}").exists() for pid in result["server_pids"])
    assert list(tmp.iterdir()) == []


def test_server_ends_when_the_importer_is_killed(tiny, importer, tmp_path):
    pid_file = tmp_path / "pids.json"
    job, _ = _job(tiny["fmus"][3], 1)
    job.update(pid_file=str(pid_file), linger=120)
    process = importer(job, background=True)
    try:
        deadline = time.time() + 120
        while not pid_file.exists() or not pid_file.read_text():
            assert process.poll() is None and time.time() < deadline, process.communicate()
            time.sleep(0.1)
        servers = json.loads(pid_file.read_text())
        assert servers
        process.send_signal(signal.SIGKILL)
        process.wait()
        deadline = time.time() + 10
        while any(Path(f"/proc/{p}").exists() and _state(p) != "Z" for p in servers) and time.time() < deadline:
            time.sleep(0.1)
        assert not any(Path(f"/proc/{p}").exists() and _state(p) != "Z" for p in servers), "an orphan soil server"
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "gone"


def test_several_instances_in_one_master(tiny, importer, frontends):
    """Two one-wheel instances of one FMU and a two-wheel FMU in one fmpy master: each instance has
    its own server; identical inputs give identical wrenches; the two-wheel FMU's wheels start apart."""
    small = dataclasses.replace(tiny["config"], wheel=SMALL_WHEEL)  # two of the scene's wheels fill the tiny bed
    fmu2 = export_soil_fmu(small, tiny["folder"] / "two_wheels.fmu", fmi_version=2, wheel_count=2, library=frontends[2])
    description = fmpy.read_model_description(str(fmu2))
    starts = {
        v.name: float(v.start)
        for v in description.modelVariables
        if v.name.startswith("wheel_") and v.start is not None
    }
    x0, x1 = starts["wheel_0.position.x"], starts["wheel_1.position.x"]
    assert x1 - x0 > 2 * SMALL_WHEEL.outer_radius and "wheel_2.position.x" not in starts

    job, _ = _job(tiny["fmus"][2], 2)
    job["instances"].append(dict(job["instances"][0]))
    two = {"fmu": str(fmu2), "start": {}}
    job["instances"].append(two)
    for step in job["steps"]:
        step["inputs"] = [step["inputs"][0], step["inputs"][0], {}]
    result = importer(job)
    assert all(s == ["ok", "ok", "ok"] for s in result["status"])
    assert len(set(result["server_pids"])) == 3
    for outputs in result["outputs"][1:]:
        assert outputs[0] == outputs[1]
        assert all(math.isfinite(outputs[2][f"wheel_{i}.force.{a}"]) for i in (0, 1) for a in AXES)


def test_export_fmu_command_from_a_run_folder(tmp_path):
    """`cosim export-fmu RUN --fmi 3 --wheels 2` takes the run's bed, wheel, step and surface."""
    from cosim.cli import main
    from helpers import write_tiny

    scene = write_tiny(tmp_path)
    Path(scene).write_text(
        Path(scene).read_text().replace('precision = "mixed"', 'precision = "mixed"\ndevice = "cpu"')
    )
    run = tmp_path / "run"
    small = [f"wheel.{key}={getattr(SMALL_WHEEL, key)}" for key in ("radius", "width", "grouser_height")]
    assert main(
        [
            "run",
            scene,
            "--out",
            str(run),
            "--no-progress",
            "--set",
            "run.duration=0.0034",
            *[a for value in small for a in ("--set", value)],
        ]
    ) in (0, 6)  # 6: too short for a steady state
    out = tmp_path / "soil.fmu"
    # the run's own files are never an FMU's name, and nothing is written for them
    results = (run / "results.h5").read_bytes()
    assert main(["export-fmu", str(run), "--out", str(run / "results.h5"), "--overwrite"]) == 2
    assert (run / "results.h5").read_bytes() == results
    out.write_bytes(b"an older FMU")
    assert main(["export-fmu", str(run), "--out", str(out), "--fmi", "3", "--wheels", "2"]) == 3  # exists
    assert out.read_bytes() == b"an older FMU"
    for bad in (["--device", "banana"], ["--bed-folder", str(run / "results.h5")]):  # refused, nothing written
        assert main(["export-fmu", str(run), "--out", str(out), "--overwrite", *bad]) == 2, bad
        assert out.read_bytes() == b"an older FMU"
    # the run's own findings travel (run.json's, what the run started with), not the scene judged again
    run_json = json.loads((run / "run.json").read_text())
    run_json["summary"]["findings"][0]["message"] = "as the run judged it"  # after the run: what it measured
    (run / "run.json").write_text(json.dumps(run_json))
    assert main(["export-fmu", str(run), "--out", str(out), "--fmi", "3", "--wheels", "2", "--overwrite"]) == 0
    assert validate_fmu(str(out)) == []
    description = fmpy.read_model_description(str(out))
    names = {v.name for v in description.modelVariables}
    assert {"wheel_0.force.z", "wheel_1.force.z"} <= names and "wheel_2.force.z" not in names
    with zipfile.ZipFile(out) as z:
        config = json.loads(z.read("resources/soil.json"))
        bed = z.read("resources/bed.h5")
    assert bed == (run / "bed.h5").read_bytes()
    loaded = load_plan(run / "scene.toml")
    dt, macro_step = loaded.dt, loaded.macro_step
    run_info = json.loads((run / "bed.json").read_text())
    assert config["dem_step"] == dt and config["wheel_count"] == 2
    judged = run_json["summary"]["findings"]
    assert config["findings"] == judged and config["findings"][0]["message"] == "as the run judged it"
    assert config["unjudged"] == []  # the run judged what only a run can
    # a run that did not finish judged part of a run: the findings it started with, and what waits named
    stopped = {**run_json, "status": "interrupted"}
    (run / "run.json").write_text(json.dumps(stopped))
    partial = soil_config_from(run)
    assert partial.findings == stopped["findings"] and partial.unjudged is not None
    (run / "run.json").write_text(json.dumps(run_json))
    from cosim import advice

    assert config["validity"] == advice.verdict([advice.Finding(**f) for f in judged])
    assert config["surface_height"] == pytest.approx(run_info["metrics"]["height"], rel=1e-12)
    assert config["wheel"]["radius"] == loaded.scene.wheel.radius == SMALL_WHEEL.radius
    assert_every_number_has_a_unit(config, config["units"])
    assert config["units"]["wheel_material"]["stick_angle"] == "rad" and config["units"]["dem_step"] == "s"
    assert float(description.defaultExperiment.stepSize) == pytest.approx(macro_step, rel=1e-12)


def test_an_fmu_export_keeps_a_file_that_appeared_while_it_was_made(tiny, frontends, tmp_path, monkeypatch):
    """`cosim export-fmu --out FILE` without --overwrite (replace=False) looked that FILE was free, then
    replaced what appeared there while the FMU was made; now that file is kept and the FMU written beside
    it, both named (FileExistsError)."""
    from cosim.soil_fmu import build

    out = tmp_path / "soil.fmu"
    describe = build.model_description

    def another_process_writes_first(*args, **kwargs):
        out.write_bytes(b"another FMU")
        return describe(*args, **kwargs)

    monkeypatch.setattr(build, "model_description", another_process_writes_first)
    with pytest.raises(FileExistsError, match="soil.new.fmu") as info:
        export_soil_fmu(tiny["config"], out, library=frontends[2], replace=False)
    assert info.value.filename == str(out) and out.read_bytes() == b"another FMU"
    assert validate_fmu(str(tmp_path / "soil.new.fmu")) == []


def test_export_fmu_warns_of_a_server_python_that_is_no_executable_here(tiny, frontends, tmp_path, caplog):
    """--python may name a Python of the machine that will run the FMU, so it is not refused; one that is
    no executable file here (/etc/passwd, a typo) is said at export, not found at the FMU's first start."""
    with caplog.at_level("WARNING", logger="cosim.soil_fmu"):
        export_soil_fmu(tiny["config"], tmp_path / "a.fmu", python="/etc/passwd", library=frontends[2])
    assert any("'/etc/passwd' is no executable on this machine" in r.getMessage() for r in caplog.records)


def assert_every_number_has_a_unit(data: dict, units: dict, where: str = "soil.json") -> None:
    """Every number (or list of numbers) of `data` has a unit in the same place of `units`: a string, or
    for a nested object an object of the same keys."""
    for key, value in data.items():
        if key == "units" or isinstance(value, str) or value is None or key == "extra":
            continue
        if isinstance(value, dict):
            assert isinstance(units.get(key), dict), f"{where}.{key}"
            assert_every_number_has_a_unit(value, units[key], f"{where}.{key}")
        else:
            assert isinstance(units.get(key), str) and units[key], f"{where}.{key} has no unit"


def test_a_rover_scene_is_refused_before_a_bed_is_settled(tmp_path):
    """A soil FMU serves a [testbed] scene: a rover scene gets a SceneError naming the section, and
    no bed is settled into the folder first."""
    from cosim.scene import SceneError

    with pytest.raises(SceneError, match=r"testbed: a soil FMU is exported from a single-wheel scene"):
        soil_config_from(HERE.parent / "examples" / "phobos_rover_patch.toml", bed_folder=tmp_path)
    assert not any(tmp_path.iterdir())


# -- masters that retry a discarded step (issue 24) --------------------------------------------------------


def _rammed(motion, k: int) -> dict:
    """Step k's inputs with the hub rammed down at 10 m/s: the DEM diverges, the FMU answers Discard."""
    return _inputs(WheelKinematics(motion[k].position, motion[k].orientation, (0.02, 0.0, -10.0), (0, SPIN, 0)))


@pytest.mark.parametrize("version", [2, 3])
def test_fmpy_simulate_fmu_on_a_discard_stops_at_the_last_successful_time(tiny, importer, version):
    """fmpy's simulate_fmu retries a discarded FMI 2.0 step unchanged; the soil, which would refuse it forever,
    answers fmi2Terminated and fmpy stops at the last successful time. With FMI 3.0 fmpy stops at the Discard."""
    job, motion = _job(tiny["fmus"][version], 1)
    job.update(master="simulate", stop_time=4 * H)
    job["instances"][0]["start"].update(_rammed(motion, 0))
    result = importer(job, timeout=120)
    if version == 3:  # fmpy 0.3 does not retry an FMI 3.0 Discard: it raises at once (no hang either)
        assert "fmi3DoStep failed with status 2 (discard)" in result["raised"], result
        return
    assert result["last_time"] == 0.0  # the first step was refused: nothing after t = 0 was computed
    assert result["servers_after_free"] == []
    assert "retried unchanged after its Discard" in result["stdout"], result["stdout"]


@pytest.mark.parametrize("version", [2, 3])
def test_a_master_retries_a_discarded_step_from_a_restored_state_with_half_the_step(tiny, importer, version):
    """The master keeps an FMU state before each step; on Discard it restores it and retries with half the
    step, then goes on: the wrenches are bitwise those of the in-process soil taking the half steps."""
    job, motion = _job(tiny["fmus"][version], 2)
    hub0 = motion[0].position
    half = [_kinematics(hub0, H + k * H / 2) for k in range(2)]  # from t = H in two halves
    job["steps"] = [
        {"h": H, "inputs": [_inputs(motion[0])]},
        {"h": H, "inputs": [_rammed(motion, 1)], "save_state": True},  # refused
        {"h": H / 2, "inputs": [_inputs(half[0])], "restore_state": True},
        {"h": H / 2, "inputs": [_inputs(half[1])]},
    ]
    result = importer(job)
    assert [s[0] for s in result["status"]] == ["ok", "ok", "discard", "ok", "ok"], result["messages"]

    soil = _in_process_soil(tiny)
    soil.place_wheels([motion[0]])
    expected = [_as_outputs(soil.advance(soil.time + H, [motion[0]])[0])]
    expected += [_as_outputs(soil.advance(soil.time + H / 2, [k])[0]) for k in half]
    got = [result["outputs"][i][0] for i in (1, 3, 4)]
    assert got == expected


def test_a_master_that_goes_on_after_a_discard_is_told_where_the_soil_is(tiny, importer):
    """After a Discard at t = H, a doStep from 2 H (a master that logs the Discard and goes on) is an error
    that says the soil is earlier, at its last successful time, and what to do."""
    job, motion = _job(tiny["fmus"][2], 2)
    job["steps"] = [
        {"h": H, "inputs": [_inputs(motion[0])]},
        {"h": H, "inputs": [_rammed(motion, 1)]},
        {"h": H, "inputs": [_inputs(motion[1])], "t_offset": H},
    ]
    result = importer(job)
    assert [s[0] for s in result["status"]] == ["ok", "ok", "discard", "error"]
    errors = [m[2] for m in result["messages"] if m[0] == "error"]
    assert errors and f"but the soil is at t = {H!r} s, earlier: its last step was discarded" in errors[0], errors
    assert "fmi2LastSuccessfulTime" in errors[0]


@pytest.mark.parametrize("version", [2, 3])
def test_fmpy_compile_rebuilds_the_soil_fmu_and_it_steps_bitwise_like_the_original(tiny, importer, tmp_path, version):
    """The FMU declares its sources (FMI 2 SourceFiles, FMI 3 buildDescription.xml): `fmpy compile` builds its
    binary again (here after removing the shipped one) and the rebuilt FMU steps bitwise like the original."""
    if shutil.which("cmake") is None:
        pytest.skip("fmpy compile needs cmake")
    original = tiny["fmus"][version]
    rebuilt = tmp_path / f"rebuilt{version}.fmu"
    with zipfile.ZipFile(original) as src, zipfile.ZipFile(rebuilt, "w", zipfile.ZIP_DEFLATED) as out:
        for item in src.namelist():
            if not item.startswith("binaries/"):
                out.writestr(item, src.read(item))
    assert fmpy.supported_platforms(str(rebuilt)) == ["c-code"]
    done = subprocess.run(
        [sys.executable, "-m", "fmpy.cli", "compile", str(rebuilt)], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert fmpy.platform in fmpy.supported_platforms(str(rebuilt))
    job, _ = _job(original, 3)
    twin = dict(job["instances"][0], fmu=str(rebuilt))
    job["instances"].append(twin)
    job["steps"] = [dict(step, inputs=step["inputs"] * 2) for step in job["steps"]]
    result = importer(job)
    assert all(s == ["ok", "ok"] for s in result["status"]), result["status"]
    for outputs in result["outputs"]:
        assert outputs[0] == outputs[1]


# -- the SCM soil FMU ([terrain] model = "scm") ------------------------------------------------------------

K_C, K_PHI, N = 2.0e3, 8.0e5, 1.1
SCM_TERRAIN = f"""
[terrain]
model = "scm"
k_c = {K_C}
k_phi = {K_PHI}
n = {N}
cohesion = 50.0
friction_angle_deg = 30.0
janosi_k = 0.002
elastic_stiffness = 2.0e7
"""
SCM_PRESS = 2e-3  # the rolling wheel starts this far below its resting height [m]


@pytest.fixture(scope="session")
def scm(tmp_path_factory, frontends):
    """The tiny scene's smooth wheel (a rigid cylinder: Bekker's wheel) on SCM on the CPU, and its soil
    FMUs (FMI 2.0 and 3.0, one wheel): no bed is settled."""
    from helpers import write_tiny

    folder = tmp_path_factory.mktemp("scm_fmu")
    scene = Path(write_tiny(folder, SCM_TERRAIN))
    text = scene.read_text().replace('precision = "mixed"', 'precision = "mixed"\ndevice = "cpu"')
    scene.write_text(text.replace("grouser_count = 8", "grouser_count = 0"))
    config = soil_config_from(scene)
    fmus = {
        version: export_soil_fmu(config, folder / f"scm{version}.fmu", fmi_version=version, library=frontends[version])
        for version in (2, 3)
    }
    assert not any(folder.rglob("*.h5")), "no bed is settled for an SCM soil"
    return {"folder": folder, "scene": scene, "plan": load_plan(scene), "config": config, "fmus": fmus}


def _runs_scm_soil(plan):
    """The peer: the SCM soil side a run of the scene steps (cosim.system's builder)."""
    from cosim.system import TERRAIN_MODELS

    return TERRAIN_MODELS["scm"].build(plan, None)


def _bekker_static_sinkage(load: float, radius: float, width: float, spacing: float) -> float:
    """The sinkage [m] of a rigid cylinder at rest on Bekker soil under `load` [N]: load = integral over
    its contact (both halves) of (k_c / b + k_phi) z(x)^n, z(x) = z0 - (R - sqrt(R^2 - x^2)), b the
    patch's smaller extent (its length 2 x0 or the width, plus one node spacing: soil.scm's patch width)."""
    from scipy.integrate import quad
    from scipy.optimize import brentq

    def carried(z0):
        x0 = math.sqrt(max(0.0, 2 * radius * z0 - z0 * z0))
        b = min(width, 2 * x0) + spacing
        line, _ = quad(lambda x: (K_C / b + K_PHI) * max(0.0, z0 - radius + math.sqrt(radius**2 - x**2)) ** N, -x0, x0)
        return width * line - load

    return brentq(carried, 1e-7, 0.5 * radius)


def test_an_scm_grid_warp_cannot_index_is_refused_at_export(tmp_path):
    """Refused by scene key before an FMU is written (the server would refuse it only when instantiated);
    the grid's memory is the machine's that runs the FMU, and not judged here."""
    from helpers import write_tiny
    from soil.errors import InputError

    scene = write_tiny(tmp_path, SCM_TERRAIN + "node_spacing = 1.0e-6\n")
    with pytest.raises(InputError, match=r"more than Warp indexes.*terrain\.node_spacing must be at least"):
        soil_config_from(scene)


def test_scm_fmu_steps_bitwise_like_the_runs_scm_soil_and_carries_the_load_at_bekkers_sinkage(scm, importer):
    """Two instances of the SCM soil FMU in fmpy (FMI 2.0). One wheel is held still at Bekker's static
    sinkage under the scene's wheel load: the soil carries that load (to the grid's discretisation, 2 %),
    at the start and after every step. The other rolls forward while sinking, with an FMU state taken
    before its second step and restored after it, then two half steps: every output, the start's
    included, is bitwise that of the run's own ScmSoil (cosim.system) stepped in-process along the
    same steps (the half steps from a soil that never took the rolled-back one)."""
    plan, fmu = scm["plan"], scm["fmus"][2]
    wheel = plan.wheel
    load = plan.wheel_load
    sinkage = _bekker_static_sinkage(load, wheel.outer_radius, wheel.width, wheel.width / 12)
    rest = _start_hub(fmu)
    assert rest[2] == pytest.approx(plan.wheel.outer_radius, rel=1e-12)  # resting on the surface z = 0
    spacing = scm["config"].scm.parameters.node_spacing
    # half a node off y = 0, the wheel's edges fall between node rows: width / spacing = 12 rows carry it
    offset = np.array([0.0, 0.5 * spacing, -sinkage])
    held = _inputs(WheelKinematics(rest + offset, (1, 0, 0, 0), (0, 0, 0), (0, 0, 0)))
    hub0 = rest - np.array([0.0, 0.0, SCM_PRESS])
    motion = [_kinematics(hub0, k * H) for k in range(2)]
    half = [_kinematics(hub0, H + k * H / 2) for k in range(2)]  # from t = H in two halves
    job = {
        "master": "fmpy",
        "instances": [{"fmu": str(fmu), "start": held}, {"fmu": str(fmu), "start": _inputs(motion[0])}],
        "steps": [
            {"h": H, "inputs": [held, _inputs(motion[0])]},
            {"h": H, "inputs": [held, _inputs(motion[1])], "save_state": True},
            {"h": H / 2, "inputs": [held, _inputs(half[0])], "restore_state": True, "t_offset": -H},
            {"h": H / 2, "inputs": [held, _inputs(half[1])], "t_offset": -H},
        ],
    }
    result = importer(job)
    assert all(s == ["ok", "ok"] for s in result["status"]), (result["status"], result["messages"])

    for outputs in result["outputs"]:
        assert outputs[0]["wheel_0.force.z"] == pytest.approx(load, rel=2e-2)
        assert outputs[0]["wheel_0.force_end.z"] == pytest.approx(load, rel=2e-2)
        assert outputs[0]["wheel_0.sinkage"] == pytest.approx(sinkage, rel=1e-9)
        assert outputs[0]["wheel_0.contact_count"] > 0

    soil, kept = _runs_scm_soil(plan), _runs_scm_soil(plan)
    for side in (soil, kept):
        side.place_wheels([motion[0]])
    expected = [_as_outputs(soil.current_wrenches()[0])]
    expected += [_as_outputs(soil.advance(soil.time + H, [k])[0]) for k in motion]
    kept.advance(kept.time + H, [motion[0]])
    expected += [_as_outputs(kept.advance(kept.time + H / 2, [k])[0]) for k in half]
    got = [outputs[1] for outputs in result["outputs"]]
    assert got == expected
    assert expected[-1]["wheel_0.contact_count"] > 0 and expected[-1]["wheel_0.force.x"] != 0.0


def test_scm_fmu_refuses_another_gravity_and_a_bad_quaternion_naming_them(scm, importer):
    """FMI 3.0: an instance whose gravity parameter is not the scene's fails at initialization, naming
    the gravity; an instance given a zero orientation quaternion fails at that step, naming it."""
    fmu = scm["fmus"][3]
    start = _inputs(WheelKinematics(_start_hub(fmu), (1, 0, 0, 0), (0, 0, 0), (0, 0, 0)))
    bad = dict(start, **{f"wheel_0.orientation.{a}": 0.0 for a in "wxyz"})
    job = {
        "master": "fmpy",
        "instances": [{"fmu": str(fmu), "start": {**start, "gravity.z": -9.81}}, {"fmu": str(fmu), "start": start}],
        "steps": [{"h": H, "inputs": [start, bad]}],
    }
    result = importer(job)
    assert result["status"] == [["error", "ok"], ["error", "error"]], result["messages"]
    errors = [m[2] for m in result["messages"] if m[0] == "error"]
    assert any("gravity: the SCM soil's parameters hold at the scene's gravity" in e for e in errors), errors
    assert any("orientation must be a unit quaternion" in e for e in errors), errors
    assert result["servers_after_free"] == []


def test_the_grid_of_an_scm_fmu_with_many_wheels_is_judged_and_said_at_export(scm, tmp_path, capsys):
    """The server's SCM window holds every wheel of an instance side by side: with --wheels N its grid
    grows N-fold along x. Refused at export when Warp cannot index it (naming --wheels); otherwise
    `cosim export-fmu` says its nodes and memory, soil.scm's count of the lengthened window (the server
    allocates it on its own machine: not judged against this one's memory)."""
    from cosim.cli import main
    from cosim.soil_fmu.config import SCM_WHEEL_SPACING, scm_server_grid
    from soil.errors import InputError
    from soil.scm import grid_memory, grid_shape
    from soil.scm.terrain import MAX_NODES

    config = scm["config"]
    outer, (length, width) = scm["plan"].wheel.outer_radius, config.scm.window
    spacing = config.scm.parameters.node_spacing
    grid = scm_server_grid(config, 3)
    window = (length + 2 * SCM_WHEEL_SPACING * outer, width)
    nodes = int(np.prod(grid_shape(window, spacing)))
    assert grid["window"] == pytest.approx(window) and grid["nodes"] == nodes
    assert grid["cpu_bytes"] == grid_memory(nodes, config.precision, "cpu")[1] > grid["gpu_host_bytes"]
    fine = dataclasses.replace(
        config,
        scm=dataclasses.replace(config.scm, parameters=dataclasses.replace(config.scm.parameters, node_spacing=2e-5)),
    )
    assert (
        scm_server_grid(fine, 1)["nodes"]
        < MAX_NODES
        < np.prod(grid_shape((length + 9999 * SCM_WHEEL_SPACING * outer, width), 2e-5))
    )
    with pytest.raises(InputError, match=r"10000 wheel.*more than Warp indexes.*or fewer --wheels"):
        export_soil_fmu(fine, tmp_path / "many.fmu", wheel_count=10000, library=b"never built")
    assert not any(tmp_path.iterdir()), "nothing is written for a refused grid"

    assert main(["export-fmu", str(scm["scene"]), "--out", str(tmp_path / "three.fmu"), "--wheels", "3"]) == 0
    said = capsys.readouterr().out
    assert f"{nodes:,} nodes" in said and f"{grid['cpu_bytes'] / 1e6:,.0f} MB of host memory on the CPU" in said


def test_scm_soil_server_puts_a_failed_step_back_and_spreads_several_wheels(scm, frontends, tmp_path):
    """A two-wheel SCM FMU's soil server, in-process: the wheels start SCM_WHEEL_SPACING outer radii apart
    on the surface inside a window lengthened to hold both; a step that drives wheel 1 out of the window
    fails naming the window and leaves the soil at the step's start (the next step is bitwise a fresh
    soil's). A configuration without its SCM settings, and a rover scene with per-wheel terrains, are
    refused naming the field."""
    from cosim.scene import SceneError
    from cosim.soil_fmu.config import SCM_WHEEL_SPACING
    from cosim.soil_fmu.server import PROTOCOL_VERSION, SoilSession
    from soil.errors import InputError, SoilInputError

    fmu = export_soil_fmu(scm["config"], tmp_path / "two.fmu", wheel_count=2, library=frontends[2])
    description = fmpy.read_model_description(str(fmu))
    starts = {
        v.name: float(v.start)
        for v in description.modelVariables
        if v.name.startswith("wheel_") and v.start is not None
    }
    outer = scm["plan"].wheel.outer_radius
    assert starts["wheel_1.position.x"] - starts["wheel_0.position.x"] == pytest.approx(SCM_WHEEL_SPACING * outer)
    with zipfile.ZipFile(fmu) as z:
        z.extractall(tmp_path / "two")
        assert "resources/bed.h5" not in z.namelist()
    config = json.loads((tmp_path / "two" / "resources" / "soil.json").read_text())
    assert_every_number_has_a_unit(config, config["units"])
    assert config["units"]["scm"]["parameters"]["k_phi"] == "Pa m^(-n)"
    window = config["scm"]["window"]
    assert window[0] == pytest.approx(scm["config"].scm.window[0] + SCM_WHEEL_SPACING * outer)

    settings = {
        "protocol": str(PROTOCOL_VERSION),
        "resources": str(tmp_path / "two" / "resources"),
        "wheels": "2",
        "dem_step": repr(scm["config"].dem_step),
        "gravity": " ".join(repr(g) for g in scm["config"].gravity),
        "device": "cpu",
    }
    hubs = [np.array([starts[f"wheel_{i}.position.{a}"] for a in AXES]) - [0, 0, SCM_PRESS] for i in (0, 1)]
    still = np.concatenate([np.r_[hub, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0] for hub in hubs])
    away = still.copy()
    away[13 + 7] = 100.0  # wheel 1 at 100 m/s along x: 0.2 m in one step
    session, fresh = SoilSession(settings), SoilSession(settings)
    for side in (session, fresh):
        side.place(still)
    with pytest.raises(SoilInputError, match="leaves the SCM window"):
        session.step(H, away)
    assert session.soil.time == 0.0
    assert session.step(H, still) == fresh.step(H, still)

    with pytest.raises(InputError, match="terrain 'scm' needs scm"):
        dataclasses.replace(scm["config"], scm=None)
    pytest.importorskip("mujoco")
    from rover_helpers import write_small_rover

    mixed = SCM_TERRAIN + 'wheels = ["dem", "scm", "scm", "scm"]\n'
    with pytest.raises(SceneError, match=r"terrain\.wheels: a soil FMU steps one terrain model for all its wheels"):
        soil_config_from(write_small_rover(tmp_path, duration=0.02, extra=mixed), bed_folder=tmp_path / "bed")
    assert not (tmp_path / "bed").exists()


# -- the scene's validity travels with the FMU ---------------------------------------------------------------


def _soil_json(fmu) -> dict:
    with zipfile.ZipFile(fmu) as z:
        return json.loads(z.read("resources/soil.json"))


def test_an_out_of_range_scm_scene_warns_at_export_and_its_fmu_carries_and_logs_the_findings(scm, importer, capsys):
    """`cosim export-fmu` of a scene out of range (the SCM fixture: its sinkage is below 3 grain
    diameters) warns naming each failed check with its message (what to change); soil.json holds
    cosim.advice.scm_check's findings and their verdict, the modelDescription's description the
    verdict (fmpy's validation passes); an FMI master sees the verdict and each failed check as
    warnings when an instance is initialized (FMI 2.0 and 3.0)."""
    from cosim import advice
    from cosim.cli import main
    from cosim.soil_fmu.config import verdict

    expected = advice.scm_check(scm["plan"])
    failed = [f for f in expected if not f.ok]
    assert failed, "the SCM fixture is out of range"
    unjudged = [check for check, _ in advice.judged_after_the_run(scm["plan"], expected)]
    assert unjudged == ["scm_slip"], "its drive sets no slip: only a run could measure it"
    said_verdict = verdict([f.as_dict() for f in expected], unjudged)
    assert said_verdict == f"{advice.verdict(expected)} (not judged without a run's measurements: scm_slip)"
    out = scm["folder"] / "warned.fmu"
    assert main(["export-fmu", str(scm["scene"]), "--out", str(out), "--overwrite"]) == 0
    said = capsys.readouterr()
    for finding in failed:
        assert f"validity: {finding.check}: {finding.message}" in said.err, said.err
    assert f"validity: {said_verdict}" in said.out and "out of range: " in said.out
    assert validate_fmu(str(out)) == []
    assert f"validity: {said_verdict} (resources/soil.json)" in fmpy.read_model_description(str(out)).description
    for fmu in (out, scm["fmus"][3]):
        data = _soil_json(fmu)
        assert data["findings"] == [f.as_dict() for f in expected]
        assert data["validity"] == said_verdict

    job = {"master": "fmpy", "instances": [], "steps": [{"h": H, "inputs": []}]}
    for fmu in (out, scm["fmus"][3]):
        start = _inputs(WheelKinematics(_start_hub(fmu), (1, 0, 0, 0), (0, 0, 0), (0, 0, 0)))
        job["instances"].append({"fmu": str(fmu), "start": start})
        job["steps"][0]["inputs"].append(start)
    result = importer(job)
    assert all(s == ["ok", "ok"] for s in result["status"]), result["messages"]
    warnings = [m[2] for m in result["messages"] if m[0] == "warning" and m[1] == "logServer"]
    head = f"validity: {said_verdict} (see resources/soil.json: findings)"
    assert sum(head in w for w in warnings) == 2, result["messages"]  # once per instance
    for finding in failed:
        assert sum(f"validity: {finding.check}: {finding.message}" in w for w in warnings) == 2, warnings


def test_the_dem_soil_fmu_carries_the_findings_a_run_starts_with(tiny):
    """The DEM soil FMU's soil.json holds cosim.advice.check's findings on its settled bed's surface (what a
    run of the scene starts with and stores in run.json) and their verdict."""
    from cosim import advice

    expected = advice.check(tiny["plan"], tiny["config"].surface_height)
    for fmu in tiny["fmus"].values():
        data = _soil_json(fmu)
        assert data["findings"] == [f.as_dict() for f in expected]
        assert data["validity"] == advice.verdict(expected)


def test_a_valid_scene_exports_quietly_and_its_fmu_says_valid(scm, tmp_path, capsys):
    """The SCM fixture's scene with grains fine enough for a continuum passes every check: the export
    warns of nothing, says "validity: valid", and soil.json's findings are all ok, its validity "valid"."""
    from cosim import advice
    from cosim.cli import main

    scene = tmp_path / "valid.toml"
    scene.write_text(Path(scm["scene"]).read_text().replace("radius_mean = 0.0035", "radius_mean = 0.0005"))
    expected = advice.scm_check(load_plan(scene))
    assert advice.verdict(expected) == "valid"
    out = tmp_path / "valid.fmu"
    assert main(["export-fmu", str(scene), "--out", str(out)]) == 0
    said = capsys.readouterr()
    assert "validity: valid" in said.out and "validity" not in said.err, said
    data = _soil_json(out)
    assert data["findings"] == [f.as_dict() for f in expected] and data["unjudged"] == ["scm_slip"]
    assert data["validity"] == "valid (not judged without a run's measurements: scm_slip)"


def _fmi2_slave(fmu, folder: Path, name: str):
    """An fmpy FMI 2.0 slave of `fmu` in this process, instantiated, and the list its logger fills."""
    from fmpy import extract, read_model_description
    from fmpy.fmi2 import FMU2Slave, defaultCallbacks, fmi2CallbackFunctions, fmi2CallbackLoggerTYPE

    description = read_model_description(str(fmu))
    slave = FMU2Slave(
        guid=description.guid,
        unzipDirectory=extract(str(fmu), unzipdir=str(folder / f"unzipped_{name}")),
        modelIdentifier=description.coSimulation.modelIdentifier,
        instanceName=name,
    )
    logged: list[bytes] = []
    callbacks = fmi2CallbackFunctions()
    callbacks.logger = fmi2CallbackLoggerTYPE(lambda env, name, status, category, message: logged.append(message))
    callbacks.allocateMemory, callbacks.freeMemory = defaultCallbacks.allocateMemory, defaultCallbacks.freeMemory
    slave.instantiate(callbacks=callbacks)
    slave._callbacks_kept = callbacks  # the C side keeps pointers into it
    return slave, logged


def _initialized(slave) -> None:
    slave.setupExperiment(startTime=0.0)
    slave.enterInitializationMode()
    slave.exitInitializationMode()


def test_a_step_after_terminate_says_so_not_that_initialization_is_missing(scm, tmp_path):
    """doStep after fmi2Terminate was refused with "doStep before the end of initialization", which
    points the master at the wrong mistake: it says the instance is terminated and what to do."""
    from fmpy.fmi1 import FMICallException

    slave, logged = _fmi2_slave(scm["fmus"][2], tmp_path, "terminated")

    def refused_step(t: float) -> str:
        logged.clear()
        with pytest.raises(FMICallException):
            slave.doStep(currentCommunicationPoint=t, communicationStepSize=H)
        return b"\n".join(logged).decode()

    try:
        assert "doStep before the end of initialization" in refused_step(0.0)
        slave.reset()
        _initialized(slave)
        slave.doStep(currentCommunicationPoint=0.0, communicationStepSize=H)
        slave.terminate()
        said = refused_step(H)
        assert "doStep after terminate: the instance is terminated; reset it" in said, said
    finally:
        slave.freeInstance()


def test_an_fmu_state_belongs_to_its_instance(scm, tmp_path):
    """Two instances of one FMU each number their FMU states from 1: instance B took A's state, restored its
    own state 1 under it and stepped on a mix of two soils (fmi2OK). A state is refused by every other
    instance (restore, overwrite, free), naming why, and stays A's; FMI 2.0 declares no variable 0 (the
    soil's time is FMI 3.0's independent variable), and a fixed string parameter is named."""
    from fmpy.fmi1 import FMICallException

    a, logged_a = _fmi2_slave(scm["fmus"][2], tmp_path, "A")
    b, logged_b = _fmi2_slave(scm["fmus"][2], tmp_path, "B")
    try:
        for slave in (a, b):
            _initialized(slave)
        a.doStep(currentCommunicationPoint=0.0, communicationStepSize=H)
        state = a.getFMUstate()
        own = b.getFMUstate()
        b.freeFMUstate(own)
        overwrite = ctypes.byref(state)  # fmi2GetFMUstate into A's state: B would overwrite it with its soil
        for call in (  # the overwrite first: after an Error, FMI allows B no new state, but a restore or a free
            lambda: b.fmi2GetFMUstate(b.component, overwrite),
            lambda: b.setFMUstate(state),
            lambda: b.freeFMUstate(state),
        ):
            logged_b.clear()
            with pytest.raises(FMICallException):
                call()
            assert b"belongs to another instance of the FMU" in b"\n".join(logged_b), logged_b
        a.doStep(currentCommunicationPoint=H, communicationStepSize=H)
        a.setFMUstate(state)  # still A's, whole
        assert a.getRealStatus(2) == H  # fmi2LastSuccessfulTime: back at the state's time
        a.freeFMUstate(state)
        b.reset()
        _initialized(b)
        logged_b.clear()
        with pytest.raises(FMICallException):
            b.getReal([0])
        assert b"no Real variable has value reference 0" in b"\n".join(logged_b), logged_b
        b.reset()
        _initialized(b)
        logged_b.clear()
        with pytest.raises(FMICallException):
            b.setString([7], ["python3"])
        assert b"parameter python is fixed" in b"\n".join(logged_b), logged_b
    finally:
        for slave in (a, b):
            slave.terminate()
            slave.freeInstance()


def test_a_soil_fmu_runs_on_the_device_its_scene_names_or_says_which_setting_is_bad(scm, tmp_path, monkeypatch):
    """`--device default` (a scene's default) exported an FMU whose server refused 'default' at every start.
    The export keeps the scene's name; the server resolves 'default' where it runs; a bad name is refused
    naming where it came from (the parameter, $REGOLITH_SOIL_DEVICE) and what is allowed."""
    import warp as wp

    from cosim.soil_fmu.server import DEVICE_VARIABLE, SoilSession
    from soil.errors import ArgumentError

    scene = tmp_path / "default.toml"
    scene.write_text(scm["scene"].read_text().replace('device = "cpu"\n', ""))
    assert soil_config_from(scene).device == "default" and scm["config"].device == "cpu"
    monkeypatch.delenv(DEVICE_VARIABLE, raising=False)
    assert SoilSession.device("", "default") == str(wp.get_device())  # a GPU if this machine has one
    assert SoilSession.device("cpu", "default") == "cpu"
    with pytest.raises(ArgumentError, match="the FMU's device parameter: 'gpu' is no device: 'default' "):
        SoilSession.device("gpu", "cpu")
    with pytest.raises(ArgumentError, match="the FMU's device parameter: 'cuda:99' asked for, but this machine"):
        SoilSession.device("cuda:99", "cpu")
    monkeypatch.setenv(DEVICE_VARIABLE, " cpu")
    with pytest.raises(ArgumentError, match=r"\$REGOLITH_SOIL_DEVICE: ' cpu' is no device"):
        SoilSession.device("", "cpu")
    monkeypatch.delenv(DEVICE_VARIABLE)
    # end to end: an FMU told 'default' starts and steps
    slave, logged = _fmi2_slave(scm["fmus"][2], tmp_path, "default")
    try:
        slave.setString([8], ["default"])
        _initialized(slave)
        slave.doStep(currentCommunicationPoint=0.0, communicationStepSize=H)
    finally:
        slave.terminate()
        slave.freeInstance()
    # a Python that exits without a word at the start: the error names it and where it came from
    from fmpy.fmi1 import FMICallException

    slave, logged = _fmi2_slave(scm["fmus"][2], tmp_path, "silent")
    try:
        slave.setString([7], ["/bin/false"])
        with pytest.raises(FMICallException):
            _initialized(slave)
        said = b"\n".join(logged).decode()
        assert "exited with status 1 while starting" in said and "saying nothing: is /bin/false (the python" in said
    finally:
        slave.freeInstance()


def test_a_discarded_step_retried_with_other_inputs_is_not_called_unchanged(tiny, importer):
    """After a Discard the master retried the same step with other wheel motion: the FMU compared only
    the step's length, said "retried unchanged" and reported fmi2Terminated, so a master that checks it
    stopped. Only the same step with the same inputs is."""
    job, motion = _job(tiny["fmus"][2], 2)
    other = _inputs(WheelKinematics(motion[1].position, motion[1].orientation, (0.02, 0.0, -12.0), (0, SPIN, 0)))
    job["steps"] = [
        {"h": H, "inputs": [_inputs(motion[0])]},
        {"h": H, "inputs": [_rammed(motion, 1)]},
        {"h": H, "inputs": [other]},  # the same step from t = H, other motion: refused too
        {"h": H, "inputs": [other]},  # and again, unchanged
    ]
    result = importer(job)
    assert [s[0] for s in result["status"]] == ["ok", "ok", "discard", "discard", "discard"], result["messages"]
    discards = [m[2] for m in result["messages"] if m[0] == "discard" and "retry" in m[2]]
    unchanged = [i for i, text in enumerate(discards) if "retried unchanged" in text]
    assert unchanged == [len(discards) - 1], discards  # only the last one
    # with several wheels the refusal names the wheel whose hub is nearest the grain that diverged
    from types import SimpleNamespace

    from cosim.soil_fmu.server import SoilSession
    from soil import SimulationDiverged

    hubs = [WheelKinematics((x, 0.0, 0.05), (1, 0, 0, 0), (0, 0, 0), (0, 0, 0)) for x in (0.0, 0.3, 0.6)]
    error = SimulationDiverged("overlap", position=np.array([0.31, 0.02, 0.03]))
    said = SoilSession.nearest_wheel(SimpleNamespace(wheel_count=3), error, hubs)
    assert said == f" of wheel_1 (its hub {math.hypot(0.01, 0.02, 0.02):.3g} m from the grain that diverged)"
    assert SoilSession.nearest_wheel(SimpleNamespace(wheel_count=1), error, hubs[:1]) == ""


def test_the_fmu_overhead_benchmark_runs_and_its_fmu_gives_the_in_process_wrenches_bit_for_bit():
    """benchmarks/soil_fmu_overhead.py (BENCHMARKS.md's soil FMU section) had rotted: it imported a test
    module that is gone and passed an argument soil_config_from no longer takes. Its smallest run steps the
    FMU and the in-process soil side by side on the tests' tiny scene, and their wrenches are equal."""
    script = Path(__file__).resolve().parent.parent / "benchmarks" / "soil_fmu_overhead.py"
    done = subprocess.run(
        [sys.executable, str(script), "--steps", "3", "--substeps", "1"], capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "wrenches bitwise equal: True" in done.stdout, done.stdout[-2000:]
