"""results.h5 follows the documented layout, the XDMF points at real data, a killed run leaves a readable file."""

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from cosim.output import (
    REQUIRED_ATTRIBUTES,
    RESULTS_FORMAT,
    ROVER_SERIES,
    SOIL_SERIES,
    WHEEL_SERIES,
    ResultsWriter,
    documented_layout,
    open_results,
    xdmf_references,
)
from cosim.plan import load_plan
from cosim.scene import scene_from_text
from cosim.single_wheel import PHASE_DRIVING, PHASE_LANDING


def test_layout_matches_the_documentation(tiny_run):
    import h5py

    with open_results(tiny_run / "results.h5") as f:
        mesh = f["wheels/mesh"]
        layout = documented_layout(
            wheels=1,
            particles=f["particles/radius"].shape[0],
            vertices=mesh["vertices"].shape[0],
            triangles=mesh["triangles"].shape[0],
            columns=f["rover/state"].shape[1],
            boundaries=f["boundaries/kind"].shape[0],
        )
        found = set()
        f.visititems(lambda name, obj: found.add(name) if isinstance(obj, h5py.Dataset) else None)
        assert found == set(layout), f"undocumented {found - set(layout)}, missing {set(layout) - found}"
        steps = f["wheels/time"].shape[0]
        snapshots = f["particles/time"].shape[0]
        for name, (shape, kind) in layout.items():
            dataset = f[name]
            expected = tuple(
                (steps if name.startswith(("wheels", "rover", "boundaries", "soil")) else snapshots) if s is None else s
                for s in shape
            )
            assert dataset.shape == expected, name
            assert dataset.dtype.kind == kind, name
        for key in REQUIRED_ATTRIBUTES:
            assert key in f.attrs, key
        assert f.attrs["format"] == RESULTS_FORMAT and f.attrs["status"] in ("complete", "unsteady")
        assert json.loads(f["rover/state"].attrs["columns"])[0] == "x"
        assert len(json.loads(f["rover/state"].attrs["units"])) == f["rover/state"].shape[1]
        assert "warp-lang" in json.loads(f.attrs["versions"])
        scene = scene_from_text(f.attrs["scene_toml"])
        assert scene.scene.name == "tiny"
        summary = json.loads(f.attrs["summary"])
        assert summary["macro_steps"] == steps and "steady_state" in summary
        # the time series are consistent with each other and with the definitions of cosim.metrics
        assert np.all(np.diff(f["wheels/time"][()]) > 0)
        phase = f["wheels/phase"][()]
        # landing, then the drive
        assert phase[0] == PHASE_LANDING and phase[-1] == PHASE_DRIVING and np.all(np.diff(phase) >= 0)
        np.testing.assert_allclose(f["wheels/drawbar_pull"][:, 0], f["wheels/force"][:, 0, 0])
        np.testing.assert_allclose(f["wheels/driving_torque"][:, 0], -f["wheels/torque"][:, 0, 1])
        start = f["wheels/position"][np.argmax(phase == PHASE_DRIVING) - 1, 0, 0]
        driving = phase == PHASE_DRIVING
        np.testing.assert_allclose(f["wheels/travel"][driving, 0], f["wheels/position"][driving, 0, 0] - start)
        assert np.all(np.isnan(f["wheels/slip"][phase == PHASE_LANDING, 0]))  # the wheel does not turn while landing
        assert steps - np.sum(phase == PHASE_LANDING) == load_plan(tiny_run / "scene.toml").drive_steps
        # the walls: over the drive the floor (boundary 0) carries the grains' weight and the wheel's load,
        # less what the side walls hold by friction
        load = float(np.sum(f["particles/radius"][()] ** 3) * 4 / 3 * np.pi * 2600 * 1.625) + 0.3 * 1.625
        walls = f["boundaries/force"][phase == PHASE_DRIVING].mean(axis=0)
        assert -1.05 * load < walls[0, 2] < -0.6 * load, (walls[:, 2], load)
        assert np.sum(walls[:, 2]) == pytest.approx(-load, rel=0.1)


def test_every_dataset_carries_its_unit(tiny_run):
    import h5py

    missing = []
    with open_results(tiny_run / "results.h5") as f:

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset) and not obj.attrs.get("units"):
                missing.append(name)

        f.visititems(visit)
        assert f["wheels/force"].attrs["units"] == "N" and f["wheels/slip"].attrs["units"] == "1"
        assert f["particles/position"].attrs["units"] == "m"
    assert not missing, missing


def test_the_summary_and_the_root_attributes_carry_their_units(tiny_run):
    """run.json's summary and results.h5's (the same) name each number's SI unit; so do the root attributes."""
    from helpers import assert_every_number_has_its_unit

    summary = json.loads((tiny_run / "run.json").read_text())["summary"]
    assert_every_number_has_its_unit(summary)
    units = summary["units"]
    expected = {"sinkage": "m", "sinkage_sem": "m", "drawbar_pull": "N", "driving_torque": "N m", "window": "s"}
    expected.update(dt="s", slip="1", particle_count="count", coupling_energy_created="J")
    assert {key: units[key] for key in expected} == expected
    with open_results(tiny_run / "results.h5") as f:
        assert json.loads(f.attrs["summary"])["units"] == units
        attributes = json.loads(f.attrs["units"])
        numeric = {k for k, v in f.attrs.items() if isinstance(v, (np.number, np.ndarray)) and k != "order_seed"}
    assert numeric <= set(attributes), numeric - set(attributes)
    assert (attributes["gravity"], attributes["wheel_load"], attributes["omega"]) == ("m/s^2", "N", "rad/s")


def numbers_without_a_unit(node: dict, units: dict | None, path: str = "") -> list[str]:
    """The places of the numbers in a JSON object that no units table covers: a dict with its own `units`
    is judged by it, a list of dicts by each one's `unit`, any other number by the table above it."""
    found = []
    for key, value in node.items():
        here = f"{path}{key}"
        if key == "units":
            continue
        if isinstance(value, dict):
            own = value.get("units")
            found += (
                numbers_without_a_unit(value, own, "")
                if own is not None
                else numbers_without_a_unit(value, units, here + ".")
            )
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            found += [f"{here}[{i}]" for i, v in enumerate(value) if "unit" not in v]
        else:
            numbers = [v for v in (value if isinstance(value, list) else [value]) if isinstance(v, (int, float))]
            if any(not isinstance(v, bool) for v in numbers) and here not in (units or {}):
                found.append(here)
    return found


def test_every_number_of_run_json_carries_its_unit(tiny_run):
    """run.json's own wall_time and a bed given as a file (its metrics, its grain count) had no unit: the
    probe of the files read every number against a units table."""
    info = json.loads((tiny_run / "run.json").read_text())
    assert info["bed"]["source"] == "file" and info["bed"]["metrics"]["height"] > 0
    assert numbers_without_a_unit(info, info.get("units")) == []


def test_a_bed_file_carries_the_units_its_arrays_are_documented_in(tiny_bed):
    """Every dataset of a bed file has the unit SoilState (state/), SavedBed (particles/, boundaries/)
    documents for it; the file's root `units` names those of gravity, the metrics, the material table's
    fields (as soil.Material documents them: its angles in radians) and the bed's spec."""
    from dataclasses import fields

    import h5py

    import soil.materials
    import soil.state

    with h5py.File(tiny_bed, "r") as f:
        units: dict = {}
        f.visititems(
            lambda name, obj: units.update({name: obj.attrs.get("units")}) if isinstance(obj, h5py.Dataset) else None
        )
        attributes = json.loads(f.attrs["units"])
        numeric = {k for k in f.attrs if k == "gravity" or k.startswith("metric_")}
        materials, spec = json.loads(f.attrs["materials"]), json.loads(f.attrs["spec"])
    assert None not in units.values() and "" not in units.values(), units
    assert numeric | {"materials", "spec"} == set(attributes)
    assert attributes["gravity"] == "m/s^2" and attributes["metric_height"] == "m"
    assert set(attributes["materials"]) == {f.name for f in fields(soil.Material)} == set(materials[0])
    assert attributes["materials"]["stick_angle"] == "rad" and set(attributes["spec"]) == set(spec)
    particles = {"radius": "m", "mass": "kg", "inv_mass": "1/kg", "inv_inertia": "1/(kg m^2)", "material": "1"}
    assert {k: units[f"particles/{k}"] for k in particles} == particles
    assert units["boundaries/geometry"] == "m"
    info = json.loads((Path(tiny_bed).parent / "bed.json").read_text())  # the settling's record beside it
    assert info["units"]["report.kinetic_energy"] == "J" and info["units"]["metrics.height"] == "m"
    assert {f"metrics.{k}" for k in info["metrics"]} | {"dt", "wall_time", "report.time"} <= set(info["units"])
    for name in (n.split("/", 1)[1] for n in units if n.startswith("state/")):
        assert units[f"state/{name}"] == soil.state.STATE_UNITS[name]
    # the tables say what the attributes' documentation says
    for table, documented in (
        (soil.state.STATE_UNITS, _documented_units(soil.state, "SoilState", "__init__")),
        (attributes["materials"], _documented_units(soil.materials, "Material")),
    ):
        assert len(documented) >= 10
        for name, unit in table.items():
            if name in documented:
                assert unit in documented[name], (name, unit, documented[name])


def test_the_checkpoint_unit_tables_say_what_the_attributes_documentation_says():
    """The units a checkpoint carries (state_dict_units) for the wheels' wrenches, the soil's control, its
    step controller, its divergence monitor and a moving patch, and those of a soil FMU's wheel and SCM
    parameters, are those their attributes document."""
    import cosim.contract
    import soil.control
    import soil.geometry
    import soil.integrator
    import soil.patch
    import soil.scm.terrain
    import soil.stability

    control = {f"{k}_host": v for k, v in soil.control.SoilControl.STATE_UNITS.items()}
    control.update(external_force=soil.control.SoilControl.STATE_UNITS["external_force"])
    controller = soil.integrator.StepController(tolerance=1e-3).state_dict_units()
    # the tolerance is an error in m/s where the error is not normalised (the field `normalise` says so)
    assert soil.integrator.StepController(tolerance=1e-3, normalise=False).state_dict_units()["tolerance"] == "m/s"
    for table, documented, least in (
        (cosim.contract.WRENCH_UNITS, _documented_units(cosim.contract, "WheelWrench"), 7),
        (control, _documented_units(soil.control, "SoilControl", "__init__"), 11),
        (controller, _documented_units(soil.integrator, "StepController"), 14),
        (soil.stability.DivergenceMonitor.STATE_UNITS, _documented_units(soil.stability, "DivergenceMonitor"), 7),
        (soil.patch.SoilPatch.STATE_UNITS, _documented_units(soil.patch, "SoilPatch", "__init__"), 4),
        # and a soil FMU's soil.json (its wheel, its SCM parameters)
        (soil.geometry.GROUSER_WHEEL_UNITS, _documented_units(soil.geometry, "GrouserWheel"), 5),
        (soil.scm.terrain.SCM_PARAMETER_UNITS, _documented_units(soil.scm.terrain, "ScmParameters"), 10),
    ):
        checked = [name for name in table if name in documented]
        assert len(checked) >= least, (checked, documented)
        for name in checked:
            assert table[name] in documented[name], (name, table[name], documented[name])
    # a calibration file's [units] (scene keys) say what ScmParameters' fields say
    from cosim.scm_calibration import SOIL_UNITS

    for key, unit in SOIL_UNITS.items():
        assert unit == soil.scm.terrain.SCM_PARAMETER_UNITS[key.removesuffix("_deg")], key


def _documented_units(module, name: str, method: str | None = None) -> dict[str, tuple[str, ...]]:
    """The unit in brackets that opens the docstring of each attribute of class `name` of `module` (its
    fields, or what its `method` assigns to self); "[-]": "1" or "count"."""
    import ast
    import re

    tree = ast.parse(Path(module.__file__).read_text())
    cls = next(c for c in tree.body if isinstance(c, ast.ClassDef) and c.name == name)
    body = (
        cls.body
        if method is None
        else next(n for n in cls.body if isinstance(n, ast.FunctionDef) and n.name == method).body
    )
    found = {}
    for statement, following in zip(body, body[1:]):
        target = statement.targets[0] if isinstance(statement, ast.Assign) else getattr(statement, "target", None)
        if (
            isinstance(target, (ast.Attribute, ast.Name))
            and isinstance(following, ast.Expr)
            and isinstance(following.value, ast.Constant)
            and (unit := re.search(r"\[([^\]]+)\]", str(following.value.value)))
        ):
            found[target.attr if isinstance(target, ast.Attribute) else target.id] = (
                ("1", "count") if unit.group(1) == "-" else (unit.group(1),)
            )
    return found


def test_xdmf_references_existing_datasets(tiny_run):
    """results.xdmf: three temporal collections (the grains last, for meshio), each DataItem a whole dataset
    of results.xdmf.h5 of the declared shape, and the snapshots' times and grains those of results.h5."""
    import xml.etree.ElementTree as ET

    path = tiny_run / "results.xdmf"
    root = ET.parse(path).getroot()
    collections = root.findall("./Domain/Grid")
    assert [c.get("Name") for c in collections] == ["wheels", "rover", "particles"]
    assert [c.get("CollectionType") for c in collections] == ["Temporal"] * 3
    particles = collections[-1].findall("Grid")
    assert particles[0].find("Topology").get("TopologyType") == "Polyvertex"
    assert {a.get("Name") for a in particles[0].findall("Attribute")} == {
        "radius [m]",
        "velocity [m s-1]",
        "position [m]",
    }
    assert not root.findall(".//DataItem[@ItemType='HyperSlab']")  # meshio follows no hyperslab
    refs = xdmf_references(str(path))
    assert len(refs) >= 5 * len(particles)
    with open_results(tiny_run / "results.h5") as f, open_results(tiny_run / "results.xdmf.h5") as data:
        assert len(particles) == f["particles/time"].shape[0]
        for k, grid in enumerate(particles):
            assert float(grid.find("Time").get("Value")) == f["particles/time"][k]
        for file, dataset, shape in refs:
            assert os.path.samefile(file, tiny_run / "results.xdmf.h5")
            assert data[dataset].shape == shape, dataset
            assert data[dataset].attrs["units"], dataset
        last = particles[-1].find("Geometry/DataItem").text.split(":")[1]
        np.testing.assert_array_equal(data[last][()], f["particles/position"][-1])


def _writer(path, flush_every=3):
    return ResultsWriter.create(
        path,
        attrs={"name": "t"},
        radius=np.ones(4),
        wheel_count=1,
        mesh=(np.eye(3), np.array([[0, 1, 2]]), np.zeros(3, int)),
        rover_columns=["x"],
        rover_units=["m"],
        flush_every=flush_every,
    )


def _record(t):
    record = {"time": t, "phase": PHASE_DRIVING, "rover_state": [t]}
    for name, (tail, *_) in WHEEL_SERIES.items():
        record[name] = np.full((1,) if tail is None else (1, tail), t)
    for name, (tail, *_) in ROVER_SERIES.items():
        record[f"rover_{name}"] = np.full(() if tail is None else (tail,), t)
    for name in SOIL_SERIES:
        record[f"soil_{name}"] = t
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
    # a resume needs no repair tool: the first 8 records and the snapshot go on in a fresh file
    writer = ResultsWriter.resume(path, steps=8, snapshots=1, flush_every=4)
    for k in range(8, 11):
        writer.append_step(_record(100.0 + k))
    writer.close("complete")
    with open_results(path) as f:
        assert f.attrs["status"] == "complete"
        assert list(f["wheels/time"][()]) == [float(k) for k in range(8)] + [108.0, 109.0, 110.0]
        assert f["wheels/force"].shape == (11, 1, 3) and f["wheels/force"].attrs["units"] == "N"
        assert f["particles/position"].shape == (1, 4, 3)


def test_xdmf_kept_by_the_writer_equals_one_written_afresh(tmp_path, monkeypatch):
    """The writer makes each snapshot's XDMF grids once (its writes grow with the new snapshots, not with
    all so far): after 30 snapshots, a resume that cuts them to 12 and writes 5 more at other times, and
    the data file removed under it, results.xdmf is the one written from the results file alone."""
    from collections import Counter

    from cosim import output

    made = []
    grids = output._snapshot_grids
    monkeypatch.setattr(output, "_snapshot_grids", lambda data, name: made.append(name) or grids(data, name))

    def afresh(results):
        with open_results(results) as f:
            output.write_xdmf(f, str(tmp_path / "fresh" / "results.xdmf"))
        (tmp_path / "fresh" / "results.xdmf.h5").unlink()
        return (tmp_path / "fresh" / "results.xdmf").read_text()

    (tmp_path / "fresh").mkdir()
    path = tmp_path / "results.h5"
    grains = np.zeros((4, 3))
    writer = _writer(path)
    for k in range(30):
        writer.add_snapshot(0.125 * k, grains + k, grains, np.full((3, 3), k))
    assert sorted(made) == [f"{k:06d}" for k in range(30)]  # each once
    writer.close("interrupted")
    assert (tmp_path / "results.xdmf").read_text() == afresh(path)

    writer = ResultsWriter.resume(path, steps=0, snapshots=12, flush_every=3)
    made.clear()
    for k in range(12, 17):
        writer.add_snapshot(0.125 * k + 0.0625, grains - k, grains, np.full((3, 3), -k))
    (tmp_path / "results.xdmf.h5").unlink()  # removed under the running writer: made again
    writer.add_snapshot(3.0, grains, grains, np.zeros((3, 3)))
    writer.close("complete")
    # once for the resumed writer, once more when its data file went (the last snapshot came after)
    assert Counter(made) == {**{f"{k:06d}": 2 for k in range(17)}, "000017": 1}
    text = (tmp_path / "results.xdmf").read_text()
    assert text == afresh(path)
    assert 'Value="1.5625"' in text and 'Value="1.5"' not in text  # the resumed snapshot 12, not the cut one


def test_every_json_file_of_a_run_is_strict_json(tiny_run, tmp_path):
    """run.json (and summary.json, study.json, ensemble.json, bed.json: one writer) held Python's NaN
    for what was not measured: no JSON, so jq, JavaScript's JSON.parse and strict parsers refused the
    whole file. A non-finite number is now null; numpy numbers and arrays are plain JSON. The summary
    results.h5 holds is strict JSON too (it held NaN where run.json holds null)."""
    import math

    from cosim.folders import write_json

    def strict(text):
        return json.loads(text, parse_constant=lambda name: pytest.fail(f"{name} is no JSON"))

    info = strict((tiny_run / "run.json").read_text())
    with open_results(tiny_run / "results.h5") as f:  # the same summary, as the results file holds it: strict too
        held = strict(f.attrs["summary"])
    for key, value in held.items():  # null exactly where run.json's is
        if value is None or isinstance(value, (int, float)):
            assert info["summary"][key] == value, key
    import shutil

    from cosim.output import ResultsWriter

    copy = tmp_path / "results.h5"  # a summary with what a run does not measure (a constant speed's correlation)
    shutil.copy(tiny_run / "results.h5", copy)
    ResultsWriter(copy, xdmf=False).mark("complete", summary={"slip": 0.1, "forward_speed_correlation_time": math.nan})
    with open_results(copy) as f:
        assert strict(f.attrs["summary"]) == {"slip": 0.1, "forward_speed_correlation_time": None}
    # and what reads it takes null as not measured: `cosim plot` of a run without a window (its [nan, nan])
    # and of a steady one whose slip was not measured (a TypeError, exit 1, once they were null)
    from cosim.plots import plot_output

    for name, summary in (
        ("no_window", {"steady_state": "no landing", "window": [math.nan, math.nan]}),
        ("no_slip", {"steady_state": "steady", "window": [0.1, 0.2], "slip": math.nan, "drawbar_pull": 0.0}),
    ):
        (tmp_path / "runs" / name).mkdir(parents=True)
        shutil.copy(copy, tmp_path / "runs" / name / "results.h5")
        ResultsWriter(tmp_path / "runs" / name / "results.h5", xdmf=False).mark("complete", summary=summary)
        assert plot_output(str(tmp_path / "runs" / name))
    assert plot_output(str(tmp_path / "runs"))  # both: the slip against drawbar pull scatter too
    path = tmp_path / "summary.json"
    write_json(str(path), {"k": math.nan, "n": np.float32(np.inf), "rows": [np.array([1.0, np.nan])], "i": np.int64(3)})
    assert strict(path.read_text()) == {"k": None, "n": None, "rows": [[1.0, None]], "i": 3}


def test_a_study_scatter_without_steady_runs_says_so(tmp_path, monkeypatch):
    """A precision study whose runs all ended too short wrote scatter.png as three empty panels, nothing
    said. The statistics are over steady runs: a group with none is marked on every panel, and the title
    gives each group's steady count."""
    import math

    from cosim import plots

    figures = []  # closed after saving, still readable
    monkeypatch.setattr(plots, "save_figure", lambda fig, path, dpi: figures.append(fig))
    steady = {"travel_mean": 5e-3, "travel_min": 4e-3, "travel_max": 6e-3, "travel_std": 1e-3}
    steady |= {"slip_mean": 0.2, "slip_min": 0.1, "slip_max": 0.3, "slip_std": 0.1}
    steady |= {"sinkage_mean": 3e-3, "sinkage_min": 2e-3, "sinkage_max": 4e-3, "sinkage_std": 1e-3}
    none = {name: math.nan for name in steady}
    rows = [
        {"precision": "single", "replicas": 3, "steady": 0, **none},
        {"precision": "double", "replicas": 3, "steady": 2, **steady},
    ]
    plots.plot_scatter(str(tmp_path), rows, "precision")
    (figure,) = figures
    assert "steady: 0, 2" in figure._suptitle.get_text()
    for axis in figure.axes:
        marks = [t for t in axis.texts if t.get_text() == "no steady run"]
        assert len(marks) == 1 and marks[0].get_position()[0] == 0  # at the single group, not at double
