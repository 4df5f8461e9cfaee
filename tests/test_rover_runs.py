"""Rover runs end to end: the force balance on a slope and the stuck criterion, the same rover as MJCF and as
FMU, a drive-controller FMU against the Python controller it implements, bitwise resume (a moving patch;
an FMU rover with an FMU controller), the run folder's files and plots, and a sweep over controllers."""

import json
import math
import os
from pathlib import Path

import h5py
import numpy as np
import pytest

from cosim.beds import settled_bed
from cosim.cli import main
from cosim.launch import final_state, resume, run_plan
from cosim.output import documented_layout, open_results, read_series, xdmf_references
from cosim.plan import load_plan
from cosim.single_wheel import PHASE_DRIVING
from helpers import assert_checkpoint_units
from rover_helpers import MOON, RIG_BALLAST, RIG_CARRIAGE, RIG_WHEEL, write_rig, write_small_rover

pytest.importorskip("mujoco")


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("rover_runs")


@pytest.fixture(scope="module")
def rig_bed(folder):
    """The rig's 20 x 5 cm bed, settled once (cosim.beds caches it)."""
    return settled_bed(load_plan(write_rig(folder, name="bed")), str(folder / "rig_bed")).path


@pytest.fixture(scope="module")
def fmus(tmp_path_factory):
    pytest.importorskip("fmpy")
    pytest.importorskip("pythonfmu")
    from rover_models.fmu_src.build_fmus import build_rover_fmu, build_slip_controller_fmu

    out = tmp_path_factory.mktemp("rover_fmus")
    return {"rover": str(build_rover_fmu(out)), "controller": str(build_slip_controller_fmu(out, 4))}


# -- a slope ---------------------------------------------------------------------------------


def test_on_a_slope_the_forces_balance_slip_grows_and_the_stuck_criterion_fires(folder, rig_bed):
    """The rig driven uphill (gravity tilted about y) on slopes of 0, 10 and 20 deg with a grousered wheel,
    and on 20 deg with a smooth one. Physical bounds at steady state: the soil carries (ballast + wheel)
    g cos(slope) normal to the bed and pulls the whole rig uphill with (ballast + wheel + carriage)
    g sin(slope) (within 4 batch standard errors and 3 % of the weight: the rig's coupling error); the
    grousered wheel climbs every slope and is never immobile; the smooth wheel, whose grip is the
    friction of its rim, is past its traction limit on 20 deg (measured slip 0.96): the stuck
    criterion fires and it is immobile for most of the drive. Whether the grousered wheel's slip grows
    with the slope is not asserted: one 1.2 s run per slope cannot tell (measured with the passive
    stick/slip switch: 0.30, 0.47 and 0.31 at 0, 10 and 20 deg)."""
    runs = {}
    for name, slope, grousers in (("g0", 0, 8), ("g10", 10, 8), ("g20", 20, 8), ("smooth20", 20, 0)):
        scene = write_rig(folder, name=f"slope_{name}", slope_deg=slope, grousers=grousers, duration=1.2)
        if not grousers:
            text = (
                open(scene)
                .read()
                .replace("grouser_count = 0\ngrouser_height = 0.003\ngrouser_thickness = 0.002", "grouser_count = 0")
            )
            open(scene, "w").write(text)
        plan = load_plan(scene, [f'bed.bed_file="{rig_bed}"'])
        assert plan.slope == pytest.approx(math.radians(slope), abs=1e-12)
        runs[name] = (slope, run_plan(plan, str(folder / f"slope_{name}")).summary)
    weight = MOON * (RIG_BALLAST + RIG_WHEEL)
    for name, (slope, s) in runs.items():
        angle = math.radians(slope)
        normal = weight * math.cos(angle)
        pull = MOON * (RIG_BALLAST + RIG_WHEEL + RIG_CARRIAGE) * math.sin(angle)
        assert abs(s["normal_force"] - normal) < 0.03 * weight, (name, s["normal_force"], normal)
        assert abs(s["net_traction"] - pull) < 4 * s["net_traction_sem"] + 0.03 * weight, (name, s, pull)
    assert all(runs[name][1]["slip"] < 0.9 for name in ("g0", "g10", "g20"))
    assert all(runs[name][1]["time_immobile"] == 0 and not runs[name][1]["stuck"] for name in ("g0", "g10", "g20"))
    smooth = runs["smooth20"][1]
    assert smooth["stuck"] and smooth["steady_state"] == "stuck" and smooth["slip"] > 0.9
    assert smooth["time_immobile"] > 0.5 * 1.2


# -- the same rover as MJCF and as FMU -----------------------------------------------------------


def test_the_same_rover_as_mjcf_and_as_fmu_gives_the_same_traverse(folder, fmus):
    """The small MMX-like rover as the built-in MJCF (MuJoCo) and as the project's FMU (an independent
    rigid-body model of the same rover), each driven 0.4 s at 1.5 rad/s on the same three beds (bed.seed
    1-3): slip, sinkage and the wheels' load agree within the scatter between beds (the mean of the two
    models' differences on each bed within 3 of its standard errors, plus a floor of 0.02 in slip and a quarter grain
    radius in sinkage: what a user cannot tell apart), and the load is the rover's weight plus its
    vertical momentum change over the window (momentum balance). Summation orders on one bed would not
    do for the scatter: over 0.4 s their runs agree to 1e-6 in slip, while a window's mean slip moves by
    0.02 with any small change (the two models' own differences, another bed)."""
    beds = [
        settled_bed(
            load_plan(write_small_rover(folder, name="bed_small"), [f"bed.seed={seed}"]), str(folder / f"bed_{seed}")
        ).path
        for seed in (1, 2, 3)
    ]
    stats = {}
    for kind in ("mmx", "fmu"):
        values = []
        for k, bed in enumerate(beds):
            path = write_small_rover(folder, kind=kind, fmu=fmus["rover"], name=f"{kind}", duration=0.4)
            plan = load_plan(path, [f'bed.bed_file="{bed}"', f"bed.seed={k + 1}", f"run.order_seed={k}"])
            values.append(run_plan(plan, str(folder / f"{kind}_{k}")).summary)
        stats[kind] = values
    weight = load_plan(folder / "mmx.toml").rover.mass * MOON
    report = {}
    for name, floor in (("slip", 0.02), ("sinkage", 0.25 * 0.005), ("normal_force", 0.0)):
        a = np.array([s[name] for s in stats["mmx"]])
        b = np.array([s[name] for s in stats["fmu"]])
        error = float(np.std(a - b, ddof=1)) / math.sqrt(len(a))  # paired: the two models on each bed
        report[name] = [a.mean(), b.mean(), error]
        assert abs(a.mean() - b.mean()) <= 3 * error + floor, json.dumps(report)
    # the load is the weight plus what stops the rover's settling over the window (0.4 s of driving
    # after the landing is too short for it to be at rest: measured M dv_z / dt = 5-10 % of the weight)
    mass = load_plan(folder / "mmx.toml").rover.mass
    for kind in ("mmx", "fmu"):
        for seed, summary in enumerate(stats[kind]):
            with h5py.File(folder / f"{kind}_{seed}" / "results.h5", "r") as f:
                t, vz = f["rover/time"][:], f["rover/linear_velocity"][:, 2]
            start, end = summary["window"]
            settling = mass * (np.interp(end, t, vz) - np.interp(start, t, vz)) / (end - start)
            assert summary["normal_force"] == pytest.approx(weight + settling, abs=0.05 * weight), (kind, seed)


def test_the_rover_fmu_moves_as_the_mjcf_on_an_analytic_terrain(fmus):
    """The rover FMU and MuJoCo's MJCF of the same rover on the spring-damper terrain (cosim.terrain), driven
    at 2 rad/s for 1 s: the two models integrate the same equations of motion with the same implicit motor
    damping and step, about different reference points (the FMU the centre of mass, MuJoCo the body
    origin), so they agree to the integration error, far below what a wrong frame, sign or inertia would
    give (1e-2 of the motion)."""
    from cosim.controllers import ConstantSpeed
    from cosim.coupler import Coupler, stack_records
    from cosim.terrain import SpringDamperTerrain
    from rover_models.fmu_rover import FmuRover
    from rover_models.mjcf import MMX_WHEELS, mmx_rover_xml
    from rover_models.mujoco_rover import MujocoRover

    g = (0.0, 0.0, -9.81)

    def run(rover):
        soil = SpringDamperTerrain(0.1, 4, traction="slip", substeps=2, stiffness=2e5, damping=2000, slip_velocity=0.05)
        return stack_records(Coupler(soil, rover, 2e-3, gravity=g, controller=ConstantSpeed(2.0, 4)).run(1.0))

    a = run(MujocoRover(mmx_rover_xml(gravity=g), list(MMX_WHEELS), gravity=g))
    fmu = FmuRover(fmus["rover"], 4, gravity=g)
    b = run(fmu)
    fmu.close()
    for key in ("position", "linear_velocity", "angular_velocity"):
        scale = np.abs(a[key]).max()
        assert np.abs(a[key] - b[key]).max() < 1e-4 * scale, key
    assert a["position"][-1, 0, 0] - a["position"][0, 0, 0] > 0.15  # it drove


def test_the_slip_controller_fmu_commands_what_the_python_slip_controller_does(fmus):
    """cosim.fmu_controller.FmuController around the project's slip-controller FMU and
    cosim.controllers.SlipController with the same gains, fed the same wheel states at the same times
    (turned, moving and slipping wheels, a clamp at omega_min), command the same speeds to rounding."""
    from cosim.contract import WheelKinematics, WheelWrench
    from cosim.controllers import SlipController
    from cosim.fmu_controller import FmuController

    params = {"target_slip": 0.25, "wheel_radius": 0.05, "kp": 1.5, "ki": 10.0, "omega_min": 0.2, "omega_max": 6.0}
    fmu = FmuController(fmus["controller"], 4, start_values=params)
    python = SlipController(0.25, 0.05, 4, kp=1.5, ki=10.0, omega_min=0.2, omega_max=6.0)
    rng = np.random.default_rng(3)
    for step in range(40):
        t = 0.01 * step
        states = []
        for i in range(4):
            yaw = 0.3 * i
            q = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
            forward = np.array([math.cos(yaw), math.sin(yaw), 0.0])
            axle = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
            v = (0.05 + 0.05 * rng.random()) * forward if step % 7 else -0.01 * forward
            states.append(WheelKinematics([0, 0, 0.05], q, v, (1.0 + 2.0 * rng.random()) * axle))
        wrenches = [WheelWrench() for _ in range(4)]
        a, b = fmu(t, states, wrenches), python(t, states, wrenches)
        np.testing.assert_allclose(a.values, b.values, rtol=1e-12, atol=1e-12)
    fmu.close()


# -- checkpoints -------------------------------------------------------------------------------


def _same_run(a, b):
    state_a, state_b = final_state(str(a)), final_state(str(b))
    assert set(state_a) == set(state_b)
    for key in state_a:
        np.testing.assert_array_equal(state_a[key], state_b[key], err_msg=key)  # bitwise
    with open_results(a / "results.h5") as fa, open_results(b / "results.h5") as fb:
        for group in ("wheels", "rover", "soil", "particles"):
            for name in fa[group]:
                if hasattr(fa[group][name], "shape"):
                    np.testing.assert_array_equal(fa[group][name][()], fb[group][name][()], err_msg=name)
    # results.xdmf's data: rebuilt after the resume, the same snapshots
    with open_results(a / "results.xdmf.h5") as fa, open_results(b / "results.xdmf.h5") as fb:
        assert list(fa["snapshots"]) == list(fb["snapshots"])
        for name in fa["snapshots"]:
            for key in fa["snapshots"][name]:
                np.testing.assert_array_equal(fa["snapshots"][name][key][()], fb["snapshots"][name][key][()])


def _interrupted(plan, out, after=2):
    """Run, stop after the `after`-th checkpoint that falls in the drive, resume."""
    seen = []

    def stop(runner):
        if runner.drive_start_step >= 0:  # the controller has started: its state is in the checkpoint
            seen.append(runner.system.coupler.step_count)
        if len(seen) == after:
            raise KeyboardInterrupt("test: stopped after a checkpoint")

    with pytest.raises(KeyboardInterrupt):
        run_plan(plan, str(out), hooks={"checkpoint": stop})
    assert_checkpoint_units(out / "checkpoint.npz")
    with np.load(out / "checkpoint.npz") as data:
        stopped_at = {key: data[key] for key in data.files}
    resume(str(out))
    return stopped_at


PATCH = """
[patch]
length = 0.12
width = 0.12
band = 0.0115
clearance = 0.0115
"""


def test_resume_of_a_rover_on_a_moving_patch_is_bitwise(folder):
    """A rig on a moving patch, stopped after its second checkpoint in the drive (the window has moved by then
    and moves again after it) and resumed: every array of the final state and every dataset of results.h5 (the
    ragged particle snapshots included) equal an uninterrupted run's bit for bit."""
    scene = write_rig(
        folder,
        name="patch_resume",
        heading=20.0,
        speed=4.0,
        duration=1.6,
        length=0.1,
        width=0.1,
        radius=0.005,
        snapshots=0.3,
        checkpoints=0.5,
        extra=PATCH,
    )
    plan = load_plan(scene)
    baseline = run_plan(plan, str(folder / "patch_a"))
    assert baseline.summary["patch_moves"] >= 4
    stopped_at = _interrupted(plan, folder / "patch_b")
    assert 0 < int(stopped_at["soil/patch/moves"]) < baseline.summary["patch_moves"]
    _same_run(folder / "patch_a", folder / "patch_b")


def test_resume_of_an_fmu_rover_with_an_fmu_controller_is_bitwise(folder, fmus):
    """The rover FMU driven by the slip-controller FMU: both FMUs save and restore their state in the
    checkpoint, so the resumed run is the uninterrupted one bit for bit."""
    extra = f"""
[rover.controllers.fmu_slip]
kind = "fmu"
file = "{fmus["controller"]}"
start_values = {{target_slip = 0.3, wheel_radius = 0.025, omega_max = 3.0, omega_min = 0.3}}
"""
    scene = write_small_rover(
        folder,
        kind="fmu",
        fmu=fmus["rover"],
        name="fmu_resume",
        drive="fmu_slip",
        duration=0.3,
        checkpoints=0.2,
        extra=extra,
    )
    bed = settled_bed(load_plan(scene), str(folder / "small_bed")).path
    plan = load_plan(scene, [f'bed.bed_file="{bed}"'])
    run_plan(plan, str(folder / "fmu_a"))
    stopped_at = _interrupted(plan, folder / "fmu_b", after=1)
    assert stopped_at["rover/controller/fmu_state"].size > 0 and stopped_at["rover/model/fmu_state"].size > 0
    _same_run(folder / "fmu_a", folder / "fmu_b")


# -- the run folder ----------------------------------------------------------------------------


def test_a_rover_run_folder_has_documented_results_units_xdmf_and_plots(folder):
    """The patch run's results.h5 follows the documented (ragged) layout, every dataset has its unit, the
    XDMF points inside the datasets (grains, wheels, rover body), and `cosim plot` draws the trajectory
    and the wheels."""
    import h5py

    run = folder / "patch_a"
    if not (run / "results.h5").exists():
        pytest.skip("needs test_resume_of_a_rover_on_a_moving_patch_is_bitwise's run")
    with open_results(run / "results.h5") as f:
        assert f["particles"].attrs["layout"] == "ragged"
        mesh = f["wheels/mesh"]
        layout = documented_layout(
            wheels=1,
            particles=0,
            vertices=mesh["vertices"].shape[0],
            triangles=mesh["triangles"].shape[0],
            columns=f["rover/state"].shape[1],
            boundaries=f["boundaries/kind"].shape[0] if "boundaries" in f else 0,
            ragged=True,
        )
        found, missing_units = set(), []

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                found.add(name)
                if not obj.attrs.get("units"):
                    missing_units.append(name)

        f.visititems(visit)
        assert found == set(layout), (found - set(layout), set(layout) - found)
        assert not missing_units, missing_units
        counts, first = f["particles/count"][()], f["particles/first"][()]
        assert np.all(first[1:] == first[:-1] + counts[:-1]) and first[-1] + counts[-1] == f["particles/id"].shape[0]
        assert f.attrs["kind"] == "rover" and f["rover/position"].attrs["units"] == "m"
    for file, dataset, shape in xdmf_references(str(run / "results.xdmf")):
        with open_results(file) as f:
            assert f[dataset].shape == shape, dataset
    assert main(["plot", str(run)]) == 0
    for name in ("trajectory.png", "wheels.png"):
        assert os.path.getsize(run / "plots" / name) > 10_000
    series = read_series(run / "results.h5")
    driving = series["phase"] == PHASE_DRIVING
    assert np.all(np.isfinite(series["speed_command"][driving])) and np.all(np.isnan(series["torque_command"]))


def test_a_sweep_compares_controllers_side_by_side(folder, rig_bed):
    """`cosim sweep --param rover.drive=...` runs the scene once per named controller and tabulates their
    slip, travel, energy per metre and time immobile, each with its unit."""
    extra = """
[rover.controllers.slow]
kind = "speed"
speed = 1.0

[rover.controllers.fast]
kind = "speed"
speed = 2.5
"""
    scene = write_rig(folder, name="sweep", duration=0.6, extra=extra)
    text = Path(scene).read_text().replace('[rover.drive]\nkind = "speed"\nspeed = 2.0\n', "")
    text = text.replace('wheels = ["wheel"]\n', 'wheels = ["wheel"]\ndrive = "slow"\n')
    open(scene, "w").write(text)
    out = folder / "sweep_out"
    code = main(
        [
            "sweep",
            scene,
            "--param",
            "rover.drive=slow,fast",
            "--set",
            f'bed.bed_file="{rig_bed}"',
            "--serial",
            "--out",
            str(out),
        ]
    )
    statuses = [r["status"] for r in json.loads((out / "study.json").read_text())["rows"]]
    assert code == (0 if statuses == ["complete", "complete"] else 6), statuses  # 6: a point not steady
    header, *rows = (out / "study.csv").read_text().splitlines()
    assert header.startswith("rover.drive,ok,status,validity,steady_state,slip [1],travel [m]")
    assert "energy_per_metre [J/m]" in header and "time_immobile [s]" in header
    table = json.loads((out / "study.json").read_text())["rows"]
    assert [r["rover.drive"] for r in table] == ["slow", "fast"]
    assert table[1]["travel"] > table[0]["travel"]  # the faster drive goes farther in the same time
