"""Stage 2's teacher: the run's own stage-1 network, frozen, and the three ways it holds stage 2
to its prior knowledge (``mode.teacher``, :class:`memrl.modes.TeacherConfig`):

- **distillation** (QDagger, Agarwal et al. 2022): the loss's :class:`memrl.losses.DistillTerm`
  reads the teacher and the factor :attr:`TeacherState.scale` set here, ``max(0, 1 - student /
  teacher)`` of their drives that survive and reach, never rising once lowered;
- **roll-ins** (JSRL, Uchendu et al. 2022): the teacher drives the first h steps of each training
  episode (:meth:`Teacher.roll_in`); h steps down by ``roll_in / roll_in_stages`` whenever the
  combined policy (teacher for h steps, then the student, both greedy) drives at least
  ``tolerance`` x its best score so far, which starts at the teacher's own; or h is drawn for
  each episode (``roll_in_random``);
- **warm start** (WSRL, Zhou et al. 2024): for the stage's first ``warm_start`` env steps the
  teacher acts (greedy, then the stage's epsilon at its start value; the schedule does not
  move) and no update is due (:meth:`Teacher.warming`; the trainer's update schedule starts
  after them), so the stage's buffer starts with exactly those transitions (rounded up to
  whole steps of all envs).

The drives are the stage-1 drive scenes (:func:`memrl.dqn.stage1.drive_check`): apart from the
training, periodic and test scenes. Everything that changes is in :class:`TeacherState`,
saved with the run's checkpoints, so a resumed run continues the same schedules.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn

from memrl.dqn.stage1 import drive_check
from memrl.evaluation.policies import RollInActor
from memrl.modules.qnet import decision_values
from memrl.modules.risk import TASK_ACTION_KEY

log = logging.getLogger(__name__)

TEACHER_JSON = "teacher.json"
"""The teacher's record in a run folder: its drives and each check of the student."""


@dataclass
class TeacherState:
    """What the teacher's schedules have reached (saved in checkpoints)."""

    scale: float = 0.0
    """The distillation's weight factor (1 at the start with ``distill_weight``, else 0)."""
    h: int = 0
    """The roll-in curriculum's current h (steps the teacher drives)."""
    best: int | None = None
    """The best drive score of the combined policy so far (None: the teacher's, not yet driven)."""
    teacher_both: int | None = None
    """The teacher's drives that survived and reached (None: not driven yet)."""
    next_check: int = 0
    """Env steps of the stage at which the next check is due."""
    checks: list[dict[str, Any]] = field(default_factory=list)
    """Each check: env steps, the student's (and combined policy's) score, scale and h after it."""


def needs_drives(cfg: Any) -> bool:
    """The student is checked by drives: distillation or the roll-in curriculum is on."""
    return float(cfg.distill_weight) > 0 or (int(cfg.roll_in) > 0 and not bool(cfg.roll_in_random))


class Teacher:
    """The frozen stage-1 network of an online stage and its schedules.

    Args:
        cfg: the mode's ``teacher`` node.
        net: the stage-1 network (``checkpoints/stage1.pt``), frozen here.
        env_cfg: the run's env config (the drives).
        num_envs: envs the stage acts in.
        seed: the run's seed (the random roll-in's draws).
        device: where the acting runs.
        run_dir: where ``teacher.json`` is written.
    """

    def __init__(self, cfg: Any, net: nn.Module, env_cfg: Any, num_envs: int, seed: int,
                 device: torch.device, run_dir: Path) -> None:
        self.cfg, self.env_cfg, self.device, self.run_dir = cfg, env_cfg, device, run_dir
        self.net = net.to(device).eval().requires_grad_(False)
        roll_in = int(cfg.roll_in)
        self.state = TeacherState(scale=1.0 if float(cfg.distill_weight) > 0 else 0.0, h=roll_in,
                                  next_check=int(cfg.check_every))
        self.h_env = torch.full((num_envs,), roll_in, dtype=torch.long, device=device)
        """Each env's h in its current episode."""
        self.generator = torch.Generator().manual_seed(int(seed) + 1)  # the random roll-in's own draws

    # ------------------------------------------------------------------ acting
    def warming(self, frames: int) -> bool:
        """The stage's env steps ``frames`` are still in the warm start."""
        return frames < int(self.cfg.warm_start)

    @torch.no_grad()
    def greedy(self, pixels: torch.Tensor) -> torch.Tensor:
        """The teacher's greedy actions ``[N]`` (its safe choice where it has a risk critic)."""
        return decision_values(self.net, pixels).argmax(-1)

    @torch.no_grad()
    def act_warm(self, td: TensorDictBase, explore: Any) -> None:
        """Warm start: the teacher's action, then the stage's epsilon-greedy at its current
        value (not stepped)."""
        td["action"] = self.greedy(td["pixels"]).reshape(td.shape)
        explore(td)

    @torch.no_grad()
    def roll_in(self, td: TensorDictBase, lengths: torch.Tensor) -> None:
        """Roll-ins: where an env's episode has taken fewer than its h steps (``lengths``), the
        teacher's greedy action replaces the agent's."""
        if int(self.cfg.roll_in) == 0:
            return
        lengths = lengths.to(self.device).reshape(-1)
        if bool(self.cfg.roll_in_random):
            new = lengths == 0  # an episode's first step: its h
            if bool(new.any()):
                draws = torch.randint(0, int(self.cfg.roll_in) + 1, (int(new.sum()),),
                                      generator=self.generator)
                self.h_env[new] = draws.to(self.device)
        else:
            self.h_env.fill_(self.state.h)
        guided = lengths < self.h_env
        if bool(guided.any()):
            action = td["action"]
            guide = self.greedy(td["pixels"]).reshape(action.shape)
            td["action"] = torch.where(guided.reshape(action.shape), guide, action)
            if TASK_ACTION_KEY in td.keys():  # the teacher's steps: what it executed it proposed
                td[TASK_ACTION_KEY] = torch.where(guided.reshape(action.shape), guide, td[TASK_ACTION_KEY])

    # ------------------------------------------------------------------ checks
    def after_steps(self, student: nn.Module, frames: int) -> bool:
        """At ``frames`` env steps of the stage: the due check of the student, which moves the
        distillation's scale and the curriculum's h; returns whether one was made."""
        s, cfg = self.state, self.cfg
        distilling = float(cfg.distill_weight) > 0 and s.scale > 0  # a scale of 0 stays 0
        curriculum = int(cfg.roll_in) > 0 and not bool(cfg.roll_in_random) and s.h > 0  # h = 0 stays 0
        if not (distilling or curriculum) or frames < s.next_check:
            return False
        while s.next_check <= frames:
            s.next_check += int(cfg.check_every)
        if s.teacher_both is None:
            s.teacher_both = self._drive(self.net)
            s.best = s.teacher_both
        row: dict[str, Any] = {"env_steps": frames}
        if distilling:
            row["student"] = self._drive(student)
            s.scale = min(s.scale, distill_scale(row["student"], s.teacher_both))
        if curriculum:
            combined = self._drive(student, s.h)
            row["combined"], row["h_driven"] = combined, s.h
            s.h, s.best = curriculum_step(s.h, combined, s.best, int(cfg.roll_in), int(cfg.roll_in_stages),
                                          float(cfg.tolerance))
        row.update(scale=s.scale, h=s.h)
        s.checks.append(row)
        log.info("teacher check at %d env steps: %s (teacher %d/%d)", frames, row, s.teacher_both,
                 int(cfg.drive_episodes))
        self.write()
        return True

    def _drive(self, student: nn.Module, h: int | None = None) -> int:
        """Drives of ``student`` (with ``h``: the combined policy) that survived and reached."""
        actor = None if h is None else RollInActor(self.net, student, h)
        cfg = self.cfg
        return int(drive_check(student, self.env_cfg, int(cfg.drive_episodes), int(cfg.drive_seed),
                               actor=actor)["both"])

    def write(self) -> None:
        """``teacher.json``: the state's record."""
        record = {"drive_episodes": int(self.cfg.drive_episodes), **dataclasses.asdict(self.state)}
        (self.run_dir / TEACHER_JSON).write_text(json.dumps(record, indent=2))

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        return {"state": dataclasses.asdict(self.state), "h_env": self.h_env.cpu(),
                "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.state = TeacherState(**state["state"])
        self.h_env.copy_(state["h_env"])
        self.generator.set_state(state["generator"])


def distill_scale(student: int, teacher: int) -> float:
    """QDagger's factor ``max(0, 1 - student / teacher)`` (0 where the teacher scores nothing)."""
    return 0.0 if teacher <= 0 else max(0.0, 1.0 - student / teacher)


def curriculum_step(h: int, score: int, best: int | None, roll_in: int, stages: int,
                    tolerance: float) -> tuple[int, int]:
    """JSRL's gate: at ``score >= tolerance x best`` h steps down by ``roll_in / stages``
    (rounded, to no less than 0); the best becomes the larger of the two. Returns (h, best)."""
    reference = score if best is None else best
    if h > 0 and score >= tolerance * reference:
        h = max(0, h - max(1, round(roll_in / stages)))
    return h, max(score, reference)
