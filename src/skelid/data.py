"""Marker data: the one object every reader returns.

``MarkerData`` holds marker positions ``positions (F, M, D)`` for ``F`` frames,
``M`` markers and ``D`` = 2 or 3 coordinates, with NaN wherever a marker is
missing, the marker ``names``, the sampling ``rate`` in Hz and the length
``units`` (``"mm"``, ``"m"`` or ``"cm"``). It is immutable: methods return new
objects.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from skelid.errors import DataError

#: sampling rates accepted, in Hz
RATE_RANGE = (1e-2, 1e6)
UNIT_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


def unit_scale(src: str, dst: str) -> float:
    """Factor that converts a length in ``src`` units to ``dst`` units."""
    try:
        return UNIT_TO_MM[src] / UNIT_TO_MM[dst]
    except KeyError as exc:
        raise DataError(
            f"unknown length unit {exc.args[0]!r}", f"use one of {', '.join(UNIT_TO_MM)}"
        ) from None


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
    """

    positions: np.ndarray
    names: tuple[str, ...]
    rate: float
    units: str = "mm"
    source: str = ""
    meta: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        pos = np.array(self.positions, dtype=float)  # own copy: callers keep theirs
        if pos.ndim != 3 or pos.shape[2] not in (2, 3):
            raise DataError(
                f"marker positions must have shape (frames, markers, 2 or 3), got {pos.shape}"
            )
        names = tuple(str(n) for n in self.names)
        if len(names) != pos.shape[1]:
            raise DataError(f"{len(names)} marker names for {pos.shape[1]} markers")
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise DataError(
                f"duplicate marker names {dup} in {self.source or 'data'}",
                "rename the markers so that each name is unique",
            )
        numeric = isinstance(self.rate, int | float | np.integer | np.floating) \
            and not isinstance(self.rate, bool | np.bool_)
        rate_ok = numeric and bool(RATE_RANGE[0] <= float(self.rate) <= RATE_RANGE[1])
        if not rate_ok:
            raise DataError(f"sampling rate must be between {RATE_RANGE[0]:g} and {RATE_RANGE[1]:g} Hz, "
                            f"got {self.rate!r} in {self.source or 'the data'}", "give the rate in Hz")
        unit_scale(self.units, "mm")
        pos[~np.isfinite(pos)] = np.nan
        pos.setflags(write=False)
        object.__setattr__(self, "positions", pos)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "rate", float(self.rate))

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
        aliases = aliases or {}
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
        return self.replace(positions=self.positions[start:stop])

    def __repr__(self) -> str:
        return (
            f"MarkerData({self.n_frames} frames x {self.n_markers} markers x {self.dim}D, "
            f"{self.rate:g} Hz, {self.units}{', ' + self.source if self.source else ''})"
        )
