"""Table III (mean and IQM with intervals) and the pairwise comparisons (difference, P(a > b)) as
markdown (for people) and CSV (for tools)."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

from memrl.evaluation.stats import ALL, COLUMNS, Cell, Difference, Row

LANE_NAMES = {"random": "random", "non_goal": "non-goal"}

PAPER_TABLE3: dict[str, dict[tuple[str, str], float]] = {
    "Default": {("random", "survival"): 53, ("random", "goal"): 50,
                ("non_goal", "survival"): 33, ("non_goal", "goal"): 29},
    "A": {("random", "survival"): 49, ("random", "goal"): 37,
          ("non_goal", "survival"): 37, ("non_goal", "goal"): 10},
    "B": {("random", "survival"): 67, ("random", "goal"): 66,
          ("non_goal", "survival"): 51, ("non_goal", "goal"): 48},
    "human": {("random", "survival"): 50.7, ("random", "goal"): 50.3},
}
"""The paper's Table III (per 100 episodes), by row and column: survival / goal from random
starts, then from non-goal starts (Default 53/50 and 33/29: the issue's "Default 33/29
survival/goal from non-goal starts"); the people drove random starts only. Constant-speed
traffic: rows of other traffic (``B (learned)``) have no paper value."""


def paper_value(row: str, column: tuple[str, str]) -> float | None:
    """The paper's number for a row (its name: Default, A, B, human) and column, if any."""
    return PAPER_TABLE3.get(row, {}).get(column)


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


def fmt_iqm(cell: Cell) -> str:
    """``53.0 [50, 57]``: IQM and its interval."""
    if cell.iqm is None or cell.iqm_low is None or cell.iqm_high is None:
        return ""
    return f"{cell.iqm:.1f} [{_num(cell.iqm_low)}, {_num(cell.iqm_high)}]" + \
        ("\u2020" if cell.over == "episodes" else "")


def fmt_p(d: Difference) -> str:
    """``0.83 [0.5, 1]``: P(a > b) and its interval; an em dash when not defined."""
    if d.p_improvement is None or d.p_low is None or d.p_high is None:
        return "\u2014"
    return f"{d.p_improvement:.2f} [{d.p_low:.2g}, {d.p_high:.2g}]"


def column_name(column: tuple[str, str]) -> str:
    return f"{LANE_NAMES.get(column[0], column[0])} {column[1]}"


def markdown(rows: Sequence[Row], diffs: Sequence[Difference], confidence: float = 0.95,
             title: str = "Table III: survival and goal scores (per 100 episodes)") -> str:
    """The table, the differences and a plain-words verdict."""
    pct = f"{100 * confidence:g}%"
    cols = [c for c in COLUMNS if any(c in r.cells for r in rows)]
    heads = [h for c in cols for h in (column_name(c), f"{column_name(c)} IQM")]
    lines = [f"### {title}", "",
             f"Per column: mean over seeds [{pct} bootstrap interval] (per-seed values), then the "
             f"interquartile mean (IQM, the mean of the middle 50% of seeds; the mean below 4 seeds) "
             f"[{pct} bootstrap interval].",
             "", "| method | n | " + " | ".join(heads) + " |",
             "|---|---|" + "---|" * len(heads)]
    for r in rows:
        cells = [text for c in cols for text in
                 ((fmt_cell(r.cells[c], confidence), fmt_iqm(r.cells[c])) if c in r.cells else ("", ""))]
        lines.append(f"| {r.label} | {len(r.units)} | " + " | ".join(cells) + " |")
    lines += ["", "n: seeds (or people) per row. \u2020: a single unit; interval over its episodes. "
              "Rows are whole configurations: runs whose configs differ in more than the seed are "
              "separate rows, labelled by the keys that differ."]
    if any(len(r.units) < 5 for r in rows if len(r.units) > 1):
        lines.append("With fewer than 5 seeds a percentile bootstrap interval is little more than "
                     "the range of the seeds (it undercovers); treat it as a lower bound on the spread.")
    if diffs:
        lines += ["", f"### Pairwise comparisons ({pct} bootstrap intervals)", "",
                  "Difference of the means, and the probability of improvement P(a > b): the chance "
                  "that a seed of a scores above a seed of b (ties count 1/2; 0.5: no difference). "
                  "All columns: the mean difference over every (seed, column) and the mean of the "
                  "columns' P(a > b), seeds resampled within each column (stratified bootstrap).", "",
                  "| comparison | column | difference | interval | excludes 0 | P(a > b) [interval] |",
                  "|---|---|---|---|---|---|"]
        for d in diffs:
            mark = "**yes**" if d.cell.excludes_zero() else "no"
            over = "\u2020" if d.cell.over == "episodes" else ""
            lines.append(f"| {d.a} \u2212 {d.b} | {column_name(d.column)} | {d.cell.mean:+.1f} | "
                         f"[{_num(d.cell.low)}, {_num(d.cell.high)}]{over} | {mark} | {fmt_p(d)} |")
        lines += ["", verdict(diffs, pct)]
    return "\n".join(lines) + "\n"


def verdict(diffs: Sequence[Difference], pct: str) -> str:
    """Per comparison: which columns' intervals exclude zero (or 0.5 for P(a > b)), then the
    comparison over all columns."""
    out = []
    for a, b in dict.fromkeys((d.a, d.b) for d in diffs):
        mine = [d for d in diffs if (d.a, d.b) == (a, b) and d.column != ALL]
        overall = [d for d in diffs if (d.a, d.b) == (a, b) and d.column == ALL]
        sure = [d for d in mine if d.cell.excludes_zero()]
        n = f"{a} vs {b} ({mine[0].n_a} vs {mine[0].n_b} units)"
        if sure:
            parts = ", ".join(f"{column_name(d.column)} {d.cell.mean:+.1f}" for d in sure)
            out.append(f"{n}: the {pct} interval excludes zero for {parts}.")
        else:
            out.append(f"{n}: no difference is distinguishable from zero at {pct}.")
        probable = [d for d in mine if d.p_low is not None and d.p_high is not None
                    and (d.p_low > 0.5 or d.p_high < 0.5)]
        if probable:
            parts = ", ".join(f"{column_name(d.column)} {fmt_p(d)}" for d in probable)
            out.append(f"P({a} > {b}) excludes 0.5 for {parts}.")
        for d in overall:
            out.append(f"Over all columns: {d.cell.mean:+.1f} [{_num(d.cell.low)}, {_num(d.cell.high)}], "
                       f"P({a} > {b}) = {fmt_p(d)}.")
    if any(min(d.n_a, d.n_b) < 5 and d.cell.over == "seeds" for d in diffs):
        out.append("With so few seeds these intervals are optimistic; more seeds, not more "
                   "evaluation episodes, would make them trustworthy.")
    return " ".join(out)


def _paper_text(row: Row, column: tuple[str, str]) -> str:
    """The paper's value of a row without configuration variants ("" otherwise)."""
    value = None if row.variant else paper_value(row.base or row.label, column)
    return "" if value is None else _num(float(value))


def side_by_side(rows: Sequence[Row], confidence: float = 0.95) -> str:
    """Table III with the paper's number beside each of ours: mean [interval], IQM [interval]."""
    pct = f"{100 * confidence:g}%"
    cols = [c for c in COLUMNS if any(c in r.cells for r in rows)]
    heads = [h for c in cols for h in (column_name(c), "paper")]
    lines = [f"Per column: mean over seeds [{pct} stratified-bootstrap interval]; IQM [{pct} interval]; "
             "then the paper's value (Table III, constant-speed traffic).", "",
             "| method | n | " + " | ".join(heads) + " |", "|---|---|" + "---|" * len(heads)]
    for r in rows:
        cells = []
        for c in cols:
            cell = r.cells.get(c)
            ours = "" if cell is None else \
                f"{fmt_cell(cell, confidence, per_unit=False)}; IQM {fmt_iqm(cell)}"
            cells += [ours, _paper_text(r, c) or "\u2014"]
        lines.append(f"| {r.label} | {len(r.units)} | " + " | ".join(cells) + " |")
    lines += ["", "Per-seed values:", "", "| method | units | " + " | ".join(column_name(c) for c in cols)
              + " |", "|---|---|" + "---|" * len(cols)]
    for r in rows:
        vals = [", ".join(_num(v) for v in r.cells[c].values) if c in r.cells else "" for c in cols]
        lines.append(f"| {r.label} | {', '.join(r.units)} | " + " | ".join(vals) + " |")
    return "\n".join(lines) + "\n"


def _round(x: float | None) -> float | str:
    return "" if x is None else round(x, 4)


def write_csv(rows: Sequence[Row], diffs: Sequence[Difference], table_path: Path, diff_path: Path) -> None:
    """Long-format CSVs: one line per (row, column) and per (comparison, column)."""
    with table_path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["method", "n", "units", "initial_lane", "metric", "mean", "ci_low", "ci_high",
                    "iqm", "iqm_low", "iqm_high", "ci_over", "values", "episodes", "base", "config",
                    "paper"])
        for r in rows:
            config = ";".join(f"{k}={v}" for k, v in r.variant.items())
            for (lane, metric), c in r.cells.items():
                w.writerow([r.label, len(r.units), ";".join(r.units), lane, metric, round(c.mean, 4),
                            round(c.low, 4), round(c.high, 4), _round(c.iqm), _round(c.iqm_low),
                            _round(c.iqm_high), c.over, ";".join(_num(v) for v in c.values),
                            ";".join(map(str, c.episodes)), r.base or r.label, config,
                            _paper_text(r, (lane, metric))])
    with diff_path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["a", "b", "n_a", "n_b", "initial_lane", "metric", "difference", "ci_low", "ci_high",
                    "ci_over", "excludes_zero", "p_improvement", "p_low", "p_high"])
        for d in diffs:
            w.writerow([d.a, d.b, d.n_a, d.n_b, *d.column, round(d.cell.mean, 4), round(d.cell.low, 4),
                        round(d.cell.high, 4), d.cell.over, int(d.cell.excludes_zero()),
                        _round(d.p_improvement), _round(d.p_low), _round(d.p_high)])
