"""What every FMU side shares (the FMU rover and the FMU drive controller): reading the model
description with clear errors, instantiation that cleans up after itself, variable lookup by
name, lazy exit from initialization, doStep with retries in halves, and close.

Nothing here knows about wheels or the coupling: rover_models.fmu_rover and
cosim.fmu_controller build on FmuSession.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
import zipfile
from typing import Any

import numpy as np
from fmpy import extract, read_model_description
from fmpy.fmi1 import FMICallException

from soil.errors import InputError, RegolithError

_DISCARD, _ERROR = 2, 3

log = logging.getLogger(__name__)


class FmuError(InputError, ValueError):
    """An FMU file cannot be used: not an FMU, no or a broken model description, wrong kind."""


class FmuVariableError(InputError, KeyError):
    """A variable the convention needs is missing or has the wrong type/causality."""

    def __str__(self):  # KeyError would print the message with quotes
        return str(self.args[0])


class FmuStepError(RegolithError, RuntimeError):
    """The FMU refused a step and it could not be retried, or a call to it failed (fmi*Error or
    fmi*Fatal: the FMU's own failure, named with its file, not a bug of the project's)."""


@contextlib.contextmanager
def fmu_call(path: str, what: str):
    """Turn fmpy's FMICallException of the calls inside into an FmuStepError naming the FMU's file and
    `what` was asked of it (fmpy's message names the FMI function and the status it returned)."""
    try:
        yield
    except FMICallException as error:
        raise FmuStepError(f"{path}: {what}: {error}") from error


def _guarded(path: str, what: str, function):
    """`function` (an fmpy setter or getter) with its FMI failures named (fmu_call)."""

    def call(*args, **kwargs):
        with fmu_call(path, what):
            return function(*args, **kwargs)

    return call


def read_cosim_description(path: str | os.PathLike):
    """fmpy model description of a co-simulation FMU; FmuError naming the path and the problem
    unless it is a readable FMI 2.0 or 3.0 co-simulation FMU."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FmuError(f"{path}: FMU file not found")
    if not zipfile.is_zipfile(path):
        raise FmuError(f"{path}: not an FMU (an FMU is a zip archive)")
    try:
        with zipfile.ZipFile(path) as archive:
            if "modelDescription.xml" not in archive.namelist():
                raise FmuError(f"{path}: not an FMU: the archive has no modelDescription.xml")
            ET.fromstring(archive.read("modelDescription.xml"))
        md = read_model_description(path)
    except FmuError:
        raise
    except Exception as error:  # noqa: BLE001 - fmpy's own (a schema ValidationError, an FMI version it does not know)
        raise FmuError(f"{path}: modelDescription.xml cannot be read: {type(error).__name__}: {error}") from None
    if md.coSimulation is None:
        raise FmuError(f"{path} is not a co-simulation FMU")
    if md.fmiVersion not in ("2.0", "3.0"):
        raise FmuError(f"{path}: FMI {md.fmiVersion} is not supported (2.0 and 3.0 are)")
    return md


def check_binaries(path: str | os.PathLike, md) -> None:
    """FmuError naming the FMU file when it ships no binary this machine can load (only C sources, or
    binaries for other platforms): before anything is unpacked."""
    import fmpy

    path = os.fspath(path)
    found = fmpy.supported_platforms(path)  # FMI 2.0 platform names for both versions (linux64, win64, ...)
    here = fmpy.platform
    if here not in found:
        others = ", ".join(p for p in found if p != "c-code") or "none"
        sources = " It ships C sources: rebuild it here with `fmpy compile`." if "c-code" in found else ""
        raise FmuError(f"{path}: the FMU has no binary for this platform ({here}; binaries for: {others}).{sources}")


CHILD_TIMEOUT = 120.0
"""Longest wait for a child process to instantiate an FMU [s] (check_instantiates)."""

CRASH_SIGNALS = ("SIGSEGV", "SIGBUS", "SIGILL", "SIGFPE", "SIGABRT", "SIGSYS")
"""The signals by which a process's own code dies (not those sent from outside: SIGKILL, SIGTERM)."""

_INSTANTIATED: set[tuple[str, int, int]] = set()
"""The FMU files (real path, size [bytes], modification time [ns]) a child process of this one has
instantiated without dying."""

_CHILD_DONE = "fmu instantiated, initialized and freed"
"""What the child prints last: its FMU did not crash it (a crash after it, at exit, is not the FMU's use)."""

_PACKAGES = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
"""The folder holding rover_models: the child imports the same copy, whatever the working folder."""


def check_instantiates(path: str | os.PathLike) -> None:
    """FmuError naming the file when instantiating the FMU kills a process: a damaged binary or missing
    resources can crash the FMU's own code (a segmentation fault), which no Python error catches and
    which would end a run without a word. Tried in a child process once per file and process, with the
    FMU's own start values (a run's may differ); an error the child raises is left to the instantiation
    in this process, which names it."""
    path = os.fspath(path)
    info = os.stat(path)
    key = (os.path.realpath(path), info.st_size, info.st_mtime_ns)
    if key in _INSTANTIATED:
        return
    search = os.pathsep.join(filter(None, [_PACKAGES, os.environ.get("PYTHONPATH")]))
    with tempfile.TemporaryDirectory(prefix="fmu_check_") as scratch:  # what a dying child leaves unpacked
        said_file = os.path.join(scratch, "said.txt")
        with open(said_file, "w") as said:  # a file, not a pipe: a helper process the FMU starts may keep it
            try:
                code = subprocess.run(
                    [sys.executable, "-m", "rover_models.fmu_session", path],
                    stdout=said,
                    stderr=subprocess.STDOUT,
                    timeout=CHILD_TIMEOUT,
                    env={**os.environ, "TMPDIR": scratch, "PYTHONPATH": search},
                    start_new_session=True,  # a Ctrl-C for this process group is not the FMU's crash
                ).returncode
            except subprocess.TimeoutExpired:
                raise FmuError(
                    f"{path}: the FMU did not instantiate within {CHILD_TIMEOUT:g} s in a child process "
                    "(its code hangs)"
                ) from None
        with open(said_file, errors="replace") as said:
            text = said.read()
    finished = _CHILD_DONE in text
    if code < 0 and not finished:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        tail = text.strip()[-500:]
        cause = (
            "its binary or its resources are damaged or missing; build or export it again"
            if name in CRASH_SIGNALS
            else "stopped from outside (out of memory?)"
        )
        raise FmuError(
            f"{path}: instantiating the FMU killed the process ({name}): {cause}"
            + (f". It printed: {tail}" if tail else "")
        )
    if code == 0 or finished:
        _INSTANTIATED.add(key)


def instantiate_cosim(path: str | os.PathLike, md, instance_name: str, start_time: float):
    """Unpack and instantiate a co-simulation FMU (model description `md`) and enter
    initialization mode at start_time [s]; a failure removes the unpacked files again. An FMU
    that crashes the process instantiating it is refused first (check_instantiates).

    Returns (slave, unzip directory, set_real, get_real): the fmpy FMU2Slave/FMU3Slave and
    its Real (2.0) / Float64 (3.0) setter and getter.
    """
    check_binaries(path, md)
    check_instantiates(path)
    return _instantiate(path, md, instance_name, start_time)


def _instantiate(path: str | os.PathLike, md, instance_name: str, start_time: float):
    unzipdir = extract(os.fspath(path))
    kwargs = dict(
        guid=md.guid,
        unzipDirectory=unzipdir,
        modelIdentifier=md.coSimulation.modelIdentifier,
        instanceName=instance_name,
    )
    cwd = os.getcwd()  # fmpy enters the library's folder to load it and stays there when loading fails
    try:
        fmu: Any
        if md.fmiVersion == "2.0":
            from fmpy.fmi2 import FMU2Slave

            fmu = FMU2Slave(**kwargs)
            fmu.instantiate()
            fmu.setupExperiment(startTime=start_time)
            fmu.enterInitializationMode()
            kind, set_value, get_value = "Reals", fmu.setReal, fmu.getReal
        else:
            from fmpy.fmi3 import FMU3Slave

            fmu = FMU3Slave(**kwargs)
            fmu.instantiate()
            fmu.enterInitializationMode(startTime=start_time)
            kind, set_value, get_value = "Float64s", fmu.setFloat64, fmu.getFloat64
        where = os.fspath(path)
        return (
            fmu,
            unzipdir,
            _guarded(where, f"setting {kind}", set_value),
            _guarded(where, f"reading {kind}", get_value),
        )
    except Exception as error:
        os.chdir(cwd)  # never stay in the folder that is removed next
        shutil.rmtree(unzipdir, ignore_errors=True)
        raise FmuError(f"{os.fspath(path)}: the FMU could not be instantiated: {error}") from error


class FmuSession:
    """What every FMU side shares: the model description, variable lookup by name with
    clear errors, lazy exit from initialization, doStep with retries in halves, and
    cleanup. FmuRover and cosim.fmu_controller.FmuController build on it; the subclass
    instantiates the FMU (instantiate_cosim) into `fmu`, `_unzipdir`, `_set`, `_get`."""

    def __init__(self, fmu: str | os.PathLike, max_halvings: int, retry_on_error: bool, instance_name: str):
        self.path = os.fspath(fmu)
        self.md = read_cosim_description(self.path)
        self.fmi_version = self.md.fmiVersion
        """'2.0' or '3.0'."""
        self._real_type = "Real" if self.fmi_version == "2.0" else "Float64"
        self.variables = {v.name: v for v in self.md.modelVariables}
        """FMU variables by name (fmpy ScalarVariable)."""
        self.can_vary_step = bool(self.md.coSimulation.canHandleVariableCommunicationStepSize)
        """Whether the FMU accepts communication steps of varying size (needed for retries)."""
        self.max_halvings = int(max_halvings)
        self.retry_on_error = bool(retry_on_error)
        self.instance_name = instance_name
        self.fmu: Any = None
        """The fmpy slave (an FMU2Slave or FMU3Slave); None before instantiation and after close()."""
        self._unzipdir: str | None = None
        self._initializing = False
        self.failed = False
        """Whether the FMU answered Error or Fatal (FmuStepError): close() then frees it without terminating."""

    def _listing(self) -> str:
        return "; ".join(f"{v.name} ({v.causality}, {v.type})" for v in self.md.modelVariables)

    def _vr(self, name: str, causalities: tuple[str, ...] | None) -> int:
        v = self.variables.get(name)
        if v is None:
            raise FmuVariableError(f"{self.path}: no variable {name!r}; the FMU has: {self._listing()}")
        if v.type != self._real_type:
            raise FmuVariableError(
                f"{self.path}: variable {name!r} is {v.type}, expected {self._real_type}; "
                f"the FMU has: {self._listing()}"
            )
        if causalities is not None and v.causality not in causalities:
            raise FmuVariableError(
                f"{self.path}: variable {name!r} has causality {v.causality}, expected "
                f"{' or '.join(causalities)}; the FMU has: {self._listing()}"
            )
        return v.valueReference

    def _watched(self, instantiated):
        """instantiate_cosim's (fmu, unzip directory, set, get), the setter and getter marking the session
        `failed` when the FMU answers them Error or Fatal (FmuStepError)."""
        fmu, unzipdir, set_value, get_value = instantiated
        return fmu, unzipdir, self._marking(set_value), self._marking(get_value)

    def _marking(self, function):
        def call(*args, **kwargs):
            with self._call(None):
                return function(*args, **kwargs)

        return call

    @contextlib.contextmanager
    def _call(self, what: str | None):
        """fmu_call(path, what) (what None: the call names itself already), the session marked `failed` on an
        Error or a Fatal answer (close() then only frees the FMU)."""
        try:
            if what is None:
                yield
            else:
                with fmu_call(self.path, what):
                    yield
        except FmuStepError as error:
            cause = error.__cause__
            # Error or Fatal (a Discard of a get or set is no failure: FMI allows terminate after it)
            self.failed = self.failed or getattr(cause, "status", _ERROR) >= _ERROR
            raise

    def _ready(self) -> None:
        """Leave initialization mode on first use (parameters can be set until then)."""
        if self._initializing:
            with self._call("leaving initialization mode"):
                self.fmu.exitInitializationMode()
            self._initializing = False

    def _step(self, t: float, h: float, depth: int) -> None:
        try:
            result = self.fmu.doStep(currentCommunicationPoint=t, communicationStepSize=h)
        except FMICallException as err:
            retryable = err.status == _DISCARD or (self.retry_on_error and err.status == _ERROR)
            if not retryable:  # Error (not retried) or Fatal: the FMU failed; a smaller step would not help
                self.failed = True
                raise FmuStepError(f"{self.path}: at t={t:g} s (H={h:g} s): {err}") from err
            if not self.can_vary_step:
                raise FmuStepError(
                    f"{self.path}: doStep(t={t:g} s, H={h:g} s) refused (status {err.status}) and the FMU "
                    f"cannot handle variable communication step sizes, so it cannot be retried with smaller steps"
                ) from err
            if depth >= self.max_halvings:
                raise FmuStepError(
                    f"{self.path}: doStep(t={t:g} s) still refused after {depth} halvings (H={h:g} s)"
                ) from err
            self._step(t, h / 2, depth + 1)
            self._step(t + h / 2, h / 2, depth + 1)
            return
        if self.fmi_version == "3.0":
            _, terminate, early, last = result
            if terminate:
                raise FmuStepError(f"{self.path}: the FMU asked to terminate at t={last:g} s")
            if early and last < t + h:  # FMI 3.0 early return: go on from where it stopped
                self._step(last, t + h - last, depth)

    @property
    def can_save_state(self) -> bool:
        """Whether the FMU can hand out its state as bytes (canGetAndSetFMUstate and canSerializeFMUstate)."""
        cs = self.md.coSimulation
        return bool(cs.canGetAndSetFMUstate and cs.canSerializeFMUstate)

    def save_state(self) -> np.ndarray:
        """The FMU's serialized state (fmi*SerializeFMUstate) as bytes, shape (n,), uint8; FmuError when the
        FMU cannot save its state."""
        if not self.can_save_state:
            raise FmuError(
                f"{self.path}: the FMU cannot save its state (it does not declare canGetAndSetFMUstate "
                "and canSerializeFMUstate), so a run with it cannot be continued from a checkpoint"
            )
        self._ready()
        with self._call("saving its state"):
            state = self.fmu.getFMUState()
            try:
                return np.frombuffer(self.fmu.serializeFMUState(state), dtype=np.uint8).copy()
            finally:
                self.fmu.freeFMUState(state)

    def load_state(self, data: np.ndarray) -> None:
        """Put a state from `save_state` back into the (instantiated) FMU."""
        if not self.can_save_state:
            raise FmuError(
                f"{self.path}: the FMU cannot restore a saved state (it does not declare "
                "canGetAndSetFMUstate and canSerializeFMUstate): this run cannot be resumed"
            )
        self._ready()
        with self._call("restoring a saved state"):
            state = self.fmu.deserializeFMUState(np.asarray(data, dtype=np.uint8).tobytes())
            try:
                self.fmu.setFMUState(state)
            finally:
                self.fmu.freeFMUState(state)

    def close(self) -> None:
        """Terminate and free the FMU instance, remove the unpacked files. An FMU that failed (answered Error
        or Fatal) is only freed: FMI allows no terminate after Error, no call but free after Fatal, and
        what it answered would hide why it stopped."""
        if self.fmu is not None:
            try:
                if not self.failed:
                    with fmu_call(self.path, "terminating"):
                        self._ready()
                        self.fmu.terminate()
            except FmuStepError as error:  # said, not raised: the run's own end, or its error, is what matters
                log.warning("%s", error)
            finally:
                self.fmu.freeInstance()
                self.fmu = None
                if self._unzipdir is not None:
                    shutil.rmtree(self._unzipdir, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _instantiate_and_free(path: str) -> None:
    """check_instantiates' child: instantiate the FMU, enter and leave initialization, free it."""
    md = read_cosim_description(path)
    fmu, unzipdir, _, _ = _instantiate(path, md, "check", 0.0)
    try:
        fmu.exitInitializationMode()
        fmu.terminate()
    finally:
        fmu.freeInstance()
        shutil.rmtree(unzipdir, ignore_errors=True)
    print(_CHILD_DONE, flush=True)


if __name__ == "__main__":
    _instantiate_and_free(sys.argv[1])
