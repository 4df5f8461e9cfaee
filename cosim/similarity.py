"""The gravity twin: the DEM-similar scene at another gravity (`cosim scale`).

For Hertz contacts (with Lehr damping, a Mindlin-Kelvin tangential element, Coulomb
friction angles and a rolling coefficient), scaling gravity by s and every stiffness by
s leaves the overlaps of a grain under its neighbours' weight unchanged; times then scale
by 1 / sqrt(s) and speeds by sqrt(s). Every term of the contact law follows: the Lehr
force c v with c = 2 D sqrt(m k) scales as sqrt(s) sqrt(s) = s like the weight, and so do
the tangential spring and the cohesion (a pressure). So

    |g| x s, E x s (grains and wheel), cohesion x s, forces x s (drawbar load),
    speeds x sqrt(s) (omega, stick speed), times / sqrt(s) (duration, dt, macro step,
    the PID's dt_min and dt_max, landing, settling, output intervals), force rates x s^1.5
    (drawbar ramp), lengths, masses, densities, angles, restitution, Poisson's ratio, D unchanged,

is an exact similarity of the DEM: the twin's trajectories are the original's, played at
another speed, and travel / r, slip and sinkage / r are the same (within the summation-
order scatter, since rounding differs). A Phobos wheel test can so be reproduced at
Earth gravity with a 1720 x stiffer soil, and back.

This is not the granular scaling law of Slonaker et al. (Phys. Rev. E 95, 052901, 2017),
[P / (M g sqrt(g L)), V / sqrt(g L)] = f(M / (rho L^3), omega sqrt(L / g)), which holds for
a stiff medium at a FIXED grain stiffness (real sand): it predicts how a wheel's power and
speed change with gravity when the soil does not change. The twin changes the soil's
stiffness with gravity, so it makes no claim about real sand at another gravity; it says
that a simulation at one gravity stands for the whole family, and it checks a code's
milli-g numerics against an Earth-g run.

The other terrains follow the same rule, pressures and forces x s at the same lengths: SCM's
Bekker moduli k_c and k_phi, its cohesion and its unloading stiffness x s, its pressure damping
[Pa s/m] x sqrt(s), its step / sqrt(s) (n, K, the angles and the grid unchanged: the Bekker
sinkage is the same); the analytic ground's stiffness x s, damping x sqrt(s) and slip velocity
x sqrt(s), its defaults made explicit first. A calibration file holds the soil at the gravity it
was measured at: the twin keeps one calibrated at the twin's gravity and refuses any other
(`cosim calibrate-scm` of the DEM scene's twin makes one). The twin is named after its file
unless --set scene.name names it (a run of it without --out goes to runs/TWIN-STEM, not into the
original's folder).
"""

from __future__ import annotations

import math
import os

import numpy as np

from soil import gravity_vector

from .scene import SCENE_NUMBER_RANGE, Scene, SceneError, load_scene

TIME_KEYS = [
    ("run", "duration"),
    ("run", "dt"),
    ("run", "macro_step"),
    ("landing", "max_time"),
    ("landing", "hold_time"),
    ("bed", "settle_max_time"),
    ("output", "snapshot_interval"),
    ("output", "checkpoint_interval"),
    ("run", "dt_min"),
    ("run", "dt_max"),
    ("terrain", "time_step"),
]
"""Scene keys that are times [s]: / sqrt(s)."""
STIFFNESS_KEYS = [
    ("soil", "youngs_modulus"),
    ("soil", "cohesion"),
    ("wheel.material", "youngs_modulus"),
    ("wheel.material", "cohesion"),
    ("testbed", "drawbar_load"),
    ("terrain", "k_c"),
    ("terrain", "k_phi"),
    ("terrain", "cohesion"),
    ("terrain", "elastic_stiffness"),
    ("terrain", "stiffness"),
]
"""Scene keys that scale like a force or a pressure, at the same lengths: x s (Pa, N, Pa m^(1-n), Pa m^-n,
Pa/m, N/m)."""
SPEED_KEYS = [
    ("testbed", "omega"),
    ("soil", "stick_speed"),
    ("wheel.material", "stick_speed"),
    ("terrain", "slip_velocity"),
    ("terrain", "damping"),
    ("terrain", "pressure_damping"),
]
"""Scene keys that are speeds or rates [m/s, rad/s], or a force or pressure per speed [N s/m, Pa s/m]
(s / sqrt(s)): x sqrt(s)."""
RATE_KEYS = [("testbed", "drawbar_ramp")]
"""Force rates [N/s]: x s^1.5."""


def _section(data: dict, dotted: str) -> dict:
    node = data
    for part in dotted.split("."):
        node = node.setdefault(part, {})
    return node


MAX_GRAVITY_RATIO = 1e8
"""The largest ratio of a twin's gravity to its scene's, either way [-]: a micro-g asteroid's to the
Earth's is 1e6; far beyond, the twin's scaled keys leave what a scene takes."""


def gravity_twin(scene: Scene, gravity) -> tuple[dict, float]:
    """(the twin scene as a dictionary, the factor s = |g_new| / |g_old|)."""
    if scene.rover is not None:
        raise SceneError(
            [
                "rover: the gravity twin scales the single-wheel [testbed]'s keys; a rover scene's drives, "
                "masses and model are not scaled here"
            ]
        )
    old = gravity_vector(scene.scene.gravity)
    if isinstance(gravity, bool):  # read as 1 m/s^2 otherwise
        raise SceneError([f"--gravity: a preset name or a magnitude [m/s^2], not {str(gravity).lower()}"])
    if not isinstance(gravity, str) and np.ndim(gravity) != 0:  # its direction would be dropped silently
        raise SceneError(
            [f"--gravity: a preset name or a magnitude [m/s^2], not {gravity!r}: the twin keeps the scene's direction"]
        )
    try:
        target = gravity_vector(gravity)
    except ValueError as error:
        raise SceneError([f"--gravity: {error}"]) from None
    if np.max(np.abs(target)) > SCENE_NUMBER_RANGE[1]:  # its norm would overflow
        raise SceneError([f"--gravity: {gravity} m/s^2: a scene number is of magnitude <= {SCENE_NUMBER_RANGE[1]:g}"])
    g_old, g_new = float(np.linalg.norm(old)), float(np.linalg.norm(target))
    if g_old <= 0 or g_new <= 0:
        raise SceneError([f"--gravity: both gravities must be > 0 (scene {g_old:g}, target {g_new:g} m/s^2)"])
    if not 1 / MAX_GRAVITY_RATIO <= g_new / g_old <= MAX_GRAVITY_RATIO:
        raise SceneError(
            [
                f"--gravity: {g_new:g} m/s^2 is {g_new / g_old:.3g} x the scene's {g_old:g} m/s^2; allowed: "
                f"{1 / MAX_GRAVITY_RATIO:g} .. {MAX_GRAVITY_RATIO:g} x (the twin's stiffnesses scale by that "
                "ratio, its times by one over its root)"
            ]
        )
    s = g_new / g_old
    data = scene.to_dict()
    data.setdefault("scene", {})["gravity"] = [float(v) for v in old * s]
    # the wheel's modulus defaults to the soil's: make it explicit before scaling both
    wheel_material = _section(data, "wheel.material")
    wheel_material.setdefault("youngs_modulus", _section(data, "soil").get("youngs_modulus", 2.0e5))
    soil = _section(data, "soil")
    soil.setdefault("youngs_modulus", 2.0e5)
    if scene.terrain is not None and scene.terrain.model == "analytic":  # its defaults made explicit, then scaled
        import inspect

        from .terrain import SpringDamperTerrain

        defaults = inspect.signature(SpringDamperTerrain.__init__).parameters
        terrain = _section(data, "terrain")
        for key in ("stiffness", "damping", "slip_velocity"):
            terrain.setdefault(key, defaults[key].default)
    for keys, factor in (
        (TIME_KEYS, 1 / math.sqrt(s)),
        (STIFFNESS_KEYS, s),
        (SPEED_KEYS, math.sqrt(s)),
        (RATE_KEYS, s**1.5),
    ):
        for section, key in keys:
            node = _section(data, section)
            if key in node and node[key] is not None:
                node[key] = float(node[key]) * factor
    for section, key, default in (
        ("testbed", "omega", 0.25),
        ("run", "duration", 3.0),
        ("landing", "max_time", 30.0),
        ("bed", "settle_max_time", 10.0),
        ("output", "snapshot_interval", 0.25),
        ("output", "checkpoint_interval", 0.5),
    ):
        node = _section(data, section)
        if key not in node:  # a default of the schema: scale it explicitly
            node[key] = default * (math.sqrt(s) if key == "omega" else 1 / math.sqrt(s))
    data["bed"].pop("bed_file", None)  # a bed settled at the old gravity cannot serve the twin
    _check_calibration(scene, g_new)
    return data, s


def _check_calibration(scene: Scene, g_new: float) -> None:
    """Refuse a terrain.calibration not calibrated at the twin's gravity `g_new` [m/s^2] (SceneError naming
    the key, the file and both gravities): a soil's calibration holds at the gravity it was measured at."""
    from .scm_calibration import read_calibration, same_gravity

    name = scene.terrain.calibration if scene.terrain is not None else None
    if name is None:
        return
    path = scene.resolve(name)
    assert path is not None
    gravity = read_calibration(path).gravity
    if not same_gravity(gravity, g_new):
        shipped = "none is shipped at this gravity: examples/terrain holds the main job's soil at Phobos' and Earth's"
        for place, file in (
            ("Earth", "earth_twin_regolith_scm_beds.toml"),
            ("Phobos", "phobos_regolith_scm_beds.toml"),
        ):
            if same_gravity(g_new, float(np.linalg.norm(gravity_vector(place.lower())))):
                shipped = (
                    f"the shipped example: terrain/{file}, the main job's soil at {place}, beside "
                    "examples/phobos_single_wheel_scm.toml"
                )
        raise SceneError(
            [
                f"terrain.calibration: {path} is calibrated at |g| = {gravity:.4g} m/s^2, the twin's is "
                f"{g_new:.4g} m/s^2: a soil's calibration holds at its gravity; name one calibrated at the twin's "
                "(--set terrain.calibration='\"FILE\"', relative to the scene's folder), made by `cosim "
                f"calibrate-scm` of the twin of the DEM scene it was calibrated on ({shipped})"
            ]
        )


def _plain_name(name: str) -> bool:
    """Whether `name` passes scene.name's own check (a plain folder name under runs/)."""
    from pydantic import ValidationError

    from .scene import SceneSection

    try:
        SceneSection(name=name)
    except ValidationError:
        return False
    return True


def write_gravity_twin(path: str, gravity, out: str, overwrite: bool = False, overrides=None) -> tuple[str, float]:
    """Write the twin of the scene file `path` at `gravity` (preset or magnitude) to `out`: without
    `overwrite`, an `out` that exists is refused (OutputExistsError) and one that appears while the twin is
    made is kept, the twin written beside it (FileExistsError naming both: soil.files.place_new)."""
    import tomli_w

    from soil.files import atomic_path

    from .plan import resolve
    from .scene import parse_value, validate_scene

    scene = load_scene(path, overrides)
    data, s = gravity_twin(scene, parse_value(str(gravity)))
    if not any(o.split("=", 1)[0].strip() == "scene.name" for o in overrides or []):  # a name given is kept
        stem = os.path.splitext(os.path.basename(out))[0]
        data["scene"]["name"] = stem if _plain_name(stem) else f"{scene.scene.name}_twin"
    try:  # the twin must be a valid scene too: what it refuses is named as the twin's (a scaled key's value)
        twin = validate_scene(data, base_dir=scene.base_dir)
        resolve(twin)
    except SceneError as error:
        raise SceneError(error.problems, source=f"the twin of {path} at |g| x {s:.6g}") from None
    if os.path.exists(out) and not overwrite:
        from .folders import OutputExistsError

        raise OutputExistsError(f"{out!r} exists; pass --overwrite to replace it")
    header = (
        f"# The DEM-similar twin of {os.path.basename(path)} at |g| x {s:.9g} (cosim scale; "
        "cosim/similarity.py): stiffnesses and forces x s, speeds x sqrt(s), times / sqrt(s).\n"
    )
    # a crash leaves the former file whole; without overwrite, a file that appeared meanwhile is kept
    with atomic_path(out, replace=overwrite) as temporary, open(temporary, "w") as f:
        f.write(header + tomli_w.dumps(twin.to_dict()))
    return out, s
