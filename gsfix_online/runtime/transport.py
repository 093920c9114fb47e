"""The Transport interface every node talks to, and its in-memory test double.

A transport publishes :class:`~gsfix_online.runtime.wire.Message` objects and returns decoded
ones from ``recv``. Malformed input never reaches the node: it is counted per reason in
``rejected``, logged at most once per reason per period, and ``recv`` moves on to the next
message. ``ZmqTransport`` (``zmq_transport.py``) is the real one; :class:`InMemoryTransport` replays
scripted messages (or raw, possibly malformed, frame lists) and captures what is published, with
no threads and no sockets, like dora-rs' ``MockNode``.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections import Counter, deque
from collections.abc import Iterable, Sequence
from typing import NamedTuple

from gsfix_online.runtime.ratelog import RateLimitedLog
from gsfix_online.runtime.wire import (
    DEFAULT_MAX_MESSAGE_BYTES,
    Message,
    WireError,
    decode,
    encode,
    subscription_prefix,
    topic_matches,
)

logger = logging.getLogger(__name__)


class TransportError(RuntimeError):
    """A socket could not be set up, or a message cannot be sent."""


class TransportTimeout(TransportError):
    """A reliable send or flush gave up on a receiver that was absent too long (not connected
    yet, or gone); the message it was sending was not queued, nothing else was dropped."""


class TransportInterrupted(TransportError):
    """A reliable send or flush that waited for acknowledgements was stopped by ``interrupt()``
    (SIGINT/SIGTERM); the message names how many were still unacknowledged."""


class Transport(ABC):
    """Publish/receive messages on topics; subscriptions are fixed at construction.

    Subscriptions: ``"rgbd/cam0"`` is that topic only, ``"rgbd/"`` every topic under ``rgbd/``,
    ``""`` everything. Counters, all cumulative: ``received[topic]`` (delivered to the caller),
    ``dropped[topic]`` (superseded before being read, latest-only delivery) and
    ``rejected[reason]`` (malformed input, reasons from ``wire.REASONS`` plus ``"envelope"``);
    ``unsent_at_close[topic]``: latest-only messages still parked when ``close`` gave up on them.
    """

    def __init__(
        self,
        subscriptions: Sequence[str] = ("",),
        max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
        log_period_s: float = 10.0,
    ) -> None:
        if isinstance(subscriptions, str):
            raise TypeError("subscriptions must be a list of topics, not one string")
        self.subscriptions = tuple(subscriptions)
        self._prefixes = tuple(subscription_prefix(s) for s in self.subscriptions)
        self.max_message_bytes = max_message_bytes
        self.received: Counter[str] = Counter()
        self.dropped: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self.unsent_at_close: Counter[str] = Counter()
        self.closed = False
        self._log = RateLimitedLog(logger, log_period_s)

    @abstractmethod
    def publish(self, msg: Message, reliable: bool = False) -> None:
        """Send ``msg``; ``reliable`` selects no-loss delivery (blocks while the receiver is
        behind; raises :class:`TransportTimeout` if it is gone, :class:`TransportInterrupted`
        after ``interrupt()``).

        The arrays are handed over without a copy: do not modify them after publishing.
        """

    @abstractmethod
    def recv(self, timeout_ms: int = 0) -> Message | None:
        """Next valid message on a subscribed topic, or None after ``timeout_ms``."""

    @abstractmethod
    def close(self) -> None:
        """Flush what can be flushed within the linger time and release sockets."""

    def flush(self, timeout_s: float | None = None) -> bool:
        """Wait until everything published has gone out (reliable: acknowledged); False if that
        did not happen within ``timeout_s``. ``None``: no deadline while the receivers are
        there; raises :class:`TransportTimeout` naming one that is gone."""
        return True

    def interrupt(self) -> None:
        """Make a reliable send or flush that is waiting for acknowledgements, now or later,
        raise :class:`TransportInterrupted` (for SIGINT/SIGTERM handlers; only sets a flag)."""
        return  # this one never waits for acknowledgements

    @property
    def publishes_latest(self) -> bool:
        """Whether latest-only publications (heartbeats, stats) have somewhere to go."""
        return True

    def queue_depth(self) -> int:
        """Messages received but not yet returned by ``recv`` (as far as the transport knows)."""
        return 0

    def stats(self) -> dict[str, float]:
        """Transport-specific counters for the node's ``stats`` message."""
        return {}

    def matches(self, topic: str) -> bool:
        return any(topic_matches(s, topic) for s in self.subscriptions)

    def matches_raw(self, topic_frame: bytes) -> bool:
        """The SUB filter rule on the raw topic frame."""
        return any(topic_frame.startswith(p) for p in self._prefixes)

    def _reject(self, reason: str, detail: str) -> None:
        self.rejected[reason] += 1
        self._log.warning(reason, f"rejected message ({detail})")

    def _decode(self, frames: Sequence[object]) -> Message | None:
        """Decode, or count and log the rejection and return None."""
        try:
            msg = decode(frames, self.max_message_bytes)
        except WireError as exc:
            self._reject(exc.reason, str(exc))
            return None
        self.received[msg.topic] += 1
        return msg

    def __enter__(self) -> Transport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Published(NamedTuple):
    message: Message  # decoded back from the wire frames, as a receiver would see it
    reliable: bool


class InMemoryTransport(Transport):
    """Scripted input, captured output; every message goes through encode/decode.

    ``feed(msg)`` queues a Message (encoded first) and ``feed(frames)`` a raw frame list, as if it
    had arrived on a subscribed socket. ``recv`` never waits: it returns None once the script is
    used up. ``outbox`` holds what was published; ``published`` just the messages.
    """

    def __init__(
        self,
        subscriptions: Sequence[str] = ("",),
        script: Iterable[Message | Sequence[object]] = (),
        max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
        log_period_s: float = 10.0,
        bus: InMemoryBus | None = None,
    ) -> None:
        super().__init__(subscriptions, max_message_bytes, log_period_s)
        self.inbox: deque[Sequence[object]] = deque()
        self.outbox: list[Published] = []
        self._bus = bus
        for item in script:
            self.feed(item)

    @property
    def published(self) -> list[Message]:
        return [p.message for p in self.outbox]

    def feed(self, item: Message | Sequence[object]) -> None:
        self.inbox.append(encode(item) if isinstance(item, Message) else item)

    def publish(self, msg: Message, reliable: bool = False) -> None:
        if self.closed:
            raise TransportError("publish on a closed transport")
        frames = encode(msg)
        self.outbox.append(Published(decode(frames, self.max_message_bytes), reliable))
        if self._bus is not None:
            self._bus.deliver(self, frames)

    def recv(self, timeout_ms: int = 0) -> Message | None:
        while self.inbox and not self.closed:
            msg = self._decode(self.inbox.popleft())
            if msg is not None:
                return msg
        return None

    def queue_depth(self) -> int:
        return len(self.inbox)

    def close(self) -> None:
        self.closed = True


class InMemoryBus:
    """Connects in-memory transports: a publish reaches every other member subscribed to it."""

    def __init__(self, max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> None:
        self.max_message_bytes = max_message_bytes
        self.members: list[InMemoryTransport] = []

    def transport(self, subscriptions: Sequence[str] = ("",)) -> InMemoryTransport:
        t = InMemoryTransport(subscriptions, max_message_bytes=self.max_message_bytes, bus=self)
        self.members.append(t)
        return t

    def deliver(self, sender: InMemoryTransport, frames: Sequence[object]) -> None:
        topic_frame = bytes(frames[0])  # type: ignore[arg-type]
        for t in self.members:
            if t is not sender and not t.closed and t.matches_raw(topic_frame):
                t.inbox.append(frames)
