"""Which Gaussians a frame saw: the count behind each Gaussian's ``observations``.

A Gaussian counts as seen by a frame when the frame's render drew it (its footprint lies in the
image) and the frame's measured depth at its centre's pixel does not lie in front of it (it is
not hidden behind the surface the camera measured). Pixels without depth give no evidence and
count nothing. Pure function on tensors.
"""

from __future__ import annotations

import torch
from torch import Tensor

from gsfix_online.mapping.splat.render_output import RenderOutput

# A Gaussian up to this fraction of the measured depth behind the surface is on it (the
# sensor's noise and the Gaussian's own extent), not hidden behind it
SURFACE_REL_TOL = 0.1


def seen_by(
    out: RenderOutput,  # the frame's render of the map (info: means2d, radii, depths)
    depth_m: Tensor,  # [H, W] the frame's measured depth at the render's resolution, 0 = none
    rel_tol: float = SURFACE_REL_TOL,
) -> Tensor:  # [N] bool
    """The Gaussians of the render that the frame saw (module doc)."""
    H, W = depth_m.shape
    uv = torch.round(out.means2d[0].detach()).long()  # [N, 2] px
    z = out.info["depths"][0].detach()  # [N] m, camera z of each centre
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H) & (z > 0)
    measured = torch.zeros_like(z)
    idx = inside.nonzero().squeeze(1)
    measured[idx] = depth_m[uv[idx, 1], uv[idx, 0]].to(z.dtype)
    return out.visible & inside & (measured > 0) & (z <= measured * (1.0 + rel_tol))
