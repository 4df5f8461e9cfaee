"""regolith-cosim coupling layer.

Kept light on purpose: importing `cosim` pulls in nothing but the standard library; the protocols below
load (with numpy and the soil package, and so warp) on first use. The MuJoCo and FMU adapters live in
`rover_models` and import their heavy dependencies themselves.

Modules:
    contract     the soil <-> rover protocols (WheelKinematics, WheelWrench, SoilSide, RoverSide)
    terrain      SpringDamperTerrain, an analytic SoilSide standing in for the DEM
    coupler      Coupler (Gauss-Seidel / Jacobi macro stepping, energy bookkeeping)
    controllers  drive controllers (constant speed, slip/traction control)
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .contract import RoverSide, SoilSide, WheelKinematics, WheelWrench

__all__ = ["RoverSide", "SoilSide", "WheelKinematics", "WheelWrench"]


def __getattr__(name: str):
    # the contract's names on first use: `cosim.cli` starts on the standard library alone, so Ctrl-C while
    # the heavy modules load (warp: about a second) is its own to answer
    if name in __all__:
        from . import contract

        return getattr(contract, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
