"""Device<->host transfers per coupled macro step: what cosim.dem_soil.DemSoil.advance asks of the host.

Counts, per macro step of a grousered wheel working in a small bed, the device->host reads
(wp.array.numpy: a copy from a GPU, the same call on the CPU) and the host->device copies
(wp.array.assign from host data). On a GPU every read makes the host wait for the device.

    python benchmarks/host_reads.py                         # this checkout
    python benchmarks/host_reads.py --source /path/to/old   # another checkout of the project (before/after)
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", default=ROOT, help="checkout whose soil and cosim packages to measure")
    parser.add_argument("--substeps", type=int, default=10, help="DEM steps per macro step")
    parser.add_argument("--macro-steps", type=int, default=10)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    sys.path.insert(0, os.path.abspath(args.source))
    import numpy as np
    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    from cosim.contract import WheelKinematics
    from cosim.dem_soil import DemSoil
    from soil import GrouserWheel, Material, Simulation, SoilBuilder

    builder = SoilBuilder(gravity=9.81)
    mat = builder.add_material(Material(youngs_modulus=1e6, restitution=0.3))
    builder.add_container((0, 0, 0), (0.09, 0.03, 0.1), mat)
    rng = np.random.default_rng(2)
    grid = np.stack(np.meshgrid(np.arange(13), np.arange(4), np.arange(3), indexing="ij"), -1).reshape(-1, 3)
    builder.add_particles(0.0035 + grid * 0.0068 + rng.uniform(-2e-4, 2e-4, grid.shape), 0.003, mat)
    builder.add_wheel(
        GrouserWheel(radius=0.02, width=0.012, grouser_count=8, grouser_height=0.002, grouser_thickness=0.0015), mat
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model, state, control = builder.finalize(args.device, "double")
    dt = 1e-4
    soil = DemSoil(Simulation(model, state, control), dt, surface_height=0.02)
    counts = {"reads": 0, "writes": 0}
    numpy, assign = wp.array.numpy, wp.array.assign

    def counted_numpy(array):
        counts["reads"] += 1
        return numpy(array)

    def counted_assign(array, source):
        counts["writes"] += not isinstance(source, wp.array)
        return assign(array, source)

    wp.array.numpy, wp.array.assign = counted_numpy, counted_assign
    macro = args.substeps * dt
    per_step = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for k in range(args.macro_steps + 1):
            before = dict(counts)
            t = k * macro
            start = WheelKinematics(
                np.array([0.03 + 0.05 * t, 0.015, 0.0415 - 0.3 * t]),
                np.array([1.0, 0, 0, 0]),
                np.array([0.05, 0.0, -0.3]),
                np.array([0.0, 2.5, 0.0]),
            )
            soil.advance((k + 1) * macro, [start])
            if k:  # the first one loads kernels and captures graphs
                per_step.append({key: counts[key] - before[key] for key in counts})
    reads = [p["reads"] for p in per_step]
    writes = [p["writes"] for p in per_step]
    print(f"source: {os.path.abspath(args.source)}")
    print(f"{args.substeps} DEM steps per macro step, {args.macro_steps} macro steps on {args.device}")
    print(f"device->host reads per macro step: mean {np.mean(reads):.1f}, max {max(reads)}")
    print(f"host->device copies per macro step: mean {np.mean(writes):.1f}, max {max(writes)}")


if __name__ == "__main__":
    main()
