"""A plain-Python reference of n-step windows over per-stream lists of 1-step transitions."""

from __future__ import annotations

import torch


def reference(steps: list, n: int, gamma: float) -> list[dict]:
    """Per row in write order (step-major, row i = stream i): the n-step target's parts.

    ``steps``: one ``[S]`` tensordict per env step (all steps stored, none overwritten).
    A window runs over later steps of the same stream while the previous one is not done.
    """
    out = []
    for t, td in enumerate(steps):
        for s in range(td.shape[0]):
            total, m, u = float(td["next", "reward"][s, 0]), 1, t
            while m < n and not bool(steps[u]["next", "done"][s, 0]) and u + 1 < len(steps):
                u += 1
                total = total + gamma ** m * float(steps[u]["next", "reward"][s, 0])
                m += 1
            last = steps[u][s]
            out.append({"reward": torch.tensor([total], dtype=torch.float32), "m": m,
                        "terminated": bool(last["next", "terminated"][0]),
                        "done": bool(last["next", "done"][0]),
                        "next_pixels": last["next", "pixels"]})
    return out
