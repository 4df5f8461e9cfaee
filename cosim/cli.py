"""The `cosim` command line (also `python -m cosim`).

    cosim run SCENE.toml [--out DIR] [--device D] [--precision P] [--set key=value ...] [--overwrite]
    cosim resume OUT
    cosim advise SCENE.toml [--set key=value ...] [--overlap-factor U]
    cosim plot OUT
    cosim study precision SCENE.toml --replicas N [--precisions single,mixed,double] [--out DIR]
                                     [--workers N | --scheduler ADDRESS | --serial]
    cosim study timestep SCENE.toml [--out DIR] [--duration S]
    cosim sweep SCENE.toml --param wheel.radius=0.03,0.04 --param wheel.grouser_count=0,12 [--out DIR] ...

Exit status: 0 done, 1 unexpected error, 2 bad scene or arguments, 3 output folder not
empty (nothing overwritten), 4 the simulation diverged, 130 interrupted (resume it).
"""

from __future__ import annotations

import argparse
import math
import os
import sys

EXIT_OK, EXIT_ERROR, EXIT_SCENE, EXIT_EXISTS, EXIT_DIVERGED, EXIT_INTERRUPTED = 0, 1, 2, 3, 4, 130


def _quiet_warp():
    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no per-module load lines


def _overrides(args) -> list[str]:
    overrides = list(getattr(args, "set", None) or [])
    if getattr(args, "device", None):
        overrides.append(f'scene.device="{args.device}"')
    if getattr(args, "precision", None):
        overrides.append(f'scene.precision="{args.precision}"')
    return overrides


def _load(args):
    from .scene import load_scene

    return load_scene(args.scene, _overrides(args))


def cmd_run(args) -> int:
    from .runner import run_scene

    scene = _load(args)
    out = args.out or os.path.join("runs", scene.scene.name)
    _quiet_warp()
    result = run_scene(args.scene, out, overwrite=args.overwrite, progress=not args.no_progress,
                       overrides=_overrides(args))
    _print_summary(result)
    return EXIT_OK


def cmd_resume(args) -> int:
    from .runner import resume

    _quiet_warp()
    result = resume(args.out, progress=not args.no_progress)
    _print_summary(result)
    return EXIT_OK


def _print_summary(result) -> None:
    s = result.summary
    print(f"{result.status}: {result.out_dir}")
    for key in ("simulated_time", "travel", "mean_slip", "mean_sinkage", "mean_drawbar_pull", "wall_time",
                "particle_count", "particle_steps_per_second"):
        if key in s:
            value = s[key]
            print(f"  {key:26s} {value:.6g}" if isinstance(value, float) else f"  {key:26s} {value}")


def cmd_plot(args) -> int:
    from .plots import plot_output

    for path in plot_output(args.out, args.plot_dir):
        print(path)
    return EXIT_OK


def cmd_advise(args) -> int:
    scene = _load(args)
    for line in advise(scene, overlap_factor=args.overlap_factor):
        print(line)
    return EXIT_OK


def advise(scene, overlap_factor: float = 0.01) -> list[str]:
    """Stiffness and time-step advice for a scene (uses soil.advisor)."""
    from soil import advisor

    soil = scene.soil_material()
    bed = scene.bed
    g = scene.gravity_magnitude()
    r_min = bed.radius_mean * (1 - bed.radius_spread)
    outer, width, _ = scene.wheel_extent()
    weight = scene.testbed.mass * g
    # ground pressure: the weight over the wheel's width times a contact length of
    # 2 sqrt(2 R s) at a sinkage s of one mean grain radius
    contact_length = 2.0 * math.sqrt(2.0 * outer * bed.radius_mean)
    pressure = weight / (width * contact_length)
    height = bed.depth
    e_min = advisor.macroscopic_stiffness(height, pressure, overlap_factor, bed.radius_mean, soil.density, g)
    rayleigh = advisor.rayleigh_time_step(soil.youngs_modulus, soil.poisson_ratio, soil.density, r_min)
    rim_speed = abs(scene.testbed.omega) * outer
    speed = math.sqrt(2 * g * height) + rim_speed
    contact = advisor.hertz_contact_time(soil.youngs_modulus, soil.poisson_ratio, soil.density, r_min,
                                         max(speed, 1e-9))
    advice = advisor.recommended_time_step(soil, radius=r_min, gravity=g, height=height, pressure=pressure)
    dt, h, substeps = scene.time_steps()
    lines = [
        f"scene {scene.scene.name}: |g| = {g:.4g} m/s^2, grains r = {bed.radius_mean:.4g} m "
        f"(smallest {r_min:.4g} m), E = {soil.youngs_modulus:.4g} Pa",
        f"  wheel ground pressure p    {pressure:.4g} Pa  (weight {weight:.4g} N over {width:.3g} m x "
        f"{contact_length:.3g} m)",
        f"  eq. 10 stiffness E_mP >=   {e_min:.4g} Pa  (z_h = {height:.3g} m, overlap factor u = {overlap_factor:g}); "
        f"the scene's E is {'OK' if soil.youngs_modulus >= e_min else 'TOO SOFT: overlaps exceed u r'}"
        f" ({soil.youngs_modulus / e_min:.3g} x)",
        f"  Rayleigh step              {rayleigh:.4g} s  (0.1..0.3 x: {0.1 * rayleigh:.3g} .. {0.3 * rayleigh:.3g} s)",
        f"  Hertz contact time         {contact:.4g} s  (two smallest grains at {speed:.3g} m/s)",
        f"  recommended dt range       {advice.dt_min:.4g} .. {advice.dt_max:.4g} s  (critical step "
        f"{advice.critical_step:.4g} s)",
        f"  the scene uses dt = {dt:.4g} s, macro step H = {h:.4g} s ({substeps} substeps), "
        f"{scene.macro_step_count()} macro steps; "
        + ("dt is within the advised limit" if dt <= advice.dt_max else "dt is ABOVE the advised limit"),
        "  largest stable step by trial: cosim study timestep SCENE",
    ]
    return lines


def _study_args(args) -> dict:
    executor = "serial" if args.serial else "dask"
    return dict(executor=executor, scheduler=args.scheduler, workers=args.workers, overwrite=args.overwrite)


def cmd_study(args) -> int:
    from . import study

    scene = _load(args)
    _quiet_warp()
    if args.kind == "precision":
        out = args.out or os.path.join("runs", f"{scene.scene.name}_precision")
        precisions = [p.strip() for p in args.precisions.split(",") if p.strip()]
        report = study.precision_study(scene, out, replicas=args.replicas, precisions=precisions, **_study_args(args))
        failed = sum(1 for r in report["replicas"] if not r.get("ok"))
        print(f"study written to {out} ({failed} failed replica(s))")
        return EXIT_OK if failed == 0 else EXIT_ERROR
    out = args.out or os.path.join("runs", f"{scene.scene.name}_timestep")
    study.timestep_study(scene, out, duration=args.duration, overwrite=args.overwrite)
    return EXIT_OK


def cmd_sweep(args) -> int:
    from . import study

    scene = _load(args)
    _quiet_warp()
    out = args.out or os.path.join("runs", f"{scene.scene.name}_sweep")
    report = study.sweep(scene, out, args.param, **_study_args(args))
    failed = sum(1 for r in report["rows"] if not r.get("ok"))
    print(f"sweep written to {out} ({failed} failed point(s))")
    return EXIT_OK if failed == 0 else EXIT_ERROR


def cmd_export_fmu(args) -> int:
    """cosim export-fmu SCENE_OR_RUN_DIR --out soil.fmu [--fmi 2|3] [--wheels N] (docs/fmu.md)."""
    import tempfile

    from .soil_fmu import export_soil_fmu, soil_config_from

    _quiet_warp()
    with tempfile.TemporaryDirectory(prefix="soil_fmu_bed_") as scratch:
        config = soil_config_from(args.source, bed_folder=args.bed_folder or scratch)
        if args.device:
            config.device = args.device
        path = export_soil_fmu(config, args.out, fmi_version=args.fmi, wheel_count=args.wheels, python=args.python)
    print(f"wrote {path}: FMI {args.fmi}.0 co-simulation, {args.wheels} wheel(s), DEM step {config.dem_step:.4g} s, "
          f"surface z = {config.surface_height:.4g} m; the soil server runs on {config.device}")
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cosim", description="regolith-cosim: DEM soil co-simulated with rovers")
    sub = parser.add_subparsers(dest="command", required=True)

    def scene_options(p, device=True):
        p.add_argument("scene", help="scene file (TOML)")
        p.add_argument("--set", action="append", metavar="KEY=VALUE",
                       help="override a scene key, e.g. --set wheel.radius=0.05 (repeatable)")
        if device:
            p.add_argument("--device", help="Warp device: cpu, cuda, cuda:N (overrides scene.device)")
            p.add_argument("--precision", choices=["single", "double", "mixed"],
                           help="overrides scene.precision")

    p = sub.add_parser("run", help="run a scene")
    scene_options(p)
    p.add_argument("--out", help="output folder (default runs/<scene name>)")
    p.add_argument("--overwrite", action="store_true", help="replace the run in a non-empty output folder")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("resume", help="continue an interrupted run from its checkpoint")
    p.add_argument("out", help="the run's output folder")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_resume)

    p = sub.add_parser("advise", help="stiffness (paper eq. 10) and time-step advice for a scene")
    scene_options(p)
    p.add_argument("--overlap-factor", type=float, default=0.01, help="allowed overlap / radius (eq. 10's u)")
    p.set_defaults(func=cmd_advise)

    p = sub.add_parser("plot", help="PNGs of travel, sinkage, slip, drawbar pull")
    p.add_argument("out", help="a run folder or a study folder")
    p.add_argument("--plot-dir", help="where to write the PNGs (default OUT/plots)")
    p.set_defaults(func=cmd_plot)

    def cluster_options(p):
        p.add_argument("--out", help="output folder")
        p.add_argument("--workers", type=int, help="LocalCluster worker processes (default: CPU cores)")
        p.add_argument("--scheduler", help="address of a running dask scheduler (instead of a LocalCluster)")
        p.add_argument("--serial", action="store_true", help="run the tasks one after another in this process")
        p.add_argument("--overwrite", action="store_true")

    p = sub.add_parser("study", help="precision (replica scatter) or time-step studies")
    p.add_argument("kind", choices=["precision", "timestep"])
    scene_options(p)
    cluster_options(p)
    p.add_argument("--replicas", type=int, default=3, help="replicas per precision (the paper: 20)")
    p.add_argument("--precisions", default="single,mixed,double")
    p.add_argument("--duration", type=float, default=0.2, help="timestep: simulated time of each try [s]")
    p.set_defaults(func=cmd_study)

    p = sub.add_parser("sweep", help="runs over a grid of scene values")
    scene_options(p)
    cluster_options(p)
    p.add_argument("--param", action="append", required=True, metavar="KEY=V1,V2,...")
    p.set_defaults(func=cmd_sweep)

    p = sub.add_parser("export-fmu", help="the soil as an FMI 2.0/3.0 co-simulation FMU (docs/fmu.md)")
    p.add_argument("source", help="a scene file (TOML) or a run folder")
    p.add_argument("--out", required=True, help="the .fmu file to write")
    p.add_argument("--fmi", type=int, choices=[2, 3], default=2, help="FMI version (default 2)")
    p.add_argument("--wheels", type=int, default=1, help="wheels in one FMU instance, on one bed (default 1)")
    p.add_argument("--device", help="the soil server's default Warp device (default: the scene's)")
    p.add_argument("--python", help="the soil server's default Python (default: this one)")
    p.add_argument("--bed-folder", help="where a scene's bed is settled and cached (default: a temporary folder)")
    p.set_defaults(func=cmd_export_fmu)
    return parser


def main(argv=None) -> int:
    from .runner import OutputExistsError, RunDiverged
    from .scene import SceneError

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except SceneError as error:
        print(f"cosim: error: {error}", file=sys.stderr)
        return EXIT_SCENE
    except (OutputExistsError, FileExistsError) as error:
        print(f"cosim: error: {error}", file=sys.stderr)
        return EXIT_EXISTS
    except RunDiverged as error:
        print(f"cosim: error: {error}", file=sys.stderr)
        return EXIT_DIVERGED
    except KeyboardInterrupt as error:
        print(f"\ncosim: interrupted. {error}".rstrip(), file=sys.stderr)
        return EXIT_INTERRUPTED
    except (FileNotFoundError, ValueError) as error:
        print(f"cosim: error: {error}", file=sys.stderr)
        return EXIT_ERROR


if __name__ == "__main__":
    sys.exit(main())
