"""Pairs camera frames (no pose) with poses from a SLAM front end, by timestamp.

Poses arrive on their own stream, usually a little after the frames they belong to. A frame waits
until a pose at or after its stamp has arrived, then gets the SE(3) interpolation of the two
bracketing poses (times the extrinsic ``T_SC``: the camera pose in the tracked frame). A frame is
reported unpaired when the bracketing poses are more than ``max_gap_s`` apart, when it is older
than the pose history, or when no pose at or after it arrived while the stream (frames or poses)
moved ``max_wait_s`` past it, e.g. because the SLAM front end lost track.

Time is data time: decisions use the stamps of the frames and poses received, never a wall clock,
so replays at any speed pair the same way.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from gsfix_online.core.config import rng
from gsfix_online.core.se3 import interpolate_pose
from gsfix_online.core.types import RGBDFrame, check_pose


class UnposedFrame(Protocol):
    stamp_ns: int

    def posed(self, T_world_cam: npt.NDArray[np.float64]) -> RGBDFrame: ...


@dataclass(frozen=True)
class PoseAssociationConfig:
    max_gap_s: float = field(
        default=0.1, metadata=rng(0.0, 60.0, "max time between bracketing poses, s")
    )
    max_wait_s: float = field(
        default=0.5, metadata=rng(0.0, 60.0, "poses this far past a frame end its wait, s")
    )
    history_s: float = field(default=30.0, metadata=rng(0.1, 3600.0, "pose history kept, s"))
    max_pending: int = field(
        default=64, metadata=rng(1, 100_000, "frames waiting for a pose; older ones are dropped")
    )
    T_SC: list[float] = field(
        default_factory=list
    )  # camera pose in the tracked frame, 16 numbers row-major

    def validate(self) -> None:
        if self.T_SC and len(self.T_SC) != 16:
            raise ValueError(f"T_SC must have 16 numbers (row-major 4x4), got {len(self.T_SC)}")


@dataclass
class AssociationStats:
    paired: int = 0
    too_old: int = 0  # frame older than the pose history
    gap: int = 0  # bracketing poses farther apart than max_gap_s
    timed_out: int = 0  # no pose at or after the frame while the stream moved max_wait_s past it
    overflow: int = 0  # more than max_pending frames waiting
    poses_out_of_order: int = 0  # poses older than the newest one, ignored

    @property
    def unpaired(self) -> int:
        return self.too_old + self.gap + self.timed_out + self.overflow


@dataclass
class PoseAssociator:
    """Stateful pairing stage. ``add_pose`` and ``add_frame`` return the frames that became ready."""

    cfg: PoseAssociationConfig
    stats: AssociationStats = field(default_factory=AssociationStats)

    def __post_init__(self) -> None:
        self._T_SC = (
            np.asarray(self.cfg.T_SC, dtype=np.float64).reshape(4, 4)
            if self.cfg.T_SC
            else np.eye(4)
        )
        self._stamps: deque[int] = deque()
        self._poses: deque[npt.NDArray[np.float64]] = deque()
        self._pending: deque[UnposedFrame] = deque()
        self._latest_ns: int | None = None  # newest stamp seen on either stream: the data clock

    def _tick(self, stamp_ns: int) -> None:
        self._latest_ns = stamp_ns if self._latest_ns is None else max(self._latest_ns, stamp_ns)

    def add_pose(self, stamp_ns: int, T_world_S: npt.ArrayLike) -> list[RGBDFrame]:
        """A pose of the tracked frame S; invalid poses raise FrameError (checked once, here)."""
        T = check_pose(T_world_S, "T_world_S")
        self._tick(int(stamp_ns))
        if self._stamps and stamp_ns <= self._stamps[-1]:
            self.stats.poses_out_of_order += 1
            return []
        self._stamps.append(int(stamp_ns))
        self._poses.append(T)
        horizon = stamp_ns - int(self.cfg.history_s * 1e9)
        while len(self._stamps) > 2 and self._stamps[1] < horizon:
            self._stamps.popleft()
            self._poses.popleft()
        return self._drain()

    def add_frame(self, frame: UnposedFrame) -> list[RGBDFrame]:
        self._tick(int(frame.stamp_ns))
        self._pending.append(frame)
        if len(self._pending) > self.cfg.max_pending:
            self._pending.popleft()
            self.stats.overflow += 1
        return self._drain()

    @property
    def pending(self) -> int:
        return len(self._pending)

    def _drain(self) -> list[RGBDFrame]:
        out: list[RGBDFrame] = []
        while self._pending:
            frame = self._pending[0]
            result = self._try_pose(frame.stamp_ns)
            if result is None:  # wait for more poses
                break
            self._pending.popleft()
            if isinstance(result, str):
                setattr(self.stats, result, getattr(self.stats, result) + 1)
                continue
            self.stats.paired += 1
            out.append(frame.posed(result @ self._T_SC))
        return out

    def _try_pose(self, stamp: int) -> npt.NDArray[np.float64] | str | None:
        """The pose at ``stamp``, the name of the stat that says why there is none, or None to wait."""
        if not self._stamps or self._stamps[-1] < stamp:
            assert self._latest_ns is not None
            return "timed_out" if self._latest_ns - stamp > self.cfg.max_wait_s * 1e9 else None
        stamps = np.fromiter(self._stamps, dtype=np.int64, count=len(self._stamps))
        i = int(np.searchsorted(stamps, stamp, side="left"))
        if stamps[i] == stamp:
            return self._poses[i]
        if i == 0:
            return "too_old"
        t0, t1 = int(stamps[i - 1]), int(stamps[i])
        if t1 - t0 > self.cfg.max_gap_s * 1e9:
            return "gap"
        return interpolate_pose(self._poses[i - 1], self._poses[i], (stamp - t0) / (t1 - t0))
