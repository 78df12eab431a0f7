"""OpenSim TRC marker files (tab- or comma-separated text).

Layout: a ``PathFileType`` line, a line of header keys (``DataRate``,
``NumFrames``, ``NumMarkers``, ``Units``, ...) and their values, a line
``Frame# Time name1 <blank> <blank> name2 ...``, a line of ``X1 Y1 Z1 ...``
labels, then one row per frame. Header counts are often wrong, so the reader
trusts the rows and the name line; blank fields and ``NaN`` are missing markers.
The sampling rate is ``DataRate``; where the ``Time`` column's mean step per row
differs from ``1 / DataRate`` by more than 5 % (a decimated export), a
:class:`~skelid.errors.SkelidWarning` says so; ``meta["time_step"]`` holds the
step the Time column shows and ``meta["time_start"]`` its first time (None without one).
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from skelid.data import MarkerData
from skelid.errors import DataError, FormatError, SkelidWarning
from skelid.io._common import (
    as_path,
    check_magnitude,
    normalise_units,
    parse_rate,
    parse_table,
    read_text,
    split_fields,
    split_lines,
    time_column,
)
from skelid.io.atomic import atomic_write


def trc_header(lines: list[str], path: Path) -> tuple[str, dict, float, str]:
    """Separator, header keys and values, rate and units from a TRC file's first three lines."""
    sep = "\t" if "\t" in lines[0] else ","
    keys, vals = split_fields(lines[1], sep), split_fields(lines[2], sep)
    header = {k: v for k, v in zip(keys, vals, strict=False) if k}
    rate_text = header.get("DataRate") or header.get("CameraRate")
    if rate_text is None:
        raise FormatError(f"{path}: line 2 has no DataRate key", "put the sampling rate in Hz under DataRate")
    rate = parse_rate(rate_text, path, "DataRate on line 3")
    units = normalise_units(header.get("Units"))
    if units not in ("mm", "m", "cm"):
        raise FormatError(f"{path}: line 3 gives units {header.get('Units')!r}; expected mm, cm or m",
                          "set Units in the header")
    return sep, header, rate, units


def read_trc(path) -> MarkerData:
    """Read a TRC file.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    MarkerData
        ``positions (F, M, 3)`` in the file's units, F = the data rows present.
        ``meta["header"]`` holds the header keys and values as written.

    Raises
    ------
    FormatError
        Naming the file and line, for anything that is not a readable TRC file.
    """
    path = as_path(path, "data file")
    lines = split_lines(read_text(path, "TRC"))
    if not lines[0].lstrip().startswith("PathFileType"):
        raise FormatError(f"{path}: line 1 does not start with 'PathFileType'; not a TRC file",
                          "check the file format or the file extension")
    if len(lines) < 5:
        raise FormatError(f"{path}: only {len(lines)} lines; a TRC file has 5 header lines before the data",
                          "check that the file is complete")
    sep, header, rate, units = trc_header(lines, path)
    name_fields = split_fields(lines[3], sep)
    if len(name_fields) < 3 or name_fields[0].lower() not in ("frame#", "frame"):
        raise FormatError(f"{path}: line 4 should be 'Frame#, Time, marker names...'",
                          "check the header lines of the file")
    names = [n for n in name_fields[2:] if n]
    if not names:
        raise FormatError(f"{path}: line 4 names no markers")
    M = len(names)
    rows, times = [], []
    for i, line in enumerate(lines[5:], start=6):
        if not line.strip(sep + " \t"):
            continue
        f = split_fields(line, sep)
        if len(f) > 2 + 3 * M and any(f[2 + 3 * M:]):
            raise FormatError(f"{path}: line {i} has {len(f) - 2} coordinates for {M} markers",
                              "check that the marker-name line lists every marker")
        rows.append((i, f[2:2 + 3 * M]))
        times.append((i, f[1] if len(f) > 1 else ""))
    if not rows:
        raise FormatError(f"{path}: no data rows after the header", "check that the file is complete")
    pos = parse_table(rows, 3 * M, path).reshape(len(rows), M, 3)
    check_magnitude(pos, path, units)
    step = _time_step(times, path)
    if step is not None and abs(step * rate - 1.0) > 0.05:
        warnings.warn(f"{path}: the Time column advances {step:.6g} s per row but DataRate says {rate:g} Hz "
                      f"({1 / rate:.6g} s); using DataRate (the rows may be decimated)", SkelidWarning, stacklevel=2)
    start = next((float(v) for _i, v in times if v.strip()), None)  # checked by _time_step
    return MarkerData(pos, tuple(names), rate, units, source=str(path),
                      meta={"header": header, "format": "trc", "time_step": step, "time_start": start})


def _time_step(times: list[tuple[int, str]], path: Path) -> float | None:
    """Mean step of the Time column; None where the column is blank (DataRate alone gives the rate).

    The column is checked as every text reader checks its time column
    (:func:`skelid.io._common.time_column`): numbers that increase row by row.
    """
    t = time_column(times, path, "Time")
    if t is None or t.size < 2:
        return None
    with np.errstate(over="ignore"):
        step = (t[-1] - t[0]) / (t.size - 1)
    return float(step) if math.isfinite(step) and step > 0 else None


def _number(x: float) -> str:
    """Shortest text that reads back as exactly ``x``."""
    short = f"{x:.15g}"
    return short if float(short) == x else repr(float(x))


def _check_names(data: MarkerData, sep: str, fmt: str) -> None:
    for n in data.names:
        if not n or n != n.strip() or any(c in n for c in (sep, "\n", "\r")):
            raise DataError(f"marker name {n!r} cannot be written to a {fmt} file",
                            f"rename the marker: no {sep!r}, line breaks or blanks at either end")


def write_trc(path, data: MarkerData) -> None:
    """Write ``data`` as a tab-separated TRC file; atomic.

    2-D data get Z = 0 where the marker is present (blank where it is missing).
    Values are written with full precision, so :func:`read_trc` gives back the
    same numbers.
    """
    path = Path(path)
    _check_names(data, "\t", "TRC")
    pos = data.positions
    if data.dim == 2:
        z = np.where(np.isfinite(pos).all(axis=2, keepdims=True), 0.0, np.nan)
        pos = np.concatenate([pos, z], axis=2)
    F, M, _ = pos.shape
    rate = _number(data.rate)
    with atomic_write(path, newline="\n") as fh:
        fh.write(f"PathFileType\t4\t(X/Y/Z)\t{path.name}\n")
        fh.write("DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\t"
                 "OrigDataStartFrame\tOrigNumFrames\n")
        fh.write(f"{rate}\t{rate}\t{F}\t{M}\t{data.units}\t{rate}\t1\t{F}\n")
        fh.write("Frame#\tTime\t" + "\t".join(f"{n}\t\t" for n in data.names).rstrip("\t") + "\n")
        fh.write("\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, M + 1)) + "\n\n")
        t = data.time
        flat = pos.reshape(F, 3 * M)
        for k in range(F):
            vals = "\t".join("" if not math.isfinite(v) else _number(v) for v in flat[k])
            fh.write(f"{k + 1}\t{t[k]:.6f}\t{vals}\n")


def write_csv(path, data: MarkerData) -> None:
    """Write ``data`` as a flat CSV: ``frame,time,A_x,A_y[,A_z],...``; atomic.

    The first line is a comment ``# units=mm rate=100``; a missing marker is a
    blank field. :func:`skelid.io.read_csv` reads it back exactly.
    """
    _check_names(data, ",", "CSV")
    axes = "xyz"[: data.dim]
    cols = ["frame", "time"] + [f"{n}_{a}" for n in data.names for a in axes]
    flat = data.positions.reshape(data.n_frames, -1)
    with atomic_write(path, newline="\n") as fh:
        fh.write(f"# units={data.units} rate={_number(data.rate)}\n")
        fh.write(",".join(cols) + "\n")
        for k in range(data.n_frames):
            vals = ",".join("" if not math.isfinite(v) else _number(v) for v in flat[k])
            fh.write(f"{k + 1},{k / data.rate:.6f},{vals}\n")
