"""Shared code of the camera nodes (``realsense``, ``oak``): publish unposed ``rgbd`` frames.

Poses come from the SLAM front end and are attached by the ``associate`` node.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

from gsfix_online.runtime import Message, Node, NodeRuntimeConfig, Transport
from gsfix_online.sources.camera import CameraFrame
from nodes._common import run_source


def camera_message(frame: CameraFrame, topic: str) -> Message:
    """An unposed ``rgbd`` message (``posed: False``, no T_world_cam)."""
    return Message(
        topic=topic,
        type="rgbd",
        seq=frame.seq,
        stamp_ns=frame.stamp_ns,
        frame_id=frame.frame_id,
        meta={"posed": False},
        arrays={"color": frame.color, "depth": frame.depth, "K": frame.intrinsics.K},
    )


def messages(frames: Iterable[CameraFrame], topic: str) -> Iterator[Message]:
    for frame in frames:
        yield camera_message(frame, topic)


def run_camera(
    name: str,
    source: Iterable[CameraFrame],
    topic: str,
    reliable: bool,
    transport: Transport,
    runtime: NodeRuntimeConfig,
) -> int:
    node = Node(name, transport, handlers={}, config=runtime)
    return run_source(node, messages(source, topic), reliable=reliable)
