"""Go-back-N bookkeeping against a simulated lossy, duplicating channel (no sockets)."""

from __future__ import annotations

import random
from collections import deque

import pytest

from gsfix_online.runtime.reliable import (
    ENVELOPE,
    MAGIC,
    ReceiveOrder,
    SendWindow,
    parse_envelope,
)


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
                    to_rx.append((win.envelope(p), p.frames[0]))
        while to_rx:
            env, payload = to_rx.popleft()
            parsed = parse_envelope(env)
            assert parsed is not None
            link_seq, base, window = parsed
            verdict = rx.accept(b"tx", link_seq, base)
            if verdict == "deliver":
                delivered.append(payload)
            ack = rx.ack_due(b"tx", verdict, window, now=now)
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


def test_unsent_messages_form_a_suffix() -> None:
    win = SendWindow(window=4, resend_s=1.0)
    for i in range(3):
        win.add([i], 0.0)
    first = win.to_send(0.0)[0]
    win.mark_sent(first, 0.0)  # then the socket said EAGAIN
    assert [p.link_seq for p in win.to_send(0.0)] == [2, 3]


def test_bad_envelopes() -> None:
    assert parse_envelope(ENVELOPE.pack(MAGIC, 5, 3, 8)) == (5, 3, 8)
    assert parse_envelope(b"short") is None
    assert parse_envelope(ENVELOPE.pack(b"XXXX", 5, 3, 8)) is None
    assert parse_envelope(ENVELOPE.pack(MAGIC, 0, 0, 8)) is None
    assert parse_envelope(ENVELOPE.pack(MAGIC, 3, 5, 8)) is None  # base after link_seq
    assert parse_envelope(ENVELOPE.pack(MAGIC, 3, 1, 0)) is None


def test_ack_batching() -> None:
    rx = ReceiveOrder(ack_interval_s=1.0)
    acks = []
    for seq in range(1, 9):
        verdict = rx.accept(b"a", seq, 1)
        acks.append(rx.ack_due(b"a", verdict, window=8, now=0.0))
    assert acks == [None, None, None, 4, None, None, None, 8]  # every window // 2
    rx.accept(b"a", 9, 5)
    assert rx.ack_due(b"a", "deliver", 8, now=0.0) is None and rx.has_deferred
    assert rx.deferred_acks(0.5) == []
    assert rx.deferred_acks(1.5) == [(b"a", 9)]  # ack_interval_s later
    assert not rx.has_deferred
    rx.accept(b"a", 10, 5)
    assert rx.ack_due(b"a", "deliver", 8, now=3.0) == 10  # interval since the last ack passed
    assert rx.accept(b"a", 4, 3) == "duplicate"
    assert rx.ack_due(b"a", "duplicate", 8, now=3.1) == 10  # re-ack at once


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
