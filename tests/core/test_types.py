from __future__ import annotations

import numpy as np
import pytest

from gsfix_online.core.types import ROTATION_ATOL, FrameError, Intrinsics, check_pose, make_frame

K = Intrinsics(50.0, 50.0, 19.5, 14.5, 40, 30)


def pose_with(ij: tuple[int, int], value: float) -> np.ndarray:
    T = np.eye(4)
    T[ij] = value
    return T


def good(**kw):
    args = dict(
        color=np.zeros((30, 40, 3), np.uint8),
        depth=np.ones((30, 40), np.float32),
        intrinsics=K,
        T_world_cam=np.eye(4),
        stamp_ns=5,
    )
    args.update(kw)
    return make_frame(**args)


def test_valid_frame_rgb_and_gray():
    f = good()
    assert (
        f.color.shape == (30, 40, 3)
        and f.T_world_cam.dtype == np.float64
        and f.n_depth_invalidated == 0
    )
    g = good(color=np.zeros((30, 40), np.uint8))
    assert g.is_gray and not f.is_gray


@pytest.mark.parametrize(
    ("kw", "msg"),
    [
        (dict(color=np.zeros((30, 40, 3), np.float32)), "color must be uint8"),
        (dict(color=np.zeros((30, 40, 4), np.uint8)), "color must be uint8"),
        (
            dict(depth=np.ones((30, 40), np.uint16)),
            "depth must be float32 [H, W] metres, got uint16 [30, 40]",
        ),
        (dict(depth=np.ones((30, 41), np.float32)), "sizes differ"),
        (
            dict(color=np.zeros((20, 40, 3), np.uint8), depth=np.ones((20, 40), np.float32)),
            "intrinsics are for 40x30",
        ),
        (dict(T_world_cam=np.eye(3)), "must be [4, 4]"),
        (dict(T_world_cam=np.full((4, 4), np.nan)), "NaN or inf"),
        (dict(T_world_cam=np.diag([1.0, 1.0, 1.0, np.inf])), "NaN or inf"),
        (dict(T_world_cam=pose_with((0, 3), np.nan)), "NaN or inf"),  # in the translation
        (dict(T_world_cam=pose_with((3, 2), 0.1)), "last row must be [0, 0, 0, 1]"),
        (dict(T_world_cam=np.diag([1.0, 1.0, 1.1, 1.0])), "not orthonormal"),
        (dict(T_world_cam=np.diag([1.0, 1.0, -1.0, 1.0])), "reflection"),
        (dict(stamp_ns=1.5), "stamp_ns must be an integer"),
        (dict(frame_id=""), "frame_id"),
    ],
)
def test_invalid_frames_raise_one_line(kw, msg):
    with pytest.raises(FrameError) as err:
        good(**kw)
    assert msg in str(err.value) and "\n" not in str(err.value)


def test_bad_depth_pixels_become_invalid_and_are_counted():
    d = np.ones((30, 40), np.float32)
    d[0, :3] = [np.nan, np.inf, -np.inf]
    d[1, :2] = [-0.5, -1e-9]
    f = good(depth=d)
    assert f.n_depth_invalidated == 5
    assert np.all(f.depth[0, :3] == 0) and np.all(f.depth[1, :2] == 0) and f.depth[2, 0] == 1.0
    assert np.isnan(d[0, 0])  # the caller's array is not modified


@pytest.mark.parametrize(
    ("args", "msg"),
    [
        ((0.0, 50.0, 19.5, 14.5, 40, 30), "focal lengths must be positive"),
        ((50.0, np.nan, 19.5, 14.5, 40, 30), "finite"),
        ((50.0, 50.0, 200.0, 14.5, 40, 30), "principal point"),
        ((50.0, 50.0, 19.5, 14.5, 0, 30), "image size"),
    ],
)
def test_bad_intrinsics(args, msg):
    with pytest.raises(FrameError, match=msg):
        Intrinsics(*args)


def test_intrinsics_K_round_trip_and_scaling():
    assert Intrinsics.from_K(K.K, 40, 30) == K
    half = K.scaled(20, 15)
    # pixel-centre convention: centre of the image stays the centre
    assert half.cx == pytest.approx((K.cx + 0.5) / 2 - 0.5) and half.fx == pytest.approx(25.0)
    with pytest.raises(FrameError, match="K must be"):
        Intrinsics.from_K(np.ones((3, 3)), 40, 30)
    for ij in [(0, 1), (1, 0), (2, 0), (2, 1), (2, 2)]:  # each entry that must be 0 (or 1)
        bad = K.K
        bad[ij] += 1e-3
        with pytest.raises(FrameError, match="K must be"):
            Intrinsics.from_K(bad, 40, 30)


def test_check_pose_accepts_float32_round_off():
    from scipy.spatial.transform import Rotation

    T = np.eye(4, dtype=np.float32)
    T[:3, :3] = Rotation.from_euler("xyz", [0.3, -1.2, 2.0]).as_matrix().astype(np.float32)
    assert check_pose(T).dtype == np.float64


def test_check_pose_matches_a_numpy_reference():
    """Scalar checks against max |R^T R - I| and det(R) in NumPy, over rotations perturbed by
    1e-7 .. 1e-2 (both sides of ROTATION_ATOL) and reflections."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    accepted = rejected = 0
    for k in range(300):
        R = Rotation.random(random_state=rng).as_matrix()
        R = R + rng.normal(0.0, 10 ** rng.uniform(-7, -2), (3, 3))
        if k % 4 == 0:
            R[:, 0] *= -1.0  # a reflection
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, rng.normal(0.0, 10.0, 3)
        err = np.abs(R.T @ R - np.eye(3)).max()
        if err <= ROTATION_ATOL and np.linalg.det(R) >= 0:
            np.testing.assert_array_equal(check_pose(T), T)
            accepted += 1
        else:
            msg = "not orthonormal" if err > ROTATION_ATOL else "reflection"
            with pytest.raises(FrameError, match=msg):
                check_pose(T)
            rejected += 1
    assert accepted > 50 and rejected > 50
