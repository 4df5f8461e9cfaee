"""A four-wheeled MMX-like rover (MuJoCo) driving over a DEM regolith bed.

    python examples/rover_traverse.py                      # CPU-small: a 1:3 rover on ~4k grains, Phobos
    python examples/rover_traverse.py --gravity earth      # the same on Earth
    python examples/rover_traverse.py --size full --device cuda:0   # 25 kg rover, ~0.5 M grains (GPU)

Writes OUT/traverse.npz (the coupler's per-macro-step records: wheel kinematics and
wrenches) and prints travel, mean slip and sinkage per wheel. The settled bed is cached
in OUT/bed.h5 and reused.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gravity", default="phobos", help="preset name or magnitude [m/s^2]")
    parser.add_argument("--size", choices=["small", "full"], default="small")
    parser.add_argument("--device", default=None, help="cpu, cuda:0 (default: Warp's default device)")
    parser.add_argument("--precision", default="mixed", choices=["single", "double", "mixed"])
    parser.add_argument("--duration", type=float, default=None, help="driving time [s]")
    parser.add_argument("--out", default="runs/traverse")
    args = parser.parse_args(argv)

    import mujoco
    import warp as wp

    from soil import GrouserWheel, Simulation, gravity_vector
    from soil.bed import PHOBOS_REGOLITH, BedSpec, bed_metrics, build_bed, rayleigh_time_step, save_bed, settle
    from cosim.controllers import ConstantSpeed
    from cosim.coupler import Coupler
    from cosim.dem_soil import DemSoil
    from rover_models.mjcf import MMX_WHEELS, mmx_rover_xml
    from rover_models.mujoco_rover import MujocoRover

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no per-module load lines
    gravity = gravity_vector(args.gravity if not _is_number(args.gravity) else float(args.gravity))
    g = float(np.linalg.norm(gravity))
    # macroscopic stiffness adapted to the load (paper eq. 10): PHOBOS_REGOLITH at Phobos, scaled with g
    soil_material = PHOBOS_REGOLITH.with_(youngs_modulus=PHOBOS_REGOLITH.youngs_modulus * max(1.0, g / 5.7e-3))
    if args.size == "small":
        wheel = GrouserWheel(radius=0.035, width=0.025, grouser_count=12, grouser_height=0.004, grouser_thickness=0.002)
        rover_xml = mmx_rover_xml(wheel_radius=wheel.radius, wheel_width=wheel.width, body_mass=0.6, leg_mass=0.05,
                                  wheel_mass=0.1, body_size=(0.14, 0.12, 0.06), wheelbase=0.14, track=0.16,
                                  leg_drop=0.035, gravity=tuple(gravity))
        spec = BedSpec(length=0.42, width=0.24, depth=0.025, radius_mean=4e-3, radius_spread=0.15,
                       material=soil_material)
    else:
        wheel = GrouserWheel(radius=0.1, width=0.06, grouser_count=16, grouser_height=0.008, grouser_thickness=0.004)
        rover_xml = mmx_rover_xml(gravity=tuple(gravity))
        spec = BedSpec(length=1.4, width=0.75, depth=0.08, radius_mean=2.5e-3, radius_spread=0.2,
                       material=soil_material)
    os.makedirs(args.out, exist_ok=True)
    dt = 0.2 * rayleigh_time_step(spec.material, spec.radius_mean * (1 - spec.radius_spread))
    bed_file = os.path.join(args.out, "bed.h5")
    start = time.perf_counter()
    if not os.path.exists(bed_file):
        sim = Simulation(*build_bed(spec, gravity).finalize(args.device, args.precision))
        print(f"settling {sim.model.particle_count} grains at g = {g:.4g} m/s^2, dt = {dt:.3g} s ...", flush=True)
        report = settle(sim, dt, ke_ratio=1e-3, max_time=80 * math.sqrt(spec.radius_mean / g))
        metrics = bed_metrics(sim, spec)
        print(f"  settled={report['settled']} in {report['time']:.3g} s simulated, bed height "
              f"{metrics['height'] * 1e3:.1f} mm, packing {metrics['packing_fraction']:.3f}", flush=True)
        save_bed(bed_file, sim, spec, metrics)

    soil = DemSoil.from_bed(bed_file, [wheel] * 4, soil_material, dt, device=args.device, precision=args.precision)
    rover = MujocoRover(rover_xml, list(MMX_WHEELS), gravity=gravity)
    # over the bed's start, lowered until the first wheel just touches the highest grain under it:
    # a wheel pressed into the grains would be shot off the ground in milli-g
    rover.data.qpos[0:2] = [0.12 if args.size == "small" else 0.35, spec.width / 2]
    mujoco.mj_forward(rover.model, rover.data)
    hubs = [k.position for k in rover.wheel_kinematics()]
    lift = max(soil.highest_grain_under(i, hub) + wheel.outer_radius - hub[2] for i, hub in enumerate(hubs))
    rover.data.qpos[2] += lift + 1e-4
    mujoco.mj_forward(rover.model, rover.data)
    soil.place_wheels(rover.wheel_kinematics())
    hub_speed = 0.01 if g < 0.1 else 0.05  # slow on Phobos, where a fast rover lifts off
    controller = ConstantSpeed(hub_speed / wheel.radius, 4)
    coupler = Coupler(soil, rover, 10 * dt, gravity=gravity, controller=controller)
    duration = args.duration or (0.12 / hub_speed if args.size == "small" else 0.4 / hub_speed)
    print(f"driving {duration:.3g} s at {hub_speed * 100:.1f} cm/s on {soil.sim.model.particle_count} grains ...",
          flush=True)
    x0 = np.array([k.position[0] for k in rover.wheel_kinematics()])
    coupler.run(duration)
    rec = coupler.records()
    np.savez(os.path.join(args.out, "traverse.npz"), **rec)
    travel = rec["position"][-1, :, 0] - x0
    half = rec["time"] > rec["time"][-1] / 2
    rim = np.abs(rec["angular_velocity"][half, :, 1]) * wheel.radius
    slip = 1 - np.mean(rec["linear_velocity"][half, :, 0], axis=0) / np.maximum(np.mean(rim, axis=0), 1e-12)
    print(f"wall time {time.perf_counter() - start:.1f} s; records in {args.out}/traverse.npz")
    for i, name in enumerate(MMX_WHEELS):
        print(f"  {name}: travel {travel[i] * 100:.2f} cm, slip {slip[i]:.2f}, "
              f"sinkage {np.mean(rec['sinkage'][half, i]) * 1e3:.2f} mm")


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


if __name__ == "__main__":
    main()
