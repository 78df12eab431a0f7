"""The live stopping rule (``target_sd``) and the default live form of a model with few parameters."""

import math
from pathlib import Path

import numpy as np
import pytest

from skelid.errors import SettingError
from skelid.estimators.sampler import sample_prior
from skelid.live import DONE_NOISE_DOF, Session, message, run
from skelid.model import load_model
from skelid.simulate import builtin_model, simulate

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


@pytest.fixture(scope="module")
def case_a():
    return builtin_model("case-a")


@pytest.fixture(scope="module")
def moving(case_a):
    return simulate(case_a, n_frames=400, sigma=5.0, rng=np.random.default_rng(1)).data


@pytest.mark.parametrize("target,words", [
    ({"L9": 1.0}, "target_sd names 'L9', which 'case_a' does not have"),
    (-1.0, "target_sd of L2 must be above 0"),
    (0, "target_sd of L2 must be above 0"),
    (float("nan"), "target_sd of L2 must be finite"),
    (float("inf"), "target_sd of L2 must be finite"),
    ("1", "target_sd of L2 must be a number"),
    (True, "target_sd of L2 must be a number"),
    ({}, "target_sd names no parameter"),
    ({"L2": None}, "target_sd of L2 must be a number"),
])
def test_a_target_that_cannot_be_reached_is_refused_in_one_line(case_a, target, words):
    with pytest.raises(SettingError) as exc:
        Session(case_a, target_sd=target)
    assert words in str(exc.value) and "\n" not in str(exc.value)


def test_without_a_target_nothing_is_done_and_the_message_says_null(case_a, moving):
    s = Session(case_a, labels=moving.names, rate=100.0)
    est = [s.push(f) for f in moving.positions[:60]][-1]
    assert est.done is None and message(est)["done"] is None
    assert all(a.dof >= 0 for a in s.advice())
    assert s._kept is None  # no frames kept without a stopping rule
    assert Session(case_a, method="grid", target_sd=1.0)._kept is None  # nor in the grid form


def test_a_session_says_done_once_the_target_is_reached_and_not_before(case_a, moving):
    target = 1.0
    s = Session(case_a, labels=moving.names, rate=100.0, target_sd=target)
    ests = []
    for f in moving.positions:
        ests.append(s.push(f))
        if ests[-1].done:
            break
    done = ests[-1]
    assert done.done, "400 frames of motion at 5 mm noise reach an sd of 1 mm"
    p = done.parameters["L2"]
    assert done.healthy and p.status == "identified" and p.sd <= target
    assert not any(e.done for e in ests[:-1])
    # case A leaves one residual degree of freedom a frame for the noise level: done waits for DONE_NOISE_DOF
    assert done.frame >= DONE_NOISE_DOF
    # done comes once the target is reached, verified at every frame's smoothed pose: a check that finds the sd
    # still above it is made again once the frames have grown by an eighth
    reached = [e.frame for e in ests if e.parameters["L2"].sd <= target and e.healthy
               and e.parameters["L2"].status == "identified" and e.frame >= DONE_NOISE_DOF]
    assert reached and done.frame - reached[0] <= max(50, reached[0] // 8) + 1, (reached[0], done.frame)
    (advice,) = s.advice()
    assert advice.text.startswith("done: every requested parameter has reached its target sd")
    assert "L2 sd" in advice.text and "<= 1 mm" in advice.text
    assert advice.dof == -1 and advice.joint == "" and advice.sd_after == advice.sd_now == p.sd
    msg = message(done, s.advice())
    assert msg["done"] is True and msg["advice"][0]["text"].startswith("done:")


def test_two_frames_are_never_done_on_their_own_noise_level(case_a):
    """The grid form once said done after two frames of a still arm at 5 mm noise: their two residual degrees
    of freedom put the noise at 0.4 mm and L2's sd at 0.45 mm (7 sd off the truth)."""
    from skelid.model.kinematics import marker_positions

    y0 = marker_positions(case_a, case_a.theta_center, np.array([-35.2, 2.7, 1.05, 1.25, 0.36]))
    frames = y0[None] + np.random.default_rng(3).normal(0.0, 5.0, (60, 3, 2))
    for method in ("grid", "auto"):
        s = Session(case_a, labels=case_a.marker_names, rate=100.0, method=method, target_sd=5.0)
        assert not any(s.push(f).done for f in frames)
    known = Session(case_a, labels=case_a.marker_names, rate=100.0, sigma=5.0, target_sd=5.0)
    assert any(known.push(f).done for f in frames)  # a stated noise level needs no residuals


def test_a_still_stream_is_never_done(case_a, moving):
    """Frames of one pose leave the estimate on where the model places the markers ('placement'), however
    small its sd: the stopping rule waits for motion."""
    still = np.repeat(moving.positions[:1], 300, axis=0)
    still = still + np.random.default_rng(2).normal(0.0, 0.01, still.shape)
    s = Session(case_a, labels=moving.names, rate=100.0, target_sd=50.0)
    ests = [s.push(f) for f in still]
    assert not any(e.done for e in ests)
    assert ests[-1].parameters["L2"].status != "identified"


def test_a_target_for_some_parameters_ignores_the_others():
    model = load_model(EXAMPLES / "tennis_arm.toml")
    trial = simulate(model, n_frames=300, sigma=0.001, rng=np.random.default_rng(4)).data
    asked = {"elbow_x": 0.05}  # within reach; the other five are not asked about
    s = Session(model, labels=trial.names, units=trial.units, rate=100.0, target_sd=asked)
    est = None
    for f in trial.positions:
        est = s.push(f)
        if est.done:
            break
    assert est.done
    ps = est.parameters
    assert ps["elbow_x"].sd <= 0.05
    (advice,) = s.advice()
    assert "elbow_x sd" in advice.text and "wrist" not in advice.text


def test_run_stops_at_the_first_done_estimate_and_its_message_says_so(case_a, moving):
    class Sink:
        def __init__(self):
            self.messages = []

        def send(self, msg):
            self.messages.append(msg)

    sink = Sink()
    s = Session(case_a, labels=moving.names, rate=100.0, target_sd=1.0)
    est = run(s, iter(moving.positions), [sink], until_done=True)
    assert est.done and sink.messages[-1]["done"] is True
    assert sink.messages[-1]["advice"][0]["text"].startswith("done:")
    assert len(sink.messages) == est.frame < len(moving.positions)
    assert not any(m["done"] for m in sink.messages[:-1])


def test_the_default_form_runs_the_gaussian_update_with_the_grid_beside_it_early(case_a):
    """A model with few parameters runs the Gaussian form (its motion model removes the per-frame poses'
    O(sigma^2) bias, which the grid form keeps); the grid runs beside it over the early frames, so a first
    linearisation in another basin is left (here the Gaussian form alone ended 13 sd off, on its bound)."""
    rng = np.random.default_rng([5, 10])
    theta = sample_prior(case_a, 1, rng)[0]
    data = simulate(case_a, theta=theta, n_frames=300, sigma=5.0, rng=rng).data
    s = Session(case_a, labels=data.names, rate=100.0)
    assert s.method == "gaussian"
    est = None
    for f in data.positions:
        est = s.push(f)
    p = est.parameters["L2"]
    assert abs(p.mean - theta[0]) < 3 * p.sd and p.status == "identified" and est.health == "ok"
    assert s._shadow is None  # left after the early frames
    assert Session(case_a, method="grid").method == "grid"
    assert math.isfinite(p.sd)


def _joint_by_joint(model, theta, q0, n_frames, sigma, rng):
    """Frames of a routine that turns one joint rotation at a time through the central 60 % of its range
    (1 s each, reached in 0.2 s), the others at rest, after 20 still frames."""
    from skelid.estimators.fit.pose import _rotation_ranges
    from skelid.model.kinematics import marker_positions

    ranges = _rotation_ranges(model)
    moves = [(k, 0.5 * (ranges[k][0] + ranges[k][1]), 0.3 * (ranges[k][1] - ranges[k][0]))
             for k, d in enumerate(model.dofs) if d.kind == "R" and model.parent_index[d.segment] >= 0]
    poses, q = [np.repeat(q0[None], 20, axis=0)], q0.copy()
    for i in range(n_frames // 100 + 1):
        k, centre, half = moves[i % len(moves)]
        start = q.copy()
        start[k] = centre
        ease = (0.5 - 0.5 * np.cos(np.linspace(0.0, np.pi, 20)))[:, None]
        sweep = np.repeat(start[None], 100, axis=0)
        sweep[:, k] = centre + half * np.sin(np.linspace(0.0, 2.0 * np.pi, 100, endpoint=False))
        poses += [q[None] + ease * (start - q)[None], sweep]
        q = sweep[-1].copy()
    poses = np.concatenate(poses)[:n_frames]
    return np.stack([marker_positions(model, theta, p) for p in poses]) + sigma * rng.standard_normal(
        (n_frames, len(model.markers), model.dim))


@pytest.mark.parametrize("checked", [True, False])
def test_done_under_the_motion_model_is_made_again_from_every_frame_at_its_smoothed_pose(monkeypatch, checked):
    """The 3-D arm turned one joint at a time: each frame linearised once, at the mean of its time, leaves a
    wrist coordinate 2.8 sd off when the sd reaches the target (3.6 sd where the estimate also held the frames
    linearised at their filtered poses); the estimate that says done is made from every frame linearised at its
    smoothed pose at the current mean, and holds the truth (under 1 sd here; without that check it does not)."""
    from skelid import live
    from skelid.estimators.sampler import sample_prior
    from skelid.simulate import simulate_motion

    if not checked:
        monkeypatch.setattr(live, "_DONE_KEEP", 0)
    model = load_model(EXAMPLES / "tennis_arm.toml")
    rng = np.random.default_rng([23, 2])
    theta = sample_prior(model, 1, rng)[0]
    q0 = simulate_motion(model, 1, 100.0, rng)[0]
    frames = _joint_by_joint(model, theta, q0, 1200, 0.001, np.random.default_rng([29, 2]))
    s = Session(model, labels=model.marker_names, units="m", rate=100.0, target_sd=0.001, rng=np.random.default_rng(0))
    est = None
    for f in frames:
        est = s.push(f)
        if est.done:
            break
    assert est.done
    z = np.abs(est.theta - theta) / np.sqrt(np.diag(est.cov))
    if checked:
        assert z.max() < 1.5, z
        assert s._verified_until > est.frame
    else:
        assert z.max() > 2.5, z  # the bias the check removes


@pytest.mark.parametrize("check", ["at done", "early", "none"])
def test_a_batch_fit_of_the_same_frames_leaves_a_wrong_basin(monkeypatch, check):
    """The 3-D arm following the advice: from its first frames the Gaussian form sat in another basin (the elbow
    centre 30-55 sd off, every frame's residuals within what its noise estimate allowed, health "ok"). A batch
    fit of the same frames, run as a check at done or after the early frames (either alone), puts the elbow
    elsewhere, and the basin whose frames fit better (eight times lower residuals) is taken: the estimate that
    says done holds the truth; without either check it does not."""
    from skelid import live
    from skelid.estimators.sampler import sample_prior
    from skelid.model.kinematics import marker_positions
    from skelid.simulate import simulate_motion

    if check != "at done":
        monkeypatch.setattr(live, "_batch_theta", lambda *a: None)
    if check != "early":
        monkeypatch.setattr(live, "_basin_fit", lambda *a: None)
    model = load_model(EXAMPLES / "tennis_arm.toml")
    rng = np.random.default_rng([23, 65])
    theta = sample_prior(model, 1, rng)[0]
    q = simulate_motion(model, 1, 100.0, rng)[0]
    noise = np.random.default_rng([29, 65])
    s = Session(model, labels=model.marker_names, units="m", rate=100.0, target_sd=0.001, rng=np.random.default_rng(0))
    plan, est = np.repeat(q[None], 20, axis=0), None
    for _ in range(40):
        for pose in plan:
            est = s.push(marker_positions(model, theta, pose) + 0.001 * noise.standard_normal((len(model.markers), 3)))
            if est.done:
                break
        if est.done:
            break
        q = plan[-1].copy()
        a = s.advice()[0]
        lo, hi = np.radians(a.lower_deg), np.radians(a.upper_deg)
        start = q.copy()
        start[a.dof] = 0.5 * (lo + hi)
        sweep = np.repeat(start[None], 100, axis=0)
        sweep[:, a.dof] = start[a.dof] + 0.5 * (hi - lo) * np.sin(np.linspace(0.0, 2.0 * np.pi, 100, endpoint=False))
        ease = (0.5 - 0.5 * np.cos(np.linspace(0.0, np.pi, 20)))[:, None]
        plan = np.concatenate([q[None] + ease * (start - q)[None], sweep])
    assert est.done
    z = np.abs(est.theta - theta) / np.sqrt(np.diag(est.cov))
    if check == "none":
        assert z.max() > 20.0, z  # the basin the checks leave
    else:
        assert z.max() < 3.0, z


@pytest.mark.parametrize("settled", [True, False])
def test_the_early_basin_check_compares_minima_not_a_minimum_with_the_estimate(monkeypatch, settled):
    """The 3-D arm turned one joint at a time, no target: after 200 frames the batch fit's minimum fits those
    frames better than the session's estimate does, yet lies in another basin (the estimate taken there ends
    more than 10 sd off at frame 260). Settled by the same joint fit, the session's own basin fits better still,
    and the session keeps it: under 6 sd at frame 260, where the estimate holds the 200 early frames only
    (the next block is folded in from frame 350), in which the last joints have barely moved."""
    from skelid import live
    from skelid.estimators.sampler import sample_prior
    from skelid.simulate import simulate_motion

    if not settled:
        basin_fit = live._basin_fit
        monkeypatch.setattr(live, "_basin_fit", lambda model, frames, rate, theta=None: basin_fit(model, frames, rate))
    model = load_model(EXAMPLES / "tennis_arm.toml")
    rng = np.random.default_rng([23, 25])
    theta = sample_prior(model, 1, rng)[0]
    q0 = simulate_motion(model, 1, 100.0, rng)[0]
    s = Session(model, labels=model.marker_names, units="m", rate=100.0, rng=np.random.default_rng(0))
    for f in _joint_by_joint(model, theta, q0, 260, 0.001, np.random.default_rng([29, 25])):
        est = s.push(f)
    z = np.abs(est.theta - theta) / np.sqrt(np.diag(est.cov))
    if settled:
        assert z.max() < 6.0, z
    else:
        assert z.max() > 10.0, z
