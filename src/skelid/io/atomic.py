"""Atomic output: write to a temporary file beside the target, then rename.

An interrupted run (an exception, Ctrl-C) leaves either the previous file or
no file, never a half-written one. :func:`atomic_dir` does the same for an
output folder: everything is written into a hidden temporary sibling folder
and moved in only when the whole output is complete.

Ctrl-C, ``SIGTERM`` and the end of a time limit raise an exception on their way
out (:mod:`skelid._stop`): the temporary file or folder is removed, and an
output is never moved into place once a stop was asked for, even one that
a library dropped; the renames that move a finished folder in are never cut
in two (a stop during them takes effect once the folder is complete).

A run killed outright (``SIGKILL``, a power cut) cannot clean up after itself:
it may leave a hidden ``.NAME.*.part`` file or folder beside the target, but
never a partial file under the target's own name. Folders left that way are
removed by the next run that writes the same output folder.

Nothing is clobbered: only regular files and folders are written, and a
symbolic link (dangling or not), a FIFO, a device or a socket under the
target's name is refused, never replaced. An existing output folder is
refused unless ``overwrite`` is given, which replaces it whole (the old
contents are removed, never mixed with the new). A writer holds an exclusive
lock on its target (:func:`target_lock`, a ``flock`` on a file in the
temporary folder, released by the kernel if the process dies), so a second
run writing the same target at the same time is refused with one line. Every
``OSError`` while writing (no space, file too large, no permission, ...)
becomes one line.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import os
import re
import shutil
import stat
import tempfile
from pathlib import Path

from skelid import _stop
from skelid.errors import SkelidError

#: errno values that mean "you cannot write here", not "skelid has a bug"
WRITE_ERRNOS = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.ENAMETOOLONG}

#: files written last into an output folder: their presence says the folder is complete
INDEX_FILES = ("result.json", "summary.json")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _cannot_write(path: Path, exc: OSError) -> SkelidError:
    reason = exc.strerror or errno.errorcode.get(exc.errno or 0) or str(exc) or type(exc).__name__
    return SkelidError(f"cannot write {path}: {reason}",
                       "choose an output location you can write to, with enough free space")


def _kind(mode: int) -> str:
    if stat.S_ISLNK(mode):
        return "a symbolic link"
    if stat.S_ISFIFO(mode):
        return "a named pipe (FIFO)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def check_target(path, folder: bool = False) -> os.stat_result | None:
    """The ``lstat`` of an output target (None if absent); refuse anything but a regular file or folder.

    Raises
    ------
    SkelidError
        ``path`` is a symbolic link (even a dangling one), a FIFO, a device or
        a socket; or a file where a folder is wanted and the reverse.
    """
    path = Path(path)
    try:
        st = os.lstat(path)
    except (FileNotFoundError, NotADirectoryError):  # absent (a file on the way is reported when creating it)
        return None
    except OSError as exc:
        raise _cannot_write(path, exc) from None
    if folder and stat.S_ISDIR(st.st_mode) or not folder and stat.S_ISREG(st.st_mode):
        return st
    if stat.S_ISDIR(st.st_mode):
        raise SkelidError(f"cannot write {path}: it is a folder", "give the name of a file, not a folder")
    if stat.S_ISREG(st.st_mode):
        raise SkelidError(f"output folder {path} is an existing file",
                          "give --out the name of a folder, not of a file")
    raise SkelidError(f"output {path} is {_kind(st.st_mode)}; skelid writes only regular files and folders "
                      "and never replaces anything else", "remove it, or choose another output name")


@contextlib.contextmanager
def target_lock(path):
    """Hold an exclusive lock on output ``path`` (its absolute name) while the block runs.

    The lock is a ``flock`` on a file named by a hash of the path in a private
    folder of the temporary directory: nothing appears beside the target, and a
    killed process releases it.

    Raises
    ------
    SkelidError
        Another process holds the lock (another run is writing ``path``).
    """
    key = hashlib.sha256(str(Path(path).absolute()).encode()).hexdigest()[:32]
    folder = Path(tempfile.gettempdir()) / f"skelid-locks-{os.getuid()}"
    try:
        folder.mkdir(mode=0o700, exist_ok=True)
        fd = os.open(folder / f"{key}.lock", os.O_RDWR | os.O_CREAT, 0o600)
    except OSError:  # no private temporary folder: go on unlocked rather than refuse to work
        yield
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise SkelidError(f"another skelid run is writing {path} right now",
                              "wait for it to finish, or choose another output name") from None
        yield
    finally:
        os.close(fd)


def ensure_parent(path) -> Path:
    """Create the folder that will hold ``path``; a one-line error if that is impossible."""
    parent = Path(path).parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        blocker = next((p for p in (parent, *parent.parents) if p.exists() and not p.is_dir()), parent)
        raise SkelidError(f"cannot write {path}: {blocker} is a file, not a folder",
                          "choose an output path whose folders are folders") from None
    except OSError as exc:
        raise _cannot_write(parent, exc) from None
    return parent


@contextlib.contextmanager
def atomic_write(path, mode: str = "w", encoding: str | None = "utf-8", newline: str | None = None):
    """Open a temporary file for writing that replaces ``path`` only on success.

    The new file gets the permissions of the file it replaces, or the usual
    ``0o666`` less the umask for a new file.

    Raises
    ------
    SkelidError
        ``path`` is a folder, or its folder cannot be created or written to.
    """
    path = Path(path)
    check_target(path)
    ensure_parent(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    except OSError as exc:
        raise _cannot_write(path, exc) from None
    try:
        kw = {} if "b" in mode else {"encoding": encoding, "newline": newline}
        with os.fdopen(fd, mode, **kw) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        try:
            mode_bits = path.stat().st_mode & 0o777
        except OSError:
            mode_bits = 0o666 & ~_umask()
        os.chmod(tmp, mode_bits)
        check_target(path)  # nothing but a regular file has appeared there meanwhile
        _stop.check()  # never in place once a stop was asked for
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise _cannot_write(path, exc) from None
        raise


def check_output_dir(path, overwrite: bool = False) -> Path:
    """Check early, before any long computation, that ``path`` can be an output folder.

    Raises
    ------
    SkelidError
        ``path`` is an existing file, a symbolic link, FIFO or device, an
        existing non-empty folder (unless ``overwrite``), or a folder on its
        way is a file.
    """
    path = Path(path)
    st = check_target(path, folder=True)
    if st is not None and not overwrite and any(path.iterdir()):
        raise SkelidError(f"output folder {path} already exists",
                          "choose a new --out folder, or add --overwrite to replace it whole")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise SkelidError(f"cannot create output folder {path}: {parent} is a file",
                                  "choose an output path whose folders are folders")
            break
    return path


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


def sweep_stale(path) -> list[Path]:
    """Remove temporary folders that killed runs left beside output folder ``path``."""
    path = Path(path)
    pattern = re.compile(rf"^\.{re.escape(path.name)}\.(\d+)\.[^.]+\.part$")
    removed = []
    if not path.parent.is_dir():
        return removed
    for entry in path.parent.iterdir():
        m = pattern.match(entry.name)
        if m and entry.is_dir() and not _pid_alive(int(m.group(1))):
            shutil.rmtree(entry, ignore_errors=True)
            removed.append(entry)
    return removed


@contextlib.contextmanager
def atomic_dir(path, protect=(), overwrite: bool = False):
    """Build an output folder in a temporary sibling, then move it in.

    Yields the temporary folder; write every output file into it. On success
    ``path`` appears in one rename. An existing non-empty ``path`` is refused
    unless ``overwrite``, which replaces it whole: the old folder is moved
    aside, the new one moved in, and the old one removed. On any exception the
    temporary folder is removed and ``path`` is left as it was. The target is
    locked against a concurrent writer throughout (:func:`target_lock`).

    Parameters
    ----------
    path : path-like
        The output folder.
    protect : sequence of path-like
        Input files that must never be replaced or removed (a clear error if
        one lies in the folder being replaced).
    overwrite : bool
        Replace an existing folder whole.
    """
    path = check_output_dir(path, overwrite)
    parent = ensure_parent(path)
    with target_lock(path):
        check_output_dir(path, overwrite)  # again, now that no other run can be writing it
        sweep_stale(path)
        try:
            tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.{os.getpid()}.", suffix=".part", dir=parent))
        except OSError as exc:
            raise _cannot_write(parent, exc) from None
        try:
            os.chmod(tmp, 0o777 & ~_umask())
            yield tmp
            with _stop.deferred():  # the renames are never cut in two: a stop during them waits for them
                _stop.check()  # never moved in once a stop was asked for
                _commit(tmp, path, {Path(p).resolve() for p in protect}, overwrite)
        except BaseException as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            if isinstance(exc, OSError):
                raise _cannot_write(path, exc) from None
            raise


def _commit(tmp: Path, path: Path, protect: set, overwrite: bool) -> None:
    st = check_target(path, folder=True)
    if st is not None:
        inside = [p for p in protect if path.resolve() in p.parents]
        if inside:
            raise SkelidError(f"replacing {path} would delete the input file {inside[0]}",
                              "choose another --out folder")
        if any(path.iterdir()) and not overwrite:
            raise SkelidError(f"output folder {path} already exists",
                              "choose a new --out folder, or add --overwrite to replace it whole")
    if st is None or not any(path.iterdir()):
        with contextlib.suppress(OSError):
            path.rmdir()  # an empty folder: replace it in one rename
        os.rename(tmp, path)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{path.name}.{os.getpid()}.", suffix=".part", dir=path.parent))
    os.rename(path, old / "old")  # aside (a sweep removes it if this run is killed now)
    os.rename(tmp, path)
    shutil.rmtree(old, ignore_errors=True)
