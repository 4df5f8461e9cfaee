"""Run output: results.h5 (HDF5, written as the run goes) and results.xdmf (ParaView).

HDF5 layout of ``results.h5`` (S = macro steps recorded, W = wheels, T = particle
snapshots, N = particles, V = wheel-mesh vertices, F = wheel-mesh triangles, K = rover
state columns). Every time-series dataset grows along its first axis.

    /                               attributes:
        format          "regolith-cosim results 1"
        status          "running" | "complete" | "interrupted" | "diverged" | "failed"
        name            scene name
        scene_toml      the scene as run (TOML text, --set overrides applied)
        scene_source    the scene file's original text ("" when not from a file)
        versions        JSON {package: version} (regolith-cosim, warp-lang, numpy, h5py, ...)
        created         ISO 8601 time the run started
        precision, device, scheme, order_seed (-1: none)
        dt [s], macro_step [s], substeps, duration [s], gravity [m/s^2] (3,)
        surface_height [m], start_position [m] (3,), omega [rad/s], rim_radius [m]
        particle_count, wheel_names (JSON list), bed (JSON: settle report + metrics)
        message         why the run stopped ("" when complete)
    /wheels/                        one row per macro step, wheel quantities at its end
        time              (S,)       [s]
        position          (S, W, 3)  hub position [m]
        orientation       (S, W, 4)  quaternion (w, x, y, z) body -> world
        linear_velocity   (S, W, 3)  [m/s]
        angular_velocity  (S, W, 3)  [rad/s]
        force             (S, W, 3)  soil force on the wheel held over the step [N]
        torque            (S, W, 3)  soil torque about the hub [N m]
        sinkage           (S, W)     [m]  (surface height - lowest rim point)
        contact_count     (S, W)     int64
        work_on_rover     (S, W)     [J]
        work_on_soil      (S, W)     [J]
        travel            (S, W)     hub x - start x [m]
        slip              (S, W)     1 - v_x / (omega r) [-]
        drawbar_pull      (S, W)     force x [N]
        driving_torque    (S, W)     -torque y [N m]
        mesh/vertices     (V, 3)     all wheel meshes in their wheel frames [m] (for display)
        mesh/triangles    (F, 3)     int32, indices into vertices
        mesh/wheel        (V,)       int32, wheel index of each vertex
    /rover/
        time              (S,)       [s]
        state             (S, K)     attribute `columns` (JSON) names the columns; single-wheel
                                     rig: x, y, z [m], vx, vy, vz [m/s], angle [rad]
    /particles/
        radius            (N,)       [m]  (model order: fixed for the run)
        time              (T,)       [s]
        position          (T, N, 3)  float64 [m]
        velocity          (T, N, 3)  float32 [m/s]
        wheel_vertices    (T, V, 3)  float32 [m], the wheel meshes posed at each snapshot

The file is written in SWMR mode (libver 'latest'): records are buffered and flushed
every `flush_every` macro steps, so a killed run leaves a readable file with everything
up to the last flush; `open_results` reads it (also while the run is still writing).
``results.xdmf`` beside it references /particles (Polyvertex) and the wheel mesh
(Triangle) as temporal collections via HDF5 hyperslabs; open it in ParaView
("Xdmf3 Reader S" or "XDMF Reader").
"""

from __future__ import annotations

import json
import os
import xml.etree.ElementTree as ET
from datetime import datetime, timezone

import numpy as np

from soil.files import atomic_write_text

RESULTS_FORMAT = "regolith-cosim results 1"
RESULTS_FILE = "results.h5"
XDMF_FILE = "results.xdmf"

WHEEL_SERIES = {
    # name: (trailing shape given W, dtype)
    "position": (3, np.float64), "orientation": (4, np.float64), "linear_velocity": (3, np.float64),
    "angular_velocity": (3, np.float64), "force": (3, np.float64), "torque": (3, np.float64),
    "sinkage": (None, np.float64), "contact_count": (None, np.int64), "work_on_rover": (None, np.float64),
    "work_on_soil": (None, np.float64), "travel": (None, np.float64), "slip": (None, np.float64),
    "drawbar_pull": (None, np.float64), "driving_torque": (None, np.float64),
}
"""Per-wheel datasets under /wheels, each shaped (S, W) or (S, W, k)."""


def package_versions() -> dict:
    from importlib import metadata

    versions = {}
    for name in ("regolith-cosim", "warp-lang", "numpy", "scipy", "h5py", "pydantic", "mujoco", "fmpy", "dask",
                 "distributed"):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    import h5py

    versions["hdf5"] = h5py.version.hdf5_version
    return versions


def documented_layout(wheels: int, particles: int, vertices: int, triangles: int, columns: int) -> dict:
    """{dataset path: (shape with None for the growing axis, numpy kind)}: the layout above."""
    layout = {"wheels/time": ((None,), "f"), "rover/time": ((None,), "f"), "rover/state": ((None, columns), "f"),
              "particles/radius": ((particles,), "f"), "particles/time": ((None,), "f"),
              "particles/position": ((None, particles, 3), "f"), "particles/velocity": ((None, particles, 3), "f"),
              "particles/wheel_vertices": ((None, vertices, 3), "f"),
              "wheels/mesh/vertices": ((vertices, 3), "f"), "wheels/mesh/triangles": ((triangles, 3), "i"),
              "wheels/mesh/wheel": ((vertices,), "i")}
    for name, (tail, dtype) in WHEEL_SERIES.items():
        shape = (None, wheels) if tail is None else (None, wheels, tail)
        layout[f"wheels/{name}"] = (shape, np.dtype(dtype).kind)
    return layout


REQUIRED_ATTRIBUTES = ("format", "status", "name", "scene_toml", "scene_source", "versions", "created", "precision",
                       "device", "scheme", "order_seed", "dt", "macro_step", "substeps", "duration", "gravity",
                       "surface_height", "start_position", "omega", "rim_radius", "particle_count", "wheel_names",
                       "bed", "message")


def open_results(path, mode="r"):
    """Open a results.h5 for reading, also while a run still writes it (SWMR) or after it was killed."""
    import h5py

    path = os.fspath(path)
    try:
        return h5py.File(path, mode, libver="latest", locking=False)
    except OSError:
        if mode != "r":
            raise
        return h5py.File(path, "r", libver="latest", swmr=True, locking=False)


class ResultsWriter:
    """Buffered, crash-tolerant writer of results.h5 (see the module docstring for the layout).

    Create with `ResultsWriter.create(...)` for a new run or `ResultsWriter.reopen(...)` to
    continue a run (datasets are cut back to the counts of the checkpoint).
    Use as a context manager or call `close(status, message)`.
    """

    def __init__(self, path, flush_every: int = 50, xdmf: bool = True):
        self.path = os.fspath(path)
        self.flush_every = int(flush_every)
        self.xdmf = xdmf
        self._file = None
        self._buffer: list[dict] = []
        self.steps = 0
        """Macro-step records written or buffered."""
        self.snapshots = 0
        """Particle snapshots written."""

    # -- create / reopen -----------------------------------------------------------
    @classmethod
    def create(cls, path, *, attrs: dict, radius: np.ndarray, wheel_count: int, mesh: tuple,
               rover_columns: list[str], flush_every: int = 50, xdmf: bool = True) -> "ResultsWriter":
        """A new file; refuses to replace an existing one (the caller decides about that)."""
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
            f.attrs.setdefault("created", datetime.now(timezone.utc).isoformat(timespec="seconds"))
            f.attrs["versions"] = json.dumps(package_versions())
            rows = max(1, min(1024, 4 * flush_every))
            g = f.create_group("wheels")
            g.create_dataset("time", (0,), np.float64, maxshape=(None,), chunks=(rows,))
            for name, (tail, dtype) in WHEEL_SERIES.items():
                shape = (0, w) if tail is None else (0, w, tail)
                g.create_dataset(name, shape, dtype, maxshape=(None,) + shape[1:], chunks=(rows,) + shape[1:])
            m = g.create_group("mesh")
            m["vertices"] = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
            m["triangles"] = np.asarray(triangles, dtype=np.int32).reshape(-1, 3)
            m["wheel"] = np.asarray(vertex_wheel, dtype=np.int32)
            r = f.create_group("rover")
            r.create_dataset("time", (0,), np.float64, maxshape=(None,), chunks=(rows,))
            state = r.create_dataset("state", (0, len(rover_columns)), np.float64, maxshape=(None, len(rover_columns)),
                                     chunks=(rows, len(rover_columns)))
            state.attrs["columns"] = json.dumps(list(rover_columns))
            p = f.create_group("particles")
            p["radius"] = np.asarray(radius, dtype=np.float64)
            p.create_dataset("time", (0,), np.float64, maxshape=(None,), chunks=(64,))
            p.create_dataset("position", (0, n, 3), np.float64, maxshape=(None, n, 3), chunks=(1, n, 3))
            p.create_dataset("velocity", (0, n, 3), np.float32, maxshape=(None, n, 3), chunks=(1, n, 3))
            nv = len(m["vertices"])
            p.create_dataset("wheel_vertices", (0, nv, 3), np.float32, maxshape=(None, nv, 3), chunks=(1, nv, 3))
            f.swmr_mode = True
        except BaseException:
            f.close()
            raise
        writer._file = f
        writer._write_xdmf()
        return writer

    @classmethod
    def reopen(cls, path, steps: int, snapshots: int, flush_every: int = 50, xdmf: bool = True) -> "ResultsWriter":
        """Continue a file: cut the time series back to `steps` rows and the snapshots to `snapshots`."""
        import h5py

        writer = cls(path, flush_every, xdmf)
        if not os.path.isfile(writer.path):
            raise FileNotFoundError(f"{writer.path} not found: nothing to resume")
        try:
            f = h5py.File(writer.path, "r+", libver="latest")
        except OSError as error:
            raise OSError(f"cannot reopen {writer.path} for writing ({error}); if the run was killed, clear the file's "
                          f"SWMR flag with `h5clear -s {writer.path}` and resume again") from error
        try:
            if f.attrs.get("format") != RESULTS_FORMAT:
                raise ValueError(f"{writer.path} is not a regolith-cosim results file")
            for name in ["time", *WHEEL_SERIES]:
                _cut(f["wheels"][name], steps, "wheels/" + name)
            _cut(f["rover/time"], steps, "rover/time")
            _cut(f["rover/state"], steps, "rover/state")
            for name in ("time", "position", "velocity", "wheel_vertices"):
                _cut(f["particles"][name], snapshots, "particles/" + name)
            f.attrs["status"] = "running"
            f.attrs["message"] = ""
            f.swmr_mode = True
        except BaseException:
            f.close()
            raise
        writer._file = f
        writer.steps = int(steps)
        writer.snapshots = int(snapshots)
        return writer

    # -- writing --------------------------------------------------------------------
    def append_step(self, record: dict) -> None:
        """Buffer one macro step: keys 'time', every WHEEL_SERIES name, 'rover_state' (K,)."""
        self._buffer.append(record)
        self.steps += 1
        if len(self._buffer) >= self.flush_every:
            self.flush()

    def add_snapshot(self, time: float, position: np.ndarray, velocity: np.ndarray,
                     wheel_vertices: np.ndarray) -> None:
        """Write one particle snapshot now (and flush)."""
        self.flush_records()
        p = self._file["particles"]
        k = self.snapshots
        for name, value in (("time", time), ("position", position), ("velocity", velocity),
                            ("wheel_vertices", wheel_vertices)):
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
        rows = self._buffer
        start = self.steps - len(rows)
        stop = self.steps

        def put(dataset, values):
            dataset.resize(stop, axis=0)
            dataset[start:stop] = values

        put(f["wheels/time"], np.array([r["time"] for r in rows], dtype=np.float64))
        put(f["rover/time"], np.array([r["time"] for r in rows], dtype=np.float64))
        for name in WHEEL_SERIES:
            put(f["wheels"][name], np.array([r[name] for r in rows]))
        put(f["rover/state"], np.array([r["rover_state"] for r in rows], dtype=np.float64))
        self._buffer = []

    def flush(self) -> None:
        """Write buffered records and flush the file to disk."""
        if self._file is None:
            return
        self.flush_records()
        self._file.flush()

    def close(self, status: str = "complete", message: str = "") -> None:
        """Flush, close, and record the final status (a short reopen: SWMR forbids attribute writes)."""
        import h5py

        if self._file is None:
            return
        try:
            self.flush()
        finally:
            self._file.close()
            self._file = None
        with h5py.File(self.path, "r+", libver="latest") as f:
            f.attrs["status"] = status
            f.attrs["message"] = message
        self._write_xdmf()

    def __enter__(self):
        return self

    def __exit__(self, kind, value, traceback):
        if kind is None:
            self.close("complete")
        else:
            self.close("interrupted" if issubclass(kind, KeyboardInterrupt) else "failed", str(value))
        return False

    # -- XDMF -------------------------------------------------------------------------
    def _write_xdmf(self) -> None:
        if not self.xdmf:
            return
        if self._file is not None:
            write_xdmf(self._file, os.path.join(os.path.dirname(os.path.abspath(self.path)), XDMF_FILE))
        else:
            with open_results(self.path) as f:
                write_xdmf(f, os.path.join(os.path.dirname(os.path.abspath(self.path)), XDMF_FILE))


def _cut(dataset, count: int, name: str) -> None:
    if dataset.shape[0] < count:
        raise ValueError(f"results file holds {dataset.shape[0]} rows of {name}, the checkpoint expects {count}: "
                         "the file is older than the checkpoint")
    dataset.resize(count, axis=0)


# ------------------------------------------------------------------------------------
# XDMF


def _data_item(parent, h5name: str, path: str, shape: tuple, dtype) -> ET.Element:
    dtype = np.dtype(dtype)
    number = "Int" if dtype.kind in "iu" else "Float"
    item = ET.SubElement(parent, "DataItem", Dimensions=" ".join(str(s) for s in shape), NumberType=number,
                         Precision=str(dtype.itemsize), Format="HDF")
    item.text = f"{h5name}:{path}"
    return item


def _slab(parent, h5name: str, path: str, full_shape: tuple, dtype, index: int) -> ET.Element:
    """Row `index` of a (T, ...) dataset as an XDMF HyperSlab."""
    tail = full_shape[1:]
    slab = ET.SubElement(parent, "DataItem", ItemType="HyperSlab", Type="HyperSlab",
                         Dimensions=" ".join(str(s) for s in tail))
    rank = len(full_shape)
    select = ET.SubElement(slab, "DataItem", Dimensions=f"3 {rank}", Format="XML")
    start = [index] + [0] * (rank - 1)
    stride = [1] * rank
    count = [1, *tail]
    select.text = " ".join(str(v) for v in (*start, *stride, *count))
    _data_item(slab, h5name, path, full_shape, dtype)
    return slab


def write_xdmf(f, xdmf_path: str) -> None:
    """Write an XDMF 3 file describing the particle snapshots (and wheel meshes) of an open results file.

    Written to a temporary file and renamed, so a reader never sees half a file.
    """
    h5name = os.path.basename(f.filename)
    p = f["particles"]
    times = p["time"][()]
    t_count = len(times)
    n = p["radius"].shape[0]
    root = ET.Element("Xdmf", Version="3.0")
    domain = ET.SubElement(root, "Domain")
    grains = ET.SubElement(domain, "Grid", Name="particles", GridType="Collection", CollectionType="Temporal")
    mesh = f["wheels/mesh"]
    nv = mesh["vertices"].shape[0]
    nt = mesh["triangles"].shape[0]
    wheel = ET.SubElement(domain, "Grid", Name="wheels", GridType="Collection", CollectionType="Temporal")
    for k in range(t_count):
        grid = ET.SubElement(grains, "Grid", Name=f"particles_{k}", GridType="Uniform")
        ET.SubElement(grid, "Time", Value=repr(float(times[k])))
        ET.SubElement(grid, "Topology", TopologyType="Polyvertex", NumberOfElements=str(n), NodesPerElement="1")
        geometry = ET.SubElement(grid, "Geometry", GeometryType="XYZ")
        _slab(geometry, h5name, "/particles/position", (t_count, n, 3), p["position"].dtype, k)
        radius = ET.SubElement(grid, "Attribute", Name="radius", AttributeType="Scalar", Center="Node")
        _data_item(radius, h5name, "/particles/radius", (n,), p["radius"].dtype)
        velocity = ET.SubElement(grid, "Attribute", Name="velocity", AttributeType="Vector", Center="Node")
        _slab(velocity, h5name, "/particles/velocity", (t_count, n, 3), p["velocity"].dtype, k)

        wgrid = ET.SubElement(wheel, "Grid", Name=f"wheels_{k}", GridType="Uniform")
        ET.SubElement(wgrid, "Time", Value=repr(float(times[k])))
        topology = ET.SubElement(wgrid, "Topology", TopologyType="Triangle", NumberOfElements=str(nt))
        _data_item(topology, h5name, "/wheels/mesh/triangles", (nt, 3), mesh["triangles"].dtype)
        wgeometry = ET.SubElement(wgrid, "Geometry", GeometryType="XYZ")
        _slab(wgeometry, h5name, "/particles/wheel_vertices", (t_count, nv, 3), p["wheel_vertices"].dtype, k)
    ET.indent(root)
    text = '<?xml version="1.0" ?>\n<!DOCTYPE Xdmf SYSTEM "Xdmf.dtd" []>\n' + ET.tostring(root, encoding="unicode")
    atomic_write_text(xdmf_path, text + "\n")


def xdmf_references(xdmf_path: str) -> list[tuple[str, str, tuple, tuple | None]]:
    """(h5 file, dataset path, declared shape, hyperslab (start, stride, count) or None) of every
    HDF DataItem in an XDMF file (used by the tests and `cosim plot --check`)."""
    tree = ET.parse(xdmf_path)
    folder = os.path.dirname(os.path.abspath(xdmf_path))
    refs = []
    parents = {child: parent for parent in tree.iter() for child in parent}
    for item in tree.iter("DataItem"):
        if item.get("Format") != "HDF":
            continue
        name, path = item.text.strip().split(":", 1)
        shape = tuple(int(s) for s in item.get("Dimensions").split())
        slab = None
        parent = parents.get(item)
        if parent is not None and parent.get("ItemType") == "HyperSlab":
            select = [c for c in parent if c.get("Format") == "XML"][0]
            values = [int(v) for v in select.text.split()]
            rank = len(shape)
            slab = (tuple(values[:rank]), tuple(values[rank:2 * rank]), tuple(values[2 * rank:]))
        refs.append((os.path.join(folder, name), path, shape, slab))
    return refs


def read_series(path) -> dict:
    """The time series of one results.h5 as numpy arrays (+ 'attrs'), for plots and studies."""
    with open_results(path) as f:
        out = {name: f["wheels"][name][()] for name in ["time", *WHEEL_SERIES]}
        out["rover_state"] = f["rover/state"][()]
        out["rover_columns"] = json.loads(f["rover/state"].attrs["columns"])
        out["snapshot_time"] = f["particles/time"][()]
        out["attrs"] = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    return out
