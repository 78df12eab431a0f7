"""Delimited text marker files: Vicon Nexus CSV and column-header CSV/TXT.

:func:`read_csv` looks at the header and reads either layout:

**Vicon Nexus export.** A section line ``Trajectories``, the rate, the marker
names (one every three columns, with their ``Subject:`` prefix), ``Frame,Sub
Frame,X,Y,Z,...``, a units line (``mm``), then one row per frame until a blank
line or the end of the file. Other sections (``Devices``, ``Model Outputs``)
are skipped. A blank field is a missing marker.

**Column header.** Optional ``#`` comment lines with ``key=value`` pairs
(``# units=mm rate=100``, as :func:`skelid.io.write_csv` writes), then one
header line naming every column, then one row per frame. A column is the time
(``t``, ``time``, ``t(s)``), a frame number (``frame``, ``Frame#``) or a
coordinate ``<marker><sep><axis>[ (unit)]`` with ``sep`` one of ``_``, space,
``.`` or ``:`` and ``axis`` X, Y or Z (``m1_X (m)``, ``LASI_x``). Each marker
has X, Y and optionally Z columns, in that order; all markers have the same
number. Units come from the column headers or the comment; the rate from the
comment or, failing that, from the time column:

.. math:: \\text{rate} = 1 / \\operatorname{median}_k (t_{k+1} - t_k),

with a :class:`~skelid.errors.SkelidWarning` if the steps are not uniform to
within 1 %. A time column, where there is one, must increase row by row (also when
the comment gives the rate): rows out of order, repeated or pasted from two takes
are refused with their line. Blank fields and ``NaN`` are missing; ``0,0,0`` is a valid
position here (a pendulum's pivot sits at the origin).
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from skelid.data import MarkerData
from skelid.errors import FormatError, SkelidWarning
from skelid.io._common import (
    as_path,
    check_magnitude,
    guess_units,
    normalise_units,
    parse_rate,
    parse_table,
    read_text,
    sniff_separator,
    split_fields,
    split_lines,
    time_column,
)

VICON_SECTIONS = ("trajectories", "devices", "joints", "model outputs", "segments")

TIME_COLUMN = re.compile(r"^(t|time)\s*([\(\[]\s*(s|sec|seconds)\s*[\)\]])?$", re.I)
FRAME_COLUMN = re.compile(r"^(frame\s*#?|frame[ _]?(number|no\.?)|sample|index)$", re.I)
COORD_COLUMN = re.compile(
    r"^(?P<name>.*?\S)\s*[_ .:]\s*(?P<axis>[xyz])\s*(?:[\(\[]\s*(?P<unit>[^\)\]]*?)\s*[\)\]])?$", re.I)
_KEY_VALUE = re.compile(r"([A-Za-z_]+)\s*=\s*(\S+)")


def read_csv(path) -> MarkerData:
    """Read a Vicon Nexus CSV export or a column-header CSV/TXT file.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    MarkerData
        ``positions (F, M, D)`` in the file's units (D = 2 or 3); the names as
        written in the file (a Vicon ``Subject:`` prefix is kept).

    Raises
    ------
    FormatError
        Naming the file and line, for anything that is not a readable file of
        either layout.
    """
    path = as_path(path, "data file")
    lines = split_lines(read_text(path, "CSV"))
    first = next((i for i, line in enumerate(lines) if line.strip()), None)
    if first is None:
        raise FormatError(f"{path}: the file is empty", "check that the file is complete")
    sep = sniff_separator(lines[first])
    if split_fields(lines[first], sep)[0].lower() in VICON_SECTIONS:
        return _read_vicon(path, lines)
    return _read_columns(path, lines)


# --------------------------------------------------------------------- Vicon
_VICON_NAME_FIX = "every marker takes three columns X, Y, Z with its name above X"


def _trajectories_start(path: Path, lines: list[str]) -> int:
    """Index of the ``Trajectories`` section line, refused if absent or too short for its header."""
    start = next((i for i, line in enumerate(lines) if line.split(",", 1)[0].strip().lower() == "trajectories"),
                 None)
    if start is None:
        raise FormatError(f"{path}: Vicon CSV without a 'Trajectories' section; no marker data",
                          "export the trajectories from Nexus")
    if len(lines) < start + 6:
        raise FormatError(f"{path}: the Trajectories section (line {start + 1}) ends before its data",
                          "check that the file is complete")
    return start


def _vicon_names(path: Path, line: str, lineno: int) -> list[str]:
    """The marker names of the name line: one above each X column, from the third column on."""
    name_fields = split_fields(line, ",")
    last = max((i for i, n in enumerate(name_fields) if n), default=-1)
    if last < 2:
        raise FormatError(f"{path}: line {lineno} names no markers")
    M = (last - 2) // 3 + 1
    names = []
    for k, field in enumerate(name_fields[: 2 + 3 * M]):
        if k >= 2 and (k - 2) % 3 == 0:
            if not field:
                raise FormatError(f"{path}: line {lineno}, column {k + 1}: marker name missing", _VICON_NAME_FIX)
            names.append(field)
        elif field:
            raise FormatError(f"{path}: line {lineno}, column {k + 1}: {field!r} is not above an X column",
                              _VICON_NAME_FIX)
    return names


def _check_vicon_axes(path: Path, line: str, lineno: int, M: int) -> None:
    """The axis line reads ``Frame,Sub Frame`` then X, Y, Z for each of the ``M`` markers."""
    got = [a.upper() for a in split_fields(line, ",")[2: 2 + 3 * M]]
    if got != ["X", "Y", "Z"] * M:
        raise FormatError(f"{path}: line {lineno} should read 'Frame,Sub Frame' then X,Y,Z for each of the "
                          f"{M} markers", "check the header lines of the Trajectories section")


def _vicon_units(path: Path, line: str, lineno: int, M: int) -> str | None:
    """The one length unit of the units line (None if blank); mixed or unknown units are refused."""
    unit_set = {u for u in split_fields(line, ",")[2: 2 + 3 * M] if u}
    if len(unit_set) > 1:
        raise FormatError(f"{path}: line {lineno} mixes units {sorted(unit_set)}",
                          "export all trajectories in one unit")
    units = normalise_units(unit_set.pop()) if unit_set else None
    if units is not None and units not in ("mm", "cm", "m"):
        raise FormatError(f"{path}: line {lineno} gives units {units!r}; expected mm, cm or m")
    return units


def _vicon_rows(path: Path, lines: list[str], first: int, M: int) -> list[tuple[int, list[str]]]:
    """(line number, coordinate fields) of each data row from ``lines[first]`` to the first blank line."""
    rows = []
    for i in range(first, len(lines)):
        f = split_fields(lines[i], ",")
        if not any(f):
            break  # end of the section
        if len(f) > 2 + 3 * M and any(f[2 + 3 * M:]):
            raise FormatError(f"{path}: line {i + 1} has {len(f) - 2} coordinates for {M} markers",
                              "check that the marker-name line lists every marker")
        rows.append((i + 1, f[2: 2 + 3 * M]))
    if not rows:
        raise FormatError(f"{path}: no data rows in the Trajectories section", "check that the file is complete")
    return rows


def _read_vicon(path: Path, lines: list[str]) -> MarkerData:
    """The Trajectories section of a Vicon Nexus CSV export: rate, names, axes, units, then the rows."""
    start = _trajectories_start(path, lines)
    rate = parse_rate(split_fields(lines[start + 1], ",")[0], path, f"the rate on line {start + 2}")
    names = _vicon_names(path, lines[start + 2], start + 3)
    M = len(names)
    _check_vicon_axes(path, lines[start + 3], start + 4, M)
    units = _vicon_units(path, lines[start + 4], start + 5, M)
    rows = _vicon_rows(path, lines, start + 5, M)
    pos = parse_table(rows, 3 * M, path).reshape(len(rows), M, 3)
    check_magnitude(pos, path, units or "(file units)")
    guessed = units is None
    if guessed:
        units = guess_units(pos, path)
    return MarkerData(pos, tuple(names), rate, units, source=str(path),
                      meta={"format": "vicon-csv", "units_guessed": guessed})


# ------------------------------------------------------------------- columns
#: one marker's columns: name, axes (``x``, ``y``, ``z``), column indices, units written in the headers
_Group = tuple[str, list[str], list[int], list[str]]


def _comment_block(path: Path, lines: list[str]) -> tuple[dict[str, str], int]:
    """``key=value`` pairs of the leading blank and ``#`` lines, and the index of the header line after them."""
    comment: dict[str, str] = {}
    h = 0
    while h < len(lines) and (not lines[h].strip() or lines[h].lstrip().startswith("#")):
        comment.update({k.lower(): v for k, v in _KEY_VALUE.findall(lines[h])})
        h += 1
    if h == len(lines):
        raise FormatError(f"{path}: no header line naming the columns", "add a header line such as 'time,A_x,A_y,A_z'")
    return comment, h


def _header_names(path: Path, line: str, h: int, sep: str) -> list[str]:
    """The column names of the header line (trailing blanks dropped); refused if none is a coordinate."""
    head = split_fields(line, sep)
    while head and not head[-1]:
        head.pop()
    if not any(COORD_COLUMN.match(text) for text in head):
        shown = line.strip()
        shown = shown if len(shown) <= 40 else shown[:37] + "..."
        raise FormatError(f"{path}: not a marker table: line {h + 1} ({shown!r}) names no coordinate columns",
                          "give a marker file whose header names columns '<marker>_x', '<marker>_y', '<marker>_z'")
    return head


def _not_a_coordinate(path: Path, h: int, c: int, text: str) -> FormatError:
    """The error for a column that is not a coordinate: a second time or frame column, or an unknown one."""
    if TIME_COLUMN.match(text) or FRAME_COLUMN.match(text):
        return FormatError(f"{path}: line {h + 1}, column {c + 1}: a second {text!r} column",
                           "keep one time column and one frame column")
    shown = text if len(text) <= 30 else text[:27] + "..."
    return FormatError(f"{path}: line {h + 1}, column {c + 1}: {shown!r} is neither a time, a frame nor a "
                       "coordinate column", "name coordinate columns '<marker>_x', '<marker>_y', '<marker>_z'")


def _add_coordinate(groups: list[_Group], m: re.Match, c: int) -> None:
    """Put coordinate column ``c`` in its marker's group: the last one if it continues it, else a new one."""
    name, axis, unit = m["name"], m["axis"].lower(), m["unit"]
    if groups and groups[-1][0] == name and groups[-1][2][-1] == c - 1:
        groups[-1][1].append(axis)
        groups[-1][2].append(c)
        groups[-1][3].append(unit or "")
    else:
        groups.append((name, [axis], [c], [unit or ""]))


def _classify_columns(path: Path, h: int, head: list[str]) -> tuple[int | None, int | None, list[_Group]]:
    """The time column, the frame column (the first of each; None if absent) and the markers' column groups."""
    time_col = frame_col = None
    groups: list[_Group] = []
    for c, text in enumerate(head):
        if TIME_COLUMN.match(text) and time_col is None:
            time_col = c
            continue
        if FRAME_COLUMN.match(text) and frame_col is None:
            frame_col = c
            continue
        m = COORD_COLUMN.match(text)
        if m is None:
            raise _not_a_coordinate(path, h, c, text)
        _add_coordinate(groups, m, c)
    return time_col, frame_col, groups


def _check_groups(path: Path, h: int, groups: list[_Group]) -> None:
    """Every marker has columns X, Y or X, Y, Z in that order, the same for all markers."""
    dims = {"".join(g[1]) for g in groups}
    bad = next((g for g in groups if "".join(g[1]) not in ("xy", "xyz")), None)
    if bad is not None or len(dims) != 1:
        g = bad or groups[0]
        raise FormatError(f"{path}: line {h + 1}: marker {g[0]!r} has columns {''.join(g[1]).upper()}; every "
                          "marker needs X, Y (and Z) in that order, the same for all markers",
                          "check the header line for a missing, repeated or misplaced column")


def _column_rows(path: Path, lines: list[str], h: int, sep: str, n_head: int, cols: list[int],
                 time_col: int | None) -> tuple[list[tuple[int, list[str]]], list[tuple[int, str]]]:
    """(line number, coordinate fields) of each data row after the header, and (line number, time) of each.

    Blank and ``#`` lines are skipped; a short row is padded with blanks; a row with
    values beyond the ``n_head`` named columns is refused.
    """
    rows, times = [], []
    for i in range(h + 1, len(lines)):
        line = lines[i]
        if not line.strip(sep + " \t") or line.lstrip().startswith("#"):
            continue
        f = split_fields(line, sep)
        if len(f) > n_head and any(f[n_head:]):
            raise FormatError(f"{path}: line {i + 1} has {len(f)} fields but the header names {n_head} columns",
                              "check the header line and the separators")
        f += [""] * (n_head - len(f))
        rows.append((i + 1, [f[c] for c in cols]))
        if time_col is not None:
            times.append((i + 1, f[time_col]))
    if not rows:
        raise FormatError(f"{path}: no data rows after the header", "check that the file is complete")
    return rows, times


def _read_columns(path: Path, lines: list[str]) -> MarkerData:
    """A column-header file: comment, header line, column groups, units, rows, then the rate."""
    comment, h = _comment_block(path, lines)
    sep = sniff_separator(lines[h])
    head = _header_names(path, lines[h], h, sep)
    time_col, _, groups = _classify_columns(path, h, head)
    _check_groups(path, h, groups)
    names = [g[0] for g in groups]
    D = len(groups[0][1])
    units = _units_of(path, h, groups, comment)
    cols = [c for g in groups for c in g[2]]
    rows, times = _column_rows(path, lines, h, sep, len(head), cols, time_col)
    pos = parse_table(rows, len(cols), path).reshape(len(rows), len(names), D)
    rate = _rate_of(path, comment, times)
    check_magnitude(pos, path, units or "(file units)")
    guessed = units is None
    if guessed:
        units = guess_units(pos, path)
    return MarkerData(pos, tuple(names), rate, units, source=str(path),
                      meta={"format": "csv", "units_guessed": guessed, "comment": comment})


def _units_of(path: Path, h: int, groups, comment: dict) -> str | None:
    found = {normalise_units(u) for g in groups for u in g[3] if u}
    if "units" in comment:
        found.add(normalise_units(comment["units"]))
    found.discard(None)
    if len(found) > 1:
        raise FormatError(f"{path}: line {h + 1} mixes units {sorted(found)}", "use one length unit for all columns")
    if not found:
        return None
    units = found.pop()
    if units not in ("mm", "cm", "m"):
        raise FormatError(f"{path}: units {units!r}; expected mm, cm or m",
                          "write the unit in the header, e.g. 'A_x (mm)' or '# units=mm'")
    return units


def _rate_of(path: Path, comment: dict, times: list[tuple[int, str]]) -> float:
    """The rate of the ``# rate=`` comment, else of the time column's median step.

    A time column is checked either way (:func:`skelid.io._common.time_column`): rows out of
    order are refused even where the comment gives the rate.
    """
    t = time_column(times, path)
    if "rate" in comment:
        return parse_rate(comment["rate"], path, "the rate in the comment line")
    if t is None or t.size < 2:
        why = "no time column" if not times else "an empty time column" if t is None else "only one row"
        raise FormatError(f"{path}: no sampling rate: no '# rate=' comment and {why}",
                          "add a time column or a first line '# rate=<Hz>'")
    with np.errstate(over="ignore", invalid="ignore"):
        dt = np.diff(t)
    if not np.all(np.isfinite(dt)):
        raise FormatError(f"{path}: time values too large to give a sampling rate", "check the time column")
    step = float(np.median(dt))
    if np.max(np.abs(dt - step)) > 0.01 * step:
        warnings.warn(f"{path}: time steps are not uniform (from {dt.min():.6g} to {dt.max():.6g} s); "
                      f"rate taken from the median step", SkelidWarning, stacklevel=3)
    rate = float(f"{1.0 / step:.6g}")
    if not (np.isfinite(rate) and rate > 0):
        raise FormatError(f"{path}: time steps of {step:g} s give no usable sampling rate",
                          "check the time column or add a first line '# rate=<Hz>'")
    return rate
