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
    args = p.parse_args(argv)
    cfg = ServerConfig()
    cfg = dataclasses.replace(cfg, mapper=dataclasses.replace(cfg.mapper, distill_iters=0))
    server = MapServer(cfg, started=0.0)
    name = server.add_run(args.run).name
    metrics = json.loads((args.run / "metrics.json").read_text())
    rows = []
    print(f"{'view':>4}  {'node: from':<18} {'m':>5}  {'server: from':<18} {'m':>5}  |diff|")
    for v in metrics["views"]:
        if not v["repair"]:
            continue
        cam = v["camera"]
        job = server.begin_repair({"map": name, **cam}, 0.0)
        job.run(lambda f, t: None)
        server.finish_repair(job, ok=True)
        reason = job.result["reason"]
        got = re.search(r"from the (.+?)(?: at ([0-9.]+) m from the keyframes)?(?:;|$)", reason)
        src, dist = (got.group(1), got.group(2)) if got else ("?", None)
        out = cv2.imread(str(args.run / "views" / v["view"] / "output.png"))[..., ::-1]
        diff = float(np.abs(out.astype(np.float32) - job.image.astype(np.float32)).mean())
        row = {
            "view": v["view"],
            "node_from": v.get("model", {}).get("choice_from", ""),
            "node_distance_m": v.get("model", {}).get("keyframe_distance_m"),
            "server_from": src,
            "server_distance_m": None if dist is None else float(dist),
            "mean_abs_diff": diff,
        }
        rows.append(row)
        nd = row["node_distance_m"]
        print(f"{row['view']:>4}  {row['node_from']:<18} {'-' if nd is None else f'{nd:.2f}':>5}  "
              f"{src:<18} {dist or '-':>5}  {diff:6.2f}")  # fmt: skip
    same = sum(r["node_from"] == r["server_from"] for r in rows)
    print(f"{same} of {len(rows)} views: the same source of the choice")
    if args.out:
        args.out.write_text(json.dumps({"run": str(args.run), "views": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
