"""Atomic file writes: a crash or an interrupt never leaves a half-written file in place."""

from __future__ import annotations

import errno
import os
import tempfile
from contextlib import contextmanager


@contextmanager
def atomic_path(path, suffix: str = ".tmp", replace: bool = True):
    """Yield a temporary path beside `path` to write to; on success it is fsynced and renamed
    onto `path` (os.replace, atomic), on any error it is removed and `path` is left untouched.

    A missing folder of `path` is made (a command's output goes where it was told), and removed
    again, with every folder above it that this call made, when the write fails: a failed write
    leaves no empty folders. `path` an existing folder is refused before anything is made. An
    OSError is raised naming `path`, never the temporary file (the user knows only `path`), also one
    that names no file (e.g. a full disk during a write).

    replace False: a file that appeared at `path` meanwhile (another process's: its name was free when the
    caller looked, an hour of work before) is left as it is, and what was made is kept beside it
    (place_new: FileExistsError naming both).

    The file gets the permissions of a normally created one (mkstemp's 0600 would hide it).
    `path` a symbolic link: the file it points to is written (beside that file) and the link stays, as
    open(path, "w") does (replacing the link left its file stale and the link gone). A caller that writes
    a file of one kind (an export, a picture) checks first what that file is: output_target.

    A write killed with SIGKILL (which no handler sees) leaves its temporary, tmpXXXXXXXX`suffix`, beside
    the file; nothing removes it, as nothing can tell it from a live writer's on a shared file system.
    """

    path = os.fspath(path)
    if os.path.isdir(path):
        raise IsADirectoryError(errno.EISDIR, "Is a directory: a file cannot be written there", path)
    # a link's file is written beside that file; a new name only where the caller looked (replace False)
    written = os.path.realpath(path) if os.path.islink(path) and replace else path
    created: list[str] = []
    temporary = None
    try:
        folder = os.path.dirname(os.path.abspath(written))
        created = make_folders(folder)
        for attempt in range(2):
            try:
                handle, temporary = tempfile.mkstemp(suffix=suffix, dir=folder)
                break
            except FileNotFoundError as error:  # another process's failed write removed the folder it made
                if attempt:
                    raise with_path(error, path, replace=error.filename) from error
                created += make_folders(folder)
            except OSError as error:  # it names the temporary file it tried to make
                raise with_path(error, path, replace=error.filename) from error
        assert temporary is not None, "made in the loop above, or raised"
        os.close(handle)
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(temporary, 0o666 & ~mask)
        yield temporary
        descriptor = os.open(temporary, os.O_RDONLY)
        try:
            os.fsync(descriptor)
        finally:
            os.close(descriptor)
        if replace:
            os.replace(temporary, written)
        else:
            place_new(temporary, written)
    except BaseException as error:
        if temporary is not None and os.path.lexists(temporary):
            os.remove(temporary)
        remove_empty_folders(created)
        if isinstance(error, OSError) and (not error.filename or error.filename == temporary):
            raise with_path(error, path, replace=temporary) from error  # a full disk while writing: name the file
        raise


def output_target(path, suffixes: tuple[str, ...], inputs=(), what: str = "--out") -> str:
    """The file a write of `path` makes (atomic_path: the file a symbolic link names, the link kept), after
    refusing, before anything is written, a `path` that would replace what is not the writer's own to
    replace (ArgumentError naming `path`, the file it reaches and what is allowed):

    - one that reaches one of `inputs` (the files of the run being read: its results.h5, its checkpoint), also
      through a link, a hard link or a folder that is a link;
    - one whose file, the link's target for a link, does not end in one of `suffixes` (lower case): a link
      named view.png that names results.h5 is refused, not written through.

    A link whose target ends in an allowed suffix is written through (its target replaced, the link kept);
    a link to a folder is left to the caller (a folder of frames)."""
    from .errors import ArgumentError

    path = os.fspath(path)
    target = os.path.realpath(path)
    for given in inputs:
        if given is None:
            continue
        given = os.fspath(given)
        same = target == os.path.realpath(given)
        if not same and os.path.exists(target) and os.path.exists(given):
            try:
                same = os.path.samefile(target, given)
            except OSError:
                same = False
        if same:
            direct = target == os.path.abspath(path)
            reached = "is" if direct else f"leads to {target}, which is"
            raise ArgumentError(
                f"{what} {path!r} {reached} a file of the run it reads ({given}): it is never written; "
                f"{'' if direct else 'remove the link or '}name another {' or '.join(suffixes)} file"
            )
    if os.path.isdir(target):
        return target
    if not target.lower().endswith(tuple(s.lower() for s in suffixes)):
        if os.path.basename(target) == os.path.basename(os.path.abspath(path)):
            raise ArgumentError(f"{what} {path!r}: the file must end in {' or '.join(suffixes)}")
        raise ArgumentError(
            f"{what} {path!r} is a link to {target}, which is not a {' or '.join(suffixes)} file: it is not "
            "written through; name a new file, or remove the link"
        )
    return target


NO_HARD_LINKS = {errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.ENOSYS, errno.EXDEV, errno.EMLINK}
"""The errors of os.link on a file system without hard links (FAT, some network mounts)."""


def place_new(temporary: str, path: str) -> None:
    """Move the finished file `temporary` to `path` only if no file is there (os.link refuses an existing
    name, atomically; a file system without hard links is looked at first, then written); else keep it
    as PATH-STEM.new[-k]SUFFIX beside it, placed the same way, and raise FileExistsError naming `path` and
    the kept file."""
    if _placed(temporary, path):
        return
    stem, extension = os.path.splitext(path)
    for k in range(1, 10**6):
        kept = f"{stem}.new{'' if k == 1 else f'-{k}'}{extension}"
        if _placed(temporary, kept):
            raise FileExistsError(
                errno.EEXIST,
                "appeared while it was being made (another process wrote it) and was left as it is; what was "
                f"made is {kept}",
                path,
            )
    raise FileExistsError(errno.EEXIST, f"appeared while it was being made; what was made is {temporary}", path)


def _placed(temporary: str, path: str) -> bool:
    """Whether `temporary` now is `path` (False, `temporary` kept, when a file is there already)."""
    try:
        os.link(temporary, path)
    except FileExistsError:
        return False
    except OSError as error:
        if error.errno not in NO_HARD_LINKS:
            raise
        if os.path.lexists(path):  # no hard links here: look, then move (a process could still come between)
            return False
        os.replace(temporary, path)
        return True
    os.remove(temporary)
    return True


def make_folders(folder) -> list[str]:
    """Make `folder` and the folders above it that are missing (os.makedirs); returns those made, the
    topmost first, for remove_empty_folders. A folder another process makes meanwhile is not among them,
    and one it removes meanwhile (its failed write, remove_empty_folders) is made again."""
    for attempt in range(3):
        try:
            return _make_folders(os.path.abspath(os.fspath(folder)))
        except FileNotFoundError:  # a folder above was removed between the look and the mkdir
            if attempt == 2:
                raise
    raise AssertionError("unreachable")


def _make_folders(folder: str) -> list[str]:
    missing = []
    while not os.path.isdir(folder) and os.path.dirname(folder) != folder:
        missing.append(folder)
        folder = os.path.dirname(folder)
    made: list[str] = []
    try:
        for name in reversed(missing):
            try:
                os.mkdir(name)
            except FileExistsError:
                if os.path.isdir(name):  # made meanwhile by another process: not ours to remove
                    continue
                raise
            made.append(name)
    except BaseException:
        remove_empty_folders(made)
        raise
    return made


def remove_empty_folders(made: list[str]) -> None:
    """Remove the folders make_folders made, the deepest first, as long as they are empty (what was written
    into them since stays, and so do the folders that hold it)."""
    for name in reversed(made):
        try:
            os.rmdir(name)
        except OSError:
            return


def with_path(error: OSError, path, replace=None) -> OSError:
    """`error` naming `path` when it names no file (a write into an open file, HDF5's own errors) or names
    `replace` (a temporary file the user never heard of): the user must learn which file a full disk or a
    read-only mount stopped."""
    if error.filename and (replace is None or error.filename != replace):
        return error
    strerror = error.strerror or str(error)
    if replace is not None:
        strerror = strerror.replace(os.fspath(replace), os.fspath(path))
    named = OSError(error.errno, strerror, os.fspath(path))  # the subclass of its errno (IsADirectoryError, ...)
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
