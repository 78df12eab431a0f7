"""SIGTERM and SIGINT at any point of a fit or a batch: exit 130/143 with one line, nothing half-written."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from skelid import _stop
from skelid.io.atomic import atomic_dir
from skelid.io.trc import write_trc
from skelid.simulate import builtin_model, simulate
from tests.conftest import EXAMPLES

CODES = {signal.SIGINT: 130, signal.SIGTERM: 143}


def _start(args, cwd):
    """The console entry point in a subprocess, with the usual disposition of SIGINT (as in a terminal)."""
    return subprocess.Popen([sys.executable, "-c", "import sys; from skelid.cli import main; sys.exit(main())",
                             *args], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _catches_sigterm(pid: int) -> bool:
    """Whether the process has its SIGTERM handler installed (Linux: the SigCgt mask of /proc/PID/status)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return True  # it has just exited
    mask = int(next(line.split()[1] for line in status.splitlines() if line.startswith("SigCgt:")), 16)
    return bool(mask >> (signal.SIGTERM - 1) & 1)


def _wait_handling(p, timeout: float = 60.0) -> float:
    """Wait until the command handles its signals (past the start-up imports); the time it took."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout and p.poll() is None and not _catches_sigterm(p.pid):
        time.sleep(0.01)
    return time.monotonic() - t0


def _assert_one_line(err: str):
    assert "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1, err


def _assert_absent_or_complete(out: Path):
    hidden = [q.name for q in out.parent.iterdir() if q.name.startswith(f".{out.name}.")]
    assert not hidden, hidden
    if out.exists():
        names = sorted(q.name for q in out.iterdir())
        assert "result.json" in names and not [n for n in names if n.startswith(".")], names
        json.loads((out / "result.json").read_text())


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs Linux's /proc to see the handlers")
def test_sigterm_and_sigint_anywhere_in_a_fit_leave_nothing_half_written(tmp_path):
    trc = tmp_path / "walk.trc"
    write_trc(trc, simulate(builtin_model("case-a"), n_frames=1200, sigma=5.0, rng=np.random.default_rng(0)).data)
    args = ["fit", str(EXAMPLES / "case_a.toml"), str(trc), "--quiet", "--out"]
    p = _start([*args, str(tmp_path / "timed")], tmp_path)
    ready = _wait_handling(p)
    t0 = time.monotonic()
    _, err = p.communicate(timeout=120)
    assert p.returncode == 0, err
    run = time.monotonic() - t0  # from the handlers' installation to the end, writing included
    # six points over the run (the reading, the fit, the figures, the move into place) and one past it
    for k, frac in enumerate((0.02, 0.25, 0.5, 0.75, 0.9, 0.97, 1.1)):
        sig = (signal.SIGTERM, signal.SIGINT)[k % 2]
        out = tmp_path / f"fit{k}"
        p = _start([*args, str(out)], tmp_path)
        _wait_handling(p)
        time.sleep(frac * run)
        if p.poll() is None:
            p.send_signal(sig)
        _, err = p.communicate(timeout=120)
        assert p.returncode in (CODES[sig], 0), (frac, p.returncode, err)
        assert "Traceback" not in err, err
        if p.returncode == 0:  # it finished first: the whole folder
            assert (out / "result.json").exists()
        else:
            _assert_one_line(err)
        _assert_absent_or_complete(out)
    assert ready < 60


class _SignalInDestructor:
    """Sends SIGTERM to its own process from ``__del__``, where Python cannot raise the handler's exception."""

    def __del__(self):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)  # the handler runs here; its SystemExit is dropped


def test_a_stop_dropped_in_a_destructor_is_raised_again_silently(capsys):
    with _stop.handling():
        with pytest.raises(SystemExit) as exc:
            _SignalInDestructor()
            for _ in range(500):  # raised again within RETRY_S
                time.sleep(0.01)
    assert exc.value.code == 143
    assert "Traceback" not in capsys.readouterr().err
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # everything restored


def test_a_dropped_stop_never_lets_an_output_folder_appear(tmp_path):
    out = tmp_path / "out"
    with _stop.handling():
        with pytest.raises(SystemExit):
            with atomic_dir(out) as tmp:
                (tmp / "result.json").write_text("{}")
                _SignalInDestructor()  # the folder is complete, but a stop was asked for
    assert not out.exists() and not list(tmp_path.iterdir())


def test_a_stop_during_a_deferred_step_waits_for_its_end():
    """SIGINT's usual disposition first: a library another test ran in this process (a Dask cluster)
    may have left its own handler, which :func:`_stop.handling` rightly leaves in place."""
    done = []
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with _stop.handling():
            with pytest.raises(KeyboardInterrupt):
                with _stop.deferred():
                    os.kill(os.getpid(), signal.SIGINT)
                    deadline = time.monotonic() + 10.0
                    while _stop.pending() is None and time.monotonic() < deadline:
                        time.sleep(0.01)  # the request is recorded, not raised
                    assert _stop.pending() == signal.SIGINT
                    done.append(True)  # not cut short
    finally:
        signal.signal(signal.SIGINT, before)
    assert done == [True]


@pytest.mark.dask
@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs Linux's /proc to see the handlers")
def test_sigterm_during_a_batch_keeps_a_valid_table(tmp_path):
    pytest.importorskip("distributed", reason="the [dask] extra (dask[distributed]) is not installed")
    from skelid.batch import columns, read_table

    model = builtin_model("case-a")
    trials = tmp_path / "trials"
    trials.mkdir()
    for k in range(40):
        write_trc(trials / f"t{k:02d}.trc", simulate(model, sigma=5.0, n_frames=200, rng=np.random.default_rng(k)).data)
    out = tmp_path / "rows.csv"
    p = _start(["batch", "case-a", str(trials / "*.trc"), "--out", str(out), "--workers", "1", "--quiet"], tmp_path)
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline and p.poll() is None and not out.exists():
        time.sleep(0.05)  # the first rows are in the table
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode in (143, 0), err
    assert "Traceback" not in err, err
    rows = read_table(out, columns(model))  # whole, every row matching its checksum
    assert rows and all(r["error"] is None for r in rows)
    if p.returncode == 143:
        _assert_one_line(err)
        assert len(rows) < 40


def _numba_style(stop):
    """What compiled code raises when a stop lands while it calls back into Python."""
    def raiser(*args, **kwargs):
        try:
            raise stop
        except BaseException as exc:
            raise SystemError("<numba dispatcher> returned a result with an exception set") from exc
    return raiser


@pytest.mark.parametrize("where", ["fit", "push"])
def test_a_ctrl_c_that_compiled_code_turned_into_a_system_error_reaches_an_api_caller_as_such(monkeypatch, where):
    """From Python, a Ctrl-C during a fit or a live push is a KeyboardInterrupt, as everywhere else, even when
    numba's dispatcher reported it as a ``SystemError``; a ``SystemError`` of its own passes unchanged."""
    from skelid.estimators import MarkerEstimator
    from skelid.estimators.fit import pose
    from skelid.live import Session

    model = builtin_model("case-a")
    trial = simulate(model, n_frames=60, sigma=1.0, rng=np.random.default_rng(0))

    def call():
        if where == "fit":
            MarkerEstimator(model, rng=0).fit(trial.data)
        else:
            s = Session(model, labels=trial.data.names, rate=100.0)
            for frame in trial.data.positions:
                s.push(frame)

    monkeypatch.setattr(pose, "fit_pose", _numba_style(KeyboardInterrupt()))
    monkeypatch.setattr(pose, "_fit", _numba_style(KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        call()
    monkeypatch.setattr(pose, "_fit", lambda *a, **k: (_ for _ in ()).throw(SystemError("a real one")))
    monkeypatch.setattr(pose, "fit_pose", lambda *a, **k: (_ for _ in ()).throw(SystemError("a real one")))
    with pytest.raises(SystemError, match="a real one"):
        call()


def test_the_stop_inside_a_system_error_is_found_through_its_cause_and_context():
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise SystemError("returned a result with an exception set")  # noqa: B904 - the context is the point
    except SystemError as exc:
        assert isinstance(_stop.stop_in(exc), KeyboardInterrupt)
    assert _stop.stop_in(SystemError("alone")) is None
    assert isinstance(_stop.stop_in(SystemExit(143)), SystemExit) and _stop.stop_in(SystemExit(0)) is None
