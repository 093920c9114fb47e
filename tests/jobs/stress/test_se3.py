"""Stress properties of gsfix_online/core/se3.py and trajectory.py (SE(3), quaternions, pose interpolation)."""

from __future__ import annotations

import numpy as np
import pytest

from gsfix_online.core.se3 import look_at
from gsfix_online.jobs.stress import properties
from gsfix_online.jobs.stress.runner import assert_property


@pytest.mark.parametrize("prop", properties("geometry"), ids=lambda p: p.name)
def test_property_holds(prop):
    assert_property(prop)


def test_look_at_with_the_target_on_the_eye_raises_instead_of_nan():
    # found by geometry.look_at: the zero viewing direction was divided by its length
    with pytest.raises(ValueError, match="apart from the eye"):
        look_at([1e4, 2.0, 3.0], [1e4, 2.0, 3.0])
    T = look_at([1e4, 2.0, 3.0], [1e4, 2.0, 3.0 + 1e-9])  # 1 nm apart still aims
    np.testing.assert_allclose(T[:3, 2], [0.0, 0.0, 1.0], atol=1e-9)
