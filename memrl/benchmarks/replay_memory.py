"""Replay memory: resident memory added by filling the training buffer with N transitions.

Each variant runs in a fresh subprocess (``python -m memrl.benchmarks.replay_memory``), which
reads its own ``VmRSS`` from ``/proc/self/status`` after imports and a warm-up on a tiny
buffer, builds ``agent_buffer(N)``, fills it with N env-shaped transitions (episodes of 1-300
steps, :mod:`memrl.benchmarks.synthetic`), samples once, and reads ``VmRSS`` again:

- ``compact``: the training default, :class:`memrl.data.frame_store.FrameStackStorage`
  (each frame once, in a ring of ``2 N + 3`` frames, allocated and touched at the first write);
- ``naive``: TorchRL's ``LazyTensorStorage`` with both full stacks per transition.

If the machine lacks the memory for the naive variant at N, it is measured at the largest
count that fits and scaled to N (flagged ``naive_extrapolated``).
"""

from __future__ import annotations

import argparse
import gc
import json
import subprocess
import sys
import time
from typing import Any

NAIVE_BYTES_PER_TRANSITION = 2 * 4 * 84 * 84  # two uint8 stacks of 4 frames


def _status_kb(field: str) -> int:
    """A ``/proc/self/status`` field in kB (``VmRSS``, ``VmHWM``)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise RuntimeError(f"/proc/self/status has no {field}")


def mem_available() -> int:
    """``MemAvailable`` of the machine [bytes]."""
    with open("/proc/meminfo") as f:
        for line in f:
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("/proc/meminfo has no MemAvailable")


def measure(variant: str, transitions: int, seed: int = 0) -> dict[str, Any]:
    """In this process: RSS added by an ``agent_buffer`` of ``transitions``, filled."""
    import torch

    from memrl.benchmarks.synthetic import episodes
    from memrl.data.buffers import agent_buffer

    torch.set_num_threads(1)
    compact = {"compact": True, "naive": False}[variant]
    warm = agent_buffer(64, 8, compact=compact)  # lazy imports and first allocations
    for ep in episodes(200, seed + 1):
        warm.extend(ep)
    warm.sample()
    del warm, ep
    gc.collect()
    before = _status_kb("VmRSS")
    rb = agent_buffer(transitions, 32, compact=compact)
    start, n_eps = time.perf_counter(), 0
    for ep in episodes(transitions, seed):
        rb.extend(ep)
        n_eps += 1
    fill_s = time.perf_counter() - start
    del ep
    gc.collect()
    batch = rb.sample()
    assert batch["pixels"].shape[1:] == (4, 84, 84) and batch["pixels"].dtype == torch.uint8
    after = _status_kb("VmRSS")
    out = {"variant": variant, "transitions": len(rb), "episodes": n_eps,
           "rss_before_mib": round(before / 1024, 1), "rss_after_mib": round(after / 1024, 1),
           "added_bytes": (after - before) * 1024,
           "added_mib": round((after - before) / 1024, 1),
           "peak_rss_mib": round(_status_kb("VmHWM") / 1024, 1),
           "added_bytes_per_transition": round((after - before) * 1024 / max(len(rb), 1)),
           "fill_s": round(fill_s, 2)}
    if compact:
        storage = rb.storage
        out.update(ring_frames=storage.ring_size, frames_pushed=storage._head,
                   storage_bytes=storage.nbytes())
    return out


def _subprocess(variant: str, transitions: int, seed: int, timeout: float) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "memrl.benchmarks.replay_memory", "--variant", variant,
           "--transitions", str(transitions), "--seed", str(seed)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run(transitions: int = 100_000, naive: bool = True, seed: int = 0,
        timeout_s: float = 300.0, limit_gb: float = 2.0) -> dict[str, Any]:
    """Both variants side by side, each in its own process; bytes (1 GB = 1e9 B) and ratios."""
    res: dict[str, Any] = {"transitions": transitions, "limit_gb": limit_gb}
    res["compact"] = _subprocess("compact", transitions, seed, timeout_s)
    if naive:
        # leave 2 GB to the rest of the machine; measure at a smaller count if N does not fit
        fits = int((mem_available() - 2 * 2**30) / (1.1 * NAIVE_BYTES_PER_TRANSITION))
        count = max(1000, min(transitions, fits))
        res["naive"] = _subprocess("naive", count, seed, timeout_s)
        res["naive_extrapolated"] = count < transitions
        naive_bytes = res["naive"]["added_bytes"] * transitions / count
        res["naive_added_gb"] = round(naive_bytes / 1e9, 3)
        res["ratio_compact_to_naive"] = round(res["compact"]["added_bytes"] / naive_bytes, 3)
    res["compact_added_gb"] = round(res["compact"]["added_bytes"] / 1e9, 3)
    res["compact_within_limit"] = res["compact"]["added_bytes"] <= limit_gb * 1e9
    return res


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variant", choices=["compact", "naive"], required=True)
    parser.add_argument("--transitions", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(json.dumps(measure(args.variant, args.transitions, args.seed)))


if __name__ == "__main__":
    main()
