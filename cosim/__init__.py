"""regolith-cosim coupling layer.

Kept light on purpose: importing `cosim` pulls in numpy only. The MuJoCo and FMU
adapters live in `rover_models` and import their heavy dependencies themselves.

Modules:
    contract     the soil <-> rover protocols (WheelKinematics, WheelWrench, SoilSide, RoverSide)
    terrain      SpringDamperTerrain, an analytic SoilSide standing in for the DEM
    coupler      Coupler (Gauss-Seidel / Jacobi macro stepping, energy bookkeeping)
    controllers  drive controllers (constant speed, slip/traction control)
"""

from .contract import RoverSide, SoilSide, WheelKinematics, WheelWrench

__all__ = ["RoverSide", "SoilSide", "WheelKinematics", "WheelWrench"]
