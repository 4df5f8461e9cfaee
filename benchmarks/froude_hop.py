"""Where does a driven wheel start to hop? A scan of the Froude number Fr = omega^2 r / g on the testbed.

The same scene (examples/phobos_single_wheel.toml unless --scene is given) is run after
landing at wheel speeds omega that give the Froude numbers of --froude, each on the same
settled bed and for the same number of wheel turns. For each the drive reports:

    airborne   fraction of the drive's macro steps with no grain touching the wheel [-]
    lift       largest height of the hub above its landed height during the drive / wheel radius [-]
    vz_rms     RMS vertical hub speed during the drive / sqrt(g r) [-]

The hop onset is the smallest Froude number at which the wheel leaves the soil
(airborne > 1 %). Before it, the slip starts to depend on the speed (the test stops being
quasi-static); cosim/advice.py sets FROUDE_LIMIT at the largest Froude number whose slip
matches the slowest run's (docs/validity.md).

    python benchmarks/froude_hop.py --froude 0.01 0.03 0.1 0.3 --turns 0.5 --out runs/froude_hop [--replicas 2]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default=os.path.join(ROOT, "examples", "phobos_single_wheel.toml"))
    parser.add_argument("--froude", type=float, nargs="+", default=[0.01, 0.03, 0.1, 0.3])
    parser.add_argument("--turns", type=float, default=0.5, help="wheel turns of each drive [-]")
    parser.add_argument("--replicas", type=int, default=1, help="summation orders per Froude number")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--out", default="runs/froude_hop")
    args = parser.parse_args(argv)

    import warp as wp

    wp.config.log_level = wp.LOG_ERROR
    from cosim.beds import settled_bed
    from cosim.launch import run_plan
    from cosim.output import read_series
    from cosim.plan import load_plan
    from cosim.single_wheel import PHASE_DRIVING

    base = load_plan(args.scene, args.set)
    os.makedirs(args.out, exist_ok=True)
    bed = settled_bed(base, args.out, progress=True)
    rows = []
    for froude in args.froude:
        omega = math.sqrt(froude * base.g / base.wheel.outer_radius)
        duration = args.turns * 2 * math.pi / omega
        for k in range(args.replicas):
            plan = base.with_changes(
                **{
                    "testbed.omega": omega,
                    "run.duration": duration,
                    "bed.bed_file": bed.path,
                    "run.order_seed": k,
                    "output.snapshot_interval": 0.0,
                    "output.checkpoint_interval": duration,
                }
            )
            out = os.path.join(args.out, f"fr_{froude:.3g}_{k}")
            started = time.perf_counter()
            result = run_plan(plan, out, overwrite=True)
            wall = time.perf_counter() - started
            s = read_series(os.path.join(out, "results.h5"))
            drive = s["phase"] == PHASE_DRIVING
            z = s["position"][:, 0, 2]
            landed = z[np.argmax(drive) - 1] if drive.any() else math.nan
            scale = math.sqrt(base.g * base.wheel.outer_radius)
            row = {
                "froude": froude,
                "omega": omega,
                "replica": k,
                "status": result.status,
                "steady_state": result.summary.get("steady_state"),
                "airborne": float(np.mean(s["contact_count"][drive, 0] == 0)) if drive.any() else math.nan,
                "lift": float((z[drive].max() - landed) / base.wheel.outer_radius) if drive.any() else math.nan,
                "vz_rms": float(np.sqrt(np.mean(s["linear_velocity"][drive, 0, 2] ** 2)) / scale)
                if drive.any()
                else math.nan,
                "slip": result.summary.get("slip"),
                "wall_time": wall,
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
    onset = min((r["froude"] for r in rows if r["airborne"] > 0.01), default=None)
    report = {
        "scene": args.scene,
        "overrides": args.set,
        "rows": rows,
        "onset": onset,
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.python_version()}",
        "units": {  # lift and vz_rms are scaled: by the outer radius r, by sqrt(g r)
            "froude": "1",
            "onset": "1",
            "omega": "rad/s",
            "replica": "1",
            "airborne": "1",
            "lift": "1",
            "vz_rms": "1",
            "slip": "1",
            "wall_time": "s",
        },
    }
    with open(os.path.join(args.out, "froude_hop.json"), "w") as f:
        json.dump(report, f, indent=2)
    print("\n| Fr | omega [rad/s] | airborne [-] | lift / r [-] | vz_rms / sqrt(g r) [-] | slip | status |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        slip = "-" if r["slip"] is None else f"{r['slip']:.3f}"
        print(
            f"| {r['froude']:.3g} | {r['omega']:.3g} | {r['airborne']:.3f} | {r['lift']:.3f} | {r['vz_rms']:.3f} "
            f"| {slip} | {r['steady_state']} |"
        )
    print(f"\nhop onset (airborne > 1 %): Fr = {onset}")


if __name__ == "__main__":
    main()
