"""What every renderer backend returns (:mod:`.render`, :mod:`.render_cpu`, :mod:`.render_cuda`).

Its own module so that the backends and the dispatcher import it without importing each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from torch import Tensor

# The low-pass every render applies (gsplat's ``eps2d``, px²): each Gaussian's projected 2D
# covariance gets this much added on its diagonal, so a render is at best its content convolved
# with a Gaussian of this variance (a standard deviation of 0.55 px). A map that holds an image
# exactly still renders it that much softer (core.metrics.sharpness, ``footprint_px2``).
EPS2D = 0.3


@dataclass
class RenderOutput:
    """A rendered view. ``info`` is gsplat-compatible (``packed=False`` layout, one camera)."""

    color: Tensor  # [H, W, C] composited over the background
    depth: Tensor  # [H, W] m, expected z-depth Σ w z / α (0 where α = 0)
    alpha: Tensor  # [H, W] accumulated opacity 1 - T
    info: dict[str, Any] = field(default_factory=dict)
    # info keys: means2d [1, N, 2] px (grad retained), radii [1, N, 2] int32 (0 = not drawn),
    # depths [1, N], conics [1, N, 3], width, height, n_cameras (1), gaussian_ids (None),
    # tile_size, n_isects; what gsplat's DefaultStrategy.step_post_backward reads.

    @property
    def means2d(self) -> Tensor:  # [1, N, 2] px; its .grad is dL/d(means2d) after backward
        return self.info["means2d"]

    @property
    def radii(self) -> Tensor:  # [N, 2] int32 px
        return self.info["radii"][0]

    @property
    def visible(self) -> Tensor:  # [N] bool, drawn in this view
        return (self.info["radii"][0] > 0).all(-1)
