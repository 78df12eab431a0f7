"""The live session: labelled frames in, an immutable estimate out after each."""

from pathlib import Path

import numpy as np
import pytest

from skelid.errors import DataError, ModelError
from skelid.estimators.marker import MarkerEstimator
from skelid.live import Session
from skelid.model import load_model
from skelid.simulate import builtin_model, simulate

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _run(session, positions):
    est = None
    for frame in positions:
        est = session.push(frame)
    return est


@pytest.mark.parametrize("name,method,sigma,frames", [("case-a", "gaussian", 1.0, 300),
                                                       ("case-a", "grid", 1.0, 150),
                                                       ("tennis_arm", "gaussian", 0.001, 200)])
def test_last_live_estimate_agrees_with_the_batch_estimate(name, method, sigma, frames):
    model = builtin_model(name) if name.startswith("case") else load_model(EXAMPLES / f"{name}.toml")
    trial = simulate(model, n_frames=frames, sigma=sigma, rng=np.random.default_rng(3))
    session = Session(model, labels=trial.data.names, units=trial.data.units, rate=trial.data.rate,
                      method=method, rng=np.random.default_rng(0))
    est = _run(session, trial.data.positions)
    batch = MarkerEstimator(model, rng=np.random.default_rng(0)).fit(trial.data)
    sd = np.sqrt(np.diag(batch.cov_))
    live = np.array([est.parameters[n].mean for n in model.parameter_names])
    np.testing.assert_array_less(np.abs(live - batch.theta_), sd)
    assert est.healthy and est.health == "ok"
    if method == "gaussian":  # with the batch method's motion model too
        smooth = Session(model, labels=trial.data.names, units=trial.data.units, rate=trial.data.rate,
                         method=method, cutoff=6.0, rng=np.random.default_rng(0))
        est = _run(smooth, trial.data.positions)
        np.testing.assert_array_less(np.abs(est.theta - batch.theta_), sd)


def test_estimate_is_immutable_and_complete():
    model = builtin_model("case-b")
    trial = simulate(model, n_frames=20, sigma=2.0, rng=np.random.default_rng(1))
    session = Session(model, labels=trial.data.names, units="mm", rate=100.0, method="gaussian")
    est = _run(session, trial.data.positions)
    assert est.frame == 20 and est.time == pytest.approx(0.2)
    assert set(est.marker_residuals) == set(model.marker_names)
    assert set(est.joint_centres) == {s.joint.name for s in model.segments}
    assert est.pose.shape == (model.n_pose,)
    with pytest.raises(ValueError):
        est.pose[0] = 1.0
    with pytest.raises(TypeError):
        est.parameters["x"] = None
    with pytest.raises(AttributeError):
        est.frame = 3
    p = est.parameters["L2"]
    assert p.interval[0] < p.mean < p.interval[1]


def test_dict_frames_in_other_units_and_names_give_the_same_estimate():
    model = builtin_model("case-b")
    trial = simulate(model, n_frames=15, sigma=2.0, rng=np.random.default_rng(2))
    names = trial.data.names
    a = Session(model, labels=names, units="mm", method="gaussian")
    b = Session(model, labels={f"stream_{n}": n for n in names}, units="m", method="gaussian")
    for frame in trial.data.positions:
        ea = a.push(frame)
        eb = b.push({f"stream_{n}": xyz / 1000.0 for n, xyz in zip(names, frame, strict=True)} | {"other": [1, 2, 3]})
    np.testing.assert_allclose(eb.theta, ea.theta, rtol=1e-9)


def test_a_missing_marker_and_a_swapped_label_mid_stream_are_flagged_and_do_not_break_it():
    model = load_model(EXAMPLES / "tennis_arm.toml")
    trial = simulate(model, n_frames=80, sigma=0.001, rng=np.random.default_rng(4))
    names = list(trial.data.names)
    y = trial.data.positions.copy()
    y[30:34, 2] = np.nan  # a marker drops out
    i, j = 1, 5  # two markers on different segments swap labels
    y[50:54, [i, j]] = y[50:54, [j, i]]
    clean = Session(model, labels=names, method="gaussian", rng=np.random.default_rng(0))
    glitched = Session(model, labels=names, method="gaussian", rng=np.random.default_rng(0))
    flags = {}
    for t, (a, b) in enumerate(zip(trial.data.positions, y, strict=True)):
        ec = clean.push(a)
        eg = glitched.push(b)
        flags[t] = (eg.healthy, eg.health, eg.rejected)
    assert all(not flags[t][0] and "missing" in flags[t][1] for t in range(30, 34))
    for t in range(50, 54):
        assert not flags[t][0] and set(flags[t][2]) == {names[i], names[j]}, flags[t]
    assert flags[79][0]
    sd = np.sqrt(np.diag(ec.cov))
    np.testing.assert_array_less(np.abs(eg.theta - ec.theta), 0.5 * sd)


def test_bad_input_gives_one_line_errors():
    model = builtin_model("case-a")
    with pytest.raises(DataError, match="none of the labels"):
        Session(model, labels=["a", "b"])
    with pytest.raises(DataError, match="unknown length unit"):
        Session(model, units="furlong")
    with pytest.raises(ModelError, match="unknown live method"):
        Session(model, method="magic")
    s = Session(model, labels=model.marker_names)
    with pytest.raises(DataError, match="array frame"):
        s.push(np.zeros((2, 3)))


def test_advice_ranks_movements_in_words():
    model = load_model(EXAMPLES / "tennis_arm.toml")
    trial = simulate(model, n_frames=30, sigma=0.001, rng=np.random.default_rng(5))
    session = Session(model, labels=trial.data.names, method="gaussian")
    assert session.advice() == []
    _run(session, trial.data.positions)
    advice = session.advice()
    assert advice and all(a.sd_after <= a.sd_now * (1 + 1e-9) for a in advice)
    assert [a.sd_after for a in advice] == sorted(a.sd_after for a in advice)
    assert advice[0].text.startswith(("bend the", "turn the")) and "°" in advice[0].text


def test_readme_live_loop_runs_as_written(capsys):
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    section = text.split("## VR / live", 1)[1]
    code = section.split("```python", 1)[1].split("```", 1)[0]
    assert len(code.strip().splitlines()) <= 12
    exec(compile(code, "README.md", "exec"), {})
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 2 and "True" in out[0] and out[1].startswith(("bend the", "turn the"))


@pytest.mark.parametrize("name", ["case-a", "arm10"])
def test_the_sessions_own_pose_fit_is_fit_pose(name):
    """The session's direct kernel call (or, without the kernel, numpy) gives fit_pose's numbers exactly."""
    from skelid.estimators.pose import fit_pose
    from skelid.live import _FramePose

    root = Path(__file__).resolve().parents[1]
    model = builtin_model(name) if name == "case-a" else load_model(root / "benchmarks" / "arm10.toml")
    trial = simulate(model, n_frames=6, sigma=0.002 if name == "arm10" else 2.0, rng=np.random.default_rng(5))
    y = trial.data.positions[..., : model.dim].copy()
    y[2, 1] = np.nan  # a missing marker
    session = Session(model, method="gaussian")
    fit = _FramePose(model, session._ws)
    theta = model.theta_center
    for t in range(len(y)):
        q0 = trial.pose[t] + 0.05
        expected, _ = fit_pose(model, theta, y[t], q0, n_iter=10, ws=session._ws)
        np.testing.assert_array_equal(fit(theta, y[t], q0), expected)


def test_the_motion_model_does_not_carry_a_prediction_through_a_long_gap():
    """A 0.4 s dropout of every marker: the held poses are let go instead of extrapolated through it (which put
    this trial's estimate 13.6 sd away from the uninterrupted one)."""
    model = load_model(EXAMPLES / "tennis_arm.toml")
    trial = simulate(model, n_frames=300, sigma=0.001, rng=np.random.default_rng(0))
    y = trial.data.positions.copy()
    y[150:190] = np.nan
    clean = Session(model, labels=trial.data.names, method="gaussian", cutoff=6.0)
    gap = Session(model, labels=trial.data.names, method="gaussian", cutoff=6.0)
    for a, b in zip(trial.data.positions, y, strict=True):
        ec, eg = clean.push(a), gap.push(b)
        assert eg.healthy == bool(np.isfinite(b).all())
    np.testing.assert_array_less(np.abs(eg.theta - ec.theta), np.sqrt(np.diag(ec.cov)))


def test_the_default_motion_model_follows_a_fast_movement():
    """The simulated arm motion played five times faster (up to 7.5 Hz): a fixed 6 Hz motion model puts this
    trial's estimate 26 sd from the truth; the default chooses its cutoff from the frames and stays close."""
    model = load_model(EXAMPLES / "tennis_arm.toml")
    trial = simulate(model, n_frames=300, sigma=0.001, rate=20.0, rng=np.random.default_rng(0))
    session = Session(model, labels=trial.data.names, rate=100.0, method="gaussian")
    est = _run(session, trial.data.positions)
    assert session._cutoff_now > 6.0
    np.testing.assert_array_less(np.abs(est.theta - trial.theta), 3.0 * np.sqrt(np.diag(est.cov)))
    with pytest.raises(ModelError, match="unknown cutoff"):
        Session(model, cutoff="fast")


def test_a_swapped_label_the_marker_screen_cannot_see_does_not_pass_into_the_motion_model():
    """Case A's three markers barely fix the pose: with two labels swapped the pose fit finds a pose that fits
    them, so no marker stands out, but that pose jumps away from the motion model's prediction. Without that
    check this trial's estimate went 30 sd from the clean one."""
    model = builtin_model("case-a")
    trial = simulate(model, n_frames=300, sigma=1.0, rng=np.random.default_rng(0))
    y = trial.data.positions.copy()
    y[200:204, [0, 2]] = y[200:204, [2, 0]]
    clean = Session(model, labels=trial.data.names, method="gaussian")
    glitched = Session(model, labels=trial.data.names, method="gaussian")
    flagged, reasons = [], []
    for t, (a, b) in enumerate(zip(trial.data.positions, y, strict=True)):
        ec, eg = clean.push(a), glitched.push(b)
        if not eg.healthy:
            flagged.append(t)
            reasons.append(eg.health)
    assert flagged == [200, 201, 202, 203]
    # the first swapped frames are caught by the jump; once the prediction has run on, the marker screen may be
    # the one to see the swap
    assert "jumps beyond the motion model" in reasons[0]
    assert all(r.endswith("frame not used") for r in reasons)
    np.testing.assert_array_less(np.abs(eg.theta - ec.theta), 0.5 * np.sqrt(np.diag(ec.cov)))


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("name,cutoff", [("tennis_arm", "auto"), ("tennis_arm", None), ("case-a", None)])
def test_a_noise_free_stream_is_fitted_at_the_noise_floor(monkeypatch, compiled, name, cutoff):
    """Markers without noise leave rounding-level residuals; the noise level is held at the documented floor,
    so theta's precision keeps the prior and stays regular, on the compiled and the numpy path alike."""
    from skelid.estimators import _live_kernel
    from skelid.live import noise_floor

    if compiled and not _live_kernel.AVAILABLE:
        pytest.skip("numba not installed or SKELID_NUMBA=0")
    if not compiled:
        monkeypatch.setattr(_live_kernel, "ready", lambda: False)
    model = builtin_model(name) if name.startswith("case") else load_model(EXAMPLES / f"{name}.toml")
    trial = simulate(model, n_frames=60, sigma=0.0, rng=np.random.default_rng(3))
    session = Session(model, labels=trial.data.names, method="gaussian", cutoff=cutoff)
    assert (session._step is not None) == compiled
    for frame in trial.data.positions:
        est = session.push(frame)
        assert est.healthy, est.health
    floor = np.sqrt(noise_floor(model))
    assert est.sigma == pytest.approx(floor)  # the residuals are rounding; the floor holds
    sd = np.sqrt(np.diag(est.cov))
    assert np.all(np.isfinite(sd)) and np.all(sd > 0)
    np.testing.assert_array_less(np.abs(est.theta - trial.theta), 3.0 * sd)
    given = Session(model, labels=trial.data.names, method="gaussian", cutoff=cutoff, sigma=0.0)
    assert _run(given, trial.data.positions[:10]).sigma == pytest.approx(floor)


def test_a_negative_noise_level_is_a_one_line_error():
    model = builtin_model("case-a")
    for sigma in (-1.0, float("nan")):
        with pytest.raises(DataError, match="sigma must be"):
            Session(model, labels=model.marker_names, sigma=sigma)
