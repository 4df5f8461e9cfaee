"""Atomic file writes: a crash or an interrupt never leaves a half-written file in place."""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager


@contextmanager
def atomic_path(path, suffix: str = ".tmp"):
    """Yield a temporary path beside `path` to write to; on success it is fsynced and renamed
    onto `path` (os.replace, atomic), on any error it is removed and `path` is left untouched.

    The file gets the permissions of a normally created one (mkstemp's 0600 would hide it).
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    handle, temporary = tempfile.mkstemp(suffix=suffix, dir=folder)
    os.close(handle)
    try:
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(temporary, 0o666 & ~mask)
        yield temporary
        descriptor = os.open(temporary, os.O_RDONLY)
        try:
            os.fsync(descriptor)
        finally:
            os.close(descriptor)
        os.replace(temporary, path)
    except BaseException:
        if os.path.exists(temporary):
            os.remove(temporary)
        raise


def atomic_write_text(path, text: str) -> None:
    """Write `text` to `path` atomically (atomic_path)."""
    with atomic_path(path) as temporary:
        with open(temporary, "w") as out:
            out.write(text)
