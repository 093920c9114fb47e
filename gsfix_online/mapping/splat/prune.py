"""Pruning: remove Gaussians that are transparent, huge, tiny, non-finite or too large on screen.

The reasons may overlap (a Gaussian can be both transparent and tiny); each count in
:class:`PruneResult` is per reason and ``mask`` is their union.
"""

from __future__ import annotations

import math
import weakref
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass, field

import torch
from torch import Tensor

from gsfix_online.core.config import rng
from gsfix_online.mapping.splat.gaussians import PARAM_KEYS, GaussianMap


@dataclass(frozen=True)
class PruneConfig:
    """Thresholds of :func:`prune`; a Gaussian exactly at a threshold is kept."""

    min_opacity: float = field(
        default=0.005, metadata=rng(0, 1, "opacity below this is transparent (gsplat: 0.005)")
    )
    max_scale_m: float = field(
        default=1.0, metadata=rng(0, None, "largest axis sigma above this is huge, m")
    )
    min_scale_m: float = field(
        default=1e-5, metadata=rng(0, None, "largest axis sigma below this is tiny, m")
    )
    max_radius_px: float = field(
        default=0.0,
        metadata=rng(0, None, "screen radius above this is too large, px; 0 = off (needs radii)"),
    )

    def validate(self) -> None:
        if self.min_scale_m >= self.max_scale_m:
            raise ValueError(
                f"min_scale_m {self.min_scale_m} must be below max_scale_m {self.max_scale_m}"
            )

    def __post_init__(self) -> None:
        self.validate()


@dataclass(frozen=True)
class PruneResult:
    mask: Tensor  # [N] bool, True = prune
    n_transparent: int
    n_huge: int
    n_tiny: int
    n_nonfinite: int
    n_large_on_screen: int

    @property
    def n_pruned(self) -> int:
        return int(self.mask.sum())


def prune_mask(
    opacity_logits: Tensor,  # [N]
    log_scales: Tensor,  # [N, 3] log-metres
    cfg: PruneConfig,
    nonfinite: Tensor | None = None,  # [N] bool: any parameter of the Gaussian is NaN or inf
    radii_px: Tensor | None = None,  # [N] largest screen radius over the views rendered, px
) -> PruneResult:
    """Which Gaussians to prune under ``cfg`` (pure; nothing is modified)."""
    n = opacity_logits.shape[0]
    assert opacity_logits.shape == (n,) and log_scales.shape == (n, 3)
    with torch.no_grad():
        # float64 so that sigmoid does not round opacities near the threshold; scales are
        # compared in log space, where extreme values (1e-6 .. 1e3 m) stay exact.
        transparent = torch.sigmoid(opacity_logits.double()) < cfg.min_opacity
        max_log = log_scales.double().amax(dim=1)
        huge = max_log > math.log(cfg.max_scale_m)
        tiny = max_log < (math.log(cfg.min_scale_m) if cfg.min_scale_m > 0 else -math.inf)
        bad = torch.zeros(n, dtype=torch.bool) if nonfinite is None else nonfinite.cpu()
        large = torch.zeros(n, dtype=torch.bool)
        if radii_px is not None and cfg.max_radius_px > 0:
            large = radii_px.cpu() > cfg.max_radius_px
        transparent, huge, tiny = transparent.cpu(), huge.cpu(), tiny.cpu()
        # NaN compares false everywhere above, so non-finite ones are caught by `bad` only.
        mask = transparent | huge | tiny | bad | large
    return PruneResult(
        mask=mask.to(opacity_logits.device),
        n_transparent=int(transparent.sum()),
        n_huge=int(huge.sum()),
        n_tiny=int(tiny.sum()),
        n_nonfinite=int(bad.sum()),
        n_large_on_screen=int(large.sum()),
    )


def nonfinite_rows(gmap: GaussianMap) -> Tensor:  # [N] bool
    """Gaussians with any NaN or inf parameter."""
    with torch.no_grad():
        bad = torch.zeros(len(gmap), dtype=torch.bool, device=gmap.device)
        for key in PARAM_KEYS:
            p = gmap.params[key]
            bad |= ~torch.isfinite(p.flatten(1)).all(dim=1) if p.dim() > 1 else ~torch.isfinite(p)
    return bad


def prune(
    gmap: GaussianMap,
    cfg: PruneConfig,
    optimizers: Mapping[str, torch.optim.Optimizer] | None = None,
    radii_px: Tensor
    | None = None,  # [N] px, e.g. the max of the renderer's radii since the last prune
) -> PruneResult:
    """Remove from ``gmap`` (and its optimizers' state) what :func:`prune_mask` selects."""
    n = len(gmap)
    if radii_px is not None and tuple(radii_px.shape) != (n,):
        raise ValueError(f"radii_px must be [{n}] (one per Gaussian), got {list(radii_px.shape)}")
    result = prune_mask(
        gmap.params["opacities"].detach(),
        gmap.params["scales"].detach(),
        cfg,
        nonfinite=nonfinite_rows(gmap),
        radii_px=radii_px,
    )
    if result.n_pruned:
        gmap.remove(result.mask, optimizers)
    return result


# ----------------------------------------------------------------------------------------------
# Free-space carving
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CarveConfig:
    """Remove Gaussians that a depth frame saw through (floaters in observed free space)."""

    enabled: bool = False
    margin_m: float = field(default=0.05, metadata=rng(0, None, "absolute margin, m"))
    margin_rel: float = field(
        default=0.1, metadata=rng(0, 1, "margin as a share of the observed depth")
    )
    window_px: int = field(
        default=5, metadata=rng(1, 63, "nearest depth in this window counts (edges, pose error)")
    )
    extent_sigmas: float = field(
        default=2.0, metadata=rng(0, None, "a Gaussian's depth extent: this many largest sigmas")
    )


def project_points(
    points: Tensor,  # [..., 3] world, m
    K: Tensor,  # [3, 3] pixels
    T_world_cam: Tensor,  # [4, 4]
) -> tuple[Tensor, Tensor, Tensor]:  # camera z [...], nearest pixel u, v [...] (long)
    """World points' camera z-depth and nearest pixel in a pinhole view."""
    T = T_world_cam.to(points)
    p = (points - T[:3, 3]) @ T[:3, :3]  # camera frame
    z = p[..., 2]
    zs = z.clamp_min(1e-6)
    u = torch.round(K[0, 0] * p[..., 0] / zs + K[0, 2]).long()
    v = torch.round(K[1, 1] * p[..., 1] / zs + K[1, 2]).long()
    return z, u, v


_NEAREST: OrderedDict[tuple[int, int, int], tuple[weakref.ref[Tensor], Tensor]] = OrderedDict()
_NEAREST_MAX = 512  # a bound; an entry also goes when its depth tensor is freed


def nearest_surface(
    depth_m: Tensor,  # [H, W] observed z-depth, 0 = invalid
    window_px: int,
) -> Tensor:  # [H, W] the nearest valid depth in the window around each pixel; inf = none
    """The nearest measured surface around each pixel (a min filter over valid depth).

    Computed once per depth tensor and window: the passes judge distillation's seeds against
    the same stored views after every step, and the filter cost more than the step. A depth
    changed in place (a new tensor version) or a new tensor is filtered again."""
    key = (id(depth_m), depth_m._version, window_px)
    hit = _NEAREST.get(key)
    if hit is not None and hit[0]() is depth_m:
        _NEAREST.move_to_end(key)
        return hit[1]
    d = torch.where(depth_m > 0, depth_m, torch.full_like(depth_m, math.inf))
    w = window_px // 2
    nearest = -torch.nn.functional.max_pool2d(-d[None, None], 2 * w + 1, 1, w)[0, 0]
    _NEAREST[key] = (weakref.ref(depth_m, lambda _: _NEAREST.pop(key, None)), nearest)
    while len(_NEAREST) > _NEAREST_MAX:
        _NEAREST.popitem(last=False)
    return nearest


def carve_mask(
    means: Tensor,  # [N, 3] world, m
    log_scales: Tensor,  # [N, 3] log-metres
    depth_m: Tensor,  # [H, W] observed z-depth, 0 = invalid
    K: Tensor,  # [3, 3] pixels
    T_world_cam: Tensor,  # [4, 4]
    cfg: CarveConfig,
    footprint: bool = False,
    whole: bool = True,
) -> Tensor:  # [N] bool: in front of the observed surface, whole Gaussian, beyond the margin
    """Gaussians whose centre projects onto a pixel whose surface (the nearest valid depth in a
    ``window_px`` window) lies behind the Gaussian's far end by more than
    ``max(margin_m, margin_rel * depth)``: the camera saw that surface through them. With
    ``footprint``, a Gaussian whose centre projects outside the image but whose extent
    (``extent_sigmas`` of its largest sigma) reaches into it is judged at the image pixel
    nearest its centre: one close to the camera can cover the whole view from just outside.
    Without ``whole``, the centre is judged instead of the far end: a large Gaussian whose
    centre stands in front of the surface covers it, even if its tail reaches behind."""
    with torch.no_grad():
        H, W = depth_m.shape
        z, u, v = project_points(means, K, T_world_cam)
        zs = z.clamp_min(1e-6)
        extent = cfg.extent_sigmas * log_scales.amax(1).exp()
        r = torch.ceil(K[0, 0] * extent / zs).long() if footprint else torch.zeros_like(u)
        inside = (z > 0) & (u + r >= 0) & (u - r < W) & (v + r >= 0) & (v - r < H)
        nearest = nearest_surface(depth_m, cfg.window_px)
        valid = depth_m > 0  # the pixel itself must have been measured
        ui, vi = u.clamp(0, W - 1), v.clamp(0, H - 1)
        surf = nearest[vi, ui]
        margin = torch.clamp(surf * cfg.margin_rel, min=cfg.margin_m)
        far = z + extent if whole else z
        return inside & valid[vi, ui] & torch.isfinite(surf) & (far < surf - margin)


def hidden_mask(
    points: Tensor,  # [..., 3] world, m
    depth_m: Tensor,  # [H, W] observed z-depth, 0 = invalid
    K: Tensor,  # [3, 3] pixels
    T_world_cam: Tensor,  # [4, 4]
    cfg: CarveConfig,
) -> Tensor:  # [...] bool: the view cannot see the point (or did not measure where it lies)
    """Points this view's depth does not see: outside the image, behind the camera, on a pixel
    with no measured depth, or behind the measured surface of their pixel by at least
    ``max(margin_m, margin_rel * depth)``. A Gaussian centred there renders after that surface's
    Gaussians, which hide it. In front of the surface, or behind it by less than the margin,
    the view sees the point: a Gaussian there would cover what the view measured."""
    with torch.no_grad():
        H, W = depth_m.shape
        z, u, v = project_points(points, K, T_world_cam)
        inside = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        surf = depth_m[v.clamp(0, H - 1), u.clamp(0, W - 1)]
        margin = torch.clamp(surf * cfg.margin_rel, min=cfg.margin_m)
        seen = inside & (surf > 0) & (z < surf + margin)
        return ~seen


def push_behind(
    means: Tensor,  # [M, 3] world, m: seeds on their own view's rays
    origin: Tensor,  # [3] their view's camera centre, world
    views: list[tuple[Tensor, Tensor, Tensor]],  # (depth [H, W], K, T_world_cam) of other views
    cfg: CarveConfig,
    max_factor: float = 3.0,
    n_steps: int = 64,
) -> Tensor:  # [M] factor >= 1 along the ray from ``origin``; 1 where none hides the seed
    """How far each seed must move away from its camera, along its own ray, until no other view
    sees it (:func:`hidden_mask`): the first of ``n_steps`` factors spaced geometrically in
    ``[1, max_factor]``. Its own view renders it on the same pixels (scale it by the factor
    too); the other views see their measured surfaces in front of it instead of a floater.
    A seed that no factor hides keeps factor 1 (carving judges it)."""
    with torch.no_grad():
        M = means.shape[0]
        factors = torch.logspace(0.0, math.log10(max_factor), n_steps, dtype=means.dtype,
                                 device=means.device)  # fmt: skip
        pts = origin + factors[:, None, None] * (means - origin)  # [S, M, 3]
        hidden = torch.ones(n_steps, M, dtype=torch.bool, device=means.device)
        for depth, K, T in views:
            hidden &= hidden_mask(pts, depth.to(means.device), K.to(means), T.to(means), cfg)
        first = torch.argmax(hidden.to(torch.uint8), dim=0)  # first True (0 when none)
        return torch.where(hidden.any(dim=0), factors[first], torch.ones_like(factors[0]))
