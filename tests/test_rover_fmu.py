"""FmuRover with FMUs built here: pythonfmu (FMI 2.0) and a gcc-compiled C source FMU (FMI 3.0)."""

from __future__ import annotations

import os
import re
import shutil
import zipfile

import numpy as np
import pytest

fmpy = pytest.importorskip("fmpy")
pytest.importorskip("pythonfmu")

from cosim.contract import RoverSide, WheelWrench  # noqa: E402
from cosim.controllers import ConstantSpeed  # noqa: E402
from cosim.coupler import Coupler, stack_records  # noqa: E402
from cosim.terrain import SpringDamperTerrain  # noqa: E402
from rover_models import fmu_session  # noqa: E402
from rover_models.fmu_rover import FmuRover, FmuStepError, FmuVariableError  # noqa: E402
from rover_models.fmu_src.build_fmus import build_rig_fmu2, build_rig_fmu3  # noqa: E402


@pytest.fixture(scope="session")
def fmus(tmp_path_factory):
    """The test FMUs, built once per session."""
    folder = tmp_path_factory.mktemp("fmus")
    out = {
        "fmi2": build_rig_fmu2(folder),
        "fmi2_fixed": build_rig_fmu2(folder, variable_steps=False),
    }
    if shutil.which("gcc"):
        out["fmi3"] = build_rig_fmu3(folder)
    return out


def _fmi3(fmus):
    if "fmi3" not in fmus:
        pytest.skip("gcc not available: the FMI 3.0 test FMU cannot be built")
    return fmus["fmi3"]


def _free_fall(rover, t_end=0.05):
    """Rig without soil: the hub falls, z(t) from the FMU's semi-implicit Euler."""
    z0 = rover.wheel_kinematics()[0].position[2]
    rover.advance(t_end)
    k = rover.wheel_kinematics()[0]
    return z0, k


@pytest.mark.parametrize("version", ["fmi2", "fmi3"])
def test_fmu_loads_steps_and_falls_under_the_pushed_gravity(fmus, version):
    path = fmus["fmi2"] if version == "fmi2" else _fmi3(fmus)
    rover = FmuRover(path, wheel_count=1, gravity=(0, 0, -1.62), start_values={"hub_height": 1.0})
    assert isinstance(rover, RoverSide) and rover.fmi_version == ("2.0" if version == "fmi2" else "3.0")
    z0, k = _free_fall(rover, 0.05)
    assert rover.time == 0.05
    # Semi-implicit Euler, h = 1 ms, n = 50 steps: v = -g t exactly, z = z0 - g h^2 n (n+1) / 2.
    assert k.linear_velocity[2] == pytest.approx(-1.62 * 0.05, rel=1e-12)
    assert k.position[2] == pytest.approx(z0 - 1.62 * 1e-6 * 50 * 51 / 2, rel=1e-12)
    rover.close()


@pytest.mark.parametrize("version", ["fmi2", "fmi3"])
def test_mjcf_and_fmu_rigs_give_the_same_coupled_trajectory(fmus, version):
    """The single-wheel rig as MJCF (MuJoCo) and as FMU, each coupled to the same
    SpringDamperTerrain (drop 5 mm, wheel driven at 5 rad/s, H = 1 ms, 0.5 s).

    Tolerance 1e-9 of each quantity's scale: both integrate the same three decoupled
    equations (x: total mass; z: ballast + wheel; spin: I_yy with the motor's kv
    implicit) with the same semi-implicit Euler and the same 1 ms step, so only rounding
    may differ. A wrong frame, sign, velocity point or quaternion order would show up at
    the 1e-2 level."""
    mujoco_rover = pytest.importorskip("rover_models.mujoco_rover")
    from rover_models.mjcf import single_wheel_rig_xml

    path = fmus["fmi2"] if version == "fmi2" else _fmi3(fmus)

    def run(rover):
        soil = SpringDamperTerrain(0.1, 1, slip_velocity=0.05, substeps=2)
        coupler = Coupler(soil, rover, 1e-3, controller=ConstantSpeed(5.0, 1))
        return stack_records(coupler.run(0.5))

    ref = run(mujoco_rover.MujocoRover(single_wheel_rig_xml(hub_height=0.105), ["wheel"]))
    fmu = FmuRover(path, 1, start_values={"hub_height": 0.105})
    got = run(fmu)
    fmu.close()
    assert ref["force"][:, 0, 2].max() > 50.0  # the wheel did land and roll
    for key in ("position", "orientation", "linear_velocity", "angular_velocity", "force", "torque"):
        scale = np.abs(ref[key]).max()
        np.testing.assert_allclose(got[key], ref[key], rtol=0, atol=1e-9 * scale, err_msg=key)


@pytest.mark.parametrize("version", ["fmi2", "fmi3"])
def test_discarded_step_is_retried_in_halves(fmus, version):
    """max_step = 1 ms: a 4 ms macro step is refused (Discard) and must be retried as
    four 1 ms steps; the result equals stepping at 1 ms directly."""
    path = fmus["fmi2"] if version == "fmi2" else _fmi3(fmus)
    retried = FmuRover(path, 1, start_values={"max_step": 1e-3, "hub_height": 1.0})
    direct = FmuRover(path, 1, start_values={"hub_height": 1.0})
    wrench = [WheelWrench(force=[3.0, 0, 40.0], torque=[0, 0.2, 0])]
    for rover in (retried, direct):
        rover.apply_wheel_wrenches(wrench)
    for n in range(1, 6):
        retried.advance(4e-3 * n)
        for m in range(4):
            direct.advance(4e-3 * (n - 1) + 1e-3 * (m + 1))
    assert retried.time == pytest.approx(0.02, abs=1e-15)
    a, b = retried.wheel_kinematics()[0], direct.wheel_kinematics()[0]
    np.testing.assert_allclose(a.position, b.position, rtol=1e-12)
    np.testing.assert_allclose(a.angular_velocity, b.angular_velocity, rtol=1e-12)
    # Too few halvings allowed: a clear error, not a crash.
    stubborn = FmuRover(path, 1, start_values={"max_step": 1e-3}, max_halvings=1)
    with pytest.raises(FmuStepError, match="halvings"):
        stubborn.advance(4e-3)
    for rover in (retried, direct, stubborn):
        rover.close()


def test_an_fmu_that_fails_is_named_not_taken_for_a_bug(fmus, monkeypatch):
    """An FMU answering fmi2Error (not retried) or fmi2Fatal in doStep, or failing a get or a set: an
    FmuStepError (the project's error, exit 1 with its message) naming the file, the call, the time and
    the status; a controller FMU's failure is a ControllerError naming the drive's scene key."""
    from fmpy.fmi1 import FMICallException

    from cosim.controllers import DriveCommand
    from cosim.rover import ControllerError, RoverDriver

    rover = FmuRover(fmus["fmi2"], 1, start_values={"hub_height": 1.0})
    rover.advance(1e-3)

    def fails(status):
        def call(*args, **kwargs):
            raise FMICallException(function="fmi2DoStep", status=status)

        return call

    for status, label in ((3, "error"), (4, "fatal")):
        monkeypatch.setattr(rover.fmu, "doStep", fails(status))
        with pytest.raises(
            FmuStepError, match=rf"{re.escape(str(fmus['fmi2']))}: at t=0.001 s .*status {status} \({label}\)"
        ):
            rover.advance(2e-3)
    assert rover.failed
    rover.close()
    # a get answered Fatal: named, and the session marked failed by that alone
    reading = FmuRover(fmus["fmi2"], 1, start_values={"hub_height": 1.0})
    reading.advance(1e-3)
    called = []
    monkeypatch.setattr(reading.fmu, "getReal", fails(4))
    monkeypatch.setattr(reading.fmu, "terminate", lambda *a: called.append("terminate"))
    reading._get = reading._marking(fmu_session._guarded(reading.path, "reading Reals", reading.fmu.getReal))
    assert not reading.failed
    discarding = reading._marking(fmu_session._guarded(reading.path, "reading Reals", fails(2)))
    with pytest.raises(FmuStepError, match="status 2"):
        discarding([0])
    assert not reading.failed  # a Discard is no failure: FMI allows terminate after it
    with pytest.raises(FmuStepError, match="reading Reals: fmi2DoStep failed with status 4"):
        reading.wheel_kinematics()
    # FMI allows no call but free after Fatal (no terminate after Error): the failed FMU is only freed
    assert reading.failed
    reading.close()
    assert reading.fmu is None and called == []
    # a terminate that fails on an FMU that did not fail is said, not raised over how the run ended
    closing = FmuRover(fmus["fmi2"], 1, start_values={"hub_height": 1.0})
    monkeypatch.setattr(closing.fmu, "terminate", fails(3))
    closing.close()
    assert closing.fmu is None

    class Failing:
        def __call__(self, t, states, wrenches):
            raise FmuStepError("ctl.fmu: at t=0.5 s (H=0.004 s): fmi2DoStep failed with status 4 (fatal).")

    class Still:
        wheel_names, time = ["wheel_0"], 0.5

    driver = RoverDriver(Still(), Failing(), takes_speed=True, landed=True, label="rover.drive (fmu ctl.fmu)")
    with pytest.raises(ControllerError, match=r"rover.drive \(fmu ctl.fmu\) at t = 0.5 s: ctl.fmu: .*fatal"):
        driver.command(0.5, [], [])
    assert isinstance(driver.last_command, DriveCommand)


def test_discard_without_variable_steps_is_a_clear_error(fmus):
    rover = FmuRover(fmus["fmi2_fixed"], 1, start_values={"max_step": 1e-3})
    assert not rover.can_vary_step
    rover.advance(1e-3)  # allowed size: fine
    with pytest.raises(FmuStepError, match="variable communication step"):
        rover.advance(5e-3)
    rover.close()


def _rewrite_model_description(src, dst, old, new):
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "modelDescription.xml":
                text = data.decode()
                assert old in text
                data = text.replace(old, new).encode()
            zout.writestr(item, data)
    return dst


def test_wrong_variable_names_list_the_fmu_variables(fmus, tmp_path):
    path = _fmi3(fmus)
    renamed = _rewrite_model_description(path, tmp_path / "renamed.fmu", '"wheel_0.velocity.y"', '"wheel_0.vel_y"')
    with pytest.raises(FmuVariableError) as err:
        FmuRover(renamed, 1)
    message = str(err.value)
    assert "wheel_0.velocity.y" in message and "wheel_0.vel_y" in message and "gravity.z" in message

    retyped = _rewrite_model_description(
        path,
        tmp_path / "retyped.fmu",
        '<Float64 name="wheel_0.force.z" valueReference="13" causality="input" start="0.0"/>',
        '<Int32 name="wheel_0.force.z" valueReference="13" causality="input" start="0"/>',
    )
    with pytest.raises(FmuVariableError, match="wheel_0.force.z.*Int32.*expected Float64"):
        FmuRover(retyped, 1)

    # Right name and type, wrong causality.
    wrong_causality = _rewrite_model_description(
        fmus["fmi2"], tmp_path / "causality.fmu", 'causality="output"', 'causality="local"'
    )
    with pytest.raises(FmuVariableError, match="causality local, expected output"):
        FmuRover(wrong_causality, 1)


def test_wheel_count_mismatch_is_a_clear_error(fmus):
    with pytest.raises(ValueError, match=r"expects 4 wheel\(s\).*the FMU has 1 \(wheel_0\)"):
        FmuRover(fmus["fmi2"], wheel_count=4)
    rover = FmuRover(fmus["fmi2"])
    with pytest.raises(ValueError, match="4 wheels"):
        Coupler(SpringDamperTerrain(0.1, 4), rover, 1e-3)
    rover.close()


def test_speed_command_drives_the_wheel(fmus):
    rover = FmuRover(fmus["fmi2"], 1, gravity=(0, 0, 0))
    rover.set_wheel_speeds([3.0])
    rover.advance(0.2)  # motor time constant I / kv = 0.25 ms
    assert rover.wheel_kinematics()[0].angular_velocity[1] == pytest.approx(3.0, rel=1e-9)
    with pytest.raises(FmuVariableError, match="torque_command"):
        rover.set_wheel_torques([1.0])
    rover.close()


@pytest.mark.parametrize(
    "case",
    [
        "not_a_zip",
        "no_model_description",
        "truncated_model_description",
        "schema_invalid_model_description",
        "unknown_fmi_version",
        "no_wheels",
        "broken_binary",
        "no_resources",
        "truncated_binary",
    ],
)
def test_a_file_that_is_not_a_rover_fmu_is_a_clear_error(tmp_path, fmus, case, monkeypatch):
    """Each names the file and what is wrong; nothing is left unpacked in the temp folder (a
    folder of this test's own, so another test's files, made in parallel, cannot show there)."""
    import tempfile
    import zipfile

    from rover_models.fmu_session import FmuError

    path = tmp_path / f"{case}.fmu"
    if case == "not_a_zip":
        path.write_text("hello")
        words = "not an FMU"
    elif case == "no_model_description":
        with zipfile.ZipFile(path, "w") as z:
            z.writestr("binaries/readme.txt", "x")
        words = "no modelDescription.xml"
    elif case == "truncated_model_description":
        with zipfile.ZipFile(fmus["fmi2"]) as src, zipfile.ZipFile(path, "w") as z:
            for item in src.namelist():
                data = src.read(item)
                z.writestr(item, data[: len(data) // 2] if item == "modelDescription.xml" else data)
        words = "modelDescription.xml cannot be read"
    elif case in ("schema_invalid_model_description", "unknown_fmi_version"):  # fmpy's own errors: were exit 1
        with zipfile.ZipFile(fmus["fmi2"]) as src, zipfile.ZipFile(path, "w") as z:
            for item in src.namelist():
                data = src.read(item)
                if item == "modelDescription.xml":
                    old = b'fmiVersion="2.0"'
                    assert old in data
                    data = data.replace(old, old + b' bogus="1"' if case.startswith("schema") else b'fmiVersion="9.0"')
                z.writestr(item, data)
        words = "modelDescription.xml cannot be read"
    elif case == "broken_binary":  # instantiation fails: the unpacked folder must go again
        with zipfile.ZipFile(fmus["fmi2"]) as src, zipfile.ZipFile(path, "w") as z:
            for item in src.namelist():
                data = src.read(item)
                z.writestr(item, b"\0" * 64 if item.startswith("binaries/") and item.endswith(".so") else data)
        words = "could not be instantiated"
    elif case in ("no_resources", "truncated_binary"):  # the FMU's own code crashes: a child process dies
        with zipfile.ZipFile(fmus["fmi2"]) as src, zipfile.ZipFile(path, "w") as z:
            for item in src.namelist():
                data = src.read(item)
                if case == "truncated_binary" and item.startswith("binaries/") and item.endswith(".so"):
                    z.writestr(item, data[:1000])
                elif case == "truncated_binary" or not item.startswith("resources/"):
                    z.writestr(item, data)
        # the shim without its resources dereferences null; dlopen of a cut ELF dies of SIGBUS or SIGSEGV
        # on the glibc seen, or refuses it (then fmpy's error names it)
        words = "instantiating the FMU killed the process (SIG"
    else:  # a valid FMU without the wheel_<i>.* convention
        from pythonfmu.builder import FmuBuilder

        script = tmp_path / "plain_fmu.py"
        script.write_text(
            "from pythonfmu import Fmi2Causality, Fmi2Slave, Real\n\n\n"
            "class PlainFmu(Fmi2Slave):\n"
            "    def __init__(self, **kwargs):\n"
            "        super().__init__(**kwargs)\n"
            "        self.x = 0.0\n"
            "        self.register_variable(Real('x', causality=Fmi2Causality.output))\n\n"
            "    def do_step(self, t, h):\n"
            "        return True\n"
        )
        path = FmuBuilder.build_FMU(script, dest=tmp_path)
        words = "needs wheel_<i>"
    (tmp_path / "tmp").mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    before = set(os.listdir(tempfile.gettempdir()))
    with pytest.raises(FmuError) as info:
        FmuRover(path)
    if case == "truncated_binary" and "could not be instantiated" in str(info.value):
        words = "Failed to load shared library"
    assert str(path) in str(info.value) and words in str(info.value), str(info.value)
    assert set(os.listdir(tempfile.gettempdir())) - before == set()


def test_a_missing_rover_fmu_and_a_missing_controller_fmu_are_named_together(tmp_path):
    """The FMU example's scene without its FMUs built named only the rover's file; the run then failed again
    on the slip controller's. Every missing file is named at once."""
    from pathlib import Path

    from cosim.plan import load_plan
    from cosim.scene import SceneError

    example = Path(__file__).resolve().parent.parent / "examples" / "fmu_rover.toml"
    rover, controller = tmp_path / "rover.fmu", tmp_path / "controller.fmu"
    overrides = [f'rover.file="{rover}"', f'rover.controllers.fmu_slip.file="{controller}"']
    with pytest.raises(SceneError) as error:
        load_plan(example, overrides)
    said = "\n".join(error.value.problems)
    assert f"rover.file: {rover}: FMU file not found" in said
    assert f"rover.controllers.fmu_slip.file: {controller}: FMU file not found" in said
    # a rover whose FMU names its wheels (no rover.wheel_count): the controller is opened for any count
    text = example.read_text().replace("wheel_count = 4\n", "")
    scene = tmp_path / "no_count.toml"
    scene.write_text(text)
    with pytest.raises(SceneError) as error:
        load_plan(scene, overrides)
    assert f"rover.controllers.fmu_slip.file: {controller}: FMU file not found" in "\n".join(error.value.problems)
