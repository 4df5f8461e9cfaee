"""Replicas batched as worlds of one simulation (cosim.batch): each replica's results are bit for bit those
of the same replica run alone, a stop signal or a dead run's process loses nothing of any run, and the
batch refuses what it cannot run."""

import json
import os
import shutil
import signal
import threading
import time

import numpy as np
import pytest

from cosim.batch import batch_problem, run_batched
from cosim.beds import check_memory
from cosim.launch import final_state, resume, run_plan
from cosim.output import read_series
from cosim.plan import load_plan
from cosim.scene import SceneError
from cosim.study import replica_run, slip_study
from helpers import assert_checkpoint_units, write_tiny
from soil.bed import read_bed, read_bed_header
from soil.memory import SoilTooLargeError

REPLICAS = 3
SAME_EVERYWHERE = ("wall_time", "session_wall_time", "particle_steps_per_second", "real_time_factor")


@pytest.mark.parametrize("step_control", ["fixed", "pid"])
def test_batched_replicas_equal_their_runs_alone(tmp_path, tiny_bed, step_control):
    """At fixed steps and under the PID step control (each world its own controller: its substeps,
    series dem_steps, those of its run alone)."""
    plan = load_plan(write_tiny(tmp_path), [f'bed.bed_file="{tiny_bed}"', f'run.step_control="{step_control}"'])
    replicas = REPLICAS if step_control == "fixed" else 2
    alone = replica_run(plan, str(tmp_path / "alone"), replicas, executor="serial", batched=False)
    together = replica_run(plan, str(tmp_path / "together"), replicas, batched=True)
    assert together["batched"] and not alone["batched"]
    for a, b in zip(alone["results"], together["results"]):
        assert a["ok"] and b["ok"], (a.get("error"), b.get("error"))
        series_a, series_b = read_series(f"{a['out_dir']}/results.h5"), read_series(f"{b['out_dir']}/results.h5")
        assert len(series_a["time"]) > 20
        if step_control == "pid":  # the controller chose: substeps of varying count per macro step
            assert len(set(series_a["soil_dem_steps"].tolist())) > 1
        for name, values in series_a.items():
            if isinstance(values, np.ndarray) and name not in SAME_EVERYWHERE:
                assert np.array_equal(values, series_b[name], equal_nan=True), f"{b['out_dir']}: {name} differs"
        for name, value in a["summary"].items():
            if isinstance(value, float) and "wall" not in name and "per_second" not in name:
                assert value == b["summary"][name] or (np.isnan(value) and np.isnan(b["summary"][name])), name
    # the replicas are replicas: their summation orders make them differ
    drawbar = [read_series(f"{r['out_dir']}/results.h5")["drawbar_pull"].tobytes() for r in together["results"]]
    assert len(set(drawbar)) == replicas


def test_a_batched_slip_study_gives_the_study_run_one_by_one(tmp_path, tiny_bed):
    """Worlds of one batch may differ in their rig: two imposed slips in one simulation."""
    plan = load_plan(write_tiny(tmp_path), [f'bed.bed_file="{tiny_bed}"'])
    alone = slip_study(plan, str(tmp_path / "alone"), [0.1, 0.5], executor="serial", batched=False, plot=False)
    together = slip_study(plan, str(tmp_path / "together"), [0.1, 0.5], batched=True, plot=False)
    for a, b in zip(alone["runs"], together["runs"]):
        assert a["ok"] and b["ok"] and a["label"] == b["label"], (a.get("error"), b.get("error"))
        forces = [read_series(f"{r['out_dir']}/results.h5")["force"] for r in (a, b)]
        assert np.array_equal(*forces), b["label"]
    assert together["runs"][0]["summary"]["slip"] != together["runs"][1]["summary"]["slip"]


def test_replicas_over_beds_pair_the_slips_on_a_bed_each_in_one_simulation(tmp_path):
    """--vary-bed: replica k settles its own bed (bed.seed + k) and runs every slip on it; batched, every
    slip on every bed is a world of one simulation, each world on its own bed, bit for bit its run alone."""
    plan = load_plan(write_tiny(tmp_path), ["bed.seed=3"])  # beds the wheel lands on quickly: a short test
    study = slip_study(plan, str(tmp_path / "study"), [0.1, 0.5], replicas=2, batched=True, plot=False, vary="bed")
    beds = study["bed_files"]
    assert study["vary"] == "bed" and len(set(beds)) == 2
    headers = [read_bed_header(path) for path in beds]
    assert [h["spec"]["seed"] for h in headers] == [3, 4]
    assert headers[0]["particle_count"] == headers[1]["particle_count"]  # one geometry, two fills
    assert not np.array_equal(*(np.sort(read_bed(path).radius) for path in beds))  # other fills: other grains
    for run in study["runs"]:
        assert run["ok"], run.get("error")
        k = int(run["label"].rsplit(" ", 1)[1])
        with open(f"{run['out_dir']}/run.json") as f:
            assert json.load(f)["bed"]["path"] == beds[k]  # replica k on bed k at every slip
        assert run["batch"]["worlds"] == 4  # one simulation: 2 slips x 2 beds
    # a world is the scene with that bed's seed and file, its replica's order, its slip, run alone: on
    # either bed (the worlds' grains differ, their largest grain too, and so the batch's neighbour cells)
    both = study["runs"][1:3]  # slip 0.1 on bed 4, slip 0.5 on bed 3
    assert {run["overrides"]["bed.seed"] for run in both} == {3, 4}
    for run in both:
        alone = str(tmp_path / f"alone_{run['label'].replace(' ', '_')}")
        run_plan(load_plan(write_tiny(tmp_path), [f"{k}={json.dumps(v)}" for k, v in run["overrides"].items()]), alone)
        series = [read_series(f"{folder}/results.h5") for folder in (run["out_dir"], alone)]
        for name in ("force", "torque", "sinkage"):
            assert np.array_equal(series[0][name], series[1][name]), (run["label"], name)


def test_replicas_over_beds_too_large_for_one_simulation_run_as_one_per_bed(tmp_path, tiny_bed, monkeypatch):
    """Where the worlds of every bed do not fit the device together, each bed's worlds are a simulation."""
    import cosim.batch
    import cosim.beds
    from cosim.study import _run_tasks
    from soil.memory import SoilTooLargeError

    def fits(plan, worlds=1):
        if worlds > 2:
            raise SoilTooLargeError(f"{worlds} worlds do not fit")

    batches = []
    monkeypatch.setattr(cosim.beds, "check_memory", fits)
    monkeypatch.setattr(
        cosim.batch,
        "run_batched",
        lambda plans, out_dirs, overwrite=False: batches.append(out_dirs) or [{"ok": True} for _ in plans],
    )
    text = load_plan(write_tiny(tmp_path)).scene.to_toml()
    tasks = [
        {"scene_toml": text, "out_dir": f"{bed}_{slip}", "overrides": {"bed.bed_file": f"{tiny_bed}" if bed else None}}
        for slip in (0.1, 0.5)
        for bed in (0, 1)
    ]
    for task in tasks:  # two beds: the tiny bed, and none (each task's own)
        task["overrides"] = {k: v for k, v in task["overrides"].items() if v}
    results = _run_tasks(None, tasks, batched=True)
    assert sorted(batches) == [["0_0.1", "0_0.5"], ["1_0.1", "1_0.5"]]
    assert [r["ok"] for r in results] == [True] * 4 and results[0]["overrides"] == {}


def test_a_batch_stopped_by_a_signal_stops_its_study(tmp_path, tiny_bed, monkeypatch):
    """A batch whose runs a SIGTERM stopped (each with a checkpoint) returned their results as failed, and a
    slip or precision study tabulated them, exit 1, and started its next batch. The stop now ends the study
    there as a KeyboardInterrupt named SIGTERM (what the command line exits 143 on), no further batch
    started; so does a stop that came when every run of the batch had ended."""
    import cosim.batch
    import cosim.beds
    from cosim.study import _run_tasks
    from soil.memory import SoilTooLargeError

    def fits(plan, worlds=1):
        if worlds > 2:
            raise SoilTooLargeError(f"{worlds} worlds do not fit")

    batches = []

    def stopped(plans, out_dirs, overwrite=False):
        batches.append(out_dirs)
        return [{"ok": False, "status": "interrupted", "signal": "SIGTERM"} for _ in plans]

    monkeypatch.setattr(cosim.beds, "check_memory", fits)
    monkeypatch.setattr(cosim.batch, "run_batched", stopped)
    text = load_plan(write_tiny(tmp_path)).scene.to_toml()
    tasks = [
        {"scene_toml": text, "out_dir": f"{bed}_{slip}", "overrides": {"bed.bed_file": f"{tiny_bed}"} if bed else {}}
        for slip in (0.1, 0.5)
        for bed in (0, 1)
    ]
    with pytest.raises(KeyboardInterrupt, match="SIGTERM: the batched runs stopped") as stop:
        _run_tasks(None, tasks, batched=True)
    assert stop.value.signal == "SIGTERM" and len(batches) == 1  # the second bed's batch never started

    def ended_before_the_stop(plans, out_dirs, overwrite=False):
        batches.append(out_dirs)
        return [{"ok": True, "status": "complete", "stop_received": "SIGINT"} for _ in plans]

    monkeypatch.setattr(cosim.batch, "run_batched", ended_before_the_stop)
    with pytest.raises(KeyboardInterrupt, match="SIGINT") as stop:
        _run_tasks(None, tasks, batched=True)
    assert stop.value.signal == "SIGINT" and len(batches) == 2


def fixed_plan(tmp_path, tiny_bed):
    return load_plan(write_tiny(tmp_path), [f'bed.bed_file="{tiny_bed}"'])


def test_what_a_batch_cannot_run_is_refused_by_name(tmp_path, tiny_bed):
    analytic = load_plan(write_tiny(tmp_path), ['terrain.model="analytic"'])
    assert batch_problem(analytic).startswith("terrain.model")
    with pytest.raises(SceneError, match="--batched: terrain.model"):
        replica_run(analytic, str(tmp_path / "analytic"), 2, batched=True)
    # replicas over beds need a bed of grains each, settled from its own seed
    with pytest.raises(SceneError, match="--vary-bed: terrain.model 'analytic' settles no bed"):
        replica_run(analytic, str(tmp_path / "analytic"), 2, vary="bed")
    with pytest.raises(SceneError, match="--vary-bed: bed.bed_file = .* fixes one bed"):
        replica_run(fixed_plan(tmp_path, tiny_bed), str(tmp_path / "fixed"), 2, vary="bed")
    with pytest.raises(SceneError, match="vary: 'grains' is not a variation; allowed: order, bed"):
        slip_study(fixed_plan(tmp_path, tiny_bed), str(tmp_path / "fixed"), [0.1], vary="grains")
    # the worlds share one soil: runs that differ in it are refused by name
    other = load_plan(write_tiny(tmp_path), [f'bed.bed_file="{tiny_bed}"', "scene.precision='double'"])
    with pytest.raises(ValueError, match="its precision is 'double', run 0's 'mixed'"):
        run_batched([fixed_plan(tmp_path, tiny_bed), other], [str(tmp_path / "a"), str(tmp_path / "b")])
    # worlds of other beds must hold beds of one shape: a shorter box's bed is refused, naming both files
    shorter = load_plan(write_tiny(tmp_path), ["bed.length=0.1", "bed.settle_max_time=0.005"])
    with pytest.raises(ValueError, match=r"run 1 .* its bed .*bed.h5 differs from run 0's .* in its grain count"):
        run_batched([fixed_plan(tmp_path, tiny_bed), shorter], [str(tmp_path / "c"), str(tmp_path / "d")])
    # K copies must fit: checked before anything is allocated (a million tiny beds: about a terabyte)
    fixed = load_plan(write_tiny(tmp_path), [f'bed.bed_file="{tiny_bed}"'])
    with pytest.raises(SoilTooLargeError, match="as 1000000 batched replicas does not fit"):
        check_memory(fixed, 1_000_000)


# -- a stop signal, a dead run: the batch's runs in processes of their own ------------------------------

SEEDS = (0, 1)


def seed_plan(tmp_path, tiny_bed, seed):
    return load_plan(write_tiny(tmp_path), [f'bed.bed_file="{tiny_bed}"', f"run.order_seed={seed}"])


@pytest.fixture(scope="module")
def runs_alone(tmp_path_factory, tiny_bed):
    """The tiny scene's runs of order seeds SEEDS, each alone, uninterrupted."""
    folder = tmp_path_factory.mktemp("alone")
    out = []
    for seed in SEEDS:
        run_plan(seed_plan(folder, tiny_bed, seed), str(folder / f"seed_{seed}"))
        out.append(str(folder / f"seed_{seed}"))
    return out


def assert_same_run(a: str, b: str) -> None:
    """Every series of results.h5 and the final soil state equal to the last bit (wall clocks aside; and
    the divergence monitor's bounds, which a batch's worlds share: a resumed world's start from the batch's)."""
    series_a, series_b = read_series(f"{a}/results.h5"), read_series(f"{b}/results.h5")
    assert len(series_a["time"]) == len(series_b["time"]) > 20
    for name, values in series_a.items():
        if isinstance(values, np.ndarray) and name not in SAME_EVERYWHERE:
            assert np.array_equal(values, series_b[name], equal_nan=True), f"{b}: {name} differs"
    state_a, state_b = final_state(a), final_state(b)
    assert set(state_a) == set(state_b)
    for key in state_a:
        if "/monitor/" not in key:
            np.testing.assert_array_equal(state_a[key], state_b[key], err_msg=key)


def stop_the_first_run(monkeypatch, first):
    """cosim.launch.run_plan made to stop (a stop requested, then its checkpoint) at macro step 60 of the
    run whose folder first(out_dir) picks; returns the run_plan it replaced (set it back to go on)."""
    import cosim.launch

    run_alone = cosim.launch.run_plan

    def stopped_in_the_first(plan, out_dir, **kwargs):
        def stop(runner):
            if runner.system.coupler.step_count == 60:
                runner.stop_requested = True

        return run_alone(plan, out_dir, hooks={"step": stop} if first(out_dir) else None, **kwargs)

    monkeypatch.setattr(cosim.launch, "run_plan", stopped_in_the_first)
    return run_alone


def when_checkpointed(folders, action) -> threading.Thread:
    """Call action() once every folder's checkpoint.npz exists (each run is past its first checkpoint:
    the runs' processes take turns, so one may be well behind another)."""

    def watch():
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            if all(os.path.exists(os.path.join(folder, "checkpoint.npz")) for folder in folders):
                break
            time.sleep(0.02)
        action()

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    return thread


def world_processes() -> list[int]:
    """This process's batch children (cosim.batch.world_process), by /proc."""
    pids = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                command = f.read()
            with open(f"/proc/{entry}/stat") as f:
                parent = int(f.read().rsplit(")", 1)[1].split()[1])
        except OSError:
            continue
        if b"world_process" in command and parent == os.getpid():
            pids.append(int(entry))
    return pids


def test_a_stop_signal_stops_every_replica_of_a_batch_and_one_resume_finishes_them(tmp_path, tiny_bed, runs_alone):
    """SIGTERM to batched replicas (what a scheduler sends): every run stops after its macro step with a
    checkpoint. They were recorded as failed (ensemble.json: 0 of 2 steady, exit 1) and `cosim resume OUT`
    refused the folder. Now the stop says how to finish them (exit 143), and `cosim resume OUT` resumes each
    to the end its run alone reaches, bit for bit, and writes the ensemble."""
    from cosim.cli import main
    from cosim.study import REPLICAS_FILE

    out = tmp_path / "replicas"
    folders = [str(out / f"replica_{k:03d}") for k in range(len(SEEDS))]
    when_checkpointed(folders, lambda: os.kill(os.getpid(), signal.SIGTERM))
    with pytest.raises(KeyboardInterrupt, match=f"SIGTERM: the replicas stopped .*cosim resume {out}") as stop:
        replica_run(seed_plan(tmp_path, tiny_bed, SEEDS[0]), str(out), len(SEEDS), batched=True)
    assert stop.value.signal == "SIGTERM" and (out / REPLICAS_FILE).is_file() and not (out / "ensemble.json").exists()
    for folder in folders:  # a world's checkpoint is its scene's alone, units included
        assert assert_checkpoint_units(os.path.join(folder, "checkpoint.npz"))["soil/simulation/state/position"] == "m"
    assert main(["resume", str(out)]) == 6  # each ends unsteady, as alone (the tiny drive is too short to judge)
    for folder, alone in zip(folders, runs_alone):
        assert_same_run(alone, folder)
    report = json.loads((out / "ensemble.json").read_text())
    assert [(r["ok"], r["status"]) for r in report["results"]] == [(True, "unsteady")] * len(SEEDS)
    assert report["stats"]["replicas"] == len(SEEDS) and report["stats"]["steady"] == 0


def test_replicas_stopped_one_by_one_resume_as_a_set_each_as_its_run_alone(tmp_path, tiny_bed, runs_alone, monkeypatch):
    """Replicas run one by one, stopped (a stop requested, then a checkpoint) in the first: the second never
    began. `cosim resume OUT` resumes the first and runs the second, each bit for bit its run alone, and
    writes the ensemble; a second resume takes both as they are and writes it again."""
    import cosim.launch
    from cosim.cli import main

    run_alone = stop_the_first_run(monkeypatch, lambda folder: folder.endswith("replica_000"))
    out = tmp_path / "replicas"
    with pytest.raises(KeyboardInterrupt, match=f"SIGINT: the replicas stopped .*cosim resume {out}"):
        replica_run(seed_plan(tmp_path, tiny_bed, SEEDS[0]), str(out), len(SEEDS), executor="serial", batched=False)
    assert (out / "replica_000" / "checkpoint.npz").is_file() and not (out / "replica_001").exists()
    monkeypatch.setattr(cosim.launch, "run_plan", run_alone)
    for _ in range(2):
        assert main(["resume", str(out)]) == 6  # unsteady, as alone: the tiny drive is too short to judge
        for k, alone in enumerate(runs_alone):
            assert_same_run(alone, str(out / f"replica_{k:03d}"))
        report = json.loads((out / "ensemble.json").read_text())
        assert report["resumed"] and [r["status"] for r in report["results"]] == ["unsteady"] * len(SEEDS)
    # a replica that fails on resume (its checkpoint cut short) is named; the other is still taken
    checkpoint = out / "replica_000" / "checkpoint.npz"
    checkpoint.write_bytes(checkpoint.read_bytes()[:5000])
    assert main(["resume", str(out)]) == 1  # a run failed
    report = json.loads((out / "ensemble.json").read_text())
    assert [r["status"] for r in report["results"]] == ["failed", "unsteady"]
    assert str(checkpoint) in report["results"][0]["error"]
    # its scene.toml edited: still the set's replica (the run's own record is results.h5's), taken as it is
    edited = out / "replica_001" / "scene.toml"
    edited.write_text(edited.read_text().replace("duration = 0.12", "duration = 0.06"))
    assert main(["resume", str(out)]) == 1
    assert [r["status"] for r in json.loads((out / "ensemble.json").read_text())["results"]] == ["failed", "unsteady"]
    # a run of another replica put in its folder while the set was stopped (the set's lock covers its own folder,
    # not each replica's) was taken as the replica and pooled into the ensemble without a word, counted twice
    shutil.rmtree(out / "replica_001")
    shutil.copytree(runs_alone[0], out / "replica_001")  # order seed 0: replica_000's run
    assert main(["resume", str(out)]) == 1
    report = json.loads((out / "ensemble.json").read_text())
    assert [r["status"] for r in report["results"]] == ["failed", "failed"]
    assert "holds a run of another scene than this replica's (run.order_seed differ)" in report["results"][1]["error"]
    assert report["stats"]["replicas"] == len(SEEDS) and report["stats"]["averaged"] == 0


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="finds the batch's processes in /proc")
def test_a_run_whose_process_dies_leaves_the_batch_and_the_others_finish_as_alone(tmp_path, tiny_bed, runs_alone):
    """kill -9 of one run's process: its result says so, the other run goes on to its result alone bit for
    bit, and the dead run resumes from its checkpoint to its own."""
    plans = [seed_plan(tmp_path, tiny_bed, seed) for seed in SEEDS]
    out = [str(tmp_path / f"replica_{k}") for k in range(len(plans))]
    killed: list[int] = []

    def kill_one():
        pids = world_processes()
        assert len(pids) == len(plans), pids
        killed.append(pids[0])
        os.kill(pids[0], signal.SIGKILL)

    when_checkpointed(out, kill_one)  # whichever run dies can resume
    results = run_batched(plans, out)
    assert killed
    dead = [k for k, r in enumerate(results) if not r["ok"]]
    assert len(dead) == 1 and "exit code -9" in results[dead[0]]["error"], results
    (alive,) = set(range(len(plans))) - set(dead)
    assert results[alive]["status"] in ("complete", "unsteady")
    assert_same_run(runs_alone[alive], out[alive])
    assert resume(out[dead[0]]).status in ("complete", "unsteady")
    assert_same_run(runs_alone[dead[0]], out[dead[0]])


# -- a run that cannot start: refused before the batch, or leaving it without harm -----------------------


def test_a_batch_refuses_missing_plans_unequal_counts_and_taken_folders_before_anything_runs(
    tmp_path, tiny_bed, runs_alone
):
    from filelock import FileLock

    from cosim.folders import FolderInUseError, OutputExistsError
    from soil.errors import ArgumentError

    plan = fixed_plan(tmp_path, tiny_bed)
    fresh = tmp_path / "fresh"
    with pytest.raises(ArgumentError, match="no plans given"):
        run_batched([], [])
    with pytest.raises(ArgumentError, match="2 plans for 1 out_dirs: give one output folder per plan"):
        run_batched([plan, plan], [str(fresh)])
    # one folder twice, however spelled: two runs would write one folder
    with pytest.raises(ArgumentError, match="runs 0 and 1 have the same output folder"):
        run_batched([plan, plan], [str(fresh), str(tmp_path / "other" / ".." / "fresh")])
    # a folder that holds a run, or that another process runs in: refused before any run starts
    with pytest.raises(OutputExistsError, match="already holds a run"):
        run_batched([plan, plan], [str(fresh), runs_alone[0]])
    busy = tmp_path / "busy"
    busy.mkdir()
    with FileLock(str(busy / ".lock")):
        with pytest.raises(FolderInUseError, match="is in use by another process"):
            run_batched([plan, plan], [str(fresh), str(busy)])
    assert not fresh.exists(), "nothing was written for the run that would have started"


def test_a_run_that_fails_at_its_start_leaves_the_batch_and_the_others_run_as_alone(
    tmp_path, tiny_bed, runs_alone, monkeypatch
):
    """A run whose process fails before it places its wheels (its folder taken after the batch's check:
    the check is skipped here) leaves the batch: its wheels, where they were built, are lifted clear of
    its grains (they lay inside its bed and threw its grains out, which stopped every world as a
    divergence), and the other run gives its results alone, bit for bit, in either order."""
    import cosim.batch

    monkeypatch.setattr(cosim.batch, "_check_folders", lambda *args: None, raising=False)
    for order in ((0, 1), (1, 0)):
        plans = [seed_plan(tmp_path, tiny_bed, SEEDS[k]) for k in order]
        fresh = str(tmp_path / f"fresh_{order[0]}")
        # the world of seed 0 goes to its run alone's folder, which holds a run: it cannot start
        folders = [runs_alone[0] if k == 0 else fresh for k in order]
        results = run_batched(plans, folders)
        failed, ran = (results[0], results[1]) if order[0] == 0 else (results[1], results[0])
        assert not failed["ok"] and failed["error"].startswith("OutputExistsError"), failed.get("error")
        assert ran["ok"], ran.get("error")
        assert_same_run(runs_alone[1], fresh)


def test_a_sweep_stopped_in_its_first_point_is_finished_by_one_resume(
    tmp_path, tiny_bed, runs_alone, monkeypatch, capsys
):
    """A sweep (over run.order_seed, one run per point) stopped in its first point's run: the second never
    began, and nothing finished the sweep but running it all again (`cosim resume OUT`: 'not a run folder').
    Now the stop says how to finish it, and `cosim resume OUT` resumes the first, runs the second, each bit
    for bit its run alone, and writes the sweep's table; an edited recipe is refused, nothing touched."""
    import cosim.launch
    from cosim.cli import main
    from cosim.study import SWEEP_FILE, sweep
    from soil.errors import DamagedFileError

    run_alone = stop_the_first_run(monkeypatch, lambda folder: os.path.basename(folder).startswith("000_"))
    out = tmp_path / "sweep"
    params = ["run.order_seed=" + ",".join(map(str, SEEDS))]
    with pytest.raises(KeyboardInterrupt, match=f"SIGINT: the sweep stopped .*cosim resume {out}"):
        sweep(seed_plan(tmp_path, tiny_bed, SEEDS[0]), str(out), params, executor="serial", plot=False)
    points = [out / f"{k:03d}_order_seed={seed}" for k, seed in enumerate(SEEDS)]
    assert (points[0] / "checkpoint.npz").is_file() and not points[1].exists() and not (out / "study.json").exists()
    monkeypatch.setattr(cosim.launch, "run_plan", run_alone)
    assert main(["resume", str(out)]) == 6  # unsteady, as alone: the tiny drive is too short to judge
    for point, alone in zip(points, runs_alone):
        assert_same_run(alone, str(point))
    table = json.loads((out / "study.json").read_text())
    assert [row["run.order_seed"] for row in table["rows"]] == list(SEEDS)
    assert [row["status"] for row in table["rows"]] == ["unsteady"] * len(SEEDS)
    recipe = out / SWEEP_FILE
    recipe.write_text(recipe.read_text().replace('"plot": false', '"plot": true'))
    before = (out / "study.json").read_bytes()
    with pytest.raises(DamagedFileError, match="no longer matches its digest"):
        cosim.study.resume_sweep(str(out))
    assert (out / "study.json").read_bytes() == before
    recipe.write_text(recipe.read_text().replace('"plot": true', '"plot": false'))  # whole again

    def stopped_while_tabulating(*args, **kwargs):
        raise KeyboardInterrupt

    # a stop while the table is written says how to finish it (it said only "interrupted")
    monkeypatch.setattr(cosim.study, "_sweep_report", stopped_while_tabulating)
    with pytest.raises(KeyboardInterrupt, match=f"the sweep stopped .*cosim resume {out}.* writes its table"):
        cosim.study.resume_sweep(str(out))
    # a sweep without its recipe (made before it had one) names its runs, each resumable alone
    recipe.unlink()
    assert main(["resume", str(out)]) == 2
    said = capsys.readouterr().err
    assert f"holds a sweep's runs ({points[0].name}, {points[1].name}) without the recipe" in said, said


def test_a_slip_study_stopped_in_a_run_is_finished_by_one_resume(tmp_path, tiny_bed, monkeypatch):
    """A slip study (one slip, two replicas, one by one) stopped in its first run: its table was never
    written, and only `--from-runs` over the runs that had finished, or the whole study again, followed.
    Now `cosim resume OUT` resumes the stopped run (bit for bit its run uninterrupted), runs the replica
    that never began, and writes the table as the uninterrupted study writes it."""
    import cosim.launch
    from cosim.cli import main
    from cosim.study import SLIP_FILE, slip_study

    run_alone = stop_the_first_run(monkeypatch, lambda folder: folder.endswith("replica_000"))
    out = tmp_path / "slip"
    with pytest.raises(KeyboardInterrupt, match=f"SIGINT: the slip study stopped .*cosim resume {out}"):
        slip_study(seed_plan(tmp_path, tiny_bed, 0), str(out), [0.2], replicas=2, executor="serial", plot=False)
    runs = [out / "slip_+0.200" / f"replica_{k:03d}" for k in range(2)]
    assert (runs[0] / "checkpoint.npz").is_file() and not runs[1].exists() and (out / SLIP_FILE).is_file()
    monkeypatch.setattr(cosim.launch, "run_plan", run_alone)
    assert main(["resume", str(out)]) in (0, 6)  # the tiny drive may be too short to judge steady
    reference = tmp_path / "reference"  # replica 0 run alone, uninterrupted: order seed 0 at slip 0.2
    alone = [f'bed.bed_file="{tiny_bed}"', "run.order_seed=0", 'testbed.mode="slip"', "testbed.slip=0.2"]
    run_alone(load_plan(write_tiny(tmp_path), alone), str(reference))
    assert_same_run(str(reference), str(runs[0]))
    table = json.loads((out / "study.json").read_text())
    assert [row["replicas"] for row in table["rows"]] == [2] and table["rows"][0]["failed"] == 0
    assert {r["status"] for r in table["runs"]} <= {"complete", "unsteady"}


def test_a_precision_study_stopped_in_a_run_is_finished_by_one_resume(tmp_path, tiny_bed, runs_alone, monkeypatch):
    """A precision study (mixed, two replicas, one by one) stopped in its first run: `cosim resume OUT`
    resumes it and runs the second, each bit for bit its run alone, and writes the table, marked resumed."""
    import cosim.launch
    from cosim.cli import main
    from cosim.study import PRECISION_FILE, precision_study

    run_alone = stop_the_first_run(monkeypatch, lambda folder: folder.endswith("replica_000"))
    out = tmp_path / "precision"
    plan = seed_plan(tmp_path, tiny_bed, SEEDS[0])
    with pytest.raises(KeyboardInterrupt, match=f"SIGINT: the precision study stopped .*cosim resume {out}"):
        precision_study(plan, str(out), replicas=2, precisions=["mixed"], executor="serial", plot=False, batched=False)
    runs = [out / "mixed" / f"replica_{k:03d}" for k in range(2)]
    assert (runs[0] / "checkpoint.npz").is_file() and not runs[1].exists() and (out / PRECISION_FILE).is_file()
    monkeypatch.setattr(cosim.launch, "run_plan", run_alone)
    assert main(["resume", str(out)]) == 6  # unsteady, as alone: the tiny drive is too short to judge
    for run, alone in zip(runs, runs_alone):
        assert_same_run(alone, str(run))
    table = json.loads((out / "study.json").read_text())
    assert table["resumed"] and [row["replicas"] for row in table["rows"]] == [2]


def test_a_sweep_resumes_on_the_beds_it_settled_when_their_keys_are_reckoned_otherwise(tmp_path, monkeypatch):
    """A sweep's recipe named its beds by bed key, and a resume looked each point's up by the key it reckons
    now: on another device class, or after the contact law's version changed, a KeyError (an unexpected
    error). The recipe keeps each point's bed; the resume runs on those, never settling again."""
    import cosim.launch
    import cosim.plan
    from cosim.study import SWEEP_FILE, resume_sweep, sweep

    run_alone = cosim.launch.run_plan

    def stopped_at_once(plan, out_dir, **kwargs):
        def stop(runner):
            runner.stop_requested = True

        return run_alone(plan, out_dir, hooks={"step": stop}, **kwargs)

    monkeypatch.setattr(cosim.launch, "run_plan", stopped_at_once)
    out = tmp_path / "sweep"
    plan = load_plan(write_tiny(tmp_path), ["run.duration=0.02"])
    with pytest.raises(KeyboardInterrupt, match="the sweep stopped"):
        sweep(plan, str(out), ["testbed.omega=0.5,1.0"], executor="serial", plot=False)
    beds = json.loads((out / SWEEP_FILE).read_text())["beds"]
    assert len(beds) == 2 and beds[0] == beds[1] and os.path.isfile(beds[0])  # one bed key: one bed
    settled = os.path.getmtime(beds[0])
    monkeypatch.setattr(cosim.launch, "run_plan", run_alone)
    monkeypatch.setattr(cosim.plan, "LAW_VERSION", 99)  # every bed key reckoned otherwise now
    report = resume_sweep(str(out))
    assert [row["status"] for row in report["rows"]] == ["unsteady", "unsteady"]  # run to their ends
    assert os.path.getmtime(beds[0]) == settled and sorted(os.listdir(out / "beds")) == [
        os.path.basename(os.path.dirname(beds[0]))
    ]
