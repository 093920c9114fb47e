"""The output folder of a repair run: per-view images, ``metrics.json`` and the report page.

Layout (``NNN`` = the view's number, from 000 in file order)::

    DIR/views/NNN/gs.png      3DGS render before repair (the GSFixer input when repaired)
    DIR/views/NNN/alpha.png   3DGS render opacity (0..255)
    DIR/views/NNN/mesh.png    mesh render
    DIR/views/NNN/gs_inpaint.png
                              the 3DGS render alone, its holes (alpha < 0.5) inpainted by
                              OpenCV Telea: the Gaussian map filled as mesh_inpaint fills the mesh
    DIR/views/NNN/mesh_fill.png, inpaint.png, inpaint_ns.png, inpaint_fsr.png, mesh_inpaint.png
                              the baselines (see ``repair.baselines``): mesh fill; mesh fill +
                              OpenCV Telea, + Navier-Stokes, + FSR (cv2.xphoto; written with
                              the report: it takes seconds per view); the mesh alone + Telea;
                              Navier-Stokes and FSR only when ground truth scores the run
    DIR/views/NNN/fixed.png   GSFixer's own output (absent when the planner skipped the view)
    DIR/views/NNN/output.png  the repair delivered and distilled: GSFixer where it measured
                              better than the fallbacks, theirs elsewhere (repair.fallback);
                              for a skipped view its 2D output (see ``output_or_gs``)
    DIR/views/NNN/final.png   3DGS render after distillation
    DIR/views/NNN/provenance.png, provenance.npz
                              where each pixel of the delivered output (output_or_gs) came
                              from (repair.provenance): the 3DGS or mesh render where that map
                              covered it, or real frames warped (observed); GSFixer, a
                              classical fill, or the 3DGS render of Gaussians grown from
                              other repaired views (synthesised);
                              colours with a legend, and per pixel the source index, its weight
                              (confidence, < 1 in blends) and the synthesised share
    DIR/metrics.json          per view: score, skip decision and reason, timings, PSNR/SSIM
    DIR/report.html           images side by side and the tables
    DIR/timeline.png          when each node was busy, and its CPU use (drawn by the job that
                              launched the graph once every node stopped, and added to the
                              report: jobs/repair_run.py)

With ground truth (``GTDIR/NNN.png``), every stage is scored: the raw 3DGS render, the mesh
render, the mesh-fill and OpenCV-inpainting baselines (and the mesh render alone, its holes
inpainted: what a user gets from Open3D and OpenCV without a Gaussian map), GSFixer (``fixed``;
and ``fixed_or_gs``, the 2D output over all views, the 3DGS render where a view was skipped) and
the final render. ``summary.best_classical`` names the classical baseline (``CLASSICAL``) with
the highest mean PSNR. Each stage is also scored per region class (``repair.fallback.regions``:
``both`` maps cover the pixel, ``gs_only``, ``mesh_only``, ``neither``), in ``views[i].regions``
and, pooled over the views (PSNR of the region's mean squared error, SSIM map averaged over its
pixels), in ``summary.regions[stage][region]`` (``summary.region_groups`` per group).
Images are written as they arrive (atomically), so a partial run leaves complete files.
Views can be grouped (``groups``: name -> view ids, e.g. the held-out input frames of
``repair --holdout``); each group is scored on its own in ``summary.groups``, next to the rest
(``novel``). ``output_or_gs`` is the 2D result over all views: the repair where there was one;
where the planner skipped a view (the map explains it), the fallbacks composed as the held-out
frames chose per region when the view lies within their reach (GSFixer's regions take mesh fill
+ Telea: it did not run), else its 3DGS render wherever it covers the view and the run's
measured fallback in its holes. A skipped view's ``output.png`` is that 2D result too; what
distillation fitted (the planner's fill of its holes) scores the map's fidelity.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import numpy.typing as npt

from gsfix_online.core.io import atomic_write_bytes, atomic_write_text
from gsfix_online.repair.fallback import REGIONS

if TYPE_CHECKING:
    from gsfix_online.core.metrics import MaskedScores

log = logging.getLogger(__name__)

STAGES = (
    "gs", "gs_inpaint", "mesh", "mesh_fill", "inpaint", "inpaint_ns", "inpaint_fsr",
    "mesh_inpaint", "ref_warp", "ref_inpaint", "fixed", "fixed_or_gs", "output", "output_or_gs",
    "final",
)  # fmt: skip
# What a user can do with the mesh and OpenCV alone; the best of them is named in the summary
# A view whose final-map render is this far from its delivered output (PSNR, dB) is listed in
# metrics.json: on tank:real (40 frames, seed 0) the views the final map kept were 24-44 dB from
# their outputs; a view veiled by distillation's seeds, 18.6 dB (its final map 2.1 dB below the
# output against the ground truth)
MAP_FIDELITY_LOW_DB = 20.0
# ... and whose final-map render is this much less sharp than its output (map_sharpness: mean
# gradient magnitude) seen through the renderer's own low-pass (render_output.EPS2D): the demo's
# veiled view 001 had 0.39 against the output itself, its other views 0.85-0.98
# (benchmarks/results/distill_veil_cpu.md). Against the output itself, a map that holds it
# exactly scores only what the low-pass (a Gaussian blur of 0.55 px) leaves of it, 0.86-0.95
# on the runs measured, and tank seed 1's view 004, fitted 80 more steps until its render was
# 44.8 dB from the output, still had 0.88 (benchmarks/results/sharpness_footprint_cpu.md).
# That ratio stays in metrics.json as map_sharpness_raw.
MAP_SHARPNESS_LOW = 0.9
# An input keyframe next to a repaired view whose render lost more than this (PSNR against the
# frame, dB) between before the repaired views were distilled and the end is listed in
# metrics.json: what distilling the repairs cost what the robot observed (the splat node's
# kept_keyframes)
KEYFRAME_LOSS_DB = 0.1


def keyframes_kept(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """metrics.json's ``keyframes_kept`` from the splat node's rows (``keyframe_id``,
    ``view_id``: the repaired view it is a neighbour of, -1 none; ``before_db``, ``after_db``):
    each row's change; over the neighbours, the median, the worst and those that lost more than
    ``KEYFRAME_LOSS_DB``; over every keyframe, the median and the worst. A row whose
    ``after_db`` is None (the map no longer stores the keyframe) has no change: it is listed
    in ``gone`` and left out of the figures."""
    out = [
        {**r, "change_db": None if r["after_db"] is None else r["after_db"] - r["before_db"]}
        for r in rows
    ]

    def spread(sel: list[dict[str, Any]]) -> tuple[float | None, float | None]:
        ch = [r["change_db"] for r in sel if math.isfinite(r["change_db"])]
        return (float(np.median(ch)), min(ch)) if ch else (None, None)

    measured = [r for r in out if r["change_db"] is not None]
    near = [r for r in measured if r["view_id"] >= 0]
    median, worst = spread(near)
    all_median, all_worst = spread(measured)
    return {
        "keyframes": out,
        "median_change_db": median,
        "worst_change_db": worst,
        "lost": [r["keyframe_id"] for r in near if r["change_db"] < -KEYFRAME_LOSS_DB],
        "lost_above_db": KEYFRAME_LOSS_DB,
        "all_median_change_db": all_median,
        "all_worst_change_db": all_worst,
        "gone": [r["keyframe_id"] for r in out if r["change_db"] is None],
    }


TIMELINE_PNG = "timeline.png"
# (``ref_inpaint``: the real frames nearest the view warped by the mesh depth, the mesh and Telea
# in the rest, repair.ref_warp: a user can make it with Open3D and OpenCV; ``best_classical_maps``
# names the best without it, the maps' own renders and OpenCV)
CLASSICAL = ("mesh_fill", "inpaint", "inpaint_ns", "inpaint_fsr", "mesh_inpaint", "ref_inpaint")
VIEW_FILES = (
    "gs", "alpha", "gs_inpaint", "mesh", "mesh_fill", "inpaint", "inpaint_ns", "inpaint_fsr",
    "mesh_inpaint", "ref_warp", "ref_inpaint", "fixed", "output", "final", "provenance",
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


def _region_json(x: MaskedScores) -> dict[str, float]:
    return {"psnr_db": x.psnr_db, "ssim": x.ssim, "pixels": x.pixels}


def _region_means(
    views: list[dict[str, dict[str, MaskedScores]]],  # per view: stage -> region -> scores
) -> dict[str, dict[str, dict[str, float]]]:
    """Per stage and region, the scores pooled over the views (each pixel weighs the same)."""
    from gsfix_online.core.metrics import pooled

    out: dict[str, dict[str, dict[str, float]]] = {}
    for stage in STAGES:
        regions = sorted({r for v in views for r in v.get(stage, {})}, key=REGIONS.index)
        for r in regions:
            parts = [v[stage][r] for v in views if r in v.get(stage, {})]
            p = pooled(parts)
            assert p is not None  # parts without pixels are never stored
            out.setdefault(stage, {})[r] = {**_region_json(p), "views": len(parts)}
    return out


def _best(stages: dict[str, dict[str, float]], among: tuple[str, ...]) -> dict[str, Any] | None:
    """The stage of ``among`` with the highest mean PSNR (None if none was scored)."""
    scored = [s for s in among if s in stages]
    if not scored:
        return None
    best = max(scored, key=lambda s: stages[s]["psnr_db"])
    return {"stage": best, "psnr_db": stages[best]["psnr_db"], "ssim": stages[best]["ssim"]}


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
    fill: bool = False  # skipped, but its holes are filled (mesh fill + Telea) and distilled
    keyframe_distance_m: float | None = None  # the planner's (planner.keyframe_distance)

    @property
    def name(self) -> str:
        return f"{self.view_id:03d}"

    @property
    def complete(self) -> bool:
        if self.repair is None or "final" not in self.images:
            return False
        return not self.distils or "output" in self.images

    @property
    def distils(self) -> bool:
        """Its output is distilled: a repaired view, or a skipped one whose holes are filled."""
        return bool(self.repair) or self.fill


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
        # How far the held-out frames' choice (``fallback``) holds: their farthest keyframe
        # distance, m; None when the choice was not measured on held-out frames
        self.holdout_reach_m: float | None = None
        # The trainer's choice the repairs held beyond that reach (fallback.for_view); None: no
        # repair recorded one
        self.trainer_choice: dict[str, Any] | None = None
        # Per held-out frame, the choice measured on the other held-out frames (None: it was
        # the only one); a held-out frame is scored, so it never follows ``fallback`` itself
        self.fallback_without: dict[int, dict[str, Any] | None] = {}
        self._fsr_missing_said = False

    @property
    def scored(self) -> bool:
        """Ground truth will score the views (``gt_dir``, or held-out frames in ``groups``):
        only then are the baselines that serve the scoring alone made (Navier-Stokes and FSR;
        mesh fill + Telea and mesh + Telea are the fallback floor, and always made)."""
        return self.gt_dir is not None or bool(self.groups)

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
        fill: bool = False,
        keyframe_distance_m: float | None = None,
    ) -> ViewRecord:
        rec = self.view(view_id)
        rec.fill = fill and not repair
        rec.keyframe_distance_m = keyframe_distance_m
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
        # [H, W] the 3DGS render's share from Gaussians grown from repaired views (with gs)
        synthesised: npt.NDArray[np.float32] | None = None,
    ) -> None:
        """The renders a view was scored (or repaired) from; later calls replace earlier ones.
        The cheap baselines are made here, FSR by :meth:`finish_baselines`."""
        from gsfix_online.repair.baselines import fill_and_inpaint, gs_inpaint, inpaint_telea

        rec = self.view(view_id)
        if gs is not None:  # a 3DGS render without it: a map with nothing synthesised
            rec.images.pop("gs_synthesised", None)
            if synthesised is not None:
                rec.images["gs_synthesised"] = np.asarray(synthesised, np.float32)
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
            methods = ("telea", "ns") if self.scored else ("telea",)
            b = fill_and_inpaint(im["gs"], im["alpha"].astype(np.float32), im["mesh"],
                                 im["valid"], methods)  # fmt: skip
            im["mesh_fill"], im["inpaint"] = b["mesh_fill"], b["telea"]
            if "ns" in b:
                im["inpaint_ns"] = b["ns"]
            im["mesh_inpaint"] = inpaint_telea(im["mesh"], ~im["valid"])
            im["gs_inpaint"] = gs_inpaint(im["gs"], im["alpha"].astype(np.float32))
            im.pop("inpaint_fsr", None)  # made from the earlier renders
            for key in ("mesh_fill", "inpaint", "inpaint_ns", "mesh_inpaint", "gs_inpaint"):
                if key in im:
                    write_png(self._dir(rec) / f"{key}.png", im[key])
            self._ref_inpaint(rec)

    def on_ref(
        self,
        view_id: int,
        image: npt.NDArray[np.uint8],  # [H, W, 3] the view's reference warp (0 in its holes)
        valid: npt.NDArray[np.bool_],  # [H, W] its pixels
    ) -> None:
        """The view's reference warp (the planner's); with its mesh render it makes the fallback
        ``ref_inpaint``."""
        rec = self.view(view_id)
        rec.images["ref_warp"], rec.images["ref_valid"] = np.asarray(image), np.asarray(valid)
        write_png(self._dir(rec) / "ref_warp.png", rec.images["ref_warp"])
        self._ref_inpaint(rec)

    def _ref_inpaint(self, rec: ViewRecord) -> None:
        from gsfix_online.repair.fallback import ref_inpaint

        im = rec.images
        if {"ref_warp", "ref_valid", "mesh", "valid", "gs", "alpha"} <= set(im):
            im["ref_inpaint"] = ref_inpaint(im["mesh"], im["valid"], im["ref_warp"],
                                            im["ref_valid"], im["gs"], im["alpha"])  # fmt: skip
            write_png(self._dir(rec) / "ref_inpaint.png", im["ref_inpaint"])

    def finish_baselines(self, limit: int | None = None) -> int:
        """Mesh fill + FSR of every view with both renders that lacks it (seconds per view: see
        ``repair.baselines.FSR_FLAG``), when the run is :attr:`scored`; at most ``limit`` views
        (None: all). Returns how many were made. The writer makes them one at a time while it
        waits for distillation, and the rest when the metrics are written."""
        from gsfix_online.repair import baselines
        from gsfix_online.repair.baselines import inpaint, mesh_fill

        if not self.scored:
            return 0
        if baselines.FSR_FLAG is None:  # a comparison only: the run's outputs never use it
            if not self._fsr_missing_said:
                log.warning(
                    "FSR baseline left out: OpenCV's contrib build (cv2.xphoto) is not installed; "
                    "pip install opencv-contrib-python-headless in place of opencv-python-headless"
                )
                self._fsr_missing_said = True
            return 0
        made = 0
        for rec in self.views.values():
            im = rec.images
            if "inpaint_fsr" in im or "mesh_fill" not in im:
                continue
            if limit is not None and made >= limit:
                break
            made += 1
            t0 = time.perf_counter()
            fill = mesh_fill(im["gs"], im["alpha"].astype(np.float32), im["mesh"], im["valid"])
            im["inpaint_fsr"] = inpaint(fill.image, fill.missing, "fsr")
            rec.timings["inpaint_fsr_s"] = time.perf_counter() - t0
            write_png(self._dir(rec) / "inpaint_fsr.png", im["inpaint_fsr"])
        return made

    def on_fixed(
        self,
        view_id: int,
        image: npt.NDArray[np.uint8],
        timings: dict[str, float],
        model: dict,
        region: npt.NDArray[np.uint8] | None = None,  # [H, W] what compose composed it by
    ) -> None:
        """The repair delivered for a view (``output``); it is GSFixer's own (``fixed``) too
        unless :meth:`on_fixer` brings that separately. ``region``: the regions its output was
        composed by (``fallback.far_regions``), for its provenance; None: the renders'."""
        from gsfix_online.repair.fallback import FLAT

        if region is not None and (np.shape(region) != image.shape[:2] or np.max(region) > FLAT):
            raise ValueError(f"region must be [H, W] of the output with indices 0..{FLAT}, got "
                             f"{list(np.shape(region))} up to {np.max(region)}")  # fmt: skip
        rec = self.view(view_id)
        rec.images["output"] = rec.images["distilled"] = image
        if region is not None:
            rec.images["region"] = np.asarray(region, np.uint8)
        rec.images.setdefault("fixed", image)
        rec.timings.update(timings)
        rec.model = dict(model)
        write_png(self._dir(rec) / "output.png", image)
        if not (self._dir(rec) / "fixed.png").is_file():
            write_png(self._dir(rec) / "fixed.png", image)

    def on_filled(self, view_id: int, image: npt.NDArray[np.uint8]) -> None:
        """The fill of a skipped view (mesh fill + Telea in its holes), distilled as a repair."""
        rec = self.view(view_id)
        rec.images["output"] = rec.images["distilled"] = image
        write_png(self._dir(rec) / "output.png", image)

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

    def to_distil(self) -> list[ViewRecord]:
        return [r for r in self.views.values() if r.distils]

    def fixed_count(self) -> int:
        return sum(1 for r in self.accepted() if "output" in r.images)

    # -- metrics and report ------------------------------------------------------------------

    def _stage_images(self, rec: ViewRecord) -> dict[str, npt.NDArray[np.uint8]]:
        im = rec.images
        out: dict[str, npt.NDArray[np.uint8]] = {}
        for key in STAGES:
            if key in im:
                out[key] = im[key]
        if "gs" in im:
            out["fixed_or_gs"] = im["fixed"] if "fixed" in im else im["gs"]
            out["output_or_gs"] = im["output"] if "output" in im else self._skipped_output(rec)
        return out

    def _near_choice(self, rec: ViewRecord) -> Any:
        """The held-out frames' choice per region for a skipped view within their reach, with
        GSFixer's regions given to the fallback measured better there (GSFixer did not run on
        it; ``Choice.without_fixer``); None when the run measured no choice on held-out frames
        or the view lies beyond their reach."""
        from gsfix_online.repair.fallback import Choice

        reach, d = self.holdout_reach_m, rec.keyframe_distance_m
        measured = self._measured_for(rec)
        if measured is None or reach is None or d is None or d > reach:
            return None
        return Choice.from_json(json.dumps(measured)).without_fixer()

    def _measured_for(self, rec: ViewRecord) -> dict[str, Any] | None:
        """The run's measured choice as a view may follow it: a held-out frame is scored, so
        it takes the choice the *other* held-out frames measured (None for a lone one)."""
        return self.fallback_without.get(rec.view_id, self.fallback)

    def _skipped_recipe(self, rec: ViewRecord) -> tuple[Any, float]:
        """How the 2D output of a view the planner skipped (no GSFixer ran on it) is composed:
        (the choice per region, the seam feathering in px), or (None, 0) for the bare 3DGS
        render; it blends nothing (no GSFixer). Within the held-out frames' reach it follows their choice per region, as a
        repaired view there does (:meth:`_near_choice`): on tank:drift (40 frames, seed 1) the
        two skipped held-out frames went from 20.76 and 20.86 dB (their 3DGS render where it
        covers) to 22.26 and 21.70, where the held-out frames had measured the mesh better.
        Elsewhere the planner found that the map explains it (few holes, 3DGS and mesh agree),
        so the 3DGS render is trusted wherever it covers the view, and only its holes take the
        fallback the run measured best there (mesh fill + Telea where no choice was
        measured)."""
        from gsfix_online.repair.fallback import FEATHER_PX, REGIONS, Choice, fixer_only

        im = rec.images
        if "inpaint" not in im:
            return None, 0.0
        if self.fallback is None or "mesh_inpaint" not in im:
            return replace(fixer_only(), per_region=dict.fromkeys(REGIONS, "inpaint")), 0.0
        near = self._near_choice(rec)
        if near is not None:
            return near, FEATHER_PX
        measured = self._measured_for(rec)
        if measured is None:  # a lone held-out frame: no measurement but its own
            return replace(fixer_only(), per_region=dict.fromkeys(REGIONS, "inpaint")), 0.0
        choice = Choice.from_json(json.dumps(measured)).without_fixer()
        trusted = dict(choice.per_region, both="inpaint", gs_only="inpaint")  # the 3DGS render
        return replace(choice, per_region=trusted, share={}), 0.0

    def _skipped_output(self, rec: ViewRecord) -> npt.NDArray[np.uint8]:
        """The 2D output of a view the planner skipped (:meth:`_skipped_recipe`)."""
        from gsfix_online.repair.fallback import compose, regions

        im = rec.images
        choice, feather_px = self._skipped_recipe(rec)
        if choice is None:
            return im["gs"]
        cands = {k: im[k] for k in ("inpaint", "mesh_inpaint", "ref_inpaint") if k in im}
        return compose(cands, regions(im["alpha"], im["valid"]), choice, feather_px)

    def _output_recipe(self, rec: ViewRecord) -> tuple[Any, float, float]:
        """How a view's delivered 2D output (``output_or_gs``) was composed: (the choice per
        region, the seam feathering in px, the sigma a blend blurs its fallback by: 0 for a run
        recorded before, whose blends were per-pixel means), or (None, 0, 0) for the bare 3DGS
        render."""
        from gsfix_online.repair.fallback import FEATHER_PX, REGIONS, Choice, fixer_only

        m = rec.model
        if rec.repair and "output" in rec.images:
            if "choice" not in m:  # GSFixer everywhere (a run from before the choice)
                return fixer_only(), 0.0, 0.0
            per_region = {r: str(m["choice"].get(r, "fixed")) for r in REGIONS}
            share = {r: float(w) for r, w in m.get("choice_share", {}).items()}
            return (Choice(per_region, {}, {}, 0, "", share), float(m.get("feather_px", FEATHER_PX)),
                    float(m.get("detail_px", 0.0)))  # fmt: skip
        skipped_near = m.get("choice_from") == "held-out frames (skipped)"
        if rec.fill and "output" in rec.images and not skipped_near:  # the planner's fill
            return replace(fixer_only(), per_region=dict.fromkeys(REGIONS, "inpaint")), 0.0, 0.0
        return (*self._skipped_recipe(rec), 0.0)

    def view_provenance(self, rec: ViewRecord) -> Any:
        """Where each pixel of the view's delivered output came from
        (:class:`.provenance.Provenance`); None without its renders."""
        from gsfix_online.repair.provenance import candidate_sources, provenance, single

        im = rec.images
        if not {"gs", "alpha", "valid"} <= set(im):
            return None
        sources = candidate_sources(im["alpha"], im["valid"], ref_valid=im.get("ref_valid"),
                                    gs_synthesised=im.get("gs_synthesised"))  # fmt: skip
        choice, feather_px, detail_px = self._output_recipe(rec)
        if choice is None:
            return single(sources, "gs")
        return provenance(sources, self.composed_region(rec), choice, feather_px, detail_px)

    def composed_region(self, rec: ViewRecord) -> npt.NDArray[np.uint8] | None:
        """[H, W] the regions the view's output was composed by (index into
        ``fallback.REGIONS``, or ``FLAT``): the repair node's for a repaired view, else those
        of its renders; None without its renders."""
        from gsfix_online.repair.fallback import regions

        im = rec.images
        region = im.get("region") if rec.repair else None
        if region is None and {"alpha", "valid"} <= set(im):
            region = regions(im["alpha"], im["valid"])
        return region

    def finish_provenance(self) -> dict[int, dict[str, float]]:
        """Write every view's ``provenance.png`` (colours with a legend) and ``provenance.npz``
        (the source index, its confidence and the synthesised share per pixel, and the regions
        the output was composed by); returns each view's shares of the sources."""
        import io

        from gsfix_online.repair.fallback import REGIONS
        from gsfix_online.repair.provenance import image, to_npz

        shares = {}
        for vid, rec in self.views.items():
            prov = self.view_provenance(rec)
            if prov is None:
                continue
            write_png(self._dir(rec) / "provenance.png", image(prov))
            buf = io.BytesIO()
            # region: index into regions ("flat": a far view's no-map hole given to the fill)
            np.savez_compressed(buf, **to_npz(prov), region=self.composed_region(rec),
                                regions=np.array([*REGIONS, "flat"]))  # fmt: skip
            atomic_write_bytes(self._dir(rec) / "provenance.npz", buf.getvalue())
            shares[vid] = {k: round(v, 4) for k, v in prov.shares().items()}
        return shares

    def measure_fallbacks(self) -> bool:
        """When no repair brought the run's measured choice (the planner skipped every view)
        but the held-out frames have ground truth, the choice among the fallbacks per region,
        measured here on those frames as the repair node would (GSFixer never ran, so it takes
        no region), and its reach (the farthest held-out frame's keyframe distance); True if
        it measured one."""
        from gsfix_online.repair.fallback import (
            RegionErrors,
            accumulate,
            held_out_choices,
            regions,
        )

        frames = [self.views[v] for v in self.groups.get("holdout", ()) if v in self.views]
        if self.fallback is not None or self.gt_dir is None or not frames:
            return False
        each, ids, reach = [], [], []
        for rec in frames:
            im, gt_path = rec.images, self.gt_dir / f"{rec.name}.png"
            if not gt_path.is_file() or not {"alpha", "valid", "inpaint", "mesh_inpaint"} <= set(
                im
            ):
                continue
            h, w = im["alpha"].shape[:2]
            cands = {k: im[k] for k in ("inpaint", "mesh_inpaint", "ref_inpaint") if k in im}
            cands["fixed"] = im["inpaint"]  # no repair: never better than a fallback
            each.append(RegionErrors())
            accumulate(each[-1], read_png_rgb(gt_path, w, h), cands,
                       regions(im["alpha"], im["valid"]))  # fmt: skip
            ids.append(rec.view_id)
            reach.append(rec.keyframe_distance_m)
        if not each:
            return False
        h = held_out_choices(each, ids, min_fraction=0.01)
        why = "measured by the writer on the held-out frames (no view was repaired)"
        self.fallback = json.loads(replace(h.all, why=f"{why}; {h.all.why}").to_json())
        self.fallback_without = {
            v: None if o is None else json.loads(replace(o, why=f"{why}, without frame {v}; "
                                                                f"{o.why}").to_json())
            for v, o in h.without.items()
        }  # fmt: skip
        self.holdout_reach_m = None if None in reach else max(reach)  # type: ignore[type-var]
        return True

    def finish_skipped(self) -> None:
        """The 2D output of every skipped view within the held-out frames' reach
        (:meth:`_skipped_output`), written as its ``output.png`` with the choice it followed;
        made when the metrics are written, once the run's choice is final (measured here on
        the held-out frames when no repair brought one: :meth:`measure_fallbacks`)."""
        self.measure_fallbacks()
        for rec in self.views.values():
            im = rec.images
            if rec.repair is not False or not {"inpaint", "mesh_inpaint"} <= set(im):
                continue
            near = self._near_choice(rec)
            if near is None:
                continue
            im["output"] = self._skipped_output(rec)
            rec.model.update(choice=near.per_region, choice_from="held-out frames (skipped)")
            write_png(self._dir(rec) / "output.png", im["output"])

    def view_metrics(
        self, rec: ViewRecord
    ) -> tuple[dict[str, dict[str, float]], dict[str, dict[str, MaskedScores]]]:
        """PSNR/SSIM of each stage against the view's ground truth, and per region class
        (stage -> region -> scores; regions without pixels left out). Empty without truth."""
        from gsfix_online.core.metrics import region_scores
        from gsfix_online.repair.fallback import regions

        if self.gt_dir is None:
            return {}, {}
        gt_path = self.gt_dir / f"{rec.name}.png"
        im = rec.images
        if not gt_path.is_file() or "gs" not in im:
            return {}, {}
        h, w = im["gs"].shape[:2]
        gt = read_png_rgb(gt_path, w, h)
        region = regions(im["alpha"], im["valid"]) if "alpha" in im and "valid" in im else None
        out, per_region = {}, {}
        for stage, img in self._stage_images(rec).items():
            whole, by_region = region_scores(img, gt, region, REGIONS)
            out[stage] = {"psnr_db": whole.psnr_db, "ssim": whole.ssim}
            if by_region:
                per_region[stage] = by_region
        return out, per_region

    def map_fidelity(self, rec: ViewRecord) -> float | None:
        """PSNR (dB) of the final map's render against what the view delivered (its output),
        for a view whose output was distilled: how much of the delivered repair the map keeps.
        Needs no ground truth; None when either image is missing."""
        from gsfix_online.core.metrics import psnr

        im = rec.images
        target = im.get("distilled")  # the planner's fill of a skipped view, or the output
        if not rec.distils or "final" not in im or target is None:
            return None
        return psnr(im["final"], target)

    def map_sharpness(self, rec: ViewRecord) -> tuple[float | None, float | None]:
        """Sharpness (:func:`core.metrics.sharpness`) of the final map's render over that of
        what the view delivered seen through the renderer's low-pass (``EPS2D``: the most a
        render of a map that holds it exactly can have), and over that of the output itself
        (raw), for a view whose output was distilled: under 1 the map renders it blurrier (a
        veil); no ground truth needed. None when an image is missing or flat."""
        from gsfix_online.core.metrics import sharpness
        from gsfix_online.mapping.splat.render_output import EPS2D

        im = rec.images
        target = im.get("distilled")
        if not rec.distils or "final" not in im or target is None:
            return None, None
        final = sharpness(im["final"])
        ratios = [final / b if b > 0 else None
                  for b in (sharpness(target, footprint_px2=EPS2D), sharpness(target))]  # fmt: skip
        return ratios[0], ratios[1]

    def metrics(self, extra: dict[str, Any] | None = None) -> dict[str, Any]:
        self.finish_baselines()
        self.finish_skipped()
        provenance = self.finish_provenance()
        views = []
        reasons: dict[str, int] = {}
        by_region: dict[int, dict[str, dict[str, MaskedScores]]] = {}
        for vid in sorted(self.views):
            rec = self.views[vid]
            m, by_region[vid] = self.view_metrics(rec)
            if rec.repair is False:
                key = rec.reason.split(" (")[0]
                reasons[key] = reasons.get(key, 0) + 1
            files = {k: f"views/{rec.name}/{k}.png" for k in VIEW_FILES}
            files = {k: p for k, p in files.items() if (self.out / p).is_file()}
            sharp, sharp_raw = self.map_sharpness(rec)
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
                    "map_fidelity_db": self.map_fidelity(rec),
                    "map_sharpness": sharp,
                    "map_sharpness_raw": sharp_raw,
                    # each source's share of the delivered output's pixels (provenance.npz)
                    "provenance": provenance.get(vid),
                    "regions": {
                        st: {r: _region_json(x) for r, x in rs.items()}
                        for st, rs in by_region[vid].items()
                    },  # fmt: skip
                }
            )
        stages = _stage_means(views)
        groups, region_groups = {}, {}
        if self.groups:
            grouped = {vid for ids in self.groups.values() for vid in ids}
            members = {name: [v for v in views if v["view_id"] in ids]
                       for name, ids in self.groups.items()}  # fmt: skip
            members["novel"] = [v for v in views if v["view_id"] not in grouped]
            for name, vs in members.items():
                groups[name] = _stage_means(vs)
                region_groups[name] = _region_means([by_region[v["view_id"]] for v in vs])
        n_rep = sum(1 for v in views if v["repair"])
        timing_keys = sorted({k for v in views for k in v["timings_s"]})
        totals = {
            k: float(np.nansum([v["timings_s"].get(k, math.nan) for v in views]))
            for k in timing_keys
        }
        fidelity = {v["view"]: v["map_fidelity_db"] for v in views
                    if v["map_fidelity_db"] is not None}  # fmt: skip
        summary = {
            "views": len(views),
            "repaired": n_rep,
            "skipped": len(views) - n_rep,
            "skip_reasons": reasons,
            "ground_truth": str(self.gt_dir) if self.gt_dir else None,
            "stages": stages,
            "best_classical": _best(stages, CLASSICAL),
            "best_classical_maps": _best(stages, tuple(c for c in CLASSICAL if c != "ref_inpaint")),
            "groups": groups,
            "regions": _region_means(list(by_region.values())),
            "region_groups": region_groups,
            "fallback": self.fallback,
            # how far it holds (None: not measured on held-out frames), and the trainer's
            # choice that views beyond held (fallback.for_view; the map server follows both)
            "holdout_reach_m": self.holdout_reach_m,
            "trainer_choice": self.trainer_choice,
            # per held-out frame (by its name), the choice the other held-out frames measured,
            # which the frame followed (None: it was the only one)
            "fallback_without": {f"{v:03d}": c for v, c in sorted(self.fallback_without.items())},
            # repaired views per source of their choice (repair.fallback.for_view): the
            # held-out frames' per region near the keyframes, the mesh first beyond
            "choice_from": dict(
                Counter(
                    str(v["model"].get("choice_from", ""))
                    for v in views
                    if v["repair"] and v["model"].get("choice_from")
                )
            ),
            # the final map against the delivered outputs (no ground truth): the median, and
            # the views it keeps worst (under MAP_FIDELITY_LOW_DB: a veil or a hole)
            "map_fidelity": {
                "median_db": float(np.median(list(fidelity.values()))) if fidelity else None,
                "low": sorted(k for k, x in fidelity.items() if x < MAP_FIDELITY_LOW_DB),
                "low_below_db": MAP_FIDELITY_LOW_DB,
                # views the final map renders blurrier than what they delivered (a veil)
                "blurred": sorted(
                    v["view"]
                    for v in views
                    if v["map_sharpness"] is not None and v["map_sharpness"] < MAP_SHARPNESS_LOW
                ),
                "blurred_below": MAP_SHARPNESS_LOW,
            },
            "stage_time_totals_s": totals,
        }
        return _clean({"summary": summary, "views": views, **(extra or {})})

    def write(self, extra: dict[str, Any] | None = None, title: str = "GSFix3D repair") -> dict:
        """Write ``metrics.json`` and ``report.html``; returns the metrics."""
        from gsfix_online.core import pages as page
        from gsfix_online.core.pages import Plot, Report, Table, ViewRow, write_report

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
        for group, regions in [("", s["regions"]), *s["region_groups"].items()]:
            if regions:
                tables.append(region_table(regions, f": {group} views" if group else ""))
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
                # no ground truth needed: how much of the output was synthesised, and how
                # closely and how sharply the final map renders what the view delivered
                (v["provenance"] or {}).get("synthesised"),
                v["map_fidelity_db"],
                v["map_sharpness"],
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
            "synthesised",
            "map keeps dB",
            "map sharpness",
        )
        tables.append(Table("Views", cols, vrows))
        kept = m.get("keyframes_kept") or {}
        if kept.get("keyframes"):
            krows = [(r["keyframe_id"], f"{r['view_id']:03d}" if r["view_id"] >= 0 else "",
                      r["before_db"], "no longer stored" if r["after_db"] is None else r["after_db"],
                      "" if r["change_db"] is None else r["change_db"])
                     for r in sorted(kept["keyframes"], key=lambda r: r["view_id"] < 0)]  # fmt: skip
            tables.append(Table(
                "Input keyframes: their render before the repaired views were distilled and in "
                "the final map (PSNR against the frame; the neighbours of a repaired view first)",
                ("keyframe", "next to view", "before dB", "final dB", "change dB"), krows,
            ))  # fmt: skip
        trows = [(k, v) for k, v in s["stage_time_totals_s"].items()]
        trows += [(k, v) for k, v in (m.get("timings_s") or {}).items()]
        tables.append(Table("Time (s)", ("stage", "seconds"), trows))
        views = []
        for v in m["views"]:
            images = {
                k: v["files"][k]
                for k in (
                    "gs",
                    "gs_inpaint",
                    "mesh",
                    "inpaint",
                    "inpaint_ns",
                    "inpaint_fsr",
                    "mesh_inpaint",
                    "fixed",
                    "output",
                    "final",
                    "provenance",
                )  # fmt: skip
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
        if s["best_classical"]:
            b = s["best_classical"]
            # an exact image's PSNR is infinite, null in metrics.json
            db = "infinite PSNR" if b["psnr_db"] is None else f"{b['psnr_db']:.2f} dB"
            notes.append(f"Best classical baseline: {b['stage']} ({db}, SSIM {b['ssim']:.3f}).")
        write_report(self.out / "report.html", Report(title, tables, views, notes, plots))
        return m


def region_rows(
    regions: Mapping[str, Mapping[str, Mapping[str, float]]],  # row -> region -> psnr_db, ssim
) -> tuple[list[str], list[list[Any]]]:
    """Columns and rows of a table of PSNR and SSIM per row (stage, method) and region class."""
    cols = ["stage"] + [f"{r} {k}" for r in REGIONS for k in ("dB", "SSIM")]
    rows = [
        [name, *[by.get(r, {}).get(k) for r in REGIONS for k in ("psnr_db", "ssim")]]
        for name, by in regions.items()
    ]
    return cols, rows


def region_table(
    regions: dict[str, dict[str, dict[str, float]]],  # stage -> region -> psnr_db, ssim, pixels
    title_suffix: str = "",
) -> Any:  # inspection.report.Table
    """PSNR and SSIM per stage (rows) and region class (columns), and each region's pixels."""
    from gsfix_online.core.pages import Table

    pixels = {r: max((by[r]["pixels"] for by in regions.values() if r in by), default=0)
              for r in REGIONS}  # fmt: skip
    total = sum(pixels.values()) or 1
    share = ", ".join(f"{r} {100 * n / total:.1f} %" for r, n in pixels.items())
    title = f"Error per region class{title_suffix} (share of pixels: {share})"
    return Table(title, *region_rows(regions))
