"""How a command stops early (Ctrl-C, ``SIGTERM``, its time limit) without leaving anything half-written.

While :func:`handling` is active (the command line holds it around every command), a stop request
raises, in the main thread, the exception of its kind:

========================  ============================================  ===========
request                   exception                                     exit status
========================  ============================================  ===========
``SIGINT`` (Ctrl-C)       :class:`KeyboardInterrupt`                    130
``SIGTERM``               :class:`SystemExit` ``(143)``                 143
the time limit            :class:`DeadlineExceeded` (its one-line        2
                          :class:`~skelid.errors.SkelidError` inside)
========================  ============================================  ===========

Every atomic writer (:mod:`skelid.io.atomic`) removes what it had begun as the exception passes, so
an output folder is either absent or complete. Three rules keep that true wherever the request lands:

* Python cannot raise an exception everywhere: one raised inside a ``__del__``, a weak-reference
  callback or the garbage collector is printed (``Exception ignored in ...``, with a traceback) and
  dropped, and the program goes on. A stop request is therefore also *recorded*; a dropped one is
  not printed, and is raised again a moment later (:func:`_unraisable`).
* An output is never moved into place once a stop was requested (:func:`check`, called by the
  writers just before their rename), except what a stopping command saves on purpose
  (:func:`cleanup`: the rows a batch has finished). That also covers a stop whose exception
  another turned into its own on the way (numba's compiled code reports an exception raised while
  it called back into Python as a ``SystemError``).
* The few steps that must not be cut in two (the renames that move a finished folder in, starting
  and closing a cluster) run under :func:`deferred`: a request during them takes effect when they end.

A second signal while the first one's exception is on its way out is ignored, so that the cleanup
(removing a temporary folder, writing the rows a batch has finished) is not cut short.

Examples
--------
>>> from skelid import _stop
>>> with _stop.handling():
...     _stop.pending() is None
True
"""

from __future__ import annotations

import contextlib
import functools
import signal
import sys
import threading
import time


class DeadlineExceeded(BaseException):  # noqa: N818 - named for what happened, like KeyboardInterrupt
    """The command ran past its time limit; ``error`` is the one-line :class:`~skelid.errors.SkelidError`.

    A ``BaseException``, like :class:`KeyboardInterrupt`, so that no ``except Exception`` on its way
    out mistakes it for a failure of the step it interrupts.
    """

    def __init__(self, error):
        super().__init__(str(error))
        self.error = error


#: seconds after a dropped stop request (see the module docstring) before it is raised again
RETRY_S = 0.02
EXIT_CODES = {signal.SIGINT: 130, signal.SIGTERM: 143}


class _State:
    """The process's stop request (one at a time: signal handlers are process-wide)."""

    def __init__(self):
        self.active = False  # handling() is installed
        self.request = None  # None, a signal number, or the time limit's error
        self.delivered = False  # its exception has been raised and not dropped
        self.deferring = 0  # depth of deferred() blocks
        self.cleanup = 0  # depth of cleanup() blocks
        self.deadline = None  # time.monotonic() at which the time limit ends
        self.deadline_error = None
        self.alarm = False  # SIGALRM is ours


_STATE = _State()


def pending():
    """The stop requested so far: None, a signal number, or the time limit's error."""
    return _STATE.request


def exception_for(request) -> BaseException:
    """The exception a stop request raises (see the table in the module docstring)."""
    if request == signal.SIGINT:
        return KeyboardInterrupt()
    if request == signal.SIGTERM:
        return SystemExit(EXIT_CODES[signal.SIGTERM])
    return DeadlineExceeded(request)


def _deliver():
    """Raise the recorded request now, unless it is deferred or already on its way out."""
    st = _STATE
    if st.request is None or st.delivered or st.deferring:
        return
    st.delivered = True
    raise exception_for(st.request)


def _request(request):
    st = _STATE
    if st.request is None:
        st.request = request
    _deliver()


def _on_signal(signum, frame):
    _request(signum)


def _on_alarm(signum, frame):
    st = _STATE
    if st.request is not None:  # a dropped request, raised again
        _deliver()
        return
    if st.deadline is None:
        return
    left = st.deadline - time.monotonic()
    if left > 0:  # woken early (a dropped request that has since gone): sleep on
        signal.setitimer(signal.ITIMER_REAL, left)
        return
    _request(st.deadline_error)


def _is_stop(exc) -> bool:
    return isinstance(exc, KeyboardInterrupt | DeadlineExceeded) or \
        isinstance(exc, SystemExit) and exc.code in EXIT_CODES.values()


def stop_in(exc: BaseException | None) -> BaseException | None:
    """The stop (Ctrl-C, ``SIGTERM``, the time limit) that ``exc`` is, or was raised from or during; None if
    none. Compiled code reports a stop raised while it called back into Python as a ``SystemError`` whose
    cause is the stop."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if _is_stop(exc):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def interruptible(func):
    """``func`` as a Python caller expects it to stop: a Ctrl-C that compiled code turned into a
    ``SystemError`` on its way out reaches the caller as the :class:`KeyboardInterrupt` it was (likewise
    the other stops of the module docstring). Any other ``SystemError`` passes unchanged."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except SystemError as exc:
            stop = stop_in(exc)
            if stop is None:
                raise
            raise stop from None
    return wrapper


def _unraisable(previous):
    def hook(info):
        st = _STATE
        if st.request is not None and _is_stop(info.exc_value):
            st.delivered = False  # dropped where Python cannot raise: raise it again in a moment
            if st.alarm:
                signal.setitimer(signal.ITIMER_REAL, RETRY_S)
            return
        previous(info)
    return hook


@contextlib.contextmanager
def handling(process_ends: bool = False):
    """Turn ``SIGINT``, ``SIGTERM`` and the time limit into the exceptions of the module docstring.

    Only in the main thread, and only for signals still at their usual disposition (an ignored
    ``SIGINT``, as a shell gives a background job, stays ignored; a handler someone else installed
    stays in place). Everything is restored on exit, except with ``process_ends`` (the process ends
    with the block): the two signals are then ignored while the interpreter shuts down. The command's
    outputs are complete by then, and its exit status says how it went; Python restores the default
    disposition early in its shutdown, so that a signal during the rest of it (freeing the modules,
    about half a second after a fit) would otherwise end the process as killed, without a line.
    """
    st = _STATE
    if st.active or threading.current_thread() is not threading.main_thread():
        yield
        return
    usual = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: signal.SIG_DFL}
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGALRM)}
    hook = sys.unraisablehook
    st.__init__()
    st.active = True
    try:
        for s, usual_handler in usual.items():
            if saved[s] is usual_handler:
                signal.signal(s, _on_signal)
        if saved[signal.SIGALRM] is signal.SIG_DFL:
            signal.signal(signal.SIGALRM, _on_alarm)
            st.alarm = True
        sys.unraisablehook = _unraisable(hook)
        yield
    finally:
        if st.alarm:
            signal.setitimer(signal.ITIMER_REAL, 0)
        for s, h in saved.items():
            ours = signal.getsignal(s) is _on_signal
            signal.signal(s, signal.SIG_IGN if ours and process_ends and s != signal.SIGALRM else h)
        sys.unraisablehook = hook
        st.__init__()


@contextlib.contextmanager
def deadline(seconds: float, error):
    """Stop the block with :class:`DeadlineExceeded` ``(error)`` once it has run ``seconds``.

    Inert outside :func:`handling` (or where ``SIGALRM`` belongs to someone else).
    """
    st = _STATE
    if not st.alarm or not seconds > 0:
        yield
        return
    st.deadline, st.deadline_error = time.monotonic() + seconds, error
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        st.deadline = st.deadline_error = None


@contextlib.contextmanager
def deferred():
    """A stop requested during the block takes effect when it ends (the block is never cut in two)."""
    st = _STATE
    st.deferring += 1
    try:
        yield
    finally:
        st.deferring -= 1
    _deliver()


def check() -> None:
    """Raise the stop requested so far, unless inside :func:`cleanup`.

    Writers call it just before they move an output into place, which they reach only when the block
    that wrote it ended without an exception: a request is pending there only if its exception was
    dropped or turned into another on its way (see the module docstring), and no output appears.
    """
    st = _STATE
    if st.request is not None and not st.cleanup:
        st.delivered = True
        raise exception_for(st.request)


@contextlib.contextmanager
def cleanup():
    """Outputs written in the block are moved into place even after a stop request (what a stopped
    batch has finished is kept); a request during it waits for its end, as in :func:`deferred`."""
    st = _STATE
    st.cleanup += 1
    try:
        with deferred():
            yield
    finally:
        st.cleanup -= 1
