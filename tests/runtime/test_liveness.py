"""A reliable sender waits for a slow receiver as long as it is connected, and names one that is
gone (killed, or frozen: heartbeats) within the grace period; a signal ends the wait."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from gsfix_online.runtime import liveness
from gsfix_online.runtime.config import EndpointConfig, TransportConfig
from gsfix_online.runtime.transport import TransportInterrupted, TransportTimeout
from gsfix_online.runtime.zmq_transport import ZmqTransport
from tests.runtime.test_zmq_transport import ROOT, make_pair, run_thread, small

SINK = Path(__file__).with_name("sink_proc.py")
FAST_HEARTBEATS = dict(heartbeat_s=0.1, heartbeat_timeout_s=0.5)


@pytest.mark.parametrize("kind", ["ipc", "tcp"])
def test_a_slow_receiver_is_waited_for_as_long_as_it_is_connected(
    kind: str, ipc_dir: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """1.5 s per message against a 1 s absence limit (the old no-ack timeout raised on the
    third send): every message arrives in order, nothing is resent, and the wait is logged.
    The receiver's thread sleeps in its handler; heartbeats every 0.1 s still get answers."""
    n, delay_s = 3, 1.5
    monkeypatch.setattr(liveness, "WAIT_LOG_FIRST_S", 0.5)
    cfg = dict(
        reliable_window=2, reliable_send_timeout_s=1.0, reliable_resend_s=0.1, **FAST_HEARTBEATS
    )
    tx, rx = make_pair("reliable", kind, ipc_dir, **cfg)
    got: list[int] = []
    stop = threading.Event()

    def consume() -> None:  # acks go out from the next recv, after the slow "handler"
        while not stop.is_set():
            if (m := rx.recv(50)) is not None:
                got.append(m.seq)
                time.sleep(delay_s)

    th, errors = run_thread(consume)
    caplog.set_level(logging.INFO, logger=liveness.__name__)
    try:
        t0 = time.monotonic()
        for i in range(n):
            tx.publish(small(i), reliable=True)
        assert tx.flush()  # no deadline: the receiver is connected
        elapsed = time.monotonic() - t0
        stop.set()
        th.join(5.0)
        assert not errors, errors
        assert got == list(range(n))
        assert elapsed > (n - 1) * delay_s  # it did wait for the slow receiver
        address = rx.input_addresses[0]
        assert tx.stats()[f"reliable_resends/{address}"] == 0  # connected: nothing resent
        assert tx.stats()[f"reliable_connected/{address}"] == 1.0  # heartbeats answered
        assert rx.stats()["reliable_duplicates"] == 0
        waits = [r.getMessage() for r in caplog.records if "to acknowledge" in r.getMessage()]
        assert waits, caplog.text
        assert f"waiting for the receiver at {address} to acknowledge" in waits[0]
        assert "it is connected (busy), waiting since" in waits[0]
    finally:
        stop.set()
        tx.close()
        rx.close()


def start_sink(ipc_dir: Path, bind: str, delay_s: float) -> tuple[subprocess.Popen[bytes], str]:
    ready = ipc_dir / "ready"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, str(SINK), bind, str(ready), str(delay_s)],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    deadline = time.monotonic() + 20.0
    while not ready.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    if not ready.exists():
        proc.kill()
        raise AssertionError(proc.communicate(timeout=5)[0].decode())
    return proc, ready.read_text()


@pytest.mark.parametrize(
    ("how", "kind"), [("killed", "ipc"), ("frozen", "tcp")], ids=["killed-ipc", "frozen-tcp"]
)
def test_a_receiver_that_is_gone_is_named_within_the_grace_period(
    how: str, kind: str, ipc_dir: Path
) -> None:
    """The receiver is busy with the first message (its handler sleeps a minute) when it is
    killed (the connection closes) or frozen (SIGSTOP: only the heartbeats notice)."""
    bind = "tcp://127.0.0.1:*" if kind == "tcp" else f"ipc://{ipc_dir}/sink"
    proc, address = start_sink(ipc_dir, bind, delay_s=60.0)
    out = EndpointConfig(address, False, "reliable", name="frames", peer="sink")
    cfg = TransportConfig(
        outputs=(out,),
        reliable_window=2,
        reliable_send_timeout_s=0.5,
        linger_s=0.1,
        **FAST_HEARTBEATS,
    )
    tx = ZmqTransport(cfg, "src")
    stopped_at: list[float] = []

    def stop_receiver() -> None:
        proc.send_signal(signal.SIGKILL if how == "killed" else signal.SIGSTOP)
        stopped_at.append(time.monotonic())

    try:
        deadline = time.monotonic() + 10.0
        while not tx.stats()[f"reliable_connected/{address}"] and time.monotonic() < deadline:
            time.sleep(0.01)  # so that what follows is a disconnect, not a late start
        tx.publish(small(0), reliable=True)
        tx.publish(small(1), reliable=True)  # the window is full; the sink sleeps on message 0
        timer = threading.Timer(0.5, stop_receiver)
        timer.start()
        with pytest.raises(TransportTimeout) as err:
            tx.publish(small(2), reliable=True)  # blocked until the sink is gone, then 0.5 s
        waited = time.monotonic() - stopped_at[0]
        timer.join()
        msg = str(err.value)
        assert f"src: reliable send to node 'sink' (output 'frames', {address}) failed" in msg
        assert "it disconnected at" in msg and "2 messages unacknowledged" in msg
        # the grace (0.5 s), plus the heartbeat timeout (0.5 s) when frozen, plus scheduling
        assert 0.45 < waited < (3.0 if how == "killed" else 3.5), waited
    finally:
        tx.close()
        proc.kill()  # also ends a stopped process
        proc.wait()
        if proc.stdout:
            proc.stdout.close()


def test_interrupt_ends_a_blocked_flush_and_says_what_is_left(ipc_dir: Path) -> None:
    tx, rx = make_pair("reliable", "ipc", ipc_dir, reliable_window=4, linger_s=0.1)
    try:
        tx.publish(small(0), reliable=True)
        tx.publish(small(1), reliable=True)  # rx never reads: connected, and busy forever
        threading.Timer(0.3, tx.interrupt).start()  # what a SIGTERM handler does
        t0 = time.monotonic()
        with pytest.raises(TransportInterrupted, match="2 messages unacknowledged"):
            tx.flush()
        assert time.monotonic() - t0 < 1.5
    finally:
        tx.close()
        rx.close()
