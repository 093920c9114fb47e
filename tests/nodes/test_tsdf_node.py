"""TSDF node on the in-memory transport: integrate, render replies, snapshots, stats, stop_after."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from gsfix_online.nodes import tsdf

from gsfix_online.core.config import build
from gsfix_online.core.types import Intrinsics, make_frame
from gsfix_online.runtime import InMemoryTransport, Message, NodeRuntimeConfig, frame_to_message
from gsfix_online.runtime.graph import load_graph, node_params

K = Intrinsics(40.0, 40.0, 31.5, 23.5, 64, 48)


def plane_frames(n: int = 4, z: float = 1.0):
    frames = []
    for i in range(n):
        T = np.eye(4)
        T[0, 3] = 0.02 * i
        depth = np.full((K.height, K.width), z, np.float32)
        color = np.full((K.height, K.width, 3), (40, 120, 200), np.uint8)
        frames.append(make_frame(color, depth, K, T, 1_000_000 * (i + 1), seq=i))
    return frames


def request(request_id: int, what: list[str], T: np.ndarray | None = None) -> Message:
    return Message(
        topic="render_request/planner",
        type="render_request",
        stamp_ns=42,
        frame_id="camera",
        meta={"width": K.width, "height": K.height, "request_id": request_id, "what": what},
        arrays={"K": K.K, "T_world_cam": np.eye(4) if T is None else T},
    )


def params(tmp_path: Path, **kw) -> tsdf.Params:
    base = {"mesh_dir": str(tmp_path / "mesh"), "tsdf": {"voxel_size": 0.02, "block_count": 64}}
    return build(tsdf.Params, base={**base, **kw})


def test_node_integrates_renders_and_snapshots(tmp_path):
    t = InMemoryTransport()
    node, service = tsdf.build_node(
        "tsdf", params(tmp_path, write_periodic=False), t, NodeRuntimeConfig()
    )
    for f in plane_frames():
        t.feed(frame_to_message(f, "rgbd/cam0"))
    t.feed(frame_to_message(plane_frames(1)[0], "rgbd/cam0", posed=False))  # skipped, counted
    t.feed(request(7, ["color", "depth", "alpha"]))
    t.feed(request(8, ["depth"]))
    t.feed(Message(topic="tsdf/snapshot", type="command", meta={"kind": "snapshot", "path": ""}))
    node.run_until_idle()
    assert not node.handler_errors
    out = {m.topic: m for m in t.published if not m.topic.startswith(("heartbeat/", "stats/"))}
    replies = [m for m in t.published if m.type == "render_reply"]
    assert [m.meta["request_id"] for m in replies] == [7, 8]
    full, depth_only = replies
    assert set(full.arrays) == {"color", "depth", "alpha"} and set(depth_only.arrays) == {"depth"}
    inner = (slice(8, -8), slice(12, -12))
    assert full.arrays["alpha"][inner].min() == 1.0
    assert np.abs(full.arrays["depth"][inner] - 1.0).max() < 0.01  # half a voxel
    assert np.abs(full.arrays["color"][inner].astype(int) - (40, 120, 200)).max() <= 1
    assert full.stamp_ns == 42 and full.meta["mesh_version"] == 1
    snap = out["mesh/tsdf"]
    assert snap.type == "map_event" and snap.meta["kind"] == "mesh_written"
    assert snap.meta["step"] == 4 and snap.meta["triangles"] > 0
    assert sorted(Path(p).name for p in snap.meta["files"]) == ["mesh.glb", "mesh.ply"]
    assert all(Path(p).is_file() for p in snap.meta["files"])
    stats = node.stats_meta(node.clock())
    assert stats["tsdf/frames"] == 4 and stats["tsdf/unposed"] == 1 and stats["tsdf/renders"] == 2
    assert stats["tsdf/blocks"] > 0 and stats["tsdf/invalid_depth"] == 0


def test_node_writes_periodic_meshes_and_stops_after(tmp_path):
    frames = plane_frames(6)
    t = InMemoryTransport(script=[frame_to_message(f, "rgbd/cam0") for f in frames])
    p = params(
        tmp_path,
        stop_after=6,
        tsdf={
            "voxel_size": 0.02,
            "remesh_min_frames": 1,
            "remesh_max_frames": 3,
            "remesh_new_blocks": 1000,
        },
    )
    assert tsdf.run("tsdf", p, t, NodeRuntimeConfig(poll_timeout_ms=0)) == 0
    meshes = [m for m in t.published if m.topic == "mesh/tsdf"]
    # First frame: first mesh; then every 3 frames (no new blocks beyond the first view).
    assert [m.meta["step"] for m in meshes] == [1, 4]
    assert (tmp_path / "mesh" / "mesh.ply").is_file() and (tmp_path / "mesh" / "mesh.glb").is_file()


def test_node_snapshot_to_a_named_file_and_empty_volume_renders_nothing(tmp_path):
    t = InMemoryTransport()
    node, _ = tsdf.build_node("tsdf", params(tmp_path), t, NodeRuntimeConfig())
    t.feed(request(1, ["alpha", "color"]))
    target = tmp_path / "snap" / "x.ply"
    t.feed(
        Message(
            topic="tsdf/snapshot", type="command", meta={"kind": "snapshot", "path": str(target)}
        )
    )
    node.run_until_idle()
    reply = next(m for m in t.published if m.type == "render_reply")
    assert reply.arrays["alpha"].max() == 0 and reply.arrays["color"].shape == (
        K.height,
        K.width,
        3,
    )
    assert target.is_file()


def test_graph_with_a_tsdf_node_loads():
    g = load_graph("configs/graphs/tsdf_local.yaml")
    p = node_params(g.nodes["tsdf"])
    assert isinstance(p, tsdf.Params) and p.tsdf.voxel_size == 0.02
