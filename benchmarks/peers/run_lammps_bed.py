"""Time LAMMPS on a settled granular bed; print one JSON line.

Scene (the same one our own bed benchmark should use, via make_random_fill):
N spheres of radius 2.5 mm +- 20 % on a 0.2 m x 0.2 m base with walls, Earth
gravity, E = 1e8 Pa, nu = 0.3, rho = 2600 kg/m^3, mu = 0.5, e = 0.5,
dt = 0.2 x the Rayleigh time step of the smallest sphere. The bed is first
settled (untimed but reported), then ``--steps`` steps are timed.

Run from the repository root::

    python benchmarks/peers/run_lammps_bed.py            # 10k spheres, 200 steps
    python benchmarks/peers/run_lammps_bed.py --rolling-friction 0.1
"""

import argparse
import json
import os
import platform
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from benchmarks.peers import lammps_peer  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=10_000, help="number of spheres")
    parser.add_argument("--steps", type=int, default=200, help="timed steps")
    parser.add_argument("--settle-time", type=float, default=0.3, help="settling time simulated first [s]")
    parser.add_argument("--rolling-friction", type=float, default=0.0, help="mu_roll (0 = off)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    density, youngs, poisson = 2600.0, 1e8, 0.3
    box_lo = np.array([0.0, 0.0, 0.0])
    box_hi = np.array([0.2, 0.2, 0.5])
    positions, radii = lammps_peer.make_random_fill(args.n, 2.5e-3, 0.2, box_lo, box_hi, args.seed)
    dt_rayleigh = lammps_peer.rayleigh_time_step(radii.min(), density, youngs, poisson)
    dt = 0.2 * dt_rayleigh
    settle_steps = int(round(args.settle_time / dt))

    result = lammps_peer.run_bed(
        positions,
        radii,
        density,
        youngs,
        poisson,
        friction_coefficient=0.5,
        restitution=0.5,
        rolling_friction=args.rolling_friction,
        box_lo=box_lo,
        box_hi=box_hi,
        gravity=[0.0, 0.0, -9.81],
        dt=dt,
        steps=args.steps,
        settle_first_steps=settle_steps,
    )
    speeds = np.linalg.norm(result["velocities"], axis=1)
    print(
        json.dumps(
            {
                "peer": "lammps",
                "lammps_version": result["lammps_version"],
                "n": args.n,
                "steps": args.steps,
                "dt": dt,
                "dt_rayleigh": dt_rayleigh,
                "seconds": result["seconds"],
                "particle_steps_per_second": result["particle_steps_per_second"],
                "settle_steps": settle_steps,
                "settle_seconds": result["settle_seconds"],
                "settle_particle_steps_per_second": args.n * settle_steps / result["settle_seconds"],
                "rolling_friction": args.rolling_friction,
                "kinetic_energy": result["kinetic_energy"],
                "mean_speed": float(speeds.mean()),
                "max_speed": float(speeds.max()),
                "bed_height": result["bed_height"],
                "packing_fraction": result["packing_fraction"],
                "packing_fraction_bulk": result["packing_fraction_bulk"],
                "threads": 1,
                "mpi_ranks": 1,
                "cpu": platform.processor() or platform.machine(),
                "command": " ".join(["python"] + sys.argv),
            }
        )
    )


if __name__ == "__main__":
    main()
