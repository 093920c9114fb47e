"""SE(3) helpers on numpy arrays. Quaternions are Hamilton, ordered (x, y, z, w) as in TUM and ROS."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

Array = npt.NDArray[np.float64]


def make_T(R: npt.ArrayLike, t: npt.ArrayLike) -> Array:
    """[3, 3] rotation and [3] translation -> [4, 4] transform."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


def inv_T(T: npt.ArrayLike) -> Array:
    """Inverse of a rigid [..., 4, 4] transform, exact for orthonormal rotations."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def quat_xyzw_to_R(q: npt.ArrayLike) -> Array:
    """Unit quaternion(s) [..., 4] (x, y, z, w) -> rotation matrices [..., 3, 3]. Rejects zero norm."""
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1)
    if np.any(~np.isfinite(n)) or np.any(n < 1e-12):
        raise ValueError("quaternion has zero or non-finite norm")
    return Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(*q.shape[:-1], 3, 3)


def R_to_quat_xyzw(R: npt.ArrayLike) -> Array:
    """Rotation matrices [..., 3, 3] -> unit quaternions [..., 4] (x, y, z, w) with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()
    q = np.where(q[:, 3:4] < 0, -q, q)
    return q.reshape(*R.shape[:-2], 4)


def pose_from_tq(t: npt.ArrayLike, q_xyzw: npt.ArrayLike) -> Array:
    """Translation [..., 3] and quaternion [..., 4] (x, y, z, w) -> [..., 4, 4]."""
    t = np.asarray(t, dtype=np.float64)
    R = quat_xyzw_to_R(q_xyzw)
    T = np.zeros((*t.shape[:-1], 4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def pose_to_tq(T: npt.ArrayLike) -> tuple[Array, Array]:
    """[..., 4, 4] -> (translation [..., 3], quaternion [..., 4] x, y, z, w)."""
    T = np.asarray(T, dtype=np.float64)
    return T[..., :3, 3].copy(), R_to_quat_xyzw(T[..., :3, :3])


def interpolate_pose(T0: npt.ArrayLike, T1: npt.ArrayLike, alpha: float) -> Array:
    """SE(3) interpolation between two poses: slerp on rotation, linear on translation (alpha in [0, 1])."""
    T0 = np.asarray(T0, dtype=np.float64)
    T1 = np.asarray(T1, dtype=np.float64)
    r0 = Rotation.from_matrix(T0[:3, :3])
    r_rel = r0.inv() * Rotation.from_matrix(T1[:3, :3])
    R = (r0 * Rotation.from_rotvec(r_rel.as_rotvec() * alpha)).as_matrix()
    return make_T(R, (1.0 - alpha) * T0[:3, 3] + alpha * T1[:3, 3])


def look_at(
    eye: npt.ArrayLike, target: npt.ArrayLike, up: npt.ArrayLike = (0.0, 0.0, 1.0)
) -> Array:
    """Camera-to-world pose (OpenCV axes: z forward, y down) at ``eye`` looking at ``target``."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    # Guard (stress suite, geometry.look_at): a target on the eye has no viewing direction, and
    # dividing by its zero length gave an all-NaN pose.
    length = float(np.linalg.norm(z))
    if not (length > 0 and np.isfinite(length)):
        raise ValueError(
            f"look_at needs a finite target apart from the eye, got eye {eye.tolist()} and "
            f"target {np.asarray(target).tolist()}"
        )
    z /= length
    up = np.asarray(up, dtype=np.float64)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along `up`: pick any perpendicular
        x = np.cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.stack([x, y, z], axis=1), eye)


def pose_distances(
    A: npt.ArrayLike,  # [M, 4, 4] camera-to-world
    B: npt.ArrayLike,  # [N, 4, 4]
    rotation_weight_m: float,
) -> Array:  # [M, N] metres
    """Distance between every pose of ``A`` and every pose of ``B``: the translation plus the
    relative rotation angle (radians) times ``rotation_weight_m`` (how far that rotation moves
    a point at that distance in front of the camera)."""
    a = np.asarray(A, np.float64).reshape(-1, 4, 4)
    b = np.asarray(B, np.float64).reshape(-1, 4, 4)
    dt = np.linalg.norm(a[:, None, :3, 3] - b[None, :, :3, 3], axis=-1)
    trace = np.einsum("iab,jab->ij", a[:, :3, :3], b[:, :3, :3])  # trace(R_i^T R_j)
    angle = np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0))
    return dt + float(rotation_weight_m) * angle


def most_redundant(
    poses: npt.ArrayLike,  # [N, 4, 4] camera-to-world, oldest first, N >= 2
    rotation_weight_m: float,
) -> int:
    """Index of the pose nearest another (:func:`pose_distances`), never the newest (last);
    the older on ties: what a bounded store of views evicts first."""
    d = pose_distances(poses, poses, rotation_weight_m)
    np.fill_diagonal(d, np.inf)
    return int(np.argmin(d.min(axis=1)[:-1]))
