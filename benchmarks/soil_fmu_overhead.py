"""Cost of the soil FMU (front end + server process + socket) against the in-process DemSoil.

Exports a scene's soil as an FMU, then steps the FMU (fmpy, FMI 2.0) and the in-process
DemSoil side by side, alternating macro step by macro step (a loaded machine slows both
alike), with the same wheel motion; prints the server's start time, the wall time per macro
step of each, their ratio, and checks that the wrenches are bitwise equal (CPU).

    python benchmarks/soil_fmu_overhead.py [SCENE.toml] [--steps 40] [--substeps 1,10]

Without a scene it uses the tests' tiny scene (about 300 grains) on the CPU.
"""

import argparse
import json
import math
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", nargs="?", help="scene file (default: the tests' tiny scene on the CPU)")
    parser.add_argument("--steps", type=int, default=40, help="macro steps per measurement")
    parser.add_argument("--substeps", default="1,10", help="DEM steps per macro step, comma separated")
    args = parser.parse_args()

    import warp as wp

    wp.config.quiet = True
    from fmpy import extract, read_model_description
    from fmpy.fmi2 import FMU2Slave

    from cosim.contract import WheelKinematics
    from cosim.scene import load_scene
    from cosim.soil_fmu import export_soil_fmu, soil_config_from
    from cosim.soil_fmu.config import soil_from_config
    from soil import quiet_warp

    quiet_warp()
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        scene_file = args.scene
        if scene_file is None:
            from helpers import TINY_SCENE

            scene_file = folder / "tiny.toml"
            scene_file.write_text(TINY_SCENE.replace('precision = "mixed"', 'precision = "mixed"\ndevice = "cpu"'))
        config = soil_config_from(scene_file, bed_folder=folder)
        path = export_soil_fmu(config, folder / "soil.fmu")
        md = read_model_description(str(path))
        var = {v.name: v for v in md.modelVariables}
        hub0 = np.array([float(var[f"wheel_0.position.{a}"].start) for a in "xyz"]) - [0, 0, 0.004]
        names = [
            f"wheel_0.{q}.{a}"
            for q, axes in (
                ("position", "xyz"),
                ("orientation", "wxyz"),
                ("velocity", "xyz"),
                ("angular_velocity", "xyz"),
            )
            for a in axes
        ]
        refs = [var[n].valueReference for n in names]
        outputs = [var[f"wheel_0.{q}.{a}"].valueReference for q in ("force", "torque") for a in "xyz"]
        speed, spin = 0.02, 0.8

        def kinematics(t):
            return WheelKinematics(
                hub0 + [speed * t, 0, 0],
                (math.cos(spin * t / 2), 0, math.sin(spin * t / 2), 0),
                (speed, 0, 0),
                (0, spin, 0),
            )

        def values(k):
            return [*k.position, *k.orientation, *k.linear_velocity, *k.angular_velocity]

        scene = load_scene(scene_file)
        print(
            f"scene {scene_file}: {scene.scene.device}, precision {scene.scene.precision}, "
            f"DEM step {config.dem_step:.4g} s"
        )
        for substeps in [int(s) for s in args.substeps.split(",")]:
            h = substeps * config.dem_step
            with zipfile.ZipFile(path) as z:
                soil = soil_from_config(json.loads(z.read("resources/soil.json")), config.bed_file)
            fmu = FMU2Slave(
                guid=md.guid,
                unzipDirectory=extract(str(path)),
                modelIdentifier=md.coSimulation.modelIdentifier,
                instanceName="soil",
            )
            fmu.instantiate()
            fmu.setupExperiment(startTime=0.0)
            fmu.enterInitializationMode()
            fmu.setReal(refs, values(kinematics(0.0)))
            started = time.perf_counter()
            fmu.exitInitializationMode()
            start_time = time.perf_counter() - started
            soil.place_wheels([kinematics(0.0)])
            wall_fmu = wall_soil = 0.0
            equal = True
            t = 0.0
            for _ in range(args.steps):
                k = kinematics(t)
                started = time.perf_counter()
                fmu.setReal(refs, values(k))
                fmu.doStep(t, h)
                got = fmu.getReal(outputs)
                wall_fmu += time.perf_counter() - started
                started = time.perf_counter()
                w = soil.advance(soil.time + h, [k])[0]
                wall_soil += time.perf_counter() - started
                equal &= got == [*w.force, *w.torque]
                t += h
            fmu.terminate()
            fmu.freeInstance()
            n = soil.sim.model.particle_count
            print(
                f"{n} grains, {substeps} DEM step(s) per macro step, {args.steps} macro steps: server start "
                f"{start_time:.2f} s; per macro step FMU {1e3 * wall_fmu / args.steps:.2f} ms, in-process "
                f"{1e3 * wall_soil / args.steps:.2f} ms, ratio {wall_fmu / wall_soil:.2f}; "
                f"wrenches bitwise equal: {equal}"
            )


if __name__ == "__main__":
    main()
