"""The DEM soil as an FMI 2.0 / 3.0 co-simulation FMU that any FMI tool can load.

The FMU is a small compiled front end (soil_fmu.c with fmi2.c or fmi3.c, built with the
local C compiler; it links no Python) plus resources: the settled bed and the soil
configuration. When initialization ends, the front end starts the soil server
(the module cosim.soil_fmu.server), which runs the DEM in its own process on its own
device, and forwards each doStep's wheel kinematics to it over a socket pair; the server
answers with the wheel wrenches. docs/fmu.md documents the variables, the protocol and
what the FMU needs at run time.

    from cosim.soil_fmu import export_soil_fmu, soil_config_from
    config = soil_config_from("runs/phobos")          # a run folder or a scene file
    export_soil_fmu(config, "soil.fmu", fmi_version=3, wheel_count=4)

Modules: config (SoilFmuConfig, soil_config_from), build (front end, modelDescription,
export_soil_fmu), server (the soil server).
"""

from .build import build_frontend, export_soil_fmu
from .config import SoilFmuConfig, soil_config_from

__all__ = ["SoilFmuConfig", "build_frontend", "export_soil_fmu", "soil_config_from"]
