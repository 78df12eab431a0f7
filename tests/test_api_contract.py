"""The public Python API refuses bad input as the command line does.

Every public callable given anything (wrong types and shapes, NaN and infinities, empty
and huge arrays, unknown units, duplicate names) either returns a correct result or
raises a :class:`~skelid.errors.SkelidError` with one line: never a raw ``ValueError``,
``TypeError``, ``AttributeError`` or ``IndexError`` from inside, never a numpy warning.

Also here: no estimate leaves its prior's support, degenerate data are refused, and a
rigid shift of all markers leaves the estimates where they were.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from skelid import load_model
from skelid.data import MarkerData
from skelid.errors import DataError, ModelError, SettingError, SkelidError, SkelidWarning
from skelid.estimators import MarkerEstimator, MarkerGridFilter, PaperFilter
from skelid.estimators.base import MAX_COUNT, check_settings, in_support
from skelid.estimators.multitrial import MultiTrialEstimator
from skelid.estimators.sampler import SamplerEstimator
from skelid.io import read_markers
from skelid.io.frames import to_dataframe, to_inference_data, to_xarray
from skelid.model import model_from_dict
from skelid.result import FitRun
from skelid.simulate import builtin_model, simulate

CASE_A = builtin_model("case-a")
TRIAL = simulate(CASE_A, n_frames=40, sigma=3.0, rng=np.random.default_rng(0))
FAST = settings(max_examples=40, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
SLOW = settings(max_examples=6, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow])


def outcome(f, *args, **kwargs):
    """``('ok', value)`` or ``('refused', error)``; anything else (or a numpy warning) fails the test."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # numpy's divide / invalid / overflow warnings
        warnings.simplefilter("error", np.exceptions.ComplexWarning)
        warnings.simplefilter("ignore", SkelidWarning)  # a user's warning is allowed
        try:
            return "ok", f(*args, **kwargs)
        except SkelidError as exc:
            msg = str(exc)
            assert msg and "\n" not in msg, f"not one line: {msg!r}"
            return "refused", exc


# --------------------------------------------------------------------------- strategies
FLOATS = st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from([0.0, -0.0, 1e300, -1e300, 5e-324])
ODD = st.one_of(st.none(), st.booleans(), st.integers(-10, 10), FLOATS, st.text(max_size=5), st.binary(max_size=3),
                st.just([]), st.just({}), st.just(object()), st.just(1 + 2j))


@st.composite
def positions(draw):
    """Arrays of many dtypes and shapes, with NaN, inf and huge values, or no array at all."""
    kind = draw(st.sampled_from(["float", "int", "complex", "bool", "str", "object", "list", "odd"]))
    if kind == "odd":
        return draw(ODD)
    if kind == "list":
        return draw(st.sampled_from([[[[1.0, 2.0]], [[1.0]]], [[["a", "b"]]], [], [[[]]], [[[1, 2, 3]]]]))
    shape = draw(hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=4))
    if kind == "float":
        return draw(hnp.arrays(float, shape, elements=FLOATS))
    if kind == "int":
        return draw(hnp.arrays(np.int64, shape, elements=st.integers(-10**6, 10**6)))
    if kind == "complex":
        return np.zeros(shape, complex)
    if kind == "bool":
        return np.zeros(shape, bool)
    if kind == "str":
        return np.full(shape, "1.0")
    return np.full(shape, None, dtype=object)


NAMES = st.one_of(ODD, st.text(min_size=1, max_size=4),
                  st.lists(st.text(min_size=0, max_size=3), max_size=5),
                  st.lists(st.sampled_from(["A", "B", "A"]), max_size=4),
                  st.lists(st.integers(0, 3), max_size=4).map(tuple))
RATES = st.one_of(ODD, st.floats(-1e7, 1e7), st.sampled_from([100.0, 1e-3, 1e7, math.nan, math.inf, 0]))
UNITS = st.one_of(ODD, st.sampled_from(["mm", "cm", "m", "in", "MM", "", " mm"]))


def check_marker_data(d: MarkerData) -> None:
    """What a MarkerData promises: shape, dtype, no infinities, unique string names, a rate, a unit."""
    pos = d.positions
    assert pos.dtype == float and pos.ndim == 3 and pos.shape[2] in (2, 3)
    assert not np.isinf(pos).any() and not pos.flags.writeable
    assert isinstance(d.names, tuple) and len(d.names) == pos.shape[1] == len(set(d.names))
    assert all(isinstance(n, str) for n in d.names)
    assert math.isfinite(d.rate) and d.rate > 0 and d.units in ("mm", "cm", "m")


# --------------------------------------------------------------------------- MarkerData
@st.composite
def marker_data_args(draw):
    """Valid arguments with one of them (or none) replaced by something odd."""
    F, M, D = draw(st.integers(0, 5)), draw(st.integers(0, 4)), draw(st.sampled_from([2, 3]))
    args = {"positions": draw(hnp.arrays(float, (F, M, D), elements=st.floats(-1e4, 1e4) | st.just(np.nan))),
            "names": [f"m{k}" for k in range(M)], "rate": draw(st.sampled_from([100.0, 60, np.float32(250.0)])),
            "units": draw(st.sampled_from(["mm", "cm", "m"]))}
    which = draw(st.sampled_from(["none", "positions", "names", "rate", "units", "all"]))
    odd = {"positions": positions(), "names": NAMES, "rate": RATES, "units": UNITS}
    for k in odd if which == "all" else [which] if which != "none" else []:
        args[k] = draw(odd[k])
    return args


@FAST
@given(args=marker_data_args())
def test_marker_data_accepts_only_what_it_can_hold(args):
    pos = args["positions"]
    kind, d = outcome(MarkerData, **args)
    if kind == "ok":
        check_marker_data(d)
        if isinstance(pos, np.ndarray):  # the caller's array is copied, not taken over
            assert d.positions is not pos


def test_marker_data_refusals_name_the_problem():
    P = TRIAL.data.positions
    cases = {
        "strings": (np.full(P.shape, "1"), TRIAL.data.names, 100.0, "strings"),
        "complex": (P.astype(complex), TRIAL.data.names, 100.0, "complex"),
        "objects": (P.astype(object), TRIAL.data.names, 100.0, "objects"),
        "inf": (np.where(P > 0, np.inf, P), TRIAL.data.names, 100.0, "infinite"),
        "-inf": (np.where(P > 0, -np.inf, P), TRIAL.data.names, 100.0, "infinite"),
        "duplicates": (P, ("A", "A", "C"), 100.0, "duplicate marker names"),
        "one string, three markers": (P, "ABC", 100.0, "1 marker names for 3 markers"),
        "rate 0": (P, TRIAL.data.names, 0.0, "sampling rate"),
        "rate inf": (P, TRIAL.data.names, math.inf, "sampling rate"),
        "rate nan": (P, TRIAL.data.names, math.nan, "sampling rate"),
        "rate a string": (P, TRIAL.data.names, "100", "sampling rate"),
    }
    for label, (pos, names, rate, needle) in cases.items():
        kind, exc = outcome(MarkerData, pos, names, rate)
        assert kind == "refused" and isinstance(exc, DataError) and needle in str(exc), (label, exc)
    assert outcome(MarkerData, P, TRIAL.data.names, 100.0, "inch")[0] == "refused"
    # a single string is one name, never split into letters
    assert MarkerData(P[:, :1], "ABC", 100.0).names == ("ABC",)


@FAST
@given(names=NAMES | st.just("A"), start=st.integers(-3, 50) | ODD, stop=st.none() | st.integers(-3, 50) | ODD,
       units=UNITS)
def test_marker_data_methods_return_marker_data_or_refuse(names, start, stop, units):
    for f, args in ((TRIAL.data.select, (names,)), (TRIAL.data.frames, (start, stop)), (TRIAL.data.to_units, (units,))):
        kind, d = outcome(f, *args)
        if kind == "ok":
            check_marker_data(d)
    assert TRIAL.data.select("A").names == ("A",)


# --------------------------------------------------------------------------- estimators
ESTIMATORS = {"marker": MarkerEstimator, "paper": PaperFilter, "marker-grid": MarkerGridFilter,
              "marker-smc": SamplerEstimator, "marker-multi": MultiTrialEstimator}


@pytest.mark.parametrize("name", list(ESTIMATORS))
@pytest.mark.parametrize("model", [None, "case-a", 5, CASE_A.to_dict(), np.zeros(3)])
def test_estimators_refuse_what_is_not_a_model(name, model):
    with pytest.raises(ModelError, match="needs a skelid Model"):
        ESTIMATORS[name](model)


BAD_SETTINGS = st.sampled_from(["n_iter", "sigma", "rng", "rate", "cutoff", "n_boot", "outlier_threshold",
                                "artefact_rms", "noise", "placement_sd", "theta0"])


@FAST
@given(setting=BAD_SETTINGS, value=ODD | st.integers(-5, 0) | st.just(np.array([np.inf])))
def test_settings_are_checked_before_any_work(setting, value):
    est = MarkerEstimator(CASE_A, **{setting: value})
    kind, exc = outcome(check_settings, est)
    if kind == "refused":
        assert isinstance(exc, SettingError) and setting in str(exc)
        with pytest.raises(SettingError):  # fit refuses it the same way, before reading the data
            est.fit(TRIAL.data)


@pytest.mark.parametrize("setting, value", [("theta0", [250.0, 1.0]), ("theta0", 250.0),
                                            ("pose0", np.zeros((3, 5))), ("pose0", np.zeros((40, 2)))])
def test_starting_values_of_the_wrong_shape_are_setting_errors(setting, value):
    with pytest.raises(SettingError, match=f"setting {setting} of shape"):
        MarkerEstimator(CASE_A, **{setting: value}).fit(TRIAL.data)


def test_negative_n_iter_is_a_setting_error():
    with pytest.raises(SettingError, match="n_iter=-3"):
        MarkerEstimator(CASE_A, n_iter=-3).fit(TRIAL.data)


COUNT_SETTINGS = [("marker", "n_iter"), ("marker", "n_boot"), ("paper", "max_iter"), ("marker-grid", "n_iter"),
                  ("marker-smc", "n_particles"), ("marker-smc", "n_moves"), ("marker-smc", "inner_iter"),
                  ("marker-multi", "n_iter")]


@pytest.mark.parametrize("name, setting", COUNT_SETTINGS)
@pytest.mark.parametrize("value", [10**30, MAX_COUNT + 1], ids=["huge", "one-too-many"])
def test_absurd_counts_are_setting_errors_before_any_work(name, setting, value):
    est = ESTIMATORS[name](CASE_A, **{setting: value})
    with pytest.raises(SettingError, match=f"setting {setting}={value} is not usable .*from [12] to {MAX_COUNT}"):
        est.fit([TRIAL.data] if name == "marker-multi" else TRIAL.data)


@pytest.mark.parametrize("name, setting", COUNT_SETTINGS)
def test_the_largest_count_is_usable(name, setting):
    check_settings(ESTIMATORS[name](CASE_A, **{setting: MAX_COUNT}))


@pytest.mark.parametrize("setting", ["outlier_threshold", "sigma", "artefact_rms", "placement_sd"])
def test_an_integer_beyond_int64_is_a_setting_error(setting):
    with pytest.raises(SettingError, match=f"setting {setting}={10**30} is not usable"):
        MarkerEstimator(CASE_A, **{setting: 10**30}).fit(TRIAL.data)


@pytest.mark.parametrize("axes", [[1], (np.linspace(230.0, 270.0, 5), np.linspace(0.0, 1.0, 3)),
                                  (np.ones((3, 2)),), (np.linspace(270.0, 230.0, 5),), (np.array([250.0, 250.0]),)],
                         ids=["scalar", "two-for-one-parameter", "2-d", "decreasing", "repeated"])
def test_grid_axes_that_do_not_fit_the_model_are_setting_errors(axes):
    with pytest.raises(SettingError, match=r"setting axes does not fit model 'case_a': 1 parameter\(s\) \['L2'\]"):
        MarkerGridFilter(CASE_A, axes=axes).fit(TRIAL.data)


@pytest.mark.parametrize("name", ["marker", "marker-smc"])
@pytest.mark.parametrize("n_frames", [1, 3])
def test_too_few_frames_are_refused_with_the_count(name, n_frames):
    data = MarkerData(TRIAL.data.positions[:n_frames], TRIAL.data.names, 100.0)
    with pytest.raises(DataError, match=f"has {n_frames} frame"):
        ESTIMATORS[name](CASE_A).fit(data)


@pytest.mark.parametrize("n_frames", [1, 2])
def test_a_trial_among_several_needs_the_frames_of_its_motion_model(n_frames):
    short = MarkerData(TRIAL.data.positions[:n_frames], TRIAL.data.names, 100.0, source="short.trc")
    with pytest.raises(DataError, match="short.trc: .*needs at least 3 frames"):
        MultiTrialEstimator(CASE_A, rng=0).fit([short, TRIAL.data])


@st.composite
def fit_data(draw):
    """Data for case A: odd objects, arrays of wrong shape or dtype, or MarkerData with holes,
    infinities, constant frames, frozen markers, huge offsets or other units."""
    kind = draw(st.sampled_from(["odd", "array", "data", "data", "data"]))
    if kind == "odd":
        return draw(ODD | positions())
    F = draw(st.integers(0, 12))
    P = np.array(TRIAL.data.positions[:F])
    change = draw(st.sampled_from(["none", "nan", "inf", "constant", "frozen", "huge", "shift", "all-nan"]))
    if change == "nan" and F:
        P[draw(st.integers(0, F - 1)), draw(st.integers(0, 2))] = np.nan
    elif change == "inf" and F:
        P[0, 0, 0] = np.inf
    elif change == "constant" and F:
        P[:] = P[0]
    elif change == "frozen" and F:
        P[:, :2] = P[0, :2]
    elif change == "huge":
        P = P * 1e9
    elif change == "shift":
        P = P + draw(st.sampled_from([1e4, -1e6, 1e8]))
    elif change == "all-nan":
        P[:] = np.nan
    if kind == "array":
        return P[:, : draw(st.integers(1, 3))]
    units = draw(st.sampled_from(["mm", "cm", "m"]))
    try:
        return MarkerData(P, TRIAL.data.names, 100.0, units)
    except DataError:
        return P  # then as an array


@FAST
@given(data=fit_data(), name=st.sampled_from(["paper", "marker-grid"]))
def test_online_estimators_fit_or_refuse(data, name):
    kw = {"rate": 100.0, "rng": 0}
    if name == "marker-grid":
        kw["axes"] = (np.linspace(220.0, 280.0, 7),)
    kind, est = outcome(lambda: ESTIMATORS[name](CASE_A, **kw).fit(data))
    if kind == "ok":
        check_result(est)


@SLOW
@given(data=fit_data())
def test_marker_estimator_fits_or_refuses(data):
    kind, est = outcome(lambda: MarkerEstimator(CASE_A, rate=100.0, rng=0, n_boot=1, jackknife=False).fit(data))
    if kind == "ok":
        check_result(est)


def check_result(est) -> None:
    """A fitted estimator's result: finite numbers, every point inside the prior's support."""
    r = est.result()
    for p, prior in zip(r.parameters.values(), (q.prior for q in est.model.parameters), strict=True):
        assert all(math.isfinite(x) for x in (p.map, p.mean, p.sd, *p.interval)), p
        assert prior.lower <= p.map <= prior.upper and prior.lower <= p.mean <= prior.upper, p


# --------------------------------------------------------------------------- simulate, readers, model, results
@st.composite
def simulate_args(draw):
    """Valid arguments of simulate with one of them (or none) replaced by something odd."""
    args = {"theta": None, "n_frames": draw(st.integers(1, 30)), "rate": draw(st.sampled_from([100.0, 50, 1e3])),
            "sigma": draw(st.floats(0.0, 20.0)), "rng": np.random.default_rng(1),
            "noise": draw(st.sampled_from(["iid", "sta"])), "sta_amplitude": draw(st.floats(0.0, 20.0))}
    odd = {"theta": st.just([1.0, 2.0]) | st.just([np.nan]) | st.just([250.0]) | ODD,
           "n_frames": st.integers(-2, 0) | ODD, "rate": RATES, "sigma": FLOATS | ODD, "rng": ODD,
           "noise": st.sampled_from(["gauss", "IID"]) | ODD, "sta_amplitude": st.floats(-5.0, 0.0) | FLOATS | ODD}
    which = draw(st.sampled_from(["none", "none", *odd]))
    if which != "none":
        args[which] = draw(odd[which])
    return args


@FAST
@given(args=simulate_args())
def test_simulate_runs_or_refuses(args):
    kind, trial = outcome(simulate, CASE_A, **args)
    if kind == "ok":
        check_marker_data(trial.data)
        assert trial.data.n_frames == args["n_frames"] >= 1 and np.isfinite(trial.data.positions).all()


@pytest.mark.parametrize("kwargs, needle", [
    ({"sigma": -1.0}, "sigma=-1.0"), ({"n_frames": 0}, "n_frames=0"), ({"rate": 0.0}, "sampling rate"),
    ({"noise": "gauss"}, "noise='gauss'"), ({"theta": [1.0, 2.0]}, "theta of shape (2,)"),
    ({"sigma": math.inf}, "sigma=inf")])
def test_simulate_names_the_argument(kwargs, needle):
    with pytest.raises(SettingError) as exc:
        simulate(CASE_A, **{"n_frames": 10, **kwargs})
    assert needle in str(exc.value)
    with pytest.raises(ModelError):
        simulate(None, n_frames=10)


@pytest.mark.parametrize("path", [None, 5, 1.5, ["a.trc"], b"", "", "\0x", object()])
def test_readers_and_load_model_refuse_what_is_not_a_path(path):
    for f in (read_markers, load_model):
        kind, exc = outcome(f, path)
        assert kind == "refused", (f, path)


def test_readers_refuse_missing_files_and_folders(tmp_path):
    for f in (read_markers, load_model):
        for p in (tmp_path / "nope.trc", tmp_path):
            assert outcome(f, p)[0] == "refused"


@FAST
@given(text=st.text(max_size=200) | st.sampled_from([
    "[model]\nname='x'\n", "[model]\nname='x'\ndim=2\nunits='mm'\n[[segments]]\nname=1\n",
    '[model]\nname = "x"\ndim = 7\n', "[[parameters]]\nname='L'\n"]))
def test_load_model_reads_or_refuses_any_text(tmp_path_factory, text):
    path = tmp_path_factory.mktemp("model") / "m.toml"
    path.write_text(text, encoding="utf-8")
    outcome(load_model, path)


@pytest.fixture(scope="module")
def fitted_run():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkelidWarning)
        r = PaperFilter(CASE_A, rng=0).fit(TRIAL.data).result()
    return FitRun({r.method: r})


@FAST
@given(which=st.sampled_from(["none", "none", "result", "method", "n_draws"]),
       result=ODD | st.sampled_from([FitRun(), {"schema_version": 1}, {"methods": 5}, {"schema_version": "x"}]),
       method=st.sampled_from(["nope", "PAPER"]) | ODD, n_draws=st.integers(-2, 0) | ODD)
def test_result_conversions_convert_or_refuse(fitted_run, which, result, method, n_draws):
    args = {"result": fitted_run, "method": None, "n_draws": 5}
    args.update({which: {"result": result, "method": method, "n_draws": n_draws}[which]} if which != "none" else {})
    kind, frame = outcome(to_dataframe, args["result"])
    if kind == "ok":
        assert len(frame) >= 1 or args["result"] is not fitted_run
    outcome(to_xarray, args["result"], args["method"])  # the paper method has no per-frame arrays: refused
    kind, idata = outcome(to_inference_data, args["result"], args["method"], n_draws=args["n_draws"])
    if which == "none":
        assert kind == "ok" and idata.posterior["L2"].shape == (1, 5)


# --------------------------------------------------------------------------- the prior's support
def test_a_point_beyond_a_bound_is_put_on_it_and_says_so():
    class Prior:
        lower, upper = 200.0, 300.0

    (m, mean), ci, status = in_support(Prior, (708.0, 708.0), (400.0, 1000.0), "poor")
    assert (m, mean, ci, status) == (300.0, 300.0, (300.0, 300.0), "on-bound")
    # a point inside stays; the interval never leaves the support (the posterior has no mass outside)
    assert in_support(Prior, (250.0, 251.0), (190.0, 310.0), "identified") == ((250.0, 251.0), (200.0, 300.0),
                                                                              "identified")
    assert in_support(Prior, (250.0, 251.0), (210.0, 290.0), "identified") == ((250.0, 251.0), (210.0, 290.0),
                                                                              "identified")
    assert in_support(Prior, (200.0, 200.0), (200.0, 210.0), "identified")[2] == "on-bound"
    assert in_support(Prior, (100.0, 100.0), (90.0, 110.0), "unidentified")[2] == "unidentified"


def _narrow_prior(lower, upper):
    d = CASE_A.to_dict()
    d["parameters"][0]["prior"] = {"type": "uniform", "lower": lower, "upper": upper}
    return model_from_dict(d)


def test_an_optimum_beyond_the_prior_is_reported_on_its_bound():
    """The truth (250 mm) is outside [200, 230]: the grid's estimate sits on 230 and its status says so."""
    model = _narrow_prior(200.0, 230.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkelidWarning)
        r = MarkerGridFilter(model, rng=0).fit(TRIAL.data).result()
    p = r.parameters["L2"]
    assert p.status == "on-bound" and 200.0 <= p.map <= 230.0 and 200.0 <= p.mean <= 230.0
    assert p.map == pytest.approx(230.0, abs=5.0)


@pytest.mark.parametrize("name, needle", [("marker", "sits on the bound 230"), ("paper", "no solution inside")])
def test_the_other_fits_refuse_an_optimum_beyond_the_bounds_of_their_only_parameter(name, needle):
    with pytest.raises(SkelidError, match=needle):
        ESTIMATORS[name](_narrow_prior(200.0, 230.0), rng=0).fit(TRIAL.data)


def test_the_marker_fit_holds_a_corrected_estimate_inside_the_support():
    """A bias correction or a normal prior that moves the estimate beyond a bound is undone, and reported."""
    from skelid.estimators.marker import Estimate, support_stage

    class St:
        bounds = (np.array([200.0, -10.0]), np.array([300.0, 10.0]))

    est, beyond = support_stage(St, Estimate(np.array([708.0, 0.5]), np.eye(2)))
    np.testing.assert_array_equal(est.theta, [300.0, 0.5])
    assert beyond[0] == 708.0 and np.isnan(beyond[1])


# --------------------------------------------------------------------------- degenerate data
@pytest.mark.parametrize("name", ["marker", "paper", "marker-grid", "marker-smc"])
def test_frozen_data_are_refused(name):
    frozen = MarkerData(np.repeat(TRIAL.data.positions[:1], 20, axis=0), TRIAL.data.names, 100.0)
    with pytest.raises(DataError, match="nothing moves"):
        ESTIMATORS[name](CASE_A).fit(frozen)


def test_frames_that_repeat_exactly_are_flagged():
    """A capture frozen half way: the copies would pass for information, so the fit says so."""
    from skelid.estimators.marker import repeated_frames

    y = np.array(TRIAL.data.positions)
    assert repeated_frames(y) == 0
    y[25:] = y[24]
    y[30, 0] = np.nan  # a gap breaks the run: frame 30 differs from 29, and 31 from 30
    assert repeated_frames(y) == 15 - 2
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkelidWarning)
        est = MarkerEstimator(CASE_A, rng=0).fit(TRIAL.data.replace(positions=y))
        plain = MarkerEstimator(CASE_A, rng=0).fit(TRIAL.data)
    assert "repeated-frames" in {w.code for w in est.warnings_}
    assert "repeated-frames" not in {w.code for w in plain.warnings_}


def test_the_same_file_twice_is_refused(tmp_path):
    from skelid.checks import check_distinct_files
    from skelid.io import write_trc

    path = tmp_path / "trial.trc"
    write_trc(path, TRIAL.data)
    (tmp_path / "link.trc").symlink_to(path)
    check_distinct_files([path, tmp_path / "other.trc"])
    for twice in ([path, path], [path, tmp_path / "link.trc"]):
        with pytest.raises(DataError, match="is given twice"):
            check_distinct_files(twice)


def test_a_copy_of_a_file_is_refused_and_a_file_of_the_same_size_is_not(tmp_path):
    from skelid.checks import check_distinct_files
    from skelid.io import write_trc

    path, copy, other = tmp_path / "trial.trc", tmp_path / "copy.trc", tmp_path / "other.trc"
    write_trc(path, TRIAL.data)
    copy.write_bytes(path.read_bytes())
    text = path.read_text()
    other.write_text(text.replace("\t0.010000\t", "\t0.010001\t", 1))  # one digit more: same size, other bytes
    assert other.stat().st_size == path.stat().st_size and other.read_bytes() != path.read_bytes()
    check_distinct_files([path, other])
    with pytest.raises(DataError, match="copy.trc holds the same bytes as .*trial.trc"):
        check_distinct_files([path, other, copy])


# --------------------------------------------------------------------------- where the data sit
#: largest relative change of the estimate, its sd and sigma under a rigid shift of up to 1e4 mm: about
#: thirty times the worst that benchmarks/shift_invariance.py measured for any shift up to 1e7 mm (case A,
#: 40 frames: 1e-7, 5.2e-7 and 2.1e-7). The fit works about the data's centre, so what is left is the
#: shifted data's rounding moved by the fit's stopping rule (tests/test_invariance.py: none for whole mm).
SHIFT_RTOL = {"mean": 3e-6, "sd": 3e-5, "sigma": 6e-6}


def _fit_values(data):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkelidWarning)
        r = MarkerEstimator(CASE_A, rng=0).fit(data).result()
    return (np.array([p.mean for p in r.parameters.values()]), np.array([p.sd for p in r.parameters.values()]),
            r.noise.sigma)


BASE = _fit_values(TRIAL.data)


@settings(max_examples=5, deadline=None, derandomize=True, database=None)
@given(shift=hnp.arrays(float, 2, elements=st.floats(-1e4, 1e4)))
def test_a_rigid_shift_leaves_the_estimates_unchanged(shift):
    mean, sd, sigma = _fit_values(TRIAL.data.replace(positions=TRIAL.data.positions + shift))
    np.testing.assert_allclose(mean, BASE[0], rtol=SHIFT_RTOL["mean"])
    np.testing.assert_allclose(sd, BASE[1], rtol=SHIFT_RTOL["sd"])
    assert sigma == pytest.approx(BASE[2], rel=SHIFT_RTOL["sigma"])


def test_coordinates_beyond_the_fit_range_are_refused_in_one_line():
    far = TRIAL.data.replace(positions=TRIAL.data.positions + 2e7)
    with pytest.raises(DataError, match="beyond the 1e\\+07 mm \\(10000 m\\) a fit accepts"):
        MarkerEstimator(CASE_A).fit(far)
    with pytest.raises(DataError, match="beyond the 1e\\+07 mm"):  # in the model's units, whatever the data's
        PaperFilter(CASE_A).fit(far.to_units("m"))
    with pytest.raises(DataError, match="beyond the 1e\\+07 mm"):  # an array as well
        MarkerGridFilter(CASE_A, rate=100.0).fit(np.asarray(far.positions))
    PaperFilter(CASE_A).fit(TRIAL.data.replace(positions=TRIAL.data.positions + 9e6))  # inside: fitted


@pytest.mark.parametrize("trials", [None, 3, [None], [TRIAL.data, "x"], [TRIAL.data, np.zeros((4, 3, 3))], [TRIAL], [],
                                    "no_such.trc"])
def test_osim_fit_trials_are_marker_data_or_files_or_refused(trials, tmp_path):
    """The OpenSim fit takes MarkerData or paths of marker files; anything else is one line, before any work."""
    from skelid.scaling import fit_osim

    kind, _ = outcome(fit_osim, tmp_path / "never_read.osim", trials)
    assert kind == "refused"


def test_osim_fit_reads_marker_files_as_the_readers_do(tmp_path):
    from skelid.io import write_trc
    from skelid.scaling import checked_trials

    path = tmp_path / "trial.trc"
    data = MarkerData(np.random.default_rng(1).normal(size=(5, 3, 3)) * 100, ("A", "B", "C"), 100.0, "mm")
    write_trc(path, data)
    got = checked_trials([path, str(path), data])
    assert [type(t) for t in got] == [MarkerData] * 3
    np.testing.assert_allclose(got[0].positions, read_markers(path).positions)
    np.testing.assert_allclose(got[1].positions, got[0].positions)


def test_osim_fit_refuses_an_unknown_marker_mode(tmp_path):
    from skelid.scaling import fit_osim

    with pytest.raises(SettingError, match="marker mode"):
        fit_osim(tmp_path / "never_read.osim", [TRIAL.data], markers="offset")


# --------------------------------------------------------------------------- live Session
@st.composite
def session_args(draw):
    """A Session's settings, one of them (or none, or all) replaced by something odd."""
    args = {"labels": list(CASE_A.marker_names), "units": "mm", "rate": 100.0, "method": "gaussian"}
    odd = {"labels": NAMES | st.dictionaries(st.text(max_size=3), st.text(max_size=3) | ODD, max_size=3),
           "units": UNITS, "rate": RATES, "sigma": ODD | st.floats(-10, 10), "outlier_sd": ODD,
           "n_iter": ODD | st.integers(-3, 3), "method": ODD | st.sampled_from(["grid", "gaussian", "paper", ""]),
           "cutoff": ODD | st.sampled_from(["auto", "none", 6.0, -1.0, 1e9])}
    which = draw(st.sampled_from(["none", "all", *odd]))
    for k in odd if which == "all" else [which] if which != "none" else []:
        args[k] = draw(odd[k])
    return args


@st.composite
def live_frames(draw):
    """Frames a stream might send: the model's markers as arrays or mappings, with odd values or shapes."""
    good = np.asarray(TRIAL.data.positions[draw(st.integers(0, 39))], float)
    kind = draw(st.sampled_from(["good", "array", "mapping", "odd", "scaled", "partial"]))
    if kind == "good":
        return good
    if kind == "array":
        return draw(positions())
    if kind == "scaled":  # the right shape, values anywhere (NaN, inf, huge, zero)
        return good * draw(st.sampled_from([0.0, 1e-9, 1e3, 1e12, np.nan, np.inf, -1.0]))
    if kind == "partial":
        return {n: draw(st.sampled_from([list(v), v * np.nan, [float("inf")] * 2, "1,2", [], [1.0], None]))
                for n, v in zip(CASE_A.marker_names, good, strict=True)}
    if kind == "mapping":
        return draw(st.dictionaries(st.text(max_size=3) | st.sampled_from(CASE_A.marker_names), ODD | positions(),
                                    max_size=4))
    return draw(ODD)


def check_live_estimate(e, frames_pushed: int) -> None:
    """What a LiveEstimate promises: the frame count, a finite estimate, one health line, statuses known."""
    from skelid.result import STATUSES

    assert e.frame == frames_pushed and isinstance(e.health, str) and "\n" not in e.health
    assert np.all(np.isfinite(e.theta)) and e.theta.shape == (CASE_A.n_params,)
    for p in e.parameters.values():
        assert p.status in STATUSES and math.isfinite(p.sd) and p.interval[0] <= p.interval[1]


@settings(max_examples=200, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(args=session_args(), frames=st.lists(live_frames(), min_size=1, max_size=6))
def test_a_session_starts_or_refuses_and_every_push_gives_an_estimate_or_refuses(args, frames):
    """Any settings: a Session or one SkelidError line. Any frames: an estimate (healthy or saying what went
    wrong) or one DataError line, after which the session goes on as before."""
    from skelid.live import Session

    kind, s = outcome(Session, CASE_A, **args)
    if kind == "refused":
        return
    pushed = 0
    for f in [*frames, np.asarray(TRIAL.data.positions[0], float)]:
        kind, e = outcome(s.push, f)
        if kind == "refused":
            assert isinstance(e, DataError), type(e)
            continue
        pushed += 1
        check_live_estimate(e, pushed)


@pytest.mark.parametrize("method", ["marker", "paper", "marker-grid", "marker-smc"])
def test_a_nearly_still_noisy_trial_stays_inside_the_prior_with_every_method(tmp_path, method, capsys):
    """Two hundred frames of one pose with 1 mm noise, through the command line: every method's estimate lies
    inside the prior's bounds [200, 300] or the fit is refused in one line (exit 2); the marker methods call
    the length 'placement', not 'identified'."""
    import json

    from skelid.cli import main
    from skelid.io.trc import write_trc

    rng = np.random.default_rng(5)
    pos = np.repeat(np.asarray(TRIAL.data.positions[:1]), 200, axis=0) + rng.normal(0.0, 1.0, (200, 3, 2))
    path = tmp_path / "still.trc"
    write_trc(path, TRIAL.data.replace(positions=pos))
    out = tmp_path / "fit"
    rc = main(["fit", "case-a", str(path), "--method", method, "--out", str(out), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc in (0, 2), err
    if rc == 2:
        assert err.count("\n") == 0 and not out.exists()
        return
    p = json.loads((out / "result.json").read_text())["results"][method]["parameters"]["L2"]
    assert 200.0 <= p["map"] <= 300.0 and 200.0 <= p["interval"][0] <= p["interval"][1] <= 300.0, p
    if method != "paper":  # the paper's method is reproduced as published
        assert p["status"] == "placement", p["status"]


# --------------------------------------------------------------------------- joint angles
@pytest.fixture(scope="module")
def leg_geometry(tmp_path_factory):
    """The OpenSim leg of the scaling tests at its nominal geometry, with a small covariance."""
    from skelid import angles
    from skelid.io.osim import osim_coordinates, osim_parameters, read_osim
    from tests.test_scaling import MODEL, marker_xml

    path = tmp_path_factory.mktemp("api-leg") / "leg.osim"
    path.write_text(MODEL.format(markers=marker_xml()))
    base, info = read_osim(path)
    model = osim_parameters(base, info, "bodies", "offsets")
    sd = np.array([p.prior.sd for p in model.parameters])
    return angles.FittedGeometry(model, model.theta_nominal.copy(), np.diag((0.02 * sd) ** 2), "joint",
                                 osim_coordinates(path), None, str(path))


@settings(max_examples=40, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frames=st.integers(0, 4), kept=st.integers(0, 12), spoil=st.sampled_from(["none", "nan", "inf", "huge", "one"]),
       units=st.sampled_from(["mm", "cm", "m"]), n_draws=st.sampled_from([0, 3, -1, 2.5, None, "x", True]))
def test_joint_angles_give_every_coordinate_or_refuse(leg_geometry, frames, kept, spoil, units, n_draws):
    """Any trial (any number of frames, some or none of the model's markers, NaN, inf, huge values, any unit)
    and any number of draws: the joint angles with finite sds where a frame's pose is fixed, or one line."""
    from skelid import angles
    from skelid.model.kinematics import marker_positions

    model = leg_geometry.model
    q = np.zeros((frames, model.n_pose))
    q[:, 3:6] = [100.0, 900.0, 50.0]
    y = marker_positions(model, leg_geometry.theta, q) + np.random.default_rng(frames).normal(0, 0.5, (frames, 12, 3))
    if spoil == "nan" and frames:
        y[0, 0] = np.nan
    elif spoil == "inf" and frames:
        y[-1, 2, 1] = np.inf
    elif spoil == "huge" and frames:
        y[0] = 1e12
    elif spoil == "one" and frames:
        y[:, 1:] = np.nan
    y = y / {"mm": 1.0, "cm": 10.0, "m": 1000.0}[units]
    names = model.marker_names[:kept]
    kind, value = outcome(lambda: angles.joint_angles(
        leg_geometry, MarkerData(y[:, :kept], names, 60.0, units), n_draws=n_draws, rng=np.random.default_rng(0)))
    if kind == "ok":
        a = value
        assert a.value.shape == (frames, len(a.names)) and a.sd.shape == a.value.shape
        fitted = np.array([s == "fitted" for s in a.status])
        assert np.all(np.isfinite(a.sd[np.ix_(a.fixed, fitted)]))
        assert np.all(np.isnan(a.value[np.ix_(~a.fixed, fitted)]))
