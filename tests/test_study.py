"""``memrl.study``: a tiny real study end to end, re-run (nothing retrains, same report), a
killed run resumed, the grid-change refusal, and the command line once.

The tests of one study share its folder (module fixture) and run in file order: the last one
kills a run of it.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from memrl.errors import ConfigError
from memrl.studies.report import DATE_PREFIX, WALL_PREFIX

ROOT = Path(__file__).resolve().parents[1]
TRAIN = ["+experiment=smoke", "total_frames=64", "agent.warmup_frames=16", "buffer.capacity=200",
         "mode.stage1.max_updates=4", "mode.stage1.check_every=2", "env.duration=30", "logger=none",
         "checkpoint_every=1", "eval.every=1", "eval.episodes=1"]
"""The smoke preset shrunk to seconds per run, with a periodic evaluation every episode."""


def quoted(items: list[str]) -> str:
    """A Hydra list of quoted strings (``+x=y`` needs the quotes inside a list)."""
    return "[" + ",".join(f"'{i}'" for i in items) + "]"


def study_overrides(folder: Path, train: list[str] = TRAIN, modes: str = "[Default,B]",
                    report: tuple[str, ...] = (), seeds: str = "[0,1]") -> list[str]:
    return [f"study.dir={folder}", f"study.modes={modes}", f"study.seeds={seeds}",
            f"study.train_overrides={quoted(train)}", "study.workers=1", "study.progress=false",
            f"study.report_overrides={quoted(['n_resamples=200', 'curve_resamples=50', *report])}",
            "protocol.episodes=2", "protocol.duration=30"]


def without_volatile(text: str) -> list[str]:
    return [x for x in text.splitlines() if not x.startswith((WALL_PREFIX, DATE_PREFIX))]


@pytest.fixture(scope="module")
def first(tmp_path_factory):
    """A 2 modes x 2 seeds study, run once."""
    from hydra import compose, initialize_config_dir

    from memrl.configs import register_configs
    from memrl.study import study

    folder = tmp_path_factory.mktemp("study") / "s"
    register_configs()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("study", study_overrides(folder))
    return cfg, study(cfg)


def test_a_tiny_study_trains_evaluates_and_reports(first):
    _, result = first
    folder = result.dir
    assert sorted(result.trained) == ["B_constant_s0", "B_constant_s1", "Default_constant_s0",
                                      "Default_constant_s1"]
    assert result.failed == {} and result.skipped == []
    for run in result.trained:
        assert (folder / "runs" / run / "eval" / "eval.json").is_file()
        assert (folder / "runs" / run / "train.log").stat().st_size > 0
    for name in ("scripted", "random"):
        assert (folder / "baselines" / name / "eval.json").is_file()
    with result.table_csv.open() as f:
        rows = list(csv.DictReader(f))
    assert {r["method"] for r in rows} == {"Default", "B", "scripted", "random"}
    paper = {(r["method"], r["initial_lane"], r["metric"]): r["paper"] for r in rows}
    assert paper[("B", "non_goal", "goal")] == "48" and paper[("Default", "random", "survival")] == "53"
    assert paper[("scripted", "random", "goal")] == ""
    md = result.report.read_text()
    for text in ("| B | 2 |", "| Default | 2 |", "B \u2212 Default", "P(B > Default)", "| B stage 1 |",
                 "B_constant_s1", "machine:", "budget per run: total_frames=64", result.command,
                 "## Non-goal starts by traffic", "| B stage 1 | "):
        assert text in md, text
    walls = [json.loads((folder / "runs" / r / "summary.json").read_text())["train_wall_s"]
             for r in result.trained]
    assert f"- total: training {sum(walls):,.0f} s (sum over 4 runs), evaluation " in md
    # training cost: each run's row from its summary.json, by hand
    cost = md.split("## Training cost")[1].split("## ")[0]
    for run in result.trained:
        s = json.loads((folder / "runs" / run / "summary.json").read_text())
        stage1 = s["stage1"]["updates"] if run.startswith("B_") else 0
        assert stage1 > 0 or run.startswith("Default_")
        wall = s["train_wall_s"]
        assert (f"| {run} | {s['frames']:,} | {s['updates']:,} | {stage1:,} | {wall:,.0f} | "
                f"{s['updates'] / wall:,.1f} | {s['frames'] / wall:,.1f} |") in cost, run
    assert (folder / "fig5.png").is_file() and (folder / "study.json").is_file()
    assert (folder / "fig_stage2.png").is_file() and (folder / "fig7_B.png").is_file()
    assert "![fig_stage2](fig_stage2.png)" in md
    # training episodes: Default's row from its two episodes.csv, by hand
    lengths, late_lengths = [], []
    for seed in (0, 1):
        with (folder / "runs" / f"Default_constant_s{seed}" / "episodes.csv").open() as f:
            eps = list(csv.DictReader(f))
        end = float(eps[-1]["env_steps"])
        lengths.append(sum(float(e["length"]) for e in eps) / len(eps))
        late = [float(e["length"]) for e in eps if float(e["env_steps"]) > 0.75 * end]
        late_lengths.append(sum(late) / len(late))
    training = md.split("## Training episodes")[1].split("## ")[0]
    row = next(x for x in training.splitlines() if x.startswith("| Default | "))
    cells = [c.strip() for c in row.split("|")[1:-1]]
    assert cells[2] == f"{(lengths[0] + lengths[1]) / 2:.1f} ({lengths[0]:.1f}, {lengths[1]:.1f})"
    assert cells[3].startswith(f"{(late_lengths[0] + late_lengths[1]) / 2:.1f} (")
    # survived and reached from non-goal starts: B stage 1's row from its two episodes.csv, by hand
    both = []
    for seed in (0, 1):
        with (folder / "stage1" / f"B_constant_s{seed}" / "episodes.csv").open() as f:
            ng = [e for e in csv.DictReader(f) if e["initial_lane"] == "non_goal"]
        both.append(100 * sum(e["survived"] == "1" and e["goal"] == "1" for e in ng) / len(ng))
    row = f"| B stage 1 | 2 | {(both[0] + both[1]) / 2:.1f} | seed 0: {both[0]:.0f}, seed 1: {both[1]:.0f} |"
    assert row in md


def test_the_report_sets_each_seeds_stage_1_against_its_final_weights(first):
    """Survived and reached (non-goal) per seed, stage-1 weights and final ones, from their two
    episodes.csv by hand; the count of seeds where the final is higher and P(final > stage 1)
    by hand (pairs won, ties 1/2, over n m)."""
    _, result = first
    md = result.report.read_text()

    def both(path):
        with path.open() as f:
            ng = [e for e in csv.DictReader(f) if e["initial_lane"] == "non_goal"]
        return 100 * sum(e["survived"] == "1" and e["goal"] == "1" for e in ng) / len(ng)

    before = [both(result.dir / "stage1" / f"B_constant_s{seed}" / "episodes.csv") for seed in (0, 1)]
    after = [both(result.dir / "runs" / f"B_constant_s{seed}" / "eval" / "episodes.csv") for seed in (0, 1)]
    higher = sum(a > b for a, b in zip(after, before, strict=True))
    p = sum(1.0 if a > b else 0.5 if a == b else 0.0 for a in after for b in before) / 4
    row = (f"| B | {before[0]:.0f}, {before[1]:.0f} | {after[0]:.0f}, {after[1]:.0f} | "
           f"{higher} of 2 | {p:.2f} [")
    assert row in md.split("## Mode B: stage-1 weights against the final weights")[1].split("## ")[0]


def test_gain_counts_higher_seeds_and_the_probability_of_improvement():
    from memrl.evaluation.stats import gain

    g = gain([64, 82, 81], [86, 86, 85])
    assert (g.higher, g.p) == (3, 1.0) and g.p_low == g.p_high == 1.0
    g = gain([80, 81], [81, 78])  # 81 > 80, 81 = 81, 78 < both: (1 + 0.5) / 4
    assert (g.higher, g.p) == (1, 0.375) and 0.0 <= g.p_low <= g.p <= g.p_high <= 1.0
    assert gain([70], [75]).p is None
    with pytest.raises(ValueError, match="2 values before, 1 after"):
        gain([1, 2], [3])


def test_the_report_says_how_each_stage_1_ended(first):
    """One row per B run from its summary.json and config, by hand: the kept check's update,
    its drives, held-out agreement and steering recall (none for Default runs)."""
    _, result = first
    md = result.report.read_text()
    assert "## Mode B: how stage 1 ended" in md and "| Default_constant_s0 | " not in md.split(
        "## Mode B: how stage 1 ended")[1].split("## ")[0]
    for seed in (0, 1):
        run = result.dir / "runs" / f"B_constant_s{seed}"
        s1 = json.loads((run / "summary.json").read_text())["stage1"]
        kept = s1["best_updates"] or s1["updates"]
        i = [d["updates"] for d in s1["drives"]].index(kept) if s1["drives"] else len(s1["agreements"]) - 1
        episodes = int(OmegaConf.load(run / "config.yaml").mode.stage1.drive_episodes)
        drive = f"{s1['drives'][i]['both']} of {episodes}" if s1["drives"] else "\u2014"
        row = (f"| B_constant_s{seed} | {s1['updates']:,} | {s1['stop_reason']} | {kept:,} | {drive} | "
               f"{s1['agreements'][i]:.2f} | {s1['parts'][i]['steering_recall']:.2f} |")
        assert row in md, row


def test_stage1_weights_are_evaluated_from_the_loss_module(first):
    from memrl.checkpoint import load_stage1_qnet

    _, result = first
    run = result.dir / "runs" / "B_constant_s0"
    state = torch.load(run / "checkpoints" / "stage1.pt", weights_only=False)["loss_module"]
    net = load_stage1_qnet(run)
    online = {k: v for k, v in state.items() if k.startswith("value_network_params.")}
    assert len(online) == len(net.state_dict())
    assert all(any(torch.equal(v, w) for w in online.values()) for v in net.state_dict().values())
    doc = json.loads((result.dir / "stage1" / "B_constant_s0" / "eval.json").read_text())
    assert doc["name"] == "B stage 1" and doc["meta"]["run"] == str(run)


def test_running_it_again_retrains_nothing_and_writes_the_same_report(first):
    from memrl.study import study

    cfg, result = first
    runs = sorted((result.dir / "runs").glob("*/checkpoints/final.pt"))
    before = {p: p.stat().st_mtime_ns for p in runs}
    evals = {p: p.stat().st_mtime_ns for p in result.dir.glob("**/eval.json")}
    text = result.report.read_text()
    again = study(cfg)
    assert again.trained == [] and again.resumed == [] and sorted(again.skipped) == sorted(result.trained)
    assert again.evaluated == [] and len(again.reused) == 8  # 4 runs, 2 stage-1 weights, 2 baselines
    assert {p: p.stat().st_mtime_ns for p in runs} == before
    assert {p: p.stat().st_mtime_ns for p in result.dir.glob("**/eval.json")} == evals
    assert without_volatile(again.report.read_text()) == without_volatile(text)


def test_a_second_call_reports_the_same_runs_against_mixed_traffic_beside_the_constant_report(first):
    """protocol.opponent=mixed: evaluations into eval_mixed/ (and *_mixed/), the report into
    test_mixed/; the constant evaluations and report stay as they were, and a constant call
    afterwards still reports (and reuses) only its own."""
    from hydra import compose, initialize_config_dir

    from memrl.evaluation.results import read_result
    from memrl.study import study

    cfg, result = first
    folder = result.dir
    constant = {p: p.read_bytes() for p in folder.glob("**/eval.json")}
    assert len(constant) == 8
    report = result.report.read_text()
    assert ", constant-speed cars" in report
    pool = folder / "runs" / "Default_constant_s0"
    mixed = f"protocol.opponent={{type:mixed,learned_fraction:0.5,pool:['{pool}'],epsilon:0.0}}"
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        mcfg = compose("study", [*study_overrides(folder), "study.train=false", mixed])
    out = study(mcfg)
    assert out.report == folder / "test_mixed" / "report.md" and out.trained == []
    made = sorted(Path(p).relative_to(folder).as_posix() for p in out.evaluated)
    assert made == ["baselines/random_mixed", "baselines/scripted_mixed",
                    "runs/B_constant_s0/eval_mixed", "runs/B_constant_s1/eval_mixed",
                    "runs/Default_constant_s0/eval_mixed", "runs/Default_constant_s1/eval_mixed",
                    "stage1/B_constant_s0_mixed", "stage1/B_constant_s1_mixed"]
    for place in made:
        r = read_result(folder / place)
        assert r.protocol["opponent"]["type"] == "mixed" and r.protocol["opponent"]["pool"] == [str(pool)]
        assert r.env["opponent"]["type"] == "mixed"
    assert {p: p.read_bytes() for p in constant} == constant
    assert result.report.read_text() == report
    md = out.report.read_text()
    assert "mixed cars (each driven by one of 1 past agent with probability 0.5)" in md
    assert "`eval_mixed/`" in md and "| B stage 1 | 2 |" in md
    assert (folder / "test_mixed" / "table3.csv").is_file() and (folder / "test_mixed" / "fig5.png").is_file()
    again = study(cfg)  # constant again: its own 8 evaluations, none of the mixed ones
    assert again.evaluated == [] and len(again.reused) == 8
    assert all("_mixed" not in p for p in again.reused)
    assert without_volatile(again.report.read_text()) == without_volatile(report)


def test_a_killed_run_resumes_and_only_it(first):
    """study.status says where each run stands; the study then trains just what is left."""
    from memrl.study import study, study_status

    cfg, result = first
    run = result.dir / "runs" / "B_constant_s1"
    (run / "summary.json").unlink()  # as if killed after its last checkpoint
    (run / "checkpoints" / "final.pt").unlink()
    (result.dir / "runs" / "Default_constant_s1" / "eval" / "eval.json").unlink()
    shutil.rmtree(result.dir / "runs" / "Default_constant_s0")  # as if never started
    lines = study_status(cfg)  # reads the folder, changes nothing
    assert lines[1] == "2 finished, 1 resumable, 1 not started of 4 runs; 2 evaluated"
    state = torch.load(run / "checkpoints" / "last" / "state.pt", weights_only=False)["counters"]
    with (run / "updates.csv").open() as f:
        last = list(csv.DictReader(f))[-1]
    assert (f"| B_constant_s1 | resumable | {last['stage']} | {int(last['env_steps']):,} | "
            f"{int(last['updates']):,} | 64 env steps | B2: {state['frames']:,} env steps, "
            f"{state['updates']:,} updates | yes |") in lines
    assert "| Default_constant_s0 | not started |  |  |  | 64 env steps |  | no |" in lines
    from memrl.run_lock import run_lock

    with run_lock(run):  # as a process training it holds it
        assert "| B_constant_s1 | running | " in "\n".join(study_status(cfg))
    done = json.loads((result.dir / "runs" / "Default_constant_s1" / "summary.json").read_text())
    assert (f"| Default_constant_s1 | finished | default | {done['frames']:,} | {done['updates']:,} | "
            "64 env steps |  | no |") in lines
    assert not (run / "summary.json").exists() and not (result.dir / "runs" / "Default_constant_s0").exists()
    # an interim report (study.train=false): the finished runs only, nothing trained
    interim_cfg = cfg.copy()
    interim_cfg.study.train = False
    interim = study(interim_cfg)
    assert interim.trained == interim.resumed == [] and interim.failed == {}
    assert sorted(interim.skipped) == ["B_constant_s0", "Default_constant_s1"]
    assert interim.evaluated == [str(result.dir / "runs" / "Default_constant_s1" / "eval")]
    md = interim.report.read_text()
    assert "(2 of 4 runs finished)" in md and "Not finished: Default_constant_s0, B_constant_s1." in md
    assert "| B | 1 |" in md and "| Default | 1 |" in md
    assert not (run / "summary.json").exists() and not (result.dir / "runs" / "Default_constant_s0").exists()
    again = study(cfg)
    assert again.resumed == ["B_constant_s1"] and again.trained == ["Default_constant_s0"]
    assert len(again.skipped) == 2
    # the resumed run's evaluation (its stage-1 weights did not change) and the new run's
    assert sorted(again.evaluated) == sorted([
        str(run / "eval"), str(result.dir / "runs" / "Default_constant_s0" / "eval")])
    assert (run / "summary.json").is_file() and "| B | 2 |" in again.report.read_text()
    resumed = json.loads((run / "summary.json").read_text())  # both calls' training time
    assert resumed["train_wall_s"] > resumed["wall_s"] > 0


def test_a_runs_training_time_counts_every_call_or_is_said_to_be_unknown():
    from memrl.studies.report import train_wall, training_total

    assert train_wall({"wall_s": 5.0, "train_wall_s": 12.5, "resumed_from_episode": 4}) == 12.5
    assert train_wall({"wall_s": 5.0, "resumed_from_episode": None}) == 5.0  # one call: all of it
    # resumed from a checkpoint that did not record the earlier calls' time
    assert train_wall({"wall_s": 5.0, "resumed_from_episode": 4}) is None
    assert train_wall({"wall_s": 5.0, "train_wall_s": None, "resumed_from_episode": 4}) is None
    assert training_total([12.5, None, 5.0]) == ("training 18 s (sum over 2 runs) (1 resumed from "
                                                 "checkpoints that did not record it: not counted)")
    assert training_total([None, None]).startswith("training time unknown (2 resumed")


def test_an_interim_report_of_a_study_with_no_finished_run_is_refused(tmp_path, compose_cfg):
    from memrl.study import study

    folder = tmp_path / "s"
    with pytest.raises(ConfigError, match="study.train.*none has finished yet") as info:
        study(compose_cfg("study", [*study_overrides(folder), "study.train=false"]))
    assert "\n" not in str(info.value) and not folder.exists()  # nothing written, no baseline run


def test_changing_the_train_overrides_of_a_study_is_refused(tmp_path, compose_cfg):
    from memrl.study import check_record, study

    folder = tmp_path / "s"
    check_record(folder, compose_cfg("study", study_overrides(folder)))
    changed = compose_cfg("study", study_overrides(folder, [*TRAIN, "agent.lr=0.001"]))
    with pytest.raises(ConfigError, match="study.train_overrides") as info:
        study(changed)
    assert "\n" not in str(info.value) and "allow_changes" in str(info.value)
    assert sorted(p.name for p in folder.iterdir()) == [".study.json.lock", "study.json"]  # nothing trained
    allowed = compose_cfg("study", [*study_overrides(folder, [*TRAIN, "agent.lr=0.001"]),
                                    "study.allow_changes=true"])
    check_record(folder, allowed)
    doc = json.loads((folder / "study.json").read_text())
    assert doc["train_overrides"][-1] == "agent.lr=0.001" and len(doc["changes"]) == 1


def test_a_damaged_study_record_is_refused_in_one_line_and_kept(tmp_path, compose_cfg):
    from memrl.errors import UserError, one_line
    from memrl.study import check_record

    folder = tmp_path / "s"
    check_record(folder, compose_cfg("study", study_overrides(folder)))
    record = folder / "study.json"
    whole = record.read_text()
    record.write_text(whole[: len(whole) // 2])  # as a reader saw a record written in place
    with pytest.raises(UserError) as info:
        check_record(folder, compose_cfg("study", study_overrides(folder)))
    assert one_line(info.value).startswith(f"{record}: unreadable (") and "remove it" in str(info.value)
    assert record.read_text() == whole[: len(whole) // 2]  # left for the user to restore
    record.write_text("[1, 2]")
    with pytest.raises(UserError, match="not a study record"):
        check_record(folder, compose_cfg("study", study_overrides(folder)))


def test_the_record_is_replaced_whole_under_the_folder_lock(tmp_path, compose_cfg, monkeypatch):
    """Two study calls on one folder (one process per mode): the record is read and written
    under the folder's lock, and replaced at once, never written in place."""
    import os

    from filelock import FileLock, Timeout

    from memrl.study import check_record

    folder = tmp_path / "s"
    check_record(folder, compose_cfg("study", study_overrides(folder)))
    old = (folder / "study.json").read_text()
    seen = []
    real = os.replace

    def replace(src, dst):
        seen.append(((folder / "study.json").read_text(), json.loads(open(src).read())["seeds"]))
        with pytest.raises(Timeout):  # the call holds the lock while it writes
            FileLock(folder / ".study.json.lock", timeout=0).acquire()
        return real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    check_record(folder, compose_cfg("study", study_overrides(folder, seeds="[0,1,2]")))
    assert seen == [(old, [0, 1, 2])]  # the old record whole until the new one replaced it
    assert json.loads((folder / "study.json").read_text())["seeds"] == [0, 1, 2]
    assert sorted(p.name for p in folder.iterdir()) == [".study.json.lock", "study.json"]  # no temp file left


def test_train_overrides_reach_every_run_and_the_grid_keys_are_its_own(tmp_path, compose_cfg):
    from memrl.studies.grid import cells

    train = [*TRAIN, "agent.lr=0.0005", "env.num_envs=2", "device=cpu"]
    cfg = compose_cfg("study", [*study_overrides(tmp_path, train, "[A,B]"), "study.opponents=[constant]"])
    grid = cells(cfg.study, tmp_path / "runs")
    assert [c.name for c in grid] == ["A_constant_s0", "A_constant_s1", "B_constant_s0", "B_constant_s1"]
    assert all(c.cfg.agent.lr == 0.0005 and c.cfg.total_frames == 64 for c in grid)
    assert all(c.cfg.env.num_envs == 2 and c.cfg.device == "cpu" for c in grid)
    assert [c.cfg.mode.name for c in grid] == ["A", "A", "B", "B"] and grid[1].cfg.seed == 1


def test_jobs_train_in_spawned_processes_and_a_failing_run_lets_the_others_finish(tmp_path):
    from omegaconf import OmegaConf

    from memrl.studies.grid import Cell, run_cells
    from tests.study_helpers import fake_trainer

    grid = [Cell("Default", "constant", s, tmp_path / f"Default_constant_s{s}", [], OmegaConf.create({}))
            for s in (0, 1, 2)]
    seen: list[str] = []
    out = run_cells(grid, jobs=2, trainer=fake_trainer, finished=lambda c: seen.append(c.name))
    assert out.trained == ["Default_constant_s0", "Default_constant_s2"]  # the grid's order
    assert sorted(seen) == out.trained  # each finished run, once, in this process; not the failed one
    assert out.failed == {"Default_constant_s1": "RuntimeError: Default_constant_s1 diverged"}
    again = run_cells(grid, jobs=2, trainer=fake_trainer, finished=lambda c: seen.append(c.name))
    assert again.skipped == out.trained and list(again.failed) == ["Default_constant_s1"]
    assert len(seen) == 2  # skipped runs are not finished again


def test_each_run_is_evaluated_as_it_finishes_and_the_report_reuses_it(tmp_path, compose_cfg):
    from memrl.study import study

    folder = tmp_path / "s"
    result = study(compose_cfg("study", [*study_overrides(folder, modes="[Default]"), "study.baselines=[]"]))
    runs = [folder / "runs" / f"Default_constant_s{seed}" for seed in (0, 1)]
    # seed 0's evaluation was written before seed 1 began training
    assert (runs[0] / "eval" / "eval.json").stat().st_mtime_ns < (runs[1] / "config.yaml").stat().st_mtime_ns
    assert sorted(result.evaluated) == [str(r / "eval") for r in runs] and result.reused == []
    assert result.report.is_file()


def test_evaluate_none_trains_only_and_the_same_command_reports_later(tmp_path, compose_cfg):
    from memrl.study import study

    folder = tmp_path / "s"
    args = [*study_overrides(folder, modes="[Default]", seeds="[0]"), "study.baselines=[]"]
    trained = study(compose_cfg("study", [*args, "study.evaluate=none"]))
    run = folder / "runs" / "Default_constant_s0"
    assert trained.trained == ["Default_constant_s0"] and trained.evaluated == []
    assert (run / "checkpoints" / "final.pt").is_file() and not (run / "eval").exists()
    assert not (folder / "report.md").exists()
    with pytest.raises(ConfigError, match="study.evaluate.*neither train nor evaluate") as info:
        study(compose_cfg("study", [*args, "study.evaluate=none", "study.train=false"]))
    assert "\n" not in str(info.value)
    later = study(compose_cfg("study", [*args, "study.train=false"]))
    assert later.skipped == ["Default_constant_s0"] and later.evaluated == [str(run / "eval")]
    assert later.report.is_file() and "Default_constant_s0" in later.report.read_text()


def test_the_command_line_runs_a_study(tmp_path):
    folder = tmp_path / "cli"
    args = [*study_overrides(folder, modes="[Default]", report=("rollouts.rows=[]",)),
            "study.seeds=[0]", "study.baselines=[random]"]
    env = {**os.environ, "MEMRL_ROOT": str(tmp_path), "SDL_VIDEODRIVER": "dummy"}
    proc = subprocess.run([sys.executable, "-m", "memrl.study", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (folder / "runs" / "Default_constant_s0" / "summary.json").is_file()
    md = (folder / "report.md").read_text()
    assert "| Default | 1 |" in md and "| random | 1 |" in md
    assert (folder / "study.log").is_file() and "python -m memrl.study study.dir=" in md
    sight = md[md.index("## Does the learner see its crash coming"):].split("\n## ")[0].splitlines()
    assert any(line.startswith("| Default | non-goal |") for line in sight)
    assert not any(line.startswith("| random |") for line in sight)  # the random policy has no Q-values


VARIANTS = "{paths:['env.bev.path_time=2'],plain:['env.bev.path_time=0']}"
"""Two variants of the tiny study: every car's path drawn into the view, or not."""


def test_a_study_of_variants_trains_reports_and_compares_each_variant_on_its_own(tmp_path, compose_cfg):
    from memrl.study import study

    folder = tmp_path / "v"
    cfg = compose_cfg("study", [*study_overrides(folder, report=("rollouts.rows=[]",)), "study.seeds=[0]",
                                f"study.variants={VARIANTS}", "study.baselines=[random]"])
    result = study(cfg)
    assert sorted(result.trained) == ["paths_B_constant_s0", "paths_Default_constant_s0",
                                      "plain_B_constant_s0", "plain_Default_constant_s0"]
    for name, seconds in (("paths", 2.0), ("plain", 0.0)):
        for mode in ("Default", "B"):
            saved = (folder / "runs" / f"{name}_{mode}_constant_s0" / "config.yaml").read_text()
            assert f"path_time: {seconds}" in saved and f"variant: {name}" in saved
        doc = json.loads((folder / "stage1" / f"{name}_B_constant_s0" / "eval.json").read_text())
        assert doc["name"] == f"B ({name}) stage 1"
    with result.table_csv.open() as f:
        rows = list(csv.DictReader(f))
    assert {r["method"] for r in rows} == {"Default (paths)", "B (paths)", "Default (plain)",
                                           "B (plain)", "random"}
    assert all(r["paper"] == "" for r in rows if "(" in r["method"])  # not the paper's setting
    with (folder / "differences.csv").open() as f:
        pairs = {(r["a"], r["b"]) for r in csv.DictReader(f)}
    assert pairs == {("B (paths)", "Default (paths)"), ("B (plain)", "Default (plain)")}
    md = result.report.read_text()
    for text in ("| B (paths) | 1 |", "| Default (plain) | 1 |", "| B (plain) stage 1 |",
                 "grid: variants paths, plain \u00d7 modes Default, B",
                 "- variant paths: `env.bev.path_time=2`",
                 "| B (paths) \u2212 Default (paths) | random goal |", "| paths_B_constant_s0 |",
                 'study.variants={paths:["env.bev.path_time=2"],plain:["env.bev.path_time=0"]}'):
        assert text in md, text
    assert json.loads((folder / "study.json").read_text())["variants"] == {
        "paths": ["env.bev.path_time=2"], "plain": ["env.bev.path_time=0"]}


def test_without_variants_the_run_folders_and_labels_are_unchanged(tmp_path, compose_cfg):
    from memrl.studies.grid import cells

    plain = cells(compose_cfg("study", study_overrides(tmp_path)).study, tmp_path / "runs")
    assert [(c.name, c.label) for c in plain] == [
        ("Default_constant_s0", "Default"), ("Default_constant_s1", "Default"),
        ("B_constant_s0", "B"), ("B_constant_s1", "B")]
    assert all(c.cfg.variant is None and c.variant is None for c in plain)
    cfg = compose_cfg("study", [*study_overrides(tmp_path, [*TRAIN, "env.bev.path_time=1"], "[B]"),
                                "study.seeds=[0]", "study.opponents=[mixed]",
                                "study.variants={paths:['env.bev.path_time=3'],base:[]}"])
    grid = cells(cfg.study, tmp_path / "runs")
    assert [(c.name, c.label) for c in grid] == [("paths_B_mixed_s0", "B (paths, mixed)"),
                                                 ("base_B_mixed_s0", "B (base, mixed)")]
    assert [c.cfg.env.bev.path_time for c in grid] == [3.0, 1.0]  # the variant's after the study's


def test_a_test_traffic_of_agents_trained_on_other_frames_is_refused_before_any_write(tmp_path, compose_cfg):
    """protocol.opponent's learned cars drive on each run's frames: a pool agent trained on the
    paper's plain frames cannot test runs of memrl's default frames (every car's path drawn),
    so the study stops at its start naming the file, before training anything."""
    from memrl.checkpoint import save_qnet
    from memrl.checkpoint.opponents import OpponentPoolError
    from memrl.modules.qnet import QNetwork
    from memrl.study import study

    plain = save_qnet(tmp_path / "plain" / "final.pt", QNetwork(), {"bev": {"path_time": 0.0}})
    folder = tmp_path / "s"
    mixed = f"protocol.opponent={{type:mixed,learned_fraction:0.5,pool:['{plain}'],epsilon:0.0}}"
    with pytest.raises(OpponentPoolError) as info:
        study(compose_cfg("study", [*study_overrides(folder), mixed]))
    assert str(plain) in str(info.value) and "bev.path_time 0.0 there, 2.0 here" in str(info.value)
    assert not folder.exists()


@pytest.mark.parametrize(("variants", "key", "text"), [
    ("{c*u:['env.bev.path_length=20']}", "study.variants", "variant name 'c*u'"),
    ("{a b:['env.bev.path_length=20']}", "study.variants", "variant name 'a b'"),
    ("{.cue:['env.bev.path_length=20']}", "study.variants", "variant name '.cue'"),
    ("[cue]", "study.variants", "give a mapping of names to lists"),
    ("{cue:['env.bev.path_length']}", "study.variants.cue", "give key=value overrides"),
    ("{cue:['seed=3']}", "study.variants.cue", "give key=value overrides"),
])
def test_a_bad_variant_is_refused_with_one_line(tmp_path, compose_cfg, variants, key, text):
    from memrl.study import study

    folder = tmp_path / "s"
    cfg = compose_cfg("study", [*study_overrides(folder), f"study.variants={variants}"])
    with pytest.raises(ConfigError) as info:
        study(cfg)
    message = str(info.value)
    assert message.startswith(f"config '{key}':") and text in message and "\n" not in message
    assert not folder.exists()  # refused before any write


def test_adding_or_changing_a_variant_of_a_study_needs_allow_changes(tmp_path, compose_cfg):
    from memrl.study import check_record

    folder = tmp_path / "s"

    def cfg(variants: str | None, *extra: str):
        return compose_cfg("study", [*study_overrides(folder), *extra,
                                     *([f"study.variants={variants}"] if variants else [])])

    check_record(folder, cfg(None))  # a study made without variants
    for variants in ("{cue:['env.bev.path_length=20']}", "{cue:['env.bev.path_length=20'],nocue:[]}"):
        with pytest.raises(ConfigError, match="study.variants") as info:
            check_record(folder, cfg(variants))
        assert "\n" not in str(info.value) and "allow_changes" in str(info.value)
    check_record(folder, cfg("{cue:['env.bev.path_length=20'],nocue:[]}", "study.allow_changes=true"))
    check_record(folder, cfg("{cue:['env.bev.path_length=20']}"))  # a subset: no change
    with pytest.raises(ConfigError, match="study.variants"):
        check_record(folder, cfg("{cue:['env.bev.path_length=10']}"))
    doc = json.loads((folder / "study.json").read_text())
    assert doc["variants"] == {"cue": ["env.bev.path_length=20"], "nocue": []}
    assert [c["key"] for c in doc["changes"]] == ["study.variants"]


def test_a_run_saved_before_the_variant_key_still_resumes(compose_cfg):
    from memrl.checkpoint.resume import comparable, config_diff, with_legacy_values
    from memrl.modes import MODES, used

    cfg = compose_cfg("train", MODES["default"].own_overrides(TRAIN))  # a Default cell's config
    old = {k: v for k, v in comparable(cfg).items() if k != "variant"}  # a checkpoint's config then
    # compared as a resume compares them: the keys the run's mode reads (memrl.modes.used)
    assert cfg.variant is None and config_diff(used(with_legacy_values(old)), used(comparable(cfg))) == []


def test_a_study_continues_an_earlier_studys_runs_to_a_bigger_budget(tmp_path, compose_cfg):
    """study.extend_from: the earlier run, copied and resumed, ends as an uninterrupted run at
    the bigger budget ends; the earlier study stays as it was; bad sources are refused."""
    from memrl.checkpoint import resume as ckpt
    from memrl.study import study

    long = [*TRAIN, "total_episodes=null"]  # the smoke preset also stops at 3 episodes
    short = [o if o != "total_frames=64" else "total_frames=32" for o in long]
    extra = ["study.baselines=[]"]
    first = study(compose_cfg("study", [*study_overrides(tmp_path / "a", short, "[B]", seeds="[0]"), *extra]))
    fresh = study(compose_cfg("study", [*study_overrides(tmp_path / "c", long, "[B]", seeds="[0]"), *extra]))
    src = first.dir / "runs" / "B_constant_s0"
    kept = {p: p.read_bytes() for p in src.rglob("*") if p.is_file() and "checkpoints" in p.parts}
    ended = json.loads((src / "summary.json").read_text())
    assert 32 <= ended["frames"] < 64 and fresh.trained == ["B_constant_s0"]

    ext = study(compose_cfg("study", [*study_overrides(tmp_path / "b", long, "[B]", seeds="[0]"), *extra,
                                      f"study.extend_from={first.dir}"]))
    assert ext.extended == ext.resumed == ["B_constant_s0"] and ext.trained == []
    run, ref = ext.dir / "runs" / "B_constant_s0", fresh.dir / "runs" / "B_constant_s0"
    done, uninterrupted = (json.loads((r / "summary.json").read_text()) for r in (run, ref))
    assert done["resumed_from_episode"] == ended["episodes"]
    for key in ("frames", "episodes", "updates", "stage"):
        assert done[key] == uninterrupted[key], key
    assert done["frames"] >= 64
    a = torch.load(run / "checkpoints" / "final.pt", weights_only=False)["qnet"]
    b = torch.load(ref / "checkpoints" / "final.pt", weights_only=False)["qnet"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert (run / "episodes.csv").read_text() == (ref / "episodes.csv").read_text()
    assert json.loads((ext.dir / "study.json").read_text())["extended"] == {"B_constant_s0": str(src)}
    # the earlier run is untouched (its checkpoint files were linked, not moved or rewritten)
    assert {p: p.read_bytes() for p in kept} == kept and (src / "summary.json").is_file()
    ckpt.check_manifest(ckpt.find(src))
    # again: the continued run is finished now, nothing is copied or trained
    again = study(compose_cfg("study", [*study_overrides(tmp_path / "b", long, "[B]", seeds="[0]"), *extra,
                                        f"study.extend_from={first.dir}"]))
    assert again.extended == again.trained == again.resumed == [] and again.skipped == ["B_constant_s0"]
    assert json.loads((ext.dir / "study.json").read_text())["extended"] == {"B_constant_s0": str(src)}  # kept

    refusals = [
        ([*long, "agent.lr=0.001"], str(first.dir), "agent.lr"),
        (short, str(first.dir), "already within this study's budget"),
        (long, str(tmp_path / "nowhere"), "holds no runs/"),
        (long, str(tmp_path / "d"), "this study's own folder"),
        (long, str(tmp_path / "unfinished"), "has not finished"),
    ]
    shutil.copytree(first.dir, tmp_path / "unfinished")
    (tmp_path / "unfinished" / "runs" / "B_constant_s0" / "summary.json").unlink()
    for train, earlier, text in refusals:
        with pytest.raises(ConfigError, match="study.extend_from") as info:
            study(compose_cfg("study", [*study_overrides(tmp_path / "d", train, "[B]", seeds="[0]"), *extra,
                                        f"study.extend_from={earlier}"]))
        assert text in str(info.value) and "\n" not in str(info.value)
        assert not (tmp_path / "d").exists()  # nothing written


def test_a_continued_run_links_its_checkpoint_files_and_copies_what_it_appends_to(tmp_path):
    """Decided inside the run folder: an earlier study kept under a folder named checkpoints
    still gets its CSVs copied (a resume appends to them), not linked."""
    from memrl.studies.extend import copy_run

    src = tmp_path / "checkpoints" / "runs" / "B_constant_s0"
    for name in ("episodes.csv", "summary.json", "checkpoints/last/state.pt", "checkpoints/final.pt",
                 "eval/eval.json"):
        (src / name).parent.mkdir(parents=True, exist_ok=True)
        (src / name).write_text(name)
    dst = tmp_path / "copy"
    copy_run(src, dst)
    files = sorted(str(p.relative_to(dst)) for p in dst.rglob("*") if p.is_file())
    assert files == ["checkpoints/last/state.pt", "episodes.csv"]
    def inode(path: Path) -> int:
        return path.stat().st_ino

    assert inode(dst / "checkpoints/last/state.pt") == inode(src / "checkpoints/last/state.pt")
    assert inode(dst / "episodes.csv") != inode(src / "episodes.csv")
    assert (dst / "episodes.csv").read_text() == "episodes.csv"
