"""The camera path through the scene, and held-out novel views.

In the tank, the path is a centripetal Catmull-Rom spline through control points along one side of the bays it
visits, crossing each web through the middle of its lightening hole; it is resampled at constant
speed (easing in and out). The camera looks along the path with yaw, pitch and roll sweeps that
repeat with distance travelled, so a shorter sequence sees the same places at a coarser step.
Other scene families pass their own control points and a constant yaw / pitch offset (the room:
a loop around the table, looking out at the walls).

Novel views are sampled away from the path (other bays, up at the deck, down at the floor, toward
the far end, back at the path) and kept when the fraction of their pixels whose surface the
trajectory observed (voxel set) lies in the configured range: extreme views that are still
repairable.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from gsfix_online.core.se3 import look_at
from gsfix_online.core.types import Intrinsics
from gsfix_online.scene.config import ShipTankConfig
from gsfix_online.scene.geometry import TankLayout
from gsfix_online.scene.render import Renderer

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]

YAW_PERIOD_M = 1.3  # one yaw sweep per this much path
PITCH_PERIOD_M = 1.9
ROLL_PERIOD_M = 2.9
ROLL_DEG = 3.0
NOVEL_KINDS = ("deck", "far_end", "back_at_path", "other_bay", "floor", "any")
NOVEL_MIN_PATH_DIST = 0.45  # m between a novel camera and the trajectory
NOVEL_MIN_SPACING = 0.5  # m between two novel cameras (or 45 deg between their view directions)


class SceneLayoutError(ValueError):
    """The configured tank leaves no room for the trajectory or the novel views."""


class Layout(Protocol):
    """What the path check and the novel-view search need of a layout (tank, room): the free
    box 0..length x 0..width x 0..height and its bays along x (a room is one bay)."""

    @property
    def length(self) -> float: ...
    @property
    def width(self) -> float: ...
    @property
    def height(self) -> float: ...
    @property
    def n_bays(self) -> int: ...
    def bay(self, i: int) -> tuple[float, float]: ...


# --------------------------------------------------------------------------------------------
# Trajectory
# --------------------------------------------------------------------------------------------


def control_points(cfg: ShipTankConfig, lay: TankLayout) -> F64:  # [M, 3]
    W, H = lay.width, lay.height
    n_visit = cfg.bays_visited or max(1, lay.n_bays - 1)
    pts = []
    for i in range(n_visit):
        x0, x1 = lay.bay(i)
        k = max(2, round((x1 - x0) / 0.75))
        for j, f in enumerate(np.linspace(0.35, 0.65, k)):
            side = (i * k + j) % 2  # alternate a little across and up
            pts.append((x0 + f * (x1 - x0), W * (0.33, 0.42)[side], H * (0.42, 0.58)[side]))
        if i + 1 < n_visit:  # through the hole of web i
            hy, hz = lay.hole_yz[i]
            xk = lay.web_x[i]
            pts += [(xk - 0.25, hy, hz), (xk + 0.25, hy, hz)]
    return np.asarray(pts, np.float64)


def spline_dense(points: F64, samples_per_segment: int = 64) -> tuple[F64, F64]:
    """Centripetal Catmull-Rom through ``points`` [M, 3]: dense samples [K, 3] and their arc length [K]."""
    P = np.concatenate([2 * points[:1] - points[1:2], points, 2 * points[-1:] - points[-2:-1]])
    dense = []
    for i in range(1, len(P) - 2):
        p0, p1, p2, p3 = P[i - 1], P[i], P[i + 1], P[i + 2]
        t0 = 0.0
        t1 = t0 + np.linalg.norm(p1 - p0) ** 0.5
        t2 = t1 + np.linalg.norm(p2 - p1) ** 0.5
        t3 = t2 + np.linalg.norm(p3 - p2) ** 0.5
        t = np.linspace(t1, t2, samples_per_segment, endpoint=False)[:, None]
        a1 = (t1 - t) / (t1 - t0) * p0 + (t - t0) / (t1 - t0) * p1
        a2 = (t2 - t) / (t2 - t1) * p1 + (t - t1) / (t2 - t1) * p2
        a3 = (t3 - t) / (t3 - t2) * p2 + (t - t2) / (t3 - t2) * p3
        b1 = (t2 - t) / (t2 - t0) * a1 + (t - t0) / (t2 - t0) * a2
        b2 = (t3 - t) / (t3 - t1) * a2 + (t - t1) / (t3 - t1) * a3
        dense.append((t2 - t) / (t2 - t1) * b1 + (t - t1) / (t2 - t1) * b2)
    dense.append(points[-1:])
    C = np.concatenate(dense)
    return C, np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(C, axis=0), axis=1))])


def eased_arc(n: int, total: float) -> F64:
    """``n`` arc-length positions in [0, total] with zero speed at both ends [n]."""
    u = np.linspace(0.0, 1.0, n)
    return total * (u - np.sin(2 * np.pi * u) / (2 * np.pi))


def camera_poses(
    cfg: ShipTankConfig,
    lay: Layout,
    points: F64 | None = None,  # [M, 3] control points; None = the tank's
    yaw_offset_deg: float = 0.0,  # added to the heading along the path
    pitch_offset_deg: float = 0.0,
) -> F64:  # [N, 4, 4] T_world_cam
    """The camera's exact poses, ``cfg.n_frames`` of them."""
    if points is None:
        assert isinstance(lay, TankLayout), "only the tank has default control points"
        points = control_points(cfg, lay)
    C, s_dense = spline_dense(points)
    s = eased_arc(cfg.n_frames, float(s_dense[-1]))
    pos = np.stack([np.interp(s, s_dense, C[:, k]) for k in range(3)], axis=1)
    tangent = np.gradient(C, axis=0)
    heading = np.interp(s, s_dense, np.unwrap(np.arctan2(tangent[:, 1], tangent[:, 0])))
    yaw = heading + np.radians(cfg.yaw_sweep_deg) * np.sin(2 * np.pi * s / YAW_PERIOD_M)
    pitch = np.radians(cfg.pitch_sweep_deg) * np.sin(2 * np.pi * s / PITCH_PERIOD_M + 1.0)
    roll = np.radians(ROLL_DEG) * np.sin(2 * np.pi * s / ROLL_PERIOD_M + 2.0)
    if yaw_offset_deg or pitch_offset_deg:
        yaw = yaw + np.radians(yaw_offset_deg)
        pitch = pitch + np.radians(pitch_offset_deg)
    return np.stack([_pose(p, y, pi, r) for p, y, pi, r in zip(pos, yaw, pitch, roll, strict=True)])


def _pose(eye: F64, yaw: float, pitch: float, roll: float) -> F64:
    fwd = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    T = look_at(eye, eye + fwd)
    c, s = np.cos(roll), np.sin(roll)
    R_roll = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # about the optical axis
    T[:3, :3] = T[:3, :3] @ R_roll
    return T


def check_clearance(
    renderer: Renderer, lay: Layout, positions: F64, clearance: float, what: str
) -> float:
    """Raise SceneLayoutError if a camera is outside the tank or nearer than ``clearance`` to geometry."""
    p = np.asarray(positions).reshape(-1, 3)
    box = np.array([lay.length, lay.width, lay.height])
    outside = np.flatnonzero(np.any((p < 0) | (p > box), axis=1))
    if len(outside):
        raise SceneLayoutError(
            f"{what} camera {outside[0]} at {p[outside[0]].round(3).tolist()} is outside the scene"
        )
    d = renderer.distance(p)
    i = int(np.argmin(d))
    if d[i] < clearance:
        raise SceneLayoutError(
            f"{what} camera {i} at {p[i].round(3).tolist()} is {d[i]:.3f} m from the structure (clearance {clearance} m)"
        )
    return float(d[i])


# --------------------------------------------------------------------------------------------
# Observed surface and coverage
# --------------------------------------------------------------------------------------------

_KEY_OFF = 1 << 20  # voxel indices in [-2^20, 2^20) fit 21 bits per axis


class ObservedSurface:
    """Voxels (edge ``voxel`` m) that hold at least one surface point seen by the trajectory."""

    def __init__(self, voxel: float) -> None:
        self.voxel = voxel
        self._chunks: list[npt.NDArray[np.int64]] = []
        self._keys: npt.NDArray[np.int64] | None = None

    def keys_of(self, points: npt.ArrayLike) -> npt.NDArray[np.int64]:  # [N, 3] -> [N]
        idx = (
            np.floor(np.asarray(points, np.float64).reshape(-1, 3) / self.voxel).astype(np.int64)
            + _KEY_OFF
        )
        return (idx[:, 0] << 42) | (idx[:, 1] << 21) | idx[:, 2]

    def add(self, points: npt.ArrayLike) -> None:
        self._chunks.append(np.unique(self.keys_of(points)))
        self._keys = None
        if len(self._chunks) >= 32:
            self._compact()

    def _compact(self) -> npt.NDArray[np.int64]:
        if self._keys is None:
            self._keys = (
                np.unique(np.concatenate(self._chunks)) if self._chunks else np.zeros(0, np.int64)
            )
            self._chunks = [self._keys]
        return self._keys

    def __len__(self) -> int:
        return len(self._compact())

    def seen(self, points: npt.ArrayLike) -> npt.NDArray[np.bool_]:  # [N, 3] -> [N]
        keys = self._compact()
        q = self.keys_of(points)
        if len(keys) == 0:
            return np.zeros(len(q), bool)
        i = np.minimum(np.searchsorted(keys, q), len(keys) - 1)
        return keys[i] == q

    def coverage(self, points: npt.ArrayLike) -> float:
        """Fraction of ``points`` [N, 3] in observed voxels (0 for no points)."""
        seen = self.seen(points)
        return float(seen.mean()) if len(seen) else 0.0


def observed_points(
    depth: npt.NDArray[np.float32], points: F64, depth_min: float, depth_max: float
) -> F64:
    """World points [K, 3] of pixels a range-limited depth sensor measures."""
    ok = (depth >= depth_min) & (depth <= depth_max) & (depth > 0)
    return points[ok]


# --------------------------------------------------------------------------------------------
# Novel views
# --------------------------------------------------------------------------------------------


@dataclass
class NovelView:
    T_world_cam: F64  # [4, 4]
    coverage: float  # fraction of hit pixels whose surface the trajectory observed
    kind: str  # which sampler made it (NOVEL_KINDS)


def _candidate(kind: str, rng: np.random.Generator, lay: Layout, path: F64, margin: float) -> F64:
    L, W, H = lay.length, lay.width, lay.height
    bays = list(range(lay.n_bays))
    if kind == "other_bay":  # a bay the robot never entered, if there is one
        unvisited = [
            i
            for i in bays
            if not np.any((path[:, 0] >= lay.bay(i)[0]) & (path[:, 0] <= lay.bay(i)[1]))
        ]
        bays = unvisited or bays
    bay = bays[int(rng.integers(len(bays)))]
    x0, x1 = lay.bay(bay)
    eye = np.array(
        [
            rng.uniform(x0 + margin, x1 - margin),
            rng.uniform(margin, W - margin),
            rng.uniform(margin, H - margin),
        ]
    )
    jitter = rng.uniform(-1.0, 1.0, 2)
    if kind == "deck":
        target = np.array([eye[0] + jitter[0], eye[1] + jitter[1], H])
    elif kind == "floor":
        target = np.array([eye[0] + jitter[0], eye[1] + jitter[1], 0.0])
    elif kind == "far_end":
        target = np.array([0.0 if eye[0] > L / 2 else L, rng.uniform(0, W), rng.uniform(0, H)])
    elif kind == "back_at_path":
        target = path[rng.integers(len(path))]
    else:  # other_bay / any: a random direction
        yaw, pitch = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(-50, 50))
        target = eye + [np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)]
    if np.linalg.norm(target - eye) < 0.3:
        target = eye + np.array([1.0, 0.0, 0.0])
    return _pose(eye, *_yaw_pitch(target - eye), np.radians(rng.uniform(-12, 12)))


def _yaw_pitch(d: F64) -> tuple[float, float]:
    d = d / np.linalg.norm(d)
    return float(np.arctan2(d[1], d[0])), float(np.arcsin(np.clip(d[2], -0.999, 0.999)))


def select_novel_views(
    cfg: ShipTankConfig,
    lay: Layout,
    renderer: Renderer,
    intr: Intrinsics,
    observed: ObservedSurface,
    path: F64,  # [N, 3] trajectory camera positions
    keep_out: Sequence[tuple[Sequence[float], Sequence[float]]] = (),  # solid boxes (lo, hi), m
) -> list[NovelView]:
    """Up to ``cfg.n_novel`` views with coverage in [novel_coverage_min, novel_coverage_max],
    deterministic. No camera inside a ``keep_out`` box (furniture) grown by the margin."""
    rng = np.random.default_rng([cfg.seed, 0x5EE])
    margin = cfg.clearance + 0.05
    chosen: list[NovelView] = []
    for i in range(cfg.novel_candidates):
        if len(chosen) >= cfg.n_novel:
            break
        kind = NOVEL_KINDS[i % len(NOVEL_KINDS)]
        T = _candidate(kind, rng, lay, path, margin)
        eye, fwd = T[:3, 3], T[:3, 2]
        if np.min(np.linalg.norm(path - eye, axis=1)) < NOVEL_MIN_PATH_DIST:
            continue
        if renderer.distance(eye[None])[0] < margin:
            continue
        if any(
            np.all(eye > np.asarray(lo) - margin) and np.all(eye < np.asarray(hi) + margin)
            for lo, hi in keep_out
        ):
            continue
        if any(
            np.linalg.norm(v.T_world_cam[:3, 3] - eye) < NOVEL_MIN_SPACING
            and v.T_world_cam[:3, 2] @ fwd > np.cos(np.pi / 4)
            for v in chosen
        ):
            continue
        depth, points, mask = renderer.depth(intr, T)
        if mask.mean() < 0.99:
            continue
        cov = observed.coverage(points[mask])
        if cfg.novel_coverage_min <= cov <= cfg.novel_coverage_max:
            chosen.append(NovelView(T, cov, kind))
    if len(chosen) < cfg.n_novel:
        logger.warning(
            "found %d of %d novel views in %d candidates",
            len(chosen),
            cfg.n_novel,
            cfg.novel_candidates,
        )
    return chosen
