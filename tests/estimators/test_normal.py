import numpy as np
import pytest
from scipy import sparse

from skelid.estimators.uncertainty.normal import eliminate_poses, solve_normal


def _dense(Jq, Jt, R):
    T, m, Q = Jq.shape
    P = Jt.shape[-1]
    J = np.zeros((T * m, P + T * Q))
    J[:, :P] = Jt.reshape(T * m, P)
    for t in range(T):
        J[t * m:(t + 1) * m, P + t * Q:P + (t + 1) * Q] = Jq[t]
    N = J.T @ J
    N[P:, P:] += R.toarray()
    return N


@pytest.mark.parametrize("penalised", [True, False])
def test_eliminated_normal_equations_equal_the_dense_solve(penalised):
    rng = np.random.default_rng(0)
    T, m, Q, P = 12, 4, 2, 3
    Jq, Jt = rng.normal(size=(T, m, Q)), rng.normal(size=(T, m, P))
    if penalised:
        D = sparse.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(T - 2, T))
        R = sparse.kron(D.T @ D, sparse.diags([3.0, 0.5])).tocsc()
    else:
        R = sparse.csc_matrix((T * Q, T * Q))
    el = eliminate_poses(Jq, Jt, R if penalised else None)
    N = _dense(Jq, Jt, R)
    np.testing.assert_allclose(el.S, np.linalg.inv(np.linalg.inv(N)[:P, :P]), rtol=1e-9)
    g_t, g_q = rng.normal(size=(5, P)), rng.normal(size=(5, T, Q))
    d_t, d_q = solve_normal(el, g_t, g_q)
    ref = np.linalg.solve(N, np.concatenate([g_t, g_q.reshape(5, -1)], axis=1).T).T
    np.testing.assert_allclose(d_t, ref[:, :P], rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(d_q.reshape(5, -1), ref[:, P:], rtol=1e-7, atol=1e-10)
