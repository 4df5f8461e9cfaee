"""Two checkouts of the project measured in turn by one benchmark script (its --compare mode).

    median = in_turn(__file__, other_checkout, ["--grains", "8000"], repeats=5, keys=("wall_ms",))

Runs `script --source CHECKOUT --json ARGS` for the other checkout and this one, alternately,
`repeats` times each (so both see the same machine load), prints every result as it comes and the
medians of `keys`, and returns those medians by name: {"other": {...}, "this": {...}}.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def in_turn(script: str, other: str, args: list[str], repeats: int, keys: tuple[str, ...]) -> dict:
    sources = {"other": os.path.abspath(other), "this": ROOT}
    runs: dict = {name: [] for name in sources}
    for _ in range(repeats):
        for name, source in sources.items():
            done = subprocess.run(
                [sys.executable, os.path.abspath(script), "--source", source, "--json", *args],
                capture_output=True,
                text=True,
                check=True,
            )
            runs[name].append(json.loads(done.stdout.strip().splitlines()[-1]))
            print(name, json.dumps(runs[name][-1]), flush=True)
    median = {name: {key: statistics.median(r[key] for r in rows) for key in keys} for name, rows in runs.items()}
    for name, source in sources.items():
        print(f"{name} ({source}): median of {repeats}: {json.dumps(median[name])}")
    return median
