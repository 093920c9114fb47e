"""The repair node's component: the choice per region measured on held-out input frames."""

from __future__ import annotations

import json
import logging
from dataclasses import replace

import numpy as np
import pytest

from gsfix_online.fixer.config import FixerConfig, InferenceConfig
from gsfix_online.repair.fallback import BLEND_DETAIL_PX, FLAT, REGIONS, Choice
from gsfix_online.repair.outputs import write_png
from gsfix_online.runtime import Message
from gsfix_online.runtime.requests import render_request
from gsfix_online.runtime.wire import decode, encode
from gsfix_online.services.repair import Params, RepairService
from tests.fixer.conftest import tiny_model_cfg
from tests.mapping.splat.test_mapper import H, K, W, plane_frame


def wire(msg: Message) -> Message:
    """``msg`` as a receiver gets it: checked against its type's schema."""
    return decode(encode(msg))


def _texture(seed: int) -> np.ndarray:  # [H, W, 3] uint8, smooth
    v, u = np.mgrid[0:H, 0:W]
    img = np.stack([120 + 60 * np.sin(u / 5 + seed), 120 + 50 * np.cos(v / 4), 100 + u], axis=2)
    return np.clip(img, 0, 255).astype(np.uint8)


def _decision(vid: int, kind: str, gt: np.ndarray) -> Message:
    """The planner's renders of a held-out frame: the 3DGS render is the camera image with a
    hole (left quarter), the mesh render sees everything but 40 levels too bright."""
    alpha = np.ones((H, W), np.float32)
    alpha[:, : W // 4] = 0.0
    if kind == "gs":
        color = gt.copy()
        color[alpha < 0.5] = 0
        arrays = {"color": color, "alpha": alpha}
    else:
        color = np.clip(gt.astype(int) + 40, 0, 255).astype(np.uint8)
        arrays = {"color": color, "alpha": np.ones((H, W), np.float32)}
    return Message(f"decision/planner/{kind}", "render_reply", vid,
                   meta={"view_id": vid, "request_id": vid}, arrays=arrays)  # fmt: skip


def _holdout_service(tmp_path) -> RepairService:  # noqa: ANN001
    """Held-out frames 1 and 2 with their camera images; a fresh residual GSFixer returns its
    3DGS input, so holes stay black and the fallbacks win there."""
    gt_dir = tmp_path / "gt"
    gt_dir.mkdir()
    for vid in (1, 2):
        write_png(gt_dir / f"{vid:03d}.png", _texture(vid))
    fixer = FixerConfig(model=tiny_model_cfg(residual=True), inference=InferenceConfig(steps=1))
    params = Params(fixer=fixer, checkpoint="base", holdout_views=[1, 3], gt_dir=str(gt_dir))
    return RepairService("repair", params, 0.0)


def test_the_choice_is_measured_on_the_held_out_frames_before_any_repair(tmp_path):
    # where both maps cover, the exact 3DGS render (mesh fill) beats the bright mesh
    svc = _holdout_service(tmp_path)
    assert svc.choice.per_region["both"] == "fixed"  # nothing measured yet
    svc.on_view(render_request("planner", 0, plane_frame(0).T_world_cam, K.K, W, H,
                               ("color", "alpha"), topic="view/planner",
                               meta={"view_id": 0}))  # fmt: skip
    svc.on_reply(_decision(0, "gs", _texture(0)))  # the user's view: not a held-out frame
    svc.on_reply(_decision(1, "gs", _texture(1)))
    svc.on_reply(_decision(1, "mesh", _texture(1)))
    svc.on_reply(_decision(2, "gs", _texture(2)))
    assert svc.work(1.0) == ([], False)  # frame 2's mesh render has not come: no repair yet
    assert sorted(svc.holdout) == [1, 2]
    svc.on_reply(_decision(2, "mesh", _texture(2)))
    out, _ = svc.work(2.0)
    assert [m.type for m in out] == ["render_request"]  # the view goes ahead
    c = svc.choice
    assert "2 held-out input frames" in c.why and c.samples == 2
    assert c.per_region["both"] == "inpaint" and c.per_region["mesh_only"] != "fixed"
    assert c.mse["both"]["inpaint"] == 0.0 and c.mse["both"]["mesh_inpaint"] > 1000
    assert svc.holdout_version == svc.repairer.version == 0
    # measured once per model: more decisions change nothing
    svc.on_reply(_decision(1, "gs", _texture(5)))
    svc.work(3.0)
    assert svc.choice is c


def test_without_held_out_frames_repairs_do_not_wait():
    fixer = FixerConfig(model=tiny_model_cfg(residual=True), inference=InferenceConfig(steps=1))
    svc = RepairService("repair", Params(fixer=fixer, checkpoint="base"), 0.0)
    svc.on_view(render_request("planner", 0, plane_frame(0).T_world_cam, K.K, W, H,
                               ("color", "alpha"), topic="view/planner",
                               meta={"view_id": 0}))  # fmt: skip
    out, _ = svc.work(0.0)
    assert [m.type for m in out] == ["render_request"]
    assert svc.choice.per_region["both"] == "fixed"


def test_regions_the_held_out_frames_lack_are_measured_with_the_views_holes_cut_in(tmp_path):
    """Held-out frames lie on the mapped trajectory: here no pixel of them is outside both maps.
    The views to repair have such a part (their right half); its shape is cut into the held-out
    frames to measure that region (and the others they lack), and the choice says so."""
    svc = _holdout_service(tmp_path)
    empty = np.zeros((H, W), np.float32)
    empty[:, : W // 2] = 1.0  # the user's view: nothing in its right half
    for kind in ("gs", "mesh"):
        svc.on_reply(Message(f"decision/planner/{kind}", "render_reply", 0,
                             meta={"view_id": 0, "request_id": 0, "repair": True},
                             arrays={"color": np.zeros((H, W, 3), np.uint8),
                                     "alpha": empty}))  # fmt: skip
    assert list(svc.hole_shapes) == [0] and svc.hole_shapes[0].sum() == H * (W - W // 2)
    svc.on_view(render_request("planner", 0, plane_frame(0).T_world_cam, K.K, W, H,
                               ("color", "alpha"), topic="view/planner",
                               meta={"view_id": 0}))  # fmt: skip
    for vid in (1, 2):
        for kind in ("gs", "mesh"):
            svc.on_reply(_decision(vid, kind, _texture(vid)))
    out, _ = svc.work(1.0)
    assert [m.type for m in out] == ["render_request"]
    c = svc.choice
    assert c.pixels["neither"] == 0 and "1 views' holes cut in" in c.why
    assert "neither: 0 px measured, takes the backup measurement's" in c.why
    # a fresh residual GSFixer leaves the cut hole black: a fallback fills it
    assert c.per_region["neither"] in ("inpaint", "mesh_inpaint")
    assert c.per_region["both"] == "inpaint"  # measured on the frames as they are


def _reply(vid: int, server: str, gt: np.ndarray) -> Message:
    d = _decision(vid, "gs" if server == "splat" else "mesh", gt)
    return Message(f"render_reply/repair/{server}", "render_reply", vid,
                   meta={"request_id": vid}, arrays=d.arrays)  # fmt: skip


def test_a_view_farther_from_the_keyframes_than_the_held_out_frames_takes_the_mesh_first(
    tmp_path,
):
    """The held-out frames (0.10 and 0.25 m from a keyframe) measure the 3DGS render best where
    it covers; the trainer measured GSFixer best over all its samples. A view 0.20 m off takes
    the held-out choice per region, one 1.4 m off takes the mesh where it covers and GSFixer
    and mesh + Telea half and half in the holes, and each repair says which and why; the distilled mask follows the view's own
    choice."""
    svc = _holdout_service(tmp_path)
    svc.params = replace(svc.params, distill_mask="delivered")  # as the repair graph
    svc.trainer_choice = Choice(dict.fromkeys(REGIONS, "fixed"),
                                {r: {"fixed": 1.0, "inpaint": 9.0, "mesh_inpaint": 9.0}
                                 for r in REGIONS}, dict.fromkeys(REGIONS, 100), 4,
                                "4 held-out samples; overall best fixed")  # fmt: skip
    for vid, dist in ((1, 0.10), (2, 0.25)):
        for kind in ("gs", "mesh"):
            d = _decision(vid, kind, _texture(vid))
            d.meta["keyframe_distance_m"] = dist
            svc.on_reply(d)
    assert svc.holdout_reach == 0.25
    out, inputs = {}, {}
    grown = np.zeros((H, W), np.float32)
    grown[: H // 4, W // 2 :] = 0.9
    for vid, dist in ((0, 0.20), (3, 1.4)):
        svc.on_view(render_request("planner", vid, plane_frame(0).T_world_cam, K.K, W, H,
                                   ("color", "alpha"), topic="view/planner",
                                   meta={"view_id": vid, "keyframe_distance_m": dist}))  # fmt: skip
        sent, _ = svc.work(1.0 + vid)
        assert [m.type for m in sent] == ["render_request"]
        gs = _reply(vid, "splat", _texture(vid))
        if vid == 0:  # the top of its right half shows what other views' repairs grew
            gs.arrays["synthesised"] = grown
        svc.on_reply(gs)
        svc.on_reply(_reply(vid, "tsdf", _texture(vid)))
        msgs, _ = svc.work(2.0 + vid)
        out[vid] = next(m for m in msgs if m.type == "repaired_view")
        inputs[vid] = next(m for m in msgs if m.topic.endswith("/gs"))
    near, far = out[0].meta, out[3].meta
    assert svc.near_measured and svc.choice.per_region["both"] == "inpaint"
    assert near["choice_from"] == "held-out frames" and near["keyframe_distance_m"] == 0.20
    assert Choice.from_json(near["choice"]).per_region == svc.choice.per_region
    assert far["choice_from"] == "mesh first"
    assert near["feather_px"] == far["feather_px"] == svc.params.feather_px  # for its provenance
    assert near["detail_px"] == far["detail_px"] == BLEND_DETAIL_PX  # how its blends were made
    c = Choice.from_json(far["choice"])
    assert [c.source(r) for r in REGIONS] == [("mesh_inpaint", 0.0), ("inpaint", 0.0),
                                              ("mesh_inpaint", 0.0), ("mesh_inpaint", 0.5)]  # fmt: skip
    assert "1.40 m" in c.why
    assert Choice.from_json(far["measured_choice"]).per_region == svc.choice.per_region
    # how far the measurement holds, for the writer's skipped views
    assert near["holdout_reach_m"] == far["holdout_reach_m"] == 0.25
    # near: the 3DGS render is kept where it covers, so only the hole (left quarter) is
    # distilled, and the part of the render other views' repairs grew (a hole the map filled:
    # the view keeps what it delivered there); far: the mesh replaced the rest of the view
    band = svc.params.distill_dilate_px
    mask = out[0].arrays["mask"]
    assert (mask[: H // 4, W // 2 :] == 255).all()
    assert mask[H // 4 + band :, W // 2 :].max() == 0
    assert out[3].arrays["mask"].min() > 0
    # the writer gets the share with the render, for the view's provenance
    np.testing.assert_array_equal(inputs[0].arrays["synthesised"], grown)
    assert "synthesised" not in inputs[3].arrays


def _renders(vid: int, gt: np.ndarray, gs_off: int, mesh_off: int, topic: str) -> list[Message]:
    """Both renders of frame ``vid`` covering it all, ``gs_off`` and ``mesh_off`` levels
    brighter than its camera image, as ``topic`` (a decision or the repair's own reply)."""
    out = []
    for kind, off in (("gs", gs_off), ("mesh", mesh_off)):
        color = np.clip(gt.astype(int) + off, 0, 255).astype(np.uint8)
        t = f"decision/planner/{kind}" if topic == "decision" else \
            f"render_reply/repair/{'splat' if kind == 'gs' else 'tsdf'}"  # fmt: skip
        out.append(Message(t, "render_reply", vid,
                           meta={"view_id": vid, "request_id": vid, "keyframe_distance_m": 0.1},
                           arrays={"color": color, "alpha": np.ones((H, W), np.float32)}))  # fmt: skip
    return out


def test_a_held_out_frame_follows_the_choice_the_other_held_out_frames_measured(tmp_path):
    """Frame 1's mesh render is exact and its 3DGS render 30 levels off; frame 2's 3DGS render
    is exact and its mesh 40 off. Over both the 3DGS render (mesh fill + Telea) is best, which
    the views to repair take; but each held-out frame is scored against its own image, so it
    follows what the *other* frame measured: frame 2 takes the mesh, though its own image
    would pick the 3DGS render."""
    svc = _holdout_service(tmp_path)
    offsets = {1: (30, 0), 2: (0, 40)}
    for vid, (g, m) in offsets.items():
        for msg in _renders(vid, _texture(vid), g, m, "decision"):
            svc.on_reply(msg)
    assert svc.holdout_reach == 0.1
    sent = {}
    for vid in (0, 2):  # a view to repair, then held-out frame 2
        svc.on_view(render_request("planner", vid, plane_frame(0).T_world_cam, K.K, W, H,
                                   ("color", "alpha"), topic="view/planner",
                                   meta={"view_id": vid, "keyframe_distance_m": 0.1}))  # fmt: skip
        assert [m.type for m in svc.work(1.0 + vid)[0]] == ["render_request"]
        for msg in _renders(vid, _texture(2), *offsets[2], "reply"):
            svc.on_reply(msg)
        msgs, _ = svc.work(2.0 + vid)
        sent[vid] = wire(next(m for m in msgs if m.type == "repaired_view"))
    assert svc.choice.per_region["both"] == "inpaint"
    assert {v: c.per_region["both"] for v, c in svc.own_choice.items() if c} == {
        1: "inpaint", 2: "mesh_inpaint"}  # fmt: skip
    assert "without frame 2" in svc.own_choice[2].why
    view, frame = sent[0].meta, sent[2].meta
    assert view["choice_from"] == "held-out frames"
    assert Choice.from_json(view["choice"]).per_region["both"] == "inpaint"
    assert frame["choice_from"] == "the other held-out frames"
    assert Choice.from_json(frame["choice"]).per_region["both"] == "mesh_inpaint"
    # its output is the mesh (+40), not its exact 3DGS render
    out = sent[2].arrays["color"].astype(int)
    assert abs(np.median(out - _texture(2).astype(int)) - 40) <= 1
    # the writer gets each frame's own choice, for the held-out frames it composes itself
    without = json.loads(frame["measured_choice_without"])
    assert without["2"]["per_region"]["both"] == "mesh_inpaint"


def test_a_lone_held_out_frame_takes_no_choice_from_its_own_image(tmp_path):
    svc = _holdout_service(tmp_path)
    svc.params = replace(svc.params, holdout_views=[1, 2])
    for msg in _renders(1, _texture(1), 0, 40, "decision"):
        svc.on_reply(msg)
    svc.on_view(render_request("planner", 1, plane_frame(0).T_world_cam, K.K, W, H,
                               ("color", "alpha"), topic="view/planner",
                               meta={"view_id": 1, "keyframe_distance_m": 0.1}))  # fmt: skip
    svc.work(1.0)
    for msg in _renders(1, _texture(1), 0, 40, "reply"):
        svc.on_reply(msg)
    msgs, _ = svc.work(2.0)
    meta = next(m for m in msgs if m.type == "repaired_view").meta
    assert svc.near_measured and svc.own_choice == {1: None}
    assert meta["choice_from"] == "trainer"  # not its own truth (no trainer choice: GSFixer)
    assert json.loads(meta["measured_choice_without"]) == {"1": None}  # for the writer


def test_the_far_no_map_share_and_flatness_are_checked_where_they_are_read() -> None:
    from gsfix_online.core.config import ConfigError, build

    assert build(Params, overrides=["far_neither_share=1"]).far_neither_share == 1.0
    with pytest.raises(ConfigError, match=r"far_neither_share: value 1.5 is out of range \[0, 1\]"):
        build(Params, overrides=["far_neither_share=1.5"])
    assert build(Params, overrides=["flat_hole_std=0"]).flat_hole_std == 0.0  # off
    assert build(Params, overrides=["far_gs_only_holes=all"]).far_gs_only_holes == "all"
    with pytest.raises(ConfigError, match="far_gs_only_holes"):
        build(Params, overrides=["far_gs_only_holes=some"])


def test_the_wait_message_names_the_run_awaited_and_the_runs_ended_so_far() -> None:
    fixer = FixerConfig(model=tiny_model_cfg(residual=True), inference=InferenceConfig(steps=1))
    svc = RepairService("repair", Params(fixer=fixer, checkpoint="run"), 0.0)
    assert svc.waiting_for(1) == "the trainer's plan (sent when the input ends)"
    reason = "run 1 is on; run 2 follows on all 16 training and 4 held-out samples"
    plan = {"run": 2, "will_train": True, "reason": reason, "train": 16, "holdout": 4,
            "max_steps": 600, "version": 1, "step": 20}  # fmt: skip
    svc.on_plan(wire(Message("trainer_plan/trainer", "trainer_plan", 0, meta=plan)))
    ckpt = {"path": "", "version": 1, "step": 20, "run": 1, "run_done": True, "mode": "gs_mesh"}
    svc.on_checkpoint(wire(Message("checkpoint/trainer", "model_checkpoint", 0, meta=ckpt)))
    assert svc.runs_done == 1
    assert (
        svc.waiting_for(2)
        == f"fine-tuning run 2 to end (1 ended so far; when the input ended: {reason})"
    )


def _ref_decision(vid: int, value: int) -> Message:
    alpha = np.zeros((H, W), np.float32)
    alpha[:, W // 2 :] = 1.0
    color = np.full((H, W, 3), value, np.uint8) * (alpha[..., None] > 0)
    return Message("decision/planner/ref", "render_reply", vid,
                   meta={"view_id": vid, "request_id": vid},
                   arrays={"color": color, "alpha": alpha})  # fmt: skip


def test_in_mode_mesh_gs_ref_each_view_is_repaired_with_its_own_warp() -> None:
    """A view's warp (its decision's ``ref``), a held-out frame's (kept with its renders), and
    none for a view the planner warped nothing into."""
    fixer = FixerConfig(model=tiny_model_cfg("mesh+gs+ref"), inference=InferenceConfig(steps=1))
    svc = RepairService("repair", Params(fixer=fixer, checkpoint="base", holdout_views=[1, 2]),
                        0.0)  # fmt: skip
    seen: dict[int, tuple] = {}
    inner = svc.repairer.repair

    def spy(gs, mesh, ref_color=None, ref_valid=None):  # noqa: ANN001, ANN202
        seen[len(seen)] = (ref_color, ref_valid)
        return inner(gs, mesh, ref_color, ref_valid)

    svc.repairer.repair = spy  # type: ignore[method-assign]
    svc.on_reply(wire(_ref_decision(0, 200)))
    svc.on_reply(wire(_ref_decision(1, 90)))
    assert set(svc.view_refs) == {0, 1} and "ref" in svc.holdout[1]
    for vid in (0, 1, 2):
        svc.on_view(render_request("planner", vid, plane_frame(0).T_world_cam, K.K, W, H,
                                   ("color", "alpha"), topic="view/planner",
                                   meta={"view_id": vid}))  # fmt: skip
        sent, _ = svc.work(1.0 + vid)
        assert [m.type for m in sent] == ["render_request"]
        svc.on_reply(_reply(vid, "splat", _texture(vid)))
        svc.on_reply(_reply(vid, "tsdf", _texture(vid)))
        msgs, _ = svc.work(2.0 + vid)
        assert any(m.type == "repaired_view" for m in msgs)
    for vid, value in ((0, 200), (1, 90)):
        color, valid = seen[vid]
        assert valid.dtype == np.bool_ and valid[:, W // 2 :].all() and not valid[:, : W // 2].any()
        assert (color[:, W // 2 :] == value).all()
    assert seen[2] == (None, None)
    assert svc.counts["with_references"] == 2 and not svc.view_refs


def test_the_reference_warp_is_measured_on_the_held_out_frames_and_used_where_it_wins(tmp_path):
    """The planner's warp of the real frames nearest each view (``decision/<planner>/ref``):
    at the held-out frames it is the truth while both renders are off, so every region chooses
    ``ref_inpaint``; a held-out frame that is also repaired is composed from its own warp."""
    svc = _holdout_service(tmp_path)
    every = np.ones((H, W), np.float32)

    def decision(vid: int, kind: str) -> Message:
        gt = _texture(vid)
        if kind == "ref":
            arrays = {"color": gt, "alpha": every}
        else:
            arrays = _decision(vid, kind, gt).arrays
            arrays["color"] = np.clip(gt.astype(int) + (-30 if kind == "gs" else 40), 0, 255)
            arrays["color"] = arrays["color"].astype(np.uint8)
        return wire(Message(f"decision/planner/{kind}", "render_reply", vid,
                            meta={"view_id": vid, "request_id": vid}, arrays=arrays))  # fmt: skip

    for vid in (1, 2):
        for kind in ("gs", "mesh", "ref"):
            svc.on_reply(decision(vid, kind))
    svc.on_view(render_request("planner", 1, plane_frame(0).T_world_cam, K.K, W, H,
                               ("color", "alpha"), topic="view/planner",
                               meta={"view_id": 1}))  # fmt: skip
    sent, _ = svc.work(1.0)
    assert [m.type for m in sent] == ["render_request"]
    assert svc.choice.per_region == dict.fromkeys(REGIONS, "ref_inpaint")
    assert svc.choice.mse["both"]["ref_inpaint"] == 0.0 < svc.choice.mse["both"]["inpaint"]
    for server, kind in (("splat", "gs"), ("tsdf", "mesh")):
        d = decision(1, kind)
        svc.on_reply(Message(f"render_reply/repair/{server}", "render_reply", 1,
                             meta={"request_id": 1}, arrays=d.arrays))  # fmt: skip
    msgs, _ = svc.work(2.0)
    repaired = next(m for m in msgs if m.type == "repaired_view")
    np.testing.assert_array_equal(repaired.arrays["color"], _texture(1))
    assert svc.counts["with_references"] == 1


def test_a_far_views_no_map_hole_in_a_flat_wall_takes_mesh_and_telea_alone():
    """Without held-out frames every view takes the mesh first. Of its two no-map holes, the one
    in a flat grey wall takes mesh + Telea alone (fallback.far_regions) and the repair sends it
    with its regions; the one in the textured part keeps GSFixer half and half. What only the
    3DGS map covers (observed, or grown by repaired views) is a hole too."""
    fixer = FixerConfig(model=tiny_model_cfg(residual=True), inference=InferenceConfig(steps=1))
    params = Params(fixer=fixer, checkpoint="base", distill_mask="delivered")  # as the graph
    svc = RepairService("repair", params, 0.0)
    svc.trainer_choice = Choice(dict.fromkeys(REGIONS, "fixed"),
                                {r: {"fixed": 1.0, "inpaint": 9.0, "mesh_inpaint": 9.0}
                                 for r in REGIONS}, dict.fromkeys(REGIONS, 100), 4, "")  # fmt: skip
    mesh = _texture(0)
    mesh[:, : W // 2] = 120  # a flat wall on the left
    valid = np.ones((H, W), np.float32)
    flat_hole, textured_hole = (slice(8, 18), slice(6, 16)), (slice(14, 26), slice(30, 40))
    valid[flat_hole] = valid[textured_hole] = 0.0
    alpha = np.zeros((H, W), np.float32)  # the 3DGS map covers two patches the mesh lacks
    grown, seen = (slice(26, 36), slice(36, 46)), (slice(26, 36), slice(20, 30))
    valid[grown] = valid[seen] = 0.0
    alpha[grown] = alpha[seen] = 1.0
    synthesised = np.zeros((H, W), np.float32)
    synthesised[grown] = 1.0  # what other views' repairs grew
    svc.on_view(render_request("planner", 5, plane_frame(0).T_world_cam, K.K, W, H,
                               ("color", "alpha"), topic="view/planner",
                               meta={"view_id": 5, "keyframe_distance_m": 2.0}))  # fmt: skip
    sent, _ = svc.work(1.0)
    assert [m.type for m in sent] == ["render_request"]
    meta = {"request_id": 5}
    gs = {"color": np.zeros((H, W, 3), np.uint8), "alpha": alpha, "synthesised": synthesised}
    svc.on_reply(Message("render_reply/repair/splat", "render_reply", 5, meta=meta, arrays=gs))
    svc.on_reply(Message("render_reply/repair/tsdf", "render_reply", 5, meta=meta,
                         arrays={"color": mesh, "alpha": valid}))  # fmt: skip
    msgs, _ = svc.work(2.0)
    rv = wire(next(m for m in msgs if m.type == "repaired_view"))
    assert rv.meta["choice_from"] == "mesh first"
    region = rv.arrays["region"]  # what the output was composed by, for its provenance
    assert (region[flat_hole] == FLAT).all() and (region[textured_hole] == 3).all()
    assert int((region == FLAT).sum()) == 100 and svc.counts["flat_holes"] == 1
    # what repaired views grew: a hole (the default, "grown"); what the 3DGS map observed: kept
    assert (region[grown] == 3).all() and (region[seen] == 1).all()
    # distilled where repaired views grew it (the view fits what it delivered there), not where
    # the 3DGS map observed it (the middles lie beyond the holes' widening)
    middle, grown_middle = (slice(29, 33), slice(23, 27)), (slice(29, 33), slice(39, 43))
    assert (rv.arrays["mask"][grown_middle] == 255).all()
    assert (rv.arrays["mask"][middle] == 0).all()

    def again(vid: int, holes: str) -> Message:  # the same view, another far_gs_only_holes
        svc.params = replace(svc.params, far_gs_only_holes=holes)
        svc.on_view(render_request("planner", vid, plane_frame(0).T_world_cam, K.K, W, H,
                                   ("color", "alpha"), topic="view/planner",
                                   meta={"view_id": vid, "keyframe_distance_m": 2.0}))  # fmt: skip
        svc.work(3.0 + vid)
        meta = {"request_id": vid}
        svc.on_reply(Message("render_reply/repair/splat", "render_reply", vid, meta=meta,
                             arrays=gs))  # fmt: skip
        svc.on_reply(Message("render_reply/repair/tsdf", "render_reply", vid, meta=meta,
                             arrays={"color": mesh, "alpha": valid}))  # fmt: skip
        msgs, _ = svc.work(4.0 + vid)
        return next(m for m in msgs if m.type == "repaired_view")

    every = again(6, "all")  # the observed part too, but the map keeps it: not distilled,
    # nor the band of the neighbouring holes' widening over it
    assert (every.arrays["region"][seen] == 3).all() and (every.arrays["mask"][seen] == 0).all()
    assert (every.arrays["mask"][grown] == 255).all()
    kept = again(7, "none")  # the 3DGS render wherever only the 3DGS map covers
    assert (kept.arrays["region"][seen] == 1).all() and (kept.arrays["region"][grown] == 1).all()
    out = rv.arrays["color"].astype(int)
    assert np.abs(out[10:16, 8:14] - 120).max() <= 3  # Telea carries the wall on
    fixed = next(m for m in msgs if m.topic.endswith("/fixer")).arrays["color"].astype(int)
    # the textured hole: half GSFixer (its 3DGS input is black there: a residual repair)
    inner = (slice(17, 23), slice(33, 37))
    assert np.abs(out[inner] - fixed[inner]).mean() > 20


def _distilled(vid: int, server: str = "splat") -> Message:
    return Message(f"distill/{server}", "map_event", vid, frame_id="world",
                   meta={"kind": "distilled", "version": vid + 1, "step": 10, "view_id": vid,
                         "distill_s": 1.0, "passes_pending": 4, "passes_s": 0.0,
                         "gaussians": 100})  # fmt: skip


def test_with_wait_distilled_the_next_view_waits_for_the_last_ones_distillation(caplog):
    """With wait_distilled the next view's renders are asked for only once the splat node has
    announced the last repaired view distilled (not another view's announcement, not another
    server's), or once ``distilled_wait_s`` has passed (counted); the wait says what it waits
    for; without it, at once."""
    fixer = FixerConfig(model=tiny_model_cfg(residual=True), inference=InferenceConfig(steps=1))
    for wait in (True, False):
        params = Params(fixer=fixer, checkpoint="base", wait_distilled=wait, distilled_wait_s=20)
        svc = RepairService("repair", params, 0.0)
        for vid in (0, 1, 2):
            svc.on_view(render_request("planner", vid, plane_frame(0).T_world_cam, K.K, W, H,
                                       ("color", "alpha"), topic="view/planner",
                                       meta={"view_id": vid}))  # fmt: skip
        sent, _ = svc.work(0.0)
        assert [m.type for m in sent] == ["render_request"]
        svc.on_reply(_reply(0, "splat", _texture(0)))
        svc.on_reply(_reply(0, "tsdf", _texture(0)))
        msgs, _ = svc.work(1.0)
        assert any(m.type == "repaired_view" for m in msgs)
        sent, _ = svc.work(2.0)
        if not wait:
            assert [m.type for m in sent] == ["render_request"]
            continue
        assert sent == []
        with caplog.at_level(logging.INFO, logger="gsfix_online.services.repair"):
            svc.next_log = 0.0
            svc.work(2.5)
        assert "2 views wait for the splat node to distil view 000" in caplog.text
        svc.on_map_event(wire(_distilled(5)))  # another view's announcement
        svc.on_map_event(wire(_distilled(0, "other")))  # another map's
        assert svc.work(3.0)[0] == []
        svc.on_map_event(wire(_distilled(0)))
        sent, _ = svc.work(4.0)
        assert [int(m.meta["request_id"]) for m in sent] == [1]
        svc.on_reply(_reply(1, "splat", _texture(1)))
        svc.on_reply(_reply(1, "tsdf", _texture(1)))
        svc.work(5.0)
        assert svc.work(24.0)[0] == [] and svc.counts["distill_waits_timed_out"] == 0
        sent, _ = svc.work(25.5)  # view 1 was never announced: given up 20 s after it was sent
        assert [int(m.meta["request_id"]) for m in sent] == [2]
        assert svc.counts["distill_waits_timed_out"] == 1
