from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from gsfix_online.core.config import ConfigError, build
from gsfix_online.core.se3 import interpolate_pose, look_at
from gsfix_online.core.types import FrameError, Intrinsics, make_frame
from gsfix_online.sources.pose_association import PoseAssociationConfig, PoseAssociator

K = Intrinsics(20.0, 20.0, 7.5, 5.5, 16, 12)
MS = 1_000_000


@dataclass
class Cam:
    stamp_ns: int

    def posed(self, T):  # noqa: ANN001, ANN201
        return make_frame(
            np.zeros((12, 16), np.uint8), np.ones((12, 16), np.float32), K, T, self.stamp_ns
        )


def pose(i: int) -> np.ndarray:
    return look_at([0.1 * i, 0.0, 0.0], [0.1 * i + 1.0, 0.3 * i, 0.2])


def test_frames_wait_for_later_poses_and_interpolate():
    T_SC = look_at([0.05, 0, 0], [0, 1, 0])
    assoc = PoseAssociator(PoseAssociationConfig(T_SC=T_SC.ravel().tolist()))
    assert assoc.add_pose(0, pose(0)) == []
    assert assoc.add_frame(Cam(25 * MS)) == []  # no pose after it yet: waits
    assert assoc.pending == 1
    out = assoc.add_pose(50 * MS, pose(1))
    assert len(out) == 1 and out[0].stamp_ns == 25 * MS
    assert np.allclose(out[0].T_world_cam, interpolate_pose(pose(0), pose(1), 0.5) @ T_SC)
    exact = assoc.add_frame(Cam(50 * MS))  # exact stamp: immediate
    assert len(exact) == 1 and np.allclose(exact[0].T_world_cam, pose(1) @ T_SC)
    assert assoc.stats.paired == 2 and assoc.stats.unpaired == 0


def test_unpaired_reasons_are_counted():
    assoc = PoseAssociator(PoseAssociationConfig(max_gap_s=0.1, max_wait_s=0.2))
    assoc.add_pose(100 * MS, pose(0))
    assert assoc.add_frame(Cam(50 * MS)) == [] and assoc.stats.too_old == 1  # before the history
    assoc.add_pose(400 * MS, pose(1))  # 300 ms hole
    assert assoc.add_frame(Cam(250 * MS)) == [] and assoc.stats.gap == 1
    # SLAM lost track: frames keep coming, no pose after 400 ms
    for t in (450, 500, 550, 600, 650):
        assert assoc.add_frame(Cam(t * MS)) == []
    assert assoc.stats.timed_out == 0  # 650 - 450 = 200 ms: not past max_wait yet
    assoc.add_frame(Cam(700 * MS))
    assert assoc.stats.timed_out == 1  # 450 waited 250 ms of stream time; 500 waited exactly 200
    assert assoc.pending == 5
    assoc.add_pose(300 * MS, pose(2))  # older than the newest pose
    assert assoc.stats.poses_out_of_order == 1


def test_bounded_pending_and_history():
    assoc = PoseAssociator(PoseAssociationConfig(max_pending=3, max_wait_s=60.0, history_s=1.0))
    for t in range(5):
        assoc.add_frame(Cam(t * MS))
    assert assoc.pending == 3 and assoc.stats.overflow == 2
    for i in range(100):
        assoc.add_pose(i * 100 * MS, pose(0))
    assert len(assoc._stamps) <= 12  # ~1 s of history at 10 Hz


def test_bad_poses_and_config_rejected():
    assoc = PoseAssociator(PoseAssociationConfig())
    with pytest.raises(FrameError, match="T_world_S contains NaN"):
        assoc.add_pose(0, np.full((4, 4), np.nan))
    with pytest.raises(ConfigError, match="T_SC must have 16 numbers"):
        build(PoseAssociationConfig, base={"T_SC": [1.0]})
