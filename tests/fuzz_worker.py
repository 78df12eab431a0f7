"""A long-lived process that runs ``skelid`` command lines for the fuzz tests.

Started once under an address-space limit (``RLIMIT_AS``), it reads one JSON
request per line on stdin, ``{"argv": [...], "cwd": "..."}``, runs
:func:`skelid.cli.main` there with stdout and stderr captured, and answers one
JSON line ``{"code", "stdout", "stderr", "seconds"}``. Starting Python and
importing numpy once instead of per case keeps hundreds of cases within a
minute.
"""

import contextlib
import io
import json
import os
import resource
import sys
import time

if __name__ == "__main__":
    limit_mb = int(sys.argv[1])
    if limit_mb > 0:
        resource.setrlimit(resource.RLIMIT_AS, (limit_mb * 2**20, limit_mb * 2**20))
    from skelid.cli import main  # noqa: E402

    # the answers go to a copy of fd 1; anything a library writes to fd 1 itself goes nowhere
    proto = os.fdopen(os.dup(1), "w")
    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)
    sys.stdout = io.TextIOWrapper(os.fdopen(1, "wb"), write_through=True)
    for line in sys.stdin:
        req = json.loads(line)
        out, err = io.StringIO(), io.StringIO()
        t0 = time.perf_counter()
        os.chdir(req["cwd"])
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(req["argv"])
            except BaseException as exc:  # noqa: BLE001 - anything escaping main is reported, not hidden
                code = f"escaped {type(exc).__name__}: {exc}"
        proto.write(json.dumps({"code": code, "stdout": out.getvalue()[-20000:], "stderr": err.getvalue()[-20000:],
                                "seconds": time.perf_counter() - t0}) + "\n")
        proto.flush()
