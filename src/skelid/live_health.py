"""Health checks of a live session: swapped labels from the markers' own tracks, misfit over a recent window.

**Tracks.** Each marker ``i`` is predicted from its last two positions,
``p_i(t) = 2 y_i(t-1) - y_i(t-2)``; its innovation ``e_i = y_i(t) - p_i(t)``
has a per-coordinate variance ``v_i`` that is estimated robustly from the last
:data:`TRACK_WINDOW` frames, ``v_i = median |e_i|^2 / median(chi^2_D)`` (noise
``6 sigma^2`` plus the movement's own acceleration), so that
``|e_i|^2 / v_i ~ chi^2_D`` while marker ``i`` keeps its label. Markers ``i`` and
``j`` look swapped when

.. math::

    \\frac{|y_i - p_i|^2}{v_i} > c, \\quad \\frac{|y_j - p_j|^2}{v_j} > c, \\quad
    \\frac{|y_i - p_j|^2}{v_j} \\le c, \\quad \\frac{|y_j - p_i|^2}{v_i} \\le c, \\quad
    |y_i - p_j|^2 + |y_j - p_i|^2 \\le \\tfrac14 \\left(|y_i - p_i|^2 + |y_j - p_j|^2\\right),

``c`` the ``1 - 10^{-6}`` quantile of ``chi^2_D``: both markers left their own
tracks, and each lies on the other's. Only the markers beyond ``c`` are paired
(a matrix of them, no loop); on clean data two markers must both leave their
tracks at a ``10^{-6}`` level in one frame *and* land on each other's, which
takes two markers within the noise of each other's path (and then their labels
hardly matter). A frame found swapped is kept in the history swapped back, so
that the rest of a swap lasting several frames is found too and its end is no
new swap.

**Misfit over a recent window.** The squared residual distances ``r_{ti}^2``
of the last :data:`MISFIT_WINDOW` frames used whole (each frame's pose fitted
freely) are kept. Against a noise variance ``s^2`` the window's sum has
``sum_t (n_t D - Q)`` degrees of freedom, and each marker's
``E r_{ti}^2 = s^2 (D - h_{ti}) <= D s^2`` (``h`` its leverage in the pose fit).
The window misfits when ``sum r^2 / (s^2 dof)`` is beyond both the ``1 - p``
quantile of its distribution (``p`` = :data:`MISFIT_P`; ``chi^2_dof / dof``
for a stated noise level, ``F(dof, dof_s)`` against the residuals of the
frames before the window, on their ``dof_s`` degrees of freedom, for an
estimated one) and an effect size, :data:`EFFECT_WINDOW`; a marker misfits
when its mean ``r^2 / (D s^2)`` over the window is beyond both the
``1 - p / M`` quantile and :data:`EFFECT_MARKER`. Bounding each marker's
expectation by ``D s^2`` (leverage 0) can only make the marker test
conservative; the effect sizes keep a long window from flagging a misfit too
small to matter, and an estimated noise level from flagging its own
fluctuation. The session hands each frame to the window capped at its own
per-frame bound (and each marker at its own), so that a few frames already
reported do not fill the window for its whole length.

Example
-------
Labels A and C of case A swapped for five frames:

>>> import numpy as np
>>> from skelid.simulate import builtin_model, simulate
>>> model = builtin_model("case-a")
>>> y = simulate(model, n_frames=60, sigma=1.0, rng=np.random.default_rng(0)).data.positions.copy()
>>> y[40:45, [0, 2]] = y[40:45, [2, 0]]
>>> tracks = MarkerTracks(n_markers=3, dim=2, floor=1e-10)
>>> {t: pairs for t, frame in enumerate(y) if (pairs := tracks.check(frame))}
{40: [(0, 2)], 41: [(0, 2)], 42: [(0, 2)], 43: [(0, 2)], 44: [(0, 2)]}
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import NamedTuple

import numpy as np
from scipy.stats import chi2, f

#: innovations kept per marker for the scale of its track
TRACK_WINDOW = 25
#: innovations a marker's track needs before it is tested
TRACK_MIN = 5
#: the scale of the tracks is recomputed every this many frames (a median per frame costs more than the test)
TRACK_EVERY = 10
#: tail probability of ``chi^2_D`` beyond which a marker has left its track
SWAP_P = 1e-6
#: swapped back, the two markers' innovations are at most this fraction of theirs as labelled
SWAP_DECISIVE = 0.25
#: frames in the misfit window
MISFIT_WINDOW = 50
#: frames the window needs before it is tested
MISFIT_MIN = 10
#: the markers' test over the window is made every this many frames
MISFIT_EVERY = 5
#: tail probability of the window tests (the marker test's is divided by the number of markers)
MISFIT_P = 1e-6
#: the least ratio of the window's residual variance to the noise variance that is called a misfit
EFFECT_WINDOW = 4.0
#: the least ratio of a marker's mean squared residual distance to ``D s^2`` that is called a misfit
EFFECT_MARKER = 4.0


@lru_cache(maxsize=512)
def _ratio_limit(p: float, dof: int, dof_noise: int | None) -> float:
    """The ``1 - p`` quantile of ``chi^2_dof / dof`` (a known noise level, ``dof_noise`` None) or of
    ``F(dof, dof_noise)`` (one estimated on ``dof_noise`` degrees of freedom)."""
    if dof_noise is None:
        return float(chi2.isf(p, dof)) / dof
    return float(f.isf(p, dof, dof_noise))


def _down(n: int) -> int:
    """``n`` rounded down to a power of two (a quantile at fewer degrees of freedom is only larger)."""
    return 1 << (max(int(n), 1).bit_length() - 1)


def ratio_limit(p: float, dof: int, dof_noise: int | None = None) -> float:
    """The bound on ``RSS / (s^2 dof)`` at tail probability ``p`` (see the module notes).

    The noise level's degrees of freedom are rounded down to a power of two, so that the quantile is
    computed a few times per session rather than per frame; rounding down only raises the bound.
    """
    return _ratio_limit(p, int(dof), None if dof_noise is None else _down(dof_noise))


def swapped_pairs(y, pred, var, limit: float, decisive: float = SWAP_DECISIVE, e2=None) -> list[tuple[int, int]]:
    """Pairs of markers whose labels look swapped against their tracks (module notes).

    Parameters
    ----------
    y : (M, D) float
        The frame (NaN where missing).
    pred : (M, D) float
        Each marker's predicted position (NaN where its track cannot say).
    var : (M,) float
        Per-coordinate variance of each track's innovation (NaN where not known yet).
    limit : float
        ``c``: the bound on ``|e|^2 / v`` of a marker on its own track.
    e2 : (M,) float, optional
        ``|y - pred|^2`` per marker, where already computed.

    Returns
    -------
    list of (int, int)
        Disjoint pairs ``(i, j)``, ``i < j``, the most decisive first; empty for a clean frame.
    """
    if e2 is None:
        d = y - pred
        e2 = np.einsum("md,md->m", d, d)
    off = e2 > limit * var  # NaN (missing, no track, no scale) compares False
    if np.count_nonzero(off) < 2:
        return []
    k = np.flatnonzero(off)
    d = y[k][:, None, :] - pred[k][None, :, :]
    cross = np.einsum("abd,abd->ab", d, d)  # cross[a, b] = |y_a - p_b|^2: y_a taken for marker b
    both = cross + cross.T
    ok = ((cross <= limit * var[k][None, :]) & (cross.T <= limit * var[k][:, None])
          & (both <= decisive * (e2[k][:, None] + e2[k][None, :])))
    a, b = np.nonzero(np.triu(ok, 1))
    if not a.size:
        return []
    order = np.argsort(both[a, b] / (e2[k][a] + e2[k][b]))
    pairs, taken = [], set()
    for n in order:  # the few candidates: disjoint pairs, the most decisive first
        i, j = int(k[a[n]]), int(k[b[n]])
        if i not in taken and j not in taken:
            pairs.append((i, j))
            taken.update((i, j))
    return pairs


class MarkerTracks:
    """Each marker's track through the frames of a session, to see labels that swap (module notes).

    Parameters
    ----------
    n_markers, dim : int
    floor : float
        The least noise variance (:func:`~skelid.estimators.online.grid.noise_floor`): an innovation's
        variance is held at least at ``6 floor``.
    """

    def __init__(self, n_markers: int, dim: int, floor: float):
        self.limit = float(chi2.isf(SWAP_P, dim))
        self._median = float(chi2.median(dim))
        self._floor = 6.0 * floor
        self._e2 = np.full((TRACK_WINDOW, n_markers), np.nan)  # recent squared innovations
        self._n = 0  # innovations recorded (frames with a prediction)
        self._var = np.full(n_markers, np.nan)
        self._off = self._var  # limit * var: beyond it a marker is off its track
        self.reset()

    def reset(self) -> None:
        """Forget the last positions (a frozen or zeroed stream broke the tracks); the scales are kept."""
        self._last = self._before = None

    def predict(self) -> np.ndarray | None:
        """Each marker's predicted position ``(M, D)`` (NaN where it was missing), or None without two frames."""
        if self._before is None:
            return None
        return 2.0 * self._last - self._before

    def check(self, y) -> list[tuple[int, int]]:
        """The pairs of markers in frame ``y (M, D)`` whose labels look swapped (:func:`swapped_pairs`).

        The frame is then remembered with those pairs swapped back (the tracks follow the markers, not the
        labels), and its innovations update the tracks' scales.
        """
        pairs = []
        pred = self.predict()
        if pred is not None:
            d = y - pred
            e2 = (d * d).sum(axis=1)
            # two markers off their tracks are needed for a swap: the pairs are looked at only then
            if self._n >= TRACK_MIN and np.count_nonzero(e2 > self._off) >= 2:
                pairs = swapped_pairs(y, pred, self._var, self.limit, e2=e2)
            if pairs:
                y = _swapped_back(y, pairs)
                d = y - pred
                e2 = (d * d).sum(axis=1)
            self._record(e2)
        self._before, self._last = self._last, y
        return pairs

    def amend(self, pairs=(), lost=()) -> None:
        """Correct the last frame remembered: ``pairs`` found swapped by another check, ``lost`` markers
        (left out as outliers) not to be followed from it."""
        if self._last is None:
            return
        y = _swapped_back(self._last, pairs) if pairs else self._last.copy()
        y[list(lost)] = np.nan
        self._last = y

    def _record(self, e2) -> None:
        """Keep the frame's squared innovations ``(M,)`` (NaN where a marker has none)."""
        row = self._n % TRACK_WINDOW
        np.copyto(self._e2[row], e2, where=e2 == e2)  # a marker without one keeps its older value there
        self._n += 1
        if self._n <= TRACK_MIN or self._n % TRACK_EVERY == 0:
            # a marker never seen keeps NaN, and so no scale
            med = np.median(self._e2[:min(self._n, TRACK_WINDOW)], axis=0)
            self._var = np.maximum(med / self._median, self._floor)
            self._off = self.limit * self._var


def _swapped_back(y, pairs) -> np.ndarray:
    """``y`` with the rows of each pair exchanged (a copy)."""
    y = y.copy()
    for i, j in pairs:
        y[[i, j]] = y[[j, i]]
    return y


class Misfit(NamedTuple):
    """The outcome of :meth:`MisfitWindow.check`: what exceeds the noise, and by how much."""

    n_frames: int  # frames in the window
    sd: float | None  # the window's residual sd per coordinate, sqrt(RSS / dof), where beyond the bound
    noise_sd: float | None  # the noise sd it was tested against (stated, or of the frames before the window)
    markers: np.ndarray  # indices of the markers beyond the bound, worst first
    marker_rms: np.ndarray  # their rms residual distance over the window


class MisfitWindow:
    """The squared residual distances of the last :data:`MISFIT_WINDOW` frames used whole (module notes).

    The window as a whole is tested at every frame from running totals; the markers, from sums over the
    window, every :data:`MISFIT_EVERY` frames (their last finding stands in between), so that a frame costs
    a few ``(M,)`` writes.

    Parameters
    ----------
    n_markers, dim, n_pose : int
    floor : float
        The least noise variance (:func:`~skelid.estimators.online.grid.noise_floor`): the frames before
        the window are held at least at it (a noise-free stream's residuals are rounding).
    """

    def __init__(self, n_markers: int, dim: int, n_pose: int, floor: float = 0.0):
        self.D, self.Q, self.floor = dim, n_pose, floor
        self._r2 = np.zeros((MISFIT_WINDOW, n_markers))  # each frame's squared residual distances, 0 if missing
        self._seen = np.zeros((MISFIT_WINDOW, n_markers), dtype=bool)
        self._rss = np.zeros(MISFIT_WINDOW)  # each frame's residual sum of squares
        self._dof = np.zeros(MISFIT_WINDOW)  # and its n D - Q
        self._n = 0
        self._rss_in = self._dof_in = 0.0  # the window's totals
        self._rss_before = self._dof_before = 0.0  # the frames that have left it
        self._markers = (np.zeros(0, dtype=int), np.zeros(0))  # the markers' last finding

    def add(self, r2, seen, rss: float, n_seen: int) -> None:
        """Keep a frame's squared residual distances ``r2 (M,)`` (0 where a marker is missing, ``seen``
        False), their sum ``rss`` and the number of markers seen."""
        row = self._n % MISFIT_WINDOW
        dof = float(max(n_seen * self.D - self.Q, 0))
        if self._n >= MISFIT_WINDOW:
            old_rss, old_dof = float(self._rss[row]), float(self._dof[row])
            self._rss_before += old_rss
            self._dof_before += old_dof
            self._rss_in -= old_rss
            self._dof_in -= old_dof
        self._r2[row], self._seen[row], self._rss[row], self._dof[row] = r2, seen, rss, dof
        self._rss_in += rss
        self._dof_in += dof
        self._n += 1
        if self._n % MISFIT_WINDOW == 0:  # afresh once per turn: no rounding builds up
            self._rss_in, self._dof_in = float(self._rss.sum()), float(self._dof.sum())

    def sums(self) -> tuple[float, int]:
        """The window's residual sum of squares and its degrees of freedom ``sum_t (n_t D - Q)``."""
        return self._rss_in, int(round(self._dof_in))

    def check(self, s2: float, dof_noise: int | None = None) -> Misfit | None:
        """Whether the window's residuals exceed the noise variance ``s2``; None when nothing does.

        Parameters
        ----------
        s2 : float
            The noise variance: stated (``dof_noise`` None) or estimated on ``dof_noise`` degrees of
            freedom. An estimated one includes the window's own residuals: the window as a whole is then
            tested against the residuals of the frames that have left it (once they have 30 degrees of
            freedom), each marker against ``s2``.
        """
        n = min(self._n, MISFIT_WINDOW)
        if n < MISFIT_MIN:
            return None
        rss, dof = self.sums()
        sd = noise_sd = None
        if dof > 0:
            ref, ref_dof = s2, None
            if dof_noise is not None:
                ref_dof = int(round(self._dof_before))
                ref = max(self._rss_before / ref_dof, self.floor) if ref_dof >= 30 else None
            if ref is not None and ref > 0 and rss / (ref * dof) > max(
                    EFFECT_WINDOW, ratio_limit(MISFIT_P, _down(dof), ref_dof)):
                sd, noise_sd = math.sqrt(rss / dof), math.sqrt(ref)
        if self._n <= MISFIT_MIN or self._n % MISFIT_EVERY == 0:
            self._markers = self._marker_check(n, s2, dof_noise)
        markers, rms = self._markers
        if sd is None and not markers.size:
            return None
        return Misfit(n, sd, noise_sd, markers, rms)

    def _marker_check(self, n: int, s2: float, dof_noise: int | None) -> tuple[np.ndarray, np.ndarray]:
        """The markers whose mean ``r^2 / (D s2)`` over the window is beyond the bound, worst first, and
        their rms residual distances."""
        seen = self._seen[:n].sum(axis=0)
        total = self._r2[:n].sum(axis=0)
        m = total / (self.D * s2 * np.maximum(seen, 1))
        tested = seen >= MISFIT_MIN
        if not (tested & (m > EFFECT_MARKER)).any():
            return np.zeros(0, dtype=int), np.zeros(0)
        lim = max(EFFECT_MARKER, ratio_limit(MISFIT_P / seen.size, _down(self.D * int(seen[tested].min())),
                                             dof_noise))
        bad = np.flatnonzero(tested & (m > lim))
        markers = bad[np.argsort(-m[bad])]
        return markers, np.sqrt(total[markers] / seen[markers])
