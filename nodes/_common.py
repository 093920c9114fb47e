"""Helpers shared by node entry points: a source loop that keeps the node's health topics alive,
render requests addressed back to their requester, and a loop with work between messages."""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Callable, Iterable
from typing import Any

from gsfix_online.runtime import Message, Node, Transport, TransportError, TransportInterrupted
from gsfix_online.runtime.requests import render_request, reply_server, reply_topic  # noqa: F401  (re-exported for the nodes)

logger = logging.getLogger(__name__)


def run_source(
    node: Node, messages: Iterable[Message], reliable: bool, flush_timeout_s: float | None = None
) -> int:
    """Publish ``messages`` from a source, serving housekeeping in between; stop on SIGINT/SIGTERM.

    Reliable sends block while a receiver is behind, for as long as it is connected, however
    slow: a replay loses nothing. At the end, waits under the same rule until every reliable
    message is acknowledged (``flush_timeout_s``: at most that long instead). Returns 1, with
    one error line, when a receiver is gone (the line names it and how many messages it did
    not acknowledge) or the bounded wait ran out; else 0. A signal stops it at once, also while
    it waits, and the log says how many messages were left unacknowledged.
    """
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, node.request_stop)
    sent = 0
    topics: set[str] = set()  # what this source published (not the node's own stats)
    ok = True
    try:
        for msg in messages:
            if node.stop_requested:
                break
            node.publish(msg, reliable=reliable)
            sent += 1
            topics.add(msg.topic)
            node.spin_once(0)
        if not node.stop_requested:
            ok = node.transport.flush(flush_timeout_s)
            if not ok:  # the bounded wait ran out, or latest-only messages found no room
                within = "" if flush_timeout_s is None else f" after {flush_timeout_s:g} s"
                logger.error("%s: messages still not delivered%s", node.name, within)
    except TransportInterrupted as exc:  # a signal while waiting for a receiver
        logger.warning("%s; stopping on a signal", exc)  # exc names the node, receiver, count
    except TransportError as exc:  # a receiver is gone: exc names it and what it did not ack
        logger.error("%s", exc)
        ok = False
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        node.transport.close()
    t = node.transport
    # every message not delivered is accounted for: superseded while parked, or still parked
    logger.info("%s: sent %d messages (%d superseded before they left, %d unsent at close)",
                node.name, sent, sum(t.dropped[k] for k in topics),
                sum(t.unsent_at_close[k] for k in topics))  # fmt: skip
    return 0 if ok else 1


def close_quietly(transport: Transport) -> None:
    try:
        transport.close()
    except Exception:  # closing after a failure must not hide the failure
        logger.debug("close failed", exc_info=True)


# --------------------------------------------------------------------------------------------
# A loop with work between messages (render requests: gsfix_online.runtime.requests)
# --------------------------------------------------------------------------------------------


def run_loop(node: Node, work: Callable[[], bool], label: str = "work") -> int:
    """Run ``node`` until SIGINT/SIGTERM or ``request_stop``, calling ``work()`` after each
    message or wait; ``work`` returns True while it has more to do (then the loop does not wait
    for messages); the node's timeline shows the calls that took time as ``label``. A node that ends on its own (``request_stop`` from a handler) first waits,
    under the rule of a blocked send, until its reliable messages are acknowledged: a reader
    that is restarting gets what it had not acknowledged (closing after the linger time lost
    it; benchmarks/results/fault_findings.md). A signal ends that wait at once. Closes the
    transport; returns 0."""
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, node.request_stop)
    busy = False
    try:
        while not node.stop_requested:
            node.spin_once(0 if busy else None)
            if not node.stop_requested:
                with node.span(label):
                    busy = work()
        try:
            node.transport.flush(None)
        except TransportInterrupted as exc:
            logger.warning("%s; stopping on a signal", exc)
        except TransportError as exc:  # a reader is gone: exc names it and what it lost
            logger.error("%s", exc)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        node.transport.close()
    return 0
