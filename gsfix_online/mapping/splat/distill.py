"""Distillation's inputs: a repaired view as a frame, its anchor, the masks it is fitted on.

:meth:`Mapper.distill` fits the map to a repaired view (GSFixer's output at a novel pose). This
module prepares what it fits: the view checked and made a frame in the map's colour
(:func:`repaired_frame`), and, with ``distill_anchor``, the anchor (:func:`anchor`): the map's
own render without distillation's seeds where it shows a surface outside the repair's mask, so
that seeds grown for other views that veil it are pulled away. The seeds (growth from the mesh
depth) and the fit are the mapper's; carving of seeds is :mod:`.carving`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from gsfix_online.core.types import Intrinsics, RGBDFrame, make_frame
from gsfix_online.mapping.splat.render_output import RenderOutput
from gsfix_online.mapping.splat.views import REPAIRED_FRAME_ID, check_size


@dataclass(frozen=True)
class RepairedView:
    """A repaired view ready to distil."""

    frame: RGBDFrame  # the image (anchored where anchored) with the seed depth (0 = no seed)
    # what the keyframe store keeps (anchored: the anchor's surface as depth); None = ``frame``
    stored: RGBDFrame | None
    mask: npt.NDArray[np.bool_] | None  # [H, W] the pixels it is fitted on; None = all


def repaired_frame(
    image: npt.NDArray[np.uint8],  # [H, W, 3] RGB (or [H, W]) repaired view
    T_world_cam: npt.ArrayLike,  # [4, 4]
    K: npt.ArrayLike,  # [3, 3] px
    channels: int,  # the map's: a grayscale map takes the luma
    train_downscale: int,
    mask: npt.NDArray[Any] | None = None,  # [H, W]: nonzero = repaired pixels; None = all
    stamp_ns: int = 0,
    depth: npt.NDArray[np.float32] | None = None,  # [H, W] m, 0 = unknown (mesh render)
) -> RepairedView:
    """Check a repaired view and make it a frame in the map's colour, its seed depth the
    given depth (zero without one); raises ValueError on a bad image, mask or depth."""
    img = np.asarray(image)
    if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
        raise ValueError(
            f"image must be uint8 [H, W, 3] or [H, W], got {img.dtype} {list(img.shape)}"
        )
    H, W = img.shape[:2]
    check_size(H, W, train_downscale)
    if channels == 1 and img.ndim == 3:
        img = np.rint(img.astype(np.float32) @ np.float32([0.299, 0.587, 0.114])).astype(np.uint8)
    elif channels == 3 and img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if mask is not None and np.asarray(mask).shape != (H, W):
        raise ValueError(f"mask must be [{H}, {W}], got {list(np.asarray(mask).shape)}")
    if depth is not None:
        depth = np.asarray(depth)
        if depth.dtype != np.float32 or depth.shape != (H, W):
            raise ValueError(
                f"depth must be float32 [{H}, {W}] m, got {depth.dtype} {list(depth.shape)}"
            )
    intr = Intrinsics.from_K(K, width=W, height=H)
    seed_depth = np.zeros((H, W), np.float32) if depth is None else depth
    frame = make_frame(img, seed_depth, intr, T_world_cam, stamp_ns, frame_id=REPAIRED_FRAME_ID)
    return RepairedView(frame, None, None if mask is None else np.asarray(mask) != 0)


def anchor(
    view: RepairedView,
    unseeded: RenderOutput,  # the map without distillation's seeds at the view's pose
    min_alpha: float = 0.5,
) -> RepairedView:
    """The view anchored: outside its mask, where the map renders a surface, the image is the
    map's render (fitted there, other views' seeds that veil it are pulled away); seeds only
    in the holes; the store keeps the anchor's surface as depth, for carving seeds in front of
    it. The view is fitted on holes | anchored."""
    assert view.mask is not None
    f = view.frame
    img, seed_depth = f.color, f.depth
    color0 = unseeded.color.clamp(0, 1).cpu().numpy()
    holes = view.mask
    anchored = (unseeded.alpha.cpu().numpy() >= min_alpha) & ~holes
    if color0.shape[-1] == 1:
        color0 = color0[..., 0]
    anchor_img = np.rint(color0 * 255).astype(np.uint8)
    img = np.where(anchored[..., None] if img.ndim == 3 else anchored, anchor_img, img)
    stored = make_frame(img, np.where(anchored, unseeded.depth.cpu().numpy(), np.float32(0)),
                        f.intrinsics, f.T_world_cam, f.stamp_ns, frame_id=REPAIRED_FRAME_ID)  # fmt: skip
    seed_depth = np.where(holes, seed_depth, np.float32(0))  # seeds only in the holes
    frame = make_frame(img, seed_depth, f.intrinsics, f.T_world_cam, f.stamp_ns,
                       frame_id=REPAIRED_FRAME_ID)  # fmt: skip
    return RepairedView(frame, stored, holes | anchored)
