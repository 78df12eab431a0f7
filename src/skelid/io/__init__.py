"""Readers that return one :class:`~skelid.data.MarkerData`, and writers.

``read_markers(path)`` picks the reader from the file's extension.
"""

from pathlib import Path

from skelid.data import MarkerData
from skelid.errors import FormatError
from skelid.io.atomic import atomic_write
from skelid.io.c3d import check_c3d_header, read_c3d
from skelid.io.trc import read_trc, write_csv, write_trc

READERS = {".trc": read_trc, ".c3d": read_c3d}


def read_markers(path) -> MarkerData:
    """Read a marker file of any supported format."""
    path = Path(path)
    if not path.exists():
        raise FormatError(f"data file {path} does not exist", "check the path")
    if path.is_dir():
        raise FormatError(f"{path} is a folder, not a marker file")
    reader = READERS.get(path.suffix.lower())
    if reader is None:
        raise FormatError(f"{path}: unsupported file type {path.suffix!r}",
                          f"use one of: {', '.join(sorted(READERS))}")
    return reader(path)


__all__ = ["read_markers", "read_trc", "read_c3d", "check_c3d_header", "write_trc", "write_csv", "atomic_write",
           "READERS"]
