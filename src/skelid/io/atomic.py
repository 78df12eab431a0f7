"""Atomic output: write to a temporary file beside the target, then rename.

An interrupted run (an exception, Ctrl-C) leaves either the previous file or
no file, never a half-written one. :func:`atomic_dir` does the same for an
output folder: everything is written into a hidden temporary sibling folder
and moved in only when the whole output is complete.

A run killed outright (``SIGKILL``, a power cut) cannot clean up after itself:
it may leave a hidden ``.NAME.*.part`` file or folder beside the target, but
never a partial file under the target's own name. Folders left that way are
removed by the next run that writes the same output folder.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import tempfile
from pathlib import Path

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
    return SkelidError(f"cannot write {path}: {exc.strerror or exc}",
                       "choose an output location you can write to, with enough free space")


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
    if path.is_dir():
        raise SkelidError(f"cannot write {path}: it is a folder", "give the name of a file, not a folder")
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
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError) and exc.errno in WRITE_ERRNOS:
            raise _cannot_write(path, exc) from None
        raise


def check_output_dir(path) -> Path:
    """Check early, before any long computation, that ``path`` can be an output folder.

    Raises
    ------
    SkelidError
        ``path`` is an existing file, or a folder on its way is a file.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise SkelidError(f"output folder {path} is an existing file",
                          "give --out the name of a folder (new or existing), not of a file")
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
def atomic_dir(path, protect=()):
    """Build an output folder in a temporary sibling, then move it in.

    Yields the temporary folder; write every output file into it. On success a
    new ``path`` appears in one rename. An existing ``path`` keeps the files
    this run does not write (nothing of the user's is deleted); its index file
    (``result.json`` or ``summary.json``) is removed first and put back last,
    so an index is only ever beside a complete set of files. On any exception
    the temporary folder is removed and ``path`` is left as it was.

    Parameters
    ----------
    path : path-like
        The output folder.
    protect : sequence of path-like
        Input files that must never be replaced (a clear error if an output
        would land on one).
    """
    path = check_output_dir(path)
    parent = ensure_parent(path)
    sweep_stale(path)
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.{os.getpid()}.", suffix=".part", dir=parent))
    except OSError as exc:
        raise _cannot_write(parent, exc) from None
    try:
        os.chmod(tmp, 0o777 & ~_umask())
        yield tmp
        _commit(tmp, path, {Path(p).resolve() for p in protect})
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(exc, OSError) and exc.errno in WRITE_ERRNOS:
            raise _cannot_write(path, exc) from None
        raise


def _commit(tmp: Path, path: Path, protect: set) -> None:
    names = sorted(p.name for p in tmp.iterdir())
    clash = [path / n for n in names if (path / n).resolve() in protect]
    if clash:
        raise SkelidError(f"output {clash[0]} would overwrite an input file",
                          "choose another --out folder")
    if not path.exists() or (path.is_dir() and not any(path.iterdir())):
        with contextlib.suppress(OSError):
            path.rmdir()  # an empty folder: replace it in one rename
        try:
            os.rename(tmp, path)
            return
        except OSError:
            if not path.is_dir():
                raise
    index = [n for n in names if n in INDEX_FILES]
    for n in index:
        with contextlib.suppress(FileNotFoundError):
            (path / n).unlink()
    for n in [n for n in names if n not in INDEX_FILES] + index:
        if (path / n).is_dir() and not (tmp / n).is_dir():
            raise SkelidError(f"cannot write {path / n}: a folder of that name is in the way",
                              "remove or rename that folder, or choose another --out folder")
        os.replace(tmp / n, path / n)
    tmp.rmdir()
