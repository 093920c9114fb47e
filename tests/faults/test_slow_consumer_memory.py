"""A slow consumer behind a real replay process: the sender's memory stays bounded (its RSS,
sampled twice a second) and every frame that does not reach the consumer is counted with its
reason.

Reliable: the sender blocks once ``reliable_window`` frames are unacknowledged, so it holds at
most the window and the consumer gets every frame. Latest-only: the sender keeps one parked frame
per topic (a newer one supersedes it: counted in the sender's ``dropped/<topic>``) and the
receiver one per topic (counted in its own ``dropped/<topic>``); sent = received + dropped.

``make test`` samples 10 s per mode; ``pytest -m slow tests/faults`` runs the full minute.
"""

from __future__ import annotations

import io
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from gsfix_online.runtime import Message, Node, NodeRuntimeConfig
from gsfix_online.runtime.graph import load_graph, transport_for
from gsfix_online.runtime.launcher import Launcher
from gsfix_online.runtime.zmq_transport import ZmqTransport
from gsfix_online.sources.mcap_log import write_mcap
from tests.conftest import make_frames

FPS = 20.0  # the replay's rate: four times what the consumer takes
CONSUMER_S = 0.2  # the consumer's time per frame
W, H = 240, 180  # 173 KB of colour and depth per frame: a queue of them grows 3.5 MB a second


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS for {pid}")


def _run(run_dir: Path, mode: str, seconds: float) -> tuple[list[float], dict, Node, int, str]:
    """Replay ``seconds`` of frames at FPS into a consumer that takes CONSUMER_S per frame;
    returns the sender's RSS samples (MB), its last stats, the consumer, frames, its log."""
    n = int(seconds * FPS)
    frames = make_frames(n=n, width=W, height=H, fps=FPS)
    log = run_dir / "log.mcap"
    write_mcap(log, frames)
    graph = {
        "name": "mem",
        "transport": "ipc",
        "run_dir": str(run_dir),
        "hosts": {"local": "127.0.0.1", "robot": "127.0.0.1"},
        "nodes": {
            "replay": {
                "kind": "replay",
                "machine": "robot",
                "restart": "never",
                "outputs": {"frames": mode},
                "params": {
                    "source": {"path": str(log)},
                    "replay": {"mode": "realtime"},
                    "reliable": mode == "reliable",
                },
                "runtime": {"stats_period_s": 0.5},
            },
            "slow": {"kind": "monitor", "inputs": ["replay/frames"]},  # wiring only
        },
    }
    (run_dir / "graph.yaml").write_text(yaml.safe_dump(graph))
    g = load_graph(run_dir / "graph.yaml")
    seqs: list[int] = []
    stats: dict = {}

    def on_frame(msg: Message) -> None:
        seqs.append(msg.seq)
        time.sleep(CONSUMER_S)

    def on_stats(msg: Message) -> None:
        stats.update(msg.meta)

    consumer = Node(
        "slow",
        ZmqTransport(transport_for(g, "slow"), name="slow"),
        {"rgbd": on_frame, "stats": on_stats},
        NodeRuntimeConfig(poll_timeout_ms=20),
    )
    th = threading.Thread(target=consumer.run, daemon=True)  # until request_stop
    th.start()
    log_out = io.StringIO()
    launcher = Launcher(g, machine="robot", out=log_out)  # the replay only, as on a robot
    launcher.start()
    proc = launcher.procs["replay"].popen
    rss: list[float] = []
    try:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and proc.poll() is None:
            if seqs:  # sampled from the first delivered frame on: its imports and start are over
                rss.append(_rss_mb(proc.pid))
            time.sleep(0.5)
    finally:
        launcher.stop()  # a reliable replay is still waiting for the consumer: SIGTERM
        time.sleep(2 * CONSUMER_S)  # the consumer takes what it holds
        consumer.request_stop()
        th.join(10)
    out = log_out.getvalue()
    return rss, stats, consumer, len(seqs), out


@pytest.fixture
def run_dir(short_dir: Path) -> Path:
    return short_dir


def _check(mode: str, seconds: float, run_dir: Path) -> None:
    rss, stats, consumer, got, out = _run(run_dir, mode, seconds)
    assert len(rss) >= seconds, (rss, out)  # the sender ran the whole time (2 samples a second)
    # 1. Memory: once the first seconds are over (imports, the first window of frames) RSS
    #    stays flat: from the second quarter of the samples to their end it grows less than a
    #    queue of every frame would in two seconds. Samples start at the first delivered frame:
    #    on a loaded machine the sender's start-up ran into the second quarter otherwise.
    q = len(rss) // 4
    growth = max(rss[3 * q :]) - float(np.median(rss[q : 2 * q]))
    assert growth < 7, f"sender RSS grew {growth:.1f} MB: {np.round(rss, 1).tolist()}"
    # 2. Every frame that did not arrive is counted, with its reason: the sender's final
    #    counts are in its last log line (its periodic stats can miss the drops of its last
    #    half second, which a loaded machine made the difference between pass and fail)
    final = re.search(r"replay: sent (\d+) messages \((\d+) superseded before they left, "
                      r"(\d+) unsent at close\)", out)  # fmt: skip
    assert final is not None, out
    sent, at_sender, unsent = (int(x) for x in final.groups())
    assert sent > 0
    assert int(stats.get("dropped/rgbd/cam0", 0)) <= at_sender  # the stats lag the final count
    at_receiver = consumer.transport.dropped["rgbd/cam0"]
    if mode == "reliable":  # nothing dropped: the sender waited
        assert at_sender == at_receiver == 0
        assert got >= seconds / CONSUMER_S * 0.6, (got, out)
        assert sent - got <= 32 + 1, (sent, got)  # at most the window was in flight at the end
    else:  # the consumer keeps the newest frame; the rest is counted where it was dropped
        assert at_sender + at_receiver > 0, (stats, consumer.transport.dropped)
        # sent = received + dropped at either end + parked at close (one may be in flight
        # between the sockets when the consumer stops)
        total = got + at_sender + at_receiver + unsent
        assert sent - 1 <= total <= sent, (got, at_sender, at_receiver, unsent, sent)


@pytest.mark.parametrize("mode", ["reliable", "latest"])
def test_a_slow_consumer_keeps_the_sender_memory_bounded_and_drops_counted(mode, run_dir):  # noqa: ANN001
    _check(mode, 10.0, run_dir)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["reliable", "latest"])
def test_a_slow_consumer_for_a_minute(mode, run_dir):  # noqa: ANN001
    _check(mode, 60.0, run_dir)
