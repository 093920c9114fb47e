"""What a user would do without GSFixer, kept as baselines in every report.

(a) the raw 3DGS render; (b) **mesh fill**: the 3DGS render where its alpha is high, the mesh
render elsewhere; (c) **OpenCV inpainting** (Telea) of what is still missing after (b).
Images are uint8 [H, W] or [H, W, 3]; alpha is float [H, W] in [0, 1]; masks are bool [H, W].
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt


@dataclass(frozen=True)
class FillResult:
    image: npt.NDArray[np.uint8]  # [H, W] or [H, W, 3]
    missing: npt.NDArray[np.bool_]  # [H, W]: neither the 3DGS map nor the mesh covers it


def _check(name: str, arr: np.ndarray, shape: tuple[int, ...], dtype: str) -> None:
    if arr.shape[:2] != shape[:2] or arr.dtype.kind != dtype:
        kind = {"u": "uint8", "f": "float", "b": "bool"}[dtype]
        raise ValueError(
            f"{name} must be {kind} {list(shape[:2])}..., got {arr.dtype} {list(arr.shape)}"
        )


def mesh_fill(
    gs_color: npt.NDArray[np.uint8],  # [H, W(, 3)]
    gs_alpha: npt.NDArray[np.floating],  # [H, W]
    mesh_color: npt.NDArray[np.uint8],  # [H, W(, 3)]
    mesh_valid: npt.NDArray[np.bool_],  # [H, W]
    alpha_min: float = 0.5,
) -> FillResult:
    """Baseline (b): keep the 3DGS render where ``gs_alpha >= alpha_min``, take the mesh render
    where the mesh was hit, and report the pixels neither covers."""
    shape = gs_color.shape
    _check("gs_color", gs_color, shape, "u")
    _check("gs_alpha", gs_alpha, shape, "f")
    _check("mesh_color", mesh_color, shape, "u")
    _check("mesh_valid", mesh_valid, shape, "b")
    if mesh_color.shape != shape:
        raise ValueError(
            f"mesh_color must match gs_color {list(shape)}, got {list(mesh_color.shape)}"
        )
    from_gs = gs_alpha >= alpha_min
    use_mesh = ~from_gs & mesh_valid
    out = gs_color.copy()
    out[use_mesh] = mesh_color[use_mesh]
    return FillResult(out, ~from_gs & ~mesh_valid)


def inpaint_telea(
    image: npt.NDArray[np.uint8],  # [H, W(, 3)]
    missing: npt.NDArray[np.bool_],  # [H, W]
    radius_px: float = 5.0,
) -> npt.NDArray[np.uint8]:
    """Baseline (c): OpenCV's Telea inpainting of the ``missing`` pixels (others unchanged)."""
    _check("image", image, image.shape, "u")
    _check("missing", missing, image.shape, "b")
    if not missing.any():
        return image.copy()
    if missing.all():  # nothing to propagate from: Telea would return the input unchanged
        return image.copy()
    out = cv2.inpaint(
        np.ascontiguousarray(image), missing.astype(np.uint8), radius_px, cv2.INPAINT_TELEA
    )
    return out.reshape(image.shape)
