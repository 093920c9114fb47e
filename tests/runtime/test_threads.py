"""The thread tuner: it keeps the count whose steps measured faster, and follows a change."""

from __future__ import annotations

import pytest

from gsfix_online.runtime.threads import ThreadTuner


def drive(tuner: ThreadTuner, seconds: dict[int, float], steps: int) -> list[int]:
    """Run ``steps`` steps that take ``seconds[threads]`` each; the counts used."""
    used = []
    for _ in range(steps):
        n = tuner.next()
        used.append(n)
        tuner.record(seconds[n])
    return used


def test_it_times_each_count_then_keeps_the_faster_and_sets_it_only_on_a_change() -> None:
    calls: list[int] = []
    tuner = ThreadTuner((1, 2), trial=3, hold=10, set_threads=calls.append)
    used = drive(tuner, {1: 0.6, 2: 0.35}, 6 + 10)
    assert used[:6] == [1, 1, 1, 2, 2, 2]  # the trial
    assert used[6:] == [2] * 10  # then the faster, held
    assert tuner.chosen == 2 and tuner.medians == {1: 0.6, 2: 0.35}
    assert calls == [1, 2]  # torch is told only when the count changes


def test_on_busy_cores_it_keeps_one_thread_and_returns_to_two_when_they_are_free() -> None:
    tuner = ThreadTuner((1, 2), trial=3, hold=5, set_threads=lambda n: None)
    drive(tuner, {1: 0.6, 2: 8.0}, 6)  # two threads beside busy processes: barriers wait
    assert tuner.chosen == 1
    assert drive(tuner, {1: 0.6, 2: 8.0}, 5) == [1] * 5
    drive(tuner, {1: 0.6, 2: 0.35}, 6)  # the next trial, the other processes gone
    assert tuner.chosen == 2 and tuner.trials == 2


def test_other_work_between_steps_gets_the_chosen_count_not_the_trial_s() -> None:
    calls: list[int] = []
    tuner = ThreadTuner((1, 2), trial=3, hold=5, set_threads=calls.append)
    drive(tuner, {1: 0.3, 2: 5.0}, 6)  # 1 chosen
    drive(tuner, {1: 0.3, 2: 5.0}, 5 + 4)  # held, then the next trial: now on 2 threads
    assert tuner.current == 2
    assert tuner.settle() == 1 and tuner.current == 1 and calls[-1] == 1
    assert tuner.next() == 2  # the trial goes on (a switch: its first step is not timed)


def test_a_switch_s_first_step_is_not_timed() -> None:
    tuner = ThreadTuner((1, 2), trial=3, hold=5, set_threads=lambda n: None)
    times = iter([9.0, 0.5, 0.5, 9.0, 0.3, 0.3])  # each count's first step pays the pool resize
    for _ in range(6):
        tuner.next()
        tuner.record(next(times))
    assert tuner.medians == {1: 0.5, 2: 0.3}


@pytest.mark.parametrize(("counts", "trial", "hold"), [((), 3, 5), ((0, 2), 3, 5), ((1, 2), 1, 5)])
def test_bad_settings_are_refused(counts: tuple[int, ...], trial: int, hold: int) -> None:
    with pytest.raises(ValueError, match="must be"):
        ThreadTuner(counts, trial=trial, hold=hold, set_threads=lambda n: None)
