"""Views to repair: what a planner is asked for (a pose, optionally a camera) and where they come from.

A view list is a TUM pose file, ``timestamp tx ty tz qx qy qz qw`` per line, camera-to-world
(OpenCV axes), numbered from 0 in file order. A view without intrinsics takes the input camera's
(the planner learns it from the first keyframe), at the processing resolution.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt

ViewOrigin = Literal["file", "request", "proposal"]


@dataclass(frozen=True)
class View:
    view_id: int
    T_world_cam: npt.NDArray[np.float64]  # [4, 4] camera-to-world, m
    K: npt.NDArray[np.float64] | None = None  # [3, 3] px; None = the input camera's
    width: int = 0  # 0 = the input camera's
    height: int = 0
    origin: ViewOrigin = "file"

    @property
    def has_camera(self) -> bool:
        return self.K is not None and self.width > 0 and self.height > 0

    def with_camera(self, K: npt.NDArray[np.float64], width: int, height: int) -> View:
        """This view with the given camera, unless it has its own."""
        if self.has_camera:
            return self
        return replace(self, K=np.asarray(K, np.float64), width=int(width), height=int(height))


def read_views(
    path: str | Path,
    K: npt.NDArray[np.float64] | None = None,  # [3, 3] px for every view; None = input camera
    width: int = 0,
    height: int = 0,
) -> list[View]:
    """The views of a TUM pose list, numbered 0.. in file order (stamps are not used: views
    may share one, and they are not sorted)."""
    from gsfix_online.core.se3 import pose_from_tq
    from gsfix_online.sources.base import SourceError

    path = Path(path)
    if not path.is_file():
        raise SourceError(f"view list {path} does not exist (expected a TUM pose list)")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            raise SourceError(f"{path}:{lineno}: pose values must be numbers") from None
        if len(vals) != 8 or not np.all(np.isfinite(vals)) or np.linalg.norm(vals[4:]) < 1e-6:
            raise SourceError(
                f"{path}:{lineno}: expected 'timestamp tx ty tz qx qy qz qw' (finite, unit "
                f"quaternion), got {line.strip()!r}"
            )
        rows.append(vals[1:])
    if not rows:
        raise SourceError(f"view list {path} holds no poses")
    arr = np.asarray(rows, np.float64)
    poses = pose_from_tq(arr[:, :3], arr[:, 3:])
    return [View(i, np.asarray(T, np.float64), K, width, height) for i, T in enumerate(poses)]


def _yaw(T_world_cam: npt.NDArray[np.float64], deg: float) -> npt.NDArray[np.float64]:
    """Turn the camera about its own y axis (OpenCV: down), i.e. look left/right."""
    a = np.deg2rad(deg)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    out = T_world_cam.copy()
    out[:3, :3] = T_world_cam[:3, :3] @ R
    return out


def propose_around(
    T_world_cam: npt.NDArray[np.float64],  # [4, 4] a keyframe's camera-to-world
    yaw_deg: float,
    back_m: float,
) -> list[npt.NDArray[np.float64]]:
    """Views beside a keyframe: stepped back by ``back_m`` along its optical axis and turned by
    +-``yaw_deg``, so they look at the edges of what the keyframe saw (where maps break first)."""
    T = np.asarray(T_world_cam, np.float64).copy()
    T[:3, 3] -= back_m * T[:3, 2]
    return [_yaw(T, yaw_deg), _yaw(T, -yaw_deg)]
