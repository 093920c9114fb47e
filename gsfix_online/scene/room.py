"""A furnished room: layout, triangle mesh and the hand-held camera path around its table.

World frame: x along the room (0..length), y across (0..width), z up (0..height), metres; the same
conventions, mesh type, renderer and novel-view search as the tank. Parts: floor, ceiling and four
walls (one papered) with skirting; a door in a recess with architrave and handle (wall y = width);
a window recess with a sill and a blind above a column radiator (wall x = length); a bookshelf
full of books (wall x = 0); a sideboard with doors, handles, a vase and books (wall y = 0); a sofa
with cushions (wall y = width); framed pictures; a table with two chairs, a bowl, cups and a book
on a rug in the middle; a pot in a corner; two pendant lamps with shades. Sizes are fixed, the
room's size comes from the config, book sizes and colours and small placements from the seed.

The camera loops around the table at hand height (1.25-1.45 m), looking out at the walls and
furniture and a little down; ``room_loop`` turns of the loop (0.8 leaves part of the room to the
novel views).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import numpy.typing as npt

from gsfix_online.scene.config import ShipTankConfig
from gsfix_online.scene.primitives import Part, TankMesh, box, grid, orient, tube

F64 = npt.NDArray[np.float64]
Box = tuple[tuple[float, float, float], tuple[float, float, float]]  # (lo, hi) corners, m


class RoomMaterial(IntEnum):
    WALL = 0
    WALLPAPER = 1
    CEILING = 2
    FLOOR = 3
    RUG = 4
    WOOD = 5
    WOOD_DARK = 6
    FABRIC = 7
    METAL = 8  # painted: radiator, legs, handles, cords
    DOOR = 9
    TRIM = 10  # frames, skirting, sill
    BLIND = 11  # venetian blind in the window recess
    SHADE = 12  # lamp shades
    CERAMIC = 13  # vase, bowl, cups, pot
    BOOK = 16  # BOOK + k, k < N_BOOK_COLOURS
    PICTURE = 32  # PICTURE + k, k < N_PICTURES


N_BOOK_COLOURS = 16
N_PICTURES = 8

# Depth of the furniture zone along each wall, m: what the camera loop stays clear of.
ZONE_X0, ZONE_XL, ZONE_Y0, ZONE_YW = 0.35, 0.12, 0.45, 0.85
PATH_MARGIN = 0.5  # m between the loop and the furniture zones
CAMERA_Z = (1.25, 1.45)  # hand height, alternating between control points
CONTROL_SPACING = 0.5  # m of loop between control points
YAW_OFFSET_DEG = -35.0  # from the direction of travel toward the outside of the loop
PITCH_OFFSET_DEG = -12.0
ROOM_LAMP_POWER = 2.2  # multiplies cfg.light_power: two pendant lamps light a whole room
ROOM_AMBIENT = 2.5  # multiplies cfg.ambient: light bounces more in a white room than in a tank
RECESS = 0.18  # wall thickness at the door and window, m


@dataclass(frozen=True)
class RoomLayout:
    """Where everything is; derived from the config (and the seed for small placements)."""

    length: float
    width: float
    height: float
    table_centre: tuple[float, float]  # also the centre of the camera loop
    path_axes: tuple[float, float]  # semi-axes of the loop (x, y), m
    rug: tuple[float, float, float, float]  # x0, x1, y0, y1
    door: tuple[float, float, float]  # x0, x1, top z; in the wall y = width
    window: tuple[float, float, float, float]  # y0, y1, z0, z1; in the wall x = length
    lamps: tuple[tuple[float, float, float], ...]
    keep_out: tuple[Box, ...]  # furniture bounding boxes: no novel camera inside

    @property
    def n_bays(self) -> int:
        return 1  # one open space; the novel-view search treats it as the tank's single bay

    def bay(self, i: int) -> tuple[float, float]:
        assert i == 0
        return 0.0, self.length


def room_layout(cfg: ShipTankConfig) -> RoomLayout:
    L, W, H = cfg.room_length, cfg.room_width, cfg.room_height
    cx = (ZONE_X0 + L - ZONE_XL) / 2.0
    cy = (ZONE_Y0 + W - ZONE_YW) / 2.0
    a = (L - ZONE_X0 - ZONE_XL) / 2.0 - PATH_MARGIN
    b = (W - ZONE_Y0 - ZONE_YW) / 2.0 - PATH_MARGIN
    lamp_z = H - 0.6
    return RoomLayout(
        length=L,
        width=W,
        height=H,
        table_centre=(cx, cy),
        path_axes=(a, b),
        rug=(cx - 1.0, cx + 1.0, cy - 0.7, cy + 0.7),
        door=(L - 1.35, L - 0.45, 2.05),
        window=(W / 2 - 0.7, W / 2 + 0.7, 0.9, 2.1),
        lamps=((cx - 0.18 * L, cy, lamp_z), (cx + 0.18 * L, cy, lamp_z)),
        keep_out=(
            ((0.0, W / 2 - 0.6, 0.0), (ZONE_X0, W / 2 + 0.6, 1.9)),  # bookshelf
            ((0.3 * L, 0.0, 0.0), (0.3 * L + 1.6, ZONE_Y0 + 0.04, 1.1)),  # sideboard
            ((0.5, W - ZONE_YW, 0.0), (2.5, W, 0.9)),  # sofa
            ((cx - 1.12, cy - 0.42, 0.0), (cx + 1.12, cy + 0.42, 0.9)),  # table and chairs
            ((L - 0.56, 0.24, 0.0), (L - 0.24, 0.56, 0.42)),  # pot
            ((L - ZONE_XL, W / 2 - 0.7, 0.0), (L, W / 2 + 0.7, 0.8)),  # radiator
        ),
    )


# --------------------------------------------------------------------------------------------
# Mesh
# --------------------------------------------------------------------------------------------

X, Y, Z = np.eye(3)


def _rect(origin: npt.ArrayLike, u: npt.ArrayLike, v: npt.ArrayLike, normal: F64, e: float) -> Part:
    return orient(grid(origin, u, v, e), normal)


def _wall_with_hole(
    origin: F64,  # [3] wall corner
    eu: F64,  # [3] unit, along the wall
    ev: F64,  # [3] unit, up
    size: tuple[float, float],  # (along, up), m
    hole: tuple[float, float, float, float] | None,  # (u0, u1, v0, v1) in metres on the wall
    normal: F64,  # into the room
    e: float,
) -> list[Part]:
    """A wall rectangle minus one rectangular opening, as up to four plain rectangles."""
    lu, lv = size
    if hole is None:
        return [_rect(origin, lu * eu, lv * ev, normal, e)]
    u0, u1, v0, v1 = hole
    rects = [(0.0, u0, 0.0, lv), (u1, lu, 0.0, lv), (u0, u1, v1, lv), (u0, u1, 0.0, v0)]
    return [
        _rect(origin + a * eu + c * ev, (b - a) * eu, (d - c) * ev, normal, e)
        for a, b, c, d in rects
        if b - a > 1e-6 and d - c > 1e-6
    ]


def _shell(lay: RoomLayout, e: float) -> list[tuple[Part, int]]:
    L, W, H = lay.length, lay.width, lay.height
    M = RoomMaterial
    dx0, dx1, dz1 = lay.door
    wy0, wy1, wz0, wz1 = lay.window
    d = RECESS
    out: list[tuple[Part, int]] = [
        (_rect([0, 0, 0], [L, 0, 0], [0, W, 0], Z, e), M.FLOOR),
        (_rect([0, 0, H], [L, 0, 0], [0, W, 0], -Z, e), M.CEILING),
    ]
    o = np.zeros(3)
    out += [(p, M.WALLPAPER) for p in _wall_with_hole(o, X, Z, (L, H), None, Y, e)]
    out += [(p, M.WALL) for p in _wall_with_hole(o, Y, Z, (W, H), None, X, e)]
    door = (dx0, dx1, 0.0, dz1)
    out += [(p, M.WALL) for p in _wall_with_hole(np.array([0, W, 0]), X, Z, (L, H), door, -Y, e)]
    win = (wy0, wy1, wz0, wz1)
    out += [(p, M.WALL) for p in _wall_with_hole(np.array([L, 0, 0]), Y, Z, (W, H), win, -X, e)]
    # Door recess: reveals, threshold, the door and its handle, architrave on the wall.
    out += [
        (_rect([dx0, W, 0], [0, d, 0], [0, 0, dz1], X, e), M.WALL),
        (_rect([dx1, W, 0], [0, d, 0], [0, 0, dz1], -X, e), M.WALL),
        (_rect([dx0, W, dz1], [dx1 - dx0, 0, 0], [0, d, 0], -Z, e), M.WALL),
        (_rect([dx0, W, 0], [dx1 - dx0, 0, 0], [0, d, 0], Z, e), M.FLOOR),
        (_rect([dx0, W + d, 0], [dx1 - dx0, 0, 0], [0, 0, dz1], -Y, e), M.DOOR),
        (box([dx1 - 0.11, W + d - 0.012, 0.93], [dx1 - 0.06, W + d, 1.09], e), M.METAL),
        (box([dx1 - 0.2, W + d - 0.065, 0.99], [dx1 - 0.075, W + d - 0.012, 1.025], e), M.METAL),
    ]
    t, w = 0.02, 0.07
    for lo, hi in (
        ([dx0 - w, W - t, 0], [dx0, W, dz1 + w]),
        ([dx1, W - t, 0], [dx1 + w, W, dz1 + w]),
        ([dx0, W - t, dz1], [dx1, W, dz1 + w]),
    ):
        out.append((box(lo, hi, 2 * e), M.TRIM))
    # Window recess: reveals, the blind at the back, a sill (the recess floor) and a radiator.
    out += [
        (_rect([L, wy0, wz0], [d, 0, 0], [0, 0, wz1 - wz0], Y, e), M.WALL),
        (_rect([L, wy1, wz0], [d, 0, 0], [0, 0, wz1 - wz0], -Y, e), M.WALL),
        (_rect([L, wy0, wz1], [d, 0, 0], [0, wy1 - wy0, 0], -Z, e), M.WALL),
        (_rect([L + d, wy0, wz0], [0, wy1 - wy0, 0], [0, 0, wz1 - wz0], -X, e), M.BLIND),
        (box([L - 0.05, wy0 - 0.05, wz0 - 0.03], [L + d, wy1 + 0.05, wz0], 2 * e), M.TRIM),
    ]
    y = wy0 + 0.05
    while y + 0.035 <= wy1 - 0.05:  # radiator columns
        out.append((box([L - 0.1, y, 0.15], [L - 0.03, y + 0.035, wz0 - 0.12], e), M.METAL))
        y += 0.05
    # Skirting boards (interrupted by the door).
    s, h = 0.015, 0.08
    for lo, hi in (
        ([0, 0, 0], [L, s, h]),
        ([0, 0, 0], [s, W, h]),
        ([L - s, 0, 0], [L, W, h]),
        ([0, W - s, 0], [dx0 - w, W, h]),
        ([dx1 + w, W - s, 0], [L, W, h]),
    ):
        out.append((box(lo, hi, 4 * e), M.TRIM))
    return out


def _picture(
    centre: tuple[float, float, float], axis: int, sign: float, size: tuple[float, float], k: int
) -> list[tuple[Part, int]]:
    """A framed picture on a wall normal to ``axis`` facing ``sign``; ``size`` (across, up)."""
    across = 1 if axis == 0 else 0
    c = np.asarray(centre, np.float64)
    wa, hz = size[0] / 2, size[1] / 2

    def slab(a0: float, a1: float, z0: float, z1: float, t: float) -> Part:
        lo, hi = c.copy(), c.copy()
        lo[across], hi[across] = c[across] + a0, c[across] + a1
        lo[2], hi[2] = c[2] + z0, c[2] + z1
        lo[axis], hi[axis] = sorted((c[axis], c[axis] + sign * t))
        return box(lo, hi, 1.0)

    f = 0.04
    out = [(slab(-wa, wa, -hz, hz, 0.02), RoomMaterial.PICTURE + k)]
    for a0, a1, z0, z1 in (
        (-wa - f, wa + f, -hz - f, -hz),
        (-wa - f, wa + f, hz, hz + f),
        (-wa - f, -wa, -hz, hz),
        (wa, wa + f, -hz, hz),
    ):
        out.append((slab(a0, a1, z0, z1, 0.035), RoomMaterial.WOOD_DARK))
    return out


def _bookshelf(lay: RoomLayout, rng: np.random.Generator, e: float) -> list[tuple[Part, int]]:
    W = lay.width
    M = RoomMaterial
    d, top = 0.33, 1.9
    y0, y1 = W / 2 - 0.6, W / 2 + 0.6
    boxes = [
        ([0, y0, 0], [d, y0 + 0.02, top]),
        ([0, y1 - 0.02, 0], [d, y1, top]),
        ([0, y0 + 0.02, top - 0.02], [d, y1 - 0.02, top]),
        ([0, y0 + 0.02, 0], [0.01, y1 - 0.02, top - 0.02]),  # back panel
        ([0.01, y0 + 0.02, 0], [d, y1 - 0.02, 0.07]),  # plinth
    ]
    levels = [0.07 + 0.45 * k for k in range(4)]
    boxes += [([0.01, y0 + 0.02, z], [d, y1 - 0.02, z + 0.02]) for z in levels[1:]]
    out: list[tuple[Part, int]] = [(box(lo, hi, 2 * e), M.WOOD) for lo, hi in boxes]
    for z in levels:
        base = z + (0.02 if z > 0.07 else 0.0)
        y = y0 + 0.02 + rng.uniform(0.0, 0.04)
        while True:
            if rng.random() < 0.08:  # a gap in the row
                y += rng.uniform(0.05, 0.2)
            bw = rng.uniform(0.02, 0.055)
            if y + bw > y1 - 0.025:
                break
            bh = rng.uniform(0.2, 0.38)
            bd = rng.uniform(0.16, 0.26)
            k = int(rng.integers(N_BOOK_COLOURS))
            out.append(
                (box([d - 0.01 - bd, y, base], [d - 0.01, y + bw, base + bh], 1.0), M.BOOK + k)
            )
            y += bw + (0.002 if rng.random() < 0.7 else rng.uniform(0.005, 0.02))
    return out


def _sideboard(lay: RoomLayout, rng: np.random.Generator, e: float) -> list[tuple[Part, int]]:
    M = RoomMaterial
    x0 = 0.3 * lay.length
    x1, dp, top = x0 + 1.6, ZONE_Y0, 0.8
    out: list[tuple[Part, int]] = [(box([x0, 0, 0.12], [x1, dp, top], 2 * e), M.WOOD_DARK)]
    for lx in (x0 + 0.05, x1 - 0.09):
        for ly in (0.05, dp - 0.09):
            out.append((box([lx, ly, 0], [lx + 0.04, ly + 0.04, 0.12], 1.0), M.METAL))
    n, gap = 3, 0.004
    pw = (x1 - x0 - (n + 1) * gap) / n
    for i in range(n):
        a = x0 + gap + i * (pw + gap)
        out.append((box([a, dp, 0.15], [a + pw, dp + 0.015, top - 0.03], 2 * e), M.WOOD))
        hx = a + pw / 2
        out.append(
            (box([hx - 0.06, dp + 0.015, 0.69], [hx + 0.06, dp + 0.035, 0.705], 1.0), M.METAL)
        )
    vx = x0 + rng.uniform(0.2, 0.45)
    out.append(
        (tube([vx, dp / 2, top], [0, 0, 0.28], X, Y, 0.07, 0.07, 24, 2 * e, caps=True), M.CERAMIC)
    )
    bx = x1 - rng.uniform(0.35, 0.55)
    for j, (w, dd, h) in enumerate(((0.3, 0.22, 0.04), (0.27, 0.2, 0.035), (0.24, 0.17, 0.05))):
        z0 = top + sum((0.04, 0.035, 0.05)[:j])
        k = int(rng.integers(N_BOOK_COLOURS))
        out.append((box([bx, 0.08, z0], [bx + w, 0.08 + dd, z0 + h], 1.0), M.BOOK + k))
    return out


def _sofa(lay: RoomLayout, e: float) -> list[tuple[Part, int]]:
    M, W = RoomMaterial, lay.width
    x0, x1, y0 = 0.5, 2.5, W - ZONE_YW
    arm, back = 0.18, W - 0.22
    out: list[tuple[Part, int]] = [
        (box([x0 + arm, y0, 0.1], [x1 - arm, W, 0.4], 2 * e), M.FABRIC),
        (box([x0, y0, 0.1], [x0 + arm, W, 0.62], 2 * e), M.FABRIC),
        (box([x1 - arm, y0, 0.1], [x1, W, 0.62], 2 * e), M.FABRIC),
        (box([x0 + arm, back, 0.4], [x1 - arm, W, 0.85], 2 * e), M.FABRIC),
    ]
    mid = (x0 + x1) / 2
    for a, b in ((x0 + arm, mid - 0.005), (mid + 0.005, x1 - arm)):
        out.append((box([a, y0 + 0.01, 0.4], [b, back, 0.52], 2 * e), M.FABRIC))
        out.append((box([a + 0.02, back - 0.12, 0.52], [b - 0.02, back, 0.88], 2 * e), M.FABRIC))
    for fx in (x0 + 0.04, x1 - 0.08):
        for fy in (y0 + 0.04, W - 0.08):
            out.append((box([fx, fy, 0], [fx + 0.04, fy + 0.04, 0.1], 1.0), M.WOOD_DARK))
    return out


def _table(lay: RoomLayout, rng: np.random.Generator, e: float) -> list[tuple[Part, int]]:
    M = RoomMaterial
    cx, cy = lay.table_centre
    rx0, rx1, ry0, ry1 = lay.rug
    out: list[tuple[Part, int]] = [
        (box([rx0, ry0, 0.0], [rx1, ry1, 0.01], 2 * e), M.RUG),
        (box([cx - 0.6, cy - 0.4, 0.72], [cx + 0.6, cy + 0.4, 0.76], 2 * e), M.WOOD),
    ]
    for lx in (cx - 0.54, cx + 0.49):
        for ly in (cy - 0.34, cy + 0.29):
            out.append((box([lx, ly, 0.01], [lx + 0.05, ly + 0.05, 0.72], 2 * e), M.WOOD_DARK))
    for s in (-1.0, 1.0):  # chairs at both ends, backs outward
        xc = cx + s * (0.6 + 0.08 + 0.21)
        out.append((box([xc - 0.21, cy - 0.21, 0.44], [xc + 0.21, cy + 0.21, 0.48], 2 * e), M.WOOD))
        for lx in (xc - 0.19, xc + 0.155):
            for ly in (cy - 0.19, cy + 0.155):
                out.append((box([lx, ly, 0.01], [lx + 0.035, ly + 0.035, 0.44], 2 * e), M.METAL))
        bx0, bx1 = sorted((xc + s * 0.18, xc + s * 0.21))
        out.append((box([bx0, cy - 0.2, 0.48], [bx1, cy + 0.2, 0.9], 2 * e), M.WOOD))
    top = 0.76
    j = rng.uniform(-0.05, 0.05, 4)
    out.append(
        (
            tube(
                [cx - 0.2 + j[0], cy + 0.1, top], [0, 0, 0.07], X, Y, 0.11, 0.11, 32, e, caps=True
            ),
            M.CERAMIC,
        )
    )
    for ux, uy in ((0.25 + j[1], -0.2), (0.38, 0.18 + j[2])):
        cup = tube([cx + ux, cy + uy, top], [0, 0, 0.095], X, Y, 0.04, 0.04, 16, e, caps=True)
        out.append((cup, M.CERAMIC))
    bx = cx - 0.45 + j[3]
    k = int(rng.integers(N_BOOK_COLOURS))
    out.append(
        (box([bx, cy - 0.3, top], [bx + 0.23, cy - 0.3 + 0.31, top + 0.03], 1.0), M.BOOK + k)
    )
    return out


def _lamps(lay: RoomLayout, e: float) -> list[tuple[Part, int]]:
    """Shades open at the bottom, cords and ceiling roses."""
    H = lay.height
    out: list[tuple[Part, int]] = []
    for lx, ly, lz in lay.lamps:
        # The bulb sits level with the shade's lower rim: the walls are lit up to its height.
        shade = tube([lx, ly, lz - 0.01], [0, 0, 0.18], X, Y, 0.17, 0.17, 40, e)
        out.append((shade, RoomMaterial.SHADE))
        lid = tube([lx, ly, lz + 0.17], [0, 0, 0.004], X, Y, 0.17, 0.17, 40, e, caps=True)
        out.append((lid, RoomMaterial.SHADE))  # closed top: no hot spot on the ceiling
        cord = tube([lx, ly, lz + 0.17], [0, 0, H - lz - 0.17], X, Y, 0.006, 0.006, 8, e)
        out.append((cord, RoomMaterial.METAL))
        rose = tube([lx, ly, H - 0.03], [0, 0, 0.03], X, Y, 0.05, 0.05, 16, e, caps=True)
        out.append((rose, RoomMaterial.TRIM))
    return out


def build_room(cfg: ShipTankConfig) -> TankMesh:
    """The room described by ``cfg`` as a :class:`TankMesh` (materials are RoomMaterial ids)."""
    lay = room_layout(cfg)
    rng = np.random.default_rng([cfg.seed, 0x2003])
    e = cfg.mesh_edge
    L, W = lay.length, lay.width
    pics = rng.permutation(N_PICTURES)
    parts = [
        *_shell(lay, e),
        *_bookshelf(lay, rng, e),
        *_sideboard(lay, rng, e),
        *_sofa(lay, e),
        *_table(lay, rng, e),
        *_lamps(lay, e),
        *_picture((0.3 * L + 0.45, 0.0, 1.55), 1, 1.0, (0.6, 0.45), int(pics[0])),
        *_picture((0.3 * L + 1.2, 0.0, 1.6), 1, 1.0, (0.4, 0.55), int(pics[1])),
        *_picture((1.5, W, 1.5), 1, -1.0, (0.9, 0.6), int(pics[2])),
        *_picture((0.0, W / 2 - 1.05, 1.45), 0, 1.0, (0.35, 0.5), int(pics[3])),
    ]
    pot = tube([L - 0.4, 0.4, 0.0], [0, 0, 0.42], X, Y, 0.16, 0.16, 32, e, caps=True)
    parts.append((pot, RoomMaterial.CERAMIC))
    return TankMesh.from_parts(parts, lay)


# --------------------------------------------------------------------------------------------
# Camera path
# --------------------------------------------------------------------------------------------


def room_control_points(cfg: ShipTankConfig, lay: RoomLayout) -> F64:  # [M, 3]
    """Points on an ellipse around the table, counter-clockwise from the sideboard side."""
    (cx, cy), (a, b) = lay.table_centre, lay.path_axes
    turns = cfg.room_loop
    perimeter = math.pi * (3 * (a + b) - math.sqrt((3 * a + b) * (a + 3 * b)))  # Ramanujan
    n = max(4, math.ceil(turns * perimeter / CONTROL_SPACING) + 1)
    theta = -0.6 * math.pi + 2 * math.pi * turns * np.linspace(0.0, 1.0, n)
    radial = np.where(np.arange(n) % 2, 0.94, 1.0)  # weave in and out a little
    z = np.where(np.arange(n) % 2, CAMERA_Z[1], CAMERA_Z[0])
    return np.stack([cx + a * radial * np.cos(theta), cy + b * radial * np.sin(theta), z], -1)


def room_poses(cfg: ShipTankConfig, lay: RoomLayout) -> F64:  # [N, 4, 4] T_world_cam
    from gsfix_online.scene.trajectory import camera_poses

    return camera_poses(
        cfg,
        lay,
        room_control_points(cfg, lay),
        yaw_offset_deg=YAW_OFFSET_DEG,
        pitch_offset_deg=PITCH_OFFSET_DEG,
    )
