"""Whose seeds make a region of a repaired view's final render? (issue 43's final-map blurs)

For a finished repair run (``RUN/repair``), the final map's Gaussians with opacity above
``--min-opacity`` whose centres project into a box of one view are matched to the repaired
keyframes whose seed depth (``seed_depths`` in ``work/map.pt``, the mesh depth each repaired view
was seeded at) they lie at, within ``--tolerance`` of it. Printed: how many are observed and how
many grown from repaired views, the matches per repaired keyframe, and their mean colour against
the output's and the final render's over the box. A blur made of the view's own seeds was
recoloured by later fits; one made of another view's seeds is that view's veil.

Centres are not footprints: a large Gaussian whose centre projects outside the box (or outside
the view) can still cover it. With ``--render`` the box is also rendered from the final map with
the splat node's settings, split by who could paint it: observed against grown from repaired
views, and the grown ones by size (largest axis sigma over ``--big``) and by whether their centre
lies in the view; each split prints its median opacity and depth over the box, beside the true
depth where ``--truth-depth`` gives it (a 16-bit PNG, ``--depth-scale`` units per m).

    .venv/bin/python benchmarks/seed_sources.py RUN/repair 003 --box 0 140 140 240
    .venv/bin/python benchmarks/seed_sources.py RUN/repair 004 --box 0 60 80 120 --render \\
        --truth-depth RUN/scene/novel/depth/004.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import numpy.typing as npt

SH_C0 = 0.28209479177387814  # degree-0 spherical harmonic (sh0 -> colour offset)


def project(
    T_world_cam: npt.NDArray, K: npt.NDArray, X: npt.NDArray
) -> tuple[npt.NDArray, npt.NDArray]:
    """Pixel coordinates [N, 2] and z-depth [N] of world points X [N, 3]."""
    T = np.linalg.inv(T_world_cam)
    Xc = X @ T[:3, :3].T + T[:3, 3]
    z = Xc[:, 2]
    uv = Xc[:, :2] / np.maximum(z[:, None], 1e-6) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    return uv, z


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a repair run folder (metrics.json, work/map.pt)")
    ap.add_argument("view", help="the view's name, e.g. 003")
    ap.add_argument("--box", type=int, nargs=4, metavar=("X0", "Y0", "X1", "Y1"), required=True)
    ap.add_argument("--min-opacity", type=float, default=0.3)
    ap.add_argument("--tolerance", type=float, default=0.05, help="relative depth tolerance")
    ap.add_argument("--render", action="store_true", help="render the box by who could paint it")
    ap.add_argument("--big", type=float, default=0.1, help="--render: a large sigma, m")
    ap.add_argument("--truth-depth", type=Path, help="--render: the view's true depth (PNG)")
    ap.add_argument("--depth-scale", type=float, default=5000.0, help="PNG units per m")
    a = ap.parse_args()
    import cv2
    import torch

    state = torch.load(a.run / "work" / "map.pt", weights_only=True)
    g = state["map"]
    means, origin = g["means"].numpy(), g["origin"].numpy().astype(int)
    opacity = torch.sigmoid(g["opacities"]).numpy()
    colour = g["sh0"].numpy().reshape(len(means), -1) * SH_C0 + 0.5
    views = json.loads((a.run / "metrics.json").read_text())["views"]
    cam = next(v for v in views if v["view"] == a.view)["camera"]
    T, K = np.reshape(cam["T_world_cam"], (4, 4)), np.reshape(cam["K"], (3, 3))
    x0, y0, x1, y1 = a.box
    uv, z = project(T, K, means)
    inside = (z > 0) & (uv[:, 0] >= x0) & (uv[:, 0] < x1) & (uv[:, 1] >= y0) & (uv[:, 1] < y1)
    idx = np.nonzero(inside & (opacity > a.min_opacity))[0]
    print(f"view {a.view}, box {a.box}: {len(idx)} Gaussians over opacity {a.min_opacity} "
          f"({int((origin[idx] == 0).sum())} observed, {int((origin[idx] != 0).sum())} grown "
          "from repaired views)")  # fmt: skip
    frames = {int(it["kf_id"]): it["frame"] for it in state["store"]["items"]}
    for kf_id, depth in sorted(state["seed_depths"].items(), key=lambda kv: int(kv[0])):
        frame, d = frames[int(kf_id)], np.asarray(depth)
        Tk = np.asarray(frame["T_world_cam"], np.float64)
        Kk = np.asarray(frame["K"], np.float64)
        u, zk = project(Tk, Kk, means[idx])
        ui, vi = np.rint(u[:, 0]).astype(int), np.rint(u[:, 1]).astype(int)
        ok = (zk > 0) & (ui >= 0) & (ui < d.shape[1]) & (vi >= 0) & (vi < d.shape[0])
        at = np.zeros(len(idx))
        at[ok] = d[vi[ok], ui[ok]]
        match = ok & (at > 0) & (np.abs(zk - at) < a.tolerance * at)
        if match.any():
            print(f"  repaired keyframe {int(kf_id)}: {int(match.sum())} at its seed depth, mean "
                  f"colour {[round(float(c), 2) for c in colour[idx[match]].mean(0)]}")  # fmt: skip
    for name in ("output", "final"):
        img = cv2.imread(str(a.run / "views" / a.view / f"{name}.png"))[y0:y1, x0:x1, ::-1]
        print(f"  {name} over the box: mean colour "
              f"{[round(float(c) / 255.0, 2) for c in img.reshape(-1, 3).mean(0)]}")  # fmt: skip
    if a.render:
        render_split(a, T, K, uv, z)
    return 0


def render_split(a: argparse.Namespace, T: npt.NDArray, K: npt.NDArray, uv: npt.NDArray,
                 z: npt.NDArray) -> None:  # fmt: skip
    """The box rendered from the final map by subsets of its Gaussians (module doc)."""
    import cv2
    import torch
    import yaml

    from gsfix_online.core.config import build
    from gsfix_online.mapping.splat.mapper import MapperConfig
    from gsfix_online.services.splat import load_snapshot

    graph = yaml.safe_load((a.run / "work/graph.yaml").read_text())
    m = load_snapshot(build(MapperConfig, base=graph["nodes"]["splat"]["params"]["mapper"]),
                      a.run / "work/map.pt")  # fmt: skip
    x0, y0, x1, y1 = a.box
    H, W = cv2.imread(str(a.run / "views" / a.view / "output.png")).shape[:2]  # the view's size
    if a.truth_depth is not None:
        truth = cv2.imread(str(a.truth_depth), cv2.IMREAD_UNCHANGED)[y0:y1, x0:x1] / a.depth_scale
        print(f"  true depth over the box: median {float(np.median(truth)):.2f} m")
    g = m.gmap
    rep = g.repaired().cpu().numpy()
    big = g.scales.detach().amax(1).cpu().numpy() > a.big
    in_view = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    splits = {"all": np.ones_like(rep), "observed": ~rep, "repaired": rep,
              f"repaired, sigma > {a.big} m": rep & big, f"repaired, sigma <= {a.big} m": rep & ~big,
              "repaired, centre in the view": rep & in_view,
              "repaired, centre outside the view": rep & ~in_view}  # fmt: skip
    for name, keep in splits.items():
        with torch.no_grad():
            out = m.render(T, K, W, H, keep=torch.from_numpy(keep).to(g.device))
        alpha = out.alpha.cpu().numpy()[y0:y1, x0:x1]
        depth = out.depth.cpu().numpy()[y0:y1, x0:x1]
        print(f"  {name} ({int(keep.sum())}): opacity {float(np.median(alpha)):.2f}, depth "
              f"{float(np.median(depth[alpha > 0.5])) if (alpha > 0.5).any() else 0.0:.2f} m "
              "(median where opacity > 0.5)")  # fmt: skip


if __name__ == "__main__":
    raise SystemExit(main())
