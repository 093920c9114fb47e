"""Trainer node: GSFixer fine-tuning in the background, as a node. Wiring only: the component
(model, latent caches, disocclusion masks, policy state, checkpoints; its docstring lists the
messages) is :class:`gsfix_online.services.trainer.TrainerService`. This loop drains the queue,
runs one slice of work, publishes the announcements and logs progress every ``log_every_s``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from gsfix_online.runtime import Node, NodeRuntimeConfig, Transport
from gsfix_online.services.trainer import POLICY_FILE, Params, TrainerService  # noqa: F401  (Params: the node's config)

logger = logging.getLogger(__name__)


def build_node(
    name: str,
    params: Params,
    transport: Transport,
    runtime: NodeRuntimeConfig,
    clock: Callable[[], float] = time.monotonic,
) -> tuple[Node, TrainerService]:
    service = TrainerService(name, params, clock)
    handlers = {
        "keyframe": service.on_keyframe,
        "map_event": service.on_map_event,
        "input_end": service.on_input_end,
    }
    node = Node(name, transport, handlers, config=runtime, extra_stats=service.stats, clock=clock)
    return node, service


def step(node: Node, service: TrainerService, params: Params) -> bool:
    """Drain the queue, then one slice of work; False when nothing was there to do."""
    busy = service.busy
    handled = node.spin_once(0 if busy else None)  # idle: wait for input as a plain node
    while handled and not node.stop_requested:
        handled = node.spin_once(0)
    line = service.progress_line()
    if line is not None:
        logger.info("%s: %s", node.name, line)
    did = False
    if service.busy and not node.stop_requested:
        with node.span("fine-tune"):
            msgs = service.work(node.time_ns())
        for msg in msgs:
            node.publish(msg, reliable=params.announce == "reliable")
        did = True
        if params.stop_after_steps and service.trainer.step >= params.stop_after_steps:
            node.request_stop()
    return did


def run(name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig) -> int:
    import os
    import signal
    import threading

    import torch

    if params.nice:
        os.nice(params.nice)
    if params.threads:
        torch.set_num_threads(params.threads)
    node, service = build_node(name, params, transport, runtime)
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, node.request_stop)
    try:
        while not node.stop_requested:
            step(node, service, params)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        transport.close()
        logger.info("%s: %s", name, service.stats())
    return 0
