"""The soil server: the soil of an exported soil FMU (the DEM's grains, or SCM), in a process of its own.

    python -E -m cosim.soil_fmu.server --fd 3

The FMU's compiled front end (soil_fmu.c) starts it like this (without the working directory
on sys.path) when initialization ends, with its end
of a socket pair as descriptor 3, stdout on /dev/null and stderr on a pipe it reads
(lines starting "warning: " become FMI warnings). Messages are frames of a little-endian
header (uint32 kind, uint32 payload length) and a payload; the front end asks, the server
answers each request with one message:

    INIT  (1) text "key value" lines: protocol, instance, resources, wheels, dem_step,
              gravity (3 numbers), device        -> OK (10) text, or ERROR
    PLACE (2) float64[W, 13] wheel inputs          -> OUTPUTS (11) float64[W, 15], or ERROR
    STEP  (3) float64 step [s], float64[W, 13]     -> OUTPUTS, DISCARD (12) text, or ERROR
    BYE   (4)                                      -> OK, then the server exits
    SAVE  (5) uint32 id: keep the soil as it is now under id (an FMU state; an id again: replace it) -> OK
    RESTORE (6) uint32 id: put the soil back to the state kept under id                    -> OK, or ERROR
    FREE  (7) uint32 id: forget that state                                                 -> OK
    ERROR (13) text: what went wrong.

Wheel inputs: position (3) [m], orientation quaternion w x y z (4), velocity (3) [m/s],
angular velocity (3) [rad/s]. Outputs: force, torque (mean over the step), force_end,
torque_end (3 each) [N, N m], sinkage [m], work on the soil [J], contact count.
A STEP advances the soil by `step` from the kinematics (constant velocity over the step,
DemSoil.advance or ScmSoil.advance). A step the soil cannot take (soil.SimulationDiverged: the
DEM's divergence checks, or a non-finite wrench) puts the soil back to the step's start and
answers DISCARD, so the importer can retry a shorter step; a step that fails otherwise (an SCM
wheel leaving its node window) puts it back too and answers ERROR.
The server exits when the socket closes or its parent (the importer) dies. docs/fmu.md
describes the whole FMU.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import socket
import struct
import sys
import threading
import time
import traceback
import warnings

import numpy as np

from soil.errors import ArgumentError, DamagedFileError, InternalError

PROTOCOL_VERSION = 2
INIT, PLACE, STEP, BYE, SAVE, RESTORE, FREE = 1, 2, 3, 4, 5, 6, 7
OK, OUTPUTS, DISCARD, ERROR = 10, 11, 12, 13
HEADER = struct.Struct("<II")
INPUTS_PER_WHEEL = 13
OUTPUTS_PER_WHEEL = 15
CONFIG_FILE = "soil.json"
BED_FILE = "bed.h5"
DEVICE_VARIABLE = "REGOLITH_SOIL_DEVICE"


class Channel:
    """Framed messages over a stream socket."""

    def __init__(self, sock: socket.socket):
        self.sock = sock

    def send(self, kind: int, payload: bytes = b"") -> None:
        self.sock.sendall(HEADER.pack(kind, len(payload)) + payload)

    def receive(self) -> tuple[int, bytes] | None:
        """The next message, or None when the other end closed the socket."""
        header = self._exactly(HEADER.size)
        if header is None:
            return None
        kind, length = HEADER.unpack(header)
        payload = self._exactly(length)
        return None if payload is None else (kind, payload)

    def _exactly(self, size: int) -> bytes | None:
        chunks, left = [], size
        while left:
            chunk = self.sock.recv(min(left, 1 << 20))
            if not chunk:
                return None
            chunks.append(chunk)
            left -= len(chunk)
        return b"".join(chunks)


class StepRefused(RuntimeError):
    """The soil could not take the step; it is back at the step's start."""


class StepStart:
    """The DEM soil at the start of a macro step, to go back to when the step is refused: a snapshot
    of the whole simulation (soil.Simulation.snapshot), kept on its device (no host read)."""

    def __init__(self, soil):
        self.soil = soil
        self.snapshot = None

    def take(self) -> None:
        self.snapshot = self.soil.sim.snapshot(into=self.snapshot)

    def restore(self) -> None:
        assert self.snapshot is not None, "restore() follows take()"
        self.soil.sim.restore(self.snapshot)


class StateStart:
    """The SCM soil at the start of a macro step: its checkpoint (ScmSoil.state_dict), host copies
    of the node window's few thousand nodes (cheap next to a step)."""

    def __init__(self, soil):
        self.soil = soil
        self.state: dict | None = None

    def take(self) -> None:
        self.state = self.soil.state_dict()

    def restore(self) -> None:
        assert self.state is not None, "restore() follows take()"
        self.soil.load_state_dict(self.state)


STEP_STARTS: dict[str, type[StepStart] | type[StateStart]] = {"dem": StepStart, "scm": StateStart}
"""How each terrain keeps its state at a step's start (and an FMU state)."""


class SoilSession:
    """The soil of one FMU instance."""

    def __init__(self, settings: dict):
        from soil import quiet_warp

        from .config import soil_from_config

        protocol = int(settings.get("protocol", 0))
        if protocol != PROTOCOL_VERSION:
            raise ArgumentError(
                f"the FMU front end speaks protocol {protocol}, this server {PROTOCOL_VERSION}: "
                "export the FMU again with the regolith-cosim this Python has"
            )
        resources = settings["resources"]
        path = os.path.join(resources, CONFIG_FILE)
        try:
            with open(path) as f:
                config = json.load(f)
        except (json.JSONDecodeError, UnicodeDecodeError) as error:  # an edited or cut resource file
            raise DamagedFileError(f"{path} is not the JSON the export wrote ({error}): export the FMU again") from None
        if not isinstance(config, dict):
            raise DamagedFileError(f"{path} holds no table of settings: export the FMU again")
        self.wheel_count = int(settings["wheels"])
        if self.wheel_count != int(config["wheel_count"]):
            raise ArgumentError(f"the front end has {self.wheel_count} wheels, {CONFIG_FILE} {config['wheel_count']}")
        dem_step = float(settings["dem_step"])
        if not dem_step > 0:
            raise ArgumentError(f"dem_step must be > 0 [s], got {dem_step!r}")
        device = self.device(settings.get("device"), config["device"])
        gravity = [float(g) for g in settings["gravity"].split()]
        self.terrain = config.get("terrain", "dem")
        if self.terrain == "scm" and not np.allclose(gravity, config["gravity"], rtol=1e-12, atol=0):
            # SCM's pressure-sinkage law holds the gravity it was given (or calibrated) for
            raise ArgumentError(
                f"gravity: the SCM soil's parameters hold at the scene's gravity {config['gravity']} m/s^2, "
                f"the FMU's gravity parameter asks for {gravity}: export the FMU from a scene at that gravity"
            )
        validity_warnings(config)  # before the slow part: a master shows it even if the start fails
        quiet_warp()
        self.soil = soil_from_config(config, os.path.join(resources, BED_FILE), dem_step, device)
        self.soil.set_gravity(gravity)
        self.step_start = STEP_STARTS[self.terrain]
        self.start = self.step_start(self.soil)
        self.states: dict[int, StepStart | StateStart] = {}
        """FMU states (fmi2GetFMUstate, fmi3GetFMUState) by the front end's id: copies of the soil."""
        if self.terrain == "scm":
            terrain = self.soil.terrain
            nx, ny = terrain.shape
            self.description = (
                f"SCM terrain of {nx} x {ny} nodes, {self.wheel_count} wheel(s) on {terrain.device}, "
                f"precision {terrain.precision.name}, SCM step {dem_step:.6g} s"
            )
        else:
            sim = self.soil.sim
            self.description = (
                f"{sim.particle_count} grains, {self.wheel_count} wheel(s) on {sim.device}, "
                f"precision {sim.precision_name}, DEM step {dem_step:.6g} s"
            )

    @staticmethod
    def device(parameter: str | None, configured: str) -> str:
        """The Warp device to step on: the FMU's `device` parameter, else $REGOLITH_SOIL_DEVICE, else the
        scene's device the export kept (`configured`; 'default' is resolved here, on the machine that runs
        the soil); ArgumentError naming where a bad name came from and what is allowed."""
        from cosim.probe import resolve_device
        from cosim.scene import SceneError

        for name, field in (
            (parameter, "the FMU's device parameter"),
            (os.environ.get(DEVICE_VARIABLE), f"${DEVICE_VARIABLE}"),
            (configured, "the exported scene's device (resources/soil.json)"),
        ):
            if name:
                try:
                    return resolve_device(name, field)
                except SceneError as error:
                    raise ArgumentError("; ".join(error.problems)) from None
        return resolve_device("default", "the default device")

    def kinematics(self, values: np.ndarray):
        from cosim.contract import WheelKinematics

        rows = values.reshape(self.wheel_count, INPUTS_PER_WHEEL)
        return [WheelKinematics(r[0:3], r[3:7], r[7:10], r[10:13]) for r in rows]

    def place(self, values: np.ndarray) -> bytes:
        self.soil.place_wheels(self.kinematics(values))
        self.soil.start_health_checks()  # the DEM's divergence monitor; nothing on SCM
        return outputs(self.soil.current_wrenches())

    def step(self, step: float, values: np.ndarray) -> bytes:
        from soil import SimulationDiverged

        if not step > 0:
            raise ArgumentError(f"the step must be > 0 [s], got {step!r}")
        kinematics = self.kinematics(values)
        soil = self.soil
        self.start.take()
        try:
            wrenches = soil.advance(soil.time + step, kinematics)
            soil.check_health()  # the DEM's speed, overlap, energy and NaN bounds (soil.stability)
            data = outputs(wrenches)
            if not np.all(np.isfinite(np.frombuffer(data, "<f8"))):
                raise SimulationDiverged("a wheel wrench is not finite")
        except SimulationDiverged as error:
            self.start.restore()
            raise StepRefused(
                f"the soil refused the step from t = {soil.time:.9g} s by {step:.6g} s and is back at "
                f"its start; retry a shorter step or gentler wheel motion{self.nearest_wheel(error, kinematics)}: "
                f"{error}"
            ) from error
        except BaseException:
            self.start.restore()
            raise
        return data

    def nearest_wheel(self, error, kinematics) -> str:
        """With several wheels, the refusal's words on the wheel whose motion the master should change, the
        one whose hub is nearest the grain that diverged ("of wheel_i (its hub D m from ...)"); "" with one
        wheel or no position."""
        if self.wheel_count < 2 or getattr(error, "position", None) is None:
            return ""
        position = np.asarray(error.position, dtype=float)
        distances = [float(np.linalg.norm(position - np.asarray(k.position, dtype=float))) for k in kinematics]
        if not all(map(math.isfinite, distances)):  # a grain gone non-finite is near no wheel
            return ""
        wheel = int(np.argmin(distances))
        return f" of wheel_{wheel} (its hub {distances[wheel]:.3g} m from the grain that diverged)"

    def save(self, ident: int) -> bytes:
        kept = self.states.get(ident) or self.step_start(self.soil)
        kept.take()
        self.states[ident] = kept
        return f"FMU state {ident} kept at t = {self.soil.time:.9g} s".encode()

    def restore(self, ident: int) -> bytes:
        if ident not in self.states:
            raise ArgumentError(f"no FMU state {ident} (freed, or taken by another soil)")
        self.states[ident].restore()
        return f"FMU state {ident} restored: t = {self.soil.time:.9g} s".encode()

    def free(self, ident: int) -> bytes:
        self.states.pop(ident, None)
        return f"FMU state {ident} freed".encode()


WARNING_LINE = 500
"""Longest stderr warning line [characters]: the front end reads lines of up to 511 bytes and logs
the rest of a longer one as another line, not as a warning."""


def validity_warnings(config: dict) -> None:
    """Warn (stderr "warning: " lines: FMI warnings in the master, category logServer) of the scene's
    validity out of range, as soil.json holds it: its verdict, then each failed check's message."""
    from .build import failed_findings

    failed = failed_findings(config)
    if not failed and not config.get("unjudged"):
        return
    lines = [f"validity: {config.get('validity')} (see resources/{CONFIG_FILE}: findings)"]
    lines += [f"validity: {f.get('check')}: {f.get('message')}" for f in failed]
    for line in lines:
        text = " ".join(str(line).split()).encode("utf-8")
        if len(text) > WARNING_LINE:
            text = text[: WARNING_LINE - 3] + b"..."
        print(f"warning: {text.decode('utf-8', 'ignore')}", file=sys.stderr, flush=True)


def outputs(wrenches) -> bytes:
    rows = [
        np.r_[w.force, w.torque, w.force_end, w.torque_end, w.sinkage, w.work_on_soil, w.contact_count]
        for w in wrenches
    ]
    return np.asarray(rows, dtype="<f8").tobytes()


def parse_settings(text: str) -> dict:
    settings = {}
    for line in text.splitlines():
        key, _, value = line.partition(" ")
        if key:
            settings[key] = value
    return settings


def serve(channel: Channel) -> None:
    """Answer the front end's requests until BYE or the socket closes."""
    try:
        _answer(channel)
    except (BrokenPipeError, ConnectionResetError):
        pass  # the front end is gone (its instance was freed or its process died)


def _answer(channel: Channel) -> None:
    session = None
    while True:
        message = channel.receive()
        if message is None:
            return
        kind, payload = message
        try:
            if kind == INIT:
                session = SoilSession(parse_settings(payload.decode()))
                channel.send(OK, session.description.encode())
            elif kind == BYE:
                channel.send(OK, b"bye")
                return
            elif session is None:
                raise InternalError(f"message kind {kind} before INIT")
            elif kind == PLACE:
                channel.send(OUTPUTS, session.place(np.frombuffer(payload, "<f8")))
            elif kind == STEP:
                values = np.frombuffer(payload, "<f8")
                channel.send(OUTPUTS, session.step(float(values[0]), values[1:]))
            elif kind in (SAVE, RESTORE, FREE):
                ident = int(np.frombuffer(payload, "<u4")[0])
                action = {SAVE: session.save, RESTORE: session.restore, FREE: session.free}[kind]
                channel.send(OK, action(ident))
            else:
                raise InternalError(f"unknown message kind {kind}")
        except StepRefused as refused:
            channel.send(DISCARD, str(refused).encode())
        except Exception as error:
            traceback.print_exc()
            channel.send(ERROR, f"{type(error).__name__}: {error}".encode())


def _exit_with(parent: int) -> None:
    """End this process when the importer that started it is gone (no orphan servers)."""
    while os.getppid() == parent:
        time.sleep(0.25)
    os._exit(0)


def _one_line_warnings(message, category, filename, lineno, file=None, line=None):
    text = " ".join(str(message).split())
    print(f"warning: {category.__name__}: {text}", file=sys.stderr, flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m cosim.soil_fmu.server", description=__doc__.splitlines()[0])
    parser.add_argument("--fd", type=int, required=True, help="descriptor of this server's end of the socket pair")
    args = parser.parse_args(argv)
    threading.Thread(target=_exit_with, args=(os.getppid(),), daemon=True).start()
    warnings.showwarning = _one_line_warnings
    with socket.socket(fileno=args.fd) as sock:
        serve(Channel(sock))
    return 0


if __name__ == "__main__":
    sys.exit(main())
