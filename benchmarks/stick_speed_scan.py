"""Angle of repose against the stick speed v_Tmin, at Earth gravity and on the Phobos twin.

With the passive stick/slip switch (docs/physics.md section 1.3) v_Tmin only selects the stick
or the slip angle; this scan measures how much that moves a heap. Scene:
benchmarks/scenes/heap_stick_scan.toml (650 grains, stick/slip 25/20 deg, rolling friction 0.1);
the twin has |g| = 5.7e-3 m/s^2 and E x s (s = 5.7e-3 / 9.80665), the same heap in DEM terms.
v_Tmin is given as a fraction of sqrt(|g| d) (d: the mean grain diameter, 4 mm).

    python benchmarks/stick_speed_scan.py --ratios 5e-6 5e-4 5e-3 5e-2 0.5 5e3 --replicas 2 --out runs/stick_scan

Writes OUT/stick_speed_scan.json and OUT/stick_speed_scan.png (and prints one line per point).
"""

import argparse
import json
import math
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from cosim.lab import repose_test  # noqa: E402
from cosim.lab.scene import lab_scene_from_text, resolve_lab  # noqa: E402

SCENE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "scenes", "heap_stick_scan.toml")
GRAVITY = {"earth": 9.80665, "phobos": 5.7e-3}
DIAMETER = 0.004  # [m] the scene's mean grain diameter


def scan(gravity: str, ratios, replicas: int, out: str) -> list[dict]:
    text = open(SCENE).read()
    s = GRAVITY[gravity] / GRAVITY["earth"]
    overrides = {"scene.gravity": GRAVITY[gravity], "soil.youngs_modulus": 2.0e5 * s, "lab.replicas": replicas}
    points = []
    for ratio in ratios:
        speed = ratio * math.sqrt(GRAVITY[gravity] * DIAMETER)
        start = time.time()
        plan = resolve_lab(lab_scene_from_text(text, overrides={**overrides, "soil.stick_speed": speed}))
        report = repose_test(plan, os.path.join(out, f"{gravity}_{ratio:g}"), executor="serial")
        angle = report["repose_angle_deg"]
        point = dict(gravity=gravity, ratio=ratio, stick_speed_m_s=speed, angle_deg=angle, wall_s=time.time() - start)
        print(json.dumps(point), flush=True)
        points.append(point)
    return points


def figure(points: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6))
    for gravity, marker in (("earth", "o"), ("phobos", "s")):
        rows = [p for p in points if p["gravity"] == gravity]
        if rows:
            ax.errorbar(
                [p["ratio"] for p in rows],
                [p["angle_deg"]["mean"] for p in rows],
                yerr=[p["angle_deg"]["std"] if p["angle_deg"]["n"] > 1 else 0 for p in rows],
                marker=marker,
                capsize=3,
                label=f"{gravity} ({GRAVITY[gravity]:g} m/s^2)",
            )
    ax.set_xscale("log")
    ax.set_xlabel("stick speed v_Tmin / sqrt(g d) [-]")
    ax.set_ylabel("angle of repose [deg]")
    ax.set_title("heap of 650 grains, stick/slip 25/20 deg (mean +- sd of replicas)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ratios", type=float, nargs="+", default=[5e-6, 5e-4, 5e-3, 5e-2, 0.5, 5e3])
    parser.add_argument("--gravities", nargs="+", default=["earth", "phobos"], choices=sorted(GRAVITY))
    parser.add_argument("--replicas", type=int, default=2)
    parser.add_argument("--out", default="runs/stick_scan")
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    points = [p for g in args.gravities for p in scan(g, args.ratios, args.replicas, args.out)]
    with open(os.path.join(args.out, "stick_speed_scan.json"), "w") as f:
        json.dump(points, f, indent=1)
    figure(points, os.path.join(args.out, "stick_speed_scan.png"))


if __name__ == "__main__":
    main()
