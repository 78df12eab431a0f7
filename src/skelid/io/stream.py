"""Live streams: marker frames in from Lab Streaming Layer (LSL), estimates out over LSL, UDP or a file.

A marker stream is an LSL stream of ``3 M`` numeric channels, ``x, y, z`` of
each of ``M`` markers in turn. Its marker names come from the stream's XML
metadata (``desc/channels/channel/label``: ``RASI_X``, ``RASI_Y``, ``RASI_Z``
or ``RASI x`` ...; three channels of one name also do) or are given; its
length unit from ``desc/channels/channel/unit`` (``mm``, ``millimeters``,
``m`` ...) or is given. Nothing is guessed: a stream whose channels or units
cannot be read is refused with one :class:`~skelid.errors.StreamError` line.

:class:`LslFrames` is an iterable of ``(M, 3)`` frames for
:meth:`skelid.live.Session.feed` or :func:`skelid.live.run`;
:func:`publish` plays a recording (:class:`~skelid.data.MarkerData`) as such
a stream at its own rate, so that everything can be tried without a
motion-capture system. :class:`LslMessages`, :class:`UdpMessages` and
:class:`JsonLines` send each ``skelid.live/1`` message (docs/live-protocol.md)
on: an LSL string stream, a UDP datagram, a line of a file.

pylsl is optional (``pip install skelid[live]``); it is imported only when a
stream is opened.
"""

from __future__ import annotations

import json
import math
import os
import re
import socket
import sys
import time
from pathlib import Path

import numpy as np

from skelid.errors import SkelidError, StreamError

#: LSL stream type of the marker streams :func:`publish` makes
MARKER_TYPE = "MoCap"
#: LSL stream type of the estimate streams :class:`LslMessages` makes
MESSAGE_TYPE = "skelid.live"
#: the largest UDP payload over IPv4
UDP_MAX = 65507

_UNITS = {"mm": "mm", "millimeter": "mm", "millimeters": "mm", "millimetre": "mm", "millimetres": "mm",
          "cm": "cm", "centimeter": "cm", "centimeters": "cm", "centimetre": "cm", "centimetres": "cm",
          "m": "m", "meter": "m", "meters": "m", "metre": "m", "metres": "m"}
_AXIS = re.compile(r"^(.*?)[\s_.:/-]*([xyzXYZ])$")


#: where liblsl looks for its settings besides ``$LSLAPICFG``
_LSL_CONFIGS = (Path("lsl_api.cfg"), Path.home() / "lsl_api" / "lsl_api.cfg", Path("/etc/lsl_api/lsl_api.cfg"))


def _quiet_liblsl() -> None:
    """Point liblsl at settings that keep its own log to fatal errors, unless the user has settings of their own.

    liblsl writes INFO lines and a line per reconnection to stderr; skelid reports every stream problem in
    one line of its own. Only before liblsl is loaded, and never over a configuration the user set up.
    """
    if "pylsl" in sys.modules or os.environ.get("LSLAPICFG") or any(p.is_file() for p in _LSL_CONFIGS):
        return
    os.environ["LSLAPICFG"] = str(Path(__file__).with_name("lsl_quiet.cfg"))


def pylsl():
    """The pylsl module, or one line saying how to install it."""
    _quiet_liblsl()
    try:
        import pylsl as lsl
    except (ImportError, RuntimeError, OSError) as exc:  # RuntimeError/OSError: pylsl without its liblsl
        raise SkelidError(f"Lab Streaming Layer support is not installed ({exc.__class__.__name__}: {exc})",
                          "pip install skelid[live]") from None
    return lsl


def _lsl_error(lsl, name: str) -> type[BaseException]:
    """pylsl's exception ``name`` (``LostError``, ``TimeoutError``): in ``pylsl`` before 1.17, ``pylsl.util`` since."""
    found = getattr(lsl, name, None)
    if found is None:
        import pylsl.util

        found = getattr(pylsl.util, name)
    return found


def marker_names(labels, name: str) -> list[str]:
    """Marker names from the channel labels of a stream (``x, y, z`` of each marker in turn).

    Raises
    ------
    StreamError
        A channel count that is not three per marker, or three channels that are not one marker's
        ``x, y, z``.
    """
    labels = [str(lb).strip() for lb in labels]
    if len(labels) % 3:
        raise StreamError(f"stream {name!r} has {len(labels)} channels; a marker stream has three per marker "
                          "(x, y, z)", "send x, y, z of every marker, or give the marker names with --labels")
    out = []
    for k in range(0, len(labels), 3):
        three = labels[k:k + 3]
        parts = [_AXIS.match(lb) for lb in three]
        if all(parts) and [p.group(2).lower() for p in parts] == ["x", "y", "z"] \
                and len({p.group(1) for p in parts}) == 1 and parts[0].group(1):
            out.append(parts[0].group(1))
        elif len(set(three)) == 1 and three[0]:
            out.append(three[0])
        else:
            raise StreamError(f"stream {name!r}: channels {k + 1}-{k + 3} ({', '.join(map(repr, three))}) are not "
                              "one marker's x, y, z", "label the channels NAME_X, NAME_Y, NAME_Z, or give the "
                              "marker names with --labels")
    return out


def stream_unit(units, name: str) -> str | None:
    """The stream's length unit from its channels' ``unit`` fields (None if none states one).

    Raises
    ------
    StreamError
        A unit skelid does not know, or channels in different units.
    """
    found = {u.strip() for u in units if u and u.strip()}
    if not found:
        return None
    known = {_UNITS.get(u.lower()) for u in found}
    if None in known:
        bad = sorted(u for u in found if u.lower() not in _UNITS)
        raise StreamError(f"stream {name!r} states the unit {bad[0]!r}, not a length unit skelid knows",
                          "send mm, cm or m, or state the unit with --units")
    if len(known) > 1:
        raise StreamError(f"stream {name!r} mixes units ({', '.join(sorted(found))})",
                          "send every channel in one unit, or state it with --units")
    return known.pop()


def _channels(info) -> tuple[list[str], list[str]]:
    """The labels and units in an LSL stream info's ``desc/channels`` (empty strings where absent)."""
    labels, units = [], []
    ch = info.desc().child("channels").child("channel")
    while not ch.empty():
        labels.append(ch.child_value("label"))
        units.append(ch.child_value("unit"))
        ch = ch.next_sibling("channel")
    return labels, units


class LslFrames:
    """The frames of an LSL marker stream, as ``(M, 3)`` arrays: an iterable for :meth:`Session.feed`.

    Parameters
    ----------
    name : str
        The stream's name.
    labels : sequence of str, optional
        The markers' names, in channel order (default: from the stream's metadata).
    units : str, optional
        The stream's length unit (default: from its metadata).
    timeout : float
        Seconds to wait for the stream to appear, and for each frame once it sends.

    Attributes
    ----------
    labels : list of str
    units : str
    rate : float or None
        The stream's nominal rate (None for an irregular stream).
    last_stamp : float or None
        LSL time stamp of the frame yielded last (the sender's clock, corrected to this machine's).
    n_frames : int
        Frames yielded so far.

    Raises
    ------
    StreamError
        No stream of that name within ``timeout``; channels that are not three per marker or do not match
        ``labels``; no units stated anywhere. Iterating raises it when the stream stops sending for
        ``timeout`` seconds or is lost.
    """

    def __init__(self, name: str, labels=None, units: str | None = None, timeout: float = 5.0):
        lsl = pylsl()
        if not (isinstance(timeout, int | float) and math.isfinite(timeout) and timeout > 0):
            raise StreamError(f"timeout must be a positive number of seconds, got {timeout!r}", "e.g. 5")
        self.name, self.timeout = name, float(timeout)
        found = lsl.resolve_byprop("name", name, minimum=1, timeout=self.timeout)
        if not found:
            raise StreamError(f"no LSL stream named {name!r} found within {self.timeout:g} s",
                              "start the sender first (skelid replay TRIAL --lsl NAME plays a file), check the "
                              "name, or wait longer with --timeout")
        self._lsl = lsl
        # recover: a sender that goes away still has its frames drained from the buffer; then the timeout ends it
        self._inlet = lsl.StreamInlet(found[0], max_buflen=360, recover=True)
        # subscribed before the checks, so that a sender waiting for a receiver loses no frame to them
        self._inlet.open_stream(timeout=self.timeout)
        try:
            info = self._inlet.info(timeout=self.timeout)
        except _lsl_error(lsl, "TimeoutError"):
            raise StreamError(f"stream {name!r} did not send its description within {self.timeout:g} s",
                              "check the sender, or wait longer with --timeout") from None
        n = info.channel_count()
        ch_labels, ch_units = _channels(info)
        if labels is not None:
            labels = [str(lb) for lb in labels]
            if 3 * len(labels) != n:
                raise StreamError(f"stream {name!r} has {n} channels; {len(labels)} labels need {3 * len(labels)} "
                                  "(x, y, z per marker)", "give one label per marker the stream sends")
            self.labels = labels
        elif len(ch_labels) == n and all(ch_labels):
            self.labels = marker_names(ch_labels, name)
        elif n % 3:
            self.labels = marker_names([""] * n, name)  # raises: not three channels per marker
        else:
            raise StreamError(f"stream {name!r} names no channels in its metadata",
                              "give the marker names with --labels, in channel order")
        stated = stream_unit(ch_units, name)
        if units is None and stated is None:
            raise StreamError(f"stream {name!r} states no unit", "state it with --units mm (or cm, m)")
        self.units = units if units is not None else stated
        srate = info.nominal_srate()
        self.rate = float(srate) if srate > 0 else None
        self.last_stamp: float | None = None
        self.n_frames = 0

    def __iter__(self):
        lsl, M = self._lsl, len(self.labels)
        lost = _lsl_error(lsl, "LostError")
        while True:
            try:
                sample, stamp = self._inlet.pull_sample(timeout=self.timeout)
            except lost:
                raise StreamError(f"stream {self.name!r} was lost after {self.n_frames} frames",
                                  "check the sender; the estimate so far is kept") from None
            if sample is None:
                raise StreamError(f"stream {self.name!r} sent nothing for {self.timeout:g} s after "
                                  f"{self.n_frames} frames", "check the sender, or wait longer with --timeout")
            self.last_stamp = stamp
            self.n_frames += 1
            yield np.asarray(sample, dtype=float).reshape(M, 3)

    def close(self) -> None:
        self._inlet.close_stream()


def publish(data, name: str, rate: float | None = None, loop: bool = False, max_frames: int | None = None,
            wait: float = 0.0, stop=None, source_id: str | None = None, linger: float = 0.5) -> int:
    """Play ``data`` (:class:`~skelid.data.MarkerData`) as an LSL marker stream at its own rate.

    Each frame goes out when its time comes (``frame / rate`` after the first), x, y, z of each marker in
    the file's order and units (a planar recording gets z = 0), NaN where a marker is missing. The
    channels are labelled ``NAME_X``, ``NAME_Y``, ``NAME_Z`` with the unit, as :class:`LslFrames` reads.

    Parameters
    ----------
    rate : float, optional
        Frames per second (default the recording's).
    loop : bool
        Start again after the last frame (until ``max_frames`` or ``stop``).
    max_frames : int, optional
        Frames to send at most.
    wait : float
        Seconds to wait for a receiver before the first frame (0: start at once). A receiver that
        connects later misses the frames sent before.
    stop : threading.Event, optional
        Set to stop.
    linger : float
        Seconds the stream stays up after the last frame while a receiver is connected (an outlet that
        goes at once can take its last frame with it).

    Returns
    -------
    int
        Frames sent.
    """
    lsl = pylsl()
    rate = float(data.rate if rate is None else rate)
    if not (math.isfinite(rate) and rate > 0):
        raise StreamError(f"rate must be a positive number of frames per second, got {rate!r}", "e.g. --rate 100")
    F, M, D = data.positions.shape
    info = lsl.StreamInfo(name, MARKER_TYPE, 3 * M, rate, lsl.cf_float32, source_id or f"skelid-replay-{name}")
    channels = info.desc().append_child("channels")
    for marker in data.names:
        for axis in "XYZ":
            ch = channels.append_child("channel")
            ch.append_child_value("label", f"{marker}_{axis}")
            ch.append_child_value("type", f"Position{axis}")
            ch.append_child_value("unit", data.units)
    outlet = lsl.StreamOutlet(info)
    frames = data.positions if D == 3 else np.concatenate([data.positions, np.zeros((F, M, 3 - D))], axis=-1)
    frames = np.where(np.isnan(data.positions).any(axis=-1, keepdims=True), np.nan, frames).reshape(F, 3 * M)
    if wait > 0:
        outlet.wait_for_consumers(wait)
    sent, start = 0, time.perf_counter()
    try:
        while True:
            for row in frames:
                if (max_frames is not None and sent >= max_frames) or (stop is not None and stop.is_set()):
                    return sent
                delay = start + sent / rate - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
                outlet.push_sample(row.tolist())
                sent += 1
            if not loop:
                return sent
    finally:
        if sent and outlet.have_consumers():
            time.sleep(linger)  # the outlet's last samples are still on their way when it goes
        del outlet


class LslMessages:
    """Each message as one sample (a JSON string) of an LSL stream of type ``skelid.live``."""

    def __init__(self, name: str, source_id: str | None = None):
        lsl = pylsl()
        info = lsl.StreamInfo(name, MESSAGE_TYPE, 1, lsl.IRREGULAR_RATE, lsl.cf_string,
                              source_id or f"skelid-live-{name}")
        info.desc().append_child_value("schema", "skelid.live/1")
        self.outlet = lsl.StreamOutlet(info)

    def send(self, message: dict) -> None:
        self.outlet.push_sample([dumps(message)])

    def close(self) -> None:
        del self.outlet


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` as ``(host, port)``.

    Raises
    ------
    SkelidError
        Not of that form, or a port outside 1-65535.
    """
    host, sep, port = str(text).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise SkelidError(f"--udp {text!r} is not HOST:PORT", "give e.g. --udp 127.0.0.1:9870")
    return host.strip("[]"), int(port)


class UdpMessages:
    """Each message as one UDP datagram of UTF-8 JSON to ``address`` (``HOST:PORT``)."""

    def __init__(self, address: str):
        host, port = parse_address(address)
        try:
            self.target = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
        except OSError as exc:
            raise SkelidError(f"--udp {address!r}: cannot resolve {host!r} ({exc.strerror or exc})",
                              "give an address this machine can reach, e.g. 127.0.0.1:9870") from None
        self.sock = socket.socket(self.target[0], socket.SOCK_DGRAM)

    def send(self, message: dict) -> None:
        data = dumps(message).encode("utf-8")
        if len(data) > UDP_MAX:
            raise StreamError(f"a message of {len(data)} bytes is too long for one UDP datagram ({UDP_MAX})",
                              "use the LSL output (--lsl-out) for a model this large")
        try:
            self.sock.sendto(data, self.target[4])
        except OSError:
            pass  # a datagram nobody receives (port closed, network down) is lost, as UDP's are

    def close(self) -> None:
        self.sock.close()


class JsonLines:
    """Each message as one line of JSON in an open text file."""

    def __init__(self, fh):
        self.fh = fh

    def send(self, message: dict) -> None:
        self.fh.write(dumps(message) + "\n")

    def close(self) -> None:
        pass


def dumps(message: dict) -> str:
    """A message as compact JSON (no NaN: :func:`skelid.live.message` has made those null)."""
    return json.dumps(message, separators=(",", ":"), allow_nan=False)
