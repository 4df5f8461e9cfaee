"""SCM's own coupling step against a finer one: the convergence behind cosim.scm_soil.BOUNCE_PHASE.

A scene on SCM alone couples at SCM's own step (cosim.scm_soil.scm_macro_step: 0.2 rad of the
wheel's elastic bounce, or a quarter node spacing of the grouser tips' travel) unless it sets
run.macro_step. This runs the scene on an SCM calibration at one imposed slip with the DEM's own
macro step (from the grains' Rayleigh time: what an SCM scene coupled at before) and at
the given steps, and prints DP/W, sinkage and torque of each, their difference from the DEM step's run
and the wall time (the same script, one run after the other).

    python benchmarks/scm_step.py examples/phobos_single_wheel.toml \
        --calibration examples/terrain/phobos_regolith_scm_wheel.toml --slip 0.2 --duration 10 \
        --steps own,0.01,0.02,0.04,0.08,0.16 --out runs/scm_step
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


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene")
    parser.add_argument("--calibration", required=True, help="SCM calibration file ([terrain] calibration)")
    parser.add_argument("--slip", type=float, default=0.2)
    parser.add_argument("--duration", type=float, default=10.0, help="driving after landing [s]")
    parser.add_argument("--steps", default="own,0.01,0.02,0.04", help="'own' or macro steps [s], comma-separated")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)

    from cosim.launch import run_plan
    from cosim.plan import load_plan
    from cosim.scm_soil import elastic_bounce, node_spacing, scm_parameters

    base = {
        "terrain.model": "scm",
        "terrain.calibration": os.path.abspath(args.calibration),
        "testbed.mode": "slip",
        "testbed.slip": args.slip,
        "run.duration": args.duration,
    }
    dem_step = load_plan(args.scene).macro_step
    rows = []
    for label in ["dem", *args.steps.split(",")]:
        overrides = dict(base)
        if label == "dem":
            overrides.update({"run.macro_step": dem_step, "run.substeps": None})
        elif label != "own":
            overrides.update({"run.macro_step": float(label), "run.substeps": None})
        else:
            overrides.update({"run.macro_step": None})
        plan = load_plan(args.scene, overrides)
        values = dict(plan.terrain.parameters)
        values["node_spacing"] = node_spacing(values, [plan.wheel])
        parameters = scm_parameters({"pressure_damping": 0.0, **values})
        omega, _ = elastic_bounce(parameters, plan.wheel, plan.wheel_load, plan.g)
        started = time.perf_counter()
        result = run_plan(plan, os.path.join(args.out, f"step_{label}"), overwrite=True)
        wall = time.perf_counter() - started
        s = result.summary
        rows.append(
            {
                "label": "DEM's macro step" if label == "dem" else label,
                "macro_step_s": plan.macro_step,
                "bounce_phase_rad": omega * plan.macro_step,
                "dp_over_w": s["dp_over_w"],
                "sinkage_m": s["sinkage"],
                "torque_n_m": s["driving_torque"],
                "wall_time_s": wall,
                "simulated_s": s["simulated_time"],
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    reference = rows[0]  # the DEM's macro step: what an SCM scene coupled at before it had its own
    print(f"\n{args.scene} on {args.calibration}, slip {args.slip}, {args.duration} s driving; {platform.machine()}")
    print("| macro step [s] | omega_e H [rad] | DP/W | sinkage [mm] | torque [uN m] ", end="")
    print("| dDP/W | dsinkage | dtorque | wall [s] |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        d_dp = r["dp_over_w"] - reference["dp_over_w"]
        d_z = (r["sinkage_m"] - reference["sinkage_m"]) / reference["sinkage_m"]
        d_t = (r["torque_n_m"] - reference["torque_n_m"]) / reference["torque_n_m"]
        name = f"{r['macro_step_s']:.4g} ({r['label']})" if not r["label"][0].isdigit() else f"{r['macro_step_s']:.4g}"
        print(
            f"| {name} | {r['bounce_phase_rad']:.3f} | {r['dp_over_w']:+.4f} | {1e3 * r['sinkage_m']:.3f} | "
            f"{1e6 * r['torque_n_m']:.3f} | {d_dp:+.4f} | {100 * d_z:+.2f} % | {100 * d_t:+.2f} % | "
            f"{r['wall_time_s']:.2f} |"
        )
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "scm_step.json"), "w") as f:
        json.dump({"rows": rows, "units": "SI; bounce_phase_rad = omega_e x macro step"}, f, indent=1)
    if not all(math.isfinite(r["dp_over_w"]) for r in rows):
        sys.exit(1)


if __name__ == "__main__":
    main()
