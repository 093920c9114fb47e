"""Reliable fan-out (one link per reader) and topic routes: graph wiring and real sockets."""

from __future__ import annotations

import shutil
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from gsfix_online.core.config import ConfigError, build
from gsfix_online.runtime.graph import NodeFile, address, load_graph, node_file, transport_for
from gsfix_online.runtime.transport import TransportError
from gsfix_online.runtime.wire import Message
from gsfix_online.runtime.zmq_transport import ZmqTransport


@pytest.fixture
def run_dir() -> Iterator[Path]:
    d = Path(tempfile.mkdtemp(prefix="gsfix-", dir="/tmp"))  # short: ipc paths max ~107 chars
    yield d
    shutil.rmtree(d, ignore_errors=True)


def write_graph(path: Path, transport: str, run_dir: Path, port_base: int = 47100) -> Path:
    graph = {
        "name": "fan",
        "transport": transport,
        "run_dir": str(run_dir),
        "port_base": port_base,
        "nodes": {
            "src": {
                "kind": "monitor",
                "outputs": {"a": "reliable", "b": "reliable", "live": "latest"},
                "routes": {"a": ["keyframe/"], "b": ["render_reply/"]},
            },
            "r1": {"kind": "monitor", "inputs": ["src/a", "src/b"]},
            "r2": {"kind": "monitor", "inputs": ["src/a", "src/live"]},
            "r3": {"kind": "monitor", "inputs": ["src/b"], "listen": {"ext": "reliable"}},
        },
    }
    p = path / f"graph-{transport}.yaml"
    p.write_text(yaml.safe_dump(graph))
    return p


@pytest.mark.parametrize("transport", ["ipc", "tcp"])
def test_reliable_output_gets_one_link_per_reader(tmp_path: Path, run_dir: Path, transport: str):
    g = load_graph(write_graph(tmp_path, transport, run_dir))
    src = transport_for(g, "src")
    by_topics = {}
    for ep in src.outputs:
        by_topics.setdefault(ep.topics, []).append(ep)
    assert [len(by_topics[t]) for t in (("keyframe/",), ("render_reply/",), ())] == [2, 2, 1]
    assert all(not ep.bind for t in (("keyframe/",), ("render_reply/",)) for ep in by_topics[t])
    assert by_topics[()][0].bind and by_topics[()][0].mode == "latest"
    # Every link has its own address, and each reader binds exactly the addresses sent to it.
    sent = [ep.address for ep in src.outputs if ep.mode == "reliable"]
    assert len(set(sent)) == 4
    bound = [ep.address for r in ("r1", "r2", "r3") for ep in transport_for(g, r).inputs if ep.bind]
    assert set(sent) <= set(bound)
    assert transport_for(g, "r2").inputs[1].address == by_topics[()][0].address  # latest: SUB
    if transport == "tcp":
        # Ports of the first links and the listen input are those of a graph without fan-out:
        # outputs a, b, live, then r3's listen input, then the extra links.
        ports = {ep.address.rsplit(":", 1)[1] for ep in src.outputs}
        assert ports == {"47100", "47101", "47102", "47104", "47105"}
        assert address(g, "r3", "ext").endswith(":47103")


def test_links_name_their_reader_and_carry_the_graph_timeouts(tmp_path: Path, run_dir: Path):
    """Log lines and errors of a reliable sender name the reading node and the output."""
    p = write_graph(tmp_path, "ipc", run_dir)
    raw = yaml.safe_load(p.read_text())
    raw.update(reliable_send_timeout_s=7, reliable_connect_timeout_s=70)
    p.write_text(yaml.safe_dump(raw))
    g = load_graph(p)
    src = transport_for(g, "src")
    links = sorted((ep.name, ep.peer) for ep in src.outputs if ep.mode == "reliable")
    assert links == [("a", "r1"), ("a", "r2"), ("b", "r1"), ("b", "r3")]
    assert (src.reliable_send_timeout_s, src.reliable_connect_timeout_s) == (7, 70)
    assert [ep.name for ep in transport_for(g, "r3").inputs] == ["src/b", "ext"]
    # what `gsfix-online node NAME --config FILE` reads back
    text = yaml.safe_dump(node_file(g, "src"))
    assert build(NodeFile, base=yaml.safe_load(text)).transport == src


def test_routes_must_name_outputs(tmp_path: Path, run_dir: Path) -> None:
    p = write_graph(tmp_path, "ipc", run_dir)
    raw = yaml.safe_load(p.read_text())
    raw["nodes"]["src"]["routes"] = {"nope": ["x/"]}
    p.write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError, match="routes names 'nope'"):
        load_graph(p)


def msg(topic: str, i: int) -> Message:
    return Message(
        topic=topic, type="input_end", seq=i, meta={"frames": i, "keyframes": i, "samples": 0}
    )


def test_fanout_and_routes_over_real_sockets(tmp_path: Path, run_dir: Path) -> None:
    g = load_graph(write_graph(tmp_path, "ipc", run_dir))
    logs: dict[str, list[str]] = {r: [] for r in ("r1", "r2", "r3")}
    stop = threading.Event()
    ready = threading.Barrier(4)

    def receive(name: str) -> None:  # each receiver on its own thread, acking as it reads
        t = ZmqTransport(transport_for(g, name), name=name)
        ready.wait()
        try:
            while not stop.is_set():
                m = t.recv(20)
                if m is not None:
                    logs[name].append(f"{m.topic}:{m.seq}")
        finally:
            t.close()

    threads = [threading.Thread(target=receive, args=(r,)) for r in logs]
    for th in threads:
        th.start()
    ready.wait()
    src = ZmqTransport(transport_for(g, "src"), name="src")
    try:
        for i in range(40):  # more than the window: acks from both readers of `a` are needed
            src.publish(msg("keyframe/src", i), reliable=True)
            if i % 4 == 0:
                src.publish(msg("render_reply/r1/src", i), reliable=True)
        with pytest.raises(TransportError, match="no reliable output"):
            src.publish(msg("stray/src", 0), reliable=True)  # routed nowhere: an error, not a drop
        assert src.flush(10.0)
    finally:
        stop.set()
        for th in threads:
            th.join(10)
        src.close()
    kf = [f"keyframe/src:{i}" for i in range(40)]
    rr = [f"render_reply/r1/src:{i}" for i in range(0, 40, 4)]
    assert [x for x in logs["r1"] if x.startswith("keyframe")] == kf  # in order, complete
    assert [x for x in logs["r1"] if x.startswith("render_reply")] == rr
    assert logs["r2"] == kf  # output a only
    assert logs["r3"] == rr  # output b only
