"""The node run loop: receive, dispatch to a handler, publish results and health topics.

A node is a thin event loop around a component::

    node = Node("mapper", transport, {"rgbd": on_rgbd, "render_request": on_request})
    sys.exit(node.run())  # until SIGINT/SIGTERM

Handlers are looked up by exact topic first, then by message type. A handler returns None, a
Message or a list of Messages; those are published latest-only (call ``node.publish(msg,
reliable=True)`` inside the handler for reliable outputs). A handler exception is counted in
``handler_errors``, logged at most once per kind per period, and the loop goes on, unless
``on_handler_error: raise``.

Every ``heartbeat_period_s`` the node publishes ``heartbeat/<name>``; every ``stats_period_s``
``stats/<name>`` with, per topic, the receive rate, received/dropped counts, rejections per
reason, queue depth and the p50/p99 handler latency over the period.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager
from types import FrameType
from typing import Any

import numpy as np

from gsfix_online.runtime.config import NodeRuntimeConfig
from gsfix_online.runtime.ratelog import RateLimitedLog
from gsfix_online.runtime.timeline import Timeline
from gsfix_online.runtime.transport import Transport
from gsfix_online.runtime.wire import Message

logger = logging.getLogger(__name__)

HandlerResult = Message | Iterable[Message] | None
Handler = Callable[[Message], HandlerResult]


class Node:
    """Dispatch loop over a :class:`Transport`; ``clock`` is monotonic seconds."""

    def __init__(
        self,
        name: str,
        transport: Transport,
        handlers: Mapping[str, Handler],
        config: NodeRuntimeConfig | None = None,
        clock: Callable[[], float] = time.monotonic,
        time_ns: Callable[[], int] = time.time_ns,  # stamps of heartbeat and stats
        extra_stats: Callable[[], Mapping[str, Any]] | None = None,  # component counters
        timeline: Timeline | None = None,  # busy spans; default: the launcher's, if it set one
    ) -> None:
        self.name = name
        self.extra_stats = extra_stats
        self.timeline = timeline if timeline is not None else Timeline.from_env(name)
        self.transport = transport
        self.handlers = dict(handlers)
        self.config = config or NodeRuntimeConfig()
        self.clock = clock
        self.time_ns = time_ns
        self.stop_requested = False
        self.handled: Counter[str] = Counter()  # per topic
        self.unhandled: Counter[str] = Counter()  # per type: no handler for it
        self.handler_errors: Counter[str] = Counter()  # per exception class
        self._latencies_s: deque[float] = deque(maxlen=self.config.latency_window)
        self._log = RateLimitedLog(logger, self.config.log_period_s, clock)
        self._started = clock()
        self._next_heartbeat = self._started
        self._next_stats = self._started + self.config.stats_period_s
        self._stats_at = self._started
        self._received_at_stats: Counter[str] = Counter()
        self._seq: Counter[str] = Counter()

    # ----------------------------------------------------------------------------------------
    # Loop
    # ----------------------------------------------------------------------------------------

    def request_stop(self, signum: int | None = None, frame: FrameType | None = None) -> None:
        """End the loop after the current message. As a SIGINT/SIGTERM handler (``signum``
        given) also interrupt a reliable send or flush that waits for a slow receiver."""
        self.stop_requested = True
        if signum is not None:
            self.transport.interrupt()

    def spin_once(self, timeout_ms: int | None = None) -> bool:
        """Housekeeping, then wait for one message and handle it; True if one was handled."""
        self._housekeeping()
        wait = self.config.poll_timeout_ms if timeout_ms is None else timeout_ms
        msg = self.transport.recv(wait)
        if msg is None:
            return False
        self._dispatch(msg)
        return True

    def run_until_idle(self, max_messages: int | None = None) -> int:
        """Handle messages until none is waiting (for scripted transports); returns the count."""
        n = 0
        while not self.stop_requested and (max_messages is None or n < max_messages):
            if not self.spin_once(0):
                break
            n += 1
        self._housekeeping()
        return n

    def run(self) -> int:
        """Loop until SIGINT/SIGTERM or ``request_stop``; closes the transport; returns 0."""
        previous: dict[int, Any] = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                previous[sig] = signal.signal(sig, self.request_stop)
        logger.info("%s: running (pid %d)", self.name, os.getpid())
        try:
            while not self.stop_requested:
                self.spin_once()
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
            self.transport.close()
        logger.info("%s: stopped", self.name)
        return 0

    @contextmanager
    def span(self, label: str) -> Iterator[None]:
        """Mark work done between messages (a fine-tuning slice, a distillation pass) on the
        node's timeline; a no-op without one."""
        if self.timeline is None:
            yield
        else:
            with self.timeline.span(label):
                yield

    def publish(self, msg: Message, reliable: bool = False) -> None:
        self.transport.publish(msg, reliable=reliable)

    def _dispatch(self, msg: Message) -> None:
        handler = self.handlers.get(msg.topic) or self.handlers.get(msg.type)
        if handler is None:
            self.unhandled[msg.type] += 1
            return
        t0 = self.clock()
        wall0 = time.time()
        try:
            out = handler(msg)
            if isinstance(out, Message):
                self.publish(out)
            elif out is not None:
                for m in out:
                    self.publish(m)
        except Exception as exc:
            kind = type(exc).__name__
            self.handler_errors[kind] += 1
            self._log.warning(
                f"handler:{kind}",
                f"{self.name}: handler for {msg.topic} ({msg.type}) failed: {kind}: {exc}",
            )
            if self.config.on_handler_error == "raise":
                raise
        finally:
            self._latencies_s.append(self.clock() - t0)
            self.handled[msg.topic] += 1
            if self.timeline is not None:
                self.timeline.add(msg.type, wall0, time.time())

    # ----------------------------------------------------------------------------------------
    # Health topics
    # ----------------------------------------------------------------------------------------

    def _housekeeping(self) -> None:
        now = self.clock()
        if now >= self._next_heartbeat:
            self._next_heartbeat = now + self.config.heartbeat_period_s
            meta = {"node": self.name, "pid": os.getpid(), "uptime_s": now - self._started}
            self._publish_health("heartbeat", meta)
        if now >= self._next_stats:
            self._next_stats = now + self.config.stats_period_s
            self._publish_health("stats", self.stats_meta(now))

    def _publish_health(self, kind: str, meta: dict[str, Any]) -> None:
        if not self.transport.publishes_latest:
            return  # a pure consumer (no outputs): its health shows in its log and exit code
        msg = Message(
            topic=f"{kind}/{self.name}",
            type=kind,
            seq=self._seq[kind],
            stamp_ns=self.time_ns(),
            frame_id=self.name,
            meta=meta,
        )
        self._seq[kind] += 1
        try:
            self.transport.publish(msg)
        except Exception as exc:  # health reporting must never stop the node
            self._log.warning(f"health:{kind}", f"{self.name}: cannot publish {kind}: {exc}")

    def stats_meta(self, now: float) -> dict[str, Any]:
        """The ``stats`` message content; resets the latency window and the rate baseline."""
        t = self.transport
        period = max(now - self._stats_at, 1e-9)
        meta: dict[str, Any] = {"node": self.name, "period_s": period}
        for topic, n in sorted(t.received.items()):
            meta[f"rate_hz/{topic}"] = (n - self._received_at_stats[topic]) / period
            meta[f"received/{topic}"] = n
        for topic, n in sorted(t.dropped.items()):
            meta[f"dropped/{topic}"] = n
        for reason, n in sorted(t.rejected.items()):
            meta[f"rejected/{reason}"] = n
        meta["rejected_total"] = sum(t.rejected.values())
        meta["dropped_total"] = sum(t.dropped.values())
        meta["handler_errors"] = sum(self.handler_errors.values())
        meta["unhandled"] = sum(self.unhandled.values())
        meta["queue_depth"] = t.queue_depth()
        lat = np.array(self._latencies_s) * 1e3
        meta["latency_n"] = int(lat.size)
        meta["latency_p50_ms"] = float(np.percentile(lat, 50)) if lat.size else 0.0
        meta["latency_p99_ms"] = float(np.percentile(lat, 99)) if lat.size else 0.0
        meta.update(t.stats())
        if self.extra_stats is not None:
            meta.update(self.extra_stats())
        self._latencies_s.clear()
        self._received_at_stats = Counter(t.received)
        self._stats_at = now
        return meta
