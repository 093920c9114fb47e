"""hypothesis strategies for extreme but legal inputs, shared by the stress properties.

Ranges (the issue's): scales 1e-6 to 1e3 m per axis (so anisotropy up to 1e9), depths 1 mm to
1 km, means on the near plane, on the camera plane and behind the camera, zero, tiny and
unnormalised quaternions (norm 1e-5 to 1e6), focal lengths 0.05 to 1e5 px with any aspect, principal points
anywhere :class:`~gsfix_online.core.types.Intrinsics` accepts, poses up to 10 km from the origin.
Log-uniform draws cover each range evenly per decade, and the bounds themselves are drawn
explicitly (``sampled_from``), since that is where things break.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt
from hypothesis import strategies as st

from gsfix_online.core.types import Intrinsics

SCALE_RANGE_M = (1e-6, 1e3)
DEPTH_RANGE_M = (1e-3, 1e3)
FAR_FROM_ORIGIN_M = 1e4  # 10 km
FOCAL_RANGE_PX = (0.05, 1e5)
NEAR_M = 0.01  # the renderer's default near plane


def log_uniform(lo: float, hi: float) -> st.SearchStrategy[float]:
    """Floats in [lo, hi], uniform in log, with both bounds drawn explicitly too."""
    inner = st.floats(math.log(lo), math.log(hi)).map(lambda v: min(max(math.exp(v), lo), hi))
    return st.one_of(st.sampled_from([lo, hi]), inner)


def unit_quat_wxyz(draw: st.DrawFn) -> npt.NDArray[np.float64]:  # [4] unit (w, x, y, z)
    v = np.array(draw(st.lists(st.floats(-1, 1), min_size=4, max_size=4)))
    n = float(np.linalg.norm(v))
    if n < 1e-3:  # hypothesis shrinks towards zero: take the identity there
        return np.array([1.0, 0.0, 0.0, 0.0])
    return v / n


@st.composite
def quats_wxyz(draw: st.DrawFn) -> npt.NDArray[np.float64]:  # [4] (w, x, y, z), any norm
    """Unit, unnormalised (norm 1e-5 to 1e6), tiny (1e-20: the identity) or zero quaternions.

    Norms near 1e-6 (|q|² near QUAT_EPS = 1e-12, where the map's rule switches to the identity)
    are left out: there float32 and float64 may take different sides of the switch."""
    kind = draw(st.sampled_from(["unit", "scaled", "tiny", "zero", "axis"]))
    if kind == "zero":
        return np.zeros(4)
    if kind == "axis":
        q = np.zeros(4)
        q[draw(st.integers(0, 3))] = draw(st.sampled_from([1.0, -1.0, 1e-5, 1e6]))
        return q
    q = unit_quat_wxyz(draw)
    if kind == "scaled":
        return q * draw(log_uniform(1e-5, 1e6))
    if kind == "tiny":
        return q * 1e-20
    return q


@st.composite
def scale_triplets(draw: st.DrawFn) -> npt.NDArray[np.float64]:  # [3] m
    """Per-axis scales 1e-6 to 1e3 m: independent, isotropic, needles and discs (anisotropy
    1e3 to 1e9, where 2D covariances are nearly singular)."""
    kind = draw(st.sampled_from(["independent", "isotropic", "needle", "disc"]))
    if kind == "independent":
        return np.array(draw(st.tuples(*[log_uniform(*SCALE_RANGE_M)] * 3)))
    if kind == "isotropic":
        return np.full(3, draw(log_uniform(*SCALE_RANGE_M)))
    big, small = draw(log_uniform(1.0, SCALE_RANGE_M[1])), draw(log_uniform(SCALE_RANGE_M[0], 1e-3))
    s = np.array([big, small, small] if kind == "needle" else [big, big, small])
    return s[np.array(draw(st.permutations([0, 1, 2])))]


@st.composite
def rotations(draw: st.DrawFn) -> npt.NDArray[np.float64]:  # [3, 3]
    """Rotations: random, identity, and half turns (where axis-angle is ambiguous)."""
    from scipy.spatial.transform import Rotation

    kind = draw(st.sampled_from(["random", "identity", "half_turn", "tiny"]))
    if kind == "identity":
        return np.eye(3)
    if kind == "half_turn":
        axis = unit_quat_wxyz(draw)[1:]
        axis = axis / np.linalg.norm(axis) if np.linalg.norm(axis) > 1e-6 else np.array([1, 0, 0])
        return Rotation.from_rotvec(math.pi * axis).as_matrix()
    if kind == "tiny":
        return Rotation.from_rotvec(
            np.array(draw(st.tuples(*[log_uniform(1e-12, 1e-6)] * 3)))
        ).as_matrix()
    w, x, y, z = unit_quat_wxyz(draw)
    return Rotation.from_quat([x, y, z, w]).as_matrix()


@st.composite
def poses(draw: st.DrawFn, far: bool = True) -> npt.NDArray[np.float64]:  # [4, 4] rigid
    """Rigid transforms whose translation is 0 to 10 km from the origin (``far``) or <= 10 m."""
    T = np.eye(4)
    T[:3, :3] = draw(rotations())
    direction = unit_quat_wxyz(draw)[1:]
    n = np.linalg.norm(direction)
    direction = direction / n if n > 1e-6 else np.array([1.0, 0.0, 0.0])
    hi = FAR_FROM_ORIGIN_M if far else 10.0
    dist = draw(st.one_of(st.just(0.0), log_uniform(1e-3, hi)))
    T[:3, 3] = dist * direction
    return T


@st.composite
def intrinsics(draw: st.DrawFn, width: int | None = None, height: int | None = None) -> Intrinsics:
    """Pinhole intrinsics: focal lengths 0.05 to 1e5 px each (aspect up to 2e6: nearly
    singular), principal point anywhere Intrinsics accepts."""
    w = width if width is not None else draw(st.integers(4, 24))
    h = height if height is not None else draw(st.integers(4, 24))
    fx = draw(log_uniform(*FOCAL_RANGE_PX))
    fy = draw(st.one_of(st.just(fx), log_uniform(*FOCAL_RANGE_PX)))
    cx = draw(st.one_of(st.just(w / 2), st.floats(-0.5 * w, 1.5 * w)))
    cy = draw(st.one_of(st.just(h / 2), st.floats(-0.5 * h, 1.5 * h)))
    return Intrinsics(fx, fy, cx, cy, w, h)


@st.composite
def camera_points(draw: st.DrawFn, K: Intrinsics) -> tuple[float, float, float]:
    """A point in the camera frame: in front (depth 1 mm to 1 km) at a pixel in or near the
    image, on the near plane, on the camera plane (z = 0) or behind the camera."""
    kind = draw(st.sampled_from(["front", "front", "near_plane", "camera_plane", "behind"]))
    u = draw(st.floats(-0.5 * K.width, 1.5 * K.width))
    v = draw(st.floats(-0.5 * K.height, 1.5 * K.height))
    if kind == "camera_plane":
        return draw(st.floats(-1, 1)), draw(st.floats(-1, 1)), 0.0
    z = {
        "front": draw(log_uniform(*DEPTH_RANGE_M)),
        "near_plane": draw(st.sampled_from([NEAR_M, math.nextafter(NEAR_M, 1), 1.01 * NEAR_M])),
        "behind": -draw(log_uniform(*DEPTH_RANGE_M)),
    }[kind]
    return (u - K.cx) / K.fx * abs(z), (v - K.cy) / K.fy * abs(z), z


@st.composite
def gaussian_params(draw: st.DrawFn, K: Intrinsics, n_max: int = 8) -> dict[str, Any]:
    """1..n_max Gaussians in the camera frame: means [N, 3], quats [N, 4] (w, x, y, z),
    scales [N, 3] m (each axis 1e-6 to 1e3), opacities [N] in [0, 1], colours [N, 3]."""
    n = draw(st.integers(1, n_max))
    means = [draw(camera_points(K)) for _ in range(n)]
    quats = [draw(quats_wxyz()) for _ in range(n)]
    scales = [draw(scale_triplets()) for _ in range(n)]
    opac = [
        draw(st.one_of(st.sampled_from([0.0, 1.0, 1 / 255]), st.floats(0, 1))) for _ in range(n)
    ]
    colors = [draw(st.tuples(*[st.floats(0, 1)] * 3)) for _ in range(n)]
    return {
        "means_cam": np.array(means, np.float64),
        "quats": np.array(quats, np.float64),
        "scales": np.array(scales, np.float64),
        "opacities": np.array(opac, np.float64),
        "colors": np.array(colors, np.float64),
    }
