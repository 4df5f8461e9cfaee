"""--overwrite keeps what is not a run's, and an overwrite stopped before the new run is built leaves the old
run resumable on its own bed; a kill between the bed cache's two files leaves a cache the next run settles again."""

import json
import os

import pytest

from cosim import beds
from cosim.cli import main
from helpers import write_tiny
from soil.bed import read_bed_header


def test_overwrite_refuses_a_folder_of_a_runs_names_but_no_run(tmp_path, capsys):
    folder = tmp_path / "project"
    (folder / "plots").mkdir(parents=True)
    (folder / "plots" / "figure.png").write_bytes(b"mine")
    scene = write_tiny(folder, name="scene.toml")
    text = (folder / "scene.toml").read_text()
    code = main(["run", scene, "--out", str(folder), "--overwrite", "--no-progress", "--set", "run.duration=0.02"])
    assert code == 3
    assert "but no run" in capsys.readouterr().err
    assert (folder / "plots" / "figure.png").read_bytes() == b"mine"
    assert (folder / "scene.toml").read_text() == text


def test_an_overwrite_stopped_after_its_bed_settled_keeps_the_old_runs_bed(tmp_path, monkeypatch, capsys):
    scene = write_tiny(tmp_path)
    out = tmp_path / "run"
    assert main(["run", scene, "--out", str(out), "--no-progress", "--set", "run.duration=0.02"]) in (0, 6)
    old = json.loads((out / "run.json").read_text())["bed"]["key"]

    def stopped(*args, **kwargs):  # Ctrl-C (or a kill) while the new run's system is built
        raise KeyboardInterrupt

    monkeypatch.setattr("cosim.launch.CoupledSystem.build", stopped)
    with pytest.raises(KeyboardInterrupt):
        from cosim.launch import run_scene

        run_scene(scene, str(out), overwrite=True, overrides=["bed.seed=2", "run.duration=0.02"])
    assert read_bed_header(str(out / "bed.h5"))["key"] == old
    assert json.loads((out / "bed.json").read_text())["key"] == old


def test_a_kill_between_the_bed_files_leaves_a_cache_settled_again(tmp_path, monkeypatch):
    scene = write_tiny(tmp_path)
    out = tmp_path / "run"
    assert main(["run", scene, "--out", str(out), "--no-progress", "--set", "run.duration=0.02"]) in (0, 6)
    real = beds.write_json

    def killed(path, data):
        if os.path.basename(path) == beds.BED_INFO_FILE:
            raise SystemExit("killed")
        return real(path, data)

    monkeypatch.setattr(beds, "write_json", killed)
    with pytest.raises(SystemExit):
        main(["run", scene, "--out", str(tmp_path / "other"), "--no-progress", "--set", "bed.seed=2"])
    with pytest.raises(SystemExit):  # the cache of a folder holding no run is written as the bed settles
        from cosim.folders import RunFolder

        RunFolder(out).clear_run()
        main(["run", scene, "--out", str(out), "--no-progress", "--set", "bed.seed=2", "--set", "run.duration=0.02"])
    assert not (out / beds.BED_INFO_FILE).exists()  # no bed.json describing another bed.h5
    monkeypatch.setattr(beds, "write_json", real)
    assert main(["run", scene, "--out", str(out), "--no-progress", "--set", "run.duration=0.02"]) in (0, 6)
