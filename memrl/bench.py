"""``python -m memrl.bench [env ...]``: side-by-side benchmarks, printed and saved as JSON."""

from __future__ import annotations

import json
import logging
import os
import platform
from collections.abc import Callable
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from memrl.cli import run_hydra, run_task
from memrl.configs import register_configs
from memrl.schemas import check_bench

log = logging.getLogger(__name__)


def _env(cfg: DictConfig) -> dict[str, Any]:
    from memrl.benchmarks import env_speed

    return env_speed.run(**OmegaConf.to_container(cfg, resolve=True))  # type: ignore[arg-type]


def _opponents(cfg: DictConfig) -> dict[str, Any]:
    from memrl.benchmarks import env_speed

    return env_speed.run_opponents(**OmegaConf.to_container(cfg, resolve=True))  # type: ignore[arg-type]


def _batched(cfg: DictConfig) -> dict[str, Any]:
    from memrl.benchmarks import batched_speed

    return batched_speed.run(**OmegaConf.to_container(cfg, resolve=True))  # type: ignore[arg-type]


def _learner(cfg: DictConfig) -> dict[str, Any]:
    from memrl.benchmarks import learner_speed

    return learner_speed.run(**OmegaConf.to_container(cfg, resolve=True))  # type: ignore[arg-type]


def _memory(cfg: DictConfig) -> dict[str, Any]:
    from memrl.benchmarks import replay_memory

    return replay_memory.run(**OmegaConf.to_container(cfg, resolve=True))  # type: ignore[arg-type]


def _e2e(cfg: DictConfig) -> dict[str, Any]:
    from memrl.benchmarks import e2e

    values: dict[str, Any] = OmegaConf.to_container(cfg, resolve=True)  # type: ignore[assignment]
    for key in ("overlap", "num_envs", "gpu_num_envs", "gpu_batch_sizes", "update_modes", "gpu_update_modes"):
        values[key] = tuple(values[key])
    return e2e.run(**values)


def _stage1(cfg: DictConfig) -> dict[str, Any]:
    from memrl.benchmarks import stage1_check

    values: dict[str, Any] = OmegaConf.to_container(cfg, resolve=True)  # type: ignore[assignment]
    return stage1_check.run(**values)


def _pool(cfg: DictConfig) -> dict[str, Any]:
    from memrl.benchmarks import pool_speed

    return pool_speed.run(**OmegaConf.to_container(cfg, resolve=True))  # type: ignore[arg-type]


def _seeds(cfg: DictConfig) -> dict[str, Any]:
    from memrl.benchmarks import seeds_speed

    return seeds_speed.run(**OmegaConf.to_container(cfg, resolve=True))  # type: ignore[arg-type]


def _group(cfg: DictConfig) -> dict[str, Any]:
    from memrl.benchmarks import group_speed

    return group_speed.run(**OmegaConf.to_container(cfg, resolve=True))  # type: ignore[arg-type]


def _eval(cfg: DictConfig) -> dict[str, Any]:
    from memrl.benchmarks import eval_speed

    return eval_speed.run(**OmegaConf.to_container(cfg, resolve=True))  # type: ignore[arg-type]


BENCHMARKS: dict[str, Callable[[DictConfig], dict[str, Any]]] = {"env": _env, "stage1": _stage1,
                                                                 "opponents": _opponents,
                                                                 "learner": _learner,
                                                                 "memory": _memory,
                                                                 "e2e": _e2e, "batched": _batched,
                                                                 "eval": _eval, "pool": _pool,
                                                                 "seeds": _seeds, "group": _group}


def machine() -> dict[str, Any]:
    """What the figures were measured on."""
    import torch

    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "load_average": list(os.getloadavg()),  # 1, 5, 15 min, at the start of the run
    }


def bench(cfg: DictConfig, out_dir: Path) -> dict[str, Any]:
    """Run the selected benchmarks; write ``bench.json`` to ``out_dir`` and return the figures."""
    check_bench(cfg)  # every value (benchmark names included) before anything runs
    result: dict[str, Any] = {"machine": machine()}
    for name in cfg.benchmarks:
        log.info("running benchmark %s", name)
        result[name] = BENCHMARKS[name](cfg[name])
        print(json.dumps({name: result[name]}, indent=2))
    result["machine"]["load_average_end"] = list(os.getloadavg())
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "bench.json").write_text(json.dumps(result, indent=2))
    log.info("wrote %s", out_dir / "bench.json")
    return result


@hydra.main(version_base="1.3", config_path="conf", config_name="bench")
def main(cfg: DictConfig) -> None:
    run_task(lambda c: bench(c, Path(c.paths.output_dir)), cfg)


if __name__ == "__main__":
    register_configs()
    run_hydra(main, positional_key="benchmarks")
