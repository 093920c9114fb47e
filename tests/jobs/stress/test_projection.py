"""Stress properties of the EWA projection (gsfix_online/mapping/splat/render_cpu.py), and the
inputs that broke it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gsfix_online.core.types import Intrinsics
from gsfix_online.jobs.stress import properties
from gsfix_online.jobs.stress.runner import assert_property
from gsfix_online.jobs.stress.splat import check_single_gaussian, exact_alpha
from gsfix_online.mapping.splat.render_cpu import project_gaussians

PROPS = [
    p for p in properties("splat") if p.name in ("splat.single_gaussian_exact", "splat.projection")
]


@pytest.mark.parametrize("prop", PROPS, ids=lambda p: p.name)
def test_property_holds(prop):
    assert_property(prop)


@pytest.mark.parametrize("angle", [math.pi / 4, 0.3, 1.0])
@pytest.mark.parametrize("fx", [1e3, 5e3, 5e4])
def test_needle_1km_by_1um_at_1cm_turned_in_the_image_keeps_its_alpha(fx, angle):
    # found by splat.single_gaussian_exact: cxx·cyy - cxy² of this needle's 2D covariance
    # (cxx ~ 1e22 px²) cancelled; the needle vanished (alpha 0), covered the whole image, or
    # got an indefinite conic (alpha 0.99 at opacity 0.9)
    ex = {
        "K": Intrinsics(fx, fx, 8.0, 6.0, 16, 12),
        "z": 0.0101,
        "q": np.array([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)]),
        "scales": np.array([1e3, 1e-6, 1e-6]),
        "opacity": 0.9,
    }
    check_single_gaussian(ex)
    want = exact_alpha(ex["K"], ex["z"], ex["q"], ex["scales"], 0.9)
    assert want.max() == pytest.approx(0.9, abs=2e-3)  # the needle crosses the image...
    if fx <= 5e3:  # ...and leaves most of it clear (at 5e4 px, 1 µm at 1 cm is 5 px wide)
        assert (want == 0).mean() > 0.5


def test_quaternion_of_norm_1e_minus_12_projects_as_the_identity_rotation():
    # found by splat.single_gaussian_exact: q·rsqrt(|q|² + 1e-24) is no rotation for |q|
    # near 1e-12 (norm 0.7 here), so the needle lost its long axis; the map's rule (and the
    # viewer's, the PLY export's) reads |q|² < 1e-12 as the identity
    K = torch.tensor([[100.0, 0, 8], [0, 100.0, 6], [0, 0, 1]], dtype=torch.float64)
    scales = torch.tensor([[1.0, 1e-6, 1e-6]], dtype=torch.float64)
    means = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64)
    tiny = torch.tensor([[0.0, 0.0, 0.7071e-12, 0.7071e-12]], dtype=torch.float64)
    ident = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    got = project_gaussians(means, tiny, scales, torch.eye(4, dtype=torch.float64), K, 16, 12)
    ref = project_gaussians(means, ident, scales, torch.eye(4, dtype=torch.float64), K, 16, 12)
    torch.testing.assert_close(got.cov2d, ref.cov2d)
    assert float(got.cov2d[0, 0]) == pytest.approx((100.0 / 2.0) ** 2 + 0.3)
