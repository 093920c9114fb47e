"""RealSense camera node: publishes unposed ``rgbd`` frames (latest-only: live frames, the newest wins)."""

from __future__ import annotations

from dataclasses import dataclass, field

from gsfix_online.nodes.camera import run_camera

from gsfix_online.core.config import rng
from gsfix_online.runtime import NodeRuntimeConfig, Transport
from gsfix_online.sources.realsense import RealSenseConfig


@dataclass(frozen=True)
class Params:
    realsense: RealSenseConfig = field(default_factory=RealSenseConfig)
    topic: str = "rgbd/cam0"
    reliable: bool = False
    # the processing resolution: frames wider than this are resized before they are published
    # (as source.max_width does for recorded input); 0 = as captured
    max_width: int = field(default=0, metadata=rng(0, None, "px; 0 = as captured"))


def run(name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig) -> int:
    from gsfix_online.sources.realsense import RealSenseSource

    with RealSenseSource(params.realsense) as source:
        return run_camera(
            name, source, params.topic, params.reliable, transport, runtime, params.max_width
        )
