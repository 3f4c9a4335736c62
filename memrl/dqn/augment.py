"""DrQ-style image shifts of sampled batches (Kostrikov et al., 2020; Yarats et al., 2021).

Each stack is padded by replicating its border ``pad`` pixels and cropped back to its size at
a random offset: one offset per stack (its 4 frames move together, so motion between frames is
kept), drawn independently for ``pixels`` and ``("next", "pixels")``. Applied to sampled
batches only, never to stored data or to acting. Written here because TorchRL has no
shift-crop transform (its ``RandomCropTensorDict`` crops along batch dimensions).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase


def random_shift(pixels: torch.Tensor, pad: int, generator: torch.Generator) -> torch.Tensor:
    """``pixels`` ``[..., C, H, W]`` shifted by up to ``pad`` pixels each way, one offset per
    stack, the border replicated (a new tensor, same dtype)."""
    if pad <= 0:
        return pixels
    *batch, c, h, w = pixels.shape
    flat = pixels.reshape(-1, c, h, w)
    n, dev = flat.shape[0], flat.device
    offset = torch.randint(0, 2 * pad + 1, (n, 2), generator=generator, device=generator.device).to(dev)
    rows = (torch.arange(h, device=dev)[None, :] + offset[:, :1] - pad).clamp_(0, h - 1)  # [n, H]
    cols = (torch.arange(w, device=dev)[None, :] + offset[:, 1:] - pad).clamp_(0, w - 1)  # [n, W]
    stack, frame = torch.arange(n, device=dev), torch.arange(c, device=dev)
    out = flat[stack[:, None, None, None], frame[None, :, None, None], rows[:, None, :, None],
               cols[:, None, None, :]]
    return out.reshape(*batch, c, h, w)


def shift_batch(batch: TensorDictBase, pad: int, generator: torch.Generator) -> TensorDictBase:
    """A shallow copy of ``batch`` with ``pixels`` and ``("next", "pixels")`` shifted
    independently (:func:`random_shift`); the batch itself is left as it is."""
    out = batch.exclude("pixels", ("next", "pixels"))
    out.set("pixels", random_shift(batch["pixels"], pad, generator))
    out.set(("next", "pixels"), random_shift(batch["next", "pixels"], pad, generator))
    return out
