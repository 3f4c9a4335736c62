"""The double-DQN learner: online and target networks (kept by TorchRL's ``DQNLoss``), Adam,
hard target updates; its loss is the sum of the stage's terms on a :class:`QFunctions` view."""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.modules import QValueActor
from torchrl.objectives import DQNLoss, HardUpdate

from memrl.data.priority_sampler import TD_KEY
from memrl.dqn.augment import shift_batch
from memrl.dqn.config import UPDATE_MODES, AgentConfig
from memrl.losses import LossTerm, td_term
from memrl.modules.qnet import QNetwork, acting_actor, make_q_actor
from memrl.values import QFunctions


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


def update_mode(mode: str, device: torch.device) -> str:
    """``agent.update_mode``, checked against the device (``captured``: CUDA graphs, CUDA only)."""
    if mode not in UPDATE_MODES:
        raise ValueError(f"agent.update_mode: unknown {mode!r} ({', '.join(UPDATE_MODES)})")
    if mode == "captured" and device.type != "cuda":
        raise ValueError(f"agent.update_mode=captured needs a CUDA device (device is {device.type}); "
                         "use agent.update_mode=compiled")
    return mode


class Learner:
    """Online/target Q-networks, optimizer and update step.

    The loss is the sum of the current stage's terms (:mod:`memrl.losses`; by default
    eq. (1) alone), on the sampled batch shifted by ``agent.augment_shift`` pixels when set.
    A stage change (:meth:`start_stage`) sets the terms and the optimizer; nothing else
    changes the learner.

    Args:
        cfg: the ``agent`` config.
        device: where the networks and the optimizer live.
        terms: the loss terms of the first stage (None: the network's own TD term, as ``cfg``
            sets it: eq. (1)'s for Table I).
        seed: seed of the learner's own generator (image shifts), so that shifts do not depend
            on what the acting thread draws meanwhile.
        network: the Q-network, as a ``network`` config node or stored architecture (built
            with ``agent.pool_first``), or a built module; None: Table I.
    """

    def __init__(self, cfg: AgentConfig | Any, device: torch.device | str = "cpu",
                 terms: tuple[LossTerm, ...] | None = None, seed: int = 0,
                 network: Mapping[str, Any] | torch.nn.Module | None = None) -> None:
        self.cfg, self.device = cfg, torch.device(device)
        self.augment_shift = int(cfg.augment_shift)
        self.shift_generator = torch.Generator(device=self.device).manual_seed(int(seed))
        self.actor: QValueActor = make_q_actor(pool_first=bool(cfg.pool_first), network=network)
        self.actor.to(self.device)
        self.qnet: QNetwork = self.actor.module[0].module  # the bare network inside the actor
        self.acting_actor: QValueActor = acting_actor(self.actor)
        """What the acting policy runs: :attr:`actor`, or a crash-risk critic's safe choice."""
        self.terms = tuple(terms) if terms is not None else (td_term(cfg, self.qnet),)
        precision = str(cfg.precision)
        # bf16 autocast is a CPU speed-up (oneDNN); on CUDA `auto` keeps float32
        self.qnet.conv_dtype = conv_dtype(precision) if self.device.type == "cpu" or \
            precision != "auto" else None
        if cfg.channels_last:
            # Before DQNLoss copies the parameters: online and target weights, and Adam's
            # moments, all stay channels_last (NHWC convs and pools run faster on CPU).
            self.qnet.to(memory_format=torch.channels_last)
        self.compiled = bool(cfg.compile) and compile_qnet(
            self.qnet, (1, int(cfg.batch_size)), self.device)
        self.update_mode = update_mode(str(getattr(cfg, "update_mode", "eager")), self.device)
        self.loss_module = DQNLoss(self.actor, loss_function="l2", delay_value=True,
                                   double_dqn=True, action_space="categorical")
        self.loss_module.make_value_estimator(gamma=cfg.gamma)
        # TorchRL's HardUpdate copies on the step after `interval` skipped ones: pass interval - 1
        # so that the copy happens every `target_update_interval` updates exactly.
        self.target_updater = HardUpdate(
            self.loss_module, value_network_update_interval=cfg.target_update_interval - 1)
        self.optimizer = self._adam()
        self._grad_step = self._compiled_grad_step()
        self.updates = 0
        self.teacher: torch.nn.Module | None = None
        """A frozen teacher network the stage distils (:mod:`memrl.dqn.teacher`; None: none)."""
        self.teacher_scale = 0.0
        """The distillation's current weight factor (the teacher's schedule sets it)."""

    def loss(self, batch: TensorDictBase) -> torch.Tensor:
        """The stage's loss on a batch (differentiable): the sum of its terms, in their order,
        on the batch shifted by ``augment_shift`` pixels (when > 0). The TD term's squared TD
        errors go into ``batch`` under ``TD_KEY`` (prioritized replay's priorities)."""
        given = batch
        if self.augment_shift > 0:
            batch = shift_batch(batch, self.augment_shift, self.shift_generator)
        q = self.q_functions(batch)
        total: torch.Tensor | None = None
        for term in self.terms:
            value = term(batch, q)
            if value is not None:
                total = value if total is None else total + value
        if total is None:
            raise ValueError(f"no loss term applies to this batch (terms: {[t.name for t in self.terms]})")
        if q.td_error is not None:
            given.set(TD_KEY, q.td_error)
        return total

    def q_functions(self, batch: TensorDictBase) -> QFunctions:
        """What the terms see of the online and target networks on ``batch``."""
        return QFunctions(self.loss_module, self.qnet, batch, keep_batch_q=len(self.terms) > 1,
                          teacher=self.teacher, teacher_scale=self.teacher_scale)

    def start_stage(self, terms: tuple[LossTerm, ...], lr: float | None = None,
                    fresh_optimizer: bool = False) -> None:
        """Begin a stage: its loss terms, a fresh Adam at ``agent.lr`` when ``fresh_optimizer``,
        then its own learning rate ``lr`` when given (None: keep the optimizer's)."""
        self.terms = tuple(terms)
        if fresh_optimizer:
            self.optimizer = self._adam()
        if lr is not None:
            for group in self.optimizer.param_groups:
                group["lr"] = lr
        self._grad_step = self._compiled_grad_step()  # a new optimizer and terms: a new trace

    def _adam(self) -> torch.optim.Adam:
        # captured: Adam keeps its step count on the device, as a CUDA graph needs
        return torch.optim.Adam(self.loss_module.parameters(), lr=self.cfg.lr,
                                capturable=self.update_mode == "captured")

    def _compiled_grad_step(self) -> Any:
        """The gradient step this ``update_mode`` runs: :meth:`_eager_grad_step`, or it compiled."""
        if self.update_mode == "eager":
            return self._eager_grad_step
        mode = "reduce-overhead" if self.update_mode == "captured" else None
        return torch.compile(self._eager_grad_step, dynamic=False, mode=mode)

    def update(self, batch: TensorDictBase) -> float:
        """One gradient step and a target-update tick; returns the loss value (a host read)."""
        return float(self.step(batch))

    def step(self, batch: TensorDictBase) -> torch.Tensor:
        """One gradient step and a target-update tick; returns the loss, detached, where it was
        computed (no host synchronisation: the trainer reads losses every ``loss_readback``)."""
        try:
            if self.update_mode == "captured":
                torch.compiler.cudagraph_mark_step_begin()  # one training step per replay
                loss = self._grad_step(batch).clone()  # a graph's output is overwritten at its next replay
            else:
                loss = self._grad_step(batch)
        except Exception as err:
            if not self.compiled and self.update_mode == "eager":
                raise
            # A (re)compilation failed inside the forward or backward, before the optimizer
            # step: drop the compiled code and redo this update eagerly.
            self.qnet._compiled_call_impl = None
            what = "agent.compile" if self.compiled else f"agent.update_mode={self.update_mode}"
            self.compiled, self.update_mode = False, "eager"
            self._grad_step = self._eager_grad_step
            self.optimizer.zero_grad(set_to_none=True)
            warnings.warn(f"{what}: compiled update failed ({type(err).__name__}: {err}); "
                          "running eager", RuntimeWarning, stacklevel=2)
            loss = self._grad_step(batch)
        self.target_updater.step()  # a Python counter: outside the compiled step
        self.updates += 1
        return loss

    def _eager_grad_step(self, batch: TensorDictBase) -> torch.Tensor:
        """The stage's loss, backward, gradient clipping and Adam: what ``compiled`` compiles."""
        loss = self.loss(batch)
        for group in self.optimizer.param_groups:
            for p in group["params"]:
                p.grad = None  # Optimizer.zero_grad(set_to_none=True), which dynamo does not trace
        loss.backward()
        if self.cfg.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.loss_module.parameters(), self.cfg.grad_clip)
        self.optimizer.step()
        return loss.detach()

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
        state = {"loss_module": self.loss_module.state_dict(),
                 "optimizer": self.optimizer.state_dict(), "updates": self.updates,
                 "target_updater": self.target_updater.state_dict()}
        if self.augment_shift > 0:
            state["shift_generator"] = self.shift_generator.get_state()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.loss_module.load_state_dict(state["loss_module"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.target_updater.load_state_dict(state["target_updater"])
        self.updates = int(state["updates"])
        if "shift_generator" in state:
            self.shift_generator.set_state(state["shift_generator"])
