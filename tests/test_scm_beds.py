"""An SCM run's error bar over its calibration's beds (`cosim run SCENE --replicas K --vary-bed` on
[terrain] model = "scm"): replica k runs on the soil the calibration fitted on bed k ([source]
replica_fits), each replica carries its load at Bekker's sinkage for its own bed's soil, the
ensemble's scatter is the beds', and what cannot vary is refused, naming the file, before anything
is written."""

import json
import math

import numpy as np
import pytest
from test_scm_run import K_C, K_PHI, SMOOTH, N, _static_sinkage

from cosim.cli import main
from cosim.output import read_series
from cosim.plan import load_plan
from cosim.scene import SceneError
from cosim.scm_calibration import (
    SOIL_KEYS,
    CalibrationError,
    ScmCalibration,
    bed_soils,
    read_calibration,
    write_calibration,
)
from cosim.single_wheel import PHASE_LANDING
from cosim.study import replica_run
from helpers import write_tiny

SOIL = {
    "k_c": K_C,
    "k_phi": K_PHI,
    "n": N,
    "cohesion": 50.0,
    "friction_angle_deg": 30.0,
    "janosi_k": 0.002,
    "elastic_stiffness": 2.0e7,
}
BED_K_PHI = [0.5 * K_PHI, K_PHI, 2.0 * K_PHI]
"""Three beds' own k_phi: the beds' scatter a calibration over beds records."""
AT_REST = [*SMOOTH, "landing.speed_ratio=0.002"]
"""The smooth wheel, landed until it sinks at 1/10 of the default rest speed: on the softest bed the
default leaves it creeping 8 % short of Bekker's sinkage."""


def _calibration(fits: dict, gravity: float, wheel: dict | None = None) -> ScmCalibration:
    source = {"replica_fits": fits, **({"wheel": wheel} if wheel else {})}
    return ScmCalibration(dict(SOIL), {k: 0.0 for k in SOIL_KEYS}, gravity, source)


def _scene_on(tmp_path, fits: dict, extra: str = "") -> str:
    """The tiny scene on SCM from a calibration file (at the scene's gravity) holding `fits`."""
    g = load_plan(write_tiny(tmp_path, name="probe.toml")).g
    write_calibration(str(tmp_path / "cal.toml"), _calibration(fits, g))
    return write_tiny(tmp_path, f'\n[terrain]\nmodel = "scm"\ncalibration = "cal.toml"\n{extra}')


def test_each_bed_takes_its_own_fit_and_keeps_the_files_value_where_it_has_none():
    fits = {"k_phi": [1.0, 2.0, math.nan], "n": [0.9, 1.2, 1.0], "janosi_k": [0.001, 0.003, 0.004]}
    soils = bed_soils(_calibration(fits, 9.81, wheel={"fitted": ["janosi_k"]}))
    assert [s["k_phi"] for s in soils] == [1.0, 2.0, K_PHI]  # bed 2's fit failed: the file's value
    assert [s["n"] for s in soils] == [0.9, 1.2, 1.0]
    assert {s["janosi_k"] for s in soils} == {SOIL["janosi_k"]}  # fitted to the wheel over all beds
    assert all(s["k_c"] == K_C for s in soils)
    assert bed_soils(_calibration({}, 9.81)) == [] and bed_soils(_calibration({"n": [1.0]}, 9.81)) == []
    with pytest.raises(CalibrationError, match=r"c.toml: \[source.replica_fits\] n: must be a list of numbers"):
        bed_soils(_calibration({"n": ["a", 1.0]}, 9.81), "c.toml")
    with pytest.raises(CalibrationError, match=r"\[source.replica_fits\] k_x: not an SCM key"):
        bed_soils(_calibration({"k_x": [1.0, 2.0]}, 9.81))
    with pytest.raises(
        CalibrationError, match=r"c.toml: \[source.replica_fits\]: every key must hold one value per bed"
    ):
        bed_soils(_calibration({"k_phi": [1.0, 2.0], "n": [0.9, 1.2, 1.0]}, 9.81), "c.toml")  # would misalign


def test_a_wheel_fit_over_beds_gives_each_bed_its_own_wheel_fit_and_its_labs_held_keys():
    """A --from-wheel file over beds: bed k takes the wheel's fit on bed k ([source.wheel] replica_fits)
    for the keys the wheel fitted and the lab's fit of bed k for the others; the wheel's beds set the
    count (the lab's fourth bed had no wheel runs)."""
    lab = {"k_c": [10.0, 20.0, 30.0, 40.0], "k_phi": [1.0, 2.0, 3.0, 4.0]}
    wheel = {"fitted": ["k_phi", "n"], "replica_fits": {"k_phi": [5.0, 6.0, 7.0], "n": [0.3, math.nan, 0.5]}}
    soils = bed_soils(_calibration(lab, 9.81, wheel=wheel))
    assert [s["k_phi"] for s in soils] == [5.0, 6.0, 7.0] and [s["k_c"] for s in soils] == [10.0, 20.0, 30.0]
    assert [s["n"] for s in soils] == [0.3, N, 0.5]  # bed 1's wheel fit of n failed: the file's value
    bad = {**wheel, "replica_fits": {"n": "0.3"}}
    with pytest.raises(CalibrationError, match=r"w.toml: \[source.wheel.replica_fits\] n: must be a list"):
        bed_soils(_calibration(lab, 9.81, wheel=bad), "w.toml")


def test_replicas_over_the_calibrations_beds_carry_the_load_at_each_beds_bekker_sinkage(tmp_path):
    """Each replica is the wheel at rest on its own bed's soil: Bekker's sinkage for that bed's k_phi
    (theory, within the 6 % of the single-soil test), so the ensemble's scatter is the beds' own."""
    scene = _scene_on(tmp_path, {"k_phi": BED_K_PHI})
    plan = load_plan(scene, AT_REST)
    report = replica_run(plan, str(tmp_path / "beds"), 3, vary="bed", executor="serial")
    beds = report["calibration_beds"]
    assert [s["k_phi"] for s in beds["soils"]] == BED_K_PHI and beds["units"]["k_phi"] == "Pa m^(-n)"
    assert "SCM on calibration bed k's soil, cal.toml" in report["text"]
    json.loads((tmp_path / "beds" / "ensemble.json").read_text())  # written and readable
    rest = []
    for k, k_phi in enumerate(BED_K_PHI):
        run = tmp_path / "beds" / f"replica_{k:03d}"
        assert dict(load_plan(run / "scene.toml").terrain.parameters)["k_phi"] == k_phi
        series = read_series(run / "results.h5")
        landing = np.flatnonzero(series["phase"] == PHASE_LANDING)
        load = float(series["attrs"]["wheel_load"])
        expected = _static_sinkage(load, plan.wheel.rim_radius, plan.wheel.width, plan.wheel.width / 12, k_phi)
        rest.append(series["sinkage"][landing[-5:], 0].mean())
        np.testing.assert_allclose(rest[-1], expected, rtol=6e-2, err_msg=f"bed {k}")
    assert rest[0] > rest[1] > rest[2]  # the softer bed sinks deeper
    sinkage = report["stats"]["metrics"]["sinkage"]
    assert sinkage["n"] == 3 and sinkage["std"] > 0


def test_a_scene_key_wins_over_every_beds_fit(tmp_path):
    scene = _scene_on(tmp_path, {"k_phi": BED_K_PHI, "n": [0.9, 1.0, 1.1]}, extra=f"k_phi = {K_PHI}\n")
    report = replica_run(load_plan(scene, AT_REST), str(tmp_path / "beds"), 2, vary="bed", executor="serial")
    assert [sorted(s) for s in report["calibration_beds"]["soils"]] == [sorted(set(SOIL_KEYS) - {"k_phi"})] * 2
    for k, n in enumerate([0.9, 1.0]):
        parameters = dict(load_plan(tmp_path / "beds" / f"replica_{k:03d}" / "scene.toml").terrain.parameters)
        assert parameters["k_phi"] == K_PHI and parameters["n"] == n


@pytest.mark.parametrize(
    "fits, replicas, named",
    [
        ({}, 2, "holds no beds' own fits ([source] replica_fits): calibrate over beds"),
        ({"k_phi": BED_K_PHI}, 4, "was fitted on 3 beds ([source] replica_fits): at most 3 replicas"),
        ({"n": [1.0, -0.5]}, 2, "calibration bed 1's [source.replica_fits] n = -0.5: "),
    ],
)
def test_what_the_beds_cannot_give_is_refused_naming_the_file_before_anything_is_written(
    tmp_path, fits, replicas, named
):
    plan = load_plan(_scene_on(tmp_path, fits), SMOOTH)
    _assert_refused(tmp_path, plan, replicas, named)


def test_beds_that_differ_only_in_keys_the_scene_sets_itself_are_no_variation(tmp_path):
    """The scene's own k_phi wins over every bed's: beds whose fits differ only in k_phi would run one
    soil K times (an error bar of 0), so that is refused as a file without beds' own fits."""
    scene = _scene_on(tmp_path, {"k_phi": BED_K_PHI}, extra=f"k_phi = {K_PHI}\n")
    _assert_refused(tmp_path, load_plan(scene, SMOOTH), 2, "holds no beds' own fits ([source] replica_fits)")


def _assert_refused(tmp_path, plan, replicas: int, named: str) -> None:
    with pytest.raises(SceneError) as error:
        replica_run(plan, str(tmp_path / "beds"), replicas, vary="bed", executor="serial")
    assert any(named in p and "cal.toml" in p for p in error.value.problems), error.value.problems
    assert not (tmp_path / "beds").exists()


def test_replicas_over_summation_orders_alone_are_refused_on_scm_naming_vary_bed(tmp_path, capsys):
    """SCM sums in a fixed order: K replicas over summation orders would be one run K times, an
    error bar of 0. Refused (exit 2) before anything is written, naming --vary-bed."""
    from cosim.study import slip_study

    plan = load_plan(_scene_on(tmp_path, {"k_phi": BED_K_PHI}), SMOOTH)
    with pytest.raises(SceneError, match="sums in a fixed order.*add --vary-bed"):
        replica_run(plan, str(tmp_path / "order"), 2, executor="serial")
    with pytest.raises(SceneError, match="sums in a fixed order"):
        slip_study(plan, str(tmp_path / "order"), [0.1], replicas=2, executor="serial", plot=False)
    scene = write_tiny(tmp_path, '\n[terrain]\nmodel = "scm"\ncalibration = "cal.toml"\n', name="cli.toml")
    assert main(["run", scene, "--replicas", "2", "--serial", "--out", str(tmp_path / "order")]) == 2
    assert "--vary-bed" in capsys.readouterr().err and not (tmp_path / "order").exists()


def test_the_cli_runs_an_scm_scene_over_its_calibrations_beds(tmp_path, capsys):
    scene = _scene_on(tmp_path, {"k_phi": BED_K_PHI[:2]})
    out = tmp_path / "cli"
    code = main(["run", scene, "--replicas", "2", "--vary-bed", "--serial", "--out", str(out), *_sets(SMOOTH)])
    printed = capsys.readouterr().out
    assert code in (0, 4) and "SCM on calibration bed k's soil" in printed and "sinkage" in printed
    assert read_calibration(str(tmp_path / "cal.toml")).source["replica_fits"]["k_phi"] == BED_K_PHI[:2]


def _sets(overrides: list[str]) -> list[str]:
    return [item for o in overrides for item in ("--set", o)]


def test_a_mixed_rovers_replica_k_takes_bed_k_of_the_grains_and_of_the_calibration(tmp_path):
    """A rover with a wheel on the DEM and the others on SCM: replica k settles bed.seed + k for the
    DEM wheel and puts the SCM wheels on the soil calibration bed k gave (the plan of each replica)."""
    from cosim.study import _check_variation, _replica_overrides
    from rover_helpers import write_small_rover

    pytest.importorskip("mujoco")
    g = load_plan(write_small_rover(tmp_path, duration=0.02)).g
    write_calibration(str(tmp_path / "cal.toml"), _calibration({"k_phi": BED_K_PHI}, g))
    mixed = '\n[terrain]\nmodel = "scm"\ncalibration = "cal.toml"\nwheels = ["dem", "scm", "scm", "scm"]\n'
    plan = load_plan(write_small_rover(tmp_path, duration=0.02, extra=mixed))
    soils = _check_variation(plan, "bed", 2)
    for k in range(2):
        replica = plan.with_changes(**_replica_overrides(k, None, "bed", plan, soils))
        assert replica.terrain.model == "mixed" and replica.bed.spec.seed == plan.bed.spec.seed + k
        assert dict(replica.terrain.parameters)["k_phi"] == BED_K_PHI[k]


def test_a_slip_study_over_the_calibrations_beds_and_its_table_from_the_runs_say_so(tmp_path):
    """`cosim study slip --vary-bed` on SCM: replica k on bed k's soil at every slip; the table made
    again from the runs' folders (--from-runs) knows their soils from the runs' scenes alone."""
    from cosim.study import slip_study, slip_study_from_runs

    plan = load_plan(_scene_on(tmp_path, {"k_phi": BED_K_PHI[:2]}), SMOOTH)
    study = slip_study(plan, str(tmp_path / "slip"), [0.1, 0.3], replicas=2, vary="bed", executor="serial", plot=False)
    again = slip_study_from_runs([str(tmp_path / "slip")], str(tmp_path / "table"), plot=False)
    for report in (study, again):
        assert report["vary"] == "bed"
        assert [s["k_phi"] for s in report["calibration_beds"]["soils"]] == BED_K_PHI[:2]
    for k, k_phi in enumerate(BED_K_PHI[:2]):
        for slip in ("+0.100", "+0.300"):
            scene = tmp_path / "slip" / f"slip_{slip}" / f"replica_{k:03d}" / "scene.toml"
            assert dict(load_plan(scene).terrain.parameters)["k_phi"] == k_phi


def test_replicas_over_beds_give_how_many_of_them_were_out_of_range(tmp_path, capsys):
    """Replicas on the calibration's three beds, grains of 1.4 mm: the stiffest two beds' wheels sink
    under SCM's 3 grain diameters, the softest's not. The ensemble gives the failed check with how many
    of the replicas failed it, as their run.json say, in ensemble.json, ensemble.csv and the printed
    table (`cosim run --replicas` never read the runs' validity)."""
    import csv

    scene = _scene_on(tmp_path, {"k_phi": BED_K_PHI})
    out = tmp_path / "beds"
    args = ["run", scene, "--replicas", "3", "--vary-bed", "--serial", "--out", str(out)]
    assert main([*args, *_sets([*SMOOTH, "bed.radius_mean=0.0007"])]) in (0, 6)  # 6: the softest bed still sinks
    printed = capsys.readouterr().out
    failed = []
    for k in range(3):
        summary = json.loads((out / f"replica_{k:03d}" / "run.json").read_text())["summary"]
        failed.append([f["check"] for f in summary["findings"] if not f["ok"]])
    assert failed[0] == [] and failed[1] == failed[2] == ["scm_sinkage_grains"], failed  # the scene as meant
    expected = "out of range: scm_sinkage_grains (2/3)"
    ensemble = json.loads((out / "ensemble.json").read_text())
    assert ensemble["validity"] == ensemble["stats"]["validity"] == expected
    with open(out / "ensemble.csv", newline="") as f:
        assert {r["validity"] for r in csv.DictReader(f)} == {expected}
    assert any(line.startswith(f"  ! {expected}:") for line in printed.splitlines()), printed
