"""The signals that stop a command cleanly, and the exit status each gives.

Ctrl-C (SIGINT), SIGTERM (a batch scheduler, `docker stop`) and SIGHUP (the terminal or the ssh session
closed) all stop a run after its macro step with a checkpoint (`cosim resume OUT` continues it); the
command exits 128 + the signal's number (130, 143, 129), as a shell reports a process the signal ended.
A signal the command was started ignoring (`nohup` ignores SIGHUP) stays ignored.
"""

from __future__ import annotations

import signal
import threading

STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))
"""Ctrl-C, SIGTERM and (where the system has it) SIGHUP."""
STOP_NAMES = tuple(signal.Signals(number).name for number in STOP_SIGNALS)
SIGNAL_WORDS = {"SIGINT": "Ctrl-C"}
"""How a message names a stop signal (the others by their names)."""


def install(handler) -> dict:
    """`handler` for every stop signal not ignored at the start (nohup's SIGHUP stays ignored). Returns the
    handlers it replaced, for `restore`; empty outside the main thread, where Python allows no handler."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    former = {}
    for number in STOP_SIGNALS:
        if signal.getsignal(number) is signal.SIG_IGN and number != signal.SIGINT:
            continue
        former[number] = signal.signal(number, handler)
    return former


def restore(former: dict) -> None:
    """Put back the handlers `install` replaced (one set outside Python, which Python reports as None: the
    default)."""
    for number, handler in former.items():
        signal.signal(number, signal.SIG_DFL if handler is None else handler)


def stop_name(stop: BaseException) -> str:
    """The name of the signal behind a stop: a RunInterrupted's or a set's `signal`, or the first word of
    a KeyboardInterrupt raised by a handler here ('SIGTERM', 'SIGHUP twice: ...'); a bare Ctrl-C: SIGINT."""
    name = getattr(stop, "signal", None)
    if name in STOP_NAMES:
        return name
    words = str(stop).split(maxsplit=1)
    first = words[0].rstrip(":") if words else ""
    return first if first in STOP_NAMES else "SIGINT"


def exit_status(name: str) -> int:
    """128 + the signal's number: 130 for SIGINT, 143 for SIGTERM, 129 for SIGHUP."""
    return 128 + int(getattr(signal, name, signal.SIGINT))
