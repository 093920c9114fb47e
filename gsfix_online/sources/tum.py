"""TUM RGB-D layout: ``rgb.txt``, ``depth.txt``, ``groundtruth.txt`` and the image folders.

Lines are ``timestamp path`` (images) or ``timestamp tx ty tz qx qy qz qw`` (camera-to-world poses),
``#`` starts a comment. Colour and depth are matched one-to-one within ``max_assoc_s`` (0.02 s),
poses are interpolated at the colour stamp. Depth PNGs are 16-bit, 5000 units per metre.
Intrinsics come from ``camera.json`` when present (written by gsfix-online), else from the
Freiburg camera named in the folder (freiburg1/2/3), else from ``source.camera``.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt

from gsfix_online.core.se3 import pose_to_tq
from gsfix_online.core.trajectory import Trajectory
from gsfix_online.core.types import Intrinsics, RGBDFrame
from gsfix_online.sources.base import (
    FileItem,
    FileSequenceReader,
    SourceError,
    associate,
    ns_to_seconds,
    seconds_to_ns,
    write_color,
    write_depth_png,
)
from gsfix_online.sources.config import PoseConflicts
from gsfix_online.sources.pose_list import checked_trajectory

DEPTH_SCALE = 5000.0
# Published ROS-default calibrations of the Freiburg Kinects (fx, fy, cx, cy at 640x480).
FREIBURG = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}


def _data_lines(path: Path) -> Iterator[tuple[int, list[str]]]:
    if not path.is_file():
        raise SourceError(f"tum: {path} does not exist")
    with path.open() as fh:
        for lineno, line in enumerate(fh, 1):
            line = line.strip()
            if line and not line.startswith("#"):
                yield lineno, line.replace(",", " ").split()


def read_file_list(path: Path) -> tuple[list[int], list[str]]:
    """``timestamp path`` lines -> (stamps_ns, relative paths)."""
    stamps, paths = [], []
    for lineno, parts in _data_lines(path):
        if len(parts) < 2:
            raise SourceError(
                f"tum: {path}:{lineno}: expected 'timestamp path', got {' '.join(parts)!r}"
            )
        stamps.append(seconds_to_ns(parts[0]))
        paths.append(parts[1])
    return stamps, paths


def read_pose_list(path: Path, conflicts: PoseConflicts = "error") -> Trajectory:
    """``timestamp tx ty tz qx qy qz qw`` lines -> Trajectory (camera-to-world), checked by
    :func:`~gsfix_online.sources.pose_list.checked_trajectory` (unit quaternions, one pose per
    stamp unless ``conflicts`` says which to keep)."""
    stamps, tq, lines = [], [], []
    for lineno, parts in _data_lines(path):
        if len(parts) != 8:
            raise SourceError(
                f"{path}:{lineno}: expected 'timestamp tx ty tz qx qy qz qw', got {len(parts)} fields"
            )
        try:
            vals = [float(v) for v in parts[1:]]
        except ValueError:
            raise SourceError(f"{path}:{lineno}: pose values must be numbers") from None
        stamps.append(seconds_to_ns(parts[0]))
        tq.append(vals)
        lines.append(lineno)
    return checked_trajectory(str(path), stamps, tq, lines, conflicts)


def write_pose_list(
    path: Path, stamps_ns: Sequence[int], poses: npt.ArrayLike, header: str = ""
) -> None:
    """Write camera-to-world poses as TUM lines ``timestamp tx ty tz qx qy qz qw``."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    t, q = pose_to_tq(poses)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as fh:
        fh.write(f"# {header or 'timestamp tx ty tz qx qy qz qw'}\n")
        for s, ti, qi in zip(stamps_ns, t, q, strict=True):
            fh.write(f"{ns_to_seconds(s)} " + " ".join(f"{v:.17g}" for v in (*ti, *qi)) + "\n")


def write_intrinsics_json(path: Path, intr: Intrinsics, depth_scale: float | None = None) -> None:
    data: dict[str, float | int] = dataclasses.asdict(intr)
    if depth_scale is not None:
        data["depth_scale"] = depth_scale
    path.write_text(json.dumps(data, indent=2))


def read_intrinsics_json(path: Path) -> tuple[Intrinsics, float | None]:
    try:
        d = json.loads(path.read_text())
        intr = Intrinsics(
            float(d["fx"]),
            float(d["fy"]),
            float(d["cx"]),
            float(d["cy"]),
            int(d["width"]),
            int(d["height"]),
        )
    except (KeyError, TypeError, ValueError, json.JSONDecodeError) as exc:
        raise SourceError(f"{path}: expected fx, fy, cx, cy, width, height ({exc})") from None
    return intr, (float(d["depth_scale"]) if "depth_scale" in d else None)


class TumReader(FileSequenceReader):
    format = "tum"

    def __init__(self, path: str | Path, cfg) -> None:  # noqa: ANN001 - SourceConfig
        super().__init__(path, cfg)
        root = self.path
        rgb_ns, rgb = read_file_list(root / "rgb.txt")
        depth_ns, depth = read_file_list(root / "depth.txt")
        pairs = associate(rgb_ns, depth_ns, int(cfg.max_assoc_s * 1e9))
        self.n_unpaired = len(rgb_ns) + len(depth_ns) - 2 * len(pairs)
        self.trajectory = read_pose_list(
            root / (cfg.pose_file or "groundtruth.txt"), cfg.pose_conflicts
        )
        gap = int(cfg.max_pose_gap_s * 1e9)
        self.items = [
            FileItem(
                root / rgb[i], root / depth[j], self.trajectory.query(rgb_ns[i], gap), rgb_ns[i]
            )
            for i, j in pairs
        ]
        self._intr: Intrinsics | None = None
        scale = None
        if (root / "camera.json").is_file():
            self._intr, scale = read_intrinsics_json(root / "camera.json")
        self.scale = self.depth_scale(scale or DEPTH_SCALE)
        self._freiburg = next((k for k in FREIBURG if k in root.resolve().name), None)

    def intrinsics(self, item: FileItem, width: int, height: int) -> Intrinsics:
        if self.cfg.camera.is_set:
            return self.intrinsics_from_config(width, height)
        if self._intr is not None:
            return self._intr
        if self._freiburg is not None:
            return Intrinsics(*FREIBURG[self._freiburg], 640, 480).scaled(width, height)
        return self.intrinsics_from_config(width, height)

    def _frames(self) -> Iterator[RGBDFrame]:
        self.stats.unpaired = self.n_unpaired
        yield from super()._frames()


def write_tum(
    root: str | Path,
    frames: Iterable[RGBDFrame],
    depth_scale: float = DEPTH_SCALE,
    pose_file: str = "groundtruth.txt",
) -> int:
    """Write frames in the TUM layout (plus ``camera.json``); returns the number written."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    stamps, poses = [], []
    n = 0
    with (root / "rgb.txt").open("w") as frgb, (root / "depth.txt").open("w") as fdep:
        frgb.write("# timestamp filename\n")
        fdep.write("# timestamp filename\n")
        for f in frames:
            s = ns_to_seconds(f.stamp_ns)
            name = f"{s}.png"
            write_color(root / "rgb" / name, f.color)
            write_depth_png(root / "depth" / name, f.depth, depth_scale)
            frgb.write(f"{s} rgb/{name}\n")
            fdep.write(f"{s} depth/{name}\n")
            if n == 0:
                write_intrinsics_json(root / "camera.json", f.intrinsics, depth_scale)
            stamps.append(f.stamp_ns)
            poses.append(f.T_world_cam)
            n += 1
    write_pose_list(root / pose_file, stamps, np.asarray(poses).reshape(-1, 4, 4))
    return n


def looks_like(path: Path) -> bool:
    return path.is_dir() and (path / "rgb.txt").is_file() and (path / "depth.txt").is_file()
