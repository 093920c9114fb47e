"""Map server node: the maps of finished runs (``gsfix-online serve RUN_DIR``) or of a live graph,
on a ZeroMQ ROUTER socket for :class:`gsfix_online.apps.client.MapClient`.

The component is :class:`gsfix_online.services.map_server.MapServer`; this loop adds the
socket, the clock and a worker thread for repairs. Requests are answered in order of arrival; a
request that waited in the server longer than the ``timeout_s`` its client gave is dropped (the
client has given up on it). While a repair runs on the worker, every other request is still
answered, the client of the repair gets a progress message at least every
``progress_every_s`` (from its acceptance on: the worker renders the view too), and a second
repair is answered ``busy``.

In a graph (kind ``map_server``) the node also serves the graph's map as ``live.map`` (default
``live``): the splat node's exports (``export/``) and the TSDF node's meshes (``mesh/``). A repair
of the live map goes through the graph (:mod:`gsfix_online.services.live_map`): the node sends
the view to the planner (output ``view_request/<node>``), follows the planner's decision, the
repair node's ``repaired_view`` and the splat node's ``distill/`` announcement, asks the splat
node for an export (on ``live.export_topic``) and answers with the repair and the map's new
version, or with the planner's skip reason and its 3DGS render; the client hears each stage.
``configs/graphs/repair_served.yaml`` wires it.
"""

from __future__ import annotations

import logging
import queue
import signal
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from gsfix_online.apps.client import PROTOCOL, ProtocolError, pack, unpack
from gsfix_online.core.config import rng
from gsfix_online.runtime import Message, Node, NodeRuntimeConfig, Transport
from gsfix_online.services.live_map import LiveConfig, LiveMap
from gsfix_online.services.map_server import MapServer, RepairJob, RequestError, ServerConfig

logger = logging.getLogger(__name__)

MAX_REQUEST_BYTES = 1 << 20  # requests are small; a larger one closes its connection
POLL_MS = 50
GRAPH_BATCH = 256  # graph messages handled at most between two looks at the request socket


@dataclass(frozen=True)
class Params:
    runs: list[str] = field(default_factory=list)  # run folders to serve, by folder name
    host: str = "127.0.0.1"
    port: int = field(default=5590, metadata=rng(1, 65535, "TCP port of the request socket"))
    server: ServerConfig = field(default_factory=ServerConfig)
    progress_every_s: float = field(
        default=1.0, metadata=rng(0.05, 60, "a repair's client hears from it at least this often")
    )
    threads: int = field(default=0, metadata=rng(0, 256, "torch threads; 0 = torch default"))
    live: LiveConfig = field(default_factory=LiveConfig)  # a graph's map and its repairs


@dataclass
class _Request:
    identity: bytes
    id: Any
    op: str
    args: dict[str, Any]
    deadline: float


@dataclass
class _Running:
    job: RepairJob | None  # None: a live repair, followed through the graph by LiveMap
    req: _Request
    last_sent: float
    progress: tuple[float, str] = (0.0, "rendering the view")


class RequestLoop:
    """The ROUTER socket around a MapServer: receive, answer, run repairs on a worker."""

    def __init__(
        self,
        service: MapServer,
        params: Params,
        clock: Any = time.monotonic,
        live: LiveMap | None = None,
        node: Node | None = None,  # publishes what a live repair sends to the graph
    ) -> None:
        import zmq

        self.zmq = zmq
        self.service = service
        self.params = params
        self.clock = clock
        self.live = live
        self.node = node
        s = zmq.Context.instance().socket(zmq.ROUTER)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.MAXMSGSIZE, MAX_REQUEST_BYTES)
        s.setsockopt(zmq.HEARTBEAT_IVL, 1000)
        s.setsockopt(zmq.HEARTBEAT_TIMEOUT, 3000)
        self.address = f"tcp://{params.host}:{params.port}"
        s.bind(self.address)
        self.sock = s
        self.pending: deque[_Request] = deque()
        self.events: queue.Queue[tuple[str, Any]] = queue.Queue()
        self.running: _Running | None = None

    def close(self) -> None:
        self.sock.close(linger=0)

    # -- frames ------------------------------------------------------------------------------

    def _send(self, identity: bytes, header: dict[str, Any], buffers: dict | None = None) -> None:
        try:  # a client that is gone or not reading is dropped, never waited for
            self.sock.send_multipart([identity, *pack(header, buffers)], self.zmq.NOBLOCK)
        except self.zmq.Again:
            logger.warning("dropping an answer to a client that does not read")

    def _error(self, req: _Request, kind: str, message: str) -> None:
        self.service.count(req.op, ok=False)
        logger.info("%s %s: %s", req.op, kind, message)
        self._send(req.identity, {"id": req.id, "status": "error", "kind": kind, "error": message})

    def _receive(self) -> None:
        """Move every request waiting on the socket into the queue, stamped now."""
        now = self.clock()
        while self.sock.poll(0):
            frames = self.sock.recv_multipart(copy=False)
            identity = bytes(frames[0])
            try:
                header, _ = unpack(frames[1:])
                if not isinstance(header.get("op"), str) or not isinstance(
                    header.get("args", {}), dict
                ):
                    raise ProtocolError("a request needs an op (str) and args (map)")
                timeout = float(header.get("timeout_s", 10.0))
            except (ProtocolError, TypeError, ValueError) as exc:
                self.service.count("invalid", ok=False)
                if len(frames) > 1 and bytes(frames[1]) == PROTOCOL:
                    self._send(identity, {"id": None, "status": "error", "kind": "bad_request",
                                          "error": f"malformed request: {exc}"})  # fmt: skip
                continue
            self.pending.append(
                _Request(
                    identity,
                    header.get("id"),
                    header["op"],
                    dict(header.get("args", {})),
                    now + timeout,
                )  # fmt: skip
            )

    # -- one round ---------------------------------------------------------------------------

    def step(self, timeout_ms: int = POLL_MS) -> None:
        """Wait up to ``timeout_ms`` for requests, then answer what is due."""
        if not self.pending and self.events.empty():
            self.sock.poll(timeout_ms)
        self._receive()
        self._repair_events()
        while self.pending:
            req = self.pending.popleft()
            now = self.clock()
            if now > req.deadline:  # its client gave up while it waited here
                self.service.counts["expired"] += 1
                continue
            self._answer(req, now)
            self._receive()
            self._repair_events()

    def _answer(self, req: _Request, now: float) -> None:
        try:
            if req.op == "repair":
                self._start_repair(req, now)
                return
            result, buffers = self.service.handle(req.op, req.args, now)
        except RequestError as exc:
            self._error(req, exc.kind, str(exc))
            return
        except Exception as exc:  # a bug or a broken file: answer it, keep serving
            logger.exception("%s failed", req.op)
            self._error(req, "failed", f"{req.op} failed: {type(exc).__name__}: {exc}")
            return
        self.service.count(req.op, ok=True)
        self._send(req.identity, {"id": req.id, "status": "ok", "result": result}, buffers)

    # -- repairs -----------------------------------------------------------------------------

    def _start_repair(self, req: _Request, now: float) -> None:
        if self.live is not None and self.node is not None:
            if self.live.wants(req.args):
                for msg in self.live.begin(req.args, now):  # RequestError: busy, bad pose, ...
                    self.node.publish(msg, reliable=True)
                self.running = _Running(None, req, now)
                return
            self.live.check_idle(now)

        job = self.service.begin_repair(req.args, now)  # RequestError: busy, bad pose, ...
        events = self.events

        def work() -> None:
            try:
                job.run(lambda f, t: events.put(("progress", (f, t))))
                events.put(("done", None))
            except Exception as exc:
                logger.exception("repair failed")
                events.put(("failed", f"repair failed: {type(exc).__name__}: {exc}"))

        self.running = _Running(job, req, now)
        self._progress(0.0, "accepted; rendering the view")  # the worker renders it
        threading.Thread(target=work, name="map-server-repair", daemon=True).start()

    def _progress(self, fraction: float, text: str) -> None:
        run = self.running
        assert run is not None
        run.progress, run.last_sent = (fraction, text), self.clock()
        self._send(run.req.identity, {"id": run.req.id, "status": "progress",
                                      "result": {"fraction": fraction, "text": text}})  # fmt: skip

    def _repair_events(self) -> None:
        run = self.running
        if run is None:
            return
        if self.live is not None:
            self.live.poll(self.clock())
            for u in self.live.take_updates():
                self.events.put((u.kind, u))
        while True:
            try:
                kind, value = self.events.get_nowait()
            except queue.Empty:
                break
            if kind == "progress":
                self._progress(*((value.fraction, value.text) if run.job is None else value))
                continue
            self.running = None
            if run.job is None:  # a live repair's end: LiveMap's Update
                result, image, failure = value.result, value.image, value.text
            else:
                result = self.service.finish_repair(run.job, ok=kind == "done")
                image, failure = run.job.image, value
            if kind == "done":
                self.service.count("repair", ok=True)
                logger.info("repair: %s", result["reason"])
                self._send(run.req.identity, {"id": run.req.id, "status": "ok", "result": result},
                           {"image": image})  # fmt: skip
            else:
                self._error(run.req, "failed", failure)
            return
        if self.clock() - run.last_sent >= self.params.progress_every_s:
            self._progress(*run.progress)  # still working: the client's deadline moves on


# ------------------------------------------------------------------------------------------------
# Entry points: `gsfix-online serve` and the graph node
# ------------------------------------------------------------------------------------------------


def build_service(params: Params, clock: Any = time.monotonic) -> MapServer:
    service = MapServer(params.server, clock())
    for run in params.runs:
        service.add_run(run)
    return service


def _loop(loop: RequestLoop, node: Node | None, stop: threading.Event) -> None:
    while not stop.is_set() and not (node is not None and node.stop_requested):
        loop.step()
        # every graph message waiting (the splat node's render replies pass by here too: a
        # reliable sender blocks while this node is behind)
        for _ in range(GRAPH_BATCH):
            if node is None or not node.spin_once(0):
                break


def _with_signals(stop: threading.Event, extra: Any = None) -> dict[int, Any]:
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):

            def handler(signum: int, frame: Any) -> None:
                stop.set()
                if extra is not None:
                    extra()

            previous[sig] = signal.signal(sig, handler)
    return previous


def serve(params: Params, ready: Any = None) -> int:
    """Serve ``params.runs`` until SIGINT/SIGTERM; ``ready(loop)`` is called once bound."""
    import torch

    if params.threads:
        torch.set_num_threads(params.threads)
    service = build_service(params)
    loop = RequestLoop(service, params)
    stop = threading.Event()
    previous = _with_signals(stop)
    try:
        if ready is not None:
            ready(loop)
        _loop(loop, None, stop)
    finally:
        for sig, h in previous.items():
            signal.signal(sig, h)
        loop.close()
    logger.info("map server %s: %s", loop.address, service.stats(time.monotonic())[0])
    return 0


def build_node(
    name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig,
    service: MapServer, clock: Any = time.monotonic,
) -> tuple[Node, LiveMap]:  # fmt: skip
    """The graph side: the live map's announcements and the messages of its repairs."""
    live = LiveMap(name, params.live, service)
    node: Node

    def on_map_event(msg: Message) -> None:
        for out in live.on_map_event(msg, clock()):
            node.publish(out, reliable=True)

    def stats() -> dict[str, Any]:
        maps = service.stats(clock())[0]["maps"]
        return {**{f"maps/{k}": v for k, v in maps.items()}, **live.stats()}

    handlers = {
        "render_reply": lambda msg: live.on_decision(msg, clock()),
        "repaired_view": lambda msg: live.on_repaired(msg, clock()),
        "map_event": on_map_event,
    }
    node = Node(name, transport, handlers, config=runtime, clock=clock, extra_stats=stats)
    return node, live


def run(name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig) -> int:
    """The graph node: serve ``params.runs`` and the graph's live map, repairs of it included."""
    import torch

    if params.threads:
        torch.set_num_threads(params.threads)
    service = build_service(params)
    node, live = build_node(name, params, transport, runtime, service)
    loop = RequestLoop(service, params, live=live, node=node)
    stop = threading.Event()
    previous = _with_signals(stop, node.request_stop)
    logger.info("%s: serving %s on %s", name, ", ".join(service.maps) or "no map yet", loop.address)
    try:
        _loop(loop, node, stop)
    finally:
        for sig, h in previous.items():
            signal.signal(sig, h)
        loop.close()
        node.transport.close()
    return 0
