"""Stage 2's teacher (``mode.teacher``, :mod:`memrl.dqn.teacher`; modes qdagger, jsrl, wsrl):
the distillation's KL and its weight's schedule against hand computations, a roll-in that hands
over at step h and a curriculum that moves h as specified, a warm start that fills exactly the
configured transitions before any update, and a run with all three that resumes exactly."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from memrl.dqn.teacher import Teacher, curriculum_step, distill_scale
from memrl.losses import DistillTerm, distill_kl
from memrl.modes import TeacherConfig
from memrl.values import QFunctions
from tests.helpers import TINY, assert_kill_and_resume_is_exact, tiny
from tests.test_network import fixed_input


class Constant(torch.nn.Module):
    """Q-values that prefer ``action`` by 1 whatever the pixels."""

    def __init__(self, action: int, n: int = 9) -> None:
        super().__init__()
        self.q = torch.nn.Parameter(torch.zeros(n).index_fill_(0, torch.tensor([action]), 1.0))

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        return self.q.expand(*pixels.shape[:-3], -1)


def test_the_distillation_kl_against_a_hand_computation():
    teacher, student = torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([[0.0, 0.0, 0.0]])
    # tau = 2: p = softmax([0.5, 0, 0]), q uniform; KL = sum p (log p - log 1/3)
    e = math.exp(0.5)
    p = [e / (e + 2), 1 / (e + 2), 1 / (e + 2)]
    want = sum(pi * (math.log(pi) - math.log(1 / 3)) for pi in p)
    assert float(distill_kl(teacher, student, 2.0)) == pytest.approx(want, rel=1e-6)
    assert float(distill_kl(student + 3.0, student, 1.0)) == pytest.approx(0.0, abs=1e-7)  # same softmax


def test_the_distillation_term_weighs_the_agents_own_states_by_the_current_scale():
    teacher, student = Constant(0), Constant(4)
    pixels = fixed_input()[:4]
    batch = TensorDict({"pixels": pixels, "is_demo": torch.tensor([[True], [False], [False], [True]])}, [4])
    q = QFunctions(None, student, batch, teacher=teacher, teacher_scale=0.25)
    value = DistillTerm(weight=2.0, temperature=0.5)(batch, q)
    want = 2.0 * 0.25 * float(distill_kl(teacher(pixels[1:3]), student(pixels[1:3]), 0.5))
    assert float(value) == pytest.approx(want, rel=1e-6) and want > 0
    value.backward()
    assert student.q.grad is not None and float(student.q.grad.abs().sum()) > 0
    # nothing at scale 0, without a teacher, or on demos alone
    unscaled = QFunctions(None, student, batch, teacher=teacher, teacher_scale=0.0)
    assert DistillTerm(2.0)(batch, unscaled) is None
    assert DistillTerm(2.0)(batch, QFunctions(None, student, batch)) is None
    demos = batch.clone().set("is_demo", torch.ones(4, 1, dtype=torch.bool))
    on_demos = QFunctions(None, student, demos, teacher=teacher, teacher_scale=1.0)
    assert DistillTerm(2.0)(demos, on_demos) is None


def test_the_distillation_weight_falls_with_the_students_drives_and_never_rises(tmp_path, monkeypatch):
    assert distill_scale(10, 40) == 0.75 and distill_scale(40, 40) == 0.0 and distill_scale(45, 40) == 0.0
    assert distill_scale(3, 0) == 0.0  # a teacher that drives nothing teaches nothing
    cfg = TeacherConfig(distill_weight=1.0, check_every=100, drive_episodes=40)
    teacher = Teacher(cfg, Constant(0), {}, num_envs=2, seed=0, device=torch.device("cpu"), run_dir=tmp_path)
    scores = iter([40, 10, 30, 20, 44])  # the teacher's drives, then the student's at each check
    monkeypatch.setattr(teacher, "_drive", lambda net, h=None: next(scores))
    assert teacher.state.scale == 1.0 and not teacher.after_steps(Constant(4), 99)
    scales = []
    for frames in (100, 250, 300, 420):
        assert teacher.after_steps(Constant(4), frames)
        scales.append(teacher.state.scale)
    assert scales == [0.75, 0.25, 0.25, 0.0]  # 1 - 10/40, 1 - 30/40, not back up at 20/40, 0 at 44
    assert [c["env_steps"] for c in teacher.state.checks] == [100, 250, 300, 420]
    assert teacher.state.next_check == 500 and not teacher.after_steps(Constant(4), 499)


def test_a_roll_in_hands_over_to_the_agent_at_step_h(tmp_path):
    cfg = TeacherConfig(roll_in=3, roll_in_stages=3)
    teacher = Teacher(cfg, Constant(2), {}, num_envs=5, seed=0, device=torch.device("cpu"), run_dir=tmp_path)
    td = TensorDict({"pixels": fixed_input()[:5], "action": torch.full((5,), 7)}, [5])
    teacher.roll_in(td, torch.tensor([0, 1, 2, 3, 9]))
    assert td["action"].tolist() == [2, 2, 2, 7, 7]  # the teacher's for steps 0-2, the agent's from step 3
    teacher.state.h = 0  # the curriculum's end: the agent everywhere
    td["action"] = torch.full((5,), 7)
    teacher.roll_in(td, torch.zeros(5, dtype=torch.long))
    assert td["action"].tolist() == [7] * 5


def test_the_random_roll_in_draws_h_for_each_episode_at_its_first_step(tmp_path):
    cfg = TeacherConfig(roll_in=4, roll_in_random=True)
    teacher = Teacher(cfg, Constant(2), {}, num_envs=3, seed=5, device=torch.device("cpu"), run_dir=tmp_path)
    want = torch.randint(0, 5, (3,), generator=torch.Generator().manual_seed(6))
    td = TensorDict({"pixels": fixed_input()[:3], "action": torch.full((3,), 7)}, [3])
    teacher.roll_in(td, torch.zeros(3, dtype=torch.long))
    assert torch.equal(teacher.h_env, want)
    before = teacher.h_env.clone()
    teacher.roll_in(td, torch.tensor([1, 0, 6]))  # only env 1 starts an episode
    assert teacher.h_env[0] == before[0] and teacher.h_env[2] == before[2]


def test_the_curriculum_moves_h_down_only_when_the_combined_policy_holds_its_best():
    # roll_in 150 in 5 stages: steps of 30; tolerance 0.9 of the best so far (the teacher's 36 at first)
    assert curriculum_step(150, 33, 36, 150, 5, 0.9) == (120, 36)  # 33 >= 32.4: down
    assert curriculum_step(120, 32, 36, 150, 5, 0.9) == (120, 36)  # 32 < 32.4: stays
    assert curriculum_step(120, 38, 36, 150, 5, 0.9) == (90, 38)  # better than the best: down, new best
    assert curriculum_step(0, 40, 38, 150, 5, 0.9) == (0, 40)  # never below 0
    assert curriculum_step(20, 30, 30, 150, 7, 1.0) == (0, 30)  # round(150 / 7) = 21 > 20: to 0


def test_the_curriculum_drives_the_combined_policy_at_the_current_h(tmp_path, monkeypatch):
    cfg = TeacherConfig(roll_in=90, roll_in_stages=3, check_every=10, tolerance=0.9)
    teacher = Teacher(cfg, Constant(0), {}, num_envs=2, seed=0, device=torch.device("cpu"), run_dir=tmp_path)
    driven = []
    scores = iter([30, 28, 20, 29, 30])

    def drive(net, h=None):
        driven.append(h)
        return next(scores)

    monkeypatch.setattr(teacher, "_drive", drive)
    for frames in (10, 20, 30, 40):
        teacher.after_steps(Constant(4), frames)
    assert driven == [None, 90, 60, 60, 30]  # the teacher alone once, then the combined policy at h
    assert [c["h"] for c in teacher.state.checks] == [60, 60, 30, 0]  # 28 >= 27; 20 < 27; 29; 30
    assert teacher.state.scale == 0.0  # no distillation asked for


def test_the_warm_start_fills_exactly_its_transitions_with_the_teachers_actions_before_any_update(
        compose_cfg, tmp_path, demos, monkeypatch):
    from memrl.checkpoint import load_stage1_qnet
    from memrl.dqn.learner import Learner
    from memrl.dqn.loop import Trainer
    from memrl.modules.qnet import decision_values

    # 4 envs x 30 steps: 120 env steps of the teacher, with epsilon 0 (its greedy actions)
    cfg = compose_cfg("train", tiny("wsrl") + ["env.num_envs=4", "total_frames=200", "total_episodes=null",
                                               "mode.teacher.warm_start=120", "agent.warmup_frames=20",
                                               "mode.stage2.eps_start=0", "mode.stage2.eps_end=0"])
    seen = []
    original = Learner.step

    def step(self, batch):
        if not seen:
            buffer = trainer.stage.buffer
            seen.append(getattr(buffer, "online_buffer", buffer))
            seen.append(len(seen[0]))
            seen.append(trainer.counters.frames)
        return original(self, batch)

    trainer = Trainer(cfg, tmp_path / "run", demos)
    trainer.run_offline()  # stage 1's own updates
    monkeypatch.setattr(Learner, "step", step)
    updates_before = trainer.counters.updates
    trainer.run()
    agent, stored = seen[0], seen[1]
    assert stored == 120 and seen[2] == 120 and trainer.counters.updates > updates_before
    teacher = load_stage1_qnet(tmp_path / "run" / "checkpoints")
    rows = agent.storage.get(torch.arange(120)) if hasattr(agent, "storage") else agent[:120]
    with torch.no_grad():
        want = decision_values(teacher, rows["pixels"]).argmax(-1)
    assert torch.equal(rows["action"].reshape(-1), want)


def test_a_run_with_all_three_levers_resumes_exactly(compose_cfg, tmp_path, demos, monkeypatch):
    from memrl.modes import MODES
    from tests.helpers import TINY_STAGE1

    extra = ["env.num_envs=4", "total_episodes=12", "checkpoint_every=3", *MODES["qdagger"].overrides,
             *TINY_STAGE1, "mode.teacher.roll_in=10", "mode.teacher.roll_in_stages=2",
             "mode.teacher.warm_start=40", "mode.teacher.check_every=60", "mode.teacher.drive_episodes=2"]
    cfg, full = assert_kill_and_resume_is_exact(compose_cfg, tmp_path, demos, monkeypatch, extra)
    import json

    record = json.loads((tmp_path / "full" / "teacher.json").read_text())
    assert full.stage == "Q2" and len(record["checks"]) >= 2 and record["teacher_both"] is not None
    assert json.loads((tmp_path / "cut" / "teacher.json").read_text()) == record


@pytest.mark.parametrize(("override", "message"), [
    ("mode.teacher.temperature=0", "config 'mode.teacher.temperature': must be > 0, got 0"),
    ("mode.teacher.tolerance=1.5", "config 'mode.teacher.tolerance': must be in (0, 1], got 1.5"),
    ("mode.teacher.roll_in=-1", "config 'mode.teacher.roll_in': must be >= 0, got -1"),
])
def test_bad_teacher_values_are_refused_naming_the_key(compose_cfg, override, message):
    from memrl.schemas import check_train

    with pytest.raises(ValueError) as err:
        check_train(compose_cfg("train", [*TINY, "+mode=qdagger", override]))
    assert str(err.value).startswith(message), str(err.value)
