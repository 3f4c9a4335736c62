"""The double-DQN learner: TorchRL ``DQNLoss`` with eq. (1)'s 1/2, Adam, hard target updates."""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.modules import QValueActor
from torchrl.objectives import DQNLoss, HardUpdate

from memrl.dqn.config import AgentConfig
from memrl.modules.qnet import QNetwork, make_q_actor


def _option(cfg: Any, key: str, default: Any) -> Any:
    """``cfg.key`` for a dataclass or a DictConfig that may predate the key."""
    return getattr(cfg, key, default) if not hasattr(cfg, "get") else cfg.get(key, default)


def conv_dtype(precision: str) -> torch.dtype | None:
    """The Q-network's conv trunk dtype for ``agent.precision`` (None: float32)."""
    if precision == "bfloat16":
        return torch.bfloat16
    if precision not in ("auto", "float32"):
        raise ValueError(f"agent.precision: unknown {precision!r} (auto, float32, bfloat16)")
    return torch.bfloat16 if precision == "auto" and native_bf16() else None


def native_bf16() -> bool:
    """Whether oneDNN runs bfloat16 natively on this CPU (AVX512-BF16, AMX...); False where
    torch lacks the check."""
    try:
        return bool(torch.backends.mkldnn.is_available()
                    and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def compile_qnet(qnet: QNetwork, batch_sizes: tuple[int, ...] = (1, 32),
                 device: torch.device | str = "cpu") -> bool:
    """``torch.compile`` the network's forward in place, then run it once per batch size, with
    and without gradients; on any failure (no C++ compiler, an unsupported op) warn and put the
    eager forward back. Returns whether the network stays compiled."""
    try:
        qnet.compile(dynamic=False)
        for n in batch_sizes:
            x = torch.zeros(n, 4, 84, 84, dtype=torch.uint8, device=device)
            qnet(x).sum().backward()
            with torch.no_grad():
                qnet(x)
        qnet.zero_grad(set_to_none=True)
        return True
    except Exception as err:  # inductor raises many kinds; all mean "run eager"
        qnet._compiled_call_impl = None  # nn.Module.compile's hook: back to the eager forward
        qnet.zero_grad(set_to_none=True)
        warnings.warn(f"agent.compile: torch.compile failed ({type(err).__name__}: {err}); "
                      "running eager", RuntimeWarning, stacklevel=2)
        return False


class Learner:
    """Online/target Q-networks, optimizer and update step.

    The loss is eq. (1): the mean of 1/2 (r + gamma Q_target(s', argmax_a Q(s', a)) - Q(s, a))^2,
    with no bootstrap on terminated transitions. TorchRL's ``l2`` distance has no 1/2; the
    update multiplies it by 0.5.
    """

    def __init__(self, cfg: AgentConfig | Any, device: torch.device | str = "cpu",
                 network: Mapping[str, Any] | torch.nn.Module | None = None) -> None:
        """``network``: the Q-network, as a ``network`` config node or stored architecture
        (built with ``agent.pool_first``), or a built module; None: Table I."""
        self.cfg, self.device = cfg, torch.device(device)
        self.actor: QValueActor = make_q_actor(pool_first=bool(_option(cfg, "pool_first", True)),
                                               network=network)
        self.actor.to(self.device)
        self.qnet: QNetwork = self.actor.module[0].module  # the bare network inside the actor
        precision = str(_option(cfg, "precision", "float32"))
        # bf16 autocast is a CPU speed-up (oneDNN); on CUDA `auto` keeps float32
        self.qnet.conv_dtype = conv_dtype(precision) if self.device.type == "cpu" or \
            precision != "auto" else None
        if _option(cfg, "channels_last", False):
            # Before DQNLoss copies the parameters: online and target weights, and Adam's
            # moments, all stay channels_last (NHWC convs and pools run faster on CPU).
            self.qnet.to(memory_format=torch.channels_last)
        self.compiled = bool(_option(cfg, "compile", False)) and compile_qnet(
            self.qnet, (1, int(cfg.batch_size)), self.device)
        self.loss_module = DQNLoss(self.actor, loss_function="l2", delay_value=True,
                                   double_dqn=True, action_space="categorical")
        self.loss_module.make_value_estimator(gamma=cfg.gamma)
        # TorchRL's HardUpdate copies on the step after `interval` skipped ones: pass interval - 1
        # so that the copy happens every `target_update_interval` updates exactly.
        self.target_updater = HardUpdate(
            self.loss_module, value_network_update_interval=cfg.target_update_interval - 1)
        self.optimizer = torch.optim.Adam(self.loss_module.parameters(), lr=cfg.lr)
        self.updates = 0

    margin_weight: float = 0.0
    """Weight of the large-margin loss on demo transitions (0: eq. (1) only); set per stage."""
    margin: float = 0.8
    """Margin [Q units] by which the demo action must beat every other action."""

    def loss(self, batch: TensorDictBase) -> torch.Tensor:
        """Eq. (1) on a batch (differentiable), plus, when ``margin_weight > 0``, DQfD's
        large-margin loss on its demo items: max_a [Q(s, a) + margin * (a != a_demo)] - Q(s, a_demo)
        (Hester et al., 2018), which makes the greedy action reproduce the demonstrations."""
        loss = 0.5 * self.loss_module(batch)["loss"]
        if self.margin_weight > 0 and "is_demo" in batch.keys():
            demo = batch["is_demo"].reshape(-1)
            if bool(demo.any()):
                q = self.qnet(batch["pixels"][demo])
                a = batch["action"][demo].reshape(-1, 1)
                margins = torch.full_like(q, self.margin).scatter_(-1, a, 0.0)
                excess = (q + margins).max(-1).values - q.gather(-1, a).squeeze(-1)
                loss = loss + self.margin_weight * excess.mean()
        return loss

    def update(self, batch: TensorDictBase) -> float:
        """One gradient step and a target-update tick; returns the loss value."""
        try:
            return self._update(batch)
        except Exception as err:
            if not self.compiled:
                raise
            # A (re)compilation failed inside the forward or backward, before the optimizer
            # step: drop the compiled forward and redo this update eagerly.
            self.qnet._compiled_call_impl = None
            self.compiled = False
            self.optimizer.zero_grad(set_to_none=True)
            warnings.warn(f"agent.compile: compiled update failed ({type(err).__name__}: {err}); "
                          "running eager", RuntimeWarning, stacklevel=2)
            return self._update(batch)

    def _update(self, batch: TensorDictBase) -> float:
        loss = self.loss(batch)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.cfg.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.loss_module.parameters(), self.cfg.grad_clip)
        self.optimizer.step()
        self.target_updater.step()
        self.updates += 1
        return float(loss.detach())

    def sync_target(self) -> None:
        """Copy the online network into the target network now."""
        with torch.no_grad():
            self.loss_module.target_value_network_params.data.copy_(
                self.loss_module.value_network_params.data)

    @torch.no_grad()
    def q_values(self, pixels: torch.Tensor) -> torch.Tensor:
        """Online Q-values ``[..., 9]`` of uint8 stacked pixels."""
        return self.qnet(pixels)

    def state_dict(self) -> dict[str, Any]:
        return {"loss_module": self.loss_module.state_dict(),
                "optimizer": self.optimizer.state_dict(), "updates": self.updates,
                "target_updater": self.target_updater.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.loss_module.load_state_dict(state["loss_module"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.target_updater.load_state_dict(state["target_updater"])
        self.updates = int(state["updates"])

    def set_lr(self, lr: float) -> None:
        """Learning rate of the current optimizer (mode B stage 1 may use its own)."""
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    def reset_optimizer(self) -> None:
        """Fresh Adam moments (mode B stage 2 starts a new optimisation)."""
        self.optimizer = torch.optim.Adam(self.loss_module.parameters(), lr=self.cfg.lr)
