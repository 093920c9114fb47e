"""When each node of a graph is busy, and with what: spans written by the nodes, CPU sampled by
the launcher, both as JSON lines in one folder.

A node process records a span around every handler call (labelled by the message type) and
around the work it does between messages (fine-tuning slices, distillation passes), when the
launcher set ``GSFIX_TIMELINE_DIR`` for it. Spans of one label that follow each other within
``merge_gap_s`` are merged, so a node mapping 200 frames writes a few lines, not 200. The
launcher samples each node's CPU time (user + system, children excluded) once a second into
``cpu.jsonl`` of the same folder. :mod:`gsfix_online.jobs.timeline` draws the chart.

Lines: ``{"node": str, "label": str, "t0": s, "t1": s}`` in ``<node>.jsonl`` (wall-clock
seconds since the epoch, so processes agree), ``{"t": s, "cpu_s": {node: s}}`` in ``cpu.jsonl``.
"""

from __future__ import annotations

import atexit
import json
import logging
import os
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

logger = logging.getLogger(__name__)

ENV_DIR = "GSFIX_TIMELINE_DIR"  # set by the launcher for the processes it starts
CPU_FILE = "cpu.jsonl"


class Timeline:
    """Busy spans of one node, appended to ``<folder>/<node>.jsonl``; ``clock`` is wall seconds."""

    def __init__(
        self,
        node: str,
        folder: str | os.PathLike[str],
        clock: Callable[[], float] = time.time,
        merge_gap_s: float = 0.25,  # spans of one label closer than this become one
        min_span_s: float = 0.002,  # shorter ``span`` blocks (work with nothing to do) are not busy
        flush_every_s: float = 5.0,  # a killed node loses at most this much of its timeline
    ) -> None:
        self.node = node
        self.path = Path(folder) / f"{node}.jsonl"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.clock = clock
        self.merge_gap_s = merge_gap_s
        self.min_span_s = min_span_s
        self.flush_every_s = flush_every_s
        self._open: list[float | str] | None = None  # [label, t0, t1] not yet written
        self._lines: list[str] = []
        self._flushed_at = clock()

    @classmethod
    def from_env(cls, node: str) -> Timeline | None:
        """The node's timeline if the launcher asked for one (``GSFIX_TIMELINE_DIR``)."""
        folder = os.environ.get(ENV_DIR, "")
        if not folder:
            return None
        timeline = cls(node, folder)
        atexit.register(timeline.close)  # a node stopped by SIGTERM returns; its exit runs this
        return timeline

    def add(self, label: str, t0: float, t1: float) -> None:
        """Record that the node was busy with ``label`` from ``t0`` to ``t1`` (wall seconds)."""
        o = self._open
        if o is not None and o[0] == label and t0 - float(o[2]) <= self.merge_gap_s:
            o[2] = max(float(o[2]), t1)
        else:
            self._close_open()
            self._open = [label, t0, t1]
        if t1 - self._flushed_at >= self.flush_every_s:
            self.flush()

    @contextmanager
    def span(self, label: str) -> Iterator[None]:
        """Record the block as busy, unless it took under ``min_span_s``: the work a loop calls
        after every poll returns at once when there is none, and that is idle time."""
        t0 = self.clock()
        try:
            yield
        finally:
            t1 = self.clock()
            if t1 - t0 >= self.min_span_s:
                self.add(label, t0, t1)

    def _close_open(self) -> None:
        if self._open is not None:
            label, t0, t1 = self._open
            rec = {"node": self.node, "label": label, "t0": round(float(t0), 4)}
            rec["t1"] = round(float(t1), 4)
            self._lines.append(json.dumps(rec))
            self._open = None

    def flush(self, final: bool = False) -> None:
        """Append the closed spans (and with ``final`` the open one) to the file."""
        if final:
            self._close_open()
        self._flushed_at = self.clock()
        if not self._lines:
            return
        try:
            with self.path.open("a") as fh:
                fh.write("\n".join(self._lines) + "\n")
        except OSError as exc:  # the timeline is a diagnostic: never stop a node for it
            logger.warning("%s: cannot write its timeline %s: %s", self.node, self.path, exc)
        self._lines.clear()

    def close(self) -> None:
        self.flush(final=True)


def append_cpu_sample(folder: Path, t: float, cpu_s: Mapping[str, float]) -> None:
    """One line of ``cpu.jsonl``: each node's CPU seconds so far, at wall time ``t``."""
    line = json.dumps({"t": round(t, 3), "cpu_s": {k: round(v, 3) for k, v in cpu_s.items()}})
    with (folder / CPU_FILE).open("a") as fh:
        fh.write(line + "\n")


def read_folder(folder: Path) -> tuple[list[dict], list[dict]]:
    """(spans, cpu samples) of a timeline folder; a damaged last line (a killed node) is skipped."""
    spans: list[dict] = []
    cpu: list[dict] = []
    for path in sorted(folder.glob("*.jsonl")):
        rows = cpu if path.name == CPU_FILE else spans
        for line in path.read_text().splitlines():
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                logger.warning("%s: skipping a damaged line", path)
    return spans, cpu


def summarize(spans: list[dict], cpu: list[dict]) -> dict:
    """Per node: busy seconds (spans, overlaps counted once), busy seconds per label, CPU
    seconds (its last sample); the run's start, end and wall seconds."""
    times = [s["t0"] for s in spans] + [c["t"] for c in cpu]
    ends = [s["t1"] for s in spans] + [c["t"] for c in cpu]
    if not times:
        return {"t_start": 0.0, "t_end": 0.0, "wall_s": 0.0, "nodes": {}}
    t_start, t_end = min(times), max(ends)
    nodes: dict[str, dict] = {}
    by_node: dict[str, list[dict]] = {}
    for s in spans:
        by_node.setdefault(s["node"], []).append(s)
    for name, rows in by_node.items():
        labels: dict[str, float] = {}
        for s in rows:
            labels[s["label"]] = labels.get(s["label"], 0.0) + s["t1"] - s["t0"]
        busy, end = 0.0, -float("inf")  # union of the spans
        for s in sorted(rows, key=lambda r: r["t0"]):
            lo = max(s["t0"], end)
            if s["t1"] > lo:
                busy += s["t1"] - lo
            end = max(end, s["t1"])
        nodes[name] = {
            "busy_s": round(busy, 2),
            "labels_s": {k: round(v, 2) for k, v in labels.items()},
        }
    last: dict[str, float] = {}  # a node's last reading (one that exited is in earlier samples)
    for c in cpu:
        last.update(c["cpu_s"])
    for name, sec in last.items():
        nodes.setdefault(name, {"busy_s": 0.0, "labels_s": {}})["cpu_s"] = round(sec, 2)
    wall = t_end - t_start
    return {"t_start": t_start, "t_end": t_end, "wall_s": round(wall, 2), "nodes": nodes}
