"""The real frames a node keeps to warp into views (:mod:`.ref_warp`): the splat node's keyframes
and frame samples, as their messages carry them (colour, depth, intrinsics, pose).

A :class:`ReferenceStore` holds at most ``capacity`` of them; one more evicts the most redundant
(the one whose pose is nearest another's, as the keyframe store does), never the newest. A
frame with an id already held replaces it (a resent message). :meth:`ReferenceStore.warp` is
the reference warp of a view from the store; :func:`warp_arrays` reads one back from the
message that carries it (the planner's ``decision/<planner>/ref``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from gsfix_online.core.se3 import most_redundant
from gsfix_online.repair.ref_warp import Reference, RefWarp, RefWarpConfig, ref_warp

ROTATION_WEIGHT_M = 0.5  # eviction: metres a radian of rotation counts, as KeyframeConfig's


def reference_from_arrays(arrays: Mapping[str, Any]) -> Reference:
    """A reference from a keyframe message's arrays (``color``, ``depth``, ``K``,
    ``T_world_cam``); ValueError naming a missing array."""
    missing = [k for k in ("color", "depth", "K", "T_world_cam") if k not in arrays]
    if missing:
        raise ValueError(f"a reference frame needs arrays {missing}, got {sorted(arrays)}")
    return Reference(
        np.ascontiguousarray(arrays["color"], np.uint8),
        np.ascontiguousarray(arrays["depth"], np.float32),
        np.asarray(arrays["K"], np.float64),
        np.asarray(arrays["T_world_cam"], np.float64),
    )


class ReferenceStore:
    """At most ``capacity`` reference frames by id (see the module doc)."""

    def __init__(self, capacity: int = 200) -> None:
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
            raise ValueError(f"capacity must be an int >= 1, got {capacity!r}")
        self.capacity = capacity
        self._refs: dict[int, Reference] = {}  # insertion order: oldest first
        self.n_evicted = 0

    def __len__(self) -> int:
        return len(self._refs)

    @property
    def refs(self) -> list[Reference]:
        return list(self._refs.values())

    def add(self, ref_id: int, ref: Reference) -> None:
        self._refs.pop(ref_id, None)
        self._refs[ref_id] = ref
        if len(self._refs) > self.capacity:
            ids = list(self._refs)
            poses = np.stack([self._refs[i].T_world_cam for i in ids])
            del self._refs[ids[most_redundant(poses, ROTATION_WEIGHT_M)]]
            self.n_evicted += 1

    def warp(
        self,
        K: npt.ArrayLike,  # [3, 3]
        T_world_cam: npt.ArrayLike,  # [4, 4]
        depth: npt.NDArray[np.floating],  # [H, W] the view's mesh depth, metres; 0 = none
        valid: npt.NDArray[np.bool_],  # [H, W] the mesh hit a surface
        cfg: RefWarpConfig,
    ) -> RefWarp | None:
        """The view's reference warp; None while the store is empty."""
        if not self._refs:
            return None
        h, w = np.shape(depth)
        return ref_warp(K, T_world_cam, np.asarray(depth, np.float32), np.asarray(valid, bool),
                        int(w), int(h), self.refs, cfg)  # fmt: skip


def warp_arrays(
    arrays: Mapping[str, Any] | None,  # a ``decision/<planner>/ref`` message's: color, alpha
) -> tuple[npt.NDArray[np.uint8] | None, npt.NDArray[np.bool_] | None]:
    """(image, valid) of a view's reference warp as a message carries it; (None, None) for
    none, as :func:`~gsfix_online.repair.fallback.baseline_candidates` takes them."""
    if arrays is None:
        return None, None
    return np.asarray(arrays["color"], np.uint8), np.asarray(arrays["alpha"]) > 0.5
