"""The virtual soil lab: bulk properties of a simulated soil, measured as in a laboratory.

    cosim lab repose SCENE      angle of repose of a heap (cosim.lab.repose)
    cosim lab shear SCENE       direct shear: peak and residual friction angle and cohesion (cosim.lab.shear)
    cosim lab plate SCENE       pressure-sinkage of plates and its Bekker fit (cosim.lab.plate)
    cosim calibrate SCENE ...   contact parameters tuned to target bulk values (cosim.lab.calibrate)

A lab scene is a scene file (cosim.scene) with optional [lab], [repose], [shear] and
[plate] sections (cosim.lab.scene). Each test writes a folder: scene.toml, a CSV with the
unit of every column in its header, summary.json (the measured values, their replica
statistics and the dimensionless numbers that keep the test quasi-static) and a figure.
docs/lab.md describes the tests, the definitions, the fits and the calibration loop.
"""

from .calibrate import calibrate
from .plate import bekker_fit, plate_test
from .repose import measure_heap, repose_test
from .scene import LabPlan, LabScene, load_lab_plan, resolve_lab
from .shear import mohr_coulomb, shear_test

__all__ = [
    "LabPlan",
    "LabScene",
    "bekker_fit",
    "calibrate",
    "load_lab_plan",
    "measure_heap",
    "mohr_coulomb",
    "plate_test",
    "repose_test",
    "resolve_lab",
    "shear_test",
]
