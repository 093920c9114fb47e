"""Monitor node: counts and checks what arrives (frames per topic, gaps in sequence numbers,
stamps going backwards, frames that fail validation) and writes a JSON report on exit.

With ``stop_after`` it exits once that many ``rgbd`` frames arrived, which makes it the consumer
of test and benchmark graphs."""

from __future__ import annotations

import json
import logging
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from gsfix_online.core.config import rng
from gsfix_online.core.io import atomic_write_text
from gsfix_online.runtime import Message, Node, NodeRuntimeConfig, Transport, message_to_frame

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Params:
    stop_after: int = field(
        default=0, metadata=rng(0, None, "exit after this many rgbd frames; 0 = never")
    )
    report: str = ""  # JSON report path, written on exit


@dataclass
class FrameCheck:
    """The monitor's component: pure bookkeeping over received messages."""

    frames: int = 0
    by_topic: Counter[str] = field(default_factory=Counter)
    invalid: int = 0
    seq_gaps: int = 0
    stamp_backwards: int = 0
    last_seq: dict[str, int] = field(default_factory=dict)
    last_stamp: dict[str, int] = field(default_factory=dict)
    checksum: int = 0  # sum of depth-pixel counts: a cheap end-to-end content check

    def on_rgbd(self, msg: Message) -> None:
        try:
            frame = message_to_frame(msg)
        except ValueError:
            self.invalid += 1
            return
        self.frames += 1
        self.by_topic[msg.topic] += 1
        if msg.topic in self.last_seq and frame.seq != self.last_seq[msg.topic] + 1:
            self.seq_gaps += 1
        if msg.topic in self.last_stamp and frame.stamp_ns < self.last_stamp[msg.topic]:
            self.stamp_backwards += 1
        self.last_seq[msg.topic] = frame.seq
        self.last_stamp[msg.topic] = frame.stamp_ns
        self.checksum += int((frame.depth > 0).sum())

    def report(self) -> dict[str, object]:
        return {
            "frames": self.frames,
            "by_topic": dict(self.by_topic),
            "invalid": self.invalid,
            "seq_gaps": self.seq_gaps,
            "stamp_backwards": self.stamp_backwards,
            "valid_depth_pixels": self.checksum,
        }


def run(name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig) -> int:
    check = FrameCheck()
    node: Node

    def on_rgbd(msg: Message) -> None:
        check.on_rgbd(msg)
        if params.stop_after and check.frames >= params.stop_after:
            node.request_stop()

    node = Node(name, transport, handlers={"rgbd": on_rgbd}, config=runtime)
    try:
        node.run()
    finally:
        if params.report:
            atomic_write_text(
                Path(params.report), json.dumps({"node": name, **check.report()}, indent=2)
            )
        logger.info("%s: %s", name, json.dumps(check.report()))
    return 0
