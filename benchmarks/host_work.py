"""The host's own work per macro step of a coupled run (what a GPU waits on between DEM steps), for
this checkout or another one.

    python benchmarks/host_work.py                          # this checkout
    python benchmarks/host_work.py --compare /path/to/old   # the other checkout and this one, in turn

A run of the main job (examples/phobos_single_wheel.toml through cosim.launch.run_plan, as `cosim
run` does) at the GPU suite's small batched sizes (benchmarks/gpu_suite.py BATCH_OVERRIDES: 364
coarse grains, landing off), so that its DEM steps are cheap and the host's part is large. The
host work per macro step is the wall between the run's macro steps less the time spent in its DEM
steps (Simulation._run_step: on the CPU they compute there; on a GPU they only launch): the rig,
the coupler, the soil's bookkeeping around its steps (path, report, checks), the records and the
results writer. Of it, the rows' share: making and writing a step's row (cosim.records.step_row,
ResultsWriter.append_step), which the runner does while the soil computes the next step (on a GPU
it then overlaps the device's steps; on the CPU the DEM steps compute at their launch, so nothing
overlaps here). The run is made once first (kernels compiled, the bed settled), then timed; with
--profile the timed run is also profiled (cProfile: its cumulative times by function).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WARMUP_STEPS = 10
"""Macro steps left out of the timing (the first steps capture their graphs)."""


def measure(source: str, duration: float, profile: bool) -> dict:
    sys.path.insert(0, source)
    sys.path.insert(0, os.path.join(source, "benchmarks"))
    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    import logging

    logging.disable(logging.WARNING)
    import gpu_suite

    from cosim import records
    from cosim.beds import settled_bed
    from cosim.launch import run_plan
    from cosim.output import ResultsWriter
    from cosim.plan import load_plan
    from soil.simulation import Simulation

    overrides = {
        "scene.device": "cpu",
        **gpu_suite.QUIET_OUTPUT,
        **gpu_suite.BATCH_OVERRIDES[0],
        **gpu_suite.BATCH_OVERRIDES[1],
        "run.duration": duration,
    }
    folder = tempfile.mkdtemp(prefix="host_work_")
    bed = settled_bed(load_plan(gpu_suite.MAIN_SCENE, overrides), folder)
    plan = load_plan(gpu_suite.MAIN_SCENE, {**overrides, "bed.bed_file": os.path.abspath(bed.path)})
    run_plan(plan, os.path.join(folder, "warm"), overwrite=True)

    clocks = {"dem": 0.0, "rows": 0.0}

    def timed(function, clock):
        def run(*args, **kwargs):
            started = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                clocks[clock] += time.perf_counter() - started

        return run

    Simulation._run_step = timed(Simulation._run_step, "dem")  # type: ignore[method-assign]
    records.step_row = timed(records.step_row, "rows")
    ResultsWriter.append_step = timed(ResultsWriter.append_step, "rows")  # type: ignore[method-assign]
    marks: list[tuple[float, float, float]] = []
    hooks = {"step": lambda runner: marks.append((time.perf_counter(), clocks["dem"], clocks["rows"]))}
    profiler = None
    if profile:
        import cProfile

        profiler = cProfile.Profile()
        profiler.enable()
    status = run_plan(plan, os.path.join(folder, "timed"), overwrite=True, hooks=hooks)
    if profiler is not None:
        profiler.disable()
        import pstats

        pstats.Stats(profiler, stream=sys.stderr).sort_stats("cumulative").print_stats(45)
    (wall0, dem0, rows0), (wall1, dem1, rows1) = marks[WARMUP_STEPS - 1], marks[-1]
    steps = len(marks) - WARMUP_STEPS
    return {
        "source": source,
        "status": status.status,
        "timed_macro_steps": steps,
        "wall_ms_per_macro_step": 1e3 * (wall1 - wall0) / steps,
        "dem_ms_per_macro_step": 1e3 * (dem1 - dem0) / steps,
        "host_ms_per_macro_step": 1e3 * ((wall1 - wall0) - (dem1 - dem0)) / steps,
        "rows_ms_per_macro_step": 1e3 * (rows1 - rows0) / steps,
        "profiled": profile,
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", default=ROOT, help="checkout whose packages to measure")
    parser.add_argument("--compare", help="another checkout: measure it and this one in turn, --repeats times")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--duration", type=float, default=0.6, help="simulated drive [s] (0.6: 319 macro steps)")
    parser.add_argument("--profile", action="store_true", help="also print the timed run's profile (stderr)")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON line")
    args = parser.parse_args(argv)
    if args.compare:
        from checkouts import in_turn

        keys = ("wall_ms_per_macro_step", "dem_ms_per_macro_step", "host_ms_per_macro_step", "rows_ms_per_macro_step")
        median = in_turn(__file__, args.compare, ["--duration", str(args.duration)], args.repeats, keys)
        print(
            f"host work per macro step, other / this: "
            f"{median['other']['host_ms_per_macro_step'] / median['this']['host_ms_per_macro_step']:.2f}"
        )
        return
    result = measure(os.path.abspath(args.source), args.duration, args.profile)
    print(json.dumps(result) if args.json else json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
