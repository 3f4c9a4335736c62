"""Table III from synthetic evaluation folders: numbers, intervals, differences; the report
command end to end with its figures; Fig. 7 replays and videos of real episodes."""

from __future__ import annotations

import csv
import json
import logging

import cv2
import numpy as np
import pytest

from memrl.errors import ConfigError
from memrl.evaluate import evaluate
from memrl.evaluation import stats, tables
from memrl.evaluation.figures import band, find_training_runs, learning_curves, smooth
from memrl.evaluation.periodic import PERIODIC_CSV, PERIODIC_FIELDS
from memrl.evaluation.protocol import ProtocolConfig
from memrl.evaluation.results import find_results
from memrl.report import report
from tests.eval_helpers import fake_eval, fake_run

REPORT = ["evaluate_missing=false", "rollouts.rows=[]", "progress=false", "n_resamples=2000",
          "curve_resamples=200"]


def sweep(root, compose_cfg, scores: dict[str, list[tuple[int, int]]], episodes: int = 0):
    """Run folders of each mode with evaluations of the given (survival, goal) per seed."""
    for mode, per_seed in scores.items():
        for seed, (surv, goal) in enumerate(per_seed):
            run = fake_run(root, compose_cfg, mode=mode, seed=seed, episodes=episodes)
            label = {"default": "Default"}.get(mode, mode)
            fake_eval(run / "eval", label, f"seed {seed}", surv, goal,
                      meta={"kind": "checkpoint", "run": str(run)})


# --------------------------------------------------------------------------- numbers
def test_table_means_per_seed_values_and_intervals(tmp_path, compose_cfg):
    sweep(tmp_path, compose_cfg, {"default": [(50, 40), (60, 40)], "B": [(80, 70), (90, 74)],
                                  "A": [(50, 30), (62, 36), (56, 33)]})
    fake_eval(tmp_path / "scripted", "scripted", "scripted", 100, 50)
    results = find_results([tmp_path])
    rows = {r.label: r for r in stats.table(results)}
    assert list(rows) == ["Default", "A", "B", "scripted"]
    d = rows["Default"].cells[("random", "survival")]
    assert d.values == [50.0, 60.0] and d.mean == 55.0 and d.over == "seeds"
    # two seeds: every resample is (a,a), (a,b), (b,a) or (b,b); each end has 25% > 2.5%
    assert (d.low, d.high) == (50.0, 60.0)
    g = rows["Default"].cells[("non_goal", "goal")]
    assert (g.mean, g.low, g.high) == (40.0, 40.0, 40.0)  # equal seeds: no spread
    a = rows["A"].cells[("random", "survival")]
    assert a.mean == pytest.approx(56.0) and 50.0 <= a.low < 56.0 < a.high <= 62.0
    assert rows["A"].units == ["seed 0", "seed 1", "seed 2"]
    # one unit: the interval is over its 100 episodes (binomial: 50 +- 1.96 * 5)
    s = rows["scripted"].cells[("random", "goal")]
    assert s.over == "episodes" and s.mean == 50.0 and s.low == pytest.approx(40.2, abs=3)
    assert s.high == pytest.approx(59.8, abs=3)
    assert rows["scripted"].cells[("non_goal", "survival")].low == 100.0


def test_pairwise_differences_say_which_intervals_exclude_zero(tmp_path, compose_cfg):
    sweep(tmp_path, compose_cfg, {"default": [(50, 40), (60, 40)], "B": [(80, 40), (90, 40)],
                                  "A": [(50, 30), (62, 46)]})
    results = find_results([tmp_path])
    pairs = [["B", "Default"], ["A", "Default"]]
    diffs = {(d.a, d.column): d.cell for d in stats.differences(results, pairs)}
    b = diffs[("B", ("random", "survival"))]
    # B - Default: {80, 85, 90} - {50, 55, 60}; the extremes 20 and 40 each have 6.25% > 2.5%
    assert (b.mean, b.low, b.high) == (30.0, 20.0, 40.0) and b.excludes_zero()
    assert diffs[("B", ("random", "goal"))].mean == 0 and not diffs[("B", ("random", "goal"))].excludes_zero()
    a = diffs[("A", ("random", "survival"))]
    assert a.mean == pytest.approx(1.0) and a.low < 0 < a.high and not a.excludes_zero()
    md = tables.markdown(stats.table(results), stats.differences(results, pairs))
    assert "| B \u2212 Default | random survival | +30.0 | [20, 40] | **yes** |" in md
    assert "| A \u2212 Default | random survival | +1.0 |" in md
    assert ("B vs Default (2 vs 2 units): the 95% interval excludes zero for random survival +30.0, "
            "non-goal survival +30.0.") in md
    assert "A vs Default (2 vs 2 units): no difference is distinguishable from zero at 95%." in md
    assert "these intervals are optimistic" in md
    # a missing row is left out, not an error
    assert stats.differences(results, [["human", "Default"]]) == []


def test_single_unit_differences_resample_episodes(tmp_path):
    fake_eval(tmp_path / "a", "scripted", "scripted", 90, 90)
    fake_eval(tmp_path / "b", "random", "random", 10, 50)
    [d] = [x for x in stats.differences(find_results([tmp_path]), [["scripted", "random"]])
           if x.column == ("random", "survival")]
    assert d.cell.over == "episodes" and d.cell.mean == 80.0 and 70 < d.cell.low < 80 < d.cell.high < 90


def test_mixed_protocols_are_refused(tmp_path):
    fake_eval(tmp_path / "a", "scripted", "scripted", 90, 90)
    fake_eval(tmp_path / "b", "random", "random", 10, 50, n=20)
    with pytest.raises(ValueError, match="different protocols"):
        stats.check_protocols(find_results([tmp_path]))


# --------------------------------------------------------------------------- the command
def test_report_on_synthetic_run_folders(tmp_path, compose_cfg):
    sweep(tmp_path / "sweep", compose_cfg, {"default": [(50, 40), (60, 40)], "A": [(40, 20), (44, 30)],
                                            "B": [(80, 70), (90, 74)]}, episodes=30)
    fake_eval(tmp_path / "human_ann", "human", "ann", 48, 50)
    fake_eval(tmp_path / "human_bob", "human", "bob", 52, 52)
    folders = ",".join(str(tmp_path / name) for name in ("sweep", "human_ann", "human_bob"))
    cfg = compose_cfg("report", [f"runs=[{folders}]", *REPORT])
    files = report(cfg, out_dir=tmp_path / "out")
    with files.table_csv.open() as f:
        rows = {(r["method"], r["initial_lane"], r["metric"]): r for r in csv.DictReader(f)}
    b = rows[("B", "non_goal", "goal")]
    assert (float(b["mean"]), float(b["ci_low"]), float(b["ci_high"])) == (72.0, 70.0, 74.0)
    assert b["values"] == "70;74" and b["units"] == "seed 0;seed 1" and b["ci_over"] == "seeds"
    h = rows[("human", "random", "survival")]
    assert (float(h["mean"]), h["n"], h["units"]) == (50.0, "2", "ann;bob")
    with files.differences_csv.open() as f:
        diffs = {(r["a"], r["initial_lane"], r["metric"]): r for r in csv.DictReader(f)}
    assert diffs[("B", "random", "survival")]["excludes_zero"] == "1"
    assert diffs[("A", "random", "survival")]["difference"] == "-13.0"
    md = files.table_md.read_text()
    assert md.index("| Default |") < md.index("| A |") < md.index("| B |") < md.index("| human |")
    doc = json.loads(files.report_json.read_text())
    assert len(doc["sources"]) == 8 and doc["rows"][0]["label"] == "Default"
    img = cv2.imread(str(files.fig5))
    assert img is not None and img.shape[1] > 800 and img.std() > 10


def test_report_evaluates_runs_without_an_evaluation(tmp_path, compose_cfg):
    run = fake_run(tmp_path / "sweep", compose_cfg, mode="A", seed=4)
    cfg = compose_cfg("report", [f"runs=[{tmp_path / 'sweep'}]", *REPORT, "evaluate_missing=true",
                                 "protocol.episodes=2", "protocol.duration=10", "workers=1", "fig5=false"])
    files = report(cfg, out_dir=tmp_path / "out")
    assert (run / "eval" / "eval.json").is_file() and "| A | 1 |" in files.markdown
    mtime = (run / "eval" / "eval.json").stat().st_mtime_ns
    report(cfg, out_dir=tmp_path / "out2")  # evaluated under this protocol already: not again
    assert (run / "eval" / "eval.json").stat().st_mtime_ns == mtime


def test_report_refuses_to_replace_an_evaluation_under_another_protocol(tmp_path, compose_cfg):
    """evaluate_missing under another protocol: one line naming the folder and the differing
    key, nothing evaluated or replaced; overwrite=true replaces it."""
    from memrl.errors import UserError

    run = fake_run(tmp_path / "sweep", compose_cfg, mode="A", seed=4)
    base = [f"runs=[{tmp_path / 'sweep'}]", *REPORT, "evaluate_missing=true", "protocol.episodes=2",
            "workers=1", "fig5=false"]
    report(compose_cfg("report", [*base, "protocol.duration=10"]), out_dir=tmp_path / "out")
    first = (run / "eval" / "eval.json").read_bytes()
    longer = compose_cfg("report", [*base, "protocol.duration=12"])
    with pytest.raises(UserError, match=r"eval holds an evaluation under another protocol \(differs in: "
                       r"duration\); evaluating would replace it: overwrite=true"):
        report(longer, out_dir=tmp_path / "out2")
    assert (run / "eval" / "eval.json").read_bytes() == first and not (tmp_path / "out2").exists()
    longer.overwrite = True
    report(longer, out_dir=tmp_path / "out3")
    assert json.loads((run / "eval" / "eval.json").read_text())["protocol"]["duration"] == 12


def test_report_evaluates_mixed_test_traffic_into_eval_mixed(tmp_path, compose_cfg):
    """Under protocol.opponent=mixed the missing evaluation goes where memrl.evaluate and the
    study put it (eval_mixed/), and no eval/ folder is made or replaced."""
    run = fake_run(tmp_path / "sweep", compose_cfg, mode="A", seed=4)
    pool = fake_run(tmp_path / "pool", compose_cfg, seed=2)
    mixed = f"protocol.opponent={{type:mixed,learned_fraction:0.5,pool:['{pool}'],epsilon:0.0}}"
    cfg = compose_cfg("report", [f"runs=[{tmp_path / 'sweep'}]", *REPORT, "evaluate_missing=true", mixed,
                                 "protocol.episodes=2", "protocol.duration=10", "workers=1", "fig5=false"])
    files = report(cfg, out_dir=tmp_path / "out")
    doc = json.loads((run / "eval_mixed" / "eval.json").read_text())
    assert doc["protocol"]["opponent"]["type"] == "mixed" and not (run / "eval").exists()
    assert "| A | 1 |" in files.markdown


def test_report_needs_evaluations(tmp_path, compose_cfg):
    with pytest.raises(ValueError, match="runs"):
        report(compose_cfg("report", REPORT), out_dir=tmp_path)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ConfigError, match="no evaluation") as info:  # one line naming the folder
        report(compose_cfg("report", [f"runs=[{tmp_path / 'empty'}]", *REPORT]), out_dir=tmp_path / "out")
    assert str(tmp_path / "empty") in str(info.value) and not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- figures
def test_smoothing_and_bands():
    assert smooth(np.array([1.0, 2.0, 3.0, 4.0]), 2).tolist() == [1.0, 1.5, 2.5, 3.5]
    assert smooth(np.array([1.0, 3.0]), 1).tolist() == [1.0, 3.0]
    curves = np.array([[0.0, 10.0], [2.0, 10.0]])
    lo, hi = band(curves, 0.95, 500, seed=0)
    assert lo.tolist() == [0.0, 10.0] and hi.tolist() == [2.0, 10.0]


def test_fig5_has_periodic_panels_when_runs_logged_them(tmp_path, compose_cfg):
    for seed in (0, 1):
        run = fake_run(tmp_path, compose_cfg, mode="B", seed=seed, episodes=40)
        with (run / PERIODIC_CSV).open("w", newline="") as f:
            w = csv.DictWriter(f, PERIODIC_FIELDS)
            w.writeheader()
            for ep in (10, 20, 30):
                w.writerow({k: ep for k in PERIODIC_FIELDS})
    runs = find_training_runs([tmp_path])
    assert [(r.label, r.seed) for r in runs] == [("B", 0), ("B", 1)] and runs[0].periodic is not None
    path = learning_curves(runs, tmp_path / "fig5.png", window=5, n_resamples=100)
    assert path is not None and cv2.imread(str(path)).shape[1] == 2400  # four panels at 120 dpi
    assert learning_curves([], tmp_path / "none.png") is None


def test_fig7_strip_and_video_replay_the_evaluated_episodes(tmp_path, compose_cfg, caplog):
    ev = compose_cfg("evaluate", ["policy=scripted", "protocol.episodes=3", "protocol.duration=40",
                                  "workers=1", "progress=false", "env.vehicles_count=5"])
    [result] = evaluate(ev, out_dir=tmp_path / "scripted")
    cfg = compose_cfg("report", [f"runs=[{tmp_path / 'scripted'}]", *REPORT, "rollouts.rows=[scripted,human]",
                                 "rollouts.count=2", "rollouts.steps=[0,10,39,80]", "rollouts.fps=20"])
    with caplog.at_level(logging.INFO):
        files = report(cfg, out_dir=tmp_path / "out")
    assert "differs from its evaluation" not in caplog.text  # the replays are the evaluated episodes
    assert "no evaluation of row human" in caplog.text
    [strip], [video] = files.strips, files.videos
    img = cv2.imread(str(strip))
    assert img is not None and img.std() > 10 and img.shape[1] >= 4 * 120
    cap = cv2.VideoCapture(str(video))
    assert int(cap.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little") in (b"avc1", b"h264")  # H.264
    frames = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    ok, first = cap.read()
    cap.release()
    recs = [r for r in result.records() if r.initial_lane == "non_goal"][:2]
    assert ok and first.std() > 10
    assert frames == sum(r.steps + 1 + 10 for r in recs)  # every step, and the end held 10 frames


def test_protocol_config_matches_the_paper(compose_cfg):
    from memrl.evaluation.protocol import check_protocol

    p = compose_cfg("evaluate", ["policy=random"]).protocol
    assert check_protocol(p) == ProtocolConfig()  # constant traffic from the opponent group
    assert (p.episodes, list(p.vehicles_count), p.duration) == (100, [0, 5], 300)


def test_rows_evaluated_on_fewer_settings_still_compare(tmp_path):
    fake_eval(tmp_path / "a", "scripted", "scripted", 90, 90)
    human = ProtocolConfig(initial_lanes=["random"])
    fake_eval(tmp_path / "h", "human", "ann", 50, 50, protocol=human)
    results = find_results([tmp_path])
    stats.check_protocols(results)  # same scenes for the random starts: comparable
    rows = {r.label: r for r in stats.table(results)}
    assert set(rows["scripted"].cells) == set(stats.COLUMNS)
    assert set(rows["human"].cells) == {("random", "survival"), ("random", "goal")}
    md = tables.markdown(list(rows.values()), [])
    [line] = [x for x in md.splitlines() if x.startswith("| human |")]
    assert line.startswith("| human | 1 | 50.0 [") and line.endswith("|  |  |")


def test_evaluate_takes_its_traffic_from_the_opponent_group(compose_cfg):
    from memrl.evaluation.protocol import check_protocol

    p = compose_cfg("evaluate", ["policy=random", "opponent=mixed", "env.opponent.pool=[x]"]).protocol
    assert check_protocol(p).opponent["type"] == "mixed"
    assert check_protocol(p).opponent["pool"] == ["x"]


def test_fig5_pools_each_run_to_its_own_end():
    from memrl.evaluation.figures import pool

    p = pool([np.array([0.0, 10.0, 20.0]), np.array([0.0, 20.0, 40.0])],
             [np.array([1.0, 1.0, 1.0]), np.array([3.0, 3.0, 3.0])], n_resamples=100, points=5)
    assert p.x.tolist() == [0.0, 10.0, 20.0, 30.0, 40.0]
    assert p.n.tolist() == [2, 2, 2, 1, 1] and p.mean.tolist() == [2.0, 2.0, 2.0, 3.0, 3.0]
    assert p.low[0] == 1.0 and p.high[0] == 3.0 and p.low[-1] == p.high[-1] == 3.0


def test_fig5_marks_runs_that_end_together_once():
    from memrl.evaluation.figures import drops

    x = np.arange(101.0)  # span 100: drops within 2 of the first of a group are one mark
    n = np.array([5] * 40 + [4] * 58 + [3, 2, 1])  # one run ends at 39, three at 97, 98, 99
    assert drops(x, n) == [(39, 4), (97, 1)]
    assert drops(x, n, merge=0.0) == [(39, 4), (97, 3), (98, 2), (99, 1)]
    assert drops(x, np.full(101, 5)) == []


def test_fig5_draws_runs_of_different_lengths_against_env_steps(tmp_path, compose_cfg):
    for seed, n in ((0, 40), (1, 25)):
        fake_run(tmp_path, compose_cfg, mode="B", seed=seed, episodes=n)
    runs = find_training_runs([tmp_path])
    assert sorted(len(r.columns["env_steps"]) for r in runs) == [25, 40]
    path = learning_curves(runs, tmp_path / "fig5.png", window=5, n_resamples=100)
    assert path is not None and cv2.imread(str(path)).std() > 10


def test_fig7_strip_names_the_method_and_says_when_nothing_succeeded():
    from memrl.evaluation.protocol import EpisodeRecord
    from memrl.evaluation.rollouts import Capture, strip

    rec = EpisodeRecord(initial_lane="non_goal", episode=0, seed=7, steps=2, episode_return=0.0,
                        collided=True, reached_target=False, duration=300, target_lane=1,
                        start_lane=0, vehicles=2)
    scenes = [np.full((60, 40, 3), 64, np.uint8)] * 3
    cap = Capture(rec, scenes, [np.zeros((84, 84), np.uint8)] * 3, [4, 4])
    plain = strip([cap], [0, 2])
    named = strip([cap], [0, 2], title="Fig. 7: B, seed 0", note="no episode of B succeeded")
    assert named.shape[0] == plain.shape[0] + 28 + 24
    red = (named[..., 0] > 150) & (named[..., 1] < 80) & (named[..., 2] < 80)
    assert red[28:52].any() and not red[:28].any()  # the note, in red, under the title
    legend = plain[-24:]
    assert (np.abs(legend.astype(int) - [255, 220, 0]).sum(-1) == 0).any()  # the agent's swatch


def test_rows_of_other_traffic_follow_their_mode():
    from memrl.evaluation.rows import row_rank

    names = ["random", "B (learned)", "zeta", "B", "Default (mixed)", "Default", "A"]
    assert sorted(names, key=row_rank) == ["Default", "Default (mixed)", "A", "B", "B (learned)",
                                           "random", "zeta"]


def test_the_study_report_counts_non_goal_episodes_that_survived_and_reached(tmp_path):
    from memrl.evaluation.protocol import ProtocolConfig, scenario_seeds
    from memrl.evaluation.results import write_result
    from memrl.studies.report import both_section
    from tests.eval_helpers import records

    def result(unit: str, survived: list[bool], goal: list[bool]):
        recs = records(survived, goal, "non_goal", seeds=scenario_seeds(0, 4)) + \
            records([True] * 4, [True] * 4, "random", seeds=scenario_seeds(0, 4))  # not counted
        return write_result(tmp_path / unit, "B", recs, ProtocolConfig(episodes=4),
                            scenario_seeds(0, 4), {"unit": unit})

    # seed 0: survived & reached only in episode 0 (1 of 4); seed 1: episodes 1 and 2 (2 of 4)
    a = result("seed 0", [True, True, False, False], [True, False, True, False])
    b = result("seed 1", [False, True, True, True], [True, True, True, False])
    from memrl.evaluation.stats import StatsConfig

    assert "| B | 2 | 37.5 | seed 0: 25, seed 1: 50 |" in both_section([[a, b]], StatsConfig())
    assert both_section([[]], StatsConfig()) == []


def test_the_study_report_splits_non_goal_scores_by_the_number_of_other_cars(tmp_path):
    """Episodes pooled over the row's seeds per car count, against a hand count."""
    import dataclasses

    from memrl.evaluation.protocol import ProtocolConfig, scenario_seeds
    from memrl.evaluation.results import write_result
    from memrl.evaluation.stats import StatsConfig
    from memrl.studies.traffic import by_cars, traffic_section
    from tests.eval_helpers import records

    def result(unit: str, survived: list[bool], goal: list[bool], cars: list[int]):
        recs = [dataclasses.replace(r, vehicles=v) for r, v in zip(
            records(survived, goal, "non_goal", seeds=scenario_seeds(0, 4)), cars, strict=True)]
        recs += records([False] * 4, [False] * 4, "random", seeds=scenario_seeds(0, 4))  # not counted
        return write_result(tmp_path / unit, "Default", recs, ProtocolConfig(episodes=4),
                            scenario_seeds(0, 4), {"unit": unit})

    a = result("seed 0", [True, False, True, False], [True, True, False, False], [0, 5, 0, 5])
    b = result("seed 1", [True, True, False, False], [True, True, True, True], [0, 2, 5, 5])
    # 0 cars: 3 episodes, all survived, 2 reached; 2 cars: 1, survived and reached;
    # 5 cars: 4 episodes, none survived, 3 reached
    assert by_cars([a, b]) == {0: (3, 100.0, 200 / 3), 2: (1, 100.0, 100.0), 5: (4, 0.0, 75.0)}
    lines = traffic_section([[a, b]], StatsConfig())
    assert "| row | 0 cars | 2 cars | 5 cars |" in lines
    assert "| Default | 100 / 67 (3) | 100 / 100 (1) | 0 / 75 (4) |" in lines
    assert traffic_section([[]], StatsConfig()) == []
