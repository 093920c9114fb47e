"""Fixtures of the fault tests: the ``slow`` variants run only when ``-m`` selects them.

``make test`` runs ``-m "not gpu and not device"``, which would include ``slow`` tests; the
full-length variants (a minute of RSS sampling, say) are meant for ``pytest -m slow tests/faults``.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    expr = config.getoption("-m") or ""
    if "slow" in expr and "not slow" not in expr:
        return
    skip = pytest.mark.skip(reason="full-length variant: run with -m slow")
    for item in items:
        if "faults" in item.nodeid and item.get_closest_marker("slow"):
            item.add_marker(skip)


@pytest.fixture
def short_dir() -> Iterator[Path]:
    """A folder with a short path (ipc socket paths are limited to ~107 characters)."""
    d = Path(tempfile.mkdtemp(prefix="gsfix-f-", dir="/tmp"))
    yield d
    shutil.rmtree(d, ignore_errors=True)
