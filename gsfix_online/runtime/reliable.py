"""Go-back-N bookkeeping for reliable links: sequence numbers, acks, resends. No sockets, no clock.

A reliable link is DEALER (senders) -> ROUTER (one receiver). Each data message travels as
``[envelope + topic, header, arrays...]``: the wire format's frames (``wire.py``) with the 24-byte
envelope :data:`ENVELOPE` in front of the topic frame, in the same frame (one frame fewer to
send and receive per message): magic ``b"GSR2"``, ``link_seq`` (1, 2, ... per sender), ``base``
(the sender's oldest unacked ``link_seq``) and ``window`` (its window size). The magic is the
link protocol's version: the first version (``b"GSR1"``) sent the envelope as a frame of its own;
a receiver rejects such messages (reason ``envelope``, naming the old version) rather than
guess. The receiver delivers ``link_seq`` strictly in
order, drops duplicates and anything after a gap, and answers with ``ack`` messages carrying the
highest ``link_seq`` delivered (cumulative). The sender keeps at most ``window`` unacked messages
(credit-based flow control: a slow consumer slows the sender, nothing is dropped) and resends all
of them, oldest first, when no ack has made progress for ``resend_s`` (doubling, up to 8x, while
the receiver stays silent, so a long outage does not flood the link with copies), unless its
``may_resend`` says nothing can have been lost (the transport: the receiver stayed connected).

``base`` lets a receiver that restarts (empty state) start at the right place: it expects
``base`` first, so unacked messages lost with the old receiver are resent, not skipped.

Acks are ordinary ``ack`` messages on topic ``_ack``. The receiver builds them from a template
(:func:`ack_frames`: the encoder's own bytes with ``ack_seq`` spliced in) and the sender reads
them with :func:`read_ack`, which recognises exactly those bytes and hands anything else to the
full ``wire.decode``.
"""

from __future__ import annotations

import itertools
import math
import struct
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import msgpack

from gsfix_online.runtime.schema import INT64_MAX, WireError
from gsfix_online.runtime.wire import Message, decode, encode

ENVELOPE = struct.Struct("<4sQQI")  # magic, link_seq, base, window
MAGIC = b"GSR2"  # envelope in front of the topic frame
MAGIC_V1 = b"GSR1"  # the first version: the envelope was a frame of its own

Verdict = Literal["deliver", "duplicate", "gap"]


@dataclass(slots=True)
class Pending:
    link_seq: int
    frames: list[object]  # topic, header, arrays (not copied)
    sent_at: float | None = None  # None = not yet (re)sent


class SendWindow:
    """Sender side of one link."""

    def __init__(self, window: int, resend_s: float) -> None:
        assert window >= 1 and resend_s > 0
        self.window = window
        self.resend_s = resend_s
        self.pending: deque[Pending] = deque()
        self.next_seq = 1
        self.acked = 0  # highest link_seq acknowledged
        self.resends = 0  # messages sent more than once
        self._progress_at = 0.0
        self._sent = 0  # pending[:_sent] have been sent (always a prefix)
        self._backoff = 1  # doubles after each resend without progress (receiver gone), max 8
        # Asked when the resend timer fires: False restarts the timer instead (the messages are
        # still on their way). None: always resend.
        self.may_resend: Callable[[], bool] | None = None

    @property
    def full(self) -> bool:
        return len(self.pending) >= self.window

    @property
    def all_sent(self) -> bool:
        """Every pending message has been sent at least once (none waits behind the HWM)."""
        return self._sent == len(self.pending)

    @property
    def base(self) -> int:
        return self.pending[0].link_seq if self.pending else self.next_seq

    def add(self, frames: list[object], now: float) -> Pending:
        assert not self.full
        if not self.pending:
            self._progress_at = now
        p = Pending(self.next_seq, frames)
        self.next_seq += 1
        self.pending.append(p)
        return p

    def push(self, frames: list[object], now: float) -> tuple[Pending, bytes] | None:
        """The fast path of a stream that keeps up: if the window has room and every pending
        message has been sent, add ``frames`` and return it with its envelope (send it, then
        ``mark_sent``); else None (``add`` once there is room, and send through ``to_send``)."""
        pending = self.pending
        n = len(pending)
        if n >= self.window or self._sent != n:
            return None
        if not n:
            self._progress_at = now
        seq = self.next_seq
        p = Pending(seq, frames)
        self.next_seq = seq + 1
        pending.append(p)
        return p, ENVELOPE.pack(MAGIC, seq, pending[0].link_seq, self.window)

    def envelope(self, p: Pending) -> bytes:
        return ENVELOPE.pack(MAGIC, p.link_seq, self.base, self.window)

    def on_ack(self, ack_seq: int, now: float) -> int:
        """Drop every pending message <= ``ack_seq``; returns how many were freed."""
        freed = 0
        while self.pending and self.pending[0].link_seq <= ack_seq:
            self.pending.popleft()
            freed += 1
        self._sent = max(0, self._sent - freed)
        if ack_seq > self.acked:
            self.acked = min(ack_seq, self.next_seq - 1)
        if freed:
            self._progress_at = now
            self._backoff = 1
        return freed

    def to_send(self, now: float) -> list[Pending]:
        """Messages to (re)send now, oldest first; call ``mark_sent`` for each one sent.

        Sent messages always form a prefix of ``pending``, so the receiver sees them in order.
        """
        if self._sent:
            stalled_since = max(self._progress_at, self.pending[0].sent_at or 0.0)
            if now - stalled_since < self.resend_s * self._backoff:
                pass
            elif self.may_resend is not None and not self.may_resend():
                self._progress_at = now  # still on their way: ask again after the same interval
            else:
                for p in itertools.islice(self.pending, self._sent):
                    p.sent_at = None
                self.resends += self._sent
                self._sent = 0
                self._progress_at = now
                self._backoff = min(8, 2 * self._backoff)
        if self._sent == len(self.pending):
            return []
        return list(itertools.islice(self.pending, self._sent, None))

    def mark_sent(self, p: Pending, now: float) -> None:
        assert p is self.pending[self._sent], "send in order"
        p.sent_at = now
        self._sent += 1


def parse_envelope(head: bytes) -> tuple[int, int, int] | None:
    """(link_seq, base, window) of a data message's first frame (the envelope, then the topic
    frame: at least one more byte), or None if it does not start with a valid envelope."""
    if len(head) <= ENVELOPE.size:
        return None
    magic, link_seq, base, window = ENVELOPE.unpack_from(head)
    if magic != MAGIC or link_seq < 1 or not 1 <= base <= link_seq or window < 1:
        return None
    return link_seq, base, window


def envelope_problem(head: bytes) -> str:
    """Why ``head`` (a data message's first frame) has no valid envelope, in one line."""
    if len(head) == ENVELOPE.size and head.startswith(MAGIC_V1):
        return (
            f"reliable envelope {MAGIC_V1.decode()} from an older sender; this receiver reads "
            f"{MAGIC.decode()} (envelope and topic in one frame)"
        )
    return "reliable message without a valid envelope"


@dataclass(slots=True)
class _Peer:
    expected: int
    since_ack: int = 0
    acked_at: float = 0.0


class ReceiveOrder:
    """Receiver side: per-sender next expected ``link_seq`` and when to acknowledge."""

    def __init__(self, ack_interval_s: float = 0.02) -> None:
        self.ack_interval_s = ack_interval_s
        self.peers: dict[bytes, _Peer] = {}
        self.duplicates = 0
        self.gaps = 0
        self.due_at = math.inf  # when the earliest held-back ack is due (inf: none is held)

    def receive(
        self, sender: bytes, link_seq: int, base: int, window: int, now: float
    ) -> tuple[Verdict, int | None]:
        """Classify one message and say which cumulative ack to send now (None: held back).

        In order -> ``deliver``; already delivered -> ``duplicate``; after a missing one ->
        ``gap`` (dropped: the sender resends from the gap). Deliveries are acknowledged every
        ``window // 2`` messages or ``ack_interval_s``, whichever comes first, so a fast stream
        costs the sender one wake-up per half window, not one per message; held-back acks come
        from :meth:`deferred_acks`. Duplicates and gaps are answered at once.
        """
        peer = self.peers.get(sender)
        if peer is None:
            peer = self.peers[sender] = _Peer(expected=base)
        elif base > peer.expected:  # cannot happen unless the receiver's state was lost
            peer.expected = base
        if link_seq == peer.expected:
            verdict: Verdict = "deliver"
            peer.expected = link_seq + 1
            peer.since_ack += 1
            if peer.since_ack < max(1, window // 2):
                due = peer.acked_at + self.ack_interval_s
                if now < due:
                    if due < self.due_at:
                        self.due_at = due
                    return verdict, None
        elif link_seq < peer.expected:
            self.duplicates += 1
            verdict = "duplicate"
        else:
            self.gaps += 1
            verdict = "gap"
        peer.since_ack = 0
        peer.acked_at = now
        return verdict, peer.expected - 1

    @property
    def has_deferred(self) -> bool:
        return self.due_at != math.inf

    def deferred_acks(self, now: float, force: bool = False) -> list[tuple[bytes, int]]:
        """Acks held back by batching that are now due (all of them with ``force``)."""
        due = []
        self.due_at = math.inf
        for sender, peer in self.peers.items():
            if not peer.since_ack:
                continue
            if force or now >= peer.acked_at + self.ack_interval_s:
                peer.since_ack = 0
                peer.acked_at = now
                due.append((sender, peer.expected - 1))
            else:
                self.due_at = min(self.due_at, peer.acked_at + self.ack_interval_s)
        return due


# --------------------------------------------------------------------------------------------
# Acks on the wire
# --------------------------------------------------------------------------------------------

ACK_TOPIC = "_ack"


def _ack_template() -> tuple[bytes, bytes, bytes]:
    """The topic frame, and the header bytes before and after ``ack_seq``, as ``encode`` makes
    them (so the template cannot drift from the encoder)."""
    mark = INT64_MAX  # packs as 9 bytes that occur nowhere else in an ack header
    topic, header = encode(Message(topic=ACK_TOPIC, type="ack", meta={"ack_seq": mark}))
    assert isinstance(topic, bytes) and isinstance(header, bytes)
    packed_mark = msgpack.packb(mark)
    assert header.count(packed_mark) == 1
    before, after = header.split(packed_mark)
    return topic, before, after


_ACK_TOPIC_FRAME, _ACK_BEFORE, _ACK_AFTER = _ack_template()
_ACK_SEQ_START = len(_ACK_BEFORE)


def ack_frames(ack_seq: int) -> list[bytes]:
    """The frames of the ``ack`` message for ``ack_seq``: byte for byte what ``encode`` gives."""
    assert type(ack_seq) is int and 0 <= ack_seq <= INT64_MAX
    return [_ACK_TOPIC_FRAME, _ACK_BEFORE + msgpack.packb(ack_seq) + _ACK_AFTER]


def read_ack(frames: Sequence[object], max_bytes: int) -> int:
    """``ack_seq`` of an ack message, with the outcome of ``decode`` (WireError otherwise).

    A sender reads an ack per half window, each one right after waking up, when the full decode
    runs cold and costs tens of microseconds. So the bytes :func:`ack_frames` makes are read
    directly: the template's fixed bytes around one msgpack int, which decode would accept and
    read as that ``ack_seq`` (a test checks both against decode). Anything else is decoded in full.
    """
    if len(frames) == 2:
        topic = frames[0] if type(frames[0]) is bytes else getattr(frames[0], "bytes", None)
        header = frames[1] if type(frames[1]) is bytes else getattr(frames[1], "bytes", None)
        if (
            topic == _ACK_TOPIC_FRAME
            and type(header) is bytes
            and len(topic) + len(header) <= max_bytes
            and header.startswith(_ACK_BEFORE)
            and header.endswith(_ACK_AFTER)
        ):
            try:  # exactly one msgpack object between the fixed bytes (else ExtraData etc.)
                ack_seq = msgpack.unpackb(header[_ACK_SEQ_START : len(header) - len(_ACK_AFTER)])
            except Exception:  # msgpack raises many types for hostile input
                ack_seq = None
            if type(ack_seq) is int and 0 <= ack_seq <= INT64_MAX:
                return ack_seq
    msg = decode(frames, max_bytes)
    if msg.type != "ack":
        raise WireError("schema", f"reliable sender got {msg.type!r}, expected ack")
    return msg.meta["ack_seq"]
