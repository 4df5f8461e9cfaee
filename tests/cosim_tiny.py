"""A tiny single-wheel scene (~200 grains, a fraction of a second) shared by the tool tests."""

TINY_SCENE = """
[scene]
name = "tiny"
gravity = "moon"
precision = "mixed"

[bed]
length = 0.12
width = 0.06
depth = 0.026
radius_mean = 0.0035
settle_max_time = 0.6
settle_ke_ratio = 0.05

[wheel]
radius = 0.025
width = 0.02
grouser_count = 8
grouser_height = 0.003
grouser_thickness = 0.002

[testbed]
mass = 2.0
omega = 1.0

[run]
duration = 0.12
macro_step = 0.0017

[output]
snapshot_interval = 0.03
checkpoint_interval = 0.03
flush_every = 7
"""


def write_tiny(folder, extra: str = "", name: str = "tiny.toml") -> str:
    path = folder / name
    path.write_text(TINY_SCENE + extra)
    return str(path)
