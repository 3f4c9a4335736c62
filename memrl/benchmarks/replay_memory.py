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

With ``streams`` S > 1 (default 16), both variants are also measured as the batched trainer
writes: S envs stepped together (:func:`stream_batches`, episodes of 1-300 steps per env), one
``extend`` of S rows per env step followed by one ``sample(32)``, until N transitions are
stored; reported: the RSS added, and the write and sample time per env step (mean over the
steps, and the median, which leaves out one-time costs such as the compact ring's first touch;
data generation not timed), for the compact storage with ``streams=S`` and the plain one, and
for the compact storage sampled with ``buffer.crash_share`` = 0.1 (``crash``: the cost of finding
the crash rows at every sample; the synthetic episodes end in a crash half the time), and for
the compact storage with prioritized replay, ``buffer.priority`` = 0.5 (``priority``: its
sample time includes writing the batch's new priorities back, as the trainer does after each
update, from random TD errors).
"""

from __future__ import annotations

import argparse
import gc
import json
import subprocess
import sys
import time
from collections.abc import Iterator
from typing import Any

NAIVE_BYTES_PER_TRANSITION = 2 * 4 * 84 * 84  # two uint8 stacks of 4 frames
CRASH_SHARE = 0.1
"""``buffer.crash_share`` of the ``crash`` variant (the compact storage otherwise)."""
PRIORITY = 0.5
"""``buffer.priority`` (alpha) of the ``priority`` variant (the compact storage otherwise)."""
VARIANTS = {"compact": True, "crash": True, "priority": True, "naive": False}
"""Each variant and whether it stores compactly."""


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


def stream_batches(streams: int, total: int, seed: int = 0, max_len: int = 300, size: int = 84,
                   stack: int = 4) -> Iterator[Any]:
    """``total // streams`` env steps of ``streams`` envs, one TensorDict of ``[streams]`` rows
    each (row i = env i), random frames stacked as ``CatFrames(padding="same")`` does."""
    import numpy as np
    import torch
    from tensordict import TensorDict

    rng = np.random.default_rng(seed)
    left = np.zeros(streams, dtype=np.int64)  # steps left in each env's episode
    stk = np.zeros((streams, stack, size, size), dtype=np.uint8)
    for _ in range(total // streams):
        reset = left == 0
        if reset.any():  # the reset frame repeated; a fresh array: the last one was yielded
            stk = stk.copy()
            stk[reset] = rng.integers(0, 256, (int(reset.sum()), 1, size, size), dtype=np.uint8)
            left[reset] = rng.integers(1, max_len + 1, int(reset.sum()))
        new = rng.integers(0, 256, (streams, 1, size, size), dtype=np.uint8)
        nxt = np.concatenate([stk[:, 1:], new], 1)
        left -= 1
        done = torch.from_numpy(left == 0)[:, None]
        term = done & torch.from_numpy(rng.random((streams, 1)) < 0.5)
        yield TensorDict({
            "pixels": torch.from_numpy(stk), "action": torch.from_numpy(rng.integers(0, 9, streams)),
            "is_demo": torch.zeros(streams, dtype=torch.bool),
            "next": {"pixels": torch.from_numpy(nxt),
                     "reward": torch.from_numpy(rng.normal(size=(streams, 1)).astype(np.float32)),
                     "done": done, "terminated": term, "truncated": done & ~term},
        }, [streams])
        stk = nxt


def measure_streams(variant: str, transitions: int, streams: int, seed: int = 0,
                    batch_size: int = 32) -> dict[str, Any]:
    """In this process: RSS added and time per env step of ``streams`` envs written together."""
    import torch

    from memrl.data.buffers import agent_buffer, priority_sampler

    torch.set_num_threads(1)
    compact = VARIANTS[variant]
    share = CRASH_SHARE if variant == "crash" else 0.0
    alpha = PRIORITY if variant == "priority" else 0.0
    warm = agent_buffer(64 * streams, 8, compact=compact, streams=streams, crash_share=share, priority=alpha)
    for td in stream_batches(streams, 16 * streams, seed + 1):
        warm.extend(td)
        warm.sample()
    del warm, td
    gc.collect()
    before = _status_kb("VmRSS")
    rb = agent_buffer(transitions, batch_size, compact=compact, streams=streams, crash_share=share,
                      priority=alpha)
    sampler = priority_sampler(rb)
    writes, samples = [], []
    for td in stream_batches(streams, transitions, seed):
        # the TD errors an update would give, drawn before the clock (and only here: the other
        # variants draw their samples from torch's generator as before)
        delta = torch.rand(batch_size) if sampler is not None else None
        t0 = time.perf_counter()
        rb.extend(td)
        t1 = time.perf_counter()
        batch = rb.sample()
        if sampler is not None and delta is not None:
            sampler.update_priority(batch["index"], delta)
        samples.append(time.perf_counter() - t1)
        writes.append(t1 - t0)
    steps, write_s, sample_s = len(writes), sum(writes), sum(samples)
    step_times = sorted(w + s for w, s in zip(writes, samples, strict=True))
    del td
    gc.collect()
    assert batch["pixels"].shape == (batch_size, 4, 84, 84)
    after = _status_kb("VmRSS")
    out = {"variant": variant, "streams": streams, "transitions": len(rb), "env_steps": steps,
           "added_bytes": (after - before) * 1024,
           "added_mib": round((after - before) / 1024, 1),
           "write_us_per_step": round(1e6 * write_s / steps, 1),
           "sample_us_per_step": round(1e6 * sample_s / steps, 1),
           "step_us": round(1e6 * (write_s + sample_s) / steps, 1),
           "step_us_median": round(1e6 * step_times[steps // 2], 1)}
    if compact:
        storage = rb.storage
        out.update(ring_frames=storage.ring_size, frames_pushed=storage._head,
                   storage_bytes=storage.nbytes())
    return out


def _subprocess(variant: str, transitions: int, seed: int, timeout: float,
                streams: int = 1) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "memrl.benchmarks.replay_memory", "--variant", variant,
           "--transitions", str(transitions), "--seed", str(seed), "--streams", str(streams)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _naive_count(transitions: int, streams: int = 1) -> int:
    """Transitions the naive variant is measured at: N, or what fits (leaving 2 GB)."""
    fits = int((mem_available() - 2 * 2**30) / (1.1 * NAIVE_BYTES_PER_TRANSITION))
    return max(1000, min(transitions, fits)) // streams * streams


def run_streams(transitions: int, streams: int, naive: bool, seed: int,
                timeout_s: float) -> dict[str, Any]:
    """Compact (``streams=S``) and plain storage written S rows per env step, same run."""
    res: dict[str, Any] = {"streams": streams}
    res["compact"] = _subprocess("compact", transitions, seed, timeout_s, streams)
    res["compact_added_gb"] = round(res["compact"]["added_bytes"] / 1e9, 3)
    res["crash"] = _subprocess("crash", transitions, seed, timeout_s, streams)
    res["ratio_crash_to_compact_sample_time"] = round(
        res["crash"]["sample_us_per_step"] / res["compact"]["sample_us_per_step"], 3)
    res["priority"] = _subprocess("priority", transitions, seed, timeout_s, streams)
    res["ratio_priority_to_compact_sample_time"] = round(
        res["priority"]["sample_us_per_step"] / res["compact"]["sample_us_per_step"], 3)
    if naive:
        count = _naive_count(transitions, streams)
        res["naive"] = _subprocess("naive", count, seed, timeout_s, streams)
        res["naive_extrapolated"] = count < transitions
        naive_bytes = res["naive"]["added_bytes"] * transitions / count
        res["naive_added_gb"] = round(naive_bytes / 1e9, 3)
        res["ratio_compact_to_naive_bytes"] = round(res["compact"]["added_bytes"] / naive_bytes, 3)
        res["ratio_compact_to_naive_step_time"] = round(
            res["compact"]["step_us"] / res["naive"]["step_us"], 3)
    return res


def run(transitions: int = 100_000, naive: bool = True, seed: int = 0,
        timeout_s: float = 300.0, limit_gb: float = 2.0, streams: int = 16) -> dict[str, Any]:
    """Both variants side by side, each in its own process; bytes (1 GB = 1e9 B) and ratios.

    ``streams`` > 1 adds :func:`run_streams` under ``"streams"`` (1 leaves it out).
    """
    res: dict[str, Any] = {"transitions": transitions, "limit_gb": limit_gb}
    res["compact"] = _subprocess("compact", transitions, seed, timeout_s)
    if naive:
        # leave 2 GB to the rest of the machine; measure at a smaller count if N does not fit
        count = _naive_count(transitions)
        res["naive"] = _subprocess("naive", count, seed, timeout_s)
        res["naive_extrapolated"] = count < transitions
        naive_bytes = res["naive"]["added_bytes"] * transitions / count
        res["naive_added_gb"] = round(naive_bytes / 1e9, 3)
        res["ratio_compact_to_naive"] = round(res["compact"]["added_bytes"] / naive_bytes, 3)
    res["compact_added_gb"] = round(res["compact"]["added_bytes"] / 1e9, 3)
    res["compact_within_limit"] = res["compact"]["added_bytes"] <= limit_gb * 1e9
    if streams > 1:
        res["streams"] = run_streams(transitions, streams, naive, seed, timeout_s)
    return res


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variant", choices=list(VARIANTS), required=True)
    parser.add_argument("--transitions", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--streams", type=int, default=1)
    args = parser.parse_args()
    if args.streams > 1:
        print(json.dumps(measure_streams(args.variant, args.transitions, args.streams, args.seed)))
    else:
        print(json.dumps(measure(args.variant, args.transitions, args.seed)))


if __name__ == "__main__":
    main()
