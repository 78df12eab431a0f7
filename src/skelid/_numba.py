"""Whether the compiled kernels run, and how they are compiled without holding up a fit.

Every compiled kernel of skelid (the pose fits' Levenberg-Marquardt kernel, the
compiled kinematics, the live session's linearisation) follows one rule, kept here:

* ``SKELID_NUMBA`` selects the path: ``0`` (or ``false``, ``no``, ``off``) always
  the numpy path (numba is not even imported); ``wait`` always the compiled
  path, waiting for the compilation if numba's disk cache is cold (the tests use
  this, so that a result never depends on when the cache was written);
  ``compile`` marks the background process that compiles; anything else (the
  default): compiled once cached, numpy path meanwhile.
* A kernel missing from numba's disk cache is compiled in a separate process
  (:func:`compile_in_background`), so the fit that needs it goes on with the numpy
  path; such processes take turns (:func:`one_at_a_time`), leaving the other cores
  to the fit.
* :class:`Gate` answers "can this kernel run now without compiling here?" and looks
  at the cache at most every half second while it is cold, so asking per frame
  costs nothing.

Examples
--------
>>> from skelid import _numba
>>> _numba.MODE in ("0", "false", "no", "off") or _numba.AVAILABLE
True
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import tempfile
import time
import zlib
from collections.abc import Callable, Hashable

MODE = os.environ.get("SKELID_NUMBA", "1").strip().lower()
if MODE in ("0", "false", "no", "off"):  # pragma: no cover - depends on the environment
    numba = None
else:
    import numba

AVAILABLE = numba is not None

#: while a kernel is not cached, look at the cache again at most this often (seconds)
RECHECK_S = 0.5


def _lock_path(name: str) -> str:
    """A lock file per user and installed copy of skelid."""
    where = zlib.crc32(os.path.abspath(__file__).encode())
    uid = getattr(os, "getuid", lambda: 0)()
    return os.path.join(tempfile.gettempdir(), f"skelid-numba-{name}-{uid}-{where:x}.lock")


@contextlib.contextmanager
def compile_lock(name: str):
    """Hold the lock of kernel ``name`` (one process compiles it at a time; released on exit)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: no lock
        fcntl = None
    with open(_lock_path(name), "a") as fh:
        if fcntl is not None:
            fcntl.flock(fh, fcntl.LOCK_EX)
        yield


def in_disk_cache(dispatcher, signature: tuple) -> bool:
    """Whether numba's disk cache holds ``dispatcher`` compiled for ``signature`` (numba types).

    True where the cache's index cannot be read (numba's internals changed): the kernel is
    then compiled in the process that first calls it.
    """
    try:
        key = dispatcher._cache._index_key(signature, dispatcher.targetctx.codegen())
        return dispatcher._cache._cache_file._load_index().get(key) is not None
    except Exception:  # noqa: BLE001 - numba internals changed: compile when first called
        return True


def one_at_a_time(lock: str | None = None) -> str:
    """Code that waits for every other compiling process of this installed copy before going on.

    A fit that finds several kernels missing starts one process per kernel; run together, they
    would take every core from the fit that runs meanwhile on the numpy path (on two cores, three
    compilations left it about half of one). Taken in turn, they leave the fit a core. The lock is
    taken before numba is imported, so a waiting process costs nothing; it is released when the
    process ends. ``lock``: the lock file (default: one per user and installed copy).
    """
    path = lock or _lock_path("compile")
    return ("try:\n    import fcntl\nexcept ImportError:\n    fcntl = None\n"
            f"_lock = open({path!r}, 'a')\n"
            "if fcntl is not None:\n    fcntl.flock(_lock, fcntl.LOCK_EX)\n")


def compile_in_background(warming: dict, key, code: str, cached, wait: bool, timeout: float) -> bool:
    """Run ``code`` (which compiles a kernel into numba's disk cache) in one separate process per ``key``.

    ``warming`` holds the processes already started; ``cached()`` says whether the kernel is in the
    cache. The processes of all kernels compile one at a time (:func:`one_at_a_time`), leaving the
    other cores to the fit that goes on meanwhile, except with ``SKELID_NUMBA=wait``, where the caller
    waits for them and they run side by side. Returns ``cached()`` after waiting at most ``timeout``
    seconds when ``wait``.
    """
    proc = warming.get(key)
    if proc is None and not cached():
        env = dict(os.environ, SKELID_NUMBA="compile", PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
        proc = warming[key] = subprocess.Popen(
            [sys.executable, "-c", ("" if MODE == "wait" else one_at_a_time()) + code], env=env,
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    if proc is not None and wait:
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            return False
    return cached()


class Gate:
    """Whether a module's compiled kernels can run now; starts their compilation when they cannot.

    One per kernel module. ``compiled(key)``: loaded in this process; ``cached(key)``: in numba's
    disk cache; ``warm(key, wait)``: compile into the cache in a separate process (see
    :func:`compile_in_background`, with this gate's :attr:`warming`); ``mode()``: the module's
    ``SKELID_NUMBA`` mode (default :data:`MODE`).
    """

    def __init__(self, compiled: Callable[[Hashable], bool], cached: Callable[[Hashable], bool],
                 warm: Callable[[Hashable, bool], bool], mode: Callable[[], str] = lambda: MODE):
        self.compiled, self.cached, self.warm, self.mode = compiled, cached, warm, mode
        self.found: dict = {}  # kernels found in the cache (they stay there)
        self.last_check: dict = {}
        self.warming: dict[Hashable, subprocess.Popen] = {}

    def ready(self, key) -> bool:
        """False without numba (or with ``SKELID_NUMBA=0``); with ``SKELID_NUMBA=wait`` always True
        (compiling first if the cache is cold). Otherwise True once cached; while it is not, starts
        the compilation in the background (once) and answers False, looking at the cache again at
        most every :data:`RECHECK_S` seconds."""
        if not AVAILABLE:
            return False
        mode = self.mode()
        if self.found.get(key) or mode == "compile" or self.compiled(key):  # "compile": the warm-up process
            return True
        if mode == "wait":
            if not self.cached(key):
                self.warm(key, True)
            return True
        now = time.monotonic()
        if now - self.last_check.get(key, -float("inf")) < RECHECK_S:
            return False
        self.last_check[key] = now
        if self.cached(key):
            self.found[key] = True  # once cached, always ready: the throttle is for a cold cache only
            return True
        self.warm(key, False)
        return False
