"""Qualisys Track Manager TSV exports (tab-separated text).

Layout: header lines ``KEY<TAB>value...`` (``NO_OF_FRAMES``, ``FREQUENCY``,
``NO_OF_MARKERS``, ``MARKER_NAMES``, ``DATA_INCLUDED``, ...), then, in recent
versions, a column line ``Frame<TAB>Time<TAB>name X<TAB>name Y...``, then one
row per frame. Older versions have no column line and no frame or time
columns. Lengths are in millimetres (the Qualisys default; the file does not
say). A marker is missing where its fields are blank or ``NaN``, or where
``X = Y = Z = 0``, which is how Qualisys writes an untracked marker.

Header counts (``NO_OF_FRAMES``) are not trusted: the rows present are read.
The rate is ``FREQUENCY``; a ``Time`` column, where the column line has one, must
increase row by row (rows out of order or pasted from two takes are refused).
A ``.tsv`` file without the Qualisys header is read as a column-header file by
:func:`skelid.io.read_csv`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from skelid.data import MarkerData
from skelid.errors import FormatError
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

#: Header keys that identify a Qualisys TSV file (any of them on line 1).
QUALISYS_KEYS = ("NO_OF_FRAMES", "NO_OF_CAMERAS", "NO_OF_MARKERS", "FREQUENCY", "NO_OF_ANALOG",
                 "ANALOG_FREQUENCY", "DESCRIPTION", "TIME_STAMP", "DATA_INCLUDED", "MARKER_NAMES")


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _header_block(lines: list[str]) -> tuple[dict[str, list[str]], int, list[str] | None]:
    """The header keys (upper case -> non-blank values), the index of the first data line, the column line.

    The header ends at the column line (``Frame<TAB>Time<TAB>...``, returned) or, in files
    without one, at the first line that starts with a number (the column line is then None).
    """
    header: dict[str, list[str]] = {}
    h = 0
    columns = None
    while h < len(lines):
        f = split_fields(lines[h], "\t")
        if f[0] and _is_number(f[0]):
            break  # first data row (files without a column line)
        h += 1
        if f[0].lower() == "frame":
            columns = f
            break
        if f[0]:
            header[f[0].upper()] = [v for v in f[1:] if v]
    return header, h, columns


def _check_included(path: Path, header: dict) -> None:
    """``DATA_INCLUDED``, where given, is 3-D marker data only."""
    included = {v.upper() for v in header.get("DATA_INCLUDED", [])}
    if included - {"3D"}:
        raise FormatError(f"{path}: DATA_INCLUDED is {' '.join(header['DATA_INCLUDED'])!r}; only 3D marker "
                          "data can be read", "export 3D marker trajectories from Qualisys")


def _frequency(path: Path, header: dict) -> float:
    """The sampling rate of the ``FREQUENCY`` line."""
    if "FREQUENCY" not in header or not header["FREQUENCY"]:
        raise FormatError(f"{path}: no FREQUENCY line in the header", "add 'FREQUENCY<TAB><Hz>' to the header")
    return parse_rate(header["FREQUENCY"][0], path, "FREQUENCY")


def _units(path: Path, header: dict) -> str:
    """The length unit of a ``UNITS`` line, else the Qualisys default ``mm``."""
    if not ("UNITS" in header and header["UNITS"]):
        return "mm"
    units = normalise_units(header["UNITS"][0])
    if units not in ("mm", "cm", "m"):
        raise FormatError(f"{path}: UNITS is {header['UNITS'][0]!r}; expected mm, cm or m")
    return units


def _marker_names(path: Path, header: dict, columns: list[str] | None, h: int) -> tuple[list[str], int]:
    """The marker names (``MARKER_NAMES``, else those of the column line) and the index of the first X column.

    Without a column line the index is 0 here; the first data row decides it.
    """
    names = header.get("MARKER_NAMES")
    lead = 0
    if columns is not None:
        coord = [k for k, c in enumerate(columns) if c[-2:].upper() in (" X", " Y", " Z") and len(c) > 2]
        if not coord:
            raise FormatError(f"{path}: line {h}: the column line names no '<marker> X' columns")
        lead = coord[0]
        col_names = [columns[k][:-2] for k in coord[::3]]
        if not names:
            names = col_names
        elif len(col_names) != len(names):
            raise FormatError(f"{path}: MARKER_NAMES lists {len(names)} markers but line {h} has columns for "
                              f"{len(col_names)}", "make the header and the column line agree")
    if not names:
        raise FormatError(f"{path}: no MARKER_NAMES line in the header", "add 'MARKER_NAMES<TAB>name1<TAB>...'")
    return names, lead


def _lead_of_first_row(path: Path, f: list[str], lineno: int, M: int) -> int:
    """Columns before the coordinates in a file without a column line: up to three (frame, time, ...)."""
    if len(f) not in range(3 * M, 3 * M + 4):
        raise FormatError(f"{path}: line {lineno} has {len(f)} fields for {M} markers",
                          "check MARKER_NAMES against the data columns")
    return len(f) - 3 * M


def _data_rows(path: Path, lines: list[str], h: int, M: int, columns: list[str] | None,
               lead: int) -> list[tuple[int, list[str]]]:
    """(line number, coordinate fields) of each non-blank line from ``lines[h]`` on."""
    rows = []
    for i in range(h, len(lines)):
        if not lines[i].strip():
            continue
        f = split_fields(lines[i], "\t")
        if columns is None and i == h:
            lead = _lead_of_first_row(path, f, i + 1, M)
        if len(f) > lead + 3 * M and any(f[lead + 3 * M:]):
            raise FormatError(f"{path}: line {i + 1} has {len(f) - lead} coordinates for {M} markers",
                              "check MARKER_NAMES against the data columns")
        rows.append((i + 1, f[lead: lead + 3 * M]))
    if not rows:
        raise FormatError(f"{path}: no data rows after the header", "check that the file is complete")
    return rows


def _check_time(path: Path, lines: list[str], rows: list[tuple[int, list[str]]], columns: list[str] | None,
                lead: int) -> None:
    """The ``Time`` column of the column line, where there is one, increases row by row
    (:func:`skelid.io._common.time_column`); ``FREQUENCY`` gives the rate."""
    col = next((k for k, c in enumerate((columns or [])[:lead]) if c.lower() == "time"), None)
    if col is None:
        return
    times = []
    for i, _ in rows:
        f = split_fields(lines[i - 1], "\t")
        times.append((i, f[col] if col < len(f) else ""))
    time_column(times, path, "Time")


def read_tsv(path) -> MarkerData:
    """Read a Qualisys TSV export (or, without its header, a column-header TSV).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    MarkerData
        ``positions (F, M, 3)`` in mm; ``meta["header"]`` holds the header keys.

    Raises
    ------
    FormatError
        Naming the file and line, for anything that is not a readable file.
    """
    path = as_path(path, "data file")
    lines = split_lines(read_text(path, "TSV"))
    first = split_fields(lines[0], "\t")[0].upper()
    if first not in QUALISYS_KEYS:
        from skelid.io.csvfile import read_csv

        return read_csv(path)
    header, h, columns = _header_block(lines)
    _check_included(path, header)
    rate = _frequency(path, header)
    units = _units(path, header)
    names, lead = _marker_names(path, header, columns, h)
    M = len(names)
    rows = _data_rows(path, lines, h, M, columns, lead)
    _check_time(path, lines, rows, columns, lead)
    pos = parse_table(rows, 3 * M, path).reshape(len(rows), M, 3)
    pos[np.all(pos == 0.0, axis=2)] = np.nan
    check_magnitude(pos, path, units)
    return MarkerData(pos, tuple(names), rate, units, source=str(path),
                      meta={"format": "qualisys-tsv", "header": header})
