"""Repair node: GSFixer on the views the planner accepted, as a node. Wiring only: the component
(queue, render exchange, model choice; its docstring lists the messages) is
:class:`gsfix_online.services.repair.RepairService`.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from gsfix_online.nodes._common import run_loop

from gsfix_online.runtime import Node, NodeRuntimeConfig, Transport
from gsfix_online.services.repair import Params, RepairService  # noqa: F401  (the node's config)

logger = logging.getLogger(__name__)


def build_node(
    name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig,
    clock: Any = time.monotonic,
) -> tuple[Node, RepairService]:  # fmt: skip
    service = RepairService(name, params, clock())
    handlers = {
        "render_request": service.on_view,
        "render_reply": service.on_reply,
        "model_checkpoint": service.on_checkpoint,
        "trainer_plan": service.on_plan,
        "map_event": service.on_map_event,
    }
    node = Node(name, transport, handlers, config=runtime, clock=clock, extra_stats=service.stats)
    return node, service


def step(node: Node, service: RepairService, clock: Any = time.monotonic) -> bool:
    msgs, busy = service.work(clock())
    for m in msgs:
        node.publish(m, reliable=True)
    return busy


def run(name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig) -> int:
    import torch

    if params.threads:
        torch.set_num_threads(params.threads)
    node, service = build_node(name, params, transport, runtime)
    fx = params.fixer
    logger.info("%s: GSFixer %s, %d DDIM step(s) on %d codec grid(s), model %s%s", name,
                fx.model.mode, fx.inference.steps, fx.inference.shifts, fx.model.source,
                f" {fx.model.path}" if fx.model.path else " (the packaged base)")  # fmt: skip
    try:
        return run_loop(node, lambda: step(node, service), "repair")
    finally:
        logger.info("%s: %s", name, service.stats())
