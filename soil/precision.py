"""Floating-point precision modes (DESIGN.md section 4).

`hi` is the type of everything where rounding accumulates: absolute positions and
their updates, velocities, force/torque sums, contact history, wheel wrench sums.
`lo` is the type of the contact-law evaluation and the per-particle constants.

- single: hi = lo = float32
- double: hi = lo = float64
- mixed:  hi = float64, lo = float32
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

PRECISIONS = ("single", "double", "mixed")


@dataclass(frozen=True)
class Precision:
    name: str
    hi: type
    lo: type

    @property
    def vec_hi(self):
        return wp.types.vector(3, self.hi)

    @property
    def np_hi(self):
        return np.float64 if self.hi is wp.float64 else np.float32

    @property
    def np_lo(self):
        return np.float64 if self.lo is wp.float64 else np.float32


def get_precision(name: str) -> Precision:
    """Return the Precision for 'single', 'double' or 'mixed'."""
    if isinstance(name, Precision):
        return name
    if name == "single":
        return Precision("single", wp.float32, wp.float32)
    if name == "double":
        return Precision("double", wp.float64, wp.float64)
    if name == "mixed":
        return Precision("mixed", wp.float64, wp.float32)
    raise ValueError(f"precision must be one of {PRECISIONS}, got {name!r}")
