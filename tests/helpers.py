"""Shared test helpers: tiny training configs and prior knowledge made on the spot."""

from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDictBase

from memrl.checkpoint import save_qnet
from memrl.data.transitions import to_transitions
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.torchrl_env import make_env, unwrap
from memrl.envs.vehicles import IDLE
from memrl.modules.policy import DrivingPolicy, PolicyModule
from memrl.modules.qnet import QNetwork

TINY = [
    "+experiment=smoke", "total_frames=null", "total_episodes=3", "env.duration=30",
    "agent.warmup_frames=20", "agent.batch_size=8", "agent.train_every=4", "log_every=5",
    "buffer.capacity=400", "checkpoint_every=1", "progress=false", "logger=none",
]
"""Overrides that make a training run take seconds (any mode: no mode key)."""

TINY_STAGE1 = ["mode.stage1.max_updates=12", "mode.stage1.check_every=4",
               "mode.stage1.criterion=agreement_or_plateau", "mode.stage1.drive_episodes=0"]
"""The seconds-long stage-1 stop rule, for a mode whose ``mode`` node has ``stage1`` settings."""


def tiny(mode: str | None = None) -> list[str]:
    """:data:`TINY` for ``mode`` (None or default: TINY itself): TINY + :func:`tiny_mode`."""
    return [*TINY, *tiny_mode(mode)]


def tiny_mode(mode: str | None = None) -> list[str]:
    """The overrides that select ``mode`` (none for None or default) and, when the mode has an
    offline stage, :data:`TINY_STAGE1`."""
    from memrl.modes import MODES

    if mode in (None, "default"):
        return []
    spec = MODES[str(mode)]
    return [*spec.overrides, *(TINY_STAGE1 if spec.pretrains else [])]


class KeepGoing(DrivingPolicy):
    """Keeps speed and curvature: a stand-in demonstrator for plumbing tests."""

    def act(self, env, pixels) -> int:
        return IDLE


def make_demos(n: int, seed: int = 0, duration: int = 30) -> TensorDictBase:
    """``n`` demo transitions recorded through the real TorchRL pipeline."""
    env = make_env({"duration": duration, "vehicles_count": 0}, seed=seed)
    policy = PolicyModule(KeepGoing(), unwrap(env))
    parts, total = [], 0
    while total < n:
        td = env.rollout(duration, policy, break_when_any_done=True)
        parts.append(to_transitions(td, is_demo=True))
        total += len(td)
    return torch.cat(parts)[:n]


def empty_road(**config) -> LaneChangeEnv:
    """A reset env with target lane 1 and no other car: the base of hand-made situations."""
    env = LaneChangeEnv(config={"target_lane": 1, **config})
    env.reset(seed=0)
    env.remove_others()
    return env


def save_pool(root: Path, seeds: tuple[int, ...] = (1, 2), head_scale: float = 1.0) -> list[str]:
    """``final.pt`` files of freshly initialised Q-networks (one per seed), for learned cars;
    ``head_scale`` multiplies the last layer's weights (spread Q-values: no near-ties)."""
    paths = []
    for seed in seeds:
        torch.manual_seed(seed)
        net = QNetwork()
        with torch.no_grad():
            net.head[-1].weight.mul_(head_scale)
        paths.append(str(save_qnet(root / f"agent{seed}" / "final.pt", net, {})))
    return paths


def csv_rows(path: Path) -> list[dict[str, str]]:
    """The rows of a CSV file with a header."""
    import csv

    with path.open() as f:
        return list(csv.DictReader(f))


def assert_same_final_weights_and_agent_buffers(cfg, demos, run_a: Path, run_b: Path) -> None:
    """Two finished runs of ``cfg`` end with equal weights and equal agent buffers (checked by
    resuming each into a fresh trainer)."""
    from memrl.dqn.loop import Trainer

    a = torch.load(run_a / "checkpoints" / "final.pt", weights_only=False)["qnet"]
    b = torch.load(run_b / "checkpoints" / "final.pt", weights_only=False)["qnet"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    buffers = []
    for i, run in enumerate((run_a, run_b)):
        trainer = Trainer(cfg, run.parent / f"probe_{i}", demos)
        trainer.resume(run)
        buffer = trainer.stage.buffer
        buffers.append(getattr(buffer, "online_buffer", buffer))  # mode A: the agent's part
    assert len(buffers[0]) == len(buffers[1]) > 0
    idx = torch.arange(len(buffers[0]))
    assert (buffers[0].storage.get(idx) == buffers[1].storage.get(idx)).all()


class Killed(RuntimeError):
    """A simulated kill in the middle of a run."""


def train_killed_after(monkeypatch, cfg, run_dir: Path, demos, episodes: int) -> None:
    """Train ``cfg`` into ``run_dir`` and kill it as soon as ``episodes`` episodes are done
    (it keeps its last checkpoint before them, as a kill -9 would)."""
    import pytest

    from memrl.dqn.loop import Trainer
    from memrl.train import train

    original = Trainer._episodes_done

    def dying(self, ends):
        original(self, ends)
        if self.counters.episodes >= episodes:
            raise Killed("simulated kill")

    monkeypatch.setattr(Trainer, "_episodes_done", dying)
    with pytest.raises(Killed):
        train(cfg, run_dir, demos=demos)
    monkeypatch.setattr(Trainer, "_episodes_done", original)


def assert_kill_and_resume_is_exact(compose_cfg, tmp_path: Path, demos, monkeypatch, extra: list[str]):
    """Train ``TINY + extra`` (12 episodes, a checkpoint every 3) uninterrupted into ``full``,
    and killed after 8 episodes then resumed into ``cut``: same counters, episode rows, final
    weights and agent buffers. Returns the config and the uninterrupted run's summary."""
    from memrl.checkpoint import resume as ckpt
    from memrl.train import train

    cfg = compose_cfg("train", TINY + extra)
    full = train(cfg, tmp_path / "full", demos=demos)
    train_killed_after(monkeypatch, cfg, tmp_path / "cut", demos, episodes=8)
    state = ckpt.load_state(tmp_path / "cut" / "checkpoints" / "last")
    assert 3 <= state["counters"]["episodes"] < 8
    resumed = train(compose_cfg("train", TINY + extra + [f"resume={tmp_path / 'cut'}"]), demos=demos)
    for key in ("frames", "episodes", "updates"):
        assert getattr(resumed, key) == getattr(full, key), key
    assert csv_rows(tmp_path / "cut" / "episodes.csv") == csv_rows(tmp_path / "full" / "episodes.csv")
    assert_same_final_weights_and_agent_buffers(cfg, demos, tmp_path / "full", tmp_path / "cut")
    return cfg, full


EVERY_STAGE = [(None, "default", []), ("A", "A", []), ("B", "B1", []), ("B", "B2", []),
               ("B", "B2", ["mode.stage2.demo_fraction=0"])]
"""(mode, stage, overrides) of every stage, B's stage 2 with and without its demo share."""


def built_stage_buffer(compose_cfg, demos, mode, stage: str, overrides: list[str]):
    """The buffer that stage ``stage`` of ``TINY + mode + overrides`` is built with."""
    import torch

    from memrl.dqn.builder import StageInputs, build_stage
    from memrl.modes import mode_of

    cfg = compose_cfg("train", TINY + tiny_mode(mode) + overrides)
    return build_stage(mode_of(cfg).stage(stage), StageInputs.of(cfg), demos, 1, torch.device("cpu")).buffer


def tree_hashes(folder: Path) -> dict[str, str]:
    """SHA-256 of every file below ``folder`` (hidden ones too) and ``<dir>`` for every folder:
    equal before and after a refusal when it wrote, changed and removed nothing."""
    import hashlib

    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file()
            else "<dir>" for p in sorted(folder.rglob("*"))}


def flip_middle_byte(path: Path) -> None:
    """One byte in the middle of ``path`` inverted; the size stays."""
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def inside_hydra_run(name: str, overrides: list[str], call):
    """``call()`` as if inside a Hydra run of ``conf/<name>.yaml`` with ``overrides`` (its
    ``HydraConfig`` set for the call, the previous one put back after)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig

    from memrl.configs import register_configs
    from tests.conftest import CONF_DIR

    register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name=name, overrides=overrides, return_hydra_config=True)
    before = HydraConfig.instance().cfg
    HydraConfig.instance().set_config(cfg)
    try:
        return call()
    finally:
        HydraConfig.instance().cfg = before
