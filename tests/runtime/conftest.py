"""Fixtures of the runtime tests; the data is generated in samples.py."""

from __future__ import annotations

import pytest

from gsfix_online.runtime.wire import Message
from tests.runtime.samples import sample_messages


@pytest.fixture
def samples() -> dict[str, Message]:
    return sample_messages()
