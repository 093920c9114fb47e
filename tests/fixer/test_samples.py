"""Frame samples for GSFixer's training set: spacing, motion gate, keyframes reset the count."""

from __future__ import annotations

import numpy as np

from gsfix_online.core.se3 import make_T
from gsfix_online.fixer.samples import SamplePolicy, step


def pose(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    return make_T(np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]), [x, 0.0, 0.0])


def test_every_nth_moving_frame_is_a_sample() -> None:
    pol = SamplePolicy(every=3, min_move_m=0.05, min_turn_deg=5.0)
    st = pol.initialize_state()
    taken = [step(pol, st, pose(0.1 * i), False) for i in range(10)]
    assert [i for i, t in enumerate(taken) if t] == [2, 5, 8]
    assert st.samples == 3


def test_a_still_camera_gives_no_samples_and_a_turn_counts_as_motion() -> None:
    pol = SamplePolicy(every=2, min_move_m=0.05, min_turn_deg=5.0)
    st = pol.initialize_state()
    assert step(pol, st, pose(0.0), False) is False
    assert step(pol, st, pose(0.0), False) is True  # the first sample: nothing to compare with
    assert not any(step(pol, st, pose(0.01), False) for _ in range(6))  # 1 cm: standing still
    assert step(pol, st, pose(0.01, yaw_deg=10.0), False) is True  # turned 10 degrees


def test_keyframes_are_not_samples_and_restart_the_spacing() -> None:
    pol = SamplePolicy(every=2, min_move_m=0.0, min_turn_deg=0.0)
    st = pol.initialize_state()
    got = [step(pol, st, pose(0.1 * i), i in (1, 4)) for i in range(7)]
    assert got == [False, False, False, True, False, False, True]


def test_every_zero_is_keyframes_only() -> None:
    pol = SamplePolicy(every=0)
    st = pol.initialize_state()
    assert not any(step(pol, st, pose(0.2 * i), False) for i in range(20))


def test_a_long_log_thins_out_instead_of_growing_without_bound() -> None:
    pol = SamplePolicy(every=1, min_move_m=0.0, min_turn_deg=0.0, max_samples=4)
    st = pol.initialize_state()
    taken = [i for i in range(60) if step(pol, st, pose(0.1 * i), False)]
    # 4 samples 1 apart, then 4 samples 2 apart, 4 samples 4 apart, then 8 apart
    assert taken[:12] == [0, 1, 2, 3, 5, 7, 9, 11, 15, 19, 23, 27]
    assert taken[12:] == [35, 43, 51, 59]
