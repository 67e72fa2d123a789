"""Table 1 as one object: its column heads, its rows of cells (best values bold), the notes under it.

Built once from an EvalResult; the Markdown file (`markdown`) and the HTML page both render this
object, so they show the same cells and neither reads the other back.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

from admc.common.metrics import METRICS, NONFINITE_RULE
from admc.pipeline.evaluation.records import (
    BEST_PERCENT_RULE,
    FLOOR_COLUMN,
    FLOOR_ROW,
    FLOOR_RULE,
    EvalResult,
    TableRow,
)

TITLE = "Table 1: aggregate results over the test images"
NOT_APPLICABLE = "–"


@dataclass(frozen=True)
class Cell:
    text: str
    bold: bool = False


@dataclass(frozen=True)
class Note:
    """A paragraph under the table: a bold label (may be empty) and its text."""

    label: str
    text: str


@dataclass(frozen=True)
class Table1:
    head: list[str]
    rows: list[list[Cell]]
    notes: list[Note]

    def markdown(self) -> str:
        """The table and its notes as Markdown (bold as **x**), without the title."""
        lines = ["| " + " | ".join(self.head) + " |", "|" + "---|" * len(self.head)]
        lines += ["| " + " | ".join(f"**{c.text}**" if c.bold else c.text for c in row) + " |" for row in self.rows]
        for note in self.notes:
            lines += ["", f"**{note.label}** {note.text}" if note.label else note.text]
        return "\n".join(lines)


def build_table1(result: EvalResult) -> Table1:
    """Table 1 of an evaluation: per spp, one line per method and the references' floor."""
    head = (
        ["spp", "Denoiser"]
        + [f"{m.label} {'↓' if m.lower_is_better else '↑'} {part}" for m in METRICS for part in ("Avg.", "B.P.")]
        + [f"{FLOOR_COLUMN} ↓ Avg."]
    )
    rows = []
    for spp in sorted({row.spp for row in result.table}):
        rows += _spp_rows(spp, [row for row in result.table if row.spp == spp])
    return Table1(head, rows, _notes(result))


def _spp_rows(spp: int, rows: list[TableRow]) -> list[list[Cell]]:
    """The lines of one spp, best average and highest B.P. of each metric bold, then the floor line."""
    best = {m.key: (min if m.lower_is_better else max)(row.average[m.key] for row in rows) for m in METRICS}
    top = {m.key: max(row.best_percent[m.key] for row in rows) for m in METRICS}
    unbiased = min(row.relmse_minus_floor for row in rows)
    lines = []
    for i, row in enumerate(rows):
        cells = [Cell(str(spp) if i == 0 else ""), Cell(row.method)]
        for m in METRICS:
            cells.append(Cell(f"{row.average[m.key]:.4f}", row.average[m.key] == best[m.key]))
            cells.append(Cell(f"{row.best_percent[m.key]:.2f}%", row.best_percent[m.key] == top[m.key]))
        cells.append(Cell(f"{row.relmse_minus_floor:.4f}", row.relmse_minus_floor == unbiased))
        lines.append(cells)
    # every method at one spp is scored against the same references
    floors = {"relmse": rows[0].reference_floor, "one_minus_ssim": rows[0].ssim_floor}
    texts = ["", FLOOR_ROW] + [
        t
        for m in METRICS
        for t in ((f"{floors[m.key]:.4f}", NOT_APPLICABLE) if m.key in floors else (NOT_APPLICABLE,) * 2)
    ]
    lines.append([Cell(t) for t in texts + [NOT_APPLICABLE]])
    return lines


def _notes(result: EvalResult) -> list[Note]:
    counts = ", ".join(f"{spp} spp: {n}" for spp, n in sorted({(row.spp, row.n_images) for row in result.table}))
    notes = [
        Note("", f"Images per spp: {counts}. Best average and highest B.P. in bold."),
        Note("B.P.", BEST_PERCENT_RULE + " Shown rounded to 2 decimals."),
        Note(FLOOR_ROW, FLOOR_RULE),
        Note("Devices:", "; ".join(f"{name}: {dev}" for name, dev in result.devices.items())),
    ]
    if result.sources:
        notes.append(Note("Weights:", "; ".join(f"{name}: {path}" for name, path in result.sources.items())))
    if result.not_run:
        notes.append(Note("Not run:", "; ".join(f"{name}: {why}" for name, why in result.not_run.items())))
    notes.append(Note("Non-finite values", NONFINITE_RULE + " " + _nonfinite_summary(result)))
    return notes


def _nonfinite_summary(result: EvalResult) -> str:
    counts = defaultdict(int)
    for r in result.path_tracer:
        counts["noisy inputs"] += r.nonfinite
    for r in result.records:
        counts[r.method] += r.nonfinite
    return "Counted: " + ", ".join(f"{name} {n}" for name, n in counts.items()) + "."


def table1_markdown(table: Table1) -> str:
    """The whole table1.md file: title, the table with its notes, the metric definitions."""
    lines = [f"# {TITLE}", "", table.markdown(), "", "## Metric definitions", ""]
    for m in METRICS:
        lines += [f"**{m.label}**: " + " ".join(m.definition.split()), ""]
    return "\n".join(lines)
