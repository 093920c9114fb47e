"""SkipPolicy(enabled=False) repairs every view, even one with no surface, and says why."""

from __future__ import annotations

import numpy as np

from gsfix_online.repair.planner import SkipPolicy, score_view


def test_disabled_policy_repairs_every_view():
    h, w = 8, 8
    gs, alpha = np.zeros((h, w, 3), np.uint8), np.zeros((h, w), np.float32)
    s = score_view(gs, alpha, gs, np.zeros((h, w), bool), SkipPolicy(enabled=False))
    assert s.repair and s.reason.endswith("skipping disabled") and s.surface_fraction == 0.0
    s = score_view(gs, alpha + 1, gs, np.ones((h, w), bool), SkipPolicy(enabled=False))
    assert s.repair and s.hole_fraction == 0.0
