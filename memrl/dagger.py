"""``python -m memrl.dagger``: DAgger with the scripted driver on call, a ceiling for imitation.

Writes a run folder shaped like a training run: ``config.yaml``, ``checkpoints/final.pt``,
``summary.json`` and ``dagger.csv`` (per iteration: states labelled, dataset size, the
iteration's drive scores, agreement with the expert, loss); ``python -m memrl.evaluate
policy=checkpoint policy.run=<folder>`` evaluates it through the Table III protocol (row
``DAgger``). The algorithm and its loss: :mod:`memrl.imitation.dagger`.
"""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from memrl.cli import run_hydra, run_task
from memrl.configs import register_configs
from memrl.schemas import check_dagger


def dagger(cfg: DictConfig) -> Path:
    """Run DAgger on ``cfg`` (``conf/dagger.yaml``) into ``cfg.paths.output_dir``; the folder."""
    from memrl.imitation.dagger import run_dagger

    check_dagger(cfg)
    out = Path(str(cfg.paths.output_dir))
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    logs = run_dagger(cfg, out)
    last = logs[-1]
    print(f"dagger: {len(logs)} iterations, dataset {last.dataset} states, last iteration's driving: "
          f"survival {last.survival:.0f}%, goal {last.goal:.0f}% of {last.episodes} episodes; {out}")
    return out


@hydra.main(version_base="1.3", config_path="conf", config_name="dagger")
def main(cfg: DictConfig) -> None:
    run_task(dagger, cfg)


if __name__ == "__main__":
    register_configs()
    run_hydra(main)
