"""The example model of the tutorial matches the recording it was written for."""

import itertools

import numpy as np
import pytest

from skelid.data import MarkerData
from skelid.model import load_model
from skelid.workflows import check_units, data_overview
from tests.conftest import EXAMPLES
from tests.helpers import load_script

TENNIS = "kineticstoolkit-tennis/kinematics_tennis_serve_nan.c3d"


@pytest.fixture
def tennis(shared_data):
    ezc3d = pytest.importorskip("ezc3d")
    c = ezc3d.c3d(str(shared_data / TENNIS))
    point = c["parameters"]["POINT"]
    pos = np.transpose(c["data"]["points"][:3], (2, 1, 0))
    return MarkerData(pos, point["LABELS"]["value"], float(point["RATE"]["value"][0]),
                      point["UNITS"]["value"][0], source=TENNIS)


def test_tennis_arm_model_fits_the_recording(tennis):
    model = load_model(EXAMPLES / "tennis_forearm.toml")
    assert (model.dim, model.units, model.parameter_names) == (3, "m", ("forearm_length",))
    check_units(model, tennis)  # no error: the model's distances are the data's
    y = tennis.select(model.marker_names, model.marker_labels).positions
    seg = [m.segment for m in model.markers]
    pos = np.array([m.position for m in model.markers])
    for a, b in itertools.combinations(range(len(seg)), 2):
        if seg[a] == seg[b]:  # markers on one segment: the model's distance is the recording's median
            d = np.nanmedian(np.linalg.norm(y[:, a] - y[:, b], axis=1))
            assert np.linalg.norm(pos[a] - pos[b]) == pytest.approx(d, rel=0.02)
    ov = data_overview(tennis, model)
    rsho = next(m for m in ov["markers"] if m["name"] == "Derrick:RSHO")
    assert rsho["used_by_model"] and rsho["frames_missing"] == 145
    assert (ov["n_frames"], ov["rate_hz"], ov["units"]) == (1092, 50.0, "m")


def test_pig_model_is_built_from_the_static_trial_and_fits_both_recordings(shared_data):
    """examples/pig_lower_limb.toml is what examples/build_pig.py writes, and its markers are in both trials."""
    from skelid.io import read_c3d

    def read(trial):  # in this process: the files are known to be sound, and the test must stay fast
        return read_c3d(shared_data / "ktk-gait-pig" / f"{trial}.c3d", isolate=False)

    static = read("static")
    build_pig = load_script(EXAMPLES / "build_pig.py")
    assert build_pig.build(static) == (EXAMPLES / "pig_lower_limb.toml").read_text()
    model = load_model(EXAMPLES / "pig_lower_limb.toml")
    for data in (static, read("gait")):
        assert set(model.marker_names) <= set(data.names)
    # nominal hip centres (Harrington's regression) are symmetric about the pelvis's mid-plane
    hips = [s.joint.position for s in model.segments if s.joint.name in ("hip_r", "hip_l")]
    np.testing.assert_allclose(hips[0][:2], hips[1][:2])
    assert hips[0][2] == pytest.approx(-hips[1][2])
