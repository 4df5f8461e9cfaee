"""A run's output folder: its files, its lock, and the rules for replacing a run.

    scene.toml        the scene as run (overrides applied)
    scene.edited.toml a scene.toml edited after the run started, kept aside by `cosim resume`
    run.json          status, summary, validity findings, wall time
    bed.h5, bed.json  the settled bed (a cache kept across --overwrite)
    bed_diverged.npz  the last good state of a bed that exploded while settling (until one settles)
    results.h5        time series and particle snapshots (cosim.output)
    results.xdmf      the snapshots for ParaView, VTK and meshio (XDMF 3)
    results.xdmf.h5   its data: each snapshot as plain datasets
    results.vtkhdf    the snapshots as one temporal VTKHDF file (cosim.vtkhdf)
    checkpoint.npz    what `cosim resume` continues from (written atomically)
    diverged_state.npz  the last good soil state when the DEM exploded
    plots/            `cosim plot`
    .lock             held while a process runs or resumes the folder

A folder in use by another process is refused (FolderInUseError): the lock is an OS file
lock, released when its process ends, even by kill -9. A folder holding a run is only
replaced with overwrite=True, and only after the new run has been validated and built
(the caller calls `clear_run` at that point).
"""

from __future__ import annotations

import json
import math
import os
import shutil

from filelock import FileLock, Timeout

from soil.errors import RegolithError
from soil.files import atomic_write_text

RESULTS_FILE = "results.h5"
XDMF_FILE = "results.xdmf"
XDMF_DATA_FILE = "results.xdmf.h5"
VTKHDF_FILE = "results.vtkhdf"
CHECKPOINT_FILE = "checkpoint.npz"
RUN_FILE = "run.json"
SCENE_FILE = "scene.toml"
EDITED_SCENE_FILE = "scene.edited.toml"
DIVERGED_FILE = "diverged_state.npz"
PLOTS_DIR = "plots"
LOCK_FILE = ".lock"
RUN_OUTPUTS = (
    RESULTS_FILE,
    XDMF_FILE,
    XDMF_DATA_FILE,
    VTKHDF_FILE,
    CHECKPOINT_FILE,
    RUN_FILE,
    SCENE_FILE,
    EDITED_SCENE_FILE,
    DIVERGED_FILE,
    PLOTS_DIR,
)
"""What a run writes (the bed cache and foreign files are not among them)."""
RUN_EVIDENCE = tuple(n for n in RUN_OUTPUTS if n not in (SCENE_FILE, PLOTS_DIR))
"""The names that make a folder a run's (a run writes run.json first; scene.toml and plots/ alone are a project
folder's own as well): --overwrite replaces only such a folder."""


class OutputFolderError(RegolithError, OSError):
    """The output folder cannot be used as asked."""


class OutputExistsError(OutputFolderError, FileExistsError):
    """The output folder already holds a run and overwrite was not asked for."""


class FolderInUseError(OutputFolderError):
    """Another process is running or resuming a run in this folder."""


class RunFolder:
    """Paths and lock of one run folder. Use `with RunFolder(path).locked(): ...`."""

    def __init__(self, path: str | os.PathLike):
        self.path = os.path.abspath(os.fspath(path))
        self._lock: FileLock | None = None

    def file(self, name: str) -> str:
        """Absolute path of a file of the folder."""
        return os.path.join(self.path, name)

    @property
    def results(self) -> str:
        return self.file(RESULTS_FILE)

    @property
    def checkpoint(self) -> str:
        return self.file(CHECKPOINT_FILE)

    def create(self) -> None:
        """Make the folder (and its parents); a clear error when the path names a file or lies below one."""
        if os.path.exists(self.path) and not os.path.isdir(self.path):
            raise OutputFolderError(
                f"output folder {self.path!r} exists and is a file, not a folder: choose another --out"
            )
        try:
            os.makedirs(self.path, exist_ok=True)
        except (NotADirectoryError, FileExistsError):
            raise OutputFolderError(
                f"cannot create the output folder {self.path!r}: a part of the path is a file, not a folder"
            ) from None

    def locked(self) -> RunFolder:
        """Take the folder's lock (FolderInUseError when another process holds it); a context manager."""
        self.create()
        lock = FileLock(self.file(LOCK_FILE))
        try:
            lock.acquire(timeout=0)
        except Timeout:
            raise FolderInUseError(
                f"output folder {self.path!r} is in use by another process (a run, a study or a lab test holds "
                f"its {LOCK_FILE}); wait for it to finish, stop it, or choose another --out"
            ) from None
        self._lock = lock
        return self

    def __enter__(self) -> RunFolder:
        if self._lock is None:
            self.locked()
        return self

    def __exit__(self, *exc) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def run_files(self) -> list[str]:
        """The run outputs present (sorted names)."""
        return sorted(n for n in RUN_OUTPUTS if os.path.exists(self.file(n)))

    def holds_run(self) -> bool:
        """Whether the folder holds a run: its record (run.json), results, checkpoint, ... (RUN_EVIDENCE). A
        scene.toml and a plots/ alone are no run's: a project folder's own scene and pictures."""
        return any(os.path.exists(self.file(n)) for n in RUN_EVIDENCE)

    def check_free(self, overwrite: bool) -> None:
        """Refuse a folder holding a run unless overwrite, and a folder holding files of a run's names but no
        run (the user's scene.toml, plots/) even with overwrite (nothing is removed here)."""
        present = self.run_files()
        if present and not self.holds_run():
            raise OutputExistsError(
                f"output folder {self.path!r} holds {', '.join(present)} but no run (no {RUN_FILE}, "
                f"{RESULTS_FILE} or {CHECKPOINT_FILE}): they are not a run's to replace, so nothing was "
                "overwritten or removed, even with --overwrite: choose another --out, or move them yourself"
            )
        if present and not overwrite:
            raise OutputExistsError(
                f"output folder {self.path!r} already holds a run ({', '.join(present)}); "
                "nothing is overwritten: choose another --out, continue with `cosim resume`, or "
                "pass --overwrite to replace the run (a cached bed.h5 is kept and reused)"
            )

    def clear_run(self) -> None:
        """Remove the previous run's outputs (the bed cache and other files stay)."""
        for name in RUN_OUTPUTS:
            path = self.file(name)
            if os.path.isdir(path):
                shutil.rmtree(path)
            elif os.path.exists(path):
                os.remove(path)


def read_json(path: str) -> dict:
    """A run folder's JSON file (run.json) as a dict; {} when it is missing, unreadable or not a table."""
    try:
        with open(path) as f:
            data = json.load(f)
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def write_json(path: str, data: dict) -> None:
    """Write a JSON file atomically (numpy scalars and arrays allowed). A number that is not finite (nan:
    not measured) is written as null: Python's NaN is no JSON, and jq, JavaScript and strict parsers refuse
    the whole file."""
    atomic_write_text(path, json.dumps(finite_or_null(data), indent=2, allow_nan=False) + "\n")


def read_json_numbers(path: str):
    """A JSON file write_json wrote, each null as nan (a number that was not measured): what its numbers'
    readers compute with (None * 1 is an error, nan * 1 is nan)."""
    with open(path) as f:
        return null_as_nan(json.load(f))


def null_as_nan(value):
    """`value` with every None, also in lists and dicts, as nan (the inverse of finite_or_null)."""
    if value is None:
        return math.nan
    if isinstance(value, dict):
        return {key: null_as_nan(item) for key, item in value.items()}
    if isinstance(value, list):
        return [null_as_nan(item) for item in value]
    return value


def finite_or_null(value):
    """`value` with numpy scalars and arrays as Python numbers and lists, and every non-finite number None."""
    import numpy as np

    if isinstance(value, np.ndarray):
        value = value.tolist()
    elif isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: finite_or_null(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_null(item) for item in value]
    return value
