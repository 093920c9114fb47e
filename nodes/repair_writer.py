"""Repair writer node: collects a repair run into its output folder and ends it. Wiring only:
the component is :class:`gsfix_online.services.writer.WriterService`.

Inputs (by type, then topic):

- ``render_reply`` on ``decision/<planner>/gs|mesh``: every view's decision and renders;
  on ``repair_input/<repair>/gs|mesh``: the renders GSFixer got; on
  ``render_reply/<this node>/<gs_server>``: final renders.
- ``repaired_view``: the repair (the same message the splat node distils): GSFixer's output
  where it measured better than the fallbacks, else theirs; on ``repair_input/<repair>/fixer``
  GSFixer's own output. From the planner (meta ``fill_only``): the fill of a skipped view's holes.
- ``map_event`` on ``distill/`` (kind ``distilled``): distillation progress of the splat node;
  on ``mesh/`` (``mesh_written``): the mesh snapshot it asked the TSDF node for; on ``export/``
  (``exported``): the map export it asked for. Those it asks for with ``command`` messages
  (kind ``snapshot`` on the TSDF node's ``snapshot_topic``, ``export`` on the splat node's).

With ``expected_views`` = N it ends the run by itself: once N views (or more: the planner's
decisions say how many views it holds, its proposals included) are decided, every accepted
view is repaired and distilled (and every skipped view the planner filled), the passes are
done, it renders every view from the final map (``final.png``), asks the TSDF node for
``mesh.ply`` and the splat node for the standard 3DGS export (``map/``), writes
``metrics.json`` and ``report.html`` (see :mod:`gsfix_online.repair.outputs`) and exits 0.
While it collects, it makes the scoring baselines that are due (FSR, when ground truth
scores the run) one view at a time between messages, not all at the end.
Requests are re-sent after ``reply_timeout_s``. With ``expected_views`` = 0 it writes the metrics on exit.

``OUT/work/progress.json`` says how far the run is (views in all, decided, repaired, distilled,
final renders, the phase and what it waits for); ``gsfix-online repair`` shows it as it changes.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from gsfix_online.nodes._common import run_loop

from gsfix_online.runtime import Node, NodeRuntimeConfig, Transport
from gsfix_online.services.writer import Params, WriterService  # noqa: F401  (the node's config)

logger = logging.getLogger(__name__)


def build_node(
    name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig,
    clock: Any = time.monotonic,
) -> tuple[Node, WriterService]:  # fmt: skip
    service = WriterService(name, params, clock())
    handlers = {
        "render_reply": service.on_render_reply,
        "repaired_view": service.on_repaired,
        "map_event": service.on_map_event,
    }
    node = Node(name, transport, handlers, config=runtime, clock=clock)
    return node, service


def step(node: Node, service: WriterService, clock: Any = time.monotonic) -> bool:
    msgs, finished = service.work(clock())
    for m in msgs:
        node.publish(m, reliable=True)
    if finished:
        logger.info("%s: wrote %s", node.name, service.out / "metrics.json")
        node.request_stop()
        return False
    return service.idle_work()


def run(name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig) -> int:
    import torch

    # Scoring runs kornia's SSIM on small images: one thread, since with two on a loaded 2-core
    # machine OpenMP barriers made each image 30-50x slower (8-14 ms against 200-430 ms)
    torch.set_num_threads(1)
    node, service = build_node(name, params, transport, runtime)
    try:
        run_loop(node, lambda: step(node, service), "write")
    finally:
        if service.phase.name != "done":
            service.write(time.monotonic())  # what arrived so far
    return 0
