"""results.h5 follows the documented layout, the XDMF points at real data, a killed run leaves a readable file."""

import json
import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from cosim.output import (REQUIRED_ATTRIBUTES, RESULTS_FORMAT, ResultsWriter, documented_layout, open_results,
                          xdmf_references)
from cosim.scene import scene_from_text
from cosim_tiny import write_tiny


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    import warp as wp

    from cosim.runner import run_scene

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no per-module load lines
    folder = tmp_path_factory.mktemp("output")
    result = run_scene(write_tiny(folder), str(folder / "run"), progress=False, log=None)
    assert result.status == "complete"
    return folder / "run"


def test_layout_matches_the_documentation(tiny_run):
    import h5py

    with open_results(tiny_run / "results.h5") as f:
        mesh = f["wheels/mesh"]
        layout = documented_layout(wheels=1, particles=f["particles/radius"].shape[0],
                                   vertices=mesh["vertices"].shape[0], triangles=mesh["triangles"].shape[0],
                                   columns=f["rover/state"].shape[1])
        found = set()
        f.visititems(lambda name, obj: found.add(name) if isinstance(obj, h5py.Dataset) else None)
        assert found == set(layout), f"undocumented {found - set(layout)}, missing {set(layout) - found}"
        steps = f["wheels/time"].shape[0]
        snapshots = f["particles/time"].shape[0]
        for name, (shape, kind) in layout.items():
            dataset = f[name]
            expected = tuple((steps if name.startswith(("wheels", "rover")) else snapshots) if s is None else s
                             for s in shape)
            assert dataset.shape == expected, name
            assert dataset.dtype.kind == kind, name
        for key in REQUIRED_ATTRIBUTES:
            assert key in f.attrs, key
        assert f.attrs["format"] == RESULTS_FORMAT and f.attrs["status"] == "complete"
        assert json.loads(f["rover/state"].attrs["columns"])[0] == "x"
        assert "warp-lang" in json.loads(f.attrs["versions"])
        scene = scene_from_text(f.attrs["scene_toml"], check_files=False)
        assert scene.scene.name == "tiny"
        # the time series are consistent with each other
        assert np.all(np.diff(f["wheels/time"][()]) > 0)
        np.testing.assert_allclose(f["wheels/drawbar_pull"][:, 0], f["wheels/force"][:, 0, 0])
        np.testing.assert_allclose(f["wheels/travel"][:, 0], f["wheels/position"][:, 0, 0]
                                   - f.attrs["start_position"][0])
        assert steps == scene.macro_step_count()
        assert snapshots == 1 + int(np.ceil(steps / round(0.03 / f.attrs["macro_step"])))


def test_xdmf_references_existing_datasets(tiny_run):
    import xml.etree.ElementTree as ET

    path = tiny_run / "results.xdmf"
    root = ET.parse(path).getroot()
    collections = root.findall("./Domain/Grid")
    assert [c.get("CollectionType") for c in collections] == ["Temporal", "Temporal"]
    particles = collections[0].findall("Grid")
    assert particles[0].find("Topology").get("TopologyType") == "Polyvertex"
    assert {a.get("Name") for a in particles[0].findall("Attribute")} == {"radius", "velocity"}
    refs = xdmf_references(str(path))
    assert len(refs) >= 3 * len(particles)
    with open_results(tiny_run / "results.h5") as f:
        assert len(particles) == f["particles/time"].shape[0]
        for k, grid in enumerate(particles):
            assert float(grid.find("Time").get("Value")) == f["particles/time"][k]
        for file, dataset, shape, slab in refs:
            assert os.path.samefile(file, tiny_run / "results.h5")
            data = f[dataset]
            assert data.shape == shape, dataset
            if slab is not None:
                start, stride, count = slab
                assert all(s + c <= n for s, c, n in zip(start, count, data.shape)), (dataset, slab)
                assert data[start[0]].shape == tuple(count[1:])


def _writer(path, flush_every=3):
    return ResultsWriter.create(path, attrs={"name": "t"}, radius=np.ones(4), wheel_count=1,
                                mesh=(np.eye(3), np.array([[0, 1, 2]]), np.zeros(3, int)),
                                rover_columns=["x"], flush_every=flush_every)


def _record(t):
    from cosim.output import WHEEL_SERIES

    record = {"time": t, "rover_state": [t]}
    for name, (tail, _) in WHEEL_SERIES.items():
        record[name] = np.full((1,) if tail is None else (1, tail), t)
    return record


def test_exception_leaves_a_closed_readable_file(tmp_path):
    path = tmp_path / "results.h5"
    with pytest.raises(RuntimeError):
        with _writer(path) as writer:
            for k in range(5):
                writer.append_step(_record(0.1 * k))
            raise RuntimeError("boom")
    with open_results(path) as f:
        assert f.attrs["status"] == "failed" and "boom" in f.attrs["message"]
        assert f["wheels/time"].shape == (5,)  # the buffered records were flushed too


def test_refuses_to_replace_results(tmp_path):
    path = tmp_path / "results.h5"
    _writer(path).close()
    with pytest.raises(FileExistsError):
        _writer(path)


def test_killed_writer_leaves_a_readable_file(tmp_path):
    """SIGKILL (no cleanup at all) after some flushes: everything flushed can be read."""
    path = tmp_path / "results.h5"
    script = textwrap.dedent(f"""
        import os, signal, sys
        sys.path.insert(0, {os.path.dirname(__file__)!r})
        from test_output import _writer, _record
        w = _writer({str(path)!r}, flush_every=4)
        for k in range(10):
            w.append_step(_record(float(k)))
        w.add_snapshot(1.0, [[0, 0, 0]] * 4, [[0, 0, 0]] * 4, [[0, 0, 0]] * 3)
        for k in range(10, 13):
            w.append_step(_record(float(k)))  # buffered, never flushed
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == -signal.SIGKILL, done.stderr
    with open_results(path) as f:
        assert f.attrs["status"] == "running"
        times = f["wheels/time"][()]
        assert list(times) == [float(k) for k in range(10)]
        assert f["particles/position"].shape == (1, 4, 3)
