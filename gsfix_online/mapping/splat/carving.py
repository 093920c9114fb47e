"""Carving: remove (or push back) the Gaussians that a stored view's depth sees through.

A keyframe's measured depth is free space up to the surface; a Gaussian in front of it is a
floater (pose error, depth noise) and goes (:func:`carve_view`, with ``carve.enabled``).
Distillation's seeds stand at a guessed depth; those that a stored view sees through are
removed (:func:`carve_seeded`, ``carve_seeds``) or moved back along their own ray
(:func:`push_seeds`, ``distill_push_seeds``). The judging views are the input keyframes (their
measured depth) and the repaired views (their depth where the map explained them):
:func:`judging_views`. The geometry is :func:`.prune.carve_mask` and :func:`.prune.push_behind`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import Tensor

from gsfix_online.mapping.splat.growth import GrowthResult
from gsfix_online.mapping.splat.keyframes import Keyframe
from gsfix_online.mapping.splat.optimize import MapOptimizer
from gsfix_online.mapping.splat.prune import CarveConfig, carve_mask, push_behind
from gsfix_online.mapping.splat.views import REPAIRED_FRAME_ID, TrainView

# (depth [H, W] m, K [3, 3] px, T_world_cam [4, 4]) of a view that judges seeds
Judge = tuple[Tensor, Tensor, Tensor]


def carve_view(
    optim: MapOptimizer,
    depth: Tensor,  # [H, W] m, 0 = invalid
    K: Tensor,  # [3, 3] px
    T_world_cam: Tensor,  # [4, 4] the view's pose with its correction
    cfg: CarveConfig,
) -> int:
    """Remove the Gaussians that this view's depth saw through; returns how many."""
    g = optim.gmap
    if not len(g):
        return 0
    mask = carve_mask(
        g.means.detach(), g.params["scales"].detach(), depth, K, T_world_cam, cfg
    )  # fmt: skip
    return optim.remove_carved(mask)


def judging_views(
    keyframes: Iterable[Keyframe],
    repair_masks: Mapping[int, npt.NDArray[np.bool_]],  # kf_id -> a repaired view's mask
    anchored: set[int],  # repaired views fitted with an anchor
    keyframe_view: Callable[[Keyframe], TrainView],
    posed: Callable[[TrainView], Tensor],  # a view -> [4, 4] its corrected pose
    seed_depths: Mapping[int, npt.NDArray[np.float32]] | None = None,  # kf_id -> [H, W] m
    made: dict[int, tuple[tuple[Any, ...], Tensor]] | None = None,  # reused repaired depths
) -> list[Judge]:
    """(depth [H, W], K, T_world_cam) of the stored views that judge distillation's seeds:
    the input keyframes (their measured depth: free space the camera saw) and the repaired
    views (their stored depth where the map explained them, outside their holes). With
    ``seed_depths`` (the veil guard), a repaired view judges in its holes too, with the depth
    its seeds were grown at (the mesh's, where the input observed a surface): a Gaussian
    another view put in front of it is a veil over what that view delivered.

    ``made`` keeps each repaired view's judging depth between calls (rebuilt when its mask,
    anchor or seed depth changes), so that filters of it (prune.nearest_surface) are reused."""
    views = []
    live = set()
    for kf in keyframes:
        if kf.frame.frame_id == REPAIRED_FRAME_ID:
            holes = repair_masks.get(kf.kf_id)
            seeds = None if seed_depths is None else seed_depths.get(kf.kf_id)
            # only where the map explained that view: a guess in its holes must not move or
            # remove what another guess put there (an anchored view holds no depth there)
            cut = holes is not None and kf.kf_id not in anchored
            # what the depth is made of, held (so no other array takes its id while cached)
            key = (kf.frame.depth, holes if cut else None, seeds)
            live.add(kf.kf_id)
            kept = None if made is None else made.get(kf.kf_id)
            if kept is not None and all(a is b for a, b in zip(kept[0], key, strict=True)):
                depth = kept[1]
            else:
                d = np.array(kf.frame.depth, np.float32)
                if cut:
                    d[holes] = 0.0
                if seeds is not None:
                    d = np.where(d > 0, d, seeds).astype(np.float32)
                depth = torch.from_numpy(d)
                if made is not None:
                    made[kf.kf_id] = (key, depth)
            K = torch.as_tensor(kf.frame.intrinsics.K, dtype=torch.float32)
            T = torch.as_tensor(kf.frame.T_world_cam, dtype=torch.float32)
        else:
            view = keyframe_view(kf)
            if view.depth is None:
                continue
            depth, K, T = view.depth, view.K, posed(view)
        if bool((depth > 0).any()):
            views.append((depth, K, T))
    if made is not None:
        for kf_id in [k for k in made if k not in live]:
            del made[kf_id]
    return views


def carve_seeded(
    optim: MapOptimizer, views: list[Judge], cfg: CarveConfig, whole: bool = True
) -> int:
    """Remove the Gaussians distillation seeded that a judging view sees through
    (prune.carve_mask with footprint; without ``whole``, those whose centre stands in front of
    the surface); returns how many. A guessed seed in front of what
    another view sees would stand there as a floater, hiding the surface; it is judged at
    seeding and again after each fit, since fitting moves and grows it. Only seeded Gaussians
    are judged: a guess never removes what the input mapped, and one guess never removes
    another."""
    seeded = optim.seeded()
    if not bool(seeded.any()):
        return 0
    g = optim.gmap
    idx = torch.nonzero(seeded).squeeze(1)
    means, scales = g.means.detach()[idx], g.params["scales"].detach()[idx]
    seen = torch.zeros(len(idx), dtype=torch.bool, device=means.device)
    for depth, K, T in views:
        seen |= carve_mask(means, scales, depth.to(means.device), K.to(means.device),
                           T.to(means.device), cfg, footprint=True, whole=whole)  # fmt: skip
    mask = torch.zeros(len(g), dtype=torch.bool, device=means.device)
    mask[idx[seen]] = True
    return optim.remove_carved(mask)


def push_seeds(
    res: GrowthResult,
    T_world_cam: npt.ArrayLike,  # [4, 4] the pose the seeds were grown from
    views: list[Judge],
    cfg: CarveConfig,
    push_max: float,
) -> tuple[GrowthResult, int]:
    """``res`` with each seed moved along its own ray until no judging view sees it
    (prune.push_behind, at most ``push_max`` times as far), and how many moved."""
    if not views:
        return res, 0
    means = torch.from_numpy(res.means)
    origin = torch.as_tensor(np.asarray(T_world_cam)[:3, 3], dtype=torch.float32)
    f = push_behind(means, origin, views, cfg, push_max)
    n_pushed = int((f > 1).sum())
    means = origin + f[:, None] * (means - origin)
    log_scales = torch.from_numpy(res.log_scales) + torch.log(f)[:, None]
    return dataclasses.replace(res, means=means.numpy().astype(np.float32),
                               log_scales=log_scales.numpy().astype(np.float32)), n_pushed  # fmt: skip
