"""Bad input is refused at start with one line naming the key or file, and leaves nothing behind.

The table calls each command's typed function on the real composed config (as the
``@hydra.main`` does); a few rows run the real command line to prove the one-line output, the
exit status and that Hydra's run folder is not left behind.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.errors import HydraException
from omegaconf.errors import OmegaConfBaseException

from memrl.errors import USAGE_EXIT, exit_status, is_user_error, one_line

ROOT = Path(__file__).resolve().parents[1]
RUN_MARKERS = ("config.yaml", "summary.json", "checkpoints", "episodes.csv", "metadata.json",
               "transitions", "eval.json", "bench.json", "deploy.json", "observations.png",
               "table3.md", "provenance.json", ".hydra")
"""Names that make a folder look like a run, an evaluation or a dataset."""


def commands():
    from memrl.bench import bench
    from memrl.dagger import dagger
    from memrl.deploy import deploy
    from memrl.evaluate import evaluate
    from memrl.preview import preview
    from memrl.record import record
    from memrl.report import report
    from memrl.study import study
    from memrl.train import train

    return {"train": lambda c, out: train(c, out), "record": lambda c, out: record(c),
            "evaluate": lambda c, out: evaluate(c, out), "report": lambda c, out: report(c, out),
            "deploy": lambda c, out: deploy(c, out), "bench": lambda c, out: bench(c, out),
            "preview": lambda c, out: preview(c, out), "study": lambda c, out: study(c),
            "dagger": lambda c, out: dagger(c)}


def left_behind(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.name in RUN_MARKERS]


# (command, overrides, what the message must name); one row per top-level key of each command
# and per defect of the hardening issue that a config or a missing file triggers.
ROWS = [
    # train: every top-level key
    ("train", ["seed=-1"], "seed"),
    ("train", ["seed=4294967296"], "seed"),
    ("train", ["seed=abc"], "seed"),
    ("train", ["seeds=[-1]"], "seeds"),
    ("train", ["seeds=[]"], "seeds"),
    ("train", ["seeds_engine=both"], "seeds_engine"),
    ("train", ["agent.update_mode=captured", "device=cpu"], "agent.update_mode"),
    ("train", ["device=gpu"], "device"),
    ("train", ["env.num_envs=0"], "num_envs"),
    ("train", ["env.num_envs=500", "buffer.capacity=400"], "env.num_envs"),
    ("train", ["+mode=B", "mode.stage2.demo_fraction=1.5"], "mode.stage2.demo_fraction"),
    ("train", ["+mode=B", "mode.stage2.margin_weight=-1"], "mode.stage2.margin_weight"),
    ("train", ["+mode=A", "mode.margin_weight=-1"], "mode.margin_weight"),
    # a key of another mode: one line naming the mode that has it
    ("train", ["mode.stage1.lr=1e-3"], "'mode.stage1.lr': mode default has no such key (mode B's"),
    ("train", ["+mode=B", "mode.demo_fraction=0.2"], "'mode.demo_fraction': mode B has no such key"),
    ("train", ["total_frames=-5"], "total_frames"),
    ("train", ["total_frames=0"], "total_frames"),
    ("train", ["total_episodes=0"], "total_episodes"),
    ("train", ["total_episodes=null", "total_frames=null"], "total_frames"),
    ("train", ["log_every=0"], "log_every"),
    ("train", ["checkpoint_every=0"], "checkpoint_every"),
    ("train", ["progress=maybe"], "progress"),
    ("train", ["resume=/nonexistent/run"], "resume"),
    ("train", ["overwrite=perhaps"], "overwrite"),
    ("train", ["self_play_every=-1"], "self_play_every"),
    ("train", ["self_play_every=5"], "self_play_every"),
    ("train", ["debug=maybe"], "debug"),
    ("train", ["seeed=1"], "seeed"),
    ("train", ["variant=a/b"], "variant"),
    # train: the groups
    ("train", ["buffer.capacity=-1"], "buffer.capacity"),
    ("train", ["agent.lr=-1"], "agent.lr"),
    ("train", ["agent.batch_size=0"], "agent.batch_size"),
    ("train", ["eval.every=-1"], "eval.every"),
    ("train", ["eval.unit=frames"], "eval.unit"),
    ("train", ["eval.episodes=0"], "eval.episodes"),
    ("train", ["eval.initial_lanes=[left]"], "eval.initial_lanes"),
    ("train", ["env.vehicles_count=[5,0]"], "vehicles_count"),
    ("train", ["env.bev.path_time=11"], "bev.path_time"),
    ("train", ["env.bev.path_length=20", "env.bev.path_time=2"], "bev.path_length,bev.path_time"),
    ("train", ["env.lanes_count=1"], "lanes_count"),
    ("train", ["env.duration=0"], "duration"),
    ("train", ["env.lane_width=inf"], "lane_width"),
    ("train", ["env.reward.collision=nan"], "reward.collision"),
    ("train", ["env.vehicles_count=[0,1000]"], "vehicles_count"),
    ("train", ["env.spawn_gap=-1"], "spawn_gap"),
    ("train", ["env.initial_speed=[20,30]"], "initial_speed"),
    ("train", ["env.road_length=10"], "road_length"),
    ("train", ["opponent=learned"], "opponent.pool"),
    ("train", ["+mode=B", "mode.demos_path=/nonexistent/demos"], "mode.demos_path"),
    ("train", ["+mode=A", "mode.demo_fraction=1.5"], "mode.demo_fraction"),
    ("train", ["+mode=B", "mode.example.action_noise=1"], "mode.example.action_noise"),
    ("train", ["+mode=A", "mode.example.episodes=0"], "mode.example.episodes"),
    # issue 64 item 5: values that meant nothing or something else
    ("train", ["agent.grad_clip=-1"], "'agent.grad_clip': must be >= 0, got -1.0"),
    ("train", ["agent.grad_clip=nan"], "'agent.grad_clip'"),
    ("train", ["agent.n_step=301"], "'agent.n_step': 301 steps summed is longer than an episode"),
    ("train", ["+mode=B", "mode.stage1.margin=-1"], "'mode.stage1.margin'"),
    ("train", ["+mode=B", "mode.stage1.plateau_checks=0"], "'mode.stage1.plateau_checks'"),
    ("train", ["+mode=B", "mode.stage1.plateau_tol=nan"], "'mode.stage1.plateau_tol'"),
    ("train", ["+mode=B", "mode.stage1.check_every=0"], "'mode.stage1.check_every': must be >= 1"),
    ("train", ["+mode=B", "mode.stage1.check_every=40000"],
     "'mode.stage1.check_every': 40000 updates between checks is more than mode.stage1.max_updates"),
    ("train", ["+mode=B", "mode.stage1.criterion=plateau", "mode.stage1.plateau_checks=30"],
     "'mode.stage1.plateau_checks': a window of 30 checks"),
    ("train", ["buffer.capacity=1000000000"], "'buffer.capacity': 1000000000 transitions need at least"),
    ("deploy", ["deploy.speed_pid.p=inf"], "'deploy.speed_pid.p': must be >= 0, got inf"),
    ("deploy", ["deploy.speed_pid.p=nan"], "'deploy.speed_pid.p'"),
    ("deploy", ["deploy.sensors.gyro_bias=nan"], "'deploy.sensors.gyro_bias': must be a finite number"),
    ("evaluate", ["policy=scripted", "protocol.seed=-1"], "'protocol.seed'"),
    ("report", ["runs=[.]", "rollouts.crash_frames=301"],
     "'rollouts.crash_frames': 301 steps before a crash is a window longer than an episode"),
    ("preview", ["steps=[0,301]"], "'steps': [0, 301]: a step after the episode's end"),
    # record
    ("record", ["episodes=0"], "episodes"),
    ("record", ["resume=/nonexistent/recording"], "resume"),
    ("record", ["seed=-3"], "seed"),
    ("record", ["keep=some"], "keep"),
    ("record", ["tail_steps=-1"], "tail_steps"),
    ("record", ["action_noise=1.5"], "action_noise"),
    ("record", ["overwrite=perhaps"], "overwrite"),
    ("record", ["example=true", "tail_steps=5"], "example"),
    ("record", ["example=true", "recipe.tail_steps=-2"], "recipe.tail_steps"),
    ("record", ["progress=maybe"], "progress"),
    ("record", ["debug=maybe"], "debug"),
    ("record", ["env.lanes_count=1"], "lanes_count"),
    # evaluate
    ("evaluate", ["policy=scripted", "workers=-1"], "workers"),
    ("evaluate", ["policy=scripted", "resume=/nonexistent/evaluation"], "resume"),
    ("evaluate", ["policy=scripted", "batch=0"], "batch"),
    ("evaluate", ["policy=scripted", "progress=maybe"], "progress"),
    ("evaluate", [], "policy.run"),
    ("evaluate", ["policy=scripted", "debug=maybe"], "debug"),
    ("evaluate", ["policy=scripted", "overwrite=maybe"], "overwrite"),
    ("evaluate", ["policy.run=/nonexistent/run"], "policy.run"),
    ("evaluate", ["policy=scripted", "protocol.episodes=0"], "episodes"),
    ("evaluate", ["policy=scripted", "env.vehicles_count=-1"], "vehicles_count"),
    # report
    ("report", [], "runs"),
    ("report", ["runs=[/nonexistent/sweep]"], "runs"),
    ("report", ["runs=[.]", "workers=-1"], "workers"),
    ("report", ["runs=[.]", "batch=0"], "batch"),
    ("report", ["runs=[.]", "confidence=1.5"], "confidence"),
    ("report", ["runs=[.]", "n_resamples=0"], "n_resamples"),
    ("report", ["runs=[.]", "bootstrap_seed=-1"], "bootstrap_seed"),
    ("report", ["runs=[.]", "comparisons=[[B]]"], "comparisons"),
    ("report", ["runs=[.]", "row_ignore=[seed,'']"], "row_ignore"),
    ("report", ["runs=[.]", "train_runs=[/nonexistent/run]"], "train_runs"),
    ("report", ["runs=[.]", "smooth=0"], "smooth"),
    ("report", ["runs=[.]", "curve_resamples=0"], "curve_resamples"),
    ("report", ["runs=[.]", "rollouts.count=0"], "rollouts.count"),
    ("report", ["runs=[.]", "rollouts.initial_lane=left"], "rollouts.initial_lane"),
    ("report", ["runs=[.]", "rollouts.pick=best"], "rollouts.pick"),
    ("report", ["runs=[.]", "rollouts.steps=[-1]"], "rollouts.steps"),
    ("report", ["runs=[.]", "rollouts.fps=0"], "rollouts.fps"),
    ("report", ["runs=[.]", "fig5=sometimes"], "fig5"),
    ("report", ["runs=[.]", "evaluate_missing=often"], "evaluate_missing"),
    ("report", ["runs=[.]", "overwrite=maybe"], "overwrite"),
    ("report", ["runs=[.]", "progress=maybe"], "progress"),
    ("report", ["runs=[.]", "debug=maybe"], "debug"),
    # deploy
    ("deploy", ["deploy.episodes=0"], "episodes"),
    ("deploy", ["deploy.policy=fast"], "policy"),
    ("deploy", ["deploy.policy=checkpoint", "deploy.checkpoint=/nonexistent/final.pt"],
     "deploy.checkpoint"),
    ("deploy", ["deploy.plot_episode=99"], "plot_episode"),
    ("deploy", ["env.initial_lane=left"], "initial_lane"),
    ("deploy", ["debug=maybe"], "debug"),
    # bench
    ("bench", ["benchmarks=[nope]"], "benchmarks"),
    ("bench", ["benchmarks=[]"], "benchmarks"),
    ("bench", ["env.steps=0"], "env.steps"),
    ("bench", ["opponents.vehicles_count=0"], "opponents.vehicles_count"),
    ("bench", ["batched.sizes=[0]"], "batched.sizes"),
    ("bench", ["batched.seconds=0"], "batched.seconds"),
    ("bench", ["batched.rounds=0"], "batched.rounds"),
    ("bench", ["learner.batch_sizes=[0]"], "learner.batch_sizes"),
    ("bench", ["learner.seconds=0"], "learner.seconds"),
    ("bench", ["memory.transitions=0"], "memory.transitions"),
    ("bench", ["e2e.total_frames=0"], "e2e.total_frames"),
    ("bench", ["stage1.updates=0"], "stage1.updates"),
    ("bench", ["eval.episodes=0"], "eval.episodes"),
    ("bench", ["pool.cars=[0]"], "pool.cars"),
    ("bench", ["pool.networks=0"], "pool.networks"),
    ("bench", ["seeds.seeds=[0]"], "seeds.seeds"),
    ("bench", ["group.seeds=0"], "group.seeds"),
    ("bench", ["group.one_process_threads=-1"], "group.one_process_threads"),
    ("bench", ["debug=maybe"], "debug"),
    # preview
    ("preview", ["seed=-1"], "seed"),
    ("preview", ["driver=fast"], "driver"),
    ("preview", ["steps=[]"], "steps"),
    ("preview", ["steps=[-1]"], "steps"),
    ("preview", ["scale=0"], "scale"),
    ("preview", ["env.bev.width=4"], "bev.width"),
    ("preview", ["debug=maybe"], "debug"),
    # study
    ("study", ["study.modes=[Default,C]"], "study.modes"),
    ("study", ["study.modes=[]"], "study.modes"),
    ("study", ["study.modes=[A,A]"], "study.modes"),
    ("study", ["study.seeds=[-1]"], "study.seeds"),
    ("study", ["study.seeds=[]"], "study.seeds"),
    ("study", ["study.opponents=[nobody]"], "study.opponents"),
    ("study", ["study.baselines=[human]"], "study.baselines"),
    ("study", ["study.jobs=0"], "study.jobs"),
    ("study", ["study.seeds_per_process=0"], "study.seeds_per_process"),
    ("study", ["study.workers=-1"], "study.workers"),
    ("study", ["study.batch=0"], "study.batch"),
    ("study", ["study.stage1=maybe"], "study.stage1"),
    ("study", ["study.allow_changes=maybe"], "study.allow_changes"),
    ("study", ["study.progress=maybe"], "study.progress"),
    ("study", ["study.train_overrides=['seed=3']"], "study.train_overrides"),
    ("study", ["study.train_overrides=['+mode=A']"], "study.train_overrides"),
    ("study", ["study.opponents=[constant]", "study.train_overrides=['opponent=mixed']"],
     "study.train_overrides"),
    ("study", ["study.train_overrides=['agent.lrr=1']"], "agent.lrr"),
    ("study", ["study.train_overrides=['total_frames=0']"], "total_frames"),
    ("study", ["study.dir=/proc/nope"], "study.dir"),
    ("study", ["study.nmae=x"], "study.nmae"),
    ("study", ["protocol.episodes=0"], "episodes"),
    ("study", ["debug=maybe"], "debug"),
    # dagger
    ("dagger", ["seed=-1"], "seed"),
    ("dagger", ["iterations=0"], "iterations"),
    ("dagger", ["steps_per_iteration=0"], "steps_per_iteration"),
    ("dagger", ["beta=1.5"], "beta"),
    ("dagger", ["epochs=0"], "epochs"),
    ("dagger", ["batch_size=0"], "batch_size"),
    ("dagger", ["lr=0"], "lr"),
    ("dagger", ["progress=maybe"], "progress"),
    ("dagger", ["debug=maybe"], "debug"),
    ("dagger", ["env.num_envs=0"], "num_envs"),
    ("dagger", ["agent.threads=-1"], "agent.threads"),
    ("dagger", ["demos=human"], "demos"),
]


@pytest.fixture
def project(tmp_path, monkeypatch):
    """A temporary project root (``MEMRL_ROOT``) and working directory."""
    monkeypatch.setenv("MEMRL_ROOT", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    return tmp_path


def refusal(compose_cfg, command: str, overrides: list[str], out: Path) -> BaseException:
    """The error that ``command`` raises for ``overrides``, composing as Hydra does."""
    try:
        cfg = compose_cfg(command, overrides)
        commands()[command](cfg, out)
    except Exception as err:  # the assertions below judge it
        return err
    raise AssertionError(f"{command} {overrides} was accepted")


def assert_one_line_naming(err: BaseException, name: str) -> str:
    assert is_user_error(err), f"{type(err).__name__} would print a traceback: {err}"
    assert exit_status(err) == USAGE_EXIT
    message = one_line(err)
    assert "\n" not in message and name in message, message
    return message


@pytest.mark.parametrize(("command", "overrides", "name"), ROWS,
                         ids=[f"{c}:{' '.join(o) or 'defaults'}" for c, o, _ in ROWS])
def test_bad_value_is_refused_at_start(compose_cfg, project, command, overrides, name):
    out = project / "outputs" / command / "runs" / "now"
    err = refusal(compose_cfg, command, overrides, out)
    assert_one_line_naming(err, name)
    assert not out.exists() and left_behind(project) == []


def test_the_table_covers_every_top_level_key(compose_cfg):
    """One row per top-level key of every command (keys that take any string excepted)."""
    from memrl.schemas import SCHEMAS

    free = {"task_name", "out", "env", "agent", "buffer", "mode", "network", "eval", "logger", "paths",
            "demos", "protocol", "policy", "deploy", "memory", "e2e", "stage1", "learner", "opponents"}
    for command in SCHEMAS:
        keys = set(compose_cfg(command).keys()) - free
        named = {o.split("=")[0].split(".")[0].lstrip("+") for c, ovs, _ in ROWS if c == command
                 for o in ovs} | {n.split(".")[0] for c, _, n in ROWS if c == command}
        assert keys <= named, (command, keys - named)
    assert len(ROWS) >= 40


@pytest.mark.parametrize("action", [-1, 9, 2.5, "3", True, np.float32(2.0), torch.tensor(2.0),
                                    np.array([1, 2])], ids=repr)
def test_gym_env_refuses_actions_outside_0_to_8(action):
    from memrl.envs.lane_change import LaneChangeEnv

    env = LaneChangeEnv(config={"vehicles_count": 0})
    env.reset(seed=0)
    before = (env.vehicle.speed, env.vehicle.curvature)
    with pytest.raises(ValueError) as info:
        env.step(action)
    message = assert_one_line_naming(info.value, repr(action))
    assert "0..8" in message
    assert (env.vehicle.speed, env.vehicle.curvature) == before  # nothing was executed


@pytest.mark.parametrize("action", [0, 8, np.int64(3), np.uint8(5), torch.tensor(2),
                                    np.array(4), torch.tensor([7])], ids=repr)
def test_gym_env_accepts_integer_scalars(action):
    from memrl.envs.lane_change import LaneChangeEnv
    from memrl.envs.vehicles import ACTIONS

    env = LaneChangeEnv(config={"vehicles_count": 0})
    env.reset(seed=0)
    speed = env.vehicle.speed
    env.step(action)
    ds, _ = ACTIONS[int(action.item() if hasattr(action, "item") else action)]
    assert env.vehicle.speed == pytest.approx(speed + 0.1 * ds)


def test_unwritable_data_folder_is_found_before_the_example_is_recorded(compose_cfg, project):
    blocker = project / "blocker"
    blocker.write_text("a file where the data folder should go\n")
    out = project / "outputs" / "train" / "runs" / "now"
    err = refusal(compose_cfg, "train", ["+mode=A", f"paths.data_dir={blocker}/data"], out)
    assert_one_line_naming(err, "paths.data_dir")
    assert not out.exists() and left_behind(project) == []


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_data_folder_is_found_before_the_example_is_recorded(compose_cfg, project):
    data = project / "data"
    data.mkdir()
    data.chmod(0o555)
    try:
        err = refusal(compose_cfg, "train", ["+mode=A", f"paths.data_dir={data}"],
                      project / "run")
        assert_one_line_naming(err, str(data))
    finally:
        data.chmod(0o755)


def test_full_disk_during_a_checkpoint_names_the_folder(tmp_path, monkeypatch):
    from memrl.checkpoint import resume as ckpt

    def short_write(obj, f, *args, **kwargs):
        raise RuntimeError("[enforce fail at inline_container.cc:778] . PytorchStreamWriter "
                           "failed writing file data/0: file write failed")

    monkeypatch.setattr(torch, "save", short_write)
    with pytest.raises(ckpt.CheckpointError) as info:
        ckpt.save(tmp_path / "checkpoints" / "last", {"x": 1}, None)
    message = assert_one_line_naming(info.value, str(tmp_path / "checkpoints" / "last.tmp"))
    assert "MB free" in message and "file write failed" in message
    assert not (tmp_path / "checkpoints" / "last.tmp").exists()
    assert not (tmp_path / "checkpoints" / "last").exists()


# ---------------------------------------------------------------------------------------------
# the real command line


def cli(args: list[str], root: Path, **env: str) -> subprocess.CompletedProcess:
    environ = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    environ.update(MEMRL_ROOT=str(root), SDL_VIDEODRIVER="dummy", **env)
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, env=environ,
                          capture_output=True, text=True, timeout=300)


CLI_ROWS = [
    (["memrl.train", "seed=-1"], "'seed'"),
    (["memrl.train", "seed=abc"], "'seed'"),
    (["memrl.train", "seeed=1"], "seeed"),
    (["memrl.train", "+agent.lrr=1"], "config 'agent.lrr': no such key (did you mean 'agent.lr'?)"),
    (["memrl.train", "+foo=bar"], "config 'foo': no such key"),
    (["memrl.train", "env.vehicles_count=[5,0]"], "vehicles_count"),
    (["memrl.train", "env.lane_width=inf"], "lane_width"),
    (["memrl.train", "+mode=B", "mode.demos_path=/nonexistent/demos"], "mode.demos_path"),
    (["memrl.train", "mode.stage1.lr=1e-3"],
     "config 'mode.stage1.lr': mode default has no such key (mode B's key: add +mode=B)"),
    (["memrl.record", "episodes=0"], "'episodes'"),
    (["memrl.bench", "nope"], "benchmarks"),
    (["memrl.study", "study.train_overrides=['agent.lrr=1']"], "agent.lrr"),
    (["memrl.dagger", "iterations=0"], "'iterations'"),
    (["memrl.train", "network._target_=os.system"],
     "config 'network._target_': cannot import 'os.system' (Located non-class"),
    (["memrl.deploy", "deploy.speed_pid.p=nan"], "config 'deploy.speed_pid.p': must be >= 0, got nan"),
    (["memrl.train", "buffer.capacity=1000000000"], "config 'buffer.capacity': 1000000000 transitions"),
]


@pytest.mark.parametrize(("args", "name"), CLI_ROWS, ids=[" ".join(a) for a, _ in CLI_ROWS])
def test_command_line_prints_one_line_and_leaves_no_run_folder(tmp_path, args, name):
    proc = cli(args, tmp_path)
    _assert_refused(proc, tmp_path, name)


def test_unwritable_output_folder_is_refused_before_hydra_writes(tmp_path):
    blocker = tmp_path / "blocker"
    blocker.write_text("a file where the outputs should go\n")
    proc = cli(["memrl.preview", f"paths.output_root={blocker}/outputs"], tmp_path)
    _assert_refused(proc, tmp_path, "paths.output_root")


def _assert_refused(proc: subprocess.CompletedProcess, tmp_path: Path, name: str) -> None:
    assert proc.returncode == USAGE_EXIT, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and name in lines[0], proc.stderr
    assert left_behind(tmp_path) == [] and not (tmp_path / "outputs" / "train" / "runs").exists()


def test_a_missing_dataset_leaves_no_run_folder_behind(tmp_path):
    """A data error found after Hydra made its folder: the folder goes too."""
    dataset = tmp_path / "not_a_dataset"
    dataset.mkdir()
    proc = cli(["memrl.train", "+mode=A", f"mode.demos_path={dataset}"], tmp_path)
    assert proc.returncode == USAGE_EXIT, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and str(dataset) in lines[0], proc.stderr
    runs = tmp_path / "outputs" / "train" / "runs"
    assert not runs.exists() or list(runs.iterdir()) == []


@pytest.mark.parametrize("switch", ["HYDRA_FULL_ERROR", "debug=true"])
def test_full_traceback_on_request(tmp_path, switch):
    env = {"HYDRA_FULL_ERROR": "1"} if switch == "HYDRA_FULL_ERROR" else {}
    args = ["memrl.train", "seed=-1", *([switch] if "=" in switch else [])]
    proc = cli(args, tmp_path, **env)
    assert proc.returncode != 0
    assert "Traceback (most recent call last)" in proc.stderr and "'seed'" in proc.stderr


def test_user_errors_and_bugs_are_told_apart():
    assert is_user_error(OmegaConfBaseException("x")) and is_user_error(HydraException("x"))
    assert is_user_error(FileNotFoundError(2, "No such file or directory", "/a/b"))
    assert "/a/b" in one_line(FileNotFoundError(2, "No such file or directory", "/a/b"))
    assert not is_user_error(ZeroDivisionError("bug")) and exit_status(KeyError("k")) == 1


def test_gym_env_refuses_step_none_and_moves_nothing():
    from memrl.envs.lane_change import LaneChangeEnv

    env = LaneChangeEnv(config={"vehicles_count": 2})
    env.reset(seed=0)
    before = (env.steps, [tuple(c.position) for c in env.others])
    with pytest.raises(ValueError) as info:
        env.step(None)
    assert "0..8" in assert_one_line_naming(info.value, "None")
    assert (env.steps, [tuple(c.position) for c in env.others]) == before


@pytest.mark.parametrize("end", ["terminated", "truncated"])
def test_gym_env_warns_once_when_stepped_after_the_episode_ended(end):
    import warnings

    from memrl.envs.lane_change import LaneChangeEnv
    from memrl.envs.vehicles import IDLE

    env = LaneChangeEnv(config={"vehicles_count": 0, "duration": 3, "initial_offset": 0.0})
    env.reset(seed=0)
    if end == "terminated":
        env.vehicle.crashed = True  # a crash ends the episode at the next step
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        flags = [env.step(IDLE)[2:4] for _ in range(3 if end == "truncated" else 1)]
        assert caught == []  # stepping up to the end says nothing
        assert flags[-1][0 if end == "terminated" else 1]
        env.step(IDLE)
        env.step(IDLE)
    messages = [str(w.message) for w in caught]
    assert len(messages) == 1 and f"{end} = True" in messages[0] and "reset()" in messages[0], messages
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        env.reset(seed=1)
        env.step(IDLE)
    assert caught == []  # a new episode starts quiet


@pytest.mark.parametrize("num_envs", [None, 2])
def test_make_env_refuses_a_device_that_is_none_at_one_env_as_at_two(num_envs):
    from memrl.envs.config import BatchedEnvError
    from memrl.envs.torchrl_env import make_env

    with pytest.raises(BatchedEnvError) as info:
        make_env({}, num_envs=num_envs, device="tpu")
    assert_one_line_naming(info.value, "'tpu'")


def _hashes(root: Path) -> dict[str, str]:
    import hashlib

    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_report_on_a_garbled_eval_json_is_one_line_and_leaves_no_folders(tmp_path):
    run = tmp_path / "run"
    (run / "eval").mkdir(parents=True)
    (run / "eval" / "eval.json").write_text("{garbled")
    before = _hashes(tmp_path)
    proc = cli(["memrl.report", f"runs=[{run}]", "evaluate_missing=false"], tmp_path)
    assert proc.returncode == USAGE_EXIT, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        f"error: {run / 'eval' / 'eval.json'}: not an evaluation memrl can read"), proc.stderr
    assert not (tmp_path / "outputs").exists() and _hashes(tmp_path) == before


def test_a_refused_deploy_leaves_no_empty_output_folders(tmp_path):
    """The refusal comes after Hydra made ``outputs/deploy/runs/<time>/``: each folder it made
    goes, the folders that were there stay."""
    (tmp_path / "outputs").mkdir()
    proc = cli(["memrl.deploy", "deploy.policy=checkpoint", f"deploy.checkpoint={tmp_path}"], tmp_path)
    assert proc.returncode == USAGE_EXIT, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        f"error: {tmp_path}: no trained network found (expected a run folder with "
        "checkpoints/final.pt, or a final.pt file)"]
    assert [p.name for p in tmp_path.iterdir()] == ["outputs"] and not any((tmp_path / "outputs").iterdir())


def test_read_result_names_a_garbled_or_incomplete_eval_json(tmp_path):
    from memrl.evaluation.results import read_result

    for text in ("{garbled", "[]", '{"name": "x"}'):
        (tmp_path / "eval.json").write_text(text)
        with pytest.raises(ValueError) as info:
            read_result(tmp_path)
        assert_one_line_naming(info.value, f"{tmp_path / 'eval.json'}: not an evaluation memrl can read")


def test_evaluate_of_a_run_whose_final_pt_was_deleted_names_it_in_one_line(
        compose_cfg, project, smoke_run):
    import shutil

    run = project / "run"
    shutil.copytree(smoke_run, run)
    (run / "checkpoints" / "final.pt").unlink()
    before = _hashes(project)
    out = project / "outputs" / "evaluate" / "runs" / "now"
    err = refusal(compose_cfg, "evaluate", [f"policy.run={run}"], out)
    message = assert_one_line_naming(err, f"policy 'run': no finished training run (checkpoints/final.pt) "
                                          f"in {run}")
    assert "Error in call to target" not in message and "CheckpointSource" not in message
    assert _hashes(project) == before and not out.exists()


def test_report_of_a_run_evaluated_under_two_protocols_is_refused_before_evaluating(
        compose_cfg, project, smoke_run):
    import shutil

    from memrl.evaluate import evaluate
    from memrl.report import report

    run = project / "run"
    shutil.copytree(smoke_run, run)
    small = ["protocol.episodes=1", "protocol.duration=10", "protocol.initial_lanes=[random]",
             "workers=1", "batch=1", "progress=false"]
    evaluate(compose_cfg("evaluate", [f"policy.run={run}", *small]), out_dir=project / "x")
    evaluate(compose_cfg("evaluate", [f"policy.run={run}", "policy.subdir=eval_b", *small,
                                      "protocol.seed=7"]), out_dir=project / "x")
    before = _hashes(project)
    report_args = [f"runs=[{run}]", "fig5=false", "rollouts.rows=[]", "progress=false", *small[:3]]
    for extra in (["evaluate_missing=false"], ["evaluate_missing=true", "overwrite=true", "protocol.seed=9"]):
        out = project / "outputs" / "report" / "runs" / "now"
        with pytest.raises(ValueError) as info:
            report(compose_cfg("report", [*report_args, *extra]), out)
        message = assert_one_line_naming(info.value,
                                         "config 'runs': evaluations made under different protocols")
        assert str(run / "eval_b") in message
        assert _hashes(project) == before and not out.exists()  # nothing evaluated, nothing replaced


def test_a_start_refused_at_the_dataset_check_leaves_an_existing_folder_as_it_was(tmp_path):
    """Hydra writes ``.hydra/*.yaml`` and the log before the dataset's own check refuses it:
    a folder that was there keeps its files, bytes and times."""
    dataset = tmp_path / "not_a_dataset"
    dataset.mkdir()
    folder = tmp_path / "mine"
    (folder / ".hydra").mkdir(parents=True)
    for name in ("config.yaml", "hydra.yaml", "overrides.yaml"):
        (folder / ".hydra" / name).write_text(f"# my own {name}\n")
    before = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in folder.rglob("*") if p.is_file()}
    proc = cli(["memrl.train", "+mode=A", f"mode.demos_path={dataset}", f"hydra.run.dir={folder}"], tmp_path)
    assert proc.returncode == USAGE_EXIT, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and str(dataset) in lines[0], proc.stderr
    after = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in folder.rglob("*") if p.is_file()}
    assert after == before
