"""Marker data: the one object every reader returns.

``MarkerData`` holds marker positions ``positions (F, M, D)`` for ``F`` frames,
``M`` markers and ``D`` = 2 or 3 coordinates, with NaN wherever a marker is
missing, the marker ``names``, the sampling ``rate`` in Hz and the length
``units`` (``"mm"``, ``"m"`` or ``"cm"``). It is immutable: methods return new
objects.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from skelid.errors import DataError

#: sampling rates accepted, in Hz
RATE_RANGE = (1e-2, 1e6)
UNIT_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
#: largest marker coordinate a fit accepts, in mm (10 km: capture volumes span a few metres, so a
#: coordinate beyond it is a unit or an origin gone wrong). The fits work about the data's own centre
#: (:func:`skelid.estimators.base.fit_origin`), so where the data sit changes no number beyond rounding:
#: random shifts of 1e2 to 1e7 mm moved the marker fit's estimates of cases A and B by at most 4.4e-7 of
#: their value, their sd by 6.5e-6 and sigma by 2.1e-7, as much at 1e2 mm as at 1e7 mm
#: (benchmarks/shift_invariance.py); shifts by whole millimetres of data on a binary grid change nothing
#: at all (tests/test_invariance.py)
MAX_FIT_COORDINATE_MM = 1e7


def unit_scale(src: str, dst: str) -> float:
    """Factor that converts a length in ``src`` units to ``dst`` units."""
    for u in (src, dst):
        if not isinstance(u, str) or u not in UNIT_TO_MM:
            raise DataError(f"unknown length unit {u!r}", f"use one of {', '.join(UNIT_TO_MM)}")
    return UNIT_TO_MM[src] / UNIT_TO_MM[dst]


def check_positions(positions, units: str = "mm", where: str = "the data", max_mm: float | None = None) -> np.ndarray:
    """Marker coordinates as a new float array, or a one-line :class:`DataError`.

    Accepted: real numbers (integers or floats, not booleans, strings, complex numbers or
    objects), NaN for a missing coordinate, and with ``max_mm`` magnitudes up to that many mm
    (in ``units``; a fit uses :data:`MAX_FIT_COORDINATE_MM`). An infinite coordinate is
    refused, not taken for a missing one.

    Returns
    -------
    (...) float
        A copy: the caller's array is never changed.
    """
    kind = getattr(getattr(positions, "dtype", None), "kind", None)
    if kind is None:
        try:
            arr = np.array(positions)
        except (TypeError, ValueError):
            raise DataError(f"marker positions in {where} are not a rectangular array of numbers",
                            "give an array of shape (frames, markers, 2 or 3)") from None
        kind = arr.dtype.kind
    else:
        arr = positions
    if kind not in "iuf":
        what = {"b": "booleans", "c": "complex numbers", "U": "strings", "S": "bytes", "O": "objects"}.get(
            kind, f"values of type {arr.dtype}")
        raise DataError(f"marker positions in {where} are {what}, not real numbers",
                        "give the coordinates as a float array, NaN for a missing marker")
    pos = np.array(arr, dtype=float)
    inf = np.isinf(pos)
    if inf.any():
        at = tuple(int(i) for i in np.argwhere(inf)[0])
        raise DataError(f"{int(inf.sum())} marker coordinate(s) in {where} are infinite (the first at index {at})",
                        "give NaN for a missing marker, or fix the coordinates")
    if max_mm is not None:
        check_range(pos, units, where, max_mm)
    return pos


def check_range(pos: np.ndarray, units: str, where: str, max_mm: float = MAX_FIT_COORDINATE_MM) -> None:
    """Refuse coordinates ``pos`` (float, NaN missing) beyond ``max_mm`` millimetres in one line."""
    limit = max_mm / unit_scale(units, "mm")
    with np.errstate(invalid="ignore"):
        big = np.abs(pos) > limit
    if big.any():
        raise DataError(f"marker coordinates in {where} reach {float(np.nanmax(np.abs(pos))):.3g} {units}, beyond "
                        f"the {limit:g} {units} ({max_mm / 1e3:g} m) a fit accepts",
                        "check the file's units, or subtract a reference point (e.g. the lab origin) first")


def check_names(names, n_markers: int, where: str = "the data") -> tuple[str, ...]:
    """Marker names as a tuple of ``n_markers`` unique strings, or a one-line :class:`DataError`.

    A single string is one name (``"ABC"`` is one marker, never three).
    """
    if isinstance(names, str):
        names = (names,)
    try:
        names = tuple(names)
    except TypeError:
        raise DataError(f"marker names in {where} must be a sequence of strings, got {type(names).__name__}",
                        "give one name per marker, e.g. ('RSHO', 'RELB', 'RWRA')") from None
    bad = [n for n in names if not isinstance(n, str)]
    if bad:
        raise DataError(f"marker names in {where} must be strings, got {bad[0]!r} ({type(bad[0]).__name__})",
                        "give one name (a string) per marker")
    names = tuple(str(n) for n in names)
    if len(names) != n_markers:
        raise DataError(f"{len(names)} marker names for {n_markers} markers in {where}",
                        "give exactly one name per marker (the second axis of positions)")
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise DataError(f"duplicate marker names {dup} in {where}",
                        "rename the markers so that each name is unique")
    return names


def _iterable(v) -> bool:
    try:
        iter(v)
    except TypeError:
        return False
    return True


def check_rate(rate, where: str = "the data") -> float:
    """A sampling rate in Hz within :data:`RATE_RANGE`, or a one-line :class:`DataError`."""
    numeric = isinstance(rate, int | float | np.integer | np.floating) and not isinstance(rate, bool | np.bool_)
    if not (numeric and bool(RATE_RANGE[0] <= float(rate) <= RATE_RANGE[1])):
        raise DataError(f"sampling rate must be between {RATE_RANGE[0]:g} and {RATE_RANGE[1]:g} Hz, "
                        f"got {rate!r} in {where}", "give the rate in Hz")
    return float(rate)


@dataclass(frozen=True, eq=False)
class MarkerData:
    """Marker trajectories.

    Parameters
    ----------
    positions : (F, M, D) float
        Marker positions; NaN marks a missing marker in a frame.
    names : tuple of str, length M
        Marker names as they appear in the file.
    rate : float
        Sampling rate in Hz.
    units : str
        Length unit of ``positions``: ``"mm"``, ``"cm"`` or ``"m"``.
    source : str, optional
        Where the data came from (a path), for messages.

    Raises
    ------
    DataError
        In one line: positions that are not an ``(F, M, 2 or 3)`` array of real numbers, or hold
        an infinity (NaN is a missing marker; an infinity is not); names that are not one string
        per marker, or not unique (a single string is one name); a rate outside
        :data:`RATE_RANGE` (or not a number); units other than mm, cm and m.
    """

    positions: np.ndarray
    names: tuple[str, ...]
    rate: float
    units: str = "mm"
    source: str = ""
    meta: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        source = self.source
        if source is None:
            source = ""
        if not isinstance(source, str | os.PathLike):
            raise DataError(f"MarkerData source must be a string (a path), got {type(source).__name__}",
                            "give the file the data came from, or leave it out")
        source = str(source)
        where = source or "the data"
        if not isinstance(self.meta, Mapping):
            raise DataError(f"MarkerData meta must be a dict, got {type(self.meta).__name__}",
                            "give a dict or leave it out")
        unit_scale(self.units, "mm")
        pos = check_positions(self.positions, self.units, where)  # own copy: callers keep theirs
        if pos.ndim != 3 or pos.shape[2] not in (2, 3):
            raise DataError(
                f"marker positions must have shape (frames, markers, 2 or 3), got {pos.shape}",
                "give an array of shape (frames, markers, 2 or 3)")
        names = check_names(self.names, pos.shape[1], where)
        rate = check_rate(self.rate, where)
        pos.setflags(write=False)
        object.__setattr__(self, "positions", pos)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "rate", rate)
        object.__setattr__(self, "source", source)

    # ------------------------------------------------------------------ shape
    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    @property
    def n_markers(self) -> int:
        return self.positions.shape[1]

    @property
    def dim(self) -> int:
        return self.positions.shape[2]

    @property
    def time(self) -> np.ndarray:
        """(F,) float: time of each frame in seconds from the first."""
        return np.arange(self.n_frames) / self.rate

    @property
    def present(self) -> np.ndarray:
        """(F, M) bool: marker present (all coordinates finite) in frame."""
        return np.isfinite(self.positions).all(axis=2)

    # ---------------------------------------------------------- derived data
    def to_units(self, units: str) -> MarkerData:
        """The same data in other length units."""
        k = unit_scale(self.units, units)
        return self.replace(positions=self.positions * k, units=units)

    def replace(self, **changes) -> MarkerData:
        kw = dict(
            positions=self.positions, names=self.names, rate=self.rate,
            units=self.units, source=self.source, meta=self.meta,
        )
        kw.update(changes)
        return MarkerData(**kw)

    def select(self, names, aliases: dict[str, str] | None = None) -> MarkerData:
        """The markers ``names`` in that order.

        Parameters
        ----------
        names : sequence of str
            Marker names wanted (model names).
        aliases : dict, optional
            Model name -> name in the file, where they differ.

        Raises
        ------
        DataError
            Naming every marker that is not in the data.
        """
        if isinstance(names, str):
            names = (names,)  # one name, never its letters
        if not _iterable(names):
            raise DataError(f"the names to select must be a sequence of strings, got {type(names).__name__}",
                            "give the marker names, e.g. ('RSHO', 'RELB')")
        names = tuple(names)
        names = check_names(names, len(names), "the names to select")
        aliases = aliases or {}
        if not isinstance(aliases, Mapping):
            raise DataError(f"aliases must be a dict of model name to name in the file, got {type(aliases).__name__}",
                            "give {model name: file name} or leave it out")
        index = {n: i for i, n in enumerate(self.names)}
        wanted = [aliases.get(n, n) for n in names]
        missing = [w for w in wanted if w not in index]
        if missing:
            # tolerate a subject prefix ("Derrick:RSHO") when the bare name is unique
            bare = {}
            for i, n in enumerate(self.names):
                bare.setdefault(n.rsplit(":", 1)[-1], []).append(i)
            for w in list(missing):
                if len(bare.get(w, [])) == 1:
                    index[w] = bare[w][0]
                    missing.remove(w)
        if missing:
            where = self.source or "the data"
            raise DataError(
                f"marker(s) {', '.join(missing)} required by the model are not in {where}",
                "check the marker names in the model file or add an [aliases] table "
                f"(the file has: {', '.join(self.names[:12])}{', ...' if self.n_markers > 12 else ''})",
            )
        idx = [index[w] for w in wanted]
        return self.replace(positions=self.positions[:, idx, :], names=tuple(names))

    def frames(self, start: int = 0, stop: int | None = None) -> MarkerData:
        """Frames ``start:stop``."""
        for name, v in (("start", start), ("stop", stop)):
            if not (v is None and name == "stop") and not (isinstance(v, int | np.integer) and not isinstance(v, bool)):
                raise DataError(f"frames({name}={v!r}): a frame index must be an integer", "e.g. data.frames(0, 100)")
        return self.replace(positions=self.positions[start:stop])

    def __repr__(self) -> str:
        return (
            f"MarkerData({self.n_frames} frames x {self.n_markers} markers x {self.dim}D, "
            f"{self.rate:g} Hz, {self.units}{', ' + self.source if self.source else ''})"
        )
