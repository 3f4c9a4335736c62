"""The policy interface shared by the agent, scripted drivers, humans and evaluation.

A :class:`DrivingPolicy` picks one of the 9 actions each step from the env's world state
and/or the agent's stacked pixels. :class:`PolicyModule` runs any of them inside a TorchRL
rollout or collector (it reads the world state through the env it was given).
:class:`GreedyPolicy` is the trained agent (argmax Q) and :class:`FrameStack` the stacked
pixels of a plain gym env: one of each, shared by evaluation, stage-1 drives, recording and
the deploy baseline.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.stride import history_length, select_frames
from memrl.envs.vehicles import N_ACTIONS
from memrl.modules.qnet import QNetwork, decision_values


class StopRecording(Exception):  # noqa: N818 - a request, not an error
    """Raised by a policy (e.g. the human pressing Esc) to end a recording early; the episode
    under way is dropped and the finished ones are kept."""


class DrivingPolicy(ABC):
    """Decides the agent's action; may read the world state (privileged) or only pixels."""

    def reset(self, env: LaneChangeEnv) -> None:  # noqa: B027
        """Called after each env reset (default: nothing to prepare)."""

    @abstractmethod
    def act(self, env: LaneChangeEnv, pixels: np.ndarray) -> int:
        """Action index in [0, 9) for the current step; ``pixels`` is uint8 ``[4, H, W]``."""


class FrameStack:
    """``n`` frames ``stride`` steps apart along the channel axis, oldest first, the first frame
    standing in for the steps before a reset (:mod:`memrl.envs.stride`).

    What TorchRL's ``CatFrames(padding="same")`` (every ``stride``-th of its frames) and the
    batched engine's frame ring give, for a plain gym env stepped by hand
    (``tests/test_evaluate.py``, ``tests/test_frame_stride.py`` check the equality).
    """

    # Hand-written: mirrors TorchRL's CatFrames (padding="same") on plain numpy arrays.
    def __init__(self, n: int = 4, stride: int = 1) -> None:
        self.n, self.stride = n, stride
        self.history: np.ndarray | None = None
        """The last ``(n - 1) * stride + 1`` frames, newest last."""
        self.frames: np.ndarray | None = None
        """The stack (the observation)."""

    def reset(self, obs: np.ndarray) -> np.ndarray:
        """Start a stack from the reset observation ``[C, H, W]``; returns ``[n * C, H, W]``."""
        self.history = np.concatenate([obs] * history_length(self.n, self.stride))
        self.frames = select_frames(self.history, obs.shape[0], self.stride)
        return self.frames

    def push(self, obs: np.ndarray) -> np.ndarray:
        """Drop the oldest frame, append ``obs``; returns the stack."""
        assert self.history is not None, "FrameStack.push before reset"
        self.history = np.concatenate([self.history[obs.shape[0]:], obs])
        self.frames = select_frames(self.history, obs.shape[0], self.stride)
        return self.frames


class GreedyPolicy(DrivingPolicy):
    """argmax Q of a Q-network (the trained agent), for one stack or a whole batch at once.

    The network is a copy (the one given is left as it is) in channels-last memory format:
    about 2x faster on CPU (oneDNN), the same Q-values (tested against the plain network).
    On CPU a large batch goes through in chunks: its activations then stay in the caches
    (one thread: about 0.4 ms per sample in chunks of 8 to 32, 0.8 ms in one batch of 192).

    Args:
        net: a Q-network taking uint8 ``[B, frames, H, W]``.
        device: where the copy runs (``to`` moves it later).
        cpu_chunk: samples per forward pass on CPU (None: the whole batch at once).
    """

    def __init__(self, net: nn.Module, device: torch.device | str = "cpu",
                 cpu_chunk: int | None = 16) -> None:
        self.net = copy.deepcopy(net).eval()
        self.cpu_chunk = cpu_chunk
        self.to(device)

    def to(self, device: torch.device | str) -> GreedyPolicy:
        """Move the network to ``device``; returns self."""
        self.device = torch.device(device)
        self.net.to(device=self.device, memory_format=torch.channels_last)  # type: ignore[call-overload]
        return self

    def _parts(self, pixels: torch.Tensor) -> list[torch.Tensor]:
        """``pixels`` on the device, channels-last, in chunks of ``cpu_chunk`` on the CPU."""
        x = pixels.to(self.device, non_blocking=True)
        chunk = self.cpu_chunk if self.device.type == "cpu" and self.cpu_chunk else len(x)
        return [part.contiguous(memory_format=torch.channels_last) for part in x.split(max(1, chunk))]

    @torch.inference_mode()
    def q_values(self, pixels: torch.Tensor) -> torch.Tensor:
        """Q-values ``[B, actions]`` of uint8 stacks ``[B, frames, H, W]`` (moved to the device)."""
        parts = [self._forward(part) for part in self._parts(pixels)]
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        """The network's forward; the 2x2 max-pools of a Table I trunk (any :class:`QNetwork`
        that keeps its forward) as strided maxima (the same values; nn.MaxPool2d on
        channels-last CPU tensors is about a third of the pass)."""
        net = self.net
        if not isinstance(net, QNetwork) or type(net).forward is not QNetwork.forward or \
                net.conv_dtype is not None or x.device.type != "cpu":
            return net(x)
        batch = x.shape[:-3]
        h = x.reshape(-1, *x.shape[-3:]).to(torch.float32).div_(255.0)  # as QNetwork.forward
        for layer in net.features:
            h = max_pool_2x2(h) if _plain_2x2_pool(layer) else layer(h)
        return net.head(h).reshape(*batch, -1)

    @torch.inference_mode()
    def outputs(self, pixels: torch.Tensor) -> dict[str, torch.Tensor]:
        """The network's declared outputs (``net.outputs``: ``"q"`` and, e.g., a distribution's
        logits or a crash risk) of uint8 stacks ``[B, frames, H, W]``; a network without
        ``outputs``: ``{"q": Q-values}``. In chunks on CPU, as :meth:`q_values`."""
        declared = getattr(self.net, "outputs", None)
        if declared is None:
            return {"q": self.q_values(pixels)}
        parts = [declared(part) for part in self._parts(pixels)]
        return {key: torch.cat([p[key] for p in parts]) for key in parts[0]}

    def act_batch(self, pixels: torch.Tensor) -> torch.Tensor:
        """Greedy actions (int64 ``[B]``, on the device) of a batch of stacks: argmax Q, or a
        crash-risk critic's safe choice (:func:`memrl.modules.qnet.decision_values`)."""
        if getattr(self.net, "decide", None) is None:
            return self.q_values(pixels).argmax(-1)
        with torch.inference_mode():
            return torch.cat([decision_values(self.net, part).argmax(-1) for part in self._parts(pixels)])

    def act(self, env: LaneChangeEnv, pixels: np.ndarray) -> int:
        return int(self.act_batch(torch.from_numpy(np.ascontiguousarray(pixels))[None])[0])


def _plain_2x2_pool(layer: nn.Module) -> bool:
    return (isinstance(layer, nn.MaxPool2d) and layer.kernel_size in (2, (2, 2))
            and layer.stride in (2, (2, 2)) and layer.padding in (0, (0, 0))
            and layer.dilation in (1, (1, 1)) and not layer.ceil_mode)


def max_pool_2x2(x: torch.Tensor) -> torch.Tensor:
    """``F.max_pool2d(x, 2)`` (odd sizes floored) as the maximum of the four strided views."""
    # Hand-written: the same maxima as torch's max_pool2d, about 2x faster on channels-last CPU tensors.
    h, w = x.shape[-2] // 2 * 2, x.shape[-1] // 2 * 2
    x = x[..., :h, :w]
    return torch.maximum(torch.maximum(x[..., 0::2, 0::2], x[..., 0::2, 1::2]),
                         torch.maximum(x[..., 1::2, 0::2], x[..., 1::2, 1::2]))


class RandomPolicy(DrivingPolicy):
    """Uniform over the 9 actions, from its own seeded generator."""

    def __init__(self, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)

    def act(self, env: LaneChangeEnv, pixels: np.ndarray) -> int:
        return int(self.rng.integers(N_ACTIONS))


class PolicyModule(TensorDictModuleBase):
    """Wraps a :class:`DrivingPolicy` as a TorchRL policy: reads ``pixels``, writes ``action``.

    Args:
        policy: the driving policy.
        env: the gym env whose world state the policy may read (``unwrap(torchrl_env)``).
    """

    in_keys = ["pixels"]
    out_keys = ["action"]

    def __init__(self, policy: DrivingPolicy, env: LaneChangeEnv) -> None:
        super().__init__()
        self.policy = policy
        self.env = env
        self._last_steps = -1

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        if self.env.steps == 0 and self._last_steps != 0:
            self.policy.reset(self.env)
        self._last_steps = self.env.steps
        pixels = td["pixels"].cpu().numpy()
        action = self.policy.act(self.env, pixels)
        td.set("action", torch.tensor(action, dtype=torch.int64))
        return td


class PerturbedPolicy(DrivingPolicy):
    """Executes a uniform random action instead of ``policy``'s with probability ``noise`` per
    step (DART-style noise injection); the wrapped driver still decides every step.

    ``perturbed`` flags, per step since the last reset, whether the executed action differs
    from the driver's. Recording keeps only the other steps, so the prior knowledge shows the
    driver's own actions from the off-path states its noise led to (recoveries), never the
    noise.
    """

    def __init__(self, policy: DrivingPolicy, noise: float, seed: int = 0) -> None:
        if not 0.0 <= noise < 1.0:
            raise ValueError(f"action noise must be in [0, 1), got {noise!r}")
        self.policy = policy
        self.noise = noise
        self.rng = np.random.default_rng(seed)
        self.perturbed: list[bool] = []
        self.needs_render = bool(getattr(policy, "needs_render", False))

    def reset(self, env: LaneChangeEnv) -> None:
        self.perturbed = []
        self.policy.reset(env)

    def act(self, env: LaneChangeEnv, pixels: np.ndarray) -> int:
        action = self.policy.act(env, pixels)
        executed = int(self.rng.integers(N_ACTIONS)) if self.rng.random() < self.noise else action
        self.perturbed.append(executed != action)
        return executed

    def close(self) -> None:
        close = getattr(self.policy, "close", None)
        if callable(close):
            close()
