"""The tank compartment as a triangle mesh with one material id per triangle.

World frame: x along the tank (0..length), y across (0..width), z up (0..height), metres.
Parts: shell plating seen from inside (deck with a manhole and its coaming), transverse web frames
with an oval lightening hole (a ring between the rectangle and the ellipse, both faces and the hole
rim), L-profile longitudinals on the sides, floor and deck, flat-bar web stiffeners, triangular
brackets at web/shell corners, a vertical ladder below the manhole, and two pipes with flanges.

Every part has its own vertices (no welding across parts), so vertex normals are flat on plates and
smooth around pipes. Triangles are wound so that their normal points into free space.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from gsfix_online.scene.config import ShipTankConfig

if TYPE_CHECKING:
    import open3d as o3d

    from gsfix_online.scene.room import RoomLayout

F64 = npt.NDArray[np.float64]
Part = tuple[F64, npt.NDArray[np.int64]]  # vertices [V, 3], triangles [T, 3]


class Material(IntEnum):
    SHELL = 0
    WEB = 1
    STIFFENER = 2
    BRACKET = 3
    LADDER = 4
    PIPE = 5
    PIPE_RED = 6
    FLANGE = 7
    COAMING = 8


@dataclass(frozen=True)
class Pipe:
    y: float
    z: float
    radius: float
    material: Material


@dataclass(frozen=True)
class TankLayout:
    """Where everything is; derived from the config, shared by mesh, appearance and trajectory."""

    length: float
    width: float
    height: float
    web_x: tuple[float, ...]  # web mid-planes
    web_thickness: float
    hole_yz: tuple[tuple[float, float], ...]  # lightening-hole centre (y, z) per web
    hole_axes: tuple[float, float]  # semi-axes (y, z)
    manhole_xy: tuple[float, float]  # deck manhole centre
    manhole_axes: tuple[float, float]  # semi-axes (x, y)
    coaming_height: float
    ladder_xy: tuple[float, float]  # ladder centre line
    side_long_z: tuple[float, ...]  # longitudinals on both side walls
    floor_long_y: tuple[float, ...]  # longitudinals on floor and deck
    pipes: tuple[Pipe, ...]
    lamps: tuple[tuple[float, float, float], ...]  # one point lamp per bay

    @property
    def n_bays(self) -> int:
        return len(self.web_x) + 1

    def bay(self, i: int) -> tuple[float, float]:
        """x range of bay ``i`` between the web plate faces."""
        edges = (0.0, *self.web_x, self.length)
        h = self.web_thickness / 2.0
        x0 = edges[i] + (h if i > 0 else 0.0)
        x1 = edges[i + 1] - (h if i + 1 < len(edges) - 1 else 0.0)
        return x0, x1


def tank_layout(cfg: ShipTankConfig) -> TankLayout:
    L, W, H = cfg.tank_length, cfg.tank_width, cfg.tank_height
    n = cfg.n_web_frames
    web_x = tuple(L * (k + 1) / (n + 1) for k in range(n))
    a, b = cfg.web_hole_width / 2.0, cfg.web_hole_height / 2.0
    # Holes alternate a little across the tank so that bays do not look identical.
    shift = min(0.25, W / 2.0 - a - 0.45)
    hole_yz = tuple((W / 2.0 + shift * (1 if k % 2 else -1), H * 0.5) for k in range(n))
    bay0 = (web_x[0] if web_x else L) / 2.0
    manhole = (bay0, W - 0.55)
    side_z = tuple(H * (k + 1) / (round(H / 0.65)) for k in range(max(1, round(H / 0.65) - 1)))
    n_floor = max(1, round(W / 0.64) - 1)
    floor_y = tuple(W * (k + 1) / (n_floor + 1) for k in range(n_floor))
    pipes = (Pipe(0.45, 0.35, 0.10, Material.PIPE), Pipe(0.35, H - 0.42, 0.05, Material.PIPE_RED))
    lamps = []
    for i in range(n + 1):
        x0 = 0.0 if i == 0 else web_x[i - 1]
        x1 = L if i == n else web_x[i]
        lamps.append(((x0 + x1) / 2.0, W * (0.62 if i % 2 else 0.4), H * 0.7))
    return TankLayout(
        length=L,
        width=W,
        height=H,
        web_x=web_x,
        web_thickness=0.014,
        hole_yz=hole_yz,
        hole_axes=(a, b),
        manhole_xy=manhole,
        manhole_axes=(0.3, 0.2),
        coaming_height=0.3,
        ladder_xy=(manhole[0], W - 0.2),
        side_long_z=side_z,
        floor_long_y=floor_y,
        pipes=pipes,
        lamps=tuple(lamps),
    )


# --------------------------------------------------------------------------------------------
# The mesh
# --------------------------------------------------------------------------------------------


@dataclass
class TankMesh:
    """Triangle soup of the scene; any mesh (a test plane) works with the renderer."""

    vertices: F64  # [V, 3] world, metres
    triangles: npt.NDArray[np.int32]  # [T, 3]
    vertex_normals: npt.NDArray[np.float32]  # [V, 3] unit, into free space
    material: npt.NDArray[np.uint8]  # [T] Material
    layout: TankLayout | RoomLayout | None = None

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    @classmethod
    def from_parts(
        cls, parts: Sequence[tuple[Part, int]], layout: TankLayout | RoomLayout | None = None
    ) -> TankMesh:
        verts, tris, norms, mats = [], [], [], []
        offset = 0
        for (V, T), mat in parts:
            verts.append(V)
            tris.append(T + offset)
            norms.append(_vertex_normals(V, T))
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


def _vertex_normals(V: F64, T: npt.NDArray[np.int64]) -> F64:
    """Area-weighted vertex normals of one part."""
    n = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])  # [T, 3], length = 2 * area
    out = np.zeros_like(V)
    for k in range(3):
        for c in range(3):
            out[:, c] += np.bincount(T[:, k], weights=n[:, c], minlength=len(V))
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)


def _orient(part: Part, ref: npt.ArrayLike) -> Part:
    """Flip triangles whose normal disagrees with ``ref`` ([3] or [T, 3] directions into free space)."""
    V, T = part
    n = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
    flip = np.einsum("ij,ij->i", n, np.broadcast_to(np.asarray(ref, np.float64), n.shape)) < 0
    T = T.copy()
    T[flip] = T[flip][:, [0, 2, 1]]
    return V, T


def _convex(part: Part) -> Part:
    """Orient a convex solid (box, prism) away from its centre."""
    V, T = part
    return _orient(part, V[T].mean(axis=1) - V.mean(axis=0))


def _nseg(length: float, max_edge: float) -> int:
    return max(1, math.ceil(length / max_edge - 1e-9))


def _grid(origin: npt.ArrayLike, u: npt.ArrayLike, v: npt.ArrayLike, max_edge: float) -> Part:
    """Parallelogram origin + s u + t v (s, t in [0, 1]) as a quad grid; normal along u x v."""
    o, u, v = (np.asarray(a, np.float64) for a in (origin, u, v))
    nu, nv = _nseg(float(np.linalg.norm(u)), max_edge), _nseg(float(np.linalg.norm(v)), max_edge)
    s, t = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    V = o + s.reshape(-1, 1) * u + t.reshape(-1, 1) * v  # [(nu+1)(nv+1), 3]
    idx = np.arange(V.shape[0]).reshape(nu + 1, nv + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    T = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    )
    return V, T


def _merge(parts: Sequence[Part]) -> Part:
    offset, Vs, Ts = 0, [], []
    for V, T in parts:
        Vs.append(V)
        Ts.append(T + offset)
        offset += len(V)
    return np.concatenate(Vs), np.concatenate(Ts)


def _box(lo: npt.ArrayLike, hi: npt.ArrayLike, max_edge: float) -> Part:
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
            faces.append(_grid(o, u, v, max_edge))
    return _convex(_merge(faces))


def _tube(
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
    ns = _nseg(float(np.linalg.norm(axis)), max_edge)
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
    part = _orient((V, T), radial)
    if not caps:
        return part
    discs = []
    for end, sign in ((0.0, -1.0), (1.0, 1.0)):
        centre = c0 + end * axis
        Vd = np.concatenate([centre[None], centre + ring])
        i = np.arange(n_around)
        Td = np.stack([np.zeros(n_around, np.int64), 1 + i, 1 + (i + 1) % n_around], -1)
        discs.append(_orient((Vd, Td), sign * axis))
    return _merge([part, *discs])


def _prism(p0: npt.ArrayLike, p1: npt.ArrayLike, p2: npt.ArrayLike, thickness: float) -> Part:
    """Triangular plate (a bracket) centred on the triangle's plane."""
    P = np.asarray([p0, p1, p2], np.float64)
    n = np.cross(P[1] - P[0], P[2] - P[0])
    n *= thickness / 2.0 / np.linalg.norm(n)
    V = np.concatenate([P - n, P + n])  # bottom 0..2, top 3..5
    T = np.array(
        [[0, 1, 2], [3, 4, 5], [0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [2, 0, 3], [2, 3, 5]]
    )
    return _convex((V, T))


def _ring_2d(
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
    k = _nseg(float(((s_out - 1) * np.linalg.norm(d, axis=1)).max()), max_edge)  # longest spoke
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


def _plane_part(
    P2: F64, T: npt.NDArray[np.int64], origin: F64, U: F64, Vv: F64, normal: npt.ArrayLike
) -> Part:
    V = origin + P2[:, :1] * U + P2[:, 1:] * Vv
    return _orient((V, T), normal)


# --------------------------------------------------------------------------------------------
# Tank parts
# --------------------------------------------------------------------------------------------


def _shell(lay: TankLayout, e: float) -> list[tuple[Part, int]]:
    L, W, H = lay.length, lay.width, lay.height
    X, Y, Z = np.eye(3)
    parts = [
        _orient(_grid([0, 0, 0], [L, 0, 0], [0, W, 0], e), Z),  # floor
        _orient(_grid([0, 0, 0], [L, 0, 0], [0, 0, H], e), Y),  # side y = 0
        _orient(_grid([0, W, 0], [L, 0, 0], [0, 0, H], e), -Y),  # side y = W
        _orient(_grid([0, 0, 0], [0, W, 0], [0, 0, H], e), X),  # end x = 0
        _orient(_grid([L, 0, 0], [0, W, 0], [0, 0, H], e), -X),  # end x = L
    ]
    # Deck: a panel with the manhole (ring triangulation) and plain strips around it.
    (mx, my), (ma, mb) = lay.manhole_xy, lay.manhole_axes
    px0, px1 = max(0.0, mx - 2 * ma), min(L, mx + 2 * ma)
    py0, py1 = max(0.0, my - 2 * mb - 0.1), W
    P2, T2, t_loop = _ring_2d((px0, px1, py0, py1), (mx, my), (ma, mb), 64, e)
    parts.append(_plane_part(P2, T2, np.array([0, 0, H]), X, Y, -Z))
    for x0, x1, y0, y1 in ((0, px0, 0, W), (px1, L, 0, W), (px0, px1, 0, py0)):
        if x1 - x0 > 1e-6 and y1 - y0 > 1e-6:
            parts.append(_orient(_grid([x0, y0, H], [x1 - x0, 0, 0], [0, y1 - y0, 0], e), -Z))
    out: list[tuple[Part, int]] = [(p, Material.SHELL) for p in parts]
    # Coaming (seen from inside the tube) and the closed cover on top of it.
    ch = lay.coaming_height
    coaming = _tube([mx, my, H], [0, 0, ch], X, Y, ma, mb, t_loop, e)
    out.append(((coaming[0], coaming[1][:, [0, 2, 1]]), Material.COAMING))
    nl = len(t_loop)
    Vd = np.concatenate(
        [
            [[mx, my, H + ch]],
            np.stack([mx + ma * np.cos(t_loop), my + mb * np.sin(t_loop), np.full(nl, H + ch)], -1),
        ]
    )
    i = np.arange(nl)
    Td = np.stack([np.zeros(nl, np.int64), 1 + i, 1 + (i + 1) % nl], -1)
    out.append((_orient((Vd, Td), -Z), Material.COAMING))
    return out


def _webs(lay: TankLayout, e: float) -> list[tuple[Part, int]]:
    W, H = lay.width, lay.height
    X, Y, Z = np.eye(3)
    t = lay.web_thickness
    a, b = lay.hole_axes
    out: list[tuple[Part, int]] = []
    for xk, (hy, hz) in zip(lay.web_x, lay.hole_yz, strict=True):
        ring, tri, t_loop = _ring_2d((0.0, W, 0.0, H), (hy, hz), (a, b), _nseg(2 * (W + H), e), e)
        for side in (-1.0, 1.0):
            face = _plane_part(ring, tri, np.array([xk + side * t / 2, 0, 0]), Y, Z, side * X)
            out.append((face, Material.WEB))
        rim = _tube([xk - t / 2, hy, hz], [t, 0, 0], Y, Z, a, b, t_loop, e)
        out.append(((rim[0], rim[1][:, [0, 2, 1]]), Material.WEB))  # faces the hole axis
        # Vertical flat-bar stiffeners on the +x face, either side of the hole.
        for ys in (hy - a - 0.35, hy + a + 0.35):
            if 0.2 < ys < W - 0.2:
                bar = _box([xk + t / 2, ys - 0.006, 0], [xk + t / 2 + 0.1, ys + 0.006, H], 2 * e)
                out.append((bar, Material.STIFFENER))
    return out


def _longitudinals(lay: TankLayout, e: float) -> list[tuple[Part, int]]:
    """L-profiles: a 150 x 10 web on the plating and an 80 x 12 flange at its toe."""
    L, W, H = lay.length, lay.width, lay.height
    hw, tw, bf, tf = 0.15, 0.010, 0.08, 0.012
    boxes = []
    for z in lay.side_long_z:
        for wall, s in ((0.0, 1.0), (W, -1.0)):
            y_toe = wall + s * hw
            y_f = y_toe + s * tf
            boxes.append(([0, min(wall, y_toe), z - tw / 2], [L, max(wall, y_toe), z + tw / 2]))
            boxes.append(([0, min(y_toe, y_f), z - bf], [L, max(y_toe, y_f), z + tw / 2]))
    (mx, my), (ma, mb) = lay.manhole_xy, lay.manhole_axes
    for y in lay.floor_long_y:
        for base, s in ((0.0, 1.0), (H, -1.0)):
            spans = [(0.0, L)]
            if base == H and abs(y - my) < mb + 0.1:  # deck longitudinal cut around the manhole
                spans = [(0.0, mx - ma - 0.06), (mx + ma + 0.06, L)]
            z_toe = base + s * hw
            z_f = z_toe + s * tf
            for x0, x1 in spans:
                if x1 - x0 < 0.05:
                    continue
                y0 = y - tw / 2
                boxes.append(([x0, y0, min(base, z_toe)], [x1, y0 + tw, max(base, z_toe)]))
                boxes.append(([x0, y0, min(z_toe, z_f)], [x1, y0 + bf, max(z_toe, z_f)]))
    return [(_box(lo, hi, 2 * e), Material.STIFFENER) for lo, hi in boxes]


def _brackets(lay: TankLayout) -> list[tuple[Part, int]]:
    """Tripping brackets from each web face to the floor and deck (every other gap between
    longitudinals) and to the side shell (lowest and highest gap)."""
    W, H = lay.width, lay.height
    t, leg = 0.012, 0.26
    ys = np.concatenate([[0.0], lay.floor_long_y, [W]])
    zs = np.concatenate([[0.0], lay.side_long_z, [H]])
    y_mid = ((ys[:-1] + ys[1:]) / 2)[::2]
    z_mid = ((zs[:-1] + zs[1:]) / 2)[[0, -1]]
    corners = []  # (corner on the web face, side of the web (+-x), leg into the tank)
    for xk in lay.web_x:
        for s in (-1.0, 1.0):
            xf = xk + s * lay.web_thickness / 2
            for y in y_mid:
                corners += [((xf, y, 0.0), s, (0, 0, leg)), ((xf, y, H), s, (0, 0, -leg))]
            for z in z_mid:
                corners += [((xf, 0.0, z), s, (0, leg, 0)), ((xf, W, z), s, (0, -leg, 0))]
    out: list[tuple[Part, int]] = []
    for corner, s, into in corners:
        c = np.asarray(corner)
        out.append((_prism(c, c + (s * leg, 0, 0), c + into, t), Material.BRACKET))
    return out


def _ladder(lay: TankLayout, e: float) -> list[tuple[Part, int]]:
    """Two flat-bar rails with stand-offs to the side shell and round rungs every 0.28 m."""
    H, W = lay.height, lay.width
    lx, ly = lay.ladder_xy
    _, Y, Z = np.eye(3)
    half, depth, tr = 0.2, 0.065, 0.012
    out: list[tuple[Part, int]] = []
    for x in (lx - half, lx + half):
        rail = _box([x - tr / 2, ly - depth / 2, 0], [x + tr / 2, ly + depth / 2, H], 2 * e)
        out.append((rail, Material.LADDER))
        for z in (0.45, H / 2 + 0.2, H - 0.35):
            stay = _box([x - tr / 2, ly + depth / 2, z - 0.03], [x + tr / 2, W, z + 0.03], e)
            out.append((stay, Material.LADDER))
    for z in np.arange(0.3, H - 0.1, 0.28):
        rung = _tube([lx - half, ly, z], [2 * half, 0, 0], Y, Z, 0.013, 0.013, 10, e)
        out.append((rung, Material.LADDER))
    return out


def _pipes(lay: TankLayout, e: float) -> list[tuple[Part, int]]:
    """Pipes along the tank with flange pairs mid-bay, collars at the webs, and supports."""
    L, H = lay.length, lay.height
    _, Y, Z = np.eye(3)
    edges = (0.0, *lay.web_x, L)
    joints = [(x0 + x1) / 2 + 0.2 for x0, x1 in zip(edges[:-1], edges[1:], strict=True)]
    out: list[tuple[Part, int]] = []
    for pipe in lay.pipes:
        y, z, r = pipe.y, pipe.z, pipe.radius
        n = max(12, int(2 * np.pi * r / 0.025))
        out.append((_tube([0, y, z], [L, 0, 0], Y, Z, r, r, n, 2 * e), pipe.material))
        rings = [(xj + dx, 0.026, 1.55 * r) for xj in joints for dx in (-0.026, 0.0)]
        rings += [(xk - 0.04, 0.08, 1.25 * r) for xk in lay.web_x]
        for x0, length, radius in rings:
            ring = _tube([x0, y, z], [length, 0, 0], Y, Z, radius, radius, n, e, caps=True)
            out.append((ring, Material.FLANGE))
        for xj in joints:  # saddles on the floor or hangers from the deck
            x = xj - 0.45
            z0, z1 = (0.0, z - 0.6 * r) if z < H / 2 else (z + 0.6 * r, H)
            out.append(
                (_box([x - 0.04, y - 0.06, z0], [x + 0.04, y + 0.06, z1], e), Material.STIFFENER)
            )
    return out


def build_tank(cfg: ShipTankConfig) -> TankMesh:
    """The compartment described by ``cfg`` as a :class:`TankMesh`."""
    lay = tank_layout(cfg)
    e = cfg.mesh_edge
    parts = [
        *_shell(lay, e),
        *_webs(lay, e),
        *_longitudinals(lay, e),
        *_brackets(lay),
        *_ladder(lay, e),
        *_pipes(lay, e),
    ]
    return TankMesh.from_parts(parts, lay)


def plane_mesh(corners: npt.ArrayLike, material: int = 0) -> TankMesh:
    """Two triangles over four corners [4, 3] (in order around the quad); for tests and calibration."""
    V = np.asarray(corners, np.float64).reshape(4, 3)
    return TankMesh.from_parts([((V, np.array([[0, 1, 2], [0, 2, 3]])), material)])
