"""A scene on the analytic terrain ([terrain] model = "analytic") runs through the same entry point,
runner and writer as on the DEM, and writes the same results file: the same datasets (less the
walls and grains a continuum has none of), and physics that matches the terrain's closed form."""

import h5py
import numpy as np
import pytest

from cosim.contract import SoilSide
from cosim.launch import resume, run_scene
from cosim.output import documented_layout, read_series
from cosim.plan import load_plan
from cosim.scene import SceneError
from cosim.single_wheel import PHASE_DRIVING
from cosim.system import CoupledSystem
from cosim.terrain import WRENCH_SAMPLES, SpringDamperTerrain
from helpers import assert_checkpoint_units, write_tiny

STIFFNESS = 500.0
"""[N/m]: the tiny wheel (0.3 kg on the moon, 0.486 N) sinks about 1 mm."""
DAMPING = 24.0
"""[N s/m]: about critical for the tiny wheel, so it comes to rest soon after it lands."""

ANALYTIC = f"""
[terrain]
model = "analytic"
stiffness = {STIFFNESS}
damping = {DAMPING}
friction = 0.5
surface_height = 0.01
"""

LONGER = ["run.duration=0.4"]
"""A drive long enough for the wheel to come to rest on the spring to 1e-4 (cheap: no grains)."""


def _datasets(path) -> dict:
    """{dataset path: shape} of a results file."""
    found = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: found.update({name: obj.shape}) if isinstance(obj, h5py.Dataset) else None)
    return found


@pytest.fixture(scope="module")
def analytic_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("analytic")
    result = run_scene(write_tiny(folder, ANALYTIC), str(folder / "run"), overrides=LONGER)
    return folder / "run", result


def test_the_analytic_terrain_is_a_soil_side(tmp_path):
    plan = load_plan(write_tiny(tmp_path, ANALYTIC))
    system = CoupledSystem.build(plan, None)
    assert isinstance(system.soil, SpringDamperTerrain) and isinstance(system.soil, SoilSide)
    assert system.bed is None and system.boundaries() is None and system.soil.particles() is None
    assert system.soil.surface_height == 0.01 and system.soil.stiffness == STIFFNESS


def test_a_testbed_scene_on_the_analytic_terrain_writes_a_dem_runs_datasets(analytic_run, tiny_run):
    run, result = analytic_run
    assert result.status in ("complete", "unsteady")
    assert not (run / "bed.h5").exists()  # no bed settled for a terrain without grains
    analytic, dem = _datasets(run / "results.h5"), _datasets(tiny_run / "results.h5")
    assert set(analytic) == {name for name in dem if not name.startswith("boundaries/")}
    with h5py.File(run / "results.h5", "r") as f:
        layout = documented_layout(
            wheels=1,
            particles=0,
            vertices=f["wheels/mesh/vertices"].shape[0],
            triangles=f["wheels/mesh/triangles"].shape[0],
            columns=f["rover/state"].shape[1],
        )
        assert f.attrs["particle_count"] == 0 and f.attrs["surface_height"] == 0.01
        assert f["particles/position"].shape == (len(f["particles/time"]), 0, 3)
    assert set(layout) == set(analytic)
    for name, (shape, _) in layout.items():
        assert len(analytic[name]) == len(shape) and all(s is None or s == a for s, a in zip(shape, analytic[name]))


def test_the_wheel_rests_on_the_analytic_terrain_as_its_closed_form_says(analytic_run):
    run, _ = analytic_run
    series = read_series(run / "results.h5")
    attrs = series["attrs"]
    driving = series["phase"] == PHASE_DRIVING
    assert driving.sum() == load_plan(run / "scene.toml").drive_steps  # it landed, then drove the whole drive
    driving[: np.flatnonzero(driving)[0] + driving.sum() // 2] = False  # the drive's second half: at rest on it
    load = float(attrs["wheel_load"])
    static_sinkage = SpringDamperTerrain(0.025, 1, stiffness=STIFFNESS).static_sinkage(load)
    # the steady normal force carries the wheel's load, and the wheel sinks the spring's load / stiffness
    np.testing.assert_allclose(series["normal_force"][driving, 0], load, rtol=1e-3)
    np.testing.assert_allclose(series["sinkage"][driving, 0], static_sinkage, rtol=1e-3)
    assert np.all(series["contact_count"][driving, 0] == 1)
    assert np.all(series["soil_particle_count"] == 0) and np.all(series["soil_dem_steps"] == 0)
    assert len(series["snapshot_time"]) >= 2
    # its step is its wrench samples' (each macro step in WRENCH_SAMPLES), not the bed's grains' DEM step
    plan = load_plan(run / "scene.toml")
    assert attrs["substeps"] == WRENCH_SAMPLES and attrs["dt"] == pytest.approx(plan.macro_step / WRENCH_SAMPLES)
    assert attrs["dt"] != pytest.approx(plan.dt)


def test_an_analytic_run_resumes_to_the_uninterrupted_result(analytic_run, tmp_path):
    run, _ = analytic_run
    stopped = {}

    def stop(runner):
        if runner.system.coupler.step_count == 100:
            runner.stop_requested = True
            stopped["at"] = runner.system.coupler.time

    from cosim.runner import RunInterrupted

    with pytest.raises(RunInterrupted):
        run_scene(write_tiny(tmp_path, ANALYTIC), str(tmp_path / "run"), hooks={"step": stop}, overrides=LONGER)
    assert stopped
    units = assert_checkpoint_units(tmp_path / "run" / "checkpoint.npz")
    assert units["soil/hub_position"] == "m" and units["coupler/lagged/force"] == "N"
    resume(str(tmp_path / "run"))
    first, second = read_series(run / "results.h5"), read_series(tmp_path / "run" / "results.h5")
    for name in ("time", "position", "force", "sinkage", "rover_state"):
        np.testing.assert_array_equal(first[name], second[name], err_msg=name)


def test_a_rover_scene_runs_on_the_analytic_terrain(tmp_path):
    from rover_helpers import write_small_rover

    pytest.importorskip("mujoco")
    terrain = '\n[terrain]\nmodel = "analytic"\nstiffness = 2000.0\ndamping = 40.0\n'
    result = run_scene(write_small_rover(tmp_path, duration=0.15, extra=terrain), str(tmp_path / "run"))
    assert result.status in ("complete", "unsteady")
    series = read_series(tmp_path / "run" / "results.h5")
    driving = series["phase"] == PHASE_DRIVING
    assert driving.any()
    weight = float(series["attrs"]["rover_mass"]) * float(np.linalg.norm(series["attrs"]["gravity"]))
    # the wheels together carry the rover's weight, and their springs' sinkage carries it on average
    # (the body still rocks on its four springs: each wheel's share moves, their sum does not)
    np.testing.assert_allclose(series["normal_force"][driving].sum(axis=1), weight, rtol=2e-2)
    np.testing.assert_allclose(2000.0 * series["sinkage"][driving].sum(axis=1).mean(), weight, rtol=2e-2)
    # each wheel's travel is its own hub's advance since the drive started (it was measured from the body's
    # centre: the front wheels started 0.2 m ahead, the rear ones 0.2 m behind)
    with h5py.File(tmp_path / "run" / "results.h5", "r") as f:
        travel, hubs = f["wheels/travel"][()], f["wheels/position"][()]
    start = np.argmax(driving) - 1  # the last landing row: where the drive started
    np.testing.assert_allclose(travel[driving], hubs[driving, :, 0] - hubs[start, :, 0], atol=1e-5)


def test_a_mujoco_rover_that_becomes_unstable_stops_the_run_as_diverged(tmp_path, capsys, monkeypatch):
    """A wheel torque of 1e6 N m on the small rover: MuJoCo finds its accelerations huge and resets the
    model to its start (time 0 too), where the run stepped on without end. It is a divergence (exit 4)
    naming the rover, the time and what to change."""
    from cosim.cli import main
    from rover_helpers import write_small_rover

    pytest.importorskip("mujoco")
    monkeypatch.chdir(tmp_path)  # MuJoCo writes its warning to MUJOCO_LOG.TXT in the working folder
    terrain = '\n[terrain]\nmodel = "analytic"\nstiffness = 2000.0\ndamping = 40.0\n'
    scene = write_small_rover(tmp_path, duration=0.15, extra=terrain)
    drive = 'rover.drive={kind="torque", torque=1e6}'
    assert main(["run", scene, "--out", str(tmp_path / "run"), "--no-progress", "--set", drive]) == 4
    message = capsys.readouterr().err
    assert "the rover diverged during the drive: the MuJoCo model became unstable at t = " in message, message


def test_terrain_keys_are_checked():
    from cosim.scene import validate_scene

    with pytest.raises(SceneError) as error:
        validate_scene({"terrain": {"model": "dem", "stiffness": 1.0}})
    assert any(p.startswith("terrain.stiffness: a key of the analytic terrain") for p in error.value.problems)
    with pytest.raises(SceneError) as error:
        validate_scene({"terrain": {"model": "analytic", "stifness": 1.0}})
    assert "terrain.stifness: unknown key (not a scene setting; check the spelling)" in error.value.problems
    with pytest.raises(SceneError) as error:
        validate_scene({"terrain": {"model": "fem"}})
    assert any(p.startswith("terrain.model:") for p in error.value.problems)
    assert validate_scene({}).terrain is None  # a DEM scene's scene.toml stays as it was
