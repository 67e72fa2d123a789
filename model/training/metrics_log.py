"""Training metrics to a CSV file (long format: step, tag, value) and TensorBoard event files.

On resume, rows and events after the resumed step (written by the interrupted run after its last
checkpoint) are dropped, so the logs read as one uninterrupted run.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

from torch.utils.tensorboard import SummaryWriter

from admc.stores.atomic import publishing

CSV_NAME = "metrics.csv"
TENSORBOARD_DIR = "tensorboard"
HEADER = ["step", "tag", "value"]


class MetricsLog:
    def __init__(self, out_dir: Path, resume_step: int | None = None):
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        self.csv_path = out_dir / CSV_NAME
        if resume_step is not None and self.csv_path.is_file():
            self._truncate(resume_step)
        else:
            with publishing(self.csv_path) as tmp:
                tmp.write_text(",".join(HEADER) + "\n")
        self._file = self.csv_path.open("a", newline="")
        self._csv = csv.writer(self._file)
        self.writer = SummaryWriter(str(out_dir / TENSORBOARD_DIR), purge_step=resume_step)

    def _truncate(self, step: int) -> None:
        with self.csv_path.open(newline="") as f:
            rows = [r for r in csv.reader(f)][1:]
        kept = [r for r in rows if len(r) == 3 and r[0].isdigit() and int(r[0]) <= step]
        with publishing(self.csv_path) as tmp, tmp.open("w", newline="") as f:
            csv.writer(f).writerows([HEADER, *kept])

    def log(self, step: int, values: dict[str, float]) -> None:
        for tag, value in values.items():
            self._csv.writerow([step, tag, repr(float(value))])
            if math.isfinite(value):
                self.writer.add_scalar(tag, value, step)
        self._file.flush()

    def close(self) -> None:
        self._file.close()
        self.writer.close()
