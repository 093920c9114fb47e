"""Fixtures of the runtime tests; the data is generated in samples.py."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from gsfix_online.runtime.wire import Message
from tests.runtime.samples import sample_messages


@pytest.fixture
def samples() -> dict[str, Message]:
    return sample_messages()


@pytest.fixture
def ipc_dir() -> Iterator[Path]:
    d = Path(tempfile.mkdtemp(prefix="gsfix-", dir="/tmp"))  # short: ipc paths max ~107 chars
    yield d
    shutil.rmtree(d, ignore_errors=True)
