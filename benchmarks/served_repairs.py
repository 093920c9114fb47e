"""Does the map server repair a run's views as the run's repair node did? For each repaired view
of a finished run, the server (in this process, no sockets) repairs the view's camera on the
run's final map without distilling it, and the table sets the source of its choice and its
keyframe distance beside the repair node's (metrics.json), with the mean absolute difference of
the two images (8-bit levels; they differ where the final map renders differently from the
map the node repaired from).

    .venv/bin/python benchmarks/served_repairs.py RUN/repair [--out FILE.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys
from pathlib import Path

import cv2
import numpy as np

from gsfix_online.services.map_server import MapServer, ServerConfig


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run", type=Path, help="a run folder of gsfix-online repair (or demo's repair/)")
    p.add_argument("--out", type=Path, default=None)
    p.add_argument(
        "--all",
        action="store_true",
        help="also the views the run scored without repairing (held-out frames)",
    )
    args = p.parse_args(argv)
    cfg = ServerConfig()
    cfg = dataclasses.replace(cfg, mapper=dataclasses.replace(cfg.mapper, distill_iters=0))
    server = MapServer(cfg, started=0.0)
    name = server.add_run(args.run).name
    metrics = json.loads((args.run / "metrics.json").read_text())
    rows = []
    truth = metrics.get("summary", {}).get("ground_truth")
    print(f"{'view':>4}  {'node: from':<26} {'m':>5}  {'server: from':<18} {'m':>5}  |diff|"
          + ("  node and server PSNR dB against the truth" if truth else ""))  # fmt: skip
    for v in metrics["views"]:
        out_path = args.run / "views" / v["view"] / "output.png"
        if not (v["repair"] or (args.all and out_path.is_file())):
            continue
        cam = v["camera"]
        job = server.begin_repair({"map": name, **cam}, 0.0)
        job.run(lambda f, t: None)
        server.finish_repair(job, ok=True)
        reason = job.result["reason"]
        got = re.search(r"from the (.+?)(?: at ([0-9.]+) m from the keyframes)?(?:;|$)", reason)
        src, dist = (got.group(1), got.group(2)) if got else ("?", None)
        out = cv2.imread(str(out_path))[..., ::-1]
        diff = float(np.abs(out.astype(np.float32) - job.image.astype(np.float32)).mean())
        gt_path = Path(truth) / f"{v['view']}.png" if truth else None
        gt = cv2.imread(str(gt_path))[..., ::-1] if gt_path and gt_path.is_file() else None
        row = {
            "view": v["view"],
            "node_from": v.get("model", {}).get("choice_from", ""),
            "node_distance_m": v.get("model", {}).get("keyframe_distance_m"),
            "server_from": src,
            "server_distance_m": None if dist is None else float(dist),
            "mean_abs_diff": diff,
            "node_psnr_db": None if gt is None else _psnr(out, gt),
            "server_psnr_db": None if gt is None else _psnr(job.image, gt),
        }
        rows.append(row)
        nd = row["node_distance_m"]
        vs = "" if gt is None else f"  {row['node_psnr_db']:6.2f} {row['server_psnr_db']:6.2f}"
        print(f"{row['view']:>4}  {row['node_from']:<26} {'-' if nd is None else f'{nd:.2f}':>5}  "
              f"{src:<18} {dist or '-':>5}  {diff:6.2f}{vs}")  # fmt: skip
    same = sum(r["node_from"].split(" (")[0] == r["server_from"] for r in rows)
    print(f"{same} of {len(rows)} views: the same source of the choice")
    scored = [r for r in rows if r["node_psnr_db"] is not None]
    if scored:
        print(f"against the truth, median over {len(scored)} views: node "
              f"{np.median([r['node_psnr_db'] for r in scored]):.2f} dB, server "
              f"{np.median([r['server_psnr_db'] for r in scored]):.2f} dB")  # fmt: skip
    if args.out:
        args.out.write_text(json.dumps({"run": str(args.run), "views": rows}, indent=1))
    return 0


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(255**2 / mse)


if __name__ == "__main__":
    sys.exit(main())
