"""What reading and opening a settled bed costs, side by side in one process: read_bed of a bed file
without the SHA-256 digest (written before 2026-12-06) and of the same bed with it; the rows put in
partner order when the bed opens under an order seed (soil.grains.rows_in_partner_order), against
the same rows already in order.

    python benchmarks/bed_open.py BED.h5 [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

from soil.bed import DIGEST_ATTRIBUTE, read_bed
from soil.grains import rows_in_partner_order


def best_of(repeats: int, work) -> float:
    """The shortest wall time [s] of `repeats` calls of work()."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        work()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bed", help="a bed file (a run's bed.h5)")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    import h5py

    with tempfile.TemporaryDirectory() as folder:
        with_digest, without = os.path.join(folder, "with.h5"), os.path.join(folder, "without.h5")
        bed = read_bed(args.bed)
        bed.write(with_digest)
        bed.write(without)
        with h5py.File(without, "a") as f:
            del f.attrs[DIGEST_ATTRIBUTE]
        plain = best_of(args.repeats, lambda: read_bed(without))
        checked = best_of(args.repeats, lambda: read_bed(with_digest))
    rows = {name: value for name, value in bed.state.items()}
    n = len(bed.radius)
    order = np.random.default_rng(1).permutation(n)  # an order seed's renumbering of the rows
    inverse = np.empty_like(order)
    inverse[order] = np.arange(n)
    shuffled = {k: (np.asarray(v)[order] if np.ndim(v) and len(v) == n else v) for k, v in rows.items()}
    neighbours = shuffled["neighbours"]
    shuffled["neighbours"] = np.where(neighbours >= 0, inverse[np.maximum(neighbours, 0)], -1).astype(np.int32)
    ordered = rows_in_partner_order(shuffled)
    sort = best_of(args.repeats, lambda: rows_in_partner_order(shuffled))
    skip = best_of(args.repeats, lambda: rows_in_partner_order(ordered))
    megabytes = os.path.getsize(args.bed) / 1e6
    print(f"bed: {n} grains, {megabytes:.1f} MB, list width {rows['neighbours'].shape[1]}; best of {args.repeats}")
    print(f"read_bed without digest {plain * 1e3:.1f} ms, with digest {checked * 1e3:.1f} ms ({checked / plain:.2f} x)")
    print(f"rows renumbered put in partner order {sort * 1e3:.1f} ms, rows already in order {skip * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
