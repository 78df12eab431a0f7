"""skelid batch under faults (the checks of benchmarks/batch_faults.py on smaller batches): a Dask worker killed
mid-run leaves every trial's row exactly once and nothing partial; a full disk (a file-size limit) stops the batch
with one line, leaves a valid table, and a re-run fits only the trials missing from it."""

from pathlib import Path

import pytest

from tests.helpers import load_script

pytest.importorskip("pyarrow.parquet", reason="the [dask] extra (pyarrow) is not installed")
pytest.importorskip("distributed", reason="the [dask] extra (dask[distributed]) is not installed")

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def study():
    return load_script(ROOT / "benchmarks" / "batch_faults.py", "batch_faults_study")


def _trials(study, folder: Path, n: int):
    return folder, study.make_trials(folder, n)


@pytest.mark.dask  # about 10 s: one batch of 20 trials on two worker processes, one of them killed
def test_a_killed_worker_leaves_every_trial_once_and_nothing_partial(study, tmp_path):
    folder, trials = _trials(study, tmp_path / "trials", 20)
    res = study.killed_worker(folder, trials, tmp_path, workers=2, kill_after=1, timeout=120)
    if not res["kills"]:  # the batch outran the watcher (it polls the table every 0.2 s): again, twice as long
        again = tmp_path / "again"
        again.mkdir()
        folder, trials = _trials(study, again / "trials", 40)
        res = study.killed_worker(folder, trials, again, workers=2, kill_after=1, timeout=120)
    assert len(res["kills"]) == 1, "the batch ended before a worker could be killed"
    assert res["completed"], res["attempts"]
    assert res["table_unreadable"] == 0 and res["table_polls"] > 0  # readable whenever it was looked at
    final = res["final"]
    assert final["readable"], final["why_not"]
    assert final["exactly_once"] and final["rows"] == len(trials), final
    assert not final["incomplete_rows"] and not final["part_entries"], final
    assert final["result_folders"] == len(trials) and not final["folders_incomplete"] and not final["folders_missing"]
    assert not final["folders_unnamed"] and final["rows_without_folder"] == 0
    if final["errors"]:  # a row the kill failed is allowed only if --retry-failed fits it
        retry = res["retry_failed"]
        assert retry["exit"] == 0 and not retry["check"]["errors"] and retry["check"]["exactly_once"], retry


@pytest.mark.dask  # about 12 s: a batch of 12 trials under a file-size limit, then again without it
def test_a_full_disk_is_one_line_leaves_a_valid_table_and_a_rerun_fits_only_the_rest(study, tmp_path):
    folder, trials = _trials(study, tmp_path / "trials", 12)
    res = study.disk_full(folder, trials, tmp_path, workers=2, timeout=120, results=False)
    limited = res["limited"]
    assert limited["exit"] == 2 and not limited["hung"], limited
    assert res["one_line"] and not res["traceback"], limited["stderr"]
    assert "File too large" in res["message"] and "full.parquet" in res["message"]
    left = res["table_after"]
    assert left["readable"], left["why_not"]  # the last table written whole, or none at all
    assert res["rows_left"] < 12 and not left["twice"] and not left["errors"] and not left["incomplete_rows"]
    assert not left["part_entries"] and limited["table_unreadable"] == 0
    rerun = res["rerun"]
    assert rerun["exit"] == 0 and rerun["stderr"] == [], rerun
    assert res["fitted_only_missing"], (res["rows_left"], rerun["summary"])
    final = res["final"]
    assert final["exactly_once"] and final["rows"] == 12 and not final["errors"] and not final["part_entries"]
    assert res["ok"]
