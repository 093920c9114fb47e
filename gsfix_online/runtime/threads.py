"""Torch's thread count for a loop of like steps, chosen by their measured wall time.

Two threads make a CPU rasterizer step of the Gaussian map 1.75x faster on idle cores, and many
times slower on busy ones: OpenMP's barriers wait for the thread the scheduler has paused (a
distillation that took 4 s on one thread took 81 s on two beside two other busy processes;
benchmarks/results/demo_5min_cpu.md). Whether the cores are free changes within a run (the
other nodes of a graph work in bursts, and a robot's computer runs other programs), so the
count is measured, not configured: :class:`ThreadTuner` times a few steps at each candidate
count in turn, keeps the fastest for a while, then times them again.
"""

from __future__ import annotations

import statistics
from collections.abc import Callable, Sequence


def _set_torch_threads(n: int) -> None:
    import torch

    torch.set_num_threads(n)


class ThreadTuner:
    """Chooses among ``counts`` threads for repeated steps of similar cost.

    Call :meth:`next` before a step (it sets the count and returns it) and :meth:`record` with
    the step's wall seconds after it. A trial times ``trial`` steps at each count (the first
    after a switch is not counted: the thread pool resizes); the fastest by median is then kept
    for ``hold`` steps, after which the next trial starts."""

    def __init__(
        self,
        counts: Sequence[int],
        trial: int = 4,
        hold: int = 40,
        set_threads: Callable[[int], None] = _set_torch_threads,
    ) -> None:
        if not counts or min(counts) < 1:
            raise ValueError(f"thread counts must be >= 1, got {list(counts)}")
        if trial < 2 or hold < 0:
            raise ValueError(f"trial must be >= 2 and hold >= 0, got {trial} and {hold}")
        self.counts = list(dict.fromkeys(counts))
        self.trial, self.hold = trial, hold
        self._set = set_threads
        self.current = 0  # the count the threads are set to (0: not set yet)
        self.chosen = self.counts[0]
        self.trials = 0  # trials completed
        self.medians: dict[int, float] = {}  # seconds per step at each count, last trial
        self._plan: list[int] = []  # the counts of the steps still to time in this trial
        self._times: dict[int, list[float]] = {}
        self._held = 0
        self._timing: int | None = None  # the count of the step under way, when it is timed
        self._start_trial()

    def _start_trial(self) -> None:
        self._plan = [c for c in self.counts for _ in range(self.trial)]
        self._times = {c: [] for c in self.counts}

    def next(self) -> int:
        """The thread count for the next step (already set)."""
        if self._plan:
            n = self._plan.pop(0)
            self._timing = n if n == self.current else None  # a switch's first step: warm-up
        else:
            n, self._timing = self.chosen, None
            self._held += 1
        if n != self.current:
            self._set(n)
            self.current = n
        return n

    def settle(self) -> int:
        """Set the chosen count for other work between steps (a trial's count may be the slow
        one); the trial goes on with the next step."""
        if self.chosen != self.current:
            self._set(self.chosen)
            self.current = self.chosen
        return self.chosen

    def record(self, seconds: float) -> None:
        """The wall seconds of the step :meth:`next` was called for."""
        if self._timing is not None:
            self._times[self._timing].append(seconds)
            self._timing = None
        if not self._plan and self._times:  # the trial's last step
            timed = {c: statistics.median(t) for c, t in self._times.items() if t}
            if timed:
                self.medians = timed
                self.chosen = min(timed, key=lambda c: (timed[c], c))
            self.trials += 1
            self._times, self._held = {}, 0
        elif not self._plan and self._held >= self.hold:
            self._start_trial()
