"""Rover scenes: every bad rover input is rejected at plan time, naming the field, with exit code 2,
before anything runs (no bed is settled, no run folder written)."""

import os
from pathlib import Path

import numpy as np
import pytest

from cosim.cli import main
from cosim.plan import load_plan
from rover_helpers import write_rig, write_small_rover

pytest.importorskip("mujoco")


@pytest.fixture(scope="module")
def fmus(tmp_path_factory):
    """The project's rover FMU and a slip-controller FMU for one wheel (built from rover_models/fmu_src)."""
    pytest.importorskip("fmpy")
    pytest.importorskip("pythonfmu")
    from rover_models.fmu_src.build_fmus import build_rover_fmu, build_slip_controller_fmu

    folder = tmp_path_factory.mktemp("fmus")
    return {
        "rover": str(build_rover_fmu(folder)),
        "controller1": str(build_slip_controller_fmu(folder, 1)),
        "controller4": str(build_slip_controller_fmu(folder, 4)),
    }


def _rig(tmp_path, extra="", **kw):
    return write_rig(tmp_path, extra=extra, **kw)


BAD = [
    # (what, how the rig scene is changed: extra TOML or --set overrides, field named, words of the message)
    ("a wheel body the MJCF lacks", ['rover.wheels=["wheel", "wheel_2"]'], "rover.wheels", "not in the model"),
    ("a reported body the MJCF lacks", ['rover.body="chassis"'], "rover.body", "not in the model"),
    ("a missing MJCF file", ['rover.file="nowhere.xml"'], "rover.file", "not found"),
    ("an unknown controller", ['rover.drive="turbo"'], "rover.drive", "unknown controller"),
    ("an unknown drive kind", ['rover.drive.kind="warp"'], "rover.drive.kind", "'speed'"),
    (
        "a callable that cannot be imported",
        ['rover.drive={kind="python", function="no_such_module:make"}'],
        "rover.drive.function",
        "cannot import",
    ),
    (
        "a module without the callable",
        ['rover.drive={kind="python", function="os:no_such_function"}'],
        "rover.drive.function",
        "no callable",
    ),
    ("one speed per wheel, wrong count", ["rover.drive.speed=[1.0, 2.0]"], "rover.drive.speed", "2 values for 1"),
    (
        "a slip drive without its top speed",
        ['rover.drive={kind="slip", target_slip=0.2}'],
        "rover.drive.omega_max",
        "required",
    ),
    ("keys of another drive kind", ["rover.drive.target_slip=0.2"], "rover.drive.target_slip", "kind = 'speed'"),
    ("a rover and a testbed", ["testbed.mass=1.0"], "rover", "not both"),
    ("an FMU's wheel prefix on an MJCF rover", ['rover.wheel_prefix="axle_"'], "wheel_prefix", "model = 'fmu'"),
    (
        "a patch too small for the rover",
        ["patch.length=0.04", "patch.width=0.04"],
        "patch.length",
        "must hold the rover",
    ),
    ("a patch too narrow for the rover", ["patch.length=1.0", "patch.width=0.04"], "patch.width", "must hold"),
    ("a rover wider than its bed", ["bed.width=0.02", "bed.radius_mean=0.002"], "bed.width", "rover"),
    ("gravity pointing up", ["scene.gravity=[0.0, 0.0, 1.6]"], "scene.gravity", "down"),
    (
        "a controller named as a path (a sweep's folder)",
        ['rover.controllers={"../../escaped"={kind="speed", speed=1.0}}'],
        "rover.controllers",
        "plain name",
    ),
]


@pytest.mark.parametrize("what,changes,field,words", BAD, ids=[b[0] for b in BAD])
def test_bad_rover_input_is_rejected_with_exit_code_2(tmp_path, capsys, what, changes, field, words):
    scene = _rig(tmp_path)
    out = tmp_path / "out"
    args = ["run", scene, "--out", str(out), "--no-progress"]
    for change in changes:
        args += ["--set", change]
    assert main(args) == 2
    message = capsys.readouterr().err
    assert field in message and words in message, message
    assert not out.exists() or not os.listdir(out), "nothing may be written before the scene is valid"


@pytest.mark.parametrize(
    "change, words",
    [
        # the carriage and ballast joints gone: the wheel can only spin in place (it ran to "never touched")
        ((r'<joint name="(carriage_x|ballast_z)" type="slide" axis="[0-9 ]+"/>', ""), "no joint lies between"),
        # the wheel on a slide joint: its velocity motor pushes it sideways, it never turns
        (('type="hinge"', 'type="slide"'), "rover.drive"),
    ],
    ids=["fixed to the world", "a wheel on a slide joint"],
)
def test_an_mjcf_rover_that_cannot_drive_is_refused(tmp_path, capsys, change, words):
    import re

    scene = _rig(tmp_path)
    xml = tmp_path / "rig.xml"
    xml.write_text(re.sub(change[0], change[1], xml.read_text()))
    out = tmp_path / "out"
    assert main(["run", scene, "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cosim: error:") and words in err, err
    assert not out.exists() or not os.listdir(out)


@pytest.mark.parametrize(
    "change, pair", [("track", "'wheel_fl' and 'wheel_fr'"), ("wheelbase", "'wheel_fl' and 'wheel_rl'")]
)
def test_wheels_that_overlap_are_refused_naming_them(tmp_path, capsys, change, pair):
    """A track narrower than the wheels' width, a wheelbase shorter than their diameter: the wheels would
    sit inside each other (advise passed, the run ended unsteady)."""
    from rover_helpers import write_small_rover

    pytest.importorskip("mujoco")
    scene = write_small_rover(tmp_path)
    assert main(["advise", scene, "--set", f"rover.mmx.{change}=0.01"]) == 2
    err = capsys.readouterr().err
    assert f"rover: wheels {pair} overlap" in err, err
    assert main(["advise", scene]) == 0  # the rover as built: its wheels apart


def _steered_rover(tmp_path, turns: dict[str, float], **mmx) -> str:
    """The small rover as an MJCF file whose wheel bodies are turned about +z by `turns` [rad] (steered at
    the start); returns the scene's path."""
    from rover_helpers import SMALL_MMX, write_small_rover
    from rover_models.mjcf import mmx_rover_xml

    params = {**SMALL_MMX, "body_size": tuple(SMALL_MMX["body_size"]), **mmx}
    xml = mmx_rover_xml(wheel_radius=0.025, wheel_width=0.02, **params)
    for wheel, turn in turns.items():
        xml = xml.replace(f'<body name="{wheel}" ', f'<body name="{wheel}" euler="0 0 {turn}" ')
    (tmp_path / "steered.xml").write_text(xml)
    scene = write_small_rover(tmp_path)
    original = Path(scene).read_text()
    text = original.split("[rover.mmx]")[0].replace('model = "mmx"', 'model = "mjcf"\nfile = "steered.xml"')
    wheels = 'wheels = ["wheel_fl", "wheel_fr", "wheel_rl", "wheel_rr"]'
    tail = original.split("[rover.controllers.cruise]")[1]
    (tmp_path / "steered.toml").write_text(f"{text}{wheels}\n[rover.controllers.cruise]{tail}")
    return str(tmp_path / "steered.toml")


@pytest.mark.parametrize(
    "turns, mmx, refused",
    [
        ({}, {"track": 0.025}, None),  # side by side, 5 mm apart
        ({"wheel_fl": -0.7854, "wheel_fr": 0.7854}, {"track": 0.025}, "'wheel_fl' and 'wheel_fr' overlap (steered"),
        ({"wheel_fl": 0.7854, "wheel_fr": 0.7854}, {"track": 0.025}, "'wheel_fl' and 'wheel_fr' overlap (hubs"),
        ({"wheel_fl": -0.035, "wheel_fr": 0.035}, {"track": 0.025}, None),  # 2 deg of toe-in: still apart
        ({w: 1.5708 for w in ("wheel_fl", "wheel_fr", "wheel_rl", "wheel_rr")}, {"wheelbase": 0.03}, None),
        ({}, {"wheelbase": 0.03}, "'wheel_fl' and 'wheel_rl' overlap"),
    ],
    ids=["apart", "toe-in 45 deg", "both turned 45 deg", "toe-in 2 deg", "crab 90 deg", "wheelbase under 2R"],
)
def test_wheels_steered_at_the_start_are_checked_about_their_own_axles(tmp_path, capsys, turns, mmx, refused):
    """Each wheel's cylinder about its own axle (its body's y): wheels turned into each other overlap though
    their hubs are apart, and a short wheelbase is no overlap when the wheels are turned 90 deg (crab):
    their axles then run along the wheelbase, 30 mm apart against 20 mm wide wheels."""
    pytest.importorskip("mujoco")
    scene = _steered_rover(tmp_path, turns, **mmx)
    code = main(["advise", scene])
    err = capsys.readouterr().err
    if refused is None:
        assert "overlap" not in err and code == 0, err
    else:
        assert code == 2 and f"rover: wheels {refused}" in err, err


def test_a_folder_named_as_the_mjcf_file_is_named_a_folder(tmp_path, capsys):
    scene = _rig(tmp_path)
    (tmp_path / "models.xml").mkdir()
    assert main(["advise", scene, "--set", 'rover.file="models.xml"']) == 2
    assert "rover.file: " in (err := capsys.readouterr().err) and "models.xml' is a folder; give the MJCF file" in err


def test_a_badly_formed_mjcf_is_named_in_one_line(tmp_path, capsys):
    """MuJoCo's parse error spans lines (the error, the element, its line): the scene's error gives it on
    one line after the file's name, so the message reads as one problem of rover.file."""
    scene = _rig(tmp_path)
    xml = tmp_path / "rig.xml"
    xml.write_text(xml.read_text().replace('size="', 'size="x', 1))
    assert main(["advise", scene]) == 2
    err = capsys.readouterr().err
    problem = next(line for line in err.splitlines() if "rover.file:" in line)
    assert "rig.xml: XML Error: bad format in attribute 'size'; Element " in problem, err
    assert err.count("Element ") == 1 and not any(line.startswith("Element") for line in err.splitlines()), err


def test_a_compact_rig_whose_wheel_body_carries_its_own_slides_is_a_rover_that_drives(tmp_path, capsys):
    """The rule above counts the wheel body's own joints besides its spin hinge: a rig whose wheel hangs
    from the world on its own slide joints moves (the review found it refused)."""
    import re

    scene = _rig(tmp_path)
    xml = tmp_path / "rig.xml"
    text = re.sub(r'<joint name="(carriage_x|ballast_z)" type="slide" axis="[0-9 ]+"/>', "", xml.read_text())
    hinge = '<joint name="wheel_hinge" type="hinge" axis="0 1 0"/>'
    own = '<joint name="x" type="slide" axis="1 0 0"/><joint name="z" type="slide" axis="0 0 1"/>'
    xml.write_text(text.replace(hinge, own + hinge))
    assert main(["advise", scene]) == 0, capsys.readouterr().err


def test_a_controller_factory_that_fails_is_named(tmp_path, capsys):
    """A python drive whose factory refuses its arguments (or fails otherwise): exit code 2 naming the
    function, its args and the error (it was an 'unexpected error'), and no run files written."""
    scene = _rig(tmp_path)
    out = tmp_path / "out"
    drive = 'rover.drive={kind="python", function="os:getcwd", args={bogus=1}}'
    assert main(["run", scene, "--out", str(out), "--no-progress", "--set", drive]) == 2
    message = capsys.readouterr().err
    assert "rover.drive.function: os:getcwd" in message and "{'bogus': 1}" in message and "TypeError" in message
    from cosim.folders import RunFolder

    assert RunFolder(str(out)).run_files() == [], "no run files before the controller is built (its bed may be)"


def test_a_controller_factory_that_cannot_take_its_arguments_is_named_before_the_bed(tmp_path, capsys):
    """A python drive whose factory's signature cannot take (wheel_count, wheel_radius, **args) is named by
    `advise` and by the plan (exit 2), not by the run once its bed has settled; a factory that takes them
    through **kwargs passes."""
    scene = _rig(tmp_path)
    (tmp_path / "drives.py").write_text(
        "def needs_gain(wheel_count, wheel_radius, gain):\n    return lambda t, states, wrenches: None\n"
        "def takes_any(wheel_count, wheel_radius, **kwargs):\n    return lambda t, states, wrenches: None\n"
    )
    missing = 'rover.drive={kind="python", function="drives:needs_gain"}'
    assert main(["advise", scene, "--set", missing]) == 2
    message = capsys.readouterr().err
    assert "rover.drive.function: drives:needs_gain" in message and "TypeError" in message and "gain" in message
    unknown = 'rover.drive={kind="python", function="drives:needs_gain", args={gain=1.0, bogus=2}}'
    assert main(["advise", scene, "--set", unknown]) == 2
    assert "bogus" in capsys.readouterr().err
    assert main(["advise", scene, "--set", 'rover.drive={kind="python", function="drives:takes_any", args={x=1}}']) == 0


def test_fmu_rover_input_errors_name_the_field(tmp_path, fmus, capsys):
    """An FMU without the rover variables, a wheel count the FMU does not have, an FMU controller for
    another wheel count: exit code 2, the field named, the FMU's variables listed."""
    cases = [
        # the controller FMU has no wheel_0.force.* inputs: not a rover
        (['rover.model="fmu"', f'rover.file="{fmus["controller1"]}"'], "rover.file", "force"),
        # the rover FMU has four wheels, the scene says two
        (["rover.wheel_count=2"], "rover.wheel_count", "the scene expects 2 wheel(s)"),
        # a drive-controller FMU for one wheel on a four-wheeled rover
        (
            [f'rover.drive={{kind="fmu", file="{fmus["controller1"]}"}}'],
            "rover.drive.file",
            "missing wheel_1.speed_command",
        ),
        # FMU placement keys the rover FMU has, but an MJCF key it cannot take
        (['rover.body="chassis"'], "rover.body", "body.* outputs"),
    ]
    for changes, field, words in cases:
        scene = write_small_rover(tmp_path, kind="fmu", fmu=fmus["rover"])
        args = ["run", scene, "--out", str(tmp_path / "out"), "--no-progress"]
        for change in changes:
            args += ["--set", change]
        assert main(args) == 2, changes
        message = capsys.readouterr().err
        assert field in message and words in message, message


def test_a_controller_fmu_that_kills_its_process_is_refused_before_the_run(tmp_path, fmus, capsys):
    """A controller FMU instantiates at its first command, after settling and landing: one whose code
    crashes (here its resources are missing, and the FMU's C code dereferences null) is found when the
    scene is planned, in a child process, and named with the signal (exit 2, nothing written)."""
    import zipfile

    damaged = tmp_path / "no_resources.fmu"
    with zipfile.ZipFile(fmus["controller4"]) as src, zipfile.ZipFile(damaged, "w") as z:
        for item in src.namelist():
            if not item.startswith("resources/"):
                z.writestr(item, src.read(item))
    scene = write_small_rover(tmp_path)
    out = tmp_path / "out"
    drive = f'rover.drive={{kind="fmu", file="{damaged}"}}'
    assert main(["run", scene, "--out", str(out), "--no-progress", "--set", drive]) == 2
    message = capsys.readouterr().err
    assert f"rover.drive.file: {damaged}: instantiating the FMU killed the process (SIG" in message, message
    assert not out.exists() or not os.listdir(out)


def test_a_good_rover_scene_resolves_with_its_wheels_footprint_and_mass(tmp_path, fmus):
    """The plan reads the rover's wheels, mass and footprint from the model itself: the MJCF and the FMU of
    the same rover agree (their masses to rounding, their hubs exactly: the same geometry)."""
    from rover_helpers import SMALL_MMX

    mjcf = load_plan(write_small_rover(tmp_path, name="m"))
    fmu = load_plan(write_small_rover(tmp_path, kind="fmu", fmu=fmus["rover"], name="f"))
    mass = SMALL_MMX["body_mass"] + 4 * (SMALL_MMX["leg_mass"] + SMALL_MMX["wheel_mass"])
    assert mjcf.rover.mass == pytest.approx(mass, rel=1e-12)
    assert fmu.rover.mass == pytest.approx(mass, rel=1e-12)
    assert mjcf.rover.wheel_names == ("wheel_fl", "wheel_fr", "wheel_rl", "wheel_rr")
    assert fmu.rover.wheel_names == ("wheel_0", "wheel_1", "wheel_2", "wheel_3")
    assert abs(mjcf.rover.hub_offsets - fmu.rover.hub_offsets).max() < 1e-12
    assert mjcf.wheel_load == pytest.approx(mass * 1.625 / 4, rel=1e-9)
    assert mjcf.rover.takes_speed and mjcf.rover.takes_torque and fmu.rover.takes_speed and fmu.rover.takes_torque


def test_a_rover_fmu_without_binaries_is_blamed_on_rover_file(tmp_path, fmus, capsys):
    """An FMU that ships no binary for this platform: exit 2, rover.file named (not rover.start_values)."""
    import zipfile

    stripped = tmp_path / "no_binaries.fmu"
    with zipfile.ZipFile(fmus["rover"]) as src, zipfile.ZipFile(stripped, "w") as out:
        for item in src.namelist():
            if not item.startswith("binaries/"):
                out.writestr(item, src.read(item))
    scene = write_small_rover(tmp_path, kind="fmu", fmu=str(stripped))
    assert main(["advise", scene]) == 2
    err = capsys.readouterr().err
    problem = err.splitlines()[1]
    assert problem.startswith("  - rover.file:") and "no binary for this platform" in problem, err
    assert "start_values" not in err


def test_a_run_opens_its_rover_model_once(tmp_path, monkeypatch):
    """Resolving a scene probes its rover (cosim.probe: the MJCF compiled) once; the run that follows
    uses that plan (its paths are absolute from the start) and does not resolve the scene again."""
    import cosim.probe
    from cosim.launch import run_scene

    probes = []
    probe_rover = cosim.probe.probe_rover

    def counted(*args, **kwargs):
        probes.append(args[1])
        return probe_rover(*args, **kwargs)

    monkeypatch.setattr(cosim.probe, "probe_rover", counted)
    scene = write_rig(tmp_path, duration=0.015, length=0.1, width=0.1, radius=0.005, checkpoints=0.015)
    run_scene(scene, str(tmp_path / "run"), overrides=["landing.enabled=false"])
    assert len(probes) == 1


class _TwoWheels:
    """The least a RoverDriver asks of its rover model: its wheels' names."""

    wheel_names = ("wheel_l", "wheel_r")
    time = 0.0


def _speeds(values):
    from cosim.controllers import DriveCommand

    return lambda t, states, wrenches: DriveCommand("speed", values)


def _speeds_of_mode(mode):
    from cosim.controllers import DriveCommand

    return DriveCommand(mode, [0.1, 0.1])


def _raises(t, states, wrenches):
    raise RuntimeError("boom in controller")


@pytest.mark.parametrize(
    "controller, words",
    [
        (_raises, "raised RuntimeError: boom in controller at t = 2.5 s"),
        (lambda t, states, wrenches: _speeds_of_mode("velocity"), "raised ArgumentError: DriveCommand mode must be"),
        (lambda t, states, wrenches: "fast", "returned str, not a cosim.controllers.DriveCommand"),
        (_speeds([0.1, float("nan")]), "commanded speeds [0.1, nan]: every value must be finite"),
        (_speeds([0.1, float("inf")]), "every value must be finite"),
        (_speeds([0.1, 0.1, 0.1]), "commanded 3 wheels, the rover has 2"),
        (_speeds([[0.1], [0.1]]), "values must be one per wheel, shape (wheel_count,), got (2, 1)"),
    ],
)
def test_a_controller_that_fails_while_driving_is_named_with_the_time(controller, words):
    """A user's controller that raises, returns no DriveCommand or commands nan while driving: a
    ControllerError (bad input, exit 2) naming the drive and the time; it was an unexpected error (exit 1)
    or, for nan, MuJoCo's warning and a run that went on to an 'airborne' result."""
    from cosim.rover import ControllerError, RoverDriver

    label = "rover.controllers.gentle (ctl:make)"
    driver = RoverDriver(_TwoWheels(), controller, landed=True, label=label, user_code=True)
    with pytest.raises(ControllerError) as refused:
        driver.command(2.5, [], [])
    assert str(refused.value).startswith(f"{label} ") and words in str(refused.value)
    np.testing.assert_array_equal(driver.last_command.values, [0.0, 0.0])  # the records keep the last good one
