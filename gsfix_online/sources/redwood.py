"""The Redwood / Open3D reconstruction-system layout.

```
SCENE/image/*.jpg|png    colour (a folder named color/ is accepted too), sorted by name
SCENE/depth/*.png        16-bit depth in millimetres (1000 units per metre), sorted by name
SCENE/*.log              trajectory: per frame a line "id id n" then 4 lines of a camera-to-world 4x4
SCENE/intrinsic.json     optional Open3D PinholeCameraIntrinsic: width, height, intrinsic_matrix (column-major)
```
The first id of each ``.log`` entry is the frame index. Frames are stamped index / 30 s.
Without ``intrinsic.json`` the PrimeSense default (525, 525, 319.5, 239.5) is used at 640x480,
otherwise ``source.camera``.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from gsfix_online.core.types import Intrinsics, RGBDFrame, check_pose
from gsfix_online.sources.base import (
    FileItem,
    FileSequenceReader,
    SourceError,
    write_color,
    write_depth_png,
)

DEPTH_SCALE = 1000.0
FPS = 30.0
PRIMESENSE = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
_IMAGE_EXT = (".jpg", ".jpeg", ".png")


def read_log(path: Path) -> dict[int, np.ndarray]:
    """Redwood ``.log`` trajectory -> {frame index: [4, 4] camera-to-world}."""
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    if len(lines) % 5:
        raise SourceError(
            f"redwood: {path}: expected groups of 5 lines (ids + 4x4), got {len(lines)} lines"
        )
    out = {}
    for k in range(0, len(lines), 5):
        head = lines[k]
        if len(head) != 3 or not all(v.lstrip("-").isdigit() for v in head):
            raise SourceError(
                f"redwood: {path}:{k + 1}: expected 'id id n', got {' '.join(head)!r}"
            )
        try:
            M = np.array([[float(v) for v in row] for row in lines[k + 1 : k + 5]])
        except ValueError:
            raise SourceError(f"redwood: {path}:{k + 2}: matrix values must be numbers") from None
        if M.shape != (4, 4):
            raise SourceError(f"redwood: {path}:{k + 2}: expected 4 rows of 4 numbers")
        out[int(head[0])] = check_pose(M, f"{path.name} entry {head[0]}")
    return out


class RedwoodReader(FileSequenceReader):
    format = "redwood"

    def __init__(self, path: str | Path, cfg) -> None:  # noqa: ANN001 - SourceConfig
        super().__init__(path, cfg)
        root = self.path
        img_dir = root / "image" if (root / "image").is_dir() else root / "color"
        if not img_dir.is_dir() or not (root / "depth").is_dir():
            raise SourceError(f"redwood: {root} needs image/ (or color/) and depth/ folders")
        colors = sorted(p for p in img_dir.iterdir() if p.suffix.lower() in _IMAGE_EXT)
        depths = sorted(p for p in (root / "depth").iterdir() if p.suffix.lower() == ".png")
        if len(colors) != len(depths):
            raise SourceError(
                f"redwood: {len(colors)} colour images but {len(depths)} depth images in {root}"
            )
        logs = sorted(root.glob("*.log")) if not cfg.pose_file else [root / cfg.pose_file]
        if len(logs) != 1:
            raise SourceError(
                f"redwood: expected one .log trajectory in {root}, found {len(logs)}; set source.pose_file"
            )
        poses = read_log(logs[0])
        self.items = [
            FileItem(c, d, poses.get(i), int(round(i * 1e9 / FPS)))
            for i, (c, d) in enumerate(zip(colors, depths, strict=True))
        ]
        self.scale = self.depth_scale(DEPTH_SCALE)
        self._intr: Intrinsics | None = None
        if (root / "intrinsic.json").is_file():
            try:
                d = json.loads((root / "intrinsic.json").read_text())
                K = (
                    np.asarray(d["intrinsic_matrix"], dtype=np.float64).reshape(3, 3).T
                )  # stored column-major
                self._intr = Intrinsics.from_K(K, int(d["width"]), int(d["height"]))
            except (KeyError, TypeError, ValueError, json.JSONDecodeError) as exc:
                raise SourceError(
                    f"redwood: {root / 'intrinsic.json'}: expected width, height, intrinsic_matrix ({exc})"
                ) from None

    def intrinsics(self, item: FileItem, width: int, height: int) -> Intrinsics:
        if self.cfg.camera.is_set:
            return self.intrinsics_from_config(width, height)
        if self._intr is not None:
            return self._intr
        if (width, height) == (PRIMESENSE.width, PRIMESENSE.height):
            return PRIMESENSE
        return self.intrinsics_from_config(width, height)


def write_redwood(root: str | Path, frames: Iterable[RGBDFrame], color_ext: str = ".png") -> int:
    """Write frames in the Redwood layout (``image/``, ``depth/`` in mm, ``trajectory.log``, ``intrinsic.json``)."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    n = 0
    with (root / "trajectory.log").open("w") as fl:
        for f in frames:
            write_color(root / "image" / f"{n:06d}{color_ext}", f.color)
            write_depth_png(root / "depth" / f"{n:06d}.png", f.depth, DEPTH_SCALE)
            fl.write(f"{n} {n} {n + 1}\n")
            for row in f.T_world_cam:
                fl.write(" ".join(f"{v:.17g}" for v in row) + "\n")
            if n == 0:
                k = f.intrinsics
                d = {
                    "width": k.width,
                    "height": k.height,
                    "intrinsic_matrix": k.K.T.ravel().tolist(),
                }
                (root / "intrinsic.json").write_text(json.dumps(d, indent=2))
            n += 1
    return n


def looks_like(path: Path) -> bool:
    return (
        path.is_dir()
        and (path / "depth").is_dir()
        and ((path / "image").is_dir() or (path / "color").is_dir())
        and any(path.glob("*.log"))
    )
