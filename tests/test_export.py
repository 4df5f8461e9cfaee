"""The run's snapshots open in the readers users reach for: meshio and VTK read results.xdmf, VTK's
vtkHDFReader reads results.vtkhdf (every step, equal to results.h5), all without error output; and
`cosim view` draws a movie of the run.

Three outputs: the tiny run (a real run: landing and drive), a file of the main job's size (5,642
grains, 9 snapshots, four walls and a plate) and a ragged one (a moving patch: the grains change), the last two
written with ResultsWriter from made-up grains.
"""

import os

import numpy as np
import pytest

from cosim.cli import main
from cosim.output import BOUNDARY_SERIES, ROVER_SERIES, SOIL_SERIES, WHEEL_SERIES, ResultsWriter, open_results
from cosim.snapshots import read_snapshot, snapshot_count
from cosim.vtkhdf import write_vtkhdf

vtk = pytest.importorskip("vtk")
MAIN_JOB_GRAINS = 5642
MAIN_JOB_SNAPSHOTS = 9  # 14 s of driving and about 6 s of landing, a snapshot every 2.5 s


def _row(t: float, walls: int) -> dict:
    row = {"time": t, "phase": int(t > 0.5), "rover_state": [t]}
    for name, (tail, *_) in WHEEL_SERIES.items():
        row[name] = np.full((1,) if tail is None else (1, tail), 1e-3 * t)
    for name, (tail, *_) in BOUNDARY_SERIES.items():
        row[f"boundary_{name}"] = np.full((walls,) if tail is None else (walls, tail), 1e-3 * t)
    for name, (tail, *_) in ROVER_SERIES.items():
        row[f"rover_{name}"] = np.full(() if tail is None else (tail,), t)
    for name in SOIL_SERIES:
        row[f"soil_{name}"] = 1
    return row


def made_up_results(folder, grains: int, snapshots: int, ragged: bool = False) -> str:
    """results.h5 (and its results.xdmf) of `grains` made-up grains in a 0.16 m bed with a cube for a wheel,
    four walls and a plate, and `snapshots` snapshots (ragged: a different number of grains in each)."""
    rng = np.random.default_rng(1)
    cube = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float) * 0.02
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1]])
    geometry = np.array(
        [[0, 0, 0, 0, 0, 1], [0, 0, 0, 1, 0, 0], [0.16, 0.065, 0.1, -1, 0, 0], [0, 0, 0, 0, 1, 0]]
        + [[0.05, 0.02, 0.04, 0.08, 0.045, 0.05]],  # four planes (point, normal) and a box (corners): a plate
        dtype=float,
    )
    kinds = np.array([0, 0, 0, 0, 1])
    walls = len(geometry)
    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, "results.h5")
    writer = ResultsWriter.create(
        path,
        attrs={"name": "made_up", "gravity": [0, 0, -5.7e-3], "surface_height": 0.034, "kind": "testbed"},
        radius=np.full(grains, 2e-3),
        wheel_count=1,
        mesh=(cube, faces, np.zeros(len(cube), int)),
        rover_columns=["x"],
        rover_units=["m"],
        boundaries={"kind": kinds, "geometry": geometry, "report": np.ones(walls, int)},
        ragged=ragged,
    )
    with writer:
        for k in range(snapshots):
            t = 0.25 * k
            for j in range(3):
                writer.append_step(_row(t + 0.25 * (j + 1) / 3, walls))
            n = grains - 7 * k if ragged else grains
            position = rng.uniform([0, 0, 0], [0.16, 0.065, 0.034], (n, 3))
            hub = np.array([0.04 + 0.01 * k, 0.0325, 0.05])
            writer.add_snapshot(
                t,
                position,
                rng.normal(0, 1e-3, (n, 3)).astype(np.float32),
                (cube + hub).astype(np.float32),
                rover_pose=(hub, np.eye(3)),
                radius=np.full(n, 2e-3) if ragged else None,
                ids=np.arange(7 * k, 7 * k + n) if ragged else None,
            )
    return path


@pytest.fixture(scope="module", params=["tiny_run", "main_job_size", "ragged"])
def run(request, tmp_path_factory):
    if request.param == "tiny_run":
        return request.getfixturevalue("tiny_run")
    folder = tmp_path_factory.mktemp(request.param)
    if request.param == "main_job_size":
        made_up_results(folder, MAIN_JOB_GRAINS, MAIN_JOB_SNAPSHOTS)
    else:
        made_up_results(folder, 300, 4, ragged=True)
    return folder


@pytest.fixture
def vtk_messages(tmp_path):
    """VTK's errors and warnings go to a file; yields a function that returns what was written."""
    log = tmp_path / "vtk.log"
    window = vtk.vtkFileOutputWindow()
    window.SetFileName(str(log))
    window.SetFlush(True)
    previous = vtk.vtkOutputWindow.GetInstance()
    vtk.vtkOutputWindow.SetInstance(window)
    yield lambda: log.read_text() if log.exists() else ""
    vtk.vtkOutputWindow.SetInstance(previous)


def _snapshots(run):
    with open_results(run / "results.h5") as f:
        return [read_snapshot(f, k) for k in range(snapshot_count(f))]


def _xdmf_grain_arrays(run) -> set:
    """The point arrays of the grains in results.xdmf: the grain ids too where the grains change."""
    with open_results(run / "results.h5") as f:
        ragged = f["particles"].attrs["layout"] == "ragged"
    return {"radius [m]", "velocity [m s-1]", "position [m]"} | ({"id [1]"} if ragged else set())


def test_meshio_reads_the_xdmf_time_series(run, capfd):
    meshio = pytest.importorskip("meshio")
    import warnings

    snapshots = _snapshots(run)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with meshio.xdmf.TimeSeriesReader(str(run / "results.xdmf")) as reader:
            points, cells = reader.read_points_cells()
            assert reader.num_steps == len(snapshots)
            assert points.shape == (len(snapshots[0].ids), 3) and cells[0].type == "vertex"
            for k in (0, len(snapshots) - 1):
                time, point_data, _ = reader.read_data(k)
                assert time == snapshots[k].time
                assert set(point_data) == _xdmf_grain_arrays(run)
                np.testing.assert_array_equal(point_data["position [m]"], snapshots[k].position)
                np.testing.assert_array_equal(point_data["velocity [m s-1]"], snapshots[k].velocity)
    captured = capfd.readouterr()
    assert captured.out == "" and captured.err == ""


def _blocks(data) -> dict:
    """{block name: dataset} of a VTK composite dataset (a partitioned collection: its first partitions)."""
    if data.IsA("vtkPartitionedDataSetCollection"):
        return {
            data.GetMetaData(i).Get(vtk.vtkCompositeDataSet.NAME()): data.GetPartition(i, 0)
            for i in range(data.GetNumberOfPartitionedDataSets())
        }
    out = {}
    iterator = data.NewIterator()
    iterator.InitTraversal()
    while not iterator.IsDoneWithTraversal():
        out[iterator.GetCurrentMetaData().Get(vtk.vtkCompositeDataSet.NAME())] = iterator.GetCurrentDataObject()
        iterator.GoToNextItem()
    return out


def _arrays(attributes) -> set:
    return {attributes.GetArrayName(i) for i in range(attributes.GetNumberOfArrays())}


def test_vtk_xdmf_reader_reads_every_step_without_messages(run, vtk_messages):
    from vtk.util.numpy_support import vtk_to_numpy

    snapshots = _snapshots(run)
    reader = vtk.vtkXdmfReader()
    reader.SetFileName(str(run / "results.xdmf"))
    reader.UpdateInformation()
    times = reader.GetOutputInformation(0).Get(vtk.vtkStreamingDemandDrivenPipeline.TIME_STEPS())
    assert len(times) == len(snapshots)
    for k in (0, len(snapshots) - 1):
        reader.UpdateTimeStep(times[k])
        blocks = _blocks(reader.GetOutputDataObject(0))
        assert set(blocks) == {"particles", "wheels", "rover"}
        grains = blocks["particles"]
        assert grains.GetNumberOfPoints() == grains.GetNumberOfCells() == len(snapshots[k].ids)
        assert _arrays(grains.GetPointData()) == _xdmf_grain_arrays(run)
        assert _arrays(blocks["rover"].GetPointData()) == {"forward [1]", "up [1]"}
        np.testing.assert_allclose(vtk_to_numpy(grains.GetPoints().GetData()), snapshots[k].position)
        assert blocks["wheels"].GetNumberOfPoints() == len(snapshots[k].wheel_vertices)
    assert vtk_messages() == ""


def test_the_xdmf_of_a_run_without_grains_opens_in_vtk_and_meshio(tmp_path, vtk_messages, capfd):
    """An SCM or analytic run has no grains: its results.xdmf held an empty grain collection, which VTK's
    XDMF reader refused ("Error in Update() of Topology") and meshio's time series reader took for the run
    (0 points). It holds the wheels and the rover only: VTK reads both without a message, meshio the
    rover's pose over time (the last collection)."""
    meshio = pytest.importorskip("meshio")
    run = tmp_path / "scm"
    made_up_results(run, 0, 3)
    snapshots = _snapshots(run)
    reader = vtk.vtkXdmfReader()
    reader.SetFileName(str(run / "results.xdmf"))
    reader.UpdateInformation()
    times = reader.GetOutputInformation(0).Get(vtk.vtkStreamingDemandDrivenPipeline.TIME_STEPS())
    assert len(times) == len(snapshots) == 3
    reader.UpdateTimeStep(times[-1])
    blocks = _blocks(reader.GetOutputDataObject(0))
    assert set(blocks) == {"wheels", "rover"}
    assert blocks["wheels"].GetNumberOfPoints() == len(snapshots[-1].wheel_vertices)
    assert vtk_messages() == ""
    with meshio.xdmf.TimeSeriesReader(str(run / "results.xdmf")) as series:
        points, _ = series.read_points_cells()
        assert series.num_steps == 3 and points.shape == (1, 3)
        _, point_data, _ = series.read_data(2)
        assert set(point_data) == {"forward [1]", "up [1]"}
    assert capfd.readouterr().err == ""


def test_an_export_keeps_a_file_that_appeared_while_it_was_written(tmp_path, monkeypatch):
    """`cosim export vtkhdf RUN --out FILE` without --overwrite looked that FILE was free, then replaced
    what appeared there while it wrote; now that file is kept and the export written beside it, both
    named (FileExistsError); the run's own results.vtkhdf is made again as before."""
    import h5py

    import cosim.vtkhdf

    run, out = tmp_path / "run", tmp_path / "export.vtkhdf"
    made_up_results(run, 300, 2)
    write = cosim.vtkhdf._write

    def another_process_writes_first(f, count, temporary):
        out.write_bytes(b"another export")
        write(f, count, temporary)

    monkeypatch.setattr(cosim.vtkhdf, "_write", another_process_writes_first)
    with pytest.raises(FileExistsError, match="export.new.vtkhdf") as info:
        write_vtkhdf(run / "results.h5", out, replace=False)
    assert info.value.filename == str(out) and out.read_bytes() == b"another export"
    with h5py.File(tmp_path / "export.new.vtkhdf", "r") as f:
        assert "VTKHDF" in f
    assert write_vtkhdf(run / "results.h5", out) == str(out) and out.read_bytes() != b"another export"


def test_vtkhdf_round_trip(run, vtk_messages):
    """vtkHDFReader reads every snapshot of results.vtkhdf: grains, wheels, rover and walls, the positions,
    velocities and radii those of results.h5."""
    from vtk.util.numpy_support import vtk_to_numpy

    snapshots = _snapshots(run)
    with open_results(run / "results.h5") as f:
        faces = int(np.sum(np.where(f["boundaries/kind"][()] == 1, 6, 1)))
    path = write_vtkhdf(run / "results.h5", run / "export.vtkhdf")
    reader = vtk.vtkHDFReader()
    reader.SetFileName(path)
    reader.UpdateInformation()
    assert reader.GetNumberOfSteps() == len(snapshots)
    for k, snapshot in enumerate(snapshots):
        reader.SetStep(k)
        reader.Update()
        blocks = _blocks(reader.GetOutputDataObject(0))
        assert set(blocks) == {"grains", "wheels", "rover", "boundaries"}
        grains = blocks["grains"]
        assert grains.GetNumberOfPoints() == grains.GetNumberOfVerts() == len(snapshot.ids)
        assert _arrays(grains.GetPointData()) == {"radius [m]", "velocity [m s-1]", "displacement [m]", "id [1]"}
        np.testing.assert_array_equal(vtk_to_numpy(grains.GetPoints().GetData()), snapshot.position)
        point_data = grains.GetPointData()
        np.testing.assert_array_equal(vtk_to_numpy(point_data.GetArray("velocity [m s-1]")), snapshot.velocity)
        np.testing.assert_array_equal(vtk_to_numpy(point_data.GetArray("radius [m]")), snapshot.radius)
        np.testing.assert_array_equal(vtk_to_numpy(point_data.GetArray("id [1]")), snapshot.ids)
        wheels = blocks["wheels"]
        np.testing.assert_array_equal(vtk_to_numpy(wheels.GetPoints().GetData()), snapshot.wheel_vertices)
        assert wheels.GetNumberOfPolys() > 0
        np.testing.assert_array_equal(vtk_to_numpy(blocks["rover"].GetPoints().GetData())[0], snapshot.rover_position)
        assert blocks["boundaries"].GetNumberOfPolys() == faces  # a quad per plane, six per box
        assert _arrays(blocks["boundaries"].GetCellData()) == {"wall [1]", "force [N]"}
    assert reader.GetTimeValue() == pytest.approx(snapshots[-1].time)
    assert vtk_messages() == ""


def test_a_run_ends_with_its_vtkhdf_and_the_cli_exports_it(tiny_run, tmp_path, capsys):
    assert (tiny_run / "results.vtkhdf").stat().st_size > 0
    out = tmp_path / "again.vtkhdf"
    assert main(["export", "vtkhdf", str(tiny_run), "--out", str(out)]) == 0
    assert out.stat().st_size > 0 and str(out) in capsys.readouterr().out
    # an existing file is replaced only when asked; a name that is not an export's is never written
    before = out.read_bytes()
    assert main(["export", "vtkhdf", str(tiny_run), "--out", str(out)]) == 3
    assert "pass --overwrite" in capsys.readouterr().err and out.read_bytes() == before
    assert main(["export", "vtkhdf", str(tiny_run), "--out", str(out), "--overwrite"]) == 0
    results = (tiny_run / "results.h5").read_bytes()
    for name in ("results.h5", "checkpoint.npz"):
        assert main(["export", "vtkhdf", str(tiny_run), "--out", str(tiny_run / name), "--overwrite"]) == 2
        assert "must end in .vtkhdf or .hdf" in capsys.readouterr().err
    assert (tiny_run / "results.h5").read_bytes() == results


def test_view_draws_the_run_and_the_frames_differ_where_the_wheel_moved(tiny_run, tmp_path, capsys):
    from matplotlib.image import imread

    snapshots = _snapshots(tiny_run)
    hub = [s.wheel_vertices.mean(axis=0) for s in (snapshots[0], snapshots[-1])]
    assert np.linalg.norm(hub[1] - hub[0]) > 5e-3  # the wheel landed and drove
    first, last = tmp_path / "first.png", tmp_path / "last.png"
    assert main(["view", str(tiny_run), "--out", str(first), "--frame", "0", "--dpi", "40"]) == 0
    assert main(["view", str(tiny_run), "--out", str(last), "--dpi", "40"]) == 0  # the last snapshot
    first_image, last_image = imread(first), imread(last)
    assert first_image.shape == last_image.shape
    changed = np.any(np.abs(first_image - last_image) > 0.1, axis=2)
    assert changed.mean() > 0.01
    # the rows and columns that changed include those of the wheel's way: between the two hubs, in the
    # upper panel (the side view) and in the lower one (the cut)
    rows = np.flatnonzero(changed.any(axis=1))
    assert rows.min() < changed.shape[0] / 2 < rows.max()
    assert str(last) in capsys.readouterr().out


def test_view_writes_a_movie_and_frames_of_a_moving_patch(tmp_path, capsys):
    from cosim.view import ffmpeg_path

    folder = tmp_path / "patch"
    made_up_results(folder, 300, 4, ragged=True)
    movie = tmp_path / ("run.mp4" if ffmpeg_path() else "run.gif")
    assert main(["view", str(folder), "--out", str(movie), "--dpi", "30", "--color", "displacement"]) == 0
    assert movie.stat().st_size > 5_000
    frames = tmp_path / "frames"
    assert main(["view", str(folder), "--out", f"{frames}{os.sep}", "--dpi", "30"]) == 0
    assert sorted(os.listdir(frames)) == [f"frame_{k:04d}.png" for k in range(4)]
    assert str(movie) in capsys.readouterr().out
    # what exists is replaced only with --overwrite; a shorter run's frames replace all the old ones
    before = {p.name: p.read_bytes() for p in [movie, *frames.iterdir()]}
    shorter = tmp_path / "shorter"
    made_up_results(shorter, 300, 2, ragged=True)
    for out in (str(movie), str(frames)):
        assert main(["view", str(shorter), "--out", out, "--dpi", "30"]) == 3
        assert "pass --overwrite" in capsys.readouterr().err
    assert before == {p.name: p.read_bytes() for p in [movie, *frames.iterdir()]}
    assert main(["view", str(shorter), "--out", str(frames), "--dpi", "30", "--overwrite"]) == 0
    assert sorted(os.listdir(frames)) == ["frame_0000.png", "frame_0001.png"]
    assert main(["view", str(shorter), "--out", str(movie), "--dpi", "30", "--overwrite"]) == 0
    assert movie.read_bytes() != before[movie.name]
    assert not [p for p in [*tmp_path.iterdir(), *frames.iterdir()] if p.name.startswith("tmp")]  # no temporaries


def test_view_stopped_midway_leaves_the_former_frames_whole(tmp_path, monkeypatch, capsys):
    """`cosim view RUN --out FRAMES --overwrite` removed the former frames first and drew the new ones in
    their place: stopped midway (Ctrl-C, kill -9) it left part of a set with nothing saying so. The new
    set is drawn beside (FRAMES.drawing-*) and takes the folder's place once whole: at every moment of
    the drawing FRAMES holds the former set, and a view stopped midway leaves it and nothing else."""
    from cosim import view

    longer, shorter, frames = tmp_path / "longer", tmp_path / "shorter", tmp_path / "frames"
    made_up_results(longer, 300, 4, ragged=True)
    made_up_results(shorter, 300, 3, ragged=True)
    assert main(["view", str(longer), "--out", str(frames), "--dpi", "20"]) == 0
    former = {p.name: p.read_bytes() for p in frames.iterdir()}
    assert len(former) == 4
    save = view.save_figure
    drawn = []

    def stopped_at_the_third(fig, path, dpi):
        assert {p.name: p.read_bytes() for p in frames.iterdir()} == former  # a kill here: the former set
        if len(drawn) == 2:
            raise KeyboardInterrupt
        save(fig, path, dpi)
        drawn.append(path)

    monkeypatch.setattr(view, "save_figure", stopped_at_the_third)
    assert main(["view", str(shorter), "--out", str(frames), "--dpi", "20", "--overwrite"]) == 130
    assert all(os.path.dirname(p) != str(frames) for p in drawn)  # drawn elsewhere
    assert {p.name: p.read_bytes() for p in frames.iterdir()} == former
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "longer", "shorter"]  # no drawing left
    monkeypatch.setattr(view, "save_figure", save)
    assert main(["view", str(shorter), "--out", str(frames), "--dpi", "20", "--overwrite"]) == 0
    assert sorted(os.listdir(frames)) == [f"frame_{k:04d}.png" for k in range(3)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "longer", "shorter"]
    assert oct(frames.stat().st_mode & 0o777) == oct(0o777 & ~_umask())  # a folder as any other
    # a link to a folder of frames: the folder it names is drawn again, the link stays
    link = tmp_path / "link"
    link.symlink_to(frames, target_is_directory=True)
    assert main(["view", str(longer), "--out", str(link), "--dpi", "20", "--overwrite"]) == 0
    assert link.is_symlink() and len(os.listdir(frames)) == 4
    link.unlink()
    former = {p.name: p.read_bytes() for p in frames.iterdir()}
    # stopped between moving the former set aside and putting the new one in its place: the former is put back
    rename = os.rename

    def stopped_between(source, target):
        rename(source, target)
        if ".former-" in str(target):
            raise KeyboardInterrupt

    monkeypatch.setattr(os, "rename", stopped_between)
    assert main(["view", str(shorter), "--out", str(frames), "--dpi", "20", "--overwrite"]) == 130
    monkeypatch.setattr(os, "rename", rename)
    assert {p.name: p.read_bytes() for p in frames.iterdir()} == former
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "longer", "shorter"]
    # a file put into the folder while the view drew is not removed with the former frames: kept, and said

    def a_note_arrives(fig, path, dpi):
        (frames / "notes.txt").write_text("mine")
        save(fig, path, dpi)

    monkeypatch.setattr(view, "save_figure", a_note_arrives)
    assert main(["view", str(shorter), "--out", str(frames), "--dpi", "20", "--overwrite"]) == 0
    kept = [p for p in tmp_path.iterdir() if ".former-" in p.name]
    assert len(kept) == 1 and os.listdir(kept[0]) == ["notes.txt"] and kept[0].name in capsys.readouterr().err
    assert sorted(os.listdir(frames)) == [f"frame_{k:04d}.png" for k in range(3)]
    # the working folder (or one above it) is never taken for a folder of frames: it would be moved away
    monkeypatch.chdir(frames)
    for out in (".", str(tmp_path)):
        assert main(["view", str(shorter), "--out", out, "--dpi", "20", "--overwrite"]) == 2
        assert "is the working folder or holds it" in capsys.readouterr().err
    assert os.getcwd() == str(frames) and len(os.listdir(frames)) == 3


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_view_without_ffmpeg_writes_a_gif_and_says_what_an_mp4_needs(tmp_path, monkeypatch, capsys):
    from cosim import view

    monkeypatch.setattr(view, "ffmpeg_path", lambda: None)
    folder = tmp_path / "patch"
    made_up_results(folder, 100, 2, ragged=True)
    assert main(["view", str(folder), "--dpi", "30"]) == 0  # the default: RUN/plots/view.gif
    assert (folder / "plots" / "view.gif").stat().st_size > 1_000
    assert main(["view", str(folder), "--out", str(tmp_path / "movie.mp4")]) == 2
    assert "imageio-ffmpeg" in capsys.readouterr().err


def test_view_refuses_bad_arguments_with_one_line(tiny_run, tmp_path, capsys):
    (tmp_path / "notes").write_text("a user's file, not a folder of frames")
    empty = tmp_path / "empty"
    made_up_results(empty, 10, 0)
    for argv, named in (
        (["view", str(tmp_path / "missing")], "missing"),
        (["view", str(tiny_run), "--out", str(tmp_path / "movie.avi")], "movie.avi"),
        (["view", str(empty)], "results.h5"),
        (["view", str(tiny_run), "--out", str(tmp_path / "one.png"), "--frame", "999"], "--frame"),
        (["view", str(tiny_run), "--out", str(tmp_path / "m.mp4"), "--frame", "3"], "--frame 3: picks the snapshot"),
        (["view", str(tiny_run), "--out", str(tmp_path / "frames"), "--frame", "2"], "draws every one"),
        (["export", "vtkhdf", str(empty)], "results.h5"),
        (["view", str(tiny_run), "--out", str(tmp_path / "f.png"), "--fps", "0"], "--fps 0: allowed 1 to 120"),
        (["view", str(tiny_run), "--out", str(tmp_path / "f.mp4"), "--fps", "1000000"], "--fps 1000000: allowed"),
        (["view", str(tiny_run), "--out", str(tmp_path / "f.png"), "--dpi", "-5"], "--dpi -5: allowed 10 to 600"),
        (["view", str(tiny_run), "--out", str(tmp_path / "f.png"), "--dpi", "7000"], "--dpi 7000: allowed"),
        (["view", str(tiny_run), "--out", str(tmp_path)], "holds files that are not a view's frames"),
        (["view", str(tiny_run), "--out", str(tmp_path / "notes")], "notes' is a file; frames go into a folder"),
        (["run", str(tiny_run / "scene.toml"), "--replicas", "0"], "--replicas must be 1 to 10000"),
    ):
        assert main(argv) == 2, argv
        error = capsys.readouterr().err.strip()
        assert named in error and "\n" not in error, error


def _files(folder) -> dict:
    return {str(path.relative_to(folder)): path.read_bytes() for path in folder.rglob("*") if path.is_file()}


def test_an_export_that_cannot_be_written_names_the_target_and_leaves_no_folder(tmp_path, capsys, monkeypatch):
    """The error named the temporary file (`DIR/tmpXXXX.vtkhdf.tmp: Is a directory`), which the user never
    gave; a missing folder of `--out` is made, but a failed export removes again what it made."""
    import errno

    from cosim import vtkhdf

    folder = tmp_path / "run"
    made_up_results(folder, 20, 2)
    (folder / "results.vtkhdf").mkdir()  # the run's own export, in the way
    (folder / "results.vtkhdf" / "notes.txt").write_text("a user's file")
    before = _files(tmp_path)
    assert main(["export", "vtkhdf", str(folder)]) == 5
    err = capsys.readouterr().err
    assert err.startswith(f"cosim: error: {folder / 'results.vtkhdf'}: Is a directory") and ".tmp" not in err, err
    if os.path.isdir("/proc/self"):  # a folder no file can be made in
        assert main(["export", "vtkhdf", str(folder), "--out", "/proc/x.vtkhdf"]) == 5
        err = capsys.readouterr().err
        assert err.startswith("cosim: error: /proc/x.vtkhdf: ") and ".tmp" not in err, err

    def full(f, count, temporary):
        raise OSError(errno.ENOSPC, "No space left on device")  # as h5py reports it: no file name

    out = tmp_path / "new" / "deeper" / "x.vtkhdf"
    with monkeypatch.context() as patch:
        patch.setattr(vtkhdf, "_write", full)
        assert main(["export", "vtkhdf", str(folder), "--out", str(out)]) == 5
    assert capsys.readouterr().err == f"cosim: error: {out}: No space left on device\n"
    assert sorted(os.listdir(tmp_path)) == ["run"] and _files(tmp_path) == before  # no folder, no temporary
    assert main(["export", "vtkhdf", str(folder), "--out", str(out)]) == 0  # its folders made
    assert out.stat().st_size > 0 and os.listdir(out.parent) == ["x.vtkhdf"]


def test_atomic_path_writes_the_file_a_symbolic_link_points_to(tmp_path):
    """A results or calibration path that is a link (current.toml -> v3.toml) was replaced by a regular file:
    the link gone, the file it named left stale. Now the named file is written atomically, the link kept,
    as open(path, "w") would; a failed write leaves both as they were."""
    from pathlib import Path

    from soil.files import atomic_path, atomic_write_text

    (tmp_path / "store").mkdir()
    named = tmp_path / "store" / "v3.toml"
    named.write_text("old")
    link = tmp_path / "current.toml"
    link.symlink_to(os.path.relpath(named, tmp_path))
    with pytest.raises(RuntimeError), atomic_path(link) as temporary:
        assert os.path.dirname(temporary) == str(named.parent)  # beside the file: one filesystem, atomic
        Path(temporary).write_text("half")
        raise RuntimeError("the writer failed")
    assert link.is_symlink() and named.read_text() == "old" and os.listdir(named.parent) == ["v3.toml"]
    atomic_write_text(link, "new")
    assert link.is_symlink() and os.readlink(link) == os.path.join("store", "v3.toml")
    assert named.read_text() == "new" and os.listdir(named.parent) == ["v3.toml"]
    dangling = tmp_path / "next.toml"
    dangling.symlink_to(tmp_path / "store" / "v4.toml")
    atomic_write_text(dangling, "made")  # a link to a file not yet made: the file is made, as open() does
    assert dangling.is_symlink() and (tmp_path / "store" / "v4.toml").read_text() == "made"


def test_atomic_path_removes_only_the_folders_it_made(tmp_path):
    from pathlib import Path

    from soil.files import atomic_path

    (tmp_path / "kept").mkdir()
    target = tmp_path / "kept" / "a" / "b" / "file.txt"
    with pytest.raises(RuntimeError), atomic_path(target) as temporary:
        assert os.path.dirname(temporary) == str(target.parent)
        raise RuntimeError("the writer failed")
    assert os.listdir(tmp_path) == ["kept"] and os.listdir(tmp_path / "kept") == []
    with pytest.raises(IsADirectoryError) as info, atomic_path(tmp_path / "kept"):
        pass
    assert info.value.filename == str(tmp_path / "kept") and os.listdir(tmp_path / "kept") == []
    with atomic_path(target) as temporary:
        Path(temporary).write_text("whole")
    assert target.read_text() == "whole" and os.listdir(target.parent) == ["file.txt"]


def test_an_export_or_a_view_never_writes_through_a_link_to_the_run_or_to_a_file_not_its_own(tmp_path, capsys):
    """A symbolic link at the export's or the view's output was written through: RUN/results.vtkhdf linked to
    results.h5 (or a --out link to it, to the checkpoint, or to any file) turned the run's results.h5 into the
    export or a PNG. Such an output is refused before anything is written (exit 2, naming the link and what
    is allowed), every file left byte for byte; a link to a file of the export's own suffix is written through,
    the link kept."""
    import h5py

    run = tmp_path / "run"
    made_up_results(run, 60, 2)
    (run / "checkpoint.npz").write_bytes(b"the run's checkpoint")
    (tmp_path / "notes.txt").write_text("a user's file")
    (run / "plots").mkdir()

    def regular() -> dict:  # the files, not the links
        return {path: path.read_bytes() for path in tmp_path.rglob("*") if path.is_file() and not path.is_symlink()}

    before = regular()

    def link(name, target):
        path = tmp_path / name if os.sep not in name else run / name.split(os.sep, 1)[1]
        path.symlink_to(target)
        return str(path)

    own = link(f"run{os.sep}results.vtkhdf", "results.h5")  # the run's own export, made at the end of a run
    export, view = ["export", "vtkhdf", str(run), "--overwrite", "--out"], ["view", str(run), "--dpi", "20"]
    cases = [
        (export[:3], own, "a file of the run it reads"),
        ([*export, own], own, "a file of the run it reads"),
        ([*export, link("a.vtkhdf", run / "results.h5")], "a.vtkhdf", "a file of the run it reads"),
        ([*export, link("c.vtkhdf", run / "checkpoint.npz")], "c.vtkhdf", "a file of the run it reads"),
        ([*export, link("n.hdf", tmp_path / "notes.txt")], "n.hdf", "not a .vtkhdf or .hdf file"),
        ([*view, "--overwrite", "--out", link("p.png", run / "results.h5")], "p.png", "a file of the run it reads"),
        ([*view, "--overwrite", "--out", link("m.gif", tmp_path / "notes.txt")], "m.gif", "not a .gif file"),
    ]
    for name in ("view.mp4", "view.gif"):  # the run's own picture, whichever view makes here
        link(f"run{os.sep}plots{os.sep}{name}", os.path.join("..", "results.h5"))
    cases.append((view, "view.", "a file of the run it reads"))
    link(f"run{os.sep}plots{os.sep}travel_sinkage.png", os.path.join("..", "results.h5"))
    cases.append((["plot", str(run)], "travel_sinkage.png", "not a .png file"))
    for argv, named, allowed in cases:
        assert main(argv) == 2, argv
        error = capsys.readouterr().err.strip()
        assert named in error and allowed in error and "\n" not in error, (argv, error)
        assert regular() == before, argv  # results.h5, the checkpoint and the user's file untouched
    assert (run / "results.vtkhdf").is_symlink() and (tmp_path / "a.vtkhdf").is_symlink()
    # a link to an export is written through: its file replaced, the link kept
    (tmp_path / "store").mkdir()
    (tmp_path / "store" / "old.vtkhdf").write_bytes(b"an older export")
    good = link("good.vtkhdf", os.path.join("store", "old.vtkhdf"))
    assert main(["export", "vtkhdf", str(run), "--out", good, "--overwrite"]) == 0
    assert os.path.islink(good) and os.readlink(good) == os.path.join("store", "old.vtkhdf")
    with h5py.File(tmp_path / "store" / "old.vtkhdf", "r") as f:
        assert "VTKHDF" in f


@pytest.mark.parametrize("kind", ["picture.png", "movie.gif", "frames", "frames.v2"])
def test_view_keeps_an_output_that_appeared_while_it_drew(tmp_path, monkeypatch, capsys, kind):
    """`cosim view RUN --out OUT` without --overwrite looked that OUT was free, then replaced what appeared
    there while it drew. Now, as `cosim export`, what appeared is kept and the view is written beside it
    (OUT-STEM.new.SUFFIX, a folder OUT.new: frames.v2.new, not frames.new.v2), both named, exit 5; with
    --overwrite it is replaced."""
    from cosim import view

    run, out = tmp_path / "run", tmp_path / kind
    made_up_results(run, 60, 2)
    draw = view._Frame.draw

    if kind == "frames.v2":  # a dotted name is a folder of frames where that folder exists (empty here)
        out.mkdir()

    def another_process_writes_first(frame, s, values):
        if kind.startswith("frames") and not (out / "notes.txt").exists():
            out.mkdir(exist_ok=True)
            (out / "notes.txt").write_text("another process's")
        elif not os.path.lexists(out):
            out.write_bytes(b"another process's")
        draw(frame, s, values)

    monkeypatch.setattr(view._Frame, "draw", another_process_writes_first)
    assert main(["view", str(run), "--out", str(out), "--dpi", "20"]) == 5
    error = capsys.readouterr().err
    stem, suffix = os.path.splitext(kind)
    kept = tmp_path / (f"{kind}.new" if kind.startswith("frames") else f"{stem}.new{suffix}")
    assert str(out) in error and str(kept) in error, error
    if kind.startswith("frames"):
        assert os.listdir(out) == ["notes.txt"] and (out / "notes.txt").read_text() == "another process's"
        assert sorted(os.listdir(kept)) == ["frame_0000.png", "frame_0001.png"]
    else:
        assert out.read_bytes() == b"another process's" and kept.stat().st_size > 100
    assert sorted(os.listdir(tmp_path)) == sorted(["run", kind, kept.name])  # nothing else left
    if not kind.startswith("frames"):
        assert main(["view", str(run), "--out", str(out), "--dpi", "20", "--overwrite"]) == 0
        assert out.read_bytes() != b"another process's"


def test_view_refuses_a_file_written_as_a_folder_before_it_draws(tmp_path, monkeypatch, capsys):
    """`--out picture.png/` where picture.png is a file drew every frame and then failed ("Not a directory"):
    it is refused at once, with the message a file given for a folder of frames gets."""
    from cosim import view

    run, picture = tmp_path / "run", tmp_path / "picture.png"
    made_up_results(run, 60, 2)
    picture.write_bytes(b"a picture")

    def never(*args):
        raise AssertionError("drawn before the output was checked")

    monkeypatch.setattr(view._Frame, "draw", never)
    for overwrite in ([], ["--overwrite"]):
        assert main(["view", str(run), "--out", f"{picture}{os.sep}", "--dpi", "20", *overwrite]) == 2
        error = capsys.readouterr().err.strip()
        assert "picture.png" in error and "is a file; frames go into a folder" in error, error
        assert picture.read_bytes() == b"a picture" and sorted(os.listdir(tmp_path)) == ["picture.png", "run"]


def test_plot_of_an_hdf5_file_that_is_not_a_results_file_says_so(tmp_path, capsys):
    """`cosim plot` of an HDF5 results.h5 that another program wrote said "the results file is damaged
    (... object 'wheels' doesn't exist)"; it says what `cosim view` and `cosim export` say."""
    import h5py

    folder = tmp_path / "other"
    folder.mkdir()
    with h5py.File(folder / "results.h5", "w") as f:
        f["x"] = np.arange(3)
    before = _files(tmp_path)
    for command in (["plot"], ["view"], ["export", "vtkhdf"]):
        assert main([*command, str(folder)]) == 2, command
        error = capsys.readouterr().err
        assert f"{folder / 'results.h5'}: not a regolith-cosim results file (format None" in error, (command, error)
    assert _files(tmp_path) == before


def test_ctrl_c_or_sigterm_while_warp_loads_exits_with_one_line(tmp_path, monkeypatch, capsys):
    """Ctrl-C in the first second of any command, while `import cosim` loaded warp (through the package's
    own __init__, before main ran), printed a 29-line traceback, and SIGTERM killed it without a word: the
    command line now starts on the standard library alone, and main answers a stop while warp loads."""
    import subprocess
    import sys

    from cosim import cli

    loaded = subprocess.run(
        [sys.executable, "-c", "import sys, cosim.cli; print(sorted({'warp', 'numpy'} & set(sys.modules)))"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert loaded.stdout.strip() == "[]", loaded.stdout
    for raised, code in ((KeyboardInterrupt(), 130), (KeyboardInterrupt("SIGTERM"), 143)):

        def loading_warp(verbose, raised=raised):
            raise raised

        monkeypatch.setattr(cli, "_setup_output", loading_warp)
        assert main(["plot", str(tmp_path)]) == code
        assert capsys.readouterr().err.strip().startswith("cosim: interrupted.")


def test_ctrl_c_while_a_command_starts_exits_130_without_a_traceback(tmp_path, monkeypatch, capsys):
    """Ctrl-C while `cosim` loaded its modules (before its handlers were in place) printed a traceback."""
    import sys
    import types

    class Loading(types.ModuleType):
        def __getattr__(self, name):
            raise KeyboardInterrupt

    monkeypatch.setitem(sys.modules, "cosim.lab.common", Loading("cosim.lab.common"))
    try:
        code = main(["plot", str(tmp_path)])
    except KeyboardInterrupt:
        code = "a KeyboardInterrupt traceback"
    assert code == 130
    assert "cosim: interrupted" in capsys.readouterr().err
