"""ScanNet++ iPhone captures, after the official frame and depth extraction.

```
SCENE/iphone/rgb/frame_000000.jpg        colour (1920x1440 as captured; .png also accepted)
SCENE/iphone/depth/frame_000000.png      16-bit depth in millimetres (256x192 as captured)
SCENE/iphone/pose_intrinsic_imu.json     {"frame_000000": {"aligned_pose": 4x4, "intrinsic": 3x3, "timestamp": s}}
```
``SCENE`` or ``SCENE/iphone`` may be given. ``aligned_pose`` is camera-to-world with ARKit
camera axes (y up, z backward); it is converted to OpenCV axes by flipping y and z. Colour is
resized to the depth resolution and the intrinsics (given for the colour image) scaled with it.
Frames without a ``timestamp`` are stamped index / 60 s.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from gsfix_online.core.types import RGBDFrame, check_pose
from gsfix_online.sources.base import (
    FileItem,
    FileSequenceReader,
    SourceError,
    write_color,
    write_depth_png,
)

DEPTH_SCALE = 1000.0
FPS = 60.0
ARKIT_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips camera y and z (its own inverse)


def _iphone_dir(path: Path) -> Path:
    return path / "iphone" if (path / "iphone" / "pose_intrinsic_imu.json").is_file() else path


class ScannetppReader(FileSequenceReader):
    format = "scannetpp"
    resize_color_to_depth = True

    def __init__(self, path: str | Path, cfg) -> None:  # noqa: ANN001 - SourceConfig
        super().__init__(path, cfg)
        root = _iphone_dir(self.path)
        meta_path = root / "pose_intrinsic_imu.json"
        try:
            meta = json.loads(meta_path.read_text())
        except FileNotFoundError:
            raise SourceError(f"scannetpp: {meta_path} does not exist") from None
        except json.JSONDecodeError as exc:
            raise SourceError(f"scannetpp: {meta_path}: not valid JSON ({exc})") from None
        self.items = []
        for i, name in enumerate(sorted(meta)):
            entry = meta[name]
            color = next(
                (
                    root / "rgb" / f"{name}{ext}"
                    for ext in (".jpg", ".png")
                    if (root / "rgb" / f"{name}{ext}").is_file()
                ),
                None,
            )
            depth = root / "depth" / f"{name}.png"
            if color is None or not depth.is_file():
                self.stats.unpaired += 1
                continue
            try:
                T = check_pose(
                    np.asarray(entry["aligned_pose"], dtype=np.float64) @ ARKIT_TO_OPENCV,
                    f"{name}.aligned_pose",
                )
                K = np.asarray(entry["intrinsic"], dtype=np.float64)
            except (KeyError, TypeError, ValueError) as exc:
                raise SourceError(
                    f"scannetpp: {meta_path}: {name}: needs aligned_pose and intrinsic ({exc})"
                ) from None
            stamp = (
                int(round(float(entry["timestamp"]) * 1e9))
                if "timestamp" in entry
                else int(round(i * 1e9 / FPS))
            )
            self.items.append(FileItem(color, depth, T, stamp, K))
        self._n_unpaired = self.stats.unpaired
        self.scale = self.depth_scale(DEPTH_SCALE)

    def _frames(self) -> Iterator[RGBDFrame]:
        self.stats.unpaired = self._n_unpaired
        yield from super()._frames()


def write_scannetpp(root: str | Path, frames: Iterable[RGBDFrame], color_ext: str = ".png") -> int:
    """Write frames in the ScanNet++ iPhone layout under ``root/iphone``."""
    root = Path(root) / "iphone"
    meta = {}
    n = 0
    for f in frames:
        name = f"frame_{n:06d}"
        write_color(root / "rgb" / f"{name}{color_ext}", f.color)
        write_depth_png(root / "depth" / f"{name}.png", f.depth, DEPTH_SCALE)
        meta[name] = {
            "aligned_pose": (f.T_world_cam @ ARKIT_TO_OPENCV).tolist(),
            "intrinsic": f.intrinsics.K.tolist(),
            "timestamp": f.stamp_ns / 1e9,
        }
        n += 1
    root.mkdir(parents=True, exist_ok=True)
    (root / "pose_intrinsic_imu.json").write_text(json.dumps(meta))
    return n


def looks_like(path: Path) -> bool:
    return (_iphone_dir(path) / "pose_intrinsic_imu.json").is_file()
