"""Starting poses: rigid fits of segments, inverse kinematics, tracking."""

import numpy as np
import pytest

from skelid.estimators.fit.pose import rigid_poses, segment_placements, track_poses
from skelid.model import forward_kinematics, marker_positions, model_from_dict
from skelid.simulate import simulate
from tests.helpers import tree_3d, tree_3d_functional


def _three_markers_everywhere(model):
    """The test tree with a third (and fourth) marker on every segment."""
    d = model.to_dict()
    extra = {"thigh": [20, -350, -30], "shank": [35, -200, -40], "foot": [60, -10, -45],
             "arm": [[60, -20, 0], [-30, 40, 10]]}
    for seg, pos in extra.items():
        for j, xyz in enumerate(pos if isinstance(pos[0], list) else [pos]):
            d["markers"].append({"name": f"{seg}_extra{j}", "segment": seg, "position": xyz})
    return model_from_dict(d, "tree3d_rigid")


@pytest.mark.parametrize("make", [tree_3d, tree_3d_functional])
def test_rigid_fits_recover_every_coordinate_without_noise(make):
    model = _three_markers_everywhere(make())
    rng = np.random.default_rng(4)
    theta = model.theta_nominal + (rng.normal(0, 3, model.n_params) if model.n_params else 0)
    q_true = rng.uniform(-1.2, 1.2, size=(50, model.n_pose))
    q_true[:, :3] *= 500
    y = marker_positions(model, theta, q_true)
    R, p, placed = segment_placements(model, theta, y)
    assert placed.all()
    kin = forward_kinematics(model, theta, q_true)
    np.testing.assert_allclose(R, kin.R_world_seg, atol=1e-9)
    np.testing.assert_allclose(p, kin.p_world_seg, atol=1e-7)
    q, known = rigid_poses(model, theta, y)
    assert known.all()
    # same placement (angles may differ by 2 pi or take the other Euler branch)
    np.testing.assert_allclose(marker_positions(model, theta, q), y, atol=1e-7)


def test_segments_with_missing_or_collinear_markers_are_not_placed():
    model = _three_markers_everywhere(tree_3d())
    y = marker_positions(model, model.theta_nominal, np.zeros((3, model.n_pose)))
    y[1, list(model.marker_names).index("t1")] = np.nan  # thigh down to two markers
    _, _, placed = segment_placements(model, model.theta_nominal, y)
    thigh = model.segment_index["thigh"]
    assert placed[0].all() and not placed[1, thigh] and placed[1].sum() == 4
    q, known = rigid_poses(model, model.theta_nominal, y)
    # the hip (thigh vs pelvis) and the knee (shank vs thigh) are unknown in frame 1
    hip_knee = [k for k, d in enumerate(model.dofs) if d.segment in (thigh, thigh + 1)]
    assert not known[1, hip_knee].any() and known[1, :6].all() and known[0].all()


def test_tracking_finds_the_global_minimum_on_a_fast_3d_trial():
    """Segments with two markers and a fast, large motion: rigid fits + tracking still get every frame."""
    model = tree_3d()
    trial = simulate(model, n_frames=60, rate=20.0, sigma=0.0, rng=np.random.default_rng(7))
    q, rss = track_poses(model, trial.theta, trial.data.positions, np.random.default_rng(0))
    assert rss.max() < 1e-8


def test_tracking_with_a_stride_reaches_the_same_poses():
    model = tree_3d()
    trial = simulate(model, n_frames=120, rate=100.0, sigma=0.0, rng=np.random.default_rng(8))
    q, rss = track_poses(model, trial.theta, trial.data.positions, np.random.default_rng(0), stride=4)
    assert rss.max() < 1e-8
