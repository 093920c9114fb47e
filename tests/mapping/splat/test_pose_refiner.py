"""Pose refinement (pose_refiner.py): tracking recovers a known offset on the analytic plane,
kept corrections give the keyframes' and nearby poses, forgotten ones leave the optimiser."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from gsfix_online.core.se3 import make_T
from gsfix_online.mapping.splat.keyframes import KeyframeConfig
from gsfix_online.mapping.splat.mapper import Mapper
from gsfix_online.mapping.splat.pose_refiner import PoseRefiner
from gsfix_online.mapping.splat.poses import PoseConfig, corrected
from gsfix_online.mapping.splat.views import downscale_view, frame_view
from tests.mapping.splat.test_mapper import (
    CFG,
    one_thread,  # noqa: F401 -- autouse: one torch thread
    plane_frame,
)


@pytest.fixture(scope="module")
def mapped() -> Mapper:
    """The plane from two frames at exact poses, refined (tracking needs a converged map)."""
    torch.manual_seed(0)
    m = Mapper(dataclasses.replace(CFG, keyframes=KeyframeConfig(min_overlap=0.99)))
    for i in range(2):
        m.process(plane_frame(0.15 * i, i))
    m.refine(100)
    return m


def test_tracking_recovers_a_small_known_offset(mapped: Mapper) -> None:
    truth = plane_frame(0.075, 5)  # between the two mapped frames
    dx = 0.02  # the given pose is 2 cm off along x
    T = truth.T_world_cam.copy()
    T[0, 3] += dx
    view = downscale_view(frame_view(truth.with_pose(T), mapped.device), 2)
    refiner = PoseRefiner(PoseConfig(enabled=True), CFG.depth_weight, mapped.device)
    xi = refiner.track(mapped.render, view, torch.zeros(6), mapped.scene_scale)
    T_fixed = corrected(torch.as_tensor(T), xi.double(), mapped.scene_scale).detach().numpy()
    err = abs(T_fixed[0, 3] - truth.T_world_cam[0, 3])
    assert xi.any() and err < 0.5 * dx, err


def test_tracking_keeps_the_given_pose_where_the_map_is_empty() -> None:
    m = Mapper(CFG)  # nothing mapped: no opaque pixel
    view = frame_view(plane_frame(), m.device)
    refiner = PoseRefiner(PoseConfig(enabled=True), CFG.depth_weight, m.device)
    assert torch.equal(refiner.track(m.render, view, torch.zeros(6), 2.0), torch.zeros(6))


def test_kept_corrections_move_keyframe_and_nearby_poses(mapped: Mapper) -> None:
    refiner = PoseRefiner(PoseConfig(enabled=True), CFG.depth_weight, torch.device("cpu"))
    kfs = list(mapped.store)
    assert np.array_equal(refiner.pose_for(np.eye(4), kfs, 1.0, 2.0), np.eye(4))  # none kept
    refiner.keep(kfs[-1].kf_id, torch.tensor([0.01, 0.0, 0.0, 0.0, 0.0, 0.0]))  # 2 cm at scale 2
    T_kf = refiner.keyframe_pose(kfs[-1], 2.0)
    np.testing.assert_allclose(T_kf[:3, 3] - kfs[-1].frame.T_world_cam[:3, 3], [0.02, 0, 0],
                               atol=1e-6)  # fmt: skip
    near = make_T(np.eye(3), kfs[-1].frame.T_world_cam[:3, 3] + [0.0, 0.01, 0.0])
    np.testing.assert_allclose(refiner.pose_for(near, kfs, 1.0, 2.0)[:3, 3] - near[:3, 3],
                               [0.02, 0, 0], atol=1e-6)  # fmt: skip
    ((m, deg),) = refiner.corrections(kfs, 2.0).values()
    assert m == pytest.approx(0.02, abs=1e-6) and deg == pytest.approx(0.0, abs=1e-3)
    assert refiner.stats(kfs, 2.0)["pose_max_mm"] == pytest.approx(20.0, abs=1e-3)
    torch.testing.assert_close(refiner.last_correction(kfs), torch.tensor([0.01, 0, 0, 0, 0, 0]))
    refiner.forget(set())
    assert refiner.poses == {} and refiner.opt is not None and not refiner.opt.param_groups
