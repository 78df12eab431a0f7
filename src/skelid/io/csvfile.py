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
within 1 %. Blank fields and ``NaN`` are missing; ``0,0,0`` is a valid
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
    check_magnitude,
    guess_units,
    normalise_units,
    parse_number,
    parse_rate,
    parse_table,
    read_text,
    sniff_separator,
    split_fields,
    split_lines,
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
    path = Path(path)
    lines = split_lines(read_text(path, "CSV"))
    first = next((i for i, line in enumerate(lines) if line.strip()), None)
    if first is None:
        raise FormatError(f"{path}: the file is empty", "check that the file is complete")
    sep = sniff_separator(lines[first])
    if split_fields(lines[first], sep)[0].lower() in VICON_SECTIONS:
        return _read_vicon(path, lines)
    return _read_columns(path, lines)


# --------------------------------------------------------------------- Vicon
def _read_vicon(path: Path, lines: list[str]) -> MarkerData:
    start = next((i for i, line in enumerate(lines) if line.split(",", 1)[0].strip().lower() == "trajectories"),
                 None)
    if start is None:
        raise FormatError(f"{path}: Vicon CSV without a 'Trajectories' section; no marker data",
                          "export the trajectories from Nexus")
    if len(lines) < start + 6:
        raise FormatError(f"{path}: the Trajectories section (line {start + 1}) ends before its data",
                          "check that the file is complete")
    sep = ","
    rate = parse_rate(split_fields(lines[start + 1], sep)[0], path, f"the rate on line {start + 2}")
    name_fields = split_fields(lines[start + 2], sep)
    last = max((i for i, n in enumerate(name_fields) if n), default=-1)
    if last < 2:
        raise FormatError(f"{path}: line {start + 3} names no markers")
    M = (last - 2) // 3 + 1
    names = []
    for k, field in enumerate(name_fields[: 2 + 3 * M]):
        if k >= 2 and (k - 2) % 3 == 0:
            if not field:
                raise FormatError(f"{path}: line {start + 3}, column {k + 1}: marker name missing",
                                  "every marker takes three columns X, Y, Z with its name above X")
            names.append(field)
        elif field:
            raise FormatError(f"{path}: line {start + 3}, column {k + 1}: {field!r} is not above an X column",
                              "every marker takes three columns X, Y, Z with its name above X")
    axes = split_fields(lines[start + 3], sep)
    want = ["X", "Y", "Z"] * M
    got = [a.upper() for a in axes[2: 2 + 3 * M]]
    if got != want:
        raise FormatError(f"{path}: line {start + 4} should read 'Frame,Sub Frame' then X,Y,Z for each of the "
                          f"{M} markers", "check the header lines of the Trajectories section")
    unit_set = {u for u in split_fields(lines[start + 4], sep)[2: 2 + 3 * M] if u}
    if len(unit_set) > 1:
        raise FormatError(f"{path}: line {start + 5} mixes units {sorted(unit_set)}",
                          "export all trajectories in one unit")
    units = normalise_units(unit_set.pop()) if unit_set else None
    if units is not None and units not in ("mm", "cm", "m"):
        raise FormatError(f"{path}: line {start + 5} gives units {units!r}; expected mm, cm or m")
    rows = []
    for i in range(start + 5, len(lines)):
        f = split_fields(lines[i], sep)
        if not any(f):
            break  # end of the section
        if len(f) > 2 + 3 * M and any(f[2 + 3 * M:]):
            raise FormatError(f"{path}: line {i + 1} has {len(f) - 2} coordinates for {M} markers",
                              "check that the marker-name line lists every marker")
        rows.append((i + 1, f[2: 2 + 3 * M]))
    if not rows:
        raise FormatError(f"{path}: no data rows in the Trajectories section", "check that the file is complete")
    pos = parse_table(rows, 3 * M, path).reshape(len(rows), M, 3)
    check_magnitude(pos, path, units or "(file units)")
    guessed = units is None
    if guessed:
        units = guess_units(pos, path)
    return MarkerData(pos, tuple(names), rate, units, source=str(path),
                      meta={"format": "vicon-csv", "units_guessed": guessed})


# ------------------------------------------------------------------- columns
def _read_columns(path: Path, lines: list[str]) -> MarkerData:
    comment: dict[str, str] = {}
    h = 0
    while h < len(lines) and (not lines[h].strip() or lines[h].lstrip().startswith("#")):
        comment.update({k.lower(): v for k, v in _KEY_VALUE.findall(lines[h])})
        h += 1
    if h == len(lines):
        raise FormatError(f"{path}: no header line naming the columns", "add a header line such as 'time,A_x,A_y,A_z'")
    sep = sniff_separator(lines[h])
    head = split_fields(lines[h], sep)
    while head and not head[-1]:
        head.pop()
    if not any(COORD_COLUMN.match(text) for text in head):
        shown = lines[h].strip()
        shown = shown if len(shown) <= 40 else shown[:37] + "..."
        raise FormatError(f"{path}: not a marker table: line {h + 1} ({shown!r}) names no coordinate columns",
                          "give a marker file whose header names columns '<marker>_x', '<marker>_y', '<marker>_z'")
    time_col = frame_col = None
    groups: list[tuple[str, list[str], list[int], list[str]]] = []  # name, axes, columns, units
    for c, text in enumerate(head):
        if TIME_COLUMN.match(text) and time_col is None:
            time_col = c
            continue
        if FRAME_COLUMN.match(text) and frame_col is None:
            frame_col = c
            continue
        m = COORD_COLUMN.match(text)
        if m is None and (TIME_COLUMN.match(text) or FRAME_COLUMN.match(text)):
            raise FormatError(f"{path}: line {h + 1}, column {c + 1}: a second {text!r} column",
                              "keep one time column and one frame column")
        if m is None:
            shown = text if len(text) <= 30 else text[:27] + "..."
            raise FormatError(f"{path}: line {h + 1}, column {c + 1}: {shown!r} is neither a time, a frame nor a "
                              "coordinate column", "name coordinate columns '<marker>_x', '<marker>_y', '<marker>_z'")
        name, axis, unit = m["name"], m["axis"].lower(), m["unit"]
        if groups and groups[-1][0] == name and groups[-1][2][-1] == c - 1:
            groups[-1][1].append(axis)
            groups[-1][2].append(c)
            groups[-1][3].append(unit or "")
        else:
            groups.append((name, [axis], [c], [unit or ""]))
    dims = {"".join(g[1]) for g in groups}
    bad = next((g for g in groups if "".join(g[1]) not in ("xy", "xyz")), None)
    if bad is not None or len(dims) != 1:
        g = bad or groups[0]
        raise FormatError(f"{path}: line {h + 1}: marker {g[0]!r} has columns {''.join(g[1]).upper()}; every "
                          "marker needs X, Y (and Z) in that order, the same for all markers",
                          "check the header line for a missing, repeated or misplaced column")
    names = [g[0] for g in groups]
    D = len(groups[0][1])
    units = _units_of(path, h, groups, comment)
    cols = [c for g in groups for c in g[2]]
    rows, times = [], []
    for i in range(h + 1, len(lines)):
        line = lines[i]
        if not line.strip(sep + " \t") or line.lstrip().startswith("#"):
            continue
        f = split_fields(line, sep)
        if len(f) > len(head) and any(f[len(head):]):
            raise FormatError(f"{path}: line {i + 1} has {len(f)} fields but the header names {len(head)} columns",
                              "check the header line and the separators")
        f += [""] * (len(head) - len(f))
        rows.append((i + 1, [f[c] for c in cols]))
        if time_col is not None:
            times.append((i + 1, f[time_col]))
    if not rows:
        raise FormatError(f"{path}: no data rows after the header", "check that the file is complete")
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
    if "rate" in comment:
        return parse_rate(comment["rate"], path, "the rate in the comment line")
    if len(times) < 2:
        raise FormatError(f"{path}: no sampling rate: no '# rate=' comment and "
                          f"{'only one row' if times else 'no time column'}",
                          "add a time column or a first line '# rate=<Hz>'")
    t = np.array([parse_number(v, path, f"the time on line {i}") for i, v in times])
    with np.errstate(over="ignore", invalid="ignore"):
        dt = np.diff(t)
    if np.any(dt <= 0):
        k = int(np.argmax(dt <= 0))
        raise FormatError(f"{path}: line {times[k + 1][0]}: time {t[k + 1]:g} does not increase",
                          "sort the rows by time and remove repeated rows")
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
