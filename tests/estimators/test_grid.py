import numpy as np
import pytest
from scipy.special import logsumexp

from skelid.estimators.fit.likelihood import frame_terms, log_det_pose_information
from skelid.estimators.fit.pose import fit_pose
from skelid.estimators.online.grid import MarkerGridFilter
from skelid.simulate import builtin_model, simulate

AXES = (np.linspace(240.0, 260.0, 9),)


def test_fit_equals_folding_update_and_keeps_history():
    model = builtin_model("case-b")
    trial = simulate(model, sigma=4.0, n_frames=40, rng=np.random.default_rng(1))
    filt = MarkerGridFilter(model, sigma=4.0, axes=AXES, history_steps=(10, 40)).fit(trial.data)
    state = filt.init_state()
    for frame in trial.data.positions:
        state = filt.update(state, frame)
    post = filt.posterior(state)
    np.testing.assert_allclose(post.log_weights, filt.posterior_.log_weights, atol=1e-12)
    assert [s for s, _ in filt.posterior_.history] == [10, 40]
    assert logsumexp(filt.posterior_.log_weights) == pytest.approx(0.0, abs=1e-12)
    assert state.rss.shape == (9,)  # O(grid) state, no history of frames


def test_grid_equals_brute_force_enumeration():
    """Per hypothesis and frame: the best pose from the true pose, RSS and log det, summed."""
    model = builtin_model("case-b")
    sigma = 3.0
    trial = simulate(model, sigma=sigma, n_frames=15, rng=np.random.default_rng(2))
    filt = MarkerGridFilter(model, sigma=sigma, axes=AXES, n_iter=30).fit(trial.data)
    y = trial.data.positions
    log_w = []
    for L in AXES[0]:
        q, rss = fit_pose(model, np.array([L]), y, trial.pose, n_iter=60)
        _, Jq, _ = frame_terms(model, np.array([L]), q, y)
        log_w.append(-rss.sum() / (2 * sigma**2) - 0.5 * log_det_pose_information(Jq).sum())
    log_w = np.array(log_w) - logsumexp(log_w)
    np.testing.assert_allclose(filt.posterior_.log_weights, log_w, atol=1e-6)


def test_noise_free_data_put_the_mode_on_the_truth():
    model = builtin_model("case-a")
    trial = simulate(model, theta=[247.5], sigma=0.0, n_frames=30, rng=np.random.default_rng(3))
    filt = MarkerGridFilter(model, sigma=1.0, axes=(np.linspace(240, 255, 7),)).fit(trial.data)
    assert filt.posterior_.map[0] == 247.5
    assert filt.map_path_[-1] == 247.5


def test_a_still_trial_gives_placement_not_identified():
    """Two hundred frames of one pose: the grid posterior narrows, but only through where the model puts
    the markers; the status is 'placement' with a still-joint warning, as the marker method says. A moving
    trial stays 'identified'."""
    import warnings

    from skelid.errors import SkelidWarning

    model = builtin_model("case-a")
    moving = simulate(model, n_frames=300, sigma=5.0, rng=np.random.default_rng(0)).data
    rng = np.random.default_rng(1)
    still = moving.replace(positions=np.repeat(moving.positions[:1], 200, 0) + rng.normal(0.0, 1.0, (200, 3, 2)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkelidWarning)
        r_still = MarkerGridFilter(model).fit(still).result()
        r_moving = MarkerGridFilter(model).fit(moving).result()
    assert r_still.parameters["L2"].status == "placement"
    assert "still-joint" in [w.code for w in r_still.warnings]
    assert r_moving.parameters["L2"].status == "identified"
    assert "still-joint" not in [w.code for w in r_moving.warnings]
