"""Which input frames become GSFixer training triplets, beside the mapping keyframes.

The mapping keyframe policy picks frames for the Gaussian map (view overlap), and on a slow or
short trajectory it may pick very few: a real 120-frame indoor log gave 2, too few to fine-tune
on. GSFixer's training set therefore also draws *frame samples* from the input itself: every
``every``-th frame, as long as the camera moved at least ``min_move_m`` or turned at least
``min_turn_deg`` since the last sample (a robot standing still adds nothing new). Keyframes
count as samples, so the two sets do not crowd the same poses. On a long log the spacing
doubles after every ``max_samples`` samples, so the set (and the trainer's memory) grows with
the logarithm of the length, not the length.

Policy in the house style: frozen parameters, explicit state, a pure ``step``; no IO, no clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from gsfix_online.core.config import rng

# Frame samples get training ids from here on, so they never collide with mapping keyframe ids.
FRAME_SAMPLE_ID0 = 100_000_000


@dataclass(frozen=True)
class SamplePolicy:
    """Parameters of the frame sampler (``every`` 0 turns it off: keyframes only)."""

    every: int = field(
        default=4, metadata=rng(0, 100_000, "frames between samples; 0 = keyframes only")
    )
    min_move_m: float = field(
        default=0.05, metadata=rng(0, None, "camera travel since the last sample, m")
    )
    min_turn_deg: float = field(
        default=5.0, metadata=rng(0, 180, "or camera rotation since the last sample, degrees")
    )
    max_samples: int = field(
        default=64, metadata=rng(1, None, "samples after which the spacing doubles (again)")
    )

    def initialize_state(self) -> SampleState:
        return SampleState()


@dataclass
class SampleState:
    frames: int = 0  # frames seen
    since_last: int = 0  # frames since the last sample (or keyframe)
    last_pose: npt.NDArray[np.float64] | None = None  # [4, 4] T_world_cam of the last sample
    samples: int = 0  # frame samples taken (keyframes not counted)


def _moved(a: npt.NDArray[np.float64], b: npt.NDArray[np.float64]) -> tuple[float, float]:
    """(translation m, rotation deg) between two camera poses."""
    dt = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
    c = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
    return dt, math.degrees(math.acos(float(np.clip(c, -1.0, 1.0))))


def step(
    policy: SamplePolicy,
    state: SampleState,
    T_world_cam: npt.NDArray[np.float64],  # [4, 4]
    is_keyframe: bool,
) -> bool:
    """Record one mapped frame; True if it should become a frame sample (never a keyframe,
    which is sent as a keyframe already)."""
    state.frames += 1
    state.since_last += 1
    T = np.asarray(T_world_cam, np.float64)
    if is_keyframe:
        state.since_last, state.last_pose = 0, T
        return False
    every = policy.every * 2 ** (state.samples // policy.max_samples)
    if policy.every == 0 or state.since_last < every:
        return False
    if state.last_pose is not None:
        dt, dr = _moved(state.last_pose, T)
        if dt < policy.min_move_m and dr < policy.min_turn_deg:
            return False
    state.since_last, state.last_pose = 0, T
    state.samples += 1
    return True
