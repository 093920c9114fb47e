"""One renderer interface for the Gaussian map: colour, depth, alpha and what densification needs.

``render(..., backend="auto")`` uses gsplat's CUDA rasterizer when ``torch.cuda.is_available()``
and our PyTorch tile rasterizer (:mod:`.render_cpu`) otherwise. Both follow gsplat's math
(EWA projection, ``eps2d`` low-pass, alpha clamp 0.99, alpha threshold 1/255, transmittance stop
1e-4, near/far culling) and return the same :class:`RenderOutput`.

Conventions (as gsplat's ``rasterization``):

- ``scales`` are standard deviations in metres, already activated (the map stores log-scales
  and passes ``exp``); ``opacities`` are in [0, 1], already activated (``sigmoid``);
  ``quats`` are (w, x, y, z) of any norm, normalised inside the graph, and a quaternion with
  |q|² < 1e-12 means the identity rotation (the map's rule, ``gaussians.normalize_quats``).
- ``colors`` are either post-activation colours [N, C] (C = 1 for grayscale maps, or 3) or, with
  ``sh_degree``, SH coefficients [N, K, C] evaluated towards the camera as
  ``max(Σ basis·coeff + 0.5, 0)``.
- ``viewmat`` is world -> camera (``T_cam_world``) with OpenCV axes; pass ``T_world_cam=``
  instead to give the camera pose.
- ``depth`` is the expected z-depth normalised by alpha, Σ wᵢ zᵢ / max(α, 1e-10) (gsplat's
  ``"ED"``). Every contributing Gaussian has alpha >= 1/255, so α is either 0 (depth 0) or at
  least 1/255 and the division is safe; ``depth * alpha`` is the un-normalised sum.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from gsfix_online.mapping.splat.render_output import EPS2D, RenderOutput

Backend = Literal["auto", "cpu", "cuda"]

__all__ = ["Backend", "RenderOutput", "render", "resolve_backend"]


def resolve_backend(backend: Backend, device: torch.device | None = None) -> Literal["cpu", "cuda"]:
    """The backend ``backend`` names; ``auto`` is the device of the data (``device``), or,
    without one, CUDA when torch sees a GPU (where a map that has no data yet is placed)."""
    if backend == "auto":
        if device is not None:
            return "cuda" if device.type == "cuda" else "cpu"
        return "cuda" if torch.cuda.is_available() else "cpu"
    if backend not in ("cpu", "cuda"):
        raise ValueError(f"backend must be 'auto', 'cpu' or 'cuda', got {backend!r}")
    return backend


def _shape(t: Tensor) -> str:
    return f"{str(t.dtype).replace('torch.', '')} {list(t.shape)}"


def _check_inputs(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float,
    far: float,
    sh_degree: int | None,
    background: Tensor | None,
) -> None:
    """Validate once, at the public boundary; one line saying what was expected and what came."""
    if means.ndim != 2 or means.shape[1] != 3 or not means.is_floating_point():
        raise ValueError(f"means must be float [N, 3] world metres, got {_shape(means)}")
    n, dt = means.shape[0], means.dtype
    for name, t, shp in (
        ("quats", quats, (n, 4)),
        ("scales", scales, (n, 3)),
        ("opacities", opacities, (n,)),
        ("viewmat", viewmat, (4, 4)),
        ("K", K, (3, 3)),
    ):
        if tuple(t.shape) != shp or t.dtype != dt:
            want = f"{str(dt).replace('torch.', '')} {list(shp)}"
            raise ValueError(f"{name} must be {want} like means, got {_shape(t)}")
    if sh_degree is None:
        if colors.ndim != 2 or colors.shape[0] != n or colors.shape[1] < 1:
            raise ValueError(
                f"colors must be [N={n}, C] (or SH with sh_degree), got {_shape(colors)}"
            )
    else:
        need = (sh_degree + 1) ** 2
        if not 0 <= sh_degree <= 3:
            raise ValueError(f"sh_degree must be in 0..3, got {sh_degree}")
        if colors.ndim != 3 or colors.shape[0] != n or colors.shape[1] < need:
            raise ValueError(
                f"colors must be SH [N={n}, K>={need}, C] for sh_degree {sh_degree}, "
                f"got {_shape(colors)}"
            )
    if colors.dtype != dt:
        raise ValueError(f"colors must be {dt} like means, got {_shape(colors)}")
    C = colors.shape[-1]
    if background is not None and (tuple(background.shape) != (C,) or background.dtype != dt):
        raise ValueError(
            f"background must be {str(dt).replace('torch.', '')} [{C}], got {_shape(background)}"
        )
    if width <= 0 or height <= 0:
        raise ValueError(f"width and height must be positive, got {width}x{height}")
    if not 0 < near < far:
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    with torch.no_grad():
        for name, t in (("means", means), ("quats", quats), ("scales", scales), ("colors", colors)):
            bad = int((~torch.isfinite(t)).sum())
            if bad:
                raise ValueError(f"{name} has {bad} non-finite values")
        if n and not bool(((opacities >= 0) & (opacities <= 1)).all()):
            raise ValueError("opacities must be activated values in [0, 1] (apply sigmoid first)")
        if n and bool((scales < 0).any()):
            raise ValueError("scales must be activated (>= 0, apply exp to log-scales first)")


def render(
    means: Tensor,  # [N, 3] world, m
    quats: Tensor,  # [N, 4] (w, x, y, z), any norm
    scales: Tensor,  # [N, 3] m, activated
    opacities: Tensor,  # [N] in [0, 1], activated
    colors: Tensor,  # [N, C] colours, or [N, K, C] SH coefficients with sh_degree
    viewmat: Tensor | None,  # [4, 4] T_cam_world (OpenCV axes); None if T_world_cam is given
    K: Tensor,  # [3, 3] pixels
    width: int,
    height: int,
    *,
    T_world_cam: Tensor | None = None,  # [4, 4] camera pose, instead of viewmat
    backend: Backend = "auto",
    near: float = 0.01,
    far: float = 1e10,
    sh_degree: int | None = None,
    background: Tensor | None = None,  # [C]; default black
    eps2d: float = EPS2D,
    tile_size: int = 4,  # CPU only; gsplat's CUDA kernels use 16
    absgrad: bool = False,  # CUDA only: also fill info["means2d"].absgrad
) -> RenderOutput:
    """Render one view of the Gaussians with the chosen backend."""
    # 1. Camera
    if (viewmat is None) == (T_world_cam is None):
        raise ValueError("give exactly one of viewmat (T_cam_world) and T_world_cam")
    if viewmat is None:
        viewmat = torch.linalg.inv(T_world_cam)
    # 2. Check inputs
    _check_inputs(
        means, quats, scales, opacities, colors, viewmat, K, width, height, near, far,
        sh_degree, background,
    )  # fmt: skip
    # 3. Dispatch
    kind = resolve_backend(backend, means.device)
    if (kind == "cuda") != (means.device.type == "cuda"):
        raise ValueError(f"backend {kind} cannot render Gaussians on {means.device}")
    if kind == "cuda":
        from gsfix_online.mapping.splat.render_cuda import render_cuda

        return render_cuda(
            means, quats, scales, opacities, colors, viewmat, K, width, height,
            near=near, far=far, sh_degree=sh_degree, background=background, eps2d=eps2d,
            absgrad=absgrad,
        )  # fmt: skip
    from gsfix_online.mapping.splat.render_cpu import render_cpu

    return render_cpu(
        means, quats, scales, opacities, colors, viewmat, K, width, height,
        near=near, far=far, sh_degree=sh_degree, background=background, eps2d=eps2d,
        tile_size=tile_size,
    )  # fmt: skip
