"""Mode B stage 1: train on prior knowledge alone until the behaviour converges."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict import TensorDictBase

from memrl.envs.config import LaneChangeConfig
from memrl.evaluation.jobs import module_device
from memrl.evaluation.policies import GreedyActor
from memrl.evaluation.protocol import ProtocolConfig, protocol_env, scenario_seeds
from memrl.evaluation.runner import Job, run_jobs
from memrl.modes import Stage1Config
from memrl.modules.qnet import decision_values

log = logging.getLogger(__name__)


@dataclass
class Stage1Progress:
    """What stage 1 has done so far (saved in checkpoints)."""

    updates: int = 0
    losses: list[float] = field(default_factory=list)
    """Mean TD loss of each check interval."""
    agreements: list[float] = field(default_factory=list)
    """Greedy/demo action agreement on held-out demos at each check."""
    parts: list[dict[str, float]] = field(default_factory=list)
    """At each check, :func:`agreement_parts` of the held-out demos."""
    drives: list[dict[str, int]] = field(default_factory=list)
    """At each check with ``drive_episodes``: :func:`drive_check` counts and ``updates``."""
    best_updates: int = 0
    """Updates of the checked weights that drove best so far (0: none yet)."""
    drive_s: float = 0.0
    """Wall time spent in those drives [s]."""
    stop_reason: str = ""
    done: bool = False


def split_demos(demos: TensorDictBase, holdout_fraction: float,
                seed: int, keep_order: bool = False) -> tuple[TensorDictBase, TensorDictBase]:
    """(train, held-out) parts of the demos, by a seeded permutation; ``keep_order``: the train
    part in dataset order (n-step windows chain consecutive demos; held-out ones are gaps)."""
    gen = torch.Generator().manual_seed(seed)
    perm = torch.randperm(len(demos), generator=gen)
    n_hold = max(1, int(round(holdout_fraction * len(demos))))
    train = perm[n_hold:].sort().values if keep_order else perm[n_hold:]
    return demos[train], demos[perm[:n_hold]]


@torch.no_grad()
def agreement(qnet: torch.nn.Module, held_out: TensorDictBase, chunk: int = 256) -> float:
    """Share of held-out demo transitions where the greedy action equals the demo's."""
    hits = 0
    for start in range(0, len(held_out), chunk):
        part = held_out[start:start + chunk]
        hits += int((decision_values(qnet, part["pixels"]).argmax(-1) == part["action"]).sum())
    return hits / len(held_out)


@torch.no_grad()
def agreement_parts(qnet: torch.nn.Module, held_out: TensorDictBase,
                    chunk: int = 256) -> dict[str, float]:
    """Agreement per action component on held-out demos, to see what the network imitates:

    ``speed`` and ``curvature``: share of transitions whose greedy action has the demo's speed
    (curvature) change; ``steering_recall``: of the demo steps that change curvature (the
    lane-change and lane-keeping corrections, ~12% of scripted demos), the share where the
    greedy action changes curvature the same way; ``steering_share``: how often the greedy
    action changes curvature at all; ``greedy_actions``: how many different greedy actions
    the held-out states get (1: the output no longer depends on the input, a collapsed network).
    """
    greedy = torch.cat([decision_values(qnet, held_out[i:i + chunk]["pixels"]).argmax(-1)
                        for i in range(0, len(held_out), chunk)])
    demo = held_out["action"].reshape(-1)
    same_curv = greedy % 3 == demo % 3  # index = 3 * speed index + curvature index
    steer = demo % 3 != 1
    return {
        "speed": float((greedy // 3 == demo // 3).float().mean()),
        "curvature": float(same_curv.float().mean()),
        "steering_recall": float(same_curv[steer].float().mean()) if bool(steer.any()) else 0.0,
        "steering_share": float((greedy % 3 != 1).float().mean()),
        "greedy_actions": float(greedy.unique().numel()),
    }


def drive_counts(qnet: torch.nn.Module, env_cfg: Any, seeds: list[int], batch: int = 10, *,
                 device: torch.device | str | None = None, actor: Any = None) -> dict[str, int]:
    """The behaviour itself: the greedy agent drives one non-goal episode among 0-5
    constant-speed cars (the protocol's rules on the run's env) per reset seed; returns the
    counts of ``survived``, ``reached`` (the target lane) and ``both`` in the same episode.

    The episodes run on the batched engine, all at once on ``device`` (None: the network's
    device; ``batch``: envs in lockstep on the gym path, used only when the engine cannot draw
    the env's frames); ``actor``: another actor in its place (JSRL's combined policy)."""
    duration = int(env_cfg.get("duration", LaneChangeConfig.duration))  # the run's length
    protocol = ProtocolConfig(episodes=len(seeds), initial_lanes=["non_goal"], duration=duration)
    job = Job(protocol_env(env_cfg, protocol, "non_goal"), "non_goal", list(enumerate(seeds)))
    device = device if device is not None else module_device(qnet)
    actor = GreedyActor(qnet) if actor is None else actor
    records = run_jobs(actor, [job], batch=batch, device=device).records  # type: ignore[arg-type]
    return {"survived": sum(r.survived for r in records), "reached": sum(r.goal for r in records),
            "both": sum(r.survived and r.goal for r in records)}


def drive_check(qnet: torch.nn.Module, env_cfg: Any, episodes: int, seed: int = 0,
                batch: int = 10, *, device: torch.device | str | None = None,
                actor: Any = None) -> dict[str, int]:
    """:func:`drive_counts` over ``episodes`` scenes of their own seed domain (``stage1``),
    apart from the training, periodic and Table III scenes, so choosing weights by it does
    not tune on the test scenes."""
    return drive_counts(qnet, env_cfg, scenario_seeds(seed, episodes, domain="stage1"), batch, device=device,
                        actor=actor)


def stop_reason(cfg: Stage1Config, progress: Stage1Progress) -> str:
    """Why stage 1 should stop now ('' to go on), per ``cfg.criterion``."""
    if progress.updates >= cfg.max_updates:
        return f"max_updates ({cfg.max_updates})"
    if cfg.criterion == "max_updates":
        return ""
    agreed = bool(progress.agreements) and progress.agreements[-1] >= cfg.agreement
    flat = False
    k = cfg.plateau_checks
    if len(progress.losses) > k:
        before, now = progress.losses[-k - 1], progress.losses[-1]
        flat = (before - now) / max(abs(before), 1e-8) < cfg.plateau_tol
    if agreed and cfg.criterion in ("agreement", "agreement_or_plateau"):
        return f"agreement {progress.agreements[-1]:.3f} >= {cfg.agreement}"
    if flat and cfg.criterion in ("plateau", "agreement_or_plateau"):
        return f"loss plateau over {k} checks (< {cfg.plateau_tol:.0%} better)"
    if cfg.criterion == "behaviour" and progress.drives:
        both, n = progress.drives[-1]["both"], cfg.drive_episodes
        if both >= cfg.drive_target * n:
            return f"behaviour: {both}/{n} drive episodes survived and reached >= {cfg.drive_target}"
    return ""


class Stage1Checks:
    """Mode B stage 1's periodic check: loss, held-out agreement, optional behaviour drives
    (keeping the weights that drove best), and the stop decision.

    Args:
        cfg: the ``mode.stage1`` node.
        env_cfg: the run's env config (drives).
        held_out: demos kept out of the stage-1 buffer.
        progress: the run's :class:`Stage1Progress` (updated in place).
    """

    def __init__(self, cfg: Any, env_cfg: Any, held_out: TensorDictBase,
                 progress: Stage1Progress) -> None:
        self.cfg, self.env_cfg, self.held_out, self.progress = cfg, env_cfg, held_out, progress
        self.best: dict[str, torch.Tensor] | None = None
        """With drives: the loss module's weights that drove best so far."""

    def due(self) -> bool:
        p, cfg = self.progress, self.cfg
        return p.updates % int(cfg.check_every) == 0 or p.updates >= int(cfg.max_updates)

    def check(self, qnet: torch.nn.Module, loss_module: torch.nn.Module,
              recent_losses: list[float]) -> dict[str, float]:
        """Measure now, decide whether to stop (``progress.stop_reason``); the logger values."""
        p, cfg = self.progress, self.cfg
        p.losses.append(float(sum(recent_losses) / max(len(recent_losses), 1)))
        p.agreements.append(agreement(qnet, self.held_out))
        p.parts.append(agreement_parts(qnet, self.held_out))
        drove = int(cfg.drive_episodes) > 0
        if drove:
            start = time.perf_counter()
            counts = drive_check(qnet, self.env_cfg, int(cfg.drive_episodes), int(cfg.drive_seed))
            p.drive_s += time.perf_counter() - start
            p.drives.append({"updates": p.updates, **counts})
            best = next((d["both"] for d in p.drives if d["updates"] == p.best_updates), -1)
            if bool(cfg.keep_best) and counts["both"] >= best:
                p.best_updates = p.updates
                self.best = {k: v.detach().clone() for k, v in loss_module.state_dict().items()}
        if p.parts[-1]["greedy_actions"] == 1:
            log.warning("stage 1: %d updates: the greedy action is the same on all %d held-out demo "
                        "states: the network's output does not depend on its input (collapsed, "
                        "e.g. dead ReLU units: python -m memrl.tools.stage1_probe); it may not recover",
                        p.updates, len(self.held_out))
        p.stop_reason = stop_reason(cfg, p)
        log.info(
            "stage 1: %d updates, loss %.4f, agreement %.3f (%s)%s%s", p.updates, p.losses[-1],
            p.agreements[-1], ", ".join(f"{k} {v:.3f}" for k, v in p.parts[-1].items()),
            f", drive {p.drives[-1]}" if drove else "",
            f" -> stop: {p.stop_reason}" if p.stop_reason else "")
        return {"check_loss": p.losses[-1], "agreement": p.agreements[-1],
                **{f"agreement_{k}": v for k, v in p.parts[-1].items()},
                **({f"drive_{k}": p.drives[-1][k] for k in ("survived", "reached", "both")}
                   if drove else {})}

    def finish(self, loss_module: torch.nn.Module) -> None:
        """Stage 1 is over: put back the weights that drove best (when not the last ones)."""
        p = self.progress
        p.done = True
        if self.best is not None and p.best_updates != p.updates:
            loss_module.load_state_dict(self.best)
            p.stop_reason += f"; weights of update {p.best_updates} (drove best)"
        self.best = None
