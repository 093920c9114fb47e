"""Planner node: takes view requests, scores each view from cheap renders, passes on those that
need repair and reports every decision with its reason. Wiring only: the component is
:class:`gsfix_online.services.planner.PlannerService`.

Inputs (exact topic first, then type):

- ``views`` (param): a TUM pose list read at start, views numbered 0.. in file order.
- ``render_request`` from outside the graph (its ``listen`` input): a view request with its own
  K, width and height (meta ``input_camera: true`` = use the input camera instead).
- ``keyframe`` (from the splat node): keyframe poses for observation counts, the input camera,
  and optional proposals of views beside keyframes.
- ``render_reply`` on ``render_reply/<this node>/<server>``: renders from ``gs_server`` (3DGS:
  colour, alpha) and ``mesh_server`` (mesh: colour, depth, alpha = hit), and progress probes.

Between messages the :class:`~gsfix_online.repair.scheduler.ViewPlanner` says what to request
(gate on mapping progress, pacing, re-sends). Outputs, all reliable:

- ``render_request/<node>`` to both servers (replies come back to this node);
- ``decision/<node>/gs`` and ``decision/<node>/mesh`` for every view (``render_reply`` messages
  with the renders; meta: ``view_id``, ``repair``, ``reason``, the score fractions, ``K`` (9) and
  ``T_world_cam`` (16) flattened, ``width``, ``height``, ``score_s``);
- ``view/<node>`` for views that need repair (a ``render_request`` with the same meta);
- ``repaired_view/<node>`` for views it skipped that still have holes (``fill_skipped``): mesh
  fill + Telea with the holes as mask (:func:`~gsfix_online.repair.repairer.fill_skipped`), for
  the splat node to distil and the writer to record (meta ``fill_only: true``; the decision's
  meta says ``fill: true``).
"""

from __future__ import annotations

import logging
import time
from typing import Any

from gsfix_online.nodes._common import run_loop

from gsfix_online.runtime import Message, Node, NodeRuntimeConfig, Transport
from gsfix_online.services.planner import Params, PlannerService, ViewCamera, decision_messages  # noqa: F401  (Params: the node's config)

logger = logging.getLogger(__name__)


def build_node(
    name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig,
    clock: Any = time.monotonic,
) -> tuple[Node, PlannerService]:  # fmt: skip
    service = PlannerService(name, params)
    node: Node

    def on_reply(msg: Message) -> None:
        for out in service.on_reply(msg, clock()):
            node.publish(out, reliable=True)

    handlers = {
        "keyframe": service.on_keyframe,
        "render_request": service.on_view_request,
        "render_reply": on_reply,
    }
    node = Node(name, transport, handlers, config=runtime, clock=clock, extra_stats=service.stats)
    return node, service


def step(node: Node, service: PlannerService, clock: Any = time.monotonic) -> bool:
    """Send what the planner asks for now; always False (the loop waits for replies)."""
    for msg in service.poll(clock()):
        node.publish(msg, reliable=True)
    return False


def run(name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig) -> int:
    node, service = build_node(name, params, transport, runtime)
    try:
        return run_loop(node, lambda: step(node, service), "plan")
    finally:
        logger.info("%s: %s", name, service.stats())
