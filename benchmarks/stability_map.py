"""Where the numerics hold: a soil's small pile over a grid of the numbers that decide stability.

For one soil (--soil phobos: soil.bed.PHOBOS_REGOLITH, the main job's grains; --soil lammps:
the grains of the LAMMPS comparison bed, benchmarks/beds.py; --soil SCENE.toml: that scene's
[soil]) each point of the grid

    gravity [m/s^2] x Young's modulus [Pa] x grain radius [m] x step factor x precision x method

runs a pile of 27 grains (3 x 3 x 3, radius 0.9..1 x r, friction, damping and rolling as the
soil has them) in a box, dropped by two radii onto each other and the floor (an impact at
once, then resting contacts), for 400 advised steps of simulated time. The step is
factor x the advisor's dt_max (soil.advisor.recommended_time_step); method is
velocity-verlet or jolt-beeman at that fixed step, or jolt-beeman with the PID step control
on the device (Simulation.macro_step_adaptive, tolerance --tol) allowed factor x dt_max as
its longest step. Each point is classified

- stable:   finite, and the total energy (kinetic + gravity + elastic) never rises above its
            start by more than --drift x (kinetic energy at the start + M g r);
- drift:    finite, but the energy rose above that bound (the integrator pumps energy in);
- diverged: the divergence monitor stopped it (soil.stability: non-finite, speed, overlap or
            energy bound; the table says when and why).

Writes stability_<soil>.csv (one row per point: class, when/why, force evaluations, energy
drift) and stability_<soil>.png (one panel per method and factor: E against g, a marker per
radius, coloured by class) to --out, and prints a markdown table plus the points where the
advisor's own step (factor 1) is not stable.

    python benchmarks/stability_map.py --soil phobos                 # small grid, ~1 min on a 2-core CPU
    python benchmarks/stability_map.py --soil examples/earth_single_wheel.toml   # a scene's soil
    python benchmarks/stability_map.py --soil phobos --grid medium   # every axis, factors 1 and 4 only
    python benchmarks/stability_map.py --soil lammps --grid full     # every axis at full resolution
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import itertools
import math
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402

from soil import ContactLaw, JoltBeeman, Simulation, SoilBuilder, StepController, VelocityVerlet, advisor  # noqa: E402
from soil.bed import PHOBOS_REGOLITH  # noqa: E402
from soil.stability import SimulationDiverged  # noqa: E402

GRIDS = {
    "small": dict(
        gravity=(1e-4, 5.7e-3, 30.0),
        youngs_modulus=(1e4, 1e6, 1e9),
        radius=(1e-4, 1e-2),
        factor=(1.0, 4.0),
        precision=("double",),
        method=("velocity-verlet", "jolt-beeman", "pid"),
    ),
    "medium": dict(
        gravity=(1e-4, 5.7e-3, 1.62, 9.81, 30.0),
        youngs_modulus=(1e4, 1e5, 1e6, 1e7, 1e8, 1e9),
        radius=(1e-4, 1e-3, 1e-2),
        factor=(1.0, 4.0),
        precision=("single", "double"),
        method=("velocity-verlet", "jolt-beeman", "pid"),
    ),
    "full": dict(
        gravity=(1e-4, 5.7e-3, 1.62, 9.81, 30.0),
        youngs_modulus=(1e4, 1e5, 1e6, 1e7, 1e8, 1e9),
        radius=(1e-4, 1e-3, 1e-2),
        factor=(0.5, 1.0, 2.0, 4.0),
        precision=("single", "double"),
        method=("velocity-verlet", "jolt-beeman", "pid"),
    ),
}
ADVISED_STEPS = 400
"""Simulated time of a point, in advised steps (~25 contact times of the drop's impact)."""


def soil_material(name: str):
    """The soil's grains: 'phobos', 'lammps', or a scene file's soil (cosim.plan: [soil])."""
    if name == "phobos":
        return PHOBOS_REGOLITH
    if name == "lammps":
        from benchmarks.beds import material

        return material()
    from cosim.plan import load_plan

    return load_plan(name).soil_material


def pile(material, gravity: float, radius: float, precision: str, seed: int = 3) -> Simulation:
    """27 grains in a 3 x 3 x 3 stack in a box, every grain moving down at sqrt(2 g 2r)."""
    builder = SoilBuilder(gravity=gravity)
    mat = builder.add_material(material)
    r = radius
    builder.add_container((0, 0, 0), (7.5 * r, 7.5 * r, 60 * r), mat)
    rng = np.random.default_rng(seed)
    k = np.arange(27)
    lattice = np.stack([k % 3, (k // 3) % 3, k // 9], 1)
    positions = np.array([1.3 * r, 1.3 * r, 1.2 * r]) + lattice * np.array([2.45 * r, 2.45 * r, 2.3 * r])
    positions += rng.uniform(-0.15 * r, 0.15 * r, positions.shape)
    positions[:, 2] = np.maximum(positions[:, 2], r)
    speed = math.sqrt(2 * gravity * 2 * r)
    builder.add_particles(positions, r * rng.uniform(0.9, 1.0, 27), mat, velocities=(0, 0, -speed))
    law = ContactLaw(rolling=material.rolling_friction > 0, cohesion=material.cohesion > 0)
    model, state, control = builder.finalize("cpu", precision, law=law)
    return Simulation(model, state, control, integrator=VelocityVerlet())


def total_energy(sim: Simulation) -> float:
    return sim.kinetic_energy() + sim.gravity_energy() + sim.elastic_energy()


def run_point(soil: str, gravity, youngs_modulus, radius, factor, precision, method, tol, drift_bound) -> dict:
    material = dataclasses.replace(soil_material(soil), youngs_modulus=youngs_modulus)
    sim = pile(material, gravity, radius, precision)
    advice = advisor.recommended_time_step(sim)
    dt = factor * advice.dt_max
    if method != "velocity-verlet":
        sim.integrator = JoltBeeman()
    if method == "pid":
        sim.enable_step_control(StepController(tolerance=tol, dt_max=dt))
    energy0 = total_energy(sim)
    scale = sim.kinetic_energy() + float(sim.model.mass_numpy().sum()) * gravity * radius
    duration = ADVISED_STEPS * advice.dt_max
    chunks = 20
    row = dict(
        soil=soil,
        gravity=gravity,
        youngs_modulus=youngs_modulus,
        radius=radius,
        factor=factor,
        precision=precision,
        method=method,
        advised_dt=advice.dt_max,
        critical_dt=advice.critical_step,
        dt=dt,
    )
    rise = -math.inf
    sim.monitor.arm(sim)
    try:
        for _ in range(chunks):
            if method == "pid":
                sim.macro_step_adaptive(duration / chunks)
                sim.monitor.check(sim)
            else:
                sim.run(duration / chunks, dt, check_every=10)
            rise = max(rise, (total_energy(sim) - energy0) / scale)
    except SimulationDiverged as error:
        row.update(
            result="diverged",
            when=f"t = {error.time:.3g} s ({error.time / duration:.0%} of the run), step {error.step}",
            why=error.reason,
        )
    else:
        row.update(result="drift" if rise > drift_bound else "stable", when="", why="")
    row.update(
        energy_rise=rise,
        evaluations=sim.contacts.evaluations,
        rejected=sim.rejected_steps,
        steps=sim.steps,
    )
    return row


def figure(rows: list[dict], path: str, axes: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods, factors = axes["method"], axes["factor"]
    colours = {"stable": "tab:green", "drift": "tab:orange", "diverged": "tab:red"}
    markers = dict(zip(axes["radius"], "os^v"))
    fig, grid = plt.subplots(
        len(methods), len(factors), figsize=(3.2 * len(factors), 2.8 * len(methods)), squeeze=False, sharex=True
    )
    for (i, method), (j, factor) in itertools.product(enumerate(methods), enumerate(factors)):
        ax = grid[i][j]
        for shift, (radius, marker) in enumerate(markers.items()):
            picked = [r for r in rows if r["method"] == method and r["factor"] == factor and r["radius"] == radius]
            for precision_shift, precision in enumerate(axes["precision"]):
                points = [r for r in picked if r["precision"] == precision]
                ax.scatter(
                    # side by side, not on top of each other: radius, then precision
                    [r["youngs_modulus"] * 2.2 ** (shift + len(markers) * precision_shift) for r in points],
                    [r["gravity"] for r in points],
                    c=[colours[r["result"]] for r in points],
                    marker=marker,
                    s=40,
                    label=f"r = {radius * 1e3:g} mm" if precision_shift == 0 else None,
                )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(f"{method}, {factor:g} x advised dt", fontsize=9)
        if j == 0:
            ax.set_ylabel("gravity [m/s^2]")
        if i == len(methods) - 1:
            ax.set_xlabel("Young's modulus [Pa]")
    grid[0][0].legend(fontsize=7)
    fig.suptitle("green stable, orange energy drift, red diverged", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


COLUMN_UNITS = {
    "gravity": "m/s^2",
    "youngs_modulus": "Pa",
    "radius": "m",
    "factor": "1",
    "advised_dt": "s",
    "critical_dt": "s",
    "dt": "s",
    "energy_rise": "1",
    "evaluations": "count",
    "rejected": "count",
    "steps": "count",
}
"""The units of a stability CSV's numeric columns (its header names them: 'gravity [m/s^2]'); the
energy rise is a fraction of KE0 + M g r."""


def read_rows(path: str) -> list[dict]:
    """The rows of a stability CSV written by main(), keyed by column name without its unit, numbers as numbers."""
    with open(path) as f:
        rows = [{key.split(" [")[0]: value for key, value in row.items()} for row in csv.DictReader(f)]
    for row in rows:
        for name in ("gravity", "youngs_modulus", "radius", "factor"):
            row[name] = float(row[name])
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--soil", default="phobos", help="phobos, lammps, or a scene file (TOML) whose [soil] is mapped"
    )
    parser.add_argument("--grid", choices=tuple(GRIDS), default="small")
    parser.add_argument("--tol", type=float, default=1e-2, help="PID tolerance (normalised local error)")
    parser.add_argument("--drift", type=float, default=0.02, help="energy-rise bound, fraction of KE0 + M g r")
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "figures"))
    args = parser.parse_args()
    axes = GRIDS[args.grid]
    os.makedirs(args.out, exist_ok=True)
    rows = []
    names = ("gravity", "youngs_modulus", "radius", "factor", "precision", "method")
    for point in itertools.product(*(axes[n] for n in names)):
        row = run_point(args.soil, *point, args.tol, args.drift)
        rows.append(row)
        print(
            f"g {row['gravity']:g} E {row['youngs_modulus']:g} r {row['radius']:g} x{row['factor']:g} "
            f"{row['precision']} {row['method']}: {row['result']} {row['when']} {row['why']} "
            f"({row['evaluations']} evaluations)",
            flush=True,
        )
    label = os.path.splitext(os.path.basename(args.soil))[0]
    csv_path = os.path.join(args.out, f"stability_{label}.csv")
    with open(csv_path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow([f"{key} [{COLUMN_UNITS[key]}]" if key in COLUMN_UNITS else key for key in rows[0]])
        writer.writerows([list(row.values()) for row in rows])
    figure(rows, os.path.join(args.out, f"stability_{label}.png"), axes)
    print(f"\n{csv_path}\n")
    columns = [(m, f) for m in axes["method"] for f in axes["factor"]]
    print("| g [m/s^2] | E [Pa] | r [mm] | " + " | ".join(f"{m} {f:g}x" for m, f in columns) + " |")
    print("|---" * (3 + len(columns)) + "|")
    short = {"stable": "ok", "drift": "drift", "diverged": "DIV"}
    for g, e, r in itertools.product(axes["gravity"], axes["youngs_modulus"], axes["radius"]):
        cells = []
        for m, f in columns:
            found = [
                x
                for x in rows
                if (x["gravity"], x["youngs_modulus"], x["radius"], x["method"], x["factor"]) == (g, e, r, m, f)
            ]
            cells.append("/".join(short[x["result"]] for x in found))
        print(f"| {g:g} | {e:g} | {r * 1e3:g} | " + " | ".join(cells) + " |")
    counts = {}
    for row in rows:
        key = (row["method"], row["factor"])
        counts.setdefault(key, {"stable": 0, "drift": 0, "diverged": 0})[row["result"]] += 1
    print("\n| method | factor | stable | drift | diverged | force evaluations |")
    print("|---|---|---|---|---|---|")
    for (method, factor), c in counts.items():
        evaluations = sum(r["evaluations"] for r in rows if (r["method"], r["factor"]) == (method, factor))
        print(f"| {method} | {factor:g} | {c['stable']} | {c['drift']} | {c['diverged']} | {evaluations} |")
    failing = [r for r in rows if r["factor"] == 1.0 and r["result"] != "stable"]
    advised = sum(r["factor"] == 1.0 for r in rows)
    print(f"\nthe advisor's step (factor 1) not stable at {len(failing)} of {advised} points")
    for r in failing:
        print(
            f"  g {r['gravity']:g} E {r['youngs_modulus']:g} r {r['radius']:g} {r['precision']} {r['method']}: "
            f"{r['result']} {r['when']} {r['why']}"
        )


if __name__ == "__main__":
    main()
