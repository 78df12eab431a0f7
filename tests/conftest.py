import os
from pathlib import Path

# the suite's linear algebra is many small factorisations: one BLAS thread each is faster than
# threads contending for two cores (set before numpy loads, for this process and every subprocess)
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import matplotlib  # noqa: E402
import pytest  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

threadpool_limits(1)  # in case a plugin loaded numpy before this file
matplotlib.use("Agg")
os.environ.setdefault("MPLBACKEND", "Agg")
# every test runs the compiled pose kernel (or the numpy path where it asks for it), never a mix that
# depends on when the kernel's cache was written; the kernels compile in the background from the start
os.environ.setdefault("SKELID_NUMBA", "wait")

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
EXAMPLES = ROOT / "examples"


@pytest.fixture
def shared_data():
    if not SHARED.is_dir():
        pytest.skip(f"shared data folder {SHARED} is absent")
    return SHARED


def pytest_sessionstart(session):
    from skelid.estimators.fit import _lm_kernel
    from skelid.estimators.online import _live_kernel
    from skelid.model import _fk_kernel

    for planar in (True, False):  # compile both drivers on the side while the first tests run
        _lm_kernel.warm(planar, wait=False)
        _fk_kernel.warm(planar, wait=False)
    _lm_kernel.warm("custom", wait=False)  # the pose fit of models with custom joints
    _fk_kernel.warm("band", wait=False)
    _live_kernel.warm(wait=False)  # and the live session's frame step


def pytest_terminal_summary(terminalreporter):
    """The cases the command-line fuzz harness tried, per class of input."""
    import sys

    fuzz = sys.modules.get("tests.test_fuzz_cli")
    if fuzz is not None and fuzz.COUNTS:
        terminalreporter.write_sep("-", "fuzz cases tried per class")
        for line in fuzz.summary_lines():
            terminalreporter.write_line(line)
