"""What a user would do without GSFixer, kept as baselines in every report.

(a) the raw 3DGS render; (b) **mesh fill**: the 3DGS render where its alpha is high, the mesh
render elsewhere; (c) **classical inpainting** of what is still missing after (b), by each of
OpenCV's methods: Telea (``cv2.INPAINT_TELEA``, fast marching), Navier-Stokes
(``cv2.INPAINT_NS``) and frequency-selective reconstruction (FSR, ``cv2.xphoto.inpaint`` of the
contrib build, ``opencv-contrib-python-headless``); (d) each map alone, its holes inpainted by
Telea: the mesh render (``mesh_inpaint`` in reports: Open3D and OpenCV without a Gaussian map)
and the 3DGS render (``gs_inpaint``: the Gaussian map held to the same fill, so that the two maps
are compared on what they render rather than on what they leave empty).
Images are uint8 [H, W] or [H, W, 3] RGB; alpha is float [H, W] in [0, 1]; masks are bool [H, W].
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
import numpy.typing as npt

InpaintMethod = Literal["telea", "ns", "fsr"]
INPAINT_METHODS: tuple[InpaintMethod, ...] = ("telea", "ns", "fsr")

# FSR_FAST, not FSR_BEST: BEST costs far more than the 2 s a 320x240 view may take. Measured on
# the shared 2-core machine (load average 8): a 320x240 view with 12 % missing, FAST 0.63 s, BEST
# 12.4 s; a 1200x680 view with 12 % missing, FAST 6.3 s, BEST 179 s. FSR's time grows with the
# missing area (FAST, 320x240: 0.15 s at 2 %, 4.5 s at 30 %; 1200x680: 1.5 s at 2 %, 40 s at
# 30 %) and with the machine's load (FAST at load 16: 8.2 s and 41 s for the 12 % views, where
# Telea took 0.28 s and 1.4 s). So the reports make it once per view, with the metrics.
FSR_FLAG = cv2.xphoto.INPAINT_FSR_FAST if hasattr(cv2, "xphoto") else None
FSR_BLOCK = 16  # pixels: the block size FSR fills in
ALPHA_MIN = 0.5  # a 3DGS render covers a pixel where its alpha reaches this


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
    alpha_min: float = ALPHA_MIN,
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


def inpaint(
    image: npt.NDArray[np.uint8],  # [H, W(, 3)] RGB
    missing: npt.NDArray[np.bool_],  # [H, W]
    method: InpaintMethod = "telea",
    radius_px: float = 5.0,  # telea and ns: the neighbourhood each filled pixel draws from
) -> npt.NDArray[np.uint8]:  # [H, W(, 3)]
    """Baseline (c): OpenCV's inpainting of the ``missing`` pixels by ``method``; the other
    pixels are returned unchanged."""
    if method not in INPAINT_METHODS:
        raise ValueError(
            f"inpainting method must be one of {list(INPAINT_METHODS)}, got {method!r}"
        )
    if (
        image.dtype != np.uint8
        or image.ndim not in (2, 3)
        or image.shape[2:] not in ((), (1,), (3,))
    ):
        raise ValueError(
            f"image must be uint8 [H, W] or [H, W, 1|3], got {image.dtype} {list(image.shape)}"
        )
    if missing.dtype != np.bool_ or missing.shape != image.shape[:2]:
        raise ValueError(
            f"missing must be bool {list(image.shape[:2])}, got {missing.dtype} {list(missing.shape)}"
        )
    if not missing.any() or missing.all():  # nothing to fill, or nothing to propagate from
        return image.copy()
    src = np.ascontiguousarray(image)
    if method != "fsr":
        flag = cv2.INPAINT_TELEA if method == "telea" else cv2.INPAINT_NS
        return cv2.inpaint(src, missing.astype(np.uint8), radius_px, flag).reshape(image.shape)
    if FSR_FLAG is None:
        raise ImportError(
            "FSR inpainting needs OpenCV's contrib build: pip uninstall opencv-python-headless "
            "&& pip install opencv-contrib-python-headless"
        )
    colour = src.ndim == 3 and src.shape[2] == 3
    bgr = cv2.cvtColor(src, cv2.COLOR_RGB2BGR) if colour else src.reshape(src.shape[:2])
    # OpenCV's FSR fills whole 16x16 blocks only: the pixels of a last, partial block row or
    # column stay unfilled (measured: any height or width not a multiple of 16). Mirror the
    # image and the mask out to whole blocks, and crop the result back.
    h, w = missing.shape
    pad = ((0, -h % FSR_BLOCK), (0, -w % FSR_BLOCK))
    known = np.pad(np.where(missing, 0, 255).astype(np.uint8), pad, mode="symmetric")
    padded = np.pad(bgr, pad + ((0, 0),) * (bgr.ndim - 2), mode="symmetric")
    dst = np.zeros_like(padded)
    cv2.xphoto.inpaint(padded, known, dst, FSR_FLAG)
    dst = dst[:h, :w]
    out = (cv2.cvtColor(dst, cv2.COLOR_BGR2RGB) if colour else dst).reshape(image.shape)
    # FSR works in a luma/chroma space: a round trip moves known colour pixels by up to one level
    out[~missing] = image[~missing]
    return out


def inpaint_telea(
    image: npt.NDArray[np.uint8],  # [H, W(, 3)]
    missing: npt.NDArray[np.bool_],  # [H, W]
    radius_px: float = 5.0,
) -> npt.NDArray[np.uint8]:
    """Baseline (c) by Telea's method (what the fallbacks of repair.fallback use)."""
    return inpaint(image, missing, "telea", radius_px)


def gs_inpaint(
    gs_color: npt.NDArray[np.uint8],  # [H, W(, 3)]
    gs_alpha: npt.NDArray[np.floating],  # [H, W]
    alpha_min: float = ALPHA_MIN,
) -> npt.NDArray[np.uint8]:
    """Baseline (d) for the Gaussian map: its render where ``gs_alpha >= alpha_min``, Telea's
    fill of the rest (no mesh)."""
    _check("gs_color", gs_color, gs_color.shape, "u")
    _check("gs_alpha", gs_alpha, gs_color.shape, "f")
    return inpaint_telea(gs_color, gs_alpha < alpha_min)


def fill_and_inpaint(
    gs_color: npt.NDArray[np.uint8],  # [H, W(, 3)]
    gs_alpha: npt.NDArray[np.floating],  # [H, W]
    mesh_color: npt.NDArray[np.uint8],  # [H, W(, 3)]
    mesh_valid: npt.NDArray[np.bool_],  # [H, W]
    methods: tuple[InpaintMethod, ...] = INPAINT_METHODS,
    alpha_min: float = ALPHA_MIN,
) -> dict[str, npt.NDArray[np.uint8]]:  # "mesh_fill" and each method -> [H, W(, 3)]
    """Baselines (b) and (c) of one view: mesh fill, then each inpainting of what it misses."""
    fill = mesh_fill(gs_color, gs_alpha, mesh_color, mesh_valid, alpha_min)
    out = {"mesh_fill": fill.image}
    for m in methods:
        out[m] = inpaint(fill.image, fill.missing, m)
    return out
