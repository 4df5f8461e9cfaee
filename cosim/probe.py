"""Probing what a scene names outside itself: the machine's devices, rover models, drive controllers.

Resolving a scene (cosim.plan) needs a few facts that only opening something gives: whether the
asked-for CUDA device exists, a rover's wheel names, hub positions, mass and actuators (an MJCF is
compiled, an FMU instantiated at its start pose and closed), whether a drive's FMU opens and what it
commands, whether a Python drive's callable imports. This module does that opening, once per plan;
`cosim.plan.resolve` turns the answers into the plan and checks them against the rest of the scene.

Problems are reported as SceneError (or appended to a `problems` list) naming the scene key to change.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from soil import MeshWheel
from soil.errors import ArgumentError, RegolithError

from .scene import DriveSection, MmxSection, Scene, SceneError


def resolve_device(name: str, field: str = "scene.device") -> str:
    """A Warp device name for a scene's device ('default' -> the first GPU, else 'cpu'); SceneError naming
    `field` (where the name came from) if it is no device name or this machine has no such device."""
    import warp as wp  # Warp starts itself on the first device query

    from soil.devices import device_names

    from .scene import is_device_name

    if not is_device_name(name):
        raise SceneError(
            [f"{field}: {name!r} is no device: 'default' (a GPU when present, else the CPU), 'cpu', 'cuda' or 'cuda:N'"]
        )
    if name == "default":
        return str(wp.get_device())
    if name == "cpu":
        return "cpu"
    names = device_names()
    index = 0 if name == "cuda" else int(name[5:])
    if index >= len(names) - 1:
        have = ", ".join(names)
        raise SceneError(
            [
                f"{field}: {name!r} asked for, but this machine has no such CUDA device "
                f"(it has: {have}); use 'default' (a GPU when present, else the CPU) or 'cpu'"
            ]
        )
    return f"cuda:{index}"


def rover_wheel_names(scene: Scene) -> list[str]:
    """The wheel names the scene gives or implies; an FMU's are read from it (SceneError naming rover.file,
    rover.wheel_count or rover.wheel_prefix when they do not fit the convention)."""
    from rover_models.mjcf import MMX_WHEELS

    rover = scene.rover
    assert rover is not None
    if rover.model == "mmx":
        return list(rover.wheels or MMX_WHEELS)
    if rover.model == "mjcf":
        assert rover.wheels is not None  # the validator requires an MJCF's wheel names
        return list(rover.wheels)
    path = scene.resolve(rover.file)
    assert path is not None  # the validator requires an FMU's file
    try:
        from rover_models.fmu_rover import check_rover_fmu
    except ImportError as error:
        raise SceneError([f"rover.model: 'fmu' needs fmpy ({error}); pip install 'regolith-cosim[fmu]'"]) from None
    try:
        found = check_rover_fmu(path, rover.wheel_count, rover.wheel_prefix)
    except RegolithError as error:
        field = (
            "rover.wheel_count"
            if "the scene expects" in str(error) and rover.wheel_count is not None
            else "rover.wheel_prefix"
            if "the scene expects" in str(error)
            else "rover.file"
        )
        raise SceneError([f"{field}: {error}"]) from None
    return [f"{rover.wheel_prefix}{i}" for i in range(found["wheel_count"])]


def mmx_xml(scene: Scene, gravity) -> str:
    """The built-in rover's MJCF for a scene ([rover.mmx], the [wheel] radius and width)."""
    from rover_models.mjcf import mmx_rover_xml

    w = scene.wheel
    radius = w.radius if w.type == "grouser" else None
    assert scene.rover is not None
    params = (scene.rover.mmx or MmxSection()).model_dump()
    params["body_size"] = tuple(params["body_size"])
    if radius is None:  # a mesh wheel: its extents from the mesh
        path = scene.resolve(w.file)
        assert path is not None and w.scale is not None  # the validator requires the file, defaults the scale
        shape = MeshWheel.load(path, scale=w.scale)
        radius = shape.outer_radius
        width = float(np.ptp(shape.vertices[:, 1]))
    else:
        assert w.width is not None  # the validator fills a grouser wheel's width
        width = w.width
    g = (float(gravity[0]), float(gravity[1]), float(gravity[2]))
    return mmx_rover_xml(wheel_radius=radius, wheel_width=width, gravity=g, **params)


def import_callable(spec: str, base_dir: str | None):
    """The object named by 'module:function' (the scene file's folder searched first); SceneError
    naming rover.drive.function when it cannot be imported."""
    import importlib
    import sys

    module_name, _, name = spec.partition(":")
    added = base_dir if base_dir is not None and base_dir not in sys.path else None
    if added is not None:
        sys.path.insert(0, added)
    try:
        module = importlib.import_module(module_name)
    except Exception as error:  # noqa: BLE001 - any failure to import is the user's module's problem
        raise SceneError(
            [f"rover.drive.function: cannot import module {module_name!r}: {type(error).__name__}: {error}"]
        ) from None
    finally:
        if added is not None:
            sys.path.remove(added)
    target = getattr(module, name, None)
    if target is None or not callable(target):
        raise SceneError([f"rover.drive.function: module {module_name!r} has no callable {name!r}"])
    return target


@dataclass(frozen=True)
class RoverLayout:
    """What opening a rover model says about it at its start heading."""

    hub_offsets: np.ndarray
    """Hub positions relative to the base's frame origin at the start pose [m], shape (W, 3)."""
    axles: np.ndarray
    """Each wheel's axle (its body's local y) in the world frame at the start pose, unit [-], shape (W, 3)."""
    mass: float
    """Total mass [kg] (nan when an FMU does not say)."""
    takes_speed: bool
    """Whether the rover takes wheel speed commands."""
    takes_torque: bool
    """Whether the rover takes wheel torque commands."""
    start_parameters: bool
    """Whether the scene can place it (an MJCF always; an FMU with start.x/y/z/heading parameters)."""

    def takes(self, command: str) -> bool:
        """Whether the rover takes wheel `command`s ('speed' or 'torque')."""
        return self.takes_speed if command == "speed" else self.takes_torque


def probe_rover(scene: Scene, source: str, names: list[str], gravity, problems: list[str]) -> RoverLayout | None:
    """Open the scene's rover (`source`: an MJCF's path or text, an FMU's path) with wheels `names` under
    `gravity` [m/s^2], shape (3,), at its start heading; None (the reason appended to `problems`) when it
    cannot be opened."""
    rover = scene.rover
    assert rover is not None
    if rover.model == "fmu":
        return _inspect_fmu(scene, source, len(names), gravity, problems)
    heading = math.radians(rover.start.heading_deg)
    return _inspect_mjcf(source, names, rover.body, heading, gravity, "rover.file", problems)


def probe_drive(
    scene: Scene, section: DriveSection, key: str, wheel_count: int | None, problems: list[str]
) -> str | None:
    """Open a drive's controller as a run would (an FMU instantiated, a Python callable imported), problems
    named under the scene key `key` appended to `problems`; the wheel command kind an FMU controller gives
    ('speed' or 'torque'; None for other drives or when it cannot be opened)."""
    if section.kind == "fmu":
        file = scene.resolve(section.file)
        assert file is not None  # the validator requires an FMU drive's file
        try:
            from rover_models.fmu_session import check_binaries, check_instantiates

            from .fmu_controller import FmuController

            controller = FmuController(file, wheel_count, mode=section.mode, start_values=section.start_values)
            check_binaries(file, controller.md)  # it instantiates at its first command, after settling and landing:
            check_instantiates(file)  # what would fail then is found now
            return controller.mode
        except ImportError as error:
            problems.append(f"{key}.kind: an FMU controller needs fmpy ({error})")
        except ArgumentError as error:  # the mode asked for, or the FMU's outputs leave it open
            problems.append(f"{key}.mode: {error}")
        except RegolithError as error:
            problems.append(f"{key}.file: {error}")
        except ValueError as error:
            problems.append(f"{key}.mode: {error}")
    elif section.kind == "python":
        assert section.function is not None  # the validator requires a python drive's function
        try:
            factory = import_callable(section.function, scene.base_dir)
        except SceneError as error:
            problems += [p.replace("rover.drive.function", f"{key}.function") for p in error.problems]
        else:
            _check_factory_arguments(factory, section, key, problems)
    return None


def _check_factory_arguments(factory, section: DriveSection, key: str, problems: list[str]) -> None:
    """A python drive's factory that cannot take (wheel_count, wheel_radius, **args) named now, not when the
    run builds its controller after the bed settled; the call itself, the user's code, waits for the run."""
    import inspect

    try:
        signature = inspect.signature(factory)
    except (TypeError, ValueError):  # a callable without a signature (some builtins): its call will say
        return
    args = dict(section.args or {})
    try:
        signature.bind(wheel_count=1, wheel_radius=(1.0,), **args)
    except TypeError as error:
        problems.append(
            f"{key}.function: {section.function}(wheel_count, wheel_radius, **args) with args {args!r} "
            f"cannot be called: TypeError: {error}"
        )


def _inspect_mjcf(
    source: str, wheels: list[str], body: str | None, heading: float, gravity, field: str, problems: list[str]
) -> RoverLayout | None:
    """Compile an MJCF, find its wheels and base, and measure it at the start heading."""
    try:
        from rover_models.mujoco_rover import MujocoRover
    except ImportError as error:
        problems.append(f"rover.model: an MJCF rover needs mujoco ({error}); pip install 'regolith-cosim[mujoco]'")
        return None
    try:
        rover = MujocoRover(source, wheels, gravity=gravity)
    except KeyError as error:
        problems.append(f"rover.wheels: {error.args[0]}")
        return None
    except (ValueError, FileNotFoundError, OSError) as error:
        problems.append(f"{field}: the MJCF cannot be loaded: {error}")
        return None
    if body is not None:  # the reported body must exist
        try:
            rover.body_id(body)
        except KeyError as error:
            problems.append(f"rover.body: {error.args[0]}")
            return None
    if rover.fixed_to_world:
        problems.append(
            f"{field}: no joint lies between the world and the wheels' bodies: the rover is fixed where it stands "
            "(give its base a <freejoint/>)"
        )
        return None
    rover.move_base(np.zeros(3), heading)
    origin = rover.body_kinematics(rover.body_id()).position
    kinematics = rover.wheel_kinematics()
    hubs = np.array([k.position for k in kinematics]) - origin
    drives = rover.drives
    return RoverLayout(hubs, _axles(kinematics), rover.total_mass, bool(drives["speed"]), bool(drives["torque"]), True)


def _axles(wheels) -> np.ndarray:
    """Each wheel's axle (its body's local y, soil.geometry's wheel frame) in the world frame [-], shape (W, 3)."""
    from soil.control import quaternion_to_matrix

    return np.array([quaternion_to_matrix(k.orientation)[:, 1] for k in wheels])


def _inspect_fmu(scene: Scene, path: str, count: int, gravity, problems: list[str]) -> RoverLayout | None:
    """Open a rover FMU at its start pose (scene start values), read its wheels and body, close it."""
    from rover_models.fmu_rover import FmuRover, check_rover_fmu
    from rover_models.fmu_session import FmuError

    rover = scene.rover
    assert rover is not None
    found = check_rover_fmu(path, count, rover.wheel_prefix)
    start = rover.start
    values = dict(rover.start_values or {})
    if found["start"]:
        values.update({"start.x": 0.0, "start.y": 0.0, "start.heading": math.radians(start.heading_deg)})
    elif start.x is not None or start.y is not None or start.heading_deg != 0.0:
        problems.append(
            f"rover.start: the FMU {path} has no start.x, start.y, start.z, start.heading parameters, so "
            "the scene cannot place it; remove [rover.start] (the FMU starts where it says)"
        )
    try:
        fmu = FmuRover(path, count, gravity=gravity, start_values=values, prefix=rover.wheel_prefix)
    except FmuError as error:  # the file itself: no binary for this platform, cannot be instantiated
        problems.append(f"rover.file: {error}")
        return None
    except RegolithError as error:
        problems.append(f"rover.start_values: {error}")
        return None
    try:
        body = fmu.body_kinematics()
        wheels = fmu.wheel_kinematics()
        hubs = np.array([k.position for k in wheels]) - (body.position if found["start"] else 0.0)
        mass = fmu.total_mass
    finally:
        fmu.close()
    return RoverLayout(
        hubs,
        _axles(wheels),
        math.nan if mass is None else mass,
        bool(found["speed"]),
        bool(found["torque"]),
        bool(found["start"]),
    )
