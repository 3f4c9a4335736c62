"""Rows of the results page from evaluation folders: python v3status.py [study dir]."""
import csv
import json
import sys
from pathlib import Path


def figures(path: Path) -> str:
    rows = list(csv.DictReader((path / "episodes.csv").open()))
    ng = [r for r in rows if r["initial_lane"] == "non_goal"]
    rd = [r for r in rows if r["initial_lane"] == "random"]
    s = lambda rs, k: sum(int(r[k]) for r in rs)  # noqa: E731
    both = sum(int(r["survived"]) and int(r["reached_target"]) for r in ng)
    cars = " / ".join(f"{s([r for r in ng if int(r['vehicles']) == n], 'survived')} of "
                      f"{len([r for r in ng if int(r['vehicles']) == n])}" for n in (3, 4, 5))
    kinds = [r["crash_kind"] for r in rows if int(r["collided"])]
    crash = " / ".join(str(kinds.count(k)) for k in ("ahead", "behind", "side", "road_edge"))
    other = len(kinds) - sum(kinds.count(k) for k in ("ahead", "behind", "side", "road_edge"))
    return (f"{s(ng, 'survived')} | {s(ng, 'reached_target')} | {both} | {s(rd, 'survived')} | "
            f"{s(rd, 'reached_target')} | {cars} | {crash}" + (f" (+{other} other)" if other else ""))


def training(run: Path) -> str:
    d = json.loads((run / "summary.json").read_text())
    w = d.get("train_wall_s") or d.get("wall_s")
    return f"{d['updates']:,} updates in {w:,.0f} s ({d['updates'] / w:.1f} updates/s)"


if __name__ == "__main__":
    study = Path(sys.argv[1] if len(sys.argv) > 1 else "studies/table3_300k_v3")
    for run in sorted((study / "runs").iterdir()):
        tests = (p for p in run.iterdir() if p.name.startswith("eval") and (p / "episodes.csv").is_file())
        for sub in sorted(tests):
            print(f"| {run.name} {sub.name} | {figures(sub)} | "
                  f"{training(run) if (run / 'summary.json').is_file() else ''} |")
        for st in sorted(study.glob(f"stage1*/{run.name}*")):
            if (st / "episodes.csv").is_file():
                print(f"| ({st.parent.name}/{st.name}) | {figures(st)} | |")
