"""Stress properties of the Gaussian map: projection, rasterisation, optimisation, distillation.

- ``splat.single_gaussian_exact``: one Gaussian on the optical axis, any rotation, scales and
  depth, rendered by the CPU rasterizer, against the exact alpha at every pixel centre computed
  in float64 without cancellation (the 2D determinant by the Lagrange identity, the quadratic
  form as a sum of squares; see :func:`exact_alpha`);
- ``splat.projection``: culled rows aside, conics are positive definite and finite, and the
  cheap frustum pre-cull keeps every Gaussian the full projection keeps;
- ``splat.render_forward_backward``: colour, depth and alpha finite and within their bounds
  (colour between the extreme colours, depth between the extreme drawn depths, alpha in [0, 1])
  and every gradient finite, for mixtures of extreme Gaussians seen from poses 10 km out;
- ``splat.mapper_steps`` and ``splat.distill``: a :class:`~gsfix_online.mapping.splat.mapper.Mapper`
  fed frames with depths 1 mm to 1 km, saturated colours and extreme intrinsics, then optimised
  or given a repaired view: every map parameter stays finite and no step is skipped as
  non-finite.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
from hypothesis import strategies as st

from gsfix_online.core.types import Intrinsics, make_frame
from gsfix_online.jobs.stress import Property
from gsfix_online.jobs.stress.strategies import (
    DEPTH_RANGE_M,
    NEAR_M,
    gaussian_params,
    intrinsics,
    log_uniform,
    poses,
    quats_wxyz,
    scale_triplets,
    unit_quat_wxyz,
)
from gsfix_online.mapping.splat.gaussians import QUAT_EPS
from gsfix_online.mapping.splat.render_output import EPS2D  # the renderer's low-pass, px²

ALPHA_MIN, ALPHA_MAX = 1.0 / 255.0, 0.99


def _torch() -> Any:
    import torch

    return torch


# -- one Gaussian against the exact alpha ------------------------------------------------------


def exact_alpha(
    K: Intrinsics,
    z: float,  # depth of the mean, on the optical axis, m
    q_wxyz: np.ndarray,  # [4]
    scales: np.ndarray,  # [3] m
    opacity: float,
) -> np.ndarray:  # [H, W] alpha at the pixel centres, float64
    """Alpha of one Gaussian at (0, 0, z) in the camera frame, without cancellation.

    With G = J R S (2 x 3; J = diag(fx, fy) / z on the axis), Σ = G Gᵀ + eps I has
    det Σ = |g0 × g1|² + eps (|g0|² + |g1|²) + eps² (Lagrange identity), and for an offset d the
    form dᵀ adj(Σ) d = |Gᵀ d⊥|² + eps |d|² with d⊥ = (-dy, dx): sums of squares only. A
    quaternion with |q|² < QUAT_EPS is the identity (the map's rule).
    """
    q = np.asarray(q_wxyz, np.float64)
    n2 = float(q @ q)
    w, x, y, zq = q / math.sqrt(n2) if n2 >= QUAT_EPS else (1.0, 0.0, 0.0, 0.0)
    R = np.array(
        [
            [1 - 2 * (y * y + zq * zq), 2 * (x * y - w * zq), 2 * (x * zq + w * y)],
            [2 * (x * y + w * zq), 1 - 2 * (x * x + zq * zq), 2 * (y * zq - w * x)],
            [2 * (x * zq - w * y), 2 * (y * zq + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    G = np.diag([K.fx / z, K.fy / z]) @ np.eye(2, 3) @ R @ np.diag(scales)  # [2, 3]
    g0, g1 = G
    det = float(np.sum(np.cross(g0, g1) ** 2) + EPS2D * (g0 @ g0 + g1 @ g1) + EPS2D**2)
    v, u = np.meshgrid(np.arange(K.height) + 0.5, np.arange(K.width) + 0.5, indexing="ij")
    dx, dy = u - K.cx, v - K.cy
    perp = np.stack([-dy, dx], -1)  # [H, W, 2]
    form = np.sum((perp @ G) ** 2, -1) + EPS2D * (dx * dx + dy * dy)
    a = np.minimum(ALPHA_MAX, opacity * np.exp(-0.5 * form / det))
    return np.where(a >= ALPHA_MIN, a, 0.0)


@st.composite
def _single_gaussian(draw: st.DrawFn) -> dict[str, Any]:
    K = draw(intrinsics(width=16, height=12))
    z = draw(st.one_of(log_uniform(1.01 * NEAR_M, DEPTH_RANGE_M[1]), log_uniform(0.0101, 0.1)))
    q, scales = draw(quats_wxyz()), draw(scale_triplets())
    if draw(st.booleans()):  # the corner: a long needle or disc, turned, near the camera
        fx = draw(log_uniform(1e3, 1e5))
        K = dataclasses.replace(K, fx=fx, fy=draw(st.one_of(st.just(fx), log_uniform(1e3, 1e5))))
        z = draw(log_uniform(0.0101, 1.0))
        q = unit_quat_wxyz(draw)
        big, small = draw(log_uniform(10.0, 1e3)), draw(log_uniform(1e-6, 1e-4))
        scales = np.array([big, small, small] if draw(st.booleans()) else [big, big, small])
    # The mean projects to the principal point: keep it inside the image, where the EWA
    # Jacobian is not clamped (outside image + 15 % it is, by design, and the oracle has no clamp)
    K = dataclasses.replace(K, cx=min(max(K.cx, 0.0), 16.0), cy=min(max(K.cy, 0.0), 12.0))
    return {
        "K": K,
        "z": z,
        "q": q,
        "scales": scales,
        "opacity": draw(st.sampled_from([0.9, 0.5, 1.0])),
    }


def check_single_gaussian(ex: dict[str, Any]) -> None:
    """The CPU rasterizer's alpha matches :func:`exact_alpha` at every pixel (one Gaussian)."""
    torch = _torch()
    from gsfix_online.mapping.splat.render import render

    K: Intrinsics = ex["K"]
    want = exact_alpha(K, ex["z"], ex["q"], ex["scales"], ex["opacity"])
    f32 = torch.float32
    out = render(
        torch.tensor([[0.0, 0.0, ex["z"]]], dtype=f32), torch.tensor(ex["q"][None], dtype=f32),
        torch.tensor(ex["scales"][None], dtype=f32), torch.tensor([ex["opacity"]], dtype=f32),
        torch.ones(1, 1), torch.eye(4), torch.tensor(K.K, dtype=f32), K.width, K.height,
        backend="cpu", eps2d=EPS2D,
    )  # fmt: skip
    got = out.alpha.double().numpy()
    # float32 conics, means and scales: a few 1e-3 in alpha measured on legal inputs; pixels on
    # the 1/255 threshold may flip between 0 and 1/255
    err = np.abs(got - want)
    near_threshold = np.abs(want - ALPHA_MIN) < 2e-3
    worst = float(np.where(near_threshold, 0.0, err).max())
    assert worst < 0.02, (
        f"alpha is off the exact value by {worst:.3f} (max exact {want.max():.3f}, "
        f"max rendered {got.max():.3f})"
    )


# -- projection ----------------------------------------------------------------------------------


@st.composite
def _scene(draw: st.DrawFn, n_max: int = 8) -> dict[str, Any]:
    K = draw(intrinsics())
    return {
        "K": K,
        "T_world_cam": draw(poses()),
        "g": draw(gaussian_params(K, n_max)),
        "background": np.array(draw(st.tuples(*[st.floats(0, 1)] * 3))),
    }


def _world_tensors(ex: dict[str, Any], requires_grad: bool = False) -> dict[str, Any]:
    torch = _torch()
    T = ex["T_world_cam"]
    g = ex["g"]
    means_w = g["means_cam"] @ T[:3, :3].T + T[:3, 3]
    out = {
        "means": torch.tensor(means_w, dtype=torch.float32),
        "quats": torch.tensor(g["quats"], dtype=torch.float32),
        "scales": torch.tensor(g["scales"], dtype=torch.float32),
        "opacities": torch.tensor(g["opacities"], dtype=torch.float32),
        "colors": torch.tensor(g["colors"], dtype=torch.float32),
    }
    for t in out.values():
        t.requires_grad_(requires_grad)
    return out


def check_projection(ex: dict[str, Any]) -> None:
    """Kept rows have finite positive-definite conics and finite means; the pre-cull keeps them."""
    torch = _torch()
    from gsfix_online.mapping.splat.render_cpu import frustum_candidates, project_gaussians

    K: Intrinsics = ex["K"]
    p = _world_tensors(ex)
    Kt = torch.tensor(K.K, dtype=torch.float32)
    viewmat = torch.linalg.inv(torch.tensor(ex["T_world_cam"], dtype=torch.float32))
    proj = project_gaussians(
        p["means"], p["quats"], p["scales"], viewmat, Kt, K.width, K.height, eps2d=EPS2D
    )
    kept = (proj.radii > 0).all(-1)
    assert bool((proj.radii >= 0).all()), "negative radius"
    a, b, c = proj.conics[kept].double().unbind(-1)
    assert torch.isfinite(proj.conics[kept]).all(), f"non-finite conics {proj.conics[kept]}"
    assert torch.isfinite(proj.means2d[kept]).all(), "non-finite means2d"
    assert bool((a > 0).all() and (c > 0).all()), f"conic not positive: {proj.conics[kept]}"
    # the determinant of a float32 conic (a c - b²) may round to 0 for extreme anisotropy
    assert bool((a * c - b * b >= -1e-6 * a * c).all()), f"indefinite conic {proj.conics[kept]}"
    cand = frustum_candidates(p["means"], p["scales"], viewmat, Kt, K.width, K.height, eps2d=EPS2D)
    missing = set(torch.nonzero(kept).squeeze(1).tolist()) - set(cand.tolist())
    assert not missing, f"the pre-cull dropped Gaussians {sorted(missing)} the projection keeps"


# -- rasterisation forward and backward ----------------------------------------------------------


def check_render(ex: dict[str, Any]) -> None:
    """Finite, bounded images and finite gradients for mixtures of extreme Gaussians."""
    torch = _torch()
    from gsfix_online.mapping.splat.render import render

    K: Intrinsics = ex["K"]
    p = _world_tensors(ex, requires_grad=True)
    bg = torch.tensor(ex["background"], dtype=torch.float32)
    out = render(
        p["means"], p["quats"], p["scales"], p["opacities"], p["colors"], None,
        torch.tensor(K.K, dtype=torch.float32), K.width, K.height,
        T_world_cam=torch.tensor(ex["T_world_cam"], dtype=torch.float32), backend="cpu",
        background=bg, eps2d=EPS2D,
    )  # fmt: skip
    for name, img in (("color", out.color), ("depth", out.depth), ("alpha", out.alpha)):
        assert torch.isfinite(img).all(), f"non-finite {name}"
    alpha = out.alpha.detach()
    assert float(alpha.min()) >= 0 and float(alpha.max()) <= 1, "alpha outside [0, 1]"
    cols = torch.cat([p["colors"].detach(), bg[None]])
    lo, hi = cols.min(0).values - 1e-5, cols.max(0).values + 1e-5
    color = out.color.detach()
    assert bool(((color >= lo) & (color <= hi)).all()), "colour outside its inputs' range"
    drawn = out.visible & (p["opacities"].detach() >= ALPHA_MIN)
    if bool(drawn.any()):
        z = out.info["depths"][0][drawn].double()
        d = out.depth.detach().double()[alpha > 0]
        lo_z, hi_z = float(z.min()), float(z.max())
        slack = 1e-4 * max(abs(lo_z), abs(hi_z)) + 1e-6
        assert bool(((d >= lo_z - slack) & (d <= hi_z + slack)).all()), (
            f"depth {float(d.min())}..{float(d.max())} outside the drawn {lo_z}..{hi_z}"
        )
    g = torch.Generator().manual_seed(0)
    w_c = torch.rand(out.color.shape, generator=g)
    w_d = torch.rand(out.depth.shape, generator=g) / max(1.0, float(out.depth.detach().max()))
    loss = (out.color * w_c).sum() + (out.depth * w_d).sum() + out.alpha.sum()
    loss.backward()
    for name, t in p.items():
        assert torch.isfinite(t.grad).all(), f"non-finite gradient of {name}: {t.grad}"
    assert torch.isfinite(out.means2d.grad).all(), "non-finite means2d gradient (densification)"


# -- the mapper: optimisation and distillation ---------------------------------------------------


def stress_mapper_config() -> Any:
    """Mapper settings that let every extreme through: growth from 1 mm to 1 km, no downscale."""
    from gsfix_online.mapping.splat.growth import GrowthConfig
    from gsfix_online.mapping.splat.mapper import DensifyConfig, MapperConfig

    return MapperConfig(
        backend="cpu",
        train_downscale=1,
        kf_iters=2,
        non_kf_iters=1,
        non_kf_every=1,
        distill_iters=2,
        scene_scale_m=0.0,
        growth=GrowthConfig(max_cell_px=4, min_cell_px=1, min_depth_m=1e-3, max_depth_m=1e3),
        densify=DensifyConfig(refine_every=5, start_step=2),
        prune_every=7,
    )


@st.composite
def extreme_frames(draw: st.DrawFn, n: int = 2, size: tuple[int, int] = (12, 9)) -> list[Any]:
    """Frames with depths 1 mm to 1 km (and holes), saturated or random colours, extreme
    intrinsics (focal 0.5 to 1e4 px) and poses up to 10 km out, near each other."""
    w, h = size
    fx = draw(log_uniform(0.5, 1e4))
    K = Intrinsics(fx, draw(st.one_of(st.just(fx), log_uniform(0.5, 1e4))), w / 2, h / 2, w, h)
    T0 = draw(poses())
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        kind = draw(st.sampled_from(["random", "black", "white"]))
        color = {
            "random": rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
            "black": np.zeros((h, w, 3), np.uint8),
            "white": np.full((h, w, 3), 255, np.uint8),
        }[kind]
        base = draw(log_uniform(*DEPTH_RANGE_M))
        spread = draw(st.sampled_from([0.0, 0.1, 3.0]))  # 3: depths over six decades
        depth = (base * np.exp(spread * rng.standard_normal((h, w)))).clip(1e-3, 1e3)
        depth[rng.random((h, w)) < 0.1] = 0.0
        T = T0.copy()
        T[:3, 3] += 0.01 * i * base
        frames.append(make_frame(color, depth.astype(np.float32), K, T, 10**9 * (i + 1), seq=i))
    return frames


def _finite_map(mapper: Any, what: str) -> None:
    torch = _torch()
    for key, prm in mapper.gmap.params.items():
        bad = int((~torch.isfinite(prm.detach())).sum())
        assert not bad, f"{what}: {bad} non-finite values in the map's {key}"
    assert mapper.n_nonfinite_steps == 0, (
        f"{what}: {mapper.n_nonfinite_steps} of {mapper.n_steps} steps had non-finite gradients"
    )


@st.composite
def _mapper_run(draw: st.DrawFn) -> dict[str, Any]:
    return {"frames": draw(extreme_frames()), "refine": draw(st.integers(0, 8))}


def check_mapper_steps(ex: dict[str, Any]) -> None:
    """Mapping and refining on extreme frames: the map stays finite, no step is skipped."""
    from gsfix_online.mapping.splat.mapper import Mapper

    mapper = Mapper(stress_mapper_config())
    for f in ex["frames"]:
        mapper.process(f)
    mapper.refine(ex["refine"])
    _finite_map(mapper, "after mapping")
    f = ex["frames"][-1]
    color, depth, alpha = mapper.render_numpy(f.T_world_cam, f.intrinsics.K, f.width, f.height)
    for name, img in (("colour", color), ("depth", depth), ("alpha", alpha)):
        assert np.isfinite(img).all(), f"non-finite rendered {name}"


@st.composite
def _distill_case(draw: st.DrawFn) -> dict[str, Any]:
    frames = draw(extreme_frames(n=1))
    f = frames[0]
    h, w = f.height, f.width
    rng = np.random.default_rng(draw(st.integers(0, 2**31 - 1)))
    image = draw(
        st.sampled_from(
            [
                np.zeros((h, w, 3), np.uint8),
                np.full((h, w, 3), 255, np.uint8),
                rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
                rng.integers(0, 256, (h, w), dtype=np.uint8),
            ]
        )
    )
    mask = draw(
        st.sampled_from(
            [None, np.zeros((h, w), bool), np.ones((h, w), bool), rng.random((h, w)) < 0.1]
        )
    )
    depth = draw(st.sampled_from(["none", "frame", "zeros", "far", "near"]))
    depth_map = {
        "none": None,
        "frame": f.depth,
        "zeros": np.zeros((h, w), np.float32),
        "far": np.full((h, w), 1e3, np.float32),
        "near": np.full((h, w), 1e-3, np.float32),
    }[depth]
    T = f.T_world_cam.copy()
    T[:3, 3] += draw(st.sampled_from([0.0, 1e-3, 1.0]))
    return {"frames": frames, "image": image, "mask": mask, "depth": depth_map, "T": T}


def check_distill(ex: dict[str, Any]) -> None:
    """Distilling an extreme repaired view keeps the map finite and adds one keyframe."""
    from gsfix_online.mapping.splat.mapper import Mapper

    mapper = Mapper(stress_mapper_config())
    f = ex["frames"][0]
    mapper.process(f)
    n_kf = len(mapper.store)
    mapper.distill(
        ex["image"], ex["T"], f.intrinsics.K, iters=3, mask=ex["mask"], depth=ex["depth"]
    )
    assert len(mapper.store) == n_kf + 1 or len(mapper.store) == mapper.store.capacity
    _finite_map(mapper, "after distillation")


PROPERTIES = [
    Property(
        "splat.single_gaussian_exact",
        "one Gaussian (any rotation, scales 1e-6..1e3 m, depth near..1 km): alpha = exact alpha",
        _single_gaussian,
        check_single_gaussian,
        ci_examples=40,
    ),
    Property(
        "splat.projection",
        "finite positive-definite conics for kept Gaussians; the pre-cull keeps every one",
        _scene,
        check_projection,
        ci_examples=40,
    ),
    Property(
        "splat.render_forward_backward",
        "finite, bounded colour, depth, alpha and finite gradients for extreme mixtures",
        _scene,
        check_render,
        ci_examples=30,
    ),
    Property(
        "splat.mapper_steps",
        "mapping and refining on extreme frames: finite map, no skipped step",
        _mapper_run,
        check_mapper_steps,
        ci_examples=6,
    ),
    Property(
        "splat.distill",
        "distilling extreme repaired views (masks, depths, gray): finite map",
        _distill_case,
        check_distill,
        ci_examples=6,
    ),
]
