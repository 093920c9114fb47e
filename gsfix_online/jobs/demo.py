"""``gsfix-online demo``: the main job on the embedded synthetic ship tank.

1. Generate the scene (TUM folder, MCAP log, ground truth, novel views with their images).
2. Replay the log and the TUM folder through their readers; both must give the same frames.
3. Run the repair graph on the log as real processes (:mod:`gsfix_online.jobs.repair_run`): replay ->
   TSDF and 3DGS in parallel -> keyframes -> background fine-tuning -> planner (the scene's novel
   views plus the planner's own proposals) -> repair -> distillation into the Gaussian map.
4. Draw ``figure.png`` (:mod:`gsfix_online.jobs.figure`): 4 repaired views, each stage
   and baseline beside the ground truth. Print one table per stage and baseline on the novel
   views (PSNR and SSIM against the scene's ground truth) and the time of each stage;
   ``summary.json`` and the report page hold the same.
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gsfix_online.core.io import atomic_write_text
from gsfix_online.jobs.config import Config

logger = logging.getLogger(__name__)


@dataclass
class StageTimes:
    rows: list[tuple[str, float, str]] = field(default_factory=list)  # (stage, seconds, note)

    def add(self, stage: str, seconds: float, note: str = "") -> None:
        self.rows.append((stage, seconds, note))

    def table(self) -> str:
        width = max(len(r[0]) for r in self.rows)
        lines = [
            f"{'stage':<{width}}  {'time':>8}  result",
            f"{'-' * width}  {'-' * 8}  {'-' * 40}",
        ]
        lines += [f"{s:<{width}}  {t:>7.2f}s  {n}" for s, t, n in self.rows]
        return "\n".join(lines)


def _replay(
    path: Path, cfg: Config, progress: bool, desc: str
) -> tuple[list[int], dict[str, int], float]:
    from gsfix_online.core.progress import track
    from gsfix_online.sources import open_source
    from gsfix_online.sources.replay import paced

    reader = open_source(cfg.source, path)
    t0 = time.perf_counter()
    stamps = []
    frames = paced(reader, cfg.replay, time.monotonic, time.sleep)
    for frame in track(frames, desc, len(reader), "frame", enabled=progress):
        stamps.append(frame.stamp_ns)
    return stamps, reader.stats.as_dict(), time.perf_counter() - t0


def run_demo(cfg: Config, out: Path, progress: bool = True, profile: bool = False) -> int:
    """Run the demo into ``out``; prints a table of stages and writes ``summary.json``. Returns 0.
    ``profile``: every node of the repair graph profiles itself (``repair/work/profile/``)."""
    from gsfix_online.core.config import write_config
    from gsfix_online.jobs.config import read_sections
    from gsfix_online.scene import generate_ship_tank
    from gsfix_online.sources.mcap_log import write_mcap

    # 0. The graph's settings checked before the scene is made; the demo's settings beside the
    # outputs (every node's, as it ran: repair/work/graph.yaml)
    check_graph_settings(cfg)
    out.mkdir(parents=True, exist_ok=True)
    write_config(read_sections(cfg, READS), out / "config.yaml")
    times = StageTimes()

    # 1. Generate the scene with its ground truth
    t0 = time.perf_counter()
    scene = generate_ship_tank(cfg.scene, out / "scene", write_mcap=write_mcap)
    cov = np.asarray(scene.novel_coverage, dtype=float)
    cov_note = f"coverage {cov.min():.2f}..{cov.max():.2f}" if len(cov) else "no novel views"
    times.add(
        "scene",
        time.perf_counter() - t0,
        f"{scene.n_frames} frames, {scene.n_novel} novel views ({cov_note})",
    )

    # 2. Replay the MCAP log and the TUM folder; both must give the same frames
    log_stamps, log_stats, dt_log = _replay(
        out / "scene" / "log.mcap", cfg, progress, "replay mcap"
    )
    times.add(
        "replay mcap",
        dt_log,
        f"{len(log_stamps)} frames, {len(log_stamps) / dt_log:.0f} frames/s, {log_stats['depth_pixels_invalidated']} bad depth px",
    )
    tum_stamps, tum_stats, dt_tum = _replay(out / "scene" / "tum", cfg, progress, "replay tum")
    times.add(
        "replay tum", dt_tum, f"{len(tum_stamps)} frames, {len(tum_stamps) / dt_tum:.0f} frames/s"
    )
    if log_stamps != tum_stamps:
        raise RuntimeError(
            f"MCAP log and TUM folder disagree: {len(log_stamps)} vs {len(tum_stamps)} frames"
        )

    # 3. The repair graph on the log, with a progress bar over the views
    metrics, dt_graph, graph_log = _repair_graph(
        out / "scene", out / "repair", cfg, progress, profile
    )
    s = metrics["summary"]
    times.add(
        "repair graph",
        dt_graph,
        f"{s['views']} views: {s['repaired']} repaired, {s['skipped']} skipped; log {graph_log}",
    )
    for stage, seconds in s.get("stage_time_totals_s", {}).items():
        times.add(f"  {stage}", seconds, "summed over views")

    # 4. The figure: the first 4 repaired views, every stage beside the ground truth (a run
    # that repaired none has no figure; its table still says why)
    from gsfix_online.jobs.figure import repaired_views, write_views_figure

    gt_dir = out / "scene" / "novel" / "color"
    fig_views = repaired_views(out / "repair", gt_dir, 4)
    fig_note = "no figure.png (no view was repaired)"
    if fig_views:
        fig_w, fig_h = write_views_figure(
            out / "repair", out / "figure.png", gt_dir, fig_views, scale=0.75
        )
        fig_note = (f"figure.png ({fig_w}x{fig_h}: ground truth, best classical, 3DGS, mesh, "
                    f"GSFixer, output, final map, provenance)")  # fmt: skip

    print(times.table())
    print()
    print(quality_table(s.get("stages", {})))
    summary = {
        "scene": str(out / "scene"),
        "frames": scene.n_frames,
        "novel_views": scene.n_novel,
        "novel_coverage": cov.tolist(),
        "stages": [{"stage": s, "seconds": round(t, 3), "result": n} for s, t, n in times.rows],
        "replay_stats": {"mcap": log_stats, "tum": tum_stats},
        "quality": s.get("stages", {}),
        "repair": {k: v for k, v in s.items() if k != "stages"},
    }
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2))
    print(
        f"outputs in {out}: summary.json, config.yaml, {fig_note}, scene/, repair/ "
        f"(report {out / 'repair' / 'report.html'}, views, map, mesh)"
    )
    return 0


# Rows of the quality table: metrics.json stage -> what the user reads. "fixed_or_gs" is GSFixer on
# every view (a view the planner skipped keeps its 3DGS render), "output_or_gs" the 2D output
# delivered (GSFixer or a fallback per region, repair.fallback), so all rows cover the same views.
QUALITY_ROWS = (
    ("gs", "raw 3DGS render"),
    ("mesh", "TSDF mesh render"),
    ("mesh_fill", "mesh fill (3DGS where alpha is high, else mesh)"),
    ("gs_inpaint", "3DGS + OpenCV Telea inpainting"),
    ("inpaint", "mesh fill + OpenCV Telea inpainting"),
    ("inpaint_ns", "mesh fill + OpenCV Navier-Stokes inpainting"),
    ("inpaint_fsr", "mesh fill + OpenCV FSR inpainting (xphoto)"),
    ("mesh_inpaint", "mesh + OpenCV Telea inpainting"),
    ("ref_warp", "real frames warped by the mesh depth"),
    ("ref_inpaint", "real frames warped + mesh fill + Telea"),
    ("fixed_or_gs", "GSFixer (2D repair)"),
    ("output_or_gs", "2D output (GSFixer or fallback per region)"),
    ("final", "GSFix3D: 3DGS after distillation"),
)


def quality_table(stages: dict[str, dict[str, float]]) -> str:
    """PSNR / SSIM per stage on the novel views, with the gain over the raw 3DGS render."""
    base = stages.get("gs", {}).get("psnr_db")
    lines = [
        f"{'novel views vs ground truth':<50}  {'PSNR dB':>8}  {'vs 3DGS':>8}  {'SSIM':>6}  views",
        f"{'-' * 50}  {'-' * 8}  {'-' * 8}  {'-' * 6}  -----",
    ]
    for key, label in QUALITY_ROWS:
        v = stages.get(key)
        if v is None:
            continue
        gain = f"{v['psnr_db'] - base:+8.2f}" if base is not None else f"{'':>8}"
        lines.append(f"{label:<50}  {v['psnr_db']:8.2f}  {gain}  {v['ssim']:6.3f}  {v['views']:>5}")
    return "\n".join(lines)


# The root sections the demo reads (gsfix_online.jobs.config.Config): the replay of its log (the
# check and the graph's replay node), the scene, GSFixer (the trainer and the repair node) and
# its own. Any other key of ``gsfix-online demo`` names a node of the repair graph.
READS = ("replay", "scene", "fixer", "demo")


def graph_settings(cfg: Config) -> tuple[dict[str, Any], dict[str, str]]:
    """The demo's settings of the repair graph (``gather``'s pair): its overrides, and the root
    sections its nodes share (``replay``, ``fixer``; a node's own key wins over them)."""
    import copy

    from gsfix_online.core.config import deep_merge, gather, to_dict

    settings, origins = gather(None, [*cfg.demo.graph_overrides, *cfg.demo.extra_overrides])
    shared = {"replay": to_dict(cfg.replay), "fixer": copy.deepcopy(cfg.fixer)}
    for key, value in shared.items():
        if value:
            settings[key] = deep_merge(value, settings.get(key) or {})
            origins.setdefault(key, f"the demo's {key} section")
    return settings, origins


def check_graph_settings(cfg: Config) -> None:
    """One-line error for a setting the repair graph does not take, before anything runs."""
    import copy

    from gsfix_online.core.config import read_yaml
    from gsfix_online.jobs.repair_run import DEFAULT_GRAPH
    from gsfix_online.runtime.graph import apply_settings

    apply_settings(copy.deepcopy(read_yaml(DEFAULT_GRAPH)), *graph_settings(cfg),
                   where=str(DEFAULT_GRAPH), also=READS, shared=("replay", "fixer"))  # fmt: skip


def _repair_graph(
    scene_dir: Path, out: Path, cfg: Config, progress: bool, profile: bool = False
) -> tuple[dict, float, Path]:
    """Run the repair graph over the scene's log; -> (metrics.json content, seconds, log path)."""
    import shutil

    from gsfix_online.core.progress import Progress
    from gsfix_online.jobs.repair_run import DEFAULT_GRAPH, prepare, run_graph

    # The demo owns its folder and starts over: an earlier run's checkpoints would be resumed
    shutil.rmtree(out, ignore_errors=True)
    settings, origins = graph_settings(cfg)
    graph_file, _, n_views = prepare(
        scene_dir / "log.mcap",
        scene_dir / "novel" / "views.txt",
        out,
        views_gt=scene_dir / "novel" / "color",
        graph_path=DEFAULT_GRAPH,
        settings=(settings, origins),
    )
    log_path = graph_file.with_name("graph.log")
    # The progress follows the writer's progress.json; node lines go to graph.log only
    with (
        Progress("repair graph (views decided)", n_views, "view", enabled=progress) as bar,
        open(os.devnull, "w") as sink,
    ):
        res = run_graph(graph_file, log=sink, timeout_s=cfg.demo.timeout_s or None, progress=bar,
                        profile=profile)  # fmt: skip
    if res.returncode != 0:
        raise RuntimeError(f"repair graph: {res.message}")
    return res.metrics, res.seconds, log_path
