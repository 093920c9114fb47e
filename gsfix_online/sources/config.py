"""Configuration of frame sources (dataset readers, bags, MCAP logs) and replay."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from gsfix_online.core.config import rng

SourceFormat = Literal["auto", "tum", "replica", "redwood", "scannetpp", "okvis", "rosbag", "mcap"]
PoseSource = Literal["auto", "pose", "tf", "none"]
PoseConflicts = Literal["error", "first"]


@dataclass(frozen=True)
class CameraConfig:
    """Intrinsics override: when set (fx, fy > 0) it replaces the dataset's own; needed where a dataset has none."""

    fx: float = field(default=0.0, metadata=rng(0, None, "focal length x, pixels"))
    fy: float = field(default=0.0, metadata=rng(0, None, "focal length y, pixels"))
    cx: float = field(default=0.0, metadata=rng(None, None, "principal point x, pixels"))
    cy: float = field(default=0.0, metadata=rng(None, None, "principal point y, pixels"))

    @property
    def is_set(self) -> bool:
        return self.fx > 0 and self.fy > 0


@dataclass(frozen=True)
class SourceConfig:
    """Where frames come from and how to read them."""

    format: SourceFormat = "auto"  # auto = detect from the files at `path`
    path: str = ""  # dataset folder, bag file or folder, or .mcap log
    depth_scale: float = field(
        default=0.0, metadata=rng(0, None, "raw depth units per metre; 0 = the format's own")
    )
    # a depth_scale that makes the median depth of every one of the first frames implausible
    # (under 0.1 m or over 30 m) is refused unless forced
    force_depth_scale: bool = False
    camera: CameraConfig = field(default_factory=CameraConfig)
    max_assoc_s: float = field(
        default=0.02, metadata=rng(0, 10, "max colour/depth time difference, s")
    )
    max_pose_gap_s: float = field(
        default=0.1, metadata=rng(0, 3600, "max gap between poses to interpolate, s")
    )
    # two different poses listed at one stamp: an error, or keep the first listed (warned)
    pose_conflicts: PoseConflicts = "error"
    pose_file: str = ""  # TUM/OKVIS: pose list relative to `path` (TUM default groundtruth.txt)
    # Camera pose in the tracked frame (IMU/body): T_world_cam = T_world_S @ T_SC; 16 numbers row-major.
    # Empty = identity, except for OKVIS trajectories, which are IMU poses and require it.
    T_SC: list[float] = field(default_factory=list)
    stride: int = field(default=1, metadata=rng(1, None, "use every n-th frame"))
    max_frames: int = field(
        default=0, metadata=rng(0, None, "stop after this many frames; 0 = all")
    )
    # The processing resolution: wider frames are resized where they are read (colour area-
    # averaged, depth nearest, intrinsics scaled; sources/resolution.py) to this width, the
    # height keeping the aspect ratio; the input files stay untouched. The repair graph sets
    # 640 (benchmarks/results/processing_resolution_cpu.md).
    max_width: int = field(
        default=0, metadata=rng(0, None, "process frames at most this wide, px; 0 = as read")
    )
    # Bags (ROS1 .bag, ROS2 db3/MCAP):
    color_topic: str = "/camera/color/image_raw"
    depth_topic: str = "/camera/aligned_depth_to_color/image_raw"
    camera_info_topic: str = "/camera/color/camera_info"
    pose_source: PoseSource = "auto"  # auto: pose_topic if present in the bag, else tf
    pose_topic: str = "/pose"  # geometry_msgs/PoseStamped
    tf_parent: str = "map"  # tf: transform parent -> child gives T_world_S
    tf_child: str = "camera_link"

    def validate(self) -> None:
        if self.T_SC and len(self.T_SC) != 16:
            raise ValueError(f"T_SC must have 16 numbers (row-major 4x4), got {len(self.T_SC)}")


@dataclass(frozen=True)
class ReplayConfig:
    """Replay speed: `realtime` follows the stamps, `max` goes as fast as the consumer takes frames."""

    mode: Literal["realtime", "max"] = "max"
    speed: float = field(
        default=1.0, metadata=rng(1e-3, 1e3, "realtime mode: multiple of real time")
    )
    # Held-out evaluation (`gsfix-online repair --holdout K`): frames with index % K == K // 2
    # are not replayed; the repair command scores every stage at them against the real images.
    holdout_every: int = field(
        default=0, metadata=rng(0, 100_000, "keep every K-th frame out of the replay; 0 = none")
    )
