"""Go-back-N bookkeeping against a simulated lossy, duplicating channel (no sockets)."""

from __future__ import annotations

import random
from collections import deque
from collections.abc import Sequence

import msgpack
import pytest
import zmq
from hypothesis import given, settings
from hypothesis import strategies as st

from gsfix_online.runtime.reliable import (
    ACK_TOPIC,
    ENVELOPE,
    MAGIC,
    MAGIC_V1,
    ReceiveOrder,
    SendWindow,
    ack_frames,
    envelope_problem,
    parse_envelope,
    read_ack,
)
from gsfix_online.runtime.wire import Message, WireError, decode, encode


def simulate(
    n: int, loss: float, dup: float, seed: int, restart_after: int | None = None
) -> tuple[list[int], SendWindow]:
    """Send payloads 0..n-1 through a channel that loses/duplicates messages and acks."""
    rng = random.Random(seed)
    win, rx = SendWindow(window=4, resend_s=0.05), ReceiveOrder(ack_interval_s=0.01)
    to_rx: deque[tuple[bytes, int]] = deque()
    to_tx: deque[int] = deque()
    delivered: list[int] = []
    now, next_payload, restarted = 0.0, 0, False
    while (win.pending or next_payload < n) and now < 60.0:
        now += 0.001
        while not win.full and next_payload < n:
            win.add([next_payload], now)
            next_payload += 1
        for p in win.to_send(now):
            win.mark_sent(p, now)
            for _ in range(2 if rng.random() < dup else 1):
                if rng.random() >= loss:
                    to_rx.append((win.envelope(p) + b"t\x00", p.frames[0]))
        while to_rx:
            env, payload = to_rx.popleft()
            parsed = parse_envelope(env)
            assert parsed is not None
            link_seq, base, window = parsed
            verdict, ack = rx.receive(b"tx", link_seq, base, window, now)
            if verdict == "deliver":
                delivered.append(payload)
            if ack is not None and rng.random() >= loss:
                to_tx.append(ack)
            if restart_after is not None and not restarted and len(delivered) == restart_after:
                rx, restarted = ReceiveOrder(ack_interval_s=0.01), True  # state and queue lost
                to_rx.clear()
        to_tx.extend(a for _, a in rx.deferred_acks(now))
        while to_tx:
            win.on_ack(to_tx.popleft(), now)
    return delivered, win


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize(("loss", "dup"), [(0.0, 0.0), (0.1, 0.0), (0.0, 0.2), (0.2, 0.2)])
def test_exactly_once_in_order(seed: int, loss: float, dup: float) -> None:
    delivered, win = simulate(200, loss, dup, seed)
    assert delivered == list(range(200))
    assert not win.pending
    if loss == 0:
        assert win.resends == 0


@pytest.mark.parametrize("seed", range(3))
def test_receiver_restart_loses_nothing(seed: int) -> None:
    delivered, _ = simulate(100, 0.05, 0.05, seed, restart_after=37)
    first, second = delivered[:37], delivered[37:]
    assert first == list(range(37))
    # The new receiver starts at the sender's oldest unacked message: at most a few messages
    # are delivered twice (delivered but not yet acked when the old one died), none are lost.
    assert second[0] <= 37 and second == list(range(second[0], 100))


def test_window_blocks_at_capacity_and_acks_free_it() -> None:
    win = SendWindow(window=3, resend_s=1.0)
    for i in range(3):
        win.add([i], 0.0)
    assert win.full and win.base == 1
    assert [p.link_seq for p in win.to_send(0.0)] == [1, 2, 3]
    assert win.on_ack(2, 0.1) == 2 and not win.full and win.base == 3
    assert win.on_ack(1, 0.2) == 0  # stale ack


def test_resend_after_stall_only() -> None:
    win = SendWindow(window=4, resend_s=0.5)
    win.add([0], 0.0)
    win.add([1], 0.0)
    for p in win.to_send(0.0):
        win.mark_sent(p, 0.0)
    assert list(win.to_send(0.4)) == []
    win.on_ack(1, 0.45)  # progress resets the stall timer
    assert list(win.to_send(0.9)) == []
    assert [p.link_seq for p in win.to_send(0.96)] == [2]
    assert win.resends == 1


def test_may_resend_holds_the_resend_until_a_disconnect() -> None:
    """The transport's gate: while the receiver stays connected nothing is resent (its pipe
    would fill); after a disconnect everything unacknowledged goes again, once."""
    win = SendWindow(window=4, resend_s=0.5)
    dropped = [False]
    asked: list[float] = []

    def may_resend() -> bool:
        asked.append(t)
        return dropped[0]

    win.may_resend = may_resend
    win.add([0], 0.0)
    win.add([1], 0.0)
    for p in win.to_send(0.0):
        win.mark_sent(p, 0.0)
    resent = []
    for k in range(1, 300):  # 0 .. 3 s in 10 ms steps
        t = k / 100
        if k == 160:
            dropped[0] = True  # the receiver went away at 1.6 s
        sent = win.to_send(t)
        for p in sent:
            win.mark_sent(p, t)
        if sent:
            resent.append((t, [p.link_seq for p in sent]))
            dropped[0] = False  # the gate reports a disconnect once
    assert asked[:3] == [0.5, 1.0, 1.5]  # held: asked again every resend_s, no backoff
    assert resent == [(2.0, [1, 2])] and win.resends == 2


def test_unsent_messages_form_a_suffix() -> None:
    win = SendWindow(window=4, resend_s=1.0)
    for i in range(3):
        win.add([i], 0.0)
    first = win.to_send(0.0)[0]
    win.mark_sent(first, 0.0)  # then the socket said EAGAIN
    assert [p.link_seq for p in win.to_send(0.0)] == [2, 3]


def test_bad_envelopes() -> None:
    topic = b"rgbd/cam0\x00"
    assert parse_envelope(ENVELOPE.pack(MAGIC, 5, 3, 8) + topic) == (5, 3, 8)
    assert parse_envelope(b"short") is None
    assert parse_envelope(ENVELOPE.pack(MAGIC, 5, 3, 8)) is None  # no topic after it
    assert parse_envelope(ENVELOPE.pack(b"XXXX", 5, 3, 8) + topic) is None
    assert parse_envelope(ENVELOPE.pack(MAGIC, 0, 0, 8) + topic) is None
    assert parse_envelope(ENVELOPE.pack(MAGIC, 3, 5, 8) + topic) is None  # base after link_seq
    assert parse_envelope(ENVELOPE.pack(MAGIC, 3, 1, 0) + topic) is None


def test_an_envelope_of_the_first_version_is_named() -> None:
    v1 = ENVELOPE.pack(MAGIC_V1, 1, 1, 8)  # a frame of its own, before the topic frame
    assert parse_envelope(v1) is None and parse_envelope(v1 + b"t\x00") is None
    assert "GSR1" in envelope_problem(v1) and "GSR2" in envelope_problem(v1)
    assert envelope_problem(b"junk") == "reliable message without a valid envelope"


def test_ack_batching() -> None:
    rx = ReceiveOrder(ack_interval_s=1.0)
    acks = []
    for seq in range(1, 9):
        verdict, ack = rx.receive(b"a", seq, 1, window=8, now=0.0)
        assert verdict == "deliver"
        acks.append(ack)
    assert acks == [None, None, None, 4, None, None, None, 8]  # every window // 2
    assert rx.receive(b"a", 9, 5, 8, now=0.0) == ("deliver", None) and rx.has_deferred
    assert rx.due_at == 1.0  # the last ack (0.0) + ack_interval_s
    assert rx.deferred_acks(0.5) == []
    assert rx.has_deferred and rx.due_at == 1.0
    assert rx.deferred_acks(1.5) == [(b"a", 9)]  # ack_interval_s later
    assert not rx.has_deferred
    assert rx.receive(b"a", 10, 5, 8, now=3.0) == ("deliver", 10)  # the interval has passed
    assert rx.receive(b"a", 4, 3, 8, now=3.1) == ("duplicate", 10)  # re-ack at once
    assert rx.receive(b"a", 12, 5, 8, now=3.2) == ("gap", 10)  # 11 is missing: ack what came
    assert (rx.duplicates, rx.gaps) == (1, 1)


def test_deferred_acks_of_two_senders() -> None:
    rx = ReceiveOrder(ack_interval_s=1.0)
    # A first message is acknowledged at once (no ack for longer than the interval)
    assert rx.receive(b"a", 1, 1, 16, now=10.0) == ("deliver", 1)
    assert rx.receive(b"b", 1, 1, 16, now=10.5) == ("deliver", 1)
    assert rx.receive(b"a", 2, 1, 16, now=10.6) == ("deliver", None)
    assert rx.receive(b"b", 2, 1, 16, now=10.7) == ("deliver", None)
    assert rx.due_at == 11.0  # a's, the earlier one
    assert rx.deferred_acks(11.2) == [(b"a", 2)]
    assert rx.due_at == 11.5  # b's is still held
    assert rx.deferred_acks(11.2, force=True) == [(b"b", 2)]
    assert not rx.has_deferred and rx.deferred_acks(99.0) == []


def test_push_is_the_fast_path_of_add() -> None:
    win = SendWindow(window=2, resend_s=1.0)
    pushed = win.push(["m1"], 0.0)
    assert pushed is not None
    p, env = pushed
    assert parse_envelope(env + b"t\x00") == (1, 1, 2) and p.link_seq == 1
    assert win.push(["m2"], 0.0) is None  # m1 not marked sent yet: go through add/to_send
    win.mark_sent(p, 0.0)
    p2, env2 = win.push(["m2"], 0.0) or (None, b"")
    assert parse_envelope(env2 + b"t\x00") == (2, 1, 2)  # base: m1 is still unacked
    win.mark_sent(p2, 0.0)
    assert win.push(["m3"], 0.0) is None and win.full  # window full
    assert win.on_ack(1, 0.1) == 1
    p3, env3 = win.push(["m3"], 0.1) or (None, b"")
    assert parse_envelope(env3 + b"t\x00") == (3, 2, 2)


def test_resend_backs_off_while_the_receiver_is_silent() -> None:
    win = SendWindow(window=2, resend_s=0.5)
    win.add([0], 0.0)
    resent_at = []
    for k in range(800):  # 0 .. 8 s in 10 ms steps
        t = k / 100
        for p in win.to_send(t):
            win.mark_sent(p, t)
            resent_at.append(t)
    assert resent_at == [0.0, 0.5, 1.5, 3.5, 7.5]  # 0.5, 1, 2, 4 s apart (capped at 8x)
    win.on_ack(1, 7.6)
    win.add([1], 7.6)
    win.mark_sent(win.to_send(7.6)[0], 7.6)
    assert win.to_send(8.09) == [] and len(win.to_send(8.11)) == 1  # back to 0.5 s


# --------------------------------------------------------------------------------------------
# Acks on the wire: the template against encode, the fast reader against decode
# --------------------------------------------------------------------------------------------

ACK_SEQS = [0, 1, 127, 128, 255, 256, 65535, 65536, 2**32 - 1, 2**32, 2**63 - 1]


def read_ack_reference(frames: Sequence[object], max_bytes: int) -> int:
    """What the sender did before the fast path: the full decode."""
    msg = decode(frames, max_bytes)
    if msg.type != "ack":
        raise WireError("schema", f"reliable sender got {msg.type!r}, expected ack")
    return msg.meta["ack_seq"]


def outcome(read: object, frames: Sequence[object], max_bytes: int = 1 << 20) -> object:
    try:
        return read(frames, max_bytes)  # type: ignore[operator]
    except WireError as exc:
        return exc.reason


@pytest.mark.parametrize("ack_seq", ACK_SEQS)
def test_ack_frames_are_the_encoders_bytes(ack_seq: int) -> None:
    want = encode(Message(topic=ACK_TOPIC, type="ack", meta={"ack_seq": ack_seq}))
    assert ack_frames(ack_seq) == want
    assert read_ack(want, 1 << 20) == read_ack_reference(want, 1 << 20) == ack_seq


def test_read_ack_reads_zmq_frames() -> None:
    frames = [zmq.Frame(f) for f in ack_frames(300)]
    assert read_ack(frames, 1 << 20) == 300
    assert outcome(read_ack, frames, 10) == outcome(read_ack_reference, frames, 10) == "too_large"


def test_read_ack_falls_back_to_decode() -> None:
    other = encode(Message(topic=ACK_TOPIC, type="ack", meta={"ack_seq": 5, "extra": 1}))
    assert read_ack(other, 1 << 20) == 5  # another encoder's valid ack: decoded in full
    stamped = encode(Message(topic=ACK_TOPIC, type="ack", meta={"ack_seq": 6}), sent_mono_ns=1)
    assert read_ack(stamped, 1 << 20) == 6
    beat = Message(topic="_ack", type="heartbeat", meta={"node": "n", "pid": 1, "uptime_s": 0.0})
    assert outcome(read_ack, encode(beat)) == "schema"


# A middle that is not one non-negative int64 must go through the full decode
middles = st.one_of(
    st.integers(-(2**63), 2**64 - 1).map(msgpack.packb),
    st.one_of(st.none(), st.booleans(), st.floats(), st.text(max_size=4)).map(msgpack.packb),
    st.lists(st.integers(0, 300), max_size=3).map(msgpack.packb),
    st.binary(max_size=12),
    st.tuples(st.integers(0, 2**63 - 1), st.binary(min_size=1, max_size=3)).map(
        lambda t: msgpack.packb(t[0]) + t[1]
    ),
)


@settings(max_examples=1500, deadline=None, database=None)
@given(
    ack_seq=st.integers(0, 2**63 - 1),
    middle=middles,
    edit=st.sampled_from(["middle", "cut", "append", "prepend", "topic", "frames", "none"]),
    extra=st.binary(min_size=1, max_size=4),
    max_bytes=st.sampled_from([1 << 20, 40]),
)
def test_read_ack_agrees_with_decode(
    ack_seq: int, middle: bytes, edit: str, extra: bytes, max_bytes: int
) -> None:
    topic, header = ack_frames(ack_seq)
    frames: list[object] = [topic, header]
    start = header.index(b"ack_seq") + len(b"ack_seq")
    end = start + len(msgpack.packb(ack_seq))
    if edit == "middle":
        frames[1] = header[:start] + middle + header[end:]
    elif edit == "cut":
        frames[1] = header[: -len(extra)]
    elif edit == "append":
        frames[1] = header + extra
    elif edit == "prepend":
        frames[1] = extra + header
    elif edit == "topic":
        frames[0] = extra + topic
    elif edit == "frames":
        frames.append(extra)
    for form in (frames, [zmq.Frame(f) for f in frames], [memoryview(f) for f in frames]):
        assert outcome(read_ack, form, max_bytes) == outcome(read_ack_reference, form, max_bytes)
