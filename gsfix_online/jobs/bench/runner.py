"""One run of the benchmark: the repair graph with a run's overrides, timed and scored.

:func:`run_one` prepares and launches the repair graph (:mod:`gsfix_online.jobs.repair_run`, real
processes) and returns one flat row:

- wall time per stage, from the nodes' log lines stamped as they arrive (mapping until the splat
  node's end of the input, the refinement after it, fine-tuning from the trainer's end of the
  input until its run stopped) and from ``metrics.json`` (GSFixer and distillation summed over
  views, the writer's final renders, mesh and export);
- CPU seconds of all node processes (``cpu_s``: what the run costs, nearly independent of other
  jobs on the machine, unlike wall time);
- peak memory: the largest resident set of each node process, sampled every 0.5 s with psutil,
  summed over the nodes (``peak_rss_mb``), and the largest single node (``peak_node_rss_mb``);
- novel-view PSNR/SSIM of the raw 3DGS render (``gs``), GSFixer's 2D output (``fixed``: the
  3DGS render where the planner skipped a view), the delivered repair (``output``) and the final
  map after distillation (``final``);
- with ground-truth depth (``NNN.png`` in metres times ``depth_scale``): the final map's depth
  error at the views; with a ground-truth mesh: the TSDF mesh's accuracy and completeness (cm).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

logger = logging.getLogger(__name__)

# Log lines that mark stage boundaries: (stage edge, node prefix, text in the line)
MARKS = {
    "map_end": ("[splat]", "end of the input after"),
    "refine_start": ("[splat]", "refining the map over"),
    "refine_end": ("[splat]", "refined, loss"),
    "finetune_start": ("[trainer]", "end of the input ("),
    "finetune_end": ("[trainer]", "stopped ("),
}
STAGES = ("gs", "fixed_or_gs", "output_or_gs", "final")  # the stages scored in every row
STAGE_COLUMNS = {"gs": "gs", "fixed_or_gs": "fixed", "output_or_gs": "output", "final": "final"}


@dataclass(frozen=True)
class BenchInput:
    """What every run of a sweep reads: the input, its views and their ground truth."""

    src: Path  # any input a reader accepts
    views: Path | None  # TUM pose list of the views to repair
    views_gt: Path | None = None  # NNN.png ground-truth images of those views
    depth_gt: Path | None = None  # NNN.png ground-truth depth, metres * depth_scale
    gt_mesh: Path | None = None  # ground-truth mesh (PLY) for mesh accuracy/completeness
    holdout: int = 0  # repair --holdout K
    name: str = ""  # how the results name it
    depth_scale: float = 5000.0

    def describe(self) -> dict[str, Any]:
        return {"name": self.name or str(self.src), "src": str(self.src),
                "views": str(self.views or ""), "holdout": self.holdout}  # fmt: skip


class _StampedLog:
    """A text stream for :func:`run_graph`'s node lines: stamps the lines that mark stage edges
    (monotonic seconds) and forwards everything to ``out`` (None: drop)."""

    def __init__(self, out: Any = None) -> None:
        self.out = out
        self.marks: dict[str, float] = {}
        self._part = ""

    def write(self, s: str) -> int:
        now = time.monotonic()
        self._part += s
        *lines, self._part = self._part.split("\n")
        for line in lines:
            for mark, (node, text) in MARKS.items():
                # a stage starts at its first line and ends at its last (a later run's)
                first = mark.endswith("_start") and mark in self.marks
                if line.startswith(node) and text in line and not first:
                    self.marks[mark] = now
        if self.out is not None:
            self.out.write(s)
        return len(s)

    def flush(self) -> None:
        if self.out is not None:
            self.out.flush()


class PeakMemory:
    """Samples the resident memory of this process's descendants (the graph's nodes) in a
    thread: per process the largest value seen."""

    def __init__(self, period_s: float = 0.5) -> None:
        self.period_s = period_s
        self.peak_by_pid: dict[int, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="peak-rss", daemon=True)

    def _loop(self) -> None:
        import psutil

        me = psutil.Process()
        while not self._stop.wait(self.period_s):
            for p in me.children(recursive=True):
                try:
                    rss = p.memory_info().rss
                except psutil.Error:  # ended between the listing and the read
                    continue
                self.peak_by_pid[p.pid] = max(self.peak_by_pid.get(p.pid, 0), rss)

    def __enter__(self) -> PeakMemory:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    @property
    def total_mb(self) -> float:
        return sum(self.peak_by_pid.values()) / 2**20

    @property
    def largest_mb(self) -> float:
        return max(self.peak_by_pid.values(), default=0) / 2**20


def _children_cpu_s() -> float:
    """CPU seconds (user + system) of this process's ended and waited-for children: the node
    processes of the runs so far. Unlike wall time, it barely moves with other jobs' load."""
    import resource

    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def _span(marks: dict[str, float], a: str, b: str) -> float | None:
    return marks[b] - marks[a] if a in marks and b in marks else None


def stage_times(
    marks: dict[str, float], t0: float, metrics: dict[str, Any], total_s: float
) -> dict[str, float | None]:
    """Wall seconds per stage (None where the run did not log it)."""
    totals = metrics["summary"].get("stage_time_totals_s") or {}
    phases = metrics.get("timings_s") or {}
    return {
        "total_s": total_s,
        "map_s": marks["map_end"] - t0 if "map_end" in marks else None,
        "refine_s": _span(marks, "refine_start", "refine_end"),
        "finetune_s": _span(marks, "finetune_start", "finetune_end"),
        "fix_s": totals.get("fix_s"),
        "distill_s": (totals.get("distill_s") or 0.0) + (phases.get("distill_passes_s") or 0.0),
        "passes_s": phases.get("distill_passes_s"),  # of distill_s: the passes after repairs
        "write_s": sum(phases.get(k) or 0.0 for k in ("final_s", "mesh_s", "export_s")),
    }


def image_scores(metrics: dict[str, Any]) -> dict[str, float | None]:
    """PSNR/SSIM per stage: of the novel views when the run held frames out, else of all."""
    s = metrics["summary"]
    stages = (s.get("groups") or {}).get("novel") or s.get("stages") or {}
    out: dict[str, float | None] = {}
    for stage, col in STAGE_COLUMNS.items():
        v = stages.get(stage) or {}
        out[f"psnr_{col}"] = v.get("psnr_db")
        out[f"ssim_{col}"] = v.get("ssim")
    out["views"] = s.get("views")
    out["repaired"] = s.get("repaired")
    return out


def depth_error_cm(run_dir: Path, metrics: dict[str, Any], depth_gt: Path, scale: float) -> float:
    """Mean |depth| error (cm) of the final 3DGS map at the views that have ground-truth depth,
    over pixels where both the render (alpha >= 0.5) and the ground truth have depth."""
    import cv2
    import torch

    from gsfix_online.mapping.splat.ply import load_model
    from gsfix_online.mapping.splat.render import render

    g = load_model(run_dir / "map").gmap
    if len(g) == 0:
        return float("nan")
    errs: list[npt.NDArray[np.float64]] = []
    for v in metrics["views"]:
        path = depth_gt / f"{v['view_id']:03d}.png"
        cam = v.get("camera") or {}
        if not path.is_file() or not cam:
            continue
        w, h = int(cam["width"]), int(cam["height"])
        gt = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64) / scale
        if gt.shape != (h, w):
            gt = cv2.resize(gt, (w, h), interpolation=cv2.INTER_NEAREST)
        K = torch.tensor(cam["K"], dtype=torch.float32).reshape(3, 3)
        T = torch.tensor(cam["T_world_cam"], dtype=torch.float32).reshape(4, 4)
        with torch.no_grad():
            out = render(g.means, g.params["quats"], g.scales, g.opacities, g.sh, None, K, w, h,
                         T_world_cam=T, sh_degree=g.sh_degree, backend="cpu")  # fmt: skip
        alpha = out.alpha.numpy()
        depth = out.depth.numpy()  # expected z-depth, already divided by alpha
        ok = (alpha >= 0.5) & (gt > 0)
        errs.append(np.abs(depth[ok] - gt[ok]))
    err = np.concatenate(errs) if errs else np.zeros(0)
    return 100.0 * float(err.mean()) if err.size else float("nan")


def mesh_scores(mesh_path: Path, gt_mesh: Path, points: int = 50_000) -> dict[str, float]:
    """Accuracy and completeness (cm) of the run's mesh against the ground truth
    (:func:`gsfix_online.jobs.tsdf_report.surface_metrics` on points sampled on both)."""
    import open3d as o3d

    from gsfix_online.jobs.tsdf_report import nn_distances, surface_metrics

    o3d.utility.random.seed(0)
    rec = o3d.io.read_triangle_mesh(str(mesh_path))
    gt = o3d.io.read_triangle_mesh(str(gt_mesh))
    gt_pts = np.asarray(gt.sample_points_uniformly(points).points)
    rec_pts = (np.asarray(rec.sample_points_uniformly(points).points)
               if len(rec.triangles) else gt_pts[:0])  # fmt: skip
    m = surface_metrics(nn_distances(rec_pts, gt_pts), nn_distances(gt_pts, rec_pts), [0.05])
    return {"mesh_accuracy_cm": m["accuracy_cm"], "mesh_completeness_cm": m["completeness_cm"]}


def run_one(
    inp: BenchInput,
    overrides: list[str],
    out: Path,
    timeout_s: float | None = None,
    log: Any = None,  # a text stream for the node lines (None: only OUT/work/graph.log)
) -> dict[str, Any]:
    """The repair graph over ``inp`` with ``overrides``, into the fresh folder ``out``; one row
    (see the module doc). A failed run's row has ``rc`` 1 and its ``error``."""
    import shutil

    from gsfix_online.jobs.repair_run import prepare, run_graph

    # 1. A fresh run folder (the trainer would resume an earlier run's checkpoints)
    if out.exists():
        shutil.rmtree(out)
    graph, info, n_views = prepare(
        inp.src, inp.views, out, inp.views_gt, overrides=overrides, holdout=inp.holdout
    )
    # 2. The graph as processes, its memory sampled and its stage lines stamped
    stamped = _StampedLog(log)
    cpu0 = _children_cpu_s()
    t0 = time.monotonic()
    with PeakMemory() as mem:
        res = run_graph(graph, log=stamped, timeout_s=timeout_s)  # type: ignore[arg-type]
    row: dict[str, Any] = {
        "rc": res.returncode, "frames": info.frames, "width": info.width,
        "height": info.height, "n_views": n_views, "peak_rss_mb": mem.total_mb,
        "peak_node_rss_mb": mem.largest_mb, "cpu_s": _children_cpu_s() - cpu0,
    }  # fmt: skip
    if res.returncode != 0 or res.metrics is None:
        return row | {"total_s": res.seconds, "error": res.message}
    if not res.metrics.get("map"):  # the writer wrote what it had when it was stopped
        return row | {"rc": 1, "total_s": res.seconds, "error": "stopped before the map export"}
    # 3. Times and scores
    row |= stage_times(stamped.marks, t0, res.metrics, res.seconds)
    row |= image_scores(res.metrics)
    if inp.depth_gt is not None:
        row["depth_mae_cm"] = depth_error_cm(out, res.metrics, inp.depth_gt, inp.depth_scale)
    if inp.gt_mesh is not None and (out / "mesh.ply").is_file():
        row |= mesh_scores(out / "mesh.ply", inp.gt_mesh)
    return row


def read_metrics(run_dir: Path) -> dict[str, Any]:
    return json.loads((run_dir / "metrics.json").read_text())


__all__ = ["BenchInput", "PeakMemory", "image_scores", "run_one", "stage_times"]
