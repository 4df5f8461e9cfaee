"""soil: the DEM regolith model in NVIDIA Warp kernels (CPU or CUDA).

from soil import SoilBuilder, Material, Simulation
builder = SoilBuilder(gravity="phobos")
builder.add_material(Material(youngs_modulus=1e7))
builder.add_container((0, 0, 0), (0.1, 0.1, 0.1))
builder.add_particles(positions, radii)
model, state, control = builder.finalize(device="cpu", precision="mixed")
sim = Simulation(model, state, control)
sim.run(duration=1.0, dt=1e-4)
force, torque, contacts = sim.boundary_wrenches()   # the grains' push on each wall
"""

import threading

import warp as _wp

from . import advisor
from .advisor import largest_stable_step, macroscopic_stiffness, rayleigh_time_step, recommended_time_step
from .builder import SoilBuilder
from .contact import ContactLaw
from .control import SoilControl
from .errors import OverlapWarning, SoilInputError
from .geometry import GrouserWheel, MeshWheel
from .gravity import GRAVITY_PRESETS, gravity_vector
from .integrator import JoltBeeman, StepController, VelocityVerlet, make_integrator
from .materials import Material, damping_ratio_for_restitution, restitution_of_damping_ratio
from .model import SoilModel
from .neighbours import NeighbourSettings
from .precision import PRECISIONS, get_precision
from .scm import ScmParameters, ScmTerrain
from .simulation import MacroStepReport, Simulation, SimulationDiverged
from .snapshot import SimulationSnapshot
from .stability import DivergenceMonitor
from .state import SoilState

__all__ = [
    "DivergenceMonitor",
    "JoltBeeman",
    "StepController",
    "advisor",
    "largest_stable_step",
    "macroscopic_stiffness",
    "rayleigh_time_step",
    "recommended_time_step",
    "ContactLaw",
    "GRAVITY_PRESETS",
    "GrouserWheel",
    "MacroStepReport",
    "MeshWheel",
    "Material",
    "NeighbourSettings",
    "OverlapWarning",
    "PRECISIONS",
    "Simulation",
    "SimulationDiverged",
    "SimulationSnapshot",
    "SoilBuilder",
    "SoilControl",
    "SoilInputError",
    "SoilModel",
    "ScmParameters",
    "ScmTerrain",
    "SoilState",
    "VelocityVerlet",
    "damping_ratio_for_restitution",
    "get_precision",
    "gravity_vector",
    "make_integrator",
    "quiet_warp",
    "restitution_of_damping_ratio",
]


def quiet_warp() -> None:
    """Silence Warp's banner and per-module load messages (warnings and errors still show), and start
    Warp with the C stderr held back: its native library prints a CUDA-driver warning on every process
    of a machine without a GPU (each dask worker's too), whatever the log level. What Warp printed is
    shown after all if it fails to start. A scene that asks for a GPU there is refused by name when it
    is planned. Safe from several threads (a dask worker's): one starts Warp, the others wait."""
    global _warp_started
    _wp.config.log_level = max(_wp.config.log_level, _wp.LOG_WARNING)
    with _warp_start_lock:
        if _warp_started:
            return
        import os
        import sys
        import tempfile

        sys.stderr.flush()
        saved = os.dup(2)
        with tempfile.TemporaryFile() as held:
            try:
                os.dup2(held.fileno(), 2)
                _wp.init()
            except BaseException:
                os.dup2(saved, 2)
                held.seek(0)
                sys.stderr.write(held.read().decode(errors="replace"))
                raise
            finally:
                os.dup2(saved, 2)
                os.close(saved)
        _warp_started = True


_warp_started = False
_warp_start_lock = threading.Lock()
