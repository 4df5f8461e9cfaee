"""Particle-steps per second on a settled bed: regolith-cosim (single/mixed/double) vs LAMMPS.

One run, side by side, same scene: N spheres (radius 2.5 mm +- 20 %) filled with
`make_random_fill` into a box, settled once under Earth gravity with our code
(double precision), then timed from the same settled positions:
our Simulation in each precision, and LAMMPS (pair granular hertz/material + mindlin,
fix wall/gran) with the same material, friction, restitution and dt. Prints a markdown
table and one JSON line per row.

    python benchmarks/throughput.py --n 10000 50000 --steps 200 [--device cpu]
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

import warp as wp  # noqa: E402

from benchmarks.peers import lammps_peer  # noqa: E402
from soil import ContactLaw, Material, Simulation, SoilBuilder  # noqa: E402

DENSITY, YOUNGS, POISSON, MU, RESTITUTION = 2600.0, 1e7, 0.3, 0.5, 0.5


def material() -> Material:
    angle = math.atan(MU)
    # stick_speed large: plain Coulomb (Cundall-Strack), the model LAMMPS has
    return Material(youngs_modulus=YOUNGS, poisson_ratio=POISSON, density=DENSITY, restitution=RESTITUTION,
                    stick_angle=angle, slip_angle=angle, stick_speed=1e9)


def build(positions, radii, box_hi, device, precision):
    builder = SoilBuilder(gravity="earth")
    mat = builder.add_material(material())
    builder.add_container((0, 0, 0), box_hi, mat)
    builder.add_particles(positions, radii, mat)
    model, state, control = builder.finalize(device=device, precision=precision,
                                             law=ContactLaw(damping=True, friction=True))
    return Simulation(model, state, control)


def settled_bed(n, device, seed=0, settle_time=0.15):
    side = 0.3 if n <= 20000 else 0.5
    box_hi = np.array([side, side, 1.0])
    positions, radii = lammps_peer.make_random_fill(n, 2.5e-3, 0.2, (0, 0, 0), box_hi, seed)
    dt = 0.2 * lammps_peer.rayleigh_time_step(radii.min(), DENSITY, YOUNGS, POISSON)
    cache = os.path.join(ROOT, "benchmarks", "cache", f"bed_{n}_{seed}.npz")
    if os.path.exists(cache):
        data = np.load(cache)
        return data["positions"], radii, box_hi, dt, float(data["settle_seconds"])
    sim = build(positions, radii, box_hi, device, "double")
    start = time.perf_counter()
    sim.run(settle_time, dt)
    seconds = time.perf_counter() - start
    settled = sim.positions()[np.argsort(sim.model.particle_order)]
    os.makedirs(os.path.dirname(cache), exist_ok=True)
    np.savez(cache, positions=settled, settle_seconds=seconds)
    return settled, radii, box_hi, dt, seconds


def time_ours(positions, radii, box_hi, dt, steps, device, precision):
    sim = build(positions, radii, box_hi, device, precision)
    sim.run(10 * dt, dt)  # warm-up: kernels loaded, contacts formed
    wp.synchronize()
    start = time.perf_counter()
    sim.run(steps * dt, dt)
    wp.synchronize()
    seconds = time.perf_counter() - start
    contacts = float(sim.state.contact_count.numpy().mean())
    return seconds, contacts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, nargs="+", default=[10000, 50000])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--precisions", nargs="+", default=["single", "mixed", "double"])
    parser.add_argument("--no-lammps", action="store_true")
    args = parser.parse_args()
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no per-module load lines
    rows = []
    machine = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, {args.device}"
    for n in args.n:
        positions, radii, box_hi, dt, settle_seconds = settled_bed(n, args.device)
        for precision in args.precisions:
            seconds, contacts = time_ours(positions, radii, box_hi, dt, args.steps, args.device, precision)
            rows.append(dict(code="regolith-cosim", precision=precision, n=n, steps=args.steps, dt=dt,
                             seconds=seconds, particle_steps_per_second=n * args.steps / seconds,
                             contacts_per_particle=contacts, device=args.device))
            print(json.dumps(rows[-1]), flush=True)
        if not args.no_lammps and lammps_peer.lammps_available():
            result = lammps_peer.run_bed(positions, radii, DENSITY, YOUNGS, POISSON, MU, RESTITUTION, 0.0,
                                         (0, 0, 0), box_hi, (0, 0, -9.81), dt, args.steps, settle_first_steps=10)
            rows.append(dict(code="LAMMPS", precision="double", n=n, steps=args.steps, dt=dt,
                             seconds=result["seconds"], particle_steps_per_second=result["particle_steps_per_second"],
                             contacts_per_particle=float("nan"), device="cpu (1 rank)"))
            print(json.dumps(rows[-1]), flush=True)
    print(f"\nmachine: {machine}\n")
    print("| code | precision | particles | particle-steps/s | ratio to LAMMPS |")
    print("|---|---|---|---|---|")
    for row in rows:
        peer = [r for r in rows if r["code"] == "LAMMPS" and r["n"] == row["n"]]
        ratio = row["particle_steps_per_second"] / peer[0]["particle_steps_per_second"] if peer else float("nan")
        print(f"| {row['code']} | {row['precision']} | {row['n']} | {row['particle_steps_per_second']:.3g} | "
              f"{ratio:.2f} |")


if __name__ == "__main__":
    main()
