"""OpenSim TRC marker files (tab- or comma-separated text).

Layout: a ``PathFileType`` line, a line of header keys (``DataRate``,
``NumFrames``, ``NumMarkers``, ``Units``, ...) and their values, a line
``Frame# Time name1 <blank> <blank> name2 ...``, a line of ``X1 Y1 Z1 ...``
labels, then one row per frame. Header counts are often wrong, so the reader
trusts the rows and the name line; blank fields and ``NaN`` are missing markers.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from skelid.data import MarkerData
from skelid.errors import FormatError
from skelid.io.atomic import atomic_write


def _split(line: str, sep: str) -> list[str]:
    return [f.strip() for f in line.rstrip("\r\n").split(sep)]


def read_trc(path) -> MarkerData:
    """Read a TRC file.

    Raises
    ------
    FormatError
        Naming the file and line, for anything that is not a readable TRC file.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError:
        raise FormatError(f"{path}: not a text file (TRC files are tab-separated text)",
                          "check that this is a .trc file") from None
    except OSError as exc:
        raise FormatError(f"cannot read {path}: {exc.strerror or exc}") from None
    lines = text.splitlines()
    if len(lines) < 5 or not lines[0].startswith("PathFileType"):
        raise FormatError(f"{path}: line 1 does not start with 'PathFileType'; not a TRC file",
                          "check the file format or the file extension")
    sep = "\t" if "\t" in lines[0] else ","
    keys, vals = _split(lines[1], sep), _split(lines[2], sep)
    header = {k: v for k, v in zip(keys, vals, strict=False) if k}
    try:
        rate = float(header.get("DataRate") or header.get("CameraRate"))
    except (TypeError, ValueError):
        raise FormatError(f"{path}: line 3 has no valid DataRate (got {header.get('DataRate')!r})",
                          "put the sampling rate in Hz under DataRate") from None
    if not (math.isfinite(rate) and rate > 0):
        raise FormatError(f"{path}: DataRate must be a positive number, got {rate}")
    units = (header.get("Units") or "").strip().lower()
    if units not in ("mm", "m", "cm"):
        raise FormatError(f"{path}: line 3 gives units {header.get('Units')!r}; expected mm, cm or m",
                          "set Units in the header")
    name_fields = _split(lines[3], sep)
    if len(name_fields) < 3 or name_fields[0].lower() not in ("frame#", "frame"):
        raise FormatError(f"{path}: line 4 should be 'Frame#, Time, marker names...'")
    names = [n for n in name_fields[2:] if n]
    if not names:
        raise FormatError(f"{path}: line 4 names no markers")
    M = len(names)
    rows = []
    for i, line in enumerate(lines[5:], start=6):
        if not line.strip() or not line.strip(sep + " "):
            continue
        f = _split(line, sep)
        vals = f[2:2 + 3 * M]
        if len(f) > 2 + 3 * M and any(x for x in f[2 + 3 * M:]):
            raise FormatError(f"{path}: line {i} has {len(f) - 2} coordinates for {M} markers",
                              "check that the marker-name line lists every marker")
        vals += [""] * (3 * M - len(vals))
        try:
            rows.append([float(v) if v else math.nan for v in vals])
        except ValueError:
            bad = next(v for v in vals if v and not _isfloat(v))
            raise FormatError(f"{path}: line {i} has a value that is not a number: {bad!r}") from None
    if not rows:
        raise FormatError(f"{path}: no data rows after the header")
    pos = np.array(rows, dtype=float).reshape(len(rows), M, 3)
    if np.any(np.abs(pos[np.isfinite(pos)]) > 1e12):
        raise FormatError(f"{path}: coordinates larger than 1e12 {units}; the file is corrupt")
    return MarkerData(pos, tuple(names), rate, units, source=str(path),
                      meta={"header": header, "format": "trc"})


def _isfloat(v: str) -> bool:
    try:
        float(v)
        return True
    except ValueError:
        return False


def write_trc(path, data: MarkerData) -> None:
    """Write ``data`` as a tab-separated TRC file (2-D data get Z = 0); atomic."""
    path = Path(path)
    pos = data.positions
    if data.dim == 2:
        pos = np.concatenate([pos, np.zeros(pos.shape[:2] + (1,))], axis=2)
    F, M, _ = pos.shape
    with atomic_write(path, newline="\n") as fh:
        fh.write(f"PathFileType\t4\t(X/Y/Z)\t{path.name}\n")
        fh.write("DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\t"
                 "OrigDataStartFrame\tOrigNumFrames\n")
        fh.write(f"{data.rate:.6g}\t{data.rate:.6g}\t{F}\t{M}\t{data.units}\t{data.rate:.6g}\t1\t{F}\n")
        fh.write("Frame#\tTime\t" + "\t".join(f"{n}\t\t" for n in data.names).rstrip("\t") + "\n")
        fh.write("\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, M + 1)) + "\n\n")
        t = data.time
        flat = pos.reshape(F, 3 * M)
        for k in range(F):
            vals = "\t".join("" if not math.isfinite(v) else repr(float(v)) for v in flat[k])
            fh.write(f"{k + 1}\t{t[k]:.6f}\t{vals}\n")


def write_csv(path, data: MarkerData) -> None:
    """Write ``data`` as a flat CSV: ``frame,time,A_x,A_y[,A_z],...``; atomic."""
    axes = "xyz"[: data.dim]
    cols = ["frame", "time"] + [f"{n}_{a}" for n in data.names for a in axes]
    flat = data.positions.reshape(data.n_frames, -1)
    with atomic_write(path, newline="\n") as fh:
        fh.write(f"# units={data.units} rate={data.rate:g}\n")
        fh.write(",".join(cols) + "\n")
        for k in range(data.n_frames):
            vals = ",".join("" if not math.isfinite(v) else repr(float(v)) for v in flat[k])
            fh.write(f"{k + 1},{k / data.rate:.6f},{vals}\n")
