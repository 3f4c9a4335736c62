"""Table III's statistics against hand computations: IQM, the stratified bootstrap, P(X > Y);
rows split by run configuration; duplicated evaluations refused."""

from __future__ import annotations

import csv
import itertools
import shutil

import numpy as np
import pytest
from omegaconf import OmegaConf
from scipy.stats import trim_mean

from memrl.evaluation import bootstrap as bs
from memrl.evaluation import rows, stats
from memrl.evaluation.results import find_results
from memrl.report import report
from tests.eval_helpers import fake_eval, fake_run

REPORT = ["evaluate_missing=false", "rollouts.rows=[]", "progress=false", "n_resamples=2000", "fig5=false"]


# --------------------------------------------------------------------------- IQM
@pytest.mark.parametrize(("scores", "expected"), [
    ([1, 2, 3, 100], 2.5),                   # n=4: drop 1 each end -> (2 + 3) / 2
    ([5, 1, 3, 9, 7], 5.0),                  # n=5: drop 1 each end -> (3 + 5 + 7) / 3
    ([10, 1, 2, 3, 4, 5, 6, 100], 4.5),      # n=8: drop 2 each end -> (3 + 4 + 5 + 6) / 4
    ([0, 30, 90], 40.0),                     # n=3: floor(3 / 4) = 0 dropped -> the mean
])
def test_iqm_is_the_mean_of_the_middle_half(scores, expected):
    assert bs.point([scores], bs.iqm) == pytest.approx(expected, rel=1e-12)


def test_iqm_aggregates_runs_and_tasks_together_and_batches():
    x = np.array([[1.0, 100.0], [2.0, 3.0]])  # runs x tasks -> {1, 2, 3, 100}
    assert bs.point([x], bs.iqm) == 2.5
    batch = np.stack([x, x + 1.0, np.zeros_like(x)])  # leading resample axis
    assert bs.iqm(batch).tolist() == [2.5, 3.5, 0.0]


# --------------------------------------------------------------------------- stratified bootstrap
def test_stratified_resamples_keep_each_task_and_draw_tasks_independently():
    # two runs x two tasks; per task 4 equally likely resamples of its runs, independently:
    # 16 equally likely outcomes whose aggregate means are the 9 distinct values below
    x = np.array([[0.0, 0.0], [4.0, 20.0]])
    exact: dict[float, float] = {}
    for i0, i1 in itertools.product(itertools.product(range(2), repeat=2), repeat=2):
        value = (x[list(i0), 0].mean() + x[list(i1), 1].mean()) / 2
        exact[value] = exact.get(value, 0.0) + 1 / 16
    assert len(exact) == 9
    n = 20_000
    res = bs.stratified_resamples(x, n, np.random.default_rng(0))
    assert res.shape == (n, 2, 2)
    assert set(np.unique(res[:, :, 0])) == {0.0, 4.0} and set(np.unique(res[:, :, 1])) == {0.0, 20.0}
    values, counts = np.unique(bs.aggregate_mean(res), return_counts=True)
    assert set(values.tolist()) == set(exact)  # a joint draw of runs would give only {0, 6, 12}
    for v, c in zip(values.tolist(), counts.tolist(), strict=True):
        p = exact[v]  # binomial frequency: within 5 standard errors
        assert abs(c / n - p) < 5 * np.sqrt(p * (1 - p) / n)


def test_interval_matches_a_direct_numpy_reimplementation():
    x = np.array([[3.0, 7.0], [1.0, 9.0], [4.0, 2.0], [8.0, 5.0], [6.0, 6.0]])
    n = 500
    idx = np.random.default_rng(7).integers(0, 5, size=(n, 5, 2))  # run drawn per (resample, slot, task)
    values = [trim_mean([x[idx[r, i, t], t] for i in range(5) for t in range(2)], 0.25) for r in range(n)]
    expected = np.percentile(values, [2.5, 97.5])
    got = bs.interval([x], bs.iqm, 0.95, n, np.random.default_rng(7))
    assert got == pytest.approx(tuple(expected), rel=1e-12)


def _quantile(dist: dict[float, float], p: float) -> float:
    """The smallest value whose cumulative probability reaches ``p``."""
    total = 0.0
    for v in sorted(dist):
        total += dist[v]
        if total >= p - 1e-12:
            return v
    return max(dist)


def test_one_task_interval_against_exact_enumeration():
    # one task: the ordinary bootstrap over 4 seeds, 4^4 equally likely resamples
    seeds = np.array([0.0, 10.0, 20.0, 100.0])
    dist: dict[float, float] = {}
    for idx in itertools.product(range(4), repeat=4):
        v = float(trim_mean(seeds[list(idx)], 0.25))
        dist[v] = dist.get(v, 0.0) + 1 / 256
    n = 20_000
    eps = 5 * np.sqrt(0.025 * 0.975 / n)  # 5 standard errors of an empirical cdf at 2.5%
    low, high = bs.interval([seeds], bs.iqm, 0.95, n, np.random.default_rng(1))
    assert _quantile(dist, 0.025 - eps) <= low <= _quantile(dist, 0.025 + eps)
    assert _quantile(dist, 0.975 - eps) <= high <= _quantile(dist, 0.975 + eps)
    assert low < bs.point([seeds], bs.iqm) == 15.0 < high


def test_degenerate_and_bad_scores():
    assert bs.interval([[40.0, 40.0]], bs.iqm, 0.95, 100, np.random.default_rng(0)) == (40.0, 40.0)
    with pytest.raises(ValueError, match="at least one run"):
        bs.as_scores([])
    with pytest.raises(ValueError, match="different numbers of tasks"):
        bs.interval([np.zeros((2, 1)), np.zeros((2, 2))], bs.mean_difference, 0.95, 10,
                     np.random.default_rng(0))


# --------------------------------------------------------------------------- P(X > Y)
def test_probability_of_improvement_counts_pairs_with_ties_as_half():
    x, y = [3.0, 4.0, 5.0], [1.0, 4.0, 2.0]
    # pairs x > y: 3 beats 1, 2; 4 beats 1, 2 and ties 4; 5 beats all three -> 7.5 of 9
    assert bs.point([x, y], bs.probability_of_improvement) == pytest.approx(7.5 / 9, rel=1e-12)
    assert bs.point([y, x], bs.probability_of_improvement) == pytest.approx(1.5 / 9, rel=1e-12)
    assert bs.point([x, x], bs.probability_of_improvement) == 0.5
    # two tasks: the mean of the per-task probabilities (task 2: [0, 0] vs [1] -> 0)
    two = bs.point([[[3.0, 0.0], [4.0, 0.0]], [[1.0, 1.0]]], bs.probability_of_improvement)
    assert two == pytest.approx((1.0 + 0.0) / 2)


def test_probability_of_improvement_interval_matches_a_direct_reimplementation():
    x, y = np.array([3.0, 4.0, 5.0, 7.0]), np.array([1.0, 4.0, 2.0])
    n = 400
    rng = np.random.default_rng(3)
    ix = rng.integers(0, 4, size=(n, 4, 1))  # x resampled first, then y, from one generator
    iy = rng.integers(0, 3, size=(n, 3, 1))
    values = []
    for r in range(n):
        xs, ys = x[ix[r, :, 0]], y[iy[r, :, 0]]
        wins = sum(1.0 if a > b else 0.5 if a == b else 0.0 for a in xs for b in ys)
        values.append(wins / (4 * 3))
    expected = np.percentile(values, [2.5, 97.5])
    got = bs.interval([x, y], bs.probability_of_improvement, 0.95, n, np.random.default_rng(3))
    assert got == pytest.approx(tuple(expected), rel=1e-12)


# --------------------------------------------------------------------------- rows
def _runs(root, compose_cfg, mode, seeds, overrides=(), scores=(50, 40)):
    for seed in seeds:
        run = fake_run(root, compose_cfg, mode=mode, seed=seed, env=list(overrides))
        label = {"default": "Default"}.get(mode, mode)
        fake_eval(run / "eval", label, f"seed {seed}", scores[0] + seed, scores[1],
                  meta={"kind": "checkpoint", "run": str(run)})


def test_rows_split_by_differing_config_keys(tmp_path, compose_cfg):
    _runs(tmp_path / "short", compose_cfg, "default", [0, 1], ["total_frames=12000"])
    _runs(tmp_path / "long", compose_cfg, "default", [0, 1, 2], ["total_frames=20000"], scores=(70, 60))
    _runs(tmp_path / "short", compose_cfg, "B", [0, 1], ["total_frames=12000"], scores=(80, 60))
    _runs(tmp_path / "long", compose_cfg, "B", [0, 1], ["total_frames=20000"], scores=(80, 60))
    # differing only in the seed and in keys that cannot change what is learned: one row
    _runs(tmp_path / "a", compose_cfg, "A", [0], ["log_every=7", "progress=true"])
    _runs(tmp_path / "a", compose_cfg, "A", [1], ["checkpoint_every=3", "logger=csv"])
    results = find_results([tmp_path])
    table = {r.label: r for r in stats.table(results, stats.StatsConfig(n_resamples=200))}
    assert list(table) == ["Default (total_frames=12000)", "Default (total_frames=20000)", "A",
                           "B (total_frames=12000)", "B (total_frames=20000)"]
    assert table["Default (total_frames=12000)"].units == ["seed 0", "seed 1"]
    assert table["Default (total_frames=20000)"].units == ["seed 0", "seed 1", "seed 2"]
    assert table["Default (total_frames=20000)"].variant == {"total_frames": 20000}
    assert table["A"].base == "A" and table["A"].units == ["seed 0", "seed 1"]
    # B vs Default compares equal budgets only
    diffs = stats.differences(results, [["B", "Default"]], stats.StatsConfig(n_resamples=200))
    assert sorted({(d.a, d.b) for d in diffs}) == [
        ("B (total_frames=12000)", "Default (total_frames=12000)"),
        ("B (total_frames=20000)", "Default (total_frames=20000)")]


def test_rows_still_split_after_the_runs_moved(tmp_path, compose_cfg):
    _runs(tmp_path / "x", compose_cfg, "B", [0], ["total_frames=100"])
    _runs(tmp_path / "y", compose_cfg, "B", [0], ["total_frames=200"])
    shutil.move(tmp_path / "x", tmp_path / "moved_x")  # eval.json still names the old folder
    labels = [g.label for g in rows.split_rows(find_results([tmp_path]))]
    assert labels == ["B (total_frames=100)", "B (total_frames=200)"]


def test_row_labels_name_nested_keys_and_every_difference(tmp_path, compose_cfg):
    _runs(tmp_path / "x", compose_cfg, "A", [0], ["agent.lr=0.001"])
    _runs(tmp_path / "y", compose_cfg, "A", [0], ["agent.lr=0.0005", "mode.demo_fraction=0.2"])
    labels = [g.label for g in rows.split_rows(find_results([tmp_path]))]
    assert labels == ["A (agent.lr=0.0005, mode.demo_fraction=0.2)",
                      "A (agent.lr=0.001, mode.demo_fraction=0.1)"]


def test_each_seeds_own_stage1_source_does_not_split_a_row(tmp_path, compose_cfg):
    """mode.stage1.init names a different run per seed (``.../B_constant_s${seed}``): one row."""
    for seed in (0, 1):
        _runs(tmp_path / "b", compose_cfg, "B", [seed], [f"mode.stage1.init=/s/B_constant_s{seed}"])
    groups = rows.split_rows(find_results([tmp_path]))
    assert [(g.label, len(g.results)) for g in groups] == [("B", 2)]


def test_ignored_keys_match_the_report_config(compose_cfg):
    assert tuple(compose_cfg("report", ["runs=[.]"]).row_ignore) == rows.IGNORED_KEYS
    assert rows.is_ignored("paths.output_dir", rows.IGNORED_KEYS) and not rows.is_ignored("seeds", ["seed"])


def test_a_run_evaluated_twice_is_refused(tmp_path, compose_cfg):
    _runs(tmp_path, compose_cfg, "B", [0, 1])
    shutil.copytree(tmp_path / "B_0" / "eval", tmp_path / "B_0" / "eval_again")
    with pytest.raises(ValueError, match="was evaluated twice") as err:
        stats.table(find_results([tmp_path]))
    run = tmp_path.resolve() / "B_0"
    assert str(run) in str(err.value) and "\n" not in str(err.value)
    cfg = compose_cfg("report", [f"runs=[{tmp_path}]", *REPORT])
    with pytest.raises(ValueError, match=f"run {run} was evaluated twice"):
        report(cfg, out_dir=tmp_path / "out")


def test_two_runs_of_one_seed_and_configuration_are_refused(tmp_path, compose_cfg):
    _runs(tmp_path / "first", compose_cfg, "B", [0, 1])
    _runs(tmp_path / "again", compose_cfg, "B", [1])  # seed 1 again: it would count twice
    with pytest.raises(ValueError, match="row 'B' has two evaluations of seed 1") as err:
        stats.table(find_results([tmp_path]))
    assert "\n" not in str(err.value)
    # two evaluations of one baseline are the same unit too
    fake_eval(tmp_path / "s1", "scripted", "scripted", 90, 90)
    fake_eval(tmp_path / "s2", "scripted", "scripted", 90, 90)
    with pytest.raises(ValueError, match="row 'scripted' has two evaluations of scripted"):
        stats.table(find_results([tmp_path / "s1", tmp_path / "s2"]))


# --------------------------------------------------------------------------- outputs
def test_report_writes_iqm_and_probability_of_improvement(tmp_path, compose_cfg):
    default = [(10, 10), (20, 20), (30, 30), (100, 40)]
    b = [(20, 10), (40, 20), (50, 30), (60, 40)]
    for mode, per_seed in (("default", default), ("B", b)):
        for seed, (surv, goal) in enumerate(per_seed):
            run = fake_run(tmp_path, compose_cfg, mode=mode, seed=seed)
            fake_eval(run / "eval", {"default": "Default"}.get(mode, mode), f"seed {seed}", surv, goal,
                      meta={"kind": "checkpoint", "run": str(run)})
    files = report(compose_cfg("report", [f"runs=[{tmp_path}]", *REPORT]), out_dir=tmp_path / "out")
    with files.table_csv.open() as f:
        table = {(r["method"], r["initial_lane"], r["metric"]): r for r in csv.DictReader(f)}
    d = table[("Default", "random", "survival")]
    assert float(d["mean"]) == 40.0 and float(d["iqm"]) == 25.0  # middle half {20, 30}
    assert float(d["iqm_low"]) <= 25.0 <= float(d["iqm_high"]) and d["values"] == "10;20;30;100"
    with files.differences_csv.open() as f:
        diffs = {(r["a"], r["initial_lane"], r["metric"]): r for r in csv.DictReader(f)}
    s = diffs[("B", "random", "survival")]
    # B {20, 40, 50, 60} vs Default {10, 20, 30, 100}: wins 1 + 0.5 + 3 + 3 + 3 = 10.5 of 16
    assert float(s["p_improvement"]) == pytest.approx(10.5 / 16, abs=1e-4)
    assert 0 <= float(s["p_low"]) <= 10.5 / 16 <= float(s["p_high"]) <= 1
    assert float(diffs[("B", "random", "goal")]["p_improvement"]) == 0.5  # equal seeds
    # over all columns: the mean of the four columns' P (survival 10.5/16 twice, goal 0.5 twice)
    # and the mean difference over every (seed, column) score (+2.5 twice, 0 twice)
    agg = diffs[("B", "all", "columns")]
    assert float(agg["p_improvement"]) == pytest.approx((2 * 10.5 / 16 + 2 * 0.5) / 4, abs=1e-4)
    assert float(agg["difference"]) == pytest.approx(1.25) and agg["ci_over"] == "seeds"
    assert float(agg["p_low"]) <= float(agg["p_improvement"]) <= float(agg["p_high"])
    md = files.table_md.read_text()
    assert "random survival IQM" in md and "P(a > b)" in md
    assert f"Over all columns: {1.25:+.1f} [" in md and "P(B > Default) = 0.58 [" in md
    assert "| B \u2212 Default | random survival | +2.5 |" in md and "| 0.66 [" in md
    doc = OmegaConf.load(files.report_json)
    assert doc.rows[0].cells["random/survival"].iqm == 25.0
    [p] = [d.p_improvement for d in doc.differences if d.column == "random/survival"]
    assert p == pytest.approx(10.5 / 16)
