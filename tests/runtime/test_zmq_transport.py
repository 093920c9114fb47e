"""ZmqTransport over ipc and tcp (127.0.0.1, free ports): reliable, latest-only, shutdown."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zmq

from gsfix_online.runtime import zmq_transport
from gsfix_online.runtime.config import EndpointConfig, TransportConfig
from gsfix_online.runtime.reliable import ENVELOPE, MAGIC, MAGIC_V1, ReceiveOrder
from gsfix_online.runtime.transport import TransportError, TransportTimeout
from gsfix_online.runtime.wire import Message, encode
from gsfix_online.runtime.zmq_transport import ZmqTransport, _LatestInbox
from tests.runtime.samples import intrinsics_K, rgbd_message

ROOT = Path(__file__).resolve().parents[2]
H, W = 480, 640
K = intrinsics_K(W, H)


def bind_address(kind: str, ipc_dir: Path, name: str) -> str:
    return "tcp://127.0.0.1:*" if kind == "tcp" else f"ipc://{ipc_dir}/{name}"


def make_pair(
    mode: str, kind: str, ipc_dir: Path, **cfg: object
) -> tuple[ZmqTransport, ZmqTransport]:
    rx = ZmqTransport(
        TransportConfig(
            inputs=(EndpointConfig(bind_address(kind, ipc_dir, "rx"), True, mode),), **cfg
        ),
        name="rx",
    )
    tx = ZmqTransport(
        TransportConfig(outputs=(EndpointConfig(rx.input_addresses[0], False, mode),), **cfg),
        name="tx",
    )
    return tx, rx


def big_frame(i: int) -> Message:
    """640x480 RGB-D (1.2 MB) whose pixels encode ``i``."""
    return Message(
        "rgbd/cam0",
        "rgbd",
        seq=i,
        stamp_ns=i,
        frame_id="cam0",
        meta={"posed": False},
        arrays={
            "color": np.full((H, W, 3), i % 256, np.uint8),
            "depth": np.full((H, W), float(i), np.float32),
            "K": K,
        },
    )


def small(i: int, topic: str = "hb/x") -> Message:
    return Message(topic, "heartbeat", seq=i, meta={"node": "x", "pid": 1, "uptime_s": 0.0})


def run_thread(fn: object) -> tuple[threading.Thread, list[BaseException]]:
    errors: list[BaseException] = []

    def wrapped() -> None:
        try:
            fn()  # type: ignore[operator]
        except BaseException as exc:  # reported by the test thread
            errors.append(exc)

    th = threading.Thread(target=wrapped, daemon=True)
    th.start()
    return th, errors


def wait_subscribed(tx: ZmqTransport, rx: ZmqTransport) -> None:
    """PUB/SUB drops what is sent before the subscription arrives: probe until one gets through."""
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline:
        tx.publish(small(0, "probe/x"))
        if rx.recv(20) is not None:
            while rx.recv(50) is not None:
                pass
            return
    raise AssertionError("subscriber never connected")


@pytest.mark.parametrize("kind", ["ipc", "tcp"])
def test_reliable_delivers_every_frame_in_order_to_a_slow_consumer(
    kind: str, ipc_dir: Path
) -> None:
    tx, rx = make_pair("reliable", kind, ipc_dir, reliable_window=8)
    try:

        def send() -> None:
            for i in range(300):
                tx.publish(big_frame(i), reliable=True)
            assert tx.flush(10.0)

        th, errors = run_thread(send)
        seqs: list[int] = []
        deadline = time.monotonic() + 30.0
        while (len(seqs) < 300 or th.is_alive()) and time.monotonic() < deadline:
            m = rx.recv(20)
            if m is None:
                continue
            assert m.arrays["color"][-1, -1, -1] == m.seq % 256 and m.arrays["depth"][0, 0] == m.seq
            seqs.append(m.seq)
            time.sleep(0.001)  # the consumer is slower than the sender
        th.join(5.0)
        assert not errors, errors
        assert seqs == list(range(300))
        assert not rx.rejected and not rx.dropped
        assert tx.stats()[f"reliable_unacked/{rx.input_addresses[0]}"] == 0
    finally:
        tx.close()
        rx.close()


@pytest.mark.parametrize("kind", ["ipc", "tcp"])
def test_latest_only_delivers_the_newest_and_counts_every_drop(kind: str, ipc_dir: Path) -> None:
    tx, rx = make_pair("latest", kind, ipc_dir)
    try:
        wait_subscribed(tx, rx)

        def send() -> None:
            for i in range(100):
                tx.publish(big_frame(i))
            assert tx.flush_latest(5.0)

        th, errors = run_thread(send)
        seqs: list[int] = []
        while True:
            m = rx.recv(300)
            if m is None and not th.is_alive():
                break
            if m is not None:
                seqs.append(m.seq)
                time.sleep(0.02)  # slow consumer
        assert not errors, errors
        dropped = tx.dropped["rgbd/cam0"] + rx.dropped["rgbd/cam0"]
        assert seqs[-1] == 99  # the newest frame arrives
        assert seqs == sorted(seqs) and len(seqs) < 100
        assert dropped > 0 and len(seqs) + dropped == 100  # every frame delivered or counted
    finally:
        tx.close()
        rx.close()


def test_latest_only_publish_never_blocks_without_subscribers() -> None:
    tx = ZmqTransport(TransportConfig(outputs=(EndpointConfig("tcp://127.0.0.1:*", True),)))
    try:
        t0 = time.monotonic()
        for i in range(50):
            tx.publish(big_frame(i))
        assert time.monotonic() - t0 < 2.0
    finally:
        tx.close()


def test_reliable_sender_raises_while_consumer_has_not_connected_then_loses_nothing(
    ipc_dir: Path,
) -> None:
    addr = f"ipc://{ipc_dir}/late"
    cfg = dict(reliable_window=2, reliable_connect_timeout_s=0.3, reliable_resend_s=0.05)
    tx = ZmqTransport(
        TransportConfig(outputs=(EndpointConfig(addr, mode="reliable"),), **cfg), "tx"
    )
    rx = None
    try:
        tx.publish(small(0), reliable=True)
        tx.publish(small(1), reliable=True)  # the window (2) is full now
        t0 = time.monotonic()
        with pytest.raises(TransportTimeout, match=r"late failed: it has not connected in 0\.\d s"):
            tx.publish(small(2), reliable=True)
        assert 0.25 <= time.monotonic() - t0 < 1.5
        rx = ZmqTransport(
            TransportConfig(inputs=(EndpointConfig(addr, True, "reliable"),), **cfg), "rx"
        )
        seqs: list[int] = []
        deadline = time.monotonic() + 5.0
        while len(seqs) < 2 and time.monotonic() < deadline:
            tx.flush(0.01)
            if (m := rx.recv(10)) is not None:
                seqs.append(m.seq)
        tx.publish(small(2), reliable=True)  # the caller retries the refused message
        while len(seqs) < 3 and time.monotonic() < deadline:
            if (m := rx.recv(10)) is not None:
                seqs.append(m.seq)
        assert seqs == [0, 1, 2]
        assert rx.recv(10) is None  # the next recv sends the ack for what was consumed
        assert tx.flush(1.0)
    finally:
        tx.close()
        if rx is not None:
            rx.close()


def test_reliable_survives_a_receiver_restart(ipc_dir: Path) -> None:
    addr = f"ipc://{ipc_dir}/restart"
    cfg = dict(reliable_window=8, reliable_resend_s=0.1, linger_s=0.1)
    tx = ZmqTransport(
        TransportConfig(outputs=(EndpointConfig(addr, mode="reliable"),), **cfg), "tx"
    )
    rx = ZmqTransport(
        TransportConfig(inputs=(EndpointConfig(addr, True, "reliable"),), **cfg), "rx1"
    )

    def send() -> None:
        for i in range(60):
            tx.publish(small(i), reliable=True)
        assert tx.flush(10.0)

    th, errors = run_thread(send)
    try:
        first: list[int] = []
        while len(first) < 20:
            if (m := rx.recv(100)) is not None:
                first.append(m.seq)
        rx.close()  # the receiver dies with messages queued
        rx = ZmqTransport(
            TransportConfig(inputs=(EndpointConfig(addr, True, "reliable"),), **cfg), "rx2"
        )
        second: list[int] = []
        deadline = time.monotonic() + 10.0
        while (not second or second[-1] < 59 or th.is_alive()) and time.monotonic() < deadline:
            if (m := rx.recv(20)) is not None:
                second.append(m.seq)
        th.join(5.0)
        assert not errors, errors
        assert first == list(range(20))
        assert second[0] <= 20 and second == list(range(second[0], 60))
    finally:
        tx.close()
        rx.close()


def test_malformed_input_on_both_socket_kinds_is_counted(ipc_dir: Path) -> None:
    latest, reliable = f"ipc://{ipc_dir}/latest", f"ipc://{ipc_dir}/reliable"
    rx = ZmqTransport(
        TransportConfig(
            inputs=(EndpointConfig(latest, True), EndpointConfig(reliable, True, "reliable")),
            subscriptions=("rgbd/",),
        ),
        "rx",
    )
    ctx = zmq.Context()
    pub, dealer = ctx.socket(zmq.PUB), ctx.socket(zmq.DEALER)
    try:
        pub.connect(latest)
        dealer.connect(reliable)
        deadline = time.monotonic() + 5.0
        while not rx.rejected["header_msgpack"] and time.monotonic() < deadline:
            pub.send_multipart([b"rgbd/cam0\x00", b"\xc1"])  # until the subscription is up
            rx.recv(20)
        dealer.send_multipart([b"no envelope"])
        dealer.send_multipart([ENVELOPE.pack(MAGIC_V1, 1, 1, 4), *encode(rgbd_message(6))])
        dealer.send_multipart([ENVELOPE.pack(MAGIC, 1, 1, 4) + b"rgbd/cam0\x00", b"\x80"])
        topic, *rest = encode(rgbd_message(7))
        dealer.send_multipart([ENVELOPE.pack(MAGIC, 2, 1, 4) + topic, *rest])  # type: ignore[operator]
        pub.send_multipart(encode(rgbd_message(8)))
        got = {m.seq for m in iter(lambda: rx.recv(200), None)}
        assert got == {7, 8}
        assert rx.rejected["envelope"] == 2 and rx.rejected["header_keys"] == 1
        assert dealer.poll(1000)  # the reliable sender got its ack
    finally:
        pub.close(0)
        dealer.close(0)
        ctx.term()
        rx.close()


def test_a_latest_message_wakes_a_node_that_also_has_one_reliable_input(ipc_dir: Path) -> None:
    """With one reliable and one latest-only input, a wait covers both sockets."""
    latest, reliable = f"ipc://{ipc_dir}/latest", f"ipc://{ipc_dir}/reliable"
    rx = ZmqTransport(
        TransportConfig(
            inputs=(EndpointConfig(latest, True), EndpointConfig(reliable, True, "reliable"))
        ),
        "rx",
    )
    tx = ZmqTransport(TransportConfig(outputs=(EndpointConfig(latest),)), "tx")
    try:
        wait_subscribed(tx, rx)

        def publish_later() -> None:
            time.sleep(0.1)
            tx.publish(small(5))

        th, errors = run_thread(publish_later)
        t0 = time.monotonic()
        msg = rx.recv(3000)
        waited = time.monotonic() - t0
        th.join()
        assert not errors
        assert msg is not None and msg.seq == 5
        assert waited < 1.0, waited  # not the whole timeout on the reliable socket alone
    finally:
        tx.close()
        rx.close()


def test_configuration_errors_are_one_line() -> None:
    with pytest.raises(TransportError, match="must start with ipc://"):
        ZmqTransport(TransportConfig(inputs=(EndpointConfig("udp://1.2.3.4:5"),)))
    with pytest.raises(TransportError, match="cannot connect"):
        ZmqTransport(TransportConfig(inputs=(EndpointConfig("tcp://127.0.0.1:port"),)))
    t = ZmqTransport(TransportConfig())
    with pytest.raises(TransportError, match="no reliable output"):
        t.publish(small(0), reliable=True)
    with pytest.raises(TransportError, match="no latest-only output"):
        t.publish(small(0))
    t.close()
    with pytest.raises(TransportError, match="closed"):
        t.recv(0)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_node_process_exits_cleanly_on_signal(sig: int, ipc_dir: Path) -> None:
    in_addr, out_addr, ready = f"ipc://{ipc_dir}/in", f"ipc://{ipc_dir}/out", ipc_dir / "ready"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    script = Path(__file__).with_name("node_proc.py")
    proc = subprocess.Popen(
        [sys.executable, str(script), in_addr, out_addr, str(ready)],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    hb = None
    try:
        deadline = time.monotonic() + 20.0
        while not ready.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert ready.exists(), proc.communicate(timeout=5)[0].decode()
        hb = ZmqTransport(
            TransportConfig(inputs=(EndpointConfig(out_addr),), subscriptions=("heartbeat/",))
        )
        beat = hb.recv(5000)
        assert beat is not None and beat.meta["pid"] == proc.pid  # its loop is running
        t0 = time.monotonic()
        proc.send_signal(sig)
        rc = proc.wait(timeout=2.0)
        elapsed = time.monotonic() - t0
        out = proc.stdout.read().decode() if proc.stdout else ""
        assert rc == 0, out
        assert elapsed < 2.0
        assert "proc: stopped" in out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stdout:
            proc.stdout.close()
        if hb is not None:
            hb.close()


def test_latest_inbox_wakes_on_every_empty_to_full_transition() -> None:
    """The main thread checks the slots before it waits, so one wake-up per refill is enough."""
    inbox = _LatestInbox([])  # no sockets: the test thread plays the drain thread

    def woken() -> bool:
        return bool(select.select([inbox.wake_fd], [], [], 0)[0])

    def frames(topic: bytes) -> list[zmq.Frame]:
        return [zmq.Frame(topic + b"\x00"), zmq.Frame(b"h")]

    try:
        assert not woken()
        inbox._put(frames(b"a"))
        assert woken()
        inbox.clear_wakes()
        inbox._put(frames(b"b"))  # slots were not empty: no new wake-up needed
        inbox._put(frames(b"a"))  # replaces the unread "a": counted as a drop
        assert not woken() and len(inbox) == 2
        assert [bytes(inbox.pop()[0].buffer) for _ in range(2)] == [b"b\x00", b"a\x00"]
        assert inbox.pop() is None and inbox.take_drops() == {"a": 1}
        inbox._put(frames(b"c"))  # empty again: wake
        assert woken()
    finally:
        assert inbox.close()


def test_a_held_back_ack_ends_the_receivers_wait_when_it_is_due(
    ipc_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An idle receiver holding back a batched ack waits once, until the ack is due, sends it,
    then waits out the rest: no wake-up every few ms while the ack is held."""
    tx, rx = make_pair("reliable", "ipc", ipc_dir)
    rx._order = ReceiveOrder(ack_interval_s=0.1)  # wide enough to hold the ack on a busy machine
    timed_out: list[int] = []  # wait_ms of each receive on rx's input that got nothing
    real = zmq_transport._recv_within

    def recv_within(sock: zmq.Socket, wait_ms: int, *args: object, **kwargs: object) -> object:
        parts = real(sock, wait_ms, *args, **kwargs)  # type: ignore[arg-type]
        if parts is None and wait_ms > 0 and sock in rx._routers:
            timed_out.append(wait_ms)
        return parts

    monkeypatch.setattr(zmq_transport, "_recv_within", recv_within)
    try:
        for i in range(2):  # the first is acked at once, the second's ack is held back
            tx.publish(
                Message("t/a", "heartbeat", i, 0, "", {"node": "n", "pid": 1, "uptime_s": 0.0}),
                reliable=True,
            )
            assert rx.recv(2000) is not None
        assert rx._order.has_deferred
        timed_out.clear()
        assert rx.recv(300) is None
        assert not rx._order.has_deferred  # the ack went out during the wait
        assert tx.flush(1.0)  # and reached the sender
        assert len(timed_out) <= 3, timed_out  # until the ack, the rest, rounding
        assert timed_out[0] >= 20, timed_out  # the first wait ran until the ack was due
    finally:
        tx.close()
        rx.close()
