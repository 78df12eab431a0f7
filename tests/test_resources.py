"""Memory and time estimated before allocation; refused beyond the limits with one line."""

import sys

import numpy as np
import pytest

from skelid import resources
from skelid.errors import SkelidError
from skelid.simulate import builtin_model, simulate
from tests.helpers import run_cli


def _tiny_step_model(tmp_path, step):
    text = (resources.Path(__file__).resolve().parents[1] / "examples" / "case_a.toml").read_text()
    p = tmp_path / "tiny.toml"
    p.write_text(text.replace("grid_step = 0.5", f"grid_step = {step}"))
    assert f"grid_step = {step}" in p.read_text()
    return p


@pytest.fixture(scope="module")
def trial(tmp_path_factory):
    import numpy as np

    from skelid.io import write_trc
    from skelid.simulate import simulate
    p = tmp_path_factory.mktemp("res") / "a.trc"
    write_trc(p, simulate(builtin_model("case-a"), n_frames=60, rng=np.random.default_rng(0)).data)
    return p


@pytest.mark.parametrize("step, method", [(1e-6, "paper"), (1e-6, "marker-grid"), (1e-12, "paper")])
def test_tiny_grid_step_is_refused_before_allocating(tmp_path, trial, step, method):
    model = _tiny_step_model(tmp_path, step)
    r = run_cli(["fit", model, trial, "--method", method], memory_mb=2500)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr[-2000:]
    assert "grid_step" in lines[0] and ("--max-memory" in lines[0] or "grid" in lines[0])


def test_lower_limit_refuses_and_names_the_flag(trial):
    r = run_cli(["fit", "case-a", trial, "--max-memory", "100K"], memory_mb=None)
    assert r.returncode == 2 and "--max-memory" in r.stderr and r.stderr.count("\n") == 1
    r = run_cli(["fit", "case-a", trial], memory_mb=None, env={"SKELID_MAX_TIME": "1e-6"})
    assert r.returncode == 2 and "--max-time" in r.stderr and r.stderr.count("\n") == 1


def test_a_million_frames_are_refused_with_an_estimate():
    m = builtin_model("case-a")
    with pytest.raises(resources.ResourceError, match=r"would take roughly .* \(fix: use fewer frames"):
        resources.check(resources.fit_cost(m, "marker", 10**6), resources.Limits())
    with pytest.raises(resources.ResourceError, match="particles"):
        resources.check(resources.fit_cost(m, "marker-smc", 10**6), resources.Limits(seconds=1e12))


def test_grid_points_never_overflow():
    d = builtin_model("case-a").to_dict()
    d["parameters"][0]["grid_step"] = 1e-300
    from skelid.model import model_from_dict

    m = model_from_dict(d)
    assert resources.grid_points(m) > 1e300
    with pytest.raises(SkelidError, match="grid_step"):
        resources.check_grid(m, "paper")
    with pytest.raises(SkelidError, match="grid_step"):
        _ = m.parameters[0].grid


@pytest.mark.parametrize("text, n", [("4G", 4 * 2**30), ("512M", 512 * 2**20), ("1.5GiB", int(1.5 * 2**30)),
                                     ("1000", 1000), ("2kb", 2048)])
def test_parse_size(text, n):
    assert resources.parse_size(text) == n


@pytest.mark.parametrize("text", ["", "-1G", "lots", "0", "1e999G"])
def test_parse_size_refuses(text):
    with pytest.raises(SkelidError):
        resources.parse_size(text)


def test_estimate_frames(trial):
    n = resources.estimate_frames(trial)
    assert 50 <= n <= 70


def test_the_time_limit_covers_every_trial_of_a_fit_and_of_a_batch(tmp_path):
    """Twelve trials cost twelve times one in the estimate behind --max-time: a limit one trial fits in
    refuses the twelve, for a several-trial fit and for a batch alike, in one line and with nothing written."""
    from skelid.io.trc import write_trc

    model = builtin_model("case-a")
    paths = []
    for k in range(12):
        p = tmp_path / "trials" / f"t{k:02d}.trc"
        p.parent.mkdir(exist_ok=True)
        write_trc(p, simulate(model, n_frames=300, sigma=2.0, rng=np.random.default_rng(k)).data)
        paths.append(p)
    one, twelve = resources.trials_cost([model], paths[:1]).seconds, resources.trials_cost([model], paths).seconds
    assert twelve > 10 * one
    limit = f"{(one * twelve) ** 0.5:.3f}s"  # between the two
    r = run_cli(["fit", "case-a", *paths, "--max-time", limit, "--out", tmp_path / "fit"], memory_mb=None)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "would take roughly" in r.stderr and "12 trials" in r.stderr and "--max-time" in r.stderr
    assert not (tmp_path / "fit").exists()
    batch_one = resources.batch_cost(model, "marker", paths[:1], 1).seconds
    batch_all = resources.batch_cost(model, "marker", paths, 1).seconds
    assert batch_all > batch_one + 10 * (batch_one - resources.BATCH_START_SECONDS)
    limit = f"{(batch_one + batch_all) / 2:.3f}s"
    r = run_cli(["batch", "case-a", str(tmp_path / "trials" / "*.trc"), "--out", tmp_path / "b.csv",
                 "--workers", "1", "--max-time", limit], memory_mb=None)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "12 trials" in r.stderr and "--max-time" in r.stderr
    assert not (tmp_path / "b.csv").exists()
    r = run_cli(["fit", "case-a", paths[0], "--max-time", limit, "--out", tmp_path / "fit1"], memory_mb=None)
    assert r.returncode == 0, r.stderr  # one trial fits within it


def test_a_fit_that_runs_past_its_time_limit_is_stopped_in_one_line(tmp_path, monkeypatch, capsys):
    """A job the cost estimate lets through but that runs longer (the estimate bypassed here) is stopped at
    --max-time: exit 2, one line naming the limit, no result folder."""
    from skelid.cli import main
    from skelid.io.trc import write_trc

    trial = tmp_path / "long.trc"
    write_trc(trial, simulate(builtin_model("case-a"), n_frames=20000, sigma=2.0,
                              rng=np.random.default_rng(0)).data)
    monkeypatch.setattr(resources, "check", lambda cost, limits=None, what="": cost)
    out = tmp_path / "fit"
    assert main(["fit", "case-a", str(trial), "--max-time", "0.5s", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "ran past its time limit of" in err and "--max-time" in err, err
    assert not out.exists()


_KEPT = """
import os, sys
import numpy as np
from skelid.resources import keep_freed_memory
took = keep_freed_memory() if sys.argv[1] == "keep" else None
def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
before = rss()
a = np.ones(2**24)  # 128 MiB, written
del a
print(took, (rss() - before) / 2**20)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_freed_arrays_stay_in_the_heap_for_the_next_ones_with_the_programs_setting():
    """A 128 MiB array made and freed: by default glibc maps it afresh and returns it to the system (the
    kernel zeroes new pages for every one: 29 of 110 CPU seconds of a six-trial full-body fit); with the
    program's setting the heap keeps it for the next array."""
    import subprocess

    runs = {how: subprocess.run([sys.executable, "-c", _KEPT, how], capture_output=True, text=True, check=True)
            .stdout.split() for how in ("default", "keep")}
    if runs["keep"][0] != "True":
        pytest.skip("not glibc")
    assert float(runs["default"][1]) < 16.0
    assert float(runs["keep"][1]) > 120.0


def test_one_blas_thread_holds_every_blas_library_loaded_after_the_first_use(tmp_path):
    """The command line's start loads numpy's BLAS but not scipy's; the limit must reach both, whichever loads
    first (with scipy's left at its default, the gait2354 fit spent 60 % more CPU than wall on two cores)."""
    import os
    import subprocess

    pytest.importorskip("threadpoolctl")
    code = (
        "from skelid._linalg import one_blas_thread\n"
        "with one_blas_thread():\n"
        "    import scipy.linalg\n"
        "    from threadpoolctl import threadpool_info\n"
        "    print(sorted({(i['filepath'], i['num_threads']) for i in threadpool_info()"
        " if i['user_api'] == 'blas'}))\n"
    )
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    env["OPENBLAS_NUM_THREADS"] = "4"  # a default above one, whatever the machine's cores
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    libs = eval(r.stdout)  # noqa: S307  (our own printout of a list of tuples)
    assert libs and all(n == 1 for _, n in libs), libs
