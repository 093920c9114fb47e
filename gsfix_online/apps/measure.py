"""Distances in the map: pick points with click rays, measure them, keep named labels in JSON.

A click in the viewer is a ray (origin and direction in the world frame, metres). Its pick point
is the first hit of the ray on the TSDF mesh (Open3D ``RaycastingScene``) or, for a map without
a mesh, the Gaussian map's expected depth along the ray (the splat renderer's depth at one pixel
whose optical axis is the ray). A pick says whether it lies on a synthesised surface (mostly
Gaussians grown from repaired views: :func:`synthesised_near`), which a measurement's reader
must know. Two picks make a measurement; a named measurement is a label.
Labels are saved as JSON next to the map (``labels.json``)::

    {"version": 1, "labels": [{"name": "frame 12 to 13", "a": [x, y, z], "b": [x, y, z],
                               "distance_m": 0.6, "synthesised": [false, true]}]}

``distance_m`` is written for people reading the file; on load it is recomputed from the points
and a stored value that disagrees by more than 1 mm is an error (the file was edited by hand).
``synthesised`` says which points lay on a synthesised surface when measured (absent in older
files: neither).
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from gsfix_online.core.io import atomic_write_text
from gsfix_online.mapping.mesh import TriMesh

logger = logging.getLogger(__name__)

LABELS_VERSION = 1
LABELS_FILE = "labels.json"
DISTANCE_CHECK_M = 1e-3  # a stored distance_m may differ from |b - a| by this much (rounding)
SPLAT_MIN_ALPHA = 0.5  # a ray through less accumulated opacity than this hits nothing
SPLAT_PICK_FOCAL_PX = 1000.0  # focal length of the one-pixel camera that picks on splats
# A pick lies on a synthesised surface when at least this share of the Gaussians at it (by
# opacity and distance) grew from repaired views; Gaussians count out to NEAR_SIGMAS sigmas
SYNTHESISED_MIN_SHARE = 0.5
NEAR_SIGMAS = 3.0

Vec3 = npt.NDArray[np.float64]  # [3]


class LabelsError(ValueError):
    """A labels file or a label does not follow the format in the module docstring."""


# ----------------------------------------------------------------------------------------------
# Rays
# ----------------------------------------------------------------------------------------------


def check_ray(origin: npt.ArrayLike, direction: npt.ArrayLike) -> tuple[Vec3, Vec3]:
    """(origin [3], unit direction [3]) as float64, or a one-line ValueError."""
    o = np.asarray(origin, dtype=np.float64)
    d = np.asarray(direction, dtype=np.float64)
    if o.shape != (3,) or d.shape != (3,):
        raise ValueError(
            f"ray origin and direction must be [3], got {list(o.shape)} and {list(d.shape)}"
        )
    if not (np.isfinite(o).all() and np.isfinite(d).all()):
        raise ValueError(f"ray must be finite, got origin {o.tolist()} direction {d.tolist()}")
    n = float(np.linalg.norm(d))
    if n < 1e-9:
        raise ValueError(f"ray direction must be non-zero, got {d.tolist()}")
    return o, d / n


def pixel_ray(
    T_world_cam: npt.ArrayLike,  # [4, 4] camera-to-world, OpenCV axes
    K: npt.ArrayLike,  # [3, 3] pixels
    u: float,  # pixel column (pixel centres at integers)
    v: float,  # pixel row
) -> tuple[Vec3, Vec3]:
    """The world ray through pixel (u, v): (camera centre [3], unit direction [3])."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    d_cam = np.linalg.solve(np.asarray(K, dtype=np.float64), np.array([u, v, 1.0]))
    return check_ray(T[:3, 3], T[:3, :3] @ d_cam)


def ray_camera(origin: Vec3, direction: Vec3) -> npt.NDArray[np.float64]:  # [4, 4]
    """A camera-to-world pose at ``origin`` whose optical axis (z) is the unit ``direction``."""
    z = direction
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = origin
    return T


# ----------------------------------------------------------------------------------------------
# Picking
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Pick:
    point: Vec3  # [3] world, metres
    range_m: float  # distance from the ray origin
    source: Literal["mesh", "splats"]
    # share of the Gaussians at the point that grew from repaired views (synthesised_near);
    # None where no Gaussian is near it
    synthesised: float | None = None

    @property
    def on_synthesised(self) -> bool:
        """The point lies on a synthesised surface (mostly Gaussians no input frame saw)."""
        return self.synthesised is not None and self.synthesised >= SYNTHESISED_MIN_SHARE


def mesh_hit(scene: Any, origin: Vec3, direction: Vec3) -> float | None:
    """Distance along the unit ray to its first hit on an Open3D ``RaycastingScene``, or None."""
    import open3d.core as o3c

    ray = np.concatenate([origin, direction]).astype(np.float32)[None]  # [1, 6]
    t = float(scene.cast_rays(o3c.Tensor(ray))["t_hit"].numpy()[0])
    return t if math.isfinite(t) else None


def render_splats(
    gmap: Any,  # GaussianMap
    T_world_cam: npt.ArrayLike,  # [4, 4] camera-to-world, OpenCV axes
    K: npt.ArrayLike,  # [3, 3] pixels
    width: int,
    height: int,
) -> tuple[npt.NDArray[np.uint8], npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """(colour uint8 [H, W, 3], z-depth [H, W] m, alpha [H, W]) of the Gaussian map at a pose,
    with the project's renderer (gsplat on CUDA, the CPU rasterizer otherwise)."""
    import torch

    from gsfix_online.mapping.splat.render import render

    g = gmap
    T = torch.tensor(np.asarray(T_world_cam, np.float32), device=g.device)
    Kt = torch.tensor(np.asarray(K, np.float32), device=g.device)
    with torch.no_grad():
        out = render(
            g.means, g.params["quats"], g.scales, g.opacities, g.sh, None, Kt, width, height,
            T_world_cam=T, sh_degree=g.sh_degree,
        )  # fmt: skip
        rgb = out.color.clamp(0, 1).mul(255).round().to(torch.uint8).cpu().numpy()
    if rgb.shape[2] == 1:
        rgb = np.repeat(rgb, 3, axis=2)
    return rgb, out.depth.cpu().numpy(), out.alpha.cpu().numpy()


def splat_hit(gmap: Any, origin: Vec3, direction: Vec3) -> float | None:
    """Expected depth of the Gaussian map along the unit ray, or None where the ray's
    accumulated opacity is below SPLAT_MIN_ALPHA (it passes through empty space)."""
    if len(gmap) == 0:
        return None
    K = np.array([[SPLAT_PICK_FOCAL_PX, 0, 0], [0, SPLAT_PICK_FOCAL_PX, 0], [0, 0, 1.0]])
    _, depth_m, alpha = render_splats(gmap, ray_camera(origin, direction), K, 1, 1)
    if float(alpha[0, 0]) < SPLAT_MIN_ALPHA:
        return None
    return float(depth_m[0, 0])  # z-depth along the optical axis = range along the ray


def synthesised_near(gmap: Any, point: npt.ArrayLike) -> float | None:
    """The share of the Gaussians at a world point that grew from repaired views: each Gaussian
    within NEAR_SIGMAS of its largest sigma weighs opacity x exp(-d^2 / 2 sigma^2); None when
    none is that near (the point is on the mesh alone, or in empty space)."""
    import torch

    if gmap is None or len(gmap) == 0:
        return None
    with torch.no_grad():
        p = torch.as_tensor(np.asarray(point, np.float32), device=gmap.device)
        sigma = gmap.scales.max(dim=1).values  # [N] m
        d = (gmap.means - p).norm(dim=1)  # [N] m
        near = d <= NEAR_SIGMAS * sigma
        if not bool(near.any()):
            return None
        w = gmap.opacities[near] * torch.exp(-0.5 * (d[near] / sigma[near]) ** 2)
        total = float(w.sum())
        if total <= 0.0:
            return None
        return float(w[gmap.repaired()[near]].sum()) / total


class Picker:
    """Turns click rays into points on the mesh (first hit) or, without a mesh, on the splats."""

    def __init__(self, mesh: TriMesh | None = None, gmap: Any | None = None) -> None:
        self.gmap = gmap  # GaussianMap or None
        self._scene = None
        if mesh is not None and not mesh.is_empty:
            import open3d as o3d
            import open3d.core as o3c

            self._scene = o3d.t.geometry.RaycastingScene()
            self._scene.add_triangles(
                o3c.Tensor(np.ascontiguousarray(mesh.vertices, np.float32)),
                o3c.Tensor(np.ascontiguousarray(mesh.triangles, np.uint32)),
            )

    @property
    def has_mesh(self) -> bool:
        return self._scene is not None

    def pick(self, origin: npt.ArrayLike, direction: npt.ArrayLike) -> Pick | None:
        o, d = check_ray(origin, direction)
        if self._scene is not None:
            t = mesh_hit(self._scene, o, d)
            source: Literal["mesh", "splats"] = "mesh"
        elif self.gmap is not None:
            t = splat_hit(self.gmap, o, d)
            source = "splats"
        else:
            return None
        if t is None:
            return None
        return Pick(o + t * d, t, source, synthesised_near(self.gmap, o + t * d))


def distance_m(a: npt.ArrayLike, b: npt.ArrayLike) -> float:
    """Euclidean distance between two world points, metres."""
    return float(np.linalg.norm(np.asarray(b, np.float64) - np.asarray(a, np.float64)))


# ----------------------------------------------------------------------------------------------
# Labels
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Label:
    """A named two-point measurement in the world frame."""

    name: str
    a: tuple[float, float, float]  # metres
    b: tuple[float, float, float]
    # whether a and b lay on a synthesised surface (Pick.on_synthesised) when measured
    synthesised: tuple[bool, bool] = (False, False)

    @property
    def distance_m(self) -> float:
        return distance_m(self.a, self.b)

    @classmethod
    def make(
        cls, name: str, a: npt.ArrayLike, b: npt.ArrayLike,
        synthesised: Sequence[bool] = (False, False),
    ) -> Label:  # fmt: skip
        """Validate a label given by the user: a non-empty one-line name, two finite points and
        whether each lay on a synthesised surface."""
        if not isinstance(name, str) or not name.strip() or "\n" in name:
            raise LabelsError(f"label name must be non-empty text on one line, got {name!r}")
        pts = []
        for key, p in (("a", a), ("b", b)):
            try:
                arr = np.asarray(p, dtype=np.float64)
            except (TypeError, ValueError):
                arr = np.zeros(0)
            if arr.shape != (3,) or not np.isfinite(arr).all():
                raise LabelsError(f"label {name!r}: {key} must be 3 finite numbers, got {p!r}")
            pts.append((float(arr[0]), float(arr[1]), float(arr[2])))
        flags = list(synthesised) if isinstance(synthesised, list | tuple) else None
        if flags is None or len(flags) != 2 or not all(isinstance(f, bool) for f in flags):
            raise LabelsError(
                f"label {name!r}: synthesised must be two true/false values, got {synthesised!r}"
            )
        return cls(name.strip(), pts[0], pts[1], (flags[0], flags[1]))

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "a": list(self.a),
            "b": list(self.b),
            "distance_m": round(self.distance_m, 6),
            "synthesised": list(self.synthesised),
        }


def labels_to_json(labels: Sequence[Label]) -> str:
    return json.dumps(
        {"version": LABELS_VERSION, "labels": [x.to_json() for x in labels]}, indent=2
    )


def labels_from_json(text: str, where: str = LABELS_FILE) -> list[Label]:
    """Parse a labels file; every problem is a one-line LabelsError naming ``where``."""
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise LabelsError(f"{where}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("labels"), list):
        raise LabelsError(f'{where}: expected {{"version": 1, "labels": [...]}}')
    if doc.get("version") != LABELS_VERSION:
        raise LabelsError(f"{where}: version must be {LABELS_VERSION}, got {doc.get('version')!r}")
    out = []
    for i, item in enumerate(doc["labels"]):
        if not isinstance(item, dict) or not {"name", "a", "b"} <= item.keys():
            raise LabelsError(f"{where}: label {i} must have name, a and b")
        try:
            label = Label.make(item["name"], item["a"], item["b"],
                               item.get("synthesised", [False, False]))  # fmt: skip
        except LabelsError as exc:
            raise LabelsError(f"{where}: label {i}: {exc}") from None
        stored = item.get("distance_m")
        if stored is not None and (
            not isinstance(stored, int | float)
            or abs(float(stored) - label.distance_m) > DISTANCE_CHECK_M
        ):
            raise LabelsError(
                f"{where}: label {i} ({label.name!r}): distance_m {stored!r} disagrees with its "
                f"points ({label.distance_m:.4f} m)"
            )
        out.append(label)
    return out


def save_labels(path: str | os.PathLike[str], labels: Sequence[Label]) -> Path:
    """Write the labels atomically (a reader sees the old file or the whole new one)."""
    p = Path(path)
    atomic_write_text(p, labels_to_json(labels) + "\n")
    logger.info("saved %d labels to %s", len(labels), p)
    return p


def load_labels(path: str | os.PathLike[str]) -> list[Label]:
    """The labels in ``path``; a missing file is an error (the caller decides what that means)."""
    p = Path(path)
    if not p.is_file():
        raise LabelsError(f"{p}: no labels file")
    return labels_from_json(p.read_text(), str(p))
