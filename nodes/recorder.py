"""Recorder node: writes posed ``rgbd`` frames to our MCAP log, in small chunks so that a crash
loses at most the last chunk (the reader streams a log without its summary). The replay node and
every reader read the result."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from gsfix_online.core.config import rng
from gsfix_online.runtime import Message, Node, NodeRuntimeConfig, Transport, message_to_frame
from gsfix_online.sources.mcap_log import McapLogWriter

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Params:
    path: str = "recording.mcap"
    topics: list[str] = field(default_factory=lambda: ["rgbd/"])  # topic prefixes to record
    chunk_bytes: int = field(
        default=1 << 20, metadata=rng(4096, 1 << 30, "MCAP chunk size: the most a crash can lose")
    )
    stop_after: int = field(
        default=0, metadata=rng(0, None, "exit after this many frames; 0 = never")
    )


def run(name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig) -> int:
    # in place, not atomic: a crash keeps every finished chunk
    writer = McapLogWriter(params.path, chunk_size=params.chunk_bytes, atomic=False)
    node: Node

    def on_rgbd(msg: Message) -> None:
        if not any(msg.topic.startswith(p) for p in params.topics) or not msg.meta.get(
            "posed", True
        ):
            return
        writer.write(message_to_frame(msg))
        if params.stop_after and writer.frames >= params.stop_after:
            node.request_stop()

    node = Node(name, transport, handlers={"rgbd": on_rgbd}, config=runtime)
    try:
        return node.run()
    finally:
        writer.close()
        logger.info("%s: %d frames recorded to %s", name, writer.frames, params.path)
