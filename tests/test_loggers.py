"""TorchRL logger backends: one env-step x-axis, stage-1 points, hyperparameters, resume, extras."""

from __future__ import annotations

import csv
import importlib.util
import io
import json
import logging
import re
import sys
from pathlib import Path

import pytest

from memrl.dqn.loop import Trainer
from memrl.loggers import LoggerBackendMissing, check_backend, flat_hparams, run_name
from memrl.train import train
from tests.helpers import TINY, csv_rows, tiny

TIMING = ("train/updates_per_s", "train/frames_per_s", "stage1/updates_per_s", "stage1/frames_per_s")
"""Points whose values depend on the machine's speed (their steps must still match)."""


rows = csv_rows


def tb_events(log_dir: Path) -> list:
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    return [event for path in sorted(log_dir.glob("events.out.tfevents.*"))
            for event in EventFileLoader(str(path)).Load()]


def points(run_dir: Path, backend: str) -> dict[str, list[tuple[int, float]]]:
    """Every scalar the backend holds, as ``{tag: [(step, value), ...]}`` in logging order."""
    out: dict[str, list[tuple[int, float]]] = {}
    base = run_dir / "logs" / "train"
    if backend == "csv":
        for path in sorted((base / "scalars").rglob("*.csv")):
            tag = path.relative_to(base / "scalars").with_suffix("").as_posix()
            out[tag] = [(int(s), float(v)) for s, v in csv.reader(path.open())]
    else:  # tensorboard: the raw events of every event file (no purge of out-of-order steps)
        from tensorboard.util.tensor_util import make_ndarray

        for event in tb_events(base):
            for value in event.summary.value:
                number = float(make_ndarray(value.tensor)) if value.HasField("tensor") \
                    else value.simple_value
                out.setdefault(value.tag, []).append((event.step, number))
    return out


BACKENDS = ["csv", pytest.param("tensorboard", marks=pytest.mark.skipif(
    importlib.util.find_spec("tensorboard") is None, reason="tensorboard not installed"))]


@pytest.mark.parametrize("backend", BACKENDS)
def test_episode_update_and_eval_points_share_the_env_step_axis(compose_cfg, tmp_path, backend):
    cfg = compose_cfg("train", TINY + [f"logger={backend}", "eval.every=3", "eval.episodes=1"])
    train(cfg, tmp_path)
    got = points(tmp_path, backend)
    episodes, updates = rows(tmp_path / "episodes.csv"), rows(tmp_path / "updates.csv")
    assert [s for s, _ in got["episode/return"]] == [int(r["env_steps"]) for r in episodes]
    assert [v for _, v in got["episode/return"]] == [float(r["return"]) for r in episodes]
    assert [s for s, _ in got["episode/epsilon"]] == [int(r["env_steps"]) for r in episodes]
    assert len(updates) >= 2
    assert got["train/loss"] == [(int(r["env_steps"]), pytest.approx(float(r["loss"])))
                                 for r in updates]
    assert got["train/updates"] == [(int(r["env_steps"]), float(r["updates"])) for r in updates]
    assert [s for s, _ in got["eval/survival_random"]] == [int(episodes[2]["env_steps"])]
    assert not any(tag.startswith("stage1/") for tag in got)


def test_mode_b_logs_stage1_loss_agreement_and_drives_against_its_updates(
        compose_cfg, tmp_path, demos, monkeypatch):
    import memrl.dqn.stage1 as stage1

    monkeypatch.setattr(stage1, "drive_check",
                        lambda *a, **k: {"survived": 3, "reached": 2, "both": 1})
    cfg = compose_cfg("train", tiny("B") + ["logger=csv", "mode.stage1.drive_episodes=4",
                                       "mode.stage1.criterion=max_updates"])
    summary = train(cfg, tmp_path, demos=demos)
    got = points(tmp_path, "csv")
    updates = rows(tmp_path / "updates.csv")
    stage1 = [r for r in updates if r["stage"] == "B1"]
    stage2 = [r for r in updates if r["stage"] == "B2"]
    assert stage1 and stage2
    # stage 1 takes no env step: its points are at its updates, the rest at env steps
    assert [s for s, _ in got["stage1/loss"]] == [int(r["updates"]) for r in stage1]
    assert [s for s, _ in got["train/loss"]] == [int(r["env_steps"]) for r in stage2]
    checks = [4, 8, 12]  # check_every=4, max_updates=12
    assert summary.stage1["updates"] == 12
    assert got["stage1/agreement"] == [(u, pytest.approx(a)) for u, a in
                                       zip(checks, summary.stage1["agreements"], strict=True)]
    assert [s for s, _ in got["stage1/agreement_steering_recall"]] == checks
    assert got["stage1/drive_both"] == [(u, 1.0) for u in checks]
    assert [s for s, _ in got["stage1/check_loss"]] == checks


def test_flat_hparams_of_the_resolved_config():
    flat = flat_hparams({"agent": {"lr": 1e-3, "overlap": True}, "env": {"lanes": [0, 5]},
                         "resume": None, "task_name": "train"})
    assert flat == {"agent.lr": 1e-3, "agent.overlap": True, "env.lanes": "[0, 5]",
                    "resume": "null", "task_name": "train"}


@pytest.mark.parametrize("backend", BACKENDS)
def test_resolved_config_is_logged_as_hyperparameters(compose_cfg, tmp_path, backend):
    cfg = compose_cfg("train", TINY + [f"logger={backend}", "total_episodes=1"])
    train(cfg, tmp_path)
    if backend == "csv":
        text = (tmp_path / "logs" / "train" / "texts" / "hparams0.txt").read_text()
        lines = set(text.splitlines())
        assert {"agent.lr: 0.00025", "env.duration: 30", "logger._target_: "
                "torchrl.record.loggers.csv.CSVLogger", f"paths.output_dir: {tmp_path}"} <= lines
        return
    from tensorboard.plugins.hparams.plugin_data_pb2 import HParamsPluginData

    (session,) = [p for p in (tmp_path / "logs" / "train").iterdir() if p.is_dir()]
    hparams = {}
    for event in tb_events(session):
        for value in event.summary.value:
            if value.tag == "_hparams_/session_start_info":
                data = HParamsPluginData.FromString(value.metadata.plugin_data.content)
                hparams = dict(data.session_start_info.hparams)
    assert hparams["agent.lr"].number_value == pytest.approx(0.00025)
    assert hparams["env.duration"].number_value == 30
    assert hparams["paths.output_dir"].string_value == str(tmp_path)


class Killed(RuntimeError):
    pass


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("mode", [None, "B"])
def test_a_resumed_run_logs_each_point_once_as_the_uninterrupted_run(
        compose_cfg, tmp_path, demos, monkeypatch, backend, mode):
    extra = ["total_episodes=6", "checkpoint_every=2", f"logger={backend}"]
    train(compose_cfg("train", tiny(mode) + extra), tmp_path / "full", demos=demos)
    original = Trainer._episodes_done

    def dying(self, ends):  # killed after episode 5: it (after the checkpoint at 4) is redone
        original(self, ends)
        if self.counters.episodes == 5:
            raise Killed("simulated kill")

    monkeypatch.setattr(Trainer, "_episodes_done", dying)
    with pytest.raises(Killed):
        train(compose_cfg("train", tiny(mode) + extra), tmp_path / "cut", demos=demos)
    monkeypatch.setattr(Trainer, "_episodes_done", original)
    before = points(tmp_path / "cut", backend)
    assert [s for s, _ in before["episode/return"]] == [
        int(r["env_steps"]) for r in rows(tmp_path / "cut" / "episodes.csv")[:4]]
    train(compose_cfg("train", tiny(mode) + extra + [f"resume={tmp_path / 'cut'}"]), demos=demos)

    full, resumed = points(tmp_path / "full", backend), points(tmp_path / "cut", backend)
    assert sorted(resumed) == sorted(full)
    for tag, series in full.items():
        if tag in TIMING:
            assert [s for s, _ in resumed[tag]] == [s for s, _ in series], tag
        else:
            assert resumed[tag] == series, tag
    assert len(full["episode/return"]) == 6


def test_a_missing_backend_is_refused_in_one_line_naming_its_extra(compose_cfg, tmp_path,
                                                                   monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name in ("wandb", "mlflow") else real(name, *a))
    with pytest.raises(LoggerBackendMissing) as err:
        check_backend({"_target_": "torchrl.record.loggers.wandb.WandbLogger"})
    assert str(err.value) == ("logger WandbLogger needs the 'wandb' package: "
                              "pip install -e \".[wandb]\" (or choose logger=csv)")
    cfg = compose_cfg("train", TINY + ["logger=mlflow"])
    with pytest.raises(LoggerBackendMissing, match=r'pip install -e "\.\[mlflow\]"') as err:
        train(cfg, tmp_path / "run")
    assert "\n" not in str(err.value)
    assert not (tmp_path / "run").exists()
    check_backend({"_target_": "torchrl.record.loggers.csv.CSVLogger"})  # no package needed


def test_without_progress_bar_a_line_every_log_every_updates(compose_cfg, tmp_path, caplog, monkeypatch):
    cfg = compose_cfg("train", TINY + ["progress=false"])
    with caplog.at_level(logging.INFO, logger="memrl.dqn.records"):
        summary = train(cfg, tmp_path)
    lines = [r.getMessage() for r in caplog.records if r.name == "memrl.dqn.records"]
    updates = rows(tmp_path / "updates.csv")
    assert summary.updates // 5 == len(updates) == len(lines) >= 2
    assert [line.split(",")[0] for line in lines] == [f"updates {r['updates']}" for r in updates]
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="memrl.dqn.records"):  # off a terminal (pytest's pipes)
        train(compose_cfg("train", TINY + ["progress=true"]), tmp_path / "no_terminal")
    assert len([r for r in caplog.records if r.name == "memrl.dqn.records"]) == len(lines)
    caplog.clear()
    monkeypatch.setattr(sys, "stderr", Terminal())  # on a terminal the bar replaces the lines
    with caplog.at_level(logging.INFO, logger="memrl.dqn.records"):
        train(compose_cfg("train", TINY + ["progress=true"]), tmp_path / "bar")
    assert not [r for r in caplog.records if r.name == "memrl.dqn.records"]
    assert re.search(r"\d+%\|", sys.stderr.getvalue())  # the bar was drawn


class Terminal(io.StringIO):
    """A stderr that says it is a terminal."""

    def isatty(self) -> bool:
        return True


def test_run_name_is_the_run_folder_under_the_output_root(tmp_path):
    root = tmp_path / "outputs"
    assert run_name(root / "train" / "multiruns" / "t" / "3", root) == "train/multiruns/t/3"
    assert run_name(tmp_path / "elsewhere", root) == "elsewhere"


def test_wandb_run_is_named_after_the_run_folder_and_resumed_by_id(compose_cfg, tmp_path,
                                                                   monkeypatch):
    pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    run_dir = tmp_path / "outputs" / "train" / "runs" / "first"
    base = TINY + ["logger=wandb", f"paths.output_root={tmp_path / 'outputs'}"]
    train(compose_cfg("train", base + ["total_episodes=1"]), run_dir)
    ref = json.loads((run_dir / "logs" / "logger.json").read_text())
    assert ref["backend"] == "WandbLogger" and ref["id"]
    (first,) = (run_dir / "logs" / "wandb").glob("offline-run-*")
    assert first.name.endswith(ref["id"])
    train(compose_cfg("train", base + ["total_episodes=2", f"resume={run_dir}"]))
    assert json.loads((run_dir / "logs" / "logger.json").read_text())["id"] == ref["id"]
    assert all(p.name.endswith(ref["id"]) for p in (run_dir / "logs" / "wandb").glob("offline-run-*"))


def test_mlflow_run_named_after_the_folder_with_params_and_one_point_per_step(
        compose_cfg, tmp_path, monkeypatch):
    pytest.importorskip("mlflow")
    from mlflow.tracking import MlflowClient

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    run_dir = tmp_path / "outputs" / "train" / "runs" / "first"
    base = TINY + ["logger=mlflow", f"logger.tracking_uri={uri}", "checkpoint_every=2",
                   f"paths.output_root={tmp_path / 'outputs'}"]
    original = Trainer.run_episode

    def dying(self):
        if self.counters.episodes == 3:
            raise Killed("simulated kill")
        original(self)

    monkeypatch.setattr(Trainer, "run_episode", dying)
    with pytest.raises(Killed):
        train(compose_cfg("train", base + ["total_episodes=4"]), run_dir)
    monkeypatch.setattr(Trainer, "run_episode", original)
    train(compose_cfg("train", base + ["total_episodes=4", f"resume={run_dir}"]))
    run_id = json.loads((run_dir / "logs" / "logger.json").read_text())["id"]
    run = MlflowClient(uri).get_run(run_id)
    assert run.info.run_name == "train/runs/first"
    assert run.data.params["agent.lr"] == "0.00025"
    history = MlflowClient(uri).get_metric_history(run_id, "episode/return")
    assert [m.step for m in history] == [int(r["env_steps"]) for r in rows(run_dir / "episodes.csv")]


def test_held_points_reach_the_backend_only_at_flush_grouped_by_step():
    from memrl.loggers import HeldLog

    class Backend:
        def __init__(self):
            self.calls = []

        def log_metrics(self, metrics, step):
            self.calls.append((dict(metrics), step))

        def flush(self):
            self.calls.append("flush")

    backend = Backend()
    held = HeldLog(backend)
    for name, value, step in [("a", 1, 10), ("b", 2, 10), ("a", 3, 10), ("c", 4, 20)]:
        held.log_scalar(name, value, step)
    assert backend.calls == []  # nothing before the checkpoint
    held.flush()
    assert backend.calls == [({"a": 1.0, "b": 2.0}, 10), ({"a": 3.0}, 10), ({"c": 4.0}, 20), "flush"]
    held.flush()
    assert backend.calls[-1] == "flush" and len(backend.calls) == 5
