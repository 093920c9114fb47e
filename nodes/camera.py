"""Shared code of the camera nodes (``realsense``, ``oak``): publish unposed ``rgbd`` frames.

Poses come from the SLAM front end and are attached by the ``associate`` node.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

from gsfix_online.nodes._common import run_source

from gsfix_online.runtime import Message, Node, NodeRuntimeConfig, Transport, frame_to_message
from gsfix_online.sources.camera import CameraFrame
from gsfix_online.sources.resolution import frames_at


def messages(frames: Iterable[CameraFrame], topic: str) -> Iterator[Message]:
    for frame in frames:
        yield frame_to_message(frame, topic, posed=False)


def run_camera(
    name: str,
    source: Iterable[CameraFrame],
    topic: str,
    reliable: bool,
    transport: Transport,
    runtime: NodeRuntimeConfig,
    max_width: int = 0,  # the processing resolution (SourceConfig.max_width); 0 = as captured
) -> int:
    node = Node(name, transport, handlers={}, config=runtime)
    return run_source(node, messages(frames_at(source, max_width), topic), reliable=reliable)
