"""Rover-side adapters and assets.

Nothing heavy is imported here: `rover_models.mujoco_rover` needs mujoco,
`rover_models.fmu_rover` needs fmpy. `rover_models.mjcf` builds the MJCF strings of the
bundled models from parameters; `asset_path(name)` gives the default MJCF files.
"""

from pathlib import Path

ASSETS = Path(__file__).resolve().parent / "assets"
"""Folder of the bundled MJCF files."""


def asset_path(name: str) -> Path:
    """Path of a bundled asset, e.g. asset_path('mmx_rover.xml')."""
    path = ASSETS / name
    if not path.exists():
        raise FileNotFoundError(f"no asset {name!r}; available: {sorted(p.name for p in ASSETS.iterdir())}")
    return path
