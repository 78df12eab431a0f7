"""Nothing lost, nothing half-written: atomic files and folders, and runs killed half-way."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from skelid.errors import SkelidError
from skelid.io.atomic import atomic_dir, atomic_write, sweep_stale
from skelid.io.trc import write_trc
from skelid.simulate import builtin_model, simulate
from tests.conftest import EXAMPLES

PNG = b"\x89PNG\r\n\x1a\n"


def _siblings(path: Path) -> list[Path]:
    """Hidden temporaries beside ``path``."""
    return [p for p in path.parent.iterdir() if p.name.startswith(f".{path.name}.")]


def test_atomic_write_keeps_old_file_on_error(tmp_path):
    p = tmp_path / "x.json"
    p.write_text("old")
    with pytest.raises(KeyError), atomic_write(p) as fh:
        fh.write("half")
        raise KeyError("stop")
    assert p.read_text() == "old" and not _siblings(p)


def test_atomic_write_gives_new_files_normal_permissions(tmp_path):
    p = tmp_path / "x.txt"
    with atomic_write(p) as fh:
        fh.write("x")
    mask = os.umask(0)
    os.umask(mask)
    assert p.stat().st_mode & 0o777 == 0o666 & ~mask


def test_new_folder_appears_whole_or_not_at_all(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(RuntimeError), atomic_dir(out) as tmp:
        (tmp / "a.png").write_bytes(b"a")
        assert not out.exists()
        raise RuntimeError("interrupted")
    assert not out.exists() and not _siblings(out)
    with atomic_dir(out) as tmp:
        (tmp / "a.png").write_bytes(b"a")
        (tmp / "result.json").write_text("{}")
    assert sorted(p.name for p in out.iterdir()) == ["a.png", "result.json"]
    assert not _siblings(out)


def test_existing_folder_is_refused_or_replaced_whole(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.png").write_text("previous run")
    (out / "result.json").write_text('{"old": 1}')
    with pytest.raises(SkelidError, match="already exists .*--overwrite"), atomic_dir(out) as tmp:
        pass
    assert json.loads((out / "result.json").read_text()) == {"old": 1}
    with atomic_dir(out, overwrite=True) as tmp:
        (tmp / "result.json").write_text('{"new": 1}')
    assert [p.name for p in out.iterdir()] == ["result.json"]  # nothing of the previous run is left
    assert json.loads((out / "result.json").read_text()) == {"new": 1}
    assert not _siblings(out)


def test_output_never_replaces_an_input(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    data = out / "result.json"
    data.write_text("input")
    with pytest.raises(SkelidError, match="would delete the input"), \
            atomic_dir(out, protect=[data], overwrite=True) as tmp:
        (tmp / "result.json").write_text("output")
    assert data.read_text() == "input"


def test_stale_folders_of_dead_runs_are_swept(tmp_path):
    out = tmp_path / "out"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    stale = tmp_path / f".out.{dead}.abcd1234.part"
    stale.mkdir()
    (stale / "result.json").write_text('{"half')
    alive = tmp_path / f".out.{os.getpid()}.efgh5678.part"  # a run still going: left alone
    alive.mkdir()
    assert sweep_stale(out) == [stale]
    assert not stale.exists() and alive.exists()


# ----------------------------------------------------------------------------- killed runs
def _start(args, cwd):
    """The CLI in a subprocess with Ctrl-C delivered as KeyboardInterrupt, as in a terminal."""
    return subprocess.Popen([sys.executable, "-m", "skelid.cli", *args], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _wait_busy(p, cpu_seconds: float = 4.0, timeout: float = 90.0):
    """Wait until the child has done real work (past its imports), then return."""
    stat = Path(f"/proc/{p.pid}/stat")
    if not stat.exists():  # not Linux: a fixed wait well inside the run
        time.sleep(2.5)
        return
    tick = os.sysconf("SC_CLK_TCK")
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and p.poll() is None:
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # it has just exited
            return
        if (int(fields[11]) + int(fields[12])) / tick >= cpu_seconds:  # utime + stime
            return
        time.sleep(0.05)


def _assert_complete_or_absent(out: Path, index: str):
    """No partial file under ``out``: either no folder, or every file in it is whole."""
    if not out.exists():
        return
    names = [p.name for p in out.iterdir()]
    assert not [n for n in names if n.endswith(".part") or n.startswith(".")], names
    assert index in names, names
    json.loads((out / index).read_text())
    for p in out.glob("*.png"):
        data = p.read_bytes()
        assert data[:8] == PNG and data.rstrip().endswith(b"IEND\xaeB`\x82"), p


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_interrupted_demo_leaves_nothing(tmp_path, sig, code):
    out = tmp_path / "demo"
    p = _start(["demo", "--frames", "5000", "--out", str(out), "--quiet"], tmp_path)
    _wait_busy(p)  # well inside the fit of case A
    assert p.poll() is None, p.communicate()
    p.send_signal(sig)
    _, err = p.communicate(timeout=60)
    assert p.returncode == code, err
    assert "Traceback" not in err
    assert not out.exists() and not _siblings(out)


def test_interrupt_keeps_the_previous_output(tmp_path):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "summary.json").write_text('{"previous": true}\n')
    p = _start(["demo", "--frames", "5000", "--out", str(out), "--quiet", "--overwrite"], tmp_path)
    _wait_busy(p)
    p.send_signal(signal.SIGINT)
    p.communicate(timeout=60)
    assert p.returncode == 130
    assert [q.name for q in out.iterdir()] == ["summary.json"]
    assert json.loads((out / "summary.json").read_text()) == {"previous": True}
    assert not _siblings(out)


def test_sigkill_while_writing_leaves_no_partial_file(tmp_path):
    """SIGKILL cannot be caught: kill the moment the output is being written, then check."""
    trc = tmp_path / "long.trc"
    write_trc(trc, simulate(builtin_model("case-a"), n_frames=1500, sigma=5.0).data)
    out = tmp_path / "fit"
    p = _start(["fit", str(EXAMPLES / "case_a.toml"), str(trc), "--out", str(out), "--quiet"], tmp_path)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and p.poll() is None:
        tmp = _siblings(out)
        if tmp and tmp[0].is_dir() and any(tmp[0].iterdir()):
            break  # the figures are being written
        time.sleep(0.005)
    p.kill()
    p.communicate(timeout=30)
    _assert_complete_or_absent(out, "result.json")
    leftovers = _siblings(out)
    assert all(q.is_dir() and q.name.endswith(".part") for q in leftovers), leftovers
    with atomic_dir(out, overwrite=True) as tmp:  # the next run removes what the killed one left
        (tmp / "result.json").write_text("{}")
    assert not _siblings(out)


def test_sigkill_mid_run_keeps_previous_output(tmp_path):
    out = tmp_path / "demo"
    p = _start(["demo", "--frames", "5000", "--out", str(out), "--quiet"], tmp_path)
    _wait_busy(p)
    p.kill()
    p.communicate(timeout=30)
    assert not out.exists()
    assert not list(tmp_path.rglob("*.json")) and not list(tmp_path.rglob("*.png"))
