"""Live sessions on real streams: a recording replayed over LSL on this machine, estimates out over UDP and LSL."""

import json
import math
import socket
import sys
import threading
import uuid
from pathlib import Path

import numpy as np
import pytest

from skelid.cli import main
from skelid.errors import SkelidError, StreamError
from skelid.io import write_trc
from skelid.io.stream import dumps, marker_names, parse_address, stream_unit
from skelid.live import SCHEMA, Session, message
from skelid.simulate import builtin_model, simulate


def _name(tag: str) -> str:
    """A stream name no other test (or anyone else on this machine) uses."""
    return f"skelid-test-{tag}-{uuid.uuid4().hex[:8]}"


@pytest.fixture(scope="module")
def trial():
    return simulate(builtin_model("case-a"), n_frames=120, sigma=1.0, rng=np.random.default_rng(0))


@pytest.fixture(scope="module")
def trc(trial, tmp_path_factory):
    path = tmp_path_factory.mktemp("live") / "arm.trc"
    write_trc(path, trial.data)
    return path


def _publisher(data, name, **kw):
    from skelid.io.stream import publish

    t = threading.Thread(target=publish, args=(data, name), kwargs={"wait": 10.0} | kw, daemon=True)
    t.start()
    return t


# ------------------------------------------------------------------ the message and the stream's metadata
def test_a_message_is_plain_json_with_the_schema_and_nulls_for_what_is_not_finite(trial):
    model = builtin_model("case-a")
    s = Session(model, labels=trial.data.names, method="gaussian")
    for f in trial.data.positions[:20]:
        est = s.push(f)
    msg = json.loads(dumps(message(est, s.advice()[:2], stamp=12.5)))
    assert msg["schema"] == SCHEMA == "skelid.live/1"
    assert msg["frame"] == 20 and msg["stamp"] == 12.5 and msg["units"] == "mm" and msg["healthy"] is True
    (p,) = msg["parameters"]
    assert p["name"] == "L2" and p["lower"] < p["mean"] < p["upper"]
    assert p["mean"] == pytest.approx(est.parameters["L2"].mean)
    assert [c["joint"] for c in msg["joint_centres"]] == ["shoulder", "M", "N"]
    assert all(len(c["position"]) == 3 and c["position"][2] == 0.0 for c in msg["joint_centres"])  # planar: z = 0
    assert len(msg["advice"]) == 2 and msg["advice"][0]["sd_after"] <= msg["advice"][0]["sd_now"]
    empty = Session(model, labels=trial.data.names, method="gaussian").push(np.full((3, 3), np.nan))
    msg = json.loads(dumps(message(empty)))
    assert msg["sigma"] is not None and msg["joint_centres"] == [] and msg["advice"] == []
    assert "missing" in msg["health"]


def test_marker_names_and_units_come_from_the_channel_metadata():
    assert marker_names(["RASI_X", "RASI_Y", "RASI_Z", "L.Knee x", "L.Knee y", "L.Knee z"], "s") == \
        ["RASI", "L.Knee"]
    assert marker_names(["A", "A", "A"], "s") == ["A"]
    with pytest.raises(StreamError, match="7 channels; a marker stream has three per marker"):
        marker_names(["a"] * 7, "s")
    with pytest.raises(StreamError, match="channels 1-3 .* are not one marker's x, y, z"):
        marker_names(["A_X", "B_Y", "A_Z"], "s")
    assert stream_unit(["millimeters"] * 3, "s") == "mm" and stream_unit(["", ""], "s") is None
    assert stream_unit(["m", "meters"], "s") == "m"
    with pytest.raises(StreamError, match="mixes units"):
        stream_unit(["mm", "m"], "s")
    with pytest.raises(StreamError, match="'deg', not a length unit"):
        stream_unit(["deg"], "s")


def test_udp_addresses_are_checked():
    assert parse_address("127.0.0.1:9870") == ("127.0.0.1", 9870)
    assert parse_address("[::1]:5") == ("::1", 5)
    for bad in ("localhost", "host:0", ":9870", "h:99999", "h:x"):
        with pytest.raises(SkelidError, match="is not HOST:PORT"):
            parse_address(bad)


def test_without_pylsl_one_line_says_how_to_install_it(monkeypatch):
    from skelid.io.stream import LslFrames

    monkeypatch.setitem(sys.modules, "pylsl", None)
    with pytest.raises(SkelidError, match=r"fix: pip install skelid\[live\]"):
        LslFrames("anything")


# ------------------------------------------------------------------ end to end on this machine
def _udp_receiver(n_expected, out):
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(15.0)

    def receive():
        try:
            while len(out) < n_expected:
                out.append(json.loads(sock.recv(1 << 16)))
        except TimeoutError:
            pass
        sock.close()

    t = threading.Thread(target=receive, daemon=True)
    t.start()
    return sock.getsockname()[1], t


def _lsl_receiver(name, n_expected, out):
    pylsl = pytest.importorskip("pylsl")

    def receive():
        found = pylsl.resolve_byprop("name", name, timeout=10.0)
        if not found:
            return
        inlet = pylsl.StreamInlet(found[0])
        out.append(inlet.info(timeout=5.0).type())
        inlet.open_stream(timeout=5.0)
        while len(out) < n_expected + 1:
            sample, _ = inlet.pull_sample(timeout=5.0)
            if sample is None:
                return
            out.append(json.loads(sample[0]))

    t = threading.Thread(target=receive, daemon=True)
    t.start()
    return t


def test_replay_to_live_to_udp_and_lsl(trial, trc, tmp_path, capsys):
    pytest.importorskip("pylsl")
    from skelid.io import read_markers

    markers, estimates = _name("markers"), _name("estimates")
    n = 800  # several passes of the file (2 s at 400 Hz): time for the LSL receiver to connect on a busy machine
    udp, lsl = [], []
    port, t_udp = _udp_receiver(n, udp)
    t_lsl = _lsl_receiver(estimates, 5, lsl)
    sender = _publisher(read_markers(trc), markers, rate=400.0, loop=True)
    out = tmp_path / "live.jsonl"
    code = main(["live", "case-a", "--lsl", markers, "--udp", f"127.0.0.1:{port}", "--lsl-out", estimates,
                 "--out", str(out), "--max-frames", str(n), "--timeout", "5"])
    assert code == 0, capsys.readouterr().err
    t_udp.join(20)
    t_lsl.join(20)
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    assert [m["frame"] for m in lines] == list(range(1, n + 1))
    assert all(m["schema"] == SCHEMA and m["stamp"] is not None for m in lines)
    # the same estimate as a session fed the file directly (the stream carries float32)
    direct = Session(builtin_model("case-a"), labels=trial.data.names, units="mm", rate=400.0)
    passes = -(-n // len(trial.data.positions))
    for f in np.concatenate([trial.data.positions] * passes)[:n].astype(np.float32):
        est = direct.push(f)
    assert lines[-1]["parameters"][0]["mean"] == pytest.approx(est.parameters["L2"].mean, rel=1e-9)
    assert lines[-1]["healthy"] and lines[-1]["health"] == "ok"
    assert len(udp) == n and udp[-1] == lines[-1]
    assert lsl[0] == "skelid.live" and len(lsl) == 6 and all(m["schema"] == SCHEMA for m in lsl[1:])
    assert {m["frame"] for m in lsl[1:]} <= set(range(1, n + 1))
    fin = direct.finish().parameters["L2"]  # the last line: every frame folded in
    assert f"{n} frames; L2 {fin.mean:.4g} ± {fin.sd:.2g} mm" in capsys.readouterr().err
    sender.join(0)  # the looping sender is a daemon: it goes with the test process


def test_a_stream_that_vanishes_is_one_line_and_what_came_is_kept(trial, tmp_path, capsys):
    pytest.importorskip("pylsl")
    name = _name("vanish")
    _publisher(trial.data, name, rate=400.0, max_frames=25)
    out = tmp_path / "live.jsonl"
    code = main(["live", "case-a", "--lsl", name, "--out", str(out), "--timeout", "1"])
    err = capsys.readouterr().err
    assert code == 2
    errors = [line for line in err.splitlines() if line.startswith("skelid: error:")]
    assert len(errors) == 1 and "after 25 frames" in errors[0] and "Traceback" not in err
    assert len(out.read_text().splitlines()) == 25


def test_a_stream_with_the_wrong_channel_count_is_one_line(capsys):
    pylsl = pytest.importorskip("pylsl")
    name = _name("channels")
    outlet = pylsl.StreamOutlet(pylsl.StreamInfo(name, "MoCap", 7, 100.0, pylsl.cf_float32, name))
    code = main(["live", "case-a", "--lsl", name, "--timeout", "2", "--units", "mm"])
    err = capsys.readouterr().err
    del outlet
    assert code == 2 and "has 7 channels; a marker stream has three per marker" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_labels_that_do_not_match_the_stream_and_no_stream_at_all_are_one_line(trial, capsys):
    pylsl = pytest.importorskip("pylsl")
    name = _name("labels")
    info = pylsl.StreamInfo(name, "MoCap", 9, 100.0, pylsl.cf_float32, name)
    outlet = pylsl.StreamOutlet(info)
    assert main(["live", "case-a", "--lsl", name, "--labels", "A,B", "--units", "mm", "--timeout", "2"]) == 2
    assert "has 9 channels; 2 labels need 6" in capsys.readouterr().err
    assert main(["live", "case-a", "--lsl", name, "--timeout", "2", "--units", "mm"]) == 2
    assert "names no channels in its metadata" in capsys.readouterr().err
    assert main(["live", "case-a", "--lsl", name, "--labels", "X,Y,Z", "--units", "mm", "--timeout", "2"]) == 2
    assert "none of the labels matches a marker of 'case_a'" in capsys.readouterr().err
    del outlet
    assert main(["live", "case-a", "--lsl", _name("absent"), "--timeout", "0.3"]) == 2
    assert "no LSL stream named" in capsys.readouterr().err


def test_replay_refuses_a_bad_file_and_rate_in_one_line(trc, tmp_path, capsys):
    assert main(["replay", str(tmp_path / "none.trc"), "--lsl", "x"]) == 2
    assert "does not exist" in capsys.readouterr().err
    pytest.importorskip("pylsl")
    assert main(["replay", str(trc), "--lsl", _name("rate"), "--rate", "-3", "--wait", "0"]) == 2
    assert "rate must be a positive number" in capsys.readouterr().err
    assert main(["replay", str(trc), "--lsl", _name("short"), "--max-frames", "3", "--wait", "0"]) == 0
    assert "3 frames of" in capsys.readouterr().err


def test_the_replayed_stream_carries_labels_units_and_rate(trial):
    pytest.importorskip("pylsl")
    from skelid.io.stream import LslFrames

    name = _name("meta")
    data = trial.data
    _publisher(data, name, rate=250.0, max_frames=5)
    src = LslFrames(name, timeout=5.0)
    assert src.labels == list(data.names) and src.units == data.units and src.rate == 250.0
    frames = [f for _, f in zip(range(5), src, strict=False)]
    assert math.isclose(float(frames[0][0, 0]), float(np.float32(data.positions[0, 0, 0])))
    assert src.n_frames == 5 and src.last_stamp is not None


def test_the_protocol_document_lists_exactly_the_fields_a_message_has(trial):
    import re

    text = (Path(__file__).resolve().parents[1] / "docs" / "live-protocol.md").read_text()
    tables = re.split(r"\n(?=Each entry of `parameters`)", text.split("## Fields", 1)[1].split("## Example", 1)[0])
    documented = [re.findall(r"^\| `(\w+)`(?:, `(\w+)`)? \|", t, flags=re.M) for t in tables]
    top = {a for a, _ in documented[0]}
    param = {x for pair in documented[1] for x in pair if x}
    s = Session(builtin_model("case-a"), labels=trial.data.names, method="gaussian")
    for f in trial.data.positions[:30]:
        est = s.push(f)
    msg = message(est, s.advice()[:1], stamp=1.0)
    assert top == set(msg) and param == set(msg["parameters"][0])
    example = json.loads(text.split("```json", 1)[1].split("```", 1)[0])
    assert set(example) == set(msg) and example["schema"] == SCHEMA
    assert set(example["advice"][0]) == set(msg["advice"][0])


SUBJECT01 = Path(__file__).resolve().parents[2] / "shared" / "data" / "opensim-subject01"


@pytest.mark.skipif(not SUBJECT01.is_dir(), reason="../shared/data/opensim-subject01 is not here")
def test_a_real_walking_trial_replayed_to_an_opensim_model(tmp_path, capsys):
    """walk_free_01.trc (41 markers, 73 frames, mm) against the scaled subject01 model (39 markers): the model
    keeps the markers the stream carries, every frame is used, the scales land near the model's own (1), and the
    markers the model does not follow (residuals of 50-78 mm against a noise sd of 14 mm) are named."""
    pytest.importorskip("pylsl")
    from skelid.io import read_markers

    name = _name("walk")
    data = read_markers(SUBJECT01 / "walk_free_01.trc")
    _publisher(data, name, rate=300.0)
    out = tmp_path / "walk.jsonl"
    code = main(["live", str(SUBJECT01 / "std_subject01_simbody.osim"), "--lsl", name, "--out", str(out),
                 "--timeout", "1.5"])
    err = capsys.readouterr().err
    assert code == 2 and "sent nothing for 1.5 s after 73 frames" in err  # the trial ends: one line, kept
    msgs = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(msgs) == 73 and msgs[-1]["units"] == "mm"
    assert not any("not used" in m["health"] for m in msgs), [m["health"] for m in msgs if not m["healthy"]]
    assert all("markers that do not follow the model" in m["health"] for m in msgs[10:])
    scales = {p["name"]: p for p in msgs[-1]["parameters"]}
    assert scales and all(p["unit"] == "1" and 0.9 < p["mean"] < 1.1 for p in scales.values())


def test_liblsl_is_kept_quiet_unless_the_user_configured_it(monkeypatch, tmp_path):
    import os

    from skelid.io import stream

    monkeypatch.delitem(sys.modules, "pylsl", raising=False)
    monkeypatch.delenv("LSLAPICFG", raising=False)
    monkeypatch.setattr(stream, "_LSL_CONFIGS", ())
    stream._quiet_liblsl()
    path = os.environ["LSLAPICFG"]
    assert "[log]\nlevel = -3" in open(path).read()
    own = tmp_path / "lsl_api.cfg"
    own.write_text("[log]\nlevel = 0\n")
    monkeypatch.setenv("LSLAPICFG", str(own))
    stream._quiet_liblsl()
    assert os.environ["LSLAPICFG"] == str(own)
    monkeypatch.delenv("LSLAPICFG")
    monkeypatch.setattr(stream, "_LSL_CONFIGS", (own,))
    stream._quiet_liblsl()
    assert "LSLAPICFG" not in os.environ


@pytest.mark.parametrize("args,words", [
    (["--udp", "nonsense"], "--udp 'nonsense' is not HOST:PORT"),
    (["--out", "{tmp}"], "is a folder"),
    (["--timeout", "-1"], "timeout must be a positive number"),
    (["--rate", "nan"], "--rate must be a finite number"),
    (["--target-sd", "abc"], "--target-sd 'abc' is not a number or NAME=SD pairs"),
    (["--target-sd", "L2=1,=2"], "is not a number or NAME=SD pairs"),
    (["--target-sd", "L9=1"], "target_sd names 'L9', which 'case_a' does not have"),
    (["--target-sd", "0"], "target_sd of L2 must be above 0"),
])
def test_live_options_are_refused_before_any_wait_for_the_stream(args, words, tmp_path, capsys):
    import time

    t = time.perf_counter()
    argv = ["live", "case-a", "--lsl", _name("never"), "--timeout", "10", *[a.format(tmp=tmp_path) for a in args]]
    assert main(argv) == 2
    assert time.perf_counter() - t < 5.0  # refused up front, not after --timeout
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1


def test_a_live_run_builds_its_compiled_kernels_before_the_session_starts(monkeypatch, capsys):
    """A session keeps the path it starts on: on a cold cache ``skelid live`` builds the kernels first (one line
    says so) rather than running the whole session on the numpy path; on a warm one it says nothing."""
    from skelid.cli import _live_kernels
    from skelid.estimators.fit import _lm_kernel
    from skelid.estimators.online import _live_kernel

    if not _lm_kernel.AVAILABLE:
        pytest.skip("numba is not installed")
    calls = []
    monkeypatch.setattr(_lm_kernel, "MODE", "1")
    monkeypatch.setattr(_lm_kernel, "warm", lambda key, wait=True: calls.append(("pose", key, wait)))
    monkeypatch.setattr(_live_kernel, "warm", lambda wait=True: calls.append(("live", wait)))
    monkeypatch.setattr(_lm_kernel, "_cached", lambda key: False)
    monkeypatch.setattr(_live_kernel, "_cached", lambda: False)
    _live_kernels(builtin_model("case-a"), quiet=False)
    assert calls == [("pose", True, True), ("live", True)]
    assert "building skelid's compiled kernels once" in capsys.readouterr().err
    calls.clear()
    monkeypatch.setattr(_lm_kernel, "_cached", lambda key: True)
    monkeypatch.setattr(_live_kernel, "_cached", lambda: True)
    _live_kernels(builtin_model("case-a"), quiet=False)
    assert calls == [] and capsys.readouterr().err == ""
    monkeypatch.setattr(_live_kernel, "_cached", lambda: False)  # the live step alone
    from skelid.live import build_kernels

    assert build_kernels(builtin_model("case-a")) and calls == [("pose", True, True), ("live", True)]
    monkeypatch.setattr(_lm_kernel, "MODE", "0")
    calls.clear()
    assert not build_kernels(builtin_model("case-a")) and calls == []
