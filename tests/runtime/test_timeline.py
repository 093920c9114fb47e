"""The nodes' busy spans: merging, the file format, the summary, the node's dispatch spans."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from PIL import Image

from gsfix_online.core import pages
from gsfix_online.runtime import InMemoryTransport, Node
from gsfix_online.runtime.timeline import (
    ENV_DIR,
    Timeline,
    append_cpu_sample,
    read_folder,
    summarize,
)
from tests.runtime.samples import rgbd_message, sample_messages


class FakeClock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def test_spans_of_one_label_merge_within_the_gap(tmp_path):
    clock = FakeClock()
    tl = Timeline("splat", tmp_path, clock=clock, merge_gap_s=0.25, min_span_s=0.002)
    tl.add("rgbd", 1000.0, 1000.5)
    tl.add("rgbd", 1000.6, 1001.0)  # 0.1 s later: the same span
    tl.add("rgbd", 1001.0, 1001.001)  # a 1 ms handler call: merged too
    tl.add("distil", 1001.1, 1002.0)  # another label: a new span
    tl.add("rgbd", 1003.0, 1003.5)  # 1 s after the last rgbd: a new span
    tl.close()
    rows = [json.loads(x) for x in (tmp_path / "splat.jsonl").read_text().splitlines()]
    assert [(r["label"], r["t0"], r["t1"]) for r in rows] == [
        ("rgbd", 1000.0, 1001.001),
        ("distil", 1001.1, 1002.0),
        ("rgbd", 1003.0, 1003.5),
    ]
    assert {r["node"] for r in rows} == {"splat"}


def test_closed_spans_are_written_every_flush_period(tmp_path):
    clock = FakeClock()
    tl = Timeline("trainer", tmp_path, clock=clock, flush_every_s=5.0)
    tl.add("fine-tune", 1000.0, 1001.0)
    tl.add("keyframe", 1001.5, 1002.0)
    assert not (tmp_path / "trainer.jsonl").exists()  # nothing before the period
    clock.t = 1006.0
    tl.add("fine-tune", 1005.0, 1006.0)  # ends past the period: the closed spans go out
    assert len((tmp_path / "trainer.jsonl").read_text().splitlines()) == 2
    tl.close()
    assert len((tmp_path / "trainer.jsonl").read_text().splitlines()) == 3


def test_span_context_measures_the_block_and_drops_empty_work(tmp_path):
    clock = FakeClock()
    tl = Timeline("repair", tmp_path, clock=clock, min_span_s=0.002)
    with tl.span("repair"):
        clock.t += 2.5
    with tl.span("plan"):  # a poll with nothing to do: not busy
        clock.t += 0.001
    tl.close()
    (row,) = read_folder(tmp_path)[0]
    assert row["label"] == "repair" and row["t1"] - row["t0"] == pytest.approx(2.5)


def test_from_env_only_when_the_launcher_asked(tmp_path, monkeypatch):
    monkeypatch.delenv(ENV_DIR, raising=False)
    assert Timeline.from_env("tsdf") is None
    monkeypatch.setenv(ENV_DIR, str(tmp_path / "tl"))
    tl = Timeline.from_env("tsdf")
    assert tl is not None and tl.path == tmp_path / "tl" / "tsdf.jsonl"


def test_read_folder_skips_a_damaged_last_line(tmp_path):
    (tmp_path / "a.jsonl").write_text(
        '{"node": "a", "label": "x", "t0": 1, "t1": 2}\n{"node": "a", "lab'
    )
    append_cpu_sample(tmp_path, 3.0, {"a": 0.5})
    spans, cpu = read_folder(tmp_path)
    assert spans == [{"node": "a", "label": "x", "t0": 1, "t1": 2}]
    assert cpu == [{"t": 3.0, "cpu_s": {"a": 0.5}}]


def test_summary_counts_overlapping_spans_once():
    spans = [
        {"node": "splat", "label": "rgbd", "t0": 10.0, "t1": 14.0},
        {"node": "splat", "label": "render_request", "t0": 12.0, "t1": 15.0},  # overlaps 2 s
        {"node": "trainer", "label": "fine-tune", "t0": 11.0, "t1": 20.0},
    ]
    cpu = [{"t": 10.0, "cpu_s": {"splat": 0.0}}, {"t": 21.0, "cpu_s": {"splat": 4.5, "trainer": 8}}]
    s = summarize(spans, cpu)
    assert s["wall_s"] == 11.0 and s["t_start"] == 10.0
    assert s["nodes"]["splat"]["busy_s"] == 5.0
    assert s["nodes"]["splat"]["labels_s"] == {"rgbd": 4.0, "render_request": 3.0}
    assert s["nodes"]["splat"]["cpu_s"] == 4.5 and s["nodes"]["trainer"]["cpu_s"] == 8
    assert summarize([], [])["nodes"] == {}


def test_node_records_a_span_per_handled_message_and_its_work(tmp_path):
    tl = Timeline("mapper", tmp_path, merge_gap_s=0.0, min_span_s=0.0)
    t = InMemoryTransport(script=[rgbd_message(0), sample_messages()["pose"]])
    node = Node("mapper", t, {"rgbd": lambda m: None, "pose": lambda m: None}, timeline=tl)
    assert node.run_until_idle() == 2
    with node.span("distil"):
        pass
    tl.close()
    spans, _ = read_folder(tmp_path)
    assert [s["label"] for s in spans] == ["rgbd", "pose", "distil"]


def test_timeline_figure_draws_a_row_per_node():
    spans = [
        {"node": "splat", "label": "rgbd", "t0": 0.0, "t1": 4.0},
        {"node": "trainer", "label": "fine-tune", "t0": 2.0, "t1": 9.0},
    ]
    cpu = [{"t": float(t), "cpu_s": {"splat": 0.9 * t, "trainer": 0.5 * t}} for t in range(10)]
    cpu_s = sum(n["cpu_s"] for n in summarize(spans, cpu)["nodes"].values())
    fig = pages.timeline_figure(spans, cpu, cpu_used=(cpu_s, 2))
    ax = fig.axes[0]
    assert [t.get_text() for t in ax.get_yticklabels()] == ["splat", "trainer"]
    assert "9 s wall; the nodes used 70% of 2 cores" in ax.get_title()  # (8.1 + 4.5) / (9 x 2)
    assert [t.get_text() for t in ax.get_legend().get_texts()] == [
        "map frames",
        "fine-tune GSFixer",
    ]
    png = pages.figure_png(fig)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
    assert img.shape[0] > 100 and img.std() > 10  # bars drawn, not a blank canvas
