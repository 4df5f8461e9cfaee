"""The speed-accuracy trade of the SCM tier against the DEM, for the main job's wheel.

For each case, an SCM calibration file is run at the slips of a DEM slip study (`cosim study
slip`: replicas, 95 % intervals) on the study's own scene with `[terrain] model = "scm"`, and
its DP/W, sinkage and torque / (W r) are compared with the DEM's at each slip: the difference,
the relative difference, and whether it is within the DEM's 95 % interval or within 15 %. Wall
time per simulated second of both comes from the runs' summaries (a loaded machine inflates
the DEM's; --timing measures both side by side on a quiet one).

    python benchmarks/scm_trade.py --out runs/scm_trade \
        --case "Phobos, lab-calibrated=runs/dem_phobos:examples/terrain/phobos_regolith_scm_beds.toml" \
        --case "Phobos, wheel-calibrated=runs/dem_phobos:wheel_phobos.toml" ... [--timing]

A case is NAME=DEM_STUDY:CALIBRATION[:SCENE]: SCENE (e.g. the DEM scene's gravity twin, `cosim
scale`) instead of the study's own; the comparison is dimensionless (DP/W, T / (W r); sinkage in m,
which a twin keeps). Writes trade.json, trade.csv (units in the header),
trade.png (DP/W, sinkage and torque against slip, DEM with error bars, one line per case) and
prints the tables BENCHMARKS.md quotes.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from cosim.folders import read_json_numbers, write_json  # noqa: E402 (after the path)
from cosim.lab.scm_wheel import RELATIVE_TOLERANCE as TOLERANCE  # noqa: E402 (after the path)
from cosim.metrics import SUMMARY_RULE, summary_is_current  # noqa: E402 (after the path)

QUANTITIES = (
    ("dp_over_w", "DP/W", "1"),
    ("sinkage", "sinkage", "m"),
    ("torque_over_wr", "T/(W r)", "1"),
)


def dem_rows(study_folder: str) -> tuple[dict, list[dict]]:
    """The DEM slip study's report and, per slip, mean and 95 % half-interval of each QUANTITY."""
    study = read_json_numbers(os.path.join(study_folder, "study.json"))  # not measured: nan
    if not summary_is_current(study):  # its means are of another window than the SCM runs compared with it
        raise SystemExit(
            f"{os.path.join(study_folder, 'study.json')}: a table of runs summarized under an older steady-window "
            f"rule (cosim.metrics.SUMMARY_RULE {SUMMARY_RULE}); `cosim resume` its study to make it again"
        )
    load = study["wheel_load"]
    from cosim.scene import scene_from_text

    rim = scene_from_text(study["scene_toml"]).wheel.radius
    rows = []
    for row in study["rows"]:
        averaged = row.get("averaged", row.get("steady", 0))
        if not averaged:
            continue
        rows.append(
            {
                "slip": row["slip_set"],
                "replicas": averaged,
                "steady": row.get("steady", 0),
                "dp_over_w": row["dp_over_w_mean"],
                "dp_over_w_ci95": row["dp_over_w_ci95"],
                "sinkage": row["sinkage_mean"],
                "sinkage_ci95": row["sinkage_ci95"],
                "torque_over_wr": row["driving_torque_mean"] / (load * rim),
                "torque_over_wr_ci95": row["driving_torque_ci95"] / (load * rim),
            }
        )
    return study, rows


def seconds_per_simulated_second(study: dict) -> float:
    """Mean wall time per simulated second over a study's completed runs [s/s]."""
    ratios = [
        r["summary"]["wall_time"] / r["summary"]["simulated_time"]
        for r in study.get("runs", [])
        if r.get("ok") and r.get("summary", {}).get("simulated_time")
    ]
    return sum(ratios) / len(ratios) if ratios else math.nan


def scm_study(study: dict, calibration: str, out_dir: str, scene: str | None = None) -> dict:
    """The DEM study's scene (or `scene`, e.g. its gravity twin) on the SCM calibration, one run per
    slip of the study (SCM is deterministic)."""
    from cosim import study as studies
    from cosim.plan import load_plan, resolve
    from cosim.scene import scene_from_text

    if scene:
        plan = load_plan(scene, on_scm(calibration))
    else:
        plan = resolve(scene_from_text(study["scene_toml"], overrides=on_scm(calibration)))
    slips = [row["slip_set"] for row in study["rows"]]
    runs = os.path.join(out_dir, "runs")
    studies.slip_study(plan, runs, slips, replicas=1, executor="serial", overwrite=True, plot=False)
    # tabulated as the DEM's: runs whose traction is steady count even where the sinkage drifts
    report = studies.slip_study_from_runs([runs], os.path.join(out_dir, "table"), True, False, include_sinking=True)
    report["runs_study"] = runs
    return report


def on_scm(calibration: str) -> dict:
    """Scene overrides that put the wheel on the SCM of a calibration file."""
    return {"terrain.model": "scm", "terrain.calibration": os.path.abspath(calibration)}


def compare(dem: list[dict], scm: list[dict]) -> list[dict]:
    """Per slip and quantity: DEM mean and interval, SCM value, difference, relative difference, agreement."""
    out = []
    for d in dem:
        s = next((r for r in scm if abs(r["slip"] - d["slip"]) < 1e-9), None)
        if s is None:
            continue
        row = {"slip": d["slip"], "scm_status": s.get("status", "steady")}
        for key, _, _ in QUANTITIES:
            difference = s[key] - d[key]
            relative = abs(difference) / abs(d[key]) if d[key] else math.inf
            row.update(
                {
                    f"{key}_dem": d[key],
                    f"{key}_dem_ci95": d[f"{key}_ci95"],
                    f"{key}_scm": s[key],
                    f"{key}_difference": difference,
                    f"{key}_relative": relative,
                    f"{key}_agrees": abs(difference) <= d[f"{key}_ci95"] or relative <= TOLERANCE,
                }
            )
        out.append(row)
    return out


def figure(path: str, dem_sets: dict, cases: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(QUANTITIES), figsize=(4.2 * len(QUANTITIES), 4.4))
    for (key, label, unit), ax in zip(QUANTITIES, axes):
        scale, shown = (1e3, "mm") if unit == "m" else (1.0, unit)
        for name, rows in dem_sets.items():
            ax.errorbar(
                [r["slip"] for r in rows],
                [scale * r[key] for r in rows],
                yerr=[scale * r[f"{key}_ci95"] for r in rows],
                fmt="o-",
                capsize=3,
                lw=2,
                label=f"DEM {name} (95 %)",
            )
        # the axis spans the DEM's intervals and SCM's steady values; a run with no steady state (a
        # wheel hopping on a too stiff soil) is drawn hollow, pinned to the edge where off the scale
        shown_values = [
            scale * (r[key] + sign * r[f"{key}_ci95"]) for rows in dem_sets.values() for r in rows for sign in (-1, 1)
        ]
        shown_values += [scale * r[f"{key}_scm"] for c in cases for r in c["comparison"] if r["scm_status"] == "steady"]
        low, high = min(shown_values), max(shown_values)
        pad = 0.15 * (high - low or 1.0)
        low, high = low - pad, high + pad
        for case in cases:
            rows = case["comparison"]
            (line,) = ax.plot(
                [r["slip"] for r in rows], [min(max(scale * r[f"{key}_scm"], low), high) for r in rows], "--"
            )
            for r in rows:
                value = scale * r[f"{key}_scm"]
                steady = r["scm_status"] == "steady"
                marker = "s" if low <= value <= high else ("^" if value > high else "v")
                ax.plot(
                    r["slip"],
                    min(max(value, low), high),
                    marker,
                    color=line.get_color(),
                    mfc=line.get_color() if steady else "none",
                )
            line.set_label(
                f"SCM {case['name']}"
                + ("" if all(r["scm_status"] == "steady" for r in rows) else " (hollow: not steady)")
            )
        ax.set_ylim(low, high)
        ax.set_xlabel("slip [-]")
        ax.set_ylabel(f"{label} [{shown}]")
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.tight_layout(rect=(0, 0.2, 1, 1))
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=7, frameon=False)
    fig.savefig(path, dpi=130)


def timing(study_folder: str, calibration: str, out_dir: str, duration: float | None = None, repeats: int = 3) -> dict:
    """SCM and DEM runs of the study's scene at its first slip, one after the other on this machine:
    wall time per simulated second of each (landing included; `duration` [s] of driving, default the
    study's own), each at its own coupling step (SCM's: cosim.scm_soil.scm_macro_step). SCM runs
    first, `repeats` times (its runs are equal to the bit; a run of seconds is at the mercy of the
    machine's other work: the median counts), then the DEM once (minutes: its noise averages out)."""
    import statistics

    from cosim.launch import run_plan
    from cosim.plan import resolve
    from cosim.scene import scene_from_text

    study = read_json_numbers(os.path.join(study_folder, "study.json"))  # not measured: nan
    base = {"testbed.mode": "slip", "testbed.slip": study["rows"][0]["slip_set"]}
    if duration is not None:
        base["run.duration"] = duration
    out = {}
    for name, extra, count in (("scm", on_scm(calibration), repeats), ("dem", {"bed.bed_file": study["bed_file"]}, 1)):
        plan = resolve(scene_from_text(study["scene_toml"], overrides={**base, **extra}))
        walls = []
        for _ in range(count):
            started = time.perf_counter()
            result = run_plan(plan, os.path.join(out_dir, f"timing_{name}"), overwrite=True)
            walls.append(time.perf_counter() - started)
        wall = statistics.median(walls)
        simulated = result.summary["simulated_time"]
        out[name] = {
            "wall_time_s": wall,
            "wall_times_s": walls,
            "simulated_s": simulated,
            "macro_step_s": plan.macro_step,
        }
        out[name]["seconds_per_simulated_second"] = wall / simulated
    out["ratio"] = out["dem"]["seconds_per_simulated_second"] / out["scm"]["seconds_per_simulated_second"]
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", action="append", default=[], help="NAME=DEM_STUDY:CALIBRATION[:SCENE] (repeatable)")
    parser.add_argument("--out", required=True)
    parser.add_argument("--timing", help="DEM_STUDY:CALIBRATION: time a DEM and an SCM run of it side by side")
    parser.add_argument(
        "--timing-duration", type=float, default=None, help="driving time of the timed runs [s] (default: the study's)"
    )
    args = parser.parse_args(argv)
    if not args.case and not args.timing:
        parser.error("give a --case, --timing or both")
    os.makedirs(args.out, exist_ok=True)
    cases, dem_sets = [], {}
    for index, text in enumerate(args.case):
        name, _, spec = text.partition("=")
        folder, calibration, *scene = spec.split(":")
        study, dem = dem_rows(folder)
        dem_sets.setdefault(os.path.basename(os.path.normpath(folder)), dem)
        started = time.perf_counter()
        report = scm_study(study, calibration, os.path.join(args.out, f"case_{index}"), scene[0] if scene else None)
        scm_rows = []
        load, rim = report["wheel_load"], scm_rim(report)
        for row in report["rows"]:
            if "dp_over_w_mean" in row:
                values = {k: row[f"{k}_mean"] for k in ("dp_over_w", "sinkage", "driving_torque")}
                status = "steady"
            else:  # no steady traction (e.g. a wheel hopping on a too stiff soil): the window's means, marked
                run_folder = f"slip_{row['slip_set']:+.3f}"
                summary = next(r["summary"] for r in report["runs"] if run_folder in r["out_dir"])
                values = {k: summary.get(k, math.nan) for k in ("dp_over_w", "sinkage", "driving_torque")}
                status = summary["steady_state"]
            scm_rows.append(
                {
                    "slip": row["slip_set"],
                    "dp_over_w": values["dp_over_w"],
                    "sinkage": values["sinkage"],
                    "torque_over_wr": values["driving_torque"] / (load * rim),
                    "status": status,
                }
            )
        comparison = compare(dem, scm_rows)
        cases.append(
            {
                "name": name,
                "dem_study": os.path.abspath(folder),
                "calibration": os.path.abspath(calibration),
                "scene": os.path.abspath(scene[0]) if scene else "the DEM study's",
                "comparison": comparison,
                "agreeing_slips": {k: sum(r[f"{k}_agrees"] for r in comparison) for k, _, _ in QUANTITIES},
                "slips": len(comparison),
                "dem_seconds_per_simulated_second": seconds_per_simulated_second(study),
                "scm_seconds_per_simulated_second": seconds_per_simulated_second(report),
                "scm_study_wall_s": time.perf_counter() - started,
            }
        )
    result = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.python_version()}",
        "tolerance": TOLERANCE,
        "cases": cases,
        "units": {  # of each case's comparison rows (the rest: "1"); the wall times' keys end in their unit
            f"comparison.{key}_{part}": unit
            for key, _, unit in QUANTITIES
            for part in ("dem", "dem_ci95", "scm", "difference")
        },
    }
    if args.timing:
        folder, _, calibration = args.timing.rpartition(":")
        result["timing"] = timing(folder, calibration, args.out, args.timing_duration)
    write_json(os.path.join(args.out, "trade.json"), result)
    if cases:
        write_csv(os.path.join(args.out, "trade.csv"), cases)
        figure(os.path.join(args.out, "trade.png"), dem_sets, cases)
    print(tables(result))


def scm_rim(report: dict) -> float:
    from cosim.scene import scene_from_text

    return scene_from_text(report["scene_toml"]).wheel.radius


def write_csv(path: str, cases: list[dict]) -> None:
    keys = ["slip"] + [f"{k}_{s}" for k, _, _ in QUANTITIES for s in ("dem", "dem_ci95", "scm", "relative", "agrees")]
    units = {"slip": "1", "sinkage_dem": "m", "sinkage_dem_ci95": "m", "sinkage_scm": "m"}
    with open(path, "w") as f:
        f.write(",".join(["case"] + [f"{k} [{units.get(k, '1')}]" for k in keys] + ["scm_status [-]"]) + "\n")
        for case in cases:
            for row in case["comparison"]:
                values = [json.dumps(case["name"])] + [f"{row[k]:.6g}" for k in keys] + [row["scm_status"]]
                f.write(",".join(values) + "\n")


def tables(result: dict) -> str:
    lines = []
    for case in result["cases"]:
        lines.append(f"\n{case['name']} (DEM: {case['dem_study']}, SCM: {case['calibration']})")
        lines.append("| slip | DP/W DEM | DP/W SCM | sinkage DEM [mm] | sinkage SCM [mm] | T/(W r) DEM | T/(W r) SCM |")
        lines.append("|---|---|---|---|---|---|---|")
        for r in case["comparison"]:
            mark = {k: "" if r[f"{k}_agrees"] else " x" for k, _, _ in QUANTITIES}
            lines.append(
                f"| {r['slip']:.2f} | {r['dp_over_w_dem']:+.3f} +- {r['dp_over_w_dem_ci95']:.3f} | "
                f"{r['dp_over_w_scm']:+.3f}{mark['dp_over_w']} | "
                f"{1e3 * r['sinkage_dem']:.2f} +- {1e3 * r['sinkage_dem_ci95']:.2f} | "
                f"{1e3 * r['sinkage_scm']:.2f}{mark['sinkage']} | "
                f"{r['torque_over_wr_dem']:.3f} +- {r['torque_over_wr_dem_ci95']:.3f} | "
                f"{r['torque_over_wr_scm']:.3f}{mark['torque_over_wr']} |"
                + ("" if r["scm_status"] == "steady" else f" SCM: {r['scm_status']}")
            )
        agree = ", ".join(f"{label} {case['agreeing_slips'][k]}/{case['slips']}" for k, label, _ in QUANTITIES)
        lines.append(
            f"agreeing (within the DEM's 95 % interval or {100 * result['tolerance']:.0f} %): {agree}; wall time per "
            f"simulated second: DEM {case['dem_seconds_per_simulated_second']:.3g} s, "
            f"SCM {case['scm_seconds_per_simulated_second']:.3g} s (x marks a disagreement)"
        )
    if "timing" in result:
        t = result["timing"]
        lines.append(
            f"\nside by side: DEM {t['dem']['seconds_per_simulated_second']:.3g} s, SCM "
            f"{t['scm']['seconds_per_simulated_second']:.3g} s per simulated second: SCM {t['ratio']:.0f}x faster"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    main()
