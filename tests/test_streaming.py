import numpy as np
import pytest

from skelid.estimators.online.grid import MarkerGridFilter
from skelid.estimators.paper import PaperFilter
from skelid.io import read_trc, write_trc
from skelid.simulate import builtin_model, simulate
from skelid.streaming import fit_online, iter_chunks, iter_trc


def test_trc_chunks_are_the_file(tmp_path):
    trial = simulate(builtin_model("case-b"), sigma=3.0, n_frames=45, rng=np.random.default_rng(0))
    y = np.array(trial.data.positions)
    y[10:13, 1] = np.nan
    path = tmp_path / "t.trc"
    write_trc(path, trial.data.replace(positions=y))
    whole = read_trc(path)
    chunks = list(iter_trc(path, chunk_frames=7))
    assert [c.n_frames for c in chunks] == [7] * 6 + [3]
    np.testing.assert_array_equal(np.concatenate([c.positions for c in chunks]), whole.positions)
    assert {(c.names, c.rate, c.units) for c in chunks} == {(whole.names, whole.rate, whole.units)}


def test_online_grid_filter_over_chunks_equals_fit():
    model = builtin_model("case-a")
    trial = simulate(model, sigma=10.0, n_frames=60, rng=np.random.default_rng(1))
    est = MarkerGridFilter(model, axes=(np.linspace(220, 280, 25),), history_steps=(20,))
    fitted = est.fit(trial.data)
    res = fit_online(est, iter_chunks(trial.data, 17), keep_path=True)
    assert (res.n_frames, res.n_chunks) == (60, 4)
    np.testing.assert_array_equal(res.posterior.log_weights, fitted.posterior_.log_weights)
    np.testing.assert_array_equal(res.map_path, fitted.map_path_)
    assert [h[0] for h in res.state.history] == [20]  # O(K) state: snapshots only where asked


def test_online_paper_filter_from_a_file(tmp_path):
    model = builtin_model("case-a")
    trial = simulate(model, sigma=5.0, n_frames=80, rng=np.random.default_rng(2))
    path = tmp_path / "t.trc"
    write_trc(path, trial.data)
    res = fit_online(PaperFilter(model), iter_trc(path, chunk_frames=25))
    fitted = PaperFilter(model).fit(read_trc(path))
    assert res.n_frames == 80
    assert res.posterior.summary()["L2"]["mean"] == pytest.approx(fitted.posterior_.summary()["L2"]["mean"],
                                                                   rel=1e-9)
