"""Checks of a user's input before a fit: the files exist, the units agree, what the data hold.

Each turns a mistake into one :class:`~skelid.errors.SkelidError` line before it becomes a
traceback or a silently wrong number.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from skelid.data import MarkerData, unit_scale
from skelid.errors import DataError, FormatError, ModelError
from skelid.model.description import Model


def check_input_file(path, what: str = "data file") -> Path:
    """An existing, readable, non-empty regular file, or a one-line error naming it."""
    path = Path(path)
    cls = ModelError if what.startswith("model") else FormatError
    if not path.exists():
        raise cls(f"{what} {path} does not exist", "check the path")
    if path.is_dir():
        raise cls(f"{what} {path} is a folder, not a file", f"give the path of the {what} itself")
    try:
        with open(path, "rb") as fh:
            head = fh.read(1)
    except OSError as exc:
        raise cls(f"cannot read {what} {path}: {exc.strerror or exc}",
                  "check the file's permissions") from None
    if not head:
        raise cls(f"{what} {path} is empty", "check that the file was written completely")
    return path


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
    y = data.positions[:, [idx[model.marker_names[i]] for i in mi]] * unit_scale(data.units, model.units)
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
