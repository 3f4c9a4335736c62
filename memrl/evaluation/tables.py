"""Table III and the pairwise differences as markdown (for people) and CSV (for tools)."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

from memrl.evaluation.stats import COLUMNS, Cell, Difference, Row

LANE_NAMES = {"random": "random", "non_goal": "non-goal"}


def _num(x: float) -> str:
    return f"{x:.1f}".rstrip("0").rstrip(".") if abs(x - round(x)) < 1e-9 else f"{x:.1f}"


def fmt_cell(cell: Cell, confidence: float, per_unit: bool = True) -> str:
    """``53.5 [50, 57] (50, 57)``: mean, interval, per-unit values."""
    text = f"{cell.mean:.1f} [{_num(cell.low)}, {_num(cell.high)}]"
    if cell.over == "episodes":
        text += "\u2020"  # dagger: interval over episodes (one unit)
    if per_unit and len(cell.values) > 1:
        text += " (" + ", ".join(_num(v) for v in cell.values) + ")"
    return text


def column_name(column: tuple[str, str]) -> str:
    return f"{LANE_NAMES.get(column[0], column[0])} {column[1]}"


def markdown(rows: Sequence[Row], diffs: Sequence[Difference], confidence: float = 0.95,
             title: str = "Table III: survival and goal scores (per 100 episodes)") -> str:
    """The table, the differences and a plain-words verdict."""
    pct = f"{100 * confidence:g}%"
    cols = [c for c in COLUMNS if any(c in r.cells for r in rows)]
    lines = [f"### {title}", "",
             f"Mean over seeds [{pct} bootstrap interval] (per-seed values).",
             "", "| method | n | " + " | ".join(column_name(c) for c in cols) + " |",
             "|---|---|" + "---|" * len(cols)]
    for r in rows:
        cells = [fmt_cell(r.cells[c], confidence) if c in r.cells else "" for c in cols]
        lines.append(f"| {r.label} | {len(r.units)} | " + " | ".join(cells) + " |")
    lines += ["", "n: seeds (or people) per row. \u2020: a single unit; interval over its episodes."]
    if any(len(r.units) < 5 for r in rows if len(r.units) > 1):
        lines.append("With fewer than 5 seeds a percentile bootstrap interval is little more than "
                     "the range of the seeds (it undercovers); treat it as a lower bound on the spread.")
    if diffs:
        lines += ["", f"### Pairwise differences ({pct} bootstrap interval)", "",
                  "| comparison | column | difference | interval | excludes 0 |", "|---|---|---|---|---|"]
        for d in diffs:
            mark = "**yes**" if d.cell.excludes_zero() else "no"
            over = "\u2020" if d.cell.over == "episodes" else ""
            lines.append(f"| {d.a} \u2212 {d.b} | {column_name(d.column)} | {d.cell.mean:+.1f} | "
                         f"[{_num(d.cell.low)}, {_num(d.cell.high)}]{over} | {mark} |")
        lines += ["", verdict(diffs, pct)]
    return "\n".join(lines) + "\n"


def verdict(diffs: Sequence[Difference], pct: str) -> str:
    """One sentence per comparison: which columns' intervals exclude zero."""
    out = []
    for a, b in dict.fromkeys((d.a, d.b) for d in diffs):
        mine = [d for d in diffs if (d.a, d.b) == (a, b)]
        sure = [d for d in mine if d.cell.excludes_zero()]
        n = f"{a} vs {b} ({mine[0].n_a} vs {mine[0].n_b} units)"
        if sure:
            parts = ", ".join(f"{column_name(d.column)} {d.cell.mean:+.1f}" for d in sure)
            out.append(f"{n}: the {pct} interval excludes zero for {parts}.")
        else:
            out.append(f"{n}: no difference is distinguishable from zero at {pct}.")
    if any(min(d.n_a, d.n_b) < 5 and d.cell.over == "seeds" for d in diffs):
        out.append("With so few seeds these intervals are optimistic; more seeds, not more "
                   "evaluation episodes, would make them trustworthy.")
    return " ".join(out)


def write_csv(rows: Sequence[Row], diffs: Sequence[Difference], table_path: Path, diff_path: Path) -> None:
    """Long-format CSVs: one line per (row, column) and per (comparison, column)."""
    with table_path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["method", "n", "units", "initial_lane", "metric", "mean", "ci_low", "ci_high",
                    "ci_over", "values", "episodes"])
        for r in rows:
            for (lane, metric), c in r.cells.items():
                w.writerow([r.label, len(r.units), ";".join(r.units), lane, metric, round(c.mean, 4),
                            round(c.low, 4), round(c.high, 4), c.over,
                            ";".join(_num(v) for v in c.values), ";".join(map(str, c.episodes))])
    with diff_path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["a", "b", "n_a", "n_b", "initial_lane", "metric", "difference", "ci_low", "ci_high",
                    "ci_over", "excludes_zero"])
        for d in diffs:
            w.writerow([d.a, d.b, d.n_a, d.n_b, *d.column, round(d.cell.mean, 4), round(d.cell.low, 4),
                        round(d.cell.high, 4), d.cell.over, int(d.cell.excludes_zero())])
