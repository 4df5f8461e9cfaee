"""Are two runs' results.h5 equal to the last bit? (a refactor's check: same scene, same machine)

    python benchmarks/compare_runs.py runs/before/results.h5 runs/after/results.h5

Compares every dataset (shape, dtype and bytes) and every attribute of both files, except the
attributes that name the run rather than its physics (run id, wall times, dates, paths, a bed's
source (cache or settled), software versions), with the folder above each run folder (where its
scene and the scene's own files lie) written the same in both. Exit 0 when equal, 1 with the differences listed.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import h5py
import numpy as np

RUN_SPECIFIC = (
    "run_id",
    "wall",
    "date",
    "created",
    "per_second",
    "path",
    "version",
    "host",
    "machine",
    "started",
    "finished",
    "source",
)
"""Attribute names (substrings, case-insensitive) that differ between two runs of the same physics."""


def _skip(name: str) -> bool:
    return any(word in name.lower() for word in RUN_SPECIFIC)


def _json_free_of_run_fields(value):
    """A JSON attribute (the summary, the plan) without its run-specific fields, to compare the rest."""
    if isinstance(value, dict):
        return {k: _json_free_of_run_fields(v) for k, v in value.items() if not _skip(k)}
    if isinstance(value, list):
        return [_json_free_of_run_fields(v) for v in value]
    return value


def _attribute(value, folder: str):
    if isinstance(value, bytes):
        value = value.decode()
    if isinstance(value, str):
        value = value.replace(folder, "<scene folder>")  # a scene's own files, named by absolute path
        try:
            return _json_free_of_run_fields(json.loads(value))
        except ValueError:
            return value
    return np.asarray(value)


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()
    return a == b


def compare(path_a: str, path_b: str) -> list[str]:
    """The differences between two results files (empty when equal to the last bit)."""
    differences: list[str] = []
    folders = [os.path.dirname(os.path.dirname(os.path.abspath(p))) for p in (path_a, path_b)]
    with h5py.File(path_a, "r") as fa, h5py.File(path_b, "r") as fb:
        names_a: dict[str, object] = {}
        names_b: dict[str, object] = {}
        fa.visititems(lambda n, o: names_a.__setitem__(n, o))
        fb.visititems(lambda n, o: names_b.__setitem__(n, o))
        for name in sorted(set(names_a) ^ set(names_b)):
            differences.append(f"{name}: only in {'the first' if name in names_a else 'the second'} file")
        for name in ["/"] + sorted(set(names_a) & set(names_b)):
            oa, ob = fa[name], fb[name]
            if isinstance(oa, h5py.Dataset) and isinstance(ob, h5py.Dataset):
                if not _same(oa[()], ob[()]):
                    differences.append(f"{name}: dataset differs")
            for key in sorted(set(oa.attrs) | set(ob.attrs)):
                if _skip(key):
                    continue
                if key not in oa.attrs or key not in ob.attrs:
                    differences.append(f"{name} attribute {key}: only in one file")
                elif not _same(_attribute(oa.attrs[key], folders[0]), _attribute(ob.attrs[key], folders[1])):
                    differences.append(f"{name} attribute {key}: differs")
    return differences


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("first")
    parser.add_argument("second")
    args = parser.parse_args()
    differences = compare(args.first, args.second)
    for line in differences:
        print(line)
    print("equal to the last bit" if not differences else f"{len(differences)} differences")
    return 0 if not differences else 1


if __name__ == "__main__":
    sys.exit(main())
