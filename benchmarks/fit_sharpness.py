"""How sharp does the final map render a repaired view when fitted on it for longer?

Loads a demo run's final map (``RUN/repair/work/map.pt``, with the splat node's mapper settings
from ``RUN/repair/work/graph.yaml``), picks the stored repaired view at the camera of each
view given, and fits it as polish does (:meth:`Mapper.train_step` on the view with
``--partners`` other repaired views drawn each step, the distillation loss) for ``--iters``
steps. Every ``--every`` steps it renders the view and prints: its PSNR against the output it
was fitted to (the map's fidelity), the sharpness ratio against the output itself (issue 43's
measure) and against the output through the renderer's low-pass (``render_output.EPS2D``: the
writer's ``map_sharpness``), and the PSNR against the ground truth beside the output's. The
run's files are only read.

    .venv/bin/python benchmarks/fit_sharpness.py RUN --views 4 --iters 80 --partners 2 \\
        [--json benchmarks/results/sharpness_footprint_cpu.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def fit_view(run: Path, m: Any, cfg: Any, view: dict[str, Any], a: argparse.Namespace) -> dict:
    """Fit one view's stored repair ``a.iters`` steps; its scores every ``a.every`` steps."""
    import torch

    from gsfix_online.core.metrics import psnr, sharpness
    from gsfix_online.mapping.splat.render_output import EPS2D
    from gsfix_online.mapping.splat.views import REPAIRED_FRAME_ID
    from gsfix_online.repair.outputs import read_png_rgb

    cam = view["camera"]
    K = np.asarray(cam["K"], np.float64).reshape(3, 3)
    T_view = np.asarray(cam["T_world_cam"], np.float64).reshape(4, 4)
    W, H = cam["width"], cam["height"]
    repaired = [kf for kf in m.store if kf.frame.frame_id == REPAIRED_FRAME_ID]
    kf = min(repaired, key=lambda k: float(np.abs(np.asarray(k.frame.T_world_cam) - T_view).sum()))
    T = m.pose_for(T_view)
    out = read_png_rgb(run / f"repair/views/{view['view']}/output.png")
    gt = read_png_rgb(run / f"scene/novel/color/{view['view']}.png", W, H)
    base_raw, base_lp = sharpness(out), sharpness(out, footprint_px2=EPS2D)

    def score(step: int) -> dict[str, float]:
        with torch.no_grad():
            img = m.render(T, K, W, H).color.clamp(0, 1).cpu().numpy()
        s = sharpness(img)
        return {"step": step, "fidelity_db": psnr(img, out), "sharpness_raw": s / base_raw,
                "sharpness": s / base_lp, "truth_db": psnr(img, gt)}  # fmt: skip

    rows = [score(0)]
    others = [k for k in repaired if k is not kf]
    t0 = time.perf_counter()
    for i in range(a.iters):
        pick = m.rng.choice(len(others), min(a.partners, len(others)), replace=False)
        batch = [m._keyframe_view(kf)] + [m._keyframe_view(others[int(j)]) for j in pick]
        m.train_step(batch, lam=cfg.distill_lambda, l1_weight=1.0 - cfg.distill_lambda)
        if (i + 1) % a.every == 0 or i + 1 == a.iters:
            rows.append(score(i + 1))
    return {"output_truth_db": psnr(out, gt), "steps": rows, "fit_s": time.perf_counter() - t0}


def main() -> int:
    import torch
    import yaml

    from gsfix_online.core.config import build
    from gsfix_online.mapping.splat.mapper import MapperConfig
    from gsfix_online.mapping.splat.render_output import EPS2D
    from gsfix_online.services.splat import load_snapshot

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path, help="a gsfix-online demo --out folder")
    ap.add_argument("--views", type=int, nargs="+", required=True, help="view indices")
    ap.add_argument("--iters", type=int, default=80)
    ap.add_argument("--partners", type=int, default=2)
    ap.add_argument("--every", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)

    graph = yaml.safe_load((a.run / "repair/work/graph.yaml").read_text())
    cfg = build(MapperConfig, base=graph["nodes"]["splat"]["params"]["mapper"])
    views = json.loads((a.run / "repair/metrics.json").read_text())["views"]
    result: dict[str, Any] = {"run": str(a.run), "iters": a.iters, "partners": a.partners,
                              "eps2d": EPS2D, "views": {}}  # fmt: skip
    for vi in a.views:
        m = load_snapshot(cfg, a.run / "repair/work/map.pt")  # afresh per view
        r = result["views"][views[vi]["view"]] = fit_view(a.run, m, cfg, views[vi], a)
        print(f"view {views[vi]['view']} (output {r['output_truth_db']:.2f} dB against the "
              f"truth; {r['fit_s']:.0f} s)")  # fmt: skip
        print("| steps | fidelity dB | sharpness (raw) | sharpness (low-pass) | truth dB |")
        print("|---:|---:|---:|---:|---:|")
        for x in r["steps"]:
            print(f"| {x['step']} | {x['fidelity_db']:.2f} | {x['sharpness_raw']:.3f} | "
                  f"{x['sharpness']:.3f} | {x['truth_db']:.2f} |")  # fmt: skip
    if a.json:
        a.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
