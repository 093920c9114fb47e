"""Small valid messages of every type, generated here (shared by the runtime tests)."""

from __future__ import annotations

import numpy as np

from gsfix_online.runtime.wire import REGISTRY, Message

T0_NS = 1_700_000_000_000_000_000


def pose(tx: float = 0.0) -> np.ndarray:  # [4, 4] rotation about z by 0.3 rad, translation x
    c, s = np.cos(0.3), np.sin(0.3)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3] = tx
    return T


def intrinsics_K(w: int, h: int) -> np.ndarray:  # [3, 3] pixels
    return np.array([[0.8 * w, 0.0, (w - 1) / 2], [0.0, 0.8 * w, (h - 1) / 2], [0.0, 0.0, 1.0]])


def rgbd_message(i: int = 0, h: int = 6, w: int = 8, topic: str = "rgbd/cam0") -> Message:
    rng = np.random.default_rng(i)
    return Message(
        topic=topic,
        type="rgbd",
        seq=i,
        stamp_ns=T0_NS + i * 33_333_333,
        frame_id="cam0_optical",
        meta={"posed": True},
        arrays={
            "color": rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
            "depth": rng.uniform(0.3, 5.0, (h, w)).astype(np.float32),
            "K": intrinsics_K(w, h),
            "T_world_cam": pose(0.1 * i),
        },
    )


def sample_messages(h: int = 6, w: int = 8) -> dict[str, Message]:
    """One valid message per registered type, keyed by type."""
    rng = np.random.default_rng(7)
    color = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    depth = rng.uniform(0.3, 5.0, (h, w)).astype(np.float32)
    alpha = rng.uniform(0.0, 1.0, (h, w)).astype(np.float32)
    K, T = intrinsics_K(w, h), pose(1.5)
    gray = rng.integers(0, 256, (h, w), dtype=np.uint8)

    def m(type_: str, topic: str, meta: dict, arrays: dict | None = None) -> Message:
        return Message(topic, type_, 3, T0_NS, "cam0_optical", meta, arrays or {})

    out = {
        "rgbd": m(
            "rgbd",
            "rgbd/cam0",
            {"posed": True},
            {"color": color, "depth": depth, "K": K, "T_world_cam": T},
        ),
        "pose": m(
            "pose", "pose/body", {"parent": "map", "child": "base_link"}, {"T_world_body": T}
        ),
        "camera_info": m(
            "camera_info",
            "camera_info/cam0",
            {"width": w, "height": h, "distortion_model": "plumb_bob"},
            {"K": K, "D": np.array([0.1, -0.05, 0.0, 0.0, 0.01])},
        ),
        "keyframe": m(
            "keyframe",
            "keyframes/cam0",
            {"keyframe_id": 12},
            {
                "color": gray,
                "depth": depth,
                "K": K,
                "T_world_cam": T,
                "gs_render": color,
                "gs_alpha": alpha,
            },
        ),
        "render_request": m(
            "render_request",
            "render/request",
            {"width": w, "height": h, "request_id": 5, "what": ["color", "alpha"]},
            {"K": K, "T_world_cam": T},
        ),
        "render_reply": m(
            "render_reply", "render/reply", {"request_id": 5}, {"color": color, "alpha": alpha}
        ),
        "repaired_view": m(
            "repaired_view",
            "repair/views",
            {"keyframe_id": 12, "model_step": 300},
            {
                "color": color,
                "K": K,
                "T_world_cam": T,
                "mask": (alpha > 0.5).astype(np.uint8) * 255,
            },
        ),
        "model_checkpoint": m(
            "model_checkpoint",
            "checkpoint/trainer",
            {
                "path": "/tmp/ckpt/step300.safetensors",
                "version": 2,
                "step": 300,
                "run": 1,
                "run_done": False,
                "mode": "gs_mesh",
                "heldout_loss": 0.042,
            },  # fmt: skip
        ),
        "trainer_plan": m(
            "trainer_plan",
            "trainer_plan/trainer",
            {
                "run": 1,
                "will_train": True,
                "reason": "run 1 is due",
                "train": 9,
                "holdout": 2,
                "max_steps": 600,
                "version": 0,
                "step": 0,
            },  # fmt: skip
        ),
        "input_end": m(
            "input_end", "input_end/splat", {"frames": 40, "keyframes": 11, "samples": 6}
        ),
        "map_event": m(
            "map_event",
            "mesh/tsdf",
            {
                "kind": "mesh_written",
                "version": 3,
                "step": 40,
                "path": "/tmp/mesh/mesh.ply",
                "files": ["/tmp/mesh/mesh.ply"],
                "vertices": 120,
                "triangles": 200,
            },  # fmt: skip
        ),
        "command": m("command", "tsdf/snapshot", {"kind": "snapshot", "path": ""}),
        "heartbeat": m(
            "heartbeat", "heartbeat/mapper", {"node": "mapper", "pid": 1234, "uptime_s": 12.5}
        ),
        "stats": m(
            "stats", "stats/mapper", {"node": "mapper", "period_s": 5.0, "rate_hz/rgbd/cam0": 29.9}
        ),
        "ack": m("ack", "_ack", {"ack_seq": 41}),
    }
    assert set(out) == set(REGISTRY), "add a sample for every registered type"
    return out
