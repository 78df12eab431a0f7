"""Sums of products over frames and markers, done by BLAS.

The fits sum Jacobian products over frames and marker coordinates (``einsum("tkp,tkq->pq")``) and
form per-frame Gram matrices (``einsum("tkq,tkr->tqr")``). ``np.einsum`` does these in its own loops;
a matrix product over the flattened axes gives the same sums (to rounding: 2e-14 relative on the
fits' Jacobians) 4 to 9 times faster, which is most of the time of a full-body fit's Gauss-Newton
steps.

Examples
--------
>>> import numpy as np
>>> A = np.arange(24.0).reshape(2, 3, 4)
>>> bool(np.allclose(summed_gram(A), np.einsum("tkp,tkq->pq", A, A)))
True
>>> bool(np.allclose(frame_gram(A), np.einsum("tkq,tkr->tqr", A, A)))
True
"""

from __future__ import annotations

import contextlib
import functools

import numpy as np


def summed_gram(A, B=None, w=None) -> np.ndarray:
    """``(P, Q)``: ``sum_{t,k} A[t,k,p] w[k] B[t,k,q]`` (``einsum("tkp,k,tkq->pq")``).

    Parameters
    ----------
    A : (..., K, P) float
    B : (..., K, Q) float, optional
        ``A`` if None.
    w : (K,) float, optional
        Weights per row ``k`` (the second-to-last axis); none if None.
    """
    A = np.asarray(A, dtype=float)
    a = A.reshape(-1, A.shape[-1])
    b = a if B is None else np.asarray(B, dtype=float).reshape(-1, np.shape(B)[-1])
    if w is not None:
        w = np.broadcast_to(np.asarray(w, dtype=float), A.shape[:-1]).reshape(-1)
        return (a * w[:, None]).T @ b
    return a.T @ b


def summed_product(A, r) -> np.ndarray:
    """``(P,)``: ``sum_{t,k} A[t,k,p] r[t,k]`` (``einsum("tkp,tk->p")``)."""
    A = np.asarray(A, dtype=float)
    return A.reshape(-1, A.shape[-1]).T @ np.asarray(r, dtype=float).reshape(-1)


def frame_gram(A, B=None) -> np.ndarray:
    """``(T, P, Q)``: ``sum_k A[t,k,p] B[t,k,q]`` per frame (``einsum("tkp,tkq->tpq")``); ``B = A`` if None."""
    A = np.asarray(A, dtype=float)
    return np.matmul(A.swapaxes(-1, -2), A if B is None else np.asarray(B, dtype=float))


def psd_sqrt(S) -> np.ndarray:
    """Symmetric square root of a (nearly) symmetric positive semi-definite matrix (negative
    eigenvalues from rounding are taken as 0)."""
    w, V = np.linalg.eigh(0.5 * (S + np.swapaxes(S, -1, -2)))
    return (V * np.sqrt(np.clip(w, 0.0, None))[..., None, :]) @ np.swapaxes(V, -1, -2)


@functools.lru_cache(maxsize=1)
def _blas_controller():
    """The BLAS libraries of numpy and scipy, found once (a few ms); limiting them is then cheap.

    A controller sees only the libraries loaded when it is made. scipy ships an OpenBLAS of its own,
    loaded with ``scipy.linalg``; made before that import (the command line's start imports no scipy),
    the controller left it at its default threads: the gait2354 fit of subject01 took 17.2 s CPU for
    11.0 s wall on two cores, against 10.5 s CPU with ``OPENBLAS_NUM_THREADS=1``.
    """
    import scipy.linalg  # noqa: F401  (loads scipy's BLAS, so that the controller sees it)
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def one_blas_thread():
    """A context in which BLAS uses one thread: a fit is many small factorisations, which threads only slow
    down, and on busy cores OpenBLAS' threads spin while they wait for each other.

    Measured on the gait2354 fit on two busy cores: 8.5 s CPU with one thread, 84 s with OpenBLAS' default;
    one banded Cholesky of 3171 unknowns (a live session's check of an OpenSim model's early frames, beside
    two other busy processes) 25 s against milliseconds. Entering it costs about 10 microseconds. A no-op
    without ``threadpoolctl``.
    """
    try:
        controller = _blas_controller()
    except ImportError:  # pragma: no cover
        return contextlib.nullcontext()
    return controller.limit(limits=1, user_api="blas")
