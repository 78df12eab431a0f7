"""skelid batch: one row per trial on a local Dask cluster, failures as rows, resumable."""

import json
import re
import sys

import numpy as np
import pytest

from skelid.batch import columns, read_table, write_table
from skelid.cli import main
from skelid.io import write_trc
from skelid.simulate import builtin_model, simulate
from tests.conftest import EXAMPLES

pq = pytest.importorskip("pyarrow.parquet", reason="the [dask] extra (pyarrow) is not installed")
pytest.importorskip("distributed", reason="the [dask] extra (dask[distributed]) is not installed")


@pytest.mark.dask  # about 10 s: a two-process local cluster, four 100-frame trials
def test_batch_writes_one_row_per_trial_records_failures_and_resumes(tmp_path, capsys):
    model = builtin_model("case-a")
    trials = tmp_path / "trials"
    trials.mkdir()
    for k in range(3):
        trial = simulate(model, sigma=5.0, n_frames=100, rng=np.random.default_rng(k))
        write_trc(trials / f"t{k}.trc", trial.data)
    (trials / "t3.trc").write_text("PathFileType\t4\t(X/Y/Z)\tbroken.trc\nnot a trc file\n")
    out = tmp_path / "results.parquet"
    args = ["batch", str(EXAMPLES / "case_a.toml"), str(trials / "*.trc"), "--out", str(out),
            "--method", "paper", "--workers", "2", "--quiet", "--json"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary == {**summary, "trials": 4, "fitted": 3, "failed": 1, "skipped": 0}
    rows = pq.read_table(out).to_pylist()
    assert [r["file"].rsplit("/", 1)[-1] for r in rows] == ["t0.trc", "t1.trc", "t2.trc", "t3.trc"]
    for r in rows[:3]:
        assert r["error"] is None and r["n_frames"] == 100 and r["frames_used"] > 50
        assert r["L2_ci_low"] < r["L2"] < r["L2_ci_high"] and 230 < r["L2"] < 270
        assert r["method"] == "paper" and r["sigma"] == 15.0 and r["seconds"] > 0
    bad = rows[3]
    assert bad["error"] and "\n" not in bad["error"] and "t3.trc" in bad["error"]
    assert bad["L2"] is None
    # a re-run finds every trial in the table and adds nothing
    assert main(args) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["skipped"] == 4 and again["fitted"] == again["failed"] == 0
    assert pq.read_table(out).to_pylist() == rows


def test_batch_csv_and_bad_arguments_are_one_line_errors(tmp_path, capsys):
    assert main(["batch", "case-a", str(tmp_path / "*.trc"), "--out", str(tmp_path / "r.csv")]) == 2
    assert "no file matches" in capsys.readouterr().err
    trial = simulate(builtin_model("case-a"), sigma=5.0, n_frames=30)
    write_trc(tmp_path / "a.trc", trial.data)
    assert main(["batch", "case-a", str(tmp_path / "*.trc"), "--out", str(tmp_path / "r.xlsx")]) == 2
    assert "unsupported table type" in capsys.readouterr().err
    (tmp_path / "r.csv").write_text("file,other\nx,1\n")
    assert main(["batch", "case-a", str(tmp_path / "*.trc"), "--out", str(tmp_path / "r.csv")]) == 2
    assert "not those of a skelid batch table" in capsys.readouterr().err


def test_csv_table_round_trip(tmp_path):
    model = builtin_model("case-a")
    cols = columns(model)
    rows = _rows(cols)
    out = tmp_path / "r.csv"
    write_table(out, rows, cols)
    def strip(rs):
        return [{k: v for k, v in r.items() if k != "row_sha256"} for r in rs]

    assert strip(read_table(out, cols)) == strip(sorted(rows, key=lambda r: r["file"]))


def _rows(cols):
    key = {"method": "paper", "settings": '{"seed": 0}', "skelid_version": "0.1.0"}
    return [dict.fromkeys(cols) | key | {"file": "/b.trc", "file_sha256": "bb", "n_frames": 10, "frames_used": 9,
                                         "L2": 250.5, "L2_sd": 1.25, "L2_ci_low": 248.0, "L2_ci_high": 253.0,
                                         "L2_crlb_sd": 1.1, "L2_status": "poor", "sigma": 15.0, "seconds": 0.5},
            dict.fromkeys(cols) | key | {"file": "/a.trc", "file_sha256": "aa",
                                         "error": "a, \"quoted\" problem"}]


@pytest.mark.parametrize("damage, message", [
    (lambda t: t[:-12], "truncated or corrupt|does not match its checksum"),
    (lambda t: t.replace("250.5", "260.5"), "does not match its checksum"),
    (lambda t: t.replace("250.5", "abc"), "is corrupt: line 3 has 'abc'"),
    (lambda t: t + t.splitlines()[2] + "\n", "duplicate rows"),
    (lambda t: t.replace(",", ";"), "not those of a skelid batch table"),
    (lambda t: "\x00\xff" + t, "cannot read|not those"),
])
def test_damaged_tables_are_refused_in_one_line(tmp_path, capsys, damage, message):
    cols = columns(builtin_model("case-a"))
    out = tmp_path / "r.csv"
    write_table(out, _rows(cols), cols)
    out.write_text(damage(out.read_text()))
    before = out.read_bytes()
    write_trc(tmp_path / "a.trc", simulate(builtin_model("case-a"), sigma=5.0, n_frames=30).data)
    assert main(["batch", "case-a", str(tmp_path / "*.trc"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.search(message, err[0]), err
    assert out.read_bytes() == before


class _Now:
    """A stand-in for a Dask client that runs each task at once, in this process."""

    class Future:
        def __init__(self, fn, args):
            self.key, self.value = object(), fn(*args)

        def result(self):
            return self.value

    def submit(self, fn, *args, key=None, pure=None):
        return self.Future(fn, args)

    def close(self):
        pass


def test_exactly_once_keyed_by_content_method_and_settings(tmp_path, monkeypatch):
    from skelid import batch

    monkeypatch.setattr(batch, "_client", lambda workers, scheduler: (_Now(), None))
    monkeypatch.setattr(batch, "_finished", lambda client, futures: iter(futures))
    trials = tmp_path / "trials"
    trials.mkdir()
    for k in range(2):
        write_trc(trials / f"t{k}.trc", simulate(builtin_model("case-a"), sigma=5.0, n_frames=30,
                                                 rng=np.random.default_rng(k)).data)
    out = tmp_path / "r.csv"
    run = lambda **kw: batch.run_batch("case-a", str(trials / "*.trc"), out, method="paper", **kw)  # noqa: E731
    assert run()["fitted"] == 2
    assert run()["skipped"] == 2  # the same settings: nothing again
    assert run(seed=1)["fitted"] == 2  # another seed: new rows beside the old
    assert run(sigma=10.0)["fitted"] == 2
    rows = read_table(out, columns(builtin_model("case-a")))
    assert len(rows) == 6 and len({batch.row_key(r) for r in rows}) == 6
    # each parameter's columns are those of to_dataframe: estimate, sd, interval, bound, status
    assert all(r["L2_status"] == "identified" and r["L2_crlb_sd"] is None for r in rows)  # paper: no bound
    assert all(r["L2_ci_low"] < r["L2"] < r["L2_ci_high"] and r["L2_sd"] > 0 for r in rows)
    (trials / "t0.trc").rename(trials / "renamed.trc")  # the same content under another name: not again
    assert run()["skipped"] == 2


def test_results_folders_go_through_the_serializer(tmp_path, monkeypatch, capsys):
    from skelid import batch
    from skelid.io.results import read_run

    monkeypatch.setattr(batch, "_client", lambda workers, scheduler: (_Now(), None))
    monkeypatch.setattr(batch, "_finished", lambda client, futures: iter(futures))
    write_trc(tmp_path / "t0.trc", simulate(builtin_model("case-a"), sigma=5.0, n_frames=30,
                                            rng=np.random.default_rng(0)).data)
    (tmp_path / "bad.trc").write_text("not a trc file\n")
    out, res = tmp_path / "r.csv", tmp_path / "runs"
    assert main(["batch", "case-a", str(tmp_path / "*.trc"), "--out", str(out), "--method", "paper",
                 "--results", str(res), "--quiet"]) == 0
    rows = {r["file"].rsplit("/", 1)[-1]: r for r in read_table(out, columns(builtin_model("case-a")))}
    assert rows["bad.trc"]["result_dir"] is None and rows["bad.trc"]["error"]
    folder = rows["t0.trc"]["result_dir"]
    assert folder.startswith(str(res / "t0-")) and [p.name for p in res.iterdir()] == [folder.rsplit("/", 1)[-1]]
    run = read_run(folder)
    p = run.results["paper"].parameters["L2"]
    assert (p.mean, p.interval) == (rows["t0.trc"]["L2"], (rows["t0.trc"]["L2_ci_low"], rows["t0.trc"]["L2_ci_high"]))
    assert run.context["provenance"]["command"][:2] == ["skelid", "batch"] and run.arrays["markers"].shape[0] == 30
    # a file where the folder belongs is refused before any work
    (tmp_path / "afile").write_text("x")
    assert main(["batch", "case-a", str(tmp_path / "*.trc"), "--out", str(tmp_path / "r2.csv"),
                 "--results", str(tmp_path / "afile")]) == 2
    assert not (tmp_path / "r2.csv").exists()


def test_a_cluster_that_does_not_start_is_one_line(tmp_path, capsys, monkeypatch):
    import distributed

    def dies(*args, **kwargs):  # what LocalCluster raises when a worker is killed while it starts
        raise RuntimeError("Nanny failed to start.")

    monkeypatch.setattr(distributed, "LocalCluster", dies)
    write_trc(tmp_path / "t0.trc", simulate(builtin_model("case-a"), sigma=5.0, n_frames=30,
                                            rng=np.random.default_rng(0)).data)
    out = tmp_path / "r.csv"
    assert main(["batch", "case-a", str(tmp_path / "*.trc"), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "did not start: Nanny failed to start" in err[0] and "run the command again" in err[0]
    assert not out.exists()


@pytest.mark.dask  # a scheduler in this process, with no worker
def test_a_batch_left_with_no_worker_stops_in_one_line_instead_of_waiting_forever(tmp_path, capsys, monkeypatch):
    from distributed import LocalCluster

    from skelid import batch

    monkeypatch.setattr(batch, "NO_WORKER_WAIT", 1.0)
    monkeypatch.setattr(batch, "_POLL_S", 0.2)
    write_trc(tmp_path / "t0.trc", simulate(builtin_model("case-a"), sigma=5.0, n_frames=30,
                                            rng=np.random.default_rng(0)).data)
    out = tmp_path / "r.csv"
    with LocalCluster(n_workers=0, processes=False, dashboard_address=None) as cluster:
        code = main(["batch", "case-a", str(tmp_path / "*.trc"), "--out", str(out), "--quiet",
                     "--scheduler", cluster.scheduler_address])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "no Dask worker has been connected for 1 s; 1 trial(s)" in err[0], err
    assert not out.exists()  # nothing finished, nothing written


def test_parameter_names_whose_columns_collide_are_one_line():
    from skelid.errors import SkelidError
    from skelid.model import model_from_dict

    spec = builtin_model("case-a").to_dict()
    extra = dict(spec["parameters"][0], name="L2_sd")
    spec["parameters"].append(extra)
    with pytest.raises(SkelidError, match="column 'L2_sd' twice"):
        columns(model_from_dict(spec, "clash"))


def test_missing_extra_is_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)
    assert main(["batch", "case-a", str(tmp_path / "*.trc"), "--out", str(tmp_path / "r.parquet")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "dask[distributed]" in err[0] and "pip install" in err[0]


def test_an_osim_models_trial_that_lacks_some_markers_is_fitted_with_those_it_has(tmp_path):
    """A lab's marker set is its whole protocol: a trial without one of its markers is fitted with the model
    of the markers it has (as 'skelid fit' does), not failed; one without the model's file is still refused."""
    from skelid.batch import fit_trial
    from skelid.data import MarkerData
    from tests.test_scaling import MODEL, _trials, marker_xml

    leg = tmp_path / "leg.osim"
    leg.write_text(MODEL.format(markers=marker_xml()))
    _, move = _trials(leg, {"pelvis": 1.0, "thigh": 1.1, "shank": 1.0})
    keep = [i for i, n in enumerate(move.names) if n != "thigh2"]
    write_trc(tmp_path / "miss.trc", MarkerData(move.positions[:, keep], [move.names[i] for i in keep], move.rate,
                                                move.units, "sim"))
    from skelid.simulate import resolve_model

    model = resolve_model(leg)
    row = fit_trial(str(tmp_path / "miss.trc"), model, osim=str(leg))
    assert row["error"] is None
    assert row["scale_thigh"] == pytest.approx(1.1, abs=1e-3)
    strict = fit_trial(str(tmp_path / "miss.trc"), model)
    assert "thigh2" in strict["error"]


@pytest.mark.dask
def test_a_batch_beside_another_cluster_prints_nothing_under_quiet(tmp_path):
    """With port 8787 taken (another Dask cluster running), the local cluster's health endpoint moves to another
    port without a warning on stderr: under --quiet a batch prints nothing, so a stop's one line stays one line."""
    pytest.importorskip("distributed", reason="the [dask] extra (dask[distributed]) is not installed")
    import socket
    import subprocess

    model = builtin_model("case-a")
    for k in range(2):
        write_trc(tmp_path / f"t{k}.trc", simulate(model, sigma=5.0, n_frames=100, rng=np.random.default_rng(k)).data)
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("", 8787))
        except OSError:
            pass  # already taken by another cluster: the case under test
        else:
            s.listen()
        cli = "import sys; from skelid.cli import main; sys.exit(main())"
        p = subprocess.run([sys.executable, "-c", cli, "batch", "case-a", str(tmp_path / "*.trc"), "--out",
                            str(tmp_path / "rows.csv"), "--workers", "1", "--quiet"], capture_output=True,
                           text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stderr == ""
    assert len(read_table(tmp_path / "rows.csv", columns(model))) == 2
