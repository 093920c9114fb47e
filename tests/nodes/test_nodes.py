"""Node logic on the in-memory transport, and the SLAM example against the real decoder."""

from __future__ import annotations

import msgpack
import numpy as np
from gsfix_online.nodes import associate, monitor

from examples.slam_pose_publisher import packb, pose_message
from gsfix_online.core.se3 import interpolate_pose, look_at
from gsfix_online.runtime import InMemoryTransport, Node, decode, frame_to_message, message_to_frame
from gsfix_online.runtime.graph import load_graph, transport_for
from gsfix_online.sources.camera import CameraFrame
from gsfix_online.sources.pose_association import PoseAssociationConfig, PoseAssociator


def test_example_msgpack_matches_msgpack():
    obj = {
        "v": 1,
        "neg": -5,
        "neg64": -(2**40),
        "big": 2**40,
        "f": 1.5,
        "s": "x" * 40,
        "l": list(range(20)),
        "none": None,
        "b": True,
    }
    assert msgpack.unpackb(packb(obj)) == obj


def test_example_pose_decodes_with_our_wire_format():
    T = look_at([1, 2, 3], [0, 0, 0])
    msg = decode(pose_message(7, 123_456_789, T))
    assert (
        msg.type == "pose"
        and msg.topic == "pose/slam"
        and msg.seq == 7
        and msg.stamp_ns == 123_456_789
    )
    assert np.array_equal(msg.arrays["T_world_body"], T)


def test_associate_node_pairs_camera_frames_with_slam_poses(frames):
    t = InMemoryTransport()
    published = []
    handlers = associate.handlers(
        PoseAssociator(PoseAssociationConfig()), published.append, "rgbd/cam0/posed"
    )
    node = Node("associate", t, handlers=handlers)
    f0, f1 = frames[0], frames[1]
    cam = CameraFrame(f0.color, f0.depth, f0.intrinsics, (f0.stamp_ns + f1.stamp_ns) // 2, "cam", 0)
    t.feed(frame_to_message(cam, "rgbd/cam0", posed=False))
    t.feed(pose_message(0, f0.stamp_ns, f0.T_world_cam))
    t.feed(pose_message(1, f1.stamp_ns, f1.T_world_cam))
    node.run_until_idle()
    assert len(published) == 1
    out = message_to_frame(published[0])
    assert np.allclose(out.T_world_cam, interpolate_pose(f0.T_world_cam, f1.T_world_cam, 0.5))
    assert np.array_equal(out.color, f0.color)


def test_monitor_counts_gaps_and_backwards_stamps(frames):
    from gsfix_online.runtime import frame_to_message

    check = monitor.FrameCheck()
    for i in (0, 1, 3, 2):
        check.on_rgbd(frame_to_message(frames[i], "rgbd/a"))
    assert check.frames == 4 and check.seq_gaps == 2 and check.stamp_backwards == 1


def test_example_graphs_load_and_wire_consistently():
    for path in ("configs/graphs/replay_local.yaml", "configs/graphs/robot_workstation.yaml"):
        g = load_graph(path)
        binds = [
            e.address
            for n in g.nodes
            for e in (*transport_for(g, n).inputs, *transport_for(g, n).outputs)
            if e.bind
        ]
        assert len(binds) == len(set(binds))  # every address is bound exactly once
        for n in g.nodes:
            for e in (*transport_for(g, n).inputs, *transport_for(g, n).outputs):
                assert e.address in binds  # and every connect has a binder


def test_recorder_writes_a_log_the_readers_replay(tmp_path, frames):
    from gsfix_online.nodes import recorder

    from gsfix_online.runtime import NodeRuntimeConfig, frame_to_message
    from gsfix_online.sources import SourceConfig, open_source

    t = InMemoryTransport()
    for f in frames:
        t.feed(frame_to_message(f, "rgbd/cam0"))
    params = recorder.Params(
        path=str(tmp_path / "rec.mcap"), stop_after=len(frames), chunk_bytes=8192
    )
    assert recorder.run("recorder", params, t, NodeRuntimeConfig(poll_timeout_ms=0)) == 0
    got = list(open_source(SourceConfig(), tmp_path / "rec.mcap"))
    assert len(got) == len(frames)
    for a, b in zip(got, frames, strict=True):
        assert np.array_equal(a.color, b.color) and np.array_equal(a.depth, b.depth)
        assert np.allclose(a.T_world_cam, b.T_world_cam, atol=1e-12) and a.stamp_ns == b.stamp_ns
