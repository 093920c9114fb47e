"""Pose-association node: unposed camera frames + SLAM poses in, posed ``rgbd`` frames out.

Subscribes to camera ``rgbd`` messages (``posed: False``) and ``pose`` messages (the SLAM front
end's ``T_world_body``; see examples/slam_pose_publisher.py); publishes posed frames reliably on
``topic``. Frames it cannot pair are counted by reason and appear in its stats."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from gsfix_online.core.types import RGBDFrame
from gsfix_online.runtime import (
    Message,
    Node,
    NodeRuntimeConfig,
    Transport,
    frame_to_message,
    message_to_frame,
)
from gsfix_online.sources.pose_association import PoseAssociationConfig, PoseAssociator


@dataclass(frozen=True)
class Params:
    association: PoseAssociationConfig = field(default_factory=PoseAssociationConfig)
    topic: str = "rgbd/cam0/posed"  # posed frames go to every output: reliable and latest-only


@dataclass(frozen=True)
class _Unposed:
    msg: Message

    @property
    def stamp_ns(self) -> int:
        return self.msg.stamp_ns

    def posed(self, T_world_cam: npt.NDArray[np.float64]) -> RGBDFrame:
        return message_to_frame(self.msg, T_world_cam=T_world_cam)


def handlers(
    assoc: PoseAssociator, publish: Callable[[Message], None], topic: str
) -> dict[str, Callable[[Message], None]]:
    def out(frames: list[RGBDFrame]) -> None:
        for f in frames:
            publish(frame_to_message(f, topic))

    def on_rgbd(msg: Message) -> None:
        if not msg.meta.get("posed", True):  # posed frames are not ours to pair
            out(assoc.add_frame(_Unposed(msg)))

    def on_pose(msg: Message) -> None:
        out(assoc.add_pose(msg.stamp_ns, msg.arrays["T_world_body"]))

    return {"rgbd": on_rgbd, "pose": on_pose}


def run(name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig) -> int:
    assoc = PoseAssociator(params.association)
    node: Node

    cfg = getattr(transport, "config", None)  # the in-memory test transport has no sockets
    modes = {e.mode for e in cfg.outputs} if cfg is not None else {"reliable"}

    def publish(msg: Message) -> None:
        for mode in sorted(modes):
            node.publish(msg, reliable=mode == "reliable")

    node = Node(name, transport, handlers=handlers(assoc, publish, params.topic), config=runtime)
    return node.run()
