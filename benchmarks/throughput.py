"""DEM throughput: particle-steps per second against LAMMPS, cost per particle-step from small
to large beds, what step capture saves, and device memory per grain.

    python benchmarks/throughput.py                # all sections, full sizes (~1 h on one CPU core)
    python benchmarks/throughput.py --quick        # all sections, small sizes (minutes)
    python benchmarks/throughput.py --sections lammps --n 10000 50000 200000 --steps 200

Sections (side by side in one run, same beds, same dt):

- lammps: a random fill settled once under Earth gravity with this code (double; cached in
  benchmarks/cache; beds above 50,000 grains are tiles of the settled 50,000 bed), then timed
  from the same positions in each precision and in LAMMPS on one thread (pair granular
  hertz/material + mindlin, fix wall/gran, the same material, friction, restitution, dt, skin).
- scaling: cost per particle-step [us] of jittered lattice beds from 1,000 to 200,000 grains,
  deep (a cube) and shallow (4 grains deep, footprint 2.5:1).
- capture: the same steps replayed from captured graphs and launched kernel by kernel.
- reorder: settled fills stored in the space-filling curve's order and in their fill order.
- storage: settled fills with the neighbour lists and contact history stored per grain and per slot
  (SoilBuilder.finalize(storage=...)), mixed precision.
- memory: device bytes per grain of a Simulation in each precision.

Times are taken both as wall-clock and as the process's CPU time; on a machine shared with
other work the CPU-time ratios are the steadier figures. Prints markdown tables; --json
writes every row.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import warp as wp  # noqa: E402

from benchmarks import beds  # noqa: E402
from benchmarks.peers import lammps_peer  # noqa: E402

PRECISIONS = ("single", "mixed", "double")


def machine(device: str) -> str:
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    name = platform.processor() or platform.machine()
    if device.startswith("cuda"):
        name = wp.get_device(device).name
    return f"{name}, {os.cpu_count()} cores, device {device}, load average {load:.1f} at start"


def time_ours(sim, steps: int, dt: float, warmup: int = 10) -> dict:
    """Wall and CPU seconds of `steps` steps (one macro step), after `warmup` steps."""
    sim.macro_step(warmup, dt)  # kernels loaded, graphs captured, contacts formed
    wall, cpu = time.perf_counter(), time.process_time()
    sim.macro_step(steps, dt)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    n = sim.model.particle_count
    return dict(
        wall_seconds=wall,
        cpu_seconds=cpu,
        particle_steps_per_second=n * steps / wall,
        us_per_particle_step_cpu=cpu / (n * steps) * 1e6,
        contacts_per_particle=float(sim.contact_counts().mean()),
    )


def time_lammps(positions, radii, box_hi, dt: float, steps: int) -> dict:
    """LAMMPS on one thread: wall time of `steps` timed steps, CPU time as the difference of
    runs of 2 x steps and steps (setup cancels; nan where that difference is not positive)."""
    args = (
        positions,
        radii,
        beds.DENSITY,
        beds.YOUNGS,
        beds.POISSON,
        beds.MU,
        beds.RESTITUTION,
        0.0,
        (0, 0, 0),
        box_hi,
        (0, 0, -9.81),
        dt,
    )
    cpu = []
    for count in (steps, 2 * steps):
        start = time.process_time()
        result = lammps_peer.run_bed(*args, count, settle_first_steps=10)
        cpu.append(time.process_time() - start)
        if count == steps:
            wall = result["seconds"]
    n = len(radii)
    # at a few steps the two runs' setups differ by more than the steps cost: no CPU time is measured then
    extra = cpu[1] - cpu[0] if cpu[1] > cpu[0] else float("nan")
    return dict(
        wall_seconds=wall,
        cpu_seconds=extra,
        particle_steps_per_second=n * steps / wall,
        us_per_particle_step_cpu=extra / (n * steps) * 1e6,
    )


def section_lammps(args, rows, log):
    for n in args.n:
        positions, radii, box_hi, dt = beds.settled_bed(n, args.device, log=log)
        n = len(radii)
        peer = None
        if not args.no_lammps and lammps_peer.lammps_available():
            peer = time_lammps(positions, radii, box_hi, dt, args.steps)
            rows.append(
                dict(
                    section="lammps",
                    code="LAMMPS",
                    precision="double",
                    n=n,
                    steps=args.steps,
                    dt=dt,
                    device="cpu (1 rank)",
                    **peer,
                )
            )
            log(json.dumps(rows[-1]))
        for precision in args.precisions:
            sim = beds.build(positions, radii, box_hi, args.device, precision)
            row = dict(
                section="lammps",
                code="regolith-cosim",
                precision=precision,
                n=n,
                steps=args.steps,
                dt=dt,
                device=args.device,
                **time_ours(sim, args.steps, dt),
                bytes_per_grain=sim.bytes_per_grain()["total"],
            )
            if peer:
                row["ratio_wall"] = row["particle_steps_per_second"] / peer["particle_steps_per_second"]
                row["ratio_cpu"] = peer["us_per_particle_step_cpu"] / row["us_per_particle_step_cpu"]
            rows.append(row)
            log(json.dumps(row))


def section_scaling(args, rows, log):
    for shape in ("deep", "shallow"):
        for n in args.scaling_n:
            positions, radii, box_hi = beds.lattice_bed(n, shape)
            sim = beds.build(positions, radii, box_hi, args.device, args.scaling_precision)
            row = dict(
                section="scaling",
                shape=shape,
                precision=args.scaling_precision,
                n=len(radii),
                steps=args.steps,
                device=args.device,
                **time_ours(sim, args.steps, 2e-6, warmup=50),
            )
            rows.append(row)
            log(json.dumps(row))


def section_capture(args, rows, log):
    for n in args.capture_n:
        positions, radii, box_hi = beds.lattice_bed(n, "deep")
        timed = {}
        for capture in (True, False):
            sim = beds.build(positions, radii, box_hi, args.device, "double", capture=capture)
            timed[capture] = time_ours(sim, args.steps, 2e-6, warmup=50)
        captured, launched = timed[True]["us_per_particle_step_cpu"], timed[False]["us_per_particle_step_cpu"]
        rows.append(
            dict(
                section="capture",
                n=len(radii),
                steps=args.steps,
                device=args.device,
                precision="double",
                captured_us=captured,
                launched_us=launched,
                saving=1.0 - captured / launched,
                captured_wall=timed[True]["wall_seconds"],
                launched_wall=timed[False]["wall_seconds"],
            )
        )
        log(json.dumps(rows[-1]))


def section_reorder(args, rows, log):
    from soil import NeighbourSettings

    for n in args.reorder_n:
        positions, radii, box_hi, dt = beds.settled_bed(n, args.device, log=log)
        timed = {}
        for reorder in (True, False):
            sim = beds.build(
                positions, radii, box_hi, args.device, "double", neighbours=NeighbourSettings(reorder=reorder)
            )
            timed[reorder] = time_ours(sim, args.steps, dt)["us_per_particle_step_cpu"]
        rows.append(
            dict(
                section="reorder",
                n=len(radii),
                steps=args.steps,
                device=args.device,
                precision="double",
                reordered_us=timed[True],
                unordered_us=timed[False],
                speedup=timed[False] / timed[True],
            )
        )
        log(json.dumps(rows[-1]))


def section_storage(args, rows, log):
    for n in args.storage_n:
        positions, radii, box_hi, dt = beds.settled_bed(n, args.device, log=log)
        timed = {}
        for storage in ("grain", "slot"):
            sim = beds.build(positions, radii, box_hi, args.device, "mixed", storage=storage)
            timed[storage] = time_ours(sim, args.steps, dt)["us_per_particle_step_cpu"]
        rows.append(
            dict(
                section="storage",
                n=len(radii),
                steps=args.steps,
                device=args.device,
                precision="mixed",
                grain_us=timed["grain"],
                slot_us=timed["slot"],
                speedup=timed["grain"] / timed["slot"],
            )
        )
        log(json.dumps(rows[-1]))


def section_memory(args, rows, log):
    positions, radii, box_hi = beds.lattice_bed(args.memory_n, "shallow")
    for precision in PRECISIONS:
        sim = beds.build(positions, radii, box_hi, args.device, precision)
        sim.macro_step(20, 2e-6)
        sim.monitor.arm(sim)  # its last-good copy counts too
        parts = sim.bytes_per_grain()
        rows.append(
            dict(
                section="memory",
                precision=precision,
                n=len(radii),
                capacity=sim.state.capacity,
                rigid_capacity=sim.state.rigid_capacity,
                **{k: float(v) for k, v in parts.items()},
            )
        )
        log(json.dumps(rows[-1]))


def tables(rows, header: str) -> str:
    out = [header, ""]
    lam = [r for r in rows if r["section"] == "lammps"]
    if lam:
        out += [
            "| grains | code | precision | particle-steps/s (wall) | us per particle-step (CPU) | ratio to LAMMPS "
            "(CPU) | ratio (wall) | contacts per grain |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in lam:
            out.append(
                f"| {r['n']} | {r['code']} | {r['precision']} | {r['particle_steps_per_second']:.3g} | "
                f"{r['us_per_particle_step_cpu']:.3f} | {r.get('ratio_cpu', float('nan')):.2f} | "
                f"{r.get('ratio_wall', float('nan')):.2f} | "
                f"{r.get('contacts_per_particle', float('nan')):.2f} |"
            )
        out.append("")
    scaling = [r for r in rows if r["section"] == "scaling"]
    if scaling:
        out += [
            "| bed | grains | us per particle-step (CPU) | relative to the smallest | contacts per grain |",
            "|---|---|---|---|---|",
        ]
        for shape in ("deep", "shallow"):
            these = [r for r in scaling if r["shape"] == shape]
            for r in these:
                out.append(
                    f"| {shape} | {r['n']} | {r['us_per_particle_step_cpu']:.3f} | "
                    f"{r['us_per_particle_step_cpu'] / these[0]['us_per_particle_step_cpu']:.2f} | "
                    f"{r['contacts_per_particle']:.2f} |"
                )
            if these:
                costs = [r["us_per_particle_step_cpu"] for r in these]
                out.append(f"| {shape}: max / min | | {max(costs) / min(costs):.2f} | | |")
        out.append("")
    capture = [r for r in rows if r["section"] == "capture"]
    if capture:
        out += ["| grains | captured: us per particle-step (CPU) | launched one by one | saving |", "|---|---|---|---|"]
        for r in capture:
            out.append(f"| {r['n']} | {r['captured_us']:.3f} | {r['launched_us']:.3f} | {100 * r['saving']:.0f} % |")
        out.append("")
    reorder = [r for r in rows if r["section"] == "reorder"]
    if reorder:
        out += [
            "| grains (settled fill) | stored in curve order: us per particle-step (CPU) | in fill order | speed-up |",
            "|---|---|---|---|",
        ]
        for r in reorder:
            out.append(f"| {r['n']} | {r['reordered_us']:.3f} | {r['unordered_us']:.3f} | {r['speedup']:.2f} |")
        out.append("")
    storage = [r for r in rows if r["section"] == "storage"]
    if storage:
        out += [
            "| grains (settled fill, mixed) | per grain: us per particle-step (CPU) | per slot | speed-up |",
            "|---|---|---|---|",
        ]
        for r in storage:
            out.append(f"| {r['n']} | {r['grain_us']:.3f} | {r['slot_us']:.3f} | {r['speedup']:.2f} |")
        out.append("")
    memory = [r for r in rows if r["section"] == "memory"]
    if memory:
        keys = [k for k in memory[0] if k not in ("section", "precision", "n", "capacity", "rigid_capacity")]
        out += ["| precision | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
        for r in memory:
            out.append(f"| {r['precision']} | " + " | ".join(f"{r[k]:.0f}" for k in keys) + " |")
        r = memory[0]
        out.append(
            f"\n(bytes per grain; {r['n']} grains, {r['capacity']} neighbour slots and {r['rigid_capacity']} "
            "wall/wheel slots per grain)"
        )
    return "\n".join(out)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sections",
        nargs="+",
        default=["lammps", "scaling", "capture", "reorder", "storage", "memory"],
        choices=["lammps", "scaling", "capture", "reorder", "storage", "memory"],
    )
    parser.add_argument("--quick", action="store_true", help="small sizes and few steps (minutes)")
    parser.add_argument("--n", type=int, nargs="+", default=None, help="grains of the LAMMPS comparison")
    parser.add_argument("--scaling-n", type=int, nargs="+", default=None)
    parser.add_argument("--scaling-precision", default="double", choices=PRECISIONS)
    parser.add_argument("--capture-n", type=int, nargs="+", default=None)
    parser.add_argument("--reorder-n", type=int, nargs="+", default=None)
    parser.add_argument("--storage-n", type=int, nargs="+", default=None)
    parser.add_argument("--memory-n", type=int, default=None)
    parser.add_argument("--steps", type=int, default=None)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--precisions", nargs="+", default=list(PRECISIONS), choices=PRECISIONS)
    parser.add_argument("--no-lammps", action="store_true")
    parser.add_argument("--json", default=None, help="write the rows to this file")
    args = parser.parse_args(argv)
    quick = args.quick
    args.n = args.n or ([10000] if quick else [10000, 50000, 200000])
    args.scaling_n = args.scaling_n or ([1000, 10000] if quick else [1000, 10000, 50000, 200000])
    args.capture_n = args.capture_n or [1000, 10000]
    args.reorder_n = args.reorder_n or ([10000] if quick else [10000, 50000])
    args.storage_n = args.storage_n or ([10000] if quick else [10000, 50000])
    args.memory_n = args.memory_n or (10000 if quick else 100000)
    args.steps = args.steps or (50 if quick else 200)
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no per-module load lines
    command = "python benchmarks/throughput.py " + " ".join(argv or sys.argv[1:])
    header = f"machine: {machine(args.device)}\ncommand: {command}"
    print(header, flush=True)
    rows: list[dict] = []

    def log(text):
        print(text, flush=True)

    for name in args.sections:
        globals()[f"section_{name}"](args, rows, log)
    print()
    print(tables(rows, header))
    if args.json:
        from cosim.folders import finite_or_null

        with open(args.json, "w") as f:  # strict JSON: what was not measured (nan) is null
            json.dump(finite_or_null(rows), f, indent=1, allow_nan=False)


if __name__ == "__main__":
    main()
