"""The live health study (benchmarks/live_health.py): its faults touch only their frames, and it reads the names
the session's health text gives (so that a change of wording cannot turn "named right" into "none named")."""

from pathlib import Path

import numpy as np
import pytest

from skelid.live import Session
from skelid.model import load_model
from skelid.simulate import builtin_model, simulate
from tests.helpers import load_script

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def study():
    return load_script(ROOT / "benchmarks" / "live_health.py", "live_health_study")


@pytest.mark.parametrize("fault", ["swap", "dropout", "frozen", "knocked marker", "units cm"])
def test_each_fault_changes_its_own_frames_only(study, fault):
    y = np.random.default_rng(0).normal(size=(study.FRAMES, 4, 3))
    f, (start, end, culprit) = study._faulty(fault, y, np.random.default_rng(1))
    outside = np.ones(len(y), dtype=bool)
    outside[start:end] = False
    np.testing.assert_array_equal(f[outside], y[outside])
    inside = slice(start, end)
    if fault == "swap":
        i, j = culprit
        np.testing.assert_array_equal(f[inside][:, [i, j]], y[inside][:, [j, i]])
        assert end - start == 10
    elif fault == "dropout":
        assert np.isnan(f[inside, culprit]).all() and end - start == 20
        np.testing.assert_array_equal(np.delete(f[inside], culprit, axis=1), np.delete(y[inside], culprit, axis=1))
    elif fault == "frozen":
        assert end - start == 30 and (f[inside] == y[start - 1]).all()
    elif fault == "knocked marker":
        d = f[inside] - y[inside]
        np.testing.assert_allclose(np.linalg.norm(d[:, culprit], axis=-1), study.KNOCK)
        np.testing.assert_allclose(d[:, culprit], np.broadcast_to(d[0, culprit], d[:, culprit].shape))
        assert not np.delete(d, culprit, axis=1).any()
    else:
        np.testing.assert_allclose(f, y / 10.0)


def _texts(model, y, names):
    s = Session(model, labels=names, units=model.units, rate=100.0)
    return [e.health for e in map(s.push, y) if not e.healthy]


def test_the_pair_a_swap_names_is_read_from_the_session_text(study):
    model = builtin_model("case-a")
    trial = simulate(model, n_frames=60, sigma=1.0, rng=np.random.default_rng(0))
    y = trial.data.positions.copy()
    y[40:45, [0, 2]] = y[40:45, [2, 0]]
    texts = _texts(model, y, trial.data.names)
    assert texts and all(study._named(t, model.marker_names)[0] == ("A", "C") for t in texts)


def test_the_marker_a_knock_names_is_read_from_the_session_text(study):
    model = load_model(ROOT / "examples" / "arm.toml")
    trial = simulate(model, n_frames=70, sigma=1.0, rng=np.random.default_rng(0))
    y = trial.data.positions.copy()
    y[60:, 4] += [0.0, 0.0, 30.0]
    texts = _texts(model, y, trial.data.names)
    assert texts and {study._named(t, model.marker_names)[1] for t in texts} == {model.marker_names[4]}
