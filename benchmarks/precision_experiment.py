"""The paper's precision experiment at CPU scale: does single precision lose what double and mixed keep?

At Phobos gravity, with a stiffness NOT adapted to milli-g (E = --stiff, default 1e8 Pa) the
grains' resting overlaps fall below the float32 resolution of their positions: single
precision should misjudge contacts (stick/slip, overlaps) and scatter. With the eq. 10
stiffness (the scene's own E) single precision should hold. For each stiffness and
precision, --replicas runs that differ only in the summation order (cosim study precision)
on one settled bed give the scatter of slip, sinkage and travel, and the wall time per
replica: the speed-accuracy table of BENCHMARKS.md, and plots like the paper's figures 3-4
(travel and sinkage over time, replicas overlaid, one panel per precision).

    python benchmarks/precision_experiment.py --scene benchmarks/scenes/precision_small.toml --replicas 4 \
        --out runs/precision [--workers 2] [--stiff 1e8] [--batched]

The stiff soil needs a DEM step about (E_stiff / E)^(2/5) x shorter: its run.dt is taken
from the Hertz contact time of the scene's impact speed at the stiff modulus (10 steps per
contact), and its bed is settled at that stiffness.
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


EXTRA_UNITS = {
    "youngs_modulus": "Pa",
    "dt": "s",
    "study_wall_time": "s",
    "landed_sinkage": "m",
    "final_sinkage": "m",
    "final_travel": "m",
    "drive_slip": "1",
    "replicas": "count",
    "steady": "count",
    "failed": "count",
}
"""The units of the rows' columns beside the study's metrics (cosim.study.METRIC_UNITS)."""


def row_units(rows: list[dict]) -> dict[str, str]:
    """The unit of each column of the rows that has one (precision_experiment.json's `units`)."""
    from cosim.study import METRIC_UNITS, column_units

    return column_units(list(rows[0]) if rows else [], {**METRIC_UNITS, **EXTRA_UNITS})


def stiff_overrides(plan, modulus: float) -> dict:
    """Scene overrides for the same scene with Young's modulus `modulus` [Pa] (grains and wheel) and a DEM
    step of a tenth of the grain-grain Hertz contact time at the scene's impact speed."""
    from soil import advisor

    spec = plan.bed.spec
    material = plan.soil_material
    smallest = spec.radius_min
    speed = math.sqrt(2 * plan.g * spec.depth) + plan.testbed.omega * plan.wheel.outer_radius
    contact = advisor.hertz_contact_time(modulus, material.poisson_ratio, material.density, smallest, speed)
    dt = contact / 10
    substeps = max(1, round(plan.macro_step / dt))
    rayleigh = advisor.rayleigh_time_step(modulus, material.poisson_ratio, material.density, smallest)
    return {
        "soil.youngs_modulus": modulus,
        "wheel.material.youngs_modulus": modulus,
        "run.dt": dt,
        "run.substeps": substeps,
        "run.dt_factor": None,
        "run.macro_step": None,
        "bed.settle_dt_factor": min(1.0, dt / rayleigh),
    }  # the bed settles with the run's step


END_KEYS = ("landed_sinkage", "final_sinkage", "final_travel", "drive_slip")
"""Per replica, from its results.h5: sinkage [m] at the end of the landing and over the last
tenth of the run, travel [m] at the end, slip [-] from mean speeds over the drive's second half.
The paper compares such trajectories over time, whether or not a run reached a steady state."""


def end_values(path: str) -> dict:
    import numpy as np

    from cosim.metrics import forward_speed, slip_of
    from cosim.output import read_series
    from cosim.single_wheel import PHASE_DRIVING

    s = read_series(path)
    drive = np.flatnonzero(s["phase"] == PHASE_DRIVING)
    sinkage = s["sinkage"][:, 0]
    last = max(1, len(sinkage) // 10)
    late = drive[len(drive) // 2 :] if len(drive) else drive
    rim = float(s["attrs"]["rim_radius"]) if "attrs" in s else None
    return {
        "landed_sinkage": float(sinkage[drive[0]]) if len(drive) else math.nan,
        "final_sinkage": float(sinkage[-last:].mean()),
        "final_travel": float(s["travel"][-1, 0]),
        "drive_slip": float(slip_of(forward_speed(s)[late].mean(), s["angular_velocity"][late, 0, 1].mean(), rim))
        if len(late) and rim
        else math.nan,
    }


def spread(ends: list[dict]) -> dict:
    """Mean, standard deviation (ddof 1), min and max over the replicas of each END_KEYS value."""
    import numpy as np

    out = {}
    for key in END_KEYS:
        values = np.array([e[key] for e in ends], dtype=float)
        values = values[np.isfinite(values)]
        out.update(
            {
                f"{key}_mean": float(values.mean()) if len(values) else math.nan,
                f"{key}_std": float(values.std(ddof=1)) if len(values) > 1 else math.nan,
                f"{key}_min": float(values.min()) if len(values) else math.nan,
                f"{key}_max": float(values.max()) if len(values) else math.nan,
            }
        )
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default=os.path.join(ROOT, "benchmarks", "scenes", "precision_small.toml"))
    parser.add_argument("--replicas", type=int, default=4)
    parser.add_argument("--stiff", type=float, default=1e8, help="the non-adapted Young's modulus [Pa]")
    parser.add_argument("--precisions", default="single,mixed,double")
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--serial", action="store_true")
    parser.add_argument(
        "--batched",
        action="store_true",
        help="each precision's replicas as worlds of one simulation (a replica's wall time: its time in the batch)",
    )
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--out", default="runs/precision")
    args = parser.parse_args(argv)

    import warp as wp

    wp.config.log_level = wp.LOG_ERROR
    from cosim.plan import load_plan
    from cosim.study import precision_study

    base = load_plan(args.scene, args.set)
    precisions = [p.strip() for p in args.precisions.split(",") if p.strip()]
    cases = {"adapted": base, "stiff": base.with_changes(**stiff_overrides(base, args.stiff))}
    rows = []
    for name, plan in cases.items():
        started = time.perf_counter()
        report = precision_study(
            plan,
            os.path.join(args.out, name),
            replicas=args.replicas,
            precisions=precisions,
            executor="serial" if args.serial else "dask",
            workers=args.workers,
            overwrite=True,
            batched=args.batched,  # off unless asked: the table's wall time is per replica run alone
        )
        wall = time.perf_counter() - started
        for row in report["rows"]:
            ends = [
                end_values(os.path.join(args.out, name, row["precision"], f"replica_{k:03d}", "results.h5"))
                for k in range(args.replicas)
            ]
            rows.append(
                {
                    "case": name,
                    "youngs_modulus": plan.soil_material.youngs_modulus,
                    "dt": plan.dt,
                    "study_wall_time": wall,
                    **{k: v for k, v in row.items() if k != "stats"},
                    **spread(ends),
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    with open(os.path.join(args.out, "precision_experiment.json"), "w") as f:
        json.dump(
            {
                "scene": args.scene,
                "overrides": args.set,
                "rows": rows,
                "replicas": args.replicas,
                "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
                "units": row_units(rows),
            },
            f,
            indent=2,
            default=float,
        )
    wall_column = "wall per replica, batched [s]" if args.batched else "wall per replica [s]"
    print(
        f"\n| E [Pa] | dt [s] | precision | steady | {wall_column} | landed sinkage [mm] | final sinkage [mm] "
        "| final travel [mm] (min..max) | slip, drive's 2nd half |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:

        def cell(key, scale=1e3, r=r):
            return f"{r[key + '_mean'] * scale:.4g} +- {r[key + '_std'] * scale:.2g}"

        print(
            f"| {r['youngs_modulus']:.3g} | {r['dt']:.3g} | {r['precision']} | {r['steady']}/{r['replicas']} | "
            f"{r.get('wall_time_mean', math.nan):.4g} | {cell('landed_sinkage')} | {cell('final_sinkage')} | "
            f"{cell('final_travel')} ({r['final_travel_min'] * 1e3:.3g}..{r['final_travel_max'] * 1e3:.3g}) | "
            f"{cell('drive_slip', 1.0)} |"
        )


if __name__ == "__main__":
    main()
