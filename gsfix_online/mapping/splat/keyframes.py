"""Keyframe selection by novelty, and a bounded keyframe store that keeps coverage.

Selection (a frozen config plus explicit state, like gsplat's strategies)::

    state = initialize_state()
    for frame in frames:
        res = grow(frame, growth_cfg, alpha, rendered)
        decision = select_keyframe(frame, len(res), state, cfg, alpha=alpha)
        if decision.is_keyframe:
            store.add(frame, render, alpha, len(res))

A frame is a keyframe when it is the first, when growth added at least ``min_new_gaussians``
(GSFusion's rule, ``kf_thresh`` = 50), or when its overlap with the last keyframe is below
``min_overlap``. Overlap alone starves slow trajectories: a camera that creeps or turns in place
keeps seeing what its last keyframe saw, and a real 640x480 indoor log of 120 frames got 2
keyframes. Spacing rules therefore also make a keyframe of a frame ``max_interval_s`` after the
last keyframe, ``max_translation_m`` away from it or turned ``max_rotation_deg`` from it, and of
any frame while keyframes are fewer than ``min_share`` of the frames seen (each 0 = off).

The share rule is for slow paths: on a path of normal speed the overlap rule keeps enough
keyframes, and the share only adds cost. With ``share_below_step_m`` > 0 it applies while the
path so far is slow: the mean pose distance between consecutive frames (the store's distance
below) under that. The mean is over the whole path, as the share is over all frames seen: judged
since the last keyframe, a normal path's slow start and end (easing in and out) opened the rule,
and the deficit of its fast middle then made a keyframe of every frame there.

Overlap comes from reprojected depth (the share of the frame's valid depth samples that the last
keyframe saw at a consistent depth) or from the render's alpha (the share of the frame the map
already covers). A frame without valid depth has no depth overlap and is judged by its new
Gaussians alone.

The store holds at most ``capacity`` input keyframes and, apart from them, ``repaired_capacity``
repaired views (distillation's). Adding one more of a kind evicts the most redundant of that
kind: the keyframe (never the newest) whose pose is closest to another's of its kind, with
distance ``|t_i - t_j| + rotation_weight_m * angle(R_i^T R_j)``; ties evict the older. A repaired
view never evicts a frame the robot observed: in one store, each repaired view evicted the input
keyframe nearest it, the frame that would keep the view's fit from moving what was observed.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
import torch

from gsfix_online.core.config import rng
from gsfix_online.core.se3 import most_redundant, pose_distances
from gsfix_online.core.types import Intrinsics, RGBDFrame, make_frame
from gsfix_online.mapping.splat.growth import as_float32, unproject
from gsfix_online.mapping.splat.views import REPAIRED_FRAME_ID, resize

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
OverlapSource = Literal["depth", "alpha"]
Reason = Literal[
    "first", "new_gaussians", "low_overlap", "interval", "moved", "turned", "share", "none"
]


@dataclass(frozen=True)
class KeyframeConfig:
    """Keyframe selection and the keyframe store's size."""

    min_new_gaussians: int = field(
        default=50,
        metadata=rng(0, None, "a frame adding at least this many Gaussians is a keyframe"),
    )
    min_overlap: float = field(
        default=0.7,
        metadata=rng(0, 1, "overlap with the last keyframe below this makes a keyframe"),
    )
    overlap_from: OverlapSource = "depth"  # depth: reprojected depth; alpha: the render's alpha
    overlap_stride_px: int = field(
        default=4, metadata=rng(1, 64, "depth overlap sample stride, px")
    )
    depth_tolerance: float = field(
        default=0.05,
        metadata=rng(0, 1, "relative depth difference still counted as the same surface"),
    )
    alpha_thresh: float = field(
        default=0.5, metadata=rng(0, 1, "alpha overlap: covered pixel threshold")
    )
    max_interval_s: float = field(
        default=0.0, metadata=rng(0, None, "a frame this long after the last keyframe is one, s")
    )
    max_translation_m: float = field(
        default=0.0, metadata=rng(0, None, "a frame this far from the last keyframe is one, m")
    )
    max_rotation_deg: float = field(
        default=0.0, metadata=rng(0, 180, "a frame turned this far from the last keyframe is one")
    )
    min_share: float = field(
        default=0.0, metadata=rng(0, 1, "keyframes fewer than this share of the frames: a keyframe")
    )
    share_below_step_m: float = field(
        default=0.0,
        metadata=rng(0, None, "min_share only while the path's mean pose distance per frame is "
                     "below this, m; 0 = always"),
    )  # fmt: skip
    capacity: int = field(default=64, metadata=rng(2, 100_000, "input keyframes kept in the store"))
    repaired_capacity: int = field(
        default=64, metadata=rng(2, 100_000, "repaired views kept in the store, apart from them")
    )
    rotation_weight_m: float = field(
        default=0.5, metadata=rng(0, None, "pose distance: metres per radian of rotation")
    )


@dataclass
class KeyframeState:
    """What selection remembers between frames."""

    last_keyframe: RGBDFrame | None = None
    n_frames: int = 0
    n_keyframes: int = 0
    path_m: float = 0.0  # pose distance between consecutive frames, summed over the frames seen
    last_T_world_cam: F64 | None = None  # [4, 4] the pose of the last frame seen


@dataclass(frozen=True)
class KeyframeDecision:
    is_keyframe: bool
    reason: Reason
    overlap: float  # with the last keyframe (depth) or the map (alpha); NaN when not measured
    n_new_gaussians: int


# ----------------------------------------------------------------------------------------------
# Pure math
# ----------------------------------------------------------------------------------------------


def depth_overlap(
    frame: RGBDFrame,
    ref: RGBDFrame,
    stride_px: int = 4,
    depth_tolerance: float = 0.05,
) -> float:
    """Share of ``frame``'s valid depth samples that ``ref`` sees at a consistent depth; NaN if none."""
    # 1. Valid depth samples of the new frame, unprojected to the world
    v, u = np.mgrid[0 : frame.height : stride_px, 0 : frame.width : stride_px]
    z = frame.depth[v, u].astype(np.float64)
    ok = np.isfinite(z) & (z > 0)
    if not ok.any():
        return math.nan
    pw = unproject(
        u[ok].astype(np.float64),
        v[ok].astype(np.float64),
        z[ok],
        frame.intrinsics.K,
        frame.T_world_cam,
    )
    # 2. Into the reference camera, projected to its nearest pixel
    T_ref_world = np.linalg.inv(ref.T_world_cam)
    pc = pw @ T_ref_world[:3, :3].T + T_ref_world[:3, 3]
    K = ref.intrinsics.K
    zc = pc[:, 2]
    in_front = zc > 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        ur = np.rint(K[0, 0] * pc[:, 0] / zc + K[0, 2])
        vr = np.rint(K[1, 1] * pc[:, 1] / zc + K[1, 2])
    inside = in_front & (ur >= 0) & (ur < ref.width) & (vr >= 0) & (vr < ref.height)
    # 3. The same surface: the reference depth there agrees within the tolerance
    zr = np.zeros_like(zc)
    zr[inside] = ref.depth[vr[inside].astype(int), ur[inside].astype(int)]
    same = inside & (zr > 0) & (np.abs(zr - zc) <= depth_tolerance * zr)
    return float(np.count_nonzero(same) / len(zc))


def alpha_overlap(alpha: F32, alpha_thresh: float = 0.5) -> float:  # alpha [H, W]
    """Share of pixels the map already covers (render alpha at least ``alpha_thresh``)."""
    return float(np.count_nonzero(alpha >= alpha_thresh) / alpha.size)


def frame_to_dict(frame: RGBDFrame) -> dict[str, Any]:
    """A frame as tensors and plain values (snapshots); :func:`frame_from_dict` inverts it."""
    return {
        "color": torch.from_numpy(frame.color.copy()),
        "depth": torch.from_numpy(frame.depth.copy()),
        "K": torch.from_numpy(frame.intrinsics.K),
        "T_world_cam": torch.from_numpy(frame.T_world_cam.copy()),
        "stamp_ns": frame.stamp_ns,
        "frame_id": frame.frame_id,
        "seq": frame.seq,
    }


def frame_from_dict(d: dict[str, Any]) -> RGBDFrame:
    depth = d["depth"].numpy()
    K = Intrinsics.from_K(d["K"].numpy(), width=depth.shape[1], height=depth.shape[0])
    return make_frame(
        d["color"].numpy(),
        depth,
        K,
        d["T_world_cam"].numpy(),
        d["stamp_ns"],
        d["frame_id"],
        d["seq"],
    )


def _check_alpha(alpha: Any, frame: RGBDFrame) -> F32:
    a = as_float32(alpha, "alpha")
    if a.shape != (frame.height, frame.width):
        raise ValueError(f"alpha must be [{frame.height}, {frame.width}], got {list(a.shape)}")
    return a


# ----------------------------------------------------------------------------------------------
# Selection policy
# ----------------------------------------------------------------------------------------------


def initialize_state() -> KeyframeState:
    return KeyframeState()


def select_keyframe(
    frame: RGBDFrame,
    n_new_gaussians: int,
    state: KeyframeState,
    cfg: KeyframeConfig,
    alpha: Any = None,  # [H, W] render alpha at the frame's pose before growth; needed for "alpha"
) -> KeyframeDecision:
    """Decide whether ``frame`` is a keyframe; updates ``state`` in place."""
    if not isinstance(frame, RGBDFrame):
        raise TypeError(f"frame must be an RGBDFrame, got {type(frame).__name__}")
    if (
        isinstance(n_new_gaussians, bool)
        or not isinstance(n_new_gaussians, (int, np.integer))
        or n_new_gaussians < 0
    ):
        raise ValueError(f"n_new_gaussians must be a non-negative int, got {n_new_gaussians!r}")
    n_new = int(n_new_gaussians)
    overlap = math.nan
    if cfg.overlap_from == "alpha":
        if alpha is None:
            raise ValueError("overlap_from is 'alpha' but no alpha was given")
        overlap = alpha_overlap(_check_alpha(alpha, frame), cfg.alpha_thresh)
    elif state.last_keyframe is not None:
        overlap = depth_overlap(
            frame, state.last_keyframe, cfg.overlap_stride_px, cfg.depth_tolerance
        )

    if state.last_T_world_cam is not None:
        state.path_m += float(
            pose_distances(state.last_T_world_cam, frame.T_world_cam, cfg.rotation_weight_m)[0, 0]
        )
    state.last_T_world_cam = frame.T_world_cam

    reason: Reason = "none"
    if state.last_keyframe is None:
        reason = "first"
    elif n_new >= cfg.min_new_gaussians and cfg.min_new_gaussians > 0:
        reason = "new_gaussians"
    elif overlap < cfg.min_overlap:  # False for NaN
        reason = "low_overlap"
    else:
        reason = _spacing(frame, state, cfg)
    state.n_frames += 1
    if reason != "none":
        state.last_keyframe = frame
        state.n_keyframes += 1
    return KeyframeDecision(reason != "none", reason, overlap, n_new)


def _spacing(frame: RGBDFrame, state: KeyframeState, cfg: KeyframeConfig) -> Reason:
    """The spacing rules' reason for a keyframe (time, translation, rotation, share), or none."""
    last = state.last_keyframe
    assert last is not None
    if cfg.max_interval_s > 0 and frame.stamp_ns - last.stamp_ns >= cfg.max_interval_s * 1e9:
        return "interval"
    if cfg.max_translation_m > 0:
        moved = np.linalg.norm(frame.T_world_cam[:3, 3] - last.T_world_cam[:3, 3])
        if moved >= cfg.max_translation_m:
            return "moved"
    if cfg.max_rotation_deg > 0:
        R = last.T_world_cam[:3, :3].T @ frame.T_world_cam[:3, :3]
        angle = math.degrees(math.acos(float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
        if angle >= cfg.max_rotation_deg:
            return "turned"
    slow = cfg.share_below_step_m <= 0 or mean_step_m(state) < cfg.share_below_step_m
    if cfg.min_share > 0 and slow and state.n_keyframes < cfg.min_share * (state.n_frames + 1):
        return "share"
    return "none"


def mean_step_m(state: KeyframeState) -> float:
    """Mean pose distance between consecutive frames over the path so far (the frame being judged
    included, not yet counted in ``n_frames``), metres; 0 before a second frame."""
    return state.path_m / state.n_frames if state.n_frames else 0.0


# ----------------------------------------------------------------------------------------------
# Store
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Keyframe:
    """A keyframe as GSFixer fine-tuning and replay need it."""

    kf_id: int  # increasing, never reused
    frame: RGBDFrame  # colour, depth, pose, intrinsics, stamp
    render: F32 | None  # [H, W, C] Gaussian render at the pose, colour in [0, 1]
    alpha: F32 | None  # [H, W] its alpha
    n_new_gaussians: int = 0
    # [h, w, C + 1] what the map rendered at the pose before the frame changed it, colour then
    # alpha, at the training resolution (the render growth compared the frame against,
    # Mapper.process): the keyframe's render GSFixer trains on under keyframe_render "before",
    # kept so that a node resumed from a snapshot announces the keyframe again as it first did
    prior: F32 | None = None


def prior_images(
    kf: Keyframe, height: int, width: int
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]] | None:
    """``kf.prior`` at ``height`` x ``width``, bilinear: colour [H, W, C] in [0, 1] and alpha
    [H, W]; None when the keyframe has none (restored from a snapshot that kept none)."""
    if kf.prior is None:
        return None
    both = resize(torch.from_numpy(kf.prior), height, width)
    return np.ascontiguousarray(both[..., :-1]), np.ascontiguousarray(both[..., -1])


class KeyframeStore:
    """At most ``capacity`` input keyframes and ``repaired_capacity`` repaired views; adding
    beyond either evicts the most redundant one of that kind (module doc)."""

    def __init__(self, capacity: int, rotation_weight_m: float = 0.5, repaired_capacity: int = 64):
        for name, n in (("capacity", capacity), ("repaired_capacity", repaired_capacity)):
            if isinstance(n, bool) or not isinstance(n, int) or n < 2:
                raise ValueError(f"{name} must be an int >= 2, got {n!r}")
        self.capacity = capacity
        self.repaired_capacity = repaired_capacity
        self.rotation_weight_m = float(rotation_weight_m)
        self._items: list[Keyframe] = []  # oldest first
        self._next_id = 0
        self.n_evicted = 0

    @classmethod
    def from_config(cls, cfg: KeyframeConfig) -> KeyframeStore:
        return cls(cfg.capacity, cfg.rotation_weight_m, cfg.repaired_capacity)

    def __len__(self) -> int:
        return len(self._items)

    def __iter__(self) -> Iterator[Keyframe]:
        return iter(list(self._items))

    def __getitem__(self, kf_id: int) -> Keyframe:
        for kf in self._items:
            if kf.kf_id == kf_id:
                return kf
        raise KeyError(f"no keyframe {kf_id} in the store (ids {[k.kf_id for k in self._items]})")

    @property
    def ids(self) -> list[int]:
        return [kf.kf_id for kf in self._items]

    @property
    def latest(self) -> Keyframe | None:
        return self._items[-1] if self._items else None

    def add(
        self,
        frame: RGBDFrame,
        render: Any = None,  # [H, W, C] in [0, 1], numpy or torch
        alpha: Any = None,  # [H, W]
        n_new_gaussians: int = 0,
    ) -> tuple[Keyframe, Keyframe | None]:
        """Store ``frame`` as the newest keyframe; returns it and the evicted keyframe, if any."""
        if not isinstance(frame, RGBDFrame):
            raise TypeError(f"frame must be an RGBDFrame, got {type(frame).__name__}")
        render_np, alpha_np = self._check_render(frame, render, alpha)
        kf = Keyframe(self._next_id, frame, render_np, alpha_np, int(n_new_gaussians))
        self._next_id += 1
        self._items.append(kf)
        repaired = frame.frame_id == REPAIRED_FRAME_ID
        kind = [
            i
            for i, k in enumerate(self._items)
            if (k.frame.frame_id == REPAIRED_FRAME_ID) == repaired
        ]
        evicted = None
        if len(kind) > (self.repaired_capacity if repaired else self.capacity):
            evicted = self._items.pop(kind[self._most_redundant(kind)])
            self.n_evicted += 1
        return kf, evicted

    def remove(self, kf_id: int) -> Keyframe:
        """Take keyframe ``kf_id`` out of the store (ids are never reused); returns it."""
        kf = self[kf_id]
        self._items.remove(kf)
        return kf

    def update_render(self, kf_id: int, render: Any, alpha: Any) -> Keyframe:
        """Replace a keyframe's render and alpha (the map changed since it was stored)."""
        old = self[kf_id]
        render_np, alpha_np = self._check_render(old.frame, render, alpha)
        return self._replace(old, render=render_np, alpha=alpha_np)

    def set_prior(self, kf_id: int, prior: Any) -> Keyframe:
        """Keep the map's render before keyframe ``kf_id`` changed it (``Keyframe.prior``:
        [h, w, C + 1], colour in [0, 1] then alpha, at any resolution)."""
        old = self[kf_id]
        p = as_float32(prior, "prior")
        c = 1 if old.frame.is_gray else 3
        if p.ndim != 3 or p.shape[2] != c + 1:
            raise ValueError(f"prior must be [h, w, {c + 1}] (colour, alpha), got {list(p.shape)}")
        return self._replace(old, prior=p.copy())

    def _replace(self, old: Keyframe, **changes: Any) -> Keyframe:
        new = dataclasses.replace(old, **changes)
        self._items[self._items.index(old)] = new
        return new

    def sample(
        self, n: int, rng: np.random.Generator, exclude_latest: bool = True
    ) -> list[Keyframe]:
        """Up to ``n`` distinct random keyframes (for replay), oldest first."""
        pool = self._items[:-1] if exclude_latest else self._items
        if n <= 0 or not pool:
            return []
        idx = np.sort(rng.choice(len(pool), size=min(n, len(pool)), replace=False))
        return [pool[i] for i in idx]

    def state_dict(self) -> dict[str, Any]:
        """The store as tensors and plain values (for ``torch.save`` with ``weights_only``)."""
        return {
            "capacity": self.capacity,
            "repaired_capacity": self.repaired_capacity,
            "rotation_weight_m": self.rotation_weight_m,
            "next_id": self._next_id,
            "n_evicted": self.n_evicted,
            "items": [
                {
                    "kf_id": kf.kf_id,
                    "frame": frame_to_dict(kf.frame),
                    "render": None if kf.render is None else torch.from_numpy(kf.render.copy()),
                    "alpha": None if kf.alpha is None else torch.from_numpy(kf.alpha.copy()),
                    "n_new_gaussians": kf.n_new_gaussians,
                    "prior": None if kf.prior is None else torch.from_numpy(kf.prior.copy()),
                }
                for kf in self._items
            ],
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> KeyframeStore:
        # snapshots before 2026-12-01 have no repaired_capacity: the default
        store = cls(int(state["capacity"]), float(state["rotation_weight_m"]),
                    int(state.get("repaired_capacity", 64)))  # fmt: skip
        store._next_id, store.n_evicted = int(state["next_id"]), int(state["n_evicted"])
        for item in state["items"]:
            render = None if item["render"] is None else item["render"].numpy()
            alpha = None if item["alpha"] is None else item["alpha"].numpy()
            frame = frame_from_dict(item["frame"])
            prior = item.get("prior")  # snapshots before 2026-11-30 have none
            store._items.append(
                Keyframe(
                    item["kf_id"],
                    frame,
                    render,
                    alpha,
                    int(item["n_new_gaussians"]),
                    None if prior is None else prior.numpy(),
                )
            )
        return store

    def _most_redundant(self, idx: list[int]) -> int:  # a position in idx (store positions)
        poses = np.stack([self._items[i].frame.T_world_cam for i in idx])
        return most_redundant(poses, self.rotation_weight_m)

    @staticmethod
    def _check_render(frame: RGBDFrame, render: Any, alpha: Any) -> tuple[F32 | None, F32 | None]:
        if (render is None) != (alpha is None):
            raise ValueError("render and alpha must be given together")
        if render is None:
            return None, None
        c = 1 if frame.is_gray else 3
        r = as_float32(render, "render")
        if r.shape != (frame.height, frame.width, c):
            raise ValueError(
                f"render must be [{frame.height}, {frame.width}, {c}], got {list(r.shape)}"
            )
        return r.copy(), _check_alpha(alpha, frame).copy()
