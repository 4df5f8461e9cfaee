"""regolith-cosim coupling layer.

Kept light on purpose: importing `cosim` pulls in nothing but the standard library; the protocols below
load (with numpy and the soil package, and so warp) on first use. The MuJoCo and FMU adapters live in
`rover_models` and import their heavy dependencies themselves.

Modules, along the one path from a scene to results:
    scene, plan     the scene file (validated) and the run plan derived from it (frozen; probe: what it
                    opens to resolve a scene: devices, rover models, drives)
    beds            the settled bed a run starts on (settled or loaded, cached per bed key)
    system          the coupled system: the soil side (TERRAIN_MODELS), the rover side, the coupler
    contract        the soil <-> rover protocols (WheelKinematics, WheelWrench, SoilSide, RoverSide)
    dem_soil, scm_soil, terrain
                    the soil sides: the DEM, the Soil Contact Model, an analytic spring-damper ground
    single_wheel, rover, controllers, fmu_controller
                    the rover sides: the single-wheel testbed, MJCF/FMU rovers, drive controllers
    coupler         Coupler (Gauss-Seidel / Jacobi macro stepping, energy bookkeeping)
    runner, records the loop (landing, drive, checkpoints, stop signals: stop_signals) and its rows
    launch          a plan to a finished run folder (folders: the folder, its lock, its JSON files)
    output, snapshots, vtkhdf
                    results.h5 (writer and readers), its snapshots, the VTKHDF/XDMF exports
    metrics         slip, sinkage, drawbar pull, steady-state windows (one definition each)
    advice          the advisor's dimensionless numbers and validity checks
    study, batch    replicas, sweeps and studies (dask or serial; batched worlds on one device)
    lab, soil_fmu   the soil lab (repose, shear, plate, calibration) and the soil as an FMU
    scm_calibration, similarity
                    SCM calibration files; the gravity twin of a scene (`cosim scale`)
    plots, view     figures and movies of a run folder
    cli             the `cosim` command
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
