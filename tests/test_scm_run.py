"""Scenes on the SCM terrain ([terrain] model = "scm", cosim.scm_soil) run through the same entry
point, runner and writer as on the DEM and the analytic terrain: the same datasets, a wheel that
carries its load at Bekker's sinkage, a resume bit for bit, a heterogeneous rover (one wheel on the
DEM, the others on SCM) and its resume bit for bit, and bad [terrain] keys refused by name."""

import math
import re

import h5py
import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import brentq

from cosim.contract import SoilSide
from cosim.dem_soil import DemSoil
from cosim.launch import resume, run_scene
from cosim.output import read_series
from cosim.plan import load_plan
from cosim.scene import SceneError, validate_scene
from cosim.scm_soil import CompositeSoil, ScmSoil, chord_angular_velocity
from cosim.single_wheel import PHASE_DRIVING, PHASE_LANDING
from cosim.system import CoupledSystem
from helpers import assert_checkpoint_units, write_tiny
from soil.control import quaternion_integrate

K_C, K_PHI, N = 2.0e3, 8.0e5, 1.1
SCM = f"""
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
SMOOTH = ["wheel.grouser_count=0", "run.duration=0.3"]
"""The tiny wheel without grousers (a rigid cylinder: Bekker's wheel), driven long enough to roll steadily."""


def _datasets(path) -> dict:
    found = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: found.update({name: obj.shape}) if isinstance(obj, h5py.Dataset) else None)
    return found


@pytest.fixture(scope="module")
def scm_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scm")
    result = run_scene(write_tiny(folder, SCM), str(folder / "run"), overrides=SMOOTH)
    return folder / "run", result


def test_the_scm_terrain_is_a_soil_side(tmp_path):
    system = CoupledSystem.build(load_plan(write_tiny(tmp_path, SCM)), None)
    assert isinstance(system.soil, ScmSoil) and isinstance(system.soil, SoilSide)
    assert system.bed is None and system.boundaries() is None and system.soil.particles() is None
    assert system.soil.books().element_count == 0


def test_a_testbed_scene_on_scm_writes_the_analytic_runs_datasets(scm_run, tmp_path):
    run, result = scm_run
    assert result.status in ("complete", "unsteady")
    assert not (run / "bed.h5").exists()
    analytic = tmp_path / "analytic"
    analytic.mkdir()
    terrain = '\n[terrain]\nmodel = "analytic"\nstiffness = 500.0\ndamping = 24.0\n'
    run_scene(write_tiny(analytic, terrain), str(analytic / "run"), overrides=["run.duration=0.02"])
    assert set(_datasets(run / "results.h5")) == set(_datasets(analytic / "run" / "results.h5"))


def _static_sinkage(load, radius, width, spacing, k_phi=K_PHI):
    """The rim bottom's sinkage [m] of a rigid cylinder at rest on Bekker soil: load = integral over its
    contact (both halves) of (k_c / b + k_phi) z(x)^n, z(x) = z0 - (R - sqrt(R^2 - x^2)), b the patch's
    smaller extent (its length 2 x0 or the width, plus one node spacing: soil.scm's patch width)."""

    def carried(z0):
        x0 = math.sqrt(max(0.0, 2 * radius * z0 - z0 * z0))
        b = min(width, 2 * x0) + spacing
        line, _ = quad(lambda x: (K_C / b + k_phi) * max(0.0, z0 - radius + math.sqrt(radius**2 - x**2)) ** N, -x0, x0)
        return width * line - load

    return brentq(carried, 1e-7, 0.5 * radius)


def test_view_of_an_scm_run_says_it_has_no_grains(scm_run, tmp_path):
    """An SCM run has no grains for `cosim view` to draw: a clear input error naming the file (it was a
    numpy error on an empty array), and nothing written."""
    from cosim.view import render
    from soil.errors import InputError

    run, _ = scm_run
    with pytest.raises(InputError, match=r"results.h5: no grains to draw .*cosim plot RUN"):
        render(str(run), str(tmp_path / "view.mp4"))
    assert not (tmp_path / "view.mp4").exists()


def test_an_scm_run_records_the_steps_it_took_not_its_beds_grains(scm_run, tmp_path):
    """An SCM run's `dt` and `substeps` (results.h5's attributes, the summary, the progress bar) were the
    DEM step its bed's grains would take (here 1.4e-4 s, 12 a macro step) next to SCM's own steps in
    /soil (one a macro step): the file contradicted itself. They are SCM's: each macro step in equal
    steps of at most terrain.time_step, as /soil counts them."""
    import json

    def recorded(run):
        with h5py.File(run / "results.h5", "r") as f:
            attrs = dict(f.attrs)
            steps, dt_mean = f["soil/dem_steps"][()], f["soil/dt_mean"][()]
        summary = json.loads(attrs["summary"])
        assert np.all(steps == attrs["substeps"]), (set(steps), attrs["substeps"])
        np.testing.assert_allclose(dt_mean, attrs["dt"], rtol=1e-9)
        assert summary["dt"] == attrs["dt"] and attrs["dt"] * attrs["substeps"] == pytest.approx(attrs["macro_step"])
        return attrs

    run, _ = scm_run
    assert recorded(run)["substeps"] == 1  # time_step unset: the macro step
    finer = tmp_path / "finer"
    plan = load_plan(write_tiny(tmp_path, SCM), SMOOTH)
    time_step = plan.macro_step / 2.5  # three equal steps a macro step
    run_scene(write_tiny(tmp_path, SCM), str(finer), overrides=["run.duration=0.05", f"terrain.time_step={time_step}"])
    attrs = recorded(finer)
    assert attrs["substeps"] == 3 and attrs["dt"] == pytest.approx(plan.macro_step / 3)
    assert plan.dt != pytest.approx(attrs["dt"])  # the bed's grains' step, which no SCM run takes


def test_resume_of_an_scm_run_points_to_error_bars_over_beds(scm_run, tmp_path, capsys):
    """`cosim resume` of a finished SCM run pointed to `--replicas 5` over summation orders, which
    `cosim run` refuses for SCM (it sums in one order: an error bar of 0); it says what `cosim run` says."""
    import shutil

    from cosim.cli import main

    run = shutil.copytree(scm_run[0], tmp_path / "run")
    summary = read_series(run / "results.h5")["attrs"]["summary"]
    assert '"steady_state": "steady"' in summary  # the hint is given for a steady run
    assert main(["resume", str(run), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "error bars: cosim run SCENE --replicas 3 --vary-bed" in out and "--replicas 5" not in out


def test_the_progress_bar_counts_the_landing_and_gives_scms_step(tmp_path, capsys):
    """The bar read 'landing: 0/N macro steps' through the whole landing (N the drive's steps) and gave
    the bed's DEM step and '0 particle-steps/s' for SCM: it counts the landing's steps against the most
    it may take, then the drive's, with the step SCM takes."""
    plan = load_plan(write_tiny(tmp_path, SCM), SMOOTH)
    run_scene(write_tiny(tmp_path, SCM), str(tmp_path / "run"), progress=True, overrides=SMOOTH)
    bar = capsys.readouterr().err.replace("\r", "\n")
    landed = [int(n) for n in re.findall(rf"landing \(ends at rest\): (\d+)/{plan.landing.max_steps} macro", bar)]
    driven = [int(n) for n in re.findall(rf"driving: (\d+)/{plan.drive_steps} macro", bar)]
    assert max(landed) > 0 and max(driven) == plan.drive_steps, (landed[-3:], driven[-3:])
    assert f"dt {plan.macro_step:.3g} s" in bar and "particle-steps" not in bar


def test_the_wheel_carries_its_load_at_bekkers_sinkage(scm_run):
    run, _ = scm_run
    series = read_series(run / "results.h5")
    load = float(series["attrs"]["wheel_load"])
    plan = load_plan(run / "scene.toml")
    landing = np.flatnonzero(series["phase"] == PHASE_LANDING)
    rest = landing[-5:]  # at rest before the drive: the static wheel
    expected = _static_sinkage(load, plan.wheel.rim_radius, plan.wheel.width, plan.wheel.width / 12)
    np.testing.assert_allclose(series["normal_force"][rest, 0], load, rtol=2e-2)
    np.testing.assert_allclose(series["sinkage"][rest, 0], expected, rtol=6e-2)
    driving = np.flatnonzero(series["phase"] == PHASE_DRIVING)
    steady = driving[len(driving) // 2 :]
    np.testing.assert_allclose(series["normal_force"][steady, 0].mean(), load, rtol=2e-2)
    assert np.all(series["contact_count"][steady, 0] > 0)
    assert np.all(series["soil_particle_count"] == 0)


def test_an_scm_run_resumes_bit_for_bit(scm_run, tmp_path):
    run, _ = scm_run

    def stop(runner):
        if runner.system.coupler.step_count == 120:
            runner.stop_requested = True

    from cosim.runner import RunInterrupted

    with pytest.raises(RunInterrupted):
        run_scene(write_tiny(tmp_path, SCM), str(tmp_path / "run"), hooks={"step": stop}, overrides=SMOOTH)
    units = assert_checkpoint_units(tmp_path / "run" / "checkpoint.npz")
    assert units["soil/scm/plastic"] == "m" and units["rover/angle"] == "rad"
    resume(str(tmp_path / "run"))
    first, second = read_series(run / "results.h5"), read_series(tmp_path / "run" / "results.h5")
    for name in ("time", "position", "force", "torque", "sinkage", "rover_state", "contact_count"):
        np.testing.assert_array_equal(first[name], second[name], err_msg=name)


def test_a_resume_refuses_a_mesh_wheel_whose_file_changed_since_the_run_started(tmp_path):
    """A mesh wheel's file changed after the run was interrupted: the resume drove the rest of the run on the
    new wheel (1.3 x larger: "airborne") while results.h5 kept the old one. It is refused by name, before
    anything is touched; with the run's mesh put back it resumes."""
    import hashlib

    from cosim.runner import RunInterrupted
    from soil import GrouserWheel, MeshWheel
    from soil.errors import ArgumentError

    shape = GrouserWheel(radius=0.025, width=0.02, grouser_count=8, grouser_height=0.003, grouser_thickness=0.002)
    wheel = MeshWheel(*shape.to_mesh(arc_segments=72))
    wheel.save(tmp_path / "wheel.obj")
    original = (tmp_path / "wheel.obj").read_bytes()
    scene = write_tiny(tmp_path, SCM)
    mesh = ['wheel={type = "mesh", file = "wheel.obj"}', "run.duration=0.1"]
    mesh += ["terrain.node_spacing=0.002", "terrain.window_length=0.3", "terrain.window_width=0.2"]  # any wheel's

    def stop(runner):
        if runner.system.coupler.step_count == 20:
            runner.stop_requested = True

    with pytest.raises(RunInterrupted):
        run_scene(scene, str(tmp_path / "run"), hooks={"step": stop}, overrides=mesh)
    MeshWheel(wheel.vertices * 1.1, wheel.triangles).save(tmp_path / "wheel.obj")

    def digests():
        folder = tmp_path / "run"
        return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.iterdir() if p.is_file()}

    before = digests()
    with pytest.raises(ArgumentError, match=r"the wheel mesh read now \(wheel.file\) is not the one the run drove"):
        resume(str(tmp_path / "run"))
    assert digests() == before
    (tmp_path / "wheel.obj").write_bytes(original)
    assert resume(str(tmp_path / "run")).status in ("complete", "unsteady")


def test_a_stop_while_the_run_s_files_are_finished_lets_them_be_finished(tmp_path):
    """One Ctrl-C after the drive's last step, while the summary was made, broke off the closing work:
    run.json stayed 'running', results.h5 'running' or without its summary, no results.vtkhdf. A first stop
    signal from there lets the files be finished, as the run would have; then the caller stops (a serial
    study starts no further run): RunInterrupted, saying nothing is left to resume."""
    import json
    import signal

    from cosim.runner import RunInterrupted, Runner

    summary = Runner.summary

    def stopped_while_summarising(runner, *args):
        signal.raise_signal(signal.SIGINT)  # the runner's own handler: a first Ctrl-C
        return summary(runner, *args)

    scene = write_tiny(tmp_path, SCM)
    original = signal.getsignal(signal.SIGINT)
    try:
        Runner.summary = stopped_while_summarising
        with pytest.raises(RunInterrupted, match=r"Ctrl-C: the run had ended \((complete|unsteady)\) and its files"):
            run_scene(scene, str(tmp_path / "run"), overrides=["run.duration=0.05"])
    finally:
        Runner.summary = summary
    assert signal.getsignal(signal.SIGINT) is original  # the run's handlers are taken back
    record = json.loads((tmp_path / "run" / "run.json").read_text())
    assert record["status"] in ("complete", "unsteady")
    with h5py.File(tmp_path / "run" / "results.h5", "r") as f:
        assert f.attrs["status"] == record["status"] and json.loads(f.attrs["summary"])["steady_state"]
    assert (tmp_path / "run" / "results.vtkhdf").is_file()
    # a run that failed (here: its first checkpoint) and is stopped while closing: the caller stops too (a
    # serial study ran its next replica), told how the run ended
    from cosim import runner as runner_module

    def full(path, data, units):
        raise OSError(28, "No space left on device", str(path))

    write_checkpoint = runner_module.write_checkpoint
    try:
        Runner.summary, runner_module.write_checkpoint = stopped_while_summarising, full
        with pytest.raises(RunInterrupted, match=r"the run had ended \(failed: OSError: .*No space left on device"):
            run_scene(scene, str(tmp_path / "failed"), overrides=["run.duration=0.05"])
    finally:
        Runner.summary, runner_module.write_checkpoint = summary, write_checkpoint
    assert json.loads((tmp_path / "failed" / "run.json").read_text())["status"] == "failed"


def test_a_full_disk_names_the_file_the_run_failed_at_not_the_closing_s_next_failure(tmp_path, monkeypatch, capsys):
    """The disk filled at a checkpoint; closing the run, rewriting results.xdmf met the full disk again and
    that error replaced the first: exit 5 named results.xdmf, run.json stayed 'running'. The checkpoint is
    named, run.json says 'failed' with it, and the closing's own failure is only said."""
    import errno
    import json

    from cosim import runner
    from cosim.cli import main
    from cosim.output import ResultsWriter

    def full(path):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(runner, "write_checkpoint", lambda path, data, units: full(path))
    monkeypatch.setattr(ResultsWriter, "update_xdmf", lambda writer: full(tmp_path / "run" / "results.xdmf"))
    scene = write_tiny(tmp_path, SCM)
    assert main(["run", scene, "--out", str(tmp_path / "run"), "--no-progress", "--set", "run.duration=0.05"]) == 5
    err = capsys.readouterr().err
    (line,) = [line for line in err.splitlines() if line.startswith("cosim: error")]
    assert "checkpoint.npz: No space left on device" in line, err
    assert "results.xdmf not brought up to date" in err
    record = json.loads((tmp_path / "run" / "run.json").read_text())
    assert record["status"] == "failed" and "checkpoint.npz" in record["message"]
    # a finished run whose closing fails at results.xdmf, a view derived from results.h5: still finished
    monkeypatch.undo()
    monkeypatch.setattr(ResultsWriter, "update_xdmf", lambda writer: full(tmp_path / "run2" / "results.xdmf"))
    assert main(["run", scene, "--out", str(tmp_path / "run2"), "--no-progress", "--set", "run.duration=0.05"]) in (
        0,
        6,
    )
    assert json.loads((tmp_path / "run2" / "run.json").read_text())["status"] in ("complete", "unsteady")


def test_a_resume_says_in_run_json_that_the_run_runs_again(tmp_path):
    """A resume left run.json 'interrupted' with the old message while it ran (killed, it still said so, its
    checkpoint past that): it says 'running' as a run's start does, and the run's end says how it ended."""
    import json

    from cosim.runner import RunInterrupted

    scene = write_tiny(tmp_path, SCM)
    folder = tmp_path / "run"

    def stop(runner):
        if runner.system.coupler.step_count == 10:
            runner.stop_requested = True

    with pytest.raises(RunInterrupted):
        run_scene(scene, str(folder), hooks={"step": stop}, overrides=["run.duration=0.05"])
    assert json.loads((folder / "run.json").read_text())["status"] == "interrupted"
    seen = []

    def look(runner):
        if not seen:
            seen.append(json.loads((folder / "run.json").read_text()))

    result = resume(str(folder), hooks={"step": look})
    assert seen[0]["status"] == "running" and seen[0]["message"].startswith("resumed from its checkpoint at t = ")
    assert "summary" not in seen[0] and seen[0]["run_id"]
    assert json.loads((folder / "run.json").read_text())["status"] == result.status


def test_an_scm_grid_too_large_is_refused_before_the_run_folder(tmp_path):
    """A node spacing that makes a grid Warp cannot index is refused by scene key before the run's
    folder is made, so a run already there is left as it was."""
    from soil.errors import InputError

    scene = write_tiny(tmp_path, SCM + "node_spacing = 1.0e-6\n")
    out = tmp_path / "run"
    with pytest.raises(InputError, match=r"more than Warp indexes .*terrain\.node_spacing.*terrain\.window_length"):
        run_scene(scene, str(out))
    assert not out.exists()
    from cosim.cli import advise_lines

    advice = advise_lines(load_plan(scene))  # advice before a run says what the run refuses
    assert any(line.startswith("  [OUT OF RANGE] scm_grid_size: ") for line in advice)
    assert "scm_grid_size" in next(line for line in advice if line.startswith("verdict: out of range"))


@pytest.mark.parametrize("key", ["window_length", "window_width"])
def test_an_scm_window_smaller_than_the_wheel_is_named_by_its_key(tmp_path, key):
    """A window that cannot hold the wheel's footprint (its outer radius along x, half its width along y,
    each side of the centre's node) is refused by key before the folder is made, and advise says so
    (the run refused it at its first step, naming a `window` no scene has)."""
    from cosim.cli import advise_lines
    from cosim.scene import SceneError

    scene = write_tiny(tmp_path, SCM + f"{key} = 1.0e-3\n")
    out = tmp_path / "run"
    with pytest.raises(SceneError, match=rf"terrain\.{key}: the SCM window .* must hold the wheels' footprints"):
        run_scene(scene, str(out))
    assert not out.exists()
    advice = advise_lines(load_plan(scene))
    assert any(line.startswith("  [OUT OF RANGE] scm_grid_size: ") and key in line for line in advice)
    # the size the message allows is a window the run takes
    from cosim.scm_soil import check_scm_grid

    with pytest.raises(SceneError) as refused:
        check_scm_grid(load_plan(scene))
    least = float(str(refused.value).rsplit(">= ", 1)[1].split(" m")[0])
    check_scm_grid(load_plan(scene, [f"terrain.{key}={least}"]))
    run_scene(scene, str(out), overrides=[*SMOOTH, f"terrain.{key}={least}", "run.duration=0.02"])


def test_a_rover_scene_runs_on_scm(tmp_path):
    from rover_helpers import write_small_rover

    pytest.importorskip("mujoco")
    result = run_scene(write_small_rover(tmp_path, duration=0.15, extra=SCM), str(tmp_path / "run"))
    assert result.status in ("complete", "unsteady")
    analytic = tmp_path / "analytic"
    analytic.mkdir()
    terrain = '\n[terrain]\nmodel = "analytic"\nstiffness = 2000.0\ndamping = 40.0\n'
    run_scene(write_small_rover(analytic, duration=0.02, extra=terrain), str(analytic / "run"))
    assert set(_datasets(tmp_path / "run" / "results.h5")) == set(_datasets(analytic / "run" / "results.h5"))
    series = read_series(tmp_path / "run" / "results.h5")
    driving = series["phase"] == PHASE_DRIVING
    weight = float(series["attrs"]["rover_mass"]) * float(np.linalg.norm(series["attrs"]["gravity"]))
    np.testing.assert_allclose(series["normal_force"][driving].sum(axis=1).mean(), weight, rtol=5e-2)
    assert series["rover_travel"][-1] > 0


def test_a_heterogeneous_rover_puts_each_wheel_on_its_soil(tmp_path):
    from rover_helpers import write_small_rover

    pytest.importorskip("mujoco")
    mixed = SCM + 'wheels = ["dem", "scm", "scm", "scm"]\n'
    scene = write_small_rover(tmp_path, duration=0.02, extra=mixed)
    plan = load_plan(scene)
    assert plan.terrain.model == "mixed" and plan.terrain.wheel_models == ("dem", "scm", "scm", "scm")
    result = run_scene(scene, str(tmp_path / "run"))
    assert result.status in ("complete", "unsteady")
    from cosim.beds import settled_bed

    system = CoupledSystem.build(plan, settled_bed(plan, str(tmp_path / "run")))
    soil = system.soil
    assert isinstance(soil, CompositeSoil)
    assert isinstance(soil.soil_of(0), DemSoil) and all(isinstance(soil.soil_of(i), ScmSoil) for i in (1, 2, 3))
    assert soil.soil_of(0).surface_height == soil.soil_of(1).surface_height
    series = read_series(tmp_path / "run" / "results.h5")
    assert np.all(series["soil_particle_count"] > 0)  # the DEM wheel's grains
    touching = series["contact_count"][-1]
    assert np.all(touching > 0)  # every wheel on its soil: grains under wheel 0, SCM nodes under 1-3


def test_a_heterogeneous_rover_run_resumes_bit_for_bit(tmp_path):
    """The heterogeneous rover (wheel 0 on the DEM's grains, 1-3 on SCM) stopped on request a few steps
    into its drive (a checkpoint of both soils, then RunInterrupted) and resumed: its final state and
    results.h5 (every dataset and attribute but the run's own: benchmarks/compare_runs.py) are the
    uninterrupted run's to the last bit. Particle snapshots before and after the stop are compared too."""
    from benchmarks.compare_runs import compare
    from cosim.beds import settled_bed
    from cosim.launch import final_state, run_plan
    from cosim.runner import RunInterrupted
    from rover_helpers import write_small_rover

    pytest.importorskip("mujoco")
    mixed = SCM + 'wheels = ["dem", "scm", "scm", "scm"]\n'
    scene = write_small_rover(tmp_path, duration=0.03, snapshots=0.012, checkpoints=1.0, extra=mixed)
    bed = settled_bed(load_plan(scene), str(tmp_path / "bed")).path  # one bed for both runs
    plan = load_plan(scene, [f'bed.bed_file="{bed}"'])
    run_plan(plan, str(tmp_path / "whole"))

    def stop(runner):
        if runner.drive_start_step >= 0 and runner.system.coupler.step_count == runner.drive_start_step + 4:
            runner.stop_requested = True

    with pytest.raises(RunInterrupted):
        run_plan(plan, str(tmp_path / "resumed"), hooks={"step": stop})
    units = assert_checkpoint_units(tmp_path / "resumed" / "checkpoint.npz")
    assert units["soil/part0/simulation/state/position"] == "m" and units["soil/part1/scm/shear"] == "m"
    stopped = read_series(tmp_path / "resumed" / "results.h5")
    assert 0 < len(stopped["time"]) < len(read_series(tmp_path / "whole" / "results.h5")["time"])
    resume(str(tmp_path / "resumed"))
    whole, resumed = final_state(str(tmp_path / "whole")), final_state(str(tmp_path / "resumed"))
    assert set(whole) == set(resumed)
    assert any(k.startswith("soil/part0/") for k in whole) and any(k.startswith("soil/part1/scm/") for k in whole)
    for key in whole:
        np.testing.assert_array_equal(whole[key], resumed[key], err_msg=key)
    assert compare(str(tmp_path / "whole" / "results.h5"), str(tmp_path / "resumed" / "results.h5")) == []


def test_chord_angular_velocity_turns_the_start_into_the_end():
    q0 = np.array([0.9, 0.1, -0.3, 0.2])
    q0 /= np.linalg.norm(q0)
    q1 = quaternion_integrate(q0, [0.3, -1.2, 0.5], 0.01)
    np.testing.assert_allclose(chord_angular_velocity(q0, q1, 0.01), [0.3, -1.2, 0.5], rtol=1e-9)


@pytest.mark.parametrize(
    "terrain, problem",
    [
        ({"model": "scm", "k_c": 1.0}, 'terrain.k_phi: model = "scm" needs the soil\'s'),
        ({"model": "scm", "calibration": "c.toml", "kphi": 1.0}, "terrain.kphi: unknown key"),
        ({"model": "dem", "janosi_k": 0.01}, "terrain.janosi_k: a key of the SCM terrain"),
        ({"model": "analytic", "node_spacing": 0.01}, "terrain.node_spacing: a key of the SCM terrain"),
        ({"model": "scm", "calibration": "c.toml", "n": -1.0}, "terrain.n:"),
        ({"model": "scm", "calibration": "c.toml", "wheels": ["dem", "fem"]}, "terrain.wheels.1:"),
        ({"model": "scm", "calibration": "c.toml", "stiffness": 1.0}, "terrain.stiffness: a key of the analytic"),
    ],
)
def test_bad_terrain_keys_are_refused_by_name(terrain, problem):
    with pytest.raises(SceneError) as error:
        validate_scene({"terrain": terrain})
    assert any(p.startswith(problem) for p in error.value.problems), error.value.problems


def test_a_missing_calibration_file_is_refused(tmp_path):
    with pytest.raises(SceneError) as error:
        load_plan(write_tiny(tmp_path, '\n[terrain]\nmodel = "scm"\ncalibration = "nowhere.toml"\n'))
    assert any(p.startswith("terrain.calibration:") and "nowhere.toml" in p for p in error.value.problems)


def test_a_scene_on_scm_alone_steps_at_its_own_bounce_and_travel_limits(tmp_path):
    """Without run.macro_step a scene on SCM alone couples at SCM's own step, not at the grains'
    Rayleigh time: 0.2 rad of the wheel's elastic bounce, omega_e = sqrt(K_e A g / W) with A the width
    times the contact length at Bekker's closed-form sinkage (z0 = (3 W / ((3 - n)(k_c + b k_phi)
    sqrt(D)))^(2 / (2 n + 1)), computed here), or a quarter node spacing (the default: the width / 12 or
    the grouser thickness / 1.5, whichever is finer) of the tips' travel, whichever is shorter; a given
    macro step and a DEM scene keep theirs."""
    scene = write_tiny(tmp_path, SCM)
    plan = load_plan(scene, {"run.macro_step": None})
    load, wheel = plan.wheel_load, plan.wheel
    r, b = wheel.outer_radius, wheel.width
    z0 = (3 * load / ((3 - N) * (K_C + b * K_PHI) * math.sqrt(2 * r))) ** (2 / (2 * N + 1))
    area = b * 2 * math.sqrt(2 * r * z0)
    bounce = math.sqrt(2.0e7 * area * plan.g / load)
    spacing = min(b / 12, wheel.shape.grouser_thickness / 1.5)
    travel = spacing / (4 * plan.testbed.omega * r)
    assert plan.macro_step == pytest.approx(min(0.2 / bounce, travel), rel=1e-9)
    assert plan.substeps == 1 and plan.dt == plan.macro_step and plan.dt_setting == "run.macro_step"
    fast = load_plan(scene, {"run.macro_step": None, "testbed.omega": 40.0})  # the tips' travel binds
    assert fast.macro_step == pytest.approx(spacing / (4 * 40.0 * r), rel=1e-9)
    assert load_plan(scene).macro_step == 0.0017  # given: kept
    dem = load_plan(write_tiny(tmp_path, "", "dem.toml"), {"run.macro_step": None})
    assert dem.macro_step == pytest.approx(dem.dt * dem.substeps) and dem.substeps == 10
    # a checkpoint stepped at another H (a run begun before SCM had its own step) is not continued
    from cosim.launch import _check_macro_step

    _check_macro_step({"coupler/step_count": 7, "coupler/time": 7 * plan.macro_step}, plan)
    with pytest.raises(SceneError, match="run.macro_step: the run stepped 0.0017 s"):
        _check_macro_step({"coupler/step_count": 7, "coupler/time": 7 * 0.0017}, plan)


def test_a_macro_step_that_does_not_resolve_the_wheel_s_bounce_on_scm_is_flagged(tmp_path):
    """scm_coupling_step: omega_e H of the wheel's elastic bounce (omega_e = sqrt(K_e A g / W) with Bekker's
    closed-form sinkage, computed here) against 2 rad; the run.macro_step it names passes. `cosim advise`
    printed omega_e H (29.5 rad in a user's scene) and judged nothing."""
    from cosim.advice import SCM_BOUNCE_LIMIT
    from cosim.system import validity

    scene = write_tiny(tmp_path, SCM)
    plan = load_plan(scene)
    load, r, b = plan.wheel_load, plan.wheel.outer_radius, plan.wheel.width
    z0 = (3 * load / ((3 - N) * (K_C + b * K_PHI) * math.sqrt(2 * r))) ** (2 / (2 * N + 1))
    bounce = math.sqrt(2.0e7 * b * 2 * math.sqrt(2 * r * z0) * plan.g / load)

    def judged(step):
        findings = validity(load_plan(scene, {"run.macro_step": step}), 0.0)
        return next(f for f in findings if f.check == "scm_coupling_step")

    slow = 3.0 / bounce  # 3 rad a step
    finding = judged(slow)
    assert not finding.ok and finding.value == pytest.approx(3.0, rel=1e-9) and finding.unit == "rad"
    named = float(finding.message.split("set run.macro_step <= ")[1].split(" s")[0])
    assert named == pytest.approx(SCM_BOUNCE_LIMIT / bounce, rel=1e-3) and judged(named).ok
    own = judged(None)
    assert own.ok and own.value <= 0.2 * (1 + 1e-9)  # SCM's own step: 0.2 rad, or the tips' travel


def test_advise_on_an_scm_scene_gives_the_grid_and_the_step_not_the_grains(tmp_path, capsys):
    """`cosim advise` on SCM: the soil's parameters, the grid, Bekker's static sinkage (computed here
    from the closed form) and the coupling step with its bounce phase; no Rayleigh step or grain
    memory (there are no grains to step)."""
    from cosim.cli import main

    scene = tmp_path / "own_step.toml"
    with open(write_tiny(tmp_path, SCM)) as f:
        scene.write_text(f.read().replace("macro_step = ", "# "))
    assert main(["advise", str(scene)]) == 0
    text = capsys.readouterr().out
    plan = load_plan(scene)
    r, b, load = plan.wheel.outer_radius, plan.wheel.width, plan.wheel_load
    z0 = (3 * load / ((3 - N) * (K_C + b * K_PHI) * math.sqrt(2 * r))) ** (2 / (2 * N + 1))
    assert f"static sinkage (Bekker)    {z0:.4g} m" in text
    assert f"H = {plan.macro_step:.4g} s (omega_e H = 0.2 rad; set by SCM's own step)" in text
    assert "node spacing" in text and "scm_sinkage_grains" in text
    assert "Rayleigh" not in text and "memory estimate" not in text


def test_the_advisor_says_where_scm_cannot_represent_the_run(tmp_path):
    from cosim.system import validity

    def failed(overrides):
        plan = load_plan(write_tiny(tmp_path, SCM), overrides)
        return {f.check for f in validity(plan, 0.0) if not f.ok}, {f.check for f in validity(plan, 0.0)}

    bad, _ = failed(['testbed.mode="slip"', "testbed.slip=0.7", "testbed.omega=3.0"])
    assert {"scm_grousers", "scm_sinkage_grains", "scm_slip", "scm_froude"} <= bad
    # a smooth wheel sinking many fine grains deep, slowly, at a moderate slip: nothing to flag
    bad, checked = failed(
        ["wheel.grouser_count=0", "bed.radius_mean=0.0002", 'testbed.mode="slip"', "testbed.slip=0.3"]
    )
    assert not bad and {"scm_sinkage_grains", "scm_slip", "scm_froude"} <= checked
    message = next(f.message for f in validity(load_plan(write_tiny(tmp_path, SCM)), 0.0) if f.check == "scm_grousers")
    assert "use the DEM" in message
    # a run's summary: the measured slip is judged, not the one set (a free wheel's emerges)
    plan = load_plan(write_tiny(tmp_path, SCM), ['testbed.mode="slip"', "testbed.slip=0.1"])
    measured = next(f for f in validity(plan, 0.0, {"slip": 0.75}) if f.check == "scm_slip")
    assert not measured.ok and "(measured)" in measured.message
    assert next(f for f in validity(plan, 0.0) if f.check == "scm_slip").ok
    # the slips of a DP-slip study: 0.4, where the Phobos wheel fit lies inside the DEM's interval, is SCM's;
    # 0.6, where neither current wheel fit gives the DEM's thrust (BENCHMARKS.md, the steady window's
    # section), is the DEM's
    for slip, ok in ((0.4, True), (0.6, False)):
        plan = load_plan(write_tiny(tmp_path, SCM), ['testbed.mode="slip"', f"testbed.slip={slip}"])
        assert next(f for f in validity(plan, 0.0) if f.check == "scm_slip").ok is ok, slip


def test_the_default_grid_resolves_the_grousers_and_a_coarser_one_is_flagged(tmp_path):
    """The default node spacing is the width / 12 or the thinnest grouser / 1.5, whichever is finer;
    `scm_grouser_grid` fails a coarser grid, naming the key and the bound, and a smooth wheel has no
    grousers to resolve."""
    from cosim.scm_soil import scm_settings
    from cosim.system import validity

    def grid(overrides):
        plan = load_plan(write_tiny(tmp_path, SCM), overrides)
        findings = {f.check: f for f in validity(plan, 0.0)}
        return plan, scm_settings(plan, [0], 0.0).parameters.node_spacing, findings.get("scm_grouser_grid")

    plan, spacing, finding = grid(["wheel.grouser_thickness=0.001"])
    assert spacing == pytest.approx(0.001 / 1.5, rel=1e-12) and spacing < plan.wheel.width / 12 and finding.ok
    plan, spacing, finding = grid(["wheel.grouser_thickness=0.004"])  # thicker than 1.5 x width / 12
    assert spacing == pytest.approx(plan.wheel.width / 12, rel=1e-12) and finding.ok
    _, spacing, finding = grid(["wheel.grouser_thickness=0.001", "terrain.node_spacing=0.001"])
    assert spacing == 0.001 and not finding.ok and finding.setting == "terrain.node_spacing"
    assert "node_spacing <= 0.000667 m" in finding.message and finding.value == pytest.approx(1.0)
    plan, spacing, finding = grid(["wheel.grouser_count=0"])
    assert spacing == pytest.approx(plan.wheel.width / 12, rel=1e-12) and finding is None


def _drawbar_beat(tmp_path, name: str, overrides: list[str]) -> dict:
    """The main job's wheel on its wheel-fitted SCM soil, 60 s driven at slip 0.05, after the first 3.5 s
    of driving: DP/W's mean, standard deviation and strongest spectral line [Hz] (with the record's
    frequency resolution [Hz]), the mean rim sinkage [m], and the plan."""
    import os

    scene = os.path.join(os.path.dirname(__file__), "..", "examples", "phobos_single_wheel_scm.toml")
    calibration = 'terrain.calibration="terrain/phobos_regolith_scm_wheel.toml"'
    overrides = [calibration, "run.duration=60.0", "testbed.slip=0.05", *overrides]
    run_scene(scene, str(tmp_path / name), overrides=overrides)
    series = read_series(tmp_path / name / "results.h5")
    driving = np.flatnonzero(series["phase"] == PHASE_DRIVING)
    kept = driving[series["time"][driving] >= series["time"][driving[0]] + 3.5]
    pull = series["drawbar_pull"][kept, 0] / float(series["attrs"]["wheel_load"])
    step = float(np.median(np.diff(series["time"][kept])))
    power = np.abs(np.fft.rfft(pull - pull.mean())) ** 2
    frequencies = np.fft.rfftfreq(len(pull), step)
    return {
        "mean": float(pull.mean()),
        "std": float(pull.std()),
        "line": float(frequencies[1 + np.argmax(power[1:])]),
        "resolution": float(frequencies[1]),
        "sinkage": float(series["sinkage"][kept, 0].mean()),
        "plan": load_plan(scene, overrides),
    }


@pytest.mark.slow
def test_grousers_thinner_than_a_node_spacing_make_the_forces_beat_with_the_grid(tmp_path):
    """The main job's grousers (2 mm) on SCM at slip 0.05 (benchmarks/scm_grid.py). On a grid of 2.67 mm
    (the former default, width / 12) the nodes sample them: the grousers meet the grid at a phase that
    moves by frac(p / h) of a spacing per grouser pitch p = (1 - s) 2 pi r / N on the ground, and DP/W's
    strongest line is that beat, 1 / T_b = dist(p / h, nearest integer) / T_g (T_g = 2 pi / (N omega);
    18.5 s here), within the record's resolution; its scatter is about 2x the default grid's (measured
    0.138 and 0.070). The default grid (t / 1.5) gives the mean DP/W and rim sinkage of a grid 2.2x finer
    still (h = 0.3 t) within 0.015 W and 0.3 mm (measured 0.004 and 0.10 mm), and scatters more than it
    (the grousers' own passage is what is left)."""
    coarse = _drawbar_beat(tmp_path, "coarse", ["terrain.node_spacing=0.002667"])
    default = _drawbar_beat(tmp_path, "default", [])
    fine = _drawbar_beat(tmp_path, "fine", ["terrain.node_spacing=0.0006"])
    plan = coarse["plan"]
    shape, omega = plan.wheel.shape, plan.scene.testbed.omega
    pitch = (1 - 0.05) * 2 * math.pi * shape.radius / shape.grouser_count
    ratio = pitch / 0.002667
    beat = abs(ratio - round(ratio)) * shape.grouser_count * omega / (2 * math.pi)
    assert abs(coarse["line"] - beat) < coarse["resolution"]
    assert default["std"] < 0.7 * coarse["std"] and fine["std"] < default["std"]
    assert abs(default["mean"] - fine["mean"]) < 0.015 and abs(default["sinkage"] - fine["sinkage"]) < 3e-4


def test_the_traverse_example_lands_and_drives_its_rover_forward(tmp_path):
    """examples/phobos_rover_scm_traverse.toml (the full-size rover's 100 m at Phobos gravity on SCM, README
    step 14), its first seconds of driving: on SCM no bed walls bound the drive (its [bed] is 0.16 m long)."""
    pytest.importorskip("mujoco")
    import os

    scene = os.path.join(os.path.dirname(__file__), "..", "examples", "phobos_rover_scm_traverse.toml")
    plan = load_plan(scene)
    assert plan.terrain.model == "scm" and plan.scene.run.duration * 0.006 > 90.0  # about 100 m planned
    run_scene(scene, str(tmp_path / "run"), overrides=["run.duration=3.0"])
    series = read_series(tmp_path / "run" / "results.h5")
    driving = series["phase"] == PHASE_DRIVING
    assert driving.sum() == 30 and np.all(series["contact_count"][driving] > 0)
    assert series["rover_travel"][-1] > 0.005  # [m] it moves off from rest in 3 s at 6 mm/s


def test_an_scm_soil_names_a_step_a_rim_or_a_wheel_it_cannot_take():
    """ScmSoil(time_step="0.001") was a TypeError, a negative rim radius gave that sinkage without a word,
    and highest_point_under(5) an IndexError."""
    from soil import GrouserWheel
    from soil.errors import ArgumentError
    from soil.scm import ScmParameters, ScmTerrain

    parameters = ScmParameters(2.0e3, 8.0e5, 1.1, 50.0, math.radians(30.0), 0.002, 2.0e7, 0.005)
    terrain = ScmTerrain(parameters, [GrouserWheel(0.05, 0.02)], window=(0.3, 0.2))
    for time_step, rims, words in (("0.001", [0.05], "time_step must be a number"), (1e-3, [-0.05], "rim_radii")):
        with pytest.raises(ArgumentError, match=words):
            ScmSoil(terrain, time_step, rims)
    with pytest.raises(ArgumentError, match=r"wheel must be in \[0, 1\), got 5"):
        ScmSoil(terrain, 1e-3, [0.05]).highest_point_under(5, (0.0, 0.0, 0.05))


def test_a_wheel_sinking_past_its_calibration_without_a_landing_is_out_of_range(tmp_path):
    """The main job's SCM wheel at 10 x its load (3 kg) sinks on past its 30 mm radius and never comes to
    rest: no landing, so no window and no measured sinkage, and the run said 'valid' (the calibration-depth
    check waits for the run's sinkage, the slip check of a free wheel for its slip). It is judged on the
    deepest its rim reached (the results' own sinkage series), beyond the 16.5 mm the calibration's DEM
    tests reached, and the slip check it could not make is named 'not judged'."""
    from pathlib import Path

    scene = Path(__file__).parent.parent / "examples" / "phobos_single_wheel_scm.toml"
    out = tmp_path / "heavy"
    result = run_scene(str(scene), str(out), overrides=["testbed.mass=3.0", 'testbed.mode="free"'])
    summary = result.summary
    assert summary["steady_state"] == "no landing"
    deepest = float(np.nanmax(read_series(out / "results.h5")["sinkage"][:, 0]))
    assert summary["deepest_sinkage"] == pytest.approx(deepest) and deepest > 0.0165
    depth = next(f for f in summary["findings"] if f["check"] == "scm_calibration_depth")
    assert not depth["ok"] and "deepest rim sinkage (no window's sinkage)" in depth["message"], depth
    assert summary["not_judged"] == ["scm_slip"]
    assert summary["validity"].startswith("out of range: scm_calibration_depth; not judged: scm_slip")
