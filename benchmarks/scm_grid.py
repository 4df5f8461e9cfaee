"""SCM's node grid against a grousered wheel: how the spacing h sets the drawbar pull's beat.

Each node casts one vertical ray onto the wheel, so a grouser thinner than a few spacings is
sampled, not resolved: as the wheel advances by one grouser pitch on the ground, p = (1 - s) 2 pi r / N,
the grousers meet the nodes at a phase that moves by frac(p / h) of a spacing, and the forces beat
with the period T_g / dist(p / h, nearest integer), T_g = 2 pi / (N omega) the grousers' passage.
A mean over a window shorter than a few beats carries part of one: the window's phase sets it.

For each spacing (as a fraction of the grouser thickness t) and slip, the scene runs `--duration`
seconds of driving on SCM; over the drive after its first `--skip` seconds it reports the mean and
standard deviation of DP/W and of the rim sinkage, the largest spectral line of DP/W (its period and
amplitude), the predicted beat period, and the range of the means over every window of `--window`
seconds (starting each half second): what one run of that length could have printed.

    python benchmarks/scm_grid.py --out runs/scm_grid \
        --scene examples/phobos_single_wheel_scm.toml \
        --set terrain.calibration='"terrain/phobos_regolith_scm_wheel.toml"' \
        --ratios 1.333 0.9 0.667 0.45 0.3 --slips 0.1 0.4 --duration 60

Writes grid.json, grid.csv (units in the header), grid.png (DP/W against time at the first slip, each
spacing's 1 s and `--window` running means) and prints the table BENCHMARKS.md quotes.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

COLUMNS = (
    ("spacing_over_thickness", "1"),
    ("node_spacing", "m"),
    ("slip", "1"),
    ("dp_over_w_mean", "1"),
    ("dp_over_w_std", "1"),
    ("sinkage_mean", "m"),
    ("sinkage_std", "m"),
    ("line_period", "s"),
    ("line_amplitude", "1"),
    ("beat_period", "s"),
    ("window_mean_low", "1"),
    ("window_mean_high", "1"),
    ("wall_time", "s"),
)


def beat_period(pitch: float, spacing: float, passage: float) -> float:
    """T_g / dist(p / h, nearest integer) [s]: the grousers' passage period T_g [s] over the distance of
    the ground pitch p [m] in node spacings h [m] from a whole number (inf when they are commensurate)."""
    ratio = pitch / spacing
    distance = abs(ratio - round(ratio))
    return passage / distance if distance > 0 else math.inf


def measure(scene: str, overrides: list[str], ratio: float, slip: float, args, out: str) -> dict:
    """One run at node spacing `ratio` x the grouser thickness and imposed `slip`: the row's COLUMNS."""
    from cosim.launch import run_plan
    from cosim.output import read_series
    from cosim.plan import load_plan
    from cosim.single_wheel import PHASE_DRIVING

    probe = load_plan(scene, overrides)
    thickness = probe.wheel.shape.grouser_thickness
    spacing = ratio * thickness
    plan = load_plan(
        scene,
        [*overrides, f"terrain.node_spacing={spacing!r}", f"testbed.slip={slip!r}", f"run.duration={args.duration!r}"],
    )
    start = time.perf_counter()
    run_plan(plan, os.path.join(out, f"h{ratio:g}_s{slip:g}"), overwrite=True)
    wall = time.perf_counter() - start
    series = read_series(os.path.join(out, f"h{ratio:g}_s{slip:g}", "results.h5"))
    t = np.asarray(series["time"], dtype=float)
    driving = np.flatnonzero(np.asarray(series["phase"]) == PHASE_DRIVING)
    begin = t[driving[0]] + args.skip
    kept = (t >= begin) & (np.arange(len(t)) >= driving[0])
    dp = np.asarray(series["drawbar_pull"])[kept, 0] / plan.wheel_load
    sinkage = np.asarray(series["sinkage"])[kept, 0]
    time_kept = t[kept]
    step = float(np.median(np.diff(time_kept)))
    power = np.abs(np.fft.rfft(dp - dp.mean())) ** 2
    frequency = np.fft.rfftfreq(len(dp), step)
    line = int(np.argmax(power[1:])) + 1
    windows = [
        float(dp[(time_kept >= a) & (time_kept < a + args.window)].mean())
        for a in np.arange(time_kept[0], time_kept[-1] - args.window + step, 0.5)
    ]
    shape = plan.wheel.shape
    omega = plan.scene.testbed.omega
    passage = 2 * math.pi / (shape.grouser_count * omega)
    pitch = (1 - slip) * 2 * math.pi * shape.radius / shape.grouser_count
    return {
        "spacing_over_thickness": ratio,
        "node_spacing": spacing,
        "slip": slip,
        "dp_over_w_mean": float(dp.mean()),
        "dp_over_w_std": float(dp.std()),
        "sinkage_mean": float(sinkage.mean()),
        "sinkage_std": float(sinkage.std()),
        "line_period": float(1 / frequency[line]),
        "line_amplitude": float(2 * math.sqrt(power[line]) / len(dp)),
        "beat_period": beat_period(pitch, spacing, passage),
        "window_mean_low": min(windows),
        "window_mean_high": max(windows),
        "wall_time": wall,
    }


def plot(out: str, ratios: list[float], slip: float, window: float) -> None:
    """grid.png: DP/W against the time of driving at `slip`, one colour per spacing ratio (thin: 1 s
    running means; thick: `window` running means, the averages one run of that length could print)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cosim.output import read_series
    from cosim.single_wheel import PHASE_DRIVING

    fig, ax = plt.subplots(figsize=(9, 4.5))
    for ratio, colour in zip(ratios, plt.rcParams["axes.prop_cycle"].by_key()["color"] * 4):
        series = read_series(os.path.join(out, f"h{ratio:g}_s{slip:g}", "results.h5"))
        driving = np.asarray(series["phase"]) == PHASE_DRIVING
        t = np.asarray(series["time"], dtype=float)[driving]
        t = t - t[0]
        dp = np.asarray(series["drawbar_pull"])[driving, 0] / float(series["attrs"]["wheel_load"])
        step = float(np.median(np.diff(t)))
        for span, width, label in ((1.0, 0.6, None), (window, 2.0, f"h = {ratio:g} t")):
            n = max(1, int(round(span / step)))
            mean = np.convolve(dp, np.ones(n) / n, mode="valid")
            ax.plot(t[n - 1 :], mean, lw=width, color=colour, alpha=1.0 if label else 0.4, label=label)
    ax.set_xlabel("time of driving [s]")
    ax.set_ylabel("DP/W [1]")
    ax.set_title(f"SCM, grousered wheel at slip {slip:g}: 1 s (thin) and {window:g} s (thick) running means")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "grid.png"), dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default=os.path.join(ROOT, "examples", "phobos_single_wheel_scm.toml"))
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="a scene key=value")
    parser.add_argument("--ratios", type=float, nargs="+", default=[1.333, 0.9, 0.667, 0.45, 0.3])
    parser.add_argument("--slips", type=float, nargs="+", default=[0.1, 0.4])
    parser.add_argument("--duration", type=float, default=60.0, help="[s] of driving")
    parser.add_argument("--skip", type=float, default=3.5, help="[s] of driving left out at its start")
    parser.add_argument("--window", type=float, default=10.0, help="[s] the windows' length")
    parser.add_argument("--out", default="runs/scm_grid")
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    rows = [measure(args.scene, args.overrides, r, s, args, args.out) for s in args.slips for r in args.ratios]
    with open(os.path.join(args.out, "grid.json"), "w") as f:
        json.dump({"args": vars(args), "units": dict(COLUMNS), "rows": rows}, f, indent=1)
    with open(os.path.join(args.out, "grid.csv"), "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow([f"{name} [{unit}]" for name, unit in COLUMNS])
        writer.writerows([[row[name] for name, _ in COLUMNS] for row in rows])
    plot(args.out, args.ratios, args.slips[0], args.window)
    print(
        "| slip | h / t | h [mm] | DP/W mean +- std | sinkage [mm] mean +- std | largest line: period [s], amplitude "
        f"| beat [s] | {args.window:g}-s windows' DP/W | wall [s] |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['slip']:g} | {r['spacing_over_thickness']:g} | {r['node_spacing'] * 1e3:.3g} "
            f"| {r['dp_over_w_mean']:+.3f} +- {r['dp_over_w_std']:.3f} "
            f"| {r['sinkage_mean'] * 1e3:.2f} +- {r['sinkage_std'] * 1e3:.2f} "
            f"| {r['line_period']:.2f}, {r['line_amplitude']:.3f} | {r['beat_period']:.3g} "
            f"| {r['window_mean_low']:+.3f} .. {r['window_mean_high']:+.3f} | {r['wall_time']:.1f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
