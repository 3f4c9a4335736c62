"""Per-run wall time and commits of a study's runs, for runs that predate ``summary.json``'s
``train_wall_s``: each call from its ``provenance.json`` start/resume time to its last
``train.log`` line.

    python docs/results/table3/run_walls.py <study>/runs > docs/results/table3/runs.md
"""

from __future__ import annotations

import json
import re
import sys
from datetime import UTC, datetime
from pathlib import Path

STAMP = re.compile(r"^\[(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d),\d+\]")
DONE = "[memrl.train][INFO] - done: "


def calls(run: Path) -> tuple[float, int, list[str], datetime, datetime | None]:
    """Seconds summed over the run's calls, the number of calls, the commits, first start, last line."""
    events = json.loads((run / "provenance.json").read_text())
    starts = [datetime.fromisoformat(e["time"]) for e in events]
    lines = [(datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S").replace(tzinfo=UTC), line)
             for line in (run / "train.log").read_text().splitlines() if (m := STAMP.match(line))]
    stamps = [t for t, _ in lines]
    total = 0.0
    for i, start in enumerate(starts):
        end = starts[i + 1] if i + 1 < len(starts) else None
        window = [(t, line) for t, line in lines if t >= start and (end is None or t < end)]
        done = [t for t, line in window if DONE in line]  # a call ends at its "done:" line
        if window:  # (later lines there: a call that died before its provenance entry)
            total += ((done[0] if done else window[-1][0]) - start).total_seconds()
    commits = sorted({e["git"]["commit"][:7] + ("+dirty" if e["git"]["dirty"] else "") for e in events})
    return total, len(starts), commits, starts[0], stamps[-1] if stamps else None


if __name__ == "__main__":
    print("| run | calls | training wall [s] | commits | first start (UTC) | last log line (UTC) |")
    print("|---|---|---|---|---|---|")
    for run in sorted(Path(sys.argv[1]).glob("*/")):
        if (run / "summary.json").is_file():
            total, n, commits, first, last = calls(run)
            print(f"| {run.name} | {n} | {total:,.0f} | {', '.join(commits)} | {first:%Y-%m-%d %H:%M} | "
                  f"{last:%Y-%m-%d %H:%M} |" if last else "| |")
