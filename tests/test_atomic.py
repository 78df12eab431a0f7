"""Nothing lost, nothing half-written: atomic files and folders, and runs killed half-way."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from skelid.errors import SkelidError
from skelid.io.atomic import atomic_dir, atomic_write, sweep_stale


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


def test_existing_folder_keeps_the_users_files(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    (out / "result.json").write_text('{"old": 1}')
    with atomic_dir(out) as tmp:
        (tmp / "result.json").write_text('{"new": 1}')
    assert (out / "notes.txt").read_text() == "mine"
    assert json.loads((out / "result.json").read_text()) == {"new": 1}


def test_output_never_replaces_an_input(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    data = out / "result.json"
    data.write_text("input")
    with pytest.raises(SkelidError, match="would overwrite an input"), atomic_dir(out, protect=[data]) as tmp:
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
