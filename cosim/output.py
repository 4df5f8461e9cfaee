"""Run output: results.h5 (HDF5, written as the run goes) and results.xdmf (ParaView, VTK, meshio).

HDF5 layout of ``results.h5`` (S = macro steps recorded, W = wheels, T = particle
snapshots, N = particles, V = wheel-mesh vertices, F = wheel-mesh triangles, K = rover
state columns). Every dataset carries a `units` attribute ("1": dimensionless, "count")
and a `description`; every time series grows along its first axis. Every dataset but a scalar is
chunked with HDF5's Fletcher-32 checksum on each chunk (CHECKSUMMED), so that bytes changed on disk
fail the read (cosim.snapshots.read_results_data names the file and the dataset; a file still being
written is read again first, as its writer rewrites a chunk in place) instead of being read as
numbers; a file written before 2026-12-07 has none and is read as it is.

    /                               attributes:
        format          "regolith-cosim results 2"
        status          "running" | "complete" | "unsteady" | "interrupted" | "diverged" | "failed"
                        (unsteady: finished, without a steady-state result)
        message         why the run stopped ("" when complete)
        summary         JSON: the run's summary (cosim.metrics.summarize), written at the end; its
                        `units` the unit of each number in it (cosim.metrics.SUMMARY_UNITS)
        units           JSON: the unit of each numeric attribute below (cosim.records.ATTRIBUTE_UNITS)
        name, scene_toml (the scene as run), scene_source (the scene file's text), versions (JSON),
        created, precision, device, scheme, integrator, order_seed (-1: none), dt [s] and substeps (the soil's
        step and steps per macro step: the DEM's, SCM's on SCM alone: cosim.records.soil_step), macro_step [s],
        duration [s], gravity [m/s^2] (3,), surface_height [m], start_position [m] (3,), omega [rad/s],
        rim_radius [m], outer_radius [m], wheel_load [N], mode, particle_count, wheel_names (JSON),
        bed (JSON: source, settle report, metrics), findings (JSON: the validity checks at the start)
    /wheels/                        one row per macro step, wheel quantities at its end
        time              (S,)       [s]
        phase             (S,)       0 landing, 1 driving (cosim.single_wheel.PHASE_LANDING, PHASE_DRIVING)
        position          (S, W, 3)  hub position [m]
        orientation       (S, W, 4)  quaternion (w, x, y, z) body -> world [1]
        linear_velocity   (S, W, 3)  [m/s]
        angular_velocity  (S, W, 3)  [rad/s]
        force             (S, W, 3)  soil force on the wheel held over the step [N]
        torque            (S, W, 3)  soil torque about the hub held over the step [N m]
        force_end         (S, W, 3)  soil force at the end of the step [N]
        torque_end        (S, W, 3)  soil torque about the hub at the end of the step [N m]
        contact_count     (S, W)     grains touching the wheel (SCM: grid nodes in contact; analytic: 1 or 0) [count]
        work_on_rover     (S, W)     [J]
        work_on_soil      (S, W)     [J]
        travel, slip, sinkage, sinkage_tips, drawbar_pull, driving_torque, normal_force, power
                          (S, W)     cosim.metrics definitions [m, 1, m, m, N, N m, N, W]
        speed_command     (S, W)     wheel speed commanded over the step [rad/s] (nan: a torque was)
        torque_command    (S, W)     wheel torque commanded over the step [N m] (nan: a speed was)
        mesh/vertices     (V, 3)     all wheel meshes in their wheel frames [m] (for display)
        mesh/triangles    (F, 3)     indices into vertices
        mesh/wheel        (V,)       wheel index of each vertex
    /boundaries/                    the container walls (B = boundaries), one row per macro step
        force             (S, B, 3)  force of the grains on each wall at the end of the step [N]
        torque            (S, B, 3)  torque about the wall's reference point (a plane's point, a box's
                                     centre, moved with the wall) [N m]
        contact_count     (S, B)     grains touching each wall [count]
        displacement      (S, B, 3)  how far each wall moved from its place at the start [m]
        kind              (B,)       0 plane, 1 box;  geometry (B, 6) [m] as built;  report (B,) 1 when summed
    /rover/
        time              (S,)       [s]
        state             (S, K)     attributes `columns` and `units` (JSON lists) name them
        position          (S, 3)     the rover body's frame origin (testbed: the hub) [m]
        orientation       (S, 4)     its quaternion (w, x, y, z), body -> world [1]
        linear_velocity   (S, 3)     [m/s]
        angular_velocity  (S, 3)     [rad/s]
        forward_speed, slip, net_traction, power, travel
                          (S,)       cosim.metrics rover definitions [m/s, 1, N, W, m]
    /soil/
        particle_count    (S,)       grains simulated [count]
        mass              (S,)       their mass [kg]
        mass_added        (S,)       soil placed ahead by a moving patch so far [kg]
        mass_removed      (S,)       soil removed behind it so far [kg]
        moves             (S,)       how often the patch moved so far [count]
        dem_steps         (S,)       DEM steps of the macro step (PID: accepted substeps) [count]
        dem_steps_rejected (S,)      PID substeps thrown away in the macro step [count]
        dt_min, dt_mean, dt_max (S,) shortest, mean, longest DEM step of the macro step [s]
        force_evaluations (S,)       force evaluations of the macro step, rejected included [count]
    /particles/                      (attribute `layout`: "fixed" or "ragged")
        time              (T,)       [s]
        wheel_vertices    (T, V, 3)  float32 [m], the wheel meshes posed at each snapshot
        rover_position    (T, 3)     the rover body at each snapshot [m]
        rover_forward     (T, 3)     its x axis, world [1]
        rover_up          (T, 3)     its z axis, world [1]
      fixed (the grains stay the same):
        radius            (N,)       [m]  (model order: fixed for the run)
        position          (T, N, 3)  float64 [m]
        velocity          (T, N, 3)  float32 [m/s]
      ragged (a moving patch: grains come and go; snapshot k is rows first[k] .. first[k] + count[k]):
        first, count      (T,)       [count]
        id                (R,)       grain id, unique over the run [1]
        radius            (R,)       [m]
        position          (R, 3)     float64 [m]
        velocity          (R, 3)     float32 [m/s]

The file is written in SWMR mode (libver 'latest'): records are buffered and flushed
every `flush_every` macro steps, so a killed run leaves a readable file with everything
up to the last flush; `open_results` reads it (also while a run is still writing). A
resume (`ResultsWriter.resume`) copies what the checkpoint covers into a fresh file and
replaces the old one atomically, so a file left flagged by a killed writer needs no tool.
``results.xdmf`` beside it shows the snapshots as temporal collections: the wheel meshes
(Triangle), the rover body (a point with its forward and up axes) and the grains (Polyvertex);
its data file ``results.xdmf.h5`` holds each snapshot as plain datasets (`sync_xdmf_data`), so
that ParaView, VTK's XDMF reader and meshio's `TimeSeriesReader` read it, also while the run
writes results.h5. At the end of a run ``results.vtkhdf`` (cosim.vtkhdf) follows.
"""

from __future__ import annotations

import json
import os
import xml.etree.ElementTree as ET
from datetime import datetime, timezone
from functools import partial
from typing import Any

import numpy as np

from soil.errors import DamagedFileError
from soil.files import atomic_path, atomic_write_text, with_path

from .folders import XDMF_DATA_FILE, XDMF_FILE, finite_or_null, null_as_nan
from .snapshots import ARRAY_NAMES, read_results_data, read_snapshot, read_whole, snapshot_datasets

RESULTS_FORMAT = "regolith-cosim results 2"

WHEEL_SERIES = {
    # name: (trailing shape (None: per wheel scalar), dtype, units, description)
    "position": (3, np.float64, "m", "hub position, world frame"),
    "orientation": (4, np.float64, "1", "quaternion (w, x, y, z), wheel body -> world"),
    "linear_velocity": (3, np.float64, "m/s", "hub velocity, world frame"),
    "angular_velocity": (3, np.float64, "rad/s", "wheel angular velocity, world frame"),
    "force": (3, np.float64, "N", "soil force on the wheel held over the macro step, world frame"),
    "torque": (3, np.float64, "N m", "soil torque about the hub held over the macro step, world frame"),
    "force_end": (3, np.float64, "N", "soil force on the wheel at the end of the macro step"),
    "torque_end": (3, np.float64, "N m", "soil torque about the hub at the end of the macro step"),
    "contact_count": (
        None,
        np.int64,
        "count",
        "grains touching the wheel at the end of the step (SCM: grid nodes in contact; analytic terrain: 1 in contact)",
    ),
    "work_on_rover": (None, np.float64, "J", "work of the held wrench on the rover over this macro step"),
    "work_on_soil": (None, np.float64, "J", "work done on the soil over this macro step"),
    "travel": (None, np.float64, "m", "hub travel forward since the drive started"),
    "slip": (None, np.float64, "1", "slip 1 - v / (omega r); nan while the wheel does not turn"),
    "sinkage": (None, np.float64, "m", "surface height - lowest rim point"),
    "sinkage_tips": (None, np.float64, "m", "surface height - (hub height - outer radius): the tips' envelope"),
    "drawbar_pull": (None, np.float64, "N", "soil force on the wheel along its forward direction"),
    "driving_torque": (None, np.float64, "N m", "torque the drive supplies against the soil"),
    "normal_force": (None, np.float64, "N", "soil force on the wheel along the bed normal"),
    "power": (None, np.float64, "W", "power the drive delivers against the soil torque, driving_torque x spin"),
    "speed_command": (None, np.float64, "rad/s", "wheel speed commanded over the step (nan: a torque was)"),
    "torque_command": (None, np.float64, "N m", "wheel torque commanded over the step (nan: a speed was)"),
}
"""Per-wheel datasets under /wheels, each shaped (S, W) or (S, W, k)."""

BOUNDARY_SERIES = {
    # name: (trailing shape (None: per wall scalar), dtype, units, description)
    "force": (3, np.float64, "N", "force of the grains on the wall at the end of the macro step, world frame"),
    "torque": (3, np.float64, "N m", "torque of the grains about the wall's reference point (plane point, box centre)"),
    "contact_count": (None, np.int64, "count", "grains touching the wall"),
    "displacement": (3, np.float64, "m", "displacement of the wall from its place at the start"),
}
"""Per-wall datasets under /boundaries, each shaped (S, B) or (S, B, 3)."""

ROVER_SERIES = {
    # name: (trailing shape (None: scalar), units, description); row key "rover_<name>"
    "position": (3, "m", "rover body frame origin, world frame"),
    "orientation": (4, "1", "quaternion (w, x, y, z), rover body -> world"),
    "linear_velocity": (3, "m/s", "velocity of the body frame origin, world frame"),
    "angular_velocity": (3, "rad/s", "body angular velocity, world frame"),
    "forward_speed": (None, "m/s", "body velocity along its forward direction"),
    "slip": (None, "1", "1 - forward speed / mean rim speed of the wheels (nan: they turn against each other)"),
    "net_traction": (None, "N", "sum of the wheels' soil forces along the rover's forward direction"),
    "power": (None, "W", "sum of the wheels' drive power against the soil"),
    "travel": (None, "m", "horizontal path length of the body since the drive started"),
}
"""Rover datasets under /rover, each shaped (S,) or (S, k)."""

SOIL_SERIES = {
    # name: (dtype, units, description); row key "soil_<name>"
    "particle_count": (np.int64, "count", "grains simulated"),
    "mass": (np.float64, "kg", "mass of the grains simulated"),
    "mass_added": (np.float64, "kg", "soil placed ahead by the moving patch so far"),
    "mass_removed": (np.float64, "kg", "soil removed behind the moving patch so far"),
    "moves": (np.int64, "count", "moves of the patch so far"),
    "dem_steps": (np.int64, "count", "DEM steps of the macro step (run.step_control = 'pid': accepted substeps)"),
    "dem_steps_rejected": (np.int64, "count", "PID substeps computed and thrown away in the macro step"),
    "dt_min": (np.float64, "s", "shortest DEM step of the macro step"),
    "dt_mean": (np.float64, "s", "mean DEM step of the macro step (its span / dem_steps)"),
    "dt_max": (np.float64, "s", "longest DEM step of the macro step"),
    "force_evaluations": (np.int64, "count", "force evaluations of the macro step (rejected substeps included)"),
}
"""Soil bookkeeping under /soil, each shaped (S,)."""

STEP_SERIES = {
    "wheels/time": ("s", "end time of the macro step"),
    "wheels/phase": ("1", "0: landing, 1: driving"),
    "rover/time": ("s", "end time of the macro step"),
}


def package_versions() -> dict:
    from importlib import metadata

    import h5py

    versions = {}
    for name in (
        "regolith-cosim",
        "warp-lang",
        "numpy",
        "scipy",
        "h5py",
        "pydantic",
        "mujoco",
        "fmpy",
        "dask",
        "distributed",
    ):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    versions["hdf5"] = h5py.version.hdf5_version
    return versions


def documented_layout(
    wheels: int, particles: int, vertices: int, triangles: int, columns: int, boundaries: int = 0, ragged: bool = False
) -> dict:
    """{dataset path: (shape with None for the growing axis, numpy kind)}: the layout above (ragged:
    the particle rows R are the growing axis of the row datasets)."""
    layout = {
        "wheels/time": ((None,), "f"),
        "wheels/phase": ((None,), "i"),
        "rover/time": ((None,), "f"),
        "rover/state": ((None, columns), "f"),
        "particles/time": ((None,), "f"),
        "particles/wheel_vertices": ((None, vertices, 3), "f"),
        "particles/rover_position": ((None, 3), "f"),
        "particles/rover_forward": ((None, 3), "f"),
        "particles/rover_up": ((None, 3), "f"),
        "wheels/mesh/vertices": ((vertices, 3), "f"),
        "wheels/mesh/triangles": ((triangles, 3), "i"),
        "wheels/mesh/wheel": ((vertices,), "i"),
    }
    if ragged:
        layout.update(
            {
                "particles/first": ((None,), "i"),
                "particles/count": ((None,), "i"),
                "particles/id": ((None,), "i"),
                "particles/radius": ((None,), "f"),
                "particles/position": ((None, 3), "f"),
                "particles/velocity": ((None, 3), "f"),
            }
        )
    else:
        layout.update(
            {
                "particles/radius": ((particles,), "f"),
                "particles/position": ((None, particles, 3), "f"),
                "particles/velocity": ((None, particles, 3), "f"),
            }
        )
    for name, (tail, dtype, _, _) in WHEEL_SERIES.items():
        layout[f"wheels/{name}"] = ((None, wheels) if tail is None else (None, wheels, tail), np.dtype(dtype).kind)
    if boundaries:
        for name, (tail, dtype, _, _) in BOUNDARY_SERIES.items():
            shape = (None, boundaries) if tail is None else (None, boundaries, tail)
            layout[f"boundaries/{name}"] = (shape, np.dtype(dtype).kind)
        layout.update(
            {
                "boundaries/kind": ((boundaries,), "i"),
                "boundaries/geometry": ((boundaries, 6), "f"),
                "boundaries/report": ((boundaries,), "i"),
            }
        )
    for name, (tail, _, _) in ROVER_SERIES.items():
        layout[f"rover/{name}"] = ((None,) if tail is None else (None, tail), "f")
    for name, (dtype, _, _) in SOIL_SERIES.items():
        layout[f"soil/{name}"] = ((None,), np.dtype(dtype).kind)
    return layout


REQUIRED_ATTRIBUTES = (
    "format",
    "status",
    "message",
    "name",
    "scene_toml",
    "scene_source",
    "versions",
    "created",
    "precision",
    "device",
    "scheme",
    "integrator",
    "order_seed",
    "dt",
    "macro_step",
    "substeps",
    "duration",
    "gravity",
    "surface_height",
    "start_position",
    "omega",
    "rim_radius",
    "outer_radius",
    "wheel_load",
    "mode",
    "particle_count",
    "wheel_names",
    "bed",
    "findings",
)


def open_results(path, mode="r"):
    """Open a results.h5 for reading, also while a run still writes it (SWMR) or after it was killed.

    A file that is not HDF5 or is shorter than its header says (cut short) is refused at once
    (DamagedFileError): SWMR reads retry failed reads and would take minutes to give up on it."""
    import h5py

    from soil.files import check_hdf5

    path = os.fspath(path)
    check_hdf5(path, "results file")
    try:
        return h5py.File(path, mode, libver="latest", locking=False)
    except OSError:
        if mode != "r":
            raise
        return h5py.File(path, "r", libver="latest", swmr=True, locking=False)


CHECKSUMMED = {"fletcher32": True}
"""The create_dataset options of every results dataset (a Fletcher-32 checksum per chunk, which HDF5
verifies on each read; a filter needs chunks, which h5py picks where none are given)."""


def _fixed(group, name: str, data) -> None:
    """A dataset written once, whole, with its checksum."""
    group.create_dataset(name, data=data, **CHECKSUMMED)


def _units(dataset, units: str, description: str) -> None:
    dataset.attrs["units"] = units
    dataset.attrs["description"] = description


class ResultsWriter:
    """Buffered, crash-tolerant writer of results.h5 (see the module docstring for the layout).

    `ResultsWriter.create(...)` starts a new file, `ResultsWriter.resume(...)` continues one
    from a checkpoint's counts. Call `close(status, message, summary)` at the end.
    """

    def __init__(self, path, flush_every: int = 50, xdmf: bool = True):
        self.path = os.fspath(path)
        self.flush_every = int(flush_every)
        self.xdmf = xdmf
        self._file: Any = None  # the open h5py.File (h5py is imported when needed); None when closed
        self._buffer: list[dict] = []
        self._datasets: dict[str, Any] = {}  # the open file's record datasets by path (h5py lookups cost)
        self._xdmf_known: dict[str, tuple] = {}  # write_xdmf's grids made so far, by snapshot
        self.steps = 0
        """Macro-step records written or buffered."""
        self.snapshots = 0
        """Particle snapshots written."""

    # -- create / resume -----------------------------------------------------------
    @classmethod
    def create(
        cls,
        path,
        *,
        attrs: dict,
        radius: np.ndarray,
        wheel_count: int,
        mesh: tuple,
        rover_columns: list[str],
        rover_units: list[str],
        boundaries: dict | None = None,
        flush_every: int = 50,
        xdmf: bool = True,
        ragged: bool = False,
    ) -> ResultsWriter:
        """A new file; refuses to replace an existing one (the caller decides about that).

        boundaries: {'kind' (B,), 'geometry' (B, 6) [m], 'report' (B,)} of the soil's walls, or None.
        ragged: the grains change between snapshots (a moving patch): `radius` gives the first
        snapshot's count only, each snapshot gives its own radii."""
        import h5py

        writer = cls(path, flush_every, xdmf)
        if os.path.exists(writer.path):
            raise FileExistsError(f"{writer.path} exists; refusing to overwrite results")
        vertices, triangles, vertex_wheel = mesh
        n = len(radius)
        w = int(wheel_count)
        f = h5py.File(writer.path, "w", libver="latest")
        try:
            for key, value in attrs.items():
                f.attrs[key] = value
            f.attrs["format"] = RESULTS_FORMAT
            f.attrs["status"] = "running"
            f.attrs["message"] = ""
            f.attrs["summary"] = "{}"
            if "created" not in f.attrs:
                f.attrs["created"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
            f.attrs["versions"] = json.dumps(package_versions())
            rows = max(1, min(1024, 4 * flush_every))

            def series(group, name, shape, dtype, units, description):
                dataset = group.create_dataset(
                    name, shape, dtype, maxshape=(None,) + shape[1:], chunks=(rows,) + shape[1:], **CHECKSUMMED
                )
                _units(dataset, units, description)

            g = f.create_group("wheels")
            series(g, "time", (0,), np.float64, *STEP_SERIES["wheels/time"])
            series(g, "phase", (0,), np.int8, *STEP_SERIES["wheels/phase"])
            for name, (tail, dtype, units, description) in WHEEL_SERIES.items():
                series(g, name, (0, w) if tail is None else (0, w, tail), dtype, units, description)
            m = g.create_group("mesh")
            _fixed(m, "vertices", np.asarray(vertices, dtype=np.float64).reshape(-1, 3))
            _units(m["vertices"], "m", "wheel mesh vertices in their wheel frames")
            _fixed(m, "triangles", np.asarray(triangles, dtype=np.int32).reshape(-1, 3))
            _units(m["triangles"], "1", "vertex indices of each triangle")
            _fixed(m, "wheel", np.asarray(vertex_wheel, dtype=np.int32))
            _units(m["wheel"], "1", "wheel index of each vertex")
            if boundaries is not None and len(boundaries["kind"]):
                nb = len(boundaries["kind"])
                b = f.create_group("boundaries")
                for name, (tail, dtype, units, description) in BOUNDARY_SERIES.items():
                    series(b, name, (0, nb) if tail is None else (0, nb, tail), dtype, units, description)
                _fixed(b, "kind", np.asarray(boundaries["kind"], dtype=np.int32))
                _units(b["kind"], "1", "0 plane (point, unit normal), 1 box (lower corner, upper corner)")
                _fixed(b, "geometry", np.asarray(boundaries["geometry"], dtype=np.float64).reshape(nb, 6))
                described = "each wall's geometry row as built (plane: point [m], normal [1]; box: corners [m])"
                _units(b["geometry"], "m", described)
                _fixed(b, "report", np.asarray(boundaries["report"], dtype=np.int8))
                _units(b["report"], "1", "1: the wall's force is summed; 0: it reads zero")
            r = f.create_group("rover")
            series(r, "time", (0,), np.float64, *STEP_SERIES["rover/time"])
            series(r, "state", (0, len(rover_columns)), np.float64, "see columns/units", "rover state per step")
            r["state"].attrs["columns"] = json.dumps(list(rover_columns))
            r["state"].attrs["units"] = json.dumps(list(rover_units))
            for name, (tail, units, description) in ROVER_SERIES.items():
                series(r, name, (0,) if tail is None else (0, tail), np.float64, units, description)
            g = f.create_group("soil")
            for name, (dtype, units, description) in SOIL_SERIES.items():
                series(g, name, (0,), dtype, units, description)
            p = f.create_group("particles")
            p.attrs["layout"] = "ragged" if ragged else "fixed"
            p.create_dataset("time", (0,), np.float64, maxshape=(None,), chunks=(64,), **CHECKSUMMED)
            _units(p["time"], "s", "snapshot times")
            if ragged:
                chunk = max(1024, min(65536, len(radius)))
                for name, dtype, units, description in (
                    ("first", np.int64, "count", "first row of each snapshot"),
                    ("count", np.int64, "count", "rows of each snapshot"),
                ):
                    p.create_dataset(name, (0,), dtype, maxshape=(None,), chunks=(64,), **CHECKSUMMED)
                    _units(p[name], units, description)
                for name, row, dtype, units, description in (
                    ("id", (), np.int64, "1", "grain id, unique over the run"),
                    ("radius", (), np.float64, "m", "grain radii"),
                    ("position", (3,), np.float64, "m", "grain centres"),
                    ("velocity", (3,), np.float32, "m/s", "grain velocities"),
                ):
                    p.create_dataset(name, (0, *row), dtype, maxshape=(None, *row), chunks=(chunk, *row), **CHECKSUMMED)
                    _units(p[name], units, description)
            else:
                _fixed(p, "radius", np.asarray(radius, dtype=np.float64))
                _units(p["radius"], "m", "grain radii (model order)")
                # HDF5 chunks are not empty: a soil without grains (N = 0) gets an open grain axis for its chunk
                grains, grain_chunk = (n, (1, n, 3)) if n else (None, (1, 1, 3))
                p.create_dataset(
                    "position", (0, n, 3), np.float64, maxshape=(None, grains, 3), chunks=grain_chunk, **CHECKSUMMED
                )
                _units(p["position"], "m", "grain centres")
                p.create_dataset(
                    "velocity", (0, n, 3), np.float32, maxshape=(None, grains, 3), chunks=grain_chunk, **CHECKSUMMED
                )
                _units(p["velocity"], "m/s", "grain velocities")
            nv = len(m["vertices"])
            p.create_dataset(
                "wheel_vertices", (0, nv, 3), np.float32, maxshape=(None, nv, 3), chunks=(1, nv, 3), **CHECKSUMMED
            )
            _units(p["wheel_vertices"], "m", "wheel meshes posed at each snapshot, world frame")
            p.create_dataset("rover_position", (0, 3), np.float64, maxshape=(None, 3), chunks=(64, 3), **CHECKSUMMED)
            _units(p["rover_position"], "m", "rover body frame origin at each snapshot")
            for name, axis in (("rover_forward", "x"), ("rover_up", "z")):
                p.create_dataset(name, (0, 3), np.float64, maxshape=(None, 3), chunks=(64, 3), **CHECKSUMMED)
                _units(p[name], "1", f"rover body {axis} axis at each snapshot, world frame")
            f.swmr_mode = True
        except BaseException:
            f.close()
            raise
        writer._file = f
        writer._write_xdmf()
        return writer

    @classmethod
    def resume(cls, path, steps: int, snapshots: int, flush_every: int = 50, xdmf: bool = True) -> ResultsWriter:
        """Continue a file from a checkpoint: its first `steps` records and `snapshots` snapshots are
        copied into a fresh file that atomically replaces it (a file a killed writer left flagged
        as open needs no repair tool), and writing goes on there."""
        import h5py

        writer = cls(path, flush_every, xdmf)
        if not os.path.isfile(writer.path):
            raise FileNotFoundError(f"{writer.path} not found: nothing to resume")
        with atomic_path(writer.path, ".h5.tmp") as temporary:
            with open_results(writer.path) as old, h5py.File(temporary, "w", libver="latest") as new:
                if old.attrs.get("format") != RESULTS_FORMAT:
                    raise DamagedFileError(
                        f"{writer.path} is not a regolith-cosim results file of format {RESULTS_FORMAT!r}"
                    )
                rows = {}
                if "first" in old["particles"]:  # ragged snapshots: keep the rows of the first `snapshots`
                    kept = (
                        int(old["particles/first"][snapshots - 1] + old["particles/count"][snapshots - 1])
                        if snapshots
                        else 0
                    )
                    rows = {f"particles/{name}": kept for name in ("id", "radius", "position", "velocity")}
                _copy_truncated(
                    old,
                    new,
                    {"wheels": steps, "rover": steps, "boundaries": steps, "soil": steps, "particles": snapshots},
                    rows,
                )
                new.attrs["status"] = "running"
                new.attrs["message"] = ""
        # the XDMF data file is rebuilt from the cut results: a resumed snapshot may differ from the lost one
        data_path = os.path.join(os.path.dirname(os.path.abspath(writer.path)), XDMF_DATA_FILE)
        if os.path.exists(data_path):
            os.remove(data_path)
        f = h5py.File(writer.path, "r+", libver="latest")
        f.swmr_mode = True
        writer._file = f
        writer.steps = int(steps)
        writer.snapshots = int(snapshots)
        return writer

    # -- writing --------------------------------------------------------------------
    def append_step(self, row: dict) -> None:
        """Buffer one macro step: 'time' [s], 'phase', every WHEEL_SERIES name (W, ...), 'rover_state' (K,),
        'rover_<name>' for every ROVER_SERIES name, 'soil_<name>' for every SOIL_SERIES name, and with walls
        'boundary_<name>' for every BOUNDARY_SERIES name (B, ...)."""
        self._buffer.append(row)
        self.steps += 1
        if len(self._buffer) >= self.flush_every:
            self.flush()

    def add_snapshot(
        self,
        time: float,
        position: np.ndarray,
        velocity: np.ndarray,
        wheel_vertices: np.ndarray,
        rover_pose: tuple | None = None,
        radius: np.ndarray | None = None,
        ids: np.ndarray | None = None,
    ) -> None:
        """Write one particle snapshot now (and flush). rover_pose: (position [m] (3,), rotation body -> world
        (3, 3)) of the rover body; radius [m] and ids: the grains' (a ragged file only). An OSError names the
        file (as flush's)."""
        try:
            self._add_snapshot(time, position, velocity, wheel_vertices, rover_pose, radius, ids)
        except OSError as error:
            raise with_path(error, self.path) from error

    def _add_snapshot(self, time, position, velocity, wheel_vertices, rover_pose, radius, ids) -> None:
        self.flush_records()
        p = self._file["particles"]
        k = self.snapshots
        pose = rover_pose if rover_pose is not None else (np.full(3, np.nan), np.full((3, 3), np.nan))
        axes = np.asarray(pose[1], dtype=np.float64)
        per_snapshot = [
            ("time", time),
            ("wheel_vertices", wheel_vertices),
            ("rover_position", pose[0]),
            ("rover_forward", axes[:, 0]),
            ("rover_up", axes[:, 2]),
        ]
        if p.attrs.get("layout") == "ragged":
            first = int(p["position"].shape[0])
            rows = len(position)
            per_snapshot += [("first", first), ("count", rows)]
            for name, value in (("position", position), ("velocity", velocity), ("radius", radius), ("id", ids)):
                dataset = p[name]
                dataset.resize(first + rows, axis=0)
                dataset[first : first + rows] = value
        else:
            per_snapshot += [("position", position), ("velocity", velocity)]
        for name, value in per_snapshot:
            dataset = p[name]
            dataset.resize(k + 1, axis=0)
            dataset[k] = value
        self.snapshots += 1
        self._file.flush()
        self._write_xdmf()

    def flush_records(self) -> None:
        if not self._buffer:
            return
        f = self._file
        if self._datasets.get("file") is not f:  # a new or reopened file: look its datasets up again
            self._datasets = {"file": f}
        rows = self._buffer
        start = self.steps - len(rows)
        stop = self.steps

        def put(path, values):
            dataset = self._datasets.get(path)
            if dataset is None:
                dataset = self._datasets[path] = f[path]
            dataset.resize(stop, axis=0)
            dataset[start:stop] = values

        times = np.array([r["time"] for r in rows], dtype=np.float64)
        put("wheels/time", times)
        put("rover/time", times)
        put("wheels/phase", np.array([r["phase"] for r in rows], dtype=np.int8))
        for name in WHEEL_SERIES:
            put(f"wheels/{name}", np.array([r[name] for r in rows]))
        if "boundaries" in f:
            for name in BOUNDARY_SERIES:
                put(f"boundaries/{name}", np.array([r[f"boundary_{name}"] for r in rows]))
        put("rover/state", np.array([r["rover_state"] for r in rows], dtype=np.float64))
        for name in ROVER_SERIES:
            put(f"rover/{name}", np.array([r[f"rover_{name}"] for r in rows], dtype=np.float64))
        for name, (dtype, _, _) in SOIL_SERIES.items():
            put(f"soil/{name}", np.array([r[f"soil_{name}"] for r in rows], dtype=dtype))
        self._buffer = []

    def flush(self) -> None:
        """Write buffered records and flush the file to disk (an OSError names the file)."""
        if self._file is None:
            return
        try:
            self.flush_records()
            self._file.flush()
        except OSError as error:
            raise with_path(error, self.path) from error

    def close(self, status: str | None = None, message: str = "", summary: dict | None = None) -> None:
        """Flush and close; with a status, record it (see `mark`)."""
        if self._file is not None:
            try:
                self.flush()
            finally:
                self._file.close()
                self._file = None
        if status is not None:
            self.mark(status, message, summary)

    def mark(self, status: str, message: str = "", summary: dict | None = None, xdmf: bool = True) -> None:
        """Record the final status, message and summary in the closed file (SWMR forbids attribute writes),
        then (xdmf) bring results.xdmf up to date (update_xdmf)."""
        import h5py

        with h5py.File(self.path, "r+", libver="latest") as f:
            f.attrs["status"] = status
            f.attrs["message"] = message
            if summary is not None:  # a nan (not measured) as null, as run.json: strict JSON readers take it
                f.attrs["summary"] = json.dumps(finite_or_null(summary), allow_nan=False)
        if xdmf:
            self.update_xdmf()

    def update_xdmf(self) -> None:
        """Write results.xdmf (and its results.xdmf.h5) again from the results: a view derived from them."""
        self._write_xdmf()

    def __enter__(self):
        return self

    def __exit__(self, kind, value, traceback):
        if kind is None:
            self.close("complete")
        else:
            self.close("interrupted" if issubclass(kind, KeyboardInterrupt) else "failed", str(value))
        return False

    def _write_xdmf(self) -> None:
        if not self.xdmf:
            return
        target = os.path.join(os.path.dirname(os.path.abspath(self.path)), XDMF_FILE)
        if self._file is not None:
            write_xdmf(self._file, target, self._xdmf_known)
        else:
            with open_results(self.path) as f:
                write_xdmf(f, target, self._xdmf_known)


def _copy_truncated(old, new, counts: dict, rows: dict | None = None) -> None:
    """Copy file `old` into `new`, cutting the growing datasets of each top group to counts[group] rows
    (rows[dataset path], when given, instead)."""
    import h5py

    for key, value in old.attrs.items():
        new.attrs[key] = value

    def visit(name, obj):
        if isinstance(obj, h5py.Group):
            group = new.require_group(name)
            for key, value in obj.attrs.items():
                group.attrs[key] = value
            return
        count = (rows or {}).get(name, counts[name.split("/")[0]])
        growing = obj.maxshape[0] is None
        if growing and obj.shape[0] < count:
            raise DamagedFileError(
                f"the results file holds {obj.shape[0]} rows of {name}, the checkpoint expects {count}: "
                "the file is older than the checkpoint"
            )
        data = obj[:count] if growing else obj[()]
        if growing:
            dataset = new.create_dataset(name, data=data, maxshape=obj.maxshape, chunks=obj.chunks, **CHECKSUMMED)
        else:  # written once: chunks h5py picked for an empty one can exceed its fixed shape, so it picks anew
            dataset = new.create_dataset(name, data=data, **(CHECKSUMMED if np.ndim(data) else {}))
        for key, value in obj.attrs.items():
            dataset.attrs[key] = value

    old.visititems(visit)


GRAIN_DATASETS = frozenset(f"/particles/{name}" for name in ("position", "velocity", "radius", "id"))
"""The datasets of a results file that grow with its grains (h5py names): what check_results(data=False)
leaves to the snapshot reader."""


def check_results(path, data: bool = True) -> dict:
    """The root attributes of a results.h5 after checking that it is one and can be read to its end:
    DamagedFileError naming the file otherwise (FileNotFoundError when it is absent). data False: the
    grains' datasets (GRAIN_DATASETS) by their headers and attributes only, so a picture of one snapshot
    of a large file stays cheap (cosim.snapshots.read_snapshot reads and checks them a snapshot at a
    time); every other dataset, the series, meshes and walls a reader takes whole, is read through."""

    path = os.fspath(path)
    try:
        with open_results(path) as f:
            attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
            if attrs.get("format") != RESULTS_FORMAT:
                raise DamagedFileError(
                    f"{path}: not a regolith-cosim results file (format {attrs.get('format')!r}, "
                    f"expected {RESULTS_FORMAT!r})"
                )
            for dataset in _datasets(f):  # a damaged header or chunk fails here, not midway
                if data or dataset.name not in GRAIN_DATASETS:
                    read_results_data(f, partial(_read_through, dataset), dataset.name.lstrip("/"))
                else:
                    dataset.shape, dataset.dtype, dict(dataset.attrs)
            problem = _structure_problem(f)
            if problem:
                raise DamagedFileError(f"{path}: the results file is damaged ({problem})")
            json.loads(attrs.get("summary", "{}"))
    except (DamagedFileError, FileNotFoundError):
        raise
    except Exception as error:  # h5py reports damaged files as OSError, RuntimeError, KeyError, ...
        raise DamagedFileError(f"{path}: the results file is damaged ({error})") from None
    return attrs


def stored_wheel_mesh(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The wheels' mesh a results file keeps (wheels/mesh: vertices [m] (V, 3) in wheel frames, triangles
    (F, 3), owner wheel (V,)): the wheels its run drove; DamagedFileError when it cannot be read."""
    with open_results(path) as f:
        return tuple(read_whole(f, f"wheels/mesh/{name}") for name in ("vertices", "triangles", "wheel"))


def _structure_problem(f) -> str:
    """What a results file lacks of what ResultsWriter.create makes (a dataset gone, or, in a file that
    was closed, series of unequal lengths), or "": a resume appends to every one of them, a reader
    reads them. A file left 'running' (its writer killed, perhaps inside a flush) may hold more rows
    of some series than of others: a resume cuts them all to its checkpoint's count."""
    step = (
        ["wheels/time", "wheels/phase", "rover/time", "rover/state"]
        + [f"wheels/{name}" for name in WHEEL_SERIES]
        + [f"rover/{name}" for name in ROVER_SERIES]
        + [f"soil/{name}" for name in SOIL_SERIES]
        + ([f"boundaries/{name}" for name in BOUNDARY_SERIES] if "boundaries" in f else [])
    )
    per_snapshot, whole_run = snapshot_datasets("particles" in f and f["particles"].attrs.get("layout") == "ragged")
    snapshot = [f"particles/{name}" for name in per_snapshot]
    fixed = ["wheels/mesh/vertices", "wheels/mesh/triangles", "wheels/mesh/wheel"]
    fixed += [f"particles/{name}" for name in whole_run]
    missing = [name for name in step + snapshot + fixed if name not in f]
    if missing:
        return f"missing {', '.join(missing[:4])}{' ...' if len(missing) > 4 else ''}"
    if f.attrs.get("status") == "running":  # a writer killed inside a flush: resume cuts every series
        return ""
    for names, length in ((step, "wheels/time"), (snapshot, "particles/time")):
        rows = len(f[length])
        uneven = [name for name in names if f[name].shape[0] != rows]
        if uneven:
            return f"{uneven[0]} has {f[uneven[0]].shape[0]} rows where {length} has {rows}"
    return ""


READ_BLOCK_BYTES = 64 * 2**20
"""Most bytes check_results holds of one dataset at a time [B]: a run's snapshots can outgrow memory."""


def _read_through(dataset) -> None:
    """Read every row of `dataset` once, in blocks of at most READ_BLOCK_BYTES (or one row, when a row
    is larger)."""
    if dataset.ndim == 0 or dataset.shape[0] == 0:
        dataset[()]
        return
    row = max(1, dataset.dtype.itemsize * int(np.prod(dataset.shape[1:])))
    rows = max(1, READ_BLOCK_BYTES // row)
    for start in range(0, dataset.shape[0], rows):
        dataset[start : start + rows]


def _datasets(f) -> list:
    import h5py

    found: list = []
    f.visititems(lambda name, obj: found.append(obj) if isinstance(obj, h5py.Dataset) else None)
    return found


def read_series(path) -> dict:
    """The time series of one results.h5 as numpy arrays (the wheel series by name, 'rover_<name>',
    'soil_<name>', 'rover_state', 'rover_columns', 'snapshot_time', 'attrs'), for summaries, plots and studies.
    DamagedFileError naming the file when it is damaged."""

    try:
        return _read_series(path)
    except (DamagedFileError, FileNotFoundError):
        raise
    except Exception as error:  # h5py reports damaged files as OSError, RuntimeError, KeyError, ...
        raise DamagedFileError(f"{os.fspath(path)}: the results file is damaged ({error})") from None


def _read_series(path) -> dict:
    with open_results(path) as f:
        out = {
            name: read_whole(f, f"wheels/{name}") for name in ["time", "phase", *WHEEL_SERIES] if name in f["wheels"]
        }
        out["rover_state"] = read_whole(f, "rover/state")
        out.update({f"rover_{name}": read_whole(f, f"rover/{name}") for name in ROVER_SERIES if name in f["rover"]})
        if "soil" in f:
            out.update({f"soil_{name}": read_whole(f, f"soil/{name}") for name in SOIL_SERIES if name in f["soil"]})
        out["rover_columns"] = json.loads(f["rover/state"].attrs["columns"])
        out["snapshot_time"] = read_whole(f, "particles/time")
        out["attrs"] = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    _check_series(out)
    return out


PLOTTED_SERIES = ("travel", "sinkage", "sinkage_tips", "slip", "drawbar_pull", "driving_torque")
"""The wheel series every results file has had and `cosim plot` draws."""


def _step_series(series: dict) -> list[str]:
    """The names of read_series' per-macro-step series (a row each)."""
    names = [n for n in series if n in WHEEL_SERIES or n in ("time", "phase") or n.startswith(("rover_", "soil_"))]
    return [n for n in names if n != "rover_columns"]


def series_until(series: dict, last_time: float) -> dict:
    """read_series' result with the rows after `last_time` [s] left out of every per-step series."""
    kept = np.asarray(series["time"]) <= last_time
    return {name: value[kept] if name in _step_series(series) else value for name, value in series.items()}


def _check_series(out: dict) -> None:
    """ValueError (read_series: DamagedFileError naming the file) when read_series' result lacks a series
    a reader draws, holds series of unequal lengths, or a summary that is not a JSON table. A file
    still being written (status 'running') may hold steps of some series not yet in others: those
    are cut to the shortest instead."""
    missing = [f"wheels/{name}" for name in ("time", "phase", *PLOTTED_SERIES) if name not in out]
    if missing:
        raise ValueError(f"missing {', '.join(missing)}")
    if not isinstance(json.loads(out["attrs"].get("summary", "{}")), dict):
        raise ValueError("its summary attribute is not a JSON table")
    steps = _step_series(out)
    rows = min(len(out[n]) for n in steps)
    uneven = [n for n in steps if len(out[n]) != rows]
    if uneven and out["attrs"].get("status") != "running":
        raise ValueError(
            f"its series have unequal lengths ({uneven[0]}: {len(out[uneven[0]])} rows, the shortest {rows})"
        )
    for name in uneven:
        out[name] = out[name][:rows]


# ------------------------------------------------------------------------------------
# XDMF

XDMF_DATA_FORMAT = "regolith-cosim xdmf data 1"


def _plain(group, name: str, data, units: str, description: str) -> None:
    if name in group:
        del group[name]
    group[name] = data
    _units(group[name], units, description)


def sync_xdmf_data(f, data_path: str, known: dict | None = None) -> np.ndarray:
    """Bring results.xdmf.h5 up to date with the open results file `f`: each particle snapshot as plain
    datasets (no hyperslabs: meshio's XDMF reader follows none), copied once and kept when its time is
    unchanged; snapshots the results no longer hold (a resume cut them) are removed. Returns the
    snapshots' times [s] (S,).

    known: what an earlier call of the same writer left (write_xdmf's cache: snapshot name -> (time, ...));
    a snapshot in it at the same time is taken as written without being looked at, so that a run's
    writes cost per new snapshot, not per snapshot so far. Entries that no longer hold are dropped.

    Layout (V wheel-mesh vertices, F triangles, n grains of the snapshot):
        /mesh/triangles (F, 3), /mesh/wheel (V,) [1], /mesh/vertex (1, 1) [1]: the rover's one-point cell
        /grains/radius (N,) [m], /grains/vertex (N, 1) [1]   (fixed layout: the same grains in every snapshot)
        /snapshots/<k:06d>/   attribute time [s]
            position (n, 3) [m], velocity (n, 3) [m/s], wheel_vertices (V, 3) [m],
            rover_position, rover_forward, rover_up (1, 3) [m, 1, 1]
            radius (n,) [m], vertex (n, 1) [1], id (n,) [1]   (ragged layout: the grains change)
    """
    import h5py

    known = {} if known is None else known
    if not os.path.exists(data_path):
        known.clear()  # a new data file (or one removed under the writer): nothing in it yet
    p = f["particles"]
    times = p["time"][()]
    ragged = p.attrs.get("layout") == "ragged"
    with h5py.File(data_path, "a", locking=False) as out:
        out.attrs["format"] = XDMF_DATA_FORMAT
        out.attrs["results"] = os.path.basename(f.filename)
        if "mesh" not in out:
            mesh = out.create_group("mesh")
            _plain(mesh, "triangles", f["wheels/mesh/triangles"][()], "1", "vertex indices of each wheel triangle")
            _plain(mesh, "wheel", f["wheels/mesh/wheel"][()], "1", "wheel index of each vertex")
            _plain(mesh, "vertex", np.zeros((1, 1), np.int32), "1", "the one-point cell of the rover body")
        if not ragged and "grains" not in out:
            grains = out.create_group("grains")
            radius = p["radius"][()]
            _plain(grains, "radius", radius, "m", "grain radii (model order)")
            _plain(grains, "vertex", np.arange(len(radius), dtype=np.int32)[:, None], "1", "one cell per grain")
        snapshots = out.require_group("snapshots")
        for name in list(snapshots):
            if int(name) >= len(times):
                del snapshots[name]
        for name in [n for n in known if int(n) >= len(times)]:
            del known[name]
        for k, time in enumerate(times):
            name = f"{k:06d}"
            if name in known and known[name][0] == time:
                continue
            known.pop(name, None)
            if name in snapshots and snapshots[name].attrs.get("time") == time:
                continue
            if name in snapshots:
                del snapshots[name]
            snap = snapshots.create_group(name)
            s = read_snapshot(f, k, check=False)  # the writer's own data, as it wrote it
            if ragged:
                _plain(snap, "radius", s.radius, "m", "grain radii")
                _plain(snap, "id", s.ids, "1", "grain id, unique over the run")
                _plain(snap, "vertex", np.arange(len(s.ids), dtype=np.int32)[:, None], "1", "one cell per grain")
            _plain(snap, "position", s.position, "m", "grain centres")
            _plain(snap, "velocity", s.velocity, "m/s", "grain velocities")
            _plain(snap, "wheel_vertices", s.wheel_vertices, "m", "wheel meshes posed, world frame")
            _plain(snap, "rover_position", s.rover_position[None], "m", "rover body frame origin")
            _plain(snap, "rover_forward", s.rover_forward[None], "1", "rover body x axis, world frame")
            _plain(snap, "rover_up", s.rover_up[None], "1", "rover body z axis, world frame")
            snap.attrs["time"] = time  # last: a snapshot with its time is complete
            snap.attrs["time_units"] = "s"
    return times


def _data_item(parent, h5name: str, path: str, dataset) -> ET.Element:
    dtype = dataset.dtype
    item = ET.SubElement(
        parent,
        "DataItem",
        Dimensions=" ".join(str(s) for s in dataset.shape),
        NumberType="Int" if dtype.kind in "iu" else "Float",
        Precision=str(dtype.itemsize),
        Format="HDF",
    )
    item.text = f"{h5name}:{path}"
    return item


XDMF_COLLECTIONS = ("wheels", "rover", "particles")
"""results.xdmf's temporal collections, in file order (meshio's reader takes the last: the grains; a run
without grains has no grain collection, and meshio takes the rover's pose)."""


def _snapshot_grids(data, name: str) -> tuple[str, ...]:
    """The XML of snapshot `name`'s grid in each of XDMF_COLLECTIONS, indented for its place in the file."""
    h5name = XDMF_DATA_FILE
    where = f"/snapshots/{name}"
    time = repr(float(data[where].attrs["time"]))

    def grid(collection: str, topology: str, cells: str, geometry: str, arrays: dict) -> str:
        uniform = ET.Element("Grid", Name=f"{collection}_{name}", GridType="Uniform")
        ET.SubElement(uniform, "Time", Value=time)
        element = ET.SubElement(uniform, "Topology", TopologyType=topology, NumberOfElements=str(data[cells].shape[0]))
        if topology == "Polyvertex":
            element.set("NodesPerElement", "1")
        _data_item(element, h5name, cells, data[cells])
        _data_item(ET.SubElement(uniform, "Geometry", GeometryType="XYZ"), h5name, geometry, data[geometry])
        for key, path in arrays.items():
            kind = "Vector" if len(data[path].shape) == 2 else "Scalar"
            attribute = ET.SubElement(uniform, "Attribute", Name=ARRAY_NAMES[key], AttributeType=kind, Center="Node")
            _data_item(attribute, h5name, path, data[path])
        ET.indent(uniform, level=3)  # Xdmf > Domain > collection > this grid
        return ET.tostring(uniform, encoding="unicode")

    ragged = "id" in data[where]
    per_grain = where if ragged else "/grains"
    arrays = {"radius": f"{per_grain}/radius", "velocity": f"{where}/velocity", "position": f"{where}/position"}
    if ragged:
        arrays["id"] = f"{where}/id"
    return (
        grid("wheels", "Triangle", "/mesh/triangles", f"{where}/wheel_vertices", {"wheel": "/mesh/wheel"}),
        grid(
            "rover",
            "Polyvertex",
            "/mesh/vertex",
            f"{where}/rover_position",
            {"forward": f"{where}/rover_forward", "up": f"{where}/rover_up"},
        ),
        grid("particles", "Polyvertex", f"{per_grain}/vertex", f"{where}/position", arrays),
    )


def stored_summary(attrs) -> dict:
    """The run summary a results file's attributes hold (`attrs`: read_series's 'attrs', or the file's),
    with nan where it holds null (not measured: strict JSON, as run.json); {} before the run ends."""
    return null_as_nan(json.loads(attrs.get("summary", "{}")))


def write_xdmf(f, xdmf_path: str, known: dict | None = None) -> None:
    """Write results.xdmf (XDMF 3) and its data file results.xdmf.h5 (`sync_xdmf_data`) for an open
    results file: three temporal collections, the wheel meshes (Triangle), the rover body (a point with
    its forward and up axes) and, last, the grains (Polyvertex, with radius, velocity and position as
    point data; a run without grains has none: meshio's time series reader takes the last collection,
    holds its first mesh fixed and gives per step only the point data). Every DataItem names a whole
    dataset of the data file, so the readers need no hyperslabs and the file stays readable while
    results.h5 is being written.

    known: a dict the caller keeps between calls (ResultsWriter does): each snapshot's time and grids'
    XML, made once, so a write costs per new snapshot and the XML's length, not a read of every
    snapshot so far (which made a run's writes quadratic in its snapshots).

    The XML is written to a temporary file and renamed, so a reader never sees half a file.
    """
    import h5py

    known = {} if known is None else known
    data_path = os.path.join(os.path.dirname(os.path.abspath(xdmf_path)), XDMF_DATA_FILE)
    times = sync_xdmf_data(f, data_path, known)
    names = [f"{k:06d}" for k in range(len(times))]
    new = [(name, time) for name, time in zip(names, times) if name not in known]
    if new:
        with h5py.File(data_path, "r", locking=False) as data:
            for name, time in new:
                known[name] = (time, _snapshot_grids(data, name))
    root = ET.Element("Xdmf", Version="3.0")
    domain = ET.SubElement(root, "Domain")
    particles = f["particles"]
    # a run without grains (SCM, the analytic terrain): no grain collection, whose empty grids VTK's XDMF
    # reader refuses ("Error in Update() of Topology") and meshio's would take as the last (0 points)
    grains = particles.attrs.get("layout") == "ragged" or particles["radius"].shape[0] > 0
    collections = XDMF_COLLECTIONS if grains else tuple(c for c in XDMF_COLLECTIONS if c != "particles")
    for collection in collections:
        grid = ET.SubElement(domain, "Grid", Name=collection, GridType="Collection", CollectionType="Temporal")
        if names:
            grid.text = f"@{collection}@"  # the snapshots' grids go here, as made once
    ET.indent(root)
    text = '<?xml version="1.0" ?>\n' + ET.tostring(root, encoding="unicode")
    for c, collection in enumerate(XDMF_COLLECTIONS):
        if collection in collections and names:
            grids = "\n      ".join(known[name][1][c] for name in names)
            text = text.replace(f"@{collection}@", f"\n      {grids}\n    ", 1)
    atomic_write_text(xdmf_path, text + "\n")


def xdmf_references(xdmf_path: str) -> list[tuple[str, str, tuple]]:
    """(h5 file, dataset path, declared shape) of every HDF DataItem in an XDMF file (used by the tests)."""
    tree = ET.parse(xdmf_path)
    folder = os.path.dirname(os.path.abspath(xdmf_path))
    refs = []
    for item in tree.iter("DataItem"):
        if item.get("Format") != "HDF":
            continue
        text, dimensions = item.text, item.get("Dimensions")
        assert text is not None and dimensions is not None  # an HDF DataItem names its dataset and shape
        name, path = text.strip().split(":", 1)
        refs.append((os.path.join(folder, name), path, tuple(int(s) for s in dimensions.split())))
    return refs
