"""Keyframe pose refinement: the SE(3) correction's math, and the mapper correcting a keyframe whose
front-end pose is off, on the analytic textured plane of test_mapper."""

from __future__ import annotations

import dataclasses
import io

import numpy as np
import pytest
import torch

from gsfix_online.geometry.se3 import make_T
from gsfix_online.mapping.splat.keyframes import KeyframeConfig
from gsfix_online.mapping.splat.mapper import Mapper
from gsfix_online.mapping.splat.poses import PoseConfig, clamp_, corrected, offsets, prior_loss
from gsfix_online.types import RGBDFrame, make_frame
from tests.mapping.splat.test_mapper import CFG, plane_frame


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def test_zero_correction_is_the_pose_and_a_known_one_moves_it_in_the_camera_frame():
    rot = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 deg about z
    T = torch.eye(4)
    T[:3, :3], T[:3, 3] = rot, torch.tensor([1.0, 2.0, 3.0])
    assert torch.equal(corrected(T, torch.zeros(6), 2.0), T)
    # upsilon is in scene-scale units and applied in the camera frame: camera x = world y here
    out = corrected(T, torch.tensor([0.05, 0.0, 0.0, 0.0, 0.0, 0.0]), 2.0)
    torch.testing.assert_close(out[:3, 3], torch.tensor([1.0, 2.1, 3.0]))
    torch.testing.assert_close(out[:3, :3], rot)
    xi = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, np.radians(1.0)])
    m, deg = offsets(T, corrected(T, xi, 2.0))
    assert m == pytest.approx(0.0, abs=1e-6) and deg == pytest.approx(1.0, abs=1e-3)
    assert float(prior_loss(torch.tensor([3.0, 0, 0, 0, 4.0, 0]))) == 25.0


def test_the_correction_is_differentiable_and_clamped():
    xi = torch.zeros(6, requires_grad=True)
    corrected(torch.eye(4), xi, 1.0)[0, 3].backward()
    assert xi.grad is not None and float(xi.grad[0]) == 1.0
    cfg = PoseConfig(max_rotation_deg=1.0, max_translation=0.01)
    big = torch.tensor([0.03, 0.04, 0.0, 0.5, 0.0, 0.0])
    clamp_(big, cfg)
    assert float(big[:3].norm()) == pytest.approx(0.01) and float(big[0] / big[1]) == 0.75
    assert float(big[3:].norm()) == pytest.approx(np.radians(1.0))


def _shifted(f: RGBDFrame, dx: float) -> RGBDFrame:
    T = f.T_world_cam.copy()
    T[0, 3] += dx
    return make_frame(f.color, f.depth, f.intrinsics, T, f.stamp_ns, seq=f.seq)


TRUE = [plane_frame(0.15 * i, i) for i in range(5)]


@pytest.fixture(scope="module")
def corrected_map() -> Mapper:
    """The plane's frames, the third one's pose 4 cm off along x, mapped with corrections."""
    given = [TRUE[0], TRUE[1], _shifted(TRUE[2], 0.04), TRUE[3], TRUE[4]]
    torch.manual_seed(0)
    cfg = dataclasses.replace(
        CFG,
        keyframes=KeyframeConfig(min_overlap=0.99),
        poses=PoseConfig(enabled=True, lr=1e-3),
    )
    m = Mapper(cfg)
    for f in given:
        m.process(f)
    m.refine(100)
    return m


def test_without_corrections_the_mapper_keeps_no_pose_parameters():
    m = Mapper(dataclasses.replace(CFG, keyframes=KeyframeConfig(min_overlap=0.99)))
    for f in TRUE[:3]:
        m.process(f)
    assert len(m.store) == 2 and m.poses == {} and "pose_corrected" not in m.stats()
    assert m.pose_corrections() == {}


def test_a_keyframe_whose_pose_is_off_is_corrected_towards_the_truth(corrected_map):
    m = corrected_map
    kfs = {kf.frame.seq: kf for kf in m.store}
    assert 2 in kfs and len(kfs) >= 3  # the shifted frame is a keyframe
    assert kfs[0].kf_id not in m.poses  # the first keyframe holds the gauge
    err_before = abs(kfs[2].frame.T_world_cam[0, 3] - TRUE[2].T_world_cam[0, 3])
    err_after = abs(m.keyframe_pose(kfs[2])[0, 3] - TRUE[2].T_world_cam[0, 3])
    assert err_before == pytest.approx(0.04) and err_after < 0.3 * err_before, err_after
    s = m.stats()
    assert s["pose_corrected"] == len(kfs) - 1 and 20 < s["pose_max_mm"] < 60
    # a pose near that keyframe moves with it (the world-frame correction of the nearest one)
    near = _shifted(TRUE[2], 0.045).T_world_cam
    assert abs(m.pose_for(near)[0, 3] - (TRUE[2].T_world_cam[0, 3] + 0.005)) < 0.3 * 0.04
    np.testing.assert_array_equal(m.pose_for(TRUE[0].T_world_cam), TRUE[0].T_world_cam)
    # snapshots keep the corrections
    buf = io.BytesIO()
    torch.save(m.state_dict(), buf)
    buf.seek(0)
    back = Mapper(m.cfg)
    back.load_state_dict(torch.load(buf, weights_only=True))
    np.testing.assert_allclose(back.keyframe_pose(kfs[2]), m.keyframe_pose(kfs[2]))


def test_repaired_views_keep_the_pose_they_were_asked_at(corrected_map):
    m = Mapper(corrected_map.cfg)
    m.load_state_dict(corrected_map.state_dict())  # a copy: the fixture stays as mapped
    image = np.full((36, 48, 3), 128, np.uint8)
    T = make_T(np.eye(3), [0.1, 0.0, 0.0])
    assert m.store.latest is not None
    res = m.distill(image, T, m.store.latest.frame.intrinsics.K, iters=3)
    kf = m.store[res.keyframe_id]
    assert kf.kf_id not in m.poses and len(m.poses) == len(corrected_map.poses) >= 2
    np.testing.assert_array_equal(m.keyframe_pose(kf), kf.frame.T_world_cam)
