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

**Leave one marker out.** Which marker misfits is asked of the markers
themselves: in frame ``t``, with its pose refitted (linearised: ``r_t`` the
residual after the Gauss-Newton step, ``H_t = J_t (J_t^T J_t)^{-1} J_t^T`` the
pose fit's hat matrix), leaving marker ``k`` out lowers the residual sum of
squares by

.. math::

    \\delta_{tk} = r_{tk}^\\top (I_D - H_{t,kk})^{+} r_{tk}

(``H_{t,kk}`` the marker's ``D x D`` block, ``+`` the pseudo-inverse: the
directions the pose absorbs carry nothing). Over the window,
``L_k = sum_t (RSS_t - delta_{tk}) / s^2`` is what is left with marker ``k``
free in every frame. Where the least ``L_k`` explains the misfit (with
marker ``k`` left out, :func:`left_out`, no other marker is beyond the
markers' bound), marker ``k`` is named only when its ``L_k`` is below every
other marker's by :data:`ALIKE_MARGIN` (a likelihood ratio of 1000 between
"marker ``k`` misfits" and "marker ``j`` does"); markers within that margin
of the least are alike, and the window's finding lists them as candidates
instead of naming one. Where no one marker explains it (two markers misfit,
or all), the markers beyond the bound are listed as before. Case A has one
residual degree of freedom per frame:
each ``r_t`` is the one direction the pose cannot follow, every
``delta_{tk}`` equals ``RSS_t``, and no frame can say which marker moved.

**Scale.** Distances between markers of one rigid segment are fixed by the
model (whatever the pose and the parameters); their ratio
``rho = sqrt(sum d_obs^2 / sum d_model^2)`` says at once how far the stream's
scale is off. A model without such pairs is compared by the markers' spread,
their rms distance from their centroid, against its range over poses within
the joints' ranges and parameters within their priors
(:func:`scale_reference`): ``rho`` lies in ``[spread / hi, spread / lo]``, and
in every recent frame's such interval, which narrows it as the poses change
(:class:`ScaleCheck`). The scale is off when ``rho`` is beyond
:data:`SCALE_OFF` either way, and a stream unit ``u`` is named when its
factor ``U_declared / U_u`` lies within :data:`SCALE_MATCH` of ``rho``
(``mm``, ``cm``, ``m`` and inches, 25.4 mm).

**Bounds.** An estimate pressed against its prior's bound is one the data put
beyond it. The Gaussian form's mean is held on the bound; there the
unbounded solve ``m`` with its sd ``s`` gives ``z = (a - m) / s`` beyond the
bound ``a``. The grid form sees no further than its edge; where a parameter's
marginal posterior is largest at the edge, its log weights ``l_0, l_1, l_2``
from the edge inward, a parabola through them (``D_1 = l_0 - l_1``,
``D_2 = l_0 - l_2``) has its peak ``z = (2 D_1 - D_2 / 2) / sqrt(D_2 - 2 D_1)``
sd beyond the edge (a log posterior falling into the grid without bending
down, ``D_2 <= 2 D_1``, by more than a unit a step: beyond by more than the
grid can show). Beyond :data:`BOUND_Z` the estimate is pressed against the
bound: the data contradict the prior's support (wrong units, a wrong model).

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
import statistics
from collections import deque
from functools import lru_cache
from typing import NamedTuple

import numpy as np
from scipy.stats import chi2, f, qmc

from skelid.estimators.fit.pose import _rotation_ranges
from skelid.model.description import Model
from skelid.model.kinematics import marker_positions

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
#: a marker is named only when, left out, the rest fit better than with any other left out by this many noise
#: variances: ``2 log 1000``, a likelihood ratio of 1000 (markers closer than that are alike)
ALIKE_MARGIN = 2.0 * math.log(1000.0)
#: the markers are left out in turn afresh every this many frames while the same ones stay beyond the bound
#: (a pass over the window's frames costs a batch of Jacobians): once the window has turned over
ALIKE_EVERY = MISFIT_WINDOW
#: frames of the window a step of that refresh takes (one step a push)
ALIKE_CHUNK = 10
#: a leverage block's eigenvalue below this is a direction the pose absorbs (no residual there)
_ABSORBED = 1e-8
#: a scale beyond this factor either way is off: the scale's range already allows for every pose and parameter
#: value the model allows; this leaves room for poses beyond the sampled ones and a subject beyond the priors
#: (a unit error is a factor 2.54 or more)
SCALE_OFF = 1.5
#: a stream unit is named when its factor lies within this factor of the frame's scale
SCALE_MATCH = 1.25
#: model poses (and parameter values) sampled for the range of the markers' spread
SCALE_SAMPLES = 256
#: a stream found on scale is checked again every this many frames (every frame for the first ones)
SCALE_EVERY = 10
#: the frames checked whose spreads bound the scale together
SCALE_KEEP = 50
#: the stream units a scale is matched against, in mm (inches too: a stream in inches is a common mistake)
STREAM_UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
#: an estimate beyond its prior's bound by more than this many sd is pressed against it
BOUND_Z = 4.0


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
    markers: np.ndarray  # indices of the markers beyond the bound, worst first (the one left out best first)
    marker_rms: np.ndarray  # their rms residual distance over the window
    alike: np.ndarray = np.zeros(0, dtype=int)  # where no one marker can be told: the candidates, best first
    alike_rms: np.ndarray = np.zeros(0)  # their rms residual distance over the window


class MisfitWindow:
    """The squared residual distances of the last :data:`MISFIT_WINDOW` frames used whole (module notes).

    The window as a whole is tested at every frame from running totals; the markers, from sums over the
    window, every :data:`MISFIT_EVERY` frames (their last finding stands in between), so that a frame costs
    a few ``(M,)`` writes; markers beyond the bound are left out in turn when they change, and every
    :data:`ALIKE_EVERY` frames while they do not: that refresh is taken a step at a time by
    :meth:`advance`, which the session calls in the time between frames, not while a frame waits.

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
        self._y = np.full((MISFIT_WINDOW, n_markers, dim), np.nan)  # each frame (to leave one marker out)
        self._q = np.full((MISFIT_WINDOW, n_pose), np.nan)  # and its pose
        self._rss = np.zeros(MISFIT_WINDOW)  # each frame's residual sum of squares
        self._dof = np.zeros(MISFIT_WINDOW)  # and its n D - Q
        self._n = 0
        self._rss_in = self._dof_in = 0.0  # the window's totals
        self._rss_before = self._dof_before = 0.0  # the frames that have left it
        self._markers = (np.zeros(0, dtype=int), np.zeros(0), np.zeros(0, dtype=int), np.zeros(0))  # last finding
        self._loo = None  # (markers beyond the bound, frame count, alike): the last leave-one-out finding
        self._refresh = None  # (markers, frame count, steps): its refresh, a few frames of the window a push

    def add(self, r2, seen, rss: float, n_seen: int, y=None, q=None) -> None:
        """Keep a frame's squared residual distances ``r2 (M,)`` (0 where a marker is missing, ``seen``
        False), their sum ``rss`` and the number of markers seen; with the frame ``y (M, D)`` and its pose
        ``q (Q,)``, the markers can be left out in turn (:meth:`check`)."""
        row = self._n % MISFIT_WINDOW
        if y is None or q is None:
            self._q[row] = np.nan
        else:
            self._y[row], self._q[row] = y, q
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

    def check(self, s2: float, dof_noise: int | None = None, linearise=None) -> Misfit | None:
        """Whether the window's residuals exceed the noise variance ``s2``; None when nothing does.

        Parameters
        ----------
        s2 : float
            The noise variance: stated (``dof_noise`` None) or estimated on ``dof_noise`` degrees of
            freedom. An estimated one includes the window's own residuals: the window as a whole is then
            tested against the residuals of the frames that have left it (once they have 30 degrees of
            freedom), each marker against ``s2``.
        linearise : callable, optional
            ``linearise(q (T, Q)) -> (x (T, M, D), dx/dq (T, M, D, Q))`` at the current parameters: with it
            (and the frames and poses given to :meth:`add`), markers beyond the bound are named only where
            leaving one out tells it apart from the others (:func:`leave_one_out`, :func:`alike_markers`).
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
            self._markers = self._marker_check(n, s2, dof_noise, linearise)
        markers, rms, alike, alike_rms = self._markers
        if sd is None and not markers.size and not alike.size:
            return None
        return Misfit(n, sd, noise_sd, markers, rms, alike, alike_rms)

    def _marker_check(self, n: int, s2: float, dof_noise: int | None, linearise=None) -> tuple:
        """The markers whose mean ``r^2 / (D s2)`` over the window is beyond the bound, worst first, and
        their rms residual distances; where leaving markers out cannot tell one of them from the others,
        none such, and the markers alike with their rms residual distances instead."""
        none = np.zeros(0, dtype=int), np.zeros(0)
        seen = self._seen[:n].sum(axis=0)
        total = self._r2[:n].sum(axis=0)
        m = total / (self.D * s2 * np.maximum(seen, 1))
        tested = seen >= MISFIT_MIN
        if not (tested & (m > EFFECT_MARKER)).any():
            return *none, *none
        lim = max(EFFECT_MARKER, ratio_limit(MISFIT_P / seen.size, _down(self.D * int(seen[tested].min())),
                                             dof_noise))
        bad = np.flatnonzero(tested & (m > lim))
        if not bad.size:
            return *none, *none
        markers = bad[np.argsort(-m[bad])]
        rms = np.sqrt(total / np.maximum(seen, 1))
        if linearise is not None and np.isfinite(self._q[:n]).all():
            key = tuple(bad.tolist())
            if self._loo is not None and self._loo[0] == key:
                alike = self._loo[2]  # the same markers beyond the bound: the last finding stands
                if self._n - self._loo[1] >= ALIKE_EVERY and self._refresh is None:
                    # until its refresh, spread over the next pushes, is done
                    self._refresh = (key, self._n, self._alike_steps(n, s2, tested, lim, linearise))
            else:
                alike = finish_steps(self._alike_steps(n, s2, tested, lim, linearise))
                self._loo, self._refresh = (key, self._n, alike), None
            if alike.size > 1:
                return *none, alike, rms[alike]
            if alike.size:  # the one marker that, left out, leaves the rest fitting best comes first
                markers = np.concatenate([alike, markers[markers != alike[0]]])
        return markers, rms[markers], *none

    def advance(self) -> bool:
        """One step of the pending refresh of the leave-one-out finding (False when none is pending); its
        answer replaces the finding when it is done and the same markers are still beyond the bound."""
        if self._refresh is None:
            return False
        key, at, steps = self._refresh
        try:
            next(steps)
        except StopIteration as done:
            self._refresh = None
            if self._loo is not None and self._loo[0] == key:
                self._loo = (key, at, done.value)
        return True

    def _alike_steps(self, n: int, s2: float, tested, limit: float, linearise):
        """:func:`alike_markers` over the window's ``n`` frames (linearised by ``linearise``) where the best
        marker left out explains the misfit: no other marker's mean ``r^2 / (D s2)`` is then beyond
        ``limit`` (the markers' bound); none where no one marker does (two markers misfit, or all).

        A generator over the window as it is now, :data:`ALIKE_CHUNK` frames a step (the sums are over
        frames), whose return value is the answer: a refresh runs a step between two frames (:meth:`advance`),
        so that no frame pays for the whole window (a batch of Jacobians: 5 ms for an OpenSim leg)."""
        y, seen, q = self._y[:n].copy(), self._seen[:n].copy(), self._q[:n].copy()
        chunks, left = [], np.zeros(seen.shape[1])
        for a in range(0, n, ALIKE_CHUNK):
            sl = slice(a, a + ALIKE_CHUNK)
            x, J = linearise(q[sl])
            refitted = _refitted(y[sl] - x, J, seen[sl])
            rss, drop, _ = leave_one_out(y[sl] - x, J, seen[sl], refitted)
            left += (rss[:, None] - drop).sum(axis=0)
            chunks.append((sl, x, J, refitted))
            yield
        alike = alike_markers(left / s2, tested)
        if not alike.size:
            return alike
        total = np.zeros(seen.shape[1])
        for sl, x, J, refitted in chunks:
            rest = left_out(y[sl] - x, J, seen[sl], int(alike[0]), refitted)
            total += np.einsum("tmd,tmd->m", rest, rest)
            yield
        m = total / (self.D * s2 * np.maximum(seen.sum(axis=0), 1))
        return alike if not (tested & (m > limit)).any() else alike[:0]


def finish_steps(steps):
    """Run a generator of steps to its end: its return value."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value


# --------------------------------------------------------------------------- which marker: leave one out
def _refitted(r, J, seen):
    """The residuals ``(T, M, D)`` after one Gauss-Newton step of each frame's pose, the Jacobian ``(T, M, D, Q)``
    with missing markers' rows zero, and ``(J^T J)^{-1}`` ``(T, Q, Q)``."""
    T, M, D, Q = J.shape
    J = np.where(seen[..., None, None], J, 0.0)
    Jf = J.reshape(T, M * D, Q)
    A = np.swapaxes(Jf, 1, 2) @ Jf
    A = A + np.eye(Q) * (1e-10 * np.maximum(np.trace(A, axis1=1, axis2=2) / Q, 1e-300))[:, None, None]
    G = np.linalg.inv(A)
    rf = np.where(seen[..., None], r, 0.0).reshape(T, M * D)
    step = (G @ (np.swapaxes(Jf, 1, 2) @ rf[..., None]))  # (T, Q, 1): the pose's Gauss-Newton step
    rf = rf - (Jf @ step)[..., 0]
    return rf.reshape(T, M, D), J, G


def _times_g(J, G):
    """``J G`` per frame: ``(T, M, D, Q)`` from ``J (T, M, D, Q)`` and ``G (T, Q, Q)``, one product a frame."""
    T, M, D, Q = J.shape
    return (J.reshape(T, M * D, Q) @ G).reshape(T, M, D, Q)


def _pinv_psd(B):
    """Pseudo-inverse of symmetric positive semi-definite blocks ``(..., D, D)`` (the directions the pose
    absorbs, eigenvalues below :data:`_ABSORBED`, left out), and their ranks ``(...)``."""
    w, V = np.linalg.eigh(B)
    keep = w > _ABSORBED
    inv = np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0)
    return (V * inv[..., None, :]) @ np.swapaxes(V, -1, -2), keep.sum(axis=-1)


def leave_one_out(r, J, seen, refitted=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each frame's residual sum of squares and how much leaving each marker out would lower it (module notes).

    Parameters
    ----------
    r : (T, M, D) float
        Residuals ``y - x`` at poses near each frame's fit (anything where a marker is missing).
    J : (T, M, D, Q) float
        ``dx/dq`` there.
    seen : (T, M) bool
        Markers present.
    refitted : tuple, optional
        :func:`_refitted` of ``(r, J, seen)``, where already computed.

    Returns
    -------
    rss : (T,) float
        Each frame's residual sum of squares after one Gauss-Newton step of its pose.
    drop : (T, M) float
        ``delta_{tk}``: how much lower it is with marker ``k`` left out of frame ``t`` (0 where missing).
    rank : (T, M) int
        The residual degrees of freedom that go with marker ``k`` (0 where missing).
    """
    r, J, G = _refitted(r, J, seen) if refitted is None else refitted
    D = r.shape[-1]
    H = np.einsum("tmdq,tmeq->tmde", _times_g(J, G), J)  # (T, M, D, D): each marker's block of the hat matrix
    Binv, rank = _pinv_psd(np.eye(D) - H)
    drop = ((Binv @ r[..., None])[..., 0] * r).sum(axis=-1)
    return np.einsum("tmd,tmd->t", r, r), drop, np.where(seen, rank, 0)


def left_out(r, J, seen, k: int, refitted=None) -> np.ndarray:
    """The residuals ``(T, M, D)`` of the markers with marker ``k`` left out of every frame (its own 0).

    With ``B = I - H_{kk}`` (module notes), leaving marker ``k`` out moves each frame's pose by
    ``-(J^T J)^{-1} J_k^T B^+ r_k``, and so the other markers' residuals by ``H_{ok} B^+ r_k``.

    Parameters
    ----------
    r, J, seen, refitted
        As for :func:`leave_one_out`.
    k : int
    """
    r, J, G = _refitted(r, J, seen) if refitted is None else refitted
    D = r.shape[-1]
    Hk = np.einsum("tmdq,teq->tmde", _times_g(J, G), J[:, k])  # (T, M, D, D): H_{ok}
    Binv, _ = _pinv_psd(np.eye(D) - Hk[:, k])
    out = r + (Hk @ (Binv @ r[:, k, :, None])[:, None])[..., 0]
    out[:, k] = 0.0
    return np.where(seen[..., None], out, 0.0)


def alike_markers(left, tested) -> np.ndarray:
    """The markers that explain a misfit alike: each of them left out, the rest fit within
    :data:`ALIKE_MARGIN` noise variances of the best.

    Parameters
    ----------
    left : (M,) float
        ``L_k``: what is left of the window's residual sum of squares, in noise variances, with marker ``k``
        left out of every frame.
    tested : (M,) bool
        Markers seen in enough frames to be judged.

    Returns
    -------
    (K,) int
        The best marker first, then the others within the margin; one marker where one stands out.
    """
    idx = np.flatnonzero(tested)
    if not idx.size:
        return idx
    v = left[idx]
    near = idx[v <= v.min() + ALIKE_MARGIN]
    return near[np.argsort(left[near], kind="stable")]


# --------------------------------------------------------------------------- scale
class ScaleReference(NamedTuple):
    """What the model says of its markers' scale (:func:`scale_reference`)."""

    pairs: np.ndarray  # (K, 2) int: markers on one rigid segment, their distance fixed by the model
    pair_d2: np.ndarray  # (K,) float: those distances squared
    spread: tuple[float, float]  # the least and largest rms distance of all markers from their centroid
    samples: np.ndarray  # (S, M, D) float: the sampled marker positions (for the spread of fewer markers)


@lru_cache(maxsize=64)
def scale_reference(model: Model) -> ScaleReference:
    """Marker pairs whose distance the model fixes, and the range of the markers' spread.

    The spread's range is taken over :data:`SCALE_SAMPLES` points of a Halton sequence (deterministic)
    through the rotational pose coordinates' ranges (the joints' ranges, or a wide default) and the
    parameters' prior intervals. A pair of markers on one segment is kept where its distance is the
    same at every sample (to ``1e-9`` of it): a parameter that moves one marker of a segment (a marker
    offset) leaves the pair out.
    """
    ranges = _rotation_ranges(model)
    lo = np.array([p.prior.lower for p in model.parameters], float)
    hi = np.array([p.prior.upper for p in model.parameters], float)
    rot = sorted(ranges)
    u = qmc.Halton(d=len(rot) + model.n_params, scramble=False).random(SCALE_SAMPLES)
    pose = np.zeros((SCALE_SAMPLES, model.n_pose))
    for n, k in enumerate(rot):
        a, b = ranges[k]
        pose[:, k] = a + (b - a) * u[:, n]
    theta = lo + (hi - lo) * u[:, len(rot):]
    x = marker_positions(model, theta, pose)
    segment = np.array([m.segment for m in model.markers])
    i, j = np.nonzero(np.triu(segment[:, None] == segment[None, :], 1))
    d2 = np.square(x[:, i] - x[:, j]).sum(axis=-1)
    rigid = np.all(np.abs(np.sqrt(d2) - np.sqrt(d2[0])) <= 1e-9 * np.sqrt(d2[0]), axis=0) & (d2[0] > 0)
    spread = _spread(x)
    return ScaleReference(np.stack([i[rigid], j[rigid]], axis=1), d2[0, rigid],
                          (float(spread.min()), float(spread.max())), x)


def _spread(x) -> np.ndarray:
    """The rms distance of the markers ``x (..., M, D)`` from their centroid ``(...)``."""
    c = x - x.mean(axis=-2, keepdims=True)
    return np.sqrt(np.einsum("...md,...md->...", c, c) / x.shape[-2])


class Scale(NamedTuple):
    """A frame's scale against the model's (:meth:`ScaleCheck.check`)."""

    low: float  # the frame's scale over the model's, at least (observed / model)
    high: float  # and at most (equal to low where rigid segments say)
    rigid: bool  # from distances within rigid segments (else from the markers' spread)
    unit: str | None  # the stream's likely unit, where one fits
    factor: float | None  # the declared unit over that unit (the scale it would give)

    @property
    def off(self) -> bool:
        """Whether the frame is off scale (beyond :data:`SCALE_OFF` of the model's either way)."""
        return self.high < 1.0 / SCALE_OFF or self.low > SCALE_OFF


class ScaleCheck:
    """Each frame's scale against the model's, to see a stream in the wrong unit (module notes).

    :meth:`check` looks at one frame; a session asks every :data:`SCALE_EVERY` frames once the first
    frames were on scale (a stream's unit does not come and go), and at every frame while one is off.
    Over the last :data:`SCALE_KEEP` frames checked: the rigid segments' scale is their median (a frame
    with a marker astray, a swapped label, does not move it); the markers' spread bounds the scale only
    loosely in one frame (a bent chain draws its markers together), and the frames together narrow it as
    the poses change: the scale lies within every frame's bounds but the most extreme tenth either way
    (where they still disagree, between the medians of the bounds).

    Parameters
    ----------
    model : Model
    declared : str
        The unit the stream says it is in (its coordinates are converted from it to the model's).
    """

    def __init__(self, model: Model, declared: str):
        self.ref = scale_reference(model)
        self._i, self._j = self.ref.pairs[:, 0], self.ref.pairs[:, 1]
        self._d2 = float(self.ref.pair_d2.sum())
        diff = np.zeros((self._i.size, len(model.markers)))  # (K, M): y_i - y_j of each pair as one product
        diff[np.arange(self._i.size), self._i] = 1.0
        diff[np.arange(self._i.size), self._j] = -1.0
        self._diff = diff
        self._all = len(model.markers)
        self._subsets: dict = {}
        self._rigid: deque = deque(maxlen=SCALE_KEEP)  # the scale of each recent frame's rigid segments
        self._low: deque = deque(maxlen=SCALE_KEEP)  # the scale each recent frame's spread allows, at least
        self._high: deque = deque(maxlen=SCALE_KEEP)  # and at most
        base = STREAM_UNITS_MM.get(declared)
        self._units = [] if base is None else [(u, base / mm) for u, mm in STREAM_UNITS_MM.items() if u != declared]

    def check(self, y, present, keep: bool = True) -> Scale | None:
        """The scale of frame ``y (M, D)`` (model units; ``present (M,)`` its markers seen) with the recent
        frames checked, or None when too few markers are seen to tell (one pair on a rigid segment, or two
        markers). ``keep`` False: the frame alone, not remembered (a frame that will not be used)."""
        n = int(np.count_nonzero(present))
        if self._i.size:
            rho = None
            if n == self._all:
                d = (self._diff @ y).ravel()
                rho = math.sqrt(float(d @ d) / self._d2)
            else:
                both = present[self._i] & present[self._j]
                if both.any():
                    d = y[self._i[both]] - y[self._j[both]]
                    rho = math.sqrt(float(np.einsum("kd,kd->", d, d)) / float(self.ref.pair_d2[both].sum()))
            if rho is not None:
                if keep:
                    self._rigid.append(rho)
                    rho = statistics.median(self._rigid)  # a frame with a marker astray does not move it
                return self._named(rho, rho, True)
        if n < 2:
            return None
        if n == self._all:
            lo, hi = self.ref.spread
        else:
            lo, hi = self._subset(present)
            y = y[present]
        c = (y - y[0]).ravel()  # about one marker: no rounding from the data's distance to the origin
        m = c.reshape(n, -1).sum(axis=0) / n
        s = math.sqrt(max(float(c @ c) / n - float(m @ m), 0.0))
        if not keep:
            return self._named(s / hi, s / lo, False)
        self._low.append(s / hi)
        self._high.append(s / lo)
        lows, highs = sorted(self._low), sorted(self._high)
        k = len(lows) // 10  # the most extreme tenth either way left out: a frame with a marker astray
        low, high = lows[-1 - k], highs[k]
        if not low <= high:  # the frames disagree (poses beyond the sampled ones): the medians, an interval still
            low, high = statistics.median(lows), statistics.median(highs)
        return self._named(low, high, False)

    def _subset(self, present) -> tuple[float, float]:
        """The range of the spread of the markers ``present`` only (kept per set of markers)."""
        key = present.tobytes()
        if key not in self._subsets:
            s = _spread(self.ref.samples[:, present])
            self._subsets[key] = (float(s.min()), float(s.max()))
        return self._subsets[key]

    def _named(self, low: float, high: float, rigid: bool) -> Scale:
        """The finding, with the stream unit whose factor lies nearest ``[low, high]`` (within
        :data:`SCALE_MATCH`) where the frame is off scale."""
        best, unit, factor = math.log(SCALE_MATCH), None, None
        if low > 0 and (high < 1.0 / SCALE_OFF or low > SCALE_OFF):
            a, b = math.log(low), math.log(high)
            for u, rho in self._units:
                v = math.log(rho)
                gap = max(a - v, v - b, 0.0)
                if gap <= best:
                    best, unit, factor = gap, u, rho
        return Scale(low, high, rigid, unit, factor)


# --------------------------------------------------------------------------- bounds
def gaussian_bound_z(raw, sd, lower, upper) -> np.ndarray:
    """How far beyond its prior's bounds the unbounded solve puts each parameter, in sd (module notes).

    Parameters
    ----------
    raw, sd : (P,) float
        The unbounded posterior mean and its sd.
    lower, upper : (P,) float

    Returns
    -------
    (P,) float
        ``(lower - raw) / sd`` below the interval, ``(raw - upper) / sd`` above it, ``-inf`` inside.
    """
    below, above = (lower - raw) / sd, (raw - upper) / sd
    return np.where(raw < lower, below, np.where(raw > upper, above, -np.inf))


def grid_bound_z(log_w, at=None) -> tuple[np.ndarray, np.ndarray]:
    """Where each parameter's marginal posterior on a grid is largest at an edge, how far beyond it
    its peak lies, in sd (module notes).

    Parameters
    ----------
    log_w : (n_1, ..., n_P) float
        Log posterior weights on the grid, one axis per parameter.
    at : tuple of int, optional
        The index of the grid's most probable point: only the parameters for which it lies on an edge are
        looked at (a marginal over the other axes costs a pass over the grid).

    Returns
    -------
    z : (P,) float
        ``-inf`` where the marginal's largest weight is inside; ``inf`` where it falls from the edge by
        more than a unit a step without bending down.
    edge : (P,) int
        -1 at the lower edge, 1 at the upper, 0 inside.
    """
    P = log_w.ndim
    z, edge = np.full(P, -np.inf), np.zeros(P, dtype=int)
    for a in range(P):  # one to three parameters
        if at is not None and at[a] not in (0, log_w.shape[a] - 1):
            continue
        other = tuple(b for b in range(P) if b != a)
        m = np.logaddexp.reduce(log_w, axis=other) if other else log_w
        if m.size < 3:
            continue
        k = int(np.argmax(m))
        if k not in (0, m.size - 1):
            continue
        w = m if k == 0 else m[::-1]
        d1, d2 = float(w[0] - w[1]), float(w[0] - w[2])
        if not d1 > 0:  # flat at the edge (a prior alone): the posterior does not rise toward the bound
            continue
        bend = d2 - 2.0 * d1
        z[a] = (2.0 * d1 - 0.5 * d2) / math.sqrt(bend) if bend > 0 else (math.inf if d1 > 1.0 else 0.0)
        edge[a] = -1 if k == 0 else 1
    return z, edge
