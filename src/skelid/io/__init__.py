"""Readers that return one :class:`~skelid.data.MarkerData`, and writers.

=========================  ==========================  =========================
format                     reader                      extensions
=========================  ==========================  =========================
C3D (ezc3d, guarded)       :func:`read_c3d`            ``.c3d``
OpenSim TRC                :func:`read_trc`            ``.trc``
Vicon Nexus CSV, column    :func:`read_csv`            ``.csv``, ``.txt``
CSV/TXT (``write_csv``)
Qualisys TSV               :func:`read_tsv`            ``.tsv``
=========================  ==========================  =========================

:func:`read_markers` trusts a file's content over its name: it recognises
each format from the first bytes (:func:`sniff_format`) and reads a C3D file
named ``.trc`` as C3D. Only when the content is not recognised does the
extension choose the reader, whose error then says what is wrong; a file with
neither a recognised content nor a marker-file extension (``.xml``,
``.osim``, ``LICENSE``) is refused with one line.
"""

from __future__ import annotations

import codecs

from skelid.data import MarkerData
from skelid.errors import FormatError
from skelid.io.atomic import atomic_write
from skelid.io.c3d import bone_points, check_c3d_header, read_c3d
from skelid.io.csvfile import COORD_COLUMN, FRAME_COLUMN, TIME_COLUMN, VICON_SECTIONS, read_csv
from skelid.io.qualisys import QUALISYS_KEYS, read_tsv
from skelid.io.trc import read_trc, write_csv, write_trc

READERS = {".c3d": read_c3d, ".trc": read_trc, ".csv": read_csv, ".txt": read_csv, ".tsv": read_tsv}

#: Reader for each format name that :func:`sniff_format` returns.
FORMAT_READERS = {"c3d": read_c3d, "trc": read_trc, "vicon-csv": read_csv, "csv": read_csv,
                  "qualisys-tsv": read_tsv}

_SNIFF_BYTES = 8192


def _read_head(path) -> bytes | None:
    """The first :data:`_SNIFF_BYTES` bytes of ``path``, or None if it cannot be read."""
    try:
        with open(path, "rb") as fh:
            return fh.read(_SNIFF_BYTES)
    except OSError:
        return None


def _head_text(head: bytes) -> str | None:
    """The bytes read as text (UTF-16 by its byte-order mark, else UTF-8), or None if binary (NUL bytes)."""
    if head[:2] in (codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE):
        return head[: len(head) // 2 * 2].decode("utf-16", errors="replace")
    if b"\x00" in head:
        return None
    return head.decode("utf-8-sig", errors="replace")


def _binary_format(head: bytes) -> str | None:
    """``"c3d"`` for binary content whose second byte is the C3D key ``0x50``, else None."""
    return "c3d" if len(head) >= 2 and head[1] == 0x50 else None


def _separator(line: str) -> str:
    """The most frequent of tab, comma and semicolon in ``line`` (tab on a tie)."""
    return max(("\t", ",", ";"), key=line.count)


def _is_trc(first: str, field0: str) -> bool:
    """An OpenSim TRC file opens with ``PathFileType``."""
    return first.startswith("PathFileType")


def _is_qualisys(first: str, field0: str) -> bool:
    """A Qualisys TSV export opens with one of its header keys."""
    return field0.upper() in QUALISYS_KEYS


def _is_vicon(first: str, field0: str) -> bool:
    """A Vicon Nexus CSV export opens with a section name (``Trajectories``, ``Devices``, ...)."""
    return field0.lower() in VICON_SECTIONS


#: Formats told by the first non-blank line (and its first field), tried in this order.
_FIRST_LINE_FORMATS = (("trc", _is_trc), ("qualisys-tsv", _is_qualisys), ("vicon-csv", _is_vicon))


def _first_line_format(lines: list[str]) -> str | None:
    """The format that the first non-blank line names, or None."""
    first = next((line for line in lines if line), "")
    field0 = first.split(_separator(first), 1)[0].strip()
    return next((fmt for fmt, test in _FIRST_LINE_FORMATS if test(first, field0)), None)


def _header_fields(lines: list[str], head: bytes) -> list[str] | None:
    """Fields of the first line that is neither blank nor a ``#`` comment (None if there is none).

    When that line is the last one read and the read stopped at :data:`_SNIFF_BYTES`, its
    last field may be cut and is left out.
    """
    k = next((i for i, line in enumerate(lines) if line and not line.startswith("#")), None)
    if k is None:
        return None
    fields = [f.strip() for f in lines[k].split(_separator(lines[k]))]
    if k == len(lines) - 1 and len(head) == _SNIFF_BYTES:
        fields = fields[:-1]  # the header line goes on beyond the bytes read
    return fields


def _is_column_header(fields: list[str]) -> bool:
    """At least two coordinate columns, and every named column a coordinate, time or frame column."""
    coords = sum(1 for f in fields if COORD_COLUMN.match(f))
    return coords >= 2 and all(COORD_COLUMN.match(f) or TIME_COLUMN.match(f) or FRAME_COLUMN.match(f)
                               for f in fields if f)


def sniff_format(path) -> str | None:
    """The format of a marker file from its first bytes, or None if not recognised.

    Returns
    -------
    str or None
        ``"c3d"``, ``"trc"``, ``"vicon-csv"``, ``"qualisys-tsv"``, ``"csv"``.
    """
    head = _read_head(path)
    if head is None:
        return None
    text = _head_text(head)
    if text is None:
        return _binary_format(head)
    lines = [line.strip() for line in text.replace("\r", "\n").split("\n")]
    fmt = _first_line_format(lines)
    if fmt is not None:
        return fmt
    fields = _header_fields(lines, head)
    return "csv" if fields is not None and _is_column_header(fields) else None


def read_markers(path) -> MarkerData:
    """Read a marker file of any supported format.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    MarkerData

    Raises
    ------
    FormatError
        One line naming the file: it does not exist, is not a marker file, or
        is malformed.
    """
    from skelid.io._common import check_regular_file

    path = check_regular_file(path, "data file")
    fmt = sniff_format(path)
    if fmt is not None:
        return FORMAT_READERS[fmt](path)
    reader = READERS.get(path.suffix.lower())
    if reader is None:
        kind = f"file type {path.suffix!r}" if path.suffix else "file without an extension"
        raise FormatError(f"{path}: not a marker file (unsupported {kind}, content not recognised)",
                          f"give a marker file: {', '.join(sorted(READERS))}")
    return reader(path)


__all__ = [
    "read_markers", "read_c3d", "read_trc", "read_csv", "read_tsv", "write_trc", "write_csv",
    "check_c3d_header", "bone_points", "sniff_format", "atomic_write", "READERS", "FORMAT_READERS",
]
