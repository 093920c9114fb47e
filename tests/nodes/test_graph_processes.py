"""A real multi-process graph: replay -> monitor over ipc and tcp, reliable, every frame arrives."""

from __future__ import annotations

import io
import json
import socket

import pytest
import yaml

from gsfix_online.core.types import make_frame
from gsfix_online.runtime.graph import load_graph
from gsfix_online.runtime.launcher import Launcher, node_import_env
from gsfix_online.runtime.timeline import read_folder
from gsfix_online.sources.mcap_log import write_mcap
from tests.conftest import make_frames

N = 300


def free_port_base(n: int = 4) -> int:
    """A base port with n free ports after it (probed on loopback)."""
    for _ in range(50):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            base = s.getsockname()[1]
        if base + n >= 65000:
            continue
        try:
            for p in range(base, base + n):
                with socket.socket() as s:
                    s.bind(("127.0.0.1", p))
            return base
        except OSError:
            continue
    raise RuntimeError("no free ports")


@pytest.fixture(scope="module")
def log_300(tmp_path_factory):
    path = tmp_path_factory.mktemp("log") / "log.mcap"
    base = make_frames(n=4, width=64, height=48)
    frames = (
        make_frame(f.color, f.depth, f.intrinsics, f.T_world_cam, (i + 1) * 100_000_000, seq=i)
        for i in range(N)
        for f in [base[i % 4]]
    )
    write_mcap(path, frames)
    return path


def graph_yaml(tmp_path, log, transport: str) -> str:
    graph = {
        "name": f"t-{transport}",
        "transport": transport,
        "port_base": free_port_base(),
        "nodes": {
            "replay": {
                "kind": "replay",
                "restart": "never",
                "outputs": {"frames": "reliable"},
                "params": {"source": {"path": str(log)}, "replay": {"mode": "max"}},
            },
            "monitor": {
                "kind": "monitor",
                "restart": "never",
                "inputs": ["replay/frames"],
                "params": {"stop_after": N, "report": str(tmp_path / "report.json")},
            },
        },
    }
    path = tmp_path / "graph.yaml"
    path.write_text(yaml.safe_dump(graph))
    return path


@pytest.mark.parametrize("transport", ["ipc", "tcp"])
def test_replay_graph_delivers_every_frame(tmp_path, log_300, transport):
    graph = load_graph(graph_yaml(tmp_path, log_300, transport))
    out = io.StringIO()
    profile = tmp_path / "profile" if transport == "ipc" else None
    launcher = Launcher(graph, out=out, timeline_dir=tmp_path / "timeline", cpu_sample_s=0.2,
                        profile_dir=profile)  # fmt: skip
    rc = launcher.run(timeout_s=120)
    logs = out.getvalue()
    assert rc == 0, logs[-3000:]
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["frames"] == N and report["by_topic"] == {"rgbd/cam0": N}, logs[-2000:]
    assert report["seq_gaps"] == 0 and report["stamp_backwards"] == 0 and report["invalid"] == 0
    expected = sum(int((f.depth > 0).sum()) for f in make_frames(n=4, width=64, height=48)) * N // 4
    assert report["valid_depth_pixels"] == expected  # content arrived intact
    assert "[replay]" in logs and "[monitor]" in logs  # log lines carry the node name
    # the timeline: the monitor's handler spans, written by the node process at exit, and the
    # launcher's CPU samples of both processes, growing
    spans, cpu = read_folder(tmp_path / "timeline")
    mine = [s for s in spans if s["node"] == "monitor"]
    assert {s["label"] for s in mine} == {"rgbd"}, spans
    assert all(s["t1"] >= s["t0"] for s in mine)
    assert {n for c in cpu for n in c["cpu_s"]} == {"replay", "monitor"}
    assert [c["t"] for c in cpu] == sorted(c["t"] for c in cpu)
    replay_cpu = [c["cpu_s"]["replay"] for c in cpu if "replay" in c["cpu_s"]]
    assert replay_cpu == sorted(replay_cpu) and replay_cpu[-1] > 0.1  # python starting is > 0.1 s
    if profile is not None:  # each node's call tree, written when it ended
        assert "spin_once" in (profile / "monitor.txt").read_text()
        assert "run_source" in (profile / "replay.txt").read_text()
        assert (profile / "monitor.html").stat().st_size > 1000


def test_nodes_import_the_package_this_process_runs_not_one_in_the_working_directory(
    tmp_path, log_300, monkeypatch
):
    """A graph started inside a folder that holds other `gsfix_online` and `nodes` packages (a
    checkout of another version) runs the same code in its node processes as in the launcher."""
    cwd = tmp_path / "checkout"
    for pkg in ("gsfix_online", "nodes"):
        (cwd / pkg).mkdir(parents=True)
        (cwd / pkg / "__init__.py").write_text("raise ImportError('the checkout in the cwd')\n")
    monkeypatch.chdir(cwd)
    out = io.StringIO()
    rc = Launcher(load_graph(graph_yaml(tmp_path, log_300, "ipc")), out=out).run(timeout_s=120)
    logs = out.getvalue()
    assert rc == 0 and "the checkout in the cwd" not in logs, logs[-3000:]
    assert json.loads((tmp_path / "report.json").read_text())["frames"] == N


def test_node_processes_import_from_where_this_process_did():
    """Without the working directory on their path, nodes still find the package this process
    imported: a source tree's or an editable install's folder goes first on PYTHONPATH (the
    test suite runs from one), other entries kept after it."""
    import os
    from pathlib import Path

    import gsfix_online

    root = str(Path(gsfix_online.__file__).resolve().parents[1])
    env = node_import_env({"PYTHONPATH": "/elsewhere"})
    assert env["PYTHONSAFEPATH"] == "1"
    assert env["PYTHONPATH"].split(os.pathsep) == [root, "/elsewhere"]
    assert node_import_env({})["PYTHONPATH"] == root
