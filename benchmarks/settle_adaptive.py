"""Settling a bed at Phobos gravity to a kinetic-energy threshold: fixed step vs adaptive step.

Same bed (soil.bed.BedSpec, PHOBOS_REGOLITH, E = 2e5 Pa, radius 2.5 mm +- 20 %), same
threshold (soil.bed.kinetic_energy_threshold, ratio --ke-ratio), one run each, side by side:

- fixed:    jolt-Beeman with the advisor's dt_max (soil.advisor.recommended_time_step);
- adaptive: jolt-Beeman + PID StepController (tolerance --tol), dt_max = --dt-max-factor
            (default 2) x the advised step (the controller decides), defaults otherwise.

A run that diverges is a result too: its row says when (soil.stability.SimulationDiverged).

Prints a markdown table (simulated settling time, force evaluations, rejected steps,
wall time) and one JSON line per row.

    python benchmarks/settle_adaptive.py --n 2000 [--tol 1e-3] [--device cpu]
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

import warp as wp  # noqa: E402

from soil import JoltBeeman, Simulation, StepController, advisor  # noqa: E402
from soil.bed import BedSpec, build_bed, kinetic_energy_threshold  # noqa: E402
from soil.stability import SimulationDiverged  # noqa: E402


def bed_spec(n: int) -> BedSpec:
    """A bed of about n grains: 0.1 m wide, 0.04 m deep inserted, length set by n."""
    pitch = 2 * 2.5e-3 * 1.2 * 1.02
    per_metre = (0.1 // pitch) * (0.04 // pitch) / pitch
    return BedSpec(length=max(0.03, n / per_metre), width=0.1, depth=0.04)


def make(spec, device, precision):
    model, state, control = build_bed(spec, "phobos").finalize(device=device, precision=precision)
    return Simulation(model, state, control, integrator=JoltBeeman())


def settle(sim, advance, threshold, interval, max_time):
    """advance(sim, interval) until the kinetic energy < threshold (after 10 intervals)."""
    start = time.perf_counter()
    energy = sim.kinetic_energy()
    outcome = None
    while sim.time < max_time:
        try:
            advance(sim, interval)
        except SimulationDiverged as error:  # a measured outcome too: report it as a row
            outcome = f"diverged at t = {error.time:.3g} s"
            print(error, file=sys.stderr)
            break
        energy = sim.kinetic_energy()
        if energy < threshold and sim.time > 10 * interval:
            break
    wp.synchronize()
    settled = outcome or ("yes" if energy < threshold else "no")
    return dict(
        settled=settled,
        time=sim.time,
        kinetic_energy=energy,
        wall_s=time.perf_counter() - start,
        evaluations=sim.contacts.evaluations,
        rejected=sim.rejected_steps,
        steps=sim.steps,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=2000, help="about this many grains")
    parser.add_argument("--tol", type=float, default=1e-3, help="normalised tolerance of the adaptive run")
    parser.add_argument("--ke-ratio", type=float, default=1e-3, help="settled: KE < ratio N m g r")
    parser.add_argument("--max-time", type=float, default=20.0, help="give up after this simulated time [s]")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--precision", default="double")
    parser.add_argument(
        "--norms",
        nargs="+",
        default=["rms", "max"],
        choices=["rms", "max", "rms-unguarded"],
        help="error norms of the adaptive runs (one run each); rms-unguarded: grain_factor = inf",
    )
    parser.add_argument(
        "--dt-max-factor", type=float, default=2.0, help="adaptive runs: dt_max = this x the advised step"
    )
    args = parser.parse_args()
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    wp.init()
    spec = bed_spec(args.n)
    probe = make(spec, args.device, args.precision)
    advice = advisor.recommended_time_step(probe)
    threshold = kinetic_energy_threshold(probe, args.ke_ratio)
    interval = 0.25 * math.sqrt(spec.radius_mean / 5.7e-3)  # a quarter of sqrt(r/g)
    # warm-up: kernels compiled/loaded outside the timed runs
    probe.run(2 * advice.dt_max, advice.dt_max)
    probe.run_adaptive(2 * advice.dt_max, StepController(dt_max=advice.dt_max))

    rows = []
    sim = make(spec, args.device, args.precision)
    fixed = settle(sim, lambda s, d: s.run(d, advice.dt_max, check_every=100), threshold, interval, args.max_time)
    rows.append(dict(method=f"fixed dt = {advice.dt_max:.3g} s (advised)", **fixed))
    for norm in args.norms:
        sim = make(spec, args.device, args.precision)
        guard = dict(norm="rms", grain_factor=math.inf) if norm == "rms-unguarded" else dict(norm=norm)
        controller = StepController(tolerance=args.tol, dt_max=args.dt_max_factor * advice.dt_max, **guard)
        adaptive = settle(
            sim, lambda s, d, controller=controller: s.run_adaptive(d, controller), threshold, interval, args.max_time
        )
        rows.append(dict(method=f"adaptive tol = {args.tol:g}, {norm} norm", **adaptive))

    n = probe.model.particle_count
    print(
        f"\n{n} grains, Phobos gravity 5.7e-3 m/s^2, E = {spec.material.youngs_modulus:g} Pa, "
        f"{args.precision}, device {args.device} ({platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cores); threshold {threshold:.3g} J (ratio {args.ke_ratio:g}); "
        f"advised dt {advice.dt_max:.3g} s, Rayleigh {advice.rayleigh:.3g} s\n"
    )
    print("| method | settled | simulated [s] | force evaluations | rejected | wall [s] | evaluations/s |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        print(
            f"| {row['method']} | {row['settled']} | {row['time']:.3f} | {row['evaluations']} | {row['rejected']} "
            f"| {row['wall_s']:.1f} | {row['evaluations'] / row['wall_s']:.0f} |"
        )
    for row in rows:
        print(json.dumps(dict(n=n, **row)))


if __name__ == "__main__":
    main()
