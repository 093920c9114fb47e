"""The stress suite's hypothesis profiles and one intra-op thread.

Profiles (registered by :func:`gsfix_online.jobs.stress.runner.register_profiles`): ``ci`` runs each
property's ``ci_examples`` derandomised examples with no deadline (make test); ``long`` is what
``gsfix-online stress --minutes N`` uses. They are applied per property, not loaded globally,
so the other hypothesis tests keep their own settings.
"""

from __future__ import annotations

import pytest
import torch

from gsfix_online.jobs.stress.runner import register_profiles

register_profiles()


@pytest.fixture(autouse=True)
def _one_thread():
    """Tiny tensors gain nothing from threads; on a shared 2-core machine a second intra-op
    thread makes each step many times slower (tests/fixer/conftest.py has the figures)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
