"""The wall-clock budgets of a fine-tune (train.minutes, train.oidn_minutes), counted across resumes."""

from __future__ import annotations

import time


class Clock:
    """The wall-clock time a phase has trained, across resumes (`before`: the checkpoint's), against its
    budget in minutes (0: none). Counting starts when the clock is made, so loading the store and the start's
    validation count too: the budget is what the user waits for."""

    def __init__(self, minutes: float, before: float = 0.0) -> None:
        self.budget = 60.0 * minutes
        self.before = before
        self.started = time.perf_counter()

    def seconds(self) -> float:
        return self.before + time.perf_counter() - self.started

    def spent(self) -> bool:
        return self.budget > 0 and self.seconds() >= self.budget

    def spent_before(self) -> bool:
        """The budget was spent by the steps a resumed checkpoint holds (a fresh run takes one step at least)."""
        return self.budget > 0 and self.before >= self.budget
