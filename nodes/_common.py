"""Helpers shared by node entry points: a source loop that keeps the node's health topics alive."""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Iterable
from typing import Any

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
