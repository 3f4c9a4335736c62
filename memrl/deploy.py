"""``python -m memrl.deploy``: the agent's commands through PID control of a simulated car.

As in the paper's road test (Sec. IV-D), the speed and curvature the agent commands become set
points of two PID loops (P=2000, I=100, D=0) on accelerator and steering; here they drive a
vehicle model, an EKF estimates the state from noisy sensors, and the agent sees the scene
drawn around the estimated pose. See :mod:`memrl.control` for the pieces.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import hydra
from omegaconf import DictConfig, OmegaConf

from memrl.cli import run_hydra, run_task
from memrl.configs import register_configs
from memrl.control.config import DeployConfig, check_deploy_config
from memrl.schemas import check_deploy

if TYPE_CHECKING:  # the env and vehicle stacks load on the first run, not for --help
    from memrl.control.episode import EpisodeRecord
    from memrl.modules.policy import DrivingPolicy

log = logging.getLogger(__name__)


@dataclass
class DeploySummary:
    """Aggregate metrics, per-episode metrics and the files written."""

    metrics: dict[str, float | int]
    episodes: list[dict[str, Any]]
    json: Path
    png: Path


def deploy_config(node: DictConfig) -> DeployConfig:
    """Typed, checked :class:`DeployConfig` from the composed ``deploy`` node."""
    merged = OmegaConf.merge(OmegaConf.structured(DeployConfig), node)
    return check_deploy_config(OmegaConf.to_object(merged))  # type: ignore[arg-type]


def make_policy(cfg: DeployConfig) -> DrivingPolicy:
    """The driver named by ``cfg.policy`` (imported lazily: each needs only its own module)."""
    if cfg.policy == "scripted":
        from memrl.modules.scripted import ScriptedDriver

        return ScriptedDriver()
    if cfg.policy == "checkpoint":
        try:
            from memrl.checkpoint import load_policy  # type: ignore[import-not-found]
        except ModuleNotFoundError as err:
            if err.name not in ("memrl.checkpoint", "memrl"):
                raise
            raise RuntimeError(
                "deploy.policy=checkpoint needs memrl.checkpoint.load_policy(path), which comes "
                "with the training module; it is not in this checkout. Use deploy.policy=scripted."
            ) from err
        assert cfg.checkpoint is not None
        return load_policy(cfg.checkpoint)
    from memrl.modules.policy import RandomPolicy

    return RandomPolicy(cfg.seed)


def _json_safe(values: dict[str, Any]) -> dict[str, Any]:
    """NaN (an undefined metric) -> None, so that the file is strict JSON."""
    return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in values.items()}


def deploy(cfg: DictConfig, out_dir: Path, policy: DrivingPolicy | None = None) -> DeploySummary:
    """Run ``cfg.deploy.episodes`` lane-change episodes through the deployed car.

    Episode k uses env seed ``seed + k`` and sensor seed ``[seed, k]``. Writes ``deploy.json``
    (aggregate and per-episode metrics, config) and ``deploy.png`` (episode ``plot_episode``).
    With ``compare_simulator``, the same seeds are replayed in the plain simulator (``sim_*``).

    Args:
        cfg: the composed ``deploy`` config (keys ``env`` and ``deploy``).
        out_dir: where to write.
        policy: the driver; default: built from ``cfg.deploy.policy``.
    """
    from memrl.control.baseline import simulator_summary
    from memrl.control.episode import run_episode
    from memrl.control.metrics import episode_metrics, summarize
    from memrl.control.plot import plot_episode
    from memrl.control.tracking import TrackedCar
    from memrl.envs.lane_change import LaneChangeEnv
    from memrl.envs.torchrl_env import env_kwargs

    check_deploy(cfg)
    dcfg = deploy_config(cfg.deploy)
    policy = policy or make_policy(dcfg)
    env = LaneChangeEnv(config=env_kwargs(cfg.env))
    car = TrackedCar(dcfg)
    records: list[EpisodeRecord] = []
    try:
        for k in range(dcfg.episodes):
            rec = run_episode(env, policy, car, seed=dcfg.seed + k, sensor_seed=[dcfg.seed, k])
            records.append(rec)
            m = episode_metrics(rec)
            log.info("episode %d/%d seed %d: %s, overshoot %.2f m, speed/curvature RMS %.3f m/s "
                     "%.4f rad/m", k + 1, dcfg.episodes, rec.seed,
                     "success" if m["success"] else ("collision" if rec.collided else "missed"),
                     m["overshoot"], m["speed_tracking_rms"], m["curvature_tracking_rms"])
        metrics = summarize(records)
        if dcfg.compare_simulator:
            metrics.update(simulator_summary(env, policy, [r.seed for r in records]))
    finally:
        env.close()
    episodes = [_json_safe(episode_metrics(r)) for r in records]
    out_dir.mkdir(parents=True, exist_ok=True)
    json_path = out_dir / "deploy.json"
    json_path.write_text(json.dumps({
        "policy": dcfg.policy, "checkpoint": dcfg.checkpoint, "metrics": _json_safe(metrics),
        "episodes": episodes,
        "config": {k: OmegaConf.to_container(cfg[k], resolve=True) for k in ("env", "deploy")},
    }, indent=2))
    png = plot_episode(records[dcfg.plot_episode], env.cfg.lanes_count, env.cfg.lane_width,
                       out_dir / "deploy.png")
    log.info("deploy metrics (%s): %s", dcfg.policy, json.dumps(_json_safe(metrics), indent=2))
    log.info("wrote %s and %s", json_path, png)
    return DeploySummary(metrics, episodes, json_path, png)


@hydra.main(version_base="1.3", config_path="conf", config_name="deploy")
def main(cfg: DictConfig) -> None:
    run_task(lambda c: deploy(c, Path(c.paths.output_dir)), cfg)


if __name__ == "__main__":
    register_configs()
    run_hydra(main)
