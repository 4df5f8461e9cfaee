"""The results writer's cost per particle snapshot as a run's snapshots accumulate (results.h5, its
XDMF and the XDMF's data file), for this checkout or another one.

    python benchmarks/writer_cost.py                                 # this checkout
    python benchmarks/writer_cost.py --compare /path/to/old          # the other checkout and this one, in turn

A ResultsWriter of the main job's size (5,642 grains, one grousered wheel's mesh) writes --snapshots
snapshots, a macro step's records between them; the figure is the wall per snapshot over the first
and the last tenth of them. A writer whose cost per snapshot grows with the snapshots so far makes
a run's writing quadratic in its snapshot count (a movie's 0.1 s snapshots over 60 s: 600).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def measure(grains: int, snapshots: int) -> dict:
    import numpy as np

    from cosim.output import ROVER_SERIES, SOIL_SERIES, WHEEL_SERIES, ResultsWriter
    from cosim.single_wheel import PHASE_DRIVING
    from soil import GrouserWheel

    mesh = GrouserWheel(radius=0.03, width=0.032, grouser_count=10, grouser_height=0.003, grouser_thickness=0.002)
    vertices, triangles = mesh.to_mesh(arc_segments=240)  # as cosim.system.CoupledSystem.wheel_mesh
    rng = np.random.default_rng(1)
    position = rng.uniform(0.0, 0.1, (grains, 3))

    def record(t):
        row = {"time": t, "phase": PHASE_DRIVING, "rover_state": [t]}
        for name, (tail, *_) in WHEEL_SERIES.items():
            row[name] = np.full((1,) if tail is None else (1, tail), t)
        for name, (tail, *_) in ROVER_SERIES.items():
            row[f"rover_{name}"] = np.full(() if tail is None else (tail,), t)
        for name in SOIL_SERIES:
            row[f"soil_{name}"] = t
        return row

    seconds = []
    with tempfile.TemporaryDirectory() as folder:
        writer = ResultsWriter.create(
            os.path.join(folder, "results.h5"),
            attrs={"name": "writer_cost"},
            radius=np.full(grains, 2e-3),
            wheel_count=1,
            mesh=(vertices, triangles, np.zeros(len(vertices), int)),
            rover_columns=["x"],
            rover_units=["m"],
        )
        for k in range(snapshots):
            writer.append_step(record(0.1 * k))
            started = time.perf_counter()
            writer.add_snapshot(0.1 * k, position, position, vertices)
            seconds.append(time.perf_counter() - started)
        writer.close("complete")
    tenth = max(1, snapshots // 10)
    return {
        "grains": grains,
        "snapshots": snapshots,
        "first_tenth_ms_per_snapshot": 1e3 * float(np.mean(seconds[:tenth])),
        "last_tenth_ms_per_snapshot": 1e3 * float(np.mean(seconds[-tenth:])),
        "total_s": float(np.sum(seconds)),
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", default=ROOT, help="checkout whose cosim and soil packages to measure")
    parser.add_argument("--compare", help="another checkout: measure it, then this one")
    parser.add_argument("--grains", type=int, default=5642)
    parser.add_argument("--snapshots", type=int, default=200)
    parser.add_argument("--json", action="store_true", help="print the result as one JSON line")
    args = parser.parse_args(argv)
    sizes = ["--grains", str(args.grains), "--snapshots", str(args.snapshots)]
    if args.compare:
        for name, source in (("other", os.path.abspath(args.compare)), ("this", ROOT)):
            done = subprocess.run(
                [sys.executable, os.path.abspath(__file__), "--source", source, "--json", *sizes],
                capture_output=True,
                text=True,
                check=True,
                env={**os.environ, "PYTHONPATH": source},
            )
            print(name, done.stdout.strip().splitlines()[-1], flush=True)
        return
    sys.path.insert(0, os.path.abspath(args.source))
    result = measure(args.grains, args.snapshots)
    result["source"] = os.path.dirname(os.path.dirname(os.path.abspath(sys.modules["cosim"].__file__)))
    print(json.dumps(result) if args.json else json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
