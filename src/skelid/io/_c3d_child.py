"""The part of the C3D reader that calls ezc3d; runs in a child process.

This module imports nothing from skelid, so that :mod:`skelid.io.c3d` can run
its source with ``python -c`` in a fresh interpreter. It reads one file with
ezc3d and writes what the parent needs to an ``.npz`` file:

- ``points``    (F, N, 3) float: every 3-D point as ezc3d returns it,
- ``residuals`` (F, N) float: the point residuals (negative = not tracked),
- ``info``      JSON text: labels, units, rate, the computed-point groups.

Command line: ``python -c <source> C3D_PATH OUT_NPZ MEMORY_LIMIT_BYTES``.
Exit status 0 on success; 3 with a one-line message on stderr when ezc3d
raises. A crash inside ezc3d ends the child with a signal, which the parent
reports.
"""

import json
import sys

#: Point groups in which Vicon Nexus and Plug-in-Gait list computed points.
COMPUTED_GROUPS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS")


def _values(group: dict, key: str) -> list:
    entry = group.get(key)
    if not isinstance(entry, dict):
        return []
    value = entry.get("value")
    if value is None:
        return []
    if hasattr(value, "tolist"):
        value = value.tolist()
    return value if isinstance(value, list) else [value]


def _point_arrays(data: dict):
    """``points (F, N, 3)`` and ``residuals (F, N)`` from ezc3d's ``data`` (zero points if it holds none).

    ezc3d gives points as ``(4, N, F)`` (homogeneous) and residuals as ``(1, N, F)``;
    residuals of another shape are taken as zero (all tracked).
    """
    import numpy as np

    pts = np.asarray(data["points"], dtype=float)
    if pts.ndim != 3 or pts.shape[0] < 3:
        pts = np.zeros((4, 0, 0))
    points = np.ascontiguousarray(pts[:3].transpose(2, 1, 0))
    res = np.asarray(data.get("meta_points", {}).get("residuals", np.zeros((1, 0, 0))), dtype=float)
    if res.ndim == 3 and res.shape[1:] == pts.shape[1:]:
        residuals = np.ascontiguousarray(res[0].T)
    else:
        residuals = np.zeros(points.shape[:2])
    return points, residuals


def _labels(point: dict) -> list:
    """``POINT:LABELS`` followed by ``LABELS2``, ``LABELS3``, ... for as long as they go on."""
    labels = [str(v) for v in _values(point, "LABELS")]
    k = 2
    while f"LABELS{k}" in point:
        labels += [str(v) for v in _values(point, f"LABELS{k}")]
        k += 1
    return labels


def _groups(point: dict) -> dict:
    """Group name -> labels of the computed-point groups: the usual ones, then those in ``TYPE_GROUPS``."""
    groups = {g: [str(v).strip() for v in _values(point, g)] for g in COMPUTED_GROUPS if g in point}
    for g in _values(point, "TYPE_GROUPS"):
        g = str(g).strip().upper()
        if g and g in point and g not in groups and g != "LABELS":
            groups[g] = [str(v).strip() for v in _values(point, g)]
    return groups


def _header_summary(header: dict) -> dict:
    """The numbers of ezc3d's header summary of the points."""
    return {key: (float(v) if isinstance(v, float) else int(v))
            for key, v in header.get("points", {}).items() if isinstance(v, (int, float))}


def _first_number(values: list):
    """The first value as a float, or None if there is none or it is not a number."""
    try:
        return float(values[0]) if values else None
    except (TypeError, ValueError):
        return None


def extract(path: str):
    """Read ``path`` with ezc3d.

    Returns
    -------
    points : (F, N, 3) float
    residuals : (F, N) float
    info : dict
        ``labels`` (LABELS, LABELS2, ... joined), ``units`` (str or None),
        ``rate`` (float or None), ``groups`` (group name -> labels),
        ``header`` (ezc3d's header summary of the points).
    """
    import ezc3d

    c = ezc3d.c3d(path, extract_forceplat_data=False)
    point = c["parameters"].get("POINT", {})
    points, residuals = _point_arrays(c["data"])
    labels = _labels(point)
    units = _values(point, "UNITS")
    rate = _values(point, "RATE")
    groups = _groups(point)
    header = _header_summary(c["header"])
    info = {
        "labels": labels,
        "units": str(units[0]) if units else None,
        "rate": _first_number(rate),
        "groups": groups,
        "header": header,
    }
    return points, residuals, info


def _limit_memory(limit: int) -> None:
    """Cap the address space so that a corrupt count fails fast instead of swapping."""
    if limit <= 0:
        return
    try:
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (limit, resource.getrlimit(resource.RLIMIT_AS)[1]))
    except (ImportError, ValueError, OSError):  # not on this platform: run without the cap
        pass


def main(argv) -> int:
    path, out, limit = argv[1], argv[2], int(argv[3])
    import ezc3d  # noqa: F401  (imported before the memory cap: its own start-up is not the file's fault)
    import numpy as np

    try:
        vm = 0
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmSize:"):
                    vm = int(line.split()[1]) * 1024
        limit = limit + vm if limit > 0 else 0
    except OSError:
        limit = 0  # no /proc: no reliable base to add the cap to
    _limit_memory(limit)
    try:
        points, residuals, info = extract(path)
        np.savez(out, points=points, residuals=residuals, info=np.array(json.dumps(info)))
    except BaseException as exc:  # noqa: BLE001  (reported to the parent as one line)
        msg = " ".join(f"{type(exc).__name__}: {exc}".split())
        sys.stderr.write(msg[:500] + "\n")
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
