"""The rates of docs/results/gpu-h100-2026-11-27.md from the 12 runs' train-log lines (kept in
train_logs/): updates/s and env steps/s of each run between 02:18:00 (the CUDA tests beside
them were over) and its last line, and their sum. Run: python docs/results/gpu-h100-2026-11-27/rates.py"""

import datetime as dt
import re
from pathlib import Path

LINE = re.compile(r"\[([^\]]+)\].*updates (\d+), env steps (\d+), stage B2")
FROM = dt.datetime(2026, 11, 27, 2, 18, 0)
total_updates = total_steps = 0.0
for log in sorted((Path(__file__).parent / "train_logs").glob("*.log")):
    points = [(dt.datetime.strptime(m[1], "%Y-%m-%d %H:%M:%S,%f"), int(m[2]), int(m[3]))
              for m in map(LINE.match, log.read_text().splitlines()) if m]
    window = [p for p in points if p[0] >= FROM]
    (t0, u0, s0), (t1, u1, s1) = window[0], window[-1]
    seconds = (t1 - t0).total_seconds()
    total_updates += (u1 - u0) / seconds
    total_steps += (s1 - s0) / seconds
    print(f"{log.stem}: {(u1 - u0) / seconds:.2f} updates/s, {(s1 - s0) / seconds:.1f} env steps/s "
          f"over {seconds:.0f} s; last line: {u1} updates, {s1} env steps")
print(f"all: {total_updates:.1f} updates/s, {total_steps:.1f} env steps/s")
