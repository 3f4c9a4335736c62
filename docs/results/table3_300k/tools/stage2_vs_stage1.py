"""S&R (non-goal: survived and reached) of B's final and stage-1 weights per seed, and P(final > stage 1)
with its 95% stratified-bootstrap interval (memrl.evaluation.bootstrap):
python stage2_vs_stage1.py [study dir] [traffic: constant | mixed] [test: eval | eval_mixed]."""
import csv
import sys
from pathlib import Path

import numpy as np

from memrl.evaluation.bootstrap import interval, probability_of_improvement


def sr(folder: Path) -> int:
    rows = [r for r in csv.DictReader((folder / "episodes.csv").open()) if r["initial_lane"] == "non_goal"]
    return sum(int(r["survived"]) and int(r["reached_target"]) for r in rows)


study = Path(sys.argv[1] if len(sys.argv) > 1 else "studies/table3_300k_v3")
traffic = sys.argv[2] if len(sys.argv) > 2 else "constant"
test = sys.argv[3] if len(sys.argv) > 3 else "eval"
suffix = test.removeprefix("eval")  # stage-1 tests in mixed traffic: stage1/<run>_mixed
final, first = [], []
for run in sorted((study / "runs").glob(f"B_{traffic}_s*")):
    stage1 = study / "stage1" / (run.name + suffix)
    if (run / test / "episodes.csv").is_file() and (stage1 / "episodes.csv").is_file():
        final.append(sr(run / test))
        first.append(sr(stage1))
        print(f"{run.name}: stage 1 {first[-1]}, final {final[-1]}, {final[-1] - first[-1]:+d}")
x, y = np.array(final, float)[:, None], np.array(first, float)[:, None]
p = float(probability_of_improvement(x, y))
lo, hi = interval([x, y], probability_of_improvement, 0.95, 2000, np.random.default_rng(0))
higher = sum(a > b for a, b in zip(final, first, strict=True))
print(f"higher on {higher} of {len(final)} seeds; "
      f"mean {np.mean(final):.1f} vs {np.mean(first):.1f}; P(final > stage 1) = {p:.2f} [{lo:.2f}, {hi:.2f}]")
