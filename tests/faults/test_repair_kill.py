"""A repair run whose splat node and trainer are killed (kill -9) while it runs still finishes
with every view: the launcher restarts both (``restart: on-failure`` in the repair graph), the
splat node resumes from DIR/work/map.pt and the trainer restores DIR/work/keyframes.

The whole repair graph as processes on the tiny tank of the repair command test: slow on 2
cores (about 2 minutes), so it runs with ``pytest -m slow tests/faults``.
"""

from __future__ import annotations

import io
import json
import os
import signal
import threading
import time
from pathlib import Path

import pytest

from gsfix_online.jobs.repair_run import prepare, run_graph
from tests.jobs.test_repair_run import EAGER, FAST, tank  # noqa: F401  (the fixture)


def _child(name: str) -> int | None:
    """The pid of this process's child that runs node ``name``, if any."""
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            cmd = (d / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        if ppid == os.getpid() and b"node" in cmd and name.encode() in cmd:
            return int(d.name)
    return None


def _killer(work: Path, killed: list[str], stop: threading.Event) -> None:
    """kill -9 the splat node once it has a snapshot, the trainer once it holds keyframes."""
    due = {"splat": lambda: (work / "map.pt").is_file(),
           "trainer": lambda: any((work / "keyframes").glob("kf_*.npz"))}  # fmt: skip
    while due and not stop.is_set():
        for name, ready in list(due.items()):
            pid = _child(name) if ready() else None
            if pid is not None:
                os.kill(pid, signal.SIGKILL)
                killed.append(name)
                del due[name]
        time.sleep(0.1)


@pytest.mark.slow
def test_a_repair_run_whose_splat_node_and_trainer_are_killed_finishes_every_view(
    tank: Path,  # noqa: F811
    tmp_path: Path,
) -> None:
    out = tmp_path / "run"
    over = [*FAST, *EAGER, "splat.snapshot_every=2"]
    graph, _, n = prepare(tank / "log.mcap", tank / "views3.txt", out, overrides=over)
    killed: list[str] = []
    stop = threading.Event()
    th = threading.Thread(target=_killer, args=(out / "work", killed, stop), daemon=True)
    th.start()
    log = io.StringIO()
    try:
        res = run_graph(graph, log=log, timeout_s=400)
    finally:
        stop.set()
        th.join(5)
    logs = log.getvalue()
    assert sorted(killed) == ["splat", "trainer"], logs[-4000:]
    assert res.returncode == 0, res.message + logs[-4000:]
    assert "resumed from" in logs and "restored" in logs, logs[-4000:]
    m = json.loads((out / "metrics.json").read_text())
    views = {v["view"]: v for v in m["views"]}
    assert sorted(views) == ["000", "001", "002"] and n == 3
    for name in views:
        d = out / "views" / name
        assert (d / "gs.png").is_file() and (d / "final.png").is_file(), name
