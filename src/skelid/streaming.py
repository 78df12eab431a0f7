"""Long trials in bounded memory: frames in chunks, the online form of an estimator.

An online estimator (:class:`~skelid.estimators.online.grid.MarkerGridFilter`,
:class:`~skelid.estimators.paper.PaperFilter`) has ``init_state()`` and
``update(state, frame)``; its state is ``O(K)`` for ``K`` hypotheses (running
sums, the last pose of each hypothesis, snapshots of the posterior at the
estimator's ``history_steps``), whatever the trial length.
:func:`fit_online` folds ``update`` over frames that arrive in chunks, so a
trial of any length needs the memory of one chunk plus that state:

.. code-block:: python

    from skelid.streaming import fit_online, iter_trc
    res = fit_online(MarkerGridFilter(model), iter_trc("long.trc", chunk_frames=10_000))
    res.posterior.summary()

:func:`iter_trc` reads a TRC file a chunk at a time; :func:`iter_chunks` cuts
a :class:`~skelid.data.MarkerData` already in memory. The per-frame most likely
value (``O(F)``) is kept only when asked (``keep_path=True``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

from skelid.data import MarkerData, unit_scale
from skelid.errors import DataError, FormatError
from skelid.estimators.base import prepare
from skelid.io._common import parse_table, split_fields
from skelid.io.trc import trc_header


class OnlineFit(NamedTuple):
    """What :func:`fit_online` returns."""

    state: object  # the estimator's final online state
    posterior: object  # GridPosterior
    n_frames: int
    n_chunks: int
    map_path: np.ndarray | None  # (F,) most likely value of the first parameter, if kept


def iter_chunks(data: MarkerData, chunk_frames: int = 10_000) -> Iterator[MarkerData]:
    """Consecutive chunks of ``chunk_frames`` frames of ``data`` (views, no copies)."""
    chunk_frames = max(int(chunk_frames), 1)
    for a in range(0, data.n_frames, chunk_frames):
        yield data.replace(positions=data.positions[a:a + chunk_frames])


def iter_trc(path, chunk_frames: int = 10_000) -> Iterator[MarkerData]:
    """Read a TRC file ``chunk_frames`` rows at a time.

    The header is read as :func:`skelid.io.read_trc` reads it; each chunk is a
    :class:`~skelid.data.MarkerData` with the file's names, rate and units.

    Raises
    ------
    FormatError
        The file is not a TRC file, or a row is malformed (naming the line).
    """
    path = Path(path)
    chunk_frames = max(int(chunk_frames), 1)
    try:
        fh = open(path, encoding="utf-8-sig", newline=None)
    except OSError as exc:
        raise FormatError(f"cannot read {path}: {exc.strerror or exc}", "check the path") from None
    with fh:
        try:
            head = [fh.readline().rstrip("\n") for _ in range(5)]
        except UnicodeDecodeError:
            raise FormatError(f"{path}: not a UTF-8 text file", "use skelid.io.read_markers for this file") from None
        if not head[0].lstrip().startswith("PathFileType"):
            raise FormatError(f"{path}: line 1 does not start with 'PathFileType'; not a TRC file",
                              "check the file format or the file extension")
        sep, header, rate, units = trc_header(head, path)
        names = tuple(n for n in split_fields(head[3], sep)[2:] if n)
        if not names:
            raise FormatError(f"{path}: line 4 names no markers")
        M = len(names)

        def chunk(rows):
            pos = parse_table(rows, 3 * M, path).reshape(len(rows), M, 3)
            return MarkerData(pos, names, rate, units, source=str(path),
                              meta={"header": header, "format": "trc", "first_line": rows[0][0]})

        rows = []
        try:
            for lineno, line in enumerate(fh, start=6):
                if not line.strip(sep + " \t\r\n"):
                    continue
                f = split_fields(line.rstrip("\n"), sep)
                if len(f) > 2 + 3 * M and any(f[2 + 3 * M:]):
                    raise FormatError(f"{path}: line {lineno} has {len(f) - 2} coordinates for {M} markers",
                                      "check that the marker-name line lists every marker")
                rows.append((lineno, f[2:2 + 3 * M]))
                if len(rows) == chunk_frames:
                    yield chunk(rows)
                    rows = []
        except UnicodeDecodeError:
            raise FormatError(f"{path}: not a UTF-8 text file", "use skelid.io.read_markers for this file") from None
        if rows:
            yield chunk(rows)


def _frames(model, chunk: MarkerData, first: bool) -> np.ndarray:
    """The model's markers of one chunk ``(F_c, M, D)``, model order and units.

    The first chunk gets every check of :func:`skelid.estimators.base.prepare`;
    later ones only the selection (a marker may well be missing for a whole chunk).
    """
    if first:
        try:
            return prepare(model, chunk)
        except DataError as exc:
            if "missing in every frame" not in exc.problem:
                raise
    sel = chunk.select(model.marker_names, model.marker_labels)
    y = sel.positions * unit_scale(chunk.units, model.units)
    return y[..., : model.dim] if model.dim == 2 and y.shape[2] == 3 else y


def fit_online(estimator, chunks: Iterable[MarkerData] | MarkerData, keep_path: bool = False,
               chunk_frames: int = 10_000, progress=None) -> OnlineFit:
    """Fold ``estimator.update`` over every frame of ``chunks``.

    Parameters
    ----------
    estimator : MarkerGridFilter or PaperFilter
        Any estimator with ``init_state()``, ``update(state, frame)`` and a
        ``model``.
    chunks : iterable of MarkerData, or MarkerData
        Consecutive pieces of one trial (a MarkerData is cut into
        ``chunk_frames`` frames).
    keep_path : bool
        Keep the most likely value of the first parameter after every frame
        (``O(F)`` memory).
    progress : callable, optional
        Called with the number of frames of each chunk once it is done.

    Returns
    -------
    OnlineFit
    """
    if isinstance(chunks, MarkerData):
        chunks = iter_chunks(chunks, chunk_frames)
    model = estimator.model
    state = estimator.init_state()
    path = [] if keep_path else None
    n_frames = n_chunks = 0
    for chunk in chunks:
        y = _frames(model, chunk, first=n_chunks == 0)
        for frame in y:
            state = estimator.update(state, frame)
            if keep_path:
                path.append(_map_value(estimator, state))
        n_frames += len(y)
        n_chunks += 1
        if progress is not None:
            progress(len(y))
    if n_frames == 0:
        raise DataError("no frames to fit", "check the file")
    post = estimator.posterior(state) if hasattr(estimator, "posterior") else state.posterior
    return OnlineFit(state, post, n_frames, n_chunks, None if path is None else np.asarray(path))


def _map_value(estimator, state) -> float:
    post = estimator.posterior(state) if hasattr(estimator, "posterior") else state.posterior
    lw = post.log_weights
    k = np.unravel_index(int(np.argmax(lw)), lw.shape)[0]
    v = post.axes[0][k]
    return float(v) if math.isfinite(v) else math.nan
