"""SCM calibration files: the SCM soil parameters the DEM's virtual tests gave at one gravity
(written by `cosim calibrate-scm`, cosim.lab.scm; read by a scene's [terrain] calibration key).

    write_calibration("terrain.toml", calibration)
    calibration = read_calibration("terrain.toml")      # .parameters, .standard_errors, .gravity, .source

The file (TOML) records its format version, the SCM parameters and their standard errors, the
gravity, the soil (its material and grain size) and the DEM tests it came from with their settings.
"""

from __future__ import annotations

import math
import os
import re
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib

import tomli_w

from soil.errors import InputError, RegolithWarning, is_real
from soil.files import atomic_path

FORMAT_VERSION = 1
"""The calibration file's format version."""

SOIL_KEYS = ("k_c", "k_phi", "n", "cohesion", "friction_angle_deg", "janosi_k", "elastic_stiffness")
"""The SCM soil parameters a calibration gives (scene keys of [terrain] model = "scm")."""
SOIL_UNITS = {
    "k_c": "Pa m^(1-n)",
    "k_phi": "Pa m^(-n)",
    "n": "1",
    "cohesion": "Pa",
    "friction_angle_deg": "deg",
    "janosi_k": "m",
    "elastic_stiffness": "Pa/m",
}
"""The unit of each SOIL_KEYS parameter (and of its standard error): a calibration file's [units]."""

GRAVITY_TOLERANCE = 1e-3
"""Relative difference of |g| below which a calibration's gravity is the scene's [-]."""


class CalibrationGravityWarning(RegolithWarning):
    """An SCM calibration is used at a gravity other than the one its DEM tests ran at: a soil's
    pressure-sinkage and shear depend on gravity (a reduced-gravity soil is not the Earth soil)."""


class CalibrationError(InputError, ValueError):
    """A calibration file is unreadable or incomplete (the message names the file and the key): bad input."""


@dataclass
class ScmCalibration:
    """An SCM calibration: the parameters, their standard errors and where they came from."""

    parameters: dict[str, float]
    """SOIL_KEYS -> value (SI; the angle in degrees)."""
    standard_errors: dict[str, float]
    """SOIL_KEYS -> standard error of the fit (same units); nan where not estimated."""
    gravity: float
    """|g| of the DEM tests [m/s^2]."""
    source: dict[str, Any] = field(default_factory=dict)
    """The soil (material, grain size) and the DEM tests (their settings and summaries)."""


def write_calibration(path: str, calibration: ScmCalibration, replace: bool = True) -> None:
    """Write a calibration file (TOML), atomically (soil.files.atomic_path: a crash leaves the former file
    whole; its folder is made); replace False: a file that appeared at `path` while the calibration ran is
    kept, the calibration written beside it (FileExistsError naming both)."""
    data = {
        "format": FORMAT_VERSION,
        "gravity": float(calibration.gravity),
        "scm": {k: float(calibration.parameters[k]) for k in SOIL_KEYS},
        "standard_error": {k: float(calibration.standard_errors.get(k, math.nan)) for k in SOIL_KEYS},
        "units": {"gravity": "m/s^2", **SOIL_UNITS},  # [scm]'s and [standard_error]'s; [source] keys name theirs
        "source": _plain(calibration.source),
    }
    with atomic_path(path, replace=replace) as temporary, open(temporary, "wb") as f:
        tomli_w.dump(data, f)


def read_calibration(path: str) -> ScmCalibration:
    """Read a calibration file; CalibrationError names what is wrong with it."""
    if not os.path.isfile(path):  # a folder, a missing path, a FIFO or a device (read forever)
        raise CalibrationError(f"{path}: not a calibration file (no such regular file)")
    try:
        with open(path, "rb") as f:
            data = tomllib.loads(f.read().decode("utf-8-sig"))  # a byte-order mark is no TOML statement
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as error:
        raise CalibrationError(f"{path}: not a readable calibration file ({error})") from None
    if "format" not in data:  # a scene or another TOML file given where a calibration goes
        raise CalibrationError(
            f"{path}: not an SCM calibration file (no `format` key; `cosim calibrate-scm` writes one)"
        )
    if isinstance(data.get("format"), bool) or data.get("format") != FORMAT_VERSION:  # true == 1 in Python
        raise CalibrationError(f"{path}: format {data.get('format')!r}, this version reads format {FORMAT_VERSION}")
    for table in ("scm", "standard_error", "source", "units"):
        if not isinstance(data.get(table, {}), dict):
            raise CalibrationError(f"{path}: [{table}] must be a table of keys, got {data[table]!r}")
    for table in ("scm", "standard_error"):  # a misspelt key was dropped without a word
        unknown = [k for k in data.get(table, {}) if k not in SOIL_KEYS]
        if unknown:
            raise CalibrationError(
                f"{path}: [{table}] {unknown[0]}: not an SCM soil key; allowed: {', '.join(SOIL_KEYS)}"
            )
    expected_units = {"gravity": "m/s^2", **SOIL_UNITS}
    for key, unit in data.get("units", {}).items():  # the values are read in these units: another one is not converted
        if key in expected_units and unit != expected_units[key]:
            raise CalibrationError(
                f"{path}: [units] {key} = {unit!r}: this version reads {key} in {expected_units[key]!r} only "
                "(the values are not converted): write the value in that unit and the unit back"
            )
    scm = data.get("scm", {})
    missing = [k for k in SOIL_KEYS if k not in scm]
    if missing:
        raise CalibrationError(f"{path}: [scm] lacks {', '.join(missing)}")
    wrong = [k for k in SOIL_KEYS if not _finite_number(scm[k])]
    if wrong:  # a text ("0.094"), a boolean, an inf or a nan where a number stands
        raise CalibrationError(f"{path}: [scm] {wrong[0]} must be a finite number, got {scm[wrong[0]]!r}")
    gravity = data.get("gravity")
    if not _finite_number(gravity) or not gravity >= 0:
        raise CalibrationError(f"{path}: gravity must be a finite |g| >= 0 [m/s^2], got {gravity!r}")
    errors = data.get("standard_error", {})
    wrong = [
        k for k, v in errors.items() if not ((_finite_number(v) and v >= 0) or (isinstance(v, float) and math.isnan(v)))
    ]
    if wrong:
        raise CalibrationError(
            f"{path}: [standard_error] {wrong[0]} must be a number >= 0 (nan: not estimated), got {errors[wrong[0]]!r}"
        )
    return ScmCalibration(
        {k: float(scm[k]) for k in SOIL_KEYS},
        {k: float(v) for k, v in errors.items()},
        float(gravity),
        data.get("source", {}),
    )


def _finite_number(value) -> bool:
    """A TOML number (not a boolean), finite."""
    return is_real(value) and math.isfinite(value)


def tested_sinkage(calibration: ScmCalibration, path: str = "") -> float | None:
    """The deepest sinkage [m] the calibration's DEM tests reached: the plates' largest sinkage and
    the wheel runs' rim sinkages (the upper ends of their 95 % intervals); None when the file does
    not say. CalibrationError names a [source] entry that is not a number."""
    source = calibration.source
    where = f"{path}: " if path else ""
    for name in ("plate", "wheel"):
        if not isinstance(source.get(name, {}), dict):
            raise CalibrationError(f"{where}[source] {name} must be a table, got {source[name]!r:.60}")
    try:
        depths = [float(source.get("plate", {}).get("max_sinkage_m", math.nan))]
        for run in source.get("wheel", {}).get("slips", []):
            spread = float(run.get("sinkage_ci95", 0.0))
            depths.append(float(run.get("sinkage", math.nan)) + (spread if math.isfinite(spread) else 0.0))
    except (AttributeError, TypeError, ValueError) as error:
        keys = "[source.plate] max_sinkage_m or [source.wheel] slips' sinkage"
        raise CalibrationError(f"{where}{keys}: {error}") from None
    depths = [d for d in depths if math.isfinite(d) and d > 0]
    return max(depths) if depths else None


def fitted_node_spacing(calibration: ScmCalibration, path: str = "") -> float | None:
    """The node spacing [m] a wheel fit's SCM wheel ran on ([source.wheel] node_spacing_m); None when the
    file does not say (a lab calibration, a fit made before it was recorded). CalibrationError names an
    entry that is not a positive number."""
    wheel = calibration.source.get("wheel", {})
    if not isinstance(wheel, dict):
        raise CalibrationError(f"{path + ': ' if path else ''}[source] wheel must be a table, got {wheel!r:.60}")
    value = wheel.get("node_spacing_m")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        where = f"{path}: " if path else ""
        raise CalibrationError(f"{where}[source.wheel] node_spacing_m must be a node spacing > 0 [m], got {value!r}")
    return float(value)


def fitted_slips(calibration: ScmCalibration, path: str = "") -> tuple[float, float] | None:
    """The lowest and highest slip [-] of the DEM wheel runs a wheel fit was fitted on ([source.wheel] slips'
    `slip`); None when the file records none (a lab calibration). CalibrationError names an entry that is
    not a finite number."""
    wheel = calibration.source.get("wheel", {})
    where = f"{path}: " if path else ""
    if not isinstance(wheel, dict):
        raise CalibrationError(f"{where}[source] wheel must be a table, got {wheel!r:.60}")
    runs = wheel.get("slips", [])
    if not isinstance(runs, list) or not all(isinstance(run, dict) for run in runs):
        raise CalibrationError(f"{where}[source.wheel] slips must be an array of tables, got {runs!r:.60}")
    slips = [run["slip"] for run in runs if "slip" in run]  # a run that records none says nothing of the range
    if not all(_finite_number(slip) for slip in slips):
        raise CalibrationError(
            f"{where}[source.wheel] slips: each run's slip must be a finite number, got {slips!r:.80}"
        )
    return (float(min(slips)), float(max(slips))) if slips else None


WHEEL_FIT_TOLERANCE = 0.1
"""A wheel within this relative difference of a wheel fit's own in rim radius, width, grouser count and
height, and load, is taken for that wheel (`scm_calibration_wheel`) [-]: a convention, not a measured
bound; the fit's keys compensate SCM's errors for the wheel and load it was fitted on."""


@dataclass(frozen=True)
class FittedWheel:
    """The wheel a wheel fit (`calibrate-scm --from-wheel`) was fitted on, at its load ([source.wheel]
    geometry and wheel_load_n)."""

    type: str
    """'grouser' or 'mesh'."""
    rim_radius: float
    """Rim radius [m] (a mesh: its outer radius)."""
    width: float
    """Width along the axle [m]."""
    grouser_count: int
    """Grousers [-] (0: smooth, or a mesh)."""
    grouser_height: float
    """Grouser height [m] (0 without grousers)."""
    load: float
    """The wheel's load in the fitted runs [N]."""
    mesh_sha256: str = ""
    """A mesh wheel's digest of its scaled vertices and triangles (mesh_digest); '' for a grouser wheel."""


def mesh_digest(mesh) -> str:
    """SHA-256 of a mesh wheel's scaled vertices [m] and triangles, whatever the order of its vertices
    and triangles (a file saved again may list them otherwise): the vertices sorted, the triangles in
    those vertices' ranks (equal vertices share one), each turned to its least rotation (its winding
    kept), sorted. Another shape, another scale, or the same mesh in a format that rounds its numbers
    otherwise (STL holds float32) gives another digest."""
    import hashlib

    vertices = np.asarray(mesh.vertices, dtype=np.float64) + 0.0  # -0.0 and 0.0 hash alike
    _, rank = np.unique(vertices, axis=0, return_inverse=True)  # equal vertices share one rank
    triangles = rank.reshape(-1)[np.asarray(mesh.triangles, dtype=np.int64)]
    turns = np.stack([np.roll(triangles, -k, axis=1) for k in range(3)], axis=1)  # each triangle's 3 rotations
    flat = turns.reshape(-1, 3)
    order = np.empty(len(flat), dtype=np.int64)
    order[np.lexsort(flat.T[::-1])] = np.arange(len(flat))
    triangles = turns[np.arange(len(triangles)), order.reshape(-1, 3).argmin(axis=1)]  # the least rotation
    triangles = triangles[np.lexsort(triangles.T[::-1])]
    digest = hashlib.sha256(np.ascontiguousarray(vertices[np.lexsort(vertices.T[::-1])]).tobytes())
    digest.update(np.ascontiguousarray(triangles).tobytes())
    return digest.hexdigest()


def is_mesh_digest(value) -> bool:
    """Whether a record's mesh_sha256 is one mesh_digest writes: 64 lower-case hexadecimal digits."""
    return isinstance(value, str) and re.fullmatch(r"[0-9a-f]{64}", value) is not None


def wheel_record(wheel) -> dict:
    """A wheel plan's (cosim.plan.WheelPlan) shape as a wheel fit records it ([source.wheel] geometry),
    SI units in each key's suffix; a mesh wheel's with its digest (mesh_digest)."""
    shape = wheel.shape
    grousers = int(getattr(shape, "grouser_count", 0))
    mesh = not hasattr(shape, "grouser_count")
    return {
        "type": "mesh" if mesh else "grouser",
        "rim_radius_m": float(wheel.rim_radius),
        "width_m": float(wheel.width),
        "grouser_count": grousers,
        "grouser_height_m": float(getattr(shape, "grouser_height", 0.0)) if grousers else 0.0,
        **({"mesh_sha256": mesh_digest(shape)} if mesh else {}),
    }


def fitted_wheel(calibration: ScmCalibration, path: str = "") -> FittedWheel | None:
    """The wheel and load a wheel fit was fitted on ([source.wheel] geometry, wheel_load_n); None when the
    file records no geometry (a lab calibration, a fit made before it was recorded). CalibrationError names
    an entry of the wrong kind, or entries that contradict each other (grousers without a height, a mesh
    with grousers, a geometry without its load)."""
    wheel = calibration.source.get("wheel", {})
    where = f"{path}: " if path else ""
    if not isinstance(wheel, dict):
        raise CalibrationError(f"{where}[source] wheel must be a table, got {wheel!r:.60}")
    geometry, load = wheel.get("geometry"), wheel.get("wheel_load_n")
    if geometry is None:
        return None
    if not isinstance(geometry, dict):
        raise CalibrationError(f"{where}[source.wheel] geometry must be a table, got {geometry!r:.60}")
    problems = []
    kind = geometry.get("type")
    if kind not in ("grouser", "mesh"):
        problems.append(f"geometry.type must be 'grouser' or 'mesh', got {kind!r:.40}")
    numbers = {}
    for key, positive in (("rim_radius_m", True), ("width_m", True), ("grouser_height_m", False)):
        value: Any = geometry.get(key)
        numbers[key] = float(value) if _finite_number(value) else math.nan  # nan fails both comparisons
        if not (numbers[key] > 0 or (numbers[key] == 0 and not positive)):
            problems.append(
                f"geometry.{key} must be a finite number {'> 0' if positive else '>= 0'} [m], got {value!r:.40}"
            )
    count = geometry.get("grouser_count")
    if isinstance(count, bool) or not isinstance(count, int) or count < 0:
        problems.append(f"geometry.grouser_count must be a whole number >= 0, got {count!r:.40}")
        count = None  # no contradiction judged on it
    height = numbers["grouser_height_m"]
    if count is not None and math.isfinite(height) and (count > 0) != (height > 0):
        problems.append(
            f"geometry.grouser_count {count} and grouser_height_m {height!r} contradict each other: grousers have "
            "a height > 0, a smooth wheel none"
        )
    digest = geometry.get("mesh_sha256", "")
    if kind == "mesh" and (count not in (0, None) or not is_mesh_digest(digest)):
        problems.append(
            "a mesh's geometry has grouser_count 0 and its mesh_sha256 (64 lower-case hexadecimal digits), got "
            f"{count!r} and {digest!r:.70}"
        )
    if kind == "grouser" and "mesh_sha256" in geometry:
        problems.append(f"geometry.mesh_sha256 belongs to a mesh, not to a {kind} wheel")
    load_value = float(load) if isinstance(load, (int, float)) and _finite_number(load) else math.nan
    if not load_value > 0:
        problems.append(f"wheel_load_n must be a finite number > 0 [N] beside the geometry, got {load!r:.40}")
    if problems:
        raise CalibrationError(f"{where}[source.wheel] " + "; ".join(problems))
    return FittedWheel(
        str(kind),
        numbers["rim_radius_m"],
        numbers["width_m"],
        int(count or 0),
        height,
        load_value,
        str(digest),
    )


def failed_lab_checks(calibration: ScmCalibration, path: str = "") -> tuple[str, ...] | None:
    """The DEM lab tests' quasi-static numbers out of range ([source] lab_checks, written by calibrate-scm:
    each test's, name, value, limit, ok), as 'plate inertial number I = 0.0036 > 0.001'; None when the
    file does not record them (a calibration made before they were). CalibrationError names a record of
    the wrong shape."""
    checks = calibration.source.get("lab_checks")
    if checks is None:
        return None
    where = f"{path}: " if path else ""
    if not isinstance(checks, list) or not all(
        isinstance(c, dict)
        and isinstance(c.get("test"), str)
        and isinstance(c.get("name"), str)
        and isinstance(c.get("ok"), bool)
        and (_finite_number(c.get("value")) or (is_real(c.get("value")) and c.get("ok") is False))
        and _finite_number(c.get("limit"))
        for c in checks
    ):
        raise CalibrationError(
            f"{where}[source] lab_checks must be tables of test, name, value, limit (numbers) and ok, got "
            f"{checks!r:.80}"
        )
    return tuple(
        f"{c['name'] if c['name'].startswith(c['test']) else c['test'] + ' ' + c['name']} = {c['value']:.3g} > "
        f"{c['limit']:.3g}"  # "plate speed ...", not "plate plate speed ..."
        for c in checks
        if not c["ok"]
    )


def bed_soils(calibration: ScmCalibration, path: str = "") -> list[dict[str, float]]:
    """Each calibration bed's SCM soil (SOIL_KEYS -> value), in bed order: the file's [scm] with the keys
    each bed was fitted on alone ([source] replica_fits, `calibrate-scm --replicas R`) taken from that
    bed's own fit. A bed whose fit of a key failed (nan) keeps the file's value of it. The keys a wheel
    fit moved ([source.wheel] fitted) take bed k's own wheel fit ([source.wheel] replica_fits: the fit
    repeated on each bed of a slip study over beds; the wheel's beds then set the count) or, without
    it, keep the file's value. [] when the file holds no beds' own fits. The beds' fits keep what one
    soil's parameters share (k_phi and n move together between beds), which the per-key standard
    errors do not. CalibrationError names a malformed entry."""
    where = f"{path}: " if path else ""
    fits = _bed_fits(calibration.source.get("replica_fits", {}), f"{where}[source.replica_fits]")
    wheel = calibration.source.get("wheel", {})
    if not isinstance(wheel, dict):
        raise CalibrationError(f"{where}[source] wheel must be a table (the wheel fit's record), got {wheel!r:.60}")
    wheel_fits = _bed_fits(wheel.get("replica_fits", {}), f"{where}[source.wheel.replica_fits]")
    fitted = wheel.get("fitted", [])
    if not isinstance(fitted, list) or not all(isinstance(k, str) for k in fitted):
        raise CalibrationError(f"{where}[source.wheel] fitted must be a list of SCM keys, got {fitted!r:.60}")
    varied = {k: v for k, v in fits.items() if k not in set(fitted)}
    varied.update(wheel_fits)
    beds = max((len(v) for v in (wheel_fits or varied).values()), default=0)
    soils = []
    for bed in range(beds if beds >= 2 else 0):
        soil = dict(calibration.parameters)
        for key, values in varied.items():
            if bed < len(values) and math.isfinite(values[bed]):
                soil[key] = float(values[bed])
        soils.append(soil)
    return soils


def _bed_fits(fits, where: str) -> dict[str, list]:
    """A replica_fits table (SCM key -> a value per bed) checked; CalibrationError names what is wrong."""
    if not isinstance(fits, dict):
        raise CalibrationError(f"{where} must be a table of SCM keys, got {fits!r}")
    for key, values in fits.items():
        if key not in SOIL_KEYS:
            raise CalibrationError(f"{where} {key}: not an SCM key; allowed: {', '.join(SOIL_KEYS)}")
        if not isinstance(values, list) or not all(is_real(v) for v in values):  # true was read as 1.0
            raise CalibrationError(
                f"{where} {key}: must be a list of numbers (nan: a bed's failed fit), got {values!r}"
            )
        if any(math.isinf(v) for v in values):  # was taken as a failed fit, that bed silently on the pooled value
            raise CalibrationError(f"{where} {key}: an infinite value (nan marks a bed's failed fit), got {values!r}")
    counts = {key: len(values) for key, values in fits.items()}
    if len(set(counts.values())) > 1:  # a value per bed, in bed order: lists of unequal length misalign the beds
        listed = ", ".join(f"{key} {count}" for key, count in counts.items())
        raise CalibrationError(f"{where}: every key must hold one value per bed (the same count); got {listed}")
    return fits


def out_of_range(parameters: dict[str, float]) -> dict[str, str]:
    """SOIL_KEYS -> what is wrong, for the parameters outside what [terrain] model = "scm" takes
    (cosim.scene.TerrainSection's bounds, and k_c + k_phi > 0): a fit of tests too small or noisy for
    the soil can give them (a negative n or friction angle)."""
    from pydantic import ValidationError

    from .scene import TerrainSection

    given = {k: parameters[k] for k in SOIL_KEYS if k in parameters}
    problems: dict[str, str] = {}
    try:
        # a calibration named: the keys not given are not missing, only the given ones are judged
        TerrainSection.model_validate({"model": "scm", "calibration": "-", **given})
    except ValidationError as error:
        for item in error.errors():
            if item["loc"] and item["loc"][0] in given:
                key = str(item["loc"][0])
                unit = f" {SOIL_UNITS[key]}" if SOIL_UNITS[key] != "1" else ""
                problems[key] = f"{key} = {given[key]:.6g}{unit}: {item['msg'].lower()}"
    if not problems and given.get("k_c", 1.0) + given.get("k_phi", 1.0) <= 0:
        problems["k_phi"] = "k_c + k_phi = 0: the Bekker moduli carry no load"
    return problems


def same_gravity(a: float, b: float) -> bool:
    """Whether two |g| [m/s^2] are one gravity (within GRAVITY_TOLERANCE)."""
    return abs(a - b) <= GRAVITY_TOLERANCE * max(abs(a), abs(b), 1e-12)


def warn_gravity(calibrated: float, scene: float, path: str) -> None:
    """CalibrationGravityWarning when a calibration of |g| `calibrated` is used at |g| `scene` [m/s^2]."""
    if not same_gravity(calibrated, scene):
        warnings.warn(
            f"{path}: the SCM calibration ran its DEM tests at |g| = {calibrated:.4g} m/s^2, the scene's gravity is "
            f"{scene:.4g} m/s^2; calibrate at the scene's gravity (cosim calibrate-scm SCENE)",
            CalibrationGravityWarning,
            stacklevel=3,
        )


def _plain(value):
    """A TOML-writable copy (no None, numpy scalars as Python numbers)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items() if v is not None}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value if v is not None]
    if isinstance(value, np.ndarray):
        return [_plain(v) for v in value.tolist()]
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    return value
