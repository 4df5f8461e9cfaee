"""Small rover scenes for the rover tests: a one-wheel rig (the MJCF of rover_models.mjcf.single_wheel_rig_xml
used as a rover) and a small MMX-like rover, on beds of a few hundred coarse grains at lunar gravity.

They are deliberately coarse (2-3 grain diameters across a wheel: `cosim advise` says so): the tests
check mechanics (force balance, books, bitwise continuation) and compare configurations with each
other on the same grains, not traction numbers.
"""

import math

from rover_models.mjcf import single_wheel_rig_xml

MOON = 1.625
"""|g| of the tests [m/s^2]."""

RIG_BALLAST, RIG_WHEEL, RIG_CARRIAGE = 0.08, 0.02, 0.002
"""The rig's masses [kg]: the soil carries ballast + wheel; the slope pulls on all three."""

SOIL = """
[soil]
youngs_modulus = 3.0e5

[bed]
length = {length}
width = {width}
depth = 0.03
radius_mean = {radius}
radius_spread = 0.15
settle_max_time = 2.0
settle_ke_ratio = 0.005
"""

RIG = """
[scene]
name = "{name}"
gravity = {gravity}
precision = "mixed"
device = "cpu"
{soil}
[wheel]
radius = 0.02
width = 0.02
grouser_count = {grousers}
grouser_height = {grouser_height}
grouser_thickness = 0.002

[rover]
model = "mjcf"
file = "rig.xml"
wheels = ["wheel"]

[rover.start]
heading_deg = {heading}

[rover.drive]
kind = "speed"
speed = {speed}

[landing]
max_time = 1.5

[run]
duration = {duration}
macro_step = 0.003
dt_factor = 0.25

[output]
snapshot_interval = {snapshots}
checkpoint_interval = {checkpoints}
flush_every = 25
"""


def gravity(slope_deg: float = 0.0) -> str:
    """The tests' gravity tilted by `slope_deg` about y (uphill towards +x), as TOML."""
    a = math.radians(slope_deg)
    return f"[{-MOON * math.sin(a)!r}, 0.0, {-MOON * math.cos(a)!r}]"


def write_rig(
    folder,
    name="rig",
    slope_deg=0.0,
    heading=0.0,
    speed=2.0,
    duration=1.5,
    length=0.2,
    width=0.05,
    grousers=8,
    grouser_height=0.003,
    snapshots=0.0,
    checkpoints=1.0,
    radius=0.0035,
    extra="",
) -> str:
    """A rig scene (and its rig.xml) in `folder`; returns the scene's path."""
    (folder / "rig.xml").write_text(
        single_wheel_rig_xml(
            wheel_radius=0.02,
            wheel_width=0.02,
            wheel_mass=RIG_WHEEL,
            carriage_mass=RIG_CARRIAGE,
            ballast_mass=RIG_BALLAST,
            motor_kv=0.5,
            gravity=(0.0, 0.0, -MOON),
        )
    )
    soil = SOIL.format(length=length, width=width, radius=radius)
    text = RIG.format(
        name=name,
        gravity=gravity(slope_deg),
        soil=soil,
        grousers=grousers,
        grouser_height=grouser_height,
        heading=heading,
        speed=speed,
        duration=duration,
        snapshots=snapshots,
        checkpoints=checkpoints,
    )
    path = folder / f"{name}.toml"
    path.write_text(text + extra)
    return str(path)


SMALL_ROVER = """
[scene]
name = "{name}"
gravity = "moon"
precision = "mixed"
device = "cpu"
{soil}
[wheel]
radius = 0.025
width = 0.02
grouser_count = 8
grouser_height = 0.003
grouser_thickness = 0.002

[rover]
drive = "{drive}"
{model}
[rover.controllers.cruise]
kind = "speed"
speed = 1.5

[rover.controllers.slip]
kind = "slip"
target_slip = 0.3
omega_max = 3.0
omega_min = 0.3

[landing]
max_time = 1.5

[run]
duration = {duration}
macro_step = 0.003
dt_factor = 0.25

[output]
snapshot_interval = {snapshots}
checkpoint_interval = {checkpoints}
flush_every = 25
{extra}"""

SMALL_MMX = {
    "body_mass": 0.4,
    "leg_mass": 0.02,
    "wheel_mass": 0.05,
    "body_size": [0.1, 0.08, 0.04],
    "wheelbase": 0.1,
    "track": 0.1,
    "leg_drop": 0.02,
    "motor_kv": 2.0,
}
"""The small MMX-like rover ([rover.mmx]); the FMU takes the same as start values."""


def small_rover_model(kind: str, fmu: str | None = None) -> str:
    """The [rover] model lines: the built-in MJCF ('mmx') or the project's rover FMU ('fmu') with the same
    parameters."""
    if kind == "mmx":
        rows = "\n".join(f"{k} = {v}" for k, v in SMALL_MMX.items())
        return f'model = "mmx"\n[rover.mmx]\n{rows}\n'
    values = {
        **{k: v for k, v in SMALL_MMX.items() if k != "body_size"},
        "wheel_radius": 0.025,
        "wheel_width": 0.02,
        **{f'"body_size.{a}"': v for a, v in zip("xyz", SMALL_MMX["body_size"])},
    }
    inline = ", ".join(f"{k} = {v}" for k, v in values.items())
    return f'model = "fmu"\nfile = "{fmu}"\nstart_values = {{{inline}}}\n'


def write_small_rover(
    folder,
    kind="mmx",
    fmu=None,
    name="small",
    drive="cruise",
    duration=0.5,
    length=0.25,
    width=0.15,
    radius=0.005,
    snapshots=0.0,
    checkpoints=1.0,
    extra="",
) -> str:
    """The small four-wheeled rover scene in `folder` (MJCF or FMU); returns its path."""
    model = small_rover_model(kind, fmu)
    text = SMALL_ROVER.format(
        name=name,
        soil=SOIL.format(length=length, width=width, radius=radius),
        model=model,
        drive=drive,
        duration=duration,
        snapshots=snapshots,
        checkpoints=checkpoints,
        extra=extra,
    )
    path = folder / f"{name}.toml"
    path.write_text(text)
    return str(path)
