"""The TSDF node's component without a transport: renders hold every integrated frame, and the
input's last frame announces a mesh of every frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gsfix_online.core.config import build
from gsfix_online.core.types import Intrinsics, make_frame
from gsfix_online.runtime import Message, frame_to_message
from gsfix_online.services.tsdf import Params, TsdfService

K = Intrinsics(40.0, 40.0, 31.5, 23.5, 64, 48)


def plane(i: int, x: float = 0.0) -> Message:
    """A fronto-parallel plane 1 m ahead, seen from x + 0.01 i (m)."""
    T = np.eye(4)
    T[0, 3] = x + 0.01 * i
    depth = np.full((K.height, K.width), 1.0, np.float32)
    color = np.full((K.height, K.width, 3), (40, 120, 200), np.uint8)
    return frame_to_message(make_frame(color, depth, K, T, 1_000_000 * (i + 1), seq=i), "rgbd/c")


def render(svc: TsdfService, x: float = 0.0) -> np.ndarray:  # [H, W] alpha
    T = np.eye(4)
    T[0, 3] = x
    req = Message(
        "render_request/planner", "render_request", stamp_ns=1, frame_id="camera",
        meta={"width": K.width, "height": K.height, "request_id": 1, "what": ["alpha"]},
        arrays={"K": K.K, "T_world_cam": T},
    )  # fmt: skip
    return svc.on_render_request(req).arrays["alpha"]


def params(tmp_path: Path, **kw) -> Params:
    # The remesh policy's defaults: a new mesh after 5 frames with 64 new blocks or after 50
    # frames; here voxels fused from fewer than 3 frames are not meshed (the default meshes every
    # fused voxel), so later frames add surface without adding blocks.
    base = {"mesh_dir": str(tmp_path / "mesh"), "write_periodic": False,
            "tsdf": {"voxel_size": 0.02, "block_count": 64, "mesh_weight_threshold": 3.0}}  # fmt: skip
    return build(Params, base={**base, **kw})


def test_renders_hold_every_integrated_frame_not_only_the_policys_mesh(tmp_path: Path):
    svc = TsdfService("tsdf", params(tmp_path))
    svc.on_rgbd(plane(0))
    inner = (slice(8, -8), slice(12, -12))
    # One frame: its voxels weigh 1, under the mesh threshold: nothing to render yet.
    assert render(svc).max() == 0.0
    # Two more frames of the same plane add no block, so the policy keeps the empty mesh; the
    # plane is fused from 3 frames now and the render must show it (the policy's mesh did not).
    for i in (1, 2):
        svc.on_rgbd(plane(i))
    assert not svc.volume.needs_remesh()
    assert render(svc)[inner].min() == 1.0
    extracted = svc.volume.mesh_version
    # Nothing integrated since: the next render reuses that mesh.
    assert render(svc)[inner].min() == 1.0 and svc.volume.mesh_version == extracted


def test_the_inputs_last_frame_announces_a_mesh_of_every_frame(tmp_path: Path):
    svc = TsdfService("tsdf", params(tmp_path, input_frames=4))
    out = [svc.on_rgbd(plane(i)) for i in range(4)]
    assert out[:3] == [[], [], []]  # no periodic writes; the policy would not remesh either
    (msg,) = out[3]
    assert msg.topic == "mesh/tsdf" and msg.type == "map_event"
    assert msg.meta["kind"] == "mesh_written"
    assert msg.meta["step"] == 4 and msg.meta["triangles"] > 0
    assert Path(msg.meta["path"]).is_file()
    # A frame delivered again (a restarted replay) is not integrated and announces nothing.
    assert svc.on_rgbd(plane(3)) == [] and svc.repeated == 1


def test_while_a_known_input_arrives_renders_keep_the_policys_mesh(tmp_path: Path):
    svc = TsdfService("tsdf", params(tmp_path, input_frames=4))
    svc.on_rgbd(plane(0))
    assert render(svc).max() == 0.0  # the first mesh: one frame, under the weight threshold
    for i in (1, 2):
        svc.on_rgbd(plane(i))
    # 3 of 4 frames: a progress probe does not pay for an extraction per frame
    assert render(svc).max() == 0.0 and svc.volume.mesh_version == 1
    (msg,) = svc.on_rgbd(plane(3))  # the last frame: the mesh of every frame, announced
    assert msg.meta["version"] == 2 and render(svc)[8:-8, 12:-12].min() == 1.0


def test_unposed_frames_count_toward_the_input(tmp_path: Path):
    svc = TsdfService("tsdf", params(tmp_path, input_frames=3))
    assert svc.on_rgbd(plane(0)) == [] and svc.on_rgbd(plane(1)) == []
    unposed = plane(2)
    unposed.meta["posed"] = False
    (msg,) = svc.on_rgbd(unposed)
    assert msg.meta["step"] == 2 and svc.unposed == 1


def test_frames_dropped_as_repeated_warn_once_and_stay_counted(tmp_path: Path, caplog):
    svc = TsdfService("tsdf", params(tmp_path))
    with caplog.at_level("WARNING", logger="gsfix_online.services.tsdf"):
        for i in reversed(range(4)):  # an input out of time order: only the newest is used
            svc.on_rgbd(plane(i))
    assert (svc.volume.frames, svc.repeated, svc.stats()["tsdf/repeated"]) == (1, 3, 3)
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "dropped as repeated" in warnings[0]
    assert "tsdf/repeated" in warnings[0]


def test_renders_give_the_planes_guess_where_the_mesh_saw_nothing(tmp_path: Path):
    from gsfix_online.mapping.mesh_render import MeshRenderer
    from tests.mapping.test_mesh_planes import K as BOX_K
    from tests.mapping.test_mesh_planes import looking_along_x, lower_half_box, true_box_exit

    box, k = MeshRenderer(lower_half_box()), BOX_K
    svc = TsdfService("tsdf", build(Params, base={
        "mesh_dir": str(tmp_path / "mesh"), "write_periodic": False,
        "tsdf": {"voxel_size": 0.04, "depth_max": 6.0}}))  # fmt: skip
    for i, (y, tilt) in enumerate([(1.2, 0.0), (1.5, -10.0), (1.8, 0.0), (1.5, 10.0)]):
        T = looking_along_x((0.8, y, 0.6), tilt)
        r = box.render(T, k)
        frame = make_frame(r.rgb(), r.depth_m, k, T, 1_000_000 * (i + 1), seq=i)
        svc.on_rgbd(frame_to_message(frame, "rgbd/c"))
    T = looking_along_x((1.0, 1.5, 1.0), up_tilt_deg=10.0)  # above what the frames saw
    req = Message(
        "render_request/repair", "render_request", stamp_ns=1, frame_id="camera",
        meta={"width": k.width, "height": k.height, "request_id": 1,
              "what": ["alpha", "guessed_depth"]},
        arrays={"K": k.K, "T_world_cam": T},
    )  # fmt: skip
    out = svc.on_render_request(req).arrays
    seen, guess = out["alpha"] > 0, out["guessed_depth"]
    assert guess.dtype == np.float32 and (guess[seen] == 0).all()
    truth, ceiling = true_box_exit(T)
    unseen = ~seen & (guess > 0)
    assert unseen.sum() > 0.2 * k.width * k.height
    # where the truth is a wall the frames saw part of (not the ceiling, which no frame saw),
    # the guess is that wall, to a voxel: the planes fitted to the TSDF mesh tilt by about 0.5°
    err = np.abs(guess - truth)[unseen & ~ceiling]
    assert np.median(err) < 0.04
