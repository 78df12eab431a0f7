"""The one switch between the compiled kernels and the numpy path (skelid._numba)."""

import os
import subprocess
import sys

import pytest

from skelid import _numba
from skelid.estimators.fit import _lm_kernel
from skelid.estimators.online import _live_kernel
from skelid.model import _fk_kernel


def test_every_kernel_reads_the_same_switch():
    assert _lm_kernel.AVAILABLE is _fk_kernel.AVAILABLE is _live_kernel.AVAILABLE is _numba.AVAILABLE
    assert _lm_kernel.MODE == _fk_kernel.MODE == _numba.MODE
    assert _lm_kernel.compile_in_background is _numba.compile_in_background


def test_skelid_numba_0_turns_every_kernel_off_without_importing_numba():
    code = ("import sys\nfrom skelid.estimators.fit import _lm_kernel\n"
            "from skelid.estimators.online import _live_kernel\nfrom skelid.model import _fk_kernel\n"
            "from skelid.estimators.online import _live_kernel\nfrom skelid.model import _fk_kernel\n"
            "print(_lm_kernel.AVAILABLE, _fk_kernel.AVAILABLE, _live_kernel.AVAILABLE, _lm_kernel.ready(True), "
            "_fk_kernel.ready('band'), 'numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], env=dict(os.environ, SKELID_NUMBA="0"), capture_output=True,
                         text=True, timeout=120, check=True).stdout.split()
    assert out == ["False"] * 6


def test_a_cold_kernel_is_warmed_once_and_found_when_cached(monkeypatch):
    if not _numba.AVAILABLE:
        pytest.skip("the compiled kernels are turned off (SKELID_NUMBA=0)")
    cached, started = {"k": False}, []
    gate = _numba.Gate(lambda k: False, lambda k: cached[k], lambda k, wait: started.append((k, wait)), lambda: "1")
    assert not gate.ready("k")
    assert not gate.ready("k")  # looked at again only after a while, and not warmed twice
    assert started == [("k", False)]
    cached["k"] = True
    gate.last_check.clear()
    assert gate.ready("k")
    cached["k"] = False
    assert gate.ready("k")  # once found, ready without looking again
    wait = _numba.Gate(lambda k: False, lambda k: False, lambda k, w: started.append((k, w)), lambda: "wait")
    assert wait.ready("j") and started[-1] == ("j", True)
