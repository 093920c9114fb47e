"""How much can any choice among the candidates gain over the reference warp at held-out frames?

For each repair run folder given (``--holdout``: the held-out frames' camera images in
``RUN/work/gt``), per held-out frame: the PSNR of ``ref_inpaint`` (the warp of the real frames,
its holes from the mesh, then Telea), and what an *oracle* would gain over it by taking, in every
block of ``B`` x ``B`` pixels, whichever candidate is closest to the truth there (``ref_inpaint``,
``inpaint``: the 3DGS render with mesh fill and Telea, ``mesh_inpaint``, and GSFixer's ``fixed``
where the frame was repaired), for B = 1 (per pixel), 8, 16 and 32; and the best single blend
weight between the warp and the 3DGS render. No rule without the truth can do better than the
oracle at its block size, so a block oracle under a bar says the bar needs a better candidate,
not a better choice.

    .venv/bin/python benchmarks/warp_headroom.py RUN1 RUN2 ... [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import numpy as np

from gsfix_online.repair.outputs import read_png_rgb

CANDIDATES = ("ref_inpaint", "inpaint", "mesh_inpaint", "fixed")
BLOCKS = (1, 8, 16, 32)
EDGE_LEVELS = 8.0  # grey levels per pixel: the truth's gradient that makes an edge pixel


def db(mse: float) -> float:  # an exact image scores 100 dB, not infinity
    return float(10 * np.log10(255.0**2 / max(mse, 255.0**2 * 1e-10)))


def frame_row(view: Path, gt_path: Path) -> dict[str, float] | None:
    if not gt_path.is_file() or not (view / "ref_inpaint.png").is_file():
        return None
    gt = read_png_rgb(gt_path).astype(np.float64)
    h, w = gt.shape[:2]
    cands = {c: read_png_rgb(view / f"{c}.png", w, h).astype(np.float64)
             for c in CANDIDATES if (view / f"{c}.png").is_file()}  # fmt: skip
    err = np.stack([((x - gt) ** 2).mean(-1) for x in cands.values()])  # [C, H, W]
    base = db(float(err[0].mean()))
    row = {"ref_inpaint_db": base, "candidates": float(len(cands))}
    for b in BLOCKS:
        crop = err[:, : h // b * b, : w // b * b]  # whole blocks; the warp scored on them too
        e = crop.reshape(len(err), h // b, b, w // b, b).mean((2, 4))
        row[f"oracle_{b}px_gain_db"] = db(float(e.min(0).mean())) - db(float(crop[0].mean()))
    warp, gs = cands["ref_inpaint"], cands["inpaint"]
    # where the warp loses: the truth's edges (luma gradient over EDGE_LEVELS per pixel) against
    # flat pixels; and how much a global gain and offset fitted to the truth would add
    gy, gx = np.gradient(gt.mean(-1))
    edge = np.hypot(gx, gy) > EDGE_LEVELS
    row["edge_share"] = float(edge.mean())
    row["ref_inpaint_edges_db"] = db(float(err[0][edge].mean())) if edge.any() else float("nan")
    row["ref_inpaint_flat_db"] = db(float(err[0][~edge].mean())) if (~edge).any() else float("nan")
    x = np.stack([warp.mean(-1).ravel(), np.ones(h * w)], 1)
    gain, offset = np.linalg.lstsq(x, gt.mean(-1).ravel(), rcond=None)[0]
    row["exposure_oracle_gain_db"] = db(float(((np.clip(warp * gain + offset, 0, 255) - gt) ** 2
                                               ).mean())) - base  # fmt: skip
    row["best_blend_gain_db"] = max(
        db(float(((a * warp + (1 - a) * gs - gt) ** 2).mean())) for a in np.linspace(0, 1, 21)
    ) - base  # fmt: skip
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="repair run folders made with --holdout")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    out = {}
    print("| run | frames | ref_inpaint median dB | oracle gain per pixel | per 8 px | per 16 px "
          "| per 32 px | best single blend with 3DGS |\n|---|---:|---:|---:|---:|---:|---:|---:|")  # fmt: skip
    for run in a.runs:
        rows = {}
        for view in sorted((run / "views").iterdir()):
            r = frame_row(view, run / "work" / "gt" / f"{view.name}.png")
            if r is not None:
                rows[view.name] = r
        out[str(run)] = rows
        if not rows:
            continue

        def med(k: str, rows: dict = rows) -> float:  # type: ignore[type-arg]
            return statistics.median(r[k] for r in rows.values())

        gains = " | ".join(f"+{med(f'oracle_{b}px_gain_db'):.2f}" for b in BLOCKS)
        print(f"| {run.name} | {len(rows)} | {med('ref_inpaint_db'):.2f} | {gains} | "
              f"{med('best_blend_gain_db'):+.2f} |")  # fmt: skip
    print(
        "\nwhere the warp loses, per run (range over its frames): edge share, PSNR at edges, "
        "on flat pixels, gain from a global exposure fitted to the truth"
    )
    for run, rows in out.items():
        if rows:
            rng = {k: (min(r[k] for r in rows.values()), max(r[k] for r in rows.values()))
                   for k in ("edge_share", "ref_inpaint_edges_db", "ref_inpaint_flat_db",
                             "exposure_oracle_gain_db")}  # fmt: skip
            print(f"{Path(run).name}: " + ", ".join(f"{k} {lo:.2f}..{hi:.2f}"
                                                    for k, (lo, hi) in rng.items()))  # fmt: skip
    if a.json:
        a.json.write_text(json.dumps({"blocks_px": BLOCKS, "runs": out}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
