"""A dense reference rasterizer: every pixel against every Gaussian, one Gaussian at a time.

The oracle for the tile rasterizer's compositing, forward and backward (plain autograd). It
follows gsplat's per-pixel loop literally: Gaussians in depth order; σ = ½a·dx² + b·dx·dy + ½c·dy²
at the pixel centre; alpha = min(0.99, o·exp(-σ)); skip alpha < 1/255; stop the pixel before the
Gaussian whose next transmittance would be <= 1e-4. Memory is pixels x features per step, fine
for the small images the tests use; it is slow by design.
"""

from __future__ import annotations

import torch
from torch import Tensor


def dense_composite(
    means2d: Tensor,  # [N, 2] px
    conics: Tensor,  # [N, 3] (a, b, c)
    opacities: Tensor,  # [N]
    feats: Tensor,  # [N, F]
    depths: Tensor,  # [N] sort key
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:  # Σ w·f [H, W, F], alpha [H, W]
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=means2d.dtype) + 0.5,
        torch.arange(width, dtype=means2d.dtype) + 0.5,
        indexing="ij",
    )
    T = torch.ones(height, width, dtype=means2d.dtype)
    done = torch.zeros(height, width, dtype=torch.bool)
    acc = torch.zeros(height, width, feats.shape[1], dtype=means2d.dtype)
    for i in torch.argsort(depths, stable=True).tolist():
        dx = means2d[i, 0] - xs
        dy = means2d[i, 1] - ys
        a, b, c = conics[i]
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        alpha = torch.clamp(opacities[i] * torch.exp(-sigma), max=0.99)
        use = (alpha >= 1.0 / 255.0) & (sigma >= 0) & ~done
        next_T = T * (1.0 - alpha)
        stop = use & (next_T <= 1e-4)
        use = use & ~stop
        done = done | stop
        w = torch.where(use, alpha * T, 0.0)
        acc = acc + w[..., None] * feats[i]
        T = torch.where(use, next_T, T)
    return acc, 1.0 - T


def dense_render(
    means: Tensor,  # [N, 3] world
    quats: Tensor,  # [N, 4] (w, x, y, z)
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, C]
    viewmat: Tensor,  # [4, 4] world -> camera
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
) -> tuple[Tensor, Tensor, Tensor]:  # color [H, W, C], depth [H, W] (Σwz/α), alpha [H, W]
    """End-to-end oracle: gsplat's torch projection + :func:`dense_composite`."""
    from gsplat.cuda._torch_impl import _fully_fused_projection, _quat_scale_to_covar_preci

    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    radii, means2d, depths, conics, _ = _fully_fused_projection(
        means, covars, viewmat[None], K[None], width, height, near_plane=near, far_plane=far
    )
    vis = (radii[0] > 0).all(-1)
    feats = torch.cat([colors, depths[0, :, None]], -1)
    acc, alpha = dense_composite(
        means2d[0, vis], conics[0, vis], opacities[vis], feats[vis], depths[0, vis], width, height
    )
    C = colors.shape[1]
    return acc[..., :C], acc[..., C] / alpha.clamp_min(1e-10), alpha
