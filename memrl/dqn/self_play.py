"""Self-play: every ``self_play_every`` episodes the agent joins the learned cars' pool."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf

from memrl.checkpoint import load_qnet, save_qnet
from memrl.errors import UserError


class SelfPlayPool:
    """Snapshots of the agent in ``<run>/pool/``, added to the learned cars' controller.

    Args:
        every: episodes between snapshots (0: off).
        controller: the env's learned-car controller (None: the env has no learned cars).
        run_dir: the run folder.
        env_cfg: the run's env config (saved with each snapshot).
    """

    def __init__(self, every: int, controller: Any | None, run_dir: Path, env_cfg: Any) -> None:
        if every and controller is None:
            raise UserError("config 'self_play_every': snapshots join the learned cars' pool; "
                            "it needs opponent=learned or opponent=mixed")
        self.every, self.controller, self.run_dir = int(every), controller, run_dir
        self.env_cfg = OmegaConf.to_container(env_cfg, resolve=True) \
            if OmegaConf.is_config(env_cfg) else dict(env_cfg)

    def _path(self, episodes: int) -> Path:
        return self.run_dir / "pool" / f"episode_{episodes:07d}.pt"

    def after_episode(self, episodes: int, qnet: torch.nn.Module) -> None:
        """Snapshot the agent when ``episodes`` (finished so far) is a multiple of ``every``."""
        if self.every and episodes % self.every == 0:
            path = self._path(episodes)
            save_qnet(path, qnet, self.env_cfg)  # type: ignore[arg-type]
            self.controller.add_network(load_qnet(path)[0])  # type: ignore[union-attr]

    def restore(self, episodes: int) -> None:
        """After a resume: the snapshots taken up to ``episodes`` rejoin the pool, in order."""
        for n in range(self.every, episodes + 1, self.every) if self.every else []:
            self.controller.add_network(load_qnet(self._path(n))[0])  # type: ignore[union-attr]
