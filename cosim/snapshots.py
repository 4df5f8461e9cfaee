"""The particle snapshots of a results.h5, one at a time, the same way for both layouts (fixed and ragged).

The exports (results.xdmf, results.vtkhdf) and `cosim view` read the snapshots through `read_snapshot`,
so the two layouts of /particles (cosim.output) are unpacked in one place.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

ARRAY_NAMES = {
    "radius": "radius [m]",
    "velocity": "velocity [m s-1]",
    "position": "position [m]",
    "displacement": "displacement [m]",
    "id": "id [1]",
    "forward": "forward [1]",
    "up": "up [1]",
    "wheel": "wheel [1]",
    "wall": "wall [1]",
    "force": "force [N]",
}
"""The names results.xdmf and results.vtkhdf give their arrays: viewers show names, not HDF5 attributes,
so each name carries its unit (written without '/', which VTKHDF array names cannot hold)."""


TORN_READ_TRIES = 5
"""How often a read of a results file still being written is tried before the file is called damaged."""
TORN_READ_PAUSE = 0.1
"""The pause between those tries [s]."""
_pause = time.sleep  # how read_results_data waits (a test takes its place)


def read_results_data(f, read, what: str):
    """read() of the open results file `f`; DamagedFileError naming the file and `what` when h5py cannot
    read it (a chunk's bytes changed: its Fletcher-32 checksum fails). A file still being written (status
    'running') is read while its writer rewrites a chunk in place, and a read that meets the chunk half
    written fails its checksum as well (a few reads in a thousand of a file flushed without pause): such
    a read is tried again, TORN_READ_TRIES times in all, TORN_READ_PAUSE apart."""
    from soil.errors import DamagedFileError

    for attempt in range(TORN_READ_TRIES):
        try:
            return read()
        except (KeyError, OSError, RuntimeError) as error:  # how h5py reports damaged bytes
            if isinstance(error, KeyError) or attempt + 1 == TORN_READ_TRIES or not _being_written(f):
                raise DamagedFileError(f"{f.filename}: the results file is damaged ({what}: {error})") from None
            _pause(TORN_READ_PAUSE)
    raise AssertionError("unreachable")


def read_whole(f, name: str):
    """Dataset `name` of an open results file, whole, through read_results_data."""
    return read_results_data(f, lambda: f[name][()], name)


def _being_written(f) -> bool:
    try:
        status = f.attrs.get("status")
    except (KeyError, OSError, RuntimeError):
        return False
    return (status.decode() if isinstance(status, bytes) else status) == "running"


@dataclass(frozen=True)
class Snapshot:
    """One particle snapshot (n grains, V wheel-mesh vertices), world frame, SI units."""

    index: int
    """Its index among the file's snapshots [-]."""
    time: float
    """[s]"""
    position: np.ndarray
    """Grain centres [m], shape (n, 3)."""
    velocity: np.ndarray
    """Grain velocities [m/s], shape (n, 3)."""
    radius: np.ndarray
    """Grain radii [m], shape (n,)."""
    ids: np.ndarray
    """Grain ids, unique over the run (fixed layout: the model index) [-], shape (n,)."""
    wheel_vertices: np.ndarray
    """The wheel meshes posed [m], shape (V, 3)."""
    rover_position: np.ndarray
    """The rover body's frame origin (testbed: the hub) [m], shape (3,)."""
    rover_forward: np.ndarray
    """Its x axis, a unit vector [-], shape (3,)."""
    rover_up: np.ndarray
    """Its z axis, a unit vector [-], shape (3,)."""


def snapshot_datasets(ragged: bool) -> tuple[list[str], list[str]]:
    """The particles group's datasets ResultsWriter.create makes: (those with a row per snapshot, those
    of the whole run), for the fixed layout or the ragged one (a moving patch)."""
    per_snapshot = ["time", "wheel_vertices", "rover_position", "rover_forward", "rover_up"]
    per_snapshot += ["first", "count"] if ragged else ["position", "velocity"]
    return per_snapshot, (["id", "radius", "position", "velocity"] if ragged else ["radius"])


def snapshot_count(f) -> int:
    """Snapshots in an open results file, after checking that every snapshot dataset is there with a
    row per snapshot and that every dataset a reader uses holds numbers of its shape (reader_problem):
    DamagedFileError naming the file otherwise (a reader then stops before it writes).
    A file still 'running' (being written, or its writer killed) counts the snapshots every dataset holds."""
    from soil.errors import DamagedFileError

    if "particles" not in f:
        raise DamagedFileError(f"{f.filename}: the results file is damaged (missing particles)")
    p = f["particles"]
    ragged = p.attrs.get("layout") == "ragged"
    per_snapshot, fixed = snapshot_datasets(ragged)
    missing = [f"particles/{name}" for name in per_snapshot + fixed if name not in p]
    problem = f"missing {', '.join(missing)}" if missing else ""
    count = 0
    if not problem:
        count = int(p["time"].shape[0])
        if f.attrs.get("status") == "running":  # being written, or its writer killed inside a flush
            count = min(int(p[name].shape[0]) for name in per_snapshot)
        uneven = [name for name in per_snapshot if p[name].shape[0] != count]
        if uneven and f.attrs.get("status") != "running":
            problem = f"particles/{uneven[0]} has {p[uneven[0]].shape[0]} rows for {count} snapshots"
        elif not ragged and p["position"].shape[1:] != (len(p["radius"]), 3):
            problem = f"particles/position has shape {p['position'].shape}, not (snapshots, {len(p['radius'])}, 3)"
        else:
            problem = reader_problem(f, count)
    if problem:
        raise DamagedFileError(f"{f.filename}: the results file is damaged ({problem})")
    return count


REAL, INTEGER = "fiu", "iu"
"""numpy dtype kinds of a dataset of real numbers and of one of integers (no text, no complex numbers)."""


def reader_datasets(f) -> dict[str, tuple[str, tuple]]:
    """The datasets of a results file that the readers (the exports, `cosim view`) use, each with its dtype
    kinds and its shape: a number is a size, a letter a size that must be the same in every dataset it
    appears in (V wheel-mesh vertices, N grains, F triangles, W wheels, B walls), None a row count checked
    elsewhere (snapshot_count, check_results: a file being written may hold more rows of some)."""
    ragged = f["particles"].attrs.get("layout") == "ragged"
    grains = (None,) if ragged else ("N",)
    per_grain = (None,) if ragged else (None, "N")
    shapes = {
        "particles/time": (REAL, (None,)),
        "particles/wheel_vertices": (REAL, (None, "V", 3)),
        "particles/rover_position": (REAL, (None, 3)),
        "particles/rover_forward": (REAL, (None, 3)),
        "particles/rover_up": (REAL, (None, 3)),
        "particles/radius": (REAL, grains),
        "particles/position": (REAL, (*per_grain, 3)),
        "particles/velocity": (REAL, (*per_grain, 3)),
        "wheels/mesh/vertices": (REAL, ("V", 3)),
        "wheels/mesh/triangles": (INTEGER, ("F", 3)),
        "wheels/mesh/wheel": (INTEGER, ("V",)),
        "wheels/time": (REAL, (None,)),
        "wheels/phase": (INTEGER, (None,)),
        "wheels/slip": (REAL, (None, "W")),
        "wheels/sinkage": (REAL, (None, "W")),
        "rover/slip": (REAL, (None,)),
    }
    if ragged:
        shapes.update({"particles/first": (INTEGER, (None,)), "particles/count": (INTEGER, (None,))})
        shapes["particles/id"] = (INTEGER, (None,))
    if "boundaries" in f:
        shapes.update(
            {
                "boundaries/kind": (INTEGER, ("B",)),
                "boundaries/geometry": (REAL, ("B", 6)),
                "boundaries/force": (REAL, (None, "B", 3)),
                "boundaries/displacement": (REAL, (None, "B", 3)),
            }
        )
    return shapes


def reader_problem(f, count: int) -> str:
    """What is wrong with the datasets the readers use (reader_datasets: missing, of another dtype or shape;
    a value no run writes in the small ones read whole: a time that is not finite, a triangle's vertex past
    the mesh, a wall of no known kind, not finite or moved by a displacement that is not, a snapshot's rows
    past the grains), or "". The
    snapshots' grains are checked as they are read (read_snapshot): a file may hold more than memory."""
    import h5py

    sizes: dict[str, int] = {}
    for name, (kinds, shape) in reader_datasets(f).items():
        if name not in f or not isinstance(f[name], h5py.Dataset):
            return f"missing {name}"
        dataset = f[name]
        if dataset.dtype.kind not in kinds:
            what = "integers" if kinds == INTEGER else "numbers"
            return f"{name} holds {dataset.dtype} values, not {what}"
        if len(dataset.shape) != len(shape):
            return f"{name} has shape {dataset.shape}, not ({_sizes(shape, sizes)})"
        for size, actual in zip(shape, dataset.shape):
            if isinstance(size, str):
                size = sizes.setdefault(size, int(actual))
            if size is not None and size != actual:
                return f"{name} has shape {dataset.shape}, not ({_sizes(shape, sizes)})"
    for name in ("particles/time", "wheels/time", "boundaries/geometry", "boundaries/displacement"):
        values = read_whole(f, name) if name in f else np.zeros(0)
        if not np.all(np.isfinite(values)):
            return _not_finite(name, values)
    triangles = read_whole(f, "wheels/mesh/triangles")
    if triangles.size and (triangles.min() < 0 or triangles.max() >= sizes["V"]):
        return f"wheels/mesh/triangles points past the {sizes['V']} vertices of wheels/mesh/vertices"
    if "boundaries" in f:
        kinds, geometry = read_whole(f, "boundaries/kind"), read_whole(f, "boundaries/geometry")
        unknown = ~np.isin(kinds, (0, 1))
        if unknown.any():
            return f"boundaries/kind {kinds[unknown][0]} is neither 0 (a plane) nor 1 (a box)"
        planes = np.flatnonzero((kinds == 0) & (np.linalg.norm(geometry[:, 3:], axis=1) == 0))
        if len(planes):
            return f"boundaries/geometry row {planes[0]}: a plane with a zero normal"
    if f["particles"].attrs.get("layout") == "ragged":
        p = f["particles"]
        first = read_results_data(f, lambda: p["first"][:count], "particles/first")
        rows = read_results_data(f, lambda: p["count"][:count], "particles/count")
        held = min(int(p[name].shape[0]) for name in ("id", "radius", "position", "velocity"))
        bad = np.flatnonzero((first < 0) | (rows < 0) | (first + rows > held))
        if len(bad):
            k = int(bad[0])
            return f"particles/first, count of snapshot {k} ({first[k]}, {rows[k]}) point past the {held} grain rows"
    return ""


def _sizes(shape: tuple, sizes: dict) -> str:
    return ", ".join("rows" if size is None else str(sizes.get(size, size)) for size in shape)


def _not_finite(name: str, values, where: str = "") -> str:
    values = np.asarray(values)
    bad = values[~np.isfinite(values)].ravel()
    values_ = "1 value that is" if len(bad) == 1 else f"{len(bad)} values that are"
    return f"{name}{where} holds {values_} not finite ({bad[0]}): a run that diverges stops before it writes one"


def read_snapshot(f, k: int, check: bool = True) -> Snapshot:
    """Snapshot k of an open results file (h5py.File, cosim.output.open_results); DamagedFileError naming
    the file and the snapshot when h5py cannot read it (a damaged chunk) or (check) a grain or the wheels
    are where no run puts them: a position, velocity or radius that is not finite, a radius not above 0
    (a run that diverges stops before it writes a snapshot). Check snapshot_count first: it checks the
    datasets' dtypes and shapes."""
    from soil.errors import DamagedFileError

    snapshot = read_results_data(f, lambda: _read_snapshot(f, k), f"particles of snapshot {k}")
    problem = _snapshot_problem(snapshot) if check else ""
    if problem:
        raise DamagedFileError(f"{f.filename}: the results file is damaged ({problem})")
    return snapshot


def _snapshot_problem(s: Snapshot) -> str:
    where = f" of snapshot {s.index}"
    for name, values in (
        ("particles/position", s.position),
        ("particles/velocity", s.velocity),
        ("particles/radius", s.radius),
        ("particles/wheel_vertices", s.wheel_vertices),
    ):
        if not np.all(np.isfinite(values)):
            return _not_finite(name, values, where)
    if len(s.radius) and s.radius.min() <= 0:
        return f"particles/radius{where} holds a radius of {s.radius.min()} m: a grain's is above 0"
    if not np.isfinite(s.time):
        return _not_finite("particles/time", [s.time], where)
    return ""


def _read_snapshot(f, k: int) -> Snapshot:
    p = f["particles"]
    if p.attrs.get("layout") == "ragged":
        rows = slice(int(p["first"][k]), int(p["first"][k] + p["count"][k]))
        position, velocity = p["position"][rows], p["velocity"][rows]
        radius, ids = p["radius"][rows], p["id"][rows]
    else:
        position, velocity = p["position"][k], p["velocity"][k]
        radius = p["radius"][()]
        ids = np.arange(len(radius), dtype=np.int64)
    return Snapshot(
        index=k,
        time=float(p["time"][k]),
        position=position,
        velocity=velocity,
        radius=radius,
        ids=ids,
        wheel_vertices=p["wheel_vertices"][k],
        rover_position=p["rover_position"][k],
        rover_forward=p["rover_forward"][k],
        rover_up=p["rover_up"][k],
    )


class Displacements:
    """Each grain's displacement [m] from where it was first seen in the snapshots (a grain a moving
    patch places later starts from where it was placed). Feed the snapshots in order."""

    def __init__(self) -> None:
        self._ids = np.zeros(0, dtype=np.int64)  # sorted
        self._first = np.zeros((0, 3), dtype=np.float64)

    def of(self, snapshot: Snapshot) -> np.ndarray:
        """(n, 3) displacement of the snapshot's grains [m]."""
        ids = np.asarray(snapshot.ids, dtype=np.int64)
        new = ~np.isin(ids, self._ids)
        if new.any():
            ids_all = np.concatenate([self._ids, ids[new]])
            first_all = np.concatenate([self._first, snapshot.position[new]])
            order = np.argsort(ids_all, kind="stable")
            self._ids, self._first = ids_all[order], first_all[order]
        return snapshot.position - self._first[np.searchsorted(self._ids, ids)]
