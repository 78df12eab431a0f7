"""Latency of a live session on a real stream: marker frame in over LSL, estimate out over UDP, on this machine.

A simulated trial is published as an LSL marker stream by ``skelid replay`` in a
child process (its own interpreter, so that the sender's timing does not share
this process's lock); this process reads it with
:class:`skelid.io.stream.LslFrames`, runs :func:`skelid.live.run` with a
:class:`~skelid.io.stream.UdpMessages` sender, and a thread receives each
datagram. The latency of a frame is ``local_clock()`` at the datagram's
arrival less the frame's LSL time stamp (the sender's ``local_clock()`` when
it pushed the frame; one clock, one machine): LSL transport, the session's
update, the advice when it is due, the JSON and the UDP hop together. The
first ``--skip`` frames are reported apart: the first pose's random starts and
the early re-linearisations (after 10, 25, 50, 100 and 200 frames; the last
takes a few hundred milliseconds on the tennis arm, and the frames that arrive
meanwhile queue behind it, so the default 250 takes them in too).

    python benchmarks/live_lsl.py [--frames 1000] [--rate 100] [--cases case-a tennis_arm]

Writes ``benchmarks/results/live_lsl.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import provenance, results_dir, write_results  # noqa: E402

CASES = {"case-a": "case-a", "tennis_arm": str(ROOT / "examples" / "tennis_arm.toml")}
SIGMA = {"case-a": 1.0, "tennis_arm": 0.001}  # model units (mm, m)


def _receiver(out: list, done: threading.Event):
    from pylsl import local_clock

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.5)

    def receive():
        while not done.is_set():
            try:
                data = sock.recv(1 << 16)
            except TimeoutError:
                continue
            t = local_clock()
            msg = json.loads(data)
            out.append((msg["frame"], t - msg["stamp"], msg["healthy"]))
        sock.close()

    th = threading.Thread(target=receive, daemon=True)
    th.start()
    return sock.getsockname()[1], th


def one_case(case: str, n_frames: int, rate: float, skip: int, seed: int) -> dict:
    from skelid.io import write_trc
    from skelid.io.stream import LslFrames, UdpMessages
    from skelid.live import Session, build_kernels, run
    from skelid.loading import load_model
    from skelid.simulate import builtin_model, simulate

    model = builtin_model(case) if case == "case-a" else load_model(CASES[case])
    build_kernels(model)  # as `skelid live` does: the session runs the compiled path from its first frame
    trial = simulate(model, n_frames=n_frames, rate=rate, sigma=SIGMA[case], rng=np.random.default_rng(seed))
    name = f"skelid-bench-{uuid.uuid4().hex[:8]}"
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "trial.trc"
        write_trc(path, trial.data)
        sender = subprocess.Popen([sys.executable, "-m", "skelid.cli", "replay", str(path), "--lsl", name,
                                   "--wait", "30", "--quiet"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                  env=os.environ.copy())
        try:
            got: list = []
            done = threading.Event()
            port, th = _receiver(got, done)
            source = LslFrames(name, timeout=30.0)
            session = Session(model, labels=source.labels, units=source.units, rate=source.rate)
            t0 = time.perf_counter()
            run(session, source, [UdpMessages(f"127.0.0.1:{port}")], max_frames=n_frames)
            wall = time.perf_counter() - t0
            time.sleep(0.3)
            done.set()
            th.join(2.0)
        finally:
            sender.terminate()
            sender.wait(10)
    lat = np.array([ms for f, ms, _ in got if f > skip]) * 1e3
    early = np.array([ms for f, ms, _ in got if f <= skip]) * 1e3
    healthy = sum(h for f, _, h in got if f > skip)
    return {"case": case, "method": session.method, "n_params": model.n_params, "n_markers": len(model.markers),
            "rate": rate, "frames_sent": n_frames, "messages_received": len(got), "skip": skip,
            "p50_ms": float(np.percentile(lat, 50)), "p99_ms": float(np.percentile(lat, 99)),
            "max_ms": float(lat.max()), "early_p50_ms": float(np.percentile(early, 50)) if early.size else None,
            "early_max_ms": float(early.max()) if early.size else None,
            "healthy_share": healthy / max(lat.size, 1), "wall_s": wall}


def markdown(res: dict) -> str:
    p = res["provenance"]
    lines = ["# Live session on an LSL stream: marker frame in → estimate out (UDP), this machine", "",
             f"Commit `{p['commit'][:10]}`, {p['date']}, {p['cpu']}, {p['cores']} cores, load {p['load_average']} "
             f"at the start; `{p['command']}`. Latency: UDP arrival less the frame's LSL time stamp (one clock). "
             "The sender is `skelid replay` in its own process at the trial's rate. \"First frames\": the first "
             "pose's random starts and the early re-linearisations (the last after 200 frames) with the frames "
             "queued behind them; the other columns are the frames after them.", "",
             "| case | form | parameters | frames | received | p50 | p99 | max | first frames: p50 / max | healthy |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        early = (f"{r['early_p50_ms']:.2f} / {r['early_max_ms']:.1f} ms (first {r['skip']})"
                 if r["early_p50_ms"] is not None else "-")
        lines.append(f"| {r['case']} | {r['method']} | {r['n_params']} | {r['frames_sent']} at {r['rate']:g} Hz | "
                     f"{r['messages_received']} | {r['p50_ms']:.2f} ms | {r['p99_ms']:.2f} ms | {r['max_ms']:.1f} ms | "
                     f"{early} | {r['healthy_share']:.0%} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--skip", type=int, default=250, help="Frames reported apart at the start.")
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None, help="Results file stem (default results/live_lsl).")
    args = ap.parse_args()
    rows = [one_case(c, args.frames, args.rate, args.skip, args.seed) for c in args.cases]
    write_results(args.out or results_dir() / "live_lsl", {"provenance": provenance(), "rows": rows}, markdown)


if __name__ == "__main__":
    main()
