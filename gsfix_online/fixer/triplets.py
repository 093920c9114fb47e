"""Training triplets ``(I_mesh, I_gs, I_gt)`` for GSFixer, and the degradations of pretraining.

- :func:`triplet_from_keyframe`: a ``keyframe`` message's arrays (the camera image, the splat
  render and its alpha) plus the mesh render at the same pose become one triplet, with the
  keyframe's own alpha holes as extra mask candidates for augmentation.
- :func:`degrade_gs` / :func:`degrade_mesh`: stand-ins for the two conditions when only ground
  truth exists (pretraining): a 3DGS-like render is ground truth blurred, noisy and with soft
  holes that show black background (missing Gaussians); a mesh-like render is the ground-truth
  mesh rendered with its (blurry) vertex colours, or ground truth heavily blurred without one.

All functions are pure: numpy arrays in, float tensors out, randomness from the generator given.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import torch
from torch import Tensor

from gsfix_online.core.config import rng
from gsfix_online.fixer.config import MaskConfig
from gsfix_online.fixer.masks import BoolImage, alpha_hole_mask, procedural_mask


@dataclass
class Triplet:
    """One training example; images float32 [3, H, W] in [0, 1]."""

    image_mesh: Tensor  # [3, H, W] mesh render (zeros in mode gs)
    image_gs: Tensor  # [3, H, W] Gaussian-map render
    image_gt: Tensor  # [3, H, W] camera image
    alpha_holes: list[BoolImage] = field(default_factory=list)  # [H, W] mask candidates


def to_chw(image: npt.NDArray[Any]) -> Tensor:  # [H, W] or [H, W, 3] uint8/float -> [3, H, W]
    """An image as float [3, H, W] in [0, 1]; gray is replicated, uint8 is scaled by 1/255."""
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3 or image.shape[2] not in (1, 3):
        raise ValueError(f"image must be [H, W] or [H, W, 1|3], got {list(image.shape)}")
    t = torch.from_numpy(np.array(image))  # a copy: message arrays are read-only views
    t = t.float() / 255.0 if image.dtype == np.uint8 else t.float()
    return t.permute(2, 0, 1).expand(3, -1, -1).contiguous()


def triplet_from_keyframe(
    arrays: dict[str, npt.NDArray[Any]],  # a keyframe message: color, gs_render, gs_alpha, ...
    mesh_color: npt.NDArray[np.uint8] | None,  # [H, W, 3] or [H, W] mesh render at the pose
    alpha_threshold: float = 0.5,
) -> Triplet:
    """The triplet of one keyframe; without a mesh render the mesh image is black (mode gs)."""
    # 1. Check inputs (the wire schema checked dtypes and equal sizes already)
    gt = to_chw(arrays["color"])
    gs = to_chw(arrays["gs_render"])
    _, h, w = gt.shape
    if mesh_color is not None and tuple(mesh_color.shape[:2]) != (h, w):
        raise ValueError(f"mesh render must be {h}x{w}, got {list(mesh_color.shape)}")
    # 2. Conditions
    mesh = to_chw(mesh_color) if mesh_color is not None else torch.zeros_like(gt)
    # 3. The keyframe's own holes, as candidates for mask augmentation
    holes = alpha_hole_mask(arrays["gs_alpha"].astype(np.float32), alpha_threshold)
    return Triplet(mesh, gs, gt, [holes] if holes.any() else [])


# ------------------------------------------------------------------------------------------
# Degradations for pretraining
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DegradeConfig:
    """How ground truth is turned into the two conditions; sizes are fractions of min(H, W)."""

    gs_blur: tuple[float, float] = field(
        default=(0.0, 0.012), metadata=rng(0, 1, "3DGS blur sigma range / min(H, W)")
    )
    gs_noise: tuple[float, float] = field(
        default=(0.0, 0.06), metadata=rng(0, 1, "3DGS Gaussian noise sigma range (0..1 units)")
    )
    gs_hole_prob: float = field(
        default=0.8, metadata=rng(0, 1, "probability of holes in the 3DGS image")
    )
    gs_hole_area: tuple[float, float] = field(
        default=(0.03, 0.35), metadata=rng(0, 1, "area fraction of the holes")
    )
    gs_hole_soft: float = field(
        default=0.015, metadata=rng(0, 1, "blur sigma of the hole edges / min(H, W)")
    )
    mesh_blur: float = field(
        default=0.03, metadata=rng(0, 1, "blur of ground truth standing in for a mesh render")
    )
    mesh_noise: float = field(
        default=0.01, metadata=rng(0, 1, "Gaussian noise on the mesh image (0..1 units)")
    )

    def validate(self) -> None:
        for name in ("gs_blur", "gs_noise", "gs_hole_area"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"{name} must satisfy 0 <= min <= max, got {(lo, hi)}")


def _gauss(img: npt.NDArray[np.float32], sigma: float) -> npt.NDArray[np.float32]:
    return cv2.GaussianBlur(img, (0, 0), sigma) if sigma > 0.3 else img


def degrade_gs(
    gt: npt.NDArray[np.float32],  # [H, W, 3] in [0, 1]
    rng_: np.random.Generator,
    cfg: DegradeConfig,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:  # image [H, W, 3], alpha [H, W]
    """A 3DGS-like render: blurred, noisy, with soft holes showing a black background."""
    h, w = gt.shape[:2]
    side = min(h, w)
    img = _gauss(gt, rng_.uniform(*cfg.gs_blur) * side)
    img = img + rng_.normal(0, rng_.uniform(*cfg.gs_noise), img.shape).astype(np.float32)
    alpha = np.ones((h, w), np.float32)
    if rng_.random() < cfg.gs_hole_prob:
        shapes = MaskConfig(shape_area=cfg.gs_hole_area, max_shapes=4)
        hole = procedural_mask(rng_, h, w, shapes).astype(np.float32)
        alpha = 1.0 - np.clip(_gauss(hole, cfg.gs_hole_soft * side), 0, 1)
    img = np.clip(img, 0, 1) * alpha[:, :, None]
    return img.astype(np.float32), alpha


def degrade_mesh(
    gt: npt.NDArray[np.float32],  # [H, W, 3] in [0, 1]
    rng_: np.random.Generator,
    cfg: DegradeConfig,
    mesh_color: npt.NDArray[np.float32] | None = None,  # [H, W, 3] vertex-colour render or None
    mesh_valid: npt.NDArray[np.bool_] | None = None,  # [H, W] where the mesh was hit
) -> npt.NDArray[np.float32]:  # [H, W, 3]
    """A mesh-like render: the mesh's own render when given, else ground truth heavily blurred."""
    h, w = gt.shape[:2]
    img = mesh_color if mesh_color is not None else _gauss(gt, cfg.mesh_blur * min(h, w))
    img = img + rng_.normal(0, cfg.mesh_noise, img.shape).astype(np.float32)
    img = np.clip(img, 0, 1)
    if mesh_valid is not None:
        img = img * mesh_valid[:, :, None]
    return img.astype(np.float32)


def relit_mesh_render(
    albedo_render: npt.NDArray[np.float32],  # [H, W, 3] vertex-albedo render in [0, 1]
    gt: npt.NDArray[np.float32],  # [H, W, 3] lit ground truth
    valid: npt.NDArray[np.bool_],  # [H, W]
    sigma_frac: float = 0.05,
) -> npt.NDArray[np.float32]:  # [H, W, 3]
    """Give an albedo render the scene's low-frequency light, as a fused TSDF mesh has it.

    A TSDF mesh's vertex colours average the lit camera images, so they carry shading but no
    detail finer than a voxel. The ground-truth mesh stores albedo; multiplying it by the ratio
    of the blurred lit image to the blurred albedo render puts the (blurred) light back.
    """
    s = sigma_frac * min(gt.shape[:2])
    lum_gt = _gauss(gt.mean(axis=2), s)
    lum_alb = _gauss(albedo_render.mean(axis=2), s)
    ratio = lum_gt / np.maximum(lum_alb, 1e-3)
    out = np.clip(albedo_render * ratio[:, :, None], 0, 1) * valid[:, :, None]
    return out.astype(np.float32)
