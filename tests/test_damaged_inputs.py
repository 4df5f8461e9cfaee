"""Nothing lost, nothing silently wrong: damaged or foreign files (results, checkpoint, bed, mesh), a
scene too large for the machine, a scene name that is a path, kill -9 after the final checkpoint,
SIGTERM, and a bed that explodes while it settles. Each case asserts the exit code, the first line
of the message, and that no file written before changed (checksums).

One complete and one interrupted tiny run are shared by the module; each case works on a copy."""

import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from cosim.cli import main
from cosim.launch import run_plan
from cosim.plan import load_plan
from cosim.study import STUDY_MARK
from helpers import write_tiny


def digests(folder) -> dict:
    """sha256 of every file under folder (the lock file aside)."""
    out = {}
    for root, _, files in os.walk(folder):
        for name in files:
            if name != ".lock":
                path = os.path.join(root, name)
                with open(path, "rb") as f:
                    out[os.path.relpath(path, folder)] = hashlib.sha256(f.read()).hexdigest()
    return out


def first_error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    assert "Scheduler at" not in err and "Register worker" not in err, err  # the dask cluster's chatter stays quiet
    lines = [line for line in err.splitlines() if line.startswith("cosim: error:")]
    assert lines, err
    return lines[0]


def resume_refused(folder, capsys) -> str:
    """`cosim resume FOLDER`, which must be refused (exit 2) with every file of the folder as it was; the
    first line of its error."""
    before = digests(folder)
    assert main(["resume", str(folder), "--no-progress"]) == 2
    line = first_error_line(capsys)
    assert digests(folder) == before
    return line


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_tiny(tmp_path_factory.mktemp("damaged"))


@pytest.fixture(scope="module")
def complete(scene, tiny_bed, tmp_path_factory):
    """A finished tiny run on the shared bed."""
    out = tmp_path_factory.mktemp("complete") / "run"
    result = run_plan(load_plan(scene, [f'bed.bed_file="{tiny_bed}"']), str(out))
    assert result.status in ("complete", "unsteady")
    return out


def stopped_after_a_checkpoint(plan, out) -> None:
    """Run `plan` into `out` and stop it hard three macro steps after its first checkpoint."""
    seen = []

    def checkpoint(runner):
        seen.append(runner.system.coupler.step_count)

    def step(runner):
        if seen and runner.system.coupler.step_count == seen[0] + 3:
            raise KeyboardInterrupt("test: stopped")

    with pytest.raises(KeyboardInterrupt):
        run_plan(plan, str(out), hooks={"checkpoint": checkpoint, "step": step})


@pytest.fixture(scope="module")
def interrupted(scene, tiny_bed, tmp_path_factory):
    """A tiny run stopped hard three macro steps after its first checkpoint (status interrupted)."""
    out = tmp_path_factory.mktemp("interrupted") / "run"
    stopped_after_a_checkpoint(load_plan(scene, [f'bed.bed_file="{tiny_bed}"']), out)
    assert json.loads((out / "run.json").read_text())["status"] == "interrupted"
    return out


def copy(folder, tmp_path, name="copy"):
    target = tmp_path / name
    shutil.copytree(folder, target, ignore=shutil.ignore_patterns(".lock"))
    return target


def cut(path, fraction):
    os.truncate(path, int(os.path.getsize(path) * fraction))


# -- row 1: a bed_file that is another HDF5 file ------------------------------------------------
def test_row01_a_results_file_given_as_bed_file_is_one_clear_line(scene, complete, tmp_path, capsys):
    before = digests(complete)
    for command in (["advise", scene], ["run", scene, "--out", str(tmp_path / "o"), "--no-progress"]):
        assert main([*command, "--set", f'bed.bed_file="{complete / "results.h5"}"']) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err and err.startswith("cosim: error: invalid scene")
        assert "bed.bed_file" in err and "not a regolith-cosim bed file" in err, err
    assert digests(complete) == before and not (tmp_path / "o").exists()


# -- row 2: a scene too large for the machine -----------------------------------------------------
HUGE = ["--set", "bed.length=10", "--set", "bed.width=10", "--set", "bed.depth=1", "--set", "bed.radius_mean=0.001"]


def test_row02_a_huge_scene_is_refused_with_the_estimate(scene, tmp_path, capsys):
    assert main(["advise", scene, *HUGE]) == 0
    out = capsys.readouterr().out
    assert "memory estimate" in out and "grains in double" in out and "DOES NOT FIT" in out
    assert main(["run", scene, "--out", str(tmp_path / "huge"), "--no-progress", *HUGE]) == 2
    line = first_error_line(capsys)
    assert "does not fit this machine" in line and "GB of host memory" in line and "free" in line, line
    assert not (tmp_path / "huge").exists()


def test_row02_a_huge_patch_is_refused_with_the_estimate(tmp_path, capsys):
    """A [patch] runs on its window's grains, not the tile's: a kilometre-wide window of 2 cm grains
    (about 4e9 grains) is refused before the tile is settled."""
    huge = ["--set", "patch.length=1000", "--set", "patch.width=1000"]
    rover = os.path.join(os.path.dirname(__file__), "..", "examples", "phobos_rover_patch.toml")
    assert main(["advise", rover, *huge]) == 0
    assert "DOES NOT FIT" in capsys.readouterr().out
    assert main(["run", rover, "--out", str(tmp_path / "huge"), "--no-progress", *huge]) == 2
    line = first_error_line(capsys)
    assert "does not fit this machine" in line and "GB of host memory" in line, line
    assert not (tmp_path / "huge").exists()


@pytest.mark.parametrize("precision", ["single", "mixed", "double"])
def test_the_memory_estimate_matches_the_measured_bytes_per_grain(precision):
    """soil.memory's formula against Simulation.bytes_per_grain() of a small bed (monitor armed)."""
    from soil import Simulation
    from soil.bed import BedSpec, build_bed, grain_count
    from soil.memory import device_bytes_per_grain

    spec = BedSpec(length=0.06, width=0.04, depth=0.03, radius_mean=0.002)
    model, state, control = build_bed(spec, "moon").finalize(device="cpu", precision=precision)
    assert model.particle_count == grain_count(spec)
    sim = Simulation(model, state, control)
    sim.monitor.arm(sim)
    measured = sim.bytes_per_grain()["total"]
    assert measured == pytest.approx(device_bytes_per_grain(precision), rel=0.1)


def _device_bytes_held(root) -> int:
    """Bytes of every distinct Warp array reachable from `root` through the soil package's objects and their
    containers (a view counted once, at its allocation's largest capacity): what the object holds, counted
    without asking it."""
    import gc
    import types

    import warp as wp

    spans: dict[int, int] = {}
    seen: set[int] = set()
    todo = [root]
    while todo:
        obj = todo.pop()
        if id(obj) in seen or isinstance(obj, (type, types.ModuleType, str, bytes, int, float, np.ndarray)):
            continue
        seen.add(id(obj))
        if isinstance(obj, wp.array):
            if obj.ptr:
                spans[obj.ptr] = max(spans.get(obj.ptr, 0), obj.capacity)
        elif isinstance(obj, (dict, list, tuple, set)) or (type(obj).__module__ or "").startswith("soil"):
            todo.extend(gc.get_referents(obj))
    return sum(spans.values())


@pytest.mark.parametrize("precision", ["single", "mixed", "double"])
def test_bytes_per_grain_counts_every_device_array_the_simulation_holds(precision):
    """Simulation.bytes_per_grain() (what soil.memory's estimate was measured from) against the arrays the
    simulation holds after a macro step, found by walking its objects: it left out the grains' constants, the
    external force and the list saved at each macro step's start (44 + 92 B a grain in mixed, 4 %)."""
    from soil import Simulation
    from soil.bed import BedSpec, build_bed

    spec = BedSpec(length=0.12, width=0.06, depth=0.03, radius_mean=0.002)
    model, state, control = build_bed(spec, "moon").finalize(device="cpu", precision=precision)
    sim = Simulation(model, state, control)
    sim.macro_step(2, 1e-6)
    sim.monitor.arm(sim)
    counted = sim.bytes_per_grain()["total"] * model.particle_count
    held = _device_bytes_held(sim)
    assert counted <= held, "nothing counted that is not held"
    assert held - counted < 0.005 * held, (held - counted) / model.particle_count  # fixed-size arrays only


# -- rows 3, 4, 5: a results.h5 cut short -------------------------------------------------------
def test_row03_resume_of_an_interrupted_run_with_a_cut_results_file(interrupted, tmp_path, capsys):
    folder = copy(interrupted, tmp_path)
    cut(folder / "results.h5", 0.5)
    line = resume_refused(folder, capsys)
    assert "results.h5: the results file is truncated" in line and "nothing was changed" in line, line
    assert "checkpoint" in line and "--overwrite" in line


@pytest.mark.parametrize("damage", ["a series gone", "a series cut short", "a snapshot dataset gone", "a bad summary"])
def test_row03b_a_results_file_missing_a_part_is_refused_before_anything_changes(
    interrupted, complete, tmp_path, capsys, damage
):
    """A readable HDF5 results.h5 that lacks what a run writes (a dataset deleted, a series shorter than
    the others, a summary that is not JSON): resume refuses it before it rewrites the file or removes
    the XDMF data, and plot, view and export name the file; exit 2 each, nothing changed."""
    import h5py

    readers = {  # the commands that read the damaged part
        "a series gone": [["plot"], ["view"]],
        "a series cut short": [["plot"]],
        "a snapshot dataset gone": [["view"], ["export", "vtkhdf"]],
        "a bad summary": [["plot"]],
    }
    for kind, source, commands in (
        ("interrupted", interrupted, [["resume"]]),
        ("complete", complete, readers[damage]),
    ):
        folder = copy(source, tmp_path, name=kind)
        with h5py.File(folder / "results.h5", "a") as f:
            if damage == "a series gone":
                del f["wheels/sinkage"]
            elif damage == "a series cut short":
                f["wheels/drawbar_pull"].resize(3, axis=0)
            elif damage == "a snapshot dataset gone":
                del f["particles/position"]
            else:
                f.attrs["summary"] = "{bad"
        before = digests(folder)
        for command in commands:
            args = [*command, str(folder)] + (["--no-progress"] if command == ["resume"] else [])
            if command == ["view"]:
                args += ["--out", str(tmp_path / "frame.png")]
            assert main(args) == 2, (damage, command)
            line = first_error_line(capsys)
            assert "results.h5" in line and "damaged" in line, line
            assert digests(folder) == before, (damage, command)


def test_row03c_a_file_whose_writer_was_killed_inside_a_flush_still_resumes(interrupted, tmp_path, capsys):
    """A writer killed between two datasets of one flush leaves some series a row longer than others,
    its status 'running': not damage. Resume cuts every series to its checkpoint; view reads the
    snapshots every dataset holds."""
    import h5py

    folder = copy(interrupted, tmp_path)
    with h5py.File(folder / "results.h5", "a") as f:
        f.attrs["status"] = "running"
        for name in ("wheels/sinkage", "particles/position"):
            dataset = f[name]
            dataset.resize(dataset.shape[0] + 1, axis=0)
    assert main(["view", str(folder), "--out", str(tmp_path / "frame.png"), "--dpi", "40"]) == 0
    assert main(["resume", str(folder), "--no-progress"]) in (0, 6)


def test_row04_plot_of_a_cut_results_file_writes_no_empty_figures(interrupted, tmp_path, capsys):
    folder = copy(interrupted, tmp_path)
    cut(folder / "results.h5", 0.5)
    before = digests(folder)
    assert main(["plot", str(folder)]) == 2
    line = first_error_line(capsys)
    assert "results.h5: the results file is truncated" in line and "no plot was written" in line, line
    assert digests(folder) == before and not (folder / "plots").exists()


def test_row05_plot_of_a_complete_run_cut_to_30_percent_fails_at_once(complete, tmp_path, capsys):
    folder = copy(complete, tmp_path)
    cut(folder / "results.h5", 0.3)
    before = digests(folder)
    start = time.perf_counter()
    assert main(["plot", str(folder)]) == 2
    assert time.perf_counter() - start < 20  # the SWMR read used to retry for minutes
    assert "truncated" in first_error_line(capsys)
    assert digests(folder) == before


def test_row05b_view_and_export_of_a_results_file_with_a_damaged_header_say_so(complete, tmp_path, capsys):
    """Flipped bits in an HDF5 object header (its checksum fails): `cosim view` and `cosim export` were an
    unexpected error (exit 1, h5py's KeyError); they are exit 2 naming the file, the earlier picture kept."""
    folder = copy(complete, tmp_path)
    picture = tmp_path / "frame.png"
    assert main(["view", str(folder), "--out", str(picture), "--dpi", "40"]) == 0
    data = bytearray((folder / "results.h5").read_bytes())
    headers = [m.start() for m in re.finditer(b"OHDR", bytes(data))]
    assert len(headers) > 3
    data[headers[len(headers) // 2] + 12] ^= 0xFF  # inside a dataset's object header, not its signature
    (folder / "results.h5").write_bytes(bytes(data))
    before = digests(folder)
    before_picture = picture.read_bytes()
    for command in (
        ["view", str(folder), "--out", str(picture), "--dpi", "40", "--overwrite"],
        ["export", "vtkhdf", str(folder), "--out", str(tmp_path / "x.vtkhdf")],
    ):
        capsys.readouterr()
        assert main(command) == 2, command
        assert "results.h5: the results file is damaged" in first_error_line(capsys)
    assert digests(folder) == before and picture.read_bytes() == before_picture
    assert not (tmp_path / "x.vtkhdf").exists()


# -- rows 6, 7: a damaged or foreign checkpoint ---------------------------------------------------
@pytest.mark.parametrize("damage", ["cut", "flipped"])
def test_row06_resume_with_a_damaged_checkpoint(interrupted, tmp_path, capsys, damage):
    folder = copy(interrupted, tmp_path)
    path = folder / "checkpoint.npz"
    if damage == "cut":
        cut(path, 0.5)
    else:
        data = bytearray(path.read_bytes())
        data[len(data) // 2] ^= 0xFF
        path.write_bytes(bytes(data))
    line = resume_refused(folder, capsys)
    assert "checkpoint.npz: the checkpoint is damaged" in line and "nothing was changed" in line, line
    assert "results.h5 is readable: it holds" in line  # what can still be recovered


def test_row06_a_checkpoint_whose_arrays_were_changed_fails_its_checksum(interrupted, tmp_path):
    from soil.errors import DamagedFileError
    from soil.stability import read_checkpoint

    data = dict(np.load(interrupted / "checkpoint.npz"))
    data["coupler/time"] = np.array(1.0)  # a valid archive, but not what was written
    np.savez(tmp_path / "edited.npz", **data)
    with pytest.raises(DamagedFileError, match="do not match their SHA-256 checksum"):
        read_checkpoint(tmp_path / "edited.npz")


def test_row07_another_runs_checkpoint_is_refused(interrupted, complete, tmp_path, capsys):
    folder = copy(interrupted, tmp_path)
    shutil.copy(complete / "checkpoint.npz", folder / "checkpoint.npz")
    line = resume_refused(folder, capsys)
    assert "checkpoint.npz: the checkpoint belongs to another run" in line, line
    assert json.loads((folder / "run.json").read_text())["status"] == "interrupted"  # still resumable
    shutil.copy(interrupted / "checkpoint.npz", folder / "checkpoint.npz")
    assert main(["resume", str(folder), "--no-progress"]) in (0, 6)


def test_row07c_another_runs_results_file_is_refused(interrupted, complete, tmp_path, capsys):
    """Another run's results.h5 copied into the folder was cut to the checkpoint's rows and continued:
    a finished file of two runs' rows under the other's run id, exit 0 and a mixed summary."""
    folder = copy(interrupted, tmp_path)
    shutil.copy(complete / "results.h5", folder / "results.h5")
    line = resume_refused(folder, capsys)
    assert "results.h5: the results file belongs to another run" in line, line
    # run.json garbled too: it cannot tell which of the two is this folder's, and says so (it blamed
    # the intact checkpoint)
    (folder / "run.json").write_text("not json {")
    line = resume_refused(folder, capsys)
    assert "belong to different runs, and run.json cannot be read to tell which" in line, line


def test_row07b_a_garbled_run_json_keeps_the_runs_id_through_resume(interrupted, complete, tmp_path, capsys):
    """run.json emptied or garbled (an editor, a full disk): resume says so and goes on from the intact
    checkpoint, whose owner is still checked against results.h5; the run.json it writes carries the run's
    id again (it was lost, and with it the check of every later checkpoint's owner)."""
    folder = copy(interrupted, tmp_path)
    run_id = json.loads((folder / "run.json").read_text())["run_id"]
    (folder / "run.json").write_text("not json {")
    shutil.copy(complete / "checkpoint.npz", folder / "checkpoint.npz")  # another run's: still found
    assert main(["resume", str(folder), "--no-progress"]) == 2
    shutil.copy(interrupted / "checkpoint.npz", folder / "checkpoint.npz")
    capsys.readouterr()
    assert main(["resume", str(folder), "--no-progress"]) in (0, 6)
    assert "run.json cannot be read as a run's record" in capsys.readouterr().err
    info = json.loads((folder / "run.json").read_text())
    assert info["run_id"] == run_id and info["status"] in ("complete", "unsteady")


# -- row 8: a cached bed replaced by another scene's ----------------------------------------------
def test_row08_a_replaced_cached_bed_is_refused(scene, tmp_path, capsys):
    short = ["--set", "run.duration=0.0017", "--set", "landing.enabled=false", "--no-progress"]
    own, other = tmp_path / "own", tmp_path / "other"
    assert main(["run", scene, "--out", str(own), *short]) in (0, 6)
    assert main(["run", scene, "--out", str(other), "--set", "bed.length=0.1", *short]) in (0, 6)
    capsys.readouterr()
    shutil.copy(other / "bed.h5", own / "bed.h5")
    before = digests(own)
    assert main(["run", scene, "--out", str(own), "--overwrite", *short]) == 2
    line = first_error_line(capsys)
    assert "bed.h5: the cached bed was made for another scene" in line, line
    assert digests(own) == before


# -- row 8b: a bed file changed on disk -----------------------------------------------------------
def test_row08b_a_bed_with_a_flipped_bit_or_rows_past_its_list_is_refused_naming_it(tiny_bed, tmp_path, capsys):
    """A bed carries the SHA-256 of what it is read from: one flipped bit of a grain's radius fails it.
    A bed without one (written before it) is checked for rows that point past its arrays: a neighbour
    count beyond the list's width would have a kernel write past them (a crash, or silently wrong)."""
    import h5py

    from soil.bed import DIGEST_ATTRIBUTE

    with h5py.File(tiny_bed, "r") as f:
        assert DIGEST_ATTRIBUTE in f.attrs
    scene = write_tiny(tmp_path)
    short = ["--set", "run.duration=0.0017", "--set", "landing.enabled=false", "--no-progress"]
    for damage in ("bit", "count", "partner", "position"):
        bed = tmp_path / f"{damage}.h5"
        shutil.copy(tiny_bed, bed)
        with h5py.File(bed, "a") as f:
            if damage == "bit":
                radius = f["particles/radius"][()]
                radius.view(np.uint32 if radius.dtype.itemsize == 4 else np.uint64)[7] ^= 1
                f["particles/radius"][...] = radius
            else:
                del f.attrs[DIGEST_ATTRIBUTE]  # a bed of before the digest
                name, value = {"count": ("neighbour_count", 1000), "partner": ("neighbours", 10**8)}.get(
                    damage, ("position", np.nan)
                )
                rows = f[f"state/{name}"][()]
                rows[5] = value
                f[f"state/{name}"][...] = rows
        out = tmp_path / f"run_{damage}"
        assert main(["run", scene, "--out", str(out), "--set", f'bed.bed_file="{bed}"', *short]) == 2
        line = first_error_line(capsys)
        expected = {
            "bit": "does not match its SHA-256",
            "count": "state/neighbour_count must be in 0..",
            "partner": "state/neighbours must be grain indices",
            "position": "state/position must be finite",
        }
        assert str(bed) in line and expected[damage] in line, line


# -- row 9: a mesh wheel wound inside out, and unreadable meshes ----------------------------------
def test_row09_an_inverted_mesh_is_turned_over_and_open_meshes_are_refused(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    from soil import GrouserWheel, MeshWheel
    from soil.geometry import MeshOrientationWarning

    vertices, triangles = GrouserWheel(0.025, 0.02, 8, 0.003, 0.002).to_mesh(90)
    trimesh.Trimesh(vertices, triangles[:, ::-1], process=False).export(tmp_path / "inverted.stl")
    with pytest.warns(MeshOrientationWarning, match="inside out"):
        mesh = MeshWheel.load(tmp_path / "inverted.stl")
    assert mesh.volume == pytest.approx(MeshWheel(vertices, triangles).volume, rel=1e-9) and mesh.volume > 0
    trimesh.Trimesh(vertices, triangles[:-2], process=False).export(tmp_path / "open.stl")
    with pytest.raises(ValueError, match="open.stl' is not closed"):
        MeshWheel.load(tmp_path / "open.stl")
    # a vertex that is not a number is named as such, not taken for a hole
    lines = trimesh.exchange.obj.export_obj(trimesh.Trimesh(vertices, triangles, process=False)).splitlines()
    first = next(k for k, line in enumerate(lines) if line.startswith("v "))
    lines[first + 3] = "v nan 0.0 0.01"
    (tmp_path / "nan.obj").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match="nan.obj': 1 vertices are not finite"):
        MeshWheel.load(tmp_path / "nan.obj")


@pytest.mark.parametrize("name", ["garbage.stl", "cut.stl", "garbage.obj"])
def test_a_corrupt_mesh_file_names_the_file_and_its_format(tmp_path, capsys, name):
    pytest.importorskip("trimesh")
    from soil import GrouserWheel, MeshWheel

    path = tmp_path / name
    if name == "cut.stl":
        MeshWheel(*GrouserWheel(0.025, 0.02, 8, 0.003, 0.002).to_mesh(90)).save(path)
        cut(path, 0.5)
    else:
        path.write_bytes(bytes(range(256)) * 4)
    scene = write_tiny(tmp_path)
    grouser = (
        "[wheel]\nradius = 0.025\nwidth = 0.02\ngrouser_count = 8\ngrouser_height = 0.003\ngrouser_thickness = 0.002\n"
    )
    with open(scene) as f:
        text = f.read().replace(grouser, f'[wheel]\ntype = "mesh"\nfile = "{name}"\n')
    with open(scene, "w") as f:
        f.write(text)
    assert main(["advise", scene]) == 2
    err = capsys.readouterr().err
    kind = "STL (binary or ASCII)" if name.endswith(".stl") else "Wavefront OBJ"
    assert f"wheel.file: cannot read wheel mesh '{path}': not a readable {kind} file" in err, err
    assert "charset" not in err and "Traceback" not in err


# -- row 10: kill -9 right after the final checkpoint ---------------------------------------------
def test_row10_kill_9_after_the_final_checkpoint_then_resume_finishes_the_result(scene, tiny_bed, complete, tmp_path):
    out = tmp_path / "killed"
    script = textwrap.dedent(f"""
        import os, signal
        from cosim.plan import load_plan
        from cosim.launch import run_plan
        def kill(runner):
            if runner.done:  # the final checkpoint is on disk: die before the results are finished
                os.kill(os.getpid(), signal.SIGKILL)
        run_plan(load_plan({scene!r}, ['bed.bed_file="{tiny_bed}"']), {str(out)!r}, hooks={{"checkpoint": kill}})
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == -signal.SIGKILL, done.stderr
    assert json.loads((out / "run.json").read_text())["status"] == "running"
    assert main(["resume", str(out), "--no-progress"]) in (0, 6)
    info, reference = (json.loads((f / "run.json").read_text()) for f in (out, complete))
    assert info["status"] == reference["status"] and info["summary"]["slip"] == reference["summary"]["slip"]
    from cosim.output import open_results

    with open_results(out / "results.h5") as f:
        assert f.attrs["status"] == info["status"] and json.loads(f.attrs["summary"])["slip"] == info["summary"]["slip"]


# -- row 11: a bed that explodes while it settles ------------------------------------------------
def test_row11_a_divergence_while_settling_is_exit_4_with_the_phase_and_the_key(scene, tmp_path, capsys):
    args = ["--set", "scene.gravity=1000", "--set", "bed.settle_dt_factor=1", "--no-progress"]
    assert main(["run", scene, "--out", str(tmp_path / "boom"), *args]) == 4
    line = first_error_line(capsys)
    assert line.startswith("cosim: error: the bed diverged while settling, at t = ") and "grain " in line, line
    assert "bed.settle_dt_factor" in line and "scene.gravity" in line and "last_good" not in line
    assert set(os.listdir(tmp_path / "boom")) <= {".lock", "bed_diverged.npz"}  # no bed, nothing of a run
    assert_last_good_kept(line, tmp_path / "boom")


def assert_last_good_kept(line: str, folder) -> None:
    """The error names the settling's last good state; the file holds finite grains from before the divergence."""
    from soil.stability import read_checkpoint

    path = folder / "bed_diverged.npz"
    assert "the settling's last good state (t = " in line and line.rstrip().endswith(str(path)), line
    good = read_checkpoint(path)  # its checksum verified
    diverged_at = float(line.split("at t = ")[1].split(" s")[0])
    assert 0.0 <= float(good["time"]) < diverged_at
    assert good["position"].ndim == 2 and good["position"].shape[1] == 3 and np.isfinite(good["position"]).all()
    assert json.loads(str(np.load(path)["units"]))["position"] == "m"  # its arrays carry their units


def test_row11_on_dask_workers_the_divergence_crosses_as_itself_exit_4(scene, tmp_path, capsys):
    # replicas over beds settle their beds on dask workers: the error reaches the command as itself
    args = ["--set", "scene.gravity=1000", "--set", "bed.settle_dt_factor=1", "--no-progress"]
    out = tmp_path / "boom"
    assert main(["run", scene, "--out", str(out), "--replicas", "2", "--vary-bed", "--workers", "2", *args]) == 4
    line = first_error_line(capsys)
    assert line.startswith("cosim: error: the bed diverged while settling, at t = ") and "grain " in line, line
    # no bed was written: a bed's folder holds at most its settling's last good state, and the error names one
    ours = (".lock", STUDY_MARK, "replicas.json")  # the set's lock, mark and recipe
    kept = [os.path.join(d, f) for d, _, files in os.walk(out) for f in files if f not in ours]
    assert kept and all(re.fullmatch(r"beds/seed_\d+/bed_diverged\.npz", os.path.relpath(f, out)) for f in kept), kept
    named = line.rstrip().rsplit(" is ", 1)[1]
    assert named in kept, (named, kept)
    assert_last_good_kept(line, Path(named).parent)


# -- row 12: a scene name that is a path ---------------------------------------------------------
def test_row12_a_scene_name_is_a_name_not_a_path(scene, tmp_path, capsys, monkeypatch):
    work = tmp_path / "a" / "b"
    work.mkdir(parents=True)
    monkeypatch.chdir(work)
    assert main(["run", scene, "--no-progress", "--set", 'scene.name="../../x"']) == 2
    err = capsys.readouterr().err
    assert err.startswith("cosim: error: invalid scene") and "scene.name: must be a plain name, not a path" in err
    assert not (tmp_path / "x").exists() and not (work / "runs").exists()


# -- row 13: SIGTERM, and a closed terminal (SIGHUP) ------------------------------------------------
def run_stopped_at_step_20(scene, tiny_bed, out, at_step: str, options: str = "") -> str:
    """A child script running the tiny scene into `out` that runs `at_step` (Python lines, `self` the runner)
    after macro step 20."""
    head = textwrap.dedent("""
        import os, signal, sys, time
        from cosim import runner
        from cosim.cli import main
        original = runner.Runner._after_step
        def after_step(self, record):
            original(self, record)
            if self.system.coupler.step_count == 20:
    """)
    tail = textwrap.dedent(f"""
        runner.Runner._after_step = after_step
        sys.exit(main(["run", {scene!r}, "--out", {str(out)!r}, {options}"--set", 'bed.bed_file="{tiny_bed}"']))
    """)
    return head + textwrap.indent(textwrap.dedent(at_step).strip("\n") + "\n", " " * 8) + tail


def assert_checkpointed_at_step_20_and_resumes(out, complete) -> None:
    """A checkpoint of the moment of the stop, and a resume to the uninterrupted run's slip, bit for bit."""
    assert int(np.load(out / "checkpoint.npz")["coupler/step_count"]) == 20  # a checkpoint of the moment
    assert main(["resume", str(out), "--no-progress"]) in (0, 6)
    info, reference = (json.loads((f / "run.json").read_text()) for f in (out, complete))
    assert info["summary"]["slip"] == reference["summary"]["slip"]  # bitwise on the CPU


def test_row13_sigterm_checkpoints_stops_cleanly_and_resumes(scene, tiny_bed, complete, tmp_path):
    out = tmp_path / "term"
    sigterm = "os.kill(os.getpid(), signal.SIGTERM)  # what a batch scheduler or `docker stop` sends\n"
    script = run_stopped_at_step_20(scene, tiny_bed, out, sigterm, options='"--no-progress", ')
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 143, done.stderr
    assert "cosim: interrupted. SIGTERM: stopped at t = " in done.stderr
    assert json.loads((out / "run.json").read_text())["status"] == "interrupted"
    assert_checkpointed_at_step_20_and_resumes(out, complete)


def test_row13_a_closed_terminal_checkpoints_stops_cleanly_and_resumes(scene, tiny_bed, complete, tmp_path):
    """A run in a terminal that closes (an ssh session dropped) gets SIGHUP, and every later write to the
    terminal fails (EIO). It used to die as if killed -9, without a checkpoint of that moment; it stops as
    on SIGTERM, with a checkpoint, exit 129, and resumes to the uninterrupted run's numbers."""
    import pty

    out = tmp_path / "hangup"
    wait = """
        try:
            print("STEP 20", flush=True)  # the test closes the terminal now
        except OSError:  # closed already (EIO): this line is the test's, not the run's
            pass
        waited = time.monotonic()
        while not self.stop_requested and time.monotonic() - waited < 60:
            time.sleep(0.01)
    """
    script = run_stopped_at_step_20(scene, tiny_bed, out, wait)  # progress bars on: the terminal shows them
    pid, terminal = pty.fork()  # the child's session and controlling terminal: its stdin, stdout, stderr
    if pid == 0:  # the child: progress bars and log lines on the terminal, as a user's run has them
        try:
            os.execv(sys.executable, [sys.executable, "-c", script])
        finally:
            os._exit(127)
    said = b""
    deadline = time.monotonic() + 300
    while b"STEP 20" not in said and time.monotonic() < deadline:
        try:
            said += os.read(terminal, 4096)
        except OSError:  # the child ended (EIO on Linux)
            break
    os.close(terminal)  # the terminal closes: the kernel sends SIGHUP to its session
    _, status = os.waitpid(pid, 0)
    assert b"STEP 20" in said, said.decode(errors="replace")[-2000:]
    assert os.waitstatus_to_exitcode(status) == 129, said.decode(errors="replace")[-2000:]
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "interrupted" and "SIGHUP" in info["message"], info.get("message")
    assert_checkpointed_at_step_20_and_resumes(out, complete)


def test_a_command_started_under_nohup_keeps_ignoring_the_hangup():
    """`nohup cosim run ...` starts the command with SIGHUP ignored, so that it outlives the terminal: the
    stop handlers of a command, a run and a batch leave it ignored (they would stop the run otherwise),
    and handle Ctrl-C and SIGTERM as ever."""
    from cosim import stop_signals
    from cosim.cli import _stop_on_signals

    def handler(signum, frame):
        raise AssertionError("not called")

    for ignored in (True, False):
        before = signal.signal(signal.SIGHUP, signal.SIG_IGN if ignored else signal.SIG_DFL)
        try:
            command = _stop_on_signals()
            try:
                run = stop_signals.install(handler)
                try:
                    assert (signal.getsignal(signal.SIGHUP) is signal.SIG_IGN) == ignored
                    assert signal.getsignal(signal.SIGTERM) is handler and signal.getsignal(signal.SIGINT) is handler
                finally:
                    stop_signals.restore(run)
                assert (signal.getsignal(signal.SIGHUP) is signal.SIG_IGN) == ignored
            finally:
                stop_signals.restore(command)
        finally:
            signal.signal(signal.SIGHUP, before)


# -- row 14: a run folder moved whole -------------------------------------------------------------
def test_row14_a_run_folder_moved_whole_resumes_on_the_bed_it_carries(scene, tiny_bed, complete, tmp_path, capsys):
    here = tmp_path / "here" / "run"
    here.mkdir(parents=True)
    for name in ("bed.h5", "bed.json"):  # the run's own settled bed, in its folder (the cache of the scene's key)
        shutil.copy2(Path(tiny_bed).parent / name, here / name)
    stopped_after_a_checkpoint(load_plan(scene), here)
    assert json.loads((here / "run.json").read_text())["bed"]["source"] == "cache"
    there = tmp_path / "there"
    shutil.move(tmp_path / "here", there)  # to another disk or machine: the checkpoint's absolute bed path is gone
    gone = copy(there / "run", tmp_path, "without_bed")
    os.remove(gone / "bed.h5")
    line = resume_refused(gone, capsys)
    assert f"the run's bed '{here / 'bed.h5'}' is gone" in line and "invalid scene" not in line, line
    assert main(["resume", str(there / "run"), "--no-progress"]) in (0, 6)
    info, reference = (json.loads((f / "run.json").read_text()) for f in (there / "run", complete))
    assert info["status"] == reference["status"] and info["summary"]["slip"] == reference["summary"]["slip"]
    assert info["bed"]["path"] == str(there / "run" / "bed.h5")


# -- misleading messages ------------------------------------------------------------------------
def test_a_wheel_larger_than_its_bed_is_named_as_such(scene, capsys):
    assert main(["advise", scene, "--set", "wheel.radius=0.07"]) == 2
    err = capsys.readouterr().err
    assert (
        err.splitlines()[1].startswith("  - wheel.radius: the wheel (outer radius 0.07301 m") and "does not fit" in err
    )
    assert "run.duration" not in err


def test_a_full_disk_during_the_run_names_the_file(scene, tiny_bed, tmp_path, capsys, monkeypatch):
    import errno

    from cosim import output

    def full(self):
        raise OSError(errno.ENOSPC, "No space left on device")  # as h5py reports it: no file name

    monkeypatch.setattr(output.ResultsWriter, "flush_records", full)
    out = tmp_path / "full"
    assert main(["run", scene, "--out", str(out), "--no-progress", "--set", f'bed.bed_file="{tiny_bed}"']) == 5
    line = first_error_line(capsys)
    assert line == f"cosim: error: {out / 'results.h5'}: No space left on device", line


def test_resume_of_an_empty_folder_leaves_nothing_behind(tmp_path, capsys):
    """A folder that holds no run is bad input (exit 2, as plot and export-fmu of one), not an OS error; one
    whose run stopped before its first checkpoint is said to be that, not "not a run folder"."""
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["resume", str(empty), "--no-progress"]) == 2
    assert "not a run folder that can be resumed" in first_error_line(capsys)
    assert os.listdir(empty) == []
    assert main(["resume", str(tmp_path / "nowhere"), "--no-progress"]) == 2
    assert "is not a folder: nothing to resume" in first_error_line(capsys)
    # a run stopped before its first checkpoint: said so, with the command that runs it again
    for name in ("scene.toml", "run.json", "results.h5"):
        (empty / name).write_text("")
    assert main(["resume", str(empty), "--no-progress"]) == 2
    line = first_error_line(capsys)
    assert "the run stopped before its first checkpoint" in line and f"cosim run {empty / 'scene.toml'}" in line
    # one that diverged there: the divergence named, and a rerun with the change it names (as it was, it
    # diverges again)
    (empty / "run.json").write_text(json.dumps({"status": "diverged", "message": "grain 7 left the box"}))
    assert main(["resume", str(empty), "--no-progress"]) == 2
    line = first_error_line(capsys)
    assert "the run diverged before its first checkpoint (grain 7 left the box)" in line and "--set KEY=VALUE" in line
    # one that failed there (a full disk) runs again as it was; a finished one whose checkpoint is gone: nothing
    (empty / "run.json").write_text(json.dumps({"status": "failed", "message": "OSError: disk full"}))
    assert main(["resume", str(empty), "--no-progress"]) == 2
    line = first_error_line(capsys)
    assert "the run failed before its first checkpoint (OSError: disk full)" in line and "--overwrite" in line
    (empty / "run.json").write_text(json.dumps({"status": "complete"}))
    assert main(["resume", str(empty), "--no-progress"]) == 2
    assert "the run finished (complete) and its checkpoint is gone" in first_error_line(capsys)


@pytest.mark.parametrize("edit", [b"# an edit by hand\n", b"\xff\xfe not UTF-8\n"], ids=["edited", "unreadable"])
def test_a_resumed_runs_edited_scene_is_kept_aside_and_its_scene_written_back(complete, tmp_path, capsys, edit):
    """Resume runs the checkpoint's copy of the scene; a scene.toml edited since (or damaged) was left as
    edited, a folder whose scene.toml was not its results' scene. It is kept whole as scene.edited.toml
    and scene.toml written back: the scene the results were made with (results.h5's own copy)."""
    import h5py

    folder = copy(complete, tmp_path)
    with h5py.File(folder / "results.h5", "r") as f:
        ran = f.attrs["scene_toml"]
    assert (folder / "scene.toml").read_text() == ran  # the scene the results hold
    edited = (ran.encode() if edit.startswith(b"#") else b"") + edit
    (folder / "scene.toml").write_bytes(edited)
    capsys.readouterr()
    assert main(["resume", str(folder), "--no-progress"]) == 6  # the tiny run: too short (under one grouser passage)
    assert "edited file kept as scene.edited.toml" in capsys.readouterr().err
    assert (folder / "scene.toml").read_text() == ran
    assert (folder / "scene.edited.toml").read_bytes() == edited
    assert main(["resume", str(folder), "--no-progress"]) == 6  # nothing left to put back
    assert "scene.toml" not in capsys.readouterr().err
    assert (folder / "scene.edited.toml").read_bytes() == edited
    (folder / "scene.toml").write_bytes(b"second = 2\n")  # a second edit is kept beside the first
    assert main(["resume", str(folder), "--no-progress"]) == 6  # the tiny run: too short (under one grouser passage)
    assert "kept as scene.edited.2.toml" in capsys.readouterr().err
    assert (folder / "scene.edited.toml").read_bytes() == edited
    assert (folder / "scene.edited.2.toml").read_bytes() == b"second = 2\n"
    assert (folder / "scene.toml").read_text() == ran


def test_an_edited_scene_is_kept_on_a_file_system_without_hard_links(complete, tmp_path, capsys, monkeypatch):
    """Where a hard link cannot be made (FAT, some network mounts) the edited scene.toml is copied aside,
    not left as edited with a warning that did not say scene.toml stayed so."""
    folder = copy(complete, tmp_path)
    ran = (folder / "scene.toml").read_text()
    (folder / "scene.toml").write_text(ran + "# edited\n")

    def no_links(source, target):
        raise PermissionError(1, "Operation not permitted", source)

    monkeypatch.setattr(os, "link", no_links)
    assert main(["resume", str(folder), "--no-progress"]) == 6  # the tiny run: too short (under one grouser passage)
    assert "kept as scene.edited.toml" in capsys.readouterr().err
    assert (folder / "scene.toml").read_text() == ran
    assert (folder / "scene.edited.toml").read_text() == ran + "# edited\n"


def test_a_lab_test_whose_every_replica_diverged_is_exit_4(tmp_path, capsys, monkeypatch):
    import cosim.lab
    from cosim.lab.common import successful

    failed = [{"ok": False, "diverged": True, "label": "repose 0", "error": "SimulationDiverged: boom"}]

    def diverging(plan, out, **kwargs):
        return successful(failed, "repose")

    monkeypatch.setattr(cosim.lab, "repose_test", diverging)
    scene = os.path.join(os.path.dirname(__file__), "..", "examples", "phobos_lab.toml")
    assert main(["lab", "repose", scene, "--out", str(tmp_path / "lab"), "--serial"]) == 4
    line = first_error_line(capsys)
    assert "every repose replica diverged" in line and "run.dt_factor" in line, line


def test_a_full_disk_while_a_checkpoint_is_written_names_the_checkpoint(tmp_path):
    import errno
    from unittest import mock

    from soil.stability import write_checkpoint

    def full(file, **arrays):
        raise OSError(errno.ENOSPC, "No space left on device")  # a write into an open file names no path

    with mock.patch("numpy.savez", full), pytest.raises(OSError) as info:
        write_checkpoint(tmp_path / "checkpoint.npz", {"a": np.zeros(3)})
    assert info.value.filename == str(tmp_path / "checkpoint.npz") and info.value.errno == errno.ENOSPC
    assert os.listdir(tmp_path) == []  # no temporary file left behind


# -- a refused command leaves an --overwrite folder as it was -------------------------------------
LAB = os.path.join(os.path.dirname(__file__), "..", "examples", "phobos_lab.toml")
LAST_SEED = ["--set", f"bed.seed={2**63 - 1}"]


@pytest.mark.parametrize(
    "command, named",
    [
        (["lab", "repose", LAB, "--set", "repose.tube_width=1e-6"], "repose.tube_width"),
        (["lab", "shear", LAB, "--set", "shear.length=1e-6"], "shear.length"),
        (["lab", "repose", LAB, "--replicas", "2", *LAST_SEED], "bed.seed: replica k is filled with bed.seed + k"),
        (
            [
                "calibrate",
                LAB,
                "--target",
                "repose=30",
                "--vary",
                "soil.rolling_friction=0:0.3",
                "--set",
                "repose.tube_width=1e-6",
            ],
            "repose.tube_width",
        ),
        (
            ["calibrate", LAB, "--target", "repose=30", "--vary", "repose.tube_width=1e-6:0.05"],
            "repose.tube_width",  # the range's lower end is a valid scene whose tube cannot be built
        ),
        (["calibrate-scm", LAB, "--set", "shear.length=1e-6"], "shear.length"),
        (["study", "slip", "SCENE", "--vary-bed", "--replicas", "2", "--slips", "0.2", *LAST_SEED], "--vary-bed"),
    ],
    ids=[
        "repose tube",
        "shear box",
        "lab seeds",
        "calibrate tube",
        "calibrate range",
        "calibrate-scm box",
        "study seeds",
    ],
)
def test_a_refused_command_leaves_the_overwrite_folder_as_it_was(scene, tmp_path, capsys, command, named):
    """Each check runs before the folder it would replace is cleared: a geometry that cannot be built,
    a range end that cannot, replicas' seeds past 2^63 - 1. Exit 2, the folder's files unchanged."""
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "summary.json").write_text('{"earlier": "result"}')
    before = digests(folder)
    command = [scene if part == "SCENE" else part for part in command]
    where = (
        ["--work", str(folder), "--out", str(tmp_path / "soil.toml")]
        if command[0] == "calibrate-scm"
        else ["--out", str(folder)]
    )
    assert main([*command, *where, "--overwrite", "--serial"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.startswith("cosim: error:") and named in err, err
    assert digests(folder) == before


# -- export and view of a results file whose datasets hold what no run writes -------------------------
def _replace_dataset(f, name, data):
    attrs = dict(f[name].attrs)
    del f[name]
    f[name] = data
    f[name].attrs.update(attrs)


def _geometry_cut_to_3_columns(f):
    _replace_dataset(f, "boundaries/geometry", f["boundaries/geometry"][()][:, :3])


def _times_as_text(f):
    _replace_dataset(f, "particles/time", np.array([f"t={t}" for t in f["particles/time"][()]], dtype="S"))


def _one_position_nan(f):
    f["particles/position"][0, 3, 1] = np.nan  # the first snapshot: the one view sizes its figure by


def _a_triangle_past_the_mesh(f):
    triangles = f["wheels/mesh/triangles"][()]
    triangles[0, 0] = len(f["wheels/mesh/vertices"]) + 5
    f["wheels/mesh/triangles"][...] = triangles


def _a_wall_displacement_inf(f):
    f["boundaries/displacement"][2, 0, 0] = np.inf


@pytest.mark.parametrize(
    "damage, named",
    [
        (_geometry_cut_to_3_columns, "boundaries/geometry has shape (5, 3), not (5, 6)"),
        (_times_as_text, "particles/time holds |S"),
        (_one_position_nan, "particles/position of snapshot 0 holds 1 value that is not finite (nan)"),
        (_a_triangle_past_the_mesh, "wheels/mesh/triangles points past the"),
        (_a_wall_displacement_inf, "boundaries/displacement holds 1 value that is not finite (inf)"),
    ],
    ids=["geometry 3 columns", "times as text", "a position nan", "a triangle past the mesh", "a wall moved inf"],
)
def test_export_and_view_of_results_holding_what_no_run_writes_name_the_dataset(
    complete, tmp_path, capsys, damage, named
):
    """A dataset the readers use of another dtype or shape, or holding a value no run writes (a non-finite
    grain position: a run that diverges stops before its snapshot), was an unexpected error (exit 1:
    IndexError, ValueError) or an export with nan in its points (exit 0). It is exit 2 naming the file and
    the dataset; the run's own results.vtkhdf and an earlier picture stay as they were."""
    import h5py

    folder = copy(complete, tmp_path)
    picture = tmp_path / "frame.png"
    assert main(["view", str(folder), "--out", str(picture), "--dpi", "20"]) == 0
    with h5py.File(folder / "results.h5", "r+") as f:
        assert len(f["boundaries/kind"]) == 5
        damage(f)
    before, before_picture = digests(folder), picture.read_bytes()
    for command in (
        ["export", "vtkhdf", str(folder)],  # the run's own results.vtkhdf, made again
        ["export", "vtkhdf", str(folder), "--out", str(tmp_path / "new" / "x.vtkhdf")],
        ["view", str(folder), "--out", str(picture), "--dpi", "20", "--overwrite"],
        ["view", str(folder), "--out", str(tmp_path / "frames"), "--dpi", "20"],
    ):
        assert main(command) == 2, command
        line = first_error_line(capsys)
        assert line.startswith(f"cosim: error: {folder / 'results.h5'}: the results file is damaged ("), line
        assert named in line, line
    assert digests(folder) == before and picture.read_bytes() == before_picture
    assert sorted(os.listdir(tmp_path)) == ["copy", "frame.png"]  # no folder made, no temporary left


# -- changed bytes in a results dataset's data (not its header) ------------------------------------
def _chunk_middle(path, name: str) -> int:
    """The file offset of a byte in the middle of the first stored chunk of dataset `name` (its data)."""
    import h5py

    with h5py.File(path, "r") as f:
        chunk = f[name].id.get_chunk_info(0)
    return chunk.byte_offset + chunk.size // 2


def _flip(path, offset: int) -> None:
    """Flip every bit of the byte at `offset` in place (twice: the byte as it was)."""
    with open(path, "r+b") as out:
        out.seek(offset)
        byte = out.read(1)[0]
        out.seek(offset)
        out.write(bytes([byte ^ 0xFF]))


def _flip_in_chunk(path, name: str) -> None:
    _flip(path, _chunk_middle(path, name))


PLOT = ["plot", "{folder}"]
VIEW = ["view", "{folder}", "--out", "{tmp}/frame.png", "--dpi", "20"]
EXPORT = ["export", "vtkhdf", "{folder}"]


@pytest.mark.parametrize(
    "name, commands",
    [
        ("wheels/sinkage", [PLOT, VIEW]),
        ("wheels/time", [PLOT, VIEW, EXPORT]),
        ("wheels/mesh/triangles", [VIEW, EXPORT]),
        ("boundaries/force", [EXPORT]),
        ("particles/position", [VIEW, EXPORT]),
    ],
    ids=["a sinkage", "a step time", "a triangle", "a wall force", "a grain position"],
)
def test_a_results_file_with_changed_data_bytes_is_named_not_read_as_numbers(
    complete, tmp_path, capsys, name, commands
):
    """Every results dataset carries a Fletcher-32 checksum per chunk: a byte changed on disk in a series'
    data was read as a number (a plot of a wrong sinkage, exit 0). It is exit 2 naming the file, nothing
    written."""
    folder = copy(complete, tmp_path)
    _flip_in_chunk(folder / "results.h5", name)
    before = digests(folder)
    for command in commands:
        command = [part.format(folder=folder, tmp=tmp_path) for part in command]
        assert main(command) == 2, command
        line = first_error_line(capsys)
        assert line.startswith(f"cosim: error: {folder / 'results.h5'}: the results file is damaged ("), line
        assert ("(particles of snapshot 0: " if name.startswith("particles/") else f"({name}: ") in line, line
    assert digests(folder) == before
    assert sorted(os.listdir(tmp_path)) == ["copy"]


def test_resume_of_a_results_file_with_changed_data_bytes_is_refused(interrupted, tmp_path, capsys):
    """A resume copies the results up to its checkpoint into a fresh file: a changed byte in them was copied
    as a number. It is refused naming the file, the folder as it was; a resumed file keeps its checksums."""
    import h5py

    folder = copy(interrupted, tmp_path)
    with h5py.File(folder / "results.h5", "r") as f:
        assert all(f[name].fletcher32 for name in ("wheels/slip", "rover/state", "particles/radius"))
    _flip_in_chunk(folder / "results.h5", "wheels/slip")
    assert "results.h5: the results file is damaged" in resume_refused(folder, capsys)

    intact = copy(interrupted, tmp_path, "intact")
    assert main(["resume", str(intact), "--no-progress"]) == 6  # too short: the tiny run passes under one grouser
    with h5py.File(intact / "results.h5", "r") as f:
        assert f["wheels/slip"].fletcher32 and f["particles/position"].fletcher32


def test_a_chunk_torn_for_a_moment_in_a_file_being_written_is_read_again(interrupted, tmp_path, monkeypatch):
    """A reader of a file its writer still writes (status 'running') may meet a chunk the writer is
    rewriting in place: its checksum fails for that moment (a few reads in a thousand of a file flushed
    without pause, measured). The read is tried again and gets the chunk whole; a chunk that stays
    damaged is named after the tries, as is one of a file no one writes (at once)."""
    import h5py

    import cosim.snapshots
    from cosim.output import read_series
    from soil.errors import DamagedFileError

    path = copy(interrupted, tmp_path) / "results.h5"
    with h5py.File(path, "r+") as f:
        f.attrs["status"] = "running"  # as a live writer's (or a killed one's) file
    whole = read_series(path)["sinkage"]
    offset = _chunk_middle(path, "wheels/sinkage")
    pauses: list[float] = []
    writing = [False]

    def pause(seconds):
        pauses.append(seconds)
        if writing[0]:  # the writer finishes its chunk while the reader waits
            _flip(path, offset)
            writing[0] = False

    monkeypatch.setattr(cosim.snapshots, "_pause", pause)
    tries, wait = cosim.snapshots.TORN_READ_TRIES, cosim.snapshots.TORN_READ_PAUSE
    _flip(path, offset)
    writing[0] = True
    assert np.array_equal(read_series(path)["sinkage"], whole)
    assert pauses == [wait]

    pauses.clear()
    _flip(path, offset)  # damaged for good
    with pytest.raises(DamagedFileError, match=r"results\.h5: the results file is damaged \(wheels/sinkage: "):
        read_series(path)
    assert pauses == [wait] * (tries - 1)

    pauses.clear()
    with h5py.File(path, "r+") as f:
        f.attrs["status"] = "interrupted"
    with pytest.raises(DamagedFileError, match="wheels/sinkage"):
        read_series(path)
    assert pauses == []


# -- a picture or a table whose write fails midway ----------------------------------------------------
def test_a_plot_whose_write_fails_midway_leaves_the_earlier_pictures_whole(complete, tmp_path, capsys, monkeypatch):
    """`cosim plot` wrote its pictures in place: a full disk (or a crash) while one was written left half a
    picture where a whole one had been. Each is written beside it and renamed (cosim.plots.save_figure):
    the error names the picture, and the pictures there are as they were, with no temporary file left."""
    import errno

    import matplotlib.figure

    folder = copy(complete, tmp_path)
    assert main(["plot", str(folder)]) == 0
    plots = folder / "plots"
    before = digests(plots)
    assert before
    real_savefig = matplotlib.figure.Figure.savefig

    def disk_full_midway(figure, target, **options):
        real_savefig(figure, target, **options)
        if hasattr(target, "truncate"):  # the disk filled while the picture was written
            target.truncate(100)
        else:
            os.truncate(target, 100)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", disk_full_midway)
    assert main(["plot", str(folder)]) == 5
    line = first_error_line(capsys)
    assert "No space left on device" in line and any(str(plots / name) in line for name in before), line
    assert digests(plots) == before


def test_a_plot_refuses_a_link_at_a_later_picture_before_it_replaces_an_earlier_one(complete, tmp_path, capsys):
    """A picture link that leads to the run's results.h5 was refused only when its picture came to be saved,
    after the pictures before it had been replaced: every name is checked before the first is written."""
    folder = copy(complete, tmp_path)
    assert main(["plot", str(folder)]) == 0
    plots = folder / "plots"
    (plots / "slip_drawbar.png").unlink()  # the second picture written
    (plots / "slip_drawbar.png").symlink_to(folder / "results.h5")
    (plots / "travel_sinkage.png").write_bytes(b"the earlier picture")  # the first written: it must stay
    before = digests(plots)
    results = (folder / "results.h5").read_bytes()
    assert main(["plot", str(folder)]) == 2
    line = first_error_line(capsys)
    assert "slip_drawbar.png" in line and "results.h5" in line, line
    assert digests(plots) == before and (folder / "results.h5").read_bytes() == results


def test_a_lab_table_whose_write_fails_midway_leaves_the_earlier_one_whole(tmp_path):
    """A lab test's CSV tables were written row by row in place: a failure midway left the table cut short
    (a full disk, a signal). It is written whole or not at all."""
    import errno

    from cosim.lab import common

    class Unwritable:
        def __str__(self):
            raise OSError(errno.ENOSPC, "No space left on device")

    path = tmp_path / "plate.csv"
    common.write_csv(str(path), [("width", "m", [0.01, 0.02]), ("pressure", "Pa", [1.5, 2.5])])
    before = path.read_bytes()
    assert before.splitlines() == [b"width [m],pressure [Pa]", b"0.01,1.5", b"0.02,2.5"]
    rows = np.array([0.01] * 5000 + [Unwritable()], dtype=object)
    with pytest.raises(OSError, match="No space left"):
        common.write_csv(str(path), [("width", "m", rows)])
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["plate.csv"]


def test_a_picture_name_without_its_format_is_refused_before_anything_is_written(tmp_path):
    """save_figure takes the format from the name's extension: a name without one was an empty file where
    the picture should be and the picture under a stray temporary name beside it."""
    import matplotlib.figure

    from cosim.plots import save_figure
    from soil.errors import ArgumentError

    with pytest.raises(ArgumentError, match="a picture's name ends in its format"):
        save_figure(matplotlib.figure.Figure(), str(tmp_path / "picture"), 20)
    save_figure(matplotlib.figure.Figure(), str(tmp_path / "picture.PNG"), 20)
    assert os.listdir(tmp_path) == ["picture.PNG"]
    assert (tmp_path / "picture.PNG").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("hard_links", [True, False], ids=["hard links", "no hard links"])
def test_an_output_that_appeared_while_it_was_made_is_kept_and_so_is_the_work(tmp_path, monkeypatch, hard_links):
    """`calibrate-scm --out FILE` looks that FILE is free, runs its DEM tests (minutes to an hour), then
    wrote FILE over whatever another process had put there meanwhile (a `cosim scale` twin: gone). Without
    --overwrite the file that appeared is left as it is and the calibration kept beside it, both named
    (soil.files.atomic_path(replace=False): os.link, or a look first where the file system has no hard
    links); a free name is written as before."""
    import errno

    from soil.files import atomic_path

    if not hard_links:

        def no_links(source, target):
            raise OSError(errno.EPERM, "Operation not permitted")

        monkeypatch.setattr(os, "link", no_links)
    target = tmp_path / "terrain.toml"
    with pytest.raises(FileExistsError) as info:
        with atomic_path(target, replace=False) as temporary:
            Path(temporary).write_text("calibrated")
            target.write_text("twin scene")  # another process, while the DEM tests ran
    assert target.read_text() == "twin scene"
    kept = tmp_path / "terrain.new.toml"
    assert kept.read_text() == "calibrated" and str(kept) in str(info.value) and info.value.filename == str(target)
    with pytest.raises(FileExistsError, match="terrain.new-2.toml"):  # a second time: the first kept file stays
        with atomic_path(target, replace=False) as temporary:
            Path(temporary).write_text("again")
    assert sorted(os.listdir(tmp_path)) == ["terrain.new-2.toml", "terrain.new.toml", "terrain.toml"]
    free = tmp_path / "free.toml"
    with atomic_path(free, replace=False) as temporary:
        Path(temporary).write_text("calibrated")
    assert free.read_text() == "calibrated" and "free.toml" in os.listdir(tmp_path)
    assert not [name for name in os.listdir(tmp_path) if name.startswith("tmp")]
    # calibrate-scm's own writer, as it writes --out without --overwrite
    from cosim.scm_calibration import read_calibration, write_calibration

    shipped = Path(__file__).parent.parent / "examples" / "terrain" / "phobos_regolith_scm_beds.toml"
    with pytest.raises(FileExistsError, match="terrain.new-3.toml"):
        write_calibration(str(target), read_calibration(str(shipped)), replace=False)
    assert target.read_text() == "twin scene"
    assert (
        read_calibration(str(tmp_path / "terrain.new-3.toml")).parameters == read_calibration(str(shipped)).parameters
    )


def test_a_scale_twin_keeps_a_file_that_appeared_while_it_was_made(tmp_path, monkeypatch, capsys):
    """`cosim scale --out FILE` looked that FILE was free, then replaced whatever appeared there before its
    write (another process's twin, gone). Without --overwrite the file that appeared is kept and the twin
    written beside it, both named (exit 5); with --overwrite it is replaced, as asked."""
    import tomli_w

    scene, out = write_tiny(tmp_path), tmp_path / "twin.toml"
    dumps = tomli_w.dumps

    def another_process_writes_first(data, **kwargs):
        out.write_text("another twin")
        return dumps(data, **kwargs)

    monkeypatch.setattr(tomli_w, "dumps", another_process_writes_first)
    assert main(["scale", scene, "--gravity", "earth", "--out", str(out)]) == 5
    err = capsys.readouterr().err
    assert out.read_text() == "another twin" and "twin.new.toml" in err and str(out) in err
    assert "|g| x" in (tmp_path / "twin.new.toml").read_text()  # the twin, kept
    assert main(["scale", scene, "--gravity", "earth", "--out", str(out), "--overwrite"]) == 0
    assert "|g| x" in out.read_text()
