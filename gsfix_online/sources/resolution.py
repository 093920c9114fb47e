"""The processing resolution: frames resized once, where they enter, to at most ``max_width``.

Every reader (:class:`~gsfix_online.sources.base.FrameSource`) and the live camera nodes go
through :func:`at_processing_resolution`, so the maps, fine-tuning and repair all work at one
resolution while the input files stay untouched. Three rules keep a resized frame the same
camera:

- colour is area-averaged (``cv2.INTER_AREA``): each output pixel is the mean of the input
  pixels it covers;
- depth is sampled at the nearest input pixel centre, never averaged: a pixel on an edge takes
  one side's depth, not a depth between the two surfaces, and a valid depth is never mixed
  with an invalid 0;
- intrinsics follow the pixel-centre convention (:meth:`~gsfix_online.core.types.Intrinsics.
  scaled`): ``fx' = fx * sx``, ``cx' = (cx + 0.5) * sx - 0.5`` with ``sx = W' / W`` (and the
  same in y with ``sy = H' / H``), so a 3D point projects to the same place in the image.

The height keeps the aspect ratio, rounded to a multiple of 8 pixels (``SIZE_MULTIPLE``:
1200x680 at max_width 640 is 640x360); ``sy`` is then ``360 / 680``, not exactly ``sx``, and the
intrinsics say so (fx and fy are scaled apart).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import replace
from typing import Literal, TypeVar

import numpy as np
import numpy.typing as npt

from gsfix_online.core.types import RGBDFrame
from gsfix_online.sources.camera import CameraFrame

FrameT = TypeVar("FrameT", RGBDFrame, CameraFrame)


# A resized frame's width and height are multiples of this: GSFixer's fine-tuning takes images
# whose sides are multiples of its codec's downsampling (4 for the packaged model, 8 for Stable
# Diffusion 2's VAE; fixer/train.py refuses others). 1200x680 at 640 is 640x360, not 640x363.
SIZE_MULTIPLE = 8


def processing_size(width: int, height: int, max_width: int) -> tuple[int, int]:
    """(width, height) at which a ``width`` x ``height`` camera is processed: scaled down to
    ``max_width`` keeping the aspect ratio, both sides rounded to a multiple of
    ``SIZE_MULTIPLE`` (the width down, the height to nearest), or unchanged when it is that
    narrow already or ``max_width`` is 0 (no limit). Frames are never upsampled."""
    if max_width < 0:
        raise ValueError(f"max_width must be 0 (no limit) or a width in pixels, got {max_width}")
    if not max_width or width <= max_width:
        return width, height
    m = SIZE_MULTIPLE
    w = max(m, max_width // m * m)
    return w, max(m, round(height * w / width / m) * m)


def resize_color(
    color: npt.NDArray[np.uint8],  # [H, W, 3] RGB or [H, W] grayscale
    width: int,
    height: int,
    mode: Literal["area", "cubic"] = "area",
) -> npt.NDArray[np.uint8]:  # [height, width(, 3)]
    """Colour at ``width`` x ``height``: area-averaged (``cv2.INTER_AREA``) to process a frame
    at a lower resolution, or bicubic (``cv2.INTER_CUBIC``) to deliver a repair at the camera's
    resolution; ``color`` itself when it has that size."""
    import cv2

    if color.shape[:2] == (height, width):
        return color
    flag = cv2.INTER_AREA if mode == "area" else cv2.INTER_CUBIC
    return cv2.resize(color, (width, height), interpolation=flag)


def nearest_index(n_in: int, n_out: int) -> npt.NDArray[np.intp]:  # [n_out]
    """The input pixel whose centre is nearest each output pixel's centre, along one axis:
    output pixel i covers input ``[(i) * n_in / n_out, (i + 1) * n_in / n_out)``, its centre is
    at ``(i + 0.5) * n_in / n_out`` in input pixel units (pixel k spans [k, k + 1))."""
    centre = (np.arange(n_out, dtype=np.float64) + 0.5) * (n_in / n_out)
    return np.minimum(np.floor(centre).astype(np.intp), n_in - 1)


def resize_depth(
    depth_m: npt.NDArray[np.float32],  # [H, W] metres, 0 = invalid
    width: int,
    height: int,
) -> npt.NDArray[np.float32]:  # [height, width] metres, 0 = invalid
    """Depth sampled at the nearest input pixel centre: every output depth is one input depth
    (an edge stays two surfaces; a 0 is never averaged into a valid depth)."""
    h, w = depth_m.shape
    if (h, w) == (height, width):
        return depth_m
    rows, cols = nearest_index(h, height), nearest_index(w, width)
    return np.ascontiguousarray(depth_m[rows[:, None], cols[None, :]])


def at_processing_resolution(frame: FrameT, max_width: int) -> FrameT:
    """``frame`` (posed or not) at its processing resolution (:func:`processing_size`): colour,
    depth and intrinsics resized together; the same object when it needs no resizing."""
    k = frame.intrinsics
    w, h = processing_size(k.width, k.height, max_width)
    if (w, h) == (k.width, k.height):
        return frame
    return replace(
        frame,
        color=resize_color(frame.color, w, h),
        depth=resize_depth(frame.depth, w, h),
        intrinsics=k.scaled(w, h),
    )


def frames_at(frames: Iterable[FrameT], max_width: int) -> Iterator[FrameT]:
    """Every frame of ``frames`` at its processing resolution (the live camera nodes' path)."""
    processing_size(1, 1, max_width)  # a negative max_width fails before the first frame
    for frame in frames:
        yield at_processing_resolution(frame, max_width)
