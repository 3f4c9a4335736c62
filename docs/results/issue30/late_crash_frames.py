"""Frames before a run's late crashes, from its own replay buffer: one row per crash, the newest
frame of the stacks 40, 20, 10 and 0 env steps before the crash step, then the frame at the crash.

    python docs/results/issue30/late_crash_frames.py <run folder> <out.png> [--after 90000] [--count 6]

Reads ``checkpoints/last/buffer`` of a Default run whose buffer was never overwritten (one row
per env step of all envs; a stream's next step is ``num_envs`` rows on). Up is the driving
direction; the agent is the bright car in the middle. Written by hand: a diagnostic of one run.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch
import yaml

from memrl.data.buffers import agent_buffer

BACK = (40, 20, 10, 0)
"""Env steps before the crash step whose newest frame is shown."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--after", type=int, default=90_000, help="first buffer row of the crashes")
    parser.add_argument("--count", type=int, default=6)
    args = parser.parse_args()
    cfg = yaml.safe_load((args.run / "config.yaml").read_text())
    streams = int(cfg["env"]["num_envs"])
    rb = agent_buffer(int(cfg["buffer"]["capacity"]), 32, streams=streams)
    rb.loads(args.run / "checkpoints" / "last" / "buffer")
    td = rb.storage.get(torch.arange(len(rb)))
    crashes = td["next", "terminated"].reshape(-1).nonzero().squeeze(-1)
    crashes = crashes[crashes >= max(args.after, streams * max(BACK))][: args.count]
    tiles = []
    for row in crashes.tolist():
        frames = [td["pixels"][row - streams * back][-1].numpy() for back in BACK]
        frames.append(td["next", "pixels"][row][-1].numpy())
        tiles.append(np.concatenate([np.pad(f, 2, constant_values=255) for f in frames], 1))
    image = np.concatenate(tiles, 0)
    cv2.imwrite(str(args.out), cv2.resize(image, None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST))
    print(f"{len(tiles)} crashes (buffer rows {crashes.tolist()}) -> {args.out}")


if __name__ == "__main__":
    main()
