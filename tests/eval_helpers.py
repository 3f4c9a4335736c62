"""Helpers of the evaluation and report tests: run folders and evaluations made by hand."""

from __future__ import annotations

import csv
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from memrl.checkpoint import save_qnet
from memrl.evaluation.protocol import EpisodeRecord, ProtocolConfig, scenario_seeds
from memrl.evaluation.results import EvalResult, write_result
from memrl.modules.qnet import QNetwork
from tests.helpers import tiny

Compose = Callable[..., DictConfig]


def fake_run(root: Path, compose_cfg: Compose, mode: str = "default", seed: int = 0,
             env: Sequence[str] = (), episodes: int = 0) -> Path:
    """A finished training run folder: the real composed train config, an untrained network
    (seeded) as ``checkpoints/final.pt`` and ``episodes`` synthetic rows of ``episodes.csv``."""
    run = root / f"{mode}_{seed}"
    overrides = [*tiny(mode), f"seed={seed}", *env]
    cfg = compose_cfg("train", overrides)
    cfg.paths.output_dir = str(run)
    run.mkdir(parents=True)
    (run / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    torch.manual_seed(1000 + seed)
    save_qnet(run / "checkpoints" / "final.pt", QNetwork(), OmegaConf.to_container(cfg.env, resolve=True))
    if episodes:
        write_episodes_csv(run, [(10.0 * seed + e, 50 + e + seed) for e in range(episodes)])
    return run


def write_episodes_csv(run: Path, rows: Sequence[tuple[float, int]]) -> None:
    """``episodes.csv`` with the given (return, survival steps) per episode."""
    with (run / "episodes.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["episode", "env_steps", "return", "survival_steps", "length", "collided",
                    "reached_target", "epsilon", "stage"])
        for i, (ret, steps) in enumerate(rows, start=1):
            w.writerow([i, 100 * i, ret, steps, steps, 0, 1, 0.5, "default"])


def records(survived: Sequence[bool], goal: Sequence[bool], lane: str = "random",
            duration: int = 300, seeds: Sequence[int] | None = None) -> list[EpisodeRecord]:
    """Hand-built episode records with the given outcomes (a crash ends at step 123)."""
    seeds = list(seeds) if seeds is not None else list(range(len(survived)))
    return [EpisodeRecord(initial_lane=lane, episode=i, seed=seeds[i],
                          steps=duration if s else 123, episode_return=float(i),
                          collided=not s, reached_target=g, duration=duration,
                          target_lane=1, start_lane=0, vehicles=3)
            for i, (s, g) in enumerate(zip(survived, goal, strict=True))]


def outcome_records(survival: int, goal: int, n: int = 100,
                    lanes: Sequence[str] = ("random", "non_goal")) -> list[EpisodeRecord]:
    """``n`` episodes per initial-lane setting with exactly ``survival`` and ``goal`` successes."""
    seeds = scenario_seeds(0, n)
    out = []
    for lane in lanes:
        out += records([i < survival for i in range(n)], [i < goal for i in range(n)], lane, seeds=seeds)
    return out


def fake_eval(folder: Path, name: str, unit: str, survival: int, goal: int, n: int = 100,
              protocol: ProtocolConfig | None = None, meta: dict | None = None) -> EvalResult:
    """An evaluation folder whose scores are ``survival`` and ``goal`` (of ``n``) in both settings."""
    protocol = protocol or ProtocolConfig(episodes=n)
    return write_result(folder, name, outcome_records(survival, goal, n, protocol.initial_lanes), protocol,
                        scenario_seeds(protocol.seed, n), {"unit": unit, **(meta or {})})
