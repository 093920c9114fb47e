"""Real spherical harmonics colour, degrees 0 to 3, for any number of channels.

Same basis, signs and ordering as gsplat's ``_eval_sh_bases_fast`` (Sloan, JCGT 2013), so SH
coefficients move between our renderer, gsplat's CUDA rasterizer and the standard 3DGS PLY
unchanged. gsplat's own torch function only takes 3 channels; grayscale maps need 1.
"""

from __future__ import annotations

import torch
from torch import Tensor

SH_C0 = 0.28209479177387814


def num_sh_bases(degree: int) -> int:
    """Coefficients per channel for ``degree`` (1, 4, 9, 16)."""
    return (degree + 1) ** 2


def sh_bases(
    degree: int,
    dirs: Tensor,  # [N, 3] unit view directions (camera -> Gaussian)
) -> Tensor:  # [N, (degree+1)^2]
    """Evaluate the real SH basis up to ``degree`` (0..3) at unit directions."""
    assert 0 <= degree <= 3, degree
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        a = 0.48860251190292
        out += [-a * y, a * z, -a * x]
    if degree >= 2:
        z2 = z * z
        fc1 = x * x - y * y
        fs1 = 2 * x * y
        b = -1.092548430592079 * z
        out += [
            0.5462742152960395 * fs1,
            b * y,
            0.9461746957575601 * z2 - 0.3153915652525201,
            b * x,
            0.5462742152960395 * fc1,
        ]
    if degree >= 3:
        fc2 = x * fc1 - y * fs1
        fs2 = x * fs1 + y * fc1
        c = -2.285228997322329 * z2 + 0.4570457994644658
        b3 = 1.445305721320277 * z
        a3 = -0.5900435899266435
        out += [
            a3 * fs2,
            b3 * fs1,
            c * y,
            z * (1.865881662950577 * z2 - 1.119528997770346),
            c * x,
            b3 * fc1,
            a3 * fc2,
        ]
    return torch.stack(out, dim=-1)


def eval_sh(
    degree: int,
    dirs: Tensor,  # [N, 3] view directions (camera -> Gaussian), any length > 0
    coeffs: Tensor,  # [N, K, C] with K >= (degree+1)^2
) -> Tensor:  # [N, C]
    """Colour from SH coefficients, gsplat's convention: ``max(Σ basis·coeff + 0.5, 0)``.

    Only the first ``(degree+1)^2`` coefficients are used, so a map can grow its degree during
    training. Zero-length directions give the degree-0 colour (no NaN).
    """
    n = num_sh_bases(degree)
    assert coeffs.shape[-2] >= n, (coeffs.shape, degree)
    unit = dirs * torch.rsqrt((dirs * dirs).sum(-1, keepdim=True).clamp_min(1e-20))
    bases = sh_bases(degree, unit)  # [N, n]
    rgb = torch.einsum("nk,nkc->nc", bases, coeffs[..., :n, :])
    return torch.clamp_min(rgb + 0.5, 0.0)
