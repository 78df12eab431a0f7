"""Data that cannot inform a fit, special files and hostile names: one line each, before any fit."""

import os
import re
import stat
import threading

import numpy as np
import pytest

from skelid.cli import main
from skelid.data import MarkerData
from skelid.errors import DataError
from skelid.io import write_trc
from skelid.simulate import builtin_model, simulate


@pytest.fixture(scope="module")
def rows(tmp_path_factory):
    p = tmp_path_factory.mktemp("dc") / "ok.trc"
    write_trc(p, simulate(builtin_model("case-a"), n_frames=40, rng=np.random.default_rng(1)).data)
    lines = p.read_text().splitlines()
    return lines[:6], lines[6:]


def _trc(path, head, body, rate=None):
    h = list(head)
    f = h[2].split("\t")
    if rate is not None:
        f[0] = f[1] = f[5] = rate
    f[2] = f[7] = str(len(body))
    h[2] = "\t".join(f)
    path.write_text("\n".join(h + body) + "\n")
    return path


def _run(capsys, *args):
    code = main([str(a) for a in args])
    err = capsys.readouterr().err
    return code, err


def _one_line_error(code, err, pattern):
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert re.search(pattern, lines[0]), lines[0]


@pytest.mark.parametrize("n", [1, 2])
def test_one_and_two_row_files(tmp_path, rows, capsys, n):
    p = _trc(tmp_path / "short.trc", rows[0], rows[1][:n])
    code, err = _run(capsys, "fit", "case-a", p, "--method", "marker")
    _one_line_error(code, err, rf"has {n} frame\(s\) .* needs at least 5")


def test_all_frames_missing_but_one(tmp_path, rows, capsys):
    body = []
    for k, r in enumerate(rows[1]):
        c = r.split("\t")
        if k != 7:
            c[2:] = [""] * (len(c) - 2)
        body.append("\t".join(c))
    p = _trc(tmp_path / "nan.trc", rows[0], body)
    code, err = _run(capsys, "fit", "case-a", p)
    _one_line_error(code, err, r"has 1 frame\(s\) .*\(40 frames in all\)")


@pytest.mark.parametrize("rate", ["1e300", "5e-324", "0", "-5", "nan"])
def test_absurd_rates(tmp_path, rows, capsys, rate):
    p = _trc(tmp_path / "rate.trc", rows[0], rows[1], rate=rate)
    code, err = _run(capsys, "fit", "case-a", p)
    _one_line_error(code, err, r"DataRate|rate")


def test_time_column_with_tiny_steps(tmp_path, capsys):
    """A CSV's rate comes from its time column: steps of 1e-300 s are refused."""
    data = simulate(builtin_model("case-a"), n_frames=30, rng=np.random.default_rng(2)).data
    lines = ["time,A_x,A_y,B_x,B_y,C_x,C_y"]
    for k in range(30):
        vals = ",".join(f"{v:.4f}" for v in data.positions[k].ravel())
        lines.append(f"{k * 1e-300!r},{vals}")
    p = tmp_path / "t.csv"
    p.write_text("\n".join(lines) + "\n")
    code, err = _run(capsys, "fit", "case-a", p)
    _one_line_error(code, err, r"rate|time")


def test_constant_data_is_refused(tmp_path, rows, capsys):
    first = rows[1][0].split("\t")
    body = ["\t".join(r.split("\t")[:2] + first[2:]) for r in rows[1]]
    p = _trc(tmp_path / "const.trc", rows[0], body)
    for method in ("marker", "paper"):
        code, err = _run(capsys, "fit", "case-a", p, "--method", method)
        _one_line_error(code, err, "nothing moves")


def test_markerdata_rate_is_checked():
    with pytest.raises(DataError, match="sampling rate"):
        MarkerData(np.zeros((3, 2, 2)), ("a", "b"), rate=1e300)
    with pytest.raises(DataError, match="sampling rate"):
        MarkerData(np.zeros((3, 2, 2)), ("a", "b"), rate="100")


def test_fifo_is_refused_without_hanging(tmp_path, rows, capsys):
    fifo = tmp_path / "pipe.trc"
    os.mkfifo(fifo)
    done = []
    t = threading.Thread(target=lambda: done.append(main(["fit", "case-a", str(fifo)])), daemon=True)
    t.start()
    t.join(60)
    if t.is_alive():  # unblock the reader so the test process can end, then fail
        with open(fifo, "w"):
            pass
        pytest.fail("skelid hung reading a FIFO")
    err = capsys.readouterr().err
    assert done == [2] and "named pipe" in err and err.count("\n") == 1
    code, err = _run(capsys, "fit", fifo, _trc(tmp_path / "ok.trc", *rows))
    _one_line_error(code, err, "model file .* named pipe")


@pytest.mark.skipif(not os.path.exists("/dev/null") or not stat.S_ISCHR(os.stat("/dev/null").st_mode),
                    reason="no /dev/null device")
def test_device_and_folder_are_refused(tmp_path, capsys):
    code, err = _run(capsys, "fit", "case-a", "/dev/null")
    _one_line_error(code, err, "is a device")
    code, err = _run(capsys, "fit", "case-a", tmp_path)
    _one_line_error(code, err, "is a folder")


def test_long_file_refused_before_parsing(tmp_path, rows, capsys, monkeypatch):
    body = rows[1] * 2500  # 100000 rows
    p = _trc(tmp_path / "long.trc", rows[0], body)
    monkeypatch.setenv("SKELID_MAX_TIME", "60")
    code, err = _run(capsys, "fit", "case-a", p)
    _one_line_error(code, err, r"fit of about \d{5,6} frames would take roughly .*--max-time")


def test_names_unsafe_as_figure_text_are_drawn_literally(tmp_path):
    from skelid import plots

    data = MarkerData(np.random.default_rng(0).normal(size=(20, 2, 2)), (r"$\foo$", "$x^{"), rate=100.0)
    out = plots.trajectories(data, tmp_path / "t.png", title=r"$\foo$ model")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
