"""Checkpoints and resume (bitwise on the CPU), divergence handling, and dask ensembles vs serial runs."""

import json

import numpy as np
import pytest

from cosim.output import open_results
from cosim.runner import RunDiverged, RunInterrupted, final_state, resume, run_scene
from cosim.scene import load_scene
from cosim.study import precision_study
from cosim_tiny import write_tiny


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted run; its bed is reused by the others (same bed file content, same result)."""
    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no per-module load lines
    folder = tmp_path_factory.mktemp("study")
    scene_path = write_tiny(folder)
    result = run_scene(scene_path, str(folder / "reference"), progress=False, log=None)
    assert result.status == "complete"
    return scene_path, folder / "reference"


def _scene(reference, *extra):
    scene_path, ref = reference
    return load_scene(scene_path, [f'bed.bed_file="{ref / "bed.h5"}"', *extra])


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
        assert fb.attrs["status"] == "complete"


def test_resume_after_a_hard_interrupt_is_bitwise_identical(reference, tmp_path):
    baseline = tmp_path / "baseline"
    assert run_scene(_scene(reference), str(baseline), progress=False, log=None).status == "complete"
    checkpoints = []

    def stop_after_second_checkpoint(runner):
        checkpoints.append(runner.coupler.step_count)
        if len(checkpoints) == 2:
            raise KeyboardInterrupt("test: killed after the second checkpoint")

    def stop_mid_interval(runner):  # between checkpoints: resume must roll back to the last one
        if checkpoints and runner.coupler.step_count == checkpoints[-1] + 3:
            raise KeyboardInterrupt("test: killed between checkpoints")

    broken = tmp_path / "broken"
    with pytest.raises(KeyboardInterrupt):
        run_scene(_scene(reference), str(broken), progress=False, log=None,
                  hooks={"after_checkpoint": stop_after_second_checkpoint, "after_step": stop_mid_interval})
    info = json.loads((broken / "run.json").read_text())
    assert info["status"] == "interrupted"
    with open_results(broken / "results.h5") as f:
        assert f.attrs["status"] == "interrupted"
        assert f["wheels/time"].shape[0] > checkpoints[-1]  # records past the checkpoint exist; resume cuts them
    assert resume(str(broken), progress=False, log=None).status == "complete"
    _assert_same_run(baseline, broken)
    with pytest.raises(AssertionError):  # the comparison can fail: a different run differs
        other = tmp_path / "other"
        run_scene(_scene(reference, "run.order_seed=7"), str(other), progress=False, log=None)
        _assert_same_run(baseline, other)


def test_clean_stop_then_resume_is_bitwise_identical(reference, tmp_path):
    baseline = tmp_path / "baseline"
    run_scene(_scene(reference), str(baseline), progress=False, log=None)
    stopped = tmp_path / "stopped"

    def request_stop(runner):  # what the first Ctrl-C does
        if runner.coupler.step_count == 25:
            runner.stop_requested = True

    with pytest.raises(RunInterrupted):
        run_scene(_scene(reference), str(stopped), progress=False, log=None, hooks={"after_step": request_stop})
    checkpoint = np.load(stopped / "checkpoint.npz")
    assert int(checkpoint["coupler/step_count"]) == 25  # the stop wrote a checkpoint at that step
    resume(str(stopped), progress=False, log=None)
    _assert_same_run(baseline, stopped)


def test_divergence_stops_with_the_last_good_state(reference, tmp_path):
    out = tmp_path / "boom"

    def explode(runner):  # a grain suddenly flies off, as in a DEM explosion
        if runner.coupler.step_count == 9:
            v = runner.sim.state.velocity.numpy()
            v[0] = (0.0, 0.0, 1e3)
            runner.sim.state.velocity.assign(v)

    with pytest.raises(RunDiverged, match="last good state") as info:
        run_scene(_scene(reference), str(out), progress=False, log=None, hooks={"after_step": explode})
    assert "checkpoint.npz" in str(info.value) and "max_speed" in str(info.value)
    with open_results(out / "results.h5") as f:
        assert f.attrs["status"] == "diverged"
    assert json.loads((out / "run.json").read_text())["status"] == "diverged"
    checkpoint = np.load(out / "checkpoint.npz")
    v = checkpoint["soil/velocity"]
    assert int(checkpoint["coupler/step_count"]) < 10
    assert np.all(np.isfinite(v)) and np.max(np.linalg.norm(v, axis=1)) < 1.0


def test_dask_ensemble_matches_serial_runs(reference, tmp_path):
    scene = _scene(reference)
    kwargs = dict(replicas=2, precisions=("single", "mixed"), log=lambda *a: None, plot=False)
    serial = precision_study(scene, str(tmp_path / "serial"), executor="serial", **kwargs)
    ensemble = precision_study(scene, str(tmp_path / "dask"), executor="dask", workers=2, **kwargs)
    keys = ("travel", "mean_slip", "mean_sinkage", "mean_drawbar_pull", "final_sinkage", "simulated_time")
    assert len(serial["replicas"]) == len(ensemble["replicas"]) == 4
    for a, b in zip(serial["replicas"], ensemble["replicas"]):
        assert a["ok"] and b["ok"], (a.get("error"), b.get("error"))
        assert (a["precision"], a["replica"]) == (b["precision"], b["replica"])
        assert {k: a["summary"][k] for k in keys} == {k: b["summary"][k] for k in keys}
    # replicas differ only in the summation order (order_seed = replica index), on one shared bed
    for r in serial["replicas"]:
        with open_results(f"{r['out_dir']}/results.h5") as f:
            assert f.attrs["order_seed"] == r["replica"]
            assert json.loads(f.attrs["bed"])["path"] == serial["bed_file"]


def test_timestep_study_finds_a_stable_limit(reference, tmp_path):
    from cosim.study import timestep_study

    report = timestep_study(_scene(reference), str(tmp_path / "ts"), duration=0.03, growth=2.0, log=lambda *a: None)
    assert report["largest_stable"] is not None and report["first_unstable"] is not None
    assert report["largest_stable"] < report["first_unstable"]
    assert report["tried"][-1]["stable"] is False and "advisor" in report
    assert json.loads((tmp_path / "ts" / "study.json").read_text())["kind"] == "timestep"
