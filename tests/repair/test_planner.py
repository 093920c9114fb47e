"""Skip decisions: scores on synthetic renders, reasons, observation counts on an analytic rig."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gsfix_online.core.se3 import make_T
from gsfix_online.repair.planner import (
    SkipPolicy,
    keyframe_distance,
    observation_counts,
    score_view,
)

H, W = 32, 48


def renders(hole_cols: int = 0, shift: int = 0):
    rng = np.random.default_rng(1)
    mesh = np.repeat(np.linspace(40, 220, W, dtype=np.float32)[None], H, 0)
    mesh = mesh.astype(np.uint8)
    gs = np.clip(mesh.astype(int) + rng.integers(-3, 4, mesh.shape) + shift, 0, 255).astype(
        np.uint8
    )
    alpha = np.ones((H, W), np.float32)
    alpha[:, :hole_cols] = 0.0
    return gs, alpha, mesh, np.ones((H, W), bool)


def test_good_view_is_skipped_with_its_numbers():
    s = score_view(*renders(), SkipPolicy())
    assert not s.repair and s.hole_fraction == 0.0 and s.disagree_fraction == 0.0
    assert s.reason.startswith("map explains the view") and math.isnan(s.underobserved_fraction)


def test_holes_and_disagreement_trigger_repair_and_are_named():
    s = score_view(*renders(hole_cols=W // 4), SkipPolicy())
    assert s.repair and s.hole_fraction == 0.25 and "holes 25.0%" in s.reason
    s = score_view(*renders(shift=60), SkipPolicy())
    assert s.repair and s.disagree_fraction == 1.0 and "disagree" in s.reason


def test_view_without_surface_is_skipped():
    gs, alpha, mesh, valid = renders()
    s = score_view(gs, alpha * 0, mesh, np.zeros_like(valid), SkipPolicy())
    assert not s.repair and "little mapped surface" in s.reason


def test_empty_part_of_the_view_triggers_repair():
    gs, alpha, mesh, valid = renders()
    valid[:, : W // 4] = False  # neither map holds the left quarter: never observed
    alpha[:, : W // 4] = 0.0
    s = score_view(gs, alpha, mesh, valid, SkipPolicy())
    assert s.repair and s.hole_fraction == 0.0 and s.empty_fraction == 0.25
    assert s.reason == "empty 25.0% > 5.0%"
    # below the threshold it stays a skip, and the reason reports the figure
    s = score_view(gs, alpha, mesh, valid, SkipPolicy(empty_fraction=0.3))
    assert not s.repair and "empty 25.0%" in s.reason


def test_underobserved_surface_triggers_repair():
    gs, alpha, mesh, valid = renders()
    obs = np.full((H, W), 5, np.int32)
    obs[:, : W // 2] = 1
    s = score_view(gs, alpha, mesh, valid, SkipPolicy(), observations=obs)
    assert s.repair and s.underobserved_fraction == 0.5


def test_observation_counts_on_a_plane_seen_by_shifted_cameras():
    K = np.array([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]])
    depth = np.full((H, W), 2.0, np.float32)
    depth[0, 0] = 0.0
    views = np.stack([make_T(np.eye(3), [0, 0, 0]), make_T(np.eye(3), [100.0, 0, 0])])
    counts = observation_counts(depth, K, np.eye(4), views, K, (W, H))
    assert counts[0, 0] == 0 and (counts.ravel()[1:] == 1).all()
    # A camera shifted by half the footprint (2 m * 24/40 = 1.2 m half width) sees half the view.
    half = np.stack([make_T(np.eye(3), [1.2, 0, 0])])
    c = observation_counts(depth, K, np.eye(4), half, K, (W, H))
    assert c[5, W // 2 + 2] == 1 and c[5, 2] == 0


def test_keyframe_distance_adds_translation_and_rotation_at_the_surface_depth():
    def yaw(deg: float) -> np.ndarray:
        a = math.radians(deg)
        return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])

    kfs = np.stack([make_T(np.eye(3), [0, 0, 0]), make_T(np.eye(3), [2.0, 0, 0])])
    assert keyframe_distance(kfs[1], kfs, 1.5) == 0.0  # at a keyframe
    assert math.isclose(keyframe_distance(make_T(np.eye(3), [0.3, 0.4, 0]), kfs, 1.5), 0.5)
    # turned 90 degrees at a keyframe: the image centre's surface point moves 1.5 * pi / 2 m
    turned = make_T(yaw(90), [2.0, 0, 0])
    assert math.isclose(keyframe_distance(turned, kfs, 1.5), 1.5 * math.pi / 2)
    # the nearest keyframe by the sum: 0.9 m from the first beats 1.1 m + 90 deg
    T = make_T(yaw(90), [0.9, 0, 0])
    assert math.isclose(keyframe_distance(T, np.stack([make_T(yaw(90), [0, 0, 0]), kfs[1]]),
                                          1.0), 0.9)  # fmt: skip
    with pytest.raises(ValueError, match="at least one keyframe"):
        keyframe_distance(T, np.zeros((0, 4, 4)), 1.0)
