import numpy as np
import pytest

from skelid.errors import ModelError
from skelid.model import load_model, model_from_dict
from skelid.simulate import builtin_model
from tests.conftest import EXAMPLES, ROOT
from tests.helpers import tree_3d


@pytest.mark.parametrize("case", ["case_a", "case_b"])
def test_example_files_are_the_builtin_models(case):
    shipped = ROOT / "src" / "skelid" / "models" / f"{case}.toml"
    assert (EXAMPLES / f"{case}.toml").read_bytes() == shipped.read_bytes()
    assert load_model(EXAMPLES / f"{case}.toml") == builtin_model(case.replace("_", "-"))


def test_case_geometry():
    a, b = builtin_model("case-a"), builtin_model("case-b")
    assert a.marker_names == ("A", "B", "C") and b.marker_names == ("A", "B", "D", "C")
    assert a.parameter_names == ("L2",) and a.theta_nominal[0] == 250.0
    assert a.n_pose == 5 and a.dim == 2 and a.units == "mm"


@pytest.mark.parametrize("make", [lambda: builtin_model("case-b"), tree_3d])
def test_to_dict_round_trip(make):
    m = make()
    assert model_from_dict(m.to_dict()) == m
    hash(m)


def test_model_is_frozen():
    m = builtin_model("case-a")
    with pytest.raises(AttributeError):
        m.name = "x"


def test_priors():
    m = tree_3d()
    th = np.array([[400.0, 0.0, 25.0], [600.0, 0.0, 25.0]])
    lp = m.log_prior(th)
    assert np.isfinite(lp[0]) and lp[1] == -np.inf


def _base():
    return builtin_model("case-a").to_dict()


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d["segments"][1]["joint"].update(type="ball"), "segments.1..joint.type: unknown value 'ball'"),
    (lambda d: d["segments"][1].update(parent="torso"), "not a segment"),
    (lambda d: d["markers"][0].update(segment="leg"), "not in the model"),
    (lambda d: d["parameters"][0].update(joint="Q"), "refers to joint 'Q'"),
    (lambda d: d["parameters"][0]["prior"].update(lower=400.0),
     "parameters.0..prior: lower 400 must be below upper 300"),
    (lambda d: d["markers"][0].update(position=[1.0]), "markers.0..position: must have 2 numbers, got 1"),
    (lambda d: d.update(extra=1), "extra: unknown key"),
    (lambda d: d["segments"][2].update(parent="hand"), "cycle"),
])
def test_invalid_models_give_one_line_errors(mutate, message):
    d = _base()
    mutate(d)
    with pytest.raises(ModelError, match=message) as info:
        model_from_dict(d, "bad.toml")
    assert "\n" not in str(info.value)


def test_bad_toml_file(tmp_path):
    p = tmp_path / "m.toml"
    p.write_text("[model\nname=1")
    with pytest.raises(ModelError, match="not valid TOML"):
        load_model(p)
    with pytest.raises(ModelError, match="does not exist"):
        load_model(tmp_path / "nope.toml")


def test_a_custom_joint_without_motions_is_a_weld_and_a_carried_motion_needs_its_vector():
    from skelid.model.kinematics import marker_positions

    d = {"model": {"name": "w", "dim": 3},
         "segments": [{"name": "a", "joint": {"type": "free"}},
                      {"name": "b", "parent": "a",
                       "joint": {"type": "custom", "position": [0, 10, 0], "coordinates": [], "motions": []}}],
         "markers": [{"name": "m", "segment": "b", "position": [1, 2, 3]}]}
    model = model_from_dict(d)
    assert model.n_pose == 6
    q = np.array([5.0, 6.0, 7.0, 0.3, -0.2, 0.1])
    R = marker_positions(model, np.zeros(0), q) - q[:3]
    np.testing.assert_allclose(np.linalg.norm(R), np.linalg.norm([1, 12, 3]))  # rigid: distance kept
    carried = {"kind": "carried", "axis": [1, 0, 0], "function": {"type": "constant", "coefficients": [20.0]}}
    d["segments"][1]["joint"]["motions"] = [carried]
    with pytest.raises(ModelError, match="vector"):
        model_from_dict(d)
    carried["vector"] = [0.0, 0.0, 1.0]
    d["segments"][1]["joint"]["motions"] = [{"kind": "rotation", "axis": [0, 1, 0], "coordinate": "c",
                                             "function": {"type": "linear", "coefficients": [1.0, 0.0]}}, carried]
    d["segments"][1]["joint"]["coordinates"] = ["c"]
    model = model_from_dict(d)
    q = np.zeros(7)
    q[6] = 0.5  # the z axis turned by 0.5 rad about y has x component sin(0.5): the centre moves 20 sin(0.5)
    x0 = marker_positions(model, np.zeros(0), np.zeros(7))
    x1 = marker_positions(model, np.zeros(0), q)
    centre_shift = 20 * np.sin(0.5)
    Ry = np.array([[np.cos(0.5), 0, np.sin(0.5)], [0, 1, 0], [-np.sin(0.5), 0, np.cos(0.5)]])
    np.testing.assert_allclose(x1[0], np.array([0, 10, 0]) + [centre_shift, 0, 0] + Ry @ [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(x0[0], [1, 12, 3], atol=1e-12)
