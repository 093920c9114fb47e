"""Far views' holes no map covers: blend GSFixer into mesh + Telea only where they agree?

A far view's holes that neither map covers take GSFixer and mesh + Telea half and half
(``fallback.FAR_NEITHER_SHARE``), or mesh + Telea alone where the hole's surroundings are flat
(``FLAT``). Where the two fills disagree on a hole's colour the half-and-half output sits between
them. This recomposes every far view of finished runs from the candidates they saved
(``fixed.png``, ``inpaint.png``, ``mesh_inpaint.png``; no model runs), as ``far_regions`` composes
it, and then gives each hole (connected part of the ``neither`` region) whose mean colours in the
two fills differ by more than a threshold (RGB levels, Euclidean) to mesh + Telea alone. Per
threshold: the PSNR over the run's best classical baseline (``summary.best_classical``, per view)
and the views under it. Threshold ``inf`` is the rule as shipped, 0 mesh + Telea in every hole.

    .venv/bin/python benchmarks/far_neither_agreement.py RUN [RUN ...] [--json FILE]

(RUN: a demo's output folder, with ``repair/`` and the ground truth in ``scene/novel/color``.)
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_far_regions import far_view  # noqa: E402

from gsfix_online.core.io import atomic_write_text  # noqa: E402
from gsfix_online.core.metrics import psnr  # noqa: E402
from gsfix_online.repair.fallback import FLAT, NEITHER, compose, far_regions  # noqa: E402
from gsfix_online.repair.outputs import read_png_rgb  # noqa: E402

THRESHOLDS = (0.0, 8.0, 16.0, 24.0, 32.0, math.inf)


def view_row(run: Path, v: dict[str, Any], classical: str) -> dict[str, Any] | None:
    """One far view with a GSFixer share in its no-map holes: PSNR over the classical baseline
    per threshold, None for any other view."""
    fv = far_view(run, v)
    if fv is None or not fv.choice.share.get("neither"):
        return None
    d = run / "repair/views" / v["view"]
    gt, choice, feather, detail, cands = fv.gt, fv.choice, fv.feather, fv.detail, fv.cands
    region, grown = fv.region, fv.grown
    base = far_regions(region, cands, choice, feather, holes=grown)
    n, label = cv2.connectedComponents((base == NEITHER).astype(np.uint8), connectivity=8)
    fixed, telea = (cands[c].astype(np.float32) for c in ("fixed", "mesh_inpaint"))
    differ = [0.0] + [
        float(np.linalg.norm(fixed[label == i].mean(0) - telea[label == i].mean(0)))
        for i in range(1, n)
    ]
    floor = psnr(read_png_rgb(d / f"{classical}.png"), gt)
    out: dict[str, Any] = {"view": v["view"], "holes_differ": differ[1:],
                           "exact_db": psnr(compose(cands, base, choice, feather, detail),
                                            read_png_rgb(d / "output.png")),
                           "over_floor_db": {}}  # fmt: skip
    for th in THRESHOLDS:
        reg = base.copy()
        for i in range(1, n):
            if differ[i] > th:
                reg[label == i] = FLAT
        out["over_floor_db"][str(th)] = (
            psnr(compose(cands, reg, choice, feather, detail), gt) - floor
        )
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--json", type=Path, help="write the results here")
    a = ap.parse_args()
    res = []
    for run in a.runs:
        m = json.loads((run / "repair/metrics.json").read_text())
        classical = m["summary"]["best_classical"]["stage"]
        rows = [r for v in m["views"] if (r := view_row(run, v, classical)) is not None]
        res.append({"run": str(run), "classical": classical, "views": rows})
    rows = [r for x in res for r in x["views"]]
    print(f"{len(rows)} far views of {len(res)} runs; PSNR over the best classical baseline, dB")
    print("| threshold | mean | views under | worst |\n|---:|---:|---:|---:|")
    for th in map(str, THRESHOLDS):
        d = [r["over_floor_db"][th] for r in rows]
        print(f"| {th} | {statistics.mean(d):+.3f} | {sum(x < 0 for x in d)} | {min(d):+.2f} |")
    if a.json:
        atomic_write_text(a.json, json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
