"""Core data types: pinhole intrinsics and posed RGB-D frames, validated once at the boundary.

Conventions used everywhere in gsfix-online:
- ``T_world_cam`` is a 4x4 float64 camera-to-world transform, camera axes OpenCV
  (x right, y down, z forward).
- depth is float32 metres, 0 marks an invalid pixel.
- colour is uint8, HxWx3 RGB or HxW grayscale (the ship rig records grayscale).
- ``stamp_ns`` is int64 nanoseconds of sensor time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

ROTATION_ATOL = (
    1e-4  # max |R^T R - I| entry accepted as orthonormal (float32 round trips stay ~1e-7)
)


class FrameError(ValueError):
    """A frame, pose or intrinsics failed validation."""


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels, for an image of ``width`` x ``height``."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        if not all(map(math.isfinite, (self.fx, self.fy, self.cx, self.cy))):
            raise FrameError(
                f"intrinsics must be finite, got fx={self.fx} fy={self.fy} cx={self.cx} cy={self.cy}"
            )
        if (
            int(self.width) != self.width
            or int(self.height) != self.height
            or self.width <= 0
            or self.height <= 0
        ):
            raise FrameError(
                f"intrinsics image size must be positive integers, got {self.width}x{self.height}"
            )
        if self.fx <= 0 or self.fy <= 0:
            raise FrameError(
                f"intrinsics focal lengths must be positive, got fx={self.fx} fy={self.fy}"
            )
        # The principal point may sit a little outside the image (cropped sensors), never far.
        if not (
            -0.5 * self.width <= self.cx <= 1.5 * self.width
            and -0.5 * self.height <= self.cy <= 1.5 * self.height
        ):
            raise FrameError(
                f"intrinsics principal point ({self.cx}, {self.cy}) is far outside the {self.width}x{self.height} image"
            )
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def K(self) -> npt.NDArray[np.float64]:  # [3, 3] pixels
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def from_K(cls, K: npt.ArrayLike, width: int, height: int) -> Intrinsics:
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise FrameError(f"K must be [3, 3], got {list(K.shape)}")
        # Scalar checks: a 3x3 is cheaper in Python floats than in NumPy calls (once per frame).
        (fx, s, cx), (zero, fy, cy), last = K.tolist()
        if max(abs(s), abs(zero), abs(last[0]), abs(last[1]), abs(last[2] - 1.0)) > 1e-9:
            raise FrameError(f"K must be [[fx,0,cx],[0,fy,cy],[0,0,1]], got {K.tolist()}")
        return cls(fx, fy, cx, cy, width, height)

    def scaled(self, width: int, height: int) -> Intrinsics:
        """Intrinsics for the same camera resampled to ``width`` x ``height`` (pixel-centre convention)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            self.fx * sx,
            self.fy * sy,
            (self.cx + 0.5) * sx - 0.5,
            (self.cy + 0.5) * sy - 0.5,
            width,
            height,
        )


def check_pose(T: npt.ArrayLike, name: str = "T_world_cam") -> npt.NDArray[np.float64]:
    """Return ``T`` as float64 [4, 4] (a copy) or raise a one-line FrameError.

    Rejects NaN or inf, a last row other than [0, 0, 0, 1], a rotation that is not orthonormal
    (max |R^T R - I| entry above ROTATION_ATOL) and a reflection (det R < 0). The checks run on
    Python floats: for a 4x4 that is several times faster than NumPy calls, and it runs per frame.
    """
    T = np.asarray(T)
    if T.shape != (4, 4):
        raise FrameError(f"{name} must be [4, 4], got {list(T.shape)}")
    if not np.issubdtype(T.dtype, np.floating):
        raise FrameError(f"{name} must be floating point, got {T.dtype}")
    T = T.astype(np.float64)
    (a, b, c, x), (d, e, f, y), (g, h, i, z), last = T.tolist()
    if not all(map(math.isfinite, (a, b, c, x, d, e, f, y, g, h, i, z, *last))):
        raise FrameError(f"{name} contains NaN or inf")
    if max(abs(last[0]), abs(last[1]), abs(last[2]), abs(last[3] - 1.0)) > 1e-9:
        raise FrameError(f"{name} last row must be [0, 0, 0, 1], got {last}")
    # R^T R - I is symmetric: its diagonal and upper triangle (columns' norms and dot products).
    err = max(
        abs(a * a + d * d + g * g - 1.0),
        abs(b * b + e * e + h * h - 1.0),
        abs(c * c + f * f + i * i - 1.0),
        abs(a * b + d * e + g * h),
        abs(a * c + d * f + g * i),
        abs(b * c + e * f + h * i),
    )
    if err > ROTATION_ATOL:
        raise FrameError(
            f"{name} rotation is not orthonormal (max |R^T R - I| = {err:.2e} > {ROTATION_ATOL:g})"
        )
    if a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) < 0:
        raise FrameError(f"{name} rotation is a reflection (det < 0)")
    return T


def sanitize_depth(depth: npt.NDArray[np.float32]) -> tuple[npt.NDArray[np.float32], int]:
    """Set NaN, inf and negative depths to 0 (invalid); return the depth and how many were set."""
    if depth.size and depth.min() >= 0 and depth.max() < np.inf:  # min is NaN if any pixel is
        return depth, 0  # the usual case, in two reductions instead of four passes and a count
    bad = ~np.isfinite(depth) | (depth < 0)
    n = int(np.count_nonzero(bad))
    if n:
        depth = depth.copy()
        depth[bad] = 0.0
    return depth, n


class ImageSize:
    """Size and colour mode of a frame holding ``color`` and ``intrinsics`` (RGBDFrame, CameraFrame)."""

    color: npt.NDArray[np.uint8]
    intrinsics: Intrinsics

    @property
    def height(self) -> int:
        return self.intrinsics.height

    @property
    def width(self) -> int:
        return self.intrinsics.width

    @property
    def is_gray(self) -> bool:
        return self.color.ndim == 2


@dataclass(frozen=True, eq=False)
class RGBDFrame(ImageSize):
    """A posed RGB-D frame. Build it with :func:`make_frame`, which validates every field."""

    color: npt.NDArray[np.uint8]  # [H, W, 3] RGB or [H, W] grayscale
    depth: npt.NDArray[np.float32]  # [H, W] metres, 0 = invalid
    intrinsics: Intrinsics
    T_world_cam: npt.NDArray[np.float64]  # [4, 4] camera-to-world, OpenCV axes
    stamp_ns: int
    frame_id: str = "camera"
    seq: int = 0
    n_depth_invalidated: int = field(default=0, compare=False)  # NaN/inf/negative pixels set to 0

    def with_pose(self, T_world_cam: npt.ArrayLike) -> RGBDFrame:
        return replace(self, T_world_cam=check_pose(T_world_cam))


def check_images(
    color: np.ndarray,  # [H, W, 3] or [H, W] uint8
    depth: np.ndarray,  # [H, W] float32 metres
    intrinsics: Intrinsics,
    stamp_ns: object,
) -> None:
    """The checks every frame type shares: dtypes, shapes, matching sizes and an integer stamp."""
    if not isinstance(intrinsics, Intrinsics):
        raise FrameError(f"intrinsics must be an Intrinsics, got {type(intrinsics).__name__}")
    if color.dtype != np.uint8 or not (
        color.ndim == 2 or (color.ndim == 3 and color.shape[2] == 3)
    ):
        raise FrameError(
            f"color must be uint8 [H, W, 3] or [H, W], got {color.dtype} {list(color.shape)}"
        )
    if depth.dtype != np.float32 or depth.ndim != 2:
        raise FrameError(
            f"depth must be float32 [H, W] metres, got {depth.dtype} {list(depth.shape)}"
        )
    if color.shape[:2] != depth.shape:
        raise FrameError(
            f"color {list(color.shape[:2])} and depth {list(depth.shape)} sizes differ"
        )
    if (intrinsics.height, intrinsics.width) != depth.shape:
        raise FrameError(
            f"intrinsics are for {intrinsics.width}x{intrinsics.height}, images are {depth.shape[1]}x{depth.shape[0]}"
        )
    if isinstance(stamp_ns, (bool, float)) or not isinstance(stamp_ns, (int, np.integer)):
        raise FrameError(
            f"stamp_ns must be an integer (nanoseconds), got {type(stamp_ns).__name__}"
        )


def make_frame(
    color: npt.ArrayLike,
    depth: npt.ArrayLike,
    intrinsics: Intrinsics,
    T_world_cam: npt.ArrayLike,
    stamp_ns: int,
    frame_id: str = "camera",
    seq: int = 0,
) -> RGBDFrame:
    """Validate inputs and build an :class:`RGBDFrame`.

    Raises FrameError (one line) for wrong shapes or dtypes, a bad pose or intrinsics that do not
    match the images. NaN, inf and negative depth pixels are set to 0 and counted in
    ``frame.n_depth_invalidated``: they are common in real sensor data and not a reason to drop a frame.
    """
    color = np.asarray(color)
    depth = np.asarray(depth)
    check_images(color, depth, intrinsics, stamp_ns)
    if not isinstance(frame_id, str) or not frame_id:
        raise FrameError(f"frame_id must be a non-empty string, got {frame_id!r}")
    T = check_pose(T_world_cam)
    depth, n_bad = sanitize_depth(depth)
    return RGBDFrame(
        color=np.ascontiguousarray(color),
        depth=np.ascontiguousarray(depth),
        intrinsics=intrinsics,
        T_world_cam=T,
        stamp_ns=int(stamp_ns),
        frame_id=frame_id,
        seq=int(seq),
        n_depth_invalidated=n_bad,
    )
