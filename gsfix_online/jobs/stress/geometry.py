"""Stress properties of the pose math: SE(3), quaternions (numpy and torch), interpolation."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from hypothesis import strategies as st

from gsfix_online.core.se3 import (
    R_to_quat_xyzw,
    interpolate_pose,
    inv_T,
    look_at,
    pose_from_tq,
    pose_to_tq,
    quat_xyzw_to_R,
)
from gsfix_online.core.trajectory import Trajectory
from gsfix_online.core.types import check_pose
from gsfix_online.jobs.stress import Property
from gsfix_online.jobs.stress.strategies import log_uniform, poses, quats_wxyz, rotations

ORTHO_ATOL = 1e-12  # float64 rotations stay orthonormal to a few ulp


def _rigid(T: np.ndarray, what: str) -> None:
    assert np.isfinite(T).all(), f"{what} has NaN or inf: {T.tolist()}"
    check_pose(T, what)  # raises FrameError (not orthonormal, reflection, last row)
    err = float(np.abs(T[:3, :3].T @ T[:3, :3] - np.eye(3)).max())
    assert err < ORTHO_ATOL, f"{what} rotation is off orthonormal by {err:.1e}"


def _angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return math.acos(min(1.0, max(-1.0, c)))


# -- quaternions -----------------------------------------------------------------------------


def check_quat_to_rotation(q_wxyz: np.ndarray) -> None:
    """Any non-degenerate quaternion gives a rotation and round-trips up to sign and norm; a
    degenerate one (|q| < 1e-12) raises ValueError, never a NaN matrix."""
    q = np.array([*q_wxyz[1:], q_wxyz[0]])  # x, y, z, w
    n = float(np.linalg.norm(q))
    if n < 1e-12:
        try:
            R = quat_xyzw_to_R(q)
        except ValueError as exc:
            assert "zero" in str(exc), f"unclear error for |q| = {n:g}: {exc}"
            return
        raise AssertionError(f"|q| = {n:g} gave a rotation instead of an error: {R.tolist()}")
    R = quat_xyzw_to_R(q)
    T = np.eye(4)
    T[:3, :3] = R
    _rigid(T, "quat_xyzw_to_R")
    back = R_to_quat_xyzw(R)
    unit = q / n
    assert min(np.abs(back - unit).max(), np.abs(back + unit).max()) < 1e-9, (
        f"quaternion {unit.tolist()} came back as {back.tolist()}"
    )


def check_torch_normalize(q_wxyz: np.ndarray) -> None:
    """The map's quaternion activation (float32, differentiable) is unit and has finite
    gradients for any quaternion the map may hold, zero and tiny ones included."""
    import torch

    from gsfix_online.mapping.splat.gaussians import normalize_quats

    q = torch.tensor(q_wxyz, dtype=torch.float32)[None].requires_grad_(True)
    u = normalize_quats(q)
    assert torch.isfinite(u).all(), f"normalize_quats({q_wxyz.tolist()}) = {u.tolist()}"
    assert abs(float(u.detach().norm()) - 1.0) < 1e-5, (
        f"|normalize_quats(q)| = {float(u.detach().norm())}"
    )
    (u * torch.tensor([0.3, -0.2, 0.5, 0.7])).sum().backward()
    assert torch.isfinite(q.grad).all(), f"gradient of normalize_quats at {q_wxyz.tolist()}"


# -- SE(3) -----------------------------------------------------------------------------------


def check_inverse_and_tq(T: np.ndarray) -> None:
    """inv_T and the (t, q) round trip hold 10 km from the origin to float64 precision."""
    scale = max(1.0, float(np.abs(T[:3, 3]).max()))
    err = float(np.abs(inv_T(T) @ T - np.eye(4)).max())
    assert err < 1e-15 * 64 * scale, f"inv_T(T) @ T is off identity by {err:.1e}"
    back = pose_from_tq(*pose_to_tq(T))
    err = float(np.abs(back - T).max())
    assert err < 1e-12 * scale, f"pose_from_tq(pose_to_tq(T)) is off by {err:.1e}"


def check_interpolation(ex: dict[str, Any]) -> None:
    """interpolate_pose is rigid and finite for any pair (half turns, identical poses, 10 km
    away), hits both ends, and moves the rotation by alpha times the angle between them."""
    T0, T1, a = ex["T0"], ex["T1"], ex["alpha"]
    T = interpolate_pose(T0, T1, a)
    _rigid(T, f"interpolate_pose(alpha={a})")
    scale = max(1.0, float(np.abs(T0[:3, 3]).max()), float(np.abs(T1[:3, 3]).max()))
    want_t = (1 - a) * T0[:3, 3] + a * T1[:3, 3]
    assert np.abs(T[:3, 3] - want_t).max() < 1e-12 * scale, "translation is not the lerp"
    total = _angle(T0[:3, :3], T1[:3, :3])
    if total < math.pi - 1e-6:  # at a half turn the shorter way is either way
        got = _angle(T0[:3, :3], T[:3, :3])
        assert abs(got - a * total) < 1e-7, f"rotated {got} of {total} rad at alpha {a}"
    for end, want in ((0.0, T0), (1.0, T1)):
        err = float(np.abs(interpolate_pose(T0, T1, end) - want).max())
        assert err < 1e-9 * scale, f"alpha={end} misses the end pose by {err:.1e}"


def check_trajectory_query(ex: dict[str, Any]) -> None:
    """Trajectory.query over int64 stamps (near its limits too) returns None or a rigid pose."""
    traj = Trajectory(np.array(ex["stamps"], np.int64), np.stack(ex["poses"]))
    for stamp in ex["queries"]:
        T = traj.query(stamp, max_gap_ns=ex["max_gap"])
        if T is not None:
            _rigid(T, f"query({stamp})")


def check_look_at(ex: dict[str, Any]) -> None:
    """look_at gives a rigid pose whose z axis points at the target for any eye and target
    (10 km away, 1e-9 m apart, along up, a tiny up); target == eye raises ValueError, never NaN."""
    eye, target, up = ex["eye"], ex["target"], ex["up"]
    if np.array_equal(eye, target):
        try:
            T = look_at(eye, target, up)
        except ValueError:
            return
        raise AssertionError(f"look_at({eye.tolist()}, {target.tolist()}, {up.tolist()}) = {T}")
    T = look_at(eye, target, up)
    _rigid(T, "look_at")
    d = target - eye
    err = float(np.abs(T[:3, 2] - d / np.linalg.norm(d)).max())
    assert err < 1e-9, f"look_at's z axis is off the target direction by {err:.1e}"


# -- strategies ------------------------------------------------------------------------------


def _interp_pairs() -> Any:
    @st.composite
    def pairs(draw: st.DrawFn) -> dict[str, Any]:
        T0 = draw(poses())
        kind = draw(st.sampled_from(["random", "same", "half_turn_apart", "nearby"]))
        if kind == "random":
            T1 = draw(poses())
        else:
            T1 = T0.copy()
            if kind == "half_turn_apart":
                T1[:3, :3] = T0[:3, :3] @ np.diag([1.0, -1.0, -1.0])
            elif kind == "nearby":
                T1[:3, :3] = T0[:3, :3] @ draw(rotations())
                T1[:3, 3] += draw(log_uniform(1e-9, 1.0))
        alpha = draw(st.one_of(st.sampled_from([0.0, 1.0, 1e-12, 1 - 1e-12]), st.floats(0, 1)))
        return {"T0": T0, "T1": T1, "alpha": alpha}

    return pairs()


def _trajectories() -> Any:
    i64 = st.integers(-(2**62), 2**62)

    @st.composite
    def traj(draw: st.DrawFn) -> dict[str, Any]:
        n = draw(st.integers(1, 4))
        stamps = draw(st.lists(i64, min_size=n, max_size=n))
        stamps += [stamps[0] + d for d in draw(st.lists(st.integers(1, 3), max_size=2))]
        return {
            "stamps": stamps,
            "poses": [draw(poses()) for _ in stamps],
            "queries": draw(
                st.lists(st.one_of(i64, st.sampled_from(stamps)), min_size=1, max_size=4)
            ),
            "max_gap": draw(st.sampled_from([0, 1, 10**9, 2**63 - 1])),
        }

    return traj()


def _look_at_args() -> Any:
    @st.composite
    def args(draw: st.DrawFn) -> dict[str, Any]:
        eye = draw(poses())[:3, 3]
        kind = draw(st.sampled_from(["random", "same", "tiny", "along_up"]))
        up = np.array(draw(st.sampled_from([(0.0, 0.0, 1.0), (0.0, -1.0, 0.0), (1e-9, 0, 0)])))
        if kind == "same":
            target = eye.copy()
        elif kind == "along_up":
            target = eye + draw(log_uniform(1e-6, 1e4)) * up / np.linalg.norm(up)
        else:
            d = draw(poses(far=False))[:3, 0]  # a unit vector
            target = eye + d * (draw(log_uniform(1e-9, 1e-3)) if kind == "tiny" else 10.0)
        return {"eye": eye, "target": target, "up": up}

    return args()


PROPERTIES = [
    Property(
        "geometry.quat_to_rotation",
        "quat_xyzw_to_R: a rotation for every non-degenerate quaternion, an error for a zero one",
        quats_wxyz,
        check_quat_to_rotation,
        ci_examples=60,
    ),
    Property(
        "geometry.torch_normalize_quats",
        "the map's quaternion activation is unit with finite gradients (zero, 1e-20, 1e6)",
        quats_wxyz,
        check_torch_normalize,
        ci_examples=60,
    ),
    Property(
        "geometry.inverse_and_tq",
        "inv_T and the (t, q) round trip at float64 precision up to 10 km from the origin",
        poses,
        check_inverse_and_tq,
        ci_examples=60,
    ),
    Property(
        "geometry.interpolation",
        "interpolate_pose: rigid, ends hit, rotation angle alpha x total (half turns, 10 km)",
        _interp_pairs,
        check_interpolation,
        ci_examples=60,
    ),
    Property(
        "geometry.trajectory_query",
        "Trajectory.query near the int64 limits: None or a rigid pose",
        _trajectories,
        check_trajectory_query,
        ci_examples=40,
    ),
    Property(
        "geometry.look_at",
        "look_at: rigid and aimed for any eye and target; an error when they coincide",
        _look_at_args,
        check_look_at,
        ci_examples=40,
    ),
]
