"""Planner, repair and splat-distillation nodes on the in-memory transport."""

from __future__ import annotations

import dataclasses
import json
import logging

import numpy as np
import torch
from gsfix_online.nodes import planner, repair, splat
from gsfix_online.nodes._common import render_request

from gsfix_online.fixer.config import FixerConfig, InferenceConfig, ModelConfig
from gsfix_online.repair.fallback import REGIONS, Choice
from gsfix_online.repair.planner import SkipPolicy
from gsfix_online.repair.provenance import GS, GS_REPAIRED, MESH
from gsfix_online.repair.scheduler import PacingPolicy
from gsfix_online.runtime import InMemoryTransport, Message, NodeRuntimeConfig, frame_to_message
from gsfix_online.runtime.wire import decode, encode
from tests.fixer.conftest import TINY_DEFAULT
from tests.mapping.splat.test_mapper import CFG, H, K, W, plane_frame

RUNTIME = NodeRuntimeConfig(poll_timeout_ms=0, on_handler_error="raise")


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def reply(requester: str, server: str, rid: int, holes: bool, frames: int = 5) -> Message:
    alpha = np.ones((H, W), np.float32)
    if holes:
        alpha[:, : W // 2] = 0
    color = np.full((H, W, 3), 128, np.uint8)
    return Message(f"render_reply/{requester}/{server}", "render_reply",
                   meta={"request_id": rid, "frames": frames},
                   arrays={"color": color, "alpha": alpha,
                           "depth": np.full((H, W), 2.0, np.float32)})  # fmt: skip


def keyframe_message(keyframe_id: int = 0) -> Message:
    """The splat node's keyframe announcement of the plane seen from the origin (its 3DGS render
    the camera image, fully opaque)."""
    f = plane_frame(0.0)
    return Message("keyframe/splat", "keyframe", meta={"keyframe_id": keyframe_id},
                   arrays={"color": f.color, "depth": f.depth, "K": K.K,
                           "T_world_cam": f.T_world_cam, "gs_render": f.color,
                           "gs_alpha": np.ones((H, W), np.float32)})  # fmt: skip


def test_planner_node_scores_views_and_passes_on_those_that_need_repair(tmp_path):
    views = tmp_path / "views.txt"
    views.write_text("0 0 0 0 0 0 0 1\n0 0 0 0.1 0 0 0 1\n")
    t = InMemoryTransport()
    clock = Clock()
    params = planner.Params(views=str(views), pacing=PacingPolicy(min_frames=5))
    node, svc = planner.build_node("planner", params, t, RUNTIME, clock)
    t.feed(keyframe_message())
    node.run_until_idle()
    planner.step(node, svc, clock)
    (probe,) = [p for p in t.outbox if p.message.type == "render_request"]
    assert probe.reliable and probe.message.meta["request_id"] == -1
    assert probe.message.meta["reply_to"] == "planner"
    t.feed(reply("planner", "splat", -1, False))
    t.feed(reply("planner", "tsdf", -1, False))
    t.feed(reply("someone_else", "splat", 0, False))  # not ours: ignored
    node.run_until_idle()
    clock.t = 1.0
    planner.step(node, svc, clock)
    req = t.outbox[-1].message
    assert req.meta["request_id"] == 0 and (req.meta["width"], req.meta["height"]) == (W, H)
    np.testing.assert_array_equal(req.arrays["K"], K.K)  # the input camera, from the keyframe
    t.feed(reply("planner", "splat", 0, holes=True))
    t.feed(reply("planner", "tsdf", 0, holes=False))
    node.run_until_idle()
    out = [p for p in t.outbox if not p.message.topic.startswith(("render_request", "heartbeat"))]
    topics = [p.message.topic for p in out]
    assert topics == ["decision/planner/gs", "decision/planner/mesh", "decision/planner/ref",
                      "view/planner"]  # fmt: skip
    assert all(p.reliable for p in out)
    gs, mesh, ref, view = (p.message for p in out)
    # the keyframe, a real frame at the view's pose, warped into it by the mesh depth
    assert ref.meta["references"] == 1 and ref.arrays["alpha"].min() == 1.0
    np.testing.assert_array_equal(ref.arrays["color"], keyframe_message().arrays["color"])
    assert gs.meta["repair"] and "holes 50.0%" in gs.meta["reason"] and gs.meta["view_id"] == 0
    assert mesh.arrays["alpha"].min() == 1.0 and view.type == "render_request"
    assert view.meta["T_world_cam"] == np.eye(4).ravel().tolist()
    assert svc.stats()["planner/decided"] == 1


def test_repair_node_repairs_with_the_base_and_sends_reliably():
    fixer = FixerConfig(
        model=ModelConfig(default=TINY_DEFAULT, random_init=True),
        inference=InferenceConfig(steps=1),
    )
    t = InMemoryTransport()
    clock = Clock()
    node, svc = repair.build_node("repair", repair.Params(fixer=fixer), t, RUNTIME, clock)
    view = render_request("planner", 3, plane_frame(0).T_world_cam, K.K, W, H, ("color", "alpha"),
                          topic="view/planner", meta={"view_id": 3})  # fmt: skip
    t.feed(view)
    node.run_until_idle()
    repair.step(node, svc, clock)
    asks = [p.message for p in t.outbox if p.message.type == "render_request"]
    assert len(asks) == 1 and asks[0].meta["reply_to"] == "repair"
    t.feed(reply("repair", "splat", 3, holes=True))
    t.feed(reply("repair", "tsdf", 3, holes=False))
    node.run_until_idle()
    repair.step(node, svc, clock)
    out = {p.message.topic: p for p in t.outbox if not p.message.topic.startswith("render_req")}
    rv = out["repaired_view/repair"]
    assert rv.reliable and rv.message.meta["view_id"] == 3 and rv.message.meta["model_version"] == 0
    assert rv.message.arrays["color"].shape == (H, W, 3)
    # distillation fits the view where the map has holes (columns :W/2) and a 3-px band
    mask = rv.message.arrays["mask"]
    assert mask.dtype == np.uint8 and (mask[:, : W // 2 + 3] == 255).all()
    assert (mask[:, W // 2 + 3 :] == 0).all()
    assert out["repair_input/repair/gs"].message.arrays["alpha"].min() == 0.0
    assert svc.counts["repaired"] == 1


def test_splat_node_distils_then_runs_passes_between_messages(tmp_path, monkeypatch):
    n = torch.get_num_threads()
    torch.set_num_threads(1)  # see tests/mapping/splat/test_mapper.py
    try:
        _distil_and_pass(tmp_path)
    finally:
        torch.set_num_threads(n)


def _distil_and_pass(tmp_path):
    mapper = dataclasses.replace(CFG, kf_iters=1, non_kf_iters=0, distill_iters=2)
    params = splat.Params(
        mapper=mapper,
        distill_passes=2,
        pass_slice_steps=1,
        stats_every=100,
        write_root=str(tmp_path),
    )  # exports named in messages go there
    svc = splat.SplatService("splat", params)
    for i in range(2):
        svc.on_rgbd(frame_to_message(plane_frame(0.1 * i, i), "rgbd/cam0"))
    steps0 = svc.mapper.n_steps
    observed = svc.mapper.observed_ids()
    near = svc.mapper.nearest_observed(plane_frame(0.05).T_world_cam, params.kept_keyframes)
    kept_before = svc.mapper.observed_psnr(observed, params.kept_downscale)
    assert near and set(near) <= set(observed) == set(kept_before)
    rv = Message("repaired_view/repair", "repaired_view",
                 meta={"keyframe_id": -1, "model_step": 0, "view_id": 7},
                 arrays={"color": np.full((H, W, 3), 200, np.uint8), "K": K.K,
                         "T_world_cam": plane_frame(0.05).T_world_cam})  # fmt: skip
    first = svc.on_repaired_view(rv)
    n_views = len(svc.mapper.store)  # keyframes + the repaired view
    per_pass = -(-n_views // mapper.refine_views)
    assert first.topic == "distill/splat" and first.meta["version"] == 1
    assert first.meta["view_id"] == 7 and first.meta["passes_pending"] == 2 * per_pass
    assert svc.mapper.n_steps == steps0 + 2
    done = [svc.distill_passes(0) for _ in range(2 * per_pass)]
    assert done[-1] is not None and done[-1].meta["passes_pending"] == 0
    assert all(d is None for d in done[:-1]) and svc.distill_passes(0) is None
    assert svc.mapper.n_steps == steps0 + 2 + 2 * per_pass
    exp = svc.on_export(Message("splat/export", "command",
                                meta={"kind": "export", "path": str(tmp_path / "map")}))  # fmt: skip
    assert (
        exp.type == "map_event" and first.type == "map_event" and first.meta["kind"] == "distilled"
    )
    assert (
        exp.meta["kind"] == "exported"
        and exp.topic == "export/splat"
        and list((tmp_path / "map").glob("point_cloud/*/*.ply"))
    )
    # every input keyframe before the repaired view was distilled and now, its neighbours
    # marked with its id (kept_keyframes)
    kept_after = svc.mapper.observed_psnr(observed, params.kept_downscale)
    assert json.loads(exp.meta["keyframes_kept"]) == [
        {"keyframe_id": k, "view_id": 7 if k in near else -1, "before_db": kept_before[k],
         "after_db": kept_after[k]}
        for k in sorted(observed)
    ]  # fmt: skip
    assert decode(encode(exp)).meta == exp.meta  # it passes the wire's checks
    r = svc.on_render_request(render_request("writer", 1, plane_frame(0).T_world_cam, K.K, W, H,
                                             ("color",)))  # fmt: skip
    assert r.topic == "render_reply/writer/splat" and r.meta["frames"] == 2


def test_splat_node_logs_the_keyframes_after_each_distillation_stage(caplog):
    """With ``kept_stages`` the node logs every measured keyframe's change after the view's own
    steps, the passes and polish, and the repaired views' neighbours' apart; each figure is the
    render's PSNR now against the first one."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)  # see tests/mapping/splat/test_mapper.py
    try:
        mapper = dataclasses.replace(CFG, kf_iters=1, non_kf_iters=0, distill_iters=2,
                                     polish_below_db=100.0, polish_iters=2, polish_rounds=1)  # fmt: skip
        svc = splat.SplatService("splat", splat.Params(mapper=mapper, distill_passes=1,
                                                       pass_slice_steps=8, kept_stages=True))  # fmt: skip
        for i in range(3):  # half a metre apart: each frame a keyframe
            svc.on_rgbd(frame_to_message(plane_frame(0.5 * i, i), "rgbd/cam0"))
        rv = Message("repaired_view/repair", "repaired_view",
                     meta={"keyframe_id": -1, "model_step": 0, "view_id": 7},
                     arrays={"color": np.full((H, W, 3), 200, np.uint8), "K": K.K,
                             "T_world_cam": plane_frame(0.05).T_world_cam})  # fmt: skip
        with caplog.at_level(logging.INFO, logger="gsfix_online.services.splat"):
            svc.on_repaired_view(rv)
            while svc.distill_passes(0) is None:
                pass
        stages = [
            r.getMessage() for r in caplog.records if "input keyframes changed" in r.getMessage()
        ]
        assert [m.split(" after ")[1].split(" the ")[0] for m in stages] == [
            "repaired view 7's own steps", "the passes", "polish"]  # fmt: skip
        with caplog.at_level(logging.INFO, logger="gsfix_online.services.splat"):
            change = svc._log_kept("a check")
        now = svc.mapper.observed_psnr(svc.mapper.observed_ids())
        assert change == {k: now[k] - svc.kept_before[k] for k in now}
        assert set(change) == set(svc.mapper.observed_ids()) and change
        # the neighbours of the repaired view (kept_keyframes, 2 here): their median and count
        near = [change[k] for k in svc.kept_near]
        msg = caplog.records[-1].getMessage()
        assert len(change) == 3 and len(near) == 2, (change, near)
        assert f"the 2 neighbours of repaired views by {np.median(near):+.2f}" in msg, msg
        assert f"{sum(v < -0.1 for v in near)} lost over 0.1 dB" in msg, msg
        svc.params = dataclasses.replace(svc.params, kept_stages=False)
        assert svc._log_kept("off") == {}
        # a measured keyframe the map no longer stores keeps its row, with no after_db
        gone = svc.mapper.observed_ids()[0]
        svc.mapper.store.remove(gone)
        rows = {r["keyframe_id"]: r for r in svc.keyframes_kept()}
        assert set(rows) == set(svc.kept_before) and rows[gone]["after_db"] is None
        assert all(r["after_db"] is not None for k, r in rows.items() if k != gone)
    finally:
        torch.set_num_threads(n)


def test_repair_node_in_run_mode_waits_for_the_end_of_a_fine_tuning_run(tmp_path):
    from gsfix_online.fixer.checkpoint import save_checkpoint
    from gsfix_online.fixer.loader import load_fixer

    model = ModelConfig(default=TINY_DEFAULT, random_init=True)
    bundle = load_fixer(model)
    paths = [save_checkpoint(tmp_path, bundle, step, model) for step in (20, 40)]
    fixer = FixerConfig(model=model, inference=InferenceConfig(steps=1))
    t = InMemoryTransport()
    clock = Clock()
    params = repair.Params(fixer=fixer, checkpoint="run", checkpoint_wait_s=100.0)
    node, svc = repair.build_node("repair", params, t, RUNTIME, clock)
    t.feed(render_request("planner", 3, plane_frame(0).T_world_cam, K.K, W, H, ("color",),
                          topic="view/planner", meta={"view_id": 3}))  # fmt: skip

    def announce(version: int, done: bool, run: int = 1) -> Message:
        meta = {"path": str(paths[version - 1]), "version": version, "step": 20 * version,
                "run_done": done, "run": run, "mode": "gs_mesh"}  # fmt: skip
        return Message("checkpoint/trainer", "model_checkpoint", meta=meta)

    def asks() -> int:
        node.run_until_idle()
        repair.step(node, svc, clock)
        return sum(p.message.type == "render_request" for p in t.outbox)

    # An intermediate checkpoint of a run that goes on: the view waits, no model is loaded
    t.feed(announce(1, done=False))
    assert asks() == 0 and not svc.repairer.ready
    # The run's end: its checkpoint is loaded and the view goes ahead
    t.feed(announce(2, done=True))
    assert asks() == 1 and svc.repairer.version == 2
    # Without any announcement, `run` gives up after checkpoint_wait_s and takes the base
    t2, clock2 = InMemoryTransport(), Clock()
    node2, svc2 = repair.build_node("repair", params, t2, RUNTIME, clock2)
    repair.step(node2, svc2, clock2)
    assert not svc2.repairer.ready
    clock2.t = 100.0
    t2.feed(render_request("planner", 4, plane_frame(0).T_world_cam, K.K, W, H, ("color",),
                           topic="view/planner", meta={"view_id": 4}))  # fmt: skip
    node2.run_until_idle()
    repair.step(node2, svc2, clock2)
    assert svc2.repairer.ready and svc2.repairer.version == 0


def test_repair_node_in_run_mode_waits_for_as_many_runs_as_configured(tmp_path):
    from gsfix_online.fixer.checkpoint import save_checkpoint
    from gsfix_online.fixer.loader import load_fixer

    model = ModelConfig(default=TINY_DEFAULT, random_init=True)
    bundle = load_fixer(model)
    paths = [save_checkpoint(tmp_path, bundle, step, model) for step in (20, 40)]
    fixer = FixerConfig(model=model, inference=InferenceConfig(steps=1))
    t, clock = InMemoryTransport(), Clock()
    params = repair.Params(
        fixer=fixer, checkpoint="run", checkpoint_runs=2, checkpoint_wait_s=100.0
    )
    node, svc = repair.build_node("repair", params, t, RUNTIME, clock)
    t.feed(render_request("planner", 3, plane_frame(0).T_world_cam, K.K, W, H, ("color",),
                          topic="view/planner", meta={"view_id": 3}))  # fmt: skip

    def asks_after(version: int, run: int) -> int:
        meta = {"path": str(paths[version - 1]), "version": version, "step": 20 * version,
                "run_done": True, "run": run, "mode": "gs_mesh"}  # fmt: skip
        t.feed(Message("checkpoint/trainer", "model_checkpoint", meta=meta))
        node.run_until_idle()
        repair.step(node, svc, clock)
        return sum(p.message.type == "render_request" for p in t.outbox)

    # The end of run 1 is not enough; the end of run 2 brings its model and the view goes ahead
    assert asks_after(1, run=1) == 0 and not svc.repairer.ready
    assert asks_after(2, run=2) == 1 and svc.repairer.version == 2


def _planner_with_one_view(tmp_path):
    """A planner that holds one keyframe (the input camera) and has asked for one view's renders
    (surfaces seen once count as observed)."""
    views = tmp_path / "views.txt"
    views.write_text("0 0 0 0 0 0 0 1\n")
    t, clock = InMemoryTransport(), Clock()
    params = planner.Params(views=str(views), skip=SkipPolicy(min_observations=1))
    node, svc = planner.build_node("planner", params, t, RUNTIME, clock)
    t.feed(keyframe_message())
    node.run_until_idle()
    planner.step(node, svc, clock)
    return t, node, svc


def test_a_skipped_view_with_holes_is_filled_distilled_and_waited_for(tmp_path):
    """The planner skips a view the map explains; its few holes are still closed (mesh fill +
    Telea, distilled there), and the writer ends the collection only once that is distilled."""
    from gsfix_online.nodes import repair_writer

    t, node, _ = _planner_with_one_view(tmp_path)
    gs = reply("planner", "splat", 0, holes=False)
    gs.arrays["alpha"][10:12, 20:22] = 0.0  # 4 px: 0.2 % of the surface, below hole_fraction
    gs.arrays["color"][10:12, 20:22] = 0
    grown = np.zeros((H, W), np.float32)
    grown[25:29, 36:40] = 1.0  # a patch that other views' repairs grew: the view keeps it
    gs.arrays["synthesised"] = grown
    mesh = reply("planner", "tsdf", 0, holes=False)
    mesh.arrays["color"][:] = 140
    t.feed(gs)
    t.feed(mesh)
    node.run_until_idle()
    out = {p.message.topic: p for p in t.outbox if p.message.topic.startswith(
        ("decision/", "view/", "repaired_view/"))}  # fmt: skip
    assert set(out) == {"decision/planner/gs", "decision/planner/mesh", "decision/planner/ref",
                        "repaired_view/planner"}  # fmt: skip
    dec = out["decision/planner/gs"].message
    assert not dec.meta["repair"] and dec.meta["fill"] and "map explains" in dec.meta["reason"]
    fill = out["repaired_view/planner"]
    assert fill.reliable and fill.message.meta["fill_only"] and fill.message.meta["view_id"] == 0
    a = fill.message.arrays
    hole = np.zeros((H, W), bool)
    hole[10:12, 20:22] = True
    np.testing.assert_array_equal(a["color"][~hole], gs.arrays["color"][~hole])  # 3DGS kept
    assert (a["color"][hole] == 140).all()  # the mesh fills the holes
    assert (a["mask"][7:15, 17:25] == 255).all() and (a["mask"][22:32, 33:43] == 255).all()
    assert a["mask"].sum() == 255 * (8 * 8 + 10 * 10)
    np.testing.assert_array_equal(dec.arrays["synthesised"], grown)  # for the writer
    np.testing.assert_array_equal(a["depth"], np.full((H, W), 2.0, np.float32))
    np.testing.assert_array_equal(a["T_world_cam"], np.eye(4))

    writer = repair_writer.WriterService(
        "writer", repair_writer.Params(out_dir=str(tmp_path / "run"), expected_views=1), 0.0
    )
    writer.on_render_reply(dec)
    writer.on_render_reply(out["decision/planner/mesh"].message)
    # the view sits at the keyframe: its distance is kept for the held-out frames' reach
    assert dec.meta["keyframe_distance_m"] == writer.outputs.views[0].keyframe_distance_m == 0.0
    writer.work(1.0)
    assert writer.phase.name == "collect"  # the fill has not come
    writer.on_repaired(fill.message)
    rec = writer.outputs.views[0]
    assert rec.fill and not rec.repair and "fixed" not in rec.images
    np.testing.assert_array_equal(rec.images["output"], a["color"])
    # its provenance: the mesh where the map had holes, the 3DGS render elsewhere, observed,
    # but for the patch other views' repairs grew: synthesised
    prov = writer.outputs.view_provenance(rec)
    patch = grown > 0
    assert (prov.source[hole] == MESH).all() and (prov.source[~hole & ~patch] == GS).all()
    assert (prov.source[patch] == GS_REPAIRED).all()
    np.testing.assert_array_equal(prov.synthesised, patch.astype(np.float32))
    writer.work(2.0)
    assert writer.phase.name == "collect"  # ... nor its distillation
    writer.on_map_event(Message("distill/splat", "map_event", meta={
        "kind": "distilled", "version": 1, "step": 0, "view_id": 0, "distill_s": 0.5,
        "passes_pending": 0, "passes_s": 0.0, "gaussians": 10}))  # fmt: skip
    writer.work(3.0)
    assert writer.phase.name == "final"
    # a repair brings the run's measured choice and how far it holds (outputs.finish_skipped)
    choice = Choice(dict.fromkeys(REGIONS, "mesh_inpaint"), {}, {}, 4, "4 held-out frames")
    for reach in (0.4, None):
        writer.on_repaired(Message("repaired_view/repair", "repaired_view", 5, meta={
            "view_id": 5, "model_step": 10, "model_version": 1, "choice": choice.to_json(),
            "choice_from": "held-out frames", "measured_choice": choice.to_json(),
            "holdout_reach_m": reach, "feather_px": 2.5, "detail_px": 6.0},
            arrays={"color": a["color"]}))  # fmt: skip
        assert writer.outputs.fallback["per_region"] == choice.per_region
        assert writer.outputs.views[5].model["feather_px"] == 2.5  # the output's provenance
        assert writer.outputs.views[5].model["detail_px"] == 6.0
        assert writer.outputs.holdout_reach_m == reach


def test_a_skipped_view_without_holes_is_not_filled(tmp_path):
    t, node, _ = _planner_with_one_view(tmp_path)
    t.feed(reply("planner", "splat", 0, holes=False))
    t.feed(reply("planner", "tsdf", 0, holes=False))
    node.run_until_idle()
    topics = [p.message.topic for p in t.outbox if not p.message.topic.startswith(
        ("render_request", "heartbeat"))]  # fmt: skip
    assert topics == ["decision/planner/gs", "decision/planner/mesh", "decision/planner/ref"]
    assert not t.outbox[-1].message.meta["fill"]
