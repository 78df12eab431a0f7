"""C3D files, read with ezc3d in a guarded child process.

What is read
------------
``POINT:LABELS`` (and ``LABELS2``, ...), ``POINT:RATE`` and ``POINT:UNITS``
give the names, the sampling rate and the length unit; nothing is converted.
A point ``p`` of frame ``f`` is missing (NaN) where

.. math:: r_{fp} < 0 \\quad\\text{or}\\quad x_{fp} = y_{fp} = z_{fp} = 0,

with ``r`` the C3D residual. If ``POINT:UNITS`` is absent or blank, the unit is
guessed from the spread of the markers (see
:func:`skelid.io._common.guess_units`) and a :class:`~skelid.errors.SkelidWarning`
says so.

Computed points (Plug-in-Gait angles, forces, moments, powers, scalars,
normalised ground reactions ``LNormalisedGRF``, and modelled points such as
joint centres ``LHJC``/``RKJC`` or the segment axes ``PELO``/``LFEA``) are not
markers: they are listed in
``meta["computed_points"]`` and their ``(F, 3)`` arrays are kept in
``meta["computed"]`` (e.g. to compare an estimate with Vicon's joint centres),
but they are not in ``positions``. A point is computed if its label is in one of
the groups ``POINT:ANGLES``, ``FORCES``, ``MOMENTS``, ``POWERS``, ``SCALARS``,
``REACTIONS`` (or another group named in ``POINT:TYPE_GROUPS``), or if its name
(without a ``Subject:`` prefix) matches :data:`COMPUTED_NAME`: files rewritten
by other tools often keep the points but drop the groups, so the names decide
where the groups are absent. :func:`bone_points` gathers the segment "bones"
(four points each: origin, anterior, lateral, proximal) from the computed points.

Guarding the native code
------------------------
ezc3d is C++; a corrupt file can make it crash the interpreter or allocate
memory without bound (a flipped byte in ``POINT:FRAMES`` makes it try to
allocate gigabytes). So the reader

1. validates the 512-byte header itself (:func:`check_c3d_header`): byte 2 is
   the C3D key ``0x50``, the parameter section lies inside the file and names
   a known processor type, and the file is long enough for the frames and
   points the header declares (ezc3d itself reads a truncated file without a
   word). A file that fails is refused at once;
2. runs ezc3d in a fresh interpreter (``python -c``) with a time limit and a
   cap on its address space; a crash, a timeout or a failed allocation in the
   child becomes a :class:`~skelid.errors.FormatError` naming the file.

The header check cannot see inside the parameter section, so it is never
conclusive on its own and the child process is used for every file.
Measured cost (``benchmarks/c3d_isolation_overhead.py``, results in
``benchmarks/results/``; 2-core Linux machine, files of 0.7-2.3 MB): about
0.11 s more per file than reading in-process (0.13-0.15 s against
0.02-0.04 s), well under the 0.5 s that would justify reading unguarded when
the header looks sound. ``isolate=False`` reads in the
current process for callers who trust their files.
"""

from __future__ import annotations

import json
import math
import os
import re
import signal
import struct
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

from skelid.data import MarkerData
from skelid.errors import FormatError, SkelidWarning
from skelid.io import _c3d_child
from skelid.io._common import as_path, check_magnitude, guess_units, normalise_units, read_bytes

#: Names of computed (not measured) points, matched against the label without
#: a ``Subject:`` prefix: joint centres (``LHJC``, ``R_KJC``, ``LHipJointCentre``),
#: Plug-in-Gait kinematic and kinetic outputs (``LHipAngles``, ``LKneeMoment``),
#: centre of mass, and Plug-in-Gait segment origins and axes (``PELO``, ``LFEA``).
COMPUTED_NAME = re.compile(
    r"""(JC|Joint_?Cent(re|er))$
      | (Angles?|Forces?|Moments?|Powers?|GRF)$
      | ^Cent(re|er)_?Of_?Mass
      | ^[LR]?(PEL|FE|TI|FO|TO|HED|TRX|CL|HU|RA|HN)[OALP]$""",
    re.X,
)

#: A Plug-in-Gait "bone" point: the segment (side letter and segment code) and
#: which of its four points it is (origin, anterior, lateral, proximal).
BONE_POINT = re.compile(r"^(?P<segment>[LR]?(PEL|FE|TI|FO|TO|HED|TRX|CL|HU|RA|HN))(?P<point>[OALP])$")
BONE_POINT_NAMES = {"O": "origin", "A": "anterior", "L": "lateral", "P": "proximal"}

_PROCESSORS = {84: "Intel", 85: "DEC", 86: "MIPS"}
_BLOCK = 512

#: Address space the child may use beyond its start-up, in bytes: a floor plus
#: a multiple of the file size (ezc3d needs about ten times the file size).
_MEMORY_FLOOR = 1 << 30
_MEMORY_PER_BYTE = 64


def check_c3d_header(path, raw: bytes | None = None) -> dict:
    """Validate the header block of a C3D file without native code.

    Parameters
    ----------
    path : str or Path
    raw : bytes, optional
        The file's bytes, if already read.

    Returns
    -------
    dict
        ``n_points``, ``n_analog`` (analog samples per frame), ``first_frame``,
        ``last_frame``, ``scale``, ``data_start`` (block), ``rate``,
        ``processor``, ``parameter_blocks``, and ``consistent``: whether the
        file is exactly as long as the header says (False when the header
        cannot tell, e.g. more than 65535 frames).

    Raises
    ------
    FormatError
        If the file cannot be a C3D file: too short, wrong key byte, a
        parameter section outside the file, an unknown processor type, or
        fewer data bytes than the header declares (a truncated file).
    """
    path = as_path(path, "data file")
    if raw is None:
        raw = read_bytes(path, "C3D")
    size = len(raw)
    fix = "check that this is a C3D file and that it was copied completely"
    if size < _BLOCK:
        raise FormatError(f"{path}: {size} bytes; a C3D file has at least one 512-byte header block", fix)
    if raw[1] != 0x50:
        raise FormatError(f"{path}: byte 2 is 0x{raw[1]:02X}, not the C3D key 0x50; not a C3D file", fix)
    p = raw[0]
    if p < 2 or (p - 1) * _BLOCK + 4 > size:
        raise FormatError(f"{path}: the parameter section pointer (block {p}) lies outside the "
                          f"{size}-byte file; the file is corrupt", fix)
    start = (p - 1) * _BLOCK
    n_blocks, proc = raw[start + 2], raw[start + 3]
    if proc not in _PROCESSORS:
        raise FormatError(f"{path}: unknown processor type {proc} in the parameter section "
                          "(expected 84, 85 or 86); the file is corrupt", fix)
    if n_blocks == 0 or start + n_blocks * _BLOCK > size:
        raise FormatError(f"{path}: the parameter section ({n_blocks} blocks from block {p}) runs past the "
                          f"end of the {size}-byte file; the file is truncated or corrupt", fix)
    end = ">" if proc == 86 else "<"
    words = struct.unpack(end + "12H", raw[:24])
    n_points, n_analog, first, last, data_start, analog_per_frame = (
        words[1], words[2], words[3], words[4], words[8], words[9])
    if proc == 85:
        scale, rate = _dec_float(raw[12:16]), _dec_float(raw[20:24])
    else:
        scale, rate = struct.unpack(end + "f", raw[12:16])[0], struct.unpack(end + "f", raw[20:24])[0]
    info = {
        "n_points": n_points, "n_analog": n_analog, "first_frame": first, "last_frame": last,
        "scale": scale, "data_start": data_start, "analog_per_frame": analog_per_frame, "rate": rate,
        "processor": _PROCESSORS[proc], "parameter_blocks": n_blocks, "consistent": False,
    }
    if not (data_start >= p + n_blocks and math.isfinite(scale) and last >= first >= 1):
        return info  # the parameters may still describe the data: ezc3d decides
    width = 4 if scale < 0 else 2
    frames = last - first + 1
    need = frames * (4 * n_points + n_analog) * width
    have = size - (data_start - 1) * _BLOCK
    if need > have:
        raise FormatError(f"{path}: the header declares {frames} frames of {n_points} points and {n_analog} "
                          f"analog samples ({need} bytes of data) but only {max(have, 0)} bytes follow; "
                          "the file is truncated or its header is corrupt", "re-export or re-copy the file")
    info["consistent"] = need <= have < need + _BLOCK
    return info


def _dec_float(b: bytes) -> float:
    """A DEC (VAX F) float stored as two little-endian 16-bit words."""
    return struct.unpack("<f", b[2:4] + b[0:2])[0] / 4.0


def read_c3d(path, *, isolate: bool = True, timeout: float | None = None) -> MarkerData:
    """Read the 3-D points of a C3D file.

    Parameters
    ----------
    path : str or Path
    isolate : bool, default True
        Run ezc3d in a child process, so that a crash on a corrupt file is a
        FormatError and not the end of the interpreter.
    timeout : float, optional
        Seconds the child may take; default 20 s plus 2 s per MB.

    Returns
    -------
    MarkerData
        ``positions (F, M, 3)`` of the measured markers in the file's units;
        ``meta["computed_points"]`` (names) and ``meta["computed"]`` (name ->
        ``(F, 3)`` array) for the computed points, ``meta["header"]`` from
        :func:`check_c3d_header`, ``meta["units_guessed"]``.

    Raises
    ------
    FormatError
        For anything that is not a readable C3D file, naming the file.
    """
    path = as_path(path, "data file")
    raw = read_bytes(path, "C3D")
    header = check_c3d_header(path, raw)
    extracted = _extract_in_child(path, len(raw), timeout) if isolate else None
    if extracted is None:
        try:
            extracted = _c3d_child.extract(str(path))
        except (RuntimeError, OSError, ValueError, TypeError, KeyError, MemoryError, IndexError,
                UnicodeDecodeError) as exc:
            raise FormatError(f"{path}: ezc3d cannot read the file ({' '.join(str(exc).split())[:200]})",
                              "check that the file is a valid C3D file") from None
    return _to_marker_data(path, *extracted, header)


_CHILD_SOURCE: str | None = None


def _child_source() -> str:
    global _CHILD_SOURCE
    if _CHILD_SOURCE is None:
        _CHILD_SOURCE = Path(_c3d_child.__file__).read_text(encoding="utf-8")
    return _CHILD_SOURCE


def _extract_in_child(path: Path, size: int, timeout: float | None):
    """``(points, residuals, info)`` read by ezc3d in a child process; None if no child can be started."""
    if timeout is None:
        timeout = 20.0 + 2.0 * size / 1e6
    limit = _MEMORY_FLOOR + _MEMORY_PER_BYTE * size
    env = dict(os.environ)
    env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
    with tempfile.TemporaryDirectory(prefix="skelid-c3d-") as tmp:
        out = Path(tmp) / "points.npz"
        cmd = [sys.executable, "-c", _child_source(), str(path.resolve()), str(out), str(limit)]
        try:
            proc = subprocess.run(cmd, stdin=subprocess.DEVNULL, capture_output=True, timeout=timeout,
                                  env=env, cwd=tmp)
        except OSError as exc:  # no interpreter to start (embedded Python, exhausted process table)
            warnings.warn(f"{path}: cannot start a child process to read the C3D file ({exc}); reading it in "
                          "this process, unguarded", SkelidWarning, stacklevel=3)
            return None
        except subprocess.TimeoutExpired:
            raise FormatError(f"{path}: reading the C3D file took more than {timeout:.0f} s; the file is "
                              "probably corrupt (a wrong frame or point count)",
                              "check the file, or pass a longer timeout to read_c3d") from None
        if proc.returncode < 0:
            try:
                sig = signal.Signals(-proc.returncode).name
            except ValueError:
                sig = f"signal {-proc.returncode}"
            raise FormatError(f"{path}: ezc3d crashed ({sig}) reading the file; the file is corrupt",
                              "re-export the file from the capture software")
        if proc.returncode != 0:
            lines = [line for line in proc.stderr.decode("utf-8", "replace").splitlines() if line.strip()]
            msg = " ".join(lines[-1].split()) if lines else ""  # the child's one-line report comes last
            if "bad_alloc" in msg or "MemoryError" in msg:
                raise FormatError(f"{path}: the file declares more data than it can hold "
                                  "(ezc3d ran out of memory); the file is corrupt",
                                  "re-export the file from the capture software")
            raise FormatError(f"{path}: ezc3d cannot read the file ({msg[-200:] or f'exit {proc.returncode}'})",
                              "check that the file is a valid C3D file")
        try:
            with np.load(out, allow_pickle=False) as z:
                points, residuals = z["points"], z["residuals"]
                info = json.loads(str(z["info"]))
        except (OSError, ValueError, KeyError) as exc:
            raise FormatError(f"{path}: the C3D reader process returned no data ({exc})") from None
    return points, residuals, info


def _bare(name: str) -> str:
    return name.rsplit(":", 1)[-1]


def _checked_points(path: Path, points, residuals) -> tuple[np.ndarray, np.ndarray]:
    """``points (F, N, 3)`` and ``residuals (F, N)`` as floats, refused if misshapen or empty."""
    points = np.asarray(points, dtype=float)
    residuals = np.asarray(residuals, dtype=float)
    if points.ndim != 3 or points.shape[2] != 3 or residuals.shape != points.shape[:2]:
        raise FormatError(f"{path}: ezc3d returned points of shape {points.shape}; the file is corrupt")
    F, N, _ = points.shape
    if N == 0:
        raise FormatError(f"{path}: the file has no 3-D points (analog data only?)",
                          "export the marker trajectories to the C3D file")
    if F == 0:
        raise FormatError(f"{path}: the file has no frames of 3-D points")
    return points, residuals


def _point_labels(info: dict, n_points: int) -> list[str]:
    """One label per point: the file's, cut or padded to ``n_points``, a blank one named ``point<k>``."""
    labels = [str(s).strip() for s in info.get("labels", [])][:n_points]
    labels += [""] * (n_points - len(labels))
    return [lab or f"point{i + 1}" for i, lab in enumerate(labels)]


def _is_rate(value, types) -> bool:
    """Whether ``value`` is a finite positive number of one of ``types``."""
    return isinstance(value, types) and math.isfinite(value) and value > 0


def _point_rate(path: Path, info: dict, header: dict):
    """The sampling rate: ``POINT:RATE``, else the header's."""
    rate = info.get("rate")
    if _is_rate(rate, (int, float)):
        return rate
    rate = header.get("rate")
    if not _is_rate(rate, float):
        raise FormatError(f"{path}: no valid sampling rate in POINT:RATE ({info.get('rate')!r}) "
                          "nor in the header", "set POINT:RATE in the file")
    return rate


def _with_gaps(points: np.ndarray, residuals: np.ndarray) -> np.ndarray:
    """``points`` with NaN where a point is missing: negative residual, all zeros, or not finite."""
    missing = (residuals < 0) | np.all(points == 0.0, axis=2) | ~np.isfinite(points).all(axis=2)
    return np.where(missing[..., None], np.nan, points)


def _point_units(path: Path, info: dict, positions: np.ndarray) -> str | None:
    """The length unit of ``POINT:UNITS`` (None if absent), the coordinates checked for size in it."""
    units = normalise_units(info.get("units"))
    if units is not None and units not in ("mm", "cm", "m"):
        raise FormatError(f"{path}: POINT:UNITS is {units!r}; only mm, cm and m are supported",
                          "export the file in mm, cm or m")
    check_magnitude(positions, path, units or "(file units)")
    return units


def _computed_indices(labels: list[str], info: dict) -> list[int]:
    """Indices of the computed points: listed in a computed-point group, or named like one."""
    in_groups = {_bare(n) for names in info.get("groups", {}).values() for n in names if n}
    return [i for i, n in enumerate(labels) if _bare(n) in in_groups or n in in_groups
            or COMPUTED_NAME.search(_bare(n))]


def _to_marker_data(path: Path, points, residuals, info: dict, header: dict) -> MarkerData:
    """What the child read as :class:`MarkerData`: the measured markers, the computed points in ``meta``."""
    points, residuals = _checked_points(path, points, residuals)
    N = points.shape[1]
    labels = _point_labels(info, N)
    rate = _point_rate(path, info, header)
    positions = _with_gaps(points, residuals)
    units = _point_units(path, info, positions)
    guessed = units is None
    if guessed:  # guessed here, so that the warning (stacklevel 3) points at read_c3d
        units = guess_units(positions, path)
    computed = _computed_indices(labels, info)
    measured = [i for i in range(N) if i not in set(computed)]
    if not measured:
        raise FormatError(f"{path}: all {N} points are computed (angles, forces, joint centres); "
                          "no marker trajectories", "export the marker trajectories to the C3D file")
    meta = {
        "format": "c3d",
        "header": header,
        "units_guessed": guessed,
        "computed_points": [labels[i] for i in computed],
        "computed": {labels[i]: positions[:, i, :].copy() for i in computed},
        "point_groups": info.get("groups", {}),
    }
    return MarkerData(positions[:, measured, :], tuple(labels[i] for i in measured), float(rate), units,
                      source=str(path), meta=meta)


def bone_points(data: MarkerData) -> dict[str, dict[str, np.ndarray]]:
    """The Plug-in-Gait segment "bones" among a C3D file's computed points.

    Plug-in Gait writes each segment as four points: its origin (``O``) and
    the tips of its anterior (``A``), lateral (``L``) and proximal (``P``) axes,
    each one segment length from the origin (e.g. ``LFEO``, ``LFEA``, ``LFEL``,
    ``LFEP`` for the left femur). Which joint centre each point is depends on the
    segment; see Vicon's Plug-in Gait output specification.

    Parameters
    ----------
    data : MarkerData
        As returned by :func:`read_c3d` (its ``meta["computed"]``).

    Returns
    -------
    dict
        Segment code without a subject prefix (``"LFE"``, ``"PEL"``) -> ``{"origin",
        "anterior", "lateral", "proximal"}`` -> ``(F, 3)`` array in the file's
        units; only segments whose four points are all present.
    """
    found: dict[str, dict[str, np.ndarray]] = {}
    for label, xyz in (data.meta or {}).get("computed", {}).items():
        m = BONE_POINT.match(_bare(label))
        if m:
            found.setdefault(m["segment"], {})[BONE_POINT_NAMES[m["point"]]] = xyz
    return {seg: pts for seg, pts in found.items() if len(pts) == 4}
