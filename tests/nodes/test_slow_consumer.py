"""A real replay node process behind a deliberately slow consumer: every frame arrives and replay
exits 0 although the consumer takes far longer than the graph's absence limit; a SIGTERM while
replay waits for acknowledgements stops it at once and says what was left unacknowledged.

The consumer is a node in the test process (a test-only handler that sleeps per frame) on the
wiring the graph gives its reader; replay runs as ``gsfix-online node``, as the launcher runs it.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import yaml

from gsfix_online.runtime import Message, Node, NodeRuntimeConfig
from gsfix_online.runtime.graph import load_graph, transport_for, write_node_file
from gsfix_online.runtime.zmq_transport import ZmqTransport
from gsfix_online.sources.mcap_log import write_mcap
from tests.conftest import make_frames

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def run_dir() -> Iterator[Path]:
    d = Path(tempfile.mkdtemp(prefix="gsfix-", dir="/tmp"))  # short: ipc paths max ~107 chars
    yield d
    shutil.rmtree(d, ignore_errors=True)


def start_replay(
    run_dir: Path, n: int, on_frame: Callable[[Message], None]
) -> tuple[subprocess.Popen[str], Node, threading.Event, threading.Thread]:
    """Replay of an ``n``-frame log in a process (window 2: its sends block), into the node
    ``slow`` in this process, which calls ``on_frame`` per frame on its own thread."""
    log = run_dir / "log.mcap"
    write_mcap(log, make_frames(n=n, width=32, height=24))
    graph = {
        "name": "slow",
        "transport": "ipc",
        "run_dir": str(run_dir),
        "reliable_send_timeout_s": 0.5,  # far below the consumer's slowness
        "nodes": {
            "replay": {
                "kind": "replay",
                "restart": "never",
                "outputs": {"frames": "reliable"},
                "params": {"source": {"path": str(log)}, "replay": {"mode": "max"}},
            },
            "slow": {"kind": "monitor", "inputs": ["replay/frames"]},  # wiring only: see above
        },
    }
    (run_dir / "graph.yaml").write_text(yaml.safe_dump(graph))
    g = load_graph(run_dir / "graph.yaml")
    node_file = write_node_file(g, "replay", run_dir / "replay.yaml")
    raw = yaml.safe_load(node_file.read_text())
    raw["transport"]["reliable_window"] = 2
    node_file.write_text(yaml.safe_dump(raw))

    consumer = Node(
        "slow",
        ZmqTransport(transport_for(g, "slow"), name="slow"),  # binds before replay starts
        {"rgbd": on_frame},
        NodeRuntimeConfig(poll_timeout_ms=20),
    )
    stop = threading.Event()

    def loop() -> None:  # acks go out from the next receive, after the slow handler
        try:
            while not stop.is_set():
                consumer.spin_once()
        finally:
            consumer.transport.close()

    th = threading.Thread(target=loop, daemon=True)
    th.start()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "gsfix_online.apps.cli",
            "node",
            "replay",
            "--config",
            str(node_file),
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    return proc, consumer, stop, th


def finish(proc: subprocess.Popen[str], timeout_s: float) -> tuple[int, str]:
    try:
        out, _ = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        raise AssertionError(f"replay did not end within {timeout_s} s:\n{out}") from None
    return proc.returncode, out


def test_replay_waits_for_a_slow_consumer_and_drops_nothing(run_dir: Path) -> None:
    """1.5 s per frame, 4 frames, a 0.5 s absence limit and a window of 2: replay blocks on its
    third send and waits about 3 s for its final acknowledgements (the old no-ack timeout and
    the old fixed final wait would have given up), then exits 0."""
    n, delay_s = 4, 1.5
    seqs: list[int] = []

    def on_frame(msg: Message) -> None:
        seqs.append(msg.seq)
        time.sleep(delay_s)  # a handler that takes its time (distilling, say)

    proc, _, stop, th = start_replay(run_dir, n, on_frame)
    try:
        t0 = time.monotonic()
        rc, out = finish(proc, timeout_s=60)
        elapsed = time.monotonic() - t0
    finally:
        stop.set()
        th.join(10)
    assert rc == 0, out
    assert seqs == list(range(n)), out
    assert elapsed > (n - 1) * delay_s, out  # replay ended only once the last frame was read
    assert f"replay: sent {n} messages" in out and "unacknowledged" not in out, out


def test_sigterm_stops_replay_while_it_waits_and_says_what_was_left(run_dir: Path) -> None:
    """The consumer takes the first frame and never finishes it; replay has sent both frames and
    waits for their acknowledgement. SIGTERM ends it promptly, exit 0, naming the count."""
    n = 2
    got_one = threading.Event()
    release = threading.Event()

    def on_frame(msg: Message) -> None:
        got_one.set()
        release.wait(30)  # stuck until the test ends

    proc, _, stop, th = start_replay(run_dir, n, on_frame)
    try:
        assert got_one.wait(30), finish(proc, 5)[1]
        time.sleep(0.3)  # replay is in its final wait by now
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        rc, out = finish(proc, timeout_s=10)
        elapsed = time.monotonic() - t0
    finally:
        release.set()
        stop.set()
        th.join(10)
    assert rc == 0, out
    assert elapsed < 3.0, out  # the close still gives acks linger_s (1 s)
    assert f"{n} messages unacknowledged" in out, out
    assert "node 'slow' (output 'frames'," in out, out
