"""Progress: plain periodic lines to a pipe or file, one live line on a terminal."""

from __future__ import annotations

import fcntl
import io
import json
import os
import pty
import struct
import subprocess
import sys
import termios
import textwrap

import pytest

from gsfix_online.core.progress import EVERY_ENV, Progress, default_every_s, track


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_plain_lines_every_period_with_counts_rate_and_wait():
    clock, out = FakeClock(), io.StringIO()
    p = Progress("repair", total=10, unit="view", stream=out, every_s=30.0, clock=clock)
    assert not p.live  # a StringIO is no terminal
    for i in range(1, 7):  # one update every 10 s: lines at 30 s and 60 s only
        clock.t += 10.0
        p.set(i, waiting="the planner's decisions" if i < 6 else "")
    clock.t += 5.0
    p.set(total=12, text="2 distilled")  # proposals raise the total; no line yet (65 s < 90 s)
    p.close()
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue()
    assert lines == [
        "repair: 3/10 views (30 %), 0.10 view/s, 30 s elapsed, about 1 min 10 s left; "
        "waiting for the planner's decisions",
        "repair: 6/10 views (60 %), 0.10 view/s, 1 min 00 s elapsed, about 40 s left",
        "repair: 6/12 views (50 %), 0.09 view/s, 1 min 05 s elapsed, about 1 min 05 s left; "
        "2 distilled (done)",
    ]


def test_tick_prints_while_waiting_and_disabled_prints_nothing():
    clock, out = FakeClock(), io.StringIO()
    p = Progress("pretrain", None, "step", stream=out, every_s=1.0, clock=clock)
    p.set(waiting="a connected splat node")
    clock.t += 1.5
    p.tick()
    assert out.getvalue() == (
        "pretrain: 0 steps, 0.00 step/s, 2 s elapsed; waiting for a connected splat node\n"
    )
    quiet = io.StringIO()
    with Progress("x", 3, stream=quiet, every_s=0.001, enabled=False) as q:
        q.update(3)
    assert quiet.getvalue() == ""


def test_track_counts_items_and_log_lines_pass_through():
    out = io.StringIO()
    got = list(track(range(4), "replay", unit="frame", stream=out, every_s=1e6))
    assert got == [0, 1, 2, 3]
    assert out.getvalue().startswith("replay: 4/4 frames (100 %)")
    assert out.getvalue().endswith("(done)\n")
    p = Progress("graph", stream=out, every_s=1e6)
    sink = p.lines()
    sink.write("[tsdf] first\n[splat] sec")
    sink.write("ond\n")
    assert out.getvalue().splitlines()[-2:] == ["[tsdf] first", "[splat] second"]


def test_every_s_from_environment(monkeypatch):
    monkeypatch.setenv(EVERY_ENV, "5")
    assert default_every_s() == 5.0
    monkeypatch.setenv(EVERY_ENV, "-1")
    with pytest.raises(ValueError, match=r"GSFIX_PROGRESS_EVERY_S must be a positive .*'-1'"):
        default_every_s()
    with pytest.raises(ValueError, match="every_s must be a positive"):
        Progress("x", every_s=0.0)


SCRIPT = textwrap.dedent(
    """
    import logging, sys, time
    from gsfix_online.core.progress import Progress
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    with Progress("steps", total=5, unit="step", every_s=0.01) as p:
        for i in range(1, 6):
            p.set(i, text=f"loss {1.0 / i:.2f}")
            if i == 3:
                p.write("a log line")
                logging.getLogger("x").info("a logging record")
            time.sleep(0.05)
    """
)


def _run(stdout: int, stderr: int) -> subprocess.Popen[bytes]:
    env = {k: v for k, v in os.environ.items() if k != "GSFIX_PROGRESS_EVERY_S"}
    return subprocess.Popen(
        [sys.executable, "-c", SCRIPT], stdout=stdout, stderr=stderr, env=env,
        stdin=subprocess.DEVNULL,
    )  # fmt: skip


def test_pipe_gets_plain_lines_without_carriage_returns():
    proc = _run(subprocess.PIPE, subprocess.STDOUT)
    out, _ = proc.communicate(timeout=60)
    text = out.decode()
    assert proc.returncode == 0
    assert "\r" not in text
    lines = text.splitlines()
    assert "a log line" in lines and "a logging record" in lines
    progress = [ln for ln in lines if ln.startswith("steps: ")]
    assert progress[-1].startswith("steps: 5/5 steps (100 %)") and progress[-1].endswith("(done)")
    assert 2 <= len(progress) <= 6  # every_s = 0.01: a line per update at most


def test_terminal_gets_one_live_line():
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 120, 0, 0))  # 120 columns
    proc = _run(slave, slave)
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 4096)
        except OSError:  # EIO: the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    os.close(master)
    assert proc.wait(timeout=60) == 0
    text = b"".join(chunks).decode(errors="replace")
    assert "\r" in text and "steps" in text and "3/5" in text and "loss 0.33" in text
    # the bar redraws in place: the only line breaks are the two log lines printed above it
    rows = [r for r in text.replace("\r\n", "\n").split("\n") if r.strip("\r ")]
    assert len(rows) == 3, rows
    assert sum("a log line" in r for r in rows) == 1
    assert sum("a logging record" in r for r in rows) == 1
    assert "elapsed" not in text and "(done)" not in text  # no plain lines on a terminal


def test_repair_progress_counts_the_planners_proposed_views(tmp_path):
    """Planner decisions carry how many views it holds (its proposals included); the writer
    waits for all of them and its progress.json is what ``gsfix-online repair`` shows."""
    from gsfix_online.nodes import planner, repair_writer

    from gsfix_online.jobs.repair_run import show_progress
    from gsfix_online.repair.scheduler import PacingPolicy, ProposalPolicy
    from gsfix_online.runtime import InMemoryTransport, NodeRuntimeConfig
    from tests.mapping.splat.test_mapper import H, W
    from tests.nodes.test_repair_nodes import Clock, keyframe_message, reply

    views = tmp_path / "views.txt"
    views.write_text("0 0 0 0 0 0 0 1\n")  # one view from the file
    t, clock = InMemoryTransport(), Clock()
    params = planner.Params(
        views=str(views), pacing=PacingPolicy(min_frames=5),
        proposals=ProposalPolicy(every_keyframes=1, max_proposals=2),
    )  # fmt: skip
    runtime = NodeRuntimeConfig(poll_timeout_ms=0, on_handler_error="raise")
    node, svc = planner.build_node("planner", params, t, runtime, clock)
    kf = keyframe_message()
    t.feed(kf)
    node.run_until_idle()
    assert svc.views_total == 3  # the file's view and two proposals beside the keyframe
    planner.step(node, svc, clock)
    t.feed(reply("planner", "splat", -1, False))
    t.feed(reply("planner", "tsdf", -1, False))
    node.run_until_idle()
    clock.t = 1.0
    planner.step(node, svc, clock)
    t.feed(reply("planner", "splat", 0, holes=True))
    t.feed(reply("planner", "tsdf", 0, holes=False))
    node.run_until_idle()
    decisions = [p.message for p in t.outbox if p.message.topic.startswith("decision/")]
    # the 3DGS and mesh renders, and the keyframe warped into the view (decision/planner/ref)
    assert [d.meta["views_total"] for d in decisions] == [3, 3, 3]

    out = tmp_path / "run"
    writer = repair_writer.WriterService(
        "writer", repair_writer.Params(out_dir=str(out), expected_views=1), 0.0
    )
    for d in decisions:
        writer.on_render_reply(d)
    msgs, finished = writer.work(1.0)
    assert not finished and writer.target_views == 3  # not 1: the proposals count too
    state = json.loads((out / "work" / "progress.json").read_text())
    assert state == {"views": 3, "decided": 1, "accepted": 1, "repaired": 0, "distilled": 0,
                     "final": 0, "phase": "collect", "waiting": "the planner's decisions"}  # fmt: skip
    shown = io.StringIO()
    p = Progress("repair", 1, "view", stream=shown, every_s=1e6)
    show_progress(p, out / "work" / "progress.json")
    assert (p.n, p.total) == (1, 3)
    assert p.line().startswith("repair: 1/3 views (33 %)")
    assert p.line().endswith("0/1 repaired, 0 distilled, 0 final; collect; "
                             "waiting for the planner's decisions")  # fmt: skip
    assert kf.arrays["depth"].shape == (H, W)
