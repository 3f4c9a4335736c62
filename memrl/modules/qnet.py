"""The Q-networks (Table I and its variants), built from the ``network`` config, and their
TorchRL actor.

A network is config (``conf/network/*.yaml``, ``_target_`` + keyword arguments) and travels
with its weights: :func:`build_qnet` instantiates it and records the arguments in ``net.arch``,
which every weights file stores next to the weights (``memrl.checkpoint``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.data import Categorical
from torchrl.modules import QValueActor

from memrl.envs.vehicles import N_ACTIONS
from memrl.modules.network_config import NetworkConfig

TABLE1_TARGET = "memrl.modules.qnet.QNetwork"
"""``_target_`` of the paper's Table I network (``conf/network/table1.yaml``)."""

RUNTIME_ARGS = ("pool_first",)
"""Constructor arguments that change speed, never outputs nor parameter names (not stored)."""


class QNetwork(nn.Module):
    """Table I: three 3x3 conv layers of 16 filters, each ReLU + 2x2 max-pool, FC 256, 9 outputs.

    Padding 1 ("same") keeps each conv's size, so 84 -> 42 -> 21 -> 10 after the three pools
    (the last pool floors 21 / 2); the FC layer sees 16 x 10 x 10 = 1600 features. Input is
    uint8 ``[..., frames, H, W]``, scaled to [0, 1] inside the module.

    Subclasses change a part (e.g. :class:`DuelingQNetwork` the head, through :meth:`make_head`);
    ``self.arch`` records the constructor's architecture arguments (a subclass with arguments
    of its own adds them there).

    Args:
        frames: stacked input frames (channels of the first conv).
        size: side of the square input frames [px].
        n_actions: Q-values out.
        channels: filters of each conv.
        hidden: units of the hidden FC layer.
        pool_first: max-pool before ReLU (the same outputs, a quarter of the ReLU work).
        layernorm: LayerNorm after the hidden FC layer (before its ReLU).
        layernorm_convs: a LayerNorm over (channels, H, W) after each conv (``GroupNorm`` with
            one group: per-channel affine), before its pool and ReLU.
    """

    def __init__(self, frames: int = 4, size: int = 84, n_actions: int = N_ACTIONS,
                 channels: int = 16, hidden: int = 256, pool_first: bool = True,
                 layernorm: bool = False, layernorm_convs: bool = False) -> None:
        super().__init__()
        self.frames = frames
        self.arch: dict[str, Any] = {
            "_target_": f"{type(self).__module__}.{type(self).__qualname__}", "frames": frames,
            "size": size, "n_actions": n_actions, "channels": channels, "hidden": hidden,
            "layernorm": layernorm, "layernorm_convs": layernorm_convs}
        """The architecture: what :func:`build_qnet` rebuilds this network from."""
        layers: list[nn.Module] = []
        c_in = frames
        for _ in range(3):
            # ReLU is monotonic, so max-pool then ReLU equals ReLU then max-pool; pooling first
            # runs the ReLU (forward and backward) on a quarter of the values. Parameter names
            # are the same either way.
            act_pool = [nn.MaxPool2d(2), nn.ReLU()] if pool_first else [nn.ReLU(), nn.MaxPool2d(2)]
            norm = [nn.GroupNorm(1, channels)] if layernorm_convs else []
            layers += [nn.Conv2d(c_in, channels, 3, padding=1), *norm, *act_pool]
            c_in = channels
        self.features = nn.Sequential(*layers)
        side = size
        for _ in range(3):
            side //= 2
        self.conv_size = channels * side * side
        """Features the conv trunk gives the head (:meth:`conv_features`, flattened)."""
        self.head = self.make_head(self.conv_size, hidden, n_actions, layernorm)

    def make_head(self, features: int, hidden: int, n_actions: int, layernorm: bool) -> nn.Module:
        """The part after the conv trunk: flattened features -> Q-values ``[B, n_actions]``."""
        return nn.Sequential(nn.Flatten(), *hidden_layer(features, hidden, layernorm),
                             nn.Linear(hidden, n_actions))

    conv_dtype: torch.dtype | None = None
    """Lower precision for the conv trunk (``torch.bfloat16``: autocast, weights stay float32;
    the FC head and the Q-values stay float32); None: float32 throughout."""

    config_schema: ClassVar[type] = NetworkConfig
    """Its ``network`` node's keys, ranges and cross-key check (:func:`check_network`): a
    subclass with keys of its own names its own schema here."""

    def conv_features(self, pixels: torch.Tensor) -> torch.Tensor:
        """The conv trunk's float32 output ``[B', C, h, w]`` of uint8 ``pixels [..., frames, H,
        W]``, with the leading dims flattened into ``B'`` (what the head reads)."""
        x = pixels.reshape(-1, *pixels.shape[-3:]).to(torch.float32).div_(255.0)
        if self.conv_dtype is None:
            return self.features(x)
        with torch.autocast(x.device.type, dtype=self.conv_dtype):
            features = self.features(x)
        return features.float()

    def trunk(self, pixels: torch.Tensor) -> torch.Tensor:
        """The head's output ``[B', ...]`` of uint8 ``pixels [..., frames, H, W]``, with the
        leading dims flattened into ``B'``."""
        return self.head(self.conv_features(pixels))

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        """Q-values ``[..., n_actions]`` (what acting, evaluation and deployment use)."""
        return self.trunk(pixels).reshape(*pixels.shape[:-3], -1)

    def outputs(self, pixels: torch.Tensor) -> dict[str, torch.Tensor]:
        """Its declared outputs: ``{"q": Q-values}`` (a distributional head adds its own)."""
        return {"q": self(pixels)}

    @classmethod
    def td_term(cls, agent: Any) -> TDTerm:
        """The TD term that trains this head: eq. (1) (``agent.advantage_learning`` sets alpha)."""
        return TDTerm(advantage=float(agent.advantage_learning))


@dataclass(frozen=True)
class TDTerm:
    """Eq. (1): the mean of 1/2 (r + gamma^m Q_target(s', argmax_a Q(s', a)) - Q(s, a))^2, no
    bootstrap on terminated transitions (TorchRL's double ``DQNLoss``; its ``l2`` distance has
    no 1/2; ``m`` is the batch's ``steps_to_next_obs`` where n-step returns give one, else 1).

    With ``advantage`` = alpha > 0 the target is advantage learning's (Bellemare et al., 2016):
    less alpha (max_b Q_target(s, b) - Q_target(s, a)), which leaves the greedy action's value
    as it is and multiplies the action gap by 1 / (1 - alpha)."""

    weight: float = 1.0
    advantage: float = 0.0
    """Advantage learning's alpha in [0, 1) (``agent.advantage_learning``); 0: eq. (1)."""
    name: str = "td"

    def __call__(self, batch: TensorDictBase, q: Any) -> torch.Tensor:
        """The term on ``batch``; ``q``: the learner's :class:`memrl.values.QFunctions`."""
        if self.advantage == 0:
            return self.weight * 0.5 * q.double_dqn_loss()
        # DQNLoss has no advantage-learning target: its reward is lowered by the correction
        # instead (the target is reward + bootstrap), on a copy that leaves the batch as it is.
        lowered = batch.clone(False)
        lowered.set("next", batch.get("next").clone(False))
        reward = batch.get(("next", "reward"))
        gap = self.advantage * target_action_gap(batch, q)
        lowered.set(("next", "reward"), reward - gap.reshape(reward.shape).to(reward.dtype))
        return self.weight * 0.5 * q.double_dqn_loss(lowered)


def target_action_gap(batch: TensorDictBase, q: Any) -> torch.Tensor:
    """``max_b Q_target(s, b) - Q_target(s, a)`` per item ``[B]`` (>= 0; 0 for the greedy action),
    the target network's Q of the batch's own ``pixels`` and ``action`` (``q``: QFunctions)."""
    a = batch.get("action").reshape(-1, 1).long()
    values = q.target(batch.get("pixels"))["q"].reshape(a.shape[0], -1)
    return values.max(-1).values - values.gather(-1, a).squeeze(-1)


def hidden_layer(features: int, hidden: int, layernorm: bool) -> list[nn.Module]:
    """Linear -> [LayerNorm] -> ReLU: the hidden FC layer of a head."""
    return [nn.Linear(features, hidden), *([nn.LayerNorm(hidden)] if layernorm else []), nn.ReLU()]


class DuelingHead(nn.Module):
    """Value and advantage streams; Q = V + A - mean_a(A) (Wang et al., 2016)."""

    def __init__(self, features: int, hidden: int, n_actions: int, layernorm: bool) -> None:
        super().__init__()
        self.value = nn.Sequential(nn.Flatten(), *hidden_layer(features, hidden, layernorm),
                                   nn.Linear(hidden, 1))
        self.advantage = nn.Sequential(nn.Flatten(), *hidden_layer(features, hidden, layernorm),
                                       nn.Linear(hidden, n_actions))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        a = self.advantage(features)
        return self.value(features) + a - a.mean(-1, keepdim=True)


class DuelingQNetwork(QNetwork):
    """Table I's conv trunk with a dueling head: value and advantage streams, each a hidden FC
    layer of ``hidden`` units (``conf/network/dueling.yaml``)."""

    def make_head(self, features: int, hidden: int, n_actions: int, layernorm: bool) -> nn.Module:
        return DuelingHead(features, hidden, n_actions, layernorm)


TABLE1: dict[str, Any] = {"_target_": TABLE1_TARGET, "frames": 4, "size": 84, "n_actions": N_ACTIONS,
                          "channels": 16, "hidden": 256, "layernorm": False, "layernorm_convs": False}
"""The architecture of a weights file that stores none (written before architectures were)."""


def plain_arch(arch: Mapping[str, Any]) -> dict[str, Any]:
    """``arch`` (a dict or DictConfig) as a plain dict."""
    from omegaconf import DictConfig, OmegaConf

    if isinstance(arch, DictConfig):
        return OmegaConf.to_container(arch, resolve=True)  # type: ignore[return-value]
    return dict(arch)


def build_qnet(arch: Mapping[str, Any] | None = None, **runtime: Any) -> nn.Module:
    """The network of ``arch`` (``_target_`` + arguments: a ``network`` config node or a
    stored architecture; None: Table I), with ``runtime`` arguments (``pool_first``) added.
    ``net.arch`` holds every architecture argument, to be stored with the weights."""
    from hydra.utils import instantiate

    node = plain_arch(TABLE1 if arch is None else arch)
    net = instantiate(node, **runtime, _convert_="all")
    if not isinstance(net, nn.Module):
        raise TypeError(f"network._target_ {node.get('_target_')!r} made a {type(net).__name__}, "
                        "not a torch.nn.Module")
    arch_args = {k: v for k, v in node.items() if k not in RUNTIME_ARGS}
    net.arch = {**getattr(net, "arch", {}), **arch_args}  # type: ignore[assignment]
    return net


def network_class(network: Any) -> type:
    """The class of a ``network`` node or stored architecture (its ``_target_``), a class, or a
    built network; None: Table I."""
    if network is None:
        return QNetwork
    if isinstance(network, type):
        return network
    if isinstance(network, nn.Module):
        return type(network)
    from hydra.utils import get_class

    return get_class(str(network["_target_"]))


def network_for_task(network: Any, env: Any, gamma: float) -> Any:
    """``network`` (a ``network`` node) with what its class takes from the task filled in (a
    categorical head's null support bounds: ``for_task``); unchanged for other classes."""
    fill = getattr(network_class(network), "for_task", None)
    return network if fill is None else fill(plain_arch(network), env, gamma)


def decision_values(net: nn.Module, pixels: torch.Tensor) -> torch.Tensor:
    """Values ``[..., A]`` whose argmax is ``net``'s greedy action: its ``decide`` where it has
    one (a crash-risk critic's safe choice, :mod:`memrl.modules.risk`), else its Q-values."""
    decide = getattr(net, "decide", None)
    return decide(pixels) if decide is not None else net(pixels)


def head_td_term(agent: Any, network: Any = None) -> Any:
    """The TD term of the value head ``network`` (a ``network`` node or stored architecture, a
    class or a built network; None: Table I), as the ``agent`` config sets it: its class's
    ``td_term_for(agent, node)`` where its term reads the node's keys, else ``td_term(agent)``;
    eq. (1)'s for a network that declares neither."""
    cls = network_class(network)
    by_node = getattr(cls, "td_term_for", None)
    if by_node is not None:
        node = getattr(network, "arch", network) if isinstance(network, nn.Module) else network
        return by_node(agent, plain_arch(node))
    return getattr(cls, "td_term", QNetwork.td_term)(agent)


def arch_of(net: nn.Module) -> dict[str, Any]:
    """The architecture to store with ``net``'s weights (what :func:`build_qnet` rebuilds it from)."""
    arch = getattr(net, "arch", None)
    if arch is None:
        raise TypeError(f"{type(net).__name__} records no architecture (build it with build_qnet)")
    return dict(arch)


def input_frames(net: nn.Module) -> int:
    """Stacked frames the network takes: ``net.frames``, else its first conv's input channels."""
    frames = getattr(net, "frames", None)
    if frames is None:
        conv = next((m for m in net.modules() if isinstance(m, nn.Conv2d)), None)
        frames = conv.in_channels if conv is not None else 4
    return int(frames)


class Decision(nn.Module):
    """A network seen through :func:`decision_values` (its parameters are ``net``'s)."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        return decision_values(self.net, pixels)


def acting_actor(actor: QValueActor) -> QValueActor:
    """The actor that acts as ``actor``'s network chooses (:func:`decision_values`): ``actor``
    itself for a network without ``decide``, else a ``QValueActor`` over :class:`Decision`,
    sharing its parameters (TorchRL's ``DQNLoss`` keeps ``actor``, whose values are the Q-values)."""
    net = actor.module[0].module
    if getattr(net, "decide", None) is None:
        return actor
    n_actions = int(getattr(net, "arch", {}).get("n_actions", N_ACTIONS))
    return QValueActor(Decision(net), in_keys=["pixels"], spec=Categorical(n_actions, dtype=torch.int64))


def make_q_actor(frames: int = 4, size: int = 84, pool_first: bool = True,
                 network: Mapping[str, Any] | nn.Module | None = None) -> QValueActor:
    """A TorchRL ``QValueActor`` reading ``pixels`` and writing ``action`` (int64 index),
    ``action_value`` and ``chosen_action_value``; its network is ``network`` (a built module,
    or an architecture for :func:`build_qnet`; None: Table I for ``frames`` and ``size``)."""
    if isinstance(network, nn.Module):
        net = network
    elif network is None:
        net = QNetwork(frames, size, pool_first=pool_first)
    else:
        net = build_qnet(network, pool_first=pool_first)
    n_actions = int(getattr(net, "arch", {}).get("n_actions", N_ACTIONS))
    return QValueActor(net, in_keys=["pixels"], spec=Categorical(n_actions, dtype=torch.int64))
