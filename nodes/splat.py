"""Splat node: the Gaussian map as a node. Wiring only: the component that maps frames, serves
renders, distils repaired views and schedules the passes is
:class:`gsfix_online.services.splat.SplatService` (its docstring lists the messages).
This loop adds the clock, snapshots every ``snapshot_every`` frames, map stats, SIGUSR1 exports
and the final refinement and export on exit.
"""

from __future__ import annotations

import logging
import signal
import threading

import numpy as np
from gsfix_online.nodes._common import run_loop

from gsfix_online.runtime import Message, Node, NodeRuntimeConfig, Transport, TransportError
from gsfix_online.services.splat import Params, SplatService, load_snapshot, save_snapshot  # noqa: F401  (Params: the node's config)

logger = logging.getLogger(__name__)


def run(name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig) -> int:
    import time

    import torch

    if params.threads:
        torch.set_num_threads(params.threads)
    service = SplatService(name, params)
    node: Node
    export_requested = threading.Event()
    map_times: list[float] = []

    def on_rgbd(msg: Message) -> None:
        t0 = time.perf_counter()
        out = service.on_rgbd(msg)
        map_times.append(time.perf_counter() - t0)
        for m in out:  # keyframes, frame samples, the end of the input
            node.publish(m, reliable=True)
        service.after_input_end()  # the refinement, once the trainer has heard of the end
        n = service.frames
        if params.snapshot_every and n % params.snapshot_every == 0:
            service.snapshot()
        if n % params.stats_every == 0:
            lat = np.asarray(map_times[-params.stats_every :]) * 1e3
            extra = {"map/process_p50_ms": float(np.percentile(lat, 50)),
                     "map/process_max_ms": float(lat.max())}  # fmt: skip
            node.publish(service.stats_message(time.time_ns(), float(lat.sum() / 1e3), extra))
        if export_requested.is_set():
            export_requested.clear()
            logger.info("%s: exported %s", name, service.export())
        if params.stop_after and n >= params.stop_after:
            node.request_stop()

    def on_request(msg: Message) -> None:
        node.publish(service.on_render_request(msg), reliable=params.reliable_replies)

    announce = params.announce == "reliable"

    def on_repaired(msg: Message) -> None:
        node.publish(service.on_repaired_view(msg), reliable=announce)

    def on_export(msg: Message) -> None:
        node.publish(service.on_export(msg), reliable=announce)

    def work() -> bool:
        done = service.distill_passes(time.time_ns())
        if done is not None:
            node.publish(done, reliable=announce)
        return service.pass_steps_left > 0

    handlers = {"rgbd": on_rgbd, "render_request": on_request, params.export_topic: on_export,
                "repaired_view": on_repaired}  # fmt: skip
    node = Node(name, transport, handlers=handlers, config=runtime)
    if service.frames:  # resumed: what a killed node sent unacknowledged died with it
        again = service.keyframes_again()
        try:
            for m in again:
                node.publish(m, reliable=True)
            logger.info("%s: announced the snapshot's %d keyframes again", name, len(again))
        except TransportError as exc:  # no keyframe reader in this graph, or it is gone
            logger.warning("%s: snapshot keyframes not announced again: %s", name, exc)
    previous = None
    if threading.current_thread() is threading.main_thread() and hasattr(signal, "SIGUSR1"):
        previous = signal.signal(signal.SIGUSR1, lambda *_: export_requested.set())
    try:
        run_loop(node, work, "distil")
    finally:
        if previous is not None:
            signal.signal(signal.SIGUSR1, previous)
        if service.mapper is not None and params.refine_on_exit:
            service.mapper.refine(params.refine_on_exit)
        service.snapshot()
        path = service.export()
        logger.info("%s: %d frames mapped; snapshot %s; export %s", name, service.frames,
                    params.snapshot or "-", path or "-")  # fmt: skip
    return 0
