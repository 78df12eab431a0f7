"""The estimator contract, checked for every registered estimator (scikit-learn's estimator_checks spirit).

Each check is one small function; ``CHECKS`` lists them and every estimator runs every check.
Data are tiny simulated trials so that the whole list stays fast.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from skelid.data import MarkerData
from skelid.errors import DataError, NotFittedError, SettingError, SkelidError, SkelidWarning
from skelid.estimators.base import check_settings, get_settings
from skelid.estimators.multitrial import MultiTrialEstimator
from skelid.io.results import read_run, write_run
from skelid.model import model_from_dict
from skelid.registry import estimators, make_estimator
from skelid.result import FitResult, FitRun, Warning
from skelid.simulate import builtin_model, simulate

#: small, fast settings per estimator (the contract does not depend on them)
FAST = {
    "marker": {"rng": 0},
    "paper": {"rng": 0},
    "marker-grid": {"rng": 0, "axes": (np.linspace(220.0, 280.0, 9),)},
    "marker-smc": {"rng": 0, "n_particles": 24, "n_moves": 1},
    "marker-multi": {"rng": 0, "cutoff": None, "jackknife": False},
}
#: the registered estimators and the several-trial one (not a --method: it runs when several files are given)
ESTIMATORS = {**estimators(), MultiTrialEstimator.name: MultiTrialEstimator}
#: a bad value per common setting, and the error it must raise
BAD_SETTINGS = [("sigma", -1.0), ("sigma", float("nan")), ("sigma", "15"), ("rng", "seed"), ("rate", "100"),
                ("rate", -5.0)]


def _model():
    """Case A with its one parameter called ``sigma``: a name the old result dict swallowed."""
    d = builtin_model("case-a").to_dict()
    d["parameters"][0]["name"] = "sigma"
    return model_from_dict(d)


MODEL = _model()
TRIAL = simulate(MODEL, n_frames=60, sigma=5.0, rng=np.random.default_rng(11))
#: the several-trial estimator sees the same frames as two trials
HALVES = [MarkerData(TRIAL.data.positions[a:b], TRIAL.data.names, TRIAL.data.rate, TRIAL.data.units,
                     source=f"half{k + 1}.trc") for k, (a, b) in enumerate([(0, 30), (30, 60)])]
_FITTED: dict = {}


def _new(name, **kw):
    if name in estimators():
        return make_estimator(name, MODEL, **{**FAST[name], **kw})
    est = ESTIMATORS[name](MODEL, **{**FAST[name], **kw})
    check_settings(est)  # as the registry does
    return est


def _data(name):
    """The trial(s) an estimator is fitted to: one, or the two halves for the several-trial one."""
    return HALVES if name == MultiTrialEstimator.name else TRIAL.data


def _array(name, narrow=False):
    """The same as plain arrays (``narrow``: of a shape that does not fit the model)."""
    cut = (lambda a: a[:, :2]) if narrow else (lambda a: a)
    if name == MultiTrialEstimator.name:
        return [cut(np.asarray(h.positions)) for h in HALVES]
    return cut(np.asarray(TRIAL.data.positions))


def _fitted(name):
    """One fitted estimator per name, shared by the checks that only read it."""
    if name not in _FITTED:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SkelidWarning)
            _FITTED[name] = _new(name).fit(_data(name))
    return _FITTED[name]


def _fit(est, data=None, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkelidWarning)
        return est.fit(_data(est.name) if data is None else data, **kw)


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)
    if isinstance(a, tuple | list) and isinstance(b, tuple | list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a is b or a == b


def _public_fitted(est) -> list[str]:
    return [a for a in vars(est) if a.endswith("_") and not a.startswith("_")]


# ---------------------------------------------------------------------------- checks
def check_declares_settings(name):
    cls = ESTIMATORS[name]
    assert cls.name == name and cls.settings, "every estimator declares its settings"
    est = _new(name)
    assert set(get_settings(est)) == {s.name for s in cls.settings}
    for s in cls.settings:
        assert s.allowed, f"setting {s.name} says what values it takes"


def check_init_stores_settings_only(name):
    est = _new(name)
    assert _public_fitted(est) == []
    with pytest.raises(NotFittedError):
        est.result()
    with pytest.raises(NotFittedError):
        est.result()


def check_fit_returns_self(name):
    est = _new(name)
    assert _fit(est) is est


def check_fit_leaves_settings_alone(name):
    est = _new(name)
    before = dict(get_settings(est))
    _fit(est)
    after = get_settings(est)
    assert all(_same(before[k], after[k]) for k in before), "fit changed a setting"


def check_common_fitted_attributes(name):
    est = _fitted(name)
    F = TRIAL.data.n_frames
    assert est.frames_used_.dtype == bool and est.frames_used_.shape == (F,)
    assert isinstance(est.sigma_, float) and est.sigma_ > 0
    assert tuple(est.posterior_.names) == MODEL.parameter_names
    assert isinstance(est.warnings_, tuple) and all(isinstance(w, Warning) for w in est.warnings_)


def check_fit_twice_same_result(name):
    est = _new(name)
    a = _fit(est).result()
    b = _fit(est).result()
    np.testing.assert_array_equal(a.values("mean"), b.values("mean"))
    np.testing.assert_array_equal(a.values("sd"), b.values("sd"))
    assert a.warnings == b.warnings


def check_typed_result(name):
    r = _fitted(name).result()
    assert isinstance(r, FitResult) and r.method == name
    assert r.names == MODEL.parameter_names == ("sigma",)
    p = r.parameters["sigma"]
    assert p.interval[0] <= p.mean <= p.interval[1] and p.sd > 0
    assert r.noise is not None and r.noise.sigma > 0
    assert r.frames.total == TRIAL.data.n_frames and 0 < r.frames.used <= r.frames.total


def check_result_round_trips(name, tmp_path):
    r = _fitted(name).result()
    write_run(tmp_path, FitRun({name: r}))
    back = read_run(tmp_path).results[name]
    assert back.names == r.names
    for k in r.names:
        a, b = r.parameters[k], back.parameters[k]
        assert (a.map, a.mean, a.interval, a.status, a.extra) == (b.map, b.mean, b.interval, b.status, b.extra)
        assert a.sd == b.sd or (math.isnan(a.sd) and math.isnan(b.sd))
    assert back.warnings == r.warnings and back.frames == r.frames and back.noise == r.noise
    for k, v in r.arrays.items():
        np.testing.assert_array_equal(back.arrays[k], v)


def check_array_needs_rate(name):
    with pytest.raises(SettingError, match="rate"):
        _fit(_new(name), _array(name))
    with pytest.raises(DataError, match="does not fit model"):
        _fit(_new(name, rate=100.0), _array(name, narrow=True))


def check_array_with_rate_equals_marker_data(name):
    est = _fit(_new(name, rate=TRIAL.data.rate), _array(name))
    np.testing.assert_allclose(est.result().values("mean"), _fitted(name).result().values("mean"),
                               rtol=1e-12)


def check_bad_settings_name_the_setting(name):
    for setting, value in BAD_SETTINGS:
        est = ESTIMATORS[name](MODEL, **{**FAST[name], setting: value})  # __init__ only stores it
        with pytest.raises(SettingError, match=setting) as err:
            _fit(est)
        assert isinstance(err.value, ValueError) and isinstance(err.value, SkelidError)
        assert "\n" not in err.value.one_line()
        with pytest.raises(SettingError, match=setting):  # the registry checks before any data are read
            _new(name, **{setting: value})


def check_no_frames_is_a_data_error(name):
    empty = MarkerData(np.full((5, len(MODEL.markers), MODEL.dim), np.nan), MODEL.marker_names, 100.0)
    with pytest.raises(DataError):
        _fit(_new(name), empty)


def check_fit_folds_update(name):
    est = _fitted(name)
    if not hasattr(est, "update"):
        pytest.skip(f"{name} has no online form")
    state = est.init_state()
    for frame in np.asarray(TRIAL.data.positions):
        state = est.update(state, frame)
    np.testing.assert_allclose(est.posterior(state).log_weights if hasattr(est, "posterior") and
                               callable(est.posterior) else state.posterior.log_weights,
                               est.posterior_.log_weights, atol=1e-9)


def check_progress_is_called(name):
    ticks = []
    _fit(_new(name), progress=ticks.append)
    assert sum(ticks) == TRIAL.data.n_frames


CHECKS = [check_declares_settings, check_init_stores_settings_only, check_fit_returns_self,
          check_fit_leaves_settings_alone, check_common_fitted_attributes, check_fit_twice_same_result,
          check_typed_result, check_result_round_trips, check_array_needs_rate,
          check_array_with_rate_equals_marker_data, check_bad_settings_name_the_setting,
          check_no_frames_is_a_data_error, check_fit_folds_update, check_progress_is_called]


@pytest.mark.parametrize("check", CHECKS, ids=lambda c: c.__name__.removeprefix("check_"))
@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_contract(name, check, tmp_path):
    if "tmp_path" in check.__code__.co_varnames[:check.__code__.co_argcount]:
        check(name, tmp_path)
    else:
        check(name)


def test_every_registered_estimator_has_fast_settings():
    assert set(FAST) == set(ESTIMATORS)


def test_reserved_looking_parameter_names_survive_a_marker_fit(tmp_path):
    """Three parameters called sigma, warnings and lengths keep their own entries."""
    d = builtin_model("case-b").to_dict()
    d["parameters"][0]["name"] = "sigma"
    d["parameters"] += [
        {"name": "warnings", "kind": "marker_position", "marker": "B", "axis": "x",
         "prior": {"type": "uniform", "lower": 80.0, "upper": 140.0}},
        {"name": "lengths", "kind": "marker_position", "marker": "D", "axis": "x",
         "prior": {"type": "uniform", "lower": 150.0, "upper": 210.0}}]
    model = model_from_dict(d)
    trial = simulate(model, n_frames=80, sigma=3.0, rng=np.random.default_rng(3))
    est = _fit(make_estimator("marker", model, rng=0, cutoff=None), trial.data)
    r = est.result()
    assert r.names == ("sigma", "warnings", "lengths")
    write_run(tmp_path, FitRun({"marker": r}))
    back = read_run(tmp_path).results["marker"]
    assert back.names == ("sigma", "warnings", "lengths")
    np.testing.assert_allclose(back.values("mean"), r.values("mean"))
    assert back.noise.sigma == r.noise.sigma
