"""Runs end to end: checkpoints and resume (bitwise on the CPU, also after kill -9), the folder lock,
replacing a run only after the new one is built, divergence, and dask ensembles against serial runs."""

import dataclasses
import json
import math
import os
import re
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from cosim.launch import final_state, resume, run_plan
from cosim.metrics import SUMMARY_RULE
from cosim.output import open_results
from cosim.plan import load_plan
from cosim.runner import RunDiverged, RunInterrupted
from helpers import assert_checkpoint_units, write_tiny


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    return write_tiny(tmp_path_factory.mktemp("study"))


def _plan(scene_path, tiny_bed, *extra):
    return load_plan(scene_path, [f'bed.bed_file="{tiny_bed}"', *extra])


@pytest.fixture(scope="module")
def baseline(scene_path, tiny_bed, tmp_path_factory):
    """An uninterrupted run on the shared tiny bed."""
    out = tmp_path_factory.mktemp("baseline") / "run"
    result = run_plan(_plan(scene_path, tiny_bed), str(out))
    assert result.status in ("complete", "unsteady")
    return out


def _assert_same_run(a, b):
    state_a, state_b = final_state(str(a)), final_state(str(b))
    assert set(state_a) == set(state_b)
    for key in state_a:
        np.testing.assert_array_equal(state_a[key], state_b[key], err_msg=key)  # bitwise
    with open_results(a / "results.h5") as fa, open_results(b / "results.h5") as fb:
        for group in ("wheels", "rover", "particles"):
            for name in fa[group]:
                if hasattr(fa[group][name], "shape"):
                    np.testing.assert_array_equal(fa[group][name][()], fb[group][name][()], err_msg=name)
        assert fa.attrs["status"] == fb.attrs["status"]
        assert json.loads(fa.attrs["summary"])["slip"] == json.loads(fb.attrs["summary"])["slip"]


def test_resume_after_a_hard_interrupt_is_bitwise_identical(scene_path, tiny_bed, baseline, tmp_path):
    checkpoints = []

    def stop_after_second_checkpoint(runner):
        checkpoints.append(runner.system.coupler.step_count)
        if len(checkpoints) == 2:
            raise KeyboardInterrupt("test: killed after the second checkpoint")

    def stop_mid_interval(runner):  # between checkpoints: resume must roll back to the last one
        if checkpoints and runner.system.coupler.step_count == checkpoints[-1] + 3:
            raise KeyboardInterrupt("test: killed between checkpoints")

    broken = tmp_path / "broken"
    with pytest.raises(KeyboardInterrupt):
        run_plan(
            _plan(scene_path, tiny_bed),
            str(broken),
            hooks={"checkpoint": stop_after_second_checkpoint, "step": stop_mid_interval},
        )
    info = json.loads((broken / "run.json").read_text())
    assert info["status"] == "interrupted"
    units = assert_checkpoint_units(broken / "checkpoint.npz")
    assert units["soil/simulation/state/angular_velocity"] == "rad/s" and units["loop/rest_heights"] == "m"
    with open_results(broken / "results.h5") as f:
        assert f.attrs["status"] == "interrupted"
        assert f["wheels/time"].shape[0] > checkpoints[-1]  # records past the checkpoint exist; resume cuts them
    assert resume(str(broken)).status in ("complete", "unsteady")
    _assert_same_run(baseline, broken)
    with pytest.raises(AssertionError):  # the comparison can fail: another summation order differs
        other = tmp_path / "other"
        run_plan(_plan(scene_path, tiny_bed, "run.order_seed=7"), str(other))
        _assert_same_run(baseline, other)


def test_resume_after_kill_9_needs_no_tool_and_is_bitwise_identical(scene_path, tiny_bed, baseline, tmp_path):
    """SIGKILL in the middle of the drive: results.h5 is left flagged as open for writing; resume
    copies what the checkpoint covers into a fresh file, with no lost or duplicated rows."""
    killed = tmp_path / "killed"
    script = textwrap.dedent(f"""
        import os, signal
        from cosim.plan import load_plan
        from cosim.launch import run_plan
        plan = load_plan({scene_path!r}, ['bed.bed_file="{tiny_bed}"'])
        seen = []
        def kill(runner):
            seen.append(runner.system.coupler.step_count)
            if len(seen) == 3:  # after the third checkpoint, 5 more steps, then SIGKILL
                runner.hooks["step"] = lambda r: r.system.coupler.step_count == seen[-1] + 5 and os.kill(
                    os.getpid(), signal.SIGKILL)
        run_plan(plan, {str(killed)!r}, hooks={{"checkpoint": kill}})
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == -signal.SIGKILL, done.stderr
    with open_results(killed / "results.h5") as f:
        assert f.attrs["status"] == "running"
    assert resume(str(killed)).status in ("complete", "unsteady")
    _assert_same_run(baseline, killed)


def test_clean_stop_then_resume_is_bitwise_identical(scene_path, tiny_bed, baseline, tmp_path):
    stopped = tmp_path / "stopped"

    def request_stop(runner):  # what the first Ctrl-C does
        if runner.system.coupler.step_count == 25:
            runner.stop_requested = True

    with pytest.raises(RunInterrupted):
        run_plan(_plan(scene_path, tiny_bed), str(stopped), hooks={"step": request_stop})
    checkpoint = np.load(stopped / "checkpoint.npz")
    assert int(checkpoint["coupler/step_count"]) == 25  # the stop wrote a checkpoint at that step
    resume(str(stopped))
    _assert_same_run(baseline, stopped)


def test_divergence_names_time_grain_position_and_setting(scene_path, tiny_bed, tmp_path):
    out = tmp_path / "boom"

    def explode(runner):  # a grain suddenly flies off, as in a DEM explosion
        if runner.system.coupler.step_count == 9:
            v = runner.system.soil.sim.state.velocity.numpy()
            v[3] = (0.0, 0.0, 1e3)
            runner.system.soil.sim.state.velocity.assign(v)

    with pytest.raises(RunDiverged) as info:
        run_plan(_plan(scene_path, tiny_bed, "run.dt=1.7e-4"), str(out), hooks={"step": explode})
    message = str(info.value)
    for words in (
        "diverged at t = ",
        "particle 3",
        "position (",
        "m/s exceeds",
        "Lower run.dt ",
        "during the landing",
        "run the scene again (a resume would repeat the same steps)",
        "diverged_state.npz",
    ):
        assert words in message, (words, message)
    assert not (out / "checkpoint.npz").exists() and "checkpoint.npz" not in message
    with open_results(out / "results.h5") as f:
        assert f.attrs["status"] == "diverged"
    assert json.loads((out / "run.json").read_text())["status"] == "diverged"
    good = np.load(out / "diverged_state.npz")
    assert np.all(np.isfinite(good["velocity"])) and np.max(np.linalg.norm(good["velocity"], axis=1)) < 1.0
    units = json.loads(str(good["units"]))  # every array's unit
    assert set(units) == set(good.files) - {"units", "integrity/sha256"} and units["velocity"] == "m/s"


def test_a_diverging_soil_is_checked_before_its_snapshot_and_left_out_of_the_summary(scene_path, tiny_bed, tmp_path):
    """A grain flung at step 36, where a snapshot and a checkpoint are due (every 0.03 s, the first at step
    18): the snapshot was written before the check, holding the exploding grain. Now the check comes first:
    no snapshot holds it; the rows after the last good state (the check at step 30) stay in results.h5 as
    the record of the divergence, but the summary leaves them out and names that time. A resume would
    repeat the same steps from the checkpoint of step 18 and diverge again: it is refused, nothing changed."""
    from cosim.launch import resume
    from soil.errors import ArgumentError

    out = tmp_path / "boom"
    macro_step = 0.0017

    def explode(runner):
        if runner.system.coupler.step_count == 36:
            v = runner.system.soil.sim.state.velocity.numpy()
            v[3] = (0.0, 0.0, 1e3)
            runner.system.soil.sim.state.velocity.assign(v)

    with pytest.raises(RunDiverged, match="m/s exceeds"):
        run_plan(_plan(scene_path, tiny_bed, "run.dt=1.7e-4"), str(out), hooks={"step": explode})
    with open_results(out / "results.h5") as f:
        snapshots = [f["particles/velocity"][k] for k in range(len(f["particles/time"]))]
        row_times = f["wheels/time"][()]
    assert all(np.max(np.linalg.norm(v, axis=1)) < 1.0 for v in snapshots)  # none holds the flung grain
    run = json.loads((out / "run.json").read_text())
    assert run["summary"]["last_good_time"] == pytest.approx(30 * macro_step)
    assert run["summary"]["units"]["last_good_time"] == "s"
    assert row_times[-1] == pytest.approx(36 * macro_step)  # the diverging steps' rows are kept
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    with pytest.raises(ArgumentError, match=r"diverged .*a resume repeats the same steps .*nothing was changed"):
        resume(str(out))
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before


def test_a_run_stopped_by_another_worlds_divergence_keeps_its_rows_and_resumes(
    scene_path, tiny_bed, baseline, tmp_path
):
    """A run of a batch stops when another world diverges (soil.worlds marks the error `elsewhere`): its own
    soil is sound, so its summary keeps every row and says so, and `cosim resume` continues it alone to
    the uninterrupted run's result, bit for bit."""
    from cosim.launch import resume
    from soil import SimulationDiverged

    out = tmp_path / "neighbour"

    def neighbour_diverges(runner):
        if runner.system.coupler.step_count == 20:  # after the checkpoint of step 18
            raise SimulationDiverged("world 1 diverged [a batch of 2 worlds]", None, elsewhere=True)

    with pytest.raises(RunDiverged, match=r"this run's own soil is sound. Its last checkpoint .* continues it alone"):
        run_plan(_plan(scene_path, tiny_bed), str(out), hooks={"step": neighbour_diverges})
    summary = json.loads((out / "run.json").read_text())["summary"]
    assert summary["diverged_elsewhere"] is True and "last_good_time" not in summary
    assert resume(str(out)).status in ("complete", "unsteady")
    _assert_same_run(baseline, out)


def test_a_folder_in_use_is_refused_and_left_alone(scene_path, tiny_bed, baseline, tmp_path):
    """A second `cosim run --overwrite` while a run holds the folder: refused (exit 3), nothing deleted."""
    import shutil

    from cosim.cli import main

    busy = tmp_path / "busy"
    shutil.copytree(baseline, busy)
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            textwrap.dedent(f"""
        import sys, time
        from cosim.folders import RunFolder
        with RunFolder({str(busy)!r}).locked():
            print("locked", flush=True)
            time.sleep(60)
    """),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        before = {p.name: p.stat().st_mtime_ns for p in busy.iterdir()}
        code = main(
            [
                "run",
                scene_path,
                "--out",
                str(busy),
                "--overwrite",
                "--no-progress",
                "--set",
                f'bed.bed_file="{tiny_bed}"',
            ]
        )
        assert code == 3
        assert {p.name: p.stat().st_mtime_ns for p in busy.iterdir()} == before
    finally:
        holder.kill()
        holder.wait()


@pytest.mark.parametrize(
    "override,words",
    [
        ('bed.bed_file="/nonexistent/bed.h5"', "bed.bed_file"),
        ("testbed.omega=nan", "testbed.omega"),
        ("bed.seed=-1", "bed.seed"),
        ("bed.length=inf", "bed.length"),
        ('scene.device="cuda:63"', "scene.device"),
        ('bed.bed_file="NOT_HDF5"', "bed.bed_file"),
    ],
)
def test_overwrite_with_a_bad_scene_keeps_the_old_run(
    scene_path, tiny_bed, baseline, tmp_path, capsys, override, words
):
    import shutil

    from cosim.cli import main

    old = tmp_path / "old"
    shutil.copytree(baseline, old)
    before = {p.name: p.stat().st_mtime_ns for p in old.iterdir()}
    if "NOT_HDF5" in override:  # a file that exists but is not a bed
        (tmp_path / "bed.h5").write_bytes(b"not an hdf5 file")
        override = override.replace("NOT_HDF5", str(tmp_path / "bed.h5"))
    code = main(
        [
            "run",
            scene_path,
            "--out",
            str(old),
            "--overwrite",
            "--no-progress",
            "--set",
            f'bed.bed_file="{tiny_bed}"',
            "--set",
            override,
        ]
    )
    assert code == 2
    assert words in capsys.readouterr().err
    assert {p.name: p.stat().st_mtime_ns for p in old.iterdir()} == before


def test_dask_and_batched_ensembles_match_serial_runs(scene_path, tiny_bed, tmp_path):
    """A precision study gives the same replicas run one by one, on a dask cluster, and batched (each
    precision's replicas as worlds of one simulation: one batch per precision)."""
    from cosim.study import precision_study

    plan = _plan(scene_path, tiny_bed)
    kwargs = dict(replicas=2, precisions=("single", "mixed"), plot=False)
    serial = precision_study(plan, str(tmp_path / "serial"), executor="serial", batched=False, **kwargs)
    ensemble = precision_study(plan, str(tmp_path / "dask"), executor="dask", workers=2, batched=False, **kwargs)
    batched = precision_study(plan, str(tmp_path / "batched"), batched=True, **kwargs)
    assert batched["batched"] and not serial["batched"]
    assert [r["batch"]["worlds"] for r in batched["replicas"]] == [2] * 4
    keys = ("travel", "slip", "sinkage", "drawbar_pull", "simulated_time", "steady_state")
    assert len(serial["replicas"]) == len(ensemble["replicas"]) == len(batched["replicas"]) == 4
    for a, b, c in zip(serial["replicas"], ensemble["replicas"], batched["replicas"]):
        assert a["ok"] and b["ok"] and c["ok"], (a.get("error"), b.get("error"), c.get("error"))
        assert (a["precision"], a["replica"]) == (b["precision"], b["replica"]) == (c["precision"], c["replica"])
        assert {k: a["summary"].get(k) for k in keys} == {k: b["summary"].get(k) for k in keys}
        assert {k: a["summary"].get(k) for k in keys} == {k: c["summary"].get(k) for k in keys}
    # the precisions give different runs: a batch run in the wrong precision would show
    assert serial["replicas"][0]["summary"]["drawbar_pull"] != serial["replicas"][2]["summary"]["drawbar_pull"]
    # replicas differ only in the summation order (order_seed = replica index), on one shared bed
    for r in serial["replicas"]:
        with open_results(os.path.join(r["out_dir"], "results.h5")) as f:
            assert f.attrs["order_seed"] == r["replica"]
            assert json.loads(f.attrs["bed"])["path"] == serial["bed_file"]
    header = (tmp_path / "serial" / "study.csv").read_text().splitlines()[0]
    assert "slip_mean [1]" in header and "sinkage_std [m]" in header
    # the counts carry theirs, and the paper's question per metric is a column as in the printed table
    assert "replicas [count],steady [count],failed [count]" in header and "sinkage_deterministic" in header
    for row in serial["rows"]:
        sinkage = row["stats"]["metrics"]["sinkage"]
        assert row["sinkage_deterministic"] == (sinkage["deterministic"] if sinkage["n"] >= 2 else None)


@pytest.mark.parametrize(
    "study, values, words",
    [
        ("precision", ["single", "half"], "--precisions: unknown precision 'half'; allowed: single, mixed, double"),
        ("precision", ["double", "single", "double"], "--precisions: double given twice"),
        ("precision", [], "--precisions: give at least one"),
        ("slip", [0.1, 0.3, 0.1001], "--slips: +0.100 given twice (to 3 decimals"),
        ("slip", [0.1, 1.2], "--slips: 1.2 must be in (-1, 1)"),
    ],
)
def test_a_study_refuses_bad_or_repeated_points_before_it_writes(scene_path, tiny_bed, tmp_path, study, values, words):
    """Two points of a study that would share a folder, or one that no run can make, are refused by
    name before the study's folder exists."""
    from cosim.scene import SceneError
    from cosim.study import precision_study, slip_study

    plan, out = _plan(scene_path, tiny_bed), tmp_path / "study"
    with pytest.raises(SceneError, match=re.escape(words)):
        if study == "precision":
            precision_study(plan, str(out), precisions=values, executor="serial")
        else:
            slip_study(plan, str(out), values, executor="serial")
    assert not out.exists()


def test_replicas_refuse_a_count_and_options_they_cannot_take_before_anything_runs(
    scene_path, tiny_bed, tmp_path, capsys
):
    """--replicas 10^9 settled a bed and filled 23 GB with tasks before a run; --batched with --workers or
    --serial ran on, ignoring them; replicas of a scene with run.order_seed = 5 ran seeds 0 and 1. Now: the
    count is refused by name before the scene is read, an executor with --batched is refused, an executor
    asked for without --batched runs separate runs (no batch on a GPU), and replica k sums in order
    run.order_seed + k (as far as the largest seed)."""
    from cosim.cli import main
    from cosim.scene import INT64_MAX, SceneError
    from cosim.study import MAX_REPLICAS, _batching, _replica_overrides, check_replicas, replica_run
    from soil.errors import ArgumentError

    out = tmp_path / "replicas"
    assert main(["run", str(scene_path), "--out", str(out), "--replicas", str(10**9)]) == 2
    assert f"--replicas must be 1 to {MAX_REPLICAS}" in capsys.readouterr().err and not out.exists()
    plan = _plan(scene_path, tiny_bed)
    for option in ({"workers": 2}, {"executor": "serial"}):
        with pytest.raises(ArgumentError, match="batched runs are worlds of one simulation in this process"):
            replica_run(plan, str(out), 2, batched=True, **option)
        assert not out.exists()
    gpu = dataclasses.replace(plan, device="cuda:0")  # what a GPU would batch by itself
    assert _batching(gpu, None) and not _batching(gpu, None, executor="serial") and not _batching(gpu, None, workers=2)
    seeded = _plan(scene_path, tiny_bed, "run.order_seed=5")
    assert [_replica_overrides(k, None, "order", seeded)["run.order_seed"] for k in range(3)] == [5, 6, 7]
    assert [_replica_overrides(k, None, "order", plan)["run.order_seed"] for k in range(2)] == [0, 1]
    check_replicas(_plan(scene_path, tiny_bed, f"run.order_seed={INT64_MAX - 2}"), 3, 2)
    with pytest.raises(SceneError, match=r"allowed: run.order_seed <= 9223372036854775805"):
        check_replicas(_plan(scene_path, tiny_bed, f"run.order_seed={INT64_MAX - 1}"), 3, 2)


def test_a_replicas_folder_without_its_recipe_names_the_replicas_to_resume(tmp_path, capsys):
    """Replicas interrupted before they kept their recipe: `cosim resume OUT` said "no scene.toml: not a run
    folder"; it names the replica folders, each of which resumes alone."""
    from cosim.cli import main

    for k in range(2):
        (tmp_path / f"replica_{k:03d}").mkdir()
        (tmp_path / f"replica_{k:03d}" / "scene.toml").write_text("")
    assert main(["resume", str(tmp_path)]) == 2
    said = capsys.readouterr().err
    assert "holds replicas (replica_000, replica_001) without the recipe" in said, said
    assert f"cosim resume {tmp_path / 'replica_000'}" in said
    # a precision study's runs by precision; a folder one level above a set of replicas is none of them
    for precision in ("single", "double"):
        (tmp_path / "study" / precision / "replica_000").mkdir(parents=True)
        (tmp_path / "study" / precision / "replica_000" / "scene.toml").write_text("")
    assert main(["resume", str(tmp_path / "study")]) == 2
    said = capsys.readouterr().err
    assert "holds a precision study's runs (double/replica_000, single/replica_000) without the recipe" in said
    assert main(["resume", str(tmp_path.parent)]) == 2
    said = capsys.readouterr().err
    assert "without the recipe" not in said and "not a run folder" in said, said


def test_a_set_of_replicas_is_resumed_only_from_its_own_recipe_where_it_was_made(
    scene_path, tiny_bed, tmp_path, capsys, monkeypatch
):
    """An edited replicas.json (the wheel's omega 1 -> 2 rad/s) was resumed: the ensemble's scene said 2 over
    runs made at 1. A moved set failed each replica on its old bed path, said only in ensemble.json. Both are
    refused before anything is touched, naming the file or the folder it was made in; the set, stopped while
    its beds settled, then resumes where it was made."""
    import shutil

    import cosim.study
    from cosim.cli import main
    from cosim.study import REPLICAS_FILE, replica_run

    def stopped(plan, out_dir, ex, replicas, vary):  # while the beds settle: before any run
        raise KeyboardInterrupt

    settle = cosim.study._replica_beds
    monkeypatch.setattr(cosim.study, "_replica_beds", stopped)
    out = tmp_path / "set"
    with pytest.raises(KeyboardInterrupt, match="cosim resume"):
        replica_run(_plan(scene_path, tiny_bed), str(out), 2, executor="serial", batched=False)
    monkeypatch.setattr(cosim.study, "_replica_beds", settle)
    recipe = out / REPLICAS_FILE
    text = recipe.read_text()
    recipe.write_text(text.replace("omega = 1.0", "omega = 2.0"))
    assert text != recipe.read_text()
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    assert main(["resume", str(out)]) == 2
    said = capsys.readouterr().err
    assert f"{recipe}: not the recipe its set of replicas wrote" in said and "digest" in said, said
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == before
    recipe.write_text(text)
    moved = tmp_path / "moved"
    shutil.move(out, moved)
    before = {p.relative_to(moved): p.stat().st_mtime_ns for p in moved.rglob("*")}
    assert main(["resume", str(moved)]) == 2
    assert f"the set of replicas was made in {out}" in capsys.readouterr().err
    assert {p.relative_to(moved): p.stat().st_mtime_ns for p in moved.rglob("*")} == before
    # where it was made, the set stopped while its beds settled resumes: its bed, then both runs, then its
    # table; a stop during that resume stops it (it was taken for the replica's failure, the next one run)
    shutil.move(moved, out)

    def stopped_run(task):
        raise RunInterrupted("stopped after a checkpoint", signal="SIGTERM")

    run_task = cosim.study.run_task
    monkeypatch.setattr(cosim.study, "run_task", stopped_run)
    assert main(["resume", str(out)]) == 143 and not (out / "ensemble.json").exists()
    monkeypatch.setattr(cosim.study, "run_task", run_task)
    assert main(["resume", str(out)]) == 6  # the tiny drive ends unsteady
    report = json.loads((out / "ensemble.json").read_text())
    assert report["resumed"] and [r["status"] for r in report["results"]] == ["unsteady", "unsteady"]
    assert json.loads(recipe.read_text())["beds"] == [tiny_bed, tiny_bed]  # kept for any later resume


def test_timestep_study_ends_with_an_answer_in_bounded_tries(scene_path, tiny_bed, tmp_path):
    from cosim.study import timestep_study

    report = timestep_study(_plan(scene_path, tiny_bed), str(tmp_path / "ts"), duration=0.02, growth=3.0, max_tries=5)
    assert 1 <= len(report["tried"]) <= 5
    assert report["tried"][0]["dt"] == pytest.approx(report["scene_dt"])
    assert report["largest_stable"] is not None and report["largest_stable"] >= report["scene_dt"]
    if report["first_unstable"] is not None:
        assert report["largest_stable"] < report["first_unstable"]
        assert report["tried"][-1]["stable"] is False
    assert json.loads((tmp_path / "ts" / "study.json").read_text())["kind"] == "timestep"
    # tries that end before one explodes found a lower bound, not the largest stable step: said so
    bound = timestep_study(_plan(scene_path, tiny_bed), str(tmp_path / "one"), duration=0.02, max_tries=1)
    assert bound["first_unstable"] is None and bound["largest_stable"] == pytest.approx(bound["scene_dt"])
    assert "no try was unstable (1 of --max-tries): the largest stable step is at least" in bound["note"]


def test_a_jolt_beeman_scene_carries_the_wheel_and_resumes_bitwise(scene_path, tiny_bed, baseline, tmp_path):
    """run.integrator = "jolt-beeman" (the paper's predictor-corrector): the wheel lands and, over the
    drive, the soil carries its weight (mean vertical force within 15 % of m g; measured -8 % with
    jolt-Beeman, -3.5 % with velocity Verlet on this bed: the wheel still rocks on a few coarse
    grains) at a sinkage between zero and the wheel's radius; the file names the integrator, and a
    stopped run resumes bit for bit (the previous force travels in the checkpoint). Which grains give
    way differs between integrators, so the sinkage is bounded, not compared."""
    plan = _plan(scene_path, tiny_bed, 'run.integrator="jolt-beeman"')
    assert plan.integrator == "jolt-beeman"
    whole = tmp_path / "jb"
    assert run_plan(plan, str(whole)).status in ("complete", "unsteady")
    weight = plan.testbed.mass * plan.g
    for folder in (whole, baseline):
        with open_results(folder / "results.h5") as f:
            drive = f["wheels/phase"][()] == 1
            vertical = -(f["wheels/force"][:, 0, :] @ np.asarray(plan.gravity)) / plan.g
            assert drive.sum() > 20 and abs(vertical[drive].mean() - weight) < 0.15 * weight, folder
            assert 0 < f["wheels/sinkage"][:, 0][drive].mean() < plan.wheel.rim_radius
            if folder == whole:
                assert f.attrs["integrator"] == "jolt-beeman"
    stopped = tmp_path / "stopped"

    def request_stop(runner):
        if runner.system.coupler.step_count == 25:
            runner.stop_requested = True

    with pytest.raises(RunInterrupted):
        run_plan(plan, str(stopped), hooks={"step": request_stop})
    resume(str(stopped))
    _assert_same_run(whole, stopped)


def test_a_timestep_search_that_finds_no_stable_step_ends_with_a_clear_failure(scene_path, tiny_bed, tmp_path, capsys):
    """Every try explodes (a step 20 x the advised one): the search stops after --max-tries runs,
    logs one line per try, says that no stable step was found, and the CLI exits 1."""
    from cosim.cli import main

    # tries of 100 DEM steps of the scene's 6 ms at least (study.MIN_TRY_STEPS)
    args = ["study", "timestep", scene_path, "--out", str(tmp_path / "ts"), "--max-tries", "2", "--duration", "0.6"]
    for setting in (f'bed.bed_file="{tiny_bed}"', "run.dt=0.006", "run.macro_step=0.006"):
        args += ["--set", setting]
    assert main(args) == 1
    text = capsys.readouterr().err
    assert "try 1/2" in text and "try 2/2" in text and "UNSTABLE" in text and "no stable step found in 2 tries" in text
    report = json.loads((tmp_path / "ts" / "study.json").read_text())
    assert report["largest_stable"] is None and len(report["tried"]) == 2
    assert report["units"]["scene_dt"] == report["units"]["tried.dt"] == "s"


def test_a_slip_study_is_tabulated_from_the_runs_it_holds(tmp_path):
    """A slip study stopped before its end (or run in parts): `slip_study_from_runs` tabulates the
    runs two folders hold, steady ones only, with the Student-t interval of their mean; a running
    run (no summary yet) and unsteady ones are counted but not averaged (include_sinking: the
    still-sinking and the still-rising one are); the output folder may not hold the runs it reads."""
    from scipy import stats

    from cosim.study import slip_study_from_runs
    from soil.errors import ArgumentError

    with open(write_tiny(tmp_path)) as f:
        text = f.read()

    def seeded(seed):  # a replica's scene: its order seed (part b run with --set run.order_seed=10)
        return text.replace("[run]\n", f"[run]\norder_seed = {seed}\n", 1)

    pulls = {("a", 0): -1.0e-4, ("a", 1): -3.0e-4, ("b", 0): -2.0e-4}
    for (part, k), pull in pulls.items():
        run = tmp_path / part / "slip_+0.200" / f"replica_{k:03d}"
        run.mkdir(parents=True)
        (run / "scene.toml").write_text(seeded(k + (10 if part == "b" else 0)))
        summary = {
            "summary_rule": SUMMARY_RULE,
            "steady_state": "steady",
            "drawbar_pull": pull,
            "slip": 0.2,
            "sinkage": 1e-3,
        }
        (run / "run.json").write_text(json.dumps({"status": "complete", "summary": summary}))
    unsteady = tmp_path / "b" / "slip_+0.200" / "replica_001"
    unsteady.mkdir()
    (unsteady / "scene.toml").write_text(seeded(11))
    summary = {"summary_rule": SUMMARY_RULE, "steady_state": "still sinking", "drawbar_pull": 5.0, "slip": 0.2}
    (unsteady / "run.json").write_text(json.dumps({"status": "unsteady", "summary": summary}))
    rising = tmp_path / "b" / "slip_+0.200" / "replica_002"  # its sinkage drifts upwards: averaged the same way
    rising.mkdir()
    (rising / "scene.toml").write_text(seeded(12))
    summary = {"summary_rule": SUMMARY_RULE, "steady_state": "still rising", "drawbar_pull": 7.0, "slip": 0.2}
    (rising / "run.json").write_text(json.dumps({"status": "unsteady", "summary": summary}))
    running = tmp_path / "b" / "slip_+0.400" / "replica_000"
    running.mkdir(parents=True)
    (running / "scene.toml").write_text(text)
    (running / "run.json").write_text(json.dumps({"status": "running"}))

    report = slip_study_from_runs([tmp_path / "a", tmp_path / "b"], str(tmp_path / "table"), plot=False)
    row = {r["slip_set"]: r for r in report["rows"]}
    assert row[0.2]["replicas"] == 5 and row[0.2]["steady"] == 3 and row[0.4]["steady"] == 0
    values = np.array(list(pulls.values()))
    assert row[0.2]["drawbar_pull_mean"] == pytest.approx(values.mean(), rel=1e-12)
    interval = stats.t.ppf(0.975, 2) * values.std(ddof=1) / np.sqrt(3)
    assert row[0.2]["drawbar_pull_ci95"] == pytest.approx(interval, rel=1e-12)
    assert json.loads((tmp_path / "table" / "study.json").read_text())["kind"] == "slip"
    # --include-sinking: the run whose traction is steady and sinkage drifts is averaged too
    sinking = slip_study_from_runs([tmp_path / "a", tmp_path / "b"], str(tmp_path / "t2"), include_sinking=True)
    row = {r["slip_set"]: r for r in sinking["rows"]}
    assert row[0.2]["steady"] == 3 and row[0.2]["averaged"] == 5
    assert row[0.2]["drawbar_pull_mean"] == pytest.approx((values.sum() + 5.0 + 7.0) / 5, rel=1e-12)
    with pytest.raises(ArgumentError, match="holds the runs"):
        slip_study_from_runs([tmp_path / "a"], str(tmp_path))
    # the CSV says over how many runs each mean is (steady 3, averaged 4), and counts carry their unit
    header, line = (tmp_path / "t2" / "study.csv").read_text().splitlines()[:2]
    assert header.startswith("slip_set [1],replicas [count],steady [count],averaged [count],"), header
    assert line.startswith("0.2,5,3,5,"), line
    # one slip point (0.4 has no steady run): no crossing, and none extrapolated
    assert sinking["zero_pull_slip"] is None and "does not cross zero" in sinking["zero_pull_slip_note"]


def _slip_row(slip: float, pulls: list[float]) -> dict:
    """A slip study's row at imposed `slip` whose replicas measured DP/W `pulls` [-] at that slip."""
    from cosim import metrics

    stats = {"metrics": {"dp_over_w": metrics.ensemble(pulls), "slip": metrics.ensemble([slip] * len(pulls))}}
    return {"slip_set": slip, "stats": stats}


def test_the_self_propelled_slip_is_interpolated_with_its_interval():
    """`cosim study slip` was said to find the slip where DP/W crosses zero, and did not. Rows at slips
    0.1, 0.2, 0.4 (given out of order) with DP/W -0.10, -0.03, +0.05: the zero lies at 0.2 + 0.2 x 0.03 /
    0.08 = 0.275. Its 95 % half-width (delta method, t with 2 degrees of freedom) matches the spread of
    the same interpolation over 20,000 draws of the two means from their standard errors; a curve
    that never crosses gives none (nothing extrapolated), and one replica no interval."""
    from scipy import stats

    from cosim.study import zero_pull_slip

    low, high = [-0.04, -0.03, -0.02], [0.04, 0.05, 0.06]
    rows = [_slip_row(0.4, high), _slip_row(0.1, [-0.11, -0.10, -0.09]), _slip_row(0.2, low)]
    crossing = zero_pull_slip(rows)
    assert crossing["slip"] == pytest.approx(0.275) and crossing["between"] == pytest.approx([0.2, 0.4])
    assert crossing["crossings"] == 1
    rng = np.random.default_rng(7)
    error = 0.01 / math.sqrt(3)  # each point's standard error of its mean
    d1, d2 = rng.normal(-0.03, error, 20000), rng.normal(0.05, error, 20000)
    spread = np.std(0.2 + 0.2 * d1 / (d1 - d2))
    assert crossing["ci95"] == pytest.approx(stats.t.ppf(0.975, 2) * spread, rel=0.03)
    assert zero_pull_slip([_slip_row(0.1, low), _slip_row(0.2, low)])["slip"] is None
    alone = zero_pull_slip([_slip_row(0.2, [-0.03]), _slip_row(0.4, [0.05])])
    assert alone["slip"] == pytest.approx(0.275) and math.isnan(alone["ci95"])


def test_the_self_propelled_slips_interval_pairs_the_replicas_of_one_bed():
    """Under --vary-bed replica k ran on bed k at every slip, so a bed's offset moves the mean DP/W at both
    slips the crossing is interpolated between; the interval treated the two means as independent. On
    synthetic studies of 10 beds (DP/W = 0.5 (slip - 0.2) + a bed's offset (std 0.03) + a run's scatter
    (0.01), at slips 0.1 and 0.4) the 95 % interval of the crossing now covers 0.2 in 93-97.5 % of 1000
    studies, where without the pairing it covered 90 % (measured: 0.959 against 0.904)."""
    from cosim import metrics
    from cosim.study import zero_pull_slip

    def row(slip, pulls, paired):
        stats = {"metrics": {"dp_over_w": metrics.ensemble(list(pulls)), "slip": metrics.ensemble([slip] * 10)}}
        pairs = {str(k): float(v) for k, v in enumerate(pulls)} if paired else {}
        return {"slip_set": slip, "stats": stats, "dp_over_w_by_replica": pairs}

    rng = np.random.default_rng(1)
    covered = {True: 0, False: 0}
    studies = 0
    for _ in range(1000):
        bed = rng.normal(0.0, 0.03, 10)
        low, high = -0.05 + bed + rng.normal(0.0, 0.01, 10), 0.1 + bed + rng.normal(0.0, 0.01, 10)
        crossings = {paired: zero_pull_slip([row(0.1, low, paired), row(0.4, high, paired)]) for paired in covered}
        if crossings[True]["slip"] is None:  # the curve's mean did not cross (2 of 1000)
            continue
        studies += 1
        for paired, crossing in crossings.items():
            covered[paired] += abs(crossing["slip"] - 0.2) <= crossing["ci95"]
    assert 0.93 <= covered[True] / studies <= 0.975, covered
    assert covered[False] / studies < 0.92, covered  # what the pairing corrects


def test_a_stop_asked_for_during_serial_replicas_stops_them_all(tmp_path, monkeypatch):
    """Ctrl-C or SIGTERM in a run of `--serial` replicas (the runner checkpoints and raises
    RunInterrupted) stops the study, as it stops one run: it used to mark that replica failed and run
    the others to their end."""
    from cosim import launch
    from cosim.study import Executor, run_task
    from helpers import TINY_SCENE

    started = []

    def stopped_run(plan, out_dir, **kwargs):
        started.append(out_dir)
        raise RunInterrupted("SIGTERM: stopped after a checkpoint", signal="SIGTERM")

    monkeypatch.setattr(launch, "run_plan", stopped_run)
    tasks = [{"scene_toml": TINY_SCENE, "out_dir": str(tmp_path / f"replica_{k}"), "label": str(k)} for k in range(3)]
    with pytest.raises(RunInterrupted), Executor("serial") as ex:
        ex.map(run_task, tasks)
    assert started == [str(tmp_path / "replica_0")]


def test_a_timestep_search_of_no_dem_step_or_of_endless_tries_is_refused_before_its_folder(tmp_path, capsys):
    """On the analytic terrain it settled a bed and then failed an assertion (exit 1); --duration 1e300
    ran without end. Both are bad input (exit 2), named before the study's folder is made."""
    from cosim.cli import main

    analytic = write_tiny(tmp_path, '\n[terrain]\nmodel = "analytic"\nstiffness = 500.0\n')
    out = tmp_path / "study"
    assert main(["study", "timestep", analytic, "--out", str(out)]) == 2
    assert "stable-step search is of the DEM step; this scene runs on analytic" in capsys.readouterr().err
    assert main(["study", "timestep", write_tiny(tmp_path), "--out", str(out), "--duration", "1e300"]) == 2
    assert "--duration" in capsys.readouterr().err
    # a try of one DEM step explodes at no step: it recommended 4 x the advisor's largest step, exit 0 (probe)
    assert main(["study", "timestep", write_tiny(tmp_path), "--out", str(out), "--duration", "1e-9"]) == 2
    assert "cannot show an instability; at least 100 steps: --duration >=" in capsys.readouterr().err
    # a search shrinking the step 49 times (the scene's own step exploding) would take 1.5^49 x its steps
    for tries in ("1000000000", "41", "35"):  # beyond MAX_TRIES; within it, its last try beyond MAX_PHASE_STEPS
        assert (
            main(
                ["study", "timestep", write_tiny(tmp_path), "--out", str(out), "--duration", "60", "--max-tries", tries]
            )
            == 2
        )
        assert f"--max-tries {tries}, --duration 60 s: at most 40 tries" in capsys.readouterr().err
    assert not out.exists()


def test_a_slip_study_from_the_same_runs_twice_is_refused(tmp_path):
    """`--from-runs A A` counted each run twice (its table's counts doubled)."""
    from cosim.study import slip_study_from_runs
    from soil.errors import ArgumentError

    runs = tmp_path / "runs"
    runs.mkdir()
    with pytest.raises(ArgumentError, match="given twice"):
        slip_study_from_runs([str(runs), str(runs) + "/"], str(tmp_path / "table"))
    assert not (tmp_path / "table").exists()


@pytest.mark.parametrize(
    "record, named",
    [
        ([1, 2], "a JSON object expected, got list"),
        ({"summary": "done"}, "summary must be an object"),
        ({"summary": {"sinkage": "8 mm"}}, "summary.sinkage must be a number or null"),
        ({"summary": {"steady_state": 1}}, "summary.steady_state must be a name"),
        ({"bed": "bed.h5"}, "bed must be an object with a path"),
    ],
)
def test_a_slip_run_record_of_the_wrong_shape_is_named(tmp_path, capsys, record, named):
    """--from-runs over a run.json that is JSON of another shape: exit 2 naming the file and the field,
    the table's folder not made (it was exit 1, a TypeError or AttributeError)."""
    from cosim.cli import main

    runs = tmp_path / "runs" / "slip_+0.200" / "replica_0"
    runs.mkdir(parents=True)
    (runs / "run.json").write_text(json.dumps(record))
    out = tmp_path / "table"
    assert main(["study", "slip", write_tiny(tmp_path), "--from-runs", str(tmp_path / "runs"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cosim: error:") and "run.json: not a slip run's record" in err and named in err, err
    assert not out.exists()


def test_overwrite_empties_only_a_folder_a_study_or_a_run_wrote(scene_path, tmp_path, capsys):
    """--overwrite on an ensemble (replicas, sweep, study, lab test) emptied the whole --out folder: the
    scene it was reading, a user's notes and data went with the old results. It now empties only a folder
    that a study marked or a single run's; a folder of other files is refused (exit 3), nothing removed."""
    import shutil

    from cosim.cli import main
    from cosim.folders import OutputExistsError
    from cosim.study import STUDY_MARK, prepare_study

    folder = tmp_path / "mine"
    folder.mkdir()
    shutil.copy(scene_path, folder / "scene_in.toml")
    (folder / "notes.txt").write_text("precious")
    args = ["run", str(folder / "scene_in.toml"), "--out", str(folder), "--replicas", "2", "--serial"]
    assert main([*args, "--overwrite", "--no-progress"]) == 3
    err = capsys.readouterr().err
    assert "holds files that no study marked as its own (notes.txt, scene_in.toml)" in err, err
    assert "nothing was removed" in err
    assert sorted(os.listdir(folder)) == ["notes.txt", "scene_in.toml"]
    # a folder of the user's scene alone is no run's (its scene.toml was taken for a run's output)
    lone = tmp_path / "lone"
    lone.mkdir()
    shutil.copy(scene_path, lone / "scene.toml")
    with pytest.raises(OutputExistsError, match="no study marked"):
        with prepare_study(str(lone), overwrite=True):
            pass
    assert os.listdir(lone) == ["scene.toml"]
    unmarked = tmp_path / "unmarked"  # a study written before the mark: refused, saying so
    (unmarked / "replica_000").mkdir(parents=True)
    (unmarked / "ensemble.json").write_text("{}")
    with pytest.raises(OutputExistsError, match="one written before 2026-12-06 has none"):
        with prepare_study(str(unmarked), overwrite=True):
            pass

    study = tmp_path / "study"  # a study's folder: emptied, its settled bed kept
    with prepare_study(str(study), overwrite=False):
        pass
    (study / "r000").mkdir()
    (study / "study.csv").write_text("old")
    (study / "bed.h5").write_text("bed")
    with prepare_study(str(study), overwrite=True):
        pass
    assert sorted(os.listdir(study)) == sorted([".lock", STUDY_MARK, "bed.h5"])

    run = tmp_path / "run"  # a single run's folder is replaced, as `cosim run --overwrite` replaces it
    run.mkdir()
    for name in ("results.h5", "run.json", "scene.toml", "bed_diverged.npz"):
        (run / name).write_text("old")
    with prepare_study(str(run), overwrite=True):
        pass
    assert sorted(os.listdir(run)) == sorted(
        [".lock", STUDY_MARK, "bed_diverged.npz"]
    )  # a bed's last good state is kept


def test_a_study_folder_in_use_is_refused_by_a_second_ensemble_or_lab_test(scene_path, tmp_path, capsys):
    """An ensemble's folder was not locked: a second `--replicas ... --overwrite` (or a lab test) on it while
    the first still ran emptied it under the first (its replicas' results gone, their locks too), and two
    lab tests on one folder left one's results under the other's scene.toml. A study, sweep, set of
    replicas or lab test now holds its folder's lock while it runs: a second one is refused (exit 3),
    nothing touched."""
    from cosim.cli import main
    from cosim.study import prepare_study

    study = tmp_path / "study"
    with prepare_study(str(study), overwrite=False):
        (study / "replica_000").mkdir()
        (study / "replica_000" / "results.h5").write_text("being written")
        for command in (
            ["run", scene_path, "--replicas", "2", "--serial", "--out", str(study), "--overwrite", "--no-progress"],
            [
                "lab",
                "plate",
                os.path.join(os.path.dirname(__file__), "..", "examples", "phobos_lab.toml"),
                "--serial",
                "--out",
                str(study),
                "--overwrite",
            ],
        ):
            assert main(command) == 3, command
            err = capsys.readouterr().err
            assert "is in use by another process" in err and str(study) in err, err
            assert (study / "replica_000" / "results.h5").read_text() == "being written"
    from cosim.folders import FolderInUseError, RunFolder

    with RunFolder(study / "replica_000").locked():  # a run another process started in a replica's folder
        with pytest.raises(FolderInUseError, match="replica_000"):
            with prepare_study(str(study), overwrite=True):
                pass
        assert (study / "replica_000" / "results.h5").read_text() == "being written"
    with prepare_study(str(study), overwrite=True):  # released at the end: a later study empties it
        assert not (study / "replica_000").exists()


# ------------------------------------------------------------------------------------
# the validity of the runs behind each row, point and ensemble

SCM_EXAMPLE = os.path.join(os.path.dirname(__file__), "..", "examples", "phobos_single_wheel_scm.toml")
FINE_SCM = ["bed.radius_mean=1.0e-3"]
"""The SCM main job on grains half as large (its sinkage is then over SCM's 3 grain diameters), driven
its 14 s (2.5 grouser passages over the window; 4 s were too short): at slip 0.3 a valid scene, at slip
0.8 over SCM's slip limit (scm_slip)."""


def _run_checks(folder) -> list[str] | None:
    """The checks a run failed, as its own run.json's summary findings say (None: it has no summary)."""
    record = json.loads((folder / "run.json").read_text())
    if "summary" not in record:
        return None
    return [f["check"] for f in record["summary"]["findings"] if not f["ok"]]


def _expected_validity(folders) -> str | None:
    """What a row over the runs in `folders` must say: 'valid', or each failed check (in the order the
    runs fail them) with how many of the runs that give a verdict failed it."""
    judged = [checks for checks in map(_run_checks, folders) if checks is not None]
    if not judged:
        return None
    counts: dict[str, int] = {}
    for checks in judged:
        for check in checks:
            counts[check] = counts.get(check, 0) + 1
    if not counts:
        return "valid"
    return "out of range: " + ", ".join(f"{c} ({k}/{len(judged)})" for c, k in counts.items())


def test_a_slip_studys_rows_carry_the_validity_of_their_runs(tmp_path, capsys, monkeypatch):
    """A user sizes a wheel from the DP/W-slip curve, and the study dropped what each run knew: whether
    its scene was a valid test. On SCM at slips 0.3 (valid) and 0.8 (over SCM's slip limit), each row
    carries its runs' verdict, as their run.json findings give it, in the printed table (a marker and a
    footnote naming the checks), study.csv (a `validity` column), study.json and the plot (a hollow
    marker with its legend entry)."""
    import csv

    import matplotlib.pyplot as plt

    from cosim.cli import main

    figures = []
    monkeypatch.setattr(plt, "close", figures.append)  # keep the plot's figure to read its legend
    out = tmp_path / "slip"
    sets = [item for key in FINE_SCM for item in ("--set", key)]
    args = ["study", "slip", SCM_EXAMPLE, "--slips", "0.3,0.8", "--replicas", "1", "--serial", *sets]
    assert main([*args, "--out", str(out), "--device", "cpu"]) == 0
    printed = capsys.readouterr().out
    assert "N; one run a slip)" in printed and "summation order" not in printed  # SCM sums in one order
    expected = {s: _expected_validity([out / f"slip_{s:+.3f}" / "replica_000"]) for s in (0.3, 0.8)}
    assert expected[0.3] == "valid" and "scm_slip (1/1)" in expected[0.8], expected  # the scene as meant
    report = json.loads((out / "study.json").read_text())
    assert {row["slip_set"]: row["validity"] for row in report["rows"]} == expected
    assert report["wheel"]["rim_radius_m"] == load_plan(SCM_EXAMPLE).wheel.rim_radius  # what a wheel fit checks
    with open(out / "study.csv", newline="") as f:
        table = list(csv.DictReader(f))
    assert {float(row["slip_set [1]"]): row["validity"] for row in table} == expected
    lines = printed.splitlines()
    assert "validity" in next(line for line in lines if "DP/W" in line and "slip" in line)
    row_03 = next(line for line in lines if line.strip().startswith("0.300"))
    row_08 = next(line for line in lines if line.strip().startswith("0.800"))
    assert row_03.rstrip().endswith("valid") and row_08.rstrip().endswith("out of range [1]"), printed
    assert f"  [1] {expected[0.8]}" in lines, printed
    axes = figures[-1].axes
    assert all("out of range (validity)" in [t.get_text() for t in ax.get_legend().get_texts()] for ax in axes)


def test_a_sweeps_points_carry_the_validity_of_their_runs(tmp_path, capsys):
    """`cosim sweep` printed `ok True, steady` for a point whose run was out of range: each point now
    gives its run's verdict (its run.json's) in the printed table and lines, study.csv and study.json."""
    import csv

    from cosim.cli import main

    out = tmp_path / "sweep"
    sets = [item for key in FINE_SCM for item in ("--set", key)]
    args = ["sweep", SCM_EXAMPLE, "--param", "testbed.slip=0.3,0.8", "--serial", "--out", str(out), *sets]
    assert main([*args, "--device", "cpu"]) == 0
    captured = capsys.readouterr()
    folders = {0.3: out / "000_slip=0.3", 0.8: out / "001_slip=0.8"}
    expected = {}
    for slip, folder in folders.items():
        checks = _run_checks(folder)
        expected[slip] = json.loads((folder / "run.json").read_text())["summary"]["validity"]
        assert expected[slip] == ("out of range: " + ", ".join(checks) if checks else "valid")
    assert expected[0.3] == "valid" and "scm_slip" in expected[0.8], expected
    report = json.loads((out / "study.json").read_text())
    assert {row["testbed.slip"]: row["validity"] for row in report["rows"]} == expected
    with open(out / "study.csv", newline="") as f:
        assert {float(r["testbed.slip [1]"]): r["validity"] for r in csv.DictReader(f)} == expected
    table = captured.out + captured.err  # the table is logged, the closing lines printed
    assert re.search(r"^testbed\.slip \[1\] +ok +status +validity +steady_state +slip \[1\]", table, re.M), table
    assert re.search(r"^0\.3 .* valid ", table, re.M) and re.search(
        rf"^0\.8 .* {re.escape(expected[0.8])} ", table, re.M
    )
    assert "  1 of 2 points out of range (each run.json says why):" in captured.out.splitlines()
    assert f"  ! testbed.slip=0.8: {expected[0.8]}" in captured.out.splitlines()
    assert "testbed.slip=0.3:" not in captured.out


def test_a_rows_validity_counts_its_runs_and_the_self_propelled_slip_names_an_out_of_range_row(tmp_path):
    """A row over replicas gives each failed check with how many of its runs failed it (a run without a
    summary gives none); the self-propelled slip interpolated from a row out of range says so, naming it."""
    from cosim.study import slip_study_from_runs

    with open(write_tiny(tmp_path)) as f:
        text = f.read()

    def finding(check, ok):
        return {"check": check, "ok": ok, "value": 1.0, "limit": 1.0, "message": check, "setting": "x"}

    runs = {  # slip, replica: DP/W, the checks it failed (None: still running, no summary)
        (0.2, 0): (-0.05, []),
        (0.2, 1): (-0.04, ["scm_sinkage_grains"]),
        (0.4, 0): (0.03, ["scm_slip", "scm_sinkage_grains"]),
        (0.4, 1): (0.05, ["scm_slip"]),
        (0.4, 2): (0.04, []),
        (0.4, 3): (0.0, None),
    }
    for (slip, k), (pull, failed) in runs.items():
        run = tmp_path / "runs" / f"slip_{slip:+.3f}" / f"replica_{k:03d}"
        run.mkdir(parents=True)
        (run / "scene.toml").write_text(text.replace("[run]\n", f"[run]\norder_seed = {k}\n", 1))
        record: dict = {"status": "running"}
        if failed is not None:
            checks = ["scm_slip", "scm_sinkage_grains", "scm_froude"]
            findings = [finding(c, c not in failed) for c in checks]
            summary = {
                "summary_rule": SUMMARY_RULE,
                "steady_state": "steady",
                "dp_over_w": pull,
                "slip": slip,
                "findings": findings,
            }
            summary["validity"] = "out of range: " + ", ".join(failed) if failed else "valid"
            record = {"status": "complete", "summary": summary}
        (run / "run.json").write_text(json.dumps(record))
    report = slip_study_from_runs([str(tmp_path / "runs")], str(tmp_path / "table"), plot=False)
    for row in report["rows"]:
        folders = sorted((tmp_path / "runs" / f"slip_{row['slip_set']:+.3f}").iterdir())
        assert row["validity"] == _expected_validity(folders)
    rows = {row["slip_set"]: row["validity"] for row in report["rows"]}
    assert rows[0.2] == "out of range: scm_sinkage_grains (1/2)"
    assert rows[0.4] == "out of range: scm_slip (2/3), scm_sinkage_grains (1/3)"
    assert report["zero_pull_slip"] is not None
    assert report["zero_pull_slip_validity"] == f"out of range: slip 0.2: {rows[0.2][14:]}; slip 0.4: {rows[0.4][14:]}"
    assert "a row it is interpolated from is out of range" in report["zero_pull_slip_note"]
    assert f"! the self-propelled slip is {report['zero_pull_slip_validity']}" in report["text"]


def test_the_self_propelled_slip_between_valid_rows_is_valid():
    """Interpolated between two valid rows the crossing is valid; one row out of range is named alone."""
    from cosim.study import zero_pull_slip

    low, high = _slip_row(0.2, [-0.03]), _slip_row(0.4, [0.05])
    assert zero_pull_slip([{**low, "validity": "valid"}, {**high, "validity": "valid"}])["validity"] == "valid"
    bad = {**high, "validity": "out of range: scm_slip (1/1)"}
    assert zero_pull_slip([{**low, "validity": "valid"}, bad])["validity"] == "out of range: slip 0.4: scm_slip (1/1)"
    assert zero_pull_slip([low, high])["validity"] is None  # rows that give no verdict


def test_a_check_a_run_could_not_judge_is_named_in_its_row_and_the_self_propelled_slip(tmp_path):
    """A run that measured nothing to judge a check on (a wheel that never landed: summary `not_judged`,
    its verdict 'valid; not judged: ...') read plain 'valid' in a study's rows, table and crossing: the
    study claimed a check its run never made. Each row names such checks with how many runs could not
    judge them, beside its failed ones."""
    import csv

    from cosim.study import ensemble_validity, run_validity, slip_study_from_runs, zero_pull_slip

    with open(write_tiny(tmp_path)) as f:
        text = f.read()

    def record(pull, slip, failed, unjudged):
        findings = [
            {"check": c, "ok": c not in failed, "value": 1.0, "limit": 1.0, "message": c, "setting": "x"}
            for c in ("scm_slip", "scm_froude")
        ]
        summary = {
            "summary_rule": SUMMARY_RULE,
            "steady_state": "steady",
            "dp_over_w": pull,
            "slip": slip,
            "findings": findings,
        }
        if unjudged:
            summary["not_judged"] = unjudged
        return {"status": "complete", "summary": summary}

    runs = {  # slip, replica: DP/W, failed checks, checks not judged
        (0.2, 0): (-0.05, [], ["scm_sinkage_grains"]),
        (0.2, 1): (-0.04, [], []),
        (0.4, 0): (0.03, ["scm_slip"], ["scm_sinkage_grains", "scm_grousers"]),
        (0.4, 1): (0.05, [], []),
    }
    for (slip, k), (pull, failed, unjudged) in runs.items():
        run = tmp_path / "runs" / f"slip_{slip:+.3f}" / f"replica_{k:03d}"
        run.mkdir(parents=True)
        (run / "scene.toml").write_text(text.replace("[run]\n", f"[run]\norder_seed = {k}\n", 1))
        (run / "run.json").write_text(json.dumps(record(pull, slip, failed, unjudged)))
    report = slip_study_from_runs([str(tmp_path / "runs")], str(tmp_path / "table"), plot=False)
    rows = {row["slip_set"]: row["validity"] for row in report["rows"]}
    assert rows[0.2] == "valid; not judged: scm_sinkage_grains (1/2)"
    assert rows[0.4] == "out of range: scm_slip (1/2); not judged: scm_sinkage_grains (1/2), scm_grousers (1/2)"
    assert report["zero_pull_slip_validity"] == (
        "out of range: slip 0.4: scm_slip (1/2); not judged: slip 0.2: scm_sinkage_grains (1/2); "
        "slip 0.4: scm_sinkage_grains (1/2), scm_grousers (1/2)"
    )
    assert "valid [1]" in report["text"] and f"[1] {rows[0.2]}" in report["text"]
    with open(tmp_path / "table" / "study.csv", newline="") as f:
        assert {r["validity"] for r in csv.DictReader(f)} == set(rows.values())
    # one run alone, and a crossing between rows that failed nothing but could not judge a check
    one = {"ok": True, "summary": record(-0.05, 0.2, [], ["scm_sinkage_grains"])["summary"]}
    assert run_validity(one) == "valid; not judged: scm_sinkage_grains"
    assert ensemble_validity([one, {**one, "summary": {**one["summary"], "not_judged": []}}]) == rows[0.2]
    low, high = _slip_row(0.2, [-0.03]), _slip_row(0.4, [0.05])
    crossing = zero_pull_slip([{**low, "validity": rows[0.2]}, {**high, "validity": "valid"}])
    assert crossing["validity"] == "valid; not judged: slip 0.2: scm_sinkage_grains (1/2)"
    # both rows failed a check, one could not judge another: each failure named, then what was not judged
    failed_low = {**low, "validity": "out of range: scm_froude (1/1); not judged: scm_grousers (1/1)"}
    crossing = zero_pull_slip([failed_low, {**high, "validity": "out of range: scm_slip (1/1)"}])
    assert crossing["validity"] == (
        "out of range: slip 0.2: scm_froude (1/1); slip 0.4: scm_slip (1/1); not judged: slip 0.2: scm_grousers (1/1)"
    )


def test_a_slip_studys_json_gives_every_numbers_unit_and_its_table_the_failed_runs(tmp_path):
    """study.json's rows held 32 numbers without a unit (each metric's min and max, the landing's, the
    travel's, the wall time's), and a slip whose runs all failed read as one whose runs were unsteady
    (no `failed` column); tabulated from run folders, a diverged or interrupted run's summary (of part of
    its drive) was averaged as a result. Every number of a row has its unit, the failed runs are
    counted, and only finished runs are averaged."""
    import csv

    from cosim.study import slip_study_from_runs

    with open(write_tiny(tmp_path)) as f:
        text = f.read()
    summary = {
        "summary_rule": SUMMARY_RULE,
        "steady_state": "steady",
        "dp_over_w": -0.05,
        "slip": 0.2,
        "sinkage": 0.004,
        "wall_time": 3.0,
        "travel": 0.01,
        "landing_sinkage": 0.003,
        "forward_speed": 0.001,
        "findings": [],
    }
    for slip, k, record in (
        (0.2, 0, {"status": "complete", "summary": summary}),
        (0.2, 1, {"status": "complete", "summary": {**summary, "dp_over_w": -0.04}}),
        # a diverged run's and an interrupted one's summaries are of part of a drive: no result; the first failed
        (0.4, 0, {"status": "diverged", "summary": {**summary, "slip": 0.4}}),
        (0.4, 1, {"status": "interrupted", "summary": {**summary, "slip": 0.4}}),
    ):
        run = tmp_path / "runs" / f"slip_{slip:+.3f}" / f"replica_{k:03d}"
        run.mkdir(parents=True)
        (run / "scene.toml").write_text(text.replace("[run]\n", f"[run]\norder_seed = {k}\n", 1))
        (run / "run.json").write_text(json.dumps(record))
    report = slip_study_from_runs([str(tmp_path / "runs")], str(tmp_path / "table"), plot=False)
    numbers = {key for row in report["rows"] for key, value in row.items() if isinstance(value, (int, float))}
    assert {"sinkage_min", "travel_max", "landing_sinkage_mean", "wall_time_std"} <= numbers
    assert numbers <= set(report["units"]), sorted(numbers - set(report["units"]))
    # and what the rows and runs nest (a probe of the files found them without): each row's stats by
    # metric, each run's wall time and numeric scene keys, the wheel's geometry
    units, numeric = report["units"], (lambda v: isinstance(v, (int, float)) and not isinstance(v, bool))
    nested = {m for row in report["rows"] for m, v in row["stats"]["metrics"].items() if any(map(numeric, v.values()))}
    assert {"sinkage", "wall_time"} <= nested <= set(units["stats.metrics"]), sorted(
        nested - set(units["stats.metrics"])
    )
    assert units["stats.metrics"]["sinkage"] == "m" and units["runs.wall_time"] == "s"
    keys = {k for run in report["runs"] for k, v in (run.get("overrides") or {}).items() if numeric(v)}
    assert keys <= set(units["runs.overrides"]) and units["runs.overrides"].get("testbed.slip", "1") == "1"
    assert {k for k, v in report["wheel"].items() if numeric(v)} <= set(units["wheel"])
    assert [row["failed"] for row in report["rows"]] == [0, 1] and report["units"]["failed"] == "count"
    assert [row["steady"] for row in report["rows"]] == [2, 0]  # the part-drive summaries were averaged
    with open(tmp_path / "table" / "study.csv", newline="") as f:
        assert [r["failed [count]"] for r in csv.DictReader(f)] == ["0", "1"]
    assert "0/2   (1 failed)" in report["text"]


def test_a_study_exits_1_when_a_run_failed_and_6_when_one_was_not_steady(tmp_path, monkeypatch, capsys):
    """A sweep said 0 with one of its points unsteady (6 only when none was steady) and a precision study
    said 0 with no steady replica at all; replicas and a slip study said 6 for a failed run. Each now says
    1 when a run failed (no result), else 6 when a run finished unsteady (its table says which), else 0."""
    from cosim import study
    from cosim.cli import main

    steady = {"ok": True, "status": "complete", "summary": {"steady_state": "steady"}}
    short = {"ok": True, "status": "unsteady", "summary": {"steady_state": "too short"}}
    failed = {"ok": False, "status": "failed", "error": "RunDiverged"}
    scene = write_tiny(tmp_path)
    for runs, expected in (([steady, steady], 0), ([steady, short], 6), ([short, failed], 1)):
        rows = [{"ok": r["ok"], "status": r["status"], "validity": None} for r in runs]
        monkeypatch.setattr(
            study, "sweep", lambda *a, runs=runs, rows=rows, **k: {"rows": rows, "runs": runs, "grid": {}}
        )
        assert main(["sweep", scene, "--param", "testbed.omega=0.5,0.7", "--out", str(tmp_path / "s")]) == expected
        monkeypatch.setattr(study, "precision_study", lambda *a, runs=runs, **k: {"replicas": runs})
        assert main(["study", "precision", scene, "--out", str(tmp_path / "p")]) == expected
        monkeypatch.setattr(study, "slip_study", lambda *a, runs=runs, **k: {"runs": runs, "text": ""})
        assert main(["study", "slip", scene, "--slips", "0.1,0.2", "--out", str(tmp_path / "l")]) == expected
        monkeypatch.setattr(study, "replica_run", lambda *a, runs=runs, **k: {"results": runs, "text": ""})
        assert main(["run", scene, "--replicas", "2", "--out", str(tmp_path / "r")]) == expected
    capsys.readouterr()
    # a sweep's point that could not judge a check is listed, as one out of range is
    rows = [
        {"ok": True, "status": "complete", "validity": "valid; not judged: scm_grousers", "testbed.omega": 0.5},
        {"ok": True, "status": "complete", "validity": "out of range: froude", "testbed.omega": 0.7},
    ]
    grid = {"testbed.omega": [0.5, 0.7]}
    monkeypatch.setattr(study, "sweep", lambda *a, **k: {"rows": rows, "runs": [steady, steady], "grid": grid})
    assert main(["sweep", scene, "--param", "testbed.omega=0.5,0.7", "--out", str(tmp_path / "s")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "  1 of 2 points out of range (each run.json says why):" in lines
    assert "  ! testbed.omega=0.7: out of range: froude" in lines
    assert "  1 of 2 points not judged on every check (each run.json says why):" in lines
    assert "  - testbed.omega=0.5: valid; not judged: scm_grousers" in lines


def test_replicas_and_a_precision_study_on_a_terrain_without_checks_say_not_checked(tmp_path, capsys):
    """On the analytic terrain (no validity checks: each run.json says "not checked") `cosim run --replicas 2`
    writes its replicas' verdict to ensemble.json, ensemble.csv and its printed table, and a precision study
    to its rows, study.csv and study.json: what the runs' run.json say, never "valid"."""
    import csv

    from cosim.advice import NOT_CHECKED
    from cosim.cli import main
    from cosim.study import precision_study

    scene = write_tiny(tmp_path, '\n[terrain]\nmodel = "analytic"\nstiffness = 500.0\n')
    out = tmp_path / "replicas"
    assert main(["run", scene, "--replicas", "2", "--serial", "--out", str(out)]) in (0, 4, 6)
    for replica in ("replica_000", "replica_001"):
        assert json.loads((out / replica / "run.json").read_text())["summary"]["validity"] == NOT_CHECKED
    expected = NOT_CHECKED
    ensemble = json.loads((out / "ensemble.json").read_text())
    assert ensemble["validity"] == ensemble["stats"]["validity"] == expected
    with open(out / "ensemble.csv", newline="") as f:
        assert {r["validity"] for r in csv.DictReader(f)} == {expected}
    assert f"  validity: {NOT_CHECKED}" in capsys.readouterr().out.splitlines()
    study = precision_study(
        load_plan(scene), str(tmp_path / "precision"), replicas=1, precisions=("single",), executor="serial", plot=False
    )
    assert study["rows"][0]["validity"] == NOT_CHECKED
    assert json.loads((tmp_path / "precision" / "study.json").read_text())["rows"][0]["validity"] == NOT_CHECKED
    with open(tmp_path / "precision" / "study.csv", newline="") as f:
        assert next(csv.DictReader(f))["validity"] == NOT_CHECKED


def test_a_table_from_runs_reads_every_run_first_and_counts_each_replica_once(tmp_path, tiny_bed, capsys):
    """`study slip --from-runs` (probe of 2026-12-07): an --out inside a folder it read was emptied with
    --overwrite (a replica's results gone); a run it could not read was found after --overwrite had emptied
    the old table; a copied folder (the same run_id) or a part run again (the same slip, order seed and bed)
    was counted again, the interval narrowed as if by new replicas (7 x in the probe); runs of another scene
    (testbed.mass) were averaged into one row; a partial summary of an interrupted run made the exit 0; and
    two parts on copies of one bed were labelled 'a bed each'. Now every run is read and judged first."""
    import shutil

    from cosim.cli import main
    from cosim.study import slip_study_from_runs
    from soil.errors import ArgumentError

    scene = write_tiny(tmp_path)
    text = Path(scene).read_text()
    copy = tmp_path / "bed_copy.h5"  # a part settles its own copy of the same bed (the same key)
    shutil.copy(tiny_bed, copy)

    def part(name, seeds, bed=tiny_bed, extra="", status="complete"):
        for k, seed in enumerate(seeds):
            run = tmp_path / name / "slip_+0.200" / f"replica_{k:03d}"
            run.mkdir(parents=True)
            # as the study writes it: its overrides (slip mode, slip, order seed) in the runs' scene.toml
            ran = text.replace("[run]\n", f"[run]\norder_seed = {seed}\n", 1).replace(
                "[testbed]\n", '[testbed]\nmode = "slip"\nslip = 0.2\n', 1
            )
            (run / "scene.toml").write_text(ran + extra)
            summary = {
                "summary_rule": SUMMARY_RULE,
                "steady_state": "steady",
                "dp_over_w": -0.05 + 0.01 * seed,
                "slip": 0.2,
            }
            record = {"status": status, "run_id": f"{name}{k}", "bed": {"path": str(bed)}, "summary": summary}
            (run / "run.json").write_text(json.dumps(record))

    part("a", [0, 1])
    part("b", [2, 3], bed=copy)
    table = slip_study_from_runs([str(tmp_path / "a"), str(tmp_path / "b")], str(tmp_path / "t"), plot=False)
    assert table["rows"][0]["averaged"] == 4 and "a bed each" not in table["text"], table["text"]
    before = {p: p.read_bytes() for p in (tmp_path / "t").rglob("*") if p.is_file()}

    def refused(folders, words, out="t", **options):
        with pytest.raises(ArgumentError, match=words):
            slip_study_from_runs([str(tmp_path / f) for f in folders], str(tmp_path / out), overwrite=True, **options)
        # nothing touched: the old table whole, every run's files there
        assert {p: p.read_bytes() for p in (tmp_path / "t").rglob("*") if p.is_file()} == before
        assert (tmp_path / "a" / "slip_+0.200" / "replica_000" / "run.json").is_file()

    refused(["a"], "lies inside", out="a/slip_+0.200/replica_000")
    shutil.copytree(tmp_path / "a", tmp_path / "a_copy")
    refused(["a", "a_copy"], "is a copy of")
    part("again", [1])  # replica 1 of part a run again (another run_id): the same computation
    refused(["a", "again"], r"repeats .*order_seed 1, the same bed")
    part("heavy", [5], extra="")
    heavy = tmp_path / "heavy" / "slip_+0.200" / "replica_000" / "scene.toml"
    heavy.write_text(heavy.read_text().replace("mass = 0.3\n", "mass = 0.36\n", 1))
    refused(["a", "heavy"], r"ran another scene .*testbed.mass")
    from cosim.scene import scene_from_text

    other = scene_from_text(text.replace("mass = 0.3\n", "mass = 0.36\n", 1))
    refused(["a"], r"not of the scene given \(testbed.mass", scene=other)
    (tmp_path / "b" / "slip_+0.200" / "replica_001" / "scene.toml").write_text("this is = = not toml")
    refused(["a", "b"], r"replica_001: not a slip run's folder")

    part("stopped", [7], status="interrupted")  # its summary of part of the drive says 'steady'
    out = tmp_path / "t2"  # the scene given: the study's, a free carriage (its runs' slip mode is the study's)
    assert (
        main(["study", "slip", scene, "--from-runs", str(tmp_path / "a"), str(tmp_path / "stopped"), "--out", str(out)])
        == 6
    )
    printed = capsys.readouterr().out
    assert "0.200   2/3" in printed
    assert "; mean +- its 95 % interval over the averaged runs)" in printed.splitlines()[0]  # what its +- is


def test_a_table_from_runs_refuses_runs_that_drove_two_meshes_of_one_file(tmp_path):
    """Two parts of a slip study on a mesh wheel whose file was replaced between them (the cylinder, then
    1.1 x it) name the same path, whose content now is the second's: they were averaged as one wheel. Each
    run's results.h5 keeps the mesh it drove: runs of two meshes are refused, and so is a scene given whose
    mesh is not the runs'."""
    import h5py

    from cosim.plan import load_plan
    from cosim.study import slip_study_from_runs
    from cosim.system import wheel_display_mesh
    from soil import GrouserWheel, MeshWheel
    from soil.errors import ArgumentError

    wheel = MeshWheel(*GrouserWheel(radius=0.025, width=0.02).to_mesh(arc_segments=72))
    scene = write_tiny(tmp_path)
    mesh = ['wheel={type = "mesh", file = "wheel.obj"}', "testbed.slip=0.2"]

    def part(name, scale, seed):
        MeshWheel(wheel.vertices * scale, wheel.triangles).save(tmp_path / "wheel.obj")
        plan = load_plan(scene, mesh + [f"run.order_seed={seed}"])
        run = tmp_path / name / "slip_+0.200" / "replica_000"
        run.mkdir(parents=True)
        (run / "scene.toml").write_text(plan.scene.to_toml())
        summary = {"summary_rule": SUMMARY_RULE, "steady_state": "steady", "dp_over_w": 0.1 + 0.01 * seed, "slip": 0.2}
        (run / "run.json").write_text(json.dumps({"status": "complete", "summary": summary}))
        with h5py.File(run / "results.h5", "w") as f:  # what a run keeps of its wheel
            for key, array in zip(("vertices", "triangles", "wheel"), wheel_display_mesh(plan)):
                f[f"wheels/mesh/{key}"] = array

    part("a", 1.0, 0)
    part("b", 1.0, 1)
    part("c", 1.1, 2)  # the file replaced: wheel.obj now holds the larger wheel
    with pytest.raises(ArgumentError, match=r"drove another wheel mesh than"):
        slip_study_from_runs([str(tmp_path / "a"), str(tmp_path / "c")], str(tmp_path / "t1"), plot=False)
    given = load_plan(scene, mesh).scene  # the file as it is now: c's wheel
    with pytest.raises(ArgumentError, match=r"drove another wheel mesh than the scene given names now"):
        slip_study_from_runs([str(tmp_path / "a"), str(tmp_path / "b")], str(tmp_path / "t2"), plot=False, scene=given)
    table = slip_study_from_runs([str(tmp_path / "a"), str(tmp_path / "b")], str(tmp_path / "t3"), plot=False)
    assert table["rows"][0]["averaged"] == 2


def test_a_table_from_runs_tells_input_files_by_their_content_not_their_path(tmp_path):
    """Runs whose scenes name their files by path (an SCM calibration here): parts on two calibrations
    were averaged into one row once paths were no longer compared; a part whose calibration lies
    elsewhere with the same bytes (a copy: another machine's folders) is the same scene."""
    import shutil
    from pathlib import Path

    from cosim.plan import load_plan
    from cosim.study import slip_study_from_runs
    from soil.errors import ArgumentError

    scm = Path(__file__).resolve().parent.parent / "examples" / "phobos_single_wheel_scm.toml"
    beds = scm.parent / "terrain" / "phobos_regolith_scm_beds.toml"
    copy = tmp_path / "elsewhere" / "calibration.toml"
    copy.parent.mkdir()
    shutil.copy(beds, copy)

    def part(name, calibration, seed):
        plan = load_plan(scm, [f'terrain.calibration="{calibration}"', f"run.order_seed={seed}", "testbed.slip=0.2"])
        run = tmp_path / name / "slip_+0.200" / "replica_000"
        run.mkdir(parents=True)
        (run / "scene.toml").write_text(plan.scene.to_toml())
        summary = {"summary_rule": SUMMARY_RULE, "steady_state": "steady", "dp_over_w": 0.1 + 0.01 * seed, "slip": 0.2}
        (run / "run.json").write_text(json.dumps({"status": "complete", "summary": summary}))

    part("a", beds, 0)
    part("copied", copy, 1)
    part("other", beds.parent / "phobos_regolith_scm_wheel.toml", 2)
    table = slip_study_from_runs([str(tmp_path / "a"), str(tmp_path / "copied")], str(tmp_path / "t"), plot=False)
    assert table["rows"][0]["averaged"] == 2
    with pytest.raises(ArgumentError, match=r"ran another scene .*terrain\.calibration"):
        slip_study_from_runs([str(tmp_path / "a"), str(tmp_path / "other")], str(tmp_path / "t2"), plot=False)


def test_a_wall_time_is_never_called_deterministic(tmp_path):
    """ensemble.json said of the replicas' wall time 'deterministic' True or False by the scatter of a
    clock's reading (the probe of the files found both in two sets): it is None, as the table leaves it."""
    from cosim.study import ensemble_table

    plan = load_plan(write_tiny(tmp_path))
    summary = {"summary_rule": SUMMARY_RULE, "steady_state": "steady", "sinkage": 0.004, "wall_time": 3.0}
    table = ensemble_table(
        [{"ok": True, "summary": summary}, {"ok": True, "summary": {**summary, "wall_time": 3.0}}], plan
    )
    assert table["metrics"]["wall_time"]["n"] == 2 and table["metrics"]["wall_time"]["deterministic"] is None
    assert table["metrics"]["sinkage"]["deterministic"] is True  # a metric of the physics still is judged


def test_a_summary_of_an_older_window_rule_is_made_again_by_resume_and_refused_by_a_table(
    tmp_path, tiny_run, tiny_bed, caplog
):
    """A run summarized before the window rule of 2026-12-07 (metrics.SUMMARY_RULE 2: the window starts once the
    sinkage has settled too) holds means of another window. `cosim resume` of the finished run used to say
    'already complete' and keep them; a slip table from its run.json averaged them with new runs' and a wheel
    fit fitted to them. Now resume makes the summary again from its results and final checkpoint, a table
    refuses a stale run naming the command, and a set's replica whose checkpoint is gone is failed, not kept."""
    import logging
    import shutil

    from cosim import metrics
    from cosim.folders import read_json
    from cosim.output import read_series, stored_summary
    from cosim.study import _finish_replica, slip_study_from_runs
    from soil.errors import ArgumentError

    run = tmp_path / "runs" / "slip_+0.200" / "replica_000"
    shutil.copytree(tiny_run, run)
    rows = len(read_series(str(run / "results.h5"))["time"])
    fresh = read_json(str(run / "run.json"))
    assert fresh["summary"]["summary_rule"] == metrics.SUMMARY_RULE
    old = {**fresh, "summary": {k: v for k, v in fresh["summary"].items() if k != "summary_rule"}}
    old["summary"]["sinkage"] = 1.0  # an older window's mean, as far as this test can tell
    (run / "run.json").write_text(json.dumps(old))
    with pytest.raises(ArgumentError, match=r"replica_000: its summary was made under an older steady-window rule"):
        slip_study_from_runs([str(tmp_path / "runs")], str(tmp_path / "table"))
    assert not (tmp_path / "table").exists()
    with caplog.at_level(logging.WARNING, logger="cosim.launch"):
        done = resume(str(run))
    assert "older steady-window rule" in caplog.text and "summarizing its results again" in caplog.text
    again = read_json(str(run / "run.json"))["summary"]
    assert again["summary_rule"] == metrics.SUMMARY_RULE and done.summary["summary_rule"] == metrics.SUMMARY_RULE
    # made again as the run made it (but for its wall time, and its throughput: no steps driven now)
    ignored = ("wall_time", "particle_steps_per_second")

    def kept(summary):
        units = {k: v for k, v in summary["units"].items() if k not in ignored}
        return {**{k: v for k, v in summary.items() if k not in ignored}, "units": units}

    assert kept(again) == kept(fresh["summary"])
    written = read_series(str(run / "results.h5"))
    assert len(written["time"]) == rows  # its results kept whole, not driven again
    assert stored_summary(written["attrs"])["summary_rule"] == metrics.SUMMARY_RULE  # results.h5's copy too
    # a replica of a set whose checkpoint is gone cannot be summarized again: failed, named, not averaged
    (run / "run.json").write_text(json.dumps(old))
    (run / "checkpoint.npz").unlink()
    task = {"label": "replica 0", "out_dir": str(run), "overrides": {}, "scene_toml": (run / "scene.toml").read_text()}
    result = _finish_replica(task)
    assert not result["ok"] and "older steady-window rule" in result["error"] and "resume the set" in result["error"]
    with pytest.raises(ArgumentError, match=r"older steady-window rule.*checkpoint is gone.*--overwrite"):
        resume(str(run))  # not 'nothing is left to resume': it says how
