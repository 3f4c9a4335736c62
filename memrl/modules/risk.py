"""A crash-risk critic beside any value head (``network=risk``): Q_risk(s, a), the probability
that a crash follows within its horizon (Recovery RL, Thananjeyan et al. 2021; SQRL,
Srinivasan et al. 2020), and the safe choice of action it gives every greedy consumer.

:class:`RiskQNetwork` holds the task's value head (``base``: Table I, dueling, C51, HL-Gauss)
and a critic of its own (Table I's trunk, ``channels`` / ``hidden``, one logit per action).
Its ``forward`` is the base's Q-values, so TorchRL's ``DQNLoss`` and every base TD term train
the task head unchanged; the target network's copy of the critic is its own target network
(synced with the task head's every ``agent.target_update_interval`` updates). Its
:meth:`RiskQNetwork.decide` values, which the acting policy, the evaluation, deploy and the
learned cars take the argmax of (:func:`memrl.modules.qnet.decision_values`), pick the best
task action among those with ``Q_risk <= threshold``, else the least-risk action.

:class:`RiskTerm` trains it with a binary cross-entropy TD target, on agent data and demos:
``y = c + (1 - c) gamma_risk^m Q_risk_target(s', a')``, ``c = 1`` on a crash (the transition
terminated; a time limit bootstraps), ``a'`` the policy's next action (``bootstrap=policy``:
the safe choice of the online networks) or the safest one (``safest``: the least target risk).
The task head learns from the executed action (``task_action=executed``) or from the one it
proposed before the critic's mask (``proposed``: Recovery RL's task policy, which sees the
mask as part of the environment); the critic always learns from the executed one.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn

from memrl.fields import spec
from memrl.modules.network_config import NetworkConfig, check_network
from memrl.modules.qnet import TABLE1, QNetwork, head_td_term, hidden_layer, network_for_task

BOOTSTRAPS = ("policy", "safest")
TASK_ACTIONS = ("executed", "proposed")
TASK_ACTION_KEY = "task_action"
"""An optional transition key: the action the task head proposed before the mask (runs with
``network.task_action=proposed`` store it with every transition)."""


@dataclass
class RiskConfig(NetworkConfig):
    """A crash-risk critic beside the value head ``base`` (``network=risk``); ``channels``,
    ``hidden``, ``layernorm*``: the critic's own Table I trunk."""

    base: Any = field(default_factory=lambda: {k: v for k, v in TABLE1.items()
                                               if k not in ("frames", "size", "n_actions")})
    """The task's value head: a ``network`` node of its own (``_target_`` and its keys; Table I
    by default), checked against its own schema."""
    gamma: float = spec(0.97, gt=0, lt=1)
    """``gamma_risk``: the critic's discount, so its horizon (1 / (1 - gamma), 33 steps = 3.3 s
    at 0.97) is its own, not the task's."""
    threshold: float = spec(0.1, gt=0, le=1)
    """Actions with ``Q_risk <= threshold`` are allowed; the best task action among them is
    taken (none allowed: the least-risk action)."""
    weight: float = spec(1.0, gt=0)
    """Weight of the critic's cross-entropy in the loss (beside the base head's TD term)."""
    bootstrap: str = spec("policy", choices=BOOTSTRAPS)
    """``a'`` of the target: ``policy`` (the safe choice of the online networks, what the agent
    would do) or ``safest`` (the action of least target risk)."""
    prior: float = spec(0.01, gt=0, lt=1)
    """A fresh critic's risk: its output bias starts at logit(prior), so before it has learned
    anything it allows every action (prior below ``threshold``) and the agent acts as its task
    head does, as stage 2 starting from a stage 1 without a critic needs."""
    shared_trunk: bool = False
    """The critic reads the base head's conv trunk (its own hidden and output layers on the
    base's conv features; ``channels`` and ``layernorm_convs`` are then the base's): its
    cross-entropy also trains the convs the task head reads, an auxiliary crash-prediction task.
    With ``threshold=1`` no action is ever masked: the auxiliary task alone."""
    task_action: str = spec("executed", choices=TASK_ACTIONS)
    """The action the task head's TD term learns from: ``executed`` (the masked one) or
    ``proposed`` (its own choice before the mask: its greedy action, or the exploration's draw
    applied to it; stored per transition as ``task_action``). The critic learns from the
    executed action either way; the agent acts the same either way."""

    @staticmethod
    def check(node: Any, prefix: str = "network.") -> None:
        """The base head against its own schema (its class's ``config_schema``)."""
        check_network(node.base, f"{prefix}base")


class RiskQNetwork(nn.Module):
    """A value head ``base`` and a crash-risk critic over the same stacked frames."""

    config_schema = RiskConfig

    def __init__(self, base: nn.Module, frames: int = 4, size: int = 84, n_actions: int = 9,
                 channels: int = 16, hidden: int = 256, layernorm: bool = False,
                 layernorm_convs: bool = False, pool_first: bool = True, gamma: float = 0.97,
                 threshold: float = 0.1, weight: float = 1.0, bootstrap: str = "policy",
                 prior: float = 0.01, shared_trunk: bool = False, task_action: str = "executed") -> None:
        super().__init__()
        if not isinstance(base, nn.Module):
            raise TypeError(f"RiskQNetwork: base must be a network, got {type(base).__name__}")
        self.base = base
        self.shared_trunk = bool(shared_trunk)
        if self.shared_trunk:
            if not isinstance(base, QNetwork):
                raise TypeError(f"RiskQNetwork: shared_trunk needs a base with Table I's conv trunk (a "
                                f"QNetwork), got {type(base).__name__}")
            self.critic: nn.Module = nn.Sequential(
                nn.Flatten(), *hidden_layer(base.conv_size, hidden, layernorm), nn.Linear(hidden, n_actions))
        else:
            self.critic = QNetwork(frames, size, n_actions, channels=channels, hidden=hidden,
                                   layernorm=layernorm, layernorm_convs=layernorm_convs,
                                   pool_first=pool_first)
        self.frames, self.threshold = int(frames), float(threshold)
        self.proposes = task_action == "proposed"
        """The task head learns from its proposals (the acting loop stores them, see RiskConfig)."""
        self.gamma_risk = float(gamma)
        """The critic's discount (its TD term's; the evaluation's risk calibration reads it)."""
        with torch.no_grad():  # the output layer's bias at logit(prior): see RiskConfig.prior
            out = [m for m in self.critic.modules() if isinstance(m, nn.Linear)][-1]
            out.bias.fill_(float(torch.logit(torch.tensor(float(prior), dtype=torch.float64))))

    @property
    def conv_dtype(self) -> torch.dtype | None:
        return getattr(self.base, "conv_dtype", None)

    @conv_dtype.setter
    def conv_dtype(self, value: torch.dtype | None) -> None:  # the learner's precision, for both trunks
        self.base.conv_dtype = value
        if not self.shared_trunk:
            self.critic.conv_dtype = value

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        """The base head's Q-values ``[..., A]`` (what its TD term and ``DQNLoss`` train)."""
        return self.base(pixels)

    def risk_logits(self, pixels: torch.Tensor) -> torch.Tensor:
        """The critic's logits ``[..., A]``; Q_risk = their sigmoid."""
        if not self.shared_trunk:
            return self.critic(pixels)
        return self.critic(self.base.conv_features(pixels)).reshape(*pixels.shape[:-3], -1)

    def outputs(self, pixels: torch.Tensor) -> dict[str, torch.Tensor]:
        """The base's outputs (``"q"`` and its own), ``"risk"`` ``[..., A]`` in [0, 1] and its
        ``"risk_logits"``."""
        logits = self.risk_logits(pixels)
        outputs = getattr(self.base, "outputs", None)
        base = outputs(pixels) if outputs is not None else {"q": self.base(pixels)}
        return {**base, "risk": torch.sigmoid(logits), "risk_logits": logits}

    def decide(self, pixels: torch.Tensor) -> torch.Tensor:
        """Values whose argmax is the safe choice: where some action has ``Q_risk <= threshold``,
        the task Q-values of those (the others at -inf); else ``-Q_risk`` (the least-risk action)."""
        return safe_choice(self.base(pixels), torch.sigmoid(self.risk_logits(pixels)), self.threshold)

    @classmethod
    def for_task(cls, network: dict[str, Any], env: Any, gamma: float) -> dict[str, Any]:
        """The base's task-filled node (a categorical head's null support)."""
        return {**network, "base": network_for_task(network["base"], env, gamma)}

    @classmethod
    def td_term_for(cls, agent: Any, network: Any) -> RiskTerm:
        """The base head's own TD term with the critic's cross-entropy beside it."""
        keys = {**dataclasses.asdict(RiskConfig()), **network}  # a stored node may omit defaults
        return RiskTerm(base=head_td_term(agent, network["base"]), gamma=float(keys["gamma"]),
                        weight=float(keys["weight"]), bootstrap=str(keys["bootstrap"]),
                        task_action=str(keys["task_action"]))


def safe_choice(q: torch.Tensor, risk: torch.Tensor, threshold: float) -> torch.Tensor:
    """Decision values ``[..., A]``: ``q`` where ``risk <= threshold`` (others -inf) in rows with
    an allowed action; ``-risk`` in rows without one."""
    allowed = risk <= threshold
    some = allowed.any(-1, keepdim=True)
    masked = torch.where(allowed, q, torch.full_like(q, float("-inf")))
    return torch.where(some, masked, -risk.to(q.dtype))


def risk_target(batch: TensorDictBase, next_risk: torch.Tensor, gamma: float) -> torch.Tensor:
    """``y [B]`` = 1 after a crash (the transition terminated), else ``gamma^m next_risk``
    (``m``: the steps the transition sums; a time limit bootstraps)."""
    terminated = batch.get(("next", "terminated")).reshape(-1)
    steps = batch.get("steps_to_next_obs", None)
    m = torch.ones_like(next_risk) if steps is None else steps.reshape(-1).to(next_risk.dtype)
    return torch.where(terminated, torch.ones_like(next_risk), gamma ** m * next_risk)


@dataclass(frozen=True)
class RiskTerm:
    """The base head's TD term (on a view of the base network: it sees the base's own
    attributes and outputs) plus ``weight`` x the critic's binary cross-entropy to
    :func:`risk_target`, mean over the batch."""

    base: Any
    gamma: float = 0.97
    weight: float = 1.0
    bootstrap: str = "policy"
    task_action: str = "executed"
    name: str = "td"

    def __call__(self, batch: TensorDictBase, q: Any) -> torch.Tensor:
        net: RiskQNetwork = q.qnet
        view = q.view(net.base, task_batch(batch) if self.task_action == "proposed" else batch)
        task = self.base(view.batch, view)
        q.batch_q, q.td_error = view.batch_q, view.td_error  # for the margin term and the priorities
        a = batch.get("action").reshape(-1, 1).long()
        logits = net.risk_logits(batch.get("pixels")).gather(-1, a).squeeze(-1)
        with torch.no_grad():
            y = risk_target(batch, self.next_risk(batch, q), self.gamma)
        bce = nn.functional.binary_cross_entropy_with_logits(logits.float(), y.float())
        return task + self.weight * bce

    @torch.no_grad()
    def next_risk(self, batch: TensorDictBase, q: Any) -> torch.Tensor:
        """``Q_risk_target(s', a') [B]``, ``a'`` as ``bootstrap`` says."""
        net: RiskQNetwork = q.qnet
        nxt = batch.get(("next", "pixels"))
        with q.target_params():
            target = torch.sigmoid(net.risk_logits(nxt))
        if self.bootstrap == "safest":
            return target.min(-1).values
        a_next = net.decide(nxt).argmax(-1, keepdim=True)  # the online networks' safe choice
        return target.gather(-1, a_next).squeeze(-1)



def task_batch(batch: TensorDictBase) -> TensorDictBase:
    """``batch`` with ``action`` = its ``task_action`` (a shallow copy; ``batch`` is unchanged)."""
    if TASK_ACTION_KEY not in batch.keys():
        raise KeyError(f"network.task_action=proposed: the batch has no {TASK_ACTION_KEY!r} (transitions "
                       "stored by a run that did not store the task head's proposals)")
    return batch.clone(recurse=False).set("action", batch.get(TASK_ACTION_KEY))


def proposes(network: Any) -> bool:
    """The ``network`` node (or built network) is a risk critic's whose task head learns from its
    proposals: the run stores ``task_action`` with every transition, demos included."""
    if isinstance(network, nn.Module):
        return bool(getattr(network, "proposes", False))
    try:
        target, value = network.get("_target_"), network.get("task_action", "executed")
    except AttributeError:
        return False
    return target == f"{RiskQNetwork.__module__}.{RiskQNetwork.__qualname__}" and value == "proposed"


def with_task_action(data: TensorDictBase) -> TensorDictBase:
    """``data`` (prior knowledge, a teacher's steps) with ``task_action`` = ``action``: what was
    executed is what was proposed."""
    return data.clone(recurse=False).set(TASK_ACTION_KEY, data.get("action").clone())
