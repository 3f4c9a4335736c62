"""K seeds of the train app in one process (``seeds=[...]``, :func:`memrl.train.train_seeds`)
against K single-seed processes running at once: end-to-end env steps/s of all K runs.

Both arms run ``python -m memrl.train`` as subprocesses on the same overrides and budget, so
both pay their start-up (imports, env and buffer building) inside the timed span: the figure is
what a user's K runs take. The per-run rate (``frames`` over the runs' own ``wall_s`` from
``summary.json``) is reported beside it. The one process runs with an engine per seed
(``one_process``, ``seeds_engine=own``) and, with ``engines`` naming ``shared``, with the seeds'
envs on one engine (``one_process_shared``). Arms alternate over ``rounds`` (ABBA...), each in a
fresh temporary folder.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ARMS = {"one_process": "own", "one_process_shared": "shared"}
"""One-process arms and their ``seeds_engine``."""


def _cmd(overrides: list[str], frames: int, out: Path, seeds: list[int]) -> list[str]:
    pick = [f"seed={seeds[0]}"] if len(seeds) == 1 else [f"seeds=[{','.join(map(str, seeds))}]"]
    return [sys.executable, "-m", "memrl.train", *overrides, f"total_frames={frames}", "total_episodes=null",
            *pick, f"hydra.run.dir={out}"]


def _summaries(folders: list[Path]) -> list[dict[str, Any]]:
    return [json.loads((f / "summary.json").read_text()) for f in folders]


def _arm(name: str, k: int, frames: int, overrides: list[str], root: Path, threads: int) -> dict[str, Any]:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    quiet = {"env": env, "stdout": subprocess.DEVNULL, "stderr": subprocess.PIPE}
    t0 = time.perf_counter()
    if name in ARMS:
        out = root / "group"
        one = [*overrides, f"agent.threads={threads}", f"seeds_engine={ARMS[name]}"]
        procs = [subprocess.Popen(_cmd(one, frames, out, list(range(k))), **quiet)]  # type: ignore[call-overload]
        folders = [out / f"s{s}" for s in range(k)]
    else:
        folders = [root / f"single_s{s}" for s in range(k)]
        procs = [subprocess.Popen(_cmd([*overrides, "agent.threads=1"], frames, f, [s]),
                                  **quiet) for s, f in enumerate(folders)]  # type: ignore[call-overload]
    errors = [p.communicate()[1] for p in procs]
    wall = time.perf_counter() - t0
    for p, err in zip(procs, errors, strict=True):
        if p.returncode != 0:
            raise RuntimeError(f"{name}: train exited {p.returncode}: {err.decode()[-2000:]}")
    done = _summaries(folders)
    total = sum(int(d["frames"]) for d in done)
    return {"wall_s": round(wall, 2), "frames": total, "updates": sum(int(d["updates"]) for d in done),
            "env_steps_per_s": round(total / wall, 2),
            "in_run_env_steps_per_s": round(total / max(float(d["wall_s"]) for d in done), 2)}


def run(seeds: int, frames: int, rounds: int, overrides: list[str],
        one_process_threads: int, engines: list[str]) -> dict[str, Any]:
    """``seeds`` runs of ``frames`` env steps each, in one process (``one_process_threads`` torch
    threads, 0: one per CPU; one arm per ``engines`` entry, own or shared) and in ``seeds``
    processes (one thread each)."""
    threads = one_process_threads or os.cpu_count() or 1
    order = [name for name, engine in ARMS.items() if engine in engines] + ["processes"]
    arms: dict[str, list[dict[str, Any]]] = {name: [] for name in order}
    for r in range(rounds):
        for name in order if r % 2 == 0 else order[::-1]:
            with tempfile.TemporaryDirectory(prefix="memrl_bench_group_") as tmp:
                arms[name].append(_arm(name, seeds, frames, list(overrides), Path(tmp), threads))
    best = {n: max(rows, key=lambda row: row["env_steps_per_s"]) for n, rows in arms.items()}
    base = best["processes"]["env_steps_per_s"]
    ratios = {f"{n}_over_processes": round(best[n]["env_steps_per_s"] / base, 3) for n in order[:-1]}
    return {"seeds": seeds, "frames_per_run": frames, "overrides": list(overrides),
            "cpu_count": os.cpu_count(), "one_process_threads": threads, "rounds": arms, **ratios}
