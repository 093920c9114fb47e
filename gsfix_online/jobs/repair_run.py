"""``gsfix-online repair``: the repair graph run offline over a recorded input, as real processes.

This is process code (the outer layer, like the CLI): it checks the input and the view list,
fills the graph YAML's paths, launches the nodes with the launcher and supervises them until the
writer node has written the outputs (see :mod:`gsfix_online.repair.outputs` for the layout).
A node that exits with an error stops the run with a message naming it; so does ``timeout_s``.

The planner's gate waits until both maps have integrated every frame of the input, so every view
is scored and repaired on the finished map, as a user running it after a survey expects.
"""

from __future__ import annotations

import copy
import logging
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import yaml

from gsfix_online.core.config import (
    ConfigError,
    build,
    configs_dir,
    deep_merge,
    gather,
    read_yaml,
    to_dict,
)
from gsfix_online.core.io import atomic_write_bytes, atomic_write_text

if TYPE_CHECKING:
    from gsfix_online.core.progress import Progress

logger = logging.getLogger(__name__)

DEFAULT_GRAPH = configs_dir() / "graphs" / "repair.yaml"
WRITER, REPLAY, PLANNER = "writer", "replay", "planner"


@dataclass(frozen=True)
class InputInfo:
    format: str
    frames: int  # frames the reader yields
    width: int  # the processing resolution (source.max_width), what the maps and views use
    height: int
    held_out: int = 0  # of them kept out of mapping and fine-tuning (--holdout)
    camera_width: int = 0  # the camera's own resolution, as the input holds it; 0 = width
    camera_height: int = 0

    @property
    def camera_size(self) -> tuple[int, int]:
        return (self.camera_width or self.width, self.camera_height or self.height)

    @property
    def mapped(self) -> int:
        return self.frames - self.held_out


@dataclass(frozen=True)
class RepairResult:
    returncode: int
    metrics: dict[str, Any] | None
    seconds: float
    message: str


def _set(d: dict[str, Any], dotted: str, value: Any) -> None:
    keys = dotted.split(".")
    for k in keys[:-1]:
        d = d.setdefault(k, {})
        if not isinstance(d, dict):
            raise ConfigError(f"override {dotted!r}: {k} is not a section")
    d[keys[-1]] = value


def apply_overrides(graph: dict[str, Any], overrides: list[str]) -> None:
    """``NODE.KEY=VALUE`` sets ``nodes.NODE.params.KEY`` (VALUE parsed as YAML); ``fixer.KEY``,
    ``source.KEY`` and ``replay.KEY`` set that section of every node that has it
    (:func:`gsfix_online.runtime.graph.apply_settings`)."""
    from gsfix_online.runtime.graph import apply_settings

    apply_settings(graph, *gather(None, overrides))


def inspect_input(
    source_params: dict[str, Any], holdout_every: int = 0, holdout_dir: Path | None = None
) -> InputInfo:
    """Read the input once through its reader: format, frame count, camera size and processing
    size. With ``holdout_every`` K, the frames replay will hold out (:func:`~gsfix_online.
    sources.replay.is_held_out`) are written to ``holdout_dir``: ``views.txt`` (their poses, a
    TUM list) and ``gt/NNN.png`` (their images at the processing resolution, as the reader
    yields them: the ground truth of those views)."""
    from gsfix_online.core.se3 import pose_to_tq
    from gsfix_online.repair.outputs import write_png
    from gsfix_online.sources import SourceConfig, open_source
    from gsfix_online.sources.replay import is_held_out

    cfg = build(SourceConfig, base=source_params)
    reader = open_source(cfg)
    n, first, lines = 0, None, []
    for frame in reader:
        first = first or frame
        if is_held_out(n, holdout_every):
            assert holdout_dir is not None
            t, q = pose_to_tq(frame.T_world_cam)
            vals = [frame.stamp_ns * 1e-9, *t, *q]
            lines.append(" ".join(f"{v:.9f}" for v in vals))
            write_png(holdout_dir / "gt" / f"{len(lines) - 1:03d}.png", frame.color)
        n += 1
    if first is None:
        raise ConfigError(f"input {cfg.path} ({reader.format}) holds no usable frames")
    if holdout_every and (not lines or len(lines) == n):
        raise ConfigError(
            f"--holdout {holdout_every} keeps {len(lines)} of {n} frames out: choose K so that "
            "some frames are held out and some mapped"
        )
    if lines:
        assert holdout_dir is not None
        header = "# held-out input frames: timestamp tx ty tz qx qy qz qw (camera-to-world)\n"
        atomic_write_text(holdout_dir / "views.txt", header + "\n".join(lines) + "\n")
    w, h = first.intrinsics.width, first.intrinsics.height
    cam = reader.camera or first.intrinsics
    return InputInfo(reader.format, n, w, h, len(lines), cam.width, cam.height)


def views_camera_at(planner_params: dict[str, Any], max_width: int) -> None:
    """Scale the planner's ``camera`` (the views' intrinsics, when the user gives them) to the
    processing resolution, by the rule the readers resize frames with (:mod:`~gsfix_online.
    sources.resolution`): a camera wider than ``max_width`` is scaled down to it."""
    from gsfix_online.core.types import Intrinsics
    from gsfix_online.sources.resolution import processing_size

    cam = planner_params.get("camera") or {}
    if not cam.get("fx", 0) > 0 or not max_width:
        return
    k = Intrinsics(*(float(cam.get(key, 0.0)) for key in ("fx", "fy", "cx", "cy")),
                   int(cam.get("width", 0)), int(cam.get("height", 0)))  # fmt: skip
    w, h = processing_size(k.width, k.height, max_width)
    if (w, h) != (k.width, k.height):
        s = k.scaled(w, h)
        planner_params["camera"] = {**cam, "fx": s.fx, "fy": s.fy, "cx": s.cx, "cy": s.cy,
                                    "width": w, "height": h}  # fmt: skip


def merge_views(
    work: Path, views: Path | None, views_gt: Path | None, holdout: Path
) -> tuple[Path, Path | None, int]:
    """One view list: the user's views (0..n-1), then the held-out frames (n..); one ground-truth
    folder with links to both. Returns (views file, ground-truth folder, n)."""
    from gsfix_online.repair.views import read_views

    n = len(read_views(views)) if views is not None else 0
    lines = holdout.joinpath("views.txt").read_text().splitlines()
    if views is not None:
        lines = views.read_text().splitlines() + lines
    merged = work / "views.txt"
    atomic_write_text(merged, "\n".join(lines) + "\n")
    gt = work / "gt"
    gt.mkdir(parents=True, exist_ok=True)
    for f in gt.glob("*.png"):
        f.unlink()
    if views_gt is not None:
        for i in range(n):
            src = views_gt / f"{i:03d}.png"
            if src.is_file():
                (gt / src.name).symlink_to(src.resolve())
    for src in sorted(holdout.joinpath("gt").glob("*.png")):
        (gt / f"{n + int(src.stem):03d}.png").symlink_to(src.resolve())
    return merged, gt, n


def prepare(
    src: str | Path,
    views: str | Path | None,
    out: str | Path,
    views_gt: str | Path | None = None,
    graph_path: str | Path = DEFAULT_GRAPH,
    overrides: list[str] | None = None,
    source_format: str | None = None,
    holdout: int = 0,
    files: list[str | Path] | None = None,
    settings: tuple[dict[str, Any], dict[str, str]] | None = None,
) -> tuple[Path, InputInfo, int]:
    """Check the inputs, fill the graph and write it to ``OUT/work/graph.yaml``, every node's
    params in full: what each node runs with.

    ``settings`` (:func:`~gsfix_online.core.config.gather`'s pair), then ``files`` (``-c``),
    then ``overrides`` are the user's settings (:func:`gsfix_online.runtime.graph.
    apply_settings`); they may change any node param but the path of the input.
    With ``holdout`` K, every K-th input frame is kept out of mapping and fine-tuning and
    becomes a view to score (after the views of ``views``, which may then be None).
    Returns (that file, what the input holds, the number of views)."""
    from gsfix_online.repair.views import read_views
    from gsfix_online.runtime.graph import apply_settings, parse_graph, resolved

    out = Path(out).resolve()
    work = out / "work"
    # 1. A fresh folder (the trainer would resume an earlier run's state), the views, the ground truth
    if (work / "checkpoints" / "latest").exists():
        raise ConfigError(
            f"{out} holds an earlier run's fine-tuning state ({work / 'checkpoints'}): "
            "choose a new --out folder or delete that one"
        )
    if views is None and not holdout:
        raise ConfigError("give --views VIEWS.txt, --holdout K, or both")
    n_views = len(read_views(views)) if views is not None else 0
    if views_gt is not None and not Path(views_gt).is_dir():
        raise ConfigError(f"--views-gt {views_gt} is not a folder (expected NNN.png images)")
    # 2. The graph with this run's paths, then the user's overrides
    graph = read_yaml(graph_path)
    raw = copy.deepcopy(graph)
    nodes = raw.get("nodes") or {}
    for name in (REPLAY, PLANNER, WRITER):
        if name not in nodes:
            raise ConfigError(f"{graph_path}: the repair graph needs a node named {name!r}")
    wp = nodes[WRITER].setdefault("params", {})
    wp.update({"out_dir": str(out), "gt_dir": str(Path(views_gt).resolve()) if views_gt else ""})
    if holdout:
        rp = nodes[REPLAY]["params"]
        rp["replay"] = {**(rp.get("replay") or {}), "holdout_every": int(holdout)}
    if "tsdf" in nodes:
        nodes["tsdf"].setdefault("params", {})["mesh_dir"] = str(work / "mesh")
    for name in ("tsdf", "splat"):  # the writer's mesh and map requests name files in DIR
        if name in nodes:
            nodes[name].setdefault("params", {}).setdefault("write_root", str(out))
    if "trainer" in nodes:
        tp = nodes["trainer"].setdefault("params", {})
        tp["checkpoint_dir"] = str(work / "checkpoints")
        tp["keyframe_dir"] = tp.get("keyframe_dir") or str(work / "keyframes")
    if "splat" in nodes:  # a restarted splat node resumes from it (restart: on-failure)
        sp = nodes["splat"].setdefault("params", {})
        sp["snapshot"] = sp.get("snapshot") or str(work / "map.pt")
    given, origins = copy.deepcopy(settings) if settings is not None else ({}, {})
    more, more_origins = gather(files, overrides)
    deep_merge(given, more)
    origins.update(more_origins)
    apply_settings(raw, given, origins, where=str(graph_path))
    for key in ("source.path", "replay.source.path"):
        if key in origins:
            raise ConfigError(f"{origins[key]}: the input is --input SRC, not {key}")
    src_params = {"path": str(Path(src).resolve())}
    if source_format:
        src_params["format"] = source_format
    _set(nodes[REPLAY].setdefault("params", {}), "source", {
        **(nodes[REPLAY]["params"].get("source") or {}), **src_params})  # fmt: skip
    # 3. The input, read once through its reader (fails here, not in a child process); the
    #    held-out frames become views after the user's
    info = inspect_input(nodes[REPLAY]["params"]["source"], holdout, work / "holdout")
    views_file = Path(views).resolve() if views is not None else None
    if info.held_out:
        gt = Path(views_gt) if views_gt is not None else None
        views_file, gt_dir, _ = merge_views(work, views_file, gt, work / "holdout")
        wp["gt_dir"] = str(gt_dir)
        wp["holdout_views"] = [n_views, n_views + info.held_out]
        if "repair" in nodes:  # the choice per region is measured on the held-out frames
            rp = nodes["repair"].setdefault("params", {})
            rp.update({"gt_dir": str(gt_dir), "holdout_views": wp["holdout_views"]})
        n_views += info.held_out
    assert views_file is not None
    _set(nodes[PLANNER].setdefault("params", {}), "views", str(views_file))
    # 4. The processing resolution: a camera given for the views is scaled as the frames are;
    #    the writer learns both sizes (its upsample_to_camera option)
    views_camera_at(nodes[PLANNER]["params"], int(nodes[REPLAY]["params"]["source"].get(
        "max_width", 0)))  # fmt: skip
    wp["camera_size"] = list(info.camera_size)
    wp["processing_size"] = [info.width, info.height]
    wp["expected_views"] = n_views
    pacing = nodes[PLANNER]["params"].setdefault("pacing", {})
    pacing["min_frames"] = info.mapped  # score on the finished maps
    if "samples" in (nodes.get("splat") or {}).get("outputs", {}):  # its end starts training
        nodes["splat"].setdefault("params", {})["input_frames"] = info.mapped
    for node in nodes.values():  # the last frame announces a mesh of every frame (the trainer's)
        if node.get("kind") == "tsdf":
            node.setdefault("params", {})["input_frames"] = info.mapped
    raw["run_dir"] = ""
    path = work / "graph.yaml"
    graph = resolved(parse_graph(raw, graph_path))
    atomic_write_text(path, yaml.safe_dump(to_dict(graph), sort_keys=False))
    return path, info, n_views


class _Tee:
    def __init__(self, *streams: TextIO) -> None:
        self.streams = streams

    def write(self, s: str) -> int:
        for st in self.streams:
            st.write(s)
        return len(s)

    def flush(self) -> None:
        for st in self.streams:
            st.flush()


def show_progress(progress: Progress, path: Path) -> None:
    """Show the writer's ``progress.json`` (if there is one yet): views decided of all the views
    the run will handle (the planner's proposals included), repairs, what it waits for."""
    import json

    try:
        p = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):  # not written yet
        progress.tick()
        return
    text = (f"{p['repaired']}/{p['accepted']} repaired, {p['distilled']} distilled, "
            f"{p['final']} final; {p['phase']}")  # fmt: skip
    progress.set(p["decided"], p["views"] or None, text, p["waiting"])


def write_timeline(folder: Path, out: Path) -> dict[str, Any] | None:
    """Draw the run's timeline (``out/timeline.png``, and into ``out/report.html``) and write
    its summary (``out/timeline.json``: per node busy and CPU seconds); None when no node
    recorded one."""
    import json

    from gsfix_online.core import pages
    from gsfix_online.repair.outputs import TIMELINE_PNG
    from gsfix_online.runtime.timeline import read_folder, summarize

    if not folder.is_dir():
        return None
    spans, cpu = read_folder(folder)
    if not spans and not cpu:
        return None
    summary = summarize(spans, cpu)
    cores = summary["cores"] = os.cpu_count() or 1
    cpu_s = sum(n.get("cpu_s", 0.0) for n in summary["nodes"].values())
    png = pages.figure_png(pages.timeline_figure(spans, cpu, (cpu_s, cores)))
    atomic_write_bytes(out / TIMELINE_PNG, png)
    atomic_write_text(out / "timeline.json", json.dumps(summary, indent=1) + "\n")
    report = out / "report.html"
    if report.is_file():  # absent when the writer did not finish
        pages.add_plot(report, pages.Plot("Timeline: what each node did, and its CPU use", png))
    return summary


def run_graph(
    graph_file: Path,
    log: TextIO | None = None,
    timeout_s: float | None = None,
    grace_s: float = 30.0,  # SIGTERM -> SIGKILL; generous: a busy 2-core machine stops slowly
    progress: Progress | None = None,  # views decided of all views; node lines go through it
    profile: bool = False,  # each node profiles itself into OUT/work/profile (pyinstrument)
) -> RepairResult:
    """Launch the graph, wait for the writer; stop everything; the writer's metrics."""
    import json

    from gsfix_online.runtime.graph import load_graph
    from gsfix_online.runtime.launcher import Launcher

    graph = load_graph(graph_file)
    out = Path(graph.nodes[WRITER].params["out_dir"])
    log_path = graph_file.with_name("graph.log")
    timeline_dir = graph_file.with_name("timeline")  # this run's spans only
    shutil.rmtree(timeline_dir, ignore_errors=True)
    if log is None:
        log = progress.lines() if progress is not None else sys.stdout  # type: ignore[assignment]
    t0 = time.monotonic()
    next_show = t0
    with log_path.open("w") as fh:
        profile_dir = graph_file.with_name("profile") if profile else None
        launcher = Launcher(graph, out=_Tee(fh, log), grace_s=grace_s,  # type: ignore[arg-type]
                            timeline_dir=timeline_dir, profile_dir=profile_dir)  # fmt: skip
        failed: list[str] = []

        def until() -> bool:
            nonlocal next_show
            if progress is not None and time.monotonic() >= next_show:
                next_show = time.monotonic() + 1.0
                show_progress(progress, out / "work" / "progress.json")
            for name, p in launcher.procs.items():
                if p.done and p.returncode != 0 and name not in failed:
                    failed.append(name)
            w = launcher.procs.get(WRITER)
            return bool(failed) or (w is not None and w.done)

        launcher.run(until=until, timeout_s=timeout_s)
    if progress is not None:
        show_progress(progress, out / "work" / "progress.json")
    seconds = time.monotonic() - t0
    write_timeline(timeline_dir, out)
    w = launcher.procs[WRITER]
    metrics_path = out / "metrics.json"
    if failed:
        codes = ", ".join(f"{n} (exit {launcher.procs[n].returncode})" for n in failed)
        msg = f"node {codes} died; see its [{failed[0]}] lines in {log_path}"
        return RepairResult(1, None, seconds, msg)
    if not (w.done and w.returncode == 0 and metrics_path.is_file()):
        why = f"did not finish within {timeout_s:.0f} s" if timeout_s else "stopped early"
        msg = f"{why}; node logs in {log_path}"
        return RepairResult(1, None, seconds, msg)
    metrics = json.loads(metrics_path.read_text())
    return RepairResult(0, metrics, seconds, f"-> {out}")
