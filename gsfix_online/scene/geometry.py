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

from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import numpy.typing as npt

from gsfix_online.scene.config import ShipTankConfig
from gsfix_online.scene.primitives import (  # noqa: F401  (TankMesh, Part: re-exported)
    F64,
    Part,
    TankMesh,
    box,
    convex,
    grid,
    merge_parts,
    n_segments,
    orient,
    plane_part,
    prism,
    ring_2d,
    tube,
)


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


def _shell(lay: TankLayout, e: float) -> list[tuple[Part, int]]:
    L, W, H = lay.length, lay.width, lay.height
    X, Y, Z = np.eye(3)
    parts = [
        orient(grid([0, 0, 0], [L, 0, 0], [0, W, 0], e), Z),  # floor
        orient(grid([0, 0, 0], [L, 0, 0], [0, 0, H], e), Y),  # side y = 0
        orient(grid([0, W, 0], [L, 0, 0], [0, 0, H], e), -Y),  # side y = W
        orient(grid([0, 0, 0], [0, W, 0], [0, 0, H], e), X),  # end x = 0
        orient(grid([L, 0, 0], [0, W, 0], [0, 0, H], e), -X),  # end x = L
    ]
    # Deck: a panel with the manhole (ring triangulation) and plain strips around it.
    (mx, my), (ma, mb) = lay.manhole_xy, lay.manhole_axes
    px0, px1 = max(0.0, mx - 2 * ma), min(L, mx + 2 * ma)
    py0, py1 = max(0.0, my - 2 * mb - 0.1), W
    P2, T2, t_loop = ring_2d((px0, px1, py0, py1), (mx, my), (ma, mb), 64, e)
    parts.append(plane_part(P2, T2, np.array([0, 0, H]), X, Y, -Z))
    for x0, x1, y0, y1 in ((0, px0, 0, W), (px1, L, 0, W), (px0, px1, 0, py0)):
        if x1 - x0 > 1e-6 and y1 - y0 > 1e-6:
            parts.append(orient(grid([x0, y0, H], [x1 - x0, 0, 0], [0, y1 - y0, 0], e), -Z))
    out: list[tuple[Part, int]] = [(p, Material.SHELL) for p in parts]
    # Coaming (seen from inside the tube) and the closed cover on top of it.
    ch = lay.coaming_height
    coaming = tube([mx, my, H], [0, 0, ch], X, Y, ma, mb, t_loop, e)
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
    out.append((orient((Vd, Td), -Z), Material.COAMING))
    return out


def _webs(lay: TankLayout, e: float) -> list[tuple[Part, int]]:
    W, H = lay.width, lay.height
    X, Y, Z = np.eye(3)
    t = lay.web_thickness
    a, b = lay.hole_axes
    out: list[tuple[Part, int]] = []
    for xk, (hy, hz) in zip(lay.web_x, lay.hole_yz, strict=True):
        ring, tri, t_loop = ring_2d(
            (0.0, W, 0.0, H), (hy, hz), (a, b), n_segments(2 * (W + H), e), e
        )
        for side in (-1.0, 1.0):
            face = plane_part(ring, tri, np.array([xk + side * t / 2, 0, 0]), Y, Z, side * X)
            out.append((face, Material.WEB))
        rim = tube([xk - t / 2, hy, hz], [t, 0, 0], Y, Z, a, b, t_loop, e)
        out.append(((rim[0], rim[1][:, [0, 2, 1]]), Material.WEB))  # faces the hole axis
        # Vertical flat-bar stiffeners on the +x face, either side of the hole.
        for ys in (hy - a - 0.35, hy + a + 0.35):
            if 0.2 < ys < W - 0.2:
                bar = box([xk + t / 2, ys - 0.006, 0], [xk + t / 2 + 0.1, ys + 0.006, H], 2 * e)
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
    return [(box(lo, hi, 2 * e), Material.STIFFENER) for lo, hi in boxes]


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
        out.append((prism(c, c + (s * leg, 0, 0), c + into, t), Material.BRACKET))
    return out


def _ladder(lay: TankLayout, e: float) -> list[tuple[Part, int]]:
    """Two flat-bar rails with stand-offs to the side shell and round rungs every 0.28 m."""
    H, W = lay.height, lay.width
    lx, ly = lay.ladder_xy
    _, Y, Z = np.eye(3)
    half, depth, tr = 0.2, 0.065, 0.012
    out: list[tuple[Part, int]] = []
    for x in (lx - half, lx + half):
        rail = box([x - tr / 2, ly - depth / 2, 0], [x + tr / 2, ly + depth / 2, H], 2 * e)
        out.append((rail, Material.LADDER))
        for z in (0.45, H / 2 + 0.2, H - 0.35):
            stay = box([x - tr / 2, ly + depth / 2, z - 0.03], [x + tr / 2, W, z + 0.03], e)
            out.append((stay, Material.LADDER))
    for z in np.arange(0.3, H - 0.1, 0.28):
        rung = tube([lx - half, ly, z], [2 * half, 0, 0], Y, Z, 0.013, 0.013, 10, e)
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
        out.append((tube([0, y, z], [L, 0, 0], Y, Z, r, r, n, 2 * e), pipe.material))
        rings = [(xj + dx, 0.026, 1.55 * r) for xj in joints for dx in (-0.026, 0.0)]
        rings += [(xk - 0.04, 0.08, 1.25 * r) for xk in lay.web_x]
        for x0, length, radius in rings:
            ring = tube([x0, y, z], [length, 0, 0], Y, Z, radius, radius, n, e, caps=True)
            out.append((ring, Material.FLANGE))
        for xj in joints:  # saddles on the floor or hangers from the deck
            x = xj - 0.45
            z0, z1 = (0.0, z - 0.6 * r) if z < H / 2 else (z + 0.6 * r, H)
            out.append(
                (box([x - 0.04, y - 0.06, z0], [x + 0.04, y + 0.06, z1], e), Material.STIFFENER)
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
