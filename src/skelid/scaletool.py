"""OpenSim's ScaleTool run beside skelid's fit of an OpenSim model: the factors the user's own setup gives.

A biomechanist who scales with OpenSim has a Scale setup file (``*_Setup_Scale.xml``): the generic model,
the static trial, the marker pairs of each measurement and the bodies each one scales. ``skelid fit
MODEL.osim ... --scaletool SETUP.xml`` runs that setup with the ``opensim`` package, exactly as written
(its model, static trial, time range and measurements), and puts ScaleTool's factor of every body and
axis beside skelid's interval: which of them the data contradict, and by how much.

ScaleTool's outputs are written to a temporary folder, never beside the setup; its marker placement
is not run (it does not change the factors).

Examples
--------
>>> rows = compare({"scales": {"femur_r": {"x": {"value": 1.10, "ci95": [1.05, 1.15]}}}},
...                {"scales": {"femur_r": [1.20, 1.20, 1.20]}})
>>> rows[0]["scaletool"], rows[0]["inside"]
(1.2, False)
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import time
from pathlib import Path

from skelid.errors import DataError, SettingError

#: the fix offered where the ``opensim`` package is missing
INSTALL = "install it (pip install opensim, or conda install -c opensim-org opensim), or leave --scaletool out"


def _opensim():
    """The ``opensim`` module, or one line saying how to get it."""
    try:
        import opensim
    except ImportError:
        raise SettingError("--scaletool runs OpenSim's ScaleTool, and the opensim package is not installed",
                           INSTALL) from None
    return opensim


def check_setup(setup) -> Path:
    """The setup file, checked to be an OpenSim Scale setup that names files which exist; one line otherwise.

    Raises
    ------
    SettingError
        Where ``opensim`` is not installed.
    DataError
        Where the file is missing, holds no ``<ScaleTool>``, or names a model or static trial that does
        not exist (paths relative to the setup's folder, as ScaleTool reads them).
    FormatError
        Where it is not well-formed XML.
    """
    from skelid.io._common import check_regular_file
    from skelid.io._xml import read_xml

    path = check_regular_file(setup, "Scale setup file", DataError)
    root = read_xml(path, "Scale setup file").getroot()  # any encoding OpenSim reads; one line where malformed
    tool = root if root.tag == "ScaleTool" else root.find("ScaleTool")
    if tool is None:
        raise DataError(f"{path} holds no <ScaleTool>: it is not an OpenSim Scale setup",
                        "give the setup file OpenSim's ScaleTool reads (e.g. subject01_Setup_Scale.xml)")
    for where, what in (("GenericModelMaker/model_file", "generic model"), ("ModelScaler/marker_file", "static trial")):
        name = (tool.findtext(where) or "").strip()
        if not name or name == "Unassigned":
            raise DataError(f"the Scale setup {path} names no {what} (<{where.split('/')[-1]}>)",
                            f"name the {what} in the setup, as OpenSim's ScaleTool needs it")
        if not (path.parent / name).is_file() and not Path(name).is_file():
            raise DataError(f"the {what} {name} that the Scale setup {path} names does not exist",
                            "fix the path in the setup (relative to the setup's folder)")
    _opensim()
    return path


def run_scaletool(setup) -> dict:
    """OpenSim's ScaleTool on ``setup``: every body's three factors and where they came from.

    Returns
    -------
    dict
        ``setup``, ``generic_model``, ``static_trial``, ``time_range`` (s), ``scaling_order``,
        ``measurements`` (the applied ones), ``scales`` ``{body: [x, y, z]}``, ``cpu_s``, ``wall_s``,
        ``opensim_version``.

    Raises
    ------
    DataError
        Where OpenSim cannot read the setup or its ScaleTool writes no scale set.
    """
    path = check_setup(setup)
    osim = _opensim()
    level = osim.Logger.getLevelString()
    osim.Logger.removeFileSink()  # OpenSim would write opensim.log into the working folder
    osim.Logger.setLevelString("off")  # its progress and missing-mesh lines would flood the terminal
    try:
        with tempfile.TemporaryDirectory() as tmp:
            return _run(osim, path, Path(tmp))
    finally:
        with _quiet_stdout():  # OpenSim announces the level it is set back to on the terminal
            osim.Logger.setLevelString(level)


@contextlib.contextmanager
def _quiet_stdout():
    """File descriptor 1 pointed at the null device while inside (OpenSim's logger writes to it directly)."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def _run(osim, path: Path, tmp: Path) -> dict:
    """:func:`run_scaletool` with OpenSim's outputs redirected into ``tmp``."""
    try:
        tool = osim.ScaleTool(str(path))
    except RuntimeError as exc:
        raise DataError(f"OpenSim could not read the Scale setup {path}: {_first_line(exc)}",
                        "open the setup in OpenSim's Scale tool to see what it lacks") from None
    scaler = tool.getModelScaler()
    if not scaler.getApply():
        raise DataError(f"the Scale setup {path} has its ModelScaler off (<apply>false</apply>): ScaleTool "
                        "would scale nothing", "set <apply>true</apply> in the setup's ModelScaler")
    scaler.setOutputModelFileName(str(tmp / "scaled.osim"))
    scaler.setOutputScaleFileName(str(tmp / "scale_set.xml"))
    tool.getMarkerPlacer().setApply(False)  # the placement moves markers, not factors
    c0, t0 = time.process_time(), time.perf_counter()
    try:
        tool.run()  # False without the marker placement; the scale set written is what counts
    except RuntimeError as exc:
        raise DataError(f"OpenSim's ScaleTool failed on {path}: {_first_line(exc)}",
                        "run the setup in OpenSim's Scale tool to see its log") from None
    cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    if not (tmp / "scale_set.xml").is_file():
        raise DataError(f"OpenSim's ScaleTool ran the setup {path} and wrote no scale set",
                        "run the setup in OpenSim's Scale tool to see its log")
    ss = osim.ScaleSet(str(tmp / "scale_set.xml"))
    scales = {}
    for i in range(ss.getSize()):
        s = ss.get(i)
        v = s.getScaleFactors()
        scales.setdefault(s.getSegmentName(), [float(v.get(k)) for k in range(3)])
    order = scaler.getScalingOrder()
    ms = scaler.getMeasurementSet()
    base = Path(tool.getPathToSubject() or path.parent)
    return {"setup": str(path), "generic_model": str(base / tool.getGenericModelMaker().getModelFileName()),
            "static_trial": str(base / scaler.getMarkerFileName()),
            "time_range": [float(scaler.getTimeRange().get(k)) for k in range(2)],
            "scaling_order": [str(order.get(k)) for k in range(order.size())],
            "measurements": [ms.get(k).getName() for k in range(ms.getSize()) if ms.get(k).getApply()],
            "scales": scales, "cpu_s": round(cpu, 3), "wall_s": round(wall, 3),
            "opensim_version": str(getattr(osim, "__version__", "unknown"))}


def _first_line(exc) -> str:
    text = " ".join(str(exc).split())
    return text[:200] or type(exc).__name__


def compare(table: dict, peer: dict) -> list[dict]:
    """skelid's factor and 95 % interval beside ScaleTool's, for every body and axis both scale.

    A one-factor body (``xyz``) is compared with ScaleTool's mean of its three factors (equal where its
    measurements scale all three axes alike, as they usually do).

    Returns
    -------
    list of dict
        ``body``, ``axis``, ``skelid``, ``ci95``, ``scaletool``, ``inside`` (ScaleTool's factor in
        skelid's interval), ``z`` (their difference in skelid's sd, None without an sd).
    """
    rows = []
    for body, axes in (table.get("scales") or {}).items():
        st = (peer.get("scales") or {}).get(body)
        if st is None:
            continue
        for ax, e in axes.items():
            v = sum(st) / 3.0 if ax == "xyz" else st["xyz".index(ax)]
            lo, hi = e["ci95"]
            sd = e.get("sd")
            rows.append({"body": body, "axis": ax, "skelid": e["value"], "ci95": [lo, hi], "scaletool": v,
                         "inside": bool(lo <= v <= hi),
                         "z": (v - e["value"]) / sd if sd and sd > 0 else None})
    return rows


def scaletool_entry(table: dict, peer: dict) -> dict:
    """The scaling table's ``scaletool`` entry: ScaleTool's run, the comparison and its count."""
    rows = compare(table, peer)
    return {**peer, "compared": rows, "inside": sum(r["inside"] for r in rows), "n_compared": len(rows)}
