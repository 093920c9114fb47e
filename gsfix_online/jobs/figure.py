"""Side-by-side figure of a repair run's views: the ground truth, the run's best classical
baseline (``summary.best_classical``: what the mesh and OpenCV alone give, the floor), the 3DGS
and mesh renders, GSFixer, the delivered output, the final map's render and the output's
provenance (what was observed and what synthesised), one row per view, each image tile labelled
with its PSNR against the ground truth.

The tiles are the run's own files (``views/NNN/{gs,mesh,<best>,fixed,output,final,
provenance}.png``, see :mod:`gsfix_online.repair.outputs`); a missing one is a grey tile marked
"-". ``make demo`` writes
``outputs/demo/figure.png`` with it; ``benchmarks/figure_views.py`` draws any run's.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from gsfix_online.core.metrics import psnr
from gsfix_online.repair.outputs import read_png_rgb, write_png

BEST = "best_classical"  # the column of the run's best classical baseline from its maps
COLUMNS = (
    ("gt", "ground truth"),
    (BEST, "best classical"),
    ("ref_inpaint", "real frames warped"),
    ("gs", "3DGS"),
    ("mesh", "mesh"),
    ("fixed", "GSFixer"),
    ("output", "output"),
    ("final", "final map"),
    ("provenance", "provenance"),
)
# The classical baselines' short names (repair.outputs.CLASSICAL)
CLASSICAL_TITLES = {
    "mesh_fill": "mesh fill",
    "inpaint": "mesh fill + Telea",
    "inpaint_ns": "mesh fill + NS",
    "inpaint_fsr": "mesh fill + FSR",
    "mesh_inpaint": "mesh + Telea",
    "ref_inpaint": "real frames warped + Telea",
}
UNSCORED = ("gt", "mesh", "provenance")  # tiles without a PSNR label
LABEL_PX = 18  # the white bar above each tile
GAP_PX = 2  # white gap right of and below each tile
MISSING = 230  # grey of a tile whose image the run did not write


def _label(tile: npt.NDArray[np.uint8], text: str) -> npt.NDArray[np.uint8]:
    bar = np.full((LABEL_PX, tile.shape[1], 3), 255, np.uint8)
    cv2.putText(bar, text, (3, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([bar, tile])


def best_classical(run: Path) -> str:
    """The run's best classical baseline from its maps (``metrics.json``
    ``summary.best_classical_maps``, the best without the reference warp, which has its own
    column; ``best_classical`` in runs from before it; mesh + Telea, the fallback floor, when
    the run was not scored)."""
    s = json.loads((run / "metrics.json").read_text())["summary"]
    best = s.get("best_classical_maps", s.get("best_classical"))
    return str(best["stage"]) if best else "mesh_inpaint"


def views_figure(run: Path, gt_dir: Path, view_ids: list[int]) -> npt.NDArray[np.uint8]:
    """The figure of ``view_ids`` of the run folder ``run``, ground truth ``gt_dir/NNN.png``:
    [rows x (LABEL_PX + H + GAP_PX) (+ the provenance legend), len(COLUMNS) x (W + GAP_PX), 3]
    RGB."""
    if not view_ids:
        raise ValueError("no views to draw")
    best = best_classical(run)
    rows = []
    legend_w = 0  # a provenance tile's width: its legend, of all the views, goes below them
    for vid in view_ids:
        gt_path = gt_dir / f"{vid:03d}.png"
        if not gt_path.is_file():
            raise FileNotFoundError(f"no ground truth for view {vid:03d}: {gt_path}")
        gt = read_png_rgb(gt_path)
        h, w = gt.shape[:2]
        tiles = []
        for key, title in COLUMNS:
            if key == BEST:
                key, title = best, CLASSICAL_TITLES.get(best, best)
            path = gt_path if key == "gt" else run / "views" / f"{vid:03d}" / f"{key}.png"
            if not path.is_file():
                img, text = np.full((h, w, 3), MISSING, np.uint8), f"{title}: -"
            elif key == "provenance":  # the view's colours above (and left of) their legend
                img, text = read_png_rgb(path)[:h, :w], title
                legend_w = w
            else:
                img = read_png_rgb(path, w, h)
                text = title if key in UNSCORED else f"{title} {psnr(img, gt):.2f} dB"
            tiles.append(_label(img, f"{vid:03d} {text}" if key == "gt" else text))
        pad = ((0, GAP_PX), (0, GAP_PX), (0, 0))
        rows.append(np.hstack([np.pad(t, pad, constant_values=255) for t in tiles]))
    legend = provenance_legend(run, view_ids, legend_w) if legend_w else None
    if legend is not None and legend.size:
        width = rows[0].shape[1]
        legend = legend[:, :width]
        x = width - legend.shape[1]  # under the provenance column, right-aligned
        strip = np.full((legend.shape[0], width, 3), 255, np.uint8)
        strip[:, x:] = legend
        rows.append(strip)
    return np.vstack(rows)


def provenance_legend(run: Path, view_ids: list[int], width: int) -> npt.NDArray[np.uint8]:
    """The legend of every source that is the main one of some pixel in the views'
    ``provenance.npz`` (and of blends, where a pixel's main source weighs under
    provenance.BLEND_BELOW): a source one view lacks is still named for the others."""
    from gsfix_online.repair.provenance import BLEND_BELOW, SOURCES, legend_strip

    present, blends = set(), False
    for vid in view_ids:
        path = run / "views" / f"{vid:03d}" / "provenance.npz"
        if not path.is_file():
            continue
        with np.load(path) as z:
            names = [str(n) for n in z["sources"]]
            present |= {SOURCES.index(names[i]) for i in np.unique(z["source"])
                        if names[i] in SOURCES}  # fmt: skip
            blends |= bool((z["confidence"].astype(np.float32) < BLEND_BELOW).any())
    return legend_strip(sorted(present), blends, width)


def repaired_views(run: Path, gt_dir: Path, n: int) -> list[int]:
    """The first ``n`` views the run repaired (metrics.json) that have a ground truth; the
    user's views come first (held-out frames follow them in the run's numbering)."""
    views = json.loads((run / "metrics.json").read_text())["views"]
    ids = [v["view_id"] for v in views if v.get("repair")]
    return [i for i in ids if (gt_dir / f"{i:03d}.png").is_file()][:n]


def write_views_figure(
    run: Path,
    out: Path,
    gt_dir: Path | None = None,
    views: list[int] | None = None,
    scale: float = 1.0,
) -> tuple[int, int]:
    """Draw the figure (default: the first 4 repaired views, ground truth ``run/work/gt``),
    resized by ``scale`` (area average), into the PNG ``out``; returns its (width, height)."""
    gt_dir = gt_dir or run / "work" / "gt"
    img = views_figure(run, gt_dir, views or repaired_views(run, gt_dir, 4))
    if scale != 1.0:
        size = (round(img.shape[1] * scale), round(img.shape[0] * scale))
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_png(out, img)
    return img.shape[1], img.shape[0]
