"""Floating-point precision modes (docs/physics.md section 3) and the one kernel factory cache.

`hi` is the type of everything where rounding accumulates against a small physical
scale: absolute positions and their updates, velocities, forces and their sums, wheel and
wall wrenches, the neighbour list's build positions, and the differences a contact starts
from (two positions, two velocities). Arithmetic is done in `hi` unless said otherwise.
`mid` is the stored type of what the error analysis allows in 7 digits (docs/physics.md
section 3): angular velocities, torques, and the contact history (tangential springs,
rolling and twist angles). It is read into `hi`, updated there, and rounded when stored.
`lo` is the type of the per-particle constants, of the contact law, and of the whole of a
grain pair's contact once its differences are taken in `hi`: every value it computes is
then relative to those differences, and 7 digits of each suffice.

- single: hi = mid = lo = float32
- double: hi = mid = lo = float64
- mixed:  hi = float64, mid = lo = float32

One generic source serves every precision: a module's kernels are made by a factory
function of (hi, mid, lo, switches) decorated with `kernel_factory`, which builds them once
per combination and returns them as attributes (`kernels.grain_contacts`). Where mid is hi
(single, double) its conversions are the identity: those precisions compute exactly as
they did before mid existed.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import warp as wp

from .errors import SoilInputError

PRECISIONS = ("single", "double", "mixed")
"""The precisions a simulation runs in (module docstring: what each keeps in float32 and float64)."""


@dataclass(frozen=True)
class Precision:
    name: str
    hi: type
    """Positions, velocities, forces and all arithmetic (module docstring)."""
    lo: type
    """The contact law's evaluation and the per-grain constants."""
    mid: type
    """Stored spins, torques and contact history (module docstring)."""

    @property
    def vec_hi(self):
        return wp.types.vector(3, self.hi)

    @property
    def vec_mid(self):
        return wp.types.vector(3, self.mid)

    @property
    def mat_hi(self):
        return wp.types.matrix((3, 3), self.hi)

    @property
    def np_hi(self):
        return np.float64 if self.hi is wp.float64 else np.float32

    @property
    def np_lo(self):
        return np.float64 if self.lo is wp.float64 else np.float32

    @property
    def np_mid(self):
        return np.float64 if self.mid is wp.float64 else np.float32


def get_precision(name: str) -> Precision:
    """Return the Precision for 'single', 'double' or 'mixed'."""
    if isinstance(name, Precision):
        return name
    if name == "single":
        return Precision("single", wp.float32, wp.float32, wp.float32)
    if name == "double":
        return Precision("double", wp.float64, wp.float64, wp.float64)
    if name == "mixed":
        return Precision("mixed", wp.float64, wp.float32, wp.float32)
    raise SoilInputError(f"precision must be one of {PRECISIONS}, got {name!r}")


def kernel_module(name: str, *key) -> str:
    """The Warp module of one kernel-factory call (e.g. `kernel_module("contact", hi, mid, lo, law)`):
    its kernels compile together, once per combination."""

    def part(value):
        if isinstance(value, type):
            return value.__name__
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            return "".join("1" if v else "0" for v in dataclasses.astuple(value))
        return str(value)

    return "soil_" + "_".join([name] + [part(k) for k in key])


def soil_kernel(module: str):
    """Decorator of the soil's kernels: compiled in `module` (kernel_module), forward only
    (nothing differentiates through the DEM, so no adjoint code is generated)."""
    return wp.kernel(module=module, enable_backward=False)


def kernel_factory(build):
    """Cache a factory of Warp functions and kernels per argument tuple (precision types,
    contact-law switches). The factory returns a dict of its kernels; callers get them as
    attributes of a namespace, built once per combination."""

    @functools.cache
    def cached(*args):
        return SimpleNamespace(**build(*args))

    cached.__doc__ = build.__doc__
    cached.__name__ = build.__name__
    return cached
