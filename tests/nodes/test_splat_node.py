"""Splat node on the in-memory transport: keyframes out, render replies, repaired views, resume."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from gsfix_online.nodes import splat

from gsfix_online.core.config import build
from gsfix_online.core.types import make_frame
from gsfix_online.fixer.samples import FRAME_SAMPLE_ID0, SamplePolicy
from gsfix_online.mapping.splat.keyframes import KeyframeStore
from gsfix_online.mapping.splat.ply import load_model
from gsfix_online.runtime import InMemoryTransport, Message, NodeRuntimeConfig, frame_to_message
from gsfix_online.runtime.graph import NodeEntry, node_params
from tests.mapping.splat.test_mapper import CFG, H, K, W, l1_at, plane_frame

RUNTIME = NodeRuntimeConfig(poll_timeout_ms=0, on_handler_error="raise")


@pytest.fixture(autouse=True, scope="module")
def one_thread():  # see tests/mapping/splat/test_mapper.py
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def params(tmp_path: Path, **kw: object) -> splat.Params:
    mapper = dataclasses.replace(CFG, kf_iters=1, non_kf_iters=0)
    base = {"snapshot": str(tmp_path / "map.pt"), "export_dir": str(tmp_path / "model")}
    return splat.Params(mapper=mapper, snapshot_every=2, stats_every=2, **{**base, **kw})  # type: ignore[arg-type]


def render_request(request_id: int, what: list[str]) -> Message:
    return Message(
        topic="render_request/planner",
        type="render_request",
        seq=request_id,
        meta={"width": W, "height": H, "request_id": request_id, "what": what},
        arrays={"K": K.K, "T_world_cam": plane_frame(0.05).T_world_cam},
    )


def test_node_maps_publishes_serves_and_resumes(tmp_path: Path) -> None:
    t = InMemoryTransport()
    t.feed(render_request(7, ["alpha"]))  # before any frame: an empty map
    for i in range(3):
        t.feed(frame_to_message(plane_frame(0.1 * i, i), "rgbd/cam0"))
    t.feed(render_request(8, ["color", "depth", "alpha"]))
    repaired = np.full((H, W, 3), 200, np.uint8)
    t.feed(
        Message(
            topic="repaired_view/repair",
            type="repaired_view",
            meta={"keyframe_id": 0, "model_step": 3},
            arrays={"color": repaired, "K": K.K, "T_world_cam": plane_frame(0.05).T_world_cam},
        )
    )
    t.feed(frame_to_message(plane_frame(0.3, 3), "rgbd/cam0"))
    assert splat.run("splat", params(tmp_path, stop_after=4), t, RUNTIME) == 0

    out = t.outbox
    kfs = [p for p in out if p.message.type == "keyframe"]
    assert kfs and all(p.reliable for p in kfs)
    kf = kfs[0].message
    assert kf.topic == "keyframe/splat" and kf.meta["keyframe_id"] == 0
    assert kf.arrays["gs_render"].shape == (H, W, 3) and kf.arrays["gs_render"].dtype == np.uint8
    # the render GSFixer trains on is the map's prediction before the frame (keyframe_render:
    # before): empty for the first keyframe; the alpha is the render's own
    assert kf.arrays["gs_alpha"].shape == (H, W) and float(kf.arrays["gs_alpha"].max()) == 0.0
    assert int(kf.arrays["gs_render"].max()) == 0
    np.testing.assert_array_equal(kf.arrays["color"], plane_frame(0.0).color)
    # map alpha at 3 poses near the keyframe's: the plane seen off-axis, with holes at its edges
    pa = kf.arrays["perturbed_alpha"]
    assert pa.shape == (3, H, W) and pa.dtype == np.float32 and 0 <= pa.min() <= pa.max() <= 1
    assert (pa < 0.5).any() and (pa > 0.5).any()
    np.testing.assert_array_equal(kf.arrays["T_world_cam"], plane_frame(0.0).T_world_cam)

    replies = {
        p.message.meta["request_id"]: p.message for p in out if p.message.type == "render_reply"
    }
    assert set(replies[7].arrays) == {"alpha"} and float(replies[7].arrays["alpha"].max()) == 0.0
    r8 = replies[8]
    assert set(r8.arrays) == {"color", "depth", "alpha"}
    assert r8.arrays["color"].shape == (H, W, 3) and float(r8.arrays["alpha"].mean()) > 0.5
    assert abs(float(np.median(r8.arrays["depth"])) - 2.0) < 0.2  # the plane at z = 2 m

    stats = [p.message for p in out if p.message.topic == "stats/splat/map"]
    assert stats and stats[-1].meta["map/gaussians"] > 0
    assert stats[-1].meta["map/distilled"] == 1 and stats[-1].meta["map/frames"] == 4

    # snapshot (on exit) and export exist; a restarted node resumes from the snapshot
    model = load_model(tmp_path / "model")
    snap = torch.load(tmp_path / "map.pt", weights_only=True)
    assert len(model.gmap) == snap["map"]["means"].shape[0] > 0
    assert snap["counters"]["n_frames"] == 4
    restarted = splat.SplatService("splat", params(tmp_path))
    assert restarted.mapper is not None and restarted.frames == 4
    assert len(restarted.mapper.store) == len(snap["store"]["items"])


def test_repaired_view_is_distilled(tmp_path: Path) -> None:
    service = splat.SplatService("splat", params(tmp_path, snapshot=""))
    service.on_rgbd(frame_to_message(plane_frame(), "rgbd/cam0"))
    assert service.mapper is not None
    n_kf = len(service.mapper.store)
    before = service.mapper.gmap.params["sh0"].detach().clone()
    service.on_repaired_view(
        Message(
            topic="repaired_view/repair",
            type="repaired_view",
            meta={"keyframe_id": 0, "model_step": 1},
            arrays={"color": np.full((H, W, 3), 250, np.uint8), "K": K.K,
                    "T_world_cam": plane_frame().T_world_cam},
        )
    )  # fmt: skip
    assert len(service.mapper.store) == n_kf + 1 and service.distilled == 1
    assert not torch.equal(before, service.mapper.gmap.params["sh0"].detach())


def test_a_repaired_views_region_tells_the_split_where_the_mesh_saw(tmp_path: Path) -> None:
    """The split (mapper.distill_split_px) keeps to the pixels of the repaired view's region
    where the mesh has a surface (both maps, or the mesh alone): none where neither map saw."""
    from gsfix_online.repair.fallback import BOTH, MESH_ONLY, NEITHER

    split = {}
    for cls in (NEITHER, BOTH, MESH_ONLY):
        p = params(tmp_path, snapshot="")
        p = dataclasses.replace(
            p, mapper=dataclasses.replace(p.mapper, distill_iters=0, distill_split_px=1e-3)
        )
        service = splat.SplatService("splat", p)
        f = plane_frame()
        service.on_rgbd(frame_to_message(f, "rgbd/cam0"))
        assert service.mapper is not None
        with torch.no_grad():  # an opaque surface
            service.mapper.gmap.params["opacities"][:] = torch.logit(torch.tensor(0.995))
        service.on_repaired_view(Message(
            topic="repaired_view/repair", type="repaired_view",
            meta={"keyframe_id": 0, "model_step": 1},
            arrays={"color": f.color, "K": K.K, "T_world_cam": f.T_world_cam,
                    "mask": np.full((H, W), 255, np.uint8),
                    "region": np.full((H, W), cls, np.uint8)},
        ))  # fmt: skip
        split[cls] = service.mapper.n_split
    assert split[NEITHER] == 0 and split[BOTH] == split[MESH_ONLY] > 5, split


def test_a_render_says_which_of_its_pixels_repaired_views_grew(tmp_path: Path) -> None:
    """A render request may ask for ``synthesised``: per pixel, the share of the colour that
    Gaussians grown from repaired views make. The frame saw the plane's left half; a repaired
    view fills the right half, seeded at the plane's depth (and not fitted, so that its seeds
    stay where they grew): there the share is about 1, on the left about 0."""
    p = params(tmp_path, snapshot="")
    p = dataclasses.replace(p, mapper=dataclasses.replace(p.mapper, distill_iters=0))
    service = splat.SplatService("splat", p)
    f = plane_frame()
    depth = f.depth.copy()
    depth[:, W // 2 :] = 0.0  # the camera measured nothing on the right
    service.on_rgbd(frame_to_message(
        make_frame(f.color, depth, f.intrinsics, f.T_world_cam, f.stamp_ns), "rgbd/cam0"
    ))  # fmt: skip
    before = service.on_render_request(render_request(1, ["alpha", "synthesised"])).arrays
    assert (before["synthesised"] == 0).all()  # nothing repaired yet: all of it observed
    mask = np.zeros((H, W), np.uint8)
    mask[:, W // 2 - 2 :] = 255
    service.on_repaired_view(Message(
        topic="repaired_view/repair", type="repaired_view",
        meta={"keyframe_id": 0, "model_step": 1},
        arrays={"color": f.color, "K": K.K, "T_world_cam": f.T_world_cam, "mask": mask,
                "depth": f.depth},
    ))  # fmt: skip
    reply = service.on_render_request(render_request(2, ["color", "alpha", "synthesised"]))
    share, alpha = reply.arrays["synthesised"], reply.arrays["alpha"]
    assert share.dtype == np.float32 and share.shape == (H, W)
    right, left = share[:, W // 2 + 4 :], share[:, : W // 2 - 6]
    assert alpha[:, W // 2 + 4 :].mean() > 0.5  # the repaired half renders now
    assert np.median(right) > 0.9 and np.median(left) < 0.1
    # the service's answer is the mapper's own
    m = service.mapper
    assert m is not None
    np.testing.assert_allclose(
        share, m.synthesised_share(plane_frame(0.05).T_world_cam, K.K, W, H), atol=1e-6
    )


def test_repaired_views_are_polished_when_their_passes_end(tmp_path: Path) -> None:
    fid = {}
    for below in (0.0, 60.0):  # off; on, with every repaired view under the threshold
        mapper = dataclasses.replace(CFG, kf_iters=1, non_kf_iters=0, distill_iters=0,
                                     polish_below_db=below, polish_iters=10, polish_rounds=1)  # fmt: skip
        service = splat.SplatService("splat", splat.Params(mapper=mapper, distill_passes=1,
                                                           pass_slice_steps=1))  # fmt: skip
        service.on_rgbd(frame_to_message(plane_frame(), "rgbd/cam0"))
        view = plane_frame()
        brighter = np.clip(view.color.astype(int) + 40, 0, 255).astype(np.uint8)
        service.on_repaired_view(
            Message(topic="repaired_view/repair", type="repaired_view", meta={"view_id": 3},
                    arrays={"color": brighter, "K": K.K, "T_world_cam": view.T_world_cam})
        )  # fmt: skip
        assert service.mapper is not None
        done = [service.distill_passes(i) for i in range(service.pass_steps_left)]
        assert all(d is None for d in done[:-1]) and done[-1] is not None
        assert done[-1].meta["passes_pending"] == 0
        (fid[below],) = service.mapper.fidelity().values()
    assert fid[60.0] > fid[0.0] + 1.0, fid  # 10 more steps on the repaired view


def test_a_view_the_map_explains_asks_for_one_pass_not_a_new_round(tmp_path: Path) -> None:
    mapper = dataclasses.replace(CFG, kf_iters=2, non_kf_iters=0, distill_iters=2)
    service = splat.SplatService("splat", splat.Params(mapper=mapper, distill_passes=3,
                                                       pass_restart_loss=0.01))  # fmt: skip
    view = plane_frame()
    service.on_rgbd(frame_to_message(view, "rgbd/cam0"))
    assert service.mapper is not None

    def distil(color: np.ndarray, view_id: int) -> None:
        service.on_repaired_view(
            Message(topic="repaired_view/repair", type="repaired_view", meta={"view_id": view_id},
                    arrays={"color": color, "K": K.K, "T_world_cam": view.T_world_cam})
        )  # fmt: skip

    def per_pass() -> int:
        assert service.mapper is not None
        return -(-len(service.mapper.store) // service.mapper.cfg.refine_views)

    def own() -> np.ndarray:  # the map's own render of the view: nothing to blend in
        assert service.mapper is not None
        color, _, _ = service.mapper.render_numpy(view.T_world_cam, K.K, W, H)
        return np.clip(np.rint(color * 255), 0, 255).astype(np.uint8)

    distil(own(), 1)
    assert service.pass_steps_left == per_pass()
    distil(np.clip(view.color.astype(int) + 60, 0, 255).astype(np.uint8), 2)  # brighter
    assert service.pass_steps_left == 3 * per_pass()  # a new round
    service.distill_passes(0)
    left = service.pass_steps_left
    distil(own(), 3)
    assert service.pass_steps_left == left  # the round under way goes on, not restarted


def test_params_build_from_graph_entry() -> None:
    p = node_params(NodeEntry(kind="splat", params={"mapper": {"kf_iters": 3}, "snapshot": "x.pt"}))
    assert isinstance(p, splat.Params) and p.mapper.kf_iters == 3 and p.snapshot == "x.pt"
    assert build(splat.Params).mapper.kf_iters == splat.Params().mapper.kf_iters


def test_keyframes_can_carry_the_render_from_before_the_frame(tmp_path: Path) -> None:
    # a new part of the plane: half of the keyframe's view was mapped before it came
    frames = [plane_frame(0.0, 0), plane_frame(1.0, 1)]
    sent = {}
    for when in ("after", "before"):
        svc = splat.SplatService("splat", params(tmp_path / when, keyframe_render=when))
        outs = [svc.on_rgbd(frame_to_message(f, "rgbd/cam0")) for f in frames]
        assert all(len(o) == 1 and o[0].topic == "keyframe/splat" for o in outs)
        kfs = [o[0] for o in outs]
        sent[when] = kfs
    after, before = sent["after"][1].arrays, sent["before"][1].arrays
    assert before["gs_render"].dtype == np.uint8 and before["gs_render"].shape == (H, W, 3)
    # after: the frame's own content everywhere; before: a hole where the map had nothing yet
    assert float((after["gs_alpha"] > 0.5).mean()) > 0.95
    assert 0.1 < float((before["gs_alpha"] > 0.5).mean()) < 0.9
    hole = before["gs_alpha"] < 0.05
    assert before["gs_render"][hole].max() < 13  # near black where nothing was predicted
    # the first keyframe: the map was empty before it
    assert float(sent["before"][0].arrays["gs_alpha"].max()) == 0.0


def test_frame_samples_and_the_end_of_the_input(tmp_path: Path) -> None:
    # every 2nd frame that moved 5 cm since the last sample or keyframe is a sample too
    samples = {"every": 2, "min_move_m": 0.05, "min_turn_deg": 5.0}
    p = params(tmp_path, snapshot="", input_frames=8, samples=build(SamplePolicy, base=samples))
    svc = splat.SplatService("splat", p)
    out = []
    for i in range(8):
        out += svc.on_rgbd(frame_to_message(plane_frame(0.1 * i, i), "rgbd/cam0"))
    kinds = [m.topic.split("/")[0] for m in out]
    assert kinds[-1] == "input_end" and kinds.count("input_end") == 1
    n_kf, n_s = kinds.count("keyframe"), kinds.count("fixer_sample")
    assert n_kf >= 1 and n_s >= 1 and n_kf + n_s + 1 == len(out)
    end = out[-1]
    assert end.type == "input_end" and end.meta["frames"] == 8
    assert (end.meta["keyframes"], end.meta["samples"]) == (n_kf, n_s)
    sample_ids = [m.meta["keyframe_id"] for m in out if m.topic.startswith("fixer_sample/")]
    assert all(k >= FRAME_SAMPLE_ID0 for k in sample_ids)
    for m in out[:-1]:  # a sample is a full training triplet, like a keyframe
        assert m.type == "keyframe" and m.arrays["gs_render"].shape == (H, W, 3)
    assert svc.on_rgbd(frame_to_message(plane_frame(0.9, 8), "rgbd/cam0"))[-1:] != [end]


def test_the_map_is_refined_over_its_keyframes_when_the_input_ends(tmp_path: Path) -> None:
    frames = [frame_to_message(plane_frame(0.1 * i, i), "rgbd/cam0") for i in range(4)]
    errors, steps = {}, {}
    for n in (0, 30):
        svc = splat.SplatService("splat", params(tmp_path, input_frames=4, refine_at_input_end=n))
        for m in frames[:-1]:
            svc.on_rgbd(m)
        assert svc.mapper is not None
        before = svc.mapper.n_steps
        assert svc.on_rgbd(frames[-1])[-1].topic == "input_end/splat"
        assert svc.mapper.n_steps == before  # the end goes out first: the trainer hears it now
        svc.after_input_end()
        svc.after_input_end()  # once only
        steps[n] = svc.mapper.n_steps - before
        # the map at the keyframes' own poses, against their images
        errors[n] = float(np.mean([l1_at(svc.mapper, kf.frame) for kf in svc.mapper.store]))
    assert steps[30] - steps[0] == 30  # the refinement ran once, at the end, and only then
    assert errors[30] < 0.8 * errors[0]


def test_with_pose_correction_requests_and_repairs_are_moved_as_the_map_was(
    tmp_path: Path,
) -> None:
    from gsfix_online.core.types import make_frame
    from gsfix_online.mapping.splat.keyframes import KeyframeConfig
    from gsfix_online.mapping.splat.poses import PoseConfig

    mapper = dataclasses.replace(
        CFG, kf_iters=2, non_kf_iters=0, keyframes=KeyframeConfig(min_overlap=0.99),
        poses=PoseConfig(enabled=True, lr=1e-3),
    )  # fmt: skip
    p = dataclasses.replace(params(tmp_path, snapshot=""), mapper=mapper)
    service = splat.SplatService("splat", p)
    off = plane_frame(0.3, 2)
    T_off = off.T_world_cam.copy()
    T_off[0, 3] += 0.04  # the front end's pose of the third frame is 4 cm off
    frames = [plane_frame(0.0, 0), plane_frame(0.15, 1),
              make_frame(off.color, off.depth, off.intrinsics, T_off, off.stamp_ns, seq=2)]  # fmt: skip
    for f in frames:
        service.on_rgbd(frame_to_message(f, "rgbd/cam0"))
    m = service.mapper
    assert m is not None and m.poses
    moved = m.pose_for(T_off)
    assert abs(moved[0, 3] - 0.3) < abs(T_off[0, 3] - 0.3)  # tracked towards where it was
    req = render_request(9, ["color"])
    req.arrays["T_world_cam"] = T_off
    reply = service.on_render_request(req)
    color, _, _ = m.render_numpy(moved, K.K, W, H)
    assert np.abs(reply.arrays["color"] / 255.0 - color).max() <= 0.5 / 255 + 1e-6
    service.on_repaired_view(
        Message(
            topic="repaired_view/repair",
            type="repaired_view",
            meta={"keyframe_id": 0, "model_step": 1},
            arrays={"color": off.color, "K": K.K, "T_world_cam": T_off},
        )
    )  # fmt: skip
    assert m.store.latest is not None
    np.testing.assert_allclose(m.store.latest.frame.T_world_cam, moved)


def test_a_resumed_node_announces_its_keyframes_as_it_first_did(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """After a restart from its snapshot the node announces its keyframes again with the 3DGS
    render it first sent them with: the map's prediction before each frame (keyframe_render
    "before"), not its render after it."""
    p = params(tmp_path)
    service = splat.SplatService("splat", p)
    first = []
    for i, x in enumerate((0.0, 1.0)):  # the second frame half over the mapped part
        out = service.on_rgbd(frame_to_message(plane_frame(x, i), "rgbd/cam0"))
        first += [m for m in out if m.type == "keyframe"]
    assert len(first) == 2
    predicted = first[1].arrays["gs_alpha"] > 0.5
    assert 0.1 < predicted.mean() < 0.9  # a partial prediction, not the empty or full map
    service.snapshot()
    resumed = splat.SplatService("splat", p)
    again = resumed.keyframes_again()
    assert [m.meta["keyframe_id"] for m in again] == [m.meta["keyframe_id"] for m in first]
    for a, b in zip(again, first, strict=True):
        np.testing.assert_array_equal(a.arrays["gs_render"], b.arrays["gs_render"])
        np.testing.assert_array_equal(a.arrays["gs_alpha"], b.arrays["gs_alpha"])
    after = resumed.mapper.store[1].alpha  # the render after the frame covers all of it
    assert (after > 0.5).mean() > 0.95
    # a snapshot from before priors were kept: the render after, and a warning that says so
    state = resumed.mapper.store.state_dict()
    state["items"] = [{k: v for k, v in it.items() if k != "prior"} for it in state["items"]]
    resumed.mapper.store = KeyframeStore.from_state_dict(state)
    again = resumed.keyframes_again()
    assert (again[1].arrays["gs_alpha"] > 0.5).mean() > 0.95
    assert "2 of the snapshot's keyframes kept no render from before their frame" in caplog.text
