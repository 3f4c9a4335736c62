"""A value head that outputs a categorical distribution over a fixed support of returns, and
the TD term that trains it: C51's projected double-DQN target (Bellemare et al., 2017), with
cross-entropy (``network=c51``). :mod:`memrl.modules.hlgauss` is the same head trained on
HL-Gauss targets.

Acting, evaluation, deployment and the opponent pool use the expected value
``Q(s, a) = sum_i p_i(s, a) z_i`` (the network's forward); the TD term reads the declared
``"logits"`` output through the learner's :class:`memrl.values.QFunctions`. TorchRL's
``DistributionalDQNLoss`` is not used: its actor's ``action_value`` must be the
log-distribution (acting would see no Q-values), it projects on the CPU, and it writes no TD
error for prioritized replay.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn

from memrl.errors import config_error
from memrl.fields import spec
from memrl.modules.network_config import NetworkConfig
from memrl.modules.qnet import QNetwork, hidden_layer


@dataclass
class CategoricalConfig(NetworkConfig):
    """A categorical value head (``network=c51``): Table I's trunk, ``atoms`` logits per action."""

    atoms: int = spec(51, ge=2)
    """Points of the support (C51: 51)."""
    v_min: float | None = None
    """Lowest return of the support [reward units]; null: the task's lowest discounted return
    (:func:`return_bounds`, from the reward weights, ``agent.gamma`` and ``env.duration``)."""
    v_max: float | None = None
    """Highest return of the support [reward units]; null: the task's highest (as ``v_min``)."""

    @staticmethod
    def check(node: Any, prefix: str = "network.") -> None:
        """Cross-key rule: a support from low to high."""
        lo, hi = node.get("v_min"), node.get("v_max")
        if lo is not None and hi is not None and not float(lo) < float(hi):
            raise config_error(f"{prefix}v_min", f"must be below {prefix}v_max ({hi}), got {lo}")


def return_bounds(env: Any, gamma: float) -> tuple[float, float]:
    """Bounds of an episode's discounted return ``sum_t gamma^t r_t`` from its first step.

    Each step's Table II components are 0 or 1, so a step's reward lies between the sum of the
    negative weights and the sum of the positive ones; ``collision`` ends the episode and so
    counts once; risk shaping adds ``w (risk(s) - gamma risk(s'))``, within ``[-gamma w, w]``.
    Over ``env.duration`` steps the per-step bounds add up to ``(1 - gamma^T) / (1 - gamma)``
    times themselves (``T`` for gamma 1). Table II with gamma 0.95, 300 steps: (-65, 40).
    """
    weights = {str(k): float(v) for k, v in dict(env["reward"]).items()}
    crash = weights.pop("collision", 0.0)
    shaping = float(env["shaping"]["weight"]) if "shaping" in env else 0.0
    lo = sum(min(w, 0.0) for w in weights.values()) - gamma * shaping
    hi = sum(max(w, 0.0) for w in weights.values()) + shaping
    steps = int(env["duration"])
    horizon = float(steps) if gamma == 1 else (1.0 - gamma ** steps) / (1.0 - gamma)
    return lo * horizon + min(crash, 0.0), hi * horizon + max(crash, 0.0)


class CategoricalQNetwork(QNetwork):
    """Table I's conv trunk and hidden layer, then ``n_actions x atoms`` logits: a distribution
    over ``support`` per action; the forward returns its expected values (Q-values)."""

    config_schema = CategoricalConfig

    def __init__(self, frames: int = 4, size: int = 84, n_actions: int = 9, channels: int = 16,
                 hidden: int = 256, pool_first: bool = True, layernorm: bool = False,
                 layernorm_convs: bool = False, atoms: int = 51, v_min: float | None = None,
                 v_max: float | None = None) -> None:
        if v_min is None or v_max is None or not float(v_min) < float(v_max) or atoms < 2:
            raise ValueError(f"{type(self).__name__}: need atoms >= 2 and v_min < v_max, got atoms={atoms}, "
                             f"v_min={v_min}, v_max={v_max} (null bounds are filled by for_task)")
        self.atoms, self.v_min, self.v_max = int(atoms), float(v_min), float(v_max)
        super().__init__(frames, size, n_actions, channels, hidden, pool_first, layernorm, layernorm_convs)
        self.arch.update(atoms=self.atoms, v_min=self.v_min, v_max=self.v_max)
        self.register_buffer("support", self.support_values(), persistent=False)  # rebuilt from arch

    def make_head(self, features: int, hidden: int, n_actions: int, layernorm: bool) -> nn.Module:
        return nn.Sequential(nn.Flatten(), *hidden_layer(features, hidden, layernorm),
                             nn.Linear(hidden, n_actions * self.atoms))

    def support_values(self) -> torch.Tensor:
        """The support ``z`` ``[atoms]``: C51's evenly spaced points from v_min to v_max."""
        return torch.linspace(self.v_min, self.v_max, self.atoms)

    def outputs(self, pixels: torch.Tensor) -> dict[str, torch.Tensor]:
        """``{"q": [..., A] expected values, "logits": [..., A, atoms]}``."""
        logits = self.trunk(pixels).reshape(*pixels.shape[:-3], -1, self.atoms)
        q = (torch.softmax(logits, -1) * self.support).sum(-1)
        return {"q": q, "logits": logits}

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        return self.outputs(pixels)["q"]

    def conversion_width(self) -> float:
        """Standard deviation [return units] of the Gaussian that :meth:`head_from_scalar` puts
        around each Q-value: 0.75 support spacings (HL-Gauss's default ratio)."""
        return 0.75 * (self.v_max - self.v_min) / (self.atoms - 1)

    @torch.no_grad()
    def head_from_scalar(self, weight: torch.Tensor, bias: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """This head's last layer ``([A * atoms, H], [A * atoms])`` from a scalar head's
        ``([A, H], [A])`` (Table I's, Q_a = w_a h + b_a), such that action a's distribution is
        the Gaussian of :meth:`conversion_width` s around Q_a on the support z, normalised:
        logit_(a, i) = (z_i Q_a - z_i^2 / 2) / s^2, linear in h (the -Q_a^2 / 2s^2 it omits is
        the same for every i and cancels in the softmax). Its expected value is Q_a while Q_a
        lies a few s inside the support: a stage 2 with this head starts from the scalar stage
        1's values (:func:`memrl.checkpoint.networks.offline_state`)."""
        z = self.support_values().to(torch.float64)  # [K]
        s2 = self.conversion_width() ** 2
        w = weight.to(torch.float64)[:, None, :] * z[None, :, None] / s2  # [A, K, H]
        b = (bias.to(torch.float64)[:, None] * z[None, :] - 0.5 * z[None, :] ** 2) / s2  # [A, K]
        return w.reshape(-1, weight.shape[1]).to(weight.dtype), b.reshape(-1).to(bias.dtype)

    @classmethod
    def for_task(cls, node: dict[str, Any], env: Any, gamma: float) -> dict[str, Any]:
        """``node`` with a null ``v_min`` / ``v_max`` set from :func:`return_bounds`."""
        lo, hi = return_bounds(env, gamma)
        out = dict(node)
        if out.get("v_min") is None:
            out["v_min"] = lo
        if out.get("v_max") is None:
            out["v_max"] = hi
        return out

    @classmethod
    def td_term(cls, agent: Any) -> C51Term:
        refuse_advantage_learning(cls, agent)
        return C51Term(gamma=float(agent.gamma))


def refuse_advantage_learning(cls: type, agent: Any) -> None:
    """A categorical head has no advantage-learning target: ``agent.advantage_learning`` must be 0."""
    if float(agent.advantage_learning) != 0:
        raise config_error("agent.advantage_learning", f"{cls.__name__} has no advantage-learning "
                           "target: needs 0")


def bootstrap(batch: TensorDictBase, gamma: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(reward [B], discount [B])`` of each item: the batch's (n-step) reward and
    ``gamma^m``, 0 where the transition terminated (a crash; a time limit bootstraps)."""
    reward = batch.get(("next", "reward")).reshape(-1).to(torch.float32)
    terminated = batch.get(("next", "terminated")).reshape(-1)
    steps = batch.get("steps_to_next_obs", None)
    m = torch.ones_like(reward) if steps is None else steps.reshape(-1).to(torch.float32)
    return reward, torch.where(terminated, torch.zeros_like(reward), gamma ** m)


def project(support: torch.Tensor, values: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
    """C51's projection: masses ``probs [B, K']`` at ``values [B, K']``, clipped into the
    support's range, split between the two nearest points of the evenly spaced ``support [K]``
    in proportion to nearness; ``[B, K]``, each row's mass kept."""
    lo, hi = float(support[0]), float(support[-1])
    width = (hi - lo) / (support.numel() - 1)
    v = values.clamp(lo, hi)
    near = (1.0 - (v[:, None, :] - support[None, :, None]).abs() / width).clamp_(min=0.0)  # [B, K, K']
    return (near * probs[:, None, :]).sum(-1)


def taken(batch: TensorDictBase, q: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """Of each item's own action: the online log-distribution ``[B, K]`` (with gradients) and
    the expected value ``[B]`` (detached), from the batch's online outputs (``q``: QFunctions)."""
    out = q.batch_outputs()
    a = batch.get("action").reshape(-1).long()
    rows = torch.arange(a.shape[0], device=a.device)
    return torch.log_softmax(out["logits"], -1)[rows, a], out["q"][rows, a].detach()


@dataclass(frozen=True)
class C51Term:
    """C51's TD term: the cross-entropy between the projected double-DQN target distribution
    (``r + gamma^m z`` under the target network's distribution at ``argmax_a Q_online(s', a)``,
    just ``r`` after a crash) and the online distribution of ``(s, a)``, mean over the batch.
    Its squared TD error on the expected values goes to prioritized replay."""

    gamma: float
    weight: float = 1.0
    name: str = "c51"

    def __call__(self, batch: TensorDictBase, q: Any) -> torch.Tensor:
        log_p, q_sa = taken(batch, q)
        with torch.no_grad():
            target = self.target(batch, q)
            q.td_error = ((target * q.qnet.support).sum(-1) - q_sa).pow(2)[:, None]
        return self.weight * -(target * log_p).sum(-1).mean()

    @torch.no_grad()
    def target(self, batch: TensorDictBase, q: Any) -> torch.Tensor:
        """The projected target distribution ``[B, K]``."""
        support = q.qnet.support
        next_pixels = batch.get(("next", "pixels"))
        a_star = q.greedy(next_pixels)
        logits = q.target(next_pixels)["logits"]
        p_next = torch.softmax(logits[torch.arange(a_star.shape[0], device=a_star.device), a_star], -1)
        reward, discount = bootstrap(batch, self.gamma)
        return project(support, reward[:, None] + discount[:, None] * support[None, :], p_next)
