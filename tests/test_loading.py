"""``skelid.load_model``: one entry for TOML and OpenSim models, every problem one line."""

from pathlib import Path

import pytest

import skelid
from skelid.errors import FormatError, ModelError, SkelidError
from skelid.io.osim import load_osim

ROOT = Path(__file__).resolve().parents[1]
SUBJECT01 = ROOT.parent / "shared" / "data" / "opensim-subject01"


def test_a_toml_model_loads_as_before():
    model = skelid.load_model(ROOT / "examples" / "case_a.toml")
    assert model == skelid.model.load_model(ROOT / "examples" / "case_a.toml")


@pytest.mark.skipif(not SUBJECT01.is_dir(), reason="../shared/data/opensim-subject01 is not here")
def test_an_osim_model_loads_with_one_scale_per_body_with_markers(tmp_path):
    path = SUBJECT01 / "std_subject01_simbody.osim"
    model = skelid.load_model(path)
    assert model == load_osim(path, scale="bodies", markers="none")
    assert model.n_params > 0 and all(p.kind == "scale" for p in model.parameters)
    with_offsets = skelid.load_model(path, markers="offsets")
    offsets = [p for p in with_offsets.parameters if p.kind == "marker_offset"]
    assert offsets and len(offsets) % 3 == 0 and with_offsets.n_params == model.n_params + len(offsets)
    copy = tmp_path / "model.xml"  # picked by content when the suffix says nothing
    copy.write_bytes(path.read_bytes())
    assert skelid.load_model(copy) == model


@pytest.mark.parametrize("name,text,error,words", [
    ("bad.osim", "<OpenSimDocument><unclosed", FormatError, "malformed XML"),
    ("bad.toml", "[model\nname=", ModelError, "not valid TOML"),
    ("empty.toml", "", ModelError, "missing key"),
])
def test_a_bad_model_file_is_one_line(tmp_path, name, text, error, words):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(error, match=words) as info:
        skelid.load_model(path)
    assert "\n" not in str(info.value)


def test_a_missing_file_a_folder_and_a_marker_set_for_toml_are_one_line(tmp_path):
    with pytest.raises(ModelError, match="does not exist"):
        skelid.load_model(tmp_path / "none.osim")
    with pytest.raises(ModelError, match="is a folder"):
        skelid.load_model(tmp_path)
    with pytest.raises(SkelidError, match="marker set is for an OpenSim"):
        skelid.load_model(ROOT / "examples" / "case_a.toml", marker_set=tmp_path / "m.xml")
