"""ZeroMQ transport: latest-only PUB/SUB and reliable DEALER -> ROUTER links.

Latest-only (``mode: latest``): XPUB (a PUB that can refuse instead of drop) with SNDHWM=1 and
XPUB_NODROP -> SUB with RCVHWM=1. Both ends keep only the newest message per topic:

- sender: a publish that finds the HWM=1 pipe full parks the message in a per-topic slot; a newer
  publish on that topic replaces it (counted in ``dropped``). Parked messages go out, oldest topic
  first, as soon as the pipe has room (on the next publish/recv, in ``flush_latest``, or within
  ``linger_s`` on close). So the newest message of a burst is never the one lost, which a plain
  PUB (it drops the *new* message at HWM) cannot promise.
- receiver: a background thread drains the SUB sockets as fast as messages arrive into a
  per-topic slot; ``recv`` hands slots out oldest-first (a busy topic cannot starve a quiet one);
  a message replaced before it was read is counted in ``dropped[topic]``.

A slow consumer therefore always gets the newest frame, and the sender is throttled only by the
slowest subscriber's drain thread, not its handler. ZMQ_CONFLATE is not used: it keeps only the
last *frame* of a multipart message. As with any PUB, messages published before a subscriber has
connected are not delivered to it.

Reliable (``mode: reliable``): DEALER -> ROUTER with the go-back-N protocol of
``reliable.py``: at most ``reliable_window`` unacked messages per link, in-order delivery, resend
after ``reliable_resend_s`` without progress. The receiver acknowledges messages once ``recv``
has returned them (cumulative acks, every half window or 20 ms, sent from the next ``recv`` call so
they stay off the latency path; a ``recv`` waiting for input sends a held-back one when it is due,
rounded up to 5 ms), so a slow consumer slows the sender down instead of losing data:
credit-based flow control (the sender holds at most the window, the receiver reliable_hwm
messages per socket). When the window is full, ``publish(..., reliable=True)`` blocks, and so
does ``flush()`` until every message is acknowledged: without a deadline while the receiver is
connected, however slow it is; a receiver that is not there (not connected yet, or gone) is
waited for up to ``reliable_connect_timeout_s`` / ``reliable_send_timeout_s``, then
:class:`TransportTimeout` names it and the message is NOT queued (the caller decides: retry, or
stop). The rule, the socket monitor and the heartbeats behind it are in ``liveness.py``; the
monitor is read only while a send is blocked or a resend is due. ``interrupt()`` (a signal
handler) makes a blocked wait raise :class:`TransportInterrupted`. A reliable output has exactly
one receiver; several senders may share one receiver. ``close()`` waits up to ``linger_s`` for
outstanding acks and logs a warning naming how many messages were still unacknowledged.

Sockets belong to this transport's thread except the SUB sockets, which only the drain thread
touches; it signals new data through an OS pipe so one ``zmq.Poller`` waits on all inputs.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import secrets
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import zmq

from gsfix_online.runtime.config import EndpointConfig, TransportConfig
from gsfix_online.runtime.liveness import MONITOR_EVENTS, PeerWatch, Wait
from gsfix_online.runtime.reliable import (
    ENVELOPE,
    ReceiveOrder,
    SendWindow,
    ack_frames,
    envelope_problem,
    parse_envelope,
    read_ack,
)
from gsfix_online.runtime.transport import Transport, TransportError, TransportInterrupted
from gsfix_online.runtime.wire import Message, WireError, encode, subscription_prefix

logger = logging.getLogger(__name__)

MAX_LATEST_TOPICS = 1024  # distinct topics buffered by a latest-only input before dropping
_ACK_WAIT_STEP_MS = 5  # a held-back ack goes out up to this much after it is due
_BLOCKED_WAIT_MS = 100  # a blocked send or flush looks at its receiver and signals this often
_NB, _NB_MORE = int(zmq.NOBLOCK), int(zmq.NOBLOCK | zmq.SNDMORE)  # plain ints: no enum math
# libzmq's send as pyzmq compiles it, without the Python wrapper that only adds routing_id and
# group (DRAFT sockets): a message is several frames, each one a call.
_send = zmq.backend.Socket.send
_EVENTS, _POLLIN, _RCVTIMEO = int(zmq.EVENTS), int(zmq.POLLIN), int(zmq.RCVTIMEO)


def _recv_within(
    sock: zmq.Socket,
    wait_ms: int,
    timeouts: dict[zmq.Socket, int] | None = None,
    routed: bool = False,
) -> list[zmq.Frame | bytes] | None:
    """The next multipart message, waiting up to ``wait_ms`` (0: only if one is queued).

    Waiting is a blocking receive with a timeout, not ``Socket.poll`` (which builds a Poller per
    call): one call into libzmq, with the GIL released, per message. ``timeouts`` remembers
    each socket's receive timeout, so a repeated wait sets no option (pyzmq builds an enum per
    option call). ``routed`` (a ROUTER socket): the first frame, the sender's routing id, comes
    as bytes (no Frame object to build and copy from); a ROUTER always has the sender's frames
    after it.
    """
    if wait_ms <= 0:
        if not sock.getsockopt(_EVENTS) & _POLLIN:  # cheaper than catching zmq.Again
            return None
        first = sock.recv(_NB, copy=routed)
    else:
        if timeouts is None or timeouts.get(sock) != wait_ms:
            sock.setsockopt(_RCVTIMEO, wait_ms)
            if timeouts is not None:
                timeouts[sock] = wait_ms
        try:
            first = sock.recv(0, copy=routed)
        except zmq.Again:
            return None
    # The other parts of a multipart message are already here (libzmq delivers it whole).
    # Frame.more instead of recv_multipart's getsockopt(RCVMORE) per part: this loop runs for
    # every frame of every message.
    parts: list[zmq.Frame | bytes] = [first]
    more = routed or first.more
    while more:
        frame = sock.recv(_NB, copy=False)
        parts.append(frame)
        more = frame.more
    return parts


def _send_nowait(sock: zmq.Socket, head: object, frames: list[object], start: int = 0) -> bool:
    """Send ``head`` and ``frames[start:]`` as one multipart message without blocking or
    copying; False if the HWM says wait.

    libzmq accepts or refuses a multipart message as a whole at its first frame.
    """
    last = len(frames) - 1
    try:
        _send(sock, head, _NB_MORE if last >= start else _NB, copy=False)
    except zmq.Again:
        return False
    for i in range(start, last):
        _send(sock, frames[i], _NB_MORE, copy=False)
    if last >= start:
        _send(sock, frames[last], _NB, copy=False)
    return True


class _LatestInbox:
    """Drains SUB sockets on a thread; keeps the newest message per topic.

    The main thread waits on ``wake_fd`` (an OS pipe, in the same ``zmq.Poller`` as its sockets).
    The drain thread writes one byte when the slots go from empty to non-empty; the main thread
    always looks at the slots before it waits, so that is the only moment a wake-up is needed.
    (An inproc PUSH/PULL pair would not do: a non-blocking send can report a full pipe that the
    reader has already emptied, libzmq processes that news lazily, and the wake-up is lost.)
    """

    def __init__(self, subs: list[zmq.Socket]) -> None:
        self._subs = subs
        self._slots: OrderedDict[bytes, list[zmq.Frame]] = OrderedDict()
        self._drops: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.wake_fd, self._wake_w = os.pipe()
        os.set_blocking(self.wake_fd, False)
        os.set_blocking(self._wake_w, False)
        self._thread = threading.Thread(target=self._run, name="gsfix-latest-drain", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        poller = zmq.Poller()
        for s in self._subs:
            poller.register(s, zmq.POLLIN)
        try:
            while not self._stop.is_set():
                ready = dict(poller.poll(50))
                for s in self._subs:
                    while s in ready and s.get(zmq.EVENTS) & zmq.POLLIN:
                        self._put(s.recv_multipart(_NB, copy=False))
        except zmq.ContextTerminated:
            pass
        finally:
            for s in self._subs:
                s.close(linger=0)

    def _put(self, frames: list[zmq.Frame]) -> None:
        key = bytes(frames[0].buffer)
        with self._lock:
            was_empty = not self._slots
            if key in self._slots:
                self._drops[key.rstrip(b"\0").decode("ascii", "replace")] += 1
                del self._slots[key]
            self._slots[key] = frames
            if len(self._slots) > MAX_LATEST_TOPICS:
                old, _ = self._slots.popitem(last=False)
                self._drops[old.rstrip(b"\0").decode("ascii", "replace")] += 1
            if was_empty:
                with contextlib.suppress(BlockingIOError):  # pipe full: wake-ups are pending
                    os.write(self._wake_w, b"\0")

    def pop(self) -> list[zmq.Frame] | None:
        with self._lock:
            return self._slots.popitem(last=False)[1] if self._slots else None

    def take_drops(self) -> Counter[str]:
        with self._lock:
            drops, self._drops = self._drops, Counter()
        return drops

    def __len__(self) -> int:
        return len(self._slots)

    def clear_wakes(self) -> None:
        with contextlib.suppress(BlockingIOError):
            while os.read(self.wake_fd, 4096):
                pass

    def close(self) -> bool:
        self._stop.set()
        self._thread.join(timeout=2.0)
        stopped = not self._thread.is_alive()
        if stopped:
            os.close(self._wake_w)
            os.close(self.wake_fd)
        return stopped


def _routes(prefixes: tuple[bytes, ...], topic_frame: bytes) -> bool:
    """Whether an output with these topic prefixes (empty: all) carries ``topic_frame``."""
    return not prefixes or any(topic_frame.startswith(p) for p in prefixes)


@dataclass
class _LatestOut:
    address: str
    sock: zmq.Socket  # XPUB, SNDHWM=1, XPUB_NODROP
    parked: OrderedDict[str, list[object]]  # topic -> newest frames not yet sent
    prefixes: tuple[bytes, ...] = ()  # routed topics (subscription prefixes); () = all


@dataclass
class _Link:
    address: str
    sock: zmq.Socket
    window: SendWindow
    watch: PeerWatch  # is the receiver there (socket monitor)
    prefixes: tuple[bytes, ...] = ()  # routed topics (subscription prefixes); () = all


class ZmqTransport(Transport):
    """A node's sockets, built from its :class:`TransportConfig`."""

    def __init__(self, config: TransportConfig, name: str = "node") -> None:
        super().__init__(config.subscriptions, config.max_message_bytes, config.log_period_s)
        self.config = config
        self.name = name
        self.input_addresses: list[str] = []  # actual addresses (a bound tcp://...:* resolved)
        self.output_addresses: list[str] = []
        self._linger_ms = int(config.linger_s * 1000)
        self._ctx = zmq.Context(io_threads=1)
        self._own: list[zmq.Socket] = []  # sockets of this thread, closed by close()
        self._outs: list[_LatestOut] = []
        self._links: list[_Link] = []
        self._routers: list[zmq.Socket] = []
        self._peer_router: dict[bytes, zmq.Socket] = {}
        self._acks_due: dict[bytes, int] = {}  # sender -> cumulative ack to send next
        self._reliable_routes: dict[bytes, list[_Link]] = {}  # topic frame -> its links
        self._match_all = b"" in self._prefixes  # subscribed to every topic
        self._rcvtimeo: dict[zmq.Socket, int] = {}  # receive timeout set on each socket, ms
        self._order = ReceiveOrder()
        self._interrupted = False  # set by interrupt(): blocked reliable waits give up
        self._monitors: list[zmq.Socket] = []  # PAIR sockets of the links' socket monitors
        self._inbox: _LatestInbox | None = None
        self._subs: list[zmq.Socket] = []  # handed to the drain thread once set up
        try:
            self._setup()
        except BaseException:
            self._teardown()
            raise
        self._poller = zmq.Poller()
        for s in [*self._routers, *(lk.sock for lk in self._links)]:
            self._poller.register(s, zmq.POLLIN)
        if self._inbox is not None:
            self._poller.register(self._inbox.wake_fd, zmq.POLLIN)
        self._sources: list[Callable[[], Sequence[object] | None]] = []
        if self._inbox is not None:
            self._sources.append(self._inbox.pop)
        self._sources += [lambda r=r: self._take_reliable(r) for r in self._routers]
        self._rr = 0
        # A node whose only socket is one reliable input (a recorder, a sink) blocks on it.
        # (An inbox counts even while empty: it has a __len__, so test it against None.)
        only_router = len(self._routers) == 1 and not (self._links or self._outs)
        only_router = only_router and self._inbox is None
        self._solo = self._routers[0] if only_router else None

    # ----------------------------------------------------------------------------------------
    # Setup and teardown
    # ----------------------------------------------------------------------------------------

    def _socket(
        self,
        kind: int,
        ep: EndpointConfig,
        hwm: int,
        options: dict[int, int | bytes] | None = None,
        monitor: bool = False,
    ) -> tuple[zmq.Socket, str]:
        """A socket bound or connected at ``ep``; with ``monitor``, its monitor's PAIR socket
        (set up before connecting, so no event is missed) is appended to ``_monitors``."""
        try:
            ep.validate()
        except ValueError as exc:
            raise TransportError(f"{self.name}: {exc}") from None
        s = self._ctx.socket(kind)
        s.set_hwm(hwm)
        s.setsockopt(zmq.LINGER, self._linger_ms)
        for opt, value in (options or {}).items():
            s.setsockopt(opt, value)
        if monitor:
            self._monitors.append(s.get_monitor_socket(MONITOR_EVENTS))
        try:
            if ep.bind:
                if ep.address.startswith("ipc://"):
                    Path(ep.address[len("ipc://") :]).parent.mkdir(parents=True, exist_ok=True)
                s.bind(ep.address)
                actual = s.getsockopt_string(zmq.LAST_ENDPOINT)
            else:
                s.connect(ep.address)
                actual = ep.address
        except zmq.ZMQError as exc:
            s.close(linger=0)
            verb = "bind" if ep.bind else "connect"
            raise TransportError(f"{self.name}: cannot {verb} {ep.address}: {exc}") from None
        return s, actual

    def _setup(self) -> None:
        cfg = self.config
        subs = self._subs
        for ep in cfg.inputs:
            if ep.mode == "latest":
                s, addr = self._socket(zmq.SUB, ep, 1)
                for prefix in self._prefixes:
                    s.setsockopt(zmq.SUBSCRIBE, prefix)
                subs.append(s)
            else:
                s, addr = self._socket(zmq.ROUTER, ep, cfg.reliable_hwm)
                self._own.append(s)
                self._routers.append(s)
            self.input_addresses.append(addr)
        for ep in cfg.outputs:
            prefixes = tuple(subscription_prefix(t) for t in ep.topics)
            if ep.mode == "latest":
                s, addr = self._socket(zmq.XPUB, ep, 1, {zmq.XPUB_NODROP: 1})
                self._outs.append(_LatestOut(addr, s, OrderedDict(), prefixes))
            else:
                routing_id = f"{self.name}-{os.getpid()}-{secrets.token_hex(4)}".encode()
                # ROUTING_ID: the receiver keeps link state per sender. IMMEDIATE stays 0: with
                # IMMEDIATE=1 libzmq discards acks already received but not yet read when the
                # receiver disconnects (the pipe is terminated without delay), so a receiver that
                # acks and leaves would look like one that never acked.
                options: dict[int, int | bytes] = {zmq.ROUTING_ID: routing_id}
                if cfg.heartbeat_s > 0:  # answered by the receiver's I/O thread (liveness.py)
                    options[zmq.HEARTBEAT_IVL] = max(1, int(1000 * cfg.heartbeat_s))
                    options[zmq.HEARTBEAT_TIMEOUT] = max(1, int(1000 * cfg.heartbeat_timeout_s))
                s, addr = self._socket(zmq.DEALER, ep, cfg.reliable_hwm, options, monitor=True)
                watch = PeerWatch(
                    self._monitors[-1],
                    self.name,
                    addr,
                    ep.peer,
                    ep.name,
                    cfg.reliable_connect_timeout_s,
                    cfg.reliable_send_timeout_s,
                    time.monotonic(),
                )
                window = SendWindow(cfg.reliable_window, cfg.reliable_resend_s)
                # Resend only after a disconnect: a connected receiver has what was sent, and
                # copies would fill its pipe while it is busy (then it answers no heartbeats).
                window.may_resend = watch.take_dropped
                self._links.append(_Link(addr, s, window, watch, prefixes))
            self._own.append(s)
            self.output_addresses.append(addr)
        if subs:
            self._inbox = _LatestInbox(subs)

    def _teardown(self) -> None:
        for link in self._links:
            with contextlib.suppress(zmq.ZMQError):
                link.sock.disable_monitor()
        for m in self._monitors:
            m.close(linger=0)
        if self._inbox is not None:
            stopped = self._inbox.close()  # closes the SUB sockets on its thread
        else:
            stopped = True
            for s in self._subs:
                s.close(linger=0)
        for s in self._own:
            s.close(linger=self._linger_ms)
        if stopped:
            self._ctx.term()
        else:
            logger.error(
                "%s: SUB drain thread did not stop; leaving the zmq context open", self.name
            )

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        # 1. Give outstanding reliable messages and batched acks the linger time
        deadline = time.monotonic() + self.config.linger_s
        for link in self._links:
            while link.window.pending and time.monotonic() < deadline:
                self._pump(link)
                link.sock.poll(10, zmq.POLLIN)
            if link.window.pending:
                logger.warning(
                    "%s: closing reliable output %s with %d unacknowledged messages (lost)",
                    self.name,
                    link.address,
                    len(link.window.pending),
                )
        self._flush_acks(force=True)
        if not self.flush_latest(max(0.0, deadline - time.monotonic())):
            n = sum(len(out.parked) for out in self._outs)
            self.unsent_at_close.update(t for out in self._outs for t in out.parked)
            logger.info("%s: closing with %d latest-only messages unsent", self.name, n)
        # 2. Stop the drain thread, close sockets within their linger, end the context
        self._teardown()

    # ----------------------------------------------------------------------------------------
    # Publishing
    # ----------------------------------------------------------------------------------------

    def publish(self, msg: Message, reliable: bool = False) -> None:
        if self.closed:
            raise TransportError(f"{self.name}: publish on a closed transport")
        frames = encode(msg, sent_mono_ns=time.monotonic_ns())
        topic_frame: bytes = frames[0]  # type: ignore[assignment]
        if reliable:
            links = self._reliable_routes.get(topic_frame)
            if links is None:
                links = [lk for lk in self._links if _routes(lk.prefixes, topic_frame)]
                if len(self._reliable_routes) < MAX_LATEST_TOPICS:
                    self._reliable_routes[topic_frame] = links
            if not links:
                raise TransportError(f"{self.name}: no reliable output configured for {msg.topic}")
            for link in links:
                self._send_reliable(link, frames)
        else:
            if not self._outs:
                raise TransportError(
                    f"{self.name}: no latest-only output configured for {msg.topic}"
                )
            for out in self._outs:
                if not _routes(out.prefixes, topic_frame):
                    continue  # routed elsewhere (an unrouted topic goes nowhere, like a PUB)
                if out.parked.pop(msg.topic, None) is not None:
                    self.dropped[msg.topic] += 1  # superseded before the pipe had room
                out.parked[msg.topic] = frames
                self._send_parked(out)

    def _send_parked(self, out: _LatestOut) -> None:
        while out.sock.get(zmq.EVENTS) & zmq.POLLIN:  # (un)subscription notices: never let
            out.sock.recv(zmq.NOBLOCK)  # them pile up
        while out.parked:
            topic, frames = next(iter(out.parked.items()))
            if not _send_nowait(out.sock, frames[0], frames, 1):
                return  # pipe full (HWM=1): stays parked, newest per topic
            del out.parked[topic]

    def flush_latest(self, timeout_s: float) -> bool:
        """Wait until no latest-only message is parked; False if some still are."""
        deadline = time.monotonic() + timeout_s
        while True:
            for out in self._outs:
                self._send_parked(out)
            if not any(out.parked for out in self._outs):
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.001)

    def _send_reliable(self, link: _Link, frames: list[object]) -> None:
        window = link.window
        # Fast path (a stream that keeps up): send now; acks are read when the window fills,
        # and by every recv() of the node loop, which also runs the resend timer.
        now = time.monotonic()
        pushed = window.push(frames, now)
        if pushed is not None:  # the envelope goes in front of the topic, in its frame
            if _send_nowait(link.sock, pushed[1] + frames[0], frames, 1):  # type: ignore[operator]
                window.mark_sent(pushed[0], now)
            return
        # Window full: wait for an ack (the blocking receive returns at once if one is queued).
        # A wait that ends without one looks at the receiver: no deadline while it is connected.
        wait = None  # made on the first wait without an ack: a stream that keeps up never does
        while window.full:
            self._pump(link, _BLOCKED_WAIT_MS, drain=False)
            if window.full:
                wait = wait or Wait("send", now)
                self._check_blocked(link, wait)
        window.add(frames, time.monotonic())
        self._send_due(link)

    def _check_blocked(self, link: _Link, wait: Wait) -> None:
        """Between the waits of a blocked send or flush: raise if interrupted or if the receiver
        has been absent too long; log what it waits for when due."""
        if self._interrupted:
            raise TransportInterrupted(
                f"{self.name}: reliable {wait.what} to {link.watch.label} interrupted after "
                f"{time.monotonic() - wait.started:.1f} s; {len(link.window.pending)} messages "
                "unacknowledged"
            )
        link.watch.check(wait, len(link.window.pending), time.monotonic())

    def interrupt(self) -> None:
        self._interrupted = True

    def _pump(self, link: _Link, wait_ms: int = 0, drain: bool = True) -> None:
        """Read acks (waiting up to ``wait_ms`` for the first; all queued ones with ``drain``,
        else one: they are cumulative, the rest are read by the next pump), then send what is
        due (new messages, or everything after a stall)."""
        while True:
            parts = _recv_within(link.sock, wait_ms, self._rcvtimeo)
            if parts is None:
                break
            wait_ms = 0
            try:
                ack_seq = read_ack(parts, self.max_message_bytes)
            except WireError as exc:
                self._reject(exc.reason, f"from {link.address}: {exc}")
                continue
            link.window.on_ack(ack_seq, time.monotonic())
            if not drain:
                break
        self._send_due(link)

    def _send_due(self, link: _Link) -> None:
        now = time.monotonic()
        for p in link.window.to_send(now):
            head = link.window.envelope(p) + p.frames[0]  # type: ignore[operator]
            if not _send_nowait(link.sock, head, p.frames, 1):
                break  # HWM reached: retried on the next pump, in order
            link.window.mark_sent(p, now)

    def flush(self, timeout_s: float | None = None) -> bool:
        """Wait until every reliable message is acknowledged and no latest-only message is
        parked; False if that did not happen within ``timeout_s`` (or on ``interrupt()``).

        ``None``: the rule of a blocked send (``liveness.py``): no deadline while a receiver
        is connected, :class:`TransportTimeout` naming one that is gone,
        :class:`TransportInterrupted` after ``interrupt()``. Parked latest-only messages then
        get ``linger_s`` (a latest-only output may drop by design).
        """
        start = time.monotonic()
        deadline = math.inf if timeout_s is None else start + timeout_s
        step_s = _BLOCKED_WAIT_MS / 1000
        for link in self._links:
            wait = Wait("flush", start)
            while link.window.pending:
                self._pump(link)
                if not link.window.pending:
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0 or (timeout_s is not None and self._interrupted):
                    return False
                acked = link.sock.poll(max(1, int(1000 * min(remaining, step_s))), zmq.POLLIN)
                if not acked and timeout_s is None:  # a wait without an ack: look at the receiver
                    self._check_blocked(link, wait)
        latest_s = self.config.linger_s if timeout_s is None else deadline - time.monotonic()
        return self.flush_latest(max(0.0, latest_s))

    # ----------------------------------------------------------------------------------------
    # Receiving
    # ----------------------------------------------------------------------------------------

    def recv(self, timeout_ms: int = 0) -> Message | None:
        if self.closed:
            raise TransportError(f"{self.name}: recv on a closed transport")
        if self._solo is not None:
            return self._recv_solo(self._solo, timeout_ms)
        deadline = time.monotonic() + timeout_ms / 1000
        while True:
            self._service()
            frames = self._next_frames()
            if frames is None:
                remaining_ms = 1000 * (deadline - time.monotonic())
                if remaining_ms <= 0:
                    return None
                if any(out.parked for out in self._outs):
                    remaining_ms = min(remaining_ms, 2.0)  # parked latest-only: retry soon
                elif any(lk.window.pending for lk in self._links):
                    remaining_ms = min(remaining_ms, 20.0)  # keep resend timers moving
                remaining_ms = min(remaining_ms, self._ms_until_ack_due())
                self._poller.poll(max(1, int(remaining_ms)))
                if self._inbox is not None:
                    self._inbox.clear_wakes()
                continue
            msg = self._decode(frames)
            if msg is not None:
                return msg

    def _recv_solo(self, router: zmq.Socket, timeout_ms: int) -> Message | None:
        """``recv`` of a node whose only socket is one reliable input (a recorder, a sink): one
        blocking receive on it per message, which returns at once if one is queued."""
        deadline = time.monotonic() + timeout_ms / 1000
        while True:
            now = time.monotonic()
            if self._acks_due or now >= self._order.due_at:
                self._flush_acks()
            remaining_ms = 1000 * (deadline - now)
            if remaining_ms <= 0:
                wait_ms = 0
            else:  # a batched ack held back goes out when due, not at the end of the wait
                wait_ms = max(1, int(min(remaining_ms, self._ms_until_ack_due())))
            frames = self._take_reliable(router, wait_ms)
            if frames is not None:
                msg = self._decode(frames)
                if msg is not None:
                    return msg
            elif remaining_ms <= 0:
                return None

    def _ms_until_ack_due(self) -> float:
        """How long an input wait may last before a batched ack is due (inf: none is held
        back): rounded up to a multiple of _ACK_WAIT_STEP_MS, so the wait ends after the due
        time, not just before it, and a stream's waits repeat a few values (a receive timeout
        that changes costs a setsockopt)."""
        due_at = self._order.due_at
        if due_at == math.inf:
            return due_at
        steps = math.ceil(1000 * (due_at - time.monotonic()) / _ACK_WAIT_STEP_MS)
        return _ACK_WAIT_STEP_MS * max(1, steps)

    def _service(self) -> None:
        if self._outs:
            for out in self._outs:
                if out.parked:
                    self._send_parked(out)
        if self._links:
            for link in self._links:
                self._pump(link)
        if self._acks_due or time.monotonic() >= self._order.due_at:
            self._flush_acks()
        if self._inbox is not None:
            self.dropped.update(self._inbox.take_drops())

    def _next_frames(self) -> Sequence[object] | None:
        n = len(self._sources)
        for i in range(n):
            k = (self._rr + i) % n
            frames = self._sources[k]()
            if frames is not None:
                self._rr = (k + 1) % n
                return frames
        return None

    def _take_reliable(self, router: zmq.Socket, wait_ms: int = 0) -> list[object] | None:
        """The next deliverable message on ``router`` (waiting up to ``wait_ms`` for the first
        one), acknowledging as it goes; None if there is none.

        A message comes as ``[routing id, envelope + topic, header, arrays...]``; any message
        with a valid envelope takes its place in the link's order (so a malformed one cannot
        stall the link), and what is delivered is ``[topic, header, arrays...]`` for decode.
        """
        while (parts := _recv_within(router, wait_ms, self._rcvtimeo, routed=True)) is not None:
            wait_ms = 0
            head: bytes = parts[1].bytes  # type: ignore[union-attr]
            env = parse_envelope(head)
            if env is None:
                self._reject("envelope", envelope_problem(head))
                continue
            sender: bytes = parts[0]  # type: ignore[assignment]
            self._peer_router[sender] = router
            verdict, ack = self._order.receive(sender, *env, time.monotonic())
            if ack is not None:
                if verdict == "deliver":
                    self._acks_due[sender] = ack  # sent by the next recv: off the latency path
                else:
                    self._send_ack(router, sender, ack)
            if verdict == "deliver":
                topic = head[ENVELOPE.size :]
                if self._match_all or self.matches_raw(topic):
                    frames: list[object] = parts  # type: ignore[assignment]
                    del frames[0]  # the routing id
                    frames[0] = topic
                    return frames
        return None

    def _send_ack(self, router: zmq.Socket, sender: bytes, ack_seq: int) -> None:
        # Peer gone or full: acks are cumulative, the next one covers this one.
        with contextlib.suppress(zmq.ZMQError):
            _send_nowait(router, sender, ack_frames(ack_seq))

    def _flush_acks(self, force: bool = False) -> None:
        due, self._acks_due = self._acks_due, {}
        due.update(self._order.deferred_acks(time.monotonic(), force))
        for sender, ack_seq in due.items():
            self._send_ack(self._peer_router[sender], sender, ack_seq)

    @property
    def publishes_latest(self) -> bool:
        return bool(self._outs)

    def queue_depth(self) -> int:
        return len(self._inbox) if self._inbox is not None else 0

    def stats(self) -> dict[str, float]:
        out: dict[str, float] = {}
        for lo in self._outs:
            out[f"latest_parked/{lo.address}"] = len(lo.parked)
        now = time.monotonic()
        for link in self._links:
            out[f"reliable_unacked/{link.address}"] = len(link.window.pending)
            out[f"reliable_resends/{link.address}"] = link.window.resends
            out[f"reliable_connected/{link.address}"] = float(link.watch.poll(now) == "up")
        if self._routers:
            out["reliable_duplicates"] = self._order.duplicates
            out["reliable_gaps"] = self._order.gaps
        return out
