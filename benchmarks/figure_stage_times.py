"""A bar per stage of a run's wall time: the picture of the stage table a run prints.

Reads a demo's ``summary.json`` (``outputs/demo``, or a copy such as
``benchmarks/results/one_house_demo_wheel_cpu.json``) or a repair run's ``metrics.json`` (its run
folder). Stages that ran one after the other are dark bars; the per-view stages inside the repair
graph (render, score, GSFixer, Telea, distillation) are light bars, their seconds summed over the
views (they overlap the graph's wall time and each other's nodes).

    .venv/bin/python benchmarks/figure_stage_times.py benchmarks/results/one_house_demo_wheel_cpu.json \
        --out docs/demo_stage_times.png
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

# the per-view stage keys of metrics.json and what a reader calls them
NAMES = {
    "render_s": "render views",
    "score_s": "score views",
    "fix_s": "GSFixer",
    "inpaint_fsr_s": "FSR baseline",
    "distill_s": "distil views",
    "collect_s": "collect (graph)",
    "distill_passes_s": "distillation passes",
    "final_s": "final renders",
    "mesh_s": "mesh renders",
    "export_s": "exports",
}


def stage_rows(data: dict[str, Any]) -> list[tuple[str, float, bool]]:
    """(stage, seconds, summed over views) from a demo summary or a run's metrics."""
    rows: list[tuple[str, float, bool]] = []
    if "stages" in data and isinstance(data["stages"], list):  # a demo's summary.json
        for row in data["stages"]:
            summed = row["stage"].startswith(" ")
            name = row["stage"].strip()
            rows.append((NAMES.get(name, name), float(row["seconds"]), summed))
    else:  # a repair run's metrics.json
        for name, s in (data.get("timings_s") or {}).items():
            rows.append((NAMES.get(name, name), float(s), False))
        for name, s in data["summary"].get("stage_time_totals_s", {}).items():
            rows.append((NAMES.get(name, name), float(s), True))
    return [(n, s, summed) for n, s, summed in rows if math.isfinite(s)]


def draw(rows: list[tuple[str, float, bool]], title: str) -> Any:  # -> matplotlib Figure
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    fig = Figure(figsize=(7.0, 1.3 + 0.32 * len(rows)), dpi=110, layout="constrained")
    ax = fig.add_subplot()
    colours = ["#9ecae1" if summed else "#3b6fb6" for _, _, summed in rows]
    ax.barh(range(len(rows)), [s for _, s, _ in rows], color=colours)
    ax.set_yticks(range(len(rows)), [n for n, _, _ in rows])
    ax.invert_yaxis()  # in the order the run went
    ax.set_xscale("symlog", linthresh=1.0)  # seconds to many minutes in one picture
    ax.set_xlabel("seconds (log scale above 1 s)")
    ax.set_title(title)
    for i, (_, s, _) in enumerate(rows):
        text = f" {s:.1f} s" if s < 60 else f" {s / 60:.1f} min"
        ax.annotate(text, (s, i), va="center", fontsize=8)
    ax.set_xlim(0, max(s for _, s, _ in rows) * 4)
    fig.legend(
        handles=[
            Patch(color="#3b6fb6", label="wall time"),
            Patch(color="#9ecae1", label="summed over views (inside the repair graph)"),
        ],
        loc="outside lower center", ncols=2, fontsize=8,
    )  # fmt: skip
    return fig


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="summary.json, metrics.json, or a folder holding one")
    ap.add_argument("--out", type=Path, required=True, help="PNG to write")
    ap.add_argument("--title", default="Time per stage")
    args = ap.parse_args(argv)
    path = args.run
    if path.is_dir():
        found = [path / n for n in ("summary.json", "metrics.json") if (path / n).is_file()]
        if not found:
            ap.error(f"{path} holds neither summary.json nor metrics.json")
        path = found[0]
    rows = stage_rows(json.loads(path.read_text()))
    if not rows:
        ap.error(f"{path} has no stage times")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    draw(rows, args.title).savefig(args.out)
    total = sum(s for _, s, summed in rows if not summed)
    print(f"{len(rows)} stages, {total:.0f} s wall -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
