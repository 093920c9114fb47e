"""Unposed frames from live RGB-D cameras, shared by the RealSense and OAK sources.

A camera knows its images, intrinsics and capture time, not where it was: the SLAM front end
supplies ``T_world_cam`` later, matched by ``stamp_ns`` in another stage, which turns a
:class:`CameraFrame` into a validated :class:`~gsfix_online.core.types.RGBDFrame` with :meth:`CameraFrame.posed`.

Conventions (as in :mod:`gsfix_online.core.types`): colour is uint8 RGB [H, W, 3] or grayscale [H, W];
depth is float32 metres [H, W] registered to the colour image (same pixels, same intrinsics),
0 = invalid; ``stamp_ns`` is integer nanoseconds of the clock each source documents.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from gsfix_online.core.types import (
    FrameError,
    ImageSize,
    Intrinsics,
    RGBDFrame,
    check_images,
    make_frame,
)

SENSORS_INSTALL = "pip install 'gsfix-online[sensors]'"


@dataclass(frozen=True, eq=False)
class CameraFrame(ImageSize):
    """One colour (or grayscale) image with registered depth, as the camera delivered it: no pose."""

    color: npt.NDArray[np.uint8]  # [H, W, 3] RGB or [H, W] grayscale
    depth: npt.NDArray[np.float32]  # [H, W] metres, 0 = invalid, registered to `color`
    intrinsics: Intrinsics  # pinhole, of `color` (and so of `depth`)
    stamp_ns: int  # capture time, ns; the source's docstring names the clock
    frame_id: str  # optical frame of `color`, e.g. "realsense_color_optical"
    seq: int  # index of this frame in its stream, from 0

    def __post_init__(self) -> None:
        for name in ("color", "depth"):
            if not isinstance(getattr(self, name), np.ndarray):
                raise FrameError(
                    f"{name} must be a numpy array, got {type(getattr(self, name)).__name__}"
                )
        check_images(self.color, self.depth, self.intrinsics, self.stamp_ns)
        object.__setattr__(self, "stamp_ns", int(self.stamp_ns))
        object.__setattr__(self, "seq", int(self.seq))

    def posed(self, T_world_cam: npt.ArrayLike) -> RGBDFrame:  # T_world_cam: [4, 4]
        """The validated, posed frame: NaN/inf/negative depth becomes 0 (counted), as in make_frame."""
        return make_frame(
            self.color,
            self.depth,
            self.intrinsics,
            T_world_cam,
            self.stamp_ns,
            frame_id=self.frame_id,
            seq=self.seq,
        )


@dataclass
class CameraStats:
    """What a live or replayed camera stream did, for logs and reports."""

    frames: int = 0  # frames yielded
    dropped: int = 0  # gaps in the image stream's frame/sequence numbers (camera or host drops)
    timeouts: int = 0  # waits for a frame set that ran out (end-of-recording waits excluded)
    repeated: int = 0  # frame sets that reused an image or depth frame already yielded
    unpaired: int = 0  # frame sets whose image and depth stamps were too far apart
    incomplete: int = 0  # frame sets missing the image or the depth frame

    def as_dict(self) -> dict[str, int]:
        return dict(vars(self))


def depth_units_to_m(
    raw: npt.NDArray[np.uint16],  # [H, W] depth units, 0 = invalid
    metres_per_unit: float,
) -> npt.NDArray[np.float32]:  # [H, W] metres, 0 = invalid
    """uint16 depth in sensor units -> float32 metres (a new array; 0 stays 0)."""
    assert raw.dtype == np.uint16 and raw.ndim == 2, (raw.dtype, raw.shape)
    if not (math.isfinite(metres_per_unit) and metres_per_unit > 0):
        raise FrameError(f"depth units must be positive metres per unit, got {metres_per_unit}")
    return raw.astype(np.float32) * np.float32(metres_per_unit)
