"""Scene files: every kind of mistake is rejected with a message naming the field."""

import glob
import os

import pytest

from cosim.cli import main
from cosim.scene import SceneError, load_scene, scene_from_text
from cosim_tiny import TINY_SCENE, write_tiny

EXAMPLES = os.path.join(os.path.dirname(__file__), "..", "examples")

BAD_SCENES = [
    # (what is wrong, TOML added to / replacing the tiny scene, field named, words of the allowed values)
    ("unknown key", "[bed]\nlenght = 0.2\n", "bed.lenght", "unknown key"),
    ("unknown section", "[whee]\nradius = 0.1\n", "whee", "unknown key"),
    ("wrong type", "[testbed]\nmass = \"heavy\"\n", "testbed.mass", "number"),
    ("negative radius", "[wheel]\nradius = -0.03\n", "wheel.radius", "> 0"),
    ("slip angle above stick angle", "[soil]\nstick_angle_deg = 20.0\nslip_angle_deg = 30.0\n",
     "soil.slip_angle_deg", "stick_angle_deg"),
    ("friction angle >= 90 deg", "[soil]\nstick_angle_deg = 90.0\n", "soil.stick_angle_deg", "< 90"),
    ("missing mesh file", "[wheel]\ntype = \"mesh\"\nfile = \"no_such_wheel.obj\"\n", "wheel.file", "not found"),
    ("mesh keys on a grouser wheel", "[wheel]\nfile = \"w.obj\"\n", "wheel.file", "mesh"),
    ("unknown gravity preset", "[scene]\ngravity = \"titan\"\n", "scene.gravity", "phobos"),
    ("gravity vector of 2", "[scene]\ngravity = [0.0, -1.0]\n", "scene.gravity", "3"),
    ("unknown precision", "[scene]\nprecision = \"half\"\n", "scene.precision", "'double'"),
    ("unknown device", "[scene]\ndevice = \"tpu\"\n", "scene.device", "cuda"),
    ("wheel wider than the bed", "[wheel]\nwidth = 0.07\n", "wheel.width", "wider than the bed"),
    ("wheel too close to the side walls", "[wheel]\nwidth = 0.052\n", "wheel.width", "side walls"),
    ("start too close to the wall", "[testbed]\nstart_x = 0.02\n", "testbed.start_x", "start_x >="),
    ("would drive into the far wall", "[run]\nduration = 10.0\n", "run.duration", "duration <="),
    ("dt <= 0", "[run]\ndt = 0.0\n", "run.dt", "> 0"),
    ("dt and dt_factor", "[run]\ndt = 1e-4\ndt_factor = 0.2\n", "run.dt", "not both"),
    ("macro step not a multiple of dt", "[run]\ndt = 1e-4\nmacro_step = 2.5e-4\n", "run.macro_step",
     "whole multiple"),
    ("radius spread >= 1", "[bed]\nradius_spread = 1.0\n", "bed.radius_spread", "< 1"),
    ("bed too thin for its grains", "[bed]\ndepth = 0.01\n", "bed.depth", "two of the largest grains"),
    ("missing bed file", "[bed]\nbed_file = \"nowhere.h5\"\n", "bed.bed_file", "not found"),
    ("unknown mode", "[testbed]\nmode = \"towed\"\n", "testbed.mode", "'free'"),
    ("unknown coupling scheme", "[run]\nscheme = \"newton\"\n", "run.scheme", "gauss-seidel"),
    ("grousers thicker than their spacing", "[wheel]\ngrouser_count = 60\ngrouser_thickness = 0.004\n",
     "wheel.grouser_thickness", "spacing"),
]


def _merge(extra: str) -> str:
    """The tiny scene with the sections in `extra` replacing keys of the same section."""
    import tomllib

    from cosim.scene import dump_toml

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
    return dump_toml(data)


@pytest.mark.parametrize("what,extra,field,allowed", BAD_SCENES, ids=[b[0] for b in BAD_SCENES])
def test_bad_scene_is_rejected_naming_the_field(tmp_path, what, extra, field, allowed):
    path = tmp_path / "bad.toml"
    path.write_text(_merge(extra))
    with pytest.raises(SceneError) as info:
        load_scene(path)
    message = str(info.value)
    assert field in message, message
    assert allowed in message, message


@pytest.mark.parametrize("extra,field", [(BAD_SCENES[0][1], "bed.lenght"), (BAD_SCENES[3][1], "wheel.radius"),
                                         (BAD_SCENES[18][1], "run.macro_step")])
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
        load_scene(path)
    assert len(info.value.problems) == 2


def test_set_overrides_and_toml_round_trip(tmp_path):
    path = write_tiny(tmp_path)
    scene = load_scene(path, ["wheel.radius=0.02", "scene.name=other", 'scene.gravity="phobos"'])
    assert scene.wheel.radius == 0.02 and scene.scene.name == "other"
    again = scene_from_text(scene.to_toml())
    assert again.to_dict() == scene.to_dict()
    with pytest.raises(SceneError, match="wheel.radiu"):
        load_scene(path, ["wheel.radiu=0.02"])


def test_time_steps_make_whole_macro_steps(tmp_path):
    scene = load_scene(write_tiny(tmp_path), ["run.macro_step=0.001"])
    dt, h, substeps = scene.time_steps()
    assert h == 0.001 and substeps * dt == pytest.approx(h, rel=1e-12) and dt <= 0.2 * scene.rayleigh_step()


def test_mesh_wheel_scene(tmp_path):
    pytest.importorskip("trimesh")
    from soil import GrouserWheel, MeshWheel

    vertices, triangles = GrouserWheel(radius=0.025, width=0.02, grouser_count=8, grouser_height=0.003,
                                       grouser_thickness=0.002).to_mesh(arc_segments=64)
    MeshWheel(vertices, triangles).save(tmp_path / "wheel.obj")
    (tmp_path / "mesh.toml").write_text(_merge('[wheel]\ntype = "mesh"\nfile = "wheel.obj"\n'))
    scene = load_scene(tmp_path / "mesh.toml")
    outer, width, _ = scene.wheel_extent()
    assert outer == pytest.approx(0.028, rel=0.02) and width == pytest.approx(0.02)


@pytest.mark.parametrize("path", sorted(glob.glob(os.path.join(EXAMPLES, "*.toml"))))
def test_examples_are_valid(path):
    scene = load_scene(path)
    assert scene.macro_step_count() >= 1
