"""What a loss term sees of the learner's Q-functions on one batch: :class:`QFunctions`.

A term (:mod:`memrl.losses`, or a value head's own TD term beside its network, e.g.
:mod:`memrl.modules.categorical`) never reaches into TorchRL's ``DQNLoss``: it asks this facade
for the online or target outputs of any pixels (a dict of the network's declared outputs,
``"q"`` always), the double-DQN action, TorchRL's double-DQN loss, and it reads or sets two
named fields that pass quantities between terms:

- :attr:`QFunctions.batch_q`: the online Q-values ``[B, A]`` of the batch's own ``pixels``
  with their gradient graph, as the first term that computed them left them (a later term,
  e.g. the margin term on a demo-only batch, reuses them instead of a forward of its own);
- :attr:`QFunctions.td_error`: each item's squared TD error ``[B, 1]`` (detached) on the
  expected values, ``(target - Q(s, a))^2``, set by the TD term; the learner writes it into the
  batch under :data:`memrl.data.priority_sampler.TD_KEY`, from which prioritized replay takes
  ``|delta|`` (its square root).
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn

from memrl.data.priority_sampler import TD_KEY


def network_outputs(net: nn.Module, pixels: torch.Tensor) -> dict[str, torch.Tensor]:
    """``net``'s declared outputs of ``pixels`` (``net.outputs``; a network without it: its
    forward's Q-values, ``{"q": ...}``)."""
    outputs = getattr(net, "outputs", None)
    return outputs(pixels) if outputs is not None else {"q": net(pixels)}


class QFunctions:
    """The online and target Q-functions of a learner, on one batch.

    Args:
        loss_module: TorchRL's double ``DQNLoss`` that holds the online and target parameters.
        qnet: the bare online network (inside ``loss_module``'s actor).
        batch: the sampled batch (``pixels``, ``action``, ``("next", ...)``).
    """

    def __init__(self, loss_module: Any, qnet: nn.Module, batch: TensorDictBase,
                 keep_batch_q: bool = True, teacher: nn.Module | None = None,
                 teacher_scale: float = 0.0) -> None:
        self._loss, self.qnet, self.batch = loss_module, qnet, batch
        self.teacher, self.teacher_scale = teacher, float(teacher_scale)
        """The stage's frozen teacher network (None: none) and the current weight factor of
        its distillation (:class:`memrl.losses.DistillTerm`)."""
        self._keep = keep_batch_q  # False: no later term reads batch_q (no hook on DQNLoss's call)
        self.batch_q: torch.Tensor | None = None
        """Online Q-values of the batch's ``pixels`` with gradients (None until a term computed them)."""
        self.td_error: torch.Tensor | None = None
        """Each item's squared TD error ``[B, 1]``, detached (None until the TD term set it)."""
        self._batch_outputs: dict[str, torch.Tensor] | None = None

    def online(self, pixels: torch.Tensor) -> dict[str, torch.Tensor]:
        """The online network's outputs of ``pixels`` (with gradients where enabled)."""
        return network_outputs(self.qnet, pixels)

    def batch_outputs(self) -> dict[str, torch.Tensor]:
        """The online outputs of the batch's ``pixels``, computed once (sets :attr:`batch_q`)."""
        if self._batch_outputs is None:
            self._batch_outputs = self.online(self.batch["pixels"])
            self.batch_q = self._batch_outputs["q"]
        return self._batch_outputs

    def view(self, net: nn.Module, batch: TensorDictBase | None = None) -> QFunctions:
        """The same learner seen through ``net``, a part of :attr:`qnet` (a crash-risk critic's
        value head, :mod:`memrl.modules.risk`): its outputs, online and target, and its forward
        for the hooks; a fresh :attr:`batch_q` and :attr:`td_error`; on ``batch`` (default this
        one; same pixels, e.g. other actions)."""
        return QFunctions(self._loss, net, self.batch if batch is None else batch, keep_batch_q=self._keep,
                          teacher=self.teacher, teacher_scale=self.teacher_scale)

    def target_params(self) -> Any:
        """A context in which :attr:`qnet` (and its parts) holds the target network's weights."""
        actor = self._loss.value_network
        return self._loss.target_value_network_params.to_module(actor, preserve_module_state=False)

    @torch.no_grad()
    def target(self, pixels: torch.Tensor) -> dict[str, torch.Tensor]:
        """The target network's outputs of ``pixels`` (no gradients)."""
        with self.target_params():
            return network_outputs(self.qnet, pixels)

    @torch.no_grad()
    def greedy(self, pixels: torch.Tensor) -> torch.Tensor:
        """``argmax_a Q_online(s, a)`` ``[B]`` (int64): double DQN's bootstrap action."""
        return self.online(pixels)["q"].argmax(-1)

    def double_dqn_loss(self, batch: TensorDictBase | None = None) -> torch.Tensor:
        """TorchRL's double-DQN ``l2`` loss on ``batch`` (default: this one): the mean of
        (r + gamma^m Q_target(s', argmax_a Q(s', a)) [not terminated] - Q(s, a))^2, no 1/2.
        Sets :attr:`td_error` and, when the batch's pixels are this one's, :attr:`batch_q` (the
        online forward DQNLoss ran, kept by a hook on this call only: DQNLoss returns no
        Q(s, .), and a hook kept on the module would be copied with it, as overlap mode's
        acting copy is)."""
        batch = self.batch if batch is None else batch
        pixels, seen = self.batch["pixels"], {}

        def keep(module: nn.Module, inputs: tuple[Any, ...], output: torch.Tensor) -> None:
            if inputs and inputs[0] is pixels and torch.is_grad_enabled() and output.requires_grad:
                seen.setdefault("q", output)

        handle = self.qnet.register_forward_hook(keep) if self._keep and self.batch_q is None else None
        try:
            loss = self._loss(batch)["loss"]
        finally:
            if handle is not None:
                handle.remove()
        if "q" in seen:
            self.batch_q = seen["q"]
        if TD_KEY in batch.keys():  # DQNLoss writes each item's squared TD error there
            self.td_error = batch.get(TD_KEY).detach()
        return loss
