"""Shared fixtures for the reader tests: the real data folder and fuzz counts."""

from __future__ import annotations

from collections import Counter, defaultdict
from pathlib import Path

import pytest

#: ``../shared/data`` beside the repository root (tests/io/conftest.py -> repo root is parents[2]).
DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"

#: reader name -> Counter(tried, valid, refused), filled by the fuzz tests.
FUZZ_COUNTS: dict[str, Counter] = defaultdict(Counter)


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not (DATA / "README.md").is_file():
        pytest.skip(f"real data folder {DATA} is absent (it lives beside the repository, in ../shared/data)")
    return DATA


@pytest.fixture(scope="session")
def fuzz_counts() -> dict[str, Counter]:
    return FUZZ_COUNTS


def pytest_terminal_summary(terminalreporter):
    for reader, c in sorted(FUZZ_COUNTS.items()):
        terminalreporter.write_line(
            f"fuzz: {reader} tried {c['tried']} cases, {c['valid']} valid, {c['refused']} refused")
