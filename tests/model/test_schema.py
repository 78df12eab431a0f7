"""The model file's schema: unknown keys, strict types, ranges, key paths; docs kept equal to it."""

import re
import tomllib
from pathlib import Path

import pytest

from skelid.errors import ModelError
from skelid.model import load_model, model_from_dict
from skelid.model.schema import documented_keys, reference_markdown, reference_rows, validate
from skelid.simulate import builtin_model

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "model-format.md"


def _base():
    return builtin_model("case-a").to_dict()


def _set(d, path, value):
    keys = re.findall(r"[^.\[\]]+", path)
    for k in keys[:-1]:
        d = d[int(k)] if k.isdigit() else d[k]
    last = keys[-1]
    if value is _DEL:
        del d[last]
    else:
        d[int(last) if last.isdigit() else last] = value


_DEL = object()

BAD = [
    # unknown keys, with the nearest known key suggested
    ("markers[0].postion", [1.0, 2.0], r"markers\[0\]\.postion: unknown key .*did you mean 'position'"),
    ("model.unit", "m", r"model\.unit: unknown key .*did you mean 'units'"),
    ("segments[1].joint.axis", [0, 0, 1], r"segments\[1\]\.joint\.axis: unknown key"),
    ("parameters[0].prior.sd", 5.0, r"parameters\[0\]\.prior\.sd: key not used with type = 'uniform'"),
    # strict types
    ("model.dim", 2.9, r"model\.dim: must be an integer, got 2\.9 \(a float\)"),
    ("model.dim", True, r"model\.dim: must be an integer, got True \(a boolean\)"),
    ("parameters[0].grid_step", True, r"parameters\[0\]\.grid_step: must be a number, got True"),
    ("markers[0].position", ["1", 2.0], r"markers\[0\]\.position\[0\]: must be a number, got '1' \(a string\)"),
    ("markers[0].label", 5, r"markers\[0\]\.label: must be a string, got 5"),
    ("segments[1].name", ["x"], r"segments\[1\]\.name: must be a string"),
    ("parameters[0].prior", "uniform", r"parameters\[0\]\.prior: must be a table"),
    # ranges and magnitudes
    ("segments[1].joint.range", [130.0, 20.0], r"segments\[1\]\.joint\.range: lower 130 must be below upper 20"),
    ("segments[1].joint.range", [[0.0, 20.0], [0.0, 30.0]],
     r"segments\[1\]\.joint\.range: has 2 \[lo, hi\] pair\(s\) for a revolute joint with 1 rotation"),
    ("segments[1].joint.range", [0.0, 1e6], r"joint\.range\[1\]: 1e\+06 is implausibly large"),
    ("markers[0].position", [1e308, 0.0], r"markers\[0\]\.position\[0\]: 1e\+308 is implausibly large"),
    ("parameters[0].prior", {"type": "uniform", "lower": -1e308, "upper": 1e308},
     r"parameters\[0\]\.prior\.lower: -1e\+308 is implausibly large"),
    ("parameters[0].prior", {"type": "uniform", "lower": 0.0, "upper": 5e5},
     r"parameters\[0\]\.prior: interval \[0, 500000\] mm is implausibly wide"),
    ("parameters[0].prior", {"type": "lognormal", "median": 250.0, "sd_log": 300.0},
     r"parameters\[0\]\.prior\.sd_log: 300 is implausibly large"),
    ("parameters[0].prior", {"type": "lognormal", "sd_log": 4.0},
     r"parameters\[0\]\.prior: interval .* is implausibly wide"),
    ("parameters[0].prior", {"type": "normal", "sd": -1.0}, r"parameters\[0\]\.prior\.sd: must be positive"),
    ("parameters[0].prior", {"type": "normal", "mean": 250.0, "sd": 10.0, "lower": 300.0, "upper": 200.0},
     r"parameters\[0\]\.prior: lower 300 must be below upper 200"),
    ("parameters[0].grid_step", 500.0, r"parameters\[0\]\.grid_step: 500 is wider than the prior interval"),
    ("parameters[0].grid_step", 0.0, r"parameters\[0\]\.grid_step: must be positive"),
    # missing and misplaced keys
    ("parameters[0].kind", _DEL, r"parameters\[0\]\.kind: missing key"),
    ("segments[0].joint.type", _DEL, r"segments\[0\]\.joint\.type: missing key"),
    ("parameters[0].marker", "A", r"parameters\[0\]\.marker: key not used with kind = 'length'"),
    ("segments[1].joint.type", "hing", r"segments\[1\]\.joint\.type: unknown value 'hing'"),
    ("parameters[0].kind", "lenght", r"parameters\[0\]\.kind: unknown value 'lenght' .*did you mean 'length'"),
    ("aliases", {"A": 5}, r"aliases\.A: must be a string"),
]


_IDS = [f"{b[0]}=" + ("<deleted>" if b[1] is _DEL else repr(b[1]))[:50] for b in BAD]


@pytest.mark.parametrize("path, value, message", BAD, ids=_IDS)
def test_bad_model_gives_one_line_with_key_path(path, value, message):
    d = _base()
    _set(d, path, value)
    with pytest.raises(ModelError, match=message) as info:
        model_from_dict(d, "bad.toml")
    text = str(info.value)
    assert "\n" not in text and text.startswith("bad.toml: ") and "(fix: " in text


def test_unknown_key_in_a_file_names_file_and_path(tmp_path):
    text = (ROOT / "examples" / "case_a.toml").read_text().replace("position = [110", "postion = [110", 1)
    p = tmp_path / "typo.toml"
    p.write_text(text)
    with pytest.raises(ModelError, match=r"typo\.toml: markers\[\d\]\.postion: unknown key"):
        load_model(p)


def test_every_shipped_model_is_valid():
    files = sorted((ROOT / "examples").glob("*.toml")) + sorted((ROOT / "src/skelid/models").glob("*.toml"))
    assert len(files) >= 8
    for f in files:
        m = load_model(f)
        assert model_from_dict(m.to_dict()) == m


def test_keys_of_another_joint_type_are_named_as_such():
    from tests.helpers import tree_3d

    d = tree_3d().to_dict()
    d["segments"][1]["joint"]["axis"] = [0, 0, 1]  # the hip is spherical
    with pytest.raises(ModelError, match=r"segments\[1\]\.joint\.axis: key not used with type = 'spherical'"):
        model_from_dict(d, "bad.toml")


def test_numpy_numbers_pass_bools_do_not():
    import numpy as np

    d = _base()
    d["markers"][0]["position"] = [np.float64(1.0), np.int64(2)]
    model_from_dict(d)
    d["markers"][0]["position"] = [np.bool_(True), 2.0]
    with pytest.raises(ModelError, match="must be a number"):
        model_from_dict(d)


def test_docs_key_reference_is_generated_from_the_schema():
    text = DOC.read_text()
    block = text.split("<!-- schema-reference: begin -->\n")[1].split("<!-- schema-reference: end -->")[0]
    assert block.strip() == reference_markdown().strip(), \
        "docs/model-format.md's key reference differs from the schema: regenerate it with reference_markdown()"
    assert documented_keys(text) == {r[0] for r in reference_rows()}


def test_docs_examples_use_only_schema_keys():
    text = DOC.read_text()
    blocks = re.findall(r"```toml\n(.*?)```", text, flags=re.S)
    assert blocks
    head = {"model": {"dim": 2, "units": "mm"}}
    for b in blocks:
        d = tomllib.loads(b)
        full = {**head, "segments": [{"name": "s", "joint": {"type": "free"}}],
                "markers": [{"name": "m", "segment": "s"}], **d}
        if full is not d and "model" not in d:
            full["model"] = {"dim": 3}
        validate(full, "docs")  # an unknown key or a wrong type here would raise
    # and every key written in backquotes as `key = ...` in the prose is a key of the schema
    leaves = {r[0].rsplit(".", 1)[-1].rstrip("[]") for r in reference_rows()}
    prose = {k for k in re.findall(r"`(\w+) = ", text) if len(k) > 1}  # not the maths (`a = ...`)
    assert prose <= leaves, prose - leaves
