"""A soft-tissue artefact that follows the pose is found in the residuals of an OpenSim fit and widens it."""

from __future__ import annotations

import numpy as np
import pytest

from skelid.data import MarkerData
from skelid.estimators.checks.pose_artefact import artefact_coordinates, pose_artefact
from skelid.io.osim import osim_parameters, read_osim
from skelid.model.kinematics import forward_kinematics, marker_positions
from skelid.scaling import fit_osim, fit_scales_and_offsets
from tests.helpers import leg_walk_poses
from tests.test_scaling import MODEL, marker_xml

FRAMES = 240


@pytest.fixture(scope="module")
def leg(tmp_path_factory):
    d = tmp_path_factory.mktemp("artefact")
    (d / "leg.osim").write_text(MODEL.format(markers=marker_xml()))
    base, info = read_osim(d / "leg.osim")
    model = osim_parameters(base, info, "bodies", "offsets")
    theta = model.theta_nominal.copy()
    for k, p in enumerate(model.parameters):
        if p.kind == "scale":
            theta[k] = {"pelvis": 1.02, "thigh": 1.1, "shank": 0.95}[p.target]
    q = leg_walk_poses(FRAMES, model.n_pose)
    return d / "leg.osim", model, theta, q


def _markers(model, theta, q, rng, noise: float, artefact_rms: float = 0.0) -> MarkerData:
    x = marker_positions(model, theta, q)
    if artefact_rms:
        c = artefact_coordinates(model)
        dq = q[:, c] - q[:, c].mean(axis=0)
        seg = np.asarray(model.marker_segment)
        V = {b: rng.normal(size=(3, c.size)) for b in np.unique(seg)}  # each body's skin slides as a whole
        R = forward_kinematics(model, theta, q).R_world_seg[:, seg]
        d = np.einsum("tmij,mjc,tc->tmi", R, np.stack([V[b] + 0.3 * rng.normal(size=(3, c.size)) for b in seg]), dq)
        x = x + d * artefact_rms / np.sqrt(np.mean(d**2))
    x = x + rng.normal(0.0, noise, x.shape)
    return MarkerData(x, model.marker_names, 60.0, "mm", "walk.trc")


def test_white_noise_shows_no_artefact(leg):
    path, model, theta, q = leg
    fit = fit_osim(path, [_markers(model, theta, q, np.random.default_rng(1), 2.0)])
    art = fit.result["artefact"]
    assert not art["present"] and not art["warn"] and art["p_value"] > 0.01
    assert not any("soft-tissue artefact of about" in w for w in fit.warnings)
    assert art["sigma_white"][0] == pytest.approx(2.0, rel=0.15)


def test_an_artefact_that_follows_the_pose_is_named_estimated_and_widens_the_intervals(leg):
    """The slide is found, its slopes estimated with the geometry (which they move by over half an sd), and
    some scale's interval is far wider than in the same fit on the same poses without the slide."""
    path, model, theta, q = leg
    rng = np.random.default_rng(2)
    data = _markers(model, theta, q, rng, 0.5, artefact_rms=8.0)
    fit = fit_osim(path, [data])
    art = fit.result["artefact"]
    assert art["present"] and art["p_value"] < 1e-6
    assert 8.0 / 3 < art["rms"] < 8.0 * 3  # the moment estimate of its size, within a factor of three
    assert art["sigma_white"][0] < 8.0 / 2  # the white part is told apart from the slide
    assert any("soft-tissue artefact of about" in w for w in fit.warnings)
    assert art["estimated_with_geometry"] and art["largest_sd_ratio"] > 0.5
    scales = [p.name for p in fit.model.parameters if p.kind == "scale"]
    # the reported sd is never below the bound of the model with the slide
    assert all(fit.result[n]["sd"] >= fit.result[n]["crlb_sd"] * (1 - 1e-9) for n in scales)
    plain = fit_osim(path, [_markers(model, theta, q, np.random.default_rng(2), 0.5)])
    ratio = [fit.result[n]["sd"] / plain.result[n]["sd"] for n in scales]
    assert max(ratio) > 1.5


def test_the_added_covariance_is_the_artefacts_effect_through_the_fit(leg):
    """With the fit's linearisation, the term is H^-1 G Sigma_V G^T H^-1: symmetric, positive semi-definite,
    and proportional to the artefact's variance."""
    path, model, theta, q = leg
    rng = np.random.default_rng(3)
    y = _markers(model, theta, q, rng, 0.5, artefact_rms=6.0).positions
    hinv = np.eye(model.n_params) * 1e-3
    a = pose_artefact(model, theta, [y], [q], np.array([3.0]), hinv)
    assert a.present
    w = np.linalg.eigvalsh(a.cov)
    assert np.allclose(a.cov, a.cov.T) and w.min() > -1e-9 * w.max()
    b = pose_artefact(model, theta, [y], [q], np.array([3.0]), 2.0 * hinv)
    assert np.allclose(b.cov, 4.0 * a.cov)


def test_a_still_trial_without_the_slide_sizes_the_walks_slide_from_its_excess(leg):
    """A static trial (the artefact is zero at its pose) and a walk whose markers slide by 8 mm rms from
    there: with one white level per marker for both trials (one camera system), the walk's slide is its
    excess over the static trial's noise; a level per marker and trial took most of it for noise."""
    from skelid.estimators.checks import pose_artefact as pa

    path, model, theta, q = leg
    rng = np.random.default_rng(4)
    c = artefact_coordinates(model)
    seg = np.asarray(model.marker_segment)
    V = np.stack([rng.normal(size=(3, c.size)) for _ in seg]) + np.stack(
        [{b: rng.normal(size=(3, c.size)) for b in np.unique(seg)}[b] for b in seg])
    still = np.repeat(q[:1], 60, axis=0)

    def trial(qq):
        R = forward_kinematics(model, theta, qq).R_world_seg[:, seg]
        d = np.einsum("tmij,mjc,tc->tmi", R, V, qq[:, c] - q[0, c])
        return d, marker_positions(model, theta, qq)
    d_walk, x_walk = trial(q)
    k = 8.0 / np.sqrt(np.mean(d_walk**2))
    walk = MarkerData(x_walk + k * d_walk + rng.normal(0.0, 0.5, x_walk.shape), model.marker_names, 60.0, "mm", "walk")
    x_still = marker_positions(model, theta, still)
    static = MarkerData(x_still + rng.normal(0.0, 0.5, x_still.shape), model.marker_names, 60.0, "mm", "static")
    fit = fit_osim(path, [static, walk])
    m, ys = fit.model, [t.positions for t in fit.trials]
    # where the sizes are read: the joint fit that knows of no slide (the result's geometry has it taken out)
    jo = fit_scales_and_offsets(m, ys, fit.joint.theta, fit.joint.poses)
    both = pa.pose_artefact(m, jo.theta, ys, jo.poses, jo.sigma, jo.cov)
    assert both.present
    n = np.mean(np.concatenate([np.sum((p[:, c] - np.concatenate(jo.poses)[:, c].mean(axis=0)) ** 2, axis=1)
                                for p in jo.poses]))
    # V's entries have variance 2 (shared plus own): the slide k V dq has slopes of variance 2 k^2
    # (a white level per marker and trial: 41 % short; one per marker for both trials: 18 %)
    assert both.tau_shared**2 + both.tau_own**2 == pytest.approx(2 * k**2, rel=0.3)
    assert both.rms == pytest.approx(np.sqrt((both.tau_shared**2 + both.tau_own**2) * n))



def test_a_slide_whose_slopes_cannot_be_told_from_the_geometry_is_left_out(monkeypatch):
    """Where the slopes' posterior precision comes out indefinite in floating point (noise-free data that one
    factor per body cannot fit), the joint fit goes on without the slide, with the artefact's term, instead of
    stopping on a LinAlgError; a step after the first that fails keeps the last one."""
    import skelid.estimators.checks.pose_artefact as pa
    from skelid import scaling

    def indefinite(*args, **kwargs):
        raise np.linalg.LinAlgError("leading minor not positive definite")

    monkeypatch.setattr(pa, "joint_slide", indefinite)

    class Art:
        slide = object()

    class Jo:
        info_trials, score_trials, sigma, dof = (np.eye(2),), (np.zeros(2),), np.ones(1), np.ones(1)
        theta = np.ones(2)

    monkeypatch.setattr(scaling, "_prior_terms", lambda model, theta: (np.zeros(2), np.ones(2)))
    assert scaling._slide_fit(None, Jo(), Art()) is None
