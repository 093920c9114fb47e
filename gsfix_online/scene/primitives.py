"""Mesh primitives shared by the tank and the room: boxes, grids, tubes, prisms and rings as
parts (vertices, triangles), and :class:`TankMesh`, the triangle soup with one material per
triangle that parts are assembled into. Triangles are wound so that their normal points into
free space; every part has its own vertices (no welding across parts)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    import open3d as o3d

F64 = npt.NDArray[np.float64]
Part = tuple[F64, npt.NDArray[np.int64]]  # vertices [V, 3], triangles [T, 3]


@dataclass
class TankMesh:
    """Triangle soup of the scene; any mesh (a test plane) works with the renderer."""

    vertices: F64  # [V, 3] world, metres
    triangles: npt.NDArray[np.int32]  # [T, 3]
    vertex_normals: npt.NDArray[np.float32]  # [V, 3] unit, into free space
    material: npt.NDArray[np.uint8]  # [T] Material
    layout: Any = None  # the TankLayout or RoomLayout it was built from, if any

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    @classmethod
    def from_parts(cls, parts: Sequence[tuple[Part, int]], layout: Any = None) -> TankMesh:
        verts, tris, norms, mats = [], [], [], []
        offset = 0
        for (V, T), mat in parts:
            verts.append(V)
            tris.append(T + offset)
            norms.append(vertex_normals(V, T))
            mats.append(np.full(len(T), int(mat), np.uint8))
            offset += len(V)
        return cls(
            vertices=np.concatenate(verts),
            triangles=np.concatenate(tris).astype(np.int32),
            vertex_normals=np.concatenate(norms).astype(np.float32),
            material=np.concatenate(mats),
            layout=layout,
        )

    def to_open3d(
        self, vertex_colors: npt.NDArray[np.floating] | None = None
    ) -> o3d.geometry.TriangleMesh:
        """Legacy Open3D mesh; ``vertex_colors`` [V, 3] in 0..1."""
        import open3d as o3d

        m = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.vertices), o3d.utility.Vector3iVector(self.triangles)
        )
        m.vertex_normals = o3d.utility.Vector3dVector(self.vertex_normals.astype(np.float64))
        if vertex_colors is not None:
            m.vertex_colors = o3d.utility.Vector3dVector(np.asarray(vertex_colors, np.float64))
        return m


def vertex_normals(V: F64, T: npt.NDArray[np.int64]) -> F64:
    """Area-weighted vertex normals of one part."""
    n = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])  # [T, 3], length = 2 * area
    out = np.zeros_like(V)
    for k in range(3):
        for c in range(3):
            out[:, c] += np.bincount(T[:, k], weights=n[:, c], minlength=len(V))
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)


def orient(part: Part, ref: npt.ArrayLike) -> Part:
    """Flip triangles whose normal disagrees with ``ref`` ([3] or [T, 3] directions into free space)."""
    V, T = part
    n = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
    flip = np.einsum("ij,ij->i", n, np.broadcast_to(np.asarray(ref, np.float64), n.shape)) < 0
    T = T.copy()
    T[flip] = T[flip][:, [0, 2, 1]]
    return V, T


def convex(part: Part) -> Part:
    """Orient a convex solid (box, prism) away from its centre."""
    V, T = part
    return orient(part, V[T].mean(axis=1) - V.mean(axis=0))


def n_segments(length: float, max_edge: float) -> int:
    return max(1, math.ceil(length / max_edge - 1e-9))


def grid(origin: npt.ArrayLike, u: npt.ArrayLike, v: npt.ArrayLike, max_edge: float) -> Part:
    """Parallelogram origin + s u + t v (s, t in [0, 1]) as a quad grid; normal along u x v."""
    o, u, v = (np.asarray(a, np.float64) for a in (origin, u, v))
    nu, nv = (
        n_segments(float(np.linalg.norm(u)), max_edge),
        n_segments(float(np.linalg.norm(v)), max_edge),
    )
    s, t = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    V = o + s.reshape(-1, 1) * u + t.reshape(-1, 1) * v  # [(nu+1)(nv+1), 3]
    idx = np.arange(V.shape[0]).reshape(nu + 1, nv + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    T = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    )
    return V, T


def merge_parts(parts: Sequence[Part]) -> Part:
    offset, Vs, Ts = 0, [], []
    for V, T in parts:
        Vs.append(V)
        Ts.append(T + offset)
        offset += len(V)
    return np.concatenate(Vs), np.concatenate(Ts)


def box(lo: npt.ArrayLike, hi: npt.ArrayLike, max_edge: float) -> Part:
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    d = hi - lo
    faces = []
    for ax in range(3):
        a1, a2 = (ax + 1) % 3, (ax + 2) % 3
        u, v = np.zeros(3), np.zeros(3)
        u[a1], v[a2] = d[a1], d[a2]
        for side in (lo, hi):
            o = lo.copy()
            o[ax] = side[ax]
            faces.append(grid(o, u, v, max_edge))
    return convex(merge_parts(faces))


def tube(
    c0: npt.ArrayLike,  # [3] start of the axis
    axis: npt.ArrayLike,  # [3] axis vector, its length is the tube length
    e1: npt.ArrayLike,  # [3] unit, first semi-axis direction
    e2: npt.ArrayLike,  # [3] unit, second semi-axis direction
    a: float,
    b: float,
    around: int | F64,
    max_edge: float,
    caps: bool = False,
) -> Part:
    """Elliptic cylinder c0 + s axis + a cos(t) e1 + b sin(t) e2, s in [0, 1]; optional end discs.

    ``around`` is the number of segments or the angles t themselves (to match a hole's loop).
    """
    c0, axis, e1, e2 = (np.asarray(x, np.float64) for x in (c0, axis, e1, e2))
    ns = n_segments(float(np.linalg.norm(axis)), max_edge)
    if np.isscalar(around):
        th = np.linspace(0, 2 * np.pi, around, endpoint=False)
    else:
        th = np.asarray(around, np.float64)
    n_around = len(th)
    s = np.linspace(0, 1, ns + 1)
    ring = a * np.cos(th)[:, None] * e1 + b * np.sin(th)[:, None] * e2  # [n, 3]
    V = (c0 + s[:, None, None] * axis + ring[None]).reshape(-1, 3)  # [(ns+1) n, 3]
    idx = np.arange(len(V)).reshape(ns + 1, n_around)
    nxt = np.roll(idx, -1, axis=1)
    a_, b_, c_, d_ = idx[:-1], nxt[:-1], nxt[1:], idx[1:]
    T = np.concatenate(
        [np.stack([a_, b_, c_], -1).reshape(-1, 3), np.stack([a_, c_, d_], -1).reshape(-1, 3)]
    )
    # Sides face away from the axis.
    cent = V[T].mean(axis=1)
    rel = cent - c0
    radial = rel - np.outer(rel @ axis / (axis @ axis), axis)
    part = orient((V, T), radial)
    if not caps:
        return part
    discs = []
    for end, sign in ((0.0, -1.0), (1.0, 1.0)):
        centre = c0 + end * axis
        Vd = np.concatenate([centre[None], centre + ring])
        i = np.arange(n_around)
        Td = np.stack([np.zeros(n_around, np.int64), 1 + i, 1 + (i + 1) % n_around], -1)
        discs.append(orient((Vd, Td), sign * axis))
    return merge_parts([part, *discs])


def prism(p0: npt.ArrayLike, p1: npt.ArrayLike, p2: npt.ArrayLike, thickness: float) -> Part:
    """Triangular plate (a bracket) centred on the triangle's plane."""
    P = np.asarray([p0, p1, p2], np.float64)
    n = np.cross(P[1] - P[0], P[2] - P[0])
    n *= thickness / 2.0 / np.linalg.norm(n)
    V = np.concatenate([P - n, P + n])  # bottom 0..2, top 3..5
    T = np.array(
        [[0, 1, 2], [3, 4, 5], [0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [2, 0, 3], [2, 3, 5]]
    )
    return convex((V, T))


def ring_2d(
    rect: tuple[float, float, float, float],  # u0, u1, v0, v1
    centre: tuple[float, float],
    axes: tuple[float, float],  # semi-axes along u, v
    n_around: int,
    max_edge: float,
) -> tuple[F64, npt.NDArray[np.int64], F64]:
    """Rectangle (u0, u1, v0, v1) with an elliptic hole, triangulated as a ring of spokes.

    Each spoke runs from the ellipse point at parameter t to where the ray from the centre through
    it leaves the rectangle; the rectangle corners are spokes too, so the ring covers the corners
    exactly. Returns points [P, 2], triangles [T, 3] and the loop's ellipse parameters t [n].
    """
    u0, u1, v0, v1 = rect
    cu, cv = centre
    a, b = axes
    corners = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]])
    t_corner = np.arctan2((corners[:, 1] - cv) / b, (corners[:, 0] - cu) / a) % (2 * np.pi)
    t = np.unique(
        np.round(np.concatenate([np.linspace(0, 2 * np.pi, n_around, endpoint=False), t_corner]), 9)
    )
    d = np.stack([a * np.cos(t), b * np.sin(t)], -1)  # [n, 2] centre -> ellipse
    with np.errstate(divide="ignore"):
        su = np.where(
            d[:, 0] > 0, (u1 - cu) / d[:, 0], np.where(d[:, 0] < 0, (u0 - cu) / d[:, 0], np.inf)
        )
        sv = np.where(
            d[:, 1] > 0, (v1 - cv) / d[:, 1], np.where(d[:, 1] < 0, (v0 - cv) / d[:, 1], np.inf)
        )
    s_out = np.minimum(su, sv)  # [n] >= 1 when the ellipse lies inside the rectangle
    k = n_segments(
        float(((s_out - 1) * np.linalg.norm(d, axis=1)).max()), max_edge
    )  # longest spoke
    g = np.linspace(0.0, 1.0, k + 1)[None, :, None]  # position along each spoke
    s = 1.0 + (s_out[:, None, None] - 1.0) * g  # [n, k+1, 1]: 1 on the ellipse, s_out on the border
    P = (np.array([cu, cv]) + s * d[:, None, :]).reshape(-1, 2)
    n = len(t)
    idx = np.arange(n * (k + 1)).reshape(n, k + 1)
    nxt = np.roll(idx, -1, axis=0)
    a_, b_, c_, d_ = idx[:, :-1], idx[:, 1:], nxt[:, 1:], nxt[:, :-1]
    T = np.concatenate(
        [np.stack([a_, b_, c_], -1).reshape(-1, 3), np.stack([a_, c_, d_], -1).reshape(-1, 3)]
    )
    return P, T, t


def plane_part(
    P2: F64, T: npt.NDArray[np.int64], origin: F64, U: F64, Vv: F64, normal: npt.ArrayLike
) -> Part:
    V = origin + P2[:, :1] * U + P2[:, 1:] * Vv
    return orient((V, T), normal)


# --------------------------------------------------------------------------------------------
# Tank parts
# --------------------------------------------------------------------------------------------
