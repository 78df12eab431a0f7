"""Lengths between joint centres where a joint's centre slides with a coordinate (an OpenSim knee)."""

from __future__ import annotations

import numpy as np
import pytest

from skelid.io.osim import osim_parameters, read_osim
from skelid.model.kinematics import joint_distances
from tests.test_scaling import MODEL, marker_xml


def _leg(tmp_path, scale="bodies"):
    path = tmp_path / "leg.osim"
    path.write_text(MODEL.format(markers=marker_xml()))
    base, info = read_osim(path)
    return osim_parameters(base, info, scale, "offsets")


def test_the_hip_knee_length_follows_the_knee_translation_and_the_thigh_scale(tmp_path):
    model = _leg(tmp_path)
    names = [n for n, _ in model.derived_lengths]
    assert "hip-knee" in names  # the knee centre sits only where its splines put it
    k = names.index("hip-knee")
    theta = model.theta_nominal.copy()
    thigh = model.parameter_names.index("scale_thigh")
    theta[thigh] = 1.1
    L, grad = joint_distances(model, theta)
    at_zero = np.hypot(-0.002, -0.40) * 1000.0  # the splines' values at a straight knee, mm
    assert L[k] == pytest.approx(1.1 * at_zero, rel=1e-12)
    assert grad[k, thigh] == pytest.approx(at_zero, rel=1e-6)
    assert np.count_nonzero(grad[k]) == 1  # nothing else moves it
    # batched draws give the same as one at a time
    draws = theta + np.outer([0.0, 0.05, -0.05], np.eye(model.n_params)[thigh])
    Lb, gb = joint_distances(model, draws)
    assert Lb[:, k] == pytest.approx([1.1 * at_zero, 1.15 * at_zero, 1.05 * at_zero], rel=1e-12)
    assert gb.shape == (3, len(names), model.n_params)


def test_per_axis_factors_move_the_length_along_the_knee_translation(tmp_path):
    model = _leg(tmp_path, "axes")
    k = [n for n, _ in model.derived_lengths].index("hip-knee")
    theta = model.theta_nominal.copy()
    x, y = (model.parameter_names.index(f"scale_thigh_{a}") for a in "xy")
    theta[y] = 1.2
    L, grad = joint_distances(model, theta)
    assert L[k] == pytest.approx(np.hypot(2.0, 480.0), rel=1e-12)
    assert grad[k, y] == pytest.approx(400.0 * 480.0 / np.hypot(2.0, 480.0), rel=1e-6)
    assert grad[k, x] == pytest.approx(2.0 * 2.0 / np.hypot(2.0, 480.0), rel=1e-5)


@pytest.mark.opensim
def test_gait2354_hip_knee_length_equals_opensim(shared_data):
    osim = pytest.importorskip("opensim")
    osim.Logger.removeFileSink()  # OpenSim would write opensim.log beside the model it loads
    d = shared_data / "opensim-subject01"
    base, info = read_osim(d / "gait2354_simbody.osim", d / "gait2354_Scale_MarkerSet.xml")
    model = osim_parameters(base, info, "linked", "none")
    L, _ = joint_distances(model, model.theta_nominal)
    ours = dict(zip((n for n, _ in model.derived_lengths), L, strict=True))
    m = osim.Model(str(d / "gait2354_simbody.osim"))
    state = m.initSystem()
    for i in range(m.getCoordinateSet().getSize()):
        m.getCoordinateSet().get(i).setValue(state, 0.0, False)
    m.realizePosition(state)

    def origin(body):
        p = m.getBodySet().get(body).getPositionInGround(state)
        return np.array([p.get(i) for i in range(3)]) * 1000.0

    for side in "rl":
        theirs = np.linalg.norm(origin(f"tibia_{side}") - origin(f"femur_{side}"))
        assert ours[f"hip_{side}-knee_{side}"] == pytest.approx(theirs, abs=1e-6)
