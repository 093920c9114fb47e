"""Replay node: reads any input the readers accept (dataset folder, bag, MCAP log) and publishes
posed ``rgbd`` messages with rate control. Reliable by default: at full speed nothing is lost."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, field

from gsfix_online.nodes._common import run_source

from gsfix_online.runtime import Message, Node, NodeRuntimeConfig, Transport, frame_to_message
from gsfix_online.sources import ReplayConfig, SourceConfig, open_source
from gsfix_online.sources.replay import paced


@dataclass(frozen=True)
class Params:
    source: SourceConfig = field(default_factory=SourceConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    topic: str = "rgbd/cam0"
    reliable: bool = True  # False: latest-only (live-like; a slow consumer sees the newest frame)


def messages(params: Params) -> Iterator[Message]:
    reader = open_source(params.source)
    for frame in paced(reader, params.replay, time.monotonic, time.sleep):
        yield frame_to_message(frame, params.topic)


def run(name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig) -> int:
    node = Node(name, transport, handlers={}, config=runtime)
    return run_source(node, messages(params), reliable=params.reliable)
