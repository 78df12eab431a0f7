"""Memory and time a job will need, estimated from sizes before anything is allocated.

A fit's cost grows with the model and the data:

* reading a text marker file holds about :data:`TEXT_READ_FACTOR` times the
  file's size while it parses (a C3D file about :data:`BINARY_READ_FACTOR`);
* the marker data, ``F x M x D`` numbers, are held in a few copies;
* ``paper``: the grid log-likelihoods ``F x K`` (``K`` grid points);
* ``marker-grid``: per frame, the pose Jacobians of every grid point,
  ``K x (M D) x (Q + P)`` (``Q`` pose coordinates, ``P`` parameters);
* ``marker``: the stacked Jacobians ``F x (M D) x (Q + P)``;
* ``marker-smc``: the ``marker`` fit plus every particle's poses
  ``N x F x Q``.

The memory estimate counts those arrays in float64 with a small factor for
temporaries; the time estimate is a rough figure of the same sizes, calibrated
on this project's 2-core machine (it errs on the high side). A job whose
estimate exceeds the limits is refused before it starts, with one line naming
the setting to change (``grid_step``, ``--frames``, ...) and how to raise the
limit: ``--max-memory``/``SKELID_MAX_MEMORY`` (default 4 GiB) and
``--max-time``/``SKELID_MAX_TIME`` (default 30 minutes). Before a text file
is read, its number of frames is estimated from its size and the length of
its first lines (:func:`estimate_frames`), so that a file too long to fit is
refused before it is parsed.

A job of several trials is estimated over all of them before any is read
(:func:`trial_frames` for each file's frames): the joint fit of several trials
(:func:`trials_cost`) fits their frames together, plus :data:`TRIAL_SECONDS` per
trial and a refit per model alternative; ``skelid batch`` (:func:`batch_cost`)
fits the trials one by one, ``n_workers`` at a time, plus the start of its
cluster. Estimates can be wrong (an ill-conditioned fit iterates longer), so
the command line also stops a job that runs past ``--max-time``
(:mod:`skelid._stop`).

Examples
--------
>>> parse_size("1.5G") == int(1.5 * 2**30)
True
>>> format_size(3 * 2**30)
'3.0 GiB'
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

from skelid.errors import SkelidError

DEFAULT_MAX_MEMORY = 4 * 2**30
DEFAULT_MAX_SECONDS = 1800.0
ENV_MEMORY = "SKELID_MAX_MEMORY"
ENV_TIME = "SKELID_MAX_TIME"
#: bytes of memory per byte of a text marker file while it is parsed, and of a binary one
TEXT_READ_FACTOR = 16.0
BINARY_READ_FACTOR = 4.0
#: copies of the marker array a fit holds (prepared data, poses, residuals, figures)
DATA_COPIES = 8
#: temporaries per counted array
TEMP_FACTOR = 4
#: seconds per unit of work: (frame x coordinate x unknown) for the joint fit; per grid point
SECONDS_PER_UNIT = 1e-4  # case A, 500 frames: about 1 s
SECONDS_PER_GRID_UNIT = 1e-6
SECONDS_PER_PROFILE_UNIT = 2e-7
#: stages x moves the sampler is assumed to need, for its time estimate
SMC_PASSES = 31
DEFAULT_PARTICLES = 200
#: a grid larger than this is refused whatever the memory limit (its size does not fit an index)
MAX_GRID_POINTS = 1e9
#: seconds per trial besides its frames (reading, checks, the typed result), and to start a batch's cluster
TRIAL_SECONDS = 0.5
BATCH_START_SECONDS = 5.0
#: bytes of a C3D file per marker and frame at least (four 16-bit words), for a header that gives no frames
C3D_BYTES_PER_MARKER = 8


class ResourceError(SkelidError):
    """A job would need more memory or time than the limits allow."""


@dataclass(frozen=True)
class Limits:
    """The most memory (bytes) and time (seconds) a job may be estimated to need."""

    memory: float = DEFAULT_MAX_MEMORY
    seconds: float = DEFAULT_MAX_SECONDS

    @classmethod
    def from_settings(cls, max_memory=None, max_time=None) -> Limits:
        """From the command line's values, else the environment, else the defaults."""
        mem = max_memory if max_memory is not None else os.environ.get(ENV_MEMORY)
        sec = max_time if max_time is not None else os.environ.get(ENV_TIME)
        return cls(DEFAULT_MAX_MEMORY if mem in (None, "") else parse_size(mem, "--max-memory"),
                   DEFAULT_MAX_SECONDS if sec in (None, "") else parse_seconds(sec, "--max-time"))


@dataclass(frozen=True)
class Cost:
    """Estimated peak memory (bytes) and time (seconds) of a job.

    ``driver`` says what makes the cost (``"a grid of 1e+08 points"``) and
    ``setting`` what to change to lower it; ``time_driver`` and ``time_setting``
    the same for the time where another term dominates it.
    """

    memory: float
    seconds: float
    driver: str
    setting: str
    time_driver: str = ""
    time_setting: str = ""

    def __post_init__(self):
        if not self.time_driver:
            object.__setattr__(self, "time_driver", self.driver)
            object.__setattr__(self, "time_setting", self.setting)

    def __add__(self, other: Cost) -> Cost:
        mem = self if self.memory >= other.memory else other
        sec = self if self.seconds >= other.seconds else other
        return Cost(self.memory + other.memory, self.seconds + other.seconds, mem.driver, mem.setting,
                    sec.time_driver, sec.time_setting)


_UNITS = {"": 1, "b": 1, "k": 2**10, "m": 2**20, "g": 2**30, "t": 2**40}


def parse_size(text, what: str = "--max-memory") -> int:
    """``"4G"``, ``"512M"``, ``"1.5GiB"``, ``"1000000"`` -> bytes."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([kmgtKMGT]?)(?:i?[bB])?\s*", str(text))
    if not m:
        raise SkelidError(f"{what} {text!r} is not a size", f"write e.g. {what} 8G (or 512M, or a number of bytes)")
    value = float(m.group(1)) * _UNITS[m.group(2).lower()]
    if not (math.isfinite(value) and value > 0):
        raise SkelidError(f"{what} {text!r} must be a positive size", f"write e.g. {what} 8G")
    return int(min(value, 2**62))


def parse_seconds(text, what: str = "--max-time") -> float:
    """``"3600"``, ``"90s"``, ``"30m"``, ``"2h"`` -> seconds."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([smh]?)\s*", str(text))
    if not m:
        raise SkelidError(f"{what} {text!r} is not a duration", f"write e.g. {what} 2h (or 90m, or seconds)")
    value = float(m.group(1)) * {"": 1, "s": 1, "m": 60, "h": 3600}[m.group(2)]
    if not (math.isfinite(value) and value > 0):
        raise SkelidError(f"{what} {text!r} must be a positive duration", f"write e.g. {what} 2h")
    return value


def format_size(n: float) -> str:
    for unit, k in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= k:
            return f"{n / k:.3g} {unit}"
    return f"{n:.0f} B"


def format_seconds(s: float) -> str:
    if s >= 2 * 3600:
        return f"{s / 3600:.3g} h"
    if s >= 120:
        return f"{s / 60:.3g} min"
    return f"{s:.2g} s"


# --------------------------------------------------------------------------- estimates
def grid_points(model) -> float:
    """Points of the grid filters' grid (the product over parameters), as a float (never overflows)."""
    k = 1.0
    for p in model.parameters:
        with _no_overflow():
            n = (p.prior.upper - p.prior.lower) / p.grid_step + 1.0
        k *= n if math.isfinite(n) else math.inf
    return k


class _no_overflow:
    def __enter__(self):
        import numpy as np

        self._old = np.seterr(over="ignore")

    def __exit__(self, *exc):
        import numpy as np

        np.seterr(**self._old)


def read_cost(path) -> Cost:
    """Memory and time to read a marker file, from its size."""
    path = Path(path)
    try:
        size = float(path.stat().st_size)
        with open(path, "rb") as fh:
            binary = b"\x00" in fh.read(512)
    except OSError:
        return Cost(0.0, 0.0, "", "")
    factor = BINARY_READ_FACTOR if binary else TEXT_READ_FACTOR
    return Cost(size * factor, size * 1.2e-7, f"reading a {format_size(size)} file", "a shorter file")


def estimate_frames(path, sample: int = 1 << 16) -> int | None:
    """Frames in a text marker file, estimated from its size and its first lines (None: binary or unknown)."""
    path = Path(path)
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(sample)
    except OSError:
        return None
    if b"\x00" in head[:512]:
        return None
    lines = head.splitlines()
    if len(head) == size:
        return max(len(lines) - 5, 1)
    body = lines[len(lines) // 2:-1]  # past the header; the last line may be cut
    if not body:
        return None
    per_line = sum(len(x) + 1 for x in body) / len(body)
    return int(size / per_line)


def fit_cost(model, method: str, n_frames: int, n_markers: int | None = None,
             n_particles: int = DEFAULT_PARTICLES) -> Cost:
    """Estimated memory and time of fitting ``model`` to ``n_frames`` frames with ``method``."""
    F = float(max(n_frames, 1))
    MD = float((n_markers if n_markers is not None else len(model.markers)) * model.dim)
    Q = float(model.n_pose)
    P = float(model.n_params)
    data = Cost(F * MD * 8 * DATA_COPIES, 0.0, f"{n_frames} frames", "fewer frames")
    grid = "a coarser grid_step in the model file"
    frames = Cost(0.0, F * MD * Q * SECONDS_PER_UNIT, f"{n_frames} frames", "fewer frames")
    if method == "paper":
        K = grid_points(model)
        return data + frames + Cost(F * K * 8 * TEMP_FACTOR, F * K * 1e-8,
                                    f"a grid of {K:.3g} points x {n_frames} frames", grid)
    if method == "marker-grid":
        K = grid_points(model)
        return data + Cost(K * MD * (Q + P) * 8 * TEMP_FACTOR + K * (Q + 16) * 8,
                           F * K * MD * Q * SECONDS_PER_GRID_UNIT,
                           f"a grid of {K:.3g} points x {n_frames} frames", grid)
    joint = Cost(F * MD * (Q + P) * 8 * TEMP_FACTOR * 2, F * MD * (Q + P) * SECONDS_PER_UNIT,
                 f"{n_frames} frames x {int(MD)} marker coordinates", "fewer frames")
    if method == "marker-smc":
        N = float(n_particles)
        return data + joint + Cost(N * F * Q * 8 * TEMP_FACTOR,
                                   N * SMC_PASSES * F * MD * Q * SECONDS_PER_PROFILE_UNIT,
                                   f"{n_particles} particles x {n_frames} frames", "fewer frames")
    return data + joint


def simulate_cost(model, n_frames: int) -> Cost:
    """Memory and time to simulate ``n_frames`` frames of ``model`` and write them."""
    F, MD, Q = float(n_frames), float(len(model.markers) * model.dim), float(model.n_pose)
    return Cost(F * (MD + Q) * 8 * DATA_COPIES * 2, F * (MD + Q) * 2e-6, f"{n_frames} frames", "fewer --frames")


def check(cost: Cost, limits: Limits | None = None, what: str = "this fit") -> Cost:
    """Refuse ``cost`` beyond ``limits`` with one line naming the setting to change."""
    limits = limits or Limits.from_settings()
    if not cost.memory <= limits.memory:
        raise ResourceError(
            f"{what} would need about {format_size(cost.memory)} of memory ({cost.driver}), above the limit "
            f"of {format_size(limits.memory)}",
            f"use {cost.setting}, or raise the limit with --max-memory or {ENV_MEMORY}")
    if not cost.seconds <= limits.seconds:
        raise ResourceError(
            f"{what} would take roughly {format_seconds(cost.seconds)} ({cost.time_driver}), above the limit of "
            f"{format_seconds(limits.seconds)}",
            f"use {cost.time_setting}, or raise the limit with --max-time or {ENV_TIME}")
    return cost


def check_grid(model, method: str) -> None:
    """A grid too large to index at all is refused whatever the limits."""
    if method in ("paper", "marker-grid"):
        K = grid_points(model)
        if not K <= MAX_GRID_POINTS:
            raise ResourceError(f"the {method} grid of model {model.name!r} would have {K:.3g} points",
                                "use a coarser grid_step (or narrower prior bounds) in the model file")


def _c3d_header_frames(head: bytes) -> int | None:
    """Frames a C3D header declares (``last - first + 1``; either byte order), or None."""
    import struct

    if len(head) < 12 or head[1] != 0x50:
        return None
    for order in "<>":
        first, last = struct.unpack(order + "2H", head[6:10])
        if last >= first >= 1:
            return last - first + 1
    return None


def trial_frames(path, n_markers: int) -> int:
    """Frames of a trial file, estimated before it is read.

    A text file: :func:`estimate_frames`. A binary (C3D) file: the frames its header declares, or,
    where the header cannot tell (more than 65535 frames), the most its size can hold
    (:data:`C3D_BYTES_PER_MARKER` per marker and frame). 1 for a file that cannot be read (its
    reader says why).
    """
    guess = estimate_frames(path)
    if guess is not None:
        return guess
    try:
        size = Path(path).stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(512)
    except OSError:
        return 1
    declared = _c3d_header_frames(head)
    return declared if declared is not None else max(size // (C3D_BYTES_PER_MARKER * max(n_markers, 1)), 1)


def _reading(paths) -> Cost:
    """Reading ``paths`` one after the other: the time adds up, the memory is the largest file's."""
    costs = [read_cost(p) for p in paths]
    if not costs:
        return Cost(0.0, 0.0, "", "")
    big = max(costs, key=lambda c: c.memory)
    return Cost(big.memory, sum(c.seconds for c in costs), big.driver, big.setting)


def trials_cost(models, paths) -> Cost:
    """Estimated memory and time of the joint ``marker`` fit of the trials ``paths`` (several trials of
    one body), fitted once under each model of ``models`` (the model, then its alternatives).

    All trials are held and fitted together: the fit of their frames summed (:func:`fit_cost`), plus
    :data:`TRIAL_SECONDS` per trial; each alternative repeats the fit.
    """
    models = list(models)
    n = len(paths)
    frames = sum(trial_frames(p, len(models[0].markers)) for p in paths)
    fits = [fit_cost(m, "marker", frames) for m in models]
    worst = max(fits, key=lambda c: c.memory)
    seconds = sum(c.seconds for c in fits) + n * TRIAL_SECONDS * len(models)
    what = f"{n} trials, {frames} frames in all" + (f", under {len(models)} models" if len(models) > 1 else "")
    fix = "fewer trials (or fewer --alternative models)" if len(models) > 1 else "fewer trials"
    return _reading(paths) + Cost(worst.memory, seconds, what, fix)


def batch_cost(model, method: str, paths, n_workers: int, n_particles: int = DEFAULT_PARTICLES) -> Cost:
    """Estimated memory and time of ``skelid batch``: each trial fitted on its own, ``n_workers`` at once.

    The time is the trials' (:func:`read_cost`, :func:`fit_cost`, :data:`TRIAL_SECONDS` each) shared
    among the workers, plus :data:`BATCH_START_SECONDS`; the memory, ``n_workers`` times the largest
    trial's.
    """
    n_workers = max(int(n_workers), 1)
    costs = [read_cost(p) + fit_cost(model, method, trial_frames(p, len(model.markers)), n_particles=n_particles)
             for p in paths]
    seconds = sum(c.seconds + TRIAL_SECONDS for c in costs) / n_workers + BATCH_START_SECONDS
    memory = max((c.memory for c in costs), default=0.0) * n_workers
    on = f"{n_workers} worker{'s' if n_workers > 1 else ''}"
    return Cost(memory, seconds, f"the largest trial on each of {on}", "fewer --workers",
                f"{len(paths)} trials on {on}",
                "fewer trials per run (a narrower pattern; a re-run skips the trials already in the table), or "
                "more --workers")


#: glibc's ``mallopt`` parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4


def keep_freed_memory() -> bool:
    """Serve large arrays from the heap and keep what is freed there for the next ones (glibc only).

    By default glibc maps each block over 32 MiB afresh and returns it to the system when freed; a
    full-body fit allocates its frame-stacked Jacobians (100-200 MiB) hundreds of times, and the kernel's
    zeroing of the new pages took 29 of its 110 CPU seconds (six trials of a 49-marker model; 3 s with
    this). The process's memory then stays near its peak until it ends, so this is for the command line,
    whose process ends with the job. Returns whether it took effect (False off glibc).
    """
    import ctypes
    import ctypes.util
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))
