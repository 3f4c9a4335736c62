"""Loss terms of the learner: each a small object with its weight from config, summed by the stage.

A stage lists its terms (:mod:`memrl.modes`), its value head's TD term among them (each
network declares the term that trains it, ``td_term``: eq. (1)'s :class:`TDTerm` for Table I,
:mod:`memrl.modules.categorical` for C51 and HL-Gauss); the learner adds them up
(:meth:`memrl.dqn.learner.Learner.loss`). A new term is one class with a ``__call__`` that
takes the batch and the learner's :class:`~memrl.values.QFunctions`, and one line in the
stage that uses it (``docs/extending.md``). The terms sit beside the modes that name them, below the
trainer that sums them (``tests/test_import_cycles.py``: the layer order).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import torch
from tensordict import TensorDictBase

from memrl.modules.qnet import TDTerm, head_td_term, target_action_gap
from memrl.values import QFunctions, network_outputs

__all__ = ["DistillTerm", "LossTerm", "MarginTerm", "QFunctions", "TDTerm", "distill_kl", "distill_terms",
           "margin_terms", "target_action_gap", "td_term"]


class LossTerm(Protocol):
    """One weighted part of a stage's loss."""

    name: str

    def __call__(self, batch: TensorDictBase, q: QFunctions) -> torch.Tensor | None:
        """The term's weighted value on ``batch`` (differentiable); None where it does not
        apply to this batch (adds nothing, not even a zero). ``q``: the learner's Q-functions
        on this batch (:class:`memrl.values.QFunctions`: online and target outputs, the
        batch's online Q as an earlier term left it, the TD errors for priorities)."""


def td_term(agent: Any, network: Any = None) -> LossTerm:
    """The TD term of the value head ``network`` (a ``network`` node, a class or a built
    network; None: Table I), as the ``agent`` config sets it: the head's own
    ``td_term(agent)`` (or ``td_term_for(agent, node)``); eq. (1)'s for a network that
    declares none (:func:`memrl.modules.qnet.head_td_term`)."""
    return head_td_term(agent, network)


@dataclass(frozen=True)
class MarginTerm:
    """DQfD's large-margin loss on the batch's demo items (Hester et al., 2018):
    max_a [Q(s, a) + margin * (a != a_demo)] - Q(s, a_demo), which makes the greedy action
    reproduce the demonstrations. Nothing for a batch without demo items."""

    weight: float
    margin: float = 0.8
    """[Q units] by which the demo action must beat every other action."""
    name: str = "margin"

    def __call__(self, batch: TensorDictBase, q: QFunctions) -> torch.Tensor | None:
        if "is_demo" not in batch.keys():
            return None
        demo = batch["is_demo"].reshape(-1)
        if not bool(demo.any()):
            return None
        # A batch of demos only (mode B's stage 1): the TD term's forward of the same pixels
        # serves, one forward and backward instead of two; else a forward of the demo rows.
        values = q.batch_q if q.batch_q is not None and bool(demo.all()) else \
            q.online(batch["pixels"][demo])["q"]
        a = batch["action"][demo].reshape(-1, 1)
        margins = torch.full_like(values, self.margin).scatter_(-1, a, 0.0)
        excess = (values + margins).max(-1).values - values.gather(-1, a).squeeze(-1)
        return self.weight * excess.mean()


@dataclass(frozen=True)
class DistillTerm:
    """QDagger's distillation (Agarwal et al., 2022): ``weight`` x the learner's current
    teacher scale (:attr:`QFunctions.teacher_scale`, set by :mod:`memrl.dqn.teacher`) x the
    batch mean over the agent's own states (demo rows left out) of
    KL(softmax(Q_teacher / tau) || softmax(Q / tau)); nothing without a teacher, at scale 0 or
    for a batch of demos only. KL, not CleanRL's cross-entropy: the same gradient, 0 when the
    student's softmax is the teacher's."""

    weight: float
    temperature: float = 1.0
    name: str = "distill"

    def __call__(self, batch: TensorDictBase, q: QFunctions) -> torch.Tensor | None:
        if q.teacher is None or q.teacher_scale <= 0:
            return None
        own = ~batch["is_demo"].reshape(-1) if "is_demo" in batch.keys() else None
        if own is not None and not bool(own.any()):
            return None
        student = q.batch_q if q.batch_q is not None else q.batch_outputs()["q"]  # the TD term's forward
        pixels = batch["pixels"]
        if own is not None:
            student, pixels = student[own], pixels[own]
        with torch.no_grad():
            teacher = network_outputs(q.teacher, pixels)["q"].float()
        kl = distill_kl(teacher, student.float(), self.temperature)
        return self.weight * q.teacher_scale * kl


def distill_kl(teacher_q: torch.Tensor, student_q: torch.Tensor, temperature: float) -> torch.Tensor:
    """Mean over rows of KL(softmax(teacher_q / tau) || softmax(student_q / tau))."""
    log_t = torch.log_softmax(teacher_q / temperature, -1)
    log_s = torch.log_softmax(student_q / temperature, -1)
    return (log_t.exp() * (log_t - log_s)).sum(-1).mean()


def distill_terms(weight: float, temperature: float) -> list[LossTerm]:
    """The distillation term when its weight is positive, else none."""
    return [DistillTerm(float(weight), float(temperature))] if weight > 0 else []


def margin_terms(weight: float, margin: float) -> list[LossTerm]:
    """The margin term when its weight is positive, else none (eq. (1) alone)."""
    return [MarginTerm(float(weight), float(margin))] if weight > 0 else []
