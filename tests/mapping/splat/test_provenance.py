"""Which Gaussians a frame saw, and the share of a render that repaired-view Gaussians make."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gsfix_online.mapping.splat.gaussians import ORIGIN_REPAIRED, GaussianMap
from gsfix_online.mapping.splat.provenance import seen_by, synthesised_share
from gsfix_online.mapping.splat.render import render

W, H, F = 32, 24, 30.0
K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])


def on_axis(zs: list[float], xs: list[float] | None = None, sigma: float = 0.05) -> GaussianMap:
    """Opaque grey Gaussians at (x, 0, z) in front of a camera at the origin looking along +z."""
    n = len(zs)
    xs = xs or [0.0] * n
    means = torch.tensor([[x, 0.0, z] for x, z in zip(xs, zs, strict=True)], dtype=torch.float32)
    return GaussianMap.from_tensors(
        means, torch.full((n, 3), math.log(sigma)), torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4),
        torch.full((n,), 8.0), torch.zeros(n, 1, 3),
    )  # fmt: skip


def _render(g: GaussianMap):  # noqa: ANN202
    return render(g.means, g.params["quats"], g.scales, g.opacities, g.sh, None,
                  torch.tensor(K, dtype=torch.float32), W, H,
                  T_world_cam=torch.eye(4), backend="cpu", sh_degree=0)  # fmt: skip


def test_a_frame_sees_what_lies_on_or_before_its_measured_surface():
    # on the surface, 10 % behind it (tolerance), 50 % behind it, outside the image
    g = on_axis([2.0, 2.15, 3.0, 2.0], xs=[0.0, 0.0, 0.0, 5.0])
    depth = torch.full((H, W), 2.0)
    assert seen_by(_render(g), depth).tolist() == [True, True, False, False]
    # no measured depth: no evidence, nothing counted
    assert not seen_by(_render(g), torch.zeros(H, W)).any()


def test_synthesised_share_is_what_repaired_gaussians_contribute_to_each_pixel():
    # an opaque observed Gaussian (4.5 px wide) in front of a repaired one; the centre pixel is
    # 0.7 px off its centre, and the rasterizer caps a Gaussian's alpha at 0.99 (as 3DGS does):
    # it lets 4.3 % through (measured)
    g = on_axis([2.0, 3.0], sigma=0.3)
    g.origin[1] = ORIGIN_REPAIRED
    share = synthesised_share(g, np.eye(4), K, W, H, backend="cpu")
    assert share.shape == (H, W) and share.dtype == np.float32
    assert share[H // 2, W // 2] == pytest.approx(0.0, abs=0.05)  # hidden behind it
    g.origin[:] = torch.tensor([ORIGIN_REPAIRED, 0], dtype=torch.uint8)  # now the front one
    share = synthesised_share(g, np.eye(4), K, W, H, backend="cpu")
    assert share[H // 2, W // 2] == pytest.approx(1.0, abs=0.05)
    aside = on_axis([2.0], xs=[5.0])  # a repaired Gaussian outside the view
    aside.origin[0] = ORIGIN_REPAIRED
    assert not synthesised_share(aside, np.eye(4), K, W, H, backend="cpu").any()  # 0 undrawn
    # reference: the origin rendered as a colour, over the alpha
    with torch.no_grad():
        out = _render(g)
        ref = render(g.means, g.params["quats"], g.scales, g.opacities, g.repaired().float()[:, None],
                     None, torch.tensor(K, dtype=torch.float32), W, H,
                     T_world_cam=torch.eye(4), backend="cpu").color[..., 0]  # fmt: skip
    drawn = out.alpha.numpy() >= 1e-3
    np.testing.assert_allclose(share[drawn], (ref / out.alpha).numpy()[drawn], atol=1e-5)


def test_a_map_without_repaired_gaussians_is_observed_everywhere():
    assert not synthesised_share(on_axis([2.0]), np.eye(4), K, W, H, backend="cpu").any()
    assert not synthesised_share(GaussianMap(), np.eye(4), K, W, H, backend="cpu").any()
