from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gsfix_online.core.se3 import (
    R_to_quat_xyzw,
    interpolate_pose,
    inv_T,
    look_at,
    make_T,
    pose_distances,
    pose_from_tq,
    pose_to_tq,
    quat_xyzw_to_R,
)
from gsfix_online.core.trajectory import Trajectory


def random_pose(rng):
    return make_T(
        Rotation.random(random_state=rng.integers(1 << 31)).as_matrix(), rng.normal(size=3)
    )


def test_quaternion_round_trip_and_convention():
    # 90 degrees about z: x axis maps to y
    R = quat_xyzw_to_R([0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    assert np.allclose(R @ [1, 0, 0], [0, 1, 0])
    rng = np.random.default_rng(0)
    Rs = Rotation.random(20, random_state=1).as_matrix()
    q = R_to_quat_xyzw(Rs)
    assert np.all(q[:, 3] >= 0) and np.allclose(quat_xyzw_to_R(q), Rs, atol=1e-12)
    T = random_pose(rng)
    assert np.allclose(pose_from_tq(*pose_to_tq(T)), T, atol=1e-12)
    with pytest.raises(ValueError, match="zero"):
        quat_xyzw_to_R([0, 0, 0, 0])


def test_inverse_and_interpolation():
    rng = np.random.default_rng(1)
    T0, T1 = random_pose(rng), random_pose(rng)
    assert np.allclose(inv_T(T0) @ T0, np.eye(4), atol=1e-12)
    assert np.allclose(interpolate_pose(T0, T1, 0.0), T0) and np.allclose(
        interpolate_pose(T0, T1, 1.0), T1
    )
    # half-way: rotation angle to each end is equal, translation is the mean
    Tm = interpolate_pose(T0, T1, 0.5)
    a0 = Rotation.from_matrix(T0[:3, :3].T @ Tm[:3, :3]).magnitude()
    a1 = Rotation.from_matrix(Tm[:3, :3].T @ T1[:3, :3]).magnitude()
    assert a0 == pytest.approx(a1) and np.allclose(Tm[:3, 3], (T0[:3, 3] + T1[:3, 3]) / 2)


def test_look_at_axes():
    T = look_at([0, 0, 0], [0, 0, 5], up=[0, -1, 0])
    assert np.allclose(T[:3, 2], [0, 0, 1])  # camera z looks at the target
    T = look_at(
        [1, 2, 3], [1, 2, 10]
    )  # looking along +z with up = +z: degenerate, still orthonormal
    assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3))


def test_trajectory_query_gap_and_extrinsics():
    rng = np.random.default_rng(2)
    poses = np.stack([random_pose(rng) for _ in range(3)])
    traj = Trajectory(np.array([300, 100, 200]), poses[[2, 0, 1]])  # unsorted input gets sorted
    assert np.allclose(traj.query(100, 10), poses[0])  # exact stamp
    assert np.allclose(traj.query(150, 100), interpolate_pose(poses[0], poses[1], 0.5))
    assert traj.query(150, 99) is None  # gap 100 > max 99
    assert traj.query(50, 1000) is None and traj.query(301, 1000) is None  # outside
    T_SC = random_pose(rng)
    assert np.allclose(traj.transformed(T_SC).query(200, 1), poses[1] @ T_SC)


def test_pose_distances_add_translation_and_weighted_rotation_between_every_pair():
    yaw = Rotation.from_euler("y", 90, degrees=True).as_matrix()
    A = np.stack([make_T(np.eye(3), [0, 0, 0]), make_T(yaw, [0, 0, 0])])
    B = np.stack([make_T(np.eye(3), [3.0, 4.0, 0]), make_T(np.eye(3), [0, 0, 0]), A[1]])
    d = pose_distances(A, B, 2.0)
    assert d.shape == (2, 3)
    np.testing.assert_allclose(d[0], [5.0, 0.0, np.pi])  # 90 degrees at 2 m: pi m
    np.testing.assert_allclose(d[1], [5.0 + np.pi, np.pi, 0.0], atol=1e-7)
    np.testing.assert_allclose(pose_distances(B, B, 2.0), pose_distances(B, B, 2.0).T)
