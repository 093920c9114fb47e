"""The keyframe -> GSFixer training-sample recipe, in one place.

A training sample of a keyframe (or a frame sample) is made in two halves, as the graph runs it:

1. **at the map** (:func:`map_arrays`): the camera image, depth, pose and intrinsics with the
   Gaussian map's render and alpha at the keyframe (uint8 colour, float alpha), plus the map's
   alpha at ``renders`` poses perturbed around where the map put the frame, rendered at
   ``1 / downscale`` of the frame size and resized back (nearest): the holes of views off the
   trajectory. These are the arrays a ``keyframe`` message carries (the splat service);
2. **at the trainer** (:func:`training_sample`): the TSDF mesh ray-cast at the keyframe's pose
   (:func:`mesh_image`), the triplet ``(I_mesh, I_gs, I_gt)`` with the keyframe's own alpha
   holes and the informative holes of its perturbed renders as mask candidates, and the
   disocclusions of up to ``neighbours`` earlier samples' depth warped into it.

:func:`keyframe_sample` runs both at once (the reports). :func:`render_pair` renders the mesh
and the map at any pose (the pretraining corpus and the reports' novel views). No IO; the
randomness is the generator given.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from gsfix_online.core.types import Intrinsics, RGBDFrame
from gsfix_online.fixer.masks import (
    disocclusion_mask,
    informative_hole,
    perturbed_pose,
)
from gsfix_online.fixer.triplets import Triplet, triplet_from_keyframe

Arrays = Mapping[str, npt.NDArray[Any]]


@dataclass(frozen=True)
class Perturbation:
    """The perturbed map renders sent with a keyframe (their values come from the caller's
    config: the splat node's ``perturbed_*`` and ``perturb_*`` parameters)."""

    renders: int  # renders per keyframe; 0 = none
    max_deg: float  # rotation of those poses about a random axis
    max_m: float  # translation of those poses, m
    downscale: int  # rendered at 1/downscale of the frame size


@dataclass
class TrainingSample:
    """One keyframe's training example: its triplet and disocclusion mask candidates."""

    triplet: Triplet
    disocclusions: list[npt.NDArray[np.bool_]] = field(default_factory=list)  # [H, W] each


@dataclass(frozen=True)
class RenderPair:
    """The two maps rendered at one pose; images uint8 [H, W, 3]."""

    mesh: npt.NDArray[np.uint8]  # mesh colour, black where it has no surface
    mesh_valid: npt.NDArray[np.bool_]  # [H, W] the ray hit the mesh
    gs: npt.NDArray[np.uint8]  # Gaussian-map render over black
    gs_alpha: npt.NDArray[np.float32]  # [H, W]


def rgb8(color: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    """[H, W, C] (C = 1 or 3) or [H, W], float in [0, 1] or uint8 -> [H, W, 3] uint8."""
    if color.dtype != np.uint8:
        color = np.rint(np.clip(color, 0.0, 1.0) * 255.0).astype(np.uint8)
    if color.ndim == 2:
        color = color[:, :, None]
    return np.ascontiguousarray(np.repeat(color, 3, axis=2) if color.shape[2] == 1 else color)


# ------------------------------------------------------------------------------------------
# 1. At the map
# ------------------------------------------------------------------------------------------


def perturbed_alpha(
    mapper: Any,  # mapping.splat.mapper.Mapper
    frame: RGBDFrame,
    rng: np.random.Generator,
    p: Perturbation,
) -> npt.NDArray[np.float32]:  # [P, H, W]
    """The map's alpha at ``p.renders`` poses perturbed around where the map put the frame
    (``mapper.pose_for``), at ``1 / p.downscale`` size, resized back (nearest)."""
    import cv2

    h, w = frame.depth.shape
    small = frame.intrinsics.scaled(w // p.downscale, h // p.downscale)  # same camera, 1/s size
    out = np.empty((p.renders, h, w), np.float32)
    for i in range(p.renders):
        T = perturbed_pose(mapper.pose_for(frame.T_world_cam), rng, p.max_deg, p.max_m)
        _, _, a = mapper.render_numpy(T, small.K, small.width, small.height)
        out[i] = cv2.resize(a, (w, h), interpolation=cv2.INTER_NEAREST)
    return out


def map_arrays(
    mapper: Any,  # mapping.splat.mapper.Mapper
    frame: RGBDFrame,
    render: npt.NDArray[np.floating],  # [H, W, C] the map's colour at the frame, [0, 1]
    alpha: npt.NDArray[np.floating],  # [H, W]
    rng: np.random.Generator,
    p: Perturbation,
) -> dict[str, npt.NDArray[Any]]:
    """The arrays a keyframe message carries for training (see module doc, step 1)."""
    arrays = {
        "color": frame.color,
        "depth": frame.depth,
        "K": frame.intrinsics.K,
        "T_world_cam": frame.T_world_cam,
        "gs_render": rgb8(render),
        "gs_alpha": np.ascontiguousarray(alpha, dtype=np.float32),
    }
    if p.renders:
        arrays["perturbed_alpha"] = perturbed_alpha(mapper, frame, rng, p)
    return arrays


# ------------------------------------------------------------------------------------------
# 2. At the trainer
# ------------------------------------------------------------------------------------------


def mesh_render(renderer: Any, arrays: Arrays) -> Any:  # mapping.mesh_render.MeshRender
    """The mesh (a ``MeshRenderer``) ray-cast at the sample's pose and intrinsics: colour,
    depth (the reference warp's, in mode mesh+gs+ref) and where it was hit."""
    h, w = arrays["depth"].shape
    K = Intrinsics.from_K(arrays["K"], w, h)
    return renderer.render(arrays["T_world_cam"], K)


def mesh_image(renderer: Any, arrays: Arrays) -> npt.NDArray[np.uint8]:  # [H, W, 3]
    """The mesh (a ``MeshRenderer``) ray-cast at the sample's pose and intrinsics."""
    return mesh_render(renderer, arrays).rgb()


def disocclusions(
    arrays: Arrays, neighbours: Iterable[Arrays]
) -> list[npt.NDArray[np.bool_]]:  # [H, W] each
    """What each neighbour's depth, warped into this sample, does not cover; slivers and
    near-total masks are no plausible hole and are left out."""
    h, w = arrays["depth"].shape
    out = []
    for src in neighbours:
        m = disocclusion_mask(src["depth"], src["K"], src["T_world_cam"], arrays["K"],
                              arrays["T_world_cam"], h, w)  # fmt: skip
        if 0.01 < m.mean() < 0.6:  # a sliver or nearly everything is no plausible hole
            out.append(m)
    return out


def training_sample(
    arrays: Arrays,  # map_arrays' (a keyframe message's)
    mesh_color: npt.NDArray[np.uint8] | None,  # [H, W, 3] mesh_image; None = mode gs
    alpha_threshold: float,
    neighbours: Iterable[Arrays] = (),  # earlier samples' arrays, for disocclusions
) -> TrainingSample:
    """The sample's triplet and mask candidates (see module doc, step 2)."""
    h, w = arrays["depth"].shape
    t = triplet_from_keyframe(dict(arrays), mesh_color, alpha_threshold)
    for alpha in arrays.get("perturbed_alpha", ()):  # holes of views off the trajectory
        if alpha.shape != (h, w):
            raise ValueError(f"perturbed_alpha must be [P, {h}, {w}], got {list(alpha.shape)}")
        hole = informative_hole(alpha, alpha_threshold)
        if hole is not None:
            t.alpha_holes.append(hole)
    return TrainingSample(t, disocclusions(arrays, neighbours))


# ------------------------------------------------------------------------------------------
# Both at once
# ------------------------------------------------------------------------------------------


def keyframe_sample(
    mapper: Any,  # mapping.splat.mapper.Mapper
    frame: RGBDFrame,
    render: npt.NDArray[np.floating],  # [H, W, C] the map's colour at the keyframe
    alpha: npt.NDArray[np.floating],  # [H, W]
    mesh_renderer: Any | None,  # a MeshRenderer; None = mode gs
    rng: np.random.Generator,
    p: Perturbation,
    alpha_threshold: float,
    neighbours: Iterable[Arrays] = (),
) -> tuple[dict[str, npt.NDArray[Any]], TrainingSample]:
    """:func:`map_arrays` then :func:`training_sample`: (the arrays, the sample)."""
    arrays = map_arrays(mapper, frame, render, alpha, rng, p)
    mesh = None if mesh_renderer is None else mesh_image(mesh_renderer, arrays)
    return arrays, training_sample(arrays, mesh, alpha_threshold, neighbours)


def render_pair(
    mapper: Any,  # mapping.splat.mapper.Mapper
    mesh_renderer: Any,  # a MeshRenderer
    T_world_cam: npt.NDArray[np.float64],  # [4, 4]
    intrinsics: Intrinsics,
) -> RenderPair:
    """The mesh and the Gaussian map rendered at one pose."""
    m = mesh_renderer.render(T_world_cam, intrinsics)
    color, _, alpha = mapper.render_numpy(T_world_cam, intrinsics.K, intrinsics.width,
                                          intrinsics.height)  # fmt: skip
    mesh = rgb8(m.color) * m.valid[:, :, None]
    return RenderPair(mesh, m.valid, rgb8(color), np.ascontiguousarray(alpha, np.float32))
