"""A training run's progress: a live bar on a terminal, a plain line per log_every steps elsewhere, and
the averaged losses that go to metrics.csv and TensorBoard."""

from __future__ import annotations

import sys
import time
from collections import defaultdict

from tqdm import tqdm


class Averages:
    """Running means of the logged losses since the last log line."""

    def __init__(self) -> None:
        self.sums: dict[str, float] = defaultdict(float)
        self.counts: dict[str, int] = defaultdict(int)

    def add(self, prefix: str, values: dict[str, float]) -> None:
        for k, v in values.items():
            self.sums[f"{prefix}/{k}"] += v
            self.counts[f"{prefix}/{k}"] += 1

    def pop(self) -> dict[str, float]:
        out = {k: self.sums[k] / self.counts[k] for k in self.sums}
        self.sums.clear()
        self.counts.clear()
        return out


class ProgressWindow:
    """Progress and the logged averages over the steps since the last log line.

    A live bar only on a terminal; in a log file or CI output its carriage-return redraws are noise,
    so there the logged averages go out as one plain line every log_every steps instead."""

    def __init__(self, run, start: int):  # run: trainer._Run
        self.run = run
        self.live = run.progress and sys.stderr.isatty()
        self.bar = tqdm(
            total=run.settings.steps, initial=start, disable=not self.live, desc=run.stage, dynamic_ncols=True
        )
        self.averages = Averages()
        self.start, self.patches = time.perf_counter(), 0

    def step_done(self, done: int) -> None:
        run, settings = self.run, self.run.settings
        self.bar.update(1)
        if not run.ranks.lead or (done % settings.log_every and done != settings.steps):
            return
        values = self.averages.pop()
        values["patches_per_s"] = self.patches / max(time.perf_counter() - self.start, 1e-9)
        for b, trainer in run.trainers.items():
            values.update({f"{b}/{k}": v for k, v in trainer.learning_rates().items()})
            values[f"{b}/bad_steps"] = trainer.bad_total
        values["phase"] = ("l1", "critic", "adversarial").index(settings.phase(done - 1))
        run.metrics.log(done, values)
        self.bar.set_postfix(postfix(values), refresh=False)
        if run.progress and not self.live:
            line = " ".join(f"{k}={v}" for k, v in postfix(values).items())
            print(f"{run.stage} step {done}/{settings.steps}: {line}", file=sys.stderr, flush=True)
        self.start, self.patches = time.perf_counter(), 0

    def close(self) -> None:
        self.bar.close()


def postfix(values: dict[str, float]) -> dict[str, str]:
    short = {"l1": "l1", "wasserstein": "W", "gp": "gp"}
    out = {}
    for tag, value in values.items():
        branch, _, key = tag.partition("/")
        if key in short:
            out[f"{branch[0]}.{short[key]}"] = f"{value:.3g}"
    out["p/s"] = f"{values['patches_per_s']:.1f}"
    return out
