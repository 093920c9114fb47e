"""The CUDA backend: a thin adapter to ``gsplat.rasterization`` (imported lazily).

Same conventions and output as the CPU backend (see :mod:`.render`): ``render_mode="RGB+ED"``
gives the alpha-normalised expected depth, ``packed=False`` gives the [1, N, ...] info layout
that gsplat's ``DefaultStrategy`` reads. SH with a channel count other than 3 (grayscale maps)
is evaluated here with :func:`.sh.eval_sh`, since gsplat's SH kernel takes 3 channels.
"""

from __future__ import annotations

from torch import Tensor

from gsfix_online.mapping.splat.render_output import EPS2D, RenderOutput
from gsfix_online.mapping.splat.sh import eval_sh


def _rasterization():  # noqa: ANN202
    try:
        from gsplat import rasterization
    except ImportError as e:  # pragma: no cover - depends on the install
        raise ImportError(
            "the CUDA renderer needs gsplat: pip install -e '.[cuda]' (or pip install gsplat)"
        ) from e
    return rasterization


def render_cuda(
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
    absgrad: bool = False,
) -> RenderOutput:
    rasterization = _rasterization()
    if sh_degree is not None and colors.shape[-1] != 3:
        campos = -viewmat[:3, :3].T @ viewmat[:3, 3]
        colors, sh_degree = eval_sh(sh_degree, means - campos, colors), None
    C = colors.shape[-1]
    img, alpha, meta = rasterization(
        means, quats, scales, opacities, colors, viewmat[None], K[None], width, height,
        near_plane=near, far_plane=far, eps2d=eps2d, sh_degree=sh_degree, packed=False,
        backgrounds=None if background is None else background[None], render_mode="RGB+ED",
        absgrad=absgrad,
    )  # fmt: skip
    info = dict(meta)
    info["n_isects"] = int(meta["isect_ids"].shape[0]) if "isect_ids" in meta else -1
    return RenderOutput(
        color=img[0, ..., :C], depth=img[0, ..., C], alpha=alpha[0, ..., 0], info=info
    )
