"""Checks that data can inform a model before any fit starts.

Each check is a small named function that raises a one-line
:class:`~skelid.errors.DataError` (or returns quietly); :func:`check_data`
runs them all. They look only at sizes and at the data's spread, never at a
fit:

* :func:`check_frames`: each method needs a minimum number of *usable* frames,
  frames whose present markers give more coordinates than the pose has
  (:data:`MIN_FRAMES`); a file of one or two rows, or all frames missing but
  one, is refused with the count;
* :func:`check_surplus`: the model's markers must give more coordinates per
  frame than it has pose coordinates, or no frame informs any parameter;
* :func:`check_motion`: data in which nothing moves (every coordinate constant
  over the usable frames, to rounding) carry no information about the joints
  and no noise to estimate: refused rather than fitted into a meaningless
  number.

Before those, the checks of the input itself: :func:`check_input_file` (an existing,
readable, non-empty file), :func:`check_distinct_files` (no file given twice, nor a copy of one),
:func:`check_units` (marker distances against the model's), and
:func:`data_overview` (what the file holds, each marker's gaps).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from skelid.data import MarkerData, unit_scale
from skelid.errors import DataError, FormatError, ModelError, SettingError
from skelid.estimators.fit.joint import usable_frames  # the one usable-frame rule
from skelid.model.description import Model

#: usable frames each method needs at the least (the motion model of the marker methods needs a few); a
#: trial among several ('marker-multi') need not stand alone, and its motion model asks for 3 frames itself
MIN_FRAMES = {"paper": 1, "marker-grid": 1, "marker": 5, "marker-smc": 5, "marker-multi": 1}
DEFAULT_MIN_FRAMES = 5
#: a coordinate whose peak-to-peak range over the frames is below this fraction of the model's size is still
MOTION_RTOL = 1e-9
#: frames (evenly spread) whose marker distances check_units compares with the model's: the (F, M, M)
#: distances of a long trial would take more memory than the fit
UNIT_CHECK_FRAMES = 1000


def check_finite(name: str, value):
    """``value`` if it is None or a finite number, else a one-line :class:`SettingError` naming ``name``."""
    import math

    if value is not None and not math.isfinite(value):
        raise SettingError(f"{name} must be a finite number, got {value}", f"give {name} a number such as 15")
    return value


def check_surplus(model, where: str = "the data") -> None:
    n_coord = len(model.markers) * model.dim
    if model.n_params and n_coord <= model.n_pose:
        raise DataError(
            f"model {model.name!r} has {len(model.markers)} markers ({n_coord} coordinates per frame) for "
            f"{model.n_pose} pose coordinates: no frame of {where} can inform its parameters",
            "add markers to the model (at least one coordinate more than the pose has)")


def check_moving_joint(model) -> None:
    """Refuse joint parameters (lengths, centres, axes) in a model none of whose joints can move.

    With every joint below a free root fixed, the model is one rigid body: a length or a joint
    centre between its segments is set by the markers' nominal positions alone, which no motion
    can check, so an interval from it would only restate the placement.
    """
    from skelid.model.kinds import PARAMETER_TARGET

    moving = [d for d in model.dofs if model.segments[d.segment].joint.type != "free"]
    joint_params = [p.name for p in model.parameters if PARAMETER_TARGET.get(p.kind, "joint") == "joint"]
    if joint_params and not moving:
        raise ModelError(
            f"model {model.name!r} has no joint that moves (every joint below its root is fixed), so "
            f"parameter(s) {', '.join(joint_params)} follow from the markers' nominal positions alone, not from motion",
            "give the joints the motion they have (revolute, universal, ball, ...) or remove these parameters")


def check_frames(model, y: np.ndarray, method: str, where: str = "the data") -> None:
    need = MIN_FRAMES.get(method, DEFAULT_MIN_FRAMES)
    n = int(usable_frames(model, y).sum())
    if n < need:
        raise DataError(
            f"{where} has {n} frame(s) in which the model's markers fix the pose ({len(y)} frames in all); "
            f"the {method} method needs at least {need}",
            "use a longer trial, or check that the file holds the model's markers")


def check_motion(model, y: np.ndarray, where: str = "the data") -> None:
    ok = usable_frames(model, y)
    if ok.sum() < 2:
        return
    with np.errstate(invalid="ignore"):
        ptp = np.nanmax(y[ok], axis=0) - np.nanmin(y[ok], axis=0)  # (M, D)
    size = float(np.nanmax(np.abs(y[ok]))) if np.isfinite(y[ok]).any() else 0.0
    if not np.any(ptp > MOTION_RTOL * max(size, 1e-300)):
        raise DataError(
            f"nothing moves in {where}: every marker coordinate is the same in all {int(ok.sum())} usable frames, "
            "so the data hold no information about the joints and no noise to measure",
            "give a trial in which the joints move")


def check_data(model, y: np.ndarray, methods, where: str = "the data", motion: bool = True) -> None:
    """Run every check on ``y (F, M, D)`` (model markers, model units) for each method.

    ``motion=False`` leaves out :func:`check_motion`: a still trial among several (a static trial
    beside movement trials) is checked for motion with the others.
    """
    check_moving_joint(model)
    check_surplus(model, where)
    for m in methods:
        check_frames(model, y, m, where)
    if motion:
        check_motion(model, y, where)


def check_input_file(path, what: str = "data file") -> Path:
    """An existing, readable, non-empty regular file, or a one-line error naming it."""
    from skelid.io._common import check_regular_file

    path = Path(path)
    cls = ModelError if what.startswith("model") else FormatError
    check_regular_file(path, what, cls)
    try:
        with open(path, "rb") as fh:
            head = fh.read(1)
    except OSError as exc:
        raise cls(f"cannot read {what} {path}: {exc.strerror or exc}",
                  "check the file's permissions") from None
    if not head:
        raise cls(f"{what} {path} is empty", "check that the file was written completely")
    return path


def check_distinct_files(paths, what: str = "data file") -> None:
    """Refuse the same file given twice in one line: by path (links followed) or as a byte-for-byte
    copy under another name. Its trial would count twice."""
    import os
    import stat

    seen: dict = {}
    sizes: dict[int, list] = {}
    for p in paths:
        try:
            st = os.stat(p)
            key = (st.st_dev, st.st_ino)
        except OSError:
            key, st = os.path.abspath(p), None  # a missing file is refused by check_input_file
        if key in seen:
            same = "" if str(seen[key]) == str(p) else f" (as {seen[key]})"
            raise DataError(f"{what} {p} is given twice{same}: its frames would count as two trials' worth "
                            "of information", "give each trial once")
        seen[key] = p
        if st is not None and stat.S_ISREG(st.st_mode):  # never open a pipe or a device here
            sizes.setdefault(st.st_size, []).append(p)
    for group in sizes.values():
        _check_distinct_contents(group, what)


def _check_distinct_contents(paths, what: str) -> None:
    """Among files of one size, refuse two with the same bytes (read only where sizes match)."""
    import hashlib

    if len(paths) < 2:
        return
    digests: dict = {}
    for p in paths:
        h = hashlib.sha256()
        try:
            with open(p, "rb") as fh:
                for block in iter(lambda fh=fh: fh.read(1 << 20), b""):
                    h.update(block)
        except OSError:
            continue  # an unreadable file is refused by check_input_file
        d = h.digest()
        if d in digests:
            raise DataError(f"{what} {p} holds the same bytes as {digests[d]}: its frames would count as two "
                            "trials' worth of information", "give each trial once (a copy of a file is the "
                            "same trial)")
        digests[d] = p


def _model_names_in_file(model: Model, data: MarkerData) -> dict[str, str]:
    """Model marker name -> name in the file, for the markers that are there."""
    labels = model.marker_labels
    names = set(data.names)
    bare: dict[str, list[str]] = {}
    for n in data.names:
        bare.setdefault(n.rsplit(":", 1)[-1], []).append(n)
    out = {}
    for m in model.marker_names:
        w = labels.get(m, m)
        if w in names:
            out[m] = w
        elif len(bare.get(w, [])) == 1:
            out[m] = bare[w][0]
    return out


def _path_bounds(model: Model) -> tuple[np.ndarray, np.ndarray]:
    """``(rigid (M, M), upper (M, M))``: exact distances between markers on one segment
    (NaN across segments), and upper bounds through the joint centres for any pair."""
    seg = {s.name: i for i, s in enumerate(model.segments)}
    parent = model.parent_index
    jlen = np.array([np.linalg.norm(s.joint.position) for s in model.segments])
    jlen[parent < 0] = 0.0

    def chain(s):
        out = [s]
        while parent[out[-1]] >= 0:
            out.append(int(parent[out[-1]]))
        return out

    M = len(model.markers)
    pos = [np.asarray(m.position, float) for m in model.markers]
    si = [seg[m.segment] for m in model.markers]
    rigid = np.full((M, M), np.nan)
    upper = np.zeros((M, M))
    for a in range(M):
        ca = chain(si[a])
        for b in range(M):
            if si[a] == si[b]:
                rigid[a, b] = upper[a, b] = np.linalg.norm(pos[a] - pos[b])
                continue
            cb = chain(si[b])
            common = next(s for s in ca if s in cb)
            path = ca[:ca.index(common)] + cb[:cb.index(common)]
            upper[a, b] = np.linalg.norm(pos[a]) + np.linalg.norm(pos[b]) + jlen[path].sum()
    return rigid, upper


def check_units(model: Model, data: MarkerData) -> None:
    """Compare marker distances in the data with the model's, to catch wrong units.

    Distances between markers on one segment must match the model's; any
    distance must stay below the model's bound through the joint centres.

    Raises
    ------
    DataError
        The data are ~3x or more larger (or smaller) than the model says.
    """
    names = _model_names_in_file(model, data)
    if len(names) < 2:
        return
    idx = {n: data.names.index(f) for n, f in names.items()}
    mi = [i for i, m in enumerate(model.marker_names) if m in idx]
    step = max(1, data.n_frames // UNIT_CHECK_FRAMES)  # the median distances of evenly spread frames
    y = data.positions[::step, [idx[model.marker_names[i]] for i in mi]] * unit_scale(data.units, model.units)
    with warnings.catch_warnings(), np.errstate(invalid="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        d = np.nanmedian(np.linalg.norm(y[:, :, None] - y[:, None, :], axis=-1), axis=0)
    rigid, upper = _path_bounds(model)
    rigid, upper = rigid[np.ix_(mi, mi)], upper[np.ix_(mi, mi)]
    iu = np.triu_indices(len(mi), 1)
    d, rigid, upper = d[iu], rigid[iu], upper[iu]
    ok = np.isfinite(d)
    r_rigid = d[ok & (rigid > 0)] / rigid[ok & (rigid > 0)]
    r_upper = d[ok & (upper > 0)] / upper[ok & (upper > 0)]
    factor = None
    if r_rigid.size:
        s = float(np.median(r_rigid))
        if s > 3 or s < 1 / 3:
            factor = s
    elif r_upper.size:
        s = float(np.median(r_upper))
        if s > 3 or float(np.max(r_upper)) < 1 / 30:
            factor = s
    if factor is not None:
        where = data.source or "the data"
        raise DataError(
            f"marker distances in {where} are about {factor:.3g} times those of model {model.name!r} "
            f"(file units: {data.units}, model units: {model.units}); the units of one of them are wrong",
            "check the units field of the data file and the units of the model; mm, cm and m are "
            "converted automatically",
        )


def _gap_runs(missing: np.ndarray) -> tuple[int, int]:
    """Number of runs of True in ``missing (F,)`` and the longest run."""
    if not missing.any():
        return 0, 0
    m = np.concatenate([[False], missing, [False]]).astype(int)
    starts = np.flatnonzero(np.diff(m) == 1)
    stops = np.flatnonzero(np.diff(m) == -1)
    return int(len(starts)), int((stops - starts).max())


def data_overview(data: MarkerData, model: Model | None = None) -> dict:
    """What the file holds: size, rate, units, and the gaps of every marker.

    Returns
    -------
    dict
        ``source, format, n_frames, n_markers, dim, rate_hz, units, duration_s,
        model_markers {model name: file name}, markers [{name, used_by_model,
        frames_missing, gaps, longest_gap}]``.
    """
    used = _model_names_in_file(model, data) if model is not None else {}
    in_model = {f: m for m, f in used.items()}
    present = data.present
    markers = []
    for k, n in enumerate(data.names):
        runs, longest = _gap_runs(~present[:, k])
        markers.append({"name": n, "used_by_model": n in in_model,
                        "frames_missing": int((~present[:, k]).sum()), "gaps": runs,
                        "longest_gap": longest})
    return {
        "source": data.source, "format": data.meta.get("format", Path(data.source).suffix.lstrip(".")),
        "n_frames": data.n_frames, "n_markers": data.n_markers, "dim": data.dim,
        "rate_hz": data.rate, "units": data.units,
        "duration_s": round(data.n_frames / data.rate, 6), "model_markers": used,
        "markers": markers,
    }
