"""Replica in the NICE-SLAM layout.

```
SCENE/results/frame000000.jpg   colour (.jpg as distributed; .png also accepted)
SCENE/results/depth000000.png   16-bit depth, 6553.5 units per metre
SCENE/traj.txt                  one camera-to-world 4x4 per line, 16 numbers row-major, OpenCV axes
SCENE/../cam_params.json        optional: {"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}}
```
Frames carry no timestamps; frame i is stamped i / 30 s. Without ``cam_params.json`` the
standard Replica camera (1200x680, f = 600, c = (599.5, 339.5)) is used at that image size,
otherwise ``source.camera``.
"""

from __future__ import annotations

import json
import re
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

DEPTH_SCALE = 6553.5
FPS = 30.0
REPLICA_CAMERA = (600.0, 600.0, 599.5, 339.5, 1200, 680)


def _numbered(folder: Path, prefix: str, suffixes: tuple[str, ...]) -> dict[int, Path]:
    pat = re.compile(rf"{prefix}(\d+)$")
    out = {}
    for p in folder.iterdir():
        m = pat.match(p.stem)
        if m and p.suffix.lower() in suffixes:
            out[int(m.group(1))] = p
    return out


def read_matrix_lines(path: Path) -> list[np.ndarray]:
    """Lines of 16 numbers -> list of [4, 4] float64 (row-major)."""
    if not path.is_file():
        raise SourceError(f"{path} does not exist")
    out = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            vals = np.array([float(v) for v in line.split()])
        except ValueError:
            raise SourceError(f"{path}:{lineno}: values must be numbers") from None
        if vals.size != 16:
            raise SourceError(
                f"{path}:{lineno}: expected 16 numbers (a row-major 4x4), got {vals.size}"
            )
        out.append(vals.reshape(4, 4))
    return out


class ReplicaReader(FileSequenceReader):
    format = "replica"

    def __init__(self, path: str | Path, cfg) -> None:  # noqa: ANN001 - SourceConfig
        super().__init__(path, cfg)
        res = self.path / "results"
        if not res.is_dir():
            raise SourceError(f"replica: {res} does not exist")
        colors = _numbered(res, "frame", (".jpg", ".jpeg", ".png"))
        depths = _numbered(res, "depth", (".png",))
        poses = read_matrix_lines(self.path / "traj.txt")
        ids = sorted(set(colors) & set(depths))
        self.stats.unpaired = len(colors) + len(depths) - 2 * len(ids)
        if ids and ids[-1] >= len(poses):
            raise SourceError(
                f"replica: traj.txt has {len(poses)} poses but frames go up to {ids[-1]}"
            )
        self.items = [
            FileItem(
                colors[i],
                depths[i],
                check_pose(poses[i], f"traj.txt line {i + 1}"),
                int(round(i * 1e9 / FPS)),
            )
            for i in ids
        ]
        self._cam: tuple[float, ...] | None = None
        scale = None
        for cand in (self.path / "cam_params.json", self.path.parent / "cam_params.json"):
            if cand.is_file():
                try:
                    c = json.loads(cand.read_text())["camera"]
                    self._cam = (
                        float(c["fx"]),
                        float(c["fy"]),
                        float(c["cx"]),
                        float(c["cy"]),
                        int(c["w"]),
                        int(c["h"]),
                    )
                    scale = float(c["scale"]) if "scale" in c else None
                except (KeyError, TypeError, ValueError, json.JSONDecodeError) as exc:
                    raise SourceError(
                        f"replica: {cand}: expected camera.w/h/fx/fy/cx/cy ({exc})"
                    ) from None
                break
        self.scale = self.depth_scale(scale or DEPTH_SCALE)

    def intrinsics(self, item: FileItem, width: int, height: int) -> Intrinsics:
        if self.cfg.camera.is_set:
            return self.intrinsics_from_config(width, height)
        cam = self._cam or (REPLICA_CAMERA if (width, height) == REPLICA_CAMERA[4:] else None)
        if cam is None:
            return self.intrinsics_from_config(width, height)
        return Intrinsics(*cam[:4], int(cam[4]), int(cam[5])).scaled(width, height)


def write_replica(root: str | Path, frames: Iterable[RGBDFrame], color_ext: str = ".jpg") -> int:
    """Write frames in the NICE-SLAM Replica layout with a ``cam_params.json`` beside ``results/``."""
    root = Path(root)
    (root / "results").mkdir(parents=True, exist_ok=True)
    n = 0
    with (root / "traj.txt").open("w") as ft:
        for f in frames:
            write_color(root / "results" / f"frame{n:06d}{color_ext}", f.color)
            write_depth_png(root / "results" / f"depth{n:06d}.png", f.depth, DEPTH_SCALE)
            ft.write(" ".join(f"{v:.17g}" for v in f.T_world_cam.ravel()) + "\n")
            if n == 0:
                k = f.intrinsics
                cam = {
                    "w": k.width,
                    "h": k.height,
                    "fx": k.fx,
                    "fy": k.fy,
                    "cx": k.cx,
                    "cy": k.cy,
                    "scale": DEPTH_SCALE,
                }
                (root / "cam_params.json").write_text(json.dumps({"camera": cam}, indent=2))
            n += 1
    return n


def looks_like(path: Path) -> bool:
    return path.is_dir() and (path / "results").is_dir() and (path / "traj.txt").is_file()
