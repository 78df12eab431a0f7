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


def sniff_format(path) -> str | None:
    """The format of a marker file from its first bytes, or None if not recognised.

    Returns
    -------
    str or None
        ``"c3d"``, ``"trc"``, ``"vicon-csv"``, ``"qualisys-tsv"``, ``"csv"``.
    """
    try:
        with open(path, "rb") as fh:
            head = fh.read(_SNIFF_BYTES)
    except OSError:
        return None
    if head[:2] in (codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE):
        text = head[: len(head) // 2 * 2].decode("utf-16", errors="replace")
    elif len(head) >= 2 and head[1] == 0x50 and b"\x00" in head:
        return "c3d"
    elif b"\x00" in head:
        return None
    else:
        text = head.decode("utf-8-sig", errors="replace")
    lines = [line.strip() for line in text.replace("\r", "\n").split("\n")]
    first = next((line for line in lines if line), "")
    if first.startswith("PathFileType"):
        return "trc"
    sep = max(("\t", ",", ";"), key=first.count)
    field0 = first.split(sep, 1)[0].strip()
    if field0.upper() in QUALISYS_KEYS:
        return "qualisys-tsv"
    if field0.lower() in VICON_SECTIONS:
        return "vicon-csv"
    k = next((i for i, line in enumerate(lines) if line and not line.startswith("#")), None)
    if k is None:
        return None
    fields = [f.strip() for f in lines[k].split(max(("\t", ",", ";"), key=lines[k].count))]
    if k == len(lines) - 1 and len(head) == _SNIFF_BYTES:
        fields = fields[:-1]  # the header line goes on beyond the bytes read
    coords = sum(1 for f in fields if COORD_COLUMN.match(f))
    if coords >= 2 and all(COORD_COLUMN.match(f) or TIME_COLUMN.match(f) or FRAME_COLUMN.match(f)
                           for f in fields if f):
        return "csv"
    return None


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
