"""A learned per-block blend of the reference warp and the 3DGS fill at held-out frames.

The realistic counterpart of ``warp_headroom.py``'s oracle: per block of ``--block`` pixels, a
weight ``w = sigmoid(f(features))`` blends ``ref_inpaint`` (the warp of the real frames) with
``inpaint`` (the 3DGS render, mesh fill, Telea). The features are each block's mean and maximum
of the candidates' disagreements, their gradients, the warp's holes, the 3DGS alpha and the
luma. ``f`` is linear or a 16-unit MLP, fitted (Adam, 300 steps) to minimise the blend's squared
error against the camera images. It is cross-fitted: each held-out frame is scored by a model
fitted on the run's other held-out frames only. It prints the gain over ``ref_inpaint`` per frame
(median, min, max).

    .venv/bin/python benchmarks/warp_selector.py RUN1 RUN2 ... [--block 8]
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import cv2
import numpy as np
import torch

from gsfix_online.repair.outputs import read_png_rgb


def tiles(x: np.ndarray, b: int) -> np.ndarray:  # [H, W, C] -> [N, b*b, C] (whole blocks)
    h, w = x.shape[0] // b, x.shape[1] // b
    x = x[: h * b, : w * b].reshape(h, b, w, b, -1)
    return x.transpose(0, 2, 1, 3, 4).reshape(h * w, b * b, -1)


def features(ref, gs, mesh, warp, alpha, b: int) -> np.ndarray:  # noqa: ANN001 -- [N, 18]
    def grad(a: np.ndarray) -> np.ndarray:
        gy, gx = np.gradient(a.mean(-1))
        return np.hypot(gx, gy)

    per_pixel = np.stack([
        np.abs(ref - gs).mean(-1), np.abs(ref - mesh).mean(-1), np.abs(gs - mesh).mean(-1),
        grad(ref), grad(gs), grad(mesh), (warp.sum(-1) == 0).astype(np.float32), alpha,
        ref.mean(-1),
    ], -1)  # fmt: skip
    t = tiles(per_pixel, b)
    return np.concatenate([t.mean(1), t.max(1)], 1)


def load(run: Path, b: int) -> list[tuple[np.ndarray, ...]]:
    frames = []
    for v in sorted((run / "views").iterdir()):
        gt_path = run / "work" / "gt" / f"{v.name}.png"
        if not gt_path.is_file() or not (v / "ref_inpaint.png").is_file():
            continue
        ref = read_png_rgb(v / "ref_inpaint.png").astype(np.float32)
        h, w = ref.shape[:2]
        gt, gs, mesh, warp = (read_png_rgb(p, w, h).astype(np.float32) for p in (
            gt_path, v / "inpaint.png", v / "mesh_inpaint.png", v / "ref_warp.png"))  # fmt: skip
        alpha = cv2.imread(str(v / "alpha.png"), cv2.IMREAD_UNCHANGED).astype(np.float32)
        alpha = alpha[..., 0] if alpha.ndim == 3 else alpha
        alpha = alpha / max(float(alpha.max()), 1e-6)
        frames.append((features(ref, gs, mesh, warp, alpha, b), tiles(ref, b), tiles(gs, b),
                       tiles(gt, b)))  # fmt: skip
    return frames


def fit(
    x: torch.Tensor, r: torch.Tensor, g: torch.Tensor, y: torch.Tensor, mlp: bool
) -> torch.nn.Module:
    torch.manual_seed(0)
    n = x.shape[1]
    net = (torch.nn.Sequential(torch.nn.Linear(n, 16), torch.nn.ReLU(), torch.nn.Linear(16, 1))
           if mlp else torch.nn.Linear(n, 1))  # fmt: skip
    opt = torch.optim.Adam(net.parameters(), 1e-2)
    for _ in range(300):
        w = torch.sigmoid(net(x))[:, :, None]
        loss = ((w * r + (1 - w) * g - y) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return net


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="repair run folders made with --holdout")
    ap.add_argument("--block", type=int, default=8, help="block size, px")
    a = ap.parse_args()
    for run in a.runs:
        frames = load(run, a.block)
        if len(frames) < 2:  # cross-fitting needs another frame to fit on
            print(f"{run.name}: {len(frames)} held-out frame(s) with a warp; needs 2 or more")
            continue
        gains: dict[str, list[float]] = {"linear": [], "mlp": []}
        for i, (f, r, g, y) in enumerate(frames):
            rest = [d for j, d in enumerate(frames) if j != i]
            x = np.concatenate([d[0] for d in rest])
            mu, sd = x.mean(0), x.std(0) + 1e-6

            def cat(k: int, rest: list = rest) -> torch.Tensor:  # type: ignore[type-arg]
                return torch.tensor(np.concatenate([d[k] for d in rest]))

            xt = torch.tensor((x - mu) / sd, dtype=torch.float32)
            for kind in gains:
                net = fit(xt, cat(1), cat(2), cat(3), kind == "mlp")
                with torch.no_grad():
                    w = torch.sigmoid(net(torch.tensor((f - mu) / sd, dtype=torch.float32)))
                w = w.numpy()[:, :, None]
                e_new = float(((w * r + (1 - w) * g - y) ** 2).mean())
                gains[kind].append(10 * np.log10(float(((r - y) ** 2).mean()) / e_new))
        cells = ", ".join(f"{k} {statistics.median(v):+.2f} ({min(v):+.2f} to {max(v):+.2f})"
                          for k, v in gains.items())  # fmt: skip
        print(f"{run.name}: {len(frames)} frames, {a.block} px blocks, gain over ref_inpaint "
              f"median (min to max): {cells}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
