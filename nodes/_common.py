"""Helpers shared by node entry points: a source loop that keeps the node's health topics alive,
render requests addressed back to their requester, and a loop with work between messages."""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from gsfix_online.runtime import Message, Node, Transport

logger = logging.getLogger(__name__)


def run_source(
    node: Node, messages: Iterable[Message], reliable: bool, flush_timeout_s: float = 30.0
) -> int:
    """Publish ``messages`` from a source, serving housekeeping in between; stop on SIGINT/SIGTERM.

    Reliable sends block while the receiver is behind, so a replay at full speed loses nothing.
    At the end, waits until every reliable message is acknowledged (or ``flush_timeout_s``).
    """
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, node.request_stop)
    sent = 0
    ok = True
    try:
        for msg in messages:
            if node.stop_requested:
                break
            node.publish(msg, reliable=reliable)
            sent += 1
            node.spin_once(0)
        flush = getattr(node.transport, "flush", None)
        if callable(flush) and not node.stop_requested:
            ok = bool(flush(flush_timeout_s))
            if not ok:
                logger.error(
                    "%s: %s messages still unacknowledged after %.0f s",
                    node.name,
                    "some",
                    flush_timeout_s,
                )
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        node.transport.close()
    logger.info("%s: sent %d messages", node.name, sent)
    return 0 if ok else 1


def close_quietly(transport: Transport) -> None:
    try:
        transport.close()
    except Exception:  # closing after a failure must not hide the failure
        logger.debug("close failed", exc_info=True)


# --------------------------------------------------------------------------------------------
# Render requests between nodes, and a loop with work between messages
# --------------------------------------------------------------------------------------------


def reply_topic(server: str, request: Message) -> str:
    """``render_reply/<requester>/<server>`` when the request names ``reply_to``, else
    ``render_reply/<server>``: requesters subscribe to their own namespace."""
    reply_to = request.meta.get("reply_to")
    return f"render_reply/{reply_to}/{server}" if reply_to else f"render_reply/{server}"


def render_request(
    requester: str,
    request_id: int,
    T_world_cam: np.ndarray,  # [4, 4]
    K: np.ndarray,  # [3, 3] px
    width: int,
    height: int,
    what: Iterable[str],
    topic: str | None = None,
    meta: dict[str, Any] | None = None,  # extra meta keys
) -> Message:
    """A ``render_request`` whose replies come back on ``render_reply/<requester>/<server>``."""
    return Message(
        topic=topic or f"render_request/{requester}",
        type="render_request",
        seq=max(request_id, 0),
        meta={
            "width": int(width),
            "height": int(height),
            "request_id": int(request_id),
            "what": list(what),
            "reply_to": requester,
            **(meta or {}),
        },
        arrays={
            "K": np.ascontiguousarray(K, np.float64),
            "T_world_cam": np.ascontiguousarray(T_world_cam, np.float64),
        },
    )


def reply_server(requester: str, msg: Message) -> str | None:
    """The server a render reply addressed to ``requester`` came from; None if not for us."""
    prefix = f"render_reply/{requester}/"
    return msg.topic[len(prefix) :] if msg.topic.startswith(prefix) else None


def run_loop(node: Node, work: Callable[[], bool]) -> int:
    """Run ``node`` until SIGINT/SIGTERM or ``request_stop``, calling ``work()`` after each
    message or wait; ``work`` returns True while it has more to do (then the loop does not wait
    for messages). Closes the transport; returns 0."""
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, node.request_stop)
    busy = False
    try:
        while not node.stop_requested:
            node.spin_once(0 if busy else None)
            if not node.stop_requested:
                busy = work()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        node.transport.close()
    return 0
