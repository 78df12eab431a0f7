"""The command line's error contract: a user's mistake gives exit status 2, exactly
one line on stderr naming the problem and the fix, no traceback and nothing
written; a bug in skelid gives exit status 1 and its traceback."""

import dataclasses
import json
import os
import re
import shlex
import tempfile

import numpy as np
import pytest

from skelid import workflows
from skelid.cli import main
from skelid.data import MarkerData
from skelid.io import write_trc
from skelid.simulate import builtin_model, simulate
from tests.conftest import EXAMPLES, ROOT

CASE_A = str(EXAMPLES / "case_a.toml")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("inputs")
    trial = simulate(builtin_model("case-a"), sigma=3.0, n_frames=40, rng=np.random.default_rng(0))
    f = {"good": d / "good.trc", "dir": d / "a_folder", "empty": d / "empty.trc", "empty_model": d / "empty.toml",
         "mm_as_m": d / "units.trc", "two_markers": d / "two.trc", "all_nan": d / "nan.trc",
         "binary_model": d / "binary.toml", "a_file": d / "plain_file", "c3d_named": d / "data.xyz",
         "broken_result": d / "broken_result", "no_result": d / "no_result", "ok_result": d / "ok_result"}
    write_trc(f["good"], trial.data)
    f["good_link"] = d / "link.trc"
    os.symlink(f["good"], f["good_link"])
    f["good_copy"] = d / "copy.trc"
    f["good_copy"].write_bytes(f["good"].read_bytes())
    f["dir"].mkdir()
    f["empty"].write_bytes(b"")
    f["empty_model"].write_bytes(b"")
    write_trc(f["mm_as_m"], trial.data.replace(positions=trial.data.positions / 1000.0))  # says mm, holds m
    write_trc(f["two_markers"], MarkerData(trial.data.positions[:, :2], ("A", "B"), 100.0))
    write_trc(f["all_nan"], trial.data.replace(positions=np.full_like(trial.data.positions, np.nan)))
    f["binary_model"].write_bytes(bytes(range(256)))
    f["a_file"].write_text("not a folder\n")
    f["c3d_named"].write_text("x\n")
    f["broken_result"].mkdir()
    (f["broken_result"] / "result.json").write_text('{"methods": {"paper": ')
    f["no_result"].mkdir()
    from skelid.io.results import write_run
    from skelid.result import FitRun

    f["ok_result"].mkdir()
    write_run(f["ok_result"], FitRun())
    f["nameless_result"] = d / "nameless_result"
    f["nameless_result"].mkdir()
    write_run(f["nameless_result"], FitRun(context={"data_overview": {"markers": [{"used_by_model": True}]}}))
    f["rate0_result"] = d / "rate0_result"
    f["rate0_result"].mkdir()
    write_run(f["rate0_result"], FitRun(arrays={"markers": trial.data.positions, "rate": np.array(0.0),
                                                "marker_names": np.array(trial.data.names), "units": np.array("mm")}))
    case_a = (EXAMPLES / "case_a.toml").read_text()
    f["rigid_model"] = d / "rigid.toml"  # every joint fixed: one rigid body
    f["rigid_model"].write_text(re.sub(r'type = "revolute", position = \[([^\]]*)\], range = \[[^\]]*\]',
                                       r'type = "fixed", position = [\1]', case_a))
    f["other_markers"] = d / "other_markers.toml"  # another model of the body, one marker renamed
    f["other_markers"].write_text(case_a.replace('name = "case_a"', 'name = "case_a_other"')
                                  .replace('name = "C" ', 'name = "C2"'))
    return {k: str(v) for k, v in f.items()}


BAD = {
    # label: (argv with {placeholders}, text the one line must contain)
    "output folder is an existing file": ("fit {case_a} {good} --out {a_file}", "is an existing file"),
    "output folder inside a file": ("fit {case_a} {good} --out {a_file}/sub", "is a file"),
    "data path is a folder": ("fit {case_a} {dir} --out {out}", "is a folder, not a file"),
    "model path is a folder": ("fit {dir} {good} --out {out}", "is a folder, not a file"),
    "empty data file": ("fit {case_a} {empty} --out {out}", "is empty"),
    "empty model file": ("fit {empty_model} {good} --out {out}", "is empty"),
    "binary model file": ("fit {binary_model} {good} --out {out}", "is not text"),
    "no such data file": ("fit {case_a} {dir}/nope.trc --out {out}", "does not exist"),
    "unsupported data file type": ("fit {case_a} {c3d_named} --out {out}", "unsupported file type"),
    "wrong units in the file": ("fit {case_a} {mm_as_m} --out {out}", "units"),
    "model marker not in the file": ("fit {case_a} {two_markers} --out {out}", "marker(s) C"),
    "marker missing in every frame": ("fit {case_a} {all_nan} --out {out}", "missing in every frame"),
    "unknown method": ("fit {case_a} {good} --method nonsense --out {out}", "unknown method 'nonsense'"),
    "sigma not a number": ("fit {case_a} {good} --sigma nan --out {out}", "--sigma must be a finite number"),
    "sigma zero": ("fit {case_a} {good} --sigma 0 --out {out}", "'--sigma'"),
    "sigma negative": ("fit {case_a} {good} --sigma -3 --out {out}", "'--sigma'"),
    "sigma absurdly small": ("fit {case_a} {good} --sigma 1e-300 --out {out}", "implausibly small"),
    "negative seed": ("fit {case_a} {good} --seed -1 --out {out}", "'--seed'"),
    "missing argument": ("fit {case_a}", "Missing argument 'DATA_PATHS...'"),
    "unknown option": ("fit {case_a} {good} --frobnicate", "No such option"),
    "unknown command": ("frobnicate", "No such command"),
    "simulate to an unknown file type": ("simulate case-a --out {out}.txt", "end the file name with .trc or .csv"),
    "simulate an unknown model": ("simulate case-z --out {out}.trc", "does not exist"),
    "demo into an existing file": ("demo --out {a_file} --frames 10", "is an existing file"),
    "report of a missing folder": ("report {dir}/nope", "does not exist"),
    "report of a folder without result.json": ("report {no_result} --out {out}.html", "has no result.json"),
    "report of a damaged result.json": ("report {broken_result} --out {out}.html", "is not valid JSON"),
    "report over its own input": ("report {ok_result} --out {ok_result}/result.json", "would overwrite the input"),
    "report into a folder": ("report {ok_result} --out {dir}", "is a folder"),
    "report of a result whose markers have no names": ("report {nameless_result} --out {out}.html",
                                                       "markers[0]: has no key 'name'"),
    "report of arrays.npz with a rate of 0": ("report {rate0_result} --out {out}.html", "rate] is 0 Hz"),
    "a model none of whose joints moves": ("fit {rigid_model} {good} --out {out}", "has no joint that moves"),
    "an alternative model with other markers": ("fit {case_a} {good} --alternative {other_markers} --out {out}",
                                                "uses other markers than 'case_a' (lacks C; adds C2)"),
    "the same data file twice": ("fit {case_a} {good} {good} --out {out}", "is given twice"),
    "the same data file twice under two names": ("fit {case_a} {good} {good_link} --out {out}", "is given twice"),
    "a copy of a data file beside it": ("fit {case_a} {good} {good_copy} --out {out}",
                                        "copy.trc holds the same bytes as"),
}


@pytest.mark.parametrize("label", list(BAD))
def test_bad_input_gives_one_line_and_exit_2(label, files, tmp_path, capfd):
    template, needle = BAD[label]
    out = tmp_path / "out"
    argv = shlex.split(template.format(case_a=CASE_A, out=out, **files))
    code = main(argv)
    cap = capfd.readouterr()
    lines = cap.err.strip().splitlines()
    assert code == 2, (label, cap.err)
    assert len(lines) == 1, (label, cap.err)
    assert lines[0].startswith("skelid: error: ") and needle in lines[0], (label, lines[0])
    assert "Traceback" not in cap.err
    assert not any(tmp_path.iterdir()), (label, list(tmp_path.iterdir()))  # nothing written, not even a temp


def test_unwritable_output_folder_is_a_user_error(files, tmp_path, capfd, monkeypatch):
    def denied(*a, **k):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "mkdtemp", denied)
    code = main(["fit", CASE_A, files["good"], "--out", str(tmp_path / "out"), "--quiet"])
    err = capfd.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "cannot write" in err[0] and "Permission denied" in err[0]


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root reads any file")
def test_unreadable_data_file(files, tmp_path, capfd):
    p = tmp_path / "secret.trc"
    p.write_bytes(open(files["good"], "rb").read())
    p.chmod(0)
    assert main(["fit", CASE_A, str(p)]) == 2
    assert "cannot read data file" in capfd.readouterr().err


def test_a_bug_keeps_its_traceback_and_exit_1(files, capfd, monkeypatch):
    def broken(*a, **k):
        raise RuntimeError("deliberate failure inside the library")

    monkeypatch.setattr(workflows, "fit_file", broken)
    code = main(["fit", CASE_A, files["good"], "--quiet"])
    err = capfd.readouterr().err
    assert code == 1
    assert "Traceback" in err and "RuntimeError: deliberate failure" in err
    assert "bug in skelid" in err.strip().splitlines()[-1]


def test_non_finite_estimates_are_a_bug_not_a_result(files, capfd, monkeypatch):
    from skelid.estimators.paper import PaperFilter

    real = PaperFilter.result

    def nan_result(self):
        res = real(self)
        bad = dataclasses.replace(res.parameters["L2"], mean=float("nan"))
        return dataclasses.replace(res, parameters={**res.parameters, "L2": bad})

    monkeypatch.setattr(PaperFilter, "result", nan_result)
    assert main(["fit", CASE_A, files["good"], "--quiet", "--method", "paper"]) == 1
    assert "non-finite estimates" in capfd.readouterr().err


def test_warnings_printed_once_and_recorded(tmp_path, capfd):
    trial = simulate(builtin_model("case-a"), sigma=3.0, n_frames=60, rng=np.random.default_rng(1))
    y = np.array(trial.data.positions)
    y[10:20, 1] = np.nan  # marker B missing in 10 of 60 frames
    p = tmp_path / "gappy.trc"
    write_trc(p, trial.data.replace(positions=y))
    assert main(["fit", CASE_A, str(p), "--json", "--out", str(tmp_path / "fit")]) == 0
    cap = capfd.readouterr()
    result = json.loads(cap.out)  # stdout holds only JSON
    on_disk = json.loads((tmp_path / "fit" / "result.json").read_text())
    assert result["warnings"] == on_disk["warnings"]
    messages = [w["message"] for w in result["warnings"]]
    gap = next(w for w in messages if w.startswith("marker B is missing in 10 of 60 frames"))
    assert cap.err.count(gap) == 1
    for w in messages:
        assert cap.err.count(f"skelid: warning: {w}\n") == 1
    assert all(line.startswith("skelid: warning: ") for line in cap.err.strip().splitlines())


def test_version(capfd):
    assert main(["--version"]) == 0
    assert "skelid" in capfd.readouterr().out


def test_fit_help_example_runs_as_written(tmp_path, capfd, monkeypatch):
    """The commands in `skelid fit --help` work verbatim from the repository root."""
    assert main(["fit", "--help"]) == 0
    text = capfd.readouterr().out
    commands = [ln.strip() for ln in text.splitlines() if ln.strip().startswith("skelid ")]
    assert [c.split()[1] for c in commands] == ["simulate", "fit", "report"]
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    monkeypatch.chdir(tmp_path)
    for cmd in commands:
        argv = shlex.split(cmd)[1:]
        if argv[0] == "simulate":
            argv[argv.index("--frames") + 1] = "60"  # the same command, shorter
        assert main(argv) == 0, (cmd, capfd.readouterr().err)
    assert (tmp_path / "arm-fit" / "result.json").is_file()
    assert (tmp_path / "arm-report.html").is_file()
