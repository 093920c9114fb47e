"""The Gaussians' provenance in images: which ones a frame saw, how much of a render they make.

:func:`seen_by` gives the count behind each Gaussian's ``observations``: a Gaussian counts as seen by a frame when the frame's render drew it (its footprint lies in the
image) and the frame's measured depth at its centre's pixel does not lie in front of it (it is
not hidden behind the surface the camera measured). Pixels without depth give no evidence and
count nothing. :func:`synthesised_share` renders, per pixel, the share of a view's colour that
Gaussians grown from repaired views contribute (their origin splatted as a colour channel), the
provenance image a map render returns beside its colour. Pure functions on tensors.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import Tensor

from gsfix_online.mapping.splat.gaussians import GaussianMap
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


@torch.no_grad()
def synthesised_share(
    gmap: GaussianMap,
    T_world_cam: npt.ArrayLike,  # [4, 4]
    K: npt.ArrayLike,  # [3, 3] px
    width: int,
    height: int,
    backend: Any = "auto",
    min_alpha: float = 1e-3,  # below: no Gaussian covers the pixel, share 0
) -> npt.NDArray[np.float32]:  # [H, W] in [0, 1]
    """Per pixel, the share of the render's colour that repaired-view Gaussians contribute:
    the origin rendered as a one-channel colour (1 repaired, 0 observed), over the alpha."""
    from gsfix_online.mapping.splat.render import render

    dev = gmap.device
    if len(gmap) == 0 or not bool(gmap.repaired().any()):
        return np.zeros((height, width), np.float32)
    T = torch.tensor(np.asarray(T_world_cam), dtype=torch.float32, device=dev)
    Kt = torch.tensor(np.asarray(K), dtype=torch.float32, device=dev)
    out = render(gmap.means, gmap.params["quats"], gmap.scales, gmap.opacities,
                 gmap.repaired().float()[:, None], None, Kt, width, height, T_world_cam=T,
                 backend=backend)  # fmt: skip
    share = out.color[..., 0] / out.alpha.clamp_min(min_alpha)
    share = torch.where(out.alpha >= min_alpha, share.clamp(0, 1), torch.zeros_like(share))
    return share.cpu().numpy().astype(np.float32)
