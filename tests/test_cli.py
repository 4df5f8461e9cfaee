"""The cosim command line end to end on the tiny scene: outputs, exit codes, clear one-line errors,
and no library chatter on the user's output."""

import errno
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cosim.cli import main
from cosim.output import open_results
from helpers import write_tiny
from soil.errors import ArgumentError


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory, tiny_bed):
    folder = tmp_path_factory.mktemp("cli")
    scene = write_tiny(folder)
    out = folder / "run"
    code = main(
        [
            "run",
            scene,
            "--out",
            str(out),
            "--no-progress",
            "--precision",
            "double",
            "--set",
            f'bed.bed_file="{tiny_bed}"',
        ]
    )
    assert code in (0, 6)  # the tiny drive is too short for a steady state: exit 6 says so
    return scene, out, code


def test_run_writes_a_complete_run(cli_run):
    _, out, code = cli_run
    for name in ("results.h5", "results.xdmf", "checkpoint.npz", "run.json", "scene.toml"):
        assert (out / name).is_file(), name
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == ("complete" if code == 0 else "unsteady")
    assert info["summary"]["macro_steps"] > 0 and "steady_state" in info["summary"]
    assert info["summary"]["validity"].startswith("out of range")  # the tiny scene is coarse, and is told so
    with open_results(out / "results.h5") as f:
        assert f.attrs["status"] == info["status"] and f.attrs["precision"] == "double"


def test_run_refuses_a_folder_holding_a_run(cli_run, capsys):
    scene, out, _ = cli_run
    before = os.stat(out / "results.h5").st_mtime_ns
    assert main(["run", scene, "--out", str(out), "--no-progress"]) == 3
    assert "already holds a run" in capsys.readouterr().err
    assert os.stat(out / "results.h5").st_mtime_ns == before


def test_overwrite_reuses_the_cached_bed(tmp_path, capsys):
    scene = write_tiny(tmp_path)
    out = tmp_path / "run"
    assert main(["run", scene, "--out", str(out), "--no-progress", "--set", "run.duration=0.02"]) in (0, 6)
    bed = os.stat(out / "bed.h5").st_mtime_ns
    assert main(
        [
            "run",
            scene,
            "--out",
            str(out),
            "--no-progress",
            "--overwrite",
            "--set",
            "testbed.omega=0.5",
            "--set",
            "run.duration=0.02",
        ]
    ) in (0, 6)
    assert "reusing the settled bed" in capsys.readouterr().err
    assert os.stat(out / "bed.h5").st_mtime_ns == bed


def test_plot_writes_pngs(cli_run):
    _, out, _ = cli_run
    assert main(["plot", str(out)]) == 0
    for name in ("travel_sinkage.png", "slip_drawbar.png"):
        data = (out / "plots" / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_plot_looks_for_runs_a_few_folders_deep_only(cli_run, tmp_path, capsys, monkeypatch):
    """`cosim plot /` must not walk the whole disk: runs up to SEARCH_DEPTH folders below the folder named
    are found (a folder of studies' replicas), deeper ones and those in hidden folders are not."""
    import shutil

    from cosim.plots import SEARCH_DEPTH

    _, out, _ = cli_run
    levels = [f"level_{k}" for k in range(SEARCH_DEPTH)]
    shutil.copytree(
        out, tmp_path / "shallow" / os.path.join(*levels[:-1]) / "run", ignore=shutil.ignore_patterns("plots")
    )
    shutil.copytree(out, tmp_path / "deep" / os.path.join(*levels) / "run", ignore=shutil.ignore_patterns("plots"))
    shutil.copytree(out, tmp_path / "hidden" / ".cache" / "run", ignore=shutil.ignore_patterns("plots"))
    assert main(["plot", str(tmp_path / "shallow")]) == 0
    assert (tmp_path / "shallow" / "plots" / "travel_sinkage.png").is_file()
    capsys.readouterr()
    monkeypatch.chdir(tmp_path / "deep")  # a relative folder counts its depth the same ('.' and 'a' were one)
    for name in (str(tmp_path / "deep"), str(tmp_path / "hidden"), ".", os.path.join("..", "deep")):
        assert main(["plot", name]) == 2, name
        assert f"(looked {SEARCH_DEPTH} folders deep)" in capsys.readouterr().err
    assert not (tmp_path / "deep" / "plots").exists() and not (tmp_path / "hidden" / "plots").exists()


def test_advise_prints_the_bounds_and_the_validity_checks(cli_run, capsys):
    scene, _, _ = cli_run
    assert main(["advise", scene]) == 0
    text = capsys.readouterr().out
    for words in (
        "eq. 10",
        "Rayleigh",
        "recommended dt",
        "froude",
        "grains_across",
        "floor_clearance",
        "verdict: out of range",
        "DEM steps (E = ",  # what the stiffness costs: a soil 1e8 x the bound was "valid" at 1e8 steps unsaid
    ):
        assert words in text, words
    # a soil too large for the machine is in the verdict, as a run refuses it (it was a line apart)
    assert main(["advise", scene, "--set", "bed.radius_mean=1e-5"]) == 0
    text = capsys.readouterr().out
    assert "[OUT OF RANGE] memory:" in text and "memory" in text.split("verdict:")[1].split("\n")[0], text
    assert main(["advise", scene]) == 0
    assert "memory" not in capsys.readouterr().out.split("verdict:")[1]  # the tiny scene fits
    # an analytic ground steps no grains: neither their memory nor their step count is judged
    assert main(["advise", scene, "--set", 'terrain.model="analytic"', "--set", "bed.radius_mean=1e-5"]) == 0
    text = capsys.readouterr().out
    assert "memory" not in text.split("verdict:")[1] and "DEM steps (E = " not in text, text
    # the phases before the drive at their longest (a soil of tiny grains settled an hour unsaid)
    from cosim.plan import load_plan

    plan = load_plan(scene)
    assert main(["advise", scene]) == 0
    line = next(s for s in capsys.readouterr().out.splitlines() if "before it, at most" in s)
    settling = plan.bed.settle_max_time / plan.bed.settle_dt
    assert f"{settling:.3g} DEM steps settle the bed" in line, line
    assert f"{plan.scene.landing.max_time / plan.dt:.3g} land the wheel" in line, line
    # the PID's substeps are judged against the critical step (advise spoke of the fixed dt alone, and a
    # run.dt_max of 1e30 s went unsaid until the bed diverged while settling)
    assert main(["advise", scene, "--set", "run.step_control=pid"]) == 0
    text = capsys.readouterr().out
    line = next(s for s in text.splitlines() if "the PID substeps" in s)
    assert "run.dt_max unset: the advised limit" in line and "above the critical step" not in line, line
    assert main(["advise", scene, "--set", "run.step_control=pid", "--set", "run.dt_max=1e30"]) == 0
    text = capsys.readouterr().out
    critical = float(re.search(r"critical step (\S+) s", text).group(1))
    line = next(s for s in text.splitlines() if "the PID substeps" in s)
    ratio = float(re.search(r"run.dt_max: (\S+) x the critical step", line).group(1))
    assert ratio == pytest.approx(1e30 / critical, rel=1e-2), line
    assert "above the critical step only the error estimate keeps a substep stable" in line, line


def test_a_run_says_what_settling_its_bed_costs_before_it_starts(tmp_path, monkeypatch, capsys):
    """A soil of tiny grains (soil.density = 1e-3) settled at 1.2e-7 s steps, 1.25e8 of them, for an hour
    without a word under --no-progress: the run now says the settling's DEM steps at most (its time over
    its step) before the first one. The settling itself is stopped at once here."""
    import soil.bed
    from cosim.plan import load_plan
    from helpers import write_tiny

    def stop(*args, **kwargs):
        raise KeyboardInterrupt  # the run stops as on Ctrl-C, before any step

    monkeypatch.setattr(soil.bed, "make_settled_bed", stop)
    scene = write_tiny(tmp_path)
    for overrides, words in (([], "up to about"), (['run.step_control="pid"'], "about")):
        plan = load_plan(scene, overrides)
        sets = [item for o in overrides for item in ("--set", o)]
        assert main(["run", scene, "--out", str(tmp_path / "run"), "--no-progress", "--overwrite", *sets]) != 0
        err = capsys.readouterr().err
        steps = plan.bed.settle_max_time / plan.bed.settle_dt
        assert f"settling the bed: {words} {steps:.3g} DEM steps" in err, err
        assert ("at the PID's first step" in err) == bool(overrides), err


def test_a_study_says_what_settling_its_beds_costs(tmp_path, monkeypatch, caplog):
    """A study settles its beds on dask workers, whose own log is not shown: the parent says what each
    bed's settling costs before it hands them out (the settling stopped at once here)."""
    import logging

    import soil.bed
    from cosim.plan import load_plan
    from cosim.study import Executor, _replica_beds
    from helpers import write_tiny

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(soil.bed, "make_settled_bed", stop)
    plan = load_plan(write_tiny(tmp_path))
    steps = plan.bed.settle_max_time / plan.bed.settle_dt
    for vary, words in (("bed", f"2 beds, bed.seed 1 to 2, each up to about {steps:.3g}"), ("order", "shared bed")):
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="cosim.study"), Executor("serial") as ex:
            with pytest.raises(KeyboardInterrupt):
                _replica_beds(plan, str(tmp_path / vary), ex, 2, vary)
        assert words in caplog.text and f"up to about {steps:.3g} DEM steps" in caplog.text, caplog.text


def test_resume_of_a_complete_run_does_nothing(cli_run, capsys):
    _, out, code = cli_run
    assert main(["resume", str(out), "--no-progress"]) == code
    assert "already complete" in capsys.readouterr().err


def test_resume_of_a_finished_run_prints_what_was_not_measured_as_nan(cli_run, capsys, tmp_path):
    """run.json holds null for what was not measured (strict JSON): a finished run resumed prints its summary
    from there, and a run that never touched the soil (window [null, null]) was a TypeError, exit 1; its
    window prints as none, not 'nan .. nan s'."""
    import shutil

    _, out, code = cli_run
    folder = tmp_path / "run"
    shutil.copytree(out, folder, ignore=shutil.ignore_patterns(".lock"))
    info = json.loads((folder / "run.json").read_text())
    info["summary"].update(window=[None, None], slip=None)
    (folder / "run.json").write_text(json.dumps(info))
    assert main(["resume", str(folder), "--no-progress"]) == code
    printed = capsys.readouterr().out
    assert re.search(r"window +none \(no steady state: ", printed) and re.search(r"slip +nan", printed), printed


def test_no_library_chatter_on_the_output():
    """Warp's banner and module-load lines stay off stdout and stderr (unless --verbose)."""
    for args in (["--help"], ["plot", "--help"], ["advise", "--help"]):
        done = subprocess.run([sys.executable, "-m", "cosim", *args], capture_output=True, text=True, timeout=120)
        assert done.returncode == 0
        chatter = [
            line
            for line in (done.stdout + done.stderr).splitlines()
            if line.startswith(("Warp ", "Module ")) or "CUDA warning" in line
        ]
        assert not chatter, (args, chatter)


def test_a_worker_process_starts_warp_without_chatter():
    """A dask worker's task starts with soil.quiet_warp (cosim.study); on a machine without a GPU Warp's
    native library used to print its CUDA-driver warning once per worker, into the user's output."""
    code = "from soil import quiet_warp; quiet_warp(); import warp as wp; print(wp.get_device())"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() in ("cpu", "cuda:0"), done.stdout
    chatter = [line for line in done.stderr.splitlines() if line.startswith(("Warp ", "Module ")) or "CUDA" in line]
    assert not chatter, chatter


BROKEN_START = """
import os, warp as wp, soil
def broken():
    os.write(2, b"native: no device library\\n")
    raise RuntimeError("Warp failed to start")
wp.init = broken
try:
    soil.quiet_warp()
except RuntimeError as error:
    print("raised:", error)
os.write(2, b"stderr back\\n")
"""


def test_warp_failing_to_start_still_says_why():
    """quiet_warp holds back what Warp prints while it starts, and shows it when the start fails."""
    done = subprocess.run([sys.executable, "-c", BROKEN_START], capture_output=True, text=True, timeout=120)
    assert done.stdout.strip() == "raised: Warp failed to start", done
    assert done.stderr.splitlines() == ["native: no device library", "stderr back"], done.stderr


COLD_COMPILE = """
import tempfile, warnings
from cosim.cli import _setup_output
_setup_output(False)
import warp as wp
wp.config.kernel_cache_dir = tempfile.mkdtemp()  # a first compile, as on a new machine

@wp.kernel
def twice(a: wp.array(dtype=float)):
    a[wp.tid()] = 2.0 * a[wp.tid()]

x = wp.ones(4, dtype=float, device="cpu")
wp.launch(twice, dim=4, inputs=[x], device="cpu")
print(x.numpy().sum())
warnings.warn("a file of ours left open", ResourceWarning)
"""


def test_a_first_compile_leaves_no_warning_of_warps_at_exit(tmp_path):
    """Warp's compiler folders, left to the interpreter's exit after a first compile, say nothing on a
    newcomer's first run; other resource warnings still show."""
    script = tmp_path / "cold_compile.py"  # a file: Warp reads a kernel's source
    script.write_text(COLD_COMPILE)
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "8.0"
    assert "wp_pch_" not in done.stderr and "Implicitly cleaning up" not in done.stderr, done.stderr
    assert "a file of ours left open" in done.stderr


def test_no_warp_lines_during_a_run(tmp_path, tiny_bed):
    scene = write_tiny(tmp_path)
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "cosim",
            "run",
            scene,
            "--out",
            str(tmp_path / "o"),
            "--no-progress",
            "--set",
            f'bed.bed_file="{tiny_bed}"',
            "--set",
            "run.duration=0.01",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode in (0, 6), done.stderr
    chatter = [
        line
        for line in (done.stdout + done.stderr).splitlines()
        if line.startswith(("Warp ", "Module ")) or "CUDA warning" in line
    ]
    assert not chatter, chatter
    assert done.stdout.splitlines()[0].startswith(("complete:", "unsteady:"))


@pytest.mark.parametrize("case", ["out_below_a_file", "out_is_a_file"])
def test_bad_output_paths_are_one_clear_line(tmp_path, capsys, case):
    scene = write_tiny(tmp_path)
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    out = blocker / "run" if case == "out_below_a_file" else blocker
    assert main(["run", scene, "--out", str(out), "--no-progress"]) == 3
    err = capsys.readouterr().err
    assert str(blocker) in err and err.count("\n") == 1 and "Traceback" not in err


def test_a_full_disk_is_one_clear_line_with_the_path(tmp_path, tiny_bed, capsys, monkeypatch):
    from cosim import output

    def full(path, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(output.ResultsWriter, "create", full)
    scene = write_tiny(tmp_path)
    code = main(["run", scene, "--out", str(tmp_path / "run"), "--no-progress", "--set", f'bed.bed_file="{tiny_bed}"'])
    err = capsys.readouterr().err
    assert code == 5 and "No space left on device" in err and "results.h5" in err and "Traceback" not in err


@pytest.mark.parametrize("verbose", [False, True])
def test_an_internal_error_is_exit_1_not_bad_input(tmp_path, tiny_bed, capsys, monkeypatch, verbose):
    """A plain ValueError deep inside a run is a bug, not bad input: exit 1, one line naming the error
    (its traceback under --verbose), never the exit 2 of a bad scene."""
    from cosim import advice

    def broken(plan, *measured):
        raise ValueError("an internal check broke")

    monkeypatch.setattr(advice, "check", broken)
    scene = write_tiny(tmp_path)
    flags = ["--verbose"] if verbose else []
    argv = ["run", scene, "--out", str(tmp_path / "run"), "--no-progress", "--set", f'bed.bed_file="{tiny_bed}"']
    assert main(flags + argv) == 1
    err = capsys.readouterr().err
    assert "ValueError: an internal check broke" in err
    assert ("Traceback" in err) == verbose
    if not verbose:
        assert err.count("\n") == 1


ROUND_TRIP = """
import errno, importlib, pickle, pkgutil, sys

import cosim, rover_models, soil
from cosim.beds import SettlingDiverged
from cosim.folders import OutputExistsError
from cosim.plan import load_plan
from cosim.runner import RunInterrupted
from cosim.scene import SceneError
from soil.errors import RegolithError
from soil.stability import SimulationDiverged

for package in (soil, cosim, rover_models):
    for module in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
        if not module.name.endswith("__main__"):
            importlib.import_module(module.name)
# dask's import installs its own pickling of every exception (tblib): the errors' own must hold alone
assert "distributed" not in sys.modules


def subclasses(cls):
    for sub in cls.__subclasses__():
        yield sub
        yield from subclasses(sub)


cause = SimulationDiverged(
    "blew up", {"step": 7}, time=1.5, step=7, particle=3, position=(0.1, 0.2, 0.3), reason="non-finite"
)
examples = {  # the errors whose __init__ is their own
    SimulationDiverged: cause,
    SettlingDiverged: SettlingDiverged(cause, load_plan(sys.argv[1])),
    SceneError: SceneError(["soil.density: must be > 0", "run.duration: must be > 0"], source="a.toml"),
    RunInterrupted: RunInterrupted("stopped after a checkpoint", signal="SIGTERM"),
}
errors = sorted(set(subclasses(RegolithError)), key=lambda c: (c.__module__, c.__name__))
assert len(errors) >= 20, errors
for cls in errors:
    own_init = any("__init__" in vars(c) for c in cls.__mro__[: cls.__mro__.index(RegolithError)])
    assert cls in examples or not own_init, f"{cls.__name__} has its own __init__: add an example"
    error = examples.get(cls) or cls(f"a {cls.__name__} message")
    back = pickle.loads(pickle.dumps(error))
    assert type(back) is cls and str(back) == str(error) and vars(back) == vars(error), cls
assert pickle.loads(pickle.dumps(examples[SceneError])).problems == examples[SceneError].problems
back = pickle.loads(pickle.dumps(OutputExistsError(errno.EEXIST, "File exists", "/runs/a")))
assert (back.errno, back.filename) == (errno.EEXIST, "/runs/a")
print(len(errors), "errors round-trip")
"""


def test_every_project_error_crosses_a_process_as_itself(tmp_path):
    """The exit status follows the error's type, and errors are raised on other processes (a study's
    beds on dask workers, a batch's worlds behind a pipe): each of the project's errors pickles back to
    its own type, message and attributes (a scene's problems, a divergence's place, an interrupt's
    signal), whatever its __init__ takes. In a fresh interpreter: once dask is imported (as other
    tests do), its exception pickling stands in for the errors' own."""
    done = subprocess.run(
        [sys.executable, "-c", ROUND_TRIP, write_tiny(tmp_path)], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0 and "errors round-trip" in done.stdout, done.stderr[-3000:]


def test_a_bad_scene_field_is_exit_2_naming_it(tmp_path, capsys):
    scene = write_tiny(tmp_path)
    assert main(["run", scene, "--out", str(tmp_path / "run"), "--no-progress", "--set", "wheel.radius=-1"]) == 2
    err = capsys.readouterr().err
    assert "wheel.radius" in err and "Traceback" not in err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    "command, named",
    [
        (["run"], "give --replicas K"),
        (["study", "precision", "--replicas", "2"], "study precision` compares the summation orders"),
        (["study", "slip", "--replicas", "2", "--set", "terrain.model='analytic'"], "settles no bed of grains"),
    ],
)
def test_vary_bed_where_no_beds_can_vary_is_exit_2_naming_why(tmp_path, capsys, command, named):
    scene = write_tiny(tmp_path)
    args = command[:2] + [scene] + command[2:] if command[0] == "study" else command + [scene]
    assert main([*args, "--vary-bed", "--out", str(tmp_path / "o"), "--serial"]) == 2
    err = capsys.readouterr().err
    assert "--vary" in err and named in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_a_missing_cuda_device_is_exit_2(tmp_path, capsys):
    import warp as wp

    if wp.is_cuda_available():
        pytest.skip("this machine has a GPU")
    assert main(["run", write_tiny(tmp_path), "--out", str(tmp_path / "o"), "--device", "cuda"]) == 2
    assert "scene.device" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_a_wheel_that_never_touches_the_soil_is_reported(tmp_path, tiny_bed, capsys):
    """No landing and one macro step: the wheel starts just above the grains and never reaches them."""
    scene = write_tiny(tmp_path)
    code = main(
        [
            "run",
            scene,
            "--out",
            str(tmp_path / "air"),
            "--no-progress",
            "--set",
            f'bed.bed_file="{tiny_bed}"',
            "--set",
            "landing.enabled=false",
            "--set",
            "run.duration=0.0017",
        ]
    )
    assert code == 6
    captured = capsys.readouterr()
    assert "never touched the soil" in captured.out and "never touched the soil" in captured.err
    info = json.loads((tmp_path / "air" / "run.json").read_text())
    assert info["status"] == "unsteady" and info["summary"]["steady_state"] == "never touched the soil"
    assert "slip" not in info["summary"]  # no number is printed that the soil did not produce


def test_study_precision_on_a_local_cluster(tmp_path, tiny_bed):
    scene = write_tiny(tmp_path)
    out = tmp_path / "study"
    assert (
        main(
            [
                "study",
                "precision",
                scene,
                "--replicas",
                "2",
                "--precisions",
                "single,double",
                "--out",
                str(out),
                "--workers",
                "2",
                "--set",
                f'bed.bed_file="{tiny_bed}"',
                "--set",
                "run.duration=0.03",
            ]
        )
        == 6  # 0.03 s of driving: no replica steady (it was exit 0)
    )
    report = json.loads((out / "study.json").read_text())
    assert [r["precision"] for r in report["rows"]] == ["single", "double"]
    assert all(r["steady"] < r["replicas"] for r in report["rows"])
    assert report["units"]["sinkage_mean"] == "m" and report["units"]["drawbar_pull_ci95"] == "N"
    assert set(report["units"]) >= {k for k in report["rows"][0] if k.endswith(("_mean", "_ci95"))}
    assert all(r["replicas"] == 2 and r["failed"] == 0 for r in report["rows"])
    assert (out / "plots" / "scatter.png").is_file() and (out / "plots" / "travel_sinkage.png").is_file()
    assert (out / "study.csv").read_text().startswith("precision,")
    for precision in ("single", "double"):
        for k in range(2):
            assert (out / precision / f"replica_{k:03d}" / "results.h5").is_file()


def test_sweep_validates_every_point_first(tmp_path, tiny_bed, capsys):
    scene = write_tiny(tmp_path)
    out = tmp_path / "sweep"
    # a wheel wider than the bed is a bad scene: the sweep refuses before running anything
    assert main(["sweep", scene, "--param", "wheel.width=0.02,0.07", "--out", str(out), "--serial"]) == 2
    assert "point {'wheel.width': 0.07}" in capsys.readouterr().err and not out.exists()
    code = main(
        [
            "sweep",
            scene,
            "--param",
            "testbed.omega=0.5,1.0",
            "--set",
            f'bed.bed_file="{tiny_bed}"',
            "--set",
            "run.duration=0.01",
            "--out",
            str(out),
            "--serial",
        ]
    )
    # 0.01 s runs are not steady: the table is written, and exit 6 (a run without a steady-state result,
    # as a slip study's) says that not every value is a result to trust (it was exit 0)
    assert code == 6
    assert "(0 failed, 2 not steady of 2 points)" in capsys.readouterr().out
    report = json.loads((out / "study.json").read_text())
    assert [r["ok"] for r in report["rows"]] == [True, True]
    assert all(r["status"] != "complete" for r in report["rows"])
    assert report["units"]["sinkage"] == "m" and report["units"]["drawbar_pull"] == "N"
    header = (out / "study.csv").read_text().splitlines()[0]
    # the swept key's unit too; validity: each point's run's verdict
    assert header.startswith("testbed.omega [rad/s],ok,status,validity,steady_state,slip [1]"), header
    assert report["units"]["testbed.omega"] == "rad/s"
    # a path value names its point's folder without leading out of the sweep's (it was joined as a path);
    # a key both fixed by --set and swept is refused (the sweep's values replaced the fixed one)
    again = tmp_path / "paths"
    common = ["--set", "run.duration=0.01", "--out", str(again), "--serial"]
    relative = os.path.relpath(tiny_bed, os.path.dirname(scene))  # ../../<its folder>/bed.h5
    assert relative.startswith("..")
    assert main(["sweep", scene, "--param", f'bed.bed_file="{relative}"', *common]) == 6
    (point,) = [p for p in again.iterdir() if p.name.startswith("000_")]
    assert (point / "results.h5").is_file() and (point / "run.json").is_file()
    assert main(["sweep", scene, "--param", "testbed.omega=0.5", "--set", "testbed.omega=0.7", *common]) == 2
    assert "--set testbed.omega: also swept by --param" in capsys.readouterr().err
    # a key no point reads is refused: the imposed slip of a free carriage (the two points ran bit for bit
    # the same scene, two identical rows), the drawbar load of a driven one; read where the mode uses it
    unused = tmp_path / "unused"
    common = ["--set", "run.duration=0.01", "--out", str(unused), "--serial"]
    for param, mode, why in (
        ("testbed.slip=0.1,0.3", "free", "testbed.mode is 'free': the slip emerges"),
        ("testbed.drawbar_load=0.0,0.1", "slip", "testbed.mode is 'slip'"),
        ("testbed.drawbar_ramp=0.0,0.1", "slip", "testbed.mode is 'slip'"),
    ):
        assert main(["sweep", scene, "--param", param, "--set", f'testbed.mode="{mode}"', *common]) == 2, param
        assert f"--param {param.split('=')[0]}: no point of the sweep reads it ({why}" in capsys.readouterr().err
        assert not unused.exists()
    assert main(["sweep", scene, "--param", "testbed.mode=free,slip", "--set", "testbed.slip=0.2", *common]) == 6


def test_a_failed_task_is_reported_and_the_others_finish(tmp_path, tiny_bed):
    from cosim.study import Executor, run_task

    blocker = tmp_path / "file"
    blocker.write_text("x")
    text = Path(write_tiny(tmp_path)).read_text()
    overrides = {"bed.bed_file": str(tiny_bed), "run.duration": 0.01}
    tasks = [
        {"scene_toml": text, "overrides": overrides, "out_dir": str(blocker / "a"), "label": "bad"},
        {"scene_toml": text, "overrides": overrides, "out_dir": str(tmp_path / "b"), "label": "good"},
    ]
    with Executor("serial") as ex:
        bad, good = ex.map(run_task, tasks)
    assert not bad["ok"] and "a part of the path is a file" in bad["error"]
    assert good["ok"] and good["summary"]["macro_steps"] > 0


def test_a_disk_that_turns_read_only_mid_run_loses_nothing_written(tmp_path, tiny_bed, capsys, monkeypatch):
    """The second checkpoint cannot be written (EROFS): one clear line with the path and exit 5, no
    traceback; the first checkpoint and the rows it covers stay readable, and the run resumes from it."""
    from cosim import runner
    from cosim.output import open_results

    real = runner.write_checkpoint
    calls = []

    def read_only_after_first(path, data, units=None):
        calls.append(path)
        if len(calls) >= 2:
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real(path, data, units)

    monkeypatch.setattr(runner, "write_checkpoint", read_only_after_first)
    scene = write_tiny(tmp_path)
    out = tmp_path / "run"
    code = main(["run", scene, "--out", str(out), "--no-progress", "--set", f'bed.bed_file="{tiny_bed}"'])
    err = capsys.readouterr().err
    assert code == 5 and "Read-only file system" in err and "checkpoint" in err and "Traceback" not in err
    with open_results(out / "results.h5") as f:
        assert f["wheels/time"].shape[0] > 0
    monkeypatch.setattr(runner, "write_checkpoint", real)  # the disk is writable again
    assert main(["resume", str(out), "--no-progress"]) in (0, 6)
    with open_results(out / "results.h5") as f:
        time = f["wheels/time"][()]
    assert np.all(np.diff(time) > 0)  # no lost or duplicated rows


def test_plot_and_export_fmu_of_a_folder_that_is_not_a_run_are_bad_input(tmp_path, capsys):
    """A folder named as a run that holds none is the argument's fault: exit 2, naming the folder."""
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["plot", str(empty)]) == 2
    assert f"no results.h5 under {str(empty)!r}" in capsys.readouterr().err
    assert main(["export-fmu", str(empty), "--out", str(tmp_path / "soil.fmu")]) == 2
    assert "is not a run folder: it has no scene.toml" in capsys.readouterr().err
    assert os.listdir(empty) == [] and not (tmp_path / "soil.fmu").exists()


def test_sigterm_while_the_dask_cluster_starts_closes_it_whole_then_stops(monkeypatch, capsys):
    """A SIGTERM that lands inside LocalCluster's start used to leave it half-built, and dask's own
    exit hook then printed a traceback. It is held until the cluster is whole, which is then closed,
    and the command stops with the signal's exit status (143)."""
    import os
    import signal

    import dask.distributed

    from cosim.cli import _stop_on_signals
    from cosim.stop_signals import restore
    from cosim.study import Executor

    closed = []

    class StartingCluster:  # the signal arrives while the cluster starts
        def __init__(self, **kwargs):
            os.kill(os.getpid(), signal.SIGTERM)
            self.whole = True

        def close(self):
            closed.append("cluster" if self.whole else "half")

    class FakeClient:
        def __init__(self, cluster):
            self.cluster = cluster

        def close(self):
            closed.append("client")

    monkeypatch.setattr(dask.distributed, "LocalCluster", StartingCluster)
    monkeypatch.setattr(dask.distributed, "Client", FakeClient)
    previous = _stop_on_signals()
    try:
        with pytest.raises(KeyboardInterrupt, match="SIGTERM"), Executor("dask", workers=1):
            raise AssertionError("the block must not run after a SIGTERM")
    finally:
        restore(previous)
    assert closed == ["client", "cluster"]


@pytest.mark.parametrize(
    "command, named",
    [
        (["run", "--batched"], "--batched: does not apply here: one run runs in this process"),
        (["run", "--workers", "2"], "--workers: does not apply here: one run"),
        (["study", "timestep", "--slips", "0.1"], "--slips: does not apply here: `cosim study timestep` takes"),
        (["study", "timestep", "--serial"], "--serial: does not apply here"),
        (["study", "precision", "--duration", "0.1"], "--duration: does not apply here"),
        (["study", "slip", "--precisions", "double"], "--precisions: does not apply here"),
        (["study", "slip", "--include-sinking"], "--include-sinking: does not apply here"),
        (["study", "slip", "--from-runs", "RUNS", "--replicas", "5"], "--replicas: does not apply here"),
        (["study", "slip", "--serial", "--scheduler", "tcp://127.0.0.1:8786"], "--serial and --scheduler"),
        (["study", "slip", "--serial", "--workers", "2"], "--workers: sizes the LocalCluster started here"),
    ],
)
def test_an_option_the_command_ignores_is_refused(tmp_path, capsys, command, named):
    """An option silently ignored looks as if it had acted (`--slips` on a time-step study, `--workers`
    with `--serial`): exit 2 naming it, nothing made."""
    scene = str(write_tiny(tmp_path))
    runs = tmp_path / "runs"
    runs.mkdir()
    command = [str(runs) if part == "RUNS" else part for part in command]
    line = [*command[:2], scene, *command[2:]] if command[0] == "study" else [command[0], scene, *command[1:]]
    out = tmp_path / "out"
    assert main([*line, "--out", str(out), "--no-progress"] if command[0] == "run" else [*line, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cosim: error:") and named in err, err
    assert not out.exists()


@pytest.mark.parametrize(
    "option, words",
    [
        (["--workers", "0"], "--workers must be 1 .. "),
        (["--workers", "100000"], "--workers must be 1 .. "),
        (["--scheduler", "nonsense"], "--scheduler 'nonsense': not a dask scheduler address"),
        (["--scheduler", "tcp://[::1"], "--scheduler 'tcp://[::1': not a dask scheduler address"),
        (["--scheduler", "tcp://127.0.0.1:99999"], "port 99999 is not in 1..65535"),
        (["--scheduler", "tcp://256.1.1.1:1"], "--scheduler 'tcp://256.1.1.1:1': not a dask scheduler address"),
        (["--scheduler", ""], "--scheduler '': give the dask scheduler's address"),
    ],
)
def test_a_cluster_option_out_of_range_is_named(tmp_path, capsys, option, words):
    """--workers beyond 4 a core started processes for 10 minutes (signals held while they start), a
    malformed --scheduler was an unexpected error, a port or an address out of range was tried for
    dask's 30 s connect timeout (exit 5), an empty one ignored: all are bad arguments (exit 2), refused
    before the folder is made (it held the scene, and the same command again was refused: not empty)."""
    scene = str(write_tiny(tmp_path))
    out = tmp_path / "out"
    assert main(["run", scene, "--replicas", "2", "--out", str(out), "--no-progress", *option]) == 2
    assert words in capsys.readouterr().err
    assert not out.exists(), "nothing made before the arguments are checked"


@pytest.mark.parametrize(
    "address",
    ["tcp://127.0.0.1:8786", "127.0.0.1:8786", "tcp://[::1]:8786", "tls://host.example:8786", "ws://host", "wss://h:9"],
)
def test_a_scheduler_address_dask_connects_to_is_taken(address):
    """The address check refuses only what dask cannot connect to: hostnames, IPv6, TLS and websocket
    addresses (these may leave their port out) pass."""
    from cosim.study import check_executor

    check_executor("dask", address)


def test_a_scheduler_nothing_answers_at_is_refused_before_the_folder_is_made(tmp_path, capsys):
    """dask waited its 30 s connect timeout for a --scheduler where nothing listens, then exit 5 (an OS
    error) with the run folder made: now the address is tried first, exit 2 naming it, nothing made."""
    import socket

    with socket.socket() as closed:  # a port that was free a moment ago: the connection is refused
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]
    scene = str(write_tiny(tmp_path))
    out = tmp_path / "out"
    address = f"tcp://127.0.0.1:{port}"
    assert main(["run", scene, "--replicas", "2", "--scheduler", address, "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert f"--scheduler {address!r}: nothing takes a connection at 127.0.0.1:{port}" in err, err
    assert "dask scheduler" in err and "LocalCluster" in err, err
    assert not out.exists()


def test_a_scheduler_address_is_reached_or_named_within_its_timeout(monkeypatch):
    """A host that takes the connection passes (dask finds later whether a scheduler listens); an unknown host
    is named; an address no packet reaches is refused when the timeout ends, not after dask's 30 s (played by
    a connect that times out: networks differ in how they drop a packet, some sandboxes take every one)."""
    import socket

    from cosim.study import reach_scheduler

    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(1)
        reach_scheduler(f"tcp://127.0.0.1:{server.getsockname()[1]}", timeout=5.0)
    with pytest.raises(ArgumentError, match=r"the host 'no-such-host.invalid' is not known here"):
        reach_scheduler("tcp://no-such-host.invalid:8786", timeout=1.0)  # .invalid never resolves (RFC 2606)
    reach_scheduler(None)
    waited = []

    def silent(address, timeout):
        waited.append((address, timeout))
        raise TimeoutError("timed out")

    monkeypatch.setattr(socket, "create_connection", silent)
    with pytest.raises(ArgumentError, match=r"--scheduler 'tls://sched.example:8786': nothing answered within 0.2 s"):
        reach_scheduler("tls://sched.example:8786", timeout=0.2)
    assert waited == [(("sched.example", 8786), 0.2)]


def test_without_dask_a_command_on_dask_says_what_to_install(tmp_path, tiny_bed, capsys, monkeypatch):
    """dask is an extra ([study]): without it a replica run or a lab test was an unexpected error
    (ModuleNotFoundError, exit 1) after the folder was made; now exit 2 naming the extra and --serial."""
    import sys

    monkeypatch.setitem(sys.modules, "distributed", None)
    monkeypatch.setitem(sys.modules, "distributed.comm.addressing", None)
    scene = str(write_tiny(tmp_path))
    out = tmp_path / "out"
    assert main(["run", scene, "--replicas", "2", "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "pip install 'regolith-cosim[study]'" in err and "--serial" in err, err
    assert not out.exists()
    # batched replicas run in this process (automatic on a GPU): no dask needed, none asked for
    bed = [f"bed.bed_file={tiny_bed}", "run.duration=0.02"]
    args = ["run", scene, "--replicas", "2", "--batched", "--out", str(out), "--no-progress"]
    assert main([*args, *(x for key in bed for x in ("--set", key))]) in (0, 6), capsys.readouterr().err
    assert (out / "replica_001" / "results.h5").is_file()


def test_a_pid_dt_min_above_the_advised_dt_max_is_named_by_advise_and_by_the_soil(tmp_path, capsys):
    """run.dt_min alone, above the advised limit run.dt_max defaults to: advise printed the range 0.001 ..
    0.000286 s and passed; the run stopped with 'need 0 < dt_min <= dt_max', naming no default."""
    from helpers import write_tiny
    from soil import Material, Simulation, SoilBuilder, SoilInputError, StepController

    scene = write_tiny(tmp_path)
    assert main(["advise", scene, "--set", "run.step_control=pid", "--set", "run.dt_min=1e-3"]) == 2
    err = capsys.readouterr().err
    assert "run.dt_min: 0.001 s is longer than the PID's longest substep, run.dt_max unset: the advised" in err
    builder = SoilBuilder(gravity=9.81)
    builder.add_material(Material(youngs_modulus=1e6))
    builder.add_container((0, 0, 0), (0.1, 0.1, 0.1))
    builder.add_particle((0.05, 0.05, 0.05), 0.01)
    sim = Simulation(*builder.finalize(device="cpu"), integrator="jolt-beeman")
    with pytest.raises(SoilInputError, match=r"dt_min = 1.0 s and dt_max = \S+ s, unset: the advised limit"):
        sim.enable_step_control(StepController(dt_min=1.0))


def test_our_warnings_read_as_one_line_without_the_source_that_raised_them(capsys):
    """A RegolithWarning (an OverlapWarning while a bed opened at 1e3 m/s^2) printed its file's path, line
    number and source line."""
    import logging
    import warnings

    from cosim.cli import _setup_output
    from soil import OverlapWarning

    root, handlers = logging.getLogger(), logging.getLogger().handlers[:]
    shown = warnings.showwarning
    try:
        _setup_output(verbose=False)
        warnings.warn("3 contact(s) were created with an overlap", OverlapWarning, stacklevel=1)
    finally:
        logging.captureWarnings(False)
        warnings.showwarning = shown
        root.handlers[:] = handlers
    err = capsys.readouterr().err
    assert "warning: 3 contact(s) were created with an overlap\n" in err, err
    assert "OverlapWarning" not in err and "test_cli.py" not in err, err


def test_the_log_follows_sys_stderr_from_one_command_to_the_next(monkeypatch):
    """cosim.cli.main bound its log handler to sys.stderr as it was: a caller that replaced sys.stderr
    between two commands in one process (a test's capture, closed since) got 'I/O operation on closed
    file' tracebacks instead of the second command's lines."""
    import io
    import logging

    from cosim.cli import _setup_output

    root, handlers = logging.getLogger(), logging.getLogger().handlers[:]
    first, second = io.StringIO(), io.StringIO()
    try:
        monkeypatch.setattr(sys, "stderr", first)
        _setup_output(verbose=False)
        logging.getLogger("cosim.test").warning("one")
        first.close()
        monkeypatch.setattr(sys, "stderr", second)
        logging.getLogger("cosim.test").warning("two")
    finally:
        logging.captureWarnings(False)
        root.handlers[:] = handlers
    assert second.getvalue() == "two\n"
