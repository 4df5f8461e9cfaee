"""Cost per grain-step of a coupled DEM step: cosim.dem_soil.DemSoil.advance with a grousered wheel rolling
on a standing bed at Phobos gravity, beside the same bed stepped without a wheel
(Simulation.macro_step), for this checkout or another one.

    python benchmarks/coupled_step_cost.py                          # this checkout
    python benchmarks/coupled_step_cost.py --compare /path/to/old   # the other checkout and this one,
                                                                    # alternating, in one run
    python benchmarks/coupled_step_cost.py --precision mixed        # single | mixed | double (default)

The bed is a pressed lattice (benchmarks/beds.py lattice_bed, shallow): it stands still from
the first step, so what the wheel stirs is all that moves. The wheel is made with the model,
set on the bed by the first advance (as benchmarks/gpu_suite.py does) and rolls at 1 cm/s
with 20 % slip, its grouser tips pressed 0.1 mm into the top grains.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def measure(grains: int, macro_steps: int, substeps: int, precision: str = "double") -> dict:
    import numpy as np
    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    from benchmarks import beds
    from cosim.contract import WheelKinematics
    from cosim.dem_soil import DemSoil
    from soil import GrouserWheel, Simulation, SoilBuilder
    from soil.advisor import rayleigh_time_step

    positions, radii, box = beds.lattice_bed(grains, "shallow")
    dt = 0.2 * rayleigh_time_step(beds.YOUNGS, beds.POISSON, beds.DENSITY, radii.min())
    wheel = GrouserWheel(radius=0.05, width=0.04, grouser_count=12, grouser_height=0.003, grouser_thickness=0.002)

    def simulation(with_wheel: bool):
        builder = SoilBuilder(gravity="phobos")
        mat = builder.add_material(beds.material())
        builder.add_container((0, 0, 0), box, mat)
        builder.add_particles(positions, radii, mat)
        if with_wheel:
            builder.add_wheel(wheel, mat)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the lattice starts pressed: on purpose
            return Simulation(*builder.finalize("cpu", precision))

    n = len(radii)
    result = {"grains": n, "dt": dt, "substeps": substeps, "timed_macro_steps": macro_steps, "precision": precision}

    plain = simulation(False)
    plain.macro_step(substeps, dt)  # kernels loaded, graphs captured
    started = time.perf_counter()
    rebuilds = sum(plain.macro_step(substeps, dt).rebuilds for _ in range(macro_steps))
    result["no_wheel_us_per_grain_step"] = (time.perf_counter() - started) / (macro_steps * substeps * n) * 1e6
    result["no_wheel_rebuilds_per_step"] = rebuilds / (macro_steps * substeps)

    soil = DemSoil(simulation(True), dt, surface_height=float(np.max(positions[:, 2] + radii)), wall_clearance=0.0)
    top = soil.highest_grain_under(0, (0.3 * box[0], 0.5 * box[1], 0.0))
    hub = np.array([0.3 * box[0], 0.5 * box[1], top + wheel.outer_radius - 1e-4])
    velocity = np.array([0.01, 0.0, 0.0])
    spin = np.array([0.0, 1.2 * velocity[0] / wheel.radius, 0.0])
    counted = {"rebuilds": 0}
    macro_step = soil.sim.macro_step

    def counting(*args, **kwargs):
        report = macro_step(*args, **kwargs)
        counted["rebuilds"] += report.rebuilds
        return report

    soil.sim.macro_step = counting

    def advance(k):
        start = WheelKinematics(hub + velocity * k * substeps * dt, [1.0, 0, 0, 0], velocity, spin)
        return soil.advance((k + 1) * substeps * dt, [start])[0]

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        advance(0)  # kernels loaded, graphs captured
        counted["rebuilds"] = 0
        started = time.perf_counter()
        for k in range(1, macro_steps + 1):
            wrench = advance(k)
        seconds = time.perf_counter() - started
    result["wheel_us_per_grain_step"] = seconds / (macro_steps * substeps * n) * 1e6
    result["wheel_rebuilds_per_step"] = counted["rebuilds"] / (macro_steps * substeps)
    result["wheel_contacts"] = int(wrench.contact_count)
    return result


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", default=ROOT, help="checkout whose soil and cosim packages to measure")
    parser.add_argument("--compare", help="another checkout: measure it and this one in turn, --repeats times")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--grains", type=int, default=8000)
    parser.add_argument("--macro-steps", type=int, default=20)
    parser.add_argument("--substeps", type=int, default=10, help="DEM steps per macro step")
    parser.add_argument("--precision", default="double", choices=("single", "mixed", "double"))
    parser.add_argument("--json", action="store_true", help="print the result as one JSON line")
    args = parser.parse_args(argv)
    sizes = ["--grains", str(args.grains), "--macro-steps", str(args.macro_steps), "--substeps", str(args.substeps)]
    sizes += ["--precision", args.precision]
    if args.compare:
        from checkouts import in_turn

        keys = ("no_wheel_us_per_grain_step", "wheel_us_per_grain_step", "wheel_rebuilds_per_step", "wheel_contacts")
        median = in_turn(__file__, args.compare, sizes, args.repeats, keys)
        ratio = {name: m["wheel_us_per_grain_step"] / m["no_wheel_us_per_grain_step"] for name, m in median.items()}
        print(
            f"wheel / no wheel: other {ratio['other']:.2f}, this {ratio['this']:.2f}; other / this with the wheel: "
            f"{median['other']['wheel_us_per_grain_step'] / median['this']['wheel_us_per_grain_step']:.2f}"
        )
        return
    sys.path.insert(0, os.path.abspath(args.source))
    result = measure(args.grains, args.macro_steps, args.substeps, args.precision)
    result["source"] = os.path.dirname(os.path.dirname(os.path.abspath(sys.modules["soil"].__file__)))
    print(json.dumps(result) if args.json else json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
