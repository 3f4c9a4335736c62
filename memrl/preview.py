"""``python -m memrl.preview``: write PNGs of the agent's stacked observations and the scene."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from memrl.cli import run_hydra, run_task
from memrl.configs import register_configs
from memrl.schemas import check_preview

log = logging.getLogger(__name__)


@dataclass
class PreviewFiles:
    observations: Path
    scene: Path


def _grid(rows: list[list[np.ndarray]], pad: int = 4, value: int = 128) -> np.ndarray:
    """Tile equally sized images (H, W[, 3]) row by row with a separating border."""
    def pad_img(img: np.ndarray) -> np.ndarray:
        widths = ((pad, pad), (pad, pad)) + (((0, 0),) if img.ndim == 3 else ())
        return np.pad(img, widths, constant_values=value)
    return np.concatenate([np.concatenate([pad_img(i) for i in row], axis=1) for row in rows])


def preview(cfg: DictConfig, out_dir: Path) -> PreviewFiles:
    """Step the TorchRL env with a simple policy and save what it shows at ``cfg.steps``.

    ``observations.png``: one row per captured step, the 4 stacked grayscale frames the network
    receives (oldest left). ``scene.png``: the full-scene pictures at the same steps.
    """
    import torch

    from memrl.envs.torchrl_env import make_env
    from memrl.envs.vehicles import IDLE, N_ACTIONS

    check_preview(cfg)
    import cv2

    env = make_env(cfg.env, seed=cfg.seed, render_mode="rgb_array")
    gen = torch.Generator().manual_seed(int(cfg.seed))
    wanted = sorted(int(s) for s in cfg.steps)
    td = env.reset()
    obs_rows, scenes = [], []
    for step in range(wanted[-1] + 1):
        if step in wanted:
            frames = td["pixels"].numpy()
            obs_rows.append([cv2.resize(f, None, fx=cfg.scale, fy=cfg.scale,
                                        interpolation=cv2.INTER_NEAREST) for f in frames])
            scenes.append(env.base_env.render())
        action = IDLE if cfg.driver == "idle" else int(torch.randint(N_ACTIONS, (1,), generator=gen))
        td["action"] = torch.tensor(action)
        td = env.step(td)
        if td["next", "done"].item():
            log.info("episode ended at step %d; resetting", step + 1)
            td = env.reset()
        else:
            td = td["next"]
    env.close()
    out_dir.mkdir(parents=True, exist_ok=True)
    files = PreviewFiles(out_dir / "observations.png", out_dir / "scene.png")
    cv2.imwrite(str(files.observations), _grid(obs_rows))
    cv2.imwrite(str(files.scene), cv2.cvtColor(_grid([scenes]), cv2.COLOR_RGB2BGR))
    log.info("observations at steps %s: %s", wanted, files.observations)
    log.info("scene at steps %s: %s", wanted, files.scene)
    return files


@hydra.main(version_base="1.3", config_path="conf", config_name="preview")
def main(cfg: DictConfig) -> None:
    run_task(lambda c: preview(c, Path(c.paths.output_dir)), cfg)


if __name__ == "__main__":
    register_configs()
    run_hydra(main)
