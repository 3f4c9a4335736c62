"""End-to-end training speed: the smoke preset's frames/s, updates/s and learner busy share.

Runs ``train`` (Default mode, ``+experiment=smoke``, a shorter ``total_frames``) with a
:class:`~memrl.dqn.loop.Trainer` that timestamps every update (buffer sample + learner step),
then, in the same process, times the learner alone on the run's own buffer and network: the
reference the end-to-end update rate is compared with. "After warm-up" is the span from the
first update (the random-action ``warmup_frames`` are over) to the last.
"""

from __future__ import annotations

import platform
import tempfile
import time
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

import memrl
from memrl.dqn.loop import Trainer

CONF_DIR = memrl.CONF_DIR


def compose_train(overrides: list[str]) -> DictConfig:
    """The real ``train`` config with overrides, inside or outside a running Hydra app."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from memrl.configs import register_configs

    register_configs()
    if GlobalHydra.instance().is_initialized():
        return compose("train", overrides=overrides)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("train", overrides=overrides)


GPU_READBACK = 50
"""``agent.loss_readback`` of the CUDA runs: losses read to the host 50 at a time."""


class TimedTrainer(Trainer):
    """A Trainer recording the (start, end) of every learner update (gradient step; with
    ``agent.overlap`` it runs in the learner thread, in either mode on the learner alone)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.spans: list[tuple[float, float]] = []
        step = self.learner.step

        def timed(batch: Any) -> torch.Tensor:
            t0 = time.perf_counter()
            loss = step(batch)
            self.spans.append((t0, time.perf_counter()))
            return loss

        self.learner.step = timed  # type: ignore[method-assign]


def run(total_frames: int = 1000, learner_seconds: float = 5.0, seed: int = 0,
        overrides: list[str] | None = None, overlap: tuple[bool, ...] = (False, True),
        num_envs: tuple[int, ...] = (1, 16), gpu_num_envs: tuple[int, ...] = (16, 256, 1024),
        gpu_batch_sizes: tuple[int, ...] = (32, 256), gpu_total_frames: int = 200_000,
        device: str = "auto", update_modes: tuple[str, ...] = ("eager",),
        gpu_update_modes: tuple[str, ...] = ("eager", "captured")) -> dict[str, Any]:
    """The smoke preset, side by side in this process: on the CPU for ``total_frames`` env steps
    per env count and ``agent.overlap`` value; on a CUDA device (``device``) for
    ``gpu_total_frames`` per env count and batch size; each with every ``agent.update_mode`` of
    ``update_modes`` (CPU) or ``gpu_update_modes`` (CUDA). Frames/s, updates/s and the learner's
    busy share of each run."""
    from memrl.envs.batched import resolve_device

    dev = resolve_device(device)
    base = [*(overrides or [])]
    runs = [run_one(total_frames, learner_seconds, seed,
                    [*base, "device=cpu", f"env.num_envs={n}", f"agent.overlap={bool(o)}",
                     f"agent.update_mode={m}"])
            for m in update_modes for n in num_envs for o in overlap]
    if dev.type == "cuda":
        runs += [run_one(gpu_total_frames, learner_seconds, seed,
                         [*base, f"device={dev}", f"env.num_envs={n}", f"agent.batch_size={b}",
                          "agent.overlap=false", "buffer.capacity=100000", f"agent.update_mode={m}",
                          f"agent.loss_readback={GPU_READBACK}"])
                 for m in gpu_update_modes for n in gpu_num_envs for b in gpu_batch_sizes]
    return {"device": str(dev), "threads": torch.get_num_threads(),
            "cpu": platform.processor() or platform.machine(),
            "gpu": torch.cuda.get_device_name(dev) if dev.type == "cuda" else None, "runs": runs}


def run_one(total_frames: int, learner_seconds: float, seed: int,
            overrides: list[str]) -> dict[str, Any]:
    """Train the smoke preset for ``total_frames`` env steps; figures and the busy share."""
    from memrl.dqn.config import check_train_config

    threads_before = torch.get_num_threads()
    cfg = compose_train(["+experiment=smoke", f"total_frames={total_frames}", f"seed={seed}",
                         "progress=false", "logger=none", *overrides])
    check_train_config(cfg)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = TimedTrainer(cfg, Path(tmp))
        start = time.perf_counter()
        summary = trainer.run()
        wall = time.perf_counter() - start
        spans = list(trainer.spans)
        if len(spans) < 2:
            raise RuntimeError(f"e2e: only {len(spans)} updates in {total_frames} frames; "
                               "raise total_frames above agent.warmup_frames")
        first, last = spans[0][0], spans[-1][1]
        window = last - first
        busy = sum(b - a for a, b in spans) / window
        frames_after = summary.frames - int(cfg.agent.warmup_frames)
        # The reference: the same learner and buffer, updating back to back.
        n, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < learner_seconds:
            trainer.learner.step(trainer.stage.buffer.sample())  # the timed wrapper: a few us
            n += 1
        learner_only = n / (time.perf_counter() - t0)
    torch.set_num_threads(threads_before)
    upd_after = len(spans) / window
    return {
        "preset": "+experiment=smoke (Default mode)", "num_envs": summary.num_envs,
        "device": summary.device, "total_frames": summary.frames,
        "episodes": summary.episodes, "updates": summary.updates,
        "warmup_frames": int(cfg.agent.warmup_frames), "train_every": int(cfg.agent.train_every),
        "batch_size": int(cfg.agent.batch_size),
        "agent_options": {k: cfg.agent[k] for k in ("threads", "channels_last", "compile",
                                                    "precision", "overlap", "update_mode",
                                                    "loss_readback")},
        "wall_s": round(wall, 2),
        "frames_per_s": round(summary.frames / wall, 2),
        "updates_per_s": round(summary.updates / wall, 3),
        "after_warmup_s": round(window, 2),
        "frames_per_s_after_warmup": round(frames_after / window, 2),
        "updates_per_s_after_warmup": round(upd_after, 3),
        "learner_busy_after_warmup": round(busy, 3),
        "learner_busy_whole_run": round(summary.learner_busy, 3),
        "learner_only_updates_per_s": round(learner_only, 3),
        "ratio_e2e_to_learner_only_updates": round(upd_after / learner_only, 3),
    }
