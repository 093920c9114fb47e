"""GSFusion-style growth: new Gaussians only where a frame shows what the map does not explain.

1. The image is split by a quadtree: root cells of ``max_cell_px`` are split in four while their
   luma-weighted colour variance exceeds ``var_thresh`` and they are at least twice
   ``min_cell_px`` wide, so textured regions get small cells and flat ones large cells.
2. A leaf cell is *unexplained* when at least ``need_fraction`` of its pixels are newly observed
   (the current render's alpha is below ``alpha_thresh``) or badly rendered (mean absolute
   colour error above ``error_thresh``). Without a render every cell is unexplained.
3. Each unexplained cell with a valid depth at its centre pixel gets one Gaussian: the cell centre
   unprojected with K and ``T_world_cam``, isotropic scale ``scale_mult * depth * half-diagonal``
   (the half-diagonal in normalised image units, ``0.5 * hypot(w / fx, h / fy)``, i.e.
   ``depth * half-diagonal_px / f`` for square pixels), identity rotation, opacity
   ``init_opacity`` and the cell's mean colour.

All functions here are pure numpy; :func:`grow` returns arrays ready for ``GaussianMap.add``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from gsfix_online.core.config import rng
from gsfix_online.core.types import RGBDFrame
from gsfix_online.mapping.splat.gaussians import SH_C0

F32 = npt.NDArray[np.float32]
LUMA_WEIGHTS = {1: (1.0,), 3: (0.299, 0.587, 0.114)}  # Rec. 601; sums to 1


@dataclass(frozen=True)
class GrowthConfig:
    """Where and how new Gaussians are seeded from a posed RGB-D frame."""

    max_cell_px: int = field(
        default=16, metadata=rng(1, 4096, "side of the quadtree root cells, px")
    )
    min_cell_px: int = field(
        default=2, metadata=rng(1, 4096, "smallest cell side after splits, px")
    )
    var_thresh: float = field(
        default=0.002,
        metadata=rng(
            0, None, "luma-weighted colour variance (colour in [0, 1]) above which a cell splits"
        ),
    )
    alpha_thresh: float = field(
        default=0.5, metadata=rng(0, 1, "render alpha below this marks a pixel newly observed")
    )
    error_thresh: float = field(
        default=0.1,
        metadata=rng(
            0, 1, "mean |render - image| (colour in [0, 1]) above this marks a pixel badly rendered"
        ),
    )
    need_fraction: float = field(
        default=0.5,
        metadata=rng(0, 1, "fraction of unexplained pixels for a cell to get a Gaussian"),
    )
    min_depth_m: float = field(default=0.1, metadata=rng(0, None, "nearer depth is ignored, m"))
    max_depth_m: float = field(default=10.0, metadata=rng(0, None, "farther depth is ignored, m"))
    init_opacity: float = field(default=0.5, metadata=rng(1e-4, 0.9999, "opacity of new Gaussians"))
    scale_mult: float = field(
        default=1.0, metadata=rng(1e-3, 100, "multiplier on the depth x half-diagonal / f scale")
    )

    def validate(self) -> None:
        if self.min_cell_px > self.max_cell_px:
            raise ValueError(
                f"min_cell_px {self.min_cell_px} exceeds max_cell_px {self.max_cell_px}"
            )
        if self.min_depth_m >= self.max_depth_m:
            raise ValueError(
                f"min_depth_m {self.min_depth_m} must be below max_depth_m {self.max_depth_m}"
            )

    def __post_init__(self) -> None:
        self.validate()


@dataclass(frozen=True)
class GrowthResult:
    """New Gaussians (M of them) in GaussianMap's raw parametrisation, plus what the quadtree saw."""

    means: F32  # [M, 3] world, metres
    log_scales: F32  # [M, 3] log-metres (isotropic)
    quats: F32  # [M, 4] w, x, y, z (identity)
    opacity_logits: F32  # [M]
    sh0: F32  # [M, 1, C]
    cells: npt.NDArray[np.int32]  # [M, 4] y0, x0, h, w of each Gaussian's cell, pixels
    n_cells: int  # quadtree leaves
    n_explained: int  # leaves the current render already explains
    n_invalid_depth: int  # unexplained leaves with no valid depth at their centre

    def __len__(self) -> int:
        return int(self.means.shape[0])


# ----------------------------------------------------------------------------------------------
# Pure math
# ----------------------------------------------------------------------------------------------


def integral_image(
    x: npt.NDArray[Any],
) -> npt.NDArray[np.float64]:  # [H, W, ...] -> [H+1, W+1, ...]
    out = np.zeros((x.shape[0] + 1, x.shape[1] + 1, *x.shape[2:]), dtype=np.float64)
    out[1:, 1:] = np.cumsum(np.cumsum(x, axis=0, dtype=np.float64), axis=1)
    return out


def box_sum(
    S: npt.NDArray[np.float64],  # [H+1, W+1, ...] from integral_image
    cells: npt.NDArray[np.int32],  # [M, 4] y0, x0, h, w
) -> npt.NDArray[np.float64]:  # [M, ...]
    y0, x0, h, w = cells.T
    return S[y0 + h, x0 + w] - S[y0, x0 + w] - S[y0 + h, x0] + S[y0, x0]


def quadtree_cells(
    color: F32,  # [H, W, C] in [0, 1]
    max_cell_px: int,
    min_cell_px: int,
    var_thresh: float,
) -> npt.NDArray[np.int32]:  # [M, 4] y0, x0, h, w leaves covering the image exactly once
    """Split root cells of ``max_cell_px`` while their luma-weighted colour variance > ``var_thresh``."""
    H, W, C = color.shape
    weights = np.asarray(LUMA_WEIGHTS[C])
    S1, S2 = integral_image(color), integral_image(color * color)
    ys, xs = np.meshgrid(np.arange(0, H, max_cell_px), np.arange(0, W, max_cell_px), indexing="ij")
    ys, xs = ys.ravel(), xs.ravel()
    cells = np.stack(
        [ys, xs, np.minimum(max_cell_px, H - ys), np.minimum(max_cell_px, W - xs)], axis=1
    ).astype(np.int32)
    leaves = []
    while len(cells):
        n = (cells[:, 2] * cells[:, 3]).astype(np.float64)[:, None]
        mean = box_sum(S1, cells) / n
        var = np.clip(box_sum(S2, cells) / n - mean * mean, 0.0, None) @ weights
        split_h = cells[:, 2] >= 2 * min_cell_px
        split_w = cells[:, 3] >= 2 * min_cell_px
        split = (var > var_thresh) & (split_h | split_w)
        leaves.append(cells[~split])
        cells = _split(cells[split], split_h[split], split_w[split])
    return np.concatenate(leaves) if leaves else np.zeros((0, 4), np.int32)


def _split(
    cells: npt.NDArray[np.int32],  # [M, 4]
    split_h: npt.NDArray[np.bool_],  # [M]
    split_w: npt.NDArray[np.bool_],  # [M]
) -> npt.NDArray[np.int32]:  # [<= 4M, 4]
    y0, x0, h, w = cells.T
    h0 = np.where(split_h, h // 2, h)
    w0 = np.where(split_w, w // 2, w)
    children = [
        np.stack([y0, x0, h0, w0], 1),
        np.stack([y0, x0 + w0, h0, w - w0], 1),
        np.stack([y0 + h0, x0, h - h0, w0], 1),
        np.stack([y0 + h0, x0 + w0, h - h0, w - w0], 1),
    ]
    out = np.concatenate(children)
    return out[(out[:, 2] > 0) & (out[:, 3] > 0)].astype(np.int32)


def unproject(
    u: npt.NDArray[np.float64],  # [M] pixel x (pixel centres at integers)
    v: npt.NDArray[np.float64],  # [M] pixel y
    depth_m: npt.NDArray[np.float64],  # [M] z in the camera, metres
    K: npt.NDArray[np.float64],  # [3, 3] pixels
    T_world_cam: npt.NDArray[np.float64],  # [4, 4]
) -> npt.NDArray[np.float64]:  # [M, 3] world, metres
    x = (u - K[0, 2]) / K[0, 0] * depth_m
    y = (v - K[1, 2]) / K[1, 1] * depth_m
    p_cam = np.stack([x, y, depth_m], axis=1)
    return p_cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]


def unexplained_mask(
    color: F32,  # [H, W, C] in [0, 1]
    alpha: F32 | None,  # [H, W] render alpha; None = nothing rendered
    rendered: F32 | None,  # [H, W, C] render colour in [0, 1], or None
    alpha_thresh: float,
    error_thresh: float,
) -> npt.NDArray[np.bool_]:  # [H, W]
    if alpha is None:
        return np.ones(color.shape[:2], dtype=bool)
    need = alpha < alpha_thresh
    if rendered is not None:
        need |= np.abs(rendered - color).mean(axis=2) > error_thresh
    return need


# ----------------------------------------------------------------------------------------------
# Public entry
# ----------------------------------------------------------------------------------------------


def as_float32(x: Any, name: str) -> F32:
    """A numpy or torch (any device) floating array as float32 numpy; one-line error otherwise."""
    if hasattr(x, "detach"):  # a torch tensor, possibly on a GPU
        x = x.detach().cpu().numpy()
    x = np.asarray(x)
    if not np.issubdtype(x.dtype, np.floating):
        raise ValueError(f"{name} must be floating point, got {x.dtype} {list(x.shape)}")
    return x.astype(np.float32, copy=False)


def grow(
    frame: RGBDFrame,
    cfg: GrowthConfig,
    alpha: Any = None,  # [H, W] or [H, W, 1] render alpha at the frame's pose; None = empty map
    rendered: Any = None,  # [H, W, C] (or [H, W] for grayscale) render colour in [0, 1]
) -> GrowthResult:
    """Seed Gaussians where ``frame`` observes what the current render does not explain."""
    # 1. Check inputs
    if not isinstance(frame, RGBDFrame):
        raise TypeError(f"frame must be an RGBDFrame, got {type(frame).__name__}")
    H, W = frame.depth.shape
    color = frame.color.astype(np.float32) / 255.0
    if color.ndim == 2:
        color = color[:, :, None]
    C = color.shape[2]
    if alpha is not None:
        alpha = as_float32(alpha, "alpha")
        if alpha.ndim == 3 and alpha.shape[2] == 1:
            alpha = alpha[:, :, 0]
        if alpha.shape != (H, W):
            raise ValueError(
                f"alpha must be [{H}, {W}] (or [{H}, {W}, 1]), got {list(alpha.shape)}"
            )
    if rendered is not None:
        if alpha is None:
            raise ValueError("rendered colour was given without its alpha")
        rendered = as_float32(rendered, "rendered")
        if rendered.ndim == 2 and C == 1:
            rendered = rendered[:, :, None]
        if rendered.shape != (H, W, C):
            raise ValueError(
                f"rendered must be [{H}, {W}, {C}] like the frame, got {list(rendered.shape)}"
            )

    # 2. Quadtree leaves and the cells the map does not explain yet
    cells = quadtree_cells(color, cfg.max_cell_px, cfg.min_cell_px, cfg.var_thresh)
    need = unexplained_mask(color, alpha, rendered, cfg.alpha_thresh, cfg.error_thresh)
    area = (cells[:, 2] * cells[:, 3]).astype(np.float64)
    need_frac = box_sum(integral_image(need.astype(np.float64)), cells) / area
    unexplained = (
        need_frac >= cfg.need_fraction if cfg.need_fraction > 0 else np.ones(len(cells), bool)
    )
    n_explained = int(np.count_nonzero(~unexplained))
    cells, area = cells[unexplained], area[unexplained]

    # 3. Depth at the centre pixel; invalid (0, NaN, out of range) cells get nothing
    y0, x0, h, w = (c.astype(np.float64) for c in cells.T)
    z = frame.depth[cells[:, 0] + (cells[:, 2] - 1) // 2, cells[:, 1] + (cells[:, 3] - 1) // 2]
    z = z.astype(np.float64)
    valid = np.isfinite(z) & (z > cfg.min_depth_m) & (z < cfg.max_depth_m)
    n_invalid = int(np.count_nonzero(~valid))
    cells, area, z = cells[valid], area[valid], z[valid]
    y0, x0, h, w = y0[valid], x0[valid], h[valid], w[valid]

    # 4. Parameters: position, scale, rotation, opacity, colour
    K = frame.intrinsics.K
    means = unproject(x0 + (w - 1) / 2, y0 + (h - 1) / 2, z, K, frame.T_world_cam)
    scale = cfg.scale_mult * z * 0.5 * np.hypot(w / K[0, 0], h / K[1, 1])
    mean_color = box_sum(integral_image(color), cells) / area[:, None]
    M = len(cells)
    quats = np.zeros((M, 4), np.float32)
    quats[:, 0] = 1.0
    logit = math.log(cfg.init_opacity / (1.0 - cfg.init_opacity))
    return GrowthResult(
        means=means.astype(np.float32),
        log_scales=np.repeat(np.log(scale)[:, None], 3, axis=1).astype(np.float32),
        quats=quats,
        opacity_logits=np.full(M, logit, np.float32),
        sh0=((mean_color - 0.5) / SH_C0).astype(np.float32)[:, None, :],
        cells=cells,
        n_cells=int(len(need_frac)),
        n_explained=n_explained,
        n_invalid_depth=n_invalid,
    )
