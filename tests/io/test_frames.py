"""Results as pandas, xarray and ArviZ objects (skelid.io.frames)."""

import doctest
import json

import numpy as np
import pytest

import skelid.io.frames as frames
from skelid.errors import SkelidError
from skelid.io.frames import COLUMNS, to_dataframe, to_inference_data, to_xarray
from skelid.model import model_from_dict
from skelid.model.kinematics import joint_distances
from tests.test_report import odd_result

pytest.importorskip("pandas")
pytest.importorskip("xarray")
pytest.importorskip("arviz")


def test_doctests():
    import skelid.io.legacy
    import skelid.viewer

    for module in (frames, skelid.io.legacy, skelid.viewer):
        assert doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE).failed == 0, module.__name__


@pytest.fixture
def odd(tmp_path):
    return odd_result(tmp_path / "odd")


def _doc(d):
    res = json.loads((d / "result.json").read_text())
    with np.load(d / "arrays.npz") as z:
        arrays = {k: z[k] for k in z.files}
    return res, arrays


def test_dataframe_has_a_row_per_parameter_derived_length_and_noise(odd):
    res, _ = _doc(odd)
    df = to_dataframe(odd)
    assert list(df.columns) == list(COLUMNS)
    m = res["results"]["marker"]["parameters"]
    params = list(m)
    assert list(df["name"]) == [*params, "hip-knee", "sigma"]
    assert list(df["kind"]) == ["parameter"] * len(params) + ["derived", "noise"]
    for name in params:
        row = df[df["name"] == name].iloc[0]
        assert (row["estimate"], row["map"], row["sd"]) == (m[name]["mean"], m[name]["map"], m[name]["sd"])
        assert (row["lower"], row["upper"], row["crlb_sd"]) == (*m[name]["interval"], 0.9)
    assert df.set_index("name").loc["$\\alpha$", "status"] == "poor"
    assert df.set_index("name").loc["sigma", "estimate"] == 2.0
    assert np.isnan(df.set_index("name").loc["hip-knee", "crlb_sd"])


def test_dataframe_of_a_typed_result():
    """Parameters called sigma and warnings, a derived length called lengths: no collision."""
    from skelid.result import FitResult, NoiseEstimate, ParameterEstimate

    def est(name, mean, status="identified"):
        return ParameterEstimate(name, "mm", mean, mean, 1.0, (mean - 2, mean + 2), None, status)

    r = FitResult("marker", {"sigma": est("sigma", 5.0), "warnings": est("warnings", 7.0, "poor")},
                  {"lengths": est("lengths", 300.0)}, NoiseEstimate(2.5, (2.4, 2.6)))
    df = to_dataframe(r)
    assert list(zip(df["name"], df["kind"], df["estimate"], strict=True)) == [
        ("sigma", "parameter", 5.0), ("warnings", "parameter", 7.0), ("lengths", "derived", 300.0),
        ("sigma", "noise", 2.5)]
    assert list(df["status"][:3]) == ["identified", "poor", "identified"] and df["status"].isna()[3]
    assert df["crlb_sd"].isna().all() and list(df.iloc[3][["lower", "upper"]]) == [2.4, 2.6]


def test_xarray_has_named_dims(odd):
    res, arrays = _doc(odd)
    ds = to_xarray(odd)
    assert dict(ds.sizes) == {"frame": 90, "marker": 10, "axis": 3, "coordinate": arrays["marker/pose"].shape[1]}
    np.testing.assert_array_equal(ds["pose"].values, arrays["marker/pose"])
    np.testing.assert_array_equal(ds["markers"].values, arrays["run/markers"])
    assert list(ds["marker"].values[:2]) == ["$\\foo$", "<script>alert(1)</script>"]
    assert list(ds["coordinate"].values[:6]) == ["root.tx", "root.ty", "root.tz", "root.rz", "root.rx", "root.ry"]
    assert ds["time"].values[10] == pytest.approx(0.1) and ds.attrs["units"] == "mm"
    assert to_xarray(res, arrays=arrays).identical(ds)  # the dict and its arrays give the same


def test_inference_data_from_the_gaussian_posterior(odd):
    res, arrays = _doc(odd)
    model = model_from_dict(res["context"]["model_description"])
    idata = to_inference_data(odd, n_draws=4000, rng=np.random.default_rng(1))
    post = idata.posterior
    names = list(model.parameter_names)
    assert set(post.data_vars) == {*names, "hip-knee"}
    theta = np.stack([post[n].values[0] for n in names], axis=-1)
    assert theta.shape == (4000, len(names))
    mean = np.array([res["results"]["marker"]["parameters"][n]["mean"] for n in names])
    # sd 1 each: the mean of 4000 draws is within 5 standard errors (0.08) of it
    assert np.abs(theta.mean(axis=0) - mean).max() < 0.08
    assert np.abs(theta.std(axis=0) - 1.0).max() < 0.06
    # identical draws from an identical generator
    again = to_inference_data(odd, n_draws=4000, rng=np.random.default_rng(1))
    assert again.posterior[names[0]].equals(post[names[0]])
    np.testing.assert_array_equal(idata.observed_data["markers"].values, arrays["run/markers"])
    assert "independent normals" in post.attrs["draws_from"]


def test_derived_lengths_follow_each_draw(tmp_path):
    from tests.helpers import tree_3d_functional

    model = tree_3d_functional()
    names = model.parameter_names
    lengths, _ = joint_distances(model, model.theta_nominal)
    keys = [k for k, _ in model.derived_lengths]
    assert len(keys) == 3
    cov = np.diag(np.arange(1.0, len(names) + 1))
    result = {"units": model.units, "model_description": model.to_dict(), "methods": {"marker": {
        **{n: {"map": float(v), "mean": float(v), "sd": 1.0, "ci95": [v - 2, v + 2]}
           for n, v in zip(names, model.theta_nominal, strict=True)},
        "lengths": {k: {"value": float(v), "sd": 1.0, "ci95": [v - 2, v + 2]}
                    for k, v in zip(keys, lengths, strict=True)}}}}
    arrays = {"marker.posterior.mean": model.theta_nominal, "marker.posterior.cov": cov}
    idata = to_inference_data(result, n_draws=300, rng=np.random.default_rng(2), arrays=arrays)
    post = idata.posterior
    theta = np.stack([post[n].values[0] for n in names], axis=-1)
    want, _ = joint_distances(model, theta)
    for k, key in enumerate(keys):
        np.testing.assert_allclose(post[key].values[0], want[:, k])
    assert post.attrs["draws_from"] == "the Gaussian posterior (mean and covariance)"
    assert "through the model's geometry" in post.attrs["derived_from"]
    assert "observed_data" not in idata.groups()


def test_inference_data_from_weighted_samples():
    points = np.array([[1.0, 10.0], [2.0, 20.0], [3.0, 30.0]])
    result = {"units": "mm", "methods": {"marker-smc": {
        "a": {"map": 2.0, "mean": 2.0, "sd": 0.5, "ci95": [1, 3]},
        "b": {"map": 20.0, "mean": 20.0, "sd": 5.0, "ci95": [10, 30]}}}}
    arrays = {"marker-smc.posterior.points": points, "marker-smc.posterior.weights": np.array([0.0, 1.0, 0.0])}
    idata = to_inference_data(result, n_draws=50, rng=np.random.default_rng(3), arrays=arrays)
    assert (idata.posterior["a"].values == 2.0).all() and (idata.posterior["b"].values == 20.0).all()
    arrays["marker-smc.posterior.weights"] = np.array([0.25, 0.5, 0.25])
    idata = to_inference_data(result, n_draws=400, rng=np.random.default_rng(3), arrays=arrays)
    a = idata.posterior["a"].values[0]
    assert np.isin(a, [1.0, 2.0, 3.0]).all() and (a == 2.0).sum() == 200  # systematic: exact shares
    np.testing.assert_array_equal(idata.posterior["b"].values[0], 10 * a)  # rows kept together


def test_errors_are_one_line(odd, monkeypatch):
    with pytest.raises(SkelidError, match="no method 'nope'"):
        to_xarray(odd, method="nope")
    with pytest.raises(SkelidError, match="not a skelid fit result"):
        to_dataframe({"x": 1})
    real = frames.importlib.import_module

    def missing(name):
        if name == "pandas":
            raise ImportError(name)
        return real(name)

    monkeypatch.setattr(frames.importlib, "import_module", missing)
    with pytest.raises(SkelidError, match=r"needs the pandas package.*skelid\[data\]"):
        to_dataframe(odd)
