"""Training views and their loss: what every optimisation step of the map fits.

A :class:`TrainView` is one image the map is fitted to (an input frame, a stored keyframe or a
repaired view) at some resolution, with what the step needs to score the render against it:
depth, a mask, the view's exposure (:mod:`.exposure`) and pose correction (:mod:`.poses`).
The functions here are pure torch: building a view from a frame, downscaling it, the
photometric loss, and the loss of one render against its view (:func:`view_loss`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import torch
import torch.nn.functional as F
from torch import Tensor

from gsfix_online.core.types import RGBDFrame
from gsfix_online.mapping.splat.exposure import ExposureConfig, apply_affine
from gsfix_online.mapping.splat.exposure import prior_loss as exposure_prior_loss
from gsfix_online.mapping.splat.poses import prior_loss as pose_prior_loss
from gsfix_online.mapping.splat.render_output import RenderOutput

SSIM_WINDOW = 11
REPAIRED_FRAME_ID = "repaired"  # the frame_id of repaired views in the keyframe store


@dataclass
class TrainView:
    """A training view prepared at some resolution (tensors on the map's device)."""

    color: Tensor  # [H, W, C] in [0, 1]
    depth: Tensor | None  # [H, W] m, 0 = invalid; None = no depth term
    K: Tensor  # [3, 3] px
    T_world_cam: Tensor  # [4, 4]
    mask: Tensor | None = None  # [H, W] bool: pixels that count; None = all
    affine: Tensor | None = None  # [2, C] the view's exposure (exposure.py); None = identity
    repaired: bool = False  # a repaired view (distillation), not an input keyframe
    pose: Tensor | None = None  # [6] the keyframe's pose correction (poses.py); None = as given


def photometric_loss(
    pred: Tensor,  # [H, W, C]
    target: Tensor,  # [H, W, C]
    ssim_lambda: float,
    l1_weight: float = 1.0,
    mask: Tensor | None = None,  # [H, W] bool
) -> Tensor:
    """``l1_weight * L1 + ssim_lambda * (1 - SSIM)`` (kornia SSIM, 11x11 Gaussian window)."""
    from kornia.metrics import ssim

    if mask is not None:
        m = mask[..., None].to(pred.dtype)
        pred, target = pred * m, target * m
        l1 = (pred - target).abs().sum() / (m.sum() * pred.shape[-1]).clamp_min(1.0)
    else:
        l1 = (pred - target).abs().mean()
    if ssim_lambda == 0:
        return l1_weight * l1
    s = ssim(pred.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], SSIM_WINDOW).mean()
    return l1_weight * l1 + ssim_lambda * (1.0 - s)


def predicted_color(out: RenderOutput, view: TrainView, exposure: ExposureConfig) -> Tensor:
    """The render's colour as the view would have recorded it: in the view's exposure (its
    affine; without the bias row where ``exposure.bias`` is off)."""
    if view.affine is None:
        return out.color
    affine = view.affine
    if not exposure.bias:  # the bias row stays zero
        affine = torch.cat([affine[:1], torch.zeros_like(affine[1:])])
    return apply_affine(out.color, out.alpha, affine)


def view_loss(
    out: RenderOutput,  # the map rendered at the view's (corrected) pose and resolution
    view: TrainView,
    ssim_lambda: float,
    l1_weight: float,
    depth_weight: float,  # per m
    exposure: ExposureConfig,
    pose_prior: float,
) -> Tensor:
    """The step's loss for one view: photometric (in the view's exposure), the priors of the
    view's exposure and pose correction while they are optimised, and depth L1 on valid depth."""
    pred = predicted_color(out, view, exposure)
    loss = photometric_loss(pred, view.color, ssim_lambda, l1_weight, view.mask)
    if view.affine is not None and view.affine.requires_grad and exposure.prior > 0:
        loss = loss + exposure.prior * exposure_prior_loss(view.affine)
    if view.pose is not None and view.pose.requires_grad and pose_prior > 0:
        loss = loss + pose_prior * pose_prior_loss(view.pose)
    if view.depth is not None and depth_weight > 0:
        valid = view.depth > 0
        if view.mask is not None:
            valid &= view.mask
        if bool(valid.any()):
            loss = loss + depth_weight * (out.depth - view.depth)[valid].abs().mean()
    return loss


def downscale_view(view: TrainView, s: int) -> TrainView:
    """Area-average colour, strided depth and K for pixel centres at ``(i + 0.5) * s - 0.5``."""
    if s == 1:
        return view
    H, W = view.color.shape[0] // s * s, view.color.shape[1] // s * s
    color = F.avg_pool2d(view.color[:H, :W].permute(2, 0, 1)[None], s)[0].permute(1, 2, 0)
    off = (s - 1) // 2
    depth = None if view.depth is None else view.depth[off:H:s, off:W:s].contiguous()
    mask = None if view.mask is None else view.mask[off:H:s, off:W:s].contiguous()
    K = view.K.clone()
    K[0, 0] /= s
    K[1, 1] /= s
    K[0, 2] = (K[0, 2] + 0.5) / s - 0.5
    K[1, 2] = (K[1, 2] + 0.5) / s - 0.5
    return TrainView(color.contiguous(), depth, K, view.T_world_cam, mask, view.affine,
                     view.repaired, view.pose)  # fmt: skip


def frame_view(frame: RGBDFrame, device: torch.device, use_depth: bool = True) -> TrainView:
    """A frame as a full-resolution view: colour in [0, 1], depth in m (``use_depth``)."""
    color = (
        torch.from_numpy(np.array(frame.color)).to(device).float() / 255.0
    )  # a copy: frames may be read-only views
    if color.ndim == 2:
        color = color[..., None]
    depth = torch.from_numpy(np.array(frame.depth)).to(device) if use_depth else None
    K = torch.as_tensor(frame.intrinsics.K, dtype=torch.float32, device=device)
    T = torch.as_tensor(frame.T_world_cam, dtype=torch.float32, device=device)
    return TrainView(color, depth, K, T)


def check_size(height: int, width: int, train_downscale: int) -> None:
    """The SSIM loss pads by half its window (reflection needs more pixels than that) at
    ``train_downscale``: a smaller view failed inside kornia, in later refinement steps too
    (a 3x3 repaired view stopped the splat node; benchmarks/results/fault_findings.md)."""
    side = (SSIM_WINDOW // 2 + 1) * train_downscale
    if min(height, width) < side:
        raise ValueError(
            f"image must be at least {side}x{side} pixels (SSIM window {SSIM_WINDOW} at "
            f"train_downscale {train_downscale}), got {width}x{height}"
        )


def resize(x: Tensor, height: int, width: int) -> npt.NDArray[np.float32]:
    """[h, w, C] -> [height, width, C] numpy, bilinear (pixel centres aligned)."""
    if x.shape[:2] != (height, width):
        x = F.interpolate(
            x.permute(2, 0, 1)[None], size=(height, width), mode="bilinear", align_corners=False
        )[0].permute(1, 2, 0)
    return np.ascontiguousarray(x.cpu().numpy(), dtype=np.float32)


def upsample(x: Tensor, s: int, height: int, width: int) -> npt.NDArray[np.float32]:
    """[h, w, C] -> [height, width, C] numpy by pixel repetition (edges padded)."""
    if s > 1:
        x = x.repeat_interleave(s, 0).repeat_interleave(s, 1)
    pad_h, pad_w = height - x.shape[0], width - x.shape[1]
    if pad_h or pad_w:
        x = F.pad(x.permute(2, 0, 1)[None], (0, pad_w, 0, pad_h), mode="replicate")[0].permute(
            1, 2, 0
        )
    return x.cpu().numpy()
