"""Atomic file writes: a crash or an interrupt never leaves a half-written file in place."""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager


@contextmanager
def atomic_path(path, suffix: str = ".tmp"):
    """Yield a temporary path beside `path` to write to; on success it is fsynced and renamed
    onto `path` (os.replace, atomic), on any error it is removed and `path` is left untouched (an
    OSError that names no file, e.g. a full disk during a write, is raised naming `path`).

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
    except BaseException as error:
        if os.path.exists(temporary):
            os.remove(temporary)
        if isinstance(error, OSError) and not error.filename:  # a full disk while writing: name the file
            raise with_path(error, path) from error
        raise


def with_path(error: OSError, path) -> OSError:
    """`error` naming `path` when it names no file (a write into an open file, HDF5's own errors): the user
    must learn which file a full disk or a read-only mount stopped."""
    if error.filename:
        return error
    named = OSError(error.errno, error.strerror or str(error), os.fspath(path))
    named.__cause__ = error
    return named


def atomic_write_text(path, text: str) -> None:
    """Write `text` to `path` atomically (atomic_path)."""
    with atomic_path(path) as temporary:
        with open(temporary, "w") as out:
            out.write(text)


HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def check_hdf5(path, what: str = "HDF5 file") -> None:
    """Refuse, before HDF5 opens it, a file that is not HDF5 or is shorter than its superblock says.

    A truncated file is found here in microseconds: opened, HDF5 (with SWMR reads, which retry
    failed metadata reads) can spend minutes before it fails, or fail later with an obscure
    message. DamagedFileError names the file and what is wrong; FileNotFoundError when it is absent.
    (The superblock is at offset 0: the project writes no user block. Versions 0/1 store the end of
    file address after 24 or 28 bytes plus two addresses, versions 2/3 after 12 bytes plus two.)
    """
    import struct

    from .errors import DamagedFileError

    path = os.fspath(path)
    size = os.path.getsize(path)  # FileNotFoundError when absent
    with open(path, "rb") as f:
        head = f.read(64)
    if not head.startswith(HDF5_SIGNATURE) or len(head) < 48:
        raise DamagedFileError(f"{path}: not a readable HDF5 {what} (no HDF5 signature; {size} bytes)")
    version = head[8]
    if version >= 2:
        offsets, start = head[9], 12
    else:
        offsets, start = head[13], 24 + (4 if version == 1 else 0)
    if offsets not in (4, 8) or start + 3 * offsets > len(head):
        raise DamagedFileError(f"{path}: the {what} has a damaged HDF5 superblock")
    end = struct.unpack("<Q" if offsets == 8 else "<I", head[start + 2 * offsets : start + 3 * offsets])[0]
    if end > size:
        raise DamagedFileError(
            f"{path}: the {what} is truncated: it holds {size} of the {end} bytes its header records "
            "(cut short, or its writer is creating it right now)"
        )
