"""Repair node: runs GSFixer on the views the planner accepted and sends the repairs on, reliably.

Inputs (exact topic first, then type):

- ``render_request`` on ``view/...`` (the planner's accepted views, reliable): queued in order.
- ``render_reply`` on ``render_reply/<this node>/<server>``: the view's 3DGS render (colour,
  alpha) from ``gs_server`` and its mesh render (colour, alpha = hit) from ``mesh_server``.
- ``checkpoint`` on ``checkpoint_topic`` (the trainer's announcements): with ``checkpoint:
  latest`` or ``wait`` the newer model is loaded before the next view.

One view at a time: request both renders (asked again after ``reply_timeout_s``), repair, then
publish reliably:

- ``repaired_view/<node>`` (colour, K, T_world_cam; meta ``view_id``, ``keyframe_id`` = -1,
  ``model_step``, ``model_version``, ``render_s``, ``fix_s``) to the splat node (distillation)
  and to the output writer;
- ``repair_input/<node>/gs`` and ``/mesh``: the renders GSFixer got (``render_reply`` messages,
  meta ``view_id``), for the outputs.

Which model: ``base`` = ``fixer.model`` only; ``latest`` = the base until the trainer announces
a checkpoint, then the newest; ``wait`` = no repair before the first checkpoint; ``run`` = no
repair before ``checkpoint_runs`` fine-tuning runs have ended (the trainer's announcement says
``run_done``), then the newest. ``wait`` and ``run`` give up after ``checkpoint_wait_s`` and use
the newest checkpoint announced by then, else the base.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from gsfix_online.config_schema import rng
from gsfix_online.fixer.config import FixerConfig
from gsfix_online.repair.repairer import ViewRepairer, seed_depth
from gsfix_online.runtime import Message, Node, NodeRuntimeConfig, Transport
from nodes._common import render_request, reply_server, run_loop

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Params:
    fixer: FixerConfig = field(default_factory=FixerConfig)
    checkpoint: Literal["base", "latest", "wait", "run"] = "latest"
    checkpoint_wait_s: float = field(
        default=600.0, metadata=rng(0, None, "wait: longest wait for a first checkpoint, s")
    )
    checkpoint_runs: int = field(
        default=1, metadata=rng(1, None, "run: fine-tuning runs to wait for before repairing")
    )
    checkpoint_topic: str = "checkpoint/"  # the trainer's announcements
    view_topic: str = "view/"  # the planner's accepted views
    gs_server: str = "splat"
    mesh_server: str = "tsdf"
    reply_timeout_s: float = field(
        default=30.0, metadata=rng(0.1, 3600, "ask for a view's renders again after, s")
    )
    threads: int = field(default=0, metadata=rng(0, 256, "torch threads; 0 = torch default"))
    # Send a seed depth for the whole view: the mesh's, and in parts no map holds, depth inpainted
    # from it (gsfix_online.repair.repairer.seed_depth); False: the mesh's surface only.
    seed_empty: bool = True


@dataclass
class _Current:
    msg: Message  # the accepted view
    sent: float
    started: float
    replies: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)


class RepairService:
    """Queue of accepted views, the render exchange and GSFixer; no sockets, clock passed in."""

    def __init__(self, name: str, params: Params, started: float) -> None:
        self.name = name
        self.params = params
        self.repairer = ViewRepairer(params.fixer)
        self.started = started
        if params.checkpoint not in ("wait", "run"):
            self.repairer.load_base()
        self.runs_done = 0  # the highest run whose end a checkpoint announced
        self.queue: deque[Message] = deque()
        self.current: _Current | None = None
        self.pending_checkpoint: tuple[str, int] | None = None
        self.counts = {"views": 0, "repaired": 0, "resent": 0, "checkpoints": 0}

    def on_view(self, msg: Message) -> None:
        if msg.topic.startswith(self.params.view_topic):
            self.queue.append(msg)
            self.counts["views"] += 1

    def on_checkpoint(self, msg: Message) -> None:
        if self.params.checkpoint == "base" or not msg.topic.startswith(
            self.params.checkpoint_topic
        ):
            return
        version = int(msg.meta["version"])
        if msg.meta.get("run_done", False):
            self.runs_done = max(self.runs_done, int(msg.meta.get("run", 1)))
        pending = self.pending_checkpoint[1] if self.pending_checkpoint else -1
        if version > max(self.repairer.version, pending):
            self.pending_checkpoint = (str(msg.meta["path"]), version)

    def on_reply(self, msg: Message) -> None:
        server = reply_server(self.name, msg)
        kind = {self.params.gs_server: "gs", self.params.mesh_server: "mesh"}.get(server or "")
        cur = self.current
        if kind is None or cur is None or int(msg.meta["request_id"]) != cur.msg.meta["view_id"]:
            return  # not ours, or a duplicate of an earlier view
        cur.replies[kind] = dict(msg.arrays)

    def _model(self, now: float) -> bool:
        """Swap in an announced checkpoint; False while waiting for the first one (``wait``) or
        for the end of ``checkpoint_runs`` fine-tuning runs (``run``)."""
        waited_out = now - self.started >= self.params.checkpoint_wait_s
        runs_ended = self.runs_done >= self.params.checkpoint_runs
        if self.params.checkpoint == "run" and not (runs_ended or waited_out):
            return False  # take no intermediate checkpoint: the run's end brings the best one
        if self.pending_checkpoint is not None:
            path, version = self.pending_checkpoint
            self.pending_checkpoint = None
            self.repairer.load_checkpoint(path, version)
            self.counts["checkpoints"] += 1
            logger.info("%s: using checkpoint %s (version %d)", self.name, path, version)
        if not self.repairer.ready and waited_out:
            logger.warning("%s: no checkpoint after %.0f s; using the base model", self.name,
                           self.params.checkpoint_wait_s)  # fmt: skip
            self.repairer.load_base()
        return self.repairer.ready

    def work(self, now: float) -> tuple[list[Message], bool]:
        """(messages to publish reliably, whether to come back without waiting)."""
        cur = self.current
        if cur is None:
            if not self.queue or not self._model(now):
                return [], False
            view = self.queue.popleft()
            self.current = _Current(view, now, now)
            return [self._ask(view)], False
        if len(cur.replies) < 2:
            if now - cur.sent >= self.params.reply_timeout_s:
                cur.sent = now
                self.counts["resent"] += 1
                return [self._ask(cur.msg)], False
            return [], False
        self.current = None
        return self._repair(cur, now), bool(self.queue)

    def _ask(self, view: Message) -> Message:
        m = view.meta
        return render_request(
            self.name, int(m["view_id"]), view.arrays["T_world_cam"], view.arrays["K"],
            int(m["width"]), int(m["height"]), ("color", "alpha", "depth"),
        )  # fmt: skip

    def _repair(self, cur: _Current, now: float) -> list[Message]:
        gs, mesh = cur.replies["gs"], cur.replies["mesh"]
        t0 = time.perf_counter()  # the model's own time, not the wait for renders
        out = self.repairer.repair(np.asarray(gs["color"]), np.asarray(mesh["color"]))
        fix_s = time.perf_counter() - t0
        view = cur.msg
        vid = int(view.meta["view_id"])
        self.counts["repaired"] += 1
        meta = {
            "view_id": vid,
            "keyframe_id": -1,
            "model_step": out.model_step,
            "model_version": out.model_version,
            "render_s": now - cur.started,
            "fix_s": fix_s,
        }
        logger.info("%s: repaired view %03d in %.2f s (model version %d)", self.name, vid, fix_s,
                    out.model_version)  # fmt: skip
        valid = (np.asarray(mesh["alpha"]) > 0.5).astype(np.float32)
        repaired = {"color": out.image, "K": view.arrays["K"],
                    "T_world_cam": view.arrays["T_world_cam"]}  # fmt: skip
        if "depth" in mesh:  # lets distillation grow the map into its holes
            repaired["depth"] = seed_depth(mesh["depth"], valid > 0, self.params.seed_empty)
        return [
            Message(
                f"repaired_view/{self.name}", "repaired_view", vid, view.stamp_ns, "world", meta,
                repaired,
            ),
            Message(
                f"repair_input/{self.name}/gs", "render_reply", vid, view.stamp_ns, "world",
                {"request_id": vid, "view_id": vid},
                {"color": gs["color"], "alpha": gs["alpha"]},
            ),
            Message(
                f"repair_input/{self.name}/mesh", "render_reply", vid, view.stamp_ns, "world",
                {"request_id": vid, "view_id": vid}, {"color": mesh["color"], "alpha": valid},
            ),
        ]  # fmt: skip

    def stats(self) -> dict[str, Any]:
        out = {f"repair/{k}": v for k, v in self.counts.items()}
        out.update(
            {"repair/queued": len(self.queue), "repair/model_version": self.repairer.version}
        )
        return out


def build_node(
    name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig,
    clock: Any = time.monotonic,
) -> tuple[Node, RepairService]:  # fmt: skip
    service = RepairService(name, params, clock())
    handlers = {
        "render_request": service.on_view,
        "render_reply": service.on_reply,
        "checkpoint": service.on_checkpoint,
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
    try:
        return run_loop(node, lambda: step(node, service))
    finally:
        logger.info("%s: %s", name, service.stats())
