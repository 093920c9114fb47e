"""Stress properties of GSFixer inference and one training step (gsfix_online/fixer)."""

from __future__ import annotations

import pytest

from gsfix_online.jobs.stress import properties
from gsfix_online.jobs.stress.runner import assert_property


@pytest.mark.parametrize("prop", properties("fixer"), ids=lambda p: p.name)
def test_property_holds(prop):
    assert_property(prop)
