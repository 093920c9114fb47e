"""OKVIS2 trajectories joined to RGB-D image folders.

```
SEQ/trajectory.csv       OKVIS2 CSV: header, then timestamp (ns), p_WS_W_x..z, q_WS_x..w[, velocities, biases]
SEQ/rgb/<stamp_ns>.png   colour images named by their stamp in nanoseconds
SEQ/depth/<stamp_ns>.png 16-bit depth, 1000 units per metre (source.depth_scale to change)
SEQ/camera.json          intrinsics (fx, fy, cx, cy, width, height), else source.camera
```
OKVIS2 estimates the pose of the IMU (sensor) frame S, so ``source.T_SC`` (the camera pose in
S, 16 numbers row-major) is required: ``T_world_cam = T_WS @ T_SC``. Poses are interpolated at
the colour stamps (SE(3), at most ``source.max_pose_gap_s`` apart); colour and depth pair within
``source.max_assoc_s``. ``source.pose_file`` names the CSV when the folder holds several.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy.typing as npt

from gsfix_online.core.se3 import inv_T, pose_to_tq
from gsfix_online.core.trajectory import Trajectory
from gsfix_online.core.types import Intrinsics, RGBDFrame
from gsfix_online.sources.base import (
    FileItem,
    FileSequenceReader,
    SourceError,
    associate,
    write_color,
    write_depth_png,
)
from gsfix_online.sources.config import PoseConflicts
from gsfix_online.sources.pose_list import checked_trajectory
from gsfix_online.sources.tum import read_intrinsics_json, write_intrinsics_json

DEPTH_SCALE = 1000.0
COLUMNS = ["timestamp", "p_WS_W_x", "p_WS_W_y", "p_WS_W_z", "q_WS_x", "q_WS_y", "q_WS_z", "q_WS_w"]
EXTRA = ["v_WS_W_x", "v_WS_W_y", "v_WS_W_z", "b_g_x", "b_g_y", "b_g_z", "b_a_x", "b_a_y", "b_a_z"]


def read_okvis_csv(path: Path, conflicts: PoseConflicts = "error") -> Trajectory:
    """OKVIS2 CSV -> Trajectory of T_WS (IMU-to-world). Columns are found by header name."""
    if not path.is_file():
        raise SourceError(f"okvis: {path} does not exist")
    with path.open(newline="") as fh:
        rows = csv.reader(fh)
        header = [h.strip().lstrip("#").strip() for h in next(rows, [])]
        missing = [c for c in COLUMNS if c not in header]
        if missing:
            raise SourceError(f"okvis: {path}: header lacks columns {missing} (has {header})")
        idx = [header.index(c) for c in COLUMNS]
        stamps, vals, lines = [], [], []
        for lineno, row in enumerate(rows, 2):
            if not row or not "".join(row).strip():
                continue
            try:
                stamps.append(int(row[idx[0]].strip()))
                vals.append([float(row[i]) for i in idx[1:]])
                lines.append(lineno)
            except (ValueError, IndexError):
                raise SourceError(
                    f"okvis: {path}:{lineno}: expected integer ns stamp and 7 numbers"
                ) from None
    if not vals:
        raise SourceError(f"okvis: {path} has no poses")
    return checked_trajectory(f"okvis: {path}", stamps, vals, lines, conflicts)


def _stamped_images(folder: Path) -> dict[int, Path]:
    if not folder.is_dir():
        raise SourceError(f"okvis: {folder} does not exist")
    out = {}
    for p in folder.iterdir():
        if p.suffix.lower() in (".png", ".jpg", ".jpeg") and p.stem.isdigit():
            out[int(p.stem)] = p
    return out


class OkvisReader(FileSequenceReader):
    format = "okvis"

    def __init__(self, path: str | Path, cfg) -> None:  # noqa: ANN001 - SourceConfig
        super().__init__(path, cfg)
        if not cfg.T_SC:
            raise SourceError(
                "okvis: source.T_SC must be set (camera pose in the IMU frame, 16 numbers row-major)"
            )
        csv_path = self.path / cfg.pose_file if cfg.pose_file else _find_csv(self.path)
        self.trajectory = read_okvis_csv(csv_path, cfg.pose_conflicts).transformed(self.T_SC())
        rgb = _stamped_images(self.path / "rgb")
        depth = _stamped_images(self.path / "depth")
        rgb_ns, depth_ns = sorted(rgb), sorted(depth)
        pairs = associate(rgb_ns, depth_ns, int(cfg.max_assoc_s * 1e9))
        self._n_unpaired = len(rgb) + len(depth) - 2 * len(pairs)
        gap = int(cfg.max_pose_gap_s * 1e9)
        self.items = [
            FileItem(
                rgb[rgb_ns[i]], depth[depth_ns[j]], self.trajectory.query(rgb_ns[i], gap), rgb_ns[i]
            )
            for i, j in pairs
        ]
        self.scale = self.depth_scale(DEPTH_SCALE)
        self._intr = (
            read_intrinsics_json(self.path / "camera.json")[0]
            if (self.path / "camera.json").is_file()
            else None
        )

    def intrinsics(self, item: FileItem, width: int, height: int) -> Intrinsics:
        if self._intr is not None and not self.cfg.camera.is_set:
            return self._intr
        return self.intrinsics_from_config(width, height)

    def _frames(self) -> Iterator[RGBDFrame]:
        self.stats.unpaired = self._n_unpaired
        yield from super()._frames()


def _find_csv(root: Path) -> Path:
    cands = sorted(root.glob("*.csv"))
    if len(cands) != 1:
        raise SourceError(
            f"okvis: expected one trajectory .csv in {root}, found {len(cands)}; set source.pose_file"
        )
    return cands[0]


def write_okvis(
    root: str | Path,
    frames: Iterable[RGBDFrame],
    T_SC: npt.ArrayLike,
    depth_scale: float = DEPTH_SCALE,
) -> int:
    """Write frames as an OKVIS2 CSV of IMU poses (T_WS = T_world_cam @ inv(T_SC)) plus image folders."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    T_CS = inv_T(T_SC)
    n = 0
    with (root / "trajectory.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(COLUMNS + EXTRA)
        for f in frames:
            write_color(root / "rgb" / f"{f.stamp_ns}.png", f.color)
            write_depth_png(root / "depth" / f"{f.stamp_ns}.png", f.depth, depth_scale)
            t, q = pose_to_tq(f.T_world_cam @ T_CS)
            w.writerow([f.stamp_ns, *(f"{v:.17g}" for v in (*t, *q)), *(["0"] * len(EXTRA))])
            if n == 0:
                write_intrinsics_json(root / "camera.json", f.intrinsics)
            n += 1
    return n


def looks_like(path: Path) -> bool:
    return (
        path.is_dir()
        and (path / "rgb").is_dir()
        and (path / "depth").is_dir()
        and any(path.glob("*.csv"))
    )
