"""Replicas batched as worlds of one simulation (cosim.batch): each replica's results are bit for bit those
of the same replica run alone, and the batch refuses what it cannot run."""

import numpy as np
import pytest

from cosim.batch import batch_problem
from cosim.beds import check_memory
from cosim.output import read_series
from cosim.plan import load_plan
from cosim.scene import SceneError
from cosim.study import replica_run, slip_study
from helpers import write_tiny
from soil.memory import SoilTooLargeError

REPLICAS = 3
SAME_EVERYWHERE = ("wall_time", "session_wall_time", "particle_steps_per_second", "real_time_factor")


def test_batched_replicas_equal_their_runs_alone(tmp_path, tiny_bed):
    plan = load_plan(write_tiny(tmp_path), [f'bed.bed_file="{tiny_bed}"'])
    alone = replica_run(plan, str(tmp_path / "alone"), REPLICAS, executor="serial", batched=False)
    together = replica_run(plan, str(tmp_path / "together"), REPLICAS, batched=True)
    assert together["batched"] and not alone["batched"]
    for a, b in zip(alone["results"], together["results"]):
        assert a["ok"] and b["ok"], (a.get("error"), b.get("error"))
        series_a, series_b = read_series(f"{a['out_dir']}/results.h5"), read_series(f"{b['out_dir']}/results.h5")
        assert len(series_a["time"]) > 20
        for name, values in series_a.items():
            if isinstance(values, np.ndarray) and name not in SAME_EVERYWHERE:
                assert np.array_equal(values, series_b[name], equal_nan=True), f"{b['out_dir']}: {name} differs"
        for name, value in a["summary"].items():
            if isinstance(value, float) and "wall" not in name and "per_second" not in name:
                assert value == b["summary"][name] or (np.isnan(value) and np.isnan(b["summary"][name])), name
    # the replicas are replicas: their summation orders make them differ
    drawbar = [r["summary"]["drawbar_pull"] for r in together["results"]]
    assert len(set(drawbar)) == REPLICAS


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


def fixed_plan(tmp_path, tiny_bed):
    return load_plan(write_tiny(tmp_path), [f'bed.bed_file="{tiny_bed}"'])


def test_what_a_batch_cannot_run_is_refused_by_name(tmp_path, tiny_bed):
    plan = load_plan(write_tiny(tmp_path), [f'bed.bed_file="{tiny_bed}"', 'run.step_control="pid"'])
    assert "step_control" in batch_problem(plan)
    with pytest.raises(SceneError, match="--batched: run.step_control"):
        replica_run(plan, str(tmp_path / "pid"), 2, batched=True)
    assert batch_problem(load_plan(write_tiny(tmp_path), ['terrain.model="analytic"'])).startswith("terrain.model")
    # the worlds share one soil: runs that differ in it are refused by name
    from cosim.batch import run_batched

    other = load_plan(write_tiny(tmp_path), [f'bed.bed_file="{tiny_bed}"', "scene.precision='double'"])
    with pytest.raises(ValueError, match="its precision is 'double', run 0's 'mixed'"):
        run_batched([fixed_plan(tmp_path, tiny_bed), other], [str(tmp_path / "a"), str(tmp_path / "b")])
    # K copies must fit: checked before anything is allocated (a million tiny beds: about a terabyte)
    fixed = load_plan(write_tiny(tmp_path), [f'bed.bed_file="{tiny_bed}"'])
    with pytest.raises(SoilTooLargeError, match="as 1000000 batched replicas does not fit"):
        check_memory(fixed, 1_000_000)
