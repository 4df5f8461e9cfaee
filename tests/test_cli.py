"""The cosim command line end to end on a tiny scene: run, refuse to overwrite, plot, advise, study, sweep."""

import json
import os
import subprocess
import sys

import pytest

from cosim.cli import main
from cosim.output import open_results
from cosim_tiny import write_tiny


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cli")
    scene = write_tiny(folder)
    out = folder / "run"
    assert main(["run", scene, "--out", str(out), "--no-progress", "--precision", "double"]) == 0
    return scene, out


def test_run_writes_a_complete_run(cli_run):
    _, out = cli_run
    for name in ("results.h5", "results.xdmf", "checkpoint.npz", "run.json", "scene.toml", "bed.h5"):
        assert (out / name).is_file(), name
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "complete" and info["summary"]["macro_steps"] > 0
    with open_results(out / "results.h5") as f:
        assert f.attrs["status"] == "complete" and f.attrs["precision"] == "double"


def test_run_refuses_a_non_empty_folder(cli_run, capsys):
    scene, out = cli_run
    before = os.stat(out / "results.h5").st_mtime_ns
    assert main(["run", scene, "--out", str(out), "--no-progress"]) == 3
    assert "not empty" in capsys.readouterr().err
    assert os.stat(out / "results.h5").st_mtime_ns == before


def test_overwrite_reuses_the_cached_bed(tmp_path, capsys):
    scene = write_tiny(tmp_path)
    out = tmp_path / "run"
    assert main(["run", scene, "--out", str(out), "--no-progress"]) == 0
    bed = os.stat(out / "bed.h5").st_mtime_ns
    assert main(["run", scene, "--out", str(out), "--no-progress", "--overwrite", "--set", "testbed.omega=0.5"]) == 0
    assert "reusing the settled bed" in capsys.readouterr().out
    assert os.stat(out / "bed.h5").st_mtime_ns == bed


def test_plot_writes_pngs(cli_run):
    _, out = cli_run
    assert main(["plot", str(out)]) == 0
    for name in ("travel_sinkage.png", "slip_drawbar.png"):
        data = (out / "plots" / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_advise_prints_the_stiffness_bound(cli_run, capsys):
    scene, _ = cli_run
    assert main(["advise", scene]) == 0
    text = capsys.readouterr().out
    assert "eq. 10" in text and "Rayleigh" in text and "recommended dt" in text


def test_resume_of_a_complete_run_does_nothing(cli_run, capsys):
    _, out = cli_run
    assert main(["resume", str(out), "--no-progress"]) == 0
    assert "already complete" in capsys.readouterr().out


def test_python_dash_m_cosim():
    done = subprocess.run([sys.executable, "-m", "cosim", "--help"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and "resume" in done.stdout and "sweep" in done.stdout


def test_study_precision_on_a_local_cluster(tmp_path):
    scene = write_tiny(tmp_path)
    out = tmp_path / "study"
    assert main(["study", "precision", scene, "--replicas", "2", "--precisions", "single,double", "--out", str(out),
                 "--workers", "2"]) == 0
    report = json.loads((out / "study.json").read_text())
    assert [r["precision"] for r in report["rows"]] == ["single", "double"]
    assert all(r["ok"] == 2 and "travel_std" in r and "mean_sinkage_max" in r for r in report["rows"])
    assert (out / "plots" / "scatter.png").is_file() and (out / "plots" / "travel_sinkage.png").is_file()
    assert (out / "study.csv").read_text().startswith("precision,")
    for precision in ("single", "double"):
        for k in range(2):
            assert (out / precision / f"replica_{k:03d}" / "results.h5").is_file()


def test_sweep_reports_a_failed_point_and_finishes_the_others(tmp_path, capsys):
    scene = write_tiny(tmp_path)
    out = tmp_path / "sweep"
    # run.max_speed = 1e-9 m/s: the first step counts as an explosion, that point fails
    code = main(["sweep", scene, "--param", "run.max_speed=1e-9,10.0", "--param", "testbed.omega=0.5,1.0",
                 "--out", str(out), "--serial"])
    assert code == 1
    report = json.loads((out / "study.json").read_text())
    ok = [r["ok"] for r in report["rows"]]
    assert ok == [False, False, True, True]
    assert "diverged" in report["rows"][0]["error"]
    assert "failed point" in capsys.readouterr().out
