"""Helpers shared by the text readers: decoding, line splitting, number tables.

Every failure becomes a :class:`~skelid.errors.FormatError` naming the file
and, where there is one, the line. Nothing here trusts a count written in a
header: tables are sized by the rows actually present.
"""

from __future__ import annotations

import codecs
import math
import warnings
from pathlib import Path

import numpy as np

from skelid.errors import FormatError, SkelidWarning

#: Coordinates beyond this size (in the file's units) mean a corrupt file.
MAX_COORDINATE = 1e12


def read_bytes(path: Path, what: str) -> bytes:
    """The bytes of ``path``, or a FormatError naming it."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise FormatError(f"data file {path} does not exist", "check the path") from None
    except IsADirectoryError:
        raise FormatError(f"{path} is a folder, not a {what} file", "give the path of a file") from None
    except MemoryError:
        raise FormatError(f"{path}: too large to read into memory", "split the recording") from None
    except OSError as exc:
        raise FormatError(f"cannot read {path}: {exc.strerror or exc}") from None


def read_text(path: Path, what: str) -> str:
    """Decode a text data file.

    UTF-16 is recognised by its byte-order mark. Otherwise UTF-8 (with or
    without a byte-order mark) is tried first, then Windows-1252, which older
    capture software writes for accented marker names. A file with NUL bytes
    is binary and is refused.
    """
    raw = read_bytes(path, what)
    if raw[:2] in (codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE):
        try:
            text = raw.decode("utf-16")
        except UnicodeDecodeError:
            raise FormatError(f"{path}: not valid UTF-16 text although it starts like it",
                              "save the file again as UTF-8 text") from None
        if "\x00" in text:
            raise FormatError(f"{path}: a NUL character in the text; not a {what} text file",
                              "check the file format or export the file again")
        return text
    if b"\x00" in raw:
        raise FormatError(f"{path}: binary content, not a {what} text file",
                          "check the file format or the file extension")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        return raw.decode("cp1252", errors="replace")


def split_lines(text: str) -> list[str]:
    """Lines without their end-of-line characters (``\\n``, ``\\r\\n`` or ``\\r``).

    Unlike :meth:`str.splitlines`, form feeds and other control characters
    inside a line do not start a new line, so line numbers match an editor's.
    """
    if "\n" not in text and "\r" in text:
        return text.split("\r")
    return [line[:-1] if line.endswith("\r") else line for line in text.split("\n")]


def split_fields(line: str, sep: str) -> list[str]:
    """Fields of one line, stripped of surrounding blanks."""
    return [f.strip() for f in line.split(sep)]


def sniff_separator(line: str) -> str:
    """The field separator of a header line: tab, comma or semicolon."""
    counts = {sep: line.count(sep) for sep in ("\t", ",", ";")}
    return max(counts, key=lambda s: (counts[s], s == "\t"))


def parse_number(text: str, path: Path, where: str) -> float:
    """One finite number from a header field."""
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise FormatError(f"{path}: {where} should be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise FormatError(f"{path}: {where} should be a finite number, got {text!r}")
    return value


def parse_rate(text: str, path: Path, where: str) -> float:
    """A sampling rate: a finite number of Hz within :data:`skelid.data.RATE_RANGE`."""
    from skelid.data import RATE_RANGE

    rate = parse_number(text, path, where)
    if not RATE_RANGE[0] <= rate <= RATE_RANGE[1]:
        raise FormatError(f"{path}: {where} must be a sampling rate between {RATE_RANGE[0]:g} and "
                          f"{RATE_RANGE[1]:g} Hz, got {text!r}", "correct the sampling rate in the file")
    return rate


def time_column(times: list[tuple[int, str]], path: Path, column: str = "time") -> np.ndarray | None:
    """The times of a file's rows in seconds, checked; None where every time field is blank.

    Parameters
    ----------
    times : list of (line number, text)
        The time field of each data row, in file order.
    column : str
        The column's name in the file, for messages.

    Returns
    -------
    (R,) float or None

    Raises
    ------
    FormatError
        Naming the file and line: a time field blank while others are not, a time that is not a
        finite number, or one that does not increase on the row before (a row out of order, a
        repeated row, a jump back where two takes were pasted together). The rows' order is the
        trial's time, so such a file is refused rather than read in a wrong order.
    """
    if not any(v.strip() for _i, v in times):
        return None
    t = np.empty(len(times))
    for k, (i, v) in enumerate(times):
        v = v.strip()
        if not v:
            raise FormatError(f"{path}: line {i}: the {column} field is empty while other rows have one",
                              f"fill in the {column} column of every row, or leave it empty in all of them")
        try:
            t[k] = float(v)
        except ValueError:
            raise FormatError(f"{path}: line {i}: time {v[:20]!r} is not a number",
                              f"check the {column} column") from None
        if not math.isfinite(t[k]):
            raise FormatError(f"{path}: line {i}: time {v[:20]!r} is not a finite number",
                              f"check the {column} column")
    with np.errstate(over="ignore", invalid="ignore"):
        back = ~(np.diff(t) > 0)  # differences of finite numbers; an overflow is +-inf, never NaN
    if back.any():
        k = int(np.argmax(back))
        raise FormatError(f"{path}: line {times[k + 1][0]}: time {t[k + 1]:g} does not increase "
                          f"(line {times[k][0]} has {t[k]:g})",
                          "sort the rows by time and remove repeated rows (or split pasted takes into files)")
    return t


def as_path(path, what: str = "data file", cls=FormatError) -> Path:
    """``path`` (a str or os.PathLike) as a :class:`~pathlib.Path`, or ``cls`` with one line for anything else."""
    import os

    if isinstance(path, bytes):
        path = os.fsdecode(path)
    if not isinstance(path, str | os.PathLike):
        raise cls(f"the {what} must be given as a path (str or pathlib.Path), got {type(path).__name__}",
                  f"give the path of the {what}")
    if not str(path).strip():
        raise cls(f"the {what} path is empty", f"give the path of the {what}")
    if "\0" in str(path):
        raise cls(f"the {what} path {str(path)!r} contains a NUL character", f"give the path of the {what}")
    return Path(path)


def check_regular_file(path, what: str = "data file", cls=FormatError) -> Path:
    """An existing regular file, checked without opening it (a FIFO would block, a device never end).

    Raises ``cls`` with one line for a missing path, a folder, a FIFO, a device or a socket.
    """
    import os
    import stat

    path = as_path(path, what, cls)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise cls(f"{what} {path} does not exist", "check the path") from None
    except OSError as exc:
        raise cls(f"cannot read {what} {path}: {exc.strerror or exc}", "check the path and its permissions") \
            from None
    if stat.S_ISREG(st.st_mode):
        return path
    kind = ("a folder" if stat.S_ISDIR(st.st_mode) else "a named pipe (FIFO)" if stat.S_ISFIFO(st.st_mode)
            else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)
            else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
    raise cls(f"{what} {path} is {kind}, not a file", f"give the path of the {what} itself (a regular file)")


def parse_table(rows: list[tuple[int, list[str]]], n_cols: int, path: Path) -> np.ndarray:
    """Numbers of a table; blank fields and ``NaN`` are missing.

    Parameters
    ----------
    rows : list of (line number, fields)
        Fields of each data row, already cut to the data columns; a short row
        is padded with blanks (missing markers at the end of a row).
    n_cols : int
        Number of data columns.
    path : Path
        For messages.

    Returns
    -------
    (R, n_cols) float
    """
    out = np.empty((len(rows), n_cols), dtype=float)
    nan = math.nan
    for k, (lineno, fields) in enumerate(rows):
        if len(fields) < n_cols:
            fields = fields + [""] * (n_cols - len(fields))
        try:
            out[k] = [float(v) if v else nan for v in fields[:n_cols]]
        except ValueError:
            out[k] = _parse_row_slowly(fields[:n_cols], lineno, path)
    inf = np.isinf(out)
    if inf.any():
        k, col = (int(i) for i in np.argwhere(inf)[0])
        raise FormatError(f"{path}: line {rows[k][0]}, data column {col + 1}: an infinite coordinate",
                          "blank the value (a blank field is a missing marker) or fix it")
    return out


def _parse_row_slowly(fields: list[str], lineno: int, path: Path) -> list[float]:
    values = []
    for col, v in enumerate(fields):
        v = v.strip()
        if not v:
            values.append(math.nan)
            continue
        try:
            values.append(float(v))
        except ValueError:
            shown = v if len(v) <= 20 else v[:17] + "..."
            raise FormatError(f"{path}: line {lineno}, data column {col + 1}: {shown!r} is not a number",
                              "fix or blank the value (a blank field is a missing marker)") from None
    return values


def check_magnitude(positions: np.ndarray, path: Path, units: str) -> None:
    """Refuse coordinates too large to be real (a corrupt file)."""
    finite = positions[np.isfinite(positions)]
    if finite.size and np.max(np.abs(finite)) > MAX_COORDINATE:
        raise FormatError(f"{path}: coordinates larger than {MAX_COORDINATE:g} {units}; the file is corrupt",
                          "re-export the file from the capture software")


def guess_units(positions: np.ndarray, path: Path) -> str:
    """Guess ``"m"`` or ``"mm"`` from the spread of the markers, with a warning.

    A human-sized set of markers spans tenths of a metre to two metres: its
    median distance from the per-frame centroid is below 5 if the unit is the
    metre and far above it in millimetres. Centimetres cannot be told from
    millimetres this way and are never guessed.
    """
    spread = np.nan
    present = np.isfinite(positions).all(axis=-1)
    if present.any():
        counts = present.sum(axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            centre = np.where(present[..., None], positions, 0.0).sum(axis=1, keepdims=True) / counts[..., None]
            dist = np.linalg.norm(positions - centre, axis=-1)
        dist = dist[present & (counts > 1)]
        if dist.size:
            spread = float(np.median(dist))
    units = "m" if np.isfinite(spread) and spread < 5.0 else "mm"
    warnings.warn(f"{path}: no length unit in the file; units guessed as {units!r} "
                  f"(median marker spread {spread:.3g})", SkelidWarning, stacklevel=3)
    return units


def normalise_units(text: str | None) -> str | None:
    """``"mm"``, ``"cm"`` or ``"m"`` for the usual spellings; None if blank; else the text."""
    if text is None:
        return None
    t = text.strip().strip("()[]").strip().lower()
    if not t:
        return None
    aliases = {
        "mm": "mm", "millimeter": "mm", "millimeters": "mm", "millimetre": "mm", "millimetres": "mm",
        "cm": "cm", "centimeter": "cm", "centimeters": "cm", "centimetre": "cm", "centimetres": "cm",
        "m": "m", "meter": "m", "meters": "m", "metre": "m", "metres": "m",
    }
    return aliases.get(t, text.strip())
