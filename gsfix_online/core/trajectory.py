"""Timestamped trajectories: SE(3) interpolation at query times with a maximum gap."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from gsfix_online.core.se3 import interpolate_pose


@dataclass
class Trajectory:
    """Poses sorted by time. ``stamps_ns`` [N] int64; ``poses`` [N, 4, 4] float64 (T_world_x)."""

    stamps_ns: npt.NDArray[np.int64]
    poses: npt.NDArray[np.float64]

    def __post_init__(self) -> None:
        self.stamps_ns = np.asarray(self.stamps_ns, dtype=np.int64)
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.stamps_ns) != len(self.poses):
            raise ValueError(
                f"trajectory has {len(self.stamps_ns)} stamps and {len(self.poses)} poses"
            )
        order = np.argsort(self.stamps_ns, kind="stable")
        self.stamps_ns = self.stamps_ns[order]
        self.poses = self.poses[order]
        dup = np.flatnonzero(np.diff(self.stamps_ns) == 0)
        if len(dup):
            keep = np.ones(len(self.stamps_ns), dtype=bool)
            keep[dup + 1] = False  # duplicate stamps: keep the first pose
            self.stamps_ns = self.stamps_ns[keep]
            self.poses = self.poses[keep]

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def query(self, stamp_ns: int, max_gap_ns: int) -> npt.NDArray[np.float64] | None:
        """Pose at ``stamp_ns``, interpolated between the two bracketing poses.

        Returns None when the stamp is outside the trajectory or the bracketing poses are more
        than ``max_gap_ns`` apart (an exact stamp match always succeeds).
        """
        if len(self) == 0:
            return None
        i = int(np.searchsorted(self.stamps_ns, stamp_ns, side="left"))
        if i < len(self) and self.stamps_ns[i] == stamp_ns:
            return self.poses[i].copy()
        if i == 0 or i == len(self):
            return None
        t0, t1 = int(self.stamps_ns[i - 1]), int(self.stamps_ns[i])
        if t1 - t0 > max_gap_ns:
            return None
        return interpolate_pose(self.poses[i - 1], self.poses[i], (stamp_ns - t0) / (t1 - t0))

    def transformed(self, T_right: npt.ArrayLike) -> Trajectory:
        """Trajectory of ``T_world_x @ T_right`` (e.g. IMU poses times T_SC gives camera poses)."""
        return Trajectory(self.stamps_ns.copy(), self.poses @ np.asarray(T_right, dtype=np.float64))
