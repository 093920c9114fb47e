"""CPU renderer speed and memory: forward and forward+backward at 320x240 and 640x480.

The scene is a plausible map: N flat Gaussians spread over the walls, floor and ceiling of a
4 x 3 x 6 m room seen from inside, every one in view, each sized to about 0.5·sqrt(W·H/N) px (so
the image is covered a few times over), with random in-plane anisotropy, opacity 0.3..0.95 and
RGB colour. Each configuration runs in its own process (peak RSS above the process's resident size
before the first render) on 2 threads; times are medians over repeats after one warm-up.
The processes run with OMP_WAIT_POLICY=PASSIVE: on a shared 2-core machine, OpenMP threads
that spin while waiting for a descheduled partner made fwd+bwd 2x slower (measured 0.52 s vs
0.25 s at 320x240, 50k); the goal row is also run with the default policy for reference.

    .venv/bin/python benchmarks/bench_render.py [--repeats 5] [--out benchmarks/results/render_cpu.json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import psutil
import torch

SIZES = [(320, 240), (640, 480)]
COUNTS = [10_000, 50_000, 200_000]


def room_scene(n: int, width: int, height: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """n flat Gaussians on the inside of a box, all in view of a camera at the origin (+z)."""
    g = torch.Generator().manual_seed(seed)
    f = 0.8 * width
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    half = torch.tensor([2.0, 1.5])
    depth = 6.0
    pts, nrm = [], []
    while sum(len(p) for p in pts) < n:
        m = 4 * n
        face = torch.randint(0, 5, (m,), generator=g)
        u = torch.rand(m, 3, generator=g)
        p = torch.stack(
            [(u[:, 0] * 2 - 1) * half[0], (u[:, 1] * 2 - 1) * half[1], u[:, 2] * depth], -1
        )
        nv = torch.zeros(m, 3)
        for k, (axis, val, sign) in enumerate(
            [(2, depth, -1), (0, -half[0], 1), (0, half[0], -1), (1, -half[1], 1), (1, half[1], -1)]
        ):
            sel = face == k
            p[sel, axis] = val
            nv[sel, axis] = sign
        uv = (p @ K.T)[:, :2] / p[:, 2:3]
        ok = (
            (p[:, 2] > 0.3)
            & (uv[:, 0] >= 0)
            & (uv[:, 0] < width)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] < height)
        )
        pts.append(p[ok])
        nrm.append(nv[ok])
    means = torch.cat(pts)[:n]
    normals = torch.cat(nrm)[:n]
    # rotation taking z to the normal, then a random spin about it
    z = torch.tensor([0.0, 0.0, 1.0]).expand_as(normals)
    axis = torch.cross(z, normals, dim=-1)
    s = axis.norm(dim=-1, keepdim=True)
    c = (z * normals).sum(-1, keepdim=True)
    half_angle = 0.5 * torch.atan2(s, c)
    axis = torch.where(s > 1e-6, axis / s.clamp_min(1e-6), torch.tensor([1.0, 0, 0]))
    q_align = torch.cat([torch.cos(half_angle), torch.sin(half_angle) * axis], -1)
    spin = torch.rand(n, 1, generator=g) * math.pi
    q_spin = torch.cat([torch.cos(spin), torch.zeros(n, 2), torch.sin(spin)], -1)
    quats = quat_mul(q_align, q_spin)
    sigma_px = 0.5 * math.sqrt(width * height / n)
    s_world = sigma_px * means[:, 2:3] / f
    aniso = torch.exp(torch.randn(n, 1, generator=g) * 0.4)
    scales = torch.cat([s_world * aniso, s_world / aniso, 0.1 * s_world], -1)
    return {
        "means": means,
        "quats": quats,
        "scales": scales,
        "opacities": 0.3 + 0.65 * torch.rand(n, generator=g),
        "colors": torch.rand(n, 3, generator=g),
        "viewmat": torch.eye(4),
        "K": K,
    }


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # [N, 4] (w, x, y, z)
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def run_one(n: int, width: int, height: int, repeats: int, tile_size: int) -> dict:
    from gsfix_online.mapping.splat.render import render

    torch.set_num_threads(2)
    sc = room_scene(n, width, height)
    params = [
        sc[k].clone().requires_grad_(True)
        for k in ("means", "quats", "scales", "opacities", "colors")
    ]
    rss0 = psutil.Process().memory_info().rss

    def fwd():
        with torch.no_grad():
            return render(
                *params, sc["viewmat"], sc["K"], width, height, backend="cpu", tile_size=tile_size
            )

    def fwd_bwd():
        out = render(
            *params, sc["viewmat"], sc["K"], width, height, backend="cpu", tile_size=tile_size
        )
        (out.color.sum() + out.depth.sum() * 0.1 + out.alpha.sum()).backward()
        return out

    times = {}
    for name, fn in (("forward_s", fwd), ("forward_backward_s", fwd_bwd)):
        fn()
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            out = fn()
            ts.append(time.perf_counter() - t0)
        times[name] = round(statistics.median(ts), 4)
        times[name.replace("_s", "_min_s")] = round(min(ts), 4)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB
    return {
        "n_gaussians": n,
        "width": width,
        "height": height,
        "tile_size": tile_size,
        **times,
        "n_isects": out.info["n_isects"],
        "mean_alpha": round(float(out.alpha.detach().mean()), 3),
        "peak_rss_above_start_mb": round((peak - rss0) / 2**20, 1),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--tile-size", type=int, default=4)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/render_cpu.json"))
    ap.add_argument("--one", nargs=3, type=int, metavar=("N", "W", "H"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(run_one(*args.one, args.repeats, args.tile_size)))
        return 0
    rows = []
    configs = [(n, w, h, "PASSIVE") for w, h in SIZES for n in COUNTS]
    configs.append((50_000, 320, 240, "default"))
    for n, w, h, policy in configs:
        cmd = [sys.executable, __file__, "--one", str(n), str(w), str(h)]
        cmd += ["--repeats", str(args.repeats), "--tile-size", str(args.tile_size)]
        env = dict(os.environ)
        env.pop("OMP_WAIT_POLICY", None)
        if policy != "default":
            env["OMP_WAIT_POLICY"] = policy
        res = subprocess.run(cmd, capture_output=True, text=True, check=True, env=env)
        row = {**json.loads(res.stdout.strip().splitlines()[-1]), "omp_wait_policy": policy}
        rows.append(row)
        print(
            f"{w}x{h} N={n:>6} ({policy}): fwd {row['forward_s']:.3f} s, fwd+bwd {row['forward_backward_s']:.3f} s, "
            f"{row['n_isects']} isects, peak +{row['peak_rss_above_start_mb']} MB",
            flush=True,
        )
    result = {
        "benchmark": "CPU Gaussian renderer (render_cpu), room scene",
        "torch": torch.__version__,
        "threads": 2,
        "cpu": platform.processor() or platform.machine(),
        "cpu_count": psutil.cpu_count(),
        "repeats": args.repeats,
        "goal": "forward+backward at 320x240 with 50k Gaussians under 0.5 s",
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
