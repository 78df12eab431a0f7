import numpy as np

from skelid.estimators.paper import PaperFilter
from skelid.simulate import builtin_model, simulate


def test_progress_hook_sees_every_frame_and_changes_nothing():
    model = builtin_model("case-a")
    trial = simulate(model, sigma=3.0, n_frames=30, rng=np.random.default_rng(2))
    ticks = []
    with_hook = PaperFilter(model).fit(trial.data, progress=ticks.append)
    plain = PaperFilter(model).fit(trial.data)
    assert ticks == [1] * 30
    np.testing.assert_array_equal(with_hook.measured_, plain.measured_)
