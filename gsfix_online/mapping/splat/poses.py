"""Keyframe pose refinement: a small SE(3) correction per keyframe, optimised with the map.

A visual-inertial front end's poses carry jitter and drift. A map fitted to frames whose poses
disagree by a few millimetres or a tenth of a degree blurs every surface that two of them see:
it cannot fit both, so it averages them. As Gaussian-splatting SLAM systems do (MonoGS's pose
gradients, gsplat's ``pose_opt``), each input keyframe after the first gets a correction
``xi = (upsilon, omega)`` in se(3), applied in the camera frame::

    T_world_cam' = T_world_cam @ exp(xi)

and optimised by the photometric and depth loss together with the Gaussians, with an L2 prior
towards zero (the front end's pose is the prior). A new frame is first tracked: its correction
is fitted against the map alone, so that it grows the map where its surfaces already are rather
than beside them (the doubled walls of a revisited place). The first keyframe stays fixed: it ties the
map to the front end's world frame (the gauge), so renders at the user's poses stay where they
were. Repaired views (distillation) are never corrected: their pose is the one the view was
asked at. ``upsilon`` is in units of the scene scale, so one learning rate fits any scene size.
A pose given by the user (a view to render or repair, a held-out frame) takes the world-frame
correction of the nearest input keyframe (:meth:`Mapper.pose_for`).
The exponential map is kornia's (``kornia.geometry.liegroup.Se3``).

Off by default, measured (benchmarks/results/pose_correction_cpu.json; raw 3DGS at the held-out
frames of 40-frame tank inputs, seed-1 layout): with VIO-like drift, tracking lifts it from
20.76 to 22.3-22.4 dB (mesh + Telea 22.31) and the fit at training frames from 23.0 to 24.3-25.2;
correcting keyframes with the map alone, without tracking, does nothing (20.61). But on exact
poses (the gray input) tracking costs 1.4-1.9 dB (25.17 -> 23.3-23.8): on the online map, fitted
a few steps per keyframe and tracked at 80x60 to 160x120 px, the loss is lowest a few
centimetres off the true pose (the map's under-fitted borders pull the masked pixels), so
corrections walk to the clamp (10 cm, 2 deg) even with the guard. Tracking against a converged
map and a drift test that leaves exact poses alone are the next steps; until then a user whose
front end drifts can switch it on (``mapper.poses.enabled``) and judge it with ``--holdout``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from gsfix_online.core.config import rng


@dataclass(frozen=True)
class PoseConfig:
    """Per-keyframe pose correction (off by default: the front end's poses are used as given)."""

    enabled: bool = False
    lr: float = field(default=1e-4, metadata=rng(0, None, "Adam rate of the correction"))
    prior: float = field(
        default=1.0,
        metadata=rng(0, None, "loss weight of |upsilon / scale|^2 + |omega|^2 (rad) per view"),
    )
    max_rotation_deg: float = field(
        default=2.0, metadata=rng(0, 180, "a correction is clamped to this rotation")
    )
    max_translation: float = field(
        default=0.05, metadata=rng(0, None, "... and this translation, times the scene scale")
    )
    # Tracking: a new frame's correction is fitted against the map (frozen) before the frame
    # grows it, from the better of the front end's pose and the last keyframe's correction
    # (drift is smooth), on the pixels the map renders opaque, under the same prior; it is kept
    # only if it lowers that loss by ``track_margin``. Too few opaque pixels (a frame looking
    # at unmapped space): the front end's pose.
    track_iters: int = field(default=20, metadata=rng(0, None, "pose-only steps per new frame"))
    track_lr: float = field(default=2e-3, metadata=rng(0, None, "Adam rate of tracking"))
    track_margin: float = field(
        default=0.02, metadata=rng(0, 1, "a tracked pose must lower the loss by this share")
    )
    track_downscale: int = field(
        default=2, metadata=rng(1, 8, "tracking renders at 1/n of the training resolution")
    )
    track_min_covered: float = field(
        default=0.3, metadata=rng(0, 1, "share of the frame the map must render opaque")
    )


def corrected(
    T_world_cam: Tensor,  # [4, 4]
    xi: Tensor,  # [6] (upsilon / scale, omega rad)
    scale: float,  # the scene scale, m
) -> Tensor:  # [4, 4] T_world_cam @ exp(xi), differentiable in xi
    """The keyframe's pose with its correction applied in the camera frame."""
    from kornia.geometry.liegroup import Se3

    v = torch.cat([xi[:3] * scale, xi[3:]]).to(T_world_cam.dtype)
    return T_world_cam @ Se3.exp(v).matrix()


def prior_loss(xi: Tensor) -> Tensor:
    """``|xi|^2``: the correction's distance from the front end's pose (scene-scale units)."""
    return (xi * xi).sum()


@torch.no_grad()
def clamp_(xi: Tensor, cfg: PoseConfig) -> None:
    """Keep a correction within ``max_rotation_deg`` and ``max_translation`` (in place)."""
    for part, limit in (
        (xi[:3], cfg.max_translation),
        (xi[3:], torch.deg2rad(torch.tensor(cfg.max_rotation_deg)).item()),
    ):
        n = float(part.norm())
        if n > limit > 0:
            part.mul_(limit / n)


def offsets(T_world_cam: Tensor, T_corrected: Tensor) -> tuple[float, float]:
    """(translation m, rotation deg) between a pose and its corrected pose."""
    d = torch.linalg.inv(T_world_cam.detach().double()) @ T_corrected.detach().double()
    cos = ((torch.diagonal(d[:3, :3]).sum() - 1) / 2).clamp(-1, 1)
    return float(d[:3, 3].norm()), float(torch.rad2deg(torch.arccos(cos)))
