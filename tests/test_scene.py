"""Scene files and plans: every kind of mistake is rejected with a message naming the field."""

import glob
import os
from pathlib import Path

import pytest

from cosim.cli import main
from cosim.plan import load_plan
from cosim.scene import SceneError, load_scene, scene_from_text
from helpers import SCM_TERRAIN, TINY_SCENE, write_tiny

EXAMPLES = os.path.join(os.path.dirname(__file__), "..", "examples")

BAD_SCENES = [
    # (what is wrong, TOML added to / replacing the tiny scene, field named, words of the allowed values)
    ("unknown key", "[bed]\nlenght = 0.2\n", "bed.lenght", "unknown key"),
    ("unknown section", "[whee]\nradius = 0.1\n", "whee", "unknown key"),
    ("wrong type", '[testbed]\nmass = "heavy"\n', "testbed.mass", "number"),
    ("negative radius", "[wheel]\nradius = -0.03\n", "wheel.radius", "> 0"),
    (
        "slip angle above stick angle",
        "[soil]\nstick_angle_deg = 20.0\nslip_angle_deg = 30.0\n",
        "soil.slip_angle_deg",
        "stick_angle_deg",
    ),
    ("friction angle >= 90 deg", "[soil]\nstick_angle_deg = 90.0\n", "soil.stick_angle_deg", "< 90"),
    ("missing mesh file", '[wheel]\ntype = "mesh"\nfile = "no_such_wheel.obj"\n', "wheel.file", "not found"),
    ("mesh keys on a grouser wheel", '[wheel]\nfile = "w.obj"\n', "wheel.file", "mesh"),
    ("unknown gravity preset", '[scene]\ngravity = "titan"\n', "scene.gravity", "phobos"),
    ("gravity vector of 2", "[scene]\ngravity = [0.0, -1.0]\n", "scene.gravity", "3"),
    ("unknown precision", '[scene]\nprecision = "half"\n', "scene.precision", "'double'"),
    ("unknown device", '[scene]\ndevice = "tpu"\n', "scene.device", "cuda"),
    ("wheel wider than the bed", "[wheel]\nwidth = 0.07\n", "wheel.width", "wider than the bed"),
    ("wheel too close to the side walls", "[wheel]\nwidth = 0.052\n", "wheel.width", "side walls"),
    ("start too close to the wall", "[testbed]\nstart_x = 0.02\n", "testbed.start_x", "start_x >="),
    ("would drive into the far wall", "[run]\nduration = 10.0\n", "run.duration", "duration <="),
    ("dt <= 0", "[run]\ndt = 0.0\n", "run.dt", "> 0"),
    ("dt and dt_factor", "[run]\ndt = 1e-4\ndt_factor = 0.2\n", "run.dt", "not both"),
    ("macro step not a multiple of dt", "[run]\ndt = 1e-4\nmacro_step = 2.5e-4\n", "run.macro_step", "whole multiple"),
    ("radius spread >= 1", "[bed]\nradius_spread = 1.0\n", "bed.radius_spread", "< 1"),
    ("bed too thin for its grains", "[bed]\ndepth = 0.01\n", "bed.depth", "two of the largest grains"),
    ("missing bed file", '[bed]\nbed_file = "nowhere.h5"\n', "bed.bed_file", "not found"),
    ("unknown mode", '[testbed]\nmode = "towed"\n', "testbed.mode", "'free'"),
    ("unknown coupling scheme", '[run]\nscheme = "newton"\n', "run.scheme", "gauss-seidel"),
    (
        "grousers thicker than their spacing",
        "[wheel]\ngrouser_count = 60\ngrouser_thickness = 0.004\n",
        "wheel.grouser_thickness",
        "spacing",
    ),
    # every number must be finite: inf and nan are named, not accepted
    ("infinite bed length", "[bed]\nlength = inf\n", "bed.length", "finite"),
    ("nan omega", "[testbed]\nomega = nan\n", "testbed.omega", "finite"),
    ("nan start position", "[testbed]\nstart_x = nan\n", "testbed.start_x", "finite"),
    ("infinite drawbar load", "[testbed]\ndrawbar_load = inf\n", "testbed.drawbar_load", "finite"),
    ("a drawbar load of 1e20 N", "[testbed]\ndrawbar_load = 1e20\n", "testbed.drawbar_load", "dragged backwards"),
    ("infinite snapshot interval", "[output]\nsnapshot_interval = inf\n", "output.snapshot_interval", "finite"),
    (
        "a ground 1e11 m up",
        "[terrain]\nmodel = 'analytic'\nsurface_height = 1e11\n",
        "terrain.surface_height",
        "within +-1e+06 m",
    ),
    (
        "erosion without bulldozing",
        "[terrain]\nmodel = 'scm'\nerosion_angle_deg = 5.0\n",
        "terrain.erosion_angle_deg",
        "bulldozing, which is off",
    ),
    (
        "a billion erosion passes a step",
        "[terrain]\nmodel = 'scm'\nerosion_iterations = 1000000000\n",
        "terrain.erosion_iterations",
        "<= 100",
    ),
    (
        "snapshots within a macro step",
        "[output]\nsnapshot_interval = 1e-6\n",
        "output.snapshot_interval",
        "once a macro",
    ),
    ("negative seed", "[bed]\nseed = -1\n", "bed.seed", ">= 0"),
    ("negative order seed", "[run]\norder_seed = -3\n", "run.order_seed", ">= 0"),
    ("omega zero", "[testbed]\nomega = 0.0\n", "testbed.omega", "> 0"),
    ("landing without gravity", "[scene]\ngravity = 0.0\n", "landing.enabled", "gravity"),
    # at rest for sqrt(r / |g|) = 1.3e3 s at 1e-8 m/s^2 (or a hold_time given) within max_time: never
    (
        "a landing too short to hold",
        "[scene]\ngravity = 1e-8\n",
        "landing.max_time",
        "every run would end 'no landing'",
    ),
    ("a hold longer than the landing", "[landing]\nhold_time = 2.0\n", "landing.max_time", "above 2.002 s"),
    ("a lab file's section", "[shear]\nnormal_stresses = [1.0]\n", "shear", "this is a lab file, for `cosim lab`"),
    ("scene name of 300 bytes", f"[scene]\nname = '{'n' * 300}'\n", "scene.name", "at most 128 bytes"),
    ("gravity pointing up", "[scene]\ngravity = [0.0, 0.0, 1.6]\n", "scene.gravity", "must point down"),
    ("gravity along the bed", "[scene]\ngravity = [1.6, 0.0, 0.0]\n", "scene.gravity", "within 60 deg"),
    ("a TOML date as the name", "[scene]\nname = 1979-05-27T07:32:00Z\n", "scene.name", "a date or time"),
    ("a TOML date in a list", "[scene]\ngravity = [0.0, 0.0, 1979-05-27]\n", "scene.gravity[2]", "a date or time"),
    # a boolean is no number (pydantic would read true as 1: gravity = true as 1 m/s^2)
    ("boolean gravity", "[scene]\ngravity = true\n", "scene.gravity", "not true or false"),
    ("boolean in a gravity vector", "[scene]\ngravity = [0.0, 0.0, true]\n", "scene.gravity", "not true or false"),
    ("boolean density", "[soil]\ndensity = false\n", "soil.density", "not true or false"),
    ("boolean substeps", "[run]\nmacro_step = true\n", "run.macro_step", "not true or false"),
    # and a switch takes true or false only (pydantic would read "no" as false, 1 as true)
    ("a switch as text", "[landing]\nenabled = 'no'\n", "landing.enabled", "must be true or false"),
    ("a switch as a number", "[soil.law]\nrolling = 1\n", "soil.law.rolling", "must be true or false"),
    # a finite number beyond SCENE_NUMBER_RANGE overflows what the run derives from it (the grain count,
    # the eq. 10 bound), or took a path that failed later under another key's name
    ("bed length of 1e300 m", "[bed]\nlength = 1e300\n", "bed.length", "1e+30"),
    ("load of 1e300 kg", "[testbed]\nmass = 1e300\n", "testbed.mass", "1e+30"),
    ("gravity of 1e300 m/s^2", "[scene]\ngravity = 1e300\n", "scene.gravity", "1e+30"),
    ("grain radius of 1e-300 m", "[bed]\nradius_mean = 1e-300\n", "bed.radius_mean", "1e-30"),
    ("seed beyond 64 bits", "[bed]\nseed = 99999999999999999999999\n", "bed.seed", "64-bit"),
    # a step far below the scene's scale: more than MAX_PHASE_STEPS steps in a phase, which never ends
    ("stiffness of 1e29 Pa", "[soil]\nyoungs_modulus = 1e29\n", "soil.youngs_modulus", "steps of landing (DEM"),
    ("DEM step of 1e-12 s", "[run]\ndt = 1e-12\nmacro_step = 1e-3\n", "run.dt", "steps of landing (DEM steps)"),
    ("macro step of 1e-12 s", "[run]\nmacro_step = 1e-12\n", "run.macro_step", "steps of landing (macro steps)"),
    ("SCM step of 1e-12 s", SCM_TERRAIN + "time_step = 1e-12\n", "terrain.time_step", "steps of landing (SCM"),
    # named as soil.ScmParameters at the run's start before
    (
        "Bekker moduli both 0",
        SCM_TERRAIN.replace("2.0e3", "0.0").replace("8.0e5", "0.0"),
        "terrain.k_c, terrain.k_phi",
        "carry no load",
    ),
]


def _merge(extra: str) -> str:
    """The tiny scene with the sections in `extra` replacing keys of the same section."""
    import tomli_w
    import tomllib

    data = tomllib.loads(TINY_SCENE)
    try:
        patch = tomllib.loads(extra)
    except tomllib.TOMLDecodeError:
        return TINY_SCENE + extra
    for section, values in patch.items():
        if section == "wheel" and values.get("type") == "mesh":
            data[section] = values  # a mesh wheel takes none of the grouser keys
        elif isinstance(values, dict) and isinstance(data.get(section), dict):
            data[section].update(values)
        else:
            data[section] = values
    return tomli_w.dumps(data)


@pytest.mark.parametrize("what,extra,field,allowed", BAD_SCENES, ids=[b[0] for b in BAD_SCENES])
def test_bad_scene_is_rejected_naming_the_field(tmp_path, what, extra, field, allowed):
    path = tmp_path / "bad.toml"
    path.write_text(_merge(extra))
    with pytest.raises(SceneError) as info:
        load_plan(path)
    message = str(info.value)
    assert field in message, message
    assert allowed in message, message


@pytest.mark.parametrize(
    "extra,field",
    [(BAD_SCENES[0][1], "bed.lenght"), (BAD_SCENES[3][1], "wheel.radius"), (BAD_SCENES[18][1], "run.macro_step")],
)
def test_cli_rejects_bad_scene_with_exit_2(tmp_path, capsys, extra, field):
    path = tmp_path / "bad.toml"
    path.write_text(_merge(extra))
    assert main(["run", str(path), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    assert field in capsys.readouterr().err
    assert not (tmp_path / "out").exists(), "nothing may be written for a bad scene"


def test_several_problems_are_all_listed(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text(_merge("[wheel]\nradius = -1.0\n[bed]\nlenght = 1.0\n"))
    with pytest.raises(SceneError) as info:
        load_plan(path)
    assert len(info.value.problems) == 2


def test_set_overrides_and_toml_round_trip(tmp_path):
    path = write_tiny(tmp_path)
    scene = load_scene(path, ["wheel.radius=0.02", "scene.name=other", 'scene.gravity="phobos"'])
    assert scene.wheel.radius == 0.02 and scene.scene.name == "other"
    again = scene_from_text(scene.to_toml())
    assert again.to_dict() == scene.to_dict()
    with pytest.raises(SceneError, match="wheel.radiu"):
        load_scene(path, ["wheel.radiu=0.02"])


def test_a_scene_saved_with_a_byte_order_mark_reads_as_without_and_a_folder_is_named(tmp_path):
    """Some Windows editors start a UTF-8 file with a byte-order mark, which tomllib takes for a statement
    ("Invalid statement (line 1, col 1)"): the scene reads as the same file without it."""
    path = write_tiny(tmp_path)
    marked = tmp_path / "marked.toml"
    marked.write_bytes(b"\xef\xbb\xbf" + Path(path).read_bytes())
    assert load_scene(marked).to_dict() == load_scene(path).to_dict()
    with pytest.raises(SceneError, match="is a folder; give a scene file"):
        load_scene(tmp_path)


@pytest.mark.parametrize("text", ["", "\n  \n", "# the rover's scene\n"], ids=["empty", "blank", "comments only"])
def test_a_scene_file_without_keys_is_refused_not_run_as_the_defaults(tmp_path, capsys, text):
    """A scene file cut to nothing was a valid scene of every default (a Phobos testbed named 'scene'):
    the run, lab, scale and export-fmu commands that read it refuse it by name."""
    path = tmp_path / "cut.toml"
    path.write_text(text)
    with pytest.raises(SceneError, match="the file holds no keys"):
        load_scene(path)
    assert load_scene(path, ['scene.name="given"']).scene.name == "given"  # keys given by --set instead
    out = tmp_path / "out"
    assert main(["run", str(path), "--out", str(out)]) == 2
    assert f"invalid scene in {path}" in capsys.readouterr().err and not out.exists()


def test_time_steps_make_whole_macro_steps(tmp_path):
    from soil.advisor import rayleigh_time_step

    plan = load_plan(write_tiny(tmp_path), ["run.macro_step=0.001"])
    m = plan.soil_material
    rayleigh = rayleigh_time_step(m.youngs_modulus, m.poisson_ratio, m.density, 0.0035 * 0.8)
    assert plan.macro_step == 0.001 and plan.substeps * plan.dt == pytest.approx(0.001, rel=1e-12)
    assert plan.dt <= 0.2 * rayleigh and plan.dt_setting == "run.dt_factor"
    assert load_plan(write_tiny(tmp_path), ["run.dt=1e-4"]).dt_setting == "run.dt"


def test_mesh_wheel_scene(tmp_path):
    pytest.importorskip("trimesh")
    from soil import GrouserWheel, MeshWheel

    vertices, triangles = GrouserWheel(
        radius=0.025, width=0.02, grouser_count=8, grouser_height=0.003, grouser_thickness=0.002
    ).to_mesh(arc_segments=64)
    MeshWheel(vertices, triangles).save(tmp_path / "wheel.obj")
    (tmp_path / "mesh.toml").write_text(_merge('[wheel]\ntype = "mesh"\nfile = "wheel.obj"\n'))
    plan = load_plan(tmp_path / "mesh.toml")
    assert plan.wheel.outer_radius == pytest.approx(0.028, rel=0.02) and plan.wheel.width == pytest.approx(0.02)
    (tmp_path / "broken.obj").write_text("v 0 0 0\nv 1 0 0\nf 1 2 3\n")
    (tmp_path / "broken.toml").write_text(_merge('[wheel]\ntype = "mesh"\nfile = "broken.obj"\n'))
    with pytest.raises(SceneError, match="wheel.file"):
        load_plan(tmp_path / "broken.toml")


@pytest.mark.parametrize("path", sorted(glob.glob(os.path.join(EXAMPLES, "*.toml"))))
def test_examples_are_valid(path, tmp_path_factory):
    overrides = ['scene.device="cpu"']
    if "fmus/" in Path(path).read_text():  # the example's FMUs are built from rover_models/fmu_src first
        pytest.importorskip("pythonfmu")
        from rover_models.fmu_src.build_fmus import build_rover_fmu, build_slip_controller_fmu

        folder = tmp_path_factory.mktemp("example_fmus")
        overrides += [
            f'rover.file="{build_rover_fmu(folder)}"',
            f'rover.controllers.fmu_slip.file="{build_slip_controller_fmu(folder, 4)}"',
        ]
    if "[repose]" in Path(path).read_text() or "[shear]" in Path(path).read_text():  # a lab scene (cosim lab)
        from cosim.lab.scene import load_lab_plan

        load_lab_plan(path, overrides)
        return
    plan = load_plan(path, overrides)
    assert plan.drive_steps >= 1


def test_a_bed_file_of_another_soil_or_gravity_is_refused(tmp_path, tiny_bed):
    """A saved bed brings its own grains: a scene whose [soil] or gravity differs is refused, naming both."""
    plan = load_plan(write_tiny(tmp_path), [f'bed.bed_file="{tiny_bed}"'])
    assert plan.bed.bed_file == str(tiny_bed)
    with pytest.raises(SceneError, match=r"bed.bed_file: .*youngs_modulus 1000000.0 in the file vs 2000000.0"):
        load_plan(write_tiny(tmp_path), [f'bed.bed_file="{tiny_bed}"', "soil.youngs_modulus=2e6"])
    with pytest.raises(SceneError, match=r"bed.bed_file: the bed was settled under gravity"):
        load_plan(write_tiny(tmp_path), [f'bed.bed_file="{tiny_bed}"', 'scene.gravity="mars"'])


@pytest.mark.parametrize("content", [b"not an hdf5 file", b"\x89HDF\r\n\x1a\n" + b"\0" * 40])
def test_a_bed_file_that_is_not_a_bed_is_refused(tmp_path, content):
    bad = tmp_path / "bad.h5"
    bad.write_bytes(content)
    with pytest.raises(SceneError, match=r"bed.bed_file: .*bad.h5"):
        load_plan(write_tiny(tmp_path), [f'bed.bed_file="{bad}"'])


def test_a_missing_cuda_device_is_a_scene_error(tmp_path):
    import warp as wp

    if wp.is_cuda_available():
        pytest.skip("this machine has a GPU")
    with pytest.raises(SceneError, match=r"scene.device: 'cuda' asked for.*it has: cpu"):
        load_plan(write_tiny(tmp_path), ['scene.device="cuda"'])


def test_every_numeric_scene_key_documents_its_unit():
    """key_unit reads each number's unit from its key's documentation (what a sweep's and a calibration's
    tables write beside it): every numeric key of every section has one, as documented."""
    import typing

    from pydantic import BaseModel

    from cosim.scene import Scene, key_unit

    def numbers(model, prefix=""):
        for name, field in model.model_fields.items():
            kinds = (field.annotation, *typing.get_args(field.annotation))
            section = next((t for t in kinds if isinstance(t, type) and issubclass(t, BaseModel)), None)
            if section is not None:
                yield from numbers(section, f"{prefix}{name}.")
            elif float in kinds or int in kinds:
                yield prefix + name

    keys = list(numbers(Scene))
    assert len(keys) > 90 and not [key for key in keys if key_unit(key) is None]
    expected = {"wheel.radius": "m", "soil.youngs_modulus": "Pa", "soil.stick_angle_deg": "deg", "testbed.slip": "1"}
    expected.update({"testbed.omega": "rad/s", "patch.tile_margin": "m", "run.substeps": "count"})
    expected["scene.gravity"] = "m/s^2"
    assert {key: key_unit(key) for key in expected} == expected
    assert key_unit("wheel.nope") is None and key_unit("nope.radius") is None and key_unit("landing.enabled") is None


@pytest.mark.parametrize(
    "args, option",
    [
        (["study", "slip", "--slips", "0.1,,0.2"], "--slips '0.1,,0.2'"),
        (["study", "precision", "--precisions", "single,"], "--precisions 'single,'"),
        (["sweep", "--param", "testbed.slip=0.1,"], "--param testbed.slip '0.1,'"),
    ],
)
def test_a_comma_list_with_an_empty_entry_is_refused(tmp_path, capsys, args, option):
    """'0.1,,0.2' is a value lost to a typo, not the list 0.1, 0.2: refused by name, nothing written."""
    command, *rest = args
    scene = str(write_tiny(tmp_path))
    line = [command, *rest[:1], scene, *rest[1:]] if command == "study" else [command, scene, *rest]
    assert main([*line, "--out", str(tmp_path / "out"), "--serial"]) == 2
    assert f"{option}: an empty entry" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_slip_controller_never_commands_a_backward_speed():
    from pydantic import ValidationError

    from cosim.scene import DriveSection

    DriveSection(kind="slip", target_slip=0.2, omega_max=1.0, omega_min=0.0)
    with pytest.raises(ValidationError, match="omega_min"):
        DriveSection(kind="slip", target_slip=0.2, omega_max=1.0, omega_min=-1.0)


def test_numbers_passed_to_a_model_as_they_are_keep_any_finite_magnitude():
    """An FMU's parameters (Modelica's infinity is 1e60) and a python drive's arguments go to the model
    unchanged: no magnitude bound, which holds for what a run derives numbers from. A boolean where a
    parameter's number is asked is named by its entry."""
    from pydantic import ValidationError

    from cosim.scene import DriveSection

    assert DriveSection(kind="fmu", file="c.fmu", start_values={"limit": 1e60}).start_values == {"limit": 1e60}
    assert DriveSection(kind="python", function="m:f", args={"tol": 1e-40, "seed": 2**64}).args["tol"] == 1e-40
    with pytest.raises(ValidationError, match=r"\['gain'\]: must be a number, not true or false"):
        DriveSection(kind="fmu", file="c.fmu", start_values={"gain": True})
    with pytest.raises(ValidationError, match="finite"):
        DriveSection(kind="fmu", file="c.fmu", start_values={"limit": float("inf")})


def test_scms_own_coupling_step_far_too_fine_names_the_keys_it_comes_from(tmp_path):
    """Without run.macro_step a scene on SCM alone couples at SCM's own step (the wheel's bounce on the
    elastic stiffness): a stiffness of 1e29 Pa makes it 1e-15 s, and the refusal says where it comes from."""
    import tomli_w
    import tomllib

    data = tomllib.loads(_merge(SCM_TERRAIN))
    del data["run"]["macro_step"]
    data["terrain"]["elastic_stiffness"] = 1e29
    path = tmp_path / "scm.toml"
    path.write_text(tomli_w.dumps(data))
    with pytest.raises(SceneError, match=r"run.macro_step: .* steps of landing \(macro steps\).*SCM's own coupling"):
        load_plan(path)
    data["terrain"]["elastic_stiffness"] = 2.0e7
    path.write_text(tomli_w.dumps(data))
    assert load_plan(path).substeps == 1


def test_a_scene_nested_too_deep_is_refused(tmp_path):
    """5,000 nested lists ran Python out of recursion ('unexpected error', exit 1)."""
    path = tmp_path / "deep.toml"
    path.write_text("a = " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(SceneError, match="nested too deep"):
        load_scene(path)


def test_a_sweep_key_given_twice_and_a_huge_list_are_named_briefly(tmp_path, capsys):
    """A repeated --param key replaced the first without a word; a refused list of ten million entries
    was echoed whole (30 MB on stderr)."""
    from cosim.study import parse_params

    with pytest.raises(SceneError, match="--param wheel.radius: given twice"):
        parse_params(["wheel.radius=0.03", "wheel.radius=0.04"])
    with pytest.raises(SceneError, match="--param wheel.radius: the value 0.1 is given twice"):
        parse_params(["wheel.radius=0.1,0.10"])  # one run twice, counted as two points
    # the scene coerces an integer to the float it takes: 1 and 1.0 were two points of one run (probe)
    with pytest.raises(SceneError, match="--param testbed.omega: the value 1.0 is given twice"):
        parse_params(["testbed.omega=1,1.0"])
    with pytest.raises(SceneError, match=r"the value \[1.0, 2\] is given twice"):
        parse_params(["rover.drive.speed=[[1, 2], [1.0, 2]]"])
    assert parse_params(["scene.precision=single,double"]) == {"scene.precision": ["single", "double"]}
    with pytest.raises(SceneError, match="--param: 1100 points .* more than 1000"):  # each point is planned first
        parse_params(
            [
                "wheel.radius=" + ",".join(str(0.01 + k * 1e-4) for k in range(110)),
                "testbed.slip=" + ",".join(str(k / 20) for k in range(10)),
            ]
        )
    with pytest.raises(SceneError) as info:
        scene_from_text(_merge("[output]\nflush_every = [" + "1," * 100_000 + "1]\n"))
    assert "output.flush_every" in str(info.value) and " ... " in str(info.value) and len(str(info.value)) < 1000


def test_list_values_are_swept_as_one_toml_array_and_tabulated_in_one_cell(tmp_path, capsys):
    """A list value (a per-wheel speed, a body size) was split at its commas; it is given as one TOML array
    of the values, reaches each point's scene as a list, and study.csv quotes it in one cell (the CSV was
    joined by hand: a value holding a comma shifted every column after it)."""
    import csv

    from cosim.study import _write_csv, parse_params

    grid = parse_params(["rover.mmx.body_size=[[0.1, 0.08, 0.04], [0.2, 0.1, 0.05]]", "wheel.radius=[0.03, 0.04]"])
    assert grid == {"rover.mmx.body_size": [[0.1, 0.08, 0.04], [0.2, 0.1, 0.05]], "wheel.radius": [0.03, 0.04]}
    with pytest.raises(SceneError, match=r"--param x: '\[1, 2' is no TOML array of values"):
        parse_params(["x=[1, 2"])
    rows = [{"rover.mmx.body_size": [0.1, 0.08, 0.04], "rover.file": "a,b.xml", "sinkage": 0.01, "slip": None}]
    keys = ["rover.mmx.body_size", "rover.file", "sinkage", "slip"]
    _write_csv(str(tmp_path / "study.csv"), rows, keys, {"sinkage": "m", "rover.mmx.body_size": "m"})
    header, row = list(csv.reader(open(tmp_path / "study.csv", newline="")))
    assert header == ["rover.mmx.body_size [m]", "rover.file", "sinkage [m]", "slip"]
    assert row == ["[0.1, 0.08, 0.04]", "a,b.xml", "0.01", ""]
    # a sweep's points take the lists whole: a gravity vector of two components is refused as that
    # point's scene (before any run), its list named as one value
    scene = write_tiny(tmp_path)
    out = tmp_path / "sweep"
    assert main(["sweep", scene, "--param", "scene.gravity=[[0.0, 0.0, -1.62], [0.0, -1.62]]", "--out", str(out)]) == 2
    assert "point {'scene.gravity': [0.0, -1.62]}" in capsys.readouterr().err and not out.exists()


def test_cosim_scale_to_a_boolean_gravity_is_refused(tmp_path, capsys):
    assert main(["scale", str(write_tiny(tmp_path)), "--gravity", "true", "--out", str(tmp_path / "t.toml")]) == 2
    assert "--gravity: a preset name or a magnitude [m/s^2], not true" in capsys.readouterr().err
    assert not (tmp_path / "t.toml").exists()
    # a gravity whose twin leaves what a scene takes: one line naming --gravity (was numpy's overflow
    # warnings and 17 lines about the twin's derived keys)
    for gravity, words in (("1e300", "magnitude <= 1e+30"), ("1e12", "allowed: 1e-08 .. 1e+08 x")):
        assert main(["scale", str(write_tiny(tmp_path)), "--gravity", gravity, "--out", str(tmp_path / "t.toml")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n  - ") == 1 and "--gravity: " in err and words in err, err
    assert not (tmp_path / "t.toml").exists()
    # the twin written over its own scene, even with --overwrite: the scene was lost to its twin
    scene = write_tiny(tmp_path)
    before = Path(scene).read_bytes()
    assert main(["scale", scene, "--gravity", "earth", "--out", scene, "--overwrite"]) == 2
    assert "is the scene the command reads" in capsys.readouterr().err and Path(scene).read_bytes() == before


def test_a_number_written_as_a_text_is_refused_where_only_a_number_may_stand(tmp_path):
    """`youngs_modulus = "1.0e6"` and `gravity = [0, 0, "-9.81"]` were read as numbers (pydantic's lax mode);
    a text where a text may stand (a preset, a precision) still is one."""
    path = tmp_path / "quoted.toml"
    path.write_text(TINY_SCENE.replace("youngs_modulus = 1.0e6", 'youngs_modulus = "1.0e6"'))
    assert 'youngs_modulus = "1.0e6"' in path.read_text()
    with pytest.raises(SceneError, match=r"soil.youngs_modulus: must be a number, not a text: write a TOML number"):
        load_scene(path)
    scene = write_tiny(tmp_path)
    for override, key in (
        ('run.duration="0.12"', "run.duration"),
        ('soil.stick_angle_deg="30"', "soil.stick_angle_deg"),
        ('scene.gravity=[0, 0, "-9.81"]', r"scene.gravity: \[2\]"),
    ):
        with pytest.raises(SceneError, match=rf"{key}: must be a number, not a text"):
            load_scene(scene, [override])
    assert load_scene(scene, ['scene.gravity="earth"', 'scene.precision="single"']).scene.gravity == "earth"


def test_the_pid_keys_are_refused_where_the_scene_steps_at_a_fixed_dt(tmp_path):
    """run.tolerance = 1e-9 or run.dt_max under step_control = "fixed" were ignored without a word; a scene
    written back with every default (a run's scene.toml) still reads."""
    scene = write_tiny(tmp_path)
    for override in ("run.tolerance=1e-9", "run.dt_max=1e-3", "run.dt_min=1e-6"):
        key = override.split("=")[0]
        with pytest.raises(SceneError, match=rf'{key}: only the PID step control uses it \(step_control = "pid"\)'):
            load_scene(scene, [override])
    written = load_scene(scene)
    assert scene_from_text(written.to_toml()).run.tolerance == written.run.tolerance
    pid = load_scene(scene, ['run.step_control="pid"', "run.tolerance=1e-3", "run.dt_max=1e-3"])
    assert pid.run.dt_max == 1e-3


def test_a_pid_step_far_below_the_scene_or_a_macro_step_below_its_shortest_is_refused(tmp_path):
    """run.dt_max = 1e-30 under the PID settled forever, deaf to Ctrl-C and SIGTERM (a macro step's
    substeps loop on the device); a macro step shorter than run.dt_min broke every substep's bound."""
    scene = write_tiny(tmp_path)
    pid = ['run.step_control="pid"']
    with pytest.raises(SceneError, match=r"run.dt_max: \S+ steps of .* \(PID substeps\), more than 1e\+10"):
        load_plan(scene, [*pid, "run.dt_max=1e-30"])
    short = [*pid, "run.dt_min=1e-4", "run.dt_max=2e-4", "run.macro_step=1e-5", "output.snapshot_interval=0"]
    with pytest.raises(SceneError, match=r"run.macro_step: the macro step \(1e-05 s\) is shorter than .* run.dt_min"):
        load_plan(scene, short)
    assert load_plan(scene, [*pid, "run.dt_max=1e-4"]).dt_max == 1e-4


def test_a_gravity_that_is_not_finite_is_one_line(tmp_path):
    """scene.gravity = nan gave three lines, one per kind the key takes ('must be a valid string', 'must be
    a valid list'): one line says what a gravity must be."""
    scene = write_tiny(tmp_path)
    for value, words in (("nan", "magnitude must be a finite number >= 0"), ("[0, 0, inf]", "vector must be 3")):
        with pytest.raises(SceneError) as refused:
            load_scene(scene, [f"scene.gravity={value}"])
        (problem,) = refused.value.problems
        assert problem.startswith(f"scene.gravity: a gravity {words}"), problem
