"""Stand-in readers for the shared real files, until ``skelid.io.read_markers`` reads them.

TO BE REPLACED by ``skelid.io.read_markers`` once the C3D, Vicon CSV, Qualisys
TSV and pendulum TXT readers are merged; it exists only so that the tests and
``benchmarks/real_data.py`` can use those files now. It is deliberately small:
it handles the files in ``../shared/data`` and nothing else.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from skelid.data import MarkerData


def read(path) -> MarkerData:
    """Markers of one of the shared files, NaN where missing."""
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        from skelid import io

        if suffix in io.READERS:  # the library's own reader, once it has one
            return io.read_markers(path)
    except ImportError:  # pragma: no cover
        pass
    if suffix == ".c3d":
        return _c3d(path)
    if suffix == ".tsv":
        return _qualisys_tsv(path)
    if suffix == ".csv":
        return _vicon_csv(path)
    if suffix == ".txt":
        return _pendulum_txt(path)
    raise ValueError(f"no stand-in reader for {path}")


def _c3d(path: Path) -> MarkerData:
    import ezc3d

    c = ezc3d.c3d(str(path))
    pts = np.array(c["data"]["points"][:3], dtype=float)  # (3, M, F)
    resid = np.array(c["data"]["meta_points"]["residuals"][0], dtype=float)  # (M, F)
    gone = (resid < 0) | (pts == 0).all(axis=0)
    pts[:, gone] = np.nan
    labels = list(c["parameters"]["POINT"]["LABELS"]["value"])
    units = c["parameters"]["POINT"]["UNITS"]["value"][0].strip()
    rate = float(c["header"]["points"]["frame_rate"])
    return MarkerData(np.moveaxis(pts, 0, -1).transpose(1, 0, 2), labels, rate, units, str(path))


def _qualisys_tsv(path: Path) -> MarkerData:
    lines = path.read_text().splitlines()
    head = {ln.split("\t")[0]: ln.split("\t")[1:] for ln in lines[:11]}
    names = head["MARKER_NAMES"]
    rate = float(head["FREQUENCY"][0])
    start = next(i for i, ln in enumerate(lines) if ln.startswith("Frame\t"))
    rows = [ln.split("\t")[2:] for ln in lines[start + 1:] if ln.strip()]
    a = np.array([[float(x) if x.strip() else np.nan for x in r] for r in rows])
    return MarkerData(a.reshape(len(a), len(names), 3), names, rate, "mm", str(path))


def _vicon_csv(path: Path) -> MarkerData:
    lines = path.read_text().splitlines()
    rate = float(lines[1].split(",")[0])
    label_row = lines[2].split(",")
    names = [label_row[i] for i in range(2, len(label_row), 3)]
    units = lines[4].split(",")[2].strip()
    rows = []
    for ln in lines[5:]:
        cells = ln.split(",")
        if not ln.strip() or not cells[0].strip():
            break  # the trajectories block ends at a blank row
        vals = cells[2:2 + 3 * len(names)]
        vals += [""] * (3 * len(names) - len(vals))
        rows.append([float(x) if x.strip() else np.nan for x in vals])
    a = np.array(rows)
    return MarkerData(a.reshape(len(a), len(names), 3), names, rate, units, str(path))


def _pendulum_txt(path: Path) -> MarkerData:
    header = path.read_text().splitlines()[0].split(",")
    a = np.loadtxt(path, delimiter=",", skiprows=1)
    names = [h.split("_")[0] for h in header[1::3]]
    rate = 1.0 / float(np.median(np.diff(a[:, 0])))
    return MarkerData(a[:, 1:].reshape(len(a), len(names), 3), names, round(rate, 6), "m", str(path))
