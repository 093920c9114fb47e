"""A guessed surface for what the mesh never observed: its large planes, extended.

Ship tanks and machinery rooms are built of flat plates. Where a view looks past the mesh into
a part no frame saw, the plates the mesh did see, extended, are a better guess of the surface
there than depth inpainted from the view's own border, and every view gets the same guess. The
second matters to distillation: the Gaussians two repaired views grow for one unseen part sit
on one surface instead of two that disagree by tens of centimetres, where the later view's fit
recolours the earlier view's seeds.

- :func:`fit_planes` finds up to ``max_planes`` planes by RANSAC (Open3D ``segment_plane``, with
  a fixed seed, on the points in a fixed order) on the mesh's vertices thinned to a voxel grid,
  each holding at least ``min_support`` of them, and orients each towards the vertices' median
  point: the side the space is on. A draw that finds no such plane is tried again ``retries``
  times before the fit stops: the last walls hold few points, and 3 of them are drawn rarely.
- :func:`guessed_depth` casts each pixel's ray against the planes: the nearest hit of a ray
  that leaves a plane's inner side is the guess (the inside of the planes, taken as one convex
  space). A camera outside a plane's inner side ignores that plane. Pixels no plane bounds get 0.

Measured on the 32 novel views of four procedural inputs (the demo, tank seed 1, room seeds 1
and 2), in the pixels where the mesh has no surface, against their true depth: what the repair
graph seeds (these planes within ``repairer.GUESS_RANGE`` of inpainting) is off by a median of
0.4-0.6 % per input, where depth inpainted from the mesh (Navier-Stokes) is off by 6.5-16.9 %;
under 1 % in 28 views, closer than inpainting in 31 of 32. 500 RANSAC iterations, 8 planes and
no retry missed a wall on some seeds and meshes (up to 6.6 % per input; a demo run found 6 of its
8 planes, 4.9 %); 1000 iterations, 12 planes and 3 retries found the same planes (8 in a tank, 6
in a room) on each of 4 seeds of every mesh here (``benchmarks/results/guessed_planes_cpu.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from gsfix_online.core.config import rng
from gsfix_online.core.types import Intrinsics, check_pose
from gsfix_online.mapping.mesh import TriMesh
from gsfix_online.mapping.mesh_render import world_rays

__all__ = ["PlaneGuessConfig", "Planes", "fit_planes", "guessed_depth"]


@dataclass(frozen=True)
class PlaneGuessConfig:
    enabled: bool = True
    max_planes: int = field(default=12, metadata=rng(1, 64, "planes fitted at most"))
    min_support: float = field(
        default=0.04, metadata=rng(0, 1, "share of the thinned vertices a plane must hold")
    )
    distance_m: float = field(
        default=0.03, metadata=rng(0, None, "RANSAC inlier distance to a plane, m")
    )
    voxel_m: float = field(default=0.05, metadata=rng(0, None, "vertex thinning grid, m"))
    iterations: int = field(default=1000, metadata=rng(1, None, "RANSAC iterations per plane"))
    retries: int = field(
        default=3, metadata=rng(0, None, "RANSAC draws that find no plane before the fit stops")
    )
    seed: int = 0


@dataclass(frozen=True)
class Planes:
    """Planes n . x + d = 0 in the world frame, n of unit length, n . x + d > 0 on the inner side."""

    normals: npt.NDArray[np.float64]  # [P, 3]
    offsets: npt.NDArray[np.float64]  # [P]
    support: npt.NDArray[np.int64]  # [P] thinned vertices each plane holds

    def __len__(self) -> int:
        return int(self.offsets.shape[0])


NO_PLANES = Planes(np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))


def fit_planes(mesh: TriMesh, cfg: PlaneGuessConfig) -> Planes:
    """The mesh's large planes, oriented towards its vertices' median point; none for a mesh too
    small to hold a plane of ``min_support``."""
    if not cfg.enabled or mesh.n_vertices < 3:
        return NO_PLANES
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(np.asarray(mesh.vertices, np.float64))
    )
    if cfg.voxel_m > 0:
        cloud = cloud.voxel_down_sample(cfg.voxel_m)
    # the thinned points in a fixed order: the mesh's vertex order varies from run to run, and
    # with it what a seeded RANSAC draws
    # (rounded to a micrometre: the grid's means differ in their last bits with the order summed)
    points = np.round(np.asarray(cloud.points), 6)
    points = points[_row_order(points)]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    n_all = len(points)
    centre = np.median(points, axis=0)
    need = max(3, int(np.ceil(cfg.min_support * n_all)))
    o3d.utility.random.seed(cfg.seed)
    normals, offsets, support = [], [], []
    rest = cloud
    misses = 0
    while len(normals) < cfg.max_planes and len(rest.points) >= need:
        (a, b, c, d), inliers = rest.segment_plane(cfg.distance_m, 3, cfg.iterations)
        if len(inliers) < need:  # a plane of that size draws 3 of its points rarely: try again
            misses += 1
            if misses > cfg.retries:
                break
            continue
        n = np.array([a, b, c], np.float64)
        norm = float(np.linalg.norm(n))
        if not norm > 0:
            break
        n, d = n / norm, d / norm
        if n @ centre + d < 0:
            n, d = -n, -d
        normals.append(n)
        offsets.append(d)
        support.append(len(inliers))
        rest = rest.select_by_index(inliers, invert=True)
    if not normals:
        return NO_PLANES
    # in a fixed order, not the order found: two planes of equal support (a room's opposite
    # walls) are found in either order as the CPU's rounding breaks the tie between them
    n, d = np.stack(normals), np.array(offsets)
    order = _row_order(np.column_stack([n, d]))
    return Planes(n[order], d[order], np.array(support, np.int64)[order])


def _row_order(rows: npt.NDArray[np.float64]) -> npt.NDArray[np.intp]:
    """The rows' lexicographic order, on their values rounded to 1e-6 (last bits ignored)."""
    return np.lexsort(np.round(rows, 6).T[::-1])


def guessed_depth(
    planes: Planes,
    T_world_cam: npt.ArrayLike,  # [4, 4] camera-to-world, OpenCV axes
    intrinsics: Intrinsics,
    mesh_valid: npt.NDArray[np.bool_] | None = None,  # [H, W] the mesh render hit a surface
) -> npt.NDArray[np.float32]:  # [H, W] z-depth, m; 0 where no plane bounds the ray
    """Per pixel, the z-depth at which its ray leaves the planes' inner side first; with
    ``mesh_valid``, 0 where the mesh has a surface (the guess is for what it never saw)."""
    h, w = intrinsics.height, intrinsics.width
    best = np.full((h, w), np.inf)
    if len(planes):
        rays = world_rays(check_pose(T_world_cam), intrinsics).astype(np.float64)
        origin, direction = rays[0, 0, :3], rays[..., 3:]  # z component 1: t is the z-depth
        for n, d in zip(planes.normals, planes.offsets, strict=True):
            side = float(n @ origin + d)  # > 0: the camera is on the inner side
            if side <= 0:
                continue
            slope = direction @ n  # < 0: the ray heads out through the plane
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where(slope < 0, side / -slope, np.inf)
            best = np.minimum(best, t)
    guess = np.isfinite(best) if mesh_valid is None else np.isfinite(best) & ~mesh_valid
    return np.where(guess, best, 0.0).astype(np.float32)
