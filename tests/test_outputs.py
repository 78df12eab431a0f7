"""Outputs never clobber: regular files and folders only, no replacing links or devices, a lock
against a concurrent writer, existing folders refused unless replaced whole, OSErrors as one line."""

import os
import resource
import signal
import subprocess
import sys

import pytest

from skelid.cli import main
from skelid.errors import SkelidError
from skelid.io.atomic import atomic_dir, atomic_write, target_lock


def _err(capsys, *args):
    code = main([str(a) for a in args])
    return code, capsys.readouterr().err


def _one_line(code, err, text):
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err and text in err, err


def test_out_on_a_dangling_symlink(tmp_path, capsys):
    link = tmp_path / "out"
    link.symlink_to(tmp_path / "nowhere")
    code, err = _err(capsys, "fit", "case-a", "x.trc", "--out", link)
    _one_line(code, err, "symbolic link")
    assert link.is_symlink() and not (tmp_path / "nowhere").exists()


@pytest.mark.parametrize("kind", ["symlink", "fifo"])
def test_files_never_replace_links_or_pipes(tmp_path, kind):
    target = tmp_path / "report.html"
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    if kind == "symlink":
        target.symlink_to(victim)
    else:
        os.mkfifo(target)
    with pytest.raises(SkelidError, match="symbolic link|named pipe"), atomic_write(target) as fh:
        fh.write("new")
    assert victim.read_text() == "keep"
    assert target.is_symlink() if kind == "symlink" else target.is_fifo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.html", "victim.txt"]


def test_report_out_on_a_device_is_refused(tmp_path, capsys):
    res = tmp_path / "res"
    res.mkdir()
    code, err = _err(capsys, "report", res, "--out", "/dev/null")
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err


def test_existing_out_folder_refused_before_the_fit(tmp_path, capsys):
    out = tmp_path / "fit"
    out.mkdir()
    (out / "old.png").write_bytes(b"x")
    code, err = _err(capsys, "fit", "case-a", "x.trc", "--out", out)
    _one_line(code, err, "--overwrite")
    assert [p.name for p in out.iterdir()] == ["old.png"]


def test_overwrite_replaces_the_folder_whole(tmp_path):
    out = tmp_path / "fit"
    out.mkdir()
    (out / "old.png").write_bytes(b"x")
    with atomic_dir(out, overwrite=True) as tmp:
        (tmp / "result.json").write_text("{}")
    assert [p.name for p in out.iterdir()] == ["result.json"]
    assert [p.name for p in tmp_path.iterdir()] == ["fit"]


def test_a_concurrent_writer_is_refused(tmp_path):
    out = tmp_path / "fit"
    with target_lock(out):  # another run holds the target
        with pytest.raises(SkelidError, match="another skelid run is writing"), atomic_dir(out) as tmp:
            (tmp / "result.json").write_text("{}")
        assert not out.exists()
    with atomic_dir(out) as tmp:  # released: the next run may write
        (tmp / "result.json").write_text("{}")
    assert (out / "result.json").exists()


def test_the_lock_is_released_when_its_holder_dies(tmp_path):
    out = tmp_path / "fit"
    code = ("import sys, time; from skelid.io.atomic import target_lock\n"
            f"with target_lock({str(out)!r}):\n    print('held', flush=True); time.sleep(60)\n")
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "held"
        with pytest.raises(SkelidError, match="another skelid run"), target_lock(out):
            pass
    finally:
        p.kill()
        p.wait()
    with target_lock(out):
        pass


def test_file_size_limit_is_one_line(tmp_path):
    """EFBIG (a file-size limit) while writing: one line, exit 2, nothing left behind."""
    def limit():  # pragma: no cover - runs in the child
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (2000, 2000))

    code = "import sys; from skelid.cli import main; sys.exit(main(sys.argv[1:]))"
    r = subprocess.run([sys.executable, "-c", code, "simulate", "case-a", "--frames", "200", "--out", "big.trc"],
                       cwd=tmp_path, capture_output=True, text=True, preexec_fn=limit, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr, r.stderr
    assert "File too large" in r.stderr or "EFBIG" in r.stderr
    assert list(tmp_path.iterdir()) == []
