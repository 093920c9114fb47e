"""Training views and their loss (views.py): downscaling, the photometric and per-view loss."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gsfix_online.mapping.splat.exposure import ExposureConfig
from gsfix_online.mapping.splat.render_output import RenderOutput
from gsfix_online.mapping.splat.views import (
    TrainView,
    check_size,
    downscale_view,
    frame_view,
    photometric_loss,
    resize,
    upsample,
    view_loss,
)
from tests.mapping.splat.test_mapper import H, W, Z, plane_frame


def _view(h: int = 12, w: int = 16, seed: int = 0) -> TrainView:
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[20.0, 0, (w - 1) / 2], [0, 20.0, (h - 1) / 2], [0, 0, 1]])
    return TrainView(torch.rand(h, w, 3, generator=g), torch.full((h, w), 2.0), K, torch.eye(4))


def test_frame_view_is_the_frame_in_unit_colour_and_metres() -> None:
    f = plane_frame()
    v = frame_view(f, torch.device("cpu"))
    assert v.color.shape == (H, W, 3) and v.depth is not None and v.depth.shape == (H, W)
    torch.testing.assert_close(v.color, torch.from_numpy(f.color).float() / 255)
    assert float(v.depth.mean()) == pytest.approx(Z)
    assert frame_view(f, torch.device("cpu"), use_depth=False).depth is None


@pytest.mark.parametrize("s", [1, 2, 3])
def test_downscaled_view_maps_pixel_centres(s: int) -> None:
    """A point that projects to pixel (u, v) at full resolution projects to ((u + 0.5) / s -
    0.5, ...) at 1/s: the area average's pixel centres."""
    v = _view(12, 18)
    d = downscale_view(v, s)
    assert d.color.shape == (12 // s, 18 // s, 3)
    X = torch.tensor([0.3, -0.2, 2.0])
    full = (v.K @ X)[:2] / X[2]
    low = (d.K @ X)[:2] / X[2]
    torch.testing.assert_close(low, (full + 0.5) / s - 0.5)
    if s == 2:  # area average
        torch.testing.assert_close(d.color[0, 0], v.color[:2, :2].reshape(-1, 3).mean(0))


def test_photometric_loss_is_l1_and_masked() -> None:
    a = torch.rand(20, 20, 3)
    assert float(photometric_loss(a, a, 0.2)) == pytest.approx(0.0, abs=1e-6)
    assert float(photometric_loss(a + 0.25, a, 0.0, l1_weight=2.0)) == pytest.approx(0.5)
    mask = torch.zeros(20, 20, dtype=torch.bool)
    mask[:10] = True
    b = a.clone()
    b[10:] += 1.0  # outside the mask
    assert float(photometric_loss(b, a, 0.0, mask=mask)) == pytest.approx(0.0, abs=1e-7)


def test_view_loss_adds_depth_l1_and_identity_exposure_changes_nothing() -> None:
    v = _view()
    h, w = v.color.shape[:2]
    out = RenderOutput(v.color.clone(), torch.full((h, w), 2.3), torch.ones(h, w))
    e = ExposureConfig(enabled=True, prior=0.0)
    loss = view_loss(out, v, 0.2, 1.0, depth_weight=0.5, exposure=e, pose_prior=0.0)
    assert float(loss) == pytest.approx(0.5 * 0.3, abs=1e-5)  # colour exact, depth 0.3 m off
    v.affine = torch.zeros(2, 3)  # the identity
    assert float(view_loss(out, v, 0.2, 1.0, 0.5, e, 0.0)) == pytest.approx(float(loss))
    v.affine = torch.tensor([[np.log(2.0)] * 3, [0.0] * 3])  # gain 2
    assert float(view_loss(out, v, 0.0, 1.0, 0.0, e, 0.0)) == pytest.approx(
        float(v.color.mean()), rel=1e-5
    )


def test_check_size_names_the_smallest_side() -> None:
    check_size(12, 12, 2)
    with pytest.raises(ValueError, match="at least 12x12 pixels"):
        check_size(11, 40, 2)


def test_resize_and_upsample_shapes_and_values() -> None:
    x = torch.arange(6.0).reshape(2, 3, 1)
    up = upsample(x, 2, 5, 7)
    assert up.shape == (5, 7, 1) and up[1, 1, 0] == 0.0 and up[4, 6, 0] == 5.0
    r = resize(torch.ones(4, 4, 3), 8, 6)
    assert r.shape == (8, 6, 3) and r.dtype == np.float32 and np.allclose(r, 1.0)
