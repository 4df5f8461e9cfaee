"""The particle snapshots of a results.h5, one at a time, the same way for both layouts (fixed and ragged).

The exports (results.xdmf, results.vtkhdf) and `cosim view` read the snapshots through `read_snapshot`,
so the two layouts of /particles (cosim.output) are unpacked in one place.
"""

from __future__ import annotations

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
    row per snapshot: DamagedFileError naming the file otherwise (a reader then stops before it writes).
    A file still 'running' (being written, or its writer killed) counts the snapshots every dataset holds."""
    from soil.errors import DamagedFileError

    if "particles" not in f:
        raise DamagedFileError(f"{f.filename}: the results file is damaged (missing particles)")
    p = f["particles"]
    ragged = p.attrs.get("layout") == "ragged"
    per_snapshot, fixed = snapshot_datasets(ragged)
    missing = [f"particles/{name}" for name in per_snapshot + fixed if name not in p]
    problem = f"missing {', '.join(missing)}" if missing else ""
    if not problem:
        count = int(p["time"].shape[0])
        if f.attrs.get("status") == "running":  # being written, or its writer killed inside a flush
            count = min(int(p[name].shape[0]) for name in per_snapshot)
        uneven = [name for name in per_snapshot if p[name].shape[0] != count]
        if uneven and f.attrs.get("status") != "running":
            problem = f"particles/{uneven[0]} has {p[uneven[0]].shape[0]} rows for {count} snapshots"
        elif not ragged and p["position"].shape[1:] != (len(p["radius"]), 3):
            problem = f"particles/position has shape {p['position'].shape}, not (snapshots, {len(p['radius'])}, 3)"
    if problem:
        raise DamagedFileError(f"{f.filename}: the results file is damaged ({problem})")
    return count


def read_snapshot(f, k: int) -> Snapshot:
    """Snapshot k of an open results file (h5py.File, cosim.output.open_results); DamagedFileError naming
    the file and the snapshot when h5py cannot read it (a damaged chunk)."""
    from soil.errors import DamagedFileError

    try:
        return _read_snapshot(f, k)
    except (KeyError, OSError, RuntimeError) as error:  # how h5py reports damaged bytes
        raise DamagedFileError(f"{f.filename}: the results file is damaged (snapshot {k}: {error})") from None


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
