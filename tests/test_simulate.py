"""Synthetic trials: the posture-limited motion near singular poses, and the building blocks' arguments."""

import warnings

import numpy as np
import pytest

from skelid.errors import ModelError, SettingError
from skelid.model.kinematics import marker_positions
from skelid.simulate import builtin_model, simulate_motion, simulate_posture, soft_tissue_artefact, sta_rms


def test_a_posture_trial_keeps_every_one_axis_joint_in_its_span():
    model = builtin_model("case-a")
    trial = simulate_posture(model, [240.0], 60, 0.0, (150.0, 172.0), np.random.default_rng(0))
    hinge = [k for k, d in enumerate(model.dofs)
             if d.kind == "R" and model.segments[d.segment].joint.type in ("revolute", "hinge")]
    assert len(hinge) == 2
    deg = np.degrees(trial.pose[:, hinge])
    np.testing.assert_allclose(deg.min(axis=0), 150.0, atol=1e-9)
    np.testing.assert_allclose(deg.max(axis=0), 172.0, atol=1e-9)
    # noise-free: the markers are the model's at the true geometry and poses
    np.testing.assert_allclose(trial.data.positions, marker_positions(model, np.array([240.0]), trial.pose))
    assert trial.data.rate == 100.0 and trial.theta.tolist() == [240.0]


CASE_A = builtin_model("case-a")
RNG = np.random.default_rng(0)
POSE = simulate_motion(CASE_A, 20, 100.0, np.random.default_rng(1))


@pytest.mark.parametrize("call, needle", [
    (lambda: simulate_motion(CASE_A, 0, 100.0, RNG), "n_frames=0 is not a number of frames"),
    (lambda: simulate_motion(CASE_A, -1, 100.0, RNG), "n_frames=-1 is not a number of frames"),
    (lambda: simulate_motion(CASE_A, 2.5, 100.0, RNG), "n_frames=2.5 is not a number of frames"),
    (lambda: simulate_motion(CASE_A, 10, 0.0, RNG), "sampling rate must be between"),
    (lambda: simulate_motion(CASE_A, 10, 100.0, None), "rng=None is not a numpy.random.Generator"),
    (lambda: soft_tissue_artefact(CASE_A, POSE, -1.0, 100.0, RNG), "amplitude=-1.0 is not a noise level"),
    (lambda: soft_tissue_artefact(CASE_A, POSE, np.inf, 100.0, RNG), "amplitude=inf is not a noise level"),
    (lambda: soft_tissue_artefact(CASE_A, POSE, np.nan, 100.0, RNG), "amplitude=nan is not a noise level"),
    (lambda: soft_tissue_artefact(CASE_A, POSE, 5.0, 0.0, RNG), "sampling rate must be between"),
    (lambda: soft_tissue_artefact(CASE_A, POSE[:, :2], 5.0, 100.0, RNG),
     r"pose of shape \(20, 2\) is not \(frames, 5\)"),
    (lambda: soft_tissue_artefact(CASE_A, POSE + 0j, 5.0, 100.0, RNG), "real, finite numbers"),
    (lambda: sta_rms(CASE_A, -2.0), "amplitude=-2.0 is not a noise level"),
    (lambda: simulate_posture(CASE_A, None, 10, 1.0, (0.0, 10.0), RNG), "theta=None: the true parameters"),
], ids=["motion-no-frames", "motion-negative-frames", "motion-fractional-frames", "motion-rate-0", "motion-no-rng",
        "artefact-negative", "artefact-inf", "artefact-nan", "artefact-rate-0", "artefact-pose-shape",
        "artefact-pose-complex", "rms-negative", "posture-no-theta"])
def test_the_building_blocks_name_the_bad_argument_in_one_line(call, needle):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # refused before numpy warns (divide by zero, complex parts discarded)
        with pytest.raises(SettingError, match=needle) as info:
            call()
    assert "\n" not in str(info.value) and "(fix: " in str(info.value)


@pytest.mark.parametrize("call", [lambda: simulate_motion(None, 10, 100.0, RNG),
                                  lambda: soft_tissue_artefact("case-a", POSE, 5.0, 100.0, RNG),
                                  lambda: builtin_model(5)], ids=["motion", "artefact", "builtin"])
def test_the_building_blocks_refuse_what_is_not_a_model(call):
    with pytest.raises(ModelError):
        call()


def test_the_building_blocks_still_build_a_trial():
    drift = soft_tissue_artefact(CASE_A, POSE, 5.0, 100.0, np.random.default_rng(2))
    assert drift.shape == (20, 3, 2) and np.isfinite(drift).all()
    assert sta_rms(CASE_A, 6.0) == pytest.approx(6.0 * np.sqrt(1 / 4 + 1 / 9))
    assert not soft_tissue_artefact(CASE_A, POSE, 0.0, 100.0, RNG).any()
