"""TSDF node: wires :class:`gsfix_online.services.tsdf.TsdfService` to the transport.

Inputs (dispatched by exact topic first, then by type): ``rgbd`` (integrate), ``render_request``
(-> ``render_reply`` on ``render_reply/<node>``, or ``render_reply/<requester>/<node>`` when the
request names ``reply_to``; the asked-for subset of ``color``, ``depth`` and ``alpha`` from a mesh
holding every integrated frame), and ``command`` messages of kind ``snapshot`` on
``snapshot_topic`` (write and announce the mesh). Announcements are ``map_event`` messages of
kind ``mesh_written`` on ``mesh/<node>``: ``path`` (the first file), ``version`` (mesh version), ``step`` (frames integrated), plus ``files``,
``vertices`` and ``triangles``. ``stats/<node>`` carries the volume's counters as ``tsdf/<key>``.
With ``stop_after`` the node exits after that many integrated frames.
"""

from __future__ import annotations

import logging

from gsfix_online.runtime import Message, Node, NodeRuntimeConfig, Transport
from gsfix_online.services.tsdf import Params, TsdfService

logger = logging.getLogger(__name__)

__all__ = ["Params", "TsdfService", "build_node", "run"]


def build_node(
    name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig
) -> tuple[Node, TsdfService]:
    service = TsdfService(name, params)
    node: Node

    def on_rgbd(msg: Message) -> list[Message]:
        out = service.on_rgbd(msg)
        if params.stop_after and service.volume.frames >= params.stop_after:
            node.request_stop()
        return out

    handlers = {
        params.snapshot_topic: service.on_snapshot,
        "rgbd": on_rgbd,
        "render_request": service.on_render_request,
    }
    node = Node(name, transport, handlers, config=runtime, extra_stats=service.stats)
    return node, service


def run(name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig) -> int:
    node, service = build_node(name, params, transport, runtime)
    try:
        return node.run()
    finally:
        logger.info("%s: %s", name, service.stats())
