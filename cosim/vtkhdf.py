"""results.vtkhdf: the particle snapshots of a results.h5 as one temporal VTKHDF file.

VTKHDF (the VTK file-formats documentation, "VTKHDF") is read natively, with its time steps, by
ParaView (5.12 and later) and VTK's `vtkHDFReader`. The file is a PartitionedDataSetCollection of
four PolyData blocks, each with its own `Steps` group (one step per snapshot, the same times):

    grains       one vertex per grain; point data radius [m], velocity [m s-1], displacement [m]
                 (from where the grain was first seen), id [1]
    wheels       the wheel meshes posed per snapshot (triangles); point data wheel [1]
    rover        the rover body's frame origin (testbed: the hub); point data forward [1], up [1]
    boundaries   the container walls (planes drawn over the extent of the run, boxes as six faces)
                 moved by their displacement; cell data wall [1], force [N] of the grains on the wall

Array names carry their units (`cosim.snapshots.ARRAY_NAMES`); every HDF5 dataset of the file
also has `units` and `description` attributes. A topology that does not change (the wheel
triangles, the walls, the grains of a fixed layout) is stored once and reused by every step.
Written from results.h5 alone: `cosim export vtkhdf RUN` or at the end of a run.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from soil.errors import ArgumentError
from soil.files import atomic_path, output_target

from .folders import CHECKPOINT_FILE, RESULTS_FILE, VTKHDF_FILE
from .output import check_results, open_results
from .snapshots import ARRAY_NAMES, Displacements, read_snapshot, read_whole, snapshot_count

VTKHDF_VERSION = (2, 2)
"""The VTKHDF version written (2.1 added composite data, 2.2 made temporal blocks official)."""

VTKHDF_SUFFIXES = (".vtkhdf", ".hdf")
"""The names an export is written to: a file of another name (a run's results.h5, a checkpoint) never is."""

TOPOLOGIES = ("Vertices", "Lines", "Polygons", "Strips")
"""A PolyData block's four cell arrays, in the order of the Steps offsets."""


def _describe(dataset, units: str, description: str) -> None:
    dataset.attrs["units"] = units
    dataset.attrs["description"] = description


class _Series:
    """A growing 1- or 2-d dataset of a block (rows appended per step), made at the first append with
    chunks of about one step: small arrays stay small, large ones are written in large pieces."""

    def __init__(self, group, name: str, tail: tuple, dtype, units: str, description: str):
        self.group, self.name, self.tail, self.dtype = group, name, tail, np.dtype(dtype)
        self.units, self.description = units, description
        self.dataset: Any = None  # the h5py dataset, made at the first append

    @property
    def rows(self) -> int:
        return 0 if self.dataset is None else int(self.dataset.shape[0])

    def append(self, values) -> int:
        """Append rows; returns the row they start at."""
        values = np.asarray(values, dtype=self.dtype).reshape((-1, *self.tail))
        if self.dataset is None:
            chunk = min(65536, max(64, len(values)))
            self.dataset = self.group.create_dataset(
                self.name, (0, *self.tail), dtype=self.dtype, maxshape=(None, *self.tail), chunks=(chunk, *self.tail)
            )
            _describe(self.dataset, self.units, self.description)
        start = self.rows
        self.dataset.resize(start + len(values), axis=0)
        self.dataset[start:] = values
        return start

    def __getitem__(self, row: int):
        assert self.dataset is not None
        return self.dataset[row]


class PolyBlock:
    """One temporal PolyData block of the collection: its points, one kind of cell (`topology`), its
    point and cell data, and the Steps offsets. `static_cells`: the cells (and so the point and cell
    counts) are the same in every step and written once; `static_data`: the point or cell arrays that
    are, too."""

    def __init__(
        self,
        root,
        name: str,
        index: int,
        topology: str,
        static_cells: bool,
        point_data: dict,
        cell_data: dict,
        static_data: tuple = (),
    ):
        group = root.create_group(name, track_order=True)
        group.attrs["Version"] = np.array(VTKHDF_VERSION, dtype=np.int64)
        group.attrs.create("Type", np.bytes_("PolyData"))
        group.attrs["Index"] = np.int64(index)
        self.topology = topology
        self.static_cells = static_cells
        self.static_data = set(static_data)
        self.steps = 0
        int64 = np.int64
        self.points = _Series(group, "Points", (3,), np.float64, "m", "point coordinates of every step, concatenated")
        self.number_of_points = _Series(group, "NumberOfPoints", (), int64, "count", "points of each part")
        self.cells = {}
        for name_ in TOPOLOGIES:
            cells = group.create_group(name_)
            self.cells[name_] = {
                "NumberOfCells": _Series(cells, "NumberOfCells", (), int64, "count", "cells of each part"),
                "NumberOfConnectivityIds": _Series(
                    cells, "NumberOfConnectivityIds", (), int64, "count", "connectivity ids of each part"
                ),
                "Offsets": _Series(cells, "Offsets", (), int64, "1", "start of each cell in Connectivity, per part"),
                "Connectivity": _Series(cells, "Connectivity", (), int64, "1", "point indices of the cells"),
            }
        self.point_data = {
            key: _Series(group.require_group("PointData"), ARRAY_NAMES[key], tail, dtype, units, description)
            for key, (tail, dtype, units, description) in point_data.items()
        }
        self.cell_data = {
            key: _Series(group.require_group("CellData"), ARRAY_NAMES[key], tail, dtype, units, description)
            for key, (tail, dtype, units, description) in cell_data.items()
        }
        group.require_group("FieldData")
        steps = group.create_group("Steps")
        self.steps_group = steps
        self.values = _Series(steps, "Values", (), np.float64, "s", "time of each step")
        self.part_offsets = _Series(steps, "PartOffsets", (), int64, "1", "first part of each step")
        self.number_of_parts = _Series(steps, "NumberOfParts", (), int64, "count", "parts of each step")
        self.point_offsets = _Series(steps, "PointOffsets", (), int64, "1", "first point of each step")
        self.cell_offsets = _Series(steps, "CellOffsets", (4,), int64, "1", "first cell of each step, per topology")
        self.connectivity_offsets = _Series(
            steps, "ConnectivityIdOffsets", (4,), int64, "1", "first connectivity id of each step, per topology"
        )
        self.point_data_offsets = {
            key: _Series(steps.require_group("PointDataOffsets"), ARRAY_NAMES[key], (), int64, "1", "first row")
            for key in point_data
        }
        self.cell_data_offsets = {
            key: _Series(steps.require_group("CellDataOffsets"), ARRAY_NAMES[key], (), int64, "1", "first row")
            for key in cell_data
        }
        steps.require_group("FieldDataOffsets")

    def add_step(self, time: float, points, cells, point_data: dict, cell_data: dict) -> None:
        """One step: points (n, 3) [m], cells (m, k) point indices of the block's topology, and the arrays."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        cells = np.asarray(cells, dtype=np.int64)
        first = self.steps == 0
        if first or not self.static_cells:
            self.number_of_points.append([len(points)])
            for name, arrays in self.cells.items():
                mine = cells if name == self.topology else np.zeros((0, 1), np.int64)
                arrays["NumberOfCells"].append([len(mine)])
                arrays["NumberOfConnectivityIds"].append([mine.size])
                arrays["Offsets"].append(np.arange(len(mine) + 1) * (mine.shape[1] if mine.size else 0))
                arrays["Connectivity"].append(mine.ravel())
        part = self.number_of_points.rows - 1
        self.values.append([time])
        self.part_offsets.append([part])
        self.number_of_parts.append([1])
        self.point_offsets.append([self.points.append(points)])
        cell_starts, id_starts = [], []
        for arrays in self.cells.values():
            # the reader finds a step's Offsets at CellOffsets + PartOffsets (one more offset than cells per part)
            cell_starts.append(arrays["Offsets"].rows - 1 - int(arrays["NumberOfCells"][part]) - part)
            id_starts.append(arrays["Connectivity"].rows - int(arrays["NumberOfConnectivityIds"][part]))
        self.cell_offsets.append([cell_starts])
        self.connectivity_offsets.append([id_starts])
        for arrays, offsets, values in (
            (self.point_data, self.point_data_offsets, point_data),
            (self.cell_data, self.cell_data_offsets, cell_data),
        ):
            for key, series in arrays.items():
                # a static array is read from row 0 by every step
                offsets[key].append([0 if key in self.static_data and not first else series.append(values[key])])
        self.steps += 1
        self.steps_group.attrs["NSteps"] = np.int64(self.steps)


def _box_corners(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """(8, 3) corners of an axis-aligned box; bit 0, 1, 2 of the index pick the upper x, y, z."""
    return np.array([[(upper if i & bit else lower)[axis] for axis, bit in enumerate((1, 2, 4))] for i in range(8)])


def _wall_faces(kind: int, geometry: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """(faces, 4, 3) quads of one wall: a plane (point, normal) drawn over the box lower..upper, a box
    (lower corner, upper corner) as its six faces [m]."""
    if kind == 1:
        faces = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
        return _box_corners(geometry[:3], geometry[3:])[np.array(faces)]
    point, normal = geometry[:3], geometry[3:] / np.linalg.norm(geometry[3:])
    u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    box = _box_corners(lower, upper)
    centre = (lower + upper) / 2
    centre = centre - np.dot(centre - point, normal) * normal
    su, sv = (box - centre) @ u, (box - centre) @ v
    quad = [(su.min(), sv.min()), (su.max(), sv.min()), (su.max(), sv.max()), (su.min(), sv.max())]
    return np.array([[centre + a * u + b * v for a, b in quad]])


def write_vtkhdf(results_path, vtkhdf_path=None, replace: bool = True) -> str:
    """Write the VTKHDF file of a results.h5 (default: results.vtkhdf beside it); returns its path.

    Written to a temporary file and renamed: a reader never sees half a file, and a failed export
    leaves the previous one. replace False: a file at `vtkhdf_path` (one that appeared while the export
    ran) is kept, the export written beside it (FileExistsError naming both: soil.files.place_new).

    `vtkhdf_path` a symbolic link is written through (its target replaced, the link kept) only when the
    target's name ends in .vtkhdf or .hdf and it is not the results file or the run's checkpoint: any
    other (a results.vtkhdf that links to results.h5) is refused, ArgumentError naming both, before
    anything is written (soil.files.output_target)."""
    results_path = os.fspath(results_path)
    if os.path.isdir(results_path):
        results_path = os.path.join(results_path, RESULTS_FILE)
    target = os.fspath(vtkhdf_path) if vtkhdf_path else os.path.join(os.path.dirname(results_path), VTKHDF_FILE)
    checkpoint = os.path.join(os.path.dirname(os.path.abspath(results_path)), CHECKPOINT_FILE)
    output_target(target, VTKHDF_SUFFIXES, (results_path, checkpoint), what="the export")
    # a damaged header, series, mesh or wall named (DamagedFileError), not h5py's KeyError or OSError
    check_results(results_path, data=False)
    with open_results(results_path) as f:
        # every dataset read below of its dtype and shape (DamagedFileError) before anything is made
        count = snapshot_count(f)
        if count == 0:
            raise ArgumentError(f"{results_path} holds no particle snapshots: nothing to export")
        with atomic_path(target, ".vtkhdf.tmp", replace=replace) as temporary:
            _write(f, count, temporary)
    return target


def _write(f, count: int, temporary: str) -> None:
    """Write the VTKHDF file of the open results file `f` (checked: snapshot_count) to `temporary`."""
    import h5py

    fixed = f["particles"].attrs.get("layout") != "ragged"
    with h5py.File(temporary, "w", track_order=True) as out:
        root = out.create_group("VTKHDF", track_order=True)
        root.attrs["Version"] = np.array(VTKHDF_VERSION, dtype=np.int64)
        root.attrs.create("Type", np.bytes_("PartitionedDataSetCollection"))
        f32, f64, i64 = np.float32, np.float64, np.int64
        grains = PolyBlock(
            root,
            "grains",
            0,
            "Vertices",
            static_cells=fixed,
            point_data={
                "radius": ((), f64, "m", "grain radius"),
                "velocity": ((3,), f32, "m/s", "grain velocity"),
                "displacement": ((3,), f32, "m", "displacement from where the grain was first seen"),
                "id": ((), i64, "1", "grain id, unique over the run"),
            },
            cell_data={},
            static_data=("radius", "id") if fixed else (),
        )
        wheels = PolyBlock(
            root,
            "wheels",
            1,
            "Polygons",
            static_cells=True,
            point_data={"wheel": ((), i64, "1", "wheel index of each vertex")},
            cell_data={},
            static_data=("wheel",),
        )
        rover = PolyBlock(
            root,
            "rover",
            2,
            "Vertices",
            static_cells=True,
            point_data={
                "forward": ((3,), f64, "1", "rover body x axis, world frame"),
                "up": ((3,), f64, "1", "rover body z axis, world frame"),
            },
            cell_data={},
        )
        blocks = {"grains": grains, "wheels": wheels, "rover": rover}
        walls = None
        if "boundaries" in f:
            walls = PolyBlock(
                root,
                "boundaries",
                3,
                "Polygons",
                static_cells=True,
                point_data={},
                cell_data={
                    "wall": ((), i64, "1", "wall index (results.h5 /boundaries)"),
                    "force": (
                        (3,),
                        f64,
                        "N",
                        "force of the grains on the wall at the snapshot (the end of its macro step)",
                    ),
                },
                static_data=("wall",),
            )
            blocks["boundaries"] = walls
        assembly = root.create_group("Assembly", track_order=True)
        for name in blocks:
            assembly[name] = h5py.SoftLink(f"/VTKHDF/{name}")

        triangles = read_whole(f, "wheels/mesh/triangles")
        vertex_wheel = read_whole(f, "wheels/mesh/wheel")
        if walls is not None:
            wall_faces, wall_index = _walls(f)
            step_times = read_whole(f, "wheels/time")
            force = read_whole(f, "boundaries/force")
            displacement = read_whole(f, "boundaries/displacement")
        displacements = Displacements()
        for k in range(count):
            s = read_snapshot(f, k)
            grains.add_step(
                s.time,
                s.position,
                np.arange(len(s.ids))[:, None],
                {
                    "radius": s.radius,
                    "velocity": s.velocity,
                    "displacement": displacements.of(s),
                    "id": s.ids,
                },
                {},
            )
            wheels.add_step(s.time, s.wheel_vertices, triangles, {"wheel": vertex_wheel}, {})
            rover.add_step(s.time, s.rover_position, [[0]], {"forward": s.rover_forward, "up": s.rover_up}, {})
            if walls is not None:
                # the last macro step at or before the snapshot (none yet: the walls at rest, no force)
                row = int(np.searchsorted(step_times, s.time + 1e-9)) - 1
                if row < 0:
                    moved, on_wall = np.zeros((len(wall_index), 3)), np.zeros((len(wall_index), 3))
                else:
                    moved, on_wall = displacement[row][wall_index], force[row][wall_index]
                points = (wall_faces + moved[:, None, :]).reshape(-1, 3)
                cells = np.arange(len(points)).reshape(-1, 4)
                walls.add_step(s.time, points, cells, {}, {"wall": wall_index, "force": on_wall})


def _walls(f):
    """The walls' quads (Q, 4, 3) [m] and the wall index of each quad; planes are drawn over the extent of
    the grains of the first snapshot, the wheels over the run and the walls' own points."""
    kinds = read_whole(f, "boundaries/kind")
    geometry = read_whole(f, "boundaries/geometry")
    first = read_snapshot(f, 0)
    wheel = read_whole(f, "particles/wheel_vertices").reshape(-1, 3)
    anchors = [first.position - first.radius[:, None], first.position + first.radius[:, None], wheel]
    anchors += [geometry[kinds == 0, :3], geometry[kinds == 1, :3], geometry[kinds == 1, 3:]]
    points = np.concatenate([a.reshape(-1, 3) for a in anchors if a.size])
    lower, upper = points.min(axis=0), points.max(axis=0)
    faces, index = [], []
    for i, (kind, row) in enumerate(zip(kinds, geometry)):
        quads = _wall_faces(int(kind), np.asarray(row, dtype=np.float64), lower, upper)
        faces.append(quads)
        index += [i] * len(quads)
    return np.concatenate(faces), np.array(index, dtype=np.int64)
