"""The output folder of a repair run: per-view images, ``metrics.json`` and the report page.

Layout (``NNN`` = the view's number, from 000 in file order)::

    DIR/views/NNN/gs.png      3DGS render before repair (the GSFixer input when repaired)
    DIR/views/NNN/alpha.png   3DGS render opacity (0..255)
    DIR/views/NNN/mesh.png    mesh render
    DIR/views/NNN/mesh_fill.png, inpaint.png, mesh_inpaint.png   the baselines (see
                              ``repair.baselines``: mesh fill, + Telea; the mesh alone + Telea)
    DIR/views/NNN/fixed.png   GSFixer's own output (absent when the planner skipped the view)
    DIR/views/NNN/output.png  the repair delivered and distilled: GSFixer where it measured
                              better than the fallbacks, theirs elsewhere (repair.fallback)
    DIR/views/NNN/final.png   3DGS render after distillation
    DIR/metrics.json          per view: score, skip decision and reason, timings, PSNR/SSIM
    DIR/report.html           images side by side and the tables

With ground truth (``GTDIR/NNN.png``), every stage is scored: the raw 3DGS render, the mesh
render, the mesh-fill and OpenCV-inpainting baselines (and the mesh render alone, its holes
inpainted: what a user gets from Open3D and OpenCV without a Gaussian map), GSFixer (``fixed``; and ``fixed_or_gs``,
the 2D output over all views, the 3DGS render where a view was skipped) and the final render.
Images are written as they arrive (atomically), so a partial run leaves complete files.
Views can be grouped (``groups``: name -> view ids, e.g. the held-out input frames of
``repair --holdout``); each group is scored on its own in ``summary.groups``, next to the rest
(``novel``). ``output_or_gs`` is the 2D result over all views: the repair where there was one;
where the planner skipped a view, its 3DGS render with the run's fallback choice applied.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from gsfix_online.config_schema import atomic_write_bytes, atomic_write_text

STAGES = (
    "gs", "mesh", "mesh_fill", "inpaint", "mesh_inpaint", "fixed", "fixed_or_gs", "output",
    "output_or_gs", "final",
)  # fmt: skip
VIEW_FILES = (
    "gs", "alpha", "mesh", "mesh_fill", "inpaint", "mesh_inpaint", "fixed", "output", "final",
)  # fmt: skip


def write_png(path: Path, img: npt.NDArray[np.uint8]) -> None:  # [H, W(, 3)] RGB
    bgr = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", bgr)
    assert ok, path
    atomic_write_bytes(path, buf.tobytes())


def read_png_rgb(
    path: Path, width: int | None = None, height: int | None = None
) -> npt.NDArray[np.uint8]:  # [H, W, 3]
    """An image as RGB; with a size, area-resized to it if it differs (ground truth at the
    processing resolution)."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"cannot read image {path}")
    img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if width is not None and height is not None and img.shape[:2] != (height, width):
        img = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
    return img


def _clean(v: Any) -> Any:
    """JSON without NaN/inf (they become null)."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_clean(x) for x in v]
    return v


def _stage_means(views: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Mean PSNR and SSIM per stage over the views scored at that stage."""
    per_stage: dict[str, list[tuple[float, float]]] = {s: [] for s in STAGES}
    for v in views:
        for stage, m in v["metrics"].items():
            per_stage[stage].append((m["psnr_db"], m["ssim"]))
    return {
        s: {
            "psnr_db": float(np.mean([p for p, _ in v])),
            "ssim": float(np.mean([q for _, q in v])),
            "views": len(v),
        }
        for s, v in per_stage.items()
        if v
    }


@dataclass
class ViewRecord:
    view_id: int
    repair: bool | None = None  # None: no decision yet
    reason: str = ""
    origin: str = "file"
    score: dict[str, float] = field(default_factory=dict)
    camera: dict[str, Any] = field(default_factory=dict)  # K (9), T_world_cam (16), width, height
    timings: dict[str, float] = field(default_factory=dict)
    images: dict[str, npt.NDArray[Any]] = field(default_factory=dict)  # gs, alpha, mesh, valid,...
    model: dict[str, Any] = field(default_factory=dict)  # version, step, choice of the GSFixer used

    @property
    def name(self) -> str:
        return f"{self.view_id:03d}"

    @property
    def complete(self) -> bool:
        if self.repair is None or "final" not in self.images:
            return False
        return not self.repair or "output" in self.images


class RepairOutputs:
    """Collects a run's views as their pieces arrive and writes the folder (see module doc)."""

    def __init__(
        self,
        out_dir: str | Path,
        gt_dir: str | Path | None = None,
        groups: dict[str, range] | None = None,  # name -> view ids scored as a group
    ) -> None:
        self.out = Path(out_dir)
        self.gt_dir = Path(gt_dir) if gt_dir else None
        self.groups = dict(groups or {})
        self.views: dict[int, ViewRecord] = {}
        # The fallback choice the repairs followed (repair.fallback.Choice as a dict: per region,
        # the held-out errors it came from, why); None before any repair
        self.fallback: dict[str, Any] | None = None

    def view(self, view_id: int) -> ViewRecord:
        if view_id not in self.views:
            self.views[view_id] = ViewRecord(view_id)
        return self.views[view_id]

    def _dir(self, rec: ViewRecord) -> Path:
        return self.out / "views" / rec.name

    # -- pieces ------------------------------------------------------------------------------

    def on_decision(
        self,
        view_id: int,
        repair: bool,
        reason: str,
        score: dict[str, float],
        camera: dict[str, Any],
        origin: str = "file",
        seconds: float = math.nan,
    ) -> ViewRecord:
        rec = self.view(view_id)
        rec.repair, rec.reason, rec.score, rec.camera, rec.origin = (
            repair, reason, score, camera, origin,
        )  # fmt: skip
        rec.timings["score_s"] = seconds
        return rec

    def on_renders(
        self,
        view_id: int,
        gs: npt.NDArray[np.uint8] | None = None,  # [H, W, 3]
        alpha: npt.NDArray[np.float32] | None = None,  # [H, W]
        mesh: npt.NDArray[np.uint8] | None = None,  # [H, W, 3]
        valid: npt.NDArray[np.bool_] | None = None,  # [H, W]
    ) -> None:
        """The renders a view was scored (or repaired) from; later calls replace earlier ones."""
        from gsfix_online.repair.baselines import inpaint_telea, mesh_fill

        rec = self.view(view_id)
        for key, img in (("gs", gs), ("alpha", alpha), ("mesh", mesh), ("valid", valid)):
            if img is not None:
                rec.images[key] = np.asarray(img)
                if key in ("gs", "mesh"):
                    write_png(self._dir(rec) / f"{key}.png", rec.images[key])
        if alpha is not None:
            a8 = np.rint(np.clip(rec.images["alpha"], 0.0, 1.0) * 255.0).astype(np.uint8)
            write_png(self._dir(rec) / "alpha.png", a8)
        im = rec.images
        if all(k in im for k in ("gs", "alpha", "mesh", "valid")):  # both renders: baselines
            fill = mesh_fill(im["gs"], im["alpha"].astype(np.float32), im["mesh"], im["valid"])
            im["mesh_fill"] = fill.image
            im["inpaint"] = inpaint_telea(fill.image, fill.missing)
            im["mesh_inpaint"] = inpaint_telea(im["mesh"], ~im["valid"])
            for key in ("mesh_fill", "inpaint", "mesh_inpaint"):
                write_png(self._dir(rec) / f"{key}.png", im[key])

    def on_fixed(
        self, view_id: int, image: npt.NDArray[np.uint8], timings: dict[str, float], model: dict
    ) -> None:
        """The repair delivered for a view (``output``); it is GSFixer's own (``fixed``) too
        unless :meth:`on_fixer` brings that separately."""
        rec = self.view(view_id)
        rec.images["output"] = image
        rec.images.setdefault("fixed", image)
        rec.timings.update(timings)
        rec.model = dict(model)
        write_png(self._dir(rec) / "output.png", image)
        if not (self._dir(rec) / "fixed.png").is_file():
            write_png(self._dir(rec) / "fixed.png", image)

    def on_fixer(self, view_id: int, image: npt.NDArray[np.uint8]) -> None:
        """GSFixer's own output for a view, before the choice per region."""
        rec = self.view(view_id)
        rec.images["fixed"] = image
        write_png(self._dir(rec) / "fixed.png", image)

    def on_distilled(self, view_id: int, seconds: float) -> None:
        self.view(view_id).timings["distill_s"] = seconds

    def on_final(self, view_id: int, image: npt.NDArray[np.uint8]) -> None:
        rec = self.view(view_id)
        rec.images["final"] = image
        write_png(self._dir(rec) / "final.png", image)

    # -- queries -----------------------------------------------------------------------------

    def decided(self) -> list[ViewRecord]:
        return [r for r in self.views.values() if r.repair is not None]

    def accepted(self) -> list[ViewRecord]:
        return [r for r in self.views.values() if r.repair]

    def fixed_count(self) -> int:
        return sum(1 for r in self.accepted() if "output" in r.images)

    # -- metrics and report ------------------------------------------------------------------

    def _stage_images(self, rec: ViewRecord) -> dict[str, npt.NDArray[np.uint8]]:
        im = rec.images
        out: dict[str, npt.NDArray[np.uint8]] = {}
        for key in ("gs", "mesh", "mesh_fill", "inpaint", "mesh_inpaint", "fixed", "output",
                    "final"):  # fmt: skip
            if key in im:
                out[key] = im[key]
        if "gs" in im:
            out["fixed_or_gs"] = im["fixed"] if "fixed" in im else im["gs"]
            out["output_or_gs"] = im["output"] if "output" in im else self._skipped_output(im)
        return out

    def _skipped_output(self, im: dict[str, npt.NDArray[Any]]) -> npt.NDArray[np.uint8]:
        """The 2D output of a view the planner skipped: the 3DGS render, except in the regions
        where the run's fallback choice measured a fallback better (GSFixer's regions keep the
        3DGS render: no repair ran)."""
        if self.fallback is None or not all(k in im for k in ("inpaint", "mesh_inpaint")):
            return im["gs"]
        from gsfix_online.repair.fallback import Choice, compose, regions

        choice = Choice.from_json(json.dumps(self.fallback))
        cands = {"fixed": im["gs"], "inpaint": im["inpaint"], "mesh_inpaint": im["mesh_inpaint"]}
        return compose(cands, regions(im["alpha"], im["valid"]), choice)

    def view_metrics(self, rec: ViewRecord) -> dict[str, dict[str, float]]:
        from gsfix_online.inspection.metrics import scores

        if self.gt_dir is None:
            return {}
        gt_path = self.gt_dir / f"{rec.name}.png"
        if not gt_path.is_file() or "gs" not in rec.images:
            return {}
        h, w = rec.images["gs"].shape[:2]
        gt = read_png_rgb(gt_path, w, h)
        out = {}
        for stage, img in self._stage_images(rec).items():
            s = scores(img, gt)
            out[stage] = {"psnr_db": s.psnr_db, "ssim": s.ssim}
        return out

    def metrics(self, extra: dict[str, Any] | None = None) -> dict[str, Any]:
        views = []
        reasons: dict[str, int] = {}
        for vid in sorted(self.views):
            rec = self.views[vid]
            m = self.view_metrics(rec)
            if rec.repair is False:
                key = rec.reason.split(" (")[0]
                reasons[key] = reasons.get(key, 0) + 1
            files = {k: f"views/{rec.name}/{k}.png" for k in VIEW_FILES}
            files = {k: p for k, p in files.items() if (self.out / p).is_file()}
            views.append(
                {
                    "view": rec.name,
                    "view_id": rec.view_id,
                    "origin": rec.origin,
                    "repair": rec.repair,
                    "skipped": rec.repair is False,
                    "reason": rec.reason,
                    "score": rec.score,
                    "camera": rec.camera,
                    "timings_s": rec.timings,
                    "model": rec.model,
                    "files": files,
                    "metrics": m,
                }
            )
        stages = _stage_means(views)
        groups = {}
        if self.groups:
            grouped = {vid for ids in self.groups.values() for vid in ids}
            for name, ids in self.groups.items():
                groups[name] = _stage_means([v for v in views if v["view_id"] in ids])
            groups["novel"] = _stage_means([v for v in views if v["view_id"] not in grouped])
        n_rep = sum(1 for v in views if v["repair"])
        timing_keys = sorted({k for v in views for k in v["timings_s"]})
        totals = {
            k: float(np.nansum([v["timings_s"].get(k, math.nan) for v in views]))
            for k in timing_keys
        }
        summary = {
            "views": len(views),
            "repaired": n_rep,
            "skipped": len(views) - n_rep,
            "skip_reasons": reasons,
            "ground_truth": str(self.gt_dir) if self.gt_dir else None,
            "stages": stages,
            "groups": groups,
            "fallback": self.fallback,
            "stage_time_totals_s": totals,
        }
        return _clean({"summary": summary, "views": views, **(extra or {})})

    def write(self, extra: dict[str, Any] | None = None, title: str = "GSFix3D repair") -> dict:
        """Write ``metrics.json`` and ``report.html``; returns the metrics."""
        from gsfix_online.inspection import report as page
        from gsfix_online.inspection.report import Plot, Report, Table, ViewRow, write_report

        m = self.metrics(extra)
        atomic_write_text(self.out / "metrics.json", json.dumps(m, indent=2) + "\n")
        s = m["summary"]
        tables = []
        if s["stages"]:
            rows = [(k, v["psnr_db"], v["ssim"], v["views"]) for k, v in s["stages"].items()]
            tables.append(
                Table("Stages against ground truth", ("stage", "PSNR dB", "SSIM", "views"), rows)
            )
        for group, stages in (s.get("groups") or {}).items():
            rows = [(k, v["psnr_db"], v["ssim"], v["views"]) for k, v in stages.items()]
            if rows:
                title = f"Stages against ground truth: {group} views"
                tables.append(Table(title, ("stage", "PSNR dB", "SSIM", "views"), rows))
        vrows = [
            (
                v["view"],
                "repair" if v["repair"] else "skip",
                v["reason"],
                v["score"].get("hole_fraction"),
                v["score"].get("disagree_fraction"),
                v["metrics"].get("gs", {}).get("psnr_db"),
                v["metrics"].get("inpaint", {}).get("psnr_db"),
                v["metrics"].get("fixed", {}).get("psnr_db"),
                v["metrics"].get("output", {}).get("psnr_db"),
                v["metrics"].get("final", {}).get("psnr_db"),
            )
            for v in m["views"]
        ]
        cols = (
            "view",
            "decision",
            "reason",
            "holes",
            "disagree",
            "3DGS dB",
            "Telea dB",
            "GSFixer dB",
            "output dB",
            "final dB",
        )
        tables.append(Table("Views", cols, vrows))
        trows = [(k, v) for k, v in s["stage_time_totals_s"].items()]
        trows += [(k, v) for k, v in (m.get("timings_s") or {}).items()]
        tables.append(Table("Time (s)", ("stage", "seconds"), trows))
        views = []
        for v in m["views"]:
            images = {
                k: v["files"][k]
                for k in ("gs", "mesh", "inpaint", "mesh_inpaint", "fixed", "output", "final")
                if k in v["files"]
            }
            # a repaired view: its 3DGS render and the repair under one slider
            compare = ("gs", "output") if v["repair"] and {"gs", "output"} <= set(images) else None
            views.append(ViewRow(f"view {v['view']}", images, v["reason"], compare))
        plots = []
        if any(v is not None and math.isfinite(v) for _, v in trows):
            fig = page.stage_times_figure(dict(trows))
            plots.append(Plot("Time per stage", page.figure_png(fig)))
        scored = [v for v in m["views"] if v["metrics"]]
        if scored:
            series = {
                stage: [v["metrics"].get(stage, {}).get("psnr_db") for v in scored]
                for stage in STAGES
                if any(stage in v["metrics"] for v in scored)
            }
            fig = page.psnr_figure([v["view"] for v in scored], series)
            plots.append(Plot("PSNR per view, every stage and baseline", page.figure_png(fig)))
        notes = [f"{s['views']} views: {s['repaired']} repaired, {s['skipped']} skipped."]
        write_report(self.out / "report.html", Report(title, tables, views, notes, plots))
        return m
