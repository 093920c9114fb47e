"""The planner's state machine: progress gate and probes, pacing, re-sends, skip decisions."""

from __future__ import annotations

import numpy as np
import pytest

from gsfix_online.repair.planner import SkipPolicy
from gsfix_online.repair.scheduler import PacingPolicy, ProposalPolicy, ViewPlanner
from gsfix_online.repair.views import View, propose_around, read_views

H, W = 24, 32
K = np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])


def renders(holes: bool):
    gs = np.full((H, W, 3), 120, np.uint8)
    alpha = np.ones((H, W), np.float32)
    if holes:
        alpha[:, : W // 2] = 0.0
    gs_reply = {"color": gs, "alpha": alpha, "depth": np.ones((H, W), np.float32)}
    mesh_reply = {"color": gs.copy(), "alpha": np.ones((H, W), np.float32),
                  "depth": np.full((H, W), 2.0, np.float32)}  # fmt: skip
    return gs_reply, mesh_reply


def planner(**pacing) -> ViewPlanner:
    p = ViewPlanner(SkipPolicy(), PacingPolicy(**pacing), camera=(K, W, H))
    for i in range(3):
        p.add_view(View(i, np.eye(4)))
    return p


def test_views_wait_for_the_maps_and_probes_are_paced():
    p = planner(min_frames=10, probe_every_s=2.0)
    asks = p.poll(0.0)
    assert [a.request_id for a in asks] == [-1] and asks[0].what == ("alpha",)
    assert p.poll(1.0) == []  # next probe not due
    assert p.on_reply("gs", -1, 10, {}, 1.0) is None and not p.gate_open
    assert p.poll(2.0) == []  # due, but the mesh server has not answered probe -1 yet
    p.on_reply("mesh", -1, 3, {}, 2.1)
    assert [a.request_id for a in p.poll(2.2)] == [-2]
    p.on_reply("mesh", -2, 10, {}, 2.5)
    assert p.gate_open
    asks = p.poll(2.5)
    assert [a.request_id for a in asks] == [0]  # max_in_flight = 1
    assert (asks[0].width, asks[0].height) == (W, H) and np.array_equal(asks[0].K, K)


def test_a_view_is_decided_when_both_renders_are_in_and_resent_after_a_timeout():
    p = planner(reply_timeout_s=5.0, min_interval_s=1.0)
    assert [a.request_id for a in p.poll(0.0)] == [0]
    gs, mesh = renders(holes=True)
    assert p.on_reply("gs", 0, None, gs, 0.5) is None
    assert p.poll(0.8) == []  # one in flight
    assert [a.request_id for a in p.poll(5.0)] == [0] and p.n_resent == 1  # mesh reply lost
    d = p.on_reply("mesh", 0, None, mesh, 5.5)
    assert d is not None and d.score.repair and "holes 50.0%" in d.score.reason
    assert d.seconds == pytest.approx(5.5) and d.mesh_valid.all()
    assert p.on_reply("mesh", 0, None, mesh, 5.6) is None  # a duplicate after the re-send
    assert [a.request_id for a in p.poll(5.6)] == [1]
    gs, mesh = renders(holes=False)
    p.on_reply("gs", 1, None, gs, 6.0)
    d = p.on_reply("mesh", 1, None, mesh, 6.0)
    assert d is not None and not d.score.repair and d.score.reason.startswith("map explains")


def test_views_without_a_camera_take_the_first_keyframes():
    p = ViewPlanner(SkipPolicy(), PacingPolicy())
    p.add_view(View(-1, np.eye(4)))  # gets id 0
    assert p.poll(0.0) == []  # input camera unknown yet
    p.on_keyframe(np.eye(4), K, W, H)
    (ask,) = p.poll(0.1)
    assert ask.request_id == 0 and (ask.width, ask.height) == (W, H)


def test_proposals_beside_keyframes():
    p = ViewPlanner(
        SkipPolicy(), PacingPolicy(), ProposalPolicy(every_keyframes=2, max_proposals=3)
    )
    assert p.on_keyframe(np.eye(4), K, W, H) == []
    views = p.on_keyframe(np.eye(4), K, W, H)
    assert [v.view_id for v in views] == [0, 1] and all(v.origin == "proposal" for v in views)
    p.on_keyframe(np.eye(4), K, W, H)
    assert len(p.on_keyframe(np.eye(4), K, W, H)) == 1  # max_proposals
    left, right = propose_around(np.eye(4), 30.0, 0.5)
    np.testing.assert_allclose(left[:3, 3], [0, 0, -0.5])  # stepped back along +z
    np.testing.assert_allclose(left[:3, 2], [np.sin(np.pi / 6), 0, np.cos(np.pi / 6)], atol=1e-12)
    np.testing.assert_allclose(right[:3, 2], [-np.sin(np.pi / 6), 0, np.cos(np.pi / 6)], atol=1e-12)


def test_view_list_keeps_file_order_and_equal_stamps(tmp_path):
    f = tmp_path / "views.txt"
    f.write_text("# views\n5 1 2 3 0 0 0 1\n5 4 5 6 0 0 0 1\n1 7 8 9 0 0 0 1\n")
    views = read_views(f)
    assert [v.view_id for v in views] == [0, 1, 2]
    assert [v.T_world_cam[0, 3] for v in views] == [1.0, 4.0, 7.0]


def test_an_unanswered_probe_is_replaced_after_the_reply_timeout():
    p = planner(min_frames=10, probe_every_s=1.0, reply_timeout_s=5.0)
    assert [a.request_id for a in p.poll(0.0)] == [-1]
    assert p.poll(1.0) == [] and p.poll(4.9) == []  # a busy map: no probes pile up behind it
    assert [a.request_id for a in p.poll(5.0)] == [-2]
