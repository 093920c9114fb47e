"""Our differentiable CPU rasterizer for 3D Gaussians: gsplat's math, PyTorch and numba.

Pipeline (one camera):

1. **Project** (:func:`project_gaussians`, plain autograd): EWA splatting exactly as gsplat's
   ``_fully_fused_projection``: Σ = R S Sᵀ Rᵀ from a quaternion normalised inside the graph, the
   Jacobian J W Σ Wᵀ Jᵀ with x/z and y/z clamped to the field of view plus 30 %, ``eps2d`` added
   to the 2D covariance, near/far culling, radius ``ceil(3.33 σ)``. It runs in float64: it is
   N-sized, so this costs little, and the 2D determinant of a 1e3 m Gaussian 1 cm in front of the
   camera overflows float32.
2. **Bin** (:func:`bin_tiles`, no grad): each visible Gaussian goes to every tile whose pixel
   centres it can reach with alpha >= 1/255 (gsplat's opacity-aware extent, exact per axis), and
   the (tile, depth) pairs are sorted.
3. **Rasterize** (:class:`_RasterizeTiles`, a hand-written backward): each pixel walks its
   tile's depth-ordered Gaussians in compiled code (:mod:`.raster_kernels`) with gsplat's rules:
   ``alpha = min(0.99, o·exp(-σ))``, skip alpha < 1/255, stop a pixel before the Gaussian that
   would take its transmittance to 1e-4 or below. Tiles are small (4x4 px by default), so a
   pixel evaluates few Gaussians that cannot reach it. The backward pass replays the walk
   (nothing per pixel is stored) and gets the "everything behind" term of d(colour)/d(alpha)
   from the forward output instead of a back-to-front pass. Memory is O(pixels + intersections).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from gsfix_online.mapping.splat import raster_kernels as kernels
from gsfix_online.mapping.splat.gaussians import normalize_quats
from gsfix_online.mapping.splat.raster_kernels import ALPHA_MAX, ALPHA_MIN  # noqa: F401 (API)
from gsfix_online.mapping.splat.render_output import EPS2D, RenderOutput
from gsfix_online.mapping.splat.sh import eval_sh

RADIUS_SIGMAS = 3.33  # gsplat's radius in standard deviations


@dataclass
class Projection:
    """Per-Gaussian screen-space quantities; rows with ``radii == 0`` are culled (garbage)."""

    means2d: Tensor  # [N, 2] px, input dtype, differentiable
    conics: Tensor  # [N, 3] inverse 2D covariance (a, b, c): σ = ½a·dx² + b·dx·dy + ½c·dy²
    depths: Tensor  # [N] camera z, m
    radii: Tensor  # [N, 2] int32 px, gsplat's ceil(3.33·σ); 0 = culled
    cov2d: Tensor  # [N, 3] 2D covariance (xx, xy, yy) after eps2d, px², float64


def quat_scale_to_covar(
    quats: Tensor,  # [N, 4] (w, x, y, z), any norm; |q|² < 1e-12 -> identity rotation
    scales: Tensor,  # [N, 3] standard deviations (not log), m
) -> tuple[Tensor, Tensor]:  # Σ [N, 3, 3], M = R·diag(s) [N, 3, 3]
    """3D covariance Σ = M Mᵀ; the quaternion is normalised here, inside the graph."""
    # Guard (stress suite, splat.single_gaussian_exact): the map's rule (normalize_quats):
    # |q|² < 1e-12 is the identity, anything else is normalised exactly. q·rsqrt(|q|² + 1e-24)
    # gave a matrix that is no rotation for |q|² near 1e-24 (the covariance lost an axis), and
    # a rotation other than the one the viewer and the PLY export show.
    q = normalize_quats(quats)
    w, x, y, z = q.unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))
    M = R * scales[..., None, :]
    return M @ M.transpose(-1, -2), M


def project_gaussians(
    means: Tensor,  # [N, 3] world, m
    quats: Tensor,  # [N, 4] (w, x, y, z)
    scales: Tensor,  # [N, 3] m (activated, not log)
    viewmat: Tensor,  # [4, 4] T_cam_world (world -> camera, OpenCV axes)
    K: Tensor,  # [3, 3] pixels
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = EPS2D,
) -> Projection:
    """EWA projection with gsplat's ``_fully_fused_projection`` semantics (pinhole camera)."""
    dtype = means.dtype
    f64 = torch.float64
    # 1. World -> camera, 3D covariance in the camera frame (float64, see module docstring)
    Rcw = viewmat[:3, :3].to(f64)
    t = viewmat[:3, 3].to(f64)
    p = means.to(f64) @ Rcw.T + t  # [N, 3]
    _, M = quat_scale_to_covar(quats.to(f64), scales.to(f64))
    Mc = Rcw @ M  # [N, 3, 3]; Σ_cam = Mc Mcᵀ
    # 2. Cull by depth first; culled rows use z = 1 so nothing below divides by zero or overflows
    #    (a NaN there would poison the gradients of the visible rows through 0·NaN)
    z = p[:, 2]
    in_range = (z > near) & (z < far)
    zs = torch.where(in_range, z, torch.ones_like(z))
    Kd = K.to(f64)
    fx, fy, cx, cy = Kd[0, 0], Kd[1, 1], Kd[0, 2], Kd[1, 2]
    tan_x = 0.5 * width / fx
    tan_y = 0.5 * height / fy
    lim_xp = (width - cx) / fx + 0.3 * tan_x
    lim_xn = cx / fx + 0.3 * tan_x
    lim_yp = (height - cy) / fy + 0.3 * tan_y
    lim_yn = cy / fy + 0.3 * tan_y
    tx = zs * torch.clamp(p[:, 0] / zs, min=-lim_xn, max=lim_xp)
    ty = zs * torch.clamp(p[:, 1] / zs, min=-lim_yn, max=lim_yp)
    # 3. Jacobian of the perspective map at the (clamped) mean; cov2d = (J Mc)(J Mc)ᵀ
    iz = 1.0 / zs
    zero = torch.zeros_like(zs)
    J = torch.stack(
        [fx * iz, zero, -fx * tx * iz * iz, zero, fy * iz, -fy * ty * iz * iz], dim=-1
    ).reshape(-1, 2, 3)
    JM = J @ Mc  # [N, 2, 3]
    g0, g1 = JM[:, 0], JM[:, 1]  # rows: cov2d = [[g0·g0, g0·g1], [g0·g1, g1·g1]] + eps2d I
    cxx0, cyy0 = (g0 * g0).sum(-1), (g1 * g1).sum(-1)
    cxx, cxy, cyy = cxx0 + eps2d, (g0 * g1).sum(-1), cyy0 + eps2d
    # Guard (stress suite, splat.single_gaussian_exact): the determinant by the Lagrange
    # identity, |g0|²|g1|² - (g0·g1)² = |g0 × g1|², a sum of squares. cxx·cyy - cxy² cancels
    # catastrophically for a long thin Gaussian turned in the image near the camera (1 km x
    # 1 µm at 1 cm, f = 1000 px: cxx ~ 1e22 px²): the Gaussian vanished, covered the whole
    # image, or got an indefinite conic (alpha 0.99 at opacity 0.9).
    cross = torch.linalg.cross(g0, g1, dim=-1)
    det = ((cross * cross).sum(-1) + eps2d * (cxx0 + cyy0) + eps2d * eps2d).clamp_min(1e-10)
    conics = torch.stack([cyy / det, -cxy / det, cxx / det], dim=-1)
    ps = torch.where(in_range[:, None], p, torch.ones_like(p))
    uv = (ps @ Kd[:2, :].T) / zs[:, None]  # [N, 2]
    # 4. Radii and screen culling, as gsplat
    radius = torch.ceil(RADIUS_SIGMAS * torch.sqrt(torch.stack([cxx, cyy], -1))).detach()
    with torch.no_grad():
        inside = (
            (uv[:, 0] + radius[:, 0] > 0)
            & (uv[:, 0] - radius[:, 0] < width)
            & (uv[:, 1] + radius[:, 1] > 0)
            & (uv[:, 1] - radius[:, 1] < height)
        )
        keep = in_range & inside & torch.isfinite(det) & (det > 0)
        radii = torch.where(keep[:, None], radius.clamp(max=2**30), 0).to(torch.int32)
    return Projection(
        means2d=uv.to(dtype),
        conics=conics.to(dtype),
        depths=z.to(dtype),
        radii=radii,
        cov2d=torch.stack([cxx, cxy, cyy], -1),
    )


@dataclass
class TilePlan:
    """Which Gaussians touch which tile, front to back (no gradients)."""

    tile_size: int
    tiles_x: int
    tiles_y: int
    isect_gauss: Tensor  # [M] int64 index into the visible Gaussians, sorted by (tile, depth)
    isect_tile: Tensor  # [M] int64 tile id (row-major)
    tile_start: Tensor  # [n_tiles] int64 first intersection of each tile
    tile_count: Tensor  # [n_tiles] int64 intersections per tile
    order: Tensor  # [n_tiles] int64 tiles by decreasing count: how threads share the tiles

    @property
    def n_isects(self) -> int:
        return int(self.isect_gauss.shape[0])


@torch.no_grad()
def bin_tiles(
    means2d: Tensor,  # [V, 2] px
    cov2d: Tensor,  # [V, 3] (xx, xy, yy) px², after eps2d
    opacities: Tensor,  # [V] in [1/255, 1]
    depths: Tensor,  # [V] m
    width: int,
    height: int,
    tile_size: int,
) -> TilePlan:
    """Assign Gaussians to every tile holding a pixel centre where alpha can reach 1/255.

    Outside |dx| <= k·σx (and the same in y), with k = sqrt(2 ln(255·o)), the exponent is at
    least k²/2 for any dy (the marginal bound), so alpha < 1/255 there: no contribution is lost.
    """
    ts = tile_size
    tiles_x = -(-width // ts)
    tiles_y = -(-height // ts)
    k = torch.sqrt(2.0 * torch.log(opacities.double() * 255.0).clamp_min(0.0)).clamp_max(
        RADIUS_SIGMAS
    )
    rx = k * torch.sqrt(cov2d[:, 0])
    ry = k * torch.sqrt(cov2d[:, 2])
    m = means2d.double()
    # pixel i (centre i + 0.5) is reachable iff |i + 0.5 - mx| <= rx
    x0 = torch.ceil(m[:, 0] - rx - 0.5).clamp(0, width - 1)
    x1 = torch.floor(m[:, 0] + rx - 0.5).clamp(-1, width - 1)
    y0 = torch.ceil(m[:, 1] - ry - 0.5).clamp(0, height - 1)
    y1 = torch.floor(m[:, 1] + ry - 0.5).clamp(-1, height - 1)
    tx0 = (x0 // ts).long()
    tx1 = (x1 // ts).long()
    ty0 = (y0 // ts).long()
    ty1 = (y1 // ts).long()
    empty = (x1 < x0) | (y1 < y0)
    tx1 = torch.where(empty, tx0 - 1, tx1)  # no tile columns: the kernel's loop is empty
    gauss, tile, tile_start, tile_count = (
        torch.from_numpy(a)
        for a in kernels.bin_pairs(
            *(t.cpu().numpy() for t in (tx0, tx1, ty0, ty1, depths)), tiles_x, tiles_x * tiles_y
        )
    )
    order = torch.argsort(tile_count, descending=True, stable=True)
    return TilePlan(ts, tiles_x, tiles_y, gauss, tile, tile_start, tile_count, order)


class _RasterizeTiles(torch.autograd.Function):
    """Front-to-back compositing of features over tiles; the last feature is 1 (gives alpha).

    Output: Σ w·f per pixel [H, W, F]. Both passes run the compiled kernels of
    :mod:`~gsfix_online.mapping.splat.raster_kernels` on ``torch.get_num_threads()`` threads.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx,
        means2d: Tensor,  # [V, 2]
        conics: Tensor,  # [V, 3]
        opacities: Tensor,  # [V]
        feats: Tensor,  # [V, F]
        plan: TilePlan,
        width: int,
        height: int,
    ) -> Tensor:
        arrays = [t.detach().cpu().numpy() for t in (means2d, conics, opacities, feats)]
        out = kernels.composite_forward(*arrays, *_plan_arrays(plan, width, height))
        ctx.save_for_backward(means2d, conics, opacities, feats)
        ctx.plan, ctx.width, ctx.height, ctx.out = plan, width, height, out
        return torch.from_numpy(out).to(feats.dtype)

    @staticmethod
    def backward(ctx, d_out: Tensor):  # type: ignore[override]
        means2d, conics, opacities, feats = ctx.saved_tensors
        plan: TilePlan = ctx.plan
        arrays = [t.detach().cpu().numpy() for t in (means2d, conics, opacities, feats)]
        per_isect = kernels.composite_backward(
            *arrays, *_plan_arrays(plan, ctx.width, ctx.height), ctx.out, d_out.numpy()
        )
        grad = torch.zeros(means2d.shape[0], per_isect.shape[1], dtype=torch.float64)
        grad.index_add_(0, plan.isect_gauss, torch.from_numpy(per_isect))
        grad = grad.to(means2d.dtype)
        return grad[:, 0:2], grad[:, 2:5], grad[:, 5], grad[:, 6:], None, None, None


def _plan_arrays(plan: TilePlan, width: int, height: int) -> tuple:
    """The plan as the kernels take it (after the per-Gaussian arrays)."""
    return (
        plan.isect_gauss.numpy(), plan.tile_start.numpy(), plan.tile_count.numpy(),
        plan.order.numpy(), plan.tiles_x, plan.tile_size, width, height,
        max(1, torch.get_num_threads()),
    )  # fmt: skip


def rasterize_tiles(
    means2d: Tensor,  # [V, 2] px
    conics: Tensor,  # [V, 3]
    opacities: Tensor,  # [V] in [1/255, 1]
    feats: Tensor,  # [V, F] colour channels, depth, ...
    plan: TilePlan,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:  # Σ w·f [H, W, F], alpha [H, W]
    """Differentiable front-to-back compositing of pre-binned Gaussians (no background)."""
    feats1 = torch.cat([feats, feats.new_ones(feats.shape[0], 1)], -1)  # last column -> alpha
    img = _RasterizeTiles.apply(means2d, conics, opacities, feats1, plan, width, height)
    return img[..., :-1], img[..., -1]


@torch.no_grad()
def frustum_candidates(
    means: Tensor,  # [N, 3] world, m
    scales: Tensor,  # [N, 3] m (activated)
    viewmat: Tensor,  # [4, 4] T_cam_world
    K: Tensor,  # [3, 3] pixels
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = EPS2D,
) -> Tensor:  # [Nc] int64 indices, a superset of the Gaussians project_gaussians keeps
    """Indices of the Gaussians that :func:`project_gaussians` could keep (a cheap bound).

    Same depth test; on screen, the radius is bounded from above without the rotation:
    ``sqrt(cxx) = |J_0 M| <= |J_0| max(s) + sqrt(eps2d)`` (M = R diag(s) has spectral norm
    ``max(s)``), with a 1 % and 2 px margin for rounding. Projecting only these rows gives the
    same render and gradients and saves the float64 projection and its backward for the (often
    most) Gaussians behind or beside the camera.
    """
    f64 = torch.float64
    Rcw, t = viewmat[:3, :3].to(f64), viewmat[:3, 3].to(f64)
    p = means.to(f64) @ Rcw.T + t
    z = p[:, 2]
    in_range = (z > near) & (z < far)
    zs = torch.where(in_range, z, torch.ones_like(z))
    Kd = K.to(f64)
    fx, fy, cx, cy = Kd[0, 0], Kd[1, 1], Kd[0, 2], Kd[1, 2]
    lim_x = torch.maximum((width - cx) / fx, cx / fx) + 0.3 * 0.5 * width / fx
    lim_y = torch.maximum((height - cy) / fy, cy / fy) + 0.3 * 0.5 * height / fy
    rx_ = torch.clamp(p[:, 0] / zs, -lim_x, lim_x)
    ry_ = torch.clamp(p[:, 1] / zs, -lim_y, lim_y)
    smax = scales.to(f64).amax(-1)
    slack = eps2d**0.5
    rad_x = RADIUS_SIGMAS * (fx / zs * torch.sqrt(1 + rx_ * rx_) * smax + slack) * 1.01 + 2
    rad_y = RADIUS_SIGMAS * (fy / zs * torch.sqrt(1 + ry_ * ry_) * smax + slack) * 1.01 + 2
    uv = (p @ Kd[:2, :].T) / zs[:, None]
    u, v = uv[:, 0], uv[:, 1]
    ok = in_range & (u + rad_x > 0) & (u - rad_x < width) & (v + rad_y > 0) & (v - rad_y < height)
    return torch.nonzero(ok | ~torch.isfinite(u + v)).squeeze(1)


def render_cpu(
    means: Tensor,  # [N, 3] world, m
    quats: Tensor,  # [N, 4] (w, x, y, z)
    scales: Tensor,  # [N, 3] m, activated
    opacities: Tensor,  # [N] in [0, 1]
    colors: Tensor,  # [N, C], or [N, K, C] SH with sh_degree
    viewmat: Tensor,  # [4, 4] T_cam_world
    K: Tensor,  # [3, 3] pixels
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    sh_degree: int | None = None,
    background: Tensor | None = None,  # [C]
    eps2d: float = EPS2D,
    tile_size: int = 4,
    precull: bool = True,
) -> RenderOutput:
    """The CPU backend of :func:`gsfix_online.mapping.splat.render.render` (inputs validated).

    ``precull`` projects only :func:`frustum_candidates` (same output and gradients; off in the
    tests that check exactly that).
    """
    # 1. Project the Gaussians that can be on screen; the rest get radius 0 like culled rows
    N = means.shape[0]
    if precull:
        cand = frustum_candidates(means, scales, viewmat, K, width, height, near, far, eps2d)
    else:
        cand = torch.arange(N, device=means.device)
    sub = project_gaussians(
        means[cand], quats[cand], scales[cand], viewmat, K, width, height, near, far, eps2d
    )
    means2d = sub.means2d.new_zeros(N, 2).index_copy(0, cand, sub.means2d)[None]  # [1, N, 2]
    if means2d.requires_grad:  # the tensor densification reads .grad from
        means2d.retain_grad()
    radii = sub.radii.new_zeros(N, 2).index_copy(0, cand, sub.radii)
    # 2. Keep those drawn with some alpha >= 1/255 (rows of ``sub``; ``vis`` indexes the map)
    drawn_sub = (sub.radii > 0).all(-1) & (opacities[cand] >= ALPHA_MIN)
    vis_sub = torch.nonzero(drawn_sub).squeeze(1)
    vis = cand[vis_sub]
    # 3. Colours (SH towards the camera) and depth as features to composite
    if sh_degree is None:
        cols = colors[vis]
    else:
        campos = -viewmat[:3, :3].T @ viewmat[:3, 3]
        cols = eval_sh(sh_degree, means[vis] - campos, colors[vis])
    feats = torch.cat([cols, sub.depths[vis_sub, None]], -1)  # [V, C+1]
    # 4. Bin into tiles and composite front to back
    m2d = means2d[0, vis]
    plan = bin_tiles(
        m2d.detach(), sub.cov2d[vis_sub], opacities[vis].detach(), sub.depths[vis_sub].detach(),
        width, height, tile_size,
    )  # fmt: skip
    acc, alpha = rasterize_tiles(
        m2d, sub.conics[vis_sub], opacities[vis], feats, plan, width, height
    )
    # 5. Background, normalised depth, gsplat-style info
    C = cols.shape[1]
    color = acc[..., :C]
    if background is not None:
        color = color + (1.0 - alpha)[..., None] * background
    depth = acc[..., C] / alpha.clamp_min(1e-10)
    info = {
        "means2d": means2d,
        "radii": radii[None],
        "depths": sub.depths.detach().new_zeros(N).index_copy(0, cand, sub.depths.detach())[None],
        "conics": sub.conics.detach()
        .new_zeros(N, 3)
        .index_copy(0, cand, sub.conics.detach())[None],
        "width": width,
        "height": height,
        "n_cameras": 1,
        "gaussian_ids": None,
        "tile_size": tile_size,
        "n_isects": plan.n_isects,
    }
    return RenderOutput(color=color, depth=depth, alpha=alpha, info=info)
